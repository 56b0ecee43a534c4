"""COUCH motion features (paper Sec. 4.2-4.5): J, T, G, I, E, local and global phases, control
signals, PoseNet targets and their normalisation statistics.

Small functions over batched arrays (frames or characters first) serve both training (whole
sequences, :func:`sequence_features`) and the runtime controller (one frame of state for a batch
of characters). Nothing loops over frames; loops run over the 13 trajectory samples, the two hands,
the 24 joints of the kinematic chain or the few contact runs of a sequence.

Conventions (DESIGN.md): metres, seconds, world Y up with the floor at y = 0, SMPL's 24 joints in
SMPL order. The *root frame* of a frame is ``world_from_root`` (4x4) from :func:`root_transforms`:
origin = the pelvis projected onto the floor, axes x = the body's left (``cross(up, forward)``),
y = world up, z = the horizontal facing direction. Directions are 6D rotations
(:func:`couch.rotations.matrix_to_6d`: the first two matrix columns). "In the root frame" means
``inverse(root) @ world`` for points and ``R_root^T @`` for vectors and rotations.

Hand joints: the SMPL ``left_hand``/``right_hand`` joints (22/23, knuckle-ish, ~8 cm past the
wrists) stand for the hands, because contacts lie on the palm; J itself uses joints 0..21 only.
Hand order is always (left, right).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.signal import find_peaks
from scipy.spatial.transform import Rotation, Slerp

from couch.atomic import atomic_path
from couch.body import JOINT_INDEX, NUM_JOINTS, PARENTS
from couch.geometry import apply_transform, invert_transform, make_transform
from couch.rotations import Array, axis_angle_to_matrix, matrix_to_6d, sixd_to_matrix
from couch.runs import runs
from couch.schema import ProcessedSession

ACTIONS: tuple[str, ...] = ("idle", "walk", "sit")
IDLE, WALK, SIT = 0, 1, 2
HANDS: tuple[str, ...] = ("left_hand", "right_hand")
UP = np.array([0.0, 1.0, 0.0])


@dataclasses.dataclass(frozen=True)
class FeatureConfig:
    """Feature settings; defaults are the paper's numbers (Sec. 4.2-4.3) where it gives them."""

    fps: float = 30.0  # frame rate the networks run at; other sessions are resampled
    num_joints: int = 22  # SMPL joints 0..21 in J (no hand joints 22/23)
    trajectory_samples: int = 13  # T and G: samples uniformly over [-window, +window]
    trajectory_window: float = 1.0  # s
    control_samples: int = 7  # control signal: samples uniformly over [0, window]
    control_window: float = 1.0  # s
    interaction_resolution: int = 8  # I: the chair's bounding box in res^3 voxels
    interaction_subsamples: int = 3  # per axis; occupancy = fraction of sub-samples inside
    ego_rings: int = 8  # E: radial rings out to ego_radius
    ego_radius: float = 1.2  # m
    ego_sectors: int = 16  # angular sectors, sector 0 centred near the forward direction
    ego_layers: int = 11  # height layers from the floor up to ego_height
    ego_height: float = 2.2  # m
    occupancy_voxel: float = 0.03  # m: fine object-frame grid that E looks cell centres up in
    walk_speed: float = 0.3  # m/s: smoothed root speed above which a frame is "walk"
    speed_smoothing: float = 0.2  # s: moving-average window of the root speed
    action_smoothing: float = 0.25  # s: moving-average window turning one-hot into soft labels
    hand_approach: float = 1.0  # s: longest reach before a hand contact onset
    hand_approach_speed: float = 0.15  # m/s: hand speed that starts the reach in that window
    hand_release: float = 0.5  # s: local phase falls from 1 to 0 over this after a release
    # m: a hand's control (target, C+, the baseline's contact inputs) is on only while the root
    # is this close to the target horizontally: the runtime approaches with PoseNet alone and
    # switches ControlNet on near the chair (paper Sec. 4.5), so training sees the same.
    control_radius: float = 1.5
    # m above the contact (world up; negative: below) where ControlNet's straight line h̃
    # ends. A touching hand joint stays ~6-8 cm above the contact (the palm is on it), yet on
    # the contact brings the palm closest: 7 cm above and 3 cm below were both worse (README,
    # Results so far), as PoseNet follows ControlNet's trajectory only part of the way.
    control_line_end: float = 0.0
    # s: a hand contact run that starts this close to the pelvis leaving the seat (before or
    # after), or standing after it with no later sit, is the stand-up's push-off, not part of
    # the sit: no control target (mask off, local phase 0), so the control of a seated
    # character never means "stand up now" as it did in the data (sit_contact_flags). None:
    # every run is a target (runs and caches from before the setting).
    push_off_window: float | None = 1.0
    sit_transition: float = 1.5  # s: longest sit-down transition (global phase 0 -> 1)
    step_min_interval: float = 0.4  # s: closest two left-foot strikes may be
    walk_cycle: float = 1.0  # s: nominal cycle when fewer than two strikes are found
    hand_joints: tuple[int, int] = (JOINT_INDEX["left_hand"], JOINT_INDEX["right_hand"])
    min_std: float = 1e-2  # FeatureStats floor on standard deviations

    @property
    def trajectory_offsets(self) -> np.ndarray:
        """(13,) int frame offsets of the trajectory samples ([-30, -25, ..., 30] at 30 fps)."""
        return _offsets(-self.trajectory_window, self.trajectory_window,
                        self.trajectory_samples, self.fps)

    @property
    def control_offsets(self) -> np.ndarray:
        """(7,) int frame offsets of the control samples ([0, 5, ..., 30] at 30 fps)."""
        return _offsets(0.0, self.control_window, self.control_samples, self.fps)

    @property
    def future_samples(self) -> np.ndarray:
        """Indices of the trajectory samples at offsets >= 0 (6..12 by default)."""
        return np.flatnonzero(self.trajectory_offsets >= 0)

    @property
    def ego_cells(self) -> int:
        return self.ego_rings * self.ego_sectors * self.ego_layers

    @property
    def interaction_dim(self) -> int:
        return 4 * self.interaction_resolution ** 3


def _offsets(start: float, stop: float, n: int, fps: float) -> np.ndarray:
    return np.round(np.linspace(start, stop, n) * fps).astype(np.int64)


def _frames(seconds: float, fps: float) -> int:
    return max(1, round(seconds * fps))


# ----------------------------------------------------------------------------- resampling


