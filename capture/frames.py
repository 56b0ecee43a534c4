"""One streaming interface to a Kinect camera's frames, whatever the recording format.

A camera's frames come either from an Azure Kinect recording (k4arecorder ``.mkv``, read by
:mod:`couch.capture.azure_mkv`) or from one camera of a BEHAVE-style sequence folder
(``info.json`` + ``t%04d.%03d/k<k>.color.jpg``/``k<k>.depth.png``, read by
:mod:`couch.capture.behave`). This module puts one iterator in front of both readers; all parsing
stays in them.

Public API
----------
* :func:`open_kinect_stream` ``(path, *, serial=None, kinect=None, strict=False,
  require_calibration=True)`` -> :class:`KinectStream`; iterate it for :class:`KinectFrame`, one
  frame in memory at a time (every iteration streams the source afresh).
* :class:`KinectStream` — ``calibration`` (:class:`KinectCalibration`), ``serial``, ``fps``,
  ``kind`` (``"mkv"``/``"behave"``), ``depth_grid``, ``has_color``, ``skipped``
  (:class:`FrameSkip`), ``warnings``, ``reader`` (the underlying
  :class:`AzureMkvRecording`/:class:`BehaveSequence`).
* :class:`KinectFrame` — one frame; :meth:`KinectFrame.color_rgb` decodes its colour on demand
  (None without one), :meth:`KinectFrame.require_color` raises instead.
* :class:`FrameSkip` — an image (or a stretch of a file) that could not be used, and why.

Units and frames
----------------
* ``timestamp_us`` (int, µs): for an MKV the device clock of the depth exposure
  (:attr:`KinectCapture.timestamp_us`, colour-only captures use the colour time + the depth
  delay); for BEHAVE the frame folder's time (``t0003.033`` -> 3 033 000 µs), the sequence clock.
* ``depth_mm``: (H,W) uint16 millimetres of Z along the camera axis, 0 = invalid. **Which pixel
  grid** depends on the source and is given by ``depth_grid``: ``"depth"`` for an MKV (the depth
  camera's own pixels, ``calibration.depth``: 640x576 NFOV_UNBINNED, 320x288 NFOV_2X2BINNED, ...),
  ``"color"`` for BEHAVE (registered to the colour image, ``calibration.color`` size, as BEHAVE
  stores it).
* ``ir``: (H,W) uint16 raw IR intensity in the depth grid (MKV only; None for BEHAVE).
* colour: (H,W,3) uint8 **RGB** in the colour camera's pixels (``calibration.color``), decoded
  from the stored JPEG/PNG only when :meth:`KinectFrame.color_rgb` is called;
  ``color_data`` holds the encoded bytes. A depth-only MKV (``k4arecorder --color-mode OFF``,
  ``couch-simulate --no-color``) has no COLOR track: :attr:`KinectStream.has_color` is False,
  every frame's ``color_data`` is None and :meth:`KinectFrame.color_rgb` returns None (nothing
  is counted as skipped: there was no colour to lose); :meth:`KinectFrame.require_color`
  raises instead, naming the recording. Its ``calibration.color`` is then the calibration
  file's full-resolution (3072P) colour camera, as the reader has no colour mode to specialise
  it to.

Bad input
---------
Everything that makes the source unreadable raises :class:`KinectFormatError` (a ``ValueError``)
naming the file and what was wrong, when opening (not a Matroska file, header cut off, missing
calibration attachment with ``require_calibration``, BEHAVE ``info.json``/calibration missing)
or while iterating (an inconsistent BEHAVE sequence; BEHAVE's :class:`BehaveFormatError` is
re-raised as :class:`KinectFormatError`, chained). What leaves the rest usable is skipped and
counted in :attr:`KinectStream.skipped` (reset when an iteration starts) and file-level problems
in :attr:`KinectStream.warnings`: an image of the wrong size, a frame that is not a JPEG, a file
cut mid-cluster (the frames before the cut are delivered), damaged bytes skipped to the next
cluster, a missing or truncated BEHAVE image; and a colour frame whose JPEG/PNG fails to decode
(recorded when :meth:`KinectFrame.color_rgb` finds it, which then returns None).
``strict=True`` raises :class:`KinectFormatError` for all of those instead.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Callable, Collection, Iterator
from pathlib import Path

import numpy as np

from .azure_calibration import KinectCalibration
from .azure_mkv import AzureMkvRecording, KinectFormatError, decode_color, open_azure_mkv
from .behave import BehaveFormatError, BehaveSequence, BehaveSkip, open_behave_sequence

__all__ = [
    "FrameSkip",
    "KinectFrame",
    "KinectStream",
    "open_kinect_stream",
]

log = logging.getLogger(__name__)

#: Frame rates a BEHAVE sequence's frame spacing is snapped to (the Azure Kinect's rates).
_KINECT_RATES = (5.0, 15.0, 30.0)


@dataclasses.dataclass(frozen=True)
class FrameSkip:
    """Something a stream could not use.

    Attributes:
        index: the frame's index (:attr:`KinectFrame.index`), or None for a stretch of a file or
            a folder that is not a frame.
        stream: ``COLOR``, ``DEPTH``, ``IR``, or ``ALL`` (a whole frame or a stretch of a file).
        timestamp_us: the frame's time if known (µs, as :attr:`KinectFrame.timestamp_us`).
        where: the file and byte offset (MKV) or the image/folder path (BEHAVE).
        reason: what was wrong.
    """

    index: int | None
    stream: str
    timestamp_us: int | None
    where: str
    reason: str

    def __str__(self) -> str:
        frame = "" if self.index is None else f" frame {self.index}"
        return f"{self.where}: {self.stream}{frame}: {self.reason}"


@dataclasses.dataclass(eq=False)
class KinectFrame:
    """One frame of one Kinect camera (see the module doc for units and pixel grids).

    Attributes:
        index: ordinal of the frame in its source, 0-based (MKV capture index, BEHAVE position
            in the sorted frame folders); frames that were skipped keep their number, so
            indices may have gaps.
        timestamp_us: µs; MKV device clock of the depth exposure, BEHAVE folder time.
        depth_mm: (H,W) uint16 millimetres, 0 = invalid, in the ``depth_grid`` camera's pixels;
            None if this frame has no usable depth.
        ir: (H,W) uint16 IR in the depth camera's pixels, or None (always None for BEHAVE).
        color_data: the encoded colour image (MJPEG frame, or BEHAVE's JPEG/PNG file), or None.
        color_timestamp_us: the colour image's own time in µs (MKV), or None.
        depth_grid: ``"depth"`` (MKV) or ``"color"`` (BEHAVE: depth registered to colour).
        source: where the frame came from, for messages (``cam.mkv capture 3``, a frame folder).
    """

    index: int
    timestamp_us: int
    depth_mm: np.ndarray | None
    ir: np.ndarray | None = None
    color_data: bytes | None = None
    color_timestamp_us: int | None = None
    depth_grid: str = "depth"
    source: str = ""
    _decoder: Callable[[], np.ndarray] | None = dataclasses.field(default=None, repr=False)
    _report: Callable[[KinectFrame, str], None] | None = dataclasses.field(default=None,
                                                                           repr=False)
    _stream_has_color: bool = dataclasses.field(default=True, repr=False)
    _color_unread: bool = dataclasses.field(default=False, repr=False)
    _rgb: np.ndarray | None = dataclasses.field(default=None, init=False, repr=False)
    _color_error: str | None = dataclasses.field(default=None, init=False, repr=False)

    @property
    def has_color(self) -> bool:
        """Whether the frame carries a colour image (it may still fail to decode)."""
        return self.color_data is not None

    def require_color(self) -> np.ndarray:
        """The colour image as (H,W,3) uint8 RGB, like :meth:`color_rgb`, for callers that
        cannot go on without it.

        Raises:
            KinectFormatError: the frame has no colour image (naming the source, and saying
                when the whole recording has no COLOR track), or it cannot be decoded.
        """
        rgb = self.color_rgb()
        if rgb is not None:
            return rgb
        if self._color_error is not None:
            raise KinectFormatError(self._color_error)
        if not self._stream_has_color:
            raise KinectFormatError(f"{self.source}: no colour: the recording has no COLOR "
                                    f"track (recorded depth-only, colour mode OFF)")
        if self._color_unread:
            raise KinectFormatError(f"{self.source}: colour not read (the stream was opened "
                                    f"with streams that leave COLOR out)")
        raise KinectFormatError(f"{self.source}: no colour image in this frame (dropped)")

    @property
    def color_error(self) -> str | None:
        """Why :meth:`color_rgb` returned None for a frame with colour data (after a call)."""
        return self._color_error

    def color_rgb(self) -> np.ndarray | None:
        """The colour image as (H,W,3) uint8 RGB, decoded on the first call and kept.

        Returns None if the frame has no colour image, or if it cannot be decoded: that is
        counted in the stream's :attr:`KinectStream.skipped` (once) and the reason kept in
        :attr:`color_error`.

        Raises:
            KinectFormatError: the colour cannot be decoded and the stream is ``strict``.
        """
        if self._rgb is not None:
            return self._rgb
        if self.color_data is None or self._color_error is not None:
            return None
        try:
            if self._decoder is not None:
                rgb = self._decoder()
            else:
                rgb = decode_color(self.color_data, source=self.source or None)
        except (KinectFormatError, BehaveFormatError) as exc:
            self._color_error = str(exc)
            if self._report is not None:
                self._report(self, str(exc))
            return None
        self._rgb = rgb
        return rgb


class KinectStream:
    """One Kinect camera's frames; iterate it for :class:`KinectFrame` (see the module doc).

    Each iteration streams the source from the start, one frame in memory at a time, and resets
    :attr:`skipped` and :attr:`warnings`. Open it with :func:`open_kinect_stream`.

    Attributes:
        path: the ``.mkv`` file or the BEHAVE sequence folder.
        kind: ``"mkv"`` or ``"behave"``.
        serial: the device serial (MKV ``K4A_DEVICE_SERIAL_NUMBER``, else the calibration's,
            else the file stem; BEHAVE ``calibration.json`` ``serial``, else ``k<k>``).
        kinect: BEHAVE camera file id (``k0`` -> 0); None for an MKV.
        fps: frames per second (MKV: from the tracks' DefaultDuration; BEHAVE: from the frame
            folders' spacing, snapped to 5/15/30 when within 10 %).
        depth_grid: ``"depth"`` (MKV) or ``"color"`` (BEHAVE), see :class:`KinectFrame`.
        has_color: whether the source records colour at all (False: an MKV without a COLOR
            track; its frames have no colour). A BEHAVE sequence always has colour.
        reader: the :class:`AzureMkvRecording` or :class:`BehaveSequence` underneath.
    """

    def __init__(self, path: Path, reader: AzureMkvRecording | BehaveSequence, *,
                 kinect: int | None, strict: bool) -> None:
        self.path = path
        self.reader = reader
        self.kinect = kinect
        self.strict = strict
        self._color_skips: list[FrameSkip] = []
        self._extra_warnings: list[str] = []
        if isinstance(reader, AzureMkvRecording):
            self.kind = "mkv"
            self.depth_grid = "depth"
            self.has_color = "COLOR" in reader.tracks
            self.fps = float(reader.fps)
            serial = reader.serial or (reader.calibration.serial if reader.has_calibration
                                       else None)
            self.serial = serial or path.stem
        else:
            assert kinect is not None
            self.kind = "behave"
            self.depth_grid = "color"
            self.has_color = True
            self.serial = reader.calibrations[kinect].serial or f"k{kinect}"
            self.fps = self._behave_fps(reader)

    def _behave_fps(self, seq: BehaveSequence) -> float:
        times = seq.frame_times
        steps = np.diff(times)
        steps = steps[steps > 0]
        if steps.size == 0:
            self._extra_warnings.append(f"{self.path}: fewer than two frames, frame rate "
                                        f"unknown; assuming 30 fps")
            return 30.0
        period = float(np.median(steps))
        for rate in _KINECT_RATES:
            if abs(period * rate - 1.0) < 0.1:
                return rate
        return round(1.0 / period, 3)

    # ---------------------------------------------------------------- properties
    @property
    def calibration(self) -> KinectCalibration:
        """The camera's calibration, made specific to the recording's modes.

        Raises:
            KinectFormatError: an MKV opened with ``require_calibration=False`` has none.
        """
        if isinstance(self.reader, AzureMkvRecording):
            return self.reader.calibration
        assert self.kinect is not None
        return self.reader.calibrations[self.kinect]

    @property
    def skipped(self) -> list[FrameSkip]:
        """What the current (or last) iteration could not use: the reader's skips in file
        order, then the colour frames that failed to decode."""
        if isinstance(self.reader, AzureMkvRecording):
            out = [FrameSkip(s.capture_index, s.track, s.timestamp_us,
                             f"{self.path} byte {s.byte_offset}", s.reason)
                   for s in self.reader.skipped]
        else:
            out = [self._behave_skip(s) for s in self.reader.skipped]
        return out + self._color_skips

    @property
    def warnings(self) -> list[str]:
        """File-level remarks of the current (or last) iteration, e.g. a truncated file."""
        return [*self._extra_warnings, *self.reader.warnings]

    def _behave_skip(self, skip: BehaveSkip) -> FrameSkip:
        seq = self.reader
        assert isinstance(seq, BehaveSequence)
        index = ts = None
        if skip.frame is not None:
            index = seq.frame_names.index(skip.frame)
            ts = _us(float(seq.frame_times[index]))
        name = skip.path.name
        stream = "COLOR" if ".color." in name else "DEPTH" if ".depth." in name else "ALL"
        return FrameSkip(index, stream, ts, str(skip.path), skip.reason)

    def __repr__(self) -> str:
        where = "" if self.kinect is None else f", kinect={self.kinect}"
        return (f"KinectStream({str(self.path)!r}, kind={self.kind!r}, serial={self.serial!r}"
                f"{where}, fps={self.fps:g})")

    # ---------------------------------------------------------------- iteration
    def _color_failed(self, frame: KinectFrame, reason: str) -> None:
        if self.strict:
            raise KinectFormatError(reason)
        log.warning("skipped colour of %s: %s", frame.source, reason)
        self._color_skips.append(FrameSkip(frame.index, "COLOR", frame.color_timestamp_us
                                           or frame.timestamp_us, frame.source, reason))

    def __iter__(self) -> Iterator[KinectFrame]:
        self._color_skips = []
        if isinstance(self.reader, AzureMkvRecording):
            return self._iter_mkv(self.reader)
        return self._iter_behave(self.reader)

    def _iter_mkv(self, rec: AzureMkvRecording) -> Iterator[KinectFrame]:
        for cap in rec:
            # no _decoder: KinectFrame decodes MJPEG with decode_color, naming ``source``
            yield KinectFrame(index=cap.index, timestamp_us=cap.timestamp_us,
                              depth_mm=cap.depth_mm, ir=cap.ir, color_data=cap.color_jpeg,
                              color_timestamp_us=cap.color_timestamp_us, depth_grid="depth",
                              source=f"{self.path} capture {cap.index}",
                              _report=self._color_failed, _stream_has_color=self.has_color,
                              _color_unread="COLOR" not in rec.streams)

    def _iter_behave(self, seq: BehaveSequence) -> Iterator[KinectFrame]:
        assert self.kinect is not None
        frames = seq.iter_camera(self.kinect)
        while True:
            try:
                cam = next(frames, None)
            except BehaveFormatError as exc:
                raise KinectFormatError(str(exc)) from exc
            if cam is None:
                return
            ts = _us(cam.time_s)
            yield KinectFrame(index=cam.index, timestamp_us=ts, depth_mm=cam.depth_mm,
                              color_data=cam.color_data,
                              color_timestamp_us=ts if cam.color_data is not None else None,
                              depth_grid="color", source=str(seq.path / cam.name),
                              _decoder=cam.color_rgb, _report=self._color_failed)


def _us(seconds: float) -> int:
    return math.floor(seconds * 1e6 + 0.5)


def open_kinect_stream(path: str | os.PathLike, *, serial: str | None = None,
                       kinect: int | None = None, strict: bool = False,
                       require_calibration: bool = True, depth_binning: int = 1,
                       streams: Collection[str] | None = None) -> KinectStream:
    """Open one Kinect camera's frames for streaming: an Azure ``.mkv`` or a BEHAVE sequence.

    Reads the header now (MKV tracks, tags and calibration; BEHAVE ``info.json``, calibrations
    and the list of frame folders); frames are read while iterating.

    Args:
        path: a k4arecorder ``.mkv`` file, or a BEHAVE-style sequence folder (with ``info.json``).
        serial: the camera wanted. For BEHAVE it selects the camera whose ``calibration.json``
            has this serial; for an MKV it must match the recording's serial.
        kinect: BEHAVE camera file id (``k1`` -> 1). A BEHAVE sequence with more than one camera
            needs ``serial`` or ``kinect``.
        strict: raise :class:`KinectFormatError` on the first unusable image instead of
            skipping and counting it.
        require_calibration: MKV only: raise now if ``calibration.json`` is missing or invalid
            (False: frames can be read, :attr:`KinectStream.calibration` raises). A BEHAVE
            sequence always needs its calibration files.
        depth_binning: MKV only: 2 reads a full-resolution recording's depth binned 2x2
            (:func:`~couch.capture.azure_mkv.open_azure_mkv`); a BEHAVE sequence's depth, in
            the colour camera's grid, is read as it is.
        streams: MKV only: the images to read (``COLOR``, ``DEPTH``, ``IR``; None: all), see
            :func:`~couch.capture.azure_mkv.open_azure_mkv`: the frames and their times are
            the same, the images not read are None. A BEHAVE sequence reads both its files.

    Raises:
        KinectFormatError: the path does not exist or is neither; the header is unreadable
            (naming the file and what is wrong); the calibration is missing (see above); the
            camera asked for is not there.
        ValueError: ``kinect`` given for an MKV file.
    """
    p = Path(path)
    if p.is_dir():
        if not (p / "info.json").is_file():
            raise KinectFormatError(f"{p}: a folder without info.json: not a BEHAVE sequence "
                                    f"(a Kinect stream is an .mkv file or a BEHAVE sequence "
                                    f"folder)")
        try:
            seq = open_behave_sequence(p, strict=strict)
        except BehaveFormatError as exc:
            raise KinectFormatError(str(exc)) from exc
        k = _select_behave_camera(seq, serial, kinect)
        return KinectStream(p, seq, kinect=k, strict=strict)
    if not p.exists():
        raise KinectFormatError(f"{p}: does not exist")
    if kinect is not None:
        raise ValueError(f"{p}: kinect={kinect} selects a camera of a BEHAVE sequence; an .mkv "
                         f"file holds one camera")
    rec = open_azure_mkv(p, require_calibration=require_calibration, strict=strict,
                         depth_binning=depth_binning, streams=streams)
    stream = KinectStream(p, rec, kinect=None, strict=strict)
    if serial is not None and str(serial) != stream.serial:
        raise KinectFormatError(f"{p}: recording of camera {stream.serial}, not of camera "
                                f"{serial}")
    return stream


def _select_behave_camera(seq: BehaveSequence, serial: str | None, kinect: int | None) -> int:
    serials = [c.serial or f"k{k}" for k, c in zip(seq.kinects, seq.calibrations, strict=True)]
    listing = ", ".join(f"k{k} (serial {s})" for k, s in zip(seq.kinects, serials, strict=True))
    if kinect is not None:
        if kinect not in seq.kinects:
            raise KinectFormatError(f"{seq.path}: no camera k{kinect}; cameras: {listing}")
        if serial is not None and serials[kinect] != str(serial):
            raise KinectFormatError(f"{seq.path}: camera k{kinect} has serial "
                                    f"{serials[kinect]}, not {serial}")
        return kinect
    if serial is not None:
        matches = [k for k, s in zip(seq.kinects, serials, strict=True) if s == str(serial)]
        if not matches:
            raise KinectFormatError(f"{seq.path}: no camera with serial {serial}; cameras: "
                                    f"{listing}")
        return matches[0]
    if len(seq.kinects) == 1:
        return seq.kinects[0]
    raise KinectFormatError(f"{seq.path}: a sequence of {len(seq.kinects)} cameras; choose one "
                            f"with serial= or kinect= ({listing})")
