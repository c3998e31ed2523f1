"""Compile once: the persistent compilation cache's folder, and a second CLI run that loads
every program from it instead of compiling (without XLA's spurious log line)."""

import json
import os
import subprocess
import sys
from pathlib import Path

from sssjax import _cache

SCENE = """
[camera]
origin = [0.0, 20.0, 40.0]
target = [0.0, 0.0, 0.0]
width = 8
height = 8

[render]
spp = 1
light_samples = 1

[[lights]]
type = "point"
position = [0.0, 30.0, 10.0]
intensity = 500.0

[materials.white]
type = "diffuse"
albedo = 0.5

[[shapes]]
type = "sphere"
material = "white"
radius = 5.0
"""

# runs `sssjax ARGS` in a fresh process, counting JAX's compiles and persistent-cache hits
CHILD = """
import json, sys
import jax
from sssjax.cli import main  # (a dependency compiles a program at import: not ours)
n = {"programs": 0, "hits": 0}
def dur(event, secs, **kw):
    if event == "/jax/core/compile/backend_compile_duration":
        n["programs"] += 1
def ev(event, **kw):
    if event == "/jax/compilation_cache/cache_hits":
        n["hits"] += 1
jax.monitoring.register_event_duration_secs_listener(dur)
jax.monitoring.register_event_listener(ev)
rc = main(sys.argv[1:])
print("COUNTS " + json.dumps(n), file=sys.stderr)
sys.exit(rc)
"""


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("SSSJAX_CACHE_DIR", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert _cache.cache_dir() == tmp_path / "home" / ".cache" / "sssjax" / "jax"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert _cache.cache_dir() == tmp_path / "xdg" / "sssjax" / "jax"
    monkeypatch.setenv("SSSJAX_CACHE_DIR", str(tmp_path / "mine"))
    assert _cache.cache_dir() == tmp_path / "mine"
    for off in ("off", "0", "", "None"):
        monkeypatch.setenv("SSSJAX_CACHE_DIR", off)
        assert _cache.cache_dir() is None


def test_a_cache_the_user_configured_is_left_alone():
    import jax

    mine = jax.config.jax_compilation_cache_dir  # the test suite's own (conftest.py)
    assert mine
    assert _cache.enable_cache() is None and _cache.cache_enabled() is None
    assert jax.config.jax_compilation_cache_dir == mine


def _run(tmp_path, cache, *extra):
    env = {k: v for k, v in os.environ.items() if k != "TF_CPP_MIN_LOG_LEVEL"}
    env["SSSJAX_CACHE_DIR"] = str(cache)
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE)
    out = tmp_path / "s.png"
    out.unlink(missing_ok=True)
    p = subprocess.run(
        [sys.executable, "-c", CHILD, "render", str(scene), "-o", str(out), *extra],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=600,
    )
    assert p.returncode == 0, p.stderr
    assert out.exists()
    counts = json.loads(p.stderr.rsplit("COUNTS ", 1)[1])
    return counts, p.stderr


def _entries(cache: Path) -> set[str]:
    return {p.name for p in cache.glob("*-cache")} if cache.exists() else set()


def test_second_render_loads_every_program_from_the_cache(tmp_path):
    cache = tmp_path / "cache"
    first, err1 = _run(tmp_path, cache)
    assert first["programs"] > 5 and first["hits"] == 0
    stored = _entries(cache)
    assert len(stored) >= first["programs"] - 2  # (a trivial program may not be worth it)
    second, err2 = _run(tmp_path, cache)
    # every program the second run needs comes from the cache: nothing compiles again
    assert second["hits"] == second["programs"] == first["programs"]
    assert _entries(cache) == stored
    # XLA's "machine type doesn't match" line on every cache load is kept quiet
    assert "cpu_aot_loader" not in err2 and "Machine type" not in err2
    # --no-cache compiles everything again and neither reads nor writes the folder
    third, _ = _run(tmp_path, cache, "--no-cache")
    assert third["hits"] == 0 and third["programs"] == first["programs"]
    assert _entries(cache) == stored
