"""On-line adaptation of the stereo particle filter's colour model (issue 18; not in Azad et al.).

The capture's skin and shirt classes (:mod:`jaxmocap.pf.colors`) are fitted once, on the first
frames. Where the lighting of the subject changes during the capture (a lamp switched off, the
head turning under a spot lamp, a shadow) the face leaves the skin class and the head is no
longer triangulated (dev split of the independent test world: pf_03 loses the face from frame
23 on, d^2 ~30-50 to the fitted class). :func:`observe_adaptive` runs the filter alongside the
host's image line and re-fits the classes (:func:`jaxmocap.pf.colors.adapt_capture_colors`,
exponential forgetting) from the tracked subject's pixels:

* **confident frame**: the head is triangulated and the filter's head is within
  :data:`~jaxmocap.trackers.stereo_pf.checks.VALID_HEAD_M` of it (the head blob is the model's
  head, not a prop): skin from a disc of :data:`ADAPT_HEAD_M` around the triangulated head in
  each view, shirt from the box of the estimate's projected keypoints;
* otherwise nothing is adapted. (Adapting also from the filter's own head on the frames
  shortly after a confident one, where the head is not triangulated, made the skin class
  drift onto the room on the dev split: pf_06 30 -> 127 cm.)

The colour guards of :func:`~jaxmocap.pf.colors.adapt_capture_colors` keep the classes off the
room and off an occluder passing in front of the head. Frame t is observed with the colours
adapted up to frame t - 1; the filter's trajectory over the observations is the one
:func:`jaxmocap.trackers.stereo_pf.run` computes from the same initialisation.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray, UInt8

from jaxmocap import blobs as bloblib
from jaxmocap.body import keypoint_index, keypoints
from jaxmocap.camera import project, to_camera
from jaxmocap.errors import InputError
from jaxmocap.pf.colors import adapt_capture_colors
from jaxmocap.pf.cues import Observation
from jaxmocap.trackers.stereo_pf.checks import VALID_HEAD_M
from jaxmocap.trackers.stereo_pf.filter import compile_step, online_frame
from jaxmocap.trackers.stereo_pf.observation import observe
from jaxmocap.trackers.stereo_pf.params import BLOB_PARAMS, StereoPFParams

ADAPT_HEAD_M = 0.06  # radius (m) of the disc taken as face pixels around the head keypoint
BODY_MARGIN_PX = 4  # margin of the projected keypoints' box taken as shirt candidates


def _masks(cams, centre: np.ndarray, kp: np.ndarray | None, shape: tuple[int, int]):
    """Per view: the disc of :data:`ADAPT_HEAD_M` around ``centre`` (world, m) and, with
    ``kp`` (k, 3) keypoints, their projected box plus :data:`BODY_MARGIN_PX`."""
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    heads, bodies = [], []
    for i in range(cams.K.shape[0]):
        cam = jax.tree.map(lambda a, i=i: a[i], cams)
        z = float(to_camera(cam, jnp.asarray(centre))[2])
        u, v = np.asarray(project(cam, jnp.asarray(centre)), np.float64)
        r = ADAPT_HEAD_M * float(cam.K[0, 0]) / max(z, 1e-3) if z > 0 else 0.0
        heads.append((xx - u) ** 2 + (yy - v) ** 2 <= r * r)
        if kp is not None:
            uv = np.asarray(project(cam, jnp.asarray(kp)), np.float64)
            lo = uv.min(0) - BODY_MARGIN_PX
            hi = uv.max(0) + BODY_MARGIN_PX
            bodies.append((xx >= lo[0]) & (xx <= hi[0]) & (yy >= lo[1]) & (yy <= hi[1]))
    return heads, (bodies if kp is not None else None)


def observe_adaptive(
    params: StereoPFParams,
    key: PRNGKeyArray,
    frames: UInt8[np.ndarray, "t 2 h w 3"],
    blob_params: bloblib.BlobParams | None = None,
) -> tuple[Observation, dict[str, np.ndarray]]:
    """:func:`~jaxmocap.trackers.stereo_pf.observe_sequence` with the colour model re-fitted
    on line (module docstring; ``params.adapt`` = (skin rate, shirt rate, spread cap)). The
    filter runs alongside from the first frame with a triangulated head (initialised there as
    :func:`~jaxmocap.trackers.stereo_pf.track` does, then stepped from frame 0).

    Returns the stacked observations and a log: ``confident`` (T,) the frames adapted from;
    ``skin_px`` / ``shirt_px`` (T,) pixels used; ``skin_mean`` (T, 3) the skin class
    after the frame's update."""
    if params.adapt is None or params.colors is None:
        raise InputError("stereo_pf.adapt.observe_adaptive: params without adapt_colors "
                            "(make_params(images=Images(colors=..., adapt_colors=True)))")
    skin_rate, shirt_rate, spread = params.adapt
    model = params.model
    head_i = keypoint_index(model, "head")[0]
    kp_fn = jax.jit(lambda q: keypoints(model, q))
    cams = params.likelihood.cams
    step = compile_step(params)
    blob_state = bloblib.init(blob_params or BLOB_PARAMS)
    colors = params.colors
    n = len(frames)
    log = {"confident": np.zeros(n, bool), "skin_px": np.zeros(n, np.int64),
           "shirt_px": np.zeros(n, np.int64), "skin_mean": np.zeros((n, 3))}  # fmt: skip
    out: list[Observation] = []
    state = None
    for t in range(n):
        obs, blob_state = observe(dataclasses.replace(params, colors=colors), frames[t],
                                     blob_state)
        out.append(obs)
        valid = np.asarray(obs.valid)
        state, est = online_frame(params, key, step, state, out, obs)
        if est is None:
            log["skin_mean"][t] = np.asarray(colors.skin.mean)
            continue
        q = np.asarray(est.q)
        if np.all(np.isfinite(q)):
            kp = np.asarray(kp_fn(jnp.asarray(q)), np.float64)
            pts = np.asarray(obs.points, np.float64)
            if valid[0] and np.linalg.norm(kp[head_i] - pts[0]) <= VALID_HEAD_M:
                log["confident"][t] = True
                heads, bodies = _masks(cams, pts[0], kp, frames.shape[2:4])
                colors, n_sk, n_sh = adapt_capture_colors(
                    colors, list(frames[t]), heads, bodies, skin_rate, shirt_rate, params.colors,
                    spread
                )
                log["skin_px"][t], log["shirt_px"][t] = n_sk, n_sh
        log["skin_mean"][t] = np.asarray(colors.skin.mean)
    return jax.tree.map(lambda *a: jnp.stack(a), *out), log
