"""The evaluation protocol and ``couch-eval`` on the session's ci-trained run (machinery only:
the numbers of a real run are in README's synthesis section)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from couch.synthesis import Scene, Synthesizer
from couch.synthesis.data import find_sequences, load_sequence
from couch.synthesis.evaluation import (
    EvalChair,
    contact_breakdown,
    contact_candidates,
    evaluate,
    ground_truth_row,
    miss_breakdown,
    segment_apd,
    trial_setup,
)
from couch.tools.evaluate import load_trials, main, simulated_chairs
from couch.tools.sim.chairs import make_chair, random_chair_spec


@pytest.fixture(scope="module")
def armchair():
    c = make_chair(random_chair_spec(np.random.default_rng(4), "armchair"))
    return EvalChair("armchair", c.vertices, c.faces)


def test_contact_candidates_lie_on_the_chair_on_their_side(armchair):
    cands = contact_candidates(armchair.vertices, armchair.faces)
    for side in ("left", "right"):  # 2 on the armrest + the seat's front corner
        assert {k: len(v) for k, v in cands[side].items()} == {"armrest": 2, "seat": 1}
    mesh = trimesh.Trimesh(armchair.vertices, armchair.faces, process=False)
    for side, sign in (("left", 1), ("right", -1)):
        pts = np.stack([p for points in cands[side].values() for p in points])
        assert np.all(sign * pts[:, 0] > 0.1)  # +X is the sitter's left
        _, dist, _ = trimesh.proximity.closest_point(mesh, pts)
        assert dist.max() < 0.01


def test_trial_setup_draws_starts_around_the_front(ci_run, armchair):
    syn = Synthesizer(ci_run.run_dir, "couch")
    scene = Scene.from_mesh(armchair.vertices, armchair.faces, syn.cfg)
    cands = contact_candidates(armchair.vertices, armchair.faces)
    starts, sets, parts = trial_setup(scene, cands, 50, np.random.default_rng(0))
    r = np.hypot(starts[:, 0] - scene.goal[0, 3], starts[:, 1] - scene.goal[2, 3])
    assert np.all((r >= 2.0) & (r <= 4.0))
    assert np.all(np.arctan2(starts[:, 0], starts[:, 1]) <= 2 * np.pi / 3 + 0.05)
    towards = np.arctan2(scene.goal[0, 3] - starts[:, 0], scene.goal[2, 3] - starts[:, 1])
    off = np.angle(np.exp(1j * (starts[:, 2] - towards)))
    assert np.all(np.abs(off) <= np.pi / 4) and np.ptp(off) > np.pi / 4  # facing it, varied
    asked = np.isfinite(sets[..., 0])
    assert asked.any(1).all() and asked.all(1).any() and (~asked).any()
    assert np.array_equal(parts != "", asked) and set(parts[asked]) == {"armrest", "seat"}
    world = np.c_[np.stack([p for ps in cands["left"].values() for p in ps]), np.ones(3)]
    arm_y = (world @ scene.world_from_chair.T)[0, 1]  # the armrests' centre
    assert np.all((np.abs(sets[..., 1] - arm_y) < 0.01)[asked] == (parts[asked] == "armrest"))


def test_two_hand_sets_are_ones_a_seated_person_can_hold(ci_run, armchair):
    """Both hands on one part (both armrests or both seat corners) and within HAND_SPAN: on a
    wide sofa both armrests together are out of reach, so its two-hand trials use the seat,
    while one-hand trials still ask for its armrests."""
    from couch.synthesis.evaluation import HAND_SPAN
    from couch.tools.sim.chairs import ChairSpec

    syn = Synthesizer(ci_run.run_dir, "couch")
    sofa = make_chair(ChairSpec.for_kind("sofa"))
    for chair in (armchair, EvalChair("sofa", sofa.vertices, sofa.faces)):
        cands = contact_candidates(chair.vertices, chair.faces)
        scene = Scene.from_mesh(chair.vertices, chair.faces, syn.cfg)
        _, sets, _ = trial_setup(scene, cands, 90, np.random.default_rng(1))
        seat_y = (scene.world_from_chair @ np.append(cands["left"]["seat"][0], 1.0))[1]
        count = np.isfinite(sets[..., 0]).sum(1)
        both, one = sets[count == 2], sets[count == 1]
        assert len(both) > 15 and len(one) > 40
        assert np.linalg.norm(both[:, 0] - both[:, 1], axis=-1).max() <= HAND_SPAN
        assert np.abs(both[:, 0, 1] - both[:, 1, 1]).max() < 0.01  # one part: one height
        both_on_arms = both[:, 0, 1] > seat_y + 0.05
        one_on_arms = np.nanmax(one[..., 1], axis=1) > seat_y + 0.05
        assert one_on_arms.any() and not one_on_arms.all()
        arms = np.linalg.norm(cands["left"]["armrest"][0] - cands["right"]["armrest"][0])
        if chair.name == "sofa":
            assert arms > HAND_SPAN and not both_on_arms.any()
        else:
            assert arms < HAND_SPAN and both_on_arms.any() and not both_on_arms.all()


def test_segment_apd_is_zero_for_identical_motions_and_grows_with_difference():
    rng = np.random.default_rng(0)
    j = rng.normal(0, 0.3, (60, 24, 3))
    j[:, 0, 1] = 0.9
    a, s = segment_apd([j, j.copy()], [30, 30], fps=30.0)
    assert a == pytest.approx(0.0) and s == pytest.approx(0.0)
    k = j.copy()
    k[:, 5:, 1] += 0.1  # a different pose (not a rigid move)
    a2, _ = segment_apd([j, k], [30, 30], fps=30.0)
    assert a2 > 0.1
    assert np.isnan(segment_apd([j, j], [-1, -1], fps=30.0)[0])


def test_evaluate_and_ground_truth_rows(ci_run, motion_sim, armchair):
    synths = {m: Synthesizer(ci_run.run_dir, m) for m in ("couch", "baseline")}
    rows, raw, labels, misses = evaluate(synths, [armchair], trials=3, seconds=1.5, seed=1,
                                         contact_samples=4, progress=False)
    assert labels.shape == (3, 2)
    assert set(labels.ravel()) - {""} <= {"armchair armrest", "armchair seat"}
    assert set(rows) == {"couch", "baseline"}
    for method, row in rows.items():
        assert row["ACE cm"] >= 0 and 0 <= row["AP@5 %"] <= 100
        assert raw[method].shape == (3, 2)
        # where each hand stopped: its length is the hand's distance, nothing where none asked
        off, sat = misses[method]["offset"], misses[method]["seated"]
        assert off.shape == (3, 2, 3) and sat.shape == (3, 2)
        np.testing.assert_allclose(np.linalg.norm(off, axis=-1), raw[method], equal_nan=True)
        assert np.array_equal(np.isnan(sat), labels == "")
        assert set(sat[labels != ""]) <= {0.0, 1.0}
        assert np.isfinite(row["skate mm/frame"]) and row["pen. depth cm"] >= 0
        # one chair: pooling over the chairs is that chair's contact APD (NaN for both when
        # the ci-sized ContactNet's samples leave fewer than two complete two-hand sets)
        assert row["contact APD pooled cm"] == pytest.approx(row["contact APD cm"],
                                                             nan_ok=True)
    sequences = [load_sequence(r) for r in find_sequences([motion_sim])]
    gt = ground_truth_row(sequences)
    assert gt["APD approach"] > 0 and gt["APD sit"] > 0
    # every simulated sequence has its own chair: no per-chair diversity to measure, only the
    # pooled one; two recordings of each chair with the same contacts have none per chair
    assert np.isnan(gt["contact APD cm"]) and gt["contact APD pooled cm"] > 10
    assert ground_truth_row(sequences[:2] * 2)["contact APD cm"] == 0.0
    # the simulator plants its stance feet: the data's own sliding is a small fraction of a
    # millimetre per frame (a foot dragged along the floor at walking speed is ~40)
    assert 0 < gt["skate mm/frame"] < 0.5, gt


def test_contact_breakdown_groups_the_asked_contacts():
    d = {"a": np.array([[0.01, np.nan], [0.10, 0.02], [np.nan, 0.04]]),
         "b": np.array([[0.03, np.nan], [0.02, 0.08], [np.nan, 0.06]])}
    labels = np.array([["sofa seat", ""], ["sofa armrest", "sofa seat"], ["", "sofa seat"]])
    out = contact_breakdown(d, labels)
    assert list(out) == ["sofa armrest", "sofa seat"]
    assert out["sofa armrest"] == pytest.approx({"n": 1, "a ACE cm": 10.0, "a AP@5 %": 0.0,
                                                 "b ACE cm": 2.0, "b AP@5 %": 100.0})
    seat = out["sofa seat"]
    assert seat["n"] == 3 and seat["a ACE cm"] == pytest.approx(7 / 3)
    assert seat["a AP@5 %"] == pytest.approx(100.0) and seat["b AP@5 %"] == pytest.approx(100 / 3)


def test_miss_breakdown_medians_per_asked_contact():
    up = np.array([0.0, 1.0, 0.0])
    misses = {"a": {"offset": np.array([[0.01 * up, [np.nan] * 3],
                                        [[0.03, 0.0, 0.04], 0.02 * up],
                                        [[np.nan] * 3, [0.0, -0.01, 0.0]]]),
                    "seated": np.array([[1.0, np.nan], [0.0, 1.0], [np.nan, 0.0]])}}
    labels = np.array([["sofa seat", ""], ["sofa armrest", "sofa seat"], ["", "sofa seat"]])
    out = miss_breakdown(misses, labels)
    assert list(out) == ["sofa armrest", "sofa seat"]
    # the armrest hand stopped level with its contact, 5 cm off across
    assert out["sofa armrest"] == pytest.approx({"n": 1, "a up cm": 0.0, "a across cm": 5.0,
                                                 "a seated %": 0.0})
    # seats: 1 cm above, 2 cm above and 1 cm below -> median 1 cm up, nothing across
    assert out["sofa seat"] == pytest.approx({"n": 3, "a up cm": 1.0, "a across cm": 0.0,
                                              "a seated %": 200 / 3})


def test_couch_eval_writes_table(ci_run, tmp_path, capsys):
    code = main([str(ci_run.run_dir), "-o", str(tmp_path), "--chairs", "1", "--trials", "2",
                 "--seconds", "1", "--contact-samples", "0", "--foot-lock", "-q"])
    assert code == 0, capsys.readouterr().err
    table = (tmp_path / "eval.md").read_text()
    assert "| couch |" in table and "| couch+ik |" in table and "| baseline |" in table
    assert "fp32 weights, feet locked" in table.splitlines()[0]  # the runtime is stated
    doc = json.loads((tmp_path / "eval.json").read_text())
    assert set(doc["rows"]) == {"couch", "couch+ik", "baseline"}
    assert doc["settings"]["precision"] == "fp32" and doc["settings"]["foot_lock"]
    # bootstrap intervals of every method, the reduction against the baseline for the others
    assert "bootstrap intervals over the 2 trials" in table and "- couch: ACE " in table
    assert set(doc["intervals"]) == set(doc["rows"])
    assert "ACE reduction %" in doc["intervals"]["couch"]
    assert "ACE reduction %" not in doc["intervals"]["baseline"]
    value = doc["intervals"]["couch"]["ACE cm"][0]
    assert value == pytest.approx(doc["rows"]["couch"]["ACE cm"])
    # where each method misses: per chair kind and part, the hands counted once
    assert "| contact | n | couch ACE cm |" in table
    assert doc["breakdown"] and all(k.startswith("armchair ") for k in doc["breakdown"])
    assert 2 <= sum(r["n"] for r in doc["breakdown"].values()) <= 4  # 2 trials, 1-2 hands
    # every trial's distances, for paired comparisons across runs: the table's ACE is theirs
    dist, labels, chair = load_trials(tmp_path)
    assert set(dist) == set(doc["rows"]) and labels.shape == (2, 2) and chair.shape == (2,)
    for method, d in dist.items():
        assert d.shape == (2, 2)
        assert 100 * np.nanmean(d) == pytest.approx(doc["rows"][method]["ACE cm"])
        assert np.array_equal(np.isnan(d), labels == "")  # a distance where a hand was asked
    assert set(chair) == {"armchair_00"}
    # and where each hand stopped, whose length is that distance
    assert "| contact | n | couch up cm | couch across cm | couch seated % |" in table
    assert set(doc["where"]) == set(doc["breakdown"])
    with np.load(tmp_path / "trials.npz", allow_pickle=False) as z:
        for method, d in dist.items():
            np.testing.assert_allclose(np.linalg.norm(z[f"offset/{method}"], axis=-1), d,
                                       equal_nan=True)
    np.savez(tmp_path / "other.npz", x=np.zeros(2))
    with pytest.raises(ValueError, match=r"other\.npz: not a couch-eval trials\.npz"):
        load_trials(tmp_path / "other.npz")
    (tmp_path / "cut.npz").write_bytes((tmp_path / "trials.npz").read_bytes()[:100])
    with pytest.raises(ValueError, match=r"cut\.npz: cannot read"):
        load_trials(tmp_path / "cut.npz")


def test_couch_eval_compares_with_the_plain_nsm(ci_nsm_run, tmp_path, capsys):
    """Paper Table 2: with nsm among the methods, every other method's ACE reduction against
    it is reported beside the one against the baseline, paired on the same trials."""
    code = main([str(ci_nsm_run.run_dir), "-o", str(tmp_path), "--chairs", "1", "--trials",
                 "2", "--seconds", "1", "--contact-samples", "0", "--methods",
                 "couch,baseline,nsm", "-q"])
    assert code == 0, capsys.readouterr().err
    doc = json.loads((tmp_path / "eval.json").read_text())
    assert set(doc["rows"]) == {"couch", "baseline", "nsm"}
    iv = doc["intervals"]
    for m in ("couch", "baseline"):
        value, low, high = iv[m]["ACE reduction vs NSM %"]
        assert value == pytest.approx(100 * (1 - doc["rows"][m]["ACE cm"]
                                             / doc["rows"]["nsm"]["ACE cm"]))
        assert low <= value <= high
    assert "ACE reduction vs NSM %" not in iv["nsm"] and "ACE reduction %" in iv["nsm"]
    assert "ACE reduction vs NSM " in (tmp_path / "eval.md").read_text()


def test_couch_eval_bad_input(ci_run, tmp_path, capsys):
    assert main([str(ci_run.run_dir), "-o", str(tmp_path), "--trials", "0"]) == 2
    assert main([str(ci_run.run_dir), "-o", str(tmp_path), "--chair-dir", str(tmp_path)]) == 2
    assert "no .obj/.ply" in capsys.readouterr().err
    assert main([str(ci_run.run_dir), "-o", str(tmp_path), "--which", "baseline=0"]) == 2
    assert "'0' is not 'best', 'last' or an epoch number" in capsys.readouterr().err


def test_simulated_chairs_are_new_and_varied():
    chairs = simulated_chairs(3, seed=0)
    assert [c.name.split("_")[0] for c in chairs] == ["armchair", "straight", "sofa"]
    again = simulated_chairs(3, seed=0)
    assert np.array_equal(chairs[0].vertices, again[0].vertices)


def test_hand_surface_points_are_on_the_asked_hands(ci_run, armchair):
    """ACE's hand points: a vertex of the asked hand (a few cm from its SMPL hand joint),
    NaN for a hand with no contact."""
    from couch.augment import SignedDistanceGrid
    from couch.body import JOINT_INDEX, load_body_model
    from couch.synthesis.evaluation import _body_metrics

    syn = Synthesizer(ci_run.run_dir, "couch")
    scene = Scene.from_mesh(armchair.vertices, armchair.faces, syn.cfg)
    cands = contact_candidates(armchair.vertices, armchair.faces)
    left, right = cands["left"]["armrest"][0], cands["right"]["armrest"][0]
    sets = np.array([[left, [np.nan] * 3], [left, right]])
    r = syn.synthesize(scene, np.array([[0.0, 2.0, np.pi], [0.5, 2.0, np.pi]]), sets[:, None],
                       seconds=0.3)
    sdf = SignedDistanceGrid.from_mesh(armchair.vertices, armchair.faces)
    _, _, palms = _body_metrics(r, sets, sdf, load_body_model("couch-body-coarse"))
    assert np.isnan(palms[0, :, 1]).all() and np.isfinite(palms[0, :, 0]).all()
    assert np.isfinite(palms[1]).all()
    joints = r.joints[:, :, [JOINT_INDEX["left_hand"], JOINT_INDEX["right_hand"]]]
    gap = np.linalg.norm(palms - joints, axis=-1)
    assert np.nanmax(gap) < 0.15 and np.nanmin(gap) > 0.0
    # the chosen vertex is the asked hand's closest one: nearer the contact than the joint is
    to_contact = np.linalg.norm(palms[1] - sets[1], axis=-1)
    assert np.all(to_contact <= np.linalg.norm(joints[1] - sets[1], axis=-1) + 0.02)
