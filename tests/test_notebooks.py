"""Every notebook in ``notebooks/`` runs top to bottom at ``JAXMOCAP_NOTEBOOK_SCALE=small``.

Each notebook is executed by nbclient in a child process (so the kernel's ZeroMQ sockets never
leak into this test session, where warnings are errors) with a kernel on this test's own
interpreter (a kernel spec written to a temporary folder: no ``ipykernel install`` needed).
A cell that raises fails the test with the cell's traceback; the notebooks assert their own
checks (NumPy oracles, ground truth) in their cells.
"""

import os
import subprocess
import sys
from pathlib import Path

import nbformat
import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
CELL_TIMEOUT_S = 300

RUNNER = r"""
import json, sys
from pathlib import Path
import nbformat
from jupyter_client.kernelspec import KernelSpecManager
from jupyter_client.manager import KernelManager
from nbclient import NotebookClient

src, dst, specs, timeout = sys.argv[1], sys.argv[2], Path(sys.argv[3]), int(sys.argv[4])
spec = specs / "jaxmocap-test"
spec.mkdir(parents=True, exist_ok=True)
argv = [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"]
(spec / "kernel.json").write_text(json.dumps({"argv": argv, "display_name": "jaxmocap-test",
                                              "language": "python"}))
km = KernelManager(kernel_name="jaxmocap-test",
                   kernel_spec_manager=KernelSpecManager(kernel_dirs=[str(specs)]))
nb = nbformat.read(src, as_version=4)
try:
    NotebookClient(nb, km=km, timeout=timeout,
                   resources={"metadata": {"path": str(Path(src).parent)}}).execute()
finally:
    nbformat.write(nb, dst)
"""


def test_notebooks_found():
    assert NOTEBOOKS, "no notebooks under notebooks/"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_small(path, tmp_path):
    env = dict(os.environ, JAXMOCAP_NOTEBOOK_SCALE="small")
    env.pop("MPLBACKEND", None)  # the kernel's inline backend draws the figures
    out = tmp_path / path.name
    proc = subprocess.run(
        [sys.executable, "-c", RUNNER, str(path), str(out), str(tmp_path / "kernels"),
         str(CELL_TIMEOUT_S)],
        env=env, capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, f"{path.name} failed:\n{proc.stdout[-3000:]}{proc.stderr[-6000:]}"
    nb = nbformat.read(out, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(c.execution_count for c in code)
    assert not [o for c in code for o in c.outputs if o.output_type == "error"]
    images = [o for c in code for o in c.outputs if "image/png" in o.get("data", {})]
    assert images, f"{path.name}: no figure was drawn"


def test_benchmark_runner_quick(tmp_path):
    """``python -m benchmarks --quick --only distance`` runs one cheap script at its quick size
    into a chosen folder and writes its JSON/markdown and the summary (the committed results
    are not touched)."""
    import json

    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ)
    env.pop("JAXMOCAP_BENCH_QUICK", None)  # the runner must set it for the child
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks", "--quick", "--only", "distance", "--out",
         str(tmp_path)],
        cwd=root, env=env, capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    payload = json.loads((tmp_path / "bench_distance.json").read_text())
    assert payload["size"] == "quick"
    sides = {r["kernel"] for r in payload["rows"]}
    assert sides and not any("160" in k for k in sides), sides  # the quick size only
    run = json.loads((tmp_path / "run_all.json").read_text())["runs"]
    assert [(r["name"], r["status"], r["honours_quick"]) for r in run] == [
        ("bench_distance", "ok", True)
    ]
    summary = (tmp_path / "SUMMARY.md").read_text()
    assert "`bench_distance`" in summary and "| quick |" in summary
