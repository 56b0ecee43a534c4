"""``couch-train``: train ControlNet, PoseNet, ContactNet and the NSM+Control baseline.

Paper supplementary Sec. 2: 150 epochs each; ControlNet Adam 1e-3 with cosine decay to 5e-6
over 60-frame windows with scheduled sampling; PoseNet Adam 1e-4 cosine to 5e-6; ContactNet
Adam 1e-3, beta 0.1, z 6; batch 32 (released code). The ``ci`` preset shrinks every network
so that all four train on a handful of simulated sequences in about a minute on a CPU.

Run layout (``RUN`` = ``-o``)::

    RUN/features.h5            feature cache (data.build_cache; reused while inputs are unchanged)
    RUN/<net>/checkpoint.pt    last finished epoch: model, optimizer, scheduler, RNG, history
    RUN/<net>/best.pt          model with the lowest validation loss
    RUN/<net>/epochs/NNN.pt    every epoch's model, with ``keep_epochs`` (``--keep-epochs``)
    RUN/<net>/stats.npz        normalisation (FeatureStats) fitted on the training split
    RUN/<net>/log.csv          one row per epoch: lr, losses and their components, seconds
    RUN/<net>/curves.png       loss curves

Checkpoints hold only tensors, numbers and strings (configs as JSON), so they load with
``torch.load(..., weights_only=True)``. Each epoch reseeds torch from ``(seed, epoch)`` and the
DataLoader's generator likewise, so a run resumed after epoch k gives the same weights as an
uninterrupted one (on the same device and torch build).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from tqdm import tqdm

from couch.atomic import atomic_path
from couch.body.skeleton import CONTACT_NAMES, JOINT_INDEX
from couch.cli import parse_args
from couch.schema import SchemaError
from couch.synthesis.data import (
    FeatureCache,
    FrameDataset,
    WindowDataset,
    build_cache,
    contact_rows,
    feature_config_from_json,
    find_sequences,
    fit_stats,
    make_loader,
    split,
)
from couch.synthesis.features import (
    SIT,
    FeatureConfig,
    FeatureStats,
    layout,
    tidy_future_trajectory,
)
from couch.synthesis.nets import (
    ContactNet,
    ContactNetConfig,
    ControlNet,
    ControlNetConfig,
    PoseNet,
    PoseNetConfig,
    control_loss,
    kl_divergence,
    rollout,
    scheduled_sampling_probability,
)
from couch.synthesis.plans import REPLAN_RADIUS, replay_plans

__all__ = [
    "ALL_NETS",
    "ENCODER_GROUPS",
    "GATING_GROUPS",
    "NETS",
    "POSE_NETS",
    "PRESETS",
    "NetResult",
    "TrainConfig",
    "TrainResult",
    "load_trained",
    "main",
    "pose_inputs",
    "preset_config",
    "train",
]

NETS: tuple[str, ...] = ("control", "pose", "contact", "baseline", "nsm")
#: What ``net="all"`` trains: COUCH's three networks and the NSM+Control baseline, not the
#: plain NSM (paper Table 2's first row; ``net="nsm"`` trains it on request).
ALL_NETS: tuple[str, ...] = ("control", "pose", "contact", "baseline")
#: The PoseNet variants (one architecture, one task): COUCH's, NSM+Control and NSM.
POSE_NETS: tuple[str, ...] = ("pose", "baseline", "nsm")
PRESETS: tuple[str, ...] = ("paper", "cpu", "ci")
#: Epoch set as ``teacher_forcing_until`` for a ControlNet trained without scheduled sampling
#: (teacher probability 1 in every epoch of any run); finite, so the config stays plain JSON.
TEACHER_ALWAYS = 1e9
#: Where PoseNet's control input comes from (``TrainConfig.control_source``).
CONTROL_SOURCES: tuple[str, ...] = ("data", "controlnet")
#: ``couch-train --stream``'s rows per block: ~300 MB of PoseNet's rows, about 64 pieces of
#: 256 rows from all over the data mixed in each block's batches.
STREAM_ROWS = 16384
#: The training process's peak memory while the in-memory datasets are built, over the
#: bytes of their rows (PoseNet's on 857 sequences: 9.64 GB peak for 5.17 GB of rows,
#: README *Training*).
BUILD_PEAK = 1.85
#: PoseNet's control input groups, which ``control_source="controlnet"`` replaces.
CONTROL_GROUPS: tuple[str, ...] = ("control_root_positions", "control_phases")

#: PoseNet encoder name (Table 5) -> the feature groups concatenated as its input.
ENCODER_GROUPS: dict[str, dict[str, tuple[str, ...]]] = {
    "pose": {"C": ("control_root_positions", "control_phases"),
             "JT": ("joint_positions", "joint_rotations", "joint_velocities", "trajectory"),
             "G": ("goals",), "I": ("interaction",), "E": ("ego",)},
}
# The NSM+Control baseline reads the raw hand contacts where PoseNet reads ControlNet's C+.
ENCODER_GROUPS["baseline"] = {**ENCODER_GROUPS["pose"], "C": ("contact_inputs",)}
# NSM reads no control input at all: the baseline's adaptation undone.
ENCODER_GROUPS["nsm"] = {k: v for k, v in ENCODER_GROUPS["pose"].items() if k != "C"}
#: Gating features per PoseNet variant. NSM's gating network reads the phase and the goal
#: action, not where the goal is; the baseline has no local phases (it never sees ControlNet's
#: output), so it gates on the global phase and which hands have a contact (the action), and
#: reads the contacts' positions through its C encoder alone. (Gating on the positions too, as
#: couch did before 2026-11-27, is a stronger adaptation than NSM+Control: see the README.)
GATING_GROUPS: dict[str, tuple[str, ...]] = {
    "pose": ("global_phase", "control_phases"),
    "baseline": ("global_phase", "hand_mask"),
    "nsm": ("global_phase",),
}
#: PoseNet inputs the runtime builds from its own previous predictions (see ``input_noise``).
FED_BACK_GROUPS: tuple[str, ...] = ("joint_positions", "joint_rotations", "joint_velocities",
                                    "trajectory", "global_phase")
#: PoseNet's next-pose outputs -> the J inputs they become on the next frame. The runtime feeds
#: them back unchanged (both are in the next root's frame); closed-loop training does the same.
#: It also feeds back T's present and future samples and the global phase (:func:`pose_feedback`).
POSE_FEEDBACK: dict[str, str] = {"next_joint_positions": "joint_positions",
                                 "next_joint_rotations": "joint_rotations",
                                 "next_joint_velocities": "joint_velocities"}
#: The other outputs :func:`pose_feedback` reads (T, the global phase and when it is seated).
_FEEDBACK_READS = ("future_trajectory", "global_phase_update", "next_contacts")
_LAYOUT_KEY = {"control": "controlnet", "pose": "posenet", "baseline": "baseline",
               "nsm": "nsm", "contact": "contactnet"}


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings of one network (see :func:`preset_config`).

    Attributes:
        net: control | pose | contact | baseline.
        preset: the preset it came from (paper | ci).
        epochs: training epochs.
        batch_size: samples (rows, windows or contact sets) per step.
        lr: initial Adam learning rate.
        lr_min: cosine schedule's final learning rate (ignored without ``cosine``).
        cosine: cosine-anneal the learning rate per epoch from ``lr`` to ``lr_min``.
        weight_decay: Adam weight decay (paper: none mentioned).
        grad_clip: clip the gradient norm to this (0: off).
        input_noise: PoseNet only: standard deviation of Gaussian noise added, while training,
            to the normalised inputs that the runtime feeds back from its own predictions (J,
            T and the global phase), so that the network learns to pull a drifting state back
            instead of compounding its one-step errors (0: off, the paper's recipe).
        rollout: PoseNet, baseline and NSM: frames per closed-loop training window (>= 2).
        rollout_epochs: PoseNet, baseline and NSM: the last this many epochs train on closed-loop
            windows of ``rollout`` frames instead of one-step pairs (0: off, the paper's
            recipe). In such a window J (joint positions, rotations, velocities) is, from the
            second frame on, the network's own previous prediction, as at runtime; the rest is
            the data's, and every frame's loss is against the data. On teacher-forced pairs J
            already says where the hands go next, so PoseNet learns to ignore C+; from its own
            drifted J it has to bring the hands back to where C+, the trajectory and the chair
            say they should be. Validation then runs closed loop in every epoch, and
            ``best.pt`` is the closed-loop epoch with the lowest validation loss.
        hand_weight: PoseNet, baseline and NSM: weight of the wrists' next positions and rotations
            (which place the hands) in the loss, every other output weighing 1 (1: a plain
            MSE, the paper's recipe). Validation uses the same weights, so ``best.pt`` is
            picked by the loss that was trained.
        control_source: PoseNet only: where its control input (C⁺ and the hands' local
            phases) comes from. ``"data"``: the data's future hand paths (the paper's recipe);
            ``"controlnet"``: the plans of the run's trained ControlNet (``RUN/control``,
            trained first) replayed over the same sequences as the runtime makes them
            (:func:`couch.synthesis.plans.replay_plans`), so that PoseNet learns to follow
            the control input it will be given rather than an exact future.
        window: ControlNet frames per training window (paper 60).
        stride: ControlNet rows between window starts (0: window // 2).
        stream_rows: PoseNet, the baseline and ControlNet: 0 (default) copies the rows they
            train and validate on into memory; N > 0 reads them from ``features.h5`` as
            batches need them, N rows at a time (:class:`couch.synthesis.data.BlockLoader`),
            so memory holds two blocks (the one served and the next, read ahead) instead of
            the rows (5.2 GB for the ``cpu`` PoseNet on 300k rows). Shuffling then mixes rows
            within a block of 256-row pieces drawn from all over the data, not across the
            whole data, so the batches (and the trained weights) differ from an in-memory
            run's; the one streamed PoseNet measured (with blocks of whole sequences, before
            the pieces) synthesised worse than its in-memory twin (README, *Training*), so
            stream only when the rows do not fit. ContactNet's samples (one per sequence and
            contact set) are always in memory.
        val_fraction: share of chairs (or sequences) held out for validation.
        split_by: "object" (held-out chairs when >= 3) or "sequence".
        network: the network's config (``ControlNetConfig`` etc.) as a plain dict.
    """

    net: str
    preset: str = "paper"
    epochs: int = 150
    batch_size: int = 32
    lr: float = 1e-4
    lr_min: float = 5e-6
    cosine: bool = True
    weight_decay: float = 0.0
    grad_clip: float = 0.0
    input_noise: float = 0.0
    rollout: int = 0
    rollout_epochs: int = 0
    hand_weight: float = 1.0
    control_source: str = "data"
    window: int = 60
    stride: int = 0
    stream_rows: int = 0
    val_fraction: float = 0.1
    split_by: str = "object"
    network: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> TrainConfig:
        return cls(**json.loads(text))


