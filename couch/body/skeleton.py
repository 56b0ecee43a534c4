"""The 24 SMPL joints, their parents, and the body parts that touch a chair.

Joint order and parents are SMPL's; every stage indexes joints by these names.
"""

from __future__ import annotations

import numpy as np

JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
)
PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
)
NUM_JOINTS = 24
NUM_BODY_JOINTS = 23  # all but the pelvis (global orientation)
JOINT_INDEX: dict[str, int] = {name: i for i, name in enumerate(JOINT_NAMES)}

# The body parts whose contact with the chair the processed schema records, in schema order.
CONTACT_NAMES: tuple[str, ...] = ("pelvis", "left_hand", "right_hand", "left_foot", "right_foot")

# Joints whose skinning weights make up each contact part (dominant-weight segmentation).
CONTACT_JOINTS: dict[str, tuple[str, ...]] = {
    "pelvis": ("pelvis", "left_hip", "right_hip"),
    "left_hand": ("left_wrist", "left_hand"),
    "right_hand": ("right_wrist", "right_hand"),
    "left_foot": ("left_ankle", "left_foot"),
    "right_foot": ("right_ankle", "right_foot"),
}


def contact_vertex_sets(v_template: np.ndarray, weights: np.ndarray,
                        joint_rest: np.ndarray) -> dict[str, np.ndarray]:
    """Vertex ids of each contact part, for any SMPL-format mesh (no vertex count assumed).

    Args:
        v_template: (V,3) rest-pose vertices (Y up, facing +Z).
        weights: (V,24) skinning weights.
        joint_rest: (24,3) rest-pose joints.
    Returns:
        name -> sorted vertex ids: hands are palm and fingers (wrist and hand dominated); feet
        are the soles (ankle/foot dominated, within 3 cm of the lowest foot vertex); pelvis is
        the seat (pelvis/hip dominated, behind the hip joints and below the pelvis joint).
    """
    dominant = weights.argmax(1)
    sets: dict[str, np.ndarray] = {}
    for name, joints in CONTACT_JOINTS.items():
        ids = np.flatnonzero(np.isin(dominant, [JOINT_INDEX[j] for j in joints]))
        if name.endswith("foot"):
            ids = ids[v_template[ids, 1] < v_template[ids, 1].min() + 0.03]
        elif name == "pelvis":
            hips = joint_rest[[JOINT_INDEX["left_hip"], JOINT_INDEX["right_hip"]]]
            behind = v_template[ids, 2] < hips[:, 2].mean()
            below = v_template[ids, 1] < joint_rest[JOINT_INDEX["pelvis"], 1]
            ids = ids[behind & below]
        sets[name] = np.sort(ids)
    return sets


class Skeleton:
    """Forward kinematics over SMPL's 24 joints for one shaped body (rest joints (24,3)), in
    numpy from global joint rotations (the simulator's motion and the runtime hand IK)."""

    def __init__(self, rest_joints: np.ndarray) -> None:
        self.rest = np.asarray(rest_joints, dtype=np.float64)
        self.parents = np.asarray(PARENTS)

    def offset(self, joint: int) -> np.ndarray:
        """Rest-pose vector from the parent to ``joint`` (3,)."""
        return self.rest[joint] - self.rest[self.parents[joint]]

    def bone_length(self, a: int, b: int) -> float:
        return float(np.linalg.norm(self.rest[b] - self.rest[a]))

    def forward(self, root_pos: np.ndarray, global_rot: dict[int, np.ndarray],
                upto: list[int]) -> dict[int, np.ndarray]:
        """World positions (T,3) of the joints in ``upto`` given global rotations of their
        ancestors (joint index -> (T,3,3)); ``root_pos`` is the pelvis joint (T,3)."""
        pos = {0: root_pos}
        needed = set(upto) | {a for u in upto for a in self.ancestors(u)}
        for j in sorted(needed):
            if j == 0:
                continue
            p = self.parents[j]
            pos[j] = pos[p] + global_rot[p] @ self.offset(j)
        return pos

    def ancestors(self, joint: int) -> list[int]:
        chain = []
        while self.parents[joint] >= 0:
            joint = int(self.parents[joint])
            chain.append(joint)
        return chain
