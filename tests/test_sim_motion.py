"""The simulator's procedural motion against the issue's plausibility thresholds.

Settings: one sequence per interaction type and chair kind below (seed per case), the full body
model's skeleton, 30 fps sampling. Thresholds: stance feet slide < 1 cm, penetration into the
chair < 2 cm, no joint outside its anatomical range, planned palm contacts really touch the
chair (over each hold the palm's closest vertex a median -3 to 6 mm from it, and within 1 cm
inside to 1.5 cm above it in 80 % of the hold's frames; a draw whose palm the arm cannot bring
within 1 cm is rejected), a sitting pelvis rises less than
2.5 cm after it has started down, and the interaction mix follows the COUCH dataset's
proportions.
"""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest
import torch
from scipy.spatial.transform import Rotation

from couch.body import JOINT_INDEX, load_body_model
from couch.body.limits import joint_limit_excess_deg
from couch.fitting.body import world_rotations
from couch.tools.sim import motion as sim_motion
from couch.tools.sim.chairs import make_chair, random_chair_spec
from couch.tools.sim.motion import INTERACTION_MIX, sample_interaction
from couch.tools.sim.quality import foot_slide, penetration_depth
from couch.tools.sim.scene import chair_seat_geometry
from couch.tools.sim.session import simulate_motion_dataset, simulate_sequence
from couch.tools.sim.truth import ground_truth

CASES = [("right_hand", "armchair", 1), ("left_hand", "straight", 2), ("both_hands", "sofa", 3),
         ("both_hands", "straight", 4), ("no_contact", "stool", 5), ("free", "armchair", 6),
         ("locomotion", "sofa", 7), ("right_hand", "sofa", 8)]


@pytest.fixture(scope="module")
def models():
    return load_body_model("couch-body"), load_body_model("couch-body-coarse")


@pytest.fixture(scope="module")
def sequences(models):
    full, coarse = models
    out = []
    for interaction, kind, seed in CASES:
        seq = simulate_sequence(np.random.default_rng(seed), full, coarse,
                                interaction=interaction, chair=kind)
        times = np.arange(0.0, seq.motion.duration, 1 / 30)
        truth = ground_truth("t", seq.motion, times, seq.placement, full, coarse)
        out.append((interaction, kind, seq, truth))
    return out


@pytest.mark.parametrize("case", range(len(CASES)))
def test_motion_is_plausible(case, sequences, models):
    _full, coarse = models
    interaction, _kind, seq, truth = sequences[case]
    assert foot_slide(truth.joints) < 0.01
    with torch.no_grad():
        v = coarse(betas=truth.betas[None], global_orient=truth.global_orient,
                   body_pose=truth.body_pose, transl=truth.transl).vertices.numpy()
    chair_world = seq.placement.world_vertices
    assert penetration_depth(v, chair_world, seq.placement.faces).max() < 0.02
    assert joint_limit_excess_deg(truth.body_pose).max() < 0.5
    assert v[..., 1].min() > -0.02  # nobody sinks into the floor
    labels = set(np.unique(truth.interaction).tolist())
    if interaction == "locomotion":
        assert labels == {0}
        assert not truth.contact_active[:, 0].any()  # walking past, never sitting
    else:
        assert labels <= {0, {"right_hand": 1, "left_hand": 2, "both_hands": 3,
                              "no_contact": 4, "free": 5}[interaction]}
        assert truth.contact_active[:, 0].sum() > 15  # seated for over half a second


@pytest.mark.parametrize("case", [i for i, c in enumerate(CASES) if c[0].endswith("hand")
                                  or c[0] == "both_hands"])
def test_planned_palm_contacts_touch_the_chair(case, sequences):
    interaction, _, seq, truth = sequences[case]
    sides = ["left", "right"] if interaction == "both_hands" else [interaction.split("_")[0]]
    for side in sides:
        assert side in seq.motion.hand_contacts
        column = 1 if side == "left" else 2  # /contacts/names order
        assert truth.contact_active[:, column].sum() >= 5, f"{side} hand never touches"


@pytest.mark.parametrize("case", [i for i, c in enumerate(CASES) if c[0].endswith("hand")
                                  or c[0] == "both_hands"])
