"""Body model: kinematic chain, forward kinematics, geometry and the bundled upper body.

The one body model every stage shares (DESIGN §Principles 4): loaded from a URDF/MJCF through
pytorch-kinematics, converted once to JAX arrays. See ``chain`` for the pose-vector layout.
"""

from .chain import FIXED, PRISMATIC, REVOLUTE, ROOT_DOFS, KinematicChain, fk, so3_exp
from .geometry import BOX, CAPSULE, CYLINDER, ELLIPSOID, KIND_NAMES, SPHERE, Geometry
from .load import default_body, load_body
from .mjcf import load_mjcf
from .model import (
    KEYPOINT_NAMES,
    STEREO_JOINTS,
    BodyModel,
    clip_to_limits,
    dof_index,
    expand_q,
    geom_world_poses,
    keypoint_index,
    keypoints,
    keypoints_from_transforms,
    make_body_model,
    rest_pose,
    stereo_dofs,
)
from .roles import (
    JOINT_ROLES,
    LINK_ROLES,
    BodyRoles,
    body_digest,
    infer_roles,
    read_roles_file,
    require_roles,
    roles_path,
    roles_to_json,
)
from .urdf import load_urdf

__all__ = [
    "FIXED", "REVOLUTE", "PRISMATIC", "ROOT_DOFS", "KinematicChain", "fk", "so3_exp",
    "SPHERE", "CAPSULE", "CYLINDER", "BOX", "ELLIPSOID", "KIND_NAMES", "Geometry",
    "KEYPOINT_NAMES", "STEREO_JOINTS", "BodyModel", "make_body_model", "keypoints",
    "keypoints_from_transforms", "geom_world_poses", "keypoint_index", "dof_index",
    "stereo_dofs", "expand_q", "clip_to_limits", "rest_pose", "default_body",
    "load_urdf", "load_mjcf", "BodyRoles", "LINK_ROLES", "JOINT_ROLES", "body_digest",
    "infer_roles", "load_body", "read_roles_file", "require_roles", "roles_path", "roles_to_json",
]  # fmt: skip
