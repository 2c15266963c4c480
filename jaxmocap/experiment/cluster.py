"""Dask distributed for experiments: a local cluster of single-threaded worker processes, or
an existing scheduler.

**Threads per worker.** A local cluster runs ``N`` worker processes with one Dask thread
each, and each process's own thread pools are held to one core through its environment,
set before the process imports JAX or OpenCV (:data:`WORKER_ENV`): XLA's CPU backend runs
Eigen contractions on a pool of one thread per core unless ``--xla_cpu_multi_thread_eigen=false``;
OpenMP/BLAS pools (``OMP_NUM_THREADS`` ...) likewise; OpenCV's pool is set to one thread by
the worker plugin (:class:`JaxmocapWorker`). With ``N`` = cores, the workers then share the
machine instead of each oversubscribing it (docs/results/experiments.md measures it).

**Compilation cache.** Every worker enables JAX's persistent compilation cache in the same
folder as the driver (:func:`jaxmocap._config.enable_compilation_cache`, ``JAXMOCAP_CACHE_DIR``
passed on), so a tracker compiled once on this machine is read from disk by every worker.

**Configuration affinity.** A worker's first cell of a configuration traces that tracker
(the persistent cache skips XLA's compilation, not tracing and lowering): 28-33 s against
3-7 s for each further 80-frame cell (docs/results/experiments.md). Cells of one configuration
are therefore sent to one worker, configurations dealt to the workers in turn
(:func:`affinity`), as a loose restriction: an idle worker still steals work, and a cell of a
worker that died runs elsewhere.

**Failures.** A cell that raises is retried ``retries`` times (Dask ``retries=``), then
reported; a worker process that dies mid-cell (killed, out of memory) has its cell rescheduled
on another worker by the scheduler (``distributed.scheduler.allowed-failures`` times).
"""

from __future__ import annotations

import os
from collections.abc import Callable

from distributed.diagnostics.plugin import WorkerPlugin

WORKER_ENV = {
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "TF_NUM_INTRAOP_THREADS": "1",
    "TF_NUM_INTEROP_THREADS": "1",
    "JAX_PLATFORMS": "cpu",
}


def worker_env() -> dict[str, str]:
    """The environment of a local worker process (module docstring)."""
    from jaxmocap._config import CACHE_ENV, cache_dir

    env = dict(WORKER_ENV)
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_multi_thread_eigen" not in flags:
        env["XLA_FLAGS"] = f"{flags} {WORKER_ENV['XLA_FLAGS']}".strip()
    else:
        env["XLA_FLAGS"] = flags
    env[CACHE_ENV] = str(cache_dir())
    return env


class JaxmocapWorker(WorkerPlugin):
    """Worker plugin: one OpenCV thread, JAX's persistent compilation cache on."""

    name = "jaxmocap"

    def __init__(self, cache: str):
        self.cache = cache

    def setup(self, worker) -> None:
        import cv2

        cv2.setNumThreads(1)
        os.environ.setdefault("JAXMOCAP_CACHE_DIR", self.cache)
        from jaxmocap._config import enable_compilation_cache

        enable_compilation_cache()


def local_cluster(n_workers: int, **kwargs):
    """A :class:`distributed.LocalCluster` of ``n_workers`` single-threaded processes with
    :func:`worker_env`."""
    from distributed import LocalCluster

    opts = dict(n_workers=n_workers, threads_per_worker=1, processes=True,
                dashboard_address=None, env=worker_env(), silence_logs=40)
    opts.update(kwargs)
    return LocalCluster(**opts)


def client_for(workers: int, scheduler: str | None, cluster_kwargs: dict | None = None):
    """(client, cluster or None): a client of ``scheduler``, else of a new local cluster."""
    from distributed import Client

    from jaxmocap._config import cache_dir
    from jaxmocap.errors import InputError

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as e:
            raise InputError(f"--scheduler {scheduler}: cannot connect ({e})") from None
        cluster = None
    else:
        cluster = local_cluster(max(1, workers), **(cluster_kwargs or {}))
        client = Client(cluster)
    client.register_plugin(JaxmocapWorker(str(cache_dir())), name=JaxmocapWorker.name)
    return client, cluster


def affinity(specs: list[dict], workers: list[str]) -> dict[str, str]:
    """Configuration name -> worker address: configurations in order of first appearance,
    dealt round-robin over ``workers`` (sorted, so the same cluster gives the same deal)."""
    order: dict[str, str] = {}
    addrs = sorted(workers)
    for spec in specs:
        name = spec["config"]["name"]
        if name not in order and addrs:
            order[name] = addrs[len(order) % len(addrs)]
    return order


def run_on_cluster(specs: list[dict], fn: Callable[[dict], dict],
                   accept: Callable, workers: int, scheduler: str | None, retries: int,
                   cluster_kwargs: dict) -> None:
    """Submit every cell, hand each result (or its one-line error) to ``accept`` as it
    completes (``distributed.as_completed``)."""
    from distributed import as_completed

    from jaxmocap.experiment._guard import _one_line, guarded

    client, cluster = client_for(workers, scheduler, cluster_kwargs)
    try:
        if cluster is not None:
            client.wait_for_workers(max(1, workers), timeout="120s")
        where = affinity(specs, list(client.scheduler_info()["workers"]))
        futures = {}
        for spec in specs:
            addr = where.get(spec["config"]["name"])
            f = client.submit(guarded, fn, spec, key=f"cell-{spec['cell']}", retries=retries,
                              pure=False, workers=None if addr is None else [addr],
                              allow_other_workers=True)
            futures[f.key] = (f, spec)
        for fut in as_completed([f for f, _ in futures.values()]):
            spec = futures[fut.key][1]
            try:  # waits again if the result was lost with a worker that died meanwhile
                res = fut.result()
            except Exception as e:  # raised in the cell (after the retries), KilledWorker
                accept(spec, err=_one_line(e))
            else:
                accept(spec, res)
            fut.release()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
