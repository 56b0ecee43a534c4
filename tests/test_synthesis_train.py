"""couch.synthesis.data and couch.synthesis.train on a few simulated sequences (ci preset).

Budget: simulating the 5 sequences (~65 s) and one ``train(net="all", preset="ci")`` (~10 s)
happen once per test session (``motion_sim``, ``ci_run`` in conftest.py); the other tests and
the controller's tests reuse them.
"""

from __future__ import annotations

import csv
import dataclasses
import importlib
import json
import os
import re
import shutil

import h5py
import numpy as np
import pytest
import torch

from couch.body.skeleton import CONTACT_NAMES, JOINT_INDEX
from couch.schema import SCHEMA_VERSION, read_processed, write_processed, write_session_group
from couch.synthesis.data import (
    BlockLoader,
    FeatureCache,
    FrameDataset,
    WindowDataset,
    _normalized,
    build_cache,
    chair_ids,
    collate_batch,
    contact_rows,
    find_sequences,
    fit_stats,
    load_sequence,
    make_loader,
    split,
)
from couch.synthesis.features import LAYOUT, SIT, FeatureStats
from couch.synthesis.train import (
    _TASKS,
    ALL_NETS,
    NETS,
    TEACHER_ALWAYS,
    WEIGHTED_JOINTS,
    available_memory,
    load_trained,
    main,
    output_weights,
    parse_which,
    pose_feedback,
    pose_inputs,
    preset_config,
    rows_memory,
    train,
)

FILES = ("checkpoint.pt", "best.pt", "stats.npz", "log.csv", "curves.png")


@pytest.fixture(scope="module")
def sim(motion_sim):
    return motion_sim


@pytest.fixture(scope="module")
def trained(ci_run):
    return ci_run


