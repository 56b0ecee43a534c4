"""Simulated Xsens suit: the frame change is the axis permutation, a perfect suit reproduces the
SMPL motion, every injected error (clock, heading, misalignment, noise, drift) is measured back
from the outputs with what the config asked for, the MVNX and Xbus outputs parse with independent
readers, damage to the Xbus stream is exactly what the truth says, and the inertial signals obey
physics (gravity at rest, the gyro integrates to the orientation change)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from couch.body import JOINT_INDEX, JOINT_NAMES, standing_pose
from couch.capture.mvnx import (
    FOOT_CONTACTS,
    MVN_SEGMENTS,
    MVN_SENSORS,
    MVN_TO_SMPL,
    NAMESPACE,
    couch_to_mvn_positions,
    couch_to_mvn_quaternions,
    mvn_timecode,
    mvn_to_couch_positions,
    mvn_to_couch_quaternions,
    read_mvnx,
    smpl_segment_indices,
    write_mvnx,
)
from couch.capture.xbus import (
    STATUS_RETRANSMITTED,
    XbusParser,
    XbusSample,
    parse_stream,
    read_device_map,
    write_device_map,
)
from couch.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_quat,
    quat_to_matrix,
    rotation_angle,
)
from couch.tools.sim.imu import (
    BodyTrack,
    ImuConfig,
    body_track_from_model,
    simulate_mvnx,
    simulate_xbus,
    smooth_random_walk,
)

RATE = 120.0  # track rate; the suit samples every other track frame when the clocks agree
NS = "{" + NAMESPACE + "}"
SMPL_IDX = smpl_segment_indices(MVN_SEGMENTS)  # (24,) MVN segment of each SMPL joint
# the SMPL joint whose rotation each sensor's segment has (first in SMPL order, as MVN_TO_SMPL)
SENSOR_JOINT = np.array([next(JOINT_INDEX[j] for j, s in MVN_TO_SMPL.items() if s == label)
                         for label in MVN_SENSORS])


def _motion(seconds: float, *, yaw_rate: float = 0.5) -> dict[str, np.ndarray]:
    """Smooth synthetic motion: the pelvis turns at ``yaw_rate`` rad/s and walks, the spine
    bends, an arm swings, an elbow flexes, one knee bends."""
    n = round(seconds * RATE) + 1
    t = np.arange(n) / RATE
    w = 2 * np.pi * 0.5 * t
    go = np.stack([0.1 * np.sin(w), yaw_rate * t, 0.05 * np.sin(0.7 * w)], -1)
    bp = np.tile(standing_pose(), (n, 1)).reshape(n, 23, 3).astype(np.float64)
    bp[:, JOINT_INDEX["spine1"] - 1, 0] += 0.3 * (1 - np.cos(w))
    bp[:, JOINT_INDEX["right_shoulder"] - 1, 2] += 0.6 * np.sin(w)
    bp[:, JOINT_INDEX["left_elbow"] - 1, 1] += -0.5 * (1 - np.cos(1.3 * w))
    bp[:, JOINT_INDEX["right_knee"] - 1, 0] += 0.4 * (1 - np.cos(w))
    tr = np.stack([0.3 * t, 0.9 + 0.02 * np.sin(w), 0.4 * t], -1)
    return {"time": t, "global_orient": go, "body_pose": bp.reshape(n, -1), "transl": tr}


@pytest.fixture(scope="module")
def track(coarse_model) -> BodyTrack:
    """6 s of motion at 120 Hz on the Kinect clock, shaped body."""
    betas = np.zeros(10)
    betas[:2] = [0.8, -0.5]
    return body_track_from_model(coarse_model, betas=betas, **_motion(6.0))


def _still_track(coarse_model, seconds: float, *, yaw: float = 0.0,
                 pose: np.ndarray | None = None) -> BodyTrack:
    """A body standing still (two frames suffice: the suit interpolates)."""
    go = np.array([[0.0, yaw, 0.0]] * 2)
    bp = np.tile(standing_pose() if pose is None else pose, (2, 1))
    return body_track_from_model(coarse_model, time=[0.0, seconds], global_orient=go,
                                 body_pose=bp, transl=np.array([[0.2, 0.9, -0.3]] * 2),
                                 betas=np.zeros(10))


def _mvn_rotations(track: BodyTrack, frames: np.ndarray) -> np.ndarray:
    """(K, 24, 3, 3) the track's SMPL global rotations expressed in MVN axes."""
    return quat_to_matrix(couch_to_mvn_quaternions(matrix_to_quat(track.joint_rotations[frames])))


