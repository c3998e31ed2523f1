"""The tabulated profile: exact (Monte Carlo) transport of a semi-infinite medium, interpolated.

The table `data/tabulated_profile.npz` is built by `benchmarks/profile_table.py` from
`sssjax.reference` (its docstring says how, and what each array is). In reduced units
`x = r sigmap_t`, reduced albedo `a' = sigmap_s / sigmap_t` and relative index `eta`:

- multiple scattering `R_ms(r) = R_bd(r) exp(T(log x, logit a', eta))`, d'Eon's better dipole
  `R_bd` (`sssjax.profiles`, exact in its dependence on the coefficients) corrected by the
  tabulated Monte Carlo log ratio `T` (beyond the runs' precise bins a fitted continuation
  whose error includes the model's: `profiles.tabulated_error`);
- its total `exp(T_tot(logit a', eta)) Rd_total_bd`;
- single scattering `a' sigmap_t^2 S(x, eta)` under the normally incident beam, isotropic
  phase (the exact closed form, tabulated), and its total `a' S_total(eta)`.

Interpolation is Catmull-Rom (cubic, C1) along each axis, so values and Jacobians are
continuous in the coefficients. Outside the grid the correction is held at its edge
(`a'` below 0.011 or above 0.99999, `eta` outside 1.0-1.6, `x` below 0.0108) or, beyond the
last `x` node (338 reduced mean free paths), continued along the exact asymptotic decay.
Everything is per unit power **entering** the medium, like `sssjax.dipole.Rd`.
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax.numpy as jnp
import numpy as np

TABLE_PATH = Path(__file__).with_name("data") / "tabulated_profile.npz"


@functools.cache
def table() -> dict[str, np.ndarray]:
    """The table's arrays (loaded once); a one-line error if the package lacks it."""
    if not TABLE_PATH.exists():
        raise FileNotFoundError(
            f"{TABLE_PATH}: the tabulated profile's table is missing; rebuild it with "
            "`python benchmarks/profile_table.py`"
        )
    with np.load(TABLE_PATH) as z:
        return {k: z[k] for k in z.files}


def eta_range() -> tuple[float, float]:
    """The relative indices of refraction the table covers (beyond them it is held at its
    edge, an approximation)."""
    eta = table()["eta"]
    return float(eta.min()), float(eta.max())


class EtaRangeWarning(UserWarning):
    """The tabulated profile was asked for an `eta` beyond its table (`eta_outside`)."""


def eta_outside(eta: float) -> str | None:
    """What a user must be told when `eta` is beyond the table (None within it): the
    profile there is the table's value at its edge, not exact."""
    lo, hi = eta_range()
    if lo <= eta <= hi:
        return None
    return (
        f"{eta:g} is outside the tabulated profile's range {lo:.1f}-{hi:.1f}: the profile "
        f"there is its value at eta = {min(max(eta, lo), hi):g} (not exact)"
    )


def _axis(v, nodes):
    """Indices `(..., 4)` and Catmull-Rom weights `(..., 4)` of `v` on uniform `nodes`
    (clamped to the grid)."""
    n = nodes.size
    h = float(nodes[1] - nodes[0])
    s = (v - float(nodes[0])) / h
    i = jnp.clip(jnp.floor(s), 0, n - 2)
    t = jnp.clip(s - i, 0.0, 1.0)
    t2, t3 = t * t, t * t * t
    w = jnp.stack(
        [
            0.5 * (-t3 + 2 * t2 - t),
            0.5 * (3 * t3 - 5 * t2 + 2),
            0.5 * (-3 * t3 + 4 * t2 + t),
            0.5 * (t3 - t2),
        ],
        -1,
    )
    idx = jnp.clip(i.astype(jnp.int32)[..., None] + jnp.arange(-1, 3), 0, n - 1)
    return idx, w


