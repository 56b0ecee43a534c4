"""Simulated Azure Kinect cameras: geometry against OpenCV's camera model, the depth noise model,
colour views, and camera placement. Small scenes (planes, boxes, spheres) keep it fast.

The checks are independent of the renderer's own ray set-up: pixels are undistorted here with
``cv2.undistortPoints`` (run to convergence) and points projected with ``cv2.projectPoints``.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from couch.capture.azure_calibration import KinectCalibration
from couch.capture.segmentation import SegmentationConfig, depth_edges, flying_pixels
from couch.geometry import apply_transform, invert_transform, make_transform
from couch.tools.sim import kinect
from couch.tools.sim.kinect import DepthNoise, SceneMesh

CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
# Depth-camera pose used by most tests: the scene is built in camera coordinates and moved into
# the world with it, so poses are exercised too.
POSE = make_transform(Rotation.from_rotvec([0.2, -0.4, 0.1]).as_matrix(), [0.5, 1.4, -2.0])


@pytest.fixture(scope="module")
def calib() -> KinectCalibration:
    return kinect.random_calibration(np.random.default_rng(11))


def rays(intr: kinect.CameraIntrinsics) -> np.ndarray:
    """(H, W, 3) ray (x, y, 1) of every pixel centre, computed here with OpenCV."""
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64),
                       np.arange(intr.height, dtype=np.float64))
    xy = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), intr.K(), intr.dist,
                             None, None, None, CRITERIA).reshape(intr.height, intr.width, 2)
    return np.concatenate([xy, np.ones((*xy.shape[:2], 1))], axis=-1)


def plane(point: np.ndarray, normal: np.ndarray, size: float = 30.0, pose: np.ndarray = POSE,
          **kw: object) -> SceneMesh:
    """A square (two triangles) through ``point`` with ``normal``, given in camera coordinates."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.cross(n, [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    corners = np.asarray(point, float) + size * np.array([-a - b, a - b, a + b, -a + b])
    return SceneMesh(apply_transform(pose, corners), [[0, 1, 2], [0, 2, 3]], **kw)


def box(center: np.ndarray, extents: np.ndarray, rot: np.ndarray, pose: np.ndarray = POSE,
        **kw: object) -> SceneMesh:
    m = trimesh.creation.box(extents=extents)
    v = np.asarray(m.vertices) @ rot.T + center
    return SceneMesh(apply_transform(pose, v), np.asarray(m.faces), **kw)


def sphere(center: np.ndarray, radius: float, pose: np.ndarray = POSE, **kw: object
           ) -> SceneMesh:
    m = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    return SceneMesh(apply_transform(pose, np.asarray(m.vertices) + center),
                     np.asarray(m.faces), **kw)


# ------------------------------------------------------------------------------ geometry

def test_undistorted_grid_reprojects_to_pixel_centres(calib: KinectCalibration) -> None:
    for intr in (calib.depth, calib.color):
        xy = kinect.undistorted_grid(intr)
        pts = np.concatenate([xy.reshape(-1, 2), np.ones((xy.shape[0] * xy.shape[1], 1))], 1)
        proj, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), intr.K(), intr.dist)
        u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
        err = np.abs(proj.reshape(intr.height, intr.width, 2) - np.stack([u, v], -1))
        assert err.max() < 1e-4


def test_fronto_parallel_plane_exact_everywhere(calib: KinectCalibration) -> None:
    scene = kinect.build_scene([plane([0, 0, 1.5], [0, 0, -1])])
    frame = kinect.render_depth(scene, calib, POSE, DepthNoise.none(), np.random.default_rng(0))
    assert frame.depth_mm.shape == (576, 640) and frame.depth_mm.dtype == np.uint16
    # Every pixel, the lens-distorted corners included, reads the plane's Z-depth.
    assert np.all(frame.depth_mm == 1500)
    np.testing.assert_allclose(frame.depth_true, 1.5, atol=1e-6)
    assert np.all(frame.label == 0) and not frame.flying.any()


