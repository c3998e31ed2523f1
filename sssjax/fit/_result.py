"""What a fit found (`FitResult`) and its bad-input error (`FitError`)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from .. import params as _params
from .._files import write_text
from ..media import Medium
from ..scene import Scene

__all__ = ["FitError", "FitResult"]


class FitError(ValueError):
    """Bad fit input (target, mask, parameters, initial guess): a one-line message."""


@dataclasses.dataclass
class FitResult:
    """What a fit found and how sure it is.

    `values`, `stderr`: per parameter name (`"marble.sigma_a.R"`), in mm^-1.
    `correlation`: parameter correlation matrix (order of `names`).
    `loss_initial`, `loss_final`: `0.5 sum r^2` at the start and the solution, on the last
    trace; for a re-weighting (volumetric) fit `0.5 sum r_A r_B` of its two halves, which
    carries no model variance, on the first round's trace (at the start) and on the last
    (at the solution).
    `history`: per step `{"step", "loss", "params"}`; a volumetric fit's entries are the
    points its rounds traced, then the solution (`"root": True`, the pooled rounds' root).
    """

    names: list[str]
    values: dict[str, float]
    stderr: dict[str, float]
    initial: dict[str, float]
    correlation: list[list[float]]
    media: dict[str, Medium]
    steps: int
    loss_initial: float
    loss_final: float
    status: str
    message: str
    converged: bool
    wall_time_s: float
    trace_time_s: float
    history: list[dict[str, Any]]
    warnings: list[str]
    trace_stderr: dict[str, float] | None = None  # from `refine`: the trace-noise part
    # with `eta` free: every refractive index tried, with the loss of the fit there
    eta_search: list[dict[str, float]] | None = None
    pixels: int = 0  # pixels fitted (with several traces: the ones they all see)
    highlight_pixels: int = 0  # translucent pixels left out as highlights (no user mask)
    # re-weighting transports: the median over the fitted pixels and channels of the
    # effective sample size at the solution over its value at the trace's proposal
    sample_efficiency: float | None = None
    # `(H, W)` the highlight pixels left out (not in the JSON)
    highlights: np.ndarray | None = dataclasses.field(default=None, repr=False)

    @property
    def exposure(self) -> float:
        """The fitted exposure factor (1 when it was not free)."""
        return float(self.values.get("exposure", 1.0))

    def scene_values(self) -> dict[str, Any]:
        """What the fit found as scene parameters (`sssjax.params`): every fitted medium's
        coefficients, `g` and `eta`, and each free light's factor."""
        out: dict[str, Any] = {}
        for name, med in self.media.items():
            for f in ("sigma_a", "sigma_s", "g", "eta"):
                out[f"{name}.{f}"] = np.asarray(getattr(med, f))
        out.update({n: v for n, v in self.values.items() if n.startswith("lights.")})
        return out

    def apply(self, scene: Scene) -> Scene:
        """`scene` with what the fit found: the fitted media (their `eta` too) and each free
        light's emission scaled by its factor. `render(result.apply(scene)) * result.exposure`
        is the fitted image."""
        return _params.apply(scene, self.scene_values())

    def to_json(self, path: str | Path | None = None) -> str:
        """The result as JSON (media as coefficient lists); written to `path` if given."""
        d = dataclasses.asdict(self)
        d.pop("highlights")
        d["media"] = {
            n: {
                "sigma_a": np.asarray(m.sigma_a).tolist(),
                "sigma_s": np.asarray(m.sigma_s).tolist(),
                "sigmap_s": np.asarray(m.sigmap_s).tolist(),
                "g": np.asarray(m.g).tolist(),
                "eta": float(m.eta),
            }
            for n, m in self.media.items()
        }
        d["units"] = "coefficients in 1/mm"
        text = json.dumps(d, indent=2)
        if path is not None:
            write_text(path, text)  # atomic (sssjax/_files.py)
        return text

    def summary(self) -> str:
        lines = [f"{'parameter':<24} {'value':>10} {'std err':>10} {'initial':>10}"]
        for n in self.names:
            lines.append(
                f"{n:<24} {self.values[n]:10.5g} {self.stderr[n]:10.2g} {self.initial[n]:10.5g}"
            )
        lines.append(
            f"{self.steps} steps, loss {self.loss_initial:.4g} -> {self.loss_final:.4g}, "
            f"{self.status}: {self.message}"
        )
        if self.highlight_pixels:
            lines.append(
                f"{self.pixels} pixels fitted; {self.highlight_pixels} highlight pixels "
                "(mostly mirror-reflected light, independent of the coefficients) left out"
            )
        if self.sample_efficiency is not None:
            lines.append(
                f"re-weighting: effective sample size at the solution "
                f"{self.sample_efficiency:.0%} of the trace's (median pixel)"
            )
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)
