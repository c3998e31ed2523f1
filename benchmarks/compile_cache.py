"""Compile once: the same `sssjax render` twice, with a fresh persistent compilation cache.

    python benchmarks/compile_cache.py [--scene scenes/marble_cube.toml] [--size 64] [--spp 2]
                                       [--runs 2] [--no-cache]

Each run is a fresh process (`sssjax render ... --force`) with `SSSJAX_CACHE_DIR` pointing
at a new temporary folder, so the first run fills the cache and later runs read it. For each
run it prints the wall time of the process and JAX's own figures (`jax.monitoring`): time
tracing Python to jaxprs, lowering jaxprs to MLIR, and in the backend (XLA compilation, or
loading the executable from the cache on a hit), with the number of programs and of cache hits.
Tracing and lowering are not cached by XLA's cache: every process pays them again. Trace
times nest (a jit inside a traced function counts again), so they are upper bounds.

Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "backend",
    "/jax/compilation_cache/cache_retrieval_time_sec": "cache_read",
}


def child(argv: list[str]) -> None:
    """Run `sssjax ARGV` in this process, recording JAX's compile events."""
    t0 = time.perf_counter()
    import jax

    from sssjax.cli import main

    sums = dict.fromkeys([*EVENTS.values(), "hits", "programs"], 0.0)

    def duration(event, secs, **kw):
        if event in EVENTS:
            sums[EVENTS[event]] += secs
        if event == "/jax/core/compile/backend_compile_duration":
            sums["programs"] += 1

    def count(event, **kw):
        if event == "/jax/compilation_cache/cache_hits":
            sums["hits"] += 1

    jax.monitoring.register_event_duration_secs_listener(duration)
    jax.monitoring.register_event_listener(count)
    t_import = time.perf_counter() - t0
    rc = main(argv)
    sums["import"] = t_import
    sums["wall_in_process"] = time.perf_counter() - t0
    sums["rc"] = rc
    print("FIGURES " + json.dumps(sums), file=sys.stderr)


def run_once(args, cache: Path, out: Path) -> dict:
    cmd = [
        sys.executable,
        __file__,
        "--child",
        "render",
        args.scene,
        "--width",
        str(args.size),
        "--height",
        str(args.size),
        "--spp",
        str(args.spp),
        "-o",
        str(out),
    ] + (["--no-cache"] if args.no_cache else [])
    env = dict(os.environ, SSSJAX_CACHE_DIR=str(cache))
    out.unlink(missing_ok=True)
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    line = [ln for ln in p.stderr.splitlines() if ln.startswith("FIGURES ")]
    if p.returncode != 0 or not line:
        raise SystemExit(f"run failed ({p.returncode}):\n{p.stderr[-3000:]}")
    figs = json.loads(line[-1][len("FIGURES ") :])
    figs["wall"] = wall
    figs["stderr_lines"] = len(p.stderr.splitlines()) - 1
    return figs


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(sys.argv[2:])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="scenes/marble_cube.toml")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spp", type=int, default=2)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--no-cache", action="store_true", help="pass --no-cache to every run")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cache, out = Path(tmp) / "cache", Path(tmp) / "x.png"
        print(
            f"sssjax render {args.scene} --width {args.size} --height {args.size} "
            f"--spp {args.spp}, fresh cache {cache}"
        )
        print(
            f"{'run':<4} {'wall':>6} {'import':>6} {'trace':>6} {'lower':>6} {'backend':>7} "
            f"{'(read)':>6} {'programs':>8} {'hits':>5} {'stderr':>6}   [s]"
        )
        for i in range(args.runs):
            f = run_once(args, cache, out)
            print(
                f"{i + 1:<4} {f['wall']:6.1f} {f['import']:6.1f} {f['trace']:6.1f} "
                f"{f['lower']:6.1f} {f['backend']:7.1f} {f['cache_read']:6.2f} "
                f"{int(f['programs']):8d} {int(f['hits']):5d} {f['stderr_lines']:6d}"
            )
        size = sum(p.stat().st_size for p in cache.rglob("*") if p.is_file())
        n = sum(1 for p in cache.rglob("*-cache"))
        print(f"cache: {n} executables, {size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
