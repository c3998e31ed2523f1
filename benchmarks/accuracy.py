"""How accurate are the diffusion profiles? The accuracy table against the Monte Carlo truth.

    python benchmarks/accuracy.py            # the full table (about 15 min on 2 cores)
    python benchmarks/accuracy.py --quick    # a rough one (a few minutes)
    python benchmarks/accuracy.py --presets marble,ketchup --out /tmp/acc

For every measured preset of Jensen et al. 2001 (`sssjax.media.PRESETS`: reduced
coefficients, g = 0, eta = 1.3) and each RGB channel, a normally incident pencil beam is
traced by `sssjax.reference` (the ground truth) and compared with every profile of
`sssjax.profiles`:

- the relative error of each profile's `R_d(r)` against the Monte Carlo exitance, averaged
  over each radial bin exactly (16-point Gauss-Legendre per bin), mean and maximum of
  `|model / MC - 1|` over the bins from 0.1 to 20 reduced mean free paths (`1 / sigmap_t`)
  in which the Monte Carlo is precise to 10% (one standard error);
- the relative error of each profile's total diffuse reflectance;
- the bias of Jensen's measurement step: `sssjax.measure.fit_profile(..., model=...)` fitted
  to the Monte Carlo profile (with its standard errors, bins from 0.1 mfp outwards with a
  relative standard error below 25%, absolute level: no free scale), and how far the
  recovered `sigma_a` and `sigmap_s` land from the true ones.

The diffusion profiles model **multiple** scattering only, so the primary comparison is
against the Monte Carlo total minus its single-scattering part; the comparison against the
total (what a photograph of the sample sees) is reported too. Everything is per unit power
that entered the medium (the convention of `R_d`).

It writes `docs/accuracy.md` and `docs/images/accuracy_*.png` (under `--out`).
"""

from __future__ import annotations

import argparse
import datetime
import inspect
import os
import platform
import time
from pathlib import Path

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from sssjax import measure, profiles, reference  # noqa: E402
from sssjax.media import PRESET_ETA, PRESETS, preset  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CHANNELS = "RGB"
MODELS = profiles.PROFILES
LABEL = {
    "dipole": "classic dipole",
    "better_dipole": "better dipole",
    "pbd": "PBD",
    "tabulated": "tabulated (exact)",
}
R_LO, R_HI = 0.1, 20.0  # the range of the table, in reduced mean free paths
R_FAR = 2.0  # a fit of the total that leaves out the centre, where single scattering is
TABLE_REL_SE, FIT_REL_SE = 0.10, 0.25
PLOT_PRESETS = ("marble", "skimmilk", "skin1", "ketchup")
N_PER_DECADE = 40  # radial bins per decade (`fit_profile` averages its model over each)
FIT_ROWS = 160  # rows of every fitted profile (padded): one compilation per model

SETTINGS = {
    # pilot photons, then photons for a budget of free-flight steps, at most max_photons
    "full": dict(pilot=16_384, steps=100_000_000, max_photons=6_000_000),
    "quick": dict(pilot=8_192, steps=4_000_000, max_photons=200_000),
}


# --- Monte Carlo ------------------------------------------------------------------------------
def run_channel(sa, sps, eta, edges, seed, cfg):
    """The pilot, then as many photons as the step budget allows; pooled."""
    pilot = reference.simulate(sa, sps, 0.0, eta, n_photons=cfg["pilot"], seed=seed, r_edges=edges)
    n = int(min(cfg["max_photons"], cfg["steps"] / max(pilot.steps_per_photon, 1.0)))
    n -= cfg["pilot"]
    if n < 4096:
        return pilot
    main = reference.simulate(sa, sps, 0.0, eta, n_photons=n, seed=seed + 1000, r_edges=edges)
    return reference.merge(pilot, main)


def preset_bins(name: str):
    """A preset's `sigma_a`, `sigmap_s` (float64, 1/mm) and its radial bin edges (mm): a
    centre disc, then `N_PER_DECADE` log bins per decade from 0.01 mfp of its densest
    channel to 100 mfp of its thinnest."""
    m = preset(name)
    sa = np.asarray(m.sigma_a, np.float64)
    sps = np.asarray(m.sigmap_s, np.float64)
    spt = sa + sps
    lo, hi = 1e-2 / spt.max(), 1e2 / spt.min()
    nb = int(np.ceil(N_PER_DECADE * np.log10(hi / lo)))
    return sa, sps, np.concatenate([[0.0], np.geomspace(lo, hi, nb + 1)])


