"""The body of a whole session: sync, person clouds, IMU-initialised fits, sequence fusion.

:func:`fit_session` chains the stages of issue 7 on a session folder:

1. **cameras and clock** — :func:`couch.sync.sync_session`: every camera's frames on the Kinect
   master clock (rows of the frame table), the IMU clock from the head top, the suit's poses
   resampled (slerp) at the rows' times;
2. **person clouds** — every camera's recording segmented (:func:`couch.capture.segmentation.
   segment_recording`, with the registered chair when given) and its person lifted to world
   points (:func:`couch.capture.camera_clouds.camera_clouds`, the cameras spread over a pool
   of worker processes when given one), then joined per row; a camera that dropped a row just
   adds nothing to it;
3. **IMU world → camera world** — MVN has its own heading and horizontal origin
   (:mod:`couch.capture.imu`). :func:`align_imu` finds the rotation about +Y and the
   translation that put the suit's body onto the clouds: a search over headings (every
   ``yaw_step_deg``, then finer) scoring how well the posed IMU body explains the clouds of a
   few frames, each with its best translation;
4. **subject shape** — from the subject scan when the session has one
   (:func:`couch.fitting.shape.fit_betas_to_scan`), else fitted over frames of the session
   (:func:`couch.fitting.shape.fit_shape`);
5. **per-frame fits** — :func:`couch.fitting.body.fit_bodies`, initialised from the aligned IMU
   pose (on every ``SessionFitConfig.fit_stride``-th row: steps 2-6 run on those rows only);
   then the alignment is refined on the fitted joints (every joint of every reliable frame, so
   the heading is settled by the body's own orientation) and, optionally, the IMU clock on the
   fitted joints (:func:`couch.sync.refine_imu`);
6. **reliability** — per frame and joint (:func:`fit_reliability`): a fit counts where its
   chamfer is small and, per joint, where the body surface that faces a camera there is
   actually backed by cloud points (a limb hidden behind the chair or cut away with it is not);
7. **fusion** — :func:`couch.fitting.fusion.fuse_motion` (COUCH Eq. 7–8) with the IMU's foot
   contacts.

Rows fitted: from the first to the last row at which the suit's pose could be resampled (no
extrapolation); rows inside that span that the IMU lost (gaps) keep the nearest valid IMU pose
as the initial guess and are counted. Units: metres, seconds (Kinect master clock), world frame
of the extrinsics (Y up, floor at y = 0 after :func:`couch.capture.calibration.
level_with_floor`).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from couch.body import BodyModel
from couch.capture.calibration import Extrinsics, calibrate_session
from couch.capture.camera_clouds import camera_clouds, join_row
from couch.capture.depth_bias import unmeasured_warnings
from couch.capture.pointcloud import CloudConfig, FusedCloud
from couch.capture.segmentation import (
    ChairModel,
    SegmentationConfig,
    empty_room_recording,
)
from couch.capture.session import session_files
from couch.fitting.body import BodyFit, BodyFitConfig, cached_model, fit_bodies
from couch.fitting.clouds import cloud_arrays
from couch.fitting.fusion import FusionConfig, fuse_motion
from couch.fitting.metrics import CameraView, occluder_scene, surface_distances
from couch.fitting.params import BodyParams
from couch.fitting.shape import ShapeFitConfig, fit_betas_to_scan, fit_shape
from couch.geometry import apply_transform, vertex_normals
from couch.pool import Pool, pool_map
from couch.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from couch.sync import (
    CameraTrack,
    ClockEstimate,
    KinectSync,
    ResampledImu,
    SessionSync,
    SyncError,
    refine_imu,
    resample_imu,
    sync_session,
)

__all__ = [
    "SessionFit",
    "SessionFitConfig",
    "SessionFitError",
    "WorldAlignment",
    "align_imu",
    "fit_reliability",
    "fit_session",
    "imu_body_params",
    "refine_alignment",
    "session_clouds",
]

log = logging.getLogger(__name__)


class SessionFitError(ValueError):
    """The session cannot be fitted (the message names the session and why)."""


@dataclasses.dataclass(frozen=True)
class SessionFitConfig:
    """Knobs of :func:`fit_session` (lengths in metres, angles in degrees).

    Attributes:
        body, shape, fusion: the stages' own configs.
        cloud, segmentation: the capture stage's (None: their defaults).
        align_frames: frames (those with the most points) the heading search scores.
        align_points: cloud points per frame in that search.
        yaw_step_deg: coarse heading step of the search (then refined to 1/10 of it).
        refine_clock: re-estimate the IMU clock on the fitted joints and resample again (off:
            on a 10 s simulated session it moved the head-top estimate's -0.2 ms error to
            -1.1 ms; the drift is not observable over so short a lever either way).
        good_chamfer, bad_chamfer: a frame's fit is fully reliable at or below the first
            chamfer, unreliable (weight 0) at or above the second, linear between.
        support_distance: a camera-facing body vertex is "backed" by the cloud when a point
            lies within this distance.
        min_support, full_support: a joint's reliability goes from 0 to 1 as the backed
            fraction of its camera-facing vertices goes from the first to the second.
        fuse: run the sequence fusion (else the result's ``fused`` is the per-frame fit).
        error_model: the body model (same parameters) whose surface the chamfers and the
            joints' point support are measured on. The coarse one is ~2.5x faster to measure
            but its chords cut inside the surface: its chamfers were 0.1-0.15 cm above the full
            model's on simulated sessions.
        snap_init: start the shape and per-frame fits from the aligned suit moved, frame by
            frame, onto its cloud (:func:`snap_to_clouds`) instead of where the one alignment
            of the session puts it.
        fit_stride: fit the cameras on every ``fit_stride``-th row (and the last); the fusion
            carries the suit's motion between them, with the bias the fits measured around
            (those rows have reliability 0). The person clouds, fits, chamfers and the fused
            motion's chamfer are computed on the fitted rows only, so the per-frame work
            shrinks about ``fit_stride`` times; the fusion still runs on every row.
    """

    body: BodyFitConfig = dataclasses.field(default_factory=BodyFitConfig)
    shape: ShapeFitConfig = dataclasses.field(default_factory=ShapeFitConfig)
    fusion: FusionConfig = dataclasses.field(default_factory=FusionConfig)
    cloud: CloudConfig | None = None
    segmentation: SegmentationConfig | None = None
    align_frames: int = 6
    align_points: int = 800
    yaw_step_deg: float = 10.0
    refine_clock: bool = False
    good_chamfer: float = 0.02
    bad_chamfer: float = 0.05
    support_distance: float = 0.03
    min_support: float = 0.15
    full_support: float = 0.5
    fuse: bool = True
    error_model: str = "couch-body"
    snap_init: bool = True
    fit_stride: int = 1

    def __post_init__(self) -> None:
        if not (isinstance(self.fit_stride, int) and self.fit_stride >= 1):
            raise ValueError(f"SessionFitConfig.fit_stride must be an integer >= 1, got "
                             f"{self.fit_stride!r}")

    @property
    def depth_binning(self) -> int:
        """How the depth is read (``SegmentationConfig.depth_binning``; 1 without one)."""
        return (self.segmentation or SegmentationConfig()).depth_binning


@dataclasses.dataclass(frozen=True)
class WorldAlignment:
    """The IMU's world in the cameras' world: ``p_world = R_y(yaw) · p_imu + translation``.

    Attributes:
        yaw_deg: rotation about +Y (degrees).
        translation: (3,) metres.
        residual: median distance (m) of the evidence used (cloud points to the posed body, or
            fitted to IMU joints) after alignment.
        method: ``clouds`` (heading search) or ``joints`` (refined on fitted joints).
    """

    yaw_deg: float
    translation: np.ndarray
    residual: float
    method: str

    @property
    def rotation(self) -> np.ndarray:
        """(3,3) world-from-IMU rotation."""
        return _yaw_matrix(np.deg2rad(self.yaw_deg))

    @property
    def world_from_imu(self) -> np.ndarray:
        """(4,4) homogeneous transform."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.rotation, self.translation
        return m

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(...,3) IMU-world points → world."""
        return np.asarray(points, np.float64) @ self.rotation.T + self.translation


@dataclasses.dataclass
class SessionFit:
    """A session's body motion. T = fitted rows of the frame table.

    Attributes:
        session: the session folder.
        sync: the sync stage's result (clock as first estimated from the head top).
        imu_clock: the IMU clock used in the end (refined on the fitted joints when
            ``refine_clock``).
        rows: (T,) rows of ``sync.kinect.frame_table`` fitted.
        time: (T,) Kinect master-clock seconds of those rows.
        fitted: (T,) bool, the rows the cameras were fitted on (every row unless
            ``SessionFitConfig.fit_stride`` > 1); K of them.
        clouds: K fused person clouds (world), one per fitted row.
        views: the C depth cameras (:class:`~couch.fitting.metrics.CameraView`, world).
        imu: the suit's poses at ``time`` (:class:`~couch.sync.ResampledImu`, IMU world).
        imu_filled: (T,) bool, rows where the IMU had no sample (a gap) and the nearest
            valid pose stands in.
        alignment: IMU world → world, refined on the fitted joints.
        imu_params: the IMU pose in the world with the subject's shape (the fits' start).
        betas: (10,) the subject's shape; shape_source: ``scan`` or ``clouds``.
        fit: the per-frame fits (:class:`~couch.fitting.body.BodyFit`, T frames: a row not
            fitted holds the suit's pose in ``params`` and NaN ``joints`` and errors).
        fit_chamfer: (T,) metres, symmetric chamfer of each per-frame fit to its cloud, the
            body surface counted where a camera could see it (in its image, not hidden by the
            body or the chair); NaN for fallback frames and rows not fitted.
        reliability: (T,24) the fits' weights in the fusion (0 on rows not fitted).
        foot_contact: (T,4) the IMU's heel/toe contacts (``FOOT_KEYPOINTS`` order).
        fused: the fused motion (or the per-frame fit when fusion was off).
        joints: (T,24,3) world joints of ``fused`` (full model).
        chamfer: (T,) metres, the same chamfer for ``fused`` (NaN: no points, or a row not
            fitted).
        seconds: wall time per stage.
        warnings: what may be wrong (named by stage).
        init_shift: (K,3) metres each fitted row's start was moved onto its cloud
            (:func:`snap_to_clouds`; zeros with ``snap_init`` off).
    """

    session: Path
    sync: SessionSync
    imu_clock: ClockEstimate
    rows: np.ndarray
    time: np.ndarray
    fitted: np.ndarray
    clouds: list[FusedCloud]
    views: list[CameraView]
    imu: ResampledImu
    imu_filled: np.ndarray
    alignment: WorldAlignment
    imu_params: BodyParams
    betas: np.ndarray
    shape_source: str
    fit: BodyFit
    fit_chamfer: np.ndarray
    reliability: np.ndarray
    foot_contact: np.ndarray
    fused: BodyParams
    joints: np.ndarray
    chamfer: np.ndarray
    seconds: dict[str, float]
    warnings: list[str]
    init_shift: np.ndarray | None = None

    def summary(self) -> str:
        """A few lines: what was fitted and how well."""
        c = self.imu_clock.clock
        k = int(np.count_nonzero(self.fitted))
        lines = [
            f"{self.session}: {len(self.rows)} frames "
            f"({self.time[0]:.3f}-{self.time[-1]:.3f} s)"
            + ("" if k == len(self.rows) else f", the cameras fitted on {k} of them")
            + f", {len(self.views)} cameras, "
            f"{np.mean([len(x) for x in self.clouds]):.0f} person points per frame",
            f"IMU clock: offset {c.offset_s * 1e3:+.2f} ms, drift {c.drift_ppm:+.1f} ppm; "
            f"heading {self.alignment.yaw_deg:+.1f} deg ({self.alignment.method}, residual "
            f"{self.alignment.residual * 100:.1f} cm); {int(self.imu_filled.sum())} rows in "
            f"IMU gaps" + ("" if self.init_shift is None else
                           f"; the fits' starts moved {_cm_median(self.init_shift)} "
                           f"onto the clouds"),
            f"shape from {self.shape_source}; chamfer per-frame fit "
            f"{np.nanmean(self.fit_chamfer) * 100:.2f} cm, fused "
            f"{np.nanmean(self.chamfer) * 100:.2f} cm; {int(self.fit.fallback.sum())} "
            f"fallback frames; mean reliability {self.reliability[self.fitted].mean():.2f}",
            "time: " + ", ".join(f"{k} {v:.1f} s" for k, v in self.seconds.items()),
        ]
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


# --------------------------------------------------------------------------- helpers


def _cm_median(shift: np.ndarray) -> str:
    n = np.linalg.norm(shift, axis=-1)
    return f"{np.median(n) * 100:.1f} cm (median; largest {n.max() * 100:.1f} cm)"


def _shifted(params: BodyParams, shift: np.ndarray) -> BodyParams:
    """``params`` with each frame's translation moved by ``shift`` (T,3) metres."""
    return dataclasses.replace(params, transl=(params.transl + shift).astype(params.transl.dtype))


def _yaw_matrix(yaw: np.ndarray | float) -> np.ndarray:
    """(...,3,3) rotations about +Y by ``yaw`` radians."""
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1),
                     np.stack([-s, z, c], -1)], -2)


