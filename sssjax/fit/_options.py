"""A fit's options with their defaults (`FitOptions`, used by `fit` and by fit files), and
the registries of its choices: `SOLVERS`, `LOSSES`, `WEIGHTINGS`."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._numerics import safe_sqrt
from .._registry import Registry, did_you_mean
from .._solvers import NormalGaussNewton, NormalLevenbergMarquardt
from ._result import FitError

__all__ = ["FitOptions", "SOLVERS", "LOSSES", "WEIGHTINGS", "Solver", "Weighting"]


@dataclass(frozen=True)
class Solver:
    """A least-squares solver: `make(rtol, atol)` builds it; `scalar` solvers minimise the
    loss `0.5 sum r^2` instead of taking residuals; `options` go to optimistix."""

    make: Callable
    scalar: bool = False
    options: tuple = (("jac", "fwd"),)


# The LM and GN solvers keep only the `n x n` normal equations in their state
# (`sssjax/_solvers.py`): optimistix's stock ones keep the residual function's linearisation,
# which closes over the whole transport.
SOLVERS = Registry(
    "solver",
    {
        "lm": Solver(NormalLevenbergMarquardt),
        "gn": Solver(NormalGaussNewton),
        "bfgs": Solver(optx.BFGS, scalar=True, options=()),
    },
)


# Robust losses as residual transforms r -> sign(r) sqrt(2 rho(r)) at scale c: least squares
# on the transformed residuals minimises sum rho(r).
def _cauchy(r, c):
    return jnp.sign(r) * c * safe_sqrt(jnp.log1p((r / c) ** 2))


def _huber(r, c):
    a = jnp.abs(r)
    return jnp.where(a <= c, r, jnp.sign(r) * safe_sqrt(2 * c * a - c**2))


LOSSES = Registry("loss", {"l2": lambda r, c: r, "cauchy": _cauchy, "huber": _huber})


@dataclass(frozen=True)
class Weighting:
    """Per-pixel residual weights from a level (the target's value, or the model's, in units
    of the target's mean): `weights(level, rel_floor)` or None for unit weights. `refit`:
    after a fit with the target's weights, fit again with the model's (which do not share
    the target's noise)."""

    weights: Callable | None = None
    refit: bool = False


# a re-weighting transport's rounds: where their estimating equation's instruments come from
# (`sssjax.fit._solve.RoundLinearisation`)
INSTRUMENTS = Registry(
    "instruments",
    {
        "diffusion": "the diffusion transport's exact Jacobian of the same scene",
        "smoothed": "the walks' own Jacobian, smoothed over the image",
    },
)

WEIGHTINGS = Registry(
    "weighting",
    {
        "absolute": Weighting(),
        "relative": Weighting(lambda level, floor: 1.0 / (np.abs(level) + floor), refit=True),
    },
)


@dataclass(frozen=True)
class FitOptions:
    """How a fit runs (the defaults of `fit` and of a fit file's `[solver]` table).

    - `solver`: `"lm"` (Levenberg-Marquardt), `"gn"` (Gauss-Newton) or `"bfgs"` (on the
      scalar loss); `max_steps`, `rtol`, `atol` its limits.
    - `loss`: `"l2"`, or a robust `"cauchy"` / `"huber"` for photographs with outliers
      (specular highlights, dust); `loss_scale` is their transition, in units of the
      (weighted) residual. Error bars then come from the transformed residuals.
    - `weighting`: `"absolute"` residuals in units of the target's mean level, or
      `"relative"`: each pixel's residual divided by its target value (plus `rel_floor`
      times the mean level), for targets spanning decades such as a beam-lit slab, where
      absolute residuals let the brightest pixels decide everything.
    - `traces`: number of independent traces averaged into the fitted model: one trace with
      K times the samples. A trace's noise is shared by all its pixels, and a least-squares
      fit leans toward coefficients whose image is less noisy, so a single trace biases the
      fit by more than its per-pixel error bars say; K traces cut that noise by K, at K times
      the trace time (the per-iteration cost barely grows).
    - `refine`: after the fit, trace again with a fresh seed, fit that trace alone from the
      solution, then fit the average of both. The final values are the joint fit; the
      difference between the two single-trace fits measures the trace noise, reported in
      `trace_stderr` and added (in quadrature) to `stderr`.
    - `proposal_rounds`, `proposal_tol`: with a re-weighting transport (`volumetric`), how
      many times at most the fit re-traces with its solution as the walks' proposal (at
      least 1 there), and the floor (relative, in every coefficient) on the error within
      which the solution counts as at the rounds' root: it stops early there.
    - `instruments`: with a re-weighting transport, what the rounds' estimating equation
      weighs each pixel's residual by: `"diffusion"` (default), the diffusion transport's
      exact Jacobian of the same scene, free of the walks' noise; or `"smoothed"`, the
      walks' own Jacobian smoothed over 1.5 pixels (noisy at a few spp; for scenes whose
      diffusion image does not depend on a fitted coefficient). Either keeps the fit's
      root unbiased; the better they match the exact Jacobian, the faster and tighter.
    """

    solver: str = "lm"
    max_steps: int = 50
    rtol: float = 1e-5
    atol: float = 1e-6
    loss: str = "l2"
    loss_scale: float = 0.1
    weighting: str = "absolute"
    rel_floor: float = 0.01
    traces: int = 1
    refine: bool = False
    proposal_rounds: int = 8
    proposal_tol: float = 0.02
    instruments: str = "diffusion"

    def __post_init__(self):
        if not (isinstance(self.traces, int) and self.traces >= 1):
            raise FitError(f"traces must be an integer >= 1, got {self.traces!r}")
        if not (isinstance(self.proposal_rounds, int) and self.proposal_rounds >= 0):
            raise FitError(f"proposal_rounds must be an integer >= 0, got {self.proposal_rounds!r}")
        if not self.proposal_tol > 0:
            raise FitError(f"proposal_tol must be > 0, got {self.proposal_tol}")
        LOSSES.check(self.loss, FitError)
        if not self.loss_scale > 0:
            raise FitError(f"loss_scale must be > 0, got {self.loss_scale}")
        WEIGHTINGS.check(self.weighting, FitError)
        if not self.rel_floor > 0:
            raise FitError(f"rel_floor must be > 0, got {self.rel_floor}")
        SOLVERS.check(self.solver, FitError)
        INSTRUMENTS.check(self.instruments, FitError)

    @classmethod
    def of(cls, options: FitOptions | None = None, **values: Any) -> FitOptions:
        """`options` (default: the defaults) with some fields replaced; an unknown name is a
        `FitError` with a did-you-mean hint."""
        known = [f.name for f in dataclasses.fields(cls)]
        for k in values:
            if k not in known:
                hint = did_you_mean(k, known)
                raise FitError(f"unknown fit option {k!r}{hint} (known: {', '.join(known)})")
        return dataclasses.replace(options or cls(), **values)