def bin_mean(model, edges, sa, sps, eta, orders="multiple"):
    """Exact mean of `R_d` of `model` over each annulus (16-point Gauss-Legendre per bin);
    with `orders="all"` plus the exact single scattering (`measure.model_profile`)."""
    x, w = np.polynomial.legendre.leggauss(16)
    a, b = edges[:-1, None], edges[1:, None]
    r = a + (b - a) * (x + 1) / 2
    rd = np.asarray(measure.model_profile(r, sa, sps, eta, model, orders), np.float64)
    return np.sum(2 * np.pi * r * rd * (b - a) / 2 * w, axis=1) / (
        np.pi * (b[:, 0] ** 2 - a[:, 0] ** 2)
    )


# --- comparisons ------------------------------------------------------------------------------
def compare(ref, sa, sps, eta):
    """Relative errors of every model against one channel's Monte Carlo (per entered power)."""
    ent = ref.entered()
    ell = 1.0 / (sa + sps)
    x = ent.r / ell
    out = {"n": ent.n_photons, "steps": ent.steps_per_photon, "seconds": ent.seconds}
    out["alpha_p"] = sps / (sa + sps)
    out["mc_multiple"], out["mc_multiple_se"] = ent.multiple, ent.multiple_stderr
    out["mc_total"], out["mc_total_se"] = ent.diffuse, ent.diffuse_stderr
    out["mc_lost"] = ent.lost
    models = {m: bin_mean(m, ent.r_edges, sa, sps, eta) for m in MODELS}
    # against the total, every model gets the exact single scattering added (what
    # `fit_profile(orders="all")` fits)
    models_all = {m: bin_mean(m, ent.r_edges, sa, sps, eta, "all") for m in MODELS}
    out["curves"] = models
    for part, mean, se, curves in (
        ("multiple", ent.multiple_profile, ent.multiple_profile_stderr, models),
        ("total", ent.profile, ent.profile_stderr, models_all),
    ):
        ok = (x >= R_LO) & (x <= R_HI) & (mean > 0) & (se < TABLE_REL_SE * np.abs(mean))
        out[f"{part}_range"] = (x[ok].min(), x[ok].max()) if ok.any() else (np.nan, np.nan)
        out[f"{part}_mc_se"] = float(np.median(se[ok] / mean[ok])) if ok.any() else np.nan
        for m, curve in curves.items():
            rel = curve[ok] / mean[ok] - 1 if ok.any() else np.array([np.nan])
            out[f"{part}_{m}_mean"] = float(np.mean(np.abs(rel)))
            out[f"{part}_{m}_max"] = float(np.max(np.abs(rel)))
            out[f"{part}_{m}_signed"] = rel
    for m in MODELS:
        tot = float(profiles.Rd_total(sa, sps, eta, profile=m))
        out[f"total_{m}"] = tot
        out[f"total_{m}_vs_multiple"] = tot / ent.multiple - 1
        single = float(profiles.single_scatter_total(sa, sps, eta))
        out[f"total_{m}_vs_total"] = (tot + single) / ent.diffuse - 1
    return out