def _interp(values, coords):
    """Tensor-product Catmull-Rom interpolation of `values` (one axis per coordinate) at
    `coords`, a list of `(v, nodes)` with broadcast-compatible `v`."""
    shape = jnp.broadcast_shapes(*[jnp.shape(v) for v, _ in coords])
    parts = [_axis(jnp.broadcast_to(v, shape), nodes) for v, nodes in coords]
    d = len(parts)
    idx = tuple(
        p[0].reshape(shape + tuple(4 if k == j else 1 for k in range(d)))
        for j, p in enumerate(parts)
    )
    w = None
    for j, p in enumerate(parts):
        wj = p[1].reshape(shape + tuple(4 if k == j else 1 for k in range(d)))
        w = wj if w is None else w * wj
    return jnp.sum(jnp.asarray(values)[idx] * w, axis=tuple(range(-d, 0)))


def reduced(sigma_a, sigmap_s, dtype):
    """`(sigmap_t, a', logit a')` with guards so that `sigma_a = 0` or `sigmap_s = 0` gives
    finite values and gradients (the logit is clamped to the table's range anyway)."""
    tab = table()
    sa = jnp.asarray(sigma_a, dtype)
    sp = jnp.asarray(sigmap_s, dtype)
    spt = sa + sp
    lo, hi = float(tab["logit"][0]), float(tab["logit"][-1])
    tiny = jnp.asarray(np.exp(-hi - 2.0), dtype)
    # logit a' = log sp - log sa; the floors keep the logs finite and are inactive in range
    lsa = jnp.log(jnp.maximum(sa, tiny * sp + 1e-30))
    lsp = jnp.log(jnp.maximum(sp, tiny * sa + 1e-30))
    logit = jnp.clip(lsp - lsa, lo, hi)
    rho = jnp.where(spt > 0, sp / jnp.where(spt > 0, spt, 1.0), 0.0)
    return spt, rho, logit


def ms_correction(x, logit, eta):
    """`T`, the log ratio of the exact multiple-scattering profile to the better dipole's,
    at reduced distance `x`, `logit a'` and `eta`."""
    tab = table()
    dt = jnp.result_type(x, logit, eta)
    lx_nodes = tab["log_x"]
    x_max = float(np.exp(lx_nodes[-1]))
    lx = jnp.log(jnp.maximum(x, float(np.exp(lx_nodes[0]))))
    T = _interp(
        jnp.asarray(tab["T"], dt),
        [(lx, lx_nodes), (logit, tab["logit"]), (jnp.asarray(eta, dt), tab["eta"])],
    )
    slope = _interp(jnp.asarray(tab["slope"], dt), [(logit, tab["logit"])])
    return T + slope * jnp.maximum(x - x_max, 0.0)


def ms_total_correction(logit, eta):
    """`log(exact multiple-scattering total / better-dipole total)`."""
    tab = table()
    dt = jnp.result_type(logit, eta)
    return _interp(
        jnp.asarray(tab["log_total_ratio"], dt),
        [(logit, tab["logit"]), (jnp.asarray(eta, dt), tab["eta"])],
    )


def _far_decay(eta):
    """`k = eta + sqrt(eta^2 - 1)` (1 for `eta <= 1`): single scattering far from the beam
    decays as `e^{-k x}`, by the paths that leave at the critical angle."""
    over = eta > 1.0
    e2 = jnp.where(over, eta * eta - 1.0, 1.0)  # double where: finite gradient at eta = 1
    return jnp.where(over, eta + jnp.sqrt(e2), 1.0)


def single_unit(x, eta):
    """`S(x, eta)`: single-scattering exitance per unit albedo at reduced distance `x`
    (`sigma_t = 1`), per unit power entering, normal incidence, isotropic phase."""
    tab = table()
    dt = jnp.result_type(x, eta)
    eta = jnp.asarray(eta, dt)
    lx_nodes = tab["log_x"]
    lx = jnp.log(jnp.maximum(x, float(np.exp(lx_nodes[0]))))
    log_G = _interp(jnp.asarray(tab["log_G"], dt), [(lx, lx_nodes), (eta, tab["eta_S"])])
    return jnp.exp(log_G - _far_decay(eta) * x)


def single_total_unit(eta):
    """`S_total(eta)`: the single-scattering total per unit albedo (per unit power entering)."""
    tab = table()
    dt = jnp.result_type(eta, float)
    return _interp(jnp.asarray(tab["S_total"], dt), [(jnp.asarray(eta, dt), tab["eta_S"])])
