"""Runtime configuration that the user opts into (never applied at import)."""

from __future__ import annotations

import os
from pathlib import Path

import jax
import platformdirs

CACHE_ENV = "JAXMOCAP_CACHE_DIR"


def cache_dir() -> Path:
    """The jaxmocap cache folder: ``$JAXMOCAP_CACHE_DIR`` or the user's cache dir."""
    env = os.environ.get(CACHE_ENV)
    return Path(env) if env else Path(platformdirs.user_cache_dir("jaxmocap"))


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path:
    """Turn on JAX's persistent compilation cache so a second run skips compilation.

    The cache lives in ``path``, else ``$JAXMOCAP_CACHE_DIR/jax``, else the user's cache dir
    (``~/.cache/jaxmocap/jax`` on Linux). Returns the folder used.
    """
    folder = Path(path) if path is not None else cache_dir() / "jax"
    folder.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder
