"""The parameter map of a scene: every quantity a fit can free, by name, with its value and
how it enters the image (after Mitsuba's `traverse`).

`parameters(scene)` lists them; `resolve(scene, names)` turns user names into parameters
(one-line errors for unknown or conflicting ones); `apply(scene, values)` returns the scene
with new values. The fit, fit files, the command line and `FitResult.apply` all use these, so
a name like `marble.sigma_a` is parsed here only.

| name | value | enters |
| --- | --- | --- |
| `MATERIAL.sigma_a`, `.sigma_s`, `.sigmap_s` | RGB, mm^-1 | `SHADED`: the shading only; a fit re-shades |
| `MATERIAL.g` | RGB mean cosine | `SHADED` |
| `MATERIAL.eta` | refractive index | `RETRACED`: it bends rays; a fit re-traces at each value |
| `lights.N` | factor on light `N`'s emission (1) | `EMISSION`: the image is linear in it; traced alone once |
| `exposure` | factor on the whole image (1) | `IMAGE`: not part of the scene |

The material may be left out of a name (`sigma_a`) when the scene has one translucent
material.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ._registry import did_you_mean
from .media import Medium
from .scene import Scene

__all__ = [
    "Enters",
    "Parameter",
    "ParameterError",
    "PARAM_FIELDS",
    "parameters",
    "resolve",
    "apply",
]

PARAM_FIELDS = ("sigma_a", "sigma_s", "sigmap_s", "g", "eta")  # per translucent material


class ParameterError(ValueError):
    """A bad parameter name or value: a one-line message."""


class Enters(enum.Enum):
    """How a parameter enters the image, i.e. what a new value costs."""

    SHADED = "shaded"  # the shading only: re-shade
    RETRACED = "retraced"  # the rays: re-trace (compiled tracers take it as an argument)
    EMISSION = "emission"  # linear in a light's emission: one trace with that light alone
    IMAGE = "image"  # a factor on the image, outside the scene


@dataclass(frozen=True)
class Parameter:
    """One parameter of a scene: `name`, the scene's `value` (`(3,)` RGB or a float),
    how it `enters`, and what it belongs to (`material` and `field`, or `light`)."""

    name: str
    value: Any
    enters: Enters
    material: str | None = None
    field: str | None = None
    light: int | None = None

    @property
    def rgb(self) -> bool:
        return self.enters is Enters.SHADED

    def initial(self, v: Any = None, eta_range: tuple[float, float] = (1.0, 2.5)):
        """A validated starting value (`v`, default the scene's): RGB and > 0 for the
        coefficients, `|g| < 1`, `eta` one number in `eta_range`, factors one number > 0."""
        v = self.value if v is None else v
        if self.rgb:
            a = np.broadcast_to(np.asarray(v, dtype=np.float64), (3,))
            if self.field == "g":
                if not np.all(np.isfinite(a)) or np.any(np.abs(a) >= 1):
                    raise ParameterError(
                        f"initial {self.name} must satisfy |g| < 1, got {a.tolist()}"
                    )
            elif not np.all(np.isfinite(a)) or np.any(a <= 0):
                raise ParameterError(
                    f"initial {self.name} must be finite and > 0, got {a.tolist()}"
                )
            return a
        x = float(np.asarray(v, dtype=np.float64)) if np.ndim(v) == 0 else np.nan
        if self.enters is Enters.RETRACED:
            if not eta_range[0] < x < eta_range[1]:
                raise ParameterError(
                    f"initial {self.name} must be one number in ({eta_range[0]}, "
                    f"{eta_range[1]}), got {v}"
                )
        elif self.enters is Enters.EMISSION:
            if not (np.isfinite(x) and x > 0):
                raise ParameterError(f"initial {self.name} must be one finite factor > 0, got {x}")
        elif not (np.isfinite(x) and x > 0):
            raise ParameterError(f"initial {self.name} must be finite and > 0, got {x}")
        return x


def parameters(scene: Scene) -> dict[str, Parameter]:
    """Every parameter of `scene` by name (see the module docstring), in a fixed order:
    each translucent material's fields, each light, the exposure."""
    out = {}
    for mat, med in scene.media().items():
        for f in PARAM_FIELDS:
            value = np.asarray(getattr(med, f), dtype=np.float64)
            enters = Enters.RETRACED if f == "eta" else Enters.SHADED
            value = float(value) if f == "eta" else np.broadcast_to(value, (3,))
            out[f"{mat}.{f}"] = Parameter(f"{mat}.{f}", value, enters, mat, f)
    for i in range(len(scene.lights)):
        out[f"lights.{i}"] = Parameter(f"lights.{i}", 1.0, Enters.EMISSION, light=i)
    out["exposure"] = Parameter("exposure", 1.0, Enters.IMAGE)
    return out


def canonical(scene: Scene, name: str) -> str:
    """The full name of `name` (`sigma_a` -> `marble.sigma_a` with one translucent
    material); a `ParameterError` for a name that is not a parameter of `scene`."""
    if not isinstance(name, str):
        raise ParameterError(f"parameter names are strings, got {name!r}")
    tm = scene.translucent_materials
    if name == "exposure":
        return name
    if name.startswith("lights."):
        idx, n = name.removeprefix("lights."), len(scene.lights)
        if not (idx.isdigit() and int(idx) < n):
            if not n:
                raise ParameterError(f"parameter {name!r}: the scene has no lights")
            raise ParameterError(
                f"parameter {name!r}: no such light (the scene has {n}: lights.0 .. lights.{n - 1})"
            )
        return f"lights.{int(idx)}"
    mat, _, field = name.rpartition(".")
    if not mat:
        if len(tm) != 1:
            example = f", e.g. '{tm[0]}.{name}'" if tm else ""
            raise ParameterError(
                f"parameter {name!r}: name the material ({', '.join(tm)}){example}"
            )
        mat = tm[0]
    if mat not in tm:
        raise ParameterError(
            f"parameter {name!r}: no translucent material {mat!r} (known: {', '.join(tm)})"
        )
    if field not in PARAM_FIELDS:
        known = ", ".join((*PARAM_FIELDS, "exposure", "lights.N"))
        hint = did_you_mean(field, [*PARAM_FIELDS, "exposure"])
        raise ParameterError(f"unknown parameter {field!r}{hint} (known: {known})")
    return f"{mat}.{field}"


def resolve(scene: Scene, names: Sequence[str] | None) -> list[Parameter]:
    """The parameters `names` of `scene`, in their order without repeats (default: every
    translucent material's `sigma_a` and `sigma_s`). Errors: an unknown name or material, a
    scene without translucent material, `sigma_s` with `sigmap_s` of one material, free
    `eta` of more than one material, no coefficient at all, the exposure with every light."""
    tm = scene.translucent_materials
    if not tm:
        raise ParameterError("the scene has no translucent material to fit")
    if names is None:
        names = [f"{m}.{f}" for m in tm for f in ("sigma_a", "sigma_s")]
    table = parameters(scene)
    full = list(dict.fromkeys(canonical(scene, n) for n in names))
    chosen = [table[n] for n in full]
    for mat in tm:
        if {f"{mat}.sigma_s", f"{mat}.sigmap_s"} <= set(full):
            raise ParameterError(f"{mat}: free either sigma_s or sigmap_s, not both")
    eta = sorted(p.material for p in chosen if p.enters is Enters.RETRACED)
    if len(eta) > 1:
        raise ParameterError(f"params: free the eta of one material at a time, got {eta}")
    if not any(p.enters is Enters.SHADED for p in chosen):
        raise ParameterError(
            "params: free at least one coefficient (exposure or light intensities alone fit "
            "no material)"
        )
    lights = [p for p in chosen if p.enters is Enters.EMISSION]
    if lights and len(lights) == len(scene.lights) and "exposure" in full:
        raise ParameterError(
            "params: the exposure and every light's intensity are free, but only their "
            "product is determined: fix the exposure or one light"
        )
    return chosen


def apply(scene: Scene, values: Mapping[str, Any]) -> Scene:
    """`scene` with parameters set: coefficients in mm^-1 (RGB or one number), `g`, `eta`,
    and light factors (the light's emission times the factor). `exposure` is not part of a
    scene and is ignored. A material's `g` is set before its `sigmap_s`
    (`sigma_s = sigmap_s / (1 - g)`)."""
    full = {canonical(scene, n): v for n, v in values.items()}
    mats = dict(scene.materials)
    order = {f: i for i, f in enumerate(("g", "sigma_a", "sigma_s", "sigmap_s", "eta"))}
    for name in sorted(full, key=lambda n: order.get(n.rpartition(".")[2], -1)):
        mat, _, field = name.rpartition(".")
        if mat in ("", "lights"):
            continue
        m = mats[mat].medium
        kw = dict(sigma_a=m.sigma_a, sigma_s=m.sigma_s, g=m.g, eta=m.eta)
        v = full[name]
        if field == "sigmap_s":
            kw["sigma_s"] = np.asarray(v) / (1.0 - np.asarray(kw["g"]))
        else:
            kw[field] = v
        mats[mat] = dataclasses.replace(mats[mat], medium=Medium(**kw))
    lights = list(scene.lights)
    for name, v in full.items():
        if name.startswith("lights."):
            i = int(name.removeprefix("lights."))
            lt = lights[i]
            lights[i] = dataclasses.replace(
                lt, **{lt.emission: np.asarray(getattr(lt, lt.emission)) * float(v)}
            )
    return scene.replace(materials=mats, lights=tuple(lights))