def pose_body(model: BodyModel, params: BodyParams, batch: int = 64
              ) -> tuple[np.ndarray, np.ndarray]:
    """(T,V,3) vertices and (T,24,3) joints (world metres) of ``params`` posed by ``model``
    (no grad, float64 out; ``batch`` frames at a time bound the memory)."""
    verts, joints = [], []
    for a in range(0, params.num_frames, batch):
        sl = slice(a, a + batch)
        with torch.no_grad():
            out = model(betas=params.betas[None], global_orient=params.global_orient[sl],
                        body_pose=params.body_pose[sl], transl=params.transl[sl])
        verts.append(out.vertices.cpu().numpy().astype(np.float64))
        joints.append(out.joints.cpu().numpy().astype(np.float64))
    return np.concatenate(verts), np.concatenate(joints)


def _rest_pelvis(model: BodyModel, betas: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return model.rest_joints(torch.as_tensor(betas[None], dtype=model.dtype)
                                 )[0, 0].cpu().numpy().astype(np.float64)


def imu_body_params(imu: ResampledImu, alignment: WorldAlignment | None, betas: np.ndarray,
                    model: BodyModel, rows: np.ndarray | None = None) -> BodyParams:
    """The suit's pose as SMPL parameters in the world.

    Args:
        imu: resampled suit poses (IMU world); every selected row must be valid.
        alignment: IMU world → world (None: identity).
        betas: (10,) the subject's shape (sets where the pelvis joint sits in the rest pose).
        model: the body model (its rest pelvis for ``transl``).
        rows: rows of ``imu`` to take (default all).

    Returns:
        :class:`BodyParams`: the pelvis orientation turned by the alignment, the local joint
        rotations as measured, ``transl`` putting the model's pelvis joint on the suit's.
    """
    sel = np.arange(len(imu.time)) if rows is None else np.asarray(rows)
    rot = np.eye(3) if alignment is None else alignment.rotation
    root = rot @ axis_angle_to_matrix(imu.global_orient[sel].astype(np.float64))
    pelvis = imu.joint_positions[sel, 0].astype(np.float64)
    if alignment is not None:
        pelvis = alignment.apply(pelvis)
    transl = pelvis - _rest_pelvis(model, np.asarray(betas, np.float64))
    return BodyParams(matrix_to_axis_angle(root), imu.body_pose[sel], transl,
                      np.asarray(betas, np.float32))


def _fill_gaps(valid: np.ndarray) -> np.ndarray:
    """(T,) index of the nearest valid row for every row (valid rows map to themselves)."""
    ok = np.flatnonzero(valid)
    pos = np.clip(np.searchsorted(ok, np.arange(len(valid))), 1, len(ok) - 1) if len(ok) > 1 \
        else np.zeros(len(valid), int)
    if len(ok) == 1:
        return np.full(len(valid), ok[0])
    left, right = ok[pos - 1], ok[pos]
    rows = np.arange(len(valid))
    return np.where(rows - left <= right - rows, left, right)


def _spread_rows(values: np.ndarray, keys: np.ndarray, t: int, fill: float | bool
                 ) -> np.ndarray:
    """(T,...) ``values`` (K,...) of the rows ``keys`` (indices into T), ``fill`` elsewhere."""
    values = np.asarray(values)
    if len(keys) == t:
        return values
    out = np.full((t, *values.shape[1:]), fill, dtype=values.dtype)
    out[keys] = values
    return out


def _spread(fit: BodyFit, keys: np.ndarray, filler: BodyParams) -> BodyFit:
    """``fit`` of the rows ``keys`` over all T rows of ``filler`` (T frames): a row between
    holds ``filler``'s pose, NaN joints and errors, no points, and is not a fallback."""
    t = filler.num_frames
    if len(keys) == t:
        return fit

    def put(theirs: np.ndarray, mine: np.ndarray) -> np.ndarray:
        out = np.array(theirs, dtype=mine.dtype)
        out[keys] = mine
        return out

    params = BodyParams(put(filler.global_orient, fit.params.global_orient),
                        put(filler.body_pose, fit.params.body_pose),
                        put(filler.transl, fit.params.transl), fit.params.betas)
    return dataclasses.replace(
        fit, params=params, joints=_spread_rows(fit.joints, keys, t, np.nan),
        chamfer=_spread_rows(fit.chamfer, keys, t, np.nan),
        to_surface=_spread_rows(fit.to_surface, keys, t, np.nan),
        to_points=_spread_rows(fit.to_points, keys, t, np.nan),
        num_points=_spread_rows(fit.num_points, keys, t, 0),
        fallback=_spread_rows(fit.fallback, keys, t, False))


def _chamfers(model: tuple[str, str, str], params: BodyParams, clouds: Sequence[FusedCloud],
              views: Sequence[CameraView], present: np.ndarray,
              occluders: tuple[np.ndarray, np.ndarray] | None, samples: tuple[int, int],
              pool: Pool = None, chunk: int = 25, *, fallback: np.ndarray | None = None,
              reliability: SessionFitConfig | None = None
              ) -> tuple[np.ndarray, np.ndarray | None]:
    """(T,) chamfer of ``params`` posed by ``model`` (:func:`cached_model`'s name, device,
    dtype) to their clouds, the surface counted where one of the cameras that recorded the
    frame (``present`` (T,C)) could see it; NaN: no points. With ``reliability`` (a config),
    also the (T,24) :func:`fit_reliability` weights of the same posed meshes, the chamfer NaN
    where ``fallback`` (T,). ``samples``: the surface samples of the surface → points half
    and the cloud points of the points → surface half (``error_samples``, ``error_points``):
    the surface → points half searches the whole cloud (a subsampled one would leave the
    surface farther from its nearest point and raise it). Frame t's samples are seeded with
    t, and each run of ``chunk`` frames poses its own meshes (a worker is sent parameters, not
    vertices), so ``pool`` changes nothing but the time."""
    pts = [cloud_arrays(c)[0] for c in clouds]
    t = params.num_frames
    fallback = np.zeros(t, bool) if fallback is None else np.asarray(fallback, bool)
    tasks = [(model, params.frames(slice(s, s + chunk)), pts[s:s + chunk], views,
              present[s:s + chunk], occluders, samples, s, fallback[s:s + chunk], reliability)
             for s in range(0, t, chunk)]
    out = pool_map(pool, _chamfer_run, tasks)
    chamfer = np.concatenate([np.zeros(0), *(c for c, _ in out)])
    if reliability is None:
        return chamfer, None
    return chamfer, np.concatenate([np.zeros((0, 24)), *(r for _, r in out)])


def _chamfer_run(model: tuple[str, str, str], params: BodyParams, points: Sequence[np.ndarray],
                 views: Sequence[CameraView], present: np.ndarray,
                 occluders: tuple[np.ndarray, np.ndarray] | None, samples: tuple[int, int],
                 first: int, fallback: np.ndarray, reliability: SessionFitConfig | None
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`_chamfers` of frames ``first, first + 1, ...`` (a pool task)."""
    body = cached_model(*model)
    verts = pose_body(body, params)[0]
    low = verts.astype(np.float32)
    out = np.full(len(verts), np.nan)
    scene = occluder_scene(occluders) if occluders is not None else None
    # each cloud's k-d tree once, for the chamfer and the reliability
    trees = [cKDTree(np.asarray(p, np.float32)) if len(p) else None for p in points]
    for k, p in enumerate(points):
        seen = [v for v, ok in zip(views, present[k], strict=True) if ok]
        if len(p) and seen:
            out[k] = surface_distances(low[k], body.faces, p, visible_from=seen,
                                       occluders=scene, samples=samples[0], seed=first + k,
                                       max_points=samples[1], tree=trees[k]).chamfer
    if reliability is None:
        return out, None
    out[fallback] = np.nan
    seg = body.weights.cpu().numpy().argmax(1)
    return out, _reliability_run(verts, body.faces, seg, points, views,
                                 _frame_weights(out, fallback, reliability), reliability,
                                 trees)


# --------------------------------------------------------------------------- clouds


def session_clouds(session_dir: str | os.PathLike, extrinsics: Extrinsics | dict[str, np.ndarray],
                   kinect: KinectSync, tracks: Sequence[CameraTrack], rows: np.ndarray, *,
                   chair: ChairModel | None = None,
                   segmentation: SegmentationConfig | None = None,
                   cloud: CloudConfig | None = None, progress: bool = False,
                   pool: Pool = None
                   ) -> tuple[list[FusedCloud], list[CameraView], list[str]]:
    """Person clouds at rows of the frame table.

    Every camera's frames at these rows are segmented (background from its empty-room
    recording when the session has one, else its calibration capture and its own frames), its
    systematic depth error measured on the floor of those frames and taken out
    (``cloud.depth_bias``, :mod:`couch.capture.depth_bias`), then each row's frames are fused.
    A camera's frame is found by its timestamp (the frame table indexes each camera's frame
    list, ``tracks[c].timestamp_us``).

    Args:
        session_dir: the session.
        extrinsics: camera poses (:class:`Extrinsics` or serial → (4,4) world_from_depth).
        kinect: the cameras on the master clock (``SessionSync.kinect``).
        tracks: the per-camera tracks it was synced from (``SessionSync.tracks``).
        rows: (T,) rows of ``kinect.frame_table``.
        chair: the registered chair (its points are kept out of the person), or None.
        segmentation, cloud: capture-stage configs.
        progress: progress bars.
        pool: where the cameras' recordings are segmented and lifted to points
            (:func:`couch.capture.camera_clouds.camera_clouds`, one camera per task,
            :func:`couch.pool.spawn_pool`); None: one after another here. The clouds are the
            same either way.

    Returns:
        (T clouds, the C cameras' :class:`~couch.fitting.metrics.CameraView` s (world),
        warnings: skipped captures per camera, cameras whose depth error was not measured).
    """
    files = session_files(session_dir)
    cloud = cloud or CloudConfig()
    rows = np.asarray(rows)
    by_serial = {t.serial: t.timestamp_us for t in tracks}
    track_stamps = [np.asarray(by_serial[s]) for s in kinect.serials]
    tasks = []
    for c, serial in enumerate(kinect.serials):
        cam = files.camera(serial)
        if cam is None or cam.recording is None:
            raise SessionFitError(f"{files.root}: the sync stage read camera {serial} but the "
                                  f"session has no recording for it")
        pose = (extrinsics.world_from_depth(serial) if isinstance(extrinsics, Extrinsics)
                else np.asarray(extrinsics[serial], np.float64))
        k = kinect.frame_table[rows, c]
        tasks.append(dict(recording=cam.recording, world_from_depth=pose,
                          empty_room=empty_room_recording(files.root, serial),
                          background_paths=[p for p in (cam.calibration_capture,)
                                            if p is not None],
                          chair=chair, segmentation=segmentation, cloud=cloud,
                          timestamps=track_stamps[c][k[k >= 0]]))
    parts = pool_map(pool, camera_clouds, tasks,
                     desc="segmentation" if progress else None, unit="camera")
    warnings = [f"{p.recording}: {p.skipped} capture(s) without usable depth skipped"
                for p in parts if p.skipped]
    if cloud.depth_bias:
        warnings += unmeasured_warnings(kinect.serials, [p.depth_bias for p in parts])
    clouds = [join_row(parts, kinect.frame_table[r], track_stamps, float(kinect.time[r]))
              for r in rows]
    views = [CameraView(p.world_from_depth, p.calibration.depth, p.background,
                        depth_range=p.depth_range,
                        max_incidence_deg=80.0) for p in parts]
    return clouds, views, warnings


# --------------------------------------------------------------------------- alignment


def align_imu(clouds: Sequence[FusedCloud], imu_params: BodyParams, model: BodyModel, *,
              frames: int = 6, points: int = 800, step_deg: float = 10.0, seed: int = 0,
              threads: int = 1) -> WorldAlignment:
    """The rotation about +Y and translation taking the IMU's world onto the clouds'.

    The suit's body (``imu_params``: IMU world, any shape) is posed in the ``frames`` frames
    with the most points. For every heading on a ``step_deg`` grid (then a finer grid around
    the best), the translation is found by a few robust nearest-neighbour steps (median of the
    residuals of cloud points to the body's vertices) and the heading is scored by the mean
    truncated distance (10 cm) of the points to the body. The motion of the body does not need
    to be large: the body's own shape and orientation decide. ``threads``: headings scored at
    once (the k-d tree queries, their time, release the GIL); the same result with any.

    Raises:
        SessionFitError: no frame has points.
    """
    counts = np.array([len(cloud_arrays(c)[0]) for c in clouds])
    if not counts.any():
        raise SessionFitError("no frame has person points: the IMU cannot be aligned")
    use = np.argsort(-counts, kind="stable")[:frames]
    use = use[counts[use] > 0]
    verts, _ = pose_body(model, imu_params.frames(use))
    rng = np.random.default_rng(seed)
    trees, pts = [], []
    for k, i in enumerate(use):
        p = cloud_arrays(clouds[i])[0].astype(np.float64)
        if len(p) > points:
            p = p[rng.choice(len(p), points, replace=False)]
        pts.append(p)
        trees.append(cKDTree(verts[k]))
    all_pts = np.concatenate(pts)
    centre_body = verts.reshape(-1, 3).mean(0)

    def score(yaw: float) -> tuple[float, np.ndarray]:
        rot = _yaw_matrix(yaw)
        # start with the body's centre on the points' centre, then robust ICP steps on t only
        t = _median_steps(trees, pts, rot, all_pts.mean(0) - rot @ centre_body)
        d = np.concatenate([tree.query((p - t) @ rot)[0] for tree, p in
                            zip(trees, pts, strict=True)])
        return float(np.minimum(d, 0.10).mean()), t

    step = np.deg2rad(step_deg)
    grid = np.arange(0.0, 2 * np.pi, step)
    with ThreadPoolExecutor(max(1, threads)) as ex:
        scores = [s for s, _ in ex.map(score, grid)]
        best = grid[int(np.argmin(scores))]
        fine = best + np.linspace(-step, step, 21)
        results = list(zip(ex.map(score, fine), fine, strict=True))
    (s, t), yaw = min(results, key=lambda r: r[0][0])
    deg = float((np.rad2deg(yaw) + 180.0) % 360.0 - 180.0)
    return WorldAlignment(deg, t, s, "clouds")


def _median_steps(trees: Sequence[cKDTree], pts: Sequence[np.ndarray], rot: np.ndarray,
                  t: np.ndarray, steps: int = 4, tol: float = 0.0) -> np.ndarray:
    """(3,) translation t of ``p = R v + t`` after up to ``steps`` robust nearest-neighbour
    steps on t alone (fewer once a step is shorter than ``tol`` metres): each adds the median
    residual of the points ``pts`` (world) to the nearest vertex of their body (``trees`` over
    IMU-world vertices), so points of the chair or of clothes that stand off one side do not
    drag it as a mean would."""
    for _ in range(steps):
        res = []
        for tree, p in zip(trees, pts, strict=True):
            _, j = tree.query((p - t) @ rot)  # points in the IMU world: R^T (p - t)
            res.append(p - (tree.data[j] @ rot.T + t))
        step = np.median(np.concatenate(res), axis=0)
        t = t + step
        if np.linalg.norm(step) < tol:
            break
    return t


def snap_to_clouds(clouds: Sequence[FusedCloud], params: BodyParams, model: BodyModel, *,
                   points: int = 800, steps: int = 30, min_points: int = 100, seed: int = 0,
                   pool: Pool = None, chunk: int = 50) -> np.ndarray:
    """(T,3) metres per frame that move the posed body of ``params`` onto its cloud (zeros for
    frames with fewer than ``min_points`` points): :func:`align_imu`'s robust translation
    steps, frame by frame, up to ``steps`` of them or until one is under 0.5 mm (a 20 cm offset
    of a body seen from one side takes ~15: nearest vertices pull short while they are far).

    The suit's position drifts and one rigid alignment per session leaves it where the heading
    error's lever arm puts it: on a simulated session the aligned suit stood 23 cm (median) off
    its clouds, more than the fits' 10 cm correspondence cut-off, and the fits failed (MPJPE
    4.60 cm; 1.03 cm with the fits started from here).

    ``pool``: where runs of ``chunk`` frames go (:func:`couch.pool.spawn_pool`; the points'
    subsets are drawn here, so it changes nothing but the time); None: all here.
    """
    verts, _ = pose_body(model, params)
    rng = np.random.default_rng(seed)
    subsets = []
    for cloud in clouds:
        p = cloud_arrays(cloud)[0].astype(np.float64)
        if len(p) < min_points:
            subsets.append(None)
            continue
        if len(p) > points:
            p = p[rng.choice(len(p), points, replace=False)]
        subsets.append(p)
    tasks = [(verts[s:s + chunk], subsets[s:s + chunk], steps) for s in range(0, len(verts), chunk)]
    return np.concatenate([np.zeros((0, 3)), *pool_map(pool, _snap_run, tasks)])


def _snap_run(verts: np.ndarray, points: Sequence[np.ndarray | None], steps: int) -> np.ndarray:
    """:func:`snap_to_clouds` of a run of frames (a pool task): posed meshes (n,V,3) and each
    frame's points (None: too few, no shift)."""
    out = np.zeros((len(verts), 3))
    for i, p in enumerate(points):
        if p is not None:
            out[i] = _median_steps([cKDTree(verts[i])], [p], np.eye(3), np.zeros(3), steps,
                                   tol=5e-4)
    return out


