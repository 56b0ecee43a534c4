"""Sync stage: every stream on the Kinect master clock.

* :mod:`couch.sync.kinect` — hardware-synced cameras: device clock offsets, the frame table
  (rows = capture instants, -1 where a camera dropped the frame), robust to dropped frames on any
  device including its first (whole-frame shifts settled from content).
* :mod:`couch.sync.signals` — per-camera person signals (top of the head, centroid) in world
  coordinates, one streaming pass per recording.
* :mod:`couch.sync.clock` — a linear clock ``t_other = (1 + drift·1e-6)·t_kinect + offset``
  estimated from two time series of one quantity: coarse cross-correlation, then robust least
  squares with sub-frame interpolation (:func:`refine_clock` also serves a later refinement, e.g.
  on fitted joints).
* :mod:`couch.sync.imu` — the IMU clock from the head top seen by the cameras and the suit.
* :mod:`couch.sync.resample` — IMU poses at Kinect timestamps (slerp / linear), invalid frames
  flagged, never extrapolated.
* :mod:`couch.sync.session` — all of it for a session folder.

Times are float64 seconds: Kinect master clock unless named otherwise; raw device timestamps
(µs) stay in :class:`CameraTrack`.
"""

from couch.sync.clock import (
    ClockEstimate,
    ClockModel,
    ClockSyncConfig,
    SyncError,
    coarse_offset,
    estimate_clock,
    refine_clock,
)
from couch.sync.imu import (
    HEAD_TOP_OFFSET,
    head_features,
    imu_head_top,
    imu_sample_times,
    joint_features,
    kinect_head_features,
    refine_imu,
    sync_imu,
)
from couch.sync.kinect import KinectSync, KinectSyncConfig, sync_kinect, sync_tracks
from couch.sync.resample import AFTER, BEFORE, IN_GAP, OK, ResampledImu, resample_imu
from couch.sync.session import SessionSync, sync_session
from couch.sync.signals import (
    CameraTrack,
    TrackConfig,
    camera_track,
    session_streams,
    session_tracks,
)

__all__ = [
    "AFTER",
    "BEFORE",
    "HEAD_TOP_OFFSET",
    "IN_GAP",
    "OK",
    "CameraTrack",
    "ClockEstimate",
    "ClockModel",
    "ClockSyncConfig",
    "KinectSync",
    "KinectSyncConfig",
    "ResampledImu",
    "SessionSync",
    "SyncError",
    "TrackConfig",
    "camera_track",
    "coarse_offset",
    "estimate_clock",
    "head_features",
    "imu_head_top",
    "imu_sample_times",
    "joint_features",
    "kinect_head_features",
    "refine_clock",
    "refine_imu",
    "resample_imu",
    "session_streams",
    "session_tracks",
    "sync_imu",
    "sync_kinect",
    "sync_session",
    "sync_tracks",
]
