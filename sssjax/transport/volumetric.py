"""The volumetric transport: exact light transport by random walks inside the actual
geometry of every translucent object, re-weighted (not re-traced) for other coefficients.

**The walk.** Outside objects a walker is a path tracer with unlimited depth: diffuse
surfaces (next-event estimation to every kind of light, then a cosine-weighted bounce),
mirrors, and smooth dielectric boundaries of translucent objects (the exact unpolarised
Fresnel reflectance chooses reflection or refraction, total internal reflection included).
Inside a homogeneous medium it takes exact exponential free flights, scatters with the
Henyey-Greenstein phase function and meets the boundary again. Light that leaves an object
continues as a normal ray: it can hit the floor, a mirror, a light or the object again, so
translucent shadows, light through thin parts and interreflections are in the image.
Russian roulette on the coefficient-independent weight ends paths without bias.

**Colour.** Each RGB channel has its own proposal coefficients `sigma_s0`, `sigma_t0` (the
scene's media unless given). With `spectral="mis"` (default) one walker per camera sample
serves all three channels: it draws its free flights with the proposal of a *hero* channel
chosen at random, and each channel weighs the path by `f_c / mean_k P_k`, the balance
heuristic over the three channels' path densities (one-sample MIS; every weight is at most
3 times that channel's own estimator, so long walks stay well-behaved where a fixed hero
channel is heavy-tailed). For grey-ish media one walk then does the work of three. With
`spectral="separate"` each channel has its own walkers (three per sample).

**Next-event estimation inside media.** At every scattering vertex one light is chosen by
power and connected through the boundary by the refracted path (`_connect`: planar faces in
closed form, spheres by their stationary optical paths), with the generalised geometry term,
Fresnel transmittance, phase function and attenuation. Paths that scatter, reach a covered
boundary point and leave straight into an area light are not counted again when they hit it
(the estimator already did); where the estimator cannot reach (curved sides of cylinders and
cones, large meshes) those hits count, so the image stays unbiased, only noisier. Point lights
are reached through planar faces and spheres only. Beam lights are reached by a second
scattering on the refracted beam (equiangular sampling), and their single scattering by the
medium segments that cross the beam.

**Trace once, shade many, exactly.** A path's weight depends on the coefficients only through
its number of scattering events `n` and its length `L` in each medium:
`w(sigma) = w0 (sigma_s / sigma_s0)^n exp(-(sigma_t - sigma_t0) L)` (perturbation Monte
Carlo, Hayakawa et al. 2001). Each walker keeps `K` records `(n, L)` drawn from its
contributions in proportion to their weight at the proposal (weighted reservoir sampling with
replacement, `K` independent slots), each with its channels' shares, and the total weight
`W`: `W / K sum_k a_kc f_k(sigma)` is an unbiased estimate of the walker's radiance in
channel `c` for any coefficients, exact at the proposal. Contributions of paths that never
entered a medium go to `base`. `g` is not re-weighted (it is the proposal's).

Lengths in mm, coefficients in mm^-1, radiance in W mm^-2 sr^-1 (basic radiance `L / n^2`
inside media, so refraction multiplies by the Fresnel transmittance only).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, Float, Int, PRNGKeyArray

from .._numerics import safe_div, safe_sqrt
from ..camera import camera_rays
from ..dipole import fresnel_reflectance, hg_phase
from ..sampling import stratified_2d
from ..shapes import intersect_all
from ._base import Block, Prepared, Terms, TransportMethod
from ._connect import (
    exit_map_G,
    in_face,
    planar_connection,
    refract_dir,
    sphere_connections,
    sphere_exit,
)
from ._packing import step_alive
from ._record import NO_RECORD, Recorder
from ._volscene import DIFFUSE, MIRROR, TRANSLUCENT, VolScene

__all__ = [
    "Volumetric",
    "VolumetricTerms",
    "VolumetricShading",
    "Proposal",
    "trace_block",
    "shade_terms",
    "effective_sample_size",
    "WalkStats",
]

EPS = 1e-3  # mm: ray offsets off surfaces
INSET = 1e-4  # mm: walkers entering or reflected inside a medium start this far in
RR_WEIGHT = 0.05  # Russian roulette below this path weight (camera paths start at 1)
RR_MIN_EVENTS = 4
MAX_EVENTS = 1 << 17  # safety cap; walks cut here are counted in `WalkStats.truncated`
_NU = 16  # uniform numbers per walker and event
_LEDGER = ("escaped", "emitter", "absorbed", "roulette", "cut")
_CHUNK_CPU = 128  # alive walkers are stepped in chunks of this many on CPU ...
_CHUNKS = 64  # ... and of 1/_CHUNKS of the block on accelerators (see `_chunk`)
_PHASE = 8  # events between re-packings
_BLOCK_WALKERS = 1 << 15  # walkers traced together by the renderer
# what ended each free flight (`_step(record=True)`, the ray tree)
EVENT = (
    "scatter",
    "reflect_inside",
    "exit",
    "light",
    "miss",
    "diffuse",
    "mirror",
    "reflect_outside",
    "enter",
    "through",
    "cut",
)


class Proposal(eqx.Module):
    """The coefficients the walks are sampled with, per translucent material and channel
    (`(Mt, 3)`, mm^-1), and the phase function's `g` (fixed: it is not re-weighted)."""

    sigma_s: Float[Array, "Mt 3"]
    sigma_t: Float[Array, "Mt 3"]
    g: Float[Array, "Mt 3"]

    @classmethod
    def from_media(cls, media) -> Proposal:
        if not media:
            z = jnp.zeros((0, 3))
            return cls(z, z, z)
        ss = jnp.stack([jnp.broadcast_to(m.sigma_s, (3,)) for m in media])
        st = jnp.stack([jnp.broadcast_to(m.sigma_t, (3,)) for m in media])
        g = jnp.stack([jnp.broadcast_to(m.g, (3,)) for m in media])
        return cls(ss, st, g)


class VolumetricTerms(Terms):
    """Re-weightable records of a block of pixels (`P` pixels, `R` records each, `Mt`
    materials): radiance `sum_r w_rc f_r(sigma_c)` in channel `c`. Their `prepare` has
    nothing to fold in (`eta` is geometry: the walks were traced with it)."""

    w: Float[Array, "3 P R"]  # the record's share of the pixel, per channel, at the proposal
    n: Float[Array, "P R Mt"]  # scattering events in each medium
    L: Float[Array, "P R Mt"]  # path length in each medium, mm
    sigma_s0: Float[Array, "Mt 3"]
    sigma_t0: Float[Array, "Mt 3"]
    per_walker: int = eqx.field(static=True, default=1)  # records of one walker, adjacent

    def rows(self, rows) -> VolumetricTerms:
        return VolumetricTerms(
            self.w[:, rows],
            self.n[rows],
            self.L[rows],
            self.sigma_s0,
            self.sigma_t0,
            self.per_walker,
        )

    @classmethod
    def concat(cls, parts) -> VolumetricTerms:
        host = all(isinstance(p.w, np.ndarray) for p in parts)
        cat = np.concatenate if host else jnp.concatenate
        p0 = parts[0]
        return VolumetricTerms(
            cat([p.w for p in parts], axis=1),
            cat([p.n for p in parts], axis=0),
            cat([p.L for p in parts], axis=0),
            p0.sigma_s0,
            p0.sigma_t0,
            p0.per_walker,
        )

    def sample_efficiency(self, media) -> Array:
        ess, ess0 = effective_sample_size(self, media)
        return safe_div(ess, ess0)

    def prepare(self, etas) -> VolumetricShading:
        return VolumetricShading(
            self.w, self.n, self.L, self.sigma_s0, self.sigma_t0, self.per_walker
        )

    @classmethod
    def mean(cls, parts) -> VolumetricTerms:
        """Independent traces of the same pixels (same proposal) as one trace with all their
        records, each at `1 / len(parts)` of its weight."""
        k = len(parts)
        if k == 1:
            return parts[0]
        host = all(isinstance(p.w, np.ndarray) for p in parts)
        cat = np.concatenate if host else jnp.concatenate
        return VolumetricTerms(
            cat([p.w for p in parts], axis=2) / k,
            cat([p.n for p in parts], axis=1),
            cat([p.L for p in parts], axis=1),
            parts[0].sigma_s0,
            parts[0].sigma_t0,
            parts[0].per_walker,
        )


