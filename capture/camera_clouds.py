"""One camera's share of a session's fused clouds, made where the camera's recording is read.

A stage that fuses clouds over cameras (the person for the body fits, what may be the chair for
its registration) does the same per camera: segment the recording, measure the camera's depth
error on the floor, correct the depth, mask the frames it needs and lift them to world points.
:func:`camera_clouds` does all of that for one camera and returns only the points (a few
thousand per frame, where the segmented frames are hundreds of kilobytes each), so the cameras
can be spread over worker processes (:func:`couch.pool.pool_map`); :func:`join_cameras` then
puts a frame's points together in camera order, exactly as :func:`~couch.capture.pointcloud.
fuse_clouds` would have from the same masks.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable, Sequence

import numpy as np

from .azure_calibration import KinectCalibration
from .depth_bias import DepthBias, recording_depth_bias
from .pointcloud import CloudConfig, FusedCloud, camera_cloud
from .segmentation import (
    CameraSegmentation,
    ChairModel,
    FrameSegmentation,
    SegmentationConfig,
    segment_recording,
)

__all__ = ["CameraClouds", "camera_clouds", "join_cameras", "join_row", "person_mask"]

MaskFn = Callable[..., np.ndarray]
"""``mask(frame, segmentation, depth=depth)`` → (H,W) bool pixels to lift, given the frame's
:class:`FrameSegmentation`, the camera's :class:`CameraSegmentation` and the frame's corrected
(H,W) uint16 mm depth; a module-level function (or a ``functools.partial`` of one) so that it
pickles."""


def person_mask(frame: FrameSegmentation, segmentation: CameraSegmentation,
                depth: np.ndarray | None = None) -> np.ndarray:
    """(H,W) bool: the frame's person without its depth-edge pixels (``person_reliable``)."""
    return frame.person_reliable


@dataclasses.dataclass
class CameraClouds:
    """One camera's world points of the frames asked for.

    Attributes:
        serial: the camera's serial (or the recording's stem).
        recording: the recording read.
        calibration: the device's calibration; world_from_depth: (4,4) its depth camera's pose.
        background: (H,W) float32 metres, the background model's depth.
        skipped: captures of the recording without usable depth.
        depth_bias: the camera's measured depth error (None: not measured or too little floor).
        timestamps: (K,) int64 device µs of the frames kept, in recording order.
        points, normals: K arrays (N_k,3) float32, world metres; empty where fewer than
            ``CloudConfig.min_points`` survived (as :func:`fuse_clouds` leaves a camera out).
        far: (H,W) uint16 mm, the farthest corrected depth of each pixel over the kept frames
            (0: never valid), or None when not asked for.
        depth_range: (min, max) metres of Z the camera measures (its recorded mode's, binned
            or not: :attr:`CameraSegmentation.depth_range`), or None.
    """

    serial: str
    recording: str
    calibration: KinectCalibration
    world_from_depth: np.ndarray
    background: np.ndarray
    skipped: int
    depth_bias: DepthBias | None
    timestamps: np.ndarray
    points: list[np.ndarray]
    normals: list[np.ndarray]
    far: np.ndarray | None = None
    depth_range: tuple[float, float] | None = None

    def frame(self, timestamp_us: int) -> int | None:
        """Index of the kept frame with this device timestamp, or None."""
        return self._index.get(int(timestamp_us))

    @functools.cached_property
    def _index(self) -> dict[int, int]:
        return {int(t): k for k, t in enumerate(self.timestamps)}


