"""The diffusion transport against the volumetric one, at the true coefficients.

    python benchmarks/transports.py [--size 64] [--spp 64] [--seeds 2] [--out docs/transports.md]

The three scenes of `benchmarks/vs_mitsuba.py` (a marble cube, a skim-milk cylinder, a ketchup
sphere behind eta 1.3 on a grey floor under one area light) rendered with `[sss] transport =
"diffusion"` (the dipole, direct light only, opaque shadows) and `"volumetric"` (exact random
walks, tested against closed forms and an independent photon tracer in
`tests/test_volumetric.py`; `benchmarks/vs_mitsuba.py` compares it with Mitsuba 3). Prints, per scene and
region (the object; the floor within 40 mm of it: its shadow and the light it sends down), the
ratio diffusion / volumetric per channel with its standard error (from independent volumetric
seeds), and the wall time of each render; writes the table as markdown to `--out`.
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from vs_mitsuba import regions, scene_dict  # noqa: E402

import sssjax  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SCENES = {"cube": "marble cube", "cylinder": "skim-milk cylinder", "sphere": "ketchup sphere"}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spp", type=int, default=64, help="volumetric samples per pixel")
    ap.add_argument("--seeds", type=int, default=2, help="independent volumetric renders")
    ap.add_argument("--out", default=str(ROOT / "docs" / "transports.md"))
    a = ap.parse_args()
    rows = []
    for kind, label in SCENES.items():
        base = sssjax.load_scene(scene_dict(kind, a.size, a.spp))
        vol_sc = base.with_settings(sss_transport="volumetric")
        dif_sc = base.with_settings(sss_transport="diffusion", spp=16)
        t0 = time.perf_counter()
        dif = np.asarray(sssjax.render(dif_sc, key=0))
        t_dif = time.perf_counter() - t0
        vols, t_vol = [], []
        for s in range(a.seeds):
            t0 = time.perf_counter()
            vols.append(np.asarray(sssjax.render(vol_sc, key=100 + s)))
            t_vol.append(time.perf_counter() - t0)
        vol = np.mean(vols, axis=0)
        for region, mask in regions(base).items():
            means = np.array([v[mask].mean(axis=0) for v in vols])  # (seeds, 3)
            m = means.mean(axis=0)
            se = means.std(axis=0, ddof=1) / np.sqrt(len(vols)) if len(vols) > 1 else m * 0
            ratio = dif[mask].mean(axis=0) / m
            ratio_se = ratio * se / m
            rows.append((label, region, int(mask.sum()), ratio, ratio_se))
            print(
                f"{label:20s} {region:11s} ({int(mask.sum()):5d} px)  diffusion / volumetric "
                + "  ".join(f"{r:.3f}+-{e:.3f}" for r, e in zip(ratio, ratio_se, strict=True)),
                flush=True,
            )
        print(
            f"{label:20s} wall: diffusion {t_dif:.1f} s (16 spp), volumetric "
            f"{np.mean(t_vol):.1f} s ({a.spp} spp, first includes compilation: "
            f"{', '.join(f'{t:.1f}' for t in t_vol)})",
            flush=True,
        )
        del vol
    lines = [
        "# The diffusion transport against the volumetric one",
        "",
        f"Written by `benchmarks/transports.py --size {a.size} --spp {a.spp} --seeds {a.seeds}`"
        f" ({datetime.date.today().isoformat()}, {os.cpu_count()} CPU cores):",
        "the scenes of `benchmarks/vs_mitsuba.py` at the true coefficients, the ratio of the",
        "mean radiance diffusion / volumetric per region and channel (R, G, B), +- its standard",
        "error from the independent volumetric renders. 1 is exact; the volumetric transport's",
        "own comparison with Mitsuba 3 is in the README ('Against Mitsuba 3').",
        "",
        "| scene | region | pixels | R | G | B |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for label, region, n, ratio, se in rows:
        cells = " | ".join(f"{r:.3f} +- {e:.3f}" for r, e in zip(ratio, se, strict=True))
        lines.append(f"| {label} | {region} | {n} | {cells} |")
    Path(a.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
