"""QA report of one pipeline run: ``summary.json``, plots, previews and an ``index.html``.

:func:`write_report` turns a :class:`~couch.fitting.pipeline.PipelineResult` (a finished or a
failed run) into a folder a person can open in a browser::

    index.html            the page (inline CSS, relative links, no JavaScript, no network)
    summary.json          the numbers (strict JSON: NaN/inf are written as null)
    sync.png              the cameras' and the suit's head-top height (IMU clock sync)
    fit_error.png         per-frame chamfer, reliability and person points
    contacts.png          contact timeline and interaction labels
    chair.png             the chair's per-frame pose deviation and ICP fitness
    previews/frame_XXXX.png   every camera's image with the body and the chair rendered over it

Only the parts whose stage ran are made. Every file is written atomically
(:func:`couch.atomic.atomic_path`), the HTML last.
"""

from __future__ import annotations

import html
import itertools
import json
import math
import os
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import cv2
import matplotlib
import numpy as np
import torch
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from tqdm.auto import tqdm

from couch.atomic import atomic_path
from couch.capture.azure_mkv import KinectCapture, decode_color, open_azure_mkv
from couch.capture.session import session_files
from couch.fitting.body import cached_model
from couch.fitting.chair import ChairRegistration, rotation_angle_deg
from couch.fitting.contacts import FEET, Contacts
from couch.fitting.pipeline import BodyResult, PipelineResult
from couch.fitting.session import SessionFitConfig
from couch.runs import runs
from couch.schema import INTERACTION_LABELS
from couch.tools.render import Mesh, render

# Headless: figures are made with matplotlib.figure.Figure (no pyplot figure registry), PNG via Agg.
matplotlib.use("Agg")

__all__ = ["build_summary", "plot_chair", "plot_contacts", "plot_fit_error", "plot_sync",
           "preview_frames", "render_html", "write_previews", "write_report"]

PLOTS: tuple[str, ...] = ("sync.png", "fit_error.png", "contacts.png", "chair.png")
BODY_COLOR = (0.15, 0.55, 1.0)
CHAIR_COLOR = (1.0, 0.55, 0.1)
ALPHA = 0.5
LABEL_COLORS: dict[int, str] = {0: "#9e9e9e", 1: "#e53935", 2: "#1e88e5", 3: "#8e24aa",
                                4: "#43a047", 5: "#fdd835"}
TILE_NOTE_SIZE = (640, 360)  # (width, height) of a tile that only carries a note


# --------------------------------------------------------------------------- JSON helpers


def _clean(value: Any) -> Any:
    """``value`` as strict-JSON-able Python: numpy → Python, NaN/inf → None, paths → str."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, os.PathLike):
        return str(value)
    return value


def _nan_stat(values: np.ndarray, fn: Any, scale: float = 1.0) -> float | None:
    """``fn`` (np.nanmean / np.nanmedian) of the finite values times ``scale``; None if none."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    return float(fn(v) * scale) if v.size else None


# --------------------------------------------------------------------------- summary


def _stages_summary(result: PipelineResult) -> dict[str, Any]:
    return {name: {"status": run.status, "seconds": run.seconds, "steps": dict(run.steps),
                   "error": run.error or None}
            for name, run in result.stages.items()}


def _calibration_summary(result: PipelineResult) -> dict[str, Any] | None:
    cal = result.calibration
    if cal is None:
        return None
    cams = result.extrinsics.cameras if result.extrinsics is not None else {}
    return {
        "cameras": list(cal.cameras),
        "dropped": [{"serial": s, "reason": why} for s, why in cal.dropped],
        "reprojection_mean_px": {s: cams[s].reprojection_mean_px if s in cams else None
                                 for s in cal.cameras},
        "reprojection_max_px": {s: cams[s].reprojection_max_px if s in cams else None
                                for s in cal.cameras},
        "warnings": list(cal.warnings),
    }


def _sync_summary(body: BodyResult | None) -> dict[str, Any] | None:
    if body is None:
        return None
    return {"clock_offset_ms": body.clock_offset_ms, "clock_drift_ppm": body.clock_drift_ppm,
            "clock_offset_std_ms": body.clock_offset_std_ms,
            "clock_correlation": body.clock_correlation,
            "clock_confident": bool(body.clock_confident), "heading_deg": body.heading_deg,
            "alignment_residual_m": body.alignment_residual_m, "summary": body.clock_summary}


