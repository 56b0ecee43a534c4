"""The runtime controller, its exports and ``couch-synthesize`` on the session's ci-trained run
(``ci_run`` in conftest.py: tiny networks, so these tests check the machinery, not the motion
quality; ``couch-eval`` measures that)."""

from __future__ import annotations

import av
import numpy as np
import pytest
import torch
import trimesh

from couch.body import JOINT_INDEX, load_body_model
from couch.rotations import matrix_to_axis_angle
from couch.schema import read_processed, validate
from couch.synthesis import (
    FootLockConfig,
    Scene,
    Synthesizer,
    planted_feet,
    sample_contacts,
    save_npz,
    to_processed,
    yaw_transform,
)
from couch.synthesis.features import global_rotations, pose_features, root_transforms
from couch.synthesis.metrics import SMPL_FOOT_HEIGHTS, foot_sliding
from couch.tools.sim.chairs import make_chair, random_chair_spec, save_mesh
from couch.tools.synthesize import main


@pytest.fixture(scope="module")
def chair():
    """An armchair in the chair frame, and its left armrest's top (chair frame = world)."""
    c = make_chair(random_chair_spec(np.random.default_rng(4), "armchair"))
    return c.vertices, c.faces, np.asarray(c.landmarks.left_armrest)


@pytest.fixture(scope="module")
def synth(ci_run):
    torch.set_num_threads(1)
    return Synthesizer(ci_run.run_dir, "couch")


@pytest.fixture(scope="module")
def scene(synth, chair):
    return Scene.from_mesh(chair[0], chair[1], synth.cfg, name="armchair")


#: (x, z, heading) of three characters: ahead of the chair, beside it, close in front
STARTS = np.array([[0.0, 2.5, np.pi], [1.0, 1.0, -2.0], [0.2, 0.9, np.pi]])


def _left_armrest(chair) -> np.ndarray:
    """The contact series of the three: the left hand on the left armrest, the right free."""
    return np.array([[chair[2], [np.nan] * 3]])


@pytest.fixture(scope="module")
def result(synth, scene, chair):
    return synth.synthesize(scene, STARTS, _left_armrest(chair), seconds=3.0)


def test_scene_goal_sits_on_the_seat(scene):
    goal = scene.goal
    assert abs(goal[1, 3]) < 1e-9  # roots live on the floor
    assert np.hypot(goal[0, 3], goal[2, 3]) < 0.1  # the seat is centred on x = z = 0
    assert goal[2, 2] > 0.99  # facing the chair's front (+Z)


def test_batched_result_shapes_and_invariants(result, synth):
    b, t = 3, 90
    assert result.root.shape == (b, t, 4, 4) and result.joints.shape == (b, t, 24, 3)
    assert result.body_pose.shape == (b, t, 69) and result.hands.shape == (b, t, 2, 3)
    for name in ("joints", "global_orient", "body_pose", "transl", "hands", "global_phase"):
        assert np.all(np.isfinite(getattr(result, name))), name
    assert np.allclose(result.root[..., 1, 3], 0.0)
    assert np.all((result.global_phase >= 0) & (result.global_phase <= 1))
    # Control is on only near its contact (FeatureConfig.control_radius), never for "none".
    # A frame's control is switched by the root it starts from: the previous frame's output
    # (the start pose for frame 0).
    on = result.control_on[..., 0]
    start = np.stack([STARTS[:, 0], np.zeros(len(STARTS)), STARTS[:, 1]], 1)[:, None]
    before = np.concatenate([start, result.root[:, :-1, :3, 3]], 1)
    d = result.targets[..., 0, :] - before
    assert np.all(np.hypot(d[..., 0], d[..., 2])[on] < synth.cfg.control_radius)
    assert not result.control_on[..., 1].any()
    assert not on[0, 0]  # starts 2.5 m away
    assert on[2, 0]  # starts within reach: control from the first frame


