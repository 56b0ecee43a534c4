"""Xbus framing and MTData2: published golden bytes, round trips, damaged streams counted exactly,
and properties of the incremental parser under arbitrary bytes and chunking."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from couch.capture.xbus import (
    MID,
    XDI,
    XbusError,
    XbusMessage,
    XbusParser,
    XbusSample,
    checksum,
    decode_mtdata2,
    encode_message,
    encode_mtdata2,
    mtdata2_payload,
    parse_stream,
    read_device_map,
    write_device_map,
)

# formats.md / Scottapotamas/xsens-mti docs/mtmanager_packets.md example 6 (a real MTi-300)
GOLDEN = bytes.fromhex(
    "FA FF 36 26 10 20 02 46 82 10 60 04 01 C4 FC 3E 20 10 10 3F 71 CE 6C BE A5 6B CF 3C 61 3B"
    " D8 BD 69 1D 25 E0 20 04 00 40 00 03 12")
# mtmanager_packets.md example 1: MTData2 data of 139 bytes with 11 packets, and MT Manager's
# decoding of it.
EXAMPLE1_DATA = bytes.fromhex(
    "10 20 02 A6 55 10 60 04 00 57 47 2E 20 10 10 3F 7F 7D C4 BC 10 10 7D 3B A1 57 70 BD 7E C6"
    " 56 40 20 0C BD A2 1A F8 BE 2A 8E 96 41 1D 27 A2 40 10 0C B9 4F C8 00 B9 DA 24 00 3C C9 28"
    " 80 40 30 0C 3C 02 C8 9C 3C 35 F6 C8 3C DB 0C 00 80 20 0C BB B1 7D 81 BB 96 32 00 3C 01 E8"
    " 41 80 30 10 3F 80 00 00 B6 E3 30 01 B6 C0 40 00 37 26 48 00 C0 20 0C BE 99 9C 24 3F B6 1B"
    " 56 3F 16 6A EB 30 10 04 00 01 86 DE E0 20 04 00 40 00 03")


def _sample(rng: np.random.Generator, device_id: int, counter: int) -> XbusSample:
    q = rng.normal(size=4)
    return XbusSample(
        device_id=device_id, packet_counter=counter & 0xFFFF,
        sample_time_fine=(counter * 167) & 0xFFFFFFFF, quaternion=q / np.linalg.norm(q),
        acceleration=rng.normal(0, 3, 3) + np.array([0, 0, 9.81]),
        free_acceleration=rng.normal(0, 3, 3),
        rate_of_turn=rng.normal(0, 2, 3), status_word=0x00400003)


def _session(n_samples: int = 4, n_sensors: int = 5, seed: int = 0) -> list[XbusSample]:
    """couch's convention: one message per sensor per sample, sharing counter and time."""
    rng = np.random.default_rng(seed)
    return [_sample(rng, 0x00B40000 + s, 1000 + k)
            for k in range(n_samples) for s in range(n_sensors)]