def fit_channels(
    refs, true_sa, true_sps, eta, part, control=False, r_lo=R_LO, orders=None, r_hi_mm=None
):
    """`fit_profile` of every model to the Monte Carlo profile, channel by channel.

    A channel's window: the bins from 0.1 of its mfp outwards, as far as the Monte Carlo
    has a relative SE below 25% (the tail pins `sigma_a`). Each channel is fitted alone
    (`fit_profile` fits three columns on shared radii: the channel is given in all three and
    the first result is kept), on its own radii, padded to `FIT_ROWS` rows by repeating its
    first bin with a standard error 1e6 times the value (weight 1e-6), so that the fit
    compiles once per model.

    With `control`, each model is instead fitted to its *own* exact bin means (same bins,
    same relative standard errors): what that recovers is the bias of the fitting machinery
    itself (the quadrature over each bin, the optimiser), not of the model.

    `orders` is `fit_profile`'s (default: `"multiple"` for the multiple-scattering part,
    `"all"` for the total, whose model then adds the exact single scattering); `r_hi_mm`
    cuts the window at that radius (the measurement in millimetres)."""
    if orders is None:
        orders = "multiple" if part == "multiple" else "all"
    prof = reference.to_profile(refs, component=part, normalization="entered")
    edges = refs[0].r_edges
    res = {m: {k: np.zeros(3) for k in KEYS} | {"converged": []} for m in MODELS}
    for c in range(3):
        x = prof.r * (true_sa[c] + true_sps[c])
        mean, se = prof.mean[:, c], prof.stderr[:, c]
        ok = (x >= r_lo) & (mean > 0) & (se < FIT_REL_SE * mean)
        if r_hi_mm is not None:
            ok &= prof.r <= r_hi_mm
        if ok.sum() < 3:
            for m in MODELS:
                for k in KEYS:
                    res[m][k][c] = np.nan
                res[m]["converged"].append(False)
            continue
        r, mean, se, bounds = prof.r[ok], mean[ok], se[ok], prof.bounds[ok]
        pad = FIT_ROWS - r.size
        if pad < 0:
            raise RuntimeError(f"accuracy.py: {r.size} fit rows, more than FIT_ROWS = {FIT_ROWS}")
        r = np.concatenate([r, np.full(pad, r[0])])
        bounds = np.concatenate([bounds, np.repeat(bounds[:1], pad, 0)])
        for m in MODELS:
            data = bin_mean(m, edges, true_sa[c], true_sps[c], eta)[ok] if control else mean
            sd = se / mean * data
            data = np.concatenate([data, np.full(pad, data[0])])
            sd = np.concatenate([sd, np.full(pad, 1e6 * data[0])])
            fitted = measure.Profile(
                r=r,
                mean=np.repeat(data[:, None], 3, 1),
                stderr=np.repeat(sd[:, None], 3, 1),
                counts=np.ones(r.size, np.int64),
                bounds=bounds,
            )
            fit = measure.fit_profile(fitted, eta, model=m, orders=orders)
            res[m]["sigma_a"][c] = float(fit.sigma_a[0]) / true_sa[c] - 1
            res[m]["sigmap_s"][c] = float(fit.sigmap_s[0]) / true_sps[c] - 1
            res[m]["sigma_a_se"][c] = float(fit.sigma_a_stderr[0]) / true_sa[c]
            res[m]["sigmap_s_se"][c] = float(fit.sigmap_s_stderr[0]) / true_sps[c]
            res[m]["converged"].append(bool(fit.converged[0]))
    return res


KEYS = ("sigma_a", "sigmap_s", "sigma_a_se", "sigmap_s_se")


# --- output -----------------------------------------------------------------------------------
def pct(v, digits=1):
    return "n/a" if not np.isfinite(v) else f"{100 * v:.{digits}f}"


def spct(v, digits=1):
    if not np.isfinite(v):
        return "n/a"
    return f"{100 * v:+.{digits}f}" if abs(v) < 10 else (">+999" if v > 0 else "<-999")


def plot_preset(name, refs, rows, out_dir):
    m = preset(name)
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.4), sharex="col", height_ratios=[2.2, 1])
    colors = {
        "dipole": "tab:blue",
        "better_dipole": "tab:green",
        "pbd": "tab:red",
        "tabulated": "black",
    }
    for c in range(3):
        ent = refs[c].entered()
        sa, sps = float(m.sigma_a[c]), float(m.sigmap_s[c])
        ell = 1.0 / (sa + sps)
        r = ent.r
        show = (r / ell >= 0.03) & (r / ell <= 40) & (ent.profile > 0)
        ax, axr = axes[0, c], axes[1, c]
        mp, ms = ent.multiple_profile, ent.multiple_profile_stderr
        okm = show & (mp > ms)  # a point whose error bar reaches zero says nothing on a log axis
        ax.errorbar(r[okm], mp[okm], yerr=ms[okm], fmt="o", ms=3, color="k", label="MC multiple")
        ax.plot(r[show], ent.profile[show], "x", ms=4, color="0.5", label="MC total")
        for mdl in MODELS:
            curve = rows[c]["curves"][mdl]
            ax.plot(r[show], curve[show], "-", color=colors[mdl], label=LABEL[mdl])
            good = okm & (ms < 0.3 * mp)
            axr.plot(r[good], curve[good] / mp[good] - 1, "-", color=colors[mdl])
        good = okm & (ms < 0.3 * mp)
        axr.fill_between(r[good], -ms[good] / mp[good], ms[good] / mp[good], color="0.85")
        axr.axhline(0, color="k", lw=0.6)
        for a in (ax, axr):
            a.axvline(R_LO * ell, color="0.7", ls=":", lw=0.8)
            a.axvline(R_HI * ell, color="0.7", ls=":", lw=0.8)
        ax.set_yscale("log")
        ax.set_xscale("log")
        axr.set_xscale("log")
        ax.set_title(f"{name} {CHANNELS[c]}: alpha' = {sps / (sa + sps):.4f}, mfp = {ell:.3g} mm")
        axr.set_xlabel("r (mm)")
        axr.set_ylim(-0.6, 0.6)
        if c == 0:
            ax.set_ylabel("R(r) per entered power (mm$^{-2}$)")
            axr.set_ylabel("model / MC multiple - 1\n(clipped to +-0.6)")
            ax.legend(fontsize=8)
    fig.suptitle(
        f"{name}: Monte Carlo against the diffusion profiles (dotted: 0.1 and 20 mfp; "
        "grey band: MC standard error)"
    )
    fig.tight_layout()
    path = out_dir / f"accuracy_{name}.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