def _body_summary(body: BodyResult | None) -> dict[str, Any] | None:
    if body is None:
        return None
    t = len(body.time)
    fitted = np.asarray(body.fitted, bool)
    rel = np.asarray(body.reliability, np.float64)[fitted]
    present = np.asarray(body.cameras_present, bool).reshape(t, -1)
    return {
        "frames": t,
        "fitted_frames": int(np.count_nonzero(fitted)),  # the cameras' fits (fit.fit_stride)
        # the span the fitted rows cover: last - first time + one frame period
        "duration_s": float(body.time[-1] - body.time[0] + 1.0 / body.fps) if t else 0.0,
        "fps": body.fps,
        "fit_chamfer_cm": {"mean": _nan_stat(body.fit_chamfer, np.mean, 100.0),
                           "median": _nan_stat(body.fit_chamfer, np.median, 100.0)},
        "chamfer_cm": {"mean": _nan_stat(body.chamfer, np.mean, 100.0),
                       "median": _nan_stat(body.chamfer, np.median, 100.0)},
        "reliability_mean": _nan_stat(rel, np.mean),
        "fallback_frames": int(np.count_nonzero(body.fallback)),
        "imu_gap_frames": int(np.count_nonzero(body.imu_filled)),
        "points_mean": _nan_stat(body.points, np.mean),
        "frames_seen_per_camera": {s: int(present[:, c].sum()) if c < present.shape[1] else 0
                                   for c, s in enumerate(body.camera_serials)},
        "shape_source": body.shape_source,
        "seconds": dict(body.seconds),
    }


def _chair_summary(chair: ChairRegistration | None) -> dict[str, Any] | None:
    if chair is None:
        return None
    reasons = Counter(why.split(":")[0] for _, why in chair.rejected)
    return {
        "scan": str(chair.scan) if chair.scan is not None else None,
        "world_from_object": np.asarray(chair.world_from_object, np.float64),
        "rotation_spread_deg": chair.rotation_spread_deg,
        "translation_spread_mm": chair.translation_spread_mm,
        "chamfer_cm": chair.chamfer * 100.0,
        "frames_registered": len(chair.frames),
        "frames_used": int(np.count_nonzero(chair.used)),
        "fitness_mean": _nan_stat(chair.fitness, np.mean),
        "rmse_mean_mm": _nan_stat(chair.rmse, np.mean, 1e3),
        "rejected": dict(reasons),
        "segments": [{"first": s.first, "last": s.last, "start_time": s.start_time,
                      "end_time": s.end_time, "frames": len(s.frames),
                      "rotation_spread_deg": s.rotation_spread_deg,
                      "translation_spread_mm": s.translation_spread_mm,
                      "chamfer_cm": s.chamfer * 100.0} for s in chair.segments],
        "ambiguous": bool(chair.ambiguous),
        "ambiguity_deg": list(chair.ambiguity_deg),
        "moved": bool(chair.moved),
        "depth_errors": chair.depth_errors,
    }


def _contacts_summary(contacts: Contacts | None) -> dict[str, Any] | None:
    if contacts is None:
        return None
    active = np.asarray(contacts.active, bool)
    floor = np.asarray(contacts.floor_active, bool)
    labels = np.asarray(contacts.labels).astype(np.int64)
    return {
        "frames": len(active),
        # the motion's per-frame noise and how much of the detector's guards it got
        "motion_noise_mm": float(contacts.noise) * 1e3,
        "guard": float(contacts.guard),
        "active_frames": {n: int(active[:, j].sum()) for j, n in enumerate(contacts.names)},
        "floor_frames": {n: int(floor[:, j].sum())
                         for j, n in enumerate(FEET[: floor.shape[1]])},
        "labels": {INTERACTION_LABELS[k]: int(np.count_nonzero(labels == k))
                   for k in sorted(INTERACTION_LABELS)},
    }


def build_summary(result: PipelineResult) -> dict[str, Any]:
    """The report's numbers as strict-JSON-able Python (NaN/inf → None; a section is None when
    its stage did not run). Lengths are reported in the unit named by the key (cm, mm, m)."""
    doc = {
        "session": str(result.session),
        "output": str(result.output),
        "processed": str(result.processed) if result.processed else None,
        "ok": result.ok,
        "fault": ({"stage": result.fault[0], "message": result.fault[1]}
                  if result.fault else None),
        "seconds": result.seconds,
        "frames": list(result.frames) if result.frames is not None else None,
        "stages": _stages_summary(result),
        "warnings": list(result.warnings),
        "calibration": _calibration_summary(result),
        "sync": _sync_summary(result.body),
        "body": _body_summary(result.body),
        "chair": _chair_summary(result.chair),
        "contacts": _contacts_summary(result.contacts),
    }
    return _clean(doc)


# --------------------------------------------------------------------------- plots


