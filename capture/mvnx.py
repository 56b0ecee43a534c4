"""Xsens MVN export (``.mvnx``): the recording in memory, a writer faithful to MVN's own output and
a streaming, namespace-aware reader.

Frames. :class:`MvnxRecording` mirrors the file and stays in MVN's global frame: right-handed,
metres, **Z up, X forward** (heading reset at calibration), Y left; quaternions are (w, x, y, z)
and rotate segment-frame vectors into that global frame. Convert to couch's world (X left, Y up,
Z forward) at the boundary with :func:`mvn_to_couch_positions` / :func:`mvn_to_couch_quaternions`
(and back with the ``couch_to_mvn_*`` inverses): the change of axes is the proper cyclic
permutation P = [[0,1,0],[0,0,1],[1,0,0]], so positions become ``p[..., [1, 2, 0]]`` and a rotation
R becomes P R Pᵀ, i.e. the same permutation on the quaternion's vector part.

What was checked, and against what (all outside this repository; nothing fetched is committed):

- A real MVN export: andres-fr/blender-mvnx-io ``io_anim_mvnx_utest/data/test_mocap.mvnx``
  (``<mvn version="2019.0.0">``, configuration ``UpperBody``, 23 segments, 11 sensors, 22 joints,
  3 calibration frames + 112 normal frames at 60 Hz). :func:`read_mvnx` reads it, and
  :func:`write_mvnx` of what it read reproduces the file **byte for byte** (checked with ``cmp``).
  From it: the XML declaration and Xsens's DTD comment, ``xmlns:xsi`` + ``xsi:schemaLocation`` on
  ``<mvnx version="4">``, tab indentation, LF line ends, ``<comment></comment>`` written open/close,
  ``<sensor label=".."/>`` without a space, the subject attributes (label, torsoColor, frameRate,
  segmentCount, recDate, originalFilename, configuration, userScenario) in that order, every float
  as ``%.6f`` (including ``-0.000000``), foot contacts as ``0``/``1``; calibration frames
  ``identity``, ``tpose``, ``tpose-isb`` carry only orientation and position, have no ``index`` and
  have ``time="0" tc="00:00:00:00" ms="0"``; normal frames carry ``time index tc ms type`` in that
  order, the first has ``index="0" time="0"``, and ``time`` equals ``ms`` minus the first frame's
  ``ms`` (sample time stamps, so not always round(index·1000/rate)); ``tc`` is the UTC time of day
  of ``ms`` with frames ``floor(ms mod 1000 · rate / 1000)`` (all 112 frames agree, see
  :func:`mvn_timecode`). The 23 segment labels/ids, the 22 joints and their connectors, the four
  ergonomic joint angles and the foot contact labels are as in that file; its 11 sensor labels are
  the first 11 of :data:`MVN_SENSORS`. In the identity frame every quaternion is (1, 0, 0, 0), the
  right arm lies along −Y, the toes along +X, the head along +Z; a segment's joint points
  (``pos_b``) are the identity-frame position differences of the connected segments
  (:func:`segment_points_from_pose`). Even with UpperBody, MVN exports all 23 segments: only the
  sensors are fewer, so the leg segments are present but not measured.
- The XSDs beside it (``io_anim_mvnx/data/mvnx_schema_{original,mpiea,dance_dec19}.xsd``): the
  element order inside ``<frame>`` (orientation, position, velocity, acceleration, angularVelocity,
  angularAcceleration, footContacts, sensorAcceleration, sensorFreeAcceleration,
  sensorAngularVelocity, sensorMagneticField, sensorOrientation, jointAngle, jointAngleXZY,
  jointAngleErgo, jointAngleErgoXZY, centerOfMass, marker), that only orientation and position are
  mandatory, that ``index`` became optional, that points hold ``pos_b`` or the older ``pos_s``, and
  which subject/frames attributes are required.
- The 17-sensor full-body order (``Pelvis, T8, Head, RightShoulder … LeftFoot``) also appears in an
  independent public MVNX writer (a C# exporter found by code search) and in formats.md.

Not reproduced: ``<securityCode code>`` is an Xsens checksum whose algorithm is not public; the
writer writes ``metadata.security_code`` as given (empty for simulated files). ``<marker>`` and any
element this module does not model (e.g. finger tracking) are skipped by the reader and listed in
``metadata.ignored_elements``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import os
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import IO, TypeVar
from xml.sax.saxutils import escape

import numpy as np

from couch.atomic import atomic_path

NAMESPACE = "http://www.xsens.com/mvn/mvnx"
SCHEMA_LOCATION = "http://www.xsens.com/mvn/mvnx http://www.xsens.com/mvn/mvnx/schema.xsd"
MVNX_VERSION = "4"

MVN_SEGMENTS: tuple[str, ...] = (
    "Pelvis", "L5", "L3", "T12", "T8", "Neck", "Head",
    "RightShoulder", "RightUpperArm", "RightForeArm", "RightHand",
    "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand",
    "RightUpperLeg", "RightLowerLeg", "RightFoot", "RightToe",
    "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "LeftToe",
)
"""The 23 MVN body segments; the label at position i has ``id="i+1"`` in the file."""

MVN_SENSORS: tuple[str, ...] = (
    "Pelvis", "T8", "Head", "RightShoulder", "RightUpperArm", "RightForeArm", "RightHand",
    "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand",
    "RightUpperLeg", "RightLowerLeg", "RightFoot", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot",
)
"""The 17 sensors of the MVN FullBody configuration, in file order (labelled by segment)."""


def _joint(label: str, parent: str, child: str) -> tuple[str, str, str]:
    return (label, f"{parent}/{label}", f"{child}/{label}")


MVN_JOINTS: tuple[tuple[str, str, str], ...] = (
    _joint("jL5S1", "Pelvis", "L5"),
    _joint("jL4L3", "L5", "L3"),
    _joint("jL1T12", "L3", "T12"),
    _joint("jT9T8", "T12", "T8"),
    _joint("jT1C7", "T8", "Neck"),
    _joint("jC1Head", "Neck", "Head"),
    _joint("jRightT4Shoulder", "T8", "RightShoulder"),
    _joint("jRightShoulder", "RightShoulder", "RightUpperArm"),
    _joint("jRightElbow", "RightUpperArm", "RightForeArm"),
    _joint("jRightWrist", "RightForeArm", "RightHand"),
    _joint("jLeftT4Shoulder", "T8", "LeftShoulder"),
    _joint("jLeftShoulder", "LeftShoulder", "LeftUpperArm"),
    _joint("jLeftElbow", "LeftUpperArm", "LeftForeArm"),
    _joint("jLeftWrist", "LeftForeArm", "LeftHand"),
    _joint("jRightHip", "Pelvis", "RightUpperLeg"),
    _joint("jRightKnee", "RightUpperLeg", "RightLowerLeg"),
    _joint("jRightAnkle", "RightLowerLeg", "RightFoot"),
    _joint("jRightBallFoot", "RightFoot", "RightToe"),
    _joint("jLeftHip", "Pelvis", "LeftUpperLeg"),
    _joint("jLeftKnee", "LeftUpperLeg", "LeftLowerLeg"),
    _joint("jLeftAnkle", "LeftLowerLeg", "LeftFoot"),
    _joint("jLeftBallFoot", "LeftFoot", "LeftToe"),
)
"""The 22 joints as (label, connector1, connector2); connectors are ``Segment/pointLabel`` with the
parent segment first. ``jointAngle`` values come in this order."""

ERGONOMIC_JOINTS: tuple[tuple[str, str, str], ...] = (
    ("T8_Head", "T8", "Head"),
    ("T8_LeftUpperArm", "T8", "LeftUpperArm"),
    ("T8_RightUpperArm", "T8", "RightUpperArm"),
    ("Pelvis_T8", "Pelvis", "T8"),
)
"""The ergonomic joint angles of the MVN 2019 sample as (label, parentSegment, childSegment)."""

FOOT_CONTACTS: tuple[str, ...] = ("LeftFoot_Heel", "LeftFoot_Toe", "RightFoot_Heel",
                                  "RightFoot_Toe")
"""Order of the values of ``<footContacts>`` (from ``<footContactDefinition>``)."""

CALIBRATION_TYPES: tuple[str, ...] = ("identity", "tpose", "tpose-isb", "npose")

MVN_TO_SMPL: dict[str, str] = {
    "pelvis": "Pelvis",
    "left_hip": "LeftUpperLeg",
    "right_hip": "RightUpperLeg",
    "spine1": "L5",
    "left_knee": "LeftLowerLeg",
    "right_knee": "RightLowerLeg",
    "spine2": "T12",
    "left_ankle": "LeftFoot",
    "right_ankle": "RightFoot",
    "spine3": "T8",
    "left_foot": "LeftToe",
    "right_foot": "RightToe",
    "neck": "Neck",
    "left_collar": "LeftShoulder",
    "right_collar": "RightShoulder",
    "head": "Head",
    "left_shoulder": "LeftUpperArm",
    "right_shoulder": "RightUpperArm",
    "left_elbow": "LeftForeArm",
    "right_elbow": "RightForeArm",
    "left_wrist": "LeftHand",
    "right_wrist": "RightHand",
    "left_hand": "LeftHand",
    "right_hand": "RightHand",
}
"""For each SMPL joint (keys in SMPL order, = ``couch.body.JOINT_NAMES``) the MVN segment whose
global orientation and proximal-joint position it takes (formats.md). The SMPL hand joints have no
rotation of their own, so both wrist and hand take the MVN hand segment (the public converter
michelebri/mvnx_to_smpl uses the forearm for the wrist instead). ``spine2`` falls back to ``L3``
where a file has no ``T12`` (:func:`smpl_segment_indices`)."""

_SMPL_FALLBACK = {"spine2": "L3"}

# Which sensors must be present for MVN to measure a segment: the spine and neck segments between
# sensors are interpolated from both ends, the toes follow the foot sensor.
_SEGMENT_DRIVERS: dict[str, tuple[str, ...]] = {
    "Pelvis": ("Pelvis",), "L5": ("Pelvis", "T8"), "L3": ("Pelvis", "T8"),
    "T12": ("Pelvis", "T8"), "T8": ("T8",), "Neck": ("T8", "Head"), "Head": ("Head",),
    **{f"{side}{part}": (f"{side}{part}",)
       for side in ("Right", "Left")
       for part in ("Shoulder", "UpperArm", "ForeArm", "Hand", "UpperLeg", "LowerLeg", "Foot")},
    "RightToe": ("RightFoot",), "LeftToe": ("LeftFoot",),
}

_DTD_COMMENT = (
    "<!-- Uncomment this part to use the DTD. This is disabled by default because some "
    "applications (ie Microsoft Excel) refuse to load XML files with a DTD definion.\n"
    '<!DOCTYPE mvnx SYSTEM "http://www.xsens.com/mvn/mvnx/schema.dtd">\n'
    "-->\n"
)


class MvnxError(ValueError):
    """An MVNX file is unreadable or inconsistent; the message names the file, where (frame index
    or line/column) and what was expected."""


# --------------------------------------------------------------------------- data model


@dataclasses.dataclass
class MvnxMetadata:
    """Header values of an MVNX file (strings as they appear in it)."""

    mvn_version: str = "2019.0.0"
    mvn_build: str = "couch (not an Xsens build)"
    comment: str = ""
    subject_label: str = "MVN System 1"
    subject_comment: str = ""
    torso_color: str = "#e96417"
    rec_date: str = ""
    """Local wall-clock start in MVN's format, e.g. ``Tue Nov 13 05:17:11.827 2018``."""
    original_filename: str = ""
    configuration: str = "FullBody"
    user_scenario: str = "singleLevel"
    processing_quality: str | None = None
    security_code: str = ""
    mvnx_version: str = MVNX_VERSION
    point_tag: str = "pos_b"
    """``pos_b`` (MVN 2019+) or ``pos_s`` (older exports): the element holding point positions."""
    ignored_elements: tuple[str, ...] = ()
    """Element names the reader met and skipped (e.g. ``marker``); informational only."""


