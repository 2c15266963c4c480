"""Runtime configuration that the user opts into (never applied at import)."""

from __future__ import annotations

import contextlib
import os
import re
import sys
from glob import escape as glob_escape
from pathlib import Path

import jax
import platformdirs

CACHE_ENV = "JAXMOCAP_CACHE_DIR"


def cache_dir() -> Path:
    """The jaxmocap cache folder: ``$JAXMOCAP_CACHE_DIR`` or the user's cache dir."""
    env = os.environ.get(CACHE_ENV)
    return Path(env) if env else Path(platformdirs.user_cache_dir("jaxmocap"))


def cache_folder(name: str) -> Path:
    """``cache_dir() / name``, created, and tried for writing (a file is created and removed:
    permission bits lie for root and read-only mounts); one :class:`InputError` line naming
    the folder, the cause and ``JAXMOCAP_CACHE_DIR`` otherwise."""
    import tempfile

    from jaxmocap.errors import InputError
    from jaxmocap.io.atomic import describe_os_error

    folder = cache_dir() / name
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".jaxmocap-probe.", suffix=".tmp", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        where = f"{CACHE_ENV}={os.environ[CACHE_ENV]}" if os.environ.get(CACHE_ENV) else (
            f"the default cache folder {cache_dir()}; {CACHE_ENV} is unset")
        raise InputError(f"cache folder {describe_os_error(e, folder)} ({where}); set "
                         f"{CACHE_ENV} to a folder you can write") from None
    return folder


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path:
    """Turn on JAX's persistent compilation cache so a second run skips compilation.

    The cache lives in ``path``, else ``$JAXMOCAP_CACHE_DIR/jax``, else the user's cache dir
    (``~/.cache/jaxmocap/jax`` on Linux). Returns the folder used.
    """
    folder = Path(path) if path is not None else cache_folder("jax")
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _repair_damaged_programs(folder)
    return folder


# JAX's words when a cache entry does not decompress (a write cut short by a crash, a damaged
# disk): it compiles the program again but leaves the entry, and says so on every run.
_DAMAGED_ENTRY = re.compile(r"Error reading persistent compilation cache entry for '([^']+)'")


def _repair_damaged_programs(folder: Path) -> None:
    """Damaged compiled programs in ``folder`` are detected (JAX's entries carry a checksum:
    zlib's Adler-32 or zstd's), removed so that JAX writes the program it compiles instead, and
    reported in one line each (instead of JAX's warning on every run). Installed on
    ``warnings.showwarning`` (the command line opts in through this function)."""
    import warnings

    previous = warnings.showwarning
    if getattr(previous, "jaxmocap_cache", None) == folder:
        return

    def showwarning(message, category, filename, lineno, file=None, line=None):
        m = _DAMAGED_ENTRY.match(str(message))
        if m is None:
            return previous(message, category, filename, lineno, file, line)
        for entry in sorted(folder.glob(f"{glob_escape(m.group(1))}-*-cache")):
            if not _entry_intact(entry):
                with contextlib.suppress(OSError):
                    entry.unlink()
                print(f"jaxmocap: the compiled program {entry} in the cache was damaged; "
                      "compiled again", file=sys.stderr)

    showwarning.jaxmocap_cache = folder
    warnings.showwarning = showwarning
    warnings.filterwarnings("always", message=_DAMAGED_ENTRY.pattern)


def _entry_intact(entry: Path) -> bool:
    """Whether a JAX cache entry decompresses (its codec's checksum holds)."""
    from jax._src import compilation_cache

    try:
        compilation_cache.decompress_executable(entry.read_bytes())
    except Exception:  # noqa: BLE001 (zlib.error, zstd's errors: any failure is damage)
        return False
    return True


SIDE_DEVICE_ENV = "JAXMOCAP_SIDE_DEVICE"


def choose_offscreen_gl() -> str:
    """Set ``MUJOCO_GL`` to an offscreen backend (``egl``, or ``osmesa`` where no EGL library
    is found) unless the user set one, and return it.

    Run before anything imports MuJoCo (pytorch-kinematics does): with ``MUJOCO_GL`` unset,
    MuJoCo loads the ``glfw`` package, whose import starts a Python subprocess to read GLFW's
    version; we never open a window, and a Ctrl-C during that import left the subprocess
    printing a traceback into our stderr."""
    import ctypes.util

    backend = os.environ.get("MUJOCO_GL", "").lower()
    if backend not in ("egl", "osmesa", "glx"):
        backend = "egl" if ctypes.util.find_library("EGL") else "osmesa"
        os.environ["MUJOCO_GL"] = backend
    return backend


def enable_side_device() -> bool:
    """Give JAX a second CPU device for the host-side compiled calls of live loops.

    XLA's CPU client runs one program at a time per device: in
    :func:`jaxmocap.trackers.stereo_pf.live` the blob tracker's triangulation and the capture
    colours' maps of frame t+1, dispatched while the filter step of frame t computes, waited
    for it, and the host/device overlap was lost (``docs/results/realtime_profile.md``).
    :func:`side_device` is that second device; the same compiled programs run there (identical
    results). Must run before JAX's backend starts (the CLI calls it first); returns whether
    there are now >= 2 CPU devices. ``JAXMOCAP_SIDE_DEVICE=0`` leaves JAX's devices alone; a
    count the user gave (``jax_num_cpu_devices``, ``JAX_NUM_CPU_DEVICES``,
    ``--xla_force_host_platform_device_count``) is kept.
    """
    if os.environ.get(SIDE_DEVICE_ENV, "").strip() == "0":
        return False
    user_set = "JAX_NUM_CPU_DEVICES" in os.environ or "xla_force_host_platform_device_count" in (
        os.environ.get("XLA_FLAGS", "")
    )
    if jax.config.jax_num_cpu_devices < 2 and not user_set:
        try:
            jax.config.update("jax_num_cpu_devices", 2)
        except RuntimeError:  # the backend has started: its device count is fixed
            pass
    return side_device() is not None


def side_device() -> jax.Device | None:
    """The second CPU device when JAX has one (:func:`enable_side_device`), else None."""
    cpus = jax.devices("cpu")
    return cpus[1] if len(cpus) > 1 else None
