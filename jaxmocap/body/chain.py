"""Kinematic chain and forward kinematics (Wang et al. 2011 §5; Azad et al. 2007 §III).

A body is a tree of rigid links. Link ``i`` hangs from link ``parents[i]`` through a fixed
offset ``joint_origin[i]`` (parent frame -> joint frame) followed by a 1-DOF joint motion
about / along ``joint_axis[i]`` (given in the joint frame). The root link is placed in the
world by six free DOFs, so the pose vector is

    q = (t_x, t_y, t_z,  w_x, w_y, w_z,  theta_1, ..., theta_J)

with ``t`` the root translation (m), ``w`` the root rotation vector (rad, world frame,
``R = exp([w]_x)``) and ``theta_j`` the chain's 1-DOF joints in chain order (rad or m).

Forward kinematics composes, for every link in topological order,

    T_i = T_{parents[i]} @ joint_origin[i] @ M_i(theta),   M = Rot(a, theta) | Trans(a theta) | I

and the root link ``T_0 = [exp(w), t] @ joint_origin[0]``. Rotations are composed as 3x3
matrices plus translations (no 4x4 products, no gathers in the loop; see PERF-NOTES); the
loop over links is unrolled at trace time from the chain's static topology.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, Float, Int

from jaxmocap.rotations import skew
from jaxmocap.rotations import so3_exp as so3_exp

FIXED, REVOLUTE, PRISMATIC = 0, 1, 2
ROOT_DOFS = 6  # q[0:3] root translation, q[3:6] root rotation vector


class KinematicChain(eqx.Module):
    """A tree of links with 1-DOF joints; link 0 is the root, links in topological order.

    Array fields (see docs/ARCHITECTURE.md) follow the dtype the chain was built with; the
    static tuples ``topology`` hold the same (parent, joint type, dof index) per link as
    Python ints so that ``fk`` unrolls the tree at trace time.
    """

    parents: Int[Array, " n_links"]
    joint_origin: Float[Array, "n_links 4 4"]
    joint_axis: Float[Array, "n_links 3"]
    joint_type: Int[Array, " n_links"]
    dof_index: Int[Array, " n_links"]
    lower: Float[Array, " n_dof"]
    upper: Float[Array, " n_dof"]
    link_names: tuple[str, ...] = eqx.field(static=True)
    dof_names: tuple[str, ...] = eqx.field(static=True)
    topology: tuple[tuple[int, int, int], ...] = eqx.field(static=True)

    def __init__(
        self,
        parents,
        joint_origin,
        joint_axis,
        joint_type,
        dof_index,
        lower,
        upper,
        link_names,
        dof_names,
    ):
        """Build a chain from array-likes; validates the tree (parents before children)."""
        parents_np = np.asarray(parents, dtype=np.int64).reshape(-1)
        types_np = np.asarray(joint_type, dtype=np.int64).reshape(-1)
        dofs_np = np.asarray(dof_index, dtype=np.int64).reshape(-1)
        n = parents_np.shape[0]
        link_names = tuple(str(s) for s in link_names)
        dof_names = tuple(str(s) for s in dof_names)
        if n == 0 or parents_np[0] != -1:
            raise ValueError("KinematicChain: link 0 must be the root (parents[0] == -1)")
        for i in range(1, n):
            if not 0 <= parents_np[i] < i:
                raise ValueError(
                    f"KinematicChain: link {i} ({link_names[i]!r}) has parent {parents_np[i]}; "
                    "expected a link index < i (topological order)"
                )
        if len(link_names) != n or types_np.shape[0] != n or dofs_np.shape[0] != n:
            raise ValueError(f"KinematicChain: expected {n} link names, joint types, dof indices")
        n_dof = len(dof_names)
        moving = dofs_np[types_np != FIXED]
        if sorted(moving.tolist()) != list(range(ROOT_DOFS, n_dof)):
            raise ValueError(
                f"KinematicChain: dof_index of moving joints must cover {ROOT_DOFS}..{n_dof - 1} "
                f"once each, got {sorted(moving.tolist())}"
            )
        if np.any(dofs_np[types_np == FIXED] != -1):
            raise ValueError("KinematicChain: fixed joints must have dof_index -1")
        self.parents = jnp.asarray(parents_np, dtype=jnp.int32)
        self.joint_origin = jnp.asarray(joint_origin)
        self.joint_axis = jnp.asarray(joint_axis)
        self.joint_type = jnp.asarray(types_np, dtype=jnp.int32)
        self.dof_index = jnp.asarray(dofs_np, dtype=jnp.int32)
        self.lower = jnp.asarray(lower)
        self.upper = jnp.asarray(upper)
        self.link_names = link_names
        self.dof_names = dof_names
        self.topology = tuple(
            (int(p), int(t), int(d)) for p, t, d in zip(parents_np, types_np, dofs_np, strict=True)
        )

    @property
    def n_links(self) -> int:
        return len(self.link_names)

    @property
    def n_dof(self) -> int:
        return len(self.dof_names)

    def link_index(self, name: str) -> int:
        """Index of the link called ``name`` (ValueError naming the known links otherwise)."""
        try:
            return self.link_names.index(name)
        except ValueError:
            raise ValueError(f"unknown link {name!r}; links are {self.link_names}") from None


def _mm(a: Array, b: Array) -> Array:
    """3x3 @ 3x3 as a dot (measured: broadcast multiply-sum forms fuse along the chain and
    recompute parents, 10x slower under vmap at 1000 poses; see benchmarks/bench_fk.py)."""
    return a @ b


def _mv(a: Array, v: Array) -> Array:
    return (a @ v[..., None])[..., 0]


def fk(chain: KinematicChain, q: Float[Array, " n_dof"]) -> Float[Array, "n_links 4 4"]:
    """World transforms ``T_i`` (4x4, metres) of every link for the pose vector ``q``.

    ``q`` follows the layout in the module docstring; the result follows ``q.dtype``.
    Batch with ``jax.vmap(fk, in_axes=(None, 0))``. Derivatives in ``q`` come from the
    geometric Jacobian in closed form (:func:`_fk_jvp`); in the chain's arrays from autodiff.
    """
    if q.shape != (chain.n_dof,):
        raise ValueError(f"fk: q has shape {q.shape}, expected ({chain.n_dof},)")
    dt = q.dtype
    return _fk(chain.topology, chain.joint_origin.astype(dt), chain.joint_axis.astype(dt), q)


def _fk_plain(
    topo: tuple[tuple[int, int, int], ...], origin: Array, axis: Array, q: Array
) -> Array:
    o_rot, o_t = origin[:, :3, :3], origin[:, :3, 3]
    types = np.array([t for _, t, _ in topo])
    theta = q[np.array([max(d, 0) for _, _, d in topo])] * (types != FIXED)

    # Local joint motions for all links at once (vectorised over links, outside the loop):
    # revolute Rot(a, theta) = I + sin K + (1 - cos) K^2 with K = [a]_x, so
    # origin_R @ Rot = origin_R + sin (origin_R K) + (1 - cos)(origin_R K^2).
    k = skew(axis)
    ok, okk = _mm(o_rot, k), _mm(o_rot, _mm(k, k))
    rev = (types == REVOLUTE)[:, None, None]
    s = jnp.where(rev, jnp.sin(theta)[:, None, None], 0.0)
    c1 = jnp.where(rev, (1.0 - jnp.cos(theta))[:, None, None], 0.0)
    local_r = o_rot + s * ok + c1 * okk
    pri = (types == PRISMATIC)[:, None]
    local_t = o_t + _mv(o_rot, jnp.where(pri, theta[:, None] * axis, 0.0))

    root_r = so3_exp(q[3:6])
    rots = [_mm(root_r, local_r[0])]
    trans = [_mv(root_r, local_t[0]) + q[0:3]]
    for i in range(1, len(topo)):
        p = topo[i][0]
        rots.append(_mm(rots[p], local_r[i]))
        trans.append(_mv(rots[p], local_t[i]) + trans[p])
    r = jnp.stack(rots)
    t = jnp.stack(trans)
    top = jnp.concatenate([r, t[:, :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], dtype=q.dtype), (len(topo), 1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _fk(topo: tuple[tuple[int, int, int], ...], origin: Array, axis: Array, q: Array) -> Array:
    return _fk_plain(topo, origin, axis, q)


def path_to_root(topology: tuple[tuple[int, int, int], ...], link: int) -> list[int]:
    """``link`` and its ancestors, from ``link`` up to the root (``KinematicChain.topology``)."""
    out = [int(link)]
    while topology[out[-1]][0] >= 0:
        out.append(topology[out[-1]][0])
    return out


def _ancestor_matrix(topo: tuple[tuple[int, int, int], ...]) -> np.ndarray:
    """``anc[i, k] = 1`` where link k is link i or one of its ancestors (static)."""
    anc = np.zeros((len(topo), len(topo)))
    for i in range(len(topo)):
        anc[i, path_to_root(topo, i)] = 1.0
    return anc


def _fk_tangent(topo, T: Array, axis: Array, q: Array, dq: Array) -> Array:
    """``d T_i`` for a pose tangent ``dq``: the geometric Jacobian of the tree.

    Joint k's world axis is ``a_k = R_k axis_k`` (``Rot(axis, theta)`` leaves its axis fixed)
    through the link origin ``t_k``. A revolute ``dtheta_k`` turns every link i below k
    (itself included) by ``a_k dtheta_k``: ``dR_i = [a_k]_x R_i dtheta``,
    ``dt_i = a_k x (t_i - t_k) dtheta``; a prismatic one moves it by ``a_k dtheta``. The
    root's rotation vector turns everything by ``omega`` (``[omega]_x = d exp(w) exp(w)^T``)
    about the root translation, which itself moves every link. Summed over the tree with the
    static ancestor matrix, a handful of products over all links at once: under the IK's
    vmapped forward-mode Jacobian this replaces the tangent of every link's 3x3 product."""
    types = np.array([t for _, t, _ in topo])
    dofs = np.array([max(d, 0) for _, _, d in topo])
    anc = jnp.asarray(_ancestor_matrix(topo), q.dtype)
    r, t = T[:, :3, :3], T[:, :3, 3]
    a = jnp.sum(r * axis[:, None, :], axis=-1)  # (n, 3) world joint axes R_k axis_k
    s = dq[dofs]
    b = jnp.where(jnp.asarray(types == REVOLUTE)[:, None], s[:, None] * a, 0.0)
    c = jnp.cross(b, t)
    m = jnp.where(jnp.asarray(types == PRISMATIC)[:, None], s[:, None] * a, 0.0)
    root_r, d_root = jax.jvp(so3_exp, (q[3:6],), (dq[3:6],))
    h = d_root @ root_r.T  # [omega]_x up to rounding
    omega = 0.5 * jnp.stack([h[2, 1] - h[1, 2], h[0, 2] - h[2, 0], h[1, 0] - h[0, 1]])
    turn = anc @ b  # (n, 3) joint part of every link's angular velocity
    w = omega[None, :] + turn
    v = dq[None, 0:3] + jnp.cross(omega[None, :], t - q[None, 0:3]) + jnp.cross(turn, t) \
        - anc @ c + anc @ m
    d_r = jnp.stack([jnp.cross(w, r[:, :, j]) for j in range(3)], axis=-1)  # [w]_x R
    top = jnp.concatenate([d_r, v[:, :, None]], axis=-1)
    return jnp.concatenate([top, jnp.zeros((r.shape[0], 1, 4), q.dtype)], axis=-2)