def test_smpl_parameters_reproduce_the_posed_body(result):
    """The exported SMPL parameters posed by the real body model give the exported joints."""
    model = load_body_model("couch-body")
    with torch.no_grad():
        out = model(betas=result.betas[None], global_orient=result.global_orient[0],
                    body_pose=result.body_pose[0], transl=result.transl[0])
    assert np.abs(out.joints.numpy() - result.joints[0]).max() < 1e-4


def test_smpl_conversion_inverts_the_features(synth):
    """Root-frame J of a known pose (the features' own maths) -> SMPL -> the same pose."""
    rng = np.random.default_rng(0)
    n = 4
    go = rng.normal(0, 0.3, (n, 3)) + np.array([0, 1.0, 0])
    bp = rng.normal(0, 0.3, (n, 69))
    bp[:, 63:] = 0.0  # hand joints 22/23: the controller leaves them at rest
    transl = rng.normal(0, 0.5, (n, 3))
    model = load_body_model("couch-body")
    with torch.no_grad():
        joints = model(global_orient=go, body_pose=bp, transl=transl).joints.double().numpy()
    root = root_transforms(joints)
    jpos, jrot, _ = pose_features(joints, global_rotations(go, bp), root, 30.0)
    go2, bp2, transl2, joints2 = synth.smpl(root, jpos, jrot)
    assert np.abs(joints2 - joints).max() < 1e-5
    assert np.allclose(transl2, transl, atol=1e-5)
    # Same rotations (axis-angle may differ by 2π wraps: compare via the matrices' action).
    assert np.allclose(matrix_to_axis_angle(_m(go2)), matrix_to_axis_angle(_m(go)), atol=1e-6)
    assert np.allclose(_m(bp2.reshape(n, 23, 3)), _m(bp.reshape(n, 23, 3)), atol=1e-6)


def _m(aa):
    from couch.rotations import axis_angle_to_matrix

    return axis_angle_to_matrix(np.asarray(aa, np.float64))


def test_series_moves_to_the_next_contact_set(ci_run, scene, chair):
    # reach 10 m: every active hand counts as "there", so each set ends after `hold` seconds.
    syn = Synthesizer(ci_run.run_dir, "couch", hold=0.2, reach=10.0)
    left, nan = chair[2], np.full(3, np.nan)
    right = left * np.array([-1.0, 1.0, 1.0])
    series = np.array([[left, nan], [nan, right]])
    r = syn.synthesize(scene, np.array([[0.2, 0.9, np.pi]]), series, seconds=1.0)
    idx = r.series_index[0]
    assert idx[0] == 0 and idx[-1] == 1
    assert np.all(np.diff(idx) >= 0)
    first = np.flatnonzero(idx == 1)[0]
    assert np.isnan(r.targets[0, first + 1, 0, 0]) and np.isfinite(r.targets[0, first + 1, 1, 0])


def test_which_picks_each_networks_checkpoint(ci_run, scene, chair, synth):
    """Per-network epochs: the best checkpoints' own epochs synthesise exactly what "best"
    does; another PoseNet epoch moves the motion."""
    best = {net: int(torch.load(ci_run.nets[net].dir / "best.pt", weights_only=True)["epoch"])
            for net in ("pose", "control")}
    starts, series = np.array([[0.2, 0.9, np.pi]]), np.array([[chair[2], [np.nan] * 3]])
    want = synth.synthesize(scene, starts, series, seconds=1.0).joints
    same = Synthesizer(ci_run.run_dir, "couch", which=best)
    np.testing.assert_array_equal(same.synthesize(scene, starts, series, seconds=1.0).joints,
                                  want)
    other = 1 if best["pose"] != 1 else 2
    moved = Synthesizer(ci_run.run_dir, "couch", which={"pose": other})
    assert np.abs(moved.synthesize(scene, starts, series, seconds=1.0).joints - want).max() > 1e-3


