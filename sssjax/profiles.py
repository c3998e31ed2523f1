"""Diffusion profiles `R_d(r)`: the classic dipole, d'Eon's better dipole, photon beam diffusion.

Every profile here has the convention of `sssjax.dipole.Rd`: `R_d(r)` is the radiant
exitance (mm^-2) at distance `r` from where a unit power enters a semi-infinite medium along
the normal, so that `int_0^inf 2 pi r R_d(r) dr = Rd_total`, the total diffuse reflectance.
All functions are pure jax, broadcast like `dipole.Rd` (RGB axis last) and are differentiable
with respect to `sigma_a` and `sigmap_s`, NaN-free at `r = 0` and `sigma_a = 0` (where, as in
`dipole`, the square root `sigma_tr = sqrt(...)` has a zero rather than infinite derivative).

- `"dipole"`: the classic dipole of Jensen et al. 2001 (`sssjax.dipole`), unchanged.
- `"better_dipole"`: d'Eon (2012), "A better dipole". Grosjean's diffusion coefficient
  `D = (2 sigma_a + sigmap_s) / (3 sigmap_t^2)`, `sigma_tr = sqrt(sigma_a / D)`, the real source
  at `z_r = 1/sigmap_t`, the extrapolation distance `z_b = 2 A D` with
  `A = (1 + 3 C_2) / (1 - 2 C_1)`, the virtual source at `z_v = -z_r - 2 z_b`, and the exitance
  `R_d = alpha_p (C_phi phi(r) + C_E E_n(r))`, which combines the fluence `phi` and the normal
  flux `E_n` of the dipole with `C_phi = (1 - 2 C_1)/4`, `C_E = (1 - 3 C_2)/2`. `C_1`, `C_2` are
  the first two moments of the exact Fresnel reflectance seen from inside,
  `C_k = int_0^1 F_r(mu) mu^k dmu` (`fresnel_moment`; computed by quadrature, not a fit).
  Its total is in closed form and tends to exactly 1 as `sigma_a -> 0`.
- `"pbd"`: photon beam diffusion (Habel, Christensen, Jarosz 2013), multiple-scattering part,
  as pbrt-v3's `BeamDiffusionMS`: the better-dipole point source integrated along the normally
  incident beam, at the 100 fixed depths `z_i = -ln(1 - (i + 1/2)/100) / sigmap_t` (the
  quantiles of the reduced first-collision density `sigmap_t e^{-sigmap_t z}`), each weighted
  by pbrt's `rho_p^2 kappa_i`, `kappa_i = 1 - e^{-2 sigmap_t (d_r + z_i)}`:
  `R_d(r) = rho_p^2 / 100 sum_i kappa_i (C_phi phi_i(r) + C_E E_n,i(r))`. One factor of the
  reduced albedo `rho_p` is the source strength `Q(z)/p(z)` of the depth sampling; pbrt
  multiplies by a second one, and so do we, so that `pbd` is pbrt's function. Its
  normalisation is ours: pbrt tabulates `2 pi r (BeamDiffusionSS + BeamDiffusionMS)(r)` and
  integrates it over `r` to the effective albedo `rho_eff` (exitance per unit power that
  entered; the entry Fresnel factor is in pbrt's separate `Sw` term, the exit one in `C_phi`,
  `C_E`), i.e. `int 2 pi r R_d dr = Rd_total` as for `dipole.Rd`. The
  `kappa` factor (Habel et al.) removes the unphysical contribution of shallow sources near
  `r = 0`. pbrt uses polynomial fits for the Fresnel moments; we use the exact moments (at
  `eta = 1.3` pbrt's `C_2` is 0.9% off, which changes the profile by up to 0.4%). The total
  has no elementary closed form because of `kappa`; `Rd_total` evaluates it semi-analytically
  (closed forms with the exponential integral for every term but one, which is a smooth
  Gauss-Laguerre integral; it matches quadrature of the profile to ~1e-14 in float64).

- `"tabulated"`: exact transport (no diffusion approximation), from a table of
  `sssjax.reference` Monte Carlo runs shipped with the package (`sssjax/data`, rebuilt by
  `benchmarks/profile_table.py`): the better dipole corrected by the tabulated log ratio of
  the Monte Carlo multiple-scattering exitance to it, in reduced units (`r sigmap_t`, reduced
  albedo `sigmap_s / sigmap_t`, eta 1.0-1.6), interpolated by cubics (see
  `sssjax._tabulated`). Isotropic scattering was tabulated: for `g != 0` the similarity
  relation (`sigmap_s = sigma_s (1 - g)`) is the approximation. Its Monte Carlo error is
  stored with it (`tabulated_error`).

Single scattering under the beam (`single_scatter`, `single_scatter_total`) is the exact
closed form for a normally incident beam and isotropic phase (tabulated in `eta`), for any
profile: the diffusion profiles model multiple scattering only, and a photograph sees both.

Cost: `better_dipole` is as cheap as the dipole; `pbd` evaluates 100 point sources per
distance (about 100 times the arithmetic).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from . import _tabulated, dipole
from ._numerics import safe_div, safe_sqrt
from ._registry import Registry
from .scattering import fresnel_moment, fresnel_moments

__all__ = [
    "PROFILES",
    "check_profile",
    "Rd",
    "Rd_total",
    "fresnel_moment",
    "C_phi",
    "C_E",
    "A_better",
    "diffusion_coefficient",
    "sigma_tr_better",
    "PBD_DEPTHS",
    "single_scatter",
    "single_scatter_total",
    "tabulated_covariance",
    "tabulated_error",
    "tabulated_level_error",
]

PROFILES = ("dipole", "better_dipole", "pbd", "tabulated")

# Gauss-Laguerre for the one non-elementary part of the PBD total
_LAG_X, _LAG_W = np.polynomial.laguerre.laggauss(32)
PBD_DEPTHS = 100
_PBD_Q = -np.log1p(-(np.arange(PBD_DEPTHS) + 0.5) / PBD_DEPTHS)  # z_i sigmap_t


def check_profile(profile: str) -> str:
    """`profile` if it is one of `PROFILES`, else a `ValueError` with a did-you-mean hint."""
    return Registry("profile", dict.fromkeys(PROFILES)).check(profile)


def _dtype(*xs):
    return jnp.result_type(*[jnp.asarray(x) for x in xs], float)


def _exp1(x):
    """The exponential integral `E_1(x)`, `x > 0`, to ~1e-12 relative (float64): the power
    series below 2, a continued fraction (evaluated backwards, fixed depth) above. Plain
    arithmetic, so it compiles and differentiates cheaply (`jax.scipy.special.exp1` is slow
    to compile)."""
    lo = x < 2.0
    xs = jnp.where(lo, x, 1.0)

    def series_step(n, c):
        term, acc = c
        term = term * -xs / n
        return term, acc - term / n

    _, series = jax.lax.fori_loop(1, 31, series_step, (jnp.ones_like(xs), jnp.zeros_like(xs)))
    series = -np.euler_gamma - jnp.log(xs) + series
    xl = jnp.where(lo, 2.0, x)

    def fraction_step(i, f):
        n = 30 - i
        return xl + (2 * n - 1) - n * n / f

    f = jax.lax.fori_loop(0, 30, fraction_step, xl + 61.0)
    return jnp.where(lo, series, jnp.exp(-xl) / f)


def C_phi(eta: ArrayLike) -> Array:
    """`C_phi = (1 - 2 C_1)/4`: exitance per unit fluence just inside the boundary."""
    return 0.25 * (1.0 - 2.0 * fresnel_moment(eta, 1))


def C_E(eta: ArrayLike) -> Array:
    """`C_E = (1 - 3 C_2)/2`: exitance per unit normal flux just inside the boundary."""
    return 0.5 * (1.0 - 3.0 * fresnel_moment(eta, 2))


def A_better(eta: ArrayLike) -> Array:
    """The better dipole's boundary constant `A = (1 + 3 C_2)/(1 - 2 C_1)`, `z_b = 2 A D`."""
    c1, c2 = fresnel_moments(eta, (1, 2))
    return (1.0 + 3.0 * c2) / (1.0 - 2.0 * c1)


