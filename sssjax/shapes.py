"""Geometric primitives: ray intersection, uniform area sampling, bounds and tessellation.

Every shape is an immutable `equinox.Module` pytree defined in its own *object space* and
placed in the world by an affine 4x4 homogeneous matrix `to_world` (object -> world) and its
inverse `to_object`. Lengths are in **millimetres**. Array fields are pytree leaves, so a
shape can be passed through `jax.jit`, `jax.vmap` and `jax.grad` like any other pytree.

Object-space definitions:

- `Sphere(radius)`: centred at the origin.
- `Cube(size)`: the box `[-size/2, size/2]^3`; `size` is a scalar (a cube) or a 3-vector.
- `Cylinder(radius, height)`: axis `+y` from `y = 0` to `y = height`, capped with two discs.
- `Cone(radius, height)`: base disc of `radius` at `y = 0` (capped), apex at `(0, height, 0)`.
- `QuadMesh(vertices, faces)`: quads and/or triangles, stored as triangles; intersection is
  two-sided and the normal is the geometric face normal given by the winding order
  (counter-clockwise seen from outside = outward).

Rays are batched: origins `o` and directions `d` of shape `(..., 3)` (`(N, 3)` usually); `d`
need not be unit length and `t` is the ray parameter of `o + t d` in world space. Misses are
`t = inf` with a zero normal. Normals are unit *outward* world normals whichever side the ray
comes from. All square roots and divisions use the double-`where` idiom, so values and
gradients with respect to `o` and `d` are NaN-free for misses, grazing rays and rays that start
inside a shape.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._numerics import float_dtype, safe_div, safe_sqrt

__all__ = [
    "Cone",
    "Cube",
    "Cylinder",
    "QuadMesh",
    "SHAPE_KINDS",
    "Sphere",
    "intersect_all",
    "load_obj",
    "make_shape",
    "placement",
]

_EYE4 = np.eye(4)


# --- placement ---------------------------------------------------------------------------
def _rotation(axis: int, degrees: float) -> np.ndarray:
    """Right-handed rotation by `degrees` about coordinate `axis`, exact for multiples of 90."""
    deg = float(degrees)
    if deg % 90.0 == 0.0:
        k = int(round(deg / 90.0)) % 4
        c, s = (1.0, 0.0, -1.0, 0.0)[k], (0.0, 1.0, 0.0, -1.0)[k]
    else:
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.eye(4)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def placement(
    translate: ArrayLike = (0.0, 0.0, 0.0),
    rotate: ArrayLike = (0.0, 0.0, 0.0),
    scale: ArrayLike = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The affine placement `T @ Rz @ Ry @ Rx @ S` of an object in the world, and its inverse.

    **Arguments:**

    - `translate`: world position of the object-space origin, mm.
    - `rotate`: rotation angles in **degrees** about x, then y, then z (right-handed).
    - `scale`: a scalar or a 3-vector of per-axis scale factors (non-zero), applied first.

    **Returns:** `(to_world, to_object)`, two `(4, 4)` float64 NumPy arrays.
    """
    t = np.broadcast_to(np.asarray(translate, dtype=np.float64), (3,))
    angles = np.broadcast_to(np.asarray(rotate, dtype=np.float64), (3,))
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
    for name, v in (("translate", t), ("rotate", angles), ("scale", s)):
        if not np.all(np.isfinite(v)):
            raise ValueError(f"placement {name} must be finite, got {v.tolist()}")
    if np.any(s == 0):
        raise ValueError(f"placement scale must be non-zero, got {s.tolist()}")
    T, Ti = np.eye(4), np.eye(4)
    T[:3, 3], Ti[:3, 3] = t, -t
    S, Si = np.diag([*s, 1.0]), np.diag([*(1.0 / s), 1.0])
    R = _rotation(2, angles[2]) @ _rotation(1, angles[1]) @ _rotation(0, angles[0])
    return T @ R @ S, Si @ R.T @ Ti


# --- small helpers -----------------------------------------------------------------------
def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _tiny(dtype) -> float:
    """`sqrt` of the smallest normal number: `1/x^2` stays finite for `|x| > _tiny`."""
    return float(np.sqrt(np.finfo(dtype).tiny))


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, axis=-1)


def _div(num: Array, den: Array) -> tuple[Array, Array]:
    """`(num / den, ok)`; where `|den|` is (nearly) zero the value is 0 and `ok` is False."""
    ok = jnp.abs(den) > _tiny(den.dtype)
    return safe_div(num, jnp.where(ok, den, 0.0)), ok


def _normalize(v: Array) -> Array:
    """`v / |v|`, or 0 where `v = 0`, NaN-free in value and gradient."""
    return v * safe_div(1.0, safe_sqrt(_dot(v, v)))[..., None]


def _roots(a: Array, bh: Array, c: Array, disc: Array) -> list[tuple[Array, Array]]:
    """Both roots of `a t^2 + 2 bh t + c = 0` given `disc = bh^2 - a c`, as `(t, ok)` pairs.

    The cancellation-free form `q = -(bh + sign(bh) sqrt(disc))`, roots `q / a` and `c / q`,
    also covers the linear case `a = 0` (root `-c / (2 bh)`).
    """
    real = disc >= 0
    sq = safe_sqrt(jnp.where(disc > np.finfo(disc.dtype).tiny, disc, 0.0))
    q = -(bh + jnp.where(bh >= 0, sq, -sq))
    t0, ok0 = _div(q, a)
    t1, ok1 = _div(c, q)
    return [(t0, real & ok0), (t1, real & ok1)]


def _nearest(cands, t_min: Array, t_max: Array) -> tuple[Array, Array]:
    """The nearest valid candidate `(t, ok, n_obj)` with `t_min < t < t_max`; `t = inf` if none."""
    n_rays = t_min.shape[0]
    ts = jnp.stack(
        [jnp.where(ok & (t > t_min) & (t < t_max), t, jnp.inf) for t, ok, _ in cands], axis=-1
    )
    ns = jnp.stack([jnp.broadcast_to(n, (n_rays, 3)) for *_, n in cands], axis=1)
    k = jnp.argmin(ts, axis=-1)
    t = jnp.take_along_axis(ts, k[:, None], axis=-1)[:, 0]
    n = jnp.take_along_axis(ns, k[:, None, None], axis=1)[:, 0]
    return t, n


