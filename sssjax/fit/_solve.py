"""The solver loop of a fit (`solve`) and its phases (`run`): a free `eta` searched by Brent
over re-traces, relative weights refitted at the model, `refine` with a fresh trace."""

from __future__ import annotations

import dataclasses
import functools
import sys
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._progress import Progress
from ._options import SOLVERS, WEIGHTINGS
from ._problem import ETA_RANGE, Args, FitProblem, TraceData, residual_fn
from ._result import FitError

__all__ = ["Run", "Outcome", "solve", "run", "loss_at", "jacobian"]


@dataclasses.dataclass
class Run:
    """One solver run: the solution `y`, its `args`, steps, the loss at the start, the
    history (loss and values per step) and how it ended."""

    y: Any
    args: Args
    steps: int
    loss0: float
    history: list
    converged: bool
    status: str
    message: str


@functools.lru_cache(maxsize=32)
def _solver_fn(layout, scalar: bool, loss: str = "l2"):
    residuals = residual_fn(layout, loss)
    if scalar:
        return lambda y, args: (0.5 * jnp.sum(residuals(y, args) ** 2), None)
    return lambda y, args: (residuals(y, args), None)


@eqx.filter_jit
def _loss(residuals, y, args):
    return 0.5 * jnp.sum(residuals(y, args) ** 2)


def _floored_inverse(H):
    """`H^-1` with `|eigenvalues|` floored: a cross-product Hessian is unbiased but noisy,
    and directions a trace cannot tell apart may come out with small or negative curvature."""
    lam, V = jnp.linalg.eigh(0.5 * (H + H.T))
    lam = jnp.maximum(jnp.abs(lam), 1e-6 * jnp.max(jnp.abs(lam)))
    return (V / lam) @ V.T


# the floor on the cross curvature's share of the one-trace curvature (`_decorrelated_step`)
MIN_CURVATURE_SHARE = 0.3


@eqx.filter_jit
def _decorrelated_step(residuals, y, args):
    """The Gauss-Newton step of `0.5 sum r_A r_B` at `y`, from the residuals of two
    independent halves of the samples (`residual_fn(decorrelated=True)`): gradient
    `(J_A^T r_B + J_B^T r_A) / 2`, unbiased for the noise-free one.

    The curvature: the cross product `H_x = (J_A^T J_B + J_B^T J_A) / 2` is unbiased for the
    noise-free `J^T J` but noisy, while the whole trace's `H = Jbar^T Jbar` adds the
    Jacobian's own variance (too much curvature: short steps). In the directions of their
    generalized eigenvectors, `H_x = mu H`, `mu` the share of `H` that is signal; measured on
    a thick slab under the beam (32^2 px, 64-256 spp), three of six directions had `mu`
    0-0.15 (the `sigma_a` tails' long paths: heavy-tailed derivatives) and the plain cross
    step swung by up to 30 in log. So `mu` is floored at `MIN_CURVATURE_SHARE`: full steps
    where the trace resolves the curvature, at most `1 / MIN_CURVATURE_SHARE` times the
    one-trace step where it does not. **Returns:** the step, the coordinates' standard
    errors (from `H`, divided by `sqrt(mu)`, floored) and the plain loss of the whole."""

    def res(yy):
        r = residuals(yy, args)
        return r, r

    J, r = jax.jacfwd(res, has_aux=True)(y)  # (2, m, n), (2, m)
    Ja, Jb, ra, rb = J[0], J[1], r[0], r[1]
    rbar = 0.5 * (ra + rb)  # the residuals of the whole (the halves' mean)
    Jbar = 0.5 * (Ja + Jb)
    Hx = 0.5 * (Ja.T @ Jb + Jb.T @ Ja)
    H = Jbar.T @ Jbar
    n = H.shape[0]
    # H = C C^T; mu, V: the eigen-decomposition of C^-1 H_x C^-T
    C = jnp.linalg.cholesky(H + 1e-9 * jnp.trace(H) / n * jnp.eye(n, dtype=H.dtype))
    Ci = jax.scipy.linalg.solve_triangular(C, jnp.eye(n, dtype=H.dtype), lower=True)
    M = Ci @ Hx @ Ci.T
    mu, V = jnp.linalg.eigh(0.5 * (M + M.T))
    mu = jnp.maximum(mu, MIN_CURVATURE_SHARE)
    W = Ci.T @ V  # H_floored^-1 = W diag(1/mu) W^T
    grad = 0.5 * (Ja.T @ rb + Jb.T @ ra)
    dy = -(W / mu) @ (W.T @ grad)
    m = rbar.size
    s2 = jnp.sum(rbar**2) / jnp.maximum(m - n, 1)
    cov = s2 * (W / mu) @ W.T
    return dy, jnp.sqrt(jnp.diag(cov)), 0.5 * jnp.sum(rbar**2)


