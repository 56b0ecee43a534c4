"""Depth ↔ colour geometry of one Azure Kinect: pixel rays, depth → points, and the registration
of a depth image into the colour camera (what BEHAVE's ``k{i}.depth.png`` files hold).

Public API
----------
* :func:`pixel_rays` — (H,W,2) normalised ray of every pixel centre of a camera (NaN: invalid).
* :func:`unproject_pixels` — the same for arbitrary pixel coordinates.
* :func:`project_points` — camera-frame points → pixels (+ validity), OpenCV rational model.
* :func:`depth_to_points` — (H,W) uint16 mm depth → (N,3) metres in that camera's frame.
* :func:`register_depth_to_color` — depth image → depth image in the colour camera's pixels.

Frames and units: cameras are OpenCV/SDK style (+X right, +Y down, +Z forward); pixel centres are
at integer coordinates (see :mod:`couch.capture.azure_calibration`); depth images are uint16
millimetres of **Z** (not range) with 0 = invalid; points are metres.

What :func:`register_depth_to_color` reproduces (Azure-Kinect-Sensor-SDK at commit 8bb59ca,
``src/transformation/rgbz.c`` ``transformation_depth_to_color`` and helpers, and
``intrinsic_transformation.c``), i.e. ``k4a_transformation_depth_image_to_color_camera``:

1. Every depth pixel with depth > 0 and a valid xy-table entry becomes a 3-D point
   ``(x·d, y·d, d)``; the xy table holds each pixel centre's undistorted ray and marks pixels
   whose iterative unprojection does not converge (squared reprojection error > 1e-6 px²) or
   leaves the metric radius as invalid (``transformation_init_xy_tables``,
   ``transformation_iterative_unproject``).
2. The point is moved into the colour camera (``color_from_depth``); its colour-camera Z is the
   value written, and it is projected with the colour lens; projections with Z <= 0 or
   ``x²+y² > metric_radius²`` are invalid (``transformation_project``).
3. Each 2x2 block of neighbouring depth pixels forms a quad (top-left, top-right, bottom-right,
   bottom-left). With one invalid corner the corner is replaced as
   ``transformation_check_valid_correspondences`` does; with two or more the quad is dropped;
   a quad whose depths differ by more than ``0.04693441759 · min depth`` spans an occlusion edge
   and is dropped too (no interpolation across depth discontinuities).
4. Each colour pixel centre inside the quad's bounding box (``ceil`` of the corner extremes,
   clipped) that lies inside one of its two triangles (split along top-left → bottom-right;
   top/left edges inclusive, bottom/right exclusive) gets the barycentric interpolation of the
   corner depths, rounded ``(uint16)(d + 0.5)``; the nearest surface wins (z-buffer).

Differences: numpy float64 instead of the SDK's float32 (pixels exactly on a triangle edge may
fall to the other side); OpenCV's ``undistortPoints`` (run to convergence) replaces the SDK's
Newton iteration; projection is :func:`distort`, a numpy transcription of OpenCV's rational
model (equal to ``cv2.projectPoints`` to 1e-8 px in the tests, ~20x faster); a quad with zero
area writes nothing (the SDK would write 0). Speed on this project's 2-core machines: ~0.6 s per
frame into 720P colour, ~0.8 s into 1536P.

Because the quads tile the surface, the result is as dense as the colour image wherever the
depth camera saw a continuous surface (no speckle where colour pixels are denser than depth
pixels). Everything is vectorised over pixels and quads.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from .azure_calibration import CameraIntrinsics, KinectCalibration

__all__ = [
    "UNDISTORT_CRITERIA",
    "depth_to_points",
    "distort",
    "pixel_rays",
    "project_points",
    "register_depth_to_color",
    "unproject_pixels",
]

#: Termination of ``cv2.undistortPoints``: its default (5 iterations) leaves up to ~3 px of error
#: in the corners of a Kinect depth image, whose rational lens moves the corners by ~100 px.
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-13)

# The SDK's convergence test on the squared reprojection error (px²) of an unprojected pixel.
_MAX_UNPROJECT_ERR2 = 1e-6
# rgbz.c: a quad whose depth range exceeds this fraction of its nearest depth spans an edge.
_SKIP_INTERPOLATION_RATIO = 0.04693441759
# Candidate (quad, pixel) pairs handled per chunk: bounds memory to ~100 MB whatever the input.
_CHUNK_CANDIDATES = 2_000_000


def _check_intrinsics(intr: CameraIntrinsics) -> None:
    if not isinstance(intr, CameraIntrinsics):
        raise TypeError(f"expected CameraIntrinsics, got {type(intr).__name__}")


def _distorted_r2_ok(xy: np.ndarray, intr: CameraIntrinsics) -> np.ndarray:
    """(N,) bool: normalised points inside the lens model's metric radius."""
    return (xy[:, 0] ** 2 + xy[:, 1] ** 2) <= intr.metric_radius**2


