"""capture/frames.py: one streaming interface to an Azure MKV or one camera of a BEHAVE folder.

Bad input through this interface is tested in tests/test_capture_bad_input.py.
"""

from __future__ import annotations

import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from couch.capture.azure_calibration import KinectCalibration
from couch.capture.azure_mkv import AzureMkvWriter, KinectFormatError
from couch.capture.behave import BehaveWriter, FrameImages, frame_name
from couch.capture.frames import KinectFrame, open_kinect_stream
from couch.tools.sim.kinect import place_cameras, random_calibration, world_from_color

N = 4
T0_US = 2_000_000
PERIOD_US = 66_666  # 15 fps
STAMPS = [T0_US + i * PERIOD_US for i in range(N)]


def _color(i: int, h: int = 720, w: int = 1280) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return np.stack([(xx // 4 + 20 * i) % 256, (yy // 4) % 256, np.full_like(xx, 60 * i)],
                    axis=-1).astype(np.uint8)


def _depth(i: int, shape: tuple[int, int]) -> np.ndarray:
    return np.random.default_rng(i).integers(0, 5000, shape, dtype=np.uint16)


@pytest.fixture(scope="module")
def mkv(tmp_path_factory) -> tuple[Path, KinectCalibration]:
    cal = random_calibration(np.random.default_rng(3), serial="000444555612")
    cal = KinectCalibration.from_json(cal.to_json(), "NFOV_2X2BINNED", "720P")
    path = tmp_path_factory.mktemp("frames") / "cam.mkv"
    with AzureMkvWriter(path, cal, fps=15, depth_delay_ns=-3000) as w:
        for i, ts in enumerate(STAMPS):
            jpg = cv2.imencode(".jpg", _color(i)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])[1]
            w.write(ts, jpg.tobytes(), _depth(i, (288, 320)), _depth(i + 10, (288, 320)))
    return path, cal


def test_mkv_stream(mkv):
    path, cal = mkv
    stream = open_kinect_stream(path)
    assert (stream.kind, stream.serial, stream.fps, stream.depth_grid) == \
        ("mkv", "000444555612", 15.0, "depth")
    assert stream.calibration == cal and stream.kinect is None
    assert "serial='000444555612'" in repr(stream)
    it = iter(stream)
    assert isinstance(it, types.GeneratorType)  # streamed, not a list
    frames = list(it)
    assert [f.index for f in frames] == list(range(N))
    assert [f.timestamp_us for f in frames] == STAMPS
    assert [f.color_timestamp_us for f in frames] == [t + 3 for t in STAMPS]  # depth 3 µs first
    for i, f in enumerate(frames):
        assert isinstance(f, KinectFrame) and f.depth_grid == "depth"
        np.testing.assert_array_equal(f.depth_mm, _depth(i, (288, 320)))
        np.testing.assert_array_equal(f.ir, _depth(i + 10, (288, 320)))
        assert f.color_data[:2] == b"\xff\xd8" and str(path) in f.source
        rgb = f.color_rgb()
        assert rgb.shape == (720, 1280, 3) and rgb.dtype == np.uint8
        assert np.abs(rgb.astype(int) - _color(i)).mean() < 3  # RGB, not BGR
        assert f.color_rgb() is rgb  # decoded once
    assert stream.skipped == [] and stream.warnings == []
    assert len(list(stream)) == N  # iterable again


def test_mkv_camera_selection(mkv):
    path, _ = mkv
    assert open_kinect_stream(path, serial="000444555612").serial == "000444555612"
    with pytest.raises(KinectFormatError, match="camera 000444555612, not of camera 123"):
        open_kinect_stream(path, serial="123")
    with pytest.raises(ValueError, match="BEHAVE"):
        open_kinect_stream(path, kinect=0)


def test_frame_without_colour():
    f = KinectFrame(index=0, timestamp_us=0, depth_mm=None, source="cam.mkv capture 0")
    assert not f.has_color and f.color_rgb() is None and f.color_error is None
    with pytest.raises(KinectFormatError, match=r"cam\.mkv capture 0: no colour image"):
        f.require_color()


def test_depth_only_mkv_stream(mkv, tmp_path):
    """A recording without a COLOR track (k4arecorder --color-mode OFF): depth as usual, no
    colour on any frame, nothing counted as skipped, and a clear error where colour is
    required."""
    _, cal = mkv
    path = tmp_path / "depth_only.mkv"
    with AzureMkvWriter(path, cal, fps=15, color=False) as w:
        for i, ts in enumerate(STAMPS):
            w.write(ts, depth_mm=_depth(i, (288, 320)))
    stream = open_kinect_stream(path)
    assert not stream.has_color and stream.reader.color_mode == "OFF"
    assert stream.calibration.depth == cal.depth  # the depth camera is all there is to use
    frames = list(stream)
    assert [f.timestamp_us for f in frames] == STAMPS
    for i, f in enumerate(frames):
        np.testing.assert_array_equal(f.depth_mm, _depth(i, (288, 320)))
        assert not f.has_color and f.color_rgb() is None and f.color_error is None
    assert stream.skipped == [] and stream.warnings == []
    with pytest.raises(KinectFormatError, match=r"depth_only\.mkv capture 0: .*no COLOR track"):
        frames[0].require_color()
    # with colour, require_color is color_rgb
    first = next(iter(open_kinect_stream(mkv[0])))
    assert open_kinect_stream(mkv[0]).has_color and first.require_color() is first.color_rgb()


@pytest.fixture(scope="module")
def behave(tmp_path_factory) -> tuple[Path, list[KinectCalibration]]:
    rng = np.random.default_rng(6)
    cams = place_cameras(rng, 2)
    calibs = [c for c, _ in cams]
    poses = np.stack([world_from_color(c, p) for c, p in cams])
    root = tmp_path_factory.mktemp("behave")
    w = BehaveWriter(root, "Date01_Sub01_chairwood_sit", "Date01", calibs, poses,
                     gender="male", object_category="chairwood", pointcloud_tables=False)
    for i in range(3):
        w.write_frame(1.0 + i / 30, [FrameImages(_color(i + k), _depth(i + k, (720, 1280)))
                                     for k in range(2)])
    seq = root / "Date01_Sub01_chairwood_sit"
    # BEHAVE also allows PNG colour (KinectFrameReader: k{k}.color.{jpg,png})
    folder = seq / frame_name(1.0 + 2 / 30)
    (folder / "k1.color.jpg").unlink()
    cv2.imwrite(str(folder / "k1.color.png"), _color(3)[..., ::-1])
    return seq, calibs


def test_behave_stream(behave):
    seq, calibs = behave
    for k in (0, 1):
        by_id = open_kinect_stream(seq, kinect=k)
        by_serial = open_kinect_stream(seq, serial=calibs[k].serial)
        assert by_id.kinect == by_serial.kinect == k
        stream = by_id
        assert (stream.kind, stream.serial, stream.fps, stream.depth_grid) == \
            ("behave", calibs[k].serial, 30.0, "color")
        assert stream.calibration == calibs[k]
        frames = list(stream)
        assert [f.index for f in frames] == [0, 1, 2]
        assert [f.timestamp_us for f in frames] == [1_000_000, 1_033_000, 1_067_000]
        for i, f in enumerate(frames):
            assert f.ir is None and f.depth_grid == "color"
            np.testing.assert_array_equal(f.depth_mm, _depth(i + k, (720, 1280)))
            want = _color(3 if (k, i) == (1, 2) else i + k)
            assert np.abs(f.color_rgb().astype(int) - want).mean() < 3
        assert stream.skipped == [] and stream.warnings == []


def test_behave_frame_rate_from_spacing(tmp_path):
    cams = place_cameras(np.random.default_rng(1), 1)
    calibs = [cams[0][0]]
    poses = world_from_color(*cams[0])[None]
    w = BehaveWriter(tmp_path, "seq", "Date01", calibs, poses, gender="male",
                     object_category="chair", pointcloud_tables=False)
    images = [FrameImages(_color(0), _depth(0, (720, 1280)))]
    w.write_frame(3.0, images)
    one = open_kinect_stream(tmp_path / "seq")
    assert one.fps == 30.0 and "fewer than two frames" in one.warnings[0]
    for t in (4.0, 5.0):  # the BEHAVE release's 1 fps keyframes
        w.write_frame(t, images)
    assert open_kinect_stream(tmp_path / "seq").fps == 1.0