# --- the better dipole ---------------------------------------------------------------------
def diffusion_coefficient(sigma_a: ArrayLike, sigmap_s: ArrayLike) -> Array:
    """Grosjean's (non-classical) diffusion coefficient `D = (2 sigma_a + sigmap_s) /
    (3 sigmap_t^2)` in mm (the classic dipole has `1 / (3 sigmap_t)`)."""
    sigma_a, sigmap_s = jnp.asarray(sigma_a), jnp.asarray(sigmap_s)
    return safe_div(2.0 * sigma_a + sigmap_s, 3.0 * (sigma_a + sigmap_s) ** 2)


def sigma_tr_better(sigma_a: ArrayLike, sigmap_s: ArrayLike) -> Array:
    """The better dipole's effective transport coefficient `sqrt(sigma_a / D)`, mm^-1."""
    return safe_sqrt(safe_div(jnp.asarray(sigma_a), diffusion_coefficient(sigma_a, sigmap_s)))


def _coeffs(sigma_a, sigmap_s, eta):
    dt = _dtype(sigma_a, sigmap_s, eta)
    sigma_a = jnp.asarray(sigma_a, dt)
    sigmap_s = jnp.asarray(sigmap_s, dt)
    eta = jnp.asarray(eta, dt)
    sigmap_t = sigma_a + sigmap_s
    rho = safe_div(sigmap_s, sigmap_t)
    D = diffusion_coefficient(sigma_a, sigmap_s)
    s = safe_sqrt(safe_div(sigma_a, D))
    c1, c2 = fresnel_moments(eta, (1, 2))
    z_b = 2.0 * D * (1.0 + 3.0 * c2) / (1.0 - 2.0 * c1)
    return dict(
        sigmap_t=sigmap_t,
        rho=rho,
        D=D,
        s=s,
        z_b=z_b,
        cphi=0.25 * (1.0 - 2.0 * c1),
        ce=0.5 * (1.0 - 3.0 * c2),
    )


