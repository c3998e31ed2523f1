"""Render benchmark: compile, trace and shade times, rays per second and peak memory.

    python benchmarks/render.py [--scene scenes/marble_cube.toml] [--size 256] [--spp 16]
                                [--large 512]

Prints figures; asserts nothing (the floors are in the README and the issue).
"""

from __future__ import annotations

import argparse
import resource
import time

import jax

import sssjax
from sssjax.render import Renderer, as_key
from sssjax.shade import shade


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def bench(scene_path: str, size: int, spp: int) -> None:
    scene = sssjax.load_scene(scene_path)
    h = round(size * scene.camera.height / scene.camera.width)
    scene = scene.with_settings(width=size, height=h, spp=spp)
    r = Renderer(scene)
    key = as_key(0, scene)
    media = tuple(scene.media()[n] for n in r.arrays.materials)

    t0 = time.perf_counter()
    r.render(key, media, progress=False)
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    r.render(key, media, progress=False)
    t_render = time.perf_counter() - t0

    t0 = time.perf_counter()
    tr = jax.block_until_ready(r.trace(key, progress=False))
    t_trace = time.perf_counter() - t0
    shade_j = jax.jit(shade)
    jax.block_until_ready(shade_j(tr, media))
    t0 = time.perf_counter()
    jax.block_until_ready(shade_j(tr, media))
    t_shade = time.perf_counter() - t0

    n_cam = size * h * spp
    n_t = int(tr.t_rows.shape[0])
    print(
        f"{scene_path} {size}x{h} @ {spp} spp, cloud {r.transport.cloud_n}, on "
        f"{jax.device_count()} {jax.devices()[0].platform} device(s)"
    )
    print(f"  compile (first render - second): {t_first - t_render:7.2f} s")
    print(f"  render (trace + shade, fused):   {t_render:7.2f} s")
    print(f"  trace (full Transport):          {t_trace:7.2f} s  ({n_t} translucent pixels)")
    print(f"  shade (whole image):             {t_shade:7.3f} s")
    print(f"  camera rays per second:          {n_cam / t_render:,.0f}")
    print(f"  peak RSS:                        {peak_rss_mb():7.0f} MB")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="scenes/marble_cube.toml")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--large", type=int, default=0, help="also render at this width")
    a = ap.parse_args()
    bench(a.scene, a.size, a.spp)
    if a.large:
        bench_large(a.scene, a.large, a.spp)


def bench_large(scene_path: str, size: int, spp: int) -> None:
    """One render at a large size: wall time and peak memory (the tiling bound)."""
    scene = sssjax.load_scene(scene_path)
    h = round(size * scene.camera.height / scene.camera.width)
    scene = scene.with_settings(width=size, height=h, spp=spp)
    t0 = time.perf_counter()
    img = sssjax.render(scene, 0)
    dt = time.perf_counter() - t0
    print(
        f"{scene_path} {size}x{h} @ {spp} spp: render {dt:.1f} s (incl. compile), "
        f"peak RSS {peak_rss_mb():.0f} MB, mean {img.mean():.4f}"
    )


if __name__ == "__main__":
    main()