def _save_figure(fig: Figure, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    return path


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, length) of the runs of True in a (T,) bool array."""
    return [(int(a), int(b - a)) for a, b in zip(*runs(mask), strict=True)]


def plot_sync(body: BodyResult, path: Path) -> Path | None:
    """``sync.png``: the cameras' head-top height (m) over time and the suit's, each minus its
    median (the suit's over the cameras' span); None when there is nothing to draw."""
    kt, kh = np.asarray(body.sync_time, float), np.asarray(body.sync_kinect_height, float)
    it, ih = np.asarray(body.sync_imu_time, float), np.asarray(body.sync_imu_height, float)
    if not (np.isfinite(kh).any() or np.isfinite(ih).any()):
        return None
    fig = Figure(figsize=(10, 4))
    ax = fig.add_subplot()
    if np.isfinite(kh).any():
        ax.plot(kt, kh - np.nanmedian(kh), ".-", ms=3, lw=1, label="cameras (head top)")
    if np.isfinite(ih).any():
        # the suit's median over the span the cameras saw, so the two overlay
        seen = np.isfinite(kh)
        span = (it >= kt[seen].min()) & (it <= kt[seen].max()) if seen.any() else None
        ref = ih[span] if span is not None and np.isfinite(ih[span]).any() else ih
        ax.plot(it, ih - np.nanmedian(ref), "-", lw=1, alpha=0.8, label="suit (head top)")
    ax.set_xlabel("time (s, Kinect clock)")
    ax.set_ylabel("height - median (m)")
    ax.set_title(f"IMU sync: offset {body.clock_offset_ms:.1f} ms, drift "
                 f"{body.clock_drift_ppm:.1f} ppm, correlation {body.clock_correlation:.3f}"
                 + ("" if body.clock_confident else " (not confident)"))
    ax.grid(alpha=0.3)
    ax.legend(loc="best")
    fig.tight_layout()
    return _save_figure(fig, path)


def plot_fit_error(body: BodyResult, path: Path) -> Path | None:
    """``fit_error.png``: per-frame fit and fused chamfer (cm), mean reliability and person
    points over time, on the rows the cameras were fitted on."""
    t = np.asarray(body.time, float)
    if t.size == 0:
        return None
    on = np.asarray(body.fitted, bool)
    fig = Figure(figsize=(10, 6))
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.plot(t[on], np.asarray(body.fit_chamfer, float)[on] * 100, ".-", ms=3, lw=1,
             label="per-frame fit")
    ax1.plot(t[on], np.asarray(body.chamfer, float)[on] * 100, ".-", ms=3, lw=1,
             label="fused motion")
    for a, n in _runs(np.asarray(body.imu_filled, bool)):
        ax1.axvspan(t[a], t[min(a + n, len(t) - 1)], color="orange", alpha=0.2, lw=0)
    fb = np.asarray(body.fallback, bool)
    if fb.any():
        ax1.plot(t[fb], np.zeros(fb.sum()), "rx", label="fallback")
    ax1.set_ylabel("chamfer (cm)")
    ax1.set_title("body fit error (shaded: IMU gap filled)")
    ax1.grid(alpha=0.3)
    ax1.legend(loc="best")
    rel = np.asarray(body.reliability, float).reshape(len(t), -1)[on]
    finite = np.isfinite(rel)
    mean_rel = np.where(finite, rel, 0.0).sum(axis=1) / np.maximum(finite.sum(axis=1), 1)
    ax2.plot(t[on], np.where(finite.any(axis=1), mean_rel, np.nan), "g-",
             label="mean reliability")
    ax2.set_ylim(-0.05, 1.05)
    ax2.set_ylabel("reliability")
    ax2.set_xlabel("time (s)")
    ax3 = ax2.twinx()
    ax3.plot(t[on], np.asarray(body.points, float)[on], "k:", lw=1, label="person points")
    ax3.set_ylabel("points")
    ax2.legend(handles=ax2.lines + ax3.lines, loc="best")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    return _save_figure(fig, path)


def plot_contacts(contacts: Contacts, path: Path, time: np.ndarray | None = None) -> Path | None:
    """``contacts.png``: a row per contact part (frames touching the chair), the feet's floor
    contacts and a band of the interaction label per frame. ``time``: (T,) s, else frame/fps."""
    active = np.asarray(contacts.active, bool)
    n = len(active)
    if n == 0:
        return None
    t = (np.asarray(time, float) if time is not None and len(time) == n
         else np.arange(n) / contacts.fps)
    dt = float(np.median(np.diff(t))) if n > 1 else 1.0 / contacts.fps
    floor = np.asarray(contacts.floor_active, bool)
    rows = [(f"{name} (chair)", active[:, j], "tab:blue") for j, name in enumerate(contacts.names)]
    rows += [(f"{name} (floor)", floor[:, j], "tab:brown")
             for j, name in enumerate(FEET[: floor.shape[1]])]
    fig = Figure(figsize=(10, 1.2 + 0.35 * (len(rows) + 1)))
    ax = fig.add_subplot()
    for y, (_, mask, color) in enumerate(rows):
        bars = [(t[a], n_ * dt) for a, n_ in _runs(mask)]
        ax.broken_barh(bars, (y + 0.15, 0.7), color=color)
    labels = np.asarray(contacts.labels).astype(np.int64)
    y_band = len(rows)
    for k in sorted(INTERACTION_LABELS):
        bars = [(t[a], n_ * dt) for a, n_ in _runs(labels == k)]
        if bars:
            ax.broken_barh(bars, (y_band + 0.1, 0.8), color=LABEL_COLORS.get(k, "k"))
    ax.set_yticks(np.arange(len(rows) + 1) + 0.5,
                  [r[0] for r in rows] + ["interaction label"])
    ax.set_ylim(0, len(rows) + 1)
    ax.invert_yaxis()
    ax.set_xlim(t[0], t[-1] + dt)
    ax.set_xlabel("time (s)")
    ax.set_title("contacts")
    ax.grid(axis="x", alpha=0.3)
    handles = [Patch(color=LABEL_COLORS.get(k, "k"), label=name)
               for k, name in sorted(INTERACTION_LABELS.items())]
    handles += [Patch(color="tab:blue", label="chair contact"),
                Patch(color="tab:brown", label="floor contact")]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    return _save_figure(fig, path)


def plot_chair(chair: ChairRegistration, path: Path) -> Path | None:
    """``chair.png``: per registered frame, the rotation (deg) and translation (mm) of its ICP
    pose from ``world_from_object``, and its ICP fitness; used / left-out / rejected marked."""
    n = len(chair.frames)
    if n == 0:
        return None
    t = np.asarray(chair.time, float) if len(chair.time) == n else np.asarray(chair.frames, float)
    poses = np.asarray(chair.frame_poses, float).reshape(n, 4, 4)
    ref = np.asarray(chair.world_from_object, float)
    have = np.isfinite(poses).all(axis=(1, 2))
    rot = np.full(n, np.nan)
    trans = np.full(n, np.nan)
    if have.any():
        rot[have] = rotation_angle_deg(ref, poses[have])
        trans[have] = np.linalg.norm(poses[have, :3, 3] - ref[:3, 3], axis=1) * 1e3
    used = np.asarray(chair.used, bool)
    left_out = have & ~used
    # rejected frames have no pose; those with one but left out of the averages are circled
    rejected = np.flatnonzero(~have).tolist()
    fig = Figure(figsize=(10, 7))
    axes = fig.subplots(3, 1, sharex=True)
    series = [(rot, "rotation from the pose (deg)"), (trans, "translation from the pose (mm)"),
              (np.asarray(chair.fitness, float), "ICP fitness")]
    for ax, (values, label) in zip(axes, series, strict=True):
        ax.plot(t, values, "-", color="0.6", lw=1)
        ax.plot(t[used], values[used], "o", color="tab:green", ms=4, label="used")
        if left_out.any():
            ax.plot(t[left_out], values[left_out], "o", mfc="none", color="tab:red", ms=6,
                    label="registered, not averaged")
        for k, p in enumerate(rejected):
            ax.axvline(t[p], color="tab:red", alpha=0.3, lw=2,
                       label="rejected" if k == 0 else None)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
    axes[0].set_title(f"chair registration: {int(used.sum())}/{n} frames used, spread "
                      f"{chair.rotation_spread_deg:.3f} deg / {chair.translation_spread_mm:.2f} mm")
    axes[0].legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    return _save_figure(fig, path)


def _write_plots(result: PipelineResult, directory: Path) -> tuple[list[str], list[str]]:
    """Make the plots whose data exist → (file names written, notes on plots that failed)."""
    jobs: list[tuple[str, Any]] = []
    body, chair, contacts = result.body, result.chair, result.contacts
    if body is not None:
        jobs += [("sync.png", lambda p: plot_sync(body, p)),
                 ("fit_error.png", lambda p: plot_fit_error(body, p))]
    if contacts is not None:
        time = body.time if body is not None else None
        jobs.append(("contacts.png", lambda p: plot_contacts(contacts, p, time)))
    if chair is not None:
        jobs.append(("chair.png", lambda p: plot_chair(chair, p)))
    written, notes = [], []
    for name, make in jobs:
        try:
            if make(directory / name) is not None:
                written.append(name)
        except Exception as exc:  # a report must not die of a plot; say so instead
            notes.append(f"{name}: not made ({type(exc).__name__}: {exc})")
    return written, notes


# --------------------------------------------------------------------------- previews


def preview_frames(result: PipelineResult, count: int) -> list[int]:
    """Up to ``count`` fitted rows (indices into ``result.body.time``) spread over the session:
    one per equal stretch, the one with the most chair contacts nearest the stretch's middle
    (the middle when none has contacts). Empty without a body."""
    body = result.body
    if body is None or count <= 0 or len(body.time) == 0:
        return []
    t = len(body.time)
    score = np.zeros(t)
    if result.contacts is not None and len(result.contacts.active) == t:
        score = np.asarray(result.contacts.active, bool).sum(axis=1).astype(float)
    bounds = np.linspace(0, t, min(count, t) + 1).round().astype(int)
    picks = []
    for a, b in itertools.pairwise(bounds):
        if b <= a:
            continue
        mid = (a + b - 1) // 2
        best = np.flatnonzero(score[a:b] == score[a:b].max()) + a
        picks.append(int(best[np.argmin(np.abs(best - mid))]))
    return sorted(set(picks))


def _posed_vertices(body: BodyResult, index: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """(n,V,3) world vertices (m) of the fused motion at rows ``index`` with the full body
    model, and its (F,3) faces."""
    model = cached_model(SessionFitConfig().body.model)
    p = body.params.frames(np.asarray(index, dtype=np.int64))
    with torch.no_grad():
        out = model(betas=p.betas[None], global_orient=p.global_orient, body_pose=p.body_pose,
                    transl=p.transl)
    return out.vertices.cpu().numpy().astype(np.float64), np.asarray(model.faces)


def _read_captures(path: Path, timestamps: Iterable[int]) -> tuple[dict[int, KinectCapture], Any]:
    """The captures of a recording whose ``timestamp_us`` is one of ``timestamps`` (one pass,
    stopping when all are found) and the recording's calibration."""
    want = {int(x) for x in timestamps}
    rec = open_azure_mkv(path)
    found: dict[int, KinectCapture] = {}
    for cap in rec:
        if cap.timestamp_us in want:
            found[int(cap.timestamp_us)] = cap
            if len(found) == len(want):
                break
    return found, rec.calibration


