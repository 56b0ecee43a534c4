"""Every camera's frames on the Kinect master clock: device clock offsets and the frame table.

The cameras of a rig are hardware-synchronised (wired sync, one MASTER): every device captures
at the same instants, but each stamps its frames with its **own** clock (device timestamps in µs,
started at its own power-up), and any device may drop frames, the first one included.

What the timestamps give (:func:`sync_kinect`):

1. the frame period, common to all devices (joint least squares ``s_ij = c_i + P·n_ij`` over every
   device's frames, ``n_ij`` the frame number counted from the device's first frame, so gaps of
   dropped frames are whole multiples of P; jitter of tens of µs averages out);
2. each device's clock phase ``c_i``, hence its offset from the master **up to whole frames**:
   ``offset_i = c_i - c_master - d_i·P`` with ``d_i`` the number of frames by which the device's
   first recorded frame follows the master's first recorded frame.

What they cannot give is ``d_i``: the device clocks are unrelated (offsets of seconds), so a
device that dropped its first frame(s) looks exactly like one whose clock is a frame later.
``d_i = 0`` (the recordings start at the same sync pulse) is the prior; the **content** decides:
the top of the person (:mod:`couch.sync.signals`, world coordinates, nearly view-independent) of
each device is compared with the master's at every shift within ``max_shift`` frames, and the
shift with the smallest robust mismatch wins when its log-likelihood ratio over the runner-up
is large (the person moved enough). Without motion (or without content) the prior stands and
the device is flagged ``ambiguous``.

The result, :class:`KinectSync`, has one row per capture instant seen by any device: the master
clock time of the row and, per device, the index of its frame there (-1 where it dropped it).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence

import numpy as np

from couch.sync.clock import SyncError
from couch.sync.signals import CameraTrack

__all__ = ["KinectSync", "KinectSyncConfig", "sync_kinect", "sync_tracks"]

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class KinectSyncConfig:
    """Knobs of :func:`sync_kinect`."""

    max_shift: int = 15  # whole frames tried either way for a device's first frame
    max_jitter_fraction: float = 0.2  # timestamp residual (of P) beyond which it is not synced
    min_common: int = 5  # frames with content on both devices needed to judge a shift
    min_evidence: float = 7.0  # log-likelihood ratio (nats) best vs runner-up shift to trust it
    noise_m: float = 0.005  # content noise (m): less motion per frame is "still"; cost floor


@dataclasses.dataclass
class KinectSync:
    """All cameras on the Kinect master clock. T rows (capture instants), C cameras.

    Attributes:
        serials: (C,) device serials; ``serials[master]`` is the sync master.
        sources: (C,) the recordings read, for messages.
        master: index of the master device (its clock is the Kinect clock).
        period_s: frame period (s) on the master clock (fitted, ~1/fps).
        time: (T,) float64 master-clock seconds of each row (``t0 + row·period_s``).
        frame_table: (T, C) int64 index of each device's frame at that row (its position in
            the device's frame list / :attr:`CameraTrack.timestamp_us`), -1 where the device
            has no frame (dropped, or before its first / after its last frame).
        device_offset_s: (C,) float64 device clock minus master clock (s):
            ``device_timestamp = master_time + offset + exposure delay``; 0 for the master.
        exposure_delay_s: (C,) float64 depth exposure delay after the master's (subordinate
            delay), so device c's frame at row r was exposed at ``time[r] + exposure_delay_s[c]``.
        first_row: (C,) int64 row of each device's first frame.
        shift_evidence: (C,) float64 log-likelihood ratio (nats) of the best whole-frame shift
            over the runner-up, from the content (inf for the master; NaN: no content).
        ambiguous: (C,) bool, the whole-frame shift rests on the equal-start prior only.
        timestamp_rms_us: (C,) float64 RMS of each device's timestamps about the fitted grid.
        warnings: what may be wrong (ambiguous shifts, large jitter).
    """

    serials: list[str]
    sources: list[str]
    master: int
    period_s: float
    time: np.ndarray
    frame_table: np.ndarray
    device_offset_s: np.ndarray
    exposure_delay_s: np.ndarray
    first_row: np.ndarray
    shift_evidence: np.ndarray
    ambiguous: np.ndarray
    timestamp_rms_us: np.ndarray
    warnings: list[str]

    @property
    def n_rows(self) -> int:
        return len(self.time)

    @property
    def present(self) -> np.ndarray:
        """(T, C) bool: the device has a frame at the row."""
        return self.frame_table >= 0

    def dropped_rows(self, camera: int) -> np.ndarray:
        """Rows within camera ``camera``'s recording (first to last frame) where it has no
        frame."""
        col = self.frame_table[:, camera]
        have = np.flatnonzero(col >= 0)
        if not len(have):
            return np.zeros(0, dtype=np.int64)
        inside = np.arange(have[0], have[-1] + 1)
        return inside[col[inside] < 0]

    def frame_times(self, camera: int) -> np.ndarray:
        """(N_c,) master-clock seconds of camera ``camera``'s frames, in its frame order."""
        col = self.frame_table[:, camera]
        rows = np.flatnonzero(col >= 0)
        out = np.empty(int(col.max()) + 1 if len(rows) else 0)
        out[col[rows]] = self.time[rows] + self.exposure_delay_s[camera]
        return out

    def gather(self, values: Sequence[np.ndarray]) -> np.ndarray:
        """(T, C, ...) per-row values from per-camera per-frame arrays ``values[c]`` (N_c, ...),
        NaN where a camera has no frame (float output)."""
        shape = np.asarray(values[0]).shape[1:]
        out = np.full((self.n_rows, len(values), *shape), np.nan)
        for c, v in enumerate(values):
            col = self.frame_table[:, c]
            rows = np.flatnonzero(col >= 0)
            out[rows, c] = np.asarray(v, dtype=np.float64)[col[rows]]
        return out

    def summary(self) -> str:
        """A few lines for logs and reports."""
        lines = [f"{len(self.serials)} cameras, {self.n_rows} frames at "
                 f"{1.0 / self.period_s:.3f} fps, master {self.serials[self.master]}"]
        for c, s in enumerate(self.serials):
            lines.append(f"  {s}: offset {self.device_offset_s[c]:+.6f} s, first row "
                         f"{self.first_row[c]}, {len(self.dropped_rows(c))} dropped, evidence "
                         f"{self.shift_evidence[c]:.3g}{' AMBIGUOUS' if self.ambiguous[c] else ''}")
        return "\n".join(lines + [f"  warning: {w}" for w in self.warnings])


