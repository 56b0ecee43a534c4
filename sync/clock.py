"""A linear clock between the Kinect master clock and another clock, estimated from two signals.

The model (the simulator's ``truth.json`` ``imu.clock`` and :func:`couch.fitting.sync_error`)::

    t_other = (1 + drift_ppm · 1e-6) · t_kinect + offset_s

``offset_s`` is the other clock's reading at Kinect time 0, ``drift_ppm`` its rate error. The
estimator is generic: it compares a Kinect-side time series with an other-side time series of the
*same* physical quantity (e.g. the person's centroid seen by the cameras and the suit's body
points; later, fitted joints and IMU joints) after an optional feature transform applied
identically to both sides, up to a per-channel gain and bias (nuisances, solved in closed form).

Two stages:

1. **coarse** (:func:`coarse_offset`): drift fixed at the initial guess, offset searched over the
   whole range where the recordings overlap (or a window): a masked, normalised
   cross-correlation of the features by FFT on the Kinect frame grid, the other signal sampled
   on that grid at ``phases`` sub-frame phases, so the step is a fraction of a frame;
2. **fine** (:func:`refine_clock`): weighted, robust least squares on (offset, drift) where the
   other signal is a cubic spline evaluated at ``(1 + drift)·t + offset`` (sub-frame
   interpolation), the gains and biases eliminated at every evaluation (variable projection).

:func:`estimate_clock` runs both. :func:`refine_clock` alone is the entry for a later refinement
from a first estimate (e.g. on joint positions after a body fit).

Arrays: times are float64 seconds (Kinect master clock for ``kinect_time``, the other clock for
``other_time``); values are ``(N, D)`` or ``(N, ..., 3)`` (flattened to channels after the
feature transform); NaN marks a missing sample.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable

import numpy as np
from scipy.interpolate import make_interp_spline
from scipy.optimize import OptimizeResult, least_squares

__all__ = [
    "ClockEstimate",
    "ClockModel",
    "ClockSyncConfig",
    "FeatureFn",
    "SyncError",
    "coarse_offset",
    "estimate_clock",
    "refine_clock",
]

log = logging.getLogger(__name__)

FeatureFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``features(time (N,), values (..., N, ...)) -> (..., N, F)``: applied to both sides on the
Kinect frame grid (leading batch dimensions must be carried through)."""


class SyncError(ValueError):
    """Clocks that cannot be synchronised from the given input; the message names the
    streams/files and what is wrong (no overlap, no motion, inconsistent timestamps)."""


@dataclasses.dataclass(frozen=True)
class ClockModel:
    """``t_other = (1 + drift_ppm·1e-6)·t_kinect + offset_s`` (seconds)."""

    offset_s: float
    drift_ppm: float = 0.0

    @property
    def scale(self) -> float:
        """d t_other / d t_kinect."""
        return 1.0 + self.drift_ppm * 1e-6

    def to_other(self, t_kinect: np.ndarray | float) -> np.ndarray:
        """Kinect-clock seconds → other-clock seconds."""
        return self.scale * np.asarray(t_kinect, dtype=np.float64) + self.offset_s

    def to_kinect(self, t_other: np.ndarray | float) -> np.ndarray:
        """Other-clock seconds → Kinect-clock seconds."""
        return (np.asarray(t_other, dtype=np.float64) - self.offset_s) / self.scale


@dataclasses.dataclass(frozen=True)
class ClockSyncConfig:
    """Knobs of :func:`estimate_clock` / :func:`refine_clock`."""

    min_overlap_s: float = 4.0  # shortest overlap of the two recordings a coarse match may use
    min_overlap_fraction: float = 0.5  # ... and this share of the shorter recording
    min_pairs: int = 12  # frames with the signal on both sides a coarse match needs
    phases: int = 8  # sub-frame phases of the coarse search (step = frame period / phases)
    fit_drift: bool = True  # False: drift stays at the initial value
    # Gaussian prior (std, ppm) of the drift around the initial value (default 0): two quartz
    # clocks of ±20..50 ppm each differ by up to ~100 ppm. A short session cannot measure the
    # drift (20 ppm is 0.2 ms over 10 s), and a free drift would then throw the offset at
    # Kinect time 0 off; the prior keeps it near the initial value until the data outweigh it.
    # None: no prior (maximum likelihood).
    drift_prior_ppm: float | None = 100.0
    loss: str = "soft_l1"  # scipy least_squares loss of the fine stage
    robust_scale: float = 2.5  # residuals beyond this × their MAD-sigma are down-weighted
    max_gap_s: float = 0.1  # other-side samples farther apart than this are a gap (no data)
    edge_s: float = 0.05  # Kinect frames this close to the other recording's ends are not used
    min_motion: float = 1e-3  # feature std (signal units) below which a channel counts as flat
    min_correlation: float = 0.5  # fine-fit explained variance (R²) below this: low confidence
    min_peak_ratio: float = 2.0  # coarse: rival's / peak's unexplained variance below this: low
    rival_s: float = 0.5  # ... for rivals farther than this (s) from the peak
    max_iterations: int = 50
    reweight: bool = True  # second pass with channels weighted by their residual noise


