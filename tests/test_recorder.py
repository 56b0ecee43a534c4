"""couch-record-imu end to end through a pseudo-terminal pair: a feeder thread writes a simulated,
damaged Xbus stream into the master side; the recorder (``main`` in-process) reads the slave with
pyserial. The file must be byte-identical to what was fed, and the summary must match XbusTruth.

Simulator settings: 3 s of the coarse bundled body standing and turning, ``ImuConfig()`` defaults
(17 sensors, 60 Hz, retransmission 2e-3) with stream damage raised to corrupt 1 %, truncate
0.5 %, drop 0.5 % (seed 11), so every damage kind occurs.
"""

from __future__ import annotations

import fcntl
import os
import signal
import struct
import termios
import threading
import time
import tty
from pathlib import Path

import numpy as np
import pytest

from couch.body import standing_pose
from couch.capture.recorder import PARTIAL_SUFFIX, DeviceTally, main, record
from couch.capture.xbus import XbusSample, write_device_map
from couch.tools.sim.imu import (
    MSG_CORRUPTED,
    MSG_TRUNCATED,
    ImuConfig,
    XbusTruth,
    body_track_from_model,
    simulate_xbus,
)


@pytest.fixture(scope="module")
def stream(coarse_model) -> tuple[bytes, dict[int, str], XbusTruth]:
    n = 3 * 30 + 1
    t = np.arange(n) / 30.0
    go = np.stack([0 * t, 0.5 * t, 0 * t], -1)
    bp = np.tile(standing_pose(), (n, 1))
    tr = np.stack([0.2 * t, 0.9 + 0 * t, 0 * t], -1)
    track = body_track_from_model(coarse_model, time=t, global_orient=go, body_pose=bp,
                                  transl=tr, betas=np.zeros(10))
    config = ImuConfig(corrupt_rate=0.01, truncate_rate=0.005, drop_rate=0.005)
    data, device_map, truth = simulate_xbus(track, config, np.random.default_rng(11))
    states = truth.msg_state
    assert (states == MSG_CORRUPTED).any() and (states == MSG_TRUNCATED).any()
    assert truth.dropped.any() and truth.retransmitted.any()
    return data, device_map, truth


def _inq(fd: int) -> int:
    """Bytes waiting in a tty's input queue (TIOCINQ)."""
    return struct.unpack("i", fcntl.ioctl(fd, termios.TIOCINQ, b"\0\0\0\0"))[0]


class _Feeder(threading.Thread):
    """Writes ``data`` into the pty master in random-sized chunks once the recorder has created
    ``FILE.partial`` (it opens the port first: pyserial flushes the input queue on open), waits
    until the recorder has drained the slave's queue, then ends the stream with ``finish``."""

    def __init__(self, master: int, slave: int, data: bytes, partial: Path, finish: str):
        super().__init__(daemon=True)
        self.master, self.slave, self.data = master, slave, data
        self.partial, self.finish = partial, finish
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            deadline = time.monotonic() + 20
            while not self.partial.exists():
                if time.monotonic() > deadline:
                    raise TimeoutError("the recorder never created its .partial file")
                time.sleep(0.01)
            rng = np.random.default_rng(0)
            pos = 0
            while pos < len(self.data):
                step = int(rng.integers(1, 3000))
                pos += os.write(self.master, self.data[pos:pos + step])
            # a pty master closing discards what the slave has not read yet: wait for the drain
            quiet_since = None
            while quiet_since is None or time.monotonic() - quiet_since < 0.3:
                if time.monotonic() > deadline:
                    raise TimeoutError("the recorder did not drain the pty")
                if _inq(self.slave):
                    quiet_since = None
                elif quiet_since is None:
                    quiet_since = time.monotonic()
                time.sleep(0.02)
            if self.finish == "close":
                os.close(self.master)
            elif self.finish == "sigint":
                os.kill(os.getpid(), signal.SIGINT)
        except BaseException as err:  # reported by the test (a thread cannot raise into it)
            self.error = err


def _pty() -> tuple[int, int, str]:
    master, slave = os.openpty()
    tty.setraw(slave)  # no line discipline: bytes pass unchanged before pyserial configures
    return master, slave, os.ttyname(slave)


def _expected(truth: XbusTruth) -> dict[int, tuple[int, int, int]]:
    """DeviceId → (samples, missing inside its counter range, retransmitted) from the truth."""
    out = {}
    for s, device_id in enumerate(truth.device_ids.tolist()):
        mine = (truth.msg_sensor == s) & truth.intact
        got = truth.msg_sample[mine]
        missing = int(got.max() - got.min() + 1 - len(np.unique(got)))
        out[device_id] = (int(mine.sum()), missing, int((mine & truth.retransmitted).sum()))
    return out