def resample(session: ProcessedSession, fps: float) -> ProcessedSession:
    """``session`` on a uniform ``fps`` time grid from its first time stamp to its last.

    Positions (transl, joints, contact points, object frame translations) are linear in time,
    rotations (global_orient, body_pose, object frame rotations) use scipy ``Slerp``, booleans
    and labels take the nearest frame; contact points are NaN wherever the resampled contact is
    inactive (and take the nearest frame's point where linear interpolation meets a NaN).
    ``quality`` arrays are dropped (they describe the original frames).
    """
    t_old = np.asarray(session.time, dtype=np.float64)
    n = int(np.floor((t_old[-1] - t_old[0]) * fps + 1e-6)) + 1
    t_new = t_old[0] + np.arange(n) / fps
    t_new = np.minimum(t_new, t_old[-1])
    nearest = _nearest_index(t_old, t_new)

    def linear(x: np.ndarray) -> np.ndarray:
        flat = np.asarray(x, dtype=np.float64).reshape(len(t_old), -1)
        hi = np.clip(np.searchsorted(t_old, t_new, side="right"), 1, len(t_old) - 1)
        lo = hi - 1
        w = ((t_new - t_old[lo]) / (t_old[hi] - t_old[lo]))[:, None] if len(t_old) > 1 else 0.0
        out = (1 - w) * flat[lo] + w * flat[hi] if len(t_old) > 1 else flat[lo]
        return out.reshape((n, *np.shape(x)[1:]))

    def slerp(aa: np.ndarray) -> np.ndarray:  # (T_old, J, 3) axis-angle -> (n, J, 3)
        if len(t_old) == 1:
            return np.repeat(aa, n, axis=0)
        out = np.empty((n, aa.shape[1], 3))
        for j in range(aa.shape[1]):
            out[:, j] = Slerp(t_old, Rotation.from_rotvec(aa[:, j]))(t_new).as_rotvec()
        return out

    global_orient = slerp(np.asarray(session.global_orient, np.float64)[:, None])[:, 0]
    body_pose = slerp(np.asarray(session.body_pose, np.float64).reshape(len(t_old), -1, 3))
    frame_poses = np.asarray(session.object_frame_poses, np.float64)
    rot = Rotation.from_matrix(frame_poses[:, :3, :3]).as_rotvec()[:, None]
    new_frame_poses = make_transform(axis_angle_to_matrix(slerp(rot)[:, 0]),
                                     linear(frame_poses[:, :3, 3]))
    active = np.asarray(session.contact_active)[nearest]
    points = linear(session.contact_points)
    points = np.where(np.isnan(points), np.asarray(session.contact_points)[nearest], points)
    points[~active] = np.nan
    return dataclasses.replace(
        session, fps=float(fps), time=t_new,
        global_orient=global_orient.astype(np.float32),
        body_pose=body_pose.reshape(n, -1).astype(np.float32),
        transl=linear(session.transl).astype(np.float32),
        joints=linear(session.joints).astype(np.float32),
        object_frame_poses=new_frame_poses,
        contact_active=active, contact_points=points.astype(np.float32),
        interaction=np.asarray(session.interaction)[nearest], quality={})


def _nearest_index(t_old: np.ndarray, t_new: np.ndarray) -> np.ndarray:
    hi = np.clip(np.searchsorted(t_old, t_new), 0, len(t_old) - 1)
    lo = np.clip(hi - 1, 0, len(t_old) - 1)
    return np.where(np.abs(t_new - t_old[lo]) <= np.abs(t_old[hi] - t_new), lo, hi)


def canonical_chair(session: ProcessedSession) -> ProcessedSession:
    """``session`` with its chair expressed in the canonical chair frame (seat centred on
    x = z = 0, floor y = 0, facing +Z; :func:`couch.augment.canonical_chair_frame`) instead of
    the frame it was captured or scanned in, so that I, ContactNet's condition and its contacts
    mean the same thing for every chair, and the runtime (which is given chair-frame meshes)
    sees what training saw. The world is unchanged: only ``object_vertices``, ``object_pose``
    and ``object_frame_poses`` are re-expressed."""
    from couch.augment import canonical_chair_frame  # heavy imports, only needed here

    pose = np.asarray(session.object_pose, np.float64)
    world = apply_transform(pose, np.asarray(session.object_vertices, np.float64))
    # Not warned: a backless seat (the simulator's stools) gets an arbitrary front, and a
    # warning per such sequence buried couch-train's and couch-eval's output.
    canonical = canonical_chair_frame(world, np.asarray(session.object_faces), warn=False)
    old_from_new = invert_transform(pose) @ canonical
    return dataclasses.replace(
        session, object_pose=canonical,
        object_vertices=apply_transform(invert_transform(canonical), world).astype(np.float32),
        object_frame_poses=np.asarray(session.object_frame_poses, np.float64) @ old_from_new)


# ----------------------------------------------------------------------------- root and J


def root_transforms(joints: np.ndarray) -> np.ndarray:
    """Root frames from joint positions.

    Args:
        joints: (..., 24, 3) world joint positions (SMPL order), metres.
    Returns:
        (..., 4, 4) world_from_root: origin = pelvis with y = 0; z = forward = the horizontal
        part of the mean of ``cross(left_hip - right_hip, up)`` and
        ``cross(left_shoulder - right_shoulder, up)``, normalised; y = up; x = cross(up, z).
    """
    joints = np.asarray(joints, dtype=np.float64)
    across = (joints[..., JOINT_INDEX["left_hip"], :] - joints[..., JOINT_INDEX["right_hip"], :]
              + joints[..., JOINT_INDEX["left_shoulder"], :]
              - joints[..., JOINT_INDEX["right_shoulder"], :])
    forward = np.cross(across, UP)
    forward[..., 1] = 0.0
    norm = np.linalg.norm(forward, axis=-1, keepdims=True)
    forward = np.where(norm > 1e-9, forward / np.maximum(norm, 1e-12), [0.0, 0.0, 1.0])
    up = np.broadcast_to(UP, forward.shape)
    rotation = np.stack([np.cross(up, forward), up, forward], axis=-1)
    origin = joints[..., JOINT_INDEX["pelvis"], :] * np.array([1.0, 0.0, 1.0])
    return make_transform(rotation, origin)


def global_rotations(global_orient: np.ndarray, body_pose: np.ndarray) -> np.ndarray:
    """World rotations of the 24 joints by the SMPL kinematic chain.

    Args:
        global_orient: (..., 3) axis-angle of the pelvis (world from pelvis).
        body_pose: (..., 69) axis-angle of joints 1..23 relative to their parents.
    Returns:
        (..., 24, 3, 3) world-from-joint rotations (matches the body model's joint_transforms).
    """
    go = np.asarray(global_orient, dtype=np.float64)
    local = axis_angle_to_matrix(np.concatenate(
        [go[..., None, :], np.asarray(body_pose, np.float64).reshape((*go.shape[:-1], -1, 3))],
        axis=-2))
    chain = [local[..., 0, :, :]]
    for j in range(1, NUM_JOINTS):
        chain.append(chain[PARENTS[j]] @ local[..., j, :, :])
    return np.stack(chain, axis=-3)


def to_root(points: np.ndarray, root: np.ndarray) -> np.ndarray:
    """(..., N, 3) world points -> root frame, with ``root`` (..., 4, 4) world_from_root."""
    return apply_transform(invert_transform(root), points)


def vectors_to_root(vectors: np.ndarray, root: np.ndarray) -> np.ndarray:
    """(..., N, 3) world vectors (velocities, offsets) rotated into the root frame."""
    return np.einsum("...ji,...nj->...ni", root[..., :3, :3], vectors)


def velocities(positions: np.ndarray, fps: float) -> np.ndarray:
    """(T, ...) positions -> (T, ...) velocities (units per second): backward differences, the
    first frame a forward difference (zeros for a single frame)."""
    positions = np.asarray(positions, dtype=np.float64)
    if len(positions) < 2:
        return np.zeros_like(positions)
    d = np.diff(positions, axis=0) * fps
    return np.concatenate([d[:1], d], axis=0)


