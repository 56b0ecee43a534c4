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
