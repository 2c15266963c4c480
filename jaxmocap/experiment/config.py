"""The experiment's inputs, validated before any work: the configuration file and the dataset.

**Configuration file** (TOML, or JSON with the same structure)::

    [experiment]                 # optional
    good_cm = 5.0                # a frame "< good_cm" counts as tracked well (issue 17)
    bad_cm = 15.0                # a frame "> bad_cm" should be flagged invalid (issue 17)

    [[config]]
    name = "shirt-full"          # [A-Za-z0-9_.-]+, unique
    method = "shirt"             # shirt (Wang et al. 2011) | pf (Azad et al. 2007)
    seeds = [0]                  # default [0]
    body = "bodies/other.urdf"   # optional; default the bundled body; "sequence": each
                                 # sequence folder's own body.urdf (the test world's)
    garment = "garment.json"     # optional (shirt only); default the paper's shirt on the
                                 # body; "sequence": each sequence folder's garment.json
    joints = ["l_elbow", ...]    # optional; default the method's evaluated joints
    [config.options]             # tracker parameters (below)
    pose_prior = false

Relative paths are relative to the configuration file. Tracker options:

* ``shirt``: every field of the settings groups of :func:`jaxmocap.trackers.shirt.make_params`
  by name (:class:`~jaxmocap.trackers.shirt.Search`, :class:`~jaxmocap.trackers.shirt.Rounds`,
  :class:`~jaxmocap.trackers.shirt.Colours`, :class:`~jaxmocap.trackers.shirt.Ablations`,
  and the keywords of :func:`~jaxmocap.trackers.shirt.validity_rule`; e.g. the paper's
  ablations ``pose_prior``, ``adaptive_white_balance``, ``ik_passes``, ``min_agreement``), plus
  ``covariances`` (``"trained"`` the bundled ones (default), ``"isotropic"`` 2 px / 0.3 / 0.5,
  or an ``.npz`` of :meth:`jaxmocap.ik.IKCovariances.save`), ``tuned`` (a tuned-parameters
  file of ``jaxmocap tune``, :mod:`jaxmocap.tuned`: its IK covariances, instead of
  ``covariances``), ``db`` (a pose database ``.npz``)
  or ``db_size`` (the cached database of that many poses; default the 80,000 of the paper),
  ``colors`` / ``white_balance`` (files of ``jaxmocap colors``; ``colors = "scribbles"``: fitted
  from scribbles on the sequence's own first frames (its ground-truth colour ids eroded, as a
  user scribbles a capture: needed for footage of another renderer); default: the set-up of
  :func:`jaxmocap.trackers.shirt.setup_for_sequence` from the dataset's first-frame colour ids),
  ``background`` (OpenCV MOG2 masks, as ``shirt.run(background=True)``) and
  ``scene_clusters`` (k > 0: Gaussians of the room from the scribble frames' non-shirt pixels,
  ``Colours(scene_colors=)``; with ``colors = "scribbles"`` and ``shading`` the colour
  model is fitted for the shading-invariant distance);
* ``pf``: every field of the settings groups of :func:`jaxmocap.trackers.stereo_pf.make_params`
  by name (:class:`~jaxmocap.trackers.stereo_pf.Motion`, ``Cues``, ``Proposals``,
  ``Initialisation``, ``Images`` but its ``segment`` and ``colors``: ``n_particles`` or its
  alias ``particles``, ``swivel_fraction``, ``guided``, ``use_distance``, ``sigma_g``, ...),
  plus ``azad`` (Azad's filter,
  :data:`~jaxmocap.trackers.stereo_pf.AZAD_FILTER`, under the other options), ``skin``
  (``"synth"`` the renderer's skin interval (default), ``"default"`` Azad's HSV intervals,
  ``"scribbles"`` the capture's skin and shirt colours (:mod:`jaxmocap.pf.colors`) fitted
  from scribbles on its first frames -- the shirt's ground-truth colour ids eroded, a disc on
  the face around the projected head keypoint -- or ``"auto"`` calibrated from the first
  frames without labels, :func:`jaxmocap.pf.colors.calibrate_from_frames`), ``blob_params``
  (``"tracker"`` :data:`~jaxmocap.trackers.stereo_pf.BLOB_PARAMS` (default) or ``"azad"``),
  ``smooth_lag``, ``validity`` (default true: frames flagged by
  :func:`~jaxmocap.trackers.stereo_pf.frame_validity`; false: every finite frame is valid)
  ``tuned`` (a tuned-parameters file of ``jaxmocap tune``: its cue widths sigma_g, sigma_d)
  and ``start_from_head`` (default true; false: the filter never starts from the triangulated
  head but from the shirt silhouette or the hands, :mod:`jaxmocap.trackers.stereo_pf.start`,
  to measure that start where the head is found).

**Dataset**: a folder written by ``jaxmocap synth`` (``scene.json``, ``cameras.json``,
``groundtruth.npz``, videos / PNG folders), or a folder whose sub-folders are such folders.
``--split FILE`` restricts the sequences to a list in a JSON file: a list of names (sub-folder
paths relative to the dataset), or an object of such lists (``--subset`` picks one, e.g.
``dev`` / ``test``); list items may also be objects with a ``name``, ``folder`` or ``path``.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import re
import tomllib
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from jaxmocap.errors import InputError

__all__ = [
    "ExperimentConfig",
    "ExperimentError",
    "Sequence",
    "TrackerConfig",
    "dataset_sequences",
    "tracker_settings",
    "digest_folder",
    "load_config",
]

GOOD_CM = 5.0  # issue 17: >= 90% of the frames < 5 cm off should be flagged valid
BAD_CM = 15.0  # issue 17: >= 95% of the frames > 15 cm off should be flagged invalid
METHODS = ("shirt", "pf")
SEQUENCE = "sequence"  # body / garment: the sequence folder's own body.urdf / garment.json
NAME_RE = re.compile(r"^[A-Za-z0-9_.-]+$")
TOP_KEYS = {"experiment", "config"}
EXPERIMENT_KEYS = {"good_cm", "bad_cm"}
CONFIG_KEYS = {"name", "method", "seeds", "body", "garment", "joints", "options"}
# options the experiment interprets itself (beside the trackers' make_params keywords)
SHIRT_EXTRA = {"covariances": (str,), "db": (str,), "db_size": (int,), "colors": (str,),
               "white_balance": (str,), "background": (bool,), "scene_clusters": (int,),
               "tuned": (str,), "observer": (str,)}
PF_EXTRA = {"particles": (int,), "azad": (bool,), "skin": (str,), "blob_params": (str,),
            "smooth_lag": (int,), "validity": (bool,), "search": (str,),
            "start_from_head": (bool,), "tuned": (str,), "observer": (str,)}
PF_SEARCH = ("off", "head", "hands", "all")  # stereo_pf.search: the entities searched
SHIRT_RESERVED = {"scene_colors", "dtype", "observer"}  # set by the experiment (scene_clusters,
# observer: "learn" or a model file) / the cameras
PF_RESERVED = {"segment", "colors"}  # set by the experiment (skin; "learned": observer)
PF_SKINS = ("synth", "default", "scribbles", "auto", "learned")
PATH_OPTIONS = ("covariances", "db", "colors", "white_balance", "tuned")


class ExperimentError(InputError):
    """A configuration file, dataset folder or split file that cannot be used."""


@dataclass(frozen=True)
class TrackerConfig:
    """One named tracker configuration (module docstring); paths absolute."""

    name: str
    method: str
    seeds: tuple[int, ...]
    body: str | None = None
    garment: str | None = None
    joints: tuple[str, ...] | None = None
    options: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"name": self.name, "method": self.method, "seeds": list(self.seeds),
                "body": self.body, "garment": self.garment,
                "joints": None if self.joints is None else list(self.joints),
                "options": dict(self.options)}


@dataclass(frozen=True)
class ExperimentConfig:
    configs: tuple[TrackerConfig, ...]
    good_cm: float = GOOD_CM
    bad_cm: float = BAD_CM
    path: str = ""


@dataclass(frozen=True)
class Sequence:
    name: str  # unique, used in cell folder names ("/" -> "_")
    folder: str  # absolute


# ----------------------------------------------------------------------------- config file


def _file_digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def _groups(method: str) -> dict:
    """The settings groups of ``method``'s ``make_params``: {keyword: constructor}."""
    if method == "shirt":
        from jaxmocap.trackers import shirt as mod

        return {"search": mod.Search, "rounds": mod.Rounds, "colours": mod.Colours,
                "ablations": mod.Ablations, "validity": mod.validity_rule}
    from jaxmocap.trackers import stereo_pf as mod

    return {"motion": mod.Motion, "cues": mod.Cues, "proposals": mod.Proposals,
            "initialisation": mod.Initialisation, "images": mod.Images}


