"""couch-simulate end to end: every output opened by a reader that did not write it.

Simulator settings of the session generated here (once per test module): 4 cameras, 2 s at
5 fps, NFOV_2X2BINNED depth, 20% dropped frames, default noise (1.0), IMU clock offset −0.7 s
and drift +150 ppm, seed 11.
"""

from __future__ import annotations

import dataclasses
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import av
import numpy as np
import pytest

from couch.body import load_body_model
from couch.capture.azure_calibration import KinectCalibration
from couch.capture.azure_mkv import open_azure_mkv
from couch.capture.xbus import XbusParser, read_device_map
from couch.geometry import apply_transform
from couch.schema import read_processed
from couch.tools.contact_sheet import main as contact_sheet_main
from couch.tools.sim import recording
from couch.tools.sim.chairs import load_mesh
from couch.tools.sim.clothing import (
    CLOTHING_FILE,
    body_vertices,
    clothed_surface,
    load_clothing,
)
from couch.tools.sim.kinect import LABEL_PERSON
from couch.tools.sim.session import SessionConfig, simulate_session

MVN_NS = "{http://www.xsens.com/mvn/mvnx}"
CFG = SessionConfig(duration=2.0, fps=5.0, cameras=4, depth_mode="NFOV_2X2BINNED",
                    drop_rate=0.2, clock_offset=-0.7, drift_ppm=150.0, charuco_poses=3,
                    jpeg_quality=80, seed=11)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, dict, list[np.ndarray]]:
    """The session, and the person vertices of every scene the recorder built (a spy on
    ``build_scene``): what the cameras were shown, frame by frame."""
    out = tmp_path_factory.mktemp("session")
    shown: list[np.ndarray] = []
    real = recording.build_scene

    def spy(meshes):
        shown.extend(m.vertices.copy() for m in meshes if m.label == LABEL_PERSON)
        return real(meshes)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(recording, "build_scene", spy)
        info = simulate_session(out, CFG, progress=False)
    return out, info, shown


@pytest.fixture(scope="module")
def session(recorded) -> tuple[Path, dict]:
    return recorded[0], recorded[1]


def test_layout_and_manifest(session):
    out, info = session
    manifest = json.loads((out / "session.json").read_text())
    assert len(manifest["kinect"]) == 4
    for dev in manifest["kinect"]:
        assert (out / dev["file"]).is_file() and (out / dev["calibration_capture"]).is_file()
    assert [d["sync"] for d in manifest["kinect"]].count("MASTER") == 1
    for key in ("mvnx", "xbus", "device_map"):
        assert (out / manifest["imu"][key]).is_file()
    assert info["motion"]["interaction"] in ("right_hand", "left_hand", "both_hands",
                                             "no_contact", "free", "locomotion")


def test_pyav_decodes_the_recordings_and_frames_drop_as_asked(session):
    out, info = session
    n = round(CFG.duration * CFG.fps)
    total_dropped = 0
    for cam in info["cameras"]:
        path = out / "kinect" / f"{cam['serial']}.mkv"
        with av.open(str(path)) as container:
            titles = {s.metadata.get("title") for s in container.streams.video}
            assert {"COLOR", "DEPTH"} <= titles
            depth_stream = next(s for s in container.streams.video
                                if s.metadata.get("title") == "DEPTH")
            frames = [f.to_ndarray() for f in container.decode(depth_stream)]
            attachments = [a for a in container.streams.attachments]
            assert attachments and json.loads(bytes(attachments[0].data))
            ir_stream = next(s for s in container.streams.video
                             if s.metadata.get("title") == "IR")
            container.seek(0)
            irs = [f.to_ndarray() for f in container.decode(ir_stream)]
        assert len(frames) == len(irs) == n - len(cam["dropped_frames"])
        assert frames[0].shape == irs[0].shape == (288, 320)
        assert frames[0].dtype == irs[0].dtype == np.uint16
        # our reader returns the very same depth and IR PyAV decodes
        caps = [c for c in open_azure_mkv(path) if c.depth_mm is not None]
        assert all(np.array_equal(a, c.depth_mm) and np.array_equal(b, c.ir)
                   for a, b, c in zip(frames, irs, caps, strict=True))
        valid = frames[0] > 0
        assert 0.2 < valid.mean() and 300 < np.median(frames[0][valid]) < 6000
        # the IR image lights what the depth measures (a room 1-6 m from the camera)
        assert (irs[0][valid] > 0).mean() > 0.95 and 5 < np.median(irs[0][valid]) < 3000
        total_dropped += len(cam["dropped_frames"])
    # 40 camera-frames at p = 0.2: 8 expected, binomial sd 2.5
    assert 1 <= total_dropped <= 16


