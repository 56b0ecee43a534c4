"""The simulator's Xsens MVN Awinda suit: 17 MTw sensors on the body, an MVNX export and the raw
Xbus byte stream, with IMU errors that do not cancel out, and the truth of every error injected.

Input is the ground-truth body motion (:class:`BodyTrack`, our world frame, Kinect clock). Output:

- :func:`simulate_mvnx` → an :class:`~couch.capture.mvnx.MvnxRecording` at 60 Hz on the IMU's own
  clock (write it with :func:`couch.capture.mvnx.write_mvnx`) and an :class:`ImuTruth`;
- :func:`simulate_xbus` → the bytes of a serial capture of the 17 sensors' MTData2 messages
  (couch's convention, formats.md), the DeviceId → segment map (write it with
  :func:`couch.capture.xbus.write_device_map`) and an :class:`XbusTruth`.

Both draw every random error from ``rng`` in the same fixed order before anything else, so called
with generators in the same state they describe **one session**: the same clock, heading, sensor
placement, misalignment, noise and biases (the Xbus stream then differs from the MVNX only by the
constant heading of its earth frame, ``earth_heading``).

Clock model (both outputs; all times in seconds)::

    t_imu = clock_scale · t_kinect + clock_offset,     clock_scale = 1 + drift_ppm · 1e-6

``t_imu`` is MVN's recording clock: 0 at the first sample, sample k at exactly ``t_imu = k / 60``
(the IMU runs ``drift_ppm`` faster than the Kinect clock when positive). ``clock_offset`` is the
IMU clock's reading at Kinect time 0; by default (``ImuConfig.clock_offset=None``) it is chosen so
that the recording starts ``ImuConfig.start_delay`` Kinect seconds after the track's first time.
The recording ends with the last sample whose Kinect time lies in the track. Samples that map
before the track's start (a given ``clock_offset`` that starts the IMU early) hold the first pose
and are marked ``in_track = False``. MVNX ``time`` = round(1000·t_imu) ms, ``ms`` =
``start_unix_ms`` + ``time`` (``start_unix_ms`` is the wall-clock Unix ms of t_imu = 0), ``tc``
from ``ms``; Xbus SampleTimeFine = (stf0 + round(1e4·t_imu)) mod 2³² (10 kHz ticks of the same
clock) and PacketCounter = (pc0 + k) mod 2¹⁶.

Frames. Our world: metres, X = the body's left at rest, Y up, Z forward (SMPL's T-pose faces +Z).
MVN's global frame (MVNX): Z up, X forward at calibration, Y left; in the identity pose every
segment quaternion is (1, 0, 0, 0) with the body in T-pose facing +X. Our T-pose rest also has
identity global rotations (facing +Z), so the frame change is the fixed axis permutation of
:mod:`couch.capture.mvnx` (``couch_to_mvn_*``): ``p_mvnaxes = p[[2, 0, 1]]`` and R ↦ Pᵀ R P, which
maps SMPL joint frames onto MVN segment frames too. On top of it MVN's global frame has a heading
(rotation about the vertical) relative to ours::

    v_mvn = Rz(ψ(t))ᵀ · v_mvnaxes,      ψ(t) = heading_offset + heading_drift(t)

i.e. MVN's +X axis is our forward (+Z) turned by ψ about our +Y (towards our +X, the body's left,
for ψ > 0). Positions additionally have MVN's origin: the pelvis's floor projection at the first
sample (``ImuConfig.recenter``), recorded as ``ImuTruth.origin`` (MVN axes, before the heading).
The Xbus earth frame E ("ENU-like": right-handed, Z up against gravity; it stands in for the MTw's
local east-north-up frame, which MVN resets in heading) is MVN's global frame turned by the
constant ``earth_heading`` about Z: ``v_E = Rz(earth_heading)ᵀ · v_mvn``. Sensor-frame vectors
(Acceleration, RateOfTurn) are in the sensor's own axes; a sensor with ``mount`` = identity has the
axes of its MVN segment (X forward, Y left, Z up in the T-pose).

Error model (every term is returned in the truth; magnitudes in :class:`ImuConfig`)::

    R_seg_reported  = N_s(t) · Rz(ψ(t))ᵀ · R_seg · M_seg          (23 segments, MVN frame)
    R_sens_reported = N_s(t) · Rz(ψ(t))ᵀ · R_seg · mount_s        (17 sensors)

R_seg is the true segment orientation in MVN axes; M_seg a constant few-degree calibration error
(sensor-to-segment misalignment) in the segment frame; mount_s the true placement of sensor s on
its segment (so MVN's believed sensor-to-segment rotation ``R_seg_reportedᵀ R_sens_reported =
M_segᵀ mount_s`` is constant but wrong by M); N_s(t) a smooth, time-correlated orientation error
of the fusion filter (tilt and heading, global frame; segments without a sensor take the error of
the sensor that drives them). Segment positions come, as in MVN, from the reported orientations
by forward kinematics along MVN's segment tree with the body's true dimensions, hung from a pelvis
whose horizontal path is integrated in the drifting heading frame plus a smooth random-walk drift
and a constant vertical bias. Accelerometers measure the specific force of their true site on the
segment in the true sensor frame plus a constant bias and white noise; gyros measure the true
body-frame angular rate plus bias and noise; free acceleration is, as on the device, the measured
specific force rotated by the *reported* orientation minus gravity (tilt errors leak gravity).

Defaults and their sources are documented on :class:`ImuConfig`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import torch
from scipy.ndimage import convolve1d, gaussian_filter1d

from couch.body import JOINT_INDEX, PARENTS, BodyModel
from couch.capture.mvnx import (
    MVN_JOINTS,
    MVN_SEGMENTS,
    MVN_SENSORS,
    MVN_TO_SMPL,
    MvnxMetadata,
    MvnxPose,
    MvnxRecording,
    couch_to_mvn_positions,
    couch_to_mvn_quaternions,
    mvn_rec_date,
    mvn_timecode,
    segment_points_from_pose,
)
from couch.capture.xbus import (
    MAX_DATA_LENGTH,
    STATUS_ORIENTATION_VALID,
    STATUS_RETRANSMITTED,
    STATUS_SELFTEST_OK,
    XbusSample,
    encode_mtdata2,
    parse_stream,
)
from couch.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_quat,
    quat_to_matrix,
    slerp,
)

# Unix ms of 2023-11-14 22:13:20 UTC: an arbitrary, fixed wall-clock start for reproducible files.
DEFAULT_START_UNIX_MS = 1_700_000_000_000
STANDARD_GRAVITY = 9.80665  # m/s², the "g" of datasheets (µg/√Hz)

N_SEG = len(MVN_SEGMENTS)
N_SENS = len(MVN_SENSORS)
_SEG_INDEX = {s: i for i, s in enumerate(MVN_SEGMENTS)}
SENSOR_SEGMENTS = np.array([_SEG_INDEX[s] for s in MVN_SENSORS], dtype=np.int64)
"""(17,) index into MVN_SEGMENTS of the segment each sensor (MVN_SENSORS order) is strapped to."""


def _segment_joints() -> np.ndarray:
    """(23,) SMPL joint giving each MVN segment its orientation and origin (inverse of
    MVN_TO_SMPL, taking the first SMPL joint per segment: LeftHand ← left_wrist); -1 for L3."""
    first: dict[str, int] = {}
    for joint, segment in MVN_TO_SMPL.items():
        first.setdefault(segment, JOINT_INDEX[joint])
    out = np.array([first.get(s, -1) for s in MVN_SEGMENTS], dtype=np.int64)
    assert [MVN_SEGMENTS[i] for i in np.flatnonzero(out < 0)] == ["L3"]
    return out


SEGMENT_JOINTS = _segment_joints()
"""(23,) SMPL joint index per MVN segment (-1 for L3, which lies halfway between spine1 and
spine2: orientation slerp(spine1, spine2, ½), origin the midpoint of the two joints)."""
_L3 = _SEG_INDEX["L3"]
_SPINE1, _SPINE2 = JOINT_INDEX["spine1"], JOINT_INDEX["spine2"]


def _segment_parents() -> np.ndarray:
    parents = np.full(N_SEG, -1, dtype=np.int64)
    for _, c1, c2 in MVN_JOINTS:
        parents[_SEG_INDEX[c2.split("/")[0]]] = _SEG_INDEX[c1.split("/")[0]]
    assert np.all(parents[1:] < np.arange(1, N_SEG)) and parents[0] == -1
    return parents


SEGMENT_PARENTS = _segment_parents()
"""(23,) parent segment in MVN's tree (from MVN_JOINTS' connectors), -1 for the pelvis."""

# Segments without a sensor take the fusion error of the sensor MVN drives them from.
_NOISE_FROM = {"L5": "Pelvis", "L3": "Pelvis", "T12": "T8", "Neck": "T8",
               "RightToe": "RightFoot", "LeftToe": "LeftFoot"}
_SENSOR_INDEX = {s: i for i, s in enumerate(MVN_SENSORS)}
SEGMENT_NOISE_SENSOR = np.array([_SENSOR_INDEX[_NOISE_FROM.get(s, s)] for s in MVN_SEGMENTS],
                                dtype=np.int64)

# Where each sensor sits on its segment: origin joint, distal joint, fraction along the bone and
# an extra offset in the segment's rest frame (our axes: x left, y up, z forward), metres. Real
# MTws sit on flat, little-muscled spots (sacrum, sternum, shoulder blades, lateral thigh, flat
# of the shin, back of hand, top of the foot); the site matters for the accelerometer, which also
# feels the centripetal and tangential acceleration of its lever arm.
_SENSOR_SITES: dict[str, tuple[str, str | None, float, tuple[float, float, float]]] = {
    "Pelvis": ("pelvis", "spine1", 0.5, (0.0, 0.0, -0.10)),
    "T8": ("spine3", "neck", 0.5, (0.0, 0.0, 0.09)),
    "Head": ("head", None, 0.0, (0.0, 0.10, 0.0)),
    "RightShoulder": ("right_collar", "right_shoulder", 0.5, (0.0, 0.02, -0.07)),
    "RightUpperArm": ("right_shoulder", "right_elbow", 0.5, (0.0, 0.0, -0.03)),
    "RightForeArm": ("right_elbow", "right_wrist", 0.7, (0.0, 0.02, 0.0)),
    "RightHand": ("right_wrist", "right_hand", 0.5, (0.0, 0.02, 0.0)),
    "LeftShoulder": ("left_collar", "left_shoulder", 0.5, (0.0, 0.02, -0.07)),
    "LeftUpperArm": ("left_shoulder", "left_elbow", 0.5, (0.0, 0.0, -0.03)),
    "LeftForeArm": ("left_elbow", "left_wrist", 0.7, (0.0, 0.02, 0.0)),
    "LeftHand": ("left_wrist", "left_hand", 0.5, (0.0, 0.02, 0.0)),
    "RightUpperLeg": ("right_hip", "right_knee", 0.5, (-0.07, 0.0, 0.0)),
    "RightLowerLeg": ("right_knee", "right_ankle", 0.4, (0.0, 0.0, 0.05)),
    "RightFoot": ("right_ankle", "right_foot", 0.5, (0.0, 0.04, 0.0)),
    "LeftUpperLeg": ("left_hip", "left_knee", 0.5, (0.07, 0.0, 0.0)),
    "LeftLowerLeg": ("left_knee", "left_ankle", 0.4, (0.0, 0.0, 0.05)),
    "LeftFoot": ("left_ankle", "left_foot", 0.5, (0.0, 0.04, 0.0)),
}

# MVNX footContacts order (FOOT_CONTACTS): LeftFoot_Heel, LeftFoot_Toe, RightFoot_Heel,
# RightFoot_Toe; the heel follows the ankle joint, the toe the SMPL foot (ball) joint.
_CONTACT_JOINTS = np.array([JOINT_INDEX[j] for j in ("left_ankle", "left_foot", "right_ankle",
                                                     "right_foot")], dtype=np.int64)

# Message states in XbusTruth.msg_state
MSG_INTACT, MSG_CORRUPTED, MSG_TRUNCATED, MSG_DROPPED = 0, 1, 2, 3


# --------------------------------------------------------------------------- input


@dataclasses.dataclass
class BodyTrack:
    """Ground-truth body motion on the Kinect clock, our world frame (metres, Y up, floor y = 0).

    time: (N,) float64 seconds on the Kinect clock, strictly increasing (a dense regular grid,
        e.g. 120 Hz, is best: the suit samples it with slerp/linear interpolation).
    joint_rotations: (N, 24, 3, 3) global world-from-joint rotations of the SMPL joints.
    joints: (N, 24, 3) world positions of the SMPL joints.
    betas: (10,) shape coefficients (kept for the record).
    rest_joints: (24, 3) or None: the shaped rest (T-pose) skeleton standing on the floor, pelvis
        above the origin; gives MVN's body dimensions, calibration poses and the feet's resting
        heights for foot contacts. None derives the bone vectors from the first frame and puts
        the lower foot joint at the lowest height the foot joints reach in the track.
    """

    time: np.ndarray
    joint_rotations: np.ndarray
    joints: np.ndarray
    betas: np.ndarray
    rest_joints: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.time = np.asarray(self.time, dtype=np.float64)
        self.joint_rotations = np.asarray(self.joint_rotations, dtype=np.float64)
        self.joints = np.asarray(self.joints, dtype=np.float64)
        self.betas = np.asarray(self.betas, dtype=np.float64)
        n = len(self.time)
        if self.time.shape != (n,) or n < 2 or np.any(np.diff(self.time) <= 0):
            raise ValueError(f"BodyTrack.time must be (N,) strictly increasing with N >= 2, got "
                             f"shape {self.time.shape}")
        if self.joint_rotations.shape != (n, 24, 3, 3):
            raise ValueError(f"BodyTrack.joint_rotations must be ({n}, 24, 3, 3), got "
                             f"{self.joint_rotations.shape}")
        if self.joints.shape != (n, 24, 3):
            raise ValueError(f"BodyTrack.joints must be ({n}, 24, 3), got {self.joints.shape}")
        if self.rest_joints is not None:
            self.rest_joints = np.asarray(self.rest_joints, dtype=np.float64)
            if self.rest_joints.shape != (24, 3):
                raise ValueError(f"BodyTrack.rest_joints must be (24, 3), got "
                                 f"{self.rest_joints.shape}")

    def rest_skeleton(self) -> np.ndarray:
        """(24, 3) rest joints standing on the floor, pelvis above the origin (see rest_joints)."""
        if self.rest_joints is not None:
            return self.rest_joints
        rot0, j0 = self.joint_rotations[0], self.joints[0]
        rest = np.zeros((24, 3))
        for j in range(1, 24):
            p = PARENTS[j]
            rest[j] = rest[p] + rot0[p].T @ (j0[j] - j0[p])  # SMPL bones are rigid
        feet = [JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]]
        rest[:, 1] += self.joints[:, feet, 1].min() - rest[feet, 1].min()
        return rest


def body_track_from_model(model: BodyModel, time: Any, global_orient: Any, body_pose: Any,
                          transl: Any, betas: Any, *, chunk: int = 1024) -> BodyTrack:
    """Run the body model over a motion and fill a :class:`BodyTrack`.

    Args:
        model: an SMPL-format body model (``couch.body.load_body_model``).
        time: (N,) Kinect-clock seconds.
        global_orient: (N, 3) axis-angle or (N, 3, 3); body_pose: (N, 69) / (N, 23, 3) axis-angle
            or (N, 23, 3, 3); transl: (N, 3) metres; betas: (K,) with K <= model.num_betas.
        chunk: frames per batched model call (bounds memory for long motions).
    The rest skeleton is shifted so that the rest mesh's lowest vertex is on the floor (y = 0)
    and the rest pelvis is above the origin.
    """
    time = np.asarray(time, dtype=np.float64)
    n = len(time)
    betas_row = np.asarray(betas, dtype=np.float64).reshape(1, -1)
    rots, joints = [], []
    with torch.no_grad():
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            jts, transforms = model.skeleton(
                betas=betas_row, global_orient=np.asarray(global_orient)[s:e],
                body_pose=np.asarray(body_pose)[s:e], transl=np.asarray(transl)[s:e])
            rots.append(transforms[..., :3, :3].double().cpu().numpy())
            joints.append(jts.double().cpu().numpy())
        rest = model(betas=betas_row)
    rest_joints = rest.joints[0].double().cpu().numpy()
    floor = float(rest.vertices[0, :, 1].min())
    rest_joints = rest_joints - np.array([rest_joints[0, 0], floor, rest_joints[0, 2]])
    padded = np.zeros(max(10, betas_row.shape[1]))
    padded[:betas_row.shape[1]] = betas_row[0]
    # Re-orthonormalise the float32 model's rotations (a quaternion round trip), so that angles
    # between them are meaningful down to ~1e-8 rad.
    rotations = quat_to_matrix(matrix_to_quat(np.concatenate(rots)))
    return BodyTrack(time=time, joint_rotations=rotations, joints=np.concatenate(joints),
                     betas=padded, rest_joints=rest_joints)


# --------------------------------------------------------------------------- configuration


@dataclasses.dataclass
class ImuConfig:
    """The suit's behaviour; defaults are those of a real MVN Awinda suit (sources per field).

    Datasheet numbers are those of the MTw Awinda user manual (Xsens MW0502P, "sensor
    specifications") as remembered, not re-checked here: gyro noise density 0.01 °/s/√Hz, in-run
    bias stability 10 °/h; accelerometer noise density 200 µg/√Hz; orientation accuracy roll/pitch
    0.5° (static) / 0.75° RMS (dynamic), heading 1° / 1.5° RMS. Values marked *assumption* are
    plausible magnitudes chosen for the simulator, not measured.
    """

    frame_rate: float = 60.0
    """Hz. MVN Awinda's full-body (17 MTw) rate is 60 Hz."""

    # -- clock: t_imu = (1 + drift_ppm·1e-6) · t_kinect + clock_offset
    drift_ppm: float = 40.0
    """Rate difference of the IMU clock vs the Kinect clock, ppm (> 0: the IMU clock runs fast).
    Quartz oscillators are specified at ±(20–50) ppm each, so two free-running devices differ by
    tens of ppm."""
    clock_offset: float | None = None
    """s: the IMU clock's reading at Kinect time 0. None: chosen so that the recording starts
    ``start_delay`` s (Kinect clock) after the track's first time."""
    start_delay: float = 0.5
    """s, used when clock_offset is None (*assumption*: the IMU recording starts shortly after the
    cameras')."""

    # -- heading of MVN's global frame relative to ours
    heading_offset_deg: float | None = None
    """Constant heading of MVN's frame (MVN resets heading to the subject's facing at
    calibration, which is arbitrary in our room). None: uniform in [-180°, 180°)."""
    heading_drift_deg_per_min: float = 2.0
    """Linear heading drift, °/min (*assumption*: MVN without a clean magnetic field drifts in
    heading by a few degrees per minute)."""
    heading_walk_deg_per_sqrt_min: float = 1.0
    """Random-walk heading drift: rms after one minute, ° (*assumption*), smoothed over
    ``drift_smoothing_s``."""
    earth_heading_deg: float | None = None
    """Heading of the Xbus earth frame E relative to MVN's frame; None: uniform."""

    # -- placement and calibration
    misalignment_deg: float = 3.0
    """RMS angle of the constant per-segment sensor-to-segment calibration error (random axis;
    *assumption*: N/T-pose calibrations leave errors of a few degrees)."""
    mount_deg: float = 20.0
    """RMS angle of the random true placement of each sensor on its segment (straps sit where
    they sit; the calibration measures this, up to ``misalignment_deg``)."""

    # -- orientation error of the fusion filter (smooth, correlated, not white)
    tilt_noise_deg: float = 0.5
    """RMS tilt (roll/pitch) error of each sensor's orientation (MTw static spec 0.5°)."""
    heading_noise_deg: float = 1.0
    """RMS heading error of each sensor's orientation on top of the common drift (MTw static
    heading spec 1°)."""
    noise_corr_time: float = 1.0
    """s: the orientation error's autocorrelation is exp(-(Δt/τ)²) (*assumption*: Kalman-filtered
    errors wander on a ~second scale)."""

    # -- position
    position_walk_m_per_sqrt_min: float = 0.03
    """RMS horizontal pelvis drift after one minute, m (*assumption*: MVN integrates position
    through foot contacts and drifts by a few cm per minute of motion)."""
    vertical_bias_std: float = 0.01
    """m: std of the constant vertical offset of MVN's body (body-dimension errors)."""
    drift_smoothing_s: float = 1.0
    """s: Gaussian smoothing of the heading and position random walks (MVN's drifts are smooth)."""
    recenter: bool = True
    """MVN's position origin is the pelvis's floor projection at the first sample (as after
    calibration); False keeps our world origin."""

    # -- inertial sensors
    gravity: float = 9.81
    """m/s², local gravity magnitude."""
    acc_noise_density: float = 200e-6 * STANDARD_GRAVITY
    """m/s²/√Hz (MTw: 200 µg/√Hz). White noise of std density·√(rate/2) per output sample
    (the output is an average over the sample interval, from MTw's strapdown integration)."""
    gyro_noise_density: float = math.radians(0.01)
    """rad/s/√Hz (MTw: 0.01 °/s/√Hz)."""
    acc_bias_std: float = 0.02
    """m/s², per-axis std of each sensor's constant accelerometer bias (*assumption*: ~2 mg
    residual after factory calibration)."""
    gyro_bias_std: float = math.radians(0.1)
    """rad/s, per-axis std of each sensor's constant gyro bias (*assumption*: 0.1 °/s residual
    turn-on bias; the in-run stability of 10 °/h is far smaller)."""

    # -- foot contacts (MVN's contact detection, approximated from the true motion)
    contact_height: float = 0.03
    """m above the joint's resting height (rest skeleton) for a heel/toe contact."""
    contact_speed: float = 0.25
    """m/s: maximum horizontal speed of the heel/toe joint in contact."""

    # -- Xbus stream
    corrupt_rate: float = 2e-4
    """Fraction of messages with 1–3 corrupted bytes (never the preamble, BID or LEN, so each
    damaged message is one checksum failure for a parser)."""
    truncate_rate: float = 1e-4
    """Fraction of messages cut short (the rest of the stream follows directly)."""
    drop_rate: float = 5e-4
    """Fraction of messages lost entirely (*assumption*; Awinda's radio loses a few packets)."""
    retransmit_rate: float = 2e-3
    """Fraction of samples that arrive late, retransmitted (StatusWord bit 18 set) after up to
    ``retransmit_max_delay`` later samples."""
    retransmit_max_delay: int = 6
    sample_time_fine_start: int | None = None
    """SampleTimeFine at t_imu = 0 (10 kHz ticks); None: random (device uptime)."""
    packet_counter_start: int | None = None
    """PacketCounter of sample 0; None: random."""

    @classmethod
    def perfect(cls, **overrides: Any) -> ImuConfig:
        """No error at all: clocks equal (IMU time 0 = the track's first time), MVN frame = our
        world axis-permuted (no heading, no recentering), no misalignment, placement, noise,
        drift, bias or stream damage. Keyword overrides switch single errors back on."""
        zero = dict(drift_ppm=0.0, clock_offset=None, start_delay=0.0, heading_offset_deg=0.0,
                    heading_drift_deg_per_min=0.0, heading_walk_deg_per_sqrt_min=0.0,
                    earth_heading_deg=0.0, misalignment_deg=0.0, mount_deg=0.0,
                    tilt_noise_deg=0.0, heading_noise_deg=0.0, position_walk_m_per_sqrt_min=0.0,
                    vertical_bias_std=0.0, recenter=False, acc_noise_density=0.0,
                    gyro_noise_density=0.0, acc_bias_std=0.0, gyro_bias_std=0.0,
                    corrupt_rate=0.0, truncate_rate=0.0, drop_rate=0.0, retransmit_rate=0.0)
        zero.update(overrides)
        return cls(**zero)


# --------------------------------------------------------------------------- truth


@dataclasses.dataclass
class ImuTruth:
    """Everything :func:`simulate_mvnx` injected. K samples; frames as in the module docstring.

    Clock: ``t_imu = clock_scale · t_kinect + clock_offset`` (s), clock_scale = 1 + drift_ppm·1e-6.
    imu_time (K,) = k / frame_rate; kinect_time (K,) their Kinect times; in_track (K,) False where
    the pose was held because the sample maps before the track's start.

    heading_offset (rad) and heading_drift (K,) rad: ψ(t) = heading_offset + heading_drift, with
    v_mvn = Rz(ψ)ᵀ v in MVN axes. earth_heading (rad): the Xbus frame E is MVN's frame turned by
    it about Z. origin (3,): MVN's position origin in MVN axes before the heading (metres).
    misalignment (23, 4): M_seg quaternions (w, x, y, z; segment frame, MVN axes); mount (17, 4):
    true sensor-on-segment rotations; orientation_noise (K, 17, 4): N_s(t) (global frame).
    position_drift (K, 3): the random-walk drift plus vertical bias added to MVN's pelvis position
    (MVN frame; the heading drift bends the pelvis path on top of it, see the module docstring);
    vertical_bias (m). acc_bias (17, 3) m/s², gyro_bias (17, 3) rad/s (sensor frames).

    orientation_ideal (K, 23, 4) / position_ideal (K, 23, 3): the exact segment orientations and
    origins in MVN's frame with only the constant heading offset and origin applied (no drift,
    misalignment or noise); sensor_orientation_ideal (K, 17, 4) likewise R_seg·mount_s.
    orientation, position, sensor_orientation (full precision) and foot_contacts (K, 4) are
    exactly what was exported (the file rounds to 6 decimals).
    """

    frame_rate: float
    clock_scale: float
    clock_offset: float
    drift_ppm: float
    start_unix_ms: int
    imu_time: np.ndarray
    kinect_time: np.ndarray
    in_track: np.ndarray
    heading_offset: float
    heading_drift: np.ndarray
    earth_heading: float
    origin: np.ndarray
    misalignment: np.ndarray
    mount: np.ndarray
    orientation_noise: np.ndarray
    position_drift: np.ndarray
    vertical_bias: float
    acc_bias: np.ndarray
    gyro_bias: np.ndarray
    orientation_ideal: np.ndarray
    position_ideal: np.ndarray
    sensor_orientation_ideal: np.ndarray
    orientation: np.ndarray
    position: np.ndarray
    sensor_orientation: np.ndarray
    foot_contacts: np.ndarray

    @property
    def heading(self) -> np.ndarray:
        """(K,) ψ(t) in radians."""
        return self.heading_offset + self.heading_drift

    def kinect_to_imu(self, t: np.ndarray | float) -> np.ndarray:
        """Kinect-clock seconds → IMU-clock seconds."""
        return self.clock_scale * np.asarray(t, dtype=np.float64) + self.clock_offset

    def imu_to_kinect(self, t: np.ndarray | float) -> np.ndarray:
        """IMU-clock seconds → Kinect-clock seconds."""
        return (np.asarray(t, dtype=np.float64) - self.clock_offset) / self.clock_scale


@dataclasses.dataclass
class XbusTruth:
    """Everything :func:`simulate_xbus` injected and wrote. K samples × 17 sensors = M messages.

    Clock as :class:`ImuTruth`: imu_time, kinect_time (K,); sample_time_fine (K,) and
    packet_counter (K,) as encoded (wrapped). device_ids (17,) in MVN_SENSORS order.
    Frame E: v_E = Rz(earth_heading)ᵀ Rz(ψ(t))ᵀ v (MVN axes), ψ = heading_offset + heading_drift.
    quaternion (K, 17, 4) sensor → E; acceleration (K, 17, 3) specific force in the sensor frame;
    free_acceleration (K, 17, 3) in E; rate_of_turn (K, 17, 3) rad/s sensor frame; status_word
    (K, 17): the float64 values before the float32 encoding. quaternion_ideal (K, 17, 4): sensor
    orientations in E with only the constant headings (no drift, no noise).
    mount, orientation_noise, acc_bias, gyro_bias as in :class:`ImuTruth`.

    Messages, in stream order (M,): msg_sample, msg_sensor (indices), msg_state (MSG_INTACT,
    MSG_CORRUPTED, MSG_TRUNCATED, MSG_DROPPED), msg_offset (byte offset of the preamble in the
    stream, -1 if dropped), msg_length (bytes written; 0 if dropped), retransmitted (bool: arrived
    late, StatusWord bit 18 set).
    """

    frame_rate: float
    clock_scale: float
    clock_offset: float
    drift_ppm: float
    imu_time: np.ndarray
    kinect_time: np.ndarray
    in_track: np.ndarray
    sample_time_fine: np.ndarray
    packet_counter: np.ndarray
    device_ids: np.ndarray
    heading_offset: float
    heading_drift: np.ndarray
    earth_heading: float
    mount: np.ndarray
    orientation_noise: np.ndarray
    acc_bias: np.ndarray
    gyro_bias: np.ndarray
    quaternion: np.ndarray
    quaternion_ideal: np.ndarray
    acceleration: np.ndarray
    free_acceleration: np.ndarray
    rate_of_turn: np.ndarray
    status_word: np.ndarray
    msg_sample: np.ndarray
    msg_sensor: np.ndarray
    msg_state: np.ndarray
    msg_offset: np.ndarray
    msg_length: np.ndarray
    retransmitted: np.ndarray

    @property
    def intact(self) -> np.ndarray:
        """(M,) bool: messages a parser must recover."""
        return self.msg_state == MSG_INTACT

    @property
    def damaged(self) -> np.ndarray:
        """(M,) bool: messages present in the stream but corrupted or truncated (each one is one
        rejected message for :class:`couch.capture.xbus.XbusParser`)."""
        return (self.msg_state == MSG_CORRUPTED) | (self.msg_state == MSG_TRUNCATED)

    @property
    def dropped(self) -> np.ndarray:
        """(M,) bool: messages that never reached the stream."""
        return self.msg_state == MSG_DROPPED


# --------------------------------------------------------------------------- math helpers


def _rz(angle: np.ndarray | float) -> np.ndarray:
    """(..., 3, 3) rotation about +Z by ``angle`` radians."""
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    out = np.zeros((*a.shape, 3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = c, -s, s, c
    out[..., 2, 2] = 1.0
    return out


def _apply(rot: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R · v for (..., 3, 3) and (..., 3)."""
    return np.einsum("...ij,...j->...i", rot, v)


def _apply_t(rot: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rᵀ · v for (..., 3, 3) and (..., 3)."""
    return np.einsum("...ji,...j->...i", rot, v)


def _random_rotations(rng: np.random.Generator, shape: tuple[int, ...],
                      rms_deg: float) -> np.ndarray:
    """(*shape, 3, 3) rotations about uniformly random axes with RMS angle ``rms_deg``
    (rotation vector ~ N(0, (rms/√3)² I)). Always draws, so the stream of draws is fixed."""
    rv = rng.standard_normal((*shape, 3)) * (math.radians(rms_deg) / math.sqrt(3.0))
    return axis_angle_to_matrix(rv)


def smooth_noise(rng: np.random.Generator, n: int, shape: tuple[int, ...],
                 corr_samples: float) -> np.ndarray:
    """(n, *shape) stationary Gaussian noise, unit variance, autocorrelation exp(-(Δ/τ)²) with
    τ = ``corr_samples`` samples (white if τ <= 0): white noise convolved with a Gaussian kernel
    of std τ/2, scaled by the kernel's exact energy so the variance is 1 everywhere."""
    width = int(np.prod(shape)) if shape else 1
    if corr_samples <= 0:
        return rng.standard_normal((n, *shape))
    sigma = corr_samples / 2.0
    half = math.ceil(4.0 * sigma)
    x = np.arange(-half, half + 1, dtype=np.float64)
    kernel = np.exp(-0.5 * (x / sigma) ** 2)
    kernel /= math.sqrt(float(np.sum(kernel**2)))
    white = rng.standard_normal((n + 2 * half, width))
    out = convolve1d(white, kernel, axis=0, mode="constant")[half:half + n]
    return out.reshape((n, *shape))


def smooth_random_walk(rng: np.random.Generator, n: int, dims: int, dt: float,
                       sigma_per_sqrt_s: float, smoothing_s: float) -> np.ndarray:
    """(n, dims) random walk starting at 0 with per-axis std ``sigma_per_sqrt_s``·√t, Gaussian-
    smoothed over ``smoothing_s`` seconds so that its derivatives stay small (drifts of a fusion
    filter are smooth). Always draws n·dims normals."""
    steps = rng.standard_normal((n, dims)) * (sigma_per_sqrt_s * math.sqrt(dt))
    steps[0] = 0.0
    walk = np.cumsum(steps, axis=0)
    if smoothing_s > 0 and n > 1:
        walk = gaussian_filter1d(walk, sigma=smoothing_s / dt, axis=0, mode="nearest")
    return walk - walk[:1]


def _angular_rate(rot: np.ndarray, dt: float, frame: str) -> np.ndarray:
    """(K, ..., 3) angular velocity of (K, ..., 3, 3) rotations sampled every ``dt`` s by central
    differences (one-sided at the ends): ``body`` = in the rotating frame, ``global`` = in the
    fixed frame (rad/s)."""
    k = len(rot)
    prev = np.maximum(np.arange(k) - 1, 0)
    nxt = np.minimum(np.arange(k) + 1, k - 1)
    span = ((nxt - prev) * dt).reshape((k,) + (1,) * (rot.ndim - 2))
    a, b = rot[prev], rot[nxt]
    rel = np.swapaxes(a, -1, -2) @ b if frame == "body" else b @ np.swapaxes(a, -1, -2)
    return matrix_to_axis_angle(rel) / span


def _second_difference(p: np.ndarray, dt: float) -> np.ndarray:
    """(K, ...) second time derivative by central differences (copied at the ends)."""
    out = np.zeros_like(p)
    if len(p) >= 3:
        out[1:-1] = (p[2:] - 2.0 * p[1:-1] + p[:-2]) / (dt * dt)
        out[0], out[-1] = out[1], out[-2]
    return out


def _interpolate_track(track: BodyTrack, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joint quaternions (K, 24, 4) (slerp) and positions (K, 24, 3) (linear) at Kinect times t
    (clamped to the track)."""
    time = track.time
    tq = np.clip(t, time[0], time[-1])
    idx = np.clip(np.searchsorted(time, tq, side="right") - 1, 0, len(time) - 2)
    frac = np.clip((tq - time[idx]) / (time[idx + 1] - time[idx]), 0.0, 1.0)
    quats = matrix_to_quat(track.joint_rotations)
    q = slerp(quats[idx], quats[idx + 1], np.broadcast_to(frac[:, None], (len(t), 24)))
    p = track.joints[idx] + frac[:, None, None] * (track.joints[idx + 1] - track.joints[idx])
    return q, p


def _segments_from_joints(joint_quats_mvn: np.ndarray, joint_pos_mvn: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """SMPL joints (…, 24, 4) / (…, 24, 3) in MVN axes → MVN segments (…, 23, 4) / (…, 23, 3)."""
    src = np.where(SEGMENT_JOINTS < 0, 0, SEGMENT_JOINTS)
    q = joint_quats_mvn[..., src, :].copy()
    p = joint_pos_mvn[..., src, :].copy()
    q[..., _L3, :] = slerp(joint_quats_mvn[..., _SPINE1, :], joint_quats_mvn[..., _SPINE2, :], 0.5)
    p[..., _L3, :] = 0.5 * (joint_pos_mvn[..., _SPINE1, :] + joint_pos_mvn[..., _SPINE2, :])
    return q, p


# --------------------------------------------------------------------------- the shared core


@dataclasses.dataclass
class _Draws:
    """Every random quantity of one session, drawn in a fixed order."""

    heading_offset: float
    earth_heading: float
    misalignment: np.ndarray  # (23, 3, 3)
    mount: np.ndarray  # (17, 3, 3)
    heading_drift: np.ndarray  # (K,)
    noise: np.ndarray  # (K, 17, 3, 3)
    position_walk: np.ndarray  # (K, 2)
    vertical_bias: float
    acc_bias: np.ndarray  # (17, 3)
    gyro_bias: np.ndarray  # (17, 3)
    acc_noise: np.ndarray  # (K, 17, 3)
    gyro_noise: np.ndarray  # (K, 17, 3)
    device_ids: np.ndarray  # (17,)
    stf0: int
    pc0: int


def _draw(config: ImuConfig, rng: np.random.Generator, k: int, imu_time: np.ndarray) -> _Draws:
    dt = 1.0 / config.frame_rate
    heading = rng.uniform(-math.pi, math.pi)
    if config.heading_offset_deg is not None:
        heading = math.radians(config.heading_offset_deg)
    earth = rng.uniform(-math.pi, math.pi)
    if config.earth_heading_deg is not None:
        earth = math.radians(config.earth_heading_deg)
    misalignment = _random_rotations(rng, (N_SEG,), config.misalignment_deg)
    mount = _random_rotations(rng, (N_SENS,), config.mount_deg)
    walk = smooth_random_walk(rng, k, 1, dt,
                              math.radians(config.heading_walk_deg_per_sqrt_min) / math.sqrt(60),
                              config.drift_smoothing_s)[:, 0]
    heading_drift = math.radians(config.heading_drift_deg_per_min) * imu_time / 60.0 + walk
    rv = smooth_noise(rng, k, (N_SENS, 3), config.noise_corr_time * config.frame_rate)
    # tilt about the two horizontal axes (rms over both = tilt_noise_deg), heading about Z
    rv = rv * np.array([math.radians(config.tilt_noise_deg) / math.sqrt(2.0)] * 2
                       + [math.radians(config.heading_noise_deg)])
    noise = axis_angle_to_matrix(rv)
    position_walk = smooth_random_walk(rng, k, 2, dt, config.position_walk_m_per_sqrt_min
                                       / math.sqrt(2.0) / math.sqrt(60.0),
                                       config.drift_smoothing_s)
    vertical_bias = float(rng.standard_normal() * config.vertical_bias_std)
    acc_bias = rng.standard_normal((N_SENS, 3)) * config.acc_bias_std
    gyro_bias = rng.standard_normal((N_SENS, 3)) * config.gyro_bias_std
    bandwidth = math.sqrt(config.frame_rate / 2.0)
    acc_noise = rng.standard_normal((k, N_SENS, 3)) * (config.acc_noise_density * bandwidth)
    gyro_noise = rng.standard_normal((k, N_SENS, 3)) * (config.gyro_noise_density * bandwidth)
    # MTw DeviceIds read 00B4xxxx in MT Manager; 17 distinct low halves
    device_ids = 0x00B40000 + rng.choice(0x10000, size=N_SENS, replace=False).astype(np.int64)
    stf0 = int(rng.integers(0, 2**32))
    pc0 = int(rng.integers(0, 2**16))
    if config.sample_time_fine_start is not None:
        stf0 = int(config.sample_time_fine_start) % 2**32
    if config.packet_counter_start is not None:
        pc0 = int(config.packet_counter_start) % 2**16
    return _Draws(heading, earth, misalignment, mount, heading_drift, noise, position_walk,
                  vertical_bias, acc_bias, gyro_bias, acc_noise, gyro_noise, device_ids, stf0,
                  pc0)


@dataclasses.dataclass
class _Session:
    """What both outputs derive from (MVN axes, float64)."""

    config: ImuConfig
    draws: _Draws
    clock_scale: float
    clock_offset: float
    imu_time: np.ndarray  # (K,)
    kinect_time: np.ndarray
    in_track: np.ndarray
    seg_rot: np.ndarray  # (K, 23, 3, 3) true, MVN axes, our heading
    seg_pos: np.ndarray  # (K, 23, 3) true, MVN axes, our origin
    heading_rot: np.ndarray  # (K, 3, 3) Rz(ψ(t))ᵀ
    sensor_rot_true: np.ndarray  # (K, 17, 3, 3) R_seg · mount, MVN axes, our heading
    sensor_rot_rep: np.ndarray  # (K, 17, 3, 3) reported, MVN frame
    acc_meas: np.ndarray  # (K, 17, 3) sensor frame
    gyro_meas: np.ndarray  # (K, 17, 3) sensor frame
    free_acc_mvn: np.ndarray  # (K, 17, 3) MVN frame
    joint_pos: np.ndarray  # (K, 24, 3) our world


def _clock(track: BodyTrack, config: ImuConfig) -> tuple[float, float, np.ndarray]:
    if not config.frame_rate > 0:
        raise ValueError(f"frame_rate must be positive, got {config.frame_rate}")
    scale = 1.0 + config.drift_ppm * 1e-6
    offset = (config.clock_offset if config.clock_offset is not None
              else -scale * (track.time[0] + config.start_delay))
    end = scale * track.time[-1] + offset  # IMU time of the track's last instant
    k = math.floor(end * config.frame_rate + 1e-9) + 1
    if k < 3:
        raise ValueError(f"the IMU recording would hold {max(k, 0)} samples: the track "
                         f"({track.time[0]:.3f}..{track.time[-1]:.3f} s Kinect) ends before IMU "
                         f"time {2 / config.frame_rate:.3f} s (clock_offset {offset:.3f} s)")
    return scale, float(offset), np.arange(k, dtype=np.float64) / config.frame_rate


def _simulate(track: BodyTrack, config: ImuConfig, rng: np.random.Generator) -> _Session:
    scale, offset, imu_time = _clock(track, config)
    k = len(imu_time)
    dt = 1.0 / config.frame_rate
    kinect_time = (imu_time - offset) / scale
    in_track = kinect_time >= track.time[0] - 1e-9
    draws = _draw(config, rng, k, imu_time)

    joint_q, joint_p = _interpolate_track(track, kinect_time)
    seg_q, seg_p = _segments_from_joints(couch_to_mvn_quaternions(joint_q),
                                         couch_to_mvn_positions(joint_p))
    seg_rot = quat_to_matrix(seg_q)

    heading_rot = _rz(-(draws.heading_offset + draws.heading_drift))  # Rz(ψ)ᵀ
    sensor_seg = seg_rot[:, SENSOR_SEGMENTS]
    sensor_true = sensor_seg @ draws.mount
    sensor_rep = draws.noise @ heading_rot[:, None] @ sensor_true

    # Accelerometer: specific force of the sensor's site in the true sensor frame.
    rest = track.rest_skeleton()
    sites = np.empty((k, N_SENS, 3))
    for s, name in enumerate(MVN_SENSORS):
        origin, distal, frac, extra = _SENSOR_SITES[name]
        j = JOINT_INDEX[origin]
        off = np.asarray(extra, dtype=np.float64)
        if distal is not None:
            off = off + frac * (rest[JOINT_INDEX[distal]] - rest[j])
        rot_j = quat_to_matrix(joint_q[:, j])
        sites[:, s] = joint_p[:, j] + _apply(rot_j, off)
    sites_mvn = couch_to_mvn_positions(sites)
    accel = _second_difference(sites_mvn, dt)
    gravity = np.array([0.0, 0.0, -config.gravity])
    specific = _apply_t(sensor_true, accel - gravity)
    rate = _angular_rate(sensor_true, dt, "body")
    acc_meas = specific + draws.acc_bias + draws.acc_noise
    gyro_meas = rate + draws.gyro_bias + draws.gyro_noise
    free_acc = _apply(sensor_rep, acc_meas) + gravity
    return _Session(config, draws, scale, offset, imu_time, kinect_time, in_track, seg_rot, seg_p,
                    heading_rot, sensor_true, sensor_rep, acc_meas, gyro_meas, free_acc, joint_p)


# --------------------------------------------------------------------------- MVNX


def _foot_contacts(sess: _Session, rest: np.ndarray) -> np.ndarray:
    """(K, 4) bool in FOOT_CONTACTS order: heel/toe joint within contact_height of its resting
    height and slower than contact_speed horizontally (true motion, our world)."""
    cfg = sess.config
    p = sess.joint_pos[:, _CONTACT_JOINTS]  # (K, 4, 3)
    k = len(p)
    prev = np.maximum(np.arange(k) - 1, 0)
    nxt = np.minimum(np.arange(k) + 1, k - 1)
    span = ((nxt - prev) / cfg.frame_rate)[:, None]
    d = p[nxt] - p[prev]
    speed = np.hypot(d[..., 0], d[..., 2]) / np.maximum(span, 1e-12)
    low = p[..., 1] - rest[_CONTACT_JOINTS, 1] < cfg.contact_height
    return low & (speed < cfg.contact_speed)


def simulate_mvnx(track: BodyTrack, config: ImuConfig, rng: np.random.Generator, *,
                  start_unix_ms: int = DEFAULT_START_UNIX_MS) -> tuple[MvnxRecording, ImuTruth]:
    """What MVN Analyze would export for ``track``: a FullBody MvnxRecording at
    ``config.frame_rate`` on the IMU clock, and the truth of every error injected.

    Frames (normal): orientation (K, 23, 4) and position (K, 23, 3) of the 23 segments in MVN's
    drifting global frame; velocity and acceleration (finite differences of the exported
    positions, m/s, m/s²), angularVelocity and angularAcceleration (of the exported orientations,
    global frame, rad/s, rad/s²); footContacts (K, 4); sensorOrientation (K, 17, 4) and
    sensorFreeAcceleration (K, 17, 3). Calibration frames ``identity`` and ``tpose``: identity
    orientations and the rest skeleton's segment origins (pelvis above the origin, floor z = 0);
    segment points from the identity pose. time/ms/tc: see the module docstring;
    ``start_unix_ms`` is the Unix ms of IMU time 0. The segment ↔ SMPL mapping is the inverse of
    formats.md's table (L3 halfway between spine1 and spine2; Toe ← SMPL foot).
    """
    sess = _simulate(track, config, rng)
    d, cfg = sess.draws, config
    k = len(sess.imu_time)
    dt = 1.0 / cfg.frame_rate
    rest = track.rest_skeleton()

    # Segment orientations: heading, fusion error of the driving sensor, calibration error.
    noise_seg = d.noise[:, SEGMENT_NOISE_SENSOR]
    seg_rep = noise_seg @ sess.heading_rot[:, None] @ sess.seg_rot @ d.misalignment

    # MVN's origin: where the pelvis stood at the first sample, on the floor.
    origin = np.zeros(3)
    if cfg.recenter:
        origin[:2] = sess.seg_pos[0, 0, :2]
    ideal_rot = _rz(-d.heading_offset)
    position_ideal = _apply(ideal_rot, sess.seg_pos - origin)
    orientation_ideal = ideal_rot @ sess.seg_rot

    # Pelvis: the horizontal path integrated in the drifting heading frame, plus drift and bias.
    step = np.diff(sess.seg_pos[:, 0], axis=0)
    psi = d.heading_offset + d.heading_drift
    mid_rot = _rz(-0.5 * (psi[1:] + psi[:-1]))
    pelvis = np.empty((k, 3))
    pelvis[0] = position_ideal[0, 0]
    pelvis[1:] = pelvis[0] + np.cumsum(_apply(mid_rot, step), axis=0)
    drift = np.zeros((k, 3))
    drift[:, :2] = d.position_walk
    drift[:, 2] = d.vertical_bias
    position = np.empty((k, N_SEG, 3))
    position[:, 0] = pelvis + drift
    # The rest by forward kinematics with the reported orientations and true bone vectors.
    for s in range(1, N_SEG):
        p = SEGMENT_PARENTS[s]
        bone = _apply_t(sess.seg_rot[:, p], sess.seg_pos[:, s] - sess.seg_pos[:, p])
        position[:, s] = position[:, p] + _apply(seg_rep[:, p], bone)

    velocity = np.gradient(position, dt, axis=0)
    acceleration = np.gradient(velocity, dt, axis=0)
    angular_velocity = _angular_rate(seg_rep, dt, "global")
    angular_acceleration = np.gradient(angular_velocity, dt, axis=0)
    contacts = _foot_contacts(sess, rest)

    orientation = matrix_to_quat(seg_rep)
    sensor_orientation = matrix_to_quat(sess.sensor_rot_rep)
    time_ms = np.round(sess.imu_time * 1000.0).astype(np.int64)
    unix_ms = int(start_unix_ms) + time_ms

    _, rest_seg = _segments_from_joints(np.tile([1.0, 0, 0, 0], (24, 1)),
                                        couch_to_mvn_positions(rest))
    identity = MvnxPose(np.tile([1.0, 0.0, 0.0, 0.0], (N_SEG, 1)), rest_seg)
    tpose = MvnxPose(identity.orientation.copy(), rest_seg.copy())
    rec = MvnxRecording(
        frame_rate=float(cfg.frame_rate),
        segment_labels=list(MVN_SEGMENTS),
        sensor_labels=list(MVN_SENSORS),
        time_ms=time_ms,
        unix_ms=unix_ms,
        timecode=mvn_timecode(unix_ms, cfg.frame_rate),
        orientation=orientation,
        position=position,
        frame_index=np.arange(k, dtype=np.int64),
        velocity=velocity,
        acceleration=acceleration,
        angular_velocity=angular_velocity,
        angular_acceleration=angular_acceleration,
        foot_contacts=contacts,
        sensor_free_acceleration=sess.free_acc_mvn,
        sensor_orientation=sensor_orientation,
        calibration={"identity": identity, "tpose": tpose},
        segment_points=segment_points_from_pose(identity, MVN_SEGMENTS),
        metadata=MvnxMetadata(rec_date=mvn_rec_date(int(start_unix_ms)),
                              original_filename="couch-simulated.mvn",
                              comment="simulated by couch.tools.sim.imu"),
    )
    truth = ImuTruth(
        frame_rate=float(cfg.frame_rate), clock_scale=sess.clock_scale,
        clock_offset=sess.clock_offset, drift_ppm=float(cfg.drift_ppm),
        start_unix_ms=int(start_unix_ms), imu_time=sess.imu_time,
        kinect_time=sess.kinect_time, in_track=sess.in_track,
        heading_offset=d.heading_offset, heading_drift=d.heading_drift,
        earth_heading=d.earth_heading, origin=origin,
        misalignment=matrix_to_quat(d.misalignment), mount=matrix_to_quat(d.mount),
        orientation_noise=matrix_to_quat(d.noise), position_drift=drift,
        vertical_bias=d.vertical_bias, acc_bias=d.acc_bias, gyro_bias=d.gyro_bias,
        orientation_ideal=matrix_to_quat(orientation_ideal), position_ideal=position_ideal,
        sensor_orientation_ideal=matrix_to_quat(ideal_rot @ sess.sensor_rot_true),
        orientation=orientation, position=position, sensor_orientation=sensor_orientation,
        foot_contacts=contacts,
    )
    return rec, truth


# --------------------------------------------------------------------------- Xbus


def _damage(message: bytes, state: int, rng: np.random.Generator) -> bytes:
    """A corrupted or truncated copy of one encoded (standard-length) message."""
    n = len(message)
    if state == MSG_TRUNCATED:
        # Keep at least preamble, BID, MID and LEN so a parser sees the start of a message.
        return message[:int(rng.integers(4, n))]
    out = bytearray(message)
    # Never the preamble, BID or LEN: the damage stays one candidate of the right length.
    allowed = np.r_[2, 4:n]
    where = rng.choice(allowed, size=int(rng.integers(1, 4)), replace=False)
    for pos in where:
        out[pos] = (out[pos] + int(rng.integers(1, 256))) & 0xFF
    if (sum(out) - sum(message)) % 256 == 0:  # the changes cancelled in the checksum sum
        out[where[0]] = (out[where[0]] + 1) & 0xFF
    return bytes(out)


def _check_windows(stream: bytes, offsets: np.ndarray, lengths: np.ndarray, states: np.ndarray
                   ) -> list[tuple[int, int]]:
    """Parse the stream around every damaged message and return the (first, last+1) emitted-
    message ranges where the parser does not recover exactly the intact messages and count
    exactly one error per damaged one (a damaged message that by chance forms a valid one)."""
    bad: list[tuple[int, int]] = []
    damaged = np.flatnonzero(states != MSG_INTACT)
    if not len(damaged):
        return bad
    ends = offsets + lengths
    i = 0
    while i < len(damaged):
        first = damaged[i]
        # The parser's state is clean after an intact message; a false start inside damage can
        # reach at most MAX_DATA_LENGTH + 7 bytes further, so parse up to there.
        last = first
        j = first
        reach = ends[first] + MAX_DATA_LENGTH + 7
        while j + 1 < len(states) and (ends[j] < reach or states[j] != MSG_INTACT):
            j += 1
            if states[j] != MSG_INTACT:
                last = j
                reach = ends[j] + MAX_DATA_LENGTH + 7
        while i < len(damaged) and damaged[i] <= j:
            i += 1
        a, b = int(offsets[first]), int(ends[j])
        items, stats = parse_stream(stream[a:b])
        got = [a + it.offset for it in items]
        want = offsets[first:j + 1][states[first:j + 1] == MSG_INTACT].tolist()
        errors = stats.checksum_errors + stats.malformed + stats.truncated
        if got != want or errors != int(np.sum(states[first:j + 1] != MSG_INTACT)):
            bad.append((int(first), int(last) + 1))
    return bad


def simulate_xbus(track: BodyTrack, config: ImuConfig, rng: np.random.Generator
                  ) -> tuple[bytes, dict[int, str], XbusTruth]:
    """The 17 sensors' Xbus MTData2 stream as a serial capture from the Awinda station delivers it.

    One message per sensor per sample (formats.md "our convention"): DeviceId, PacketCounter,
    SampleTimeFine, Quaternion (sensor → earth frame E, ENU bits), Acceleration (specific force,
    sensor frame, m/s²), FreeAcceleration (E, gravity removed, m/s²), RateOfTurn (sensor frame,
    rad/s), StatusWord (self-test OK | orientation valid, + bit 18 if retransmitted), float32.
    Messages are in sample order, sensors in MVN_SENSORS order; retransmitted samples arrive
    1..retransmit_max_delay samples late. With corrupt/truncate/drop rates > 0 the stream is
    damaged and ``XbusTruth`` says exactly which messages were; every damaged message is checked
    to be one rejected message for :class:`couch.capture.xbus.XbusParser` that hides no intact one
    (re-drawn otherwise). Returns (stream bytes, DeviceId → segment label, truth).
    """
    sess = _simulate(track, config, rng)
    d, cfg = sess.draws, config
    k = len(sess.imu_time)
    earth_rot = _rz(-d.earth_heading)  # Rz(earth_heading)ᵀ: MVN frame → E
    quat = matrix_to_quat(earth_rot @ sess.sensor_rot_rep)
    ideal = matrix_to_quat(earth_rot @ _rz(-d.heading_offset) @ sess.sensor_rot_true)
    free_acc = _apply(earth_rot, sess.free_acc_mvn)
    stf = (d.stf0 + np.round(sess.imu_time * 1e4).astype(np.int64)) % 2**32
    counter = (d.pc0 + np.arange(k, dtype=np.int64)) % 2**16

    # Stream order: sample-major; retransmitted samples come after a later sample's messages.
    m = k * N_SENS
    sample = np.repeat(np.arange(k), N_SENS)
    sensor = np.tile(np.arange(N_SENS), k)
    retrans = rng.random(m) < cfg.retransmit_rate
    delay = rng.integers(1, max(1, cfg.retransmit_max_delay) + 1, size=m)
    order = np.argsort(sample + np.where(retrans, delay + 0.5, 0.0), kind="stable")
    sample, sensor, retrans = sample[order], sensor[order], retrans[order]
    status = np.full((k, N_SENS), STATUS_SELFTEST_OK | STATUS_ORIENTATION_VALID, dtype=np.int64)
    status[sample[retrans], sensor[retrans]] |= STATUS_RETRANSMITTED

    u = rng.random(m)
    state = np.full(m, MSG_INTACT, dtype=np.int8)
    state[u < cfg.corrupt_rate + cfg.truncate_rate + cfg.drop_rate] = MSG_CORRUPTED
    state[u < cfg.truncate_rate + cfg.drop_rate] = MSG_TRUNCATED
    state[u < cfg.drop_rate] = MSG_DROPPED
    # A truncated message's declared length reaches into the next message: if that one were
    # damaged too, a parser would rightly see a single damaged region. Keep it intact.
    emitted = np.flatnonzero(state != MSG_DROPPED)
    for pos in np.flatnonzero(state[emitted] == MSG_TRUNCATED):
        if pos + 1 < len(emitted) and state[emitted[pos + 1]] != MSG_INTACT:
            state[emitted[pos + 1]] = MSG_INTACT

    clean: list[bytes] = []
    for s_idx, sen in zip(sample[emitted].tolist(), sensor[emitted].tolist(), strict=True):
        clean.append(encode_mtdata2(XbusSample(
            device_id=int(d.device_ids[sen]), packet_counter=int(counter[s_idx]),
            sample_time_fine=int(stf[s_idx]), quaternion=quat[s_idx, sen],
            acceleration=sess.acc_meas[s_idx, sen], free_acceleration=free_acc[s_idx, sen],
            rate_of_turn=sess.gyro_meas[s_idx, sen], status_word=int(status[s_idx, sen]))))
    em_state = state[emitted]
    pieces = list(clean)
    bad_ranges: list[tuple[int, int]] = [(0, len(pieces))]
    for _attempt in range(20):
        for a, b in bad_ranges:
            for i in range(a, b):
                if em_state[i] != MSG_INTACT:
                    pieces[i] = _damage(clean[i], int(em_state[i]), rng)
        lengths = np.fromiter((len(p) for p in pieces), dtype=np.int64, count=len(pieces))
        offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
        stream = b"".join(pieces)
        bad_ranges = _check_windows(stream, offsets, lengths, em_state)
        if not bad_ranges:
            break
    else:
        raise RuntimeError("could not draw Xbus damage that a parser tells apart from intact "
                           "messages in 20 attempts")

    msg_offset = np.full(m, -1, dtype=np.int64)
    msg_length = np.zeros(m, dtype=np.int64)
    msg_offset[emitted] = offsets
    msg_length[emitted] = lengths
    device_map = {int(d.device_ids[s]): MVN_SENSORS[s] for s in range(N_SENS)}
    truth = XbusTruth(
        frame_rate=float(cfg.frame_rate), clock_scale=sess.clock_scale,
        clock_offset=sess.clock_offset, drift_ppm=float(cfg.drift_ppm),
        imu_time=sess.imu_time, kinect_time=sess.kinect_time, in_track=sess.in_track,
        sample_time_fine=stf, packet_counter=counter, device_ids=d.device_ids.copy(),
        heading_offset=d.heading_offset, heading_drift=d.heading_drift,
        earth_heading=d.earth_heading, mount=matrix_to_quat(d.mount),
        orientation_noise=matrix_to_quat(d.noise), acc_bias=d.acc_bias, gyro_bias=d.gyro_bias,
        quaternion=quat, quaternion_ideal=ideal, acceleration=sess.acc_meas,
        free_acceleration=free_acc, rate_of_turn=sess.gyro_meas, status_word=status,
        msg_sample=sample, msg_sensor=sensor, msg_state=state, msg_offset=msg_offset,
        msg_length=msg_length, retransmitted=retrans,
    )
    return stream, device_map, truth


__all__ = [
    "DEFAULT_START_UNIX_MS", "MSG_CORRUPTED", "MSG_DROPPED", "MSG_INTACT", "MSG_TRUNCATED",
    "SEGMENT_JOINTS", "SEGMENT_NOISE_SENSOR", "SEGMENT_PARENTS", "SENSOR_SEGMENTS", "BodyTrack",
    "ImuConfig", "ImuTruth", "XbusTruth", "body_track_from_model", "simulate_mvnx",
    "simulate_xbus", "smooth_noise", "smooth_random_walk",
]