def refine_alignment(fitted_joints: np.ndarray, imu_joints: np.ndarray, weights: np.ndarray
                     ) -> WorldAlignment:
    """Heading and translation from fitted joints and the suit's joints (weighted Procrustes
    restricted to rotations about +Y).

    Args:
        fitted_joints: (T,24,3) world.
        imu_joints: (T,24,3) IMU world.
        weights: (T,24) >= 0 (e.g. the fits' reliability).
    """
    w = np.asarray(weights, np.float64).reshape(-1)
    a = np.asarray(imu_joints, np.float64).reshape(-1, 3)
    b = np.asarray(fitted_joints, np.float64).reshape(-1, 3)
    ok = (w > 0) & np.isfinite(a).all(1) & np.isfinite(b).all(1)
    if ok.sum() < 3:
        raise SessionFitError("too few reliable fitted joints to align the IMU")
    w, a, b = w[ok], a[ok], b[ok]
    for _ in range(3):  # reweighted: drop joints far off (a bad fit the weights missed)
        ca, cb = (w[:, None] * a).sum(0) / w.sum(), (w[:, None] * b).sum(0) / w.sum()
        a0, b0 = a - ca, b - cb
        # yaw maximising sum w b0·R a0 in the x-z plane
        sxx = (w * (a0[:, 0] * b0[:, 0] + a0[:, 2] * b0[:, 2])).sum()
        sxz = (w * (a0[:, 2] * b0[:, 0] - a0[:, 0] * b0[:, 2])).sum()
        yaw = np.arctan2(sxz, sxx)
        rot = _yaw_matrix(yaw)
        t = cb - rot @ ca
        r = np.linalg.norm(a @ rot.T + t - b, axis=1)
        cut = max(3.0 * np.median(r), 0.03)
        w = np.where(r > cut, 0.0, w)
    return WorldAlignment(float(np.rad2deg(yaw)), t, float(np.median(r)), "joints")


