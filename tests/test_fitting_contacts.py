"""Contacts and interaction labels (fitting/contacts.py, issue 8 item 2).

Behaviour on synthetic signals (hysteresis, gap filling, minimum durations, fps), bad inputs,
and accuracy on simulated motions against the simulator's ground truth, which the detector does
not share code with (truth: tools/sim/truth.py, a part touches when one of its unclothed
contact vertices is within 2 cm of the chair, no velocity, no hysteresis; labels: the motion
plan's interaction type from the turn at the chair to half a second into leaving).

Simulator settings: ``simulate_motion_dataset`` (motion only, no rendering), 10 s at 15 fps,
one sequence per (interaction, chair, seed) in :data:`CASES`; the detector runs on the truth
motion and on it perturbed like an IMU (``imu_like_init``: 3 deg per bone and axis, 1 cm per
axis, white per frame), with the coarse body model.

Measured when written (``pytest -s``, 19 sequences, 2850 frames), IMU-like motion / truth
motion: contact F1 pelvis 0.99 / 1.00, left hand 0.69 / 0.96, right hand 0.71 / 0.99 (feet:
2 truth frames in all, see the printout); label accuracy 0.99 / 0.99 (0.933 / 0.934 while
a touch anywhere in the episode counted as support: the left hand of right-hand sequences on
armchairs brushes the armrest while the subject turns in front of the chair); median contact
point error hands 1.4 / 0.5-0.9 cm, pelvis ~12 cm (the truth's point is its single
nearest vertex's, which jumps between seat and backrest). The detector measures the motion's
own per-frame noise and applies its guards (smoothing, speed gate, gap filling, minimum
duration) only as far as that noise asks: on the exact truth motion it trusts each frame, and
hand F1 went from 0.84 / 0.85 to 0.96 / 0.99 (the guards had dropped palms that touch the
chair for one or two frames while moving, and moved every hold's ends by a frame; at 5 fps,
measured apart, 0.90 / 0.90 to 0.95 / 0.98). What is left are the 13 frames of a left palm
hovering 2-3 cm over an armrest between two touches, which the hysteresis band holds (it
stays whole at any noise: it also holds a fitted palm through the fit's offset). On the
IMU-like motion the hands move ~3.5 cm per frame, more than the 2 cm that separates touching
from hovering, and most hand contacts last under half a second: 0.69 / 0.71, below the
issue's 0.95 (more smoothing loses the short holds: 0.45-0.53 at twice the sigma). Detection
runs at ~700 frames/s on 2 cores (coarse body model). Re-measured 2026-11-29, the simulator's
held palms resting on the chair and the band 2-2.5 cm (IMU-like / truth): left hand 0.70 /
0.96, right hand 0.74 / 1.00, labels 0.97 / 0.99 (one sofa sequence's labels 0.53 under the
perturbation; the same with the 3 cm band). Re-measured 2026-12-05 with the palm-down rule
(``ContactConfig.palm_down``) and a second two-hand sofa sequence (20 sequences, 3010 frames):
left hand 0.72 / 1.00, right hand 0.86 / 1.00, labels 0.993 / 0.992, each sequence 0.94 or
more (that sofa sequence 0.35 before the rule). Re-measured 2026-12-06 with the contact point
as the centre of a 2 cm patch instead of 1 cm (``ContactConfig.point_patch``; the truth's
point stays its single closest, so a wider patch is farther from it by construction): median
hand point error 0.88 / 0.83 cm on the truth motion (0.64 / 0.48 with 1 cm), 1.92 / 1.62 on
the IMU-like one (1.26 / 1.43), pelvis 11.1 / 11.3 cm either way.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from couch.body import CONTACT_NAMES, JOINT_INDEX
from couch.capture.segmentation import ChairModel
from couch.fitting import BodyParams
from couch.fitting.body import cached_model
from couch.fitting.contacts import (
    FEET,
    ChairSurface,
    ContactConfig,
    contact_flags,
    detect_contacts,
    drop_short_runs,
    fill_gaps,
    hysteresis,
    interaction_labels,
    motion_noise,
    palm_down,
    runs,
    smoothing_sigma,
    trim_edges,
    walking,
)
from couch.geometry import apply_transform
from couch.schema import INTERACTION_LABELS, read_processed
from couch.tools.bench.fitting import imu_like_init
from couch.tools.sim.session import simulate_motion_dataset

FPS = 15.0
# (interaction, chair kind or None for the simulator's choice, seed): seeds whose draws succeed
# quickly; every interaction type and every chair kind appears.
CASES = [
    ("right_hand", "straight", 0), ("right_hand", "straight", 1), ("right_hand", "straight", 2),
    ("right_hand", "armchair", 0), ("right_hand", "armchair", 1),
    ("left_hand", "sofa", 0), ("left_hand", "sofa", 2), ("left_hand", "straight", 0),
    ("left_hand", "straight", 1),
    ("both_hands", "sofa", 1), ("both_hands", "sofa", 2), ("both_hands", None, 17),
    ("both_hands", None, 13),
    ("no_contact", "stool", 0), ("no_contact", "stool", 1), ("no_contact", "sofa", 0),
    ("free", "straight", 0), ("free", "armchair", 1), ("free", "stool", 1),
    ("locomotion", "straight", 0),
]


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box mesh (8 vertices, 12 outward triangles)."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], float)
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [2, 3, 7], [2, 7, 6], [1, 2, 6], [1, 6, 5], [0, 4, 7], [0, 7, 3]])
    return v, f


# ----------------------------------------------------------------------- behaviour


def test_hysteresis_holds_between_thresholds():
    d = np.array([5, 3, 1.9, 2.5, 2.9, 3.1, 2.5, 1.5, 0.0]) / 100.0  # m
    enter, leave = d < 0.02, d > 0.03
    assert hysteresis(enter, leave).tolist() == [0, 0, 1, 1, 1, 0, 0, 1, 1]
    assert hysteresis(enter, leave, initial=True).tolist() == [0, 0, 1, 1, 1, 0, 0, 1, 1]
    assert hysteresis(d[:2] > 1, d[:2] > 1, initial=True).tolist() == [1, 1]
    # (T,K) at once: each column on its own
    both = hysteresis(np.stack([enter, enter[::-1]], 1), np.stack([leave, leave[::-1]], 1))
    assert both[:, 1].tolist() == hysteresis(enter[::-1], leave[::-1]).tolist()
    with pytest.raises(ValueError, match="both enters and leaves"):
        hysteresis(np.ones(3, bool), np.ones(3, bool))


def test_noise_around_one_threshold_does_not_flicker():
    rng = np.random.default_rng(0)
    t = np.arange(300) / 30.0
    # resting 1.7 cm off the surface with 3 mm of noise: around the 2 cm entry threshold
    d = np.where((t > 3) & (t < 7), 0.017, 0.05) + rng.normal(0, 0.003, len(t))
    on = contact_flags(d[:, None], np.zeros((len(t), 1)), 30.0)[:, 0]
    s, e = runs(on)
    assert len(s) == 1 and abs(s[0] / 30 - 3) < 0.2 and abs(e[0] / 30 - 7) < 0.2
    naive = d < 0.02
    assert len(runs(naive)[0]) > 1  # what the hysteresis and the durations prevent


def test_gaps_filled_and_blips_dropped():
    f = np.array([0, 1, 1, 0, 1, 1, 0, 0, 0, 1, 0, 0, 1, 1, 1], bool)
    assert fill_gaps(f, 1).tolist() == [0, 1, 1, 1, 1, 1, 0, 0, 0, 1, 0, 0, 1, 1, 1]
    assert fill_gaps(f, 3).tolist() == [0] + [1] * 14  # the leading gap is no gap
    assert drop_short_runs(f, 2).tolist() == [0, 1, 1, 0, 1, 1, 0, 0, 0, 0, 0, 0, 1, 1, 1]
    assert drop_short_runs(f, 3).tolist() == [0] * 12 + [1, 1, 1]
    two = drop_short_runs(np.stack([f, ~f], 1), 2)
    assert two[:, 0].tolist() == drop_short_runs(f, 2).tolist()
    assert two[:, 1].tolist() == drop_short_runs(~f, 2).tolist()


@pytest.mark.parametrize("fps", [5.0, 15.0, 30.0])
def test_durations_are_seconds_at_any_fps(fps):
    """The same physical signal gives the same contact times at 5, 15 and 30 fps: a 0.5 s
    contact with a 0.07 s dropout (filled) and a 0.1 s blip (dropped)."""
    cfg = ContactConfig(min_duration=0.3, max_gap=0.2)
    t = np.arange(0, 3, 1 / fps)
    d = np.full(len(t), 0.05)
    d[(t >= 1.0) & (t < 1.5)] = 0.005
    d[(t >= 1.2) & (t < 1.27)] = 0.05  # dropout inside the contact
    d[(t >= 2.5) & (t < 2.6)] = 0.005  # a 0.1 s blip
    on = contact_flags(d[:, None], np.zeros((len(t), 1)), fps, cfg)[:, 0]
    s, e = runs(on)
    assert len(s) == 1
    assert abs(t[s[0]] - 1.0) <= 1 / fps and abs(t[e[0] - 1] + 1 / fps - 1.5) <= 1 / fps + 1e-9


def test_speed_gate_rejects_passing_by():
    """A hand that sweeps past the surface at 1.5 m/s is no contact; one that stops is."""
    n = 40
    d = np.full((n, 2), 0.005)
    speed = np.zeros((n, 2))
    speed[:, 0] = 1.5
    on = contact_flags(d, speed, 30.0)
    assert not on[:, 0].any() and on[:, 1].all()
    # a resting hand that starts moving fast while still close lets go
    speed[25:, 1] = 1.5
    on = contact_flags(d, speed, 30.0)
    assert on[:25, 1].all() and not on[25:, 1].any()


def test_edges_trimmed_to_the_contact_distance():
    f = np.array([0, 1, 1, 1, 1, 1, 0, 1, 1, 0], bool)
    core = np.array([0, 0, 1, 0, 1, 0, 0, 0, 0, 0], bool)
    assert trim_edges(f, core).tolist() == [0, 0, 1, 1, 1, 0, 0, 0, 0, 0]
    both = trim_edges(np.stack([f, f], 1), np.stack([core, f], 1))
    assert both[:, 1].tolist() == f.tolist()
    with pytest.raises(ValueError, match="differ"):
        trim_edges(f, core[:5])


def test_motion_noise_measures_white_noise_not_motion():
    rng = np.random.default_rng(3)
    t = np.arange(300) / 30.0
    # a hand swinging 30 cm at 1 Hz: smooth motion, 30 fps
    track = np.stack([0.3 * np.sin(2 * np.pi * t), 0.1 * t, np.zeros_like(t)], 1)[:, None]
    assert motion_noise(track) < 0.003
    noisy = track + rng.normal(0, 0.01, track.shape)
    assert motion_noise(noisy) == pytest.approx(0.01, rel=0.15)
    assert motion_noise(track[:2]) == 0.0
    # the sigma that brings 2 cm of noise to 1 cm: (2/1)^2 / (2 sqrt(pi)) frames
    assert smoothing_sigma(0.02, 0.01, 1.0, 30.0) == pytest.approx(4 / 3.5449 / 30, rel=1e-3)
    assert smoothing_sigma(0.02, 0.01, 0.01, 30.0) == 0.01  # at most `most`
    assert smoothing_sigma(0.0, 0.01, 0.1, 30.0) == 0.0


def test_guard_zero_trusts_each_frame():
    """Exact motion: a palm that touches for one frame while sliding at 1.5 m/s touches; with
    the full guards (a noisy fit) the speed gate and the minimum duration drop it. The
    hysteresis band holds at any guard (2.5 cm inside a contact stays in it)."""
    d = np.array([0.05, 0.05, 0.01, 0.05, 0.05, 0.01, 0.01, 0.025, 0.01, 0.05])[:, None]
    speed = np.full_like(d, 1.5)
    speed[5:9] = 0.1
    exact = contact_flags(d, speed, 30.0, guard=0.0)[:, 0]
    assert exact.tolist() == [0, 0, 1, 0, 0, 1, 1, 1, 1, 0]
    guarded = contact_flags(d, speed, 30.0, guard=1.0)[:, 0]
    assert guarded.tolist() == [0, 0, 0, 0, 0, 1, 1, 1, 1, 0]
    with pytest.raises(ValueError, match="guard"):
        contact_flags(d, speed, 30.0, guard=1.5)


def test_walking_is_told_from_sitting_down():
    fps = 30.0
    t = np.arange(0, 6, 1 / fps)
    x = np.interp(t, [0, 2, 2.5], [0, 2.4, 2.6])  # walk 1.2 m/s, slow to a stop
    z = np.interp(t, [3.5, 4.3], [0, 0.3])  # sitting down moves the hips back 0.3 m
    w = walking(np.stack([x, np.zeros_like(t), z], 1), fps)
    assert w[(t > 0.2) & (t < 2.0)].all()
    assert not w[t > 2.8].any()


def test_labels_from_synthetic_contacts():
    fps, t = 10.0, 100
    pelvis = np.zeros((t, 3))
    pelvis[:30, 2] = np.arange(30) * 0.12  # walking in at 1.2 m/s
    pelvis[30:, 2] = pelvis[29, 2]
    active = np.zeros((t, 5), bool)
    active[45:90, 0] = True  # seated 4.5-9 s
    feet = np.zeros((t, 2))
    li, ri = CONTACT_NAMES.index("left_hand"), CONTACT_NAMES.index("right_hand")

    def label(**kw) -> np.ndarray:
        return interaction_labels(active, pelvis, feet, fps, **kw)

    lab = label()
    assert set(lab[:28]) == {0} and set(lab[32:]) == {4}  # no hand contact
    active[40:50, ri] = True
    assert set(label()[32:]) == {1}
    active[40:50, li] = True
    assert set(label()[32:]) == {3}
    # the left hand lies on the lap: it is not holding on to the chair
    lap = np.zeros((t, 2), bool)
    lap[:, 0] = True
    assert set(label(hand_on_lap=lap)[32:]) == {1}
    # ... unless the torso leans onto it while sitting down
    assert set(label(hand_on_lap=lap, lean=np.full(t, np.deg2rad(10)))[32:]) == {3}
    # a left palm that brushed the armrest while turning, a second before the pelvis landed
    # (and let go 0.9 s before), is no support; on the seat until 0.5 s before landing (where
    # a thigh lands), or still on it 0.2 s before, it is
    active[40:50, li] = False
    active[32:36, li] = True
    assert set(label()[32:]) == {1}
    active[32:40, li] = True
    assert set(label()[32:]) == {3}
    active[32:43, li] = True
    assert set(label()[32:]) == {3}
    active[:, [li, ri]] = False
    feet[60:80, 1] = 0.1  # the right foot crossed over the left: free interaction
    assert set(label()[32:]) == {5}
    feet[60:80, 0] = 0.1  # both feet up together: not crossed
    assert set(label()[32:]) == {4}
    assert set(interaction_labels(np.zeros((t, 5), bool), pelvis, feet, fps)) == {0}
    assert set(label()).issubset(INTERACTION_LABELS)


def test_palm_down_follows_the_hand():
    """The palm's facing from the pose: SMPL's rest pose holds the palms down; turning the
    left hand a quarter about the forearm (the world x axis at rest) faces it sideways, a
    body upside down faces both palms up. Checked against where the posed mesh's palm lies."""
    t = 3
    pose = np.zeros((t, 69))
    j = JOINT_INDEX["left_hand"] - 1  # body_pose has no pelvis
    pose[1, 3 * j] = np.pi / 2
    orient = np.zeros((t, 3))
    orient[2] = [0.0, 0.0, np.pi]
    p = BodyParams(orient, pose, np.zeros((t, 3)), np.zeros(10))
    down = palm_down(p)
    assert down.shape == (t, 2)
    np.testing.assert_allclose(down[0], [1, 1], atol=1e-6)
    np.testing.assert_allclose(down[1], [0, 1], atol=1e-6)
    np.testing.assert_allclose(down[2], [-1, -1], atol=1e-6)
    # the mesh agrees: the left palm's vertices (the detector's contact set) lie below the
    # hand joint at rest and towards -z (R_x(90 deg) applied to -y) when the hand turns
    model = cached_model("couch-body-coarse")
    with torch.no_grad():
        out = model(betas=torch.zeros(1, 10), transl=torch.zeros(2, 3, dtype=model.dtype),
                    global_orient=torch.as_tensor(orient[:2], dtype=model.dtype),
                    body_pose=torch.as_tensor(pose[:2], dtype=model.dtype))
    palm = out.vertices[:, np.asarray(model.contact_vertices["left_hand"])].numpy().mean(1)
    off = (palm - out.joints[:, JOINT_INDEX["left_hand"]].numpy())[:, 1:]  # (2, y z)
    off /= np.linalg.norm(off, axis=1, keepdims=True)
    assert off[0] @ [-1, 0] > 0.8 and off[1] @ [0, -1] > 0.8  # (30 deg to the thumb side)


