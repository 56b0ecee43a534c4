"""The subject's shape (betas) for a session (issue 7, item 2).

Two sources, as in COUCH (which took betas from 3D scans):

* :func:`fit_shape` — no scan: betas fitted jointly over a few frames spread over the session,
  alternating pose-only and pose+shape stages, coarse model first, full model to finish; the same
  objective as the per-frame fit (:mod:`couch.fitting.body`) plus a Gaussian prior on betas.
* :func:`fit_betas_to_scan` — a scan mesh of the subject (any pose, any frame): betas, pose and
  rigid placement fitted to the whole scan surface (every vertex visible, no clothing allowance
  beyond the config's).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from couch.body import standing_pose
from couch.fitting.body import BodyFitConfig, Stage, cached_model, optimise
from couch.fitting.clouds import cloud_arrays, pad_clouds
from couch.fitting.params import NUM_BETAS, BodyParams

__all__ = ["ShapeFit", "ShapeFitConfig", "fit_betas_to_scan", "fit_shape", "shape_frames"]


#: Scale (degrees) of the bone-orientation prior when fitting a scan.
SCAN_PRIOR_DEG = 30.0


@dataclasses.dataclass(frozen=True)
class ShapeFitConfig:
    """Knobs of the shape fit.

    Attributes:
        frames: frames used (spread evenly over the frames with enough points).
        rounds: alternations of a pose-only stage (``pose_iters``) and a pose+shape stage
            (``shape_iters``) on the coarse model; then ``fine_iters`` of pose+shape on the full
            model.
        lr_betas: Adam step of betas (β ~ N(0, 1) units per iteration). Adam moves each beta
            by at most about this per iteration, and subjects lie 2-3 units out on some betas:
            at 0.05 the schedule stopped short (rest-pose joint error over seven simulated
            subjects 0.71 cm mean, 0.59 at 0.2; better on five).
        w_betas: weight of the prior ‖β‖² (against the sum over frames of the fit's terms).
        body: the per-frame fit's settings (weights, models, points, seed, device).
    """

    frames: int = 8
    rounds: int = 2
    pose_iters: int = 20
    shape_iters: int = 30
    fine_iters: int = 20
    lr_betas: float = 0.2
    w_betas: float = 1.0
    body: BodyFitConfig = dataclasses.field(default_factory=BodyFitConfig)


@dataclasses.dataclass(frozen=True)
class ShapeFit:
    """Result of a shape fit.

    Attributes:
        betas: (10,) float32 shape coefficients.
        frames: (K,) the frames (or, for a scan, [0]) used.
        params: the fitted poses of those frames (with ``betas``).
    """

    betas: np.ndarray
    frames: np.ndarray
    params: BodyParams


def shape_frames(counts: np.ndarray, k: int, min_points: int) -> np.ndarray:
    """(≤k,) indices of frames spread evenly over those with at least ``min_points`` points."""
    ok = np.flatnonzero(np.asarray(counts) >= min_points)
    if len(ok) == 0:
        raise ValueError(f"no frame has {min_points} or more points: cannot fit the shape")
    if len(ok) <= k:
        return ok
    return ok[np.round(np.linspace(0, len(ok) - 1, k)).astype(int)]


def _stages(cfg: ShapeFitConfig) -> list[Stage]:
    b = cfg.body
    coarse = cached_model(b.coarse_model, b.device, b.dtype)
    full = cached_model(b.model, b.device, b.dtype)
    stages: list[Stage] = []
    for _ in range(cfg.rounds):
        stages.append(Stage(coarse, cfg.pose_iters))
        stages.append(Stage(coarse, cfg.shape_iters, fit_betas=True, lr_betas=cfg.lr_betas,
                            w_betas=cfg.w_betas))
    if cfg.fine_iters > 0:
        stages.append(Stage(full, cfg.fine_iters, lr_scale=b.fine_lr_scale, fit_betas=True,
                            lr_betas=cfg.lr_betas * b.fine_lr_scale, w_betas=cfg.w_betas))
    return [s for s in stages if s.iters > 0]


def fit_shape(clouds: Sequence[Any], init: BodyParams, *, cameras: np.ndarray | None = None,
              config: ShapeFitConfig | None = None, progress: bool = False) -> ShapeFit:
    """Betas of the session's subject from its person clouds.

    Args:
        clouds: T person clouds (as for :func:`couch.fitting.body.fit_bodies`).
        init: T frames of initial poses (the synced IMU pose); ``init.betas`` start the fit
            (zeros when nothing is known).
        cameras: (C,3) world camera centres (visibility), or None.
        config: :class:`ShapeFitConfig`.
        progress: tqdm bar.

    Returns:
        :class:`ShapeFit` (betas, the frames used and their poses).

    Raises:
        ValueError: clouds and init differ in length, or no frame has enough points.
    """
    cfg = config or ShapeFitConfig()
    if len(clouds) != init.num_frames:
        raise ValueError(f"{len(clouds)} clouds but the initial pose has {init.num_frames} "
                         f"frames")
    counts = np.array([len(cloud_arrays(c)[0]) for c in clouds])
    idx = shape_frames(counts, cfg.frames, cfg.body.min_points)
    stages = _stages(cfg)
    padded = pad_clouds([clouds[i] for i in idx], cfg.body.points, cfg.body.seed, frame_ids=idx)
    cams = None if cameras is None else np.asarray(cameras, dtype=np.float64).reshape(-1, 3)
    with tqdm(total=sum(s.iters for s in stages), disable=not progress, desc="shape fit",
              unit="it") as bar:
        aa, transl, betas = optimise(stages, padded, init.frames(idx), cams, cfg.body, idx, bar)
    params = BodyParams(aa[:, 0], aa[:, 1:].reshape(len(idx), -1), transl, betas)
    return ShapeFit(betas=betas, frames=idx, params=params)


def fit_betas_to_scan(scan_vertices: np.ndarray, scan_faces: np.ndarray | None = None, *,
                      init: BodyParams | None = None, config: ShapeFitConfig | None = None,
                      samples: int = 6000, seed: int = 0, progress: bool = False) -> ShapeFit:
    """Betas from a scan of the subject (a mesh or a point cloud, metres).

    The scan is treated as one frame seen from everywhere: every body vertex pairs with the
    scan, and the cloud → body term uses the scan's normals when faces are given.

    Args:
        scan_vertices: (V,3) scan points, metres, any frame (the pose is fitted too).
        scan_faces: (F,3) triangles, for normals and area-uniform samples; None: the vertices
            are used as they are (point-to-point where a normal would be needed).
        init: one frame of initial parameters; default: a relaxed standing pose at the scan's
            centroid facing +Z (Y up), betas 0. Give one for a scan in another orientation.
            The pose prior is widened to ``SCAN_PRIOR_DEG``: a scan's pose is known roughly.
        config: :class:`ShapeFitConfig` (its ``frames`` is ignored).
        samples: scan points used (area-uniform samples of a mesh, or a random subset).
        seed: sampling seed.
        progress: tqdm bar.

    Returns:
        :class:`ShapeFit` with ``frames`` = [0] and the scan's fitted pose.
    """
    cfg = config or ShapeFitConfig()
    v = np.asarray(scan_vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < cfg.body.min_points:
        raise ValueError(f"scan_vertices must be (V,3) with V >= {cfg.body.min_points}, got "
                         f"{v.shape}")
    rng = np.random.default_rng(seed)
    normals = None
    if scan_faces is not None:
        f = np.asarray(scan_faces, dtype=np.int64)
        if f.ndim != 2 or f.shape[1] != 3 or f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"scan_faces must be (F,3) indices into {len(v)} vertices")
        tri = v[f]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = np.linalg.norm(cross, axis=1)
        face = rng.choice(len(f), size=samples, p=area / area.sum())
        r1, r2 = rng.random((2, samples, 1))
        s = np.sqrt(r1)
        pts = (1 - s) * tri[face, 0] + s * (1 - r2) * tri[face, 1] + s * r2 * tri[face, 2]
        normals = cross[face] / np.maximum(area[face, None], 1e-12)
    else:
        pts = v[rng.choice(len(v), size=min(samples, len(v)), replace=False)]
    if init is None:
        model = cached_model(cfg.body.coarse_model, cfg.body.device, cfg.body.dtype)
        pelvis = model.rest_joints(np.zeros((1, NUM_BETAS)))[0, 0].detach().cpu().numpy()
        init = BodyParams(np.zeros((1, 3)), standing_pose()[None],
                          (pts.mean(0) - pelvis)[None], np.zeros(NUM_BETAS))
    if init.num_frames != 1:
        raise ValueError(f"init must hold one frame (the scan's pose), got {init.num_frames}")
    cloud = (pts.astype(np.float32), None if normals is None else normals.astype(np.float32))
    body = dataclasses.replace(cfg.body, points=samples,
                               surface_points=max(cfg.body.surface_points, samples),
                               prior_sigma_deg=max(cfg.body.prior_sigma_deg, SCAN_PRIOR_DEG))
    cfg = dataclasses.replace(cfg, body=body)
    padded = pad_clouds([cloud], samples, seed)
    stages = _stages(cfg)
    with tqdm(total=sum(s.iters for s in stages), disable=not progress, desc="scan shape fit",
              unit="it") as bar:
        aa, transl, betas = optimise(stages, padded, init, None, body, np.zeros(1, np.int64),
                                     bar)
    params = BodyParams(aa[:, 0], aa[:, 1:].reshape(1, -1), transl, betas)
    return ShapeFit(betas=betas, frames=np.zeros(1, np.int64), params=params)