def _tuples(value: Any) -> Any:
    """JSON lists back to the tuples the network configs use (recursively through dicts)."""
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    if isinstance(value, dict):
        return {k: _tuples(v) for k, v in value.items()}
    return value


def network_config(cfg: TrainConfig) -> ControlNetConfig | PoseNetConfig | ContactNetConfig:
    """The network config object of ``cfg.network``."""
    cls = {"control": ControlNetConfig, "contact": ContactNetConfig,
           **dict.fromkeys(POSE_NETS, PoseNetConfig)}[cfg.net]
    return cls(**_tuples(cfg.network))


def preset_config(net: str, preset: str = "paper", epochs: int | None = None) -> TrainConfig:
    """The :class:`TrainConfig` of ``net`` under ``preset``.

    ``paper``: supplementary Sec. 2 (network sizes are the nets module's paper defaults).
    ``cpu``: the same recipe on mid-size networks (hidden 64-256, 6 experts, LSTM 256) for 15
    epochs (ControlNet), 16 (PoseNet, the baseline) and 100 (ContactNet), for training runs
    of a few hundred simulated sequences on a CPU in about half an hour per network; PoseNet
    and the baseline with input noise and their last 4 epochs closed loop; ControlNet
    without scheduled sampling (the data's straight line read in every frame): its closed-loop
    plans at runtime (fed back, replanned where lost) put the hands 6 % closer than the
    scheduled-sampling ControlNet's on average over three trainings and two test chair sets
    (README, session 30). Trained for 30 epochs, every network reached a lower validation
    loss and synthesised worse: the hands ended 11-47 % farther from their contacts (README,
    session 25).
    ``ci``: the same recipe on tiny networks (hidden 32-64, 3 experts, 20-frame windows, a few
    epochs) and a faster scheduled-sampling ramp, for tests and smoke runs.
    """
    if net not in NETS:
        raise ValueError(f"unknown net {net!r}; choose from {', '.join(NETS)}")
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    ci, cpu = preset == "ci", preset == "cpu"
    if net == "control":
        if ci:
            ncfg: Any = ControlNetConfig(pose_encoder=(32, 32), control_encoder=(32, 32),
                                         lstm_hidden=64, teacher_forcing_until=1.0,
                                         teacher_forcing_off_at=4.0)
        elif cpu:
            # No scheduled sampling: the straight line from the data's hand in every frame
            # (see the docstring).
            ncfg = ControlNetConfig(pose_encoder=(128, 128), control_encoder=(128, 128),
                                    lstm_hidden=256, teacher_forcing_until=TEACHER_ALWAYS,
                                    teacher_forcing_off_at=TEACHER_ALWAYS)
        else:
            ncfg = ControlNetConfig()
        kw: dict[str, Any] = dict(lr=3e-3 if ci else 1e-3, window=20 if ci else 60,
                                  epochs=12 if ci else 15 if cpu else 150,
                                  grad_clip=1.0 if ci or cpu else 0.0)
    elif net in POSE_NETS:
        if ci:
            ncfg = PoseNetConfig(encoders={"C": (32,), "JT": (64,), "G": (32,), "I": (32,),
                                           "E": (32,)},
                                 num_experts=3, gating_hidden=(32,), expert_hidden=(64,))
        elif cpu:
            # Dropout 0.3 as in the released code, and input noise: with tens of sequences
            # instead of the paper's hours, a network trained on clean one-step pairs drifts
            # off its data within a second of closed-loop synthesis.
            ncfg = PoseNetConfig(encoders={"C": (64, 64), "JT": (256, 256), "G": (64, 64),
                                           "I": (128, 128), "E": (128, 128)},
                                 num_experts=6, gating_hidden=(64, 64), expert_hidden=(256, 256),
                                 dropout=0.3, gating_dropout=0.3)
        else:
            ncfg = PoseNetConfig()
        # cpu: the last 4 epochs closed loop (8-frame windows); without them PoseNet learns
        # to ignore C+ and its hands go where the pose alone takes them (see TrainConfig).
        kw = dict(lr=1e-3 if ci else 5e-4 if cpu else 1e-4, epochs=6 if ci else 16 if cpu
                  else 150, input_noise=0.3 if cpu else 0.0, rollout=8 if cpu else 0,
                  rollout_epochs=4 if cpu else 0)
    else:
        if ci:
            ncfg = ContactNetConfig(condition_encoder=(64, 32, 16), encoder_hidden=(32, 16),
                                    decoder_hidden=(32, 16))
        elif cpu:
            ncfg = ContactNetConfig(condition_encoder=(256, 128, 32), encoder_hidden=(64, 32),
                                    decoder_hidden=(64, 32))
        else:
            ncfg = ContactNetConfig()
        # Paper: Adam 1e-3 for 150 epochs, no schedule mentioned -> constant rate. ci has only
        # ~10 contact sets, so small batches give it a few steps per epoch.
        kw = dict(lr=3e-3 if ci else 1e-3, cosine=False,
                  epochs=15 if ci else 100 if cpu else 150, batch_size=4 if ci else 8 if cpu
                  else 32)
    if epochs is not None:
        if epochs < 1:
            raise ValueError(f"epochs must be at least 1, got {epochs}")
        kw["epochs"] = epochs
    return TrainConfig(net=net, preset=preset, network=json.loads(json.dumps(
        dataclasses.asdict(ncfg))), **kw)