# ----------------------------------------------------------------------- bad input


def test_bad_inputs_raise_clear_errors():
    model = cached_model("couch-body-coarse")
    p = BodyParams(np.zeros((3, 3)), np.zeros((3, 69)), np.zeros((3, 3)), np.zeros(10))
    v, f = _box((-0.3, 0, -0.3), (0.3, 0.45, 0.3))
    with pytest.raises(ValueError, match="non-empty"):
        detect_contacts(p, model, np.zeros((0, 3)), np.zeros((0, 3), int), fps=30.0)
    with pytest.raises(ValueError, match="faces must be a non-empty"):
        detect_contacts(p, model, v, np.zeros((0, 3), int), fps=30.0)
    with pytest.raises(ValueError, match="must index the 8 vertices"):
        ChairSurface(v, f + 5)
    with pytest.raises(ValueError, match="without chair_faces"):
        detect_contacts(p, model, v, fps=30.0)
    with pytest.raises(ValueError, match="fps"):
        detect_contacts(p, model, v, f, fps=0.0)
    with pytest.raises(TypeError, match="BodyParams"):
        detect_contacts({"transl": np.zeros((3, 3))}, model, v, f, fps=30.0)
    with pytest.raises(ValueError, match="frame counts differ"):
        BodyParams(np.zeros((3, 3)), np.zeros((4, 69)), np.zeros((3, 3)), np.zeros(10))
    with pytest.raises(ValueError, match="one T"):
        interaction_labels(np.zeros((5, 5), bool), np.zeros((6, 3)), np.zeros((5, 2)), 30.0)
    with pytest.raises(ValueError, match=r"both be \(T,K\)"):
        contact_flags(np.zeros((5, 2)), np.zeros((6, 2)), 30.0)
    with pytest.raises(ValueError, match="hysteresis"):
        ContactConfig(enter_distance=0.05, leave_distance=0.02)
    with pytest.raises(ValueError, match="palm_down"):
        ContactConfig(palm_down=1.5)