@pytest.mark.parametrize("finish", ["close", "sigint", "duration"])
def test_records_a_pty_stream_byte_identical(stream, tmp_path: Path, capsys, finish: str
                                             ) -> None:
    data, device_map, truth = stream
    out = tmp_path / "imu.xbus"
    map_path = tmp_path / "devices.json"
    write_device_map(map_path, device_map)
    master, slave, name = _pty()
    feeder = _Feeder(master, slave, data, out.with_name(out.name + PARTIAL_SUFFIX),
                     "none" if finish == "duration" else finish)
    argv = ["--port", name, "--out", str(out), "--device-map", str(map_path),
            "--flush-interval", "0.2"]
    if finish == "duration":
        argv += ["--duration", "3"]
    feeder.start()
    try:
        code = main(argv)
    finally:
        feeder.join(timeout=30)
        for fd in (master, slave):
            try:
                os.close(fd)
            except OSError:
                pass
    assert feeder.error is None, feeder.error
    assert code == 0
    assert out.read_bytes() == data
    assert not out.with_name(out.name + PARTIAL_SUFFIX).exists()

    text = capsys.readouterr().out
    reason = {"close": "port closed", "sigint": "interrupted", "duration": "duration"}[finish]
    assert f"stopped: {reason}" in text
    intact, damaged = int(truth.intact.sum()), int(truth.damaged.sum())
    assert f"messages ok    {intact} ({intact} MTData2 samples" in text
    assert f"damaged        {damaged} (" in text
    expected = _expected(truth)
    assert f"missing        {sum(m for _, m, _ in expected.values())} samples" in text
    for device_id, (samples, missing, retrans) in expected.items():
        row = (f"{device_id:08X}  {device_map[device_id]:<15} {samples:>8} {missing:>8} "
               f"{retrans:>8}    0")
        assert row in text


def test_record_summary_matches_the_truth(stream, tmp_path: Path) -> None:
    """The same counts through the library API, on a port stand-in that ends like a pty."""
    import serial

    data, device_map, truth = stream

    class Port:
        def __init__(self) -> None:
            self.pos = 0

        @property
        def in_waiting(self) -> int:
            return min(777, len(data) - self.pos)

        def read(self, size: int = 1) -> bytes:
            if self.pos >= len(data):
                raise serial.SerialException("device disconnected")
            chunk = data[self.pos:self.pos + size]
            self.pos += len(chunk)
            return chunk

    summary = record(Port(), tmp_path / "a.bin", device_map=device_map, progress=False)
    assert (tmp_path / "a.bin").read_bytes() == data
    assert summary.stats.messages_ok == int(truth.intact.sum())
    assert summary.damaged == int(truth.damaged.sum())
    assert summary.stats.bytes_in == summary.stats.bytes_ok + summary.stats.bytes_skipped
    expected = _expected(truth)
    assert {d: (t.samples, t.missing, t.retransmitted)
            for d, t in summary.devices.items()} == expected
    # every message lost from the counter ranges is a dropped or damaged one
    assert summary.missing <= int((~truth.intact).sum())


def test_a_crash_leaves_only_the_partial_file(tmp_path: Path) -> None:
    class Broken:
        calls = 0

        @property
        def in_waiting(self) -> int:
            return 10

        def read(self, size: int = 1) -> bytes:
            Broken.calls += 1
            if Broken.calls > 3:
                raise RuntimeError("bug")
            return b"\xfa" * size

    out = tmp_path / "x.bin"
    with pytest.raises(RuntimeError, match="bug"):
        record(Broken(), out, progress=False)
    assert not out.exists()
    assert (tmp_path / ("x.bin" + PARTIAL_SUFFIX)).read_bytes() == b"\xfa" * 30


def test_unopenable_port_is_a_clear_error(tmp_path: Path, capsys) -> None:
    out = tmp_path / "x.bin"
    assert main(["--port", str(tmp_path / "no-such-tty"), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "cannot open serial port" in err and "no-such-tty" in err
    assert not out.exists() and not (tmp_path / ("x.bin" + PARTIAL_SUFFIX)).exists()


def test_existing_output_is_refused(tmp_path: Path, capsys) -> None:
    out = tmp_path / "x.bin"
    out.write_bytes(b"old")
    assert main(["--port", "loop://", "--out", str(out), "--duration", "0.1"]) == 1
    assert "already exists" in capsys.readouterr().err
    assert out.read_bytes() == b"old"
    # loop:// is a pyserial port with no data: a clean, empty recording with --force
    assert main(["--port", "loop://", "--out", str(out), "--duration", "0.2", "--force",
                 "--no-progress"]) == 0
    assert out.read_bytes() == b""
    assert "stopped: duration" in capsys.readouterr().out


def test_device_tally_unwraps_counters_and_sees_late_samples() -> None:
    tally = DeviceTally()
    for pc in [65534, 65535, 1, 0, 3, 3]:  # wraps; 0 arrives late; 2 lost; 3 duplicated
        tally.add(XbusSample(device_id=1, packet_counter=pc))
    assert (tally.samples, tally.duplicates, tally.missing) == (6, 1, 1)
