"""ChArUco board: geometry of the printed image and pose from rendered synthetic views."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from couch.capture.charuco import (
    BoardSpec,
    board_corners_3d,
    board_image,
    camera_from_board,
    detect_board,
    make_board,
    refine_saddle_points,
)
from couch.geometry import make_transform, transform_distance
from couch.tools.sim import kinect


def test_board_frame_and_corners() -> None:
    spec = BoardSpec()
    corners = board_corners_3d(spec)
    assert corners.shape == ((spec.squares_x - 1) * (spec.squares_y - 1), 3)
    np.testing.assert_allclose(corners[:, 2], 0.0)
    # Row-major by id, +X along a row: id 1 is one square to the right of id 0.
    np.testing.assert_allclose(corners[0], [spec.square_length, spec.square_length, 0.0])
    np.testing.assert_allclose(corners[1] - corners[0], [spec.square_length, 0.0, 0.0])
    np.testing.assert_allclose(corners[spec.squares_x - 1] - corners[0],
                               [0.0, spec.square_length, 0.0])
    assert spec.size == pytest.approx((0.64, 0.84))
    assert isinstance(make_board(spec), cv2.aruco.CharucoBoard)


def test_board_image_maps_pixels_to_board_frame() -> None:
    """Detected corners in the flat printed image sit at ``(x + margin)·ppm − 0.5`` (pixel
    centres at integers), as board_image documents."""
    spec = BoardSpec()
    ppm = 1000.0
    img = board_image(spec, ppm)
    assert img.dtype == np.uint8
    assert img.shape == (round(spec.size[1] * ppm), round(spec.size[0] * ppm))
    assert img[0, 0] == 255 and img[int(spec.margin * ppm) + 5, int(spec.margin * ppm) + 5] == 0
    det = detect_board(img, spec)
    assert len(det.ids) == len(board_corners_3d(spec))
    assert det.rvec is None  # no camera matrix, no pose
    want = (board_corners_3d(spec)[det.ids, :2] + spec.margin) * ppm - 0.5
    np.testing.assert_allclose(det.corners, want, atol=0.05)


def test_board_image_needs_whole_pixel_squares() -> None:
    with pytest.raises(ValueError, match="whole pixels"):
        board_image(BoardSpec(), 333.0)


@pytest.mark.parametrize("kwargs, match", [
    ({"squares_x": 1}, "2x2"),
    ({"marker_length": 0.2}, "marker_length"),
    ({"margin": -0.1}, "margin"),
    ({"dictionary": "DICT_NOPE"}, "dictionary"),
])
def test_board_spec_validation(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        BoardSpec(**kwargs)


def test_detect_board_on_empty_image() -> None:
    det = detect_board(np.full((480, 640), 128, np.uint8), BoardSpec(), np.eye(3) * 500,
                       np.zeros(5))
    assert len(det.ids) == 0 and det.corners.shape == (0, 2)
    assert det.rvec is None and det.tvec is None


@pytest.fixture(scope="module")
def calib() -> kinect.KinectCalibration:
    return kinect.random_calibration(np.random.default_rng(7))


# (distance m, rotation axis, angle deg): the board centred in the colour camera's view.
VIEWS = [(1.2, "y", 15.0), (1.6, "y", 40.0), (2.0, "x", -30.0), (2.2, "xy", 25.0)]


@pytest.mark.parametrize("distance, axis, angle", VIEWS)
def test_pose_from_rendered_view(calib: kinect.KinectCalibration, distance: float, axis: str,
                                 angle: float) -> None:
    """Render the board into a Kinect colour view (sensor noise, JPEG) with a known pose and
    recover it with the device's calibration: < 0.1° and < 2 mm."""
    spec = BoardSpec()
    rot = Rotation.from_euler(axis, [angle] * len(axis), degrees=True).as_matrix()
    centre = make_transform(np.eye(3), [-spec.size[0] / 2 + spec.margin,
                                        -spec.size[1] / 2 + spec.margin, 0.0])
    color_from_board = make_transform(rot, [0.0, 0.0, distance]) @ centre
    world_from_depth = make_transform(Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix(),
                                      [0.3, 1.2, -2.0])
    world_from_board = kinect.world_from_color(calib, world_from_depth) @ color_from_board
    wall = np.array([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0.0]])
    behind = make_transform(np.eye(3), [0, 0, 0.5])  # a grey wall 0.5 m behind the board
    wall = (world_from_board @ behind @ np.c_[wall, np.ones(4)].T).T[:, :3]
    scene = kinect.build_scene([
        kinect.board_mesh(spec, world_from_board),
        kinect.SceneMesh(wall, [[0, 1, 2], [0, 2, 3]], color=(0.45, 0.45, 0.45))])
    # Light from the camera's side so the board is well exposed.
    light = kinect.Light(direction=tuple(-world_from_board[:3, 2] + 0.3 * world_from_board[:3, 1]),
                         shadows=False)
    frame = kinect.render_color(scene, calib, world_from_depth, light,
                                np.random.default_rng(1), jpeg_quality=90)
    gray = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    det = detect_board(gray, spec, calib.color.K(), calib.color.dist)
    assert len(det.ids) >= 20
    assert det.rvec is not None and det.tvec is not None
    angle_err, dist_err = transform_distance(camera_from_board(det.rvec, det.tvec),
                                             color_from_board)
    assert np.degrees(angle_err) < 0.1
    assert dist_err < 0.002
    # The detected corners agree with cv2.projectPoints through the calibration.
    proj, _ = cv2.projectPoints(board_corners_3d(spec)[det.ids],
                                cv2.Rodrigues(color_from_board[:3, :3])[0],
                                color_from_board[:3, 3], calib.color.K(), calib.color.dist)
    err = np.linalg.norm(proj.reshape(-1, 2) - det.corners, axis=1)
    assert err.max() < 0.5
    assert np.abs(err.mean()) < 0.2


