"""Multi-camera extrinsic calibration of the Kinect rig: ChArUco board views -> camera poses, and
the floor -> the world frame.

Public API
----------
* :func:`detect_boards` — stream each camera's ChArUco capture (``calibration/<serial>.mkv``),
  detect the board per frame -> :class:`BoardObservations`.
* :func:`calibrate_extrinsics` — camera poses relative to a reference camera: initialised from
  PnP poses of frames two cameras both see (chained through the camera graph), then refined
  jointly (all camera and board poses, reprojection error of every corner through each colour
  camera's full intrinsics with distortion, ``scipy.optimize.least_squares``, soft-L1 loss).
* :func:`level_with_floor` — fuse depth points of the first frames of the session recordings
  (``kinect/<serial>.mkv``), fit the floor plane (open3d ``segment_plane``) and move the world
  frame onto it (see "World frame" below).
* :func:`calibrate_session` — all of the above for a session folder (or given extrinsics read
  back from a file, so later stages can skip calibrating), optionally writing ``extrinsics.json``.
* :func:`write_extrinsics` / :func:`read_extrinsics` — the ``extrinsics.json`` file.

Frames and units
----------------
Metres everywhere. Cameras are OpenCV/SDK style (+X right, +Y down, +Z forward). The *reference
frame* is the colour camera of the reference device (the first camera unless told otherwise): the
colour cameras are what observe the board. Depth-camera poses follow from the factory
``color_from_depth`` of each device: ``ref_from_depth = ref_from_color @ color_from_depth``.

Frame pairing: the calibration captures of the rig are hardware-synchronised and start together,
so frame ``k`` of every camera's capture (:attr:`KinectCapture.index`, which keeps its number when
a capture is unusable) shows the board in the same pose.

World frame (DESIGN.md: metres, +Y up, floor at y = 0), built by :func:`level_with_floor`:
  * +Y is the floor plane's normal, oriented to the side the cameras are on;
  * the origin is on the floor, under the point all cameras look at: the least-squares
    intersection of the colour cameras' optical axes, projected along +Y onto the floor;
  * +Z is the reference colour camera's viewing direction projected onto the floor (so the
    reference camera looks along +Z, seen from above), +X = Y x Z.
The heading and origin are conventions; the floor (y = 0, +Y up) is physical.
"""

from __future__ import annotations

import itertools
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, shortest_path
from scipy.spatial.transform import Rotation

from couch.atomic import atomic_path
from couch.geometry import average_transforms, invert_transform, make_transform

from .azure_calibration import KinectCalibration
from .azure_mkv import KinectFormatError, open_azure_mkv
from .charuco import BoardSpec, board_corners_3d, camera_from_board, detect_board
from .frames import FrameSkip, open_kinect_stream
from .registration import depth_to_points, project_points
from .session import SessionLayoutError, session_files

__all__ = [
    "BoardObservations",
    "BoardView",
    "CalibrationError",
    "CameraExtrinsics",
    "Extrinsics",
    "FloorPlane",
    "calibrate_extrinsics",
    "calibrate_session",
    "detect_boards",
    "level_with_floor",
    "read_extrinsics",
    "write_extrinsics",
]

EXTRINSICS_SCHEMA_VERSION = 1


class CalibrationError(ValueError):
    """Calibration cannot proceed: a camera never saw the board, the camera graph is
    disconnected, no floor was found, or an extrinsics file is malformed."""


# ================================================================ board observations
@dataclass(frozen=True)
class BoardView:
    """The board as one camera saw it in one frame of its calibration capture.

    Attributes:
        serial: the camera (device serial).
        frame: capture index in the calibration recording (shared by all cameras, see module doc).
        ids: (N,) int32 ChArUco corner ids.
        corners: (N, 2) float64 pixel positions in the *distorted* colour image (OpenCV pixel
            centres at integers).
        camera_from_board: (4, 4) colour-camera-from-board pose from PnP (metres), or None when
            too few corners were seen for a pose.
    """

    serial: str
    frame: int
    ids: np.ndarray
    corners: np.ndarray
    camera_from_board: np.ndarray | None


@dataclass
class BoardObservations:
    """Everything :func:`detect_boards` found.

    Attributes:
        spec: the board.
        serials: the cameras, in the order given (the first is the default reference).
        calibrations: serial -> factory calibration read from its capture.
        views: every (camera, frame) in which corners were detected.
        frames_total: serial -> number of captures read from its recording.
        sources: serial -> the recording the views came from.
        skipped: serial -> frames (or images) of its capture that could not be read: a colour
            frame that does not decode, a damaged stretch of the file (see
            :class:`couch.capture.frames.FrameSkip`).
    """

    spec: BoardSpec
    serials: list[str]
    calibrations: dict[str, KinectCalibration]
    views: list[BoardView]
    frames_total: dict[str, int]
    sources: dict[str, Path] = field(default_factory=dict)
    skipped: dict[str, list[FrameSkip]] = field(default_factory=dict)

    def frames_seen(self, min_corners: int = 6) -> dict[str, int]:
        """serial -> number of frames in which the camera saw >= ``min_corners`` corners."""
        out = dict.fromkeys(self.serials, 0)
        for v in self.views:
            if len(v.ids) >= min_corners:
                out[v.serial] += 1
        return out