def test_attached_calibration_matches_the_truth(session):
    out, info = session
    for cam in info["cameras"]:
        rec = open_azure_mkv(out / "kinect" / f"{cam['serial']}.mkv")
        calib = rec.calibration
        assert isinstance(calib, KinectCalibration)
        assert (calib.depth.width, calib.depth.height) == (320, 288)
        world_from_color = np.asarray(cam["world_from_color"])
        world_from_depth = np.asarray(cam["world_from_depth"])
        # the colour camera sits where calibration's color_from_depth puts it
        assert np.allclose(world_from_depth @ np.linalg.inv(calib.color_from_depth),
                           world_from_color, atol=1e-6)


def test_device_timestamps_follow_each_device_clock(session):
    out, info = session
    for cam in info["cameras"]:
        stamps = [c.timestamp_us for c in open_azure_mkv(out / "kinect" / f"{cam['serial']}.mkv")]
        kept = [k for k in range(round(CFG.duration * CFG.fps)) if k not in cam["dropped_frames"]]
        first = info["motion"]["kinect_time_of_first_frame_s"]
        expected = (first + np.array(kept) / CFG.fps + cam["device_clock_offset_s"]) * 1e6
        assert np.abs(np.array(stamps) - expected).max() < 300  # jitter: 40 us std


def test_mvnx_parses_as_plain_xml_on_the_asked_clock(session):
    out, info = session
    root = ET.parse(out / "imu" / "recording.mvnx").getroot()
    assert root.tag == f"{MVN_NS}mvnx"
    subject = root.find(f"{MVN_NS}subject")
    assert subject.get("frameRate") == "60" and subject.get("segmentCount") == "23"
    frames = [f for f in subject.find(f"{MVN_NS}frames") if f.get("type") == "normal"]
    times = np.array([int(f.get("time")) for f in frames]) / 1000.0
    orient = np.array(frames[0].find(f"{MVN_NS}orientation").text.split(), float)
    assert orient.shape == (23 * 4,)
    assert np.allclose(np.diff(times), 1 / 60, atol=1.01e-3)
    imu = info["imu"]
    assert imu["clock_offset_s"] == pytest.approx(-0.7)
    assert imu["drift_ppm"] == pytest.approx(150.0)
    # the IMU starts 0.7 s after the Kinects (offset −0.7 s on its own clock) and then runs
    # over the rest of the session: its span is what the clock model says
    # the suit sees the motion from the first Kinect frame to 0.5 s past the last
    kinect_end = info["motion"]["kinect_time_of_first_frame_s"] + CFG.duration + 0.5
    span = (1 + 150e-6) * kinect_end - 0.7
    assert abs(times[-1] - span) < 2 / 60


def test_xbus_checksums_hold_except_where_corrupted(session):
    out, info = session
    parser = XbusParser()
    samples = parser.feed((out / "imu" / "xbus.bin").read_bytes()) + parser.flush()
    stats = parser.stats
    damaged, dropped = info["imu"]["xbus_damaged"], info["imu"]["xbus_dropped"]
    assert stats.checksum_errors + stats.truncated + stats.malformed == damaged
    assert len(samples) == info["imu"]["xbus_messages"] - damaged - dropped
    device_map = read_device_map(out / "imu" / "device_map.json")
    assert len(device_map) == 17
    assert {s.device_id for s in samples} == set(device_map)


def test_ground_truth_and_chair_scan_agree(session):
    out, info = session
    truth = read_processed(out / "ground_truth.h5")
    assert truth.num_frames == round(CFG.duration * CFG.fps)
    v, _f = load_mesh(out / "chair_scan.obj")
    assert np.allclose(v, truth.object_vertices, atol=1e-5)
    world = apply_transform(np.asarray(info["chair"]["world_from_scan"]), v)
    assert abs(world[:, 1].min()) < 1e-4  # the chair stands on the floor in the world
    assert np.allclose(truth.object_pose, info["chair"]["world_from_scan"])