def pose_features(joints: np.ndarray, global_rot: np.ndarray, root: np.ndarray, fps: float,
                  num_joints: int = 22, joint_velocities: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """J: the character's pose in its root frame.

    Args:
        joints: (T, >=num_joints, 3) world joint positions.
        global_rot: (T, >=num_joints, 3, 3) world joint rotations (:func:`global_rotations`).
        root: (T, 4, 4) world_from_root.
        fps: frame rate for the velocities.
        joint_velocities: (T, >=num_joints, 3) world velocities (m/s) to use instead of finite
            differences of ``joints`` (the runtime passes them with a single frame).
    Returns:
        positions (T, J, 3) m, rotations (T, J, 6) 6D of ``R_root^T R_joint``, velocities
        (T, J, 3) m/s rotated into the root frame of the same frame.
    """
    joints = np.asarray(joints, dtype=np.float64)[:, :num_joints]
    if joint_velocities is None:
        joint_velocities = velocities(joints, fps)
    positions = to_root(joints, root)
    rel = np.einsum("tji,tnjk->tnik", root[:, :3, :3], np.asarray(global_rot)[:, :num_joints])
    vel = vectors_to_root(np.asarray(joint_velocities)[:, :num_joints], root)
    return positions, matrix_to_6d(rel), vel


def relative_root(root: np.ndarray, other: np.ndarray) -> np.ndarray:
    """(..., 9): ``other`` (..., 4, 4) in the frame of ``root`` (..., 4, 4): position (3) and
    direction as 6D rotation (6)."""
    rel = invert_transform(root) @ other
    return np.concatenate([rel[..., :3, 3], matrix_to_6d(rel[..., :3, :3])], axis=-1)


# ----------------------------------------------------------------------------- actions, T, G


def contact_runs(active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T,) bool -> (starts, ends) int arrays of the True runs, ends inclusive."""
    starts, ends = runs(active)
    return starts, ends - 1


def root_speed(root: np.ndarray, fps: float, smoothing: float = 0.2) -> np.ndarray:
    """(T,) horizontal root speed (m/s) from (T, 4, 4) roots, moving-average smoothed over
    ``smoothing`` seconds."""
    v = velocities(root[:, :3, 3], fps)
    speed = np.linalg.norm(v[:, [0, 2]], axis=-1)
    return uniform_filter1d(speed, _frames(smoothing, fps), mode="nearest")


def action_labels(sitting: np.ndarray, speed: np.ndarray, cfg: FeatureConfig
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame actions.

    Args:
        sitting: (T,) bool, pelvis contact active.
        speed: (T,) smoothed horizontal root speed, m/s (:func:`root_speed`).
    Returns:
        labels (T,) int (0 idle, 1 walk, 2 sit) and soft labels (T, 3): the one-hot labels
        moving-averaged over ``cfg.action_smoothing`` seconds (rows sum to 1).
    """
    labels = np.where(sitting, SIT, np.where(speed > cfg.walk_speed, WALK, IDLE))
    onehot = np.eye(len(ACTIONS))[labels]
    soft = uniform_filter1d(onehot, _frames(cfg.action_smoothing, cfg.fps), axis=0,
                            mode="nearest")
    return labels, soft / soft.sum(-1, keepdims=True)


def sample_indices(num_frames: int, offsets: np.ndarray, start: int = 0) -> np.ndarray:
    """(T, K) frame indices ``t + start + offsets[k]`` clamped to the sequence."""
    t = np.arange(num_frames)[:, None] + start
    return np.clip(t + np.asarray(offsets)[None], 0, num_frames - 1)


def trajectory_features(root: np.ndarray, actions: np.ndarray, offsets: np.ndarray
                        ) -> np.ndarray:
    """T: (T, K, 12) root trajectory around each frame.

    Args:
        root: (T, 4, 4) world_from_root; actions: (T, 3) soft action labels;
        offsets: (K,) frame offsets (clamped at the sequence ends).
    Returns:
        per sample: root position (3, in the root frame of frame t; y = 0), root direction
        (6D rotation relative to the root of t), soft action labels (3).
    """
    idx = sample_indices(len(root), offsets)
    rel = relative_root(root[:, None], root[idx])
    return np.concatenate([rel, actions[idx]], axis=-1)


def goal_frames(sitting: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The goal of each frame: the next sit onset (first frame of the current or next pelvis
    contact run), else the last frame.

    Returns:
        goal frame index (T,) int and goal action (T,) int: sit for sit goals; for frames with
        no later sit, the last frame's action (walk if still moving, else idle).
    """
    starts, ends = contact_runs(sitting)
    t = np.arange(len(sitting))
    run = np.searchsorted(ends, t, side="left")
    has = run < len(starts)
    frame = np.full(len(sitting), len(sitting) - 1)
    frame[has] = starts[run[has]]
    last = WALK if labels[-1] == WALK else IDLE
    return frame, np.where(has, SIT, last)


def goal_features(root: np.ndarray, goal_root: np.ndarray, goal_action: np.ndarray,
                  offsets: np.ndarray) -> np.ndarray:
    """G: (T, K, 12) goals at the trajectory samples.

    Args:
        root: (T, 4, 4) world_from_root; goal_root: (T, 4, 4) each frame's goal root pose;
        goal_action: (T,) int goal action; offsets: (K,) frame offsets.
    Returns:
        per sample k (frame s = t + offsets[k], clamped): the goal of frame s as position (3)
        and direction (6D) relative to the root of frame s, and the goal action one-hot (3).
    """
    idx = sample_indices(len(root), offsets)
    rel = relative_root(root[idx], goal_root[idx])
    return np.concatenate([rel, np.eye(len(ACTIONS))[goal_action[idx]]], axis=-1)


# ----------------------------------------------------------------------------- I and E


def _occupancy_at(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) bool: points (N,3) inside the mesh (object frame); each connected part is tested on
    its own, so overlapping closed parts still count as inside."""
    import open3d as o3d
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces), process=False)
    parts = mesh.split(only_watertight=False) if len(mesh.faces) else []
    query = o3d.core.Tensor(np.asarray(points, np.float32))
    inside = np.zeros(len(points), dtype=bool)
    for part in parts:
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(np.asarray(part.vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(part.faces, np.uint32)))
        inside |= scene.compute_occupancy(query, nsamples=3).numpy() > 0.5
    return inside