def _yaw(rot: np.ndarray) -> np.ndarray:
    """Rotation angle about MVN's Z of (..., 3, 3) rotations about Z."""
    return np.arctan2(rot[..., 1, 0], rot[..., 0, 0])


def _rz(a: np.ndarray | float) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return axis_angle_to_matrix(np.stack(np.broadcast_arrays(0 * a, 0 * a, a), -1))


# --------------------------------------------------------------------------- body track


def test_body_track_from_model(coarse_model, track: BodyTrack) -> None:
    assert track.joint_rotations.shape == (len(track.time), 24, 3, 3)
    eye = np.einsum("nkij,nkil->nkjl", track.joint_rotations, track.joint_rotations)
    np.testing.assert_allclose(eye, np.broadcast_to(np.eye(3), eye.shape), atol=1e-5)
    # the rest skeleton stands on the floor with the pelvis above the origin
    rest = track.rest_skeleton()
    assert rest[0, 0] == pytest.approx(0) and rest[0, 2] == pytest.approx(0)
    assert 0.0 < rest[JOINT_INDEX["left_foot"], 1] < 0.1
    # without it, the bones come from the first frame (rigid SMPL bones)
    derived = BodyTrack(track.time, track.joint_rotations, track.joints, track.betas)
    bones = lambda r: r[1:] - r[[0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17,  # noqa: E731
                                 18, 19, 20, 21]]
    np.testing.assert_allclose(bones(derived.rest_skeleton()), bones(rest), atol=1e-5)
    with pytest.raises(ValueError, match="joint_rotations"):
        BodyTrack(track.time, track.joint_rotations[:, :5], track.joints, track.betas)


# --------------------------------------------------------------------------- frames


def test_frame_change_is_the_axis_permutation(coarse_model) -> None:
    # P maps MVN axes (X forward, Y left, Z up) onto ours (X left, Y up, Z forward); it is a
    # proper rotation, and the helpers implement R -> Pᵀ R P on quaternions.
    p = np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], dtype=float)
    assert np.linalg.det(p) == pytest.approx(1.0)
    np.testing.assert_array_equal(mvn_to_couch_positions(np.eye(3)), p.T)  # columns = P e_i
    rng = np.random.default_rng(1)
    r = axis_angle_to_matrix(rng.normal(size=(50, 3)))
    q_mvn = couch_to_mvn_quaternions(matrix_to_quat(r))
    np.testing.assert_allclose(quat_to_matrix(q_mvn), p.T @ r @ p, atol=1e-12)

    # Our T-pose rest (identity global rotations, facing +Z) is MVN's identity pose facing +X.
    tpose = _still_track(coarse_model, 1.0, pose=np.zeros(69))
    rec, _ = simulate_mvnx(tpose, ImuConfig.perfect(), np.random.default_rng(0))
    np.testing.assert_allclose(np.abs(rec.orientation[..., 0]), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.abs(rec.sensor_orientation[..., 0]), 1.0, atol=1e-6)
    seg = {s: i for i, s in enumerate(MVN_SEGMENTS)}
    pos = rec.position[0] - rec.position[0, seg["Pelvis"]]
    assert pos[seg["LeftHand"], 1] > 0.5 > -0.5 > pos[seg["RightHand"], 1]  # left = +Y
    assert pos[seg["Head"], 2] > 0.4  # up = +Z
    assert pos[seg["LeftToe"], 0] > pos[seg["LeftFoot"], 0] + 0.05  # toes forward = +X
    # the identity calibration pose is the same T-pose standing on MVN's floor, pelvis at x=y=0
    ident = rec.calibration["identity"]
    np.testing.assert_allclose(ident.position[0, :2], 0.0, atol=1e-9)
    assert ident.position[:, 2].min() > 0.0

    # A body turned to face our +X (the left) faces MVN's +Y: a +90° turn about MVN's Z.
    turned = _still_track(coarse_model, 1.0, yaw=np.pi / 2, pose=np.zeros(69))
    rec, _ = simulate_mvnx(turned, ImuConfig.perfect(), np.random.default_rng(0))
    np.testing.assert_allclose(quat_to_matrix(rec.orientation[:, 0]),
                               np.broadcast_to(_rz(np.pi / 2), (rec.n_frames, 3, 3)), atol=1e-6)