def test_held_palms_rest_on_the_chair(case, sequences, models):
    # A held palm rests on the surface: not hovering near the truth's 2 cm contact line (the
    # first placement left some 1.3-1.7 cm off) and not sunk into the chair.
    _, coarse = models
    _, _, seq, truth = sequences[case]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(seq.placement.world_vertices.astype(np.float32)),
                        o3d.core.Tensor(seq.placement.faces.astype(np.uint32)))
    for side, (t_on, t_off, _, part) in seq.motion.hand_contacts.items():
        held = (truth.time >= t_on) & (truth.time <= t_off)
        assert held.sum() >= 5, (side, part)
        with torch.no_grad():
            v = coarse(betas=truth.betas[None], global_orient=truth.global_orient[held],
                       body_pose=truth.body_pose[held], transl=truth.transl[held]).vertices
        hand = v[:, coarse.contact_vertices[f"{side}_hand"]].numpy()
        gap = scene.compute_signed_distance(o3d.core.Tensor(hand.reshape(-1, 3)), nsamples=5
                                            ).numpy().reshape(hand.shape[:2]).min(axis=1)
        # (a seat hold is short and the hand moves with the descending body, so its median at
        # other sample times than the generator's may read a few tenths of a millimetre inside)
        assert -0.003 < np.median(gap) < 0.006, (side, part, np.median(gap))
        # a few frames as the palm lands may still dip in or bounce (seen: 4 of 80 frames, to
        # 1.7 cm inside an armrest, as before the palms were seated; the body's penetration
        # bound above covers them), and a seat hold during the descent rolls the palm with the
        # forearm (seen: 1.2 cm above to 0.9 cm inside over 13 frames around a median of 0)
        rest = (gap > -0.01) & (gap < 0.015)
        assert rest.mean() > 0.8, (side, part, np.round(gap * 100, 2))


def test_palms_rest_part_way_when_resting_them_goes_in(sequences, models, monkeypatch):
    # When the rested palms would put the body past the penetration limit (forced here on the
    # one draw of case 0, which is accepted at its first try), the palm rests part of the way
    # down from where the plan put it, instead of staying there.
    full, coarse = models
    rested = sequences[0][2]
    assert rested.rejected == 0
    real_depth, real_gaps = sim_motion.max_penetration, sim_motion._palm_gaps
    calls = []

    def rested_goes_in(*args, **kwargs):
        calls.append(1)
        return 1.0 if len(calls) == 1 else real_depth(*args, **kwargs)

    def draw():
        seq = simulate_sequence(np.random.default_rng(CASES[0][2]), full, coarse,
                                interaction=CASES[0][0], chair=CASES[0][1])
        return real_gaps(coarse, seq.motion, (seq.chair.vertices, seq.chair.faces))["right"]

    monkeypatch.setattr(sim_motion, "max_penetration", rested_goes_in)
    part_way = draw()
    monkeypatch.setattr(sim_motion, "max_penetration", real_depth)
    monkeypatch.setattr(sim_motion, "_palm_gaps", lambda model, motion, mesh, hz=30.0: {
        side: sim_motion.TOUCH_GAP for side in motion.hand_contacts})  # nothing to correct
    planned = draw()
    rest = real_gaps(coarse, rested.motion, (rested.chair.vertices, rested.chair.faces))["right"]
    assert abs(rest - sim_motion.TOUCH_GAP) < 0.002
    assert planned > rest + 0.002, (planned, rest)  # the plan's palm hovers above the rest ...
    # ... and the first share tried, three quarters of the way down, is taken (measured: the
    # plan 5.6 mm above, rested 3.0, part way 3.7)
    assert rest < part_way < rest + 0.5 * (planned - rest), (rest, part_way, planned)


def _bench_first_draw(models, seed: int, kind: str, interaction: str,
                      config: sim_motion.MotionConfig | None = None):
    """The accuracy bench's first motion draw for a session seed, as ``simulate_sequence``
    draws it (the chair first, from the same generator), and its chair."""
    full, coarse = models
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(4)[0])
    chair = make_chair(random_chair_spec(rng, kind))
    seat = chair_seat_geometry(chair.vertices, chair.faces, chair.landmarks, chair.face_parts)
    return sim_motion.generate_motion(full, seat, rng, interaction=interaction, duration=8.0,
                                      config=config, chair_mesh=(chair.vertices, chair.faces),
                                      collision_model=coarse), chair


