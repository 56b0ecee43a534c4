"""The three networks of COUCH (Zhang et al., ECCV 2022, Sec. 4 and supplementary Sec. 2).

* :class:`ControlNet` (motion planning, Eq. 1-2): per frame, encodes the pose and the control
  signal (the straight-line points from each hand to its contact plus the hands' local phases),
  runs a 2-layer LSTM and predicts the hands' future trajectories relative to their contacts and
  their future local phases. :func:`rollout` unrolls it over a training window with scheduled
  sampling (:func:`scheduled_sampling_probability`), :func:`control_loss` is Eq. 2.
* :class:`PoseNet` (motion synthesis, Eq. 3): a mixture of experts in the style of
  Mode-Adaptive NNs / the Neural State Machine. Each named feature group has its own encoder
  (Table 5), a gating network maps a named set of gating features to expert coefficients, and
  the three-layer prediction network's expert weight tensors are blended per sample with those
  coefficients before being applied.
* :class:`ContactNet` (contact generation, Eq. 4): a conditional VAE over the two hand contacts
  given the chair-centric interaction feature, plus :func:`project_contacts`, the paper's
  post-process onto the chair surface (supplementary Sec. 3).

:class:`Normalizer` holds z-score statistics as buffers, so a checkpoint that contains it carries
its normalisation.

Feature layouts are not known here (the feature extraction is a separate module): every network
takes its input and output sizes as constructor arguments, and every function that needs to know
which columns are which (trajectory vs phase) takes the column ranges as arguments.

Defaults follow the paper; where the authors' released code (github.com/xz6014/couch) differs,
its choice is a config option and ``<Config>.released_code()`` returns a config with those
choices. Shapes use B = batch, L = sequence length, K = number of experts.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from couch.synthesis.precision import PackedLinear, Precision

__all__ = [
    "Activation",
    "Columns",
    "ContactNet",
    "ContactNetConfig",
    "ControlLoss",
    "ControlNet",
    "ControlNetConfig",
    "LSTMState",
    "Normalizer",
    "PoseNet",
    "PoseNetConfig",
    "Rollout",
    "control_loss",
    "kl_divergence",
    "linear_widths",
    "mlp",
    "project_contacts",
    "replace_columns",
    "rollout",
    "scheduled_sampling_probability",
]

Activation = Literal["elu", "leaky_relu", "relu"]
#: Column selection along the last axis: a ``slice``, a ``range`` or explicit indices.
Columns = slice | range | Sequence[int]
#: LSTM state ``(h, c)``, each (num_layers, B, hidden).
LSTMState = tuple[Tensor, Tensor]


# --------------------------------------------------------------------------------------------
# Normalisation and building blocks
# --------------------------------------------------------------------------------------------


class Normalizer(nn.Module):
    """Z-score normalisation with its statistics stored as buffers.

    Buffers ``mean`` and ``std`` are 1-D float32 of size ``dim``; being buffers they are saved in
    ``state_dict`` (and follow ``.to(device)``) but are not trained. ``std`` is floored at
    ``min_std`` when set, so constant features (e.g. an always-empty voxel) do not blow up.

    Args:
        dim: feature size D.
        mean, std: optional statistics (D,); identity (0 and 1) when omitted.
        min_std: floor applied to ``std``.
    """

    mean: Tensor
    std: Tensor

    def __init__(self, dim: int, mean: np.ndarray | Tensor | None = None,
                 std: np.ndarray | Tensor | None = None, *, min_std: float = 1e-4) -> None:
        super().__init__()
        if dim <= 0:
            raise ValueError(f"dim must be positive, got {dim}")
        self.dim = dim
        self.min_std = float(min_std)
        self.register_buffer("mean", torch.zeros(dim, dtype=torch.float32))
        self.register_buffer("std", torch.ones(dim, dtype=torch.float32))
        if mean is not None or std is not None:
            self.set_stats(mean if mean is not None else torch.zeros(dim),
                           std if std is not None else torch.ones(dim))

    @classmethod
    def from_stats(cls, mean: np.ndarray | Tensor, std: np.ndarray | Tensor, *,
                   min_std: float = 1e-4) -> Normalizer:
        """A normaliser with the given statistics, each (D,)."""
        mean_t = torch.as_tensor(mean)
        return cls(int(mean_t.shape[-1]), mean_t, std, min_std=min_std)

    @classmethod
    def from_data(cls, x: np.ndarray | Tensor, *, min_std: float = 1e-4) -> Normalizer:
        """Statistics of ``x`` (..., D) over all leading axes (population std)."""
        xt = torch.as_tensor(x, dtype=torch.float64).reshape(-1, torch.as_tensor(x).shape[-1])
        return cls.from_stats(xt.mean(0), xt.std(0, unbiased=False), min_std=min_std)

    @torch.no_grad()
    def set_stats(self, mean: np.ndarray | Tensor, std: np.ndarray | Tensor) -> None:
        """Replace the statistics in place (device kept); ``std`` is floored at ``min_std``."""
        mean_t = torch.as_tensor(mean, dtype=torch.float32).reshape(-1)
        std_t = torch.as_tensor(std, dtype=torch.float32).reshape(-1)
        if mean_t.shape != (self.dim,) or std_t.shape != (self.dim,):
            raise ValueError(f"stats must have shape ({self.dim},), got {tuple(mean_t.shape)} "
                             f"and {tuple(std_t.shape)}")
        if not (torch.isfinite(mean_t).all() and torch.isfinite(std_t).all()):
            raise ValueError("normalisation statistics must be finite")
        self.mean.copy_(mean_t)
        self.std.copy_(std_t.clamp_min(self.min_std))

    def normalize(self, x: Tensor) -> Tensor:
        """(..., D) raw -> (..., D) z-scored."""
        return (x - self.mean) / self.std

    def denormalize(self, y: Tensor) -> Tensor:
        """(..., D) z-scored -> (..., D) raw."""
        return y * self.std + self.mean

    def forward(self, x: Tensor) -> Tensor:
        return self.normalize(x)

    def extra_repr(self) -> str:
        return f"dim={self.dim}, min_std={self.min_std:g}"


def _activation(name: Activation) -> nn.Module:
    if name == "elu":
        return nn.ELU()
    if name == "leaky_relu":
        # 0.05 is the slope of the released ControlNet.
        return nn.LeakyReLU(0.05)
    if name == "relu":
        return nn.ReLU()
    raise ValueError(f"unknown activation {name!r}")


def mlp(sizes: Sequence[int], activation: Activation = "elu", dropout: float = 0.0,
        last_activation: bool = False) -> nn.Sequential:
    """Fully connected network ``sizes[0] -> sizes[1] -> ... -> sizes[-1]``.

    Each layer is ``[Dropout] Linear [activation]``; dropout is applied to each layer's input as
    in the released PoseNet (and MANN/NSM), and is omitted when 0. The activation after the last
    Linear is added only when ``last_activation`` (encoders whose output feeds another network
    want it, prediction heads do not).
    """
    if len(sizes) < 2:
        raise ValueError(f"mlp needs at least an input and an output size, got {list(sizes)}")
    layers: list[nn.Module] = []
    n = len(sizes) - 1
    for i in range(n):
        if dropout > 0:
            layers.append(nn.Dropout(dropout))
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < n - 1 or last_activation:
            layers.append(_activation(activation))
    return nn.Sequential(*layers)


def run_layers(seq: nn.Sequential, x: Tensor, start: int = 0) -> Tensor:
    """``seq[start:](x)``, calling each layer's ``forward`` directly. Module calls dispatch hooks
    (none are used here): at batch 1 the runtime's ~60 of them a frame cost ~5 % of its time."""
    for layer in itertools.islice(seq, start, None):
        x = layer.forward(x)
    return x