def _area_sampled_checkerboard(square: float, origin: tuple[float, float], size=(400, 300),
                               blur: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
    """An ideal camera image of an axis-aligned checkerboard: every pixel integrates the pattern
    over its area (200 samples per axis; the pattern is separable), then optical blur; and the
    true inner corners (pixel centres at integers)."""
    def coverage(n: int, off: float) -> np.ndarray:
        xs = np.arange(n)[:, None] - 0.5 + (np.arange(200) + 0.5)[None, :] / 200
        return (np.floor((xs - off) / square) % 2 == 0).mean(1)

    a, b = coverage(size[0], origin[0]), coverage(size[1], origin[1])
    img = (0.5 - 2 * (a[None, :] - 0.5) * (b[:, None] - 0.5)) * 200 + 30
    img = np.round(cv2.GaussianBlur(img.astype(np.float32), (0, 0), blur)).astype(np.uint8)
    nx = int((size[0] - origin[0]) // square) - 1
    ny = int((size[1] - origin[1]) // square) - 1
    truth = np.array([[origin[0] + i * square, origin[1] + j * square]
                      for j in range(1, ny) for i in range(1, nx)])
    return img, truth


def test_saddle_refinement_beats_cornersubpix_on_ideal_corners() -> None:
    img, truth = _area_sampled_checkerboard(23.7, (100.37, 80.81))
    start = truth + np.random.default_rng(0).uniform(-0.3, 0.3, truth.shape)
    ours, ok = refine_saddle_points(img, start)
    opencv = cv2.cornerSubPix(img, start.astype(np.float32).reshape(-1, 1, 2), (3, 3), (-1, -1),
                              (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6))
    err_ours = np.sqrt(np.mean((ours - truth) ** 2))
    err_cv = np.sqrt(np.mean((opencv.reshape(-1, 2) - truth) ** 2))
    print(f"rms error: saddle {err_ours:.4f} px, cornerSubPix {err_cv:.4f} px")
    assert ok.all()
    assert err_ours < 0.015 and err_ours < 0.4 * err_cv


def test_saddle_refinement_keeps_what_it_cannot_refine() -> None:
    img, truth = _area_sampled_checkerboard(23.7, (100.37, 80.81))
    flat = np.full_like(img, 128)
    pts = np.vstack([truth[:3], [[0.5, 0.5], [399.2, 150.0]]])
    out, ok = refine_saddle_points(img, pts)
    assert ok[:3].all() and not ok[3:].any()          # the image border
    assert np.array_equal(out[3:], pts[3:])
    out, ok = refine_saddle_points(flat, truth[:5])    # no saddle at all
    assert not ok.any() and np.array_equal(out, truth[:5])
    assert refine_saddle_points(img, np.zeros((0, 2)))[0].shape == (0, 2)
    with pytest.raises(ValueError, match="image"):
        refine_saddle_points(np.zeros((4, 4, 3), np.uint8), truth[:1])
