"""sssjax: a differentiable subsurface-scattering renderer in JAX.

Units: lengths in millimetres, scattering coefficients per millimetre, colour linear RGB.

Public API:

- `Medium`, `preset`, `preset_names`: scattering media and Jensen et al. 2001's measurements.
- `dipole`: the BSSRDF physics (Fresnel terms, `Rd`, `Rd_total`, `Sd`, single scattering).
"""

from . import dipole
from ._version import __version__
from .media import PRESETS, Medium, preset, preset_names

__all__ = ["__version__", "Medium", "PRESETS", "preset", "preset_names", "dipole"]
