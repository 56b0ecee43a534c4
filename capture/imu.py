"""Xsens MVN export → SMPL joint rotations and positions, in couch's world axes.

:func:`mvnx_to_smpl` turns an :class:`~couch.capture.mvnx.MvnxRecording` (MVN's global frame:
Z up, X forward at calibration, Y left) into an :class:`ImuMotion` in couch's axes (metres,
**Y up**, X = the body's left at rest, Z forward), vectorised over frames.

Mapping (formats.md, :data:`couch.capture.mvnx.MVN_TO_SMPL`): the global orientation of each SMPL
joint is the orientation of its MVN segment (pelvis ← Pelvis, spine1 ← L5, spine2 ← T12 or L3,
spine3 ← T8, …, wrists ← Hand, and the SMPL hand joints also take the Hand segment, so their local
rotation is the identity); local rotations are ``R_parentᵀ · R_child`` along :data:`PARENTS`.
Both MVN's identity pose and SMPL's rest pose are the T-pose with identity rotations, and the
change of axes P is a proper rotation, so ``R_couch = P R_mvn Pᵀ`` is the quaternion permutation
of :func:`~couch.capture.mvnx.mvn_to_couch_quaternions`; nothing else is needed.

Positions are the segment origins (MVN's proximal joint points), which are the SMPL joints of the
same table, except for the two SMPL hand joints: the Hand segment's origin is the wrist, so the
hand joint is put at ``wrist + R_hand · offset`` (see :func:`mvnx_to_smpl`, ``rest_joints``).

What stays the IMU's own (aligning it is the sync stage's job, not this module's):

- **heading**: MVN resets its heading at calibration to wherever the subject faced, so the
  motion is correct up to a constant rotation about our +Y (plus MVN's slow heading drift);
- **origin**: MVN's horizontal origin (usually where the pelvis stood at calibration); the floor
  is MVN's floor (y = 0 at MVN's z = 0);
- **clock**: :attr:`ImuMotion.time` is seconds on the IMU clock (MVNX ``time``), 0 at the first
  motion frame; ``unix_ms`` keeps MVN's absolute wall-clock stamps (``ms``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from couch.body import JOINT_INDEX, NUM_JOINTS, PARENTS
from couch.capture.mvnx import (
    MvnxRecording,
    missing_for_full_body,
    mvn_to_couch_positions,
    mvn_to_couch_quaternions,
    smpl_segment_indices,
)
from couch.rotations import matrix_to_axis_angle, quat_to_matrix

HAND_TO_FOREARM = 0.4
"""Default wrist → SMPL-hand-joint distance as a fraction of the measured forearm (elbow → wrist)
length. The SMPL hand joint sits near the knuckles: real SMPL has ≈0.35, the bundled couch body
≈0.43; pass ``rest_joints`` to :func:`mvnx_to_smpl` for the subject's own value."""

_PARENTS = np.asarray(PARENTS[1:], dtype=np.int64)
_HANDS = ((JOINT_INDEX["left_hand"], JOINT_INDEX["left_wrist"], JOINT_INDEX["left_elbow"]),
          (JOINT_INDEX["right_hand"], JOINT_INDEX["right_wrist"], JOINT_INDEX["right_elbow"]))


class ImuConversionError(ValueError):
    """An MVN recording cannot be converted to a full SMPL body (the message says what lacks)."""


@dataclasses.dataclass
class ImuMotion:
    """SMPL-ordered body motion measured by the suit, in couch's axes (metres, Y up, X = body's
    left at rest, Z forward) but with the IMU's own heading, horizontal origin and clock (see the
    module docstring). N frames, float64.

    time: (N,) seconds on the IMU clock (MVNX ``time`` / 1000), 0 at the first motion frame.
    unix_ms: (N,) int64 absolute Unix-epoch milliseconds of each frame (MVNX ``ms``).
    global_orient: (N, 3) axis-angle of the pelvis (world-from-pelvis).
    body_pose: (N, 69) axis-angle local rotations of SMPL joints 1..23 (parent-from-child), in
        SMPL order; the hand joints' entries are zero (they take the wrist's rotation).
    joint_rotations: (N, 24, 3, 3) global world-from-joint rotations.
    joint_positions: (N, 24, 3) joint positions, metres (MVN segment origins; hands see
        :func:`mvnx_to_smpl`). Not SMPL's ``transl``: that needs the subject's shape.
    foot_contacts: (N, 4) bool in ``foot_contact_labels`` order (MVN: LeftFoot_Heel,
        LeftFoot_Toe, RightFoot_Heel, RightFoot_Toe), or None if the file has none.
    frame_rate: Hz as declared by the file.
    configuration: MVN configuration name (e.g. ``FullBody``).
    truncation: None, or what was lost when the MVNX file was cut mid-way and read with
        ``read_mvnx(..., recover_truncated=True)`` (copied from ``MvnxRecording.truncation``:
        the file, where it ends and how many complete frames were kept); the N frames here are
        the ones before the cut.
    """

    time: np.ndarray
    unix_ms: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    joint_rotations: np.ndarray
    joint_positions: np.ndarray
    foot_contacts: np.ndarray | None
    foot_contact_labels: tuple[str, ...]
    frame_rate: float
    configuration: str
    truncation: str | None = None

    @property
    def n_frames(self) -> int:
        return int(self.time.shape[0])


def local_rotations(global_rot: np.ndarray) -> np.ndarray:
    """(..., 24, 3, 3) global rotations → (..., 24, 3, 3) local ones along the SMPL tree: the
    root keeps its global rotation, every other joint gets ``R_parentᵀ R_child``."""
    local = np.empty_like(global_rot)
    local[..., 0, :, :] = global_rot[..., 0, :, :]
    local[..., 1:, :, :] = np.swapaxes(global_rot[..., _PARENTS, :, :], -1, -2) \
        @ global_rot[..., 1:, :, :]
    return local