def test_baseline_runs_in_the_same_harness(ci_run, scene, chair):
    syn = Synthesizer(ci_run.run_dir, "baseline")
    assert syn.control_net is None
    r = syn.synthesize(scene, np.array([[0.2, 0.9, np.pi]]),
                       np.array([[chair[2], [np.nan] * 3]]), seconds=1.0)
    assert r.method == "baseline" and np.all(np.isfinite(r.joints))
    with pytest.raises(ValueError, match=r"hand_ik.*'couch' only"):
        Synthesizer(ci_run.run_dir, "baseline", hand_ik=True)


def test_hand_ik_runs_in_the_controller(ci_run, scene, chair):
    """Machinery only (the ci networks' phases are noise; tests/test_synthesis_hand_ik.py
    checks the IK itself): the IK'd run gives finite motion with control on."""
    syn = Synthesizer(ci_run.run_dir, "couch", hand_ik=True)
    starts, series = np.array([[0.2, 0.9, np.pi]]), np.array([[chair[2], [np.nan] * 3]])
    r = syn.synthesize(scene, starts, series, seconds=1.0)
    assert r.joints.shape == (1, 30, 24, 3) and np.all(np.isfinite(r.joints))
    assert np.all(np.isfinite(r.body_pose)) and r.control_on[..., 0].any()


#: The ci networks' characters walk with their feet above the floor: since session 57's
#: simulator change their ankles come no lower than 11.8-13.5 cm in these 5 s (SMPL's stand
#: ~7 cm up), so no foot is planted by the default rule (10 cm). The lock's tests raise the plant
#: rule's height, and the sliding metric's heights, by 6 cm.
CI_FEET_UP = 0.06


@pytest.fixture(scope="module")
def locked(ci_run, synth, scene, chair):
    """5 s of three characters without and with ``foot_lock`` (the plant rule raised by
    :data:`CI_FEET_UP`)."""
    plain = synth.synthesize(scene, STARTS, _left_armrest(chair), seconds=5.0)
    cfg = FootLockConfig(height=FootLockConfig().height + CI_FEET_UP)
    syn = Synthesizer(ci_run.run_dir, "couch", foot_lock=cfg)
    return plain, syn.synthesize(scene, STARTS, _left_armrest(chair), seconds=5.0), cfg


def test_foot_lock_edits_only_the_legs(locked):
    """``foot_lock`` is a post-process: the same path, hands and upper body as without it,
    and the legs re-bent (tests/test_synthesis_foot_lock.py checks the hold itself)."""
    result, r, cfg = locked
    assert planted_feet(result.joints[:, :, [JOINT_INDEX["left_ankle"],
                                              JOINT_INDEX["right_ankle"]]], result.fps,
                        cfg).any()
    np.testing.assert_array_equal(r.root, result.root)
    np.testing.assert_array_equal(r.hands, result.hands)
    legs = [JOINT_INDEX[f"{s}_{p}"] for s in ("left", "right")
            for p in ("knee", "ankle", "foot")]
    upper = [j for j in range(22) if j not in legs]
    np.testing.assert_allclose(r.joints[:, :, upper], result.joints[:, :, upper], atol=1e-9)
    assert not np.allclose(r.joints[:, :, legs], result.joints[:, :, legs])


def test_foot_lock_adds_no_sliding(locked):
    """Found in session 55 on the ci networks: the second character's right foot lands while
    moving 0.1-0.5 m/s (a plant by the rule: ankle under 10 cm, slower than 1 m/s); the lock
    then held it 3-4 frames until it was 5 cm off and released it over 5 frames, so its
    displacement came later, where the foot was lower and the CHOIS weight larger (0.37 mm
    per frame of sliding against 0.32 without the lock). The leash drags it instead. (The
    CHOIS heights are raised by :data:`CI_FEET_UP` as the plant rule is.)"""
    result, r, _ = locked
    heights = tuple(h + CI_FEET_UP for h in SMPL_FOOT_HEIGHTS)
    slide = [foot_sliding(j, r.fps, heights=heights) for j in r.joints]
    before = [foot_sliding(j, r.fps, heights=heights) for j in result.joints]
    assert min(before) > 0  # some foot is low enough to count
    assert np.all(np.array(slide) <= np.array(before) + 1e-9), (slide, before)