def test_standing_on_a_box_is_no_chair_contact_but_feet_on_the_floor():
    """A standing body in its rest pose: the feet are on the floor, nothing touches a box
    (a chair) a metre away; a box under the hands makes hand contacts."""
    model = cached_model("couch-body-coarse")
    t = 20
    p = BodyParams(np.zeros((t, 3)), np.zeros((t, 69)), np.zeros((t, 3)), np.zeros(10))
    from couch.fitting.contacts import _pose  # the posed vertices, to place the boxes

    verts, _ = _pose(model, p, np.arange(model.num_vertices))
    floor = verts[0, :, 1].min()
    far = _box((2, floor, 2), (2.5, floor + 0.45, 2.5))
    c = detect_contacts(p, model, *far, fps=30.0, floor_height=floor)
    assert not c.active.any() and np.isnan(c.points).all()
    assert c.floor_active.all()
    assert np.allclose(c.floor_points[..., 1], floor)
    assert set(c.labels) == {0} and c.labels.dtype == np.int8
    assert c.points.dtype == np.float32 and c.points.shape == (t, 5, 3)
    hand = verts[0, model.contact_vertices["right_hand"]]
    under = _box((hand[:, 0].min() - 0.05, floor, hand[:, 2].min() - 0.05),
                 (hand[:, 0].max() + 0.05, hand[:, 1].min() - 0.005, hand[:, 2].max() + 0.05))
    c = detect_contacts(p, model, *under, fps=30.0, floor_height=floor)
    ri = CONTACT_NAMES.index("right_hand")
    assert c.active[:, ri].all()
    assert np.allclose(c.points[:, ri, 1], hand[:, 1].min() - 0.005, atol=1e-3)
    # the same box as a registered ChairModel (its own frame + pose), moved by the pose
    pose = np.eye(4)
    pose[:3, 3] = [0.5, 0.0, -0.2]
    registered = ChairModel(under[0] - pose[:3, 3], under[1], pose)
    c2 = detect_contacts(p, model, registered, fps=30.0, floor_height=floor)
    assert np.array_equal(c2.active, c.active)
    assert np.allclose(c2.points, c.points, atol=1e-5, equal_nan=True)


