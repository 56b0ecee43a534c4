"""Fused world point clouds of the person (and the chair) from all cameras of one frame.

Per camera: the masked depth pixels → camera-frame points (:func:`depth_to_points`) → world
through that camera's ``world_from_depth``; normals by open3d (``estimate_normals``, a local
plane fit over the nearest neighbours) oriented towards that camera's centre (a depth camera only
sees surfaces that face it); a voxel downsample. The cameras' clouds are then concatenated and
cleaned with open3d's statistical outlier removal (after the downsample: it costs ~1-3 s on 300k
points, see specs/dependencies.md; radius outlier removal is avoided, it is slower still).

Downsampling each camera separately keeps every point's camera id exact and its normal oriented
by the camera that measured it; where views overlap the fused cloud is denser, which a fitter
weighting by point is free to correct with :attr:`FusedCloud.camera`.

World frame: metres, Y up, floor y = 0 (DESIGN.md).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import open3d as o3d

from couch.geometry import apply_transform

from .azure_calibration import KinectCalibration
from .registration import depth_to_points

__all__ = ["CloudConfig", "FusedCloud", "camera_cloud", "fuse_clouds"]


@dataclasses.dataclass(frozen=True)
class CloudConfig:
    """Knobs of the fused clouds (lengths in metres)."""

    voxel: float = 0.005  # voxel downsample per camera; 0 = none
    normal_radius: float = 0.03  # neighbourhood of the normal's plane fit ...
    normal_neighbours: int = 20  # ... at most this many points
    outlier_neighbours: int = 20  # statistical outlier removal: neighbours considered ...
    outlier_std: float = 2.0  # ... and the std ratio beyond which a point is dropped
    min_points: int = 10  # a camera contributing fewer points than this is left out


@dataclasses.dataclass
class FusedCloud:
    """One frame's point cloud of one object (person or chair), fused over cameras.

    Attributes:
        points: (N,3) float32 world metres.
        normals: (N,3) float32 unit normals, each facing the camera that measured the point.
        camera: (N,) int8 index of that camera (the order of the inputs to :func:`fuse_clouds`).
        time: the frame's time in seconds (the caller's clock: Kinect master clock after sync).
    """

    points: np.ndarray
    normals: np.ndarray
    camera: np.ndarray
    time: float

    def __len__(self) -> int:
        return len(self.points)

    def to_open3d(self) -> o3d.geometry.PointCloud:
        """The cloud as an open3d legacy ``PointCloud`` (points and normals)."""
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points.astype(np.float64)))
        pcd.normals = o3d.utility.Vector3dVector(self.normals.astype(np.float64))
        return pcd


def camera_cloud(depth_mm: np.ndarray, mask: np.ndarray, calib: KinectCalibration,
                 world_from_depth: np.ndarray, config: CloudConfig | None = None,
                 ) -> o3d.geometry.PointCloud:
    """World points of one camera's masked depth pixels, with camera-facing normals, downsampled.

    Args:
        depth_mm: (H,W) uint16 mm Z-depth of the depth camera.
        mask: (H,W) bool pixels to use (e.g. ``FrameSegmentation.person_reliable``).
        calib: the device.
        world_from_depth: (4,4) world pose of the depth camera (metres).
        config: downsampling and normal estimation.

    Returns:
        open3d ``PointCloud`` in world metres with normals (may be empty).
    """
    cfg = config or CloudConfig()
    masked = np.where(mask, depth_mm, 0).astype(np.uint16)
    pts = depth_to_points(masked, calib.depth)
    pose = np.asarray(world_from_depth, dtype=np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(apply_transform(pose, pts)))
    if len(pts) < 3:
        return pcd
    if cfg.voxel > 0:
        pcd = pcd.voxel_down_sample(cfg.voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.normal_radius,
                                                              max_nn=cfg.normal_neighbours))
    pcd.orient_normals_towards_camera_location(pose[:3, 3])
    return pcd


def fuse_clouds(depths: Sequence[np.ndarray | None], masks: Sequence[np.ndarray | None],
                calibs: Sequence[KinectCalibration], world_from_depth: Sequence[np.ndarray],
                time: float, config: CloudConfig | None = None) -> FusedCloud:
    """Fuse one frame's masked depth from every camera into one cleaned world cloud.

    Args:
        depths: per camera (H,W) uint16 mm depth, or None where the camera dropped the frame.
        masks: per camera (H,W) bool pixels to use (None: camera skipped).
        calibs: per camera calibration.
        world_from_depth: per camera (4,4) world pose of the depth camera.
        time: the frame's time (s), stored in the result.
        config: see :class:`CloudConfig`.

    Returns:
        :class:`FusedCloud`; empty (0 points) when no camera saw anything.
    """
    cfg = config or CloudConfig()
    if not (len(depths) == len(masks) == len(calibs) == len(world_from_depth)):
        raise ValueError(f"need one depth, mask, calibration and pose per camera; got "
                         f"{len(depths)}, {len(masks)}, {len(calibs)}, {len(world_from_depth)}")
    if len(depths) > np.iinfo(np.int8).max:
        raise ValueError(f"at most {np.iinfo(np.int8).max} cameras fit the int8 camera ids")
    pts, nrm, cam = [], [], []
    for i, (depth, mask, calib, pose) in enumerate(zip(depths, masks, calibs, world_from_depth,
                                                       strict=True)):
        if depth is None or mask is None:
            continue
        pcd = camera_cloud(depth, mask, calib, pose, cfg)
        if len(pcd.points) < cfg.min_points:
            continue
        pts.append(np.asarray(pcd.points))
        nrm.append(np.asarray(pcd.normals))
        cam.append(np.full(len(pcd.points), i, np.int8))
    if not pts:
        return FusedCloud(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                          np.zeros(0, np.int8), float(time))
    fused = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(pts)))
    normals, camera = np.concatenate(nrm), np.concatenate(cam)
    if len(fused.points) > cfg.outlier_neighbours:
        _, keep = fused.remove_statistical_outlier(cfg.outlier_neighbours, cfg.outlier_std)
        keep = np.asarray(keep, dtype=np.int64)
    else:
        keep = np.arange(len(fused.points))
    return FusedCloud(points=np.asarray(fused.points)[keep].astype(np.float32),
                      normals=normals[keep].astype(np.float32), camera=camera[keep],
                      time=float(time))