@dataclasses.dataclass
class MvnxPose:
    """One calibration frame (``identity``, ``tpose``, ``tpose-isb``, ``npose``).

    orientation: (S, 4) quaternions w, x, y, z, segment → MVN global. position: (S, 3) metres,
    MVN global (Z up). The frame attributes are kept so a written file matches the original.
    """

    orientation: np.ndarray
    position: np.ndarray
    time_ms: int = 0
    unix_ms: int = 0
    timecode: str = "00:00:00:00"


# (XML element, field name, what it is counted over, values per item), in the XSD's order.
_FRAME_ELEMENTS: tuple[tuple[str, str, str, int], ...] = (
    ("orientation", "orientation", "segment", 4),
    ("position", "position", "segment", 3),
    ("velocity", "velocity", "segment", 3),
    ("acceleration", "acceleration", "segment", 3),
    ("angularVelocity", "angular_velocity", "segment", 3),
    ("angularAcceleration", "angular_acceleration", "segment", 3),
    ("footContacts", "foot_contacts", "contact", 1),
    ("sensorAcceleration", "sensor_acceleration", "sensor", 3),
    ("sensorFreeAcceleration", "sensor_free_acceleration", "sensor", 3),
    ("sensorAngularVelocity", "sensor_angular_velocity", "sensor", 3),
    ("sensorMagneticField", "sensor_magnetic_field", "sensor", 3),
    ("sensorOrientation", "sensor_orientation", "sensor", 4),
    ("jointAngle", "joint_angle", "joint", 3),
    ("jointAngleXZY", "joint_angle_xzy", "joint", 3),
    ("jointAngleErgo", "joint_angle_ergo", "ergo", 3),
    ("jointAngleErgoXZY", "joint_angle_ergo_xzy", "ergo", 3),
    ("centerOfMass", "center_of_mass", "com", 3),
)
_BY_ELEMENT = {e[0]: e for e in _FRAME_ELEMENTS}


