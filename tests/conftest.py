"""Test configuration: strict JAX numerics, as the anchor libraries (equinox/optimistix) test.

x64 is enabled so that comparisons with OpenCV / pytorch-kinematics / finite differences are
made at float64 precision; the library itself never changes jax.config at import.

Memory: JAX keeps every compiled executable (and the arrays its traces closed over) for the
life of the process, so one pytest run over all modules grew to the sum of their programs
(6.7 GB peak RSS); :func:`_release_module_memory` drops them after each module (the on-disk
compilation cache keeps recompiles cheap), so the peak is that of the largest module.
"""

import ctypes
import gc
import os
import sys

import jax
import numpy as np
import pytest

from jaxmocap._config import enable_side_device  # noqa: E402

enable_side_device()  # as the CLI: a second CPU device for the live loops' host-side calls
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

from jaxmocap._config import enable_compilation_cache  # noqa: E402

enable_compilation_cache()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def _release():
    """Clear JAX's in-memory caches of compiled programs and traces, collect, and hand freed
    heap pages back to the OS (glibc keeps them otherwise)."""
    jax.clear_caches()
    gc.collect()
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except (OSError, AttributeError):
            pass


def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


# A module's tests share its compiled programs (no recompile between them) until the process
# holds this much; then they are released after the test (the stereo filter's module alone
# reached 3.2 GiB keeping every variant; the suite's goal is <= 3 GB per process).
RELEASE_ABOVE_BYTES = int(2.0 * 2**30)


@pytest.fixture(autouse=True, scope="module")
def _release_module_memory():
    """After each test module: release its compiled programs (:func:`_release`)."""
    yield
    _release()


@pytest.fixture(autouse=True)
def _release_when_large():
    """After a test that leaves the process above :data:`RELEASE_ABOVE_BYTES`: release."""
    yield
    if _rss_bytes() > RELEASE_ABOVE_BYTES:
        _release()
