"""Run every benchmark script and collect the results into one summary table.

    python -m benchmarks                  # every bench_*.py, results in benchmarks/results
    python -m benchmarks --quick          # small sizes, results in a temporary folder
    python -m benchmarks --only fk pf     # a subset (names with or without the bench_ prefix)
    python -m benchmarks --summary-only   # rebuild SUMMARY.md from the JSON already there

Each script runs in its own process (``python -m benchmarks.run_all --child NAME``), so its peak
resident memory is measured alone (``os.wait4`` rusage, ``ru_maxrss``) and a crash or a time-out
in one script does not stop the others. The child points ``benchmarks._common.RESULTS`` at the
output folder, so a quick run never overwrites the committed full-size results.

``--quick`` sets ``JAXMOCAP_BENCH_QUICK=1`` in the children's environment; every script picks
its small sizes through ``benchmarks._common.sized`` and records ``"size": "quick"`` in its
JSON, which the summary's "size" column shows (a script that did not shrink says "full").

The summary (``SUMMARY.md``) has one table per tracker: every stage's jaxmocap time against the
fastest plain NumPy/OpenCV/SciPy/PyTorch baseline of the same kernel measured in the same run,
with the speed-up ``baseline / jaxmocap`` (median times) as the headline column, the warm
median and min, the cold first-call time (trace + compile + run), and the script's peak RSS.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import runpy
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from jaxmocap.errors import InputError

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
QUICK_ENV = "JAXMOCAP_BENCH_QUICK"
RUN_LOG = "run_all.json"

# Which scripts measure which tracker's stages (order = order in the summary).
GROUPS = {
    "Wang et al. 2011 colour-shirt tracker": (
        "bench_color", "bench_distance", "bench_render", "bench_posedb", "bench_ik", "bench_shirt",
    ),
    "Azad et al. 2007 stereo particle filter": (
        "bench_segment", "bench_pf", "bench_stereo_pf", "bench_pf_colors",
    ),
    "Shared building blocks": ("bench_camera", "bench_fk", "bench_synth"),
    "Scaling curves": ("bench_scaling",),
}  # fmt: skip
# A jaxmocap row whose baseline was measured under a different kernel label.
BASELINE_KERNEL = {
    ("bench_stereo_pf", "1000 likelihood evaluations (incl. FK)"):
        "1000 likelihood evaluations (edge cue, incl. FK)",
}  # fmt: skip
BASELINE = re.compile(r"numpy|opencv|cv2|scipy|pytorch", re.IGNORECASE)
PAPERS = (
    "Paper anchors: Wang et al. 120 ms per frame (two 640x480 cameras, Java, 2.4 GHz Core 2 "
    "Quad); Azad et al. 66 ms per 320x240 stereo pair at N = 1000 (14 image + 23 FK/projection + "
    "29 likelihood, 3 GHz CPU)."
)


def discover() -> list[str]:
    """Names of the benchmark scripts (``bench_*.py`` beside this file), sorted."""
    return sorted(p.stem for p in HERE.glob("bench_*.py"))


def _select(only: list[str] | None) -> list[str]:
    names = discover()
    if not only:
        return names
    wanted = [n if n.startswith("bench_") else f"bench_{n}" for n in only]
    unknown = [n for n in wanted if n not in names]
    if unknown:
        raise InputError(f"--only: unknown benchmark(s) {unknown}; expected some of {names}")
    return wanted


def _child(name: str, out: Path, quick: bool) -> None:
    """Run one script as ``__main__`` with its results redirected to ``out``."""
    import benchmarks._common as common

    common.RESULTS = out
    sys.argv = [str(HERE / f"{name}.py")]
    runpy.run_module(f"benchmarks.{name}", run_name="__main__", alter_sys=True)


def run_one(name: str, out: Path, quick: bool, timeout_s: float) -> dict:
    """Run ``name`` in a child process; wall time, exit status and peak RSS (MiB) of the child."""
    log = Path(tempfile.gettempdir()) / "jaxmocap-bench-logs" / f"{name}.log"  # not committed
    log.parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(HERE.parent), env.get("PYTHONPATH")]))
    if quick:
        env[QUICK_ENV] = "1"
    cmd = [sys.executable, "-m", "benchmarks.run_all", "--child", name, "--out", str(out)]
    if quick:
        cmd.append("--quick")
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env,
                                cwd=HERE.parent)  # fmt: skip
        timed_out = False
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() - t0 > timeout_s:
                proc.kill()
                pid, status, usage = os.wait4(proc.pid, 0)
                timed_out = True
                break
            time.sleep(0.2)
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped by wait4 above
    rc = proc.returncode
    return {
        "name": name,
        "status": "timeout" if timed_out else ("ok" if rc == 0 else "failed"),
        "returncode": rc,
        "wall_s": round(time.perf_counter() - t0, 2),
        "peak_rss_mib": round(usage.ru_maxrss / 1024, 1),  # Linux: ru_maxrss in KiB
        "quick": quick,
        "honours_quick": _size(out, name) == "quick",
        "log": str(log),
    }


def _size(out: Path, name: str) -> str | None:
    """The ``size`` a script's JSON in ``out`` records (None: no JSON)."""
    path = out / f"{name}.json"
    return json.loads(path.read_text()).get("size", "full") if path.exists() else None


