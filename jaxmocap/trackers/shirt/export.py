"""The colour-shirt step exported ahead of time for the demo's set-up (cold start), and that
set-up itself (:func:`demo_scene`, :func:`demo_setup`; ``jaxmocap demo`` runs it).

A first frame on an empty compilation cache spends ~6 s tracing the step in Python (tens of
thousands of primitives) before XLA compiles it for ~16 s (``docs/results/realtime_profile.md``).
For the one set-up every newcomer runs -- ``jaxmocap demo``: two 320x240 webcams,
the bundled body and shirt, the demo's pose database -- the package ships the step already
traced and lowered (``jax.export``, StableHLO), so that first frame only compiles it.

The shipped program applies only where it is exactly the step that tracing would produce:

* the same **source**: a hash of every ``jaxmocap`` module imported while the step was traced,
  and the same versions of jax, jaxlib, equinox, optimistix and lineax;
* the same **inputs' structure**: the parameters' and state's tree, every static (non-array)
  value, every array's shape and dtype, the frames' shape and dtype, no foreground masks.

Array values (database, colour model, cameras, covariances, white balance) are arguments of
the program, not baked into it. Where the program does not apply, :func:`load` says why in
one line and the caller traces the step as usual (the compilation cache still keeps it for
the next run). ``python -m jaxmocap.trackers.shirt.export`` writes the program again; a test
fails while the shipped one is stale.
"""

from __future__ import annotations

import dataclasses
import gzip
import hashlib
import importlib.metadata
import json
import sys
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

PACKAGE_ROOT = Path(__file__).resolve().parents[2]
EXPORT_DIR = Path(__file__).resolve().with_name("exported")
PROGRAM = EXPORT_DIR / "shirt_step_demo.jaxexport.gz"
MANIFEST = EXPORT_DIR / "shirt_step_demo.json"
SETUP = "jaxmocap demo's set-up: 2 webcams 320x240, bundled body and shirt, 3,000-pose database"
REGENERATE = "python -m jaxmocap.trackers.shirt.export"
# LAPACK calls of the IK's least-squares solve (QR): jax.export guarantees compatibility only
# for a list of custom calls; the fingerprint pins the exact jax / jaxlib instead
_CUSTOM_CALLS = ("lapack_sgeqrf_ffi", "lapack_sormqr_ffi")
_LIBRARIES = ("jax", "jaxlib", "equinox", "optimistix", "lineax")

# The demo's set-up (``jaxmocap demo``): a held-out clip (docs/DATA.md), two 320x240 webcams, a
# lamp switched off and an occluder passing in front, a small pose database.
DEMO_CLIP = "humanoid3d_punch"  # held out from the database and covariances (docs/DATA.md)
DEMO_FRAMES = 20
DEMO_SIZE = (320, 240)
DEMO_DB_SIZE = 3000
DEMO_LAMP_OFF = 12  # frame at which the lamp is switched off
DEMO_OCCLUDER = (5, 8)  # frames during which a panel passes in front


def _static_token(x) -> str:
    if isinstance(x, np.ndarray):
        digest = hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest()
        return f"ndarray{x.dtype}{x.shape}:{digest}"
    if callable(x) and hasattr(x, "__qualname__"):
        return f"callable:{getattr(x, '__module__', '')}.{x.__qualname__}"
    return repr(x)


def _split(params, state):
    dyn, static = eqx.partition((params, state), eqx.is_array)
    leaves, treedef = jax.tree.flatten(dyn)
    return leaves, treedef, static


def fingerprint_inputs(params, state, frames_shape, frames_dtype) -> str:
    """Hash of everything about the step's inputs that is baked into a traced program: the
    tree, the static values, the arrays' shapes and dtypes (not their values)."""
    leaves, treedef, static = _split(params, state)
    h = hashlib.sha256(repr(treedef).encode())
    for tok in map(_static_token, jax.tree.leaves(static)):
        h.update(tok.encode())
    for a in leaves:
        h.update(f"{a.dtype}{a.shape}{getattr(a, 'weak_type', False)};".encode())
    h.update(f"frames{np.dtype(frames_dtype)}{tuple(frames_shape)}".encode())
    return h.hexdigest()