# --------------------------------------------------------------------------- reliability


def fit_reliability(params: BodyParams, clouds: Sequence[FusedCloud], chamfer: np.ndarray,
                    fallback: np.ndarray, views: Sequence[CameraView], model: BodyModel,
                    config: SessionFitConfig | None = None, *,
                    vertices: np.ndarray | None = None, pool: Pool = None,
                    chunk: int = 25) -> np.ndarray:
    """(T,24) weights of per-frame fits for the fusion, in [0, 1].

    Per frame: 0 for a fallback frame (too few points), else from its chamfer (1 at or below
    ``good_chamfer``, 0 at or above ``bad_chamfer``). Per joint: the fraction of the
    vertices the joint moves most that face a camera from inside its image and have a cloud
    point within ``support_distance``, mapped from [``min_support``, ``full_support``] to
    [0, 1] (a limb hidden behind the chair faces a camera but is not backed by points; a limb
    out of every image has no support at all). ``vertices``: the (T,V,3) posed mesh of
    ``params`` when the caller has it already. ``pool``: where runs of ``chunk`` frames go
    (:func:`couch.pool.spawn_pool`; each frame's weights depend on that frame alone, so it
    changes nothing but the time); None: all here.
    """
    cfg = config or SessionFitConfig()
    t = params.num_frames
    verts = pose_body(model, params)[0] if vertices is None else np.asarray(vertices, np.float64)
    seg = model.weights.cpu().numpy().argmax(1)  # (V,) the joint moving each vertex most
    frame_w = _frame_weights(chamfer, fallback, cfg)
    pts = [cloud_arrays(c)[0] for c in clouds]
    tasks = [(verts[s:s + chunk], np.asarray(model.faces), seg, pts[s:s + chunk], views,
              frame_w[s:s + chunk], cfg) for s in range(0, t, chunk)]
    return np.concatenate([np.zeros((0, 24)), *pool_map(pool, _reliability_run, tasks)])