# ----------------------------------------------------------------------------- summary


def _load(out: Path) -> tuple[dict[str, dict], dict[str, dict]]:
    results = {}
    for p in sorted(out.glob("bench_*.json")):
        results[p.stem] = json.loads(p.read_text())
    runs = {}
    if (out / RUN_LOG).exists():
        runs = {r["name"]: r for r in json.loads((out / RUN_LOG).read_text())["runs"]}
    return results, runs


def _is_ours(row: dict) -> bool:
    return row["implementation"].lower().startswith("jaxmocap")


def _is_baseline(row: dict) -> bool:
    return not _is_ours(row) and bool(BASELINE.search(row["implementation"]))


def _fmt(x: float | None, digits: int = 2) -> str:
    if x is None:
        return "—"
    return f"{x:.{digits}f}" if x < 100 else f"{x:.0f}"


def stage_rows(name: str, payload: dict, run: dict | None) -> list[str]:
    """Markdown rows: each jaxmocap row of ``payload`` against its best baseline."""
    rows = payload["rows"]
    rss = _fmt(run["peak_rss_mib"], 0) if run else "—"
    lines = []
    for r in rows:
        if not _is_ours(r):
            continue
        kernel = BASELINE_KERNEL.get((name, r["kernel"]), r["kernel"])
        bases = [b for b in rows if b["kernel"] == kernel and _is_baseline(b)]
        best = min(bases, key=lambda b: b["median_ms"]) if bases else None
        if best is None:
            ratio, base = "no baseline in this run", "—"
        else:
            speed = best["median_ms"] / r["median_ms"]
            ratio = f"**{speed:.2f}x**" + (" (slower)" if speed < 1 else "")
            base = f"{_fmt(best['median_ms'])} ({best['implementation']})"
        compile_s = None if r["compile_ms"] is None else r["compile_ms"] / 1e3
        lines.append(
            f"| {r['kernel']} | {ratio} | {_fmt(r['median_ms'])} ({_fmt(r['min_ms'])}) | {base} "
            f"| {_fmt(compile_s, 1)} | {r['implementation']} | `{name}` | {rss} |"
        )
    return lines