def _library_versions() -> dict[str, str]:
    return {name: importlib.metadata.version(name) for name in _LIBRARIES}


def source_hash(modules: list[str]) -> str:
    """Hash of the given ``jaxmocap`` source files (paths relative to the package)."""
    h = hashlib.sha256()
    for rel in modules:
        path = PACKAGE_ROOT / rel
        h.update(rel.encode())
        h.update(path.read_bytes() if path.exists() else b"<missing>")
    return h.hexdigest()


def _loaded_modules() -> list[str]:
    """The ``jaxmocap`` source files imported now (this one included: it wraps the step)."""
    out = {Path(__file__).resolve().relative_to(PACKAGE_ROOT).as_posix()}
    for name, mod in list(sys.modules.items()):
        f = getattr(mod, "__file__", None)
        if (name == "jaxmocap" or name.startswith("jaxmocap.")) and f and f.endswith(".py"):
            out.add(Path(f).resolve().relative_to(PACKAGE_ROOT).as_posix())
    return sorted(out)


def _output_tree(state) -> jax.tree_util.PyTreeDef:
    """The tree of ``(ShirtState, ShirtOutput)`` (every leaf an array; built from the classes,
    so that the program's flat outputs become the step's outputs without tracing it)."""
    from jaxmocap.trackers.shirt.params import FrameSignals, ShirtOutput

    signals = FrameSignals(*([0] * len(FrameSignals._fields)))
    colours = state.look is not None  # the optional outputs of ``patch_colours``

    def leaf(f):
        if f.name == "signals":
            return signals
        return 0 if f.default is not None or colours else None

    out = ShirtOutput(**{f.name: leaf(f) for f in dataclasses.fields(ShirtOutput)})
    return jax.tree.structure((state, out))


def _flat_step(treedef, static):
    from jaxmocap.trackers.shirt.frame import _step

    def flat(leaves, frames):
        params, state = eqx.combine(jax.tree.unflatten(treedef, leaves), static)
        return jax.tree.leaves(_step(params, state, frames, None))

    return flat


def export(params, state, frames) -> tuple[bytes, dict]:
    """Trace and lower the step for these inputs' structure; (serialized program, manifest)."""
    from jax import export as jex

    frames = jnp.asarray(frames)
    leaves, treedef, static = _split(params, state)
    checks = [jex.DisabledSafetyCheck.custom_call(c) for c in _CUSTOM_CALLS]
    exported = jex.export(jax.jit(_flat_step(treedef, static)), disabled_checks=checks)(
        leaves, frames
    )
    modules = _loaded_modules()
    manifest = {
        "setup": SETUP,
        "inputs": fingerprint_inputs(params, state, frames.shape, frames.dtype),
        "libraries": _library_versions(),
        "modules": modules,
        "source": source_hash(modules),
        "n_outputs": len(exported.out_avals),
    }
    return exported.serialize(), manifest


def _stale_reason(manifest: dict) -> str | None:
    if manifest["libraries"] != _library_versions():
        return f"it was exported with {manifest['libraries']}, this is {_library_versions()}"
    if manifest["source"] != source_hash(manifest["modules"]):
        return f"jaxmocap's source changed since it was exported (regenerate: {REGENERATE})"
    return None


