"""Jensen's measurement step: radial exitance profiles and fitting the dipole to them.

Jensen et al. (2001) lit a flat sample with a focused beam and fitted the dipole `R_d(r)` to
the photographed radial profile. `radial_profile` extracts the profile (mean exitant
radiance in annuli, with counts and standard errors) from an image; `fit_profile` fits
`sigma_a` and `sigmap_s` (mm^-1, per channel) with optimistix, optionally with a free
intensity scale, ignoring the (saturated) centre out to `r_min`; `model=` chooses the
diffusion profile fitted (`sssjax.profiles.PROFILES`: the classic dipole by default, the
better dipole, photon beam diffusion).

Residuals are relative (differences of logarithms, weighted by the relative standard
error): a profile spans decades, and absolute residuals would let the centre dominate.
`sigma_a` is only identifiable from the tail, beyond about one diffusion length
`1/sigma_tr`; a free scale makes it worse. The reported covariance shows this.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._tabulated import EtaRangeWarning, eta_outside
from .profiles import (
    Rd,
    check_profile,
    single_scatter,
    tabulated_covariance,
    tabulated_error,
    tabulated_level_error,
)

__all__ = [
    "Profile",
    "ProfileFit",
    "radial_profile",
    "fit_profile",
    "model_profile",
    "ORDERS",
    "check_orders",
]


@dataclasses.dataclass
class Profile:
    """A radial profile: `r` (mm, bin centres), `mean` and `stderr` `(n, channels)` (3 for
    RGB; any number is fitted channel by channel), `counts`, and optionally `bounds`
    `(n, 2)`, each annulus's inner and outer radius (mm).

    With `bounds` each `mean` is an annulus average (a Monte Carlo bin, `sssjax.reference`),
    and `fit_profile` compares it with the model's average over the same annulus; without,
    with the model's value at `r` (an image's annuli of one pixel, `r` their mean pixel
    radius). The difference matters: a profile's curvature over a bin of 6 % width moves
    its mean by up to 1 % from the value at the centroid, which biased the tabulated fit's
    `sigma_a` by -0.3 % (median over the presets) against bars of a few tenths of a percent."""

    r: np.ndarray
    mean: np.ndarray
    stderr: np.ndarray
    counts: np.ndarray
    bounds: np.ndarray | None = None


@dataclasses.dataclass
class ProfileFit:
    """Per-channel fitted coefficients (mm^-1) with standard errors, and the scale; `model`
    is the diffusion profile fitted (`sssjax.profiles.PROFILES`)."""

    sigma_a: np.ndarray
    sigmap_s: np.ndarray
    scale: np.ndarray
    sigma_a_stderr: np.ndarray
    sigmap_s_stderr: np.ndarray
    scale_stderr: np.ndarray
    steps: list[int]
    converged: list[bool]
    model: str = "dipole"
    orders: str = "multiple"


def radial_profile(
    image: np.ndarray,
    center: tuple[float, float],
    pixel_size_mm: float,
    *,
    r_max_mm: float | None = None,
    bin_mm: float | None = None,
) -> Profile:
    """Mean exitant radiance in annuli around `center` (pixel coordinates x, y).

    **Arguments:** `image` `(H, W, 3)` linear; `center` in pixels (pixel centres are at
    integer + 0.5); `pixel_size_mm` the side of a pixel on the sample; `r_max_mm` the
    largest radius (default: the distance to the nearest image edge); `bin_mm` the annulus
    width (default: one pixel).

    **Returns:** a `Profile`; annuli with fewer than 2 pixels are dropped.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"radial_profile: expected an (H, W, 3) image, got {img.shape}")
    if not pixel_size_mm > 0:
        raise ValueError(f"radial_profile: pixel_size_mm must be > 0, got {pixel_size_mm}")
    h, w = img.shape[:2]
    cx, cy = center
    ys, xs = np.mgrid[0:h, 0:w]
    r = np.hypot(xs + 0.5 - cx, ys + 0.5 - cy) * pixel_size_mm
    if r_max_mm is None:
        r_max_mm = min(cx, cy, w - cx, h - cy) * pixel_size_mm
    dr = bin_mm or pixel_size_mm
    edges = np.arange(0.0, r_max_mm + dr, dr)
    idx = np.digitize(r.ravel(), edges) - 1
    ok = (idx >= 0) & (idx < len(edges) - 1)
    idx, vals, rr = idx[ok], img.reshape(-1, 3)[ok], r.ravel()[ok]
    n = np.bincount(idx, minlength=len(edges) - 1)
    s1 = np.stack([np.bincount(idx, vals[:, c], len(edges) - 1) for c in range(3)], 1)
    s2 = np.stack([np.bincount(idx, vals[:, c] ** 2, len(edges) - 1) for c in range(3)], 1)
    rs = np.bincount(idx, rr, len(edges) - 1)
    keep = n >= 2
    n, s1, s2, rs = n[keep], s1[keep], s2[keep], rs[keep]
    mean = s1 / n[:, None]
    var = np.clip(s2 / n[:, None] - mean**2, 0, None) * n[:, None] / (n[:, None] - 1)
    return Profile(r=rs / n, mean=mean, stderr=np.sqrt(var / n[:, None]), counts=n)


