"""Rotations, one home for the whole package (floor 1: imports nothing of jaxmocap).

SO(3) exp / log, its left Jacobian and the cross-product matrix (NaN-safe near 0 as jaxlie:
a "safe where" before each division, a Taylor branch below a per-dtype threshold), quaternions,
Euler angles, batched 3x3 products, axis-swap constants, and a NumPy Rodrigues for file I/O.

Conventions: quaternions are ``(w, x, y, z)`` (DeepMimic's order), rotation matrices act on
column vectors, rotation vectors are ``angle * unit axis`` (rad). Every function broadcasts
over leading axes and follows the dtype of its input.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


def _lead(a: Array, b: Array, core_a: int, core_b: int) -> tuple[Array, Array]:
    """Give ``a`` and ``b`` the same number of batch axes (explicit rank promotion)."""
    na, nb = a.ndim - core_a, b.ndim - core_b
    n = max(na, nb)
    return a.reshape((1,) * (n - na) + a.shape), b.reshape((1,) * (n - nb) + b.shape)


def mm(a: Float[Array, "*a 3 3"], b: Float[Array, "*b 3 3"]) -> Float[Array, "... 3 3"]:
    """``a @ b`` for stacks of 3x3 matrices as a broadcast multiply-add (fuses; no dot ops)."""
    a, b = _lead(a, b, 2, 2)
    return (a[..., :, :, None] * b[..., None, :, :]).sum(-2)


def mv(a: Float[Array, "*a 3 3"], v: Float[Array, "*b 3"]) -> Float[Array, "... 3"]:
    """``a @ v`` for stacks of 3x3 matrices and 3-vectors (broadcast multiply-add)."""
    a, v = _lead(a, v, 2, 1)
    return (a * v[..., None, :]).sum(-1)


def mtm(a: Float[Array, "*a 3 3"], b: Float[Array, "*b 3 3"]) -> Float[Array, "... 3 3"]:
    """``a^T @ b`` (broadcast multiply-add)."""
    a, b = _lead(a, b, 2, 2)
    return (a[..., :, :, None] * b[..., :, None, :]).sum(-3)


def normalize_quat(q: Float[Array, "*b 4"]) -> Float[Array, "*b 4"]:
    """Unit quaternion ``q / |q|`` (DeepMimic clips store slightly non-unit ones)."""
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def quat_to_matrix(q: Float[Array, "*b 4"]) -> Float[Array, "*b 3 3"]:
    """Rotation matrix of a quaternion ``(w, x, y, z)``; normalises first."""
    w, x, y, z = jnp.moveaxis(normalize_quat(q), -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def matrix_to_quat(r: Float[Array, "*b 3 3"]) -> Float[Array, "*b 4"]:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix.

    Shepperd's method without branches: the four candidate formulas are evaluated and the
    one with the largest (well-conditioned) diagonal term is selected.
    """
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    tr = m00 + m11 + m22
    cands = jnp.stack(
        [
            jnp.stack([1 + tr, r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
                       r[..., 1, 0] - r[..., 0, 1]], -1),
            jnp.stack([r[..., 2, 1] - r[..., 1, 2], 1 + m00 - m11 - m22,
                       r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0]], -1),
            jnp.stack([r[..., 0, 2] - r[..., 2, 0], r[..., 0, 1] + r[..., 1, 0],
                       1 - m00 + m11 - m22, r[..., 1, 2] + r[..., 2, 1]], -1),
            jnp.stack([r[..., 1, 0] - r[..., 0, 1], r[..., 0, 2] + r[..., 2, 0],
                       r[..., 1, 2] + r[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        -2,
    )
    best = jnp.argmax(jnp.stack([tr, m00, m11, m22], -1), axis=-1)
    q = jnp.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = normalize_quat(q)
    return jnp.where(q[..., :1] < 0, -q, q)


def quat_to_rotvec(q: Float[Array, "*b 4"]) -> Float[Array, "*b 3"]:
    """Rotation vector (rad) of a quaternion, angle in ``[0, pi]``; NaN-free at identity."""
    q = normalize_quat(q)
    q = jnp.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s2 = jnp.sum(v * v, axis=-1)
    small = s2 < jnp.finfo(q.dtype).eps
    s = jnp.sqrt(jnp.where(small, jnp.ones_like(s2), s2))
    scale = jnp.where(small, 2.0 / q[..., 0], 2.0 * jnp.arctan2(s, q[..., 0]) / s)
    return v * scale[..., None]


def matrix_to_rotvec(r: Float[Array, "*b 3 3"]) -> Float[Array, "*b 3"]:
    """Rotation vector ``w`` with ``exp([w]_x) = r`` (the SO(3) log), ``|w| <= pi``."""
    return quat_to_rotvec(matrix_to_quat(r))


def slerp(q0: Float[Array, "*b 4"], q1: Float[Array, "*b 4"], u: Float[Array, "*#c"]
          ) -> Float[Array, "*b 4"]:
    """Spherical linear interpolation along the shorter arc, ``u`` in [0, 1] (broadcast
    against the leading axes of ``q0``)."""
    q0, q1 = normalize_quat(q0), normalize_quat(q1)
    d = jnp.sum(q0 * q1, axis=-1)
    q1 = jnp.where(d[..., None] < 0, -q1, q1)
    d = jnp.abs(d)
    near = d > 1 - 1e3 * jnp.finfo(q0.dtype).eps
    theta = jnp.arccos(jnp.clip(jnp.where(near, 0.5, d), -1.0, 1.0))
    s = jnp.sin(theta)
    a = jnp.where(near, 1 - u, jnp.sin((1 - u) * theta) / s)
    b = jnp.where(near, u, jnp.sin(u * theta) / s)
    return normalize_quat(a[..., None] * q0 + b[..., None] * q1)


def axis_angle_matrix(axis: Float[Array, "*#b 3"], angle: Float[Array, "*#b"]
                      ) -> Float[Array, "*b 3 3"]:
    """Rotation by ``angle`` (rad) about the unit ``axis`` (Rodrigues)."""
    x, y, z = jnp.moveaxis(axis, -1, 0)
    o = jnp.zeros_like(x)
    k = jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1),
                   jnp.stack([-y, x, o], -1)], -2)
    s, c = jnp.sin(angle)[..., None, None], jnp.cos(angle)[..., None, None]
    eye = jnp.broadcast_to(jnp.eye(3, dtype=k.dtype), k.shape)
    return eye + s * k + (1 - c) * mm(k, k)


