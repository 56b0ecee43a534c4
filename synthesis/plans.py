"""ControlNet's plans as the runtime makes them: one vectorised step for B characters
(:func:`control_step`, the controller's) and the replay of a trained ControlNet over a feature
cache (:func:`replay_plans`), from which PoseNet can be trained on the control input it will
read at runtime instead of the data's future hand paths (``TrainConfig.control_source``).

Frames and units as in :mod:`couch.synthesis.features`: plans are (…, 2, K, 3) metres relative
to each hand's contact, rotated into the root frame; phases (…, 2, K) in [0, 1]; hand order
(left, right).
"""

from __future__ import annotations

import numpy as np
import torch

from couch.synthesis.data import FeatureCache
from couch.synthesis.features import FeatureStats, control_in_root
from couch.synthesis.nets import ControlNet, LSTMState

__all__ = ["REPLAN_RADIUS", "control_step", "replan_lost", "replay_plans"]

#: metres: a fed-back plan whose present sample is farther than this from the hand is
#: restarted from the straight line (:func:`replan_lost`; chosen on validation chairs).
REPLAN_RADIUS = 0.3


def replan_lost(fed_back: np.ndarray, straight: np.ndarray, fresh: np.ndarray,
                mask: np.ndarray, radius: float) -> np.ndarray:
    """ControlNet's control input h̃ (B,2,K,3): its fed-back plan ``fed_back``, or the straight
    line ``straight`` (both (B,2,K,3), relative to the contact, root frame) for hands whose
    control just switched on (``fresh``, (B,2) bool) or whose plan is lost: its first sample
    (where the hand is now, as last frame predicted it) more than ``radius`` m from the
    straight line's (where the hand is). Zeros where ``mask`` (B,2) is False; ``radius`` <= 0
    never replans a running plan.

    ControlNet is trained on 2 s windows with its own plan fed back. Over a 16 s trial its plan
    drifts from the hand while the body walks up and turns (traced on 64 trials of one
    training at 0.3 m: 27 replans a trial, a median 4 s in, with the hand 71 cm from its
    contact); replanned, that training's couch hands ended 15-21 % closer on the test
    chairs and 93-95 % of its trials sat where 84-91 % had (README, *Results so far*). At
    0.1 m it also restarts plans that collapsed after a touch onto the all-zero plan of a hand
    with no contact (the hand 15 cm off): ACE was no better.
    """
    lost = np.zeros(mask.shape, bool)
    if radius > 0:
        lost = np.linalg.norm(fed_back[..., 0, :] - straight[..., 0, :], axis=-1) > radius
    return np.where((fresh | lost)[..., None, None], straight, fed_back) * mask[..., None, None]