def _frame_weights(chamfer: np.ndarray, fallback: np.ndarray, cfg: SessionFitConfig
                   ) -> np.ndarray:
    """(T,) a fit's weight from its chamfer (1 at ``good_chamfer``, 0 at ``bad_chamfer`` or
    NaN) and 0 for a fallback frame."""
    ch = np.nan_to_num(np.asarray(chamfer, np.float64), nan=np.inf)
    frame_w = np.clip((cfg.bad_chamfer - ch) / (cfg.bad_chamfer - cfg.good_chamfer), 0.0, 1.0)
    frame_w[np.asarray(fallback, bool)] = 0.0
    return frame_w


def _reliability_run(verts: np.ndarray, faces: np.ndarray, seg: np.ndarray,
                     points: Sequence[np.ndarray], views: Sequence[CameraView],
                     frame_w: np.ndarray, cfg: SessionFitConfig,
                     trees: Sequence[cKDTree | None] | None = None) -> np.ndarray:
    """:func:`fit_reliability` of a run of frames (a pool task): posed meshes (n,V,3), their
    clouds' points, the per-frame weights; ``seg`` (V,) the joint moving each vertex most;
    ``trees`` the clouds' k-d trees when the caller has them."""
    keep = np.flatnonzero(frame_w > 0)
    out = np.zeros((len(verts), 24))
    if not len(keep):
        return out
    verts = verts[keep]
    normals = vertex_normals(verts, faces)
    # facing a camera that has the vertex in its image
    facing = np.zeros(verts.shape[:2], bool)
    for view in views:
        # projecting is the cost: only vertices facing this camera and not yet seen by another
        todo = (((view.centre - verts) * normals).sum(-1) > 0) & ~facing
        facing[todo] = view.in_view(verts[todo])
    onehot = np.eye(24)[seg]  # (V,24)
    for i, k in enumerate(keep):
        tree = trees[k] if trees is not None else cKDTree(points[k])
        d, _ = tree.query(verts[i], distance_upper_bound=cfg.support_distance)
        backed = (d <= cfg.support_distance) & facing[i]
        n_facing = facing[i] @ onehot
        frac = np.divide(backed @ onehot, n_facing, out=np.zeros(24), where=n_facing > 0)
        out[k] = frame_w[k] * np.clip((frac - cfg.min_support)
                                      / (cfg.full_support - cfg.min_support), 0.0, 1.0)
    return out