def test_perfect_suit_reproduces_the_smpl_motion(track: BodyTrack, tmp_path: Path) -> None:
    rec, truth = simulate_mvnx(track, ImuConfig.perfect(), np.random.default_rng(0))
    k = rec.n_frames
    assert k == 361 and np.allclose(truth.kinect_time, np.arange(k) / 60.0)
    frames = np.arange(k) * 2  # IMU sample k is Kinect time k/60 = track frame 2k
    path = tmp_path / "perfect.mvnx"
    write_mvnx(path, rec)
    for source, atol in ((rec, 1e-6), (read_mvnx(path), 2e-6)):
        q = mvn_to_couch_quaternions(source.orientation)[:, SMPL_IDX]  # (K, 24, 4)
        err = rotation_angle(np.swapaxes(quat_to_matrix(q), -1, -2)
                             @ track.joint_rotations[frames])
        assert err.max() < atol * 10, JOINT_NAMES[int(np.argmax(err.max(0)))]
        # segment origins are the SMPL joints (the hand joints take the wrist's segment)
        p = mvn_to_couch_positions(source.position)[:, SMPL_IDX]
        body = [j for j in range(24) if j not in (22, 23)]
        np.testing.assert_allclose(p[:, body], track.joints[frames][:, body], atol=atol * 5)
    np.testing.assert_allclose(truth.orientation_ideal, truth.orientation, atol=1e-9)
    np.testing.assert_allclose(truth.position_ideal, truth.position, atol=1e-9)


# --------------------------------------------------------------------------- file formats


def test_mvnx_parses_with_a_plain_xml_parser_and_read_mvnx(track: BodyTrack,
                                                            tmp_path: Path) -> None:
    start = 1_600_000_000_123
    rec, truth = simulate_mvnx(track, ImuConfig(), np.random.default_rng(3), start_unix_ms=start)
    path = tmp_path / "suit.mvnx"
    write_mvnx(path, rec)
    root = ET.parse(path).getroot()  # non-streaming, independent of the reader
    assert root.tag == NS + "mvnx"
    subject = root.find(NS + "subject")
    assert subject is not None and subject.get("frameRate") == "60"
    assert subject.get("segmentCount") == "23" and subject.get("configuration") == "FullBody"
    assert [s.get("label") for s in subject.iter(NS + "sensor")] == list(MVN_SENSORS)
    frames = subject.find(NS + "frames")
    assert frames is not None and frames.get("sensorCount") == "17"
    normal = [f for f in frames if f.get("type") == "normal"]
    assert [f.get("type") for f in frames if f.get("type") != "normal"] == ["identity", "tpose"]
    assert len(normal) == rec.n_frames
    first, last = normal[0], normal[-1]
    assert first.get("time") == "0" and first.get("ms") == str(start)
    assert int(last.get("time")) == round(1000 * (rec.n_frames - 1) / 60)
    assert last.get("tc") == mvn_timecode([int(last.get("ms"))], 60)[0]
    quat = np.array(last.find(NS + "orientation").text.split(), dtype=float).reshape(23, 4)
    np.testing.assert_allclose(quat, rec.orientation[-1], atol=1e-6)
    contacts = last.find(NS + "footContacts").text.split()
    assert contacts == [str(int(c)) for c in rec.foot_contacts[-1]]

    back = read_mvnx(path)
    assert back.segment_labels == list(MVN_SEGMENTS) and back.sensor_labels == list(MVN_SENSORS)
    np.testing.assert_array_equal(back.time_ms, rec.time_ms)
    np.testing.assert_array_equal(back.unix_ms, start + rec.time_ms)
    assert back.timecode == rec.timecode
    assert back.foot_contact_labels == list(FOOT_CONTACTS)
    for name in ("orientation", "position", "velocity", "acceleration", "angular_velocity",
                 "sensor_orientation", "sensor_free_acceleration"):
        np.testing.assert_allclose(getattr(back, name), getattr(rec, name), atol=1e-6,
                                   err_msg=name)
    np.testing.assert_array_equal(back.foot_contacts, rec.foot_contacts)
    np.testing.assert_allclose(back.orientation, truth.orientation, atol=1e-6)
    # body dimensions: the segment points are the rest skeleton's bones (MVN axes)
    rest = track.rest_skeleton()
    bone = couch_to_mvn_positions(rest[JOINT_INDEX["left_knee"]] - rest[JOINT_INDEX["left_hip"]])
    np.testing.assert_allclose(back.segment_points["LeftUpperLeg"]["jLeftKnee"], bone, atol=1e-6)


