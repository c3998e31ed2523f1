"""Coverage of the volumetric fit's error bars on objects (2 CPU cores; run idle).

    python benchmarks/coverage.py [--objects cube cylinder sphere] [--seeds 4] [--size 64]
                                  [--spp 8] [--target-spp 32] [--rounds 8] [--json PATH]
                                  [--target-seed 1000] [--at-truth]

For each object of `benchmarks/vs_mitsuba.py` (the marble cube, the skim-milk cylinder, the
ketchup sphere: eta 1.3 on a floor under an area light) and each seed `k`: a target
rendered by the volumetric (exact) transport with seed `1000 + k`, and a fit of the object's
6 coefficients (`sigma_a`, `sigma_s` RGB, 1/mm) from x1.5 / x0.7 with independent random
numbers (seed `k`). Prints per fit the errors, the reported relative bars, the errors in
standard errors `z` and the verdict; then per object and over all the share of `|z| < 2`
(about 95 % if the bars are honest and the fit unbiased), the largest `|z|`, the share of
fits that say they converged, and the same among the converged ones (a fit that says it did
not settle warns that its bars are lower bounds). The truth is the preset the target was
rendered with: an exact target, so the bias measured is the fit's, not a model's.

The targets are the same for every run unless `--target-seed` moves them: three targets
can be low together by chance (the cylinder's seeds 1000-1002 are, in red `sigma_s`, already
at the truth). `--at-truth` judges the estimating equation and its bars alone, without the
rounds' dynamics: every round traced at the truth (no steps), all rounds pooled, the answer
the pooled root (the fit's last jump onto it; the verdicts then say "NOT settled", which
means nothing there, and the coefficients the rounds leave undetermined stay at the truth).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from vs_mitsuba import scene_dict  # noqa: E402

import sssjax  # noqa: E402
from sssjax.fit import _solve  # noqa: E402


@contextlib.contextmanager
def rounds_at_the_start():
    """The fit's rounds without steps, every round pooled: each re-traces at the start with
    new random numbers, and the answer is the pooled root (a diagnostic of the estimating
    equation, reaching into the solver's private functions)."""
    step, after = _solve.pooled_step, _solve.pooled_after
    _solve.pooled_step = lambda rounds, y: np.zeros(np.asarray(y).size)
    _solve.pooled_after = lambda pool, k, lin, start=0: pool + [(k, lin)]
    try:
        yield
    finally:
        _solve.pooled_step, _solve.pooled_after = step, after


def fit_once(
    kind: str,
    seed: int,
    size: int,
    spp: int,
    target_spp: int,
    rounds: int,
    target_seed: int = 1000,
    at_truth: bool = False,
) -> dict:
    sc = sssjax.load_scene(scene_dict(kind, size, spp))
    m = sc.media()["obj"]
    truth = np.concatenate([np.asarray(m.sigma_a), np.asarray(m.sigma_s)])
    tgt = sssjax.render(
        sssjax.load_scene(scene_dict(kind, size, target_spp)), key=target_seed + seed
    )
    fa, fs = (1.0, 1.0) if at_truth else (1.5, 0.7)
    t0 = time.perf_counter()
    with rounds_at_the_start() if at_truth else contextlib.nullcontext():
        r = sssjax.fit(
            sc,
            np.asarray(tgt),
            init={"sigma_a": truth[:3] * fa, "sigma_s": truth[3:] * fs},
            seed=seed,
            proposal_rounds=rounds,
            progress=False,
        )
    wall = time.perf_counter() - t0
    v = np.array([r.values[n] for n in r.names])
    e = np.array([r.stderr[n] for n in r.names])
    return {
        "object": kind,
        "seed": seed,
        "names": r.names,
        "truth": truth.tolist(),
        "values": v.tolist(),
        "stderr": e.tolist(),
        "z": ((v - truth) / e).tolist(),
        "converged": bool(r.converged),
        "message": r.message,
        "rounds": r.steps,
        "wall_s": wall,
    }


def summary(rows: list[dict], label: str) -> str:
    z = np.abs(np.array([r["z"] for r in rows]))
    conv = np.array([r["converged"] for r in rows])
    line = (
        f"{label}: {len(rows)} fits, |z| < 2 for {np.mean(z < 2):.0%} of {z.size} coefficients, "
        f"max |z| {z.max():.2f}; converged {conv.sum()} of {conv.size}"
    )
    if conv.any() and not conv.all():
        zc = z[conv]
        line += f" (among them |z| < 2 for {np.mean(zc < 2):.0%}, max {zc.max():.2f})"
    return line


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--objects", nargs="+", default=["cube", "cylinder", "sphere"])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--target-spp", type=int, default=32)
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--json", type=Path, default=None, help="write every fit's numbers here")
    ap.add_argument("--target-seed", type=int, default=1000, help="target k has seed this + k")
    ap.add_argument(
        "--at-truth", action="store_true", help="rounds traced at the truth, no steps, all pooled"
    )
    a = ap.parse_args()
    start = "at the truth, no steps" if a.at_truth else "from x1.5 sigma_a / x0.7 sigma_s"
    print(
        f"{a.size} x {a.size}, fit {a.spp} spp x up to {a.rounds} rounds, "
        f"targets {a.target_spp} spp (seeds {a.target_seed} + k); {start}",
        flush=True,
    )
    rows = []
    for kind in a.objects:
        for k in range(a.seeds):
            r = fit_once(kind, k, a.size, a.spp, a.target_spp, a.rounds, a.target_seed, a.at_truth)
            rows.append(r)
            rel = np.array(r["stderr"]) / np.array(r["values"])
            err = np.array(r["values"]) / np.array(r["truth"]) - 1
            print(
                f"{kind:8s} seed {k}: {r['wall_s']:.0f} s, {r['rounds']} rounds, "
                f"{'converged' if r['converged'] else 'NOT settled'}\n"
                f"  errors {' '.join(f'{x:+.1%}' for x in err)}\n"
                f"  bars   {' '.join(f'{x:.1%}' for x in rel)}\n"
                f"  z      {' '.join(f'{x:+.2f}' for x in r['z'])}",
                flush=True,
            )
            if a.json:
                a.json.write_text(json.dumps(rows, indent=1))
        print(summary([r for r in rows if r["object"] == kind], kind), flush=True)
    print(summary(rows, "all"))


if __name__ == "__main__":
    main()
