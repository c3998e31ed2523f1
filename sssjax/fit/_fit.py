"""`fit`: recover scattering coefficients from an image."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from ..scene import Scene
from ._options import FitOptions
from ._problem import FitProblem
from ._report import report
from ._result import FitResult
from ._solve import run

__all__ = ["fit"]


def fit(
    scene: Scene,
    target,
    *,
    params: Sequence[str] | None = None,
    init: dict[str, Any] | None = None,
    mask=None,
    seed=None,
    progress: bool = False,
    options: FitOptions | None = None,
    **option_values: Any,
) -> FitResult:
    """Recover scattering coefficients of the scene's translucent materials from `target`.

    Traces the scene once (per free light, per trace) and runs a least-squares solver on the
    pixel residuals of the shading, in the log of the coefficients, with forward-mode
    Jacobians; every iteration only re-shades (a free `eta` is searched over re-traces).

    **Arguments:**

    - `scene`: the scene the target was taken in (camera, lights, geometry).
    - `target`: `(H, W, 3)` linear radiance, or an image path (EXR/PNG/TIFF).
    - `params`: free parameters by name (`sssjax.params`): `"MATERIAL.FIELD"` with FIELD in
      `sigma_a`, `sigma_s`, `sigmap_s` (each RGB, mm^-1), `g` (the Henyey-Greenstein mean
      cosine, RGB; the diffusion term sees only `sigmap_s = sigma_s (1 - g)`, so `g` is
      separated from `sigma_s` by single scattering alone), `eta` (re-traced; bounded Brent
      search over `eta_init +- 0.3`; not with the volumetric transport, which cannot
      re-weight it, nor `g`), the material omitted when there is only one;
      `"exposure"`: one overall factor on the rendered image (an uncalibrated camera or
      light); `"lights.N"`: a factor on the emission of the scene's `N`-th light (0-based, in
      `[[lights]]` order), for lamps of unknown relative power. Each free light costs one
      more trace (the image is linear in each light's emission, so the fit traces each free
      light alone and shades their sum); with every light free, the exposure must be fixed.
      Default: `sigma_a` and `sigma_s` of every translucent material.
    - `init`: starting values by parameter name (RGB, mm^-1, > 0; `g` in (-1, 1); factors
      > 0); default: the scene's (exposure and light factors 1).
    - `mask`: `(H, W)` boolean pixels to fit; default: every pixel that sees a translucent
      object (the only pixels the coefficients affect) except highlights, pixels whose
      radiance is mostly coefficient-independent (a lamp's or a bright floor's mirror
      reflection), grown by one pixel: their jittered edges differ between traces by
      hundreds of times the subsurface signal. `result.highlight_pixels` counts them.
    - `seed`: trace seed (default the scene's).
    - `progress`: one line per solver step on stderr.
    - `options`, `option_values`: a `FitOptions` and/or its fields by name (`solver`,
      `max_steps`, `rtol`, `atol`, `loss`, `loss_scale`, `weighting`, `rel_floor`,
      `traces`, `refine`), where the defaults and their meaning live.

    **Returns:** a `FitResult`. A fit that fails to converge says so in `status`/`message`.
    """
    t_start = time.perf_counter()
    opts = FitOptions.of(options, **option_values)
    problem = FitProblem.build(scene, target, params, init, mask, seed, opts, progress)
    return report(problem, run(problem), t_start)
