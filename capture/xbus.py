"""Xsens Xbus low-level protocol (MTi / MTw): message framing, MTData2 samples, an incremental
parser that survives corrupted serial streams, and couch's DeviceId → body-segment sidecar.

Message: ``FA | BID | MID | LEN | DATA | CS`` where LEN 0–254 is the data length, or LEN = 0xFF
followed by a 2-byte big-endian extended length; the checksum makes
``(BID + MID + LEN bytes + DATA + CS) & 0xFF == 0`` (the preamble is not summed). MTData2
(MID 0x36) data is a run of packets ``XDI (uint16 BE) | size (uint8) | payload (BE)``.

Units and frames of a decoded :class:`XbusSample`: quaternion (w, x, y, z) rotating sensor-frame
vectors into the device's earth frame named by the XDI's coordinate bits (``ENU`` by default,
also ``NED``/``NWU``); acceleration (with gravity) and free acceleration (gravity removed, earth
frame) in m/s²; rate of turn in rad/s (sensor frame); magnetic field in arbitrary units
normalised to the earth field; SampleTimeFine in ticks of 100 µs (10 kHz, wraps at 2³²);
PacketCounter uint16 (wraps at 2¹⁶).

What was checked, and against what (nothing fetched is committed):

- Framing, checksum, extended length: ethz-asl/ethzasl_xsens_driver ``src/xsens_driver/
  mtdevice.py`` (``write_msg``: ``FA FF MID``, LEN > 254 → ``FF`` + ``!H`` length, checksum =
  ``0xFF & -sum(packet[1:])``; ``read_msg``: LEN 255 → 2-byte length). GoToConfig encodes to
  ``FA FF 30 00 D1`` and GoToMeasurement to ``FA FF 10 00 F1`` as recorded in
  Scottapotamas/xsens-mti ``docs/mtmanager_packets.md`` ("Configuration Example").
- MIDs (``mtdef.py`` class MID: GoToConfig 0x30, GoToMeasurement 0x10, MTData2 0x36, Error 0x42
  with one code byte, ReqDID 0x00 / DeviceID 0x01, WakeUp 0x3E / WakeUpAck 0x3F, Reset 0x40;
  acknowledgements are MID + 1, e.g. GoToConfigAck 0x31 in the MT Manager capture).
- MTData2 packets: ``mtdevice.py`` ``parse_MTData2`` (``!HB`` header, precision from the low two
  bits: 0 float32, 3 float64, others fixed point; coordinate frame from bits 2–3: 0 ENU, 4 NED,
  8 NWU; PacketCounter ``!H``, SampleTimeFine ``!L``, StatusWord ``!L``, Quaternion 4 floats, w
  first); XDI values and ``XDI_DeviceId = 0xE080`` in Xsens' ``xsdataidentifier.h`` (vendored
  in several public ROS drivers); Fp12.20 = int32 / 2²⁰ from Xsens' ``XsMessage_getDataF1220``.
- Golden packets from a real MTi-300 in ``docs/mtmanager_packets.md``: example 6 (the formats.md
  vector: PacketCounter 18050, SampleTimeFine 29686846, quaternion (0.944556, −0.323088, 0.013747,
  −0.056913), StatusWord 0x00400003) and example 1 (Acceleration, FreeAcceleration, RateOfTurn,
  MagneticField values, plus DeltaV 0x4010, DeltaQ 0x8030 and BaroPressure 0x3010, which this
  module does not model and skips by size) both decode to MT Manager's printed values
  (tests/test_xbus.py).
- StatusWord bits from ``xsstatusflag.h``: 0x1 self-test OK, 0x2 orientation valid,
  0x00040000 retransmitted (an older header revision used 0x00080000), 0x00400000 sync-out.

Not modelled: fixed-point 16.32 (6-byte) values are skipped and counted like unknown XDIs
(no public golden packet to verify the byte order); the Awinda station's own multi-sensor wire
format is not public, so couch's convention (formats.md) is one MTData2 message per sensor per
sample carrying DeviceId.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import os
import struct
from collections.abc import Iterable, Mapping
from enum import IntEnum
from pathlib import Path

import numpy as np

from couch.atomic import atomic_path

PREAMBLE = 0xFA
BID_MASTER = 0xFF
EXTENDED_LENGTH = 0xFF
MAX_STANDARD_LENGTH = 254
MAX_DATA_LENGTH = 8185


class MID(IntEnum):
    """Message identifiers used by couch (acknowledgements are MID + 1)."""

    ReqDID = 0x00
    DeviceID = 0x01
    InitMT = 0x02
    InitMTResults = 0x03
    GoToMeasurement = 0x10
    GoToMeasurementAck = 0x11
    GoToConfig = 0x30
    GoToConfigAck = 0x31
    MTData2 = 0x36
    WakeUp = 0x3E
    WakeUpAck = 0x3F
    Reset = 0x40
    Error = 0x42


class XDI(IntEnum):
    """MTData2 data identifiers (precision / frame bits zero: float32, ENU)."""

    PacketCounter = 0x1020
    SampleTimeFine = 0x1060
    Quaternion = 0x2010
    Acceleration = 0x4020
    FreeAcceleration = 0x4030
    RateOfTurn = 0x8020
    MagneticField = 0xC020
    StatusWord = 0xE020
    DeviceId = 0xE080


XDI_TYPE_MASK = 0xFFF0
XDI_PRECISION_MASK = 0x0003
XDI_FRAME_MASK = 0x000C
COORDINATE_FRAMES: dict[int, str] = {0x0: "ENU", 0x4: "NED", 0x8: "NWU"}
_FRAME_BITS = {name: bits for bits, name in COORDINATE_FRAMES.items()}
PRECISIONS: dict[str, int] = {"float32": 0x0, "float64": 0x3}

STATUS_SELFTEST_OK = 0x00000001
STATUS_ORIENTATION_VALID = 0x00000002
STATUS_RETRANSMITTED = 0x00040000
STATUS_SYNC_OUT = 0x00400000

ERROR_CODES: dict[int, str] = {
    3: "invalid sample period",
    4: "invalid or unimplemented message",
    30: "timer overflow during measurement",
    32: "baud rate out of range",
    33: "invalid parameter",
    40: "device error (try a firmware update)",
    41: "more data than the bus can carry (baud rate too low?)",
    42: "sample buffer full during a communication outage",
}
"""A few MID 0x42 error codes (meanings as listed in ethzasl_xsens_driver's mtdef.py)."""

# Integer packets: exact XDI → (field, struct format).
_INT_FIELDS: dict[int, tuple[str, str]] = {
    XDI.PacketCounter: ("packet_counter", ">H"),
    XDI.SampleTimeFine: ("sample_time_fine", ">I"),
    XDI.StatusWord: ("status_word", ">I"),
    XDI.DeviceId: ("device_id", ">I"),
}
# Float vectors: XDI type (precision and frame bits masked off) → (field, component count).
_VECTOR_FIELDS: dict[int, tuple[str, int]] = {
    XDI.Quaternion: ("quaternion", 4),
    XDI.Acceleration: ("acceleration", 3),
    XDI.FreeAcceleration: ("free_acceleration", 3),
    XDI.RateOfTurn: ("rate_of_turn", 3),
    XDI.MagneticField: ("magnetic_field", 3),
}
_ENCODE_ORDER = sorted([*_INT_FIELDS, *_VECTOR_FIELDS])  # ascending XDI, as MT Manager lists them


class XbusError(ValueError):
    """Bad Xbus bytes or a bad device-map file (the message says where and what was expected)."""


# --------------------------------------------------------------------------- framing


def checksum(body: bytes | bytearray) -> int:
    """The checksum byte for ``body`` = BID, MID, LEN byte(s) and DATA (no preamble)."""
    return (-sum(body)) & 0xFF


def encode_message(mid: int, data: bytes = b"", bid: int = BID_MASTER) -> bytes:
    """One complete Xbus message (preamble to checksum); extended length above 254 bytes."""
    if not (0 <= mid <= 0xFF and 0 <= bid <= 0xFF):
        raise ValueError(f"MID and BID must be bytes, got mid={mid}, bid={bid}")
    n = len(data)
    if n > MAX_DATA_LENGTH:
        raise ValueError(f"Xbus data is limited to {MAX_DATA_LENGTH} bytes, got {n}")
    if n <= MAX_STANDARD_LENGTH:
        header = bytes((bid, mid, n))
    else:
        header = bytes((bid, mid, EXTENDED_LENGTH, n >> 8, n & 0xFF))
    body = header + bytes(data)
    return bytes((PREAMBLE,)) + body + bytes((checksum(body),))


@dataclasses.dataclass(frozen=True)
class XbusMessage:
    """A checksum-valid message that is not MTData2 (e.g. an acknowledgement or an error)."""

    mid: int
    data: bytes
    bid: int = BID_MASTER
    offset: int = -1
    """Byte offset of the preamble in the stream fed to the parser (-1 if unknown)."""

    @property
    def error_code(self) -> int | None:
        """The code of an Error (MID 0x42) message, else None."""
        return self.data[0] if self.mid == MID.Error and self.data else None


# --------------------------------------------------------------------------- MTData2


@dataclasses.dataclass(eq=False)
class XbusSample:
    """One MTData2 message; any field may be absent (None). Vectors are float64 numpy arrays.

    quaternion (4,) w, x, y, z sensor → earth frame; acceleration, free_acceleration (3,) m/s²;
    rate_of_turn (3,) rad/s; magnetic_field (3,) normalised units; sample_time_fine in 100 µs
    ticks; coordinate_frame is the earth frame of the vectors (``ENU``, ``NED`` or ``NWU``).
    """

    device_id: int | None = None
    packet_counter: int | None = None
    sample_time_fine: int | None = None
    quaternion: np.ndarray | None = None
    acceleration: np.ndarray | None = None
    free_acceleration: np.ndarray | None = None
    rate_of_turn: np.ndarray | None = None
    magnetic_field: np.ndarray | None = None
    status_word: int | None = None
    coordinate_frame: str = "ENU"
    unknown_xdis: tuple[int, ...] = ()
    """XDIs of packets skipped by size (not modelled here), in message order."""
    bid: int = BID_MASTER
    offset: int = -1
    """Byte offset of the message's preamble in the stream fed to the parser (-1 if unknown)."""

    @property
    def retransmitted(self) -> bool:
        """StatusWord says the sample arrived by retransmission (wireless MTw)."""
        return bool(self.status_word is not None and self.status_word & STATUS_RETRANSMITTED)


def _fixed1220(raw: bytes) -> np.ndarray:
    return np.frombuffer(raw, dtype=">i4").astype(np.float64) / 1048576.0


_PRECISION_DECODE = {  # precision bits → (bytes per value, decoder)
    0x0: (4, lambda raw: np.frombuffer(raw, dtype=">f4").astype(np.float64)),
    0x1: (4, _fixed1220),
    0x3: (8, lambda raw: np.frombuffer(raw, dtype=">f8").astype(np.float64)),
}


def decode_mtdata2(data: bytes | bytearray | memoryview, *, bid: int = BID_MASTER,
                   offset: int = -1) -> XbusSample:
    """Decode MTData2 message data (the DATA field, without header/checksum).

    Unknown XDIs (and fixed-point 16.32) are skipped by their size and listed in
    ``unknown_xdis``. Raises XbusError if the packets do not exactly fill ``data`` or a known
    XDI has the wrong size.
    """
    data = bytes(data)
    sample = XbusSample(bid=bid, offset=offset)
    unknown: list[int] = []
    frame: int | None = None
    pos, n = 0, len(data)
    while pos < n:
        if n - pos < 3:
            raise XbusError(f"MTData2: {n - pos} trailing byte(s) at offset {pos}, too short "
                            "for a packet header (XDI + size)")
        xdi, size = (data[pos] << 8) | data[pos + 1], data[pos + 2]
        end = pos + 3 + size
        if end > n:
            raise XbusError(f"MTData2: packet 0x{xdi:04X} at offset {pos} declares {size} "
                            f"bytes but only {n - pos - 3} remain")
        raw = data[pos + 3:end]
        kind = xdi & XDI_TYPE_MASK
        if xdi in _INT_FIELDS:
            name, fmt = _INT_FIELDS[xdi]
            if size != struct.calcsize(fmt):
                raise XbusError(f"MTData2: packet 0x{xdi:04X} has {size} bytes, expected "
                                f"{struct.calcsize(fmt)}")
            setattr(sample, name, struct.unpack(fmt, raw)[0])
        elif kind in _VECTOR_FIELDS and (xdi & XDI_PRECISION_MASK) in _PRECISION_DECODE:
            name, count = _VECTOR_FIELDS[kind]
            width, decode = _PRECISION_DECODE[xdi & XDI_PRECISION_MASK]
            if size != count * width:
                raise XbusError(f"MTData2: packet 0x{xdi:04X} has {size} bytes, expected "
                                f"{count * width} ({count} values of {width} bytes)")
            if (xdi & XDI_FRAME_MASK) not in COORDINATE_FRAMES:
                raise XbusError(f"MTData2: packet 0x{xdi:04X} names an undefined coordinate "
                                "frame (bits 2-3 = 0xC)")
            setattr(sample, name, decode(raw))
            frame = xdi & XDI_FRAME_MASK if frame is None else frame
        else:
            unknown.append(xdi)
        pos = end
    sample.unknown_xdis = tuple(unknown)
    if frame is not None:
        sample.coordinate_frame = COORDINATE_FRAMES[frame]
    return sample


def mtdata2_payload(sample: XbusSample, *, precision: str = "float32") -> bytes:
    """The MTData2 DATA field for the non-None fields of ``sample``, in ascending XDI order.

    ``precision`` is ``float32`` (what MTw/MTi send by default) or ``float64``; vectors carry the
    coordinate-frame bits of ``sample.coordinate_frame``.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
    if sample.coordinate_frame not in _FRAME_BITS:
        raise ValueError(f"coordinate_frame must be one of {sorted(_FRAME_BITS)}, "
                         f"got {sample.coordinate_frame!r}")
    dtype = ">f4" if precision == "float32" else ">f8"
    low_bits = PRECISIONS[precision] | _FRAME_BITS[sample.coordinate_frame]
    out = bytearray()
    for xdi in _ENCODE_ORDER:
        if xdi in _INT_FIELDS:
            name, fmt = _INT_FIELDS[xdi]
            value = getattr(sample, name)
            if value is None:
                continue
            limit = 1 << (8 * struct.calcsize(fmt))
            if not 0 <= int(value) < limit:
                raise ValueError(f"{name}={value} does not fit {struct.calcsize(fmt)} bytes")
            raw = struct.pack(fmt, int(value))
            code = xdi
        else:
            name, count = _VECTOR_FIELDS[xdi]
            value = getattr(sample, name)
            if value is None:
                continue
            arr = np.asarray(value, dtype=np.float64)
            if arr.shape != (count,):
                raise ValueError(f"{name} must have shape ({count},), got {arr.shape}")
            raw = arr.astype(dtype).tobytes()
            code = xdi | low_bits
        out += struct.pack(">HB", code, len(raw)) + raw
    return bytes(out)


def encode_mtdata2(sample: XbusSample, *, precision: str = "float32",
                   bid: int = BID_MASTER) -> bytes:
    """A complete MTData2 message (preamble to checksum) for ``sample``."""
    return encode_message(MID.MTData2, mtdata2_payload(sample, precision=precision), bid)


# --------------------------------------------------------------------------- parser


@dataclasses.dataclass
class XbusStats:
    """What an :class:`XbusParser` saw. After :meth:`XbusParser.flush`,
    ``bytes_in == bytes_ok + bytes_skipped`` exactly.

    A damaged message is counted once: candidates (a preamble + accepted BID + valid length)
    that start inside an already rejected candidate are part of the same damage and only their
    bytes are counted. A rejected candidate overlapped by the next valid message is classified
    ``truncated`` (the message was cut short), otherwise by why it failed.
    """

    bytes_in: int = 0
    bytes_ok: int = 0
    """Bytes of valid messages (preamble to checksum)."""
    bytes_skipped: int = 0
    """Every other byte: garbage between messages and the bytes of rejected candidates."""
    messages_ok: int = 0
    samples: int = 0
    checksum_errors: int = 0
    malformed: int = 0
    """Checksum-valid MTData2 whose packets do not fill the data exactly (rejected)."""
    truncated: int = 0
    unknown_xdis: int = 0
    error_messages: int = 0
    error_codes: collections.Counter = dataclasses.field(default_factory=collections.Counter)
    """MID 0x42 error code → count."""


@dataclasses.dataclass
class _Rejected:
    kind: str
    start: int
    end: int


class XbusParser:
    """Incremental Xbus parser for a serial byte stream; never raises on stream content.

    ``feed`` returns the messages completed by the new bytes, in stream order: an
    :class:`XbusSample` per MTData2 message and an :class:`XbusMessage` for every other MID.
    After a bad message or garbage it resynchronises on the next preamble that starts a valid
    message, so an intact message is never lost to damage before it, and ``stats`` accounts for
    every byte (see :class:`XbusStats`). Call ``flush`` at the end of a stream to decide about
    bytes still waiting for a message that will never complete.

    ``bids``: the bus identifiers that may start a message (default only 0xFF, the value on a
    host link; requiring it makes false starts in noise 256 times rarer). None accepts any BID.
    """

    def __init__(self, *, bids: Iterable[int] | None = (BID_MASTER,),
                 max_data_length: int = MAX_DATA_LENGTH):
        self._bids = None if bids is None else frozenset(bids)
        self._max_length = max_data_length
        self._buf = bytearray()
        self._base = 0  # stream offset of self._buf[0]
        self._rejected: _Rejected | None = None
        self.stats = XbusStats()

    def feed(self, data: bytes | bytearray | memoryview) -> list[XbusSample | XbusMessage]:
        """Add bytes from the stream; return the messages they complete."""
        self.stats.bytes_in += len(data)
        self._buf += data
        return self._drain(final=False)

    def flush(self) -> list[XbusSample | XbusMessage]:
        """End of stream: bytes waiting for an incomplete message become ``truncated``; any
        complete messages after its start are still returned."""
        out = self._drain(final=True)
        if self._rejected is not None:
            self._count(self._rejected.kind)
            self._rejected = None
        return out

    @property
    def buffered(self) -> int:
        """Bytes held back waiting for the rest of a message."""
        return len(self._buf)

    # -- internals
    def _count(self, kind: str) -> None:
        if kind == "checksum":
            self.stats.checksum_errors += 1
        elif kind == "malformed":
            self.stats.malformed += 1
        else:
            self.stats.truncated += 1

    def _reject(self, kind: str, start: int, end: int) -> None:
        prev = self._rejected
        if prev is not None and start < prev.end:
            return  # a false start inside damage already counted
        if prev is not None:
            self._count(prev.kind)
        self._rejected = _Rejected(kind, start, end)

    def _accept_at(self, start: int) -> None:
        prev = self._rejected
        if prev is not None:
            self._count("truncated" if start < prev.end else prev.kind)
            self._rejected = None

    def _frame_length(self, buf: bytearray, pos: int) -> int | None:
        """Total message length at ``pos`` (a preamble); 0 if the header is impossible; None
        if more bytes are needed to tell."""
        avail = len(buf) - pos
        if avail < 2:
            return None
        if self._bids is not None and buf[pos + 1] not in self._bids:
            return 0
        if avail < 4:
            return None
        length = buf[pos + 3]
        if length != EXTENDED_LENGTH:
            return length + 5
        if avail < 6:
            return None
        length = (buf[pos + 4] << 8) | buf[pos + 5]
        return 0 if length > self._max_length else length + 7

    def _drain(self, *, final: bool) -> list[XbusSample | XbusMessage]:
        buf, out, pos, stats = self._buf, [], 0, self.stats
        while pos < len(buf):
            start = buf.find(PREAMBLE, pos)
            if start < 0:
                stats.bytes_skipped += len(buf) - pos
                pos = len(buf)
                break
            stats.bytes_skipped += start - pos
            pos = start
            total = self._frame_length(buf, pos)
            if total is None or (total and pos + total > len(buf)):
                if not final:
                    break  # wait for the rest
                if total or len(buf) - pos >= 2:  # a message the stream cut short
                    end = pos + total if total else len(buf)
                    self._reject("truncated", self._base + pos, self._base + end)
                stats.bytes_skipped += 1
                pos += 1
                continue
            if total == 0:
                stats.bytes_skipped += 1
                pos += 1
                continue
            item = self._decode(buf, pos, total)
            if item is None:
                stats.bytes_skipped += 1
                pos += 1
                continue
            self._accept_at(self._base + pos)
            out.append(item)
            stats.messages_ok += 1
            stats.bytes_ok += total
            pos += total
        del buf[:pos]
        self._base += pos
        return out

    def _decode(self, buf: bytearray, pos: int, total: int) -> XbusSample | XbusMessage | None:
        start, end = self._base + pos, self._base + pos + total
        if sum(buf[pos + 1:pos + total]) & 0xFF:
            self._reject("checksum", start, end)
            return None
        header = 6 if buf[pos + 3] == EXTENDED_LENGTH else 4
        bid, mid = buf[pos + 1], buf[pos + 2]
        data = bytes(buf[pos + header:pos + total - 1])
        if mid == MID.MTData2:
            try:
                sample = decode_mtdata2(data, bid=bid, offset=start)
            except XbusError:
                self._reject("malformed", start, end)
                return None
            self.stats.samples += 1
            self.stats.unknown_xdis += len(sample.unknown_xdis)
            return sample
        message = XbusMessage(mid=mid, data=data, bid=bid, offset=start)
        if mid == MID.Error:
            self.stats.error_messages += 1
            self.stats.error_codes[message.error_code if data else -1] += 1
        return message


def parse_stream(data: bytes | bytearray | memoryview, *,
                 bids: Iterable[int] | None = (BID_MASTER,),
                 max_data_length: int = MAX_DATA_LENGTH,
                 ) -> tuple[list[XbusSample | XbusMessage], XbusStats]:
    """Parse a complete recorded stream (e.g. a raw serial dump): messages and statistics."""
    parser = XbusParser(bids=bids, max_data_length=max_data_length)
    items = parser.feed(data)
    items += parser.flush()
    return items, parser.stats


# --------------------------------------------------------------------------- device map

_DEVICE_MAP_FORMAT = "couch.xbus.device_map"


def write_device_map(path: str | os.PathLike, mapping: Mapping[int, str]) -> None:
    """Write the sidecar JSON that says which body segment each DeviceId is strapped to.

    Device ids are written as 8 upper-case hex digits, as MT Manager shows them (``00B4A1C2``).
    Raises ValueError for ids outside uint32, empty labels or a segment given twice.
    """
    devices: dict[str, str] = {}
    seen: dict[str, int] = {}
    for device_id, label in sorted(mapping.items()):
        if not isinstance(device_id, int | np.integer) or not 0 <= int(device_id) < 1 << 32:
            raise ValueError(f"device id {device_id!r} is not a uint32")
        if not isinstance(label, str) or not label:
            raise ValueError(f"device {int(device_id):08X}: segment label must be a non-empty "
                             "string")
        if label in seen:
            raise ValueError(f"segment {label!r} is given to devices {seen[label]:08X} and "
                             f"{int(device_id):08X}")
        seen[label] = int(device_id)
        devices[f"{int(device_id):08X}"] = label
    doc = {"format": _DEVICE_MAP_FORMAT, "version": 1, "devices": devices}
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


def read_device_map(path: str | os.PathLike) -> dict[int, str]:
    """Read a device map written by :func:`write_device_map`: DeviceId → segment label."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise XbusError(f"{path}: line {err.lineno}, column {err.colno}: not valid JSON "
                        f"({err.msg})") from None
    except UnicodeDecodeError as err:
        raise XbusError(f"{path}: not UTF-8 text ({err.reason})") from None
    if not isinstance(doc, dict) or doc.get("format") != _DEVICE_MAP_FORMAT:
        raise XbusError(f"{path}: expected a JSON object with format={_DEVICE_MAP_FORMAT!r}")
    if doc.get("version") != 1:
        raise XbusError(f"{path}: unsupported device map version {doc.get('version')!r} "
                        "(expected 1)")
    devices = doc.get("devices")
    if not isinstance(devices, dict):
        raise XbusError(f"{path}: 'devices' must be an object of hex DeviceId → segment label")
    out: dict[int, str] = {}
    seen: dict[str, str] = {}
    for key, label in devices.items():
        text = key[2:] if key.lower().startswith("0x") else key
        try:
            device_id = int(text, 16)
        except ValueError:
            raise XbusError(f"{path}: device id {key!r} is not hexadecimal") from None
        if not 0 <= device_id < 1 << 32:
            raise XbusError(f"{path}: device id {key!r} does not fit 32 bits")
        if not isinstance(label, str) or not label:
            raise XbusError(f"{path}: device {key}: expected a segment label string, "
                            f"got {label!r}")
        if label in seen:
            raise XbusError(f"{path}: segment {label!r} is given to devices {seen[label]} and "
                            f"{key}")
        if device_id in out:
            raise XbusError(f"{path}: device id {key!r} appears twice")
        seen[label] = key
        out[device_id] = label
    return out