def _check_finite(rec: MvnxRecording) -> None:
    """Raise naming the first frame whose orientation/position is non-finite or whose
    quaternion has (near) zero norm: these would silently become NaN rotations."""
    q = np.asarray(rec.orientation, dtype=np.float64)
    p = np.asarray(rec.position, dtype=np.float64)
    bad = ~np.isfinite(q).all(axis=(1, 2)) | ~np.isfinite(p).all(axis=(1, 2)) \
        | (np.linalg.norm(q, axis=-1) < 1e-6).any(axis=1)
    if bad.any():
        f = int(np.argmax(bad))
        idx = rec.frame_index[f] if rec.frame_index is not None else f
        raise ImuConversionError(f"MVN frame #{f} (index {idx}, time {int(rec.time_ms[f])} ms): "
                                 "non-finite values or a zero quaternion in the segment "
                                 f"orientation/position ({int(bad.sum())} such frames)")


def _hand_offsets(rot: np.ndarray, pos: np.ndarray, rest_joints: np.ndarray | None
                  ) -> np.ndarray:
    """(2, 3) wrist → hand-joint vectors in the hand frame (couch axes) for (left, right).

    With ``rest_joints`` (the subject's SMPL rest skeleton, T-pose: identity global rotations)
    the offset is exact: rest[hand] − rest[wrist]. Otherwise the hand is taken to continue the
    forearm: HAND_TO_FOREARM × the elbow → wrist vector measured in the forearm's frame (median
    over frames; in MVN's T-pose the hand and forearm frames coincide)."""
    out = np.empty((2, 3))
    for side, (hand, wrist, elbow) in enumerate(_HANDS):
        if rest_joints is not None:
            out[side] = rest_joints[hand] - rest_joints[wrist]
            continue
        bone = np.einsum("nji,nj->ni", rot[:, elbow], pos[:, wrist] - pos[:, elbow])
        out[side] = HAND_TO_FOREARM * np.median(bone, axis=0)
    return out


def mvnx_to_smpl(rec: MvnxRecording, *, rest_joints: np.ndarray | None = None,
                 require_full_body: bool = True) -> ImuMotion:
    """Convert an MVN recording into SMPL joint rotations and positions in couch's axes.

    Args:
        rec: the recording as read by :func:`couch.capture.mvnx.read_mvnx` (MVN frame).
        rest_joints: optional (24, 3) SMPL rest (T-pose) joints of the subject, metres, couch
            axes; only used for the hand joints' offset from the wrist (see
            :data:`HAND_TO_FOREARM` for the default without it).
        require_full_body: raise :class:`ImuConversionError` when the recording lacks segments
            or sensors that a full-body conversion needs (e.g. an ``UpperBody`` recording, whose
            legs MVN exports without measuring them). False converts whatever segments exist,
            but missing segments still raise.

    Returns an :class:`ImuMotion` (heading, origin and clock are the IMU's own). A recording
    recovered from a cut file converts its complete frames and keeps the note in
    :attr:`ImuMotion.truncation`, so the cut stays reported downstream.
    """
    if require_full_body:
        gap = missing_for_full_body(rec)
        if not gap.complete:
            raise ImuConversionError(f"cannot convert to a full SMPL body: {gap}")
    try:
        idx = smpl_segment_indices(rec.segment_labels)
    except ValueError as err:
        raise ImuConversionError(f"cannot convert to SMPL ({rec.metadata.configuration}): "
                                 f"{err}") from None
    n = rec.n_frames
    _check_finite(rec)
    q = mvn_to_couch_quaternions(np.asarray(rec.orientation, dtype=np.float64)[:, idx])
    rot = quat_to_matrix(q).reshape(n, NUM_JOINTS, 3, 3)  # (N, 24, 3, 3), normalises q
    pos = mvn_to_couch_positions(np.asarray(rec.position, dtype=np.float64)[:, idx]).copy()
    if rest_joints is not None:
        rest_joints = np.asarray(rest_joints, dtype=np.float64)
        if rest_joints.shape != (NUM_JOINTS, 3):
            raise ValueError(f"rest_joints must be ({NUM_JOINTS}, 3), got {rest_joints.shape}")
    if n:
        offsets = _hand_offsets(rot, pos, rest_joints)
        for side, (hand, wrist, _) in enumerate(_HANDS):
            pos[:, hand] = pos[:, wrist] + rot[:, hand] @ offsets[side]
    local = local_rotations(rot)
    aa = matrix_to_axis_angle(local).reshape(n, NUM_JOINTS, 3)
    contacts = None if rec.foot_contacts is None else np.asarray(rec.foot_contacts, dtype=bool)
    return ImuMotion(
        time=np.asarray(rec.time_ms, dtype=np.float64) / 1000.0,
        unix_ms=np.asarray(rec.unix_ms, dtype=np.int64),
        global_orient=aa[:, 0].copy(),
        body_pose=aa[:, 1:].reshape(n, 3 * (NUM_JOINTS - 1)),
        joint_rotations=rot,
        joint_positions=pos,
        foot_contacts=contacts,
        foot_contact_labels=tuple(rec.foot_contact_labels),
        frame_rate=float(rec.frame_rate),
        configuration=rec.metadata.configuration,
        truncation=rec.truncation,
    )


__all__ = ["HAND_TO_FOREARM", "ImuConversionError", "ImuMotion", "local_rotations",
           "mvnx_to_smpl"]
