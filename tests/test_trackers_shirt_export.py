"""The shirt step shipped ahead of time for the demo's set-up (jaxmocap.trackers.shirt.export).

The shipped program must be current (a stale one is never used, but then the demo's first frame
traces again) and must be exactly the step that tracing produces: the oracle is the traced
``shirt.step`` on the same inputs, compared bit for bit. The demo runs in float32 and the test
session in float64, so that comparison runs in a float32 subprocess.
"""

import dataclasses
import json
import os
import subprocess
import sys
import textwrap

import jax.numpy as jnp
import numpy as np
import pytest
from test_trackers_shirt import setup  # noqa: F401  (the shirt tests' two-camera scene, a fixture)

from jaxmocap.trackers.shirt import export as shirt_export

_CHECK = textwrap.dedent(
    """
    import json, jax, numpy as np
    from jaxmocap._config import enable_compilation_cache
    from jaxmocap.trackers import shirt
    from jaxmocap.trackers.shirt import export as shirt_export
    enable_compilation_cache()
    params, state, frames = shirt_export._demo_inputs()
    program, why = shirt_export.load(params, state, frames[0])
    res = {"why": why}
    if program is not None:
        step = shirt.compile_step(params)  # takes the shipped program
        a = step(state, frames[0])
        a = a + step(a[0], frames[1])
        b = shirt.step(params, state, frames[0])  # traced
        b = b + shirt.step(params, b[0], frames[1])
        la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
        res["n"] = len(la)
        res["types"] = [type(x).__name__ for x in a]
        res["equal"] = len(la) == len(lb) and all(
            np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(la, lb))
        res["finite_q"] = bool(np.all(np.isfinite(np.asarray(a[3].q))))
    print("RESULT " + json.dumps(res))
    """
)


def test_shipped_program_is_current_and_equals_the_traced_step():
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    proc = subprocess.run([sys.executable, "-c", _CHECK], capture_output=True, text=True,
                          env=env, timeout=900)  # fmt: skip
    line = [s for s in proc.stdout.splitlines() if s.startswith("RESULT ")]
    assert proc.returncode == 0 and line, proc.stderr[-3000:]
    res = json.loads(line[0][len("RESULT "):])
    if "it was exported with" in res["why"]:  # another jax / equinox / ... than it was made for
        pytest.skip(f"{res['why']}; regenerate it with `{shirt_export.REGENERATE}`")
    assert res["why"] == "the shipped program", (
        f"{res['why']}: regenerate it with `{shirt_export.REGENERATE}` and commit "
        f"{shirt_export.EXPORT_DIR.name}/"
    )
    assert res["types"] == ["ShirtState", "ShirtOutput", "ShirtState", "ShirtOutput"]
    assert res["equal"] and res["finite_q"] and res["n"] > 20


def test_manifest_names_existing_modules_and_pinned_libraries():
    m = json.loads(shirt_export.MANIFEST.read_text())
    assert "trackers/shirt/frame.py" in m["modules"] and "trackers/shirt/export.py" in m["modules"]
    assert all((shirt_export.PACKAGE_ROOT / rel).is_file() for rel in m["modules"])
    assert set(m["libraries"]) == {"jax", "jaxlib", "equinox", "optimistix", "lineax"}
    stale = shirt_export._stale_reason(m)
    assert stale is None or "it was exported with" in stale, stale  # the sources are current


@pytest.fixture(scope="module")
def small(setup):  # noqa: F811  (pytest passes the imported fixture)
    from jaxmocap.trackers import shirt

    params = setup["params"]
    return params, shirt.init(params, setup["W0"], jnp.zeros(setup["model"].n_dof))


@pytest.mark.parametrize("change", ["masks", "size", "float64"])
def test_other_setups_are_refused_with_a_reason(small, change):
    """Inputs of another structure never run the shipped program; each gets a one-line
    reason (no tracing or compiling happens in this check)."""
    params, state = small
    frames = np.zeros((params.n_cams, 48, 64, 3), np.uint8)
    masks = None
    if change == "masks":
        masks = np.ones(frames.shape[:3], bool)
    elif change == "size":
        frames = np.zeros((params.n_cams, 40, 64, 3), np.uint8)
    program, why = shirt_export.load(params, state, jnp.asarray(frames), masks)
    assert program is None
    assert "\n" not in why
    assert ("masks" in why) if change == "masks" else ("shipped program is for" in why)


def test_fingerprint_sees_shapes_static_values_and_dtypes(small):
    params, state = small
    base = shirt_export.fingerprint_inputs(params, state, (2, 48, 64, 3), np.uint8)
    assert base == shirt_export.fingerprint_inputs(params, state, (2, 48, 64, 3), np.uint8)
    assert base != shirt_export.fingerprint_inputs(params, state, (2, 48, 66, 3), np.uint8)
    other = dataclasses.replace(params, search=dataclasses.replace(
        params.search, work_size=params.search.work_size + 8))
    assert base != shirt_export.fingerprint_inputs(other, state, (2, 48, 64, 3), np.uint8)
    st32 = dataclasses.replace(state, q=state.q.astype(jnp.float32))
    assert base != shirt_export.fingerprint_inputs(params, st32, (2, 48, 64, 3), np.uint8)

