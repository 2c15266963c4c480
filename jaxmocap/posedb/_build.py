"""Building, caching and loading the pose database (the command: :mod:`jaxmocap.commands.build_db`).

A database file is a ``.npz`` with ``maps`` (n, 40, 40) ``uint8`` colour ids, ``poses``
(n, n_dof) float32 and ``meta`` (JSON: key, sampling settings, DOF and colour names). It is
cached as ``<cache>/posedb/posedb-<key>.npz`` (cache: :func:`jaxmocap._config.cache_dir`),
where the key hashes the body model, the garment, the sampling settings, the canonical camera,
the tiny-map settings, :data:`CODE_VERSION` and the source of the renderer, garment and
sampler, so that any change builds a new database.

**Rendering cost.** A tiny map holds colour ids only, so a geom that carries no patch matters
only where it hides the shirt. The maps are cast against (a) the geoms of the links that carry
a patch or a skin geom (torso, arms, head, hands and whatever else hangs on those links, e.g. a
shoulder capsule) and (b) every other geom whose bounding sphere at the rest pose reaches above
the lowest point of the patched geoms' bounding spheres (e.g. a pelvis whose front bulges past
the shirt's lower edge: leaving the bundled body's pelvis out changes ~13 pixels of a map).
Geoms entirely below the shirt at rest (legs, feet) are left out: the database's poses hold
them at rest (only the upper body's roles are sampled), where they cannot cover the shirt from
the canonical camera. The ray caster's cost is rays x geoms, so the build costs what the shirt
costs, not what the body's geom count does (:func:`tiny_map_subset`). The model is closed over
by the jitted renderer, so each geom runs only its own primitive's test (``render._raycast``).
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import render
from ..body import BodyModel, default_body, fk, geom_world_poses, rest_pose
from ..body.geometry import BOX, CAPSULE, CYLINDER, SPHERE
from ..garment import Garment, default_garment, garment_digest
from ._sample import (
    SamplingConfig,
    canonical_camera,
    model_digest,
    sample_poses,
    source_pool,
)
from ._search import DatabaseError, PoseDB, make_posedb

CODE_VERSION = "posedb-2"  # bump when sampling or rendering code changes the database
RENDER_BATCH = 256  # poses per jitted render call (one compiled shape, last batch padded)


def database_key(config: SamplingConfig, model: BodyModel, garment: Garment) -> str:
    """The version key of a database: SHA-256 (first 20 hex digits) of everything that
    determines its content (module docstring)."""
    from ..synth import TRAIN_CLIPS

    config = config.validate()
    clips = config.clips or TRAIN_CLIPS
    h = hashlib.sha256()
    h.update(CODE_VERSION.encode())
    h.update(_source_digest().encode())
    h.update(repr(config._replace(clips=tuple(clips))).encode())
    h.update(model_digest(model, garment, canonical_camera(jnp.float32)).encode())
    h.update(f"{render.TINY_SIZE} {render.TINY_MARGIN}".encode())
    return h.hexdigest()[:20]


def _source_digest() -> str:
    """SHA-256 of the code that determines a database's content: the renderer, the garment and
    the pose sampler (so that an edit there never loads a stale cache)."""
    from .. import garment as garment_module
    from . import _sample

    files = sorted(Path(render.__file__).parent.glob("*.py"))
    files += [Path(garment_module.__file__), Path(_sample.__file__)]
    h = hashlib.sha256()
    for f in files:
        h.update(f.read_bytes())
    return h.hexdigest()


def _bounding_radius(kind: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Radius of a sphere about the geom frame's origin that holds the whole primitive."""
    r, h = size[:, 0], size[:, 1]
    return np.select(
        [kind == SPHERE, kind == CAPSULE, kind == CYLINDER, kind == BOX],
        [r, r + h, np.hypot(r, h), np.linalg.norm(size, axis=1)],
        np.max(size, axis=1),  # ellipsoid
    )


def tiny_map_subset(model: BodyModel, garment: Garment) -> tuple[BodyModel, Garment]:
    """The model and garment restricted to the geoms a tiny map needs (module docstring): the
    geoms of links that carry a patch or a skin geom, and every geom whose rest-pose bounding
    sphere reaches above the lowest point of the patched geoms'. Patch and skin indices are
    renumbered; colours, patch ids and names are unchanged."""
    geo = model.geometry
    link = np.asarray(geo.link)
    used = np.asarray(garment.skin, bool).copy()
    patched = np.zeros(geo.n_geoms, bool)
    patched[np.asarray(garment.patch_geom)] = True
    used |= patched
    if not patched.any():
        return model, garment
    T = np.asarray(geom_world_poses(model, fk(model.chain, rest_pose(model, jnp.float32))))
    z = T[:, 2, 3]
    radius = _bounding_radius(np.asarray(geo.kind), np.asarray(geo.size, float))
    shirt_bottom = np.min((z - radius)[patched])
    keep = np.flatnonzero(np.isin(link, link[used]) | (z + radius >= shirt_bottom))
    if len(keep) == geo.n_geoms:
        return model, garment
    renumber = np.full(geo.n_geoms, -1, np.int32)
    renumber[keep] = np.arange(len(keep), dtype=np.int32)
    sub = type(geo)(link=geo.link[keep], kind=geo.kind[keep], pose=geo.pose[keep],
                    size=geo.size[keep], rgba=geo.rgba[keep],
                    names=tuple(geo.names[i] for i in keep))  # fmt: skip
    model = eqx.tree_at(lambda m: m.geometry, model, sub)
    garment = eqx.tree_at(
        lambda g: (g.patch_geom, g.skin),
        garment,
        (jnp.asarray(renumber[np.asarray(garment.patch_geom)]), garment.skin[keep]),
    )
    return model, garment