def _option_table(method: str) -> tuple[dict[str, tuple[str, inspect.Parameter]], dict]:
    """The accepted options of ``method``: every field of its settings groups by name
    (unique across the groups), as ``{option: (group, parameter)}``, and the extras."""
    reserved, extra = (SHIRT_RESERVED, SHIRT_EXTRA) if method == "shirt" else \
        (PF_RESERVED, PF_EXTRA)
    table = {}
    for group, make in _groups(method).items():
        for k, p in inspect.signature(make).parameters.items():
            if k not in reserved:
                assert k not in table, f"{method}: option {k!r} in two groups"
                table[k] = (group, p)
    return table, extra


def tracker_settings(method: str, options: dict, base: dict | None = None) -> dict:
    """``make_params`` keywords from a configuration's tracker options (without the extras):
    each option set on its group (:func:`_option_table`), over ``base``'s group where it has
    one (e.g. :data:`~jaxmocap.trackers.stereo_pf.AZAD_FILTER`); lists become tuples."""
    import dataclasses

    table, _ = _option_table(method)
    makers = _groups(method)
    fields: dict[str, dict] = {}
    for k, v in options.items():
        fields.setdefault(table[k][0], {})[k] = tuple(v) if isinstance(v, list) else v
    out = dict(base or {})
    for group, kw in fields.items():
        out[group] = dataclasses.replace(out[group], **kw) if group in out and \
            dataclasses.is_dataclass(out[group]) else makers[group](**kw)
    return out