def fit_profile(
    profile: Profile,
    eta: float = 1.3,
    *,
    r_min: float = 0.0,
    free_scale: bool = False,
    init: tuple[float, float] | None = None,
    rel_floor: float = 1e-3,
    max_steps: int = 200,
    model: str = "dipole",
    orders: str = "all",
) -> ProfileFit:
    """Fit `sigma_a`, `sigmap_s` (mm^-1) per channel so that `scale R_d(r)` matches the profile.

    **Arguments:** `profile` (its `mean` in units of `R_d`, i.e. exitance in mm^-2 per unit
    power *entering* the medium, after the entry Fresnel loss: `image_to_reflectance`
    converts an image to it; any units with `free_scale`; with `profile.bounds` each mean is
    matched by the model's average over its annulus, else by its value at `r`); `eta`; `r_min` (mm) excludes the centre; `free_scale` fits an
    overall intensity per channel too; `init` the starting `(sigma_a, sigmap_s)` (default: the best point of a log grid
    over 1e-4..10 and 1e-2..30 mm^-1);
    `rel_floor` a floor on the relative error of each annulus (model error, quantisation);
    `model` the diffusion profile fitted, one of `sssjax.profiles.PROFILES` (`"dipole"`,
    `"better_dipole"`, `"pbd"`, `"tabulated"`; named `model` because `profile` is the data);
    `orders` what the data holds: `"all"` (a photograph: single and multiple scattering; the
    model adds `sssjax.profiles.single_scatter`, the exact single scattering under a normal
    beam, so the centre of the profile can be used) or `"multiple"` (multiple scattering
    only, as the diffusion profiles model it). With `model="tabulated"` the table's own
    relative Monte Carlo error is added to each annulus's in quadrature, and the error of its
    absolute level (`sssjax.profiles.tabulated_level_error`) to the covariance as one error
    common to all annuli (for bright media over a few diffusion lengths `sigma_a` rests on
    that level).

    **Returns:** a `ProfileFit` with standard errors from the Gauss-Newton covariance.
    """
    check_profile(model)
    check_orders(orders)
    if model == "tabulated" and (note := eta_outside(eta)):
        warnings.warn(
            f"fit_profile: eta {note}; model 'better_dipole' has no such limit",
            EtaRangeWarning,
            stacklevel=2,
        )
    sel = (profile.r >= r_min) & np.all(profile.mean > 0, axis=1)
    # rows padded to a multiple of 32 (weight 0): the compiled solver is shared by profiles
    # of similar length instead of recompiled for each
    n_real = int(sel.sum())
    if n_real < 3 + free_scale:
        raise ValueError(
            f"fit_profile: {n_real} annuli beyond r_min = {r_min} mm with positive values in "
            f"every channel; at least {3 + free_scale} are needed"
        )
    n_rows = 32 * max(1, -(-n_real // 32))
    real = np.arange(n_rows) < n_real
    r_np = np.asarray(profile.r[sel], np.float64)
    r_np = np.concatenate([r_np, np.full(n_rows - n_real, r_np[0] if n_real else 1.0)])
    r = jnp.asarray(r_np, jnp.asarray(profile.r).dtype)
    nodes, nw = (jnp.asarray(a, r.dtype) for a in _annulus_nodes(profile, sel, n_rows))
    out = {k: [] for k in ("sa", "sp", "sc", "esa", "esp", "esc", "steps", "ok")}
    n_p = 3 if free_scale else 2
    resid_args = _residual(free_scale, model, orders)
    for c in range(np.shape(profile.mean)[1]):
        data = np.asarray(profile.mean[sel, c], np.float64)
        rel = np.sqrt((profile.stderr[sel, c] / data) ** 2 + rel_floor**2)
        data = np.concatenate([data, np.full(n_rows - n_real, data[0])])
        rel = np.concatenate([rel, np.ones(n_rows - n_real)])
        dt = jnp.asarray(profile.mean).dtype
        logd, w = jnp.asarray(np.log(data), dt), jnp.asarray(real / rel, dt)
        args = (nodes, nw, logd, w, jnp.asarray(eta, r.dtype))
        if init is None:
            starts = _grid_starts(nodes, nw, logd, w, eta, free_scale, model=model, orders=orders)
        else:
            starts = [jnp.asarray([np.log(init[0]), np.log(init[1])] + [0.0] * free_scale)]
        # several starts from the best grid points: the (sigma_a, sigmap_s) valley along
        # constant sigma_tr has local minima; keep the lowest final loss
        best = None
        for y0 in starts:
            sol = optx.least_squares(
                resid_args,
                optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10),
                y0,
                args=args,
                max_steps=max_steps,
                throw=False,
                options={"jac": "fwd"},
            )
            loss = float(jnp.sum(_call(resid_args, sol.value, args) ** 2))
            if best is None or loss < best[0]:
                best = (loss, sol)
        sol = best[1]
        if model == "tabulated":
            # the table's own error, at the coefficients found, then a polish from there
            v0 = np.exp(np.asarray(sol.value, np.float64))
            t_err = tabulated_error(np.asarray(r), v0[0], v0[1], eta)
            w = jnp.asarray(real / np.sqrt(rel**2 + t_err**2), dt)
            args = (nodes, nw, logd, w, jnp.asarray(eta, r.dtype))
            sol = optx.least_squares(
                resid_args,
                optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10),
                sol.value,
                args=args,
                max_steps=max_steps,
                throw=False,
                options={"jac": "fwd"},
            )
        y = sol.value
        J, rr = (np.asarray(x, dtype=np.float64) for x in _jac_and_resid(resid_args, y, args))
        s2 = float(rr @ rr) / max(n_real - n_p, 1)
        # the weights are real standard errors: use chi^2/dof only when it exceeds 1
        cov = max(s2, 1.0) * np.linalg.pinv(J.T @ J)
        if model == "tabulated":
            # the table's error is correlated between neighbouring annuli (its smoothing,
            # its continued tail), so it does not average out like the data's: the sandwich
            # pinv(J^T J) J^T W (C_data + C_table) W J pinv(J^T J) instead of independent
            # errors (which understated bright media's sigma_a error 2-5x)
            v0 = np.exp(np.asarray(y, np.float64))
            wn = np.asarray(w, np.float64)
            A = np.linalg.pinv(J.T @ J) @ J.T * wn[None, :]
            C_t = tabulated_covariance(np.asarray(r), v0[0], v0[1], eta)
            cov = max(s2, 1.0) * (A * rel[None, :] ** 2) @ A.T + A @ C_t @ A.T
        if model == "tabulated" and not free_scale:
            # the table's absolute level is uncertain as a whole (its Monte Carlo total):
            # a level shift d moves every weighted residual by d w, and the solution by
            # -pinv(J^T J) J^T w d; add that, fully correlated, to the covariance
            v0 = np.exp(np.asarray(y, np.float64))
            lvl = float(tabulated_level_error(v0[0], v0[1], eta))
            dy = -np.linalg.pinv(J.T @ J) @ (J.T @ np.asarray(w, np.float64))
            cov = cov + lvl**2 * np.outer(dy, dy)
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        v = np.exp(np.asarray(y, dtype=np.float64))
        out["sa"].append(v[0])
        out["sp"].append(v[1])
        out["sc"].append(v[2] if free_scale else 1.0)
        out["esa"].append(v[0] * sd[0])
        out["esp"].append(v[1] * sd[1])
        out["esc"].append(v[2] * sd[2] if free_scale else 0.0)
        out["steps"].append(int(sol.stats["num_steps"]))
        # in float32 the Cauchy test can stay unmet at the optimum (the loss is flat to
        # rounding and LM keeps taking sub-ulp steps): a solution whose remaining (float64)
        # Gauss-Newton step is 1% of its standard error or less has converged for any use
        step = np.linalg.lstsq(J, -rr, rcond=None)[0]
        settled = bool(np.all(np.abs(step) <= np.maximum(0.01 * sd, 1e-6)))
        out["ok"].append(bool(sol.result == optx.RESULTS.successful) or settled)
    a = {k: np.asarray(v) for k, v in out.items()}
    return ProfileFit(
        a["sa"],
        a["sp"],
        a["sc"],
        a["esa"],
        a["esp"],
        a["esc"],
        list(out["steps"]),
        list(out["ok"]),
        model,
        orders,
    )