def _depth_grey(depth_mm: np.ndarray) -> np.ndarray:
    """(H,W) uint16 mm → (H,W,3) uint8 grey (near bright, invalid black)."""
    d = np.asarray(depth_mm, np.float64)
    valid = d > 0
    out = np.zeros(d.shape, np.uint8)
    if valid.any():
        lo, hi = np.percentile(d[valid], [2, 98])
        g = 1.0 - np.clip((d - lo) / max(hi - lo, 1.0), 0.0, 1.0)
        out[valid] = (40 + 200 * g[valid]).astype(np.uint8)
    return np.repeat(out[..., None], 3, axis=2)


def _resize_k(k: np.ndarray, size: tuple[int, int], new_size: tuple[int, int]) -> np.ndarray:
    """(3,3) camera matrix ``k`` of a ``size`` (w,h) image, for the image resized to
    ``new_size`` (pixel centres at integers, OpenCV's convention)."""
    sx, sy = new_size[0] / size[0], new_size[1] / size[1]
    out = np.array(k, np.float64)
    out[0, 0], out[1, 1] = out[0, 0] * sx, out[1, 1] * sy
    out[0, 2], out[1, 2] = (out[0, 2] + 0.5) * sx - 0.5, (out[1, 2] + 0.5) * sy - 0.5
    return out