def test_xbus_stream_parses_with_all_checksums_valid(track: BodyTrack, tmp_path: Path) -> None:
    config = ImuConfig(corrupt_rate=0.0, truncate_rate=0.0, drop_rate=0.0, retransmit_rate=0.01)
    stream, device_map, truth = simulate_xbus(track, config, np.random.default_rng(5))
    items, stats = parse_stream(stream)
    k = len(truth.imu_time)
    assert stats.messages_ok == stats.samples == 17 * k == len(items)
    assert stats.bytes_ok == stats.bytes_in == len(stream)
    assert stats.checksum_errors == stats.malformed == stats.truncated == stats.unknown_xdis == 0
    assert sorted(device_map.values()) == sorted(MVN_SENSORS)
    write_device_map(tmp_path / "devices.json", device_map)
    assert read_device_map(tmp_path / "devices.json") == device_map

    sensor_of = {dev: MVN_SENSORS.index(label) for dev, label in device_map.items()}
    sample_of = {int(c): i for i, c in enumerate(truth.packet_counter)}  # K < 65536: unique
    seen = np.zeros((k, 17), dtype=bool)
    for item in items:
        assert isinstance(item, XbusSample) and item.coordinate_frame == "ENU"
        i, s = sample_of[item.packet_counter], sensor_of[item.device_id]
        seen[i, s] = True
        assert item.sample_time_fine == truth.sample_time_fine[i]
        assert item.status_word == truth.status_word[i, s]
        np.testing.assert_allclose(item.quaternion, truth.quaternion[i, s], atol=1e-6)
        np.testing.assert_allclose(item.acceleration, truth.acceleration[i, s], rtol=1e-6,
                                   atol=1e-5)
        np.testing.assert_allclose(item.free_acceleration, truth.free_acceleration[i, s],
                                   rtol=1e-6, atol=1e-5)
        np.testing.assert_allclose(item.rate_of_turn, truth.rate_of_turn[i, s], rtol=1e-6,
                                   atol=1e-6)
    assert seen.all()
    # serial order: sample order, except retransmitted samples that arrive a few samples late
    order = np.array([sample_of[it.packet_counter] for it in items])
    late = np.array([it.retransmitted for it in items])
    assert late.sum() == truth.retransmitted.sum() > 0
    assert np.all(np.diff(order[~late]) >= 0)
    assert np.all(truth.status_word[truth.msg_sample[truth.retransmitted],
                                    truth.msg_sensor[truth.retransmitted]]
                  & STATUS_RETRANSMITTED)


def test_xbus_damage_is_exactly_what_the_truth_says(track: BodyTrack) -> None:
    config = ImuConfig(corrupt_rate=0.02, truncate_rate=0.01, drop_rate=0.01)
    stream, _, truth = simulate_xbus(track, config, np.random.default_rng(11))
    assert truth.damaged.sum() > 50 and truth.dropped.sum() > 20
    order = np.flatnonzero(truth.intact)  # stream order
    want = truth.msg_offset[order]
    # whole stream at once, and fed in random chunks as a serial port delivers it
    items, stats = parse_stream(stream)
    parser = XbusParser()
    chunked = []
    cuts = np.sort(np.random.default_rng(0).choice(len(stream), 300, replace=False))
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(stream)], strict=True):
        chunked += parser.feed(stream[a:b])
    chunked += parser.flush()
    for got, st in ((items, stats), (chunked, parser.stats)):
        np.testing.assert_array_equal([it.offset for it in got], want)
        assert st.checksum_errors + st.malformed + st.truncated == truth.damaged.sum()
        assert st.bytes_ok == truth.msg_length[order].sum()
    # the recovered messages carry their own, undamaged content
    for it, m in zip(items, order, strict=True):
        i, s = truth.msg_sample[m], truth.msg_sensor[m]
        assert it.device_id == truth.device_ids[s]
        assert it.packet_counter == truth.packet_counter[i]
        np.testing.assert_allclose(it.quaternion, truth.quaternion[i, s], atol=1e-6)


