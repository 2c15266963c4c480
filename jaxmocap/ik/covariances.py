"""IK term covariances (Wang §5.2 step 4): :class:`IKCovariances`, their file, whitening, and
their estimation from ground-truth sequences (the paper's training)."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from jaxmocap.body import KinematicChain
from jaxmocap.camera import Camera
from jaxmocap.errors import InputError
from jaxmocap.ik.anchors import PatchAnchors, project_anchors

COV_REL_RIDGE = 1e-6  # ridge added to estimated covariances, relative to their mean variance
COV_FLOOR_PX2 = 1e-6  # absolute ridge of Sigma_c (pixels^2)
COV_FLOOR_Q = 1e-10  # absolute ridge of Sigma_b, Sigma_p (m^2 or rad^2)
COV_FILE_VERSION = 1


def _check_cov(name: str, a: Array, tail: int | None) -> None:
    if tail == 2:
        if a.ndim not in (2, 3) or a.shape[-2:] != (2, 2):
            raise ValueError(f"IKCovariances.{name}: expected (2, 2) or (P, 2, 2), got {a.shape}")
    elif a.ndim not in (1, 2) or (a.ndim == 2 and a.shape[0] != a.shape[1]):
        raise ValueError(
            f"IKCovariances.{name}: expected (n_dof,) variances or (n_dof, n_dof), got {a.shape}"
        )


class CovarianceFileError(InputError):
    """An IK covariance file that is missing, malformed or not positive definite."""


class IKCovariances(eqx.Module):
    """Covariances of the three IK terms (Wang et al. §5.2 step 4).

    ``centroid``: Sigma_c, (2, 2) shared by all patches or (P, 2, 2) per patch, pixels^2.
    ``blend``: Sigma_b of q - q_b; ``prior``: Sigma_p of q - q_h. Each (n_dof, n_dof) or a
    vector (n_dof,) of variances (diagonal covariance). All must be positive definite.
    """

    centroid: Float[Array, "*patches 2 2"]
    blend: Float[Array, "n_dof n_dof"] | Float[Array, " n_dof"]
    prior: Float[Array, "n_dof n_dof"] | Float[Array, " n_dof"]

    def __check_init__(self):
        _check_cov("centroid", self.centroid, 2)
        _check_cov("blend", self.blend, None)
        _check_cov("prior", self.prior, None)
        if self.blend.shape[0] != self.prior.shape[0]:
            raise ValueError(
                f"IKCovariances: blend is for {self.blend.shape[0]} DOFs, prior for "
                f"{self.prior.shape[0]}"
            )

    @classmethod
    def isotropic(
        cls, centroid_px: float, blend_std: ArrayLike, prior_std: ArrayLike, n_dof: int
    ) -> IKCovariances:
        """Diagonal covariances from standard deviations (pixels; units of q per DOF)."""
        sb = jnp.broadcast_to(jnp.asarray(blend_std, float), (n_dof,))
        sp = jnp.broadcast_to(jnp.asarray(prior_std, float), (n_dof,))
        return cls(centroid=centroid_px**2 * jnp.eye(2), blend=sb**2, prior=sp**2)

    def save(self, path: str | os.PathLike) -> None:
        """Write the covariances to an ``.npz`` file (keys centroid, blend, prior, version)."""
        np.savez(
            path,
            centroid=np.asarray(self.centroid),
            blend=np.asarray(self.blend),
            prior=np.asarray(self.prior),
            version=np.int64(COV_FILE_VERSION),
        )

    @classmethod
    def load(cls, path: str | os.PathLike) -> IKCovariances:
        """Read covariances written by :meth:`save`; checks shapes and positive definiteness."""
        from jaxmocap.io.preflight import read_npz

        path = Path(path)
        fields = read_npz(path, "IK covariances .npz (IKCovariances.save)",
                          ("centroid", "blend", "prior", "version"), CovarianceFileError)
        if fields["version"].shape != () or int(fields["version"]) != COV_FILE_VERSION:
            raise CovarianceFileError(
                f"{path}: field 'version' is {fields['version']!r}, expected {COV_FILE_VERSION}"
            )
        for key in ("centroid", "blend", "prior"):
            a = fields[key]
            try:
                ok = np.issubdtype(a.dtype, np.floating) and np.all(np.isfinite(a)) and (
                    np.all(a > 0) if a.ndim == 1 else
                    a.ndim >= 2 and a.shape[-1] == a.shape[-2]
                    and np.all(np.linalg.eigvalsh(a) > 0)
                )
            except np.linalg.LinAlgError:
                ok = False
            if not ok:
                raise CovarianceFileError(
                    f"{path}: field {key!r} is not a positive definite covariance"
                )
        return cls(**{k: jnp.asarray(fields[k]) for k in ("centroid", "blend", "prior")})


def _whitener(cov: Array, dtype) -> Array:
    """``W`` with ``W^T W = Sigma^{-1}``: ``L^{-1}`` (Sigma = L L^T), or 1/sqrt for variances."""
    cov = cov.astype(dtype)
    if cov.ndim == 1:
        return jax.lax.rsqrt(cov)
    L = jnp.linalg.cholesky(cov)
    eye = jnp.broadcast_to(jnp.eye(cov.shape[-1], dtype=dtype), cov.shape)
    return jax.scipy.linalg.solve_triangular(L, eye, lower=True)


def _whiten(W: Array, x: Array) -> Array:
    return W * x if W.ndim == 1 else W @ x


# ----------------------------------------------------------------------------- covariance training


def _second_moment(e: Array, w: Array) -> tuple[Array, Array]:
    """(sum_n w_n e_n e_n^T, sum_n w_n) over the leading axis."""
    return jnp.einsum("n,ni,nj->ij", w, e, e), w.sum()


def _regularise(S: Array, floor: float) -> Array:
    S = 0.5 * (S + jnp.swapaxes(S, -1, -2))
    n = S.shape[-1]
    mean_var = jnp.trace(S, axis1=-2, axis2=-1) / n
    ridge = COV_REL_RIDGE * mean_var + floor
    return S + ridge[..., None, None] * jnp.eye(n, dtype=S.dtype)


ROBUST_CHI2 = 9.21  # chi^2_2 99% quantile: the inlier gate of the robust Sigma_c
ROBUST_ITERATIONS = 10


def _robust_second_moment(err: Array, w: Array, S0: Array) -> Array:
    """Sigma of the inliers of 2D errors ``err`` (n, 2) with weights ``w``: errors with
    Mahalanobis^2 < ROBUST_CHI2 under the current estimate are kept, their second moment is
    corrected for the truncation of a Gaussian at that radius, and this is iterated from
    ``S0``. For Gaussian data it is the ML covariance; outliers (misclassified patches) get
    no weight."""
    c = ROBUST_CHI2
    # E[e e^T | m^2 < c] = S (1 - exp(-c/2)(1 + c/2)) / (1 - exp(-c/2)) for a 2D Gaussian
    shrink = (1 - np.exp(-c / 2) * (1 + c / 2)) / (1 - np.exp(-c / 2))

    def body(_, S):
        m2 = jnp.einsum("ni,ij,nj->n", err, jnp.linalg.inv(S), err)
        wi = w * (m2 < c)
        S_in, n_in = _second_moment(err, wi)
        S_new = S_in / jnp.maximum(n_in, 1.0) / shrink
        return jnp.where(n_in >= 3, _regularise(S_new, COV_FLOOR_PX2), S)

    return jax.lax.fori_loop(0, ROBUST_ITERATIONS, body, S0)


@functools.partial(jax.jit, static_argnames=("per_patch", "robust", "diagonal"))
def estimate_covariances(
    cams: Camera,
    chain: KinematicChain,
    anchors: PatchAnchors,
    q_gt: Float[Array, "n_frames n_dof"],
    centroids: Float[Array, "n_frames n_cams n_patches 2"],
    visible: Bool[Array, "n_frames n_cams n_patches"],
    q_b: Float[Array, "n_frames n_dof"],
    *,
    per_patch: bool = False,
    predicted: Float[Array, "n_frames n_cams n_patches 2"] | None = None,
    robust: bool = False,
    diagonal: bool = False,
    q_h: Float[Array, "n_frames n_dof"] | None = None,
    min_centroid_std: float | Float[Array, ""] = 0.0,
    sequence_start: Bool[Array, " n_frames"] | None = None,
) -> IKCovariances:
    """Train Sigma_c, Sigma_b, Sigma_p on a ground-truth sequence (Wang et al. §5.2 step 4).

    As in the paper, q is replaced by the ground truth in each term and the covariance of the
    term is taken over the sequence:

        Sigma_c = E[(c^{*i}_k(q_gt) - c^{ki})(...)^T]  over visible patches, cameras, frames
        Sigma_b = E[(q_gt - q_b)(...)^T]               over frames
        Sigma_p = E[(q_gt[t] - q_gt[t-1])(...)^T]      over consecutive frames

    The moments are taken about zero, the maximum-likelihood covariance of the zero-mean
    Gaussian that the energy assumes (a bias in the errors is thus counted as error). Each is
    symmetrised and given a small ridge (``COV_REL_RIDGE`` of its mean variance plus
    ``COV_FLOOR_*``), so DOFs that never vary stay positive definite. With ``per_patch``,
    Sigma_c is (P, 2, 2), patch k's moment shrunk by one pseudo-observation of the shared
    Sigma_c (patches rarely or never seen fall back to it). ``predicted`` gives the model's
    centroids at the ground truth directly (e.g. from a render of ``q_gt`` in the tracker's
    crops, what per-view anchors predict there); default: ``anchors`` projected at ``q_gt``.
    ``robust`` (not in the paper) estimates Sigma_c from the inliers only (iterated 99%
    chi-square gate with the truncation corrected, :func:`_robust_second_moment`): the scale
    of the centroid noise that the IK's robust term (``solve_ik(robust=...)``) assumes, not
    inflated by the gross errors of misclassified patches. ``diagonal`` keeps only the
    variances of Sigma_b and Sigma_p: with fewer frames than DOFs their full moments are
    rank-deficient and the ridge alone would make the priors almost rigid along every
    direction the training frames did not move in. ``q_h`` are the poses the temporal term
    compared with at each frame (the tracker's previous output: ``q_h[t] = q*[t - 1]``, row 0
    unused); Sigma_p is then ``E[(q_gt[t] - q_h[t])(...)^T]``, the term as the tracker
    evaluates it, tracking error included (default: the ground truth's previous frame, the
    pure motion). ``min_centroid_std`` (pixels) floors the variances of Sigma_c (e.g. at the
    tracker's working-grid pixel, below which its centroids are not resolved).
    ``sequence_start`` marks the first frame of each of several training sequences stacked
    along the frame axis (pooled training): a frame so marked has no temporal term (its
    predecessor belongs to another sequence); frame 0 never has one.
    """
    if q_gt.ndim != 2 or q_gt.shape[0] < 2 or q_b.shape != q_gt.shape:
        raise ValueError(
            f"estimate_covariances: need q_gt and q_b (n_frames >= 2, n_dof) of equal shape; got "
            f"{q_gt.shape} and {q_b.shape}"
        )
    n_f, n_dof = q_gt.shape
    if visible.shape != (n_f, cams.K.shape[0], anchors.n_patches):
        raise ValueError(
            f"estimate_covariances: visible {visible.shape}, expected "
            f"({n_f}, {cams.K.shape[0]}, {anchors.n_patches})"
        )
    dt = q_gt.dtype
    if predicted is None:
        proj = jax.vmap(project_anchors, in_axes=(None, None, None, 0))(cams, chain, anchors, q_gt)
    else:
        proj = predicted.astype(dt)
    vis = jnp.asarray(visible, bool)
    err = jnp.where(vis[..., None], proj - centroids.astype(dt), 0.0)  # (T, C, P, 2)
    w = vis.astype(dt)
    S_all, n_all = _second_moment(err.reshape(-1, 2), w.reshape(-1))
    shared = _regularise(S_all / jnp.maximum(n_all, 1.0), COV_FLOOR_PX2)
    if robust:
        shared = _robust_second_moment(err.reshape(-1, 2), w.reshape(-1), shared)
    # raise the variances to the floor (the diagonal only: correlations are kept)
    var = jnp.diagonal(shared)
    shared = shared + jnp.diag(jnp.maximum(jnp.asarray(min_centroid_std, dt) ** 2 - var, 0.0))
    if per_patch:
        S_p = jnp.einsum("tcp,tcpi,tcpj->pij", w, err, err)
        n_p = w.sum((0, 1))
        sigma_c = (S_p + shared[None]) / (n_p + 1.0)[:, None, None]
        sigma_c = _regularise(sigma_c, COV_FLOOR_PX2)
    else:
        sigma_c = shared
    ones = jnp.ones(n_f, dt)
    Sb, nb = _second_moment(q_gt - q_b.astype(dt), ones)
    prev = q_gt[:-1] if q_h is None else q_h[1:].astype(dt)
    w_p = ones[1:]
    if sequence_start is not None:
        if sequence_start.shape != (n_f,):
            raise ValueError(
                f"estimate_covariances: sequence_start {sequence_start.shape}, expected ({n_f},)"
            )
        w_p = jnp.where(jnp.asarray(sequence_start, bool)[1:], 0.0, w_p)
    Sp, np_ = _second_moment(q_gt[1:] - prev, w_p)
    blend = _regularise(Sb / nb, COV_FLOOR_Q)
    prior = _regularise(Sp / jnp.maximum(np_, 1.0), COV_FLOOR_Q)
    if diagonal:
        blend, prior = jnp.diagonal(blend), jnp.diagonal(prior)
    return IKCovariances(centroid=sigma_c, blend=blend, prior=prior)


def append_centroid_covariances(cov: IKCovariances, n_patches: int,
                                more: Float[Array, "k 2 2"]) -> IKCovariances:
    """``cov`` with ``more`` (k, 2, 2) appended to Sigma_c after its ``n_patches`` patches (a
    shared (2, 2) Sigma_c repeated per patch): the covariances of extra 2D terms solved beside
    the patch centroids (:func:`jaxmocap.ik.append_anchors`)."""
    c = cov.centroid
    c = jnp.broadcast_to(c, (n_patches, 2, 2)) if c.ndim == 2 else c
    return eqx.tree_at(lambda x: x.centroid, cov,
                       jnp.concatenate([c, more.astype(c.dtype)], axis=0))
