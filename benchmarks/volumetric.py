"""Speed and noise of the volumetric transport (2 CPU cores; run idle).

    python benchmarks/volumetric.py [--size 48] [--spp 16]

Prints, on the marble cube of `benchmarks/vs_mitsuba.py`:

- render throughput (walkers / s after compilation) and the noise of the object's pixels,
  for refracted next-event estimation against plain random exits (light reached only when a
  walk leaves towards it), and for spectral MIS (one walker for RGB) against one walker per
  channel; "time to equal noise" is wall x variance, relative to the default;
- the re-weighting shade of a 256 x 256 image (the per-iteration cost of a fit: terms of the
  default shape, 16 spp x 4 records per pixel), and its forward-mode Jacobian (6 coefficients);
- a fit of the cube's 6 coefficients (or, with `--object cylinder | sphere`, the skim-milk
  cylinder's or the ketchup sphere's) from a volumetric target (independent seed), with its
  wall time, trace time and the errors in standard errors. The issue's 120 s case (256 x 256
  exact target, 4 rounds of 4 spp against a 16 spp target; about 2 min):

    python benchmarks/volumetric.py --fit-only --fit-size 256 --fit-spp 4 --target-spp 16 --rounds 4
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from vs_mitsuba import regions, scene_dict  # noqa: E402

import sssjax  # noqa: E402
from sssjax.transport import volumetric as V  # noqa: E402


def timed(fn, *a, repeat=1):
    fn(*a)  # compile
    t0 = time.perf_counter()
    for _ in range(repeat):
        out = fn(*a)
    jax.block_until_ready(out)
    return out, (time.perf_counter() - t0) / repeat


def noise_table(size: int, spp: int) -> None:
    base = sssjax.load_scene(scene_dict("cube", size, spp))
    obj = regions(base)["object"]
    rows = []
    for label, settings in (
        ("default (NEE, spectral MIS)", {}),
        ("random exits only (no NEE)", {"sss_next_event": False}),
        ("one walker per channel", {"sss_spectral": "separate"}),
    ):
        sc = base.with_settings(**settings)
        sssjax.render(sc, key=0)  # compile
        imgs, ts = [], []
        for k in (1, 2):
            t0 = time.perf_counter()
            imgs.append(np.asarray(sssjax.render(sc, key=k)))
            ts.append(time.perf_counter() - t0)
        diff = (imgs[0] - imgs[1])[obj] / np.sqrt(2)
        mean = 0.5 * (imgs[0] + imgs[1])[obj].mean(axis=0)
        rel = diff.std(axis=0) / mean
        walkers = size * size * spp * (3 if settings.get("sss_spectral") == "separate" else 1)
        rows.append((label, np.mean(ts), walkers / np.mean(ts), rel, mean))
    t0, v0 = rows[0][1], np.mean(rows[0][3] ** 2)
    print(f"\nmarble cube {size} x {size}, {spp} spp; noise = per-pixel relative sd on the object")
    for label, t, rate, rel, mean in rows:
        eq = t * np.mean(rel**2) / (t0 * v0)
        print(
            f"  {label:30s} {t:6.2f} s  {rate / 1e3:7.1f} k walkers/s  noise R G B "
            f"{rel[0]:.3f} {rel[1]:.3f} {rel[2]:.3f}  mean {mean.mean():.4f}  "
            f"time to equal noise x{eq:.2f}"
        )


def shade_timing() -> None:
    P, R, Mt = 256 * 256, 16 * 4, 1
    key = jax.random.key(0)
    k1, k2, k3 = jax.random.split(key, 3)
    terms = V.VolumetricShading(
        jax.random.uniform(k1, (3, P, R)) * 1e-2,
        jnp.floor(jax.random.exponential(k2, (P, R, Mt)) * 50.0),
        jax.random.exponential(k3, (P, R, Mt)) * 20.0,
        jnp.full((Mt, 3), 2.6),
        jnp.full((Mt, 3), 2.6),
        4,
    )
    m0 = sssjax.Medium([0.0021, 0.0041, 0.0071], [2.19, 2.62, 3.0])

    def image(y):
        med = sssjax.Medium(jnp.exp(y[:3]), jnp.exp(y[3:]))
        return terms.shade([med])

    y = jnp.log(jnp.concatenate([m0.sigma_a, m0.sigma_s]))
    _, t_shade = timed(jax.jit(image), y, repeat=5)
    _, t_jac = timed(jax.jit(jax.jacfwd(image)), y, repeat=2)
    print(
        f"\nre-weighting shade, 256 x 256 x {R} records: {1e3 * t_shade:.0f} ms per image, "
        f"forward Jacobian (6 coefficients) {1e3 * t_jac:.0f} ms"
    )


def fit_timing(size: int, spp: int, target_spp: int, rounds: int, kind: str = "cube") -> None:
    sc = sssjax.load_scene(scene_dict(kind, size, spp))
    m = sc.media()["obj"]
    t0 = time.perf_counter()
    tgt = sssjax.render(sssjax.load_scene(scene_dict(kind, size, target_spp)), key=1)
    print(f"\ntarget ({size} x {size}, {target_spp} spp): {time.perf_counter() - t0:.0f} s")
    t0 = time.perf_counter()
    r = sssjax.fit(
        sc,
        tgt,
        init={"sigma_a": np.asarray(m.sigma_a) * 1.5, "sigma_s": np.asarray(m.sigma_s) * 0.7},
        proposal_rounds=rounds,
    )
    wall = time.perf_counter() - t0
    truth = list(np.asarray(m.sigma_a)) + list(np.asarray(m.sigma_s))
    z = [(r.values[n] - t) / r.stderr[n] for n, t in zip(r.names, truth, strict=True)]
    err = [r.values[n] / t - 1 for n, t in zip(r.names, truth, strict=True)]
    print(
        f"fit of the {kind} ({size} x {size}, {spp} spp, {rounds} rounds), 6 coefficients "
        f"from x1.5 / x0.7: "
        f"{wall:.0f} s wall (trace {r.trace_time_s:.0f} s, {r.steps} steps), {r.message}"
    )
    print("  errors " + " ".join(f"{e:+.1%}" for e in err))
    print("  bars   " + " ".join(f"{r.stderr[n] / r.values[n]:.1%}" for n in r.names))
    print("  z      " + " ".join(f"{v:+.1f}" for v in z))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--fit-only", action="store_true", help="only the fit")
    ap.add_argument("--fit-size", type=int, default=None, help="default: --size")
    ap.add_argument("--fit-spp", type=int, default=None, help="default: --spp")
    ap.add_argument("--target-spp", type=int, default=None, help="default: the fit's spp")
    ap.add_argument("--rounds", type=int, default=8, help="proposal_rounds")
    ap.add_argument(
        "--object", default="cube", choices=["cube", "cylinder", "sphere"], help="the fit's scene"
    )
    a = ap.parse_args()
    if not a.fit_only:
        shade_timing()
        noise_table(a.size, a.spp)
    fs, fspp = a.fit_size or a.size, a.fit_spp or a.spp
    fit_timing(fs, fspp, a.target_spp or fspp, a.rounds, a.object)


if __name__ == "__main__":
    main()
