"""couch.synthesis.plans: ControlNet's plans replayed over a feature cache, and PoseNet trained
on them (``TrainConfig.control_source="controlnet"``), on the session's ``ci_run``."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from couch.synthesis.data import FeatureCache, build_cache, find_sequences
from couch.synthesis.features import FeatureStats
from couch.synthesis.plans import replay_plans
from couch.synthesis.train import load_trained, main, preset_config, train


@pytest.fixture(scope="module")
def replayed(ci_run):
    cache = FeatureCache(ci_run.cache_path)
    net, stats, _ = load_trained(ci_run.run_dir, "control")
    return cache, net, stats, replay_plans(cache, net, stats)


def test_replayed_plans_are_zero_where_the_control_is_off_and_not_the_data(replayed):
    cache, _, _, (positions, phases) = replayed
    assert positions.shape == (cache.num_rows, cache.dims["control_root_positions"])
    assert phases.shape == (cache.num_rows, cache.dims["control_phases"])
    off = cache.group("hand_mask") < 0.5  # (N, 2)
    k = phases.shape[1] // 2
    pos = positions.reshape(len(off), 2, k, 3)
    assert off.any() and (~off).any()
    assert np.all(pos[off] == 0) and np.all(phases.reshape(-1, 2, k)[off] == 0)
    assert np.all(np.any(pos[~off] != 0, axis=(-1, -2)))
    assert np.all((phases >= 0) & (phases <= 1))
    # ControlNet's plans, not the data's future hand paths (which PoseNet reads by default)
    data = cache.group("control_root_positions").reshape(pos.shape)
    assert np.abs(pos[~off] - data[~off]).mean() > 1e-3


def test_each_sequence_replays_as_it_would_alone(replayed, motion_sim, tmp_path):
    """Sequences are replayed side by side, padded to the longest: each one's rows equal its
    replay in a cache of its own (padding and other sequences change nothing)."""
    cache, net, stats, (positions, phases) = replayed
    refs = find_sequences([motion_sim])
    lengths = cache.lengths()
    s = int(np.argmin(lengths))  # the shortest is padded the most
    ref = next(r for r in refs if str(r) == cache.sources[s])
    alone = build_cache([ref], tmp_path / "one.h5", cache.config, progress=False)
    assert alone.num_rows == lengths[s]
    pos1, ph1 = replay_plans(alone, net, stats)
    rows = slice(cache.offsets[s], cache.offsets[s + 1])
    np.testing.assert_allclose(pos1, positions[rows], atol=1e-5)
    np.testing.assert_allclose(ph1, phases[rows], atol=1e-5)


def test_posenet_trains_on_controlnet_plans(ci_run, motion_sim, tmp_path, capsys):
    cfg = dataclasses.replace(preset_config("pose", "ci"), control_source="controlnet")
    assert main([str(motion_sim), "-o", str(tmp_path), "--net", "pose", "--preset", "ci",
                 "--control-source", "controlnet", "-q"]) == 2
    assert "train --net control first" in capsys.readouterr().err
    shutil.copytree(ci_run.run_dir / "control", tmp_path / "control")
    r = train([motion_sim], tmp_path, net="pose", progress=False, configs={"pose": cfg})
    pose = r.nets["pose"]
    assert pose.train_loss[-1] < pose.train_loss[0]
    meta = load_trained(tmp_path, "pose")[2]
    assert meta["train_config"]["control_source"] == "controlnet"
    assert meta["control_plans"]["checkpoint"].endswith("control/best.pt")
    # its control input was normalised with the plans' statistics, not the data's
    ours = FeatureStats.load(tmp_path / "pose" / "stats.npz")
    data = FeatureStats.load(ci_run.run_dir / "pose" / "stats.npz")
    assert not np.allclose(ours.std["control_root_positions"],
                           data.std["control_root_positions"])
    np.testing.assert_allclose(ours.std["joint_positions"], data.std["joint_positions"])
    with pytest.raises(ValueError, match="control_source"):
        train([motion_sim], tmp_path / "bad", net="pose", progress=False,
              configs={"pose": dataclasses.replace(cfg, control_source="oracle")})


def test_cache_groups_are_replaced_in_memory_and_restored(ci_run):
    cache = FeatureCache(ci_run.cache_path)
    data = cache.group("control_phases").copy()
    cache.replace("control_phases", np.zeros_like(data))
    assert np.all(cache.rows("control_phases", np.arange(3)) == 0)
    cache.restore("control_phases")
    np.testing.assert_array_equal(cache.group("control_phases"), data)
    with pytest.raises(ValueError, match=r"control_phases.*expected a per-row group"):
        cache.replace("control_phases", data[:-1])
