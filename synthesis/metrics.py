"""Evaluation metrics for synthesised human–chair motion (COUCH, ECCV 2022, Sec. 5), in numpy.

Conventions (DESIGN.md): world frame in metres, +Y up, floor at y = 0; SMPL's 24 joints in SMPL
order; hand order is always (left, right). Everything is vectorised over frames; the only Python
loops run over chairs (:func:`contact_apd`), table rows, or memory-bounded chunks of frames
(:func:`penetration`).

Contact accuracy (COUCH Sec. 5, "controllability"): every synthesised sequence is asked to touch
the chair at one contact point per hand (or not to use that hand). :func:`closest_hand_distances`
takes, per sequence and hand, the smallest distance over the sequence's frames between the hand's
contact point and the asked contact.

- **ACE** (Average Contact Error, :func:`ace`): the mean of those closest distances (m) over all
  sequences and requested hands.
- **AP@k** (:func:`contact_precision`): the fraction of requested hand contacts whose closest
  distance is within k metres (the paper reports k = 3, 5, 7, 9 cm).

Diversity (COUCH Sec. 5, "diversity"):

- **APD** (Average Pairwise Distance, :func:`apd`), as in the "diverse motion" literature: the mean
  Euclidean distance between all ordered pairs i != j of S samples generated for the same input.
  :func:`pose_feature_apd` applies it to root-relative joint positions ("APD on pose features").
- **Contact APD** (:func:`contact_apd`): APD of the two-hand contact positions (a 6-vector) that
  the ContactNet samples for one chair, averaged over chairs.

Physical plausibility:

- **Foot sliding** (:func:`foot_sliding`), as in CHOIS (Li et al., "Controllable Human-Object
  Interaction Synthesis", ECCV 2024) and HOI-Diff: horizontal displacement of the ankles and toes
  between consecutive frames, weighted by how close the joint is to the floor.
- **Penetration** (:func:`penetration`): how deep body mesh vertices go *into the chair*, read
  from the chair's signed distance grid (:class:`couch.augment.SignedDistanceGrid`, negative
  inside). Only the chair is considered, not the floor or self-intersections of the body.

:func:`format_table` prints a method x metric GitHub markdown table.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.distance import pdist

from couch.stats import bootstrap_interval

if TYPE_CHECKING:
    from couch.augment import SignedDistanceGrid

__all__ = [
    "AP_THRESHOLDS",
    "SMPL_FEET",
    "SMPL_FOOT_HEIGHTS",
    "ace",
    "apd",
    "closest_hand_distances",
    "closest_hand_offsets",
    "contact_apd",
    "contact_intervals",
    "contact_precision",
    "foot_sliding",
    "format_intervals",
    "format_table",
    "penetration",
    "pose_feature_apd",
]

AP_THRESHOLDS: tuple[float, ...] = (0.03, 0.05, 0.07, 0.09)
"""AP@k thresholds (m) of COUCH Sec. 5: 3, 5, 7 and 9 cm."""

SMPL_FEET: tuple[int, ...] = (7, 8, 10, 11)
"""SMPL joint indices of the left/right ankle (7, 8) and left/right foot (toe) joints (10, 11)."""

SMPL_FOOT_HEIGHTS: tuple[float, ...] = (0.08, 0.08, 0.04, 0.04)
"""Height thresholds H (m) of :data:`SMPL_FEET` for foot sliding (CHOIS: ankles 8 cm, toes 4 cm)."""

# Points queried at once in the signed distance grid (its trilinear query holds ~10 float64
# arrays of this many points), about 100 MB peak.
_QUERY_CHUNK = 1_000_000


def _shape_error(name: str, expected: str, array: np.ndarray) -> ValueError:
    return ValueError(f"{name} must have shape {expected}, got {tuple(np.shape(array))}")


def closest_hand_offsets(hands: np.ndarray, contacts: np.ndarray,
                         valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where each hand was at its closest approach to its asked contact point, per sequence.

    Args:
        hands: (N, T, 2, 3) world positions (m) of the left/right hand contact point for N
            sequences of T frames (pad shorter sequences and mark the padding in ``valid``).
            Non-finite hand positions count as invalid frames.
        contacts: (N, 2, 3) world position (m) of the contact asked of each hand; a row with any
            NaN means "no contact asked of this hand".
        valid: optional (N, T) bool, the frames to consider (default: all).

    Returns:
        offsets (N, 2, 3) float64: ``hand - contact`` (world, m) at the frame of the smallest
        ``|hand - contact|`` over valid frames, and that frame (N, 2) int; NaN offsets and
        frame -1 where no contact was asked or a sequence has no valid frame.
    """
    h = np.asarray(hands, np.float64)
    c = np.asarray(contacts, np.float64)
    if h.ndim != 4 or h.shape[2:] != (2, 3):
        raise _shape_error("hands", "(N, T, 2, 3)", h)
    n, t = h.shape[:2]
    if c.shape != (n, 2, 3):
        raise _shape_error("contacts", f"(N, 2, 3) = ({n}, 2, 3) to match hands", c)
    if valid is None:
        mask = np.ones((n, t), dtype=bool)
    else:
        mask = np.asarray(valid)
        if mask.shape != (n, t):
            raise _shape_error("valid", f"(N, T) = ({n}, {t}) to match hands", mask)
        mask = mask.astype(bool)
    vec = h - c[:, None]  # (N, T, 2, 3), NaN where no contact / bad hand
    dist = np.linalg.norm(vec, axis=-1)  # (N, T, 2)
    usable = mask[..., None] & np.isfinite(dist)
    frame = np.where(usable, dist, np.inf).argmin(axis=1)  # (N, 2)
    found = usable.any(axis=1) & np.isfinite(c).all(-1)
    offsets = np.take_along_axis(vec, frame[:, None, :, None], axis=1)[:, 0]
    return (np.where(found[..., None], offsets, np.nan),
            np.where(found, frame, -1).astype(np.int64))


