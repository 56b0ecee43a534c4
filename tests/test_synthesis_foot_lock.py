"""Foot locking (``couch.synthesis.foot_lock``): planted feet held by leg IK, checked by
forward kinematics of the rest bones on a body that slides across the floor."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from couch.body import JOINT_INDEX, PARENTS, Skeleton, load_body_model
from couch.geometry import apply_transform
from couch.rotations import matrix_to_6d, sixd_to_matrix
from couch.synthesis.controller import yaw_transform
from couch.synthesis.foot_lock import LEGS, FootLockConfig, lock_feet, planted_feet
from couch.synthesis.metrics import foot_sliding

T, FPS = 40, 30.0
ANKLES = [leg[2] for leg in LEGS]
TOES = [JOINT_INDEX["left_foot"], JOINT_INDEX["right_foot"]]


@pytest.fixture(scope="module")
def rest():
    model = load_body_model("couch-body")
    return model.rest_joints(torch.zeros(1, 10, dtype=model.dtype))[0].double().numpy()


def _sliding_body(rest, z):
    """A standing body with bent knees whose root moves along +z as ``z`` (B,T) (m, one row
    per character) and turns slowly, feet on the floor: (root (B,T,4,4), jpos (B,T,22,3),
    jrot (B,T,22,6)), root frame."""
    local = np.tile(np.eye(3), (22, 1, 1))
    for side in ("left", "right"):
        local[JOINT_INDEX[f"{side}_hip"]] = Rotation.from_euler("x", -25, degrees=True).as_matrix()
        local[JOINT_INDEX[f"{side}_knee"]] = Rotation.from_euler("x", 45, degrees=True).as_matrix()
    glob = np.empty_like(local)
    glob[0] = local[0]
    for j in range(1, 22):
        glob[j] = glob[PARENTS[j]] @ local[j]
    pos = Skeleton(rest).forward(np.zeros((1, 3)), {j: glob[None, j] for j in range(22)},
                                 list(range(22)))
    jpos = np.stack([pos[j][0] for j in range(22)])
    jpos[:, 1] += 0.07 - jpos[ANKLES, 1].min()  # ankles 7 cm up, as standing
    z = np.atleast_2d(z)
    b = len(z)
    t = np.arange(T) / FPS
    heading = np.broadcast_to(0.15 * t, z.shape)  # a slow turn: the toes would swing too
    root = yaw_transform(np.zeros_like(z).ravel(), z.ravel(), heading.ravel()).reshape(b, T, 4, 4)
    return (root, np.broadcast_to(jpos, (b, T, 22, 3)).copy(),
            np.broadcast_to(matrix_to_6d(glob), (b, T, 22, 6)).copy())


def _world(root, jpos, idx):
    return apply_transform(root, jpos[:, :, idx])


def test_planted_feet_are_low_and_slow():
    ankles = np.zeros((1, 6, 1, 3))
    ankles[0, :, 0, 2] = np.arange(6) * 0.01  # 0.3 m/s
    ankles[0, 3:, 0, 1] = 0.2  # lifted from frame 3
    assert planted_feet(ankles, FPS)[0, :, 0].tolist() == [True] * 3 + [False] * 3
    fast = ankles.copy()
    fast[0, :, 0, 1] = 0.0
    fast[0, :, 0, 2] = np.arange(6) * 0.1  # 3 m/s: a swing
    assert not planted_feet(fast, FPS).any()
    assert not planted_feet(ankles[:, :1], FPS).any()  # one frame: no speed, no plant
    with pytest.raises(ValueError, match=r"\(B,T,F,3\)"):
        planted_feet(np.zeros((6, 2, 3)), FPS)


def test_planted_feet_are_held_by_the_legs(rest):
    """A body that sways 2 cm back and forth (its feet shuffle) keeps its feet still; one that
    moves at 3 m/s is not planted."""
    cfg = FootLockConfig()
    t = np.arange(T) / FPS
    root, jpos, jrot = _sliding_body(rest, np.stack([0.02 * np.sin(2 * np.pi * 1.5 * t),
                                                     3.0 * t]))
    new_pos, new_rot, held = lock_feet(root, jpos, jrot, rest, FPS, cfg)
    assert held[0].any() and not held[1].any()  # the slow body's feet, not the fast one's
    # the fast character is untouched; nothing above the legs moves for anyone
    np.testing.assert_array_equal(new_pos[1], jpos[1])
    legs = sorted({j for leg in LEGS for j in leg[1:]} | set(TOES))
    others = [j for j in range(22) if j not in legs]
    np.testing.assert_array_equal(new_pos[:, :, others], jpos[:, :, others])
    # positions are the forward kinematics of the new rotations: bone lengths kept
    rot = sixd_to_matrix(new_rot[0])
    fk = Skeleton(rest).forward(new_pos[0, :, 0], {j: rot[:, j] for j in range(22)}, legs)
    for j in legs:
        np.testing.assert_allclose(fk[j], new_pos[0, :, j], atol=1e-9)
    # while held, ankle and toe stay where the plant began (horizontally)
    for f in range(2):
        frames = np.flatnonzero(held[0, :, f])
        first = frames[0]
        run = frames[: np.argmax(np.diff(np.r_[frames, -9]) != 1) + 1]  # the first plant
        for idx in (ANKLES[f], TOES[f]):
            w = _world(root[:1], new_pos[:1], [idx])[0, :, 0]
            np.testing.assert_allclose(w[run][:, [0, 2]], np.broadcast_to(
                w[first, [0, 2]], (len(run), 2)), atol=1e-6)
    before = foot_sliding(_world(root[:1], jpos[:1], list(range(22)))[0], FPS)
    after = foot_sliding(_world(root[:1], new_pos[:1], list(range(22)))[0], FPS)
    assert after < 0.3 * before, (before, after)


@pytest.mark.parametrize(("cfg", "speed"), [(FootLockConfig(max_offset=1.0, max_turn=10.0), 0.8),
                                           (FootLockConfig(), 0.3)], ids=["stretch", "offset"])
def test_a_hold_out_of_reach_is_dragged(rest, cfg, speed):
    """A body that glides on for 1.3 s cannot keep its foot where it was: the leg is never
    stretched past ``max_stretch``, a held foot never lies more than ``max_offset`` from where
    the network has it, and the foot follows."""
    root, jpos, jrot = _sliding_body(rest, speed * np.arange(T) / FPS)
    new_pos, _, held = lock_feet(root, jpos, jrot, rest, FPS, cfg)
    ankles = [leg[2] for leg in LEGS]
    drift = (_world(root, new_pos, ankles) - _world(root, jpos, ankles))[..., [0, 2]]
    assert np.linalg.norm(drift, axis=-1).max() <= cfg.max_offset + 1e-6
    skeleton = Skeleton(rest)
    for f, (hip, knee, ankle) in enumerate(LEGS):
        leg = skeleton.bone_length(hip, knee) + skeleton.bone_length(knee, ankle)
        reach = np.linalg.norm(new_pos[0, :, ankle] - new_pos[0, :, hip], axis=-1)
        assert reach.max() <= cfg.max_stretch * leg + 1e-6
        assert not held[0, :, f].all()  # dragged at least once
        assert held[0, :, f].any()


@pytest.mark.parametrize("speed", [0.1, 0.3, 0.5, 0.9])
def test_a_foot_landing_while_gliding_slides_no_more(rest, speed):
    """Found on the ``ci`` networks (session 55): a foot that lands while still gliding at
    0.1-0.9 m/s counts as planted; holding it and letting it go 5 cm later moved the whole
    glide into the later, lower frames, where sliding weighs more. The leash drags it at the
    network's own step instead: sliding is never higher (in total, and at any frame while an
    ankle is planted) and the lagging offset never exceeds ``max_offset``."""
    cfg = FootLockConfig()
    root, jpos, jrot = _sliding_body(rest, speed * np.arange(T) / FPS)
    root[..., 1, 3] = np.linspace(0.025, -0.06, T)  # ankles from 9.5 cm down to 1 cm
    new_pos, _, held = lock_feet(root, jpos, jrot, rest, FPS, cfg)
    feet = ANKLES + TOES
    before, after = (_world(root, p, feet)[0] for p in (jpos, new_pos))
    assert held[0].any()
    step = [np.linalg.norm(np.diff(w[..., [0, 2]], axis=0), axis=-1) for w in (before, after)]
    plant = planted_feet(before[None, :, :2], FPS, cfg)[0]  # (T, 2) ankles
    for f in range(2):  # the ankles (a toe, turned back to its heading, may differ by microns)
        on = plant[1:, f] & plant[:-1, f]
        assert np.all(step[1][on, f] <= step[0][on, f] + 1e-9), (speed, f)
    whole = [foot_sliding(w, FPS, tuple(range(4)), (0.08, 0.08, 0.04, 0.04))
             for w in (before, after)]
    assert whole[1] <= whole[0] + 1e-9, whole
    lag = np.linalg.norm((after - before)[:, :2, [0, 2]], axis=-1)
    assert lag.max() <= cfg.max_offset + 1e-6
