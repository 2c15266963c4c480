"""Retargeting a source skeleton's motion onto a :class:`~jaxmocap.body.BodyModel`.

Method: **rotation transfer through the change of rest frames**, solved segment by segment.
Each driven segment ``s`` of our body (pelvis, chest, head, upper arms, forearms, ...) is given
the source's rest-relative world rotation ``D_s`` (the rotation that takes the source segment
from its rest pose to the current pose, expressed in our Z-up world). With ``u_s`` and ``v_s``
the rest bone directions of our segment and of the source segment (world), ``S_s`` the
smallest rotation with ``S_s u_s = v_s`` and ``A_s`` our rest orientation of the link,

    G_s = D_s S_s A_s                 (desired world orientation of our link)

reproduces the source bone direction exactly, ``G_s A_s^T u_s = D_s v_s``, keeps the source's
twist about the bone, and reduces to ``C^T R C`` conjugation when both rest poses agree. The
local rotation of the joint group that moves ``s`` is then ``O^T G_parent^T G_s``, with
``G_parent`` our *actual* (limit-clipped) parent orientation, so errors never compound; it is
decomposed exactly into the group's 1-DOF joints:

* three orthogonal axes (ball joints ``*_x, *_y, *_z``): an Euler decomposition in the axes'
  order; of its two branches ``(a, b, c)`` and ``(a + pi, pi - b, c + pi)`` the one that
  violates the joint limits least is kept;
* two axes (wrists): the Euler decomposition completed by the missing middle axis; two axes
  whose missing third axis lies along the bone (gymnasium's shoulders, no twist): the swing
  that reproduces the bone direction exactly (:func:`_swing`);
* one axis (elbows): the hinge angle that best reproduces the child bone direction
  (projection onto the plane normal to the axis), exact when the source hinge is parallel.

Why not a per-frame least-squares IK on bone directions: a direction fixes only two of a ball
joint's three angles, so the twist of the upper arm (and the plane the elbow bends in) would
be left to the regulariser; the transfer is exact, closed-form and cheap (vmapped over
frames, no iterations). Angles outside the joint limits are clipped; ``q_raw`` keeps the
unclipped values so :func:`limit_report` can say how often and how far.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxmocap.body import FIXED, BodyModel, require_roles, so3_exp
from jaxmocap.body.chain import path_to_root
from jaxmocap.errors import InputError
from jaxmocap.rotations import axis_angle_matrix, euler_xyz, matrix_to_rotvec, mm, mtm, mv

# Where the bone of each driven segment of the bundled body ends: a descendant link (its rest
# origin) or a keypoint on the segment or below it. For any body with roles: role_bone_ends.
DEFAULT_BONE_ENDS = {
    "pelvis": "chest",
    "chest": "head",
    "head": "head",
    "l_upper_arm": "l_forearm",
    "l_forearm": "l_hand",
    "l_hand": "l_hand",
    "r_upper_arm": "r_forearm",
    "r_forearm": "r_hand",
    "r_hand": "r_hand",
}


# The same by roles: segment role -> ("link", role) for that role link's rest origin, or
# ("keypoint", name). The neck role is the head link on a body without a neck link.
ROLE_BONE_ENDS = {
    "pelvis": ("link", "chest"),
    "chest": ("link", "neck"),
    "neck": ("keypoint", "head"),
    "head": ("keypoint", "head"),
    **{f"{s}_upper_arm": ("link", f"{s}_forearm") for s in "lr"},
    **{f"{s}_forearm": ("link", f"{s}_hand") for s in "lr"},
    **{f"{s}_hand": ("keypoint", f"{s}_hand") for s in "lr"},
}


# When a link end sits on the segment's own origin (DeepMimic's wrist link hangs at the elbow):
# the keypoint that ends the bone instead.
_COINCIDENT_END = {"l_hand": "l_hand", "r_hand": "r_hand", "neck": "head", "chest": "chest"}


def role_bone_ends(model: BodyModel) -> dict[str, str]:
    """``{link: bone end}`` of the body's role links (:data:`ROLE_BONE_ENDS`, by its roles)."""
    roles = require_roles(model, "retarget")
    names = model.chain.link_names
    rest = _rest_transforms(np.asarray(model.chain.joint_origin, np.float64),
                            model.chain.topology)
    out = {}
    for role, (kind, end) in ROLE_BONE_ENDS.items():
        link = roles.link(role)
        if kind == "link":
            e = roles.link(end)
            gap = np.linalg.norm(rest[names.index(e), :3, 3] - rest[names.index(link), :3, 3])
            out[link] = _COINCIDENT_END.get(end, e) if gap < 1e-3 else e
        else:
            out[link] = end
    return out