def _serial_of(rec: Any, path: Path) -> str:
    """The device serial of a recording: its tag, else its calibration's, else the file stem."""
    if getattr(rec, "serial", None):
        return str(rec.serial)
    try:
        serial = rec.calibration.serial
    except KinectFormatError:
        serial = ""
    return serial if serial and serial != "000000000000" else path.stem


def detect_boards(recording_paths: Sequence[str | os.PathLike] | Mapping[str, str | os.PathLike],
                  spec: BoardSpec, *, min_corners: int = 6,
                  max_frames: int | None = None) -> BoardObservations:
    """Detect the ChArUco board in every frame of each camera's calibration capture.

    Args:
        recording_paths: the cameras' capture MKVs (``calibration/<serial>.mkv``), as a list
            (serial from each file's ``K4A_DEVICE_SERIAL_NUMBER`` tag, else its stem) or a
            mapping serial -> path.
        spec: the board.
        min_corners: fewest corners for a PnP pose (views with fewer keep corners, no pose).
        max_frames: read at most this many captures per camera (None: all).

    Returns:
        :class:`BoardObservations`; a camera that never saw the board has no views (and
        ``frames_seen()[serial] == 0``), which :func:`calibrate_extrinsics` reports.

    Raises:
        KinectFormatError: a recording cannot be read or has no colour track / calibration.
    """
    items = (list(recording_paths.items()) if isinstance(recording_paths, Mapping)
             else [(None, p) for p in recording_paths])
    serials: list[str] = []
    calibrations: dict[str, KinectCalibration] = {}
    views: list[BoardView] = []
    totals: dict[str, int] = {}
    sources: dict[str, Path] = {}
    skipped: dict[str, list[FrameSkip]] = {}
    for given, p in items:
        path = Path(p)
        stream = open_kinect_stream(path)
        if stream.kind == "mkv" and "COLOR" not in stream.reader.tracks:
            raise KinectFormatError(f"{path}: calibration capture has no COLOR track; the "
                                    f"board is detected in the colour images")
        serial = str(given) if given is not None else _serial_of(stream.reader, path)
        if serial in calibrations:
            raise ValueError(f"camera {serial} appears twice (second time: {path})")
        calib = stream.calibration
        K, dist = calib.color.K(), calib.color.dist
        n = 0
        for frame in stream:
            if max_frames is not None and n >= max_frames:
                break
            n += 1
            rgb = frame.color_rgb()  # None: no colour, or it did not decode (counted)
            if rgb is None:
                continue
            det = detect_board(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), spec, K, dist,
                               min_corners=min_corners)
            if len(det.ids) == 0:
                continue
            pose = None if det.rvec is None else camera_from_board(det.rvec, det.tvec)
            views.append(BoardView(serial, int(frame.index), det.ids, det.corners, pose))
        serials.append(serial)
        calibrations[serial] = calib
        totals[serial] = n
        sources[serial] = path
        skipped[serial] = list(stream.skipped)
    return BoardObservations(spec, serials, calibrations, views, totals, sources, skipped)


# ================================================================ extrinsics
@dataclass
class CameraExtrinsics:
    """One device's calibrated poses.

    Attributes:
        serial: device serial.
        world_from_color: (4, 4) pose of the colour camera, metres.
        world_from_depth: (4, 4) pose of the depth camera, metres
            (``world_from_color @ color_from_depth``).
        reprojection_mean_px, reprojection_max_px: corner reprojection error after refinement
            (Euclidean, colour pixels) over this camera's views; NaN if not computed.
        frames_used: frames of this camera in the joint refinement.
        frames_seen: frames in which this camera saw the board (>= min_corners corners).
    """

    serial: str
    world_from_color: np.ndarray
    world_from_depth: np.ndarray
    reprojection_mean_px: float = math.nan
    reprojection_max_px: float = math.nan
    frames_used: int = 0
    frames_seen: int = 0


@dataclass
class FloorPlane:
    """The floor found by :func:`level_with_floor`, in the reference colour camera's frame.

    Attributes:
        plane: (4,) ``(a, b, c, d)`` with ``a x + b y + c z + d = 0``, ``(a, b, c)`` the unit
            normal pointing up (towards the cameras), metres.
        inliers: points (full resolution) within the threshold used for the final fit.
        rms_m: RMS distance of those points to the plane, metres.
    """

    plane: np.ndarray
    inliers: int
    rms_m: float


@dataclass
class Extrinsics:
    """Poses of every camera of the rig.

    Attributes:
        cameras: serial -> :class:`CameraExtrinsics`, in the rig's order.
        reference: serial of the reference device (its colour camera is the reference frame).
        world_from_reference: (4, 4); the identity until :func:`level_with_floor` sets the world.
        floor: the floor plane, or None when the world frame was not levelled.
        method: how the poses were obtained (JSON-able dict, written to ``extrinsics.json``).
    """

    cameras: dict[str, CameraExtrinsics]
    reference: str
    world_from_reference: np.ndarray = field(default_factory=lambda: np.eye(4))
    floor: FloorPlane | None = None
    method: dict[str, Any] = field(default_factory=dict)

    @property
    def serials(self) -> list[str]:
        """The cameras, in order."""
        return list(self.cameras)

    def world_from_depth(self, serial: str) -> np.ndarray:
        """(4, 4) pose of ``serial``'s depth camera."""
        return self.cameras[serial].world_from_depth

    def world_from_color(self, serial: str) -> np.ndarray:
        """(4, 4) pose of ``serial``'s colour camera."""
        return self.cameras[serial].world_from_color


