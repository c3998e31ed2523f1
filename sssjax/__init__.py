"""sssjax: a differentiable subsurface-scattering renderer in JAX.

Units: lengths in millimetres, scattering coefficients per millimetre, colour linear RGB.

Public API:

- `Medium`, `preset`, `preset_names`: scattering media and Jensen et al. 2001's measurements.
- `scattering`: Fresnel terms and moments, refraction, the HG phase function.
- `dipole`, `profiles`: the dipole BSSRDF (`Rd`, `Rd_total`, `Sd`, single scattering) and the
  diffusion profiles by name.
- `load_scene`, `dump_scene` (`Scene.to_toml`): scene files read and written; `SceneArrays`: a
  scene as arrays, the argument of the transports.
- `trace`, `shade`, `render`: the geometric pass (a `Transport`), the differentiable pass,
  and both; `transport` / `TRANSPORTS`: the transports and their interface.
- `params`: the parameter map (names, values, how each enters the image).
- `fit`: recover `sigma_a`, `sigma_s` (...) from a target image (trace once, shade per step).
- `imageio`: `read_image` / `write_image` through OpenImageIO.
- `raytree`: every ray the renderer casts for one pixel (`RayTree`).
- `enable_cache`, `disable_cache`, `cache_dir`: the persistent compilation cache, on from
  import (see `sssjax._cache`; `SSSJAX_CACHE_DIR` moves it, `SSSJAX_CACHE_DIR=off` stops it).
"""

from . import _cache, dipole, imageio, params, profiles, scattering, transport
from ._arrays import MaterialKind, SceneArrays
from ._cache import cache_dir, disable_cache, enable_cache
from ._version import __version__
from .fit import FitResult, fit
from .media import PRESETS, Medium, preset, preset_names
from .raytree import RayTree, raytree
from .render import render, trace
from .scene import Scene, SceneError, dump_scene, load_scene
from .shade import shade, shade_image
from .transport import TRANSPORTS, Transport

__all__ = [
    "__version__",
    "Medium",
    "PRESETS",
    "preset",
    "preset_names",
    "dipole",
    "profiles",
    "params",
    "scattering",
    "transport",
    "imageio",
    "Scene",
    "SceneError",
    "load_scene",
    "dump_scene",
    "SceneArrays",
    "MaterialKind",
    "TRANSPORTS",
    "trace",
    "shade",
    "shade_image",
    "render",
    "raytree",
    "RayTree",
    "Transport",
    "fit",
    "FitResult",
    "enable_cache",
    "disable_cache",
    "cache_dir",
]

# last, so that nothing compiled during the imports above is in the cache's way
_cache.enable_cache()