def test_tilted_plane_depth_and_backprojection(calib: KinectCalibration) -> None:
    p0, n = np.array([0.1, -0.05, 2.0]), np.array([0.25, -0.2, -1.0])
    n /= np.linalg.norm(n)
    scene = kinect.build_scene([plane(p0, n)])
    frame = kinect.render_depth(scene, calib, POSE, DepthNoise.none(), np.random.default_rng(0))
    r = rays(calib.depth)
    z = (n @ p0) / (r @ n)                                    # analytic Z-depth per pixel
    incidence = np.degrees(np.arccos(np.abs(r @ n) / np.linalg.norm(r, axis=-1)))
    expect_valid = (z >= 0.5) & (z <= 3.86) & (incidence < 80)
    valid = frame.depth_mm > 0
    assert expect_valid.mean() > 0.95
    np.testing.assert_array_equal(valid, expect_valid)
    # Millimetre rounding, plus a few µm of open3d's float32 ray casting.
    assert np.abs(frame.depth_mm[valid] - 1000 * z[valid]).max() <= 0.5 + 0.01
    # Back-project valid pixels with the calibration: they land on the true plane (world).
    pts_cam = r[valid] * (frame.depth_mm[valid] / 1000.0)[:, None]
    pts_world = apply_transform(POSE, pts_cam)
    n_world, p_world = POSE[:3, :3] @ n, apply_transform(POSE, p0[None])[0]
    assert np.abs((pts_world - p_world) @ n_world).max() < 1e-3


def test_projected_surface_points_land_on_their_pixels(calib: KinectCalibration) -> None:
    """cv2.projectPoints of sphere points (depth frame) gives pixels whose depth is theirs."""
    c, radius = np.array([0.3, -0.2, 1.8]), 0.4
    scene = kinect.build_scene([sphere(c, radius)])
    frame = kinect.render_depth(scene, calib, POSE, DepthNoise.none(), np.random.default_rng(0))
    rng = np.random.default_rng(3)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d @ (c / np.linalg.norm(c)) < -0.7]                 # the side facing the camera
    pts = c + radius * d
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), calib.depth.K(), calib.depth.dist)
    uv = np.rint(uv.reshape(-1, 2)).astype(int)
    got = frame.depth_true[uv[:, 1], uv[:, 0]]
    # Within half a pixel's footprint (~2 mm at 1.8 m) on a slope of up to 45°, plus
    # tessellation (< 0.3 mm).
    assert np.isfinite(got).all() and len(got) > 50
    assert np.abs(got - pts[:, 2]).max() < 0.004


# ------------------------------------------------------------------------------ depth noise

def test_noise_sigma_defaults_within_spec() -> None:
    noise = DepthNoise()
    s = noise.sigma(np.array([1.0, 2.0, 3.0]))
    assert 0.0014 < s[0] < 0.0017 and 0.0019 < s[1] < 0.0023 and 0.0028 < s[2] < 0.0031
    assert noise.sigma(3.86) < 0.017                         # public spec: random error <= 17 mm
    base = kinect.random_calibration(np.random.default_rng(0))
    r2_max = float((kinect.undistorted_grid(base.depth) ** 2).sum(-1).max())
    biases = set()
    for i in range(300):
        cal = dataclasses.replace(base, serial=f"{i:012d}")
        offset, scale, radial = kinect.device_depth_bias(cal, noise)
        biases.add(offset)
        # spec: systematic error < 11 mm + 0.1 % of distance
        assert abs(offset) + r2_max * abs(radial) < 0.011 and abs(scale) <= 0.001
    assert len(biases) == 300                                 # each device its own
    assert kinect.device_depth_bias(cal, noise) == kinect.device_depth_bias(cal, noise)
    assert kinect.device_depth_bias(cal, DepthNoise.none()) == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("distance", [1.0, 2.0, 3.0])
def test_measured_noise_matches_sigma(calib: KinectCalibration, distance: float) -> None:
    noise = dataclasses.replace(DepthNoise(), dropout=0.0)
    scene = kinect.build_scene([plane([0, 0, distance], [0, 0, -1])])
    cu, cv = round(calib.depth.cx), round(calib.depth.cy)
    win = np.s_[cv - 30:cv + 31, cu - 30:cu + 31]           # near the axis: head-on incidence
    rng = np.random.default_rng(5)
    frames = np.stack([kinect.render_depth(scene, calib, POSE, noise, rng).depth_mm[win]
                       for _ in range(8)]).astype(np.float64) / 1000.0
    assert np.all(frames > 0)
    measured = np.sqrt(frames.var(axis=0, ddof=1).mean())
    expected = np.sqrt(noise.sigma(distance) ** 2 + 1e-6 / 12)  # + millimetre rounding
    assert measured == pytest.approx(expected, rel=0.15)
    # The mean error is the device's systematic error, within the public spec.
    assert abs(frames.mean() - distance) < 0.011 + 0.001 * distance