@dataclass(frozen=True)
class RefinementConfig:
    """Knobs of :func:`calibrate_extrinsics`.

    Attributes:
        min_corners: fewest corners for a view to be used.
        loss: ``least_squares`` robust loss.
        f_scale_px: residual scale (pixels) where the robust loss starts to down-weight.
        init_inlier_deg, init_inlier_m: a pair's per-frame relative poses farther than this from
            their medoid are dropped before averaging (a PnP flip of an oblique view).
    """

    min_corners: int = 6
    loss: str = "soft_l1"
    f_scale_px: float = 1.0
    init_inlier_deg: float = 2.0
    init_inlier_m: float = 0.03


def _pose_to_vec(t: np.ndarray) -> np.ndarray:
    """(..., 4, 4) -> (..., 6) ``[rotvec, translation]``."""
    return np.concatenate([Rotation.from_matrix(t[..., :3, :3]).as_rotvec(), t[..., :3, 3]],
                          axis=-1)


def _vec_to_rt(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 6) -> rotations (N, 3, 3), translations (N, 3)."""
    v = np.asarray(v).reshape(-1, 6)
    return Rotation.from_rotvec(v[:, :3]).as_matrix(), v[:, 3:]


def _robust_mean(transforms: np.ndarray, weights: np.ndarray, deg: float,
                 metres: float) -> np.ndarray:
    """Average of (N, 4, 4) poses after dropping those far from their medoid (PnP flips)."""
    if len(transforms) > 2:
        rot = Rotation.from_matrix(transforms[:, :3, :3])
        ang = np.stack([(rot[i].inv() * rot).magnitude() for i in range(len(rot))])
        dist = np.linalg.norm(transforms[:, None, :3, 3] - transforms[None, :, :3, 3], axis=-1)
        cost = np.degrees(ang) / deg + dist / metres
        medoid = int(np.argmin(np.median(cost, axis=1)))
        keep = (np.degrees(ang[medoid]) < deg) & (dist[medoid] < metres)
        transforms, weights = transforms[keep], weights[keep]
    return average_transforms(transforms, weights)


def _initial_poses(views: list[BoardView], serials: list[str], reference: str,
                   cfg: RefinementConfig) -> dict[str, np.ndarray]:
    """reference-from-colour-camera poses from PnP poses of co-observed frames.

    A pair of cameras that both posed the board in frame f gives
    ``cam_i_from_cam_j = cam_i_from_board_f @ inv(cam_j_from_board_f)``; each pair's estimates
    are robustly averaged, and every camera is chained to the reference along the path through
    the camera graph that uses the best-supported pairs (edge cost 1 / co-observed frames).

    Raises:
        CalibrationError: the graph is disconnected (names the cameras of each component).
    """
    index = {s: i for i, s in enumerate(serials)}
    posed: dict[int, dict[str, tuple[np.ndarray, int]]] = {}
    for v in views:
        if v.camera_from_board is not None:
            posed.setdefault(v.frame, {})[v.serial] = (v.camera_from_board, len(v.ids))
    pairs: dict[tuple[int, int], list[tuple[np.ndarray, float]]] = {}
    for cams in posed.values():
        names = sorted(cams, key=index.__getitem__)
        for a in range(len(names)):
            for b in range(a + 1, len(names)):
                (ti, ni), (tj, nj) = cams[names[a]], cams[names[b]]
                key = (index[names[a]], index[names[b]])
                pairs.setdefault(key, []).append((ti @ invert_transform(tj), min(ni, nj)))
    n = len(serials)
    counts = np.zeros((n, n))
    for (i, j), est in pairs.items():
        counts[i, j] = counts[j, i] = len(est)
    ncomp, labels = connected_components(counts > 0, directed=False)
    if ncomp > 1:
        groups = [[serials[i] for i in range(n) if labels[i] == c] for c in range(ncomp)]
        raise CalibrationError(
            f"the camera graph is disconnected: no frame links the camera groups "
            f"{' | '.join(', '.join(g) for g in groups)} (cameras are linked when both see the "
            f"board, with a pose, in the same frame); record more board poses between them")
    rel: dict[tuple[int, int], np.ndarray] = {}
    for (i, j), est in pairs.items():
        t = _robust_mean(np.stack([e[0] for e in est]), np.array([e[1] for e in est], float),
                         cfg.init_inlier_deg, cfg.init_inlier_m)
        rel[(i, j)], rel[(j, i)] = t, invert_transform(t)  # cam_i_from_cam_j and inverse
    cost = np.where(counts > 0, 1.0 / np.maximum(counts, 1), 0.0)
    r = index[reference]
    _, pred = shortest_path(cost, directed=False, indices=r, return_predecessors=True)
    out = {reference: np.eye(4)}
    for s in serials:
        k = index[s]
        chain = np.eye(4)  # ref_from_cam_k, built from the reference outwards
        path = [k]
        while path[-1] != r:
            path.append(int(pred[path[-1]]))
        path.reverse()  # r, ..., k
        for a, b in itertools.pairwise(path):
            chain = chain @ rel[(a, b)]
        out[s] = chain
    return out


@dataclass
class _Problem:
    """Flattened observations of the joint refinement (one row per observed corner)."""

    cam: np.ndarray  # (M,) int: index into the non-reference cameras, -1 = the reference
    cam_all: np.ndarray  # (M,) int: index into serials
    board: np.ndarray  # (M,) int: index into the refined frames
    obj: np.ndarray  # (M, 3) board-frame corner positions, metres
    img: np.ndarray  # (M, 2) detected pixels


def _residuals(x: np.ndarray, prob: _Problem, n_free: int,
               intrinsics: list[Any]) -> np.ndarray:
    """(2M,) reprojection residuals in pixels for parameters ``x``.

    ``x`` = ``[cam_from_ref (6 per non-reference camera), ref_from_board (6 per frame)]``, each
    a Rodrigues vector + translation in metres. Vectorised over corners; the only loop is over
    cameras (each has its own lens model).
    """
    rc, tc = _vec_to_rt(x[:6 * n_free])
    rb, tb = _vec_to_rt(x[6 * n_free:])
    # the reference camera is the identity pose: append it as the last entry (index -1)
    rc = np.concatenate([rc, np.eye(3)[None]])
    tc = np.concatenate([tc, np.zeros((1, 3))])
    p_ref = np.einsum("mij,mj->mi", rb[prob.board], prob.obj) + tb[prob.board]
    p_cam = np.einsum("mij,mj->mi", rc[prob.cam], p_ref) + tc[prob.cam]
    uv = np.empty((len(p_cam), 2))
    for c, intr in enumerate(intrinsics):
        sel = prob.cam_all == c
        if np.any(sel):
            uv[sel] = project_points(p_cam[sel], intr)[0]
    res = uv - prob.img
    # a point behind the camera or beyond the lens model's radius: a large finite penalty
    # keeps the solver away from it (NaN would abort least_squares)
    res[~np.isfinite(res)] = 1e3
    return res.reshape(-1)


def _sparsity(prob: _Problem, n_free: int, n_boards: int) -> coo_matrix:
    """Jacobian pattern: a corner's residuals depend on its camera's and its board's poses."""
    m = len(prob.cam)
    rows = np.repeat(np.arange(2 * m), 6)  # each residual row touches 6 board parameters
    board_cols = (6 * (n_free + np.repeat(prob.board, 2))[:, None] + np.arange(6)).reshape(-1)
    free = np.repeat(prob.cam, 2) >= 0
    cam_rows = np.repeat(np.flatnonzero(free), 6)
    cam_cols = (6 * np.repeat(prob.cam, 2)[free][:, None] + np.arange(6)).reshape(-1)
    r = np.concatenate([rows, cam_rows])
    c = np.concatenate([board_cols, cam_cols])
    return coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(2 * m, 6 * (n_free + n_boards)))