def _assert_same(a: XbusSample, b: XbusSample, float32: bool = True) -> None:
    for name in ("device_id", "packet_counter", "sample_time_fine", "status_word",
                 "coordinate_frame"):
        assert getattr(a, name) == getattr(b, name), name
    for name in ("quaternion", "acceleration", "free_acceleration", "rate_of_turn",
                 "magnetic_field"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            want = np.asarray(x, np.float32) if float32 else x
            np.testing.assert_array_equal(y, want, err_msg=name)


# --------------------------------------------------------------------------- golden bytes


def test_goto_config_and_goto_measurement_bytes() -> None:
    assert encode_message(MID.GoToConfig) == bytes.fromhex("FA FF 30 00 D1")
    assert encode_message(MID.GoToMeasurement) == bytes.fromhex("FA FF 10 00 F1")
    assert encode_message(0x0C) == bytes.fromhex("FA FF 0C 00 F5")  # ReqConfiguration
    items, stats = parse_stream(bytes.fromhex("FA FF 31 00 D0"))  # GoToConfigAck as received
    assert items == [XbusMessage(mid=MID.GoToConfigAck, data=b"", offset=0)]
    assert stats.messages_ok == 1


def test_golden_vector_from_a_real_mti() -> None:
    items, stats = parse_stream(GOLDEN)
    assert len(items) == 1 and stats.samples == 1 and stats.bytes_skipped == 0
    s = items[0]
    assert isinstance(s, XbusSample)
    assert s.packet_counter == 18050 and s.sample_time_fine == 29686846
    assert s.status_word == 0x00400003 and s.coordinate_frame == "ENU"
    np.testing.assert_allclose(s.quaternion, [0.944556, -0.323088, 0.013747, -0.056913],
                               atol=1e-6)
    assert s.device_id is None and s.acceleration is None and s.unknown_xdis == ()
    assert not s.retransmitted
    # our encoder writes these fields in the same order and bytes as the device
    assert encode_mtdata2(s) == GOLDEN


def test_mt_manager_example_with_unmodelled_packets() -> None:
    message = encode_message(MID.MTData2, EXAMPLE1_DATA)
    assert message[:4] == bytes.fromhex("FA FF 36 8B")
    items, stats = parse_stream(message)
    s = items[0]
    assert s.packet_counter == 42581 and s.sample_time_fine == 5719854
    np.testing.assert_allclose(s.quaternion, [0.99801278, -0.00879299, 0.00492375, -0.06220087],
                               atol=5e-9)
    np.testing.assert_allclose(s.acceleration, [-0.07915300, -0.16655955, 9.82217598],
                               atol=5e-8)
    np.testing.assert_allclose(s.free_acceleration, [0.00798240, 0.01110620, 0.02673912],
                               atol=5e-9)
    np.testing.assert_allclose(s.rate_of_turn, [-0.00541657, -0.00458360, 0.00792891],
                               atol=5e-9)
    np.testing.assert_allclose(s.magnetic_field, [-0.30001938, 1.42270923, 0.58756894],
                               atol=5e-8)
    assert s.unknown_xdis == (0x4010, 0x8030, 0x3010)  # DeltaV, DeltaQ, BaroPressure
    assert stats.unknown_xdis == 3 and stats.bytes_ok == len(message)


def test_checksum_rule() -> None:
    for message in (GOLDEN, encode_message(0x42, b"\x29"), encode_message(0x36, bytes(300))):
        assert sum(message[1:]) & 0xFF == 0
    assert checksum(b"\xff\x30\x00") == 0xD1


def test_extended_length_messages() -> None:
    data = bytes(range(256)) + bytes(44)
    message = encode_message(0x77, data)
    assert message[:6] == bytes([0xFA, 0xFF, 0x77, 0xFF, 0x01, 0x2C])
    assert len(message) == 300 + 7
    parser = XbusParser()
    got = [item for i in range(0, len(message), 13) for item in parser.feed(message[i:i + 13])]
    assert got == [XbusMessage(mid=0x77, data=data, offset=0)]
    assert encode_message(0x77, bytes(254))[3] == 254  # largest standard length
    with pytest.raises(ValueError, match="8185"):
        encode_message(0x77, bytes(8186))


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("precision", ["float32", "float64"])
@pytest.mark.parametrize("frame", ["ENU", "NED", "NWU"])
def test_encode_parse_round_trip(precision: str, frame: str) -> None:
    samples = _session()
    for s in samples:
        s.coordinate_frame = frame
    samples[0].magnetic_field = np.array([0.3, -0.1, 0.9])
    samples[1].status_word |= 0x00040000
    stream = b"".join(encode_mtdata2(s, precision=precision) for s in samples)
    parser = XbusParser()
    rng = np.random.default_rng(1)
    got, i = [], 0
    while i < len(stream):
        step = int(rng.integers(1, 9))
        got += parser.feed(stream[i:i + step])
        i += step
    got += parser.flush()
    assert len(got) == len(samples)
    offset = 0
    for a, b in zip(samples, got, strict=True):
        _assert_same(a, b, float32=precision == "float32")
        assert b.offset == offset
        offset += len(encode_mtdata2(a, precision=precision))
    assert got[1].retransmitted and not got[2].retransmitted
    s = parser.stats
    assert (s.messages_ok, s.samples, s.bytes_skipped, s.checksum_errors, s.truncated) == \
        (len(samples), len(samples), 0, 0, 0)
    # DeviceId is carried, XDIs are in ascending order with precision and frame bits
    payload = mtdata2_payload(samples[0], precision=precision)
    xdis = []
    pos = 0
    while pos < len(payload):
        xdi, size = struct.unpack(">HB", payload[pos:pos + 3])
        xdis.append(xdi)
        pos += 3 + size
    low = {"float32": 0, "float64": 3}[precision] | {"ENU": 0, "NED": 4, "NWU": 8}[frame]
    assert xdis == [0x1020, 0x1060, 0x2010 | low, 0x4020 | low, 0x4030 | low, 0x8020 | low,
                    0xC020 | low, 0xE020, 0xE080]


def test_encoder_rejects_values_that_do_not_fit() -> None:
    with pytest.raises(ValueError, match="packet_counter"):
        mtdata2_payload(XbusSample(packet_counter=70000))
    with pytest.raises(ValueError, match="quaternion"):
        mtdata2_payload(XbusSample(quaternion=np.zeros(3)))
    with pytest.raises(ValueError, match="coordinate_frame"):
        mtdata2_payload(XbusSample(coordinate_frame="ECEF"))


def test_fixed_point_1220_and_unknown_precision() -> None:
    raw = struct.pack(">HB4i", XDI.Quaternion | 0x1, 16, 1 << 20, -(1 << 19), 0, 3)
    s = decode_mtdata2(raw)
    np.testing.assert_allclose(s.quaternion, [1.0, -0.5, 0.0, 3 / 2**20])
    fp1632 = struct.pack(">HB", XDI.RateOfTurn | 0x2, 18) + bytes(18)
    assert decode_mtdata2(fp1632).unknown_xdis == (0x8022,)


def test_decode_rejects_packets_that_do_not_fill_the_data() -> None:
    with pytest.raises(XbusError, match="declares 9 bytes but only 2 remain"):
        decode_mtdata2(bytes.fromhex("10 20 09 00 01"))
    with pytest.raises(XbusError, match="expected 2"):
        decode_mtdata2(bytes.fromhex("10 20 03 00 01 02"))
    with pytest.raises(XbusError, match="too short"):
        decode_mtdata2(bytes.fromhex("10 20 02 00 01 E0"))


# --------------------------------------------------------------------------- damaged streams


def test_corrupted_stream_recovers_every_intact_message_and_counts_exactly() -> None:
    samples = _session(n_samples=5, n_sensors=5)  # 25 messages
    messages = [encode_mtdata2(s) for s in samples]
    corrupt = {3, 7, 8, 15}  # 7 and 8 are adjacent
    cut = 11  # loses its last 10 bytes (a dropout): the next message starts inside its span
    garbage = {5: b"\x00\x13\x37noise", 20: b"\xfa\xfa\x01"}
    stream = bytearray()
    expected, skipped = [], 0
    for k, m in enumerate(messages):
        if k in garbage:
            stream += garbage[k]
            skipped += len(garbage[k])
        if k in corrupt:
            m = bytearray(m)
            m[10] ^= 0x5A  # a data byte: the checksum no longer holds
            skipped += len(m)
        elif k == cut:
            m = m[:-10]
            skipped += len(m)
        else:
            expected.append((len(stream), samples[k]))
        stream += m
    error = encode_message(MID.Error, bytes([41]))
    stream += error
    got, stats = parse_stream(bytes(stream))
    assert [g.offset for g in got[:-1]] == [off for off, _ in expected]
    for g, (_, s) in zip(got, expected, strict=False):
        _assert_same(s, g)
    assert got[-1].mid == MID.Error and got[-1].error_code == 41
    assert stats.checksum_errors == 4 and stats.truncated == 1 and stats.malformed == 0
    assert stats.bytes_skipped == skipped
    assert stats.messages_ok == len(expected) + 1 and stats.samples == len(expected)
    assert stats.error_messages == 1 and stats.error_codes == {41: 1}
    assert stats.bytes_in == stats.bytes_ok + stats.bytes_skipped == len(stream)


def test_stream_cut_at_the_end_counts_one_truncated_message() -> None:
    messages = [encode_mtdata2(s) for s in _session(n_samples=1, n_sensors=3)]
    stream = b"".join(messages)[:-7]
    parser = XbusParser()
    got = parser.feed(stream)
    assert len(got) == 2 and parser.buffered == len(messages[2]) - 7
    assert parser.flush() == []
    s = parser.stats
    assert s.truncated == 1 and s.checksum_errors == 0 and parser.buffered == 0
    assert s.bytes_skipped == len(messages[2]) - 7 and s.bytes_in == s.bytes_ok + s.bytes_skipped


def test_checksum_valid_but_malformed_mtdata2_is_rejected() -> None:
    bad = encode_message(MID.MTData2, bytes.fromhex("10 20 09 00 01"))
    good = encode_mtdata2(_session(1, 1)[0])
    got, stats = parse_stream(good + bad + good)
    assert [g.offset for g in got] == [0, len(good) + len(bad)]
    assert stats.malformed == 1 and stats.bytes_skipped == len(bad)


def test_other_bus_ids_are_ignored_unless_accepted() -> None:
    message = encode_message(0x36, mtdata2_payload(_session(1, 1)[0]), bid=0x01)
    assert parse_stream(message)[1].bytes_skipped == len(message)
    items, _ = parse_stream(message, bids=None)
    assert items[0].bid == 0x01


# --------------------------------------------------------------------------- properties


def _chunks(data: bytes, sizes: list[int]) -> list[bytes]:
    out, i, k = [], 0, 0
    while i < len(data):
        step = sizes[k % len(sizes)] if sizes else len(data)
        out.append(data[i:i + step])
        i += step
        k += 1
    return out


def _run(data: bytes, sizes: list[int]) -> tuple[list, XbusParser]:
    parser = XbusParser()
    got = [item for chunk in _chunks(data, sizes) for item in parser.feed(chunk)]
    got += parser.flush()
    return got, parser


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=600), sizes=st.lists(st.integers(1, 64), max_size=8))
def test_arbitrary_bytes_never_raise_and_every_byte_is_accounted(data: bytes,
                                                                  sizes: list[int]) -> None:
    got, parser = _run(data, sizes)
    s = parser.stats
    assert s.bytes_in == len(data) == s.bytes_ok + s.bytes_skipped
    assert s.messages_ok == len(got)
    # chunking never changes the outcome
    whole, one = _run(data, [])
    assert [(g.offset, type(g)) for g in got] == [(g.offset, type(g)) for g in whole]
    assert (s.checksum_errors, s.truncated, s.malformed) == \
        (one.stats.checksum_errors, one.stats.truncated, one.stats.malformed)


