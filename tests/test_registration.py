"""Depth → colour registration and depth → points (capture/registration.py).

Expected values never come from this module: pixel rays come from the simulator's own
undistortion grid (``tools/sim/kinect.py`` ``undistorted_grid``) and projections from
``cv2.projectPoints``; the scene is an analytic plane whose depth in either camera is known.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from couch.capture.registration import (
    UNDISTORT_CRITERIA,
    depth_to_points,
    distort,
    pixel_rays,
    project_points,
    register_depth_to_color,
    unproject_pixels,
)
from couch.tools.sim.kinect import random_calibration, undistorted_grid


@pytest.fixture(scope="module")
def calib():
    return random_calibration(np.random.default_rng(7))


def _plane_depth(intr, normal, offset):
    """(H,W) float64 Z (metres) of the plane ``normal · p = offset`` seen by each pixel centre
    (simulator's rays), NaN where the ray misses it."""
    g = undistorted_grid(intr)
    denom = g[..., 0] * normal[0] + g[..., 1] * normal[1] + normal[2]
    z = offset / denom
    return np.where((denom > 0) & (z > 0), z, np.nan)


def _cv2_project(points, intr):
    uv, _ = cv2.projectPoints(np.asarray(points, np.float64).reshape(-1, 1, 3), np.zeros(3),
                              np.zeros(3), intr.K(), intr.dist)
    return uv.reshape(-1, 2)


def test_projection_matches_cv2(calib):
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-0.9, 0.9, (2000, 2)), np.ones(2000)]) * rng.uniform(
        0.5, 4.0, (2000, 1))
    for intr in (calib.depth, calib.color):
        uv, valid = project_points(pts, intr)
        assert valid.all()
        np.testing.assert_allclose(uv, _cv2_project(pts, intr), atol=1e-8)
        np.testing.assert_allclose(distort(pts[:, :2] / pts[:, 2:], intr), uv, atol=1e-12)
    # Behind the camera or beyond the metric radius: invalid (the SDK's rule).
    uv, valid = project_points(np.array([[0.0, 0.0, -1.0], [3.0, 0.0, 1.0], [0.1, 0.1, 1.0]]),
                               calib.depth)
    assert valid.tolist() == [False, False, True]
    assert np.isnan(uv[:2]).all()


def test_pixel_rays_converge_in_the_corners(calib):
    """Every pixel's ray reprojects onto its centre (1e-3 px), corners included; OpenCV's
    default criteria would be off by pixels there, which is why the tight ones are used."""
    intr = calib.depth
    rays = pixel_rays(intr)
    assert rays.shape == (intr.height, intr.width, 2)
    assert np.isfinite(rays[..., 0]).mean() > 0.999
    ok = np.isfinite(rays[..., 0])
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    back = _cv2_project(np.concatenate([rays[ok], np.ones((ok.sum(), 1))], axis=1), intr)
    err = np.hypot(back[:, 0] - u[ok], back[:, 1] - v[ok])
    assert err.max() < 1e-3
    np.testing.assert_allclose(rays[ok], undistorted_grid(intr)[ok], atol=1e-7)

    corners = np.array([[0, 0], [intr.width - 1, 0], [0, intr.height - 1],
                        [intr.width - 1, intr.height - 1]], dtype=np.float64)
    loose = cv2.undistortPoints(corners.reshape(-1, 1, 2), intr.K(), intr.dist).reshape(-1, 2)
    loose_err = np.hypot(*(_cv2_project(np.column_stack([loose, np.ones(4)]), intr)
                           - corners).T)
    assert loose_err.max() > 0.5  # the default criteria are not good enough here
    tight = unproject_pixels(corners, intr)
    assert np.isfinite(tight).all()
    np.testing.assert_allclose(_cv2_project(np.column_stack([tight, np.ones(4)]), intr),
                               corners, atol=1e-3)
    assert UNDISTORT_CRITERIA[1] >= 60


def test_depth_to_points_on_a_plane(calib):
    intr = calib.depth
    normal = np.array([0.1, -0.25, 1.0])
    normal /= np.linalg.norm(normal)
    z = _plane_depth(intr, normal, 1.6)
    depth = np.where(np.isfinite(z), np.rint(z * 1000), 0).astype(np.uint16)
    depth[100:110, 200:260] = 0  # invalid pixels give no points
    pts, valid = depth_to_points(depth, intr, return_valid=True)
    assert pts.shape == (int(valid.sum()), 3)
    assert not valid[100:110, 200:260].any()
    assert valid.sum() == np.count_nonzero(depth)
    # On the plane to the depth rounding (0.5 mm of Z, up to ~1.6x that along oblique rays).
    assert np.abs(pts @ normal - 1.6).max() < 1e-3
    np.testing.assert_allclose(pts[:, 2], depth[valid] / 1000.0)
    # Each point projects back onto the pixel it came from.
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    back = _cv2_project(pts, intr)
    assert np.abs(back - np.column_stack([u[valid], v[valid]])).max() < 1e-3
    assert depth_to_points(np.zeros_like(depth), intr).shape == (0, 3)