# --------------------------------------------------------------------------------------------
# Per-network tasks: datasets, model, loss
# --------------------------------------------------------------------------------------------


def pose_inputs(groups: Mapping[str, Tensor], net: str = "pose") -> dict[str, Tensor]:
    """PoseNet inputs from normalised feature groups: the encoder inputs (C, JT, G, I, E, each
    the concatenation of :data:`ENCODER_GROUPS`) and the gating features, all (B, dim)."""
    out = {enc: torch.cat([groups[g] for g in names], dim=-1)
           for enc, names in ENCODER_GROUPS[net].items()}
    out.update({g: groups[g] for g in GATING_GROUPS[net]})
    return out


@dataclasses.dataclass
class _Task:
    model: nn.Module
    train_ds: torch.utils.data.Dataset
    val_ds: torch.utils.data.Dataset
    stats: FeatureStats
    loss: Callable[[nn.Module, Any, int, bool, torch.Generator | None], dict[str, Tensor]]
    meta: dict[str, Any]
    #: PoseNet's closed-loop training windows for the last ``rollout_epochs`` epochs.
    rollout_ds: torch.utils.data.Dataset | None = None


def _to(x: Any, device: torch.device) -> Any:
    if isinstance(x, Tensor):
        return x.to(device, non_blocking=True)
    if isinstance(x, dict):
        return {k: _to(v, device) for k, v in x.items()}
    if isinstance(x, (tuple, list)):
        return type(x)(_to(v, device) for v in x)
    return x


def _control_stats(cache: FeatureCache, rows: np.ndarray) -> FeatureStats:
    """ControlNet normalisation. The straight-line input and the predicted trajectory share one
    scalar scale and no offset: scheduled sampling copies predictions into the line's columns
    and Eq. 2's regulariser compares the two, so both must live in the same space, and zero
    (= no contact target) must stay zero. Phases are already in [0, 1]; the pose is z-scored."""
    stats = fit_stats(cache, ["joint_positions"], rows)
    traj = cache.read(["next_control_positions"], rows)["next_control_positions"]
    nonzero = traj[traj != 0]
    scale = float(np.sqrt(np.mean(nonzero.astype(np.float64) ** 2))) if nonzero.size else 1.0
    scale = max(scale, cache.config.min_std)
    for g in ("control_line", "next_control_positions", "hand_phases", "next_control_phases"):
        dim = cache.dims[g]
        stats.mean[g] = np.zeros(dim, np.float32)
        is_traj = g in ("control_line", "next_control_positions")
        stats.std[g] = np.full(dim, scale if is_traj else 1.0, np.float32)
    return stats


def _control_task(cache: FeatureCache, train: np.ndarray, val: np.ndarray, cfg: TrainConfig,
                  stats: FeatureStats | None) -> _Task:
    ncfg = network_config(cfg)
    assert isinstance(ncfg, ControlNetConfig)
    stats = stats or _control_stats(cache, cache.sequence_rows(train))
    d = cache.dims
    traj, phase = d["next_control_positions"], d["next_control_phases"]
    if d["control_line"] != traj:
        raise ValueError(f"{cache.path}: control_line ({d['control_line']}) and "
                         f"next_control_positions ({traj}) must match column for column")
    dims = dict(pose_dim=d["joint_positions"], control_dim=d["control_line"] + d["hand_phases"],
                out_dim=traj + phase)
    model = ControlNet(config=ncfg, **dims)
    stride = cfg.stride or None
    stream = cfg.stream_rows > 0
    train_ds = WindowDataset(cache, cfg.window, stride, train, stats=stats, stream=stream)
    val_ds = WindowDataset(cache, cfg.window, stride, val, stats=stats, stream=stream)
    if len(train_ds) == 0:
        raise ValueError(f"{cache.path}: no training sequence has {cfg.window} frames for "
                         "ControlNet windows")
    traj_cols, phase_cols = slice(0, traj), slice(traj, traj + phase)

    def loss(model: nn.Module, batch: dict[str, Tensor], epoch: int, training: bool,
             gen: torch.Generator | None) -> dict[str, Tensor]:
        assert isinstance(model, ControlNet)
        control = torch.cat([batch["control_line"], batch["hand_phases"]], -1)
        target = torch.cat([batch["next_control_positions"], batch["next_control_phases"]], -1)
        # Validation runs at the teacher probability training ends at (closed loop once
        # scheduled sampling has run its course, as at runtime), whatever the epoch, so its
        # loss is comparable across epochs while the training probability falls.
        p = scheduled_sampling_probability(epoch if training else cfg.epochs, ncfg)
        out = rollout(model, batch["joint_positions"], control, p, control_traj=traj_cols,
                      out_traj=traj_cols, generator=gen).out
        terms = control_loss(out, target, batch["control_line"], ncfg.loss_weights,
                             traj_cols=traj_cols, phase_cols=phase_cols, reg=ncfg.reg)
        return {"loss": terms.total, "traj": terms.traj, "phase": terms.phase, "reg": terms.reg,
                "p_teacher": torch.tensor(p)}

    return _Task(model, train_ds, val_ds, stats, loss, {"model_args": dims})