def _type_ok(value, default) -> bool:
    """Whether a TOML/JSON ``value`` fits a keyword whose default is ``default``."""
    if isinstance(default, bool):
        return isinstance(value, bool)
    if isinstance(default, int) and not isinstance(default, bool):
        return isinstance(value, int) and not isinstance(value, bool)
    if isinstance(default, float):
        return isinstance(value, int | float) and not isinstance(value, bool)
    if isinstance(default, tuple | list):
        return isinstance(value, list)
    if default is None:  # float | None, Sequence | None: anything scalar or a list
        return isinstance(value, int | float | list | str) and not isinstance(value, bool)
    if isinstance(default, str):
        return isinstance(value, str)
    return True


def _check_options(where: str, method: str, options: dict, base: Path) -> dict:
    params, extra = _option_table(method)
    out = {}
    for k, v in options.items():
        if k in extra:
            if not isinstance(v, extra[k]) or (extra[k] == (int,) and isinstance(v, bool)):
                raise ExperimentError(f"{where}.options.{k}: expected "
                                      f"{extra[k][0].__name__}, got {v!r}")
        elif k in params:
            d = params[k][1].default
            if d is inspect.Parameter.empty or not _type_ok(v, d):
                raise ExperimentError(f"{where}.options.{k}: expected a value like {d!r}, "
                                      f"got {v!r}")
        else:
            known = sorted(set(params) | set(extra))
            raise ExperimentError(f"{where}.options: unknown option {k!r} for method "
                                  f"{method!r}; expected one of {', '.join(known)}")
        out[k] = v
    if method == "shirt":
        if "db" in out and "db_size" in out:
            raise ExperimentError(f"{where}.options: give db or db_size, not both")
        if "db_size" in out and not 1 <= out["db_size"] <= 500_000:
            raise ExperimentError(f"{where}.options.db_size: expected 1..500000, "
                                  f"got {out['db_size']}")
        cov = out.get("covariances", "trained")
        if cov not in ("trained", "isotropic"):
            out["covariances"] = cov
        if "tuned" in out and "covariances" in out:
            raise ExperimentError(f"{where}.options: give tuned (a file of `jaxmocap tune`) or "
                                  "covariances, not both")
        for k in PATH_OPTIONS:
            if k in out and not (k == "covariances" and out[k] in ("trained", "isotropic")) \
                    and not (k == "colors" and out[k] == "scribbles"):
                p = (base / out[k]).resolve()
                if not p.is_file():
                    raise ExperimentError(f"{where}.options.{k}: no such file {p}")
                out[k] = str(p)
    else:
        if "tuned" in out:
            p = (base / out["tuned"]).resolve()
            if not p.is_file():
                raise ExperimentError(f"{where}.options.tuned: no such file {p}")
            out["tuned"] = str(p)
            if {"sigma_g", "sigma_d"} & set(out):
                raise ExperimentError(f"{where}.options: give tuned (a file of `jaxmocap tune`) "
                                      "or sigma_g / sigma_d, not both")
        if "particles" in out and "n_particles" in out:
            raise ExperimentError(f"{where}.options: give particles or n_particles, not both")
        n = out.get("particles", out.get("n_particles", 2))
        if n < 2:
            raise ExperimentError(f"{where}.options.particles: expected >= 2, got {n}")
        if out.get("skin", "synth") not in PF_SKINS:
            raise ExperimentError(f"{where}.options.skin: expected one of "
                                  f"{', '.join(PF_SKINS)}, got {out['skin']!r}")
        if out.get("adapt_colors") and out.get("skin", "synth") not in ("scribbles", "auto"):
            raise ExperimentError(f"{where}.options.adapt_colors: adapts the capture's colours; "
                                  "expected skin = 'scribbles' or 'auto', got "
                                  f"{out.get('skin', 'synth')!r}")
        if out.get("search", "off") not in PF_SEARCH:
            raise ExperimentError(f"{where}.options.search: expected one of "
                                  f"{', '.join(PF_SEARCH)}, got {out['search']!r}")
        if out.get("search", "off") != "off" and out.get("skin", "synth") not in ("scribbles",
                                                                                 "auto"):
            raise ExperimentError(f"{where}.options.search: searches with the capture's "
                                  "colours; expected skin = 'scribbles' or 'auto'")
        if out.get("search", "off") != "off" and out.get("adapt_colors"):
            raise ExperimentError(f"{where}.options: give search or adapt_colors, not both")
        if out.get("search", "off") != "off" and out.get("hand_search"):
            raise ExperimentError(f"{where}.options: give search or hand_search, not both")
        if out.get("blob_params", "tracker") not in ("tracker", "azad"):
            raise ExperimentError(f"{where}.options.blob_params: expected 'tracker' or "
                                  f"'azad', got {out['blob_params']!r}")
        if out.get("smooth_lag", 0) < 0:
            raise ExperimentError(f"{where}.options.smooth_lag: expected >= 0, "
                                  f"got {out['smooth_lag']}")
    return out


