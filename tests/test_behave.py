"""BEHAVE-style frame folders (capture/behave.py): writer, streaming reader, bad input.

Besides write -> read round trips, the files are opened the way BEHAVE's own loaders open them
(json.load, cv2.imread IMREAD_ANYDEPTH / GRAYSCALE, PIL for colour, np.load of the point-cloud
table, ``p @ R.T + t`` with config.json), and a folder laid out by hand as the BEHAVE release
lays it out (``sequences/``, JPEG masks, fit pickles, no couch extras) is read.
"""

from __future__ import annotations

import json
import os
import pickle

import cv2
import numpy as np
import pytest
from PIL import Image

from couch.capture.behave import (
    BEHAVE_Y_UP,
    BehaveFormatError,
    BehaveWriter,
    FrameImages,
    frame_name,
    open_behave_sequence,
    parse_frame_name,
)
from couch.geometry import invert_transform
from couch.tools.sim.kinect import place_cameras, undistorted_grid, world_from_color

SEQ = "Date01_Sub01_chairwood_sit"
INFO_KEYS = {"config", "intrinsic", "cat", "gender", "empty", "kinects", "beta"}
H, W = 720, 1280  # colour 720P, the smallest mode a KinectCalibration allows


def _images(rng: np.random.Generator, with_object: bool = True) -> FrameImages:
    # Smooth colour (JPEG keeps it to a few levels), arbitrary depth and masks (lossless).
    yy, xx = np.mgrid[0:H, 0:W]
    phase = rng.uniform(0, 6.28, 3)
    color = np.stack([127 + 100 * np.sin(xx / 97.0 + yy / 131.0 + p) for p in phase], axis=-1)
    depth = rng.integers(0, 12000, (H, W), dtype=np.uint16)
    depth[rng.random((H, W)) < 0.1] = 0
    person = rng.random((H, W)) < 0.3
    obj = (rng.random((H, W)) < 0.2) if with_object else None
    return FrameImages(color.astype(np.uint8), depth, person, obj)


@pytest.fixture(scope="module")
def rig():
    rng = np.random.default_rng(11)
    cams = place_cameras(rng, 3)
    calibs = [c for c, _ in cams]
    poses = np.stack([world_from_color(c, p) for c, p in cams])
    return calibs, poses


@pytest.fixture(scope="module")
def written(tmp_path_factory, rig):
    calibs, poses = rig
    root = tmp_path_factory.mktemp("behave")
    rng = np.random.default_rng(5)
    writer = BehaveWriter(root, SEQ, "Date01", calibs, poses, gender="female",
                          object_category="chairwood", betas=np.linspace(-1, 1, 10))
    frames = {}
    for i, t in enumerate([3.0, 3.0 + 1 / 30, 3.0 + 2 / 30]):
        ims = [_images(rng, with_object=(i != 1)) for _ in calibs]
        writer.write_frame(t, ims)
        frames[frame_name(t)] = ims
    return root, writer, frames


# ---------------------------------------------------------------------------- names
def test_frame_names():
    assert frame_name(3.0) == "t0003.000"
    assert frame_name(3 + 1 / 30) == "t0003.033"
    assert frame_name(3 + 2 / 30) == "t0003.067"
    assert frame_name(0.0005) == "t0000.001"
    assert frame_name(12345.6789) == "t12345.679"
    # BEHAVE's own spelling: 't{:08.3f}'.format(t)
    for t in (0.0, 3.0, 7.533, 123.4, 9999.999):
        assert frame_name(t) == f"t{t:08.3f}"
        assert parse_frame_name(frame_name(t)) == pytest.approx(t, abs=5e-4)
    for bad in ("t3.000", "t0003.0", "t0003.0000", "frame_001", "t00003.000", "0003.000"):
        assert parse_frame_name(bad) is None
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            frame_name(bad)