def test_grazing_and_out_of_range_pixels_are_invalid(calib: KinectCalibration) -> None:
    # A plane seen at ~75° incidence on the axis: grazing on one side, far and near in range.
    n = np.array([np.sin(np.radians(75)), 0.0, -np.cos(np.radians(75))])
    p0 = np.array([0.0, 0.0, 1.5])
    scene = kinect.build_scene([plane(p0, n)])
    frame = kinect.render_depth(scene, calib, POSE, DepthNoise.none(), np.random.default_rng(0))
    r = rays(calib.depth)
    with np.errstate(divide="ignore"):
        z = (n @ p0) / (r @ n)
    incidence = np.degrees(np.arccos(np.abs(r @ n) / np.linalg.norm(r, axis=-1)))
    hit = np.isfinite(frame.depth_true)
    valid = frame.depth_mm > 0
    grazing = hit & (incidence > 80.2)
    far, near = hit & (z > 3.87), hit & (z < 0.49)
    assert grazing.sum() > 1000 and far.sum() > 1000
    assert not valid[grazing].any() and not valid[far].any() and not valid[near].any()
    good = hit & (incidence < 79.8) & (z > 0.51) & (z < 3.85)
    assert good.sum() > 10000 and valid[good].all()
    # Whole scenes too near or too far read nothing.
    for d in (0.45, 4.0):
        s = kinect.build_scene([plane([0, 0, d], [0, 0, -1])])
        assert not kinect.render_depth(s, calib, POSE, DepthNoise.none()).depth_mm.any()


def test_dropout_and_fov_cut(calib: KinectCalibration) -> None:
    scene = kinect.build_scene([plane([0, 0, 1.5], [0, 0, -1])])
    noise = dataclasses.replace(DepthNoise.none(), dropout=0.05)
    frame = kinect.render_depth(scene, calib, POSE, noise, np.random.default_rng(2))
    assert (frame.depth_mm == 0).mean() == pytest.approx(0.05, abs=0.005)
    frame = kinect.render_depth(scene, calib, POSE, DepthNoise(), np.random.default_rng(2))
    assert not frame.depth_mm[:5, :5].any() and not frame.depth_mm[-5:, -5:].any()
    assert (frame.depth_mm[250:330, 280:360] > 0).mean() > 0.99


def test_flying_pixels_only_at_depth_edges(calib: KinectCalibration) -> None:
    # No grazing cut-off here, so that every edge pixel can become a flying pixel.
    noise = dataclasses.replace(DepthNoise.none(), flying_prob=0.3, max_incidence_deg=90.0)
    rot = Rotation.from_euler("xyz", [10, 20, 5], degrees=True).as_matrix()
    scene = kinect.build_scene([plane([0, 0, 3.0], [0, 0, -1]),
                                box(np.array([0.0, 0.1, 1.6]), [0.7, 0.6, 0.5], rot)])
    frame = kinect.render_depth(scene, calib, POSE, noise, np.random.default_rng(4))
    z = np.nan_to_num(frame.depth_true.astype(np.float64), nan=0.0)
    p = np.pad(z, 1)
    nbs = np.stack([p[1:-1, :-2], p[1:-1, 2:], p[:-2, 1:-1], p[2:, 1:-1]])
    jump = np.where(nbs > 0, np.abs(nbs - z), 0.0).max(axis=0)
    edge = (z > 0) & (jump > noise.edge_jump)
    assert edge.sum() > 1000
    assert not (frame.flying & ~edge).any()
    assert frame.flying.sum() / edge.sum() == pytest.approx(0.3, abs=0.05)
    got = frame.depth_mm / 1000.0
    lo = np.where(nbs > 0, nbs, np.inf).min(axis=0)
    hi = nbs.max(axis=0)
    f = frame.flying
    assert np.all(got[f] >= np.minimum(lo[f], z[f]) - 6e-4)
    assert np.all(got[f] <= np.maximum(hi[f], z[f]) + 6e-4)
    # Everything else is exact.
    ok = (frame.depth_mm > 0) & ~f
    assert np.abs(got[ok] - z[ok]).max() <= 5e-4 + 1e-6