def _exitance(r, z, k):
    """`C_phi phi + C_E E_n` at distance `r` for a unit isotropic source at depth `z` (> 0)
    and its image at `z_v = -z - 2 z_b`. The fluence difference of the two images is written
    without cancellation (it is tiny compared to either term far away)."""
    s, D, z_b = k["s"], k["D"], k["z_b"]
    zv = z + 2.0 * z_b  # |z_v|
    d_r = jnp.sqrt(r**2 + z**2)  # z > 0: never sqrt(0)
    d_v = jnp.sqrt(r**2 + zv**2)
    delta = (zv**2 - z**2) / (d_v + d_r)  # d_v - d_r >= 0, accurately
    e_r = jnp.exp(-s * d_r)
    # phi = e^{-s d_r}/(4 pi D d_r) (1 - (d_r/d_v) e^{-s delta})
    phi = e_r / (4.0 * jnp.pi * D * d_r) * -jnp.expm1(-(s * delta + jnp.log1p(delta / d_r)))
    e_v = jnp.exp(-s * d_v)
    E_n = (z * (1.0 + s * d_r) * e_r / d_r**3 + zv * (1.0 + s * d_v) * e_v / d_v**3) / (
        4.0 * jnp.pi
    )
    return k["cphi"] * phi + k["ce"] * E_n, d_r


def _one_minus_exp_over(x):
    """`(1 - e^{-x}) / x`, 1 at `x = 0`, with finite gradients (x >= 0)."""
    ok = x > 1e-4
    xs = jnp.where(ok, x, 1.0)
    return jnp.where(ok, -jnp.expm1(-xs) / xs, 1.0 - x / 2.0 + x**2 / 6.0)


def _total_unit(z, k):
    """`int 2 pi r (C_phi phi + C_E E_n) dr` for a unit source at depth `z`, closed form:
    `C_phi (e^{-s z} - e^{-s |z_v|})/(2 D s) + C_E (e^{-s z} + e^{-s |z_v|})/2`."""
    s, z_b = k["s"], k["z_b"]
    e_z = jnp.exp(-s * z)
    phi = k["cphi"] * e_z * (z_b / k["D"]) * _one_minus_exp_over(2.0 * s * z_b)
    return phi + 0.5 * k["ce"] * (e_z + jnp.exp(-s * (z + 2.0 * z_b)))


def _pbd_kappa_loss(z, k):
    """`int 2 pi r e^{-2 sigmap_t (d_r + z)} (C_phi phi + C_E E_n) dr`: what `kappa` removes.

    The real-source terms are elementary (with the exponential integral `E_1`); the
    virtual-source terms, with `u = d_r - z`, are `e^{-2cz}/c int_0^inf e^{-t} f(t) dt`
    (`c = 2 sigmap_t`, `t = c u`) with `f` smooth on the scale of `t ~ c |z_v| > 2`:
    32-point Gauss-Laguerre."""
    s, D, z_b = k["s"], k["D"], k["z_b"]
    c = 2.0 * k["sigmap_t"]
    kk = s + c
    real = jnp.exp(-c * z) * (
        k["cphi"] * jnp.exp(-kk * z) / (2.0 * D * kk)
        + 0.5 * k["ce"] * (jnp.exp(-kk * z) - c * z * _exp1(kk * z))
    )
    dt = z.dtype
    t = jnp.asarray(_LAG_X, dt)
    w = jnp.asarray(_LAG_W, dt)
    zv = (z + 2.0 * z_b)[..., None]
    zz, cc, ss = z[..., None], c[..., None], s[..., None]
    d_r = zz + t / cc
    d_v = jnp.sqrt(t / cc * (2.0 * zz + t / cc) + zv**2)
    e_v = jnp.exp(-ss * d_v)
    f = d_r * (
        -k["cphi"][..., None] * e_v / (D[..., None] * d_v)
        + k["ce"][..., None] * zv * (1.0 + ss * d_v) * e_v / d_v**3
    )
    virtual = jnp.exp(-2.0 * c * z) / (2.0 * c) * jnp.sum(w * f, axis=-1)
    return real + virtual


