"""Analytic limb IK and forward kinematics for the simulator's procedural motion (numpy).

Everything is batched over frames (leading T). Rotations are (T,3,3) matrices; positions metres in
the world frame (Y up). A limb is three SMPL joints (hip-knee-ankle or shoulder-elbow-wrist); its
rest directions come from the shaped rest skeleton, so the solved pose reaches the targets exactly
with the body model's own bone lengths.
"""

from __future__ import annotations

import numpy as np

from couch.body import PARENTS, Skeleton  # noqa: F401  (Skeleton re-exported for the motion code)
from couch.geometry import normalize, two_bone_ik  # both also used by the motion code
from couch.rotations import matrix_to_quat, quat_to_matrix


def frame_from(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """(…,3,3) orthonormal frames: column 0 along ``primary``, column 1 = ``secondary`` made
    perpendicular to it, column 2 their cross product."""
    x = normalize(primary)
    y = normalize(secondary - (secondary * x).sum(-1, keepdims=True) * x)
    return np.stack([x, y, np.cross(x, y)], axis=-1)


def align(rest_primary: np.ndarray, rest_secondary: np.ndarray, primary: np.ndarray,
          secondary: np.ndarray) -> np.ndarray:
    """Rotation taking the rest frame (primary, secondary) onto the desired one: (…,3,3)."""
    return frame_from(primary, secondary) @ np.swapaxes(
        frame_from(rest_primary, rest_secondary), -1, -2)


def yaw_matrix(heading: np.ndarray) -> np.ndarray:
    """(T,3,3) rotations about +Y by ``heading`` radians (heading 0 faces +Z)."""
    c, s = np.cos(heading), np.sin(heading)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1),
                     np.stack([-s, z, c], -1)], -2)


