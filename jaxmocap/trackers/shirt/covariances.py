"""IK covariances for any body: the bundled trained ones, transferred by role.

Wang et al. 2011 §5.2 step 4 train the three covariances of the IK energy (centroids Sigma_c,
blend Sigma_b, temporal prior Sigma_p) on ground-truth sequences and "save them with the
model". The bundled file (:data:`TRAINED_COV_FILE`) was trained for the bundled body's 24 DOFs
(``benchmarks/experiments``, held-out clips excluded). Another body gets them **by role**
(:func:`covariances_for_body`): the root DOFs map one to one; each DOF of a joint role
(spine, neck, shoulders, elbows, wrists) takes the variance of the bundled DOF of the same
role whose rotation axis at rest is the most nearly parallel (|cos| >= :data:`AXIS_COS`);
Sigma_c is shared by all patches and carries over unchanged. DOFs without such a counterpart
(legs, extra spine links, a twist the bundled joint lacks) get the isotropic defaults
(:data:`DEFAULT_BLEND_STD`, :data:`DEFAULT_PRIOR_STD`), and the caller is told which.
Covariances trained for the body itself (``ik.estimate_covariances`` on renders of it) can
always be given instead (``jaxmocap track --ik-cov``).
"""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxmocap.body import BodyModel, default_body
from jaxmocap.body.chain import ROOT_DOFS
from jaxmocap.body.roles import JOINT_ROLES, rest_transforms
from jaxmocap.errors import InputError
from jaxmocap.ik import IKCovariances

TRAINED_COV_FILE = Path(__file__).with_name("shirt_ik_cov.npz")
AXIS_COS = 0.9  # a DOF's counterpart must turn about a nearly parallel axis at rest (< 26 deg)
DEFAULT_BLEND_STD = 0.3  # rad: the untrained default of setup_for_sequence
DEFAULT_PRIOR_STD = 0.5  # rad


def trained_covariances(n_dof: int | None = None) -> IKCovariances:
    """The bundled trained IK covariances (:data:`TRAINED_COV_FILE`), "saved with the model",
    for the bundled body. ``n_dof`` is checked against the file: a body with another DOF count
    needs :func:`covariances_for_body`."""
    cov = IKCovariances.load(TRAINED_COV_FILE)
    if n_dof is not None and cov.blend.shape[-1] != n_dof:
        raise ValueError(
            f"{TRAINED_COV_FILE}: trained for a {cov.blend.shape[-1]}-DOF body, "
            f"this body has {n_dof} DOFs; use covariances_for_body(body) (transfer by role)"
        )
    return cov


def _dof_axes(model: BodyModel) -> dict[str, np.ndarray]:
    """World rotation axis at rest of every joint DOF, by DOF name."""
    chain = model.chain
    rest = rest_transforms(chain)
    axes = {}
    for link, (_, _, d) in enumerate(chain.topology):
        if d >= ROOT_DOFS:
            a = rest[link][:3, :3] @ np.asarray(chain.joint_axis[link], np.float64)
            axes[chain.dof_names[d]] = a / np.linalg.norm(a)
    return axes


def transfer_index(source: BodyModel, target: BodyModel) -> np.ndarray:
    """Per DOF of ``target`` the index of the ``source`` DOF whose variances it takes by role
    (module docstring: the root DOFs one to one, a joint role's DOF the source DOF of that
    role about the most nearly parallel rest axis), -1 where none (the defaults)."""
    for body, what in ((source, "source"), (target, "target")):
        if body.roles is None:
            raise InputError(f"IK covariance transfer: the {what} body has no roles "
                             "(load it with jaxmocap.body.load_body)")  # fmt: skip
    src_index = {n: i for i, n in enumerate(source.chain.dof_names)}
    src_axes, tgt_axes = _dof_axes(source), _dof_axes(target)
    index = np.full(target.n_dof, -1, np.int64)
    index[:ROOT_DOFS] = np.arange(ROOT_DOFS)
    src_roles = dict(source.roles.joints)
    for role, dofs in target.roles.joints:
        if role not in JOINT_ROLES or role not in src_roles:
            continue
        for name in dofs:
            best, best_cos = None, AXIS_COS
            for cand in src_roles[role]:
                c = abs(float(tgt_axes[name] @ src_axes[cand]))
                if c >= best_cos:
                    best, best_cos = cand, c
            if best is not None:
                index[target.chain.dof_names.index(name)] = src_index[best]
    return index


def transfer_covariances(
    cov: IKCovariances, source: BodyModel, target: BodyModel
) -> tuple[IKCovariances, tuple[str, ...]]:
    """Diagonal covariances of ``source`` carried to ``target`` by role (module docstring;
    :func:`transfer_index`).

    Returns the covariances and the names of the target DOFs that got the defaults."""
    index = transfer_index(source, target)
    blend = np.asarray(cov.blend, np.float64)
    prior = np.asarray(cov.prior, np.float64)
    if blend.ndim == 2:
        blend, prior = np.diag(blend), np.diag(np.asarray(prior).reshape(blend.shape))
    hit = index >= 0
    out_b = np.where(hit, blend[np.maximum(index, 0)], DEFAULT_BLEND_STD**2)
    out_p = np.where(hit, prior[np.maximum(index, 0)], DEFAULT_PRIOR_STD**2)
    defaults = tuple(d for i, d in enumerate(target.chain.dof_names)
                     if i >= ROOT_DOFS and not hit[i])  # fmt: skip
    dt = jnp.asarray(cov.centroid).dtype
    return IKCovariances(centroid=cov.centroid, blend=jnp.asarray(out_b, dt),
                         prior=jnp.asarray(out_p, dt)), defaults  # fmt: skip


def covariances_for_body(body: BodyModel) -> tuple[IKCovariances, tuple[str, ...]]:
    """IK covariances for ``body``: the bundled trained ones for the bundled body, else
    transferred by role (module docstring). Returns them and the DOFs that got defaults."""
    bundled = default_body()
    cov = trained_covariances()
    if body is bundled or body.chain.dof_names == bundled.chain.dof_names and np.allclose(
            np.asarray(body.chain.joint_axis), np.asarray(bundled.chain.joint_axis)):
        return cov, ()
    return transfer_covariances(cov, bundled, body)


__all__ = ["TRAINED_COV_FILE", "covariances_for_body", "trained_covariances",
           "transfer_covariances", "transfer_index"]  # fmt: skip
