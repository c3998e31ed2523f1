"""Pictures: diffusion profiles, convergence plots. matplotlib with the Agg backend (no screen)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

_RGB = ("#d62728", "#2ca02c", "#1f77b4")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path, dpi: int = 110) -> Path:
    """Write `fig` to `path` (creating its folder, atomically) and close it."""
    plt = _pyplot()
    from ._files import save_figure

    fig.tight_layout()
    try:
        return save_figure(fig, path, dpi=dpi)  # atomic: never half a PNG
    finally:
        plt.close(fig)


def plot_profiles(names: Sequence[str], path: str | Path, r_max_mm: float = 20.0) -> Path:
    """Plot `R_d(r)` (log scale, mm^-2) against r (mm) per RGB channel for named presets.

    **Arguments:** `names` of presets; `path` of the PNG to write; `r_max_mm` the range.

    **Returns:** the path written.
    """
    from .dipole import Rd
    from .media import preset

    plt = _pyplot()
    r = np.linspace(0.0, r_max_mm, 400)
    n = len(names)
    cols = min(n, 3)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    for ax, name in zip(axes.ravel(), names, strict=False):
        m = preset(name)
        prof = np.asarray(Rd(r[:, None], m.sigma_a, m.sigmap_s, m.eta))
        for c in range(3):
            ax.semilogy(r, prof[:, c], color=_RGB[c], label="RGB"[c])
        ax.set_title(name)
        ax.set_xlabel("r [mm]")
        ax.set_ylabel("R_d(r) [mm$^{-2}$]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.suptitle("Classic dipole diffuse reflectance profiles (Jensen et al. 2001 media)")
    return _save(fig, path)


def fit_triptych(
    target: np.ndarray, fitted: np.ndarray, path: str | Path, left_out: np.ndarray | None = None
) -> tuple[Path, float, float]:
    """Target | fit | residual picture with PSNR and SSIM of the fit against the target.

    Images are compared after the same display mapping (scaled by the target's 99.5th
    percentile, sRGB-encoded), which is what a person sees. `left_out`: `(H, W)` pixels
    the fit did not use (its highlights), shown in blue on the residual and left out of
    its colour scale.

    **Returns:** `(path, psnr_db, ssim)`.
    """
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from .imageio import srgb_encode

    plt = _pyplot()
    s = float(np.percentile(target, 99.5)) or 1.0
    t_disp = srgb_encode(np.clip(target / s, 0, 1))
    f_disp = srgb_encode(np.clip(fitted / s, 0, 1))
    psnr = float(peak_signal_noise_ratio(t_disp, f_disp, data_range=1.0))
    ssim = float(structural_similarity(t_disp, f_disp, data_range=1.0, channel_axis=2))
    resid = np.abs(fitted - target).sum(axis=2) / s
    fig, ax = plt.subplots(1, 3, figsize=(12, 4.2))
    ax[0].imshow(t_disp)
    ax[0].set_title("target")
    ax[1].imshow(f_disp)
    ax[1].set_title(f"fit  (PSNR {psnr:.1f} dB, SSIM {ssim:.4f})")
    cmap = plt.get_cmap("magma").with_extremes(bad=(0.2, 0.45, 1.0))
    title = "|fit - target| (sum RGB, / display white)"
    if left_out is not None and left_out.any():
        resid = np.ma.masked_array(resid, mask=left_out)
        title += "\nblue: highlights the fit left out"
    im = ax[2].imshow(resid, cmap=cmap)
    ax[2].set_title(title)
    fig.colorbar(im, ax=ax[2], fraction=0.046)
    for a in ax:
        a.axis("off")
    return _save(fig, path, 100), psnr, ssim


def convergence_plot(
    history: list[dict], names: list[str], path: str | Path, eta_search: list[dict] | None = None
) -> Path:
    """Loss (log) and every parameter relative to its final value, against the step; with
    `eta_search` (a fit of `eta`), a third panel: the profile loss at each `eta` tried."""
    plt = _pyplot()
    steps = [h["step"] for h in history]
    loss = [max(h["loss"], 1e-30) for h in history]
    params = np.array([h["params"] for h in history])
    fig, ax = plt.subplots(1, 3 if eta_search else 2, figsize=(16 if eta_search else 11, 4))
    rounds = bool(history) and history[-1].get("root", False)  # a volumetric fit's rounds
    xlabel = "point traced (0: the start; last: the pooled root)" if rounds else "step"
    ax[0].semilogy(steps, loss, "o-")
    if rounds:
        ax[0].semilogy(steps[-1:], loss[-1:], "*", ms=14, color="C3", label="root (the answer)")
        ax[0].legend(fontsize=7)
    ax[0].set_xlabel(xlabel)
    ax[0].set_ylabel("loss (0.5 sum r_A r_B of the halves)" if rounds else "loss (0.5 sum r^2)")
    ax[0].grid(True, which="both", alpha=0.3)
    for i, n in enumerate(names[: params.shape[1]]):  # eta is not a solver coordinate
        c = _RGB["RGB".index(n[-1])] if n[-1] in "RGB" else None
        ls = "-" if ".sigma_a." in n else "--"
        ax[1].plot(steps, params[:, i] / params[-1, i], ls, color=c, label=n)
    ax[1].set_xlabel(xlabel)
    ax[1].set_ylabel("parameter / final value")
    ax[1].grid(True, alpha=0.3)
    ax[1].legend(fontsize=7)
    if eta_search:
        e = np.array([t["eta"] for t in eta_search])
        lv = np.maximum([t["loss"] for t in eta_search], 1e-30)
        order = np.argsort(e)
        ax[2].semilogy(e[order], lv[order], "-", color="0.7")
        ax[2].semilogy(e, lv, "o", color="C1")
        for k, (x, y) in enumerate(zip(e, lv, strict=True)):
            ax[2].annotate(str(k), (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax[2].set_xlabel("eta (each a re-trace; numbers: order tried)")
        ax[2].set_ylabel("loss after fitting the rest")
        ax[2].grid(True, which="both", alpha=0.3)
    return _save(fig, path, 100)


def measurement_plot(profile, fit, eta: float, path: str | Path, *, r_min: float = 0.0) -> Path:
    """The measured radial profile (points with error bars) against the fitted profile
    `scale R_d(r)` (lines; `fit.model`), log scale per RGB channel, and the relative residual
    below.

    **Arguments:** `profile` (`sssjax.measure.Profile` in `R_d` units), `fit`
    (`ProfileFit`), `eta`, `path` of the PNG, `r_min` the excluded centre (mm, shaded).

    **Returns:** the path written.
    """
    from .measure import model_profile

    model_name = getattr(fit, "model", "dipole")
    orders = getattr(fit, "orders", "multiple")
    plt = _pyplot()
    fig, (ax, axr) = plt.subplots(
        2, 1, figsize=(7.0, 6.4), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
    )
    r = np.asarray(profile.r)
    rr = np.linspace(max(r.min(), 1e-3), r.max(), 400)
    for c in range(3):
        sa, sp = fit.sigma_a[c], fit.sigmap_s[c]
        model = fit.scale[c] * np.asarray(model_profile(rr, sa, sp, eta, model_name, orders))
        at = fit.scale[c] * np.asarray(model_profile(r, sa, sp, eta, model_name, orders))
        ok = profile.mean[:, c] > 0
        ax.errorbar(
            r[ok], profile.mean[ok, c], yerr=profile.stderr[ok, c], fmt=".", ms=3,
            color=_RGB[c], alpha=0.6, label=f"{'RGB'[c]} measured",
        )  # fmt: skip
        ax.semilogy(
            rr, model, "-", color=_RGB[c], lw=1.2,
            label=f"{'RGB'[c]} fit: $\\sigma_a$={fit.sigma_a[c]:.4g}, "
            f"$\\sigma_s'$={fit.sigmap_s[c]:.4g} mm$^{{-1}}$",
        )  # fmt: skip
        axr.plot(r, profile.mean[:, c] / at - 1.0, ".", ms=3, color=_RGB[c])
    for a in (ax, axr):
        if r_min > 0:
            a.axvspan(0, r_min, color="0.85", zorder=0)
        a.grid(True, which="both", alpha=0.3)
    ax.set_ylabel("R_d(r) [mm$^{-2}$]")
    ax.set_title(f"Radial profile vs fitted {model_name} (grey: excluded centre)")
    ax.legend(fontsize=7, loc="upper right")
    axr.axhline(0, color="k", lw=0.6)
    axr.set_ylim(-0.1, 0.1)
    axr.set_ylabel("measured / fit - 1")
    axr.set_xlabel("r [mm]")
    return _save(fig, path)
