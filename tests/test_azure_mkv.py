"""Azure Kinect .mkv writer and streaming reader.

Besides write -> read round trips, every file is checked by readers that are not this module:
PyAV/FFmpeg (streams, codec tags, gray16be decoding, attachment, tags) and a minimal EBML walker
in this file (element layout as k4arecorder writes it, CRC-32s). A real k4arecorder recording
is read when available (see ``_real_recording``).
"""

from __future__ import annotations

import json
import os
import zlib
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from couch.capture.azure_calibration import CameraIntrinsics, KinectCalibration
from couch.capture.azure_mkv import (
    AzureMkvWriter,
    KinectFormatError,
    decode_color,
    open_azure_mkv,
)
from couch.capture.frames import open_kinect_stream

T0_US = 1_234_567  # device time of the first frame
PERIOD_US = 33_333
N_FRAMES = 4


# ------------------------------------------------------------------ helpers
@pytest.fixture(scope="module")
def calibration() -> KinectCalibration:
    depth = CameraIntrinsics(640, 576, 504.6, 504.7, 332.8, 348.8,
                             dist=[0.55, -0.02, 2e-5, -7e-5, -0.003, 0.89, 0.086, -0.014],
                             metric_radius=1.74)
    color = CameraIntrinsics(1280, 720, 611.8, 611.9, 639.3, 365.9,
                             dist=[0.33, -2.49, -1.6e-4, -1.3e-4, 1.45, 0.21, -2.30, 1.38])
    t = np.eye(4)
    t[:3, 3] = [-0.032, -0.0022, 0.0039]
    return KinectCalibration(depth=depth, color=color, color_from_depth=t,
                             depth_mode="NFOV_UNBINNED", color_resolution="720P",
                             serial="000111222333")


@pytest.fixture(scope="module")
def frames():
    """N_FRAMES of (colour JPEG 1280x720, depth (576,640) uint16 mm, IR (576,640) uint16)."""
    rng = np.random.default_rng(7)
    out = []
    for i in range(N_FRAMES):
        img = np.zeros((720, 1280, 3), np.uint8)
        img[:, :, i % 3] = 40 * (i + 1)
        ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
        assert ok
        depth = rng.integers(0, 6000, (576, 640), dtype=np.uint16)
        depth[:10] = 0  # invalid pixels
        depth[-1, -1] = 65535
        ir = rng.integers(0, 3000, (576, 640), dtype=np.uint16)
        out.append((jpg.tobytes(), depth, ir))
    return out


def _write(path: Path, calibration, frames, **kw) -> list[int]:
    stamps = [T0_US + i * PERIOD_US for i in range(len(frames))]
    with AzureMkvWriter(path, calibration, uid_seed=3, **kw) as w:
        for ts, (jpg, depth, ir) in zip(stamps, frames, strict=True):
            w.write(ts, jpg, depth, ir)
    return stamps


@pytest.fixture(scope="module")
def recording(tmp_path_factory, calibration, frames) -> tuple[Path, list[int]]:
    path = tmp_path_factory.mktemp("mkv") / "cam0.mkv"
    return path, _write(path, calibration, frames)


def _ebml(buf: bytes, pos: int, end: int):
    """Minimal independent EBML walker: yields (id, header start, data start, data end)."""
    while pos < end:
        start = pos
        n = 9 - buf[pos].bit_length()
        eid = int.from_bytes(buf[pos:pos + n], "big")
        pos += n
        m = 9 - buf[pos].bit_length()
        size = int.from_bytes(buf[pos:pos + m], "big") & ((1 << (7 * m)) - 1)
        pos += m
        yield eid, start, pos, pos + size
        pos += size


def _segment(buf: bytes):
    (_, _, _, head_end), = [e for e in _ebml(buf, 0, 40) if e[0] == 0x1A45DFA3]
    (eid, _, data, end), = list(_ebml(buf, head_end, len(buf)))
    assert eid == 0x18538067
    return data, end


def _clusters(buf: bytes):
    data, end = _segment(buf)
    return [e for e in _ebml(buf, data, end) if e[0] == 0x1F43B675]


