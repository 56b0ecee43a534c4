"""The processing pipeline behind ``couch-process``: a raw session folder to ``processed.h5``.

Stages, in order (each one's result cached by the hash of its inputs and config):

``calibrate``
    Camera extrinsics (ChArUco + floor, :func:`couch.capture.calibration.calibrate_session`),
    or the ones given. Cameras whose recording is missing or unreadable are dropped here, with a
    warning, and the rest of the pipeline runs on a *view* of the session without them.
``chair``
    The chair scan registered to the chair's points (:func:`~couch.fitting.chair.register_chair`)
    on the rows of the Kinect frame table (the sync's Kinect part runs first).
``body``
    IMU sync, person clouds without the registered chair, shape, per-frame fits and fusion
    (:func:`~couch.fitting.session.fit_session`).
``contacts``
    Contacts with the chair and the floor and interaction labels
    (:func:`~couch.fitting.contacts.detect_contacts`), then ``processed.h5`` (DESIGN.md schema).

A stage that fails (a bad recording, a bad scan) records a *fault* (stage and message naming
the file) and stops the pipeline: the result says what ran and why it stopped, and nothing
half-written is left behind. Problems a session survives (a dropped camera, skipped frames, a
symmetric chair) are *warnings*.

The cache lives in ``<output>/cache/``: one HDF5 record per stage (:mod:`couch.records`),
named by a key that hashes the code that computes the results (:func:`code_digest`), the stage's
config, the stage's input files (path, size and modification time, as ``make`` does) and the keys
of the stages it uses, so a re-run resumes where the last one stopped, and a changed input or a
changed stage's code (a changed default, a fix) re-runs that stage and those after it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import time as wallclock
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from couch.atomic import atomic_path
from couch.body.skeleton import CONTACT_NAMES
from couch.capture.azure_mkv import open_azure_mkv
from couch.capture.calibration import (
    Extrinsics,
    calibrate_session,
    read_extrinsics,
    write_extrinsics,
)
from couch.capture.segmentation import ChairModel
from couch.capture.session import SessionFiles, session_files
from couch.fitting.body import cached_model
from couch.fitting.chair import (
    ChairConfig,
    ChairRegistration,
    chair_clouds,
    load_scan,
    register_chair,
    session_scan_path,
)
from couch.fitting.contacts import ContactConfig, Contacts, detect_contacts
from couch.fitting.params import BodyParams
from couch.fitting.session import SessionFit, SessionFitConfig, fit_session
from couch.pool import spawn_pool
from couch.records import RecordError, read_record, write_record
from couch.schema import ProcessedSession, write_processed
from couch.sources import source_digest
from couch.sync import SessionSync, sync_session
from couch.sync.imu import imu_head_top, imu_sample_times

log = logging.getLogger(__name__)

STAGES: tuple[str, ...] = ("calibrate", "chair", "body", "contacts")
PROCESSED_NAME = "processed.h5"


class ProcessError(RuntimeError):
    """Bad arguments to the pipeline (unknown stage, bad frame range, missing session)."""


@dataclasses.dataclass(frozen=True)
class ProcessConfig:
    """Knobs of the pipeline.

    Attributes:
        fit: the body stage's (:class:`~couch.fitting.session.SessionFitConfig`).
        chair: the chair stage's (:class:`~couch.fitting.chair.ChairConfig`).
        contacts: the contact stage's (:class:`~couch.fitting.contacts.ContactConfig`).
        chair_frames: register the chair on at most this many rows of the frame table, evenly
            spread (0: every row). The chair is static: a few dozen frames give its average and
            spread and find a move between two static periods, at a fraction of the cost.
        contact_model: body model measuring contacts (the coarse one is ~10x faster and within
            millimetres of the full model's surface).
        device: torch device of the fits (``cpu``, ``cuda``).
    """

    fit: SessionFitConfig = dataclasses.field(default_factory=SessionFitConfig)
    chair: ChairConfig = dataclasses.field(default_factory=ChairConfig)
    contacts: ContactConfig = dataclasses.field(default_factory=ContactConfig)
    chair_frames: int = 40
    contact_model: str = "couch-body-coarse"
    device: str = "cpu"

    def __post_init__(self) -> None:
        if self.chair_frames < 0:
            raise ValueError(f"ProcessConfig.chair_frames must be >= 0, got {self.chair_frames}")


@dataclasses.dataclass
class StageRun:
    """What happened to one stage.

    Attributes:
        name: the stage.
        status: ``ran``, ``cached`` (loaded from the cache), ``failed`` or ``not run``.
        seconds: wall time (loading, for a cached stage).
        key: the cache key (hex) or "".
        steps: seconds per step inside the stage (as measured when it ran).
        error: the fault's message when it failed.
    """

    name: str
    status: str = "not run"
    seconds: float = 0.0
    key: str = ""
    steps: dict[str, float] = dataclasses.field(default_factory=dict)
    error: str = ""


@dataclasses.dataclass
class CalibrationResult:
    """The calibrate stage's record: which cameras the session is processed with.

    Attributes:
        cameras: serials kept, in the session's order.
        dropped: (serial, reason) of cameras left out.
        extrinsics_json: the ``extrinsics.json`` text (:func:`write_extrinsics`'s layout).
        warnings: what may be wrong.
    """

    cameras: list[str]
    dropped: list[tuple[str, str]]
    extrinsics_json: str
    warnings: list[str]


@dataclasses.dataclass
class BodyResult:
    """The body stage's record (a :class:`~couch.fitting.session.SessionFit` without the clouds).
    T fitted rows; world frame, metres, Kinect master-clock seconds.

    Attributes:
        time, rows: (T,) seconds and frame-table rows.
        fps: the Kinect frame rate.
        betas: (10,); global_orient (T,3), body_pose (T,69), transl (T,3): the fused motion.
        joints: (T,24,3) its joints.
        fit_joints: (T,24,3) the per-frame fits' joints; imu_joints (T,24,3): the aligned suit's.
        fit_chamfer, chamfer: (T,) metres, per-frame fit and fused motion to the clouds (NaN:
            no points / fallback / not fitted).
        reliability: (T,24); fallback, imu_filled: (T,) bool; foot_contact: (T,4) bool.
        fitted: (T,) bool, the rows the cameras were fitted on (``fit.fit_stride``); the
            per-frame fits' arrays are NaN on the others.
        points: (T,) person points per frame (NaN: not fitted); cameras_present: (T,C) bool.
        camera_serials: the C cameras; frame_timestamp_us: (T,C) int64 device timestamp (µs) of
            each camera's depth frame at each row (``KinectCapture.timestamp_us``), -1: none.
        sync_time, sync_kinect_height: (N,) every frame-table row's time and the cameras' head
            top height (m, NaN: not seen); sync_imu_time, sync_imu_height: (M,) the suit's head
            top on the Kinect clock.
        clock_offset_ms, clock_drift_ppm, clock_offset_std_ms, clock_correlation,
        clock_confident: the IMU clock; clock_summary its text.
        heading_deg, alignment_residual_m: IMU world to world.
        shape_source: ``scan`` or ``clouds``; summary: :meth:`SessionFit.summary`.
        seconds: per step; warnings.
    """

    time: np.ndarray
    rows: np.ndarray
    fps: float
    betas: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    joints: np.ndarray
    fit_joints: np.ndarray
    imu_joints: np.ndarray
    fit_chamfer: np.ndarray
    chamfer: np.ndarray
    reliability: np.ndarray
    fallback: np.ndarray
    imu_filled: np.ndarray
    foot_contact: np.ndarray
    fitted: np.ndarray
    points: np.ndarray
    cameras_present: np.ndarray
    camera_serials: list[str]
    frame_timestamp_us: np.ndarray
    sync_time: np.ndarray
    sync_kinect_height: np.ndarray
    sync_imu_time: np.ndarray
    sync_imu_height: np.ndarray
    clock_offset_ms: float
    clock_drift_ppm: float
    clock_offset_std_ms: float
    clock_correlation: float
    clock_confident: bool
    clock_summary: str
    heading_deg: float
    alignment_residual_m: float
    shape_source: str
    summary: str
    seconds: dict[str, float]
    warnings: list[str]

    @property
    def params(self) -> BodyParams:
        """The fused motion as :class:`BodyParams` (T frames)."""
        return BodyParams(betas=np.asarray(self.betas, np.float32),
                          global_orient=self.global_orient, body_pose=self.body_pose,
                          transl=self.transl)


@dataclasses.dataclass
class PipelineResult:
    """One run of the pipeline.

    Attributes:
        session: the session folder; output: the output folder.
        processed: ``processed.h5`` when written, else None.
        stages: name → :class:`StageRun`, every stage of :data:`STAGES`.
        calibration: camera selection and poses; extrinsics: the poses.
        chair: the chair registration; body: the motion; contacts: contacts and labels.
        data: the processed session written (or None).
        fault: ``(stage, message)`` of the failure that stopped the run, or None.
        traceback: the failure's traceback when it was not an expected error (a bug).
        warnings: what may be wrong, by stage.
        frames: the (start, stop) frame-table rows asked for, or None.
        seconds: wall time of the whole run.
        report: the QA report's ``index.html`` when one was written (``couch.process``).
    """

    session: Path
    output: Path
    processed: Path | None
    stages: dict[str, StageRun]
    calibration: CalibrationResult | None = None
    extrinsics: Extrinsics | None = None
    chair: ChairRegistration | None = None
    body: BodyResult | None = None
    contacts: Contacts | None = None
    data: ProcessedSession | None = None
    fault: tuple[str, str] | None = None
    traceback: str = ""
    warnings: list[str] = dataclasses.field(default_factory=list)
    frames: tuple[int, int] | None = None
    seconds: float = 0.0
    report: Path | None = None

    @property
    def ok(self) -> bool:
        """Every stage asked for ran or came from the cache."""
        return self.fault is None

    def summary(self) -> str:
        """A few lines: per stage, status and time; the fault; the warnings."""
        lines = [f"{self.session} -> {self.output} ({self.seconds:.1f} s)"]
        for s in self.stages.values():
            lines.append(f"  {s.name:<9} {s.status:<8} {s.seconds:7.1f} s"
                         + (f"  {s.error}" if s.error else ""))
        if self.fault:
            lines.append(f"FAILED at {self.fault[0]}: {self.fault[1]}")
        elif self.processed:
            lines.append(f"wrote {self.processed}")
        if self.report:
            lines.append(f"report {self.report}")
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


# --------------------------------------------------------------------------- cache keys


def _fingerprint(paths: Sequence[Path | None]) -> list[list[Any]]:
    """(path, size, mtime_ns) of each file (None / missing: recorded as such)."""
    out: list[list[Any]] = []
    for p in paths:
        if p is None:
            continue
        try:
            st = p.stat()
            out.append([str(p.resolve()), st.st_size, st.st_mtime_ns])
        except OSError:
            out.append([str(p), None, None])
    return out


def _config_json(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _config_json(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [_config_json(v) for v in obj]
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return repr(obj)


# the modules whose code each stage runs (couch.sources follows their imports); the pipeline's
# own file is hashed into every key, its imports are not followed (they are all of couch)
STAGE_CODE: dict[str, tuple[str, ...]] = {
    "calibrate": ("couch.capture.calibration", "couch.capture.session", "couch.capture.azure_mkv"),
    "chair": ("couch.fitting.chair", "couch.sync"),
    "body": ("couch.fitting.session", "couch.fitting.body", "couch.sync"),
    "contacts": ("couch.fitting.contacts", "couch.fitting.body"),
}


def code_digest(stage: str) -> str:
    """Hex sha256 of the code that computes ``stage`` (:data:`STAGE_CODE`, with what it imports,
    and this file). It stands in the keys for the version: a release number does not change
    when a default or a fix does, so keys built on it served results the code no longer
    computes."""
    own = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()
    return hashlib.sha256(f"{own}{source_digest(STAGE_CODE[stage])}".encode()).hexdigest()


def stage_key(stage: str, config: Any, inputs: Sequence[Path | None], upstream: Sequence[str],
              extra: Any = None) -> str:
    """Hex sha256 of what a stage's result depends on, the stage's :func:`code_digest` too."""
    doc = {"stage": stage, "code": code_digest(stage),
           "config": _config_json(config),
           "inputs": _fingerprint(inputs), "upstream": list(upstream), "extra": extra}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def _camera_inputs(files: SessionFiles) -> list[Path | None]:
    return [p for c in files.cameras for p in (c.recording, c.calibration_capture, c.background)]


# --------------------------------------------------------------------------- helpers


def _camera_problem(path: Path | None) -> tuple[str | None, list[str]]:
    """Why a camera's session recording cannot be used (or None), and what the header says may
    be wrong with it (a truncated file: the frames before the cut are still used)."""
    if path is None:
        return "no session recording listed", []
    if not path.is_file():
        return f"{path}: missing", []
    if path.stat().st_size == 0:
        return f"{path}: empty file", []
    try:
        rec = open_azure_mkv(path)
        next(iter(rec))
    except StopIteration:
        return f"{path}: no captures", []
    except Exception as exc:  # the reader raises its format error; anything else is as bad
        return f"{path}: unreadable ({exc})", []
    return None, list(rec.warnings)


def session_view(files: SessionFiles, keep: Sequence[str], directory: Path, *,
                 calibration: bool = False) -> Path:
    """A session folder (``directory``) whose ``session.json`` names ``files`` by absolute path
    and lists only cameras ``keep``, so every stage reading it skips the others. With
    ``calibration`` the other cameras stay listed without a session recording: their board
    captures may be what links the rig's poses together."""
    doc: dict[str, Any] = {}
    if files.manifest is not None:
        doc = json.loads(files.manifest.read_text(encoding="utf-8"))
    doc["name"] = doc.get("name", files.root.name)
    doc["kinect"] = [{"serial": c.serial,
                      "file": (str(c.recording.resolve()) if c.recording and c.serial in keep
                               else None),
                      "calibration_capture": (str(c.calibration_capture.resolve())
                                              if c.calibration_capture else None),
                      "background": str(c.background.resolve()) if c.background else None,
                      "sync": c.sync}
                     for c in files.cameras if c.serial in keep or calibration]
    imu = dict(doc.get("imu") or {})
    if files.mvnx is not None:
        imu["mvnx"] = str(files.mvnx.resolve())
    for k, v in list(imu.items()):
        if k != "mvnx" and isinstance(v, str):
            imu[k] = str((files.root / v).resolve())
    doc["imu"] = imu or None
    if files.chair_scan is not None:
        doc["chair_scan"] = str(files.chair_scan.resolve())
    if files.subject_scan is not None:
        doc["subject"] = {**(doc.get("subject") or {}), "scan": str(files.subject_scan.resolve())}
    directory.mkdir(parents=True, exist_ok=True)
    with atomic_path(directory / "session.json") as tmp:
        tmp.write_text(json.dumps(doc, indent=2), encoding="utf-8")
    return directory


def _head_heights(ss: SessionSync) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The sync's evidence for the report: the cameras' head-top height per frame-table row and
    the suit's head-top height on the Kinect clock."""
    table = ss.kinect.frame_table
    heights = np.full(table.shape, np.nan)
    for c, track in enumerate(ss.tracks):
        have = table[:, c] >= 0
        heights[have, c] = track.top[table[have, c], 1]
    seen = np.isfinite(heights)
    count = seen.sum(axis=1)
    kinect = np.where(count > 0, np.where(seen, heights, 0).sum(axis=1) / np.maximum(count, 1),
                      np.nan)
    if ss.imu is None or ss.imu_clock is None:
        return ss.kinect.time, kinect, np.zeros(0), np.zeros(0)
    t_imu = ss.imu_clock.clock.to_kinect(imu_sample_times(ss.imu))
    return ss.kinect.time, kinect, np.asarray(t_imu), imu_head_top(ss.imu)[:, 1]


def body_result(fit: SessionFit) -> BodyResult:
    """The cacheable part of a session fit."""
    ss = fit.sync
    c = fit.imu_clock
    st, sk, it, ih = _head_heights(ss)
    table = ss.kinect.frame_table[fit.rows]
    points = np.full(len(fit.rows), np.nan)
    points[fit.fitted] = [len(x) for x in fit.clouds]
    return BodyResult(
        time=fit.time, rows=fit.rows, fps=float(1.0 / ss.kinect.period_s),
        betas=np.asarray(fit.betas, np.float32),
        global_orient=np.asarray(fit.fused.global_orient, np.float32),
        body_pose=np.asarray(fit.fused.body_pose, np.float32),
        transl=np.asarray(fit.fused.transl, np.float32), joints=fit.joints,
        fit_joints=np.asarray(fit.fit.joints, np.float32),
        imu_joints=np.asarray(fit.alignment.apply(fit.imu.joint_positions), np.float32),
        fit_chamfer=fit.fit_chamfer, chamfer=fit.chamfer, reliability=fit.reliability,
        fallback=np.asarray(fit.fit.fallback, bool), imu_filled=fit.imu_filled,
        foot_contact=fit.foot_contact, fitted=fit.fitted, points=points,
        cameras_present=table >= 0, camera_serials=[str(t.serial) for t in ss.tracks],
        frame_timestamp_us=np.stack(
            [np.where(table[:, c] >= 0, np.asarray(t.timestamp_us)[np.maximum(table[:, c], 0)], -1)
             for c, t in enumerate(ss.tracks)], axis=1),
        sync_time=st, sync_kinect_height=sk, sync_imu_time=it, sync_imu_height=ih,
        clock_offset_ms=c.clock.offset_s * 1e3, clock_drift_ppm=c.clock.drift_ppm,
        clock_offset_std_ms=c.offset_std_s * 1e3, clock_correlation=c.correlation,
        clock_confident=bool(c.confident), clock_summary=c.summary(),
        heading_deg=fit.alignment.yaw_deg, alignment_residual_m=fit.alignment.residual,
        shape_source=fit.shape_source, summary=fit.summary(), seconds=dict(fit.seconds),
        warnings=list(fit.warnings))


def chair_model(reg: ChairRegistration) -> ChairModel:
    """The registered chair as the capture stage's :class:`ChairModel` (main segment's pose)."""
    return ChairModel(np.asarray(reg.vertices), np.asarray(reg.faces),
                      np.asarray(reg.world_from_object))


def processed_session(name: str, body: BodyResult, chair: ChairRegistration,
                      contacts: Contacts) -> ProcessedSession:
    """Assemble the schema's session; ``/object/frame_poses`` holds the chair's per-row ICP
    estimate where that row was registered (NaN elsewhere)."""
    t = len(body.time)
    frame_poses = np.full((t, 4, 4), np.nan)
    where = {int(r): i for i, r in enumerate(np.asarray(chair.frames))}
    for i, r in enumerate(body.rows):
        j = where.get(int(r))
        if j is not None:
            frame_poses[i] = chair.frame_poses[j]
    quality = {
        "fit_chamfer": body.fit_chamfer.astype(np.float32),
        "chamfer": body.chamfer.astype(np.float32),
        "reliability": body.reliability.astype(np.float32),
        "imu_filled": body.imu_filled,
        "contact_distance": contacts.distance,
        "floor_active": contacts.floor_active,
        "floor_points": contacts.floor_points,
        "frame_rows": body.rows.astype(np.int64),
    }
    return ProcessedSession(
        session=name, fps=body.fps, time=body.time, betas=body.betas,
        global_orient=body.global_orient, body_pose=body.body_pose, transl=body.transl,
        joints=body.joints, object_name=Path(str(chair.scan)).stem if chair.scan else "chair",
        object_vertices=np.asarray(chair.vertices, np.float32),
        object_faces=np.asarray(chair.faces, np.int32),
        object_pose=np.asarray(chair.world_from_object, np.float64),
        object_frame_poses=frame_poses, contact_active=contacts.active,
        contact_points=contacts.points, interaction=contacts.labels,
        contact_names=CONTACT_NAMES, quality=quality)


def parse_frames(text: str | None) -> tuple[int, int] | None:
    """``"start:stop"`` (either end may be empty) → (start, stop) rows; None → None."""
    if text is None or text == "":
        return None
    try:
        a, b = text.split(":")
        start = int(a) if a.strip() else 0
        stop = int(b) if b.strip() else 2**62
    except ValueError:
        raise ProcessError(f"--frames must be START:STOP (frame-table rows), got {text!r}"
                           ) from None
    if start < 0 or stop <= start:
        raise ProcessError(f"--frames {text!r}: need 0 <= START < STOP")
    return start, stop


def parse_stages(stages: str | Sequence[str] | None) -> tuple[str, ...]:
    """Stage names (comma-separated or a list; ``all``/None: every stage), in pipeline order."""
    if stages is None:
        return STAGES
    names = [s.strip() for s in (stages.split(",") if isinstance(stages, str) else stages)]
    names = [s for s in names if s]
    if names == ["all"]:
        return STAGES
    bad = [s for s in names if s not in STAGES]
    if bad or not names:
        raise ProcessError(f"unknown stage(s) {bad or names}; the stages are {', '.join(STAGES)}")
    return tuple(s for s in STAGES if s in names)


# --------------------------------------------------------------------------- the pipeline


#: the stages whose computing starts the worker pool (the chair's and the body's use it)
_POOLED = ("calibrate", "chair", "body")


class _Runner:
    """Runs the stages of one session, each through the cache."""

    def __init__(self, session_dir: Path, output: Path, config: ProcessConfig,
                 stages: tuple[str, ...], frames: tuple[int, int] | None, force: bool,
                 progress: bool, extrinsics: Extrinsics | str | os.PathLike | None,
                 workers: int = 1) -> None:
        self.root, self.out, self.cfg = session_dir, output, config
        self.workers = workers
        self.pool: ProcessPoolExecutor | None = None  # spawned by the first stage that runs
        self.wanted, self.frames, self.force, self.progress = stages, frames, force, progress
        self.given_extrinsics = extrinsics
        self.cache = output / "cache"
        self.result = PipelineResult(session=session_dir, output=output, processed=None,
                                     stages={s: StageRun(s) for s in STAGES}, frames=frames)
        self.files = session_files(session_dir)
        self.view = session_dir  # the folder stages read (a view without dropped cameras)
        self._sync: SessionSync | None = None
        self.keys: dict[str, str] = {}

    # -- cache
    def _cached(self, stage: str, cls: type, key: str) -> Any | None:
        path = self.cache / f"{stage}-{key[:20]}.h5"
        if self.force or not path.is_file():
            return None
        try:
            return read_record(path, cls)
        except RecordError as exc:
            log.warning("ignoring the cached %s result: %s", stage, exc)
            return None

    def _store(self, stage: str, key: str, obj: Any) -> None:
        self.cache.mkdir(parents=True, exist_ok=True)
        for old in self.cache.glob(f"{stage}-*.h5"):
            old.unlink()  # one result per stage: the cache does not grow with every change
        write_record(self.cache / f"{stage}-{key[:20]}.h5", obj)

    def stage(self, name: str, cls: type, key: str, compute: Callable[[], Any]) -> Any:
        """Load ``name``'s result from the cache, or compute (when asked for) and store it."""
        run = self.result.stages[name]
        run.key = key
        self.keys[name] = key
        t0 = wallclock.perf_counter()
        hit = self._cached(name, cls, key)
        if hit is not None:
            run.status, run.seconds = "cached", wallclock.perf_counter() - t0
            run.steps = dict(getattr(hit, "seconds", {}) or {})
            return hit
        if (self.pool is None and self.workers > 1 and name in _POOLED
                and self.wanted[-1] != "calibrate"):
            # spawned with the first of these stages to run (a calibration that runs makes the
            # chair's key new): the workers import the stages' modules (seconds each) while it
            # runs
            self.pool = spawn_pool(self.workers, preload=("couch.fitting.session",),
                                   start=True)
        value = compute()
        run.status, run.seconds = "ran", wallclock.perf_counter() - t0
        run.steps = dict(getattr(value, "seconds", {}) or {})
        self._store(name, key, value)
        return value

    def sync(self, extrinsics: Extrinsics) -> tuple[SessionSync, float]:
        """The session synchronised (once per run) and the seconds this call took."""
        t0 = wallclock.perf_counter()
        if self._sync is None:
            self._sync = sync_session(
                self.view, extrinsics=extrinsics,
                depth_binning=self.cfg.fit.depth_binning, progress=self.progress,
                pool=self.pool)
        return self._sync, wallclock.perf_counter() - t0

    # -- stages
    def calibrate(self) -> CalibrationResult:
        given = self.given_extrinsics
        key = stage_key("calibrate", None, [self.files.manifest, *_camera_inputs(self.files),
                                            Path(given) if isinstance(given, (str, os.PathLike))
                                            else None],
                        [], extra=None if given is None or isinstance(given, (str, os.PathLike))
                        else json.dumps({k: np.asarray(v.world_from_depth).tolist()
                                         for k, v in given.cameras.items()}))

        def compute() -> CalibrationResult:
            warnings: list[str] = []
            keep: list[str] = []
            dropped: list[tuple[str, str]] = []
            for cam in self.files.cameras:
                why, notes = _camera_problem(cam.recording)
                warnings += notes
                if why is None:
                    keep.append(cam.serial)
                else:
                    dropped.append((cam.serial, why))
                    warnings.append(f"camera {cam.serial} left out: {why}")
            if not keep:
                raise _StageFault("calibrate", f"{self.root}: no camera recording can be read ("
                                  + "; ".join(w for _, w in dropped) + ")")
            self._view(keep)
            if dropped:
                try:  # the dropped cameras' board captures may link the others
                    ext = calibrate_session(session_view(
                        self.files, keep, self.cache / "calibration_view", calibration=True),
                        given=given)
                except ValueError:
                    ext = calibrate_session(self.view, given=given)
            else:
                ext = calibrate_session(self.view, given=given)
            self.cache.mkdir(parents=True, exist_ok=True)
            write_extrinsics(self.cache / "extrinsics.json", ext)  # extrinsics() reads it back
            return CalibrationResult(cameras=keep, dropped=dropped,
                                     extrinsics_json=(self.cache / "extrinsics.json").read_text(
                                         encoding="utf-8"),
                                     warnings=warnings)

        cal = self.stage("calibrate", CalibrationResult, key, compute)
        self._view(cal.cameras)
        return cal

    def _view(self, keep: Sequence[str]) -> Path:
        if list(keep) == [c.serial for c in self.files.cameras]:
            self.view = self.root
        else:
            self.view = session_view(self.files, keep, self.cache / "session_view")
        return self.view

    def extrinsics(self, cal: CalibrationResult) -> Extrinsics:
        """The calibration's poses, through ``cache/extrinsics.json`` (rewritten from the
        record when the stage came from the cache)."""
        path = self.cache / "extrinsics.json"
        if not path.is_file() or path.read_text(encoding="utf-8") != cal.extrinsics_json:
            self.cache.mkdir(parents=True, exist_ok=True)
            with atomic_path(path) as tmp:
                tmp.write_text(cal.extrinsics_json, encoding="utf-8")
        return read_extrinsics(path)

    def chair(self, ext: Extrinsics) -> ChairRegistration:
        scan = session_scan_path(self.view)
        key = stage_key("chair", (self.cfg.chair, self.cfg.chair_frames, self.cfg.fit.segmentation,
                                  self.cfg.fit.cloud),
                        [scan, *_camera_inputs(self.files)], [self.keys["calibrate"]])

        def compute() -> ChairRegistration:
            the_scan = load_scan(scan, self.cfg.chair)  # a bad scan fails before the sync
            ss, sync_s = self.sync(ext)
            t0 = wallclock.perf_counter()
            # the whole session whatever --frames says: the chair is static, and more frames
            # average better and find a move (a frame range re-uses the cached chair)
            rows = np.arange(len(ss.kinect.time))
            if 0 < self.cfg.chair_frames < len(rows):
                rows = rows[np.unique(np.linspace(0, len(rows) - 1, self.cfg.chair_frames)
                                      .round().astype(int))]
            clouds = chair_clouds(self.view, ext, frames=rows, kinect=ss.kinect,
                                  tracks=ss.tracks, config=self.cfg.chair,
                                  segmentation=self.cfg.fit.segmentation, cloud=self.cfg.fit.cloud,
                                  progress=self.progress, pool=self.pool)
            took = wallclock.perf_counter() - t0
            reg = register_chair(the_scan, clouds, config=self.cfg.chair, progress=self.progress)
            reg.seconds = {"sync": sync_s, "clouds": took, **reg.seconds}
            reg.warnings = clouds.warnings + reg.warnings
            if reg.moved:
                reg.warnings.append(f"the chair moved: {len(reg.segments)} static periods; the "
                                    f"pose of the longest is the session's")
            return reg

        return self.stage("chair", ChairRegistration, key, compute)

    def body(self, ext: Extrinsics, chair: ChairRegistration) -> BodyResult:
        files = session_files(self.view)
        cfg = dataclasses.replace(self.cfg.fit, body=dataclasses.replace(
            self.cfg.fit.body, device=self.cfg.device))
        key = stage_key("body", cfg, [files.mvnx, files.subject_scan, *_camera_inputs(files)],
                        [self.keys["calibrate"], self.keys["chair"]], extra=self.frames)

        def compute() -> BodyResult:
            ss, sync_s = self.sync(ext)
            fit = fit_session(self.view, extrinsics=ext, chair=chair_model(chair), sync=ss,
                              frames=self.frames, config=cfg, progress=self.progress,
                              pool=self.pool, threads=self.workers)
            fit.seconds["sync"] = sync_s  # 0 when the chair stage synchronised
            return body_result(fit)

        return self.stage("body", BodyResult, key, compute)

    def contacts(self, body: BodyResult, chair: ChairRegistration) -> Contacts:
        key = stage_key("contacts", (self.cfg.contacts, self.cfg.contact_model), [],
                        [self.keys["body"], self.keys["chair"]])

        def compute() -> Contacts:
            model = cached_model(self.cfg.contact_model, "cpu", self.cfg.fit.body.dtype)
            return detect_contacts(body.params, model, chair_model(chair), fps=body.fps,
                                   config=self.cfg.contacts)

        return self.stage("contacts", Contacts, key, compute)

    def run(self) -> PipelineResult:
        res = self.result
        t_start = wallclock.perf_counter()
        last = self.wanted[-1]
        bar = tqdm(total=STAGES.index(last) + 1, desc=f"couch-process {self.root.name}",
                   unit="stage", disable=not self.progress, leave=False)
        current = "calibrate"
        try:
            current = "calibrate"
            bar.set_postfix_str(current)
            res.calibration = self.calibrate()
            res.warnings += [f"calibrate: {w}" for w in res.calibration.warnings]
            res.extrinsics = self.extrinsics(res.calibration)
            bar.update()
            if last != "calibrate":
                current = "chair"
                bar.set_postfix_str(current)
                res.chair = self.chair(res.extrinsics)
                res.warnings += [f"chair: {w}" for w in res.chair.warnings]
                bar.update()
            if last in ("body", "contacts"):
                current = "body"
                bar.set_postfix_str(current)
                res.body = self.body(res.extrinsics, res.chair)
                res.warnings += res.body.warnings  # already named by step (sync:, fit:, ...)
                bar.update()
            if last == "contacts":
                current = "contacts"
                bar.set_postfix_str(current)
                res.contacts = self.contacts(res.body, res.chair)
                bar.update()
                name = json.loads(self.files.manifest.read_text()).get("name", self.root.name) \
                    if self.files.manifest else self.root.name
                res.data = processed_session(name, res.body, res.chair, res.contacts)
                res.processed = self.out / PROCESSED_NAME
                write_processed(res.processed, res.data)
        except _StageFault as exc:
            self._fail(exc.stage, exc.message)
        except (ValueError, OSError, RecordError) as exc:
            # the stages' format / layout / registration errors (all ValueError subclasses)
            # name the file: that message is the fault
            self._fail(current, str(exc))
        except BrokenProcessPool as exc:
            self._fail(current, f"a worker process died ({exc}): out of memory, or a script "
                                f"that calls couch.process without `if __name__ == "
                                f"'__main__':` (workers are spawned and import the script); "
                                f"workers=1 (--workers 1) runs everything in this process")
        except Exception as exc:  # a bug: keep the traceback for the report, not on the console
            res.traceback = traceback.format_exc()
            self._fail(current, f"internal error ({type(exc).__name__}: {exc}); the traceback "
                                f"is in the report")
        finally:
            bar.close()
            if self.pool is not None:
                self.pool.shutdown(cancel_futures=True)
                self.pool = None
        res.seconds = wallclock.perf_counter() - t_start
        return res

    def _fail(self, stage: str, message: str) -> None:
        run = self.result.stages[stage]
        run.status, run.error = "failed", message
        self.result.fault = (stage, message)
        log.error("%s stage failed: %s", stage, message)


class _StageFault(Exception):
    def __init__(self, stage: str, message: str) -> None:
        super().__init__(f"{stage}: {message}")
        self.stage, self.message = stage, message


def run_pipeline(session_dir: str | os.PathLike, output: str | os.PathLike | None = None, *,
                 stages: str | Sequence[str] | None = None,
                 frames: str | tuple[int, int] | None = None,
                 device: str | None = None, config: ProcessConfig | None = None,
                 extrinsics: Extrinsics | str | os.PathLike | None = None, force: bool = False,
                 progress: bool = False, workers: int | None = None) -> PipelineResult:
    """Run the pipeline's stages on a session folder (see the module doc).

    Args:
        session_dir: the raw session (:func:`couch.capture.session.session_files` layout).
        output: the output folder (``processed.h5``, ``cache/``); None: ``<session>/processed``.
        stages: how far to go: the run stops after the last stage named (comma-separated or
            a list; None/``all``: every stage). Every stage up to it is loaded from the cache
            when its inputs and config are unchanged, else computed.
        frames: ``(start, stop)`` rows of the Kinect frame table, or ``"start:stop"``.
        device: torch device of the fits (overrides ``config.device``).
        config: :class:`ProcessConfig`.
        extrinsics: camera poses to use instead of calibrating (an :class:`Extrinsics` or an
            ``extrinsics.json``).
        force: ignore the cache (results are still written to it).
        progress: progress bars.
        workers: processes for the work that splits by camera or by frame (the cameras'
            passes over their recordings, segmentation, the fits, their chamfers and
            reliability), spawned when calibrate, chair or body first has to run; 1: all in
            this process; None: ``min(2, CPU count)``. The results (and cache keys) do not
            depend on it.

    Returns:
        :class:`PipelineResult`; check ``ok`` / ``fault``. Only bad arguments raise.

    Raises:
        ProcessError: the session folder does not exist, an unknown stage, a bad frame range,
            ``workers`` < 1.
    """
    root = Path(session_dir)
    if not root.is_dir():
        raise ProcessError(f"{root}: no such session folder")
    cfg = config or ProcessConfig()
    if device is not None:
        cfg = dataclasses.replace(cfg, device=device)
    rng = parse_frames(frames) if isinstance(frames, str) or frames is None else tuple(frames)
    out = Path(output) if output is not None else root / "processed"
    workers = min(2, os.cpu_count() or 1) if workers is None else int(workers)
    if workers < 1:
        raise ProcessError(f"workers must be >= 1, got {workers}")
    try:
        runner = _Runner(root, out, cfg, parse_stages(stages), rng, force, progress,  # type: ignore[arg-type]
                         extrinsics, workers)
    except ValueError as exc:  # session.json unreadable
        res = PipelineResult(session=root, output=out, processed=None,
                             stages={s: StageRun(s) for s in STAGES})
        res.fault = ("calibrate", str(exc))
        res.stages["calibrate"].status, res.stages["calibrate"].error = "failed", str(exc)
        return res
    return runner.run()
