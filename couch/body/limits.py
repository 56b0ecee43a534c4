"""Anatomical joint limits for SMPL's 23 body joints.

Each joint's local rotation (relative to its parent, in the rest frame: X = body's left, Y up,
Z forward) is decomposed into intrinsic Euler angles about X, Y and Z and each angle must lie in
the joint's range (degrees). The decomposition order puts each joint's main hinge axis first
(the hinge, then the other rotations in the hinged frame; the middle angle spans only ±90°):
X for legs and spine, Y for elbows (which flex about Y), Z for shoulders (which lower the arm
about Z). Ranges follow clinical range-of-motion tables (e.g. AAOS "Joint Motion"), widened a
little because SMPL's joint axes are not anatomical axes; shoulders get wide ranges since their
Euler angles wrap easily. Left/right ranges are mirror images: mirroring about the sagittal
plane (x → −x) keeps the x angle and negates y and z.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from couch.body.skeleton import JOINT_NAMES

Range = tuple[float, float]

# Left-side (and central) joints: (x range, y range, z range) in degrees.
#   hips: x < 0 flexes the thigh forward; z > 0 abducts the left leg.
#   knees: x > 0 flexes. ankles: x > 0 points the toes down.
#   spine: x > 0 bends forward. left elbow: y < 0 flexes. left shoulder: z < 0 lowers the arm.
_LEFT_AND_CENTRE: dict[str, tuple[Range, Range, Range]] = {
    "left_hip": ((-140, 40), (-60, 60), (-40, 75)),
    "spine1": ((-35, 60), (-40, 40), (-35, 35)),
    "left_knee": ((-10, 160), (-40, 40), (-25, 25)),
    "spine2": ((-35, 60), (-40, 40), (-35, 35)),
    "left_ankle": ((-45, 60), (-40, 40), (-35, 35)),
    "spine3": ((-35, 60), (-40, 40), (-35, 35)),
    "left_foot": ((-50, 50), (-30, 30), (-30, 30)),
    "neck": ((-50, 60), (-70, 70), (-45, 45)),
    "left_collar": ((-40, 40), (-40, 40), (-40, 40)),
    "head": ((-50, 60), (-70, 70), (-45, 45)),
    "left_shoulder": ((-180, 180), (-135, 135), (-110, 110)),
    "left_elbow": ((-100, 100), (-165, 15), (-40, 40)),
    "left_wrist": ((-100, 100), (-90, 90), (-75, 75)),
    "left_hand": ((-45, 45), (-45, 45), (-45, 45)),
}


def _mirror(r: tuple[Range, Range, Range]) -> tuple[Range, Range, Range]:
    (x, y, z) = r
    return (x, (-y[1], -y[0]), (-z[1], -z[0]))


JOINT_LIMITS_DEG: dict[str, tuple[Range, Range, Range]] = {}
for _name in JOINT_NAMES[1:]:
    if _name.startswith("right_"):
        JOINT_LIMITS_DEG[_name] = _mirror(_LEFT_AND_CENTRE["left_" + _name[len("right_"):]])
    else:
        JOINT_LIMITS_DEG[_name] = _LEFT_AND_CENTRE[_name]

_ORDER = {"left_elbow": "YXZ", "right_elbow": "YXZ", "left_shoulder": "ZYX",
          "right_shoulder": "ZYX", "left_wrist": "XZY", "right_wrist": "XZY"}

#: Each body joint's intrinsic Euler order (scipy's upper-case convention), hinge axis first.
EULER_ORDERS: dict[str, str] = {n: _ORDER.get(n, "XYZ") for n in JOINT_NAMES[1:]}

# Near gimbal lock (the middle angle within this many degrees of ±90°) the first and third
# angles may be re-split (see _unlocked) if that moves the rotation by less than _LOCK_MOVE_DEG.
_LOCK_DEG = 5.0
_LOCK_MOVE_DEG = 1.0
_LOW = np.array([[r[0] for r in JOINT_LIMITS_DEG[n]] for n in JOINT_NAMES[1:]])
_HIGH = np.array([[r[1] for r in JOINT_LIMITS_DEG[n]] for n in JOINT_NAMES[1:]])


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def body_pose_euler_deg(body_pose: np.ndarray) -> np.ndarray:
    """(T,69) axis-angle body pose → (T,23,3) Euler angles (degrees) about X, Y, Z, each joint
    decomposed in its own order (see the module docstring).

    A rotation has two Tait-Bryan decompositions, (a, b, c) and (a ± 180, ±180 − b, c ± 180);
    the one closer to the joint's range is returned, so a legal pose never reads as a violation
    because of the representation; near gimbal lock, where the first and third angles are split
    arbitrarily, they are re-split into range where that moves the rotation by under 1°
    (:func:`_unlocked`).
    """
    aa = np.asarray(body_pose, dtype=np.float64).reshape(-1, 23, 3)
    out = np.empty_like(aa)
    for j, name in enumerate(JOINT_NAMES[1:]):
        order = _ORDER.get(name, "XYZ")
        slots = ["XYZ".index(a) for a in order]
        first = Rotation.from_rotvec(aa[:, j]).as_euler(order, degrees=True)
        second = _wrap(np.stack([first[:, 0] + 180.0, 180.0 - first[:, 1],
                                 first[:, 2] + 180.0], axis=1))
        lo, hi = _LOW[j, slots], _HIGH[j, slots]
        worse = np.maximum(np.maximum(lo - first, first - hi), 0).sum(1) > np.maximum(
            np.maximum(lo - second, second - hi), 0).sum(1)
        angles = np.where(worse[:, None], second, first)
        out[:, j, slots] = _unlocked(angles, order, lo, hi)
    return out


def _excess(angles: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.maximum(np.maximum(lo - angles, angles - hi), 0).sum(-1)


def _unlocked(angles: np.ndarray, order: str, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(T,3) decompositions in ``order`` with those near gimbal lock turned into range.

    With the middle angle at ±90° only the sum or the difference of the first and third angles
    is defined, and near it the decomposition splits it arbitrarily: a legal right elbow read
    as (y, x, z) = (21.1, 89.6, -75.7) in its YXZ order, z 36° out of range, and clamping that
    frame swung the forearm 34° and back (a hand at 7 m/s in a simulated sit). Within
    ``_LOCK_DEG`` of the lock, the first and third angles are shifted together (same or
    opposite way) by the smallest amount that brings both into range, if the rotation moves by
    under ``_LOCK_MOVE_DEG``; angles already in range are returned as they are.
    """
    near = (np.abs(np.abs(angles[:, 1]) - 90.0) < _LOCK_DEG) & (_excess(angles, lo, hi) > 0)
    if not near.any():
        return angles
    a = angles[near]
    best, best_excess = a, _excess(a, lo, hi)
    for sign in (1.0, -1.0):
        # s with lo0 <= a0 + s <= hi0 and lo2 <= a2 + sign s <= hi2
        s_lo = np.maximum(lo[0] - a[:, 0], np.minimum(sign * (lo[2] - a[:, 2]),
                                                      sign * (hi[2] - a[:, 2])))
        s_hi = np.minimum(hi[0] - a[:, 0], np.maximum(sign * (lo[2] - a[:, 2]),
                                                      sign * (hi[2] - a[:, 2])))
        shift = np.clip(0.0, s_lo, s_hi)
        cand = a + shift[:, None] * np.array([1.0, 0.0, sign])
        moved = np.degrees((Rotation.from_euler(order, a, degrees=True).inv()
                            * Rotation.from_euler(order, cand, degrees=True)).magnitude())
        cand_excess = _excess(cand, lo, hi)
        take = (s_lo <= s_hi) & (moved < _LOCK_MOVE_DEG) & (cand_excess < best_excess)
        best = np.where(take[:, None], cand, best)
        best_excess = np.where(take, cand_excess, best_excess)
    out = angles.copy()
    out[near] = best
    return out


def joint_limit_excess_deg(body_pose: np.ndarray) -> np.ndarray:
    """(T,23) degrees by which each joint's worst Euler angle leaves its range (0 inside)."""
    e = body_pose_euler_deg(body_pose)
    return np.maximum(np.maximum(_LOW - e, e - _HIGH), 0.0).max(-1)


def clamp_to_limits(body_pose: np.ndarray) -> np.ndarray:
    """(T,69) axis-angle body pose with every joint's Euler angles clipped into its range.

    Rotations already inside their ranges are returned unchanged (to float precision).
    """
    aa = np.asarray(body_pose, dtype=np.float64).reshape(-1, 23, 3)
    euler = body_pose_euler_deg(aa)
    clipped = np.clip(euler, _LOW, _HIGH)
    out = aa.copy()
    for j, name in enumerate(JOINT_NAMES[1:]):
        moved = np.any(np.abs(clipped[:, j] - euler[:, j]) > 1e-9, axis=1)
        if moved.any():
            order = _ORDER.get(name, "XYZ")
            slots = ["XYZ".index(a) for a in order]
            out[moved, j] = Rotation.from_euler(order, clipped[moved][:, j][:, slots],
                                                degrees=True).as_rotvec()
    return out.reshape(np.shape(body_pose))
