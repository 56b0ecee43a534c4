"""Run-length helpers for per-frame flags: the runs of True in a (T,) bool array, and the
clean-ups contact and plant detection apply to them (gaps filled, short runs dropped, runs
trimmed to a core). Frames are indices; ends are exclusive."""

from __future__ import annotations

import numpy as np

__all__ = ["drop_short_runs", "fill_gaps", "flip_runs", "runs", "trim_edges"]


def runs(flags: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive) frame indices of the runs of True in a (T,) bool array."""
    f = np.concatenate([[False], np.asarray(flags, bool), [False]])
    edges = np.flatnonzero(f[1:] != f[:-1])
    return edges[0::2], edges[1::2]


def flip_runs(flags: np.ndarray, keep: np.ndarray, starts: np.ndarray, ends: np.ndarray
              ) -> np.ndarray:
    """(T,) bool: ``flags`` with the runs [starts, ends) selected by ``keep`` flipped."""
    out = np.asarray(flags, bool).copy()
    delta = np.zeros(len(out) + 1, dtype=np.int64)
    np.add.at(delta, starts[keep], 1)
    np.add.at(delta, ends[keep], -1)
    flip = np.cumsum(delta[:-1]) > 0
    out[flip] = ~out[flip]
    return out


def fill_gaps(flags: np.ndarray, max_frames: int) -> np.ndarray:
    """(T,) or (T,K) bool with False runs of at most ``max_frames`` between two True runs set
    True (gaps at the ends of the sequence are not gaps and stay)."""
    f = np.asarray(flags, bool)
    if f.ndim == 2:
        return np.stack([fill_gaps(f[:, k], max_frames) for k in range(f.shape[1])], 1)
    s, e = runs(~f)
    inner = (s > 0) & (e < len(f)) & (e - s <= max_frames)
    return flip_runs(f, inner, s, e)


def drop_short_runs(flags: np.ndarray, min_frames: int) -> np.ndarray:
    """(T,) or (T,K) bool with True runs shorter than ``min_frames`` set False."""
    f = np.asarray(flags, bool)
    if f.ndim == 2:
        return np.stack([drop_short_runs(f[:, k], min_frames) for k in range(f.shape[1])], 1)
    s, e = runs(f)
    return flip_runs(f, e - s < min_frames, s, e)


def trim_edges(flags: np.ndarray, core: np.ndarray) -> np.ndarray:
    """(T,) or (T,K) bool ``flags`` with each True run cut to the span from its first to its last
    ``core`` frame (a run without one goes)."""
    f = np.asarray(flags, bool)
    core = np.asarray(core, bool)
    if f.shape != core.shape:
        raise ValueError(f"trim_edges: flags {f.shape} and core {core.shape} differ")
    core = core & f
    if f.ndim == 2:
        return np.stack([trim_edges(f[:, k], core[:, k]) for k in range(f.shape[1])], 1)
    out = np.zeros_like(f)
    idx = np.flatnonzero(core)
    for a, b in zip(*runs(f), strict=True):
        inside = idx[(idx >= a) & (idx < b)]
        if len(inside):
            out[inside[0]:inside[-1] + 1] = True
    return out