def voxel_grid(vertices: np.ndarray, faces: np.ndarray, resolution: int = 8,
               subsamples: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The chair's bounding box (object frame) in ``resolution``^3 voxels.

    Returns:
        occupancy (R^3,) float32 in [0, 1]: fraction of ``subsamples``^3 points per voxel inside
        the mesh; centres (R^3, 3) object-frame voxel centres (x slowest, z fastest); size (3,)
        voxel edge lengths, m.
    """
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    size = np.maximum(hi - lo, 1e-6) / resolution
    ijk = np.stack(np.meshgrid(*[np.arange(resolution)] * 3, indexing="ij"), -1).reshape(-1, 3)
    centres = lo + (ijk + 0.5) * size
    sub = (np.arange(subsamples) + 0.5) / subsamples - 0.5
    sub = np.stack(np.meshgrid(sub, sub, sub, indexing="ij"), -1).reshape(-1, 3)
    points = (centres[:, None] + sub[None] * size).reshape(-1, 3)
    inside = _occupancy_at(v, faces, points).reshape(len(centres), -1)
    return inside.mean(1).astype(np.float32), centres, size


def chair_voxels(vertices: np.ndarray, faces: np.ndarray, object_pose: np.ndarray,
                 resolution: int = 8, subsamples: int = 3
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`voxel_grid` posed into the world by ``object_pose`` (4,4 world_from_object).

    Returns occupancy (R^3,), centres_world (R^3, 3), size (3,) (object-frame edge lengths).
    Compute once per chair.
    """
    occupancy, centres, size = voxel_grid(vertices, faces, resolution, subsamples)
    return occupancy, apply_transform(np.asarray(object_pose, np.float64), centres), size


def interaction_features(occupancy: np.ndarray, centres_world: np.ndarray, root: np.ndarray
                         ) -> np.ndarray:
    """I: (..., 4·N) per voxel (occupancy, vector root -> voxel centre in the root frame),
    voxel-major: ``[occ_0, x_0, y_0, z_0, occ_1, ...]``.

    Args:
        occupancy: (N,) voxel occupancies; centres_world: (N, 3); root: (..., 4, 4).
    """
    rel = to_root(np.broadcast_to(centres_world, (*root.shape[:-2], *centres_world.shape)), root)
    occ = np.broadcast_to(occupancy, rel.shape[:-1])[..., None]
    return np.concatenate([occ, rel], axis=-1).reshape((*root.shape[:-2], -1))


def interaction_layer(occupancy: np.ndarray, centres_world: np.ndarray, weight: np.ndarray,
                      bias: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """A linear layer over normalised I, ``y = weight ((I(root) - mean) / std) + bias``, as an
    affine map of the root pose: A (H, 13) with ``y = A @ root_affine(root)``.

    I's vectors are ``M c + m`` for the fixed voxel centres c, with (M, m) the rotation and
    translation of ``root^-1``, so the layer is affine in the 12 numbers of ``root^-1``: for a
    given chair its 4N inputs fold into 13 columns (a network's first layer over I need not
    read its (H, 4N) weights every frame).

    Args:
        occupancy: (N,); centres_world: (N, 3) (:func:`interaction_features`' arguments);
        weight: (H, 4N); bias: (H,); mean, std: (4N,) I's normalisation.
    """
    w = np.asarray(weight, np.float64) / np.asarray(std, np.float64)
    const = np.asarray(bias, np.float64) - w @ np.asarray(mean, np.float64)
    w = w.reshape(len(w), -1, 4)  # voxel-major: (occupancy, x, y, z) per voxel
    const = const + w[..., 0] @ np.asarray(occupancy, np.float64)
    rot = np.einsum("hna,nb->hab", w[..., 1:], np.asarray(centres_world, np.float64))
    return np.concatenate([const[:, None], rot.reshape(len(w), 9), w[..., 1:].sum(1)], 1)


def root_affine(root: np.ndarray) -> np.ndarray:
    """(..., 13) ``[1, M (9, row-major), m (3)]`` of ``root^-1`` = (M, m), for roots (..., 4, 4):
    what :func:`interaction_layer`'s map multiplies."""
    inv = invert_transform(root)
    return np.concatenate([np.ones((*root.shape[:-2], 1)),
                           inv[..., :3, :3].reshape(*root.shape[:-2], 9), inv[..., :3, 3]], -1)


def contact_net_condition(occupancy: np.ndarray, centres_object: np.ndarray,
                          centre: np.ndarray | None = None) -> np.ndarray:
    """ContactNet's condition (4·N,): I with vectors from the chair centre (default: the
    bounding-box centre = mean voxel centre) to each voxel, in the chair frame."""
    centre = np.mean(centres_object, axis=0) if centre is None else np.asarray(centre)
    rel = np.asarray(centres_object) - centre
    return np.concatenate([np.asarray(occupancy)[:, None], rel], axis=-1).reshape(-1)


@dataclasses.dataclass
class OccupancyGrid:
    """A fine occupancy grid of one chair in its object frame, for cheap point lookups.

    occupancy: (nx, ny, nz) bool; origin: (3,) object-frame centre of voxel (0, 0, 0);
    voxel: edge length, m; world_from_object: (4, 4).
    """

    occupancy: np.ndarray
    origin: np.ndarray
    voxel: float
    world_from_object: np.ndarray

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, faces: np.ndarray, object_pose: np.ndarray,
                  voxel: float = 0.03, pad: int = 2) -> OccupancyGrid:
        """Occupancy at the centres of ``voxel``-sized cells over the mesh's bounding box
        (object frame) padded by ``pad`` cells."""
        v = np.asarray(vertices, np.float64)
        lo = v.min(0) - pad * voxel
        shape = np.ceil((v.max(0) + pad * voxel - lo) / voxel).astype(int) + 1
        ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1)
        inside = _occupancy_at(v, faces, (lo + ijk.reshape(-1, 3) * voxel))
        return cls(inside.reshape(shape), lo, float(voxel),
                   np.asarray(object_pose, np.float64))

    def lookup(self, points_world: np.ndarray) -> np.ndarray:
        """(..., 3) world points -> (...) float32 occupancy of the nearest voxel (0 outside)."""
        p = apply_transform(invert_transform(self.world_from_object),
                            np.asarray(points_world, np.float64).reshape(-1, 3))
        return self.lookup_object(p).reshape(np.shape(points_world)[:-1])

    def lookup_object(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) object-frame points -> (...) float32 occupancy (nearest voxel, 0 outside)."""
        shape_in = np.shape(points)[:-1]
        p = np.asarray(points, np.float64).reshape(-1, 3)
        ijk = np.round((p - self.origin) / self.voxel).astype(np.int64)
        shape = np.array(self.occupancy.shape)
        ok = np.all((ijk >= 0) & (ijk < shape), axis=-1)
        ijk = np.clip(ijk, 0, shape - 1)
        occ = self.occupancy[ijk[:, 0], ijk[:, 1], ijk[:, 2]] & ok
        return occ.astype(np.float32).reshape(shape_in)


@functools.lru_cache(maxsize=8)
def ego_cell_centres(cfg: FeatureConfig) -> np.ndarray:
    """(rings·sectors·layers, 3) cylinder cell centres in the root frame (ring slowest, then
    sector, then layer). Sector s is centred at the angle (s + 0.5)·2π/sectors from +z (forward)
    towards +x (the body's left); layers run up from the floor. Cached per configuration (the
    runtime asks every frame) and read-only."""
    r = (np.arange(cfg.ego_rings) + 0.5) * cfg.ego_radius / cfg.ego_rings
    a = (np.arange(cfg.ego_sectors) + 0.5) * 2 * np.pi / cfg.ego_sectors
    h = (np.arange(cfg.ego_layers) + 0.5) * cfg.ego_height / cfg.ego_layers
    rr, aa, hh = np.meshgrid(r, a, h, indexing="ij")
    cells = np.stack([rr * np.sin(aa), hh, rr * np.cos(aa)], -1).reshape(-1, 3)
    cells.flags.writeable = False
    return cells


def ego_features(grid: OccupancyGrid, root: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """E: (..., cells) chair occupancy (0/1) at the ego-cylinder cell centres around each
    root (..., 4, 4)."""
    cells = ego_cell_centres(cfg)
    object_from_root = invert_transform(grid.world_from_object) @ root
    points = (cells @ np.swapaxes(object_from_root[..., :3, :3], -1, -2)
              + object_from_root[..., None, :3, 3])
    return grid.lookup_object(points)


# ----------------------------------------------------------------------------- hands, phases


def hand_targets(active: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One hand's target contact per frame: the mean contact point of the current or next run.

    Args:
        active: (T,) bool contact flags; points: (T, 3) world contact points (NaN inactive).
    Returns:
        targets (T, 3) world (NaN where no run follows) and mask (T,) bool.
    """
    starts, ends = contact_runs(active)
    means = np.array([np.nanmean(points[s:e + 1], axis=0) for s, e in zip(starts, ends,
                                                                          strict=True)])
    run = np.searchsorted(ends, np.arange(len(active)), side="left")
    mask = run < len(starts)
    targets = np.full((len(active), 3), np.nan)
    if len(starts):
        targets[mask] = means[run[mask]]
    return targets, mask & np.all(np.isfinite(targets), axis=-1)


