"""NaN-safe elementary functions used throughout the physics.

Every `sqrt` and division whose argument can reach zero goes through here, using the
double-`where` idiom so that both the value *and* the gradient stay finite: the unsafe
branch is evaluated on a harmless dummy input, so no NaN/inf is ever produced and then
masked (a masked NaN still poisons the gradient).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


def safe_sqrt(x: ArrayLike) -> Array:
    """`sqrt(max(x, 0))` with a finite gradient (zero) at and below 0."""
    x = jnp.asarray(x)
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def safe_div(num: ArrayLike, den: ArrayLike, fallback: ArrayLike = 0.0) -> Array:
    """`num / den`, or `fallback` where `den == 0`, with finite gradients everywhere."""
    den = jnp.asarray(den)
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fallback)


def float_dtype():
    """The default JAX float dtype: float32 unless `jax_enable_x64` is on."""
    return jnp.result_type(float)
