"""Runtime weight precision (``synthesis/precision.py``): fbgemm fp16 / int8 layers against the
fp32 networks they copy, and ``Synthesizer(precision=...)`` on the session's ci-trained run."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from torch import nn

from couch.synthesis import (
    ControlNet,
    ControlNetConfig,
    PoseNet,
    PoseNetConfig,
    Scene,
    Synthesizer,
)
from couch.synthesis.precision import PackedLinear, packed_copy
from couch.tools.sim.chairs import make_chair, random_chair_spec

# int8 quantises the activations per call as well as the weights: a few per cent
TOLERANCE = {"fp16": 2e-3, "int8": 0.06}


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm())


@pytest.fixture(autouse=True)
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("precision", ["fp16", "int8"])
def test_packed_linear_matches_the_layer(precision):
    layer = nn.Linear(300, 200)
    packed = PackedLinear(layer.weight, layer.bias, precision)
    x = torch.randn(4, 5, 300)  # any leading dimensions
    with torch.no_grad():
        want, got = layer(x), packed(x)
    assert got.shape == want.shape and got.dtype == torch.float32
    assert _rel(got, want) < TOLERANCE[precision]
    # the bias is kept exactly: a zero input gives it back
    assert torch.allclose(packed(torch.zeros(1, 300)), layer.bias.detach()[None], atol=1e-6)


def test_packed_linear_refuses_fp32():
    layer = nn.Linear(3, 2)
    with pytest.raises(ValueError, match="fp16 or int8"):
        PackedLinear(layer.weight, layer.bias, "fp32")


def _pose_net() -> PoseNet:
    cfg = PoseNetConfig(encoders={"C": (32, 32), "JT": (64, 64), "G": (32,), "I": (64,),
                                  "E": (32,)}, gating_hidden=(16, 16), num_experts=4,
                        expert_hidden=(96, 96))
    return PoseNet({"C": 10, "JT": 40, "G": 12, "I": 80, "E": 30},
                   {"global_phase": 1, "control_phases": 14}, 50, cfg).eval()


def _pose_inputs(net: PoseNet) -> dict[str, torch.Tensor]:
    return {n: torch.randn(3, d) for n, d in {**net.inputs, **net.gating_inputs}.items()}


@pytest.mark.parametrize("precision", ["fp16", "int8"])
def test_packed_pose_net_matches_fp32(precision):
    net = _pose_net()
    inputs = _pose_inputs(net)
    fast = packed_copy(net, precision, min_size=0)
    with torch.no_grad():
        (want, gate_want), (got, gate_got) = net(inputs), fast(inputs)
    assert _rel(got, want) < TOLERANCE[precision]
    assert _rel(gate_got, gate_want) < TOLERANCE[precision]
    # every layer of the copy was packed, the original untouched
    assert not any(isinstance(m, nn.Linear) for m in fast.modules())
    assert fast.packed_experts is not None and len(fast.packed_experts) == 3
    assert net.packed_experts is None and any(isinstance(m, nn.Linear) for m in net.modules())


@pytest.mark.parametrize("precision", ["fp16", "int8"])
def test_packed_control_net_step_matches_fp32(precision):
    net = ControlNet(20, 30, 12, ControlNetConfig(pose_encoder=(32, 32),
                                                  control_encoder=(32, 32),
                                                  lstm_hidden=64)).eval()
    fast = packed_copy(net, precision, min_size=0)
    state_a = state_b = None
    with torch.no_grad():
        for _ in range(5):  # the recurrent state carries the error along
            pose, control = torch.randn(2, 20), torch.randn(2, 30)
            want, state_a = net.step(pose, control, state_a)
            got, state_b = fast.step(pose, control, state_b)
    assert _rel(got, want) < TOLERANCE[precision]
    assert _rel(state_b[1], state_a[1]) < TOLERANCE[precision]


def test_small_layers_stay_fp32():
    net = _pose_net()
    fast = packed_copy(net, "fp16", min_size=64 * 64)
    kinds = {type(m).__name__ for m in fast.encoders["JT"].modules()}
    # JT's 40 x 64 input layer is below the limit, its 64 x 64 layer is not
    assert {"Linear", "PackedLinear"} <= kinds
    assert packed_copy(net, "fp32") is net
    with pytest.raises(ValueError, match="unknown precision 'bf16'"):
        packed_copy(net, "bf16")


def test_synthesizer_in_fp16_follows_fp32(ci_run):
    chair = make_chair(random_chair_spec(np.random.default_rng(4), "armchair"))
    starts = np.array([[0.2, 0.9, np.pi], [1.0, 1.5, -2.0]])
    series = np.broadcast_to(np.array([[np.asarray(chair.landmarks.left_armrest),
                                        [np.nan] * 3]]), (2, 1, 2, 3))
    syns = {p: Synthesizer(ci_run.run_dir, "couch", precision=p) for p in ("fp32", "fp16")}
    # the ci nets' layers are all small: only the experts and LSTM cells are packed
    for precision, syn in syns.items():
        packed = (syn.pose_net.packed_experts is not None,
                  syn.control_net.packed_cells is not None)
        assert packed == ((True, True) if precision == "fp16" else (False, False))
    scene = Scene.from_mesh(chair.vertices, chair.faces, syns["fp32"].cfg)
    # Each frame of 45, both runtimes step from the same state (fp32's): the tiny ci nets'
    # closed loop can grow a 0.1 mm difference into centimetres within ten frames, which says
    # nothing about the weights' precision.
    state = syns["fp32"]._initial_state(scene.goals(series), starts, len(starts))
    control_on, worst = False, 0.0
    for _ in range(45):
        twin = copy.deepcopy(state)
        want = syns["fp32"]._step(scene, state, series)
        got = syns["fp16"]._step(scene, twin, series)
        control_on |= bool(want["on"].any())
        worst = max(worst, float(np.abs(got["jpos"] - want["jpos"]).max()),
                    float(np.abs(got["root"][:, :3, 3] - want["root"][:, :3, 3]).max()))
    assert control_on
    # one step's pose and root from fp16 weights are within 0.2 mm of fp32's (0.07 measured)
    assert worst < 2e-4


def test_synthesizer_precision_errors(ci_run):
    with pytest.raises(ValueError, match="unknown precision"):
        Synthesizer(ci_run.run_dir, "couch", precision="fp8")
    with pytest.raises(ValueError, match="fbgemm's CPU kernels"):
        Synthesizer(ci_run.run_dir, "couch", precision="fp16", device="cuda")