def sit_contact_flags(active: np.ndarray, sitting: np.ndarray, window: int | None
                      ) -> np.ndarray:
    """(T,) one hand's contact flags without the runs that push off to stand up.

    Args:
        active: (T,) bool hand contact flags; sitting: (T,) bool pelvis contact flags;
        window: frames (:attr:`FeatureConfig.push_off_window`); None keeps every run.
    Returns:
        ``active`` without each run that starts within ``window`` frames of a stand-up (the
        end of a sit before the last frame), or standing after one with no sit following.
        Pelvis runs less than ``window`` apart are one sit (a landing's bounce). Half the
        simulated sits end standing, nearly all pushing off a hand first: as a control target
        that run made a seated character's control read "stand up now" (README, *Results so
        far*, session 49).
    """
    out = np.asarray(active, bool).copy()
    if window is None:
        return out
    starts, ends = contact_runs(sitting)
    keep = np.ones(len(starts), bool)
    keep[1:] = starts[1:] - ends[:-1] > window  # a sit's first run
    sit_starts = starts[keep]
    sit_ends = np.append(ends[np.flatnonzero(keep)[1:] - 1], ends[-1:])
    stand_ups = sit_ends[sit_ends < len(out) - 1]
    for s, e in zip(*contact_runs(out), strict=True):
        around = np.any(np.abs(s - stand_ups) <= window)
        seated = np.any((sit_starts <= s) & (s <= sit_ends))
        after = not seated and np.any(s > stand_ups) and not np.any(sit_starts > s)
        if around or after:
            out[s:e + 1] = False
    return out