ALBEDO_CLASSES = (
    ("alpha' >= 0.95", 0.95, 1.01),
    ("0.6 <= alpha' < 0.95", 0.6, 0.95),
    ("alpha' < 0.6", 0.0, 0.6),
)


def summary_lines(rows_all, fits_all, part):
    """Median (worst) over the channels of each reduced-albedo class, per model."""
    lines = [
        "| channels | quantity, % | " + " | ".join(LABEL[m] for m in MODELS) + " |",
        "| --- | --- | " + " | ".join("---" for _ in MODELS) + " |",
    ]

    def agg(vals):
        v = np.abs(np.asarray([x for x in vals if np.isfinite(x)], np.float64))
        if not v.size:
            return "n/a"
        med = np.median(v)
        worst = f"{100 * v.max():.0f}" if v.max() < 10 else ">999"
        return f"{100 * med:.1f} ({worst})" if med < 10 else f">999 ({worst})"

    for label, lo, hi in ALBEDO_CLASSES:
        keys = [k for k, r in rows_all.items() if lo <= r["alpha_p"] < hi]
        if not keys:
            continue
        who = f"{label} ({len(keys)})"
        rows = [rows_all[k] for k in keys]
        quantities = [
            (
                "profile: mean \\|err\\| over r",
                [[r[f"{part}_{m}_mean"] for r in rows] for m in MODELS],
            ),
            (
                "profile: max \\|err\\| over r",
                [[r[f"{part}_{m}_max"] for r in rows] for m in MODELS],
            ),
            (
                "total reflectance \\|err\\|",
                [[r[f"total_{m}_vs_{part}"] for r in rows] for m in MODELS],
            ),
        ]
        fit_keys = [(part, "")] + (
            [("total_far", f", r >= {R_FAR:g} mfp")] if part == "total" else []
        )
        for key, note in fit_keys if fits_all else ():
            for q in ("sigma_a", "sigmap_s"):
                vals = [[fits_all[n][key][m][q][c] for n, c in keys] for m in MODELS]
                quantities.append((f"fitted `{q}` \\|err\\|{note}", vals))
        for i, (name, vals) in enumerate(quantities):
            lines.append(
                f"| {who if i == 0 else ''} | {name} | " + " | ".join(agg(v) for v in vals) + " |"
            )
    return lines


def findings(rows_all, fits_all):
    """The headline numbers, per class of reduced albedo, as sentences."""
    L = ["## Findings", ""]
    med = lambda v: float(np.median(np.abs(v)))  # noqa: E731
    worst = lambda v: float(np.max(np.abs(v)))  # noqa: E731
    big = lambda v, d=1: f"{100 * v:.{d}f}%" if v < 10 else "> 1000%"  # noqa: E731
    for label, lo, hi in ALBEDO_CLASSES:
        keys = [k for k, r in rows_all.items() if lo <= r["alpha_p"] < hi]
        if not keys:
            continue
        names = sorted({n for n, _ in keys})
        shape = {m: [rows_all[k][f"multiple_{m}_mean"] for k in keys] for m in MODELS}
        best = min(MODELS, key=lambda m: med(shape[m]))
        others = ", ".join(f"{LABEL[m]} {big(med(shape[m]))}" for m in MODELS if m != best)
        text = (
            f"- **{label}** ({len(keys)} channels: {', '.join(names)}). Closest profile to the "
            f"multiple-scattering Monte Carlo: {LABEL[best]}, mean error over 0.1-20 mfp "
            f"{big(med(shape[best]))} (median channel; worst {big(worst(shape[best]), 0)})"
            f", against {others}."
        )
        if fits_all:
            for key, what in (
                ("total_far", f"a photograph with the centre (r < {R_FAR:g} mfp) left out"),
                ("multiple", "the multiple-scattering profile alone"),
            ):
                err = {
                    m: (
                        np.array([fits_all[n][key][m]["sigma_a"][c] for n, c in keys]),
                        np.array([fits_all[n][key][m]["sigmap_s"][c] for n, c in keys]),
                    )
                    for m in MODELS
                }
                fit_best = min(MODELS, key=lambda m: med(err[m][0]) + med(err[m][1]))
                a, b = err[fit_best]
                text += (
                    f" Fitted to {what}, the best is the {LABEL[fit_best]}: `sigma_a` off by "
                    f"{big(med(a))} and `sigmap_s` by {big(med(b))} (median; worst "
                    f"{big(worst(a), 0)} / {big(worst(b), 0)})."
                )
        L.append(text)
    L.append("")
    return L


