"""The experiment's summary: ``summary.json`` (every cell), ``summary.md`` (a table per
sequence and configuration, seeds averaged, and an overall row per configuration; for the
stereo filter the anchors its cells started from) and
``summary.png`` (mean error per sequence and configuration, bars; seed spread as error bars)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

COLUMNS = (  # (header, metric path, format)
    ("MPJPE cm (valid frames)", ("mpjpe_cm",), "{:.2f}"),
    ("mean cm (all frames)", ("mean_error_all_frames_cm",), "{:.2f}"),
    ("depth cm", ("depth_error_cm",), "{:.2f}"),  # the same frames, along the line of sight
    ("lateral cm", ("lateral_error_cm",), "{:.2f}"),  # ... and across it
    ("frames < good", ("frames_below_good_cm",), "{:.0%}"),
    ("valid", ("valid_share",), "{:.0%}"),
    ("bad flagged invalid", ("validity", "bad_flagged_invalid"), "{:.0%}"),
    ("good flagged valid", ("validity", "good_flagged_valid"), "{:.0%}"),
    ("recovered <= 5 frames", ("world", "recovered_in_time"), "{:.0%}"),
    ("cm, 10 frames before a lamp change", ("world", "lamp_cm_before"), "{:.2f}"),
    ("cm, 10 frames after it", ("world", "lamp_cm_after"), "{:.2f}"),
    ("cm, head + hands in view", ("world", "mean_cm_skin_in_view"), "{:.2f}"),
    ("frames with a blob off the body", ("world", "frames_blob_off_body"), "{:.1f}"),
    ("ms/frame", ("ms_per_frame",), "{:.1f}"),
)


def _get(m: dict, path) -> float | int | None:
    for k in path:
        if m is None:
            return None
        m = m.get(k)
    return m


def _mean(vals):
    vals = [v for v in vals if v is not None]
    return None if not vals else float(np.mean(vals))


def aggregate(cells: list[dict]) -> dict:
    """Seed- (and sequence-) averaged metrics of finished cells; errors listed."""
    ok = [c for c in cells if "metrics" in c]
    for c in ok:
        m = c["metrics"]
        m["valid_share"] = m["frames_valid"] / m["frames"] if m["frames"] else None
    agg = {h: _mean([_get(c["metrics"], p) for c in ok]) for h, p, _ in COLUMNS}
    agg["cells"] = len(cells)
    agg["failed"] = len(cells) - len(ok)
    agg["errors"] = [c["error"] for c in cells if "error" in c]
    vals = [c["metrics"]["mean_error_all_frames_cm"] for c in ok
            if c["metrics"]["mean_error_all_frames_cm"] is not None]
    agg["seed_std_cm"] = float(np.std(vals)) if len(vals) > 1 else None
    # the spread over seeds of the mean error (all frames): per seed, the mean over the
    # sequences it ran on (one sequence: its own value), then min and max over the seeds
    by_seed: dict = {}
    for c in ok:
        v = c["metrics"]["mean_error_all_frames_cm"]
        if v is not None:
            by_seed.setdefault(c.get("seed"), []).append(v)
    means = [float(np.mean(v)) for v in by_seed.values()]
    agg["seed_range_cm"] = (min(means), max(means)) if len(means) > 1 else None
    agg["seeds"] = len(means)
    return agg


def _fmt(v, f: str) -> str:
    return "-" if v is None else f.format(v)


def _spread(v: dict) -> str:
    """'min-max (n seeds)' of the seeds' mean errors, '-' with fewer than two seeds."""
    r = v.get("seed_range_cm")
    return "-" if r is None else f"{r[0]:.2f}-{r[1]:.2f} ({v['seeds']})"


