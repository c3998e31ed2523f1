"""A fit's report: error bars from the Gauss-Newton covariance at the solution (with the
heteroscedasticity-consistent sandwich, mapped from log space by the delta method), the
correlation matrix, the warnings, and the `FitResult`."""

from __future__ import annotations

import time

import equinox as eqx
import numpy as np

from ._problem import FitProblem, residual_args, residual_fn
from ._result import FitResult
from ._solve import UNDETERMINED_SD, Outcome, jacobian, loss_at

__all__ = ["report"]

_CH = "RGB"


def _eta_column(problem: FitProblem, out: Outcome, y) -> np.ndarray:
    """The Jacobian column of a free `eta`: central differences of re-traced residuals
    (same keys, so the same random numbers), the other parameters held at the solution."""
    args = out.run.args
    residuals = residual_fn(problem.layout, problem.options.loss)
    h = 2e-3
    cols = []
    for e in (out.eta + h, out.eta - h):
        d_e, m_e = problem.traced(out.keys, e)
        a_e = residual_args(d_e, m_e, problem.options.loss_scale, args.target.dtype)
        a_e = eqx.tree_at(lambda a: a.weights, a_e, args.weights)  # the final fit's weights
        cols.append(np.asarray(residuals(y, a_e), dtype=np.float64))
    return (cols[0] - cols[1]) / (2 * h)


