"""Rigid transforms: inverse, Kabsch fit, averaging, look-at; vertex normals; surface samples."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from couch.geometry import (
    apply_transform,
    average_transforms,
    fit_rigid_transform,
    invert_transform,
    look_at,
    make_transform,
    sample_surface,
    transform_distance,
    vertex_normals,
)


def _random_transforms(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_transform(Rotation.random(n, rng=rng).as_matrix(), rng.normal(0, 1, (n, 3)))


def test_invert_and_apply():
    t = _random_transforms(5)
    assert np.allclose(invert_transform(t) @ t, np.eye(4), atol=1e-12)
    pts = np.random.default_rng(1).normal(size=(5, 10, 3))
    assert np.allclose(apply_transform(invert_transform(t), apply_transform(t, pts)), pts)


def test_fit_rigid_transform_recovers_truth_under_noise():
    rng = np.random.default_rng(2)
    truth = _random_transforms(1, seed=3)[0]
    src = rng.uniform(-0.5, 0.5, (500, 3))
    dst = apply_transform(truth, src) + rng.normal(0, 0.002, (500, 3))
    angle, dist = transform_distance(fit_rigid_transform(src, dst), truth)
    assert np.degrees(angle) < 0.2 and dist < 0.001


def test_average_of_noisy_poses_is_closer_than_the_samples():
    rng = np.random.default_rng(4)
    truth = _random_transforms(1, seed=5)[0]
    noise = make_transform(Rotation.from_rotvec(rng.normal(0, 0.05, (200, 3))).as_matrix(),
                           rng.normal(0, 0.02, (200, 3)))
    samples = truth @ noise
    avg = average_transforms(samples)
    angle, dist = transform_distance(avg, truth)
    sample_angle, sample_dist = transform_distance(samples, truth)
    assert angle < 0.2 * np.median(sample_angle) and dist < 0.2 * np.median(sample_dist)
    # zero weight removes an outlier entirely
    outlier = _random_transforms(1, seed=9)
    with_outlier = np.concatenate([samples, outlier])
    w = np.append(np.ones(200), 0.0)
    assert np.allclose(average_transforms(with_outlier, w), avg)


def test_look_at_points_the_optical_axis_at_the_target():
    pose = look_at([2.0, 1.5, 3.0], [0.0, 1.0, 0.0])
    target_cam = apply_transform(invert_transform(pose), np.array([[0.0, 1.0, 0.0]]))[0]
    assert np.allclose(target_cam[:2], 0.0, atol=1e-12) and target_cam[2] > 0
    # world up (+Y) appears as image up (−Y in OpenCV camera coordinates)
    assert (invert_transform(pose)[:3, :3] @ np.array([0.0, 1.0, 0.0]))[1] < 0


def test_vertex_normals_of_a_sphere_and_a_batch():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    n = vertex_normals(v, f)
    assert n.shape == v.shape
    # a sphere's area-weighted normals point radially outwards (within ~1 deg at 642 vertices)
    np.testing.assert_allclose(n, v / 0.5, atol=0.02)
    # the same as summing each face's area vector into its three corners one by one
    tri = v[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    slow = np.zeros_like(v)
    for face, normal in zip(f, fn, strict=True):
        slow[face] += normal
    np.testing.assert_allclose(n, slow / np.linalg.norm(slow, axis=1, keepdims=True),
                               atol=1e-12)
    # any leading batch axes, more meshes than one chunk; rotated meshes rotate their normals
    rot = Rotation.random(2 * 21, rng=np.random.default_rng(0)).as_matrix().reshape(2, 21, 3, 3)
    batch = np.einsum("bkij,vj->bkvi", rot, v)
    nb = vertex_normals(batch, f)
    assert nb.shape == batch.shape
    np.testing.assert_allclose(nb, np.einsum("bkij,vj->bkvi", rot, n), atol=1e-12)
    assert vertex_normals(v.astype(np.float32), f).dtype == np.float32


def test_surface_samples_lie_on_the_faces_by_area_with_outward_normals():
    import trimesh

    box = trimesh.creation.box(extents=(1.0, 2.0, 4.0))  # 28 m^2
    pts, normals = sample_surface(box.vertices, box.faces, 20000, seed=3)
    assert pts.shape == normals.shape == (20000, 3)
    assert np.abs(box.nearest.signed_distance(pts[:500])).max() < 1e-9  # on the surface
    # each sample's normal is its face's: the axis it lies at the box's half extent on
    axis = np.abs(normals).argmax(1)
    assert np.allclose(np.abs(normals).max(1), 1.0)
    half = np.array([0.5, 1.0, 2.0])
    assert np.allclose(np.abs(pts[np.arange(len(pts)), axis]), half[axis])
    assert np.all(pts[np.arange(len(pts)), axis] * normals[np.arange(len(pts)), axis] > 0)
    # area-uniform: the pairs of faces normal to x, y, z hold 16, 8 and 4 of the 28 m^2
    share = np.bincount(axis, minlength=3) / len(pts)
    assert np.allclose(share, [16 / 28, 8 / 28, 4 / 28], atol=0.01)
    again = sample_surface(box.vertices, box.faces, 20000, seed=3)
    assert np.array_equal(again[0], pts) and np.array_equal(again[1], normals)
    assert not np.array_equal(sample_surface(box.vertices, box.faces, 20000, seed=4)[0], pts)