def distort(xy: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """Normalised undistorted ``(x, y)`` (N,2) → pixels (N,2): OpenCV's rational model.

    ``r² = x²+y²``, ``x' = x·(1+k1r²+k2r⁴+k3r⁶)/(1+k4r²+k5r⁴+k6r⁶) + 2p1xy + p2(r²+2x²)``,
    ``y' = y·(...) + p1(r²+2y²) + 2p2xy``, ``u = fx·x' + cx``, ``v = fy·y' + cy`` — what
    ``cv2.projectPoints`` computes (the tests compare both), in numpy because ``projectPoints``
    is ~20x slower here (it also builds Jacobians).
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    k1, k2, p1, p2, k3, k4, k5, k6 = intrinsics.dist
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([intrinsics.fx * xd + intrinsics.cx, intrinsics.fy * yd + intrinsics.cy],
                    axis=1)


def project_points(points: np.ndarray, intrinsics: CameraIntrinsics,
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points into the image with the lens distortion.

    Args:
        points: (N,3) points in the camera's frame (any length unit; only ratios matter).
        intrinsics: the camera (OpenCV rational model, pixels).

    Returns:
        uv: (N,2) float64 pixel coordinates (pixel centres at integers), as
            ``cv2.projectPoints`` gives them; NaN where invalid.
        valid: (N,) bool — Z > 0 and the normalised point within ``metric_radius`` (beyond it
            the polynomial lens model is meaningless; the SDK marks such projections invalid).
            Points projecting outside the image are *valid* here; callers clip to the image.
    """
    _check_intrinsics(intrinsics)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    uv = np.full((len(p), 2), np.nan)
    z = p[:, 2]
    valid = z > 0
    xy = np.zeros((len(p), 2))
    np.divide(p[:, :2], z[:, None], out=xy, where=valid[:, None])
    valid &= _distorted_r2_ok(xy, intrinsics)
    uv[valid] = distort(xy[valid], intrinsics)
    return uv, valid


def unproject_pixels(uv: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """Undistorted normalised rays ``(x, y)`` (the ray is ``(x, y, 1)``) of pixel coordinates.

    ``cv2.undistortPoints`` with :data:`UNDISTORT_CRITERIA`; a pixel whose result does not
    reproject onto it (squared error > 1e-6 px², the SDK's test) or lies beyond the metric radius
    is invalid, as in the SDK's xy tables.

    Args:
        uv: (N,2) pixel coordinates (pixel centres at integers).
        intrinsics: the camera.

    Returns:
        (N,2) float64 normalised coordinates on the z = 1 plane; NaN rows are invalid.
    """
    _check_intrinsics(intrinsics)
    pix = np.ascontiguousarray(np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2))
    if len(pix) == 0:
        return np.zeros((0, 2))
    xy = cv2.undistortPoints(pix, intrinsics.K(), intrinsics.dist, None, None, None,
                             UNDISTORT_CRITERIA).reshape(-1, 2)
    back, valid = project_points(np.concatenate([xy, np.ones((len(xy), 1))], axis=1),
                                 intrinsics)
    err2 = np.sum((back - pix.reshape(-1, 2)) ** 2, axis=1)
    valid &= np.isfinite(err2) & (err2 <= _MAX_UNPROJECT_ERR2)
    xy[~valid] = np.nan
    return xy


# A 2048x1536 colour table is 50 MB: keep a 4-camera rig (depth + colour) and no more.
@functools.lru_cache(maxsize=8)
def _pixel_rays_cached(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                       dist: tuple[float, ...], metric_radius: float) -> np.ndarray:
    intr = CameraIntrinsics(width, height, fx, fy, cx, cy, np.asarray(dist), metric_radius)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    xy = unproject_pixels(np.stack([u, v], axis=-1).reshape(-1, 2), intr)
    xy = xy.reshape(height, width, 2)
    xy.setflags(write=False)
    return xy


def pixel_rays(intrinsics: CameraIntrinsics) -> np.ndarray:
    """(H,W,2) float64 normalised ray ``(x, y)`` of every pixel centre (the SDK's xy table).

    NaN where the unprojection is invalid (see :func:`unproject_pixels`). Cached for the 8 most
    recent intrinsics (about 0.2 s for a 640x576 depth image, 0.5 s for 1280x720 colour on first
    use; 50 MB for 2048x1536); read-only.
    """
    _check_intrinsics(intrinsics)
    return _pixel_rays_cached(intrinsics.width, intrinsics.height, intrinsics.fx,
                              intrinsics.fy, intrinsics.cx, intrinsics.cy,
                              tuple(float(d) for d in intrinsics.dist),
                              intrinsics.metric_radius)


def _check_depth(depth_mm: np.ndarray, intr: CameraIntrinsics, what: str) -> np.ndarray:
    depth = np.asarray(depth_mm)
    if depth.shape != (intr.height, intr.width):
        raise ValueError(f"{what} must be ({intr.height}, {intr.width}) to match its "
                         f"intrinsics, got shape {depth.shape}")
    if depth.dtype != np.uint16:
        raise ValueError(f"{what} must be uint16 millimetres, got dtype {depth.dtype}")
    return depth


def depth_to_points(depth_mm: np.ndarray, intrinsics: CameraIntrinsics, *,
                    return_valid: bool = False,
                    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Back-project a depth image into a point cloud in that camera's frame.

    Works for raw depth (with ``calib.depth``) and for registered depth (with ``calib.color``:
    points in the colour camera, as BEHAVE's ``pointcloud_table.npy`` gives them).

    Args:
        depth_mm: (H,W) uint16 Z-depth in millimetres, 0 = invalid, in ``intrinsics``' pixels.
        intrinsics: the camera the depth image belongs to.
        return_valid: also return the (H,W) bool mask of the pixels that produced points.

    Returns:
        (N,3) float64 metres in the camera frame, one per valid pixel in row-major order
        (valid: depth > 0 and a valid pixel ray); with ``return_valid`` also the mask.
    """
    depth = _check_depth(depth_mm, intrinsics, "depth_mm")
    rays = pixel_rays(intrinsics)
    valid = (depth > 0) & np.isfinite(rays[..., 0])
    z = depth[valid].astype(np.float64) / 1000.0
    points = np.empty((len(z), 3))
    points[:, :2] = rays[valid] * z[:, None]
    points[:, 2] = z
    return (points, valid) if return_valid else points


def _area(ax: np.ndarray, ay: np.ndarray, bx: np.ndarray, by: np.ndarray, cx: np.ndarray,
          cy: np.ndarray) -> np.ndarray:
    """rgbz.c ``transformation_area_function``: twice the signed area of (a, b, c)."""
    return (cy - ay) * (bx - ax) - (cx - ax) * (by - ay)


def _quad_corners(u: np.ndarray, v: np.ndarray, z: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """The SDK's quads over 2x2 depth-pixel blocks, with one invalid corner replaced.

    Args:
        u, v, z, ok: (H,W) colour-pixel coordinates, colour-camera depth (mm) and validity of
            every depth pixel's correspondence.

    Returns:
        (Q,4,3) float64 ``(u, v, z)`` of the top-left, top-right, bottom-right and bottom-left
        corners of every quad kept (at most one invalid corner, no depth discontinuity).
    """
    def block(a: np.ndarray) -> list[np.ndarray]:
        return [a[:-1, :-1], a[:-1, 1:], a[1:, 1:], a[1:, :-1]]  # TL, TR, BR, BL

    valid = np.stack(block(ok), axis=-1)  # (H-1,W-1,4)
    keep = valid.sum(axis=-1) >= 3
    if not np.any(keep):
        return np.zeros((0, 4, 3))
    vals = np.stack([np.stack(block(a), axis=-1) for a in (u, v, z)], axis=-1)  # (...,4,3)
    c = vals[keep]  # (Q,4,3)
    bad = ~valid[keep]
    tl, tr, br, bl = (c[:, i].copy() for i in range(4))
    # transformation_check_valid_correspondences, for exactly one invalid corner.
    m = bad[:, 0][:, None]
    tl = np.where(m, 0.5 * (c[:, 1] + c[:, 3]), tl)
    m = bad[:, 1][:, None]
    tr = np.where(m, c[:, 2], tr)
    br = np.where(m, 0.5 * (c[:, 2] + c[:, 3]), br)
    m = bad[:, 2][:, None]
    br = np.where(m, 0.5 * (c[:, 1] + c[:, 3]), br)
    m = bad[:, 3][:, None]
    bl = np.where(m, c[:, 2], bl)
    br = np.where(m, 0.5 * (c[:, 1] + c[:, 2]), br)
    corners = np.stack([tl, tr, br, bl], axis=1)
    depths = corners[:, :, 2]
    dmin, dmax = depths.min(axis=1), depths.max(axis=1)
    continuous = (dmax - dmin) <= _SKIP_INTERPOLATION_RATIO * dmin
    return corners[continuous]


def _rasterise(corners: np.ndarray, width: int, height: int, out: np.ndarray) -> None:
    """Draw quads into the flat z-buffer ``out`` ((height*width,) uint32, 2**32-1 = empty).

    rgbz.c ``transformation_compute_bounding_box`` + ``transformation_draw_rectangle`` +
    ``transformation_point_inside_quad``, vectorised over every (quad, pixel) candidate.
    """
    u, v = corners[:, :, 0], corners[:, :, 1]
    x0 = np.maximum(np.ceil(u.min(axis=1)), 0).astype(np.int64)
    y0 = np.maximum(np.ceil(v.min(axis=1)), 0).astype(np.int64)
    x1 = np.minimum(np.ceil(u.max(axis=1)), width).astype(np.int64)
    y1 = np.minimum(np.ceil(v.max(axis=1)), height).astype(np.int64)
    bw, bh = x1 - x0, y1 - y0
    sel = (bw > 0) & (bh > 0)
    corners, x0, y0, bw, bh = corners[sel], x0[sel], y0[sel], bw[sel], bh[sel]
    count = bw * bh
    ends = np.cumsum(count)
    start = 0
    while start < len(corners):
        # Chunks of whole quads holding about _CHUNK_CANDIDATES pixels each.
        base = ends[start - 1] if start else 0
        stop = int(np.searchsorted(ends, base + _CHUNK_CANDIDATES, side="right"))
        stop = max(stop, start + 1)
        _rasterise_chunk(corners[start:stop], x0[start:stop], y0[start:stop], bw[start:stop],
                         count[start:stop], width, out)
        start = stop


def _rasterise_chunk(corners: np.ndarray, x0: np.ndarray, y0: np.ndarray, bw: np.ndarray,
                     count: np.ndarray, width: int, out: np.ndarray) -> None:
    q = np.repeat(np.arange(len(corners)), count)
    local = np.arange(len(q)) - np.repeat(np.cumsum(count) - count, count)
    px = (x0[q] + local % bw[q]).astype(np.float64)
    py = (y0[q] + local // bw[q]).astype(np.float64)
    c = corners[q]
    tl, tr, br, bl = c[:, 0], c[:, 1], c[:, 2], c[:, 3]
    a_mid = _area(tl[:, 0], tl[:, 1], br[:, 0], br[:, 1], px, py)
    ccw = a_mid >= 0
    mid = np.where(ccw[:, None], bl, tr)
    a_tl = _area(mid[:, 0], mid[:, 1], tl[:, 0], tl[:, 1], px, py)
    a_br = _area(br[:, 0], br[:, 1], mid[:, 0], mid[:, 1], px, py)
    sign = np.where(ccw, 1.0, -1.0)
    a_mid, a_tl, a_br = a_mid * sign, a_tl * sign, a_br * sign
    total = a_tl + a_mid + a_br
    inside = (a_tl >= 0) & (a_br > 0) & (total != 0)
    depth = (a_tl * br[:, 2] + a_mid * mid[:, 2] + a_br * tl[:, 2])[inside] / total[inside]
    d16 = np.floor(depth + 0.5)
    ok = (d16 >= 1) & (d16 <= 65535)
    idx = (py[inside] * width + px[inside]).astype(np.int64)[ok]
    np.minimum.at(out, idx, d16[ok].astype(np.uint32))


def register_depth_to_color(depth_mm: np.ndarray, calib: KinectCalibration) -> np.ndarray:
    """Transform a depth image into the colour camera's image (SDK semantics, see module doc).

    Args:
        depth_mm: (Hd,Wd) uint16 Z-depth in millimetres in the depth camera (``calib.depth``
            size), 0 = invalid.
        calib: the device's calibration (depth and colour intrinsics, ``color_from_depth``).

    Returns:
        (Hc,Wc) uint16 millimetres of **colour-camera Z** at each colour pixel, 0 where no depth
        pixel's surface lands (outside the depth camera's view, occlusion shadows seen only by
        the colour camera, gaps across depth discontinuities).
    """
    if not isinstance(calib, KinectCalibration):
        raise TypeError(f"expected KinectCalibration, got {type(calib).__name__}")
    depth = _check_depth(depth_mm, calib.depth, "depth_mm")
    cw, ch = calib.color.width, calib.color.height
    rays = pixel_rays(calib.depth)
    ok = (depth > 0) & np.isfinite(rays[..., 0])
    d = depth[ok].astype(np.float64)
    pts = np.empty((len(d), 3))
    pts[:, :2] = rays[ok] * d[:, None]
    pts[:, 2] = d
    # color_from_depth is in metres; the SDK transforms millimetres.
    rot = calib.color_from_depth[:3, :3]
    pts_c = pts @ rot.T + calib.color_from_depth[:3, 3] * 1000.0
    uv, proj_ok = project_points(pts_c, calib.color)

    u = np.zeros(depth.shape)
    v = np.zeros(depth.shape)
    z = np.zeros(depth.shape)
    u[ok], v[ok], z[ok] = uv[:, 0], uv[:, 1], pts_c[:, 2]
    ok[ok] = proj_ok
    corners = _quad_corners(u, v, z, ok)
    empty = np.iinfo(np.uint32).max
    zbuf = np.full(ch * cw, empty, dtype=np.uint32)
    if len(corners):
        _rasterise(corners, cw, ch, zbuf)
    zbuf[zbuf == empty] = 0
    return zbuf.astype(np.uint16).reshape(ch, cw)
