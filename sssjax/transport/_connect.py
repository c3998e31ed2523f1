"""Refracted connections: a light path from a point inside a smooth dielectric to a point
outside it, through one refraction, for next-event estimation inside translucent objects.

A scattering vertex `x` inside an object of relative index `eta` (inside / outside) cannot be
joined to a light point `y` by a straight shadow ray: light from `y` bends where it enters.
The connection is the boundary point `b` where Snell's law holds (`eta sin theta_1 =
sin theta_2`, both rays in one plane with the normal), Walter et al. 2009 ("Single scattering
in refractive media with triangle mesh boundaries"). Its measure is the *generalised
geometry term*: the solid angle at `x` per unit area at `y` along the refracted path,
`G = d omega_x / dA_y`, which replaces `cos_y / |x - y|^2` of a straight connection.

- **Planar faces** (cube and mesh faces, cylinder caps, the cone's base): the refraction point
  lies on the line between the projections of `x` and `y` on the plane, at the root of a
  monotone function (solved by safeguarded Newton), and `G` has a closed form
  (`planar_connection`).
- **Spheres**: every refracted path lies in the plane through `x`, `y` and the centre; the
  refraction points are the stationary points of the optical path `eta |b - x| + |b - y|`
  along the great circle, found on a grid and refined (`sphere_connections`; a sphere can
  focus, so there may be several). `G` comes from the Jacobian of the exit map
  (`exit_map_G`: forward-mode derivatives of "leave `x` in direction `omega`, refract, meet
  the light's plane"), which is also tested against the planar closed form.

Everything here is geometry (no scattering coefficients), in mm. The radiance convention is
basic radiance `L / n^2`: a refraction multiplies it by the Fresnel transmittance only.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._numerics import safe_div, safe_sqrt

__all__ = [
    "planar_connection",
    "in_face",
    "sphere_connections",
    "sphere_exit",
    "exit_map_G",
    "refract_dir",
]

FACE_PARALLELOGRAM, FACE_DISC, FACE_TRIANGLE = 0, 1, 2
_NEWTON_STEPS = 10


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def _unit(v):
    return v * safe_div(1.0, safe_sqrt(_dot(v, v)))[..., None]


def refract_dir(d: Array, n: Array, eta: Array) -> tuple[Array, Array]:
    """Refract unit direction `d` at a boundary whose unit normal `n` faces the incoming ray
    (`d . n < 0`); `eta = n_t / n_i`. **Returns:** `(t, ok)`, `ok` False under total
    internal reflection (then `t` is the mirror direction)."""
    cos_i = -_dot(d, n)
    inv = 1.0 / eta
    sin2_t = inv * inv * (1.0 - cos_i * cos_i)
    ok = sin2_t < 1.0
    cos_t = safe_sqrt(1.0 - sin2_t)
    t = inv[..., None] * d + (inv * cos_i - cos_t)[..., None] * n
    refl = d + 2.0 * cos_i[..., None] * n
    return jnp.where(ok[..., None], _unit(t), refl), ok


def planar_connection(
    x: Float[Array, "*b 3"],
    y: Float[Array, "*b 3"],
    c: Float[Array, "*b 3"],
    n: Float[Array, "*b 3"],
    eta: Float[Array, "*b"],
):
    """The refracted path `x -> b -> y` through the plane `(p - c) . n = 0`.

    **Arguments:** `x` inside (below the plane, `(x - c) . n < 0`), `y` outside (above it),
    `n` the unit outward normal, `eta` the relative index inside / outside.

    **Returns:** a dict with `b` (the refraction point), `d1 = |b - x|`, `d2 = |y - b|`,
    `w1` (unit direction x -> b), `w2` (b -> y), `cos1`, `cos2` (with the normal, inside and
    outside) and `G_perp = d omega_x / dA_perp(y)`, the solid angle at `x` per unit area
    perpendicular to the exit ray at `y` (multiply by the light's `cos` for its own area);
    `ok` is False where `x` or `y` is on the wrong side.
    """
    h1 = _dot(c - x, n)
    h2 = _dot(y - c, n)
    ok = (h1 > 0) & (h2 > 0)
    h1 = jnp.where(ok, h1, 1.0)
    h2 = jnp.where(ok, h2, 1.0)
    xp = x + h1[..., None] * n
    yp = y - h2[..., None] * n
    dv = yp - xp
    D = safe_sqrt(_dot(dv, dv))
    e = dv * safe_div(1.0, D)[..., None]

    # Snell: eta sin1 = sin2. Solve for tau = tan of the larger of the two angles (side P,
    # the optically thinner one), whose range [0, D / h_P] has no pole: h_P tau +
    # h_Q tan(theta_Q) = D with sin(theta_Q) = sin(theta_P) / m, m = max(eta, 1/eta) >= 1.
    # The left side increases with tau: Newton safeguarded by bisection of the bracket.
    thin_out = eta >= 1.0
    hP, hQ = jnp.where(thin_out, h2, h1), jnp.where(thin_out, h1, h2)
    m = jnp.where(thin_out, eta, 1.0 / eta)

    def parts(tau):
        root = safe_sqrt(1.0 + tau * tau)
        sP = tau / root
        sQ = sP / m
        cQ = safe_sqrt(1.0 - sQ * sQ)
        g = hP * tau + hQ * sQ / cQ - D
        dg = hP + hQ / (cQ**3 * m * root**3)
        return g, dg, sP, sQ

    lo, hi = jnp.zeros_like(D), D / hP
    tau = D / (hP + hQ / m)  # paraxial
    tau = jnp.clip(tau, lo, hi)
    for _ in range(_NEWTON_STEPS):
        g, dg, _, _ = parts(tau)
        lo = jnp.where(g <= 0, tau, lo)
        hi = jnp.where(g >= 0, tau, hi)
        new = tau - g / dg
        tau = jnp.where((new >= lo) & (new <= hi), new, 0.5 * (lo + hi))
    _, _, sP, sQ = parts(tau)
    sin1, sin2 = jnp.where(thin_out, sQ, sP), jnp.where(thin_out, sP, sQ)
    cos1, cos2 = safe_sqrt(1.0 - sin1 * sin1), safe_sqrt(1.0 - sin2 * sin2)
    r = jnp.clip(h1 * sin1 / cos1, 0.0, D)
    a1 = h1 / cos1
    a2 = h2 / cos2
    b = xp + r[..., None] * e
    w1 = _unit(b - x)
    w2 = _unit(y - b)
    # d omega_x / dA_h = sin1 / (rho rho'); sin1 / rho = 1 / (h1/cos1 + eta h2/cos2);
    # rho' = h1/cos1^2 + eta h2 cos1/cos2^3; dA_perp = cos2 dA_h
    G_perp = 1.0 / (
        cos2 * (h1 / cos1 + eta * h2 / cos2) * (h1 / cos1**2 + eta * h2 * cos1 / cos2**3)
    )
    return dict(b=b, d1=a1, d2=a2, w1=w1, w2=w2, cos1=cos1, cos2=cos2, G_perp=G_perp, ok=ok)


def in_face(p: Array, c: Array, e1: Array, e2: Array, kind: Array, slack: float = 1e-6) -> Array:
    """Whether points `p` on a face's plane lie inside it: a parallelogram `c + a e1 + b e2`
    with `|a|, |b| <= 1`, a disc (`e1`, `e2` orthogonal radii, `a^2 + b^2 <= 1`) or a
    triangle `c + a e1 + b e2` with `a, b >= 0`, `a + b <= 1`."""
    v = p - c
    uu, uv, vv = _dot(e1, e1), _dot(e1, e2), _dot(e2, e2)
    det = uu * vv - uv * uv
    pu, pv = _dot(v, e1), _dot(v, e2)
    a = safe_div(vv * pu - uv * pv, det)
    b = safe_div(uu * pv - uv * pu, det)
    s = 1.0 + slack
    para = (jnp.abs(a) <= s) & (jnp.abs(b) <= s)
    disc = a * a + b * b <= s * s
    tri = (a >= -slack) & (b >= -slack) & (a + b <= s)
    return jnp.where(kind == FACE_PARALLELOGRAM, para, jnp.where(kind == FACE_DISC, disc, tri))


def sphere_exit(x: Array, w: Array, centre: Array, radius: Array) -> tuple[Array, Array]:
    """Where the ray `x + t w` from inside a sphere leaves it: `(b, outward normal)`."""
    v = x - centre
    bh = _dot(v, w)
    cc = _dot(v, v) - radius * radius
    t = -bh + safe_sqrt(bh * bh - cc)
    b = x + t[..., None] * w
    return b, (b - centre) / radius[..., None]


def sphere_connections(
    x: Float[Array, "*b 3"],
    y: Float[Array, "*b 3"],
    centre: Float[Array, "*b 3"],
    radius: Float[Array, "*b"],
    eta: Float[Array, "*b"],
    n_grid: int = 32,
    max_roots: int = 3,
):
    """The refraction points of paths `x -> b -> y` through a sphere (`x` inside, `y`
    outside): stationary points of the optical path `eta |b - x| + |b - y|` on the great
    circle through `x` and `y` (every refracted path lies in that plane), restricted to the
    cap visible from `y`, located on `n_grid` intervals and refined by bisection + Newton.

    **Returns:** `(b (*b, max_roots, 3), ok (*b, max_roots))`. Two stationary points closer
    than one grid interval can be missed (near a caustic of the sphere).
    """
    v_y = y - centre
    dist_y = safe_sqrt(_dot(v_y, v_y))
    e1 = v_y * safe_div(1.0, dist_y)[..., None]
    v_x = x - centre
    perp = v_x - _dot(v_x, e1)[..., None] * e1
    # x on the axis through y: any plane containing the axis will do
    alt = jnp.where(
        (jnp.abs(e1[..., 0]) < 0.9)[..., None],
        jnp.array([1.0, 0.0, 0.0], dtype=x.dtype),
        jnp.array([0.0, 1.0, 0.0], dtype=x.dtype),
    )
    alt = alt - _dot(alt, e1)[..., None] * e1
    use_alt = _dot(perp, perp) < (1e-6 * radius) ** 2
    e2 = _unit(jnp.where(use_alt[..., None], alt, perp))
    cos_a = jnp.clip(radius / jnp.maximum(dist_y, radius), -1.0, 1.0)
    alpha = jnp.arccos(cos_a) * (1.0 - 1e-5)
    R = radius[..., None]

    def point(phi):
        return centre[..., None, :] + R[..., None] * (
            jnp.cos(phi)[..., None] * e1[..., None, :] + jnp.sin(phi)[..., None] * e2[..., None, :]
        )

    def dg(phi):
        b = point(phi)
        db = R[..., None] * (
            -jnp.sin(phi)[..., None] * e1[..., None, :] + jnp.cos(phi)[..., None] * e2[..., None, :]
        )
        u1 = _unit(b - x[..., None, :])
        u2 = _unit(b - y[..., None, :])
        return eta[..., None] * _dot(u1, db) + _dot(u2, db)

    s = jnp.linspace(-1.0, 1.0, n_grid + 1, dtype=x.dtype)
    phis = alpha[..., None] * s  # (*b, n + 1)
    g = dg(phis)
    change = (g[..., :-1] * g[..., 1:] <= 0) & (g[..., :-1] != g[..., 1:])
    # the first `max_roots` intervals with a sign change
    idx = jnp.argsort(~change, axis=-1, stable=True)[..., :max_roots]
    ok = jnp.take_along_axis(change, idx, axis=-1)
    lo = jnp.take_along_axis(phis[..., :-1], idx, axis=-1)
    hi = jnp.take_along_axis(phis[..., 1:], idx, axis=-1)
    g_lo = jnp.take_along_axis(g[..., :-1], idx, axis=-1)
    for _ in range(16):  # bisection: the bracket halves 16 times (grid / 65536)
        mid = 0.5 * (lo + hi)
        gm = dg(mid)
        left = (gm * g_lo) <= 0
        hi = jnp.where(left, mid, hi)
        lo = jnp.where(left, lo, mid)
        g_lo = jnp.where(left, g_lo, gm)
    phi = 0.5 * (lo + hi)
    return point(phi), ok


def exit_map_G(
    x: Float[Array, "*b 3"],
    w: Float[Array, "*b 3"],
    exit_fn,
    eta: Float[Array, "*b"],
    plane_point: Float[Array, "*b 3"],
    plane_normal: Float[Array, "*b 3"],
) -> Float[Array, "*b"]:
    """Generalised geometry term `d omega_x / dA` of the refracted exit map, by forward-mode
    derivatives: leave `x` in direction `w` (unit), meet the boundary at `exit_fn(x, w) ->
    (b, outward normal)`, refract out (`eta` inside / outside), and meet the plane through
    `plane_point` with normal `plane_normal`; `dA` is area on that plane (the light's plane
    for an area light, the plane perpendicular to the exit ray for a point light).

    **Returns:** `1 / |dF/du x dF/dv|` for `w(u, v) = normalize(w + u t1 + v t2)`, where
    `t1`, `t2` are orthonormal to `w` (so `d omega = du dv` at `u = v = 0`).
    """
    # an orthonormal basis around w (Duff et al. 2017)
    sign = jnp.where(w[..., 2] >= 0, 1.0, -1.0).astype(w.dtype)
    a = -1.0 / (sign + w[..., 2])
    bb = w[..., 0] * w[..., 1] * a
    t1 = jnp.stack([1.0 + sign * w[..., 0] ** 2 * a, sign * bb, -sign * w[..., 0]], axis=-1)
    t2 = jnp.stack([bb, sign + w[..., 1] ** 2 * a, -w[..., 1]], axis=-1)

    def F(uv):
        ww = _unit(w + uv[..., 0:1] * t1 + uv[..., 1:2] * t2)
        b, nb = exit_fn(x, ww)
        w2, _ = refract_dir(ww, -nb, 1.0 / eta)
        tp = safe_div(_dot(plane_point - b, plane_normal), _dot(w2, plane_normal))
        return b + tp[..., None] * w2

    zero = jnp.zeros(w.shape[:-1] + (2,), w.dtype)
    e_u = zero.at[..., 0].set(1.0)
    e_v = zero.at[..., 1].set(1.0)
    _, Ju = jax.jvp(F, (zero,), (e_u,))
    _, Jv = jax.jvp(F, (zero,), (e_v,))
    area = safe_sqrt(_dot(jnp.cross(Ju, Jv), jnp.cross(Ju, Jv)))
    return safe_div(1.0, area)