# ------------------------------------------------------------------ round trip
def _write_drops(path: Path, calibration, frames) -> Path:
    """Four captures: whole, colour dropped, depth and IR dropped, IR dropped."""
    jpg, depth, ir = frames[0]
    with AzureMkvWriter(path, calibration) as w:
        w.write(T0_US, jpg, depth, ir)
        w.write(T0_US + PERIOD_US, None, depth, ir)  # colour dropped
        w.write(T0_US + 2 * PERIOD_US, jpg, None, None)  # depth + IR dropped
        w.write(T0_US + 3 * PERIOD_US, jpg, depth, None)
    return path


def _shorten_block(data: bytes, cluster: int, block: int, track: int) -> bytes:
    """The file with the ``block``-th SimpleBlock of cluster ``cluster`` (of track number
    ``track``) 10 bytes shorter, the 10 bytes a Void: the cluster stays well-formed (its CRC-32
    recomputed) but the frame has the wrong byte count."""
    buf = bytearray(data)
    _, _, a, b = _clusters(bytes(buf))[cluster]
    _, start, at, end = [k for k in _ebml(bytes(buf), a, b) if k[0] == 0xA3][block]
    assert buf[at] == 0x80 | track
    size_len = at - start - 1
    buf[start + 1:at] = ((1 << (7 * size_len)) | (end - at - 10)).to_bytes(size_len, "big")
    buf[end - 10:end] = b"\xec\x88" + bytes(8)
    crc_id, _, x, y = next(_ebml(bytes(buf), a, b))
    assert crc_id == 0xBF
    buf[x:y] = zlib.crc32(bytes(buf[y:b])).to_bytes(4, "little")
    return bytes(buf)


def test_round_trip_bit_exact(recording, calibration, frames):
    path, stamps = recording
    rec = open_azure_mkv(path)
    assert rec.fps == 30 and rec.frame_period_ns == 33_333_333
    assert rec.serial == "000111222333"
    assert rec.depth_mode == "NFOV_UNBINNED"
    assert rec.color_mode == "MJPG_720P" and rec.color_resolution == "720P"
    assert rec.start_offset_ns == T0_US * 1000  # k4arecorder: first cluster at block time 0
    assert rec.tags["K4A_WIRED_SYNC_MODE"] == "STANDALONE"
    assert rec.duration_us == stamps[-1] - stamps[0]
    assert rec.calibration == KinectCalibration.from_json(calibration.to_json())
    np.testing.assert_allclose(rec.calibration.depth.K(), calibration.depth.K(), atol=1e-9)
    caps = list(rec)
    assert [c.index for c in caps] == list(range(N_FRAMES))
    assert [c.timestamp_us for c in caps] == stamps
    for cap, (jpg, depth, ir) in zip(caps, frames, strict=True):
        assert cap.color_jpeg == jpg
        assert cap.depth_mm.dtype == np.uint16 and cap.depth_mm.shape == (576, 640)
        np.testing.assert_array_equal(cap.depth_mm, depth)
        np.testing.assert_array_equal(cap.ir, ir)
        assert cap.color_timestamp_us == cap.depth_timestamp_us == cap.ir_timestamp_us
    assert rec.skipped == [] and rec.warnings == []
    assert list(rec)[2].timestamp_us == stamps[2]  # iterable more than once