@eqx.filter_jit
def _jac_res(residuals, y, args):
    return jax.jacfwd(residuals)(y, args), residuals(y, args)


@eqx.filter_jit
def _init(slv, fn, y0, args, options):
    f_struct, aux_struct = jax.eval_shape(lambda: fn(y0, args))
    return slv.init(fn, y0, args, options, f_struct, aux_struct, frozenset())


@eqx.filter_jit
def _step(slv, fn, y, args, options, state):
    y, state, _ = slv.step(fn, y, args, options, state, frozenset())
    done, res = slv.terminate(fn, y, args, options, state, frozenset())
    # the solver already evaluated the loss at the point it returns (its accepted point)
    return y, state, done, res, state.f_info.as_min()


def loss_at(problem: FitProblem, y, args: Args) -> float:
    """`0.5 sum r^2` of the (robust) residuals at `y`."""
    return float(_loss(residual_fn(problem.layout, problem.options.loss), y, args))


def jacobian(problem: FitProblem, y, args: Args):
    """The residuals' forward-mode Jacobian at `y` and the residuals."""
    return _jac_res(residual_fn(problem.layout, problem.options.loss), y, args)


def _progress_line(bar, step: int, loss: float, names: list[str], vals: np.ndarray) -> None:
    """A step on the bar (a terminal) or as a line of its own (a file or pipe)."""
    # the material name is dropped (one material in most fits); a light keeps its prefix
    short = [n if n.startswith("lights.") else n.split(".", 1)[-1] for n in names]
    shown = "  ".join(f"{n}={v:.4g}" for n, v in zip(short, vals, strict=True))
    bar.update(step, line=f"step {step:3d}  loss {loss:.6g}  {shown}", loss=loss)


def solve(
    problem: FitProblem, data: list[TraceData], media: dict, y0, weights_at=None, progress=None
) -> Run:
    """Run the solver on the traces in `data` (averaged) from `y0` (log parameters), the
    media held at `media` (by name). With relative weighting, each pixel's weight comes
    from the target's value, or the model's at `weights_at` when given."""
    opts = problem.options
    progress = problem.progress if progress is None else progress
    dt = jnp.float32 if jnp.asarray(y0).dtype == jnp.float32 else jnp.float64
    args = problem.args(data, media, dt, weights_at)
    layout, names = problem.layout, problem.names
    spec = SOLVERS[opts.solver]
    slv = spec.make(opts.rtol, opts.atol)
    options = dict(spec.options)
    fn = _solver_fn(layout, spec.scalar, opts.loss)
    residuals = residual_fn(layout, opts.loss)
    state = _init(slv, fn, y0, args, options)
    y = y0
    loss0 = float(_loss(residuals, y0, args))
    history = [{"step": 0, "loss": loss0, "params": problem.values(y0).tolist()}]
    bar = Progress(opts.max_steps, "fitting", progress, unit="steps", every_line=True)
    _progress_line(bar, 0, loss0, names, problem.values(y0))
    result = optx.RESULTS.max_steps_reached
    stalled = False
    n = 0
    for n in range(1, opts.max_steps + 1):
        y, state, done, res, lval = _step(slv, fn, y, args, options, state)
        lval = float(lval)
        history.append({"step": n, "loss": lval, "params": problem.values(y).tolist()})
        _progress_line(bar, n, lval, names, problem.values(y))
        if bool(done):
            result = res
            break
        # float32 shading puts a floor under the loss; optimistix's Cauchy test may keep
        # taking rejected LM steps there. Stop once the loss has stalled after progress
        # (or, when starting at the solution, has not moved for 8 steps).
        window = 4 if lval < 0.5 * loss0 else 8
        if n >= window - 1:
            recent = [h["loss"] for h in history[-window:]]
            if max(recent) - min(recent) <= opts.rtol * max(abs(v) for v in recent):
                result = optx.RESULTS.successful
                stalled = True
                break
    bar.close()
    converged = result == optx.RESULTS.successful
    if converged:
        status = "successful"
    else:
        status = "max_steps_reached" if result == optx.RESULTS.max_steps_reached else "failed"
    message = optx.RESULTS[result] if not converged else "converged"
    if stalled:
        message = "converged (loss unchanged to rtol over the last steps)"
    if not converged and not message:
        message = f"no convergence within {opts.max_steps} steps"
    return Run(y, args, n, loss0, history, converged, status, message)