def first_linear(seq: nn.Sequential) -> int:
    """Index of the first layer of an :func:`mlp` that is a linear map (``nn.Linear`` or, in a
    packed copy, ``PackedLinear``)."""
    for i, layer in enumerate(seq):
        if isinstance(layer, (nn.Linear, PackedLinear)):
            return i
    raise ValueError("no linear layer in the network")


def linear_widths(net: nn.Module) -> list[int]:
    """Output widths of the Linear layers of ``net`` in order (for summaries and tests)."""
    return [m.out_features for m in net.modules() if isinstance(m, nn.Linear)]


def _index(cols: Columns) -> slice | list[int]:
    """A ``Columns`` value as something that indexes the last axis."""
    if isinstance(cols, slice):
        return cols
    if isinstance(cols, range):
        if cols.step == 1:
            return slice(cols.start, cols.stop)
        return list(cols)
    return [int(i) for i in cols]


def _take(x: Tensor, cols: Columns) -> Tensor:
    return x[..., _index(cols)]


# --------------------------------------------------------------------------------------------
# ControlNet
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ControlNetConfig:
    """ControlNet hyper-parameters (paper supplementary Sec. 2.1).

    Attributes:
        pose_encoder: hidden widths of the pose encoder (paper {128, 128}).
        control_encoder: hidden widths of the control encoder (paper {128, 128}).
        lstm_hidden: LSTM hidden size (paper 512; released code 256).
        lstm_layers: LSTM layers (2).
        learn_initial_state: learnable h0/c0 (released code) instead of zeros.
        activation: encoder activation (paper does not say; released code LeakyReLU(0.05)).
        dropout: encoder dropout (none in either).
        teacher_forcing_until: last epoch with teacher probability 1 (released code 3).
        teacher_forcing_off_at: epoch from which the teacher probability is 0 (released code 10).
        per_sample_sampling: draw the scheduled-sampling Bernoulli per step *per sample* (True)
            or once per step for the whole batch (False, released code).
        loss_weights: (lambda1 trajectory, lambda2 phase, lambda3 regulariser) of Eq. 2; the paper
            gives no values. The released code uses (0.1, 0.02, 2.0) with an MSE regulariser
            (plus an extra first-point term not reproduced here). Ours: (1, 1, 0.1). The
            straight line ends on the chair's surface, where no hand joint goes (a touching
            hand joint stays ~9 cm from its contact point in the simulated data, 6-8 cm above
            it); with lambda3 = 1 the norm regulariser, whose gradient does not fade near the
            line, pulled the predicted trajectory's end onto the surface, so PoseNet was told
            the hand goes where its data never put one, and seated palms stopped ~5 cm from
            seat corners (``couch-eval`` 24 x 16 trials, same PoseNet: ACE 4.13 cm with
            lambda3 = 1, 3.24 with 0.3, 2.75 with 0.1, 3.73 with 0.03, 3.58 with 0.01,
            4.14 with 0; 3.20 against 4.02 for 0.1 and 1 on 24 other chairs; a second
            training at 0.1 with another seed: 3.75).
        reg: ``"norm"`` (paper: ||h - h_line||_2) or ``"mse"`` (released code).
    """

    pose_encoder: tuple[int, ...] = (128, 128)
    control_encoder: tuple[int, ...] = (128, 128)
    lstm_hidden: int = 512
    lstm_layers: int = 2
    learn_initial_state: bool = False
    activation: Activation = "elu"
    dropout: float = 0.0
    teacher_forcing_until: float = 3.0
    teacher_forcing_off_at: float = 10.0
    per_sample_sampling: bool = True
    loss_weights: tuple[float, float, float] = (1.0, 1.0, 0.1)
    reg: Literal["norm", "mse"] = "norm"

    def __post_init__(self) -> None:
        if self.teacher_forcing_off_at < self.teacher_forcing_until:
            raise ValueError("teacher_forcing_off_at must not precede teacher_forcing_until")
        if self.lstm_hidden <= 0 or self.lstm_layers <= 0:
            raise ValueError("LSTM sizes must be positive")

    @classmethod
    def released_code(cls) -> ControlNetConfig:
        """The authors' released choices: LSTM 256 with learnable h0/c0, LeakyReLU(0.05),
        batch-wide Bernoulli, their loss weights with the MSE regulariser."""
        return cls(lstm_hidden=256, learn_initial_state=True, activation="leaky_relu",
                   per_sample_sampling=False, loss_weights=(0.1, 0.02, 2.0), reg="mse")