def test_pyav_reads_it_independently(recording, frames):
    path, stamps = recording
    with av.open(str(path)) as c:
        titles = [s.metadata.get("title") for s in c.streams.video]
        assert titles == ["COLOR", "DEPTH", "IR"]
        color, depth, ir = c.streams.video
        assert depth.codec_tag == "b16g" and ir.codec_tag == "b16g"
        assert color.codec_tag == "MJPG"
        assert depth.codec_context.name == "rawvideo"
        assert depth.metadata["K4A_DEPTH_MODE"] == "NFOV_UNBINNED"
        assert color.metadata["K4A_COLOR_MODE"] == "MJPG_720P"
        assert c.metadata["K4A_START_OFFSET_NS"] == str(T0_US * 1000)
        assert c.metadata["K4A_DEVICE_SERIAL_NUMBER"] == "000111222333"
        assert depth.time_base == Fraction(1, 1_000_000)  # TimecodeScale 1 µs
        (att,) = c.streams.attachments
        assert att.name == "calibration.json"
        assert att.metadata["K4A_CALIBRATION_FILE"] == "calibration.json"
        doc = json.loads(bytes(att.data))
        locations = [cam["Location"] for cam in doc["CalibrationInformation"]["Cameras"]]
        assert locations == ["CALIBRATION_CameraLocationD0", "CALIBRATION_CameraLocationPV0"]
        decoded = list(c.decode(depth))
    assert [f.format.name for f in decoded] == ["gray16be"] * N_FRAMES
    assert [f.pts for f in decoded] == [s - stamps[0] for s in stamps]
    for f, (_, d, _) in zip(decoded, frames, strict=True):
        np.testing.assert_array_equal(f.to_ndarray(), d)
    with av.open(str(path)) as c:
        img = next(c.decode(c.streams.video[0])).to_ndarray(format="rgb24")
    assert img.shape == (720, 1280, 3)


def test_layout_matches_k4arecorder(recording):
    """Element order, 8-byte Segment size, reserved Voids, CRC-32s, bitmap headers."""
    path, stamps = recording
    buf = path.read_bytes()
    head = buf[:4]
    assert head == bytes.fromhex("1a45dfa3")
    seg_data, seg_end = _segment(buf)
    assert seg_end == len(buf)
    assert buf[seg_data - 8] == 0x01  # size coded on 8 bytes, as record.cpp writes it
    top = list(_ebml(buf, seg_data, seg_end))
    names = {0x114D9B74: "SeekHead", 0xEC: "Void", 0x1549A966: "Info", 0x1654AE6B: "Tracks",
             0x1941A469: "Attachments", 0x1254C367: "Tags", 0x1F43B675: "Cluster",
             0x1C53BB6B: "Cues"}
    order = [names[e[0]] for e in top]
    assert order[:8] == ["SeekHead", "Void", "Info", "Void", "Tracks", "Attachments", "Tags",
                         "Void"]
    assert set(order[8:-1]) == {"Cluster"} and order[-1] == "Cues"
    assert top[2][1] - seg_data == 1027 and top[4][1] - top[2][1] == 259  # reserved spaces
    # SeekHead positions point at the elements
    seek = {}
    for _, _, a, b in _ebml(buf, top[0][2], top[0][3]):
        kids = {k: buf[x:y] for k, _, x, y in _ebml(buf, a, b)}
        seek[int.from_bytes(kids[0x53AB], "big")] = int.from_bytes(kids[0x53AC], "big")
    for eid, start, _, _ in top:
        if eid in seek:
            assert seek[eid] == start - seg_data
    # Info: TimecodeScale 1000 ns, title
    info = {k: buf[a:b] for k, _, a, b in _ebml(buf, top[2][2], top[2][3])}
    assert int.from_bytes(info[0x2AD7B1], "big") == 1000
    assert info[0x7BA9] == b"Azure Kinect"
    # Tracks: V_MS/VFW/FOURCC with BITMAPINFOHEADERs
    fourcc = {}
    for _, _, a, b in _ebml(buf, top[4][2], top[4][3]):
        kids = {k: buf[x:y] for k, _, x, y in _ebml(buf, a, b)}
        assert kids[0x86] == b"V_MS/VFW/FOURCC"
        bih = kids[0x63A2]
        assert len(bih) == 40 and int.from_bytes(bih[:4], "little") == 40
        fourcc[kids[0x536E].decode()] = (bih[16:20], int.from_bytes(bih[14:16], "little"),
                                         int.from_bytes(bih[20:24], "little"))
        assert int.from_bytes(kids[0x23E383], "big") == 1_000_000_000 // 30
    assert fourcc == {"COLOR": (b"MJPG", 24, 0), "DEPTH": (b"b16g", 16, 640 * 576 * 2),
                      "IR": (b"b16g", 16, 640 * 576 * 2)}
    # Tags and every Cluster start with a valid CRC-32 of the rest of their data
    for eid, _, a, b in top:
        if eid in (0x1254C367, 0x1F43B675):
            crc_id, _, x, y = next(_ebml(buf, a, b))
            assert crc_id == 0xBF
            assert int.from_bytes(buf[x:y], "little") == zlib.crc32(buf[y:b])
    # Clusters: Timecode first (0 for the first), then one SimpleBlock per image
    clusters = _clusters(buf)
    assert len(clusters) == N_FRAMES  # 33 ms apart: one 32 ms window each
    for i, (_, _, a, b) in enumerate(clusters):
        kids = list(_ebml(buf, a, b))
        assert int.from_bytes(buf[kids[1][2]:kids[1][3]], "big") == stamps[i] - stamps[0]
        blocks = [k for k in kids if k[0] == 0xA3]
        assert [buf[k[2]] for k in blocks] == [0x81, 0x82, 0x83]  # tracks 1, 2, 3
        assert all(buf[k[2] + 3] == 0x80 for k in blocks)  # keyframe, no lacing