@settings(max_examples=200, deadline=None)
@given(payload=st.binary(max_size=120))
def test_any_mtdata2_data_decodes_or_raises_xbus_error(payload: bytes) -> None:
    try:
        sample = decode_mtdata2(payload)
    except XbusError:
        sample = None
    got, stats = parse_stream(encode_message(MID.MTData2, payload))
    assert stats.bytes_in == stats.bytes_ok + stats.bytes_skipped
    assert len(got) == (sample is not None) and stats.malformed == (sample is None)


# Garbage may hold any byte, 0xFA included, but not the pair FA FF: a preamble and a valid BID
# in noise start a candidate, and a candidate that reaches into the next message passes its
# checksum with probability 1/256, which no parser can tell from a real message.
# A gap may not end in FA either: two adjacent gaps would then spell FA FF across their seam.
garbage = st.binary(max_size=40).filter(lambda g: b"\xfa\xff" not in g
                                        and not g.endswith(b"\xfa"))


@settings(max_examples=150, deadline=None)
@given(n=st.integers(0, 8), seed=st.integers(0, 2**16), gaps=st.lists(garbage, max_size=9),
       sizes=st.lists(st.integers(1, 50), max_size=6), mixed=st.booleans())
def test_garbage_between_messages_never_loses_a_message(n: int, seed: int, gaps: list[bytes],
                                                        sizes: list[int], mixed: bool) -> None:
    rng = np.random.default_rng(seed)
    items: list[bytes] = []
    for k in range(n):
        if mixed and k % 3 == 2:
            # any MID but MTData2's: random bytes there are a malformed sample, not a message
            mid = int(rng.integers(0, 255))
            mid += mid >= MID.MTData2
            items.append(encode_message(mid, rng.bytes(int(rng.integers(0, 300)))))
        else:
            items.append(encode_mtdata2(_sample(rng, 0x00B40000 + k, k),
                                        precision="float64" if k % 2 else "float32"))
    stream, offsets = bytearray(), []
    for k in range(max(n, len(gaps))):
        if k < len(gaps):
            stream += gaps[k]
        if k < n:
            offsets.append(len(stream))
            stream += items[k]
    got, parser = _run(bytes(stream), sizes)
    assert [g.offset for g in got] == offsets
    assert parser.stats.bytes_skipped == sum(map(len, gaps))
    assert parser.stats.bytes_ok == sum(map(len, items))


