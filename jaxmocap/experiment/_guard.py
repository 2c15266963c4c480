"""A cell's bad input as a result, not an exception: shared by the in-process runner and the
Dask cluster (which must not retry a deterministic error)."""

from __future__ import annotations

from collections.abc import Callable

from jaxmocap.errors import InputError


def _one_line(err: BaseException) -> str:
    msg = str(err).strip().splitlines()
    return f"{type(err).__name__}: {msg[0] if msg else ''}".rstrip(": ")


def guarded(fn: Callable[[dict], dict], spec: dict) -> dict:
    """Run ``fn(spec)``; bad input (:class:`InputError`, deterministic) comes back as
    ``{"error": line}`` instead of raising, so the cluster does not retry it. Anything else
    raises (and is retried)."""
    try:
        return fn(spec)
    except InputError as e:
        return {"error": _one_line(e)}