def load(params, state, frames, masks=None) -> tuple[Callable | None, str]:
    """The shipped program as ``fn(state, frames) -> (state, output)`` when it applies to these
    inputs, else ``(None, why not)``. ``fn`` compiles on its first call (XLA only; no trace)."""
    if masks is not None:
        return None, "the shipped program has no foreground masks"
    if not (PROGRAM.exists() and MANIFEST.exists()):
        return None, f"no shipped program in {EXPORT_DIR}"
    manifest = json.loads(MANIFEST.read_text())
    frames = jnp.asarray(frames)
    if manifest["inputs"] != fingerprint_inputs(params, state, frames.shape, frames.dtype):
        return None, f"the shipped program is for {manifest['setup']} (float32)"
    stale = _stale_reason(manifest)
    if stale is not None:
        return None, f"the shipped program is stale: {stale}"
    from jax import export as jex

    exported = jex.deserialize(bytearray(gzip.decompress(PROGRAM.read_bytes())))
    out_tree = _output_tree(state)
    if out_tree.num_leaves != manifest["n_outputs"]:
        return None, "the shipped program's outputs do not match ShirtOutput (regenerate it)"
    params_leaves = jax.tree.leaves(eqx.filter(params, eqx.is_array))  # fixed for the loop
    compiled: list = []

    def fn(state, frames):
        leaves = params_leaves + jax.tree.leaves(eqx.filter(state, eqx.is_array))
        frames = jnp.asarray(frames)
        if not compiled:  # ahead of time: a jit of ``exported.call`` traced it again (and
            # compiled again, ~18 s) when the next state came back committed to its device
            compiled.append(jax.jit(exported.call).lower(leaves, frames).compile())
        return jax.tree.unflatten(out_tree, compiled[0](leaves, frames))

    return fn, "the shipped program"


def demo_scene(n_frames: int):
    """The demo's two-webcam scene of ``n_frames`` frames (:class:`jaxmocap.synth.SceneConfig`)."""
    from jaxmocap.synth import SceneConfig

    return SceneConfig(clip=DEMO_CLIP, n_frames=n_frames, rig="webcams",
                       width=DEMO_SIZE[0], height=DEMO_SIZE[1],
                       lamp_off=min(DEMO_LAMP_OFF, n_frames - 1),
                       occluder=DEMO_OCCLUDER if n_frames > DEMO_OCCLUDER[1] else None,
                       noise_sigma=0.01, seed=0)


def demo_setup(seq, progress: bool):
    """Pose database (small, cached), then the capture-session set-up of §5.1
    (:func:`jaxmocap.trackers.shirt.setup_for_sequence`). Returns ``(body, params, W0, q0)``."""
    from jaxmocap.body import default_body
    from jaxmocap.garment import default_garment
    from jaxmocap.posedb import SamplingConfig, load_or_build
    from jaxmocap.trackers.shirt.covariances import trained_covariances
    from jaxmocap.trackers.shirt.session import setup_for_sequence

    model = default_body()
    db = load_or_build(SamplingConfig(size=DEMO_DB_SIZE), model, default_garment(model),
                       progress=progress)
    # the bundled covariances, trained on other clips (the demo's clip is held out)
    cov = trained_covariances(model.n_dof)
    params, W0, _ = setup_for_sequence(seq, db, cov=cov, work_size=96)
    return model, params, W0, jnp.zeros(model.n_dof)


def _demo_inputs():
    from jaxmocap.synth import render_sequence
    from jaxmocap.trackers.shirt.params import init

    seq = render_sequence(demo_scene(2), progress=False)
    _, params, w0, q0 = demo_setup(seq, False)
    return params, init(params, w0, q0), seq.frames


def main() -> None:
    """Write the demo's program and manifest into the package (``exported/``)."""
    from jaxmocap._config import enable_compilation_cache
    from jaxmocap.io.atomic import write_bytes, write_text

    enable_compilation_cache()
    params, state, frames = _demo_inputs()
    blob, manifest = export(params, state, frames[0])
    EXPORT_DIR.mkdir(exist_ok=True)
    write_bytes(PROGRAM, gzip.compress(blob, mtime=0))
    write_text(MANIFEST, json.dumps(manifest, indent=1) + "\n")
    print(f"wrote {PROGRAM} ({PROGRAM.stat().st_size // 1024} KiB) and {MANIFEST.name}")


if __name__ == "__main__":
    main()
