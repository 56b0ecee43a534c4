"""Bad input to the capture stage: a clear error naming the file and what was wrong, or a counted
skip with the rest delivered — never a crash.

Covered here, through :func:`couch.capture.frames.open_kinect_stream` and the public consumers
(:func:`couch.capture.segmentation.segment_recording` / ``background_from_recordings``,
:func:`couch.capture.calibration.detect_boards`, :func:`couch.capture.imu.mvnx_to_smpl`):

* Azure MKV: a colour frame whose JPEG does not decode or is cut off; a depth block of the wrong
  size; the file cut at many offsets (inside the header -> :class:`KinectFormatError` naming the
  file; inside the clusters -> the frames before the cut, the cut reported); the calibration
  attachment missing; not an MKV at all.
* BEHAVE folder: a corrupt or truncated colour JPEG, a missing or corrupt depth PNG, both missing,
  strict mode, an inconsistent (wrong-size) depth image, missing calibration, camera selection.
* MVNX cut mid-file -> ``mvnx_to_smpl`` converts the frames before the cut and keeps the note; an
  unreadable XML encoding declaration (was a ``LookupError`` crash).
* Xbus: a long random serial dump with real messages spliced in; random bytes as a device map.

Already covered elsewhere (not repeated): the MKV readers' own skips and errors at the reader
level (tests/test_azure_mkv.py: not Matroska, one header cut and one cluster cut, CRC-32 damage,
garbage resync, FourCC, invalid calibration JSON), BEHAVE whole-frame skips and metadata errors
(tests/test_behave.py), MVNX truncation/malformed XML at the reader (tests/test_mvnx.py), and
arbitrary bytes / chunking / garbage between messages for the Xbus parser (tests/test_xbus.py).

Recordings are small (depth NFOV_2X2BINNED 320x288, colour 720P, six frames) so the file runs in
seconds.
"""

from __future__ import annotations

import re
import shutil
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_azure_mkv import _ebml  # the MKV tests' independent EBML walker

from couch.capture.azure_calibration import KinectCalibration
from couch.capture.azure_mkv import AzureMkvWriter, KinectFormatError
from couch.capture.behave import BehaveWriter, FrameImages
from couch.capture.calibration import detect_boards
from couch.capture.charuco import BoardSpec
from couch.capture.frames import open_kinect_stream
from couch.capture.imu import mvnx_to_smpl
from couch.capture.mvnx import (
    MVN_SEGMENTS,
    MVN_SENSORS,
    MvnxError,
    MvnxPose,
    MvnxRecording,
    mvn_timecode,
    read_mvnx,
    write_mvnx,
)
from couch.capture.segmentation import (
    SegmentationError,
    background_from_recordings,
    segment_recording,
)
from couch.capture.xbus import (
    XbusError,
    XbusSample,
    encode_mtdata2,
    parse_stream,
    read_device_map,
)
from couch.tools.sim.kinect import place_cameras, random_calibration, world_from_color

N = 6
T0_US = 5_000_000
PERIOD_US = 33_333
SERIAL = "000222333412"
# depth camera 1.5 m above the floor looking along world -Z (camera +Y down = world -Y)
WORLD_FROM_DEPTH = np.array([[1.0, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, -1, 0], [0, 0, 0, 1]])

SIMPLE_BLOCK, CLUSTER, CRC32 = 0xA3, 0x1F43B675, 0xBF