def covariance(J: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """The covariance of the coordinates from the Jacobian `J` and residuals `r`:
    `s^2 (J^T J)^-1`, each variance raised to the sandwich estimate's where that is larger.
    **Returns:** `(cov, warnings)`; an infinite covariance when `J^T J` is singular."""
    warnings = []
    dof = max(r.size - J.shape[1], 1)
    s2 = float(r @ r) / dof
    JtJ = J.T @ J
    try:
        cond = np.linalg.cond(JtJ)
        inv = np.linalg.inv(JtJ)
        cov = s2 * inv
        # the pixels' noise is far from uniform (steep profile regions are noisier), and the
        # information sits in particular pixels: the heteroscedasticity-consistent
        # "sandwich" covariance (White 1980) is honest then; take the larger of the two
        cov_hc = inv @ ((J * (r**2 * r.size / dof)[:, None]).T @ J) @ inv  # HC1
        # a numerically singular J^T J can give a negative diagonal: no ratio there (the
        # parameter's error bar is then infinite, in `report`)
        d_log = np.diag(cov)
        ok = d_log > 0
        scale_hc = np.ones_like(d_log)
        scale_hc[ok] = np.sqrt(np.clip(np.diag(cov_hc)[ok], 0, None) / d_log[ok])
        scale_hc = np.maximum(np.nan_to_num(scale_hc, nan=1.0), 1.0)
        cov = cov * np.outer(scale_hc, scale_hc)
        if not np.isfinite(cond) or cond > 1e12:
            warnings.append(
                f"the covariance is near-singular (condition number {cond:.2g}): some "
                "parameters are not identifiable from this target; their errors are unreliable"
            )
    except np.linalg.LinAlgError:
        cov = np.full((J.shape[1], J.shape[1]), np.inf)
        warnings.append("J^T J is singular: the parameters are not identifiable from this target")
    return cov, warnings


def _identifiability(problem: FitProblem, names, corr) -> list[str]:
    """Warnings about parameters the image cannot separate."""
    warnings = []
    free = problem.layout.free
    fields = {f for _, f in free}
    ss_on = problem.scene.sss.single_scattering
    # only the diffusion term reduces sigma_s to sigmap_s (a volumetric walk sees sigma_s and
    # g apart), and only where g != 0 is that a loss
    media = problem.scene.media()
    forward = sorted(m for m, f in free if f == "sigma_s" and float(np.max(np.abs(media[m].g))) > 0)
    if not problem.reweighted and forward and not ss_on:
        warnings.append(
            f"{', '.join(forward)}: sigma_s is free but single scattering is off: the dipole "
            "sees only sigmap_s = sigma_s (1 - g)"
        )
    for mat in {m for m, _ in free}:
        if (mat, "g") in free and ((mat, "sigma_s") in free or (mat, "sigmap_s") in free):
            other = "sigma_s" if (mat, "sigma_s") in free else "sigmap_s"
            idx = {n: i for i, n in enumerate(names)}
            rho = max(abs(corr[idx[f"{mat}.g.{c}"], idx[f"{mat}.{other}.{c}"]]) for c in _CH)
            if not ss_on or not np.isfinite(rho) or rho > 0.95:
                why = "is off" if not ss_on else "is too weak"
                warnings.append(
                    f"{mat}: g and {other} are both free, but the diffusion term sees only "
                    f"sigmap_s = sigma_s (1 - g) and single scattering {why} to separate "
                    f"them (correlation up to {rho:.3f}): fix g, or fit sigmap_s alone"
                )
    if problem.layout.exposure and "sigma_a" in fields:
        warnings.append(
            "exposure is free: the absolute level no longer pins the albedo, so sigma_a rests "
            "on the shape of the image alone (see its error bar)"
        )
    return warnings


def _fit_quality(problem: FitProblem, out: Outcome, names, tanh_idx, sd_log, r) -> list[str]:
    """Warnings about how the fit went: no convergence far from the start, an `eta` at the
    edge of its search, parameters left undetermined, a loss carried by a few pixels."""
    warnings = []
    run = out.run
    if out.eta is not None and min(abs(out.eta - b) for b in out.eta_bounds) < 1e-3:
        lo, hi = out.eta_bounds
        warnings.append(
            f"{problem.eta.name} = {out.eta:.4f} is at the edge of the searched range "
            f"{lo:.3f}..{hi:.3f}: start nearer, or fix eta"
        )
    sss = problem.scene.sss
    if out.eta is not None and sss.profile == "tabulated" and sss.transport == "diffusion":
        from .._tabulated import eta_outside

        if note := eta_outside(out.eta):  # the search may leave the table (eta_init +- 0.3)
            warnings.append(f"{problem.eta.name} = {note}; fix eta, or use another profile")
    if not run.converged:
        moved = np.abs(np.asarray(run.y - problem.y0, dtype=np.float64)) > np.log(10.0)
        far = [n for n, m, t in zip(names, moved, tanh_idx, strict=False) if m and not t]
        if far:
            warnings.append(
                f"no convergence, and {', '.join(far)} moved more than 10x from the start: "
                "the minimum may lie at the edge (e.g. sigma_a -> 0 when the target is "
                "brighter than the scene allows); check the target's exposure and outliers "
                "(loss='cauchy', or free the exposure)"
            )
    vague = [
        n
        for n, sd in zip(names, sd_log, strict=True)
        if not sd < UNDETERMINED_SD and n != "exposure"
    ]
    if vague:
        warnings.append(
            f"{', '.join(vague)}: not determined by this target (error bar beyond +-50%): "
            "fix them, or use a measurement that constrains them"
        )
    # a loss carried by a handful of pixels is an outlier fit, not a measurement
    r2 = np.sort(r**2)[::-1]
    n_top = max(1, r.size // 1000)
    share = float(r2[:n_top].sum() / max(r2.sum(), 1e-300))
    if share > 0.5 and r.size >= 1000:
        warnings.append(
            f"{share:.0%} of the loss comes from {n_top} of {r.size} residuals: outliers "
            "(highlights, dust, saturated pixels); mask them, or use loss='cauchy'"
        )
    return warnings


def _sample_efficiency(problem: FitProblem, out: Outcome, y) -> float | None:
    """A re-weighting transport's median (fitted pixels, channels) effective sample size at
    the solution, over its value at the proposal; None for the other transports."""
    terms = out.data[0].terms[0]
    layout = problem.layout
    media = layout.media(y[: 3 * len(layout.free)], out.run.args.media0)
    eff = terms.sample_efficiency(media)
    if eff is None:
        return None
    eff = np.asarray(eff, dtype=np.float64)
    eff = eff[eff > 0]
    return float(np.median(eff)) if eff.size else None


def report(problem: FitProblem, out: Outcome, t_start: float) -> FitResult:
    """The `FitResult` of a fit's outcome."""
    run = out.run
    y = run.y
    names, tanh_idx = problem.names, problem.tanh_idx
    J, r = jacobian(problem, y, run.args)
    J, r = np.asarray(J, dtype=np.float64), np.asarray(r, dtype=np.float64)
    if out.eta is not None:
        J = np.concatenate([J, _eta_column(problem, out, y)[:, None]], axis=1)
        names = names + [problem.eta.name]
        tanh_idx = np.append(tanh_idx, False)
    cov_log, warnings = covariance(J, r)
    if out.cov_log is not None:
        # the rounds' pooled sandwich (target and trace noise) replaces the last trace's
        # `J^T J`, which the walks' derivative noise inflates; a free eta keeps its own
        # row and column (re-traced central differences)
        k = out.cov_log.shape[0]
        cov_log[:k, :k] = out.cov_log
    vals = problem.values(y)
    # d value / d y: value for log coordinates, 1 - g^2 for atanh
    dval = np.where(tanh_idx[: y.size], 1.0 - vals**2, vals)
    if out.eta is not None:  # eta is its own coordinate
        vals, dval = np.append(vals, out.eta), np.append(dval, 1.0)
    diag = np.diag(cov_log)
    # a negative variance is a numerically singular J^T J: that parameter is not determined
    sd_log = np.where(diag >= 0, np.sqrt(np.abs(diag)), np.inf)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_log / np.outer(sd_log, sd_log)
    trace_stderr = None
    if out.trace_sd is not None:
        trace_sd = out.trace_sd
        if out.eta is not None:
            trace_sd = np.append(trace_sd, 0.0)  # refine re-fits the others at eta*
        trace_stderr = dict(zip(names, (dval * trace_sd).tolist(), strict=True))
        if out.cov_log is None:  # refine's trace noise comes on top of the statistical
            stat_sd = np.sqrt(np.abs(np.diag(cov_log)))
            sd_log = np.sqrt(sd_log**2 + trace_sd**2)
        else:  # the rounds' covariance holds both
            stat_sd = np.append(out.target_sd, np.sqrt(np.abs(diag[out.target_sd.size :])))
        ratio = np.max(trace_sd / np.maximum(stat_sd, 1e-300))
        if ratio > 2:
            warnings.append(
                f"trace noise dominates the error (up to {ratio:.0f}x the statistical "
                "error): use more traces, a larger cloud_size or more spp"
            )
    efficiency = _sample_efficiency(problem, out, y)
    if efficiency is not None and efficiency < 0.5:
        warnings.append(
            f"the re-weighting's effective sample size fell to {efficiency:.0%} of the "
            "trace's: the error bars understate the trace noise; raise proposal_rounds"
        )
    if problem.reweighted and not run.converged:
        # the pooled covariance is that of the rounds' root: rounds still moving beyond
        # their errors (or still shortening steps) have not reached it, and the distance
        # left is not in the bars
        warnings.append(
            "the re-traced rounds did not settle (still moving or still approaching their "
            "root): read the error bars as lower bounds; raise proposal_rounds or spp"
        )
    warnings += _identifiability(problem, names, corr)
    warnings += _fit_quality(problem, out, names, tanh_idx, sd_log, r)
    # an unidentified parameter has an infinite error bar (not 0 x inf = nan)
    stderr = np.where(np.isfinite(sd_log), dval * np.where(np.isfinite(sd_log), sd_log, 0), np.inf)
    dec = problem.reweighted  # the loss without the model's variance
    # a re-weighted fit: the first round's, traced at the start itself (the last trace
    # re-weighted that far from its proposal is noisier)
    steps = run.steps
    loss_initial = run.loss0 if dec else loss_at(problem, problem.y0, run.args)
    if out.eta is not None:
        steps += sum(t["steps"] for t in out.eta_search)
        loss_initial = out.eta_loss0  # at the initial eta, not the fitted one
    hl = None if problem.mask is not None else out.data[0].left_out(problem.target.shape[:2])
    layout = problem.layout
    fitted = layout.media(y[: 3 * len(layout.free)], run.args.media0)
    initial = problem.values(problem.y0).tolist()
    if out.eta is not None:
        initial.append(problem.start[problem.eta.name])
    return FitResult(
        names=names,
        values=dict(zip(names, vals.tolist(), strict=True)),
        stderr=dict(zip(names, stderr.tolist(), strict=True)),
        initial=dict(zip(names, initial, strict=True)),
        correlation=np.nan_to_num(corr).tolist(),
        media=dict(zip(layout.order, fitted, strict=True)),
        steps=steps,
        loss_initial=loss_initial,
        loss_final=loss_at(problem, y, run.args, dec),
        status=run.status,
        message=run.message,
        converged=bool(run.converged),
        wall_time_s=time.perf_counter() - t_start,
        trace_time_s=problem.trace_time,
        history=run.history,
        warnings=warnings,
        trace_stderr=trace_stderr,
        eta_search=out.eta_search,
        pixels=int(run.args.target.shape[0]),  # the pixels all traces share
        highlight_pixels=0 if hl is None else int(hl.sum()),
        highlights=hl,
        sample_efficiency=efficiency,
    )
