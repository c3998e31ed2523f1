"""Build the table behind `profile = "tabulated"` from `sssjax.reference` (rerunnable).

    python benchmarks/profile_table.py                 # run what is missing, then assemble
    # the shipped table: two passes and the bright walks (44 min on 2 cores), then a third
    # pass for the dark and middle nodes (reduced albedo 0.011-0.95; 29 min)
    python benchmarks/profile_table.py --passes 2 --budget 2e7 --bright 300000 --bright-passes 2
    python benchmarks/profile_table.py --passes 3 --budget 2e8 --max-photons 40e6 --logits=-4.5,3.0
    python benchmarks/profile_table.py --assemble      # only rebuild the table from the runs
    python benchmarks/profile_table.py --check-tail --cut 2  # the tail's held-out check

The exitant profile of a semi-infinite medium under a normally incident pencil beam depends,
in reduced units (`x = r sigmap_t`, `sigmap_t = sigma_a + sigmap_s`), only on the reduced
albedo `a' = sigmap_s / sigmap_t` and the relative index `eta` (isotropic scattering; for
`g != 0` the similarity relation `sigmap_s = sigma_s (1 - g)` is the approximation). For
every node of the grid

- `eta` in 1.0, 1.15, ..., 1.6 (5 nodes) and
- `logit a'` in -4.5, -4.0, ..., 11.5 (33 nodes, `a'` from 0.011 to 0.99999),

`sssjax.reference.simulate` traces `--photons` photons per pass (seed `SEED0 + 1000 pass +
100 i_eta + i_a`, fixed), with `sigmap_t = 1`, into log bins of `x` from 0.01 to 316
(16 per decade). The bright nodes (`logit a' >= 4`, a' > 0.98), whose far tails pin a
bright medium's `sigma_a` and cost up to ~1600 free flights per photon, get `--bright-passes`
more, in two groups (`logit a'` 7-11.5 with `--bright` photons, 4-6.5 with four times as
many): per group, eta and pass one walk at the group's brightest albedo, re-weighted to each
of its nodes by `(a'/a'_max)^n` after `n` collisions (perturbation Monte Carlo,
`reference.simulate(albedos=...)`; seed `SEED0 + 1000 pass + 100 i_eta + 99`, passes 10, 11
and 12, 13): one walk serves a whole group. Each run is saved under `--runs` (default `out/profile_table/runs`), so an
interrupted build resumes and more passes (independent seeds) can be added later; the
assembly merges every pass it finds.

**What the table stores** (`sssjax/data/tabulated_profile.npz`):

- `T[x, a', eta]`: the multiple-scattering profile as a correction to d'Eon's better dipole,
  `log(MC bin mean / better-dipole bin mean)` (both averaged over the same annulus, so the
  wide outer bins need no point-value approximation), smoothed along `log x` by a local
  quadratic fit (tricube window of +-3 bins, weights 1 / variance). Where the Monte Carlo
  has no precise bins (relative error above 20 %: the far tail, the innermost bins) the
  correction is continued: before the first precise bin as a constant; beyond the last one
  by `tail_model`'s envelope, fitted to the raw bins of the last decade: the mean of two
  fits, the asymptotic decay with its `1/x` and `1/x^2` corrections (`T` grows by `slope =
  kappa_bd - kappa` per reduced mean free path, `kappa = 1 / nu_0` Case's discrete
  eigenvalue of isotropic transport, `artanh(kappa) / kappa = 1 / a'`, `kappa_bd` the better
  dipole's `sigma_tr / sigmap_t`) and a line of free slope, with their difference counted
  as error. The smoothed values are blended into it over the last half decade of precise
  bins. `--check-tail` tests the continuation on held-out bins of the build's own runs (a
  fit to the bins up to half the last precise `x`, against the bins beyond).
- `T_err`: one standard error of `T` (relative error of the profile): the smoother's where
  the runs are precise, the envelope's beyond (statistical and model error); `continued`
  marks the latter.
- `ms_total`, `ms_total_err`: the Monte Carlo total of multiple scattering (per unit power
  entering; its error includes the photons lost beyond `r_cap`, counted as a bias bound),
  and `log_total_ratio`, its log ratio to the better dipole's total (what is interpolated).
- `log_G[x, eta_S]`, `S_total[eta_S]`: single scattering per unit albedo (`sigma_t = 1`),
  exact (`sssjax.reference.single_scatter_exitance` / `_total` quadrature, point values), on
  a finer grid of 25 `eta_S` nodes, stored as `log S + k x` with its far decay
  `e^{-k x}`, `k = eta + sqrt(eta^2 - 1)` (the critical-angle exits), taken out.

`sssjax.profiles` interpolates `T` and `log S` with Catmull-Rom cubics in `(log x, logit a',
eta)`, so Jacobians are continuous. The off-grid check of the table against fresh runs is
`tests/test_tabulated.py`.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import datetime
import math
import multiprocessing as mp
import os
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TABLE = ROOT / "sssjax" / "data" / "tabulated_profile.npz"
ETAS = np.round(np.linspace(1.0, 1.6, 5), 6)
LOGITS = np.arange(-4.5, 11.5 + 1e-9, 0.5)
PER_DECADE = 16
X_LO, X_HI = 0.01, 10**2.5
EDGES = np.concatenate([[0.0], np.geomspace(X_LO, X_HI, int(round(PER_DECADE * 4.5)) + 1)])
SEED0 = 7_000_000
REL_OK = 0.2  # bins with a larger relative standard error are not used
HALF = 3  # smoothing half-window, bins
TAIL_DECADE = 10.0  # the tail model is fitted over this factor in x before the last precise bin
MAX_PHOTONS, MIN_PHOTONS = 4_000_000, 16_384  # per node and pass, for --budget passes
# the bright passes: (lowest logit a', highest logit a' = the walk's, first pass number,
# photons relative to --bright); each group's walk at its highest albedo is re-weighted to
# all its nodes
BRIGHT_GROUPS = ((7.0, 11.5, 10, 1), (4.0, 6.5, 12, 4))


def albedo(logit):
    return 1.0 / (1.0 + np.exp(-np.asarray(logit, np.float64)))


def run_name(i_eta, i_a, p):
    return f"eta{i_eta}_a{i_a:02d}_p{p}.npz"


def _save(ref, out: Path):
    tmp = out.with_suffix(".tmp.npz")
    np.savez(
        tmp,
        profile=ref.multiple_profile,
        stderr=ref.multiple_profile_stderr,
        counts=ref.counts,
        total=ref.multiple,
        total_stderr=ref.multiple_stderr,
        lost=ref.lost,
        n_photons=ref.n_photons,
        steps=ref.steps_per_photon,
    )
    os.replace(tmp, out)


def _group_nodes(lo: float, hi: float) -> np.ndarray:
    return np.flatnonzero((LOGITS >= lo - 1e-9) & (LOGITS <= hi + 1e-9))


def _bright_one(args):
    """One perturbation walk at a group's brightest node, re-weighted to every node of the
    group (one run file per node), in a worker process."""
    i_eta, p, photons, runs, lo, hi = args
    nodes = _group_nodes(lo, hi)
    outs = [Path(runs) / run_name(i_eta, ia, p) for ia in nodes]
    if all(o.exists() for o in outs):
        return str(outs[-1]), 0.0
    from sssjax import reference

    a_max = float(albedo(LOGITS[nodes[-1]]))
    t0 = time.perf_counter()
    refs = reference.simulate(
        1.0 - a_max,
        a_max,
        0.0,
        float(ETAS[i_eta]),
        n_photons=photons,
        seed=SEED0 + 1000 * p + 100 * i_eta + 99,
        r_edges=EDGES,
        albedos=albedo(LOGITS[nodes]),
    )
    for ref, out in zip(refs, outs, strict=True):
        _save(ref.entered(), out)
    return str(outs[-1]), time.perf_counter() - t0


def bright(photons: int, passes: int, jobs: int, runs: Path):
    """The bright passes (`BRIGHT_GROUPS`): per group, eta and pass one walk of `photons`
    (times the group's factor) at the group's brightest albedo, re-weighted to each of its
    nodes (their far tails, on which a bright medium's sigma_a rests, need the most photons
    and cost the most free flights per photon: about 1600 at a' = 0.99999)."""
    runs.mkdir(parents=True, exist_ok=True)
    todo = [
        (ie, p0 + k, photons * mult, str(runs), lo, hi)
        for lo, hi, p0, mult in BRIGHT_GROUPS
        for k in range(passes)
        for ie in range(ETAS.size)
        if not (runs / run_name(ie, _group_nodes(lo, hi)[-1], p0 + k)).exists()
    ]
    print(f"profile table: {len(todo)} bright walks to do ({jobs} jobs)", flush=True)
    t0 = time.perf_counter()
    ctx = mp.get_context("spawn")
    with cf.ProcessPoolExecutor(jobs, mp_context=ctx) as ex:
        for k, (name, sec) in enumerate(ex.map(_bright_one, todo), 1):
            el = time.perf_counter() - t0
            print(
                f"  [{k}/{len(todo)}] {Path(name).name} {sec:.0f} s (elapsed {el:.0f} s)",
                flush=True,
            )


def _run_one(args):
    """One node and pass, in a worker process (float32 walk)."""
    i_eta, i_a, p, photons, runs = args
    out = Path(runs) / run_name(i_eta, i_a, p)
    if out.exists():
        return str(out), 0.0
    from sssjax import reference

    a = float(albedo(LOGITS[i_a]))
    t0 = time.perf_counter()
    ref = reference.simulate(
        1.0 - a,
        a,
        0.0,
        float(ETAS[i_eta]),
        n_photons=photons,
        seed=SEED0 + 1000 * p + 100 * i_eta + i_a,
        r_edges=EDGES,
    ).entered()
    _save(ref, out)
    return str(out), time.perf_counter() - t0


def run(
    photons: int,
    passes: int,
    jobs: int,
    runs: Path,
    budget: float | None = None,
    max_photons: int = MAX_PHOTONS,
    logits: tuple[float, float] = (-np.inf, np.inf),
):
    """Pass 0 traces `photons` per node. With a `budget` (free flights per node), every
    later pass traces `budget / steps` photons (at most `max_photons`), `steps` the mean
    free flights per photon that pass 0 measured: cheap (dark) nodes get many photons,
    where their relative error was largest. The later passes are limited to the albedo
    nodes with `logit a'` in `logits` (the shipped table's third pass: the dark nodes)."""
    runs.mkdir(parents=True, exist_ok=True)

    def n_for(ie, ia, p):
        if p == 0 or budget is None:
            return photons
        first = runs / run_name(ie, ia, 0)
        steps = float(np.load(first)["steps"]) if first.exists() else 1.0
        return int(min(max_photons, budget / max(steps, 1.0)))

    # pass 0 first: the later passes' photon counts come from the steps it measured (a
    # list made before it ran would give every node MAX_PHOTONS); dearest first within a
    # pass (high albedo walks longest), so the pool stays busy to the end
    ctx = mp.get_context("spawn")
    t0 = time.perf_counter()
    with cf.ProcessPoolExecutor(jobs, mp_context=ctx) as ex:
        for group in ([0], list(range(1, passes))):
            todo = [
                (ie, ia, p, n_for(ie, ia, p), str(runs))
                for p in group
                for ia in reversed(range(LOGITS.size))
                for ie in range(ETAS.size)
                if not (runs / run_name(ie, ia, p)).exists()
                and (p == 0 or logits[0] - 1e-9 <= LOGITS[ia] <= logits[1] + 1e-9)
            ]
            todo = [t for t in todo if t[3] >= MIN_PHOTONS]
            print(f"profile table: {len(todo)} runs to do ({jobs} jobs)", flush=True)
            for k, (name, sec) in enumerate(ex.map(_run_one, todo), 1):
                el = time.perf_counter() - t0
                print(
                    f"  [{k}/{len(todo)}] {Path(name).name} {sec:.0f} s (elapsed {el:.0f} s)",
                    flush=True,
                )


def _merged(runs: Path, ie: int, ia: int):
    files = sorted(runs.glob(f"eta{ie}_a{ia:02d}_p*.npz"))
    if not files:
        raise SystemExit(f"profile table: no runs for eta node {ie}, albedo node {ia} in {runs}")
    d = [dict(np.load(f)) for f in files]
    n = np.array([float(x["n_photons"]) for x in d])
    N = n.sum()

    def mean(k):
        return sum(ni * x[k] for ni, x in zip(n, d, strict=True)) / N

    def err(k):
        return np.sqrt(sum((ni * x[k]) ** 2 for ni, x in zip(n, d, strict=True))) / N

    return dict(
        profile=mean("profile"),
        stderr=err("stderr"),
        counts=sum(x["counts"] for x in d),
        total=float(mean("total")),
        total_stderr=float(err("total_stderr")),
        lost=float(mean("lost")),
        n_photons=int(N),
        passes=len(files),
    )


def case_kappa(a: float) -> float:
    """`kappa = 1 / nu_0` of isotropic transport at single-scattering albedo `a`:
    `artanh(k) / k = 1 / a` (bisection in float64; `kappa -> 1` as `a -> 0`)."""
    lo, hi = 0.0, 1.0
    for _ in range(200):
        k = 0.5 * (lo + hi)
        f = math.atanh(k) / k if 0 < k < 1 else (1.0 if k == 0 else math.inf)
        if f < 1.0 / a:
            lo = k
        else:
            hi = k
    return 0.5 * (lo + hi)


def _smooth(lx, t, var, ok):
    """Local weighted quadratic fit of `t` on `lx` at every node; returns the value and its
    variance (NaN where no precise bin is in the window)."""
    n = lx.size
    out, out_var = np.full(n, np.nan), np.full(n, np.nan)
    for i in range(n):
        j = np.arange(max(i - HALF, 0), min(i + HALF + 1, n))
        j = j[ok[j]]
        if j.size < 3 or not ok[i]:
            continue
        u = (lx[j] - lx[i]) / (lx[1] - lx[0])
        k = (1 - (np.abs(u) / (HALF + 1)) ** 3) ** 3
        A = np.stack([np.ones_like(u), u, u * u], 1)
        W = k / var[j]
        M = np.linalg.pinv(A.T @ (W[:, None] * A))
        coef = M @ (A.T @ (W * t[j]))
        # the variance of the kernel-weighted estimate with real weights 1 / var
        C = M @ (A.T @ ((W * W * var[j])[:, None] * A)) @ M
        out[i], out_var[i] = coef[0], C[0, 0]
    return out, out_var


def _bins():
    """Table nodes `x` (geometric bin centres, uniform in log x) and the 16-point
    Gauss-Legendre rule `(rq, wq)` of each bin's annulus, with its area."""
    lo, hi = EDGES[1:-1], EDGES[2:]
    x = np.sqrt(lo * hi)
    gx, gw = np.polynomial.legendre.leggauss(16)
    rq = lo[:, None] + (hi - lo)[:, None] * (gx + 1) / 2  # (bins, 16)
    wq = (hi - lo)[:, None] / 2 * gw * 2 * np.pi * rq
    return x, rq, wq, np.pi * (hi**2 - lo**2)


def node_data(runs: Path, ia: int, ie: int) -> dict:
    """One node's merged runs as the raw log ratio to the better dipole, per bin: `t`, its
    variance `var` (inf where imprecise), the precise mask `ok`, and the smoothed `s`, `sv`
    (NaN where not smoothed), with `x`, the asymptotic `slope` and the merged run `m`."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from sssjax import profiles

    x, rq, wq, area = _bins()
    a = float(albedo(LOGITS[ia]))
    eta = float(ETAS[ie])
    m = _merged(runs, ie, ia)
    bd = np.asarray(profiles.Rd(jnp.asarray(rq), 1.0 - a, a, eta, "better_dipole"))
    bd_mean = np.sum(wq * bd, 1) / area
    mc, se = m["profile"][1:], m["stderr"][1:]
    ok = (mc > 0) & (se < REL_OK * np.where(mc > 0, mc, 1)) & (m["counts"][1:] >= 20)
    t = np.where(ok, np.log(np.where(mc > 0, mc, 1) / bd_mean), 0.0)
    var = np.where(ok, (se / np.where(mc > 0, mc, 1)) ** 2, np.inf)
    s, sv = _smooth(np.log(x), t, var, ok)
    k_bd = float(profiles.sigma_tr_better(1.0 - a, a))
    return dict(x=x, t=t, var=var, ok=ok, s=s, sv=sv, slope=k_bd - case_kappa(a), m=m, a=a)


# Tail models: `T = slope x + sum_i c_i b_i(x)`, fitted by weighted least squares to the
# raw precise bins of the last decade (`tail_fit`); `slope = kappa_bd - kappa` is the exact
# asymptotic decay (both profiles fall as e^{-k x} / x^2 far out, each with its own k)
TAIL_BASES = {
    "line": lambda u: [np.ones_like(u)],  # the asymptote alone (the first table's tail)
    "inverse2": lambda u: [np.ones_like(u), 1.0 / u, 1.0 / u**2],  # + its 1/x corrections
    "free": lambda u: [np.ones_like(u), u],  # a straight line of free slope
}


def tail_fit(x, t, var, ok, slope, x_end, basis):
    """One of `TAIL_BASES` fitted to the precise bins `ok` over the decade before `x_end`
    (from 1 mfp at least; a half decade with the line alone where that leaves too few
    bins). Returns `T` at the nodes `x` and its standard error."""
    base = TAIL_BASES[basis]
    win = ok & (x <= x_end * (1 + 1e-9)) & (x >= max(x_end / TAIL_DECADE, 1.0))
    if win.sum() < 2 * len(base(x[:1])):
        win = ok & (x <= x_end * (1 + 1e-9)) & (x >= x_end / 10**0.5)
        base = TAIL_BASES["line"]
    B = np.stack(base(x), -1)
    w = 1.0 / var[win]
    cov = np.linalg.pinv(B[win].T @ (w[:, None] * B[win]))
    coef = cov @ (B[win].T @ (w * (t[win] - slope * x[win])))
    return B @ coef + slope * x, np.sqrt(np.einsum("...i,ij,...j->...", B, cov, B))


def tail_model(x, t, var, ok, slope, x_end, basis="envelope"):
    """The tail continuation at the nodes `x` and its standard error. `"envelope"` (what
    the table uses): the mean of the `"inverse2"` and `"free"` fits, with their full
    difference added to the statistical error as the model's uncertainty. Neither alone
    extrapolates within its error (`check_tail`: between reduced albedo 0.5 and 0.95 the
    profile still rises against the asymptote at 10-20 mfp, faster than the 1/x terms allow;
    a free slope overshoots for bright media); the truth lies between them. Any other name:
    that one of `TAIL_BASES` with its statistical error only."""
    if basis != "envelope":
        return tail_fit(x, t, var, ok, slope, x_end, basis)
    f1, e1 = tail_fit(x, t, var, ok, slope, x_end, "inverse2")
    f2, e2 = tail_fit(x, t, var, ok, slope, x_end, "free")
    return 0.5 * (f1 + f2), np.sqrt(0.5 * (e1**2 + e2**2) + (f1 - f2) ** 2)


def assemble(runs: Path, table: Path):
    import jax

    jax.config.update("jax_enable_x64", True)

    from sssjax import profiles, reference

    x, _, _, _ = _bins()
    lx = np.log(x)
    na, ne, nx = LOGITS.size, ETAS.size, x.size
    T = np.zeros((nx, na, ne))
    T_err = np.full((nx, na, ne), np.nan)
    cont = np.zeros((nx, na, ne), bool)
    tot = np.zeros((na, ne))
    tot_err = np.zeros((na, ne))
    log_total_ratio = np.zeros((na, ne))
    slope = np.zeros(na)
    photons = np.zeros((na, ne), np.int64)
    for ia in range(na):
        for ie, eta in enumerate(ETAS):
            d = node_data(runs, ia, ie)
            m, s, sv, a = d["m"], d["s"], d["sv"], d["a"]
            slope[ia] = d["slope"]
            photons[ia, ie] = m["n_photons"]
            good = np.isfinite(s)
            if not good.any():
                raise SystemExit(f"profile table: no precise bin at a'={a:.5g}, eta={eta}")
            first, last = np.argmax(good), nx - 1 - np.argmax(good[::-1])
            # the tail: the last precise bins alone carry 10-20% noise, and a bright
            # medium's sigma_a rests on them; so beyond the precise bins the table follows
            # `tail_model` (the envelope, with its error), and over the last half decade of
            # them the smoothed values are blended to it linearly in log x
            f, fe = tail_model(x, d["t"], d["var"], d["ok"], d["slope"], x[last])
            j = np.nonzero(good & (x >= x[last] / 10**0.5))[0]
            u = (lx[j] - lx[j[0]]) / max(lx[last] - lx[j[0]], 1e-12)
            col = s.copy()
            err = np.sqrt(sv)
            col[j] = (1 - u) * s[j] + u * f[j]
            err[j] = np.sqrt((1 - u) * sv[j] + u * fe[j] ** 2)
            col[:first] = s[first]
            col[last + 1 :] = f[last + 1 :]
            err[last + 1 :] = fe[last + 1 :]
            cont[last + 1 :, ia, ie] = True
            # interior holes (an isolated imprecise bin): linear in log x
            hole = ~good & (np.arange(nx) > first) & (np.arange(nx) < last)
            col[hole] = np.interp(lx[hole], lx[good], s[good])
            err[hole] = np.interp(lx[hole], lx[good], np.sqrt(sv[good]))
            T[:, ia, ie] = col
            T_err[first:, ia, ie] = err[first:]
            tot[ia, ie] = m["total"]
            tot_err[ia, ie] = math.hypot(m["total_stderr"], m["lost"])
            bd_tot = float(profiles.Rd_total(1.0 - a, a, float(eta), "better_dipole"))
            log_total_ratio[ia, ie] = math.log(m["total"] / bd_tot)
    # single scattering is a quadrature, not a walk: a finer eta grid of its own; stored as
    # log S + k(eta) x, with its exact far decay e^{-k x}, k = eta + sqrt(eta^2 - 1) (the
    # grazing exits at the critical angle), removed, which leaves a smooth function of eta
    S_ETAS = np.round(np.linspace(1.0, 1.6, 25), 6)
    ns = S_ETAS.size
    log_G = np.zeros((nx, ns))
    S_total = np.zeros(ns)
    for ie, eta in enumerate(S_ETAS):
        t_in = 1.0 - float(reference._fresnel_np(1.0, float(eta)))
        S = reference.single_scatter_exitance(x, 0.0, 1.0, 0.0, float(eta)) / t_in
        S_total[ie] = reference.single_scatter_total(0.0, 1.0, 0.0, float(eta)) / t_in
        k = float(eta) + math.sqrt(max(float(eta) ** 2 - 1.0, 0.0))
        with np.errstate(divide="ignore"):
            lg = np.log(S) + k * x
        # far out the quadrature underflows: hold the (slowly varying) remainder
        bad = ~np.isfinite(lg) | (S < 1e-280)
        if bad.any():
            lg[bad] = lg[np.argmax(bad) - 1]
        log_G[:, ie] = lg
    table.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        table,
        log_x=lx,
        logit=LOGITS,
        eta=ETAS,
        T=T.astype(np.float32),
        T_err=T_err.astype(np.float32),
        continued=cont,
        slope=slope.astype(np.float32),
        ms_total=tot.astype(np.float32),
        ms_total_err=tot_err.astype(np.float32),
        log_total_ratio=log_total_ratio.astype(np.float32),
        eta_S=S_ETAS,
        log_G=log_G.astype(np.float32),
        S_total=S_total.astype(np.float32),
        photons=photons,
        built=np.array(datetime.date.today().isoformat()),
        seed0=np.array(SEED0),
        smooth_half=np.array(HALF),
    )
    rel = T_err[np.isfinite(T_err) & ~cont]  # the precise nodes (the continued: below)
    print(
        f"profile table: wrote {table} ({table.stat().st_size / 1024:.0f} KiB); "
        f"{photons.min()}-{photons.max()} photons per node; relative error of the precise "
        f"nodes: median {np.median(rel):.2%}, 90th percentile {np.percentile(rel, 90):.2%}; "
        f"totals: median {np.median(tot_err / tot):.2%}"
    )
    x_last = np.array([[x[~cont[:, i, j]].max() for j in range(ne)] for i in range(na)])
    print(
        "profile table: precise out to x = "
        + ", ".join(
            f"{x_last[i].min():.3g}-{x_last[i].max():.3g} (a' {albedo(LOGITS[i]):.3g})"
            for i in range(0, na, 4)
        )
        + " mfp; the envelope continues beyond"
    )


def check_tail(runs: Path, cut: float = 10**0.5, bases=("line", "inverse2", "free", "envelope")):
    """Held-out check of the tail continuation on the table's own runs: for every node, the
    continuation is rebuilt from the precise bins up to `cut` times before the last one and
    compared with the held-out bins beyond (the build's own Monte Carlo, independent of the
    bins it was fitted to). Prints, per albedo node, the mean and rms over the held-out bins
    (all eta) of `z = (t - T) / sqrt(var + T_err^2)` for each `tail_model`: `|mean z| >>
    0` or `rms z >> 1` is a continuation that misleads a fit."""
    x, _, _, _ = _bins()
    print(
        f"held out: the precise bins beyond 1/{cut:.3g} of the last one; per basis: mean z, rms z"
    )
    print(f"{'logit':>6} {'a_prime':>8} {'bins':>5} " + " ".join(f"{b:>13}" for b in bases))
    allz = {b: [] for b in bases}
    for ia in range(LOGITS.size):
        zs = {b: [] for b in bases}
        for ie in range(ETAS.size):
            d = node_data(runs, ia, ie)
            good = np.isfinite(d["s"])
            last = x.size - 1 - np.argmax(good[::-1])
            x_cut = x[last] / cut
            held = d["ok"] & (x > x_cut * (1 + 1e-9))
            seen = d["ok"] & (x <= x_cut * (1 + 1e-9))
            if held.sum() < 2 or seen.sum() < 8:
                continue
            var = np.where(seen, d["var"], np.inf)
            for b in bases:
                f, fe = tail_model(x, d["t"], var, seen, d["slope"], x_cut, basis=b)
                zs[b].append((d["t"][held] - f[held]) / np.sqrt(d["var"][held] + fe[held] ** 2))
        if not zs[bases[0]]:
            continue
        row = f"{LOGITS[ia]:6.1f} {albedo(LOGITS[ia]):8.5f} {sum(z.size for z in zs[bases[0]]):5d} "
        for b in bases:
            z = np.concatenate(zs[b])
            allz[b].append(z)
            row += f" {z.mean():+6.2f} {np.sqrt(np.mean(z**2)):6.2f}"
        print(row)
    for b in bases:
        z = np.concatenate(allz[b])
        print(
            f"all nodes, {b}: {z.size} held-out bins, mean z {z.mean():+.2f}, rms z "
            f"{np.sqrt(np.mean(z**2)):.2f}, |z| > 3: {np.mean(np.abs(z) > 3):.1%}"
        )


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photons", type=int, default=65536, help="photons per node and pass")
    ap.add_argument("--passes", type=int, default=1, help="independent passes (seeds) per node")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes")
    ap.add_argument(
        "--budget",
        type=float,
        help="passes after the first: free flights per node (photons = budget / steps)",
    )
    ap.add_argument(
        "--bright",
        type=int,
        metavar="PHOTONS",
        help="add --bright-passes re-weighted walks of PHOTONS per eta for the bright nodes",
    )
    ap.add_argument("--bright-passes", type=int, default=2)
    ap.add_argument(
        "--max-photons", type=float, default=MAX_PHOTONS, help="cap per node and later pass"
    )
    ap.add_argument(
        "--logits",
        default=None,
        metavar="LO,HI",
        help="limit the passes after the first to albedo nodes with logit a' in [LO, HI]",
    )
    ap.add_argument("--runs", type=Path, default=ROOT / "out" / "profile_table" / "runs")
    ap.add_argument("--table", type=Path, default=TABLE)
    ap.add_argument("--assemble", action="store_true", help="only assemble the existing runs")
    ap.add_argument(
        "--check-tail", action="store_true", help="only the held-out check of the tail model"
    )
    ap.add_argument("--cut", type=float, default=10**0.5, help="--check-tail's held-out factor")
    a = ap.parse_args()
    t0 = time.perf_counter()
    if a.check_tail:
        check_tail(a.runs, a.cut)
        return
    if not a.assemble:
        lim = tuple(float(v) for v in a.logits.split(",")) if a.logits else (-np.inf, np.inf)
        run(a.photons, a.passes, a.jobs, a.runs, a.budget, int(a.max_photons), lim)
        if a.bright:
            bright(a.bright, a.bright_passes, a.jobs, a.runs)
    assemble(a.runs, a.table)
    print(f"profile table: done in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
