"""Foot locking: the foot-skate clean-up game-animation pipelines run after a motion
controller (the synthesised feet slide ~1-6 mm/frame, the simulated data's 0.06).

A foot is planted while its ankle is low and slow. During a plant the ankle keeps its place
(horizontally; its height stays the network's) by two-bone IK of hip-knee-ankle, and the foot
keeps its heading about the vertical (its pitch and roll stay the network's), so neither
ankle nor toe slides. The hold is a leash: where the network moves the foot on by more than
a few centimetres (or the leg would stretch), the foot is dragged after it at the network's
own step instead of being let go (a let-go hold moves the foot the whole way at once, where
it is still on the floor); after a plant the offset fades over a few frames so the foot
does not jump. It is a post-process on the output: the networks never see the edited legs
(unlike the hand IK, which they are fed back), so it cannot change where the character goes
or what its hands reach.

Everything is batch first: B characters x T frames, root-frame joints as the controller keeps
them (positions in metres, global rotations in 6D) and world_from_root transforms.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from couch.body import JOINT_INDEX, Skeleton
from couch.geometry import apply_transform
from couch.rotations import axis_angle_to_matrix, matrix_to_6d, sixd_to_matrix
from couch.runs import drop_short_runs
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
        fades to zero over this many frames. The leash: a held foot is never put farther
        from the hip than ``max_stretch`` of the leg's length, nor more than ``max_offset``
        (m) or ``max_turn`` (rad) from where the network has it; past that it is dragged
        after the network's foot (a foot the network moves slowly to a new place follows
        it, not frozen).
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


def _leashed_offsets(track: np.ndarray, plant: np.ndarray, hip: np.ndarray, ankle: np.ndarray,
                     reach: np.ndarray, cfg: FootLockConfig) -> tuple[np.ndarray, np.ndarray]:
    """(B,T,F,3) offsets to add to each foot's ``track`` (B,T,F,3: horizontal ankle position
    x, z in m and unwrapped heading in rad) that keep a planted foot where it was, and the
    (B,T,F) frames where it stayed put.

    A planted foot keeps its last position and heading; the offset is a leash: it never grows
    past ``cfg.max_offset`` (m) or ``cfg.max_turn`` (rad), nor so far that the ankle would lie
    farther than ``reach`` (F,) (m) from the hip, so a foot the network moves on is dragged
    after it at the network's own per-frame step (faster only where the leg's reach shortens
    the leash). After a plant the offset fades to zero over ``cfg.release_frames`` frames (where
    the foot is lifting or swinging); a plant that begins inside a release carries what is
    left of it, so the foot never jumps. plant: (B,T,F) bool; hip, ankle: (B,T,F,3) world (m).
    """
    b, t_len, f = plant.shape
    r = cfg.release_frames
    offset = np.zeros_like(track)
    held = np.zeros(plant.shape, bool)
    off = np.zeros((b, f, 3))
    since = np.full((b, f), r + 1)  # frames since a plant ended (r + 1: no release pending)
    # The leash is a recurrence in time: one step per frame, every character and foot at once.
    for t in range(t_len):
        p = plant[:, t]
        step = track[:, t] - track[:, t - 1] if t else np.zeros((b, f, 3))
        kept = p & plant[:, t - 1] if t else np.zeros((b, f), bool)
        since = np.where(p, 0, since + 1)
        # a release's factor per frame: (r+1-k)/(r+2-k) for its k-th frame multiplies out to
        # a linear fade, (r+1-k)/(r+1), zero from frame r+1 on
        fade = np.where(p, 1.0, np.clip(r + 1 - since, 0, None) / np.maximum(r + 2 - since, 1))
        want = np.where(kept[..., None], off - step, off * fade[..., None])
        norm = np.linalg.norm(want[..., :2], axis=-1)
        xy = want[..., :2] * np.minimum(1.0, cfg.max_offset / np.maximum(norm, 1e-12))[..., None]
        # the largest share lam of the offset that keeps |ankle - hip + lam * o| within reach
        a = ankle[:, t] - hip[:, t]
        o = np.stack([xy[..., 0], np.zeros_like(norm), xy[..., 1]], -1)
        oo, ao = (o * o).sum(-1), (a * o).sum(-1)
        disc = ao ** 2 - oo * ((a * a).sum(-1) - reach ** 2)
        lam = np.where((oo > 0) & (disc >= 0),
                       (np.sqrt(np.maximum(disc, 0.0)) - ao) / np.maximum(oo, 1e-24), 0.0)
        lam = np.where(oo > 0, np.clip(lam, 0.0, 1.0), 1.0)
        new = np.concatenate([xy * lam[..., None],
                              np.clip(want[..., 2:], -cfg.max_turn, cfg.max_turn)], -1)
        offset[:, t] = off = new
        held[:, t] = p & np.all(np.abs(new - want) < 1e-12, axis=-1)
    return offset, held


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
        and the frames (B,T,2) whose foot stayed where it was (planted, the leash slack;
        dragged frames and releases excluded).
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
    reach = cfg.max_stretch * np.array([skeleton.bone_length(h, k) + skeleton.bone_length(k, a)
                                        for h, k, a in LEGS])
    plant = drop_short_runs(plant.transpose(1, 0, 2).reshape(t, b * 2), cfg.min_frames)
    offset, hold = _leashed_offsets(track, plant.reshape(t, b, 2).transpose(1, 0, 2), hip_w,
                                    ankle_w, reach, cfg)
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
    # world's), so its toe keeps its heading.
    turn = axis_angle_to_matrix(np.einsum("n,k->nk", offset[..., 2].reshape(-1),
                                          np.array([0.0, 1.0, 0.0]))).reshape(flat, 2, 3, 3)
    for f, (ankle, toe) in enumerate(zip(ankles, toes, strict=True)):
        out[:, toe] = out[:, ankle] + np.einsum("nij,nj->ni", turn[:, f],
                                                pos[:, toe] - pos[:, ankle])
        new_rot[:, ankle] = turn[:, f] @ new_rot[:, ankle]
        new_rot[:, toe] = turn[:, f] @ new_rot[:, toe]
    return out.reshape(b, t, j, 3), matrix_to_6d(new_rot).reshape(b, t, j, 6), hold
