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
from ._problem import ETA_RANGE, Args, FitProblem, TraceData, model, residual_fn, row_pixels
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


# the width (pixels, Gaussian sigma) over which a round's Jacobian is smoothed into the
# instruments of its estimating equation (`instruments`)
INSTRUMENT_BLUR = 1.5


@eqx.filter_jit
def _halves_jacobian(residuals, y, args):
    def res(yy):
        r = residuals(yy, args)
        return r, r

    return jax.jacfwd(res, has_aux=True)(y)  # (2, m, n), (2, m)


def instruments(j: np.ndarray, pix: np.ndarray, shape: tuple) -> np.ndarray:
    """The Jacobian rows `j` `(..., m, n)` (rows `3 i + c`: channel `c` of pixel `pix[i]`
    of an image of `shape`) smoothed over the image, per channel and column: a Gaussian of
    `INSTRUMENT_BLUR` pixels, normalised over the fitted pixels (no leak from outside).

    A walk's derivative in a pixel is heavy-tailed (a long path's `n - sigma L` score), far
    noisier than the image: on the skin slab at 64 spp the signal was 1-25 % of a trace's
    `J^T J`. The image of a derivative is smooth, its noise is not, so smoothing keeps the
    signal and averages the noise over about `4 pi INSTRUMENT_BLUR^2` pixels. (Averaging
    the earlier rounds' Jacobians in as well was tried, 2026-12-06: a pixel whose
    derivative came out high then weighs alike in every round, and on the slab coverage
    fits it gave |z| of 2.9 and 4.7.)"""
    from scipy.ndimage import gaussian_filter

    h, w = shape
    lead, (m, n) = j.shape[:-2], j.shape[-2:]
    flat = j.reshape(-1, m // 3, 3, n).astype(np.float64)
    img = np.zeros((flat.shape[0], h * w, 3, n))
    img[:, pix] = flat
    cover = np.zeros(h * w)
    cover[pix] = 1.0
    sig = (0, INSTRUMENT_BLUR, INSTRUMENT_BLUR, 0, 0)
    img = gaussian_filter(img.reshape(-1, h, w, 3, n), sig, mode="constant")
    norm = gaussian_filter(cover.reshape(h, w), INSTRUMENT_BLUR, mode="constant")
    out = img.reshape(-1, h * w, 3, n)[:, pix] / norm.reshape(-1)[pix][None, :, None, None]
    return out.reshape(*lead, m, n)


class DiffusionInstruments:
    """Instruments for a re-weighting transport's rounds (`FitOptions.instruments =
    "diffusion"`) from the diffusion transport's image of the same scene: its exact
    Jacobian at the round's coefficients, on the round's rows, weighted as they are.

    Any instruments independent of the walks' residual noise keep the rounds' estimating
    equation unbiased (`RoundLinearisation`); these are a deterministic function of the
    coefficients (one fixed trace of their own), so they carry none of the walks'
    derivative noise into the step or the error bars, and the diffusion image's
    derivatives point nearly where the exact ones do (it is 10-30 % off in level, not in
    shape). Measured (2026-12-06, one seed each, from x1.5 `sigma_a` / x0.7 `sigma_s`):
    a 256 x 256 marble cube at 4 spp, 6 rounds, `sigma_s` -3..-4 % at bars of 2-2.5 %
    against -11..-20 % at 13-34 % with the smoothed instruments; a skin slab (48 x 48, 64
    spp) with bars of 5-19 % against 5-218 %."""

    def __init__(self, problem: FitProblem, dt):
        sss = dataclasses.replace(problem.scene.sss, transport="diffusion")
        scene = dataclasses.replace(problem.scene, sss=sss)
        self.problem = FitProblem(
            scene,
            problem.target,
            problem.free,
            problem.start,
            problem.options,
            problem.fit_mask,
            problem.seed,
            False,
            fit_mask=problem.fit_mask,
        )
        if problem.progress:
            print("instruments: one trace of the diffusion transport", file=sys.stderr, flush=True)
        data, media = self.problem.traced([jax.random.fold_in(problem.key, 31_337)])
        problem.trace_time += self.problem.trace_time
        self.args = self.problem.args(data, media, dt)
        self.pix = row_pixels(data)
        layout = self.problem.layout
        self._jac = jax.jit(jax.jacfwd(lambda y, args: model(layout, y, args).reshape(-1)))

    def at(self, y, pix: np.ndarray, weights: np.ndarray, scale: float) -> np.ndarray:
        """The instruments `(3 len(pix), n)` at `y` on the pixels `pix`, times the rows'
        `weights`, in units of `scale` (the rounds' residuals')."""
        jd = np.asarray(self._jac(y, self.args), np.float64)
        jd = jd * (float(self.args.scale) / scale)
        order = np.argsort(self.pix)
        k = np.clip(np.searchsorted(self.pix[order], pix), 0, self.pix.size - 1)
        i = order[k]
        hit = self.pix[i] == pix
        rows = (3 * i[:, None] + np.arange(3)).reshape(-1)
        out = np.where(np.repeat(hit, 3)[:, None], jd[rows], 0.0)
        return out * np.asarray(weights, np.float64).reshape(-1)[:, None]


def _linearised(problem, residuals, y, args, data, instr) -> RoundLinearisation:
    """A round's `RoundLinearisation` on its trace, with `instr`'s instruments
    (`DiffusionInstruments`) or, where None or for a coefficient the diffusion image does
    not show (a zero column), the walks' own smoothed ones (`instruments`)."""
    pix, shape = row_pixels(data), problem.target.shape[:2]
    j, r = (np.asarray(a) for a in _halves_jacobian(residuals, y, args))
    t = instruments(j, pix, shape).astype(j.dtype)
    if instr is not None:
        w = np.broadcast_to(np.asarray(args.weights), np.asarray(args.target).shape)
        td = instr.at(y, pix, w, float(args.scale)).astype(j.dtype)
        shown = np.any(td != 0, axis=0)
        t = np.where(shown[None, None, :], td[None], t)
    return RoundLinearisation.of(y, j, r, pix, shape, t)


@dataclasses.dataclass(frozen=True)
class RoundLinearisation:
    """One re-traced round's residuals: those of the two independent halves of its walks
    (`residual_fn(decorrelated=True)`, stacked `(2, m)`), their exact re-weighting Jacobian
    `j` `(2, m, n)` at its proposal `y` (log coordinates), so that `r_h(y') ~ r_h + j_h (y'
    - y)` near it, and the halves' instruments `t` (`DiffusionInstruments`, the same for
    both halves, or each half's smoothed Jacobian, `instruments(j)`).

    The round's estimating equation is `g(y) = (T_A^T r_B + T_B^T r_A) / 2 = 0`. Each
    half's instruments are independent of the other half's residuals, and the model is
    unbiased at every coefficient, so `E g = T^T (m_0(y) - t)`: its root is, in
    expectation, the noise-free least-squares solution (at the truth, for an exact target),
    with no lean towards the coefficients whose image is least noisy (the model variance
    in `E |t - m|^2`), whatever the instruments' own noise. `T` close to the noise-free
    Jacobian makes it efficient; a trace's own `J` is mostly noise (`instruments`), the
    diffusion transport's is none. Rounds pool by summing their equations (`pooled_step`,
    `pooled_covariance`)."""

    y: np.ndarray
    j: np.ndarray
    r: np.ndarray
    t: np.ndarray
    pix: np.ndarray | None = None  # the rows' pixels (row 3 i + c: channel c of pix[i])
    groups: np.ndarray | None = None  # each row's group of pixel blocks (`signal_grams`)

    @classmethod
    def of(cls, y, j, r, pix, shape, t=None) -> RoundLinearisation:
        """The linearisation of halves with Jacobians `j` `(2, m, n)` and residuals `r`
        `(2, m)` at `y`, rows on the pixels `pix` of an image of `shape`, with the halves'
        instruments `t` `(2, m, n)` (default: their smoothed Jacobians, `instruments`)."""
        t = instruments(j, pix, shape).astype(j.dtype) if t is None else t
        py, px = np.divmod(np.asarray(pix), shape[1])
        groups = np.repeat((5 * (py // BLOCK) + px // BLOCK) % GROUPS, 3)
        return cls(np.asarray(y, np.float64), j, r, t, np.asarray(pix), groups)

    def on(self, pix: np.ndarray) -> RoundLinearisation:
        """This round's rows of the pixels `pix` (a subset of its own, in their order)."""
        order = np.argsort(self.pix)
        i = order[np.searchsorted(self.pix[order], pix)]
        rows = (3 * i[:, None] + np.arange(3)).reshape(-1)
        return RoundLinearisation(
            self.y,
            self.j[:, rows],
            self.r[:, rows],
            self.t[:, rows],
            np.asarray(pix),
            None if self.groups is None else self.groups[rows],
        )

    def residuals(self, y) -> np.ndarray:
        """The halves' residuals at `y`, linearised: `(2, m)`."""
        dy = np.asarray(y, np.float64) - self.y
        return self.r.astype(np.float64) + self.j.astype(np.float64) @ dy

    def contributions(self, y) -> np.ndarray:
        """Each residual row's share of `g(y)` (linearised): `(m, n)`. `g` is their sum;
        rows are independent pixels, so the sum of their outer products estimates its
        covariance."""
        ra, rb = self.residuals(y)
        ta, tb = self.t.astype(np.float64)
        return 0.5 * (ta * rb[:, None] + tb * ra[:, None])

    def slope(self) -> np.ndarray:
        """`dg / dy = (T_A^T J_B + T_B^T J_A) / 2`: unbiased for `T^T J_0`, and its noise
        linear in the Jacobian's (the cross curvature `J_A^T J_B` has a noise x noise
        term, which dominated it)."""
        ja, jb = self.j.astype(np.float64)
        ta, tb = self.t.astype(np.float64)
        return 0.5 * (ta.T @ jb + tb.T @ ja)

    def gram(self) -> np.ndarray:
        """`Tbar^T Tbar`, `Tbar` the halves' mean instruments."""
        tbar = 0.5 * (self.t[0] + self.t[1]).astype(np.float64)
        return tbar.T @ tbar

    def _noise_rows(self) -> np.ndarray:
        """Rows whose outer products estimate the noise share of `gram`: the mean
        instruments `(A + B) / 2` have the noise of `(A - B) / 2`, which has no signal."""
        return 0.5 * (self.t[0].astype(np.float64) - self.t[1])

    @property
    def noise_gram(self) -> np.ndarray:
        """The estimated share of `gram` that is the instruments' noise."""
        x = self._noise_rows()
        return x.T @ x

    def signal_grams(self) -> np.ndarray:
        """`gram` less `noise_gram`, an unbiased estimate of the noise-free instruments'
        Gram matrix, split over `GROUPS` groups of pixel blocks `(GROUPS, n, n)`: nearly
        independent parts (the instruments' smoothing reaches a few pixels, the blocks are
        `BLOCK` wide) whose scatter says how well the correction is known. All in the first
        part when the rows have no groups."""
        tbar = 0.5 * (self.t[0] + self.t[1]).astype(np.float64)
        x = self._noise_rows()
        return self._by_group(tbar[:, :, None] * tbar[:, None, :] - x[:, :, None] * x[:, None, :])

    def slope_parts(self) -> np.ndarray:
        """`slope` split over the `GROUPS` groups of pixel blocks `(GROUPS, n, n)`, as
        `signal_grams` is (all in the first part when the rows have no groups)."""
        ja, jb = self.j.astype(np.float64)
        ta, tb = self.t.astype(np.float64)
        return self._by_group(
            0.5 * (ta[:, :, None] * jb[:, None, :] + tb[:, :, None] * ja[:, None, :])
        )

    def _by_group(self, rows: np.ndarray) -> np.ndarray:
        """Per-row matrices `(m, n, n)` summed over each row's group: `(GROUPS, n, n)`."""
        groups = np.zeros(rows.shape[0], int) if self.groups is None else self.groups
        out = np.zeros((GROUPS, *rows.shape[1:]))
        np.add.at(out, groups, rows)
        return out

    def loss(self, y) -> float:
        """The cross loss `0.5 sum r_A r_B` at `y`, linearised."""
        ra, rb = self.residuals(y)
        return 0.5 * float(ra @ rb)


def _aligned(rounds) -> list:
    """The rounds on the pixels they all have (a jittered edge pixel may be translucent
    in one trace and not in the next), so that their rows are the same pixels."""
    if len(rounds) < 2 or any(rd.pix is None for rd in rounds):
        return list(rounds)
    common = functools.reduce(np.intersect1d, [rd.pix for rd in rounds])
    if all(rd.pix.size == common.size for rd in rounds):
        return list(rounds)
    return [rd.on(common) for rd in rounds]


def _pooled_slope(rounds) -> np.ndarray:
    """The pooled slope `B = sum_k dg_k / dy` of aligned rounds."""
    return sum(rd.slope() for rd in rounds)


def _slope_inverse(rounds) -> np.ndarray:
    """The inverse of the pooled slope `sum_k dg_k / dy` (pseudo-inverse where singular)."""
    B = _pooled_slope(rounds)
    try:
        return np.linalg.inv(B)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(B)


# the pixel blocks (BLOCK x BLOCK, in GROUPS groups) over which the step's noise correction
# is estimated apart, to judge how well it is known (`pooled_step`)
BLOCK, GROUPS = 8, 8
# the most the noise correction may lengthen the step over the plain Gram step, per direction
MAX_STEP_GAIN = 4.0


def pooled_step(rounds, y) -> np.ndarray:
    """A Gauss-Newton step at `y` towards the root of the rounds' pooled estimating
    equation `sum_k g_k(y) = 0` (`RoundLinearisation`; each round linearised at its own
    proposal): the rounds' walks together, as one trace of all their samples, without
    re-tracing the old ones.

    The step's matrix is the instruments' Gram matrix less its estimated noise
    (`signal_grams`), not the slope `T^T J`, whose noise (the raw Jacobian's) made single
    steps run away by up to 6 in log on the skin slab. The plain Gram matrix `sum_k Tbar_k^T
    Tbar_k` is inflated by the instruments' noise: on a 256 x 256 cube at 4 spp by 5-50x in
    the `sigma_s` directions, so its steps covered 2-3 % of `sigma_s` per round. The
    corrected matrix is taken in the basis where the Gram matrix is the identity, each
    eigenvalue raised by two of its standard errors (the scatter of its estimates from
    `GROUPS` groups of pixel blocks: on a small image the correction is not known well, and
    taking it whole made the slab coverage fits wander) and clipped to `[1 / MAX_STEP_GAIN,
    1]` (noise-free, it is at most the Gram matrix): a positive definite matrix, steps at
    most `MAX_STEP_GAIN` times the plain ones in any direction.

    The step is then shortened wherever the pooled slope `B` is, beyond `SHORTEN_SE` of its
    standard errors, steeper than that matrix (`_shortened`): a Gram step converges only where the
    exact derivative is less than twice the instruments' (the iteration factor `1 - kappa`),
    and the diffusion instruments of the ketchup sphere's red channel are a quarter of it
    (`kappa` 3.7-4.2 over 14 rounds, measured 2026-12-07: red `sigma_a` oscillated by
    +-30 % per round). Where the iteration settles is the root whatever the matrix."""
    rounds = _aligned(rounds)
    M = sum(rd.gram() for rd in rounds)
    parts = sum(rd.signal_grams() for rd in rounds)  # (GROUPS, n, n)
    C = parts.sum(axis=0)
    g = _pooled_g(rounds, y)
    lam, U = np.linalg.eigh(0.5 * (M + M.T))
    W = U / np.sqrt(np.maximum(lam, 1e-12 * max(np.max(lam), 1e-300)))  # W^T M W = 1
    mu, V = np.linalg.eigh(W.T @ (0.5 * (C + C.T)) @ W)
    # the correction only as far as the blocks agree on it: each eigenvalue raised by two
    # of its standard errors (from the blocks' scatter), so a correction that the pixels
    # cannot tell from noise leaves the plain Gram step
    WV = W @ V
    se = _block_se(parts, WV)
    mu = np.clip(mu + 2.0 * se, 1.0 / MAX_STEP_GAIN, 1.0)
    step_w = -V @ ((WV.T @ g) / mu)  # in the basis where the Gram matrix is the identity
    return W @ _shortened(rounds, W, step_w)


def _shortened(rounds, W, step_w) -> np.ndarray:
    """`step_w` (in the basis `W`, `W^T M W = 1`) divided, along each right eigenvector of
    the pooled slope `K = W^T B W`, by the real part of its eigenvalue `kappa` less
    `SHORTEN_SE` of its standard errors (the scatter of the pixel-block groups' shares),
    where that exceeds 1: never further than the slope says, and unchanged where `K` cannot
    be told from 1 or is smaller (a shorter slope only slows a Gram step, as noise in `B`
    would mislead a Newton step).

    The eigenvectors of `K` itself, not only of its symmetric part: the slope `T^T J` of
    instruments unlike the exact derivative is not symmetric. On the ketchup sphere's red
    channel (64 x 64, measured 2026-12-08) `M^-1 B` was `[[5.4, -0.06], [1.7, 0.86]]` in
    (`sigma_a`, `sigma_s`): the symmetric part's eigenvectors are rotated from its own,
    and dividing along them turned the Gram step's `sigma_a` from -1.87 (towards the
    truth, -0.41) to +1.15; every such step raised the trace's loss, was halved to 1/256
    and restarted the approach, so the rounds never settled. Along `K`'s own eigenvectors
    the same step is (-0.34, +0.70), and two of the sphere's three coverage fits settle
    (none did; the third ends within 1.5 standard errors of the truth). But only
    the asymmetry that the pixel-block groups agree on (each element of `(K - K^T) / 2`
    beyond `ASYM_SE` of its standard errors; 4-5 on the sphere's red channel) is kept: the
    eigenvectors of a noisy `K` near the identity are noise. On the marble cube (6 seeds,
    64 x 64, 8 spp) following all of it left 2 fits unsettled (rms z 1.23), with
    `ASYM_SE` 2 3 of them, with 4 none (rms z 0.99; the symmetric part alone: 1 of 6,
    1.01). Where the eigenvectors are too close to parallel to separate (a condition
    number beyond `MAX_EIG_COND`), the symmetric part's are used."""
    parts = sum(rd.slope_parts() for rd in rounds)  # (GROUPS, n, n)
    parts_w = np.einsum("ia,gij,jb->gab", W, parts, W)  # the groups' shares of K
    K = parts_w.sum(axis=0)
    sym, asym = 0.5 * (K + K.T), 0.5 * (K - K.T)
    asym_se = _scatter_se(0.5 * (parts_w - parts_w.transpose(0, 2, 1)), parts)
    keep = np.abs(asym) > ASYM_SE * asym_se
    kappa, Q = np.linalg.eig(sym + np.where(keep, asym, 0.0)) if keep.any() else (None, None)
    if Q is None or not np.all(np.isfinite(kappa)) or np.linalg.cond(Q) > MAX_EIG_COND:
        kappa, Q = np.linalg.eigh(sym)
    Qinv = np.linalg.inv(Q)
    # each eigenvalue's share per group is u_i^T K_g v_i (u_i the left eigenvectors,
    # u_i^T v_i = 1): its scatter is the eigenvalue's standard error
    se = _block_se(parts, W @ Q, Qinv @ W.T)
    div = np.maximum(kappa.real - SHORTEN_SE * se, 1.0)
    return (Q @ ((Qinv @ step_w) / div)).real


# how many of its standard errors an element of the slope's antisymmetric part must exceed
# to be followed (`_shortened`); the rest is taken as noise. The errors come from the
# scatter of `GROUPS` groups (7 degrees of freedom: beyond 4 about 0.5 % of the time by
# chance; the marble cube's noise reached 3.4)
ASYM_SE = 4.0
# the condition number of `K`'s eigenvectors beyond which `_shortened` takes those of its
# symmetric part instead (nearly parallel eigenvectors, as noise makes of a near-double
# eigenvalue, would amplify the step)
MAX_EIG_COND = 1e3


# how many of its standard errors the slope's eigenvalue `kappa` is lowered by before a step
# is divided by it (`_shortened`). With 2, a direction whose instruments were 0.7 of the
# exact slope, at the 40 % slope noise of the skim-milk cylinder's `sigma_s`, was left
# unshortened, the rounds trailed its root by about one standard error and the jump onto it
# leaned on the noisy slope: 4 % of the truths beyond 3 standard errors, rms z 1.26; with
# 1, 1.3 % and 1.02 (exact instruments unchanged: 0.7 %, 0.93; with 0: 3.3 %, 1.05).
# `benchmarks/rounds_model.py`, measured 2026-12-07.
SHORTEN_SE = 1.0


def _block_se(parts, basis, left=None) -> np.ndarray:
    """The standard error of each diagonal element of `left (sum parts) basis` (`left`
    default `basis^T`; real parts), from the scatter of the pixel-block groups' shares
    `parts` `(GROUPS, n, n)` (inf with one)."""
    left = basis.T if left is None else left
    per = np.einsum("ia,gab,bi->gi", left, parts, basis).real  # (GROUPS, n): the shares
    return _scatter_se(per, parts)


def _scatter_se(per, parts) -> np.ndarray:
    """The standard error of the sum over groups of `per` `(GROUPS, ...)`, from its scatter
    over the groups of `parts` that have any rows (inf with one)."""
    used = np.count_nonzero(np.any(parts != 0, axis=(1, 2)))
    return (
        np.sqrt(used * np.var(per, axis=0, ddof=1)) if used > 1 else np.full(per.shape[1:], np.inf)
    )


def _pooled_g(rounds, y) -> np.ndarray:
    """The pooled estimating equation's value `sum_k g_k(y)` on aligned rounds."""
    return sum(rd.contributions(y).sum(axis=0) for rd in rounds)


def root_offset(rounds, y) -> np.ndarray:
    """How far `y` is from the root of the rounds' pooled equation: the Newton step
    `-B^-1 sum_k g_k(y)` (`B` the pooled slope). Noisy (as `B` is), but in the same metric
    as `pooled_covariance`, so comparing it with the error bars asks whether `y` is at the
    root within its errors; `pooled_step`'s damped step would also look small on a slow
    drift."""
    rounds = _aligned(rounds)
    return -_slope_inverse(rounds) @ _pooled_g(rounds, y)


# how far (in standard errors) the rounds' last solution may be from the pooled root for
# the final jump onto it (`to_root`): further, the linearisation is not trusted that far
ROOT_JUMP_SD = 3.0


def to_root(rounds, y, sd, tol: float) -> np.ndarray:
    """The jump from `y` onto the root of the rounds' pooled equation in its determined
    coefficients (`_determined(sd)`; the others held): the Newton step `-B_dd^-1 g_d` of
    the pooled, linearised equation, which is exact for it. Zero where any of them is
    further than `ROOT_JUMP_SD` standard errors (or `tol`) away: the rounds were still
    moving, and the slope `B` is not trusted that far.

    Why: `pooled_covariance` is the covariance of that root, but the Gram steps approach it
    only as fast as the instruments match the slope; on the ketchup sphere (64 x 64, 8
    rounds) the last solution stayed 1.1-1.7 of its standard errors short in red `sigma_a`
    round after round (measured 2026-12-07), so the answer was not the point its bars
    describe. Only at the end: jumping the proposal onto the root every round did worse on
    the slab coverage fits (3 of 36 coefficients beyond 2 standard errors, max 2.43; 1 of 36,
    max 2.01, jumping at the end; six targets, measured 2026-12-07)."""
    rounds = _aligned(rounds)
    det = np.flatnonzero(_determined(sd))
    jump = np.zeros(np.asarray(y).size)
    if det.size == 0:
        return jump
    B = _pooled_slope(rounds)
    g = _pooled_g(rounds, y)
    try:
        jd = -np.linalg.solve(B[np.ix_(det, det)], g[det])
    except np.linalg.LinAlgError:
        return jump
    if not np.all(np.isfinite(jd)) or np.any(
        np.abs(jd) > ROOT_JUMP_SD * np.maximum(np.asarray(sd)[det], tol)
    ):
        return jump
    jump[det] = jd
    return jump


def pooled_covariance(rounds, y) -> tuple[np.ndarray, np.ndarray]:
    """The covariance (log coordinates) of the pooled rounds' root `y`: the sandwich
    `B^-1 V B^-T`, `B` the pooled slope and `V` the sum over pixels of the outer products
    of each pixel's contributions to `g`, summed over the rounds first.

    Summing a pixel's contributions over the rounds first is what keeps the target's noise
    honest: it is the same in every round (one target), so it adds coherently and pooling
    more rounds does not shrink its share, while each round's trace noise is independent and
    averages down. Outer products per pixel (White's estimator) take the walks' heavy-tailed
    noise as it comes, where `s^2 (J^T J)^-1` from one trace (inflated by the derivative
    noise) claimed a fraction of the error: on the skin slab single rounds stepped +0.26 in
    log at a claimed 0.009. **Returns:** `(cov, cov_target)`, the second the target's noise
    alone (each pixel's residual variance less its trace variance, the halves' squared
    difference / 4)."""
    rounds = _aligned(rounds)
    rows = {rd.r.shape[1] for rd in rounds}
    if len(rows) != 1:
        raise ValueError(f"the rounds' residuals differ in length ({sorted(rows)})")
    b_inv = _slope_inverse(rounds)
    m, n = rounds[0].r.shape[1], rounds[0].y.size
    G = sum(rd.contributions(y) for rd in rounds)
    V = G.T @ G * (m / max(m - n, 1))  # HC1
    tsum = sum(0.5 * (rd.t[0] + rd.t[1]).astype(np.float64) for rd in rounds)
    # each row's estimate unclipped (it is often negative): clipping rows at zero made the
    # target's share 1.45x too large under heavy-tailed walk noise (Student t, 3 dof), and
    # up to all of the error on a 64 x 64 cylinder; only the share's diagonal is used
    var_t = np.mean(
        [
            r.mean(axis=0) ** 2 - 0.25 * (r[0] - r[1]) ** 2
            for r in (rd.residuals(y) for rd in rounds)
        ],
        axis=0,
    )
    Vt = (tsum * var_t[:, None]).T @ tsum
    return b_inv @ V @ b_inv.T, b_inv @ Vt @ b_inv.T


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


def loss_at(problem: FitProblem, y, args: Args, decorrelated: bool = False) -> float:
    """`0.5 sum r^2` of the (robust) residuals at `y`; `decorrelated` (a trace that splits
    into halves): `0.5 sum r_A r_B`, which carries no model variance (the plain loss of a
    re-weighted trace is lower wherever its re-weighting is less noisy, e.g. at a start of
    larger `sigma_a`, so it can read as rising over a fit that found the truth)."""
    if decorrelated and args.halves is not None:
        residuals = residual_fn(problem.layout, problem.options.loss, True)
        return float(_cross_loss(residuals, y, args))
    return float(_loss(residual_fn(problem.layout, problem.options.loss), y, args))


def jacobian(problem: FitProblem, y, args: Args):
    """The residuals' forward-mode Jacobian at `y` and the residuals."""
    return _jac_res(residual_fn(problem.layout, problem.options.loss), y, args)


def _shown(loss: float, names: list[str], vals: np.ndarray) -> str:
    # the material name is dropped (one material in most fits); a light keeps its prefix
    short = [n if n.startswith("lights.") else n.split(".", 1)[-1] for n in names]
    shown = "  ".join(f"{n}={v:.4g}" for n, v in zip(short, vals, strict=True))
    return f"loss {loss:.6g}  {shown}"


def _progress_line(
    bar, step: int, loss: float, names: list[str], vals: np.ndarray, what: str = "step"
) -> None:
    """A step on the bar (a terminal) or as a line of its own (a file or pipe)."""
    bar.update(step, line=f"{what} {step:3d}  {_shown(loss, names, vals)}", loss=loss)


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
    trace-noise estimate (half the difference of two single-trace solutions, log space).
    A re-weighting transport's rounds give the whole covariance (`cov_log`, log space), of
    which `trace_sd` is the trace noise's part and `target_sd` the target's."""

    run: Run
    keys: list
    data: list[TraceData]
    eta: float | None = None
    eta_search: list | None = None
    eta_loss0: float | None = None
    eta_bounds: tuple | None = None
    trace_sd: np.ndarray | None = None
    cov_log: np.ndarray | None = None
    target_sd: np.ndarray | None = None


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


# a step's standard error (log coefficients) beyond which "within its error" means nothing
SETTLE_MAX_SD = 0.1
# a standard error (log coefficients) beyond which a coefficient is not determined by the
# target (`FitResult` warns so, naming it): its wandering does not keep the rounds going
UNDETERMINED_SD = 0.5


def _determined(sd) -> np.ndarray:
    """Which coefficients the rounds judge: those whose standard error is below
    `UNDETERMINED_SD` (the others are reported as not determined, whatever they do)."""
    return np.asarray(sd) < UNDETERMINED_SD


def _settled(dy, sd, tol: float) -> bool:
    """Whether a re-traced round's solution is settled: its offset `dy` from the pooled
    root (log coefficients, `root_offset`) within `max(tol, sd)` in every determined
    component (`_determined`; at least one), and every such `sd` itself below
    `SETTLE_MAX_SD` (10 %): an offset whose error is larger than that is no evidence of
    having settled (an undetermined coefficient would otherwise settle at once, anywhere;
    `RoundsStop` says such a fit converged with wide bars). The coefficients beyond
    `UNDETERMINED_SD` are left out: a ketchup sphere's green and blue channels (albedo
    0.07 and 0.02, bars of 60-400 %) wandered by more than their errors round after round
    and kept its well-determined red channel "not settled" (measured 2026-12-07)."""
    sd = np.asarray(sd)
    return _within(dy, sd, tol) and bool(np.all(sd[_determined(sd)] < SETTLE_MAX_SD))


def _within(dy, sd, tol: float) -> bool:
    """Whether every determined component of the offset `dy` is within `max(tol, sd)`
    (at least one determined), whatever the size of `sd`."""
    dy, sd = np.abs(np.asarray(dy)), np.asarray(sd)
    det = _determined(sd)
    return bool(det.any() and np.all(dy[det] <= np.maximum(tol, sd[det])))


@dataclasses.dataclass
class RoundsStop:
    """The stopping rule of the re-traced rounds, fed one round at a time (`after`) with
    the solution's remaining distance to the root of the pooled equation (`root_offset`,
    log coordinates), its standard errors and the fraction of the step taken.

    Counts the consecutive rounds after a full (not shortened) step whose offset was
    `_settled` and those whose offset was within its errors at all (`at_root`, whatever
    those errors). `after` says to stop at two settled rounds in a row; `verdict` at the
    end: converged when stopped so, or, all rounds used, when the last two were within their
    (wide) errors: the solution is then at the root of the pooled equation and its
    covariance is that root's (wide bars, not understated ones). Otherwise the rounds were
    still moving. The offset, not the step taken: `pooled_step` is damped where the
    instruments keep noise, and a slow drift of small steps (+0.03 in log per round on a
    256 x 256 cube at 4 spp, ending 24 % short at z -5.6) would look settled. Coefficients
    not determined (`_determined`) are left out of both counts; the verdict says how many."""

    tol: float
    settled: int = 0
    at_root: int = 0
    undetermined: int = 0

    def after(self, off, sd, frac: float) -> bool:
        full = frac == 1.0
        self.undetermined = int(np.count_nonzero(~_determined(sd)))
        self.settled = self.settled + 1 if full and _settled(off, sd, self.tol) else 0
        within = full and _within(off, sd, self.tol)
        self.at_root = self.at_root + 1 if within else 0
        return self.settled >= 2

    def verdict(self, rounds: int) -> tuple[bool, str]:
        """**Returns:** `(converged, message)` after `rounds` rounds."""
        left = (
            f"; {self.undetermined} coefficient{'s' if self.undetermined > 1 else ''} not "
            "determined, left out"
            if self.undetermined
            else ""
        )
        if self.settled >= 2:
            return True, f"converged (within its errors of the pooled rounds' root{left})"
        if self.at_root >= 2:
            return True, (
                f"converged at the root of the pooled rounds ({rounds} rounds, within its "
                f"errors of the root, some of these above {SETTLE_MAX_SD:.0%}{left})"
            )
        return False, f"the re-traced rounds did not settle within {rounds} rounds"


# the re-weighting is trusted where the effective sample size keeps this share of the trace's
MIN_EFFICIENCY = 0.3
# the largest re-traced step (log coefficients): a shorter one when far from the solution
MAX_ROUND_STEP = 0.5
# the largest step of a coefficient the rounds cannot resolve (its step within its noise)
NOISE_STEP = 0.1


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


def _trusted_step(problem, data, args, y, dy, loss, sd=None):
    """The longest of `dy`, `dy / 2`, `dy / 4`, ... (first capped at `MAX_ROUND_STEP`) that
    stays where the trace's re-weighting is trusted (`channel_efficiency` at least
    `MIN_EFFICIENCY`) and, unless `loss` is None, does not raise the decorrelated loss
    `loss(y)` (this trace's, an unbiased estimate of the noise-free loss): a Gauss-Newton
    step from far away overshoots, and a step past the trusted region lands on a
    re-weighting whose noise is larger than the step.

    Components the rounds cannot resolve (standard error `sd` above `MAX_ROUND_STEP`, and
    the step within two of them: noise, not a direction to go) are capped on their own at
    `NOISE_STEP` and do not shorten the others: a coefficient the image barely shows
    (marble's red `sigma_a` on a cube, +-60-200 %) steps +-1 in log from round to round,
    and scaling the whole step by it held `sigma_s` to a third of its steps and restarted
    the pool at every round. (Capping them at `MAX_ROUND_STEP` instead let them wander on
    the slab coverage fits: red `sigma_s` +511 %.) **Returns:** the step taken and its
    fraction of `dy` (of its resolved components)."""
    dy = np.asarray(dy, np.float64)
    if sd is None:
        noise = np.zeros(dy.shape, bool)
    else:
        sd = np.asarray(sd)
        noise = (np.abs(dy) <= 2.0 * sd) & (sd > MAX_ROUND_STEP)
    dy = np.where(noise, np.clip(dy, -NOISE_STEP, NOISE_STEP), dy)
    big = np.max(np.abs(np.where(noise, 0.0, dy)))
    t = min(1.0, MAX_ROUND_STEP / big) if big > 0 else 1.0
    base = None if loss is None else loss(y)
    for _ in range(8):
        cand = y + jnp.asarray(t * dy, y.dtype)
        if channel_efficiency(problem, data, args.media0, cand) >= MIN_EFFICIENCY:
            if loss is None or loss(cand) <= base:
                return t * dy, t
        t *= 0.5
    return t * dy, t


def pooled_after(pool: list, k: int, lin: RoundLinearisation, start: int = 0) -> list:
    """The rounds' pool `[(round, linearisation)]` after round `k`'s `lin`: the rounds
    since `start` (where the approach ended) and at most the later half of all rounds."""
    return [(i, p) for i, p in pool + [(k, lin)] if i >= max(start, k // 2)]


@eqx.filter_jit
def _cross_loss(residuals, y, args):
    r = residuals(y, args)
    return 0.5 * jnp.sum(r[0] * r[1])


@dataclasses.dataclass
class Rounds:
    """What a re-weighting transport's rounds (`_retraced_rounds`) found: the last trace,
    the run at the solution (its `args` from the last trace), the solution's covariance in
    log coordinates (`pooled_covariance`: target and trace noise) and the target's share."""

    data: list[TraceData]
    run: Run
    cov: np.ndarray
    cov_target: np.ndarray


def _retraced_rounds(problem: FitProblem, keys, media, y, eta, refit: bool = False, history=()):
    """A re-weighting transport's fit: Gauss-Newton rounds, each on a fresh trace with the
    current solution as the walks' proposal.

    A least-squares fit to a noisy model leans toward the coefficients whose image is least
    noisy (the model's variance is part of `E |t - m|^2`; for a walk, larger `sigma_a`
    cuts the long, noisy paths), and re-weighting far from the proposal makes that noise
    larger still, so a free solve on one trace from a distant start lands far from the truth
    (measured on a thick slab: `sigma_s` 0.11 against 1.0 from a start at 0.7). Each round
    here re-traces at the current solution with new random numbers and linearises the
    residuals of two independent halves of its walks there (`RoundLinearisation`: the exact
    re-weighting derivatives), then takes one Gauss-Newton step of the pooled cross loss
    `sum_k 0.5 sum r_kA r_kB` (whose expectation carries no model variance) over the rounds
    since the approach ended (`pooled_step`), shortened until it stays where the trace's
    re-weighting is trusted and lowers that loss (`_trusted_step`). A shortened step ends
    the approach: the pool restarts at the next round. The pool keeps at most the later
    half of the rounds, so no round's outlying trace steers the solution alone (a single
    round's step is heavy-tailed: +0.26 in log at a claimed 0.009 on the skin slab) and the
    rounds' information adds up instead of a chain of short steps forgetting it. With
    relative weighting (`refit`), each round's weights come from the previous trace at
    the proposal (independent of its own noise). The rounds stop when, after two full steps
    in a row, the solution is within its standard errors (or `proposal_tol`) of the pooled
    root (`root_offset`) and those errors are below `SETTLE_MAX_SD`, or after
    `proposal_rounds` (`RoundsStop`, which also says whether the fit converged).
    **Returns:** `Rounds`."""
    opts = problem.options
    names = problem.names
    dt = jnp.float32 if jnp.asarray(y).dtype == jnp.float32 else jnp.float64
    residuals = residual_fn(problem.layout, opts.loss, True)
    history = list(history)
    loss0 = None
    bar = Progress(opts.proposal_rounds, "re-traced rounds", problem.progress, every_line=True)
    data, args, stop = None, None, RoundsStop(opts.proposal_tol)
    prev = None  # the previous round's trace: the relative weights' level, independent
    pool, start, n_rounds = [], 0, 0  # (round, linearisation) since the approach ended
    instr = None  # `DiffusionInstruments`, from the first round's mask on
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
        if instr is None and opts.instruments == "diffusion":
            instr = DiffusionInstruments(problem, dt)
        lin = _linearised(problem, residuals, y, args, data, instr)
        pool = pooled_after(pool, k, lin, start)
        window = [p for _, p in pool]
        dy = pooled_step(window, y)
        if not np.all(np.isfinite(dy)):
            raise FitError(
                "the re-traced Gauss-Newton step is not finite (a trace with no signal in "
                "the fitted pixels?): check the target and the mask"
            )
        # the halves' cross loss at the point this round traced: it carries no model
        # variance, so the rounds' losses compare (their plain loss swings with the walks'
        # noise), and the first one is the summary's `loss_initial` (`_report`)
        loss = 0.5 * float(np.sum(np.prod(lin.r, axis=0, dtype=np.float64)))
        loss0 = loss if loss0 is None else loss0
        history.append({"step": len(history), "loss": loss, "params": problem.values(y).tolist()})
        _progress_line(bar, k + 1, loss, names, problem.values(y), "round")
        if len(window) == 1:  # approaching: this trace's own (not linearised) cross loss

            def cross(yy, args=args):
                return float(_cross_loss(residuals, yy, args))
        else:  # pooled: the step solves the rounds' equation, not this trace's loss
            cross = None
        sd0 = np.sqrt(np.clip(np.diag(pooled_covariance(window, y)[0]), 0, None))
        dy, frac = _trusted_step(problem, data, args, y, dy, cross, sd0)
        y = y + jnp.asarray(dy, y.dtype)
        n_rounds = k + 1
        sd = np.sqrt(np.clip(np.diag(pooled_covariance(window, y)[0]), 0, None))
        if frac < 1.0:
            start = k + 1  # still approaching: the rounds so far were linearised too far away
        off = root_offset(window, y)  # the distance to the root, not the damped step
        if stop.after(off, sd, frac):  # two rounds in a row settled at the root
            break
    converged, message = stop.verdict(n_rounds)
    # the answer is the pooled root the covariance below describes, not the last step's end
    y = y + jnp.asarray(to_root(window, y, sd, opts.proposal_tol), y.dtype)
    # its loss on the last trace (re-weighted there: the root is within a step of it), the
    # history's last point and the summary's `loss_final`
    loss = float(_cross_loss(residuals, y, args))
    history.append(
        {"step": len(history), "loss": loss, "params": problem.values(y).tolist(), "root": True}
    )
    bar.write(f"root       {_shown(loss, names, problem.values(y))}")
    bar.close()
    # the solution's covariance from the rounds whose step found it (as the stopping rule
    # judged it). Not the last round alone after a shortened final step: at 4 spp on a
    # 256 x 256 cube one round's bars were 10-562 %, where its pool's were 5-40 %
    cov, cov_target = pooled_covariance(window, y)
    status = "successful" if converged else "max_steps_reached"
    run_ = Run(y, args, n_rounds, loss0, history, converged, status, message)
    return Rounds(data, run_, cov, cov_target)


def _rounds_outcome(out: Outcome, rounds: Rounds) -> Outcome:
    """`out` with the rounds' trace, run and covariance; the trace noise's share of the
    error is what the target's noise does not explain."""
    out.data, out.run, out.cov_log = rounds.data, rounds.run, rounds.cov
    extra = np.diag(rounds.cov) - np.diag(rounds.cov_target)
    out.trace_sd = np.sqrt(np.clip(extra, 0.0, None))
    out.target_sd = np.sqrt(np.clip(np.diag(rounds.cov_target), 0.0, None))
    return out


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
        return _rounds_outcome(out, _retraced_rounds(problem, keys, media, y0, None, refit))
    else:
        (data, media), y_start = problem.traced(keys), y0
    r = solve(problem, data, media, y_start)
    refit = WEIGHTINGS[problem.options.weighting].refit
    if problem.reweighted:
        _rounds_outcome(out, _retraced_rounds(problem, keys, media, r.y, out.eta, refit, r.history))
        out.run.steps += r.steps
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