def euler_xyz(r: Float[Array, "*b 3 3"]) -> Float[Array, "*b 3"]:
    """Angles ``(a, b, c)`` with ``r = Rx(a) @ Ry(b) @ Rz(c)`` (intrinsic x-y-z), rad.

    ``b`` lies in ``[-pi/2, pi/2]``; at the gimbal lock ``|b| = pi/2`` the split between
    ``a`` and ``c`` is arbitrary (``c = 0`` is returned there).
    """
    r02 = jnp.clip(r[..., 0, 2], -1.0, 1.0)
    cb = jnp.hypot(r[..., 0, 0], r[..., 0, 1])
    b = jnp.arctan2(r02, cb)
    lock = cb < 1e3 * jnp.finfo(r.dtype).eps
    a = jnp.where(lock, jnp.arctan2(r[..., 2, 1], r[..., 1, 1]),
                  jnp.arctan2(-r[..., 1, 2], r[..., 2, 2]))
    c = jnp.where(lock, jnp.zeros_like(b), jnp.arctan2(-r[..., 0, 1], r[..., 0, 0]))
    return jnp.stack([a, b, c], -1)


# Y-up source frames (DeepMimic, BVH: x forward, y up, z to the right) -> our Z-up world
# (x forward, y left, z up): v_ours = Y_UP_TO_Z_UP @ v_source, a +90 deg turn about x.
Y_UP_TO_Z_UP = ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0))


# ----------------------------------------------------------------------------- SO(3)