def test_depth_delay_and_explicit_offset(tmp_path, calibration, frames):
    path = tmp_path / "delay.mkv"
    _write(path, calibration, frames, depth_delay_ns=-2000, start_offset_ns=1_000_000_000,
           wired_sync_mode="SUBORDINATE", subordinate_delay_ns=160_000)
    rec = open_azure_mkv(path)
    assert rec.depth_delay_ns == -2000 and rec.start_offset_ns == 1_000_000_000
    assert rec.wired_sync_mode == "SUBORDINATE" and rec.subordinate_delay_ns == 160_000
    caps = list(rec)
    assert len(caps) == N_FRAMES
    for i, cap in enumerate(caps):
        assert cap.timestamp_us == cap.depth_timestamp_us == T0_US + i * PERIOD_US
        assert cap.color_timestamp_us == cap.timestamp_us + 2  # depth 2 µs before colour
    with av.open(str(path)) as c:
        pts = [p.pts for p in c.demux(c.streams.video[1]) if p.pts is not None]
    assert pts == [T0_US - 1_000_000 + i * PERIOD_US for i in range(N_FRAMES)]


def test_dropped_images_pair_correctly(tmp_path, calibration, frames):
    path = _write_drops(tmp_path / "drops.mkv", calibration, frames)
    caps = list(open_azure_mkv(path))
    have = [(c.color_jpeg is not None, c.depth_mm is not None, c.ir is not None) for c in caps]
    assert have == [(True, True, True), (False, True, True), (True, False, False),
                    (True, True, False)]
    assert [c.timestamp_us for c in caps] == [T0_US + i * PERIOD_US for i in range(4)]


def test_reading_some_streams_keeps_every_capture(tmp_path, recording, calibration, frames):
    """``streams``: the images left out are None and their bytes are not checked, but their
    blocks still pair into captures, so a depth-only read yields the captures, indices and
    time stamps of a full read with the same depth; a corrupt IR block is no skip there."""
    path = _write_drops(tmp_path / "drops.mkv", calibration, frames)
    full = list(open_azure_mkv(path))
    for streams in (("DEPTH",), ("COLOR",), ("IR", "DEPTH"), ()):
        caps = list(open_azure_mkv(path, streams=streams))
        assert [(c.index, c.timestamp_us) for c in caps] == \
            [(c.index, c.timestamp_us) for c in full]
        for ours, theirs in zip(caps, full, strict=True):
            for name, attr in (("COLOR", "color_jpeg"), ("DEPTH", "depth_mm"), ("IR", "ir")):
                want = getattr(theirs, attr) if name in streams else None
                got = getattr(ours, attr)
                assert (got is None) == (want is None), (streams, name)
                if want is not None:
                    assert np.array_equal(np.asarray(got), np.asarray(want))
    # through KinectStream: colour not read is said so, not taken for a dropped image
    frame = next(iter(open_kinect_stream(path, streams=("DEPTH",))))
    assert frame.ir is None and frame.depth_mm is not None
    with pytest.raises(KinectFormatError, match="colour not read"):
        frame.require_color()

    # the second capture's IR block cut short: a skip when IR is read, nothing when it is not
    bad = tmp_path / "badir.mkv"
    bad.write_bytes(_shorten_block(recording[0].read_bytes(), 1, 2, track=3))  # 3: IR
    rec = open_azure_mkv(bad)
    assert list(rec)[1].ir is None and [s.track for s in rec.skipped] == ["IR"]
    rec = open_azure_mkv(bad, streams=("DEPTH",))
    caps = list(rec)
    assert len(caps) == N_FRAMES and rec.skipped == []
    np.testing.assert_array_equal(caps[1].depth_mm, frames[1][1])
    with pytest.raises(ValueError, match="'RGB'"):
        open_azure_mkv(path, streams=("RGB",))


