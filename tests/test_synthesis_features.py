"""couch.synthesis.features on simulated sequences (walk up, sit with both hands on the chair)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import trimesh

from couch.body import JOINT_INDEX
from couch.geometry import apply_transform, invert_transform, make_transform
from couch.rotations import axis_angle_to_matrix, matrix_to_axis_angle, rotation_angle
from couch.schema import read_processed
from couch.synthesis.features import (
    LAYOUT,
    SIT,
    WALK,
    FeatureConfig,
    FeatureStats,
    OccupancyGrid,
    chair_voxels,
    contact_runs,
    control_line,
    ego_cell_centres,
    ego_features,
    global_rotations,
    integrate_root,
    interaction_features,
    interaction_layer,
    pose_features,
    resample,
    root_affine,
    root_speed,
    root_transforms,
    sequence_features,
    sit_contact_flags,
    to_root,
)
from couch.tools.sim.session import simulate_motion_dataset

CFG = FeatureConfig()


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """One simulated both-hands sequence at 30 fps (~6 s to simulate)."""
    out = tmp_path_factory.mktemp("features_sim")
    simulate_motion_dataset(out, 1, seed=5, interaction="both_hands", progress=False)
    return read_processed(out / "motion_00000.h5")


@pytest.fixture(scope="module")
def features(session):
    return sequence_features(session, CFG)


def _yawed(session, yaw: float, shift=(0.7, 0.0, -1.3)):
    """The whole session turned by ``yaw`` about world Y and shifted on the floor."""
    r = axis_angle_to_matrix(np.array([0.0, yaw, 0.0]))
    world = make_transform(r, np.asarray(shift, float))
    go = matrix_to_axis_angle(r @ axis_angle_to_matrix(session.global_orient.astype(np.float64)))
    return dataclasses.replace(
        session,
        joints=apply_transform(world, session.joints.astype(np.float64)).astype(np.float32),
        global_orient=go.astype(np.float32),
        transl=apply_transform(world, session.transl[:, None].astype(np.float64))[:, 0]
        .astype(np.float32),
        contact_points=apply_transform(world, session.contact_points.astype(np.float64))
        .astype(np.float32),
        object_pose=world @ session.object_pose,
        object_frame_poses=world @ session.object_frame_poses)


def test_tpose_root_faces_plus_z(body_model):
    with torch.no_grad():
        joints = body_model(transl=np.array([[0.3, 0.9, -0.2]])).joints.numpy().astype(float)
    root = root_transforms(joints)[0]
    np.testing.assert_allclose(root[:3, 2], [0, 0, 1], atol=1e-4)  # forward
    np.testing.assert_allclose(root[:3, 0], [1, 0, 0], atol=1e-4)  # the body's left
    np.testing.assert_allclose(root[:3, 3], [joints[0, 0, 0], 0, joints[0, 0, 2]], atol=1e-9)
    # turned by +90° about Y the body faces +X
    turned = joints @ axis_angle_to_matrix(np.array([0.0, np.pi / 2, 0.0])).T
    np.testing.assert_allclose(root_transforms(turned)[0, :3, 2], [1, 0, 0], atol=1e-4)


def test_features_invariant_to_world_yaw(session, features):
    moved = sequence_features(_yawed(session, 2.1), CFG)
    for name in ("joint_positions", "joint_rotations", "joint_velocities", "trajectory",
                 "goals", "interaction", "control_line", "control_root_positions",
                 "future_joint_positions", "goal_relative_root", "root_update",
                 "hand_contacts_chair"):
        np.testing.assert_allclose(getattr(moved, name), getattr(features, name), atol=2e-3,
                                   err_msg=name)
    for name in ("hand_phases", "global_phase", "actions"):
        np.testing.assert_allclose(getattr(moved, name), getattr(features, name), atol=1e-3,
                                   err_msg=name)
    # nearest-voxel lookups may flip a cell lying on a voxel boundary, nothing more
    assert np.mean(moved.ego != features.ego) < 1e-3
    # ... while world quantities did change
    assert np.abs(moved.root[:, :3, 3] - features.root[:, :3, 3]).max() > 0.5


def test_pose_features_reproduce_world_joints(session, features):
    joints = session.joints.astype(np.float64)[:, :22]
    root = features.root
    back = apply_transform(root, features.joint_positions.astype(np.float64))
    np.testing.assert_allclose(back, joints, atol=1e-5)
    world_vel = np.einsum("tij,tnj->tni", root[:, :3, :3], features.joint_velocities)
    fd = np.diff(joints, axis=0) * session.fps
    np.testing.assert_allclose(world_vel[1:], fd, atol=1e-3)
    np.testing.assert_allclose(world_vel[0], fd[0], atol=1e-3)
    # root on the floor under the pelvis, y up
    np.testing.assert_allclose(root[:, 1, 3], 0.0)
    np.testing.assert_allclose(root[:, :3, 1], np.broadcast_to([0, 1, 0], (len(root), 3)))
    # one frame of runtime state (batch of 1, velocities given) gives the same J
    t = 57
    rots = global_rotations(session.global_orient[t:t + 1], session.body_pose[t:t + 1])
    vel = world_vel[t:t + 1]
    p, r, v = pose_features(joints[t:t + 1], rots, root[t:t + 1], session.fps,
                            joint_velocities=vel)
    np.testing.assert_allclose(p[0], features.joint_positions[t], atol=1e-5)
    np.testing.assert_allclose(r[0], features.joint_rotations[t], atol=1e-5)
    np.testing.assert_allclose(v[0], features.joint_velocities[t], atol=1e-4)


def test_global_rotations_match_body_model(session, body_model):
    frames = slice(0, None, 17)
    go, bp = session.global_orient[frames], session.body_pose[frames]
    rots = global_rotations(go, bp)
    with torch.no_grad():
        out = body_model(betas=session.betas[None], global_orient=go, body_pose=bp,
                         transl=session.transl[frames])
    model_rots = out.joint_transforms[..., :3, :3].double().numpy()
    assert rotation_angle(np.swapaxes(rots, -1, -2) @ model_rots).max() < 1e-4
    # chaining the rotations over the rest-pose bone offsets gives the recorded joints
    rest = body_model.rest_joints(session.betas[None])[0].double().numpy()
    parents = body_model.parents.numpy()
    joints = session.joints[frames].astype(np.float64)
    for j in range(1, 24):
        p = parents[j]
        pred = joints[:, p] + np.einsum("tij,j->ti", rots[:, p], rest[j] - rest[p])
        np.testing.assert_allclose(pred, joints[:, j], atol=1e-4, err_msg=f"joint {j}")


def test_action_labels(session, features):
    sitting = session.contact_active[:, 0]
    assert sitting.any() and (~sitting).any()
    np.testing.assert_array_equal(features.action_labels == SIT, sitting)
    speed = root_speed(features.root, CFG.fps, CFG.speed_smoothing)
    walk = features.action_labels == WALK
    assert walk.sum() > CFG.fps  # the approach is walked
    assert np.all(speed[walk] > CFG.walk_speed)
    assert np.all(speed[features.action_labels == 0] <= CFG.walk_speed)
    # raw (unsmoothed) displacement over the walk frames is also fast
    step = np.linalg.norm(np.diff(features.root[:, [0, 2], 3], axis=0), axis=-1) * CFG.fps
    assert step[walk[1:]].mean() > CFG.walk_speed
    np.testing.assert_allclose(features.actions.sum(-1), 1.0, atol=1e-5)
    assert features.actions.min() >= 0


def test_trajectory_and_goals(session, features):
    traj, goals = features.trajectory, features.goals
    assert traj.shape == (session.num_frames, 13, 12) and goals.shape == traj.shape
    np.testing.assert_allclose(traj[:, 6, :3], 0.0, atol=1e-6)  # the current sample is the root
    np.testing.assert_allclose(traj[:, 6, 3:9], np.tile([1, 0, 0, 0, 1, 0], (len(traj), 1)),
                               atol=1e-6)
    np.testing.assert_allclose(traj[:, :, 1], 0.0, atol=1e-6)
    t = 40
    expected = to_root(features.root[t + 5, None, :3, 3], features.root[t])[0]
    np.testing.assert_allclose(traj[t, 7, :3], expected, atol=1e-5)
    onset = contact_runs(session.contact_active[:, 0])[0][0]
    # the goal of every frame up to the first sit is the root at the sit onset, action sit
    k = 6
    before = np.arange(0, onset + 1)
    goal_world = apply_transform(features.root[before],
                                 goals[before, k, None, :3].astype(np.float64))[:, 0]
    np.testing.assert_allclose(goal_world, np.broadcast_to(features.root[onset, :3, 3],
                                                           goal_world.shape), atol=1e-4)
    np.testing.assert_array_equal(goals[before, k, 9:], np.broadcast_to([0, 0, 1], (len(before),
                                                                                    3)))
    np.testing.assert_allclose(goals[onset, k, :3], 0.0, atol=1e-5)
    # the goal-relative root of t+1: the sit onset root itself at onset - 1, and for every frame
    # before it, the next root seen from the onset root
    rel = features.goal_relative_root.astype(np.float64)
    np.testing.assert_allclose(rel[onset - 1], [0, 0, 0, 1, 0, 0, 0, 1, 0], atol=1e-5)
    seen = apply_transform(invert_transform(features.root[onset]),
                           features.root[before[:-1] + 1, :3, 3])
    np.testing.assert_allclose(rel[before[:-1], :3], seen, atol=1e-5)


def test_hand_phases_and_control(session, features):
    fps = int(CFG.fps)
    checked = 0
    sitting = session.contact_active[:, session.contact_names.index("pelvis")]
    for h, name in enumerate(("left_hand", "right_hand")):
        # the runs of the sit; a stand-up's push-off is no control target
        window = None if CFG.push_off_window is None else round(CFG.push_off_window * CFG.fps)
        active = sit_contact_flags(session.contact_active[:, session.contact_names.index(name)],
                                   sitting, window)
        starts, ends = contact_runs(active)
        assert len(starts) > 0, name
        phase = features.hand_phases[:, h, 6]  # the current sample
        near = np.zeros(len(active), bool)
        for s, e in zip(starts, ends, strict=True):
            assert phase[s] == pytest.approx(1.0)
            assert np.all(phase[s:e + 1] == 1.0)
            near[max(s - fps, 0):e + fps // 2 + 1] = True
        s = starts[0]  # the first reach rises steadily to its onset
        assert np.all(np.diff(phase[max(s - fps, 0):s + 1]) >= -1e-6)
        assert phase[max(s - fps, 0)] < 0.5
        assert np.all(phase[~near] == 0.0)
        # local phases at the trajectory samples are the phase shifted in time
        np.testing.assert_allclose(features.hand_phases[:-30, h, 12], phase[30:], atol=1e-6)
        np.testing.assert_allclose(features.hand_phases[5:, h, 5], phase[:-5], atol=1e-6)
        # 1 s before the first onset the last control sample (1 s ahead) is at the contact
        s = starts[0]
        if s >= fps:
            t = s - fps
            assert features.hand_mask[t, h]
            last = features.control_positions[t, h, -1]
            first = features.control_positions[t, h, 0]
            # "at the contact": the hand joint sits ~10 cm from the palm-surface contact point
            assert np.linalg.norm(last) < 0.15, (name, last)
            hand_s = session.joints[s, CFG.hand_joints[h]].astype(np.float64)
            expected = features.root[t, :3, :3].T @ (hand_s - features.hand_targets[t, h])
            np.testing.assert_allclose(last, expected, atol=1e-4)
            assert np.linalg.norm(first) > np.linalg.norm(last)
            # PoseNet's copy is where the hand will be, in the root frame of t
            in_root = features.root[t, :3, :3].T @ (hand_s - features.root[t, :3, 3])
            np.testing.assert_allclose(features.control_root_positions[t, h, -1], in_root,
                                       atol=1e-4)
            assert features.control_phases[t, h, -1] == pytest.approx(1.0)
            # the control line runs from the hand (relative to the contact) to zero
            hand = session.joints[t, CFG.hand_joints[h]].astype(np.float64)
            rel = features.root[t, :3, :3].T @ (hand - features.hand_targets[t, h])
            np.testing.assert_allclose(features.control_line[t, h, 0], rel, atol=1e-4)
            np.testing.assert_allclose(features.control_line[t, h, -1], 0.0, atol=1e-6)
            checked += 1
        # after the last run no target follows: mask off and control zeroed
        after = np.arange(ends[-1] + 1, len(active))
        assert not features.hand_mask[after, h].any()
        assert np.all(features.control_line[after, h] == 0)
        assert np.all(features.control_root_positions[after, h] == 0)
    assert checked > 0


def test_global_phase(session, features):
    phase = features.global_phase
    assert phase.min() >= 0 and phase.max() <= 1
    starts, ends = contact_runs(session.contact_active[:, 0])
    s, e = starts[0], ends[0]
    np.testing.assert_array_equal(phase[s:e + 1], 1.0)
    assert phase[s - 1] > phase[s - 5] > phase[s - 9]  # rising into the sit
    rising = np.diff(phase[s - 12:s + 1])
    assert np.all(rising > 0) and phase[s - 1] > 0.9
    # it starts from 0 no more than 1.5 s before the onset, while the pelvis is still up
    start = s - 1 - int(np.argmax(phase[s - 1::-1] < 1e-6))
    assert s - start <= 1.5 * CFG.fps
    pelvis = session.joints[:, 0, 1]
    assert pelvis[start] > pelvis[s] + 0.05
    # several walk cycles of plausible length on the approach (phase wraps 1 -> 0)
    wraps = np.flatnonzero(np.diff(phase[:start]) < -0.5)
    assert len(wraps) >= 2
    cycle = np.diff(wraps) / CFG.fps
    assert np.all((cycle > 0.5) & (cycle < 2.0)), cycle


def test_root_update_integrates(features):
    root = features.root
    nxt = integrate_root(root[:-1], features.root_update[:-1].astype(np.float64))
    np.testing.assert_allclose(nxt, root[1:], atol=1e-5)


def test_group_shapes_follow_layout(session, features):
    groups = features.as_groups()
    n = session.num_frames - 1
    dims = {}
    for net in LAYOUT.values():
        dims.update(net["inputs"])
        dims.update(net["targets"])
    assert set(groups) == set(dims)
    for name, dim in dims.items():
        assert groups[name].shape == (n, dim), name
        assert groups[name].dtype == np.float32
        assert np.all(np.isfinite(groups[name])), name
    assert dims["interaction"] == 2048 and dims["ego"] == 1408
    assert dims["trajectory"] == 13 * 12 and dims["goals"] == 13 * 12
    assert dims["joint_rotations"] == 22 * 6 and dims["control_line"] == 2 * 7 * 3
    assert dims["hand_phases"] == 2 * 13 and dims["next_control_phases"] == 2 * 7
    assert features.interaction.shape == (session.num_frames, 2048)
    assert features.ego.shape == (session.num_frames, 1408)
    assert features.contact_condition.shape == (2048,)
    assert features.ego.max() == 1.0  # the chair shows up around the seated character
    # targets of row t are the inputs of row t + 1
    np.testing.assert_array_equal(groups["next_joint_positions"][:-1],
                                  groups["joint_positions"][1:])
    np.testing.assert_array_equal(groups["future_trajectory"][:-1].reshape(n - 1, 13 - 6, 12),
                                  features.trajectory[1:-1, 6:])


def test_box_chair_occupancy():
    box = trimesh.creation.box(extents=(0.6, 0.5, 0.4))
    pose = make_transform(axis_angle_to_matrix(np.array([0.0, 0.4, 0.0])), [0.1, 0.25, 0.8])
    occupancy, centres, size = chair_voxels(box.vertices, box.faces, pose)
    assert occupancy.shape == (512,) and centres.shape == (512, 3)
    np.testing.assert_allclose(occupancy, 1.0)
    np.testing.assert_allclose(size, [0.6 / 8, 0.5 / 8, 0.4 / 8])
    np.testing.assert_allclose(centres.mean(0), pose[:3, 3], atol=1e-9)
    root = make_transform(np.eye(3), [0.0, 0.0, 0.0])[None]
    feats = interaction_features(occupancy, centres, root)
    assert feats.shape == (1, 2048)
    np.testing.assert_allclose(feats.reshape(512, 4)[:, 1:], centres, atol=1e-9)

    grid = OccupancyGrid.from_mesh(box.vertices, box.faces, pose, voxel=0.03)
    roots = np.stack([make_transform(np.eye(3), [0.0, 0.0, 0.0]),
                      make_transform(axis_angle_to_matrix(np.array([0.0, np.pi, 0.0])),
                                     [0.0, 0.0, 3.5])])
    ego = ego_features(grid, roots, CFG)
    assert ego.shape == (2, 1408)
    cells = apply_transform(roots, np.broadcast_to(ego_cell_centres(CFG), (2, 1408, 3)))
    local = apply_transform(invert_transform(pose), cells)
    margin = np.min(np.array([0.3, 0.25, 0.2]) - np.abs(local), axis=-1)  # >0 inside
    clear = np.abs(margin) > 0.03
    assert (margin[0] > 0.03).sum() > 5  # the box is in front of the first character
    np.testing.assert_array_equal(ego[clear], (margin[clear] > 0).astype(np.float32))
    assert ego[1].sum() == 0  # the second stands 2.7 m away, looking elsewhere


def test_resample_round_trip(session):
    down = resample(session, 15.0)
    assert down.fps == 15.0
    np.testing.assert_allclose(np.diff(down.time), 1 / 15, atol=1e-9)
    back = resample(down, 30.0)
    n = min(back.num_frames, session.num_frames)
    assert abs(back.num_frames - session.num_frames) <= 1
    np.testing.assert_allclose(back.time[:n], session.time[:n], atol=1e-6)
    err = np.linalg.norm(back.joints[:n] - session.joints[:n], axis=-1)
    # the simulator's hands can jump tens of cm in one frame (IK switching targets), which no
    # interpolation recovers; everything else is within a few mm
    assert np.percentile(err, 99) < 0.03 and err.mean() < 0.005, (err.max(), err.mean())
    ang = rotation_angle(np.swapaxes(axis_angle_to_matrix(back.global_orient[:n].astype(float)),
                                     -1, -2) @ axis_angle_to_matrix(
                                         session.global_orient[:n].astype(float)))
    assert ang.max() < np.radians(3)
    agree = (back.contact_active[:n] == session.contact_active[:n]).mean()
    assert agree > 0.97
    assert np.all(np.isnan(back.contact_points[~back.contact_active]))
    # a 15 fps session goes through sequence_features at the config's 30 fps
    feats = sequence_features(down, CFG)
    assert feats.num_frames == back.num_frames


def test_feature_stats_round_trip(tmp_path, features):
    stats = FeatureStats.fit([features, features])
    for name, std in stats.std.items():
        assert std.min() >= 1e-2, name
    normal = stats.normalize("joint_positions", features.as_groups()["joint_positions"])
    np.testing.assert_allclose(normal.mean(0), 0.0, atol=1e-3)
    path = tmp_path / "stats.npz"
    stats.save(path)
    with np.load(path, allow_pickle=False) as raw:
        assert "ego.mean" in raw and raw["ego.std"].shape == (1408,)
    loaded = FeatureStats.load(path)
    assert set(loaded.mean) == set(stats.mean)
    for name in stats.mean:
        np.testing.assert_array_equal(loaded.mean[name], stats.mean[name])
        np.testing.assert_array_equal(loaded.std[name], stats.std[name])
    assert [p.name for p in tmp_path.iterdir()] == ["stats.npz"]  # no temp file left behind


def test_left_ankle_is_smpl_joint_7():
    assert JOINT_INDEX["left_ankle"] == 7 and CFG.hand_joints == (22, 23)


def test_phase_update_wraps_and_advance_phase_inverts_it():
    from couch.synthesis.features import advance_phase, phase_update

    phase = np.array([0.2, 0.95, 0.9, 1.0, 0.4])
    nxt = np.array([0.25, 0.02, 1.0, 1.0, 0.0])
    up = phase_update(phase, nxt)
    assert np.allclose(up, [0.05, 0.07, 0.1, 0.0, -0.4])
    assert np.all((up >= -0.5) & (up < 0.5))
    walking = np.array([False, False, False, False, False])
    seated = np.array([False, False, True, True, False])
    assert np.allclose(advance_phase(phase, up, walking), [0.25, 0.02, 0.0, 0.0, 0.0])
    # seated: 1, as throughout a pelvis contact in the data, instead of a new step cycle
    assert np.allclose(advance_phase(phase, up, seated), [0.25, 0.02, 1.0, 1.0, 0.0])
    assert np.allclose(advance_phase(phase, -up, ~walking), 1.0)


def test_interaction_layer_is_the_layer_over_normalised_i():
    """A linear layer over normalised I folds, for a given chair, into an affine map of the
    root pose: the same outputs as the layer over I built from scratch, for any rigid root."""
    rng = np.random.default_rng(3)
    n, width = 27, 5
    occupancy = rng.uniform(0, 1, n)
    centres = rng.normal(size=(n, 3))
    weight, bias = rng.normal(size=(width, 4 * n)), rng.normal(size=width)
    mean, std = rng.normal(size=4 * n), rng.uniform(0.5, 2.0, 4 * n)
    roots = make_transform(axis_angle_to_matrix(rng.normal(size=(6, 3))), rng.normal(size=(6, 3)))
    want = ((interaction_features(occupancy, centres, roots) - mean) / std) @ weight.T + bias
    got = root_affine(roots) @ interaction_layer(occupancy, centres, weight, bias, mean, std).T
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    assert root_affine(roots[0]).shape == (13,)


def test_control_line_can_end_above_the_contact():
    """h̃ runs from the hand to ``end_height`` above the contact: the world points on that
    segment, relative to the contact and seen from a yawed root, and zero for masked hands."""
    root = make_transform(axis_angle_to_matrix(np.array([0.0, 0.8, 0.0])), [0.4, 0.0, -0.2])
    hand = np.array([[0.1, 0.9, 0.5], [0.6, 1.0, 0.3]])
    target = np.array([[0.3, 0.45, 0.7], [0.0, 0.0, 0.0]])
    mask = np.array([True, False])
    line = control_line(hand, target, mask, root, samples=5, end_height=0.07)
    end = target[0] + [0.0, 0.07, 0.0]
    for k, s in enumerate(np.linspace(0.0, 1.0, 5)):
        world = hand[0] + s * (end - hand[0])
        np.testing.assert_allclose(line[0, k], root[:3, :3].T @ (world - target[0]), atol=1e-12)
    assert np.all(line[1] == 0)
    # height 0 is the line onto the contact itself
    np.testing.assert_allclose(control_line(hand, target, mask, root, samples=5)[0, -1], 0.0,
                               atol=1e-12)


def _flags(n: int, *runs: tuple[int, int]) -> np.ndarray:
    out = np.zeros(n, bool)
    for s, e in runs:
        out[s:e + 1] = True
    return out


def test_push_off_runs_are_no_sit_contacts():
    sitting = _flags(100, (20, 49), (80, 99))  # sits, stands up at frame 49, sits again
    hand = _flags(100, (15, 22), (30, 33), (45, 47), (52, 55), (62, 66), (95, 97))
    kept = sit_contact_flags(hand, sitting, window=10)
    # the touch of the sit and one well before the stand-up stay; the push-offs within 10
    # frames of the stand-up (before or after it) go; a later run before the next sit is that
    # sit's, as is everything while the last sit lasts to the end of the sequence
    np.testing.assert_array_equal(kept, _flags(100, (15, 22), (30, 33), (62, 66), (95, 97)))
    # with no later sit, every run after the stand-up is part of it
    alone = sit_contact_flags(_flags(90, (15, 22), (70, 75)), _flags(90, (20, 49)), window=10)
    np.testing.assert_array_equal(alone, _flags(90, (15, 22)))
    # a landing's bounce (pelvis off for fewer than `window` frames) is no stand-up
    bounce = _flags(100, (20, 40), (45, 99))
    np.testing.assert_array_equal(sit_contact_flags(hand, bounce, window=10), hand)
    # the window is what separates them, and None turns the rule off
    assert sit_contact_flags(hand, sitting, window=15)[30:34].all()
    assert not sit_contact_flags(hand, sitting, window=15)[45:48].any()
    assert not sit_contact_flags(hand, sitting, window=20)[30:34].any()
    np.testing.assert_array_equal(sit_contact_flags(hand, sitting, None), hand)


def test_push_off_leaves_the_seated_control_off(session):
    """A sit that ends in a push-off: the seated frames before it have no control target
    (the data's old tell for "stand up now"), and the old setting still gives one."""
    names = list(session.contact_names)
    hands = [names.index("left_hand"), names.index("right_hand")]
    active = np.array(session.contact_active, bool)
    points = np.array(session.contact_points, np.float32)
    pelvis = names.index("pelvis")
    sat = np.flatnonzero(active[:, pelvis])
    assert len(sat) > 0 and sat[0] + 60 < len(active), "the simulated sequence must sit"
    first, up = sat[0], sat[0] + 45
    # the hands let go 10 frames after the landing, both push off just before standing up
    active[first + 10:, hands] = False
    push = np.arange(up - 3, up + 2)
    active[np.ix_(push, hands)] = True
    points[np.ix_(push, hands)] = session.joints[push][:, list(CFG.hand_joints)]
    active[first:up + 1, pelvis] = True
    active[up + 1:, pelvis] = False
    standing = dataclasses.replace(session, contact_active=active, contact_points=points)
    new = sequence_features(standing, dataclasses.replace(CFG, push_off_window=1.0))
    old = sequence_features(standing, dataclasses.replace(CFG, push_off_window=None))
    seated = np.arange(first + 26, up - 3)  # past the release of the sit's touch
    assert old.hand_mask[seated].all()
    assert not new.hand_mask[seated].any()
    assert np.all(new.contact_inputs[seated] == 0)
    assert np.all(new.hand_phases[seated, :, 6] == 0)
    assert np.all(new.hand_phases[push, :, 6] == 0) and np.all(old.hand_phases[push, :, 6] == 1)