def _check_body_garment(where: str, method: str, body, garment, base: Path):
    """Body / garment files: resolved paths, or ``"sequence"`` (each sequence's own
    ``body.urdf`` / ``garment.json``, as the test world writes them); a garment is refused in
    one line for a tracker that takes none."""
    out = []
    for key, value in (("body", body), ("garment", garment)):
        if value is None or value == SEQUENCE:
            out.append(value)
            continue
        if not isinstance(value, str):
            raise ExperimentError(f"{where}.{key}: expected a file path or "
                                  f"{SEQUENCE!r}, got {value!r}")  # fmt: skip
        p = (base / value).resolve()
        if not p.is_file():
            raise ExperimentError(f"{where}.{key}: no such file {p}")
        out.append(str(p))
    body, garment = out
    if garment is not None and method != "shirt":
        raise ExperimentError(f"{where}.garment: method {method!r} takes no garment "
                              "(the stereo filter sees a single-colour shirt)")
    return body, garment


def _parse(path: Path) -> dict:
    from jaxmocap.io.preflight import MAX_JSON_DEPTH, parse_json, read_text

    what = "an experiment configuration (.toml or .json), format in docs/USER_GUIDE.md"
    text = read_text(path, what, ExperimentError)
    if path.suffix.lower() == ".json":
        doc = parse_json(text, path, what, ExperimentError)
    else:
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise ExperimentError(f"{path}: not valid TOML: {str(e).splitlines()[0]}") from None
        except RecursionError:
            raise ExperimentError(f"{path}: TOML nested too deeply (more than {MAX_JSON_DEPTH} "
                                  f"levels; expected {what})") from None
    if not isinstance(doc, dict):
        raise ExperimentError(f"{path}: expected a table with a 'config' list")
    return doc


