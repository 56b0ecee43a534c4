"""Multi-camera extrinsic calibration (capture/calibration.py) on simulated sessions.

Simulator settings (sessions generated once per module): 4 cameras, seeds 16 and 5,
1 s at 5 fps, NFOV_2X2BINNED depth, default noise (1.0: colour blur 0.6 px, sensor
noise, JPEG quality 90; depth noise with per-device biases), 720P colour.

The board captures are the simulator's own ``calibration/<serial>.mkv``: each board pose is held
between two neighbouring cameras, whole in both views (10 and 6 poses), so every pair of
neighbours shares views.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from couch.capture.calibration import (
    BoardView,
    CalibrationError,
    Extrinsics,
    calibrate_extrinsics,
    calibrate_session,
    detect_boards,
    level_with_floor,
    read_extrinsics,
    write_extrinsics,
)
from couch.capture.charuco import BoardSpec
from couch.capture.cli import calibrate_main
from couch.geometry import invert_transform, transform_distance
from couch.tools.sim.session import SessionConfig, simulate_session

SESSIONS = {
    "seed16": (SessionConfig(duration=1.0, fps=5.0, cameras=4, depth_mode="NFOV_2X2BINNED",
                             charuco_poses=10, seed=16), 10),
    "seed5": (SessionConfig(duration=1.0, fps=5.0, cameras=4, depth_mode="NFOV_2X2BINNED",
                            charuco_poses=6, seed=5), 6),
}
# The capture issue's requirement on relative camera poses.
MAX_REL_MM, MAX_REL_DEG = 2.0, 0.1


@pytest.fixture(scope="module", params=list(SESSIONS))
def calibrated(request, tmp_path_factory) -> dict:
    cfg, _ = SESSIONS[request.param]
    root = tmp_path_factory.mktemp(request.param)
    truth = simulate_session(root, cfg, progress=False)
    serials = [c["serial"] for c in truth["cameras"]]
    obs = detect_boards({s: root / "calibration" / f"{s}.mkv" for s in serials},
                        BoardSpec())
    rig = calibrate_extrinsics(obs)
    ext = level_with_floor(rig, {s: root / "kinect" / f"{s}.mkv" for s in serials})
    return {"root": root, "truth": truth, "obs": obs, "rig": rig, "ext": ext,
            "serials": serials}


def _true(truth: dict, key: str) -> dict[str, np.ndarray]:
    return {c["serial"]: np.array(c[key]) for c in truth["cameras"]}


def _relative_errors(ext: Extrinsics, truth: dict) -> dict[tuple[str, str], tuple[float, float]]:
    """(i, j) -> (deg, mm) error of depth camera i's pose relative to depth camera j."""
    t = _true(truth, "world_from_depth")
    out = {}
    for i in ext.cameras:
        for j in ext.cameras:
            if i == j:
                continue
            ours = invert_transform(ext.world_from_depth(j)) @ ext.world_from_depth(i)
            theirs = invert_transform(t[j]) @ t[i]
            ang, dist = transform_distance(ours, theirs)
            out[(i, j)] = (float(np.degrees(ang)), float(dist * 1000))
    return out


def test_every_camera_sees_the_board_and_the_fit_reprojects_well(calibrated):
    obs, ext = calibrated["obs"], calibrated["ext"]
    seen = obs.frames_seen()
    assert all(seen[s] >= 2 for s in calibrated["serials"]), seen
    for s, cam in ext.cameras.items():
        assert cam.frames_seen == seen[s] and 2 <= cam.frames_used <= seen[s]
        # saddle-refined corners of the simulated 720p images: ~0.03 px rms at the true poses
        assert cam.reprojection_mean_px < 0.1, (s, cam.reprojection_mean_px)
        assert cam.reprojection_max_px < 1.5, (s, cam.reprojection_max_px)
    print({s: (round(c.reprojection_mean_px, 3), round(c.reprojection_max_px, 3))
           for s, c in ext.cameras.items()})


