"""Rebuild `tests/data/preset_profiles.npz`: exact profiles of all 33 preset channels.

    python benchmarks/preset_profiles.py [--out tests/data/preset_profiles.npz]

For every preset of `sssjax.media` and each RGB channel: the total exitance (all orders,
per unit power entering, mm^-2) of a semi-infinite slab (eta 1.3, the preset's `sigma_a`
and `sigmap_s`, isotropic) under a pencil beam, by `sssjax.reference` with the accuracy
benchmark's budget (a pilot, then photons for 1e8 free-flight steps, at most 6 million),
40 log bins per decade from 0.01 to 100 reduced mean free paths.

The seeds (`SEED0 + 10 i + c`, the main run `+ 1000`) are used by nothing else: not by the
table's build (`benchmarks/profile_table.py`, seeds from 7 000 000) nor by
`benchmarks/accuracy.py` (seeds from 0). So `tests/test_tabulated.py` fits the tabulated
profile to data independent of the table. About 7 minutes on 2 cores; about 250 kB.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from accuracy import SETTINGS, preset_bins, run_channel

from sssjax import reference
from sssjax.media import PRESET_ETA, PRESETS

ROOT = Path(__file__).resolve().parent.parent
SEED0 = 40_000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "tests" / "data" / "preset_profiles.npz"))
    a = ap.parse_args()
    cfg = SETTINGS["full"]
    t0 = time.perf_counter()
    arrays: dict[str, np.ndarray] = {"eta": np.array(PRESET_ETA), "seed0": np.array(SEED0)}
    names = sorted(PRESETS)
    for i, name in enumerate(names):
        sa, sps, edges = preset_bins(name)
        refs = []
        for c in range(3):
            ref = run_channel(sa[c], sps[c], PRESET_ETA, edges, SEED0 + 10 * i + c, cfg)
            refs.append(ref)
            print(
                f"[{3 * i + c + 1:2d}/{3 * len(names)}] {name:9s} {'RGB'[c]}: "
                f"{ref.n_photons:8d} photons ({(time.perf_counter() - t0) / 60:4.1f} min)",
                flush=True,
            )
        prof = reference.to_profile(tuple(refs), component="total", normalization="entered")
        arrays[f"{name}/sigma_a"] = sa
        arrays[f"{name}/sigmap_s"] = sps
        arrays[f"{name}/r_edges"] = edges
        arrays[f"{name}/r"] = prof.r
        arrays[f"{name}/mean"] = prof.mean
        arrays[f"{name}/stderr"] = prof.stderr
        arrays[f"{name}/photons"] = np.array([r.n_photons for r in refs])
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **arrays)
    size = out.stat().st_size / 1e3
    print(f"wrote {out} ({size:.0f} kB) in {(time.perf_counter() - t0) / 60:.1f} min")


if __name__ == "__main__":
    main()
