"""The IMU clock against the Kinect master clock, from the person's motion seen by both.

Signal: the **top of the head**. The cameras see it as the top of the person's point cloud
(:mod:`couch.sync.signals`: nearly the same point from every side, unlike the centroid of the
visible surface); the suit gives it as the head segment's origin plus a fixed offset along the
head's up axis (:func:`imu_head_top`). Two features per frame, both blind to MVN's heading and
horizontal origin (:func:`head_features`):

* the height of the head top (m): sitting down and standing up move it by tens of centimetres,
  walking makes it bob at the step rate;
* its horizontal speed (m/s, central difference over the frame grid): walking, stopping,
  turning.

The Kinect side fuses the cameras per frame (:func:`kinect_head_features`): heights averaged
over the cameras that see the top (each camera's small constant bias removed first), velocities
differenced per camera (so a camera joining or leaving does not look like motion) and averaged.
The IMU side samples its head top at the mapped frame times and applies the same central
difference. :func:`couch.sync.clock.estimate_clock` then cross-correlates (coarse) and fits
offset and drift (fine); :func:`sync_imu` does all of it for a session.

IMU sample times: MVNX stores whole milliseconds; :func:`imu_sample_times` snaps them back onto
the suit's sample grid (``k / frame_rate``) when every stamp is within rounding of it.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from couch.body import JOINT_INDEX
from couch.capture.imu import ImuMotion
from couch.sync.clock import (
    ClockEstimate,
    ClockModel,
    ClockSyncConfig,
    SyncError,
    estimate_clock,
    refine_clock,
)
from couch.sync.kinect import KinectSync
from couch.sync.signals import CameraTrack

__all__ = [
    "HEAD_TOP_OFFSET",
    "head_features",
    "imu_head_top",
    "imu_sample_times",
    "joint_features",
    "kinect_head_features",
    "refine_imu",
    "sync_imu",
]

log = logging.getLogger(__name__)

HEAD_TOP_OFFSET = (0.0, 0.10, 0.0)
"""Head-frame vector (m) from the SMPL head joint to the top of the head (~10 cm above the joint
in the T-pose). Only its direction matters much: the estimator's per-channel bias absorbs a
constant error (on the simulator's bundled body the cameras see the top ~4-5 cm higher still),
and the top moves with the head's tilt through it."""


def imu_sample_times(imu: ImuMotion, tolerance_s: float = 6e-4) -> np.ndarray:
    """(M,) IMU-clock seconds of the samples, snapped to ``k / frame_rate`` when every MVNX
    stamp (whole ms) lies within ``tolerance_s`` of that grid; else the stamps as they are."""
    t = np.asarray(imu.time, dtype=np.float64)
    rate = float(imu.frame_rate)
    if rate <= 0 or len(t) == 0:
        return t
    snapped = np.round(t * rate) / rate
    if np.all(np.abs(snapped - t) <= tolerance_s) and np.all(np.diff(snapped) > 0):
        return snapped
    return t


def imu_head_top(imu: ImuMotion, offset: Sequence[float] = HEAD_TOP_OFFSET) -> np.ndarray:
    """(M, 3) the top of the head in the suit's frame (couch axes, metres): head joint position
    plus its rotation applied to ``offset``."""
    h = JOINT_INDEX["head"]
    return imu.joint_positions[:, h] + imu.joint_rotations[:, h] @ np.asarray(offset, float)


def head_features(time: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(..., N, 3) head-top positions on a regular frame grid ``time`` (N,) → (..., N, 2):
    height (m) and horizontal speed (m/s, central difference; NaN at the ends and where a
    neighbour is missing). A :data:`couch.sync.clock.FeatureFn`.

    The speed rather than the velocity: each camera sees the top of the head displaced towards
    itself, and as the subject walks past that displacement turns, which bends the measured
    velocity's direction far more than its length (and MVN's heading is its own anyway)."""
    p = np.asarray(positions, dtype=np.float64)
    t = np.asarray(time, dtype=np.float64)
    out = np.full((*p.shape[:-1], 2), np.nan)
    out[..., 0] = p[..., 1]
    if p.shape[-2] >= 3:
        v = (p[..., 2:, :] - p[..., :-2, :]) / (t[2:] - t[:-2])[:, None]
        out[..., 1:-1, 1] = np.hypot(v[..., 0], v[..., 2])
    return out


def kinect_head_features(kinect: KinectSync, tracks: Sequence[CameraTrack]
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``kinect``: the fused head-top features and how many cameras gave them.

    Returns:
        features: (T, 2) height (m) and horizontal speed (m/s) as :func:`head_features`
            would compute them from one consistent head-top track; NaN where no camera gives
            them.
        cameras: (T,) number of cameras that saw the top at the row.
    """
    if len(tracks) != len(kinect.serials):
        raise ValueError(f"{len(tracks)} tracks for {len(kinect.serials)} synchronised cameras")
    top = kinect.gather([t.top for t in tracks])  # (T, C, 3)
    seen = np.all(np.isfinite(top), axis=2)
    t = kinect.time
    # heights: remove each camera's constant bias against the others, then average
    height = np.where(seen, top[..., 1], np.nan)
    feats = np.full((kinect.n_rows, 2), np.nan)
    if not seen.any():
        return feats, seen.sum(axis=1)
    fused = _nanmean(height, axis=1)
    for _ in range(2):
        dev = height - fused[:, None]
        bias = np.array([np.median(d[np.isfinite(d)]) if np.isfinite(d).any() else 0.0
                         for d in dev.T])
        fused = _nanmean(height - bias, axis=1)
    # velocities per camera over its own consecutive rows, then averaged over cameras
    v = np.full((kinect.n_rows, len(tracks), 3), np.nan)
    v[1:-1] = (top[2:] - top[:-2]) / (t[2:] - t[:-2])[:, None, None]
    v_mean = _nanmean(v, axis=1)
    feats[:, 0] = fused
    feats[:, 1] = np.hypot(v_mean[:, 0], v_mean[:, 2])
    return feats, seen.sum(axis=1)


def _nanmean(a: np.ndarray, axis: int) -> np.ndarray:
    """Mean over ``axis`` ignoring NaN, NaN where all are (without numpy's warning)."""
    n = np.sum(np.isfinite(a), axis=axis)
    total = np.nansum(a, axis=axis)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def sync_imu(kinect: KinectSync, tracks: Sequence[CameraTrack], imu: ImuMotion, *,
             initial: ClockModel | None = None, search_s: float | None = None,
             config: ClockSyncConfig | None = None, imu_name: str = "IMU",
             head_offset: Sequence[float] = HEAD_TOP_OFFSET) -> ClockEstimate:
    """Estimate ``t_imu = (1 + drift·1e-6)·t_kinect + offset`` from the head top.

    Args:
        kinect: the cameras on the master clock (:func:`couch.sync.kinect.sync_tracks`).
        tracks: the cameras' :class:`~couch.sync.signals.CameraTrack` s, in ``kinect``'s order.
        imu: the suit's motion (:func:`couch.capture.imu.mvnx_to_smpl`), IMU clock.
        initial, search_s: a prior clock and the half-width of the offset window searched
            around it (default: every offset at which the recordings overlap).
        config: estimator knobs.
        imu_name: how the IMU recording is named in messages (e.g. its file).
        head_offset: see :data:`HEAD_TOP_OFFSET`.

    Returns:
        :class:`~couch.sync.clock.ClockEstimate`.

    Raises:
        SyncError: no overlap, no motion, too few frames (the message names the streams).
    """
    feats, cams = kinect_head_features(kinect, tracks)
    names = (f"Kinect ({', '.join(t.source for t in tracks)})", imu_name)
    if imu.n_frames < 4:
        raise SyncError(f"{imu_name}: only {imu.n_frames} IMU samples")
    rows = np.flatnonzero(kinect.present.any(axis=1))
    return estimate_clock(kinect.time[rows], feats[rows], imu_sample_times(imu),
                          imu_head_top(imu, head_offset), features=head_features,
                          weights=np.minimum(cams[rows], 2).astype(float), initial=initial,
                          search_s=search_s, config=config, names=names)


def refine_imu(kinect_time: np.ndarray, kinect_joints: np.ndarray, imu: ImuMotion,
               initial: ClockModel, *, joints: Sequence[int] | None = None,
               config: ClockSyncConfig | None = None, imu_name: str = "IMU") -> ClockEstimate:
    """Refine a clock on joint positions after a first body fit (the fitting stage's entry).

    Compares, per joint, the height and horizontal speed (:func:`head_features` applied to
    each joint) of the fitted joints on the Kinect frames with the suit's joints: blind to
    MVN's heading and horizontal origin.

    Args:
        kinect_time: (N,) master-clock seconds of the fitted frames (regular grid, gaps ok).
        kinect_joints: (N, 24, 3) fitted SMPL joints, world metres (NaN: no fit).
        imu: the suit's motion (IMU clock).
        initial: the clock to refine (e.g. :func:`sync_imu`'s); within ~0.1 s of the truth.
        joints: SMPL joint indices to use (default: all 24).
        config, imu_name: see :func:`sync_imu`.
    """
    sel = list(range(imu.joint_positions.shape[1])) if joints is None else list(joints)
    grid_t, full = _on_grid(np.asarray(kinect_time, dtype=np.float64),
                            np.asarray(kinect_joints, dtype=np.float64)[:, sel])
    return refine_clock(grid_t, joint_features(grid_t, full), imu_sample_times(imu),
                        imu.joint_positions[:, sel], initial, features=joint_features,
                        config=config, names=("Kinect fit", imu_name))


def joint_features(time: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """(..., N, J, 3) joint positions on a regular frame grid → (..., N, 2·J): per joint the
    height and horizontal speed of :func:`head_features`."""
    f = head_features(time, np.moveaxis(np.asarray(joints, dtype=np.float64), -2, -3))
    return np.moveaxis(f, -3, -2).reshape(*f.shape[:-3], f.shape[-2], -1)


def _on_grid(time: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values on the full regular grid their (increasing) times lie on, NaN rows in gaps."""
    if len(time) < 3 or np.any(np.diff(time) <= 0):
        raise SyncError("fitted frame times must be at least 3 and strictly increasing")
    steps = np.diff(time)
    period = float(np.min(steps))
    idx = np.concatenate([[0], np.cumsum(np.round(steps / period))]).astype(np.int64)
    grid = time[0] + period * np.arange(idx[-1] + 1)
    full = np.full((len(grid), *values.shape[1:]), np.nan)
    full[idx] = values
    return grid, full