# ------------------------------------------------------------------ data
def _color(i: int) -> np.ndarray:
    yy, xx = np.mgrid[0:720, 0:1280]
    return np.stack([(xx // 5 + 9 * i) % 256, (yy // 3) % 256, ((xx + yy) // 7) % 256],
                    axis=-1).astype(np.uint8)


def _jpeg(i: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", _color(i)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 40])
    assert ok
    return buf.tobytes()


def _undecodable(jpeg: bytes) -> bytes:
    """SOI, frame header (size) and EOI intact, Huffman table zeroed: no decoder accepts it."""
    bad = bytearray(jpeg)
    k = bad.index(b"\xff\xc4")
    bad[k + 4:k + 40] = bytes(36)
    return bytes(bad)


def _depth(i: int, shape: tuple[int, int]) -> np.ndarray:
    rng = np.random.default_rng(i)
    d = (3000 + rng.integers(-5, 6, shape)).astype(np.uint16)  # a wall at 3 m
    h, w = shape
    d[h // 3:2 * h // 3, w // 8 + 10 * i:w // 3 + 10 * i] = 2000  # something moving in front
    return d


@pytest.fixture(scope="module")
def calibration() -> KinectCalibration:
    cal = random_calibration(np.random.default_rng(21), serial=SERIAL)
    return KinectCalibration.from_json(cal.to_json(), "NFOV_2X2BINNED", "720P")


@pytest.fixture(scope="module")
def jpegs() -> list[bytes]:
    return [_jpeg(i) for i in range(N)]


@pytest.fixture(scope="module")
def depths() -> list[np.ndarray]:
    return [_depth(i, (288, 320)) for i in range(N)]


STAMPS = [T0_US + i * PERIOD_US for i in range(N)]


def _write_mkv(path: Path, calibration, jpegs, depths) -> Path:
    with AzureMkvWriter(path, calibration, uid_seed=1) as w:
        for ts, jpg, depth in zip(STAMPS, jpegs, depths, strict=True):
            w.write(ts, jpg, depth, depth // 2)
    return path


@pytest.fixture(scope="module")
def good_mkv(tmp_path_factory, calibration, jpegs, depths) -> Path:
    return _write_mkv(tmp_path_factory.mktemp("mkv") / "cam.mkv", calibration, jpegs, depths)




def _layout(buf: bytes) -> dict[str, tuple[int, int, int, int]]:
    """Top-level elements of the Segment by name (first of each), plus clusters as C0, C1..."""
    head = next(_ebml(buf, 0, 64))
    seg = next(_ebml(buf, head[3], len(buf)))
    names = {0x114D9B74: "SeekHead", 0x1549A966: "Info", 0x1654AE6B: "Tracks",
             0x1941A469: "Attachments", 0x1254C367: "Tags", 0x1C53BB6B: "Cues"}
    out = {"EBML": head, "Segment": seg}
    clusters = 0
    for e in _ebml(buf, seg[2], seg[3]):
        if e[0] == CLUSTER:
            out[f"C{clusters}"] = e
            clusters += 1
        elif e[0] in names:
            out.setdefault(names[e[0]], e)
    return out


def _blocks(buf: bytes, cluster: tuple[int, int, int, int]) -> list[tuple[int, int, int]]:
    """(header start, data start, data end) of the SimpleBlocks of a cluster (tracks 1, 2, 3 =
    COLOR, DEPTH, IR)."""
    return [(s, a, b) for eid, s, a, b in _ebml(buf, cluster[2], cluster[3])
            if eid == SIMPLE_BLOCK]


def _fix_crc(buf: bytearray, cluster: tuple[int, int, int, int]) -> None:
    crc_id, _, x, y = next(_ebml(bytes(buf), cluster[2], cluster[3]))
    assert crc_id == CRC32
    buf[x:y] = zlib.crc32(bytes(buf[y:cluster[3]])).to_bytes(4, "little")


def _named(exc: pytest.ExceptionInfo, path: Path) -> str:
    msg = str(exc.value)
    assert str(path) in msg, f"error does not name {path}: {msg}"
    return msg


# ------------------------------------------------------------------ MKV: colour
@pytest.fixture(scope="module")
def bad_jpeg_mkv(tmp_path_factory, calibration, jpegs, depths) -> Path:
    """Capture 2's JPEG does not decode, capture 4's is cut off (no EOI)."""
    bad = list(jpegs)
    bad[2] = _undecodable(jpegs[2])
    bad[4] = jpegs[4][: len(jpegs[4]) // 2]
    return _write_mkv(tmp_path_factory.mktemp("badjpeg") / "cam.mkv", calibration, bad, depths)


def test_corrupt_jpeg_in_mkv_is_a_counted_colour_skip(bad_jpeg_mkv, depths):
    stream = open_kinect_stream(bad_jpeg_mkv)
    frames = list(stream)
    assert [f.index for f in frames] == list(range(N))  # every capture still delivered
    assert [f.timestamp_us for f in frames] == STAMPS
    for f, depth in zip(frames, depths, strict=True):
        np.testing.assert_array_equal(f.depth_mm, depth)
        assert f.has_color
    assert stream.skipped == []  # colour is decoded lazily: nothing counted yet
    rgbs = [f.color_rgb() for f in frames]
    assert [r is None for r in rgbs] == [i in (2, 4) for i in range(N)]
    assert all(r.shape == (720, 1280, 3) and r.dtype == np.uint8 for r in rgbs if r is not None)
    assert frames[2].color_rgb() is None  # asking again does not count it twice
    skips = stream.skipped
    assert [(s.index, s.stream, s.timestamp_us) for s in skips] == [
        (2, "COLOR", STAMPS[2]), (4, "COLOR", STAMPS[4])]
    for s in skips:
        assert str(bad_jpeg_mkv) in s.where and str(bad_jpeg_mkv) in s.reason
    assert "could not be decoded" in skips[0].reason and "truncated" in skips[1].reason
    assert frames[2].color_error == skips[0].reason
    assert len(list(stream)) == N and stream.skipped == []  # reset per iteration

    strict = open_kinect_stream(bad_jpeg_mkv, strict=True)
    it = iter(strict)
    for _ in range(2):
        assert next(it).color_rgb() is not None
    with pytest.raises(KinectFormatError, match="could not be decoded") as err:
        next(it).color_rgb()
    assert re.search(rf"{re.escape(str(bad_jpeg_mkv))} capture 2", _named(err, bad_jpeg_mkv))


def test_corrupt_jpeg_in_calibration_capture(bad_jpeg_mkv):
    """detect_boards passes over a colour frame that does not decode and counts it."""
    obs = detect_boards([bad_jpeg_mkv], BoardSpec())
    assert obs.frames_total[SERIAL] == N
    skips = obs.skipped[SERIAL]
    assert [s.index for s in skips] == [2, 4] and all(s.stream == "COLOR" for s in skips)
    assert all(str(bad_jpeg_mkv) in str(s) for s in skips)


# ------------------------------------------------------------------ MKV: depth of the wrong size
@pytest.fixture(scope="module")
def short_depth_mkv(tmp_path_factory, good_mkv) -> Path:
    """Capture 3's DEPTH block 10 bytes short (a Void fills the gap; the cluster stays valid)."""
    buf = bytearray(good_mkv.read_bytes())
    cluster = _layout(bytes(buf))["C3"]
    start, data, end = _blocks(bytes(buf), cluster)[1]
    assert buf[data] == 0x82  # track 2 = DEPTH
    size_len = data - start - 1
    buf[start + 1:data] = ((1 << (7 * size_len)) | (end - data - 10)).to_bytes(size_len, "big")
    buf[end - 10:end] = b"\xec\x88" + bytes(8)
    _fix_crc(buf, cluster)
    path = tmp_path_factory.mktemp("shortdepth") / "cam.mkv"
    path.write_bytes(bytes(buf))
    return path


def test_wrong_size_depth_block_is_skipped_through_the_stream(short_depth_mkv, depths):
    stream = open_kinect_stream(short_depth_mkv)
    frames = list(stream)
    assert [f.index for f in frames] == list(range(N))
    assert frames[3].depth_mm is None and frames[3].ir is not None and frames[3].has_color
    np.testing.assert_array_equal(frames[4].depth_mm, depths[4])
    (skip,) = stream.skipped
    assert (skip.index, skip.stream, skip.timestamp_us) == (3, "DEPTH", STAMPS[3])
    assert "expected 184320 bytes (320x288 uint16), got 184310" in skip.reason
    assert str(short_depth_mkv) in skip.where and "byte" in skip.where
    with pytest.raises(KinectFormatError, match="184310") as err:
        list(open_kinect_stream(short_depth_mkv, strict=True))
    _named(err, short_depth_mkv)


def test_wrong_size_depth_block_is_skipped_by_segmentation(short_depth_mkv):
    seg = segment_recording(short_depth_mkv, WORLD_FROM_DEPTH)
    assert [f.index for f in seg.frames] == [0, 1, 2, 4, 5]
    assert {i for i, _ in seg.skipped} == {3}  # counted, with the reader's reason
    assert any("184310" in reason for _, reason in seg.skipped)
    bg = background_from_recordings([short_depth_mkv])
    assert bg.depth.shape == (288, 320) and bg.frames == N - 1


# ------------------------------------------------------------------ MKV: truncated
def _cut(src: Path, dst: Path, n: int) -> Path:
    dst.write_bytes(src.read_bytes()[:n])
    return dst


def _header_cuts(buf: bytes) -> dict[str, int]:
    lay = _layout(buf)
    return {"inside EBML header": 10, "inside Segment size": lay["Segment"][1] + 6,
            "inside SeekHead": lay["SeekHead"][2] + 5, "inside Info": lay["Info"][2] + 3,
            "inside Tracks": lay["Tracks"][2] + 40,
            "inside calibration attachment": lay["Attachments"][2] + 200,
            "inside Tags": lay["Tags"][2] + 30}


def test_mkv_cut_inside_the_header_is_a_clear_error(tmp_path, good_mkv):
    buf = good_mkv.read_bytes()
    for where, n in _header_cuts(buf).items():
        cut = _cut(good_mkv, tmp_path / f"{where.replace(' ', '_')}.mkv", n)
        with pytest.raises(KinectFormatError, match="truncated") as err:
            open_kinect_stream(cut, require_calibration=False)
        _named(err, cut)
        with pytest.raises(KinectFormatError) as err:  # consumers pass the error on
            segment_recording(cut, WORLD_FROM_DEPTH)
        _named(err, cut)
    cut = _cut(good_mkv, tmp_path / "tags.mkv", _header_cuts(buf)["inside Tags"])
    with pytest.raises(KinectFormatError) as err:
        detect_boards([cut], BoardSpec())
    _named(err, cut)


def test_mkv_cut_inside_the_clusters_delivers_what_came_before(tmp_path, good_mkv, depths):
    buf = good_mkv.read_bytes()
    lay = _layout(buf)
    c3 = lay["C3"]
    color, depth, _ = _blocks(buf, c3)
    cases = {  # cut -> captures fully before it
        "at the first cluster": (lay["C0"][1], 0),
        "inside a cluster header": (c3[1] + 3, 3),
        "inside a colour block": (color[1] + 1000, 3),
        "inside a depth block": (depth[1] + 5000, 3),
        "at a cluster boundary": (lay["C4"][1], 4),
        "inside the cues": (lay["Cues"][2] + 2, N),
    }
    for where, (n, complete) in cases.items():
        cut = _cut(good_mkv, tmp_path / f"{where.replace(' ', '_')}.mkv", n)
        stream = open_kinect_stream(cut)
        frames = list(stream)
        full = [f for f in frames if f.depth_mm is not None and f.has_color]
        assert [f.index for f in full] == list(range(complete)), where
        for f in full:
            np.testing.assert_array_equal(f.depth_mm, depths[f.index])
            assert f.timestamp_us == STAMPS[f.index]
        # a partial capture right at the cut may carry the images that made it
        assert len(frames) <= complete + 1, where
        reports = stream.warnings + [s.reason for s in stream.skipped]
        assert any("truncated" in r or "cut off" in r for r in reports), (where, reports)
        assert any(str(cut) in r for r in stream.warnings), where
        with pytest.raises(KinectFormatError, match=r"truncated|cut off") as err:
            list(open_kinect_stream(cut, strict=True))
        _named(err, cut)


def test_mkv_cut_inside_the_clusters_through_consumers(tmp_path, good_mkv):
    buf = good_mkv.read_bytes()
    lay = _layout(buf)
    _, depth, _ = _blocks(buf, lay["C3"])
    cut = _cut(good_mkv, tmp_path / "mid.mkv", depth[1] + 5000)
    seg = segment_recording(cut, WORLD_FROM_DEPTH)
    assert [f.index for f in seg.frames] == [0, 1, 2]
    assert any("cut off" in reason for _, reason in seg.skipped)  # the cut is reported
    assert background_from_recordings([cut]).frames == 3
    obs = detect_boards([cut], BoardSpec())
    assert obs.frames_total[SERIAL] == 4  # three captures and the colour-only one at the cut
    # no cluster at all: nothing to segment, said clearly
    empty = _cut(good_mkv, tmp_path / "noclusters.mkv", lay["C0"][1])
    with pytest.raises(SegmentationError) as err:
        segment_recording(empty, WORLD_FROM_DEPTH)
    _named(err, empty)


def test_mkv_cut_anywhere_is_an_error_or_a_prefix(tmp_path, good_mkv, depths):
    """A sweep of cuts (every 37 bytes through the header, 40 through the clusters)."""
    buf = good_mkv.read_bytes()
    first_cluster = _layout(buf)["C0"][1]
    offsets = [*range(0, first_cluster + 1, 37),
               *np.linspace(first_cluster, len(buf) - 1, 40).astype(int).tolist()]
    path = tmp_path / "cut.mkv"
    errors = 0
    for n in offsets:
        path.write_bytes(buf[:n])
        try:
            stream = open_kinect_stream(path, require_calibration=False)
        except KinectFormatError as err:
            assert str(path) in str(err), n
            assert n <= first_cluster, n  # only a header cut may refuse the whole file
            errors += 1
            continue
        frames = list(stream)
        assert [f.index for f in frames] == list(range(len(frames))), n
        for f in frames:
            if f.depth_mm is not None:
                np.testing.assert_array_equal(f.depth_mm, depths[f.index])
        assert stream.warnings, n  # the cut is always reported
    assert errors >= len(range(0, first_cluster, 37)) - 1


# ------------------------------------------------------------------ MKV: calibration missing
@pytest.fixture(scope="module")
def no_calibration_mkv(tmp_path_factory, good_mkv) -> Path:
    # Same lengths, so every size field stays valid; nothing names or tags the calibration.
    buf = good_mkv.read_bytes().replace(b"K4A_CALIBRATION_FILE", b"K4A_XALIBRATION_FILE")
    buf = buf.replace(b"calibration.json", b"calibrXtion.json")
    path = tmp_path_factory.mktemp("nocal") / "cam.mkv"
    path.write_bytes(buf)
    return path


def test_missing_calibration_attachment(no_calibration_mkv, depths):
    path = no_calibration_mkv
    with pytest.raises(KinectFormatError, match=r"no calibration\.json attachment") as err:
        open_kinect_stream(path)
    _named(err, path)
    stream = open_kinect_stream(path, require_calibration=False)
    assert stream.serial == SERIAL  # from the recording's tag
    frames = list(stream)
    assert len(frames) == N and frames[0].color_rgb() is not None
    np.testing.assert_array_equal(frames[5].depth_mm, depths[5])
    with pytest.raises(KinectFormatError, match="calibration") as err:
        _ = stream.calibration
    _named(err, path)
    for consumer in (lambda: segment_recording(path, WORLD_FROM_DEPTH),
                     lambda: detect_boards([path], BoardSpec())):
        with pytest.raises(KinectFormatError, match="calibration") as err:
            consumer()
        _named(err, path)


# ------------------------------------------------------------------ not a recording at all
def test_not_a_kinect_recording(tmp_path):
    rng = np.random.default_rng(3)
    cases = {"random.mkv": rng.bytes(5000), "empty.mkv": b"",
             "ebml_only.mkv": bytes.fromhex("1a45dfa3") + rng.bytes(2000)}
    for name, data in cases.items():
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(KinectFormatError) as err:
            open_kinect_stream(p)
        _named(err, p)
    with pytest.raises(KinectFormatError, match="does not exist"):
        open_kinect_stream(tmp_path / "missing.mkv")
    (tmp_path / "folder").mkdir()
    with pytest.raises(KinectFormatError, match=r"without info\.json") as err:
        open_kinect_stream(tmp_path / "folder")
    _named(err, tmp_path / "folder")


# ------------------------------------------------------------------ BEHAVE folders
SEQ = "Date02_Sub02_chairwood_sit"
BEHAVE_TIMES = [2.0 + i / 30 for i in range(4)]


@pytest.fixture(scope="module")
def behave_root(tmp_path_factory) -> Path:
    rng = np.random.default_rng(8)
    cams = place_cameras(rng, 2)
    calibs = [c for c, _ in cams]
    poses = np.stack([world_from_color(c, p) for c, p in cams])
    root = tmp_path_factory.mktemp("behave")
    w = BehaveWriter(root, SEQ, "Date02", calibs, poses, gender="female",
                     object_category="chairwood", pointcloud_tables=False, jpeg_quality=40)
    for i, t in enumerate(BEHAVE_TIMES):
        w.write_frame(t, [FrameImages(_color(i + k), _depth(i + k, (720, 1280)))
                          for k in range(2)])
    return root


@pytest.fixture
def behave(tmp_path, behave_root) -> Path:
    """A fresh copy to damage: returns the sequence folder."""
    root = tmp_path / "root"
    shutil.copytree(behave_root, root)
    return root / SEQ


def _frame_file(seq: Path, i: int, name: str) -> Path:
    return seq / f"t{BEHAVE_TIMES[i]:08.3f}" / name


def test_behave_corrupt_and_truncated_colour(behave):
    jpg = _frame_file(behave, 1, "k0.color.jpg")
    jpg.write_bytes(_undecodable(jpg.read_bytes()))  # complete but undecodable
    cut = _frame_file(behave, 2, "k0.color.jpg")
    cut.write_bytes(cut.read_bytes()[:3000])  # truncated: caught when read
    stream = open_kinect_stream(behave, kinect=0)
    frames = list(stream)
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert all(f.depth_mm is not None and f.depth_mm.shape == (720, 1280) for f in frames)
    assert [f.has_color for f in frames] == [True, True, False, True]
    assert [(s.index, s.stream) for s in stream.skipped] == [(2, "COLOR")]
    assert "truncated JPEG" in stream.skipped[0].reason and stream.skipped[0].where == str(cut)
    assert frames[1].color_rgb() is None and frames[0].color_rgb() is not None
    skip = stream.skipped[-1]
    assert (skip.index, skip.stream, skip.timestamp_us) == (1, "COLOR", 2_033_000)
    assert str(jpg) in skip.reason and "could not be decoded" in skip.reason
    # the other camera is untouched
    other = open_kinect_stream(behave, kinect=1)
    assert all(f.color_rgb() is not None for f in other) and other.skipped == []
    with pytest.raises(KinectFormatError, match="truncated JPEG") as err:
        list(open_kinect_stream(behave, kinect=0, strict=True))
    _named(err, cut)


def test_behave_missing_and_corrupt_depth(behave):
    _frame_file(behave, 0, "k0.depth.png").unlink()
    png = _frame_file(behave, 3, "k0.depth.png")
    data = bytearray(png.read_bytes())
    data[60:80] = bytes(20)  # inside IDAT: CRC and zlib stream broken
    png.write_bytes(bytes(data))
    _frame_file(behave, 2, "k0.depth.png").unlink()
    _frame_file(behave, 2, "k0.color.jpg").unlink()  # nothing left of frame 2
    stream = open_kinect_stream(behave, kinect=0)
    frames = list(stream)
    assert [f.index for f in frames] == [0, 1, 3]  # frame 2 skipped, indices keep their place
    assert [f.depth_mm is None for f in frames] == [True, False, True]
    assert all(f.color_rgb() is not None for f in frames)
    got = [(s.index, s.stream, Path(s.where).name, s.reason.split(":")[0]) for s in stream.skipped]
    assert got == [(0, "DEPTH", "k0.depth.png", "depth dropped"),
                   (2, "COLOR", "k0.color.jpg", "colour dropped"),
                   (2, "DEPTH", "k0.depth.png", "depth dropped"),
                   (3, "DEPTH", "k0.depth.png", "depth dropped")]
    assert "missing" in stream.skipped[0].reason
    assert "corrupt" in stream.skipped[3].reason or "truncated" in stream.skipped[3].reason


def test_behave_inconsistent_sequence_is_an_error(behave):
    cv2.imwrite(str(_frame_file(behave, 1, "k1.depth.png")), np.zeros((288, 320), np.uint16))
    stream = open_kinect_stream(behave, kinect=1)
    with pytest.raises(KinectFormatError, match="registered to the colour image") as err:
        list(stream)
    _named(err, _frame_file(behave, 1, "k1.depth.png"))
    assert len(list(open_kinect_stream(behave, kinect=0))) == 4  # camera 0 is fine
    cv2.imwrite(str(_frame_file(behave, 1, "k1.color.jpg")), np.zeros((1536, 2048, 3), np.uint8))
    with pytest.raises(KinectFormatError, match=r"2048x1536, calibration .* is for 1280x720"):
        list(open_kinect_stream(behave, kinect=1))


def test_behave_missing_calibration_and_camera_choice(behave):
    with pytest.raises(KinectFormatError, match="2 cameras; choose one"):
        open_kinect_stream(behave)
    with pytest.raises(KinectFormatError, match="no camera k5"):
        open_kinect_stream(behave, kinect=5)
    with pytest.raises(KinectFormatError, match="no camera with serial nope"):
        open_kinect_stream(behave, serial="nope")
    calib = behave.parent / "calibs" / "intrinsics" / "1" / "calibration.json"
    named = re.escape(str(behave)) + r"/\.\./calibs/intrinsics/1/calibration\.json: "
    calib.write_bytes(np.random.default_rng(0).bytes(300))
    # the sequence needs every camera's calibration (info.json's relative path, as BEHAVE)
    with pytest.raises(KinectFormatError, match=named + "cannot read camera calibration"):
        open_kinect_stream(behave, kinect=0)
    calib.unlink()
    with pytest.raises(KinectFormatError, match=named + "camera calibration is missing"):
        open_kinect_stream(behave, kinect=0)


# ------------------------------------------------------------------ MVNX cut mid-file
def _full_body(n: int) -> MvnxRecording:
    rng = np.random.default_rng(4)
    s = len(MVN_SEGMENTS)
    q = rng.normal(size=(n, s, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    time_ms = np.round(np.arange(n) * 1000 / 60).astype(np.int64)
    unix_ms = 1_600_000_000_000 + time_ms
    identity = MvnxPose(np.tile([1.0, 0, 0, 0], (s, 1)), np.round(rng.normal(size=(s, 3)), 6))
    return MvnxRecording(frame_rate=60.0, segment_labels=list(MVN_SEGMENTS),
                         sensor_labels=list(MVN_SENSORS), time_ms=time_ms, unix_ms=unix_ms,
                         timecode=mvn_timecode(unix_ms, 60), orientation=np.round(q, 6),
                         position=np.round(rng.normal(size=(n, s, 3)), 6),
                         calibration={"identity": identity})


def test_mvnx_cut_mid_file_converts_the_frames_before_the_cut(tmp_path):
    path = tmp_path / "take.mvnx"
    write_mvnx(path, _full_body(10))
    data = path.read_bytes()
    full = mvnx_to_smpl(read_mvnx(path))
    assert full.truncation is None
    cut = tmp_path / "cut.mvnx"
    cut.write_bytes(data[:data.index(b' index="6" ') + 400])  # inside frame index 6
    with pytest.raises(MvnxError, match="ends early") as err:
        read_mvnx(cut)
    _named(err, cut)
    motion = mvnx_to_smpl(read_mvnx(cut, recover_truncated=True))
    assert motion.n_frames == 6
    assert motion.truncation and str(cut) in motion.truncation
    assert "kept the 6 complete normal frames" in motion.truncation
    np.testing.assert_allclose(motion.time, full.time[:6])
    np.testing.assert_allclose(motion.global_orient, full.global_orient[:6], atol=1e-9)
    np.testing.assert_allclose(motion.body_pose, full.body_pose[:6], atol=1e-9)
    # cut before any complete motion frame: nothing to recover, said clearly
    early = tmp_path / "early.mvnx"
    early.write_bytes(data[:data.index(b' index="0" ') + 100])
    with pytest.raises(MvnxError) as err:
        read_mvnx(early, recover_truncated=True)
    _named(err, early)


@pytest.mark.parametrize("encoding", ["kTF-8", "EBCDIC", "UTF-16", "shift_jis"])
def test_mvnx_unreadable_encoding_declaration_is_a_clear_error(tmp_path, encoding):
    """Regression: a damaged encoding name raised LookupError (multi-byte ones a ValueError
    without the file name) from the XML parser."""
    path = tmp_path / "take.mvnx"
    write_mvnx(path, _full_body(2))
    data = path.read_bytes()
    head = data.index(b"?>")
    assert b'encoding="UTF-8"' in data[:head]
    path.write_bytes(data.replace(b'encoding="UTF-8"', f'encoding="{encoding}"'.encode(), 1))
    with pytest.raises(MvnxError, match="encoding") as err:
        read_mvnx(path, recover_truncated=True)
    _named(err, path)


# ------------------------------------------------------------------ Xbus
def test_long_random_serial_dump_keeps_every_message(tmp_path):
    """256 KiB of line noise with real MTData2 messages spliced in, read back from a file: no
    exception, every byte accounted for, every real message found."""
    rng = np.random.default_rng(12)
    messages = [encode_mtdata2(XbusSample(device_id=0x00B40000 + k % 3, packet_counter=k,
                                          sample_time_fine=100 * k,
                                          quaternion=np.array([1.0, 0, 0, 0])))
                for k in range(50)]
    # noise may not hold FA FF: a preamble + bus id there starts a candidate that could swallow
    # the next real message (a 1/256 checksum collision no parser can tell from a message)
    noise = [rng.bytes(int(rng.integers(0, 10_000))).replace(b"\xfa\xff", b"\xfa\x00")
             for _ in messages]
    noise = [g[:-1] + b"\x00" if g.endswith(b"\xfa") else g for g in noise]
    dump = tmp_path / "serial.bin"
    dump.write_bytes(b"".join(g + m for g, m in zip(noise, messages, strict=True))
                     + rng.bytes(5000).replace(b"\xfa\xff", b"\xfa\x00"))
    items, stats = parse_stream(dump.read_bytes())
    samples = [i for i in items if isinstance(i, XbusSample)]
    assert [s.packet_counter for s in samples] == list(range(50))
    assert stats.bytes_in == stats.bytes_ok + stats.bytes_skipped == dump.stat().st_size
    assert stats.bytes_ok == sum(map(len, messages))


def test_random_bytes_as_device_map(tmp_path):
    rng = np.random.default_rng(2)
    path = tmp_path / "devices.json"
    for size in (0, 1, 7, 64, 300):
        path.write_bytes(rng.bytes(size))
        with pytest.raises(XbusError) as err:
            read_device_map(path)
        _named(err, path)
