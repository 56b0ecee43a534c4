"""Tests of the COUCH networks (couch.synthesis.nets): sizes, MoE blending maths, ControlNet
stepping and scheduled sampling, cVAE pieces, contact projection, normalisation stats."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import trimesh

from couch.synthesis.nets import (
    ContactNet,
    ContactNetConfig,
    ControlNet,
    ControlNetConfig,
    Normalizer,
    PoseNet,
    PoseNetConfig,
    control_loss,
    kl_divergence,
    linear_widths,
    mlp,
    project_contacts,
    replace_columns,
    rollout,
    scheduled_sampling_probability,
)

# Paper-sized features (only the sizes matter here).
POSE_DIM = 22 * 3
CONTROL_DIM = 2 * 7 * 3 + 2 * 13  # straight-line points + local phases
OUT_DIM = 2 * 3 * 7 + 2 * 7  # trajectories + phases = 56
TRAJ_OUT = slice(0, 42)
PHASE_OUT = slice(42, 56)
TRAJ_CONTROL = slice(0, 42)

SMALL_CONTROL = ControlNetConfig(pose_encoder=(16, 16), control_encoder=(16, 16), lstm_hidden=32)
SMALL_POSE = PoseNetConfig(encoders={"C": (8, 8), "JT": (16, 16), "G": (8,), "I": (16,),
                                     "E": (8,)},
                           num_experts=4, gating_hidden=(16, 16), expert_hidden=(32, 32))
SMALL_CONTACT = ContactNetConfig(condition_encoder=(32, 32, 8), encoder_hidden=(16, 16),
                                 decoder_hidden=(16, 16))


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # These nets are tiny: with intra-op threads on a busy 2-core machine every op pays thread
    # hand-off costs (measured ~100x slower); restore the setting for the rest of the session.
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _small_posenet() -> PoseNet:
    return PoseNet({"C": 5, "JT": 12, "G": 6, "I": 20, "E": 10},
                   {"phase": 1, "local_phase": 4, "root_vel": 3}, out_dim=9, config=SMALL_POSE)


def _posenet_batch(net: PoseNet, b: int) -> dict[str, torch.Tensor]:
    dims = {**net.inputs, **net.gating_inputs}
    return {name: torch.randn(b, d) for name, d in dims.items()}


# ------------------------------------------------------------------ paper sizes


def test_paper_default_sizes_and_shapes() -> None:
    cn = ControlNet(POSE_DIM, CONTROL_DIM, OUT_DIM)
    assert cn.lstm.hidden_size == 512 and cn.lstm.num_layers == 2
    assert linear_widths(cn.pose_encoder) == [128, 128]
    assert linear_widths(cn.control_encoder) == [128, 128]
    assert cn.h0 is None
    out, (h, c) = cn(torch.randn(2, 5, POSE_DIM), torch.randn(2, 5, CONTROL_DIM))
    assert out.shape == (2, 5, OUT_DIM) and h.shape == c.shape == (2, 2, 512)

    code = ControlNet(POSE_DIM, CONTROL_DIM, OUT_DIM, ControlNetConfig.released_code())
    assert code.lstm.hidden_size == 256 and code.h0 is not None
    assert code.step(torch.randn(3, POSE_DIM), torch.randn(3, CONTROL_DIM))[0].shape == (3, 56)

    inputs = {"C": 56, "JT": 22 * 12 + 13 * 12, "G": 13 * 12, "I": 2048, "E": 1408}
    gating = {"phase": 1, "local_phase": 26, "root_vel": 3}
    pn = PoseNet(inputs, gating, out_dim=300)
    table5 = {"C": [128] * 3, "JT": [512] * 3, "G": [128] * 3, "I": [512] * 3, "E": [256] * 3}
    assert {k: linear_widths(v) for k, v in pn.encoders.items()} == table5
    assert linear_widths(pn.gating) == [128, 128, 10]
    assert [tuple(w.shape) for w in pn.expert_weights] == [
        (10, 128 + 512 + 128 + 512 + 256, 512), (10, 512, 512), (10, 512, 300)]
    out, gates = pn({name: torch.randn(2, d) for name, d in {**inputs, **gating}.items()})
    assert out.shape == (2, 300) and gates.shape == (2, 10)

    vae = ContactNet(2048, 6)
    assert linear_widths(vae.condition_encoder) == [512, 512, 64]
    assert vae.config.z_dim == 6 and vae.to_mu.out_features == 6 and vae.config.beta == 0.1
    c_hat, mu, logvar = vae(torch.randn(4, 6), torch.randn(4, 2048))
    assert c_hat.shape == (4, 6) and mu.shape == logvar.shape == (4, 6)
    assert ContactNetConfig.released_code().z_dim == 16


def test_mlp_activation_options() -> None:
    net = mlp([3, 4, 2], activation="leaky_relu", dropout=0.3)
    leaky = [m for m in net if isinstance(m, torch.nn.LeakyReLU)]
    assert len(leaky) == 1 and leaky[0].negative_slope == 0.05
    assert sum(isinstance(m, torch.nn.Dropout) for m in net) == 2
    assert isinstance(mlp([3, 4], last_activation=True)[-1], torch.nn.ELU)


def test_modules_follow_to() -> None:
    # Nothing is created on a fixed device/dtype: after .to(float64) every net runs in float64
    # (the same code path as .to(device)).
    d = torch.float64
    cn = ControlNet(POSE_DIM, CONTROL_DIM, OUT_DIM,
                    ControlNetConfig(lstm_hidden=8, learn_initial_state=False)).to(d)
    out, (h, _) = cn.step(torch.randn(2, POSE_DIM, dtype=d), torch.randn(2, CONTROL_DIM, dtype=d))
    assert out.dtype == h.dtype == d
    res = rollout(cn, torch.randn(2, 3, POSE_DIM, dtype=d), torch.randn(2, 3, CONTROL_DIM, dtype=d),
                  0.0, control_traj=TRAJ_CONTROL, out_traj=TRAJ_OUT)
    assert res.out.dtype == d
    pn = _small_posenet().to(d)
    batch = {k: v.to(d) for k, v in _posenet_batch(pn, 2).items()}
    assert pn(batch)[0].dtype == d
    vae = ContactNet(40, 6, SMALL_CONTACT).to(d)
    assert vae.sample(torch.randn(2, 40, dtype=d), 3).dtype == d
    assert Normalizer(4).to(d).mean.dtype == d


# ------------------------------------------------------------------ PoseNet MoE


def test_gating_is_a_distribution_and_blending_matches_explicit_experts() -> None:
    net = _small_posenet().eval()
    batch = _posenet_batch(net, 5)
    out, gates = net(batch)
    assert (gates >= 0).all()
    torch.testing.assert_close(gates.sum(-1), torch.ones(5))

    # By hand for sample 2: blend each layer's K expert matrices with its coefficients.
    s = 2
    a = gates[s].detach()
    with torch.no_grad():
        x = net.encode({k: v[s:s + 1] for k, v in batch.items()})[0]
        n_layers = len(net.expert_weights)
        for layer in range(n_layers):
            w_all, b_all = net.expert_weights[layer], net.expert_biases[layer]
            w = sum(a[k] * w_all[k] for k in range(net.config.num_experts))
            b = sum(a[k] * b_all[k] for k in range(net.config.num_experts))
            x = x @ w + b
            if layer < n_layers - 1:
                x = F.elu(x)
    torch.testing.assert_close(out[s].detach(), x, rtol=1e-5, atol=1e-5)


def test_posenet_rejects_missing_group() -> None:
    net = _small_posenet()
    batch = _posenet_batch(net, 2)
    del batch["root_vel"]
    with pytest.raises(KeyError):
        net(batch)
    with pytest.raises(ValueError):
        PoseNet({"X": 3}, {"p": 1}, 2, SMALL_POSE)


# ------------------------------------------------------------------ ControlNet


def test_step_matches_forward() -> None:
    for cfg in (SMALL_CONTROL, ControlNetConfig(lstm_hidden=16, learn_initial_state=True)):
        net = ControlNet(POSE_DIM, CONTROL_DIM, OUT_DIM, cfg).eval()
        pose, control = torch.randn(3, 6, POSE_DIM), torch.randn(3, 6, CONTROL_DIM)
        with torch.no_grad():
            full, (h_full, _) = net(pose, control)
            state = None
            steps = []
            for t in range(6):
                o, state = net.step(pose[:, t], control[:, t], state)
                steps.append(o)
        torch.testing.assert_close(torch.stack(steps, 1), full, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(state[0], h_full, rtol=1e-5, atol=1e-5)


def test_rollout_teacher_forcing_equals_forward() -> None:
    net = ControlNet(POSE_DIM, CONTROL_DIM, OUT_DIM, SMALL_CONTROL).eval()
    pose, control = torch.randn(2, 7, POSE_DIM), torch.randn(2, 7, CONTROL_DIM)
    calls = []

    def feedback(c: torch.Tensor, prev: torch.Tensor) -> torch.Tensor:
        calls.append(1)
        return c

    with torch.no_grad():
        ref, _ = net(pose, control)
        res = rollout(net, pose, control, 1.0, feedback=feedback)
    torch.testing.assert_close(res.out, ref, rtol=1e-5, atol=1e-5)
    assert not calls and not res.substituted.any()


def test_rollout_without_teacher_feeds_back_every_step() -> None:
    net = ControlNet(POSE_DIM, CONTROL_DIM, OUT_DIM, SMALL_CONTROL).eval()
    length = 5
    pose, control = torch.randn(2, length, POSE_DIM), torch.randn(2, length, CONTROL_DIM)
    seen: list[torch.Tensor] = []
    default = replace_columns(TRAJ_CONTROL, TRAJ_OUT)

    def feedback(c: torch.Tensor, prev: torch.Tensor) -> torch.Tensor:
        new = default(c, prev)
        seen.append(new)
        return new

    with torch.no_grad():
        res = rollout(net, pose, control, 0.0, feedback=feedback)
    # Step 0 has no previous prediction; every later step is fed back.
    assert len(seen) == length - 1
    assert res.substituted[:, 1:].all() and not res.substituted[:, 0].any()
    for t in range(1, length):
        fed = seen[t - 1]
        torch.testing.assert_close(fed[:, TRAJ_CONTROL], res.out[:, t - 1, TRAJ_OUT])
        # The phases (and anything outside the trajectory columns) stay ground truth.
        torch.testing.assert_close(fed[:, 42:], control[:, t, 42:])

    # With a prediction preceding the window, step 0 is fed back too; the default feedback
    # (given by column ranges) gives the same predictions as the explicit callable.
    with torch.no_grad():
        res2 = rollout(net, pose, control, 0.0, control_traj=TRAJ_CONTROL, out_traj=TRAJ_OUT,
                       prev_out=torch.zeros(2, OUT_DIM))
    assert res2.substituted.all()
    with torch.no_grad():
        res3 = rollout(net, pose, control, 0.0, control_traj=range(0, 42), out_traj=TRAJ_OUT)
    torch.testing.assert_close(res3.out, res.out)


def test_rollout_mixed_probability_is_per_sample() -> None:
    net = ControlNet(POSE_DIM, CONTROL_DIM, OUT_DIM, SMALL_CONTROL).eval()
    pose, control = torch.randn(64, 4, POSE_DIM), torch.randn(64, 4, CONTROL_DIM)
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        res = rollout(net, pose, control, 0.5, control_traj=TRAJ_CONTROL, out_traj=TRAJ_OUT,
                      generator=gen)
    frac = res.substituted[:, 1:].float().mean().item()
    assert 0.3 < frac < 0.7
    # Samples differ within a step (per sample), unlike the released code's batch-wide draw.
    assert (res.substituted[:, 1:].any(0) & ~res.substituted[:, 1:].all(0)).any()
    with torch.no_grad():
        batch_wide = rollout(net, pose, control, 0.5, control_traj=TRAJ_CONTROL,
                             out_traj=TRAJ_OUT, per_sample=False, generator=gen)
    col = batch_wide.substituted
    assert ((col == col[:1]).all())


@pytest.mark.parametrize(("epoch", "expected"),
                         [(0, 1.0), (3, 1.0), (6.5, 0.5), (10, 0.0), (20, 0.0)])
def test_scheduled_sampling_schedule(epoch: float, expected: float) -> None:
    assert scheduled_sampling_probability(epoch, ControlNetConfig()) == pytest.approx(expected)


def test_control_loss_terms() -> None:
    pred, target = torch.randn(4, OUT_DIM), torch.randn(4, OUT_DIM)
    line = torch.randn(4, 42)
    loss = control_loss(pred, target, line, (2.0, 3.0, 0.5), traj_cols=TRAJ_OUT,
                        phase_cols=PHASE_OUT)
    traj = ((pred[:, :42] - target[:, :42]) ** 2).mean()
    phase = ((pred[:, 42:] - target[:, 42:]) ** 2).mean()
    reg = (pred[:, :42] - line).norm(dim=-1).mean()
    torch.testing.assert_close(loss.total, 2 * traj + 3 * phase + 0.5 * reg)
    mse = control_loss(pred, target, line, traj_cols=TRAJ_OUT, phase_cols=PHASE_OUT, reg="mse")
    torch.testing.assert_close(mse.reg, ((pred[:, :42] - line) ** 2).mean())


# ------------------------------------------------------------------ overfitting


def _fit(loss_fn, params, steps: int = 150, lr: float = 3e-3) -> tuple[float, float]:
    opt = torch.optim.Adam(params, lr=lr)
    first = None
    for _ in range(steps):
        opt.zero_grad()
        loss = loss_fn()
        if first is None:
            first = loss.item()
        loss.backward()
        opt.step()
    with torch.no_grad():
        last = loss_fn().item()
    assert first is not None
    return first, last


def test_controlnet_overfits() -> None:
    net = ControlNet(POSE_DIM, CONTROL_DIM, OUT_DIM, SMALL_CONTROL)
    pose, control = torch.randn(4, 8, POSE_DIM), torch.randn(4, 8, CONTROL_DIM)
    target = torch.randn(4, 8, OUT_DIM)
    line = target[..., TRAJ_OUT] + 0.1 * torch.randn(4, 8, 42)
    gen = torch.Generator().manual_seed(1)

    def loss_fn() -> torch.Tensor:
        out = rollout(net, pose, control, 0.5, control_traj=TRAJ_CONTROL, out_traj=TRAJ_OUT,
                      generator=gen).out
        return control_loss(out, target, line, (1.0, 1.0, 0.1), traj_cols=TRAJ_OUT,
                            phase_cols=PHASE_OUT).total

    first, last = _fit(loss_fn, net.parameters())
    assert last < 0.3 * first


def test_posenet_overfits() -> None:
    net = _small_posenet()
    batch = _posenet_batch(net, 8)
    target = torch.randn(8, net.out_dim)
    first, last = _fit(lambda: F.mse_loss(net(batch)[0], target), net.parameters())
    assert last < 0.3 * first


def test_contactnet_overfits() -> None:
    net = ContactNet(40, 6, SMALL_CONTACT)
    c, cond = torch.randn(8, 6), torch.randn(8, 40)
    first, last = _fit(lambda: net.loss(c, cond)[0], net.parameters())
    assert last < 0.3 * first


# ------------------------------------------------------------------ ContactNet


def test_kl_formula() -> None:
    zeros = torch.zeros(3, 6)
    torch.testing.assert_close(kl_divergence(zeros, zeros), torch.zeros(3))
    # mu = 1, var = 1: 0.5 per dimension; mu = 0, var = e: 0.5 * (e - 1 - 1) per dimension.
    torch.testing.assert_close(kl_divergence(torch.ones(1, 6), torch.zeros(1, 6)),
                               torch.tensor([3.0]))
    torch.testing.assert_close(kl_divergence(torch.zeros(1, 2), torch.ones(1, 2)),
                               torch.tensor([np.e - 2.0]))


def test_contactnet_loss_and_sample_shapes() -> None:
    net = ContactNet(40, 6, SMALL_CONTACT)
    c, cond = torch.randn(5, 6), torch.randn(5, 40)
    total, recon, kl = net.loss(c, cond)
    assert total.shape == recon.shape == kl.shape == ()
    torch.testing.assert_close(total, recon + 0.1 * kl)
    gen = torch.Generator().manual_seed(0)
    s1 = net.sample(cond, 7, generator=gen)
    assert s1.shape == (5, 7, 6)
    s2 = net.sample(cond, 7, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(s1, s2)
    separate = ContactNet(40, 6, ContactNetConfig(condition_encoder=(8,), encoder_hidden=(8,),
                                                  decoder_hidden=(8,),
                                                  share_condition_encoder=False))
    assert separate.sample(cond, 2).shape == (5, 2, 6)
    assert separate(c, cond)[0].shape == (5, 6)


def test_project_contacts_on_unit_cube() -> None:
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))  # faces at +-0.5
    pred = np.array([[0.55, 0.1, -0.2],  # 5 cm outside the +x face
                     [0.1, 0.70, 0.0],  # 20 cm above the +y face
                     [0.0, 0.0, 0.45]])  # 5 cm inside the +z face
    projected, kept = project_contacts(torch.as_tensor(pred), cube.vertices, cube.faces)
    assert kept.tolist() == [True, False, True]
    np.testing.assert_allclose(projected[0], [0.5, 0.1, -0.2], atol=1e-9)
    np.testing.assert_allclose(projected[2], [0.0, 0.0, 0.5], atol=1e-9)
    _, kept_tight = project_contacts(pred, cube.vertices, cube.faces, max_distance=0.01)
    assert not kept_tight.any()


# ------------------------------------------------------------------ Normalizer


def test_normalizer_round_trip_and_state_dict() -> None:
    data = np.random.default_rng(0).normal(3.0, 2.0, size=(100, 5)).astype(np.float32)
    data[:, 4] = 7.0  # constant feature: std floored
    norm = Normalizer.from_data(data)
    assert norm.mean.dtype == torch.float32 and norm.std.shape == (5,)
    assert norm.std[4].item() == pytest.approx(1e-4)
    x = torch.as_tensor(data)
    z = norm.normalize(x)
    torch.testing.assert_close(z[:, :4].mean(0), torch.zeros(4), atol=1e-4, rtol=0)
    torch.testing.assert_close(norm.denormalize(z), x, atol=1e-4, rtol=1e-5)

    buf = io.BytesIO()
    torch.save(norm.state_dict(), buf)
    buf.seek(0)
    fresh = Normalizer(5)
    torch.testing.assert_close(fresh.normalize(x), x)  # identity before loading
    fresh.load_state_dict(torch.load(buf))
    torch.testing.assert_close(fresh.mean, norm.mean)
    torch.testing.assert_close(fresh.std, norm.std)
    torch.testing.assert_close(fresh.normalize(x), z)

    with pytest.raises(ValueError):
        Normalizer.from_stats(np.zeros(3), np.ones(4))


def test_posenet_select_outputs_keeps_the_columns_asked_for() -> None:
    net = _small_posenet().eval()
    batch = _posenet_batch(net, 4)
    with torch.no_grad():
        full, gates = net(batch)
    columns = [7, 0, 3, 4]  # any order
    net.select_outputs(columns)
    with torch.no_grad():
        got, got_gates = net(batch)
    assert got.shape == (4, 4) and net.out_dim == 4
    torch.testing.assert_close(got, full[:, columns], rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(got_gates, gates)
    with pytest.raises(ValueError, match="output columns"):
        net.select_outputs([4])  # out of the 4 left
    net.pack("fp16")
    with pytest.raises(RuntimeError, match="before pack"):
        net.select_outputs([0])


def test_posenet_takes_an_encoders_first_layer_instead_of_its_input() -> None:
    net = _small_posenet().eval()
    batch = _posenet_batch(net, 3)
    with torch.no_grad():
        want, _ = net(batch)
        first = {"I": net.encoders["I"][0](batch["I"])}
        got, _ = net({k: v for k, v in batch.items() if k != "I"}, first)
    torch.testing.assert_close(got, want)
    with pytest.raises(KeyError, match="missing input group 'I'"):
        net({k: v for k, v in batch.items() if k != "I"})


def test_posenet_follows_in_place_weight_updates() -> None:
    net = _small_posenet().eval()
    batch = _posenet_batch(net, 4)
    with torch.no_grad():
        cached, _ = net(batch)
    torch.testing.assert_close(cached, net(batch)[0].detach(), rtol=1e-5, atol=1e-5)
    with torch.no_grad():
        net.expert_weights[0].mul_(0.5)  # in place, as optimisers update
        after, _ = net(batch)
    assert not torch.allclose(after, cached)
    torch.testing.assert_close(after, net(batch)[0].detach(), rtol=1e-5, atol=1e-5)