# --------------------------------------------------------------------------- injected errors


def test_clock_offset_and_drift_are_recovered_from_the_outputs(coarse_model) -> None:
    # The pelvis turns at a known constant rate, so each sample's orientation tells its Kinect
    # time; the IMU time comes from the file's time/ms fields and the stream's SampleTimeFine.
    omega = 1.0  # rad/s
    n = int(20 * RATE) + 1
    t = np.arange(n) / RATE
    go = np.stack([0 * t, omega * t, 0 * t], -1)
    body = body_track_from_model(coarse_model, t, go, np.zeros((n, 69)),
                                 np.tile([0.0, 0.9, 0.0], (n, 1)), np.zeros(10))
    ppm, offset, start = 80.0, -0.7301, 1_650_000_000_000
    config = ImuConfig.perfect(drift_ppm=ppm, clock_offset=offset,
                               sample_time_fine_start=2**32 - 50_000)
    rec, truth = simulate_mvnx(body, config, np.random.default_rng(0), start_unix_ms=start)
    kinect = np.unwrap(_yaw(quat_to_matrix(rec.orientation[:, 0]))) / omega
    for t_imu in (rec.time_ms / 1000.0, (rec.unix_ms - start) / 1000.0):
        slope, intercept = np.polyfit(kinect, t_imu, 1)
        assert (slope - 1) * 1e6 == pytest.approx(ppm, abs=6.0)
        assert intercept == pytest.approx(offset, abs=5e-4)
    assert truth.clock_scale == 1 + ppm * 1e-6 and truth.clock_offset == offset
    np.testing.assert_allclose(truth.kinect_to_imu(truth.kinect_time), truth.imu_time)
    np.testing.assert_allclose(truth.imu_to_kinect(truth.imu_time), truth.kinect_time)

    stream, device_map, xtruth = simulate_xbus(body, config, np.random.default_rng(0))
    pelvis = next(dev for dev, label in device_map.items() if label == "Pelvis")
    samples = [it for it in parse_stream(stream)[0] if it.device_id == pelvis]
    stf = np.array([it.sample_time_fine for it in samples], dtype=np.int64)
    assert np.any(np.diff(stf) < 0)  # the 32-bit tick counter wrapped during the recording
    ticks = np.concatenate([[0], np.cumsum(np.diff(stf) % 2**32)])
    quats = np.array([it.quaternion for it in samples])
    kinect = np.unwrap(_yaw(quat_to_matrix(quats))) / omega
    slope, intercept = np.polyfit(kinect, ticks / 1e4, 1)
    assert (slope - 1) * 1e6 == pytest.approx(ppm, abs=1.0)
    assert intercept == pytest.approx(offset, abs=2e-4)
    np.testing.assert_array_equal(xtruth.imu_time, truth.imu_time)


def test_samples_before_the_track_hold_the_first_pose(track: BodyTrack) -> None:
    rec, truth = simulate_mvnx(track, ImuConfig.perfect(clock_offset=0.5),
                               np.random.default_rng(0))
    assert truth.in_track.sum() == rec.n_frames - 30 and not truth.in_track[:30].any()
    np.testing.assert_allclose(rec.orientation[:30], rec.orientation[:1].repeat(30, 0),
                               atol=1e-12)
    assert truth.kinect_time[0] == pytest.approx(-0.5)


