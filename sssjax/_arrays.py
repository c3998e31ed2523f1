"""A scene compiled to arrays: `SceneArrays`, the argument of every transport function.

Built once from a `Scene`. What may change without recompiling a transport is an array
field (the materials' albedo and reflectance, each shape's refractive index `eta`, the lights
and each light's emission `gain`, the media the trace samples with); what fixes the compiled
program is static: the geometry (the shapes, their areas and sizes: compile-time constants,
which XLA folds into the intersection code, rendering 6% faster than with the shapes as
arguments, measured on `benchmarks/render.py`), the material kinds, which shapes are
translucent objects of which material, the light kinds, the camera and the render and SSS
settings. `with_eta` / `with_gain` return new arrays: a fit of `eta` or of a light's
intensity re-traces with the same compiled functions. Lengths in mm.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .lights import LightArrays
from .media import Medium
from .scene import Camera, RenderSettings, Scene, SSSSettings
from .shapes import intersect_all
from .transport._record import NO_RECORD, Recorder

__all__ = ["MaterialKind", "SceneArrays", "EPS"]

EPS = 1e-3  # mm: ray offset off surfaces


class _ByIdentity:
    """A value carried in a static pytree field, compared and hashed by identity (the
    shapes: arrays, unhashable by value, that stay one object for a scene's arrays)."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value

    def __hash__(self) -> int:
        return id(self.value)

    def __eq__(self, other) -> bool:
        return isinstance(other, _ByIdentity) and other.value is self.value


class MaterialKind(enum.IntEnum):
    """What a shape's material does to light (`[materials.NAME] type`)."""

    DIFFUSE = 0
    MIRROR = 1
    TRANSLUCENT = 2


class SceneArrays(eqx.Module):
    """A scene as arrays (see the module docstring). `S` shapes, `No` translucent objects
    (shapes of a translucent material), `Mt` translucent materials, `L` lights."""

    albedo: Float[Array, "S 3"]  # diffuse shapes
    reflectance: Float[Array, "S 3"]  # mirrors
    eta: Float[Array, " S"]  # refractive index per shape (1 where not translucent)
    light_base: LightArrays  # the scene's lights, emission as written
    gain: Float[Array, " L"]  # per-light emission factor (scene order)
    media: tuple  # the scene's `Medium` per translucent material: the trace's proposal
    geometry: _ByIdentity = eqx.field(static=True)  # the shapes (`sssjax.shapes` pytrees)
    kind: tuple = eqx.field(static=True)  # `MaterialKind` per shape
    materials: tuple = eqx.field(static=True)  # translucent material names (shading order)
    tobj_shape: tuple = eqx.field(static=True)  # shape index of each translucent object
    tobj_mat: tuple = eqx.field(static=True)  # material index of each translucent object
    tobj_area: tuple = eqx.field(static=True)  # surface area of each object, mm^2
    tobj_diag: float = eqx.field(static=True)  # largest bounding-box diagonal of the objects
    light_kinds: tuple = eqx.field(static=True)  # `"area"` / `"point"` / `"beam"` per light
    camera: Camera = eqx.field(static=True)
    render: RenderSettings = eqx.field(static=True)
    sss: SSSSettings = eqx.field(static=True)

    @classmethod
    def from_scene(cls, scene: Scene) -> SceneArrays:
        """The arrays of `scene` (its media, eta and lights as written)."""
        mats = scene.materials
        kind = tuple(MaterialKind[mats[s.material].type.upper()] for s in scene.shapes)
        names = tuple(scene.translucent_materials)
        tobj = tuple(i for i, k in enumerate(kind) if k == MaterialKind.TRANSLUCENT)
        shapes = [s.shape for s in scene.shapes]

        def rgb(attr):
            rows = [getattr(mats[s.material], attr) for s in scene.shapes]
            return jnp.asarray(np.asarray(rows, np.float64).reshape(-1, 3), dtype=float)

        eta = np.ones(len(shapes))
        for i in tobj:
            eta[i] = float(mats[scene.shapes[i].material].medium.eta)
        diag = max(
            (float(np.linalg.norm(np.subtract(*shapes[i].bounds()[::-1]))) for i in tobj),
            default=1.0,
        )
        return cls(
            albedo=rgb("albedo"),
            reflectance=rgb("reflectance"),
            eta=jnp.asarray(eta, dtype=float),
            light_base=LightArrays.from_scene(scene.lights),
            gain=jnp.ones(len(scene.lights)),
            media=tuple(mats[n].medium for n in names),
            geometry=_ByIdentity(tuple(shapes)),
            kind=kind,
            materials=names,
            tobj_shape=tobj,
            tobj_mat=tuple(names.index(scene.shapes[i].material) for i in tobj),
            tobj_area=tuple(float(shapes[i].area()) for i in tobj),
            tobj_diag=diag,
            light_kinds=tuple(lt.kind for lt in scene.lights),
            camera=scene.camera,
            render=scene.render,
            sss=scene.sss,
        )

    # -- new arrays ------------------------------------------------------------------------
    def with_eta(self, etas: Mapping[str, float] | Sequence | Array | None) -> SceneArrays:
        """The arrays with translucent materials' refractive indices replaced: `etas` by
        material name (the others keep theirs), or one per shape; `None` changes nothing.
        Works on traced values too."""
        if etas is None:
            return self
        if isinstance(etas, Mapping):
            unknown = set(etas) - set(self.materials)
            if unknown:
                raise ValueError(f"no translucent material named {sorted(unknown)}")
            eta = self.eta
            for i, m in zip(self.tobj_shape, self.tobj_mat, strict=True):
                name = self.materials[m]
                if name in etas:
                    eta = eta.at[i].set(jnp.asarray(etas[name], dtype=eta.dtype))
        else:
            eta = jnp.asarray(etas, dtype=self.eta.dtype).reshape(self.eta.shape)
        return eqx.tree_at(lambda a: a.eta, self, eta)

    def with_gain(self, gain: Sequence | Array | None) -> SceneArrays:
        """The arrays with each light's emission times `gain` (one factor per light, scene
        order; `None`: all 1)."""
        g = jnp.ones(len(self.light_kinds)) if gain is None else gain
        g = jnp.asarray(g, dtype=self.gain.dtype).reshape(self.gain.shape)
        return eqx.tree_at(lambda a: a.gain, self, g)

    def with_media(self, media: Mapping[str, Medium] | Sequence[Medium]) -> SceneArrays:
        """The arrays with the media a trace samples with replaced (by material name, or one
        per translucent material in order; their `eta` is not geometry here: `with_eta`)."""
        if isinstance(media, Mapping):
            unknown = set(media) - set(self.materials)
            if unknown:
                raise ValueError(f"no translucent material named {sorted(unknown)}")
            media = [media.get(n, m) for n, m in zip(self.materials, self.media, strict=True)]
        media = tuple(media)
        if len(media) != len(self.materials):
            raise ValueError(f"expected {len(self.materials)} media, got {len(media)}")
        return eqx.tree_at(lambda a: a.media, self, media)

    # -- derived ---------------------------------------------------------------------------
    @property
    def shapes(self) -> tuple:
        """The shapes' geometry (`sssjax.shapes` pytrees), in scene order."""
        return self.geometry.value

    @property
    def lights(self) -> LightArrays:
        """The lights with each one's emission times its `gain`."""
        return self.light_base.scaled(self.gain, self.light_kinds)

    @property
    def n_objects(self) -> int:
        return len(self.tobj_shape)

    @property
    def has_diffuse(self) -> bool:
        return MaterialKind.DIFFUSE in self.kind

    def object_eta(self) -> Float[Array, " No"]:
        """Refractive index of each translucent object."""
        return self.eta[jnp.asarray(self.tobj_shape, dtype=jnp.int32)]

    def object_sigma_t(self) -> Float[Array, " No"]:
        """Mean extinction (over RGB) of each object's medium, mm^-1."""
        st = [jnp.mean(self.media[m].sigma_t) for m in self.tobj_mat]
        return jnp.stack(st) if st else jnp.ones(1)

    # -- geometric queries -----------------------------------------------------------------
    def intersect(self, o, d, t_max=jnp.inf):
        """Nearest shape hit `(t, n, shape_index)` over any batch shape (`-1`: a miss)."""
        o, d = jnp.broadcast_arrays(o, d)
        shp = o.shape[:-1]
        t, n, sid = intersect_all(
            self.shapes, o.reshape(-1, 3), d.reshape(-1, 3), EPS * 0.1, jnp.inf
        )
        t = jnp.where(t < t_max if np.ndim(t_max) == 0 else t < jnp.reshape(t_max, -1), t, jnp.inf)
        sid = jnp.where(jnp.isfinite(t), sid, -1)
        return t.reshape(shp), n.reshape(*shp, 3), sid.reshape(shp)

    def occluded(self, o, d, t_max, rec: Recorder = NO_RECORD):
        """Shadow ray: is there any shape between `o` and `o + t_max d`?"""
        t, _, _ = self.intersect(o, d)
        rec.shadow(o, d, t, t_max)
        return t < t_max

    def intersect_object(self, j_obj, o, d):
        """Hit `(t, n)` of the rays with translucent object `j_obj` (per ray), from inside or
        outside."""
        o, d = jnp.broadcast_arrays(o, d)
        shp = o.shape[:-1]
        o2, d2 = o.reshape(-1, 3), d.reshape(-1, 3)
        j2 = jnp.broadcast_to(j_obj, shp).reshape(-1)
        t = jnp.full(o2.shape[0], jnp.inf)
        n = jnp.zeros_like(o2)
        for j, i in enumerate(self.tobj_shape):
            tj, nj = self.shapes[i].intersect(o2, d2, EPS * 0.1, jnp.inf)
            sel = j2 == j
            t = jnp.where(sel, tj, t)
            n = jnp.where(sel[:, None], nj, n)
        return t.reshape(shp), n.reshape(*shp, 3)