def closest_hand_distances(hands: np.ndarray, contacts: np.ndarray,
                           valid: np.ndarray | None = None) -> np.ndarray:
    """Closest approach of each hand to its asked contact point, per sequence: the length of
    :func:`closest_hand_offsets` (same arguments).

    Returns:
        (N, 2) float64: min over valid frames of ``|hand - contact|`` (m); NaN where no contact
        was asked, and also where a sequence has no valid frame (so :func:`ace` and
        :func:`contact_precision` skip it; check ``np.isnan`` if that must not happen).
    """
    return np.linalg.norm(closest_hand_offsets(hands, contacts, valid)[0], axis=-1)


def ace(distances: np.ndarray) -> float:
    """Average Contact Error (m, COUCH Sec. 5): the mean of the finite entries of ``distances``
    (the (N, 2) output of :func:`closest_hand_distances`; any shape works). NaN if none."""
    d = np.asarray(distances, np.float64)
    d = d[np.isfinite(d)]
    return float(d.mean()) if d.size else math.nan


def contact_precision(distances: np.ndarray,
                      thresholds: Sequence[float] = AP_THRESHOLDS) -> dict[float, float]:
    """AP@k (COUCH Sec. 5): for each threshold k (m), the fraction in [0, 1] of finite entries of
    ``distances`` ((N, 2) closest distances in m, NaN = no contact asked) with distance <= k.

    Returns ``{k: fraction}`` in the order of ``thresholds``; fractions are NaN if no entry is
    finite. Multiply by 100 for the paper's percentages.
    """
    d = np.asarray(distances, np.float64)
    d = d[np.isfinite(d)]
    ks = [float(k) for k in thresholds]
    if not ks:
        raise ValueError("contact_precision: thresholds is empty")
    if not d.size:
        return dict.fromkeys(ks, math.nan)
    hits = d[None, :] <= np.asarray(ks)[:, None]  # (K, M)
    return {k: float(v) for k, v in zip(ks, hits.mean(axis=1), strict=True)}