@functools.partial(_fk.defjvp, symbolic_zeros=True)
def _fk_jvp(topo, primals, tangents):
    origin, axis, q = primals
    t_origin, t_axis, t_q = tangents
    zero = lambda x: isinstance(x, SymbolicZero)  # noqa: E731
    out = _fk(topo, origin, axis, q)
    if zero(t_origin) and zero(t_axis):
        return out, (jnp.zeros_like(out) if zero(t_q) else _fk_tangent(topo, out, axis, q, t_q))
    # the chain's own arrays are differentiated (e.g. fitting proportions): plain autodiff
    dense = [jnp.zeros(x.aval.shape, x.aval.dtype) if zero(x) else x for x in tangents]
    return jax.jvp(functools.partial(_fk_plain, topo), primals, tuple(dense))


FRAME_CHUNK = 256  # rows per call of over_frames: bounded memory, one program for any length


def over_frames(f, model, q: np.ndarray, chunk: int = FRAME_CHUNK) -> np.ndarray:
    """``f(model, q_t)`` for every row of ``q`` (T, n_dof) as one float64 host array
    (T, ...): jitted and vmapped over ``chunk`` rows at a time, the last chunk padded with
    copies of its first row. A capture's whole length in one vmapped call held T frames of
    intermediates at once (a `track` of 2,400 frames peaked 45 MB above its steady state while
    writing, issue 52); in chunks the peak does not grow with T and every length runs the same
    compiled program."""
    q = np.asarray(q)
    if q.ndim != 2 or q.shape[0] == 0:
        raise ValueError(f"over_frames: q must be (T >= 1, n_dof), got {q.shape}")
    g = _vmapped(f)
    out = []
    for s in range(0, q.shape[0], chunk):
        block = q[s:s + chunk]
        n = block.shape[0]
        if n < chunk:
            block = np.concatenate([block, np.repeat(block[:1], chunk - n, axis=0)])
        out.append(np.asarray(g(model, jnp.asarray(block)), np.float64)[:n])
    return np.concatenate(out)


@functools.cache
def _vmapped(f):
    return jax.jit(jax.vmap(f, in_axes=(None, 0)))