def test_foot_lock_bench_runs(ci_run, capsys):
    """Machinery only (``python -m couch.tools.bench.foot_lock``; the ci networks' sliding
    means nothing): it synthesises without and with the lock and prints both."""
    from couch.tools.bench import foot_lock as bench

    bench.main([str(ci_run.run_dir), "--chairs", "1", "--starts", "2", "--seconds", "1"])
    out = capsys.readouterr().out
    assert "mm/frame without the lock" in out and "of 2 characters" in out
    with pytest.raises(SystemExit):
        bench.main([str(ci_run.run_dir), "--chairs", "0"])


def test_exports(result, tmp_path):
    session = to_processed(result, 1)
    validate(session)
    assert session.num_frames == result.num_frames
    assert np.array_equal(session.contact_active, result.contacts[1] > 0.5)
    path = save_npz(result, tmp_path / "s.npz")
    with np.load(path, allow_pickle=False) as z:
        assert z["body_pose"].shape == result.body_pose.shape
        assert str(z["method"]) == "couch"


def test_sampled_contacts_lie_on_the_chair(ci_run, scene):
    c = sample_contacts(ci_run.run_dir, scene, 16, seed=1, max_distance=0.5)
    assert c.shape == (16, 2, 3)
    kept = np.isfinite(c).all(-1)
    assert kept.any()
    mesh = trimesh.Trimesh(scene.vertices, scene.faces, process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh, c[kept])
    assert dist.max() < 1e-6


def test_cli_writes_motion_schema_and_preview(ci_run, chair, tmp_path, capsys):
    mesh = save_mesh(tmp_path / "armchair.obj", chair[0], chair[1])
    left = ",".join(f"{v:.3f}" for v in chair[2])
    out = tmp_path / "out"
    code = main([str(ci_run.run_dir), "--chair", str(mesh), "--contacts", f"{left};none",
                 "--contacts", "none;none", "--seconds", "1", "--start", "0,1.2,180",
                 "--foot-lock", "-o", str(out), "-q"])
    assert code == 0, capsys.readouterr().err
    s = read_processed(out / "couch_000.h5")
    assert s.num_frames == 30 and s.object_name == "armchair"
    assert (out / "couch_001.h5").is_file() and not (out / "couch_001.mp4").exists()
    with av.open(str(out / "couch_000.mp4")) as c:
        assert sum(1 for _ in c.decode(video=0)) == 15  # every 2nd frame
    assert (out / "couch_000.png").is_file()


@pytest.mark.parametrize("args, message", [
    (["--contacts", "1,2;none"], "expected x,y,z"),
    (["--contacts", "0,0,0"], "left;right"),
    (["--start", "0,1"], "--start"),
    (["--seconds", "0"], "--seconds"),
    (["--precision", "bf16"], "invalid choice: 'bf16'"),
    (["--which", "pose=99"], "099.pt: no such file"),
    (["--which", "newest"], "--which 'newest'"),
])
def test_cli_bad_arguments(ci_run, chair, tmp_path, capsys, args, message):
    mesh = save_mesh(tmp_path / "c.obj", chair[0], chair[1])
    code = main([str(ci_run.run_dir), "--chair", str(mesh), "-o", str(tmp_path / "o"),
                 "-q", *args])
    assert code == 2
    assert message in capsys.readouterr().err


def test_cli_missing_chair(ci_run, tmp_path, capsys):
    assert main([str(ci_run.run_dir), "--chair", str(tmp_path / "no.obj"), "-o",
                 str(tmp_path / "o"), "-q"]) == 2
    assert "no.obj" in capsys.readouterr().err


def test_yaw_transform_heading():
    t = yaw_transform(1.0, 2.0, np.pi / 2)
    assert np.allclose(t[:3, 2], [1, 0, 0]) and np.allclose(t[:3, 3], [1, 0, 2])