def load_config(path: str | Path) -> ExperimentConfig:
    """Read and validate a configuration file (module docstring); raises
    :class:`ExperimentError` naming the file and field."""
    path = Path(path).resolve()
    doc = _parse(path)
    unknown = set(doc) - TOP_KEYS
    if unknown:
        raise ExperimentError(f"{path}: unknown top-level key(s) {sorted(unknown)}; expected "
                              "'experiment' and 'config'")
    exp = doc.get("experiment", {})
    if not isinstance(exp, dict) or set(exp) - EXPERIMENT_KEYS:
        raise ExperimentError(f"{path}: experiment: expected a table with keys "
                              f"{sorted(EXPERIMENT_KEYS)}")
    good, bad = exp.get("good_cm", GOOD_CM), exp.get("bad_cm", BAD_CM)
    for k, v in (("good_cm", good), ("bad_cm", bad)):
        if isinstance(v, bool) or not isinstance(v, int | float) or not v > 0:
            raise ExperimentError(f"{path}: experiment.{k}: expected a positive number, "
                                  f"got {v!r}")
    if good > bad:
        raise ExperimentError(f"{path}: experiment: good_cm {good} > bad_cm {bad}")
    items = doc.get("config")
    if not isinstance(items, list) or not items:
        raise ExperimentError(f"{path}: config: expected a non-empty list of tracker "
                              "configurations ([[config]] tables)")
    configs, names = [], set()
    for i, item in enumerate(items):
        where = f"{path}: config[{i}]"
        if not isinstance(item, dict):
            raise ExperimentError(f"{where}: expected a table")
        bad_keys = set(item) - CONFIG_KEYS
        if bad_keys:
            raise ExperimentError(f"{where}: unknown key(s) {sorted(bad_keys)}; expected "
                                  f"{sorted(CONFIG_KEYS)}")
        name = item.get("name")
        if not isinstance(name, str) or not NAME_RE.match(name):
            raise ExperimentError(f"{where}.name: expected a name of letters, digits, '_', '.', "
                                  f"'-', got {name!r}")
        if name in names:
            raise ExperimentError(f"{where}.name: {name!r} is used twice")
        names.add(name)
        where = f"{path}: config '{name}'"
        method = item.get("method")
        if method not in METHODS:
            raise ExperimentError(f"{where}.method: expected one of {METHODS}, got {method!r}")
        seeds = item.get("seeds", [0])
        if (not isinstance(seeds, list) or not seeds or len(set(map(str, seeds))) != len(seeds)
                or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0
                           for s in seeds)):
            raise ExperimentError(f"{where}.seeds: expected a list of distinct integers >= 0, "
                                  f"got {seeds!r}")
        joints = item.get("joints")
        if joints is not None and (not isinstance(joints, list) or not joints
                                   or not all(isinstance(j, str) for j in joints)):
            raise ExperimentError(f"{where}.joints: expected a list of keypoint names")
        options = item.get("options", {})
        if not isinstance(options, dict):
            raise ExperimentError(f"{where}.options: expected a table")
        body, garment = _check_body_garment(where, method, item.get("body"),
                                            item.get("garment"), path.parent)
        if joints is not None and body is None:
            from jaxmocap.body import KEYPOINT_NAMES

            missing = [j for j in joints if j not in KEYPOINT_NAMES]
            if missing:
                raise ExperimentError(f"{where}.joints: {missing} are not keypoints of the "
                                      f"bundled body ({', '.join(KEYPOINT_NAMES)})")
        configs.append(TrackerConfig(
            name=name, method=method, seeds=tuple(seeds), body=body, garment=garment,
            joints=None if joints is None else tuple(joints),
            options=_check_options(where, method, options, path.parent)))
    return ExperimentConfig(tuple(configs), float(good), float(bad), str(path))


