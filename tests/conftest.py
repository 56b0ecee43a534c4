"""Shared fixtures: body models are loaded once per test session."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from hypothesis import settings

from couch.body import CONTACT_NAMES, load_body_model, sitting_pose, standing_pose
from couch.geometry import make_transform
from couch.schema import ProcessedSession

# CI explores a fixed set of examples (a red CI must be reproducible); developers get fresh ones.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


@pytest.fixture(scope="session")
def body_model():
    return load_body_model("couch-body")


@pytest.fixture(scope="session")
def coarse_model():
    return load_body_model("couch-body-coarse")


@pytest.fixture(scope="session")
def processed_session(coarse_model) -> ProcessedSession:
    """A small valid session: the coarse body goes from standing to sitting over 40 frames."""
    t = 40
    w = np.linspace(0, 1, t, dtype=np.float32)[:, None]
    pose = (1 - w) * standing_pose() + w * sitting_pose()
    transl = np.zeros((t, 3), dtype=np.float32)
    transl[:, 2] = np.linspace(-1.0, 0.0, t)
    transl[:, 1] = 0.9
    with torch.no_grad():
        joints = coarse_model(body_pose=pose, transl=transl).joints.numpy()
    active = np.zeros((t, len(CONTACT_NAMES)), dtype=bool)
    active[25:, 0] = True
    active[:, 3:] = True
    points = np.full((t, len(CONTACT_NAMES), 3), np.nan, dtype=np.float32)
    points[active] = 0.1
    labels = np.zeros(t, dtype=np.int8)
    labels[25:] = 4
    pose_obj = make_transform(np.eye(3), [0.0, 0.0, 0.3])
    return ProcessedSession(
        session="test_session", fps=30.0, time=np.arange(t) / 30.0 + 12.5,
        betas=np.zeros(10, dtype=np.float32), global_orient=np.zeros((t, 3), np.float32),
        body_pose=pose.astype(np.float32), transl=transl, joints=joints.astype(np.float32),
        object_name="box_chair", object_vertices=np.random.default_rng(0).random((8, 3)),
        object_faces=np.array([[0, 1, 2], [2, 3, 0]], dtype=np.int32), object_pose=pose_obj,
        object_frame_poses=np.repeat(pose_obj[None], t, axis=0), contact_active=active,
        contact_points=points, interaction=labels, quality={"fit_error_mm": np.ones(t)},
    )


@pytest.fixture(scope="session")
def motion_sim(tmp_path_factory):
    """Five simulated motion sequences (sofa and armchair; free, one- and two-hand contacts)."""
    from couch.tools.sim.session import simulate_motion_dataset

    out = tmp_path_factory.mktemp("train_sim")
    simulate_motion_dataset(out, 5, seed=11, progress=False)
    return out


@pytest.fixture(scope="session")
def ci_run(motion_sim, tmp_path_factory):
    """Every network trained with the ``ci`` preset on :func:`motion_sim` (a TrainResult),
    every epoch's model kept (``keep_epochs``)."""
    from couch.synthesis.train import train

    run = tmp_path_factory.mktemp("train_run")
    return train([motion_sim], run, net="all", preset="ci", progress=False, seed=0,
                 keep_epochs=True)

