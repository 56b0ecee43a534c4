"""Per-frame SMPL fits to segmented person point clouds, batched over frames (issue 7, item 3).

Each frame's pose starts at a given initial pose (the synced IMU pose) and is refined so the body
explains that frame's fused person cloud (world frame, metres, Y up). Frames are the batch
dimension of every tensor: one Adam optimisation fits a whole chunk of frames at once, and since
every term but the optional smoothness is a per-frame sum, each frame's fit is the same as if it
were fitted alone (:func:`fit_bodies_frame_by_frame` does exactly that, for the benchmark).

Parameters per frame: a rotation residual per joint ``δ`` (24×3 axis-angle; the local rotation is
``R0 · exp(δ)`` with R0 the initial one, so δ = 0 is the initial pose) and a translation; the
shape (betas) is shared and held fixed here (see :mod:`couch.fitting.shape`).

Objective per frame (every term (B,) in :mod:`couch.fitting.terms`):

* points → surface: each cloud point's distance to the tangent plane of its nearest body vertex,
  robust (Geman-McClure, scale ``sigma``);
* visible surface → points: each body vertex whose normal faces a camera centre, to the plane of
  its nearest point (the rest of the body was never seen, so it must not be pulled at);
* both with a clothing allowance: the cloud is the clothed surface, so a point up to
  ``clothing_margin`` outside the body costs nothing while a point inside the body costs in full;
* a prior keeping every bone's world orientation near the initial (IMU) one (scale
  ``prior_sigma_deg``), which holds what the cloud cannot decide (hands, feet, occluded limbs);
* a joint-limit penalty (:mod:`couch.fitting.limits`);
* optionally a temporal smoothness term (off by default: it couples frames; the sequence fusion
  of COUCH Eq. 7–8 is a later step).

Correspondences (nearest vertex / point) are searched without gradient every
``correspond_every`` iterations (a k-d tree per frame, :mod:`couch.fitting.nearest`; the trees
over the clouds are built once per fit, since the clouds do not move, and every search is
bounded by ``max_distance``, beyond which a pair is dropped anyway); each pair's plane (normal,
offset) is then fixed until the next search (:func:`couch.fitting.terms.plane_cost`). Between
searches the mesh is posed by matrix products over all frames at once
(:mod:`couch.fitting.skinning`): the coarse model whole, by one product shared by the frames,
the full model only at each frame's distinct paired vertices (the pairs' union: a vertex is
often the nearest of several points). The fit runs on the coarse body model first, then
finishes on the full one; the parameters carry over unchanged (both models share joints and
parameters).

Cost (CPU, one thread, 60 frames of 4-camera clouds, default settings): ~13 ms per frame
batched, about half of it the nearest-neighbour searches (k-d tree builds and queries, ~0.5 µs
a query) and most of the rest the posing of paired vertices and the data term; fitted one frame
at a time the same work costs >10x more, the optimisation's ~2,500 small torch operations per
iteration then dominating (``python -m couch.tools.bench.fitting``).

Clouds differ in size per frame: each is subsampled to at most ``points`` points (seeded by
``seed`` + frame number, see :mod:`couch.fitting.clouds`) and padded with a mask. A frame with
fewer than ``min_points`` points keeps its initial pose and is flagged in :attr:`BodyFit.fallback`.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from couch.body import BodyModel, load_body_model
from couch.body.skeleton import JOINT_INDEX, PARENTS
from couch.fitting.clouds import PaddedClouds, cloud_arrays, pad_clouds
from couch.fitting.limits import joint_limit_penalty
from couch.fitting.metrics import surface_distances
from couch.fitting.nearest import BatchedTree
from couch.fitting.params import BodyParams
from couch.fitting.skinning import Skinner
from couch.fitting.terms import (
    bone_orientation_prior,
    plane_cost,
    smoothness,
    visible_vertices,
)
from couch.pool import Pool, pool_map
from couch.rotations import axis_angle_to_matrix, matrix_to_axis_angle

__all__ = [
    "EXTREMITIES", "BodyFit", "BodyFitConfig", "Pairs", "Stage", "cached_model", "default_stages",
    "evaluate_fit", "find_pairs", "fit_bodies", "fit_bodies_frame_by_frame", "optimise",
    "world_rotations",
]


#: A body model is posed whole in the iterations (one product for all frames) when it has at
#: most this many times as many vertices as the pairs use per frame (measured on CPU, 60
#: frames: the whole coarse mesh, 1229 vertices, 3x faster than its ~850 paired ones).
WHOLE_MESH_FACTOR = 2.0

#: Joints whose bone-orientation prior weighs ``prior_extremity_weight``: wrists and hands.
EXTREMITIES = tuple(JOINT_INDEX[n] for n in ("left_wrist", "right_wrist", "left_hand",
                                             "right_hand"))


@dataclasses.dataclass(frozen=True)
class BodyFitConfig:
    """Knobs of the per-frame fit (lengths in metres, angles in degrees or radians as named).

    Defaults were tuned on simulated sessions (clothing 0.5-3 cm, IMU-like initial poses a few
    degrees off per bone); see tests/test_fitting_body.py for what they give.

    Attributes:
        coarse_model, model: body models of the two stages (bundled names or SMPL file paths;
            they must share the skeleton and shape space).
        coarse_iters, fine_iters: Adam iterations on each.
        points: cloud points kept per frame (random subset, seeded by ``seed`` + frame).
        surface_points: visible body vertices paired with the cloud per frame and search (a
            random subset when more are visible).
        min_points: a frame with fewer points keeps its initial pose and is flagged.
        correspond_every: iterations between nearest-neighbour searches.
        max_distance: pairs farther apart than this are ignored (outliers, unseen parts).
        sigma: robust scale of the surface residuals.
        clothing_margin: how far outside the body a point may lie at no cost (the clothes).
        w_points, w_surface: weights of points → surface and visible surface → points.
        w_prior, prior_sigma_deg: weight and scale of the bone-orientation prior, a cost of
            (θ/σ)² per bone for θ away from its initial orientation. Since the data terms are
            means over pairs (not sums), σ sets the balance against the cloud rather than being
            the IMU's error itself.
        prior_extremity_weight: the prior's relative weight on wrists and hands, which the
            cloud resolves least (small, often touching the chair, partly cut away with it).
        w_limits: weight of the joint-limit penalty (per radian² of excess).
        w_smooth, smooth_sigma_deg, smooth_sigma_m: temporal smoothness (0: off).
        lr_rot, lr_transl: Adam step sizes (radians, metres per iteration).
        fine_lr_scale: their scale in the full-model stage (a restart near the optimum).
        batch_frames: frames optimised together (bounds memory).
        errors: compute per-frame fit errors on the full clouds (open3d; costs ~tens of ms a
            frame); error_samples: surface samples of the surface → points error;
            error_points: cloud points of the points → surface error (a seeded subset; 0:
            all), whose exact distances were half a chamfer's time.
        device, dtype: torch device and dtype of the optimisation.
    """

    coarse_model: str = "couch-body-coarse"
    model: str = "couch-body"
    coarse_iters: int = 30
    fine_iters: int = 10
    points: int = 1000
    surface_points: int = 1000
    seed: int = 0
    min_points: int = 100
    correspond_every: int = 10
    max_distance: float = 0.10
    sigma: float = 0.02
    clothing_margin: float = 0.01
    w_points: float = 100.0
    w_surface: float = 50.0
    w_prior: float = 1.0
    prior_sigma_deg: float = 16.0
    prior_extremity_weight: float = 4.0
    w_limits: float = 10.0
    w_smooth: float = 0.0
    smooth_sigma_deg: float = 5.0
    smooth_sigma_m: float = 0.02
    lr_rot: float = 0.01
    lr_transl: float = 0.005
    fine_lr_scale: float = 0.3
    batch_frames: int = 64
    errors: bool = True
    error_samples: int = 4000
    error_points: int = 4000
    device: str = "cpu"
    dtype: str = "float32"


@dataclasses.dataclass(frozen=True)
class Stage:
    """One optimisation stage: a body model, a number of Adam iterations, whether the shared
    betas are free (shape fitting), and its step size for betas."""

    model: BodyModel
    iters: int
    lr_scale: float = 1.0  # of the config's pose step sizes
    fit_betas: bool = False
    lr_betas: float = 0.05
    w_betas: float = 1.0  # prior on betas: w · ‖β‖² (β ~ N(0, 1)) against the frames' sum


@dataclasses.dataclass(frozen=True)
class BodyFit:
    """Result of a per-frame fit.

    Attributes:
        params: fitted :class:`BodyParams` (float32; schema shapes (T,3), (T,69), (T,3), (10,)).
        joints: (T,24,3) float32 world joints of the full model.
        chamfer: (T,) metres, symmetric chamfer of the fitted (full) body to the frame's whole
            cloud (:func:`couch.fitting.metrics.surface_distances`, visible samples only when
            cameras were given); NaN for flagged frames or when errors were not computed.
        to_surface: (T,) metres, mean cloud point → body surface distance.
        to_points: (T,) metres, mean visible body surface → nearest point distance.
        num_points: (T,) points in each frame's cloud.
        fallback: (T,) bool, frames that kept their initial pose (too few points).
        seconds: wall time of the optimisation (without the error evaluation).
    """

    params: BodyParams
    joints: np.ndarray
    chamfer: np.ndarray
    to_surface: np.ndarray
    to_points: np.ndarray
    num_points: np.ndarray
    fallback: np.ndarray
    seconds: float

    def summary(self) -> dict[str, float]:
        """Means over the fitted frames (metres) and counts."""
        ok = ~self.fallback
        return {"frames": float(len(self.fallback)), "fallback": float(self.fallback.sum()),
                "chamfer": float(np.nanmean(self.chamfer[ok])) if ok.any() else np.nan,
                "to_surface": float(np.nanmean(self.to_surface[ok])) if ok.any() else np.nan,
                "to_points": float(np.nanmean(self.to_points[ok])) if ok.any() else np.nan,
                "seconds": self.seconds}


@functools.lru_cache(maxsize=8)
def cached_model(name: str, device: str = "cpu", dtype: str = "float32") -> BodyModel:
    """A body model loaded once per process (name or path, device, dtype)."""
    return load_body_model(name, dtype=getattr(torch, dtype), device=device)


def world_rotations(local: torch.Tensor) -> torch.Tensor:
    """(B,24,3,3) local joint rotations → world rotations along SMPL's kinematic chain."""
    chain = [local[:, 0]]
    for j in range(1, local.shape[1]):
        chain.append(chain[PARENTS[j]] @ local[:, j])
    return torch.stack(chain, dim=1)