def test_clothed_surface_is_what_the_cameras_were_shown(recorded):
    """truth_clothing.npz + ground_truth.h5 rebuild the rendered (clothed) person exactly."""
    out, info, shown = recorded
    truth = read_processed(out / "ground_truth.h5")
    assert len(shown) == truth.num_frames  # mkv: every frame is built, dropped or not
    frames = [0, 3, truth.num_frames - 1]
    clothed = clothed_surface(out, frames)
    assert clothed.shape == (len(frames), *shown[0].shape)
    err = np.abs(clothed - np.stack([shown[k] for k in frames])).max()
    assert err < 1e-6, f"clothed surface off the rendered one by {err * 1e3:.4f} mm"
    assert np.allclose(clothed_surface(out)[frames], clothed, atol=1e-6)  # any chunking
    clothing, model = load_clothing(out / CLOTHING_FILE)
    assert model == CFG.model
    assert clothing.hand_scale == pytest.approx(info["clothing"]["hand_scale"])
    # the clothing is a real layer: up to ~3 cm off the body where loose, none on the face
    body = body_vertices(
        load_body_model(model), truth.betas,
        {"global_orient": truth.global_orient, "body_pose": truth.body_pose,
         "transl": truth.transl}, np.array(frames))[0]
    gap = np.linalg.norm(clothed - body, axis=-1)
    assert 0.002 < np.median(gap) < 0.02 and 0.02 < gap.max() < 0.06


def test_background_recording_is_the_empty_room(session):
    """background/<serial>.mkv: CFG.background_frames frames per camera, no person, the room as
    the session sees it (most pixels agree with the session's depth to noise)."""
    out, _ = session
    manifest = json.loads((out / "session.json").read_text())
    for dev in manifest["kinect"]:
        bg = list(open_azure_mkv(out / dev["background"]))
        assert len(bg) == CFG.background_frames
        assert all(c.depth_mm.shape == (288, 320) and c.color_jpeg for c in bg)
        first = next(iter(open_azure_mkv(out / dev["file"]))).depth_mm.astype(np.float32)
        b = bg[0].depth_mm.astype(np.float32)
        both = (first > 0) & (b > 0)
        # 30 mm, growing with depth: far floor is seen at grazing angles, where the lateral
        # jitter of the depth edges moves the depth by centimetres (binned range reaches 5.46 m)
        tol = 30.0 + 0.01 * first[both]
        same = np.abs(first - b)[both] < tol  # mm
        assert 0.6 < same.mean() < 0.99  # the person covers a part of the image
        # nothing in the empty room stands in front of what the session saw (but depth-edge
        # jitter and flying pixels)
        assert np.mean(b[both] >= first[both] - tol) > 0.98


def test_contact_sheet_tool(session, tmp_path):
    out, _ = session
    png = tmp_path / "sheet.png"
    assert contact_sheet_main([str(out), "-o", str(png), "--frame", "3"]) == 0
    import cv2

    image = cv2.imread(str(png))
    assert image is not None and image.shape[0] > 4 * 200  # one row per camera
    # colour, depth and IR side by side: 16:9 at 240 px, then two 320x288 images at 240 px
    assert image.shape[1] == round(1280 * 240 / 720) + 2 * (6 + round(320 * 240 / 288))
    assert contact_sheet_main([str(tmp_path / "nothing")]) == 1