def calibrate_extrinsics(observations: BoardObservations,
                         calibrations: Mapping[str, KinectCalibration] | None = None, *,
                         reference: str | None = None,
                         config: RefinementConfig | None = None) -> Extrinsics:
    """Poses of all cameras relative to the reference camera from ChArUco board views.

    1. Initialisation: pairwise relative poses from frames two cameras both posed, chained to the
       reference through the camera graph (see :func:`_initial_poses`); each frame's board pose
       is the mean of its cameras' PnP poses mapped into the reference frame.
    2. Joint refinement (``scipy.optimize.least_squares``, trust-region, sparse finite-difference
       Jacobian, ``config.loss`` loss): unknowns are every non-reference colour camera's pose and
       the board pose of every frame seen by >= 2 cameras; residuals are the pixel reprojection
       errors of every detected corner through that camera's full colour intrinsics (OpenCV
       rational distortion, :func:`couch.capture.registration.project_points`).

    Args:
        observations: from :func:`detect_boards`.
        calibrations: serial -> factory calibration; defaults to ``observations.calibrations``.
        reference: the reference device (default: the first camera).
        config: refinement knobs.

    Returns:
        :class:`Extrinsics` in the reference colour camera's frame (``world_from_reference`` is
        the identity; :func:`level_with_floor` sets the world), with per-camera reprojection
        errors (pixels) and frame counts.

    Raises:
        CalibrationError: a camera never saw the board, or the camera graph is disconnected
            (the message names the cameras).
    """
    cfg = config or RefinementConfig()
    calibs = dict(observations.calibrations if calibrations is None else calibrations)
    serials = list(observations.serials)
    if not serials:
        raise CalibrationError("no cameras to calibrate")
    missing = [s for s in serials if s not in calibs]
    if missing:
        raise CalibrationError(f"no factory calibration for camera(s) {', '.join(missing)}")
    reference = serials[0] if reference is None else str(reference)
    if reference not in serials:
        raise CalibrationError(f"reference camera {reference} is not among {serials}")
    views = [v for v in observations.views
             if len(v.ids) >= cfg.min_corners and v.serial in calibs]
    seen = observations.frames_seen(cfg.min_corners)
    blind = [s for s in serials if seen.get(s, 0) == 0]
    if blind:
        where = [f"{s} ({observations.sources.get(s, 'its capture')}, "
                 f"{observations.frames_total.get(s, 0)} frames)" for s in blind]
        raise CalibrationError(f"camera(s) never saw the board (>= {cfg.min_corners} corners): "
                               f"{'; '.join(where)}; check the capture and the board spec")
    if len(serials) == 1:
        c = calibs[reference]
        cam = CameraExtrinsics(reference, np.eye(4), c.color_from_depth.copy(),
                               frames_seen=seen[reference])
        return Extrinsics({reference: cam}, reference, method={"extrinsics": "single camera"})

    ref_from_cam = _initial_poses(views, serials, reference, cfg)

    # Frames seen by >= 2 cameras: a frame seen by one camera only constrains its own board pose.
    by_frame: dict[int, list[BoardView]] = {}
    for v in views:
        by_frame.setdefault(v.frame, []).append(v)
    frames = sorted(f for f, vs in by_frame.items() if len({v.serial for v in vs}) >= 2)
    ref_from_board = []
    for f in frames:
        est = [ref_from_cam[v.serial] @ v.camera_from_board for v in by_frame[f]
               if v.camera_from_board is not None]
        w = [len(v.ids) for v in by_frame[f] if v.camera_from_board is not None]
        ref_from_board.append(_robust_mean(np.stack(est), np.asarray(w, float),
                                           cfg.init_inlier_deg, cfg.init_inlier_m))

    free = [s for s in serials if s != reference]
    free_index = {s: i for i, s in enumerate(free)}
    all_index = {s: i for i, s in enumerate(serials)}
    corners3d = board_corners_3d(observations.spec)
    used = [v for f in frames for v in by_frame[f]]
    board_of = {f: i for i, f in enumerate(frames)}
    sizes = [len(v.ids) for v in used]
    prob = _Problem(
        cam=np.repeat([free_index.get(v.serial, -1) for v in used], sizes),
        cam_all=np.repeat([all_index[v.serial] for v in used], sizes),
        board=np.repeat([board_of[v.frame] for v in used], sizes),
        obj=corners3d[np.concatenate([v.ids for v in used])],
        img=np.concatenate([v.corners for v in used]),
    )
    intrinsics = [calibs[s].color for s in serials]
    x0 = np.concatenate([
        _pose_to_vec(invert_transform(np.stack([ref_from_cam[s] for s in free]))).reshape(-1),
        _pose_to_vec(np.stack(ref_from_board)).reshape(-1)])
    n_free = len(free)
    sol = least_squares(_residuals, x0, args=(prob, n_free, intrinsics),
                        jac_sparsity=_sparsity(prob, n_free, len(frames)), loss=cfg.loss,
                        f_scale=cfg.f_scale_px, x_scale="jac", method="trf",
                        xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=200)
    err = np.linalg.norm(_residuals(sol.x, prob, n_free, intrinsics).reshape(-1, 2), axis=1)
    rc, tc = _vec_to_rt(sol.x[:6 * n_free])
    cam_from_ref = make_transform(rc, tc)

    cameras: dict[str, CameraExtrinsics] = {}
    for s in serials:
        ref_from_color = (np.eye(4) if s == reference
                          else invert_transform(cam_from_ref[free_index[s]]))
        sel = prob.cam_all == all_index[s]
        cameras[s] = CameraExtrinsics(
            s, ref_from_color, ref_from_color @ calibs[s].color_from_depth,
            reprojection_mean_px=float(err[sel].mean()) if np.any(sel) else math.nan,
            reprojection_max_px=float(err[sel].max()) if np.any(sel) else math.nan,
            frames_used=len({v.frame for v in used if v.serial == s}),
            frames_seen=seen[s])
    method = {
        "extrinsics": "ChArUco board, pairwise PnP initialisation chained through the camera "
                      "graph, joint reprojection refinement (scipy least_squares)",
        "loss": cfg.loss, "f_scale_px": cfg.f_scale_px, "min_corners": cfg.min_corners,
        "board": {k: getattr(observations.spec, k) for k in
                  ("squares_x", "squares_y", "square_length", "marker_length", "dictionary",
                   "margin")},
        "frames_refined": len(frames), "corners": len(err),
        "reprojection_rms_px": float(np.sqrt(np.mean(err ** 2))),
        "solver": {"status": int(sol.status), "nfev": int(sol.nfev)},
    }
    return Extrinsics(cameras, reference, method=method)