class SourcePose(eqx.Module):
    """A source motion, already in our world frame (Z up, facing +x at rest, metres).

    ``delta[:, j]`` is the rest-relative world rotation of the source segment driving our
    link ``links[j]``; ``rest_dir[j]`` its unit rest bone direction (world). ``links[0]`` must
    be our root link; ``root_pos`` is where our root link's origin goes.
    """

    root_pos: Float[Array, "n_frames 3"]
    delta: Float[Array, "n_frames n_seg 3 3"]
    rest_dir: Float[Array, "n_seg 3"]
    links: tuple[str, ...] = eqx.field(static=True)


class Retargeted(eqx.Module):
    """Joint angles for the body model: ``q`` within limits, ``q_raw`` before clipping."""

    q: Float[Array, "n_frames n_dof"]
    q_raw: Float[Array, "n_frames n_dof"]


class _Group(NamedTuple):
    """Static plan for one segment link (hashable: nested tuples of Python floats/ints)."""

    link: int
    parent: int  # the segment link this group hangs from (-1 for the root)
    source: int  # index into SourcePose.links, -1 if not driven (its joints stay at 0)
    dofs: tuple[int, ...]
    axes: tuple[tuple[float, float, float], ...]  # b_m, in the frame after O
    origin: tuple[tuple[float, ...], ...]  # O: product of the group's joint-origin rotations
    rest: tuple[tuple[float, ...], ...]  # A_s: our rest world orientation of the link
    bone: tuple[float, float, float]  # unit rest bone direction in the link frame


def _tup(a: np.ndarray) -> tuple:
    return tuple(_tup(x) for x in a) if a.ndim > 1 else tuple(float(x) for x in a)


def _segment_links(model: BodyModel) -> list[int]:
    """Links that carry a body segment: the root, links with geometry, branch points, and the
    children of fixed joints; the massless single-child links between them only chain the
    1-DOF joints of a ball or universal joint."""
    topo = model.chain.topology
    n_children = np.bincount([p for p, _, _ in topo if p >= 0], minlength=len(topo))
    has_geom = set(np.asarray(model.geometry.link).tolist())
    return [i for i, (p, t, _) in enumerate(topo)
            if p < 0 or i in has_geom or n_children[i] != 1 or t == FIXED]


