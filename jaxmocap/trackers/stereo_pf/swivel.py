"""Elbow-swivel jumps for any shoulder (not in Azad's paper): :class:`SwivelProposal` turns an
arm as a rigid whole about its shoulder-hand line and sets the filtered shoulder hinges so that
the upper arm takes the turned rotation; :func:`swivel_arms` reads each shoulder's hinges from
the body's roles and picks how the rotation is inverted:

* ``"xyz"``: three x, y, z revolute links with identity origin rotations (the bundled body):
  the x-y-z Euler decomposition, bit for bit the round-1 proposal;
* ``"tait_bryan"``: the last three filtered hinges all turn about the shoulder's centre (no
  offset between them) and their axes, carried into one frame through the fixed origin
  rotations (``Rot(a, t) G = G Rot(G^T a, t)``), are mutually perpendicular (any order, any
  handedness, any origin rotations: dm_control's CMU humanoid's humerus z-y-x in a rotated
  frame): closed-form generalised Euler (Davenport) angles in the basis of those axes; the
  hinges above them (a clavicle) keep their values, so the hand stays exactly where it was;
* ``"gauss_newton"``: otherwise (axes not perpendicular, more or fewer hinges at the centre,
  hinges spread along a clavicle): a fixed number of Levenberg-Marquardt steps on the upper
  arm's rotation matrix over all the filtered shoulder hinges (the turn in
  :data:`GN_SUBSTEPS` increments, each from the last, so no step starts far from its target);
  unfiltered hinges keep their ``default_q`` values. The rotation is matched as well as the
  hinges allow; with offsets between hinges the shoulder's centre (and the hand) may move.

A shoulder whose filtered hinges do not span three rotation axes (fewer than three hinges, or
parallel ones) cannot swivel and is refused with one line naming the joints, the body file and
the setting. Everything runs inside the jitted filter step and vmaps over the particles.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from jaxmocap import pf
from jaxmocap.body import BodyModel, require_roles
from jaxmocap.body.chain import FIXED, PRISMATIC, REVOLUTE, so3_exp
from jaxmocap.errors import InputError
from jaxmocap.pf import cues as cuelib

SWIVEL_ARMS = (("l_shoulder", "l_hand"), ("r_shoulder", "r_hand"))  # (joint role, hand keypoint)
# Gauss-Newton inversion: the turn in this many increments, this many damped steps each
# (rotation-matrix residual). On the oblique-axes test body
# (tests/test_trackers_stereo_pf_swivel.py) 4 x 4 left the hand 1.6 mm off,
# 8 x 8 within 1e-6 m (reachable targets: 1e-8)
GN_SUBSTEPS = 8
GN_ITERATIONS = 8
GN_DAMPING = 1e-6


def _rot_xyz(a: Float[Array, " 3"]) -> Float[Array, "3 3"]:
    """Rx(a0) Ry(a1) Rz(a2): the model's 3-DOF ball joints (x, y, z revolute links)."""
    return so3_exp(jnp.array([1.0, 0.0, 0.0], a.dtype) * a[0]) @ (
        so3_exp(jnp.array([0.0, 1.0, 0.0], a.dtype) * a[1])
        @ so3_exp(jnp.array([0.0, 0.0, 1.0], a.dtype) * a[2])
    )


def _angles_xyz(m: Float[Array, "3 3"]) -> Float[Array, " 3"]:
    """The inverse of :func:`_rot_xyz` (the middle angle in [-pi/2, pi/2])."""
    b = jnp.arcsin(jnp.clip(m[0, 2], -1.0, 1.0))
    return jnp.stack([jnp.arctan2(-m[1, 2], m[2, 2]), b, jnp.arctan2(-m[0, 1], m[0, 0])])