def test_floor_point_of_a_flat_foot_does_not_jump_between_heel_and_toes():
    """A standing body rocking 2° forward and back: the lowest sole vertex swaps between heel
    and toes, the floor contact point (the sole's patch centre) stays near the middle."""
    model = cached_model("couch-body-coarse")
    from couch.fitting.contacts import _pose

    t = 40  # one slow rock at 30 fps: feet under 0.2 m/s, on the floor throughout
    orient = np.zeros((t, 3))
    orient[:, 0] = np.deg2rad(2.0) * np.sin(2 * np.pi * np.arange(t) / t)
    p = BodyParams(orient, np.zeros((t, 69)), np.zeros((t, 3)), np.zeros(10))
    verts, _ = _pose(model, p, np.arange(model.num_vertices))
    floor = verts[:, :, 1].min()
    far = _box((2, floor, 2), (2.5, floor + 0.45, 2.5))
    c = detect_contacts(p, model, *far, fps=30.0, floor_height=floor)
    assert c.floor_active.all()
    for k, name in enumerate(FEET):
        sole = verts[:, model.contact_vertices[name]]  # (T,n,3)
        middle = sole.mean(1)  # the foot itself moves ±3 cm as the body rocks
        lowest = sole[np.arange(t), sole[..., 1].argmin(1)] - middle
        # the case this is about: the lowest vertex alone moves along the foot
        assert np.ptp(lowest[:, 2]) > 0.1
        pts = c.floor_points[:, k] - middle
        assert np.ptp(pts[:, 2]) < 0.03 and np.ptp(pts[:, 0]) < 0.03
        half = np.ptp(sole[0, :, 2]) / 2
        assert np.abs(pts[:, 2]).max() < 0.5 * half