def _check_inputs(clouds: Sequence[Any], init: BodyParams, cameras: np.ndarray | None
                  ) -> np.ndarray | None:
    if not isinstance(init, BodyParams):
        raise TypeError(f"init must be BodyParams, got {type(init).__name__}")
    if len(clouds) != init.num_frames:
        raise ValueError(f"{len(clouds)} clouds but the initial pose has {init.num_frames} "
                         f"frames; give one cloud per frame (an empty one where nothing was seen)")
    if cameras is None:
        return None
    cams = np.asarray(cameras, dtype=np.float64)
    if cams.ndim != 2 or cams.shape[1] != 3 or len(cams) == 0:
        raise ValueError(f"cameras must be (C, 3) camera centres in the world, got {cams.shape}")
    return cams


@dataclasses.dataclass
class Pairs:
    """Correspondences of one nearest-neighbour search (no gradient), B frames.

    vertex: (B,N+M) long, the body vertex of each pair: N cloud → body pairs (one per padded
    cloud point), then M visible body → cloud pairs. normal: (B,3,N+M) the plane normal, xyz
    first (see :func:`couch.fitting.terms.surface_cost`); offset: (B,N+M) metres, normal ·
    the pair's cloud point (:func:`couch.fitting.terms.plane_cost`);
    weight: (B,N+M) each pair's weight: 0 for an invalid pair, else ``w_points`` (cloud → body)
    or ``w_surface`` (body → cloud) over the frame's number of valid pairs of that direction,
    so the sum is the weighted sum of the two directions' means.
    union: (B,U) long, the distinct vertices of each frame's valid pairs (padded with vertex 0):
    a vertex is often the nearest of several points, so posing ``union`` and gathering is
    cheaper than posing every pair's vertex. slot: (B,3,N+M) long, each pair's position in
    ``union``, repeated over xyz for :func:`torch.gather` (0 for an invalid pair).
    """

    vertex: torch.Tensor
    normal: torch.Tensor
    offset: torch.Tensor
    weight: torch.Tensor
    union: torch.Tensor
    slot: torch.Tensor