def _overlay_tile(cap: KinectCapture, calibration: Any, world_from_color: np.ndarray,
                  world_from_depth: np.ndarray, meshes: list[Mesh], scale: float = 0.5,
                  source: str = "") -> np.ndarray:
    """One camera's image (colour, else grey depth), undistorted, resized by ``scale``, with
    ``meshes`` ray-cast from that camera alpha-blended over it → (h,w,3) uint8 RGB."""
    if cap.color_jpeg is not None:
        img, intr, pose = decode_color(cap.color_jpeg, source=source), calibration.color, \
            world_from_color
    elif cap.depth_mm is not None:
        img, intr, pose = _depth_grey(cap.depth_mm), calibration.depth, world_from_depth
    else:
        raise ValueError("the capture has neither colour nor depth")
    h, w = img.shape[:2]
    k = _resize_k(intr.K(), (intr.width, intr.height), (w, h))
    img = cv2.undistort(img, k, intr.dist)
    rw, rh = max(1, round(w * scale)), max(1, round(h * scale))
    img = cv2.resize(img, (rw, rh), interpolation=cv2.INTER_AREA)
    k = _resize_k(k, (w, h), (rw, rh))
    hit = render(meshes, k, np.asarray(pose, np.float64), rw, rh)
    mask = hit.mesh_id >= 0
    out = img.copy()
    out[mask] = ((1 - ALPHA) * img[mask] + ALPHA * hit.rgb[mask]).astype(np.uint8)
    return out


