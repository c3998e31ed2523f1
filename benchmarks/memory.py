"""Memory benchmark: peak RSS of `sssjax render` at growing image sizes.

    python benchmarks/memory.py [--scene scenes/marble_cube.toml] [--spp 1]
                                [--sizes 256 1024] [--large]   # --large adds 4096

Each size renders in its own process (`sssjax render ... -o out.png -o out.exr`), so each
peak is that render's alone: JAX and the compiled programs (about 1.2 GB, whatever the
size), the image (12 bytes a pixel) and what does not grow with it (the tiles in flight,
the writers' strip of rows). Prints the peak RSS next to the one-line estimate that
`sssjax render` checks before it starts; asserts nothing (the figures are in the README).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def peak_rss(cmd: list[str], env: dict) -> tuple[float, float, int]:
    """Run `cmd`; its `(peak RSS in bytes, wall seconds, exit status)`."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode() if proc.stderr else ""
    rc = os.waitstatus_to_exitcode(status)
    if rc != 0:
        print(err.strip().splitlines()[-1] if err.strip() else f"exit {rc}", file=sys.stderr)
    return usage.ru_maxrss * 1024.0, wall, rc  # ru_maxrss is in KiB on Linux


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(ROOT / "scenes" / "marble_cube.toml"))
    ap.add_argument("--spp", type=int, default=1)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 1024])
    ap.add_argument("--large", action="store_true", help="also render 4096 x 4096 (slow)")
    args = ap.parse_args()
    sizes = args.sizes + ([4096] if args.large else [])

    sys.path.insert(0, str(ROOT))
    from sssjax._budget import estimate_memory, format_bytes
    from sssjax.scene import load_scene

    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    scene = load_scene(args.scene)
    print(f"{args.scene} at {args.spp} spp, png + exr outputs; peak RSS of each render's process")
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            sc = scene.with_settings(width=n, height=n, spp=args.spp)
            est = estimate_memory(sc, png=True, devices=1)
            cmd = [sys.executable, "-m", "sssjax", "render", args.scene, "--force"]
            cmd += ["--width", str(n), "--height", str(n), "--spp", str(args.spp)]
            cmd += ["-o", f"{tmp}/x.png", "-o", f"{tmp}/x.exr"]
            rss, wall, rc = peak_rss(cmd, env)
            status = "" if rc == 0 else f"  (failed: exit {rc})"
            print(
                f"  {n:5d} x {n:<5d} peak RSS {format_bytes(rss):>9}  estimate "
                f"{format_bytes(est.total):>9} ({est.describe() or 'runtime'})  "
                f"wall {wall:6.1f} s{status}",
                flush=True,
            )


if __name__ == "__main__":
    main()