# ================================================================ floor
def _first_depth_frames(path: Path, count: int) -> tuple[KinectCalibration, list[np.ndarray]]:
    rec = open_azure_mkv(path)
    frames = []
    for cap in rec:
        if cap.depth_mm is not None:
            frames.append(cap.depth_mm)
            if len(frames) >= count:
                break
    if not frames:
        raise CalibrationError(f"{path}: no depth frame to find the floor in")
    return rec.calibration, frames


def _axes_meeting_point(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Least-squares point closest to the lines ``origins[i] + s·dirs[i]`` ((N, 3) each)."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (N,3,3) projectors off each line
    a, b = proj.sum(0), np.einsum("nij,nj->i", proj, origins)
    return np.linalg.lstsq(a, b, rcond=None)[0]


def level_with_floor(extrinsics: Extrinsics,
                     recording_paths: Sequence[str | os.PathLike] | Mapping[str, str | os.PathLike],
                     *, frames: int = 1, voxel_m: float = 0.02, distance_m: float = 0.01,
                     max_planes: int = 6, max_tilt_deg: float = 20.0) -> Extrinsics:
    """Put the world frame on the floor (see the module doc for the convention).

    Args:
        extrinsics: camera poses (any world frame, e.g. from :func:`calibrate_extrinsics`).
        recording_paths: the session recordings (``kinect/<serial>.mkv``), a list (serial from
            the file) or a mapping serial -> path; cameras without one (a recording lost) add
            no floor points but must still be above the floor found.
        frames: depth frames per camera fused (the first ones of the recording).
        voxel_m: voxel size of the downsampling before RANSAC.
        distance_m: plane inlier distance (RANSAC, and the final least-squares refit on the
            full-resolution points).
        max_planes: planes extracted one after another (largest first) to look for the floor
            (fewer once what is left holds fewer points than the floor found).
        max_tilt_deg: a floor candidate's normal is within this of the cameras' mean "up"
            (−Y of the camera frames).

    Returns:
        a new :class:`Extrinsics` whose world has the floor at y = 0, +Y up; ``floor`` holds the
        plane in the reference frame.

    Raises:
        CalibrationError: no camera has a recording, a recording has no depth frames, or no
            horizontal plane with every camera above it was found.
    """
    import open3d as o3d  # heavy import, only needed here

    paths: dict[str, Path] = {}
    items = (list(recording_paths.items()) if isinstance(recording_paths, Mapping)
             else [(None, p) for p in recording_paths])
    for given, p in items:
        path = Path(p)
        serial = str(given) if given is not None else _serial_of(
            open_azure_mkv(path, require_calibration=False), path)
        paths[serial] = path
    if not any(s in paths for s in extrinsics.cameras):
        raise CalibrationError(f"no session recording for any of the camera(s) "
                               f"{', '.join(extrinsics.cameras)} (given: "
                               f"{', '.join(map(str, paths.values())) or 'none'})")
    # Work in the frame the extrinsics are in ("cur"): any earlier levelling is replaced.
    clouds = []
    for s, cam in extrinsics.cameras.items():
        if s not in paths:
            continue
        calib, depths = _first_depth_frames(paths[s], frames)
        for d in depths:
            pts = depth_to_points(d, calib.depth)
            clouds.append(pts @ cam.world_from_depth[:3, :3].T + cam.world_from_depth[:3, 3])
    points = np.concatenate(clouds)
    centres = np.stack([c.world_from_color[:3, 3] for c in extrinsics.cameras.values()])
    up = -np.mean([c.world_from_color[:3, 1] for c in extrinsics.cameras.values()], axis=0)
    up /= np.linalg.norm(up)

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel_m)
    best: tuple[int, np.ndarray] | None = None
    # the same recordings should give the same world: open3d's RANSAC draws from its own
    # global generator, unseeded unless told, and its threads stop early on whichever
    # plane is good enough first, which depends on how busy the cores are (on a loaded
    # machine 2 of 12 runs chose another floor, moving the world by ~1e-7 rad and the
    # chair by 0.08 mm): one thread, so the draws are evaluated in order
    o3d.utility.random.seed(0)
    threads = o3d.utility.get_max_threads()
    for _ in range(max_planes):
        # a later plane comes from what is left: fewer points than the floor's inliers
        # cannot hold a bigger floor
        if len(pcd.points) < 100 or (best is not None and len(pcd.points) < best[0]):
            break
        o3d.utility.set_max_threads(1)
        try:
            model, inl = pcd.segment_plane(distance_threshold=distance_m, ransac_n=3,
                                           num_iterations=1000, probability=0.99999)
        finally:
            o3d.utility.set_max_threads(threads)
        plane = np.asarray(model, dtype=np.float64)
        plane /= np.linalg.norm(plane[:3])
        if plane[:3] @ up < 0:
            plane = -plane
        tilt = math.degrees(math.acos(min(1.0, float(plane[:3] @ up))))
        # the floor: near-horizontal and every camera above it (a ceiling has them below)
        if tilt < max_tilt_deg and np.all(centres @ plane[:3] + plane[3] > 0):
            if best is None or len(inl) > best[0]:
                best = (len(inl), plane)
        pcd = pcd.select_by_index(inl, invert=True)
    if best is None:
        raise CalibrationError(f"no floor found: no plane within {max_tilt_deg} deg of the "
                               f"cameras' up direction with all cameras above it in "
                               f"{', '.join(map(str, paths.values()))}")
    plane = best[1]
    # Least-squares refit on the full-resolution inliers (RANSAC's plane comes from 3 points).
    for _ in range(2):
        near = points[np.abs(points @ plane[:3] + plane[3]) < distance_m]
        centroid = near.mean(axis=0)
        normal = np.linalg.svd(near - centroid, full_matrices=False)[2][2]
        normal *= np.sign(normal @ plane[:3])
        plane = np.append(normal, -normal @ centroid)
    dist = near @ plane[:3] + plane[3]
    floor_cur = FloorPlane(plane, len(near), float(np.sqrt(np.mean(dist ** 2))))

    # World axes expressed in the current frame.
    y = plane[:3]
    ref = extrinsics.cameras[extrinsics.reference].world_from_color
    z = ref[:3, 2] - (ref[:3, 2] @ y) * y
    if np.linalg.norm(z) < 1e-6:
        raise CalibrationError("the reference camera looks straight down; heading undefined")
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    axes = np.stack([c.world_from_color[:3, 2] for c in extrinsics.cameras.values()])
    if len(centres) >= 2:
        meet = _axes_meeting_point(centres, axes)
    else:
        meet = centres[0] + axes[0] * 2.0
    origin = meet - (meet @ y + plane[3]) * y  # dropped onto the floor along the normal
    world_from_cur = make_transform(np.stack([x, y, z]), -np.stack([x, y, z]) @ origin)

    cameras = {s: CameraExtrinsics(s, world_from_cur @ c.world_from_color,
                                   world_from_cur @ c.world_from_depth, c.reprojection_mean_px,
                                   c.reprojection_max_px, c.frames_used, c.frames_seen)
               for s, c in extrinsics.cameras.items()}
    # floor in the reference frame: transform the plane with ref_from_cur
    cur_from_ref = extrinsics.cameras[extrinsics.reference].world_from_color
    n_ref = cur_from_ref[:3, :3].T @ plane[:3]
    d_ref = plane[3] + plane[:3] @ cur_from_ref[:3, 3]
    floor = FloorPlane(np.append(n_ref, d_ref), floor_cur.inliers, floor_cur.rms_m)
    method = dict(extrinsics.method)
    method["world"] = ("floor plane (open3d segment_plane on fused depth, least-squares refit) "
                       "= y 0, +Y up; origin under the least-squares meeting point of the "
                       "colour cameras' optical axes; +Z = reference colour camera's viewing "
                       "direction projected on the floor")
    method["floor_fit"] = {"frames_per_camera": frames, "voxel_m": voxel_m,
                           "distance_m": distance_m}
    return Extrinsics(cameras, extrinsics.reference,
                      world_from_cur @ cur_from_ref, floor, method)


