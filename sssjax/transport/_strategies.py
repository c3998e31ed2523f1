"""The dipole gather strategies (`[sss] strategy`): the irradiance cloud, or per-pixel Monte
Carlo surface samples restricted to a region around `x_o` (the original report's choices).
Adding one is one entry here; `sssjax.transport.gather` evaluates them."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import jax.numpy as jnp

from .._registry import Registry

__all__ = ["Strategy", "STRATEGIES"]


@dataclass(frozen=True)
class Strategy:
    """How dipole source points are chosen.

    - `per_pixel`: False for the shared irradiance cloud, True for Monte Carlo samples drawn
      per camera sample (each with its own shadow-tested irradiance).
    - `region(r, sss)`: which candidates at distance `r` (mm) from `x_o` count (per-pixel).
    - `tries(sss)`: candidates drawn per sample slot (the first inside the region is kept).
    - `check(sss)`: `(field, message)` when the scene's `[sss]` settings do not suit the
      strategy, else None.
    """

    per_pixel: bool
    region: Callable | None = None
    tries: Callable = lambda sss: sss.tries
    check: Callable = lambda sss: None


def _within_check(sss):
    if sss.radius <= 0:
        return "radius", "strategy 'within' needs radius > 0 (mm)"
    return None


def _annulus_check(sss):
    if not 0 <= sss.inner < sss.outer:
        msg = "strategy 'annulus' needs 0 <= inner < outer, got "
        return "outer", msg + f"inner={sss.inner:g}, outer={sss.outer:g}"
    return None


STRATEGIES = Registry(
    "strategy",
    {
        "cloud": Strategy(per_pixel=False),
        "uniform": Strategy(True, lambda r, sss: jnp.ones(r.shape, bool), lambda sss: 1),
        "within": Strategy(True, lambda r, sss: r < sss.radius, check=_within_check),
        "annulus": Strategy(
            True, lambda r, sss: (r >= sss.inner) & (r < sss.outer), check=_annulus_check
        ),
    },
)