def skew(w: Float[Array, "*b 3"]) -> Float[Array, "*b 3 3"]:
    """The cross-product matrix ``[w]_x`` (``[w]_x v = w x v``), batched."""
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2
    )


def so3_exp(w: Float[Array, "*b 3"]) -> Float[Array, "*b 3 3"]:
    """Rotation matrix ``exp([w]_x)`` of a rotation vector ``w`` (rad), Rodrigues' formula.

    NaN-free values and gradients at ``w = 0``: the "safe where" substitutes a dummy angle
    before the division and a Taylor branch is used below a per-dtype threshold (as jaxlie).
    """
    theta2 = jnp.sum(w * w, axis=-1)
    small = theta2 < jnp.sqrt(jnp.finfo(w.dtype).eps)
    theta2_safe = jnp.where(small, jnp.ones_like(theta2), theta2)
    theta_safe = jnp.sqrt(theta2_safe)
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta_safe) / theta_safe)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta_safe)) / theta2_safe)
    k = skew(w)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=w.dtype), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(R: Float[Array, "3 3"]) -> Float[Array, 3]:
    """Rotation vector (rad) of a rotation matrix; the inverse of ``so3_exp`` on |w| <= pi.

    Through the unit quaternion by Shepperd's method (largest diagonal pivot), so it is
    accurate near 0 and near pi; NaN-free ("safe where" before the division).
    """
    m00, m11, m22 = R[0, 0], R[1, 1], R[2, 2]
    tr = m00 + m11 + m22
    a, b, c = R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]  # antisymmetric part
    d, e, f = R[0, 1] + R[1, 0], R[0, 2] + R[2, 0], R[1, 2] + R[2, 1]  # symmetric part
    cands = jnp.stack(
        [
            jnp.stack([1 + tr, a, b, c]),
            jnp.stack([a, 1 + m00 - m11 - m22, d, e]),
            jnp.stack([b, d, 1 - m00 + m11 - m22, f]),
            jnp.stack([c, e, f, 1 - m00 - m11 + m22]),
        ]
    )
    quat = cands[jnp.argmax(jnp.stack([tr, m00, m11, m22]))]
    quat = quat / jnp.linalg.norm(quat)
    quat = jnp.where(quat[0] < 0, -quat, quat)
    w, v = quat[0], quat[1:]
    vn2 = jnp.sum(v * v)
    small = vn2 < jnp.finfo(R.dtype).eps
    vn = jnp.sqrt(jnp.where(small, 1.0, vn2))
    scale = jnp.where(small, 2.0 / w - (2.0 / 3.0) * vn2 / w**3, 2.0 * jnp.arctan2(vn, w) / vn)
    return scale * v


def so3_left_jacobian(w: Float[Array, " 3"]) -> Float[Array, "3 3"]:
    """J_l(w) = I + (1 - cos t) / t^2 [w]_x + (t - sin t) / t^3 [w]_x^2, t = |w| (Taylor
    branch near 0, "safe where" so that values and gradients stay finite)."""
    t2 = jnp.sum(w * w)
    small = t2 < jnp.sqrt(jnp.finfo(w.dtype).eps)
    t2s = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(t2s)
    a = jnp.where(small, 0.5 - t2 / 24.0, (1.0 - jnp.cos(t)) / t2s)
    b = jnp.where(small, 1.0 / 6.0 - t2 / 120.0, (t - jnp.sin(t)) / (t2s * t))
    k = skew(w)
    return jnp.eye(3, dtype=w.dtype) + a * k + b * (k @ k)


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """NumPy rotation matrix of a rotation vector (float64; ``cameras.json``'s ``rvec``)."""
    theta = float(np.linalg.norm(rvec))
    if theta < 1e-12:
        return np.eye(3) + _skew_np(rvec)
    k = rvec / theta
    Kx = _skew_np(k)
    return np.eye(3) + math.sin(theta) * Kx + (1 - math.cos(theta)) * (Kx @ Kx)


def _skew_np(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=float)
