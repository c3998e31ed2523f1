"""Scenes: loading from TOML or a plain dict, with validation that names file, table and field.

A scene file has the tables `[camera]`, `[render]`, `[sss]`, `[[lights]]`, `[materials.NAME]`
and `[[shapes]]`. Lengths are in **mm**, scattering coefficients in **mm^-1**, colours are
linear RGB (a single number is broadcast to grey). See `scenes/*.toml` for examples and
`docs/scene_format.md` for every field.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import jax
import numpy as np

from ._registry import did_you_mean
from .media import Medium, preset, preset_names
from .profiles import check_profile
from .transport import STRATEGIES, TRANSPORTS

__all__ = [
    "SceneError",
    "SceneWarning",
    "Camera",
    "AreaLight",
    "PointLight",
    "BeamLight",
    "Material",
    "ShapeSpec",
    "RenderSettings",
    "SSSSettings",
    "Scene",
    "load_scene",
    "dump_scene",
    "scene_dict",
]


class SceneError(ValueError):
    """A problem in a scene description, reported as `FILE: [table] field: message`."""


class SceneWarning(UserWarning):
    """A scene that loads but is probably not what was meant (no lights)."""


def _emission(light) -> np.ndarray:
    for f in ("radiance", "intensity", "power"):
        if hasattr(light, f):
            return np.asarray(getattr(light, f))
    return np.ones(3)


def read_toml(path: Path, error: type[Exception], what: str) -> dict:
    """Parse a TOML file; a missing, binary or malformed file raises `error` in one line."""
    if not path.exists():
        raise error(f"{path}: {what} not found")
    if path.is_dir():
        raise error(f"{path}: is a folder, not a {what}")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise error(f"{path}: not valid TOML: {e}") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not a text file") from None
    except OSError as e:
        raise error(f"{path}: cannot read the {what}: {e.strerror or e}") from None


# --- the parsed scene ------------------------------------------------------------------
def _value_key(v: Any) -> Any:
    """A hashable stand-in for `v` that is equal exactly when the values are: arrays by
    dtype, shape and bytes, pytrees (shapes, media) by structure and leaves, dataclasses by
    their compared fields."""
    if isinstance(v, np.ndarray | jax.Array | np.generic):
        a = np.asarray(v)
        return ("array", a.dtype.str, a.shape, a.tobytes())
    if isinstance(v, _Value):
        fs = dataclasses.fields(v)
        return (type(v).__name__, *(_value_key(getattr(v, f.name)) for f in fs if f.compare))
    if isinstance(v, Mapping):
        return ("map", *((k, _value_key(x)) for k, x in v.items()))
    if isinstance(v, list | tuple):
        return ("seq", *(_value_key(x) for x in v))
    if isinstance(v, int | float | str | bool | type(None)):
        return v
    leaves, treedef = jax.tree_util.tree_flatten(v)  # an eqx.Module (shape, medium)
    return ("tree", type(v).__name__, treedef, *(_value_key(x) for x in leaves))


class _Value:
    """Equality and hashing by value (arrays element-wise), for the frozen scene records:
    `load_scene(dump_scene(scene)) == scene`, and a scene's camera and settings can be
    static parts of a jitted function's arguments."""

    def __eq__(self, other) -> bool:
        return type(self) is type(other) and _value_key(self) == _value_key(other)

    def __hash__(self) -> int:
        return hash(_value_key(self))