def test_heading_offset_and_drift_are_as_configured(track: BodyTrack) -> None:
    config = ImuConfig.perfect(heading_offset_deg=37.0, heading_drift_deg_per_min=30.0)
    rec, truth = simulate_mvnx(track, config, np.random.default_rng(2))
    k = rec.n_frames
    out = quat_to_matrix(rec.orientation[:, SMPL_IDX])
    err = out @ np.swapaxes(_mvn_rotations(track, np.arange(k) * 2), -1, -2)  # = Rz(-ψ(t))
    psi = -np.unwrap(_yaw(err), axis=0)
    np.testing.assert_allclose(psi, np.broadcast_to(psi[:, :1], psi.shape), atol=1e-6)
    slope, intercept = np.polyfit(rec.time_ms / 1000.0, psi[:, 0], 1)
    assert np.rad2deg(intercept) == pytest.approx(37.0, abs=0.01)
    assert np.rad2deg(slope) * 60 == pytest.approx(30.0, rel=1e-3)
    np.testing.assert_allclose(truth.heading, psi[:, 0], atol=1e-6)
    assert truth.heading_offset == pytest.approx(np.deg2rad(37.0))
    # positions: the same heading turns the walk (no other position error is configured)
    np.testing.assert_allclose(rec.position[0], truth.position_ideal[0], atol=1e-9)
    assert np.abs(rec.position - truth.position_ideal).max() > 0.01


def test_misalignment_and_sensor_placement_are_as_configured(track: BodyTrack) -> None:
    config = ImuConfig.perfect(heading_offset_deg=-120.0, misalignment_deg=4.0, mount_deg=20.0)
    rec, truth = simulate_mvnx(track, config, np.random.default_rng(4))
    k = rec.n_frames
    true = _mvn_rotations(track, np.arange(k) * 2)
    # reported = Rz(ψ0)ᵀ R M: the measured M must be constant in time and the one declared
    out = quat_to_matrix(rec.orientation[:, SMPL_IDX])
    m_hat = np.swapaxes(true, -1, -2) @ _rz(np.deg2rad(-120.0)) @ out  # (K, 24, 3, 3)
    spread = rotation_angle(np.swapaxes(m_hat[:1], -1, -2) @ m_hat)
    assert spread.max() < 1e-5
    m_truth = quat_to_matrix(truth.misalignment)[SMPL_IDX]
    assert rotation_angle(np.swapaxes(m_truth, -1, -2) @ m_hat[0]).max() < 1e-5
    angles = np.rad2deg(rotation_angle(quat_to_matrix(truth.misalignment)))
    assert 2.0 < np.sqrt(np.mean(angles**2)) < 6.0
    # MVN's belief of the sensor-to-segment rotation, R_segᵀ R_sensor, is constant: Mᵀ·mount
    seg = quat_to_matrix(rec.orientation[:, [MVN_SEGMENTS.index(s) for s in MVN_SENSORS]])
    believed = np.swapaxes(seg, -1, -2) @ quat_to_matrix(rec.sensor_orientation)
    seg_m = quat_to_matrix(truth.misalignment)[[MVN_SEGMENTS.index(s) for s in MVN_SENSORS]]
    expected = np.swapaxes(seg_m, -1, -2) @ quat_to_matrix(truth.mount)
    assert rotation_angle(np.swapaxes(expected, -1, -2) @ believed).max() < 1e-5
    mounts = np.rad2deg(rotation_angle(quat_to_matrix(truth.mount)))
    assert 10.0 < np.sqrt(np.mean(mounts**2)) < 30.0
    # limbs hang from misaligned segments: the joints move by a few centimetres
    shift = np.linalg.norm(rec.position - truth.position_ideal, axis=-1)
    assert 0.005 < shift.max() < 0.3


