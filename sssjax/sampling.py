"""Stratified random numbers. Every function takes an explicit `jax.random` key."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, PRNGKeyArray


def jittered_grid(key: PRNGKeyArray, n: int, batch: tuple[int, ...] = ()) -> Array:
    """`n x n` jittered strata of the unit square: one uniform point in each cell.

    **Returns:** `(*batch, n*n, 2)` points in [0, 1)^2, cell-major order.
    """
    i, j = jnp.meshgrid(jnp.arange(n), jnp.arange(n), indexing="ij")
    cells = jnp.stack([i.ravel(), j.ravel()], axis=-1).astype(jnp.result_type(float))
    u = jax.random.uniform(key, (*batch, n * n, 2))
    return (cells + u) / n


def stratified_2d(key: PRNGKeyArray, m: int, batch: tuple[int, ...] = ()) -> Array:
    """`m` stratified points of the unit square per batch element.

    A jittered `s x s` grid when `m = s^2`; otherwise a Latin hypercube (stratified in each
    coordinate separately, with an independent random pairing per batch element).

    **Returns:** `(*batch, m, 2)` in [0, 1)^2.
    """
    s = math.isqrt(m)
    if s * s == m:
        return jittered_grid(key, s, batch)
    k1, k2, k3 = jax.random.split(key, 3)
    u = jax.random.uniform(k1, (*batch, m, 2))
    x = (jnp.arange(m) + u[..., 0]) / m
    perm = jnp.argsort(jax.random.uniform(k2, (*batch, m)), axis=-1)
    y = (perm + u[..., 1]) / m
    del k3
    return jnp.stack([x, y], axis=-1)


def stratified_1d(key: PRNGKeyArray, m: int, batch: tuple[int, ...] = ()) -> Array:
    """`m` jittered strata of [0, 1) per batch element, in random order: `(*batch, m)`."""
    k1, k2 = jax.random.split(key)
    x = (jnp.arange(m) + jax.random.uniform(k1, (*batch, m))) / m
    perm = jnp.argsort(jax.random.uniform(k2, (*batch, m)), axis=-1)
    return jnp.take_along_axis(x, perm, axis=-1)