def _batch_renderer(model: BodyModel, garment: Garment):
    """A jitted ``poses (RENDER_BATCH, n_dof) -> maps`` closed over the (subset) model, so that
    the geom kinds are static (about 1.7x faster than the model as a traced argument)."""
    model, garment = tiny_map_subset(model, garment)
    cam = canonical_camera(jnp.float32)
    return jax.jit(lambda qs: render.tiny_id_maps(model, garment, qs, cam))


def render_maps(
    model: BodyModel, garment: Garment, poses: np.ndarray, progress: bool = True
) -> np.ndarray:
    """Tiny colour-id maps (n, 40, 40) ``uint8`` of database poses seen by the canonical camera,
    ``RENDER_BATCH`` poses per jitted call (vmap inside), with a tqdm progress bar."""
    from tqdm.auto import tqdm

    render_batch = _batch_renderer(model, garment)
    n = len(poses)
    out = np.zeros((n, render.TINY_SIZE, render.TINY_SIZE), np.uint8)
    with tqdm(total=n, desc="pose database", unit="map", disable=not progress) as bar:
        for s in range(0, n, RENDER_BATCH):
            qs = poses[s:s + RENDER_BATCH]
            m = len(qs)
            if m < RENDER_BATCH:
                qs = np.concatenate([qs, np.repeat(qs[-1:], RENDER_BATCH - m, axis=0)])
            out[s:s + m] = np.asarray(render_batch(jnp.asarray(qs)))[:m]
            bar.update(m)
    return out