@dataclasses.dataclass
class ClockEstimate:
    """A clock estimate and how far to trust it.

    Attributes:
        clock: the estimated :class:`ClockModel`.
        reference_time_s: Kinect time (s) at the weighted centre of the data used; the offset
            there, ``clock.to_other(reference_time_s) - reference_time_s``, and the drift are
            uncorrelated.
        offset_std_s: 1-σ uncertainty of the offset at ``reference_time_s`` (s), from the fit's
            Jacobian, the residual scale and the residuals' correlation time.
        offset_at_zero_std_s: 1-σ uncertainty of ``clock.offset_s`` (at Kinect time 0).
        drift_std_ppm: 1-σ uncertainty of the drift (ppm); NaN when the drift was not fitted.
        correlation: explained variance (R², 0..1) of the Kinect features by the other's at the
            solution, averaged over channels weighted by their variance.
        residual_rms: RMS of the normalised residuals (unit-variance channels).
        peak_ratio: coarse stage: unexplained variance (1 - mean R²) of the best rival offset
            (farther than ``rival_s`` from the peak) over the peak's (inf when there is no
            rival, NaN when the coarse stage did not run); near 1: ambiguous (periodic motion).
        coarse_offset_s: the coarse stage's offset (s), or None.
        overlap_s: Kinect seconds covered by the samples used.
        samples: number of Kinect frames used.
        channels: number of feature channels.
        confident: False when a check failed (see ``warnings``).
        warnings: why the estimate may be wrong.
        gains: (F,) per-channel gain of the other signal; biases: (F,) per-channel bias.
        drift_data_ppm, drift_data_std_ppm: the drift and its uncertainty from the data alone
            (before the prior of :attr:`ClockSyncConfig.drift_prior_ppm`).
    """

    clock: ClockModel
    reference_time_s: float
    offset_std_s: float
    offset_at_zero_std_s: float
    drift_std_ppm: float
    correlation: float
    residual_rms: float
    peak_ratio: float
    coarse_offset_s: float | None
    overlap_s: float
    samples: int
    channels: int
    confident: bool
    warnings: list[str]
    gains: np.ndarray
    biases: np.ndarray
    drift_data_ppm: float = math.nan
    drift_data_std_ppm: float = math.nan

    def summary(self) -> str:
        """One line for logs and reports."""
        drift = (f"{self.clock.drift_ppm:+.1f} ± {self.drift_std_ppm:.1f} ppm"
                 if math.isfinite(self.drift_std_ppm) else f"{self.clock.drift_ppm:+.1f} ppm "
                 f"(fixed)")
        flag = "" if self.confident else " LOW CONFIDENCE: " + "; ".join(self.warnings)
        return (f"offset {self.clock.offset_s:+.6f} s (± {1e3 * self.offset_std_s:.2f} ms at "
                f"t={self.reference_time_s:.2f} s), drift {drift}, R² {self.correlation:.3f}, "
                f"{self.samples} frames over {self.overlap_s:.1f} s{flag}")


# --------------------------------------------------------------------------- helpers


@dataclasses.dataclass
class _Grid:
    """Kinect samples on a uniform frame grid: t = t0 + k·period, k = 0..n-1."""

    t0: float
    period: float
    n: int
    index: np.ndarray  # (N,) grid row of each given sample

    @property
    def time(self) -> np.ndarray:
        return self.t0 + self.period * np.arange(self.n)


def _uniform_grid(time: np.ndarray, name: str) -> _Grid:
    """The uniform frame grid the (sorted, gap-allowed) sample times lie on."""
    t = np.asarray(time, dtype=np.float64)
    if t.ndim != 1 or len(t) < 3:
        raise SyncError(f"{name}: need at least 3 sample times, got shape {t.shape}")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise SyncError(f"{name}: sample times must be finite and strictly increasing")
    steps = np.diff(t)
    period = float(np.min(steps))
    mult = np.round(steps / period)
    period = float((t[-1] - t[0]) / mult.sum())
    index = np.concatenate([[0], np.cumsum(np.round(steps / period))]).astype(np.int64)
    resid = t - (t[0] + index * period)
    if np.max(np.abs(resid)) > 0.25 * period:
        raise SyncError(f"{name}: sample times are not on a regular frame grid (period "
                        f"{period * 1e3:.3f} ms, worst deviation {np.max(np.abs(resid)) * 1e3:.3f} "
                        f"ms)")
    t0 = float(t[0] + np.mean(resid))
    return _Grid(t0, period, int(index[-1]) + 1, index)


