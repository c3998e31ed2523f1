"""The normal-equations least-squares solvers against closed forms and optimistix's own."""

import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from sssjax._solvers import NormalGaussNewton, NormalLevenbergMarquardt

SOLVERS = {"lm": NormalLevenbergMarquardt, "gn": NormalGaussNewton}


def rosenbrock(y, args):
    # 0.5 |r|^2 is Rosenbrock's function: minimum 0 at (1, 1), a curved narrow valley
    return jnp.stack([10.0 * (y[1] - y[0] ** 2), 1.0 - y[0]])


def decay_problem(seed=0):
    """Noisy samples of `a exp(-b t) + c e^{-t / 10}`: 200 residuals, 3 parameters."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 8.0, 200)
    data = 2.0 * np.exp(-0.7 * t) + 0.5 * np.exp(-t / 10) + 0.01 * rng.standard_normal(t.size)

    def fn(y, args):
        t, data = args
        return y[0] * jnp.exp(-y[1] * t) + y[2] * jnp.exp(-t / 10) - data

    return fn, (jnp.asarray(t), jnp.asarray(data))


@pytest.mark.parametrize("name", ["lm"])
def test_rosenbrock_minimum(x64, name):
    sol = optx.least_squares(
        rosenbrock, SOLVERS[name](1e-10, 1e-12), jnp.array([-1.2, 1.0]), max_steps=200
    )
    assert sol.result == optx.RESULTS.successful
    np.testing.assert_allclose(sol.value, [1.0, 1.0], atol=1e-7)


@pytest.mark.parametrize("name", ["lm", "gn"])
def test_agrees_with_optimistix_on_a_noisy_fit(x64, name):
    """Same minimum as optimistix's stock solver of the same kind (an independent
    implementation: QR on the stacked damped operator), and the normal equations hold there."""
    fn, args = decay_problem()
    y0 = jnp.array([1.0, 0.3, 1.0])
    ours = optx.least_squares(fn, SOLVERS[name](1e-10, 1e-12), y0, args=args, max_steps=100)
    stock = {"lm": optx.LevenbergMarquardt, "gn": optx.GaussNewton}[name](1e-10, 1e-12)
    ref = optx.least_squares(fn, stock, y0, args=args, max_steps=100)
    assert ours.result == optx.RESULTS.successful
    np.testing.assert_allclose(ours.value, ref.value, rtol=1e-8)
    # the gradient J^T r vanishes at the least-squares solution
    import jax

    J = jax.jacfwd(lambda y: fn(y, args))(ours.value)
    g = J.T @ fn(ours.value, args)
    assert float(jnp.max(jnp.abs(g))) < 1e-9


def test_parameter_the_residual_ignores_stays_put(x64):
    """A zero column of J (an unidentifiable parameter) neither moves nor poisons the step."""

    def fn(y, args):
        return jnp.stack([y[0] - 3.0, 2.0 * (y[0] - 3.0), 0.0 * y[1]])

    sol = optx.least_squares(fn, NormalLevenbergMarquardt(1e-10, 1e-12), jnp.array([0.0, 5.0]))
    assert sol.result == optx.RESULTS.successful
    np.testing.assert_allclose(sol.value, [3.0, 5.0], atol=1e-8)


def test_step_budget_exhaustion_is_reported(x64):
    sol = optx.least_squares(
        rosenbrock,
        NormalLevenbergMarquardt(1e-10, 1e-12),
        jnp.array([-1.2, 1.0]),
        max_steps=3,
        throw=False,
    )
    assert sol.result != optx.RESULTS.successful
    assert "maximum number of steps" in optx.RESULTS[sol.result]