def write_summary(out: Path) -> Path:
    """Write ``out/SUMMARY.md`` from the ``bench_*.json`` (and ``run_all.json``) in ``out``."""
    results, runs = _load(out)
    lines = [
        "# Benchmark summary",
        "",
        "Generated by `python -m benchmarks` (`benchmarks/run_all.py`) from the JSON files beside "
        "this one; each script's own table has every row and its notes.",
        "",
        "- **speed-up** = median time of the fastest plain NumPy/OpenCV/SciPy/PyTorch baseline of "
        "the same kernel, measured in the same run, divided by jaxmocap's median time (> 1: "
        "jaxmocap is faster).",
        "- **warm** = median (min) ms over repeated calls after warm-up; **cold** = first call "
        "(trace + compile + run), seconds. Peak RSS: the whole script's process (jaxmocap and "
        "its baselines together), from `os.wait4` rusage.",
        "- All numbers from a 2-core machine shared with other engineers' jobs: medians are "
        "noisy, `min` is the better estimate of the uncontended cost.",
        f"- {PAPERS}",
        "",
    ]
    header = ["| stage | speed-up | warm ms median (min) | baseline ms median (impl.) "
              "| cold s | jaxmocap impl. | script | peak RSS MiB |",
              "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    listed = set()
    for title, names in GROUPS.items():
        present = [n for n in names if n in results]
        if not present:
            continue
        lines += [f"## {title}", "", *header]
        for n in present:
            lines += stage_rows(n, results[n], runs.get(n))
            listed.add(n)
        lines.append("")
    others = [n for n in results if n not in listed]
    if others:
        lines += ["## Other benchmarks", "", *header]
        for n in others:
            lines += stage_rows(n, results[n], runs.get(n))
        lines.append("")
    if "bench_scaling" in results:
        lines += ["Scaling plots: " + ", ".join(
            f"[{p}]({p})" for p in results["bench_scaling"].get("plots", [])), ""]  # fmt: skip
    lines += ["## Runs", "", "| script | measured | status | wall s | peak RSS MiB | size |",
              "|---|---|---|---|---|---|"]  # fmt: skip
    for n in sorted(set(results) | set(runs)):
        run = runs.get(n)
        date = results[n]["machine"]["date"] if n in results else "—"
        size = results[n].get("size", "full") if n in results else "—"
        if run is None:
            lines.append(f"| `{n}` | {date} | not run by run_all | — | — | {size} |")
            continue
        lines.append(f"| `{n}` | {date} | {run['status']} | {run['wall_s']:.0f} "
                     f"| {run['peak_rss_mib']:.0f} | {size} |")  # fmt: skip
    path = out / "SUMMARY.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--quick", action="store_true", help="small sizes (scripts that allow it)")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="run only these scripts")
    parser.add_argument("--out", type=Path, help="results folder (default: benchmarks/results, "
                        "or a temporary folder with --quick)")  # fmt: skip
    parser.add_argument("--summary-only", action="store_true", help="only rebuild SUMMARY.md")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per script")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        _child(args.child, args.out, args.quick)
        return 0
    out = args.out
    if out is None:
        out = Path(tempfile.gettempdir()) / "jaxmocap-bench-quick" if args.quick else RESULTS
    out.mkdir(parents=True, exist_ok=True)
    if not args.summary_only:
        names = _select(args.only)
        runs = []
        if (out / RUN_LOG).exists():  # keep earlier runs of scripts not run now
            runs = [r for r in json.loads((out / RUN_LOG).read_text())["runs"]
                    if r["name"] not in names]  # fmt: skip
        for name in names:
            print(f"[benchmarks] {name} ...", flush=True)
            r = run_one(name, out, args.quick, args.timeout)
            print(f"[benchmarks] {name}: {r['status']} in {r['wall_s']:.0f} s, "
                  f"peak RSS {r['peak_rss_mib']:.0f} MiB (log {r['log']})", flush=True)  # fmt: skip
            runs.append(r)
        runs.sort(key=lambda r: r["name"])
        (out / RUN_LOG).write_text(json.dumps({"runs": runs}, indent=1) + "\n")
    path = write_summary(out)
    print(f"[benchmarks] summary: {path}")
    failed = [] if args.summary_only else [r["name"] for r in runs if r["status"] != "ok"]
    if failed:
        print(f"[benchmarks] failed: {failed}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
