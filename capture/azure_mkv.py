"""Azure Kinect recordings (``k4arecorder`` ``.mkv``): a writer that lays files out as k4arecorder
does, and a streaming reader that accepts real k4arecorder files.

Public API
----------
* :class:`AzureMkvWriter` — context manager; ``write(timestamp_us, color_jpeg, depth_mm, ir)``.
* :func:`open_azure_mkv` -> :class:`AzureMkvRecording`; iterate it for :class:`KinectCapture`.
* :func:`decode_color` — MJPEG frame -> (H,W,3) uint8 RGB.
* :class:`KinectFormatError` (a ``ValueError``) for unreadable input.

Units and frames: timestamps are the device clock in **microseconds** (``device_timestamp_usec``);
depth is (H,W) uint16 **millimetres** with 0 = invalid; IR is (H,W) uint16 raw intensity; colour is
the camera's MJPEG bytes. Images are in the camera's own pixel grid (depth/IR share one camera;
see :mod:`couch.capture.azure_calibration` for intrinsics and ``color_from_depth``).

The file format, as checked in the primary sources
--------------------------------------------------
Azure-Kinect-Sensor-SDK (commit 8bb59ca, 2022-09-01):

``src/record/sdk/record.cpp`` (``k4a_record_create``, ``k4a_record_write_header``,
``k4a_record_write_capture``, ``k4a_record_flush``):
  * EBML header (DocType ``matroska``, versions 2/2), then a Segment whose size field is always
    8 bytes; inside it: a 1024-byte Void reserved for the SeekHead, a 256-byte Void reserved for
    the Info, Tracks, Attachments, Tags followed by a 1024-byte Void (so Tags can be rewritten),
    then Clusters, then Cues. At close the SeekHead (Info, Tracks, Attachments, Tags, Cues) and
    Info (TimecodeScale, MuxingApp, WritingApp, DateUTC, Title ``Azure Kinect``, Duration) are
    written into their Voids, the Tags are re-rendered in place (now with
    ``K4A_START_OFFSET_NS``) and the Segment size is patched.
  * Tracks: COLOR (if colour on), DEPTH (unless PASSIVE_IR), IR (if depth on), IMU (optional),
    numbered from 1 in that order. **All three video tracks are ``V_MS/VFW/FOURCC``** with a
    40-byte BITMAPINFOHEADER as CodecPrivate: colour MJPG -> biBitCount 24, biCompression
    ``MJPG`` (0x47504A4D), biSizeImage 0; DEPTH and IR -> biBitCount 16, biCompression ``b16g``
    (0x67363162), biSizeImage W*H*2. (formats.md's "COLOR: V_MJPEG" is not what the SDK writes,
    and its reader ``read_bitmap_info_header`` in ``matroska_read.cpp`` rejects any other codec
    id, so this writer follows the SDK.) DefaultDuration = 1e9 / fps ns (integer division);
    Video PixelWidth/PixelHeight.
  * Depth/IR samples are byte-swapped to **big-endian** before writing.
  * Block time = device timestamp (ns) - ``K4A_START_OFFSET_NS``; the offset is the first
    cluster's first timestamp, so the first cluster is at 0.
  * Tags (the Tags element carries a CRC-32): per track ``K4A_COLOR_TRACK`` (value = the
    TrackUID as decimal text), ``K4A_COLOR_MODE`` (``MJPG_720P``), ``K4A_DEPTH_TRACK``,
    ``K4A_DEPTH_MODE``, ``K4A_IR_TRACK``, ``K4A_IR_MODE`` (ACTIVE / PASSIVE), targeted with
    TargetType ``TRACK`` + TagTrackUID; recording-level (empty Targets) ``K4A_DEPTH_DELAY_NS``
    (only with colour and depth on), ``K4A_WIRED_SYNC_MODE``, ``K4A_SUBORDINATE_DELAY_NS``
    (SUBORDINATE only), ``K4A_COLOR_FIRMWARE_VERSION``, ``K4A_DEPTH_FIRMWARE_VERSION``,
    ``K4A_DEVICE_SERIAL_NUMBER``; ``K4A_CALIBRATION_FILE`` = ``calibration.json`` targeted at the
    attachment (TargetType ``ATTACHMENT`` + TagAttachmentUID); ``K4A_START_OFFSET_NS`` last.
  * The attachment: FileName ``calibration.json``, MimeType ``application/octet-stream``,
    FileData = the device JSON without its trailing NUL, FileUID.
``src/record/internal/matroska_write.cpp`` + ``include/k4ainternal/matroska_common.h``:
  * TimecodeScale = 1000 ns (1 µs); UIDs are random non-zero 60-bit numbers.
  * TrackEntry children (order as rendered in a real file): TrackNumber, TrackUID, TrackType
    (1 video, 17 subtitle), CodecID, Name, CodecPrivate, DefaultDuration, Video; lacing enabled
    (the default, so not written).
  * Clusters cover aligned 32 ms windows of device time (MAX_CLUSTER_LENGTH_NS), each with a
    CRC-32; blocks sorted by timestamp; Cluster Timecode = its first block's time; one video
    frame per SimpleBlock (flags 0x80, no lacing); IMU samples go to BlockGroups.
  * A CuePoint (CueTime, CueTrack, CueClusterPosition) for the first track-1 block of a cluster,
    at most one per second (CUE_ENTRY_GAP_NS).
``src/record/internal/matroska_read.cpp`` (the SDK's reader, followed by :func:`open_azure_mkv`):
  * Tracks are found by the UID in the ``K4A_*_TRACK`` tags, else by name (``DEPTH_IR`` is a
    legacy IR name); the calibration by the ``K4A_CALIBRATION_FILE`` tag, else by name.
  * ``K4A_DEPTH_MODE`` decides the expected depth/IR size (legacy spellings ``NFOV_2x2BINNED``,
    ``WFOV_2x2BINNED``); the colour resolution comes from the COLOR track's width x height.
  * fps = 1e9 / DefaultDuration (5, 15 or 30); all video tracks must share it.
  * ``get_capture``: a capture is the next block of each track whose *sync* time lies within
    half a frame period of the earliest; sync time = block time + a delay: a positive
    ``K4A_DEPTH_DELAY_NS`` is added to the colour track, a negative one (negated) to DEPTH/IR.
  * device timestamp (µs) = block time (ns) / 1000 + ``K4A_START_OFFSET_NS`` / 1000.
``docs`` page "Azure Kinect recording file format" (learn.microsoft.com): COLOR is MJPEG, NV12 or
YUY2 by mode, DEPTH/IR b16g (16-bit grayscale, big-endian), IMU 40-byte little-endian samples.

A real k4arecorder file (pyk4a ``tests/assets/recording.mkv``, k4arecord-1.4.1, MJPG_720P,
NFOV_UNBINNED, 5 fps, with IMU) was dumped element by element and matches all of the above: that
byte layout is what :class:`AzureMkvWriter` reproduces.

Why not FFmpeg/PyAV for writing: FFmpeg's Matroska muxer uses a 1 ms TimecodeScale (µs device
timestamps would be rounded), writes MJPEG as ``V_MJPEG`` (which the SDK rejects), and cannot
write the b16g FourCC (with ``allow_raw_vfw`` it writes biCompression 0 and a negative
biHeight). The container is simple enough to write directly, which keeps every byte as the SDK
writes it; PyAV serves as the independent reader in the tests.

Not reproduced: the IMU track (this writer writes none, like ``k4arecorder --imu OFF``); colour
formats other than MJPG; the ``MuxingApp``/``WritingApp`` strings (they name this module, not
libmatroska/k4arecord). The reader ignores IMU and custom tracks.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import logging
import os
import random
import secrets
import struct
import sys
import zlib
from collections import deque
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import cv2
import numpy as np

from couch.atomic import atomic_path

from .azure_calibration import COLOR_RESOLUTIONS, DEPTH_MODES, KinectCalibration
from .binning import BINNED_MODES, bin_depth, bin_ir

__all__ = [
    "STREAMS",
    "AzureMkvRecording",
    "AzureMkvWriter",
    "KinectCapture",
    "KinectFormatError",
    "SkippedFrame",
    "TrackInfo",
    "decode_color",
    "open_azure_mkv",
]

log = logging.getLogger(__name__)

#: The image streams of a recording, as its tracks are named.
STREAMS: tuple[str, ...] = ("COLOR", "DEPTH", "IR")

# ---------------------------------------------------------------- constants from the SDK
TIMECODE_SCALE_NS = 1000  # MATROSKA_TIMESCALE_NS
MAX_CLUSTER_LENGTH_NS = 32_000_000
CUE_ENTRY_GAP_NS = 1_000_000_000
FOURCC_MJPG = 0x47504A4D
FOURCC_B16G = 0x67363162
_FOURCC_NAMES = {0x3231564E: "NV12", 0x32595559: "YUY2", FOURCC_MJPG: "MJPG",
                 FOURCC_B16G: "b16g", 0x41524742: "BGRA"}
_VFW = "V_MS/VFW/FOURCC"
_LEGACY_DEPTH_MODES = {"NFOV_2x2BINNED": "NFOV_2X2BINNED", "WFOV_2x2BINNED": "WFOV_2X2BINNED"}
_SYNC_MODES = ("STANDALONE", "MASTER", "SUBORDINATE")
_SUPPORTED_FPS = (5, 15, 30)
_MATROSKA_EPOCH = _dt.datetime(2001, 1, 1, tzinfo=_dt.UTC)

# ---------------------------------------------------------------- EBML element ids
EBML, EBML_VERSION, EBML_READ_VERSION = 0x1A45DFA3, 0x4286, 0x42F7
EBML_MAX_ID_LENGTH, EBML_MAX_SIZE_LENGTH = 0x42F2, 0x42F3
DOC_TYPE, DOC_TYPE_VERSION, DOC_TYPE_READ_VERSION = 0x4282, 0x4287, 0x4285
SEGMENT = 0x18538067
SEEK_HEAD, SEEK, SEEK_ID, SEEK_POSITION = 0x114D9B74, 0x4DBB, 0x53AB, 0x53AC
INFO, TIMECODE_SCALE, MUXING_APP, WRITING_APP = 0x1549A966, 0x2AD7B1, 0x4D80, 0x5741
DATE_UTC, TITLE, DURATION = 0x4461, 0x7BA9, 0x4489
TRACKS, TRACK_ENTRY, TRACK_NUMBER, TRACK_UID, TRACK_TYPE = 0x1654AE6B, 0xAE, 0xD7, 0x73C5, 0x83
NAME, CODEC_ID, CODEC_PRIVATE, DEFAULT_DURATION = 0x536E, 0x86, 0x63A2, 0x23E383
VIDEO, PIXEL_WIDTH, PIXEL_HEIGHT = 0xE0, 0xB0, 0xBA
ATTACHMENTS, ATTACHED_FILE, FILE_NAME, FILE_MIME_TYPE = 0x1941A469, 0x61A7, 0x466E, 0x4660
FILE_DATA, FILE_UID = 0x465C, 0x46AE
TAGS, TAG, TARGETS, TARGET_TYPE, TAG_TRACK_UID = 0x1254C367, 0x7373, 0x63C0, 0x63CA, 0x63C5
TAG_ATTACHMENT_UID, SIMPLE_TAG, TAG_NAME, TAG_STRING = 0x63C6, 0x67C8, 0x45A3, 0x4487
CLUSTER, TIMECODE, SIMPLE_BLOCK, BLOCK_GROUP, BLOCK = 0x1F43B675, 0xE7, 0xA3, 0xA0, 0xA1
CUES, CUE_POINT, CUE_TIME, CUE_TRACK_POSITIONS = 0x1C53BB6B, 0xBB, 0xB3, 0xB7
CUE_TRACK, CUE_CLUSTER_POSITION = 0xF7, 0xF1
VOID, CRC32 = 0xEC, 0xBF
CHAPTERS = 0x1043A770
_TOP_LEVEL = {SEEK_HEAD, INFO, TRACKS, ATTACHMENTS, TAGS, CLUSTER, CUES, CHAPTERS, VOID, CRC32}
_TOP_LEVEL_NAMES = {SEEK_HEAD: "SeekHead", INFO: "Info", TRACKS: "Tracks",
                    ATTACHMENTS: "Attachments", TAGS: "Tags", CLUSTER: "Cluster", CUES: "Cues",
                    CHAPTERS: "Chapters", VOID: "Void", CRC32: "CRC-32"}
_UNKNOWN_SIZE = -1


class KinectFormatError(ValueError):
    """An Azure Kinect recording (or one of its frames) cannot be read; the message names the
    file, the byte or frame, and what was expected."""


# ================================================================ EBML encoding (writer side)
def _encode_id(eid: int) -> bytes:
    return eid.to_bytes((eid.bit_length() + 7) // 8, "big")


def _encode_size(n: int, length: int | None = None) -> bytes:
    """EBML variable-size integer; ``length`` forces a (longer) coding, e.g. 8 for the Segment."""
    if length is None:
        length = 1
        while n >= (1 << (7 * length)) - 1:  # all-ones is reserved for "unknown size"
            length += 1
    if length > 8 or n >= (1 << (7 * length)) - 1:
        raise ValueError(f"EBML size {n} does not fit in {length} bytes")
    return ((1 << (7 * length)) | n).to_bytes(length, "big")


def _el(eid: int, payload: bytes) -> bytes:
    return _encode_id(eid) + _encode_size(len(payload)) + payload


def _uint(eid: int, value: int) -> bytes:
    return _el(eid, int(value).to_bytes(max(1, (int(value).bit_length() + 7) // 8), "big"))


def _sint(eid: int, value: int) -> bytes:
    return _el(eid, int(value).to_bytes(8, "big", signed=True))


def _str(eid: int, text: str) -> bytes:
    return _el(eid, text.encode("utf-8"))


def _master(eid: int, *children: bytes) -> bytes:
    return _el(eid, b"".join(children))


def _with_crc(eid: int, *children: bytes) -> bytes:
    """A master element whose first child is a CRC-32 (IEEE, little-endian) of the others."""
    body = b"".join(children)
    return _el(eid, _el(CRC32, zlib.crc32(body).to_bytes(4, "little")) + body)


def _void(total: int) -> bytes:
    """A Void element of exactly ``total`` bytes (ID + size field + zero payload)."""
    if total < 2:
        raise ValueError(f"a Void element needs at least 2 bytes, got {total}")
    for length in range(1, 9):
        n = total - 1 - length
        if 0 <= n < (1 << (7 * length)) - 1:
            return _encode_id(VOID) + _encode_size(n, length) + bytes(n)
    raise ValueError(f"cannot build a Void of {total} bytes")


def _bitmapinfoheader(width: int, height: int, bit_count: int, fourcc: int,
                      size_image: int) -> bytes:
    """40-byte BITMAPINFOHEADER as ``populate_bitmap_info_header`` fills it (little-endian)."""
    return struct.pack("<IiiHHIIiiII", 40, width, height, 1, bit_count, fourcc, size_image,
                       0, 0, 0, 0)


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's SOFn header, or None if it is not a JPEG."""
    if data[:2] != b"\xff\xd8":
        return None
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        if marker == 0xDA or marker == 0xD9:  # scan or end before any frame header
            return None
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 9 > n:
                return None
            height, width = struct.unpack_from(">HH", data, i + 5)
            return width, height
        i += 2 + int.from_bytes(data[i + 2:i + 4], "big")
    return None


