"""fitting/metrics.py on cases with known answers."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from couch.body import load_body_model
from couch.fitting.metrics import (
    FOOT_KEYPOINTS,
    chamfer,
    foot_points,
    foot_skate,
    jitter,
    mpjpe,
    surface_distances,
    sync_error,
)


def test_mpjpe_of_a_known_offset():
    rng = np.random.default_rng(0)
    true = rng.normal(size=(5, 24, 3))
    pred = true.copy()
    pred[:, 3] += [0.0, 0.24, 0.0]       # one joint of 24 off by 24 cm
    np.testing.assert_allclose(mpjpe(pred, true), 0.01)
    shifted = true + np.array([1.0, 2.0, 3.0])  # a global shift is all error, unless root-aligned
    np.testing.assert_allclose(mpjpe(shifted, true), np.sqrt(14))
    np.testing.assert_allclose(mpjpe(shifted, true, root_aligned=True), 0.0, atol=1e-12)
    with pytest.raises(ValueError, match="differ"):
        mpjpe(pred[:, :10], true)
    with pytest.raises(ValueError, match=r"\(T, \*, 3\)"):
        mpjpe(pred[0], true[0])


def test_surface_distances_of_a_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(40000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # only the hemisphere facing a camera on +Z is observed, 1 cm outside the surface
    d = d[d[:, 2] > 0]
    pts = 1.01 * d
    dist = surface_distances(sphere.vertices, sphere.faces, pts,
                             visible_from=np.array([[0.0, 0.0, 5.0]]))
    # the tessellation sits inside the true sphere by < 1 mm at this subdivision
    assert np.abs(dist.to_surface - 0.01).max() < 0.0015
    # the far side was never seen, so it does not count against the cloud
    assert np.nanmax(dist.to_points) < 0.03
    everything = surface_distances(sphere.vertices, sphere.faces, pts)
    assert np.nanmax(everything.to_points) > 0.5
    assert dist.chamfer == pytest.approx(0.01, abs=0.004)


def test_points_to_surface_on_a_subset_of_the_points():
    """``max_points``: the points → surface half on a seeded subset of that many points, its
    mean within a few hundredths of a millimetre of every point's here (points 0-2 cm off a
    sphere); the surface → points half still searches every point (the same samples)."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    rng = np.random.default_rng(2)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = d * (1.0 + rng.uniform(0.0, 0.02, (len(d), 1)))
    every = surface_distances(sphere.vertices, sphere.faces, pts, seed=3)
    some = surface_distances(sphere.vertices, sphere.faces, pts, seed=3, max_points=4000)
    again = surface_distances(sphere.vertices, sphere.faces, pts, seed=3, max_points=4000)
    assert len(every.to_surface) == 20000 and len(some.to_surface) == 4000
    assert np.array_equal(some.to_surface, again.to_surface)  # seeded
    assert abs(some.to_surface.mean() - every.to_surface.mean()) < 3e-4
    assert np.array_equal(some.to_points, every.to_points)
    few = surface_distances(sphere.vertices, sphere.faces, pts[:100], seed=3, max_points=4000)
    assert len(few.to_surface) == 100  # fewer points than the cap: all of them


def test_chamfer_per_frame_and_an_empty_frame():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    verts = np.stack([sphere.vertices, sphere.vertices + np.array([0.1, 0.0, 0.0])])
    cloud = trimesh.sample.sample_surface(sphere, 30000, seed=2)[0]
    out = chamfer(verts, sphere.faces, [cloud, np.zeros((0, 3))])
    assert out[0] < 0.005 and np.isnan(out[1])
    with pytest.raises(ValueError, match="clouds"):
        chamfer(verts, sphere.faces, [cloud])


def test_foot_skate_counts_only_contact_pairs():
    t = 6
    feet = np.zeros((t, 4, 3))
    feet[:, 0, 0] = np.arange(t) * 0.002          # heel slides 2 mm / frame
    feet[:, 1, 1] = np.arange(t) * 0.05           # toe lifts: vertical motion is not skate
    contact = np.ones((t, 4), bool)
    contact[3, 0] = False                          # breaks two of the heel's pairs
    out = foot_skate(feet, contact)
    assert len(out) == 4 * (t - 1) - 2
    np.testing.assert_allclose(np.sort(out)[-3:], 2.0)
    assert out.max() == pytest.approx(2.0)
    assert foot_skate(feet, np.zeros((t, 4), bool)).size == 0
    with pytest.raises(ValueError, match="contact"):
        foot_skate(feet, contact[:, :2])


def test_jitter_of_a_cubic_and_of_noise():
    fps = 30.0
    time = np.arange(60) / fps
    cubic = np.zeros((60, 2, 3))
    cubic[..., 0] = (time ** 3)[:, None]           # jerk 6 m/s³ everywhere
    np.testing.assert_allclose(jitter(cubic, fps), 6.0, rtol=1e-6)
    noisy = cubic + np.random.default_rng(3).normal(0, 0.001, cubic.shape)
    assert jitter(noisy, fps).mean() > 2 * jitter(cubic, fps).mean()
    with pytest.raises(ValueError, match="4 frames"):
        jitter(cubic[:3], fps)


def test_foot_points_of_the_bundled_model():
    model = load_body_model("couch-body-coarse")
    rest = model().vertices.detach().numpy()
    feet = foot_points(rest, model.keypoint_ids)
    assert feet.shape == (1, 4, 3)
    # standing in the rest pose: heels behind toes (+Z is forward), all near the lowest point
    heel_l, toe_l, heel_r, toe_r = feet[0]
    assert heel_l[2] < toe_l[2] and heel_r[2] < toe_r[2]
    assert np.all(feet[0, :, 1] - rest[0, :, 1].min() < 0.06)
    assert heel_l[0] > 0 > heel_r[0]                 # SMPL: the body's left is +X
    with pytest.raises(ValueError, match="LHeel"):
        foot_points(rest, {k: 0 for k in FOOT_KEYPOINTS[1:]})


def test_sync_error():
    assert sync_error(0.1, 40.0, 0.098, 55.0) == pytest.approx((2.0, 15.0))
