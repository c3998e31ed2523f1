"""Compile once: JAX's persistent compilation cache, on by default.

A scene's renderer takes tens of seconds to compile on a small CPU and a fraction of that to
load from disk, so `import sssjax` points JAX's persistent compilation cache at a folder of
its own unless the user has configured JAX's cache already:

- the folder is `$SSSJAX_CACHE_DIR` if set, else `$XDG_CACHE_HOME/sssjax/jax`, else
  `~/.cache/sssjax/jax`; `SSSJAX_CACHE_DIR=off` (or `0`, `none`, empty) turns it off, as
  does `sssjax --no-cache` for one command and `disable_cache()` in Python;
- a cache set up by the user (`JAX_COMPILATION_CACHE_DIR` or
  `jax.config.update("jax_compilation_cache_dir", ...)`) is left alone, with its settings;
- the folder is bounded to `MAX_BYTES` (least recently used entries are evicted); a scene
  at one image size and sample count takes about 1 MB. Deleting it is always safe (the next
  run compiles again).

Loading a cached CPU executable makes XLA log an ERROR line per executable on CPUs whose
LLVM tuning flags (`+prefer-no-gather`, `+prefer-no-scatter`) are not host features
(openxla/xla#44565, jax-ml/jax#38445: spurious, the executable is the one compiled on this
machine). While sssjax's cache is on, XLA's C++ log is therefore kept to fatal messages,
like `TF_CPP_MIN_LOG_LEVEL=3`, unless the user set `TF_CPP_MIN_LOG_LEVEL` themselves.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

# `import jax` sets TF_CPP_MIN_LOG_LEVEL=1 when unset: read the user's choice before it does
_LOG_ENV = os.environ.get("TF_CPP_MIN_LOG_LEVEL")
_USER_LOG_LEVEL = _LOG_ENV if ("jax" not in sys.modules or _LOG_ENV != "1") else None

import jax  # noqa: E402

__all__ = ["MAX_BYTES", "cache_dir", "enable_cache", "disable_cache", "cache_enabled"]

ENV_DIR = "SSSJAX_CACHE_DIR"
_OFF = ("", "0", "off", "none", "false", "no")
MAX_BYTES = 1024**3  # bound on the folder (LRU eviction beyond it; needs `filelock`)
# Cache every program that took at least this long to compile: a render builds dozens of
# small programs (keys, padding, packing) that compile in 0.05-0.5 s each on 2 cores.
MIN_COMPILE_SECS = 0.0

_owned: list[Path] = []  # the folder sssjax set, while its cache is on


def cache_dir() -> Path | None:
    """The folder of sssjax's compilation cache, or `None` when `SSSJAX_CACHE_DIR` turns
    it off.

    **Returns:** `$SSSJAX_CACHE_DIR`, else `$XDG_CACHE_HOME/sssjax/jax`, else
    `~/.cache/sssjax/jax`.
    """
    env = os.environ.get(ENV_DIR)
    if env is not None:
        return None if env.strip().lower() in _OFF else Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "sssjax" / "jax"


def _quiet_xla_log() -> None:
    """Keep XLA's C++ log to fatal messages (unless the user chose a level)."""
    if _USER_LOG_LEVEL is not None:
        return
    try:  # jaxlib's runtime setter of absl's level (what `jax_logging_level` calls)
        from jax._src.lib import utils

        utils.absl_set_min_log_level(3)
    except (ImportError, AttributeError):  # older jaxlib: effective if jaxlib is not loaded
        os.environ["TF_CPP_MIN_LOG_LEVEL"] = "3"


def enable_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache in `path` (default: `cache_dir()`).

    Leaves a cache the user configured for JAX alone. A folder that cannot be created
    (read-only home) leaves the cache off rather than warning at every compile.

    **Returns:** the folder in use by sssjax, or `None` when the cache is off or the user's.
    """
    if _owned:
        disable_cache()
    if jax.config.jax_compilation_cache_dir:  # the user's own cache
        return None
    folder = Path(path).expanduser() if path is not None else cache_dir()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if not os.access(folder, os.W_OK):
            return None
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECS)
    try:  # JAX's size-bounded cache locks the folder with `filelock`
        import filelock  # noqa: F401

        jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    except ImportError:
        pass
    _owned.append(folder)
    _quiet_xla_log()
    return folder


def disable_cache() -> None:
    """Turn sssjax's compilation cache off (a cache the user configured stays on).

    Takes effect for programs compiled afterwards when nothing has been compiled since the
    cache was turned on, as in `sssjax --no-cache`."""
    if _owned:
        jax.config.update("jax_compilation_cache_dir", None)
        _owned.clear()


def cache_enabled() -> Path | None:
    """The folder of sssjax's cache while it is on, else `None`."""
    return _owned[-1] if _owned else None