def test_passive_ir_has_no_depth_track(tmp_path, calibration, frames):
    depth = CameraIntrinsics(1024, 1024, 504.6, 504.7, 524.8, 528.8)
    cal = KinectCalibration(depth=depth, color=calibration.color, depth_mode="PASSIVE_IR")
    ir = np.arange(1024 * 1024, dtype=np.uint32).reshape(1024, 1024).astype(np.uint16)
    path = tmp_path / "passive.mkv"
    with AzureMkvWriter(path, cal) as w:
        w.write(T0_US, frames[0][0], None, ir)
        with pytest.raises(ValueError, match="no DEPTH track"):
            w.write(T0_US + PERIOD_US, None, ir)
    rec = open_azure_mkv(path)
    assert sorted(rec.tracks) == ["COLOR", "IR"] and rec.depth_mode == "PASSIVE_IR"
    assert rec.tags["K4A_IR_MODE"] == "PASSIVE"
    (cap,) = list(rec)
    assert cap.depth_mm is None and cap.timestamp_us == T0_US
    np.testing.assert_array_equal(cap.ir, ir)
    with av.open(str(path)) as c:
        assert c.metadata["K4A_DEPTH_MODE"] == "PASSIVE_IR"  # recording-level, as record.cpp
        assert [s.metadata["title"] for s in c.streams.video] == ["COLOR", "IR"]


def test_colour_off_is_written_as_k4arecorder_color_mode_off(tmp_path, calibration, frames):
    """``color=False``: what record.cpp writes with K4A_COLOR_RESOLUTION_OFF: no COLOR track and
    no K4A_COLOR_TRACK / K4A_COLOR_MODE / K4A_DEPTH_DELAY_NS tags; DEPTH is track 1 (indexed by
    the Cues); firmware tags and calibration as with colour."""
    path = tmp_path / "depth_only.mkv"
    stamps = [T0_US + i * PERIOD_US for i in range(N_FRAMES)]
    with AzureMkvWriter(path, calibration, uid_seed=3, color=False) as w:
        assert w.color_mode == "OFF"
        with pytest.raises(ValueError, match="no COLOR track"):
            w.write(stamps[0], frames[0][0], frames[0][1])
        for ts, (_, depth, ir) in zip(stamps, frames, strict=True):
            w.write(ts, depth_mm=depth, ir=ir)
    with pytest.raises(ValueError, match="without colour"):
        AzureMkvWriter(tmp_path / "x.mkv", calibration, color=False, depth_delay_ns=-2000)
    rec = open_azure_mkv(path)
    assert sorted(rec.tracks) == ["DEPTH", "IR"] and rec.tracks["DEPTH"].number == 1
    assert (rec.color_mode, rec.color_resolution, rec.depth_delay_ns) == ("OFF", "OFF", 0)
    for tag in ("K4A_COLOR_TRACK", "K4A_COLOR_MODE", "K4A_DEPTH_DELAY_NS"):
        assert tag not in rec.tags
    assert rec.tags["K4A_COLOR_FIRMWARE_VERSION"] and rec.serial == "000111222333"
    caps = list(rec)
    assert [c.timestamp_us for c in caps] == stamps
    for cap, (_, depth, ir) in zip(caps, frames, strict=True):
        assert cap.color_jpeg is None and cap.color_timestamp_us is None
        np.testing.assert_array_equal(cap.depth_mm, depth)
        np.testing.assert_array_equal(cap.ir, ir)
    with av.open(str(path)) as c:  # an independent reader sees the same
        assert [s.metadata.get("title") for s in c.streams.video] == ["DEPTH", "IR"]
        assert "K4A_DEPTH_DELAY_NS" not in c.metadata
        decoded = [f.to_ndarray() for f in c.decode(c.streams.video[0])]
    assert all(np.array_equal(a, f[1]) for a, f in zip(decoded, frames, strict=True))
    # the Cues index the first track, now DEPTH
    buf = path.read_bytes()
    seg_data, seg_end = _segment(buf)
    (cues,) = [e for e in _ebml(buf, seg_data, seg_end) if e[0] == 0x1C53BB6B]
    cue_tracks = [buf[x:y] for _, _, a, b in _ebml(buf, cues[2], cues[3])  # CuePoint
                  for k, _, c, d in _ebml(buf, a, b) if k == 0xB7  # CueTrackPositions
                  for j, _, x, y in _ebml(buf, c, d) if j == 0xF7]  # CueTrack
    assert cue_tracks and set(cue_tracks) == {b"\x01"}