def local_phase(active: np.ndarray, hand_speed: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """(T,) local phase of one hand in [0, 1]: 0 away from contacts, rising linearly over the
    reach (from where the hand speed first exceeds ``cfg.hand_approach_speed`` within
    ``cfg.hand_approach`` s before the onset, not before the previous release) to 1 at the
    contact onset, 1 during the contact, falling to 0 over ``cfg.hand_release`` s after it."""
    starts, ends = contact_runs(active)
    t = np.arange(len(active), dtype=np.float64)
    phase = np.zeros(len(active))
    window, release = _frames(cfg.hand_approach, cfg.fps), _frames(cfg.hand_release, cfg.fps)
    prev_end = -1
    for s, e in zip(starts, ends, strict=True):
        lo = max(s - window, prev_end + 1, 0)
        moving = np.flatnonzero(hand_speed[lo:s] > cfg.hand_approach_speed)
        a = float(lo + moving[0]) if len(moving) else s - 1e-3
        ramp = np.interp(t, [a, s, e, e + release], [0.0, 1.0, 1.0, 0.0], left=0.0, right=0.0)
        phase = np.maximum(phase, ramp)
        prev_end = e
    return phase


def left_foot_strikes(ankle_height: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """Frames of left-foot ground strikes: local minima of the (lightly smoothed) left ankle
    height at least ``cfg.step_min_interval`` s apart."""
    h = uniform_filter1d(np.asarray(ankle_height, np.float64), 3, mode="nearest")
    peaks, _ = find_peaks(-h, distance=_frames(cfg.step_min_interval, cfg.fps),
                          prominence=0.01)
    return peaks


def global_phase(strikes: np.ndarray, sitting: np.ndarray, cfg: FeatureConfig,
                 pelvis_height: np.ndarray | None = None) -> np.ndarray:
    """(T,) global phase in [0, 1].

    Walking/idle: the walk cycle, 0 -> 1 between consecutive left-foot ``strikes`` (frames),
    extrapolated with the neighbouring cycle's length (``cfg.walk_cycle`` with < 2 strikes).
    Sitting: 0 at the start of the sit transition rising linearly to 1 at the sit onset (first
    frame of a pelvis contact run), 1 while seated. The transition starts ``cfg.sit_transition``
    s before the onset (not before the previous sit ended), or later: at the last frame in that
    window where the pelvis is still within 3 cm of its highest point there (the person is
    still standing), when ``pelvis_height`` (T,) m is given.
    """
    n = len(sitting)
    t = np.arange(n, dtype=np.float64)
    strikes = np.asarray(strikes, np.float64)
    if len(strikes) >= 2:
        cycles = np.interp(t, strikes, np.arange(len(strikes), dtype=np.float64))
        first, last = strikes[1] - strikes[0], strikes[-1] - strikes[-2]
        cycles = np.where(t < strikes[0], (t - strikes[0]) / first, cycles)
        cycles = np.where(t > strikes[-1], len(strikes) - 1 + (t - strikes[-1]) / last, cycles)
    else:
        anchor = strikes[0] if len(strikes) else 0.0
        cycles = (t - anchor) / (cfg.walk_cycle * cfg.fps)
    phase = np.mod(cycles, 1.0)
    starts, ends = contact_runs(sitting)
    prev_end = -1
    for s, e in zip(starts, ends, strict=True):
        a = max(s - _frames(cfg.sit_transition, cfg.fps), prev_end + 1, 0)
        if pelvis_height is not None and a < s:
            window = np.asarray(pelvis_height[a:s])
            a += int(np.flatnonzero(window >= window.max() - 0.03)[-1])
        if a < s:
            phase[a:s] = (t[a:s] - a) / (s - a)
        phase[s:e + 1] = 1.0
        prev_end = e
    return phase


def control_near(root: np.ndarray, targets: np.ndarray, radius: float) -> np.ndarray:
    """(..., 2) bool: each hand's target (..., 2, 3) world (NaN = none) lies within ``radius``
    m of the root (..., 4, 4) origin horizontally."""
    d = targets - root[..., None, :3, 3]
    with np.errstate(invalid="ignore"):
        return np.hypot(d[..., 0], d[..., 2]) < radius


def control_line(hand: np.ndarray, target: np.ndarray, mask: np.ndarray, root: np.ndarray,
                 samples: int = 7, end_height: float = 0.0) -> np.ndarray:
    """ControlNet input h̃: (..., 2, samples, 3) points spaced uniformly on the straight line
    from each hand (sample 0) to ``end_height`` m above its target (last sample), relative to
    the target, rotated into the root frame; zeros where ``mask`` is False.

    Args:
        hand: (..., 2, 3) world hand positions; target: (..., 2, 3) world contacts;
        mask: (..., 2) bool; root: (..., 4, 4); end_height: metres along world up
            (:attr:`FeatureConfig.control_line_end`).
    """
    w = 1.0 - np.linspace(0.0, 1.0, samples)
    end = np.where(mask[..., None], end_height * UP, 0.0)
    offset = vectors_to_root(np.where(mask[..., None], hand - target, 0.0) - end, root)
    end_root = vectors_to_root(end, root)
    return offset[..., :, None, :] * w[:, None] + end_root[..., :, None, :]


def control_signal(hand_positions: np.ndarray, phases: np.ndarray, target: np.ndarray,
                   mask: np.ndarray, root: np.ndarray, offsets: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """C⁺ of each frame: the hands' future positions at ``t + offsets`` relative to their
    target contact, rotated into the root frame of t, and their local phases there.

    Args:
        hand_positions: (T, 2, 3) world; phases: (T, 2) local phases; target: (T, 2, 3) world
        contacts; mask: (T, 2); root: (T, 4, 4); offsets: (K,) frame offsets (clamped).
    Returns:
        positions (T, 2, K, 3) (zeros where mask is False), phases (T, 2, K).
    """
    idx = sample_indices(len(root), offsets)
    future = hand_positions[idx].transpose(0, 2, 1, 3)  # (T, 2, K, 3)
    rel = np.where(mask[..., None, None], future - target[:, :, None], 0.0)
    pos = np.einsum("tji,thkj->thki", root[:, :3, :3], rel)
    return pos, phases[idx].transpose(0, 2, 1)


def control_in_root(positions: np.ndarray, target_root: np.ndarray, mask: np.ndarray
                    ) -> np.ndarray:
    """PoseNet's control input: C⁺ positions (..., 2, K, 3), relative to each hand's target and
    rotated into the root frame (:func:`control_signal`), moved back to the root's origin by the
    targets' root-frame positions ``target_root`` (..., 2, 3): where the hands will be, in the
    frame the pose is predicted in. Zeros where ``mask`` (..., 2) is False.

    Relative to the contact alone, C⁺ says how far the hand will be from a contact PoseNet is
    never shown (only ControlNet reads the contact); in the root frame it says where the hand
    goes in the frame PoseNet predicts the pose in. Measured on the same data and training
    (``couch-eval``, 6 chairs x 8 trials): AP@5 48.6 % with C⁺ relative, 58.6 % in the root frame.
    """
    return np.where(mask[..., None, None], positions + target_root[..., None, :], 0.0)


def phase_update(phase: np.ndarray, next_phase: np.ndarray) -> np.ndarray:
    """Change from ``phase`` to ``next_phase`` (both in [0, 1]) wrapped to [-0.5, 0.5)."""
    return np.mod(np.asarray(next_phase) - np.asarray(phase) + 0.5, 1.0) - 0.5


def advance_phase(phase: np.ndarray, update: np.ndarray, seated: np.ndarray) -> np.ndarray:
    """Inverse of :func:`phase_update` at runtime: ``phase + update`` wrapped into [0, 1), and 1
    while ``seated`` (bool, same shape; :func:`global_phase` is 1 throughout a pelvis contact)."""
    return np.where(seated, 1.0, np.mod(np.asarray(phase) + np.asarray(update), 1.0))


def tidy_future_trajectory(future: Array) -> Array:
    """PoseNet's predicted future trajectory (..., K, 12) (position 3, direction 6D, action
    labels 3; numpy or torch) as the runtime feeds it back: on the floor (y = 0), unit 6D
    directions, action labels clipped at 0 and summing to 1. Returns a new array; closed-loop
    training (:func:`couch.synthesis.train.pose_feedback`) applies the same rule."""
    out = future * 1.0  # a copy of either kind
    out[..., 1] = 0.0  # roots live on the floor
    out[..., 3:9] = matrix_to_6d(sixd_to_matrix(out[..., 3:9]))
    act = out[..., 9:].clip(min=0.0)
    out[..., 9:] = act / act.sum(-1)[..., None].clip(min=1e-6)
    return out


def root_update(root: np.ndarray, next_root: np.ndarray) -> np.ndarray:
    """(..., 3): (dx, dz) of ``next_root`` in the frame of ``root`` (m) and the yaw change dyaw
    (radians, positive turns forward +z towards +x) — what the runtime integrates."""
    rel = invert_transform(root) @ next_root
    return np.stack([rel[..., 0, 3], rel[..., 2, 3], np.arctan2(rel[..., 0, 2], rel[..., 2, 2])],
                    axis=-1)


def integrate_root(root: np.ndarray, update: np.ndarray) -> np.ndarray:
    """Inverse of :func:`root_update`: apply (..., 3) updates to (..., 4, 4) roots."""
    c, s = np.cos(update[..., 2]), np.sin(update[..., 2])
    # A turn about +Y and a step on the floor, entries set directly (the runtime's per-frame
    # call on one character is mostly per-call cost)
    step = np.zeros((*c.shape, 4, 4))
    step[..., 0, 0] = step[..., 2, 2] = c
    step[..., 0, 2], step[..., 2, 0] = s, -s
    step[..., 1, 1] = step[..., 3, 3] = 1.0
    step[..., 0, 3], step[..., 2, 3] = update[..., 0], update[..., 1]
    return root @ step


# ----------------------------------------------------------------------------- sequences


@dataclasses.dataclass
class SequenceFeatures:
    """Every per-frame feature of one sequence (T frames at ``fps``), float32 unless noted.

    Inputs of frame t (root frame = the root of t):
        root (T,4,4) float64 world_from_root; actions (T,3) soft (idle, walk, sit);
        action_labels (T,) int; joint_positions (T,22,3); joint_rotations (T,22,6);
        joint_velocities (T,22,3) m/s; trajectory (T,13,12) and goals (T,13,12) (see
        :func:`trajectory_features`, :func:`goal_features`); interaction (T,2048);
        ego (T,1408); global_phase (T,); hand_phases (T,2,13) local phases at the trajectory
        samples; hand_targets (T,2,3) world contact targets (NaN where none) and hand_mask (T,2);
        control_line (T,2,7,3) ControlNet input h̃; control_positions (T,2,7,3) and
        control_phases (T,2,7): the control signal C⁺ of frame t (:func:`control_signal`);
        control_root_positions (T,2,7,3): C⁺ as PoseNet reads it (:func:`control_in_root`).
    Targets of the transition t -> t+1 (row t; the last row repeats the last frame):
        future_joint_positions (T,22,3): joints of t+1 in the root frame 1 s after t+1;
        goal_relative_root (T,9): root of t+1 in the frame of frame t's goal root (position,
            6D direction): NSM's inverse (goal-centric) trajectory, which the runtime blends
            with the ego-centric update near the goal. The paper words it "relative to the
            chair"; the goal is the seated root on that chair, and being relative to it keeps
            the target well defined on chairs whose canonical front is ambiguous (stools);
        next_contacts (T,5) contact_active of t+1; root_update (T,3) (dx, dz, dyaw) from the
        root of t to the root of t+1. The remaining targets (next J, future T and G samples,
        next global phase, next C⁺) are the inputs of t+1, built by :meth:`as_groups`.
    ContactNet: contact_condition (2048,) chair-centred I; hand_contacts_chair (T,2,3) target
        contacts relative to the chair centre in the chair frame (zeros where ~hand_mask).
    NSM+Control baseline: contact_inputs (T,8): the two hand targets relative to the root of t
        (2x3, m, zeros where ~hand_mask) then hand_mask as 0/1 (2,) — the raw-contact control
        input that replaces C⁺ (optional so that hand-built instances need not give it).
    """

    fps: float
    root: np.ndarray
    actions: np.ndarray
    action_labels: np.ndarray
    joint_positions: np.ndarray
    joint_rotations: np.ndarray
    joint_velocities: np.ndarray
    trajectory: np.ndarray
    goals: np.ndarray
    interaction: np.ndarray
    ego: np.ndarray
    global_phase: np.ndarray
    hand_phases: np.ndarray
    hand_targets: np.ndarray
    hand_mask: np.ndarray
    control_line: np.ndarray
    control_positions: np.ndarray
    control_phases: np.ndarray
    control_root_positions: np.ndarray
    future_joint_positions: np.ndarray
    goal_relative_root: np.ndarray
    next_contacts: np.ndarray
    root_update: np.ndarray
    contact_condition: np.ndarray
    hand_contacts_chair: np.ndarray
    future_samples: tuple[int, ...] = (6, 7, 8, 9, 10, 11, 12)
    contact_inputs: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return len(self.root)

    def as_groups(self, drop_last: bool = True) -> dict[str, np.ndarray]:
        """Named (N, dim) float32 arrays, N = T - 1 with ``drop_last`` (each row one t -> t+1
        pair) else T. See :data:`LAYOUT` for which network reads/predicts which group."""
        n = self.num_frames
        nxt = np.minimum(np.arange(n) + 1, n - 1)
        fut = list(self.future_samples)
        flat = {
            # ControlNet
            "control_line": self.control_line,
            "hand_phases": self.hand_phases,
            "next_control_positions": self.control_positions[nxt],
            "next_control_phases": self.control_phases[nxt],
            # PoseNet inputs
            "control_root_positions": self.control_root_positions,
            "control_phases": self.control_phases,
            "joint_positions": self.joint_positions,
            "joint_rotations": self.joint_rotations,
            "joint_velocities": self.joint_velocities,
            "trajectory": self.trajectory,
            "goals": self.goals,
            "interaction": self.interaction,
            "ego": self.ego,
            "global_phase": self.global_phase,
            # PoseNet targets
            "next_joint_positions": self.joint_positions[nxt],
            "next_joint_rotations": self.joint_rotations[nxt],
            "next_joint_velocities": self.joint_velocities[nxt],
            "future_trajectory": self.trajectory[nxt][:, fut],
            "future_goals": self.goals[nxt][:, fut],
            # NSM-style: the phase's change, wrapped to [-0.5, 0.5), not its next value: a
            # regression onto a cyclic value that wraps 1 -> 0 every step cycle averages the two
            # ends (~0.5) near the wrap, and the runtime then cannot tell walking from sitting.
            "global_phase_update": phase_update(self.global_phase, self.global_phase[nxt]),
            "future_joint_positions": self.future_joint_positions,
            "goal_relative_root": self.goal_relative_root,
            "next_contacts": self.next_contacts,
            "root_update": self.root_update,
            # ContactNet
            "contact_condition": np.broadcast_to(self.contact_condition,
                                                 (n, self.contact_condition.size)),
            "hand_contacts": self.hand_contacts_chair,
            "hand_mask": self.hand_mask,
        }
        if self.contact_inputs is not None:
            flat["contact_inputs"] = self.contact_inputs
        rows = n - 1 if drop_last else n
        return {k: np.ascontiguousarray(np.asarray(v, np.float32).reshape(n, -1)[:rows])
                for k, v in flat.items()}


def layout(cfg: FeatureConfig | None = None) -> dict[str, dict[str, dict[str, int]]]:
    """Which groups each network reads and predicts, with their widths:
    ``{network: {"inputs": {group: dim}, "targets": {group: dim}}}``."""
    cfg = cfg or FeatureConfig()
    j, k, c = cfg.num_joints, cfg.trajectory_samples, cfg.control_samples
    kf = int((cfg.trajectory_offsets >= 0).sum())
    out = {
        "controlnet": {
            "inputs": {"control_line": 2 * c * 3, "hand_phases": 2 * k},
            "targets": {"next_control_positions": 2 * c * 3, "next_control_phases": 2 * c},
        },
        "posenet": {
            "inputs": {"control_root_positions": 2 * c * 3, "control_phases": 2 * c,
                       "joint_positions": j * 3, "joint_rotations": j * 6,
                       "joint_velocities": j * 3, "trajectory": k * 12, "goals": k * 12,
                       "interaction": cfg.interaction_dim, "ego": cfg.ego_cells,
                       "global_phase": 1},
            "targets": {"next_joint_positions": j * 3, "next_joint_rotations": j * 6,
                        "next_joint_velocities": j * 3, "future_trajectory": kf * 12,
                        "future_goals": kf * 12, "global_phase_update": 1,
                        "future_joint_positions": j * 3, "goal_relative_root": 9,
                        "next_contacts": 5, "root_update": 3},
        },
        "contactnet": {
            "inputs": {"contact_condition": cfg.interaction_dim},
            "targets": {"hand_contacts": 6, "hand_mask": 2},
        },
    }
    # NSM+Control baseline (paper Sec. 5): the PoseNet with the raw hand contacts as its control
    # input instead of the ControlNet's C⁺; same targets, same order otherwise. ``hand_mask``
    # (which hands have a contact) is its gating input beside the global phase.
    pose_inputs = out["posenet"]["inputs"]
    baseline_inputs: dict[str, int] = {"contact_inputs": 8, "hand_mask": 2}
    baseline_inputs.update({k: v for k, v in pose_inputs.items()
                            if k not in ("control_root_positions", "control_phases")})
    out["baseline"] = {"inputs": baseline_inputs, "targets": dict(out["posenet"]["targets"])}
    # NSM (paper Table 2's first row): the PoseNet without any hand control input, gated on
    # the global phase alone; where the hands go is the motion's own doing.
    out["nsm"] = {"inputs": {k: v for k, v in pose_inputs.items()
                             if k not in ("control_root_positions", "control_phases")},
                  "targets": dict(out["posenet"]["targets"])}
    return out


LAYOUT = layout()


def sequence_features(session: ProcessedSession, config: FeatureConfig | None = None,
                      grid: OccupancyGrid | None = None,
                      voxels: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                      ) -> SequenceFeatures:
    """All features of one processed session (resampled to ``config.fps`` first if needed).

    ``grid`` (:meth:`OccupancyGrid.from_mesh`) and ``voxels`` (:func:`voxel_grid`, object
    frame) may be passed to reuse one chair's precomputation across sequences; they are built
    from the session's mesh otherwise.
    """
    cfg = config or FeatureConfig()
    if abs(float(session.fps) - cfg.fps) > 1e-6:
        session = resample(session, cfg.fps)
    fps = cfg.fps
    joints = np.asarray(session.joints, np.float64)
    n = len(joints)
    names = list(session.contact_names)
    active = np.asarray(session.contact_active, bool)
    object_pose = np.asarray(session.object_pose, np.float64)

    root = root_transforms(joints)
    rots = global_rotations(session.global_orient, session.body_pose)
    positions, rotations, vel = pose_features(joints, rots, root, fps, cfg.num_joints)

    sitting = active[:, names.index("pelvis")]
    speed = root_speed(root, fps, cfg.speed_smoothing)
    labels, soft = action_labels(sitting, speed, cfg)
    traj = trajectory_features(root, soft, cfg.trajectory_offsets)
    goal_frame, goal_action = goal_frames(sitting, labels)
    goals = goal_features(root, root[goal_frame], goal_action, cfg.trajectory_offsets)

    if voxels is None:
        voxels = voxel_grid(session.object_vertices, session.object_faces,
                            cfg.interaction_resolution, cfg.interaction_subsamples)
    occupancy, centres_object, _ = voxels
    interaction = interaction_features(occupancy, apply_transform(object_pose, centres_object),
                                       root)
    if grid is None:
        grid = OccupancyGrid.from_mesh(session.object_vertices, session.object_faces,
                                       object_pose, cfg.occupancy_voxel)
    else:
        grid = dataclasses.replace(grid, world_from_object=object_pose)
    ego = ego_features(grid, root, cfg)

    hands = joints[:, list(cfg.hand_joints)]  # (T, 2, 3)
    hand_speed = np.linalg.norm(velocities(hands, fps), axis=-1)
    targets, mask, phases = [], [], []
    window = None if cfg.push_off_window is None else _frames(cfg.push_off_window, fps)
    for h, name in enumerate(HANDS):
        i = names.index(name)
        flags = sit_contact_flags(active[:, i], sitting, window)
        tgt, m = hand_targets(flags, np.asarray(session.contact_points[:, i], np.float64))
        targets.append(tgt)
        mask.append(m)
        phases.append(local_phase(flags, hand_speed[:, h], cfg))
    targets, mask, phases = np.stack(targets, 1), np.stack(mask, 1), np.stack(phases, 1)
    mask &= control_near(root, targets, cfg.control_radius)
    hand_phases = phases[sample_indices(n, cfg.trajectory_offsets)].transpose(0, 2, 1)
    safe_targets = np.where(mask[..., None], targets, 0.0)
    line = control_line(hands, safe_targets, mask, root, cfg.control_samples,
                        cfg.control_line_end)
    ctrl_pos, ctrl_phase = control_signal(hands, phases, safe_targets, mask, root,
                                          cfg.control_offsets)

    strikes = left_foot_strikes(joints[:, JOINT_INDEX["left_ankle"], 1], cfg)
    strikes = strikes[~sitting[strikes]]
    gphase = global_phase(strikes, sitting, cfg, joints[:, JOINT_INDEX["pelvis"], 1])

    nxt = np.minimum(np.arange(n) + 1, n - 1)
    ahead = np.minimum(nxt + _frames(1.0, fps), n - 1)
    future_joints = to_root(joints[nxt, :cfg.num_joints], root[ahead])
    chair_from_world = invert_transform(object_pose)
    goal_rel = relative_root(root[goal_frame], root[nxt])
    update = root_update(root, root[nxt])
    chair_centre = centres_object.mean(0)
    contacts_chair = np.where(mask[..., None],
                              apply_transform(chair_from_world, safe_targets) - chair_centre, 0.0)
    targets_root = np.where(mask[..., None], to_root(safe_targets, root), 0.0)  # (T, 2, 3)
    contact_inputs = np.concatenate([targets_root.reshape(n, 6), mask.astype(np.float64)], 1)

    f32 = np.float32
    return SequenceFeatures(
        fps=fps, root=root, actions=soft.astype(f32), action_labels=labels.astype(np.int64),
        joint_positions=positions.astype(f32), joint_rotations=rotations.astype(f32),
        joint_velocities=vel.astype(f32), trajectory=traj.astype(f32), goals=goals.astype(f32),
        interaction=interaction.astype(f32), ego=ego.astype(f32), global_phase=gphase.astype(f32),
        hand_phases=hand_phases.astype(f32), hand_targets=targets.astype(f32), hand_mask=mask,
        control_line=line.astype(f32), control_positions=ctrl_pos.astype(f32),
        control_phases=ctrl_phase.astype(f32),
        control_root_positions=control_in_root(ctrl_pos, targets_root, mask).astype(f32),
        future_joint_positions=future_joints.astype(f32),
        goal_relative_root=goal_rel.astype(f32), next_contacts=active[nxt],
        root_update=update.astype(f32),
        contact_condition=contact_net_condition(occupancy, centres_object).astype(f32),
        hand_contacts_chair=contacts_chair.astype(f32),
        future_samples=tuple(int(i) for i in cfg.future_samples),
        contact_inputs=contact_inputs.astype(f32))


# ----------------------------------------------------------------------------- normalisation


@dataclasses.dataclass
class FeatureStats:
    """Per-group mean and standard deviation (each (dim,) float32, std floored at ``min_std``)."""

    mean: dict[str, np.ndarray]
    std: dict[str, np.ndarray]

    @classmethod
    def fit(cls, sequences: Sequence[SequenceFeatures], min_std: float = 1e-2,
            groups: Sequence[str] | None = None) -> FeatureStats:
        """Statistics over every (t -> t+1) row of ``sequences`` (all groups by default)."""
        if not sequences:
            raise ValueError("FeatureStats.fit needs at least one sequence")
        per_seq = [s.as_groups() for s in sequences]
        names = list(groups or per_seq[0])
        mean, std = {}, {}
        for name in names:
            x = np.concatenate([g[name] for g in per_seq], axis=0).astype(np.float64)
            mean[name] = x.mean(0).astype(np.float32)
            std[name] = np.maximum(x.std(0), min_std).astype(np.float32)
        return cls(mean, std)

    def normalize(self, name: str, x: np.ndarray) -> np.ndarray:
        return (x - self.mean[name]) / self.std[name]

    def denormalize(self, name: str, x: np.ndarray) -> np.ndarray:
        return x * self.std[name] + self.mean[name]

    def save(self, path: str | os.PathLike) -> None:
        """Write an ``.npz`` (keys ``<group>.mean`` / ``<group>.std``) atomically."""
        arrays = {f"{k}.mean": v for k, v in self.mean.items()}
        arrays.update({f"{k}.std": v for k, v in self.std.items()})
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike) -> FeatureStats:
        """Read a file written by :meth:`save` (``allow_pickle=False``)."""
        path = Path(path)
        with np.load(path, allow_pickle=False) as data:
            keys = list(data.keys())
            names = [k[:-5] for k in keys if k.endswith(".mean")]
            missing = [n for n in names if f"{n}.std" not in keys]
            if missing:
                raise ValueError(f"{path}: groups {missing} have a mean but no std")
            return cls({n: data[f"{n}.mean"] for n in names},
                       {n: data[f"{n}.std"] for n in names})