class ShoulderFit(eqx.Module):
    """How one arm's filtered shoulder hinges are set from the upper arm's turned rotation.

    The upper arm's rotation relative to link ``start`` is ``G_0 Rot(a_1, t_1) G_1 ...
    Rot(a_k, t_k) G_k`` (``gs``: the constant rotations between the filtered hinges -- origin
    rotations and unfiltered hinges at ``default_q``; ``axes``: the hinges' axes). For
    ``"tait_bryan"``, ``basis`` holds the hinges' axes in the upper arm's frame as columns
    (the third times ``sign``, so that it is a rotation)."""

    gs: Float[Array, "k1 3 3"]
    axes: Float[Array, "k 3"]
    basis: Float[Array, "3 3"]
    kind: str = eqx.field(static=True)
    sign: float = eqx.field(static=True, default=1.0)

    def relative(self, theta: Float[Array, " k"]) -> Float[Array, "3 3"]:
        r = self.gs[0]
        for i in range(self.axes.shape[0]):
            r = r @ so3_exp(self.axes[i] * theta[i]) @ self.gs[i + 1]
        return r

    def solve(self, target: Float[Array, "3 3"], theta: Float[Array, " k"]
              ) -> Float[Array, " k"]:
        """Hinge angles whose :meth:`relative` is ``target`` (closed form), or as near as
        Levenberg-Marquardt from ``theta`` gets (one increment of the turn)."""
        if self.kind == "tait_bryan":
            g_all = self.gs[0]
            for g in self.gs[1:]:
                g_all = g_all @ g
            m = self.basis.T @ g_all.T @ target @ self.basis
            a = _angles_xyz(m)
            return a.at[2].multiply(self.sign)

        def residual(t):
            return (self.relative(t) - target).reshape(-1)

        eye = jnp.eye(theta.shape[0], dtype=theta.dtype)

        def lm_step(_, t):
            r, jac = residual(t), jax.jacfwd(residual)(t)
            return t - jnp.linalg.solve(jac.T @ jac + GN_DAMPING * eye, jac.T @ r)

        return jax.lax.fori_loop(0, GN_ITERATIONS, lm_step, theta)


class SwivelProposal(eqx.Module):
    """The guided proposal followed by **elbow-swivel jumps** (not in Azad's paper).

    With the shoulder and the hand fixed, an arm keeps one free motion: the elbow circles the
    shoulder-hand line (the swivel). A single-colour silhouette sees it weakly, and the filter
    that picked the wrong side at initialisation cannot cross over by small random steps
    while the hand stays pinned by the distance cue. For a random ``fraction`` of the
    particles each arm (with probability 1/2) is rotated, as a rigid whole about the line
    from its shoulder joint to its hand, by an angle uniform in [-pi, pi): the hand does not
    move, so the distance cue is unchanged and the edge cue decides. The new shoulder angles
    invert the rotated upper arm (the module docstring: closed form where the hinges allow,
    Gauss-Newton otherwise)."""

    inner: pf.GuidedProposal | None
    model: BodyModel
    default_q: Float[Array, " n_dof"]
    dofs: tuple[int, ...] = eqx.field(static=True)
    # per arm: (positions of the solved shoulder DOFs in the filtered state, link the solved
    # rotation is relative to, the shoulder's last link (the upper arm), hand keypoint name)
    arms: tuple[tuple[tuple[int, ...], int, int, str], ...] = eqx.field(static=True)
    fraction: float = eqx.field(static=True)
    fits: tuple[ShoulderFit, ...] | None = None  # per arm; None: all "xyz"

    def _swivel(self, s: Float[Array, " d"], phi: Float[Array, " a"]) -> Float[Array, " d"]:
        q = self.default_q.astype(s.dtype).at[np.asarray(self.dofs)].set(s)
        tr = cuelib.pose_transforms(self.model, q)
        hands = cuelib.distance_points(self.model, tr, tuple(arm[3] for arm in self.arms))
        dt = s.dtype
        for a, (cols, parent, link, _) in enumerate(self.arms):
            u = hands[a] - tr[link, :3, 3]
            u = u / jnp.maximum(jnp.linalg.norm(u), 1e-6)
            rp = tr[parent, :3, :3]
            c = np.asarray(cols)
            fit = None if self.fits is None else self.fits[a]
            if fit is None or fit.kind == "xyz":
                m = rp.T @ so3_exp(u * phi[a]) @ rp @ _rot_xyz(s[c])
                s = s.at[c].set(_angles_xyz(m))
                continue
            fit = jax.tree_util.tree_map(lambda x: x.astype(dt), fit)
            turned = rp.T @ so3_exp(u * phi[a]) @ tr[link, :3, :3]
            if fit.kind == "tait_bryan":
                s = s.at[c].set(fit.solve(turned, s[c]))
                continue
            here, w = rp.T @ tr[link, :3, :3], rp.T @ u * phi[a] / GN_SUBSTEPS

            def substep(k, t, fit=fit, here=here, w=w):
                return fit.solve(so3_exp(w * (k + 1).astype(w.dtype)) @ here, t)

            s = s.at[c].set(jax.lax.fori_loop(0, GN_SUBSTEPS, substep, s[c]))
        return s

    def __call__(self, x: Float[Array, "n d"], observation, key: PRNGKeyArray):
        k_inner, k_pick, k_phi, k_arm = jax.random.split(key, 4)
        if self.inner is not None:
            x = self.inner(x, observation, k_inner)
        n, n_arms = x.shape[0], len(self.arms)
        m = int(round(self.fraction * n))
        if m == 0:
            return x
        idx = jax.random.permutation(k_pick, n)[:m]
        phi = jax.random.uniform(k_phi, (m, n_arms), x.dtype, -jnp.pi, jnp.pi)
        phi = jnp.where(jax.random.bernoulli(k_arm, 0.5, (m, n_arms)), phi, 0.0)
        return x.at[idx].set(jax.vmap(self._swivel)(x[idx], phi))


