"""Record a live Xsens Xbus stream from a serial port to a raw file (``couch-record-imu``).

The bytes are stored exactly as they arrive (nothing is parsed out or re-encoded, so a later
parser fix can re-read them); an :class:`~couch.capture.xbus.XbusParser` runs alongside only to
show progress and to summarise what was received.

File safety, exactly:

- The port is opened first; then the bytes go to ``FILE.partial`` (created fresh), which is
  flushed to the OS after every chunk and ``fsync``-ed every ``flush_interval`` seconds (default
  1 s), so a crash or power loss loses at most about that much.
- On a clean stop — ``--duration`` reached, Ctrl-C (SIGINT), or the port closing (device
  unplugged, pty master closed; pyserial reports it as an error on read) — the file is flushed,
  ``fsync``-ed, closed and ``os.replace``-d onto ``FILE``. A first Ctrl-C finishes the read in
  progress (no byte is lost); a second one aborts at once but is still a clean stop.
- On any other failure (a bug, disk full, an unexpected exception) ``FILE.partial`` is left in
  place with everything flushed so far, ``FILE`` is never created, and the error propagates
  (``main`` prints it and returns 1). Rename the ``.partial`` by hand to keep it: a raw Xbus
  stream cut anywhere still parses (the cut message counts as truncated).
- ``FILE`` or ``FILE.partial`` already existing is refused (exit 1) unless ``--force``.

Clocks: the recording is the raw stream; time stamps live inside it (SampleTimeFine, 10 kHz on the
IMU clock). ``--duration`` is wall-clock seconds of this computer's monotonic clock.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any, Protocol

from couch.capture.xbus import (
    MID,
    XbusError,
    XbusParser,
    XbusSample,
    XbusStats,
    read_device_map,
)

log = logging.getLogger(__name__)

DEFAULT_BAUD = 921600  # formats.md: 115200 baud cannot carry 17 sensors × 60 Hz
PARTIAL_SUFFIX = ".partial"
_WINDOW = 4096  # packet counters remembered per device to recognise duplicates


class SerialLike(Protocol):
    """What the recorder needs of a port (a ``serial.Serial``)."""

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1) -> bytes: ...


class PortClosed(Exception):
    """Internal: the port reported that it went away."""


# --------------------------------------------------------------------------- per-device tally


@dataclasses.dataclass
class DeviceTally:
    """MTData2 samples of one device, tracked through its 16-bit PacketCounter.

    Counters are unwrapped relative to the highest one seen, so late (retransmitted) samples
    are placed correctly; ``missing`` is the number of counters between the first and the last
    seen that never arrived (samples lost or damaged inside the recording; losses before the
    first or after the last sample cannot be seen).
    """

    samples: int = 0
    retransmitted: int = 0
    duplicates: int = 0
    without_counter: int = 0
    first: int | None = None
    head: int | None = None
    _recent: set[int] = dataclasses.field(default_factory=set, repr=False)

    def add(self, sample: XbusSample) -> None:
        self.samples += 1
        self.retransmitted += int(sample.retransmitted)
        pc = sample.packet_counter
        if pc is None:
            self.without_counter += 1
            return
        if self.head is None:
            value = int(pc)
            self.first = self.head = value
        else:
            delta = (int(pc) - self.head) % 65536
            value = self.head + delta if delta < 32768 else self.head - (65536 - delta)
        if value in self._recent:
            self.duplicates += 1
            return
        self._recent.add(value)
        assert self.first is not None and self.head is not None
        self.first = min(self.first, value)
        if value > self.head:
            self.head = value
            if len(self._recent) > 2 * _WINDOW:  # bound memory on long recordings
                self._recent = {v for v in self._recent if v > self.head - _WINDOW}

    @property
    def unique(self) -> int:
        return self.samples - self.duplicates - self.without_counter

    @property
    def missing(self) -> int:
        if self.first is None or self.head is None:
            return 0
        return (self.head - self.first + 1) - self.unique


# --------------------------------------------------------------------------- summary


@dataclasses.dataclass
class RecordSummary:
    """What one recording received. ``stats`` is the parser's accounting of every byte
    (``bytes_in == bytes_ok + bytes_skipped``); ``devices`` maps DeviceId → tally."""

    out: Path
    bytes_written: int
    seconds: float
    stop_reason: str
    """``duration``, ``interrupted`` (Ctrl-C), ``port closed`` (with pyserial's message) or
    ``max bytes``."""
    stats: XbusStats
    devices: dict[int, DeviceTally]
    device_map: dict[int, str] | None = None
    other_messages: dict[int, int] = dataclasses.field(default_factory=dict)
    """MID → count of checksum-valid messages that are not MTData2."""
    no_device_id: int = 0
    """MTData2 samples without a DeviceId packet (not attributable to a sensor)."""

    @property
    def damaged(self) -> int:
        """Rejected messages: checksum errors + malformed + truncated."""
        s = self.stats
        return s.checksum_errors + s.malformed + s.truncated

    @property
    def missing(self) -> int:
        """Samples missing inside each device's PacketCounter range, summed over devices."""
        return sum(t.missing for t in self.devices.values())

    def format(self) -> str:
        """Human-readable summary (what ``couch-record-imu`` prints at the end)."""
        s = self.stats
        rate = s.messages_ok / self.seconds if self.seconds > 0 else 0.0
        lines = [
            f"recorded       {self.out} ({self.bytes_written} bytes, {self.seconds:.1f} s, "
            f"stopped: {self.stop_reason})",
            f"messages ok    {s.messages_ok} ({s.samples} MTData2 samples, {rate:.0f} msg/s)",
            f"damaged        {self.damaged} (checksum {s.checksum_errors}, malformed "
            f"{s.malformed}, truncated {s.truncated}); bytes skipped {s.bytes_skipped}",
            f"missing        {self.missing} samples (PacketCounter gaps inside each device's "
            "range: dropped or damaged)",
        ]
        if s.error_messages:
            codes = ", ".join(f"{c}×{n}" for c, n in sorted(s.error_codes.items()))
            lines.append(f"device errors  {s.error_messages} (code×count: {codes})")
        if self.other_messages:
            other = ", ".join(f"0x{m:02X}×{n}" for m, n in sorted(self.other_messages.items()))
            lines.append(f"other msgs     {other}")
        if self.no_device_id:
            lines.append(f"no DeviceId    {self.no_device_id} samples")
        if self.devices or self.device_map:
            lines.append("device    segment          samples  missing  retrans  dup")
            ids = sorted(set(self.devices) | set(self.device_map or {}))
            for device_id in ids:
                tally = self.devices.get(device_id, DeviceTally())
                if self.device_map is None:
                    label = "-"
                else:
                    label = self.device_map.get(device_id, "NOT IN MAP")
                lines.append(f"{device_id:08X}  {label:<15} {tally.samples:>8} "
                             f"{tally.missing:>8} {tally.retransmitted:>8} "
                             f"{tally.duplicates:>4}")
        return "\n".join(lines)


# --------------------------------------------------------------------------- recording


class _Tracker:
    """Feeds the parser and tallies what it returns."""

    def __init__(self) -> None:
        self.parser = XbusParser()
        self.devices: dict[int, DeviceTally] = {}
        self.other: dict[int, int] = {}
        self.no_device_id = 0

    def feed(self, data: bytes) -> None:
        self._tally(self.parser.feed(data))

    def flush(self) -> None:
        self._tally(self.parser.flush())

    def _tally(self, items: list) -> None:
        for item in items:
            if isinstance(item, XbusSample):
                if item.device_id is None:
                    self.no_device_id += 1
                else:
                    self.devices.setdefault(item.device_id, DeviceTally()).add(item)
            elif item.mid != MID.Error:
                self.other[item.mid] = self.other.get(item.mid, 0) + 1


@contextlib.contextmanager
def _sigint_as_flag(stop: threading.Event) -> Iterator[None]:
    """In the main thread, make the first SIGINT set ``stop`` (the loop then finishes the read
    in progress, so no byte already taken from the port is lost); a second one raises
    KeyboardInterrupt as usual. Elsewhere (no signal handlers allowed) do nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _read_chunk(port: SerialLike, chunk_size: int) -> bytes:
    """Read what the port holds (at most ``chunk_size``), waiting up to its timeout for the
    first byte. Asking only for bytes already waiting means pyserial's read returns after one
    OS read, so a disconnect cannot discard bytes it had already gathered."""
    import serial  # only needed with a real port

    try:
        waiting = port.in_waiting
        return port.read(max(1, min(waiting, chunk_size)))
    except (serial.SerialException, OSError) as err:
        raise PortClosed(str(err)) from err


class _Progress:
    """tqdm bar on a terminal, else a log line every ``log_interval`` seconds."""

    def __init__(self, enabled: bool, log_interval: float, name: str):
        self.bar = None
        self.log_interval = log_interval
        self.enabled = enabled
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(unit="B", unit_scale=True, desc=name, file=sys.stderr)
        self.last = time.monotonic()
        self.last_messages = 0

    def update(self, nbytes: int, stats: XbusStats, *, force: bool = False) -> None:
        if self.bar is not None:
            self.bar.update(nbytes)
        now = time.monotonic()
        interval = 0.5 if self.bar is not None else self.log_interval
        if not self.enabled or (now - self.last < interval and not force):
            return
        rate = (stats.messages_ok - self.last_messages) / max(now - self.last, 1e-9)
        self.last, self.last_messages = now, stats.messages_ok
        damaged = stats.checksum_errors + stats.malformed + stats.truncated
        if self.bar is not None:
            self.bar.set_postfix(msg_s=f"{rate:.0f}", ok=stats.messages_ok, damaged=damaged,
                                 skipped=stats.bytes_skipped, refresh=False)
        else:
            log.info("%d bytes, %d messages ok (%.0f msg/s), %d damaged (checksum %d), "
                     "%d bytes skipped", stats.bytes_in, stats.messages_ok, rate, damaged,
                     stats.checksum_errors, stats.bytes_skipped)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def record(port: SerialLike, out: str | os.PathLike, *, duration: float | None = None,
           device_map: Mapping[int, str] | None = None, stop: threading.Event | None = None,
           chunk_size: int = 65536, flush_interval: float = 1.0, max_bytes: int | None = None,
           progress: bool = True, log_interval: float = 5.0, force: bool = False,
           on_start: Callable[[Path], None] | None = None) -> RecordSummary:
    """Record ``port`` (an open ``serial.Serial`` or alike) into ``out`` (see the module
    docstring for the ``.partial`` / ``os.replace`` behaviour).

    Stops after ``duration`` seconds (monotonic clock), when ``stop`` is set (the first SIGINT
    sets it when called from the main thread), when the port closes, or after ``max_bytes``.
    The port's read timeout bounds how late a stop is noticed: set it to ~0.1 s.
    ``on_start`` is called with the ``.partial`` path once it exists (tests synchronise on it).
    Raises FileExistsError if ``out`` or ``out.partial`` exists and not ``force``.
    """
    out = Path(out)
    partial = out.with_name(out.name + PARTIAL_SUFFIX)
    if not force:
        for path in (out, partial):
            if path.exists():
                raise FileExistsError(f"{path} already exists (use --force to overwrite)")
    stop = stop or threading.Event()
    tracker = _Tracker()
    show = _Progress(progress, log_interval, out.name)
    written = 0
    reason = "interrupted"
    start = time.monotonic()
    out.parent.mkdir(parents=True, exist_ok=True)
    f: IO[bytes] = open(partial, "wb")
    clean = False
    try:
        if on_start is not None:
            on_start(partial)
        last_sync = time.monotonic()
        with _sigint_as_flag(stop):
            try:
                while True:
                    if stop.is_set():
                        reason = "interrupted"
                        break
                    if duration is not None and time.monotonic() - start >= duration:
                        reason = "duration"
                        break
                    if max_bytes is not None and written >= max_bytes:
                        reason = "max bytes"
                        break
                    want = chunk_size if max_bytes is None else min(chunk_size,
                                                                    max_bytes - written)
                    try:
                        data = _read_chunk(port, want)
                    except PortClosed as err:
                        reason = f"port closed ({err})"
                        break
                    if data:
                        f.write(data)  # raw bytes first: the file never depends on parsing
                        f.flush()
                        written += len(data)
                        tracker.feed(data)
                    now = time.monotonic()
                    if now - last_sync >= flush_interval:
                        os.fsync(f.fileno())
                        last_sync = now
                    show.update(len(data), tracker.parser.stats)
            except KeyboardInterrupt:  # a second Ctrl-C: stop now, still a clean stop
                reason = "interrupted"
        tracker.flush()
        f.flush()
        os.fsync(f.fileno())
        clean = True
    finally:
        f.close()
        show.close()
        if clean:
            os.replace(partial, out)
        else:
            log.error("recording failed; the bytes so far are in %s", partial)
    return RecordSummary(out=out, bytes_written=written, seconds=time.monotonic() - start,
                         stop_reason=reason, stats=tracker.parser.stats,
                         devices=tracker.devices,
                         device_map=dict(device_map) if device_map is not None else None,
                         other_messages=tracker.other, no_device_id=tracker.no_device_id)


# --------------------------------------------------------------------------- CLI


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="couch-record-imu",
        description="Record a raw Xsens Xbus stream from a serial port. Bytes go to FILE.partial "
                    "and are moved onto FILE on a clean stop (duration, Ctrl-C, port closed); "
                    "after a crash FILE.partial holds everything flushed so far.")
    ap.add_argument("--port", required=True, help="serial device, e.g. /dev/ttyUSB0 (any "
                    "pyserial URL also works, e.g. loop://)")
    ap.add_argument("--out", required=True, type=Path, help="output file (raw Xbus bytes)")
    ap.add_argument("--baud", type=int, default=DEFAULT_BAUD,
                    help=f"baud rate (default {DEFAULT_BAUD}; 115200 cannot carry 17 sensors)")
    ap.add_argument("--duration", type=float, default=None,
                    help="stop after this many seconds (default: until Ctrl-C or port close)")
    ap.add_argument("--device-map", type=Path, default=None,
                    help="DeviceId → segment JSON (couch.xbus.device_map) for per-sensor counts")
    ap.add_argument("--flush-interval", type=float, default=1.0,
                    help="seconds between fsyncs of FILE.partial (default 1)")
    ap.add_argument("--timeout", type=float, default=0.1,
                    help="serial read timeout in seconds; bounds how late a stop is noticed")
    ap.add_argument("--force", action="store_true",
                    help="overwrite an existing FILE / FILE.partial")
    ap.add_argument("--no-progress", action="store_true",
                    help="no progress bar or periodic log lines")
    return ap


def main(argv: list[str] | None = None) -> int:
    """``couch-record-imu --port DEV --out FILE [--baud 921600] [--duration S]
    [--device-map JSON]``: returns 0 on a clean recording, 1 with a message on stderr if the
    port, device map or output cannot be used or the recording fails."""
    args = _parser().parse_args(argv)
    prog = "couch-record-imu"
    if args.duration is not None and not args.duration > 0:
        print(f"{prog}: --duration must be positive, got {args.duration}", file=sys.stderr)
        return 1
    device_map = None
    if args.device_map is not None:
        try:
            device_map = read_device_map(args.device_map)
        except (XbusError, OSError) as err:
            print(f"{prog}: cannot read device map: {err}", file=sys.stderr)
            return 1
    if not args.force:
        for path in (args.out, args.out.with_name(args.out.name + PARTIAL_SUFFIX)):
            if path.exists():
                print(f"{prog}: {path} already exists (use --force to overwrite)",
                      file=sys.stderr)
                return 1
    import serial

    try:
        port = serial.serial_for_url(args.port, baudrate=args.baud, timeout=args.timeout)
    except (serial.SerialException, ValueError, OSError) as err:
        print(f"{prog}: cannot open serial port {args.port!r} at {args.baud} baud: {err}",
              file=sys.stderr)
        return 1
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format=f"{prog}: %(message)s")
    try:
        with port:
            summary = record(port, args.out, duration=args.duration, device_map=device_map,
                             flush_interval=args.flush_interval,
                             progress=not args.no_progress, force=args.force)
    except OSError as err:
        print(f"{prog}: recording failed: {err}", file=sys.stderr)
        return 1
    print(summary.format())
    return 0


if __name__ == "__main__":
    sys.exit(main())