def plan(model: BodyModel, links: tuple[str, ...],
         bone_ends: Mapping[str, str] | None = None) -> tuple[_Group, ...]:
    """The static retargeting plan: joint groups of every segment link, in topological order
    (``bone_ends``: link -> bone end, default :func:`role_bone_ends`)."""
    bone_ends = role_bone_ends(model) if bone_ends is None else bone_ends
    chain = model.chain
    names = chain.link_names
    for name in links:
        if name not in names:
            raise InputError(f"retarget: unknown body link {name!r}; links are {names}")
    if links[0] != names[0]:
        raise InputError(f"retarget: the first driven link (the pelvis role) must be the root "
                         f"link {names[0]!r}, "
                         f"got {links[0]!r}")
    topo = chain.topology
    origin = np.asarray(chain.joint_origin, dtype=np.float64)
    axis = np.asarray(chain.joint_axis, dtype=np.float64)
    rest = _rest_transforms(origin, topo)
    kp_link = np.asarray(model.keypoint_link)
    kp_off = np.asarray(model.keypoint_offset, dtype=np.float64)
    segs = _segment_links(model)
    groups = []
    for s in segs:
        chain_links = []
        i = s
        while i != 0 and (i == s or i not in segs):
            chain_links.append(i)
            i = topo[i][0]
        chain_links = chain_links[::-1] if s != 0 else []
        moving = [i for i in chain_links if topo[i][1] != FIXED]
        rots = [origin[i, :3, :3] for i in chain_links]
        o_total = np.eye(3)
        for r in rots:
            o_total = o_total @ r
        axes = []
        for m, i in enumerate(chain_links):
            if topo[i][1] == FIXED:
                continue
            after = np.eye(3)
            for r in rots[m + 1:]:
                after = after @ r
            axes.append(after.T @ axis[i] / np.linalg.norm(axis[i]))
        if moving and any(topo[i][1] != 1 for i in moving):
            raise InputError(f"retarget: link {names[s]!r} is moved by a prismatic joint")
        if len(axes) > 1 and not np.allclose(np.array(axes) @ np.array(axes).T,
                                             np.eye(len(axes)), atol=1e-9):
            raise InputError(f"retarget: the joints moving {names[s]!r} have non-orthogonal axes")
        end = bone_ends.get(names[s])
        if end is None:
            bone = np.array([0.0, 0.0, 1.0])
        elif end in names and end != names[s]:
            e = names.index(end)
            bone = rest[s, :3, :3].T @ (rest[e, :3, 3] - rest[s, :3, 3])
        elif end in model.keypoint_names:
            k = model.keypoint_names.index(end)
            if kp_link[k] == s:
                bone = kp_off[k]
            elif s in path_to_root(topo, int(kp_link[k]))[1:]:
                e = rest[kp_link[k]]
                bone = rest[s, :3, :3].T @ (e[:3, :3] @ kp_off[k] + e[:3, 3] - rest[s, :3, 3])
            else:
                raise InputError(f"retarget: bone end keypoint {end!r} is not on link "
                                 f"{names[s]!r} or below it")
        else:
            raise InputError(f"retarget: bone end {end!r} of {names[s]!r} is neither a "
                             "descendant link nor a keypoint")
        norm = np.linalg.norm(bone)
        if norm < 1e-9 and end in model.keypoint_names and "neck" in model.keypoint_names:
            # a head link whose origin is the head's centre (dm_control's humanoid): its bone
            # runs from the neck keypoint on it to the end
            k, kn = model.keypoint_names.index(end), model.keypoint_names.index("neck")
            if kp_link[k] == s and kp_link[kn] == s:
                bone = kp_off[k] - kp_off[kn]
                norm = np.linalg.norm(bone)
        if norm < 1e-9 and names[s] not in links:  # not driven: its bone is never used
            bone, norm = np.array([0.0, 0.0, 1.0]), 1.0
        if norm < 1e-9:
            raise InputError(f"retarget: bone of {names[s]!r} has zero length (end {end!r})")
        groups.append(_Group(
            link=s,
            parent=max((p for p in segs if p in path_to_root(topo, s)[1:]), default=-1),
            source=links.index(names[s]) if names[s] in links else -1,
            dofs=tuple(topo[i][2] for i in moving),
            axes=tuple(_tup(a) for a in axes),
            origin=_tup(o_total),
            rest=_tup(rest[s, :3, :3]),
            bone=_tup(bone / norm),
        ))
    return tuple(groups)


def _rest_transforms(origin: np.ndarray, topo) -> np.ndarray:
    """World transforms of the links at q = 0 (every joint motion is the identity there)."""
    out = [origin[0]]
    for i in range(1, len(topo)):
        out.append(out[topo[i][0]] @ origin[i])
    return np.stack(out)


def min_rotation(u: Float[Array, "*b 3"], v: Float[Array, "*b 3"]) -> Float[Array, "*b 3 3"]:
    """Smallest rotation ``S`` with ``S u = v`` for unit vectors (a half turn if opposite)."""
    c = jnp.sum(u * v, axis=-1)
    w = jnp.cross(u, v)
    opposite = c < -1 + 1e-6
    # Any axis normal to u for the half turn: u x e, with e the basis vector least aligned.
    e = jnp.eye(3, dtype=u.dtype)[jnp.argmin(jnp.abs(u), axis=-1)]
    n = jnp.cross(u, e)
    n = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
    x, y, z = jnp.moveaxis(w, -1, 0)
    o = jnp.zeros_like(x)
    k = jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1),
                   jnp.stack([-y, x, o], -1)], -2)
    scale = (1.0 / (1.0 + jnp.where(opposite, 0.0, c)))[..., None, None]
    eye = jnp.broadcast_to(jnp.eye(3, dtype=u.dtype), k.shape)
    general = eye + k + mm(k, k) * scale
    half = 2.0 * n[..., :, None] * n[..., None, :] - eye
    return jnp.where(opposite[..., None, None], half, general)


SWING_COS = np.cos(np.radians(30.0))  # a two-joint group whose missing axis is this near the bone


def _wrap(a: Array) -> Array:
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


def _violation(theta: Array, lo: Array, hi: Array) -> Array:
    return jnp.sum(jnp.maximum(lo - theta, 0.0) + jnp.maximum(theta - hi, 0.0), axis=-1)