# ================================================================ extrinsics.json
def _matrix_list(t: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(t, dtype=np.float64)]


def _json_float(v: float) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def write_extrinsics(path: str | os.PathLike, extrinsics: Extrinsics) -> None:
    """Write ``extrinsics.json`` atomically.

    Layout: ``schema_version``, ``reference`` (serial), ``world_from_reference`` (4x4),
    ``floor`` (``plane_reference`` [a, b, c, d] in the reference colour camera frame, unit
    normal up; ``inliers``; ``rms_m``) or null, ``method`` (dict), and ``cameras``: serial ->
    ``world_from_depth``, ``world_from_color`` (4x4 nested lists, metres),
    ``reprojection_error_px`` {``mean``, ``max``} (null when unknown), ``frames_used``,
    ``frames_seen``.
    """
    doc = {
        "schema_version": EXTRINSICS_SCHEMA_VERSION,
        "reference": extrinsics.reference,
        "world_from_reference": _matrix_list(extrinsics.world_from_reference),
        "floor": None if extrinsics.floor is None else {
            "plane_reference": [float(v) for v in extrinsics.floor.plane],
            "inliers": int(extrinsics.floor.inliers), "rms_m": float(extrinsics.floor.rms_m)},
        "method": extrinsics.method,
        "cameras": {s: {
            "world_from_depth": _matrix_list(c.world_from_depth),
            "world_from_color": _matrix_list(c.world_from_color),
            "reprojection_error_px": {"mean": _json_float(c.reprojection_mean_px),
                                      "max": _json_float(c.reprojection_max_px)},
            "frames_used": int(c.frames_used), "frames_seen": int(c.frames_seen),
        } for s, c in extrinsics.cameras.items()},
    }
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n")


