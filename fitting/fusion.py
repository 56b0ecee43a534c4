"""Fusion of the per-frame Kinect fits with the IMU motion over a sequence (COUCH Eq. 7 and 8;
issue 7, item 4).

The per-frame fits (:mod:`couch.fitting.body`) place the body where the cameras saw it but are
jittery, and wrong where the cameras were occluded; the synced IMU pose is smooth but its bone
orientations carry slowly varying biases and its feet slide. :func:`fuse_motion` optimises the
joint rotations and the translation of the whole sequence at once (frames are the batch dimension
of one torch optimisation) so the motion

* follows the Kinect fits where they are reliable: joint positions and bone world orientations
  near the fit's, each frame and joint weighted by its ``reliability`` (0 = ignore the fit);
* follows the IMU elsewhere: the local rotation of every joint is parametrised as the IMU's times
  a correction, ``R = R_imu · exp(δ)``, where δ is a cubic B-spline over time (control points
  every ``knot_frames`` frames) whose second differences are penalised (``sigma_bias_deg``: a
  constant or linearly drifting bias is free), so an occluded stretch keeps the IMU's motion with
  the bias measured around it, the fits' per-frame noise cannot get in, and δ stays small
  (``sigma_imu_deg``) where nothing else decides it; an optional per-frame residual
  (``sigma_frame_deg``, off by default) lets the fits correct the IMU frame by frame, and a
  constant rotation per segment (``sigma_misalign_deg``; 0 turns it off) models the
  suit's sensor-to-segment calibration, ``R = C_parentᵀ · R_imu · C_j · exp(δ)``, whose effect
  on a local rotation changes with the posture where a bias of the local rotation does not. The
  translation likewise is the IMU's plus a smooth correction when the IMU pose has one, else a
  smooth spline through the reliable fits (``sigma_transl_knot_m``);
* is smooth, COUCH Eq. 7: ``L_temp = Σ ||r_{i+1} − r_i||² + Σ ||j̈_i||²`` over local rotation
  matrices r and central-difference joint accelerations j̈ (both squared here, scales
  ``sigma_step_deg``, ``sigma_acc_m``);
* does not slide its feet, COUCH Eq. 8: ``L_slide = Σ ||f̃_i − f_i||²`` over the four foot points
  (heels and big toes, :data:`couch.fitting.metrics.FOOT_KEYPOINTS`, body-model keypoints) in the
  frames the IMU marks them in contact while the foot point is slow (``contact_max_speed``: a
  flag's first or last frame often catches the heel rising or landing), with targets f̃ one per
  contiguous run of such frames: the mean of the Kinect fits' foot point weighted by the
  reliability of its ankle and foot joints, plus the current motion's (``contact_motion_weight``
  per frame; recomputed between ``rounds``), the target height put on the floor
  (``floor_height`` plus the point's height above the sole in the rest pose) so feet in contact
  stand on the floor; and no foot point goes below the floor.

Every term is a squared residual over a scale (metres, degrees), summed over frames and divided
by T; the optimiser is L-BFGS over the whole sequence, in float64 (a float64 copy of a float32
model is made: in float32 the line search stalls on these stiff terms), on variables scaled by
the square root of their curvature (``precondition``): the terms' stiffnesses span four decades
(a leg's calibration rotation moves every planted foot point, a hand's only the hand), which
L-BFGS's short history does not learn. The frames' terms are summed over a few consecutive
spans of the sequence (``spans``), each posed with its neighbouring frames so the steps and
accelerations across a boundary count once, and the spans' gradients run on threads at once
(``threads``; the result is the same with any number): on a 30 s session at 30 fps the
fusion takes 5.9 s on one thread, 3.3 s on two (7.5 s in one span before the calibration
product and the depth-by-depth kinematics below and in :mod:`couch.body.lbs`).

Not done here: the fits' reliability must come from the caller (e.g. per-frame chamfer, point
count, the fit's ``fallback`` flags); the fusion runs on the body model it is given (coarse by
default, no full-model finish); and one call fuses one contiguous sequence held in memory.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import torch

from couch.body import BodyModel
from couch.body.skeleton import JOINT_INDEX
from couch.fitting.body import cached_model
from couch.fitting.metrics import FOOT_KEYPOINTS
from couch.fitting.params import BodyParams
from couch.fitting.skinning import Skinner
from couch.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from couch.runs import runs

__all__ = ["FusionConfig", "contact_runs", "fuse_motion"]


@dataclasses.dataclass(frozen=True)
class FusionConfig:
    """Scales (expected size of each residual; smaller = stronger) and optimiser settings.

    Lengths in metres, angles in degrees; "per frame" means between consecutive frames of a
    recording at ``reference_fps``: :func:`fuse_motion` given another ``fps`` converts them to
    the same rates per second (a rotation step per frame scales with 1/fps, an acceleration per
    frame² with 1/fps², a knot spacing in frames with fps), so a setting means the same motion
    at 5, 15 or 30 fps.
    """

    model: str = "couch-body-coarse"
    """Body model (name or path) when ``fuse_motion`` is given none."""
    sigma_kinect_m: float = 0.02
    """Joint position error of a reliable Kinect fit."""
    sigma_kinect_deg: float = 8.0
    """Bone world-orientation error of a reliable Kinect fit."""
    sigma_imu_deg: float = 10.0
    """Size of the correction to the IMU rotations (its bias) that nothing else decides."""
    knot_frames: int = 6
    """Spacing (frames) of the knots of the smooth part of the corrections to the IMU."""
    sigma_bias_deg: float = 0.5
    """Second difference per knot² of the smooth IMU rotation correction (how fast the IMU's
    bias changes its drift; a constant or linearly drifting bias costs nothing)."""
    sigma_bias_m: float = 0.005
    """Second difference per knot² of the smooth IMU translation correction (with an IMU
    translation; a constant offset or linear drift costs nothing)."""
    sigma_transl_knot_m: float = 0.005
    """Without an IMU translation: second difference per knot² of the translation spline
    (pelvis acceleration × (knot_frames / fps)²; 5 mm ≈ 0.125 m/s² at 6 frames, 30 fps: a soft
    scale against the fits' noise, reliable fits still move the pelvis faster)."""
    sigma_frame_deg: float = 0.0
    """Per-frame residual of the IMU rotation correction (the IMU's own noise; 0: none, the
    correction is the smooth spline alone). A residual lets the Kinect fits' per-frame noise
    back in, so keep it well below the fits' noise."""
    sigma_misalign_deg: float = 5.0
    """Size of each segment's constant sensor-to-segment calibration error (0: not modelled).
    A suit's calibration leaves every segment's orientation wrong by a constant rotation in
    the segment's own frame, ``R_reported = R_true · M``, so a joint's local rotation is wrong
    by ``M_parentᵀ · L · M_joint``: as the posture changes (arms hanging while walking, elbows
    bent on an armrest) the correction it needs changes with it, which the smooth bias alone
    carries over an occluded stretch as it was measured in the last posture the cameras saw.
    With this on, one constant rotation per joint (``C_j`` in ``C_parentᵀ · R_imu · C_j``) is
    fitted over the whole sequence, with this prior scale (the simulated suit's errors are 3°
    RMS per segment). On the 30 held-out simulator sessions it lowers MPJPE from 0.72 to 0.69
    cm and the hands' contact F1 moves from 0.937 / 0.940 to 0.943 / 0.940 (README,
    *Modelling the suit's calibration*)."""
    sigma_frame_m: float = 0.0
    """Per-frame residual of the IMU translation correction (0: none)."""
    sigma_step_deg: float = 10.0
    """L_temp, first term: local rotation change per frame."""
    sigma_acc_m: float = 0.01
    """L_temp, second term: central-difference joint acceleration per frame²."""
    sigma_slide_m: float = 0.002
    """L_slide: foot point distance to its contact target."""
    contact_motion_weight: float = 0.1
    """A contact run's target is the mean of the Kinect fits' foot point, weighted by their
    reliability, and the current motion's with this weight per frame (so a run the cameras
    did not see takes the motion's own mean)."""
    contact_max_speed: float = 0.3
    """A contact frame is held to its run's target only while the foot point moves slower
    than this (m/s, between neighbouring frames of the current motion)."""
    sigma_floor_m: float = 0.002
    """Foot point depth below the floor."""
    floor_height: float = 0.0
    """World height (Y) of the floor."""
    snap_to_floor: bool = True
    """Put contact targets on the floor (else only keep them above it)."""
    rounds: int = 3
    """Rounds of L-BFGS; the foot targets are recomputed from the motion before each."""
    iters: int = 50
    """L-BFGS iterations per round."""
    precondition: bool = True
    """Scale the optimiser's variables by the square root of their curvature (Jacobi; each
    estimated once before the first round by finite differences of the gradient, about 30
    gradient evaluations). The calibration rotations of the legs, which move every planted
    foot, are ~10⁴ times stiffer than those of the hands and L-BFGS's short history cannot
    learn that: on a 30 s session the fused joints ended 1.5 mm (mean) from the optimum after
    3 x 100 iterations without it, 0.7 mm after 3 x 50 with it."""
    spans: int = 2
    """The frames' terms are summed over this many consecutive spans of the sequence (at
    least 30 frames each), each span's loss and gradient computed apart, at the same time on
    up to ``threads`` threads of :func:`fuse_motion`: the same loss as one span, its sums in
    another order (which moves the optimum L-BFGS stops at by ~0.1 mm, mean over the joints of
    a 30 s session), and the same result whatever the threads."""
    device: str = "cpu"
    """Device of the default model (the optimisation runs in float64 whatever the model's)."""
    reference_fps: float = 30.0
    """Frame rate at which the per-frame scales and ``knot_frames`` are stated."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name.startswith(("sigma_frame", "sigma_misalign")):
                if not v >= 0:
                    raise ValueError(f"FusionConfig.{f.name} must be >= 0, got {v}")
            elif f.name.startswith("sigma_") and not v > 0:
                raise ValueError(f"FusionConfig.{f.name} must be > 0, got {v}")
        if self.knot_frames < 1:
            raise ValueError(f"FusionConfig.knot_frames must be >= 1, got {self.knot_frames}")
        if not self.reference_fps > 0:
            raise ValueError(f"FusionConfig.reference_fps must be > 0, got {self.reference_fps}")
        if self.spans < 1:
            raise ValueError(f"FusionConfig.spans must be >= 1, got {self.spans}")
        if self.rounds < 1 or self.iters < 1:
            raise ValueError(f"FusionConfig.rounds and iters must be >= 1, got "
                             f"{self.rounds}, {self.iters}")


def _second_difference(x: torch.Tensor) -> torch.Tensor:
    return x[2:] - 2.0 * x[1:-1] + x[:-2]


def _spline_basis(t: int, spacing: int) -> np.ndarray:
    """(T,K) uniform cubic B-spline weights of control points every ``spacing`` frames (one
    extra control point beyond each end): a C² curve, so the correction adds no jerk spikes."""
    n = max(1, int(np.ceil((t - 1) / spacing)))
    pos = np.linspace(0.0, n, t)
    x = np.abs(pos[:, None] - np.arange(-1, n + 2)[None])
    return np.where(x < 1, (4 - 6 * x ** 2 + 3 * x ** 3) / 6,
                    np.where(x < 2, (2 - x).clip(0) ** 3 / 6, 0.0))


def _diagonal_curvature(gradient: Callable[[], list[torch.Tensor]], params: list[torch.Tensor],
                        knots: torch.Tensor, knots_t: torch.Tensor, misalign: torch.Tensor,
                        parents: np.ndarray, *, step: float = 1e-4, probes: int = 2
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Estimates of the Hessian's diagonal of the loss whose gradient over ``params`` (the
    variables, holding the three named ones at scale 1) ``gradient`` returns: the difference of
    the gradient a ``step`` along a probe direction and at the current values (one gradient
    evaluation a probe; the variables are restored after each).

    * The rotation knots (K,24,3) and translation knots (K,3): ``probes`` random ±1 directions
      over both (Hutchinson's estimator), averaged over each joint's K·3 knots and over the
      translation's, where the off-diagonal terms' noise averages out: (1,24,1) and ().
    * The calibration rotations (24,3): one direction per depth of the skeleton and axis, the
      joints of that depth together. No term reads two joints of one depth (a joint's position
      and orientation depend on its ancestors and itself, its rotation step on itself and its
      parent), so each direction reads each of its joints' curvature exactly: (24,3). Ones
      when they are not optimised.
    """
    g0 = gradient()
    where = {id(p): i for i, p in enumerate(params)}

    def along(direction: dict[int, torch.Tensor]) -> list[torch.Tensor]:
        with torch.no_grad():
            saved = [p.clone() for p in params]
            for p in params:
                if id(p) in direction:
                    p.add_(step * direction[id(p)])
        g = gradient()
        with torch.no_grad():
            for p, v in zip(params, saved, strict=True):
                p.copy_(v)
        return [(a - b).detach() / step for a, b in zip(g, g0, strict=True)]

    gen = torch.Generator().manual_seed(0)
    c_knots = torch.zeros(1, knots.shape[1], 1, dtype=knots.dtype, device=knots.device)
    c_t = torch.zeros((), dtype=knots.dtype, device=knots.device)
    for _ in range(probes):
        signs = [(2 * torch.randint(0, 2, p.shape, generator=gen) - 1).to(p) for p in (knots,
                                                                                       knots_t)]
        hv = along({id(knots): signs[0], id(knots_t): signs[1]})
        c_knots += (hv[where[id(knots)]] * signs[0]).mean((0, 2), keepdim=True) / probes
        c_t += (hv[where[id(knots_t)]] * signs[1]).mean() / probes
    c_mis = torch.ones_like(misalign)
    if id(misalign) in where:
        depth = np.zeros(len(parents), int)
        for j in range(1, len(parents)):  # parents precede their children
            depth[j] = depth[parents[j]] + 1
        for level in range(depth.max() + 1):
            joints = np.flatnonzero(depth == level)
            for axis in range(3):
                direction = torch.zeros_like(misalign)
                direction[joints, axis] = 1.0
                hv = along({id(misalign): direction})[where[id(misalign)]]
                c_mis[joints, axis] = hv[joints, axis]
    return c_knots, c_t, c_mis


def contact_runs(contact: np.ndarray) -> list[tuple[int, int, int]]:
    """Contiguous runs of contact: (point k, first frame, end frame exclusive) for (T, K) bool."""
    c = np.asarray(contact, dtype=bool)
    return [(k, int(s), int(e)) for k in range(c.shape[1]) for s, e in zip(*runs(c[:, k]),
                                                                            strict=True)]


def _local_rotations(x: Any, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(T,24,3,3) local rotations and the (T,3) translation (or None) of a pose input."""
    if isinstance(x, BodyParams):
        aa = np.concatenate([x.global_orient, x.body_pose], 1).reshape(-1, 24, 3)
        return axis_angle_to_matrix(aa.astype(np.float64)), x.transl.astype(np.float64)
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 3 and a.shape[1:] == (24, 3):
        rot = axis_angle_to_matrix(a)
    elif a.ndim == 4 and a.shape[1:] == (24, 3, 3):
        rot = a
        if not np.allclose(rot @ np.swapaxes(rot, -1, -2), np.eye(3), atol=1e-3):
            raise ValueError(f"{name}: (T,24,3,3) matrices are not rotations")
    else:
        raise ValueError(f"{name} must be BodyParams, (T,24,3) axis-angle or (T,24,3,3) "
                         f"rotations, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds NaN or infinite values")
    return rot, None


def _check(kinect_fit: Any, imu_pose: Any, reliability: Any, foot_contact: Any
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    if not isinstance(kinect_fit, BodyParams):
        raise ValueError(f"kinect_fit must be BodyParams, got {type(kinect_fit).__name__}")
    t = kinect_fit.num_frames
    if t < 3:
        raise ValueError(f"fusion needs >= 3 frames, got {t}")
    kin_rot, _ = _local_rotations(kinect_fit, "kinect_fit")
    imu_rot, imu_transl = _local_rotations(imu_pose, "imu_pose")
    if len(imu_rot) != t:
        raise ValueError(f"imu_pose has {len(imu_rot)} frames, kinect_fit {t}")
    rel = np.asarray(reliability, dtype=np.float64)
    if rel.shape == (t,):
        rel = np.repeat(rel[:, None], 24, axis=1)
    if rel.shape != (t, 24):
        raise ValueError(f"reliability must be (T,) or (T,24) with T = {t}, got {rel.shape}")
    if not np.all(np.isfinite(rel)) or (rel < 0).any():
        raise ValueError("reliability must be finite and >= 0")
    fc = np.asarray(foot_contact)
    if fc.shape != (t, len(FOOT_KEYPOINTS)) or fc.dtype != bool:
        raise ValueError(f"foot_contact must be ({t}, {len(FOOT_KEYPOINTS)}) bool "
                         f"({', '.join(FOOT_KEYPOINTS)}), got {fc.shape} {fc.dtype}")
    return kin_rot, imu_rot, imu_transl, rel, fc


def fuse_motion(kinect_fit: BodyParams, imu_pose: Any, reliability: Any, foot_contact: Any,
                model: BodyModel | None = None, config: FusionConfig | None = None, *,
                fps: float | None = None, threads: int = 1) -> BodyParams:
    """Fuse per-frame Kinect fits with the synced IMU pose over a whole sequence.

    Args:
        kinect_fit: T frames of per-frame fits (world, metres, Y up); its betas are the
            subject's and stay fixed.
        imu_pose: the synced IMU pose on the same frames: :class:`BodyParams` (its translation
            then gives the motion's velocity where the fits are unreliable), or (T,24,3)
            axis-angle / (T,24,3,3) local joint rotations, SMPL order.
        reliability: (T,) or (T,24) >= 0 weights of the fits (per frame or per joint; 0 for a
            fallback frame or a garbage fit, 1 for a good one), e.g. from the fit's chamfer.
        foot_contact: (T,4) bool, the IMU's heel/toe contacts in ``FOOT_KEYPOINTS`` order.
        model: body model (default ``config.model``); must have the foot keypoints.
        config: scales and optimiser settings.
        fps: the sequence's frame rate (default ``config.reference_fps``); the per-frame
            scales are converted to it.
        threads: threads computing the spans' gradients (``config.spans``) at once; the
            result is the same with any number.

    Returns:
        The fused parameters (same betas).

    Raises:
        ValueError: on inputs of the wrong type, shape or frame count, NaNs, negative
            reliabilities, a model without foot keypoints, or threads < 1.
    """
    cfg = config or FusionConfig()
    rate = cfg.reference_fps if fps is None else float(fps)
    if not rate > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    # per-frame scales of the config are at reference_fps: the same rates per second at ``rate``
    slow = cfg.reference_fps / rate  # reference frames per frame of this sequence
    knot_frames = max(1, round(cfg.knot_frames / slow))
    kin_rot, imu_rot, imu_transl, rel, fc = _check(kinect_fit, imu_pose, reliability,
                                                   foot_contact)
    model = model if model is not None else cached_model(cfg.model, cfg.device, "float64")
    missing = [k for k in FOOT_KEYPOINTS if k not in model.keypoint_ids]
    if missing:
        raise ValueError(f"the body model has no keypoint(s) {', '.join(missing)}")
    if model.dtype != torch.float64:  # L-BFGS on these stiff terms needs double precision
        model = copy.deepcopy(model).to(dtype=torch.float64)
    dev, dt = model.device, model.dtype

    def tensor(x: Any) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x), dtype=dt, device=dev)

    t = kinect_fit.num_frames
    skin = Skinner(model)
    betas = tensor(kinect_fit.betas)
    with torch.no_grad():
        v_shaped, rest_joints = skin.rest(betas)
    foot_ids = torch.as_tensor([model.keypoint_ids[k] for k in FOOT_KEYPOINTS], device=dev)
    foot_index = foot_ids.expand(t, -1)
    clearance = (v_shaped[foot_ids, 1] - v_shaped[:, 1].min()).clamp(min=0.0)

    r_imu = tensor(imu_rot)
    r_imu_joints = r_imu.reshape(t, 24, 9).transpose(0, 1).contiguous()  # (24,T,9)
    r_kin = tensor(kin_rot)
    w_rel = tensor(rel)
    t_kin = tensor(kinect_fit.transl)
    with torch.no_grad():
        kin_posed = skin.pose(r_kin, rest_joints, t_kin)
        kin_joints, kin_orient = kin_posed.joints, kin_posed.orient
    # translation: the IMU's plus a slow correction when the IMU has one, else a free spline
    # (starting at the Kinect translation, interpolated over unreliable frames) that only
    # L_temp and the data terms shape
    frame_w = rel.mean(1)
    if imu_transl is not None:
        t_base = tensor(imu_transl)
        ok = frame_w > 0
        d0 = (np.mean(kinect_fit.transl[ok] - imu_transl[ok], axis=0) if ok.any()
              else np.zeros(3))
        dtransl0 = np.tile(d0, (t, 1))
    else:
        ok = frame_w > 0
        base = kinect_fit.transl.astype(np.float64)
        if ok.any():
            idx = np.arange(t)
            base = np.stack([np.interp(idx, idx[ok], base[ok, i]) for i in range(3)], 1)
        t_base = tensor(np.zeros((t, 3)))
        dtransl0 = base
    # corrections: smooth (a cubic B-spline, control points every knot_frames frames) plus an
    # optional per-frame residual; few smooth parameters keep L-BFGS well conditioned
    basis_np = _spline_basis(t, knot_frames)
    basis = tensor(basis_np)
    n_knots = basis.shape[1]
    # the optimiser's variables: the knots and calibration rotations, each times its scale
    # (1 until ``precondition`` sets them), so ``unscaled()`` gives their values
    knots = torch.zeros(n_knots, 24, 3, dtype=dt, device=dev, requires_grad=True)
    eps = torch.zeros(t, 24, 3, dtype=dt, device=dev, requires_grad=cfg.sigma_frame_deg > 0)
    misalign = torch.zeros(24, 3, dtype=dt, device=dev, requires_grad=cfg.sigma_misalign_deg > 0)
    # numpy's SVD least squares: torch's default CPU driver (gelsy) answered the same system
    # differently in the last bits from call to call (17 results in 30 calls), which L-BFGS
    # carried to ~0.5 mm in the fused joints
    knots_t = tensor(np.linalg.lstsq(basis_np, dtransl0, rcond=None)[0]).requires_grad_(True)
    eps_t = torch.zeros(t, 3, dtype=dt, device=dev, requires_grad=cfg.sigma_frame_m > 0)
    scaled = [knots, knots_t, misalign]
    scales = [torch.ones(1, 24, 1, dtype=dt, device=dev), torch.ones((), dtype=dt, device=dev),
              torch.ones(24, 3, dtype=dt, device=dev)]
    params = [p for p in (knots, eps, knots_t, eps_t, misalign) if p.requires_grad]
    parents = model.parents.cpu().numpy()

    def unscaled() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The spline knots (K,24,3), translation knots (K,3) and calibration rotations (24,3)."""
        k, k_t, m = (p / s for p, s in zip(scaled, scales, strict=True))
        return k, k_t, m

    def corrections(knots: torch.Tensor, knots_t: torch.Tensor, lo: int = 0,
                    hi: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The rotation (F,24,3) and translation (F,3) corrections of frames ``lo:hi``."""
        delta = torch.einsum("tk,kjc->tjc", basis[lo:hi], knots) + eps[lo:hi]
        return delta, basis[lo:hi] @ knots_t + eps_t[lo:hi]

    s_kin_rot = np.deg2rad(cfg.sigma_kinect_deg)
    s_imu = np.deg2rad(cfg.sigma_imu_deg)
    s_bias = np.deg2rad(cfg.sigma_bias_deg)
    s_frame = np.deg2rad(cfg.sigma_frame_deg)
    s_misalign = np.deg2rad(cfg.sigma_misalign_deg)
    s_step = np.deg2rad(cfg.sigma_step_deg) * slow
    s_acc = cfg.sigma_acc_m * slow ** 2
    max_step = cfg.contact_max_speed / rate  # metres per frame
    with torch.no_grad():
        kin_feet = skin.vertices(kin_posed, v_shaped, foot_index)
    # reliability of the fits' foot points: their ankle and foot joints (heel, toe per side)
    left, right = ([JOINT_INDEX[f"{side}_ankle"], JOINT_INDEX[f"{side}_foot"]]
                   for side in ("left", "right"))
    foot_joints = np.array([left, left, right, right])  # FOOT_KEYPOINTS order: L, L, R, R
    foot_rel = tensor(rel[:, foot_joints].mean(-1))

    def imu_rotations(misalign: torch.Tensor, lo: int = 0, hi: int | None = None
                      ) -> torch.Tensor:
        """(F,24,3,3) the IMU's local rotations of frames ``lo:hi`` with each segment's
        constant calibration error taken out: ``C_parentᵀ · R_imu · C_j`` (the root has no
        parent)."""
        if cfg.sigma_misalign_deg <= 0:
            return r_imu[lo:hi]
        c = axis_angle_to_matrix(misalign)  # (24,3,3)
        c_parent = torch.cat([torch.eye(3, dtype=dt, device=dev)[None], c[parents[1:]]])
        # a joint's A·R·B is linear in R: one (9,9) matrix per joint, K[(l,m),(i,k)] = A_il B_mk
        # with A = C_parentᵀ, B = C_j, applied to all frames' R as one product per joint
        # (3.5x faster with its gradient than two products of T·24 3×3 matrices)
        k = torch.einsum("jli,jmk->jlmik", c_parent, c).reshape(24, 9, 9)
        f = r_imu_joints[:, lo:hi]
        return torch.bmm(f, k).permute(1, 0, 2).reshape(f.shape[1], 24, 3, 3)

    def forward(knots: torch.Tensor, knots_t: torch.Tensor, misalign: torch.Tensor,
                lo: int = 0, hi: int | None = None) -> tuple[torch.Tensor, torch.Tensor, Any]:
        """The corrections δ, local rotations and posed skeletons of frames ``lo:hi``."""
        delta, dtransl = corrections(knots, knots_t, lo, hi)
        local = imu_rotations(misalign, lo, hi) @ axis_angle_to_matrix(delta)
        return delta, local, skin.pose(local, rest_joints, t_base[lo:hi] + dtransl)

    def targets() -> tuple[torch.Tensor, torch.Tensor]:
        """Each contact run's foot target and the frames held to it: the IMU's contact flags
        where the current motion's foot point is slow (a flag's first or last frame often
        catches the heel rising or landing, more so at low frame rates)."""
        with torch.no_grad():
            _, _, posed = forward(*unscaled())
            feet = skin.vertices(posed, v_shaped, foot_index)
        f = feet.cpu().numpy()
        step = np.zeros(f.shape[:2])
        if t > 1:
            v = np.linalg.norm(np.diff(f, axis=0), axis=-1)  # (T-1, 4)
            step = np.maximum(np.vstack([v, v[-1:]]), np.vstack([v[:1], v]))
        held = fc & (step <= max_step)
        tgt = feet.clone()
        for k, s, e in contact_runs(held):
            # where the fits saw the foot, they place it; the current motion fills in
            w = foot_rel[s:e, k, None]
            mean = ((w * kin_feet[s:e, k]).sum(0) + cfg.contact_motion_weight * feet[s:e, k].sum(0)
                    ) / (w.sum() + cfg.contact_motion_weight * (e - s))
            if cfg.snap_to_floor:
                mean[1] = cfg.floor_height + clearance[k]
            else:
                mean[1] = torch.clamp(mean[1], min=cfg.floor_height)
            tgt[s:e, k] = mean
        return tgt, tensor(held)

    def sequence_terms() -> torch.Tensor:
        """The terms over the knots and the calibration (not over frames)."""
        knots, knots_t, misalign = unscaled()
        loss = _second_difference(knots).square().sum() / s_bias ** 2
        if cfg.sigma_misalign_deg > 0:
            # one prior for the sequence (the data terms are per frame): the whole divided by T
            # below makes it weaker the longer the sequence that measures the constants
            loss = loss + misalign.square().sum() / s_misalign ** 2
        s_t = cfg.sigma_bias_m if imu_transl is not None else cfg.sigma_transl_knot_m
        return loss + _second_difference(knots_t).square().sum() / s_t ** 2

    def frame_terms(tgt: torch.Tensor, contact: torch.Tensor, a: int, b: int) -> torch.Tensor:
        """The terms of frames ``a:b``: their data, correction and foot terms, the rotation
        steps to their next frames and the accelerations centred on them. The motion is
        posed on ``a-1:b+1``, so consecutive spans' terms sum to the whole sequence's."""
        lo, hi = max(a - 1, 0), min(b + 1, t)
        delta, local, posed = forward(*unscaled(), lo, hi)
        own = slice(a - lo, b - lo)
        joints = posed.joints
        # Kinect data terms, reliability-weighted per frame and joint
        pos = (joints[own] - kin_joints[a:b]).square().sum(-1) / cfg.sigma_kinect_m ** 2
        rot = (posed.orient[own] - kin_orient[a:b]).square().sum((-1, -2)) / 2.0 / s_kin_rot ** 2
        loss = (w_rel[a:b] * (pos + rot)).sum()
        # IMU: small correction
        loss = loss + delta[own].square().sum() / s_imu ** 2
        if cfg.sigma_frame_deg > 0:
            loss = loss + eps[a:b].square().sum() / s_frame ** 2
        if cfg.sigma_frame_m > 0:
            loss = loss + eps_t[a:b].square().sum() / cfg.sigma_frame_m ** 2
        # L_temp (Eq. 7): steps i -> i+1 and accelerations at i, for frames i in a:b
        e = min(b, t - 1)
        loss = loss + (local[a - lo + 1:e - lo + 1] - local[a - lo:e - lo]
                       ).square().sum() / 2.0 / s_step ** 2
        s0 = max(a, 1)
        if e > s0:
            acc = _second_difference(joints[s0 - lo - 1:e - lo + 1])
            loss = loss + acc.square().sum() / s_acc ** 2
        # L_slide (Eq. 8) and the floor
        feet = skin.vertices(posed, v_shaped, foot_index[:hi - lo])[own]
        slide = (feet - tgt[a:b]).square().sum(-1) * contact[a:b]
        loss = loss + slide.sum() / cfg.sigma_slide_m ** 2
        below = torch.clamp(cfg.floor_height - feet[..., 1], min=0.0)
        return loss + below.square().sum() / cfg.sigma_floor_m ** 2

    # the frames' terms in contiguous spans, each span's gradient on a thread of its own
    # (torch runs an operation's kernel and a graph's backward without holding the GIL)
    n_spans = max(1, min(cfg.spans, t // 30))
    bounds = np.linspace(0, t, n_spans + 1).round().astype(int)
    spans = list(zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True))

    def span_gradient(tgt: torch.Tensor, held: torch.Tensor, i: int
                      ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        loss = frame_terms(tgt, held, *spans[i])
        if i == 0:
            loss = loss + sequence_terms()
        loss = loss / t
        return loss.detach(), torch.autograd.grad(loss, params)

    def evaluate(tgt: torch.Tensor, held: torch.Tensor
                 ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """The loss and its gradient over ``params``, the spans' summed in order."""
        run = map if executor is None else executor.map
        parts = list(run(lambda i: span_gradient(tgt, held, i), range(len(spans))))
        loss = functools.reduce(torch.add, (p[0] for p in parts))
        grads = [functools.reduce(torch.add, g) for g in zip(*(p[1] for p in parts),
                                                               strict=True)]
        return loss, grads

    with contextlib.ExitStack() as stack:
        workers = min(threads, len(spans))
        executor = stack.enter_context(ThreadPoolExecutor(workers)) if workers > 1 else None
        if cfg.precondition:
            tgt, held = targets()

            def gradient() -> list[torch.Tensor]:
                return evaluate(tgt, held)[1]

            curvatures = _diagonal_curvature(gradient, params, knots, knots_t, misalign,
                                             parents)
            ref = curvatures[0].max()
            if ref > 0:
                with torch.no_grad():
                    # Jacobi: each variable's curvature that of the stiffest joint's knots
                    for p, s, c in zip(scaled, scales, curvatures, strict=True):
                        s.copy_((c.clamp(min=1e-3 * ref) / ref).sqrt())
                        p.mul_(s)
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=cfg.iters,
                                history_size=20,
                                line_search_fn="strong_wolfe", tolerance_grad=1e-9,
                                tolerance_change=1e-12)
        for _ in range(cfg.rounds):
            tgt, held = targets()

            def closure(tgt: torch.Tensor = tgt, held: torch.Tensor = held) -> torch.Tensor:
                loss, grads = evaluate(tgt, held)
                for p, g in zip(params, grads, strict=True):
                    p.grad = g
                return loss

            opt.step(closure)
    with torch.no_grad():
        knots, knots_t, misalign = unscaled()
        _, local, _ = forward(knots, knots_t, misalign)
        aa = matrix_to_axis_angle(local).double().cpu().numpy()
        transl = (t_base + corrections(knots, knots_t)[1]).double().cpu().numpy()
    return BodyParams(aa[:, 0], aa[:, 1:].reshape(t, 69), transl, kinect_fit.betas)

