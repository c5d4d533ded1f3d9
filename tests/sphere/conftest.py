import jax
import pytest


@pytest.fixture
def x64():
    """Double precision for comparisons against references and quadrature."""
    with jax.enable_x64(True):
        yield
