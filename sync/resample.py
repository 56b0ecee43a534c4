"""IMU poses resampled onto Kinect master-clock timestamps.

Each target time is mapped to the IMU clock with the estimated :class:`~couch.sync.clock.
ClockModel`, bracketed by two IMU samples and interpolated: joint rotations by **slerp** (the
global world-from-joint rotations, so every joint turns along the shortest arc; the local
rotations and axis-angle parameters are derived from them), positions **linearly**, foot
contacts from the nearer sample. Nothing is extrapolated: a target before the first or after the
last IMU sample, or between two samples farther apart than ``max_gap_s`` (lost packets, a cut
recording), is flagged invalid (``status``), its values NaN (contacts False), and counted in
the result's :meth:`ResampledImu.summary`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from couch.body import NUM_JOINTS
from couch.capture.imu import ImuMotion, local_rotations
from couch.rotations import matrix_to_axis_angle, matrix_to_quat, quat_to_matrix, slerp
from couch.sync.clock import ClockModel
from couch.sync.imu import imu_sample_times

__all__ = ["AFTER", "BEFORE", "IN_GAP", "OK", "ResampledImu", "resample_imu"]

OK, BEFORE, AFTER, IN_GAP = 0, 1, 2, 3
_STATUS_NAMES = {OK: "ok", BEFORE: "before the IMU recording", AFTER: "after the IMU recording",
                 IN_GAP: "in a gap of the IMU recording"}


@dataclasses.dataclass
class ResampledImu:
    """The suit's motion at T Kinect master-clock times (NaN where not ``valid``).

    Attributes:
        time: (T,) Kinect master-clock seconds (the targets).
        imu_time: (T,) the IMU-clock seconds they map to.
        status: (T,) int8: :data:`OK`, :data:`BEFORE`, :data:`AFTER` or :data:`IN_GAP`.
        joint_rotations: (T, 24, 3, 3) global world-from-joint rotations (IMU heading).
        global_orient: (T, 3) axis-angle of the pelvis.
        body_pose: (T, 69) axis-angle local rotations of joints 1..23 (parent-from-child).
        joint_positions: (T, 24, 3) metres (IMU heading and origin).
        foot_contacts: (T, 4) bool (nearer sample; False where invalid), or None.
        source: how the IMU recording is named in messages.
    """

    time: np.ndarray
    imu_time: np.ndarray
    status: np.ndarray
    joint_rotations: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    joint_positions: np.ndarray
    foot_contacts: np.ndarray | None
    source: str = "IMU"

    @property
    def valid(self) -> np.ndarray:
        """(T,) bool: interpolated between two IMU samples."""
        return self.status == OK

    def take(self, index: np.ndarray) -> ResampledImu:
        """The targets ``index`` (an index array or boolean mask over the T targets), copied."""
        fc = None if self.foot_contacts is None else self.foot_contacts[index]
        return ResampledImu(time=self.time[index], imu_time=self.imu_time[index],
                            status=self.status[index],
                            joint_rotations=self.joint_rotations[index],
                            global_orient=self.global_orient[index],
                            body_pose=self.body_pose[index],
                            joint_positions=self.joint_positions[index], foot_contacts=fc,
                            source=self.source)

    def counts(self) -> dict[str, int]:
        """Number of targets per status name."""
        return {name: int(np.count_nonzero(self.status == code))
                for code, name in _STATUS_NAMES.items()}

    def summary(self) -> str:
        """One line: how many targets are valid and why the others are not."""
        c = self.counts()
        bad = ", ".join(f"{n} {k}" for k, n in c.items() if k != "ok" and n)
        return (f"{self.source}: {c['ok']} of {len(self.time)} Kinect frames resampled"
                + (f"; not resampled: {bad}" if bad else ""))


def resample_imu(imu: ImuMotion, clock: ClockModel, kinect_time: np.ndarray, *,
                 max_gap_s: float | None = None, source: str = "IMU") -> ResampledImu:
    """Resample the suit's poses at Kinect master-clock times.

    Args:
        imu: the suit's motion (:func:`couch.capture.imu.mvnx_to_smpl`), IMU clock; its sample
            times are snapped to the sample grid (:func:`couch.sync.imu.imu_sample_times`).
        clock: ``t_imu = (1 + drift·1e-6)·t_kinect + offset`` (e.g. ``sync_imu(...).clock``).
        kinect_time: (T,) Kinect master-clock seconds (e.g. ``KinectSync.time``).
        max_gap_s: IMU samples farther apart than this are not interpolated between (default:
            2.5 sample periods, i.e. a single lost sample is bridged).
        source: name of the IMU recording for messages.

    Returns:
        :class:`ResampledImu`.

    Raises:
        ValueError: fewer than two IMU samples, or non-increasing IMU times.
    """
    t_imu = imu_sample_times(imu)
    if len(t_imu) < 2:
        raise ValueError(f"{source}: {len(t_imu)} IMU sample(s); at least 2 are needed")
    if np.any(np.diff(t_imu) <= 0):
        k = int(np.argmax(np.diff(t_imu) <= 0))
        raise ValueError(f"{source}: IMU times not increasing at sample {k + 1} "
                         f"({t_imu[k]:.4f} s then {t_imu[k + 1]:.4f} s)")
    period = 1.0 / imu.frame_rate if imu.frame_rate > 0 else float(np.median(np.diff(t_imu)))
    gap = 2.5 * period if max_gap_s is None else float(max_gap_s)
    t = np.asarray(kinect_time, dtype=np.float64)
    tau = clock.to_other(t)
    n = len(t_imu)
    # bracket: t_imu[i] <= tau <= t_imu[i + 1]
    i = np.clip(np.searchsorted(t_imu, tau, side="right") - 1, 0, n - 2)
    span = t_imu[i + 1] - t_imu[i]
    u = (tau - t_imu[i]) / span
    status = np.full(len(t), OK, dtype=np.int8)
    status[(span > gap + 1e-9) & (u > 1e-9) & (u < 1.0 - 1e-9)] = IN_GAP
    status[tau < t_imu[0]] = BEFORE
    status[tau > t_imu[-1]] = AFTER
    valid = status == OK
    u = np.clip(u, 0.0, 1.0)

    q = matrix_to_quat(imu.joint_rotations)  # (N, 24, 4)
    rot = np.full((len(t), NUM_JOINTS, 3, 3), np.nan)
    pos = np.full((len(t), NUM_JOINTS, 3), np.nan)
    if valid.any():
        iv, uv = i[valid], u[valid]
        qi = slerp(q[iv], q[iv + 1], np.repeat(uv[:, None], NUM_JOINTS, axis=1))
        rot[valid] = quat_to_matrix(qi)
        p = imu.joint_positions
        pos[valid] = (1.0 - uv)[:, None, None] * p[iv] + uv[:, None, None] * p[iv + 1]
    aa = np.full((len(t), NUM_JOINTS, 3), np.nan)
    if valid.any():
        aa[valid] = matrix_to_axis_angle(local_rotations(rot[valid]))
    contacts = None
    if imu.foot_contacts is not None:
        nearest = np.where(u < 0.5, i, i + 1)
        contacts = np.asarray(imu.foot_contacts, dtype=bool)[nearest] & valid[:, None]
    return ResampledImu(time=t, imu_time=tau, status=status, joint_rotations=rot,
                        global_orient=aa[:, 0].copy(),
                        body_pose=aa[:, 1:].reshape(len(t), 3 * (NUM_JOINTS - 1)),
                        joint_positions=pos, foot_contacts=contacts, source=source)