def write_markdown(path, rows_all, fits_all, plots, meta):
    L = []
    L.append("# Accuracy of the diffusion profiles against a Monte Carlo ground truth")
    L.append("")
    L.append(
        f"Produced by `python benchmarks/accuracy.py{' --quick' if meta['quick'] else ''}` "
        f"({meta['date']}, {meta['cores']} CPU cores, {meta['minutes']:.1f} min, "
        f"{meta['photons'] / 1e6:.1f} M photons in all). Rerun it to reproduce; it rewrites this "
        "file and the plots."
    )
    L.append("")
    L.append("## What is compared")
    L.append("")
    L.append(
        "- **Ground truth**: `sssjax.reference`, a volumetric Monte Carlo random walk: a "
        "normally incident pencil beam on a semi-infinite medium with a smooth dielectric "
        f"boundary (eta = {PRESET_ETA}, exact Fresnel at every crossing, total internal "
        "reflection), isotropic scattering (g = 0, the presets are reduced coefficients), "
        "exact free flights; tested against Chandrasekhar's H function, exact single "
        "scattering and energy bookkeeping (`tests/test_reference.py`)."
    )
    L.append(
        "- **Models**: `sssjax.profiles.Rd(..., profile=)`: the classic dipole (Jensen et al. "
        "2001), the better dipole (d'Eon 2012), photon beam diffusion (PBD, Habel et al. "
        "2013, as in pbrt) and the tabulated profile (exact transport of this geometry, "
        "`benchmarks/profile_table.py`, from Monte Carlo runs with seeds independent of the "
        "ones here)."
    )
    L.append(
        "- **Normalisation**: per unit power that *entered* the medium (the convention of "
        "`R_d`); r from the entry point; mfp = 1 / sigmap_t of the channel."
    )
    L.append(
        "- **Multiple vs single scattering**: the diffusion profiles model multiple scattering "
        "only. The primary comparison is against the Monte Carlo profile *minus its "
        "single-scattering part* (light that scattered exactly once). The second set of tables "
        "compares against the total, which is what a photograph of a lit sample records; "
        "there every model has the exact single scattering under the beam "
        '(`sssjax.profiles.single_scatter`) added, as `fit_profile(orders="all")` does.'
    )
    L.append(
        f"- **Profile error**: `|model / MC - 1|`, with the model averaged exactly over each "
        f"radial bin ({N_PER_DECADE} logarithmic bins per decade), mean and maximum over the "
        f"bins from {R_LO} to {R_HI} mfp in which the Monte Carlo's standard error is below "
        f"{100 * TABLE_REL_SE:.0f}% (the `range` column says how far that reached; strongly "
        "absorbing channels have no light far out). The Monte Carlo's own typical relative "
        "error per bin is listed (`MC se`): profile errors of that size are noise."
    )
    L.append(
        "- **Measurement step**: `sssjax.measure.fit_profile(profile, 1.3, model=...)` fitted "
        f"to the Monte Carlo profile with its standard errors (the bins from {R_LO} mfp "
        f"outwards, up to 100 mfp of the channel with the longest mfp, whose relative standard "
        f"error is below {100 * FIT_REL_SE:.0f}%: the tail beyond the diffusion length is what "
        "pins `sigma_a`; the absolute level is "
        "used, no free scale, as with a calibrated beam), in log space per channel. Reported: "
        "recovered / true - 1 for `sigma_a` and `sigmap_s`, in %. Three fits: to the "
        "multiple-scattering Monte Carlo (the model's own error), to the total (what a "
        f"photograph records), and to the total from {R_FAR:g} mfp outwards (the centre, where "
        "single scattering dominates, left out as Jensen et al. left out the saturated centre; "
        "the windows use the true mfp: in practice take it from a first fit). "
        "The fit averages the model over each bin (`Profile.bounds`; until 2026-12-07 it took "
        "the value at the bin's area-weighted radius, which cost sigma_a -0.3 % in the median "
        "and up to 0.6 %); the control below measures what the fitting machinery still costs."
    )
    L.append("")
    L.extend(findings(rows_all, fits_all))
    for part, title in (
        ("multiple", "against the multiple-scattering Monte Carlo (primary)"),
        ("total", "against the total Monte Carlo (single scattering included)"),
    ):
        L.append(f"## Summary {title}")
        L.append("")
        L.append(
            "Median (worst) over the channels of each class of reduced albedo alpha' (number of "
            "channels in parentheses), in %:"
        )
        L.append("")
        L.extend(summary_lines(rows_all, fits_all, part))
        L.append("")
    for part, title in (
        ("multiple", "multiple scattering (MC total minus single scattering)"),
        ("total", "total (single scattering included)"),
    ):
        L.append(f"## Profile error against the {title}, %")
        L.append("")
        L.append(
            "mean / max of |model / MC - 1| over the range; `alpha'` the reduced albedo, "
            "`range` in mfp."
        )
        L.append("")
        L.append(
            "| preset | ch | alpha' | range | MC se | "
            + " | ".join(LABEL[m] for m in MODELS)
            + " |"
        )
        L.append("| --- | --- | --- | --- | --- | " + " | ".join("---" for _ in MODELS) + " |")
        for (name, c), row in rows_all.items():
            lo, hi = row[f"{part}_range"]
            rng = "none" if not np.isfinite(lo) else f"{lo:.2g}-{hi:.3g}"
            cells = [
                f"{pct(row[f'{part}_{m}_mean'])} / {pct(row[f'{part}_{m}_max'])}" for m in MODELS
            ]
            L.append(
                f"| {name} | {CHANNELS[c]} | {row['alpha_p']:.4f} | {rng} | "
                f"{pct(row[f'{part}_mc_se'])} | " + " | ".join(cells) + " |"
            )
        L.append("")
    L.append("## Total diffuse reflectance")
    L.append("")
    L.append(
        "Monte Carlo per entered power (multiple scattering, and total with single scattering) "
        "and each model's relative error against the multiple / total, %."
    )
    L.append("")
    L.append(
        "| preset | ch | MC multiple | MC total | "
        + " | ".join(f"{LABEL[m]} vs mult / tot" for m in MODELS)
        + " |"
    )
    L.append("| --- | --- | --- | --- | " + " | ".join("---" for _ in MODELS) + " |")
    for (name, c), row in rows_all.items():
        cells = [
            f"{spct(row[f'total_{m}_vs_multiple'])} / {spct(row[f'total_{m}_vs_total'])}"
            for m in MODELS
        ]
        L.append(
            f"| {name} | {CHANNELS[c]} | {row['mc_multiple']:.4f} +- {row['mc_multiple_se']:.4f} "
            f"| {row['mc_total']:.4f} +- {row['mc_total_se']:.4f} | " + " | ".join(cells) + " |"
        )
    L.append("")
    fit_parts = (
        ("multiple", "fitted to the multiple-scattering Monte Carlo"),
        (
            "total",
            "fitted to the total Monte Carlo (what a photograph sees; the model adds the exact "
            'single scattering, `orders="all"`)',
        ),
        (
            "total_far",
            f"fitted to the total Monte Carlo from {R_FAR:g} mfp outwards with a "
            "multiple-scattering model (Jensen's way: leave the centre out)",
        ),
        ("mm10", 'a measurement in millimetres: the total, r <= 10 mm, `orders="all"`'),
        ("mm30", 'a measurement in millimetres: the total, r <= 30 mm, `orders="all"`'),
    )
    for part, title in fit_parts if fits_all else ():
        L.append(f"## Bias of the measurement step, {title}")
        L.append("")
        L.append(
            "recovered / true - 1 in % for `sigma_a` / `sigmap_s` (the fit's own statistical "
            "error is far smaller than these biases unless marked `*`: bias < 2 standard errors; "
            "`!`: the optimiser did not report convergence)."
        )
        L.append("")
        L.append("| preset | ch | " + " | ".join(LABEL[m] for m in MODELS) + " |")
        L.append("| --- | --- | " + " | ".join("---" for _ in MODELS) + " |")
        for name, fits in fits_all.items():
            for c in range(3):
                cells = []
                for m in MODELS:
                    f = fits[part][m]
                    mark = ""
                    if (
                        abs(f["sigma_a"][c]) < 2 * f["sigma_a_se"][c]
                        or abs(f["sigmap_s"][c]) < 2 * f["sigmap_s_se"][c]
                    ):
                        mark = "*"
                    if not f["converged"][c]:
                        mark += "!"
                    cells.append(f"{spct(f['sigma_a'][c])} / {spct(f['sigmap_s'][c])}{mark}")
                L.append(f"| {name} | {CHANNELS[c]} | " + " | ".join(cells) + " |")
        L.append("")
    if fits_all:
        L += coverage_section(fits_all)
        L.append("### Control: the fitting machinery on exact data")
        L.append("")
        L.append(
            "Each model fitted to its own exact bin means (same bins, windows and relative "
            "standard errors as the Monte Carlo multiple-scattering fit). Largest and median "
            "|recovered / true - 1| over all channels, %: the part of the biases above that is "
            "not model error (the quadrature over the bins, the optimiser)."
        )
        L.append("")
        L.append("| | " + " | ".join(LABEL[m] for m in MODELS) + " |")
        L.append("| --- | " + " | ".join("---" for _ in MODELS) + " |")
        for q in ("sigma_a", "sigmap_s"):
            cells = []
            for m in MODELS:
                v = np.abs(np.concatenate([f["control"][m][q] for f in fits_all.values()]))
                cells.append(f"{100 * v.max():.2f} (median {100 * np.median(v):.2f})")
            L.append(f"| `{q}` | " + " | ".join(cells) + " |")
        L.append("")
    L.append("## Plots")
    L.append("")
    L.append(
        "Log profile against r for each channel: Monte Carlo multiple scattering (dots with "
        "error bars), Monte Carlo total (crosses), the three models (lines); below, each "
        "model's relative error against the multiple-scattering Monte Carlo."
    )
    L.append("")
    for p in plots:
        L.append(f"![{p.stem}](images/{p.name})")
        L.append("")
    L += objects_section(path.parent / "transports.md")
    path.write_text("\n".join(L))