def _expand(k, *xs):
    """Broadcast the coefficient dict and `xs` to one shape."""
    shape = jnp.broadcast_shapes(*[jnp.shape(v) for v in k.values()], *[jnp.shape(x) for x in xs])
    k = {n: jnp.broadcast_to(v, shape) for n, v in k.items()}
    return k, [jnp.broadcast_to(x, shape) for x in xs]


def _better_Rd(r, sigma_a, sigmap_s, eta):
    k = _coeffs(sigma_a, sigmap_s, eta)
    r = jnp.asarray(r, k["D"].dtype)
    z_r = safe_div(1.0, k["sigmap_t"], jnp.inf)
    E, _ = _exitance(r, z_r, k)
    return k["rho"] * E


def _better_total(sigma_a, sigmap_s, eta):
    k = _coeffs(sigma_a, sigmap_s, eta)
    z_r = safe_div(1.0, k["sigmap_t"], jnp.inf)
    return k["rho"] * _total_unit(z_r, k)


def _pbd_depths(k):
    q = jnp.asarray(_PBD_Q, k["D"].dtype)
    return {n: v[..., None] for n, v in k.items()}, safe_div(1.0, k["sigmap_t"])[..., None] * q


def _pbd_Rd(r, sigma_a, sigmap_s, eta):
    k = _coeffs(sigma_a, sigmap_s, eta)
    r = jnp.asarray(r, k["D"].dtype)
    k, (r,) = _expand(k, r)
    k, z = _pbd_depths(k)
    E, d_r = _exitance(r[..., None], z, k)
    kappa = -jnp.expm1(-2.0 * k["sigmap_t"] * (d_r + z))
    return k["rho"][..., 0] ** 2 * jnp.mean(kappa * E, axis=-1)


def _pbd_total(sigma_a, sigmap_s, eta):
    k = _coeffs(sigma_a, sigmap_s, eta)
    k, _ = _expand(k)
    k, z = _pbd_depths(k)
    per_depth = _total_unit(z, k) - _pbd_kappa_loss(z, k)
    return k["rho"][..., 0] ** 2 * jnp.mean(per_depth, axis=-1)


def _tab_Rd(r, sigma_a, sigmap_s, eta):
    dt = _dtype(r, sigma_a, sigmap_s, eta)
    spt, _, logit = _tabulated.reduced(sigma_a, sigmap_s, dt)
    x = jnp.asarray(r, dt) * spt
    T = _tabulated.ms_correction(x, logit, jnp.asarray(eta, dt))
    # T > 80 only far out, where the better dipole has underflowed: keep 0 * e^T finite
    return _better_Rd(r, sigma_a, sigmap_s, eta) * jnp.exp(jnp.minimum(T, 80.0))


def _tab_total(sigma_a, sigmap_s, eta):
    dt = _dtype(sigma_a, sigmap_s, eta)
    _, _, logit = _tabulated.reduced(sigma_a, sigmap_s, dt)
    corr = _tabulated.ms_total_correction(logit, jnp.asarray(eta, dt))
    return _better_total(sigma_a, sigmap_s, eta) * jnp.exp(corr)


@functools.cache
def _tab_err_filled() -> np.ndarray:
    """`T_err` with the nodes before the first precise one given its error."""
    err = np.asarray(_tabulated.table()["T_err"], np.float64)
    filled = err.copy()
    pos = np.arange(err.shape[0])
    for ia in range(err.shape[1]):
        for ie in range(err.shape[2]):
            j = np.nonzero(np.isfinite(err[:, ia, ie]))[0]
            if j.size:
                filled[:, ia, ie] = err[j[np.abs(pos[:, None] - j[None, :]).argmin(1)], ia, ie]
    return filled