def config_hash(cfg: TrackerConfig, good_cm: float, bad_cm: float) -> str:
    """What a cell's result depends on besides the data: the configuration (files by their
    content) and the thresholds. A cell with another hash is recomputed."""
    doc = cfg.to_dict()
    doc.pop("seeds")
    for key in ("body", "garment"):  # "sequence": the files are in the dataset's digest
        if doc[key] and doc[key] != SEQUENCE:
            doc[key] = _file_digest(Path(doc[key]))
    opts = doc["options"]
    for k in PATH_OPTIONS:
        if k in opts and Path(str(opts[k])).is_file():
            opts[k] = _file_digest(Path(opts[k]))
    doc["thresholds"] = [good_cm, bad_cm]
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


# ----------------------------------------------------------------------------- dataset


def _is_sequence(folder: Path) -> bool:
    return (folder / "scene.json").is_file()


def _split_names(split: Path, subset: str | None) -> list[str]:
    from jaxmocap.io.preflight import read_json

    doc = read_json(split, "a split file: a JSON list of sequence names, or an object of "
                    "such lists", ExperimentError)
    if isinstance(doc, dict):
        lists = {k: v for k, v in doc.items() if isinstance(v, list)}
        if subset is None:
            raise ExperimentError(f"{split}: holds the subsets {sorted(lists)}; choose one "
                                  "with --subset")
        if subset not in lists:
            raise ExperimentError(f"{split}: no subset {subset!r}; expected one of "
                                  f"{sorted(lists)}")
        doc = lists[subset]
    elif subset is not None:
        raise ExperimentError(f"{split}: a plain list has no subsets; drop --subset {subset}")
    if not isinstance(doc, list) or not doc:
        raise ExperimentError(f"{split}: expected a non-empty list of sequence names")
    names = []
    for i, item in enumerate(doc):
        if isinstance(item, dict):
            item = next((item[k] for k in ("name", "folder", "path") if k in item), None)
        if not isinstance(item, str) or not item:
            raise ExperimentError(f"{split}: item {i}: expected a sequence name or an object "
                                  "with 'name', 'folder' or 'path'")
        names.append(item)
    return names


def dataset_sequences(dataset: str | Path, split: str | Path | None = None,
                      subset: str | None = None) -> list[Sequence]:
    """The sequences of a dataset folder (module docstring), sorted by name (split order
    when a split file is given)."""
    root = Path(dataset).resolve()
    if not root.is_dir():
        raise ExperimentError(f"{root}: not a dataset folder (does not exist or is a file)")
    if split is not None:
        names = _split_names(Path(split), subset)
        seqs = []
        for n in names:
            f = (root / n).resolve()
            if not _is_sequence(f):
                raise ExperimentError(f"{split}: sequence {n!r}: {f} is not a dataset folder "
                                      "(no scene.json)")
            seqs.append(Sequence(n.replace("/", "_"), str(f)))
    elif subset is not None:
        raise ExperimentError("--subset needs --split FILE")
    elif _is_sequence(root):
        seqs = [Sequence(root.name, str(root))]
    else:
        seqs = [Sequence(f.name, str(f)) for f in sorted(root.iterdir()) if _is_sequence(f)]
        if not seqs:
            raise ExperimentError(f"{root}: no scene.json in it nor in any sub-folder; expected "
                                  "a `jaxmocap synth` folder or a folder of them")
    dup = {s.name for s in seqs if sum(t.name == s.name for t in seqs) > 1}
    if dup:
        raise ExperimentError(f"{split or root}: sequence name(s) {sorted(dup)} listed twice")
    return seqs


def digest_folder(folder: str | Path) -> str:
    """Content digest of a sequence folder (every file's relative path and bytes)."""
    h = hashlib.sha256()
    root = Path(folder)
    for p in sorted(root.rglob("*")):
        if p.is_file() and not p.name.startswith("."):
            h.update(str(p.relative_to(root)).encode() + b"\0")
            with open(p, "rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    h.update(chunk)
    return h.hexdigest()[:16]


def groundtruth_keys(folder: str | Path) -> set[str]:
    """The arrays a sequence's ``groundtruth.npz`` holds (without reading them)."""
    path = Path(folder) / "groundtruth.npz"
    try:
        with np.load(path, allow_pickle=False) as z:
            return set(z.files)
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as e:
        why = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ExperimentError(f"{path}: missing or not a readable .npz ({why})") from None