# --------------------------------------------------------------------------- device map


def test_device_map_round_trip_and_errors(tmp_path: Path) -> None:
    mapping = {0x00B4A1C2: "Pelvis", 0x00B4A1C3: "T8", 0x00000001: "LeftFoot"}
    path = tmp_path / "devices.json"
    write_device_map(path, mapping)
    doc = json.loads(path.read_text())
    assert doc["devices"]["00B4A1C2"] == "Pelvis" and doc["version"] == 1
    assert read_device_map(path) == mapping
    with pytest.raises(ValueError, match="'Pelvis' is given to devices"):
        write_device_map(tmp_path / "dup.json", {1: "Pelvis", 2: "Pelvis"})
    with pytest.raises(ValueError, match="uint32"):
        write_device_map(tmp_path / "big.json", {1 << 32: "Pelvis"})
    path.write_text('{"format": "couch.xbus.device_map", "version": 1, "devices": {"zz": "T8"}}')
    with pytest.raises(XbusError, match=r"devices\.json.*'zz' is not hexadecimal"):
        read_device_map(path)
    path.write_text("{not json")
    with pytest.raises(XbusError, match=r"devices\.json: line 1, column 2: not valid JSON"):
        read_device_map(path)
    path.write_text('{"devices": {}}')
    with pytest.raises(XbusError, match="format"):
        read_device_map(path)