class VolumetricShading(Prepared):
    """Volumetric records ready to shade (`VolumetricTerms.prepare`)."""

    w: Float[Array, "3 P R"]
    n: Float[Array, "P R Mt"]
    L: Float[Array, "P R Mt"]
    sigma_s0: Float[Array, "Mt 3"]
    sigma_t0: Float[Array, "Mt 3"]
    per_walker: int = eqx.field(static=True, default=1)  # records of one walker, adjacent

    def halves(self) -> tuple[VolumetricShading, VolumetricShading] | None:
        """The records of even and odd walkers, each at twice its weight (walks are
        independent; a walker's records share its path, so they stay together)."""
        K = self.per_walker
        R = self.w.shape[-1]
        if R % (2 * K):
            return None
        P = self.n.shape[0]

        def pick(j):
            w = self.w.reshape(3, P, R // (2 * K), 2, K)[:, :, :, j].reshape(3, P, R // 2)
            n = self.n.reshape(P, R // (2 * K), 2, K, -1)[:, :, j].reshape(P, R // 2, -1)
            L = self.L.reshape(P, R // (2 * K), 2, K, -1)[:, :, j].reshape(P, R // 2, -1)
            return VolumetricShading(2.0 * w, n, L, self.sigma_s0, self.sigma_t0, K)

        return pick(0), pick(1)

    def shade(self, media, *, multiple: bool = True, single: bool = True, **_) -> Array:
        """The exact re-weighting to `media`; `single` / `multiple`: the light scattered
        once / more than once in the media (by the records' event counts)."""
        return shade_terms(self, media, multiple=multiple, single=single)


class WalkStats(eqx.Module):
    """Diagnostics of a block's walks: events (free flights and surface hits) in total, the
    longest walk, walks cut at `MAX_EVENTS` and walkers lost (numerical leaks), and where the
    walkers' weight went (each walker's analog weight in its hero channel), summed over
    walkers: `escaped` (to the background / environment), `emitter` (into a light),
    `absorbed` (in media and on surfaces), `roulette` (net weight removed by Russian
    roulette, expectation 0) and `cut` (walks stopped at `MAX_EVENTS` or lost). They add up
    to the number of walkers."""

    events: Array
    longest: Array
    truncated: Array
    lost: Array
    escaped: Array
    emitter: Array
    absorbed: Array
    roulette: Array
    cut: Array


def _coefficient_shifts(terms: VolumetricTerms, media):
    """`(log(sigma_s / sigma_s0), sigma_t - sigma_t0)`, each `(Mt, 3)`; the log is finite at
    `sigma_s = 0` (-1e4: then `f = 0` for `n > 0`) with finite gradients."""
    ss = jnp.stack([jnp.broadcast_to(m.sigma_s, (3,)) for m in media])  # (Mt, 3)
    st = jnp.stack([jnp.broadcast_to(m.sigma_t, (3,)) for m in media])
    ratio = ss / terms.sigma_s0
    pos = ratio > 0
    log_r = jnp.where(pos, jnp.log(jnp.where(pos, ratio, 1.0)), -1e4)
    return log_r, st - terms.sigma_t0


def _log_f(n, L, log_r, d_t):
    """`log f = sum_m n log_r - d_t L`, `(3, P, R)` from `n`, `L` `(P, R, Mt)`."""
    lr = jnp.moveaxis(log_r, 1, 0)[:, None, None, :]  # (3, 1, 1, Mt)
    dt = jnp.moveaxis(d_t, 1, 0)[:, None, None, :]
    nl = jnp.where(n[None] > 0, n[None] * lr, 0.0)
    return jnp.sum(nl - dt * L[None], axis=-1)


def _log_factors(terms: VolumetricTerms, media) -> Float[Array, "3 P R"]:
    """`log f = sum_m n log(sigma_s / sigma_s0) - (sigma_t - sigma_t0) L` per channel."""
    return _log_f(terms.n, terms.L, *_coefficient_shifts(terms, media))


@jax.custom_jvp
def _reweighted_sum(w, n, L, log_r, d_t):
    """`sum_R w f`, `(3, P)`: the re-weighted records."""
    return jnp.sum(w * jnp.exp(_log_f(n, L, log_r, d_t)), axis=-1)


def _jvp_reweighted_sum(primals, tangents):
    """The closed-form tangent: `d log f = sum_m n_m d log_r - L_m d d_t`, so a tangent of
    the coefficients needs only `S_n = sum_R w f n_m` and `S_L = sum_R w f L_m`, computed once
    from the primals; a forward Jacobian (one tangent per coefficient) then costs about
    three shades instead of one per coefficient and channel. Tangents of the records
    themselves (never needed by a fit) take the general path."""
    w, n, L, log_r, d_t = primals
    dw, dn, dL, dlr, ddt = tangents
    f = jnp.exp(_log_f(n, L, log_r, d_t))
    wf = w * f
    out = jnp.sum(wf, axis=-1)
    n_pos = jnp.where(n > 0, n, 0.0)
    # broadcast-and-reduce, not einsum: XLA fuses it with the exp (einsum's batched dot
    # made a second pass over the records; 1.7x slower on 256 x 256 x 64 records)
    S_n = jnp.sum(wf[..., None] * n_pos[None], axis=2)
    S_L = jnp.sum(wf[..., None] * L[None], axis=2)
    t = jnp.einsum("cpm,mc->cp", S_n, _dense(dlr, log_r)) - jnp.einsum(
        "cpm,mc->cp", S_L, _dense(ddt, d_t)
    )
    if not isinstance(dw, SymbolicZero):
        t = t + jnp.sum(dw * f, axis=-1)
    if not (isinstance(dn, SymbolicZero) and isinstance(dL, SymbolicZero)):
        lr = jnp.moveaxis(log_r, 1, 0)[:, None, None, :]
        dt = jnp.moveaxis(d_t, 1, 0)[:, None, None, :]
        dn_, dL_ = _dense(dn, n), _dense(dL, L)
        dlog = jnp.sum(jnp.where(n[None] > 0, dn_[None] * lr, 0.0) - dt * dL_[None], axis=-1)
        t = t + jnp.sum(wf * dlog, axis=-1)
    return out, t


def _dense(t, like):
    return jnp.zeros_like(like) if isinstance(t, SymbolicZero) else t


_reweighted_sum.defjvp(_jvp_reweighted_sum, symbolic_zeros=True)


def shade_terms(terms, media, *, multiple: bool = True, single: bool = True) -> Array:
    """Radiance `(P, 3)` of the records for `media` (a sequence, one `Medium` per material,
    coefficients in mm^-1): the exact re-weighting of the walks to these coefficients.
    `single` / `multiple` keep the light scattered once / more than once (paths with no
    scattering event, light only attenuated, count with neither switched off)."""
    if terms.n.shape[-1] == 0:
        return jnp.zeros(terms.w.shape[1:2] + (3,), terms.w.dtype)
    w = terms.w
    if not (single and multiple):
        order = jnp.sum(terms.n, axis=-1)[None]
        keep = (order == 0) | ((order == 1) & single) | ((order >= 2) & multiple)
        w = jnp.where(keep, w, 0.0)
    return _reweighted_sum(w, terms.n, terms.L, *_coefficient_shifts(terms, media)).T


def effective_sample_size(terms: VolumetricTerms, media) -> tuple[Array, Array]:
    """Per pixel and channel `(P, 3)`: the effective sample size `(sum w f)^2 / sum (w f)^2`
    of the records at `media`, and its value at the proposal (`f = 1`). Their ratio falls
    from 1 as the coefficients move away from the proposal."""
    wf = terms.w * jnp.exp(_log_factors(terms, media))
    ess = safe_div(jnp.sum(wf, -1) ** 2, jnp.sum(wf * wf, -1))
    ess0 = safe_div(jnp.sum(terms.w, -1) ** 2, jnp.sum(terms.w**2, -1))
    return ess.T, ess0.T


# --- sampling helpers ----------------------------------------------------------------------
def _pcg(v):
    """PCG hash of uint32s (Jarzynski and Olano 2020): cheap, well-mixed 32 bits."""
    state = v * jnp.uint32(747796405) + jnp.uint32(2891336453)
    shift = (state >> jnp.uint32(28)) + jnp.uint32(4)
    word = ((state >> shift) ^ state) * jnp.uint32(277803737)
    return (word >> jnp.uint32(22)) ^ word


def _uniforms(seed, i, n: int):
    """`n` uniform numbers in [0, 1) per walker for event `i`, from the walker's own `seed`
    (a counter-based hash: the numbers follow the walker, whatever lane it is packed into)."""
    c = jnp.asarray(i, jnp.uint32) * jnp.uint32(n) + jnp.arange(n, dtype=jnp.uint32)
    h = _pcg(_pcg(c)[None, :] + seed[:, None])
    return (h >> jnp.uint32(8)).astype(jnp.float32) * (1.0 / (1 << 24))


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def _unit(v):
    return v * safe_div(1.0, safe_sqrt(_dot(v, v)))[..., None]


def _around(w, cos_t, phi):
    """The direction at polar angle `acos(cos_t)`, azimuth `phi` around unit `w`."""
    sign = jnp.where(w[:, 2] >= 0, 1.0, -1.0).astype(w.dtype)
    a = -1.0 / (sign + w[:, 2])
    b = w[:, 0] * w[:, 1] * a
    t = jnp.stack([1.0 + sign * w[:, 0] ** 2 * a, sign * b, -sign * w[:, 0]], axis=-1)
    s = jnp.stack([b, sign + w[:, 1] ** 2 * a, -w[:, 1]], axis=-1)
    sin_t = safe_sqrt(1.0 - cos_t * cos_t)
    v = (sin_t * jnp.cos(phi))[:, None] * t + (sin_t * jnp.sin(phi))[:, None] * s
    return _unit(v + cos_t[:, None] * w)


def _hg_cos(u, g):
    """Cosine of a Henyey-Greenstein scattering angle (with respect to the direction of
    propagation) sampled from `u` in [0, 1)."""
    small = jnp.abs(g) < 1e-3
    gs = jnp.where(small, 0.5, g)
    frac = (1.0 - gs * gs) / (1.0 - gs + 2.0 * gs * u)
    cos_hg = (1.0 + gs * gs - frac * frac) / (2.0 * gs)
    return jnp.clip(jnp.where(small, 1.0 - 2.0 * u, cos_hg), -1.0, 1.0)


def _pick_light(vs: VolScene, u):
    """Index into [area..., point..., beam...] chosen by power, and its probability."""
    cdf = vs.light_cdf
    L = cdf.shape[0]
    if L == 0:
        return jnp.zeros(u.shape, jnp.int32), jnp.ones(u.shape)
    idx = jnp.minimum(jnp.searchsorted(cdf, u, side="right"), L - 1).astype(jnp.int32)
    prev = jnp.where(idx > 0, cdf[jnp.maximum(idx - 1, 0)], 0.0)
    p = cdf[idx] - prev
    # no light has power: p = 0, and the caller's estimate is 0 / 1 instead of 0 / 0
    return idx, jnp.where(p > 0, p, jnp.inf)


def _occluded(vs: VolScene, o, d, t_max):
    t, _, _ = intersect_all(vs.shapes, o, d, EPS * 0.1, jnp.inf)
    return t < t_max


def _intersect_walkers(vs: VolScene, o, d, inside_obj, self_sid):
    """Nearest hit for walkers: those inside a medium (`inside_obj >= 0`) see only their own
    object, from `t = 0` on (a scattering vertex may lie any distance from the boundary, and
    `_step` starts walkers that enter or reflect inside `INSET` in, off the surface); a ray
    outside that leaves a surface (`self_sid >= 0`, origin on it) ignores that shape within
    `EPS` and accepts the others from `-EPS` on, so that surfaces in contact (a cube
    standing on a floor) are met where they touch rather than skipped."""
    W = o.shape[0]
    t_best = jnp.full(W, jnp.inf, o.dtype)
    n_best = jnp.zeros((W, 3), o.dtype)
    sid = jnp.full(W, -1, jnp.int32)
    after = self_sid >= 0
    for i, shape in enumerate(vs.shapes):
        t_min = jnp.where(self_sid == i, EPS, jnp.where(after, -EPS, EPS * 0.1))
        # inside: skipping the first EPS let walkers slip out (and walk on in empty space)
        t_min = jnp.where(inside_obj == i, 0.0, t_min)
        t_min = jnp.where((inside_obj >= 0) & (inside_obj != i), jnp.inf, t_min)
        t, n = shape.intersect(o, d, t_min, jnp.inf)
        closer = t < t_best
        t_best = jnp.where(closer, t, t_best)
        n_best = jnp.where(closer[:, None], n, n_best)
        sid = jnp.where(closer, i, sid)
    return t_best, n_best, sid


def _area_point(la, k, u1, u2):
    return la.corner[k] + u1[:, None] * la.edge_u[k] + u2[:, None] * la.edge_v[k]


# --- next-event estimation -------------------------------------------------------------
def _nee_diffuse(vs: VolScene, x, ns, u, geometry: bool = False):
    """Direct light at diffuse vertices `x` (facing normal `ns`), per unit albedo / pi:
    `int L_e cos dw` from one light chosen by power. **Returns:** `(W, 3)` irradiance;
    with `geometry`, also the shadow rays as `(x, y, tried, visible)` (for the ray tree)."""
    la = vs.lights
    na, npt, nb = la.n_area, la.n_point, la.n_beam
    W = x.shape[0]
    geo = dict(x=x, b=x, y=x, tried=jnp.zeros(W, bool), vis=jnp.zeros(W, bool))
    if na + npt + nb == 0:
        return (jnp.zeros((W, 3)), geo) if geometry else jnp.zeros((W, 3))
    idx, p_pick = _pick_light(vs, u[:, 0])
    E = jnp.zeros((W, 3))
    if na:
        k = jnp.minimum(idx, na - 1)
        y = _area_point(la, k, u[:, 1], u[:, 2])
        w = y - x
        d2 = _dot(w, w)
        dist = safe_sqrt(d2)
        w = w * safe_div(1.0, dist)[:, None]
        cos_x = _dot(w, ns)
        cos_l = -_dot(w, la.normal[k])
        ok = (idx < na) & (cos_x > 0) & (cos_l > 0)
        vis = ~_occluded(vs, x + EPS * ns, w, dist * (1 - 1e-4))
        g = la.area[k] * cos_x * cos_l * safe_div(1.0, d2)
        E = jnp.where((ok & vis)[:, None], la.radiance[k] * g[:, None], E)
        geo = _geo(geo, ok, x, x, y, vis)
    if npt:
        k = jnp.clip(idx - na, 0, npt - 1)
        w = la.position[k] - x
        d2 = _dot(w, w)
        dist = safe_sqrt(d2)
        w = w * safe_div(1.0, dist)[:, None]
        cos_x = _dot(w, ns)
        ok = (idx >= na) & (idx < na + npt) & (cos_x > 0)
        vis = ~_occluded(vs, x + EPS * ns, w, dist * (1 - 1e-4))
        g = cos_x * safe_div(1.0, d2)
        E = jnp.where((ok & vis)[:, None], la.intensity[k] * g[:, None], E)
        geo = _geo(geo, ok, x, x, la.position[k], vis)
    if nb:
        k = jnp.clip(idx - na - npt, 0, nb - 1)
        d = la.beam_dir[k]
        v = x - la.beam_origin[k]
        along = _dot(v, d)
        radial = safe_sqrt(_dot(v - along[:, None] * d, v - along[:, None] * d))
        cos_x = -_dot(ns, d)
        ok = (idx >= na + npt) & (along > 0) & (radial <= la.beam_radius[k]) & (cos_x > 0)
        vis = ~_occluded(vs, x + EPS * ns, -d, along * (1 - 1e-4))
        g = cos_x / (jnp.pi * la.beam_radius[k] ** 2)
        E = jnp.where((ok & vis)[:, None], la.beam_power[k] * g[:, None], E)
        geo = _geo(geo, ok, x, x, x - along[:, None] * d, vis)
    E = E / p_pick[:, None]
    return (E, geo) if geometry else E


def _geo(geo, ok, x, b, y, vis):
    """The connection `x -> b -> y` where `ok` (b = x: a straight shadow ray), kept for the
    ray tree."""
    sel = lambda a, v: jnp.where(ok.reshape(ok.shape + (1,) * (a.ndim - 1)), v, a)  # noqa: E731
    return dict(
        x=sel(geo["x"], x),
        b=sel(geo["b"], b),
        y=sel(geo["y"], y),
        tried=geo["tried"] | ok,
        vis=sel(geo["vis"], vis),
    )


def _faces(vs: VolScene, obj):
    """The planar faces of each walker's shape `obj`: `(c, n, e1, e2, kind, ok)`, gathered
    per walker, or broadcast `(1, F, ...)` when the scene has one translucent shape."""
    arrays = (vs.face_c, vs.face_n, vs.face_e1, vs.face_e2, vs.face_kind, vs.face_ok)
    if vs.single is not None:
        return tuple(a[vs.single][None] for a in arrays)
    return tuple(a[obj] for a in arrays)


def _connect_boundary(vs: VolScene, x, y, obj, eta, u_face):
    """A refracted connection `x -> b -> y` through translucent shape `obj`'s boundary.

    One planar face among those whose plane separates `x` and `y` is chosen uniformly
    (weight: their number), or one of a sphere's refraction points (weight: their number).
    **Returns:** dict with `b`, `nb` (outward normal at `b`), `w1`, `w2`, `d1`, `d2`,
    `cos1`, `G_perp` (`d omega_x / dA_perp`, times the selection weight) and `ok`.
    """
    fc, fn, f1, f2, fk, fok = _faces(vs, obj)  # (W or 1, F, ...)
    cand = fok & (_dot(fc - x[:, None, :], fn) > 0) & (_dot(y[:, None, :] - fc, fn) > 0)
    n_cand = jnp.sum(cand, axis=-1)
    pick = jnp.minimum(jnp.floor(u_face * n_cand), jnp.maximum(n_cand - 1, 0)).astype(jnp.int32)
    rank = jnp.cumsum(cand, axis=-1) - 1
    sel = cand & (rank == pick[:, None])  # one-hot over the faces
    take = lambda a: jnp.sum(jnp.where(sel[..., None], a, 0.0), axis=1)  # noqa: E731
    c, n, e1, e2 = take(fc), take(fn), take(f1), take(f2)
    kind = jnp.sum(jnp.where(sel, fk, 0), axis=1)
    pc = planar_connection(x, y, c, n, eta)
    ok_p = (n_cand > 0) & pc["ok"] & in_face(pc["b"], c, e1, e2, kind)
    out = dict(
        b=pc["b"],
        nb=n,
        w1=pc["w1"],
        w2=pc["w2"],
        d1=pc["d1"],
        d2=pc["d2"],
        cos1=pc["cos1"],
        G_perp=pc["G_perp"] * n_cand,
        ok=ok_p,
    )
    if not vs.has_sphere:
        return out
    sph = vs.is_sphere[obj]
    cen, rad = vs.sphere_c[obj], vs.sphere_r[obj]
    bs, oks = sphere_connections(x, y, cen, rad, eta)  # (W, M, 3)
    n_ok = jnp.sum(oks, axis=-1)
    pick = jnp.minimum(jnp.floor(u_face * n_ok), jnp.maximum(n_ok - 1, 0)).astype(jnp.int32)
    rank = jnp.cumsum(oks, axis=-1) - 1
    j = jnp.argmax(oks & (rank == pick[:, None]), axis=-1)
    b = jnp.take_along_axis(bs, j[:, None, None], axis=1)[:, 0]
    nb = (b - cen) / rad[:, None]
    w1 = _unit(b - x)
    w2 = _unit(y - b)
    d1 = safe_sqrt(_dot(b - x, b - x))
    d2 = safe_sqrt(_dot(y - b, y - b))
    G = exit_map_G(x, w1, lambda xx, ww: sphere_exit(xx, ww, cen, rad), eta, y, w2)
    sel = lambda a, b_: jnp.where(sph.reshape((-1,) + (1,) * (a.ndim - 1)), b_, a)  # noqa: E731
    return dict(
        b=sel(out["b"], b),
        nb=sel(out["nb"], nb),
        w1=sel(out["w1"], w1),
        w2=sel(out["w2"], w2),
        d1=sel(out["d1"], d1),
        d2=sel(out["d2"], d2),
        cos1=sel(out["cos1"], _dot(w1, nb)),
        G_perp=sel(out["G_perp"], G * n_ok),
        ok=jnp.where(sph, n_ok > 0, out["ok"]),
    )


def _nee_medium(vs: VolScene, x, d, obj, g, sig_s0, sig_t0, u, geometry: bool = False):
    """In-scattered radiance at medium vertices `x` (the walker arrived along `d`), from one
    light chosen by power, through the boundary of shape `obj`; `g`, `sig_s0`, `sig_t0`
    `(W, 3)` per channel.

    **Returns:** `(c (W, 3), dL, dn)`: the estimate at the proposal (per unit path weight),
    and the extra length in the medium and scattering events its path adds; with
    `geometry`, also the connections `(x, b, y, tried, visible)` (for the ray tree).
    """
    la = vs.lights
    na, npt, nb = la.n_area, la.n_point, la.n_beam
    W = x.shape[0]
    zero = jnp.zeros(W)
    c_out = jnp.zeros((W, 3))
    geo = dict(x=x, b=x, y=x, tried=jnp.zeros(W, bool), vis=jnp.zeros(W, bool))
    if na + npt + nb == 0:
        return (c_out, zero, zero, geo) if geometry else (c_out, zero, zero)
    eta = vs.eta[obj]
    idx, p_pick = _pick_light(vs, u[:, 0])
    dL, dn = zero, zero
    if na + npt:
        is_area = idx < na
        ka = jnp.minimum(idx, max(na - 1, 0))
        kp = jnp.clip(idx - na, 0, max(npt - 1, 0))
        ya = _area_point(la, ka, u[:, 1], u[:, 2]) if na else jnp.zeros((W, 3))
        yp = la.position[kp] if npt else jnp.zeros((W, 3))
        y = jnp.where(is_area[:, None], ya, yp) if na and npt else (ya if na else yp)
        con = _connect_boundary(vs, x, y, obj, eta, u[:, 3])
        Ft = 1.0 - fresnel_reflectance(con["cos1"], 1.0 / eta)
        vis = ~_occluded(vs, con["b"] + EPS * con["nb"], con["w2"], con["d2"] * (1 - 1e-4))
        if vs.all_convex:
            inside_ok = True
        else:  # a non-convex object: the inside segment must reach b first
            t_in, _, _ = intersect_all(vs.shapes, x, con["w1"], EPS * 0.1, jnp.inf)
            inside_ok = vs.convex[obj] | (t_in >= con["d1"] * (1 - 1e-3))
        phase = hg_phase(_dot(d, con["w1"])[:, None], g)
        att = jnp.exp(-sig_t0 * con["d1"][:, None])
        geo_f = Ft * con["G_perp"]
        if na:
            cos_l = -_dot(con["w2"], la.normal[ka])
            em_a = la.radiance[ka] * (la.area[ka] * jnp.maximum(cos_l, 0.0))[:, None]
        else:
            em_a = jnp.zeros((W, 3))
        em_p = la.intensity[kp] if npt else jnp.zeros((W, 3))
        em = jnp.where(is_area[:, None], em_a, em_p)
        ok = (idx < na + npt) & con["ok"] & vis & inside_ok
        c_out = jnp.where(ok[:, None], phase * att * geo_f[:, None] * em, 0.0)
        dL = jnp.where(ok, con["d1"], 0.0)
        tried = (idx < na + npt) & con["ok"] & inside_ok
        geo = _geo(geo, tried, x, con["b"], y, vis)
    if nb:
        is_beam = idx >= na + npt
        k = jnp.clip(idx - na - npt, 0, nb - 1)
        db = la.beam_dir[k]
        ref = jnp.where(jnp.abs(db[:, :1]) < 0.9, jnp.array([1.0, 0, 0]), jnp.array([0, 1.0, 0]))
        e1 = _unit(jnp.cross(db, ref))
        e2 = jnp.cross(db, e1)
        rho = la.beam_radius[k] * jnp.sqrt(u[:, 4])
        phi = 2.0 * jnp.pi * u[:, 5]
        ob = la.beam_origin[k] + rho[:, None] * (
            jnp.cos(phi)[:, None] * e1 + jnp.sin(phi)[:, None] * e2
        )
        tb, nbm, sid = intersect_all(vs.shapes, ob, db, EPS * 0.1, jnp.inf)
        xb = ob + jnp.where(jnp.isfinite(tb), tb, 0.0)[:, None] * db
        cos_b = -_dot(nbm, db)
        hit = (sid == obj) & (cos_b > 0)
        Ft_b = 1.0 - fresnel_reflectance(cos_b, eta)
        din, ok_r = refract_dir(db, nbm, eta)
        t_ex, _, _ = intersect_all(vs.shapes, xb - EPS * nbm, din, EPS * 0.1, jnp.inf)
        t_max = jnp.where(jnp.isfinite(t_ex), t_ex, 0.0)
        # equiangular sampling of the scattering point on the refracted beam, seen from x
        delta = _dot(x - xb, din)
        perp = x - xb - delta[:, None] * din
        h = jnp.maximum(safe_sqrt(_dot(perp, perp)), 1e-6)
        th_a = jnp.arctan2(-delta, h)
        th_b = jnp.arctan2(t_max - delta, h)
        tt = jnp.clip(delta + h * jnp.tan(th_a + u[:, 6] * (th_b - th_a)), 0.0, t_max)
        pdf = h / ((th_b - th_a) * (h * h + (tt - delta) ** 2))
        v = xb + tt[:, None] * din - x
        r2 = jnp.maximum(_dot(v, v), 1e-12)
        r = jnp.sqrt(r2)
        w = v / r[:, None]
        if vs.all_convex:
            seg_ok = True
        else:
            t_seg, _, _ = intersect_all(vs.shapes, x, w, EPS * 0.1, jnp.inf)
            seg_ok = vs.convex[obj] | (t_seg >= r * (1 - 1e-3))
        ph_x = hg_phase(_dot(d, w)[:, None], g)
        ph_y = hg_phase(_dot(din, -w)[:, None], g)
        # the beam's flux inside gives actual radiance: / eta^2 for basic radiance
        scal = Ft_b / (eta * eta) / (r2 * jnp.maximum(pdf, 1e-30))
        cb = ph_x * ph_y * la.beam_power[k] * sig_s0 * jnp.exp(-sig_t0 * (tt + r)[:, None])
        okb = is_beam & hit & ok_r & (t_max > 0) & (th_b > th_a) & seg_ok
        c_out = jnp.where(okb[:, None], cb * scal[:, None], c_out)
        dL = jnp.where(okb, tt + r, dL)
        dn = jnp.where(okb, 1.0, dn)
        geo = _geo(geo, okb, x, xb + tt[:, None] * din, ob, jnp.ones(W, bool))
    c_out = c_out / p_pick[:, None]
    return (c_out, dL, dn, geo) if geometry else (c_out, dL, dn)


class _BeamEntry(eqx.Module):
    """Where each beam's central ray enters a translucent shape, and the refracted beam as an
    elliptic cylinder (exact for a flat entry surface across the beam's footprint)."""

    x0: Array  # (Lb, 3) entry point
    din: Array  # (Lb, 3) refracted direction
    ep: Array  # (Lb, 3) cross-section axis in the plane of incidence
    es: Array  # (Lb, 3) cross-section axis perpendicular to it
    ap: Array  # (Lb,) semi-axes, mm
    as_: Array
    E_perp: Array  # (Lb, 3) flux per unit area across the refracted beam (power x F_t / area)
    sid: Array  # (Lb,) shape entered, -1 if none


def _beam_entry(vs: VolScene) -> _BeamEntry:
    la = vs.lights
    d = la.beam_dir
    t, n, sid = intersect_all(vs.shapes, la.beam_origin, d, EPS * 0.1, jnp.inf)
    x0 = la.beam_origin + jnp.where(jnp.isfinite(t), t, 0.0)[:, None] * d
    sidc = jnp.maximum(sid, 0)
    eta = vs.eta[sidc]
    cos_i = -_dot(n, d)
    ok = (sid >= 0) & (vs.kind[sidc] == TRANSLUCENT) & (cos_i > 0)
    din, ok_r = refract_dir(d, n, eta)
    cos_t = -_dot(n, din)
    es = jnp.cross(d, n)
    alt = jnp.cross(
        din, jnp.where(jnp.abs(din[:, :1]) < 0.9, jnp.array([1.0, 0, 0]), jnp.array([0, 1.0, 0]))
    )
    es = _unit(jnp.where((_dot(es, es) > 1e-12)[:, None], es, alt))
    ep = jnp.cross(es, din)
    ap = la.beam_radius * cos_t / jnp.maximum(cos_i, 1e-6)
    as_ = la.beam_radius
    Ft = 1.0 - fresnel_reflectance(cos_i, eta)
    E = la.beam_power * (Ft / (jnp.pi * ap * as_))[:, None]
    return _BeamEntry(
        x0,
        din,
        ep,
        es,
        ap,
        as_,
        jnp.where((ok & ok_r)[:, None], E, 0.0),
        jnp.where(ok & ok_r, sid, -1),
    )


def _beam_segment(be: _BeamEntry, vs: VolScene, o, d, seg, obj, g, sig_s0, sig_t0, u):
    """Single scattering of a beam on the walkers' medium segments `[o, o + seg d]` (those
    that start at a specular event: scattering vertices reach beams by next-event
    estimation): one point sampled uniformly on the segment's overlap with the refracted
    beam, `length sigma_s0 p E_perp exp(-sigma_t0 t_beam) / eta^2` (basic radiance).

    **Returns:** `(c (W, 3), s, dL)`: the estimate per unit path weight (without the
    transmittance from `o` to the point, which the caller's path weight carries), the
    point's distance along the segment and the length its path adds (one scattering event
    is added by the caller)."""
    Lb = be.x0.shape[0]
    k = jnp.minimum(jnp.floor(u[:, 0] * Lb), Lb - 1).astype(jnp.int32)
    q = o - be.x0[k]
    din, ep, es = be.din[k], be.ep[k], be.es[k]
    X0, Xd = _dot(q, ep) / be.ap[k], _dot(d, ep) / be.ap[k]
    Y0, Yd = _dot(q, es) / be.as_[k], _dot(d, es) / be.as_[k]
    A = Xd * Xd + Yd * Yd
    B = X0 * Xd + Y0 * Yd
    C = X0 * X0 + Y0 * Y0 - 1.0
    disc = B * B - A * C
    par = A < 1e-12
    root = safe_sqrt(disc)
    s1 = jnp.where(par, -jnp.inf, safe_div(-B - root, A))
    s2 = jnp.where(par, jnp.where(C <= 0, jnp.inf, -jnp.inf), safe_div(-B + root, A))
    s1 = jnp.where(par | (disc > 0), s1, jnp.inf)
    # t_beam(s) = q.din + s d.din >= 0: after the beam's entry
    qd, dd = _dot(q, din), _dot(d, din)
    s_b = safe_div(-qd, dd)
    lo = jnp.maximum(jnp.maximum(0.0, s1), jnp.where(dd > 0, s_b, -jnp.inf))
    hi = jnp.minimum(jnp.minimum(seg, s2), jnp.where(dd < 0, s_b, jnp.inf))
    hi = jnp.where((jnp.abs(dd) < 1e-12) & (qd < 0), lo, hi)
    length = jnp.maximum(hi - lo, 0.0)
    su = lo + u[:, 1] * length
    tb = jnp.maximum(qd + su * dd, 0.0)
    eta = vs.eta[jnp.maximum(obj, 0)]
    ok = (be.sid[k] == obj) & (length > 0)
    scal = jnp.where(ok, length / (eta * eta) * Lb, 0.0)
    c = sig_s0 * hg_phase(-_dot(din, d)[:, None], g) * be.E_perp[k]
    c = c * jnp.exp(-sig_t0 * tb[:, None]) * scal[:, None]
    return c, jnp.where(ok, su, 0.0), jnp.where(ok, su + tb, 0.0)


def _covered(vs: VolScene, obj, x, n):
    """Whether the boundary point `x` (outward normal `n`) of shape `obj` is reached by the
    refracted next-event estimator."""
    fc, fn, _, _, _, fok = _faces(vs, obj)
    on = (
        fok
        & (_dot(fn, n[:, None, :]) > 1.0 - 1e-4)
        & (jnp.abs(_dot(x[:, None, :] - fc, fn)) < 1e-2)
    )
    return vs.covered_all[obj] | jnp.any(on, axis=-1)


# --- the walk ------------------------------------------------------------------------------
def _init_state(o, d, hero, K, Mt, seed):
    W = o.shape[0]
    z3 = jnp.zeros((W, 3))
    f = jnp.zeros(W, bool)
    return dict(
        o=o,
        d=d,
        hero=hero,
        thr=jnp.ones((W, 3)),  # surface throughput per channel (albedo, reflectance, roulette)
        lf=z3,  # log of the medium part of the path's contribution, per channel, at the proposal
        lp=z3,  # log of the medium part of its density under each channel's proposal
        med=jnp.full(W, -1, jnp.int32),
        obj=jnp.full(W, -1, jnp.int32),
        self_sid=jnp.full(W, -1, jnp.int32),
        n=jnp.zeros((W, Mt)),
        L=jnp.zeros((W, Mt)),
        touched=f,
        skip_em=f,
        after_scatter=f,
        alive=jnp.ones(W, bool),
        events=jnp.zeros(W, jnp.int32),
        lost=f,
        ledger=jnp.zeros((W, len(_LEDGER))),
        base=z3,
        wsum=jnp.zeros(W),
        res_n=jnp.zeros((W, K, Mt)),
        res_L=jnp.zeros((W, K, Mt)),
        res_a=jnp.zeros((W, K, 3)),
        seed=seed,
    )


def _weights(thr, lf, lp, hero, mis: bool):
    """Each channel's path weight `(W, 3)`: `thr_c f_c / mean_k P_k` (spectral MIS), or the
    hero channel's own `thr_h f_h / P_h` and 0 elsewhere (`separate`)."""
    if mis:
        top = jnp.max(lp, axis=-1, keepdims=True)
        lm = top + jnp.log(jnp.mean(jnp.exp(lp - top), axis=-1, keepdims=True))
        return thr * jnp.exp(lf - lm)
    onehot = jnp.arange(3)[None, :] == hero[:, None]
    return jnp.where(onehot, thr * jnp.exp(lf - lp), 0.0)


def _hero(a, hero):
    return jnp.take_along_axis(a, hero[:, None], axis=1)[:, 0]


def _deposit(st, contrib, n_c, L_c, u_res):
    """Add contributions `contrib (W, 3)` (at the proposal) with statistics `(n_c, L_c)`:
    to `base` for paths that never entered a medium, else to the weighted reservoir (chosen
    in proportion to the channels' sum, each record keeping the channels' shares)."""
    q = jnp.sum(contrib, axis=-1)
    to_res = st["touched"] & (q > 0)
    base = st["base"] + jnp.where(st["touched"][:, None], 0.0, contrib)
    wsum = st["wsum"] + jnp.where(to_res, q, 0.0)
    p = safe_div(q, wsum)
    take = to_res[:, None] & (u_res < p[:, None])  # (W, K)
    a = contrib * safe_div(1.0, q)[:, None]
    return dict(
        st,
        base=base,
        wsum=wsum,
        res_n=jnp.where(take[..., None], n_c[:, None, :], st["res_n"]),
        res_L=jnp.where(take[..., None], L_c[:, None, :], st["res_L"]),
        res_a=jnp.where(take[..., None], a[:, None, :], st["res_a"]),
    )


def _safe_log(x):
    pos = x > 0
    return jnp.where(pos, jnp.log(jnp.where(pos, x, 1.0)), -jnp.inf)


# Over 150 lines by reason: one event of the walk (free flight, surface hit, next-event
# estimation, reservoir deposit, roulette) reads and writes the same ~20 walker arrays in
# one compiled body; split into functions they would pass that state back and forth whole.
def _step(vs: VolScene, prop: Proposal, st, u, u_res, nee=True, be=None, mis=True, record=False):
    """One event for every walker: a free flight inside a medium, or a hit outside.
    `be`: the scene's beams as they enter media (`_beam_entry`), or None without beams.
    `record`: also return the event's rays (`(state, rays)`, for the ray tree: the flight
    `o -> end`, its `EVENT` code, and the next-event connections tried)."""
    o, d, thr, lf, lp, hero = st["o"], st["d"], st["thr"], st["lf"], st["lp"], st["hero"]
    alive, med, obj = st["alive"], st["med"], st["obj"]
    K = st["res_n"].shape[1]
    W = o.shape[0]
    Mt = vs.n_materials
    inside = med >= 0
    m = jnp.maximum(med, 0)
    onehot = (jnp.arange(max(Mt, 1))[None, :] == m[:, None]) & inside[:, None]
    onehot = onehot[:, :Mt].astype(o.dtype)
    if Mt:
        st0, ss0, g3 = prop.sigma_t[m], prop.sigma_s[m], prop.g[m]  # (W, 3)
    else:
        st0 = ss0 = jnp.ones((W, 3))
        g3 = jnp.zeros((W, 3))
    st0h, gh = _hero(st0, hero), _hero(g3, hero)
    t, nrm, sid = _intersect_walkers(vs, o, d, obj, st["self_sid"])
    tl, rad = vs.lights.intersect(o, d, t)
    s = -jnp.log1p(-u[:, 0]) / st0h
    # every ray from inside a closed object meets its boundary: one that does not has
    # slipped out (a corner, a grazing hit) and would otherwise scatter on in empty space
    leak = alive & inside & (sid < 0)
    scatter = alive & inside & (s < t) & ~leak
    bnd = alive & inside & ~scatter & ~leak
    out = alive & ~inside
    hit_light = out & (tl < t)
    miss = out & ~hit_light & (sid < 0)
    surf = out & ~hit_light & (sid >= 0)
    sidc = jnp.maximum(sid, 0)
    kind = vs.kind[sidc]
    diffuse = surf & (kind == DIFFUSE)
    mirror = surf & (kind == MIRROR)
    transl = surf & (kind == TRANSLUCENT)
    t_hit = jnp.where(jnp.isfinite(t), t, 0.0)
    x_t = o + t_hit[:, None] * d
    x_s = o + jnp.where(scatter, s, 0.0)[:, None] * d
    cos = -_dot(d, nrm)  # > 0 when hitting the outside of a surface
    ns = jnp.where((cos >= 0)[:, None], nrm, -nrm)

    # the medium part of the path: the flight (to the scattering point or the boundary)
    seg = jnp.where(scatter, s, jnp.where(bnd, t_hit, 0.0))
    lf_n = lf - st0 * seg[:, None] + jnp.where(scatter[:, None], _safe_log(ss0), 0.0)
    lp_n = lp - st0 * seg[:, None] + jnp.where(scatter[:, None], _safe_log(st0), 0.0)
    n_new = st["n"] + jnp.where(scatter[:, None], onehot, 0.0)
    L_new = st["L"] + onehot * seg[:, None]
    w_prev = _weights(thr, lf, lp, hero, mis)
    w_sc = _weights(thr, lf_n, lp_n, hero, mis)

    # contributions: light scattered at the vertex, direct light on diffuse surfaces,
    # emitters and the environment seen
    obj0 = jnp.maximum(obj, 0)
    if record:  # eager-sized blocks: no branches to skip, and the rays are kept
        c_med, dL, dn, g_med = _nee_medium(vs, x_s, d, obj0, g3, ss0, st0, u[:, 1:8], True)
        if not nee:
            c_med, dL, dn = c_med * 0.0, dL * 0.0, dn * 0.0
        E, g_dif = _nee_diffuse(vs, x_t, ns, u[:, 1:4], True)
    else:
        c_med, dL, dn = jax.lax.cond(
            jnp.any(scatter) & nee,
            lambda: _nee_medium(vs, x_s, d, obj0, g3, ss0, st0, u[:, 1:8]),
            lambda: (jnp.zeros((W, 3)), jnp.zeros(W), jnp.zeros(W)),
        )
        E = jax.lax.cond(
            jnp.any(diffuse),
            lambda: _nee_diffuse(vs, x_t, ns, u[:, 1:4]),
            lambda: jnp.zeros((W, 3)),
        )
    alb = vs.albedo[sidc]
    contrib = jnp.where(scatter[:, None], w_sc * c_med, 0.0)
    contrib += jnp.where(diffuse[:, None], w_prev * alb / jnp.pi * E, 0.0)
    contrib += jnp.where((hit_light & ~st["skip_em"])[:, None], w_prev * rad, 0.0)
    contrib += jnp.where(miss[:, None], w_prev * vs.env, 0.0)
    n_c = n_new + jnp.where(scatter, dn, 0.0)[:, None] * onehot
    L_c = L_new + jnp.where(scatter, dL, 0.0)[:, None] * onehot
    new = _deposit(st, contrib, n_c, L_c, u_res[:, :K])
    if be is not None:  # beams: their single scattering on segments that start specular
        c_b, su, dL_b = _beam_segment(be, vs, o, d, seg, obj, g3, ss0, st0, u[:, 12:14])
        w_b = _weights(thr, lf - st0 * su[:, None], lp - st0 * su[:, None], hero, mis)
        on = (scatter | bnd) & ~st["after_scatter"]
        c_b = jnp.where(on[:, None], w_b * c_b, 0.0)
        new = _deposit(new, c_b, st["n"] + onehot, st["L"] + dL_b[:, None] * onehot, u_res[:, K:])

    # next directions: the phase function (hero's g) or a cosine-weighted bounce
    axis = jnp.where(scatter[:, None], d, ns)
    cos_t = jnp.where(scatter, _hg_cos(u[:, 8], gh), jnp.sqrt(1.0 - u[:, 8]))
    d_bounce = _around(axis, cos_t, 2.0 * jnp.pi * u[:, 9])
    ph = jnp.log(hg_phase(cos_t[:, None], g3))  # f and every channel's density: MIS over g
    lf_n = lf_n + jnp.where(scatter[:, None], ph, 0.0)
    lp_n = lp_n + jnp.where(scatter[:, None], ph, 0.0)
    d_mir = d + 2.0 * cos[:, None] * nrm  # reflection about the surface
    # dielectric boundaries: from inside (relative index 1 / eta) or from outside (eta)
    eta_s = vs.eta[sidc]
    eta_rel = jnp.where(bnd, 1.0 / eta_s, eta_s)
    F = fresnel_reflectance(cos, eta_rel)
    front = transl & (cos > 0)
    through = transl & ~front  # hit from behind (grazing, numerical): pass on
    refl_in = bnd & (u[:, 10] < F)
    exit_ = bnd & ~refl_in
    refl_out = front & (u[:, 10] < F)
    enter = front & ~refl_out
    d_ref, _ = refract_dir(d, jnp.where(bnd[:, None], -nrm, nrm), eta_rel)

    spec = mirror | refl_out | refl_in
    d_next = jnp.where((scatter | diffuse)[:, None], d_bounce, d)
    d_next = jnp.where(spec[:, None], d_mir, d_next)
    d_next = jnp.where((exit_ | enter)[:, None], d_ref, d_next)
    # surface events leave from the surface point itself (`_intersect_walkers` skips it)
    on_surface = diffuse | mirror | transl | bnd
    o_next = jnp.where(scatter[:, None], x_s, jnp.where(on_surface[:, None], x_t, o))
    # except into a medium: a hair inside, on the side the walker goes, so that the next
    # flight meets the boundary from t = 0 on (a face closer than EPS, at an edge, counts)
    into = enter | refl_in
    side = jnp.sign(_dot(d_next, nrm))[:, None] * nrm
    o_next = jnp.where(into[:, None], x_t + INSET * side, o_next)

    refl = vs.reflectance[sidc]
    thr_n = jnp.where(diffuse[:, None], thr * alb, jnp.where(mirror[:, None], thr * refl, thr))
    med_n = jnp.where(enter, vs.mat[sidc], jnp.where(exit_, -1, med))
    obj_n = jnp.where(enter, sid, jnp.where(exit_, -1, obj))
    covered = _covered(vs, obj0, x_t, nrm)
    skip = jnp.where(diffuse, True, st["skip_em"])
    skip = jnp.where(mirror | refl_out | enter | through, False, skip)
    skip = jnp.where(exit_, st["after_scatter"] & covered & nee, skip)
    after = jnp.where(scatter, True, jnp.where(refl_in | exit_ | enter, False, st["after_scatter"]))
    events = st["events"] + alive.astype(jnp.int32)
    # Russian roulette on the largest channel weight, after scattering or a diffuse bounce
    w_new = _weights(thr_n, lf_n, lp_n, hero, mis)
    w_max = jnp.max(w_new, axis=-1)
    rr = (scatter | diffuse) & (events >= RR_MIN_EVENTS) & (w_max < RR_WEIGHT)
    q = w_max / RR_WEIGHT
    survive = u[:, 11] < q
    thr_rr = jnp.where(
        rr[:, None], jnp.where(survive[:, None], thr_n * safe_div(1.0, q)[:, None], 0.0), thr_n
    )
    cut = alive & ((events >= MAX_EVENTS) | leak)
    dead = hit_light | miss | cut | (rr & ~survive)
    dead = dead | (diffuse & (jnp.max(alb, -1) <= 0)) | (mirror & (jnp.max(refl, -1) <= 0))
    # where each walker's (hero channel's analog) weight goes: adds up to its start weight
    a0 = _hero(thr, hero) * jnp.exp(_hero(lf, hero) - _hero(lp, hero))
    a1 = _hero(thr_n, hero) * jnp.exp(_hero(lf_n, hero) - _hero(lp_n, hero))
    a2 = _hero(thr_rr, hero) * jnp.exp(_hero(lf_n, hero) - _hero(lp_n, hero))
    a0 = jnp.where(alive, a0, 0.0)
    ledger = st["ledger"] + jnp.stack(
        [
            jnp.where(miss, a0, 0.0),
            jnp.where(hit_light, a0, 0.0),
            jnp.where(scatter | diffuse | mirror, a0 - a1, 0.0),
            jnp.where(alive, a1 - a2, 0.0),
            jnp.where(cut & ~hit_light & ~miss, a2, 0.0),
        ],
        axis=1,
    )
    out = dict(
        new,
        o=o_next,
        d=d_next,
        thr=thr_rr,
        lf=lf_n,
        lp=lp_n,
        med=med_n,
        obj=obj_n,
        self_sid=jnp.where(on_surface, sid, -1),
        n=n_new,
        L=L_new,
        touched=st["touched"] | enter,
        skip_em=skip,
        after_scatter=after,
        alive=alive & ~dead,
        events=events,
        lost=st["lost"] | leak,
        ledger=ledger,
    )
    if not record:
        return out
    # a miss ends at its origin here: the recorder draws it `far` along `d`
    end = jnp.where((scatter | on_surface)[:, None], jnp.where(scatter[:, None], x_s, x_t), o)
    end = jnp.where(hit_light[:, None], o + jnp.where(hit_light, tl, 0.0)[:, None] * d, end)
    code = jnp.select(
        [scatter, refl_in, exit_, hit_light, miss, diffuse, mirror, refl_out, enter, through],
        list(range(10)),
        default=EVENT.index("cut"),
    )
    nee_m = dict(g_med, tried=g_med["tried"] & scatter & nee)
    nee_d = dict(g_dif, tried=g_dif["tried"] & diffuse)
    rays = dict(o=o, d=d, end=end, code=code, alive=alive, inside=inside, nee_m=nee_m, nee_d=nee_d)
    return out, rays


def _walk(vs: VolScene, prop: Proposal, st: dict, nee: bool = True, mis: bool = True) -> dict:
    """Run every walker of `st` to its end.

    Most walkers end within a few events (on the background, a light, or by roulette) while
    a few wander inside a medium for thousands: every `_PHASE` events the alive ones are
    stepped, packed, in chunks of `_chunk(W)` walkers (`_packing.step_alive`; one chunk width
    compiles `_step` once, where a `switch` over three packed widths compiled it three
    times), so the cost follows the walkers that are still going, not the block.
    """
    W = st["alive"].shape[0]
    K = st["res_n"].shape[1]
    C = _chunk(W)
    be = _beam_entry(vs) if vs.lights.n_beam else None

    def steps(i, sub):
        def body(j, sub):
            u = _uniforms(sub["seed"], i + j, _NU + 2 * K).astype(sub["o"].dtype)
            return _step(vs, prop, sub, u[:, :_NU], u[:, _NU:], nee, be, mis)

        return jax.lax.fori_loop(0, _PHASE, body, sub)

    def cond(carry):
        i, st = carry
        return jnp.any(st["alive"]) & (i < MAX_EVENTS)

    def body(carry):
        i, st = carry
        if C == W:
            return i + _PHASE, steps(i, st)
        return i + _PHASE, step_alive(st, C, lambda sub, _: steps(i, sub))

    _, st = jax.lax.while_loop(cond, body, (jnp.int32(0), st))
    return st


def _chunk(W: int) -> int:
    """Walkers stepped together. On CPU a fixed `_CHUNK_CPU`: a chunk's state then stays in
    cache (marble cube, 48 x 48 x 16 spp, s per image after compiling, by chunk width:
    2048: 14.5, 512: 4.3, 256: 4.0, 128: 3.8, 64: 4.2, 32: 7.7; the former three packed widths
    7.7). On accelerators, which want wide steps, 1/`_CHUNKS` of the block (not measured)."""
    if jax.default_backend() == "cpu":
        return min(W, _CHUNK_CPU)
    return max(-(-W // _CHUNKS), 1)


def trace_block(
    vs: VolScene,
    prop: Proposal,
    camera,
    pixels: Int[Array, " P"],
    key: PRNGKeyArray,
    spp: int,
    K: int = 4,
    nee: bool = True,
    spectral: str = "mis",
) -> tuple[Float[Array, "P 3"], VolumetricTerms, WalkStats]:
    """Walk `spp` camera samples for each of `pixels` (flat indices): one walker per sample
    for all channels (`spectral="mis"`) or one per channel (`"separate"`).

    **Returns:** `(base (P, 3), terms, stats)`: the coefficient-independent radiance (paths
    that never entered a medium), the re-weightable records of the rest, and diagnostics.
    Pixel radiance at the proposal is `base + shade_terms(terms, media)`. `nee=False` turns
    off next-event estimation inside media (light then reaches them through random exits
    only: the same expectation, more noise; for tests).
    """
    if spectral not in ("mis", "separate"):
        raise ValueError(f"spectral must be 'mis' or 'separate', got {spectral!r}")
    mis = spectral == "mis"
    st, per = _start(vs, prop, camera, pixels, key, spp, K, spectral)
    st = _walk(vs, prop, st, nee, mis)
    return _finish(st, pixels.shape[0], spp, per, K, prop)


def _start(vs: VolScene, prop: Proposal, camera, pixels, key, spp: int, K: int, spectral: str):
    """The walkers of `pixels` at the camera: `(state, walkers per camera sample)`; walker
    `(p spp + s) per + c` is pixel `p`'s sample `s` (channel `c` with `separate`)."""
    mis = spectral == "mis"
    P = pixels.shape[0]
    k_cam, k_walk = jax.random.split(key)
    o, d = camera_rays(camera, pixels, stratified_2d(k_cam, spp, (P,)))  # (P, S, 3)
    per = 1 if mis else 3  # walkers per camera sample
    o = jnp.repeat(o.reshape(P * spp, 3), per, axis=0)
    d = jnp.repeat(d.reshape(P * spp, 3), per, axis=0)
    W = P * spp * per
    seed = jax.random.bits(k_walk, (W,), jnp.uint32)
    if mis:
        hero = (_pcg(seed ^ jnp.uint32(0x68E31DA4)) % jnp.uint32(3)).astype(jnp.int32)
    else:
        hero = jnp.tile(jnp.arange(3, dtype=jnp.int32), P * spp)
    return _init_state(o, d, hero, K, vs.n_materials, seed), per


def _finish(st, P: int, spp: int, per: int, K: int, prop: Proposal):
    """`(base, terms, stats)` of walked walkers (`trace_block`)."""
    Mt = st["n"].shape[-1]
    Sw = spp * per  # walkers per pixel
    base = st["base"].reshape(P, Sw, 3).sum(axis=1) / spp
    w = (st["wsum"] / (K * spp))[:, None, None] * st["res_a"]  # (W, K, 3)
    terms = VolumetricTerms(
        jnp.moveaxis(w.reshape(P, Sw * K, 3), -1, 0),
        st["res_n"].reshape(P, Sw * K, Mt),
        st["res_L"].reshape(P, Sw * K, Mt),
        prop.sigma_s,
        prop.sigma_t,
        K,
    )
    stats = WalkStats(
        events=jnp.sum(st["events"]),
        longest=jnp.max(st["events"]),
        truncated=jnp.sum(st["events"] >= MAX_EVENTS),
        lost=jnp.sum(st["lost"]),
        **{k: jnp.sum(st["ledger"][:, i]) for i, k in enumerate(_LEDGER)},
    )
    return base, terms, stats


_record_step = jax.jit(functools.partial(_step, record=True), static_argnums=(5, 7))


def _record_walk(vs: VolScene, prop: Proposal, st: dict, sel, sample, nee, mis, rec) -> dict:
    """Walk the walkers `sel` (indices; `sample`: their camera sample) one compiled event at
    a time, handing each event's rays to `rec.walk`: the same walks as `_walk` (every
    walker draws its own random numbers by event), for the ray tree."""
    K = st["res_n"].shape[1]
    be = _beam_entry(vs) if vs.lights.n_beam else None
    sub = {f: v[sel] for f, v in st.items()}
    for i in range(MAX_EVENTS):
        if not bool(jnp.any(sub["alive"])):
            break
        u = _uniforms(sub["seed"], jnp.int32(i), _NU + 2 * K).astype(sub["o"].dtype)
        sub, rays = _record_step(vs, prop, sub, u[:, :_NU], u[:, _NU:], nee, be, mis)
        rays = jax.tree_util.tree_map(np.asarray, rays)
        rec.walk(i, dict(rays, sample=np.asarray(sample)))
    return {f: v.at[sel].set(sub[f]) for f, v in st.items()}


class Volumetric(TransportMethod):
    """The volumetric transport of one scene: one phase (every pixel's walks, whose
    records exist for the pixels some path of which entered a medium). Static
    configuration: the boundary geometry for refracted next-event estimation, `records` per
    walker, the spectral mode and spp; the proposal is the arrays' media
    (`SceneArrays.with_media`), their `eta` and lights may be traced values."""

    name = "volumetric"
    two_phase = False
    reweighted = True

    def __init__(self, arrays):
        self.vs = VolScene.from_arrays(arrays)
        sss = arrays.sss
        self.records = sss.records
        self.spectral = sss.spectral
        self.nee = sss.next_event
        self.spp = arrays.render.spp
        self.materials = arrays.materials
        self.enabled = sss.enabled and arrays.n_objects > 0

    @property
    def media_dependent(self) -> bool:
        return self.enabled

    def block_pixels(self, tile: int) -> int:
        """About `_BLOCK_WALKERS` walkers per block, in whole tiles: walks end at very
        different times, and a wide block keeps the packed tail of long walks busy."""
        per_px = self.spp * (3 if self.spectral == "separate" else 1)
        tiles = max(1, _BLOCK_WALKERS // (per_px * tile * tile))
        return tiles * tile * tile

    def empty_terms(self) -> VolumetricTerms:
        Mt = len(self.materials)
        R = self.spp * self.records * (3 if self.spectral == "separate" else 1)
        z = jnp.zeros((0, R, Mt))
        return VolumetricTerms(
            jnp.zeros((3, 0, R)), z, z, jnp.zeros((Mt, 3)), jnp.zeros((Mt, 3)), self.records
        )

    def trace_block(self, arrays, state, pixels, key, rec: Recorder = NO_RECORD) -> Block:
        vs = self.vs.with_arrays(arrays)
        prop = Proposal.from_media(arrays.media)
        if rec.active:
            return self._recorded(vs, prop, arrays, pixels, key, rec)
        base, terms, _ = trace_block(
            vs,
            prop,
            arrays.camera,
            pixels,
            key,
            self.spp,
            K=self.records,
            nee=self.nee,
            spectral=self.spectral,
        )
        needs = jnp.any(terms.w > 0, axis=(0, 2))
        return Block(base, needs, terms)

    def _recorded(self, vs, prop, arrays, pixels, key, rec: Recorder) -> Block:
        """`trace_block` with the walks of the recorder's rows (`rec.rows`: pixel samples of
        the block; all when it has none) stepped one event at a time and recorded: the other
        walkers do not move, so their pixels come out black."""
        spp, K = self.spp, self.records
        st, per = _start(vs, prop, arrays.camera, pixels, key, spp, K, self.spectral)
        W = st["alive"].shape[0]
        rows = getattr(rec, "rows", None)
        want = np.ones(W, bool) if rows is None else np.repeat(np.asarray(rows, bool), per)
        sel = np.flatnonzero(want)
        mis = self.spectral == "mis"
        st = _record_walk(vs, prop, st, jnp.asarray(sel), (sel // per) % spp, self.nee, mis, rec)
        base, terms, _ = _finish(st, pixels.shape[0], spp, per, K, prop)
        needs = jnp.any(terms.w > 0, axis=(0, 2))
        return Block(base, needs, terms)