class _Other:
    """The other-side signal as a cubic spline over time, NaN outside its range and in gaps."""

    def __init__(self, time: np.ndarray, values: np.ndarray, max_gap: float, edge: float,
                 name: str) -> None:
        t = np.asarray(time, dtype=np.float64)
        v = np.asarray(values, dtype=np.float64)
        if len(t) != len(v):
            raise SyncError(f"{name}: {len(t)} times but {len(v)} samples")
        ok = np.isfinite(t) & np.all(np.isfinite(v.reshape(len(v), -1)), axis=1)
        t, v = t[ok], v[ok]
        if len(t) < 4:
            raise SyncError(f"{name}: fewer than 4 valid samples")
        if np.any(np.diff(t) <= 0):
            raise SyncError(f"{name}: sample times must be strictly increasing")
        self.name = name
        self.shape = v.shape[1:]
        self.t_first, self.t_last = float(t[0]), float(t[-1])
        self.period = float(np.median(np.diff(t)))
        self.spline = make_interp_spline(t, v.reshape(len(t), -1), k=3)
        self.edge = edge
        gaps = np.flatnonzero(np.diff(t) > max(max_gap, 2.5 * self.period))
        self.gaps = np.column_stack([t[gaps], t[gaps + 1]]) if len(gaps) else np.zeros((0, 2))

    def valid(self, tau: np.ndarray) -> np.ndarray:
        ok = (tau >= self.t_first + self.edge) & (tau <= self.t_last - self.edge)
        for a, b in self.gaps:
            ok &= ~((tau > a - self.edge) & (tau < b + self.edge))
        return ok

    def __call__(self, tau: np.ndarray) -> np.ndarray:
        """(..., *shape) values at ``tau`` (...), NaN where not valid."""
        tau = np.asarray(tau, dtype=np.float64)
        out = self.spline(np.clip(tau, self.t_first, self.t_last).ravel())
        out[~self.valid(tau).ravel()] = np.nan
        return out.reshape(*tau.shape, *self.shape)


def _features(fn: FeatureFn | None, time: np.ndarray, values: np.ndarray, lead: int) -> np.ndarray:
    """Apply ``fn`` and flatten to (..., N, F) with ``lead`` leading batch dims before N
    (float64, or complex128 when the features are complex)."""
    out = np.asarray(values if fn is None else fn(time, values))
    out = out.astype(np.complex128 if np.iscomplexobj(out) else np.float64, copy=False)
    return out.reshape(*out.shape[:lead + 1], -1)


def _complex_channels(f: np.ndarray) -> np.ndarray:
    """(F,) bool: channels with a non-zero imaginary part somewhere (2-D vectors as x + iy)."""
    if not np.iscomplexobj(f):
        return np.zeros(f.shape[-1], dtype=bool)
    im = np.where(np.isfinite(f), f.imag, 0.0)
    return np.any(im.reshape(-1, f.shape[-1]) != 0, axis=0)


