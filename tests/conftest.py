import os
from pathlib import Path

# Loading a cached CPU executable logs a spurious "machine type doesn't match" error per
# entry (same machine): keep XLA's C++ log to fatal messages in the tests.
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
# The tests' scenes are small: compiling dominates running, and LLVM's optimisation level 0
# compiles about 20% faster (measured on the 2-core machine) at no cost the tests can feel.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
    ).strip()

import jax  # noqa: E402
import pytest  # noqa: E402

# Many tests build the same small scenes in both xdist workers: share the compiled
# executables through JAX's persistent cache (fresh per checkout; it only saves time).
_CACHE = Path(__file__).resolve().parent.parent / ".pytest_cache" / "jax"
jax.config.update("jax_compilation_cache_dir", str(_CACHE))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


@pytest.fixture
def x64():
    """Run a test in float64 (gradient and quadrature tests)."""
    with jax.enable_x64(True):
        yield