def test_a_palm_the_arm_cannot_bring_down_is_rejected(models):
    # The accuracy bench's sofa-both+2000 first draw: the left palm's seat hold starts 0.08 s
    # before the landing, but the pelvis, held up over the descent, keeps the shoulder too high
    # for the straight arm; the palm hangs 4-6 cm above the seat through most of its hold and
    # touches for 0.27 s from 0.2 s after the landing. Its label said both hands supported; the
    # detector, reading 0.27 s of touch, said the right hand only (on the truth motion too).
    _, coarse = models
    with pytest.raises(sim_motion.MotionRejected, match=r"left palm stays .* above its target"):
        _bench_first_draw(models, 2023, "sofa", "both_hands")
    motion, chair = _bench_first_draw(models, 2023, "sofa", "both_hands",
                                      sim_motion.MotionConfig(max_palm_gap=np.inf))
    gaps = sim_motion._palm_gaps(coarse, motion, (chair.vertices, chair.faces))
    # measured: left 3.8 cm above the seat over its hold (median), right 0.4 cm
    assert gaps["left"] > 0.03 and gaps["right"] < 0.006, gaps


@pytest.mark.xfail(strict=True, raises=AssertionError,
                   reason="known simulator fault (README: Palms held on armrests): a held "
                   "palm's fingers follow the forearm, which turns as the body moves")
def test_a_palm_held_on_an_armrest_does_not_turn(models):
    # The accuracy bench's armchair-right+2000 draw (its first, accepted). A palm resting on an
    # armrest stays put; the simulator's hand turns up to 157 degrees away from the way it
    # landed over the hold, at up to 10,000 degrees/s (85 degrees in one 120 Hz frame;
    # measured). Strict, and only for the assertion: a mend makes this pass, and then the
    # marker goes.
    motion, _ = _bench_first_draw(models, 2005, "armchair", "right_hand")
    t_on, t_off, _, part = motion.hand_contacts["right"]
    assert part == "right_armrest"
    held = (motion.time >= t_on) & (motion.time <= t_off)
    # the hand's world rotation (chair frame)
    hand = world_rotations(torch.as_tensor(motion.local_rot[held]))[
        :, JOINT_INDEX["right_wrist"]].numpy()
    turn = np.degrees(Rotation.from_matrix(np.swapaxes(hand[:1], -1, -2) @ hand).magnitude())
    speed = np.degrees(Rotation.from_matrix(np.swapaxes(hand[:-1], -1, -2) @ hand[1:])
                       .magnitude()) / np.diff(motion.time[held])
    assert turn.max() < 15 and speed.max() < 150, (turn.max(), speed.max())


def test_interaction_mix_follows_the_couch_dataset():
    rng = np.random.default_rng(0)
    draws = [sample_interaction(rng) for _ in range(20000)]
    for name, share in INTERACTION_MIX.items():
        assert abs(draws.count(name) / len(draws) - share) < 0.01, name


def test_motion_only_dataset(tmp_path):
    summary = simulate_motion_dataset(tmp_path, 2, seed=5, progress=False)
    assert [s["file"] for s in summary["sequences"]] == ["motion_00000.h5", "motion_00001.h5"]
    from couch.schema import read_processed

    first = read_processed(tmp_path / "motion_00000.h5")
    assert first.num_frames == summary["sequences"][0]["frames"]
    # deterministic by seed, whatever the number of worker processes
    again = simulate_motion_dataset(tmp_path / "again", 2, seed=5, progress=False, workers=2)
    assert again["sequences"] == summary["sequences"]
    for entry in summary["sequences"]:
        a, b = (read_processed(d / entry["file"]) for d in (tmp_path, tmp_path / "again"))
        assert np.array_equal(a.joints, b.joints) and np.array_equal(a.body_pose, b.body_pose)
        assert np.array_equal(a.contact_active, b.contact_active)
        assert np.array_equal(a.contact_points, b.contact_points, equal_nan=True)
    with pytest.raises(ValueError, match="--workers must be >= 1"):
        simulate_motion_dataset(tmp_path / "bad", 1, seed=5, progress=False, workers=0)