def write_summary(out: Path, exp, seqs, specs: list[dict], results: dict, stats: dict) -> dict:
    from jaxmocap.io.atomic import AtomicFiles

    configs = [c.name for c in exp.configs]
    names = [s.name for s in seqs]
    cells = [results[s["cell"]] for s in specs]
    table = {}
    for c in configs:
        for s in names:
            table[(s, c)] = aggregate([x for x in cells if x["sequence"] == s
                                       and x["config"] == c])
        table[("all", c)] = aggregate([x for x in cells if x["config"] == c])
    doc = {
        "config_file": exp.path, "good_cm": exp.good_cm, "bad_cm": exp.bad_cm,
        "sequences": names, "configs": [c.to_dict() for c in exp.configs], "run": stats,
        "table": [{"sequence": s, "config": c, **v} for (s, c), v in table.items()],
        "cells": cells,
    }
    lines = [f"# Experiment: {Path(exp.path).name} on {len(names)} sequence(s)", "",
             f"good < {exp.good_cm:g} cm, bad > {exp.bad_cm:g} cm; seeds averaged (the seeds' "
             "spread: min-max over the seeds of the mean cm, all frames; on the **all** rows of "
             "each seed's mean over the sequences). Cells: "
             f"{stats['cells']} ({stats['computed']} computed, {stats['reused']} reused, "
             f"{stats['failed']} failed) in {stats['wall_s']:.1f} s.", "",
             "| sequence | config | " + " | ".join(h for h, _, _ in COLUMNS[:2])
             + " | seeds' spread cm | " + " | ".join(h for h, _, _ in COLUMNS[2:]) + " |",
             "|---" * (len(COLUMNS) + 3) + "|"]
    for s in [*names, "all"]:
        for c in configs:
            v = table[(s, c)]
            row = [f"**{s}**" if s == "all" else s, c]
            row += [_fmt(v[h], f) for h, _, f in COLUMNS[:2]] + [_spread(v)]
            row += [_fmt(v[h], f) for h, _, f in COLUMNS[2:]]
            if v["failed"]:
                row[-1] += f" ({v['failed']} failed)"
            lines.append("| " + " | ".join(row) + " |")
    starts = {}  # the stereo filter's start anchors (jaxmocap.trackers.stereo_pf.start)
    for c in cells:
        if c.get("start_anchor"):
            starts.setdefault(c["config"], []).append(c["start_anchor"])
    if starts:
        lines += ["", "Stereo filter started from: " + "; ".join(
            f"{c}: " + ", ".join(f"{a} {v.count(a)}" for a in sorted(set(v)))
            for c, v in starts.items()) + " cells"]
    errors = [c for c in cells if "error" in c]
    if errors:
        lines += ["", "## Failed cells", ""]
        lines += [f"- `{c['cell']}`: {c['error']}" for c in errors]
    with AtomicFiles() as files:
        files.path(out / "summary.json").write_text(json.dumps(doc, indent=1) + "\n")
        files.path(out / "summary.md").write_text("\n".join(lines) + "\n")
        _plot(files.path(out / "summary.png"), names, configs, cells)
    return doc


def _plot(path: Path, names: list[str], configs: list[str], cells: list[dict]) -> None:
    # a Figure of its own (no pyplot): the caller's backend is left as it is (a notebook that
    # runs an experiment keeps drawing inline)
    from matplotlib.figure import Figure

    groups = [*names, "all"]
    fig = Figure(figsize=(max(5.0, 1.0 + 0.9 * len(groups) * max(1, len(configs)) / 2), 3.6))
    ax = fig.subplots()
    w = 0.8 / max(1, len(configs))
    for j, c in enumerate(configs):
        ys, es = [], []
        for g in groups:
            vals = [x["metrics"]["mean_error_all_frames_cm"] for x in cells
                    if x["config"] == c and (g == "all" or x["sequence"] == g)
                    and "metrics" in x and x["metrics"]["mean_error_all_frames_cm"] is not None]
            ys.append(np.mean(vals) if vals else np.nan)
            es.append(np.std(vals) if len(vals) > 1 else 0.0)
        xs = np.arange(len(groups)) + (j - (len(configs) - 1) / 2) * w
        ax.bar(xs, ys, w, yerr=es, label=c, capsize=2)
    ax.set_xticks(range(len(groups)))
    ax.set_xticklabels(groups, rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("mean joint error, all frames (cm)")
    ax.set_title("configurations per sequence (bars: seeds' spread)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100, format="png")