@dataclasses.dataclass
class MvnxRecording:
    """An MVN export as stored in the file, in MVN's frame (Z up, X forward, Y left; metres).

    N normal (motion) frames, S segments, nS sensors, J joints, E ergonomic joint angles.

    Per frame, always present:
        time_ms (N,) int64: ms since the first normal frame (the file's ``time``).
        unix_ms (N,) int64: absolute Unix-epoch ms (``ms``).
        timecode: N strings ``HH:MM:SS:FF`` (``tc``; UTC time of day, FF frames at frame_rate).
        orientation (N, S, 4): segment → global quaternions, w, x, y, z.
        position (N, S, 3): segment origin (proximal joint) positions, metres.
    Optional (None when the file lacks them):
        velocity, acceleration (N, S, 3): m/s, m/s²; angular_velocity (N, S, 3) rad/s,
        angular_acceleration (N, S, 3) rad/s²; foot_contacts (N, 4) bool in
        ``foot_contact_labels`` order; sensor_acceleration, sensor_free_acceleration (N, nS, 3)
        m/s², sensor_angular_velocity (N, nS, 3) rad/s, sensor_magnetic_field (N, nS, 3) in
        arbitrary units normalised to the local earth field, sensor_orientation (N, nS, 4)
        sensor → global; joint_angle and joint_angle_xzy (N, J, 3) degrees (ZXY resp. XZY
        Euler sequences, per joint of ``joints``), joint_angle_ergo / joint_angle_ergo_xzy
        (N, E, 3) degrees;
        center_of_mass (N, C) metres, C = 3 (position; later MVN versions may append velocity and
        acceleration, C = 9).
    """

    frame_rate: float
    segment_labels: list[str]
    sensor_labels: list[str]
    time_ms: np.ndarray
    unix_ms: np.ndarray
    timecode: list[str]
    orientation: np.ndarray
    position: np.ndarray
    frame_index: np.ndarray | None = None
    """(N,) int64 ``index`` attributes; None means 0..N-1."""
    velocity: np.ndarray | None = None
    acceleration: np.ndarray | None = None
    angular_velocity: np.ndarray | None = None
    angular_acceleration: np.ndarray | None = None
    foot_contacts: np.ndarray | None = None
    sensor_acceleration: np.ndarray | None = None
    sensor_free_acceleration: np.ndarray | None = None
    sensor_angular_velocity: np.ndarray | None = None
    sensor_magnetic_field: np.ndarray | None = None
    sensor_orientation: np.ndarray | None = None
    joint_angle: np.ndarray | None = None
    joint_angle_xzy: np.ndarray | None = None
    joint_angle_ergo: np.ndarray | None = None
    joint_angle_ergo_xzy: np.ndarray | None = None
    center_of_mass: np.ndarray | None = None
    calibration: dict[str, MvnxPose] = dataclasses.field(default_factory=dict)
    """Calibration frames by type, in file order."""
    segment_points: dict[str, dict[str, np.ndarray]] = dataclasses.field(default_factory=dict)
    """segment label → {point label → (3,) position in the segment frame, metres}, file order."""
    joints: list[tuple[str, str, str]] = dataclasses.field(
        default_factory=lambda: list(MVN_JOINTS))
    ergonomic_joints: list[tuple[str, str, str]] = dataclasses.field(
        default_factory=lambda: list(ERGONOMIC_JOINTS))
    foot_contact_labels: list[str] = dataclasses.field(
        default_factory=lambda: list(FOOT_CONTACTS))
    metadata: MvnxMetadata = dataclasses.field(default_factory=MvnxMetadata)
    truncation: str | None = None
    """Set by ``read_mvnx(..., recover_truncated=True)`` when the file was cut: what was lost."""

    @property
    def n_frames(self) -> int:
        return int(np.shape(self.orientation)[0])

    def _count(self, over: str) -> int | None:
        return {"segment": len(self.segment_labels), "sensor": len(self.sensor_labels),
                "joint": len(self.joints), "ergo": len(self.ergonomic_joints),
                "contact": len(self.foot_contact_labels)}.get(over)

    def validate(self) -> None:
        """Raise ValueError if any array disagrees with the labels or the frame count."""
        n = self.n_frames
        for element, name, over, width in _FRAME_ELEMENTS:
            value = getattr(self, name)
            if value is None:
                if name in ("orientation", "position"):
                    raise ValueError(f"MvnxRecording.{name} is required")
                continue
            shape = np.shape(value)
            count = self._count(over)
            if over == "com":
                ok = len(shape) == 2 and shape[0] == n and shape[1] % 3 == 0 and shape[1] > 0
                want = f"({n}, 3k)"
            elif over == "contact":
                ok = shape == (n, count)
                want = f"({n}, {count})"
            else:
                ok = shape == (n, count, width)
                want = f"({n}, {count}, {width})"
            if not ok:
                raise ValueError(f"MvnxRecording.{name} (<{element}>) has shape {shape}, "
                                 f"expected {want}")
        for name in ("time_ms", "unix_ms"):
            if np.shape(getattr(self, name)) != (n,):
                raise ValueError(f"MvnxRecording.{name} must have shape ({n},)")
        if len(self.timecode) != n:
            raise ValueError(f"MvnxRecording.timecode has {len(self.timecode)} entries, "
                             f"expected {n}")
        if self.frame_index is not None and np.shape(self.frame_index) != (n,):
            raise ValueError(f"MvnxRecording.frame_index must have shape ({n},)")
        s = len(self.segment_labels)
        for ctype, pose in self.calibration.items():
            if np.shape(pose.orientation) != (s, 4) or np.shape(pose.position) != (s, 3):
                raise ValueError(f"calibration frame {ctype!r} must hold ({s}, 4) orientations "
                                 f"and ({s}, 3) positions")
        unknown = set(self.segment_points) - set(self.segment_labels)
        if unknown:
            raise ValueError(f"segment_points names segments not in segment_labels: "
                             f"{sorted(unknown)}")