def tabulated_error(
    r: ArrayLike, sigma_a: ArrayLike, sigmap_s: ArrayLike, eta: ArrayLike
) -> np.ndarray:
    """The tabulated profile's relative Monte Carlo error (one standard error) at `r` (mm)
    for the coefficients (mm^-1), interpolated like the profile (NumPy, float64). Where the
    table continues the profile beyond its precise bins, the error of its envelope of two
    tail fits (`benchmarks/profile_table.py`): their statistical error plus their
    difference, the model's uncertainty (`--check-tail` measures how well it covers)."""
    tab = _tabulated.table()
    spt, _, logit = _tabulated.reduced(sigma_a, sigmap_s, jnp.float32)
    x = jnp.asarray(r, jnp.float32) * spt
    lx = jnp.log(jnp.maximum(x, float(np.exp(tab["log_x"][0]))))
    out = _tabulated._interp(
        jnp.asarray(_tab_err_filled(), jnp.float32),
        [(lx, tab["log_x"]), (logit, tab["logit"]), (jnp.asarray(eta, jnp.float32), tab["eta"])],
    )
    return np.abs(np.asarray(out, np.float64))


@functools.cache
def _smoother_correlation() -> np.ndarray:
    """Correlation of the table's smoothed nodes `d = 0, 1, ...` bins apart: the overlap of
    the builder's equivalent kernel (a local quadratic with a tricube window of
    `smooth_half` bins, `benchmarks/profile_table.py`), for equal raw variances."""
    half = int(_tabulated.table().get("smooth_half", 3))
    u = np.arange(-half, half + 1.0)
    k = (1 - (np.abs(u) / (half + 1)) ** 3) ** 3
    A = np.stack([np.ones_like(u), u, u * u], 1)
    ell = (np.linalg.inv(A.T @ (k[:, None] * A)) @ (A.T * k))[0]
    rho = np.array([np.sum(ell[d:] * ell[: ell.size - d]) for d in range(ell.size)])
    return np.append(rho / rho[0], 0.0)


def tabulated_covariance(
    r: ArrayLike, sigma_a: ArrayLike, sigmap_s: ArrayLike, eta: float
) -> np.ndarray:
    """The covariance `(n, n)` of the tabulated profile's relative (log) error at the `n`
    distances `r` (mm) of one medium (scalar coefficients, mm^-1): `tabulated_error` on the
    diagonal, correlated as the builder's smoothing correlates neighbouring nodes (about two
    bins, 1/8 decade of `x`), and fully correlated beyond the last precise node (the
    continued tail moves with it) and before the first. A fit whose annuli are denser than
    the table's nodes must use this, not independent errors: its `sigma_a` error is
    otherwise understated (`sssjax.measure.fit_profile`)."""
    tab = _tabulated.table()
    r = np.asarray(r, np.float64).ravel()
    sig = tabulated_error(r, sigma_a, sigmap_s, eta).ravel()
    spt = float(sigma_a) + float(sigmap_s)
    lx_nodes = np.asarray(tab["log_x"], np.float64)
    h = lx_nodes[1] - lx_nodes[0]
    logit = np.clip(
        np.log(max(float(sigmap_s), 1e-30)) - np.log(max(float(sigma_a), 1e-30)),
        tab["logit"][0],
        tab["logit"][-1],
    )
    ia = int(np.argmin(np.abs(tab["logit"] - logit)))
    ie = int(np.argmin(np.abs(tab["eta"] - float(eta))))
    good = np.flatnonzero(np.isfinite(tab["T_err"][:, ia, ie]) & ~tab["continued"][:, ia, ie])
    u = (np.log(np.maximum(r * spt, 1e-300)) - lx_nodes[0]) / h
    if good.size:
        u = np.clip(u, good[0], good[-1])
    rho_d = _smoother_correlation()
    d = np.abs(u[:, None] - u[None, :])
    rho = np.interp(d, np.arange(rho_d.size), rho_d, right=0.0)
    return sig[:, None] * sig[None, :] * rho


