"""SMPL-format body models: loading (bundled, real SMPL npz/pkl), batched LBS, skeleton, poses."""

from couch.body.lbs import (
    blend_shapes,
    forward_kinematics,
    lbs,
    rigid_transforms,
    vertices_to_joints,
)
from couch.body.model import (
    BUNDLED_MODELS,
    BodyModel,
    BodyModelError,
    BodyOutput,
    bundled_manifest,
    bundled_model_dir,
    load_body_model,
)
from couch.body.poses import body_pose, sitting_pose, standing_pose
from couch.body.skeleton import (
    CONTACT_NAMES,
    JOINT_INDEX,
    JOINT_NAMES,
    NUM_BODY_JOINTS,
    NUM_JOINTS,
    PARENTS,
    Skeleton,
    contact_vertex_sets,
)

__all__ = [
    "BUNDLED_MODELS", "CONTACT_NAMES", "JOINT_INDEX", "JOINT_NAMES", "NUM_BODY_JOINTS",
    "NUM_JOINTS", "PARENTS", "BodyModel", "BodyModelError", "BodyOutput", "Skeleton",
    "blend_shapes", "body_pose", "bundled_manifest", "bundled_model_dir", "contact_vertex_sets",
    "forward_kinematics", "lbs", "load_body_model", "rigid_transforms", "sitting_pose",
    "standing_pose", "vertices_to_joints",
]
