"""jaxmocap._config.enable_side_device: a second CPU device for live loops' host-side calls,
only before JAX's backend starts, never over the user's own choice (fresh processes: the test
session's own JAX has started)."""

import os
import subprocess
import sys

import pytest

SCRIPT = """
import os, jax
from jaxmocap._config import enable_side_device, side_device
if os.environ.get("START_FIRST") == "1":
    jax.numpy.zeros(1)  # the backend starts before the request
ok = enable_side_device()
print(ok, len(jax.devices("cpu")), side_device() is not None)
"""


def _run(**env) -> str:
    full = {k: v for k, v in os.environ.items()
            if k not in ("JAXMOCAP_SIDE_DEVICE", "JAX_NUM_CPU_DEVICES", "XLA_FLAGS")}  # fmt: skip
    full.update(env)
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=full, capture_output=True,
                         text=True, check=True, timeout=120)  # fmt: skip
    return out.stdout.split("\n")[-2]


@pytest.mark.parametrize(
    ("env", "expected"),
    [
        ({}, "True 2 True"),
        ({"JAXMOCAP_SIDE_DEVICE": "0"}, "False 1 False"),
        ({"START_FIRST": "1"}, "False 1 False"),
        ({"JAX_NUM_CPU_DEVICES": "3"}, "True 3 True"),
    ],
)
def test_enable_side_device(env, expected):
    assert _run(**env) == expected