def test_motion_only_dataset_resumes_where_it_stopped(tmp_path, monkeypatch):
    # A run stopped after its first slot keeps that slot; the re-run draws only the rest, and a
    # finished folder asked for one more sequence draws only that one.
    from couch.tools.sim import session

    drawn: list[int] = []
    stop_at = {1}  # Ctrl-C as slot 1 begins
    real_slot = session._motion_slot

    def slot(i, *args):
        if i in stop_at:
            raise KeyboardInterrupt
        drawn.append(i)
        return real_slot(i, *args)

    monkeypatch.setattr(session, "_motion_slot", slot)
    with pytest.raises(KeyboardInterrupt):
        simulate_motion_dataset(tmp_path, 2, seed=5, duration=4.0, progress=False)
    assert drawn == [0] and not (tmp_path / "index.json").exists()
    first = (tmp_path / "motion_00000.h5").stat().st_mtime_ns
    stop_at.clear()
    summary = simulate_motion_dataset(tmp_path, 2, seed=5, duration=4.0, progress=False)
    assert drawn == [0, 1] and summary["resumed"] == 1
    assert (tmp_path / "motion_00000.h5").stat().st_mtime_ns == first
    assert [s["file"] for s in summary["sequences"]] == ["motion_00000.h5", "motion_00001.h5"]
    assert not (tmp_path / session.JOURNAL).exists()
    more = simulate_motion_dataset(tmp_path, 3, seed=5, duration=4.0, progress=False)
    assert drawn == [0, 1, 2] and more["resumed"] == 2
    assert more["sequences"][:2] == summary["sequences"]
    # asked for fewer, the slot the index no longer lists goes; a file no index listed stays
    (tmp_path / "motion_00099.h5").write_bytes(b"not ours")
    fewer = simulate_motion_dataset(tmp_path, 2, seed=5, duration=4.0, progress=False)
    assert drawn == [0, 1, 2] and fewer["removed"] == ["motion_00002.h5"]
    assert sorted(f.name for f in tmp_path.glob("motion_*.h5")) == [
        *(s["file"] for s in fewer["sequences"]), "motion_00099.h5"]
    # another request in the same folder is refused, naming what differs
    with pytest.raises(ValueError, match=r"index\.json: .*seed 5 \(now 6\)"):
        simulate_motion_dataset(tmp_path, 3, seed=6, duration=4.0, progress=False)
    with pytest.raises(ValueError, match=r"duration 4\.0 \(now None\)"):
        simulate_motion_dataset(tmp_path, 3, seed=5, progress=False)
    (tmp_path / "index.json").write_text('{"seed": 5, "fps": 30.0, "sequences": []}')
    with pytest.raises(ValueError, match="did not record what it was asked for"):
        simulate_motion_dataset(tmp_path, 3, seed=5, duration=4.0, progress=False)


def test_motion_only_command_keeps_the_frame_rate_asked(tmp_path, capsys):
    # `couch-simulate --motion-only --fps 15` wrote 30 fps motions until session 42
    from couch.schema import read_processed
    from couch.tools.sim.session import main

    assert main([str(tmp_path), "--motion-only", "--fps", "15", "--duration", "4",
                 "--seed", "7", "--quiet"]) == 0
    motion = read_processed(tmp_path / "motion_00000.h5")
    assert motion.fps == 15.0
    assert np.allclose(np.diff(motion.time), 1 / 15.0)
    # the folder holds seed 7's draw: another seed is refused, naming it, unless --no-resume
    again = [str(tmp_path), "--motion-only", "--fps", "15", "--duration", "4", "--seed", "8",
             "--quiet"]
    assert main(again) == 1
    assert "seed 7 (now 8)" in capsys.readouterr().err
    assert main([*again, "--no-resume"]) == 0
    # seed 8's only slot finds no plausible draw at 4 s: seed 7's file goes, not left for
    # training to pick up beside an index that does not list it
    index = json.loads((tmp_path / "index.json").read_text())
    assert index["request"]["seed"] == 8 and index["removed"] == ["motion_00000.h5"]
    assert [s["sequence"] for s in index["skipped"]] == [0]
    assert not list(tmp_path.glob("motion_*.h5"))


def test_motion_only_dataset_skips_an_implausible_slot(tmp_path):
    # seed 3's first slot has its only draw rejected: it is skipped and named, the rest written
    summary = simulate_motion_dataset(tmp_path, 2, seed=3, duration=4.0, progress=False,
                                      max_draws=1)
    assert [s["sequence"] for s in summary["skipped"]][:1] == [0]
    assert "plausible" in summary["skipped"][0]["reason"]
    assert len(summary["sequences"]) + len(summary["skipped"]) == 2
    assert not (tmp_path / "motion_00000.h5").exists()
    with pytest.raises(ValueError, match="--chair must be one of"):
        simulate_motion_dataset(tmp_path / "bad", 1, seed=3, chair="throne", progress=False)