@dataclasses.dataclass(frozen=True)
class FullBodyGap:
    """What a recording lacks for a full-body (17-sensor, 23-segment) fit."""

    configuration: str
    missing_segments: tuple[str, ...]
    missing_sensors: tuple[str, ...]
    unmeasured_segments: tuple[str, ...]
    """Segments present in the file whose motion no sensor measures (MVN fills them in, e.g. the
    legs of an UpperBody recording), so a fit should not trust them."""

    @property
    def complete(self) -> bool:
        return not (self.missing_segments or self.missing_sensors or self.unmeasured_segments)

    def __str__(self) -> str:
        if self.complete:
            return f"{self.configuration}: complete for a full-body fit"
        parts = []
        if self.missing_segments:
            parts.append(f"segments absent: {', '.join(self.missing_segments)}")
        if self.missing_sensors:
            parts.append(f"sensors absent: {', '.join(self.missing_sensors)}")
        if self.unmeasured_segments:
            parts.append(f"segments not measured: {', '.join(self.unmeasured_segments)}")
        return f"{self.configuration} lacks for a full-body fit: " + "; ".join(parts)


def missing_for_full_body(rec: MvnxRecording) -> FullBodyGap:
    """Compare ``rec`` with the 23 segments / 17 sensors of MVN's FullBody configuration."""
    segments = set(rec.segment_labels)
    sensors = set(rec.sensor_labels)
    return FullBodyGap(
        configuration=rec.metadata.configuration,
        missing_segments=tuple(s for s in MVN_SEGMENTS if s not in segments),
        missing_sensors=tuple(s for s in MVN_SENSORS if s not in sensors),
        unmeasured_segments=tuple(
            s for s in MVN_SEGMENTS
            if s in segments and not all(d in sensors for d in _SEGMENT_DRIVERS[s])),
    )


def smpl_segment_indices(segment_labels: Sequence[str]) -> np.ndarray:
    """(24,) int64 indices into ``segment_labels`` of the segment each SMPL joint takes
    (:data:`MVN_TO_SMPL`, SMPL order); raises ValueError naming any segment that is missing."""
    index = {label: i for i, label in enumerate(segment_labels)}
    out, missing = [], []
    for joint, segment in MVN_TO_SMPL.items():
        if segment not in index and joint in _SMPL_FALLBACK:
            segment = _SMPL_FALLBACK[joint]
        if segment not in index:
            missing.append(f"{joint}←{segment}")
            continue
        out.append(index[segment])
    if missing:
        raise ValueError(f"segments needed for SMPL joints are missing: {', '.join(missing)}")
    return np.asarray(out, dtype=np.int64)


# --------------------------------------------------------------------------- frame conversion

Array = TypeVar("Array")


def mvn_to_couch_positions(p: Array) -> Array:
    """(..., 3) MVN global (X forward, Y left, Z up) → couch world (X left, Y up, Z forward)."""
    return p[..., [1, 2, 0]]  # type: ignore[index]


def couch_to_mvn_positions(p: Array) -> Array:
    """Inverse of :func:`mvn_to_couch_positions`."""
    return p[..., [2, 0, 1]]  # type: ignore[index]


def mvn_to_couch_quaternions(q: Array) -> Array:
    """(..., 4) w, x, y, z in MVN's frame → the same rotations in couch's world: P R Pᵀ, which for
    the cyclic axis permutation P is ``[w, x, y, z] → [w, y, z, x]``."""
    return q[..., [0, 2, 3, 1]]  # type: ignore[index]


def couch_to_mvn_quaternions(q: Array) -> Array:
    """Inverse of :func:`mvn_to_couch_quaternions`."""
    return q[..., [0, 3, 1, 2]]  # type: ignore[index]


# --------------------------------------------------------------------------- time helpers