@dataclasses.dataclass
class Outcome:
    """A fit's final run and what its phases found: the traces' keys and data, the `eta`
    search (`eta`, the values tried, the loss at the start, the bounds) and `refine`'s
    trace-noise estimate (half the difference of two single-trace solutions, log space)."""

    run: Run
    keys: list
    data: list[TraceData]
    eta: float | None = None
    eta_search: list | None = None
    eta_loss0: float | None = None
    eta_bounds: tuple | None = None
    trace_sd: np.ndarray | None = None


def search_eta(problem: FitProblem, keys, y0):
    """Minimise the profile loss `min_theta loss(theta; eta)` over the free material's
    refractive index by bounded Brent search. `eta` bends rays, so each value tried is a
    re-trace (same keys: the same random numbers, so the loss is smooth in eta) and a fit of
    the other parameters from the best so far, starting with the initial `eta` itself.
    Weights stay the target's throughout, so the losses compare. The search spans
    `eta_init +- 0.3` (within `ETA_RANGE`). **Returns:** `(eta*, [{eta, loss, steps}], y at
    eta*, the loss at y0 and eta_init, the bounds, the best value's (data, media))`."""
    from scipy.optimize import minimize_scalar

    name = problem.eta.name
    eta_init = problem.start[name]
    best = {"loss": np.inf, "y": y0}
    tried, first = [], {}

    def profile_loss(eta):
        data, media = problem.traced(keys, float(eta))
        run_ = solve(problem, data, media, best["y"], progress=False)
        first.setdefault("loss0", run_.loss0)
        loss_val = loss_at(problem, run_.y, run_.args)
        tried.append({"eta": float(eta), "loss": loss_val, "steps": run_.steps})
        if problem.progress:
            print(
                f"eta search: {name} = {eta:.5f}  loss {loss_val:.6g}  ({run_.steps} steps)",
                file=sys.stderr,
                flush=True,
            )
        if loss_val < best["loss"]:
            best.update(loss=loss_val, y=run_.y, eta=float(eta), traced=(data, media))
        return loss_val

    lo = max(ETA_RANGE[0] + 1e-3, eta_init - 0.3)
    hi = min(ETA_RANGE[1], eta_init + 0.3)
    profile_loss(eta_init)  # the loss at the start, and a warm start for the search
    minimize_scalar(profile_loss, bounds=(lo, hi), method="bounded", options={"xatol": 2e-4})
    return best["eta"], tried, best["y"], first["loss0"], (lo, hi), best["traced"]


