"""Runtime hand IK: the fitting step the COUCH appendix (Sec. 3) suggests and leaves out of the
paper's evaluation ("it would be possible to fit the predicted pose to the predicted hand
position ... to further improve the satisfaction of the contact constraints").

Each frame, analytic two-bone IK of shoulder-elbow-wrist moves a point of each palm a fraction
of the way to its contact: the controller gives ControlNet's local phase of that hand (0 when a
reach starts, 1 at the contact), or PoseNet's probability that the pelvis is seated if that is
higher, so ControlNet's plan decides when the hand arrives while sitting down, a seated
character holds the asked contact, and the arm blends in from the network's own pose. The
wrist keeps its global orientation (the palm stays as the network turned it); the elbow bends
in the plane it was already bent in.

:func:`bend_limbs` is the two-bone solver itself, for any shoulder-elbow-wrist or
hip-knee-ankle chain (:mod:`couch.synthesis.foot_lock` bends the legs with it).

Everything is in the character's root frame (metres), batch first, on the root-frame global
joint rotations the controller carries (``jrot`` as 3x3) and the skeleton they give by forward
kinematics of the rest bones (what :meth:`Synthesizer.smpl` writes out).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from couch.body import JOINT_INDEX, Skeleton
from couch.geometry import normalize, two_bone_ik

__all__ = ["ARMS", "ArmRig", "bend_limbs", "forward_positions", "reach"]

#: (shoulder, elbow, wrist) SMPL joint indices of the left and right arm.
ARMS: tuple[tuple[int, int, int], ...] = tuple(
    (JOINT_INDEX[f"{s}_shoulder"], JOINT_INDEX[f"{s}_elbow"], JOINT_INDEX[f"{s}_wrist"])
    for s in ("left", "right"))


@dataclasses.dataclass(frozen=True)
class ArmRig:
    """The rest skeleton and the palm points the IK places.

    rest: (24,3) rest joints (metres, T-pose, where every global rotation is the identity);
    palm: (2,3) the point of each hand (left, right) that is put on the contact, as an offset
    from its wrist in the rest pose (e.g. the centroid of the body model's hand contact
    vertices), so that it moves with the wrist's global rotation.
    """

    rest: np.ndarray
    palm: np.ndarray

    @property
    def skeleton(self) -> Skeleton:
        return Skeleton(self.rest)


def forward_positions(pelvis: np.ndarray, rot: np.ndarray, rig: ArmRig | Skeleton,
                      joints: Sequence[int]) -> dict[int, np.ndarray]:
    """Positions (B,3) of ``joints`` and their ancestors from the pelvis (B,3) and global
    rotations rot (B,J,3,3) (:meth:`Skeleton.forward` of the rig's or the given skeleton)."""
    skeleton = rig.skeleton if isinstance(rig, ArmRig) else rig
    return skeleton.forward(pelvis, dict(enumerate(np.moveaxis(rot, 1, 0))), list(joints))


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(B,3,3) the smallest rotation taking direction a (B,3) onto direction b (B,3)."""
    a, b = normalize(a), normalize(b)
    v = np.cross(a, b)
    c = np.sum(a * b, -1)
    k = np.zeros((*v.shape[:-1], 3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k = k - np.swapaxes(k, -1, -2)
    # Rodrigues for unit a, b: I + K + K² / (1 + cos); opposite directions never occur here
    # (an arm does not fold back on itself within a frame), the floor only avoids a division by 0.
    return np.eye(3) + k + (k @ k) / np.maximum(1.0 + c, 1e-9)[..., None, None]


def reach(pelvis: np.ndarray, rot: np.ndarray, goals: np.ndarray, weights: np.ndarray,
          rig: ArmRig) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Move each palm point a fraction of the way to its goal by re-bending its arm.

    Args:
        pelvis: (B,3) pelvis positions; rot: (B,J,3,3) global joint rotations, root frame.
        goals: (B,2,3) palm goals (left, right), root frame; ignored where ``weights`` is 0.
        weights: (B,2) in [0,1]: 0 leaves the arm, 1 puts the palm on the goal (or as close as
            the arm reaches: beyond full extension it points the straight arm at it).
        rig: :class:`ArmRig`.
    Returns:
        the new rotations (B,J,3,3) (shoulders and elbows changed, wrists kept) and the change
        of every arm joint's position {joint: (B,3)} (elbows and wrists; zero where weight 0).
    """
    return bend_limbs(pelvis, rot, ARMS, rig.palm, goals, weights, rig.skeleton)


def bend_limbs(pelvis: np.ndarray, rot: np.ndarray, chains: tuple[tuple[int, int, int], ...],
               offsets: np.ndarray, goals: np.ndarray, weights: np.ndarray,
               skeleton: Skeleton) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Two-bone IK of several limbs (arms: shoulder-elbow-wrist, legs: hip-knee-ankle).

    Args:
        pelvis: (B,3) pelvis positions; rot: (B,J,3,3) global joint rotations, root frame.
        chains: L (upper, middle, end) joint indices.
        offsets: (L,3) the point of each end joint that is put on the goal, as an offset from
            the end joint in the rest pose (moves with its global rotation; zeros: the joint).
        goals: (B,L,3) goals of those points, root frame; ignored where ``weights`` is 0.
        weights: (B,L) in [0,1]: the fraction of the way from the point to its goal.
        skeleton: the rest skeleton.
    Returns:
        the new rotations (B,J,3,3) (upper and middle joints changed, end joints keep their
        global rotation) and the change of each middle and end joint's position {joint: (B,3)}.
    """
    rot = np.array(rot, dtype=np.float64)
    weights = np.clip(np.nan_to_num(np.asarray(weights, np.float64)), 0.0, 1.0)
    pos = forward_positions(pelvis, rot, skeleton, [j for chain in chains for j in chain])
    moved: dict[int, np.ndarray] = {}
    # named for the arm; a leg's hip, knee and ankle take the same places
    for h, (s, e, w) in enumerate(chains):
        shoulder, elbow, wrist = pos[s], pos[e], pos[w]
        palm = wrist + rot[:, w] @ offsets[h]
        goal = np.where(weights[:, h, None] > 0, np.nan_to_num(goals[:, h]), palm)
        wrist_goal = wrist + weights[:, h, None] * (goal - palm)
        upper, lower = skeleton.bone_length(s, e), skeleton.bone_length(e, w)
        # bend towards where the middle joint already points, away from the end-to-end line
        line = normalize(wrist - shoulder)
        pole = elbow - shoulder
        pole = pole - np.sum(pole * line, -1, keepdims=True) * line
        new_elbow, _, lower_dir, _ = two_bone_ik(shoulder, wrist_goal, pole, upper, lower)
        new_wrist = new_elbow + lower * lower_dir
        turn_upper = _rotation_between(elbow - shoulder, new_elbow - shoulder)
        turn_lower = _rotation_between(np.einsum("bij,bj->bi", turn_upper, wrist - elbow),
                                       new_wrist - new_elbow)
        keep = weights[:, h] <= 0
        turn_upper[keep] = np.eye(3)
        turn_lower[keep] = np.eye(3)
        rot[:, s] = turn_upper @ rot[:, s]
        rot[:, e] = turn_lower @ turn_upper @ rot[:, e]
        moved[e] = np.where(keep[:, None], 0.0, new_elbow - elbow)
        moved[w] = np.where(keep[:, None], 0.0, new_wrist - wrist)
    return rot, moved