def mvn_timecode(unix_ms: np.ndarray | Sequence[int], frame_rate: float) -> list[str]:
    """MVN's ``tc`` for absolute times: UTC ``HH:MM:SS:FF`` with FF = ⌊(ms mod 1000)·rate/1000⌋.

    Matches every normal frame of the public MVN 2019 sample (60 Hz)."""
    ms = np.asarray(unix_ms, dtype=np.int64)
    day_ms = np.mod(ms, 86_400_000)
    hh, mm, ss = day_ms // 3_600_000, (day_ms // 60_000) % 60, (day_ms // 1000) % 60
    ff = (np.mod(ms, 1000) * frame_rate // 1000).astype(np.int64)
    return [f"{h:02d}:{m:02d}:{s:02d}:{f:02d}"
            for h, m, s, f in zip(hh.tolist(), mm.tolist(), ss.tolist(), ff.tolist(),
                                  strict=True)]


def mvn_rec_date(unix_ms: int, tz: _dt.tzinfo | None = None) -> str:
    """``recDate`` as MVN writes it (``Tue Nov 13 05:17:11.827 2018``), local time in ``tz``
    (the recording PC's zone; default UTC)."""
    t = _dt.datetime.fromtimestamp(unix_ms / 1000, tz or _dt.UTC)
    return f"{t:%a %b %d %H:%M:%S}.{unix_ms % 1000:03d} {t.year}"


def segment_points_from_pose(pose: MvnxPose, segment_labels: Sequence[str],
                             joints: Sequence[tuple[str, str, str]] = MVN_JOINTS,
                             ) -> dict[str, dict[str, np.ndarray]]:
    """Joint points of every segment (in its own frame, metres) from a calibration pose.

    Each segment gets its proximal joint at the origin (the pelvis a ``pHipOrigin``) and each
    distal joint at R_parentᵀ (p_child − p_parent). In MVN's identity pose this reproduces the
    ``jX`` points of real exports (which additionally list anatomical landmarks ``pX``).
    """
    from couch.rotations import quat_to_matrix  # imports torch: only load it when needed

    index = {s: i for i, s in enumerate(segment_labels)}
    rot = quat_to_matrix(np.asarray(pose.orientation, dtype=np.float64))  # (S, 3, 3)
    pos = np.asarray(pose.position, dtype=np.float64)
    points: dict[str, dict[str, np.ndarray]] = {s: {} for s in segment_labels}
    for label, _, c2 in joints:
        child = c2.split("/")[0]
        if child in index:
            points[child].setdefault(label, np.zeros(3))
    root = segment_labels[0] if segment_labels else None
    if root is not None and not points[root]:
        points[root]["pHipOrigin"] = np.zeros(3)
    for label, c1, c2 in joints:
        parent, child = c1.split("/")[0], c2.split("/")[0]
        if parent in index and child in index:
            i, j = index[parent], index[child]
            points[parent][label] = rot[i].T @ (pos[j] - pos[i])
    return points


# --------------------------------------------------------------------------- writer


def _attr(value: object) -> str:
    return escape(str(value), {'"': "&quot;", "\n": "&#10;", "\r": "&#13;", "\t": "&#9;"})


def _number(x: float) -> str:
    return f"{x:g}" if float(x) != int(x) else str(int(x))


def _format_rows(values: np.ndarray, fmt: str) -> list[str]:
    """One space-separated string per row of a 2-D array."""
    row = " ".join([fmt] * values.shape[1])
    return [row % tuple(r) for r in values.tolist()]


def write_mvnx(path: str | os.PathLike, rec: MvnxRecording, *, chunk_frames: int = 2000) -> None:
    """Write ``rec`` as an MVNX 4 file laid out exactly as MVN 2019 writes it (atomic).

    Segments without entries in ``rec.segment_points`` get joint points derived from the
    ``identity`` calibration frame (:func:`segment_points_from_pose`); without one a ValueError
    asks for them. Frames are formatted ``chunk_frames`` at a time to bound memory.
    """
    rec.validate()
    points = dict(rec.segment_points)
    lacking = [s for s in rec.segment_labels if not points.get(s)]
    if lacking:
        if "identity" not in rec.calibration:
            raise ValueError(f"segments {lacking} have no points and there is no identity "
                             "calibration frame to derive them from")
        derived = segment_points_from_pose(rec.calibration["identity"], rec.segment_labels,
                                           rec.joints)
        points.update({s: derived[s] for s in lacking})
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline="\n") as f:
        _write_header(f, rec, points)
        for ctype, pose in rec.calibration.items():
            f.write(f'\t\t\t<frame time="{int(pose.time_ms)}" tc="{_attr(pose.timecode)}" '
                    f'ms="{int(pose.unix_ms)}" type="{_attr(ctype)}">\n')
            f.write(f"\t\t\t\t<orientation>"
                    f"{_format_rows(np.reshape(pose.orientation, (1, -1)), '%.6f')[0]}"
                    f"</orientation>\n")
            f.write(f"\t\t\t\t<position>"
                    f"{_format_rows(np.reshape(pose.position, (1, -1)), '%.6f')[0]}"
                    f"</position>\n")
            f.write("\t\t\t</frame>\n")
        for chunk in _frame_chunks(rec, chunk_frames):
            f.write(chunk)
        f.write("\t\t</frames>\n\t</subject>\n")
        f.write(f'\t<securityCode code="{_attr(rec.metadata.security_code)}"/>\n</mvnx>\n')


def _write_header(f: IO[str], rec: MvnxRecording,
                  points: Mapping[str, Mapping[str, np.ndarray]]) -> None:
    m = rec.metadata
    f.write('<?xml version="1.0" encoding="UTF-8"?>\n')
    f.write(_DTD_COMMENT)
    f.write(f'<mvnx xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" xmlns="{NAMESPACE}" '
            f'xsi:schemaLocation="{SCHEMA_LOCATION}" version="{_attr(m.mvnx_version)}">\n')
    f.write(f'\t<mvn version="{_attr(m.mvn_version)}" build="{_attr(m.mvn_build)}"/>\n')
    f.write(f"\t<comment>{escape(m.comment)}</comment>\n")
    quality = ("" if m.processing_quality is None
               else f' processingQuality="{_attr(m.processing_quality)}"')
    f.write(f'\t<subject label="{_attr(m.subject_label)}" torsoColor="{_attr(m.torso_color)}" '
            f'frameRate="{_number(rec.frame_rate)}" segmentCount="{len(rec.segment_labels)}" '
            f'recDate="{_attr(m.rec_date)}" originalFilename="{_attr(m.original_filename)}" '
            f'configuration="{_attr(m.configuration)}" userScenario="{_attr(m.user_scenario)}"'
            f"{quality}>\n")
    f.write(f"\t\t<comment>{escape(m.subject_comment)}</comment>\n")
    f.write("\t\t<segments>\n")
    tag = m.point_tag
    for i, label in enumerate(rec.segment_labels):
        f.write(f'\t\t\t<segment label="{_attr(label)}" id="{i + 1}">\n\t\t\t\t<points>\n')
        for name, p in points[label].items():
            xyz = " ".join(f"{v:.6f}" for v in np.asarray(p, dtype=np.float64).tolist())
            f.write(f'\t\t\t\t\t<point label="{_attr(name)}">\n'
                    f"\t\t\t\t\t\t<{tag}>{xyz}</{tag}>\n\t\t\t\t\t</point>\n")
        f.write("\t\t\t\t</points>\n\t\t\t</segment>\n")
    f.write("\t\t</segments>\n")
    if rec.sensor_labels:
        f.write("\t\t<sensors>\n")
        f.writelines(f'\t\t\t<sensor label="{_attr(s)}"/>\n' for s in rec.sensor_labels)
        f.write("\t\t</sensors>\n")
    if rec.joints:
        f.write("\t\t<joints>\n")
        for label, c1, c2 in rec.joints:
            f.write(f'\t\t\t<joint label="{_attr(label)}">\n'
                    f"\t\t\t\t<connector1>{escape(c1)}</connector1>\n"
                    f"\t\t\t\t<connector2>{escape(c2)}</connector2>\n\t\t\t</joint>\n")
        f.write("\t\t</joints>\n")
    if rec.ergonomic_joints:
        f.write("\t\t<ergonomicJointAngles>\n")
        for i, (label, parent, child) in enumerate(rec.ergonomic_joints):
            f.write(f'\t\t\t<ergonomicJointAngle label="{_attr(label)}" index="{i}" '
                    f'parentSegment="{_attr(parent)}" childSegment="{_attr(child)}"/>\n')
        f.write("\t\t</ergonomicJointAngles>\n")
    if rec.foot_contact_labels:
        f.write("\t\t<footContactDefinition>\n")
        f.writelines(f'\t\t\t<contactDefinition label="{_attr(c)}" index="{i}"/>\n'
                     for i, c in enumerate(rec.foot_contact_labels))
        f.write("\t\t</footContactDefinition>\n")
    f.write(f'\t\t<frames segmentCount="{len(rec.segment_labels)}" '
            f'sensorCount="{len(rec.sensor_labels)}" jointCount="{len(rec.joints)}">\n')