def _weighted_affine(y: np.ndarray, x: np.ndarray, w: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per channel, weighted LS of ``y ≈ g·x + h`` over axis 0 (invalid entries have w = 0);
    for complex channels g is complex (a scale and a rotation). Returns (g (F,), h (F,),
    explained variance R² (F,))."""
    sw = w.sum(axis=0)
    sw = np.where(sw > 0, sw, 1.0)
    mx = (w * x).sum(axis=0) / sw
    my = (w * y).sum(axis=0) / sw
    dx, dy = x - mx, y - my
    sxx = (w * np.abs(dx) ** 2).sum(axis=0)
    syy = (w * np.abs(dy) ** 2).sum(axis=0)
    sxy = (w * np.conj(dx) * dy).sum(axis=0)
    ok = sxx > 0
    g = np.where(ok, sxy / np.where(ok, sxx, 1.0), 0.0)
    h = my - g * mx
    both = ok & (syy > 0)
    r2 = np.where(both, np.abs(sxy) ** 2 / np.where(both, sxx * syy, 1.0), 0.0)
    return g, h, r2


def _as_real(r: np.ndarray, is_c: np.ndarray) -> np.ndarray:
    """(N, F) residuals → (N, F + n_complex) real: real parts, then the complex channels'
    imaginary parts."""
    if not np.iscomplexobj(r):
        return r
    return np.concatenate([r.real, r.imag[:, is_c]], axis=1)


# --------------------------------------------------------------------------- coarse


def _fftconvolve(a: np.ndarray, b: np.ndarray, **kwargs: object) -> np.ndarray:
    """``scipy.signal.fftconvolve``, imported at its first use: scipy.signal costs 0.4 s with
    the scipy.stats it imports, which the pool's workers (they import this module) never need."""
    from scipy.signal import fftconvolve

    return fftconvolve(a, b, **kwargs)


def _masked_ncc(x: np.ndarray, mx: np.ndarray, y: np.ndarray, my: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Normalised cross-correlation of x (N,F) against y (M,F) at every integer lag L
    (pairs x[k], y[k + L]), masked; complex channels correlate as ``Σ conj(x) y``. Returns
    (rho (N+M-1, F), real or complex, pair count (N+M-1,)); lag of row i is i - (N - 1)."""
    xm, ym = np.where(mx[:, None], x, 0.0), np.where(my[:, None], y, 0.0)
    fx, fy = mx.astype(np.float64)[:, None], my.astype(np.float64)[:, None]

    def corr(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # sum_k a[k] b[k+L]
        return _fftconvolve(b, a[::-1], axes=0, mode="full")

    n = np.round(corr(fx, fy)[:, 0].real)
    sx = corr(np.conj(xm), fy)
    sy = corr(fx, ym)
    sxx = corr(np.abs(xm) ** 2, fy).real
    syy = corr(fx, np.abs(ym) ** 2).real
    sxy = corr(np.conj(xm), ym)
    nn = n[:, None]
    vx = nn * sxx - np.abs(sx) ** 2
    vy = nn * syy - np.abs(sy) ** 2
    cov = nn * sxy - sx * sy
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = cov / np.sqrt(np.clip(vx, 0, None) * np.clip(vy, 0, None))
    rho[~np.isfinite(rho)] = 0.0
    return rho, n


def coarse_offset(grid_time: np.ndarray, kinect_features: np.ndarray, other: _Other,
                  features: FeatureFn | None, *, drift_ppm: float = 0.0,
                  window: tuple[float, float] | None = None, config: ClockSyncConfig,
                  names: tuple[str, str]) -> tuple[float, float, float]:
    """Coarse offset (drift fixed): returns (offset_s, score at the peak, peak ratio).

    The score of an offset is the mean over channels of max(ρ, 0)², ρ the Pearson correlation
    of the two features over the frames they share; the peak ratio is the best rival's
    unexplained variance over the peak's (see :attr:`ClockEstimate.peak_ratio`).

    ``grid_time`` (N,) is the uniform Kinect frame grid, ``kinect_features`` (N, F) its features
    (NaN: missing). The other signal is sampled on the same grid spacing (scaled by the drift)
    at ``config.phases`` sub-frame phases, transformed with ``features``, and cross-correlated.
    ``window`` limits the offsets searched (s, the other clock's reading at Kinect time 0).
    """
    period = float(grid_time[1] - grid_time[0])
    scale = 1.0 + drift_ppm * 1e-6
    mk = np.all(np.isfinite(kinect_features), axis=1)
    kin = np.where(mk[:, None], kinect_features, 0.0)
    is_c = _complex_channels(kinect_features)
    kinect_span = grid_time[-1] - grid_time[0]
    other_span = other.t_last - other.t_first
    need = max(config.min_overlap_s,
               config.min_overlap_fraction * min(kinect_span, other_span / scale))
    m = int(np.floor(other_span / (scale * period))) + 1
    sub = np.arange(config.phases) / config.phases
    # other samples on the Kinect spacing, one row per phase: tau = first + (j + phase)·P·scale
    tau = other.t_first + (np.arange(m)[None, :] + sub[:, None]) * period * scale
    # every phase row has the same spacing: the transform gets the first row's times
    feats = _features(features, tau[0] / scale, other(tau), lead=1)  # (phases, M, F)
    best = (-np.inf, 0.0)
    scores, offsets = [], []
    overlapping = False
    for p in range(config.phases):
        my = np.all(np.isfinite(feats[p]), axis=1)
        rho, n = _masked_ncc(kin, mk, np.where(my[:, None], feats[p], 0.0), my)
        # channels weighted equally; a real channel counts only when positively correlated,
        # a complex one (a 2-D vector) in any direction (its frames may differ by a rotation)
        score = np.mean(np.where(is_c, np.abs(rho), np.clip(rho.real, 0.0, None)) ** 2, axis=1)
        lags = np.arange(len(n)) - (len(kin) - 1)
        # kinect row k ↔ other sample j = k + lag: tau_j = scale·t_k + offset
        off = tau[p, 0] + lags * period * scale - scale * grid_time[0]
        # the recordings (not only their usable frames) must overlap by `need` seconds
        lo = np.maximum(grid_time[0], (other.t_first - off) / scale)
        hi = np.minimum(grid_time[-1], (other.t_last - off) / scale)
        allowed = hi - lo >= need - 1e-9
        if window is not None:
            allowed &= (off >= window[0]) & (off <= window[1])
        overlapping |= bool(allowed.any())
        allowed &= n >= config.min_pairs
        score[~allowed] = -np.inf
        scores.append(score)
        offsets.append(off)
        i = int(np.argmax(score))
        if score[i] > best[0]:
            best = (float(score[i]), float(off[i]))
    if not np.isfinite(best[0]):
        where = ("" if window is None else
                 f" within the offset window {window[0]:+.3f}..{window[1]:+.3f} s")
        spans = (f"(Kinect {grid_time[0]:.3f}..{grid_time[-1]:.3f} s, {names[1]} "
                 f"{other.t_first:.3f}..{other.t_last:.3f} s on its clock)")
        if not overlapping:
            raise SyncError(f"{names[0]} and {names[1]} do not overlap{where} by at least "
                            f"{need:.1f} s {spans}")
        raise SyncError(f"{names[0]} and {names[1]}: fewer than {config.min_pairs} frames "
                        f"with the signal on both sides at any offset{where} {spans}; "
                        f"{int(mk.sum())} Kinect frames have it")
    all_s, all_o = np.concatenate(scores), np.concatenate(offsets)
    order = np.argsort(all_o)
    all_s, all_o = all_s[order], all_o[order]
    # sub-step refinement: parabola through the best and its neighbours on the merged grid
    i = int(np.argmax(all_s))
    off = all_o[i]
    if 0 < i < len(all_s) - 1 and np.all(np.isfinite(all_s[i - 1:i + 2])):
        a, b, c = all_s[i - 1:i + 2]
        den = a - 2 * b + c
        if den < 0:
            off += 0.5 * (a - c) / den * (all_o[i + 1] - all_o[i - 1]) / 2
    # distinctness: unexplained variance of the best rival (> rival_s away) over the peak's
    rival = all_s[np.abs(all_o - best[1]) > config.rival_s]
    rival = rival[np.isfinite(rival)]
    ratio = (float((1.0 - rival.max()) / max(1.0 - best[0], 1e-12)) if len(rival)
             else math.inf)
    return float(off), best[0], ratio


# --------------------------------------------------------------------------- fine


def _correlation_time(r: np.ndarray) -> float:
    """1 + 2·Σ autocorrelation (in samples) of residuals r (N,F), over positive lags until the
    first negative one: how many samples one independent sample is worth."""
    factors = []
    for c in range(r.shape[1]):
        x = r[:, c] - r[:, c].mean()
        v = float(x @ x)
        if v <= 0 or len(x) < 8:
            continue
        ac = _fftconvolve(x, x[::-1], mode="full")[len(x) - 1:] / v
        neg = np.flatnonzero(ac < 0)
        stop = int(neg[0]) if len(neg) else len(ac)
        factors.append(1.0 + 2.0 * float(ac[1:stop].sum()))
    return max(1.0, float(np.median(factors))) if factors else 1.0


def _prepare(kinect_time: np.ndarray, kinect_features: np.ndarray,
             weights: np.ndarray | None, other_time: np.ndarray, other_values: np.ndarray,
             cfg: ClockSyncConfig, names: tuple[str, str]
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, _Other]:
    """The Kinect features on their full frame grid (NaN rows where no frame), weights, and
    the other signal's spline."""
    kf = np.asarray(kinect_features)
    kf = kf.astype(np.complex128 if np.iscomplexobj(kf) else np.float64, copy=False)
    if kf.ndim == 1:
        kf = kf[:, None]
    kf = kf.reshape(len(kf), -1)
    grid = _uniform_grid(np.asarray(kinect_time, dtype=np.float64), names[0])
    if len(kf) != len(grid.index):
        raise SyncError(f"{names[0]}: {len(grid.index)} frame times but {len(kf)} feature rows")
    full = np.full((grid.n, kf.shape[1]), np.nan, dtype=kf.dtype)
    full[grid.index] = kf
    w_full = np.zeros(grid.n)
    w_full[grid.index] = 1.0 if weights is None else np.asarray(weights, dtype=np.float64)
    full[~(w_full > 0)] = np.nan
    other = _Other(other_time, other_values, cfg.max_gap_s, cfg.edge_s, names[1])
    return grid.time, full, w_full, other


def refine_clock(kinect_time: np.ndarray, kinect_features: np.ndarray, other_time: np.ndarray,
                 other_values: np.ndarray, initial: ClockModel, *,
                 features: FeatureFn | None = None, weights: np.ndarray | None = None,
                 config: ClockSyncConfig | None = None,
                 names: tuple[str, str] = ("Kinect", "IMU")) -> ClockEstimate:
    """Fine stage: weighted robust least squares on offset and drift from ``initial``.

    Args:
        kinect_time: (N,) Kinect master-clock seconds of the frames (a regular frame grid, gaps
            allowed).
        kinect_features: (N, F) (or (N,)) Kinect-side features per frame, NaN where missing:
            ``features(kinect_time_grid, kinect_values)`` or an equivalent estimate of them
            (e.g. per-camera velocities averaged over cameras).
        other_time: (M,) other-clock seconds, strictly increasing.
        other_values: (M, ...) the other side's raw quantity (e.g. (M, 3) head top, (M, 24, 3)
            joints), interpolated (cubic spline) at the mapped Kinect frame times.
        initial: starting clock (from :func:`estimate_clock`'s coarse stage or an earlier fit);
            it must be within a fraction of the signal's correlation time of the truth.
        features: ``features(t, values)`` turning other values sampled on the Kinect frame grid
            ``t`` (N_grid,) into (N_grid, F) features, the same transform that made
            ``kinect_features`` (see :data:`FeatureFn`); None: the values are the features.
        weights: (N,) per-frame weights (0 = unused), e.g. how many cameras saw the frame.
        config: knobs.
        names: how the two streams are named in messages.

    Returns:
        :class:`ClockEstimate` (drift uncertainty NaN when ``config.fit_drift`` is False).

    Raises:
        SyncError: no overlap at ``initial``, no motion in the overlap, malformed times.
    """
    cfg = config or ClockSyncConfig()
    t, fk, w_full, other = _prepare(kinect_time, kinect_features, weights, other_time,
                                    other_values, cfg, names)
    return _fine(t, fk, w_full, other, features, initial, cfg, names, None)


def _fine(t: np.ndarray, fk: np.ndarray, w_full: np.ndarray, other: _Other,
          features: FeatureFn | None, initial: ClockModel, cfg: ClockSyncConfig,
          names: tuple[str, str], coarse: tuple[float, float] | None) -> ClockEstimate:
    warnings: list[str] = []
    ok_k = np.all(np.isfinite(fk), axis=1) & (w_full > 0)
    # the frames used: valid on both sides at the initial clock (kept fixed during the fit,
    # so that the objective does not jump as frames enter and leave the overlap)
    fo0 = _features(features, t, other(initial.to_other(t)), lead=0)
    use = ok_k & np.all(np.isfinite(fo0), axis=1)
    if use.sum() < 8:
        raise SyncError(f"{names[0]} and {names[1]} share only {int(use.sum())} usable frames "
                        f"at offset {initial.offset_s:+.3f} s, drift {initial.drift_ppm:+.1f} "
                        f"ppm ({names[1]} covers {other.t_first:.3f}..{other.t_last:.3f} s on "
                        f"its clock = Kinect {float(initial.to_kinect(other.t_first)):.3f}.."
                        f"{float(initial.to_kinect(other.t_last)):.3f} s; Kinect frames "
                        f"{t[0]:.3f}..{t[-1]:.3f} s)")
    is_c = _complex_channels(fk)
    y = fk[use]
    w = w_full[use][:, None] * np.ones(y.shape)
    sd = np.sqrt((w * np.abs(y - (w * y).sum(0) / w.sum(0)) ** 2).sum(0) / w.sum(0))
    flat = sd < cfg.min_motion
    if flat.all():
        raise SyncError(f"{names[0]}: no motion to synchronise on in the {int(use.sum())} "
                        f"frames that overlap {names[1]} (feature std "
                        f"{', '.join(f'{s:.2g}' for s in sd)} < {cfg.min_motion:g})")
    if flat.any():
        warnings.append(f"{int(flat.sum())} of {len(sd)} feature channels are flat")
    keep = ~flat
    y, w, sd, is_c = y[:, keep], w[:, keep], sd[keep], is_c[keep]
    tu = t[use]
    wt = w_full[use]
    t_ref = float((wt * tu).sum() / wt.sum())
    off_ref0 = float(initial.to_other(t_ref))
    drift0 = initial.drift_ppm
    use_idx = np.flatnonzero(use)

    # parameters p = [offset at t_ref (ms) - initial, drift (ppm)]: similar magnitudes
    def other_features(p: np.ndarray) -> np.ndarray:
        tau = off_ref0 + 1e-3 * p[0] + (1.0 + p[1] * 1e-6) * (t - t_ref)
        # the transform sees the full grid so that it treats both sides identically
        return _features(features, t, other(tau), lead=0)[use_idx][:, keep]

    sqrt_w = np.sqrt(w)

    def residual_matrix(p: np.ndarray, scale: np.ndarray) -> np.ndarray:
        x = other_features(p)
        bad = ~np.isfinite(x)
        x = np.where(bad, 0.0, x)
        g, h, _ = _weighted_affine(y, x, np.where(bad, 0.0, w))
        return _as_real((y - g * x - h) / scale * np.where(bad, 0.0, sqrt_w), is_c)

    def solve(p_start: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, OptimizeResult]:
        def fun(q: np.ndarray) -> np.ndarray:
            full = q if cfg.fit_drift else np.array([q[0], drift0])
            return residual_matrix(full, scale).ravel()

        r_start = fun(p_start if cfg.fit_drift else p_start[:1])
        nz = r_start[r_start != 0]
        f_scale = max(cfg.robust_scale * 1.4826 * float(np.median(np.abs(nz))), 1e-9) \
            if len(nz) else 1.0
        x0, steps = (p_start, [1e-4, 1e-3]) if cfg.fit_drift else (p_start[:1], [1e-4])
        sol = least_squares(fun, x0, loss=cfg.loss, f_scale=f_scale,
                            x_scale=np.array([1.0, 10.0][:len(x0)]), diff_step=np.array(steps),
                            max_nfev=cfg.max_iterations * 3)
        full = sol.x if cfg.fit_drift else np.array([sol.x[0], drift0])
        return full, sol

    # pass 1: channels scaled by their spread; pass 2: by their noise (the robust residual
    # scale of pass 1, per real component), so that each channel counts by its signal/noise
    p, sol = solve(np.array([0.0, drift0]), sd)
    scale = sd
    if cfg.reweight and len(sd) > 1:
        r1 = residual_matrix(p, sd)
        comp = np.concatenate([np.arange(len(sd)), np.flatnonzero(is_c)])  # column's channel
        mad = np.array([np.median(np.abs(c[c != 0])) if np.any(c != 0) else 1.0
                        for c in r1.T])
        noise = np.array([np.mean(mad[comp == k]) for k in range(len(sd))]) * 1.4826
        scale = sd * np.maximum(noise, 1e-6)
        p, sol = solve(p, scale)
    r = residual_matrix(p, scale)
    x = other_features(p)
    bad = ~np.isfinite(x)
    g, h, r2 = _weighted_affine(y, np.where(bad, 0.0, x), np.where(bad, 0.0, w))
    # uncertainty: Gauss-Newton covariance, residual scale, inflated by the residuals'
    # correlation time (neighbouring frames are not independent)
    jac = sol.jac
    dof = max(1, r.size - jac.shape[1] - 2 * r.shape[1])
    sigma2 = float((r * r).sum() / dof)
    try:
        cov_fit = np.linalg.inv(jac.T @ jac) * sigma2 * _correlation_time(r)
    except np.linalg.LinAlgError:
        cov_fit = np.full((jac.shape[1], jac.shape[1]), np.inf)
    cov = np.diag([cov_fit[0, 0], 0.0]) if not cfg.fit_drift else cov_fit
    drift_data, drift_data_std = float(p[1]), math.nan
    if cfg.fit_drift:
        drift_data_std = math.sqrt(max(cov[1, 1], 0.0))
        if cfg.drift_prior_ppm is not None and np.all(np.isfinite(cov)):
            # MAP with a Gaussian prior on the drift around the initial one: the data's
            # Gaussian (p, cov) times N(drift0, prior²), in closed form
            info = np.linalg.inv(cov)
            prior = np.diag([0.0, cfg.drift_prior_ppm ** -2])
            cov = np.linalg.inv(info + prior)
            p = cov @ (info @ p + prior @ np.array([0.0, drift0]))
    offset_ref_std = math.sqrt(max(cov[0, 0], 0.0)) * 1e-3
    drift_std = math.sqrt(max(cov[1, 1], 0.0)) if cfg.fit_drift else math.nan
    drift = float(p[1])
    offset = off_ref0 + 1e-3 * p[0] - (1.0 + drift * 1e-6) * t_ref
    zero_std = offset_ref_std if not cfg.fit_drift else math.sqrt(
        offset_ref_std ** 2 + (t_ref * 1e-6 * drift_std) ** 2)
    correlation = float(np.sum(r2 * sd ** 2) / np.sum(sd ** 2))
    anti = ~is_c & (g.real <= 0)
    if anti.any():
        warnings.append(f"{int(anti.sum())} channel(s) anti-correlated at the solution")
    if correlation < cfg.min_correlation:
        warnings.append(f"weak match: R² {correlation:.2f} < {cfg.min_correlation}")
    peak_ratio = math.nan if coarse is None else coarse[1]
    if coarse is not None and peak_ratio < cfg.min_peak_ratio:
        warnings.append(f"ambiguous coarse match: a rival offset explains nearly as much "
                        f"(unexplained variance ratio {peak_ratio:.2f} < {cfg.min_peak_ratio})")
    if not sol.success:
        warnings.append(f"fine fit did not converge: {sol.message}")
    return ClockEstimate(
        clock=ClockModel(float(offset), drift), reference_time_s=t_ref,
        offset_std_s=offset_ref_std, offset_at_zero_std_s=zero_std, drift_std_ppm=drift_std,
        correlation=correlation, residual_rms=float(np.sqrt(np.mean(r * r))),
        peak_ratio=peak_ratio, coarse_offset_s=None if coarse is None else coarse[0],
        overlap_s=float(tu[-1] - tu[0]), samples=int(use.sum()), channels=int(keep.sum()),
        confident=not warnings, warnings=warnings,
        gains=np.where(is_c, g, g.real) if np.iscomplexobj(g) else g,
        biases=np.where(is_c, h, h.real) if np.iscomplexobj(h) else h,
        drift_data_ppm=drift_data, drift_data_std_ppm=drift_data_std)


def estimate_clock(kinect_time: np.ndarray, kinect_features: np.ndarray,
                   other_time: np.ndarray, other_values: np.ndarray, *,
                   features: FeatureFn | None = None, weights: np.ndarray | None = None,
                   initial: ClockModel | None = None, search_s: float | None = None,
                   config: ClockSyncConfig | None = None,
                   names: tuple[str, str] = ("Kinect", "IMU")) -> ClockEstimate:
    """Coarse cross-correlation, then the fine least squares of :func:`refine_clock`.

    Args:
        kinect_time, kinect_features, other_time, other_values, features, weights: see
            :func:`refine_clock`.
        initial: a prior clock; with ``search_s`` the coarse search covers offsets within
            ± ``search_s`` of it, otherwise every offset at which the recordings overlap enough
            (its drift is kept during the coarse stage; default 0 ppm).
        search_s: half-width (s) of the coarse search window around ``initial``.
        config: knobs.
        names: how the two streams are named in messages.

    Raises:
        SyncError: the recordings cannot overlap (within the window) by
            ``config.min_overlap_s``; no motion; malformed times.
    """
    cfg = config or ClockSyncConfig()
    t, fk, w_full, other = _prepare(kinect_time, kinect_features, weights, other_time,
                                    other_values, cfg, names)
    drift0 = 0.0 if initial is None else initial.drift_ppm
    window = None
    if search_s is not None:
        if initial is None:
            raise ValueError("search_s needs an initial clock to search around")
        window = (initial.offset_s - search_s, initial.offset_s + search_s)
    good = np.all(np.isfinite(fk), axis=1)
    if good.sum() < 8:
        raise SyncError(f"{names[0]}: only {int(good.sum())} frames with usable features")
    sd = np.sqrt(np.mean(np.abs(fk[good] - fk[good].mean(axis=0)) ** 2, axis=0))
    if np.all(sd < cfg.min_motion):
        raise SyncError(f"{names[0]}: no motion to synchronise on (feature std "
                        f"{', '.join(f'{s:.2g}' for s in sd)} < {cfg.min_motion:g})")
    off, score, ratio = coarse_offset(t, fk, other, features, drift_ppm=drift0, window=window,
                                      config=cfg, names=names)
    log.debug("coarse offset %.4f s (score %.3f, ratio %.2f)", off, score, ratio)
    return _fine(t, fk, w_full, other, features, ClockModel(off, drift0), cfg, names,
                 (off, ratio))