def test_flying_pixel_filter_keeps_a_thin_limb(calib: KinectCalibration) -> None:
    # A bar a few pixels across, as a hand is in the binned depth mode: 1.2 cm wide at 2.5 m
    # (about 2.4 of this unbinned camera's pixels), 35 cm in front of a wall, each pixel next
    # to the depth edge. The sensor's full noise, flying pixels included.
    cfg = SegmentationConfig()
    scene = kinect.build_scene([plane([0, 0, 2.85], [0, 0, -1]),
                                box(np.array([0.0, 0.0, 2.5]), [0.012, 0.6, 0.04], np.eye(3))])
    frame = kinect.render_depth(scene, calib, POSE, DepthNoise(), np.random.default_rng(5))
    z = np.nan_to_num(frame.depth_true.astype(np.float64), nan=0.0)
    got = frame.depth_mm / 1000.0
    valid = frame.depth_mm > 0
    bar = valid & (z > 0) & (z < 2.7) & ~frame.flying
    edges = depth_edges(frame.depth_mm, cfg.edge_ratio)
    flying = flying_pixels(frame.depth_mm, cfg.edge_ratio, cfg.edge_support_ratio,
                           cfg.edge_support)
    print(f"bar: {bar.sum()} px, {edges[bar].mean():.2f} on an edge, {flying[bar].mean():.2f} "
          f"called flying")
    assert bar.sum() > 200
    assert edges[bar].mean() > 0.9  # the edge rule alone throws the bar away ...
    assert flying[bar].mean() < 0.4  # ... the support rule keeps most of it
    # and still drops what flies: of the sensor's mixed depths it keeps, none is far from the
    # nearer of the surfaces it mixes (a mix that lands on the other one is a point of it, one
    # pixel aside)
    kept = frame.flying & valid & ~flying
    p = np.pad(z, 1)
    h, w = z.shape
    nbs = np.stack([p[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)])
    off = np.abs(nbs[:, kept] - got[kept]).min(axis=0)
    print(f"flying: {(frame.flying & valid).sum()} px, {kept.sum()} kept, off by at most "
          f"{100 * off.max():.1f} cm")
    assert off.max() < 0.03


def test_default_noise_errors_are_bounded_away_from_edges(calib: KinectCalibration) -> None:
    rot = Rotation.from_euler("y", 30, degrees=True).as_matrix()
    scene = kinect.build_scene([plane([0, 0, 3.0], [0, 0, -1]),
                                box(np.array([0.0, 0.0, 1.8]), [0.8, 0.8, 0.8], rot)])
    noise = DepthNoise()
    frame = kinect.render_depth(scene, calib, POSE, noise, np.random.default_rng(8))
    z = np.nan_to_num(frame.depth_true.astype(np.float64), nan=0.0)
    kernel = np.ones((5, 5), np.uint8)
    z32 = z.astype(np.float32)
    interior = cv2.dilate(z32, kernel) - cv2.erode(z32, kernel) < 0.02
    ok = interior & (frame.depth_mm > 0)
    err = frame.depth_mm[ok] / 1000.0 - z[ok]
    bound = 0.011 + 0.001 * z[ok] + 6 * noise.sigma(z[ok]) / np.sqrt(np.cos(np.radians(80)))
    assert ok.sum() > 50000 and np.all(np.abs(err) < bound)
    assert frame.flying.sum() > 0 and (frame.depth_mm == 0).mean() < 0.2


def test_render_is_deterministic_given_rng(calib: KinectCalibration) -> None:
    scene = kinect.build_scene([sphere(np.array([0, 0, 2.0]), 0.5, label=1),
                                plane([0, 0, 3.0], [0, 0, -1])])
    a = kinect.render_depth(scene, calib, POSE, DepthNoise(), np.random.default_rng(1))
    b = kinect.render_depth(scene, calib, POSE, DepthNoise(), np.random.default_rng(1))
    c = kinect.render_depth(scene, calib, POSE, DepthNoise(), np.random.default_rng(2))
    np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
    assert (a.depth_mm != c.depth_mm).mean() > 0.3


# ------------------------------------------------------------------------------ IR

