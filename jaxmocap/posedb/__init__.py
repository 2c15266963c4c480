"""The pose database of Wang et al. 2011 §5.2, Step 2: "a database of 80,000 upper-body poses
[...] We rasterize each pose as a tiny id map r^i. At run time, we search our database for the
ten nearest neighbors r^i of our classified shirt region, resized as a tiny 40x40 id map. We
take our pose estimate to be a weighted blend of the poses corresponding to these neighbors".

* ``_sample``: the sampled poses (train clips, blends, mirrors, camera-relative orientations),
  the canonical camera, and :func:`pose_in_camera` (a database pose in a real camera's world);
* ``_search``: the id-map distance, exact and fast 10-NN search, the blend ``q_b``;
* ``_build``: rendering, the versioned ``.npz`` cache (``jaxmocap build-db``:
  :mod:`jaxmocap.commands.build_db`).

    db = load_or_build()                                  # 80,000 poses, cached
    tiny = tiny_from_classified(colour_ids)               # a classified crop -> 40x40
    q_b, nb = estimate_pose(db, tiny)                     # canonical world
    q_world = pose_in_camera(q_b, cam, root_in_camera)    # the real camera's world
"""

from ._build import (
    CODE_VERSION,
    build_database,
    cache_path,
    check_built_for,
    database_key,
    load_database,
    load_or_build,
    render_maps,
    save_database,
)
from ._sample import (
    CANON_DISTANCE,
    DEFAULT_SIZE,
    Mirror,
    SamplingConfig,
    SamplingError,
    canonical_camera,
    mirror_pose,
    mirror_table,
    pose_in_camera,
    sample_poses,
    source_pool,
)
from ._search import (
    BACKGROUND_WEIGHT,
    BLEND_SIGMA,
    CLUSTER_ANGLE,
    COARSE_PHASES,
    HYPOTHESIS_NEIGHBOURS,
    K_NEIGHBOURS,
    N_CANDIDATES,
    N_HYPOTHESES,
    POLYPHASE,
    DatabaseError,
    Hypotheses,
    Neighbours,
    PoseDB,
    blend,
    blend_poses,
    estimate_hypotheses,
    estimate_pose,
    make_posedb,
    map_distance,
    pack_map,
    query_exact,
    query_fast,
    rotvec_to_quat,
    tiny_from_classified,
    unpack_codes,
)

__all__ = [
    "CODE_VERSION", "build_database", "cache_path", "check_built_for",
    "database_key",
    "load_database", "load_or_build", "render_maps", "save_database",
    "CANON_DISTANCE", "DEFAULT_SIZE", "Mirror", "SamplingConfig", "SamplingError",
    "canonical_camera", "mirror_pose", "mirror_table", "pose_in_camera", "sample_poses",
    "source_pool", "BACKGROUND_WEIGHT", "BLEND_SIGMA", "COARSE_PHASES", "K_NEIGHBOURS",
    "N_CANDIDATES", "DatabaseError", "Neighbours", "PoseDB", "blend", "blend_poses",
    "estimate_pose", "make_posedb", "CLUSTER_ANGLE", "HYPOTHESIS_NEIGHBOURS", "N_HYPOTHESES",
    "Hypotheses", "estimate_hypotheses", "map_distance", "pack_map", "POLYPHASE",
    "query_exact", "query_fast", "rotvec_to_quat", "tiny_from_classified", "unpack_codes",
]  # fmt: skip