def _frame_numbers(stamps_us: np.ndarray, period_us: float, name: str) -> np.ndarray:
    """Frame numbers counted from the device's first frame; raises on disorder."""
    s = np.asarray(stamps_us, dtype=np.int64)
    if len(s) == 0:
        raise SyncError(f"{name}: no frames")
    d = np.diff(s)
    if np.any(d <= 0):
        k = int(np.argmax(d <= 0))
        raise SyncError(f"{name}: timestamps not strictly increasing at frame {k + 1} "
                        f"({s[k]} µs then {s[k + 1]} µs)")
    n = np.round((s - s[0]) / period_us).astype(np.int64)
    if np.any(np.diff(n) <= 0):
        k = int(np.argmax(np.diff(n) <= 0))
        raise SyncError(f"{name}: frames {k} and {k + 1} are {d[k]} µs apart, less than a frame "
                        f"period ({period_us:.0f} µs): not a {1e6 / period_us:.3g} fps stream")
    return n


def _fit_grid(numbers: list[np.ndarray], stamps: list[np.ndarray]
              ) -> tuple[float, np.ndarray, list[np.ndarray]]:
    """Common period P (µs) and per-device phase c_i (µs) of s_ij = c_i + P·n_ij; residuals."""
    num = den = 0.0
    for n, s in zip(numbers, stamps, strict=True):
        dn = n - n.mean()
        num += float(dn @ (s - s.mean()))
        den += float(dn @ dn)
    if den <= 0:
        raise SyncError("need at least two frames from one device to measure the frame period")
    period = num / den
    phases = np.array([float((s - period * n).mean()) for n, s in zip(numbers, stamps,
                                                                      strict=True)])
    resid = [s - c - period * n for n, s, c in zip(numbers, stamps, phases, strict=True)]
    return period, phases, resid


