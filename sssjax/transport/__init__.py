"""Light transports: how a scene's arrays become radiance and media-dependent terms.

- `TRANSPORTS`: the transports by name, the scene's `[sss] transport` (`"diffusion"`; the
  entries are imported when first used, so the scene loader can check a name cheaply).
- The interface (`_base.py`): `TransportMethod` (one scene's transport), `Block` (what it
  traces for a block of pixels), `Transport` (the result of `sssjax.trace`), and the
  protocol of its media-dependent `Terms` and their `Prepared` form, used by `shade` and
  `fit`.
- `Recorder` / `NO_RECORD`: the ray-tree hooks every transport function takes.
- `STRATEGIES`: the diffusion transport's dipole gather strategies (`[sss] strategy`).

The diffusion transport (`sssjax.transport.diffusion`) is made of one module per term:
`chains` (camera rays, specular chains), `cloud` (irradiance cloud and beam points),
`gather` (the profile gather on distance nodes: cloud, beams, per-pixel strategies) and
`single` (single scattering).
"""

from .._registry import Registry
from ._base import Block, Prepared, Terms, Transport, TransportMethod
from ._record import NO_RECORD, Recorder
from ._strategies import STRATEGIES, Strategy

__all__ = [
    "TRANSPORTS",
    "STRATEGIES",
    "Strategy",
    "TransportMethod",
    "Block",
    "Transport",
    "Terms",
    "Prepared",
    "Recorder",
    "NO_RECORD",
]

TRANSPORTS = Registry(
    "transport",
    {
        "diffusion": "sssjax.transport.diffusion:Diffusion",
        "volumetric": "sssjax.transport.volumetric:Volumetric",
    },
)
