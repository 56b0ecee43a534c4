"""Per-camera motion signals of the person, for synchronising clocks from content.

One streaming pass over each camera's depth frames (:func:`camera_track`) segments the person
against the camera's background (:func:`couch.capture.segmentation.foreground`), lifts the
person pixels into the world (metres, Y up, floor y = 0) and keeps a few numbers per frame:

* ``top``: the **top of the person** — the height of its ``top_rank``-th highest point (a
  fixed count rather than a quantile: a far, small person would otherwise be measured lower
  than a near one), the horizontal position the mean of the points within ``top_band`` of it.
  For a person it is the top of the head, which every camera around the subject sees at nearly
  the same height whatever side it views (unlike the centroid of the visible surface, which
  moves by tens of centimetres with the view), and which the suit's head segment gives too
  (:func:`couch.sync.imu.imu_head_top`). The points are those of the whole person mask with
  valid depth, silhouette included: the segmentation's ``reliable`` pixels leave out the
  silhouette's outer pixels, which would lower the top by a distance-dependent 1-2 pixels,
  while a mixed (flying) depth at the top of the head moves its point along a nearly
  horizontal ray, hardly in height. A frame where the top points touch the edge of the
  camera's field of view is ``clipped`` (the head is partly out of view) and its ``top`` is
  NaN.
* ``centroid`` and ``points``: the mean and number of those person points (diagnostics).

Times stay on the device's own clock (``timestamp_us``); :mod:`couch.sync.kinect` puts them on the
master clock.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from couch.capture.azure_mkv import AzureMkvRecording
from couch.capture.calibration import Extrinsics
from couch.capture.frames import KinectStream, open_kinect_stream
from couch.capture.registration import pixel_rays
from couch.capture.segmentation import (
    BackgroundModel,
    SegmentationConfig,
    background_from_recordings,
    camera_foreground,
    empty_room_recording,
)
from couch.capture.session import session_files
from couch.pool import Pool, pool_map

__all__ = ["CameraTrack", "TrackConfig", "camera_track", "session_streams", "session_tracks"]

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class TrackConfig:
    """Knobs of the per-camera signals (lengths in metres)."""

    top_rank: int = 3  # the top of the person is the height of its k-th highest point ...
    cap_depth: float = 0.03  # ... refined on the points of the top cap this deep (0: off)
    top_band: float = 0.02  # points within this of the top give its horizontal position
    min_points: int = 50  # fewer person points: no person in this frame
    min_view_fraction: float = 0.15  # fewer than this × the camera's median: partly in view
    min_top_points: int = 5  # fewer points in the top band: no top
    edge_px: float = 2.5  # top points nearer the field of view's edge: clipped
    top_pixels: str = "mask"  # "mask" (silhouette included) or "reliable" (segmentation's)
    segmentation: SegmentationConfig | None = None


@dataclasses.dataclass
class CameraTrack:
    """Per-frame person signals of one camera, N frames in recording order.

    Attributes:
        serial: device serial.
        source: the recording (file or folder) read.
        fps: nominal frame rate of the recording.
        sync_mode: ``MASTER``, ``SUBORDINATE`` or ``STANDALONE`` (MKV ``K4A_WIRED_SYNC_MODE``;
            STANDALONE for other sources).
        exposure_delay_us: delay of this device's depth exposure after the master's (MKV
            ``K4A_SUBORDINATE_DELAY_NS`` / 1000; 0 for the master).
        timestamp_us: (N,) int64 device-clock timestamps (µs) of the frames.
        top: (N, 3) float64 world metres of the top of the person; NaN where no person, too few
            top points, clipped, or the person is only partly in view (far fewer points than
            the camera's median).
        clipped: (N,) bool, the top points touch the field of view's edge.
        centroid: (N, 3) float64 world metres, mean of the person points (NaN: none).
        points: (N,) int64 number of person points (``TrackConfig.top_pixels`` with depth).
        skipped: frames read without usable depth (message per frame).
    """

    serial: str
    source: str
    fps: float
    sync_mode: str
    exposure_delay_us: float
    timestamp_us: np.ndarray
    top: np.ndarray
    clipped: np.ndarray
    centroid: np.ndarray
    points: np.ndarray
    skipped: list[str] = dataclasses.field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return len(self.timestamp_us)


def _cap_top(y: np.ndarray, start: float, depth: float, iterations: int = 5) -> float:
    """Sub-pixel height of the top of a rounded cap from its points' heights ``y``.

    The area of a sphere is spread evenly in height (Archimedes), so the points of its top cap
    of depth d have heights uniform in [top - d, top], with mean top - d/2: iterate
    ``top = mean(y >= top - d) + d/2`` from ``start``. Every point of the cap counts, not only
    the highest few, which sit on whole pixels."""
    top = start
    for _ in range(iterations):
        cap = y[y >= top - depth]
        if len(cap) < 3:
            break
        top = float(cap.mean()) + 0.5 * depth
    return top


def _edge_distance(seen: np.ndarray) -> np.ndarray:
    """(H,W) float32 distance (px) of every pixel to the edge of the field of view, taken as the
    convex hull of the pixels ``seen`` (valid in the background or any frame: the depth
    camera's NFOV octagon / WFOV circle wherever something was in range), or the image
    border."""
    h, w = seen.shape
    hull_mask = np.zeros((h + 2, w + 2), np.uint8)
    pts = np.column_stack(np.nonzero(seen)[::-1]).astype(np.int32)
    if len(pts) >= 3:
        cv2.fillConvexPoly(hull_mask, cv2.convexHull(pts + 1), 1)
    else:
        hull_mask[1:-1, 1:-1] = 1
    hull_mask[0, :] = hull_mask[-1, :] = 0
    hull_mask[:, 0] = hull_mask[:, -1] = 0
    return cv2.distanceTransform(hull_mask, cv2.DIST_L2, 3)[1:-1, 1:-1]


def camera_track(stream: KinectStream | str | os.PathLike, world_from_depth: np.ndarray,
                 background: BackgroundModel, *, config: TrackConfig | None = None,
                 progress: bool = False) -> CameraTrack:
    """One pass over a camera's frames: per-frame top of the person and centroid (world).

    Args:
        stream: an open :class:`~couch.capture.frames.KinectStream` or a path for
            :func:`~couch.capture.frames.open_kinect_stream` (depth in the depth camera's grid:
            an Azure MKV).
        world_from_depth: (4,4) world pose of the depth camera (metres, Y up, floor y = 0).
        background: the camera's background model (the empty room with the chair in place).
        config: see :class:`TrackConfig`.
        progress: show a progress bar.

    Returns:
        :class:`CameraTrack`; frames without depth keep their timestamp with NaN signals and
        are listed in ``skipped``.

    Raises:
        ValueError: a stream whose depth is not in the depth camera's grid (BEHAVE folders),
            or a pose that is not (4,4).
    """
    cfg = config or TrackConfig()
    seg = cfg.segmentation or SegmentationConfig()
    st = (stream if isinstance(stream, KinectStream)
          else open_kinect_stream(stream, depth_binning=seg.depth_binning, streams=("DEPTH",)))
    if st.depth_grid != "depth":
        raise ValueError(f"{st.path}: camera_track needs depth in the depth camera's pixels "
                         f"(an Azure MKV), got a {st.kind} stream ({st.depth_grid} grid)")
    pose = np.asarray(world_from_depth, dtype=np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"{st.path}: world_from_depth must be (4, 4), got {pose.shape}")
    if cfg.top_pixels not in ("mask", "reliable"):
        raise ValueError(f"TrackConfig.top_pixels must be 'mask' or 'reliable', got "
                         f"{cfg.top_pixels!r}")
    calib = st.calibration
    rays = pixel_rays(calib.depth)  # (H,W,2), NaN where the pixel has no ray
    rot, trans = pose[:3, :3], pose[:3, 3]
    sync_mode, delay = "STANDALONE", 0.0
    if isinstance(st.reader, AzureMkvRecording):
        sync_mode = st.reader.wired_sync_mode
        delay = st.reader.subordinate_delay_ns / 1000.0 if sync_mode == "SUBORDINATE" else 0.0
    n_pix = len(rays.reshape(-1, 2))
    stamps: list[int] = []
    tops = []  # per frame: (3,) top or NaN
    band_pixels: list[np.ndarray] = []  # per frame: flat pixel indices of the top band
    cents, counts, skipped = [], [], []
    seen = np.isfinite(background.depth)
    fg = camera_foreground(background, calib, pose, seg, reliable=cfg.top_pixels == "reliable")
    has_ray = np.isfinite(rays[..., 0])
    nan3 = np.full(3, np.nan)
    for frame in tqdm(st, desc=f"signals {st.serial}", unit="frame", disable=not progress):
        stamps.append(frame.timestamp_us)
        depth = frame.depth_mm
        top, band_px, cent, n = nan3, np.zeros(0, np.int64), nan3, 0
        if depth is None or not np.any(depth):
            skipped.append(f"{frame.source}: no usable depth")
        else:
            valid = depth > 0
            seen |= valid
            mask, reliable = fg(depth)
            sel = (mask if cfg.top_pixels == "mask" else reliable) & has_ray & valid
            n = int(np.count_nonzero(sel))
            if n >= cfg.min_points:
                z = depth[sel].astype(np.float64) * 1e-3
                world = np.column_stack([rays[sel] * z[:, None], z]) @ rot.T + trans
                # the k-th highest point: a fixed count, not a share of the points, so that
                # a far (small) person is not measured lower than a near one
                k = min(cfg.top_rank, len(world))
                y = world[:, 1]
                height = float(np.partition(y, len(world) - k)[len(world) - k])
                if cfg.cap_depth > 0:
                    height = _cap_top(y, height, cfg.cap_depth)
                band = y >= height - cfg.top_band
                if band.sum() >= cfg.min_top_points:
                    xz = world[band][:, [0, 2]].mean(axis=0)
                    top = np.array([xz[0], height, xz[1]])
                    band_px = np.flatnonzero(sel.ravel())[band]
                cent = world.mean(axis=0)
        tops.append(top)
        band_pixels.append(band_px)
        cents.append(cent)
        counts.append(n)
    # the field of view is known once every frame was seen: clip tops that touch its edge
    edge = _edge_distance(seen).ravel() if stamps else np.zeros(n_pix)
    clipped = np.array([len(b) > 0 and bool(edge[b].min() < cfg.edge_px) for b in band_pixels],
                       dtype=bool)
    top_arr = np.asarray(tops, dtype=np.float64).reshape(-1, 3)
    top_arr[clipped] = np.nan
    # a person only partly in view (walking in or out at the side): its top is a shoulder or
    # an arm, not the head; far fewer points than the camera usually sees of the person
    counts_arr = np.asarray(counts, dtype=np.int64)
    seen_person = counts_arr[counts_arr >= cfg.min_points]
    if len(seen_person):
        partial = counts_arr < cfg.min_view_fraction * np.median(seen_person)
        top_arr[partial] = np.nan
    if skipped:
        log.warning("%s: %d frame(s) without usable depth", st.path, len(skipped))
    return CameraTrack(serial=st.serial, source=str(st.path), fps=float(st.fps),
                       sync_mode=sync_mode, exposure_delay_us=delay,
                       timestamp_us=np.asarray(stamps, dtype=np.int64),
                       top=top_arr, clipped=clipped,
                       centroid=np.asarray(cents, dtype=np.float64).reshape(-1, 3),
                       points=counts_arr, skipped=skipped)


def session_streams(session_dir: str | os.PathLike) -> list[tuple[str, Path, Path | None]]:
    """The session's cameras as ``(serial, recording, calibration capture or None)``, master
    first, from ``session.json`` (``kinect[].serial/file/calibration_capture/sync``), else the
    ``kinect/*.mkv`` files in name order.

    Raises:
        FileNotFoundError: no camera recordings in the session.
        ValueError: a malformed ``session.json``.
    """
    root = Path(session_dir)
    files = session_files(root)  # SessionLayoutError (a ValueError) when malformed
    out = [(c.serial, c.recording, c.calibration_capture, c.sync) for c in files.cameras
           if c.recording is not None]
    if not out:
        raise FileNotFoundError(f"{root}: no Kinect recordings (session.json kinect[].file or "
                                f"kinect/*.mkv)")
    out.sort(key=lambda e: e[3].upper() != "MASTER")  # stable: the master first
    return [(s, f, c) for s, f, c, _ in out]


def session_tracks(session_dir: str | os.PathLike,
                   extrinsics: Extrinsics | Mapping[str, np.ndarray], *,
                   config: TrackConfig | None = None,
                   backgrounds: Mapping[str, BackgroundModel] | None = None,
                   progress: bool = False, pool: Pool = None) -> list[CameraTrack]:
    """:func:`camera_track` for every camera of a session folder, master first.

    Backgrounds: ``backgrounds[serial]`` when given; else the camera's empty-room recording
    (:func:`~couch.capture.segmentation.empty_room_recording`); else the calibration capture and
    the session recording combined (see :func:`~couch.capture.segmentation.
    background_from_recordings`).

    Args:
        session_dir: the session folder.
        extrinsics: :class:`~couch.capture.calibration.Extrinsics` or ``serial -> (4,4)
            world_from_depth``.
        config: see :class:`TrackConfig`.
        backgrounds: ready background models per serial.
        progress: progress bars (over the cameras; and over each one's frames without a
            ``pool``).
        pool: where the cameras' passes run (:func:`couch.pool.spawn_pool`, one camera per
            task); None: one after another here. The tracks are the same either way.

    Raises:
        KeyError: a camera without a pose in ``extrinsics`` (the message names it).
    """
    cfg = config or TrackConfig()
    tasks = []
    for serial, path, calibration in session_streams(session_dir):
        if isinstance(extrinsics, Extrinsics):
            if serial not in extrinsics.cameras:
                raise KeyError(f"no extrinsics for camera {serial} ({path})")
            pose = extrinsics.world_from_depth(serial)
        else:
            if serial not in extrinsics:
                raise KeyError(f"no extrinsics for camera {serial} ({path})")
            pose = np.asarray(extrinsics[serial])
        bg = backgrounds.get(serial) if backgrounds is not None else None
        if bg is None:
            empty = empty_room_recording(session_dir, serial)
            bg = [empty] if empty is not None else [p for p in (calibration, path)
                                                    if p is not None]
        tasks.append((path, pose, bg, cfg, progress and pool is None))
    return pool_map(pool, _track, tasks, desc="camera signals" if progress else None,
                    unit="camera")


def _track(path: Path, pose: np.ndarray, background: BackgroundModel | list[Path],
           config: TrackConfig, progress: bool) -> CameraTrack:
    """One camera's :func:`camera_track`, its background model built first from the
    recordings listed (a pool task: plain arguments)."""
    if not isinstance(background, BackgroundModel):
        background = background_from_recordings(background, config.segmentation)
    return camera_track(path, pose, background, config=config, progress=progress)
