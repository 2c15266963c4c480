"""Inverse kinematics from shirt-patch centroids (Wang et al. 2011, §5.2 steps 2 and 4).

Step 2 (global pose): the blended database pose ``q_b`` fixes the joint angles but not where
the body stands; a 6-DOF solve over the root translation and rotation matches the patch
centroids in every camera.

Step 4 (refinement): over all DOFs (or a chosen subset),

    q* = argmin_q  sum_{i,k} ||c^{*i}_k(q) - c^{ki}||^2_{Sigma_c}
                   + ||q - q_b||^2_{Sigma_b} + ||q - q_h||^2_{Sigma_p}

with ``||x||^2_Sigma = x^T Sigma^{-1} x``, ``c^{ki}`` (pixels) the observed centroid of patch
k in camera i, ``q_b`` the blended pose and ``q_h`` the pose of the previous frame.

**Patch anchors.** The paper takes ``c^{*i}(q)`` from the centroids of a rendered id map,
which is piecewise constant in q. Here each patch's 3D centroid is a point fixed in the frame
of the link that carries it (:class:`PatchAnchors`), computed once from the garment, and
``c^{*i}_k(q) = project(cam_i, T_link(q) @ offset_k)``: a smooth residual that Gauss-Newton
and implicit differentiation can use.

**Whitening.** Every term is turned into ordinary least squares with the Cholesky factor
``Sigma = L L^T``: ``||x||^2_Sigma = ||L^{-1} x||^2``. Diagonal covariances may be given as
vectors of variances. Missing / occluded patches have weight 0 (their residual is replaced by
0 before anything else, so NaN centroids are harmless).

**Joint limits** are kept by a smooth reparametrisation: each DOF with finite limits
``[l, u]`` is written ``q = (u + l)/2 + (u - l)/2 tanh(z)`` and the solve runs over ``z``.
Every iterate, hence the solution, lies inside the limits; a target beyond a limit drives
``z`` towards infinity and ``q`` to the limit. DOFs without finite limits (the root) are
solved directly. Gradients through the solve use optimistix' implicit adjoint (the implicit
function theorem on the normal equations); its linear solve is an SVD so that a DOF pinned
at a limit (zero Jacobian column) contributes no gradient instead of NaN.

Units: metres, radians, pixels. Covariances: pixels^2 (Sigma_c), the squared units of q
(Sigma_b, Sigma_p).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.custom_derivatives import SymbolicZero
from jax.dtypes import float0
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PyTree

from jaxmocap.body import ROOT_DOFS, BodyModel, KinematicChain, fk
from jaxmocap.camera import Camera, project, triangulate
from jaxmocap.errors import InputError
from jaxmocap.garment import Garment
from jaxmocap.render import patch_surface_points
from jaxmocap.rotations import so3_exp, so3_log

DEFAULT_MAX_STEPS = 64  # fixed iteration budget of every IK solve (static: sets the program)
DEFAULT_RTOL = 1e-7  # relative tolerance on z and on the whitened residuals (traced)
DEFAULT_ATOL = 1e-9  # absolute tolerance (traced)
LIMIT_MARGIN = 1e-6  # initial guesses on a limit start this fraction of the half range inside
MIN_KABSCH_PATCHES = 3  # a rigid fit needs 3 non-collinear triangulated anchors
KABSCH_MIN_SPREAD = 1e-6  # 2nd singular value / 1st below this: anchors collinear, fit refused
COV_REL_RIDGE = 1e-6  # ridge added to estimated covariances, relative to their mean variance
COV_FLOOR_PX2 = 1e-6  # absolute ridge of Sigma_c (pixels^2)
COV_FLOOR_Q = 1e-10  # absolute ridge of Sigma_b, Sigma_p (m^2 or rad^2)
COV_FILE_VERSION = 1

# Solution of the normal equations in the implicit adjoint: SVD (pseudo-inverse), so that a DOF
# saturated at a joint limit simply has zero sensitivity.
_OPTIONS = {"jac": "fwd"}  # forward-mode Jacobians: fewer ops than reverse for n_dof < n_res
_ADJOINT = optx.ImplicitAdjoint(linear_solver=lx.AutoLinearSolver(well_posed=False))


# ----------------------------------------------------------------------------- patch anchors


class PatchAnchors(eqx.Module):
    """The 3D centroid of every shirt patch as a point fixed in the frame of its link.

    ``link`` (P,) link index, ``offset`` (P, 3) metres in that link's frame: one anchor per
    patch shared by all cameras (:func:`anchors_from_garment`). **Per-view anchors**
    (:func:`view_anchors`) carry a leading camera axis, ``offset`` (C, P, 3), plus a pixel
    ``shift`` (C, P, 2) added to the projection, so that each camera predicts the centroid of
    the patch's *visible* part: ``c^{*i}_k(q) = project(cam_i, T_link(q) offset_ik) + shift_ik``.
    """

    link: Int[Array, " n_patches"]
    offset: Float[Array, "*cams n_patches 3"]
    shift: Float[Array, "*cams n_patches 2"] | None = None

    def __check_init__(self):
        if self.link.shape[0] != self.offset.shape[-2]:
            raise ValueError(
                f"PatchAnchors: link has {self.link.shape[0]} rows, offset "
                f"{self.offset.shape[-2]}; expected one of each per patch"
            )
        if self.offset.ndim not in (2, 3):
            raise ValueError(f"PatchAnchors: offset must be (P, 3) or (C, P, 3), got "
                             f"{self.offset.shape}")  # fmt: skip
        if self.shift is not None and self.shift.shape != self.offset.shape[:-1] + (2,):
            raise ValueError(
                f"PatchAnchors: shift {self.shift.shape}, expected {self.offset.shape[:-1] + (2,)}"
            )

    @property
    def n_patches(self) -> int:
        return self.offset.shape[-2]

    @property
    def per_view(self) -> bool:
        """Whether the anchors differ per camera (:func:`view_anchors`)."""
        return self.offset.ndim == 3


def anchors_from_samples(
    link: Int[ArrayLike, " n_patches"],
    points: Float[ArrayLike, "n_patches n_samples 3"],
    weights: Float[ArrayLike, "n_patches n_samples"] | None = None,
) -> PatchAnchors:
    """Patch anchors as the (weighted) mean of surface samples of each patch region.

    ``points[k]`` are samples of patch k's surface expressed in the frame of ``link[k]``
    (metres); ``weights`` (default uniform) e.g. area weights, 0 for padding samples.
    """
    link = np.asarray(link)
    pts = jnp.asarray(points)
    if link.ndim != 1 or pts.ndim != 3 or pts.shape[0] != link.shape[0] or pts.shape[2] != 3:
        raise ValueError(
            f"anchors_from_samples: expected link (P,) and points (P, S, 3); got link "
            f"{link.shape} and points {pts.shape}"
        )
    w = jnp.ones(pts.shape[:2], pts.dtype) if weights is None else jnp.asarray(weights, pts.dtype)
    if w.shape != pts.shape[:2]:
        raise ValueError(f"anchors_from_samples: weights {w.shape}, expected {pts.shape[:2]}")
    total = w.sum(axis=1)
    if np.any(np.asarray(total) <= 0):
        raise ValueError(
            "anchors_from_samples: patches "
            f"{np.flatnonzero(np.asarray(total) <= 0).tolist()} have no sample of positive weight"
        )
    offset = jnp.einsum("ps,psd->pd", w, pts) / total[:, None]
    return PatchAnchors(link=jnp.asarray(link, jnp.int32), offset=offset)


def anchors_from_garment(model: BodyModel, garment: Garment, dtype=None) -> PatchAnchors:
    """Patch anchors of a garment: the mean of the surface samples of each patch region.

    Samples come from :func:`jaxmocap.render.patch_surface_points` (points on the patch's
    geom, in the geom frame, kept where the patch's half-spaces hold) and are moved into the
    frame of the geom's link. Patch k of the result is patch id k + 1 of the garment.
    """
    dtype = dtype or model.geometry.pose.dtype
    pts, valid = patch_surface_points(model, garment, dtype)  # (P, S, 3) geom frame
    pose = model.geometry.pose.astype(dtype)[garment.patch_geom]  # geom -> link coordinates
    pts_link = jnp.einsum("pij,psj->psi", pose[:, :3, :3], pts) + pose[:, None, :3, 3]
    link = np.asarray(model.geometry.link)[np.asarray(garment.patch_geom)]
    return anchors_from_samples(link, pts_link, valid.astype(dtype))


def anchor_positions(
    chain: KinematicChain, anchors: PatchAnchors, q: Float[Array, " n_dof"]
) -> Float[Array, "*cams n_patches 3"]:
    """World positions (metres) of the patch anchors at pose q: ``T_link(q) @ offset``
    ((P, 3), or (C, P, 3) for per-view anchors)."""
    T = fk(chain, q)[anchors.link]
    off = anchors.offset.astype(q.dtype)
    X = jnp.einsum("pij,...pj->...pi", T[:, :3, :3], off)
    return X + T[:, :3, 3].reshape((1,) * (X.ndim - 2) + T.shape[:1] + (3,))


def _project_all(cams: Camera, X: Float[Array, "*c n 3"]) -> Float[Array, "n_cams n 2"]:
    if X.ndim == 3:  # one point set per camera
        return jax.vmap(project)(cams, X)
    return jax.vmap(project, in_axes=(0, None))(cams, X)


def _project_anchor_points(cams: Camera, X: Array, shift: Array | None) -> Array:
    c = _project_all(cams, X)
    return c if shift is None else c + shift.astype(c.dtype)


def project_anchors(
    cams: Camera, chain: KinematicChain, anchors: PatchAnchors, q: Float[Array, " n_dof"]
) -> Float[Array, "n_cams n_patches 2"]:
    """Projected anchors ``c^{*i}_k(q)`` (pixels) in every camera of a stacked Camera."""
    return _project_anchor_points(cams, anchor_positions(chain, anchors, q), anchors.shift)


VIEW_MIN_PIXELS = 4  # rendered pixels a patch needs in a view for a per-view anchor


def view_anchors(
    chain: KinematicChain,
    anchors: PatchAnchors,
    cams: Camera,
    q_ref: Float[Array, " n_dof"],
    patch: Int[Array, "n_cams h w"],
    point: Float[Array, "n_cams h w 3"],
    uv: Float[Array, "n_cams h w 2"],
    min_pixels: int = VIEW_MIN_PIXELS,
) -> PatchAnchors:
    """Per-view anchors from a render of the model at ``q_ref`` (the paper's rendered
    centroids, made smooth in q).

    Wang et al. compare the observed centroids with the centroids of the model's *rendered*
    patches, which are piecewise constant in q. Here every rendered pixel of patch k in camera
    i (``patch`` ids, world hit ``point`` at pixel position ``uv``, e.g. the ``Hits`` of
    :func:`jaxmocap.render.render_uv` on the tracker's crop grid) is carried rigidly by the
    patch's link: the anchor is the mean of those hit points in the link frame and ``shift``
    the difference between the rendered 2D centroid and the anchor's projection at
    ``q_ref``. So at ``q_ref`` the prediction equals the rendered visible-part centroid
    exactly, and near it the prediction moves with the link (visibility frozen). Patches
    with fewer than ``min_pixels`` rendered pixels in a view keep the shared anchor of
    ``anchors`` and no shift. Not differentiated w.r.t. the render (stop_gradient).
    """
    if anchors.per_view:
        raise ValueError("view_anchors: anchors must be the shared (P, 3) anchors")
    dt = q_ref.dtype
    P = anchors.n_patches
    n_cams = cams.K.shape[0]
    T = fk(chain, q_ref)[anchors.link]  # (P, 4, 4) at the reference pose
    seg = jnp.clip(patch.reshape(n_cams, -1), 0, P + 1)  # ids > P go to a discarded bin
    pts = point.reshape(n_cams, -1, 3).astype(dt)
    pix = uv.reshape(n_cams, -1, 2).astype(dt)
    fg = (seg >= 1) & (seg <= P)
    pts = jnp.where(fg[..., None], pts, 0.0)  # background points are inf

    def per_cam(seg_c, pts_c, pix_c, fg_c):
        k = jnp.clip(seg_c - 1, 0, P - 1)
        Tk = T[k]  # link of each pixel's patch
        local = jnp.einsum("nji,nj->ni", Tk[:, :3, :3], pts_c - Tk[:, :3, 3])  # R^T (X - t)
        w = fg_c.astype(dt)
        sums = jax.ops.segment_sum(local * w[:, None], seg_c, P + 2)[1 : P + 1]
        sum_uv = jax.ops.segment_sum(pix_c * w[:, None], seg_c, P + 2)[1 : P + 1]
        count = jax.ops.segment_sum(w, seg_c, P + 2)[1 : P + 1]
        safe = jnp.maximum(count, 1.0)[:, None]
        return sums / safe, sum_uv / safe, count

    off, c2d, count = jax.vmap(per_cam)(seg, pts, pix, fg)
    use = count >= min_pixels
    off = jnp.where(use[..., None], off, anchors.offset.astype(dt)[None])
    X = jnp.einsum("pij,cpj->cpi", T[:, :3, :3], off) + T[None, :, :3, 3]
    shift = jnp.where(use[..., None], c2d - jax.vmap(project)(cams, X), 0.0)
    return jax.lax.stop_gradient(PatchAnchors(anchors.link, off, shift))


# ----------------------------------------------------------------------------- covariances


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


# ----------------------------------------------------------------------------- residuals


def _zero_tangent(t):
    if not isinstance(t, SymbolicZero):
        return t
    return (
        np.zeros(t.aval.shape, t.aval.dtype)
        if t.aval.dtype == float0
        else jnp.zeros(t.aval.shape, t.aval.dtype)
    )


def _dense_jacobian(f):
    """``f(y, args)`` whose JVP in ``y`` builds the Jacobian once (vmapped forward mode).

    Gauss-Newton solvers call the linearised residual several times per step (Jacobian
    materialisation, predicted reduction, its transpose). With this rule those calls are
    matrix products with one dense ``J``, instead of re-emitting the linearised forward
    kinematics each time: a much smaller program (compile time) and fewer flops per step.
    Tangents in ``args`` (e.g. covariances, under ``jax.grad``) go through an ordinary JVP.
    """

    @jax.custom_jvp
    def g(y, args):
        return f(y, args)

    @functools.partial(g.defjvp, symbolic_zeros=True)
    def g_jvp(primals, tangents):
        y, args = primals
        ty, targs = tangents
        if isinstance(ty, SymbolicZero):
            out = f(y, args)
            tout = jnp.zeros_like(out)
        else:
            basis = jnp.eye(y.shape[0], dtype=y.dtype)
            push = lambda v: jax.jvp(lambda y_: f(y_, args), (y,), (v,))
            out, J = jax.vmap(push, out_axes=(None, -1))(basis)
            tout = J @ ty
        is_zero = lambda t: isinstance(t, SymbolicZero)
        if not all(map(is_zero, jax.tree.leaves(targs, is_leaf=is_zero))):
            targs = jax.tree.map(_zero_tangent, targs, is_leaf=is_zero)
            tout = tout + jax.jvp(lambda a: f(y, a), (args,), (targs,))[1]
        return out, tout

    return g


class _Terms(eqx.Module):
    """Everything the residual needs, passed as optimistix ``args`` (so it is differentiated)."""

    chain: KinematicChain
    cams: Camera
    anchors: PatchAnchors
    obs: Array  # (C, P, 2) observed centroids, 0 where invisible
    vis: Array  # (C, P) bool
    q_b: Array
    q_h: Array
    Wc: Array  # (P, 2, 2)
    Wb: Array
    Wp: Array
    robust: Array  # () Cauchy scale of the whitened centroid residuals; inf: plain squares


def robust_centroid_residual(r: Float[Array, "*b 2"], scale: Float[Array, ""]) -> Array:
    """Cauchy-robustified whitened 2D residuals: ``r`` rescaled so that its squared norm is
    ``rho(|r|^2) = c^2 log(1 + |r|^2 / c^2)`` (``c = scale``; ``inf``: unchanged). Smooth;
    ~``r`` for ``|r| << c``, and an outlier's pull fades as ``c^2 / |r|``."""
    n2 = jnp.sum(r**2, axis=-1, keepdims=True)
    big = n2 > jnp.finfo(r.dtype).tiny
    n2s = jnp.where(big, n2, 1.0)
    c2 = jnp.where(jnp.isfinite(scale), scale, 1.0) ** 2
    f = jnp.where(big, jnp.sqrt(c2 * jnp.log1p(n2s / c2) / n2s), 1.0)
    return jnp.where(jnp.isfinite(scale), f, 1.0) * r


def _centroid_residual(X: Array, t: _Terms) -> Array:
    d = _project_anchor_points(t.cams, X, t.anchors.shift) - t.obs  # (C, P, 2)
    r = robust_centroid_residual(jnp.einsum("pij,cpj->cpi", t.Wc, d), t.robust)
    return jnp.where(t.vis[..., None], r, 0.0).reshape(-1)


def _residual(q: Array, t: _Terms) -> Array:
    X = anchor_positions(t.chain, t.anchors, q)
    return jnp.concatenate(
        [_centroid_residual(X, t), _whiten(t.Wb, q - t.q_b), _whiten(t.Wp, q - t.q_h)]
    )


def _make_terms(chain, cams, anchors, centroids, visible, q_b, q_h, cov, robust=None) -> _Terms:
    dt = q_b.dtype
    vis = jnp.asarray(visible, bool)
    obs = jnp.where(vis[..., None], centroids.astype(dt), 0.0)
    n_p = anchors.n_patches
    if vis.shape != (cams.K.shape[0], n_p) or centroids.shape != vis.shape + (2,):
        raise ValueError(
            f"IK: expected centroids ({cams.K.shape[0]}, {n_p}, 2) and visible "
            f"({cams.K.shape[0]}, {n_p}) for {cams.K.shape[0]} cameras and {n_p} patches; got "
            f"{centroids.shape} and {vis.shape}"
        )
    if cov.blend.shape[0] != q_b.shape[0]:
        raise ValueError(
            f"IK: covariances are for {cov.blend.shape[0]} DOFs, the pose has {q_b.shape[0]}"
        )
    Wc = jnp.broadcast_to(_whitener(cov.centroid, dt), (n_p, 2, 2))
    robust = jnp.asarray(jnp.inf if robust is None else robust, dt)
    return _Terms(
        chain, cams, anchors, obs, vis, q_b, q_h.astype(dt), Wc,
        _whitener(cov.blend, dt), _whitener(cov.prior, dt), robust,
    )  # fmt: skip


def ik_residuals(
    q: Float[Array, " n_dof"],
    chain: KinematicChain,
    cams: Camera,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    q_h: Float[Array, " n_dof"],
    cov: IKCovariances,
) -> Float[Array, " n_res"]:
    """Whitened residual vector of the step-4 energy: ``E(q) = sum(ik_residuals(...)**2)``.

    Layout: ``n_cams * P * 2`` centroid terms (0 for invisible patches), then ``n_dof``
    blend-prior terms, then ``n_dof`` temporal-prior terms.
    """
    return _residual(q, _make_terms(chain, cams, anchors, centroids, visible, q_b, q_h, cov))


# ----------------------------------------------------------------------------- joint limits


def _limit_params(lower: Array, upper: Array) -> tuple[Array, Array, Array]:
    """(finite, mid, half) of the limit map; NaN-free for infinite limits."""
    finite = jnp.isfinite(lower) & jnp.isfinite(upper)
    lo = jnp.where(finite, lower, -1.0)
    hi = jnp.where(finite, upper, 1.0)
    return finite, 0.5 * (hi + lo), 0.5 * (hi - lo)


def _z_to_q(z: Array, finite: Array, mid: Array, half: Array) -> Array:
    return jnp.where(finite, mid + half * jnp.tanh(z), z)


def _q_to_z(q: Array, finite: Array, mid: Array, half: Array) -> Array:
    ratio = jnp.clip((q - mid) / half, -1.0 + LIMIT_MARGIN, 1.0 - LIMIT_MARGIN)
    return jnp.where(finite, jnp.arctanh(ratio), q)


# ----------------------------------------------------------------------------- solutions


def _default_ftol(dtype) -> float:
    """8 float eps of ``dtype``: the rounding of a sum of squares
    (:class:`FtolLevenbergMarquardt`)."""
    return 8 * float(jnp.finfo(dtype).eps)


class _FtolState(eqx.Module):
    inner: PyTree
    stop: Bool[Array, ""]


class FtolLevenbergMarquardt(optx.AbstractLeastSquaresSolver):
    """``optx.LevenbergMarquardt`` plus MINPACK's ``ftol`` test (Moré 1978; ``lmder``'s
    ``info = 1``): stop when both the actual and the predicted reduction of the sum of squares
    by the last proposed step are at most ``ftol`` times it (a rejected step's actual change
    is a rise, kept only while its prediction is that small).

    optimistix's own test (Cauchy: every residual element and every parameter changed by less
    than ``atol + rtol |.|`` on an accepted step) is kept. In float32 it is rarely met: at the
    optimum the sum of squares moves by rounding (~1e-6 relative), every proposal is rejected
    and the trust region shrinks by 4x per step until ``max_steps``. Measured on the shirt
    tracker's IK (bench scene, 24 DOF): converged after 14 and 9 steps, stopped after 42 and
    31 (docs/results/realtime_profile.md, session 12). ``ftol`` defaults to 8 float eps of the
    solve's dtype (the rounding of the loss); 0 turns the test off. ``y`` and the residual are
    single arrays."""

    inner: optx.LevenbergMarquardt
    ftol: float | Array | None
    rtol: float
    atol: float
    norm: Callable = eqx.field(static=True)

    def __init__(self, rtol, atol, ftol=None):
        self.inner = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
        self.rtol, self.atol, self.norm, self.ftol = rtol, atol, self.inner.norm, ftol

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        inner = self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
        return _FtolState(inner, jnp.array(False))

    def step(self, fn, y, args, options, state, tags):
        st = state.inner
        f0 = st.f_info.residual
        loss0 = jnp.sum(f0**2)
        dt = loss0.dtype
        ftol = jnp.asarray(_default_ftol(dt) if self.ftol is None else self.ftol, dt)
        model = f0 + st.f_info.jac.mv(st.y_eval - y)  # linearised residual after the step
        predicted = loss0 - jnp.sum(model**2)
        new_y, new_st, aux = self.inner.step(fn, y, args, options, st, tags)
        accepted = new_st.num_steps_since_acceptance == 0
        actual = loss0 - jnp.sum(new_st.f_info.residual**2)
        scale = ftol * loss0
        small = (jnp.abs(predicted) <= scale) & (~accepted | (jnp.abs(actual) <= scale))
        small = small & (ftol > 0)  # ftol = 0: the test is off
        return new_y, _FtolState(new_st, small & ~st.first_step), aux

    def terminate(self, fn, y, args, options, state, tags):
        done, result = self.inner.terminate(fn, y, args, options, state.inner, tags)
        return done | state.stop, result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state.inner, tags, result)



class IKSolution(eqx.Module):
    """Result of an IK solve.

    ``q`` the solved pose, ``result`` the optimistix result code (``optx.RESULTS.successful``
    or why not: e.g. ``nonlinear_max_steps_reached``), ``num_steps`` iterations taken,
    ``cost`` the energy (sum of squared whitened residuals) at ``q``.
    """

    q: Float[Array, "*batch n_dof"]
    result: optx.RESULTS
    num_steps: Int[Array, "*batch"]
    cost: Float[Array, "*batch"]

    @property
    def converged(self) -> Bool[Array, "*batch"]:
        return self.result == optx.RESULTS.successful


def _free_index(free_dofs: tuple[int, ...] | None, n_dof: int) -> np.ndarray:
    if free_dofs is None:
        return np.arange(n_dof)
    idx = np.asarray(free_dofs, dtype=np.int64).reshape(-1)
    if (
        idx.size == 0
        or np.any(idx < 0)
        or np.any(idx >= n_dof)
        or len(set(idx.tolist())) != idx.size
    ):
        raise ValueError(
            f"solve_ik: free_dofs must be distinct indices in [0, {n_dof}), got {free_dofs}"
        )
    return np.sort(idx)


def solve_ik(
    chain: KinematicChain,
    cams: Camera,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    q_h: Float[Array, " n_dof"],
    cov: IKCovariances,
    q_init: Float[Array, " n_dof"] | None = None,
    *,
    free_dofs: tuple[int, ...] | None = None,
    rtol: float | Float[Array, ""] = DEFAULT_RTOL,
    atol: float | Float[Array, ""] = DEFAULT_ATOL,
    max_steps: int = DEFAULT_MAX_STEPS,
    robust: float | Float[Array, ""] | None = None,
    ftol: float | Float[Array, ""] | None = None,
) -> IKSolution:
    """Pose refinement by IK (Wang et al. §5.2 step 4), Levenberg-Marquardt in optimistix.

    Minimises the energy of :func:`ik_residuals` over the DOFs ``free_dofs`` (default all;
    a static tuple of indices into q), the others staying at ``q_init`` (default ``q_b``),
    which is also the initial guess. Joint limits of ``chain`` hold for the result (tanh
    reparametrisation, see the module docstring). Levenberg-Marquardt stops on optimistix's
    test (``rtol``, ``atol``) or on MINPACK's relative reduction ``ftol``
    (:class:`FtolLevenbergMarquardt`; None: 8 float eps, 0: off); the three are traced:
    changing them does not recompile; ``free_dofs`` and ``max_steps`` are static. Never raises
    on non-convergence: check ``result`` / ``converged``. Differentiable (implicit adjoint)
    w.r.t. every array input, covariances included. Batch frames with ``jax.vmap``.

    ``robust`` (not in the paper; default None = the paper's plain squares) replaces each
    patch's whitened centroid term ``|r|^2`` by the Cauchy ``c^2 log(1 + |r|^2 / c^2)`` with
    ``c = robust`` (in standard deviations of Sigma_c; traced), so that a centroid corrupted
    by misclassified pixels cannot drag the whole pose (:func:`robust_centroid_residual`).
    """
    tol = lambda x: jnp.asarray(x, dtype=q_b.dtype)
    rob = tol(jnp.inf if robust is None else robust)
    ftol = tol(_default_ftol(q_b.dtype) if ftol is None else ftol)
    return _solve_ik(chain, cams, anchors, centroids, visible, q_b, q_h, cov, q_init,
                     free_dofs, tol(rtol), tol(atol), max_steps, rob, ftol)  # fmt: skip


@functools.partial(jax.jit, static_argnames=("free_dofs", "max_steps"))
def _solve_ik(
    chain: KinematicChain,
    cams: Camera,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    q_h: Float[Array, " n_dof"],
    cov: IKCovariances,
    q_init: Float[Array, " n_dof"] | None,
    free_dofs: tuple[int, ...] | None,
    rtol: Float[Array, ""],
    atol: Float[Array, ""],
    max_steps: int,
    robust: Float[Array, ""],
    ftol: Float[Array, ""],
) -> IKSolution:
    """The jitted core of :func:`solve_ik` (every argument explicit, tolerances arrays)."""
    terms = _make_terms(chain, cams, anchors, centroids, visible, q_b, q_h, cov, robust)
    dt = q_b.dtype
    q0 = q_b if q_init is None else q_init.astype(dt)
    idx = _free_index(free_dofs, q_b.shape[0])
    limits = _limit_params(chain.lower[idx].astype(dt), chain.upper[idx].astype(dt))

    @_dense_jacobian
    def fn(z, args):
        q_fixed, lim, t = args
        return _residual(q_fixed.at[idx].set(_z_to_q(z, *lim)), t)

    args = (q0, limits, terms)
    z0 = _q_to_z(q0[idx], *limits)
    solver = FtolLevenbergMarquardt(rtol=rtol, atol=atol, ftol=ftol)
    sol = optx.least_squares(
        fn, solver, z0, args, max_steps=max_steps, throw=False, adjoint=_ADJOINT, options=_OPTIONS
    )
    q = q0.at[idx].set(_z_to_q(sol.value, *limits))
    cost = jnp.sum(sol.state.inner.f_info.residual**2)
    return IKSolution(q=q, result=sol.result, num_steps=sol.stats["num_steps"], cost=cost)


# ----------------------------------------------------------------------------- global 6-DOF solve


def _kabsch(
    X: Float[Array, "n 3"], Y: Float[Array, "n 3"], w: Float[Array, " n"]
) -> tuple[Array, Array, Array]:
    """Weighted rigid fit ``Y ~ R X + t`` (Kabsch); returns (R, t, well_conditioned)."""
    sw = jnp.maximum(w.sum(), jnp.finfo(X.dtype).tiny)
    mx = (w[:, None] * X).sum(0) / sw
    my = (w[:, None] * Y).sum(0) / sw
    H = jnp.einsum("n,ni,nj->ij", w, X - mx[None], Y - my[None])
    U, S, Vt = jnp.linalg.svd(H)
    d = jnp.sign(jnp.linalg.det(Vt.T @ U.T))
    D = jnp.diag(jnp.stack([jnp.ones_like(d), jnp.ones_like(d), jnp.where(d == 0, 1.0, d)]))
    R = Vt.T @ D @ U.T
    t = my - R @ mx
    return R, t, S[1] > KABSCH_MIN_SPREAD * S[0]


def _root_frame(q_b: Array) -> Array:
    """q_b with the root DOFs zeroed: the body in its root-placement frame."""
    return q_b.at[:ROOT_DOFS].set(0.0)


@jax.jit
def initial_root(
    cams: Camera,
    chain: KinematicChain,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    root_prev: Float[Array, 6],
) -> tuple[Float[Array, 6], Bool[Array, ""]]:
    """Initial root (translation m, rotation vector rad) for the global solve (step 2).

    With 2+ cameras, patches seen by at least two of them are triangulated (N-view DLT,
    :func:`jaxmocap.camera.triangulate`); if at least ``MIN_KABSCH_PATCHES`` non-collinear
    ones are, the root is the closed-form rigid (Kabsch) fit of the anchors of ``q_b`` (in
    the root-placement frame) to them. Otherwise ``root_prev`` (e.g. the previous frame's
    root) is kept. Returns (root, whether the fit was used). Not differentiated.
    """
    dt = q_b.dtype
    root_prev = root_prev.astype(dt)
    if cams.K.ndim != 3 or cams.K.shape[0] < 2:
        return root_prev, jnp.array(False)
    vis = jnp.asarray(visible, bool)
    X = anchor_positions(chain, anchors, _root_frame(q_b))
    if X.ndim == 3:  # per-view anchors: their mean over cameras
        X = X.mean(0)
    Y = triangulate(cams, centroids.astype(dt), refine=False, weights=vis.astype(dt))
    seen = vis.sum(0) >= 2
    Y = jnp.where(seen[:, None], Y, 0.0)
    R, t, well = _kabsch(X, Y, seen.astype(dt))
    use = (seen.sum() >= MIN_KABSCH_PATCHES) & well
    root = jnp.where(use, jnp.concatenate([t, so3_log(R)]), root_prev)
    return jax.lax.stop_gradient(root), use


def solve_global(
    chain: KinematicChain,
    cams: Camera,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    root_init: Float[Array, 6],
    centroid_cov: Float[Array, "*patches 2 2"] | None = None,
    *,
    rtol: float | Float[Array, ""] = DEFAULT_RTOL,
    atol: float | Float[Array, ""] = DEFAULT_ATOL,
    max_steps: int = DEFAULT_MAX_STEPS,
    ftol: float | Float[Array, ""] | None = None,
) -> IKSolution:
    """Global position and orientation (Wang et al. §5.2 step 2): a 6-DOF IK.

    The joints stay at ``q_b``; the root (``q[0:6]``, whose value in ``q_b`` is ignored) is
    found by minimising ``sum_{i,k} ||c^{*i}_k(q) - c^{ki}||^2_{Sigma_c}`` over visible
    patches in all cameras (Sigma_c default: identity, pixels), starting from ``root_init``
    (see :func:`initial_root`). The rotation is solved as a left increment
    ``exp([dw]_x) R_init`` (well conditioned for any ``root_init``). Returns an
    :class:`IKSolution` (``q`` = q_b with the solved root). Tolerances traced, as
    :func:`solve_ik`.
    """
    tol = lambda x: jnp.asarray(x, dtype=q_b.dtype)
    ftol = tol(_default_ftol(q_b.dtype) if ftol is None else ftol)
    return _solve_global(chain, cams, anchors, centroids, visible, q_b, root_init, centroid_cov,
                         tol(rtol), tol(atol), max_steps, ftol)  # fmt: skip


@functools.partial(jax.jit, static_argnames=("max_steps",))
def _solve_global(
    chain: KinematicChain,
    cams: Camera,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    root_init: Float[Array, 6],
    centroid_cov: Float[Array, "*patches 2 2"] | None,
    rtol: Float[Array, ""],
    atol: Float[Array, ""],
    max_steps: int,
    ftol: Float[Array, ""],
) -> IKSolution:
    """The jitted core of :func:`solve_global`."""
    dt = q_b.dtype
    n_p = anchors.n_patches
    cov_c = jnp.eye(2, dtype=dt) if centroid_cov is None else centroid_cov
    vis = jnp.asarray(visible, bool)
    if vis.shape != (cams.K.shape[0], n_p) or centroids.shape != vis.shape + (2,):
        raise ValueError(
            f"solve_global: expected centroids (n_cams, {n_p}, 2) and visible (n_cams, {n_p}); "
            f"got {centroids.shape} and {vis.shape}"
        )
    X = anchor_positions(chain, anchors, _root_frame(q_b))
    root_init = root_init.astype(dt)
    R0, t0 = so3_exp(root_init[3:6]), root_init[0:3]
    obs = jnp.where(vis[..., None], centroids.astype(dt), 0.0)
    Wc = jnp.broadcast_to(_whitener(cov_c, dt), (n_p, 2, 2))

    def place(y, R0, t0):
        R = so3_exp(y[3:6]) @ R0
        return R, t0 + y[0:3]

    @_dense_jacobian
    def fn(y, args):
        X, R0, t0, cams, obs, vis, Wc, shift = args
        R, t = place(y, R0, t0)
        d = _project_anchor_points(cams, X @ R.T + t.reshape((1,) * (X.ndim - 1) + (3,)), shift)
        d = d - obs
        r = jnp.einsum("pij,cpj->cpi", Wc, d)
        return jnp.where(vis[..., None], r, 0.0).reshape(-1)

    args = (X, R0, t0, cams, obs, vis, Wc, anchors.shift)
    solver = FtolLevenbergMarquardt(rtol=rtol, atol=atol, ftol=ftol)
    sol = optx.least_squares(
        fn,
        solver,
        jnp.zeros(6, dt),
        args,
        max_steps=max_steps,
        throw=False,
        adjoint=_ADJOINT,
        options=_OPTIONS,
    )
    R, t = place(sol.value, R0, t0)
    q = q_b.at[0:3].set(t).at[3:6].set(so3_log(R))
    cost = jnp.sum(sol.state.inner.f_info.residual**2)
    return IKSolution(q=q, result=sol.result, num_steps=sol.stats["num_steps"], cost=cost)


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