def test_ir_falls_with_range_squared_incidence_and_albedo(calib: KinectCalibration) -> None:
    """The active IR image: the camera's own illuminator, so a surface's counts scale with its
    albedo and cos(incidence) and fall with the square of its range; and rendering it leaves
    the depth image and the generator's later draws as they are without it."""
    def centre_ir(scene: kinect.SimScene) -> float:
        f = kinect.render_depth(scene, calib, POSE, DepthNoise.none(), ir=True)
        u, v = round(calib.depth.cx), round(calib.depth.cy)  # the optical axis
        return float(np.median(f.ir[v - 3:v + 4, u - 3:u + 4]))

    grey = (0.5, 0.5, 0.5)
    near = centre_ir(kinect.build_scene([plane([0, 0, 1.0], [0, 0, -1], color=grey)]))
    far = centre_ir(kinect.build_scene([plane([0, 0, 2.0], [0, 0, -1], color=grey)]))
    dark = centre_ir(kinect.build_scene([plane([0, 0, 1.0], [0, 0, -1],
                                               color=(0.1, 0.1, 0.1))]))
    tilted = centre_ir(kinect.build_scene([plane([0, 0, 1.0], [np.sin(1.0), 0, -np.cos(1.0)],
                                                 color=grey)]))
    assert near == pytest.approx(kinect.IR_GAIN * 0.5, rel=0.01)
    assert near / far == pytest.approx(4.0, rel=0.02)
    assert dark / near == pytest.approx(0.2, rel=0.02)
    assert tilted / near == pytest.approx(np.cos(1.0), rel=0.03)

    scene = kinect.build_scene([sphere(np.array([0, 0, 2.0]), 0.5, label=1),
                                plane([0, 0, 3.0], [0, 0, -1])])
    rng_a, rng_b = np.random.default_rng(4), np.random.default_rng(4)
    a = kinect.render_depth(scene, calib, POSE, DepthNoise(), rng_a, ir=True)
    b = kinect.render_depth(scene, calib, POSE, DepthNoise(), rng_b)
    np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
    assert b.ir is None and rng_a.random() == rng_b.random()
    again = kinect.render_depth(scene, calib, POSE, DepthNoise(), np.random.default_rng(4),
                                ir=True)
    np.testing.assert_array_equal(a.ir, again.ir)  # its shot noise is seeded too
    # shot noise: sqrt(counts) on the sphere's flat-lit middle
    clean = kinect.render_depth(scene, calib, POSE, DepthNoise.none(), ir=True).ir
    sel = (a.depth_mm > 0) & (clean > 400)
    rel = (a.ir[sel].astype(float) - clean[sel]) / np.sqrt(clean[sel])
    assert 0.7 < rel.std() < 1.4


def test_charuco_board_is_found_in_the_ir_image_where_the_depth_camera_sees_it(
        calib: KinectCalibration) -> None:
    """A ChArUco board in front of the depth camera: OpenCV finds its corners in the IR image
    (what calibrating a depth camera with IR images relies on), within half a pixel of the
    board's corners projected through the depth intrinsics."""
    from couch.capture.charuco import BoardSpec, board_corners_3d, detect_board

    spec = BoardSpec()
    w, h = spec.size
    board_from_centre = make_transform(np.eye(3), [w / 2 - spec.margin, h / 2 - spec.margin, 0])
    depth_from_board = (make_transform(Rotation.from_euler("xy", [10, -15], degrees=True)
                                       .as_matrix(), [0.0, 0.0, 1.1])
                        @ invert_transform(board_from_centre))
    scene = kinect.build_scene([kinect.board_mesh(spec, POSE @ depth_from_board),
                                plane([0, 0, 3.0], [0, 0, -1])])
    f = kinect.render_depth(scene, calib, POSE, DepthNoise(), np.random.default_rng(0), ir=True)
    ir8 = np.clip(f.ir.astype(np.float32) * (255.0 / np.percentile(f.ir, 99.5)), 0, 255)
    found = detect_board(ir8.astype(np.uint8), spec)
    corners = board_corners_3d(spec)
    assert len(found.ids) >= 0.8 * len(corners)
    proj, _ = cv2.projectPoints(corners[found.ids], *(cv2.Rodrigues(depth_from_board[:3, :3])[0],
                                                       depth_from_board[:3, 3]),
                                calib.depth.K(), calib.depth.dist)
    err = np.linalg.norm(proj.reshape(-1, 2) - found.corners, axis=1)
    print(f"{len(found.ids)} of {len(corners)} corners, {np.median(err):.3f} px median, "
          f"{err.max():.3f} px largest")
    assert np.median(err) < 0.25 and err.max() < 0.5


# ------------------------------------------------------------------------------ colour