def test_relative_poses_meet_the_requirement(calibrated):
    """Every camera's pose relative to every other within 2 mm and 0.1 deg of the truth."""
    errs = _relative_errors(calibrated["ext"], calibrated["truth"])
    print({f"{i}->{j}": (round(a, 4), round(d, 2)) for (i, j), (a, d) in errs.items()})
    assert max(a for a, _ in errs.values()) <= MAX_REL_DEG
    assert max(d for _, d in errs.values()) <= MAX_REL_MM


def test_depth_and_colour_poses_follow_color_from_depth(calibrated):
    ext, obs = calibrated["ext"], calibrated["obs"]
    for s, cam in ext.cameras.items():
        expect = cam.world_from_color @ obs.calibrations[s].color_from_depth
        assert np.allclose(cam.world_from_depth, expect, atol=1e-12)
    # before levelling, the reference colour camera is the frame
    rig = calibrated["rig"]
    assert np.allclose(rig.world_from_color(rig.reference), np.eye(4))
    assert np.allclose(ext.world_from_reference, ext.world_from_color(ext.reference))


def test_floor_is_y0_and_plus_y_is_up(calibrated):
    ext, truth = calibrated["ext"], calibrated["truth"]
    t = _true(truth, "world_from_depth")
    for s, pose in t.items():
        ours = ext.world_from_depth(s)
        # camera heights above the floor agree (the floor is at y = 0 in both worlds)
        assert abs(ours[1, 3] - pose[1, 3]) < 0.005, (s, ours[1, 3], pose[1, 3])
        # world up seen from each camera agrees
        up_ours, up_true = ours[1, :3], pose[1, :3]
        angle = np.degrees(np.arccos(np.clip(up_ours @ up_true, -1.0, 1.0)))
        assert angle < 0.2, (s, angle)
    # heading convention: the reference colour camera looks along +Z (projected), origin on
    # the floor below where the cameras look
    ref = ext.world_from_color(ext.reference)
    assert ref[0, 2] == pytest.approx(0.0, abs=1e-9) and ref[2, 2] > 0
    assert ext.floor is not None and ext.floor.rms_m < 0.01


def test_levelling_gives_the_same_world_with_the_cores_busy(calibrated):
    """open3d's plane RANSAC stops its threads on whichever plane is good enough first: with the
    cores busy that varied from run to run (2 of 12 runs chose another floor). The floor fit is
    repeatable to the bit, and open3d's thread limit is left as it was."""
    import threading

    import open3d as o3d

    root, serials = calibrated["root"], calibrated["serials"]
    paths = {s: root / "kinect" / f"{s}.mkv" for s in serials}
    limit = o3d.utility.get_max_threads()
    stop = threading.Event()

    def busy() -> None:  # numpy releases the GIL: this loads the cores beside open3d
        a = np.random.default_rng(0).random((400, 400))
        while not stop.is_set():
            a = np.tanh(a @ a)

    hogs = [threading.Thread(target=busy) for _ in range(2)]
    for h in hogs:
        h.start()
    try:
        worlds = [level_with_floor(calibrated["rig"], paths) for _ in range(6)]
    finally:
        stop.set()
        for h in hogs:
            h.join()
    first = worlds[0]
    for w in worlds[1:]:
        assert np.array_equal(w.floor.plane, first.floor.plane)
        for s in serials:
            assert np.array_equal(w.world_from_depth(s), first.world_from_depth(s))
    assert o3d.utility.get_max_threads() == limit


def test_extrinsics_file_round_trip_and_given_extrinsics(calibrated, tmp_path):
    ext, root = calibrated["ext"], calibrated["root"]
    path = tmp_path / "extrinsics.json"
    write_extrinsics(path, ext)
    doc = json.loads(path.read_text())
    assert set(doc["cameras"]) == set(ext.cameras) and doc["method"]["world"]
    back = read_extrinsics(path)
    assert back.reference == ext.reference and back.serials == ext.serials
    for s in ext.cameras:
        assert np.allclose(back.world_from_depth(s), ext.world_from_depth(s), atol=1e-12)
        assert np.allclose(back.world_from_color(s), ext.world_from_color(s), atol=1e-12)
        assert back.cameras[s].reprojection_mean_px == ext.cameras[s].reprojection_mean_px
    assert np.allclose(back.floor.plane, ext.floor.plane)
    # later stages skip calibration with given extrinsics (and may write them elsewhere)
    copy = tmp_path / "copy" / "extrinsics.json"
    given = calibrate_session(root, given=path, output=copy)
    assert given.serials == ext.serials and copy.is_file()
    # given extrinsics that lack one of the session's cameras are refused
    doc["cameras"].pop(ext.serials[-1])
    path.write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match=ext.serials[-1]):
        calibrate_session(root, given=path)