# ---------------------------------------------------------------------------- round trip
def test_round_trip(written, rig):
    root, _, frames = written
    calibs, _ = rig
    seq = open_behave_sequence(root / SEQ)
    assert seq.frame_names == list(frames)
    np.testing.assert_allclose(seq.frame_times, [3.0, 3.033, 3.067])
    assert len(seq) == 3 and seq.kinects == [0, 1, 2]
    assert seq.gender == "female" and seq.category == "chairwood"
    np.testing.assert_allclose(seq.betas, np.linspace(-1, 1, 10))
    assert seq.calibrations == calibs  # exact: BEHAVE's JSON keeps every float
    for got, want in zip(seq.calibrations, calibs, strict=True):
        assert got.to_json() == want.to_json()  # factory JSON sidecar kept IMU/metadata
    assert seq.floor_aligned and not seq.warnings and not seq.skipped

    count = 0
    for frame in seq:
        want = frames[frame.name]
        assert frame.time_s == parse_frame_name(frame.name)
        assert len(frame.images) == 3
        for got, exp in zip(frame.images, want, strict=True):
            assert got.color_rgb.dtype == np.uint8 and got.color_rgb.shape == (H, W, 3)
            diff = np.abs(got.color_rgb.astype(int) - exp.color_rgb.astype(int))
            assert diff.mean() < 1.5 and np.percentile(diff, 99.9) <= 8
            assert got.depth_mm.dtype == np.uint16
            np.testing.assert_array_equal(got.depth_mm, exp.depth_mm)
            np.testing.assert_array_equal(got.person_mask, exp.person_mask)
            if exp.object_mask is None:
                assert got.object_mask is None
            else:
                np.testing.assert_array_equal(got.object_mask, exp.object_mask)
        assert frame.person_fit() is None and frame.object_fit() is None
        count += 1
    assert count == 3


def test_poses_round_trip_through_behave_convention(written, rig):
    root, _, _ = written
    _, poses = rig
    seq = open_behave_sequence(root / SEQ)
    for got, want in zip(seq.world_from_color, poses, strict=True):
        np.testing.assert_allclose(got, want, atol=1e-12)
    # BEHAVE's world is k1's colour camera: its config.json is the identity.
    np.testing.assert_allclose(seq.behave_from_color[1], np.eye(4), atol=1e-12)
    # config.json read as BEHAVE reads it (data/utils.py load_kinect_poses) maps a point from
    # camera k's colour frame into k1's colour frame with p @ R.T + t (rgbd2pclouds.py).
    x_world = np.array([[0.3, 0.9, -0.2], [1.0, 0.1, 0.5]])
    x_k1 = x_world @ invert_transform(poses[1])[:3, :3].T + invert_transform(poses[1])[:3, 3]
    for k in range(3):
        cfg = json.loads((root / "calibs/Date01/config" / str(k) / "config.json").read_text())
        assert set(cfg) == {"rotation", "translation"}
        r = np.array(cfg["rotation"]).reshape((3, 3))
        t = np.array(cfg["translation"])
        to_k = invert_transform(poses[k])
        x_k = x_world @ to_k[:3, :3].T + to_k[:3, 3]
        np.testing.assert_allclose(x_k @ r.T + t, x_k1, atol=1e-12)
    # couch_world.json takes BEHAVE-world points into ours (Y up: BEHAVE's Y is down).
    cw = json.loads((root / "calibs/Date01/config/couch_world.json").read_text())
    r = np.array(cw["rotation"]).reshape(3, 3)
    np.testing.assert_allclose(x_k1 @ r.T + np.array(cw["translation"]), x_world, atol=1e-12)