def _rot_np(axis: np.ndarray, t: float) -> np.ndarray:
    return np.asarray(so3_exp(jnp.asarray(np.asarray(axis, np.float64) * t)), np.float64)


def _segment_fit(chain, path: list[int], solved: list[int], q: np.ndarray,
                 kind: str) -> ShoulderFit:
    """The :class:`ShoulderFit` of the links ``path`` (from below the start link down to the
    upper arm), the hinges of links ``solved`` free, every other joint at ``q``."""
    origin = np.asarray(chain.joint_origin, np.float64)
    axis = np.asarray(chain.joint_axis, np.float64)
    gs, axes, g = [], [], np.eye(3)
    for link in path:
        g = g @ origin[link, :3, :3]
        _, jtype, dof = chain.topology[link]
        if link in solved:
            gs.append(g)
            axes.append(axis[link])
            g = np.eye(3)
        elif jtype == REVOLUTE:
            g = g @ _rot_np(axis[link], float(q[dof]))
    gs.append(g)
    gs, axes = np.stack(gs), np.stack(axes)
    basis, sign = np.eye(3), 1.0
    if kind == "tait_bryan":  # b_i = (G_i ... G_k)^T a_i: the axes in the upper arm's frame
        b, tail = [], np.eye(3)
        for i in range(len(axes) - 1, -1, -1):
            tail = gs[i + 1] @ tail
            b.append(tail.T @ axes[i])
        b = np.stack(b[::-1], axis=1)
        sign = float(np.sign(np.linalg.det(b)))
        basis = b * np.array([1.0, 1.0, sign])
    return ShoulderFit(gs=jnp.asarray(gs), axes=jnp.asarray(axes), basis=jnp.asarray(basis),
                       kind=kind, sign=sign)


def _span(chain, links: list[int], rng: np.random.Generator) -> int:
    """The rank of the hinges' world axes at a few random poses (one pose may be singular)."""
    from jaxmocap.body.chain import fk

    best = 0
    for _ in range(3):
        q = np.zeros(chain.n_dof)
        q[6:] = rng.uniform(-1.0, 1.0, chain.n_dof - 6)
        tr = np.asarray(fk(chain, jnp.asarray(q)), np.float64)
        w = np.stack([tr[k, :3, :3] @ np.asarray(chain.joint_axis[k], np.float64)
                      for k in links]) if links else np.zeros((0, 3))
        best = max(best, int(np.linalg.matrix_rank(w, tol=1e-6)) if len(w) else 0)
    return best