def _decompose(g: _Group, r: Array, lo: Array, hi: Array) -> Array:
    """Angles of the group's joints with ``R_b1(t1) ... R_bk(tk) = r`` (see module doc)."""
    dt = r.dtype
    b = np.array(g.axes)
    if len(b) == 1:
        a = jnp.asarray(b[0], dtype=dt)
        d = jnp.asarray(np.array(g.bone), dtype=dt)
        t = mv(r, d)
        d_perp = d - jnp.dot(a, d) * a
        return jnp.arctan2(jnp.dot(a, jnp.cross(d_perp, t)), jnp.dot(d_perp, t))[None]
    if len(b) == 2 and abs(np.cross(b[0], b[1]) @ np.array(g.bone)) > SWING_COS * np.linalg.norm(
            np.cross(b[0], b[1])):
        return _swing(g, r, lo, hi)
    if len(b) == 2:
        p = np.stack([b[0], np.cross(b[1], b[0]), b[1]], axis=1)
        sign = np.sign(np.linalg.det(p))
        p[:, 1] *= sign
        e = euler_xyz(_conj(p, r))
        return jnp.stack([e[0], e[2]])
    p = np.stack(list(b), axis=1)
    sign = float(np.sign(np.linalg.det(p)))
    p[:, 2] *= sign
    e = euler_xyz(_conj(p, r))
    alt = _wrap(jnp.stack([e[0] + jnp.pi, jnp.pi - e[1], e[2] + jnp.pi]))
    flip = jnp.asarray([1.0, 1.0, sign], dtype=dt)
    e, alt = e * flip, alt * flip
    return jnp.where(_violation(alt, lo, hi) < _violation(e, lo, hi), alt, e)


def _rotate(a: Array, v: Array, t: Array) -> Array:
    """Rodrigues: ``v`` rotated by ``t`` about the unit axis ``a``."""
    c, s_ = jnp.cos(t), jnp.sin(t)
    return v * c + jnp.cross(a, v) * s_ + a * jnp.dot(a, v) * (1.0 - c)


def _swing(g: _Group, r: Array, lo: Array, hi: Array) -> Array:
    """Two joints whose missing third axis is the bone (gymnasium's shoulders: no twist): the
    angles ``(t1, t2)`` with ``R_a1(t1) R_a2(t2) u = r u`` for the bone ``u`` -- the bone
    direction exactly, the twist given up. ``a1 . R_a2(t2) u = a1 . r u`` fixes ``t2`` (two
    roots), then ``t1`` turns ``R_a2(t2) u`` onto ``r u`` about ``a1``; of the two branches the
    one that violates the limits least."""
    dt = r.dtype
    a1, a2 = (jnp.asarray(np.array(a), dtype=dt) for a in g.axes)
    u = jnp.asarray(np.array(g.bone), dtype=dt)
    t = mv(r, u)
    k = jnp.dot(a1, a2) * jnp.dot(a2, u)
    big_a, big_b = jnp.dot(a1, u) - k, jnp.dot(a1, jnp.cross(a2, u))
    rho = jnp.sqrt(big_a**2 + big_b**2)
    phi = jnp.arctan2(big_b, big_a)
    off = jnp.arccos(jnp.clip((jnp.dot(a1, t) - k) / jnp.maximum(rho, 1e-12), -1.0, 1.0))

    def branch(t2):
        v = _rotate(a2, u, t2)
        vp, tp = v - jnp.dot(a1, v) * a1, t - jnp.dot(a1, t) * a1
        t1 = jnp.arctan2(jnp.dot(a1, jnp.cross(vp, tp)), jnp.dot(vp, tp))
        return jnp.stack([t1, _wrap(t2)])

    e, alt = branch(phi + off), branch(phi - off)
    return jnp.where(_violation(alt, lo, hi) < _violation(e, lo, hi), alt, e)


def _conj(p: np.ndarray, r: Array) -> Array:
    """``p^T r p`` for a constant ``p`` (skipped when ``p`` is the identity)."""
    if np.allclose(p, np.eye(3)):
        return r
    pj = jnp.asarray(p, dtype=r.dtype)
    return mm(mtm(pj, r), pj)


def _cmul(c: np.ndarray, r: Array, left: bool = True) -> Array:
    """``c @ r`` (or ``r @ c``) for a constant rotation ``c`` (skipped when identity)."""
    if np.allclose(c, np.eye(3)):
        return r
    cj = jnp.asarray(c, dtype=r.dtype)
    return mm(cj, r) if left else mm(r, cj)


def _group_rotation(g: _Group, theta: Array) -> Array:
    r = None
    for m, axis in enumerate(g.axes):
        rm = axis_angle_matrix(jnp.asarray(axis, dtype=theta.dtype), theta[m])
        r = rm if r is None else mm(r, rm)
    return _cmul(np.array(g.origin), r)