def tabulated_level_error(sigma_a: ArrayLike, sigmap_s: ArrayLike, eta: ArrayLike) -> np.ndarray:
    """The tabulated profile's relative error of its absolute level (one standard error of
    the Monte Carlo multiple-scattering total, lost photons included), interpolated. It is
    common to every distance, so a fit must treat it as one correlated error."""
    tab = _tabulated.table()
    rel = np.asarray(tab["ms_total_err"], np.float64) / np.asarray(tab["ms_total"], np.float64)
    _, _, logit = _tabulated.reduced(sigma_a, sigmap_s, jnp.float32)
    out = _tabulated._interp(
        jnp.asarray(rel, jnp.float32),
        [(logit, tab["logit"]), (jnp.asarray(eta, jnp.float32), tab["eta"])],
    )
    return np.abs(np.asarray(out, np.float64))


def single_scatter(r: ArrayLike, sigma_a: ArrayLike, sigmap_s: ArrayLike, eta: ArrayLike) -> Array:
    """Single-scattering exitance `R_ss(r)` (mm^-2, per unit power entering) of a
    semi-infinite medium under a normally incident pencil beam: the exact closed form for an
    isotropic phase function (`sssjax.reference.single_scatter_profile`), tabulated in `eta`
    (1.0-1.6) and interpolated. With reduced coefficients it is the similarity relation's
    stand-in for the real (phase-dependent) single scattering.

    **Arguments:** `r` mm; `sigma_a`, `sigmap_s` mm^-1; `eta`. **Returns:** broadcast shape.
    """
    dt = _dtype(r, sigma_a, sigmap_s, eta)
    spt, rho, _ = _tabulated.reduced(sigma_a, sigmap_s, dt)
    x = jnp.asarray(r, dt) * spt
    return rho * spt**2 * _tabulated.single_unit(x, jnp.asarray(eta, dt))


def single_scatter_total(sigma_a: ArrayLike, sigmap_s: ArrayLike, eta: ArrayLike) -> Array:
    """`int 2 pi r R_ss(r) dr` of `single_scatter`: the single-scattering total (per unit
    power entering), dimensionless."""
    dt = _dtype(sigma_a, sigmap_s, eta)
    _, rho, _ = _tabulated.reduced(sigma_a, sigmap_s, dt)
    return rho * _tabulated.single_total_unit(jnp.asarray(eta, dt))


# --- the public entry points -----------------------------------------------------------------
def Rd(
    r: ArrayLike,
    sigma_a: ArrayLike,
    sigmap_s: ArrayLike,
    eta: ArrayLike,
    profile: str = "dipole",
) -> Array:
    """Diffuse reflectance profile `R_d(r)` of the chosen diffusion model.

    **Arguments:**

    - `r`: distance between entry and exit points, mm (any batch shape).
    - `sigma_a`, `sigmap_s`: absorption and reduced scattering coefficients, mm^-1
      (`sigma_a + sigmap_s > 0`).
    - `eta`: relative index of refraction (inside / outside).
    - `profile`: one of `PROFILES` (`"dipole"`, `"better_dipole"`, `"pbd"`,
      `"tabulated"`); static.

    **Returns:** `R_d(r)` in mm^-2, exitance per unit power entering the medium, broadcast
    shape; `int_0^inf 2 pi r R_d(r) dr = Rd_total(..., profile)`.
    """
    check_profile(profile)
    if profile == "dipole":
        return dipole.Rd(r, sigma_a, sigmap_s, eta)
    if profile == "better_dipole":
        return _better_Rd(r, sigma_a, sigmap_s, eta)
    if profile == "tabulated":
        return _tab_Rd(r, sigma_a, sigmap_s, eta)
    return _pbd_Rd(r, sigma_a, sigmap_s, eta)


def Rd_total(
    sigma_a: ArrayLike, sigmap_s: ArrayLike, eta: ArrayLike, profile: str = "dipole"
) -> Array:
    """Total diffuse reflectance `int_0^inf 2 pi r R_d(r) dr` of the chosen profile.

    Closed form for `"dipole"` and `"better_dipole"` (the latter tends to 1 as
    `sigma_a -> 0`); semi-analytic for `"pbd"` (see the module docstring); for
    `"tabulated"` the Monte Carlo total, interpolated.

    **Arguments:** `sigma_a`, `sigmap_s` in mm^-1; `eta`; `profile` one of `PROFILES`.

    **Returns:** the dimensionless total, broadcast shape of the coefficients.
    """
    check_profile(profile)
    if profile == "dipole":
        return dipole.Rd_total(sigma_a, sigmap_s, eta)
    if profile == "better_dipole":
        return _better_total(sigma_a, sigmap_s, eta)
    if profile == "tabulated":
        return _tab_total(sigma_a, sigmap_s, eta)
    return _pbd_total(sigma_a, sigmap_s, eta)