def _eps(dtype) -> float:
    """Relative slack on containment tests so rays through edges and rims do not leak."""
    return 8.0 * float(np.finfo(dtype).eps)


def _fmt(x) -> str:
    a = np.asarray(x)
    return f"{a.item():g}" if a.ndim == 0 else "[" + ", ".join(f"{v:g}" for v in a.ravel()) + "]"


def _positive(cls: str, name: str, value, shape: tuple[int, ...] = ()) -> Array:
    """A strictly positive, finite length parameter as a float array (checked when concrete)."""
    if not _is_concrete(value):
        return value
    a = np.asarray(value, dtype=np.float64)
    if shape == (3,) and a.ndim == 0:
        a = np.full(3, a)
    if a.shape != shape:
        want = "a scalar" if shape == () else "a scalar or a 3-vector"
        raise ValueError(f"{cls}.{name} must be {want}, got shape {a.shape}")
    if not np.all(np.isfinite(a)) or np.any(a <= 0):
        raise ValueError(f"{cls}.{name} must be finite and > 0 (mm), got {_fmt(a)}")
    return jnp.asarray(a, dtype=float_dtype())


def _matrices(to_world, to_object) -> tuple[Array, Array]:
    """Validate and complete a `(to_world, to_object)` pair (either may be None)."""
    if to_world is None and to_object is None:
        eye = jnp.eye(4, dtype=float_dtype())
        return eye, eye
    mats = []
    for name, m in (("to_world", to_world), ("to_object", to_object)):
        if m is None or not _is_concrete(m):
            mats.append(m)
            continue
        a = np.asarray(m, dtype=np.float64)
        if a.shape != (4, 4):
            raise ValueError(f"{name} must be a 4x4 matrix, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite")
        if not np.allclose(a[3], [0.0, 0.0, 0.0, 1.0]):
            raise ValueError(f"{name} must be affine (last row 0 0 0 1), got {_fmt(a[3])}")
        mats.append(a)
    w, o = mats
    for name, a, b in (("to_object", o, w), ("to_world", w, o)):
        if a is None:
            if isinstance(b, np.ndarray):
                if abs(np.linalg.det(b[:3, :3])) == 0:
                    raise ValueError("the placement matrix is singular")
                a = np.linalg.inv(b)
            else:
                a = jnp.linalg.inv(b)
            if name == "to_object":
                o = a
            else:
                w = a
    if isinstance(w, np.ndarray) and isinstance(o, np.ndarray):
        err = np.max(np.abs(w @ o - _EYE4))
        if err > 1e-4:
            raise ValueError(f"to_object is not the inverse of to_world (|W O - I| = {err:.3g})")
    dt = float_dtype()
    conv = [jnp.asarray(m, dtype=dt) if isinstance(m, np.ndarray) else m for m in (w, o)]
    return conv[0], conv[1]


def _to_rays(o: ArrayLike, d: ArrayLike, dtype) -> tuple[Array, Array, tuple[int, ...]]:
    o, d = jnp.asarray(o), jnp.asarray(d)
    dt = jnp.promote_types(jnp.promote_types(o.dtype, d.dtype), dtype)
    if not jnp.issubdtype(dt, jnp.floating):
        dt = float_dtype()
    shape = jnp.broadcast_shapes(o.shape, d.shape)
    if shape[-1:] != (3,):
        raise ValueError(f"ray origins and directions must have a last axis of 3, got {shape}")
    batch = shape[:-1]
    o = jnp.broadcast_to(o.astype(dt), shape).reshape(-1, 3)
    d = jnp.broadcast_to(d.astype(dt), shape).reshape(-1, 3)
    return o, d, batch


def _orient_outward(v: np.ndarray, tris: np.ndarray, interior: np.ndarray) -> np.ndarray:
    """Flip triangles of a convex surface so that their normals point away from `interior`."""
    a, b, c = v[tris[:, 0]], v[tris[:, 1]], v[tris[:, 2]]
    nrm = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", nrm, (a + b + c) / 3.0 - interior) < 0
    tris = tris.copy()
    tris[flip] = tris[flip][:, ::-1]
    return tris


def _ring(radius: float, y: float, n: int) -> np.ndarray:
    phi = 2.0 * np.pi * np.arange(n) / n
    return np.stack([radius * np.cos(phi), np.full(n, y), radius * np.sin(phi)], axis=-1)


def _fan(centre: int, ring: np.ndarray) -> np.ndarray:
    return np.stack([np.full(len(ring), centre), ring, np.roll(ring, -1)], axis=-1)


