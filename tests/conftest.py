"""Shared fixtures (body models are loaded once per test session) and how `make test` splits
the suite over worker processes (pytest-xdist: each test file is one unit of work)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

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

#: Test files that share the session-scoped :func:`ci_run` (every network trained, ~minutes):
#: one worker runs them all, so the training happens once.
TRAINED = ("test_synthesis_controller", "test_synthesis_evaluation", "test_synthesis_plans",
           "test_synthesis_precision", "test_synthesis_select", "test_synthesis_train")
#: Units of work handed out first, longest first (each 2-8 minutes on 2 cores, measured with
#: ``--durations``): a worker that starts a long unit last keeps the suite waiting while the
#: other idles.
FIRST = ("test_process", "test_sync", "test_fitting_session", "test_fitting_chair", "trained",
         "test_sim_motion", "test_capture_calibration", "test_fitting_contacts")


def _unit(path: str) -> str:
    """The unit of work (one worker runs it whole) of a test file's path or node id."""
    module = Path(path.split("::")[0]).stem
    return "trained" if module in TRAINED else module


@pytest.hookimpl(optionalhook=True)  # a pytest-xdist hook: `make test` runs -n 2
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """Each test file is one unit of work, so its module- and session-scoped fixtures are
    built once, on one worker; the files sharing :func:`ci_run` are one unit together.
    (xdist's own ``--dist loadgroup`` marks no longer reach its scheduler under pytest 9.2, as
    the node id it rewrites is not the one pytest reports.)"""
    from xdist.scheduler import LoadScopeScheduling

    class FileUnits(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _unit(nodeid)

    return FileUnits(config, log)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """On xdist's workers (whose collection the scheduler hands out in order, with
    ``--no-loadscope-reorder``) the longest units come first; otherwise pytest's order."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    rank = {u: i for i, u in enumerate(FIRST)}
    items.sort(key=lambda item: rank.get(_unit(item.nodeid), len(FIRST)))  # stable


if os.environ.get("PYTEST_XDIST_WORKER"):
    # N workers on the machine's cores: each torch gets its share of threads instead of all of
    # them (oversubscribed OpenMP threads spin against each other).
    torch.set_num_threads(max(1, (os.cpu_count() or 1)
                              // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))))


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
    simulate_motion_dataset(out, 5, seed=21, progress=False)
    return out


@pytest.fixture(scope="session")
def ci_run(motion_sim, tmp_path_factory):
    """Every network trained with the ``ci`` preset on :func:`motion_sim` (a TrainResult),
    every epoch's model kept (``keep_epochs``)."""
    from couch.synthesis.train import train

    run = tmp_path_factory.mktemp("train_run")
    return train([motion_sim], run, net="all", preset="ci", progress=False, seed=0,
                 keep_epochs=True)


@pytest.fixture(scope="session")
def ci_nsm_run(ci_run, motion_sim, tmp_path_factory):
    """A run folder holding :func:`ci_run`'s networks and feature cache (links) and the plain
    NSM trained beside them (``net="nsm"``, ``ci`` preset; a TrainResult)."""
    from couch.synthesis.train import train

    run = tmp_path_factory.mktemp("nsm_run")
    for name in ("features.h5", "pose", "control", "baseline", "contact"):
        os.symlink(ci_run.run_dir / name, run / name)
    return train([motion_sim], run, net="nsm", preset="ci", progress=False, seed=0)