def _pose_task(cache: FeatureCache, train: np.ndarray, val: np.ndarray, cfg: TrainConfig,
               stats: FeatureStats | None) -> _Task:
    ncfg = network_config(cfg)
    assert isinstance(ncfg, PoseNetConfig)
    spec = layout(cache.config)[_LAYOUT_KEY[cfg.net]]
    missing = [g for g in [*spec["inputs"], *spec["targets"]] if g not in cache.dims]
    if missing:
        raise ValueError(f"{cache.path}: feature groups {missing} missing (cache built by an "
                         "older couch? delete it to rebuild)")
    if cfg.control_source not in CONTROL_SOURCES:
        raise ValueError(f"unknown control_source {cfg.control_source!r}; choose from "
                         f"{', '.join(CONTROL_SOURCES)}")
    groups_in, groups_out = list(spec["inputs"]), list(spec["targets"])
    stats = stats or fit_stats(cache, groups_in + groups_out, cache.sequence_rows(train))
    d = cache.dims
    inputs = {enc: sum(d[g] for g in names) for enc, names in ENCODER_GROUPS[cfg.net].items()}
    gating = {g: d[g] for g in GATING_GROUPS[cfg.net]}
    out_dim = sum(d[g] for g in groups_out)
    model = PoseNet(inputs, gating, out_dim, ncfg)
    stream = cfg.stream_rows > 0
    index_sets = [cache.sequence_rows(train), cache.sequence_rows(val)]
    if stream:
        train_ds, val_ds = (FrameDataset.streamed(cache, groups_in, groups_out, rows, stats)
                            for rows in index_sets)
    else:
        train_ds, val_ds = FrameDataset.splits(cache, groups_in, groups_out, index_sets, stats)
    widths = [d[g] for g in groups_out]
    rollout_ds = None
    if cfg.rollout_epochs > 0:
        if cfg.rollout < 2:
            raise ValueError(f"rollout_epochs {cfg.rollout_epochs} needs rollout windows of at "
                             f"least 2 frames, got rollout={cfg.rollout}")
        groups = groups_in + groups_out
        # in memory, the windows read the frame datasets' rows (the same rows, normalised
        # alike); streamed, each reads its own blocks
        rollout_ds = WindowDataset(cache, cfg.rollout, max(1, cfg.rollout // 2), train,
                                   groups=groups, stats=stats, stream=stream,
                                   rows=None if stream else {**train_ds.inputs,
                                                             **train_ds.targets})
        if len(rollout_ds) == 0:
            raise ValueError(f"{cache.path}: no training sequence has {cfg.rollout} frames for "
                             "PoseNet's closed-loop windows (rollout)")
        val_ds = WindowDataset(cache, cfg.rollout, cfg.rollout, val, groups=groups, stats=stats,
                               stream=stream,
                               rows=None if stream else {**val_ds.inputs, **val_ds.targets})
    feedback = pose_feedback(groups_out, widths, stats)
    if cfg.hand_weight <= 0:
        raise ValueError(f"hand_weight must be positive, got {cfg.hand_weight}")
    weights = output_weights(groups_out, widths, cfg.hand_weight)

    def noisy(x: dict[str, Tensor], gen: torch.Generator | None) -> dict[str, Tensor]:
        x = dict(x)
        for g in FED_BACK_GROUPS:
            if g in x:
                noise = torch.randn(x[g].shape, generator=gen, device=x[g].device)
                x[g] = x[g] + cfg.input_noise * noise.to(x[g].dtype)
        return x

    def loss(model: nn.Module, batch: Any, epoch: int, training: bool,
             gen: torch.Generator | None) -> dict[str, Tensor]:
        if isinstance(batch, dict):  # a closed-loop window (B, rollout, dim) per group
            target = torch.cat([batch[g] for g in groups_out], -1)  # (B, rollout, out)
            steps = target.shape[1]
            x = {g: batch[g][:, 0] for g in groups_in}
            preds = []
            for k in range(steps):
                pred, _ = model(pose_inputs(noisy(x, gen) if training and cfg.input_noise > 0
                                            else x, cfg.net))
                preds.append(pred)
                if k + 1 < steps:
                    # The fed-back state is not differentiated through: each frame learns to
                    # correct the state it is given, as scheduled sampling does.
                    x = feedback(pred.detach(), x, {g: batch[g][:, k + 1] for g in groups_in})
            err = torch.stack(preds, 1) - target
        else:
            x, y = batch
            if training and cfg.input_noise > 0:
                x = noisy(x, gen)
            pred, _ = model(pose_inputs(x, cfg.net))
            err = pred - torch.cat([y[g] for g in groups_out], -1)
        terms = {"loss": torch.mean(err ** 2 * weights.to(err.device))}
        # Per-group MSE components (which targets are hard, unweighted) from the same
        # prediction.
        for g, part in zip(groups_out, torch.split(err.detach() ** 2, widths, -1), strict=True):
            terms[g] = part.mean()
        return terms

    meta = {"model_args": {"inputs": inputs, "gating_inputs": gating, "out_dim": out_dim},
            "groups_in": groups_in, "groups_out": groups_out}
    return _Task(model, train_ds, val_ds, stats, loss, meta, rollout_ds)


#: Joints whose next positions and rotations ``TrainConfig.hand_weight`` weighs: the hand
#: joints are not among J's 22, the wrists' position and rotation place them.
WEIGHTED_JOINTS = (JOINT_INDEX["left_wrist"], JOINT_INDEX["right_wrist"])


def output_weights(groups_out: Sequence[str], widths: Sequence[int], hand_weight: float
                   ) -> Tensor:
    """(out_dim,) per-column loss weights of PoseNet's concatenated targets: ``hand_weight``
    on the :data:`WEIGHTED_JOINTS`' columns of ``next_joint_positions`` (3 each) and
    ``next_joint_rotations`` (6D, 6 each), 1 elsewhere."""
    w = torch.ones(int(sum(widths)))
    start = dict(zip(groups_out, np.cumsum([0, *widths[:-1]]).tolist(), strict=True))
    for group, size in (("next_joint_positions", 3), ("next_joint_rotations", 6)):
        if group in start:
            for j in WEIGHTED_JOINTS:
                w[start[group] + size * j:start[group] + size * (j + 1)] = hand_weight
    return w


def pose_feedback(groups_out: Sequence[str], widths: Sequence[int], stats: FeatureStats
                  ) -> Callable[[Tensor, Mapping[str, Tensor], Mapping[str, Tensor]],
                                dict[str, Tensor]]:
    """What the runtime feeds back, in training's units: a function ``feed(pred, x, nxt)`` from
    PoseNet's normalised prediction (B, sum(widths)) (its ``groups_out`` concatenated), the
    normalised inputs ``x`` it was made from and the data's inputs ``nxt`` of the next frame
    (each (B, dim)) to the next frame's inputs as the runtime builds them
    (:class:`couch.synthesis.controller.Synthesizer`): ``nxt`` with

    - J from the next-pose outputs (:data:`POSE_FEEDBACK`);
    - T's present and future samples from ``future_trajectory``, tidied as at runtime
      (:func:`~couch.synthesis.features.tidy_future_trajectory`; its past samples stay the
      data's: the runtime takes them from the roots it went through);
    - the global phase advanced by ``global_phase_update`` (:func:`~couch.synthesis.features.
      advance_phase`), 1 once the predicted pelvis contact or the next sit label passes 0.5.

    Measured: fine-tuned for 4 closed-loop epochs (12 held-out chairs x 8 trials, chair seeds
    0 / 1), ACE 4.95 / 5.78 cm with T and the phase fed back, 5.74 / 6.73 with J alone; trained
    from scratch (384 trials), within the noise of J alone (``docs/synthesis-history.md``).
    """
    columns, start = {}, 0
    for g, w in zip(groups_out, widths, strict=True):
        columns[g] = slice(start, start + w)
        start += w
    missing = [g for g in (*POSE_FEEDBACK, *_FEEDBACK_READS) if g not in columns]
    if missing:
        raise ValueError(f"PoseNet outputs {missing} missing: nothing to feed back")

    def moments(g: str, cols: slice = slice(None)) -> tuple[Tensor, Tensor]:
        return (torch.as_tensor(stats.mean[g][cols], dtype=torch.float32),
                torch.as_tensor(stats.std[g][cols], dtype=torch.float32))

    # input = (output * std_out + mean_out - mean_in) / std_in, as one scale and shift
    maps = {}
    for out_g, in_g in POSE_FEEDBACK.items():
        (m_out, s_out), (m_in, s_in) = moments(out_g), moments(in_g)
        maps[in_g] = (columns[out_g], s_out / s_in, (m_out - m_in) / s_in)
    n_fut = widths[list(groups_out).index("future_trajectory")]
    future_out, future_in = moments("future_trajectory"), moments("trajectory",
                                                                 slice(-n_fut, None))
    phase_in, update_out = moments("global_phase"), moments("global_phase_update")
    contacts_out = moments("next_contacts")
    pelvis = CONTACT_NAMES.index("pelvis")

    def denorm(pred: Tensor, g: str, m: tuple[Tensor, Tensor]) -> Tensor:
        return pred[:, columns[g]] * m[1].to(pred.device) + m[0].to(pred.device)

    def feed(pred: Tensor, x: Mapping[str, Tensor], nxt: Mapping[str, Tensor]
             ) -> dict[str, Tensor]:
        out = dict(nxt)
        for g, (cols, scale, shift) in maps.items():
            out[g] = pred[:, cols] * scale.to(pred.device) + shift.to(pred.device)
        fut = tidy_future_trajectory(
            denorm(pred, "future_trajectory", future_out).reshape(len(pred), -1, 12))
        m, sd = (t.to(pred.device) for t in future_in)
        out["trajectory"] = torch.cat([nxt["trajectory"][:, :-n_fut],
                                       (fut.reshape(len(pred), -1) - m) / sd], -1)
        m, sd = (t.to(pred.device) for t in phase_in)
        phase = x["global_phase"] * sd + m
        seated = ((denorm(pred, "next_contacts", contacts_out)[:, pelvis:pelvis + 1] > 0.5)
                  | (fut[:, 0, 9 + SIT:10 + SIT] > 0.5))
        update = denorm(pred, "global_phase_update", update_out)
        phase = torch.where(seated, torch.ones_like(phase), torch.remainder(phase + update, 1.0))
        out["global_phase"] = (phase - m) / sd
        return out

    return feed


def _contact_stats(cache: FeatureCache, rows: np.ndarray) -> FeatureStats:
    """ContactNet normalisation: the condition z-scored; each hand's contact coordinates
    z-scored over the rows where that hand has a target (masked hands are zeros, not data)."""
    stats = fit_stats(cache, ["contact_condition"], rows)
    c = cache.rows("hand_contacts", rows).reshape(len(rows), 2, 3).astype(np.float64)
    m = cache.rows("hand_mask", rows) > 0.5
    mean, std = np.zeros((2, 3)), np.ones((2, 3))
    for h in range(2):
        if m[:, h].any():
            mean[h] = c[m[:, h], h].mean(0)
            std[h] = np.maximum(c[m[:, h], h].std(0), cache.config.min_std)
    stats.mean["hand_contacts"] = mean.reshape(6).astype(np.float32)
    stats.std["hand_contacts"] = std.reshape(6).astype(np.float32)
    return stats


def _contact_task(cache: FeatureCache, train: np.ndarray, val: np.ndarray, cfg: TrainConfig,
                  stats: FeatureStats | None) -> _Task:
    ncfg = network_config(cfg)
    assert isinstance(ncfg, ContactNetConfig)
    train_rows, val_rows = contact_rows(cache, train), contact_rows(cache, val)
    if len(train_rows) == 0:
        raise ValueError(f"{cache.path}: no training sequence has a hand contact target; "
                         "ContactNet has nothing to learn")
    stats = stats or _contact_stats(cache, train_rows)
    cond_dim, contact_dim = cache.dims["contact_condition"], cache.dims["hand_contacts"]
    model = ContactNet(cond_dim, contact_dim, ncfg)
    groups_in, groups_out = ["contact_condition"], ["hand_contacts", "hand_mask"]
    train_ds = FrameDataset(cache, groups_in, groups_out, train_rows, stats)
    val_ds = FrameDataset(cache, groups_in, groups_out, val_rows, stats)

    def loss(model: nn.Module, batch: Any, epoch: int, training: bool,
             gen: torch.Generator | None) -> dict[str, Tensor]:
        x, y = batch
        mask = y["hand_mask"].repeat_interleave(3, dim=-1)  # (B, 6): one flag per coordinate
        c = y["hand_contacts"] * mask  # masked hands: zero target (normalised space)
        c_hat, mu, logvar = model(c, x["contact_condition"])
        # Eq. 4 with masked hands left out of the reconstruction.
        recon = ((c_hat - c) ** 2 * mask).sum(-1).mean()
        kl = kl_divergence(mu, logvar).mean()
        return {"loss": recon + ncfg.beta * kl, "recon": recon, "kl": kl}

    meta = {"model_args": {"cond_dim": cond_dim, "contact_dim": contact_dim},
            "samples": {"train": len(train_rows), "val": len(val_rows)}}
    return _Task(model, train_ds, val_ds, stats, loss, meta)


_TASKS = {"control": _control_task, "contact": _contact_task,
          **dict.fromkeys(POSE_NETS, _pose_task)}


def _build_model(net: str, cfg: TrainConfig, args: Mapping[str, Any]) -> nn.Module:
    ncfg = network_config(cfg)
    if net == "control":
        return ControlNet(config=ncfg, **args)  # type: ignore[arg-type]
    if net in POSE_NETS:
        return PoseNet(args["inputs"], args["gating_inputs"], args["out_dim"],
                       ncfg)  # type: ignore[arg-type]
    return ContactNet(args["cond_dim"], args["contact_dim"], ncfg)  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# Training loop
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass
class NetResult:
    """Outcome of one network's training (losses per epoch from its log)."""

    net: str
    dir: Path
    epochs: int
    resumed_from: int  #: last epoch finished before this call (0: fresh start)
    history: list[dict[str, float]]
    seconds: float  #: wall time of this call's epochs
    model: nn.Module | None = None

    @property
    def train_loss(self) -> list[float]:
        return [h["train_loss"] for h in self.history]

    @property
    def val_loss(self) -> list[float]:
        return [h["val_loss"] for h in self.history]


@dataclasses.dataclass
class TrainResult:
    """What :func:`train` did: the cache and each network's :class:`NetResult`."""

    run_dir: Path
    cache_path: Path
    cache_hit: bool
    skipped: list[tuple[str, str]]
    nets: dict[str, NetResult]


def _seed_all(seed: int) -> None:
    # numpy randomness (the split) uses np.random.default_rng(seed); only torch is global.
    torch.manual_seed(seed)


def _epoch_seed(seed: int, epoch: int) -> int:
    # Distinct, reproducible stream per (seed, epoch): what makes resume == uninterrupted.
    return (seed * 1_000_003 + epoch * 7919) % 2**63


def _rng_state() -> dict[str, Any]:
    state: dict[str, Any] = {"torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: Mapping[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(list(state["cuda"]))


def _save(obj: dict[str, Any], path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def _run_epoch(task: _Task, loader: Iterable[Any], epoch: int, training: bool,
               optimizer: torch.optim.Optimizer | None, cfg: TrainConfig, device: torch.device,
               gen: torch.Generator | None, bar: bool, desc: str) -> dict[str, float]:
    """Mean of each loss term over the epoch's samples (nan for an empty loader)."""
    model = task.model
    model.train(training)
    sums: dict[str, float] = {}
    count = 0
    with torch.set_grad_enabled(training):
        for batch in tqdm(loader, desc=desc, leave=False, disable=not bar, unit="batch"):
            batch = _to(batch, device)
            terms = task.loss(model, batch, epoch, training, gen)
            if training:
                assert optimizer is not None
                optimizer.zero_grad(set_to_none=True)
                terms["loss"].backward()
                if cfg.grad_clip > 0:
                    nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
                optimizer.step()
            n = _batch_size(batch)
            count += n
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach()) * n
    if count == 0:
        return {}
    return {k: v / count for k, v in sums.items()}


def _batch_size(batch: Any) -> int:
    first = batch[0] if isinstance(batch, tuple) else batch
    return int(next(iter(first.values())).shape[0])


def _write_log(path: Path, history: list[dict[str, float]]) -> None:
    """log.csv rewritten from the checkpoint's history: exactly one row per finished epoch."""
    keys: list[str] = []
    for row in history:
        keys += [k for k in row if k not in keys]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=keys, restval="")
    writer.writeheader()
    for row in history:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue())


