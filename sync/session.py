"""Sync a whole session folder: cameras on the master clock, the IMU clock, IMU poses resampled.

:func:`sync_session` chains :func:`couch.sync.signals.session_tracks` (one pass per camera),
:func:`couch.sync.kinect.sync_tracks`, :func:`couch.sync.imu.sync_imu` and
:func:`couch.sync.resample.resample_imu`; each step is usable alone.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

import numpy as np

from couch.capture.calibration import Extrinsics, calibrate_session
from couch.capture.imu import ImuMotion, mvnx_to_smpl
from couch.capture.mvnx import read_mvnx
from couch.capture.segmentation import SegmentationConfig
from couch.capture.session import session_files
from couch.pool import Pool
from couch.sync.clock import ClockEstimate, ClockModel, ClockSyncConfig
from couch.sync.imu import sync_imu
from couch.sync.kinect import KinectSync, KinectSyncConfig, sync_tracks
from couch.sync.resample import ResampledImu, resample_imu
from couch.sync.signals import CameraTrack, TrackConfig, session_tracks

__all__ = ["SessionSync", "session_mvnx", "sync_session"]

log = logging.getLogger(__name__)


@dataclasses.dataclass
class SessionSync:
    """A session on the Kinect master clock.

    Attributes:
        kinect: cameras, offsets and frame table (:class:`~couch.sync.kinect.KinectSync`).
        tracks: the per-camera signals used (:class:`~couch.sync.signals.CameraTrack`).
        imu_clock: the IMU clock estimate, or None when the session has no IMU recording.
        imu: the suit's motion on its own clock, or None.
        resampled: the suit's poses at ``kinect.time``, or None.
        imu_source: the MVNX file read, or None.
    """

    kinect: KinectSync
    tracks: list[CameraTrack]
    imu_clock: ClockEstimate | None
    imu: ImuMotion | None
    resampled: ResampledImu | None
    imu_source: str | None

    def summary(self) -> str:
        lines = [self.kinect.summary()]
        if self.imu_clock is not None:
            lines.append(f"IMU ({self.imu_source}): {self.imu_clock.summary()}")
        if self.resampled is not None:
            lines.append(self.resampled.summary())
        return "\n".join(lines)


def session_mvnx(session_dir: str | os.PathLike) -> Path | None:
    """The session's MVNX file: ``session.json`` ``imu.mvnx``, else ``imu/*.mvnx`` (None: no
    IMU recording).

    Raises:
        ValueError: a malformed ``session.json``.
        FileNotFoundError: the MVNX file it names does not exist.
    """
    files = session_files(session_dir)
    if files.mvnx is not None and not files.mvnx.is_file():
        raise FileNotFoundError(f"{files.manifest}: the IMU recording {files.mvnx} does not "
                                f"exist")
    return files.mvnx


def sync_session(session_dir: str | os.PathLike, *,
                 extrinsics: Extrinsics | dict[str, np.ndarray] | None = None,
                 track_config: TrackConfig | None = None,
                 kinect_config: KinectSyncConfig | None = None,
                 clock_config: ClockSyncConfig | None = None,
                 initial: ClockModel | None = None, search_s: float | None = None,
                 depth_binning: int = 1, progress: bool = False, pool: Pool = None
                 ) -> SessionSync:
    """Synchronise a session folder (``couch-simulate``'s layout / ``session.json``).

    Args:
        session_dir: the session.
        extrinsics: camera poses; None calibrates them (:func:`couch.capture.calibration.
            calibrate_session`).
        track_config, kinect_config, clock_config: knobs of the steps.
        initial, search_s: prior IMU clock and search half-width (see :func:`sync_imu`).
        depth_binning: 2: the cameras' passes read full-resolution depth binned 2x2 (a quarter
            of the pixels; the tracks are in world coordinates either way), unless
            ``track_config`` says otherwise. 1: as recorded.
        progress: progress bars.
        pool: where the cameras' passes run (:func:`couch.pool.spawn_pool`); None: here.

    Raises:
        SyncError: from the steps (names the files).
    """
    root = Path(session_dir)
    ext = extrinsics if extrinsics is not None else calibrate_session(root)
    if track_config is None and depth_binning != 1:
        track_config = TrackConfig(segmentation=SegmentationConfig(depth_binning=depth_binning))
    tracks = session_tracks(root, ext, config=track_config, progress=progress, pool=pool)
    kinect = sync_tracks(tracks, config=kinect_config)
    for w in kinect.warnings:
        log.warning("%s", w)
    mvnx = session_mvnx(root)
    if mvnx is None:
        return SessionSync(kinect, tracks, None, None, None, None)
    imu = mvnx_to_smpl(read_mvnx(mvnx))
    clock = sync_imu(kinect, tracks, imu, initial=initial, search_s=search_s,
                     config=clock_config, imu_name=str(mvnx))
    if not clock.confident:
        log.warning("IMU sync of %s: %s", mvnx, clock.summary())
    resampled = resample_imu(imu, clock.clock, kinect.time, source=str(mvnx))
    return SessionSync(kinect, tracks, clock, imu, resampled, str(mvnx))