def test_sofa_goal_moves_towards_the_held_armrest(synth):
    c = make_chair(random_chair_spec(np.random.default_rng(5), "sofa"))
    sofa = Scene.from_mesh(c.vertices, c.faces, synth.cfg, name="sofa")
    assert sofa.seat_half_width > 0.5
    left = np.asarray(c.landmarks.left_armrest)
    nan = np.full(3, np.nan)
    goals = sofa.goals(np.array([[[left, nan]], [[nan, nan]], [[left, left * [-1, 1, 1]]]]))
    assert goals[0, 0, 3] == pytest.approx(sofa.goal[0, 3] + sofa.seat_half_width - 0.25)
    assert goals[1, 0, 3] == pytest.approx(sofa.goal[0, 3])  # no contact: the seat centre
    assert abs(goals[2, 0, 3] - sofa.goal[0, 3]) < 0.05  # both armrests: the middle


def test_sit_goal_moves_along_a_deep_seat_towards_its_contact():
    """A hand asked on a deep seat's front corner moves the sit goal forward, keeping
    SEAT_FRONT_ROOM of seat in front of the hips (an armrest contact ahead or a shallow seat
    does not); an armrest contact behind the hips moves it back, keeping SEAT_BACK_ROOM."""
    from couch.synthesis import FeatureConfig
    from couch.synthesis.controller import (
        ARMREST_REACH_Z,
        HAND_REACH_Z,
        SEAT_BACK_ROOM,
        SEAT_FRONT_ROOM,
    )
    from couch.synthesis.evaluation import contact_candidates

    nan = np.full(3, np.nan)
    c = make_chair(random_chair_spec(np.random.default_rng(5), "sofa"))
    sofa = Scene.from_mesh(c.vertices, c.faces, FeatureConfig(), name="sofa")
    corner = contact_candidates(c.vertices, c.faces)["left"]["seat"][0]
    arm = np.asarray(c.landmarks.left_armrest)
    assert abs(sofa.seat_height - corner[1]) < 1e-6 and sofa.seat_front > corner[2]
    room = sofa.seat_front - SEAT_FRONT_ROOM - sofa.goal[2, 3]
    assert 0.0 < room < corner[2] - sofa.goal[2, 3] - HAND_REACH_Z  # the room is what binds
    front_arm = arm + np.array([0.0, 0.0, 0.3])  # well ahead of the hips
    goals = sofa.goals(np.array([[[corner, nan]], [[front_arm, nan]], [[nan, nan]]]))
    assert goals[0, 2, 3] == pytest.approx(sofa.seat_front - SEAT_FRONT_ROOM)
    assert goals[1, 2, 3] == pytest.approx(sofa.goal[2, 3])  # an armrest: not forward
    assert goals[2, 2, 3] == pytest.approx(sofa.goal[2, 3])  # no contact: the seat centre
    # an armrest contact behind the hips moves them back, at most to SEAT_BACK_ROOM
    near, far = (arm * [1, 1, 0] + [0.0, 0.0, sofa.goal[2, 3] + dz] for dz in (-0.02, -0.5))
    back = sofa.goals(np.array([[[near, nan]], [[far, nan]]]))
    assert back[0, 2, 3] == pytest.approx(near[2] - ARMREST_REACH_Z)
    assert back[1, 2, 3] == pytest.approx(sofa.seat_back + SEAT_BACK_ROOM)
    s = make_chair(random_chair_spec(np.random.default_rng(5), "straight"))
    straight = Scene.from_mesh(s.vertices, s.faces, FeatureConfig(), name="straight")
    corner = contact_candidates(s.vertices, s.faces)["right"]["seat"][0]
    assert straight.goals(np.array([[[nan, corner]]]))[0, 2, 3] == pytest.approx(
        straight.goal[2, 3])  # under SEAT_FRONT_ROOM deep: stays