def _plot(path: Path, history: list[dict[str, float]], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")  # headless; never opens a window
    import matplotlib.pyplot as plt

    epochs = [h["epoch"] for h in history]
    fig, (ax, ax_lr) = plt.subplots(1, 2, figsize=(9, 3.5))
    ax.plot(epochs, [h["train_loss"] for h in history], "o-", label="train")
    val = [h["val_loss"] for h in history]
    if any(math.isfinite(v) for v in val):
        ax.plot(epochs, val, "s-", label="validation")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss")
    if all(h["train_loss"] > 0 for h in history):
        ax.set_yscale("log")
    ax.legend()
    ax.set_title(title)
    ax_lr.plot(epochs, [h["lr"] for h in history], "-")
    ax_lr.set_xlabel("epoch")
    ax_lr.set_ylabel("learning rate")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80)
    plt.close(fig)


def rows_memory(net: str, cache: FeatureCache, sequences: np.ndarray, cfg: TrainConfig) -> int:
    """Bytes ``net``'s datasets copy into memory for these sequences (float32 rows of the
    groups it reads; 0 when ``cfg`` streams them, and for ContactNet's few samples). Building
    them peaks at ~:data:`BUILD_PEAK` times this."""
    if net == "contact" or cfg.stream_rows > 0:
        return 0
    if net == "control":
        groups: Sequence[str] = WindowDataset.DEFAULT_GROUPS
    else:
        spec = layout(cache.config)[_LAYOUT_KEY[net]]
        groups = list(dict.fromkeys([*spec["inputs"], *spec["targets"]]))
    width = sum(cache.dims.get(g, 0) for g in groups)
    return int(cache.lengths()[np.asarray(sequences, dtype=np.int64)].sum()) * width * 4


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux ``MemAvailable``), None where
    ``/proc/meminfo`` does not say."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _train_net(net: str, cache: FeatureCache, train_seqs: np.ndarray, val_seqs: np.ndarray,
               cfg: TrainConfig, out: Path, *, device: torch.device, seed: int, resume: bool,
               progress: bool, stop_after: int | None, keep_epochs: bool = False,
               extra_meta: Mapping[str, Any] | None = None) -> NetResult:
    out.mkdir(parents=True, exist_ok=True)
    ck_path, best_path, stats_path = out / "checkpoint.pt", out / "best.pt", out / "stats.npz"
    checkpoint = None
    if resume and ck_path.is_file():
        try:
            checkpoint = torch.load(ck_path, map_location="cpu", weights_only=True)
        except Exception as e:  # any unreadable checkpoint gets the same message
            raise ValueError(f"{ck_path}: cannot read checkpoint ({e}); use --no-resume") from e
        saved_meta = json.loads(checkpoint["meta"])
        # A setting added after the run was saved counts as its default.
        saved = {**{f.name: f.default for f in dataclasses.fields(TrainConfig)
                    if f.default is not dataclasses.MISSING}, **saved_meta["train_config"]}
        now = json.loads(cfg.to_json())
        if saved != now:
            # both sides' keys: a saved setting this couch no longer has counts as different
            diff = sorted(k for k in {*saved, *now} if saved.get(k) != now.get(k))
            raise ValueError(f"{ck_path}: was trained with different settings ({', '.join(diff)});"
                             " use --no-resume or another run folder")
        saved_features = feature_config_from_json(json.dumps(saved_meta["feature_config"]))
        if saved_features != cache.config:
            a, b = dataclasses.asdict(saved_features), dataclasses.asdict(cache.config)
            diff = sorted(k for k in a if a[k] != b[k])
            raise ValueError(f"{ck_path}: was trained on other features ({', '.join(diff)}); "
                             "use --no-resume or another run folder")
    stats = FeatureStats.load(stats_path) if checkpoint is not None and stats_path.is_file() \
        else None

    need, have = rows_memory(net, cache, np.concatenate([train_seqs, val_seqs]), cfg), \
        available_memory()
    if have is not None and BUILD_PEAK * need > have:
        # an OOM kill says nothing; say it before the copy is attempted
        print(f"couch-train: warning: {net}'s rows take ~{need / 2**30:.1f} GB copied into "
              f"memory (~{BUILD_PEAK * need / 2**30:.1f} GB while copied) and "
              f"{have / 2**30:.1f} GB is available; --stream (stream_rows) reads them from the "
              "feature cache instead", file=sys.stderr)
    _seed_all(seed)  # model initialisation
    task = _TASKS[net](cache, train_seqs, val_seqs, cfg, stats)
    task.stats.save(stats_path)
    model = task.model.to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    scheduler: torch.optim.lr_scheduler.LRScheduler = (
        torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=cfg.epochs,
                                                   eta_min=cfg.lr_min)
        if cfg.cosine else torch.optim.lr_scheduler.ConstantLR(optimizer, 1.0, total_iters=0))
    meta = {"net": net, "train_config": json.loads(cfg.to_json()), **task.meta,
            "feature_config": json.loads(json.dumps(dataclasses.asdict(cache.config))),
            "cache": str(cache.path), "cache_hash": cache.source_hash,
            # sources, not names: folders of simulated sequences repeat the names
            "split": {"train": [cache.sources[i] for i in train_seqs],
                      "val": [cache.sources[i] for i in val_seqs]}, **(extra_meta or {})}
    # Not sort_keys: PoseNet concatenates its encoder and gating groups in dict order.
    meta_json = json.dumps(meta)

    history: list[dict[str, float]] = []
    best_val = math.inf
    start = 1
    if checkpoint is not None:
        model.load_state_dict(checkpoint["model"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        scheduler.load_state_dict(checkpoint["scheduler"])
        _set_rng_state(checkpoint["rng"])
        history = [dict(h) for h in checkpoint["history"]]
        best_val = float(checkpoint["best_val"])
        start = int(checkpoint["epoch"]) + 1
    resumed_from = start - 1

    bs, block = cfg.batch_size, cfg.stream_rows
    loader_gen = torch.Generator()
    train_loader = make_loader(task.train_ds, bs, True, loader_gen, block)
    val_loader = make_loader(task.val_ds, bs, False, None, block)
    rollout_loader = (None if task.rollout_ds is None else
                      make_loader(task.rollout_ds, bs, True, loader_gen, block))
    first_rollout = cfg.epochs - cfg.rollout_epochs + 1
    roll_gen = torch.Generator(device=device)
    t_call = time.perf_counter()
    last = cfg.epochs if stop_after is None else min(cfg.epochs, stop_after)
    for epoch in range(start, last + 1):
        t0 = time.perf_counter()
        es = _epoch_seed(seed, epoch)
        torch.manual_seed(es)
        loader_gen.manual_seed(es + 1)
        roll_gen.manual_seed(es + 2)
        lr = optimizer.param_groups[0]["lr"]
        bar = progress
        closed = rollout_loader is not None and epoch >= first_rollout
        if closed and epoch == first_rollout:
            # best.pt comes from the closed-loop epochs: the one-step ones before them are a
            # warm-up whose closed-loop validation can be lower while their hands ignore C+.
            best_val = math.inf
        tr = _run_epoch(task, rollout_loader if closed else train_loader, epoch, True,
                        optimizer, cfg, device, roll_gen, bar,
                        f"{net} {epoch}/{cfg.epochs} train{' (closed loop)' if closed else ''}")
        # Validation draws its own fixed noise (ContactNet's z, rollout Bernoullis) without
        # touching the training streams, so it is comparable across epochs.
        with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
            torch.manual_seed(seed + 12345)
            val_gen = torch.Generator(device=device).manual_seed(seed + 54321)
            va = _run_epoch(task, val_loader, epoch, False, None, cfg, device, val_gen, bar,
                            f"{net} {epoch}/{cfg.epochs} val")
        scheduler.step()
        row: dict[str, float] = {"epoch": epoch, "lr": lr,
                                 "train_loss": tr["loss"], "val_loss": va.get("loss", math.nan)}
        row.update({f"train_{k}": v for k, v in tr.items() if k != "loss"})
        row.update({f"val_{k}": v for k, v in va.items() if k != "loss"})
        row["seconds"] = time.perf_counter() - t0
        history.append(row)
        # Without a validation set the training loss picks the best model.
        score = row["val_loss"] if math.isfinite(row["val_loss"]) else row["train_loss"]
        state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
        record = {"model": state, "epoch": epoch, "val_loss": score, "meta": meta_json}
        if score < best_val:
            best_val = score
            _save(record, best_path)
        if keep_epochs:
            _save(record, epoch_path(out, epoch))
        _save({"model": state, "optimizer": optimizer.state_dict(),
               "scheduler": scheduler.state_dict(), "epoch": epoch, "best_val": best_val,
               "history": history, "rng": _rng_state(), "meta": meta_json}, ck_path)
        _write_log(out / "log.csv", history)
        if progress:
            print(f"{net} epoch {epoch}/{cfg.epochs}: train {row['train_loss']:.4g} "
                  f"val {row['val_loss']:.4g} lr {lr:.3g} ({row['seconds']:.1f} s)")
    if history:
        _write_log(out / "log.csv", history)
        _plot(out / "curves.png", history, f"{net} ({cfg.preset})")
    return NetResult(net, out, int(history[-1]["epoch"]) if history else 0, resumed_from,
                     history, time.perf_counter() - t_call, model)


def train(data_paths: Sequence[str | os.PathLike], run_dir: str | os.PathLike, *,
          net: str = "all", preset: str = "paper", epochs: int | None = None,
          device: str = "cpu", seed: int = 0, resume: bool = True, progress: bool = True,
          threads: int | None = 1, stop_after: int | None = None,
          configs: Mapping[str, TrainConfig] | None = None,
          features: FeatureConfig | None = None, keep_epochs: bool = False,
          stream_rows: int | None = None) -> TrainResult:
    """Train ``net`` (control | pose | contact | baseline | nsm | all) on the sequences under
    ``data_paths``, writing everything into ``run_dir`` (see the module docstring).

    Args:
        data_paths: files/folders for :func:`couch.synthesis.data.find_sequences`.
        run_dir: output folder (created).
        net: which network, or "all" (:data:`ALL_NETS`: control, pose, contact, baseline in
            that order; "nsm", the plain NSM of the paper's Table 2, only when named).
        preset: "paper" or "ci" (:func:`preset_config`).
        epochs: override the preset's epochs.
        device: torch device string ("cpu", "cuda", "cuda:1").
        seed: seeds the split, initialisation, shuffling and sampling.
        resume: continue each network from its ``checkpoint.pt`` (last finished epoch).
        progress: tqdm bars and per-epoch lines.
        threads: torch CPU threads during training (1 is fastest for these small nets on few
            cores); None leaves torch's setting alone.
        stop_after: finish at most this epoch in this call (time-sliced jobs; resume later).
        configs: per-net :class:`TrainConfig` overriding the preset.
        features: the features' settings (default :class:`FeatureConfig`); the run's cache is
            rebuilt when they differ from the ones it was built with.
        keep_epochs: also keep every epoch's model (``RUN/<net>/epochs/NNN.pt``, loadable with
            ``load_trained(..., which=N)``), so that ``couch-eval --which`` can score epochs by
            closed-loop synthesis rather than by validation loss (README, *Results so far*).
            PoseNet's is ~11 MB per epoch.
        stream_rows: set every network's ``TrainConfig.stream_rows`` (read the training rows
            from the cache file N rows at a time instead of copying them into memory; 0: copy);
            None keeps the configs' (0 in every preset).
    Raises:
        FileNotFoundError / ValueError / couch.schema.SchemaError naming the offending file.
    """
    nets = list(ALL_NETS) if net == "all" else [net]
    if any(n not in NETS for n in nets):
        raise ValueError(f"unknown net {net!r}; choose from {', '.join(NETS)} or all")
    cfgs = {n: (configs or {}).get(n) or preset_config(n, preset, epochs) for n in nets}
    if stream_rows is not None:
        if stream_rows < 0:
            raise ValueError(f"stream_rows must not be negative, got {stream_rows}")
        cfgs = {n: dataclasses.replace(c, stream_rows=int(stream_rows)) for n, c in cfgs.items()}
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested but CUDA is not available")
    run = Path(run_dir)
    refs = find_sequences(data_paths)
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(max(1, int(threads)))
    try:
        cache = build_cache(refs, run / "features.h5", features, progress=progress)
        if progress:
            state = "reused" if cache.hit else "built"
            print(f"{run / 'features.h5'}: {state}, {cache.num_sequences} sequences, "
                  f"{cache.num_rows} rows, {len(cache.skipped)} skipped")
        results = {}
        for n in nets:
            cfg = cfgs[n]
            train_seqs, val_seqs = split(cache, cfg.val_fraction, seed, cfg.split_by)
            plans = (_use_controlnet_plans(cache, run, dev, progress)
                     if n == "pose" and cfg.control_source == "controlnet" else None)
            try:
                results[n] = _train_net(n, cache, train_seqs, val_seqs, cfg, run / n,
                                        device=dev, seed=seed, resume=resume,
                                        progress=progress, stop_after=stop_after,
                                        keep_epochs=keep_epochs, extra_meta=plans)
            finally:
                if plans is not None:  # the networks trained next read the data's
                    for g in CONTROL_GROUPS:
                        cache.restore(g)
    finally:
        torch.set_num_threads(old_threads)
    return TrainResult(run, cache.path, cache.hit, list(cache.skipped), results)


def _use_controlnet_plans(cache: FeatureCache, run: Path, device: torch.device,
                          progress: bool) -> dict[str, Any]:
    """Replace the cache's PoseNet control input by the run's ControlNet's replayed plans
    (``TrainConfig.control_source="controlnet"``); returns what PoseNet's meta records."""
    path = checkpoint_path(run, "control", "best")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (control_source 'controlnet' replays "
                                f"the run's ControlNet: train --net control first)")
    net, stats, _ = load_trained(run, "control", "best", str(device))
    if progress:
        print(f"replaying {path} over {cache.num_sequences} sequences for PoseNet's control "
              "input")
    assert isinstance(net, ControlNet)
    positions, phases = replay_plans(cache, net, stats, device=device)
    cache.replace("control_root_positions", positions)
    cache.replace("control_phases", phases)
    return {"control_plans": {"checkpoint": str(path), "replan": REPLAN_RADIUS}}


def epoch_path(net_dir: Path, epoch: int) -> Path:
    """Where ``keep_epochs`` keeps a network's model of ``epoch``: ``<net_dir>/epochs/NNN.pt``."""
    return net_dir / "epochs" / f"{epoch:03d}.pt"


def checkpoint_path(run_dir: str | os.PathLike, net: str, which: str | int = "best") -> Path:
    """The file of ``net``'s ``which`` checkpoint in ``run_dir``: "best" (``best.pt``), "last"
    (``checkpoint.pt``) or an epoch number (``epochs/NNN.pt``, kept with ``keep_epochs``).

    Raises:
        ValueError for another ``which``.
    """
    folder = Path(run_dir) / net
    if which == "best":
        return folder / "best.pt"
    if which == "last":
        return folder / "checkpoint.pt"
    if isinstance(which, int) and not isinstance(which, bool) and which >= 1:
        return epoch_path(folder, which)
    raise ValueError(f"checkpoint {which!r}: expected 'best', 'last' or an epoch number >= 1")


#: Which checkpoint of a run: "best", "last" or an epoch number, for every network at once or
#: per network (``{"pose": 14, "control": "best"}``, the others "best").
Which = str | int | Mapping[str, str | int]


def which_for(which: Which, net: str) -> str | int:
    """``net``'s checkpoint in ``which`` (a mapping's missing networks take "best")."""
    return which.get(net, "best") if isinstance(which, Mapping) else which


def parse_which(spec: str) -> Which:
    """A ``--which`` argument: "best", "last", an epoch number ("14"), or per network,
    comma-separated ``net=best|last|N`` ("pose=14,baseline=10"; unnamed networks "best").

    Raises:
        ValueError naming what is wrong.
    """
    def one(text: str) -> str | int:
        text = text.strip()
        if text in ("best", "last"):
            return text
        if text.isdigit() and int(text) >= 1:
            return int(text)
        raise ValueError(f"--which {spec!r}: {text!r} is not 'best', 'last' or an epoch "
                         f"number >= 1")

    if "=" not in spec:
        return one(spec)
    out: dict[str, str | int] = {}
    for part in spec.split(","):
        net, sep, value = part.partition("=")
        net = net.strip()
        if not sep or net not in NETS:
            raise ValueError(f"--which {spec!r}: {part!r} is not net=checkpoint with net one "
                             f"of {', '.join(NETS)}")
        if net in out:
            raise ValueError(f"--which {spec!r}: {net} given twice")
        out[net] = one(value)
    return out


def load_trained(run_dir: str | os.PathLike, net: str, which: str | int = "best",
                 device: str = "cpu") -> tuple[nn.Module, FeatureStats, dict[str, Any]]:
    """A trained network for inference: ``(model in eval mode, stats, meta)``.

    ``which`` is "best" (lowest validation loss), "last" (the last finished epoch) or an epoch
    number (its model, if the run kept every epoch's: ``keep_epochs``). ``meta``
    holds ``train_config`` (a :class:`TrainConfig` dict), ``model_args``, ``feature_config``,
    the split and, for PoseNets, ``groups_in``/``groups_out``. Inputs are normalised with
    ``stats`` and fed to PoseNets through :func:`pose_inputs`.
    """
    if net not in NETS:
        raise ValueError(f"unknown net {net!r}; choose from {', '.join(NETS)}")
    folder = Path(run_dir) / net
    path = checkpoint_path(run_dir, net, which)
    if not path.is_file():
        hint = ("was it trained that long, with --keep-epochs?" if isinstance(which, int)
                else f"has {net} been trained in {run_dir}?")
        raise FileNotFoundError(f"{path}: no such file ({hint})")
    ck = torch.load(path, map_location=device, weights_only=True)
    meta = json.loads(ck["meta"])
    if net in ENCODER_GROUPS:
        # A run trained on an older feature layout would fail at the first synthesised frame.
        spec = layout(feature_config_from_json(json.dumps(meta["feature_config"])))[
            _LAYOUT_KEY[net]]
        if list(meta["groups_in"]) != list(spec["inputs"]):
            raise ValueError(
                f"{path}: {net} was trained on feature groups {meta['groups_in']}, this couch "
                f"builds {list(spec['inputs'])} (the features changed since); retrain it with "
                f"couch-train")
    cfg = TrainConfig.from_json(json.dumps(meta["train_config"]))
    model = _build_model(net, cfg, meta["model_args"])
    model.load_state_dict(ck["model"])
    model.to(device).eval()
    return model, FeatureStats.load(folder / "stats.npz"), meta


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="couch-train",
        description="Train COUCH's ControlNet, PoseNet, ContactNet and the NSM+Control baseline "
                    "(and, asked by --net nsm, the plain NSM) on processed sequences (files, "
                    "augmented.h5 datasets or folders).")
    p.add_argument("data", nargs="+", help="processed .h5 files, augmented.h5 files or folders")
    p.add_argument("-o", "--output", required=True, help="run folder (checkpoints, logs, cache)")
    p.add_argument("--net", default="all", choices=[*NETS, "all"],
                   help="all: control, pose, contact and baseline; nsm (the plain NSM of the "
                        "paper's Table 2: the pose network without the contacts) only by name")
    p.add_argument("--preset", default="paper", choices=list(PRESETS))
    p.add_argument("--epochs", type=int, default=None, help="override the preset's epochs")
    p.add_argument("--rollout-epochs", type=int, default=None,
                   help="PoseNet, baseline and NSM: train the last N epochs closed loop (override "
                        "the preset's; 0: one-step pairs only)")
    p.add_argument("--rollout", type=int, default=None,
                   help="PoseNet, baseline and NSM: frames per closed-loop window (override the "
                        "preset's)")
    p.add_argument("--hand-weight", type=float, default=None, metavar="W",
                   help="PoseNet, baseline and NSM: loss weight of the wrists' next positions and "
                        "rotations, every other output 1 (default 1: a plain MSE)")
    p.add_argument("--control-source", default=None, choices=list(CONTROL_SOURCES),
                   help="PoseNet: its control input from the data's future hand paths (data, "
                        "the paper's and the default) or from the run's trained ControlNet "
                        "replayed over the same sequences (controlnet; train --net control "
                        "first)")
    p.add_argument("--control-line-end", type=float, default=None, metavar="M",
                   help="metres above each contact where ControlNet's straight line ends "
                        f"(default {FeatureConfig().control_line_end:g}; changes the features, "
                        "so the run's cache is rebuilt)")
    p.add_argument("--push-off-window", default=None, metavar="S|none",
                   help="seconds around a stand-up within which a hand's contact is its "
                        "push-off, no control target (default "
                        f"{FeatureConfig().push_off_window:g}; none: every contact is one, "
                        "as runs before session 49; changes the features)")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (default 1: fastest for these small nets)")
    p.add_argument("--no-resume", action="store_true",
                   help="start from scratch even if checkpoints exist")
    p.add_argument("--keep-epochs", action="store_true",
                   help="also keep every epoch's model (RUN/<net>/epochs/NNN.pt) to choose one "
                        "by synthesis: couch-eval --which")
    p.add_argument("--stream", type=int, nargs="?", const=STREAM_ROWS, default=None,
                   metavar="ROWS",
                   help="read the training rows from RUN/features.h5 as batches need them, "
                        f"ROWS rows at a time (default {STREAM_ROWS}), "
                        "instead of copying them into memory (for data larger than memory; "
                        "shuffles within blocks, so the weights differ from an in-memory run's "
                        "and one measured run synthesised worse: README)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``couch-train``; returns 0 on success, 2 on bad arguments or input."""
    args = parse_args(_parser(), argv)
    if isinstance(args, int):  # --help or a usage error argparse printed
        return args
    if args.epochs is not None and args.epochs < 1:
        print(f"couch-train: error: --epochs must be at least 1, got {args.epochs}",
              file=sys.stderr)
        return 2
    if args.threads < 1:
        print(f"couch-train: error: --threads must be at least 1, got {args.threads}",
              file=sys.stderr)
        return 2
    for flag, value in (("--rollout-epochs", args.rollout_epochs), ("--rollout", args.rollout)):
        if value is not None and value < 0:
            print(f"couch-train: error: {flag} must not be negative, got {value}",
                  file=sys.stderr)
            return 2
    if args.stream is not None and args.stream < 1:
        print(f"couch-train: error: --stream must be at least 1 row, got {args.stream}",
              file=sys.stderr)
        return 2
    if args.hand_weight is not None and not args.hand_weight > 0:
        print(f"couch-train: error: --hand-weight must be positive, got {args.hand_weight}",
              file=sys.stderr)
        return 2
    features: dict[str, float | None] = {}
    if args.control_line_end is not None:
        features["control_line_end"] = args.control_line_end
    if args.push_off_window is not None:
        try:
            window = (None if args.push_off_window.lower() == "none"
                      else float(args.push_off_window))
        except ValueError:
            window = -1.0
        if window is not None and not window >= 0:
            print(f"couch-train: error: --push-off-window must be seconds >= 0 or none, got "
                  f"{args.push_off_window!r}", file=sys.stderr)
            return 2
        features["push_off_window"] = window
    overrides = {k: v for k, v in (("rollout_epochs", args.rollout_epochs),
                                   ("rollout", args.rollout),
                                   ("hand_weight", args.hand_weight)) if v is not None}
    # the baseline has no ControlNet input: --control-source is PoseNet's alone
    pose_only = {} if args.control_source is None else {"control_source": args.control_source}
    configs = ({n: dataclasses.replace(preset_config(n, args.preset, args.epochs), **overrides,
                                       **(pose_only if n == "pose" else {}))
                for n in POSE_NETS} if overrides or pose_only else None)
    try:
        result = train(args.data, args.output, net=args.net, preset=args.preset,
                       epochs=args.epochs, device=args.device, seed=args.seed,
                       resume=not args.no_resume, progress=not args.quiet, threads=args.threads,
                       configs=configs, keep_epochs=args.keep_epochs,
                       stream_rows=args.stream,
                       features=FeatureConfig(**features) if features else None)
    except (FileNotFoundError, ValueError, SchemaError) as e:
        print(f"couch-train: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("couch-train: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    if not args.quiet:
        for name, r in result.nets.items():
            if r.history:
                h0, h1 = r.history[0], r.history[-1]
                print(f"{name}: epochs {r.epochs}, train {h0['train_loss']:.4g} -> "
                      f"{h1['train_loss']:.4g}, val {h0['val_loss']:.4g} -> "
                      f"{h1['val_loss']:.4g} ({r.seconds:.1f} s) in {r.dir}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
