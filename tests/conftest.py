"""Test configuration: strict JAX numerics, as the anchor libraries (equinox/optimistix) test.

x64 is enabled so that comparisons with OpenCV / pytorch-kinematics / finite differences are
made at float64 precision; the library itself never changes jax.config at import.
"""

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

from jaxmocap._config import enable_compilation_cache  # noqa: E402

enable_compilation_cache()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)
