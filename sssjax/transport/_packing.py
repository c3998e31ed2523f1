"""Running a step on the alive rows of a batch only: pack them to the front, step them in
chunks of one width, scatter them back.

Rays and walkers end at very different times; stepping the whole block would cost the
block, and a `switch` over several packed widths compiles one copy of the step per width.
One chunk width compiles the step once, and a `while_loop` over chunks runs only as many as
hold alive rows, so the cost follows the rows still going. Rows keep their own state (their
random numbers included), so the result does not depend on the packing.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array

__all__ = ["step_alive"]


def step_alive(st: dict, chunk: int, step: Callable[[dict, Array], dict]) -> dict:
    """`step(sub, idx)` on the rows of `st` whose `st["alive"]` is set, `chunk` rows at a time.

    **Arguments:** `st`: arrays with a leading row axis; `chunk`: rows per step (static);
    `step`: takes the packed rows `sub` and their row indices `idx` (`(chunk,)`, the row
    count past the alive ones) and returns the stepped rows. Rows past the alive ones are
    zeros and are dropped when scattered back, so `step` must leave zero rows harmless.

    **Returns:** `st` with its alive rows stepped (unchanged when none is alive).
    """
    M = st["alive"].shape[0]
    n_alive = jnp.sum(st["alive"])
    order = jnp.nonzero(st["alive"], size=-(-M // chunk) * chunk, fill_value=M)[0]

    def body(c):
        k, st = c
        idx = jax.lax.dynamic_slice(order, (k * chunk,), (chunk,))
        sub = {f: jnp.take(v, idx, axis=0, mode="fill", fill_value=0) for f, v in st.items()}
        sub = step(sub, idx)
        return k + 1, {f: v.at[idx].set(sub[f], mode="drop") for f, v in st.items()}

    return jax.lax.while_loop(lambda c: c[0] * chunk < n_alive, body, (jnp.int32(0), st))[1]