def coverage_section(fits_all) -> list[str]:
    """Per model, for the two measurements in millimetres (known power, every order): the
    share of the coefficients within 3% of the truth and the share whose truth lies within
    2 reported standard errors (coverage)."""
    L = ["### Measurement in millimetres: accuracy and coverage", ""]
    L.append(
        f"All channels, `sigma_a` and `sigmap_s` together ({6 * len(fits_all)} coefficients "
        "per range, fitted from 0.1 mfp outwards): the share within 3% of the truth, the share whose truth lies within 2 reported standard "
        "errors, and the largest error."
    )
    L.append("")
    L.append("| range | quantity | " + " | ".join(LABEL[m] for m in MODELS) + " |")
    L.append("| --- | --- | " + " | ".join("---" for _ in MODELS) + " |")
    for key, label in (("mm10", "r <= 10 mm"), ("mm30", "r <= 30 mm")):
        rows = {"within 3%": [], "within 2 s.e.": [], "largest \\|err\\|": []}
        for m in MODELS:
            err = np.concatenate(
                [
                    np.concatenate([f[key][m]["sigma_a"], f[key][m]["sigmap_s"]])
                    for f in fits_all.values()
                ]
            )
            se = np.concatenate(
                [
                    np.concatenate([f[key][m]["sigma_a_se"], f[key][m]["sigmap_s_se"]])
                    for f in fits_all.values()
                ]
            )
            ok = np.isfinite(err)
            rows["within 3%"].append(f"{100 * np.mean(np.abs(err[ok]) < 0.03):.0f}%")
            rows["within 2 s.e."].append(f"{100 * np.mean(np.abs(err[ok]) < 2 * se[ok]):.0f}%")
            rows["largest \\|err\\|"].append(spct(float(np.max(np.abs(err[ok])))))
        for i, (q, cells) in enumerate(rows.items()):
            L.append(f"| {label if i == 0 else ''} | {q} | " + " | ".join(cells) + " |")
    L.append("")
    return L