@pytest.mark.parametrize(("normal", "offset"), [((0.0, 0.0, 1.0), 1.2),
                                                ((0.35, -0.2, 1.0), 2.1),
                                                ((-0.5, 0.3, 1.0), 1.5)])
def test_registered_plane_matches_analytic_depth_and_is_dense(calib, normal, offset):
    n_d = np.asarray(normal) / np.linalg.norm(normal)
    z_d = _plane_depth(calib.depth, n_d, offset)
    depth = np.where(np.isfinite(z_d), np.rint(z_d * 1000), 0).astype(np.uint16)
    reg = register_depth_to_color(depth, calib)
    c = calib.color
    assert reg.shape == (c.height, c.width) and reg.dtype == np.uint16

    # The same plane in the colour camera: n_c · p_c = offset_c.
    rot, t = calib.color_from_depth[:3, :3], calib.color_from_depth[:3, 3]
    n_c = rot @ n_d
    z_c = _plane_depth(c, n_c, offset + n_c @ t)
    # Colour pixels whose surface point lies inside the depth image (between its outermost
    # pixel centres, so inside the quads) are the overlap that must be covered.
    g = undistorted_grid(c)
    p_c = np.concatenate([g * z_c[..., None], z_c[..., None]], axis=-1).reshape(-1, 3)
    uv_d = _cv2_project((p_c - t) @ rot, calib.depth).reshape(c.height, c.width, 2)
    overlap = (np.isfinite(z_c) & (uv_d[..., 0] > 0.5) & (uv_d[..., 0] < calib.depth.width - 1.5)
               & (uv_d[..., 1] > 0.5) & (uv_d[..., 1] < calib.depth.height - 1.5))
    assert overlap.sum() > 100_000

    got = reg > 0
    assert got[overlap].mean() > 0.999  # dense: no speckle where colour outnumbers depth
    holes = overlap & ~got
    assert not ndimage.binary_erosion(overlap, iterations=2)[holes].any()
    err = reg[overlap & got].astype(np.float64) - z_c[overlap & got] * 1000.0
    assert np.abs(err).max() <= 2.0, np.abs(err).max()  # mm: input and output rounding only
    # Nothing outside the depth camera's view (a pixel's width of slack at the border).
    outside = ~ndimage.binary_dilation(overlap, iterations=2)
    assert not got[outside].any()


def test_occluder_nearest_wins_without_edge_interpolation(calib):
    """A board 1.2 m away in front of a wall at 2.5 m: where both land on a colour pixel the
    board wins; no depth is interpolated across the board's edge; the colour camera, 32 mm to
    the side, sees an occlusion shadow (no depth) beside the board."""
    intr = calib.depth
    z_wall = _plane_depth(intr, np.array([0.0, 0.0, 1.0]), 2.5)
    depth = np.rint(z_wall * 1000).astype(np.uint16)
    board = np.zeros(depth.shape, bool)
    board[200:380, 250:400] = True
    z_board = _plane_depth(intr, np.array([0.0, 0.0, 1.0]), 1.2)
    depth[board] = np.rint(z_board[board] * 1000).astype(np.uint16)
    reg = register_depth_to_color(depth, calib)

    valid = reg[reg > 0].astype(np.float64)
    assert not np.any((valid > 1300) & (valid < 2300))  # no flying pixels along the edge
    # Board pixels (interior, projected with cv2) show the board, not the wall behind.
    inner = ndimage.binary_erosion(board, iterations=2)
    rays = undistorted_grid(intr)[inner]
    pts = np.column_stack([rays * 1.2, np.full(len(rays), 1.2)])
    pts_c = pts @ calib.color_from_depth[:3, :3].T + calib.color_from_depth[:3, 3]
    uv = np.rint(_cv2_project(pts_c, calib.color)).astype(int)
    hit = reg[uv[:, 1], uv[:, 0]].astype(np.float64)
    np.testing.assert_allclose(hit, pts_c[:, 2] * 1000, atol=2.0)
    # The shadow: wall the colour camera sees but the depth camera does not, beside the board
    # (on the side away from the depth camera: ~1.1 baselines of wall, ~8 px here).
    rows = slice(uv[:, 1].min() + 5, uv[:, 1].max() - 5)
    side = calib.color_from_depth[0, 3] < 0  # depth camera to the colour camera's left
    band = (reg[rows, uv[:, 0].max() + 3:uv[:, 0].max() + 30] if side
            else reg[rows, uv[:, 0].min() - 30:uv[:, 0].min() - 3])
    assert np.all(np.sum(band == 0, axis=1) >= 3)
    assert np.count_nonzero(reg) > 0.5 * reg.size


def test_registration_input_checks(calib):
    depth = np.zeros((calib.depth.height, calib.depth.width), np.uint16)
    assert not register_depth_to_color(depth, calib).any()
    with pytest.raises(ValueError, match="uint16"):
        register_depth_to_color(depth.astype(np.float32), calib)
    with pytest.raises(ValueError, match="576"):
        register_depth_to_color(depth[:-1], calib)
    with pytest.raises(TypeError):
        register_depth_to_color(depth, calib.depth)