def _shift_costs(ref_num: np.ndarray, ref_val: np.ndarray, num: np.ndarray, val: np.ndarray,
                 max_shift: int, min_common: int, noise: float,
                 bias_axes: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mismatch of ``val`` (device frames numbered ``num``) against ``ref_val`` (reference
    frames ``ref_num``) when the device's frame n is the reference's frame n + d, for
    d = -max_shift..max_shift.

    Only reference frames where the content moves by more than ``noise`` per frame count: a
    still person matches at every shift and says nothing about it. A constant offset between
    the two signals along ``bias_axes`` (default: all; the median difference) is removed
    first.

    Returns:
        costs: (2·max_shift+1,) robust mean squared mismatch (m², plus noise²); NaN with fewer
            than ``min_common`` frames.
        n_eff: (2·max_shift+1,) effective number of independent frames behind each cost
            (AR(1) correction for mismatches correlated from frame to frame).
    """
    axes = list(range(ref_val.shape[1])) if bias_axes is None else list(bias_axes)
    ok_r = np.all(np.isfinite(ref_val), axis=1)
    ok_d = np.all(np.isfinite(val), axis=1)
    size = int(max(ref_num.max(initial=0), num.max(initial=0))) + 2 * max_shift + 3
    ref = np.full((size, ref_val.shape[1]), np.nan)
    ref[ref_num[ok_r]] = ref_val[ok_r]
    # motion of the reference at each frame number: half the central difference
    motion = np.full(size, np.nan)
    motion[1:-1] = 0.5 * np.linalg.norm(ref[2:] - ref[:-2], axis=1)
    costs = np.full(2 * max_shift + 1, np.nan)
    n_eff = np.zeros(2 * max_shift + 1)
    for k, d in enumerate(range(-max_shift, max_shift + 1)):
        target = num[ok_d] + d
        inside = (target >= 0) & (target < size)
        target, v = target[inside], val[ok_d][inside]
        moving = (motion[target] > noise) & np.isfinite(ref[target, 0])  # NaN: False
        if moving.sum() < min_common:
            continue
        delta = v[moving] - ref[target[moving]]
        # e.g. each camera sees the top of the head from its side: a horizontal bias of
        # several cm towards it, nearly constant; then a trimmed mean of the squared rest
        if axes:
            delta[:, axes] -= np.median(delta[:, axes], axis=0)
        sq = np.sum(delta ** 2, axis=1)
        costs[k] = float(np.mean(np.sort(sq)[: max(min_common, math.ceil(0.8 * len(sq)))]))
        costs[k] += noise ** 2
        # lag-1 autocorrelation of the signed mismatch (frames in order), per axis
        x = delta - delta.mean(axis=0)
        den = float(np.sum(x * x))
        rho = float(np.sum(x[1:] * x[:-1]) / den) if len(x) > 2 and den > 0 else 0.0
        rho = min(max(rho, 0.0), 0.95)
        n_eff[k] = len(sq) * (1.0 - rho) / (1.0 + rho)
    return costs, n_eff


def sync_kinect(timestamps_us: Sequence[np.ndarray], *, serials: Sequence[str] | None = None,
                sources: Sequence[str] | None = None, master: int = 0,
                fps: float | None = None, content: Sequence[np.ndarray | None] | None = None,
                exposure_delay_us: Sequence[float] | None = None,
                content_bias_axes: Sequence[int] | None = None,
                config: KinectSyncConfig | None = None) -> KinectSync:
    """Put hardware-synchronised cameras on the master clock.

    Args:
        timestamps_us: per device (N_c,) int device timestamps (µs) of its frames, in order.
        serials, sources: per device names for the result and messages.
        master: index of the sync master (its clock becomes the Kinect clock).
        fps: nominal frame rate (default: from the median timestamp step).
        content: per device (N_c, D) float per-frame signal in a common frame (e.g. the top of
            the person in world metres, NaN: none) used to settle whole-frame shifts; None: the
            equal-start prior only.
        exposure_delay_us: per device exposure delay after the master (subordinate delay).
        content_bias_axes: content axes along which a device may see the content with a
            constant offset (removed before comparing; default: all). Axes without a bias
            separate a whole-frame shift from an offset even during uniform motion.
        config: knobs.

    Returns:
        :class:`KinectSync`.

    Raises:
        SyncError: timestamps out of order or closer than a frame; devices not sharing a frame
            grid (not hardware-synchronised, or different frame rates), naming the device.
    """
    cfg = config or KinectSyncConfig()
    ndev = len(timestamps_us)
    if ndev == 0:
        raise SyncError("no cameras to synchronise")
    serials = list(serials) if serials is not None else [f"camera{c}" for c in range(ndev)]
    sources = list(sources) if sources is not None else list(serials)
    stamps = [np.asarray(s, dtype=np.int64) for s in timestamps_us]
    if fps is None:
        steps = np.concatenate([np.diff(s) for s in stamps if len(s) > 1] or [np.zeros(0)])
        if len(steps) == 0:
            raise SyncError(f"{', '.join(sources)}: too few frames to measure a frame rate")
        nominal = float(np.median(steps))
    else:
        nominal = 1e6 / fps
    numbers = [_frame_numbers(s, nominal, src) for s, src in zip(stamps, sources, strict=True)]
    period, phases, resid = _fit_grid(numbers, [s.astype(np.float64) for s in stamps])
    # re-number with the fitted period (long recordings) and refit
    numbers = [_frame_numbers(s, period, src) for s, src in zip(stamps, sources, strict=True)]
    period, phases, resid = _fit_grid(numbers, [s.astype(np.float64) for s in stamps])
    rms = np.array([float(np.sqrt(np.mean(r ** 2))) for r in resid])
    worst = [float(np.max(np.abs(r))) for r in resid]
    for c in range(ndev):
        if worst[c] > cfg.max_jitter_fraction * period:
            raise SyncError(f"{sources[c]}: frame times deviate from the rig's common "
                            f"{1e6 / period:.4f} fps grid by up to {worst[c] / 1e3:.3f} ms "
                            f"(RMS {rms[c] / 1e3:.3f} ms): the camera is not hardware-"
                            f"synchronised with the others, or runs at another rate")
    # whole-frame shifts of each device's first frame against the master's
    shifts = np.zeros(ndev, dtype=np.int64)
    evidence = np.full(ndev, np.nan)
    ambiguous = np.zeros(ndev, dtype=bool)
    evidence[master] = math.inf
    warnings: list[str] = []
    for c in range(ndev):
        if c == master:
            continue
        costs = n_eff = None
        if content is not None and content[c] is not None and content[master] is not None:
            costs, n_eff = _shift_costs(numbers[master], np.asarray(content[master], float),
                                        numbers[c], np.asarray(content[c], float),
                                        cfg.max_shift, cfg.min_common, cfg.noise_m,
                                        content_bias_axes)
        if costs is None or n_eff is None or np.all(np.isnan(costs)):
            ambiguous[c] = True
            warnings.append(f"{sources[c]}: no content to confirm which master frame its first "
                            f"frame is; assumed the recordings started together")
            continue
        order = np.argsort(np.where(np.isnan(costs), np.inf, costs))
        best = int(order[0])
        runner = costs[order[1]]
        # log-likelihood ratio (nats) of the best shift over the runner-up, Gaussian mismatch
        # (NaN when no other shift could be judged: that is no evidence either)
        evidence[c] = (float(0.5 * n_eff[best] * np.log(runner / costs[best]))
                       if np.isfinite(runner) else math.nan)
        if np.isfinite(evidence[c]) and evidence[c] >= cfg.min_evidence:
            shifts[c] = best - cfg.max_shift
        else:
            ambiguous[c] = True
            warnings.append(f"{sources[c]}: the content does not settle the whole-frame shift "
                            f"(best {best - cfg.max_shift:+d} frames, evidence "
                            f"{evidence[c]:.2f} < {cfg.min_evidence}); assumed the recordings "
                            f"started together")
    # rows: the device's frame n is at row first_row + n
    first = shifts - shifts.min()
    rows = [first[c] + numbers[c] for c in range(ndev)]
    n_rows = int(max(r[-1] for r in rows)) + 1
    table = np.full((n_rows, ndev), -1, dtype=np.int64)
    for c in range(ndev):
        table[rows[c], c] = np.arange(len(rows[c]))
    delays = np.zeros(ndev) if exposure_delay_us is None else np.asarray(exposure_delay_us,
                                                                          float)
    delays = delays - delays[master]
    # master clock: row r at c_master + (r - first_master)·P (µs)
    t0_us = phases[master] - first[master] * period
    offsets_us = phases - phases[master] - (first - first[master]) * period - delays
    return KinectSync(
        serials=serials, sources=sources, master=master, period_s=period * 1e-6,
        time=(t0_us + period * np.arange(n_rows)) * 1e-6, frame_table=table,
        device_offset_s=offsets_us * 1e-6, exposure_delay_s=delays * 1e-6,
        first_row=first.astype(np.int64), shift_evidence=evidence, ambiguous=ambiguous,
        timestamp_rms_us=rms, warnings=warnings)


def sync_tracks(tracks: Sequence[CameraTrack], *, config: KinectSyncConfig | None = None
                ) -> KinectSync:
    """:func:`sync_kinect` on per-camera :class:`~couch.sync.signals.CameraTrack` s (the top of
    the person as content: each camera sees it biased horizontally towards itself by up to the
    head's radius, but at the same height); the master is the track whose ``sync_mode`` is
    MASTER, else the first.

    Raises:
        SyncError: see :func:`sync_kinect`; cameras with different nominal frame rates.
    """
    if not tracks:
        raise SyncError("no camera tracks to synchronise")
    rates = {t.fps for t in tracks}
    if len(rates) > 1:
        raise SyncError("cameras record at different frame rates: " + ", ".join(
            f"{t.source} {t.fps:g} fps" for t in tracks))
    masters = [i for i, t in enumerate(tracks) if t.sync_mode.upper() == "MASTER"]
    if len(masters) > 1:
        raise SyncError("more than one sync MASTER: " + ", ".join(tracks[i].source
                                                                   for i in masters))
    return sync_kinect([t.timestamp_us for t in tracks], serials=[t.serial for t in tracks],
                       sources=[t.source for t in tracks], master=masters[0] if masters else 0,
                       fps=tracks[0].fps, content=[t.top for t in tracks],
                       exposure_delay_us=[t.exposure_delay_us for t in tracks],
                       content_bias_axes=(0, 2), config=config)