def contact_intervals(distances: Mapping[str, np.ndarray], reference: str | None = None, *,
                      threshold: float = 0.05, level: float = 0.95, resamples: int = 2000,
                      seed: int = 0) -> dict[str, dict[str, tuple[float, float, float]]]:
    """How far ACE and AP@k can be trusted: bootstrap intervals over trials.

    A trial (one character, one asked contact set) is the unit that is resampled, both hands
    together. With a few dozen trials ACE moves by centimetres from one set of trials to the
    next, because one trial that never reaches its contact adds its whole distance to the
    mean; these intervals say how much.

    Args:
        distances: method → (N, 2) closest hand distances (m; NaN: no contact asked) of the
            same N trials (:func:`closest_hand_distances`, ``evaluate``'s raw output).
        reference: a method of ``distances`` (e.g. the baseline): every other method also gets
            its ACE reduction against it, resampled paired (the same trials for both).
        threshold: m, the AP@k reported (default AP@5).
        level: confidence level of the intervals.
        resamples, seed: bootstrap resamples and their random seed.

    Returns:
        method → {"ACE cm": (value, low, high), "AP@5 %": (...), and with ``reference``
        "ACE reduction %": (...), i.e. 100 (1 - ACE / ACE of the reference)}.
    """
    d = {m: np.asarray(v, np.float64) for m, v in distances.items()}
    sizes = {len(v) for v in d.values()}
    if len(sizes) > 1:
        raise ValueError(f"contact_intervals: the methods have different trial counts {sizes}")
    if reference is not None and reference not in d:
        raise ValueError(f"contact_intervals: reference {reference!r} is not one of {list(d)}")
    n = sizes.pop() if sizes else 0
    name = f"AP@{round(threshold * 100)} %"

    def stats(m: str) -> dict[str, Callable[[np.ndarray], float]]:
        out = {"ACE cm": lambda i: 100 * ace(d[m][i]),
               name: lambda i: 100 * contact_precision(d[m][i], [threshold])[threshold]}
        if reference is not None and m != reference:
            out["ACE reduction %"] = lambda i: 100 * (1 - ace(d[m][i]) / ace(d[reference][i]))
        return out

    every = np.arange(n)
    return {m: {k: (f(every), *bootstrap_interval(f, n, level=level, resamples=resamples,
                                                        seed=seed))
                for k, f in stats(m).items()} for m in d}