# --------------------------------------------------------------------------- the pipeline


def fit_session(session_dir: str | os.PathLike, *,
                extrinsics: Extrinsics | dict[str, np.ndarray] | None = None,
                chair: ChairModel | None = None, scan: str | os.PathLike | None = None,
                sync: SessionSync | None = None, frames: tuple[int, int] | None = None,
                config: SessionFitConfig | None = None, progress: bool = False,
                pool: Pool = None, threads: int = 1) -> SessionFit:
    """Sync, clouds, IMU-initialised per-frame fits and sequence fusion of one session.

    Args:
        session_dir: the session folder (:func:`couch.capture.session.session_files`).
        extrinsics: camera poses; None calibrates them (ChArUco + floor).
        chair: the registered chair (kept out of the person clouds), or None.
        scan: a mesh of the subject (betas from it); None: the session's ``subject_scan``
            if it has one, else the shape is fitted to the clouds.
        sync: the session already synchronised with these extrinsics (e.g. by a pipeline
            that registered the chair on the same frame table); None: synchronise here.
        frames: (start, stop) rows of the frame table to fit (the IMU's span within them);
            None: every row the IMU recording covers.
        config: :class:`SessionFitConfig`.
        progress: progress bars.
        pool: where the cameras' passes, the snap, the fits' chunks and the chamfers' and
            reliability's runs of frames go (:func:`couch.pool.spawn_pool`); None: all here.
            The fit is the same either way.
        threads: threads of this process for the IMU's heading search and the sequence fusion
            (its spans' gradients), e.g. as many as the pool's workers, which wait meanwhile.
            The same result with any.

    Raises:
        SessionFitError: no IMU recording, no overlap of the IMU with the cameras, no person
            points, an unreadable subject scan (the message names the session or file).
        SyncError, SegmentationError, KinectFormatError, MvnxError: from the stages (they name
            the files).
    """
    cfg = config or SessionFitConfig()
    root = Path(session_dir)
    seconds: dict[str, float] = {}
    warnings: list[str] = []

    t0 = time.perf_counter()
    ext = extrinsics if extrinsics is not None else calibrate_session(root)
    ss = sync if sync is not None else sync_session(
        root, extrinsics=ext, depth_binning=cfg.depth_binning, progress=progress,
        pool=pool)
    warnings += [f"sync: {w}" for w in ss.kinect.warnings]
    if ss.resampled is None or ss.imu_clock is None or ss.imu is None:
        raise SessionFitError(f"{root}: the session has no IMU recording (imu/*.mvnx); the body "
                              f"fit is initialised from the suit's pose")
    if not ss.imu_clock.confident:
        warnings.append(f"sync: IMU clock not confident: {ss.imu_clock.summary()}")
    seconds["sync"] = time.perf_counter() - t0

    valid = ss.resampled.valid
    if not valid.any():
        raise SessionFitError(f"{root}: no camera frame falls inside the IMU recording "
                              f"({ss.resampled.summary()})")
    rows = np.arange(np.flatnonzero(valid)[0], np.flatnonzero(valid)[-1] + 1)
    if frames is not None:
        rows = rows[(rows >= frames[0]) & (rows < frames[1])]
        if not len(rows):
            raise SessionFitError(f"{root}: frames {frames[0]}:{frames[1]} hold no camera frame "
                                  f"inside the IMU recording (rows {np.flatnonzero(valid)[0]}-"
                                  f"{np.flatnonzero(valid)[-1]} are)")
    filled = ~valid[rows]
    if filled.any():
        warnings.append(f"IMU: {int(filled.sum())} frame(s) in gaps of the IMU recording take "
                        f"the nearest valid pose")
    imu = ss.resampled.take(rows[_fill_gaps(valid[rows])])
    # the rows the cameras are fitted on (indices into rows); the last one closes the span so
    # the fusion interpolates the suit's bias rather than extrapolating it
    keys = np.unique(np.r_[np.arange(0, len(rows), cfg.fit_stride), len(rows) - 1])
    imu_k = imu.take(keys)

    t0 = time.perf_counter()
    clouds, views, w = session_clouds(root, ext, ss.kinect, ss.tracks, rows[keys], chair=chair,
                                        segmentation=cfg.segmentation, cloud=cfg.cloud,
                                        progress=progress, pool=pool)
    warnings += [f"capture: {x}" for x in w]
    cameras = np.array([v.centre for v in views])
    seconds["clouds"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    bcfg = cfg.body
    coarse = cached_model(bcfg.coarse_model, bcfg.device, bcfg.dtype)
    full = cached_model(bcfg.model, bcfg.device, bcfg.dtype)
    zero = np.zeros(10, np.float32)
    align = align_imu(clouds, imu_body_params(imu_k, None, zero, coarse), coarse,
                      frames=cfg.align_frames, points=cfg.align_points,
                      step_deg=cfg.yaw_step_deg, seed=bcfg.seed, threads=threads)
    suit = imu_body_params(imu_k, align, zero, coarse)  # the aligned suit, mean shape
    shift = np.zeros((len(keys), 3))
    if cfg.snap_init:
        shift = snap_to_clouds(clouds, suit, coarse,
                               points=cfg.align_points, min_points=bcfg.min_points,
                               seed=bcfg.seed, pool=pool)
    seconds["align"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    scan_path = Path(scan) if scan is not None else session_files(root).subject_scan
    if scan_path is not None:
        import trimesh

        try:
            mesh = trimesh.load(scan_path, force="mesh", process=False)
            vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        except Exception as exc:  # trimesh raises many kinds on a bad file
            raise SessionFitError(f"{scan_path}: cannot read the subject scan ({exc})") from None
        if len(vertices) == 0 or not np.isfinite(vertices).all():
            raise SessionFitError(f"{scan_path}: the subject scan has no (finite) vertices")
        try:
            betas = fit_betas_to_scan(vertices, faces if len(faces) else None,
                                      config=dataclasses.replace(cfg.shape, body=bcfg),
                                      progress=progress).betas
        except ValueError as exc:
            raise SessionFitError(f"{scan_path}: {exc}") from None
        shape_source = "scan"
    else:
        shape = fit_shape(clouds, _shifted(suit, shift), cameras=cameras,
                          config=dataclasses.replace(cfg.shape, body=bcfg), progress=progress)
        betas, shape_source = shape.betas, "clouds"
    seconds["shape"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    init = _shifted(imu_body_params(imu_k, align, betas, full), shift)
    # the fit's own errors see cameras as centres only; ours below know the images and chair
    fit = fit_bodies(clouds, init, cameras=cameras, config=dataclasses.replace(bcfg, errors=False),
                     progress=progress, pool=pool)
    seconds["fit"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    occluders = None
    if chair is not None:
        occluders = (apply_transform(np.asarray(chair.world_from_object, np.float64),
                                     np.asarray(chair.vertices, np.float64)),
                     np.asarray(chair.faces))
    measure = (cfg.error_model, bcfg.device, bcfg.dtype)
    present = ss.kinect.frame_table[rows[keys]] >= 0
    samples = (bcfg.error_samples, bcfg.error_points)
    fit_chamfer, rel = _chamfers(measure, fit.params, clouds, views, present, occluders,
                                 samples, pool, fallback=fit.fallback, reliability=cfg)
    if (rel > 0).any():
        align = refine_alignment(fit.joints, imu_k.joint_positions, rel)
    else:
        warnings.append("fit: no reliable frame; the IMU alignment rests on the heading search")
    clock = ss.imu_clock
    if cfg.refine_clock and (rel.sum(1) > 0).sum() >= 10:
        joints = np.where((rel.sum(1) > 0)[:, None, None], fit.joints, np.nan)
        try:
            clock = refine_imu(ss.kinect.time[rows[keys]], joints, ss.imu, ss.imu_clock.clock,
                               imu_name=ss.imu_source or "IMU")
            res = resample_imu(ss.imu, clock.clock, ss.kinect.time[rows],
                               source=ss.imu_source or "IMU")
            if res.valid[~filled].all():
                imu = res.take(_fill_gaps(res.valid))
            else:
                warnings.append("sync: the refined IMU clock leaves frames outside the IMU "
                                "recording; kept the head-top clock's resampling")
                clock = ss.imu_clock
        except SyncError as exc:
            warnings.append(f"sync: clock refinement on the fitted joints failed ({exc}); "
                            f"kept the head-top estimate")
    seconds["errors"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fc = (np.zeros((len(rows), 4), bool) if imu.foot_contacts is None
          else np.asarray(imu.foot_contacts, bool))
    imu_params = imu_body_params(imu, align, betas, full)
    # rows not fitted: the suit's pose stands in for a fit the fusion gives no weight
    fit = _spread(fit, keys, imu_params)
    fit_chamfer = _spread_rows(fit_chamfer, keys, len(rows), np.nan)
    rel = _spread_rows(rel, keys, len(rows), 0.0)
    if cfg.fuse:
        fused = fuse_motion(fit.params, imu_params, rel, fc, config=cfg.fusion,
                            fps=1.0 / ss.kinect.period_s, threads=threads)
    else:
        fused = fit.params
    seconds["fusion"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    with torch.no_grad():  # the skeleton alone: the same joints as posing the whole mesh
        joints = full.skeleton(betas=fused.betas[None], global_orient=fused.global_orient,
                               body_pose=fused.body_pose, transl=fused.transl)[0]
    joints = joints.cpu().numpy().astype(np.float64)
    fused_chamfer = _spread_rows(
        _chamfers(measure, fused.frames(keys), clouds, views, present, occluders,
                  samples, pool)[0], keys, len(rows), np.nan)
    seconds["errors"] += time.perf_counter() - t0
    for m in warnings:
        log.warning("%s", m)
    return SessionFit(session=root, sync=ss, imu_clock=clock, rows=rows,
                      time=ss.kinect.time[rows], fitted=np.isin(np.arange(len(rows)), keys),
                      clouds=clouds, views=views, imu=imu,
                      imu_filled=filled, alignment=align, imu_params=imu_params, betas=betas,
                      shape_source=shape_source, fit=fit, reliability=rel, foot_contact=fc,
                      fit_chamfer=fit_chamfer, fused=fused, joints=joints.astype(np.float32),
                      chamfer=fused_chamfer, seconds=seconds, warnings=warnings,
                      init_shift=shift)
