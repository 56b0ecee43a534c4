"""capture/session.py: the one reader of a session folder's layout."""

from __future__ import annotations

import json

import pytest

from couch.capture.session import SessionLayoutError, session_files


def _touch(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    return path


def test_folders_without_a_manifest(tmp_path):
    rec = _touch(tmp_path / "kinect" / "222.mkv")
    cap1 = _touch(tmp_path / "calibration" / "111.mkv")
    cap2 = _touch(tmp_path / "calibration" / "222.mkv")
    bg = _touch(tmp_path / "background" / "222.mkv")
    mvnx = _touch(tmp_path / "imu" / "take.mvnx")
    files = session_files(tmp_path)
    assert files.manifest is None and files.board is None and files.mvnx == mvnx
    assert [c.serial for c in files.cameras] == ["111", "222"]
    one, two = files.cameras
    assert (one.recording, one.calibration_capture, one.background) == (None, cap1, None)
    assert (two.recording, two.calibration_capture, two.background) == (rec, cap2, bg)
    assert files.camera("222") is two and files.camera("333") is None


def test_the_manifest_decides(tmp_path):
    _touch(tmp_path / "background" / "1.mkv")        # named null: not used
    _touch(tmp_path / "background" / "2.mkv")        # not named: found by its place
    _touch(tmp_path / "rooms" / "3.mkv")
    _touch(tmp_path / "imu" / "a.mvnx")
    doc = {"kinect": [
        {"serial": 1, "file": "kinect/1.mkv", "sync": "MASTER", "background": None,
         "calibration_capture": "calibration/1.mkv"},
        {"serial": "2", "file": "kinect/2.mkv"},
        {"serial": "3", "background": "rooms/3.mkv"}],
        "imu": {"mvnx": "imu/a.mvnx"}, "board": {"squares_x": 5}}
    (tmp_path / "session.json").write_text(json.dumps(doc))
    files = session_files(tmp_path)
    assert [c.serial for c in files.cameras] == ["1", "2", "3"]
    c1, c2, c3 = files.cameras
    assert c1.sync == "MASTER" and c1.background is None
    assert c1.calibration_capture == tmp_path / "calibration" / "1.mkv"
    assert c2.background == tmp_path / "background" / "2.mkv" and c2.calibration_capture is None
    assert c3.recording is None and c3.background == tmp_path / "rooms" / "3.mkv"
    assert files.mvnx == tmp_path / "imu" / "a.mvnx" and files.board == {"squares_x": 5}
    # named files come back as named, present or not: the step that reads one reports it
    doc["kinect"][0]["background"] = "gone.mkv"
    (tmp_path / "session.json").write_text(json.dumps(doc))
    assert session_files(tmp_path).cameras[0].background == tmp_path / "gone.mkv"


@pytest.mark.parametrize("doc, error, match", [
    ("{not json", SessionLayoutError, "malformed"),
    ('{"cameras": []}', SessionLayoutError, "malformed"),
    ('{"kinect": [{"file": "kinect/1.mkv"}]}', SessionLayoutError, "serial"),
])
def test_malformed_manifests_name_the_file(tmp_path, doc, error, match):
    (tmp_path / "session.json").write_text(doc)
    with pytest.raises(error, match=match) as info:
        session_files(tmp_path)
    assert str(tmp_path / "session.json") in str(info.value)