def _frame_chunks(rec: MvnxRecording, chunk_frames: int) -> Iterator[str]:
    n = rec.n_frames
    index = (np.arange(n, dtype=np.int64) if rec.frame_index is None
             else np.asarray(rec.frame_index, dtype=np.int64))
    present = [(element, getattr(rec, name)) for element, name, _, _ in _FRAME_ELEMENTS
               if getattr(rec, name) is not None]
    for start in range(0, n, chunk_frames):
        stop = min(n, start + chunk_frames)
        texts = []
        for element, value in present:
            block = np.asarray(value[start:stop]).reshape(stop - start, -1)
            if element == "footContacts":
                rows = _format_rows(block.astype(np.int64), "%d")
            else:
                rows = _format_rows(block.astype(np.float64), "%.6f")
            texts.append((element, rows))
        times = np.asarray(rec.time_ms[start:stop], dtype=np.int64).tolist()
        unix = np.asarray(rec.unix_ms[start:stop], dtype=np.int64).tolist()
        lines = []
        for k in range(stop - start):
            lines.append(f'\t\t\t<frame time="{times[k]}" index="{index[start + k]}" '
                         f'tc="{_attr(rec.timecode[start + k])}" ms="{unix[k]}" '
                         f'type="normal">\n')
            lines.extend(f"\t\t\t\t<{element}>{rows[k]}</{element}>\n" for element, rows in texts)
            lines.append("\t\t\t</frame>\n")
        yield "".join(lines)


# --------------------------------------------------------------------------- reader


def _local(tag: str) -> str:
    return tag.rpartition("}")[2]


def _namespace(tag: str) -> str:
    return tag[1:].partition("}")[0] if tag.startswith("{") else ""


# expat error codes that mean "the document stopped before it was complete"
_TRUNCATION_CODES = {3, 5, 6}  # no elements, unclosed token, partial character


