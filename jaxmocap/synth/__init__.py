"""Synthetic scenes from real motion capture: DeepMimic clips retargeted to our body model.

``deepmimic`` decodes pybullet's DeepMimic clips (source skeleton, Y up), ``retarget`` maps a
source motion onto a :class:`~jaxmocap.body.BodyModel` by rotation transfer, ``motion`` joins
them and defines the train / held-out split (docs/DATA.md); ``scene``, ``sequence`` and
``dataset`` render sequences with ground truth and the papers' nuisances (``jaxmocap synth``).
"""

from .dataset import DatasetError, load_dataset, write_dataset
from .deepmimic import (
    Clip,
    clip_path,
    deepmimic_skeleton,
    list_clips,
    load_deepmimic,
    resample,
    skeleton_fk,
)
from .motion import (
    DEEPMIMIC_TO_BODY,
    HELDOUT_CLIPS,
    TRAIN_CLIPS,
    clip_to_body_q,
    deepmimic_source,
    source_bone_directions,
)
from .retarget import Retargeted, SourcePose, limit_report, retarget
from .scene import SceneConfig, SceneError
from .sequence import Sequence, render_sequence

__all__ = [
    "Clip", "clip_path", "deepmimic_skeleton", "list_clips", "load_deepmimic", "resample",
    "skeleton_fk", "DEEPMIMIC_TO_BODY", "HELDOUT_CLIPS", "TRAIN_CLIPS", "clip_to_body_q",
    "deepmimic_source", "source_bone_directions", "Retargeted", "SourcePose", "limit_report",
    "retarget", "SceneConfig", "SceneError", "Sequence", "render_sequence", "DatasetError",
    "load_dataset", "write_dataset",
]  # fmt: skip
