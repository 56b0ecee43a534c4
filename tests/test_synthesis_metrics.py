"""couch.synthesis.metrics: closed-form cases of the COUCH Sec. 5 metrics, foot sliding and
penetration (a real box's signed distance grid)."""

from __future__ import annotations

import itertools
import math
import re

import numpy as np
import pytest
import trimesh

from couch.augment import SignedDistanceGrid
from couch.geometry import make_transform
from couch.synthesis.metrics import (
    ace,
    apd,
    closest_hand_distances,
    closest_hand_offsets,
    contact_apd,
    contact_intervals,
    contact_precision,
    foot_sliding,
    format_intervals,
    format_table,
    penetration,
    pose_feature_apd,
)


@pytest.fixture(scope="module")
def box_sdf() -> SignedDistanceGrid:
    """A 1 m cube centred on the chair frame's origin: top face at y = 0.5."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    return SignedDistanceGrid.from_mesh(box.vertices, box.faces, spacing=0.05)


def _line(start, stop, t: int) -> np.ndarray:
    return np.linspace(np.asarray(start, float), np.asarray(stop, float), t)


# --- contact accuracy ----------------------------------------------------------------------------

def test_hand_through_contact_gives_zero():
    t = 21
    contacts = np.array([[[0.0, 0.5, 0.0], [0.3, 0.6, 0.1]]])
    hands = np.stack([_line([-1, 0.5, 0], [1, 0.5, 0], t),  # passes (0, 0.5, 0) at frame 10
                      _line([0.3, 0.6, 0.1], [0.3, 0.6, 0.1], t)], axis=1)[None]
    d = closest_hand_distances(hands, contacts)
    assert d.shape == (1, 2)
    np.testing.assert_allclose(d, 0.0, atol=1e-12)
    assert ace(d) == pytest.approx(0.0, abs=1e-12)
    assert contact_precision(d) == {0.03: 1.0, 0.05: 1.0, 0.07: 1.0, 0.09: 1.0}


def test_closest_offsets_say_where_and_when():
    t = 21
    contacts = np.array([[[0.0, 0.5, 0.0], [0.3, 0.6, 0.1]], [[np.nan] * 3, [0.0, 0.0, 0.0]]])
    hands = np.zeros((2, t, 2, 3))
    hands[0, :, 0] = _line([-1, 0.52, 0], [1, 0.52, 0], t)  # 2 cm above it at frame 10
    hands[0, :, 1] = _line([0.3, 0.6, 0.5], [0.3, 0.6, 0.2], t)  # coming, 10 cm short at the end
    hands[1, :, 1] = 1.0
    valid = np.ones((2, t), bool)
    valid[1] = False  # sequence 1 is all padding
    off, frame = closest_hand_offsets(hands, contacts, valid)
    np.testing.assert_allclose(off[0], [[0.0, 0.02, 0.0], [0.0, 0.0, 0.1]], atol=1e-12)
    assert frame.tolist() == [[10, t - 1], [-1, -1]]
    assert np.isnan(off[1]).all()
    np.testing.assert_allclose(np.linalg.norm(off, axis=-1),
                               closest_hand_distances(hands, contacts, valid), equal_nan=True)


def test_constant_offset_and_nan_contact():
    rng = np.random.default_rng(0)
    n, t = 4, 30
    contacts = rng.uniform(-1, 1, (n, 2, 3))
    direction = rng.normal(size=(n, t, 2, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    hands = contacts[:, None] + 0.049 * direction  # every frame exactly 4.9 cm away
    hands[:, ::2] += 0.5  # half the frames much further away
    contacts[1, 0] = np.nan  # no contact asked of sequence 1's left hand
    d = closest_hand_distances(hands, contacts)
    assert np.isnan(d[1, 0])
    finite = np.delete(d.ravel(), 2)
    np.testing.assert_allclose(finite, 0.049, atol=1e-9)
    assert ace(d) == pytest.approx(0.049)
    ap = contact_precision(d)
    assert list(ap) == [0.03, 0.05, 0.07, 0.09]
    assert ap[0.03] == 0.0
    assert ap[0.05] == 1.0
    assert ap[0.07] == 1.0
    assert contact_precision(d, thresholds=(0.04,)) == {0.04: 0.0}


def test_closest_distance_valid_mask_and_mixed_precision():
    t = 10
    contacts = np.zeros((2, 2, 3))
    hands = np.full((2, t, 2, 3), [0.2, 0.0, 0.0])
    hands[0, 3, 0] = [0.0, 0.0, 0.0]  # touches at frame 3 ...
    valid = np.ones((2, t), dtype=bool)
    valid[0, 3] = False  # ... which is padding
    hands[1, 5, 1] = [0.0, 0.06, 0.0]  # the right hand of sequence 1 comes within 6 cm
    d = closest_hand_distances(hands, contacts, valid=valid)
    np.testing.assert_allclose(d, [[0.2, 0.2], [0.2, 0.06]])
    np.testing.assert_allclose(closest_hand_distances(hands, contacts)[0, 0], 0.0)
    ap = contact_precision(d)
    assert ap[0.05] == 0.0
    assert ap[0.07] == 0.25
    # a sequence without valid frames reads NaN and is skipped
    d = closest_hand_distances(hands, contacts, valid=np.zeros((2, t), bool))
    assert np.isnan(d).all()
    assert math.isnan(ace(d))
    assert all(math.isnan(v) for v in contact_precision(d).values())


def test_closest_distances_match_a_loop():
    rng = np.random.default_rng(1)
    hands = rng.normal(size=(3, 7, 2, 3))
    contacts = rng.normal(size=(3, 2, 3))
    d = closest_hand_distances(hands, contacts)
    for i, k in itertools.product(range(3), range(2)):
        expected = min(np.linalg.norm(hands[i, f, k] - contacts[i, k]) for f in range(7))
        assert d[i, k] == pytest.approx(expected)


@pytest.mark.parametrize(("hands_shape", "contacts_shape", "match"), [
    ((2, 5, 3, 3), (2, 2, 3), r"hands must have shape \(N, T, 2, 3\), got \(2, 5, 3, 3\)"),
    ((5, 2, 3), (2, 2, 3), r"hands .*got \(5, 2, 3\)"),
    ((2, 5, 2, 3), (3, 2, 3), r"contacts .*got \(3, 2, 3\)"),
])
def test_closest_distances_shape_errors(hands_shape, contacts_shape, match):
    with pytest.raises(ValueError, match=match):
        closest_hand_distances(np.zeros(hands_shape), np.zeros(contacts_shape))


def test_valid_mask_shape_error():
    with pytest.raises(ValueError, match=r"valid .*got \(5, 2\)"):
        closest_hand_distances(np.zeros((2, 5, 2, 3)), np.zeros((2, 2, 3)),
                               valid=np.ones((5, 2), bool))


# --- diversity -----------------------------------------------------------------------------------

def test_apd_closed_forms():
    assert apd(np.array([[0.0, 0.0], [3.0, 4.0]])) == pytest.approx(5.0)
    assert apd(np.array([[0.0], [1.0], [3.0]])) == pytest.approx(2.0)  # mean(1, 3, 2)
    assert apd(np.zeros((4, 6))) == 0.0


def test_apd_is_the_ordered_pair_mean():
    x = np.random.default_rng(2).normal(size=(6, 5))
    s = len(x)
    brute = sum(np.linalg.norm(x[i] - x[j]) for i in range(s) for j in range(s) if i != j)
    assert apd(x) == pytest.approx(brute / (s * (s - 1)))


@pytest.mark.parametrize("shape", [(1, 3), (0, 3), (5,), (2, 3, 4)])
def test_apd_rejects_bad_shapes(shape):
    with pytest.raises(ValueError, match=re.escape(str(shape))):
        apd(np.zeros(shape))


def test_contact_apd():
    c = np.full((3, 4, 2, 3), np.nan)
    # chair 0: two complete samples 0.1 m apart (the left hand moves), one with a dropped hand
    c[0, 0] = [[0, 0, 0], [1, 0, 0]]
    c[0, 1] = [[0.1, 0, 0], [1, 0, 0]]
    c[0, 2] = [[5, 5, 5], [np.nan, np.nan, np.nan]]
    # chair 1: three complete samples, 6-vectors at 0, 0.3 and 0.4 along one axis -> APD 0.2667
    c[1, :3] = 0.0
    c[1, 1, 1, 2] = 0.3
    c[1, 2, 1, 2] = 0.4
    # chair 2: only one complete sample -> ignored
    c[2, 0] = 1.0
    expected = np.mean([0.1, (0.3 + 0.4 + 0.1) / 3])
    assert contact_apd(c) == pytest.approx(expected)
    assert math.isnan(contact_apd(c[2:]))
    with pytest.raises(ValueError, match=r"\(L, N, 2, 3\), got \(4, 2, 3\)"):
        contact_apd(c[0])


def test_pose_feature_apd_is_root_relative():
    rng = np.random.default_rng(3)
    base = rng.normal(size=(1, 5, 24, 3))
    moved = base + rng.normal(size=(1, 5, 1, 3))  # same pose, root translated per frame
    assert pose_feature_apd(np.concatenate([base, moved])) == pytest.approx(0.0, abs=1e-12)
    other = base.copy()
    other[0, :, 5] += [0.0, 0.1, 0.0]  # one joint 10 cm higher in each of the 5 frames
    assert pose_feature_apd(np.concatenate([base, other])) == pytest.approx(0.1 * math.sqrt(5))
    with pytest.raises(ValueError, match=r"\(S, T, J, 3\)"):
        pose_feature_apd(np.zeros((5, 24, 3)))


# --- foot sliding --------------------------------------------------------------------------------

def _feet_walk(height: float, step: float, t: int = 30) -> np.ndarray:
    joints = np.zeros((t, 24, 3))
    joints[:, :, 1] = 1.0  # the rest of the body well above the floor
    joints[:, [7, 8, 10, 11], 1] = height
    joints[:, [7, 8, 10, 11], 0] = step * np.arange(t)[:, None]
    return joints


def test_foot_sliding_planted_foot_moving():
    assert foot_sliding(_feet_walk(0.0, 0.01), fps=30) == pytest.approx(0.01)
    # at half the ankle threshold the toes (H = 4 cm) are free and the ankles weigh 2 - sqrt 2
    half = foot_sliding(_feet_walk(0.04, 0.01), fps=30)
    assert half == pytest.approx(0.01 * (2 - math.sqrt(2)) / 2)


def test_foot_sliding_lifted_or_stationary_feet():
    assert foot_sliding(_feet_walk(0.3, 0.01), fps=30) == 0.0
    assert foot_sliding(_feet_walk(0.0, 0.0), fps=30) == 0.0
    vertical = _feet_walk(0.0, 0.0)
    vertical[:, [7, 8, 10, 11], 1] = np.linspace(0, 0.02, 30)[:, None]  # lifting only
    assert foot_sliding(vertical, fps=30) == 0.0


def test_foot_sliding_errors():
    with pytest.raises(ValueError, match=r"\(T, J, 3\), got \(24, 3\)"):
        foot_sliding(np.zeros((24, 3)), fps=30)
    with pytest.raises(ValueError, match="at least 2 frames"):
        foot_sliding(np.zeros((1, 24, 3)), fps=30)
    with pytest.raises(ValueError, match="fps"):
        foot_sliding(np.zeros((3, 24, 3)), fps=0)
    with pytest.raises(ValueError, match="equal length"):
        foot_sliding(np.zeros((3, 24, 3)), fps=30, feet=(7, 8), heights=(0.08,))


# --- penetration ---------------------------------------------------------------------------------

def test_penetration_inside_top_face(box_sdf):
    inside = np.array([[0.0, 0.4, 0.0], [0.1, 0.45, -0.1], [2.0, 2.0, 2.0]])  # 10 cm, 5 cm, out
    outside = np.array([[0.0, 0.6, 0.0], [0.0, 1.5, 0.0], [0.9, 0.0, 0.0]])
    single = penetration(inside[None], box_sdf)
    assert single["max_depth_m"] == pytest.approx(0.10, abs=0.01)
    assert single["mean_depth_m"] == pytest.approx(0.10, abs=0.01)
    assert single["frames_over_pct"] == 100.0
    assert single["mean_vertex_depth_m"] == pytest.approx(0.075, abs=0.01)
    clear = penetration(outside[None], box_sdf)
    assert clear == {"mean_depth_m": 0.0, "frames_over_pct": 0.0, "max_depth_m": 0.0,
                     "mean_vertex_depth_m": 0.0}
    both = penetration(np.stack([inside, outside]), box_sdf)
    assert both["max_depth_m"] == pytest.approx(0.10, abs=0.01)
    assert both["mean_depth_m"] == pytest.approx(0.05, abs=0.005)
    assert both["frames_over_pct"] == 50.0
    # 10 cm is not over a 15 cm threshold
    assert penetration(inside[None], box_sdf, depth_threshold=0.15)["frames_over_pct"] == 0.0


def test_penetration_world_from_chair(box_sdf):
    world_from_chair = make_transform(np.eye(3), [2.0, 0.0, -1.0])
    verts = np.array([[[2.0, 0.4, -1.0], [2.0, 0.7, -1.0]]])  # 10 cm inside the moved box's top
    moved = penetration(verts, box_sdf, world_from_chair=world_from_chair)
    assert moved["max_depth_m"] == pytest.approx(0.10, abs=0.01)
    assert moved["frames_over_pct"] == 100.0
    assert penetration(verts, box_sdf)["max_depth_m"] == 0.0  # the unmoved box is far away
    with pytest.raises(ValueError, match=r"world_from_chair .*got \(3, 4\)"):
        penetration(verts, box_sdf, world_from_chair=np.eye(4)[:3])


def test_penetration_chunks_agree(box_sdf, monkeypatch):
    rng = np.random.default_rng(4)
    verts = rng.uniform(-0.7, 0.7, (9, 50, 3))
    whole = penetration(verts, box_sdf)
    monkeypatch.setattr("couch.synthesis.metrics._QUERY_CHUNK", 120)  # 2 frames per query
    assert penetration(verts, box_sdf) == pytest.approx(whole)


def test_penetration_shape_error(box_sdf):
    with pytest.raises(ValueError, match=r"vertices must have shape \(T, V, 3\), got \(10, 3\)"):
        penetration(np.zeros((10, 3)), box_sdf)


# --- table ---------------------------------------------------------------------------------------

def test_format_table():
    rows = {
        "COUCH": {"ACE (m)": 0.0231, "AP@5cm": 2.3149, "APD": 12.345},
        "baseline": {"ACE (m)": float("nan"), "APD": 1234.4, "penetration": 0.0},
    }
    table = format_table(rows)
    lines = table.splitlines()
    assert len(lines) == 4  # header, separator, one line per method
    assert lines[0] == "| method | ACE (m) | AP@5cm | APD | penetration |"
    assert set(lines[1]) <= set("|-: ")
    assert lines[1].count("|") == 6
    assert lines[2] == "| COUCH | 0.0231 | 2.31 | 12.3 | – |"
    assert lines[3] == "| baseline | – | – | 1234 | 0 |"
    picked = format_table(rows, columns=["APD", "ACE (m)"]).splitlines()
    assert picked[0] == "| method | APD | ACE (m) |"
    assert picked[2] == "| COUCH | 12.3 | 0.0231 |"
    assert format_table({"x": {"v": 9.996}}).splitlines()[2] == "| x | 10.0 |"
    assert format_table({"x": {"v": -0.04567}}).splitlines()[2] == "| x | -0.0457 |"



def test_contact_intervals_cover_the_truth_and_shrink_with_trials():
    """Bootstrap intervals of ACE and AP@5 over trials: 95 % intervals hold the population
    value they were drawn from in about 95 % of repeated draws, they narrow about as
    1/sqrt(trials), and a paired reduction of a method against itself is exactly 0 on every
    resample."""
    rng = np.random.default_rng(3)
    true_ace = 0.08  # exponential closest distances: mean 8 cm, P(d <= 5 cm) = 1 - exp(-5/8)
    true_ap = 100 * (1 - math.exp(-5 / 8))

    def draw(n: int) -> np.ndarray:
        d = rng.exponential(true_ace, (n, 2))
        d[::3, 1] = np.nan  # one-hand trials
        return d

    hits = np.zeros(2)
    repeats = 60
    for seed in range(repeats):
        out = contact_intervals({"a": draw(100)}, resamples=400, seed=seed)["a"]
        hits += [out["ACE cm"][1] < 100 * true_ace < out["ACE cm"][2],
                 out["AP@5 %"][1] < true_ap < out["AP@5 %"][2]]
    assert np.all(hits / repeats >= 0.85), hits  # expected ~0.95 each
    widths = []
    for n in (100, 1600):
        d = draw(n)
        out = contact_intervals({"a": d, "b": d.copy(), "c": d * 2}, "b", seed=1)
        value, low, high = out["a"]["ACE cm"]
        assert value == pytest.approx(100 * ace(d)) and low < value < high
        assert out["a"]["ACE reduction %"] == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
        assert out["c"]["ACE reduction %"] == pytest.approx((-100.0, -100.0, -100.0))
        assert "ACE reduction %" not in out["b"]
        widths.append(high - low)
    assert 2.5 < widths[0] / widths[1] < 6  # 16x the trials: about 4x narrower
    text = format_intervals(out, 1600)
    assert "over the 1600 trials" in text and "- a: ACE " in text and "ACE reduction 0 " in text


def test_contact_intervals_bad_input():
    with pytest.raises(ValueError, match="different trial counts"):
        contact_intervals({"a": np.ones((4, 2)), "b": np.ones((5, 2))})
    with pytest.raises(ValueError, match="reference 'x'"):
        contact_intervals({"a": np.ones((4, 2))}, "x")
    one = contact_intervals({"a": np.full((1, 2), 0.02)})["a"]["ACE cm"]
    assert one[0] == pytest.approx(2.0) and math.isnan(one[1]) and math.isnan(one[2])
