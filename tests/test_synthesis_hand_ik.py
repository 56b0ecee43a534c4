"""Runtime hand IK (``couch.synthesis.hand_ik``): two-bone arm IK on the controller's root-frame
global rotations, checked by forward kinematics of the rest bones."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from couch.body import PARENTS, load_body_model
from couch.synthesis.hand_ik import ARMS, ArmRig, forward_positions, reach

B = 64


@pytest.fixture(scope="module")
def rig():
    model = load_body_model("couch-body")
    rest = model.rest_joints(torch.zeros(1, 10, dtype=model.dtype))[0].double().numpy()
    template = model.v_template.double().numpy()
    palm = np.stack([template[model.contact_vertices[f"{s}_hand"]].mean(0) - rest[w]
                     for s, (_, _, w) in zip(("left", "right"), ARMS, strict=True)])
    return ArmRig(rest=rest, palm=palm)


def _pose(rng, spread=0.6):
    """(B,3) pelvis and (B,22,3,3) global rotations of a random, bent body."""
    local = Rotation.from_rotvec(rng.normal(0, spread, (B * 22, 3))).as_matrix()
    local = local.reshape(B, 22, 3, 3)
    glob = np.empty_like(local)
    glob[:, 0] = local[:, 0]
    for j in range(1, 22):
        glob[:, j] = glob[:, PARENTS[j]] @ local[:, j]
    return rng.normal(0, 0.1, (B, 3)) + np.array([0, 0.9, 0]), glob


def _palms(pelvis, rot, rig):
    pos = forward_positions(pelvis, rot, rig, tuple(w for _, _, w in ARMS))
    return np.stack([pos[w] + rot[:, w] @ rig.palm[h] for h, (_, _, w) in enumerate(ARMS)], 1)


def test_full_weight_puts_reachable_palms_on_their_goals(rig):
    rng = np.random.default_rng(0)
    pelvis, rot = _pose(rng)
    # reachable goals: the palms of the same body with other shoulder and elbow rotations
    # (the wrists' global rotations, which the IK keeps, unchanged)
    other = rot.copy()
    for s, e, _ in ARMS:
        turn = Rotation.from_rotvec(rng.normal(0, 0.5, (B, 3))).as_matrix()
        other[:, s] = turn @ rot[:, s]
        bend = Rotation.from_rotvec(rng.normal(0, 0.5, (B, 3))).as_matrix()
        other[:, e] = bend @ turn @ rot[:, e]
    goals = _palms(pelvis, other, rig)
    new, moved = reach(pelvis, rot, goals, np.ones((B, 2)), rig)
    # exact, except within the last 0.1 % of full extension, where two_bone_ik clamps
    np.testing.assert_allclose(_palms(pelvis, new, rig), goals, atol=1e-3)
    exact = np.abs(_palms(pelvis, new, rig) - goals).max(-1) < 1e-6
    assert exact.mean() > 0.9
    arm_joints = {j for arm in ARMS for j in arm[:2]}
    for j in range(22):  # only shoulders and elbows turn; wrists keep their orientation
        if j not in arm_joints:
            np.testing.assert_array_equal(new[:, j], rot[:, j])
    eye = np.broadcast_to(np.eye(3), new.shape)
    np.testing.assert_allclose(new @ np.swapaxes(new, -1, -2), eye, atol=1e-9)
    before = forward_positions(pelvis, rot, rig, (20, 21))
    after = forward_positions(pelvis, new, rig, (20, 21))
    for j, delta in moved.items():
        np.testing.assert_allclose(delta, after[j] - before[j], atol=1e-9)


def test_weights_blend_and_zero_leaves_the_arm(rig):
    rng = np.random.default_rng(1)
    pelvis, rot = _pose(rng)
    palms = _palms(pelvis, rot, rig)
    goals = palms + rng.normal(0, 0.05, palms.shape)  # a few cm away: reachable
    weights = np.stack([np.full(B, 0.5), np.zeros(B)], 1)
    new, moved = reach(pelvis, rot, goals, weights, rig)
    out = _palms(pelvis, new, rig)
    # half way for the left hand (where the arm was not already fully stretched)
    half = np.linalg.norm(out[:, 0] - goals[:, 0], axis=-1)
    full = np.linalg.norm(palms[:, 0] - goals[:, 0], axis=-1)
    np.testing.assert_allclose(np.median(half / full), 0.5, atol=1e-6)
    np.testing.assert_array_equal(new[:, [17, 19]], rot[:, [17, 19]])  # right arm untouched
    assert not moved[19].any() and not moved[21].any()


def test_out_of_reach_goal_straightens_the_arm_towards_it(rig):
    rng = np.random.default_rng(2)
    pelvis, rot = _pose(rng)
    pos = forward_positions(pelvis, rot, rig, (16,))
    far = pos[16] + 3.0 * np.array([1.0, 0.0, 0.0])  # 3 m beside the left shoulder
    goals = np.stack([far, far], 1)
    new, _ = reach(pelvis, rot, goals, np.stack([np.ones(B), np.zeros(B)], 1), rig)
    before = np.linalg.norm(_palms(pelvis, rot, rig)[:, 0] - far, axis=-1)
    after = np.linalg.norm(_palms(pelvis, new, rig)[:, 0] - far, axis=-1)
    assert np.all(after < before)
    p = forward_positions(pelvis, new, rig, (20,))
    upper = rig.skeleton.bone_length(16, 18)
    lower = rig.skeleton.bone_length(18, 20)
    np.testing.assert_allclose(np.linalg.norm(p[20] - p[16], axis=-1), 0.999 * (upper + lower),
                               rtol=1e-6)
