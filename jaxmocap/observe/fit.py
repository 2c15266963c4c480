"""One call that trains the observation model for a body + garment (what ``jaxmocap learn``
runs): renders the training geometry (:mod:`jaxmocap.observe.scenes`), trains
(:mod:`jaxmocap.observe.train`), writes the model file (:mod:`jaxmocap.observe.io`).

Cached by the inputs' digests like the pose database: the key hashes the body, the garment, the
settings and this package's source, so a second call with the same inputs loads the file, and a
changed input trains anew. Resumable: every :data:`CHECKPOINT_EVERY` steps the model, the
optimiser state and the loss curve so far go to ``<model>.partial`` (atomically); a run killed
part-way continues from there and, since step i's batch is drawn from ``fold_in(seed, i)``,
ends with the weights an uninterrupted run gives.
"""

from __future__ import annotations

import hashlib
import io
import json
import time
from pathlib import Path
from typing import NamedTuple

import equinox as eqx
import jax
import numpy as np

from jaxmocap.body import BodyModel
from jaxmocap.body.roles import body_digest
from jaxmocap.garment import Garment, garment_digest

from . import io as obs_io
from .classes import classes_of
from .model import Observer
from .scenes import Geometry, palette_of, render_geometry
from .train import TrainConfig, optimiser, train

CHECKPOINT_EVERY = 100
# the model shipped for the bundled body and shirt (``jaxmocap learn`` with the defaults); other
# bodies and shirts with as many colours start from it (:func:`learn`). The stereo rig's
# "frame" models (``jaxmocap learn --tracker pf``) are trained from scratch: none ships while
# they measure worse than the filter's colour model (docs/results/learned_pf.md)
BUNDLED = Path(__file__).parent / "data" / "bundled.eqx"
SHIPPED = {"crop": BUNDLED}


class Settings(NamedTuple):
    """What is trained: ``poses`` rendered crops of ``size`` px, then ``steps`` steps of
    ``batch`` crops; ``seed`` fixes poses, cameras, lamps and every batch's light; ``framing``
    what the crops frame (:data:`~.scenes.FRAMINGS`: the shirt tracker's crop or a stereo
    rig's frame). The defaults train in ~8 minutes on this project's 2-core machine
    (docs/results/learned.md)."""

    poses: int = 600
    size: int = 128
    steps: int = 1200
    batch: int = 6
    seed: int = 0
    framing: str = "crop"


# a body or shirt of its own, starting from the bundled model: fewer renders and steps (the
# colours, skin and the light are learned already; the body's shapes and the shirt's layout
# are what is new)
FINE_TUNE = Settings(poses=300, steps=400)


TRAINING_SOURCES = ("classes.py", "scenes.py", "model.py", "train.py")  # what the weights depend on


def _source_digest() -> str:
    """Digest of the modules that decide the trained weights (not of the file format's or this
    module's bookkeeping, whose edits leave a cached model valid)."""
    h = hashlib.sha256()
    for name in TRAINING_SOURCES:
        h.update((Path(__file__).parent / name).read_bytes())
    return h.hexdigest()[:16]


def cache_key(model: BodyModel, garment: Garment, settings: Settings,
              start_key: str | None = None) -> str:
    """Digest of everything the trained weights depend on (``start_key``: the key of the model
    training starts from, if any)."""
    text = json.dumps([body_digest(model), garment_digest(garment), list(settings),
                       _source_digest()] + ([start_key] if start_key else []))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def cache_path(key: str, cache: str | Path | None = None) -> Path:
    from jaxmocap._config import cache_dir

    folder = Path(cache) if cache is not None else cache_dir() / "observer"
    return folder / f"observer-{key}.eqx"


def training_poses(model: BodyModel, settings: Settings) -> np.ndarray:
    """The database's pose sampler over the training clips (never a held-out clip)."""
    from jaxmocap.posedb._sample import SamplingConfig, sample_poses, source_pool
    from jaxmocap.synth import TRAIN_CLIPS

    pool = source_pool(model, tuple(TRAIN_CLIPS))
    return sample_poses(SamplingConfig(size=settings.poses, seed=settings.seed), model, pool)


def _save_partial(path: Path, model, opt_state, step: int, losses: list[float], key: str):
    from jaxmocap.io.atomic import atomic_write

    buf = io.BytesIO()
    eqx.tree_serialise_leaves(buf, (model, opt_state))
    with atomic_write(path, "wb") as f:
        f.write(json.dumps(dict(key=key, step=step, losses=losses)).encode() + b"\n")
        f.write(buf.getvalue())


def _load_partial(path: Path, like, key: str):
    """``(model, opt_state, step, losses)`` of a checkpoint for ``key``, or None (absent, for
    other inputs, or damaged: then it is ignored and training starts over; said in the log)."""
    try:
        with open(path, "rb") as f:
            head = json.loads(f.readline(1 << 24))
            if head.get("key") != key:
                return None
            model, opt_state = eqx.tree_deserialise_leaves(f, like)
        return model, opt_state, int(head["step"]), list(head["losses"])
    except (OSError, ValueError, KeyError, TypeError, RuntimeError):
        return None


def start_model(path: str | Path, classes) -> tuple[Observer, dict]:
    """A trained model to start from (any body), refused in one line when its classes are not
    as many as ``classes``' (another number of shirt colours)."""
    obs, head = obs_io.load(path)
    if obs.n_classes != classes.n:
        raise obs_io.ObserverFileError(
            f"{path}: gives {obs.n_classes} classes, this shirt needs {classes.n} (background, "
            f"{classes.n_colours} colours, head, two hands); train from scratch (no --start)")
    return obs, head