def _rounds_sd(rounds: list) -> np.ndarray | None:
    """The trace-noise error of the rounds' solution (`_retraced_rounds`): each round is a
    solution on its own trace at nearly the same proposal, so their scatter is the trace
    noise (the target's own noise, shared by all, is in the statistical error). With four
    rounds or more the solution is the mean of the later half: the error of that mean."""
    if len(rounds) < 2:
        return None
    if len(rounds) < 4:
        return 0.5 * np.abs(rounds[-1] - rounds[-2])
    tail = np.asarray(rounds[len(rounds) // 2 :])
    return tail.std(axis=0, ddof=1) / np.sqrt(len(tail))


# a step's standard error (log coefficients) beyond which "within its error" means nothing
SETTLE_MAX_SD = 0.1


def _settled(dy, sd, tol: float) -> bool:
    """Whether a re-traced round's step `dy` (log coefficients) is within its noise: every
    component within `max(tol, sd)`, and every `sd` itself below `SETTLE_MAX_SD` (10 %): a
    step whose error is larger than that is no evidence of having settled (an undetermined
    coefficient would otherwise settle at once, anywhere)."""
    dy, sd = np.abs(np.asarray(dy)), np.asarray(sd)
    return bool(np.all(dy <= np.maximum(tol, sd)) and np.all(sd < SETTLE_MAX_SD))


# the re-weighting is trusted where the effective sample size keeps this share of the trace's
MIN_EFFICIENCY = 0.3
# the largest re-traced step (log coefficients): a shorter one when far from the solution
MAX_ROUND_STEP = 0.5


def channel_efficiency(problem: FitProblem, data: list[TraceData], media0, y) -> float:
    """A re-weighting transport's sample efficiency at `y` on the trace `data`: per colour
    channel, the median (over the rows with signal) of the effective sample size at `y`
    over its value at the trace's proposal; the smallest of the channels' (each channel is
    sampled with its own proposal, and one that has collapsed spoils its coefficients).
    1 for the other transports."""
    layout = problem.layout
    media = layout.media(jnp.asarray(y)[: 3 * len(layout.free)], media0)
    worst = 1.0
    for terms in data[0].terms:
        eff = terms.sample_efficiency(media)
        if eff is None:
            continue
        eff = np.asarray(eff, dtype=np.float64)
        for c in range(eff.shape[1]):
            col = eff[:, c][eff[:, c] > 0]
            if col.size:
                worst = min(worst, float(np.median(col)))
    return worst


def _trusted_step(problem, residuals, data, args, y, dy, loss):
    """The longest of `dy`, `dy / 2`, `dy / 4`, ... (first capped at `MAX_ROUND_STEP`) that
    stays where the trace's re-weighting is trusted (`channel_efficiency` at least
    `MIN_EFFICIENCY`) and does not raise the decorrelated loss `0.5 sum r_A r_B` of this
    trace (an unbiased estimate of the noise-free loss there): a Gauss-Newton step from far
    away overshoots, and a step past the trusted region lands on a re-weighting whose noise
    is larger than the step. **Returns:** the step taken and its fraction of `dy`."""
    big = np.max(np.abs(dy))
    t = min(1.0, MAX_ROUND_STEP / big) if big > 0 else 1.0
    for _ in range(8):
        cand = y + jnp.asarray(t * dy, y.dtype)
        if channel_efficiency(problem, data, args.media0, cand) >= MIN_EFFICIENCY:
            if float(_cross_loss(residuals, cand, args)) <= loss:
                return t * dy, t
        t *= 0.5
    return t * dy, t


@eqx.filter_jit
def _cross_loss(residuals, y, args):
    r = residuals(y, args)
    return 0.5 * jnp.sum(r[0] * r[1])


def _retraced_rounds(problem: FitProblem, keys, media, y, eta, refit: bool = False, history=()):
    """A re-weighting transport's fit: Gauss-Newton rounds, each on a fresh trace with the
    current solution as the walks' proposal.

    A least-squares fit to a noisy model leans toward the coefficients whose image is least
    noisy (the model's variance is part of `E |t - m|^2`; for a walk, larger `sigma_a`
    cuts the long, noisy paths), and re-weighting far from the proposal makes that noise
    larger still, so a free solve on one trace from a distant start lands far from the truth
    (measured on a thick slab: `sigma_s` 0.11 against 1.0 from a start at 0.7). Each round
    here takes one Gauss-Newton step of `0.5 sum r_A r_B` at the proposal (the residuals of
    two independent halves of the walks, whose expectation carries no model variance) with
    the exact re-weighting derivatives there, shortened until it stays where the trace's
    re-weighting is trusted and lowers that loss (`_trusted_step`), then re-traces where it
    lands with new random numbers, so no round can tune the solution to one trace's noise.
    With relative weighting (`refit`), each round's weights come from its model at the
    proposal (where the trace is exact). The rounds stop when two steps in a row are
    within their standard errors (or `proposal_tol`), or after `proposal_rounds`; the
    solution is the mean of the later half of the rounds' (from four rounds on), whose
    scatter is each trace's noise. **Returns:** `(data, run, rounds)`: the last trace, the
    run at the solution (its `args` from the last trace) and the solution of each round."""
    opts = problem.options
    names = problem.names
    dt = jnp.float32 if jnp.asarray(y).dtype == jnp.float32 else jnp.float64
    residuals = residual_fn(problem.layout, opts.loss, True)
    history, rounds = list(history), []
    loss0 = None
    bar = Progress(opts.proposal_rounds, "re-traced rounds", problem.progress, every_line=True)
    data, args, converged, settled = None, None, False, 0
    prev = None  # the previous round's trace: the relative weights' level, independent
    for k in range(opts.proposal_rounds):
        problem.proposal = problem.media_at(y, media)
        keys_k = [jax.random.fold_in(kk, 7_919 + k) for kk in keys]  # new random numbers
        if refit and prev is None:  # the first round's weights: one more trace
            prev, _ = problem.traced([jax.random.fold_in(kk, 104_729) for kk in keys], eta)
        data, _ = problem.traced(keys_k, eta)
        args = problem.args(data, media, dt, y if refit else None, prev if refit else None)
        prev = data
        if args.halves is None:
            raise FitError(
                "the traces cannot be split into independent halves (odd walkers per "
                "pixel): use an even spp"
            )
        dy, sd, loss = _decorrelated_step(residuals, y, args)
        dy = np.asarray(dy, np.float64)
        if not np.all(np.isfinite(dy)):
            raise FitError(
                "the re-traced Gauss-Newton step is not finite (a trace with no signal in "
                "the fitted pixels?): check the target and the mask"
            )
        if loss0 is None:
            loss0 = float(loss)
            history.append(
                {"step": len(history), "loss": loss0, "params": problem.values(y).tolist()}
            )
        dy, frac = _trusted_step(
            problem, residuals, data, args, y, dy, float(_cross_loss(residuals, y, args))
        )
        y = y + jnp.asarray(dy, y.dtype)
        rounds.append(np.asarray(y, np.float64))
        history.append(
            {"step": len(history), "loss": float(loss), "params": problem.values(y).tolist()}
        )
        _progress_line(bar, k + 1, float(loss), names, problem.values(y))
        settled = settled + 1 if frac == 1.0 and _settled(dy, sd, opts.proposal_tol) else 0
        if settled >= 2:  # two steps in a row within their noise
            converged = True
            break
    bar.close()
    if len(rounds) >= 4:
        # the rounds' solutions scatter by the trace noise of each: average the later half
        y = jnp.asarray(np.mean(rounds[len(rounds) // 2 :], axis=0), y.dtype)
    message = (
        "converged (the last re-traced step within its error)"
        if converged
        else (f"the re-traced steps did not settle within {opts.proposal_rounds} rounds")
    )
    run_ = Run(
        y,
        args,
        len(rounds),
        loss0,
        history,
        converged,
        "successful" if converged else "max_steps_reached",
        message,
    )
    return data, run_, rounds


def run(problem: FitProblem) -> Outcome:
    """Every phase of a fit: trace (searching a free `eta`), solve, move a re-weighting
    transport's proposal to the solution, refit relative weights at the model, and `refine` (a fresh trace fitted alone from the solution, then the average
    of both)."""
    keys = problem.trace_keys()
    y0 = problem.y0
    out = Outcome(run=None, keys=keys, data=[])
    if problem.eta is not None:
        eta, tried, y_start, loss0, bounds, (data, media) = search_eta(problem, keys, y0)
        out.eta, out.eta_search, out.eta_loss0, out.eta_bounds = eta, tried, loss0, bounds
    elif problem.reweighted:
        # no free solve on the first trace: far from its proposal, a re-weighted trace is
        # too noisy to be fitted (see `_retraced_rounds`), so the rounds start at y0
        refit = WEIGHTINGS[problem.options.weighting].refit
        media = dict(problem.scene.media())
        out.data, out.run, rounds = _retraced_rounds(problem, keys, media, y0, None, refit)
        out.trace_sd = _rounds_sd(rounds)
        return out
    else:
        (data, media), y_start = problem.traced(keys), y0
    r = solve(problem, data, media, y_start)
    refit = WEIGHTINGS[problem.options.weighting].refit
    if problem.reweighted:
        out.data, out.run, rounds = _retraced_rounds(
            problem, keys, media, r.y, out.eta, refit, r.history
        )
        out.run.steps += r.steps
        out.trace_sd = _rounds_sd(rounds)
        return out
    out.data = data
    if refit:
        # weights from the target's own noisy values favour pixels whose noise happens to be
        # low and so bias the fit (by about the pixels' relative variance); refit with
        # weights from the fitted model instead, which does not share the target's noise
        r = solve(problem, data, media, r.y, weights_at=r.y)
    if problem.options.refine:
        k_fresh = jax.random.fold_in(problem.key, 99_991)
        fresh = problem.traced([k_fresh], out.eta)[0][0]
        if problem.progress:
            print("refine: fit a fresh trace from the solution", file=sys.stderr, flush=True)
        w_at = r.y if refit else None
        other = solve(problem, [fresh], media, r.y, weights_at=w_at)
        if problem.progress:
            print("refine: fit the average of both traces", file=sys.stderr, flush=True)
        joint = solve(problem, data + [fresh], media, 0.5 * (r.y + other.y), weights_at=w_at)
        out.keys = keys + [k_fresh]
        # two single-trace solutions differ by trace noise alone (same target): their
        # half-difference estimates the trace-noise error of the joint (mean) solution
        out.trace_sd = 0.5 * np.abs(np.asarray(r.y - other.y, dtype=np.float64))
        joint.history = r.history + other.history + joint.history
        joint.steps = r.steps + other.steps + joint.steps
        r = joint
    out.run = r
    return out