def camera_clouds(recording: str | os.PathLike, world_from_depth: np.ndarray, *,
                  empty_room: str | os.PathLike | None = None,
                  background_paths: Sequence[str | os.PathLike] = (),
                  chair: ChairModel | None = None,
                  segmentation: SegmentationConfig | None = None,
                  cloud: CloudConfig | None = None, mask: MaskFn = person_mask,
                  timestamps: Sequence[int] | np.ndarray | None = None,
                  indices: Sequence[int] | np.ndarray | None = None, step: int = 1,
                  bias_on_all: bool = False, person_dilate_px: int = 3,
                  far: bool = False) -> CameraClouds:
    """Segment one camera's recording (:func:`segment_recording`), measure its depth error
    (:func:`recording_depth_bias`, with ``cloud.depth_bias``), and lift the ``mask`` of the
    frames asked for, depth corrected, to world points (:func:`camera_cloud`).

    Args:
        recording, world_from_depth, empty_room, background_paths, chair, segmentation: as
            :func:`segment_recording`.
        cloud: points, normals and the depth error's frames.
        mask: which pixels of a frame to lift (see :data:`MaskFn`; default the person's).
        timestamps: device µs of the frames to keep; indices: positions among the usable
            captures instead; neither: every ``step``-th.
        bias_on_all: measure the depth error on ``cloud.bias_frames`` frames spread over every
            usable capture (segmenting them too) rather than over the frames asked for.
        person_dilate_px: the person's growth when the depth error leaves it out.
        far: also return the farthest depth per pixel over the kept frames.

    Raises:
        SegmentationError, KinectFormatError: from :func:`segment_recording`.
    """
    cloud = cloud or CloudConfig()
    pose = np.asarray(world_from_depth, np.float64)
    usable = np.zeros(0, np.int64)  # every usable capture's timestamp, set by select()

    def kept(stamps: np.ndarray) -> np.ndarray:
        """The timestamps of the frames asked for, in the order asked."""
        if timestamps is not None:
            return stamps[np.isin(stamps, np.asarray(timestamps, np.int64))]
        if indices is not None:
            return stamps[np.asarray(indices, int)]
        return stamps[::max(1, int(step))]

    def bias_stamps(stamps: np.ndarray) -> np.ndarray:
        # recording_depth_bias's frames, spread over the usable captures
        picks = np.unique(np.linspace(0, len(stamps) - 1, cloud.bias_frames).round().astype(int))
        return stamps[picks] if cloud.depth_bias and cloud.bias_frames >= 1 else stamps[:0]

    def select(stamps: np.ndarray) -> set[int]:
        nonlocal usable
        usable = stamps
        more = bias_stamps(stamps) if bias_on_all else stamps[:0]
        return {int(t) for t in np.concatenate([kept(stamps), more])}

    seg = segment_recording(recording, pose, empty_room=empty_room,
                            background_paths=background_paths, chair=chair,
                            config=segmentation, timestamps=select)
    by_stamp = {f.timestamp_us: f for f in seg.frames}
    frames = [by_stamp[int(t)] for t in kept(usable)]
    bias = None
    if cloud.depth_bias:
        on = [by_stamp[int(t)] for t in bias_stamps(usable)] if bias_on_all else frames
        # recording_depth_bias spreads its picks over the frames it is given: with bias_on_all
        # those are already the picks, so it takes every one
        bias = recording_depth_bias(dataclasses.replace(seg, frames=on),
                                    len(on) if bias_on_all else cloud.bias_frames,
                                    person_dilate_px)
    fix = bias.corrector(seg.calibration) if bias is not None else None
    points, normals = [], []
    farthest = np.zeros(seg.background.depth.shape, np.uint16) if far else None
    empty = np.zeros((0, 3), np.float32)
    for f in frames:
        depth = f.depth_mm if fix is None else fix(f.depth_mm)
        pcd = camera_cloud(depth, mask(f, seg, depth=depth), seg.calibration, pose, cloud)
        keep = len(pcd.points) >= cloud.min_points
        points.append(np.asarray(pcd.points, np.float32) if keep else empty)
        normals.append(np.asarray(pcd.normals, np.float32) if keep else empty)
        if farthest is not None:
            np.maximum(farthest, depth, out=farthest)
    return CameraClouds(serial=seg.serial, recording=str(recording), calibration=seg.calibration,
                        world_from_depth=pose, background=seg.background.depth,
                        skipped=len(seg.skipped), depth_bias=bias,
                        timestamps=np.array([f.timestamp_us for f in frames], np.int64),
                        points=points, normals=normals, far=farthest,
                        depth_range=seg.depth_range)


def join_cameras(parts: Sequence[CameraClouds], frames: Sequence[int | None], time: float
                 ) -> FusedCloud:
    """One frame's cloud: camera c's kept frame ``frames[c]`` (an index into its lists, None:
    the camera has no frame here), in camera order, with camera ids c."""
    pts, nrm, cam = [], [], []
    for c, (part, k) in enumerate(zip(parts, frames, strict=True)):
        if k is None or not len(part.points[k]):
            continue
        pts.append(part.points[k])
        nrm.append(part.normals[k])
        cam.append(np.full(len(part.points[k]), c, np.int8))
    if not pts:
        return FusedCloud(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                          np.zeros(0, np.int8), float(time))
    return FusedCloud(np.concatenate(pts), np.concatenate(nrm), np.concatenate(cam), float(time))


def join_row(parts: Sequence[CameraClouds], row: np.ndarray, stamps: Sequence[np.ndarray],
             time: float) -> FusedCloud:
    """:func:`join_cameras` of one row of a frame table: camera c's frame ``row[c]`` of its
    recording (< 0: dropped), found among its kept frames by its device timestamp
    ``stamps[c][row[c]]``."""
    return join_cameras(parts, [p.frame(int(s[k])) if k >= 0 else None
                                for p, s, k in zip(parts, stamps, row, strict=True)], time)