def _band(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    nxt_l, nxt_u = np.roll(lower, -1), np.roll(upper, -1)
    return np.concatenate(
        [np.stack([lower, nxt_l, nxt_u], -1), np.stack([lower, nxt_u, upper], -1)]
    )


def _pick(weights: Array, u: Array) -> Array:
    """Index of the part chosen by `u` in `[0, 1)` with probability proportional to `weights`."""
    cdf = jnp.cumsum(weights)
    idx = jnp.searchsorted(cdf, u * cdf[-1], side="right")
    return jnp.clip(idx, 0, weights.shape[0] - 1)


def _uniform_disc(radius: Array, u0: Array, u1: Array) -> tuple[Array, Array]:
    rho = radius * safe_sqrt(u0)
    phi = 2.0 * jnp.pi * u1
    return rho * jnp.cos(phi), rho * jnp.sin(phi)


# --- the common base ---------------------------------------------------------------------
class _Shape(eqx.Module):
    """Machinery shared by all primitives: the placement and the world-space wrappers."""

    to_world: Float[Array, "4 4"]
    to_object: Float[Array, "4 4"]

    # -- hooks implemented by each primitive (object space) ------------------------------
    def _centre(self) -> Array:
        return jnp.zeros(3, dtype=self.to_world.dtype)

    def _hit(self, o: Array, d: Array, t_min: Array, t_max: Array) -> tuple[Array, Array]:
        raise NotImplementedError

    def _sample_object(self, u: Array) -> tuple[Array, Array]:
        raise NotImplementedError

    def _area(self) -> Array:
        raise NotImplementedError

    def _tessellate_object(self, resolution: int) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _require_uniform_scale(self, method: str) -> None:
        """Raise if the placement is not a similarity (rotation times a uniform scale)."""
        if not _is_concrete(self.to_world):
            return
        m = np.asarray(self.to_world, dtype=np.float64)[:3, :3]
        g = m.T @ m
        s2 = np.trace(g) / 3.0
        if np.max(np.abs(g - s2 * np.eye(3))) > 1e-5 * s2:
            sv = np.linalg.svd(m, compute_uv=False)
            raise ValueError(
                f"{type(self).__name__}.{method}() needs a uniform scale; the placement scales "
                f"by {_fmt(sv)} along its principal axes (use a QuadMesh for a non-uniformly "
                "scaled instance)"
            )

    def _similarity_scale2(self) -> Array:
        """`s^2` of a similarity placement `s R` (mean squared singular value)."""
        m = self.to_world[:3, :3]
        return jnp.sum(m * m) / 3.0

    def _face_scale(self, normals_obj: Array) -> Array:
        """World/object area ratio of planar pieces with object normals (Nanson's formula)."""
        m = self.to_world[:3, :3]
        cof = normals_obj @ self.to_object[:3, :3]
        return jnp.abs(jnp.linalg.det(m)) * jnp.sqrt(_dot(cof, cof))

    # -- public API ------------------------------------------------------------------------
    def intersect(
        self, o: ArrayLike, d: ArrayLike, t_min: ArrayLike = 1e-4, t_max: ArrayLike = jnp.inf
    ) -> tuple[Float[Array, "*n"], Float[Array, "*n 3"]]:
        """The first hit of the rays `o + t d` with `t_min < t < t_max`.

        **Arguments:**

        - `o`: ray origins, world space, shape `(..., 3)` (usually `(N, 3)`), mm.
        - `d`: ray directions, same shape (need not be unit length).
        - `t_min`, `t_max`: the open interval of accepted ray parameters (scalars or `(...)`).

        **Returns:** `(t, n)`: the ray parameter of the hit, shape `(...)` (`inf` on a miss),
        and the unit outward world normal there, shape `(..., 3)` (0 on a miss).
        """
        o, d, batch = _to_rays(o, d, self.to_object.dtype)
        t_min = jnp.broadcast_to(jnp.asarray(t_min, dtype=o.dtype), batch).reshape(-1)
        t_max = jnp.broadcast_to(jnp.asarray(t_max, dtype=o.dtype), batch).reshape(-1)
        t, n = _intersect_core(self, o, d, t_min, t_max)
        return t.reshape(batch), n.reshape(*batch, 3)

    def sample(self, u: ArrayLike) -> tuple[Float[Array, "*n 3"], Float[Array, "*n 3"]]:
        """Points distributed uniformly by area over the world-space surface.

        **Arguments:**

        - `u`: uniform numbers in `[0, 1)`, shape `(..., 3)`; `u[..., 2]` picks the part (face,
          cap, side, triangle) in proportion to its area, `u[..., :2]` the position within it.

        **Returns:** `(p, n)`: world points and their unit outward normals, shape `(..., 3)`.
        The density is `1 / area()` per mm^2. Sphere, cylinder and cone need a uniform scale
        (`ValueError` otherwise).
        """
        self._require_uniform_scale("sample")
        u = jnp.asarray(u)
        if not jnp.issubdtype(u.dtype, jnp.floating):
            u = u.astype(float_dtype())
        batch = u.shape[:-1]
        p, n = _sample_core(self, u.reshape(-1, 3))
        return p.reshape(*batch, 3), n.reshape(*batch, 3)

    def area(self) -> Float[Array, ""]:
        """The exact world-space surface area, mm^2 (a 0-d array).

        Sphere, cylinder and cone need a uniform scale (`ValueError` otherwise); a cube and a
        mesh are exact under any affine placement.
        """
        self._require_uniform_scale("area")
        return _area_core(self)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The tight world-space axis-aligned bounding box `(lo, hi)`, two float64 `(3,)` arrays."""
        raise NotImplementedError

    def tessellate(self, resolution: int = 32) -> tuple[np.ndarray, np.ndarray]:
        """A closed triangle mesh of the world-space surface (caps included).

        **Arguments:**

        - `resolution`: the number of segments around curved surfaces (>= 3).

        **Returns:** `(vertices, triangles)`: float64 `(V, 3)` world points and int `(F, 3)`
        indices, wound counter-clockwise seen from outside (outward right-hand normals).
        """
        resolution = int(resolution)
        if resolution < 3:
            raise ValueError(f"tessellate resolution must be >= 3, got {resolution}")
        v, tris = self._tessellate_object(resolution)
        w = np.asarray(self.to_world, dtype=np.float64)
        v = v @ w[:3, :3].T + w[:3, 3]
        if np.linalg.det(w[:3, :3]) < 0:  # a mirroring placement flips the winding
            tris = tris[:, ::-1]
        return v, np.ascontiguousarray(tris, dtype=np.int64)

    def _world(self) -> np.ndarray:
        return np.asarray(self.to_world, dtype=np.float64)


# Jitted cores (compiled once per shape type, batch size and dtype; inlined under an outer
# `jit`), so that eager calls do not dispatch hundreds of small operations one by one.
@eqx.filter_jit
def _intersect_core(shape: _Shape, o: Array, d: Array, t_min: Array, t_max: Array):
    dt = o.dtype
    a, b = shape.to_object[:3, :3].astype(dt), shape.to_object[:3, 3].astype(dt)
    oo, do = o @ a.T + b, d @ a.T
    # Solve from the point of the ray closest to the shape's centre (better conditioned for
    # distant origins); `ts` is added back to the ray parameter afterwards.
    ts, _ = _div(-_dot(oo - shape._centre().astype(dt), do), _dot(do, do))
    t_rel, n_obj = shape._hit(oo + ts[:, None] * do, do, t_min - ts, t_max - ts)
    hit = t_rel < jnp.inf
    t = jnp.where(hit, ts + jnp.where(hit, t_rel, 0.0), jnp.inf)
    n = jnp.where(hit[:, None], _normalize(n_obj @ a), 0.0)
    return t, n


@eqx.filter_jit
def _sample_core(shape: _Shape, u: Array):
    p_obj, n_obj = shape._sample_object(u)
    w = shape.to_world
    p = p_obj @ w[:3, :3].T + w[:3, 3]
    return p, _normalize(n_obj @ shape.to_object[:3, :3])


@eqx.filter_jit
def _area_core(shape: _Shape):
    return shape._area()


# --- primitives ----------------------------------------------------------------------------
class Sphere(_Shape):
    """A sphere of `radius` (mm) centred at the object-space origin.

    **Arguments:** `radius`, then `to_world`, `to_object` (`(4, 4)`, default identity; give
    either or both, e.g. from `placement`).
    """

    radius: Float[Array, ""]

    def __init__(self, radius: ArrayLike, to_world=None, to_object=None):
        self.radius = _positive("Sphere", "radius", radius)
        self.to_world, self.to_object = _matrices(to_world, to_object)

    def _hit(self, o, d, t_min, t_max):
        r2 = self.radius * self.radius
        a, bh, c = _dot(d, d), _dot(o, d), _dot(o, o) - r2
        k, _ = _div(bh, a)
        f = o - k[:, None] * d  # closest point to the centre: disc without cancellation
        disc = a * (r2 - _dot(f, f))
        cands = [(t, ok, o + t[:, None] * d) for t, ok in _roots(a, bh, c, disc)]
        return _nearest(cands, t_min, t_max)

    def _sample_object(self, u):
        z = 1.0 - 2.0 * u[:, 0]
        rxy = safe_sqrt(1.0 - z * z)
        phi = 2.0 * jnp.pi * u[:, 1]
        n = jnp.stack([rxy * jnp.cos(phi), rxy * jnp.sin(phi), z], axis=-1)
        return self.radius * n, n

    def _area(self):
        return 4.0 * jnp.pi * self.radius**2 * self._similarity_scale2()

    def bounds(self):
        w = self._world()
        half = float(self.radius) * np.linalg.norm(w[:3, :3], axis=1)
        return w[:3, 3] - half, w[:3, 3] + half

    def _tessellate_object(self, resolution):
        r = float(self.radius)
        n_phi, n_th = resolution, max(resolution // 2, 2)
        th = np.pi * np.arange(1, n_th) / n_th
        rings = [_ring(r * np.sin(a), r * np.cos(a), n_phi) for a in th]
        v = np.concatenate([[[0.0, r, 0.0]], *rings, [[0.0, -r, 0.0]]])
        idx = [1 + j * n_phi + np.arange(n_phi) for j in range(n_th - 1)]
        tris = [_fan(0, idx[0])]
        tris += [_band(idx[j], idx[j + 1]) for j in range(n_th - 2)]
        tris.append(_fan(len(v) - 1, idx[-1]))
        tris = np.concatenate(tris)
        return v, _orient_outward(v, tris, np.zeros(3))


# Cube faces in units of the half size: outward normal N and edges E1, E2 with E1 x E2 = N.
_CUBE_N = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
_CUBE_E1 = np.array([[0, 1, 0], [0, 0, 1], [0, 0, 1], [1, 0, 0], [1, 0, 0], [0, 1, 0]], float)
_CUBE_E2 = np.array([[0, 0, 1], [0, 1, 0], [1, 0, 0], [0, 0, 1], [0, 1, 0], [1, 0, 0]], float)


class Cube(_Shape):
    """The axis-aligned box `[-size/2, size/2]^3` in object space.

    **Arguments:** `size` (mm; a scalar for a cube or a 3-vector for a box), then `to_world`,
    `to_object` (`(4, 4)`, default identity).
    """

    size: Float[Array, "3"]

    def __init__(self, size: ArrayLike, to_world=None, to_object=None):
        self.size = _positive("Cube", "size", size, shape=(3,))
        self.to_world, self.to_object = _matrices(to_world, to_object)

    def _hit(self, o, d, t_min, t_max):
        h = 0.5 * self.size
        slack = 1.0 + _eps(o.dtype)
        cands = []
        for axis in range(3):
            j, k = (axis + 1) % 3, (axis + 2) % 3
            for sign in (1.0, -1.0):
                t, ok = _div(sign * h[axis] - o[:, axis], d[:, axis])
                p = o + t[:, None] * d
                ok = ok & (jnp.abs(p[:, j]) <= h[j] * slack) & (jnp.abs(p[:, k]) <= h[k] * slack)
                cands.append((t, ok, jnp.asarray(sign * np.eye(3)[axis], dtype=o.dtype)))
        return _nearest(cands, t_min, t_max)

    def _face_areas(self):
        e1, e2, nrm = (jnp.asarray(a, dtype=self.size.dtype) for a in (_CUBE_E1, _CUBE_E2, _CUBE_N))
        return (e1 @ self.size) * (e2 @ self.size) * self._face_scale(nrm)

    def _area(self):
        return jnp.sum(self._face_areas())

    def _require_uniform_scale(self, method):
        return None  # a box stays a parallelepiped under any affine map

    def _sample_object(self, u):
        f = _pick(self._face_areas(), u[:, 2])
        nrm, e1, e2 = (jnp.asarray(a, dtype=u.dtype)[f] for a in (_CUBE_N, _CUBE_E1, _CUBE_E2))
        a, b = 2.0 * u[:, :1] - 1.0, 2.0 * u[:, 1:2] - 1.0
        return 0.5 * self.size * (nrm + a * e1 + b * e2), nrm

    def _corners(self) -> np.ndarray:
        h = 0.5 * np.asarray(self.size, dtype=np.float64)
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        return signs * h

    def bounds(self):
        w = self._world()
        p = self._corners() @ w[:3, :3].T + w[:3, 3]
        return p.min(axis=0), p.max(axis=0)

    def _tessellate_object(self, resolution):
        h = 0.5 * np.asarray(self.size, dtype=np.float64)
        ab = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
        v = np.concatenate(
            [
                h * (n + ab[:, :1] * e1 + ab[:, 1:] * e2)
                for n, e1, e2 in zip(_CUBE_N, _CUBE_E1, _CUBE_E2, strict=True)
            ]
        )
        quad = np.array([[0, 1, 2], [0, 2, 3]])
        tris = np.concatenate([quad + 4 * f for f in range(6)])
        return v, _orient_outward(v, tris, np.zeros(3))


class Cylinder(_Shape):
    """A capped cylinder of `radius` around the object `+y` axis from `y = 0` to `y = height`.

    **Arguments:** `radius`, `height` (mm), then `to_world`, `to_object` (default identity).
    """

    radius: Float[Array, ""]
    height: Float[Array, ""]

    def __init__(self, radius: ArrayLike, height: ArrayLike, to_world=None, to_object=None):
        self.radius = _positive("Cylinder", "radius", radius)
        self.height = _positive("Cylinder", "height", height)
        self.to_world, self.to_object = _matrices(to_world, to_object)

    def _centre(self):
        return jnp.stack([0.0 * self.height, 0.5 * self.height, 0.0 * self.height])

    def _hit(self, o, d, t_min, t_max):
        r, hgt = self.radius, self.height
        slack = _eps(o.dtype)
        ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        a, bh, c = dx * dx + dz * dz, ox * dx + oz * dz, ox * ox + oz * oz - r * r
        k, _ = _div(bh, a)
        fx, fz = ox - k * dx, oz - k * dz
        disc = a * (r * r - fx * fx - fz * fz)
        cands = []
        for t, ok in _roots(a, bh, c, disc):
            p = o + t[:, None] * d
            ok = ok & (p[:, 1] >= -slack * hgt) & (p[:, 1] <= hgt * (1.0 + slack))
            cands.append((t, ok, p * jnp.asarray([1.0, 0.0, 1.0], dtype=o.dtype)))
        for y_cap, ny in ((0.0, -1.0), (hgt, 1.0)):
            t, ok = _div(y_cap - oy, dy)
            x, z = ox + t * dx, oz + t * dz
            ok = ok & (x * x + z * z <= r * r * (1.0 + slack))
            cands.append((t, ok, jnp.asarray([0.0, ny, 0.0], dtype=o.dtype)))
        return _nearest(cands, t_min, t_max)

    def _parts(self):
        cap = jnp.pi * self.radius**2
        return jnp.stack([cap, 2.0 * jnp.pi * self.radius * self.height, cap])

    def _area(self):
        return jnp.sum(self._parts()) * self._similarity_scale2()

    def _sample_object(self, u):
        part = _pick(self._parts(), u[:, 2])
        r, hgt = self.radius, self.height
        phi = 2.0 * jnp.pi * u[:, 1]
        cos, sin = jnp.cos(phi), jnp.sin(phi)
        zero = jnp.zeros_like(cos)
        side_p = jnp.stack([r * cos, hgt * u[:, 0], r * sin], axis=-1)
        side_n = jnp.stack([cos, zero, sin], axis=-1)
        x, z = _uniform_disc(r, u[:, 0], u[:, 1])
        y_cap = jnp.where(part == 2, hgt, 0.0 * hgt)
        cap_p = jnp.stack([x, jnp.broadcast_to(y_cap, x.shape), z], axis=-1)
        cap_n = jnp.stack([zero, jnp.where(part == 2, 1.0, -1.0).astype(u.dtype), zero], axis=-1)
        side = (part == 1)[:, None]
        return jnp.where(side, side_p, cap_p), jnp.where(side, side_n, cap_n)

    def bounds(self):
        w = self._world()
        r, hgt = float(self.radius), float(self.height)
        u, v = w[:3, 0] * r, w[:3, 2] * r
        half = np.sqrt(u * u + v * v)  # AABB half extent of an ellipse u cos + v sin
        c0, c1 = w[:3, 3], w[:3, 3] + w[:3, 1] * hgt
        return np.minimum(c0, c1) - half, np.maximum(c0, c1) + half

    def _tessellate_object(self, resolution):
        r, hgt, n = float(self.radius), float(self.height), resolution
        v = np.concatenate(
            [_ring(r, 0.0, n), _ring(r, hgt, n), [[0.0, 0.0, 0.0]], _ring(r, 0.0, n)]
            + [[[0.0, hgt, 0.0]], _ring(r, hgt, n)]
        )
        i = np.arange(n)
        tris = np.concatenate(
            [_band(i, n + i), _fan(2 * n, 2 * n + 1 + i), _fan(3 * n + 1, 3 * n + 2 + i)]
        )
        return v, _orient_outward(v, tris, np.array([0.0, 0.5 * hgt, 0.0]))


class Cone(_Shape):
    """A cone with a base disc of `radius` at `y = 0` (capped) and its apex at `(0, height, 0)`.

    **Arguments:** `radius`, `height` (mm), then `to_world`, `to_object` (default identity).
    """

    radius: Float[Array, ""]
    height: Float[Array, ""]

    def __init__(self, radius: ArrayLike, height: ArrayLike, to_world=None, to_object=None):
        self.radius = _positive("Cone", "radius", radius)
        self.height = _positive("Cone", "height", height)
        self.to_world, self.to_object = _matrices(to_world, to_object)

    def _centre(self):
        return jnp.stack([0.0 * self.height, 0.5 * self.height, 0.0 * self.height])

    def _slant(self):
        return jnp.sqrt(self.radius**2 + self.height**2)

    def _hit(self, o, d, t_min, t_max):
        r, hgt = self.radius, self.height
        k2 = (r / hgt) ** 2
        slack = _eps(o.dtype)
        ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        # Lateral surface: x^2 + z^2 = k^2 (H - y)^2 (both nappes; keep 0 <= y <= H).
        w0 = hgt - oy
        a = dx * dx + dz * dz - k2 * dy * dy
        bh = ox * dx + oz * dz + k2 * w0 * dy
        c = ox * ox + oz * oz - k2 * w0 * w0
        disc = bh * bh - a * c
        cands = []
        up = jnp.asarray([0.0, 1.0, 0.0], dtype=o.dtype)
        for t, ok in _roots(a, bh, c, disc):
            p = o + t[:, None] * d
            ok = ok & (p[:, 1] >= -slack * hgt) & (p[:, 1] <= hgt * (1.0 + slack))
            n = jnp.stack([p[:, 0], k2 * (hgt - p[:, 1]), p[:, 2]], axis=-1)
            apex = jnp.all(n == 0, axis=-1, keepdims=True)
            cands.append((t, ok, jnp.where(apex, up, n)))
        t, ok = _div(-oy, dy)
        x, z = ox + t * dx, oz + t * dz
        ok = ok & (x * x + z * z <= r * r * (1.0 + slack))
        cands.append((t, ok, -up))
        return _nearest(cands, t_min, t_max)

    def _parts(self):
        return jnp.stack([jnp.pi * self.radius**2, jnp.pi * self.radius * self._slant()])

    def _area(self):
        return jnp.sum(self._parts()) * self._similarity_scale2()

    def _sample_object(self, u):
        part = _pick(self._parts(), u[:, 2])
        r, hgt = self.radius, self.height
        phi = 2.0 * jnp.pi * u[:, 1]
        cos, sin = jnp.cos(phi), jnp.sin(phi)
        zero = jnp.zeros_like(cos)
        # Lateral area within distance s of the apex grows as s^2: s / L = sqrt(u0).
        f = safe_sqrt(u[:, 0])
        side_p = jnp.stack([r * f * cos, hgt * (1.0 - f), r * f * sin], axis=-1)
        side_n = jnp.stack([hgt * cos, jnp.broadcast_to(r, cos.shape), hgt * sin], axis=-1)
        x, z = _uniform_disc(r, u[:, 0], u[:, 1])
        base_p = jnp.stack([x, zero, z], axis=-1)
        base_n = jnp.stack([zero, zero - 1.0, zero], axis=-1)
        side = (part == 1)[:, None]
        return jnp.where(side, side_p, base_p), jnp.where(side, side_n, base_n)

    def bounds(self):
        w = self._world()
        r, hgt = float(self.radius), float(self.height)
        u, v = w[:3, 0] * r, w[:3, 2] * r
        half = np.sqrt(u * u + v * v)
        c0, apex = w[:3, 3], w[:3, 3] + w[:3, 1] * hgt
        return np.minimum(c0 - half, apex), np.maximum(c0 + half, apex)

    def _tessellate_object(self, resolution):
        r, hgt, n = float(self.radius), float(self.height), resolution
        v = np.concatenate(
            [_ring(r, 0.0, n), [[0.0, hgt, 0.0]], [[0.0, 0.0, 0.0]], _ring(r, 0.0, n)]
        )
        i = np.arange(n)
        tris = np.concatenate([_fan(n, i), _fan(n + 1, n + 2 + i)])
        return v, _orient_outward(v, tris, np.array([0.0, 0.25 * hgt, 0.0]))


def _triangulate(faces, n_vertices: int) -> np.ndarray:
    """Fan-triangulate polygons (quads `(0,1,2),(0,2,3)`); 0-based indices, checked."""
    if isinstance(faces, np.ndarray | jax.Array) and np.ndim(faces) == 2:
        f = np.asarray(faces)
        if f.shape[1] < 3:
            raise ValueError(f"QuadMesh faces need at least 3 vertices each, got shape {f.shape}")
        tris = np.concatenate(
            [np.stack([f[:, 0], f[:, k], f[:, k + 1]], -1) for k in range(1, f.shape[1] - 1)]
        )
        # keep the triangles of one polygon together
        tris = tris.reshape(f.shape[1] - 2, len(f), 3).transpose(1, 0, 2).reshape(-1, 3)
    else:
        rows = []
        for i, face in enumerate(faces):
            face = [int(x) for x in np.asarray(face).ravel()]
            if len(face) < 3:
                raise ValueError(f"QuadMesh face {i} has {len(face)} vertices; need 3 or more")
            rows += [(face[0], face[k], face[k + 1]) for k in range(1, len(face) - 1)]
        tris = np.asarray(rows, dtype=np.int64).reshape(-1, 3)
    if len(tris) == 0:
        raise ValueError("QuadMesh needs at least one face")
    if not np.issubdtype(tris.dtype, np.integer):
        if not np.all(tris == np.round(tris)):
            raise ValueError("QuadMesh face indices must be integers")
    tris = tris.astype(np.int64)
    bad = (tris < 0) | (tris >= n_vertices)
    if np.any(bad):
        raise ValueError(
            f"QuadMesh face index {int(tris[bad][0])} out of range for {n_vertices} vertices "
            "(indices are 0-based)"
        )
    return tris.astype(np.int32)


_MESH_CHUNK = 128


class QuadMesh(_Shape):
    """A polygon mesh (quads and/or triangles), stored as triangles, intersected two-sided.

    **Arguments:**

    - `vertices`: `(V, 3)` object-space points, mm.
    - `faces`: a sequence of 0-based index lists (3 or 4 entries; larger convex polygons are
      fan-triangulated) or an `(F, 3)` / `(F, 4)` int array; a quad `(a, b, c, d)` becomes the
      triangles `(a, b, c)` and `(a, c, d)`. Wind faces counter-clockwise seen from outside.
    - `to_world`, `to_object`: `(4, 4)` placement, default identity.

    The normal of a hit or a sample is the geometric normal of its triangle by the right-hand
    rule, i.e. outward for a closed mesh with consistent counter-clockwise winding.
    """

    vertices: Float[Array, "V 3"]
    triangles: Int[Array, "F 3"]

    def __init__(self, vertices: ArrayLike, faces, to_world=None, to_object=None):
        if _is_concrete(vertices):
            v = np.asarray(vertices, dtype=np.float64)
            if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
                raise ValueError(f"QuadMesh.vertices must have shape (V >= 3, 3), got {v.shape}")
            if not np.all(np.isfinite(v)):
                raise ValueError("QuadMesh.vertices must be finite")
            self.vertices = jnp.asarray(v, dtype=float_dtype())
        else:
            self.vertices = vertices
        self.triangles = jnp.asarray(_triangulate(faces, self.vertices.shape[0]))
        self.to_world, self.to_object = _matrices(to_world, to_object)

    def _corners(self, vertices=None):
        v = self.vertices if vertices is None else vertices
        tri = v[self.triangles]
        return tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]

    def _centre(self):
        return jnp.mean(self.vertices, axis=0)

    def _hit(self, o, d, t_min, t_max):
        dt = o.dtype
        v0, e1, e2 = (x.astype(dt) for x in self._corners())
        n_tri = v0.shape[0]
        chunk = min(n_tri, _MESH_CHUNK)
        n_chunks = -(-n_tri // chunk)
        pad = n_chunks * chunk - n_tri  # degenerate (all-zero) triangles never hit

        def blocks(x):
            x = jnp.concatenate([x, jnp.zeros((pad, 3), dtype=dt)])
            return x.reshape(n_chunks, chunk, 3)

        slack, rel = _eps(dt), 2.0 * _eps(dt)
        d_len = safe_sqrt(_dot(d, d))[:, None]

        def step(carry, xs):
            t_best, k_best = carry
            v0, e1, e2, first = xs
            pvec = jnp.cross(d[:, None, :], e2[None])
            det = _dot(e1[None], pvec)
            scale = d_len * safe_sqrt(_dot(e1, e1) * _dot(e2, e2))[None]
            ok = jnp.abs(det) > jnp.maximum(rel * scale, _tiny(dt))
            inv = safe_div(1.0, jnp.where(ok, det, 0.0))
            s = o[:, None, :] - v0[None]
            bu = _dot(s, pvec) * inv
            qvec = jnp.cross(s, e1[None])
            bv = _dot(d[:, None, :], qvec) * inv
            t = _dot(e2[None], qvec) * inv
            ok = ok & (bu >= -slack) & (bv >= -slack) & (bu + bv <= 1.0 + slack)
            ok = ok & (t > t_min[:, None]) & (t < t_max[:, None])
            t = jnp.where(ok, t, jnp.inf)
            j = jnp.argmin(t, axis=1)
            tj = jnp.take_along_axis(t, j[:, None], axis=1)[:, 0]
            better = tj < t_best
            return (
                jnp.where(better, tj, t_best),
                jnp.where(better, first + j.astype(jnp.int32), k_best),
            ), None

        firsts = jnp.arange(n_chunks, dtype=jnp.int32) * chunk
        init = (jnp.full(o.shape[:1], jnp.inf, dtype=dt), jnp.zeros(o.shape[:1], jnp.int32))
        (t, k), _ = jax.lax.scan(step, init, (blocks(v0), blocks(e1), blocks(e2), firsts))
        n = jnp.cross(e1, e2)[k]
        return t, n

    def _world_vertices(self):
        w = self.to_world
        return self.vertices @ w[:3, :3].T + w[:3, 3]

    def _triangle_areas(self):
        _, e1, e2 = self._corners(self._world_vertices())
        c = jnp.cross(e1, e2)
        return 0.5 * jnp.sqrt(_dot(c, c))

    def _area(self):
        return jnp.sum(self._triangle_areas())

    def _require_uniform_scale(self, method):
        return None  # exact under any affine placement

    def _sample_object(self, u):
        f = _pick(self._triangle_areas(), u[:, 2])
        v0, e1, e2 = (x.astype(u.dtype)[f] for x in self._corners())
        s = safe_sqrt(u[:, :1])
        p = v0 + s * (1.0 - u[:, 1:2]) * e1 + s * u[:, 1:2] * e2
        return p, jnp.cross(e1, e2)

    def bounds(self):
        w = self._world()
        p = np.asarray(self.vertices, dtype=np.float64) @ w[:3, :3].T + w[:3, 3]
        return p.min(axis=0), p.max(axis=0)

    def _tessellate_object(self, resolution):
        return np.asarray(self.vertices, dtype=np.float64), np.asarray(self.triangles)


# --- OBJ files ------------------------------------------------------------------------------
def load_obj(path: str | os.PathLike) -> tuple[np.ndarray, list[list[int]]]:
    """Read the vertices and polygons of a Wavefront OBJ file.

    Only `v` and `f` lines are used (other statements and `#` comments are skipped). Face
    entries may be `i`, `i/t`, `i/t/n` or `i//n`; indices are 1-based, negative ones count
    back from the last vertex defined so far.

    **Arguments:** `path` to the `.obj` file.

    **Returns:** `(vertices, faces)`: a float64 `(V, 3)` array and a list of 0-based index
    lists (one per polygon), ready for `QuadMesh(vertices, faces)`. A malformed line or an
    index out of range raises `ValueError("path:line: ...")`; a missing file
    `FileNotFoundError`.
    """
    path = os.fspath(path)
    try:
        fh = open(path, encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise FileNotFoundError(f"OBJ file not found: {path}") from None
    vertices: list[list[float]] = []
    faces: list[list[int]] = []
    forward: list[tuple[int, int]] = []  # (line, 1-based index) checked once all v are read
    with fh:
        for line_no, raw in enumerate(fh, start=1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            tok = line.split()
            where = f"{path}:{line_no}"
            if tok[0] == "v":
                if len(tok) not in (4, 5):
                    raise ValueError(f"{where}: a vertex needs 'v x y z [w]', got {line!r}")
                try:
                    xyz = [float(x) for x in tok[1:]]
                except ValueError:
                    raise ValueError(f"{where}: bad vertex coordinate in {line!r}") from None
                if not all(math.isfinite(x) for x in xyz):
                    raise ValueError(f"{where}: non-finite vertex coordinate in {line!r}")
                vertices.append(xyz[:3])
            elif tok[0] == "f":
                if len(tok) < 4:
                    raise ValueError(f"{where}: a face needs at least 3 vertices, got {line!r}")
                face = []
                for item in tok[1:]:
                    parts = item.split("/")
                    try:
                        if len(parts) > 3 or any(p and int(p) == 0 for p in parts[1:]):
                            raise ValueError
                        i = int(parts[0])
                    except ValueError:
                        raise ValueError(f"{where}: bad face vertex {item!r} in {line!r}") from None
                    if i == 0:
                        raise ValueError(f"{where}: face index 0 is invalid (OBJ is 1-based)")
                    if i < 0:
                        j = len(vertices) + i
                        if j < 0:
                            raise ValueError(
                                f"{where}: face index {i} out of range "
                                f"({len(vertices)} vertices defined so far)"
                            )
                    else:
                        j = i - 1
                        forward.append((line_no, i))
                    face.append(j)
                faces.append(face)
    for line_no, i in forward:
        if i > len(vertices):
            raise ValueError(
                f"{path}:{line_no}: face index {i} out of range (the file has "
                f"{len(vertices)} vertices)"
            )
    if not faces:
        raise ValueError(f"{path}: no faces ('f' lines) found")
    return np.asarray(vertices, dtype=np.float64).reshape(-1, 3), faces


# --- construction from a scene description and scene queries --------------------------------
SHAPE_KINDS: dict[str, tuple[type, tuple[str, ...]]] = {
    "sphere": (Sphere, ("radius",)),
    "cube": (Cube, ("size",)),
    "cylinder": (Cylinder, ("radius", "height")),
    "cone": (Cone, ("radius", "height")),
    "quadmesh": (QuadMesh, ("vertices", "faces")),
}


def make_shape(
    kind: str,
    params: Mapping,
    translate: ArrayLike = (0.0, 0.0, 0.0),
    rotate: ArrayLike = (0.0, 0.0, 0.0),
    scale: ArrayLike = 1.0,
):
    """Build a placed primitive from a scene description.

    **Arguments:**

    - `kind`: one of `"sphere"`, `"cube"`, `"cylinder"`, `"cone"`, `"quadmesh"`
      (case-insensitive).
    - `params`: the object-space parameters: `radius` (sphere); `size` (cube); `radius`,
      `height` (cylinder, cone); `vertices`, `faces` (quadmesh; or instead `path` to an OBJ).
    - `translate`, `rotate`, `scale`: the placement, as in `placement`.

    **Returns:** the shape. Unknown kinds, missing or unexpected parameters raise `ValueError`.
    """
    key = str(kind).strip().lower()
    if key not in SHAPE_KINDS:
        raise ValueError(f"unknown shape kind {kind!r}; expected one of {sorted(SHAPE_KINDS)}")
    cls, names = SHAPE_KINDS[key]
    params = dict(params or {})
    if key == "quadmesh" and "path" in params:
        if "vertices" in params or "faces" in params:
            raise ValueError("quadmesh takes either 'path' or 'vertices' and 'faces', not both")
        params["vertices"], params["faces"] = load_obj(params.pop("path"))
    missing = [n for n in names if n not in params]
    unknown = sorted(set(params) - set(names))
    if missing or unknown:
        raise ValueError(
            f"{key} takes parameters {list(names)}"
            + (f"; missing {missing}" if missing else "")
            + (f"; unexpected {unknown}" if unknown else "")
        )
    to_world, to_object = placement(translate, rotate, scale)
    return cls(*(params[n] for n in names), to_world=to_world, to_object=to_object)


def intersect_all(
    shapes: Sequence,
    o: ArrayLike,
    d: ArrayLike,
    t_min: ArrayLike = 1e-4,
    t_max: ArrayLike = jnp.inf,
) -> tuple[Float[Array, "*n"], Float[Array, "*n 3"], Int[Array, "*n"]]:
    """The nearest hit of the rays `o + t d` among several shapes.

    **Arguments:** `shapes`, a list of shapes (the Python loop unrolls under `jit`); `o`, `d`,
    `t_min`, `t_max` as in `Sphere.intersect`.

    **Returns:** `(t, n, shape_index)`: the nearest ray parameter (`inf` on a miss), the unit
    outward normal (0 on a miss) and the index of the shape hit (`-1` on a miss, int32).
    """
    o, d = jnp.asarray(o), jnp.asarray(d)
    batch = jnp.broadcast_shapes(o.shape, d.shape)[:-1]
    dt = jnp.promote_types(jnp.promote_types(o.dtype, d.dtype), float_dtype())
    t_best = jnp.full(batch, jnp.inf, dtype=dt)
    n_best = jnp.zeros((*batch, 3), dtype=dt)
    index = jnp.full(batch, -1, dtype=jnp.int32)
    for i, shape in enumerate(shapes):
        t, n = shape.intersect(o, d, t_min, t_max)
        closer = t < t_best
        t_best = jnp.where(closer, t, t_best)
        n_best = jnp.where(closer[..., None], n, n_best)
        index = jnp.where(closer, i, index)
    return t_best, n_best, index
