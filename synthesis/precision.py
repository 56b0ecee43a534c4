"""Runtime weight precision: the trained networks' linear layers as fbgemm fp16 or int8 GEMMs.

At batch 1 the runtime is memory-bound: every frame reads all of PoseNet's expert weights
(52 MB for the paper's sizes) and ControlNet's LSTM (15 MB), more than the L3 cache holds.
Stored as fp16 (half the bytes, computed in fp32 after conversion; outputs within ~1e-3 of
fp32) or int8 (a quarter; per-output-channel weight scales, the activations quantised per call,
outputs within a few per cent), the same maths runs 2.5-5x faster per layer on an AVX2 CPU.
Training always uses fp32; this is for inference only (no gradients).

The kernels are fbgemm's, through ``torch.ops.quantized``: PyTorch marks its eager
quantisation *modules* deprecated, the ops stay (and torch is pinned exactly).
"""

from __future__ import annotations

import copy
import warnings
from typing import Literal

import torch
from torch import Tensor, nn

Precision = Literal["fp32", "fp16", "int8"]
PRECISIONS: tuple[str, ...] = ("fp32", "fp16", "int8")
#: weights below this many stay fp32 in :func:`packed_copy`
MIN_PACKED = 1 << 17


class PackedLinear(nn.Module):
    """``y = x W^T + b`` with ``W`` (out, in) packed for fbgemm in ``precision`` (fp16 or int8).

    Inputs and outputs are fp32 (..., in) -> (..., out); the bias stays fp32.
    """

    def __init__(self, weight: Tensor, bias: Tensor | None, precision: Precision) -> None:
        super().__init__()
        if precision not in ("fp16", "int8"):
            raise ValueError(f"PackedLinear packs fp16 or int8 weights, not {precision!r}")
        w = weight.detach().to(torch.float32).contiguous()
        b = None if bias is None else bias.detach().to(torch.float32).contiguous()
        self.precision, self.in_features, self.out_features = precision, w.shape[1], w.shape[0]
        if precision == "fp16":
            self._packed = torch.ops.quantized.linear_prepack_fp16(w, b)
        else:
            scale = (w.abs().amax(1) / 127.0).clamp_min(1e-12).double()
            with warnings.catch_warnings():
                # quantize_per_channel warns that quantised tensors are deprecated; torch is
                # pinned at 2.13.0, where fbgemm's dynamic int8 linear is the fast CPU path.
                warnings.simplefilter("ignore", UserWarning)
                q = torch.quantize_per_channel(w, scale, torch.zeros_like(scale, dtype=torch.long),
                                               0, torch.qint8)
            self._packed = torch.ops.quantized.linear_prepack(q, b)

    def forward(self, x: Tensor) -> Tensor:
        shape = x.shape
        flat = x.dim() != 2
        if flat:
            x = x.reshape(-1, shape[-1])
        x = x.to(torch.float32).contiguous()  # no-ops (no copy) for the runtime's inputs
        if self.precision == "fp16":
            y = torch.ops.quantized.linear_dynamic_fp16(x, self._packed)
        else:
            y = torch.ops.quantized.linear_dynamic(x, self._packed, True)
        return y.reshape(*shape[:-1], self.out_features) if flat else y

    def extra_repr(self) -> str:
        return f"in={self.in_features}, out={self.out_features}, {self.precision}"


def packed_copy(net: nn.Module, precision: Precision, min_size: int = MIN_PACKED) -> nn.Module:
    """An inference copy of ``net`` (eval mode) whose weights run in ``precision``.

    ``fp32``: ``net`` itself, unchanged. Otherwise a deep copy with every :class:`nn.Linear` of
    at least ``min_size`` weights replaced by a :class:`PackedLinear` (a smaller one stays
    fp32: it sits in the cache anyway, and fbgemm's per-call cost is ~3x torch's), and every
    sub-module with a ``pack(precision)`` method (PoseNet's experts, ControlNet's LSTM cells)
    asked to pack its own matrices (all sizes).
    """
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; choose from {', '.join(PRECISIONS)}")
    if precision == "fp32":
        return net
    out = copy.deepcopy(net).eval()
    for module in list(out.modules()):
        for name, child in list(module.named_children()):
            if isinstance(child, nn.Linear) and child.weight.numel() >= min_size:
                setattr(module, name, PackedLinear(child.weight, child.bias, precision))
    for module in list(out.modules()):
        pack = getattr(module, "pack", None)
        if callable(pack):
            pack(precision)
    return out