class _Reader:
    """Event handler for one streaming parse; accumulates header values and frame arrays."""

    def __init__(self, path: Path):
        self.path = path
        self.meta = MvnxMetadata(point_tag="")
        self.frame_rate: float | None = None
        self.segment_labels: list[str] = []
        self.sensor_labels: list[str] = []
        self.joints: list[tuple[str, str, str]] = []
        self.ergonomic: list[tuple[str, str, str]] | None = None
        self.contacts: list[str] | None = None
        self.points: dict[str, dict[str, np.ndarray]] = {}
        self.counts: dict[str, int] = {}
        self.frames_elem: ET.Element | None = None
        self.seen_root = False
        self.header_attrs: dict[str, str] = {}
        self.calibration: dict[str, MvnxPose] = {}
        self.columns: dict[str, list[np.ndarray]] = {}
        self.optional: tuple[str, ...] | None = None
        self.time_ms: list[int] = []
        self.unix_ms: list[int] = []
        self.timecode: list[str] = []
        self.index: list[int] = []
        self.ignored: set[str] = set()
        self.stack: list[str] = []
        self.last_frame: str = "before the first frame"

    # -- errors
    def error(self, where: str, what: str) -> MvnxError:
        return MvnxError(f"{self.path}: {where}: {what}")

    # -- events
    def start(self, elem: ET.Element) -> None:
        name = _local(elem.tag)
        if not self.seen_root:
            self.seen_root = True
            if name != "mvnx" or _namespace(elem.tag) not in (NAMESPACE, ""):
                raise self.error("root element", f"expected <mvnx> in namespace {NAMESPACE}, "
                                 f"found <{name}> in namespace '{_namespace(elem.tag)}' "
                                 "(not an MVNX file)")
            self.meta.mvnx_version = elem.get("version", "")
        parent = self.stack[-1] if self.stack else None
        self.stack.append(name)
        if name == "subject" and parent == "mvnx":
            self._subject(elem)
        elif name == "frames" and parent == "subject":
            self._frames_start(elem)

    def end(self, elem: ET.Element) -> None:
        name = self.stack.pop()
        parent = self.stack[-1] if self.stack else None
        if name == "frame" and parent == "frames":
            self._frame(elem)
            elem.clear()
            if self.frames_elem is not None:
                del self.frames_elem[:]  # keep memory flat on files of hundreds of MB
        elif name == "mvn" and parent == "mvnx":
            self.meta.mvn_version = elem.get("version", "")
            self.meta.mvn_build = elem.get("build", "")
        elif name == "comment" and parent == "mvnx":
            self.meta.comment = elem.text or ""
        elif name == "comment" and parent == "subject":
            self.meta.subject_comment = elem.text or ""
        elif name == "segment" and parent == "segments":
            self._segment(elem)
        elif name == "sensor" and parent == "sensors":
            self.sensor_labels.append(elem.get("label", ""))
        elif name == "joint" and parent == "joints":
            c1 = c2 = ""
            for child in elem:
                if _local(child.tag) == "connector1":
                    c1 = (child.text or "").strip()
                elif _local(child.tag) == "connector2":
                    c2 = (child.text or "").strip()
            self.joints.append((elem.get("label", ""), c1, c2))
        elif name == "ergonomicJointAngle" and parent == "ergonomicJointAngles":
            self.ergonomic = self.ergonomic or []
            self.ergonomic.append((elem.get("label", ""), elem.get("parentSegment", ""),
                                   elem.get("childSegment", "")))
        elif name == "contactDefinition" and parent == "footContactDefinition":
            self.contacts = self.contacts or []
            self.contacts.append(elem.get("label", ""))
        elif name == "securityCode" and parent == "mvnx":
            self.meta.security_code = elem.get("code", "")

    # -- header pieces
    def _subject(self, elem: ET.Element) -> None:
        a = elem.attrib
        self.header_attrs = dict(a)
        m = self.meta
        m.subject_label = a.get("label", "")
        m.torso_color = a.get("torsoColor", "")
        m.rec_date = a.get("recDate", "")
        m.original_filename = a.get("originalFilename", "")
        m.configuration = a.get("configuration", "")
        m.user_scenario = a.get("userScenario", "")
        m.processing_quality = a.get("processingQuality")
        rate = a.get("frameRate")
        try:
            self.frame_rate = float(rate) if rate is not None else None
        except ValueError:
            raise self.error("<subject>", f"frameRate={rate!r} is not a number") from None
        if self.frame_rate is None or not self.frame_rate > 0:
            raise self.error("<subject>", f"expected a positive frameRate, found {rate!r}")

    def _segment(self, elem: ET.Element) -> None:
        label = elem.get("label", "")
        pts: dict[str, np.ndarray] = {}
        for point in elem.iter():
            if _local(point.tag) != "point":
                continue
            for child in point:
                tag = _local(child.tag)
                if tag in ("pos_b", "pos_s"):
                    self.meta.point_tag = self.meta.point_tag or tag
                    xyz = self._numbers(child.text, f"segment {label!r} point "
                                        f"{point.get('label')!r}", tag)
                    if xyz.size != 3:
                        raise self.error(f"segment {label!r} point {point.get('label')!r}",
                                         f"<{tag}> has {xyz.size} values, expected 3")
                    pts[point.get("label", "")] = xyz
        self.points[label] = pts
        self.segment_labels.append(label)

    def _frames_start(self, elem: ET.Element) -> None:
        self.frames_elem = elem
        where = "<frames>"
        declared = {"segment": ("segmentCount", self.segment_labels),
                    "sensor": ("sensorCount", self.sensor_labels),
                    "joint": ("jointCount", self.joints)}
        for over, (attr, labels) in declared.items():
            raw = elem.get(attr)
            if raw is None:
                self.counts[over] = len(labels)
                continue
            try:
                value = int(raw)
            except ValueError:
                raise self.error(where, f"{attr}={raw!r} is not an integer") from None
            if labels and value != len(labels):
                raise self.error(where, f"{attr}={value} but the header lists {len(labels)} "
                                 f"{over}s")
            self.counts[over] = value
        subject_count = self.header_attrs.get("segmentCount")
        if subject_count is not None and subject_count.isdigit() \
                and int(subject_count) != self.counts["segment"]:
            raise self.error(where, f"segmentCount={self.counts['segment']} disagrees with "
                             f"<subject segmentCount={subject_count}>")
        if self.counts["segment"] == 0:
            raise self.error(where, "segmentCount is 0: no segments to read")
        if not self.segment_labels:
            if self.counts["segment"] != len(MVN_SEGMENTS):
                raise self.error(where, "no <segments> labels and segmentCount "
                                 f"{self.counts['segment']} is not the standard 23")
            self.segment_labels = list(MVN_SEGMENTS)
        if self.counts["sensor"] and not self.sensor_labels:
            raise self.error(where, f"sensorCount={self.counts['sensor']} but no <sensors> "
                             "labels")
        if self.ergonomic is not None:
            self.counts["ergo"] = len(self.ergonomic)
        if self.contacts is not None:
            self.counts["contact"] = len(self.contacts)

    def _numbers(self, text: str | None, where: str, element: str) -> np.ndarray:
        try:
            return np.array((text or "").split(), dtype=np.float64)
        except ValueError:
            bad = next(t for t in (text or "").split() if not _is_float(t))
            raise self.error(where, f"<{element}> holds {bad!r}, expected numbers") from None

    def _frame(self, elem: ET.Element) -> None:
        ftype = elem.get("type")
        idx = elem.get("index")
        where = (f"frame index {idx}" if idx is not None else f"{ftype or 'untyped'} frame")
        where += f" (time {elem.get('time')} ms, normal frame #{len(self.time_ms)})"
        if ftype is None:
            raise self.error(where, "<frame> has no type attribute")
        values: dict[str, np.ndarray] = {}
        for child in elem:
            name = _local(child.tag)
            spec = _BY_ELEMENT.get(name)
            if spec is None:
                self.ignored.add(name)
                continue
            arr = self._numbers(child.text, where, name)
            self._check_size(spec, arr, where)
            values[spec[1]] = arr
        for required in ("orientation", "position"):
            if required not in values:
                raise self.error(where, f"missing <{required}> (required in every frame)")
        try:
            time_ms = int(float(elem.get("time", "0")))
            unix_ms = int(float(elem.get("ms", "0")))
        except ValueError:
            raise self.error(where, f"time={elem.get('time')!r} / ms={elem.get('ms')!r} are "
                             "not numbers") from None
        s = self.counts["segment"]
        if ftype != "normal":
            self.calibration[ftype] = MvnxPose(values["orientation"].reshape(s, 4),
                                               values["position"].reshape(s, 3), time_ms,
                                               unix_ms, elem.get("tc", ""))
            return
        names = tuple(k for k in values if k not in ("orientation", "position"))
        if self.optional is None:
            self.optional = names
            self.columns = {k: [] for k in ("orientation", "position", *names)}
        elif set(names) != set(self.optional):
            extra = sorted(set(names) - set(self.optional))
            lacking = sorted(set(self.optional) - set(names))
            raise self.error(where, "the elements differ from earlier frames "
                             f"(extra: {extra or 'none'}, missing: {lacking or 'none'})")
        for k, arr in values.items():
            self.columns[k].append(arr)
        self.time_ms.append(time_ms)
        self.unix_ms.append(unix_ms)
        self.timecode.append(elem.get("tc", ""))
        try:
            self.index.append(int(idx) if idx is not None else len(self.index))
        except ValueError:
            raise self.error(where, f"index={idx!r} is not an integer") from None
        self.last_frame = where

    def _check_size(self, spec: tuple[str, str, str, int], arr: np.ndarray, where: str) -> None:
        element, _, over, width = spec
        if over in ("ergo", "contact", "com") and over not in self.counts:
            # No header definition: the first frame that has the element fixes its size.
            if arr.size == 0 or arr.size % width:
                raise self.error(where, f"<{element}> has {arr.size} values, expected a "
                                 f"positive multiple of {width}")
            self.counts[over] = arr.size // width
        count = self.counts.get(over, 0)
        expected = count * width
        if arr.size != expected:
            unit = {"segment": "segmentCount", "sensor": "sensorCount", "joint": "jointCount",
                    "ergo": "ergonomic joint angles", "contact": "foot contact definitions",
                    "com": "values in earlier frames"}[over]
            raise self.error(where, f"<{element}> has {arr.size} values, expected {expected} "
                             f"({width} × {unit} {count})")

    # -- result
    def build(self, truncation: str | None = None) -> MvnxRecording:
        if self.frames_elem is None:
            raise self.error("end of file", "no <frames> element (is this an MVN export?)")
        if self.optional is None:
            raise self.error("<frames>", "no frames of type 'normal' (only calibration frames)")
        n = len(self.time_ms)
        s, ns = self.counts["segment"], self.counts["sensor"]
        shapes = {"segment": (s,), "sensor": (ns,), "joint": (self.counts["joint"],),
                  "ergo": (self.counts.get("ergo", 0),), "contact": (), "com": ()}
        arrays: dict[str, np.ndarray] = {}
        for _, name, over, width in _FRAME_ELEMENTS:
            if name not in self.columns:
                continue
            stacked = np.stack(self.columns[name]) if n else np.zeros((0, 0))
            if over == "contact":
                arrays[name] = stacked.reshape(n, -1) != 0
            elif over == "com":
                arrays[name] = stacked.reshape(n, -1)
            else:
                arrays[name] = stacked.reshape((n, *shapes[over], width))
        meta = self.meta
        meta.point_tag = meta.point_tag or "pos_b"
        meta.ignored_elements = tuple(sorted(self.ignored))
        ergonomic = self.ergonomic
        if ergonomic is None:
            ergonomic = list(ERGONOMIC_JOINTS) if "joint_angle_ergo" not in arrays else [
                (f"ergo{i}", "", "") for i in range(self.counts.get("ergo", 0))]
        return MvnxRecording(
            frame_rate=float(self.frame_rate or 0.0),
            segment_labels=self.segment_labels,
            sensor_labels=self.sensor_labels,
            time_ms=np.asarray(self.time_ms, dtype=np.int64),
            unix_ms=np.asarray(self.unix_ms, dtype=np.int64),
            timecode=self.timecode,
            frame_index=np.asarray(self.index, dtype=np.int64),
            calibration=self.calibration,
            segment_points=self.points,
            joints=self.joints or list(MVN_JOINTS),
            ergonomic_joints=ergonomic,
            foot_contact_labels=self.contacts if self.contacts is not None
            else list(FOOT_CONTACTS),
            metadata=meta,
            truncation=truncation,
            **arrays,
        )


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