@pytest.fixture(scope="module")
def depth_only(session, tmp_path_factory) -> tuple[Path, dict, int]:
    """The same session (same seed) with ``color=False`` and ``ir=False``, and how many colour
    images the simulator rendered for it (a spy on ``render_color``)."""
    out = tmp_path_factory.mktemp("depth_only")
    rendered = 0
    real = recording.render_color

    def spy(*args, **kwargs):
        nonlocal rendered
        rendered += 1
        return real(*args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(recording, "render_color", spy)
        info = simulate_session(out, dataclasses.replace(CFG, color=False, ir=False),
                                progress=False)
    return out, info, rendered


def test_depth_only_session_is_the_colour_session_without_colour_or_ir(session, depth_only):
    """``color=False`` (--no-color): kinect/ and background/ have no COLOR track (as
    ``k4arecorder --color-mode OFF`` writes), their depth and timestamps are exactly the colour
    session's, colour is rendered only for the ChArUco captures, and everything else (the
    IMU, truth) is byte for byte the same; ``ir=False`` (--no-ir) leaves every IR track
    declared and empty, and changes nothing else (the ChArUco captures are the colour
    session's but for their IR)."""
    out, info = session
    out_d, info_d, rendered = depth_only
    assert rendered == CFG.charuco_poses * CFG.cameras  # the calibration captures only
    assert info_d["cameras"] == info["cameras"] and info_d["imu"] == info["imu"]
    assert info_d["config"] == {**info["config"], "color": False, "ir": False}
    # sessions at the defaults keep their truth.json bytes
    assert "color" not in info["config"] and "ir" not in info["config"]
    manifest = json.loads((out / "session.json").read_text())
    for dev in manifest["kinect"]:
        for key in ("file", "background"):
            ours, theirs = open_azure_mkv(out_d / dev[key]), open_azure_mkv(out / dev[key])
            assert sorted(ours.tracks) == ["DEPTH", "IR"] and ours.color_mode == "OFF"
            assert "K4A_COLOR_MODE" not in ours.tags and "COLOR" in theirs.tracks
            with av.open(str(out_d / dev[key])) as c:  # an independent reader agrees
                assert [s.metadata.get("title") for s in c.streams.video] == ["DEPTH", "IR"]
            a, b = list(ours), list(theirs)
            assert len(a) == len(b) > 0
            for x, y in zip(a, b, strict=True):
                assert x.color_jpeg is None and x.timestamp_us == y.timestamp_us
                assert x.ir is None and y.ir is not None
                np.testing.assert_array_equal(x.depth_mm, y.depth_mm)
        # the ChArUco captures keep colour: the same images, IR apart
        cal = dev["calibration_capture"]
        a, b = list(open_azure_mkv(out_d / cal)), list(open_azure_mkv(out / cal))
        assert len(a) == len(b) == CFG.charuco_poses
        for x, y in zip(a, b, strict=True):
            assert x.color_jpeg == y.color_jpeg and x.timestamp_us == y.timestamp_us
            np.testing.assert_array_equal(x.depth_mm, y.depth_mm)
            assert x.ir is None and y.ir is not None
    for name in ("session.json", "imu/recording.mvnx", "imu/xbus.bin", CLOTHING_FILE):
        assert (out_d / name).read_bytes() == (out / name).read_bytes(), name
    truth, truth_d = read_processed(out / "ground_truth.h5"), read_processed(
        out_d / "ground_truth.h5")
    np.testing.assert_array_equal(truth_d.joints, truth.joints)
    np.testing.assert_array_equal(truth_d.time, truth.time)


def test_depth_only_contact_sheet_says_so(depth_only, tmp_path):
    out, _, _ = depth_only
    png = tmp_path / "sheet.png"
    assert contact_sheet_main([str(out), "-o", str(png), "--frame", "3"]) == 0
    import cv2

    image = cv2.imread(str(png))
    assert image is not None and image.shape[0] > 4 * 200
    # the placeholder (as wide as the depth image) and depth: no IR panel without IR frames
    assert image.shape[1] == 2 * round(320 * 240 / 288) + 6


def test_oracle_session_is_the_same_session_without_clothes_or_suit_calibration_error(
        depth_only, tmp_path):
    """``clothing=False, imu_misalignment=0`` (--no-clothing --imu-misalignment 0): the same
    draws as the session with clothes and a miscalibrated suit (motion, cameras, IMU noise,
    the background), the cameras shown the bare body and the suit without its per-segment
    calibration error; truth.json records both, the defaults' records stay as they were."""
    out_d, info_d, _ = depth_only
    cfg = dataclasses.replace(CFG, color=False, ir=False, clothing=False,
                              imu_misalignment=0.0)
    info = simulate_session(tmp_path, cfg, progress=False)
    assert info["config"] == {**info_d["config"], "clothing": False, "imu_misalignment": 0.0}
    assert "clothing" not in info_d["config"] and "imu_misalignment" not in info_d["config"]
    assert info["cameras"] == info_d["cameras"]
    errors, errors_d = info["imu"]["errors"], info_d["imu"]["errors"]
    assert errors_d["misalignment_deg"] > 0 and errors["misalignment_deg"] == 0
    assert {k: v for k, v in errors.items() if k != "misalignment_deg"} == {
        k: v for k, v in errors_d.items() if k != "misalignment_deg"}
    truth, truth_d = (read_processed(p / "ground_truth.h5") for p in (tmp_path, out_d))
    np.testing.assert_array_equal(truth.joints, truth_d.joints)
    clothing, _ = load_clothing(tmp_path / CLOTHING_FILE)
    assert not clothing.rest_offset.any() and not clothing.fold_amp.any()
    assert clothing.hand_scale == clothing.foot_scale == 1.0
    frames = [0, truth.num_frames - 1]
    body = body_vertices(
        load_body_model(cfg.model), truth.betas,
        {"global_orient": truth.global_orient, "body_pose": truth.body_pose,
         "transl": truth.transl}, np.array(frames))[0]
    np.testing.assert_allclose(clothed_surface(tmp_path, frames), body, atol=1e-9)
    mvnx, mvnx_d = ((p / "imu/recording.mvnx").read_bytes() for p in (tmp_path, out_d))
    assert mvnx != mvnx_d  # the suit reports other segment orientations
    manifest = json.loads((out_d / "session.json").read_text())
    dev = manifest["kinect"][0]
    empty, empty_d = (open_azure_mkv(p / dev["background"]) for p in (tmp_path, out_d))
    for x, y in zip(list(empty), list(empty_d), strict=True):  # nobody there: the same room
        np.testing.assert_array_equal(x.depth_mm, y.depth_mm)


def test_no_color_needs_mkv_without_masks(tmp_path, capsys):
    from couch.tools.sim.session import main

    with pytest.raises(ValueError, match="--no-color needs --format mkv"):
        simulate_session(tmp_path, SessionConfig(color=False, fmt="frames"), progress=False)
    assert main([str(tmp_path / "s"), "--no-color", "--masks", "--quiet"]) == 1
    assert "need colour" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "sessions" / "sim_fixture"


def test_committed_fixture_session_is_complete_and_readable():
    """The bundled session (`make fixtures` regenerates it) opens with the readers."""
    from couch.capture.mvnx import read_mvnx

    manifest = json.loads((FIXTURE / "session.json").read_text())
    truth = read_processed(FIXTURE / "ground_truth.h5")
    info = json.loads((FIXTURE / "truth.json").read_text())
    assert truth.num_frames == 30 and len(manifest["kinect"]) == 4
    for dev, cam in zip(manifest["kinect"], info["cameras"], strict=True):
        caps = list(open_azure_mkv(FIXTURE / dev["file"]))
        assert len(caps) == truth.num_frames - len(cam["dropped_frames"])
        assert all(c.depth_mm.shape == (288, 320) for c in caps)
        masks = sorted((FIXTURE / "masks" / dev["serial"]).glob("*.png"))
        assert len(masks) == len(caps)
    rec = read_mvnx(FIXTURE / manifest["imu"]["mvnx"])
    assert rec.orientation.shape[1:] == (23, 4) and rec.frame_rate == 60


def test_frames_format_writes_a_behave_sequence(tmp_path):
    """--format frames: BEHAVE-style folders (1 s, 2 cameras, 5 fps, 20% drops, seed 5)."""
    import cv2

    from couch.capture.behave import open_behave_sequence

    cfg = SessionConfig(duration=1.0, fps=5.0, cameras=2, fmt="frames", drop_rate=0.2,
                        charuco_poses=1, seed=5)
    info = simulate_session(tmp_path, cfg, progress=False)
    manifest = json.loads((tmp_path / "session.json").read_text())
    seq = open_behave_sequence(tmp_path / manifest["behave_sequence"])
    truth = read_processed(tmp_path / "ground_truth.h5")
    dropped = set(info["frames_not_written"])
    assert len(seq.frame_times) == truth.num_frames - len(dropped)
    kept_times = [t for k, t in enumerate(truth.time) if k not in dropped]
    assert np.allclose(seq.frame_times, kept_times, atol=1e-3)
    frame = next(iter(seq))
    assert len(frame.images) == 2
    depth = cv2.imread(str(frame.path / "k0.depth.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == (720, 1280)  # registered to colour
    assert (depth > 0).mean() > 0.2 and frame.images[0].person_mask is not None
    for cam, pose in zip(info["cameras"], seq.world_from_color, strict=True):
        assert np.allclose(pose, cam["world_from_color"], atol=1e-6)
