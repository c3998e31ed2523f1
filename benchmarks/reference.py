"""Monte Carlo reference benchmark: photons per second of `sssjax.reference.simulate`.

    python benchmarks/reference.py [--photons 200000] [--seed 0]

For each preset, a small warm-up run compiles the walk (same shapes), then the timed run
prints photons per second, free flights (steps) per photon and steps per second.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from sssjax import reference

PRESETS = {
    # name: (sigma_a, sigma_s, g, eta)
    "marble red (albedo 0.999, eta 1.3)": (0.0021, 2.19, 0.0, 1.3),
    "skin1 red (albedo 0.96, eta 1.3)": (0.032, 0.74, 0.0, 1.3),
    "albedo 0.99, g 0.8, eta 1.0": (0.01, 4.95, 0.8, 1.0),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--photons", type=int, default=200_000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    print(f"{os.cpu_count()} CPU cores visible; {a.photons} photons per preset")
    for name, (sa, ss, g, eta) in PRESETS.items():
        reference.simulate(sa, ss, g, eta, n_photons=20_000, seed=a.seed + 1)  # compile
        t0 = time.perf_counter()
        ref = reference.simulate(sa, ss, g, eta, n_photons=a.photons, seed=a.seed)
        dt = time.perf_counter() - t0
        rate = a.photons / dt
        steps = ref.steps_per_photon
        print(
            f"{name:38s} {rate:10,.0f} photons/s ({rate * 60 / 1e6:5.2f} M/min), "
            f"{steps:6.1f} steps/photon, {rate * steps / 1e6:5.2f} M steps/s, "
            f"R_d = {ref.diffuse:.4f} +- {ref.diffuse_stderr:.4f}"
        )
        assert np.isfinite(ref.diffuse)


if __name__ == "__main__":
    main()