def _log(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_all_nets_learn_and_write_their_files(trained):
    assert list(trained.nets) == list(ALL_NETS) and "nsm" in NETS  # "all": not the plain NSM
    for net in ALL_NETS:
        r = trained.nets[net]
        for name in FILES:
            assert (r.dir / name).is_file(), f"{net}: {name} missing"
        rows = _log(r.dir / "log.csv")
        assert [int(row["epoch"]) for row in rows] == list(range(1, r.epochs + 1))
        assert {"lr", "train_loss", "val_loss", "seconds"} <= set(rows[0])
        assert r.train_loss[-1] < 0.8 * r.train_loss[0], (net, r.train_loss)
        if net != "contact":  # ContactNet sees ~10 contact sets: validation is noise in ci
            assert r.val_loss[-1] < r.val_loss[0], (net, r.val_loss)
    # Component columns: Eq. 2 terms for ControlNet, per-target MSE for PoseNet, Eq. 4 terms.
    assert {"train_traj", "train_phase", "train_reg", "val_traj"} <= set(
        _log(trained.nets["control"].dir / "log.csv")[0])
    assert "val_next_joint_positions" in _log(trained.nets["pose"].dir / "log.csv")[0]
    assert {"train_recon", "train_kl"} <= set(_log(trained.nets["contact"].dir / "log.csv")[0])
    ck = torch.load(trained.nets["pose"].dir / "checkpoint.pt", weights_only=True)
    assert ck["epoch"] == trained.nets["pose"].epochs
    assert {"model", "optimizer", "scheduler", "rng", "history", "meta"} <= set(ck)


def test_resume_continues_and_reproduces(sim, trained, tmp_path):
    first = train([sim], tmp_path, net="pose", preset="ci", progress=False, stop_after=2)
    assert first.nets["pose"].epochs == 2
    assert len(_log(tmp_path / "pose" / "log.csv")) == 2
    second = train([sim], tmp_path, net="pose", preset="ci", progress=False)
    r = second.nets["pose"]
    assert second.cache_hit
    assert r.resumed_from == 2
    assert [h["epoch"] for h in r.history] == list(range(1, r.epochs + 1))
    epochs = [int(row["epoch"]) for row in _log(tmp_path / "pose" / "log.csv")]
    assert epochs == list(range(1, r.epochs + 1))  # one row per epoch, no duplicates
    # Resumed after epoch 2, it ends where the uninterrupted run (the same seed, trained with
    # the other networks) ended, to the bit: training on one thread repeats exactly.
    ref = trained.nets["pose"].history[-1]
    assert r.history[-1]["val_loss"] == ref["val_loss"]
    assert r.history[-1]["train_loss"] == ref["train_loss"]
    mine, theirs = (torch.load(d / "checkpoint.pt", weights_only=True)["model"]
                    for d in (r.dir, trained.nets["pose"].dir))
    assert mine.keys() == theirs.keys()
    assert all(torch.equal(mine[k], theirs[k]) for k in mine)
    # A finished run resumes to "nothing left to do" and keeps its log.
    third = train([sim], tmp_path, net="pose", preset="ci", progress=False)
    assert third.nets["pose"].resumed_from == r.epochs
    assert len(_log(tmp_path / "pose" / "log.csv")) == r.epochs
    # Different settings must not silently continue an old run.
    with pytest.raises(ValueError, match=r"checkpoint\.pt: .*settings \(epochs\)"):
        train([sim], tmp_path, net="pose", preset="ci", epochs=9, progress=False)
    # A run saved before a setting existed trained as its default does: at the default now
    # it resumes ...
    ck = torch.load(tmp_path / "pose" / "checkpoint.pt", weights_only=True)
    meta = json.loads(ck["meta"])
    saved_config = dict(meta["train_config"])
    assert saved_config["hand_weight"] == 1.0
    del meta["train_config"]["hand_weight"]
    ck["meta"] = json.dumps(meta)
    torch.save(ck, tmp_path / "pose" / "checkpoint.pt")
    assert train([sim], tmp_path, net="pose", preset="ci",
                 progress=False).nets["pose"].resumed_from == r.epochs
    # ... elsewhere it is refused, naming the setting (the ci preset's lr is not the default)
    del meta["train_config"]["lr"]
    ck["meta"] = json.dumps(meta)
    torch.save(ck, tmp_path / "pose" / "checkpoint.pt")
    with pytest.raises(ValueError, match=r"settings \(lr\)"):
        train([sim], tmp_path, net="pose", preset="ci", progress=False)
    # ... nor one trained on other features (ControlNet's line ending elsewhere)
    meta["train_config"] = saved_config
    meta["feature_config"]["control_line_end"] = 0.05
    ck["meta"] = json.dumps(meta)
    torch.save(ck, tmp_path / "pose" / "checkpoint.pt")
    with pytest.raises(ValueError, match=r"other features \(control_line_end\)"):
        train([sim], tmp_path, net="pose", preset="ci", progress=False)


def test_frame_dataset_splits_match_one_by_one_and_free_the_cache(trained):
    """Training's datasets built group by group (``FrameDataset.splits``) hold what one
    FrameDataset per row set holds, and leave the cache without the groups it read from its
    file; a group given by ``replace`` stays."""
    cache = FeatureCache(trained.cache_path)
    train_seqs, val_seqs = split(cache)
    sets = [cache.sequence_rows(train_seqs), cache.sequence_rows(val_seqs)]
    _, stats, meta = load_trained(trained.run_dir, "pose", which="last")
    groups_in, groups_out = meta["groups_in"], meta["groups_out"]
    one = [FrameDataset(cache, groups_in, groups_out, rows, stats) for rows in sets]
    assert {"joint_positions", "control_phases"} <= set(cache._data)
    replaced = cache.group("control_phases") + 1.0
    cache.replace("control_phases", replaced)
    both = FrameDataset.splits(cache, groups_in, groups_out, sets, stats)
    assert "joint_positions" not in cache._data  # read again from the file on its next use
    assert cache.group("control_phases") is replaced
    for a, b in zip(one, both, strict=True):
        assert list(b.inputs) == list(a.inputs) and list(b.targets) == list(a.targets)
        np.testing.assert_array_equal(b.indices, a.indices)
        for g in a.inputs:
            expect = (_normalized(cache, g, a.indices, stats) if g == "control_phases"
                      else a.inputs[g])
            np.testing.assert_array_equal(b.inputs[g], expect)
        for g in a.targets:
            np.testing.assert_array_equal(b.targets[g], a.targets[g])
    cache.restore("control_phases")
    train_ds = FrameDataset.splits(cache, groups_in, groups_out, sets[:1], stats)[0]
    np.testing.assert_array_equal(train_ds.inputs["control_phases"],
                                  one[0].inputs["control_phases"])
    # PoseNet's closed-loop windows over the same rows share the frame dataset's arrays
    groups = groups_in + groups_out
    copied = WindowDataset(cache, 4, 2, train_seqs, groups=groups, stats=stats)
    shared = WindowDataset(cache, 4, 2, train_seqs, groups=groups, stats=stats,
                           rows={**train_ds.inputs, **train_ds.targets})
    assert shared.data["joint_positions"] is train_ds.inputs["joint_positions"]
    w = [0, len(copied) // 2, len(copied) - 1]
    for g, x in copied.__getitems__(w).items():
        assert torch.equal(shared.__getitems__(w)[g], x)
    with pytest.raises(ValueError, match="do not cover"):
        WindowDataset(cache, 4, 2, val_seqs, groups=groups, stats=stats,
                      rows={**train_ds.inputs, **train_ds.targets})


def test_fit_stats_reads_in_chunks_and_matches_numpy(trained):
    cache = FeatureCache(trained.cache_path)
    rows = cache.sequence_rows(split(cache)[0])
    groups = ["joint_positions", "contact_condition", "hand_mask"]
    cache.release(cache.dims)  # the split read the chairs' grids
    stats = fit_stats(cache, groups, rows, chunk=37)  # many uneven chunks
    assert not set(groups) & set(cache._data)  # read from the file, nothing kept
    for g in groups:
        x = cache.rows(g, rows).astype(np.float64)
        np.testing.assert_allclose(stats.mean[g], x.mean(0), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(stats.std[g], np.maximum(x.std(0), cache.config.min_std),
                                   rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="no rows"):
        fit_stats(cache, groups, rows[:0])


def _stream_setup(trained):
    cache = FeatureCache(trained.cache_path)
    train_seqs, _ = split(cache)
    _, stats, meta = load_trained(trained.run_dir, "pose", which="last")
    return cache, train_seqs, stats, meta["groups_in"], meta["groups_out"]


def test_streamed_frames_serve_the_in_memory_rows_a_block_at_a_time(trained):
    cache, train_seqs, stats, groups_in, groups_out = _stream_setup(trained)
    rows = cache.sequence_rows(train_seqs)
    mem = FrameDataset(cache, groups_in, groups_out, rows, stats)
    cache.release(cache.dims)
    streamed = FrameDataset.streamed(cache, groups_in, groups_out, rows, stats)
    assert len(streamed) == len(mem) and not streamed.inputs
    piece, block, bs = 16, 40, 7  # blocks of ~3 pieces; batches carry over between blocks
    loader = BlockLoader(streamed, bs, block, shuffle=True,
                         generator=torch.Generator().manual_seed(3), piece_rows=piece)
    plan = loader.plan()
    batches = [b for _, bb in plan for b in bb]
    assert len(plan) > 1
    assert len(batches) == len(loader) == -(-len(mem) // bs)
    assert all(len(b) == bs for b in batches[:-1]) and 0 < len(batches[-1]) <= bs
    served = np.concatenate(batches)
    np.testing.assert_array_equal(np.sort(served), np.arange(len(mem)))  # each row once
    assert not np.array_equal(served, np.arange(len(mem)))  # shuffled
    seen: dict[int, int] = {}
    carried, runs = 0, []
    for k, (hold, bb) in enumerate(plan):
        assert k + 1 == len(plan) or len(hold) >= block
        runs.append(1 + int((np.diff(hold) != 1).sum()))
        for p in np.unique(rows[np.concatenate(bb)] // piece):
            carried += p in seen  # a piece split between two blocks: items carried over
            seen[p] = k
        streamed.stream.hold(hold)
        for b in bb:
            x, y = streamed.__getitems__(b)
            ex, ey = mem.__getitems__(b)
            for g in groups_in:
                assert torch.equal(x[g], ex[g])
            for g in groups_out:
                assert torch.equal(y[g], ey[g])
    assert carried > 0
    # shuffled pieces: a block's rows come from several places in the file, not one run
    assert np.mean(runs) > 1.5
    assert streamed.stream.reads == len(plan)  # no batch read outside its block
    assert not set(cache.dims) & set(cache._data)  # the cache kept no group
    # the loader itself: reproducible from the generator's seed; lets its block go after
    def epoch(seed):
        gen = torch.Generator().manual_seed(seed)
        return torch.cat([x["joint_positions"] for x, _ in BlockLoader(
            streamed, bs, block, True, gen, piece_rows=piece)])
    first = epoch(5)
    assert torch.equal(first, epoch(5)) and not torch.equal(first, epoch(6))
    assert not streamed.stream.data and len(first) == len(mem)
    # ... and serves, block after block read ahead in a helper thread, the rows its plan says
    order = np.concatenate([b for _, bb in BlockLoader(
        streamed, bs, block, True, torch.Generator().manual_seed(5), piece_rows=piece).plan()
        for b in bb])
    np.testing.assert_array_equal(first.numpy(), mem.inputs["joint_positions"][order])
    # any item alone reads what it needs
    i = len(mem) // 3
    assert torch.equal(streamed[i][1]["next_joint_positions"],
                       mem[i][1]["next_joint_positions"])
    assert isinstance(make_loader(mem, bs), torch.utils.data.DataLoader)
    assert isinstance(make_loader(streamed, bs, block_rows=block), BlockLoader)
    with pytest.raises(ValueError, match="streamed datasets"):
        BlockLoader(mem, bs, block)


def test_streamed_windows_serve_the_in_memory_windows(trained):
    cache, train_seqs, stats, groups_in, groups_out = _stream_setup(trained)
    groups = groups_in + groups_out
    mem = WindowDataset(cache, 8, 4, train_seqs, groups=groups, stats=stats)
    cache.release(cache.dims)
    streamed = WindowDataset(cache, 8, 4, train_seqs, groups=groups, stats=stats, stream=True)
    np.testing.assert_array_equal(streamed.starts, mem.starts)
    loader = BlockLoader(streamed, 5, 10**9)  # one block: every sequence read once
    plan = loader.plan()
    assert len(plan) == 1
    np.testing.assert_array_equal(np.concatenate(plan[0][1]), np.arange(len(mem)))
    got = list(loader)
    assert streamed.stream.reads == 1
    for b, x in zip(plan[0][1], got, strict=True):
        expect = mem.__getitems__(b)
        assert list(x) == list(expect)
        for g in groups:
            assert torch.equal(x[g], expect[g])
    with pytest.raises(ValueError, match="takes no rows"):
        WindowDataset(cache, 8, 4, train_seqs, groups=groups, stream=True, rows=mem.data)


def test_streamed_training_learns_resumes_and_reproduces(sim, tmp_path):
    """PoseNet (closed-loop epochs included) and ControlNet trained on rows streamed from
    the cache: losses fall, the setting is recorded, and a resumed run ends where an
    uninterrupted one does."""
    whole = train([sim], tmp_path / "a", net="all", preset="ci", progress=False,
                  stream_rows=300)
    for net in ("pose", "control"):
        r = whole.nets[net]
        assert r.train_loss[-1] < r.train_loss[0]
        assert all(np.isfinite(r.val_loss))
        ck = torch.load(r.dir / "checkpoint.pt", weights_only=True)
        assert json.loads(ck["meta"])["train_config"]["stream_rows"] == 300
    assert json.loads(torch.load(whole.nets["contact"].dir / "checkpoint.pt", weights_only=True
                                 )["meta"])["train_config"]["stream_rows"] == 300
    part = tmp_path / "b"
    train([sim], part, net="pose", preset="ci", progress=False, stream_rows=300, stop_after=3)
    with pytest.raises(ValueError, match=r"settings \(stream_rows\)"):
        train([sim], part, net="pose", preset="ci", progress=False)  # in memory: refused
    rest = train([sim], part, net="pose", preset="ci", progress=False, stream_rows=300)
    assert rest.nets["pose"].resumed_from == 3
    for key in ("train_loss", "val_loss"):  # to the bit, as in memory
        assert rest.nets["pose"].history[-1][key] == whole.nets["pose"].history[-1][key]


def test_training_warns_when_its_rows_would_not_fit(sim, trained, tmp_path, monkeypatch,
                                                   capsys):
    cache = FeatureCache(trained.cache_path)
    seqs = np.arange(cache.num_sequences)
    cfg = preset_config("pose", "ci")
    need = rows_memory("pose", cache, seqs, cfg)
    groups = LAYOUT["posenet"]["inputs"] | LAYOUT["posenet"]["targets"]
    assert need == cache.num_rows * sum(groups.values()) * 4
    assert rows_memory("pose", cache, seqs, dataclasses.replace(cfg, stream_rows=64)) == 0
    assert rows_memory("contact", cache, seqs, preset_config("contact", "ci")) == 0
    assert available_memory() is None or available_memory() > 0
    train_module = importlib.import_module("couch.synthesis.train")
    monkeypatch.setattr(train_module, "available_memory", lambda: need)  # < the build's peak
    train([sim], tmp_path, net="pose", preset="ci", epochs=1, progress=False)
    err = capsys.readouterr().err
    assert "pose's rows take" in err and "--stream" in err
    train([sim], tmp_path / "s", net="pose", preset="ci", epochs=1, progress=False,
          stream_rows=256)
    assert "rows take" not in capsys.readouterr().err


def test_training_bench_compares_memory_and_streamed(sim, capsys):
    """``python -m couch.tools.bench.training`` trains in two child processes and prints
    their peaks, epoch times and ratios (speed itself is not asserted)."""
    from couch.tools.bench import training as bench

    bench.main([str(sim), "--preset", "ci", "--stream", "200"])
    out = capsys.readouterr().out
    assert re.search(r"pose \(ci\) in memory: peak [\d.]+ GB, mean [\d.]+ GB; epochs "
                     r"[\d.]+, [\d.]+ s", out)
    assert "pose (ci) streamed : peak" in out
    assert re.search(r"streamed / in memory: peak [\d.]+x, mean [\d.]+x, epoch time "
                     r"[\d.]+x, [\d.]+x, call [\d.]+x \(200 rows a block\)", out)


def test_load_trained_matches_the_trained_model(trained):
    cache = FeatureCache(trained.cache_path)
    train_seqs, _ = split(cache)
    rows = cache.sequence_rows(train_seqs)[:16]
    with torch.no_grad():
        for net in ("pose", "baseline"):
            model, stats, meta = load_trained(trained.run_dir, net, which="last")
            ds = FrameDataset(cache, meta["groups_in"], meta["groups_out"], rows, stats)
            x, _ = collate_batch(ds.__getitems__(range(len(rows))))
            ref = trained.nets[net].model.eval()
            assert torch.equal(model(pose_inputs(x, net))[0], ref(pose_inputs(x, net))[0])
            assert set(meta["groups_out"]) == set(LAYOUT["posenet"]["targets"])
        model, stats, _ = load_trained(trained.run_dir, "control", which="last")
        batch = WindowDataset(cache, 20, sequences=train_seqs, stats=stats).__getitems__([0, 1])
        control = torch.cat([batch["control_line"], batch["hand_phases"]], -1)
        ref = trained.nets["control"].model.eval()
        assert torch.equal(model(batch["joint_positions"], control)[0],
                           ref(batch["joint_positions"], control)[0])
        model, stats, _ = load_trained(trained.run_dir, "contact", which="last")
        ds = FrameDataset(cache, ["contact_condition"], ["hand_contacts"],
                          contact_rows(cache, train_seqs), stats)
        x, y = ds.__getitems__(range(len(ds)))
        ref = trained.nets["contact"].model.eval()
        mu, _ = model.encode(y["hand_contacts"], x["contact_condition"])
        assert torch.equal(mu, ref.encode(y["hand_contacts"], x["contact_condition"])[0])
        best, _, meta = load_trained(trained.run_dir, "contact")  # best.pt
        assert meta["train_config"]["preset"] == "ci"
        assert best.sample(x["contact_condition"][:2], 3).shape == (2, 3, 6)
    assert isinstance(FeatureStats.load(trained.nets["pose"].dir / "stats.npz"), FeatureStats)


def test_kept_epochs_load_by_number(trained):
    """``keep_epochs`` writes every epoch's model; ``which=N`` loads epoch N: the last equals
    ``checkpoint.pt``'s, best.pt's epoch equals best.pt, the first differs from the last."""
    for net in ("pose", "control"):
        r = trained.nets[net]
        assert r.epochs >= 2
        names = sorted(p.name for p in (r.dir / "epochs").iterdir())
        assert names == [f"{e:03d}.pt" for e in range(1, r.epochs + 1)]
        best_epoch = int(torch.load(r.dir / "best.pt", weights_only=True)["epoch"])
        pairs = [("last", r.epochs, True), ("best", best_epoch, True), ("last", 1, False)]
        for named, number, same in pairs:
            a = load_trained(trained.run_dir, net, which=named)[0].state_dict()
            b = load_trained(trained.run_dir, net, which=number)[0].state_dict()
            equal = all(torch.equal(a[k], b[k]) for k in a)
            assert equal == same, (net, named, number)
    with pytest.raises(FileNotFoundError, match=rf"epochs/{trained.nets['pose'].epochs + 1:03d}"
                                                r"\.pt: no such file.*--keep-epochs"):
        load_trained(trained.run_dir, "pose", which=trained.nets["pose"].epochs + 1)
    for bad in ("first", 0, -1, True):
        with pytest.raises(ValueError, match="'best', 'last' or an epoch number"):
            load_trained(trained.run_dir, "pose", which=bad)


@pytest.mark.parametrize("spec, want", [
    ("best", "best"), ("last", "last"), ("14", 14),
    ("pose=14, control=best", {"pose": 14, "control": "best"}),
    ("baseline=last", {"baseline": "last"}),
])
def test_parse_which(spec, want):
    assert parse_which(spec) == want


@pytest.mark.parametrize("spec, message", [
    ("0", "'0' is not 'best', 'last' or an epoch number"),
    ("newest", "'newest' is not"),
    ("posenet=3", "'posenet=3' is not net=checkpoint"),
    ("pose=3,pose=4", "pose given twice"),
    ("pose=3,14", "'14' is not net=checkpoint"),
    ("pose=-2", "'-2' is not"),
])
def test_parse_which_refuses(spec, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        parse_which(spec)


def test_pose_feedback_turns_next_pose_targets_into_the_next_rows_inputs(trained):
    """Closed-loop training feeds PoseNet's prediction back as the runtime does: fed the data's
    own targets, the feedback must give the data's next J and T inputs (same rows, each
    normalised as its group), and the data's next global phase wherever the runtime's rule
    for being seated (predicted pelvis contact or next sit label > 0.5) agrees with the data."""
    cache = FeatureCache(trained.cache_path)
    train_seqs, _ = split(cache)
    _, stats, meta = load_trained(trained.run_dir, "pose", which="last")
    gin, gout = meta["groups_in"], meta["groups_out"]
    ds = WindowDataset(cache, 6, sequences=train_seqs, groups=gin + gout, stats=stats)
    batch = ds.__getitems__(range(len(ds)))
    feed = pose_feedback(gout, [cache.dims[g] for g in gout], stats)
    sit_col = 9 + SIT
    agree = total = seated_rows = 0

    def denorm(t: torch.Tensor, g: str) -> torch.Tensor:
        return t * torch.as_tensor(stats.std[g]) + torch.as_tensor(stats.mean[g])

    for k in range(5):
        nxt = {g: batch[g][:, k + 1] for g in gin}
        # the other groups are passed through from the data's next row untouched
        nxt["ego"] = torch.full_like(nxt["ego"], 7.0)
        fed = feed(torch.cat([batch[g][:, k] for g in gout], -1),
                   {g: batch[g][:, k] for g in gin}, nxt)
        assert set(fed) == set(gin)
        assert torch.equal(fed["ego"], nxt["ego"])
        for g in ("joint_positions", "joint_rotations", "joint_velocities", "trajectory"):
            torch.testing.assert_close(fed[g], batch[g][:, k + 1], atol=2e-4, rtol=1e-4)
        phase = denorm(fed["global_phase"], "global_phase")
        data = denorm(batch["global_phase"][:, k + 1], "global_phase")
        fut = denorm(batch["future_trajectory"][:, k], "future_trajectory")
        contacts = denorm(batch["next_contacts"][:, k], "next_contacts")
        seated = (contacts[:, CONTACT_NAMES.index("pelvis")] > 0.5) | (fut[:, sit_col] > 0.5)
        torch.testing.assert_close(phase[seated], torch.ones_like(phase[seated]))
        same = seated == (data[:, 0] > 1 - 1e-4)
        # phases are on a circle: 0.99998 and 0 are the same
        wrapped = torch.remainder(phase[same] - data[same] + 0.5, 1.0) - 0.5
        torch.testing.assert_close(wrapped, torch.zeros_like(wrapped), atol=2e-4, rtol=0)
        agree, total = agree + int(same.sum()), total + len(same)
        seated_rows += int(seated.sum())
    # both branches of the phase rule were exercised
    assert 0 < seated_rows < total, (seated_rows, total)
    # the rule is the data's own nearly everywhere: only frames at a sit's onset differ
    assert agree >= 0.95 * total, (agree, total)
    with pytest.raises(ValueError, match="feed back"):
        pose_feedback(["root_update"], [3], stats)


def test_closed_loop_epochs_train_and_validate_closed_loop(sim, trained, tmp_path):
    """``rollout_epochs``: the last epochs train on closed-loop windows, validation is closed
    loop throughout (its loss is above the one-step run's), and the closed-loop loss falls."""
    cfg = dataclasses.replace(preset_config("pose", "ci"), rollout=4, rollout_epochs=3)
    r = train([sim], tmp_path, net="pose", progress=False, configs={"pose": cfg}).nets["pose"]
    assert len(r.history) == cfg.epochs
    one_step = trained.nets["pose"].history
    # the same model as the one-step run until the closed-loop epochs begin, so the same
    # training loss; its validation is closed loop, so higher
    first = cfg.epochs - cfg.rollout_epochs
    assert r.history[first - 1]["train_loss"] == pytest.approx(
        one_step[first - 1]["train_loss"], rel=1e-4)
    assert r.val_loss[0] > one_step[0]["val_loss"]
    assert r.val_loss[-1] < r.val_loss[0], r.val_loss
    assert r.train_loss[-1] < r.train_loss[first], r.train_loss
    # best.pt is a closed-loop epoch's model, whatever the one-step warm-up's validation was
    assert torch.load(r.dir / "best.pt", weights_only=True)["epoch"] > first
    with pytest.raises(ValueError, match="rollout"):
        train([sim], tmp_path / "bad", net="pose", progress=False,
              configs={"pose": dataclasses.replace(cfg, rollout=1)})


def test_controlnet_validates_at_the_teacher_probability_training_ends_at(sim, trained,
                                                                         tmp_path):
    """Scheduled sampling that ends closed loop validates closed loop from the first epoch;
    teacher forcing throughout (the ``cpu`` preset's ControlNet) validates teacher-forced, so
    that ``best.pt`` is picked in the conditions the network was trained for."""
    scheduled = [float(r["val_p_teacher"]) for r in _log(trained.run_dir / "control" / "log.csv")]
    assert scheduled == [0.0] * len(scheduled)
    base = preset_config("control", "ci")
    assert preset_config("control", "cpu").network["teacher_forcing_until"] == TEACHER_ALWAYS
    cfg = dataclasses.replace(base, epochs=3, network={
        **base.network, "teacher_forcing_until": TEACHER_ALWAYS,
        "teacher_forcing_off_at": TEACHER_ALWAYS})
    r = train([sim], tmp_path, net="control", progress=False, configs={"control": cfg})
    rows = _log(r.nets["control"].dir / "log.csv")
    assert [float(x["train_p_teacher"]) for x in rows] == [1.0] * 3
    assert [float(x["val_p_teacher"]) for x in rows] == [1.0] * 3
    # teacher-forced validation reads the data's lines: lower than the closed-loop one
    assert float(rows[0]["val_loss"]) < float(_log(trained.run_dir / "control" / "log.csv")[0][
        "val_loss"])


def test_hand_weight_weighs_the_wrists_in_the_loss(trained):
    """``hand_weight``: the wrists' next positions (3 columns each) and rotations (6 each)
    weigh that much in PoseNet's loss, every other column 1; the task's loss is that weighted
    mean of the squared errors."""
    assert WEIGHTED_JOINTS == (JOINT_INDEX["left_wrist"], JOINT_INDEX["right_wrist"]) == (20, 21)
    cache = FeatureCache(trained.cache_path)
    train_seqs, val_seqs = split(cache)
    model, stats, meta = load_trained(trained.run_dir, "pose", which="last")
    gout = meta["groups_out"]
    widths = [cache.dims[g] for g in gout]
    w = output_weights(gout, widths, 4.0)
    assert w.shape == (sum(widths),)
    start = dict(zip(gout, np.cumsum([0, *widths[:-1]]).tolist(), strict=True))
    expected = sorted([start["next_joint_positions"] + 3 * j + k for j in (20, 21)
                       for k in range(3)]
                      + [start["next_joint_rotations"] + 6 * j + k for j in (20, 21)
                         for k in range(6)])
    heavy = torch.nonzero(w != 1.0).flatten().tolist()
    assert heavy == expected and bool(torch.all(w[heavy] == 4.0))
    assert torch.equal(output_weights(gout, widths, 1.0), torch.ones(sum(widths)))

    cfg = dataclasses.replace(preset_config("pose", "ci"), hand_weight=4.0)
    task = _TASKS["pose"](cache, train_seqs, val_seqs, cfg, stats)
    x, y = next(iter(torch.utils.data.DataLoader(task.val_ds, batch_size=16,
                                                 collate_fn=collate_batch)))
    model.eval()
    with torch.no_grad():
        pred, _ = model(pose_inputs(x, "pose"))
        sq = (pred - torch.cat([y[g] for g in gout], -1)) ** 2
        got = task.loss(model, (x, y), 1, False, None)["loss"]
    torch.testing.assert_close(got, (sq * w).mean())
    assert float(got) > float(sq.mean())  # the wrists' errors counted four times
    with pytest.raises(ValueError, match="hand_weight"):
        _TASKS["pose"](cache, train_seqs, val_seqs,
                       dataclasses.replace(cfg, hand_weight=0.0), stats)


def test_a_run_on_older_features_is_a_clear_error(trained, tmp_path):
    """A PoseNet whose checkpoint names feature groups this couch no longer builds (C+ was
    relative to the contact before format 5) is refused at load, naming the file."""
    old = tmp_path / "run" / "pose"
    shutil.copytree(trained.nets["pose"].dir, old)
    ck = torch.load(old / "best.pt", weights_only=True)
    meta = json.loads(ck["meta"])
    meta["groups_in"] = ["control_positions" if g == "control_root_positions" else g
                         for g in meta["groups_in"]]
    ck["meta"] = json.dumps(meta)
    torch.save(ck, old / "best.pt")
    with pytest.raises(ValueError, match=r"best\.pt: pose was trained on feature groups.*"
                                         r"retrain"):
        load_trained(tmp_path / "run", "pose")


def test_cache_reused_then_rebuilt_and_skips(sim, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    for name in ("motion_00000.h5", "motion_00004.h5"):
        shutil.copy2(sim / name, data / name)
    # A one-frame sequence has no t -> t+1 pair: skipped with a reason, not fatal.
    s = read_processed(sim / "motion_00001.h5")
    one = {f: getattr(s, f)[:1] for f in ("time", "global_orient", "body_pose", "transl",
                                          "joints", "object_frame_poses", "contact_active",
                                          "contact_points", "interaction")}
    write_processed(data / "motion_00009.h5",
                    dataclasses.replace(s, session="one_frame", quality={}, **one))
    out = tmp_path / "features.h5"
    cache = build_cache(find_sequences([data]), out, progress=False)
    assert not cache.hit
    assert cache.num_sequences == 2 and len(cache.skipped) == 1
    assert "motion_00009" in cache.skipped[0][0]
    assert cache.num_rows == int(cache.offsets[-1]) == cache.group("joint_positions").shape[0]
    assert cache.group("contact_condition").shape == (2, 2048)
    assert cache.group("contact_inputs").shape == (cache.num_rows, 8)
    mtime = out.stat().st_mtime_ns
    again = build_cache(find_sequences([data]), out, progress=False)
    assert again.hit and out.stat().st_mtime_ns == mtime
    src = data / "motion_00000.h5"
    st = src.stat()
    os.utime(src, ns=(st.st_atime_ns, st.st_mtime_ns + 5_000_000_000))
    rebuilt = build_cache(find_sequences([data]), out, progress=False)
    assert not rebuilt.hit and out.stat().st_mtime_ns != mtime
    # Windows stay inside one sequence; short sequences give none but still count for PoseNet.
    w = WindowDataset(rebuilt, window=400)
    assert w.too_short >= 1
    for start in w.starts:
        seq = rebuilt.row_sequence[start]
        assert start + 400 <= rebuilt.offsets[seq + 1]


def test_find_sequences_reads_augmented_groups(sim, tmp_path):
    path = tmp_path / "aug" / "augmented.h5"
    path.parent.mkdir()
    with h5py.File(path, "w") as h5:
        h5.attrs.update(schema_version=SCHEMA_VERSION, kind="augmented")
        for i, name in enumerate(("motion_00000.h5", "motion_00003.h5")):
            s = read_processed(sim / name)
            write_session_group(h5.create_group(f"seq{i}"),
                                dataclasses.replace(s, session=f"seq{i}"))
    (tmp_path / "aug" / "notes.h5").write_bytes(b"")  # foreign file in a folder: ignored
    refs = find_sequences([tmp_path / "aug"])
    assert [r.group for r in refs] == ["seq0", "seq1"]
    assert load_sequence(refs[1]).session == "seq1"
    assert find_sequences([path, path]) == refs  # duplicates dropped


def test_baseline_gates_on_phase_and_which_hands_not_where(trained):
    """NSM+Control: the gating network reads the phase and the action (which hands have a
    contact); the contacts' positions reach the baseline through its C encoder only."""
    cache = FeatureCache(trained.cache_path)
    train_seqs, _ = split(cache)
    rows = cache.sequence_rows(train_seqs)[:32]
    model, stats, meta = load_trained(trained.run_dir, "baseline", which="last")
    ds = FrameDataset(cache, meta["groups_in"], meta["groups_out"], rows, stats)
    x, _ = collate_batch(ds.__getitems__(range(len(rows))))
    moved = dict(x)
    moved["contact_inputs"] = x["contact_inputs"].clone()
    moved["contact_inputs"][:, :6] += torch.randn(len(rows), 6)  # positions, in std units
    with torch.no_grad():
        gate = model.gate(pose_inputs(x, "baseline"))
        assert torch.equal(model.gate(pose_inputs(moved, "baseline")), gate)
        assert not torch.equal(model(pose_inputs(moved, "baseline"))[0],
                               model(pose_inputs(x, "baseline"))[0])
        flipped = dict(x)
        flipped["hand_mask"] = -x["hand_mask"] + 1.0
        assert not torch.allclose(model.gate(pose_inputs(flipped, "baseline")), gate)


def test_nsm_reads_no_contacts_and_its_hands_go_where_the_motion_takes_them(ci_nsm_run):
    """The plain NSM (paper Table 2): the pose network with no hand input, gated on the phase
    alone. It learns like the others, and two characters asked for contacts 4 cm apart in
    height (the same sit goal) move alike under it, unlike under the baseline, which reads
    them."""
    from couch.synthesis import Scene, Synthesizer
    from couch.tools.sim.chairs import make_chair, random_chair_spec

    r = ci_nsm_run.nets["nsm"]
    assert list(ci_nsm_run.nets) == ["nsm"] and ci_nsm_run.cache_hit
    for name in FILES:
        assert (r.dir / name).is_file(), name
    assert r.train_loss[-1] < 0.8 * r.train_loss[0] and r.val_loss[-1] < r.val_loss[0]
    model, _, meta = load_trained(ci_nsm_run.run_dir, "nsm")
    assert set(model.encoders) == {"JT", "G", "I", "E"}
    assert model.gating_inputs == {"global_phase": 1}
    assert not {"contact_inputs", "hand_mask", "control_root_positions"} & set(meta["groups_in"])
    assert set(meta["groups_out"]) == set(LAYOUT["posenet"]["targets"])

    torch.set_num_threads(1)
    c = make_chair(random_chair_spec(np.random.default_rng(4), "armchair"))
    left = np.asarray(c.landmarks.left_armrest)
    starts = np.array([[0.2, 0.9, np.pi]])  # within reach: control on from the start
    asked = [np.array([[left + np.array([0.0, dy, 0.0]), [np.nan] * 3]]) for dy in (0.0, 0.04)]
    joints = {}
    for method in ("nsm", "baseline"):
        syn = Synthesizer(ci_nsm_run.run_dir, method)
        scene = Scene.from_mesh(c.vertices, c.faces, syn.cfg)
        out = [syn.synthesize(scene, starts, s, seconds=1.0) for s in asked]
        np.testing.assert_array_equal(out[0].goal, out[1].goal)
        assert out[0].control_on[0, :, 0].all() and out[1].control_on[0, :, 0].all()
        joints[method] = [o.joints for o in out]
    np.testing.assert_array_equal(*joints["nsm"])
    assert np.abs(joints["baseline"][0] - joints["baseline"][1]).max() > 1e-4


def test_split_holds_out_chairs(trained):
    cache = FeatureCache(trained.cache_path)
    train_seqs, val_seqs = split(cache)
    assert len(val_seqs) == 1 and len(train_seqs) == cache.num_sequences - 1
    # Three chairs, each in one or two sequences (same name, same geometry): a chair is held
    # out whole.
    cache.object_names = ["a", "b", "c", "a", "b"]
    grids = cache.group("contact_condition").copy()
    grids[3], grids[4] = grids[0], grids[1]
    cache._data["contact_condition"] = grids
    train_seqs, val_seqs = split(cache, val_fraction=0.3, seed=1)
    held = {cache.object_names[i] for i in val_seqs}
    assert held and held.isdisjoint(cache.object_names[i] for i in train_seqs)
    assert sorted([*train_seqs, *val_seqs]) == list(range(cache.num_sequences))
    # Simulated and augmented sequences name the chair by its kind and each has its own
    # geometry: the kinds are not chairs, and none is held out whole.
    cache.object_names = ["stool", "sofa", "sofa", "sofa", "stool"]
    grids = grids.copy()
    grids[3] += 1.0
    grids[4] += 1.0
    cache._data["contact_condition"] = grids
    ids = chair_ids(cache)
    assert len(set(ids)) == 5
    assert all(i.startswith(n) for i, n in zip(ids, cache.object_names, strict=True))
    train_seqs, val_seqs = split(cache, val_fraction=0.2, seed=0)
    assert len(val_seqs) == 1 and len(train_seqs) == 4


def test_main_reports_bad_inputs(tmp_path, capsys):
    missing = tmp_path / "nope"
    assert main([str(missing), "-o", str(tmp_path / "run"), "-q"]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main([str(empty), "-o", str(tmp_path / "run"), "-q"]) == 2
    assert str(empty) in capsys.readouterr().err
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as h5:
        h5["x"] = np.zeros(3)
    assert main([str(foreign), "-o", str(tmp_path / "run"), "-q"]) == 2
    err = capsys.readouterr().err
    assert str(foreign) in err and "schema_version" in err
    assert main([str(foreign), "-o", str(tmp_path / "run"), "--net", "posenet"]) == 2
    assert main([str(foreign), "-o", str(tmp_path / "run"), "--epochs", "0"]) == 2
    assert main([str(foreign), "-o", str(tmp_path / "run"), "--rollout-epochs", "-1"]) == 2
    assert "--rollout-epochs must not be negative" in capsys.readouterr().err
    assert main([str(foreign), "-o", str(tmp_path / "run"), "--hand-weight", "0"]) == 2
    assert "--hand-weight must be positive" in capsys.readouterr().err
    assert main([str(foreign), "-o", str(tmp_path / "run"), "--stream", "0"]) == 2
    assert "--stream must be at least 1 row" in capsys.readouterr().err
    for bad in ("-1", "soon", "nan"):
        assert main([str(foreign), "-o", str(tmp_path / "run"), "--push-off-window", bad]) == 2
        assert "--push-off-window must be seconds >= 0 or none" in capsys.readouterr().err


def test_main_trains_and_resumes_finished_run(sim, trained, capsys):
    # Everything is finished already: resume loads the checkpoint and has nothing left to do.
    assert main([str(sim), "-o", str(trained.run_dir), "--net", "contact", "--preset", "ci",
                 "-q"]) == 0
    rows = _log(trained.nets["contact"].dir / "log.csv")
    assert len(rows) == trained.nets["contact"].epochs
