"""What the volumetric transport needs of a scene, as arrays: shapes, surface kinds, the
translucent objects' boundary geometry for refracted next-event estimation, and the lights.

Built once per scene (host side, NumPy); an immutable `eqx.Module`, so it is an argument of
the compiled walk: a different refractive index or light emission is a new pytree, not a
recompile. Lengths in mm.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..lights import LightArrays
from ..shapes import Cone, Cube, Cylinder, QuadMesh, Sphere
from ._connect import FACE_DISC, FACE_PARALLELOGRAM, FACE_TRIANGLE

__all__ = ["VolScene", "DIFFUSE", "MIRROR", "TRANSLUCENT", "MAX_NEE_FACES"]

DIFFUSE, MIRROR, TRANSLUCENT = 0, 1, 2
# meshes with more triangles than this get no refracted next-event estimation (their
# interior is lit through random exits only)
MAX_NEE_FACES = 48


def _cube_faces(shape: Cube):
    w = np.asarray(shape.to_world, np.float64)
    m, t = w[:3, :3], w[:3, 3]
    h = 0.5 * np.asarray(shape.size, np.float64)
    out = []
    for axis in range(3):
        j, k = (axis + 1) % 3, (axis + 2) % 3
        for sign in (1.0, -1.0):
            c = np.zeros(3)
            c[axis] = sign * h[axis]
            e1 = np.zeros(3)
            e1[j] = h[j]
            e2 = np.zeros(3)
            e2[k] = h[k]
            cw, e1w, e2w = m @ c + t, m @ e1, m @ e2
            n = np.cross(e1w, e2w)
            n /= np.linalg.norm(n)
            if np.dot(n, cw - t) < 0:
                n = -n
            out.append((cw, n, e1w, e2w, FACE_PARALLELOGRAM))
    return out


def _disc(w: np.ndarray, y: float, radius: float, up: bool):
    m, t = w[:3, :3], w[:3, 3]
    c = m @ np.array([0.0, y, 0.0]) + t
    e1, e2 = m @ np.array([radius, 0.0, 0.0]), m @ np.array([0.0, 0.0, radius])
    n = np.cross(e1, e2)
    n /= np.linalg.norm(n)
    axis = m @ np.array([0.0, 1.0, 0.0])
    if (np.dot(n, axis) > 0) != up:
        n = -n
    return (c, n, e1, e2, FACE_DISC)


def _mesh_faces(shape: QuadMesh):
    w = np.asarray(shape.to_world, np.float64)
    v = np.asarray(shape.vertices, np.float64) @ w[:3, :3].T + w[:3, 3]
    tri = np.asarray(shape.triangles)
    flip = np.linalg.det(w[:3, :3]) < 0
    out = []
    for a, b, c in tri:
        e1, e2 = v[b] - v[a], v[c] - v[a]
        n = np.cross(e1, e2)
        nn = np.linalg.norm(n)
        if nn == 0:
            continue
        n = (-n if flip else n) / nn
        out.append((v[a], n, e1, e2, FACE_TRIANGLE))
    return out


def _boundary(shape):
    """`(planar faces, sphere (centre, radius) or None, every boundary point covered by
    refracted next-event estimation, convex)` of a translucent shape."""
    if isinstance(shape, Sphere):
        w = np.asarray(shape.to_world, np.float64)
        r = float(shape.radius) * float(np.sqrt(np.mean(np.sum(w[:3, :3] ** 2, axis=0))))
        return [], (w[:3, 3], r), True, True
    if isinstance(shape, Cube):
        return _cube_faces(shape), None, True, True
    w = np.asarray(shape.to_world, np.float64)
    if isinstance(shape, Cylinder):
        r, h = float(shape.radius), float(shape.height)
        return [_disc(w, 0.0, r, False), _disc(w, h, r, True)], None, False, True
    if isinstance(shape, Cone):
        return [_disc(w, 0.0, float(shape.radius), False)], None, False, True
    if isinstance(shape, QuadMesh):
        faces = _mesh_faces(shape)
        if len(faces) > MAX_NEE_FACES:
            return [], None, False, False
        return faces, None, True, False
    raise TypeError(f"no boundary description for {type(shape).__name__}")


class VolScene(eqx.Module):
    """Scene arrays of the volumetric transport (`S` shapes, `F` planar faces per shape at
    most, `Mt` translucent materials).

    **Fields:** `kind (S,)` (`DIFFUSE`, `MIRROR`, `TRANSLUCENT`), `albedo`, `reflectance`
    `(S, 3)`, `eta (S,)` (relative index; 1 for opaque shapes), `mat (S,)` (translucent
    material index or -1); the boundary for refracted next-event estimation: planar faces
    `face_c, face_n, face_e1, face_e2 (S, F, 3)`, `face_kind`, `face_ok (S, F)`, spheres
    `is_sphere (S,)`, `sphere_c (S, 3)`, `sphere_r (S,)`, `covered_all (S,)` (every
    boundary point is reached by the estimator), `convex (S,)`; `lights` (`LightArrays`),
    `light_cdf` (next-event light selection, by power, over area, point and beam lights in
    that order), `env (3,)` (radiance of rays that escape: background plus environment).
    """

    shapes: tuple
    kind: Int[Array, " S"]
    albedo: Float[Array, "S 3"]
    reflectance: Float[Array, "S 3"]
    eta: Float[Array, " S"]
    mat: Int[Array, " S"]
    face_c: Float[Array, "S F 3"]
    face_n: Float[Array, "S F 3"]
    face_e1: Float[Array, "S F 3"]
    face_e2: Float[Array, "S F 3"]
    face_kind: Int[Array, "S F"]
    face_ok: Bool[Array, "S F"]
    is_sphere: Bool[Array, " S"]
    sphere_c: Float[Array, "S 3"]
    sphere_r: Float[Array, " S"]
    covered_all: Bool[Array, " S"]
    convex: Bool[Array, " S"]
    lights: LightArrays
    light_cdf: Float[Array, " L"]
    env: Float[Array, " 3"]
    n_materials: int = eqx.field(static=True)
    uncovered: tuple = eqx.field(static=True)  # names of shapes without refracted NEE
    has_sphere: bool = eqx.field(static=True)  # a translucent sphere: its connections are solved
    all_convex: bool = eqx.field(static=True)  # every translucent shape is convex
    single: int | None = eqx.field(static=True)  # the index of the only translucent shape

    @classmethod
    def build(cls, scene) -> VolScene:
        """From a `Scene` (its eta, media and lights as written)."""
        from .._arrays import SceneArrays

        return cls.from_arrays(SceneArrays.from_scene(scene))

    @classmethod
    def from_arrays(cls, arrays) -> VolScene:
        """From `SceneArrays`: the geometry (static: the boundary of every translucent
        shape for refracted next-event estimation, on the host) and the arrays a fit
        changes (`eta`, the lights with their gains), which may be traced values."""
        shapes = arrays.shapes
        S = len(shapes)
        kind = np.array([int(k) for k in arrays.kind], np.int32)
        mat = np.full(S, -1, np.int32)
        mat[list(arrays.tobj_shape)] = arrays.tobj_mat
        bounds = []
        uncovered = []
        for i, shp in enumerate(shapes):
            if mat[i] >= 0:
                b = _boundary(shp)
                if not b[2]:
                    uncovered.append(f"shape {i} ({type(shp).__name__.lower()})")
            else:
                b = ([], None, False, True)
            bounds.append(b)
        F = max([len(b[0]) for b in bounds] + [1])
        fc, fn, f1, f2 = (np.zeros((S, F, 3)) for _ in range(4))
        fk = np.zeros((S, F), np.int32)
        fok = np.zeros((S, F), bool)
        sph = np.zeros(S, bool)
        sc = np.zeros((S, 3))
        sr = np.ones(S)
        cov = np.zeros(S, bool)
        cvx = np.ones(S, bool)
        for i, (faces, sphere, covered, convex) in enumerate(bounds):
            for j, (c, n, e1, e2, k) in enumerate(faces):
                fc[i, j], fn[i, j], f1[i, j], f2[i, j], fk[i, j], fok[i, j] = c, n, e1, e2, k, True
            if sphere is not None:
                sph[i], sc[i], sr[i] = True, sphere[0], sphere[1]
            cov[i], cvx[i] = covered, convex
        la = arrays.lights
        f = jnp.asarray
        return cls(
            shapes=tuple(shapes),
            kind=f(kind),
            albedo=arrays.albedo,
            reflectance=arrays.reflectance,
            eta=arrays.eta,
            mat=f(mat),
            face_c=f(fc, dtype=float),
            face_n=f(fn, dtype=float),
            face_e1=f(f1, dtype=float),
            face_e2=f(f2, dtype=float),
            face_kind=f(fk),
            face_ok=f(fok),
            is_sphere=f(sph),
            sphere_c=f(sc, dtype=float),
            sphere_r=f(sr, dtype=float),
            covered_all=f(cov),
            convex=f(cvx),
            lights=la,
            light_cdf=light_cdf(la),
            env=jnp.asarray(arrays.render.background, dtype=float) + la.environment,
            n_materials=len(arrays.materials),
            uncovered=tuple(uncovered),
            has_sphere=bool(sph.any()),
            all_convex=bool(np.all(cvx[mat >= 0])),
            single=int(np.flatnonzero(mat >= 0)[0]) if np.sum(mat >= 0) == 1 else None,
        )

    def with_arrays(self, arrays) -> VolScene:
        """The same geometry with `arrays`' refractive indices and lights (traced values
        welcome: nothing static changes)."""
        la = arrays.lights
        return eqx.tree_at(
            lambda v: (v.eta, v.lights, v.light_cdf, v.env, v.albedo, v.reflectance),
            self,
            (
                arrays.eta,
                la,
                light_cdf(la),
                jnp.asarray(arrays.render.background, dtype=float) + la.environment,
                arrays.albedo,
                arrays.reflectance,
            ),
        )


def light_cdf(la: LightArrays):
    """Cumulative probabilities of choosing each light for next-event estimation, in
    proportion to its power (area, point, beam lights in that order; all 0 when dark)."""
    power = jnp.concatenate(
        [
            jnp.pi * la.area * jnp.mean(la.radiance, axis=-1),
            4.0 * jnp.pi * jnp.mean(la.intensity, axis=-1),
            jnp.mean(la.beam_power, axis=-1),
        ]
    )
    power = jnp.maximum(power, 0.0)
    total = jnp.sum(power)
    return jnp.where(total > 0, jnp.cumsum(power) / jnp.where(total > 0, total, 1.0), 0.0)