def find_pairs(verts: np.ndarray, vnormals: np.ndarray, visible: np.ndarray,
               clouds: PaddedClouds, cloud_tree: BatchedTree, frame_ids: np.ndarray,
               cfg: BodyFitConfig, search: int, device: torch.device, dtype: torch.dtype
               ) -> Pairs:
    """Both directions' nearest neighbours for the posed meshes ``verts`` (B,V,3) with vertex
    normals (B,V,3) (any memory layout, e.g. views of :meth:`Skinner.posed_mesh`'s (B,3,V)) and
    ``visible`` (B,V) vertices; ``cloud_tree`` is the clouds' :class:`BatchedTree` (built once
    per fit). Both searches stop at ``cfg.max_distance``.

    Cloud → body: every real point and its nearest visible vertex (a seen point lies on
    surface facing a camera). Visible body → cloud: at most ``cfg.surface_points`` visible
    vertices per frame (a random subset, seeded by ``cfg.seed``, the frame number and
    ``search``, so a frame gets the same pairs in a batch as alone) and their nearest points.
    Pairs farther apart than ``cfg.max_distance``, or whose point and vertex normals face
    opposite ways, are invalid.
    """
    pts, pmask, pn = clouds.points, clouds.mask, clouds.normals
    b = len(verts)
    rows = np.arange(b)[:, None]
    p_idx, p_dist = BatchedTree(verts, visible).query(pts, pmask, cfg.max_distance)
    p_ok = pmask & (p_dist < cfg.max_distance)
    p_normal = vnormals[rows, p_idx]
    if pn is not None:
        p_ok &= np.einsum("tnk,tnk->tn", pn, p_normal) > 0
    chosen = []
    for k in range(b):
        cand = np.flatnonzero(visible[k])
        if len(cand) > cfg.surface_points:
            rng = np.random.default_rng((cfg.seed, int(frame_ids[k]), search))
            cand = np.sort(rng.choice(cand, cfg.surface_points, replace=False))
        chosen.append(cand)
    m = max([len(c) for c in chosen] + [1])
    s_vid = np.zeros((b, m), np.int64)
    s_sel = np.zeros((b, m), bool)
    for k, c in enumerate(chosen):
        s_vid[k, :len(c)] = c
        s_sel[k, :len(c)] = True
    s_idx, s_dist = cloud_tree.query(verts[rows, s_vid], s_sel, cfg.max_distance)
    s_ok = s_sel & (s_dist < cfg.max_distance)
    s_cloud = pts[rows, s_idx]
    s_norm = vnormals[rows, s_vid]
    if pn is not None:
        point_normal = pn[rows, s_idx]
        s_ok &= np.einsum("tmk,tmk->tm", s_norm, point_normal) > 0
        s_norm = point_normal

    vertex = np.concatenate([p_idx, s_vid], 1)
    ok = np.concatenate([p_ok, s_ok], 1)
    union, slot = _union(vertex, ok, verts.shape[1])
    normal = np.concatenate([p_normal, s_norm], 1)
    offset = np.einsum("tpk,tpk->tp", normal, np.concatenate([pts, s_cloud], 1))
    weight = np.concatenate([p_ok / np.maximum(p_ok.sum(1, keepdims=True), 1) * cfg.w_points,
                             s_ok / np.maximum(s_ok.sum(1, keepdims=True), 1) * cfg.w_surface],
                            1)

    def t(x: np.ndarray, dt: torch.dtype | None = None) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=dt, device=device)

    # xyz first, (B,3,P), for the per-pair sums over xyz; a contiguous (B,3,P) gather index
    # (torch.gather is ~1.5x faster with it than with an expanded one)
    return Pairs(vertex=t(vertex), normal=t(normal.transpose(0, 2, 1), dtype),
                 offset=t(offset, dtype), weight=t(weight, dtype), union=t(union),
                 slot=t(np.repeat(slot[:, None], 3, axis=1)))