def control_step(net: ControlNet, stats: FeatureStats, lstm: LSTMState, jpos: np.ndarray, *,
                 straight: np.ndarray, plan: np.ndarray, phases: np.ndarray,
                 past_phases: np.ndarray, on: np.ndarray, mask: np.ndarray, replan: float,
                 device: torch.device) -> tuple[np.ndarray, np.ndarray, LSTMState]:
    """One ControlNet frame for B characters, as the runtime runs it: the control input is the
    last ``plan`` fed back, or the ``straight`` line where a hand's control just switched on or
    its plan is lost (:func:`replan_lost`); the hands' local phases are their past ones and the
    last predicted ones; a character whose control switches on with no hand on before starts
    from the LSTM's initial state.

    Args:
        net, stats: the trained ControlNet and its normalisation.
        lstm: its state ``(h, c)``, each (layers, B, hidden).
        jpos: (B,22,3) root-frame joint positions (m).
        straight: (B,2,K,3) the straight line from each hand to its contact; plan: (B,2,K,3)
            and phases (B,2,K) last frame's prediction.
        past_phases: (B,P,2) the hands' local phases at the trajectory's P past samples.
        on: (B,2) bool, hands whose control was on last frame; mask: (B,2) bool, this frame.
        replan: :func:`replan_lost`'s radius (m).
    Returns:
        the plan C⁺ (B,2,K,3) (zeros where ``mask`` is False), its phases (B,2,K) clipped to
        [0, 1] (zeros likewise), and the new LSTM state.
    """
    batch = len(jpos)
    fresh = mask & ~on
    line = replan_lost(plan, straight, fresh, mask, replan)
    hphase = np.concatenate([past_phases.transpose(0, 2, 1), phases], -1) * mask[..., None]
    restart = fresh.any(-1) & ~on.any(-1)
    if restart.any():
        h0, c0 = net.initial_state(int(restart.sum()), device)
        idx = torch.as_tensor(np.flatnonzero(restart), device=device)
        lstm[0][:, idx], lstm[1][:, idx] = h0, c0

    def norm(g: str, x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(stats.normalize(g, x.reshape(batch, -1)).astype(np.float32),
                               device=device)

    control = torch.cat([norm("control_line", line), norm("hand_phases", hphase)], -1)
    with torch.no_grad():
        out, lstm = net.step(norm("joint_positions", jpos), control, lstm)
    out = out.cpu().numpy().astype(np.float64)
    n_pos = line[0].size
    pos = stats.denormalize("next_control_positions", out[:, :n_pos])
    ph = stats.denormalize("next_control_phases", out[:, n_pos:])
    pos = pos.reshape(line.shape) * mask[..., None, None]
    ph = np.clip(ph.reshape(batch, 2, -1), 0.0, 1.0) * mask[..., None]
    return pos, ph, lstm


def replay_plans(cache: FeatureCache, net: ControlNet, stats: FeatureStats, *,
                 replan: float = REPLAN_RADIUS, device: str | torch.device = "cpu"
                 ) -> tuple[np.ndarray, np.ndarray]:
    """ControlNet run over every sequence of ``cache`` as the runtime runs it
    (:class:`couch.synthesis.controller.Synthesizer`): the data's pose and control mask, the
    straight line where a hand's control switches on or its plan is lost, its own plan and
    phases fed back otherwise.

    Returns:
        PoseNet's control input per cache row: ``control_root_positions`` (N, 2*K*3) (the
        plans moved to the root's origin, :func:`control_in_root`) and ``control_phases``
        (N, 2*K), float32, zeros where the data's control is off.
    """
    device = torch.device(device)
    cfg = cache.config
    offsets = np.asarray(cfg.trajectory_offsets)
    past = offsets[offsets < 0]
    lengths = cache.lengths()
    n_seq, n_max, k = cache.num_sequences, int(lengths.max()), cfg.control_samples
    # Sequences run side by side, each padded to the longest (rows past its end are masked).
    rows = np.minimum(cache.offsets[:-1, None] + np.arange(n_max), cache.offsets[1:, None] - 1)
    valid = np.arange(n_max) < lengths[:, None]  # (S, n_max)
    mask_all = (cache.group("hand_mask")[rows] > 0.5) & valid[..., None]
    jpos_all = cache.group("joint_positions")[rows].reshape(n_seq, n_max, -1, 3)
    line_all = cache.group("control_line")[rows].reshape(n_seq, n_max, 2, k, 3)
    history = np.zeros((n_seq, int(-past.min()), 2))
    plan, phases = np.zeros((n_seq, 2, k, 3)), np.zeros((n_seq, 2, k))
    on = np.zeros((n_seq, 2), bool)
    lstm = net.initial_state(n_seq, device)
    plans, plan_phases = np.zeros((n_seq, n_max, 2, k, 3)), np.zeros((n_seq, n_max, 2, k))
    for t in range(n_max):
        mask = mask_all[:, t]
        plan, phases, lstm = control_step(
            net, stats, lstm, jpos_all[:, t], straight=line_all[:, t].astype(np.float64),
            plan=plan, phases=phases, past_phases=history[:, len(history[0]) + past], on=on,
            mask=mask, replan=replan, device=device)
        history = np.concatenate([history[:, 1:], phases[:, None, :, 0]], 1)
        on = mask
        plans[:, t], plan_phases[:, t] = plan, phases
    # the contacts' root-frame positions are the first six columns of the baseline's input
    target_root = cache.group("contact_inputs")[rows][..., :6].reshape(n_seq, n_max, 2, 3)
    root_plans = control_in_root(plans, target_root, mask_all)
    return (root_plans[valid].reshape(-1, 2 * k * 3).astype(np.float32),
            plan_phases[valid].reshape(-1, 2 * k).astype(np.float32))