# ----------------------------------------------------------------------- accuracy


@pytest.fixture(scope="module")
def motions(tmp_path_factory):
    out = []
    for interaction, chair, seed in CASES:
        root = tmp_path_factory.mktemp(f"motion_{interaction}_{chair}_{seed}")
        simulate_motion_dataset(root, 1, seed=seed, duration=10.0, fps=FPS,
                                interaction=interaction, chair=chair, progress=False)
        out.append((f"{interaction}/{chair or 'any'}/{seed}", read_processed(
            root / "motion_00000.h5")))
    return out


def _prf(pred: np.ndarray, true: np.ndarray) -> tuple[float, float, float, np.ndarray]:
    """Precision, recall, F1 of (N,) flags; (1, 1, 1) when neither has a positive."""
    tp, fp, fn = (pred & true).sum(), (pred & ~true).sum(), (~pred & true).sum()
    if tp + fp + fn == 0:
        return 1.0, 1.0, 1.0, np.array([tp, fp, fn])
    return (tp / max(tp + fp, 1), tp / max(tp + fn, 1), 2 * tp / (2 * tp + fp + fn),
            np.array([tp, fp, fn]))


def _evaluate(motions, noisy: bool) -> dict:
    model = cached_model("couch-body-coarse")
    pred, true, errs, acc, frames = [], [], [], {}, 0
    start = time.perf_counter()
    for i, (name, truth) in enumerate(motions):
        params = BodyParams.from_processed(truth)
        if noisy:
            params = imu_like_init(params, seed=100 + i, deg=3.0, cm=1.0)
        chair = apply_transform(truth.object_pose, truth.object_vertices)
        c = detect_contacts(params, model, chair, truth.object_faces, fps=truth.fps)
        pred.append(c.active)
        true.append(truth.contact_active)
        both = c.active & truth.contact_active
        errs.append(np.where(both, np.linalg.norm(c.points - truth.contact_points, axis=-1),
                             np.nan))
        acc[name] = float(np.mean(c.labels == truth.interaction))
        frames += len(c.labels)
    seconds = time.perf_counter() - start
    pred_a, true_a, err = np.concatenate(pred), np.concatenate(true), np.concatenate(errs)
    parts = {n: _prf(pred_a[:, k], true_a[:, k]) for k, n in enumerate(CONTACT_NAMES)}
    point = {n: float(np.nanmedian(err[:, k])) if np.isfinite(err[:, k]).any() else np.nan
             for k, n in enumerate(CONTACT_NAMES)}
    label_acc = sum(acc[n] * 1.0 for n in acc) / len(acc)
    print(f"\n[{'IMU-like 3 deg / 1 cm' if noisy else 'truth motion'}] {len(motions)} "
          f"sequences, {frames} frames at {FPS:g} fps, detection {seconds:.1f} s "
          f"({frames / seconds:.0f} frames/s)")
    for n, (p, r, f1, counts) in parts.items():
        print(f"  {n:<10} P {p:.3f} R {r:.3f} F1 {f1:.3f} (tp/fp/fn {counts.tolist()}); "
              f"median point error {100 * point[n]:.2f} cm")
    print(f"  label accuracy {label_acc:.3f}; per sequence: "
          + ", ".join(f"{n} {a:.2f}" for n, a in acc.items()))
    return {"parts": parts, "point": point, "labels": label_acc, "per_sequence": acc}


@pytest.mark.parametrize("noisy", [False, True], ids=["truth_motion", "imu_like"])
def test_accuracy_against_simulator_truth(motions, noisy):
    """Pelvis contact F1 >= 0.95 and label accuracy >= 0.9 in every sequence (issue 8); the
    hands reach 0.95 on the truth motion and are guarded against regressions on the IMU-like
    one, where they miss it (module docstring)."""
    r = _evaluate(motions, noisy)
    assert r["parts"]["pelvis"][2] >= 0.95
    assert r["labels"] >= 0.9
    # both_hands/sofa/2 read 0.35 before the palm-down rule: its seat palms touch the thighs
    assert min(r["per_sequence"].values()) >= 0.9, r["per_sequence"]
    for hand in ("left_hand", "right_hand"):
        assert r["parts"][hand][2] >= (0.95 if not noisy else 0.65)
        # from the truth's single closest point; ours is a 2 cm patch's centre (docstring)
        assert r["point"][hand] <= (0.015 if not noisy else 0.025)