def _union(vertex: np.ndarray, ok: np.ndarray, num_vertices: int
           ) -> tuple[np.ndarray, np.ndarray]:
    """Distinct vertices (B,U) of each frame's valid pairs (``vertex`` (B,P) where ``ok``),
    ascending, padded with 0, and each pair's position (B,P) among them (0 where not ok)."""
    b = len(vertex)
    used = np.zeros((b, num_vertices), bool)
    used[np.broadcast_to(np.arange(b)[:, None], vertex.shape)[ok], vertex[ok]] = True
    rows, cols = np.nonzero(used)  # row-major: each frame's vertices ascending
    counts = used.sum(1)
    union = np.zeros((b, max(int(counts.max(initial=0)), 1)), np.int64)
    union[rows, np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts, counts)] = cols
    position = np.cumsum(used, axis=1) - 1
    return union, np.where(ok, np.take_along_axis(position, vertex, 1), 0)


def optimise(stages: Sequence[Stage], clouds: PaddedClouds, init: BodyParams,
             cameras: np.ndarray | None, cfg: BodyFitConfig, frame_ids: np.ndarray,
             bar: tqdm | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit the frames of ``clouds`` (all of them at once) through ``stages``.

    Args:
        stages: models and iterations, run in order; parameters carry over between stages.
        clouds: B padded clouds; init: B frames of initial parameters (and the start betas).
        cameras: (C,3) camera centres (world) for visibility, or None (every vertex counts).
        cfg: weights and step sizes.
        frame_ids: (B,) the frames' numbers in the session (seed their random subsets).
        bar: progress bar advanced once per iteration.

    Returns:
        local rotations (B,24,3) axis-angle, translations (B,3), betas (10,); numpy float32.
    """
    model0 = stages[0].model
    dev, dt = model0.device, model0.dtype

    def tensor(x: Any) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x), dtype=dt, device=dev)

    cams = tensor(cameras) if cameras is not None else None
    aa0 = np.concatenate([init.global_orient, init.body_pose], axis=1).reshape(-1, 24, 3)
    rot0 = axis_angle_to_matrix(tensor(aa0))
    orient0 = world_rotations(rot0)
    transl0 = tensor(init.transl)
    b = len(aa0)
    delta = torch.zeros(b, 24, 3, dtype=dt, device=dev, requires_grad=True)
    dtransl = torch.zeros(b, 3, dtype=dt, device=dev, requires_grad=True)
    betas = tensor(init.betas).clone().requires_grad_(True)
    prior_sigma = np.deg2rad(cfg.prior_sigma_deg)
    prior_weights = torch.ones(24, dtype=dt, device=dev)
    prior_weights[list(EXTREMITIES)] = cfg.prior_extremity_weight
    search = 0
    cloud_tree = BatchedTree(clouds.points, clouds.mask)
    for stage in stages:
        skin = Skinner(stage.model)
        groups = [{"params": [delta], "lr": cfg.lr_rot * stage.lr_scale},
                  {"params": [dtransl], "lr": cfg.lr_transl * stage.lr_scale}]
        if stage.fit_betas:
            groups.append({"params": [betas], "lr": stage.lr_betas})
        opt = torch.optim.Adam(groups)
        pairs: Pairs | None = None
        selected: torch.Tensor | None = None
        whole = False
        vertex_index: torch.Tensor | None = None
        for it in range(stage.iters):
            local = rot0 @ axis_angle_to_matrix(delta)
            v_shaped, rest_joints = skin.rest(betas)
            posed = skin.pose(local, rest_joints, transl0 + dtransl)
            if pairs is None or it % cfg.correspond_every == 0:
                with torch.no_grad():
                    full, vn = skin.posed_mesh(posed, v_shaped)
                    vis = visible_vertices(full, vn, cams)
                pairs = find_pairs(full.cpu().numpy(), vn.cpu().numpy(), vis.cpu().numpy(),
                                   clouds, cloud_tree, frame_ids, cfg, search, dev, dt)
                search += 1
                # A small model (the coarse one) is posed whole, by one product shared by all
                # frames, which beats a per-frame product over the paired vertices until
                # these are well under half the mesh (then, the full model, the pairs' union).
                whole = (skin.model.posedirs is None
                         and skin.num_vertices <= WHOLE_MESH_FACTOR * pairs.union.shape[1])
                vertex_index = (pairs.vertex[:, None].expand(-1, 3, -1).contiguous() if whole
                                else None)
                # with the shape fixed, the paired vertices' weighted rest positions hold until
                # the next search (and pose correctives, if any, are not precomputable)
                selected = (None if stage.fit_betas or skin.model.posedirs is not None
                            else skin.rest_matrix(v_shaped.detach()) if whole
                            else skin.select(v_shaped.detach(), pairs.union))
            # the pairs' body vertices, (B,3,P) xyz first
            if whole:
                mesh = skin.mesh(skin.transform_matrix(posed),
                                 skin.rest_matrix(v_shaped) if selected is None else selected)
                body = torch.gather(mesh, 2, vertex_index)
            else:
                union = skin.vertices(posed, v_shaped, pairs.union, selected)  # (B,U,3)
                body = torch.gather(union.transpose(1, 2), 2, pairs.slot)
            # both directions in one pass: w_points · mean over cloud → body pairs +
            # w_surface · mean over body → cloud pairs, as per-pair weights
            per_frame = plane_cost(pairs.normal, pairs.offset, body, pairs.weight,
                                   sigma=cfg.sigma, margin=cfg.clothing_margin)
            per_frame = per_frame + cfg.w_prior * bone_orientation_prior(
                posed.orient, orient0, prior_sigma, prior_weights)
            per_frame = per_frame + cfg.w_limits * joint_limit_penalty(local[:, 1:])
            if cfg.w_smooth > 0:
                per_frame = per_frame + cfg.w_smooth * smoothness(
                    local, transl0 + dtransl, np.deg2rad(cfg.smooth_sigma_deg),
                    cfg.smooth_sigma_m)
            loss = per_frame.sum()
            if stage.fit_betas:
                loss = loss + stage.w_betas * betas.square().sum()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if bar is not None:
                bar.update(1)
    with torch.no_grad():
        aa = matrix_to_axis_angle(rot0 @ axis_angle_to_matrix(delta))
    return (aa.cpu().numpy().astype(np.float32),
            (transl0 + dtransl).detach().cpu().numpy().astype(np.float32),
            betas.detach().cpu().numpy().astype(np.float32))


def default_stages(cfg: BodyFitConfig) -> list[Stage]:
    """Coarse model first, full model to finish (betas fixed)."""
    stages = []
    if cfg.coarse_iters > 0:
        stages.append(Stage(cached_model(cfg.coarse_model, cfg.device, cfg.dtype),
                            cfg.coarse_iters))
    if cfg.fine_iters > 0:
        stages.append(Stage(cached_model(cfg.model, cfg.device, cfg.dtype), cfg.fine_iters,
                            lr_scale=cfg.fine_lr_scale))
    if not stages:
        raise ValueError("coarse_iters and fine_iters are both 0: nothing to fit")
    return stages


def _assemble(init: BodyParams, fitted: np.ndarray, aa: np.ndarray, transl: np.ndarray,
              betas: np.ndarray) -> BodyParams:
    go, bp, tr = init.global_orient.copy(), init.body_pose.copy(), init.transl.copy()
    go[fitted] = aa[:, 0]
    bp[fitted] = aa[:, 1:].reshape(len(aa), 69)
    tr[fitted] = transl
    return BodyParams(go, bp, tr, betas)


def evaluate_fit(params: BodyParams, clouds: Sequence[Any], cameras: np.ndarray | None,
                 cfg: BodyFitConfig, fallback: np.ndarray, *, errors: bool = True,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Joints (T,24,3) of the full model and per-frame errors (chamfer, to_surface,
    to_points; (T,) metres, NaN where not computed) of fitted parameters."""
    model = cached_model(cfg.model, cfg.device, cfg.dtype)
    t = params.num_frames
    joints = np.zeros((t, 24, 3), np.float32)
    err = np.full((3, t), np.nan)
    if not errors:
        # the skeleton alone: posing every vertex only to read the joints costs more than
        # the joints themselves (same kinematic chain as the model's forward)
        skin = Skinner(model)
        with torch.no_grad():
            _, rest = skin.rest(torch.as_tensor(params.betas, dtype=model.dtype,
                                                device=model.device))
            for a in range(0, t, cfg.batch_frames):
                sl = slice(a, min(t, a + cfg.batch_frames))
                aa = np.concatenate([params.global_orient[sl], params.body_pose[sl]], 1)
                local = axis_angle_to_matrix(torch.as_tensor(
                    aa.reshape(-1, 24, 3), dtype=model.dtype, device=model.device))
                posed = skin.pose(local, rest, torch.as_tensor(
                    params.transl[sl], dtype=model.dtype, device=model.device))
                joints[sl] = posed.joints.cpu().numpy()
        return joints, err[0], err[1], err[2]
    for a in range(0, t, cfg.batch_frames):
        sl = slice(a, min(t, a + cfg.batch_frames))
        with torch.no_grad():
            out = model(betas=params.betas[None], global_orient=params.global_orient[sl],
                        body_pose=params.body_pose[sl], transl=params.transl[sl])
        joints[sl] = out.joints.cpu().numpy()
        verts = out.vertices.cpu().numpy()
        for k in range(sl.start, sl.stop):
            pts, _ = cloud_arrays(clouds[k])
            if fallback[k] or not len(pts):
                continue
            d = surface_distances(verts[k - a], model.faces, pts, visible_from=cameras,
                                  samples=cfg.error_samples, seed=k,
                                  max_points=cfg.error_points)
            err[:, k] = (d.chamfer, d.to_surface.mean(),
                         d.to_points.mean() if len(d.to_points) else np.nan)
    return joints, err[0], err[1], err[2]


def _fit(clouds: Sequence[Any], init: BodyParams, cameras: np.ndarray | None,
         cfg: BodyFitConfig, progress: bool, chunk: int, pool: Pool = None) -> BodyFit:
    cams = _check_inputs(clouds, init, cameras)
    stages = default_stages(cfg)
    counts = np.array([len(cloud_arrays(c)[0]) for c in clouds])
    fallback = counts < cfg.min_points
    fitted = np.flatnonzero(~fallback)
    iters = sum(s.iters for s in stages)
    chunks = [fitted[a:a + chunk] for a in range(0, len(fitted), chunk)]
    start = time.perf_counter()
    def task(idx: np.ndarray) -> tuple[PaddedClouds, BodyParams, Any, BodyFitConfig, np.ndarray]:
        return (pad_clouds([clouds[i] for i in idx], cfg.points, cfg.seed, frame_ids=idx),
                init.frames(idx), cams, cfg, idx)

    if pool is not None and len(chunks) > 1:
        # the chunks are independent (every term is per frame, or couples a chunk's frames
        # only): each on a worker, fitted exactly as here
        out = pool_map(pool, _fit_chunk, [task(idx) for idx in chunks],
                       desc="body fit" if progress else None, unit="chunk")
    else:
        with tqdm(total=iters * len(chunks), disable=not progress, desc="body fit",
                  unit="it") as bar:
            out = [optimise(stages, *task(idx), bar)[:2] for idx in chunks]
    aa = np.concatenate([np.zeros((0, 24, 3), np.float32), *(a for a, _ in out)])
    tr = np.concatenate([np.zeros((0, 3), np.float32), *(t for _, t in out)])
    seconds = time.perf_counter() - start
    params = _assemble(init, fitted, aa, tr, init.betas)
    joints, ch, ts, tp = evaluate_fit(params, clouds, cams, cfg, fallback, errors=cfg.errors)
    return BodyFit(params=params, joints=joints, chamfer=ch, to_surface=ts, to_points=tp,
                   num_points=counts, fallback=fallback, seconds=seconds)


def _fit_chunk(clouds: PaddedClouds, init: BodyParams, cameras: np.ndarray | None,
               cfg: BodyFitConfig, frame_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One chunk of :func:`fit_bodies` (a pool task): rotations (B,24,3) and translations
    (B,3)."""
    return optimise(default_stages(cfg), clouds, init, cameras, cfg, frame_ids)[:2]


def fit_bodies(clouds: Sequence[Any], init: BodyParams, *, cameras: np.ndarray | None = None,
               config: BodyFitConfig | None = None, progress: bool = False,
               pool: Pool = None) -> BodyFit:
    """Fit the body in every frame to its point cloud, frames batched (see the module doc).

    Args:
        clouds: T person clouds, world metres: :class:`couch.capture.pointcloud.FusedCloud`
            (points with camera-facing normals), ``(points, normals)`` pairs or (N,3) arrays;
            an empty cloud is allowed (that frame keeps its initial pose, flagged).
        init: T frames of initial parameters (the synced IMU pose); ``init.betas`` is the
            subject's shape, held fixed (from :func:`couch.fitting.shape.fit_shape` or a scan).
        cameras: (C,3) world camera centres: only body surface facing one of them is pulled
            towards the cloud. None: the whole surface is.
        config: :class:`BodyFitConfig`.
        progress: show a tqdm bar.
        pool: where the chunks of ``config.batch_frames`` frames are fitted
            (:func:`couch.pool.spawn_pool`, one torch thread per worker); None: all here.
            A chunk is fitted the same either way.

    Returns:
        :class:`BodyFit`.

    Raises:
        ValueError: clouds and init differ in frame count, a cloud is not (N,3), or cameras is
            not (C,3).
    """
    cfg = config or BodyFitConfig()
    if cfg.batch_frames < 1:
        raise ValueError(f"batch_frames must be >= 1, got {cfg.batch_frames}")
    return _fit(clouds, init, cameras, cfg, progress, cfg.batch_frames, pool)


def fit_bodies_frame_by_frame(clouds: Sequence[Any], init: BodyParams, *,
                              cameras: np.ndarray | None = None,
                              config: BodyFitConfig | None = None,
                              progress: bool = False) -> BodyFit:
    """The same fit as :func:`fit_bodies` with the same settings, one frame at a time (a Python
    loop over frames): only for the benchmark that measures what batching gains. The
    smoothness term, which couples frames, has nothing to act on here."""
    return _fit(clouds, init, cameras, config or BodyFitConfig(), progress, 1)