@pytest.mark.parametrize("case", [i for i, c in enumerate(CASES) if c[0] != "locomotion"])
def test_the_pelvis_goes_down_once(case, sequences):
    # Sitting down, the pelvis goes down and stays, without a jolt. The planned motion rises up
    # to ~2.5 cm as it leaves the walk's height at the sit's start (0.2-1.8 cm on these
    # draws). The penetration push lifted the body out of the chair wherever any vertex was in
    # it (arms through armrests, held palms) and the seated pass lowered it again: the
    # two-hand sofa draw's pelvis rose 4.1 cm after it had started down, and the 10 cm clip on
    # the push stopped lifts dead (the armchair draws and the stool: 41-86 m/s², 2.2 cm up).
    # These draws now rise 0-0.02 cm after the descent starts, at most 5.7 m/s².
    _, _, seq, _ = sequences[case]
    phases = {name: (a, b) for name, a, b in seq.motion.phases}
    t, y = seq.motion.time, seq.motion.transl[:, 1]
    sitting = (t >= phases["sit"][0]) & (t <= phases["seated"][1])
    ys = y[sitting]
    rise = ys - np.minimum.accumulate(ys)
    assert rise.max() < 0.025, rise.max()
    accel = np.abs(np.diff(y, 2)) * (1 / np.diff(t).mean()) ** 2  # m/s², 120 Hz
    assert accel[sitting[1:-1]].max() < 10.0, accel[sitting[1:-1]].max()


def _pushed_descent(bump: float, seated_y: float = 0.5):
    """A 120 Hz pelvis sitting from 0.9 m down to ``seated_y`` over 1-2 s (seated to 3.5 s),
    with a push of ``bump`` m centred at 2.05 s (a lift for an arm in an armrest)."""
    from types import SimpleNamespace

    t = np.arange(0.0, 4.0, 1 / 120)
    plan = 0.9 + (seated_y - 0.9) * sim_motion.smoothstep(t - 1.0)
    offset = np.zeros((len(t), 3))
    offset[:, 1] = bump * np.exp(-0.5 * ((t - 2.05) / 0.06) ** 2)
    transl = np.zeros((len(t), 3))
    transl[:, 1] = plan + offset[:, 1]
    phases = [("walk", 0.0, 0.9), ("sit", 1.0, 2.0), ("seated", 2.0, 3.5)]
    return SimpleNamespace(time=t, transl=transl), offset, phases, plan


def test_a_pushed_descent_pauses_instead_of_bouncing():
    motion, offset, phases, plan = _pushed_descent(0.04)
    t, before = motion.time, motion.transl[:, 1]
    assert (before - np.minimum.accumulate(before))[t >= 1.0].max() > 0.025  # it bounces
    out = sim_motion._descend_once(motion, offset, phases)
    y = plan + out[:, 1]
    down = (t >= 1.0) & (t <= 3.5)
    assert np.diff(y[down]).max() <= 1e-12  # never up again
    np.testing.assert_array_equal(out[~down], offset[~down])  # nothing moves outside
    # the pelvis is held up, not pushed down: it is at least as high wherever the push lifted
    # it, save the smoothing's rounding of the corners (6 mm at the lift's peak here)
    assert (y - before)[down].min() > -0.007
    assert y[(t > 1.9) & (t < 2.05)].min() > before.max(where=t > 1.9, initial=0) - 0.007
    # continuous into the frames around it, and no jolt (a stop dead is ~50 m/s²)
    assert np.abs(np.diff(y)).max() < 0.01
    assert (np.abs(np.diff(y, 2)) * 120**2).max() < 12.0


def test_a_descent_that_does_not_bounce_or_climbs_is_left_alone():
    motion, offset, phases, _ = _pushed_descent(0.0)
    assert sim_motion._descend_once(motion, offset, phases) is offset
    # a bar stool above the standing pelvis is climbed onto: its late lift stays
    motion, offset, phases, _ = _pushed_descent(0.0, seated_y=0.95)
    assert sim_motion._descend_once(motion, offset, phases) is offset


