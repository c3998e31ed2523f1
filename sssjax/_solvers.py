"""Optimistix least-squares solvers for few parameters and many residuals.

A fit has a handful of parameters (6 for one material's RGB `sigma_a`, `sigma_s`) and tens of
thousands of residuals. Optimistix's `LevenbergMarquardt` keeps the linearisation of the
residual function (`jax.linearize`) in its state and solves each damped step as a
least-squares problem on the `(m + n) x n` stacked operator: the state then holds everything
the linearisation closed over (for a fit, the whole transport: 60 MB at 256 x 256), which every
step copies, and a step costs 6x the Jacobian. Here the Jacobian is materialised by forward
mode once per *accepted* point into the Gauss-Newton model of the loss, `g = J^T r` and
`H = J^T J` (`n x n`), which is all the state holds; a trial point costs one residual
evaluation; every damped step is an `n x n` solve. The trust-region search is optimistix's own
(`ClassicalTrustRegion`, given the model as `FunctionInfo.EvalGradHessian`) and termination
is optimistix's Cauchy test on the parameters and the loss.

The damping is Marquardt's scaled form, `(H + lambda D^2) dy = -g` with `D` the largest
`sqrt(diag H)` seen so far (MINPACK's choice), so that it treats parameters of different
sensitivity alike without letting a fading one take unbounded steps.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int, PyTree, Scalar

__all__ = ["NormalLevenbergMarquardt", "NormalGaussNewton"]


class _State(eqx.Module):
    first_step: Bool[Array, ""]
    y_eval: Float[Array, " n"]
    search_state: PyTree
    f_info: optx.FunctionInfo.EvalGradHessian  # loss, J^T r and J^T J at the accepted point
    scale: Float[Array, " n"]  # Marquardt's D: the largest column norm of J seen so far
    aux: PyTree
    terminate: Bool[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    num_accepted_steps: Int[Array, ""]


def _model(fn, y, args) -> tuple[optx.FunctionInfo.EvalGradHessian, Any]:
    """The Gauss-Newton model of `0.5 |fn(y)|^2` at `y`, from one forward-mode Jacobian."""

    def res(_y):
        r, aux = fn(_y, args)
        return r.reshape(-1), (r, aux)

    J, (r, aux) = jax.jacfwd(res, has_aux=True)(y)  # (m, n): n forward-mode products
    r = r.reshape(-1)
    H = lx.MatrixLinearOperator(J.T @ J, lx.symmetric_tag)
    return optx.FunctionInfo.EvalGradHessian(0.5 * jnp.sum(r * r), J.T @ r, H), aux


class _NormalSolver(optx.AbstractLeastSquaresSolver):
    """Shared machinery; see `NormalLevenbergMarquardt` and `NormalGaussNewton`."""

    rtol: float
    atol: float
    norm: Callable = optx.max_norm
    damped: bool = eqx.field(static=True, default=True)
    search: optx.AbstractSearch = optx.ClassicalTrustRegion()

    def init(self, fn, y, args, options, f_struct, aux_struct, tags) -> _State:
        del options, tags
        n = y.size
        zero = optx.FunctionInfo.EvalGradHessian(
            jnp.zeros((), y.dtype),
            jnp.zeros_like(y),
            lx.MatrixLinearOperator(jnp.zeros((n, n), y.dtype), lx.symmetric_tag),
        )
        return _State(
            first_step=jnp.array(True),
            y_eval=y,
            search_state=self.search.init(y, zero),
            f_info=zero,
            scale=jnp.zeros_like(y),
            aux=jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), aux_struct),
            terminate=jnp.array(False),
            result=optx.RESULTS.successful,
            num_steps=jnp.array(0),
            num_accepted_steps=jnp.array(0),
        )

    def step(self, fn, y, args, options, state: _State, tags):
        del options, tags
        r_eval, _ = fn(state.y_eval, args)
        loss_eval = 0.5 * jnp.sum(r_eval**2)
        # the search only needs the trial point's loss; the model there is built on accept
        trial = optx.FunctionInfo.EvalGradHessian(
            loss_eval, state.f_info.grad, state.f_info.hessian
        )
        step_size, accept, search_result, search_state = self.search.step(
            state.first_step, y, state.y_eval, state.f_info, trial, state.search_state
        )

        def accepted(_):
            model, aux = _model(fn, state.y_eval, args)
            y_diff = state.y_eval - y
            f_diff = model.f - state.f_info.f
            # optimistix's Cauchy test, on the loss (as its minimisers do) rather than on
            # every residual, which float32 shading keeps from settling
            y_ok = self.norm(jnp.abs(y_diff) / (self.atol + self.rtol * jnp.abs(y))) < 1
            f_ok = jnp.abs(f_diff) < self.atol + self.rtol * jnp.abs(model.f)
            terminate = y_ok & f_ok
            return state.y_eval, model, aux, terminate & ~state.first_step

        def rejected(_):
            return y, state.f_info, state.aux, jnp.array(False)

        y, model, aux, terminate = jax.lax.cond(accept, accepted, rejected, None)
        # MINPACK's rule: D never shrinks, so a parameter whose influence fades (an
        # absorption driven towards 0) is not granted ever larger steps
        scale = jnp.maximum(state.scale, jnp.sqrt(jnp.diag(model.hessian.as_matrix())))
        dy, descent_result = self._descent(step_size, model, scale)
        result = optx.RESULTS.where(
            search_result == optx.RESULTS.successful, descent_result, search_result
        )
        new = _State(
            first_step=jnp.array(False),
            y_eval=y + dy,
            search_state=search_state,
            f_info=model,
            scale=scale,
            aux=aux,
            terminate=terminate,
            result=result,
            num_steps=state.num_steps + 1,
            num_accepted_steps=state.num_accepted_steps + jnp.where(accept, 1, 0),
        )
        return y, new, aux

    def _descent(self, step_size: Scalar, model, scale) -> tuple[Array, optx.RESULTS]:
        """The (damped) Gauss-Newton step from the model, Marquardt-scaled by `scale`."""
        jtj, g = model.hessian.as_matrix(), model.grad
        d = jnp.where(scale > 0, scale, 1.0)  # a parameter the residual ignores: leave it
        A = jtj / jnp.outer(d, d)
        eye = jnp.eye(A.shape[0], dtype=A.dtype)
        if self.damped:
            # Levenberg-Marquardt: lambda = 1 / step size, as optimistix's damped descent
            big = step_size > jnp.finfo(A.dtype).eps
            lam = jnp.where(big, 1.0 / jnp.where(big, step_size, 1.0), 1e30)
            dy = -jnp.linalg.solve(A + lam * eye, g / d) / d
        else:
            # a whisker of damping keeps an exactly singular J^T J solvable; the fit's
            # covariance check reports the non-identifiability in words
            dy = -step_size * jnp.linalg.solve(A + 1e-7 * eye, g / d) / d
        ok = jnp.all(jnp.isfinite(dy))
        return jnp.where(ok, dy, 0.0), optx.RESULTS.where(
            ok, optx.RESULTS.successful, optx.RESULTS.nonlinear_divergence
        )

    def terminate(self, fn, y, args, options, state: _State, tags):
        return state.terminate, state.result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


class NormalLevenbergMarquardt(_NormalSolver):
    """Levenberg-Marquardt with optimistix's classical trust region, stepping on the
    normal equations (for few parameters and many residuals).

    **Arguments:** `rtol`, `atol` as `optimistix.LevenbergMarquardt` (the Cauchy test on the
    parameters and the loss); `norm` (default `optimistix.max_norm`).
    """

    damped: bool = eqx.field(static=True, default=True)
    search: optx.AbstractSearch = optx.ClassicalTrustRegion()


class NormalGaussNewton(_NormalSolver):
    """Gauss-Newton (full steps) on the normal equations.

    **Arguments:** `rtol`, `atol`, `norm` as `NormalLevenbergMarquardt`.
    """

    damped: bool = eqx.field(static=True, default=False)
    search: optx.AbstractSearch = optx.LearningRate(1.0)
