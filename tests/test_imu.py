"""MVNX → SMPL conversion (capture/imu.py) against the simulated suit's ground truth.

Simulator settings: a 4 s motion of the coarse bundled body (betas[:2] = 0.8, -0.5) at 120 Hz,
suit at 60 Hz; ``ImuConfig.perfect()`` (no error, MVN heading 0, no recentring) for the exact
checks and ``ImuConfig()`` defaults (3° misalignment, 0.5°/1° fusion noise, heading drift 2°/min,
random heading, recentring, 3 cm/√min position walk) with seed 5 for the error-magnitude check.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from couch.body import JOINT_INDEX, JOINT_NAMES, standing_pose
from couch.capture.imu import HAND_TO_FOREARM, ImuConversionError, mvnx_to_smpl
from couch.capture.mvnx import (
    MVN_SEGMENTS,
    MVN_SENSORS,
    mvn_to_couch_positions,
    mvn_to_couch_quaternions,
    read_mvnx,
    smpl_segment_indices,
    write_mvnx,
)
from couch.rotations import axis_angle_to_matrix, quat_to_matrix, rotation_angle
from couch.tools.sim.imu import BodyTrack, ImuConfig, body_track_from_model, simulate_mvnx

RATE = 120.0
HANDS = [JOINT_INDEX["left_hand"], JOINT_INDEX["right_hand"]]
NOT_HANDS = [j for j in range(24) if j not in HANDS]


def _motion(seconds: float) -> dict[str, np.ndarray]:
    """Turning, walking, bending spine, swinging arm, flexing elbow and knee (axis-angle)."""
    n = round(seconds * RATE) + 1
    t = np.arange(n) / RATE
    w = 2 * np.pi * 0.5 * t
    go = np.stack([0.1 * np.sin(w), 0.6 * t, 0.05 * np.sin(0.7 * w)], -1)
    bp = np.tile(standing_pose(), (n, 1)).reshape(n, 23, 3).astype(np.float64)
    bp[:, JOINT_INDEX["spine1"] - 1, 0] += 0.3 * (1 - np.cos(w))
    bp[:, JOINT_INDEX["right_shoulder"] - 1, 2] += 0.6 * np.sin(w)
    bp[:, JOINT_INDEX["left_elbow"] - 1, 1] += -0.5 * (1 - np.cos(1.3 * w))
    bp[:, JOINT_INDEX["right_knee"] - 1, 0] += 0.4 * (1 - np.cos(w))
    bp[:, JOINT_INDEX["left_wrist"] - 1, 2] += 0.4 * np.sin(w)
    tr = np.stack([0.3 * t, 0.9 + 0.02 * np.sin(w), 0.4 * t], -1)
    return {"time": t, "global_orient": go, "body_pose": bp.reshape(n, -1), "transl": tr}


@pytest.fixture(scope="module")
def motion() -> dict[str, np.ndarray]:
    return _motion(4.0)


@pytest.fixture(scope="module")
def track(coarse_model, motion) -> BodyTrack:
    betas = np.zeros(10)
    betas[:2] = [0.8, -0.5]
    return body_track_from_model(coarse_model, betas=betas, **motion)


def _ry(angle: float) -> np.ndarray:
    return axis_angle_to_matrix(np.array([0.0, angle, 0.0]))


def test_perfect_suit_gives_back_the_smpl_motion(track: BodyTrack, motion, tmp_path: Path
                                                 ) -> None:
    rec, truth = simulate_mvnx(track, ImuConfig.perfect(), np.random.default_rng(0))
    k = rec.n_frames
    frames = np.arange(k) * 2  # IMU sample k is Kinect time k/60 = track frame 2k
    path = tmp_path / "perfect.mvnx"
    write_mvnx(path, rec)
    # in memory: float precision; through the file: its 6 decimals
    for source, atol in ((rec, 1e-6), (read_mvnx(path), 1e-5)):
        out = mvnx_to_smpl(source, rest_joints=track.rest_skeleton())
        assert out.joint_rotations.shape == (k, 24, 3, 3) and out.body_pose.shape == (k, 69)
        np.testing.assert_allclose(out.time, truth.imu_time, atol=1e-3)  # ms resolution
        err = rotation_angle(np.swapaxes(out.joint_rotations, -1, -2)
                             @ track.joint_rotations[frames])
        assert err.max() < atol, JOINT_NAMES[int(np.argmax(err.max(0)))]
        np.testing.assert_allclose(out.joint_positions, track.joints[frames], atol=atol)
        # local rotations against the body model's *input* pose (not re-derived here); the
        # hand joints take the wrist's rotation, so their local rotation is the identity
        want = axis_angle_to_matrix(motion["body_pose"][frames].reshape(k, 23, 3))
        got = axis_angle_to_matrix(out.body_pose.reshape(k, 23, 3))
        body = [j - 1 for j in NOT_HANDS[1:]]
        assert rotation_angle(np.swapaxes(got[:, body], -1, -2) @ want[:, body]).max() < atol
        np.testing.assert_allclose(out.body_pose.reshape(k, 23, 3)[:, [h - 1 for h in HANDS]],
                                   0.0, atol=1e-9)
        root = rotation_angle(axis_angle_to_matrix(out.global_orient).swapaxes(-1, -2)
                              @ axis_angle_to_matrix(motion["global_orient"][frames]))
        assert root.max() < atol
    # our axes: Y up (pelvis ~0.9 m above the floor, feet near it)
    assert 0.7 < out.joint_positions[:, 0, 1].min()
    assert out.joint_positions[:, JOINT_INDEX["left_foot"], 1].max() < 0.2
    assert out.foot_contacts is not None and out.foot_contacts.shape == (k, 4)
    np.testing.assert_array_equal(out.foot_contacts, truth.foot_contacts)
    assert out.unix_ms[0] == truth.start_unix_ms

    # without the subject's rest skeleton the hand joint continues the forearm by a fixed ratio
    approx = mvnx_to_smpl(rec)
    np.testing.assert_allclose(approx.joint_positions[:, NOT_HANDS], track.joints[frames][
        :, NOT_HANDS], atol=1e-6)
    rest = track.rest_skeleton()
    for hand in HANDS:
        wrist = hand - 2
        true_len = np.linalg.norm(rest[hand] - rest[wrist])
        forearm = np.linalg.norm(rest[wrist] - rest[wrist - 2])
        miss = np.linalg.norm(approx.joint_positions[:, hand] - track.joints[frames][:, hand],
                              axis=-1)
        assert miss.max() < abs(true_len - HAND_TO_FOREARM * forearm) + 1e-3


def test_default_suit_errors_stay_within_the_injected_magnitudes(track: BodyTrack) -> None:
    rec, truth = simulate_mvnx(track, ImuConfig(), np.random.default_rng(5))
    out = mvnx_to_smpl(rec)
    idx = smpl_segment_indices(MVN_SEGMENTS)
    # vs MVN's ideal export (constant heading and origin only): misalignment + fusion noise +
    # heading drift, a few degrees
    ideal = quat_to_matrix(mvn_to_couch_quaternions(truth.orientation_ideal[:, idx]))
    err = np.rad2deg(rotation_angle(np.swapaxes(out.joint_rotations, -1, -2) @ ideal))
    rms = float(np.sqrt(np.mean(err**2)))
    assert 1.0 < rms < 5.0, rms
    assert np.percentile(err, 99) < 12.0
    # positions vs MVN's ideal segment origins (true motion turned by the constant heading ψ0,
    # i.e. by -ψ0 about our +Y, and shifted by MVN's origin): limbs hang from misaligned
    # segments and the pelvis drifts, a few centimetres
    ideal_pos = mvn_to_couch_positions(truth.position_ideal[:, idx])
    shift = np.linalg.norm(out.joint_positions[:, NOT_HANDS] - ideal_pos[:, NOT_HANDS], axis=-1)
    assert np.sqrt(np.mean(shift**2)) < 0.05 and shift.max() < 0.15
    # the heading is MVN's own: the pelvis orientation differs from the truth at the first sample
    # by ψ0 about our +Y (to within the injected errors); nothing here undoes it
    first = truth.kinect_time[0] * RATE
    assert abs(first - round(first)) < 1e-6
    true0 = track.joint_rotations[round(first), 0]
    turned = _ry(-truth.heading_offset) @ true0
    assert np.rad2deg(rotation_angle(out.joint_rotations[0, 0].T @ turned)) < 8.0


def test_partial_configuration_is_a_clear_error(track: BodyTrack) -> None:
    rec, _ = simulate_mvnx(track, ImuConfig.perfect(), np.random.default_rng(0))
    upper = dataclasses.replace(
        rec, sensor_labels=list(MVN_SENSORS[:11]), sensor_orientation=None,
        sensor_free_acceleration=None,
        metadata=dataclasses.replace(rec.metadata, configuration="UpperBody"))
    with pytest.raises(ImuConversionError, match="UpperBody") as info:
        mvnx_to_smpl(upper)
    message = str(info.value)
    assert "RightUpperLeg" in message and "LeftFoot" in message
    # opting out converts what MVN exported (legs unmeasured but present)
    assert mvnx_to_smpl(upper, require_full_body=False).n_frames == rec.n_frames

    # a segment an SMPL joint needs is absent: named even when the full-body check is off
    keep = [i for i, s in enumerate(MVN_SEGMENTS) if s != "LeftToe"]
    no_toe = dataclasses.replace(rec, segment_labels=[MVN_SEGMENTS[i] for i in keep],
                                 orientation=rec.orientation[:, keep],
                                 position=rec.position[:, keep], velocity=None,
                                 acceleration=None, angular_velocity=None,
                                 angular_acceleration=None)
    with pytest.raises(ImuConversionError, match="LeftToe"):
        mvnx_to_smpl(no_toe)
    with pytest.raises(ImuConversionError, match="left_foot←LeftToe"):
        mvnx_to_smpl(no_toe, require_full_body=False)

    # spine2 falls back to L3 when T12 is absent
    keep = [i for i, s in enumerate(MVN_SEGMENTS) if s != "T12"]
    no_t12 = dataclasses.replace(no_toe, segment_labels=[MVN_SEGMENTS[i] for i in keep],
                                 orientation=rec.orientation[:, keep],
                                 position=rec.position[:, keep])
    out = mvnx_to_smpl(no_t12, require_full_body=False)
    l3 = MVN_SEGMENTS.index("L3")
    np.testing.assert_allclose(out.joint_positions[:, JOINT_INDEX["spine2"]],
                               mvn_to_couch_positions(rec.position[:, l3]), atol=1e-12)


def test_bad_values_name_the_frame(track: BodyTrack) -> None:
    rec, _ = simulate_mvnx(track, ImuConfig.perfect(), np.random.default_rng(0))
    orientation = rec.orientation.copy()
    orientation[7, 3] = 0.0
    with pytest.raises(ImuConversionError, match=r"frame #7 .*zero quaternion"):
        mvnx_to_smpl(dataclasses.replace(rec, orientation=orientation))
