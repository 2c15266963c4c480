"""The capture-session set-up of Wang et al. 2011 §5.1 for a rendered sequence: scribbles,
the colour model from white-light renders, the initial white balance ``W0``."""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, UInt8

from jaxmocap.body import BodyModel
from jaxmocap.camera import Camera
from jaxmocap.color import (
    ColorModel,
)
from jaxmocap.garment import Garment
from jaxmocap.ik import (
    IKCovariances,
)
from jaxmocap.posedb._search import PoseDB
from jaxmocap.trackers.shirt.params import WORK_SIZE, Search, ShirtParams, make_params

SCRIBBLE_EROSION = 2  # pixels removed from every colour region to make "scribbles"


def scribbles(colour_ids: Int[np.ndarray, "h w"], erosion: int = SCRIBBLE_EROSION) -> np.ndarray:
    """Scribble labels from a colour-id map: every colour region eroded by ``erosion`` pixels
    (OpenCV, 3x3 cross), so labels stay well inside the patches as a user's strokes would."""
    import cv2

    ids = np.asarray(colour_ids)
    out = np.zeros(ids.shape, np.int32)
    kernel = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    for k in np.unique(ids[ids > 0]):
        m = cv2.erode((ids == k).astype(np.uint8), kernel, iterations=int(erosion))
        out[m > 0] = k
    return out


SCRIBBLE_INTENSITIES = (0.7, 0.85, 1.0, 1.15, 1.3)  # light levels of the five model images
SCRIBBLE_NOISE = 0.02  # sensor noise of the model images (fraction of 255)


def fit_color_model_from_renders(
    body: BodyModel,
    garment: Garment,
    poses: Float[np.ndarray, "n n_dof"],
    cam: Camera,
    erosion: int = SCRIBBLE_EROSION,
    intensities: Sequence[float] = SCRIBBLE_INTENSITIES,
    noise_sigma: float = SCRIBBLE_NOISE,
    background: int = 128,
    seed: int = 0,
) -> ColorModel:
    """The offline colour model (Wang §5.1, Fig. 5): "scribbles" on white-balanced images.

    Pose ``i`` is rendered by ``cam`` under white light (identity illuminant) of intensity
    ``intensities[i % len]`` with sensor noise, over a grey background (the paper's five
    images are photographs; the varied light level stands in for their exposure and shading
    differences); its ground-truth colour-id map eroded by ``erosion`` pixels
    (:func:`scribbles`) labels the pixels; the Gaussians are their ML fit
    (:func:`jaxmocap.color.fit_color_model`).
    """
    from jaxmocap.color import fit_color_model
    from jaxmocap.render import default_lighting, render_rgb

    dt = cam.K.dtype
    bg = jnp.full((cam.height, cam.width, 3), background, jnp.uint8)

    @jax.jit
    def render(q, intensity, key):
        light = eqx.tree_at(lambda lt: lt.intensity, default_lighting(dt), intensity)
        return render_rgb(body, garment, q, cam, bg, light, noise_sigma=noise_sigma, key=key)

    images, labels = [], []
    for i, q in enumerate(np.asarray(poses)):
        level = jnp.asarray(intensities[i % len(intensities)], dt)
        rgb, hits = render(jnp.asarray(q, dt), level, jax.random.fold_in(jax.random.key(seed), i))
        images.append(np.asarray(rgb))
        labels.append(scribbles(np.asarray(hits.colour), erosion))
    return fit_color_model(images, labels, garment.n_colours, garment.colour_names)


def initial_white_balance(
    color: ColorModel,
    frames: UInt8[np.ndarray, "n_cams h w 3"],
    labels: Int[np.ndarray, "n_cams h w"],
) -> Float[Array, "n_cams 3 3"]:
    """``W0`` per camera from one scribbled frame of the capture's light (Wang §5.1):
    ``labels`` 0 = unlabelled, ``1..k`` colour ids (e.g. :func:`scribbles` of a ground-truth
    map)."""
    from jaxmocap.color import white_balance_from_scribbles

    return jnp.stack(
        [
            white_balance_from_scribbles(color, [f], [lab])
            for f, lab in zip(frames, labels, strict=True)
        ]
    )


def setup_for_sequence(
    seq,
    db: PoseDB,
    cov: IKCovariances | None = None,
    work_size: int = WORK_SIZE,
) -> tuple[ShirtParams, Float[Array, "n_cams 3 3"], ColorModel]:
    """Tracker set-up for a rendered :class:`jaxmocap.synth.Sequence` the way a user sets up a
    capture session (§5.1): the colour model from scribbles on white-light renders of five
    database poses placed at the subject's first position in front of camera 0
    (:func:`fit_color_model_from_renders`), ``W0`` from one scribbled frame of the scene (the
    first frame's ground-truth colour ids, eroded: :func:`scribbles`), patch anchors of the
    default garment, and ``cov`` (default: isotropic 2 px / 0.3 / 0.5). Returns
    ``(params, W0, color)``."""
    from jaxmocap.body import default_body
    from jaxmocap.camera import stack_cameras
    from jaxmocap.garment import default_garment
    from jaxmocap.ik import anchors_from_garment

    body = default_body()
    garment = default_garment(body)
    q_model = np.asarray(db.poses[:5], np.float64).copy()
    q_model[:, :3] = np.asarray(seq.groundtruth["q"][0, :3])
    color = fit_color_model_from_renders(body, garment, q_model, seq.cameras[0])
    labels = np.stack([scribbles(m) for m in seq.groundtruth["colour_ids"][0]])
    W0 = initial_white_balance(color, seq.frames[0], labels)
    cov = cov if cov is not None else IKCovariances.isotropic(2.0, 0.3, 0.5, body.n_dof)
    params = make_params(
        color,
        body,
        garment,
        stack_cameras(list(seq.cameras)),
        anchors_from_garment(body, garment),
        cov,
        db,
        search=Search(work_size=work_size),
    )
    return params, W0, color