def test_orientation_noise_has_the_configured_rms_and_is_smooth(track: BodyTrack) -> None:
    config = ImuConfig.perfect(tilt_noise_deg=0.8, heading_noise_deg=1.6, noise_corr_time=0.3)
    rec, truth = simulate_mvnx(track, config, np.random.default_rng(8))
    k = rec.n_frames
    true = _mvn_rotations(track, np.arange(k) * 2)[:, SENSOR_JOINT]  # mount = identity here
    err = matrix_to_axis_angle(quat_to_matrix(rec.sensor_orientation)
                               @ np.swapaxes(true, -1, -2))  # (K, 17, 3), global frame
    tilt = np.rad2deg(np.sqrt(np.mean(err[..., 0] ** 2 + err[..., 1] ** 2)))
    heading = np.rad2deg(np.sqrt(np.mean(err[..., 2] ** 2)))
    assert tilt == pytest.approx(0.8, rel=0.2)
    assert heading == pytest.approx(1.6, rel=0.2)
    # correlated over time, not white: neighbouring samples agree, distant ones do not
    x = err[..., 2] - err[..., 2].mean(0)
    corr = lambda lag: np.sum(x[lag:] * x[:-lag]) / np.sum(x * x)  # noqa: E731
    assert corr(1) > 0.95 and corr(60) < 0.3
    np.testing.assert_allclose(quat_to_matrix(truth.orientation_noise),
                               axis_angle_to_matrix(err), atol=1e-6)


def test_position_drift_is_as_configured(coarse_model) -> None:
    # 10 minutes of standing still (sampled at 10 Hz to keep the test fast): every pelvis
    # position error is the drift
    still = _still_track(coarse_model, 600.0)
    walk, heading_walk, rate = 0.05, 2.0, 10
    config = ImuConfig.perfect(position_walk_m_per_sqrt_min=walk, vertical_bias_std=0.02,
                               heading_walk_deg_per_sqrt_min=heading_walk, drift_smoothing_s=0.2,
                               frame_rate=rate)
    rec, truth = simulate_mvnx(still, config, np.random.default_rng(9))
    ideal = couch_to_mvn_positions(still.joints[0, 0])
    error = rec.position[:, 0] - ideal
    np.testing.assert_allclose(error, truth.position_drift, atol=1e-9)
    np.testing.assert_allclose(error[:, 2], truth.vertical_bias, atol=1e-9)
    assert truth.vertical_bias != 0.0
    assert np.abs(np.diff(error[:, :2], axis=0)).max() < 5e-3  # smooth: < 5 mm per 0.1 s
    # random walk: increments over Δ = 3 s have variance σ²·(Δ - 2s/√π) per axis (a walk
    # smoothed by a Gaussian of std s loses E|u - v| = 2s/√π of each increment)
    lag, delta = 3 * rate, 3.0
    effective = (delta - 2 * 0.2 / np.sqrt(np.pi)) / 60  # minutes
    var = np.var(np.diff(error[::lag, :2], axis=0))
    assert var / (walk**2 / 2 * effective) == pytest.approx(1.0, abs=0.3)
    var = np.var(np.diff(truth.heading_drift[::lag]))
    assert var / (np.deg2rad(heading_walk) ** 2 * effective) == pytest.approx(1.0, abs=0.3)
    # the helper's end-point spread over many walks
    walks = smooth_random_walk(np.random.default_rng(0), 600, 2000, 0.1, 1.0, 1.0)
    assert np.var(walks[-1]) == pytest.approx(59.9, rel=0.1)


def test_one_generator_state_is_one_session(track: BodyTrack) -> None:
    config = ImuConfig()
    rec, truth = simulate_mvnx(track, config, np.random.default_rng(21))
    _, _, xtruth = simulate_xbus(track, config, np.random.default_rng(21))
    for name in ("heading_offset", "earth_heading", "heading_drift", "mount",
                 "orientation_noise", "acc_bias", "gyro_bias", "kinect_time"):
        np.testing.assert_array_equal(getattr(xtruth, name), getattr(truth, name), err_msg=name)
    # default clock: 40 ppm, the IMU starts 0.5 s (Kinect) after the track
    assert truth.drift_ppm == 40.0 and truth.kinect_time[0] == pytest.approx(0.5)
    # E is MVN's frame turned by earth_heading about Z
    in_e = _rz(-truth.earth_heading) @ quat_to_matrix(rec.sensor_orientation)
    assert rotation_angle(np.swapaxes(in_e, -1, -2)
                          @ quat_to_matrix(xtruth.quaternion)).max() < 1e-6
    # default errors are realistic in size: a few degrees, a few centimetres
    err = rotation_angle(np.swapaxes(quat_to_matrix(truth.orientation_ideal), -1, -2)
                         @ _rz(-truth.heading_drift)[:, None].swapaxes(-1, -2)
                         @ quat_to_matrix(truth.orientation))
    assert 1.0 < np.rad2deg(np.sqrt(np.mean(err**2))) < 8.0