def test_runtime_features_match_training_features(synth, motion_sim):
    """The controller's J, T, G, I, E for a recorded state equal sequence_features' rows."""
    from couch.synthesis.controller import _State
    from couch.synthesis.data import find_sequences, load_sequence
    from couch.synthesis.features import (
        SIT,
        canonical_chair,
        goal_frames,
        sample_indices,
        sequence_features,
    )

    s = canonical_chair(load_sequence(find_sequences([motion_sim])[0]))
    f = sequence_features(s, synth.cfg)
    groups = f.as_groups(drop_last=False)
    scene = Scene.from_mesh(s.object_vertices, s.object_faces, synth.cfg, s.object_pose)
    goal_frame, goal_action = goal_frames(f.action_labels == SIT, f.action_labels)
    # The runtime only ever heads for a sit: frames whose goal samples all say sit (a sequence
    # that stands up and walks away has idle / walk goals after its last sit).
    heading = np.flatnonzero(np.all(goal_action[sample_indices(
        f.num_frames, synth.cfg.trajectory_offsets)] == SIT, 1))
    h = 30
    for t in (5, heading[len(heading) // 2], heading[-1]):
        idx = np.clip(np.arange(t - h, t), 0, None)
        state = _State(root=f.root[t][None], goal=f.root[goal_frame[t]][None],
                       jpos=f.joint_positions[t][None], jrot=f.joint_rotations[t][None],
                       jvel=f.joint_velocities[t][None], future=f.trajectory[t][6:][None],
                       phase=f.global_phase[t][None], hist_root=f.root[idx][None],
                       hist_action=f.actions[idx][None], hist_hphase=np.zeros((1, h, 2)),
                       line=None, c_phase=None, on=None, lstm=None, index=None, since=None,
                       held=None)
        for name, value in synth._state_features(scene, state).items():
            np.testing.assert_allclose(np.reshape(value, -1), groups[name][t], atol=2e-5,
                                       err_msg=f"{name} at frame {t}")


def test_bidirectional_blend_pulls_a_sitter_onto_the_goal(synth):
    """Near the goal and sitting, the next root is the goal-relative prediction; far away or
    walking, the ego-centric update; halfway, halfway (yaw the short way round)."""
    from couch.synthesis.controller import _State
    from couch.synthesis.features import SIT

    goal = yaw_transform(0.0, 0.0, 0.0)[None].repeat(4, 0)
    root = yaw_transform(np.array([0.0, 3.0, 0.0, 0.5]), 0.0, 3.0)  # two near, one far, one mid
    future = np.zeros((4, 7, 12))
    future[:, 0, 9 + SIT] = [1.0, 1.0, 0.0, 1.0]  # sitting, sitting, walking, sitting
    state = _State(root=root, goal=goal, jpos=None, jrot=None, jvel=None, future=future,
                   phase=None, hist_root=None, hist_action=None, hist_hphase=None, line=None,
                   c_phase=None, on=None, lstm=None, index=None, since=None, held=None)
    update = np.tile([0.0, 0.1, 0.0], (4, 1))  # 10 cm forward, no turn
    rel = np.tile([0.2, 0.0, -0.1, 1, 0, 0, 0, 1, 0], (4, 1))  # (0.2, -0.1) from the goal
    out = {"root_update": update, "goal_relative_root": rel}
    nxt = synth._next_root(state, out)
    ego = root @ yaw_transform(0.0, 0.1, 0.0)
    np.testing.assert_allclose(nxt[0], yaw_transform(0.2, -0.1, 0.0), atol=1e-9)
    np.testing.assert_allclose(nxt[1:3], ego[1:3], atol=1e-9)  # far; walking
    w = 1.0 - 0.5 / synth.blend_radius
    heading = np.arctan2(nxt[3, 0, 2], nxt[3, 2, 2])
    ego_heading = np.arctan2(ego[3, 0, 2], ego[3, 2, 2])
    assert heading == pytest.approx(ego_heading + w * np.angle(np.exp(-1j * ego_heading)))
    np.testing.assert_allclose(nxt[3, [0, 2], 3], (1 - w) * ego[3, [0, 2], 3] + w * np.array(
        [0.2, -0.1]), atol=1e-9)


def test_far_characters_are_told_to_walk():
    """Beyond ``walk_radius`` of the goal the fed-back action labels are walk; nearer, and with
    the radius 0, they are the network's."""
    from couch.synthesis.controller import walk_when_far
    from couch.synthesis.features import IDLE, WALK

    goal = yaw_transform(0.0, 0.0, 0.0)[None].repeat(3, 0)
    root = yaw_transform(np.array([0.0, 1.0, 3.0]), 0.0, 0.0)  # at the goal, 1 m, 3 m
    future = np.zeros((3, 7, 12))
    future[..., 9 + IDLE] = 1.0
    out = walk_when_far(future, root, goal, 2.0)
    np.testing.assert_array_equal(out[:2], future[:2])
    np.testing.assert_array_equal(out[2, :, 9:], np.tile(np.eye(3)[WALK], (7, 1)))
    np.testing.assert_array_equal(out[2, :, :9], future[2, :, :9])
    assert future[2, 0, 9 + IDLE] == 1.0  # the input is not changed in place
    np.testing.assert_array_equal(walk_when_far(future, root, goal, 0.0), future)


def test_near_turned_characters_are_told_to_sit():
    """Within ``sit_radius`` of the goal and turned to within 45 degrees of its heading, the
    fed-back action labels are blended towards sit, more the farther ahead the sample (the
    present unchanged, one second ahead all sit); farther, not turned, or with the radius 0,
    they are the network's."""
    from couch.synthesis.controller import sit_when_near
    from couch.synthesis.features import IDLE, SIT

    goal = yaw_transform(0.0, 0.0, np.pi)[None].repeat(4, 0)  # facing -Z
    root = yaw_transform(np.array([0.0, 0.0, 0.3, 0.6]), np.array([0.2, 0.2, 0.0, 0.0]),
                         np.array([np.pi + 0.5, np.pi - 1.0, -np.pi + 0.2, np.pi]))
    offsets = np.arange(0, 31, 5)
    future = np.zeros((4, 7, 12))
    future[..., :9] = np.arange(9)
    future[..., 9 + IDLE] = 1.0
    out = sit_when_near(future, root, goal, 0.4, offsets)
    w = offsets / 30
    for b in (0, 2):  # 20-30 cm away, turned 29 and 11 degrees from the goal's heading
        np.testing.assert_allclose(out[b, :, 9 + SIT], w)
        np.testing.assert_allclose(out[b, :, 9 + IDLE], 1 - w)
        np.testing.assert_array_equal(out[b, :, :9], future[b, :, :9])
    np.testing.assert_array_equal(out[1], future[1])  # turned 57 degrees away
    np.testing.assert_array_equal(out[3], future[3])  # 60 cm away
    assert future[0, -1, 9 + IDLE] == 1.0  # the input is not changed in place
    np.testing.assert_array_equal(sit_when_near(future, root, goal, 0.0, offsets), future)


def test_lost_plans_restart_from_the_straight_line():
    """ControlNet reads its fed-back plan, but the straight line where the control just
    switched on or where the plan's present sample is more than ``radius`` from the hand; zero
    for hands without a contact; radius 0 keeps every running plan."""
    from couch.synthesis.plans import replan_lost

    k = np.linspace(1.0, 0.0, 7)
    straight = np.zeros((2, 2, 7, 3))
    straight[..., 0] = 0.5 * k  # the hand 50 cm from its contact
    fed = np.zeros((2, 2, 7, 3))
    fed[0, 0, :, 0] = 0.45 * k  # on track, 5 cm off
    fed[0, 1, :, 0] = 0.0  # collapsed onto the contact: 50 cm off
    fed[1, 0, :, 1] = 0.3  # elsewhere, but the control just switched on
    fed[1, 1, :, 0] = 0.1  # no contact for this hand
    fresh = np.array([[False, False], [True, False]])
    mask = np.array([[True, True], [True, False]])
    out = replan_lost(fed, straight, fresh, mask, 0.2)
    np.testing.assert_array_equal(out[0, 0], fed[0, 0])
    np.testing.assert_array_equal(out[0, 1], straight[0, 1])
    np.testing.assert_array_equal(out[1, 0], straight[1, 0])
    np.testing.assert_array_equal(out[1, 1], 0.0)
    kept = replan_lost(fed, straight, fresh, mask, 0.0)
    np.testing.assert_array_equal(kept[0, 1], fed[0, 1])
    np.testing.assert_array_equal(kept[1, 0], straight[1, 0])


def test_runtime_reads_the_full_nets_predictions(synth, ci_run):
    """The runtime cuts the predictions it never reads from PoseNet's last layer; what it reads
    equals the uncut net's prediction of the same inputs."""
    from couch.synthesis.controller import READ_OUTPUTS
    from couch.synthesis.train import load_trained

    net, stats, meta = load_trained(ci_run.run_dir, "pose", "best", "cpu")
    groups_out = list(meta["groups_out"])
    assert set(groups_out) - set(READ_OUTPUTS)  # something is cut
    torch.manual_seed(0)
    inputs = {name: torch.randn(3, dim) for name, dim in {**net.inputs,
                                                           **net.gating_inputs}.items()}
    with torch.no_grad():
        full, cut = net(inputs)[0].numpy(), synth.pose_net(inputs)[0].numpy()
    assert cut.shape[1] == synth.pose_net.out_dim < full.shape[1]
    start = 0
    for g in groups_out:
        width = synth.widths[g]
        if g in READ_OUTPUTS:
            got = cut[:, synth._outputs[g]] * stats.std[g] + stats.mean[g]
            np.testing.assert_allclose(got, stats.denormalize(g, full[:, start:start + width]),
                                       rtol=1e-5, atol=1e-5, err_msg=g)
        start += width


def test_runtime_folds_the_interaction_encoders_first_layer(synth, scene, ci_run):
    """The loop's interaction encoder starts from its first layer folded per chair: equal to
    that layer over the normalised I of the same roots."""
    from couch.synthesis.features import interaction_features
    from couch.synthesis.train import load_trained

    net, stats, _ = load_trained(ci_run.run_dir, "pose", "best", "cpu")
    roots = yaw_transform(np.array([0.3, -1.0, 2.0]), np.array([1.2, 0.4, -0.7]),
                          np.array([0.0, 2.5, -1.0]))
    i = interaction_features(scene.occupancy, scene.centres_world, roots)
    with torch.no_grad():
        want = net.encoders["I"][0](torch.as_tensor(
            stats.normalize("interaction", i).astype(np.float32))).numpy()
    np.testing.assert_allclose(synth._interaction_first(scene, roots).numpy(), want,
                               rtol=1e-4, atol=1e-4)


def test_controlnet_line_end_comes_from_its_own_features(ci_run, tmp_path):
    """A run may pair a ControlNet trained with its line ending above the contact with
    another run's PoseNet: the controller builds h̃ with ControlNet's setting."""
    import json
    import shutil

    run = tmp_path / "run"
    shutil.copytree(ci_run.run_dir / "control", run / "control")
    (run / "pose").symlink_to(ci_run.run_dir / "pose")
    ck = torch.load(run / "control" / "best.pt", weights_only=True)
    meta = json.loads(ck["meta"])
    meta["feature_config"]["control_line_end"] = 0.05
    ck["meta"] = json.dumps(meta)
    torch.save(ck, run / "control" / "best.pt")
    paired = Synthesizer(run, "couch")
    assert paired.cfg.control_line_end == 0.0  # PoseNet's features
    assert paired.control_line_end == 0.05
    assert Synthesizer(ci_run.run_dir, "couch").control_line_end == 0.0