@pytest.mark.parametrize("case", range(len(CASES)))
def test_joints_move_at_human_speeds(case, sequences):
    # IK branch flips (a limb spinning 180° about its bone between frames) showed up as hands
    # and toes jumping 0.5-0.8 m in one 30 fps frame (15-25 m/s). Arms of people sitting down
    # and reaching for a chair peak near 3 m/s; the procedural gait's swinging toes reach
    # ~3.5-4x the walking speed (up to ~5.7 m/s), so the whole body gets a looser bound.
    _, _, _, truth = sequences[case]
    speed = np.linalg.norm(np.diff(truth.joints, axis=0), axis=-1) * 30.0  # (T-1, 24) m/s
    arms = slice(16, 24)  # shoulders, elbows, wrists, hands
    assert speed[:, arms].max() < 4.0, speed[:, arms].max()
    assert speed.max() < 6.0, (speed.max(), speed.max(0).argmax())


@pytest.mark.parametrize("case", range(len(CASES)))
def test_the_torso_leans_smoothly_for_the_hands(case, sequences, models):
    # The lean that brings a reaching hand's shoulder within reach was sampled in twentieths of
    # the turn (steps of up to 9° between frames: necks at 3.5-6.3 m/s, 11.6 on the two-hand
    # sofa draw), and while a hand moved onto the chair the torso bent the lean that would
    # reach the target from the still-high body (60-90° mid-descent, rejected as unreachable).
    # At the motion's own 120 Hz the torso of a person sitting down stays under 4 m/s.
    _, coarse = models
    _, _, seq, _ = sequences[case]
    m = seq.motion
    go, bp, tr, _ = m.sample(m.time)
    with torch.no_grad():
        j = coarse(betas=m.betas[None], global_orient=go, body_pose=bp, transl=tr).joints
    speed = np.linalg.norm(np.diff(j.numpy(), axis=0), axis=-1) / np.diff(m.time)[:, None]
    torso = [3, 6, 9, 12]  # spine1-3, neck (SMPL order)
    assert speed[:, torso].max() < 4.0, (speed[:, torso].max(0), m.time[speed[:, 12].argmax()])


def test_the_least_turn_is_exact_not_sampled():
    # A shoulder 0.4 m up from the pivot, turned about z towards a target 1 m out along x:
    # turned by a, it lies sqrt(r^2 + d^2 - 2 r d sin(a)) from the target (r = 0.4, d = 1).
    n = 50
    reach = np.linspace(0.95, 1.05, n)
    full = np.tile([0.0, 0.0, -np.pi / 2], (n, 1))  # y towards x
    frac = sim_motion._least_turn(np.zeros((n, 3)), np.full((n, 1), 0.4),
                                  np.tile([0.0, 1.0, 0.0], (n, 1)), full,
                                  np.tile([1.0, 0.0, 0.0], (n, 1)), reach)
    need = np.arcsin(np.clip((0.16 + 1.0 - reach**2) / 0.8, -1, 1)) / (np.pi / 2)
    need = np.where(np.hypot(0.4, 1.0) < reach, 0.0, need)
    np.testing.assert_allclose(frac, need, atol=1e-3)  # twentieths were up to 0.05 over
    assert (np.diff(frac) <= 0).all()  # farther reach, less turn: no steps back


def test_a_part_way_blend_keeps_turning_the_same_way_past_180_degrees():
    # An arm blended part of the way between its procedural pose and its IK pose swung 127° in
    # one 120 Hz frame where the two came to be 180° apart (the shortest way round changed
    # sides); seen on a two-hand sofa draw at 8 m/s.
    from scipy.spatial.transform import Rotation

    n = 40
    a = np.broadcast_to(np.eye(3), (n, 3, 3))
    b = Rotation.from_rotvec(np.radians(np.linspace(160.5, 199.5, n))[:, None] * [0.0, 0, 1]
                             ).as_matrix()  # 180° apart between frames 19 and 20
    w = np.full(n, 0.5)
    w[:3], w[-3:] = 0.0, 1.0
    out = sim_motion._blend_rot(a, b, w)
    step = np.degrees(Rotation.from_matrix(np.swapaxes(out[:-1], -1, -2) @ out[1:]).magnitude())
    partial = (w[1:] > 0) & (w[1:] < 1) & (w[:-1] > 0) & (w[:-1] < 1)
    assert step[partial].max() < 1.0, step.max()  # half of the 1° per frame that b turns
    np.testing.assert_allclose(out[:3], a[:3], atol=1e-12)
    np.testing.assert_allclose(out[-3:], b[-3:], atol=1e-12)
    # before the two are 180° apart the blend is the plain shortest-way slerp, to the bit
    plain = (Rotation.from_matrix(a) * Rotation.from_rotvec(
        (Rotation.from_matrix(a).inv() * Rotation.from_matrix(b)).as_rotvec() * w[:, None])
             ).as_matrix()
    assert np.array_equal(out[:20], plain[:20])
    assert np.abs(out[21:-3] - plain[21:-3]).max() > 1.0  # the other way round after it


