"""Real motion-capture clips for synthetic scenes: DeepMimic clips retargeted to our body.

The clips are the 20 humanoid clips that pybullet ships (``pybullet_data/data/motions``,
see docs/DATA.md for licence and provenance). :data:`TRAIN_CLIPS` feed the pose database and
the covariance training; :data:`HELDOUT_CLIPS` are kept for evaluation only (no motion family
appears on both sides).

    clip = load_deepmimic("punch")               # source skeleton, Y up
    res = clip_to_body_q(clip, default_body(), fps=30.0)
    res.q                                         # (n_frames, n_dof) for fk / keypoints
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxmocap.body import BodyModel, default_body, require_roles
from jaxmocap.rotations import Y_UP_TO_Z_UP, mm, mv
from jaxmocap.synth.deepmimic import LINKS, Clip, deepmimic_skeleton, resample, skeleton_fk
from jaxmocap.synth.retarget import (
    Retargeted,
    SourcePose,
    _retarget_frames,
    frame_bucket,
    pad_frames,
    plan,
    role_bone_ends,
)

TRAIN_CLIPS = (
    "humanoid3d_walk", "humanoid3d_run", "humanoid3d_jump", "humanoid3d_kick",
    "humanoid3d_spinkick", "humanoid3d_dance_a", "humanoid3d_backflip", "humanoid3d_cartwheel",
    "humanoid3d_getup_facedown", "humanoid3d_getup_faceup", "humanoid3d_crawl",
    "humanoid3d_roll", "humanoid3d_spin", "walker/0walk_forward", "walker/turn_right0",
    "walker/turn_right1",
)  # fmt: skip
# Held out for evaluation: punching, a second dance, and the whole left-turn family.
HELDOUT_CLIPS = ("humanoid3d_punch", "humanoid3d_dance_b", "walker/turn_left0",
                 "walker/turn_left1")

# Our body's link *role* -> the DeepMimic link that drives it (the body's roles name the link:
# ``model.roles.link(role)``; the neck role is the head link on a body without a neck link).
# Hands are not driven (the source wrists are fixed joints), so the wrist angles stay 0.
DEEPMIMIC_TO_BODY = {
    "pelvis": "root",
    "chest": "chest",
    "neck": "neck",
    "l_upper_arm": "left_shoulder",
    "l_forearm": "left_elbow",
    "r_upper_arm": "right_shoulder",
    "r_forearm": "right_elbow",
}


def deepmimic_source(clip: Clip, mapping: dict[str, str] = DEEPMIMIC_TO_BODY,
                     model: BodyModel | None = None) -> SourcePose:
    """The clip as a :class:`SourcePose` in our Z-up world; ``links`` are the links of
    ``model`` playing ``mapping``'s roles (the role names themselves when no model is given).

    With ``M`` the Y-up -> Z-up rotation, the root position is ``M p`` and a source link with
    world rotation ``G`` (rest: identity) has the rest-relative rotation ``M G M^T``; its rest
    bone direction is ``M`` times the URDF's bone (see ``deepmimic_skeleton``).
    """
    dt = clip.times.dtype
    m = jnp.asarray(np.array(Y_UP_TO_Z_UP), dtype=dt)
    rots, _ = skeleton_fk(clip)
    src = [LINKS.index(mapping[k]) for k in mapping]
    bones = deepmimic_skeleton().bone_end[src]
    bones = bones / np.linalg.norm(bones, axis=-1, keepdims=True)
    return SourcePose(
        root_pos=mv(m, clip.root_pos),
        delta=mm(mm(m, rots[:, np.array(src)]), m.T),
        rest_dir=mv(m, jnp.asarray(bones.astype(dt))),
        links=tuple(mapping) if model is None else driven_links(model, mapping),
    )


def driven_links(model: BodyModel, mapping: dict[str, str] = DEEPMIMIC_TO_BODY
                 ) -> tuple[str, ...]:
    """The links of ``model`` that play ``mapping``'s roles (by the body's roles)."""
    roles = require_roles(model, "clip_to_body_q")
    return tuple(roles.link(r) for r in mapping)


def _shared_link_order(model: BodyModel, mapping: dict[str, str]) -> dict[str, str]:
    """``mapping`` with one role per body link: where roles share a link (gymnasium's torso
    is the root, the chest and the head) the link follows the role that owns its unnamed
    geometry (:data:`~jaxmocap.body.roles._CONTAINER_ORDER`: the chest before the pelvis)."""
    from jaxmocap.body.roles import _CONTAINER_ORDER

    roles = require_roles(model, "clip_to_body_q")
    rank = {r: i for i, r in enumerate(_CONTAINER_ORDER)}
    best: dict[str, str] = {}
    for role in mapping:
        link = roles.link(role)
        if link not in best or rank.get(role, 99) < rank.get(best[link], 99):
            best[link] = role
    keep = set(best.values())
    return {r: v for r, v in mapping.items() if r in keep}


@partial(jax.jit, static_argnums=(0, 5))
def _deepmimic_q(groups, root_origin, lower, upper, arrays, mapping):
    clip = Clip(*arrays, name="", loop="none")
    src = deepmimic_source(clip, dict(mapping))
    return _retarget_frames(groups, root_origin, lower, upper, src.root_pos, src.delta,
                            src.rest_dir)


def clip_to_body_q(clip: Clip, model: BodyModel | None = None, fps: float | None = None
                   ) -> Retargeted:
    """Retarget a DeepMimic clip to ``model`` (default: the bundled body), optionally after
    resampling it to ``fps`` (slerp for rotations). See :mod:`jaxmocap.synth.retarget`.

    One jitted program from the clip's arrays to ``q`` (source FK, change of frames, joint
    decomposition), frames padded to a power-of-two bucket so that clips share compilations.
    """
    model = default_body() if model is None else model
    if fps is not None:
        clip = resample(clip, fps)
    mapping = _shared_link_order(model, DEEPMIMIC_TO_BODY)
    groups = plan(model, driven_links(model, mapping), role_bone_ends(model))
    n, nb = clip.n_frames, frame_bucket(clip.n_frames)
    arrays = tuple(pad_frames(a, nb) for a in
                   (clip.times, clip.root_pos, clip.root_quat, clip.joint_quat, clip.hinge))
    chain = model.chain
    q, q_raw = _deepmimic_q(groups, chain.joint_origin[0], chain.lower, chain.upper, arrays,
                            tuple(mapping.items()))
    return Retargeted(q=q[:n], q_raw=q_raw[:n])


def source_bone_directions(clip: Clip, mapping: dict[str, str] = DEEPMIMIC_TO_BODY
                           ) -> Float[Array, "n_frames n_seg 3"]:
    """World directions (our Z-up frame, unit) of the source bones driving ``mapping``'s roles."""
    dt = clip.times.dtype
    m = jnp.asarray(np.array(Y_UP_TO_Z_UP), dtype=dt)
    rots, _ = skeleton_fk(clip)
    src = np.array([LINKS.index(mapping[k]) for k in mapping])
    bones = jnp.asarray(deepmimic_skeleton().bone_end[src].astype(dt))
    d = mv(m, mv(rots[:, src], bones))
    return d / jnp.linalg.norm(d, axis=-1, keepdims=True)