def test_writer_streams_and_is_atomic(tmp_path, calibration, frames):
    path = tmp_path / "stream.mkv"
    jpg, depth, ir = frames[0]
    frame_bytes = 2 * depth.nbytes
    with AzureMkvWriter(path, calibration) as w:
        for i in range(6):
            w.write(T0_US + i * PERIOD_US, jpg, depth, ir)
        assert not path.exists()  # only the temporary file exists until close
        (tmp,) = [p for p in tmp_path.iterdir() if p.name.startswith(".stream.mkv.")]
        w._f.flush()
        assert tmp.stat().st_size > 4 * frame_bytes  # earlier frames are already on disk
        assert len(w._pending) <= 2  # only the newest cluster windows are held in memory
    assert path.exists() and not tmp.exists()
    with pytest.raises(RuntimeError), AzureMkvWriter(tmp_path / "boom.mkv", calibration) as w:
        w.write(T0_US, jpg, depth, ir)
        raise RuntimeError("simulated crash")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stream.mkv"]


def test_writer_rejects_bad_frames(tmp_path, calibration, frames):
    jpg, depth, ir = frames[0]
    small = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))[1].tobytes()
    with pytest.raises(ValueError, match="fps"):
        AzureMkvWriter(tmp_path / "x.mkv", calibration, fps=25)
    with pytest.raises(ValueError, match="less than one frame period"):
        AzureMkvWriter(tmp_path / "x.mkv", calibration, depth_delay_ns=40_000_000)
    with AzureMkvWriter(tmp_path / "x.mkv", calibration) as w:
        with pytest.raises(ValueError, match=r"DEPTH must be \(576,640\) uint16"):
            w.write(T0_US, None, depth.astype(np.int32))
        with pytest.raises(ValueError, match="64x48 but colour mode MJPG_720P is 1280x720"):
            w.write(T0_US, small)
        with pytest.raises(ValueError, match="not a JPEG"):
            w.write(T0_US, b"\x89PNG....")
        with pytest.raises(ValueError, match="nothing to write"):
            w.write(T0_US)
        w.write(T0_US, jpg, depth, ir)
        with pytest.raises(ValueError, match="must increase"):
            w.write(T0_US, jpg, depth, ir)


# ------------------------------------------------------------------ bad input
def test_not_matroska(tmp_path):
    for name, data in (("text.mkv", b"hello, this is not a video\n"), ("empty.mkv", b""),
                       ("png.mkv", b"\x89PNG\r\n\x1a\n" + bytes(100))):
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(KinectFormatError, match="not a Matroska file") as err:
            open_azure_mkv(p)
        assert str(p) in str(err.value)
    with pytest.raises(KinectFormatError, match="cannot open"):
        open_azure_mkv(tmp_path / "missing.mkv")


