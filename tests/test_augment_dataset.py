"""Augmented dataset (augment/dataset.py, augment/cli.py; augmentation issue item 4).

One simulated right-hand sit-down on an armchair (the simulator's motion + truth path without
rendering, as tests/test_augment_ik.py: ``simulate_sequence`` + ``ground_truth``, 8 s at 15 fps)
written as a processed.h5, augmented onto 2 shapes of ``fixtures/shapenet_mini`` drawn with
seed 3 (armchair_0 and straight_0; scale in [0.95, 1.05], 2 worker processes, default IK), read
back and checked against the issue's thresholds on the kept sequences; then a forced rejection
and bad arguments through the CLI.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import h5py
import numpy as np
import open3d as o3d
import pytest
import torch

from couch.augment import augment_dataset, canonical_chair_frame
from couch.augment.cli import main
from couch.body import load_body_model
from couch.fitting import BodyParams, pose_body
from couch.fitting.body import cached_model
from couch.fitting.metrics import foot_points, foot_skate
from couch.geometry import apply_transform
from couch.schema import read_processed, read_session_group, write_processed

SHAPES = Path(__file__).parent.parent / "fixtures" / "shapenet_mini"
FPS = 15.0


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from couch.tools.sim.session import simulate_sequence
    from couch.tools.sim.truth import ground_truth

    torch.set_num_threads(1)
    tmp = tmp_path_factory.mktemp("augment")
    start = time.perf_counter()
    full, coarse = load_body_model("couch-body"), load_body_model("couch-body-coarse")
    seq = simulate_sequence(np.random.default_rng(0), full, coarse, interaction="right_hand",
                            chair="armchair", duration=8.0)
    times = np.arange(0.0, seq.motion.duration, 1.0 / FPS)
    truth = ground_truth("sit", seq.motion, times, seq.placement, full, coarse, fps=FPS)
    assert truth.contact_active[:, 2].sum() >= 10, "the draw lost its hand contact"
    src_path = tmp / "sit" / "processed.h5"
    write_processed(src_path, truth)
    sim_s = time.perf_counter() - start
    start = time.perf_counter()
    summary = augment_dataset([src_path], SHAPES, tmp / "out", per_sequence=2,
                              scale_range=(0.95, 1.05), seed=3, workers=2,
                              cache_dir=tmp / "cache")
    print(f"\nsimulated {len(times)} frames in {sim_s:.1f} s; augment_dataset "
          f"{time.perf_counter() - start:.1f} s")
    print(summary.text())
    for s in summary.sequences:
        st = {k: (np.nan if v is None else v) for k, v in s["stats"].items()}
        print(f"  {s['shape']} ({s['category']}, scale {s['scale']:.3f}): reach median "
              f"{100 * st['reach_median']:.3f} cm, 95th {100 * st['reach_p95']:.3f} cm; skate "
              f"{st['skate_before']:.3f} -> {st['skate_after']:.3f} mm/frame; jump "
              f"{st['jump_before']:.3f} -> {st['jump_after']:.3f} m/frame; penetration 95th "
              f"{100 * st['penetration_p95_before']:.2f} -> {100 * st['penetration_p95']:.2f} cm;"
              f" {st['fallback_contacts']} fallback contacts, {st['iterations']} iterations, "
              f"{st['seconds']:.1f} s")
    with h5py.File(summary.dataset, "r") as h5:
        groups = {name: read_session_group(h5[name]) for name in h5}
    return dict(tmp=tmp, src_path=src_path, truth=truth, placement=seq.placement,
                summary=summary, groups=groups)


def test_canonical_chair_frame_matches_the_placement(run):
    truth, placement = run["truth"], run["placement"]
    world = apply_transform(truth.object_pose, truth.object_vertices.astype(np.float64))
    est = canonical_chair_frame(world, truth.object_faces)
    true = placement.world_from_chair
    cos = np.clip((np.trace(est[:3, :3].T @ true[:3, :3]) - 1) / 2, -1, 1)
    angle = np.degrees(np.arccos(cos))
    dist = np.linalg.norm(est[:3, 3] - true[:3, 3])
    print(f"chair frame from geometry: {angle:.2f} deg, {100 * dist:.2f} cm from the truth")
    np.testing.assert_allclose(est[:3, 1], [0, 1, 0], atol=1e-9)  # rotation about +Y only
    assert angle < 3.0 and dist < 0.02 and est[1, 3] == 0.0


def test_file_and_summary(run):
    summary, groups = run["summary"], run["groups"]
    doc = json.loads(summary.summary.read_text())
    assert len(doc["sequences"]) == 2 and doc["kept"] + doc["rejected"] == 2
    assert doc["kept"] == summary.kept == len(groups) >= 1
    assert doc["rejected"] == sum(doc["rejected_by_reason"].values())
    kept = [s for s in doc["sequences"] if s["kept"]]
    assert sorted(s["group"] for s in kept) == sorted(groups)
    assert len({s["shape"] for s in doc["sequences"]}) == 2  # two different shapes
    for s in doc["sequences"]:
        assert s["kept"] == (s["rejected"] is None)
    truth = run["truth"]
    for name, g in groups.items():
        parts = name.split("__")
        assert parts[0] == "sit" and parts[2] in ("0", "1") and g.object_name == parts[1]
        assert g.num_frames == truth.num_frames
        np.testing.assert_array_equal(g.contact_active, truth.contact_active)
        np.testing.assert_array_equal(g.interaction, truth.interaction)
        assert g.quality["reach_error"].shape == (g.num_frames, 5)
        assert g.quality["penetration"].shape == (g.num_frames,)


def test_contacts_on_new_surface(run):
    for name, g in run["groups"].items():
        scene = o3d.t.geometry.RaycastingScene()
        world = apply_transform(g.object_pose, g.object_vertices.astype(np.float64))
        scene.add_triangles(world.astype(np.float32), g.object_faces.astype(np.uint32))
        pts = g.contact_points[g.contact_active].astype(np.float32)
        d = np.abs(scene.compute_distance(o3d.core.Tensor(pts)).numpy())
        print(f"{name}: {len(pts)} contact points, max distance to the new chair "
              f"{1000 * d.max():.2f} mm")
        assert np.all(np.isnan(g.contact_points[~g.contact_active]))
        assert d.max() < 0.005
        assert world[:, 1].min() == pytest.approx(0.0, abs=1e-4)  # stands on the floor


def test_reach(run):
    for g in run["groups"].values():
        err = g.quality["reach_error"][g.contact_active]
        err = err[np.isfinite(err)]
        assert err.size and np.median(err) <= 0.01 and np.percentile(err, 95) <= 0.02


def _posed(model, session):
    return pose_body(model, BodyParams.from_processed(session))[0]


def test_skate_and_jumps(run):
    model = cached_model("couch-body-coarse")
    truth = run["truth"]
    f0 = foot_points(_posed(model, truth), model.keypoint_ids)
    speed = np.linalg.norm(np.diff(f0[..., [0, 2]], axis=0), axis=-1)
    on_floor = (f0[..., 1] < 0.05) & (np.vstack([speed, speed[-1:]]) < 0.01)
    plant = np.repeat(np.stack([on_floor[:, :2].all(1), on_floor[:, 2:].all(1)], 1), 2, 1)
    s0 = foot_skate(f0, plant).mean()
    jump0 = np.linalg.norm(np.diff(truth.joints, axis=0), axis=-1).max()
    for name, g in run["groups"].items():
        s1 = foot_skate(foot_points(_posed(model, g), model.keypoint_ids), plant).mean()
        jump1 = np.linalg.norm(np.diff(g.joints, axis=0), axis=-1).max()
        print(f"{name}: skate {s0:.3f} -> {s1:.3f} mm/frame, largest joint jump {jump0:.3f} -> "
              f"{jump1:.3f} m/frame")
        assert s1 <= s0 + 1.0 and jump1 <= 1.1 * jump0


def test_cli_rejection_reported(run):
    out = run["tmp"] / "cli_reject"
    code = main(["--shapes", str(SHAPES), str(run["src_path"].parent), "-o", str(out),
                 "--per-sequence", "1", "--workers", "1", "--ik-iterations", "10",
                 "--max-penetration", "-1", "--cache-dir", str(run["tmp"] / "cache"), "-q"])
    assert code == 1  # nothing kept
    doc = json.loads((out / "summary.json").read_text())
    assert doc["kept"] == 0 and doc["rejected_by_reason"] == {"penetration": 1}
    assert doc["sequences"][0]["rejected"].startswith("penetration: 95th percentile")
    with h5py.File(out / "augmented.h5", "r") as h5:
        assert len(h5) == 0 and h5.attrs["kind"] == "augmented"
    assert read_processed(run["src_path"]).session == "sit"  # source untouched


def test_cli_bad_arguments(run, tmp_path, capsys):
    src = str(run["src_path"])
    base = ["-o", str(tmp_path / "o"), "-q"]
    assert main(["--shapes", str(tmp_path / "nope"), src, *base]) == 2
    assert "nope" in capsys.readouterr().err
    assert main(["--shapes", str(SHAPES), str(tmp_path / "missing.h5"), *base]) == 2
    assert "missing.h5" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["--shapes", str(SHAPES), str(tmp_path / "empty"), *base]) == 2
    assert "no processed.h5" in capsys.readouterr().err
    assert main(["--shapes", str(SHAPES), src, "--scale-range", "1.2,0.8", *base]) == 2
    assert main(["--shapes", str(SHAPES), src, "--per-sequence", "0", *base]) == 2
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5")
    assert main(["--shapes", str(SHAPES), str(bad), *base]) == 2
    assert "bad.h5" in capsys.readouterr().err
    assert main([src, *base]) == 2  # --shapes missing
    assert not (tmp_path / "o" / "summary.json").exists()
