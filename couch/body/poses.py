"""Named key poses in SMPL's 23-joint body-pose layout (axis-angle, radians).

Rotations are local, about the parent's rest-frame axes: X to the body's left, Y up, Z forward.
Hip flexion (thigh forward) is a negative X rotation, knee flexion a positive one; a left arm
(rest: pointing +X) comes down with a negative Z rotation, a right arm with a positive one.
"""

from __future__ import annotations

import numpy as np

from couch.body.skeleton import JOINT_INDEX, NUM_BODY_JOINTS


def body_pose(**joints: tuple[float, float, float]) -> np.ndarray:
    """(69,) float32 body pose with the named joints set (degrees in, axis-angle radians out)."""
    pose = np.zeros((NUM_BODY_JOINTS, 3), dtype=np.float32)
    for name, rot_deg in joints.items():
        if name not in JOINT_INDEX or name == "pelvis":
            raise KeyError(f"unknown body joint {name!r} (pelvis is the global orientation)")
        pose[JOINT_INDEX[name] - 1] = np.deg2rad(rot_deg)
    return pose.reshape(-1)


def sitting_pose() -> np.ndarray:
    """(69,) upright seated pose: thighs level, shins vertical, hands resting on the thighs."""
    return body_pose(
        left_hip=(-90, 0, -4), right_hip=(-90, 0, 4),
        left_knee=(90, 0, 0), right_knee=(90, 0, 0),
        left_ankle=(0, 0, 0), right_ankle=(0, 0, 0),
        spine1=(4, 0, 0),
        left_shoulder=(-10, 0, -70), right_shoulder=(-10, 0, 70),
        left_elbow=(0, -65, 0), right_elbow=(0, 65, 0),
    )


def standing_pose() -> np.ndarray:
    """(69,) relaxed standing pose, arms down beside the body."""
    return body_pose(
        left_shoulder=(0, 0, -75), right_shoulder=(0, 0, 75),
        left_elbow=(0, -10, 0), right_elbow=(0, 10, 0),
    )