def test_truncated_file(tmp_path, recording):
    path, stamps = recording
    buf = path.read_bytes()
    clusters = _clusters(buf)
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(buf[:clusters[-1][2] + 1000])  # inside the last cluster's colour block
    rec = open_azure_mkv(cut)
    caps = list(rec)
    assert [c.timestamp_us for c in caps] == stamps[:-1]  # the usable part is still read
    assert any("truncated" in w and str(cut) in w for w in rec.warnings)
    assert len(rec.skipped) == 1 and "cut off" in rec.skipped[0].reason
    with pytest.raises(KinectFormatError, match="truncated"):
        list(open_azure_mkv(cut, strict=True))
    head = tmp_path / "head.mkv"
    head.write_bytes(buf[:3000])  # inside the attachment
    with pytest.raises(KinectFormatError, match="truncated") as err:
        open_azure_mkv(head)
    assert str(head) in str(err.value)


def test_missing_calibration_attachment(tmp_path, recording):
    path, _ = recording
    buf = path.read_bytes()
    # Same lengths, so every size field stays valid: no attachment named or tagged as the
    # calibration remains.
    buf = buf.replace(b"K4A_CALIBRATION_FILE", b"K4A_XALIBRATION_FILE")
    buf = buf.replace(b"calibration.json", b"calibrXtion.json")
    p = tmp_path / "nocal.mkv"
    p.write_bytes(buf)
    with pytest.raises(KinectFormatError, match=r"no calibration\.json attachment") as err:
        open_azure_mkv(p)
    assert str(p) in str(err.value)
    rec = open_azure_mkv(p, require_calibration=False)
    assert len(list(rec)) == N_FRAMES
    with pytest.raises(KinectFormatError, match="calibration"):
        _ = rec.calibration


def test_invalid_calibration_json(tmp_path, recording):
    path, _ = recording
    buf = path.read_bytes()
    buf = buf.replace(b"CALIBRATION_CameraLocationPV0", b"CALIBRATION_CameraLocationXX0")
    p = tmp_path / "badcal.mkv"
    p.write_bytes(buf)
    with pytest.raises(KinectFormatError, match="CALIBRATION_CameraLocationPV0") as err:
        open_azure_mkv(p)
    assert str(p) in str(err.value)


def test_corrupt_depth_frame_is_skipped_and_counted(tmp_path, recording, frames):
    path, stamps = recording
    p = tmp_path / "baddepth.mkv"
    p.write_bytes(_shorten_block(path.read_bytes(), 1, 1, track=2))  # 2: DEPTH
    rec = open_azure_mkv(p)
    caps = list(rec)
    assert len(caps) == N_FRAMES
    assert caps[1].depth_mm is None and caps[1].ir is not None and caps[1].color_jpeg
    assert caps[1].timestamp_us == stamps[1]
    np.testing.assert_array_equal(caps[2].depth_mm, frames[2][1])
    (skip,) = rec.skipped
    assert skip.track == "DEPTH" and skip.capture_index == 1 and skip.timestamp_us == stamps[1]
    assert "expected 737280 bytes (640x576 uint16), got 737270" in skip.reason
    assert rec.warnings == []
    with pytest.raises(KinectFormatError, match="737270") as err:
        list(open_azure_mkv(p, strict=True))
    assert str(p) in str(err.value)


def test_damaged_bytes_are_reported_by_crc(tmp_path, recording, frames):
    path, _ = recording
    buf = bytearray(path.read_bytes())
    _, _, a, b = _clusters(bytes(buf))[2]
    _, _, data, _ = [k for k in _ebml(bytes(buf), a, b) if k[0] == 0xA3][2]  # IR block
    buf[data + 100] ^= 0xFF
    p = tmp_path / "bitflip.mkv"
    p.write_bytes(bytes(buf))
    rec = open_azure_mkv(p)
    caps = list(rec)
    assert len(caps) == N_FRAMES and rec.skipped == []
    assert caps[2].ir is not None and not np.array_equal(caps[2].ir, frames[2][2])
    (warning,) = rec.warnings
    assert "CRC-32 mismatch" in warning and str(p) in warning
    with pytest.raises(KinectFormatError, match="CRC-32"):
        list(open_azure_mkv(p, strict=True))


