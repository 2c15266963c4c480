"""The trained observation model's file: one JSON header line, then the weights as
``equinox.tree_serialise_leaves`` writes them (equinox's serialisation pattern: the header's
hyper-parameters rebuild the skeleton first, then the leaves are read into it).

The header records what the model was trained for and on (issue 49 item 6): the body's and the
garment's digests (a model for another body or garment is refused in one line), the class
names, the training data (how many rendered poses, scribbled pixels), the settings, the steps,
the loss curve and the wall time. Written atomically (:mod:`jaxmocap.io.atomic`).
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import equinox as eqx
import jax

from jaxmocap.body import BodyModel
from jaxmocap.body.roles import body_digest
from jaxmocap.errors import InputError
from jaxmocap.garment import Garment, garment_digest

from .model import Observer

FORMAT = "jaxmocap-observer"
VERSION = 1
WHAT = "a trained observation model of `jaxmocap learn`"


class ObserverFileError(InputError):
    """A model file that is not one, is damaged, or was trained for another body or garment."""


def save(path: str | Path, model: Observer, header: dict) -> Path:
    """Write ``model`` with ``header`` (plus format, version and hyper-parameters) atomically."""
    from jaxmocap.io.atomic import atomic_write

    from .model import hyper

    head = dict(format=FORMAT, version=VERSION, hyper=hyper(model), **header)
    buf = io.BytesIO()
    eqx.tree_serialise_leaves(buf, model)
    path = Path(path)
    with atomic_write(path, "wb") as f:
        f.write(json.dumps(head).encode() + b"\n")
        f.write(buf.getvalue())
    return path


def read_header(path: str | Path) -> dict:
    """The header of a model file (refused in one line if it is not one)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            line = f.readline(1 << 20)
    except OSError as e:
        raise ObserverFileError(f"{path}: cannot be read ({e.strerror}); expected {WHAT}") from None
    try:
        head = json.loads(line)
    except (ValueError, UnicodeDecodeError):
        head = None
    if not isinstance(head, dict) or head.get("format") != FORMAT:
        raise ObserverFileError(f"{path}: not {WHAT} (no '{FORMAT}' header line)")
    if head.get("version") != VERSION:
        raise ObserverFileError(f"{path}: field 'version' is {head.get('version')!r}, expected "
                                f"{VERSION}; train it again with `jaxmocap learn`")
    hyp = head.get("hyper")
    if not isinstance(hyp, dict) or not all(isinstance(hyp.get(k), int) and hyp[k] > 0
                                            for k in ("n_classes", "width", "context")):
        raise ObserverFileError(f"{path}: field 'hyper': expected positive integers n_classes, "
                                "width, context")
    return head


def load(path: str | Path, model: BodyModel | None = None, garment: Garment | None = None
         ) -> tuple[Observer, dict]:
    """``(observer, header)`` from a file of :func:`save`; with ``model`` / ``garment`` the file
    must have been trained for exactly them (their digests), else it is refused in one line."""
    path = Path(path)
    head = read_header(path)
    for what, obj, digest in (("body", model, body_digest), ("garment", garment, garment_digest)):
        if obj is None:
            continue
        want, have = digest(obj), head.get(f"{what}_digest")
        if want != have:
            raise ObserverFileError(
                f"{path}: trained for another {what} ({what}_digest {have!r}, this {what} is "
                f"{want!r}); train one for it with `jaxmocap learn`")
    skeleton = Observer(key=jax.random.key(0), **head["hyper"])
    with open(path, "rb") as f:
        f.readline(1 << 20)
        try:
            obs = eqx.tree_deserialise_leaves(f, skeleton)
        except Exception as e:  # a truncated or altered weight block: any error of the reader
            raise ObserverFileError(f"{path}: its weights do not read ({type(e).__name__}); "
                                    "the file is damaged: train it again") from None
        if f.read(1):
            raise ObserverFileError(f"{path}: bytes after the weights; the file is damaged")
    return obs, head
