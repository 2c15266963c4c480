"""The package's rotations (jaxmocap.rotations) against SciPy and finite differences: SO(3)
exp / log and the left Jacobian, NaN-free near the identity (values and gradients), jit and
vmap; the NumPy Rodrigues of the camera files. (Quaternion / Euler conversions: the clip
decoding tests in test_synth_motion / test_synth; so3_exp: test_body_chain.)"""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from jaxmocap import rotations as rot


def test_skew_is_the_cross_product(rng):
    w, v = rng.normal(size=(2, 5, 3))
    np.testing.assert_allclose(np.einsum("bij,bj->bi", rot.skew(jnp.asarray(w)), v),
                               np.cross(w, v), rtol=1e-12)


def test_exp_log_against_scipy(rng):
    w = rng.normal(size=(50, 3))
    w *= rng.uniform(0, 3.1, size=(50, 1)) / np.linalg.norm(w, axis=1, keepdims=True)
    w[0] = 0.0
    w[1] = [1e-9, 0, 0]
    R = np.asarray(jax.jit(rot.so3_exp)(jnp.asarray(w)))
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-12)
    back = np.asarray(jax.vmap(rot.so3_log)(jnp.asarray(R)))
    np.testing.assert_allclose(back, w, atol=1e-9)


def test_left_jacobian_against_finite_differences(rng):
    """exp(w + e) = exp(J_l(w) e) exp(w) to first order in e."""
    for w in (rng.normal(size=3), np.array([1e-7, -2e-7, 0.0]), np.zeros(3)):
        J = np.asarray(rot.so3_left_jacobian(jnp.asarray(w)))
        R = np.asarray(rot.so3_exp(jnp.asarray(w)))
        for k in range(3):
            e = 1e-6 * np.eye(3)[k]
            d = np.asarray(rot.so3_exp(jnp.asarray(w + e))) @ R.T
            np.testing.assert_allclose(Rotation.from_matrix(d).as_rotvec(), J @ e, atol=1e-11)


def test_nan_free_gradients_at_the_identity():
    z = jnp.zeros(3)
    for f in (lambda w: rot.so3_exp(w).sum(), lambda w: rot.so3_left_jacobian(w).sum(),
              lambda w: rot.so3_log(rot.so3_exp(w)).sum()):
        assert np.all(np.isfinite(np.asarray(jax.grad(f)(z))))
    # d/dw exp(w) at 0 is skew(e_k)
    jac = jax.jacfwd(rot.so3_exp)(z)
    for k in range(3):
        np.testing.assert_allclose(jac[:, :, k], rot.skew(jnp.eye(3)[k]), atol=1e-15)


def test_numpy_rodrigues(rng):
    for w in (rng.normal(size=3), np.zeros(3), np.array([1e-13, 0, 0])):
        np.testing.assert_allclose(rot.rodrigues(w), Rotation.from_rotvec(w).as_matrix(),
                                   atol=1e-12)
