"""Foot locking: the foot-skate clean-up game-animation pipelines run after a motion
controller (the synthesised feet slide ~1-6 mm/frame, the simulated data's 0.06).

A foot is planted while its ankle is low and slow. During a plant the ankle is held where the
plant began (horizontally; its height stays the network's) by two-bone IK of hip-knee-ankle,
and the foot is turned about the vertical back to the heading it began with (its pitch and
roll stay the network's), so neither ankle nor toe slides; after a plant the hold is released
over a few frames so the foot does not jump. It is a post-process on the output: the
networks never see the edited legs (unlike the hand IK, which they are fed back), so it
cannot change where the character goes or what its hands reach.

Everything is batch first: B characters x T frames, root-frame joints as the controller keeps
them (positions in metres, global rotations in 6D) and world_from_root transforms.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from couch.body import JOINT_INDEX, Skeleton
from couch.geometry import apply_transform
from couch.rotations import axis_angle_to_matrix, matrix_to_6d, sixd_to_matrix
from couch.synthesis.features import to_root
from couch.synthesis.hand_ik import bend_limbs, forward_positions

__all__ = ["LEGS", "FootLockConfig", "lock_feet", "planted_feet"]

#: (hip, knee, ankle) SMPL joint indices of the left and right leg.
LEGS: tuple[tuple[int, int, int], ...] = tuple(
    (JOINT_INDEX[f"{s}_hip"], JOINT_INDEX[f"{s}_knee"], JOINT_INDEX[f"{s}_ankle"])
    for s in ("left", "right"))
_TOES = (JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"])


@dataclasses.dataclass(frozen=True)
class FootLockConfig:
    """When a foot counts as planted and how a plant is released.

    height: the ankle joint at most this high above the floor (m; the SMPL ankle stands ~7 cm
        up). speed: its horizontal speed at most this (m/s; a swinging foot moves at 1-4 m/s).
    min_frames: shorter plants are left alone. release_frames: after a plant the held offset
        fades to zero over this many frames. max_stretch: a plant ends where holding it would
        put the ankle farther from the hip than this share of the leg's length, or the
        foot more than ``max_offset`` (m) or ``max_turn`` (rad) from where the network has it
        (a foot the network moves slowly to a new place is re-planted there, not frozen).
    """

    height: float = 0.10
    speed: float = 1.0
    min_frames: int = 3
    release_frames: int = 5
    max_stretch: float = 0.97
    max_offset: float = 0.05
    max_turn: float = 0.5


def planted_feet(ankles: np.ndarray, fps: float, cfg: FootLockConfig = FootLockConfig()
                 ) -> np.ndarray:
    """(B,T,F) bool: which ankles (B,T,F,3, world metres, floor y = 0) are planted."""
    ankles = np.asarray(ankles, np.float64)
    if ankles.ndim != 4 or ankles.shape[-1] != 3:
        raise ValueError(f"ankles must be (B,T,F,3), got {ankles.shape}")
    if ankles.shape[1] < 2:  # no speed without a second frame: nothing to hold
        return np.zeros(ankles.shape[:3], bool)
    step = np.linalg.norm(np.diff(ankles[..., [0, 2]], axis=1), axis=-1) * fps  # (B,T-1,F)
    # a frame's speed: the slower of its two neighbouring steps, so a plant's first and last
    # frames count
    speed = np.minimum(np.concatenate([step[:, :1], step], 1),
                       np.concatenate([step, step[:, -1:]], 1))
    return (ankles[..., 1] <= cfg.height) & (speed <= cfg.speed)


def _hold_offsets(track: np.ndarray, plant: np.ndarray, hip: np.ndarray, ankle: np.ndarray,
                  leg: float, cfg: FootLockConfig) -> tuple[np.ndarray, np.ndarray]:
    """(T,K) offsets that keep one foot's ``track`` (T,K: horizontal position x, z and
    unwrapped heading) at each plant's start and fade out after it, and the (T,) frames held
    at a plant's start.

    plant: (T,) bool; hip, ankle: (T,3) world positions (m); leg: hip-to-ankle length at full
    extension (m). A plant ends early where holding it would stretch the leg beyond
    ``cfg.max_stretch`` of that length, or put the foot more than ``cfg.max_offset`` (or
    ``cfg.max_turn``) from where the network has it (the body has moved on: the foot takes a
    step); what is left of it, after the release, is a new plant.
    """
    t_len = len(track)
    offset = np.zeros_like(track)
    hold = np.zeros(t_len, bool)
    edges = np.diff(np.concatenate([[0], plant.astype(np.int8), [0]]))
    todo = list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))
    while todo:  # one pass per plant, not per frame
        s, e = todo.pop(0)
        if e - s < cfg.min_frames:
            continue
        held = np.column_stack([np.full(e - s, track[s, 0]), ankle[s:e, 1],
                                np.full(e - s, track[s, 1])])
        drift = track[s] - track[s:e]
        far = np.flatnonzero((np.linalg.norm(held - hip[s:e], axis=-1) > cfg.max_stretch * leg)
                             | (np.linalg.norm(drift[:, :2], axis=-1) > cfg.max_offset)
                             | (np.abs(drift[:, 2]) > cfg.max_turn))
        if far.size:
            todo.insert(0, (s + int(far[0]) + cfg.release_frames, e))
            e = s + int(far[0])
            if e - s < cfg.min_frames:
                continue
        offset[s:e] = drift[:e - s]
        hold[s:e] = True
        r = min(cfg.release_frames, t_len - e)
        fade = 1.0 - np.arange(1, r + 1) / (cfg.release_frames + 1)
        offset[e:e + r] = offset[e - 1] * fade[:, None]
    return offset, hold


def lock_feet(root: np.ndarray, jpos: np.ndarray, jrot: np.ndarray, rest: np.ndarray,
              fps: float, cfg: FootLockConfig = FootLockConfig()
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hold planted feet still: the ankle's horizontal position and the foot's heading.

    Args:
        root: (B,T,4,4) world_from_root, yaw about +Y only (the controller's roots).
        jpos: (B,T,J,3) root-frame joint positions (m).
        jrot: (B,T,J,6) root-frame global joint rotations (6D). rest: (24,3) rest joints.
        fps: frame rate (Hz).
    Returns:
        new jpos (B,T,J,3), new jrot (B,T,J,6) (hips and knees re-bent, ankles and toes
        turned about the vertical; knees, ankles and toes moved; everything else unchanged)
        and the frames (B,T,2) whose foot was held where its plant began (the releases
        after them excluded).
    """
    root, jpos, jrot = (np.asarray(a, np.float64) for a in (root, jpos, jrot))
    b, t, j = jpos.shape[:3]
    hips, ankles, toes = [leg[0] for leg in LEGS], [leg[2] for leg in LEGS], list(_TOES)
    skeleton = Skeleton(rest)
    flat = b * t
    rot = sixd_to_matrix(jrot.reshape(flat, j, 6))
    pos = jpos.reshape(flat, j, 3)
    pelvis = pos[:, 0]
    # The legs as the output shows them: forward kinematics of the rotations (the predicted
    # positions J also carries need not match them to the millimetre).
    fk = forward_positions(pelvis, rot, skeleton, hips + ankles + toes)
    world = apply_transform(root, np.stack([fk[k] for k in hips + ankles + toes], 1)
                            .reshape(b, t, 6, 3))
    hip_w, ankle_w, toe_w = world[:, :, :2], world[:, :, 2:4], world[:, :, 4:]
    plant = planted_feet(ankle_w, fps, cfg)
    foot = toe_w - ankle_w
    heading = np.unwrap(np.arctan2(foot[..., 0], foot[..., 2]), axis=1)  # (B,T,2)
    track = np.concatenate([ankle_w[..., [0, 2]], heading[..., None]], -1)  # (B,T,2,3)
    offset = np.zeros_like(track)
    hold = np.zeros(plant.shape, bool)
    reach = [skeleton.bone_length(h, k) + skeleton.bone_length(k, a) for h, k, a in LEGS]
    for i in range(b):
        for f, leg in enumerate(reach):
            offset[i, :, f], hold[i, :, f] = _hold_offsets(
                track[i, :, f], plant[i, :, f], hip_w[i, :, f], ankle_w[i, :, f], leg, cfg)
    goal = ankle_w.copy()
    goal[..., [0, 2]] += offset[..., :2]
    held = np.abs(offset).sum(-1) > 0  # (B,T,2)
    new_rot, moved = bend_limbs(pelvis, rot, LEGS, np.zeros((2, 3)),
                                to_root(goal, root).reshape(flat, 2, 3),
                                held.reshape(flat, 2).astype(np.float64), skeleton)
    out = pos.copy()
    for k, d in moved.items():
        out[:, k] += d
    # The foot turns about the vertical through its ankle (the root frame's +Y is the
    # world's), so its toe keeps the heading the plant began with.
    turn = axis_angle_to_matrix(np.einsum("n,k->nk", offset[..., 2].reshape(-1),
                                          np.array([0.0, 1.0, 0.0]))).reshape(flat, 2, 3, 3)
    for f, (ankle, toe) in enumerate(zip(ankles, toes, strict=True)):
        out[:, toe] = out[:, ankle] + np.einsum("nij,nj->ni", turn[:, f],
                                                pos[:, toe] - pos[:, ankle])
        new_rot[:, ankle] = turn[:, f] @ new_rot[:, ankle]
        new_rot[:, toe] = turn[:, f] @ new_rot[:, toe]
    return out.reshape(b, t, j, 3), matrix_to_6d(new_rot).reshape(b, t, j, 6), hold