def test_a_steady_pole_keeps_the_elbow_from_spinning_round_the_arm():
    # A pole fixed to the body lines up with the shoulder-wrist line when a hand passes along
    # it; the elbow then spins round the line within a few frames (a draw's elbow at 19.6 m/s).
    from couch.geometry import two_bone_ik
    from couch.tools.sim.ik import steady_pole

    n, fps = 121, 120.0
    root = np.zeros((n, 3))
    target = np.stack([np.linspace(-0.2, 0.2, n), np.full(n, -0.45), np.full(n, 0.003)], 1)
    pole = np.array([0.0, -1.0, 0.0])  # straight down: the hand passes just in front of it

    def speed(p):
        return np.linalg.norm(np.diff(p, axis=0), axis=1) * fps

    fixed = two_bone_ik(root, target, pole, 0.3, 0.25)[0]
    steady = steady_pole(root, target, pole, 0.3, 0.25, fps, 2.5)
    middle, _, lower, _ = two_bone_ik(root, target, steady, 0.3, 0.25)
    assert speed(fixed).max() > 10.0
    assert speed(middle).max() < 3.0  # 2.5 m/s round the line and the line's own 0.4 m/s
    np.testing.assert_allclose(middle + 0.25 * lower, target, atol=1e-9)  # still reaches it
    slow = np.flatnonzero(speed(fixed) < 1.0)[:10] + 1  # before the spin: untouched
    assert np.array_equal(steady[slow], np.broadcast_to(pole, (len(slow), 3)))


def test_a_sofa_is_sat_on_along_its_length_and_a_chair_in_its_middle(models):
    """People sit anywhere along a sofa, often at an end with an arm on the armrest: a
    one-hand sitter's pelvis moves along a sofa's seat (within 0.3 m of its side edges, half
    the time at an end) and its armrests become reachable; a chair is sat on in its middle."""
    from couch.tools.sim.chairs import ChairSpec, make_chair
    from couch.tools.sim.motion import generate_motion
    from couch.tools.sim.scene import chair_seat_geometry

    full, _ = models
    for kind in ("sofa", "armchair"):
        chair = make_chair(ChairSpec.for_kind(kind))
        seat = chair_seat_geometry(chair.vertices, chair.faces, chair.landmarks,
                                   chair.face_parts)
        half = max(abs(p[0]) for k in ("left_seat", "right_seat")
                   for p, _ in seat.hand_targets[k])
        xs, parts = [], []
        for seed in range(12):  # 7 of them draw on the sofa
            try:
                m = generate_motion(full, seat, np.random.default_rng(seed),
                                    interaction=("left_hand", "right_hand")[seed % 2])
            except ValueError:
                continue
            seated = next(p for p in m.phases if p[0] == "seated")
            mid = np.searchsorted(m.time, 0.5 * (seated[1] + seated[2]))
            rest = full.rest_joints(torch.as_tensor(m.betas[None], dtype=full.dtype))
            xs.append(m.transl[mid, 0] + float(rest[0, 0, 0]) - seat.seat_center[0])
            parts += [c[3] for c in m.hand_contacts.values()]
        xs = np.array(xs)
        assert len(xs) >= 6
        if kind == "sofa":
            assert np.abs(xs).max() <= half - 0.3 + 0.02 and np.ptp(xs) > 0.4
            assert np.isclose(np.abs(xs), half - 0.3, atol=0.02).sum() >= 2  # at an end
            assert any(p.endswith("armrest") for p in parts)
        else:
            assert np.abs(xs).max() < 0.02