class ControlNet(nn.Module):
    """Eq. 1: ``C+_{i+1} = f_CN(h~_i, phi_i)`` with the pose as extra input.

    Args:
        pose_dim: P, per-frame pose features (e.g. 22 joints x 3 root-relative positions).
        control_dim: Cc, per-frame control features (e.g. 2 x 7 x 3 straight-line points and
            2 x 13 local phases).
        out_dim: O, per-frame prediction (e.g. 2 x 3 x 7 trajectory + 2 x 7 phases = 56).
        config: hyper-parameters.
    """

    def __init__(self, pose_dim: int, control_dim: int, out_dim: int = 56,
                 config: ControlNetConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or ControlNetConfig()
        self.pose_dim, self.control_dim, self.out_dim = pose_dim, control_dim, out_dim
        self.pose_encoder = mlp([pose_dim, *config.pose_encoder], config.activation,
                                config.dropout, last_activation=True)
        self.control_encoder = mlp([control_dim, *config.control_encoder], config.activation,
                                   config.dropout, last_activation=True)
        lstm_in = config.pose_encoder[-1] + config.control_encoder[-1]
        self.lstm = nn.LSTM(lstm_in, config.lstm_hidden, num_layers=config.lstm_layers,
                            batch_first=True)
        self.head = nn.Linear(config.lstm_hidden, out_dim)
        shape = (config.lstm_layers, 1, config.lstm_hidden)
        if config.learn_initial_state:
            # Released code: small random learnable initial state, expanded over the batch.
            self.h0: nn.Parameter | None = nn.Parameter(torch.randn(shape) * 0.01)
            self.c0: nn.Parameter | None = nn.Parameter(torch.randn(shape) * 0.01)
        else:
            self.h0 = self.c0 = None
        #: the LSTM cells' [W_ih W_hh] as one packed matrix per layer (:meth:`pack`), or None
        self.packed_cells: nn.ModuleList | None = None

    def pack(self, precision: Precision) -> None:
        """Run :meth:`step`'s LSTM cells in ``precision`` (see
        :func:`couch.synthesis.precision.packed_copy`; inference only): each layer's input and
        recurrent matrices as one packed GEMM over ``[x, h]``."""
        self.packed_cells = nn.ModuleList(
            PackedLinear(torch.cat([getattr(self.lstm, f"weight_ih_l{k}"),
                                    getattr(self.lstm, f"weight_hh_l{k}")], dim=1),
                         getattr(self.lstm, f"bias_ih_l{k}") + getattr(self.lstm, f"bias_hh_l{k}"),
                         precision)
            for k in range(self.config.lstm_layers))

    def initial_state(self, batch: int, device: torch.device | None = None,
                      dtype: torch.dtype | None = None) -> LSTMState:
        """``(h, c)`` for a new sequence, each (layers, B, hidden)."""
        if self.h0 is not None and self.c0 is not None:
            return (self.h0.expand(-1, batch, -1).contiguous(),
                    self.c0.expand(-1, batch, -1).contiguous())
        ref = self.lstm.weight_hh_l0
        shape = (self.config.lstm_layers, batch, self.config.lstm_hidden)
        z = torch.zeros(shape, device=device or ref.device, dtype=dtype or ref.dtype)
        return z, z.clone()

    def forward(self, pose: Tensor, control: Tensor,
                state: LSTMState | None = None) -> tuple[Tensor, LSTMState]:
        """Run over a sequence.

        Args:
            pose: (B, L, P); control: (B, L, Cc); state: ``(h, c)`` or None for a new sequence.
        Returns:
            out (B, L, O) and the state after the last frame.
        """
        if pose.dim() != 3 or control.dim() != 3:
            raise ValueError("forward expects (B, L, dim) tensors; use step() for one frame")
        if state is None:
            state = self.initial_state(pose.shape[0], pose.device, pose.dtype)
        feats = torch.cat([self.pose_encoder(pose), self.control_encoder(control)], dim=-1)
        hidden, state = self.lstm(feats, state)
        return self.head(hidden), state

    def step(self, pose: Tensor, control: Tensor,
             state: LSTMState | None = None) -> tuple[Tensor, LSTMState]:
        """One frame at runtime: pose (B, P), control (B, Cc) -> out (B, O), new state.

        The same maths as :meth:`forward` over one frame, with the LSTM cells written out:
        ``torch.lstm`` costs ~9x more than its two matrix-vector products at batch 1.
        """
        if state is None:
            state = self.initial_state(pose.shape[0], pose.device, pose.dtype)
        x = torch.cat([run_layers(self.pose_encoder, pose),
                       run_layers(self.control_encoder, control)], dim=-1)
        h0, c0 = state
        hs, cs = [], []
        for layer in range(self.config.lstm_layers):
            if self.packed_cells is not None:
                gates = self.packed_cells[layer].forward(torch.cat([x, h0[layer]], dim=-1))
            else:
                gates = (F.linear(x, getattr(self.lstm, f"weight_ih_l{layer}"),
                                  getattr(self.lstm, f"bias_ih_l{layer}"))
                         + F.linear(h0[layer], getattr(self.lstm, f"weight_hh_l{layer}"),
                                    getattr(self.lstm, f"bias_hh_l{layer}")))
            i, f, g, o = gates.chunk(4, dim=-1)  # PyTorch's gate order
            c = torch.sigmoid(f) * c0[layer] + torch.sigmoid(i) * torch.tanh(g)
            x = torch.sigmoid(o) * torch.tanh(c)
            hs.append(x)
            cs.append(c)
        return self.head.forward(x), (torch.stack(hs), torch.stack(cs))


def scheduled_sampling_probability(epoch: float, config: ControlNetConfig | None = None) -> float:
    """Probability of feeding the ground truth (teacher forcing) at ``epoch``.

    1 up to ``teacher_forcing_until`` (inclusive), then linearly down to 0 at
    ``teacher_forcing_off_at``, 0 afterwards (released code: 3 and 10).
    """
    config = config or ControlNetConfig()
    start, end = config.teacher_forcing_until, config.teacher_forcing_off_at
    if epoch <= start:
        return 1.0
    if epoch >= end:
        return 0.0
    return 1.0 - (epoch - start) / (end - start)


def replace_columns(control_cols: Columns,
                    out_cols: Columns) -> Callable[[Tensor, Tensor], Tensor]:
    """Default scheduled-sampling feedback: copy ``prev_out[..., out_cols]`` into
    ``control[..., control_cols]`` (the two selections must have the same size).

    Returns ``feedback(control_t (B, Cc), prev_out (B, O)) -> control_t' (B, Cc)``.
    """
    ci, oi = _index(control_cols), _index(out_cols)

    def feedback(control_t: Tensor, prev_out: Tensor) -> Tensor:
        new = control_t.clone()
        src = prev_out[..., oi]
        if new[..., ci].shape != src.shape:
            raise ValueError(f"feedback columns differ in size: control "
                             f"{tuple(new[..., ci].shape)} vs prediction {tuple(src.shape)}")
        new[..., ci] = src.to(new.dtype)
        return new

    return feedback


class Rollout(NamedTuple):
    """Result of :func:`rollout`."""

    out: Tensor  #: (B, L, O) predictions
    state: LSTMState  #: LSTM state after the last frame
    substituted: Tensor  #: (B, L) bool, True where the control came from the previous prediction


def rollout(model: ControlNet, pose: Tensor, control: Tensor, p_teacher: float, *,
            feedback: Callable[[Tensor, Tensor], Tensor] | None = None,
            control_traj: Columns | None = None, out_traj: Columns | None = None,
            state: LSTMState | None = None, prev_out: Tensor | None = None,
            generator: torch.Generator | None = None,
            per_sample: bool | None = None, detach_feedback: bool = True) -> Rollout:
    """Unroll ControlNet over an L-frame training window with scheduled sampling.

    At each step, with probability ``1 - p_teacher`` (Bernoulli per step and per sample, or per
    step for the whole batch when ``per_sample`` is False) the control input is replaced by
    ``feedback(control_t, prev_out)``, where ``prev_out`` is the model's previous prediction;
    the rest keep the ground-truth control. The phase columns must be left alone by
    ``feedback`` (the paper always feeds ground-truth phases); the default feedback,
    :func:`replace_columns` ``(control_traj, out_traj)``, only touches the trajectory columns.
    Step 0 has no previous prediction unless ``prev_out`` is given, so it is never substituted
    otherwise. Gradients flow through the whole window (BPTT); the fed-back prediction is
    detached by default, as in the released code.

    Args:
        model: the ControlNet.
        pose: (B, L, P); control: (B, L, Cc) ground truth.
        p_teacher: probability of keeping the ground truth (:func:`scheduled_sampling_probability`).
        feedback: ``(control_t (B, Cc), prev_out (B, O)) -> (B, Cc)``; default replaces
            ``control_traj`` columns with ``out_traj`` columns.
        state: initial LSTM state (None: the model's initial state).
        prev_out: (B, O) prediction preceding the window, if any.
        generator: torch generator for the Bernoulli draws (on the tensors' device).
        per_sample: overrides ``model.config.per_sample_sampling``.
    Returns:
        :class:`Rollout` with out (B, L, O), the final state and the (B, L) substitution mask.
    """
    if not 0.0 <= p_teacher <= 1.0:
        raise ValueError(f"p_teacher must be in [0, 1], got {p_teacher}")
    if feedback is None:
        if control_traj is None or out_traj is None:
            raise ValueError("give either feedback or both control_traj and out_traj")
        feedback = replace_columns(control_traj, out_traj)
    if per_sample is None:
        per_sample = model.config.per_sample_sampling
    batch, length = pose.shape[:2]
    if length == 0:
        raise ValueError("rollout needs at least one frame")
    device = pose.device
    outs: list[Tensor] = []
    masks: list[Tensor] = []
    no = torch.zeros(batch, dtype=torch.bool, device=device)
    for t in range(length):
        control_t = control[:, t]
        mask = no
        if prev_out is not None and p_teacher < 1.0:
            n = batch if per_sample else 1
            draw = torch.rand(n, generator=generator, device=device) < (1.0 - p_teacher)
            mask = draw.expand(batch)
            if bool(mask.any()):
                fed_in = prev_out.detach() if detach_feedback else prev_out
                fed = feedback(control_t, fed_in)
                control_t = torch.where(mask[:, None], fed, control_t)
        out_t, state = model.step(pose[:, t], control_t, state)
        outs.append(out_t)
        masks.append(mask)
        prev_out = out_t
    assert state is not None  # set by the first step
    return Rollout(torch.stack(outs, 1), state, torch.stack(masks, 1))


class ControlLoss(NamedTuple):
    """Terms of Eq. 2 (``total`` is the weighted sum; the others are unweighted)."""

    total: Tensor
    traj: Tensor
    phase: Tensor
    reg: Tensor


def control_loss(pred: Tensor, target: Tensor, line_points: Tensor,
                 weights: tuple[float, float, float] = (1.0, 1.0, 1.0), *,
                 traj_cols: Columns, phase_cols: Columns,
                 reg: Literal["norm", "mse"] = "norm") -> ControlLoss:
    """Eq. 2: ``l1 * MSE(traj) + l2 * MSE(phase) + l3 * L_reg``.

    Args:
        pred, target: (..., O) ControlNet outputs and ground truth.
        line_points: (..., n_traj) the straight-line points h~_i in the same layout (and frame,
            i.e. relative to the contacts) as ``pred[..., traj_cols]``.
        weights: (lambda1, lambda2, lambda3).
        traj_cols, phase_cols: which output columns are trajectory and which are phases.
        reg: ``"norm"``: L_reg = ||h_pred - h_line||_2 over each sample's whole trajectory
            vector, averaged over the leading axes (paper); ``"mse"``: mean squared error
            (released code).
    """
    traj_pred = _take(pred, traj_cols)
    if line_points.shape != traj_pred.shape:
        raise ValueError(f"line_points {tuple(line_points.shape)} must match the trajectory "
                         f"columns {tuple(traj_pred.shape)}")
    traj = F.mse_loss(traj_pred, _take(target, traj_cols))
    phase = F.mse_loss(_take(pred, phase_cols), _take(target, phase_cols))
    diff = traj_pred - line_points
    if reg == "norm":
        reg_term = torch.linalg.vector_norm(diff, dim=-1).mean()
    elif reg == "mse":
        reg_term = diff.pow(2).mean()
    else:
        raise ValueError(f"unknown regulariser {reg!r}")
    l1, l2, l3 = weights
    return ControlLoss(l1 * traj + l2 * phase + l3 * reg_term, traj, phase, reg_term)


# --------------------------------------------------------------------------------------------
# PoseNet
# --------------------------------------------------------------------------------------------


def _table5_encoders() -> dict[str, tuple[int, ...]]:
    return {"C": (128, 128, 128), "JT": (512, 512, 512), "G": (128, 128, 128),
            "I": (512, 512, 512), "E": (256, 256, 256)}


@dataclass(frozen=True)
class PoseNetConfig:
    """PoseNet hyper-parameters (paper supplementary Sec. 2.2, Table 5).

    Attributes:
        encoders: hidden widths per input group name (Table 5; the released code uses two
            layers each and 512 for E).
        num_experts: K (10).
        gating_hidden: gating network hidden widths; with the output layer that makes three
            layers (paper 128; released code 512).
        expert_hidden: prediction network hidden widths; three layers with the output layer
            (512).
        activation: ELU (both).
        dropout: dropout before each encoder and expert layer (paper silent; released code 0.3).
        gating_dropout: the same for the gating network (released code 0.3).
    """

    encoders: dict[str, tuple[int, ...]] = field(default_factory=_table5_encoders)
    num_experts: int = 10
    gating_hidden: tuple[int, ...] = (128, 128)
    expert_hidden: tuple[int, ...] = (512, 512)
    activation: Activation = "elu"
    dropout: float = 0.0
    gating_dropout: float = 0.0

    def __post_init__(self) -> None:
        if self.num_experts < 1:
            raise ValueError("num_experts must be at least 1")

    @classmethod
    def released_code(cls) -> PoseNetConfig:
        """The authors' released choices: two-layer encoders (E at 512), gating 512, dropout
        0.3."""
        return cls(encoders={"C": (128, 128), "JT": (512, 512), "G": (128, 128),
                             "I": (512, 512), "E": (512, 512)},
                   gating_hidden=(512, 512), dropout=0.3, gating_dropout=0.3)


class PoseNet(nn.Module):
    """Mixture-of-experts motion synthesis (Eq. 3).

    Args:
        inputs: feature group name -> size, e.g. ``{"C": ..., "JT": ..., "G": ..., "I": 2048,
            "E": 1408}``; each group gets the encoder ``config.encoders[name]`` and the encoded
            groups are concatenated in this dict's order as the expert input.
        gating_inputs: name -> size of the gating features (e.g. global phase, local phases,
            root velocity); concatenated in this order. A name may also appear in ``inputs``.
        out_dim: output size.
        config: hyper-parameters.

    The expert weights of prediction layer l are ``expert_weights[l]`` (K, in, out) and
    ``expert_biases[l]`` (K, out).
    """

    def __init__(self, inputs: Mapping[str, int], gating_inputs: Mapping[str, int],
                 out_dim: int, config: PoseNetConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or PoseNetConfig()
        if not inputs or not gating_inputs:
            raise ValueError("PoseNet needs at least one input group and one gating feature")
        missing = [name for name in inputs if name not in config.encoders]
        if missing:
            raise ValueError(f"no encoder configured for input group(s) {missing}; "
                             f"configured: {sorted(config.encoders)}")
        self.inputs = dict(inputs)
        self.gating_inputs = dict(gating_inputs)
        self.out_dim = out_dim
        self.encoders = nn.ModuleDict({
            name: mlp([dim, *config.encoders[name]], config.activation, config.dropout,
                      last_activation=True)
            for name, dim in self.inputs.items()})
        self.gating = mlp([sum(self.gating_inputs.values()), *config.gating_hidden,
                           config.num_experts], config.activation, config.gating_dropout)
        expert_in = sum(config.encoders[name][-1] for name in self.inputs)
        sizes = [expert_in, *config.expert_hidden, out_dim]
        k = config.num_experts
        self.expert_weights = nn.ParameterList()
        self.expert_biases = nn.ParameterList()
        for fan_in, fan_out in itertools.pairwise(sizes):
            # Glorot-uniform per expert, as in MANN/NSM; biases start at zero.
            bound = math.sqrt(6.0 / (fan_in + fan_out))
            self.expert_weights.append(
                nn.Parameter(torch.empty(k, fan_in, fan_out).uniform_(-bound, bound)))
            self.expert_biases.append(nn.Parameter(torch.zeros(k, fan_out)))
        self.expert_dropout = nn.Dropout(config.dropout) if config.dropout > 0 else nn.Identity()
        self.expert_activation = _activation(config.activation)
        #: each prediction layer's experts as one packed (out, K*in) matrix (:meth:`pack`)
        self.packed_experts: nn.ModuleList | None = None

    def pack(self, precision: Precision) -> None:
        """Run the experts in ``precision`` (see :func:`couch.synthesis.precision.packed_copy`;
        inference only): each prediction layer's K experts as one packed (out, K*in) matrix."""
        with torch.no_grad():
            self.packed_experts = nn.ModuleList(
                PackedLinear(self._stacked(w).T, None, precision) for w in self.expert_weights)

    def select_outputs(self, columns: Sequence[int]) -> None:
        """Keep only the output ``columns`` (inference only, in place; before :meth:`pack`):
        the last prediction layer's experts lose the other columns, so :meth:`forward` returns
        (B, len(columns)) in the given order. A runtime that reads part of the prediction
        (the controller does not read the future goals or joints) reads fewer weights."""
        cols = torch.as_tensor(list(columns), dtype=torch.long)
        if cols.numel() == 0 or int(cols.min()) < 0 or int(cols.max()) >= self.out_dim:
            raise ValueError(f"output columns must lie in [0, {self.out_dim}), got "
                             f"{len(cols)} columns")
        if self.packed_experts is not None:
            raise RuntimeError("select_outputs must come before pack")
        with torch.no_grad():
            w, b = self.expert_weights[-1], self.expert_biases[-1]
            self.expert_weights[-1] = nn.Parameter(w[..., cols].contiguous(), requires_grad=False)
            self.expert_biases[-1] = nn.Parameter(b[..., cols].contiguous(), requires_grad=False)
        self.out_dim = len(cols)

    @staticmethod
    def _gather(values: Mapping[str, Tensor], dims: Mapping[str, int], what: str) -> list[Tensor]:
        out = []
        for name, dim in dims.items():
            if name not in values:
                raise KeyError(f"missing {what} {name!r}; got {sorted(values)}")
            x = values[name]
            if x.shape[-1] != dim:
                raise ValueError(f"{what} {name!r} has size {x.shape[-1]}, expected {dim}")
            out.append(x)
        return out

    def encode(self, inputs: Mapping[str, Tensor],
               first: Mapping[str, Tensor] | None = None) -> Tensor:
        """Encoded groups concatenated: (B, sum of the encoders' last widths).

        ``first``: encoder name -> the output of its first linear layer (B, width), given
        instead of its input group (which ``inputs`` then need not hold): the runtime computes
        the interaction encoder's from the root pose in closed form (I is affine in it).
        """
        first = first or {}
        out = []
        for name, dim in self.inputs.items():
            seq = self.encoders[name]
            if name in first:
                out.append(run_layers(seq, first[name], first_linear(seq) + 1))
            else:
                out.append(run_layers(seq, self._gather(inputs, {name: dim}, "input group")[0]))
        return torch.cat(out, dim=-1)

    def gate(self, inputs: Mapping[str, Tensor]) -> Tensor:
        """Expert coefficients (B, K): softmax of the gating network, non-negative, sum 1."""
        g = torch.cat(self._gather(inputs, self.gating_inputs, "gating feature"), dim=-1)
        return torch.softmax(run_layers(self.gating, g), dim=-1)

    def blend(self, coefficients: Tensor) -> list[tuple[Tensor, Tensor]]:
        """Per-sample blended weights of each prediction layer.

        coefficients (B, K) -> [(W (B, in, out), b (B, out)), ...] with
        ``W[b] = sum_k coefficients[b, k] * expert_weights[l][k]`` (likewise b).
        """
        return [(torch.einsum("bk,kio->bio", coefficients, w),
                 coefficients @ b)
                for w, b in zip(self.expert_weights, self.expert_biases, strict=True)]

    @staticmethod
    def _stacked(w: Tensor) -> Tensor:
        """Expert weights (K, in, out) as one (K*in, out) matrix, experts stacked along the
        input (rows k*in to (k+1)*in are expert k's): a view, no copy."""
        return w.reshape(-1, w.shape[-1])

    def forward(self, inputs: Mapping[str, Tensor],
                first: Mapping[str, Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """inputs: name -> (B, dim) for every input group and gating feature (``first``: see
        :meth:`encode`).

        Returns (out (B, out_dim), gating coefficients (B, K)).
        """
        coefficients = self.gate(inputs)
        x = self.encode(inputs, first)
        last = len(self.expert_weights) - 1
        for i, (w, b) in enumerate(zip(self.expert_weights, self.expert_biases, strict=True)):
            x = self.expert_dropout.forward(x)
            # sum_k c_k (x W_k + b_k) = [c_1 x, ..., c_K x] [W_1; ...; W_K] + sum_k c_k b_k: the
            # blend (:meth:`blend`) done on the input side, so that all K experts run as one GEMM
            # over the batch (not a (B, in, out) weight tensor per sample, which dominated the
            # runtime at batch 64), and nothing is left to blend after it (at batch 1 the
            # per-call cost of blending K outputs was a tenth of the experts' time).
            k, fan_in, _ = w.shape
            scaled = (coefficients[:, :, None] * x[:, None, :]).reshape(-1, k * fan_in)
            y = (self.packed_experts[i].forward(scaled) if self.packed_experts is not None
                 else scaled @ self._stacked(w))
            x = y + coefficients @ b
            if i < last:
                x = self.expert_activation.forward(x)
        return x, coefficients


# --------------------------------------------------------------------------------------------
# ContactNet
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ContactNetConfig:
    """ContactNet (cVAE) hyper-parameters (paper Sec. 4.4 and supplementary Sec. 2.3).

    Attributes:
        condition_encoder: widths of the scene/condition encoder ({512, 512, 64}); its last
            layer is linear (no activation), as in the released code.
        encoder_hidden: widths of q(z | c, cond) after concatenating c with the condition code
            (paper silent; released code {32, 32, 16}).
        decoder_hidden: widths of p(c | z, cond) (paper silent; released code {32, 32, 16}).
        z_dim: latent size (paper 6; released code 16).
        beta: KL weight (paper 0.1; released code 0.5).
        sample_sigma: test-time z ~ N(0, sigma^2) (paper: N(0, I); released code 2.0).
        activation: ReLU as in the released code (paper silent).
        share_condition_encoder: one condition encoder for q and p (True); the released code
            has a separate one in each.
    """

    condition_encoder: tuple[int, ...] = (512, 512, 64)
    encoder_hidden: tuple[int, ...] = (32, 32, 16)
    decoder_hidden: tuple[int, ...] = (32, 32, 16)
    z_dim: int = 6
    beta: float = 0.1
    sample_sigma: float = 1.0
    activation: Activation = "relu"
    share_condition_encoder: bool = True

    @classmethod
    def released_code(cls) -> ContactNetConfig:
        """The authors' released choices: z 16, KL weight 0.5, sigma 2, separate encoders."""
        return cls(z_dim=16, beta=0.5, sample_sigma=2.0, share_condition_encoder=False)


def kl_divergence(mu: Tensor, logvar: Tensor) -> Tensor:
    """KL(N(mu, exp(logvar)) || N(0, I)) per sample: (B, Z) -> (B,), summed over Z."""
    return -0.5 * (1.0 + logvar - mu.pow(2) - logvar.exp()).sum(-1)


class ContactNet(nn.Module):
    """Conditional VAE over hand contacts (Eq. 4).

    Args:
        cond_dim: condition size (the chair-centric interaction feature I, 2048 =
            8 x 8 x 8 voxels x (occupancy + vector from the chair centre); the released code
            appends the pose).
        contact_dim: size of c (2 hands x 3 = 6).
        config: hyper-parameters.
    """

    def __init__(self, cond_dim: int = 2048, contact_dim: int = 6,
                 config: ContactNetConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or ContactNetConfig()
        self.cond_dim, self.contact_dim = cond_dim, contact_dim
        act = config.activation
        self.condition_encoder = mlp([cond_dim, *config.condition_encoder], act)
        self.decoder_condition_encoder = (
            None if config.share_condition_encoder
            else mlp([cond_dim, *config.condition_encoder], act))
        code = config.condition_encoder[-1]
        self.encoder = mlp([contact_dim + code, *config.encoder_hidden], act,
                           last_activation=False)
        self.to_mu = nn.Linear(config.encoder_hidden[-1], config.z_dim)
        self.to_logvar = nn.Linear(config.encoder_hidden[-1], config.z_dim)
        self.decoder = mlp([config.z_dim + code, *config.decoder_hidden, contact_dim], act)

    def _decoder_code(self, cond: Tensor, enc_code: Tensor | None = None) -> Tensor:
        if self.decoder_condition_encoder is None:
            return enc_code if enc_code is not None else self.condition_encoder(cond)
        return self.decoder_condition_encoder(cond)

    def encode(self, c: Tensor, cond: Tensor) -> tuple[Tensor, Tensor]:
        """q(z | c, cond): c (B, 6), cond (B, D) -> mu, logvar, each (B, Z)."""
        h = self.encoder(torch.cat([c, self.condition_encoder(cond)], dim=-1))
        return self.to_mu(h), self.to_logvar(h)

    def decode(self, z: Tensor, cond: Tensor) -> Tensor:
        """p(c | z, cond): z (..., Z), cond (..., D) -> c_hat (..., 6)."""
        return self.decoder(torch.cat([z, self._decoder_code(cond)], dim=-1))

    def forward(self, c: Tensor, cond: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """c (B, 6), cond (B, D) -> (c_hat (B, 6), mu (B, Z), logvar (B, Z)); z is drawn with
        the reparameterisation trick."""
        code = self.condition_encoder(cond)
        h = self.encoder(torch.cat([c, code], dim=-1))
        mu, logvar = self.to_mu(h), self.to_logvar(h)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
        c_hat = self.decoder(torch.cat([z, self._decoder_code(cond, code)], dim=-1))
        return c_hat, mu, logvar

    def loss(self, c: Tensor, cond: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Eq. 4: ``||c_hat - c||^2 + beta * KL``, each averaged over the batch.

        Returns (total, recon, kl) scalars (recon and kl unweighted).
        """
        c_hat, mu, logvar = self(c, cond)
        recon = (c_hat - c).pow(2).sum(-1).mean()
        kl = kl_divergence(mu, logvar).mean()
        return recon + self.config.beta * kl, recon, kl

    @torch.no_grad()
    def sample(self, cond: Tensor, n: int, generator: torch.Generator | None = None,
               sigma: float | None = None) -> Tensor:
        """Draw n contact sets per condition: cond (B, D) -> (B, n, 6), z ~ N(0, sigma^2 I)
        with ``sigma = config.sample_sigma`` unless given."""
        sigma = self.config.sample_sigma if sigma is None else sigma
        batch = cond.shape[0]
        z = torch.randn(batch, n, self.config.z_dim, generator=generator, device=cond.device,
                        dtype=cond.dtype) * sigma
        code = self._decoder_code(cond)
        code = code.unsqueeze(1).expand(-1, n, -1)
        return self.decoder(torch.cat([z, code], dim=-1))


def project_contacts(pred: np.ndarray | Tensor, vertices: np.ndarray, faces: np.ndarray,
                     max_distance: float = 0.10) -> tuple[np.ndarray, np.ndarray]:
    """Project predicted contacts onto the chair surface (supplementary Sec. 3).

    Each contact within ``max_distance`` (m) of the mesh goes to its nearest surface point; the
    others are dropped (``kept`` False; their row holds the nearest surface point anyway, so use
    ``projected[kept]``).

    Args:
        pred: (N, 3) contact positions in the mesh's frame.
        vertices: (V, 3); faces: (F, 3) int.
    Returns:
        projected (N, 3) float64 and kept (N,) bool.
    """
    import trimesh  # local: heavy import, only needed by this post-process

    points = (pred.detach().cpu().numpy() if isinstance(pred, Tensor)
              else np.asarray(pred)).astype(np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=bool)
    mesh = trimesh.Trimesh(vertices=np.asarray(vertices, dtype=np.float64),
                           faces=np.asarray(faces), process=False)
    closest, distance, _ = trimesh.proximity.closest_point(mesh, points)
    return np.asarray(closest, dtype=np.float64), np.asarray(distance) <= max_distance
