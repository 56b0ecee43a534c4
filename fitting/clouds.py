"""Per-frame point clouds of different sizes → fixed-size padded arrays for batched fitting.

Each frame's cloud is subsampled to at most ``max_points`` points (a random subset without
replacement, drawn from ``numpy.random.default_rng(seed + frame)``, so a frame gets the same
subset whether it is fitted alone or in a batch), then padded to the batch's largest count with
a mask marking the real points.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["PaddedClouds", "cloud_arrays", "pad_clouds"]


@dataclasses.dataclass(frozen=True)
class PaddedClouds:
    """Clouds of T frames, padded to N points (world metres).

    Attributes:
        points: (T,N,3) float32; padding rows are 0.
        normals: (T,N,3) float32 unit normals facing the camera that saw each point, or None
            when the clouds came without normals.
        mask: (T,N) bool, True for real points.
        counts: (T,) int, points per frame before subsampling.
    """

    points: np.ndarray
    normals: np.ndarray | None
    mask: np.ndarray
    counts: np.ndarray

    @property
    def num_frames(self) -> int:
        return len(self.points)


def cloud_arrays(cloud: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """(N,3) points and (N,3) normals or None of a cloud given as a
    :class:`couch.capture.pointcloud.FusedCloud` (anything with ``points`` and ``normals``),
    a ``(points, normals)`` pair, or a bare (N,3) array.

    Raises:
        ValueError: the arrays are not (N,3), or points and normals differ in length.
    """
    if hasattr(cloud, "points"):
        pts, nrm = cloud.points, getattr(cloud, "normals", None)
    elif isinstance(cloud, tuple):
        pts, nrm = cloud
    else:
        pts, nrm = cloud, None
    pts = np.asarray(pts, dtype=np.float32)
    if pts.size == 0:
        pts = pts.reshape(0, 3)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"a cloud's points must be (N, 3), got {pts.shape}")
    if nrm is not None:
        nrm = np.asarray(nrm, dtype=np.float32).reshape(-1, 3) if np.size(nrm) == 0 else \
            np.asarray(nrm, dtype=np.float32)
        if nrm.shape != pts.shape:
            raise ValueError(f"a cloud's normals {nrm.shape} must match its points {pts.shape}")
    return pts, nrm


def pad_clouds(clouds: Sequence[Any], max_points: int, seed: int = 0,
               frame_ids: Sequence[int] | None = None) -> PaddedClouds:
    """Subsample and pad T clouds (see the module docstring).

    Args:
        clouds: T clouds (see :func:`cloud_arrays`); an empty cloud gives an all-False mask row.
        max_points: points kept per frame (> 0).
        seed: base seed of the subsets.
        frame_ids: (T,) the clouds' frame numbers in the session, which seed each frame's subset
            (default 0..T-1).

    Returns:
        :class:`PaddedClouds`; normals are None unless every non-empty cloud has them.
    """
    if max_points <= 0:
        raise ValueError(f"max_points must be > 0, got {max_points}")
    ids = range(len(clouds)) if frame_ids is None else frame_ids
    arrays = [cloud_arrays(c) for c in clouds]
    with_normals = all(n is not None for p, n in arrays if len(p))
    picked = []
    for fid, (p, n) in zip(ids, arrays, strict=True):
        if len(p) > max_points:
            sel = np.sort(np.random.default_rng(seed + int(fid)).choice(len(p), max_points,
                                                                        replace=False))
            p, n = p[sel], (n[sel] if n is not None else None)
        picked.append((p, n))
    t = len(clouds)
    size = max([len(p) for p, _ in picked] + [1])
    points = np.zeros((t, size, 3), np.float32)
    normals = np.zeros((t, size, 3), np.float32) if with_normals else None
    mask = np.zeros((t, size), bool)
    for i, (p, n) in enumerate(picked):
        points[i, :len(p)] = p
        mask[i, :len(p)] = True
        if normals is not None and n is not None:
            normals[i, :len(p)] = n
    counts = np.array([len(p) for p, _ in arrays], dtype=np.int64)
    return PaddedClouds(points, normals, mask, counts)
