"""Nearest neighbours of many frames at once, each frame searched only within itself.

One scipy ``cKDTree`` per frame, built once and queried many times (a session's clouds are fixed
during a fit). Measured here on 60 frames: a tree per frame builds and queries 2-3x faster than a
single tree over all frames shifted apart (smaller trees stay in cache), so the loop over frames
is the fast way, and batching pays off in the torch optimisation instead. A query may be bounded
by a distance (``max_distance``), which prunes the search for points with nothing near.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["BatchedTree", "batched_nearest"]


class BatchedTree:
    """k-d trees over the targets of T frames.

    Args:
        targets: (T,K,3) points.
        mask: (T,K) bool targets that may be found (default all).
    """

    def __init__(self, targets: np.ndarray, mask: np.ndarray | None = None) -> None:
        x = np.asarray(targets)  # any float dtype and layout; each frame's subset is converted
        if x.ndim != 3 or x.shape[2] != 3:
            raise ValueError(f"targets must be (T, K, 3), got {x.shape}")
        xm = np.ones(x.shape[:2], bool) if mask is None else np.asarray(mask, bool)
        if xm.shape != x.shape[:2]:
            raise ValueError(f"mask {xm.shape} must be (T, K) = {x.shape[:2]}")
        self.frames = len(x)
        self.ids = [np.flatnonzero(m) for m in xm]  # each frame's allowed target indices
        # sliding-midpoint, non-compact trees build faster than the defaults and query as fast;
        # leaves of 32 points (not 16) build and query ~10% faster on body meshes and clouds
        # of 1-13k points; each tree gets a fresh float64 copy of its frame's allowed targets,
        # so it need not copy them again
        self.trees = [cKDTree(np.asarray(x[t][ids], dtype=np.float64), leafsize=32,
                              balanced_tree=False, compact_nodes=False, copy_data=False)
                      if len(ids) else None for t, ids in enumerate(self.ids)]

    def query(self, queries: np.ndarray, mask: np.ndarray | None = None,
              max_distance: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """Each query point's nearest target of the same frame.

        Args:
            queries: (T,M,3) points (T as the targets).
            mask: (T,M) bool queries to answer (default all).
            max_distance: targets farther than this (metres) are not looked for, which
                prunes the search (the caller drops such pairs anyway).

        Returns:
            index (T,M) int64 into each frame's targets, and distance (T,M) float64; index 0
            and distance ``inf`` for a masked query, in a frame without allowed targets, or
            with no target within ``max_distance``.
        """
        q = np.asarray(queries)
        if q.ndim != 3 or q.shape[2] != 3 or len(q) != self.frames:
            raise ValueError(f"queries must be ({self.frames}, M, 3), got {q.shape}")
        t, m = q.shape[:2]
        qm = np.ones((t, m), bool) if mask is None else np.asarray(mask, bool)
        index = np.zeros((t, m), np.int64)
        dist = np.full((t, m), np.inf)
        for k, (tree, ids) in enumerate(zip(self.trees, self.ids, strict=True)):
            sel = np.flatnonzero(qm[k])
            if tree is None or not len(sel):
                continue
            d, j = tree.query(np.asarray(q[k, sel], dtype=np.float64),
                              distance_upper_bound=max_distance)
            found = np.isfinite(d)  # none within max_distance: cKDTree answers (inf, n)
            index[k, sel] = np.where(found, ids[np.minimum(j, len(ids) - 1)], 0)
            dist[k, sel] = d
        return index, dist


def batched_nearest(queries: np.ndarray, targets: np.ndarray,
                    query_mask: np.ndarray | None = None, target_mask: np.ndarray | None = None,
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Each query point's nearest target point of the same frame (a one-off
    :class:`BatchedTree`).

    Args:
        queries: (T,M,3) points; targets: (T,K,3) points (same T).
        query_mask: (T,M) bool queries to answer (default all).
        target_mask: (T,K) bool targets that may be found (default all).

    Returns:
        index (T,M) int64 into each frame's targets, and distance (T,M) float64; for a masked
        query, or in a frame without any allowed target, index 0 and distance ``inf``.
    """
    q = np.asarray(queries, dtype=np.float64)
    if q.ndim != 3 or q.shape[2] != 3 or len(q) != len(targets):
        raise ValueError(f"queries (T,M,3) and targets (T,K,3) expected, got {q.shape} and "
                         f"{np.shape(targets)}")
    return BatchedTree(targets, target_mask).query(q, query_mask)
