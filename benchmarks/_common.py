"""Shared timing and reporting helpers for the benchmark scripts.

Every benchmark times a jaxmocap implementation and a plain NumPy/OpenCV baseline *in the same
run*, and writes ``benchmarks/results/<name>.json`` and ``<name>.md``.
"""

from __future__ import annotations

import json
import os
import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import jax
import numpy as np

RESULTS = Path(__file__).parent / "results"
QUICK_ENV = "JAXMOCAP_BENCH_QUICK"
_SIZED = {"called": False}  # set by sized(): the script chose its sizes through the switch


def is_quick() -> bool:
    """Whether ``JAXMOCAP_BENCH_QUICK=1`` asks for the small sizes."""
    return os.environ.get(QUICK_ENV, "").strip() == "1"


def sized(*, full, quick):
    """``quick`` under ``JAXMOCAP_BENCH_QUICK=1``, else ``full`` (sizes, repetitions)."""
    _SIZED["called"] = True
    return quick if is_quick() else full


@dataclass
class Row:
    kernel: str
    implementation: str
    median_ms: float
    min_ms: float
    n: int
    compile_ms: float | None = None
    notes: str = ""
    extra: dict = field(default_factory=dict)


def _block(x):
    return jax.block_until_ready(x)


def time_call(fn: Callable[[], object], n: int = 50, warmup: int = 3) -> tuple[float, float]:
    """Median and min wall time (ms) of ``fn()`` after ``warmup`` calls; JAX results blocked."""
    for _ in range(warmup):
        _block(fn())
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        _block(fn())
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times)), float(np.min(times))


def time_compile(fn: Callable[[], object]) -> float:
    """Wall time (ms) of the first call (trace + compile + run)."""
    t0 = time.perf_counter()
    _block(fn())
    return (time.perf_counter() - t0) * 1e3


def machine() -> dict:
    return {
        "python": platform.python_version(),
        "jax": jax.__version__,
        "cpu_count": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def write_results(name: str, rows: list[Row], summary: list[str] | None = None) -> Path:
    """Write ``results/<name>.json`` and a markdown table ``results/<name>.md``."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    size = "quick" if is_quick() and _SIZED["called"] else "full"
    payload = {"benchmark": name, "machine": machine(), "size": size,
               "rows": [asdict(r) for r in rows], "summary": summary or []}
    (RESULTS / f"{name}.json").write_text(json.dumps(payload, indent=2) + "\n")
    lines = [f"# {name}", "", f"Machine: {payload['machine']}", "", f"Size: {size}", ""]
    lines += [f"- {s}" for s in summary or []]
    lines += ["", "| kernel | implementation | median ms | min ms | n | compile ms | notes |",
              "|---|---|---|---|---|---|---|"]
    for r in rows:
        comp = "" if r.compile_ms is None else f"{r.compile_ms:.0f}"
        lines.append(f"| {r.kernel} | {r.implementation} | {r.median_ms:.3f} | {r.min_ms:.3f} "
                     f"| {r.n} | {comp} | {r.notes} |")
    path = RESULTS / f"{name}.md"
    path.write_text("\n".join(lines) + "\n")
    return path