ORDERS = ("all", "multiple")


def check_orders(orders: str) -> str:
    """`orders` if it is `"all"` or `"multiple"`, else a one-line `ValueError`."""
    if orders not in ORDERS:
        raise ValueError(f"orders must be 'all' or 'multiple', got {orders!r}")
    return orders


def model_profile(r, sigma_a, sigmap_s, eta, model: str = "dipole", orders: str = "all"):
    """What `fit_profile` fits: `R_d(r)` of `model`, plus the exact single scattering under
    a normal beam when `orders == "all"` (mm^-2 per unit power entering)."""
    m = Rd(r, sigma_a, sigmap_s, eta, model)
    if orders == "all":
        m = m + single_scatter(r, sigma_a, sigmap_s, eta)
    return m


@functools.cache
def _residual(free_scale: bool, model: str, orders: str = "multiple"):
    """The weighted log residual `(log(scale R_d(r)) - log data) w` of `y = log(sigma_a,
    sigmap_s[, scale])`, `args = (nodes, node weights, log data, w, eta)`
    (`_annulus_nodes`): one function object per layout, so
    its compiled solver step is reused across channels and calls."""

    def resid(y, args):
        nodes, nw, logd, w, eta = args
        sa, sp = jnp.exp(y[0]), jnp.exp(y[1])
        logm = _log_annulus_model(nodes, nw, sa, sp, eta, model, orders)
        return (logm + (y[2] if free_scale else 0.0) - logd) * w

    return resid


