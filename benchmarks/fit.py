"""Fit benchmark: marble from a 256 x 256 marble_cube target, start 2x / 0.5x off.

    python benchmarks/fit.py [--size 256] [--spp 16] [--target-seed 0]

Prints trace time, time per iteration, iterations, wall time (second run, after
compilation) and the coefficient errors. `--target-seed 0` is the same seed as the fit
(recovery is then exact up to float32); another seed measures the noise-induced error.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import sssjax

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--target-seed", type=int, default=0)
    a = ap.parse_args()
    scene = sssjax.load_scene(ROOT / "scenes" / "marble_cube.toml").with_settings(
        width=a.size, height=a.size, spp=a.spp
    )
    target = sssjax.render(scene, a.target_seed)
    true = scene.media()["marble"]
    init = {"sigma_a": np.asarray(true.sigma_a) * 2, "sigma_s": np.asarray(true.sigma_s) * 0.5}
    sssjax.fit(scene, target, init=init, seed=0)  # compile
    t0 = time.perf_counter()
    res = sssjax.fit(scene, target, init=init, seed=0)
    wall = time.perf_counter() - t0
    per_it = (wall - res.trace_time_s) / max(res.steps, 1)
    tr = sssjax.trace(scene, 0)
    n_t = int(tr.t_rows.shape[0])
    print(f"marble_cube {a.size}x{a.size} @ {a.spp} spp, target seed {a.target_seed}, fit seed 0")
    print(f"  trace:                 {res.trace_time_s:7.2f} s ({n_t} translucent pixels)")
    print(f"  iterations:            {res.steps:7d} ({res.status}: {res.message})")
    print(
        f"  time per iteration:    {per_it * 1e3:7.1f} ms "
        f"({per_it * 1e3 / (n_t / 1000):.2f} ms per 1,000 translucent pixels, incl. overhead)"
    )
    print(f"  wall (after compile):  {wall:7.2f} s")
    for f, tv in (("sigma_a", true.sigma_a), ("sigma_s", true.sigma_s)):
        got = np.array([res.values[f"marble.{f}.{c}"] for c in "RGB"])
        err = got / np.asarray(tv) - 1
        se = np.array([res.stderr[f"marble.{f}.{c}"] for c in "RGB"]) / np.asarray(tv)
        print(
            f"  {f} relative error:  "
            + "  ".join(f"{e:+.4%}" for e in err)
            + "   (reported s.e. "
            + "  ".join(f"{s:.3%}" for s in se)
            + ")"
        )


if __name__ == "__main__":
    main()