# ================================================================ writer
@dataclass
class _Track:
    number: int
    uid: int
    name: str
    width: int
    height: int
    codec_private: bytes
    last_ns: int | None = None


class AzureMkvWriter:
    """Write an Azure Kinect recording laid out as ``k4arecorder --imu OFF`` writes it.

    Tracks: COLOR (MJPG, ``calibration.color_resolution``; none with ``color=False``), DEPTH
    (unless the depth mode is PASSIVE_IR) and IR, all ``V_MS/VFW/FOURCC``, numbered from 1 in
    that order; the calibration is attached as
    ``calibration.json``. Frames are written to disk as they come (only the newest one or two
    32 ms cluster windows are held in memory) into a temporary file beside ``path`` that
    replaces ``path`` on :meth:`close`; on an exception inside ``with`` (or :meth:`abort`) the
    temporary file is removed. Use it as a context manager or call :meth:`close`.

    Args:
        path: output ``.mkv``.
        calibration: the device calibration; its ``depth_mode``/``color_resolution`` set the
            track sizes and the ``K4A_DEPTH_MODE``/``K4A_COLOR_MODE`` tags, its ``serial`` the
            ``K4A_DEVICE_SERIAL_NUMBER`` tag.
        fps: 5, 15 or 30 (the SDK reader accepts no other rate).
        start_offset_ns: ``K4A_START_OFFSET_NS``. ``None`` (k4arecorder's behaviour) uses the
            first written timestamp, so the first cluster is at block time 0. An explicit value
            must not exceed any written timestamp.
        wired_sync_mode: ``STANDALONE``, ``MASTER`` or ``SUBORDINATE``.
        subordinate_delay_ns: ``K4A_SUBORDINATE_DELAY_NS`` (SUBORDINATE only; whole µs).
        depth_delay_ns: ``K4A_DEPTH_DELAY_NS``, the delay of depth after colour (whole µs, less
            than a frame period in magnitude): depth/IR are stamped ``timestamp_us`` and colour
            ``timestamp_us - depth_delay_ns/1000``.
        color_firmware_version, depth_firmware_version: the firmware tags k4arecorder writes
            (defaults are versions seen in real recordings).
        uid_seed: seed for the track/attachment UIDs (``None``: random, as the SDK).
        creation_time: the Info DateUTC (``None``: now).
        color: False records depth only, as ``k4arecorder --color-mode OFF`` (record.cpp with
            ``K4A_COLOR_RESOLUTION_OFF``): no COLOR track and no ``K4A_COLOR_TRACK``/
            ``K4A_COLOR_MODE`` tags (readers report colour mode ``OFF``), and no
            ``K4A_DEPTH_DELAY_NS`` (the SDK writes it only with colour and depth on, so
            ``depth_delay_ns`` must be 0); DEPTH becomes track 1, which the Cues index. The
            firmware tags and the calibration attachment are written as with colour.
    """

    def __init__(self, path: str | os.PathLike, calibration: KinectCalibration, *,
                 fps: int = 30, start_offset_ns: int | None = None,
                 wired_sync_mode: str = "STANDALONE", subordinate_delay_ns: int = 0,
                 depth_delay_ns: int = 0, color_firmware_version: str = "1.6.110",
                 depth_firmware_version: str = "1.6.79", uid_seed: int | None = None,
                 creation_time: _dt.datetime | None = None, color: bool = True) -> None:
        if not isinstance(calibration, KinectCalibration):
            raise TypeError(f"calibration must be a KinectCalibration, got "
                            f"{type(calibration).__name__}")
        if fps not in _SUPPORTED_FPS:
            raise ValueError(f"fps must be one of {_SUPPORTED_FPS} (the Azure Kinect's rates), "
                             f"got {fps!r}")
        if wired_sync_mode not in _SYNC_MODES:
            raise ValueError(f"wired_sync_mode must be one of {_SYNC_MODES}, got "
                             f"{wired_sync_mode!r}")
        self.frame_period_ns = 1_000_000_000 // fps
        for name, value in (("depth_delay_ns", depth_delay_ns),
                            ("subordinate_delay_ns", subordinate_delay_ns)):
            if int(value) != value or value % 1000:
                raise ValueError(f"{name} must be a whole number of microseconds (in ns), got "
                                 f"{value!r}")
        if abs(depth_delay_ns) >= self.frame_period_ns:
            raise ValueError(f"|depth_delay_ns| must be less than one frame period "
                             f"({self.frame_period_ns} ns at {fps} fps), got {depth_delay_ns}")
        if not color and depth_delay_ns:
            raise ValueError(f"depth_delay_ns is the delay of depth after colour; a recording "
                             f"without colour has none, got {depth_delay_ns}")
        if subordinate_delay_ns < 0:
            raise ValueError(f"subordinate_delay_ns must be >= 0, got {subordinate_delay_ns}")
        if start_offset_ns is not None and (int(start_offset_ns) != start_offset_ns
                                            or start_offset_ns < 0):
            raise ValueError(f"start_offset_ns must be a non-negative integer or None, got "
                             f"{start_offset_ns!r}")

        self.path = Path(path)
        self.calibration = calibration
        self.fps = fps
        self.depth_delay_ns = int(depth_delay_ns)
        self.start_offset_ns = None if start_offset_ns is None else int(start_offset_ns)
        self.frames_written = 0
        self._rng = random.Random(uid_seed) if uid_seed is not None else secrets.SystemRandom()
        self._uids: set[int] = set()
        self._creation = (creation_time or _dt.datetime.now(_dt.UTC)).replace(microsecond=0)
        if self._creation.tzinfo is None:
            self._creation = self._creation.replace(tzinfo=_dt.UTC)

        depth_mode = calibration.depth_mode
        dmode = DEPTH_MODES[depth_mode]
        self._tracks: dict[str, _Track] = {}
        self.color_mode = "OFF"  # record.cpp's mode string without colour (it is not tagged)
        if color:
            cmode = COLOR_RESOLUTIONS[calibration.color_resolution]
            self.color_mode = f"MJPG_{cmode.height}P"
            self._tracks["COLOR"] = self._new_track(
                "COLOR", cmode.width, cmode.height,
                _bitmapinfoheader(cmode.width, cmode.height, 24, FOURCC_MJPG, 0))
        b16g = _bitmapinfoheader(dmode.width, dmode.height, 16, FOURCC_B16G,
                                 dmode.width * dmode.height * 2)
        if depth_mode != "PASSIVE_IR":
            self._tracks["DEPTH"] = self._new_track("DEPTH", dmode.width, dmode.height, b16g)
        self._tracks["IR"] = self._new_track("IR", dmode.width, dmode.height, b16g)

        # Tags in the order record.cpp adds them; K4A_START_OFFSET_NS is appended at close.
        tags: list[tuple[str, str, str | None, int]] = []
        for name, t in self._tracks.items():
            if name == "IR" and depth_mode == "PASSIVE_IR":
                # record.cpp: with no depth track the mode is a recording-level tag.
                tags.append(("K4A_DEPTH_MODE", depth_mode, None, 0))
            tags.append((f"K4A_{name}_TRACK", str(t.uid), "TRACK", t.uid))
            if name == "COLOR":
                tags.append(("K4A_COLOR_MODE", self.color_mode, "TRACK", t.uid))
            elif name == "DEPTH":
                tags.append(("K4A_DEPTH_MODE", depth_mode, "TRACK", t.uid))
            else:
                tags.append(("K4A_IR_MODE", "PASSIVE" if depth_mode == "PASSIVE_IR" else "ACTIVE",
                             "TRACK", t.uid))
        if color:  # record.cpp: only with colour and depth both on (depth always is here)
            tags.append(("K4A_DEPTH_DELAY_NS", str(self.depth_delay_ns), None, 0))
        tags.append(("K4A_WIRED_SYNC_MODE", wired_sync_mode, None, 0))
        if wired_sync_mode == "SUBORDINATE":
            tags.append(("K4A_SUBORDINATE_DELAY_NS", str(int(subordinate_delay_ns)), None, 0))
        tags.append(("K4A_COLOR_FIRMWARE_VERSION", color_firmware_version, None, 0))
        tags.append(("K4A_DEPTH_FIRMWARE_VERSION", depth_firmware_version, None, 0))
        tags.append(("K4A_DEVICE_SERIAL_NUMBER", calibration.serial, None, 0))
        self._attachment_uid = self._new_uid()
        tags.append(("K4A_CALIBRATION_FILE", "calibration.json", "ATTACHMENT",
                     self._attachment_uid))
        self._tags = tags

        self._pending: dict[int, list[tuple[int, int, bytes]]] = {}
        self._last_flushed_window = -1
        self._most_recent_ns: int | None = None
        self._cues: list[tuple[int, int]] = []  # (cue time µs, cluster position)
        self._last_cue_ns = 0
        self._closed = False  # no more writes
        self._done = False  # temporary file moved into place or removed

        self._stack = contextlib.ExitStack()
        try:
            tmp = self._stack.enter_context(atomic_path(self.path))
            self._f: BinaryIO = self._stack.enter_context(open(tmp, "w+b"))
            self._write_header()
        except BaseException:
            self._done = True
            self._stack.__exit__(*sys.exc_info())
            raise

    # ---------------------------------------------------------------- public
    def __enter__(self) -> AzureMkvWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort(exc_type, exc, tb)

    def write(self, timestamp_us: int, color_jpeg: bytes | None = None,
              depth_mm: np.ndarray | None = None, ir: np.ndarray | None = None) -> None:
        """Write one capture.

        Args:
            timestamp_us: device timestamp of the depth/IR images in µs (colour is stamped
                ``timestamp_us - depth_delay_ns/1000``); strictly increasing per track.
            color_jpeg: one MJPEG frame of the colour mode's size, or ``None`` (dropped;
                always None for a writer made with ``color=False``).
            depth_mm: (H,W) uint16 depth in mm (0 = invalid) of the depth mode's size, or None.
            ir: (H,W) uint16 IR image of the depth mode's size, or ``None``.
        """
        if self._closed:
            raise ValueError(f"{self.path}: write() after close()")
        if int(timestamp_us) != timestamp_us or timestamp_us < 0:
            raise ValueError(f"timestamp_us must be a non-negative integer, got {timestamp_us!r}")
        ts_ns = int(timestamp_us) * 1000
        blocks: list[tuple[int, str, bytes]] = []
        if color_jpeg is not None:
            color = self._tracks.get("COLOR")
            if color is None:
                raise ValueError(f"frame at {timestamp_us} µs: color_jpeg given, but this "
                                 f"recording has no COLOR track (color=False)")
            data = bytes(color_jpeg)
            size = _jpeg_size(data)
            if size is None:
                raise ValueError(f"frame at {timestamp_us} µs: color_jpeg is not a JPEG (no SOI "
                                 f"marker or no frame header)")
            if size != (color.width, color.height):
                raise ValueError(f"frame at {timestamp_us} µs: color_jpeg is {size[0]}x{size[1]} "
                                 f"but colour mode {self.color_mode} is "
                                 f"{color.width}x{color.height}")
            blocks.append((ts_ns - self.depth_delay_ns, "COLOR", data))
        for name, image in (("DEPTH", depth_mm), ("IR", ir)):
            if image is None:
                continue
            track = self._tracks.get(name)
            if track is None:
                raise ValueError(f"depth mode {self.calibration.depth_mode} has no {name} track")
            image = np.asarray(image)
            if image.dtype != np.uint16 or image.shape != (track.height, track.width):
                raise ValueError(f"frame at {timestamp_us} µs: {name} must be ({track.height},"
                                 f"{track.width}) uint16 for {self.calibration.depth_mode}, got "
                                 f"{image.shape} {image.dtype}")
            blocks.append((ts_ns, name, image.astype(">u2", copy=False).tobytes()))
        if not blocks:
            raise ValueError(f"frame at {timestamp_us} µs: nothing to write (all images None)")
        if self.start_offset_ns is None:
            self.start_offset_ns = min(b[0] for b in blocks)
        for t_ns, name, _ in blocks:
            track = self._tracks[name]
            if t_ns < self.start_offset_ns:
                raise ValueError(f"frame at {timestamp_us} µs: {name} time {t_ns} ns is before "
                                 f"K4A_START_OFFSET_NS={self.start_offset_ns}")
            if track.last_ns is not None and t_ns <= track.last_ns:
                raise ValueError(f"frame at {timestamp_us} µs: {name} timestamps must increase "
                                 f"(previous {track.last_ns // 1000} µs)")
            if t_ns // MAX_CLUSTER_LENGTH_NS <= self._last_flushed_window:
                raise ValueError(f"frame at {timestamp_us} µs: {name} is older than data already "
                                 f"written to disk")
        for t_ns, name, data in blocks:
            track = self._tracks[name]
            track.last_ns = t_ns
            self._pending.setdefault(t_ns // MAX_CLUSTER_LENGTH_NS, []).append(
                (t_ns, track.number, data))
            self._most_recent_ns = max(self._most_recent_ns or 0, t_ns)
        self.frames_written += 1
        # Hold a window back one frame period (k4arecorder holds 2 s) so that a colour frame
        # delayed against depth still lands in its cluster, without buffering the recording.
        for window in sorted(self._pending):
            if (window + 1) * MAX_CLUSTER_LENGTH_NS + self.frame_period_ns <= self._most_recent_ns:
                self._write_cluster(window)

    def close(self) -> None:
        """Flush, write the seek/info/tags/cues metadata and move the file onto ``path``."""
        if self._done:
            return
        self._closed = True
        try:
            for window in sorted(self._pending):
                self._write_cluster(window)
            self._finish()
        except BaseException:
            self.abort(*sys.exc_info())
            raise
        self._done = True
        self._stack.close()

    def abort(self, exc_type: Any = None, exc: Any = None, tb: Any = None) -> None:
        """Discard the recording: the temporary file is removed, ``path`` is untouched."""
        if self._done:
            return
        self._closed = self._done = True
        if exc_type is None:
            exc_type, exc = RuntimeError, RuntimeError(f"{self.path}: recording aborted")
        self._stack.__exit__(exc_type, exc, tb)

    # ---------------------------------------------------------------- internals
    def _new_uid(self) -> int:
        while True:
            uid = self._rng.getrandbits(60)
            if uid and uid not in self._uids:
                self._uids.add(uid)
                return uid

    def _new_track(self, name: str, width: int, height: int, codec_private: bytes) -> _Track:
        return _Track(number=len(self._tracks) + 1, uid=self._new_uid(), name=name, width=width,
                      height=height, codec_private=codec_private)

    def _render_tags(self, with_offset: bool) -> bytes:
        tags = list(self._tags)
        if with_offset and self.start_offset_ns is not None:
            tags.append(("K4A_START_OFFSET_NS", str(self.start_offset_ns), None, 0))
        out = []
        for name, value, target, uid in tags:
            if target is None:
                targets = _master(TARGETS)
            elif target == "TRACK":
                targets = _master(TARGETS, _str(TARGET_TYPE, "TRACK"), _uint(TAG_TRACK_UID, uid))
            else:
                targets = _master(TARGETS, _str(TARGET_TYPE, "ATTACHMENT"),
                                  _uint(TAG_ATTACHMENT_UID, uid))
            out.append(_master(TAG, targets, _master(SIMPLE_TAG, _str(TAG_NAME, name),
                                                     _str(TAG_STRING, value))))
        return _with_crc(TAGS, *out)

    def _write_header(self) -> None:
        f = self._f
        f.write(_master(EBML, _uint(EBML_VERSION, 1), _uint(EBML_READ_VERSION, 1),
                        _uint(EBML_MAX_ID_LENGTH, 4), _uint(EBML_MAX_SIZE_LENGTH, 8),
                        _str(DOC_TYPE, "matroska"), _uint(DOC_TYPE_VERSION, 2),
                        _uint(DOC_TYPE_READ_VERSION, 2)))
        # Unknown size for now, 8 bytes wide so that close() can patch it in place.
        self._segment_size_pos = f.tell() + 4
        f.write(_encode_id(SEGMENT) + b"\x01\xff\xff\xff\xff\xff\xff\xff")
        self._segment_start = f.tell()
        self._seek_void = (f.tell(), 1024 + 3)
        f.write(_void(1024 + 3))
        self._info_void = (f.tell(), 256 + 3)
        f.write(_void(256 + 3))
        self._tracks_pos = f.tell()
        entries = []
        for t in self._tracks.values():
            entries.append(_master(
                TRACK_ENTRY, _uint(TRACK_NUMBER, t.number), _uint(TRACK_UID, t.uid),
                _uint(TRACK_TYPE, 1), _str(CODEC_ID, _VFW), _str(NAME, t.name),
                _el(CODEC_PRIVATE, t.codec_private), _uint(DEFAULT_DURATION, self.frame_period_ns),
                _master(VIDEO, _uint(PIXEL_WIDTH, t.width), _uint(PIXEL_HEIGHT, t.height))))
        f.write(_master(TRACKS, *entries))
        self._attachments_pos = f.tell()
        f.write(_master(ATTACHMENTS, _master(
            ATTACHED_FILE, _str(FILE_NAME, "calibration.json"),
            _str(FILE_MIME_TYPE, "application/octet-stream"),
            _el(FILE_DATA, self.calibration.to_json().encode("utf-8")),
            _uint(FILE_UID, self._attachment_uid))))
        self._tags_pos = f.tell()
        tags = self._render_tags(with_offset=False)
        self._tags_space = len(tags) + 1024 + 3  # Tags + the 1024-byte Void record.cpp reserves
        f.write(tags + _void(1024 + 3))

    def _write_cluster(self, window: int) -> None:
        blocks = sorted(self._pending.pop(window), key=lambda b: b[0])  # stable: track order
        offset = self.start_offset_ns or 0
        cluster_tc = (blocks[0][0] - offset) // TIMECODE_SCALE_NS
        cluster_pos = self._f.tell() - self._segment_start
        parts = [_uint(TIMECODE, cluster_tc)]
        for t_ns, number, data in blocks:
            rel = (t_ns - offset) // TIMECODE_SCALE_NS - cluster_tc
            parts.append(_el(SIMPLE_BLOCK, _encode_size(number) + struct.pack(">hB", rel, 0x80)
                             + data))
        for t_ns, number, _ in blocks:
            if number == 1:
                # matroska_write.cpp: only the first track-1 block, at most one cue a second
                # (its "last == 0" test also lets every cluster through while the last cue is 0).
                rel_ns = t_ns - offset
                if self._last_cue_ns == 0 or rel_ns >= self._last_cue_ns + CUE_ENTRY_GAP_NS:
                    self._last_cue_ns = rel_ns
                    self._cues.append((rel_ns // TIMECODE_SCALE_NS, cluster_pos))
                break
        self._f.write(_with_crc(CLUSTER, *parts))
        self._last_flushed_window = max(self._last_flushed_window, window)

    def _finish(self) -> None:
        f = self._f
        cues_pos = None
        if self._cues:
            cues_pos = f.tell()
            f.write(_master(CUES, *(
                _master(CUE_POINT, _uint(CUE_TIME, t), _master(
                    CUE_TRACK_POSITIONS, _uint(CUE_TRACK, 1), _uint(CUE_CLUSTER_POSITION, pos)))
                for t, pos in self._cues)))
        end = f.tell()

        duration = 0.0
        if self._most_recent_ns is not None:
            duration = (self._most_recent_ns - (self.start_offset_ns or 0)) / TIMECODE_SCALE_NS
        date_ns = int((self._creation - _MATROSKA_EPOCH).total_seconds()) * 1_000_000_000
        info = _master(INFO, _uint(TIMECODE_SCALE, TIMECODE_SCALE_NS), _str(MUXING_APP, "couch"),
                       _str(WRITING_APP, "couch.capture.azure_mkv"), _sint(DATE_UTC, date_ns),
                       _str(TITLE, "Azure Kinect"), _el(DURATION, struct.pack(">f", duration)))
        self._fill(self._info_void, info)

        tags = self._render_tags(with_offset=True)
        self._fill((self._tags_pos, self._tags_space), tags)

        seeks = [(INFO, self._info_void[0]), (TRACKS, self._tracks_pos),
                 (ATTACHMENTS, self._attachments_pos), (TAGS, self._tags_pos)]
        if cues_pos is not None:
            seeks.append((CUES, cues_pos))
        seek_head = _master(SEEK_HEAD, *(
            _master(SEEK, _el(SEEK_ID, _encode_id(eid)),
                    _uint(SEEK_POSITION, pos - self._segment_start)) for eid, pos in seeks))
        self._fill(self._seek_void, seek_head)

        f.seek(self._segment_size_pos)
        f.write(_encode_size(end - self._segment_start, 8))
        f.seek(end)
        f.flush()

    def _fill(self, space: tuple[int, int], element: bytes) -> None:
        """Write ``element`` at a reserved position and pad the rest with a Void."""
        pos, total = space
        rest = total - len(element)
        if rest < 0 or rest == 1:
            raise ValueError(f"{self.path}: element of {len(element)} bytes does not fit the "
                             f"{total} bytes reserved for it")
        self._f.seek(pos)
        self._f.write(element + (_void(rest) if rest else b""))
        self._f.seek(0, os.SEEK_END)


# ================================================================ reader
@dataclass
class TrackInfo:
    """One Matroska track as the reader found it.

    ``fourcc`` is the BITMAPINFOHEADER biCompression as text (e.g. ``b16g``) for
    ``V_MS/VFW/FOURCC`` tracks; ``default_duration_ns`` the frame period.
    """

    number: int
    uid: int
    name: str
    codec_id: str
    track_type: int
    width: int = 0
    height: int = 0
    default_duration_ns: int = 0
    codec_private: bytes = b""
    fourcc: str | None = None


@dataclass
class SkippedFrame:
    """An image (or a stretch of the file) the reader could not use, and why."""

    capture_index: int | None
    track: str
    timestamp_us: int | None
    byte_offset: int
    reason: str


@dataclass
class KinectCapture:
    """One capture: the images of the colour and depth cameras that belong together.

    Attributes:
        index: ordinal of the capture in the recording (0-based; captures whose images were all
            unusable keep their number, so indices may have gaps).
        timestamp_us: device time in µs of the depth/IR exposure; for a capture with colour
            only, the colour time + ``K4A_DEPTH_DELAY_NS``/1000 (the time depth would have had).
        color_jpeg: the MJPEG bytes (decode with :func:`decode_color`), or None.
        depth_mm: (H,W) uint16 millimetres, 0 = invalid, or None.
        ir: (H,W) uint16, or None.
        color_timestamp_us, depth_timestamp_us, ir_timestamp_us: each image's own device time.
    """

    index: int
    timestamp_us: int
    color_jpeg: bytes | None
    depth_mm: np.ndarray | None
    ir: np.ndarray | None
    color_timestamp_us: int | None = None
    depth_timestamp_us: int | None = None
    ir_timestamp_us: int | None = None


class _Truncated(Exception):
    pass


class _Corrupt(Exception):
    pass


def _read_vint(buf: bytes | memoryview, pos: int, end: int, is_id: bool) -> tuple[int, int]:
    """(value, length) of an EBML id (marker kept) or size (marker removed; -1 = unknown)."""
    if pos >= end:
        raise _Truncated(pos)
    first = buf[pos]
    if first == 0:
        raise _Corrupt(f"invalid EBML {'id' if is_id else 'size'} byte 0x00")
    length = 9 - first.bit_length()
    if is_id and length > 4:
        raise _Corrupt(f"invalid EBML id starting with 0x{first:02x}")
    if pos + length > end:
        raise _Truncated(pos)
    value = int.from_bytes(buf[pos:pos + length], "big")
    if is_id:
        return value, length
    value &= (1 << (7 * length)) - 1
    if value == (1 << (7 * length)) - 1:
        return _UNKNOWN_SIZE, length
    return value, length


def _children(buf: bytes | memoryview, start: int, end: int) -> Iterator[tuple[int, int, int]]:
    """(id, data start, data end) of the elements in ``buf[start:end]``; sizes are checked."""
    pos = start
    while pos < end:
        eid, n = _read_vint(buf, pos, end, True)
        size, m = _read_vint(buf, pos + n, end, False)
        data = pos + n + m
        if size == _UNKNOWN_SIZE or data + size > end:
            raise _Corrupt(f"element 0x{eid:x} at offset {pos} overruns its parent")
        yield eid, data, data + size
        pos = data + size


def _as_uint(buf: bytes | memoryview, a: int, b: int) -> int:
    return int.from_bytes(buf[a:b], "big") if b > a else 0


def _as_str(buf: bytes | memoryview, a: int, b: int) -> str:
    return bytes(buf[a:b]).rstrip(b"\x00").decode("utf-8", "replace")


@dataclass
class _Block:
    kind: str
    file_ns: int
    sync_ns: int
    data: bytes
    offset: int


class AzureMkvRecording:
    """An opened k4arecorder recording; iterate it for :class:`KinectCapture` one at a time.

    Each iteration re-opens the file and streams it cluster by cluster (only the few blocks of
    the current capture are in memory). Images that cannot be used are skipped and recorded in
    :attr:`skipped` (reset at the start of each iteration); file-level problems that end the
    iteration early (a truncated file) are also listed in :attr:`warnings`. With
    ``strict=True`` both raise :class:`KinectFormatError` instead.

    Attributes:
        path: the file.
        tags: tag name -> value (the first tag of that name, as the SDK's ``get_tag``).
        tracks: ``COLOR``/``DEPTH``/``IR`` -> :class:`TrackInfo` for the tracks present.
        fps: frames per second (1e9 // DefaultDuration).
        frame_period_ns: DefaultDuration of the video tracks.
        start_offset_ns: ``K4A_START_OFFSET_NS`` (0 if absent).
        serial: ``K4A_DEVICE_SERIAL_NUMBER`` or None.
        depth_mode: e.g. ``NFOV_UNBINNED`` (``OFF`` without depth/IR): the recorded mode.
        depth_binned: the depth and IR images are read binned 2x2 (``depth_binning=2`` on a
            full-resolution recording; :mod:`couch.capture.binning`): captures then hold the
            binned mode's image size and :attr:`calibration` is the binned mode's.
        color_mode: e.g. ``MJPG_720P`` (``OFF`` without colour).
        color_resolution: e.g. ``720P`` (from the COLOR track size) or ``OFF``.
        depth_delay_ns, wired_sync_mode, subordinate_delay_ns: the sync tags (with SDK defaults).
        duration_us: the Info Duration in µs (block time of the last frame), or None.
        streams: the images read: ``COLOR``/``DEPTH``/``IR`` (``open_azure_mkv``'s ``streams``).
    """

    def __init__(self, path: Path, *, strict: bool = False, depth_binning: int = 1,
                 streams: Collection[str] | None = None) -> None:
        if depth_binning not in (1, 2):
            raise ValueError(f"depth_binning must be 1 (as recorded) or 2 (2x2 blocks), got "
                             f"{depth_binning!r}")
        unknown = sorted(set(streams or ()) - set(STREAMS))
        if unknown:
            raise ValueError(f"streams must be among {', '.join(STREAMS)}, got "
                             f"{', '.join(map(repr, unknown))}")
        self.streams = frozenset(STREAMS if streams is None else streams)
        self.path = path
        self.strict = strict
        self.depth_binning = depth_binning
        self.depth_binned = False
        self.skipped: list[SkippedFrame] = []
        self.warnings: list[str] = []
        self.tags: dict[str, str] = {}
        self.tracks: dict[str, TrackInfo] = {}
        self._calibration: KinectCalibration | None = None
        self._calibration_error: str | None = None
        self._parse_header()
        self._header_warnings = list(self.warnings)

    # ---------------------------------------------------------------- properties
    @property
    def calibration(self) -> KinectCalibration:
        """The device calibration for this recording's modes (from ``calibration.json``).

        A camera that is off is described in its full-sensor mode (depth WFOV_UNBINNED, colour
        3072P). Raises :class:`KinectFormatError` if the attachment is missing or invalid.
        """
        if self._calibration is None:
            raise KinectFormatError(self._calibration_error or f"{self.path}: no calibration")
        return self._calibration

    @property
    def has_calibration(self) -> bool:
        return self._calibration is not None

    def __repr__(self) -> str:
        return (f"AzureMkvRecording({str(self.path)!r}, serial={self.serial!r}, "
                f"color_mode={self.color_mode!r}, depth_mode={self.depth_mode!r}, "
                f"fps={self.fps})")

    # ---------------------------------------------------------------- header
    def _fail(self, msg: str) -> KinectFormatError:
        return KinectFormatError(f"{self.path}: {msg}")

    def _parse_header(self) -> None:
        try:
            f = open(self.path, "rb")
        except OSError as exc:
            raise KinectFormatError(f"{self.path}: cannot open: {exc.strerror or exc}") from None
        with f:
            self._file_size = os.fstat(f.fileno()).st_size
            self._parse_elements(f)
        self._interpret()

    def _read_at(self, f: BinaryIO, pos: int, n: int) -> bytes:
        f.seek(pos)
        return f.read(n)

    def _header_at(self, f: BinaryIO, pos: int, end: int) -> tuple[int, int, int]:
        """(id, size or -1, header length) of the element at ``pos``."""
        head = self._read_at(f, pos, 12)
        eid, n = _read_vint(head, 0, min(len(head), end - pos), True)
        size, m = _read_vint(head, n, min(len(head), end - pos), False)
        return eid, size, n + m

    def _parse_elements(self, f: BinaryIO) -> None:
        magic = self._read_at(f, 0, 4)
        if magic != _encode_id(EBML):
            raise self._fail(f"not a Matroska file (starts with {magic.hex() or 'nothing'}, "
                             f"expected the EBML magic 1a45dfa3)")
        size = self._file_size
        try:
            _, hsize, hlen = self._header_at(f, 0, size)
            if hsize == _UNKNOWN_SIZE or hlen + hsize > size:
                raise _Truncated(0)
            head = self._read_at(f, hlen, hsize)
            doc_type = "matroska"
            for eid, a, b in _children(head, 0, len(head)):
                if eid == DOC_TYPE:
                    doc_type = _as_str(head, a, b)
            if doc_type not in ("matroska", "webm"):
                raise self._fail(f"EBML DocType is {doc_type!r}, not matroska")
            pos = hlen + hsize
            while True:  # skip Voids before the Segment
                eid, ssize, slen = self._header_at(f, pos, size)
                if eid == SEGMENT:
                    break
                if eid != VOID or ssize == _UNKNOWN_SIZE:
                    raise self._fail(f"expected a Segment at byte {pos}, found element "
                                     f"0x{eid:x}")
                pos += slen + ssize
        except _Truncated:
            raise self._fail(f"file truncated in the EBML header ({size} bytes)") from None
        except _Corrupt as exc:
            raise self._fail(f"corrupt EBML header: {exc}") from None

        self._segment_start = pos + slen
        self._segment_end = size if ssize == _UNKNOWN_SIZE else self._segment_start + ssize
        self._segment_truncated: str | None = None
        if self._segment_end > size:
            self._segment_truncated = (f"{self.path}: Segment declares {ssize} bytes but the "
                                       f"file ends {self._segment_end - size} bytes early "
                                       f"(truncated)")
            self.warnings.append(self._segment_truncated)
            self._segment_end = size
        self._elements: dict[int, bytes] = {}
        seek_heads: list[bytes] = []
        self._first_cluster: int | None = None
        pos = self._segment_start
        wanted = (INFO, TRACKS, ATTACHMENTS, TAGS)
        try:
            while pos < self._segment_end:
                eid, esize, elen = self._header_at(f, pos, self._segment_end)
                if eid == CLUSTER:
                    self._first_cluster = pos
                    break
                if esize == _UNKNOWN_SIZE:
                    raise _Corrupt(f"element {_TOP_LEVEL_NAMES.get(eid, hex(eid))} at byte {pos} "
                                   f"has an unknown size")
                if pos + elen + esize > self._segment_end:
                    raise self._fail(
                        f"truncated: {_TOP_LEVEL_NAMES.get(eid, f'element 0x{eid:x}')} at byte "
                        f"{pos} declares {esize} bytes but the file ends at byte {size}")
                if eid == SEEK_HEAD:
                    seek_heads.append(self._read_at(f, pos + elen, esize))
                elif eid in wanted and eid not in self._elements:
                    self._elements[eid] = self._read_at(f, pos + elen, esize)
                elif eid not in _TOP_LEVEL:
                    raise _Corrupt(f"unexpected element 0x{eid:x} at byte {pos}")
                pos += elen + esize
        except _Truncated as exc:
            raise self._fail(f"file truncated at byte {size} inside the recording header "
                             f"(element at byte {exc.args[0] if exc.args else pos})") from None
        except _Corrupt as exc:
            raise self._fail(f"corrupt recording header: {exc}") from None

        # Elements after the clusters (e.g. Tags of a remuxed file) are found via the SeekHead.
        for sh in seek_heads:
            try:
                for eid, a, b in _children(sh, 0, len(sh)):
                    if eid != SEEK:
                        continue
                    target, where = None, None
                    for cid, c, d in _children(sh, a, b):
                        if cid == SEEK_ID:
                            target = _as_uint(sh, c, d)
                        elif cid == SEEK_POSITION:
                            where = self._segment_start + _as_uint(sh, c, d)
                    if target in wanted and target not in self._elements and where is not None:
                        teid, tsize, tlen = self._header_at(f, where, self._segment_end)
                        if teid == target and tsize >= 0 and where + tlen + tsize <= size:
                            self._elements[target] = self._read_at(f, where + tlen, tsize)
            except (_Corrupt, _Truncated) as exc:
                self.warnings.append(f"{self.path}: unreadable SeekHead entry ({exc})")

    def _interpret(self) -> None:
        if TRACKS not in self._elements:
            raise self._fail("no Tracks element: not an Azure Kinect recording")
        try:
            self._interpret_info()
            all_tracks = self._interpret_tracks()
            tag_list = self._interpret_tags()
            attachments = self._interpret_attachments()
        except _Corrupt as exc:
            raise self._fail(f"corrupt recording header: {exc}") from None
        except _Truncated:
            raise self._fail("corrupt recording header: an element overruns its parent") from None
        for name, _value, *_ in tag_list:
            self.tags.setdefault(name, _value)

        def find_track(name: str, tag_name: str | None) -> TrackInfo | None:
            uid = 0
            tag = next((t for t in tag_list if t[0] == tag_name), None) if tag_name else None
            if tag is not None:
                _, value, target_type, track_uid, _ = tag
                if target_type == "TRACK":
                    uid = track_uid
                if uid == 0 and value.strip().isdigit():
                    uid = int(value)
            by_name = None
            for t in all_tracks:
                if uid and t.uid == uid:
                    return t
                if t.name == name and by_name is None:
                    by_name = t
            return by_name

        color = find_track("COLOR", "K4A_COLOR_TRACK")
        depth = find_track("DEPTH", "K4A_DEPTH_TRACK")
        ir = find_track("IR", "K4A_IR_TRACK") or find_track("DEPTH_IR", None)
        for name, t in (("COLOR", color), ("DEPTH", depth), ("IR", ir)):
            if t is not None:
                if t.track_type != 1:
                    raise self._fail(f"{name} track (number {t.number}) is not a video track")
                self.tracks[name] = t
        if not self.tracks:
            names = [t.name for t in all_tracks]
            raise self._fail(f"no COLOR, DEPTH or IR track (tracks: {names}); not an Azure "
                             f"Kinect recording")

        # Depth mode, as matroska_read.cpp: the K4A_DEPTH_MODE tag sets the expected size.
        depth_mode = self.tags.get("K4A_DEPTH_MODE")
        if depth_mode is None:
            if depth is not None or ir is not None:
                raise self._fail("K4A_DEPTH_MODE tag is missing but the file has depth/IR tracks")
            depth_mode = "OFF"
        depth_mode = _LEGACY_DEPTH_MODES.get(depth_mode, depth_mode)
        if depth_mode != "OFF" and depth_mode not in DEPTH_MODES:
            raise self._fail(f"unsupported K4A_DEPTH_MODE {depth_mode!r}; expected one of "
                             f"{sorted(DEPTH_MODES)}")
        self.depth_mode = depth_mode
        self.depth_binned = self.depth_binning == 2 and depth_mode in BINNED_MODES
        for name in ("DEPTH", "IR"):
            t = self.tracks.get(name)
            if t is None:
                continue
            mode = DEPTH_MODES[depth_mode]
            if (t.width, t.height) != (mode.width, mode.height):
                raise self._fail(f"{name} track is {t.width}x{t.height} but K4A_DEPTH_MODE "
                                 f"{depth_mode} is {mode.width}x{mode.height}")
            self._check_b16g(name, t)

        self.color_resolution = "OFF"
        self.color_mode = "OFF"
        if color is not None:
            self._check_mjpg(color)
            for res, mode in COLOR_RESOLUTIONS.items():
                if (mode.width, mode.height) == (color.width, color.height):
                    self.color_resolution = res
            if self.color_resolution == "OFF":
                self.warnings.append(f"{self.path}: colour size {color.width}x{color.height} is "
                                     f"not an Azure Kinect mode; no colour calibration")
            self.color_mode = self.tags.get("K4A_COLOR_MODE", f"MJPG_{color.height}P")

        periods = {n: t.default_duration_ns for n, t in self.tracks.items()}
        nonzero = {p for p in periods.values() if p}
        if len(nonzero) > 1:
            raise self._fail(f"video tracks have different frame periods (DefaultDuration ns): "
                             f"{periods}")
        if nonzero:
            self.frame_period_ns = nonzero.pop()
        else:
            self.frame_period_ns = 1_000_000_000 // 30
            self.warnings.append(f"{self.path}: no DefaultDuration; assuming 30 fps")
        self.fps = 1_000_000_000 // self.frame_period_ns

        def int_tag(name: str, default: int) -> int:
            value = self.tags.get(name)
            if value is None:
                return default
            try:
                return int(value)
            except ValueError:
                raise self._fail(f"tag {name} has an invalid value {value!r}") from None

        self.start_offset_ns = int_tag("K4A_START_OFFSET_NS", 0)
        self.depth_delay_ns = int_tag("K4A_DEPTH_DELAY_NS", 0)
        self.wired_sync_mode = self.tags.get("K4A_WIRED_SYNC_MODE", "STANDALONE")
        if self.wired_sync_mode not in _SYNC_MODES:
            raise self._fail(f"unsupported K4A_WIRED_SYNC_MODE {self.wired_sync_mode!r}")
        self.subordinate_delay_ns = (int_tag("K4A_SUBORDINATE_DELAY_NS", 0)
                                     if self.wired_sync_mode == "SUBORDINATE" else 0)
        self.serial = self.tags.get("K4A_DEVICE_SERIAL_NUMBER")

        # Calibration: by the K4A_CALIBRATION_FILE tag's attachment UID, else by file name.
        data = None
        cal_tag = next((t for t in tag_list if t[0] == "K4A_CALIBRATION_FILE"), None)
        if cal_tag is not None and cal_tag[2] == "ATTACHMENT":
            data = next((a[2] for a in attachments if a[1] == cal_tag[4]), None)
        if data is None:
            data = next((a[2] for a in attachments if a[0] == "calibration.json"), None)
        if data is None:
            self._calibration_error = (
                f"{self.path}: no calibration.json attachment (found attachments "
                f"{[a[0] for a in attachments]}); the device calibration is needed for "
                f"intrinsics and extrinsics")
        else:
            cal_depth = "WFOV_UNBINNED" if self.depth_mode == "OFF" else self.depth_mode
            if self.depth_binned:
                cal_depth = BINNED_MODES[cal_depth]
            cal_color = "3072P" if self.color_resolution == "OFF" else self.color_resolution
            try:
                self._calibration = KinectCalibration.from_json(
                    data, cal_depth, cal_color, source=f"{self.path} (calibration.json)")
            except ValueError as exc:
                self._calibration_error = str(exc)

    def _check_b16g(self, name: str, t: TrackInfo) -> None:
        if t.codec_id != _VFW or len(t.codec_private) != 40:
            raise self._fail(f"{name} track has codec {t.codec_id!r} with "
                             f"{len(t.codec_private)}-byte CodecPrivate; expected {_VFW} with a "
                             f"40-byte BITMAPINFOHEADER")
        if t.fourcc != "b16g":
            hint = (" (biCompression 0: written by FFmpeg with allow_raw_vfw, not by k4arecorder)"
                    if t.fourcc == "\x00\x00\x00\x00" else "")
            raise self._fail(f"{name} track FourCC is {t.fourcc!r}; expected 'b16g' (16-bit "
                             f"big-endian grayscale){hint}")

    def _check_mjpg(self, t: TrackInfo) -> None:
        if t.codec_id == "V_MJPEG":
            return  # not what k4arecorder writes, but the same frames (e.g. a remuxed file)
        if t.codec_id != _VFW or len(t.codec_private) != 40:
            raise self._fail(f"COLOR track has codec {t.codec_id!r}; expected {_VFW} (MJPG)")
        if t.fourcc != "MJPG":
            raise self._fail(f"COLOR track format is {t.fourcc!r}; only MJPG colour recordings "
                             f"are supported (record with k4arecorder -c 720p/1080p/...)")

    def _interpret_info(self) -> None:
        buf = self._elements.get(INFO, b"")
        self.timecode_scale_ns = 1_000_000  # Matroska's default
        self.duration_us: int | None = None
        duration = None
        for eid, a, b in _children(buf, 0, len(buf)):
            if eid == TIMECODE_SCALE:
                self.timecode_scale_ns = _as_uint(buf, a, b) or 1_000_000
            elif eid == DURATION and b - a in (4, 8):
                duration = struct.unpack(">f" if b - a == 4 else ">d", buf[a:b])[0]
        if duration is not None:
            self.duration_us = round(duration * self.timecode_scale_ns / 1000)

    def _interpret_tracks(self) -> list[TrackInfo]:
        buf = self._elements[TRACKS]
        tracks = []
        for eid, a, b in _children(buf, 0, len(buf)):
            if eid != TRACK_ENTRY:
                continue
            t = TrackInfo(number=0, uid=0, name="", codec_id="", track_type=0)
            for cid, c, d in _children(buf, a, b):
                if cid == TRACK_NUMBER:
                    t.number = _as_uint(buf, c, d)
                elif cid == TRACK_UID:
                    t.uid = _as_uint(buf, c, d)
                elif cid == NAME:
                    t.name = _as_str(buf, c, d)
                elif cid == CODEC_ID:
                    t.codec_id = _as_str(buf, c, d)
                elif cid == TRACK_TYPE:
                    t.track_type = _as_uint(buf, c, d)
                elif cid == CODEC_PRIVATE:
                    t.codec_private = bytes(buf[c:d])
                elif cid == DEFAULT_DURATION:
                    t.default_duration_ns = _as_uint(buf, c, d)
                elif cid == VIDEO:
                    for vid, e, g in _children(buf, c, d):
                        if vid == PIXEL_WIDTH:
                            t.width = _as_uint(buf, e, g)
                        elif vid == PIXEL_HEIGHT:
                            t.height = _as_uint(buf, e, g)
            if t.codec_id == _VFW and len(t.codec_private) >= 20:
                t.fourcc = t.codec_private[16:20].decode("latin-1")
            tracks.append(t)
        return tracks

    def _interpret_tags(self) -> list[tuple[str, str, str | None, int, int]]:
        """(name, value, target type, track uid, attachment uid) in file order."""
        buf = self._elements.get(TAGS, b"")
        out = []
        for eid, a, b in _children(buf, 0, len(buf)):
            if eid != TAG:
                continue
            target_type, track_uid, att_uid = None, 0, 0
            simple = []
            for cid, c, d in _children(buf, a, b):
                if cid == TARGETS:
                    for tid, e, g in _children(buf, c, d):
                        if tid == TARGET_TYPE:
                            target_type = _as_str(buf, e, g)
                        elif tid == TAG_TRACK_UID:
                            track_uid = _as_uint(buf, e, g)
                        elif tid == TAG_ATTACHMENT_UID:
                            att_uid = _as_uint(buf, e, g)
                elif cid == SIMPLE_TAG:
                    name, value = None, ""
                    for sid, e, g in _children(buf, c, d):
                        if sid == TAG_NAME:
                            name = _as_str(buf, e, g)
                        elif sid == TAG_STRING:
                            value = _as_str(buf, e, g)
                    if name is not None:
                        simple.append((name, value))
            out.extend((n, v, target_type, track_uid, att_uid) for n, v in simple)
        return out

    def _interpret_attachments(self) -> list[tuple[str, int, bytes]]:
        """(file name, uid, data) of each attachment."""
        buf = self._elements.get(ATTACHMENTS, b"")
        out = []
        for eid, a, b in _children(buf, 0, len(buf)):
            if eid != ATTACHED_FILE:
                continue
            name, uid, data = "", 0, b""
            for cid, c, d in _children(buf, a, b):
                if cid == FILE_NAME:
                    name = _as_str(buf, c, d)
                elif cid == FILE_UID:
                    uid = _as_uint(buf, c, d)
                elif cid == FILE_DATA:
                    data = bytes(buf[c:d])
            out.append((name, uid, data))
        return out

    # ---------------------------------------------------------------- streaming
    def _skip(self, capture_index: int | None, track: str, timestamp_us: int | None,
              offset: int, reason: str) -> None:
        msg = (f"{self.path}: {track} frame"
               f"{'' if capture_index is None else f' of capture {capture_index}'}"
               f"{'' if timestamp_us is None else f' at {timestamp_us} µs'} (byte {offset}): "
               f"{reason}")
        if self.strict:
            raise KinectFormatError(msg)
        log.warning("skipped %s", msg)
        self.skipped.append(SkippedFrame(capture_index, track, timestamp_us, offset, reason))

    def _warn(self, msg: str) -> None:
        if self.strict:
            raise KinectFormatError(f"{self.path}: {msg}")
        log.warning("%s: %s", self.path, msg)
        self.warnings.append(f"{self.path}: {msg}")

    def _device_us(self, file_ns: int) -> int:
        return file_ns // 1000 + self.start_offset_ns // 1000

    def _iter_blocks(self, f: BinaryIO) -> Iterator[_Block]:
        """Blocks of the COLOR/DEPTH/IR tracks in file order, cluster by cluster."""
        kinds = {t.number: name for name, t in self.tracks.items()}
        delay = self.depth_delay_ns
        sync_delay = {"COLOR": max(delay, 0), "DEPTH": max(-delay, 0), "IR": max(-delay, 0)}
        size, end = self._file_size, self._segment_end
        pos = self._first_cluster if self._first_cluster is not None else end
        while pos < end:
            try:
                eid, esize, elen = self._header_at(f, pos, end)
            except _Truncated:
                self._warn(f"file truncated at byte {size} (inside an element header at byte "
                           f"{pos}); the rest of the recording is missing")
                return
            except _Corrupt as exc:
                pos = self._resync(f, pos, f"corrupt element at byte {pos}: {exc}")
                continue
            if eid != CLUSTER:
                if eid not in _TOP_LEVEL:
                    pos = self._resync(f, pos, f"unexpected element 0x{eid:x} at byte {pos}")
                    continue
                if esize == _UNKNOWN_SIZE:
                    self._warn(f"{_TOP_LEVEL_NAMES[eid]} at byte {pos} has an unknown size; "
                               f"stopping")
                    return
                pos += elen + esize
                continue
            data_start = pos + elen
            truncated = False
            if esize == _UNKNOWN_SIZE:
                cend = self._unknown_cluster_end(f, data_start, end)
            else:
                cend = data_start + esize
                if cend > size:
                    truncated, cend = True, size
            buf = self._read_at(f, data_start, cend - data_start)
            yield from self._cluster_blocks(buf, data_start, kinds, sync_delay, truncated)
            if truncated:
                self._warn(f"file truncated: cluster at byte {pos} declares {esize} bytes but the "
                           f"file ends at byte {size}; frames after that are missing")
                return
            pos = cend
        if self._segment_truncated is not None and self.strict:
            # Cut at an element boundary: nothing is cut off mid-block, but what followed (more
            # clusters, or only the Cues) is gone. Listed in warnings at open; strict raises.
            raise KinectFormatError(f"{self._segment_truncated}; no data after byte {size}")

    def _unknown_cluster_end(self, f: BinaryIO, pos: int, end: int) -> int:
        """End of an unknown-size cluster: where the next top-level element starts."""
        while pos < end:
            try:
                eid, esize, elen = self._header_at(f, pos, end)
            except (_Truncated, _Corrupt):
                return end
            if (eid in _TOP_LEVEL and eid not in (VOID, CRC32)) or esize == _UNKNOWN_SIZE:
                return pos
            pos += elen + esize
        return min(pos, end)

    def _resync(self, f: BinaryIO, pos: int, reason: str) -> int:
        """Skip corrupt bytes: continue at the next Cluster id after ``pos``."""
        magic = _encode_id(CLUSTER)
        search = pos + 1
        chunk = 1 << 20
        while search < self._segment_end:
            data = self._read_at(f, search, chunk + 3)
            i = data.find(magic)
            if i >= 0:
                self._skip(None, "ALL", None, pos, f"{reason}; skipped {search + i - pos} bytes "
                           f"to the next cluster")
                return search + i
            if len(data) < chunk + 3:
                break
            search += chunk
        self._skip(None, "ALL", None, pos, f"{reason}; no further cluster, stopping")
        return self._segment_end

    def _cluster_blocks(self, buf: bytes, base: int, kinds: dict[int, str],
                        sync_delay: dict[str, int], truncated: bool) -> Iterator[_Block]:
        cluster_tc = None
        scale = self.timecode_scale_ns
        view = memoryview(buf)
        pos, end = 0, len(buf)
        crc = None
        while pos < end:
            try:
                eid, n = _read_vint(view, pos, end, True)
                esize, m = _read_vint(view, pos + n, end, False)
            except _Truncated:
                break  # truncated mid-header: reported by the caller
            except _Corrupt as exc:
                self._skip(None, "ALL", None, base + pos, f"corrupt cluster content ({exc}); "
                           f"rest of the cluster skipped")
                return
            a = pos + n + m
            b = a + esize
            if esize == _UNKNOWN_SIZE or b > end:
                if not truncated:
                    self._skip(None, "ALL", None, base + pos, "element overruns its cluster; rest "
                               "of the cluster skipped")
                elif eid in (SIMPLE_BLOCK, BLOCK_GROUP):
                    self._skip(None, "ALL", None, base + pos, "block cut off by the end of the "
                               "file")
                return
            if eid == CRC32 and pos == 0 and esize == 4 and not truncated:
                crc = int.from_bytes(view[a:b], "little")
                if zlib.crc32(view[b:end]) != crc:
                    self._warn(f"CRC-32 mismatch in the cluster at byte {base}: its data may be "
                               f"damaged")
            elif eid == TIMECODE:
                cluster_tc = _as_uint(view, a, b)
            elif eid in (SIMPLE_BLOCK, BLOCK_GROUP):
                ba, bb = a, b
                if eid == BLOCK_GROUP:
                    ba = bb = None
                    try:
                        for cid, c, d in _children(view, a, b):
                            if cid == BLOCK:
                                ba, bb = c, d
                    except (_Corrupt, _Truncated):
                        ba = None
                    if ba is None:
                        pos = b
                        continue
                block = self._parse_block(view, ba, bb, base, cluster_tc, scale, kinds,
                                          sync_delay)
                if block is not None:
                    yield block
            pos = b

    def _parse_block(self, view: memoryview, a: int, b: int, base: int, cluster_tc: int | None,
                     scale: int, kinds: dict[int, str], sync_delay: dict[str, int],
                     ) -> _Block | None:
        try:
            number, n = _read_vint(view, a, b, False)
        except (_Corrupt, _Truncated):
            self._skip(None, "ALL", None, base + a, "unreadable block header")
            return None
        kind = kinds.get(number)
        if kind is None:
            return None  # IMU or custom track
        if a + n + 3 > b:
            self._skip(None, kind, None, base + a, "block shorter than its header")
            return None
        if cluster_tc is None:
            self._skip(None, kind, None, base + a, "block before its cluster's Timecode")
            return None
        rel, flags = struct.unpack_from(">hB", view, a + n)
        file_ns = (cluster_tc + rel) * scale
        if flags & 0x06:
            self._skip(None, kind, self._device_us(file_ns), base + a,
                       "laced block (k4arecorder writes one frame per block)")
            return None
        # an image not read pairs by its time alone: its bytes are neither copied nor checked
        data = bytes(view[a + n + 3:b]) if kind in self.streams else b""
        return _Block(kind, file_ns, file_ns + sync_delay[kind], data, base + a)

    def __iter__(self) -> Iterator[KinectCapture]:
        self.skipped = []
        self.warnings = list(self._header_warnings)
        try:
            f = open(self.path, "rb")
        except OSError as exc:
            raise KinectFormatError(f"{self.path}: cannot open: {exc.strerror or exc}") from None
        with f:
            yield from self._pair(self._iter_blocks(f))

    def _pair(self, blocks: Iterator[_Block]) -> Iterator[KinectCapture]:
        """The SDK's ``get_capture`` pairing, streaming: the next block of every track whose
        sync time is within half a frame period of the earliest forms one capture."""
        half = self.frame_period_ns // 2
        queues: dict[str, deque[_Block]] = {k: deque() for k in self.tracks}
        exhausted = False
        newest = -1
        index = 0
        while True:
            while not exhausted:
                heads = [q[0].sync_ns for q in queues.values() if q]
                if len(heads) == len(queues) or (heads and newest > min(heads) + half):
                    break
                block = next(blocks, None)
                if block is None:
                    exhausted = True
                    break
                newest = max(newest, block.file_ns)
                queues[block.kind].append(block)
            heads = [q[0].sync_ns for q in queues.values() if q]
            if not heads:
                return
            start = min(heads)
            chosen = {k: q.popleft() for k, q in queues.items()
                      if q and q[0].sync_ns - start < half}
            capture = self._make_capture(index, chosen)
            index += 1
            if capture is not None:
                yield capture

    def _make_capture(self, index: int, chosen: dict[str, _Block]) -> KinectCapture | None:
        images: dict[str, Any] = {}
        stamps: dict[str, int] = {}
        unread = False
        for kind, block in chosen.items():
            ts = self._device_us(block.file_ns)
            stamps[kind] = ts
            if kind not in self.streams:
                unread = True
                continue
            if kind == "COLOR":
                if len(block.data) < 4 or block.data[:2] != b"\xff\xd8":
                    self._skip(index, kind, ts, block.offset,
                               f"not a JPEG frame ({len(block.data)} bytes, no SOI marker)")
                    continue
                images[kind] = block.data
            else:
                t = self.tracks[kind]
                expected = t.width * t.height * 2
                if len(block.data) != expected:
                    self._skip(index, kind, ts, block.offset,
                               f"expected {expected} bytes ({t.width}x{t.height} uint16), got "
                               f"{len(block.data)}")
                    continue
                images[kind] = (np.frombuffer(block.data, dtype=">u2")
                                .reshape(t.height, t.width).astype(np.uint16))
                if self.depth_binned:
                    images[kind] = (bin_depth if kind == "DEPTH" else bin_ir)(images[kind])
        if not images and not unread:
            return None
        if "DEPTH" in stamps:
            timestamp = stamps["DEPTH"]
        elif "IR" in stamps:
            timestamp = stamps["IR"]
        else:
            timestamp = stamps["COLOR"] + self.depth_delay_ns // 1000
        return KinectCapture(
            index=index, timestamp_us=timestamp, color_jpeg=images.get("COLOR"),
            depth_mm=images.get("DEPTH"), ir=images.get("IR"),
            color_timestamp_us=stamps["COLOR"] if "COLOR" in images else None,
            depth_timestamp_us=stamps["DEPTH"] if "DEPTH" in images else None,
            ir_timestamp_us=stamps["IR"] if "IR" in images else None)


def open_azure_mkv(path: str | os.PathLike, *, require_calibration: bool = True,
                   strict: bool = False, depth_binning: int = 1,
                   streams: Collection[str] | None = None) -> AzureMkvRecording:
    """Open a k4arecorder ``.mkv`` for streaming.

    Reads the header (tracks, tags, calibration attachment) now; frames are read when the
    returned recording is iterated.

    Args:
        path: the recording.
        require_calibration: raise now if ``calibration.json`` is missing or invalid (otherwise
            only accessing ``.calibration`` raises).
        strict: raise on the first unusable frame instead of skipping and counting it.
        depth_binning: 2: read a full-resolution recording's depth and IR binned 2x2, with the
            binned mode's calibration (:mod:`couch.capture.binning`); a binned or depth-less
            recording is read as it is. 1: as recorded.
        streams: the images to read, among ``COLOR``, ``DEPTH`` and ``IR``; None: all. The
            others' blocks still pair into captures, so the captures, their indices and time
            stamps are those of reading everything, with None for the images not read (whose
            bytes are neither copied, decoded nor checked). Depth-only work on a real recording
            (``("DEPTH",)``) then skips its IR, which k4arecorder always records, and its colour.

    Raises:
        KinectFormatError: not Matroska, truncated or corrupt header, no Azure Kinect tracks,
            unsupported track format, missing/invalid calibration (``require_calibration``).
        ValueError: ``depth_binning`` not 1 or 2; a stream name not among the three.
    """
    rec = AzureMkvRecording(Path(path), strict=strict, depth_binning=depth_binning,
                            streams=streams)
    if require_calibration and not rec.has_calibration:
        raise KinectFormatError(rec._calibration_error or f"{path}: no calibration")
    return rec


def decode_color(jpeg: bytes, *, source: str | None = None) -> np.ndarray:
    """Decode one MJPEG colour frame into a (H,W,3) uint8 **RGB** image.

    Args:
        jpeg: the frame bytes (``KinectCapture.color_jpeg``).
        source: where the frame came from (file, capture), for the error message.

    Raises:
        KinectFormatError: the bytes are not a complete JPEG or OpenCV cannot decode them.
    """
    where = f" ({source})" if source else ""
    if jpeg is None or len(jpeg) < 4 or bytes(jpeg[:2]) != b"\xff\xd8":
        raise KinectFormatError(f"colour frame{where} is not a JPEG (no SOI marker FFD8)")
    # 0xFFD9 cannot occur inside entropy-coded data (0xFF is stuffed there), so a frame that does
    # not end with EOI was cut off; OpenCV would silently decode the rest as grey.
    if not bytes(jpeg[-64:]).rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise KinectFormatError(f"colour frame{where} is truncated (no EOI marker FFD9 at its "
                                f"end, {len(jpeg)} bytes)")
    bgr = cv2.imdecode(np.frombuffer(jpeg, dtype=np.uint8), cv2.IMREAD_COLOR)
    if bgr is None or bgr.ndim != 3:
        raise KinectFormatError(f"colour frame{where} could not be decoded as JPEG "
                                f"({len(jpeg)} bytes)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