@dataclass(frozen=True, eq=False)
class Camera(_Value):
    """A pinhole or orthographic camera; positions in mm.

    `projection = "pinhole"`: `fov` is the vertical field of view in degrees.
    `projection = "orthographic"`: parallel rays along `target - origin`; `view_width` is the
    horizontal extent of the image on the plane through `origin`, in mm (pixels are square,
    `view_width / width` mm on a side), as for a telecentric measurement camera.
    """

    origin: np.ndarray
    target: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    fov: float = 40.0
    width: int = 256
    height: int = 256
    projection: str = "pinhole"
    view_width: float = 0.0

    @property
    def pixel_size_mm(self) -> float | None:
        """Side of a pixel in mm for an orthographic camera, `None` for a pinhole."""
        if self.projection != "orthographic":
            return None
        return self.view_width / self.width

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit (forward, right, up) vectors of the image plane."""
        fwd = self.target - self.origin
        fwd = fwd / np.linalg.norm(fwd)
        right = np.cross(fwd, self.up)
        right = right / np.linalg.norm(right)
        up = np.cross(right, fwd)
        return fwd, right, up


@dataclass(frozen=True, eq=False)
class AreaLight(_Value):
    """A one-sided emitting parallelogram `corner + u edge_u + v edge_v`, emitting `radiance`
    (W mm^-2 sr^-1, RGB) towards `edge_u x edge_v`."""

    kind: ClassVar[str] = "area"  # `type` in a scene file
    emission: ClassVar[str] = "radiance"  # the field the image is linear in

    corner: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    radiance: np.ndarray

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.edge_u, self.edge_v)
        return n / np.linalg.norm(n)

    @property
    def area(self) -> float:
        return float(np.linalg.norm(np.cross(self.edge_u, self.edge_v)))


@dataclass(frozen=True, eq=False)
class PointLight(_Value):
    """An isotropic point light of RGB `intensity` (W sr^-1) at `position` (mm)."""

    kind: ClassVar[str] = "point"
    emission: ClassVar[str] = "intensity"

    position: np.ndarray
    intensity: np.ndarray


@dataclass(frozen=True, eq=False)
class BeamLight(_Value):
    """A collimated beam of circular cross-section: it leaves the disc of `radius` (mm)
    around `position`, perpendicular to `direction`, and carries RGB `power` (W) along
    `direction`. A surface it hits at incidence angle `theta` receives irradiance
    `power cos(theta) / (pi radius^2)` inside the beam (Jensen's measurement setup)."""

    kind: ClassVar[str] = "beam"
    emission: ClassVar[str] = "power"

    position: np.ndarray
    direction: np.ndarray
    radius: float
    power: np.ndarray


@dataclass(frozen=True, eq=False)
class EnvironmentLight(_Value):
    """A constant environment: RGB `radiance` (W mm^-2 sr^-1) arriving from every direction
    that escapes the scene (seen by rays like the background, and lighting every surface)."""

    kind: ClassVar[str] = "environment"
    emission: ClassVar[str] = "radiance"

    radiance: np.ndarray


@dataclass(frozen=True, eq=False)
class Material(_Value):
    """`type` is `diffuse` (uses `albedo`), `mirror` (`reflectance`) or `translucent` (`medium`)."""

    name: str
    type: str
    albedo: np.ndarray = field(default_factory=lambda: np.zeros(3))
    reflectance: np.ndarray = field(default_factory=lambda: np.zeros(3))
    medium: Medium | None = None


@dataclass(frozen=True, eq=False)
class ShapeSpec(_Value):
    """One shape instance: the geometry object from `sssjax.shapes` and its material name.

    `params` are the validated fields it was built from (placement and the kind's own:
    `radius`, `size`, ...; a mesh's `vertices` and `faces`, or its OBJ `file` resolved), which
    the scene writer writes back; the geometry itself is what compares equal."""

    kind: str
    material: str
    shape: Any
    params: dict = field(default_factory=dict, compare=False)


@dataclass(frozen=True, eq=False)
class RenderSettings(_Value):
    spp: int = 16
    light_samples: int = 4
    max_depth: int = 4
    seed: int = 0
    background: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tile: int = 32


@dataclass(frozen=True, eq=False)
class SSSSettings(_Value):
    enabled: bool = True
    single_scattering: bool = True
    cloud_size: int = 8192
    single_samples: int = 1
    strategy: str = "cloud"
    samples: int = 16
    radius: float = 0.0
    inner: float = 0.0
    outer: float = 0.0
    tries: int = 8
    bins: int = 256
    beam_points: int = 2048
    profile: str = "dipole"
    transport: str = "diffusion"  # `sssjax.transport.TRANSPORTS`
    records: int = 4  # volumetric: re-weightable records kept per walker
    spectral: str = "mis"  # volumetric: one walker for all channels (MIS) or "separate"
    next_event: bool = True  # volumetric: next-event estimation inside media


@dataclass(frozen=True, eq=False)
class Scene(_Value):
    """A validated scene. Build it with `load_scene(path_or_dict)`; write it with `to_toml`.

    Scenes compare by value (`path` and `source`, where it was read from, aside)."""

    camera: Camera
    lights: tuple
    materials: dict
    shapes: tuple
    render: RenderSettings = field(default_factory=RenderSettings)
    sss: SSSSettings = field(default_factory=SSSSettings)
    path: str | None = field(default=None, compare=False)
    source: dict | None = field(default=None, compare=False)

    @property
    def translucent_materials(self) -> list[str]:
        """Names of the translucent materials that some shape uses, in a fixed order."""
        used = {s.material for s in self.shapes}
        return [n for n, m in self.materials.items() if m.type == "translucent" and n in used]

    def media(self) -> dict[str, Medium]:
        """The media of the translucent materials, by name: the argument of `shade`."""
        return {n: self.materials[n].medium for n in self.translucent_materials}

    def to_toml(self, path: str | Path | None = None, *, header: str | None = None) -> str:
        """The scene as a scene file (`dump_scene`); written to `path` when given."""
        return dump_scene(self, path, header=header)

    def replace(self, **kw) -> Scene:
        """A copy with some top-level fields replaced (`camera=...`, `render=...`)."""
        return dataclasses.replace(self, **kw)

    def with_settings(self, **kw) -> Scene:
        """A copy with render settings (`spp`, `seed`, `light_samples`, ...) or SSS settings
        (prefixed `sss_`, e.g. `sss_enabled=False`) or camera size (`width`, `height`) changed."""
        r = {k: v for k, v in kw.items() if k in RenderSettings.__dataclass_fields__}
        s = {k[4:]: v for k, v in kw.items() if k.startswith("sss_")}
        c = {k: v for k, v in kw.items() if k in ("width", "height", "fov")}
        unknown = set(kw) - set(r) - {f"sss_{k}" for k in s} - set(c)
        if unknown:
            raise TypeError(f"unknown settings: {sorted(unknown)}")
        # the scene file's own checks, naming the keyword (`width: must be >= 1, got 0`)
        ctx = _KeywordCtx()
        r = {k: _RENDER[k][0](ctx, k, _plain(v)) if k in _RENDER else v for k, v in r.items()}
        s = {k: _SSS[k][0](ctx, f"sss_{k}", _plain(v)) if k in _SSS else v for k, v in s.items()}
        c = {k: _CAMERA[k][0](ctx, k, _plain(v)) for k, v in c.items()}
        if "fov" in c and not 0 < c["fov"] < 180:
            raise ctx.err("fov", f"must be between 0 and 180 degrees, got {c['fov']:g}")
        if "profile" in s:
            check_profile(s["profile"])
        if "transport" in s:
            TRANSPORTS.check(s["transport"])
        return dataclasses.replace(
            self,
            render=dataclasses.replace(self.render, **r),
            sss=dataclasses.replace(self.sss, **s),
            camera=dataclasses.replace(self.camera, **c),
        )


# --- schema-driven validation ----------------------------------------------------------
REQUIRED = object()


class _Ctx:
    def __init__(self, file: str, table: str):
        self.file, self.table = file, table

    def err(self, field_name: str | None, msg: str) -> SceneError:
        where = f"[{self.table}]" + (f" {field_name}" if field_name else "")
        return SceneError(f"{self.file}: {where}: {msg}")


def _plain(v: Any) -> Any:
    """NumPy scalars and arrays as the Python numbers and lists a TOML file would give."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


class _KeywordCtx(_Ctx):
    """Errors of `Scene.with_settings` keywords: `spp: must be >= 1, got 0`."""

    def __init__(self):
        super().__init__("", "")

    def err(self, field_name: str | None, msg: str) -> SceneError:
        return SceneError(f"{field_name}: {msg}")


def _fmt(v: Any) -> str:
    return repr(v) if isinstance(v, str) else str(v)


def _number(ctx, name, v):
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ctx.err(name, f"expected a number, got {_fmt(v)}")
    if not math.isfinite(v):
        raise ctx.err(name, f"must be finite, got {_fmt(v)}")
    return float(v)


def _vec3(ctx, name, v):
    if not isinstance(v, list | tuple) or len(v) != 3:
        raise ctx.err(name, f"expected a list of 3 numbers, got {_fmt(v)}")
    return np.array([_number(ctx, name, x) for x in v], dtype=np.float64)


def _rgb(ctx, name, v):
    if isinstance(v, int | float) and not isinstance(v, bool):
        v = [v, v, v]
    out = _vec3(ctx, name, v)
    if np.any(out < 0):
        raise ctx.err(name, f"must be >= 0, got {_fmt([float(x) for x in out])}")
    return out


def _int(ctx, name, v):
    if isinstance(v, bool) or not isinstance(v, int):
        raise ctx.err(name, f"expected an integer, got {_fmt(v)}")
    return v


def _pos_int(ctx, name, v):
    v = _int(ctx, name, v)
    if v < 1:
        raise ctx.err(name, f"must be >= 1, got {v}")
    return v


def _nonneg_int(ctx, name, v):
    v = _int(ctx, name, v)
    if v < 0:
        raise ctx.err(name, f"must be >= 0, got {v}")
    return v


def _pos(ctx, name, v):
    v = _number(ctx, name, v)
    if v <= 0:
        raise ctx.err(name, f"must be > 0, got {v:g}")
    return v


def _nonneg(ctx, name, v):
    v = _number(ctx, name, v)
    if v < 0:
        raise ctx.err(name, f"must be >= 0, got {v:g}")
    return v


def _str(ctx, name, v):
    if not isinstance(v, str):
        raise ctx.err(name, f"expected a string, got {_fmt(v)}")
    return v


def _bool(ctx, name, v):
    if not isinstance(v, bool):
        raise ctx.err(name, f"expected true or false, got {_fmt(v)}")
    return v


def _scale(ctx, name, v):
    if isinstance(v, int | float) and not isinstance(v, bool):
        s = _pos(ctx, name, v)
        return np.array([s, s, s])
    out = _vec3(ctx, name, v)
    if np.any(out <= 0):
        raise ctx.err(name, f"must be > 0, got {_fmt([float(x) for x in out])}")
    return out


def _size(ctx, name, v):
    if isinstance(v, list | tuple):
        return _scale(ctx, name, v)
    return _pos(ctx, name, v)


def _any(ctx, name, v):
    return v


def _not_a_table(ctx: _Ctx, data: Any) -> str:
    if isinstance(data, list) and data and all(isinstance(x, Mapping) for x in data):
        return f"expected one table [{ctx.table}], got an array of tables [[{ctx.table}]]"
    text = _fmt(data)
    return f"expected a table, got {text if len(text) <= 60 else text[:57] + '...'}"


def _fields(ctx: _Ctx, data: Any, schema: dict) -> dict:
    """Check `data` against `schema` {field: (checker, default)}; unknown keys get a hint."""
    if not isinstance(data, Mapping):
        raise ctx.err(None, _not_a_table(ctx, data))
    for key in data:
        if key not in schema:
            hint = did_you_mean(key, list(schema))
            known = ", ".join(sorted(schema))
            raise ctx.err(key, f"unknown field{hint} (known fields: {known})")
    out = {}
    for name, (check, default) in schema.items():
        if name in data:
            out[name] = check(ctx, name, data[name])
        elif default is REQUIRED:
            raise ctx.err(name, "missing required field")
        else:
            out[name] = default() if callable(default) else default
    return out


_CAMERA = {
    "origin": (_vec3, REQUIRED),
    "target": (_vec3, REQUIRED),
    "up": (_vec3, lambda: np.array([0.0, 1.0, 0.0])),
    "fov": (_pos, 40.0),
    "width": (_pos_int, 256),
    "height": (_pos_int, 256),
    "projection": (_str, "pinhole"),
    "view_width": (_pos, 0.0),
}
_PROJECTIONS = ("pinhole", "orthographic")
_RENDER = {
    "spp": (_pos_int, 16),
    "light_samples": (_pos_int, 4),
    "max_depth": (_nonneg_int, 4),
    "seed": (_nonneg_int, 0),
    "background": (_rgb, lambda: np.zeros(3)),
    "tile": (_pos_int, 32),
}
_SSS = {
    "enabled": (_bool, True),
    "single_scattering": (_bool, True),
    "cloud_size": (_pos_int, 8192),
    "single_samples": (_pos_int, 1),
    "strategy": (_str, "cloud"),
    "samples": (_pos_int, 16),
    "radius": (_nonneg, 0.0),
    "inner": (_nonneg, 0.0),
    "outer": (_nonneg, 0.0),
    "tries": (_pos_int, 8),
    "bins": (_pos_int, 256),
    "beam_points": (_pos_int, 2048),
    "profile": (_str, "dipole"),
    "transport": (_str, "diffusion"),
    "records": (_pos_int, 4),
    "spectral": (_str, "mis"),
    "next_event": (_bool, True),
}
_LIGHTS = {
    "area": {
        "type": (_str, REQUIRED),
        "corner": (_vec3, REQUIRED),
        "edge_u": (_vec3, REQUIRED),
        "edge_v": (_vec3, REQUIRED),
        "radiance": (_rgb, REQUIRED),
    },
    "point": {
        "type": (_str, REQUIRED),
        "position": (_vec3, REQUIRED),
        "intensity": (_rgb, REQUIRED),
    },
    "beam": {
        "type": (_str, REQUIRED),
        "position": (_vec3, REQUIRED),
        "direction": (_vec3, REQUIRED),
        "radius": (_pos, REQUIRED),
        "power": (_rgb, REQUIRED),
    },
    "environment": {"type": (_str, REQUIRED), "radiance": (_rgb, REQUIRED)},
}
_MATERIALS = {
    "diffuse": {"type": (_str, REQUIRED), "albedo": (_rgb, REQUIRED)},
    "mirror": {"type": (_str, REQUIRED), "reflectance": (_rgb, lambda: np.ones(3))},
    "translucent": {
        "type": (_str, REQUIRED),
        "preset": (_str, None),
        "sigma_a": (_rgb, None),
        "sigma_s": (_rgb, None),
        "sigmap_s": (_rgb, None),
        "g": (_number, 0.0),
        "eta": (_pos, None),
        "scale": (_rgb, lambda: np.ones(3)),
    },
}
_PLACEMENT = {
    "type": (_str, REQUIRED),
    "material": (_str, REQUIRED),
    "translate": (_vec3, lambda: np.zeros(3)),
    "rotate": (_vec3, lambda: np.zeros(3)),
    "scale": (_scale, lambda: np.ones(3)),
}
_SHAPES = {
    "sphere": {"radius": (_pos, REQUIRED)},
    "cube": {"size": (_size, REQUIRED)},
    "cylinder": {"radius": (_pos, REQUIRED), "height": (_pos, REQUIRED)},
    "cone": {"radius": (_pos, REQUIRED), "height": (_pos, REQUIRED)},
    "quadmesh": {"vertices": (_any, None), "faces": (_any, None), "file": (_str, None)},
}
_TOP = ("camera", "render", "sss", "lights", "materials", "shapes")


def _kind(ctx: _Ctx, data: Any, kinds: dict, what: str) -> str:
    if not isinstance(data, Mapping):
        raise ctx.err(None, f"expected a table, got {_fmt(data)}")
    if "type" not in data:
        raise ctx.err("type", f"missing required field (one of: {', '.join(kinds)})")
    kind = data["type"]
    if kind not in kinds:
        hint = did_you_mean(str(kind), list(kinds))
        raise ctx.err("type", f"unknown {what} type {_fmt(kind)}{hint} (known: {', '.join(kinds)})")
    return kind


def _translucent_medium(ctx: _Ctx, f: dict) -> Medium:
    if f["preset"] is not None:
        for k in ("sigma_a", "sigma_s", "sigmap_s"):
            if f[k] is not None:
                raise ctx.err(k, "give either 'preset' or explicit coefficients, not both")
        try:
            m = preset(f["preset"])
        except ValueError as e:
            raise ctx.err("preset", str(e)) from None
        sigma_a, sigma_s, g, eta = m.sigma_a, m.sigma_s, float(m.g), float(m.eta)
        if f["eta"] is not None:
            eta = f["eta"]
    else:
        if f["sigma_a"] is None:
            raise ctx.err(
                "sigma_a",
                f"missing: give 'preset' (one of {', '.join(preset_names())}) "
                "or 'sigma_a' with 'sigma_s' or 'sigmap_s'",
            )
        if (f["sigma_s"] is None) == (f["sigmap_s"] is None):
            raise ctx.err("sigma_s", "give exactly one of 'sigma_s' and 'sigmap_s'")
        g = f["g"]
        if not -1.0 < g < 1.0:
            raise ctx.err("g", f"must satisfy |g| < 1, got {g:g}")
        sigma_a = f["sigma_a"]
        sigma_s = f["sigma_s"] if f["sigma_s"] is not None else f["sigmap_s"] / (1.0 - g)
        eta = 1.3 if f["eta"] is None else f["eta"]
    scale = f["scale"]
    sigma_t = (np.asarray(sigma_a) + np.asarray(sigma_s)) * scale
    if np.any(sigma_t <= 0):
        raise ctx.err(
            "sigma_s",
            f"sigma_a + sigma_s must be > 0 in every channel, got {[float(x) for x in sigma_t]} "
            "(a medium that neither absorbs nor scatters)",
        )
    try:
        return Medium(np.asarray(sigma_a) * scale, np.asarray(sigma_s) * scale, g, eta)
    except ValueError as e:
        raise ctx.err(None, str(e)) from None


def _parse_mesh(ctx: _Ctx, f: dict, base: Path | None):
    from . import shapes

    if f["file"] is not None:
        if f["vertices"] is not None or f["faces"] is not None:
            raise ctx.err("file", "give either 'file' or inline 'vertices' and 'faces', not both")
        path = Path(f["file"])
        if not path.is_absolute() and base is not None:
            path = base / path
        if not path.exists():
            raise ctx.err("file", f"OBJ file not found: {path}")
        if path.is_dir():
            raise ctx.err("file", f"{path} is a folder, not an OBJ file")
        try:
            return shapes.load_obj(path)
        except (ValueError, OSError) as e:
            raise ctx.err("file", f"cannot parse OBJ: {e}") from None
    if f["vertices"] is None or f["faces"] is None:
        raise ctx.err("vertices", "a quadmesh needs 'file' or both 'vertices' and 'faces'")
    try:
        verts = np.asarray(f["vertices"], dtype=np.float64)
    except (ValueError, TypeError):
        raise ctx.err("vertices", "expected a list of [x, y, z] triples") from None
    if verts.ndim != 2 or verts.shape[1] != 3 or len(verts) < 3 or not np.all(np.isfinite(verts)):
        raise ctx.err("vertices", "expected a list of at least 3 finite [x, y, z] triples")
    faces = f["faces"]
    if not isinstance(faces, list) or not faces:
        raise ctx.err("faces", "expected a non-empty list of quads or triangles (vertex indices)")
    for i, face in enumerate(faces):
        ok = isinstance(face, list) and len(face) in (3, 4)
        ok = ok and all(isinstance(j, int) and not isinstance(j, bool) for j in face)
        if not ok:
            raise ctx.err("faces", f"face {i}: expected 3 or 4 integer indices, got {_fmt(face)}")
        bad = [j for j in face if not 0 <= j < len(verts)]
        if bad:
            raise ctx.err("faces", f"face {i}: index {bad[0]} out of range 0..{len(verts) - 1}")
    return verts, faces


def _parse_camera(file: str, raw: Any) -> Camera:
    """The validated `[camera]` table."""
    cam = _fields(_Ctx(file, "camera"), raw, _CAMERA)
    cctx = _Ctx(file, "camera")
    if np.linalg.norm(cam["target"] - cam["origin"]) == 0:
        raise cctx.err("target", "must differ from 'origin'")
    if np.linalg.norm(np.cross(cam["target"] - cam["origin"], cam["up"])) < 1e-9:
        raise cctx.err("up", "must not be parallel to the viewing direction")
    if not 0 < cam["fov"] < 180:
        raise cctx.err("fov", f"must be between 0 and 180 degrees, got {cam['fov']:g}")
    if cam["projection"] not in _PROJECTIONS:
        hint = did_you_mean(cam["projection"], _PROJECTIONS)
        raise cctx.err(
            "projection",
            f"unknown projection {cam['projection']!r}{hint} (known: {', '.join(_PROJECTIONS)})",
        )
    if cam["projection"] == "orthographic" and cam["view_width"] <= 0:
        raise cctx.err("view_width", "an orthographic camera needs view_width > 0 (mm)")
    return Camera(**cam)


# 150+ lines: the loader reads the sections in file order, each a short block over the
# field tables (`_SHAPES`, `_LIGHTS`, `_MATERIALS`); the checks themselves live in `_fields`.
def load_scene(source: str | Path | Mapping, *, base_dir: str | Path | None = None) -> Scene:
    """Load and validate a scene.

    **Arguments:**

    - `source`: a path to a TOML scene file, or the same structure as a Python dict (its
      numbers may be NumPy or JAX scalars and arrays).
    - `base_dir`: folder against which relative OBJ paths resolve (default: the file's folder,
      or the working directory for a dict).

    **Returns:** a `Scene`. Every problem raises `SceneError` naming file, table and field.
    """
    from . import shapes

    if isinstance(source, Mapping):
        # NumPy / JAX values as Python numbers and lists, as a TOML file would give them
        file, data = "<dict>", _plain(source)
        base = Path(base_dir) if base_dir is not None else Path.cwd()
    else:
        path = Path(source)
        file = str(path)
        data = read_toml(path, SceneError, "scene file")
        base = Path(base_dir) if base_dir is not None else path.parent

    for key in data:
        if key not in _TOP:
            hint = did_you_mean(key, _TOP)
            raise SceneError(f"{file}: unknown table [{key}]{hint} (known: {', '.join(_TOP)})")
    if "camera" not in data:
        raise SceneError(f"{file}: missing required table [camera]")

    camera = _parse_camera(file, data["camera"])

    render = RenderSettings(**_fields(_Ctx(file, "render"), data.get("render", {}), _RENDER))
    sctx = _Ctx(file, "sss")
    sss = SSSSettings(**_fields(sctx, data.get("sss", {}), _SSS))
    try:
        check_profile(sss.profile)
    except ValueError as e:
        raise sctx.err("profile", str(e)) from None
    for name, registry in (("strategy", STRATEGIES), ("transport", TRANSPORTS)):
        try:
            registry.check(getattr(sss, name))
        except ValueError as e:
            raise sctx.err(name, str(e)) from None
    if sss.spectral not in ("mis", "separate"):
        hint = did_you_mean(sss.spectral, ["mis", "separate"])
        raise sctx.err(
            "spectral", f"unknown spectral mode {sss.spectral!r}{hint} (known: mis, separate)"
        )
    problem = STRATEGIES[sss.strategy].check(sss)
    if problem is not None:
        raise sctx.err(*problem)

    raw_lights = data.get("lights", [])
    if not isinstance(raw_lights, list):
        raise SceneError(f"{file}: [lights]: expected an array of tables ([[lights]])")
    lights = []
    for i, raw in enumerate(raw_lights):
        ctx = _Ctx(file, f"lights.{i}")
        kind = _kind(ctx, raw, _LIGHTS, "light")
        f = _fields(ctx, raw, _LIGHTS[kind])
        f.pop("type")
        if kind == "area":
            if np.linalg.norm(np.cross(f["edge_u"], f["edge_v"])) <= 0:
                raise ctx.err("edge_v", "edges must span a non-degenerate parallelogram")
            lights.append(AreaLight(**f))
        elif kind == "beam":
            norm = np.linalg.norm(f["direction"])
            if norm == 0:
                raise ctx.err("direction", "must be a non-zero vector")
            if abs(norm - 1.0) > 1e-15:  # unit already: kept as written (round trips)
                f["direction"] = f["direction"] / norm
            lights.append(BeamLight(**f))
        elif kind == "environment":
            lights.append(EnvironmentLight(**f))
        else:
            lights.append(PointLight(**f))

    raw_mats = data.get("materials", {})
    if not isinstance(raw_mats, Mapping):
        raise SceneError(f"{file}: [materials]: expected tables [materials.NAME]")
    materials = {}
    for name, raw in raw_mats.items():
        ctx = _Ctx(file, f"materials.{name}")
        kind = _kind(ctx, raw, _MATERIALS, "material")
        f = _fields(ctx, raw, _MATERIALS[kind])
        if kind == "diffuse":
            if np.any(f["albedo"] > 1):
                raise ctx.err("albedo", f"must be <= 1, got {[float(x) for x in f['albedo']]}")
            materials[name] = Material(name, kind, albedo=f["albedo"])
        elif kind == "mirror":
            if np.any(f["reflectance"] > 1):
                raise ctx.err(
                    "reflectance", f"must be <= 1, got {[float(x) for x in f['reflectance']]}"
                )
            materials[name] = Material(name, kind, reflectance=f["reflectance"])
        else:
            materials[name] = Material(name, kind, medium=_translucent_medium(ctx, f))

    raw_shapes = data.get("shapes", [])
    if not isinstance(raw_shapes, list):
        raise SceneError(f"{file}: [shapes]: expected an array of tables ([[shapes]])")
    shape_list = []
    for i, raw in enumerate(raw_shapes):
        ctx = _Ctx(file, f"shapes.{i}")
        kind = _kind(ctx, raw, _SHAPES, "shape")
        f = _fields(ctx, raw, {**_PLACEMENT, **_SHAPES[kind]})
        if f["material"] not in materials:
            known = ", ".join(materials) or "none defined"
            hint = did_you_mean(f["material"], list(materials))
            raise ctx.err("material", f"no material named {f['material']!r}{hint} (known: {known})")
        params = {k: f[k] for k in _SHAPES[kind]}
        written = {k: f[k] for k in ("translate", "rotate", "scale")}  # for the writer
        if kind == "quadmesh":
            verts, faces = _parse_mesh(ctx, f, base)
            params = {"vertices": verts, "faces": faces}
            if f["file"] is not None:
                obj = Path(f["file"])
                written["file"] = str((base / obj if base is not None else obj).resolve())
            else:
                written.update(params)
        else:
            written.update(params)
        try:
            geom = shapes.make_shape(kind, params, f["translate"], f["rotate"], f["scale"])
            area = None
            if materials[f["material"]].type == "translucent":
                area = float(geom.area())  # translucent shapes need an exact area and sampler
        except ValueError as e:
            raise ctx.err("scale", str(e)) from None
        if area is not None and not area > 0:  # (a mesh of degenerate faces)
            raise ctx.err(None, f"a translucent shape needs a surface area > 0 mm^2, got {area:g}")
        shape_list.append(ShapeSpec(kind, f["material"], geom, written))

    if not shape_list:
        raise SceneError(f"{file}: [[shapes]]: the scene has no shapes (add a [[shapes]] table)")
    if sss.profile == "tabulated" and sss.transport == "diffusion":
        from ._tabulated import eta_outside

        used = {s.material for s in shape_list}
        for name, m in materials.items():
            if name in used and m.medium is not None and (note := eta_outside(m.medium.eta)):
                warnings.warn(
                    f"{file}: [materials.{name}] eta = {note}; use profile = "
                    '"better_dipole" or transport = "volumetric"',
                    SceneWarning,
                    stacklevel=2,
                )
    if not lights or not any(np.any(_emission(lt) > 0) for lt in lights):
        warnings.warn(
            f"{file}: "
            + ("no [[lights]]" if not lights else "every light has zero emission")
            + ": the image shows only the background (and what reflects it)",
            SceneWarning,
            stacklevel=2,
        )
    return Scene(
        camera=camera,
        lights=tuple(lights),
        materials=materials,
        shapes=tuple(shape_list),
        render=render,
        sss=sss,
        path=None if isinstance(source, Mapping) else str(source),
        source=data,
    )


# --- writing ---------------------------------------------------------------------------
def _plain(v: Any) -> Any:
    """`v` as TOML values: arrays to lists of floats, NumPy scalars to Python numbers; a
    float32 value as its shortest decimal (`0.0021`, not `0.002099999925121665`), which
    reads back to the same float32."""
    if isinstance(v, np.ndarray | jax.Array):
        a = np.asarray(v)
        return [_plain(x) for x in a] if a.ndim else _plain(a[()])
    if isinstance(v, np.floating):
        return float(str(v)) if v.dtype == np.float32 else float(v)
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    if isinstance(v, Mapping):
        return {k: _plain(x) for k, x in v.items()}
    return v


def _material_dict(m: Material) -> dict:
    if m.type == "diffuse":
        return {"type": "diffuse", "albedo": _plain(m.albedo)}
    if m.type == "mirror":
        return {"type": "mirror", "reflectance": _plain(m.reflectance)}
    med = m.medium
    g = np.asarray(med.g)
    if g.ndim and not np.all(g == g.flat[0]):
        raise ValueError(f"material {m.name!r}: a scene file holds one g, got {g.tolist()}")
    return {
        "type": "translucent",
        "sigma_a": _plain(med.sigma_a),
        "sigma_s": _plain(med.sigma_s),
        "g": _plain(g.flat[0]),
        "eta": _plain(np.asarray(med.eta)),
    }


def scene_dict(scene: Scene) -> dict:
    """The scene file structure of `scene` (the dict `load_scene` accepts), from its
    validated values: media as explicit coefficients (presets and `scale` applied), a quad
    mesh read from an OBJ file by its absolute path."""
    cam = scene.camera
    camera = {f.name: _plain(getattr(cam, f.name)) for f in dataclasses.fields(cam)}
    if cam.projection != "orthographic":
        camera.pop("view_width")
    lights = []
    for lt in scene.lights:
        fields = {f.name: _plain(getattr(lt, f.name)) for f in dataclasses.fields(lt)}
        lights.append({"type": lt.kind, **fields})
    shapes = [
        {"type": s.kind, "material": s.material, **{k: _plain(v) for k, v in s.params.items()}}
        for s in scene.shapes
    ]
    return {
        "camera": camera,
        "render": {
            f.name: _plain(getattr(scene.render, f.name)) for f in dataclasses.fields(scene.render)
        },
        "sss": {f.name: _plain(getattr(scene.sss, f.name)) for f in dataclasses.fields(scene.sss)},
        "lights": lights,
        "materials": {n: _material_dict(m) for n, m in scene.materials.items()},
        "shapes": shapes,
    }


# tomli-w writes an array one item per line; arrays of numbers go on one line instead
_NUMBER = r"[-+]?(?:\d[\d_]*(?:\.\d+)?(?:[eE][-+]?\d+)?|inf|nan)"
_NUMBER_ARRAY = re.compile(rf"\[\n((?:[ ]*{_NUMBER},\n)+)[ ]*\]")


def _one_line(m: re.Match) -> str:
    return "[" + ", ".join(x.strip().rstrip(",") for x in m.group(1).splitlines()) + "]"


def dump_scene(scene: Scene, path: str | Path | None = None, *, header: str | None = None) -> str:
    """Write `scene` as a scene file: `load_scene` of the text gives a scene equal to `scene`.

    **Arguments:** `scene`; `path` to write to (never an existing file: `FileExistsError`);
    `header`, a comment put first (default: where the scene came from; units).

    **Returns:** the TOML text (lengths in mm, coefficients in mm^-1).
    """
    import tomli_w

    if header is None:
        header = f"sssjax scene written from {scene.path or 'a scene dict'}; units: mm, 1/mm"
    lines = "".join(f"# {h}\n" for h in header.splitlines())
    text = lines + "\n" + _NUMBER_ARRAY.sub(_one_line, tomli_w.dumps(scene_dict(scene)))
    if path is not None:
        with open(path, "x") as f:  # "x": fails rather than overwrite
            f.write(text)
    return text