def objects_section(transports_md: Path) -> list[str]:
    """The object-level comparison of the two transports (`benchmarks/transports.py`, which
    writes `transports.md` beside this file), carried into accuracy.md when it exists."""
    L = ["## Objects: the diffusion transport against exact (volumetric) transport", ""]
    if not transports_md.exists():
        return L + ["Run `python benchmarks/transports.py` to measure it.", ""]
    text = transports_md.read_text().splitlines()
    table = [line for line in text if line.startswith("|")]
    L += [
        "At the true coefficients, the ratio of the mean radiance rendered by the diffusion "
        "transport to the volumetric (exact) one, per region and channel, from "
        f"[`{transports_md.name}`]({transports_md.name}) (its settings and date there). The profile "
        "errors above are the diffusion model's on its own geometry (a flat semi-infinite "
        "medium); on objects it also misses light that is not direct, light leaving through "
        "the back and sides, and translucent shadows.",
        "",
        *table,
        "",
    ]
    return L


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a short run (fewer photons)")
    ap.add_argument("--presets", default=",".join(sorted(PRESETS)), help="comma-separated")
    ap.add_argument("--out", default=str(ROOT / "docs"), help="directory for accuracy.md")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-fits", action="store_true", help="profiles and totals only")
    a = ap.parse_args()
    if not a.skip_fits and "model" not in inspect.signature(measure.fit_profile).parameters:
        raise SystemExit("benchmarks/accuracy.py: sssjax.measure.fit_profile has no model= yet")
    cfg = SETTINGS["quick" if a.quick else "full"]
    names = [n.strip().lower() for n in a.presets.split(",") if n.strip()]
    for n in names:
        preset(n)  # a clear error for an unknown name
    out_dir = Path(a.out)
    img_dir = out_dir / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    eta = PRESET_ETA
    t_start = time.perf_counter()
    rows_all, fits_all, refs_all = {}, {}, {}
    photons = 0
    k = 0
    for i, name in enumerate(names):
        sa, sps, edges = preset_bins(name)
        refs = []
        for c in range(3):
            k += 1
            t0 = time.perf_counter()
            ref = run_channel(sa[c], sps[c], eta, edges, a.seed + 10 * i + c, cfg)
            refs.append(ref)
            photons += ref.n_photons
            rows_all[(name, c)] = compare(ref, sa[c], sps[c], eta)
            print(
                f"[{k:2d}/{3 * len(names)}] {name:9s} {CHANNELS[c]}: {ref.n_photons:8d} photons, "
                f"{ref.steps_per_photon:7.1f} steps/photon, {time.perf_counter() - t0:6.1f} s "
                f"(total {(time.perf_counter() - t_start) / 60:5.1f} min)",
                flush=True,
            )
        refs_all[name] = refs
        if not a.skip_fits:
            t0 = time.perf_counter()
            fits_all[name] = {
                "multiple": fit_channels(refs, sa, sps, eta, "multiple"),
                "total": fit_channels(refs, sa, sps, eta, "total"),
                "total_far": fit_channels(
                    refs, sa, sps, eta, "total", r_lo=R_FAR, orders="multiple"
                ),
                "mm10": fit_channels(refs, sa, sps, eta, "total", r_hi_mm=10.0),
                "mm30": fit_channels(refs, sa, sps, eta, "total", r_hi_mm=30.0),
                "control": fit_channels(refs, sa, sps, eta, "multiple", control=True),
            }
            print(f"      fits: {time.perf_counter() - t0:5.1f} s", flush=True)
    plots = [
        plot_preset(n, refs_all[n], [rows_all[(n, c)] for c in range(3)], img_dir)
        for n in PLOT_PRESETS
        if n in refs_all
    ]
    meta = dict(
        quick=a.quick,
        date=datetime.date.today().isoformat(),
        cores=os.cpu_count(),
        minutes=(time.perf_counter() - t_start) / 60,
        photons=photons,
        machine=f"{platform.machine()} {jax.devices()[0].platform}",
    )
    md = out_dir / "accuracy.md"
    write_markdown(md, rows_all, fits_all, plots, meta)
    print(f"wrote {md} and {len(plots)} plots in {meta['minutes']:.1f} min")
    for part in ("multiple", "total"):
        print(f"\nsummary against the {part} Monte Carlo:")
        print("\n".join(summary_lines(rows_all, fits_all, part)))


if __name__ == "__main__":
    main()