def _retarget_frames(groups: tuple[_Group, ...], root_origin: Array, lower: Array, upper: Array,
              root_pos: Array, delta: Array, rest_dir: Array) -> tuple[Array, Array]:
    dt = root_pos.dtype
    n_dof = lower.shape[0]
    lower, upper = lower.astype(dt), upper.astype(dt)
    u_world = jnp.stack([jnp.asarray(np.array(g.rest) @ np.array(g.bone), dtype=dt)
                         for g in groups if g.source >= 0])
    order = [g.source for g in groups if g.source >= 0]
    s_rot = min_rotation(u_world, rest_dir[np.array(order)])  # (n_driven, 3, 3)
    s_of = {src: s_rot[m] for m, src in enumerate(order)}

    def frame(p_root, d):
        q = jnp.zeros((n_dof,), dtype=dt)
        q_raw = q
        world = {}
        for g in groups:
            target = None
            if g.source >= 0:
                target = _cmul(np.array(g.rest), mm(d[g.source], s_of[g.source]), left=False)
            if g.parent < 0:
                o0 = root_origin.astype(dt)
                r_root = mm(target, o0[:3, :3].T)
                w = matrix_to_rotvec(r_root)
                r_root = so3_exp(w)
                t = p_root - mv(r_root, o0[:3, 3])
                q = q.at[0:6].set(jnp.concatenate([t, w]))
                q_raw = q
                world[g.link] = mm(r_root, o0[:3, :3])
                continue
            if not g.dofs:
                world[g.link] = _cmul(np.array(g.origin), world[g.parent], left=False)
                continue
            idx = np.array(g.dofs)
            lo, hi = lower[idx], upper[idx]
            if target is None:
                theta_raw = jnp.zeros((len(idx),), dtype=dt)
            else:
                local = _cmul(np.array(g.origin).T, mtm(world[g.parent], target))
                theta_raw = _decompose(g, local, lo, hi)
            theta = jnp.clip(theta_raw, lo, hi)
            q = q.at[idx].set(theta)
            q_raw = q_raw.at[idx].set(theta_raw)
            world[g.link] = mm(world[g.parent], _group_rotation(g, theta))
        return q, q_raw

    return jax.vmap(frame)(root_pos, delta)


_retarget = jax.jit(_retarget_frames, static_argnums=(0,))


def frame_bucket(n: int) -> int:
    """Padded length for ``n`` frames (a power of two >= 32): one compilation per bucket."""
    return max(32, 1 << (int(n) - 1).bit_length())


def pad_frames(x: Array, n: int) -> Array:
    """``x`` padded along axis 0 to ``n`` rows by repeating its last row."""
    return jnp.concatenate([x, jnp.repeat(x[-1:], n - x.shape[0], axis=0)], axis=0)


def retarget(model: BodyModel, source: SourcePose,
             bone_ends: Mapping[str, str] | None = None) -> Retargeted:
    """Joint angles ``q`` (n_frames, n_dof) of ``model`` reproducing ``source`` (see module doc).

    ``bone_ends`` maps link names to bone ends (default: :func:`role_bone_ends` of the body).
    Segments of the model that the source does not drive keep their joints at 0. The result
    follows the dtype of ``source.root_pos``; jitted and vmapped over frames, with the frames
    padded to :func:`frame_bucket` so that clips of similar length share one compilation.
    """
    n_seg = len(source.links)
    if source.delta.shape[1] != n_seg or source.rest_dir.shape[0] != n_seg:
        raise ValueError(f"retarget: SourcePose has {n_seg} links but delta/rest_dir hold "
                         f"{source.delta.shape[1]}/{source.rest_dir.shape[0]} segments")
    groups = plan(model, source.links, role_bone_ends(model) if bone_ends is None else bone_ends)
    chain = model.chain
    n = source.root_pos.shape[0]
    nb = frame_bucket(n)
    q, q_raw = _retarget(groups, chain.joint_origin[0], chain.lower, chain.upper,
                         pad_frames(source.root_pos, nb), pad_frames(source.delta, nb),
                         source.rest_dir)
    return Retargeted(q=q[:n], q_raw=q_raw[:n])


def limit_report(model: BodyModel, result: Retargeted, tol: float = 1e-9
                 ) -> dict[str, tuple[float, float]]:
    """Per joint that was clipped: (fraction of frames clipped, largest excess in rad)."""
    excess = np.abs(np.asarray(result.q_raw) - np.asarray(result.q))
    out = {}
    for j, name in enumerate(model.chain.dof_names):
        hit = excess[:, j] > tol
        if hit.any():
            out[name] = (float(hit.mean()), float(excess[:, j].max()))
    return out
