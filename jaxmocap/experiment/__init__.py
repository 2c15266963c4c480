"""Tracker configurations x a dataset of sequences, on Dask (``jaxmocap experiment``:
:mod:`jaxmocap.commands.experiment`).

A dataset folder of sequences (``jaxmocap synth`` folders) and a configuration file (named
tracker configurations: method, body, garment, options, seeds; :mod:`.config`) give cells
``(sequence, configuration, seed)``; each is tracked once (:mod:`.cell`), its poses,
diagnostics and metrics written to ``OUT/cells/`` (:mod:`.runner`, resumable), and the summary
compares the configurations per sequence and overall (``summary.md/json/png``,
:mod:`.summary`). Cells run in-process (``--workers 0``), on a local Dask cluster of
single-threaded processes (``--workers N``, the default one per core) or on an existing
cluster (``--scheduler ADDRESS``; :mod:`.cluster`).
"""

from __future__ import annotations

from jaxmocap.experiment.config import ExperimentError, load_config

__all__ = ["ExperimentError", "load_config", "run_experiment"]


def run_experiment(*args, **kwargs):
    """:func:`jaxmocap.experiment.runner.run_experiment` (imported lazily)."""
    from jaxmocap.experiment.runner import run_experiment as _run

    return _run(*args, **kwargs)
