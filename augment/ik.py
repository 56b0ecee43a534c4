"""IK re-posing of a captured motion onto moved contact targets (augmentation, issue item 3).

After a chair swap (:mod:`couch.augment.transfer`) each contact point of the five contact parts
(:data:`couch.body.CONTACT_NAMES`: pelvis, left/right hand, left/right foot) moves by an offset.
This module turns those offsets into smooth per-frame targets and re-poses the body to reach them
(TRUMANS, Jiang et al. CVPR 2024, Appendix B.5; COUCH, Zhang et al. ECCV 2022, Sec. 3):

1. :func:`smooth_offsets` spreads each contact run's offset over ``window`` frames before and
   after the run with a linear falloff (TRUMANS Eq. A3) and blends overlapping runs by their
   norms (Eq. A5).
2. :func:`reference_vertices` picks, per frame and part, the body vertex that carries the
   contact (the part's contact vertex nearest to the source contact point); the target of that
   vertex is its source position plus the smoothed offset (:func:`contact_targets`).
3. :func:`reposition` solves full-body IK for all frames at once: a batched, clipped-step Adam
   optimisation in torch of a per-bone rotation correction (composed on the right of the
   captured local rotation, so 0 = the captured pose) and a translation correction. Terms:
   reach (reference vertex → target), keep the captured pose (per-bone weights, heavy on
   spine/legs/root), keep planted feet where they were in the source, temporal smoothness of
   the correction, and no new joint-limit excess (:func:`couch.fitting.limits.joint_limit_excess`
   beyond the source's own). The total correction per bone is bounded (smoothly, ``tanh``) by
   ``max_correction_deg``, with ``distal_scale`` times more for wrists, hands, ankles and feet
   (TRUMANS: "bones further from the root joint have increased rotational limits"), and each
   iteration's change per bone is clipped to ``max_step_deg`` (TRUMANS' clipped CCD steps).
4. :func:`penetration` measures the deepest body vertex inside the (watertight) chair per frame.

World frame throughout: metres, Y up, floor y = 0; frames first.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
import torch
from scipy import ndimage

from couch.augment.sdf import SignedDistanceGrid
from couch.body import CONTACT_NAMES, JOINT_INDEX, BodyModel
from couch.fitting import BodyParams, contact_runs, joint_limit_excess, pose_body
from couch.rotations import axis_angle_to_matrix, matrix_to_axis_angle

__all__ = [
    "DISTAL_JOINTS",
    "IKConfig",
    "IKResult",
    "contact_targets",
    "default_reference",
    "penetration",
    "reference_vertices",
    "reposition",
    "smooth_offsets",
]

#: Bones with the larger correction bound (TRUMANS: farther from the root, larger limits).
DISTAL_JOINTS: tuple[str, ...] = ("left_ankle", "right_ankle", "left_foot", "right_foot",
                                  "left_wrist", "right_wrist", "left_hand", "right_hand")
#: Bones whose change costs ``core_weight`` times more (pose kept when only the hands move).
CORE_JOINTS: tuple[str, ...] = ("pelvis", "left_hip", "right_hip", "spine1", "left_knee",
                                "right_knee", "spine2", "left_ankle", "right_ankle", "spine3",
                                "left_foot", "right_foot", "neck", "head")
#: Foot keypoints (body-model ``keypoint_ids``) held in place while a foot is planted.
FOOT_POINTS: tuple[tuple[str, ...], tuple[str, ...]] = (("LHeel", "LBigToe", "LSmallToe"),
                                                        ("RHeel", "RBigToe", "RSmallToe"))
_CM = 0.01  # metres: the unit of the reach and plant residuals in the objective


# ----------------------------------------------------------------------------- offsets


def smooth_offsets(offsets: np.ndarray, active: np.ndarray, window: int = 30) -> np.ndarray:
    """Spread contact offsets over time with TRUMANS' linear falloff and norm-weighted blending.

    For each part ``k`` and each run ``[s, e]`` of consecutive frames where ``active[:, k]``:

    - inside the run the offset is the run's own per-frame offset, applied fully;
    - at a frame ``t`` outside it the run contributes ``c = (1 - d / window) * o`` for
      ``d < window`` (0 beyond), where ``d`` is the frame distance to the run (``s - t`` before
      it, ``t - e`` after) and ``o`` is the run's offset at its nearest end (``offsets[s]`` or
      ``offsets[e]``): TRUMANS Eq. (A3), reaching zero ``window`` frames away.

    Frames outside every run of ``k`` get the norm-weighted mean of the contributions of all
    runs of ``k``: ``Σ |c_r| c_r / Σ |c_r|`` (TRUMANS Eq. A5; a single contribution is returned
    unchanged; zero when all are zero). A frame inside a run keeps that run's offset (the contact
    must hold exactly), whatever other runs are within the window. Parts are independent.

    Args:
        offsets: (T, K, 3) metres, target minus source contact point; read only where active
            (NaN allowed elsewhere).
        active: (T, K) bool contact flags.
        window: W >= 1 frames of falloff before and after each run.

    Returns:
        (T, K, 3) float64 smoothed offsets (0 far from every run).
    """
    off = np.asarray(offsets, dtype=np.float64)
    act = np.asarray(active, dtype=bool)
    if off.ndim != 3 or off.shape[2] != 3 or act.shape != off.shape[:2]:
        raise ValueError(f"offsets must be (T, K, 3) and active (T, K), got {off.shape} and "
                         f"{act.shape}")
    if window < 1:
        raise ValueError(f"window must be >= 1 frame, got {window}")
    if np.any(~np.isfinite(off[act])):
        raise ValueError("offsets hold NaN or infinite values on active frames")
    t_idx = np.arange(len(off))
    out = np.zeros_like(off)
    for k in range(off.shape[1]):
        num = np.zeros((len(off), 3))
        den = np.zeros(len(off))
        for _, s, end in contact_runs(act[:, [k]]):
            e = end - 1  # the run's last frame
            before = t_idx < s
            d = np.where(before, s - t_idx, t_idx - e).astype(np.float64)
            w = np.clip(1.0 - d / window, 0.0, None)
            w[s:e + 1] = 0.0
            c = w[:, None] * np.where(before[:, None], off[s, k], off[e, k])
            n = np.linalg.norm(c, axis=1)
            num += n[:, None] * c
            den += n
        blended = np.divide(num, den[:, None], out=np.zeros_like(num),
                            where=den[:, None] > 0)
        out[:, k] = np.where(act[:, k, None], np.nan_to_num(off[:, k]), blended)
    return out


def _within_window(active: np.ndarray, window: int) -> np.ndarray:
    """(T, K) bool: frames less than ``window`` frames from an active frame of the part."""
    t = np.arange(len(active))[:, None]
    big = len(active) + window + 1
    last = np.maximum.accumulate(np.where(active, t, -big), axis=0)
    nxt = np.minimum.accumulate(np.where(active, t, 2 * big)[::-1], axis=0)[::-1]
    return np.minimum(t - last, nxt - t) < window


# ----------------------------------------------------------------------------- references


def default_reference(model: BodyModel) -> np.ndarray:
    """(5,) int: per contact part, its contact vertex nearest to the centroid of the part's
    contact vertices in the template (the reference point of a part with no contact)."""
    v = model.v_template.detach().cpu().numpy()
    ids = []
    for name in CONTACT_NAMES:
        s = np.asarray(model.contact_vertices[name])
        ids.append(s[np.argmin(np.linalg.norm(v[s] - v[s].mean(0), axis=1))])
    return np.asarray(ids, dtype=np.int64)


def reference_vertices(params: BodyParams, model: BodyModel, contact_points: np.ndarray,
                       vertices: np.ndarray | None = None) -> np.ndarray:
    """The body vertex that carries each part's contact, per frame.

    On a frame where part ``k`` has a contact point (finite ``contact_points[t, k]``) it is the
    vertex of ``model.contact_vertices[k]`` nearest to that point in the posed source; other
    frames take the vertex of the nearest (in time) contact frame of that part (so the falloff
    window before and after a run moves the same vertex); a part that never touches gets
    :func:`default_reference`.

    Args:
        params: the source motion (T frames).
        model: the body model (its vertex ids are returned).
        contact_points: (T, 5, 3) metres, world, NaN where the part has no contact.
        vertices: (T, V, 3) the posed source, if already computed.

    Returns:
        (T, 5) int64 vertex ids.
    """
    pts = np.asarray(contact_points, dtype=np.float64)
    n = params.num_frames
    if pts.shape != (n, len(CONTACT_NAMES), 3):
        raise ValueError(f"contact_points must be ({n}, {len(CONTACT_NAMES)}, 3), got "
                         f"{pts.shape}")
    v = pose_body(model, params)[0] if vertices is None else np.asarray(vertices)
    ref = np.repeat(default_reference(model)[None], n, axis=0)
    t = np.arange(n)
    for k, name in enumerate(CONTACT_NAMES):
        has = np.all(np.isfinite(pts[:, k]), axis=1)
        if not has.any():
            continue
        s = np.asarray(model.contact_vertices[name])
        d = np.linalg.norm(v[has][:, s] - pts[has, k][:, None], axis=2)  # (M, |s|)
        best = s[np.argmin(d, axis=1)]
        frames = t[has]
        nxt = np.clip(np.searchsorted(frames, t), 0, len(frames) - 1)
        prv = np.clip(nxt - 1, 0, len(frames) - 1)
        nearest = np.where(np.abs(frames[nxt] - t) < np.abs(t - frames[prv]), nxt, prv)
        ref[:, k] = best[nearest]
    return ref


def contact_targets(params: BodyParams, model: BodyModel, source_points: np.ndarray,
                    new_points: np.ndarray, active: np.ndarray, window: int = 30
                    ) -> tuple[np.ndarray, np.ndarray]:
    """IK targets and reference vertices for contacts moved from ``source_points`` to
    ``new_points`` (e.g. by :func:`~couch.augment.transfer.transfer_contacts`).

    The offset ``new - source`` of each active (frame, part) is smoothed with
    :func:`smooth_offsets`; the target of a part is its reference vertex's source position plus
    the smoothed offset on every frame less than ``window`` frames from one of its contacts, NaN
    elsewhere (free, only kept near the captured pose).

    Args:
        params: the source motion (T frames).
        model: the body model.
        source_points, new_points: (T, 5, 3) metres, world; read where ``active``.
        active: (T, 5) bool.
        window: falloff frames.

    Returns:
        targets (T, 5, 3) float64 with NaN, and reference vertex ids (T, 5) int64 (pass both
        to :func:`reposition`).
    """
    act = np.asarray(active, dtype=bool)
    src = np.where(act[..., None], np.asarray(source_points, np.float64), np.nan)
    new = np.where(act[..., None], np.asarray(new_points, np.float64), np.nan)
    verts = pose_body(model, params)[0]
    ref = reference_vertices(params, model, src, verts)
    offsets = smooth_offsets(np.nan_to_num(new - src), act, window)
    base = np.take_along_axis(verts, ref[..., None], axis=1)  # (T, 5, 3)
    targets = np.where(_within_window(act, window)[..., None], base + offsets, np.nan)
    return targets, ref


# ----------------------------------------------------------------------------- IK


@dataclass(frozen=True)
class IKConfig:
    """Knobs of :func:`reposition`.

    Attributes:
        iterations: Adam iterations (all frames at once; ~35 ms per iteration for 135 frames
            with the coarse model on one thread).
        step_size: Adam learning rate, radians per iteration for the rotation corrections
            (``transl_scale`` metres for the translation); decays to ``final_step`` (cosine).
        final_step: step size at the last iteration (fraction of ``step_size``).
        max_step_deg: per-iteration change of each bone's correction is clipped to this angle.
        max_correction_deg: bound on each bone's total correction (smooth, ``tanh``) ...
        distal_scale: ... times this for :data:`DISTAL_JOINTS` (wrists, hands, ankles, feet).
        transl_scale: metres per unit of the translation variable (Adam step conditioning).
        pose_weight: cost of changing a bone's local rotation, per rad², relative to a reach
            residual of 1 cm² ...
        core_weight: ... times this for :data:`CORE_JOINTS` (spine, legs, root, head): the
            arms do the work of a hand target.
        transl_weight: cost of the translation correction per cm² (moves with the pelvis).
        plant_weight: cost per cm² of a planted foot point away from its source position.
        plant_ramp: frames before and after a plant over which that cost fades in and out
            linearly, so a swing foot's correction is gone by the time the foot lands (a plain
            on/off cost let the correction snap back 2.5 cm in the frame of touch-down).
        smooth_weight: cost per rad² (and per cm² for translation, times 0.01) of the change of
            the correction between consecutive frames.
        limit_weight: cost per rad² of joint-limit excess beyond the source's own.
        penetration_weight: cost per cm² of depth of each body vertex inside the obstacle
            (``reposition(obstacle=...)``), deeper than ``penetration_margin``.
        penetration_margin: depth (m) tolerated before the cost starts (a seated body's
            buttocks press a few mm into a rigid seat model).
        window: default falloff window (frames) for callers building targets.
        tolerance: stop early when every reach error is below this (m) and the objective
            improved by less than ``rel_tolerance`` (relative) in the last iteration.
        rel_tolerance: see ``tolerance``.
    """

    iterations: int = 300
    step_size: float = 0.03
    final_step: float = 0.05
    max_step_deg: float = 2.0
    max_correction_deg: float = 35.0
    distal_scale: float = 2.0
    transl_scale: float = 0.5
    pose_weight: float = 1.0
    core_weight: float = 10.0
    transl_weight: float = 0.05
    plant_weight: float = 10.0
    plant_ramp: int = 4
    smooth_weight: float = 20.0
    limit_weight: float = 1000.0
    penetration_weight: float = 1.0
    penetration_margin: float = 0.002
    window: int = 30
    tolerance: float = 0.002
    rel_tolerance: float = 1e-4


@dataclass(frozen=True)
class IKResult:
    """What :func:`reposition` returns.

    Attributes:
        params: the re-posed motion (same betas, T frames).
        reach_error: (T, 5) metres from each reference vertex to its target, NaN without one.
        plant_error: (T, 2) metres, largest displacement of a planted foot's points from the
            source (NaN where the foot is not planted).
        iterations: optimiser iterations run.
        seconds: wall time of the solve.
        reference: (T, 5) int64 reference vertex ids used.
    """

    params: BodyParams
    reach_error: np.ndarray
    plant_error: np.ndarray
    iterations: int
    seconds: float
    reference: np.ndarray = field(repr=False)


def _plant_weights(plant: np.ndarray, ramp: int) -> np.ndarray:
    """(T, 2) in [0, 1]: 1 on the planted frames of ``plant`` (T, 2) bool, falling linearly to
    0 over ``ramp`` frames either side of each plant."""
    out = np.zeros(plant.shape)
    for k in range(plant.shape[1]):  # two feet
        if plant[:, k].any():
            frames = ndimage.distance_transform_edt(~plant[:, k])  # to the nearest plant
            out[:, k] = np.clip(1.0 - frames / (ramp + 1), 0.0, 1.0)
    return out


def _bounded(raw: torch.Tensor, limit: torch.Tensor) -> torch.Tensor:
    """Scale each (…, 3) rotation vector so its angle is ``limit * tanh(|raw| / limit)``."""
    n = torch.sqrt(raw.square().sum(-1, keepdim=True) + 1e-12)
    return raw * (limit[:, None] * torch.tanh(n / limit[:, None]) / n)


def _joint_weights(cfg: IKConfig) -> tuple[np.ndarray, np.ndarray]:
    """(24,) pose weights and (24,) correction bounds in radians."""
    w = np.full(24, cfg.pose_weight)
    w[[JOINT_INDEX[j] for j in CORE_JOINTS]] *= cfg.core_weight
    lim = np.full(24, np.deg2rad(cfg.max_correction_deg))
    lim[[JOINT_INDEX[j] for j in DISTAL_JOINTS]] *= cfg.distal_scale
    return w, lim


def reposition(params: BodyParams, model: BodyModel, targets: np.ndarray, *,
               reference: np.ndarray | None = None, plant_feet: np.ndarray | None = None,
               obstacle: SignedDistanceGrid | None = None,
               config: IKConfig | None = None) -> IKResult:
    """Full-body IK over all frames at once: move each part's reference vertex to its target.

    The unknowns are a rotation correction per frame and bone (axis-angle in the bone's local
    frame, ``R_new = R_src · exp(δ)``, bone 0 = the global orientation) and a translation
    correction per frame. The objective (see :class:`IKConfig` for the weights) sums

    - reach: |v_ref − target|² (in cm²) for every finite target;
    - keep the pose: Σ_bones w_j |δ_j|², heavy on spine, legs, root and head;
    - translation: |Δtransl|²;
    - foot plant: for feet flagged in ``plant_feet``, |p − p_src|² of the foot's heel and toe
      keypoints (their source positions: no new foot skate), faded in and out over
      ``plant_ramp`` frames around each plant (:func:`_plant_weights`);
    - smoothness: |δ_{t+1} − δ_t|² and |Δtransl_{t+1} − Δtransl_t|²;
    - joint limits: the squared excess of each Euler angle beyond its range
      (:func:`couch.fitting.limits.joint_limit_excess`) minus the source's own excess (a
      captured pose outside a range is not pulled in, and not pushed further out);
    - penetration (with ``obstacle``): for every body vertex, the squared depth (cm²) by which
      it lies inside the obstacle beyond ``penetration_margin`` (a limb brushing the new chair
      is moved out rather than the sample thrown away); a part's own contact vertices are exempt
      on the frames it has a target (a palm or the buttocks press onto the surface they touch).

    Args:
        params: the captured motion (T frames, world frame).
        model: body model (torch; the coarse bundled model is ~10x faster).
        targets: (T, 5, 3) metres, world, in :data:`~couch.body.CONTACT_NAMES` order; NaN where
            a part has no target on that frame.
        reference: (T, 5) or (5,) vertex ids whose positions must reach the targets (from
            :func:`contact_targets` / :func:`reference_vertices`); default
            :func:`default_reference` (the vertex nearest each contact set's centroid).
        plant_feet: (T, 2) bool, left/right foot planted (kept at its source position).
        obstacle: the new chair's :class:`~couch.augment.sdf.SignedDistanceGrid`, world frame.
        config: :class:`IKConfig`.

    Returns:
        :class:`IKResult`.
    """
    cfg = config or IKConfig()
    start = time.perf_counter()
    n = params.num_frames
    tg = np.asarray(targets, dtype=np.float64)
    if tg.shape != (n, len(CONTACT_NAMES), 3):
        raise ValueError(f"targets must be ({n}, {len(CONTACT_NAMES)}, 3), got {tg.shape}")
    ref = default_reference(model) if reference is None else np.asarray(reference, np.int64)
    ref = np.broadcast_to(ref, (n, len(CONTACT_NAMES))).copy()
    if ref.min() < 0 or ref.max() >= model.num_vertices:
        raise ValueError(f"reference vertex ids must be in [0, {model.num_vertices})")
    plant = np.zeros((n, 2), bool) if plant_feet is None else np.asarray(plant_feet, bool)
    if plant.shape != (n, 2):
        raise ValueError(f"plant_feet must be ({n}, 2), got {plant.shape}")
    has = np.all(np.isfinite(tg), axis=2)  # (T, 5)

    dt = model.dtype
    dev = model.device

    def ten(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x), dtype=dt, device=dev)

    betas = ten(params.betas)[None]
    aa_src = ten(np.concatenate([params.global_orient, params.body_pose], 1)).reshape(n, 24, 3)
    rot_src = axis_angle_to_matrix(aa_src)
    transl_src = ten(params.transl)
    w_pose, lim = (ten(a) for a in _joint_weights(cfg))
    has_t = ten(has)
    tg_t = ten(np.nan_to_num(tg))
    ref_t = torch.as_tensor(ref, device=dev)
    frame_idx = torch.arange(n, device=dev)[:, None]
    foot_ids = None
    if plant.any():
        missing = [k for side in FOOT_POINTS for k in side if k not in model.keypoint_ids]
        if missing:
            raise ValueError(f"{model.name}: no foot keypoint(s) {', '.join(missing)}")
        foot_ids = torch.as_tensor([[model.keypoint_ids[k] for k in side]
                                    for side in FOOT_POINTS], device=dev)  # (2, P)
    plant_t = ten(_plant_weights(plant, cfg.plant_ramp))
    free = None
    if obstacle is not None:
        exempt = np.zeros((n, model.num_vertices), bool)
        for k, name in enumerate(CONTACT_NAMES):
            ids = np.asarray(model.contact_vertices[name])
            exempt[np.ix_(has[:, k], ids)] = True
        free = ten(~exempt)
    with torch.no_grad():
        src_out = model(betas=betas, global_orient=rot_src[:, :1], body_pose=rot_src[:, 1:],
                        transl=transl_src)
        feet_src = src_out.vertices[:, foot_ids] if foot_ids is not None else None
        excess_src = joint_limit_excess(rot_src[:, 1:])

    raw = torch.zeros(n, 24, 3, dtype=dt, device=dev, requires_grad=True)
    raw_t = torch.zeros(n, 3, dtype=dt, device=dev, requires_grad=True)
    opt = torch.optim.Adam([raw, raw_t], lr=cfg.step_size)
    max_step = float(np.deg2rad(cfg.max_step_deg))

    def solve() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        delta = _bounded(raw, lim)
        rot = rot_src @ axis_angle_to_matrix(delta)
        d_tr = raw_t * cfg.transl_scale
        out = model(betas=betas, global_orient=rot[:, :1], body_pose=rot[:, 1:],
                    transl=transl_src + d_tr)
        return delta, rot, d_tr, out.vertices

    def objective() -> tuple[torch.Tensor, torch.Tensor]:
        delta, rot, d_tr, verts = solve()
        pts = verts[frame_idx, ref_t]  # (T, 5, 3)
        err = (pts - tg_t).square().sum(-1) * has_t  # m²
        loss = err.sum() / _CM ** 2
        loss = loss + (w_pose * delta.square().sum(-1)).sum()
        loss = loss + cfg.transl_weight * (d_tr / _CM).square().sum()
        if foot_ids is not None:
            f = (verts[:, foot_ids] - feet_src).square().sum(-1).sum(-1)  # (T, 2)
            loss = loss + cfg.plant_weight * (f * plant_t).sum() / _CM ** 2
        if n > 1:
            loss = loss + cfg.smooth_weight * (delta[1:] - delta[:-1]).square().sum()
            loss = loss + cfg.smooth_weight * 0.01 * ((d_tr[1:] - d_tr[:-1]) / _CM
                                                      ).square().sum()
        excess = torch.relu(joint_limit_excess(rot[:, 1:]) - excess_src)
        loss = loss + cfg.limit_weight * excess.square().sum()
        if obstacle is not None and cfg.penetration_weight > 0:
            depth = torch.relu(-obstacle.torch_query(verts) - cfg.penetration_margin)
            loss = loss + cfg.penetration_weight * ((depth / _CM).square() * free).sum()
        return loss / n, err.detach()

    def clipped(prev: torch.Tensor) -> None:
        """Clip each bone's change of this iteration to ``max_step`` (TRUMANS' clipped steps)."""
        with torch.no_grad():
            step = raw - prev
            norm = step.norm(dim=-1, keepdim=True)
            raw.copy_(prev + step * torch.clamp(max_step / (norm + 1e-12), max=1.0))

    last: dict[str, torch.Tensor] = {}

    def closure() -> torch.Tensor:
        opt.zero_grad(set_to_none=True)
        loss, err = objective()
        loss.backward()
        last["err"] = err
        return loss

    it = 0
    best = float("inf")
    for it in range(1, cfg.iterations + 1):
        frac = (it - 1) / max(cfg.iterations - 1, 1)
        cos = 0.5 * (1 + np.cos(np.pi * frac))
        for g in opt.param_groups:
            g["lr"] = cfg.step_size * (cfg.final_step + (1 - cfg.final_step) * cos)
        prev = raw.detach().clone()
        value = float(opt.step(closure).detach())
        clipped(prev)
        worst = float(last["err"].max().sqrt()) if has.any() else 0.0
        if worst < cfg.tolerance and value > best * (1 - cfg.rel_tolerance) and it > 10:
            break
        best = min(best, value)

    with torch.no_grad():
        _, rot, d_tr, verts = solve()
        aa = matrix_to_axis_angle(rot).reshape(n, 72).double().cpu().numpy()
        pts = verts[frame_idx, ref_t].double().cpu().numpy()
        feet = verts[:, foot_ids].double().cpu().numpy() if foot_ids is not None else None
        new_transl = (transl_src + d_tr).double().cpu().numpy()
    reach = np.where(has, np.linalg.norm(pts - np.nan_to_num(tg), axis=-1), np.nan)
    plant_err = np.full((n, 2), np.nan)
    if feet is not None and feet_src is not None:
        moved = np.linalg.norm(feet - feet_src.double().cpu().numpy(), axis=-1).max(-1)
        plant_err = np.where(plant, moved, np.nan)
    out = BodyParams(global_orient=aa[:, :3], body_pose=aa[:, 3:], transl=new_transl,
                     betas=params.betas)
    return IKResult(params=out, reach_error=reach, plant_error=plant_err, iterations=it,
                    seconds=time.perf_counter() - start, reference=ref)


# ----------------------------------------------------------------------------- penetration


def penetration(params: BodyParams, model: BodyModel, chair_vertices: np.ndarray,
                chair_faces: np.ndarray, chunk: int = 128) -> np.ndarray:
    """Deepest penetration of the body into a watertight chair per frame.

    Signed distances of every posed body vertex to the chair (open3d
    ``RaycastingScene.compute_signed_distance``, negative inside), in chunks of frames.

    Args:
        params: T frames, world frame.
        model: body model.
        chair_vertices: (N, 3) metres, same (world) frame; chair_faces: (F, 3) int, watertight.
        chunk: frames posed per batch.

    Returns:
        (T,) metres >= 0: minus the most negative signed distance (0 without penetration).
    """
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(chair_vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(chair_faces, np.uint32)))
    n = params.num_frames
    out = np.zeros(n)
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        v = pose_body(model, params.frames(slice(a, b)))[0].astype(np.float32)
        sd = scene.compute_signed_distance(o3d.core.Tensor(v.reshape(-1, 3))).numpy()
        out[a:b] = np.maximum(0.0, -sd.reshape(b - a, -1).min(axis=1))
    return out