def learn(model: BodyModel, garment: Garment, settings: Settings | None = None,
          out: str | Path | None = None, cache: str | Path | None = None,
          progress: bool = True, log=print, framing: str = "crop"
          ) -> tuple[Observer, dict, Path]:
    """What ``jaxmocap learn`` trains by default: for the bundled body and shirt the shipped
    model of ``framing`` (:data:`SHIPPED`); for a body or shirt of their own with as many
    colours, :data:`FINE_TUNE` from that model; else (and for a framing with no shipped model)
    the default :class:`Settings` from scratch. ``settings`` overrides the choice of settings
    (not of the start)."""
    classes = classes_of(model, garment)
    start = None
    shipped = SHIPPED.get(framing)
    if shipped is not None and shipped.exists():
        head = obs_io.read_header(shipped)
        own = (head.get("body_digest"), head.get("garment_digest")) == (
            body_digest(model), garment_digest(garment))
        if own:
            obs, head = obs_io.load(shipped, model, garment)
            if settings is None or Settings(**head["settings"]) == settings:
                if out is not None:
                    obs_io.save(out, obs, _header_of(head))
                return obs, head, shipped
        elif head["hyper"]["n_classes"] == classes.n:
            start = shipped
    if settings is None:
        settings = (FINE_TUNE if start is not None else Settings())._replace(framing=framing)
    return fit(model, garment, settings, out, cache, progress, log, start=start)


def _header_of(head: dict) -> dict:
    return {k: v for k, v in head.items() if k not in ("format", "version", "hyper")}


def fit(model: BodyModel, garment: Garment, settings: Settings | None = None,
        out: str | Path | None = None, cache: str | Path | None = None, progress: bool = True,
        log=print, start: str | Path | None = None) -> tuple[Observer, dict, Path]:
    """Train (or load from the cache) the observation model of ``model`` + ``garment``;
    returns ``(observer, header, path)``. ``out``: also write the file there. ``start``: a
    model file (any body, as many classes) whose weights training starts from."""
    from tqdm.auto import tqdm

    settings = Settings() if settings is None else settings
    classes = classes_of(model, garment)
    start_obs = start_head = None
    if start is not None:
        start_obs, start_head = start_model(start, classes)
    key = cache_key(model, garment, settings, None if start_head is None else start_head["key"])
    path = cache_path(key, cache)
    if path.exists():
        try:
            obs, head = obs_io.load(path, model, garment)
            if out is not None and Path(out).resolve() != path.resolve():
                obs_io.save(out, obs, _header_of(head))
            return obs, head, path
        except obs_io.ObserverFileError as e:
            log(f"jaxmocap learn: cached model damaged ({e}); training it again")
    t0 = time.perf_counter()
    poses = training_poses(model, settings)
    bar = tqdm(total=settings.poses, desc="rendering training scenes", disable=not progress,
               unit="crop")
    geo: Geometry = render_geometry(model, garment, classes, poses,
                                    jax.random.key(settings.seed), settings.size,
                                    progress=bar.update, framing=settings.framing)
    bar.close()
    t_geo = time.perf_counter() - t0
    config = TrainConfig(steps=settings.steps, batch=settings.batch, seed=settings.seed)
    obs = Observer(classes.n, jax.random.fold_in(jax.random.key(settings.seed), 1))
    if start_obs is not None:
        obs = start_obs
    partial = path.with_suffix(".partial")
    path.parent.mkdir(parents=True, exist_ok=True)
    like = (obs, optimiser(config).init(eqx.filter(obs, eqx.is_array)))
    resumed = _load_partial(partial, like, key)
    start, losses, opt_state = 0, [], None
    if resumed is not None:
        obs, opt_state, start, losses = resumed
        log(f"jaxmocap learn: resuming from step {start} ({partial})")
    bar = tqdm(total=settings.steps, initial=start, desc="training", disable=not progress,
               unit="step")

    def on_step(i, loss, m, st):
        losses.append(loss)
        bar.update(1)
        bar.set_postfix(loss=f"{loss:.3f}")
        if (i + 1) % CHECKPOINT_EVERY == 0 and i + 1 < settings.steps:
            _save_partial(partial, m, st, i + 1, losses, key)

    t1 = time.perf_counter()
    obs, _, _ = train(obs, geo, palette_of(garment), config, start=start, opt_state=opt_state,
                      on_step=on_step)
    bar.close()
    pixels = np.bincount(np.asarray(geo.label).reshape(-1).astype(np.int64),
                         minlength=classes.n)
    header = dict(
        key=key, body_digest=body_digest(model), garment_digest=garment_digest(garment),
        classes=list(classes.names), settings=settings._asdict(),
        data=dict(renderer="jaxmocap.render (JAX ray caster)", crops=settings.poses,
                  pixels_per_class=pixels.tolist()),
        start=None if start_head is None else dict(file=str(start), key=start_head["key"]),
        record=dict(steps=settings.steps, resumed_from=start,
                    loss_every_10=[float(np.mean(losses[i:i + 10]))
                                   for i in range(0, len(losses), 10)],
                    render_s=round(t_geo, 1), train_s=round(time.perf_counter() - t1, 1)),
        source_digest=_source_digest(),
    )
    obs_io.save(path, obs, header)
    partial.unlink(missing_ok=True)
    if out is not None:
        obs_io.save(out, obs, header)
    return obs, header, path