def test_colour_view_of_box_matches_project_points(calib: KinectCalibration) -> None:
    """The colour camera's silhouette of a box equals the box's faces projected with
    cv2.projectPoints through color_from_depth and the colour intrinsics, within 1 px."""
    rot = Rotation.from_euler("xyz", [25, -35, 10], degrees=True).as_matrix()
    center, ext = np.array([0.15, 0.1, 1.7]), np.array([0.5, 0.35, 0.4])
    mesh = box(center, ext, rot, label=kinect.LABEL_CHAIR)
    scene = kinect.build_scene([mesh])
    frame = kinect.render_color(scene, calib, POSE, kinect.Light(shadows=False),
                                np.random.default_rng(0), noise=kinect.ColorNoise.none())
    color_from_world = calib.color_from_depth @ invert_transform(POSE)
    rvec = cv2.Rodrigues(color_from_world[:3, :3])[0]
    tvec = color_from_world[:3, 3]
    # Each face outline densely sampled (distortion bends straight edges), filled, unioned.
    corners = np.array([[sx, sy, sz] for sx in (-.5, .5) for sy in (-.5, .5) for sz in (-.5, .5)])
    quads = [[0, 1, 3, 2], [4, 5, 7, 6], [0, 1, 5, 4], [2, 3, 7, 6], [0, 2, 6, 4], [1, 3, 7, 5]]
    s = np.linspace(0, 1, 100, endpoint=False)[:, None]
    predicted = np.zeros((720, 1280), np.uint8)
    for q in quads:
        local = corners[q] * ext
        outline = np.concatenate([local[i] + s * (local[(i + 1) % 4] - local[i])
                                  for i in range(4)])
        world = apply_transform(POSE, outline @ rot.T + center)
        uv, _ = cv2.projectPoints(world, rvec, tvec, calib.color.K(), calib.color.dist)
        # fillPoly's fixed point: vertices in 1/16 px, pixel centres at integers.
        cv2.fillPoly(predicted, [np.rint(uv.reshape(-1, 2) * 16).astype(np.int32)], 1,
                     shift=4)
    predicted = predicted.astype(bool)
    got = frame.chair_mask
    kernel = np.ones((3, 3), np.uint8)
    grown = cv2.dilate(predicted.astype(np.uint8), kernel).astype(bool)
    shrunk = cv2.erode(predicted.astype(np.uint8), kernel).astype(bool)
    assert got.sum() > 20000
    assert not (got & ~grown).any() and not (shrunk & ~got).any()
    assert (got ^ predicted).sum() / predicted.sum() < 0.02
    # Z-depth in the colour frame of the exact hit, consistent with the box surface.
    inside = np.argwhere(shrunk)[::97]
    xy = cv2.undistortPoints(inside[:, ::-1].astype(np.float64).reshape(-1, 1, 2),
                             calib.color.K(), calib.color.dist, None, None, None, CRITERIA)
    pts_col = np.c_[xy.reshape(-1, 2), np.ones(len(inside))] * frame.depth_true[
        inside[:, 0], inside[:, 1], None]
    world_pts = apply_transform(invert_transform(color_from_world), pts_col)
    local = (apply_transform(invert_transform(POSE), world_pts) - center) @ rot
    on_face = np.abs(np.abs(local) - ext / 2).min(axis=1)
    assert on_face.max() < 1e-3


def test_masks_labels_and_jpeg(calib: KinectCalibration) -> None:
    person = sphere(np.array([-0.25, 0.0, 1.6]), 0.3, label=kinect.LABEL_PERSON,
                    color=(0.8, 0.6, 0.5), texture="fabric", smooth=True)
    chair = box(np.array([0.35, 0.1, 2.2]), [0.5, 0.8, 0.5], np.eye(3),
                label=kinect.LABEL_CHAIR, color=(0.5, 0.3, 0.15), texture="wood")
    wall = plane([0, 0, 3.2], [0, 0, -1], color=(0.8, 0.8, 0.8))
    scene = kinect.build_scene([person, chair, wall])
    frame = kinect.render_color(scene, calib, POSE, kinect.Light(), np.random.default_rng(0))
    assert frame.rgb.shape == (720, 1280, 3) and frame.rgb.dtype == np.uint8
    assert frame.person_mask.sum() > 10000 and frame.chair_mask.sum() > 10000
    np.testing.assert_array_equal(frame.person_mask, frame.label == kinect.LABEL_PERSON)
    np.testing.assert_array_equal(frame.chair_mask, frame.label == kinect.LABEL_CHAIR)
    assert not (frame.person_mask & frame.chair_mask).any()
    assert (frame.label == 0).sum() > 100000
    assert np.nanmax(frame.depth_true[frame.person_mask]) < 1.7
    decoded = cv2.cvtColor(cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_COLOR),
                           cv2.COLOR_BGR2RGB)
    mse = np.mean((decoded.astype(float) - frame.rgb) ** 2)
    assert 10 * np.log10(255**2 / mse) > 30
    small = kinect.render_color(scene, calib, POSE, kinect.Light(), np.random.default_rng(0),
                                jpeg_quality=30)
    assert len(small.jpeg) < len(frame.jpeg)
    # The colour-camera label agrees with the depth camera's on the surfaces both see.
    depth = kinect.render_depth(scene, calib, POSE, DepthNoise.none())
    assert set(np.unique(depth.label)) == {0, 1, 2}