@eqx.filter_jit
def _call(fn, y, args):
    return fn(y, args)


@eqx.filter_jit
def _jac_and_resid(resid, y, args):
    return jax.jacfwd(resid)(y, args), resid(y, args)


# Gauss-Legendre nodes per annulus: exact for polynomials of degree 11 in r, so for a bin
# of a Monte Carlo profile (6 % wide, or a decay of a few e-folds) the quadrature error is
# far below the data's
ANNULUS_NODES = 6


def _annulus_nodes(profile: Profile, sel: np.ndarray, n_rows: int):
    """Radii and weights `(n_rows, q)` (mm, summing to 1 per row) at which `fit_profile`
    averages the model for each fitted annulus: Gauss-Legendre over `profile.bounds` with
    the area weight `r dr` (`q = ANNULUS_NODES`), or the row's `r` alone (`q = 1`) without
    bounds. Padding rows repeat the first."""
    r = np.asarray(profile.r, np.float64)
    if profile.bounds is None:
        nodes, nw = r[sel, None], np.ones((int(sel.sum()), 1))
    else:
        b = np.asarray(profile.bounds, np.float64)
        if b.shape != (r.size, 2):
            raise ValueError(
                f"fit_profile: profile.bounds must be (n, 2) = ({r.size}, 2) (inner, outer "
                f"radius per annulus), got {b.shape}"
            )
        lo, hi = b[sel, 0], b[sel, 1]
        bad = ~(np.isfinite(lo) & np.isfinite(hi) & (lo >= 0) & (hi > lo))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"fit_profile: profile.bounds must hold 0 <= inner < outer (mm), got "
                f"({lo[i]}, {hi[i]}) for the annulus at r = {r[sel][i]}"
            )
        gx, gw = np.polynomial.legendre.leggauss(ANNULUS_NODES)
        nodes = lo[:, None] + (hi - lo)[:, None] * (gx + 1) / 2
        nw = gw * nodes
        nw = nw / nw.sum(axis=1, keepdims=True)
    pad = n_rows - nodes.shape[0]
    return (
        np.concatenate([nodes, np.repeat(nodes[:1], pad, 0)]),
        np.concatenate([nw, np.repeat(nw[:1], pad, 0)]),
    )


def _log_annulus_model(nodes, nw, sa, sp, eta, model, orders):
    """`log` of the model averaged over each annulus's nodes (last axis of `nodes`)."""
    return jnp.log(jnp.sum(nw * model_profile(nodes, sa, sp, eta, model, orders), axis=-1))


