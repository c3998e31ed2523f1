import jax
import pytest


@pytest.fixture
def x64():
    """Run a test in float64 (gradient and quadrature tests)."""
    with jax.enable_x64(True):
        yield
