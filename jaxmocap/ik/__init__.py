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

Files: :mod:`.anchors`, :mod:`.residuals` (energy, limits), :mod:`.solver` (LM, ``solve_ik``),
:mod:`.global_pose` (step 2), :mod:`.covariances` (terms' covariances, their file and
estimation). Units: metres, radians, pixels. Covariances: pixels^2 (Sigma_c), the squared units of q
(Sigma_b, Sigma_p).
"""

from __future__ import annotations

from jaxmocap.ik.anchors import (
    VIEW_MIN_PIXELS,
    PatchAnchors,
    anchor_positions,
    anchors_from_garment,
    anchors_from_samples,
    append_anchors,
    project_anchors,
    view_anchors,
)
from jaxmocap.ik.covariances import (
    COV_FILE_VERSION,
    COV_FLOOR_PX2,
    COV_FLOOR_Q,
    COV_REL_RIDGE,
    ROBUST_CHI2,
    ROBUST_ITERATIONS,
    CovarianceFileError,
    IKCovariances,
    append_centroid_covariances,
    estimate_covariances,
)
from jaxmocap.ik.global_pose import (
    KABSCH_MIN_SPREAD,
    MIN_KABSCH_PATCHES,
    initial_root,
    solve_global,
)
from jaxmocap.ik.residuals import (
    LIMIT_MARGIN,
    ik_residuals,
    robust_centroid_residual,
)
from jaxmocap.ik.solver import (
    DEFAULT_ATOL,
    DEFAULT_MAX_STEPS,
    DEFAULT_RTOL,
    FtolLevenbergMarquardt,
    IKSolution,
    solve_ik,
)
from jaxmocap.rotations import so3_log

__all__ = [
    "COV_FILE_VERSION",
    "COV_FLOOR_PX2",
    "COV_FLOOR_Q",
    "COV_REL_RIDGE",
    "CovarianceFileError",
    "DEFAULT_ATOL",
    "DEFAULT_MAX_STEPS",
    "DEFAULT_RTOL",
    "FtolLevenbergMarquardt",
    "IKCovariances",
    "IKSolution",
    "KABSCH_MIN_SPREAD",
    "LIMIT_MARGIN",
    "MIN_KABSCH_PATCHES",
    "PatchAnchors",
    "ROBUST_CHI2",
    "ROBUST_ITERATIONS",
    "VIEW_MIN_PIXELS",
    "anchor_positions",
    "anchors_from_garment",
    "anchors_from_samples",
    "append_anchors",
    "append_centroid_covariances",
    "estimate_covariances",
    "ik_residuals",
    "initial_root",
    "project_anchors",
    "robust_centroid_residual",
    "so3_log",
    "solve_global",
    "solve_ik",
    "view_anchors",
]