@pytest.mark.parametrize("noise", [None, kinect.ColorNoise.none()], ids=["noisy", "perfect"])
def test_skip_color_draws_what_render_color_draws(calib: KinectCalibration, noise) -> None:
    """A depth-only recording skips the colour render but consumes its random draws: the
    shared generator ends where a colour render leaves it (without a scene: the draws never
    depend on what is seen), so the next depth frame is the same."""
    scene = kinect.build_scene([sphere(np.array([0, 0, 2.0]), 0.5, label=1),
                                plane([0, 0, 3.0], [0, 0, -1])])
    rendered, skipped = np.random.default_rng(4), np.random.default_rng(4)
    kinect.render_color(scene, calib, POSE, kinect.Light(), rendered, noise=noise)
    kinect.skip_color(calib, skipped, noise=noise)
    assert rendered.bit_generator.state == skipped.bit_generator.state
    a = kinect.render_depth(scene, calib, POSE, DepthNoise(), rendered)
    b = kinect.render_depth(scene, calib, POSE, DepthNoise(), skipped)
    np.testing.assert_array_equal(a.depth_mm, b.depth_mm)


def test_textures_give_colour_signal(calib: KinectCalibration) -> None:
    def grey_std(texture: str | None) -> float:
        floor = plane([0, 0, 2.0], [0, 0, -1], color=(0.6, 0.5, 0.4), texture=texture)
        frame = kinect.render_color(kinect.build_scene([floor]), calib, POSE,
                                    kinect.Light(direction=(0, 0, 1), shadows=False),
                                    np.random.default_rng(0), noise=kinect.ColorNoise.none())
        return float(frame.rgb[200:520, 400:880].mean(axis=2).std())

    assert grey_std(None) < 0.5
    for texture in ("wood", "fabric", "floor"):
        assert grey_std(texture) > 2.0, texture


def test_shadows(calib: KinectCalibration) -> None:
    """A ball between the key light and a wall casts a shadow on the wall, on the side away
    from the light."""
    ball = sphere(np.array([0.0, 0.0, 1.5]), 0.2, label=kinect.LABEL_PERSON)
    wall = plane([0, 0, 2.5], [0, 0, -1], color=(0.8, 0.8, 0.8))
    light_dir = tuple(POSE[:3, :3] @ np.array([0.3, 0.0, -1.0]))  # behind the camera, to +X
    scene = kinect.build_scene([ball, wall])
    images = [kinect.render_color(scene, calib, POSE,
                                  kinect.Light(direction=light_dir, shadows=shadows),
                                  np.random.default_rng(0), noise=kinect.ColorNoise.none())
              for shadows in (True, False)]
    lit, flat = images
    np.testing.assert_array_equal(lit.label, flat.label)
    wall_px = lit.label == kinect.LABEL_BACKGROUND
    shadow = wall_px & (lit.rgb.astype(int).sum(2) < flat.rgb.astype(int).sum(2) - 30)
    assert shadow.sum() > 2000
    assert np.median(np.argwhere(shadow)[:, 1]) < np.median(np.argwhere(lit.person_mask)[:, 1])
    # Only shadowed pixels change.
    same = (lit.rgb == flat.rgb).all(axis=2)
    assert (same | shadow).mean() > 0.995


def test_board_mesh_labels(calib: KinectCalibration) -> None:
    from couch.capture.charuco import BoardSpec

    spec = BoardSpec()
    pose = kinect.world_from_color(calib, POSE) @ make_transform(np.eye(3), [-0.3, -0.4, 1.5])
    mesh = kinect.board_mesh(spec, pose)
    assert mesh.label == kinect.LABEL_BOARD and mesh.planar_texture is not None
    frame = kinect.render_color(kinect.build_scene([mesh]), calib, POSE,
                                kinect.Light(shadows=False), np.random.default_rng(0))
    board = frame.label == kinect.LABEL_BOARD
    assert board.sum() > 50000
    grey = frame.rgb.mean(axis=2)[board]
    dark = (grey < 0.25 * grey.max()).mean()             # black squares and markers
    assert grey.max() > 60 and 0.3 < dark < 0.7


# ------------------------------------------------------------------------------ cameras