def _read_pose(value: Any, where: str) -> np.ndarray:
    """A (4, 4) rigid transform from nested lists, or CalibrationError naming ``where``."""
    try:
        t = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        t = np.zeros(0)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise CalibrationError(f"{where} must be a 4x4 list of finite numbers, got "
                               f"{json.dumps(value)[:120]}")
    r = t[:3, :3]
    if (not np.allclose(t[3], [0, 0, 0, 1], atol=1e-9)
            or not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0):
        raise CalibrationError(f"{where} is not a rigid transform (rotation not orthonormal "
                               f"with det +1, or bottom row not [0, 0, 0, 1])")
    return t


def read_extrinsics(path: str | os.PathLike) -> Extrinsics:
    """Read an ``extrinsics.json`` written by :func:`write_extrinsics` (or by hand, same keys).

    Only ``cameras`` with ``world_from_depth`` and ``world_from_color`` per serial are required;
    the rest is optional. Raises :class:`CalibrationError` naming the file and key on malformed
    input (invalid JSON, missing keys, non-4x4 or non-rigid matrices).
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read extrinsics: {exc.strerror or exc}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path}: expected a JSON object at the top level")
    version = doc.get("schema_version", EXTRINSICS_SCHEMA_VERSION)
    if version != EXTRINSICS_SCHEMA_VERSION:
        raise CalibrationError(f"{path}: schema_version {version!r} is not supported "
                               f"(expected {EXTRINSICS_SCHEMA_VERSION})")
    cams = doc.get("cameras")
    if not isinstance(cams, dict) or not cams:
        raise CalibrationError(f"{path}: 'cameras' must be a non-empty object serial -> poses")
    cameras: dict[str, CameraExtrinsics] = {}
    for serial, c in cams.items():
        if not isinstance(c, dict):
            raise CalibrationError(f"{path}: cameras.{serial} must be an object")
        for key in ("world_from_depth", "world_from_color"):
            if key not in c:
                raise CalibrationError(f"{path}: cameras.{serial} has no '{key}'")
        err = c.get("reprojection_error_px") or {}
        if not isinstance(err, dict):
            raise CalibrationError(f"{path}: cameras.{serial}.reprojection_error_px must be an "
                                   f"object with 'mean' and 'max'")

        def number(v: Any, key: str, serial: str = serial) -> float:
            if v is None:
                return math.nan
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise CalibrationError(f"{path}: cameras.{serial}.{key} must be a number, "
                                       f"got {v!r}")
            return float(v)

        cameras[str(serial)] = CameraExtrinsics(
            str(serial),
            _read_pose(c["world_from_color"], f"{path}: cameras.{serial}.world_from_color"),
            _read_pose(c["world_from_depth"], f"{path}: cameras.{serial}.world_from_depth"),
            number(err.get("mean"), "reprojection_error_px.mean"),
            number(err.get("max"), "reprojection_error_px.max"),
            int(number(c.get("frames_used", 0), "frames_used")),
            int(number(c.get("frames_seen", 0), "frames_seen")))
    reference = str(doc.get("reference", next(iter(cameras))))
    if reference not in cameras:
        raise CalibrationError(f"{path}: reference {reference!r} is not one of the cameras "
                               f"{list(cameras)}")
    w = doc.get("world_from_reference")
    world_from_reference = (cameras[reference].world_from_color if w is None
                            else _read_pose(w, f"{path}: world_from_reference"))
    floor = None
    f = doc.get("floor")
    if f is not None:
        plane = np.array(f.get("plane_reference") if isinstance(f, dict) else None, dtype=object)
        try:
            plane = plane.astype(np.float64)
        except (TypeError, ValueError):
            plane = np.zeros(0)
        if plane.shape != (4,) or not np.all(np.isfinite(plane)):
            raise CalibrationError(f"{path}: floor.plane_reference must be 4 finite numbers")
        floor = FloorPlane(plane, int(f.get("inliers", 0)), float(f.get("rms_m", math.nan)))
    method = doc.get("method") or {}
    if not isinstance(method, dict):
        raise CalibrationError(f"{path}: 'method' must be an object")
    return Extrinsics(cameras, reference, world_from_reference, floor,
                      {**method, "source": str(path)})


# ================================================================ session
def calibrate_session(session_dir: str | os.PathLike, *,
                      given: str | os.PathLike | Extrinsics | None = None,
                      output: str | os.PathLike | None = None,
                      spec: BoardSpec | None = None, reference: str | None = None,
                      floor_frames: int = 1) -> Extrinsics:
    """The capture stage's calibration step for one session folder.

    With ``given`` (an :class:`Extrinsics` or a path to an ``extrinsics.json``) nothing is
    calibrated: the given poses are checked against the session's cameras and returned. Else
    the board is detected in ``calibration/<serial>.mkv``, the rig calibrated and levelled with
    the floor seen in ``kinect/<serial>.mkv``. Cameras and files come from ``session.json``
    (``kinect[].serial/file/calibration_capture``, ``board``), or from the folders' MKV files.

    Args:
        session_dir: the session folder.
        given: extrinsics to use instead of calibrating.
        output: where to write ``extrinsics.json`` (None: do not write).
        spec: the board (default: ``session.json``'s ``board``, else :class:`BoardSpec`()).
        reference: reference device (default: the first camera, the sync master in
            ``session.json``).
        floor_frames: depth frames per camera for the floor.

    Raises:
        CalibrationError: see :func:`calibrate_extrinsics`, :func:`level_with_floor`,
            :func:`read_extrinsics`; given extrinsics lacking one of the session's cameras.
    """
    root = Path(session_dir)
    try:
        files = session_files(root)
    except SessionLayoutError as exc:
        raise CalibrationError(str(exc)) from None
    uncaptured = [c.serial for c in files.cameras if c.calibration_capture is None]
    if files.manifest is not None and uncaptured:
        raise CalibrationError(f"{files.manifest}: no calibration_capture for camera(s) "
                               f"{', '.join(uncaptured)}")
    captures = {c.serial: c.calibration_capture for c in files.cameras
                if c.calibration_capture is not None}
    sessions = {c.serial: c.recording for c in files.cameras if c.recording is not None}
    board_doc = files.board
    if given is not None:
        ext = given if isinstance(given, Extrinsics) else read_extrinsics(given)
        lacking = [s for s in captures if s not in ext.cameras]
        if lacking:
            where = "" if isinstance(given, Extrinsics) else f" in {given}"
            raise CalibrationError(f"given extrinsics{where} have no pose for camera(s) "
                                   f"{', '.join(lacking)} of {root}")
    else:
        if not captures:
            raise CalibrationError(f"{root}: no calibration captures (calibration/*.mkv)")
        if spec is None:
            spec = BoardSpec(**board_doc) if isinstance(board_doc, dict) else BoardSpec()
        obs = detect_boards(captures, spec)
        ext = calibrate_extrinsics(obs, reference=reference)
        ext = level_with_floor(ext, sessions, frames=floor_frames)
    if output is not None:
        write_extrinsics(output, ext)
    return ext