def apd(features: np.ndarray) -> float:
    """Average Pairwise Distance of S samples (S, D): the mean Euclidean distance over all ordered
    pairs i != j, i.e. ``sum_{i != j} |x_i - x_j| / (S (S - 1))`` (units of the features).

    Equal to the mean over unordered pairs (``scipy.spatial.distance.pdist``). Raises ValueError
    for S < 2 or a non-(S, D) array, and for non-finite features.
    """
    x = np.asarray(features, np.float64)
    if x.ndim != 2:
        raise _shape_error("apd: features", "(S, D)", x)
    if x.shape[0] < 2:
        raise ValueError(f"apd needs at least 2 samples (S, D), got shape {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError(f"apd: features of shape {x.shape} contain NaN or inf")
    return float(pdist(x).mean())


def contact_apd(contacts: np.ndarray) -> float:
    """Contact APD (COUCH Sec. 5): diversity of the sampled two-hand contacts per chair (m).

    Args:
        contacts: (L, N, 2, 3) for L chairs, N sampled (left, right) hand contact positions each,
            in metres (one frame per chair, e.g. the chair frame); a sample with any non-finite
            coordinate (a dropped contact) is left out.

    Returns:
        The mean over chairs with >= 2 complete samples of :func:`apd` of those samples'
        flattened 6-vectors; NaN if no chair has two.
    """
    c = np.asarray(contacts, np.float64)
    if c.ndim != 4 or c.shape[2:] != (2, 3):
        raise _shape_error("contacts", "(L, N, 2, 3)", c)
    complete = np.isfinite(c).all(axis=(2, 3))  # (L, N)
    flat = c.reshape(c.shape[0], c.shape[1], 6)
    per_chair = [apd(flat[i][complete[i]]) for i in range(c.shape[0]) if complete[i].sum() >= 2]
    return float(np.mean(per_chair)) if per_chair else math.nan


def pose_feature_apd(joints: np.ndarray) -> float:
    """APD on pose features: ``joints`` (S, T, J, 3) world joint positions (m) of S samples of the
    same segment; each sample's feature is its root-relative joints (joint 0 subtracted per
    frame), flattened to T*J*3. Returns :func:`apd` of those (m, a distance in R^(T*J*3))."""
    j = np.asarray(joints, np.float64)
    if j.ndim != 4 or j.shape[-1] != 3:
        raise _shape_error("joints", "(S, T, J, 3)", j)
    rel = j - j[:, :, :1]
    return apd(rel.reshape(j.shape[0], -1))


def foot_sliding(joints: np.ndarray, fps: float, feet: tuple[int, ...] = SMPL_FEET,
                 heights: tuple[float, ...] = SMPL_FOOT_HEIGHTS) -> float:
    """Foot sliding as in CHOIS / HOI-Diff, in metres per frame (at ``fps``).

    For each foot joint f (SMPL 7/8 ankles with H = 8 cm, 10/11 toes with H = 4 cm) and each pair
    of consecutive frames (t-1, t): d = horizontal (x, z) displacement (m), h = the joint's height
    y at frame t (m above the floor y = 0), weight w = clip(2 - 2^(h / H), 0, 1) (1 on the floor,
    0 at or above H), skate = d * w. The result is the mean of skate over the T-1 frame pairs and
    the feet.

    Args:
        joints: (T, J, 3) world joint positions (m, +Y up, floor at y = 0), T >= 2.
        fps: frame rate (Hz) of ``joints``, > 0. The value is a displacement per frame at this
            rate: multiply by ``fps`` for m/s, by 1000 for mm/frame. Compare methods at the same
            fps (CHOIS evaluates at 30 fps).
        feet: joint indices to test.
        heights: H (m) per entry of ``feet``.

    Differences from CHOIS's code: the weight is clipped (joints below the floor count as 1), the
    height is read at the later frame, and the mean runs over all frame pairs (CHOIS sums the
    gated frames, divides by T and reports mm).
    """
    j = np.asarray(joints, np.float64)
    if j.ndim != 3 or j.shape[-1] != 3:
        raise _shape_error("joints", "(T, J, 3)", j)
    if j.shape[0] < 2:
        raise ValueError(f"foot_sliding needs at least 2 frames, got joints of shape {j.shape}")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    idx = np.asarray(feet, dtype=int)
    h_ref = np.asarray(heights, np.float64)
    if idx.ndim != 1 or idx.size == 0 or h_ref.shape != idx.shape:
        raise ValueError(f"feet and heights must be non-empty and of equal length, got "
                         f"{len(feet)} and {len(heights)}")
    if (idx < -j.shape[1]).any() or (idx >= j.shape[1]).any():
        raise ValueError(f"feet {tuple(feet)} out of range for joints of shape {j.shape}")
    if not (h_ref > 0).all():
        raise ValueError(f"heights must be > 0, got {tuple(heights)}")
    p = j[:, idx]  # (T, F, 3)
    if not np.isfinite(p).all():
        raise ValueError("foot_sliding: foot joints contain NaN or inf")
    disp = np.linalg.norm(p[1:, :, [0, 2]] - p[:-1, :, [0, 2]], axis=-1)  # (T-1, F)
    w = np.clip(2.0 - np.exp2(p[1:, :, 1] / h_ref), 0.0, 1.0)
    return float((disp * w).mean())


def penetration(vertices: np.ndarray, sdf: SignedDistanceGrid,
                world_from_chair: np.ndarray | None = None,
                depth_threshold: float = 0.04) -> dict[str, float]:
    """Body-into-chair penetration from the chair's signed distance grid.

    Args:
        vertices: (T, V, 3) world positions (m) of the body mesh vertices over T frames.
        sdf: the chair's :class:`couch.augment.SignedDistanceGrid` in the *chair* frame (any object
            with ``query(points (..., 3)) -> (...,)`` signed distance in m, negative inside).
        world_from_chair: (4, 4) rigid transform from the chair frame to the world (None: the
            chair frame is the world); vertices are mapped by its inverse before the query.
        depth_threshold: depth (m) above which a frame counts as penetrating (default 4 cm).

    A vertex's depth is ``-min(sd, 0)`` (m). Per frame: the max depth over vertices, and the mean
    depth over the penetrating vertices (sd < 0; 0 if there are none).

    Returns:
        ``mean_depth_m``: mean over frames of the per-frame max depth (m);
        ``frames_over_pct``: percentage (0-100) of frames whose max depth > ``depth_threshold``;
        ``max_depth_m``: max depth over all frames (m);
        ``mean_vertex_depth_m``: mean over frames of the per-frame mean penetrating depth (m).

    The grid is queried in chunks of frames (about a million points each) to bound memory.
    """
    v = np.asarray(vertices, np.float64)
    if v.ndim != 3 or v.shape[-1] != 3:
        raise _shape_error("vertices", "(T, V, 3)", v)
    t, nv = v.shape[:2]
    if t == 0 or nv == 0:
        raise ValueError(f"penetration needs at least one frame and vertex, got shape {v.shape}")
    if world_from_chair is not None:
        m = np.asarray(world_from_chair, np.float64)
        if m.shape != (4, 4):
            raise _shape_error("world_from_chair", "(4, 4)", m)
        chair_from_world = np.linalg.inv(m)
        v = v @ chair_from_world[:3, :3].T + chair_from_world[:3, 3]
    chunk = max(1, _QUERY_CHUNK // nv)
    max_depth = np.empty(t)
    mean_depth = np.empty(t)
    for start in range(0, t, chunk):  # chunks of frames, for memory only
        sd = np.asarray(sdf.query(v[start:start + chunk]), np.float64)
        depth = -np.minimum(sd, 0.0)  # (chunk, V)
        n_in = (sd < 0).sum(axis=1)
        max_depth[start:start + chunk] = depth.max(axis=1)
        mean_depth[start:start + chunk] = depth.sum(axis=1) / np.maximum(n_in, 1)
    if not np.isfinite(max_depth).all():
        raise ValueError("penetration: vertices or signed distances contain NaN or inf")
    return {
        "mean_depth_m": float(max_depth.mean()),
        "frames_over_pct": float(100.0 * (max_depth > depth_threshold).mean()),
        "max_depth_m": float(max_depth.max()),
        "mean_vertex_depth_m": float(mean_depth.mean()),
    }


def _format_value(value: object) -> str:
    if value is None:
        return "–"
    if isinstance(value, str):
        return value.replace("|", "\\|")
    x = float(value)  # type: ignore[arg-type]
    if math.isnan(x):
        return "–"
    if math.isinf(x) or x == 0:
        return f"{x:g}"
    x = float(f"{x:.3g}")  # round to 3 significant digits first (9.996 -> 10.0)
    if abs(x) >= 100:  # keep every integer digit (1234.4 -> 1234, not 1.23e+03 or 1230)
        return f"{float(value):.0f}"  # type: ignore[arg-type]
    return f"{x:.{2 - math.floor(math.log10(abs(x)))}f}"


def format_table(rows: Mapping[str, Mapping[str, float]],
                 columns: Sequence[str] | None = None, first: str = "method") -> str:
    """A GitHub markdown table: one row per method (key of ``rows``, in order; ``first`` heads
    their column), one column per metric (``columns`` in the given order; default: the union
    of the rows' keys in first-seen order). Numbers are printed with 3 significant digits
    without exponent (2.31, 0.0450, 12.3; values >= 100 as integers: 1234), NaN, None and
    missing entries as "–". Flatten nested values such as the AP@k dict first:
    ``{f"AP@{k * 100:g}cm": v for k, v in ap.items()}``."""
    if columns is None:
        cols = list(dict.fromkeys(key for metrics in rows.values() for key in metrics))
    else:
        cols = list(columns)
    header = [first, *(str(c).replace("|", "\\|") for c in cols)]
    lines = [
        "| " + " | ".join(header) + " |",
        "|" + "|".join([" --- "] + [" ---: "] * len(cols)) + "|",
    ]
    for method, metrics in rows.items():
        cells = [str(method).replace("|", "\\|"), *(_format_value(metrics.get(c)) for c in cols)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def format_intervals(intervals: Mapping[str, Mapping[str, tuple[float, float, float]]],
                     trials: int, level: float = 0.95) -> str:
    """Markdown lines of :func:`contact_intervals`' output, one per method:
    ``- couch: ACE 8.72 [7.91, 9.60] cm; AP@5 41.6 [37.0, 46.1] %; ...``."""
    lines = [f"{round(level * 100)} % bootstrap intervals over the {trials} trials (a trial's "
             f"hands resampled together; reductions paired, on the same trials):", ""]
    for method, stats in intervals.items():
        parts = []
        for key, (value, low, high) in stats.items():
            label, unit = key.rsplit(" ", 1)
            parts.append(f"{label} {_format_value(value)} [{_format_value(low)}, "
                         f"{_format_value(high)}] {unit}")
        lines.append(f"- {method}: " + "; ".join(parts))
    return "\n".join(lines)