def swivel_arms(model: BodyModel, dofs: np.ndarray, default_q: np.ndarray | None = None):
    """The arms whose shoulder DOFs (joint roles ``l_shoulder``/``r_shoulder``) are filtered,
    as ``(arms, fits)`` for :class:`SwivelProposal` (``fits`` None when every arm is the
    bundled x-y-z case); raises one line if a filtered shoulder cannot swivel."""
    chain, arms, fits = model.chain, [], []
    roles = require_roles(model, "stereo_pf.make_params: swivel_fraction")
    topo = chain.topology
    pos = {int(d): i for i, d in enumerate(dofs)}
    q = np.zeros(chain.n_dof) if default_q is None else np.asarray(default_q, np.float64)
    origin = np.asarray(chain.joint_origin, np.float64)
    link_of = {d: k for k, (_, t, d) in enumerate(topo) if t != FIXED}
    rng = np.random.default_rng(0)
    for joint, hand in SWIVEL_ARMS:
        names = roles.dofs(joint)
        idx = [chain.dof_names.index(n) for n in names]
        if not any(i in pos for i in idx):
            continue  # this shoulder is not filtered: nothing to swivel
        links = sorted(link_of[i] for i in idx)
        upper = links[-1]
        # the chain from the shoulder's first hinge down to the upper arm
        path = [upper]
        while path[-1] != links[0] and topo[path[-1]][0] >= 0:
            path.append(topo[path[-1]][0])
        path = path[::-1]
        hinges = [k for k in path if topo[k][1] == REVOLUTE and topo[k][2] in pos]
        if path[0] != links[0] or _span(chain, hinges, rng) < 3:
            raise InputError(
                f"stereo_pf.make_params: swivel_fraction > 0 needs the {joint} joint {names} of "
                f"{roles.source} to turn its upper arm about three axes (filtered revolute "
                f"links in one chain; filtered here: "
                f"{tuple(chain.dof_names[topo[k][2]] for k in hinges)}); give "
                "Proposals(swivel_fraction=0) for this body (jaxmocap track --pf-swivel 0)"
            )
        xyz = (
            len(idx) == 3 and all(i in pos for i in idx) and path == links
            and np.allclose(np.asarray(chain.joint_axis)[links], np.eye(3))
            and np.allclose(origin[links, :3, :3], np.eye(3))
            and np.allclose(origin[links[1:], :3, 3], 0.0)
        )
        if xyz:
            arms.append((tuple(pos[topo[k][2]] for k in links), topo[links[0]][0], upper, hand))
            fits.append(None)
            continue
        # the hinges that turn about the shoulder's centre: up from the upper arm to the first
        # link with an offset (or a sliding joint) from its parent
        ball = []
        for k in path[::-1]:
            ball.append(k)
            if topo[k][1] == PRISMATIC or not np.allclose(origin[k, :3, 3], 0.0):
                break
        ball = ball[::-1]
        centre = [k for k in ball if k in hinges]
        kind, solved, start = "gauss_newton", hinges, topo[path[0]][0]
        if len(centre) == 3 and _span(chain, centre, rng) == 3:
            fit = _segment_fit(chain, path[path.index(centre[0]):], centre, q, "tait_bryan")
            b = np.asarray(fit.basis)
            if np.allclose(b.T @ b, np.eye(3), atol=1e-6):
                kind, solved, start = "tait_bryan", centre, topo[centre[0]][0]
        seg = path if kind == "gauss_newton" else path[path.index(solved[0]):]
        fits.append(_segment_fit(chain, seg, solved, q, kind))
        arms.append((tuple(pos[topo[k][2]] for k in solved), start, upper, hand))
    if all(f is None for f in fits):
        return tuple(arms), None
    return tuple(arms), tuple(
        f if f is not None else ShoulderFit(jnp.zeros((1, 3, 3)), jnp.zeros((0, 3)),
                                            jnp.eye(3), "xyz")
        for f in fits
    )


__all__ = ["SWIVEL_ARMS", "ShoulderFit", "SwivelProposal", "swivel_arms"]
