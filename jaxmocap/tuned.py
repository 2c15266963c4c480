"""The tuned-parameters file: what ``jaxmocap tune`` writes and ``track --tuned``,
``experiment`` (option ``tuned``) and the Python API read.

One JSON file (``tuned.json``) says which tracker the parameters are for, the parameters, the
body and garment they were tuned for (:func:`jaxmocap.body.body_digest`,
:func:`jaxmocap.garment.garment_digest`), what they were tuned on (dataset, split, sequences,
the tracker configuration) and the loss before / after. Arrays are nested lists of floats
(Python's shortest round-trip repr: the file round-trips exactly). Fields::

    {"format": "jaxmocap-tuned-parameters", "version": 1,
     "tracker": "shirt" | "pf",
     "parameters": {...},         # shirt: ik_centroid (2, 2) px^2, ik_blend / ik_prior
                                  #   (n,) variances or (n, n); pf: sigma_g, sigma_d (m)
     "body_digest": "...",        # the body the parameters are defined on
     "transfer": "none" | "role", # none: for that body only; role: defined on the bundled
                                  #   body, carried to any body by role (IK covariances tuned
                                  #   over sequences of different bodies, as the test world's)
     "dof_names": [...],          # of that body (shirt)
     "garment_digest": "..." | null,  # the shirt (null: any / per sequence / pf)
     "tuned_on": {...}, "loss": {...}}

A file whose digests do not match the body / garment in use is refused in one line naming the
file and the field (:class:`TunedFileError`, an :class:`~jaxmocap.errors.InputError`: exit
code 2 from the CLI, before any work). ``--ik-cov`` (an ``.npz`` of
:meth:`jaxmocap.ik.IKCovariances.save`) stays: a tuned file is its generalisation.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

from jaxmocap.errors import InputError

FORMAT = "jaxmocap-tuned-parameters"
VERSION = 1
TRACKERS = ("shirt", "pf")
TRANSFERS = ("none", "role")
PARAMETERS = {"shirt": ("ik_centroid", "ik_blend", "ik_prior"), "pf": ("sigma_g", "sigma_d")}


class TunedFileError(InputError):
    """A tuned-parameters file that is malformed or made for another tracker, body or shirt."""


@dataclass(frozen=True)
class TunedParameters:
    """The content of a tuned-parameters file (module docstring)."""

    tracker: str
    parameters: dict
    body_digest: str
    transfer: str = "none"
    dof_names: tuple[str, ...] = ()
    garment_digest: str | None = None
    tuned_on: dict = field(default_factory=dict)
    loss: dict = field(default_factory=dict)
    path: str = "<tuned parameters>"

    # ----------------------------------------------------------------------------- file

    def to_json(self) -> dict:
        tolist = lambda a: np.asarray(a, np.float64).tolist()
        return {"format": FORMAT, "version": VERSION, "tracker": self.tracker,
                "parameters": {k: tolist(v) for k, v in self.parameters.items()},
                "body_digest": self.body_digest, "transfer": self.transfer,
                "dof_names": list(self.dof_names), "garment_digest": self.garment_digest,
                "tuned_on": self.tuned_on, "loss": self.loss}  # fmt: skip

    def save(self, path: str | os.PathLike) -> None:
        """Write the file atomically (:func:`jaxmocap.io.atomic.write_text`: a temporary
        file beside it, renamed)."""
        from jaxmocap.io.atomic import write_text

        write_text(path, json.dumps(self.to_json(), indent=1) + "\n")

    @classmethod
    def load(cls, path: str | os.PathLike) -> TunedParameters:
        """Read and validate a file (one line naming the file and field on any problem)."""
        from jaxmocap.io.preflight import read_json

        doc = read_json(path, "tuned-parameters file (jaxmocap tune)", TunedFileError)
        bad = lambda f, what: TunedFileError(f"{path}: field {f!r} {what}")
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise bad("format", f"is not {FORMAT!r} (a file of `jaxmocap tune`)")
        if doc.get("version") != VERSION:
            raise bad("version", f"is {doc.get('version')!r}, expected {VERSION}")
        tracker = doc.get("tracker")
        if tracker not in TRACKERS:
            raise bad("tracker", f"is {tracker!r}, expected one of {', '.join(TRACKERS)}")
        transfer = doc.get("transfer", "none")
        if transfer not in TRANSFERS:
            raise bad("transfer", f"is {transfer!r}, expected one of {', '.join(TRANSFERS)}")
        for key in ("body_digest",):
            if not isinstance(doc.get(key), str):
                raise bad(key, "is missing (a 16-digit digest string expected)")
        g = doc.get("garment_digest")
        if g is not None and not isinstance(g, str):
            raise bad("garment_digest", "is not a digest string or null")
        params = doc.get("parameters")
        if not isinstance(params, dict) or set(params) != set(PARAMETERS[tracker]):
            raise bad("parameters", f"must hold exactly {', '.join(PARAMETERS[tracker])} for "
                      f"tracker {tracker!r}")
        out = {}
        for k, v in params.items():
            try:
                a = np.asarray(v, np.float64)
            except (TypeError, ValueError):
                raise bad(f"parameters.{k}", "is not a number or an array of numbers") from None
            if not np.all(np.isfinite(a)):
                raise bad(f"parameters.{k}", "holds a value that is not finite")
            out[k] = a
        _check_values(out, tracker, bad)
        dofs = doc.get("dof_names", [])
        if not isinstance(dofs, list) or not all(isinstance(d, str) for d in dofs):
            raise bad("dof_names", "is not a list of DOF names")
        return cls(tracker, out, doc["body_digest"], transfer, tuple(dofs), g,
                   doc.get("tuned_on") or {}, doc.get("loss") or {}, str(path))

    # ----------------------------------------------------------------------------- use

    def check_for(self, tracker: str, body, garment=None) -> None:
        """Refuse (:class:`TunedFileError`, one line naming the file and field) parameters
        for another tracker, body or shirt than ``body`` / ``garment`` in use."""
        from jaxmocap.body import body_digest, default_body
        from jaxmocap.garment import garment_digest

        if tracker != self.tracker:
            raise TunedFileError(f"{self.path}: field 'tracker' is {self.tracker!r}, the "
                                 f"tracker in use is {tracker!r}")
        if self.transfer == "role":
            ref = body_digest(default_body())
            if self.body_digest != ref:
                raise TunedFileError(
                    f"{self.path}: field 'body_digest' is {self.body_digest}, the bundled body "
                    f"these role-shared parameters are defined on is {ref} (tuned with another "
                    "jaxmocap version); tune again")
            if body.roles is None:
                raise TunedFileError(f"{self.path}: field 'transfer' is 'role', the body in "
                                     "use has no roles (load it with jaxmocap.body.load_body)")
        else:
            have = body_digest(body)
            if have != self.body_digest:
                raise TunedFileError(
                    f"{self.path}: field 'body_digest' is {self.body_digest}, the body in use "
                    f"is {have}; give the --body it was tuned for or tune for this body "
                    "(jaxmocap tune)")
        if self.garment_digest is not None and garment is not None:
            have = garment_digest(garment)
            if have != self.garment_digest:
                raise TunedFileError(
                    f"{self.path}: field 'garment_digest' is {self.garment_digest}, the shirt "
                    f"in use is {have}; give the --garment it was tuned for or tune for this "
                    "shirt (jaxmocap tune)")

    def ik_covariances(self, body):
        """The shirt tracker's IK covariances for ``body`` (carried by role where the file
        says so; check :meth:`check_for` first)."""
        import jax.numpy as jnp

        from jaxmocap.ik import IKCovariances

        if self.tracker != "shirt":
            raise TunedFileError(f"{self.path}: field 'tracker' is {self.tracker!r}, IK "
                                 "covariances are the shirt tracker's")
        p = self.parameters
        cov = IKCovariances(centroid=jnp.asarray(p["ik_centroid"]),
                            blend=jnp.asarray(p["ik_blend"]), prior=jnp.asarray(p["ik_prior"]))
        if self.transfer == "role":
            from jaxmocap.body import default_body
            from jaxmocap.trackers.shirt.covariances import transfer_covariances

            cov, _ = transfer_covariances(cov, default_body(), body)
        elif cov.blend.shape[0] != body.n_dof:
            raise TunedFileError(f"{self.path}: field 'parameters.ik_blend' is for "
                                 f"{cov.blend.shape[0]} DOFs, the body has {body.n_dof}")
        return cov

    def cue_widths(self) -> dict[str, float]:
        """The stereo filter's ``sigma_g``, ``sigma_d`` (settings of
        :class:`jaxmocap.trackers.stereo_pf.Cues`)."""
        if self.tracker != "pf":
            raise TunedFileError(f"{self.path}: field 'tracker' is {self.tracker!r}, cue "
                                 "widths are the stereo filter's (pf)")
        return {k: float(self.parameters[k]) for k in PARAMETERS["pf"]}


def _check_values(p: dict, tracker: str, bad) -> None:
    if tracker == "pf":
        for k in PARAMETERS["pf"]:
            if p[k].shape != () or not p[k] > 0:
                raise bad(f"parameters.{k}", "must be one positive number (metres / edge units)")
        return
    c = p["ik_centroid"]
    if c.shape != (2, 2) or not _spd(c):
        raise bad("parameters.ik_centroid", "must be a positive definite (2, 2) matrix")
    n = None
    for k in ("ik_blend", "ik_prior"):
        a = p[k]
        ok = (a.ndim == 1 and np.all(a > 0)) or (a.ndim == 2 and a.shape[0] == a.shape[1]
                                                  and _spd(a))
        if not ok or (n is not None and a.shape[0] != n):
            raise bad(f"parameters.{k}", "must be positive variances (n,) or a positive "
                      "definite (n, n) matrix, the same n for ik_blend and ik_prior")
        n = a.shape[0]


def _spd(a: np.ndarray) -> bool:
    try:
        return bool(np.allclose(a, a.T) and np.linalg.eigvalsh(a).min() > 0)
    except np.linalg.LinAlgError:
        return False


def load_tuned(path: str | os.PathLike, tracker: str, body, garment=None) -> TunedParameters:
    """Read ``path`` and check it against the tracker, body and garment in use (the Python
    API of ``track --tuned``)."""
    t = TunedParameters.load(path)
    t.check_for(tracker, body, garment)
    return t


def finite_or_none(x) -> float | None:
    """A JSON-safe float (None for NaN / inf)."""
    return float(x) if x is not None and math.isfinite(float(x)) else None


__all__ = ["FORMAT", "TunedFileError", "TunedParameters", "finite_or_none", "load_tuned"]