# --------------------------------------------------------------------------- physics


def test_accelerometer_at_rest_reads_gravity_up(coarse_model) -> None:
    still = _still_track(coarse_model, 3.0)
    _, _, truth = simulate_xbus(still, ImuConfig.perfect(mount_deg=30.0),
                                np.random.default_rng(0))
    up = np.einsum("ksij,ksj->ksi", quat_to_matrix(truth.quaternion), truth.acceleration)
    np.testing.assert_allclose(up, np.broadcast_to([0, 0, 9.81], up.shape), atol=1e-9)
    np.testing.assert_allclose(truth.free_acceleration, 0.0, atol=1e-9)
    np.testing.assert_allclose(truth.rate_of_turn, 0.0, atol=1e-9)
    assert np.abs(truth.acceleration[..., 2]).min() < 9.5  # tilted sensors: not along their z

    _, _, noisy = simulate_xbus(still, ImuConfig(), np.random.default_rng(0))
    up = np.einsum("ksij,ksj->ksi", quat_to_matrix(noisy.quaternion), noisy.acceleration)
    np.testing.assert_allclose(up.mean(0), np.broadcast_to([0, 0, 9.81], (17, 3)), atol=0.2)
    assert np.linalg.norm(noisy.acceleration, axis=-1).mean() == pytest.approx(9.81, abs=0.05)
    assert np.abs(noisy.rate_of_turn).max() < np.deg2rad(1.0)  # bias + noise only


def test_gyro_integrates_to_the_orientation_change(track: BodyTrack) -> None:
    config = ImuConfig.perfect(mount_deg=25.0, heading_offset_deg=50.0, earth_heading_deg=-10.0)
    _, _, truth = simulate_xbus(track, config, np.random.default_rng(6))
    dt = 1.0 / truth.frame_rate
    q = quat_to_matrix(truth.quaternion)  # (K, 17, 3, 3)
    w = truth.rate_of_turn
    steps = axis_angle_to_matrix(0.5 * (w[1:] + w[:-1]) * dt)  # trapezoid, body frame
    rot = q[0]
    worst = 0.0
    for i in range(len(steps)):
        rot = rot @ steps[i]
        worst = max(worst, float(rotation_angle(np.swapaxes(rot, -1, -2) @ q[i + 1]).max()))
    assert np.rad2deg(worst) < 0.2  # 0.045° over 6 s at up to 170 °/s
    total = np.rad2deg(rotation_angle(np.swapaxes(q[0], -1, -2) @ q[-1]))
    assert total.max() > 60.0  # the test motion does turn the sensors


def test_free_acceleration_matches_the_motion(track: BodyTrack) -> None:
    rec, _ = simulate_mvnx(track, ImuConfig.perfect(), np.random.default_rng(0))
    # the pelvis sensor sits on the pelvis segment: its free acceleration follows the pelvis's
    # acceleration up to the lever-arm terms of a turning, slowly bending body
    pelvis = rec.sensor_free_acceleration[:, 0]
    seg_acc = rec.acceleration[:, 0]
    assert np.sqrt(np.mean((pelvis - seg_acc)[5:-5] ** 2)) < 0.3
    assert np.sqrt(np.mean(seg_acc**2)) > 0.05


def test_foot_contacts_follow_the_feet(coarse_model) -> None:
    standing = _still_track(coarse_model, 1.0)
    rec, _ = simulate_mvnx(standing, ImuConfig.perfect(), np.random.default_rng(0))
    assert rec.foot_contacts.all()
    pose = standing_pose().reshape(23, 3)
    pose[JOINT_INDEX["left_hip"] - 1] = np.deg2rad([-60, 0, 0])
    pose[JOINT_INDEX["left_knee"] - 1] = np.deg2rad([60, 0, 0])
    lifted = _still_track(coarse_model, 1.0, pose=pose.reshape(-1))
    rec, _ = simulate_mvnx(lifted, ImuConfig.perfect(), np.random.default_rng(0))
    assert not rec.foot_contacts[:, :2].any() and rec.foot_contacts[:, 2:].all()