def test_garbage_inside_recording_resyncs(tmp_path, recording):
    path, stamps = recording
    buf = bytearray(path.read_bytes())
    _, start, _, _ = _clusters(bytes(buf))[1]
    buf[start:start + 64] = b"\x00" * 64  # destroy the second cluster's header
    p = tmp_path / "garbage.mkv"
    p.write_bytes(bytes(buf))
    rec = open_azure_mkv(p)
    caps = list(rec)
    assert [c.timestamp_us for c in caps] == [stamps[0], *stamps[2:]]
    assert len(rec.skipped) == 1 and "next cluster" in rec.skipped[0].reason


def test_ffmpeg_style_fourcc_rejected(tmp_path, recording):
    path, _ = recording
    buf = path.read_bytes().replace(b"b16g", b"\x00\x00\x00\x00")
    p = tmp_path / "ffmpeg.mkv"
    p.write_bytes(buf)
    with pytest.raises(KinectFormatError, match=r"FourCC.*expected 'b16g'"):
        open_azure_mkv(p)


def test_decode_color(frames):
    img = np.zeros((48, 64, 3), np.uint8)
    img[:, :, 2] = 255  # pure red in OpenCV's BGR
    jpg = cv2.imencode(".jpg", img)[1].tobytes()
    rgb = decode_color(jpg)
    assert rgb.shape == (48, 64, 3) and rgb.dtype == np.uint8
    assert rgb[..., 0].min() > 240 and rgb[..., 1:].max() < 15
    assert decode_color(frames[0][0]).shape == (720, 1280, 3)
    with pytest.raises(KinectFormatError, match="not a JPEG"):
        decode_color(b"garbage bytes", source="cam0.mkv capture 3")
    with pytest.raises(KinectFormatError, match="truncated"):
        decode_color(jpg[: len(jpg) // 2])
    broken = jpg[:2] + b"\xff\xc0\x00\x02" + b"\x00" * 50 + b"\xff\xd9"
    with pytest.raises(KinectFormatError, match="could not be decoded") as err:
        decode_color(broken, source="cam0.mkv capture 3")
    assert "cam0.mkv capture 3" in str(err.value)


# ------------------------------------------------------------------ a real k4arecorder file
def _real_recording() -> Path | None:
    """pyk4a's tests/assets/recording.mkv (k4arecord-1.4.1, MIT licence), if provided via
    COUCH_K4A_SAMPLE or committed as fixtures/azure/pyk4a_recording.mkv."""
    env = os.environ.get("COUCH_K4A_SAMPLE")
    for cand in (Path(env) if env else None,
                 Path(__file__).parents[1] / "fixtures" / "azure" / "pyk4a_recording.mkv"):
        if cand is not None and cand.is_file():
            return cand
    return None


@pytest.mark.skipif(_real_recording() is None, reason="no real k4arecorder sample available")
def test_real_k4arecorder_file():
    path = _real_recording()
    rec = open_azure_mkv(path)
    assert (rec.fps, rec.depth_mode, rec.color_mode) == (5, "NFOV_UNBINNED", "MJPG_720P")
    assert rec.serial == "001514394512" and rec.start_offset_ns == 336_277_000
    caps = list(rec)
    assert len(caps) == 1 and rec.skipped == [] and rec.warnings == []
    cap = caps[0]
    # pyk4a's own test expects these device timestamps for the file
    assert cap.timestamp_us == cap.color_timestamp_us == cap.ir_timestamp_us == 800_222
    assert decode_color(cap.color_jpeg).shape == (720, 1280, 3)
    assert rec.calibration.depth.fx == pytest.approx(0.4927808940410614 * 1024)
    with av.open(str(path)) as c:
        depth = next(c.decode(c.streams.video[1])).to_ndarray()
    np.testing.assert_array_equal(cap.depth_mm, depth)