def build_arrays(
    config: SamplingConfig,
    model: BodyModel,
    garment: Garment,
    progress: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Sample the poses and render their tiny maps: ``(maps uint8 (n,40,40), poses (n, n_dof))``."""
    from ..synth import TRAIN_CLIPS

    pool = source_pool(model, tuple(config.clips or TRAIN_CLIPS))
    poses = sample_poses(config, model, pool)
    return render_maps(model, garment, poses, progress), poses


def save_database(path: str | Path, maps: np.ndarray, poses: np.ndarray, meta: dict) -> Path:
    """Write a database ``.npz`` (compressed) atomically (:mod:`jaxmocap.io.atomic`)."""
    from ..io.atomic import atomic_path

    path = Path(path)
    meta = {**meta, "content_digest": content_digest(maps, poses)}
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, maps=maps, poses=poses, meta=np.array(json.dumps(meta)))
    return path


def content_digest(maps: np.ndarray, poses: np.ndarray) -> str:
    """SHA-256 of a database's arrays (dtype, shape, bytes): recorded in its ``meta`` when
    saved and checked when loaded, so that a file a crash or a disk damaged is detected rather
    than searched."""
    h = hashlib.sha256()
    for a in (maps, poses):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


META_FIELDS = ("key", "n_colours", "dof_names")  # what loading needs from ``meta``


def load_database(path: str | Path, key: str | None = None,
                  model: BodyModel | None = None, garment: Garment | None = None) -> PoseDB:
    """Load a database ``.npz`` written by :func:`save_database`, checking its structure (the
    arrays, the ``meta`` fields), ``key`` if given, and, with ``model``, that its poses are
    of that body (DOF count and names): a database of another body is refused here, not deep
    inside forward kinematics. With ``model`` and ``garment`` it must also have been built for
    exactly them (the digests its ``meta`` records, :func:`check_built_for`). Raises
    :class:`DatabaseError` (one line, file named); ``FileNotFoundError`` if there is no file."""
    from ..io.preflight import read_npz

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(path)
    what = "a pose database .npz of `jaxmocap build-db` (arrays maps, poses, meta)"
    arrays = read_npz(path, what, ("maps", "poses", "meta"), DatabaseError)
    maps, poses = arrays["maps"], arrays["poses"]
    try:
        meta = json.loads(str(arrays["meta"]))
    except (ValueError, RecursionError):
        meta = None
    if not isinstance(meta, dict):
        raise DatabaseError(f"{path}: field 'meta': expected a JSON object ({what})")
    missing = [f for f in META_FIELDS if f not in meta]
    if missing:
        raise DatabaseError(f"{path}: field 'meta.{missing[0]}' missing ({what})")
    if not isinstance(meta["n_colours"], int) or not isinstance(meta["dof_names"], list):
        raise DatabaseError(f"{path}: field 'meta': n_colours must be an integer and dof_names "
                            "a list")
    if poses.ndim != 2 or poses.shape[1] != len(meta["dof_names"]) \
            or not np.issubdtype(poses.dtype, np.floating):
        raise DatabaseError(f"{path}: field 'poses': expected float (n, {len(meta['dof_names'])}) "
                            f"for its {len(meta['dof_names'])} meta.dof_names, got "
                            f"{poses.dtype} {poses.shape}")
    digest = meta.get("content_digest")  # (absent from databases of older versions)
    if digest is not None and digest != content_digest(maps, poses):
        raise DatabaseError(f"{path}: damaged: its maps and poses do not match the digest "
                            "recorded when it was built; build it again (`jaxmocap build-db`)")
    if key is not None and meta.get("key") != key:
        raise DatabaseError(f"{path}: meta.key is {meta.get('key')!r}, expected {key!r}")
    if model is not None:
        names = list(model.chain.dof_names)
        if poses.shape[1] != len(names):
            raise DatabaseError(f"{path}: built for a body with {poses.shape[1]} DOFs, the body "
                                f"has {len(names)}; build a database for this body "
                                "(`jaxmocap build-db`)")
        if [str(n) for n in meta["dof_names"]] != names:
            bad = next(i for i, (a, b) in enumerate(zip(meta["dof_names"], names, strict=True))
                       if a != b)
            raise DatabaseError(f"{path}: DOF {bad} is {meta['dof_names'][bad]!r} in the "
                                f"database, {names[bad]!r} in the body; build a database for "
                                "this body (`jaxmocap build-db`)")
        if garment is not None:
            check_built_for(path, meta, model, garment)
    return make_posedb(maps, poses, int(meta["n_colours"]), key=str(meta["key"]))


def _meta(key: str, config: SamplingConfig, model: BodyModel, garment: Garment) -> dict:
    from ..body import body_digest

    return {"key": key, "code_version": CODE_VERSION, "config": config._asdict(),
            "dof_names": list(model.chain.dof_names), "n_colours": garment.n_colours,
            "colour_names": list(garment.colour_names), "body_digest": body_digest(model),
            "garment_digest": garment_digest(garment)}


def check_built_for(path: str | Path, meta: dict, model: BodyModel, garment: Garment) -> None:
    """Refuse, in one line, a database built for another body or shirt than ``model`` and
    ``garment`` (the digests recorded in its ``meta`` at build time)."""
    from ..body import body_digest

    want = {"body_digest": body_digest(model), "garment_digest": garment_digest(garment)}
    for field, what, option in (("body_digest", "body", "--body"),
                                ("garment_digest", "shirt", "--garment")):  # fmt: skip
        if field not in meta:
            raise DatabaseError(f"{path}: meta has no {field!r} (built by an older jaxmocap); "
                                "rebuild it with `jaxmocap build-db`")  # fmt: skip
        if meta[field] != want[field]:
            raise DatabaseError(
                f"{path}: built for another {what} ({field} {meta[field]}, this {what} "
                f"{want[field]}); rebuild it with `jaxmocap build-db --out FILE.npz` and the "
                f"same --body/--garment as here, or give the {option} it was built for")


def build_database(
    config: SamplingConfig | None = None,
    model: BodyModel | None = None,
    garment: Garment | None = None,
    out: str | Path | None = None,
    progress: bool = True,
) -> PoseDB:
    """Build a pose database (always; see :func:`load_or_build` for the cached one), writing
    it to ``out`` if given. Deterministic given the settings."""
    config = (config or SamplingConfig()).validate()
    model = model or default_body()
    garment = garment or default_garment(model)
    key = database_key(config, model, garment)
    maps, poses = build_arrays(config, model, garment, progress)
    if out is not None:
        save_database(out, maps, poses, _meta(key, config, model, garment))
    return make_posedb(maps, poses, garment.n_colours, key=key)


def cache_path(key: str, cache: str | Path | None = None) -> Path:
    """Where the database with version ``key`` is cached."""
    from .._config import cache_dir

    folder = Path(cache) if cache is not None else cache_dir() / "posedb"
    return folder / f"posedb-{key}.npz"


def load_or_build(
    config: SamplingConfig | None = None,
    model: BodyModel | None = None,
    garment: Garment | None = None,
    cache: str | Path | None = None,
    progress: bool = True,
) -> PoseDB:
    """The cached database for these settings, built and cached on first use."""
    config = (config or SamplingConfig()).validate()
    model = model or default_body()
    garment = garment or default_garment(model)
    key = database_key(config, model, garment)
    if cache is None:  # the user's cache folder: created and tried, refused naming its variable
        from .._config import cache_folder

        cache = cache_folder("posedb")
    path = cache_path(key, cache)
    if path.exists():
        try:
            return load_database(path, key, model)
        except DatabaseError as e:  # a crash or a disk left it damaged: built again, said
            why = str(e).removeprefix(f"{path}: ").split(";")[0]
            print(f"jaxmocap: the cached pose database {path} is damaged ({why}); building it "
                  "again", file=sys.stderr)
            path.unlink(missing_ok=True)
    return build_database(config, model, garment, out=path, progress=progress)
