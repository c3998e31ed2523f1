"""sssjax: a differentiable subsurface-scattering renderer in JAX.

Units: lengths in millimetres, scattering coefficients per millimetre, colour linear RGB.

Public API:

- `Medium`, `preset`, `preset_names`: scattering media and Jensen et al. 2001's measurements.
- `dipole`: the BSSRDF physics (Fresnel terms, `Rd`, `Rd_total`, `Sd`, single scattering).
- `load_scene`: a scene from a TOML file or a dict.
- `trace`, `shade`, `render`: the geometric pass, the differentiable pass, and both.
- `imageio`: `read_image` / `write_image` through OpenImageIO.
- `raytree`: every ray the renderer casts for one pixel (`RayTree`).
- `fit`: recover `sigma_a`, `sigma_s` from a target image (trace once, shade per step).
- `enable_cache`, `disable_cache`, `cache_dir`: the persistent compilation cache, on from
  import (see `sssjax._cache`; `SSSJAX_CACHE_DIR` moves it, `SSSJAX_CACHE_DIR=off` stops it).
"""

from . import _cache, dipole, imageio
from ._cache import cache_dir, disable_cache, enable_cache
from ._version import __version__
from .fit import FitResult, fit
from .media import PRESETS, Medium, preset, preset_names
from .raytree import RayTree, raytree
from .render import render
from .scene import Scene, SceneError, load_scene
from .shade import shade, shade_image
from .trace import Transport, trace

__all__ = [
    "__version__",
    "Medium",
    "PRESETS",
    "preset",
    "preset_names",
    "dipole",
    "imageio",
    "Scene",
    "SceneError",
    "load_scene",
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
