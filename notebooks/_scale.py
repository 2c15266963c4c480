"""Size switch shared by the notebooks: ``JAXMOCAP_NOTEBOOK_SCALE=small|full`` (default full).

``small`` is what the test suite runs (``tests/test_notebooks.py``: each notebook well under a
minute on a 2-core machine); ``full`` is what the committed outputs show. A notebook picks its
sizes with :func:`pick`, e.g. ``n_frames = pick(small=5, full=40)``.

Importing this module also puts the repository root on ``sys.path`` so the notebooks can use
the experiment functions in ``benchmarks/`` without installing them.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from jaxmocap.errors import InputError

ENV = "JAXMOCAP_NOTEBOOK_SCALE"
SCALES = ("small", "full")
ROOT = Path(__file__).resolve().parents[1]


def scale() -> str:
    """The requested scale, ``"small"`` or ``"full"``."""
    value = os.environ.get(ENV, "full").strip().lower()
    if value not in SCALES:
        raise InputError(f"environment variable {ENV}: expected one of {SCALES}, got {value!r}")
    return value


def pick(*, small, full):
    """``small`` or ``full`` according to :func:`scale`."""
    return small if scale() == "small" else full


for _p in (ROOT, ROOT / "benchmarks" / "experiments"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))