@functools.partial(jax.jit, static_argnames=("model", "orders"))
def _grid_log_model(nodes, nw, sa, sp, eta, model, orders="multiple"):
    """`log R_d` averaged over each annulus (`_annulus_nodes`) on the `(sa, sp)` grid,
    `(len(sa), len(sp), rows)`, one row of `sa` at a time (PBD's 100 depths would not fit
    in memory at once)."""
    return jax.lax.map(
        lambda a: _log_annulus_model(
            nodes[None], nw[None], a, sp[:, None, None], eta, model, orders
        ),
        sa,
    )


def _grid_starts(
    nodes,
    nw,
    logd,
    w,
    eta,
    free_scale,
    n_starts: int = 6,
    model: str = "dipole",
    orders: str = "multiple",
):
    """The best `n_starts` local minima of the loss on a log grid of `(sigma_a, sigmap_s)`
    (with the best log-scale offset in closed form when the scale is free), for the
    diffusion profile `model`."""
    sa = jnp.exp(jnp.linspace(np.log(1e-4), np.log(10.0), 48))
    sp = jnp.exp(jnp.linspace(np.log(1e-2), np.log(30.0), 48))
    A, P = jnp.meshgrid(sa, sp, indexing="ij")
    logm = _grid_log_model(nodes, nw, sa, sp, eta, model, orders)  # (48, 48, n)
    d = (logm - logd) * w
    off = jnp.zeros(A.shape + (1,))
    if free_scale:
        off = -jnp.sum(d * w, axis=-1, keepdims=True) / jnp.sum(w * w)
        d = d + off * w
    loss = np.asarray(jnp.where(jnp.isfinite(d).all(-1), jnp.sum(d * d, axis=-1), jnp.inf))
    pad = np.pad(loss, 1, constant_values=np.inf)
    neigh = np.min(
        [
            np.roll(np.roll(pad, a, 0), b, 1)[1:-1, 1:-1]
            for a in (-1, 0, 1)
            for b in (-1, 0, 1)
            if (a, b) != (0, 0)
        ],
        axis=0,
    )
    cand = np.argwhere(loss <= neigh)
    cand = cand[np.argsort(loss[tuple(cand.T)])][:n_starts]
    starts = []
    for i, j in cand:
        y = [jnp.log(sa[i]), jnp.log(sp[j])] + ([off[i, j, 0]] if free_scale else [])
        starts.append(jnp.asarray(y))
    return starts


# --- from an image to coefficients: the `sssjax measure` step ---------------------------
def find_center(image: np.ndarray) -> tuple[float, float]:
    """The beam's entry point in pixel coordinates `(x, y)`: the intensity-weighted centroid
    of the pixels brighter than half the maximum (of the channel sum).

    **Arguments:** `image` `(H, W, 3)` linear. **Returns:** `(x, y)` (pixel centres at +0.5).
    """
    lum = np.asarray(image, dtype=np.float64).sum(axis=-1)
    sel = lum >= 0.5 * lum.max()
    ys, xs = np.nonzero(sel)
    w = lum[ys, xs]
    return float(np.sum((xs + 0.5) * w) / w.sum()), float(np.sum((ys + 0.5) * w) / w.sum())


def image_to_reflectance(
    image: np.ndarray,
    eta: float,
    power: float | np.ndarray | None = None,
    *,
    incidence_deg: float = 0.0,
    view_deg: float = 0.0,
) -> np.ndarray:
    """Convert exitant radiance `L` to the units of `R_d` (mm^-2 per unit power entering).

    The model behind it (and behind the renderer): `L = F_t(theta_o)/pi R_d(r) Phi` with
    `Phi = P F_t(theta_i)` the beam power that enters. So
    `R_d = pi L / (F_t(theta_o) F_t(theta_i) P)`. With `power=None` only the constant
    factors are removed, and the fit must then free the scale.

    **Arguments:** `image` `(H, W, 3)` linear radiance (W mm^-2 sr^-1); `eta` the sample's
    relative index; `power` the beam power (W, scalar or RGB); `incidence_deg`, `view_deg`
    the beam's and the camera's angles from the surface normal.
    """
    from .dipole import fresnel_transmittance

    ft_i = float(fresnel_transmittance(np.cos(np.radians(incidence_deg)), eta))
    ft_o = float(fresnel_transmittance(np.cos(np.radians(view_deg)), eta))
    p = np.ones(3) if power is None else np.broadcast_to(np.asarray(power, float), (3,))
    return np.asarray(image, np.float64) * np.pi / (ft_o * ft_i * p)
