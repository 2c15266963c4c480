"""Running an experiment: the cells, in-process or on a Dask cluster, resumable.

Cells are ``(sequence, configuration, seed)``; cell ``s__c__k`` lives in
``OUT/cells/<s>__<c>__<k>/``: ``poses.npz`` (:func:`jaxmocap.io.export.write_npz` layout plus
``q_raw``, the estimate of every frame, and ``error_cm``, its per-frame mean error),
``diagnostics.csv`` and ``result.json`` (metrics, the configuration's hash and the sequence's
content digest). A cell folder is written whole or not at all (temporary folder, renamed), so a
run killed at any point resumes: a cell whose ``result.json`` carries the current hash and
digest is read back, not recomputed; a failed cell leaves no folder and is tried again.

Workers (:mod:`jaxmocap.experiment.cluster`) only track; the driver writes every file, so a
cluster needs the dataset at the same path on every machine but not the output folder.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from jaxmocap.errors import InputError
from jaxmocap.experiment._guard import _one_line, guarded
from jaxmocap.experiment.cell import cell_metrics, compute_cell, diagnostics_csv, eval_joints
from jaxmocap.experiment.config import (
    SEQUENCE,
    ExperimentConfig,
    ExperimentError,
    Sequence,
    config_hash,
    dataset_sequences,
    digest_folder,
    groundtruth_keys,
    load_config,
)

RESULT = "result.json"


def cell_name(seq: str, config: str, seed: int) -> str:
    return f"{seq}__{config}__{seed}"


def check_inputs(exp: ExperimentConfig, seqs: list[Sequence]) -> None:
    """What each configuration needs from every sequence, before any work (one line)."""
    _check_tuned(exp, seqs)
    for s in seqs:
        try:
            info = json.loads((Path(s.folder) / "scene.json").read_text())["render"]
            n_cams = len(info["cameras"])
        except (OSError, ValueError, KeyError, TypeError):
            raise ExperimentError(f"{s.folder}/scene.json: not a `jaxmocap synth` scene file "
                                  "(field render.cameras)") from None
        keys = None
        for c in exp.configs:
            if c.method == "pf" and n_cams != 2:
                raise ExperimentError(f"config '{c.name}' (pf) needs a stereo pair; sequence "
                                      f"{s.name} has {n_cams} cameras")
            if c.method == "shirt" and not ("colors" in c.options
                                            and "white_balance" in c.options):
                keys = groundtruth_keys(s.folder) if keys is None else keys
                if "colour_ids" not in keys:
                    raise ExperimentError(
                        f"config '{c.name}' (shirt): sequence {s.name} has no colour_ids in "
                        "groundtruth.npz for the session set-up; give options.colors and "
                        "options.white_balance (files of `jaxmocap colors`) or render with "
                        "--colour-ids")


def _check_tuned(exp: ExperimentConfig, seqs: list[Sequence]) -> None:
    """A configuration's tuned-parameters file (option ``tuned``) against the body and shirt
    of every sequence it runs on (:meth:`jaxmocap.tuned.TunedParameters.check_for`)."""
    from jaxmocap.experiment.cell import _body, _garment
    from jaxmocap.tuned import TunedParameters

    for c in exp.configs:
        if "tuned" not in c.options:
            continue
        tuned = TunedParameters.load(c.options["tuned"])
        cfg = c.to_dict()
        per_seq = SEQUENCE in (c.body, c.garment)
        for s in seqs if per_seq else seqs[:1]:
            body = _body(cfg, s.folder)
            garment = _garment(cfg, body, s.folder) if c.method == "shirt" else None
            try:
                tuned.check_for(c.method, body, garment)
            except InputError as e:
                raise ExperimentError(f"config '{c.name}'"
                                      + (f", sequence {s.name}" if per_seq else "")
                                      + f": {e}") from None


class Plan:
    """Every cell of an experiment with its spec, and which are already done."""

    def __init__(self, exp: ExperimentConfig, seqs: list[Sequence], out: Path, x64: bool):
        self.exp, self.seqs, self.out = exp, seqs, out
        digests = {s.name: digest_folder(s.folder) for s in seqs}
        hashes = {c.name: config_hash(c, exp.good_cm, exp.bad_cm) for c in exp.configs}
        self.cells: list[dict] = []
        for s in seqs:
            for c in exp.configs:
                for seed in c.seeds:
                    self.cells.append({
                        "cell": cell_name(s.name, c.name, seed), "sequence": s.name,
                        "folder": s.folder, "config": c.to_dict(), "seed": int(seed),
                        "config_hash": hashes[c.name], "dataset_digest": digests[s.name],
                        "x64": bool(x64)})

    def finished(self, spec: dict) -> dict | None:
        """The stored result of a cell if it is complete and current, else None."""
        path = self.out / "cells" / spec["cell"] / RESULT
        try:
            res = json.loads(path.read_text())
        except (OSError, ValueError):
            return None
        if (res.get("config_hash") == spec["config_hash"]
                and res.get("dataset_digest") == spec["dataset_digest"]
                and res.get("metrics") is not None):
            return res
        return None


def write_cell(out: Path, spec: dict, result: dict, exp: ExperimentConfig, bodies: dict) -> dict:
    """Metrics of a computed cell and its folder, written atomically (replacing a stale one)."""
    from jaxmocap.experiment.cell import _body
    from jaxmocap.io.export import pose_track, write_npz

    cfg = spec["config"]
    key = (cfg["name"], spec["folder"] if cfg.get("body") == "sequence" else None)
    if key not in bodies:
        bodies[key] = _body(cfg, spec["folder"])
    body = bodies[key]
    target = out / "cells" / spec["cell"]
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    try:
        q, valid = result["q"], np.asarray(result["valid"], bool)
        track = pose_track(body, q, valid, result["fps"])
        write_npz(tmp / "poses.npz", track, q_raw=q)
        metrics, frame_err = cell_metrics(body, result, tmp / "poses.npz", spec["folder"],
                                          eval_joints(cfg), exp.good_cm, exp.bad_cm)
        write_npz(tmp / "poses.npz", track, q_raw=q, error_cm=frame_err)
        (tmp / "diagnostics.csv").write_text(diagnostics_csv(result["diagnostics"], valid))
        doc = {k: spec[k] for k in ("cell", "sequence", "seed", "config_hash",
                                    "dataset_digest")}
        doc.update(config=cfg["name"], method=cfg["method"], metrics=metrics,
                   init_frame=result.get("init_frame"),
                   start_anchor=result.get("start_anchor"))
        (tmp / RESULT).write_text(json.dumps(doc, indent=1) + "\n")
        os.chmod(tmp, 0o777 & ~_umask())
        if target.exists():
            old = target.with_name(f".{target.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            os.replace(target, old)
            os.replace(tmp, target)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return doc


def output_folder(out, seqs: list[Sequence], dataset) -> Path:
    """``out`` checked as a new or resumable output folder
    (:func:`jaxmocap.io.atomic.check_output_folder`) that is neither a sequence's folder nor
    the dataset's, nor inside one (no command writes into its inputs)."""
    from jaxmocap.io.atomic import check_output_folder

    out = check_output_folder(out)
    res_out = out.resolve()
    for p in [Path(s.folder).resolve() for s in seqs] + [Path(dataset).resolve()]:
        if res_out == p or p in res_out.parents:
            raise ExperimentError(f"{out}: the output folder is (inside) the input {p}; "
                                  "choose another folder")
    return out


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def run_experiment(dataset, config, out, workers: int = 0, scheduler: str | None = None,
                   split=None, subset: str | None = None, retries: int = 1,
                   progress: bool = True, cell_fn: Callable[[dict], dict] | None = None,
                   cluster_kwargs: dict | None = None) -> dict:
    """Run (or resume) an experiment; returns the summary (:mod:`.summary`), also written to
    ``out``. ``workers`` 0 and no ``scheduler``: every cell in this process, in order;
    ``workers`` N: a local Dask cluster of N single-threaded processes; ``scheduler``: an
    existing Dask cluster. ``cell_fn`` replaces :func:`compute_cell` (tests)."""
    import jax
    from tqdm import tqdm

    from jaxmocap.experiment.summary import write_summary

    exp = config if isinstance(config, ExperimentConfig) else load_config(config)
    seqs = dataset_sequences(dataset, split, subset)
    if workers < 0:
        raise ExperimentError(f"--workers: expected >= 0, got {workers}")
    if retries < 0:
        raise ExperimentError(f"--retries: expected >= 0, got {retries}")
    out = output_folder(out, seqs, dataset)
    check_inputs(exp, seqs)
    fn = cell_fn or compute_cell
    plan = Plan(exp, seqs, out, bool(jax.config.jax_enable_x64))
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict] = {}
    todo = []
    for spec in plan.cells:
        done = plan.finished(spec)
        if done is not None:
            results[spec["cell"]] = done
        else:
            todo.append(spec)
    stats = {"cells": len(plan.cells), "computed": 0, "reused": len(plan.cells) - len(todo),
             "failed": 0}
    bodies: dict = {}
    t0 = time.perf_counter()
    bar = tqdm(total=len(todo), desc="experiment cells", unit="cell", disable=not progress)

    def accept(spec, res=None, err=None):
        if err is None and "error" in res:
            err = res["error"]
        if err is None:
            try:
                results[spec["cell"]] = write_cell(out, spec, res, exp, bodies)
                stats["computed"] += 1
            except InputError as e:
                err = _one_line(e)
        if err is not None:
            stats["failed"] += 1
            results[spec["cell"]] = {"cell": spec["cell"], "sequence": spec["sequence"],
                                     "config": spec["config"]["name"], "seed": spec["seed"],
                                     "method": spec["config"]["method"], "error": err}
        bar.update(1)

    if todo and workers == 0 and scheduler is None:
        for spec in todo:
            try:
                res = guarded(fn, spec)
            except Exception as e:  # reported in the summary, the run goes on
                accept(spec, err=_one_line(e))
            else:
                accept(spec, res)
    elif todo:
        from jaxmocap.experiment.cluster import run_on_cluster

        run_on_cluster(todo, fn, accept, workers, scheduler, retries, cluster_kwargs or {})
    bar.close()
    stats["wall_s"] = time.perf_counter() - t0
    return write_summary(out, exp, seqs, plan.cells, results, stats)