def axis_rotation(axis: str, angle: np.ndarray) -> np.ndarray:
    """(T,3,3) rotations about a principal axis ('x', 'y' or 'z') by ``angle`` radians."""
    c, s = np.cos(angle), np.sin(angle)
    z, o = np.zeros_like(c), np.ones_like(c)
    if axis == "x":
        rows = [[o, z, z], [z, c, -s], [z, s, c]]
    elif axis == "y":
        rows = [[c, z, s], [z, o, z], [-s, z, c]]
    else:
        rows = [[c, -s, z], [s, c, z], [z, z, o]]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def limb_rotations(rest_upper: np.ndarray, rest_lower: np.ndarray, rest_pole: np.ndarray,
                   d_upper: np.ndarray, d_lower: np.ndarray, hinge: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Global rotations (T,3,3) of a two-bone limb's bones from :func:`two_bone_ik`'s output.

    Each bone's rest direction goes onto its solved direction, and the rest hinge axis (rest
    bone × ``rest_pole``, the direction the middle joint bends towards in the rest pose) onto
    the solved ``hinge``. The hinge is perpendicular to both bones whatever the pose, so the
    twist about each bone is continuous from frame to frame. (Aligning the pole itself, made
    perpendicular to the bone, flips the bone 180° about its axis whenever the pole passes
    the bone's direction: a seated thigh points along a forward pole, an arm reaching down and
    back can point along its back-and-down pole.)
    """
    out = []
    for rest, d in ((rest_upper, d_upper), (rest_lower, d_lower)):
        rest_hinge = normalize(np.cross(rest, rest_pole))
        out.append(align(rest, np.cross(rest_hinge, rest), d, np.cross(hinge, d)))
    return out[0], out[1]


def local_from_global(global_rot: dict[int, np.ndarray], num_frames: int) -> np.ndarray:
    """SMPL local rotations (T,24,3,3) from global ones (missing joints inherit the parent's
    global rotation, i.e. get an identity local rotation)."""
    eye = np.broadcast_to(np.eye(3), (num_frames, 3, 3))
    full: dict[int, np.ndarray] = {}
    local = np.empty((num_frames, 24, 3, 3))
    for j in range(24):
        p = PARENTS[j]
        parent_g = eye if p < 0 else full[p]
        full[j] = global_rot.get(j, parent_g)
        local[:, j] = np.swapaxes(parent_g, -1, -2) @ full[j]
    return local


def transfer_twist(parent_local: np.ndarray, child_local: np.ndarray, axis: np.ndarray,
                   max_angle: float = np.pi) -> tuple[np.ndarray, np.ndarray]:
    """Move the child's twist about ``axis`` (the bone between them, rest frame) into the parent.

    The child's global rotation and the child joint's position are unchanged (the parent turns
    about the bone it shares with the child). Used for forearm pronation: IK leaves all of it in
    the wrist, anatomy puts it along the forearm. Returns new (parent_local, child_local).
    """
    axis = normalize(np.asarray(axis, dtype=np.float64))
    q = matrix_to_quat(child_local)
    proj = (q[..., 1:] @ axis)[..., None] * axis
    twist = np.concatenate([q[..., :1], proj], axis=-1)
    norm = np.linalg.norm(twist, axis=-1, keepdims=True)
    twist = np.where(norm > 1e-9, twist / np.maximum(norm, 1e-12), [1.0, 0.0, 0.0, 0.0])
    # at most ``max_angle`` of it (the parent's twist range); the rest stays in the child
    angle = 2 * np.arctan2((twist[..., 1:] @ axis), twist[..., 0])
    angle = (angle + np.pi) % (2 * np.pi) - np.pi
    angle = np.clip(angle, -max_angle, max_angle)
    twist = np.concatenate([np.cos(angle / 2)[..., None], np.sin(angle / 2)[..., None] * axis],
                           axis=-1)
    t = quat_to_matrix(twist)
    return parent_local @ t, np.swapaxes(t, -1, -2) @ child_local


def steady_pole(root: np.ndarray, target: np.ndarray, pole: np.ndarray, len_upper: float,
                len_lower: float, fps: float, max_speed: float) -> np.ndarray:
    """(T,3) poles for :func:`two_bone_ik` under which the middle joint does not swing about
    the root→target line faster than ``max_speed`` (m/s).

    A pole fixed to the body is ill-defined where the root→target line passes along it (an arm
    reaching down and back past its back-and-down pole): the bend direction, the pole made
    perpendicular to that line, then spins round it within a frame or two and the elbow sweeps
    tens of centimetres between frames. Here the bend direction's angle about the line
    (measured in a frame carried along the line from frame to frame) may change by at most
    ``max_speed`` over the middle joint's distance from the line per frame; the frames where
    the given pole stays within that are returned as given, so their solve is unchanged to the
    bit, and the others get the limited bend direction itself as their pole.

    Args:
        root, target: (T,3) m, the chain's first joint and its target, consecutive frames.
        pole: (T,3) or (3,), the direction the middle joint bends towards.
        len_upper, len_lower: m, the bone lengths.
        fps: frames per second of the T frames.
        max_speed: m/s, the fastest the middle joint may swing about the line.
    """
    root, target = np.asarray(root, np.float64), np.asarray(target, np.float64)
    pole = np.array(np.broadcast_to(pole, root.shape), np.float64)
    middle = two_bone_ik(root, target, pole, len_upper, len_lower)[0]
    e = normalize(target - root)
    radial = (middle - root) - ((middle - root) * e).sum(-1, keepdims=True) * e
    radius = np.linalg.norm(radial, axis=-1)
    bend = normalize(radial)
    # A reference direction carried along the line with no twist of its own (the recurrence
    # is inherently sequential), and the bend direction's angle about the line from it.
    ref = np.empty_like(e)
    ref[0] = bend[0]
    for t in range(1, len(e)):
        r = ref[t - 1] - (ref[t - 1] @ e[t]) * e[t]
        ref[t] = normalize(r) if np.linalg.norm(r) > 1e-6 else bend[t]
    side = np.cross(e, ref)
    angle = np.unwrap(np.arctan2((side * bend).sum(-1), (ref * bend).sum(-1)))
    step = max_speed / (fps * np.maximum(radius, 1e-3))
    limited = angle.copy()
    for t in range(1, len(angle)):
        d = angle[t] - limited[t - 1]
        if abs(d) > step[t]:
            limited[t] = limited[t - 1] + np.copysign(step[t], d)
    changed = limited != angle
    pole[changed] = (np.cos(limited)[:, None] * ref + np.sin(limited)[:, None] * side)[changed]
    return pole