_EXPAT_WHERE = re.compile(r": line \d+, column \d+$")


class _ProgressReader:
    """File wrapper that advances a tqdm bar by the bytes iterparse reads."""

    def __init__(self, f: IO[bytes], bar: object):
        self._f, self._bar = f, bar

    def read(self, size: int = -1) -> bytes:
        chunk = self._f.read(size)
        self._bar.update(len(chunk))  # type: ignore[attr-defined]
        return chunk


def read_mvnx(path: str | os.PathLike, *, recover_truncated: bool = False,
              progress: bool = False) -> MvnxRecording:
    """Read an MVNX file with a streaming, namespace-aware parse (memory stays flat).

    Motion frames are those with ``type="normal"``; every other type is a calibration frame.
    Counts come from ``<frames segmentCount sensorCount jointCount>`` and the header labels, so
    partial configurations load (see :func:`missing_for_full_body`).

    Raises MvnxError (a ValueError) naming the file and the frame or line/column for truncated
    or malformed XML, wrong element sizes, non-numeric values, or a non-MVNX document. With
    ``recover_truncated=True`` a file cut mid-way instead yields the complete normal frames
    before the cut, and ``rec.truncation`` says where it was cut and how many frames were kept.
    ``progress=True`` shows a tqdm bar over the bytes read.
    """
    path = Path(path)
    reader = _Reader(path)
    try:
        with contextlib.ExitStack() as stack:
            source: IO[bytes] | _ProgressReader = stack.enter_context(open(path, "rb"))
            if progress:
                from tqdm import tqdm

                bar = stack.enter_context(tqdm(total=path.stat().st_size, unit="B",
                                               unit_scale=True, desc=path.name))
                source = _ProgressReader(source, bar)  # type: ignore[arg-type]
            for event, elem in ET.iterparse(source, events=("start", "end")):
                if event == "start":
                    reader.start(elem)
                else:
                    reader.end(elem)
    except ET.ParseError as err:
        line, column = err.position
        code = getattr(err, "code", None)
        detail = _EXPAT_WHERE.sub("", str(err))
        truncated = code in _TRUNCATION_CODES
        where = f"line {line}, column {column}"
        context = (f"last complete frame: {reader.last_frame}; "
                   f"{len(reader.time_ms)} normal frames read")
        if truncated and recover_truncated and reader.optional is not None:
            note = (f"{path}: file ends early at {where} ({detail}); kept the "
                    f"{len(reader.time_ms)} complete normal frames before the cut")
            return reader.build(truncation=note)
        if not reader.seen_root:
            what = (f"file ends before the <mvnx> root element ({detail})" if truncated
                    else f"not an XML document ({detail})")
        elif truncated:
            what = f"file ends early, XML is incomplete ({detail}); {context}"
        else:
            what = f"malformed XML ({detail}); {context}"
        raise MvnxError(f"{path}: {where}: {what}") from None
    except (LookupError, ValueError) as err:
        # expat raises these (not ParseError) for the encoding named in the XML declaration:
        # LookupError for an unknown one, ValueError for a multi-byte one (UTF-16/32, Shift-JIS).
        if isinstance(err, MvnxError) or not (isinstance(err, LookupError)
                                              or "encoding" in str(err)):
            raise
        raise MvnxError(f"{path}: line 1: the XML declaration names an encoding the parser "
                        f"cannot read ({err}); MVN exports are UTF-8") from None
    if not reader.seen_root:
        raise reader.error("line 1", "not an XML document")
    return reader.build()
