"""Fused world point clouds of the person (and the chair) from all cameras of one frame.

Per camera: the masked depth pixels → camera-frame points → world through that camera's
``world_from_depth``. Normals come from the depth image itself, which is an organised cloud: at
every pixel a plane is fitted (least squares of the 3-D point on the pixel offsets) to the masked
pixels of its ``normal_window`` x ``normal_window`` neighbourhood, as PCL's integral-image normals
do — a few box filters over the mask's bounding box instead of a k-d tree (open3d's
``estimate_normals`` took ~8x longer, for the same 8° median error against the simulator's
surface). Each normal faces its camera (a depth camera only sees surfaces that face it).
Points farther than ``outlier_distance`` from their own plane fit (a flying pixel that survived
the mask, a window straddling two surfaces) are dropped — the statistical outlier removal this
replaces changed no distance to the simulator's surface and cost as much as the normals — then
each camera's cloud is voxel-downsampled (open3d, averaging points and normals).

Downsampling each camera separately keeps every point's camera id exact and its normal oriented
by the camera that measured it; where views overlap the fused cloud is denser, which a fitter
weighting by point is free to correct with :attr:`FusedCloud.camera`.

World frame: metres, Y up, floor y = 0 (DESIGN.md).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import cv2
import numpy as np
import open3d as o3d

from couch.geometry import apply_transform

from .azure_calibration import KinectCalibration
from .registration import pixel_rays

__all__ = ["CloudConfig", "FusedCloud", "camera_cloud", "fuse_clouds"]


@dataclasses.dataclass(frozen=True)
class CloudConfig:
    """Knobs of the fused clouds (lengths in metres)."""

    voxel: float = 0.005  # voxel downsample per camera; 0 = none
    normal_window: int = 5  # pixels: the neighbourhood of each point's plane fit (odd)
    outlier_distance: float = 0.01  # a point this far from its plane fit is dropped; 0 = keep
    min_points: int = 10  # a camera contributing fewer points than this is left out
    # measure each camera's systematic depth error on the floor of a few frames and take it out
    # of its depth before the points are made (couch.capture.depth_bias); False: as recorded
    depth_bias: bool = True
    bias_frames: int = 5


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
        config: normals, outliers and downsampling.

    Returns:
        open3d ``PointCloud`` in world metres with unit normals (may be empty).
    """
    cfg = config or CloudConfig()
    pts, nrm = _camera_points_normals(depth_mm, mask, calib, cfg)
    pose = np.asarray(world_from_depth, dtype=np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(apply_transform(pose, pts)))
    pcd.normals = o3d.utility.Vector3dVector(nrm.astype(np.float64) @ pose[:3, :3].T)
    if cfg.voxel > 0 and len(pts):
        pcd = pcd.voxel_down_sample(cfg.voxel)
        # averaged normals are no longer unit length
        n = np.asarray(pcd.normals)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return pcd


def _camera_points_normals(depth_mm: np.ndarray, mask: np.ndarray, calib: KinectCalibration,
                           cfg: CloudConfig) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N,3) float64 m of the masked valid pixels and their unit normals
    (N,3) float32 facing the camera (see the module doc), outliers dropped."""
    depth = np.asarray(depth_mm)
    rays = pixel_rays(calib.depth)
    if depth.shape != rays.shape[:2] or mask.shape != depth.shape:
        raise ValueError(f"depth {depth.shape} and mask {np.shape(mask)} must match the depth "
                         f"camera's {rays.shape[:2]} pixels")
    sel = np.asarray(mask, dtype=bool) & (depth > 0) & np.isfinite(rays[..., 0])
    r = cfg.normal_window // 2
    x, y, w, h = cv2.boundingRect(sel.view(np.uint8))
    if w == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    box = (slice(max(0, y - r), y + h + r), slice(max(0, x - r), x + w + r))
    sel_b = sel[box]
    z = np.where(sel_b, depth[box], 0).astype(np.float32) * np.float32(1e-3)
    xy = np.nan_to_num(rays[box]).astype(np.float32) * z[..., None]
    # (h,w,4): weight, then the weighted camera-frame point (0 outside the mask)
    wp = np.dstack([sel_b.astype(np.float32), xy, z])
    points = wp[sel_b][:, 1:]
    centre, du, dv = _plane_fit(wp, sel_b, r)
    normals = np.cross(du, dv)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), np.float32(1e-12))
    # a depth camera sees the side of a surface facing it: n·(0 - p) > 0
    normals *= np.where(np.einsum("nk,nk->n", normals, points) > 0, -1, 1)[:, None].astype(
        np.float32)
    keep = np.isfinite(normals).all(axis=1)
    if cfg.outlier_distance > 0:
        keep &= np.abs(np.einsum("nk,nk->n", points - centre, normals)) <= cfg.outlier_distance
    return points[keep].astype(np.float64), normals[keep]


def _plane_fit(wp: np.ndarray, sel: np.ndarray, r: int,
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least-squares plane through each selected pixel's (2r+1)² neighbourhood of an
    organised cloud: p(q) ≈ c + a·(u_q - u) + b·(v_q - v).

    Args:
        wp: (h,w,4) float32: per pixel the weight w (0: no point) and w times its 3-D point.
        sel: (h,w) bool, the N pixels to fit at.

    Returns:
        c, a, b: (N,3) float32 each: the plane's point at the pixel and its tangents ∂p/∂u,
        ∂p/∂v (NaN where the pixels around do not span a plane).
    """
    k = 2 * r + 1
    off = np.arange(-r, r + 1, dtype=np.float32)
    ku, kv = np.tile(off, (k, 1)), np.tile(off[:, None], (1, k))

    def corr(a: np.ndarray, kernel: np.ndarray) -> np.ndarray:
        """Σ over the neighbourhood of kernel(offset) · a(neighbour), at the N pixels."""
        return cv2.filter2D(a, cv2.CV_32F, kernel, borderType=cv2.BORDER_CONSTANT)[sel]

    s0, su, sv = (corr(wp, kern) for kern in (np.ones((k, k), np.float32), ku, kv))  # (N,4)
    w = wp[..., 0]
    suu, suv, svv = (corr(w, kern) for kern in (ku * ku, ku * kv, kv * kv))  # (N,)
    n = s0[:, 0]
    mu, mv, mp = su[:, 0] / n, sv[:, 0] / n, s0[:, 1:] / n[:, None]
    cuu, cuv, cvv = suu / n - mu * mu, suv / n - mu * mv, svv / n - mv * mv
    cup = su[:, 1:] / n[:, None] - mu[:, None] * mp
    cvp = sv[:, 1:] / n[:, None] - mv[:, None] * mp
    det = cuu * cvv - cuv * cuv
    with np.errstate(invalid="ignore", divide="ignore"):
        det = np.where(det > 0.05, det, np.float32(np.nan))[:, None]
        a = (cvv[:, None] * cup - cuv[:, None] * cvp) / det
        b = (cuu[:, None] * cvp - cuv[:, None] * cup) / det
    centre = mp - mu[:, None] * a - mv[:, None] * b
    return centre, a, b


def fuse_clouds(depths: Sequence[np.ndarray | None], masks: Sequence[np.ndarray | None],
                calibs: Sequence[KinectCalibration], world_from_depth: Sequence[np.ndarray],
                time: float, config: CloudConfig | None = None) -> FusedCloud:
    """Fuse one frame's masked depth from every camera into one world cloud.

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
    return FusedCloud(points=np.concatenate(pts).astype(np.float32),
                      normals=np.concatenate(nrm).astype(np.float32),
                      camera=np.concatenate(cam), time=float(time))