def test_files_open_with_independent_readers(written, rig):
    root, _, frames = written
    calibs, _ = rig
    seq_dir = root / SEQ
    info = json.loads((seq_dir / "info.json").read_text())
    assert set(info) == INFO_KEYS
    assert info["cat"] == "chairwood" and info["gender"] == "female"
    assert info["kinects"] == [0, 1, 2] and info["empty"] is None and len(info["beta"]) == 10
    # seq_utils.py joins the paths onto the sequence folder.
    config = seq_dir / info["config"]
    intrinsic = seq_dir / info["intrinsic"]
    for k, calib in enumerate(calibs):
        cfg = json.loads((config / str(k) / "config.json").read_text())
        assert len(cfg["rotation"]) == 9 and len(cfg["translation"]) == 3
        cal = json.loads((intrinsic / str(k) / "calibration.json").read_text())
        for cam, intr in (("color", calib.color), ("depth", calib.depth)):
            c = cal[cam]
            assert (c["width"], c["height"]) == (intr.width, intr.height)
            assert (c["fx"], c["fy"], c["cx"], c["cy"]) == (intr.fx, intr.fy, intr.cx, intr.cy)
            assert c["opencv"][4:] == intr.dist.tolist()  # what KinectCalib feeds cv2
            assert c["metric_radius"] == intr.metric_radius and c["codx"] == 0.0
        for key in ("color_to_depth", "depth_to_color"):
            assert len(cal[key]["rotation"]) == 9 and len(cal[key]["translation"]) == 3
        d2c = np.array(cal["depth_to_color"]["rotation"]).reshape(3, 3)
        np.testing.assert_allclose(d2c, calib.color_from_depth[:3, :3])
        assert np.linalg.norm(cal["depth_to_color"]["translation"]) < 0.1  # metres
        # pointcloud_table.npy as KinectCalib uses it: (H,W,2) rays of the colour pixels; the
        # simulator's own undistortion agrees, and BEHAVE's projection (K + opencv[4:])
        # brings each ray back to its pixel.
        table = np.load(intrinsic / str(k) / "pointcloud_table.npy", allow_pickle=False)
        assert table.shape == (H, W, 2) and table.dtype == np.float32
        ok = np.isfinite(table[..., 0])
        assert ok.mean() > 0.999
        np.testing.assert_allclose(table[ok], undistorted_grid(calib.color)[ok], atol=1e-6)
        kmat = np.array([[cal["color"]["fx"], 0, cal["color"]["cx"]],
                         [0, cal["color"]["fy"], cal["color"]["cy"]], [0, 0, 1.0]])
        sample = np.flatnonzero(ok.ravel())[::997]
        pts = np.dstack([table, np.ones((H, W), np.float32)]).reshape(-1, 3)[sample]
        uv, _ = cv2.projectPoints(pts.astype(np.float64)[:, None], np.zeros(3), np.zeros(3), kmat,
                                  np.array(cal["color"]["opencv"][4:]))
        np.testing.assert_allclose(uv.reshape(-1, 2),
                                   np.column_stack([sample % W, sample // W]), atol=0.01)

    name, ims = next(iter(frames.items()))
    for k, exp in enumerate(ims):
        folder = seq_dir / name
        depth = cv2.imread(str(folder / f"k{k}.depth.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16
        np.testing.assert_array_equal(depth, exp.depth_mm)
        np.testing.assert_array_equal(
            cv2.imread(str(folder / f"k{k}.depth.png"), cv2.IMREAD_ANYDEPTH), exp.depth_mm)
        mask = cv2.imread(str(folder / f"k{k}.person_mask.png"), cv2.IMREAD_GRAYSCALE) > 127
        np.testing.assert_array_equal(mask, exp.person_mask)
        with Image.open(folder / f"k{k}.color.jpg") as im:
            assert im.format == "JPEG" and im.size == (W, H)
            rgb = np.array(im.convert("RGB"))
        assert np.abs(rgb.astype(int) - exp.color_rgb.astype(int)).mean() < 1.5


def test_second_sequence_shares_calibration_and_conflicts_are_refused(written, rig, tmp_path):
    root, _, _ = written
    calibs, poses = rig
    # Same calibration, same date: fine (files untouched).
    before = (root / "calibs/intrinsics/0/calibration.json").stat().st_mtime_ns
    BehaveWriter(root, "Date01_Sub02_chairwood_lift", "Date01", calibs, poses, gender="male",
                 object_category="chairwood")
    assert (root / "calibs/intrinsics/0/calibration.json").stat().st_mtime_ns == before
    # A different camera pose on the same date would change another sequence's calibration.
    moved = poses.copy()
    moved[2, :3, 3] += 0.1
    with pytest.raises(ValueError, match="different calibration"):
        BehaveWriter(root, "Date01_Sub03_chairwood_sit", "Date01", calibs, moved,
                     gender="male", object_category="chairwood")


def test_writer_validation(rig, tmp_path):
    calibs, poses = rig
    kw = dict(gender="male", object_category="chairwood", pointcloud_tables=False)
    with pytest.raises(ValueError, match="3, 4, 4"):
        BehaveWriter(tmp_path, SEQ, "Date01", calibs, poses[:2], **kw)
    with pytest.raises(ValueError, match="folder name"):
        BehaveWriter(tmp_path, "../escape", "Date01", calibs, poses, **kw)
    with pytest.raises(ValueError, match="gender"):
        BehaveWriter(tmp_path, SEQ, "Date01", calibs, poses, gender="x",
                     object_category="chairwood")
    bad = poses.copy()
    bad[0, :3, :3] *= 2
    with pytest.raises(ValueError, match="rigid"):
        BehaveWriter(tmp_path, SEQ, "Date01", calibs, bad, **kw)
    w = BehaveWriter(tmp_path, SEQ, "Date01", calibs, poses, **kw)
    rng = np.random.default_rng(0)
    ims = [_images(rng) for _ in calibs]
    with pytest.raises(ValueError, match="3 cameras"):
        w.write_frame(1.0, ims[:2])
    small = FrameImages(ims[0].color_rgb[:, :-1], ims[0].depth_mm)
    with pytest.raises(ValueError, match="camera 0: color_rgb"):
        w.write_frame(1.0, [small, *ims[1:]])
    wrong = FrameImages(ims[0].color_rgb, ims[0].depth_mm.astype(np.int32))
    with pytest.raises(ValueError, match="uint16"):
        w.write_frame(1.0, [wrong, *ims[1:]])
    assert not (tmp_path / SEQ / "t0001.000").exists()  # nothing written for a bad frame
    w.write_frame(1.0, ims)
    with pytest.raises(ValueError, match="already written"):
        w.write_frame(1.0004, ims)


# ---------------------------------------------------------------------------- a real layout
def _behave_camera(w, h, fx, fy, cx, cy, dist, radius=True):
    cam = {"width": w, "height": h, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
           "opencv": [fx, fy, cx, cy, *dist]}
    if radius:
        cam.update(codx=0.0, cody=0.0, metric_radius=1.7)
    return cam


@pytest.fixture
def release(tmp_path):
    """A BEHAVE release laid out by hand (README + video2images.py): sequences/ one level down,
    JPEG masks, no couch_world.json / azure_calibration.json, a depth_to_color in mm, fits."""
    root = tmp_path / "behave"
    seq = root / "sequences" / "Date03_Sub03_chairwood_sit"
    seq.mkdir(parents=True)
    info = {"config": "../../calibs/Date03/config", "intrinsic": "../../calibs/intrinsics",
            "cat": "chairwood", "gender": "male", "empty": "../../calibs/Date03/background",
            "kinects": [0, 1], "beta": None}
    (seq / "info.json").write_text(json.dumps(info))
    dist = [0.5, -2.5, 6e-4, -2e-4, 1.4, 0.4, -2.3, 1.3]
    poses = [np.eye(4), np.eye(4)]
    poses[0][:3, :3] = cv2.Rodrigues(np.array([0.1, -1.2, 0.05]))[0]
    poses[0][:3, 3] = [2.0, 0.1, 1.5]
    for k in range(2):
        d = root / "calibs/intrinsics" / str(k)
        d.mkdir(parents=True)
        cal = {"color": _behave_camera(1280, 720, 611.0 + k, 610.5, 638.0, 363.0, dist,
                                       radius=(k == 0)),
               "depth": _behave_camera(640, 576, 504.0, 504.1, 321.0, 332.0,
                                       [6.1, 4.4, 0, 1e-4, 0.24, 6.4, 6.4, 1.2]),
               "color_to_depth": {"rotation": np.eye(3).ravel().tolist(),
                                  "translation": [32.0, 2.0, -4.0]},
               "depth_to_color": {"rotation": np.eye(3).ravel().tolist(),
                                  "translation": [-32.0, -2.0, 4.0]}}  # the SDK's mm
        (d / "calibration.json").write_text(json.dumps(cal))
        c = root / "calibs/Date03/config" / str(k)
        c.mkdir(parents=True)
        (c / "config.json").write_text(json.dumps(
            {"rotation": poses[k][:3, :3].ravel().tolist(),
             "translation": poses[k][:3, 3].tolist()}))
    rng = np.random.default_rng(3)
    for t in ("t0003.000", "t0003.033"):
        f = seq / t
        f.mkdir()
        for k in range(2):
            cv2.imwrite(str(f / f"k{k}.color.jpg"), rng.integers(0, 255, (720, 1280, 3), np.uint8))
            cv2.imwrite(str(f / f"k{k}.depth.png"),
                        rng.integers(0, 4000, (720, 1280), dtype=np.uint16))
            cv2.imwrite(str(f / f"k{k}.person_mask.jpg"),
                        np.where(rng.random((720, 1280)) < 0.5, 0, 255).astype(np.uint8))
            cv2.imwrite(str(f / f"k{k}.obj_rend_mask.jpg"), np.zeros((720, 1280), np.uint8))
        (f / "person" / "fit02").mkdir(parents=True)
        with open(f / "person" / "fit02" / "person_fit.pkl", "wb") as fh:
            pickle.dump({"pose": np.zeros(156), "betas": np.ones(10), "trans": np.arange(3.0)},
                        fh, protocol=2)
        (f / "chair" / "fit01").mkdir(parents=True)
        with open(f / "chair" / "fit01" / "chair_fit.pkl", "wb") as fh:
            pickle.dump({"angle": np.array([0.1, 0.2, 0.3]), "trans": np.ones(3)}, fh)
    (seq / "notes").mkdir()  # not a frame folder
    return seq, poses


def test_reads_a_behave_release_folder(release):
    seq_dir, poses = release
    seq = open_behave_sequence(seq_dir)
    assert seq.kinects == [0, 1] and seq.betas is None
    assert not seq.floor_aligned and "not at y = 0" in seq.warnings[0]
    for k in range(2):
        np.testing.assert_allclose(seq.behave_from_color[k], poses[k])
        np.testing.assert_allclose(seq.world_from_color[k], BEHAVE_Y_UP @ poses[k])
        cal = seq.calibrations[k]
        assert cal.depth_mode == "NFOV_UNBINNED" and cal.color_resolution == "720P"
        np.testing.assert_allclose(cal.color_from_depth[:3, 3], [-0.032, -0.002, 0.004])
        assert cal.color.metric_radius == 1.7  # absent in k1's file: the SDK default
    assert cal.color.fx == 612.0
    assert [s.path.name for s in seq.skipped] == ["notes"]
    frames = list(seq)
    assert [f.name for f in frames] == ["t0003.000", "t0003.033"]
    im = frames[0].images[0]
    assert im.person_mask.dtype == bool and 0.4 < im.person_mask.mean() < 0.6
    assert not im.object_mask.any()
    fit = frames[1].person_fit()
    assert set(fit) == {"pose", "betas", "trans"}
    np.testing.assert_array_equal(fit["trans"], np.arange(3.0))
    assert frames[1].object_fit_path().parent.parent.name == "chair"
    np.testing.assert_array_equal(frames[1].object_fit()["angle"], [0.1, 0.2, 0.3])
    assert frames[1].person_fit("fit03") is None
    assert seq.read_frame("t0003.033").name == "t0003.033"
    with pytest.raises(KeyError):
        seq.read_frame("t0009.000")


def test_unsafe_fit_pickle_is_refused(release, tmp_path):
    seq_dir, _ = release
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.makedirs, (str(marker),))

    path = seq_dir / "t0003.000" / "person" / "fit02" / "person_fit.pkl"
    path.write_bytes(pickle.dumps({"pose": Evil()}))
    frame = next(iter(open_behave_sequence(seq_dir)))  # images load; the fit is not touched
    assert not marker.exists()
    with pytest.raises(BehaveFormatError, match=r"person_fit\.pkl"):
        frame.person_fit()
    assert not marker.exists()
    path.write_bytes(b"\x80\x02}q\x00")  # cut off
    with pytest.raises(BehaveFormatError, match=r"person_fit\.pkl"):
        frame.person_fit()


# ---------------------------------------------------------------------------- bad input
@pytest.fixture
def small_seq(tmp_path, rig):
    calibs, poses = rig
    rng = np.random.default_rng(9)
    w = BehaveWriter(tmp_path, SEQ, "Date01", calibs[:1], poses[:1], gender="male",
                     object_category="chairwood", pointcloud_tables=False)
    for t in (1.0, 1.1, 1.2):
        w.write_frame(t, [_images(rng)])
    return tmp_path / SEQ


def test_missing_or_broken_metadata_is_an_error(small_seq):
    calib = small_seq.parent / "calibs/intrinsics/0/calibration.json"
    text = calib.read_text()
    calib.unlink()
    with pytest.raises(BehaveFormatError, match=r"intrinsics/0/calibration.json.*missing"):
        open_behave_sequence(small_seq)
    calib.write_text(text.replace('"fx"', '"fX"', 1))
    with pytest.raises(BehaveFormatError, match=r"calibration.json.*color.fx"):
        open_behave_sequence(small_seq)
    calib.write_text(text)
    pose = small_seq.parent / "calibs/Date01/config/0/config.json"
    pose.write_text('{"rotation": [1, 0, 0], "translation": [0, 0, 0]}')
    with pytest.raises(BehaveFormatError, match=r"config.json.*rotation"):
        open_behave_sequence(small_seq)
    info = small_seq / "info.json"
    info.write_text("{not json")
    with pytest.raises(BehaveFormatError, match=r"info.json.*not valid JSON"):
        open_behave_sequence(small_seq)
    info.unlink()
    with pytest.raises(BehaveFormatError, match=r"info.json is missing"):
        open_behave_sequence(small_seq)
    with pytest.raises(BehaveFormatError, match="not a sequence folder"):
        open_behave_sequence(small_seq / "nope")


def test_damaged_frames_are_skipped_and_reported(small_seq):
    jpg = small_seq / "t0001.000" / "k0.color.jpg"
    jpg.write_bytes(jpg.read_bytes()[:5000])  # truncated JPEG
    png = small_seq / "t0001.100" / "k0.depth.png"
    png.write_bytes(png.read_bytes()[:-100])  # truncated PNG
    mask = small_seq / "t0001.200" / "k0.obj_rend_mask.png"
    data = bytearray(mask.read_bytes())
    data[60:80] = b"\x00" * 20  # corrupt IDAT: bad CRC
    mask.write_bytes(bytes(data))
    (small_seq / "t1.5").mkdir()  # not t%04d.%03d

    seq = open_behave_sequence(small_seq)
    assert seq.frame_names == ["t0001.000", "t0001.100", "t0001.200"]
    frames = list(seq)
    assert [f.name for f in frames] == ["t0001.200"]
    assert frames[0].images[0].object_mask is None
    assert frames[0].images[0].person_mask is not None
    reasons = {(s.frame, s.path.name): s.reason for s in seq.skipped}
    assert set(reasons) == {(None, "t1.5"), ("t0001.000", "k0.color.jpg"),
                            ("t0001.100", "k0.depth.png"), ("t0001.200", "k0.obj_rend_mask.png")}
    assert "truncated JPEG" in reasons["t0001.000", "k0.color.jpg"]
    assert "truncated PNG" in reasons["t0001.100", "k0.depth.png"]
    assert "mask dropped" in reasons["t0001.200", "k0.obj_rend_mask.png"]
    assert len(list(seq)) == 1 and len(seq.skipped) == 4  # reset per iteration, not doubled

    with pytest.raises(BehaveFormatError, match=r"t1\.5"):
        open_behave_sequence(small_seq, strict=True)
    (small_seq / "t1.5").rmdir()
    strict = open_behave_sequence(small_seq, strict=True)
    with pytest.raises(BehaveFormatError, match=r"t0001.000/k0.color.jpg: truncated JPEG"):
        list(strict)


def test_missing_image_skips_the_frame(small_seq):
    (small_seq / "t0001.100" / "k0.depth.png").unlink()
    seq = open_behave_sequence(small_seq)
    assert [f.name for f in seq] == ["t0001.000", "t0001.200"]
    assert [(s.frame, s.path.name) for s in seq.skipped] == [("t0001.100", "k0.depth.png")]
    assert "missing" in seq.skipped[0].reason


def test_eight_bit_depth_is_an_error(small_seq):
    depth = small_seq / "t0001.100" / "k0.depth.png"
    cv2.imwrite(str(depth), np.zeros((H, W), np.uint8))
    seq = open_behave_sequence(small_seq)
    with pytest.raises(BehaveFormatError, match=r"k0.depth.png: depth PNG is 8-bit grey, "
                                                r"expected 16-bit"):
        list(seq)
    cv2.imwrite(str(depth), np.zeros((H, W, 3), np.uint16))
    with pytest.raises(BehaveFormatError, match="16-bit RGB"):
        list(open_behave_sequence(small_seq))


def test_unregistered_depth_and_wrong_colour_size_are_errors(small_seq):
    depth = small_seq / "t0001.100" / "k0.depth.png"
    cv2.imwrite(str(depth), np.zeros((576, 640), np.uint16))  # raw depth-camera image
    with pytest.raises(BehaveFormatError, match="registered to the colour image"):
        list(open_behave_sequence(small_seq))
    cv2.imwrite(str(depth), np.zeros((H, W), np.uint16))
    color = small_seq / "t0001.200" / "k0.color.jpg"
    cv2.imwrite(str(color), np.zeros((1536, 2048, 3), np.uint8))
    with pytest.raises(BehaveFormatError, match=r"calibration .* is for 1280x720"):
        list(open_behave_sequence(small_seq))


def test_iteration_streams(small_seq):
    """Frames are read one at a time while iterating (damage after open is still seen)."""
    seq = open_behave_sequence(small_seq)
    it = iter(seq)
    first = next(it)
    assert first.name == "t0001.000"
    (small_seq / "t0001.100" / "k0.color.jpg").write_bytes(b"")
    assert [f.name for f in it] == ["t0001.200"]
    assert seq.skipped[0].frame == "t0001.100"