def test_random_calibration_is_realistic() -> None:
    cal = kinect.random_calibration(np.random.default_rng(0))
    d, c = cal.depth, cal.color
    assert (d.width, d.height, c.width, c.height) == (640, 576, 1280, 720)
    assert 500 < d.fx < 510 and 500 < d.fy < 510 and 605 < c.fx < 618
    assert abs(d.cx - 320) < 30 and abs(d.cy - 288) < 80      # NFOV crop is off-axis in y
    assert abs(c.cx - 640) < 15 and abs(c.cy - 360) < 15
    t = cal.color_from_depth
    assert np.linalg.norm(t[:3, 3] - [-0.032, -0.0021, 0.0039]) < 0.002
    tilt = np.degrees(np.arccos(np.clip(t[:3, :3][2, 2], -1, 1)))
    assert 4 < tilt < 7                                      # depth tilted ~6° down vs colour
    # Barrel distortion of the real lens: ~100 px in the depth image's corners.
    corner = np.array([[[0.0, 0.0]]])
    ideal = (corner - [d.cx, d.cy]) / [d.fx, d.fy]
    xy = cv2.undistortPoints(corner, d.K(), d.dist, None, None, None, CRITERIA)
    assert 50 < np.linalg.norm((xy - ideal) * d.fx) < 250
    assert len(cal.serial) == 12 and cal.serial.isdigit()


def test_perturb_calibration_is_small_and_keeps_identity() -> None:
    reported = kinect.random_calibration(np.random.default_rng(1))
    true = kinect.perturb_calibration(reported, np.random.default_rng(2))
    assert true.serial == reported.serial and true != reported
    for a, b in ((true.depth, reported.depth), (true.color, reported.color)):
        assert abs(a.fx / b.fx - 1) < 0.003 and abs(a.cx - b.cx) < 2 and abs(a.cy - b.cy) < 2
        np.testing.assert_array_equal(a.dist, b.dist)
    delta = true.color_from_depth @ invert_transform(reported.color_from_depth)
    assert np.linalg.norm(delta[:3, 3]) < 0.003
    assert np.degrees(np.arccos(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1, 1))) < 0.3


def test_place_cameras(calib: KinectCalibration) -> None:
    rng = np.random.default_rng(21)
    target = np.array([0.0, 0.8, 0.0])
    cams = kinect.place_cameras(rng, n=4, target=tuple(target), radius=(2.0, 3.0),
                                height=(1.2, 2.0))
    assert len(cams) == 4
    assert len({c.serial for c, _ in cams}) == 4
    azimuths = []
    for cal, pose in cams:
        assert pose.shape == (4, 4)
        np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)
        eye = pose[:3, 3]
        assert 1.2 <= eye[1] <= 2.0
        assert 2.0 <= np.hypot(*(eye - target)[[0, 2]]) <= 3.0
        azimuths.append(np.arctan2(eye[0] - target[0], eye[2] - target[2]))
        # The target is in front and near the middle of both images.
        for intr, cam_from_world in (
                (cal.depth, invert_transform(pose)),
                (cal.color, invert_transform(kinect.world_from_color(cal, pose)))):
            p = apply_transform(cam_from_world, target[None])[0]
            assert p[2] > 1.5
            uv, _ = cv2.projectPoints(target[None], cv2.Rodrigues(cam_from_world[:3, :3])[0],
                                      cam_from_world[:3, 3], intr.K(), intr.dist)
            u, v = uv.reshape(2)
            assert abs(u - intr.width / 2) < 0.2 * intr.width
            assert abs(v - intr.height / 2) < 0.25 * intr.height
        # calibration.json round trip
        back = KinectCalibration.from_json(cal.to_json())
        assert back.serial == cal.serial
        for a, b in ((back.depth, cal.depth), (back.color, cal.color)):
            np.testing.assert_allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy],
                                       atol=1e-9)
            np.testing.assert_allclose(a.dist, b.dist, atol=1e-12)
        np.testing.assert_allclose(back.color_from_depth, cal.color_from_depth, atol=1e-12)
    gaps = np.diff(np.sort(np.mod(azimuths, 2 * np.pi)))
    gaps = np.append(gaps, 2 * np.pi - gaps.sum())
    assert gaps.min() > np.radians(50)
    with pytest.raises(ValueError):
        kinect.place_cameras(rng, n=0)


def test_scene_mesh_validation() -> None:
    v = np.zeros((3, 3))
    with pytest.raises(ValueError, match="outside"):
        SceneMesh(v, [[0, 1, 3]])
    with pytest.raises(ValueError, match="texture"):
        SceneMesh(v, [[0, 1, 2]], texture="marble")
    with pytest.raises(ValueError, match="vertex_colors"):
        SceneMesh(v, [[0, 1, 2]], vertex_colors=np.zeros((2, 3)))
    scene = kinect.build_scene([])
    assert scene.faces.shape == (0, 3)