def _note_tile(text: str, size: tuple[int, int] = TILE_NOTE_SIZE) -> np.ndarray:
    """A grey (h,w,3) uint8 tile of ``size`` (w,h) carrying ``text`` (wrapped)."""
    w, h = size
    tile = np.full((h, w, 3), 90, np.uint8)
    chars = max(10, w // 10)
    lines = [text[i:i + chars] for i in range(0, len(text), chars)][: max(1, h // 22 - 2)]
    for k, line in enumerate(lines):
        cv2.putText(tile, line, (8, 40 + 22 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (255, 255, 255), 1, cv2.LINE_AA)
    return tile


def _label(tile: np.ndarray, text: str) -> np.ndarray:
    """``tile`` with ``text`` on a dark strip at its top-left."""
    out = tile.copy()
    cv2.rectangle(out, (0, 0), (min(out.shape[1], 10 + 9 * len(text)), 22), (0, 0, 0), -1)
    cv2.putText(out, text, (5, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                cv2.LINE_AA)
    return out


def _grid(tiles: list[np.ndarray]) -> np.ndarray:
    """The (h,w,3) RGB uint8 tiles (resized to the first one's size) in a near-square grid."""
    h, w = tiles[0].shape[:2]
    cols = math.ceil(math.sqrt(len(tiles)))
    rows = math.ceil(len(tiles) / cols)
    out = np.full((rows * h, cols * w, 3), 255, np.uint8)
    for k, tile in enumerate(tiles):
        r, c = divmod(k, cols)
        if tile.shape[:2] != (h, w):
            tile = cv2.resize(tile, (w, h), interpolation=cv2.INTER_AREA)
        out[r * h:(r + 1) * h, c * w:(c + 1) * w] = tile
    return out


def _write_png(path: Path, rgb: np.ndarray) -> Path:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"{path}: PNG encoding failed")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
    return path


def _camera_captures(result: PipelineResult, frames: Sequence[int]
                     ) -> tuple[list[dict[int, KinectCapture]], list[Any], list[str]]:
    """Per camera of the body stage: the captures of the preview ``frames``, its calibration
    (None when unreadable) and why it is missing ("" when read)."""
    body = result.body
    assert body is not None
    session_problem = ""
    try:
        files = session_files(result.session)
    except (OSError, ValueError) as exc:
        files, session_problem = None, f"session unreadable: {exc}"
    caps: list[dict[int, KinectCapture]] = []
    calibs: list[Any] = []
    problems: list[str] = []
    for c, serial in enumerate(body.camera_serials):
        cam = files.camera(serial) if files is not None else None
        found: dict[int, KinectCapture] = {}
        calib, problem = None, ""
        if files is None:
            problem = session_problem
        elif cam is None or cam.recording is None:
            problem = "no recording in the session"
        else:
            stamps = [int(body.frame_timestamp_us[i, c]) for i in frames
                      if body.frame_timestamp_us[i, c] >= 0]
            try:
                found, calib = _read_captures(cam.recording, stamps)
            except Exception as exc:  # a broken recording: a note on its tiles, not a crash
                problem = f"{cam.recording} unreadable: {exc}"
        caps.append(found)
        calibs.append(calib)
        problems.append(problem)
    return caps, calibs, problems


def _frame_tiles(result: PipelineResult, i: int, meshes: list[Mesh],
                 caps: list[dict[int, KinectCapture]], calibs: list[Any],
                 problems: list[str]) -> tuple[list[np.ndarray], list[str]]:
    """The tiles of fitted row ``i``, one per camera, and notes on the ones that failed."""
    body = result.body
    assert body is not None
    cams = result.extrinsics.cameras if result.extrinsics is not None else {}
    tiles, notes, real = [], [], []
    for c, serial in enumerate(body.camera_serials):
        stamp = int(body.frame_timestamp_us[i, c])
        head = f"{serial}  t={float(body.time[i]):.2f} s"
        why = problems[c]
        if not why and stamp < 0:
            why = "no frame of this camera at this row"
        elif not why and stamp not in caps[c]:
            why = f"capture {stamp} us not found in the recording"
        elif not why and serial not in cams:
            why = "no extrinsics for this camera"
        if not why:
            try:
                tile = _overlay_tile(caps[c][stamp], calibs[c], cams[serial].world_from_color,
                                     cams[serial].world_from_depth, meshes,
                                     source=f"{serial} @ {stamp} us")
                real.append(len(tiles))
                tiles.append(_label(tile, head))
                continue
            except Exception as exc:  # a bad frame: note it, keep the other tiles
                why = f"{type(exc).__name__}: {exc}"
        notes.append(f"row {int(body.rows[i])}, camera {serial}: {why}")
        tiles.append(_label(_note_tile(why), head))
    if real:  # the grid takes its tile size from the first tile: make it a real one
        size = tiles[real[0]].shape[1::-1]
        tiles = [t if t.shape[:2] == size[::-1] else
                 cv2.resize(t, size, interpolation=cv2.INTER_AREA) for t in tiles]
    return tiles, notes


def write_previews(result: PipelineResult, directory: Path, count: int = 4,
                   progress: bool = False) -> tuple[list[tuple[str, str]], list[str]]:
    """``previews/frame_XXXX.png`` (XXXX: frame-table row) of up to ``count`` rows: every
    camera's image with the fused body and the registered chair over it.

    Returns:
        (relative path, caption) per preview written, and notes on tiles or previews skipped.
    """
    body = result.body
    frames = preview_frames(result, count)
    if body is None or not frames:
        return [], []
    if not body.camera_serials:
        return [], ["previews: the body stage recorded no cameras"]
    verts, faces = _posed_vertices(body, frames)
    chair = None
    if result.chair is not None:
        chair = Mesh(result.chair.world_vertices, np.asarray(result.chair.faces), CHAIR_COLOR)
    caps, calibs, problems = _camera_captures(result, frames)
    written, notes = [], []
    for k, i in enumerate(tqdm(frames, desc="report previews", disable=not progress,
                               leave=False)):
        meshes = [Mesh(verts[k], faces, BODY_COLOR)] + ([chair] if chair is not None else [])
        tiles, tile_notes = _frame_tiles(result, i, meshes, caps, calibs, problems)
        notes += tile_notes
        name = f"previews/frame_{int(body.rows[i]):04d}.png"
        _write_png(directory / name, _grid(tiles))
        active = ""
        if result.contacts is not None and len(result.contacts.active) > i:
            on = [n for n, a in zip(result.contacts.names, result.contacts.active[i],
                                    strict=True) if a]
            active = f"; contacts: {', '.join(on) if on else 'none'}"
        written.append((name, f"row {int(body.rows[i])}, t = {float(body.time[i]):.2f} s"
                              + active))
    return written, notes


# --------------------------------------------------------------------------- HTML

CSS = """
body { font-family: sans-serif; margin: 1.5em auto; max-width: 1300px; color: #222; }
h1 .ok { color: #2e7d32; } h1 .failed { color: #c62828; }
.fault { border: 2px solid #c62828; background: #ffebee; padding: 0.6em 1em; margin: 1em 0; }
table { border-collapse: collapse; margin: 0.4em 0 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 2px 8px; text-align: left; vertical-align: top; }
th { background: #f0f0f0; }
td.failed { color: #c62828; font-weight: bold; } td.ran, td.cached { color: #2e7d32; }
img { max-width: 100%; border: 1px solid #ddd; }
figure { margin: 1em 0; } figcaption { font-size: 0.9em; color: #555; }
pre { background: #f6f6f6; padding: 0.8em; overflow-x: auto; font-size: 0.85em; }
.none { color: #888; }
"""


def _esc(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _fmt(value: Any) -> str:
    """A summary value as HTML (escaped): None → a dash, floats to 4 significant digits, nested
    dicts and lists of dicts as tables, other lists comma-joined."""
    if value is None:
        return '<span class="none">&mdash;</span>'
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return _esc(f"{value:.4g}")
    if isinstance(value, dict):
        return _table(value) if value else '<span class="none">none</span>'
    if isinstance(value, list):
        if value and all(isinstance(v, dict) for v in value):
            return _rows_table(value)
        if value and all(isinstance(v, list) for v in value):  # a matrix
            return "<br>".join(" ".join(_fmt(x) for x in row) for row in value)
        return ", ".join(_fmt(v) for v in value) if value else '<span class="none">none</span>'
    return _esc(value)


def _table(mapping: dict[str, Any]) -> str:
    """A two-column key / value table."""
    rows = "".join(f"<tr><th>{_esc(k)}</th><td>{_fmt(v)}</td></tr>" for k, v in mapping.items())
    return f"<table>{rows}</table>"


def _rows_table(rows: list[dict[str, Any]]) -> str:
    """A table with a column per key of the dicts ``rows``."""
    keys = list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f"<th>{_esc(k)}</th>" for k in keys)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(r.get(k))}</td>" for k in keys) + "</tr>"
                   for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _stage_table(stages: dict[str, Any]) -> str:
    head = "<tr><th>stage</th><th>status</th><th>seconds</th><th>steps (s)</th><th>error</th></tr>"
    rows = []
    for name, s in stages.items():
        steps = ", ".join(f"{_esc(k)} {v:.2f}" for k, v in s["steps"].items()
                          if isinstance(v, float | int)) or "&mdash;"
        status = _esc(s["status"]).replace(" ", "-")
        rows.append(f"<tr><td>{_esc(name)}</td><td class=\"{status}\">{_esc(s['status'])}</td>"
                    f"<td>{_fmt(s['seconds'])}</td><td>{steps}</td>"
                    f"<td>{_esc(s['error'] or '')}</td></tr>")
    return f"<table>{head}{''.join(rows)}</table>"


def render_html(summary: dict[str, Any], result: PipelineResult, plots: Sequence[str],
                previews: Sequence[tuple[str, str]], notes: Sequence[str]) -> str:
    """The ``index.html`` text: one self-contained page (inline CSS, relative image links)."""
    name = Path(result.session).name or str(result.session)
    state = '<span class="ok">OK</span>' if result.ok else '<span class="failed">FAILED</span>'
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
             f"<title>couch report: {_esc(name)} ({'OK' if result.ok else 'FAILED'})</title>"
             f"<style>{CSS}</style></head><body>",
             f"<h1>couch report: {_esc(name)} &mdash; {state}</h1>"]
    if result.fault:
        parts.append(f'<div class="fault"><b>failed at stage {_esc(result.fault[0])}:</b> '
                     f"{_esc(result.fault[1])}</div>")
    parts.append(_table({"session": summary["session"], "output": summary["output"],
                         "processed": summary["processed"], "frames": summary["frames"],
                         "seconds": summary["seconds"]}))
    parts += ["<h2>Stages</h2>", _stage_table(summary["stages"]), "<h2>Warnings</h2>"]
    parts.append("<ul>" + "".join(f"<li>{_esc(w)}</li>" for w in result.warnings) + "</ul>"
                 if result.warnings else '<p class="none">none</p>')
    for section in ("calibration", "sync", "body", "chair", "contacts"):
        parts.append(f"<h2>{section.capitalize()}</h2>")
        value = summary[section]
        parts.append(_table(value) if value is not None
                     else '<p class="none">the stage did not run</p>')
    if plots:
        parts.append("<h2>Plots</h2>")
        parts += [f'<figure><img src="{_esc(p)}" alt="{_esc(p)}"></figure>' for p in plots]
    if previews:
        parts.append("<h2>Previews</h2><p>body (blue) and chair (orange) over each camera's "
                     "image</p>")
        parts += [f'<figure><img src="{_esc(p)}" alt="{_esc(p)}"><figcaption>{_esc(cap)}'
                  f"</figcaption></figure>" for p, cap in previews]
    if notes:
        parts.append("<h2>Report notes</h2><ul>"
                     + "".join(f"<li>{_esc(n)}</li>" for n in notes) + "</ul>")
    if result.traceback:
        parts.append(f"<h2>Traceback</h2><pre>{_esc(result.traceback)}</pre>")
    parts.append("</body></html>\n")
    return "\n".join(parts)


# --------------------------------------------------------------------------- the report


def _remove_stale(directory: Path, plots: Sequence[str], previews: Sequence[str]) -> None:
    """Delete this report's own files left from an earlier report that this one did not make."""
    for name in PLOTS:
        if name not in plots:
            (directory / name).unlink(missing_ok=True)
    keep = {Path(p).name for p in previews}
    for old in (directory / "previews").glob("frame_*.png"):
        if old.name not in keep:
            old.unlink(missing_ok=True)


def write_report(result: PipelineResult, directory: str | os.PathLike, *, previews: int = 4,
                 progress: bool = False) -> Path:
    """Write the QA report of a pipeline run (finished or failed) into ``directory``.

    Args:
        result: what :func:`~couch.fitting.pipeline.run_pipeline` returned.
        directory: the report folder (created; this report's earlier files are replaced).
        previews: how many preview frames to render (0: none). Previews need the body stage,
            the extrinsics and readable recordings; a camera that cannot be shown gets a tile
            with a note instead.
        progress: a progress bar over the previews.

    Returns:
        The path of ``index.html``.
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    summary = build_summary(result)
    plots, notes = _write_plots(result, out)
    try:
        shown, preview_notes = write_previews(result, out, previews, progress)
    except Exception as exc:  # e.g. the body model cannot pose the motion: no previews
        shown, preview_notes = [], [f"previews: not made ({type(exc).__name__}: {exc})"]
    notes += preview_notes
    _remove_stale(out, plots, [p for p, _ in shown])
    summary["report"] = {"plots": plots, "previews": [p for p, _ in shown], "notes": notes}
    with atomic_path(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    index = out / "index.html"
    with atomic_path(index) as tmp:
        tmp.write_text(render_html(summary, result, plots, shown, notes), encoding="utf-8")
    return index