def test_a_camera_that_never_sees_the_board(calibrated):
    root, serials = calibrated["root"], calibrated["serials"]
    paths = {s: root / "calibration" / f"{s}.mkv" for s in serials}
    # the session recording shows the person and the chair, never the board
    paths[serials[1]] = root / "kinect" / f"{serials[1]}.mkv"
    obs = detect_boards(paths, BoardSpec())
    assert obs.frames_seen()[serials[1]] == 0 and obs.frames_total[serials[1]] >= 1
    with pytest.raises(CalibrationError, match=f"never saw the board.*{serials[1]}"):
        calibrate_extrinsics(obs)


def test_a_disconnected_camera_graph(calibrated):
    obs, serials = calibrated["obs"], calibrated["serials"]
    # the last camera's frames are renumbered so they never coincide with the others'
    views = [dataclasses.replace(v, frame=v.frame + 1000) if v.serial == serials[-1] else v
             for v in obs.views]
    cut = dataclasses.replace(obs, views=views)
    with pytest.raises(CalibrationError, match="disconnected") as info:
        calibrate_extrinsics(cut)
    assert serials[-1] in str(info.value) and serials[0] in str(info.value)


@pytest.mark.parametrize("content, match", [
    ("{not json", "not valid JSON"),
    ("[1, 2]", "JSON object"),
    ('{"cameras": {}}', "non-empty"),
    ('{"cameras": {"123": {"world_from_color": [[1, 0, 0, 0]]}}}', "world_from_depth"),
    ('{"cameras": {"123": {"world_from_depth": [[1, 0], [0, 1]], "world_from_color": 1}}}',
     "4x4"),
    ('{"cameras": {"123": {"world_from_depth": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], '
     '[0, 0, 0, 1]], "world_from_color": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], '
     '[0, 0, 0, 1]]}}}', "not a rigid transform"),
])
def test_malformed_extrinsics_files(tmp_path, content, match):
    path = tmp_path / "extrinsics.json"
    path.write_text(content)
    with pytest.raises(CalibrationError, match=match) as info:
        read_extrinsics(path)
    assert str(path) in str(info.value)


def test_board_views_keep_corners_without_a_pose():
    view = BoardView("1", 0, np.array([1, 2, 3], np.int32), np.zeros((3, 2)), None)
    assert view.camera_from_board is None and len(view.ids) == 3


def test_calibrate_cli(calibrated, tmp_path, capsys):
    root, ext = calibrated["root"], calibrated["ext"]
    out = tmp_path / "extrinsics.json"
    assert calibrate_main([str(root), "--out", str(out)]) == 0
    report = capsys.readouterr().out
    assert all(s in report for s in ext.serials) and "(reference)" in report
    assert "floor: plane fit rms" in report and f"wrote {out}" in report
    written = read_extrinsics(out)
    for s in ext.serials:
        # the same calibration again (the floor's RANSAC is seeded, but open3d may run it on
        # several threads: up to ~1e-5 apart, i.e. 0.001 deg and 0.01 mm)
        assert np.allclose(written.world_from_depth(s), ext.world_from_depth(s), atol=1e-4)
    # given extrinsics lacking a camera, and a folder that is not there: exit 1, a message
    doc = json.loads(out.read_text())
    doc["cameras"].pop(ext.serials[0])
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    assert calibrate_main([str(root), "--given", str(bad), "--out", str(tmp_path / "x")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("couch-calibrate: ") and ext.serials[0] in err and str(bad) in err
    assert calibrate_main([str(tmp_path / "missing")]) == 1
    assert "is not a folder" in capsys.readouterr().err
