"""BEHAVE-style frame folders (the layout of the BEHAVE dataset, which COUCH follows): a writer
and a streaming reader.

Public API
----------
* :class:`BehaveWriter` — ``info.json``, the calibration files and one ``t%04d.%03d/`` folder per
  :meth:`~BehaveWriter.write_frame`; every file is written atomically.
* :func:`open_behave_sequence` -> :class:`BehaveSequence`; iterate it for :class:`BehaveFrame`
  (one frame in memory at a time). SMPL-H / object fits are loaded lazily through
  :meth:`BehaveFrame.person_fit` / :meth:`BehaveFrame.object_fit` with the restricted unpickler.
* :class:`FrameImages` — one camera's images of one frame.
* :meth:`BehaveSequence.iter_camera` -> :class:`CameraFrame`: one camera's colour (still encoded,
  decoded on demand) and depth per frame, each usable on its own (what
  :func:`couch.capture.frames.open_kinect_stream` reads).
* :func:`frame_name` / :func:`parse_frame_name` — time in seconds <-> ``t0003.000``.
* :class:`BehaveFormatError` (a ``ValueError``) for unreadable input; :class:`BehaveSkip` for what
  a reader skipped (``BehaveSequence.skipped``).

Layout written (``root`` holds the sequence folders and ``calibs``, as the brief specifies; the
BEHAVE release puts sequences one level deeper, in ``sequences/``; both read the same because
``info.json``'s paths are relative to the sequence folder)::

    <root>/<sequence>/info.json
    <root>/<sequence>/t0003.000/k0.color.jpg       RGB, JPEG
                               k0.depth.png       uint16 mm, 16-bit grey PNG, colour-camera pixels
                               k0.person_mask.png 0/255 8-bit PNG (only if given)
                               k0.obj_rend_mask.png
    <root>/calibs/<date>/config/<k>/config.json    BEHAVE-world-from-colour-camera k
    <root>/calibs/<date>/config/couch_world.json   couch-world-from-BEHAVE-world (ours)
    <root>/calibs/intrinsics/<k>/calibration.json  BEHAVE's intrinsics JSON
    <root>/calibs/intrinsics/<k>/pointcloud_table.npy
    <root>/calibs/intrinsics/<k>/azure_calibration.json  the factory JSON (ours)

What was checked in the BEHAVE code (github xiexh20/behave-dataset, commit 8566483)
-----------------------------------------------------------------------------------
* ``README.md`` "Dataset Structure": ``calibs/Date[xx]/config`` (camera poses),
  ``calibs/Date[xx]/background``, ``calibs/intrinsics`` (4 Kinects); ``sequences/<name>/
  info.json``, ``t*.000/k[0-3].color.jpg``, ``k[0-3].depth.png``, ``k[0-3].person_mask.jpg``,
  ``k[0-3].obj_rend_mask.jpg``, ``person/fit02`` (SMPL-H), ``<object>/fit01``; "depth images are
  already pixel aligned with color images, i.e. depth images have the same resolution".
* ``data/seq_utils.py`` (``SeqInfo``, ``save_seq_info``): ``info.json`` keys ``config``,
  ``intrinsic``, ``cat``, ``gender``, ``empty``, ``kinects``, ``beta``; ``config``, ``empty``
  and ``intrinsic`` are paths relative to the sequence folder (``join(seq, data[name])`` unless
  None); the Kinect count is ``len(kinects)`` (3 when absent) and the file ids are
  ``range(count)``; ``get_obj_name(convert=True)`` maps any ``*chair*`` category to ``chair``
  and ``*ball*`` to ``sports ball``.
* ``tools/video2images.py``: ``config='../../calibs/{date}/config'``,
  ``intrinsic='../../calibs/intrinsics'``, ``empty='../../calibs/{date}/background'``,
  ``beta=None``; frame folders ``'t{:08.3f}'.format(t)`` (= ``t%04d.%03d``), 30 fps by default;
  ``data/utils.py`` ``save_color_depth``: colour by PIL (``.jpg``), depth by ``cv2.imwrite``
  (``.png``).
* ``data/sync_frame.py`` (``KinectFrameReader``): frames are the sorted folder entries; a frame is
  complete if ``k{k}.color.{ext}`` (``jpg`` or ``png``) and ``k{k}.depth.png`` exist for every
  Kinect; depth is read with ``cv2.IMREAD_ANYDEPTH``; ``get_timestamps`` = ``float(name[1:])``.
* ``data/frame_data.py``: person mask ``k{k}.person_mask.png`` else ``.jpg``; object mask
  ``k{k}.obj_rend_mask.{png,jpg}`` else ``k{k}.obj_mask.{png,jpg}``; masks read grey and
  thresholded ``> 127``; fits ``person/<fit>/person_fit.pkl`` (``pose``, ``betas``, ``trans``)
  and ``<obj>/<fit>/<obj>_fit.pkl`` (``angle``, ``trans``) with ``obj`` the converted name
  first, then the raw category; it loads them with ``pickle`` (we never do).
* ``data/utils.py``: ``load_intrinsics`` reads ``intrinsics/<k>/calibration.json`` **and**
  ``intrinsics/<k>/pointcloud_table.npy``; ``load_kinect_poses`` reads
  ``config/<k>/config.json`` keys ``rotation`` (9 numbers, ``reshape(3, 3)``) and
  ``translation`` (3); ``load_kinect_poses_back`` inverts them; ``rotate_yaxis`` left-multiplies
  ``diag(-1, -1, 1)`` "to let y-axis point up".
* ``data/kinect_calib.py`` (``KinectCalib``): ``calibration.json`` is **not** the Azure device
  JSON but a flat one: ``color`` / ``depth`` objects with ``width``, ``height``, ``fx``, ``fy``,
  ``cx``, ``cy``, ``opencv`` (``opencv[4:]`` = the 8 OpenCV distortion coefficients passed to
  ``cv2.projectPoints``) and, in newer files, ``codx``, ``cody``, ``metric_radius``;
  ``color_to_depth`` / ``depth_to_color`` each ``{rotation (9), translation (3)}``;
  ``pc2color`` applies ``depth_to_color`` as ``p @ R.T + t`` to point clouds in **metres**.
  ``dmap2pc``: ``pointcloud_table`` is (H,W,2) ``(x/z, y/z)`` per colour pixel; points =
  ``[table, 1] * depth / 1000``, NaN entries invalid.
* ``data/kinect_transform.py``: ``local2world`` = ``config.json``'s R, t ("assume mesh world
  coordinate is in k1 color camera coordinate"); ``tools/rgbd2pclouds.py`` maps colour-camera
  points with ``pc @ R.T + t``: ``config.json`` holds **world-from-colour-camera**.
* ``challenges/lib/config.py``: ``IMAGE_WIDTH = 2048``, ``IMAGE_HEIGHT = 1536`` (colour 1536P).

Not in the BEHAVE code, so decided here: the first four ``opencv`` entries (never read by BEHAVE;
written ``[fx, fy, cx, cy]`` as a third-party BEHAVE converter that mirrors the real files does;
this reader uses the named keys); the unit of ``depth_to_color.translation`` (BEHAVE's code
treats it as metres and we write metres; the SDK's own extrinsics are millimetres, so a
translation longer than 1 — impossible for the ~32 mm baseline in metres — is read as mm);
``serial`` (written; that converter writes it too). The extra files ``couch_world.json`` and
``azure_calibration.json`` are ours; BEHAVE's loaders never list a folder, so they ignore them.

Pose convention
---------------
BEHAVE's world is the colour camera of Kinect 1 (file id ``k1``; ``k0`` when there is only one
camera): OpenCV axes, +Y **down**, not levelled. ``config/<k>/config.json`` stores
``behave_from_color_k`` (``p_behave = R @ p_color_k + t``, metres, R row-major), so Kinect 1's is
the identity. Our world (DESIGN.md: metres, +Y up, floor y = 0) is related by
``world_from_behave = world_from_color[1]``, kept in ``couch_world.json`` (same keys and
direction: ``p_world = R @ p_behave + t``), and the reader returns
``world_from_color[k] = world_from_behave @ behave_from_color_k``. A real BEHAVE folder has no
``couch_world.json``: the reader then uses BEHAVE's own ``rotate_yaxis`` flip ``diag(-1,-1,1)``
(Y up, but neither levelled nor with the floor at 0), sets ``floor_aligned = False`` and says so
in ``warnings``; the floor has to be estimated from the data.

Bad input: a missing or malformed ``info.json``, calibration or camera pose, a colour image whose
size does not match the calibration, a depth PNG that is not 16-bit grey or not registered to
the colour image raise :class:`BehaveFormatError` naming the file. Where the rest stays usable a
frame is skipped, counted and reported in ``BehaveSequence.skipped`` (``strict=True`` raises
instead): a folder whose name is not ``t%04d.%03d``, a frame with a missing, truncated or
undecodable colour/depth image, a corrupt mask (the frame is kept without that mask).
:meth:`BehaveSequence.iter_camera` (one camera, for :mod:`couch.capture.frames`) drops only the
damaged image of a frame, as a Kinect capture does, and skips the frame when neither is usable.
"""

from __future__ import annotations

import json
import math
import os
import pickle
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from couch.atomic import atomic_path
from couch.geometry import invert_transform, make_transform
from couch.safe_pickle import UnsafePickleError, safe_load_pickle

from .azure_calibration import (
    COLOR_RESOLUTIONS,
    DEFAULT_METRIC_RADIUS,
    DEPTH_MODES,
    CameraIntrinsics,
    KinectCalibration,
)
from .azure_mkv import _jpeg_size
from .registration import pixel_rays

__all__ = [
    "BEHAVE_Y_UP",
    "OBJECT_FIT",
    "PERSON_FIT",
    "BehaveFormatError",
    "BehaveFrame",
    "BehaveSequence",
    "BehaveSkip",
    "BehaveWriter",
    "CameraFrame",
    "FrameImages",
    "frame_name",
    "open_behave_sequence",
    "parse_frame_name",
]

#: Default fit folders of the BEHAVE release (README: SMPL-H in ``fit02``, objects in ``fit01``).
PERSON_FIT = "fit02"
OBJECT_FIT = "fit01"
#: BEHAVE's ``rotate_yaxis`` (data/utils.py): (4,4) flip that makes the camera's Y point up.
BEHAVE_Y_UP = np.diag([-1.0, -1.0, 1.0, 1.0])
WORLD_FILE = "couch_world.json"
AZURE_FILE = "azure_calibration.json"
GENDERS = ("male", "female", "neutral")

_FRAME_RE = re.compile(r"^t(\d{4}|[1-9]\d{4,})\.(\d{3})$")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"IEND\xaeB`\x82"
# PNG IHDR colour types (PNG spec, 11.2.2).
_PNG_COLOUR_TYPES = {0: "grey", 2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}
# A rotation read from a file counts as one if R Rᵀ = I to this tolerance (float32 storage).
_ROTATION_TOL = 1e-3


class BehaveFormatError(ValueError):
    """A BEHAVE-style sequence (or one of its files) cannot be read; the message names the file
    and what was expected."""


class _Unusable(BehaveFormatError):
    """A damaged or missing per-frame file: the frame is skipped unless the reader is strict."""

    def __init__(self, path: Path, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path = path
        self.reason = reason


@dataclass
class BehaveSkip:
    """Something a reader skipped: ``frame`` (folder name, None for sequence-level entries),
    the file or folder, and why."""

    frame: str | None
    path: Path
    reason: str


@dataclass
class FrameImages:
    """One camera's images of one frame, all in the **colour camera's** pixel grid.

    Attributes:
        color_rgb: (H,W,3) uint8 RGB.
        depth_mm: (H,W) uint16 colour-camera Z in millimetres, 0 = invalid (registered depth, see
            :func:`couch.capture.registration.register_depth_to_color`).
        person_mask: (H,W) bool, or None.
        object_mask: (H,W) bool, or None.
    """

    color_rgb: np.ndarray
    depth_mm: np.ndarray
    person_mask: np.ndarray | None = None
    object_mask: np.ndarray | None = None


def frame_name(time_s: float) -> str:
    """Folder name of the frame at ``time_s`` seconds: ``t%04d.%03d`` (BEHAVE's
    ``'t{:08.3f}'``), rounded to the millisecond. Raises ValueError for negative/non-finite."""
    t = float(time_s)
    if not math.isfinite(t) or t < 0:
        raise ValueError(f"frame time must be a finite number of seconds >= 0, got {time_s!r}")
    sec, ms = divmod(math.floor(t * 1000.0 + 0.5), 1000)
    return f"t{sec:04d}.{ms:03d}"


def parse_frame_name(name: str) -> float | None:
    """Time in seconds of a frame folder name ``t%04d.%03d``, or None if it is not one."""
    m = _FRAME_RE.match(name)
    if m is None:
        return None
    return int(m.group(1)) + int(m.group(2)) / 1000.0


def _object_folders(category: str) -> list[str]:
    """Folder names a frame's object fit may sit under (frame_data.py ``objfit_param_file``)."""
    names = []
    if "chair" in category:
        names.append("chair")
    elif "ball" in category:
        names.append("sports ball")
    names.append(category)
    return list(dict.fromkeys(names))


# ================================================================ small helpers
def _check_name(value: Any, what: str) -> str:
    if not isinstance(value, str) or not _NAME_RE.match(value):
        raise ValueError(f"{what} must be a plain folder name (letters, digits, '_', '-', '.'), "
                         f"got {value!r}")
    return value


def _rigid(t: Any, what: str) -> np.ndarray:
    m = np.asarray(t, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"{what} must be a finite (4,4) matrix, got shape {m.shape}")
    r = m[:3, :3]
    if (not np.allclose(m[3], [0, 0, 0, 1]) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6)
            or np.linalg.det(r) <= 0):
        raise ValueError(f"{what} must be a rigid transform (rotation + translation)")
    return m


def _pose_doc(t: np.ndarray) -> dict[str, list[float]]:
    """BEHAVE's ``config.json`` keys: row-major rotation (9) and translation (3, metres)."""
    return {"rotation": [float(v) for v in t[:3, :3].reshape(-1)],
            "translation": [float(v) for v in t[:3, 3]]}


def _json_text(doc: Any) -> str:
    return json.dumps(doc, indent=2, ensure_ascii=False, allow_nan=False) + "\n"


def _write_bytes(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def _same(a: Any, b: Any) -> bool:
    """JSON documents equal up to float round-off (1e-9 relative)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if (isinstance(a, int | float) and isinstance(b, int | float)
            and not isinstance(a, bool) and not isinstance(b, bool)):
        return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)
    return a == b


def _write_shared_json(path: Path, doc: Any) -> bool:
    """Write a calibration file that other sequences may share; refuse to change it.

    Returns True if the file was written, False if an identical one was already there.
    """
    if path.exists():
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            old = None
        if old is not None:
            if _same(old, doc):
                return False
            raise ValueError(f"{path} already holds a different calibration (another session "
                             f"written to the same root?); write to a new root or remove it")
    with atomic_path(path) as tmp:
        tmp.write_text(_json_text(doc), encoding="utf-8")
    return True


def _behave_camera(intr: CameraIntrinsics) -> dict[str, Any]:
    k1, k2, p1, p2, k3, k4, k5, k6 = (float(v) for v in intr.dist)
    return {
        "width": intr.width, "height": intr.height,
        "fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
        "k1": k1, "k2": k2, "k3": k3, "k4": k4, "k5": k5, "k6": k6, "p1": p1, "p2": p2,
        "codx": 0.0, "cody": 0.0, "metric_radius": intr.metric_radius,
        # BEHAVE reads opencv[4:] as cv2's distortion vector [k1,k2,p1,p2,k3,k4,k5,k6].
        "opencv": [intr.fx, intr.fy, intr.cx, intr.cy, k1, k2, p1, p2, k3, k4, k5, k6],
    }


def _behave_calibration_doc(calib: KinectCalibration) -> dict[str, Any]:
    """BEHAVE's ``intrinsics/<k>/calibration.json`` for one device (metres)."""
    return {
        "serial": calib.serial,
        "color": _behave_camera(calib.color),
        "depth": _behave_camera(calib.depth),
        "color_to_depth": _pose_doc(invert_transform(calib.color_from_depth)),
        "depth_to_color": _pose_doc(calib.color_from_depth),
    }


# ================================================================ writer
class BehaveWriter:
    """Write one sequence in BEHAVE's layout (see module doc for files and pose convention).

    The constructor writes ``info.json`` and the calibration files (shared by all sequences of a
    ``date`` under ``root``: an existing, different calibration is an error, never overwritten);
    :meth:`write_frame` writes one frame folder. Usable as a context manager (nothing to close).

    Args:
        root: folder holding the sequence folder and ``calibs``.
        sequence_name: e.g. ``Date03_Sub03_chairwood_sit`` (a plain folder name).
        date: calibration folder name, e.g. ``Date03``.
        calibrations: one :class:`KinectCalibration` per camera, in file-id order (``k0``...).
        world_from_color: (N,4,4) poses of the colour cameras in our world (metres, +Y up,
            floor y = 0).
        gender: ``male``, ``female`` or ``neutral`` (``info.json`` ``gender``).
        object_category: object name, e.g. ``chairwood`` (``info.json`` ``cat``).
        betas: subject shape (``info.json`` ``beta``), or None.
        jpeg_quality: colour JPEG quality (1-100).
        pointcloud_tables: also write ``pointcloud_table.npy`` (BEHAVE's loaders require it;
            ~25 MB per 2048x1536 camera, computed once per calibration).
    """

    def __init__(self, root: str | os.PathLike, sequence_name: str, date: str,
                 calibrations: Sequence[KinectCalibration], world_from_color: Any, *,
                 gender: str, object_category: str, betas: Any = None,
                 jpeg_quality: int = 95, pointcloud_tables: bool = True) -> None:
        self.sequence_name = _check_name(sequence_name, "sequence_name")
        if sequence_name == "calibs":
            raise ValueError("sequence_name 'calibs' would collide with the calibration folder")
        self.date = _check_name(date, "date")
        self.object_category = _check_name(object_category, "object_category")
        if gender not in GENDERS:
            raise ValueError(f"gender must be one of {GENDERS}, got {gender!r}")
        self.calibrations = list(calibrations)
        if not self.calibrations:
            raise ValueError("need at least one camera calibration")
        for i, c in enumerate(self.calibrations):
            if not isinstance(c, KinectCalibration):
                raise TypeError(f"calibrations[{i}] is {type(c).__name__}, expected "
                                "KinectCalibration")
        poses = np.asarray(world_from_color, dtype=np.float64)
        if poses.shape != (len(self.calibrations), 4, 4):
            raise ValueError(f"world_from_color must be ({len(self.calibrations)}, 4, 4) for "
                             f"{len(self.calibrations)} cameras, got shape {poses.shape}")
        self.world_from_color = [_rigid(p, f"world_from_color[{i}]")
                                 for i, p in enumerate(poses)]
        if betas is not None:
            b = np.asarray(betas, dtype=np.float64)
            if b.ndim != 1 or not np.all(np.isfinite(b)):
                raise ValueError(f"betas must be a finite 1-D array, got shape {b.shape}")
            betas = [float(v) for v in b]
        if not 1 <= int(jpeg_quality) <= 100:
            raise ValueError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
        self.jpeg_quality = int(jpeg_quality)

        self.root = Path(root)
        self.sequence_path = self.root / self.sequence_name
        self.config_path = self.root / "calibs" / self.date / "config"
        self.intrinsics_path = self.root / "calibs" / "intrinsics"
        n = len(self.calibrations)
        #: File id of the camera whose colour frame is BEHAVE's world.
        self.reference_kinect = 1 if n > 1 else 0
        self.world_from_behave = self.world_from_color[self.reference_kinect]
        behave_from_world = invert_transform(self.world_from_behave)
        self.behave_from_color = [behave_from_world @ w for w in self.world_from_color]
        self.frame_names: list[str] = []

        for k, calib in enumerate(self.calibrations):
            folder = self.intrinsics_path / str(k)
            wrote = _write_shared_json(folder / "calibration.json", _behave_calibration_doc(calib))
            azure = folder / AZURE_FILE
            if wrote or not azure.exists():
                # Only the IMU/metadata sections can differ once calibration.json matched: the
                # first writer's factory file stays.
                with atomic_path(azure) as tmp:
                    tmp.write_text(_json_text(json.loads(calib.to_json())), encoding="utf-8")
            table = folder / "pointcloud_table.npy"
            if pointcloud_tables and (wrote or not table.exists()):
                rays = pixel_rays(calib.color).astype(np.float32)
                with atomic_path(table) as tmp, tmp.open("wb") as f:
                    np.save(f, rays, allow_pickle=False)
            _write_shared_json(self.config_path / str(k) / "config.json",
                               _pose_doc(self.behave_from_color[k]))
        world_doc = {
            **_pose_doc(self.world_from_behave),
            "reference_kinect": self.reference_kinect,
            "description": ("world_from_behave: p_world = R @ p_behave + t (metres, R row-major)."
                            " couch world: +Y up, floor at y = 0. BEHAVE world: colour camera "
                            f"of k{self.reference_kinect}, +Y down."),
        }
        _write_shared_json(self.config_path / WORLD_FILE, world_doc)

        seq = self.sequence_path
        info = {
            "config": Path(os.path.relpath(self.config_path, seq)).as_posix(),
            "intrinsic": Path(os.path.relpath(self.intrinsics_path, seq)).as_posix(),
            "cat": self.object_category,
            "gender": gender,
            "empty": None,  # no background capture is written
            "kinects": list(range(n)),
            "beta": betas,
        }
        with atomic_path(seq / "info.json") as tmp:
            tmp.write_text(_json_text(info), encoding="utf-8")
        self.info = info

    def __enter__(self) -> BehaveWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def _encode_camera(self, k: int, im: FrameImages) -> dict[str, bytes | None]:
        calib = self.calibrations[k]
        h, w = calib.color.height, calib.color.width
        color = np.asarray(im.color_rgb)
        if color.shape != (h, w, 3) or color.dtype != np.uint8:
            raise ValueError(f"camera {k}: color_rgb must be ({h}, {w}, 3) uint8 to match its "
                             f"calibration ({calib.color_resolution}), got {color.shape} "
                             f"{color.dtype}")
        depth = np.asarray(im.depth_mm)
        if depth.shape != (h, w) or depth.dtype != np.uint16:
            raise ValueError(f"camera {k}: depth_mm must be ({h}, {w}) uint16 millimetres "
                             f"registered to the colour image, got {depth.shape} {depth.dtype}")
        out: dict[str, bytes | None] = {}
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(color[..., ::-1]),
                               [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise ValueError(f"camera {k}: colour image could not be JPEG-encoded")
        out["color.jpg"] = buf.tobytes()
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(depth))
        if not ok:
            raise ValueError(f"camera {k}: depth image could not be PNG-encoded")
        out["depth.png"] = buf.tobytes()
        for key, mask in (("person_mask.png", im.person_mask),
                          ("obj_rend_mask.png", im.object_mask)):
            if mask is None:
                out[key] = None
                continue
            m = np.asarray(mask)
            if m.shape != (h, w) or m.dtype != np.bool_:
                raise ValueError(f"camera {k}: {key.split('.')[0]} must be ({h}, {w}) bool, got "
                                 f"{m.shape} {m.dtype}")
            ok, buf = cv2.imencode(".png", m.astype(np.uint8) * np.uint8(255))
            if not ok:
                raise ValueError(f"camera {k}: {key} could not be PNG-encoded")
            out[key] = buf.tobytes()
        return out

    def write_frame(self, time_s: float, images: Sequence[FrameImages]) -> Path:
        """Write the frame folder ``t%04d.%03d`` of ``time_s`` (seconds, >= 0, ms resolution).

        Args:
            time_s: frame time in seconds (BEHAVE names frames by their time).
            images: one :class:`FrameImages` per camera, in calibration order; every image in
                the colour camera's size (depth registered to colour).

        Returns:
            the frame folder. All images are validated and encoded before anything is written;
            each file is then written atomically. A mask given as None removes a stale mask
            file of an earlier write of the same frame.
        """
        name = frame_name(time_s)
        if name in self.frame_names:
            raise ValueError(f"frame {name} (t = {time_s} s) was already written; frame times "
                             "must differ by at least 1 ms")
        images = list(images)
        if len(images) != len(self.calibrations):
            raise ValueError(f"expected images of {len(self.calibrations)} cameras, got "
                             f"{len(images)}")
        encoded = [self._encode_camera(k, im) for k, im in enumerate(images)]
        folder = self.sequence_path / name
        folder.mkdir(parents=True, exist_ok=True)
        for k, files in enumerate(encoded):
            for key, data in files.items():
                path = folder / f"k{k}.{key}"
                if data is None:
                    path.unlink(missing_ok=True)
                else:
                    _write_bytes(path, data)
        self.frame_names.append(name)
        return folder


# ================================================================ reading helpers
def _read_json(path: Path, what: str) -> Any:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise BehaveFormatError(f"{path}: {what} is missing") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise BehaveFormatError(f"{path}: cannot read {what}: {exc}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise BehaveFormatError(f"{path}: {what} is not valid JSON: {exc}") from None


def _number(value: Any, path: Path, what: str) -> float:
    if (not isinstance(value, int | float) or isinstance(value, bool)
            or not math.isfinite(value)):
        raise BehaveFormatError(f"{path}: {what} must be a finite number, got {value!r:.100}")
    return float(value)


def _numbers(value: Any, n: int, path: Path, what: str, at_least: bool = False) -> list[float]:
    if not isinstance(value, list) or (len(value) < n if at_least else len(value) != n):
        count = f"at least {n}" if at_least else str(n)
        raise BehaveFormatError(f"{path}: {what} must be a list of {count} numbers, got "
                                f"{value!r:.100}")
    return [_number(v, path, what) for v in value[:n]]


def _pose_from_doc(doc: Any, path: Path, what: str) -> np.ndarray:
    if not isinstance(doc, dict):
        raise BehaveFormatError(f"{path}: {what} must be an object with 'rotation' and "
                                f"'translation', got {type(doc).__name__}")
    rot = np.array(_numbers(doc.get("rotation"), 9, path, f"{what} 'rotation'")).reshape(3, 3)
    trans = np.array(_numbers(doc.get("translation"), 3, path, f"{what} 'translation'"))
    if (not np.allclose(rot @ rot.T, np.eye(3), atol=_ROTATION_TOL)
            or np.linalg.det(rot) <= 0):
        raise BehaveFormatError(f"{path}: {what} 'rotation' is not a rotation matrix "
                                f"(row-major 3x3 expected)")
    return make_transform(rot, trans)


def _intrinsics_from_doc(doc: Any, path: Path, what: str) -> CameraIntrinsics:
    if not isinstance(doc, dict):
        raise BehaveFormatError(f"{path}: '{what}' must be an object")
    size = []
    for key in ("width", "height"):
        v = doc.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
            raise BehaveFormatError(f"{path}: '{what}.{key}' must be a positive integer, got "
                                    f"{v!r}")
        size.append(v)
    fx, fy, cx, cy = (_number(doc.get(k), path, f"'{what}.{k}'") for k in ("fx", "fy", "cx", "cy"))
    if "opencv" in doc:
        dist = _numbers(doc["opencv"], 12, path, f"'{what}.opencv'", at_least=True)[4:12]
    else:
        dist = [_number(doc.get(k), path, f"'{what}.{k}'")
                for k in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")]
    for key in ("codx", "cody"):
        if key in doc and _number(doc[key], path, f"'{what}.{key}'") != 0.0:
            raise BehaveFormatError(f"{path}: '{what}.{key}' is non-zero (Rational6KT lens "
                                    "model, which OpenCV's model cannot express)")
    # Older BEHAVE files have no metric_radius (KinectCalib then uses NaN); the SDK treats
    # <= 0.0001 as "not estimated" and uses its default.
    radius = doc.get("metric_radius")
    if (not isinstance(radius, int | float) or isinstance(radius, bool)
            or not math.isfinite(radius) or radius <= 0.0001):
        radius = DEFAULT_METRIC_RADIUS
    try:
        return CameraIntrinsics(size[0], size[1], fx, fy, cx, cy, np.array(dist), radius)
    except ValueError as exc:
        raise BehaveFormatError(f"{path}: '{what}': {exc}") from None


def _mode_for(size: tuple[int, int], table: dict, path: Path, what: str) -> str:
    for mode, info in table.items():
        if (info.width, info.height) == size:
            return mode
    known = sorted({f"{i.width}x{i.height}" for i in table.values()})
    raise BehaveFormatError(f"{path}: {what} size {size[0]}x{size[1]} is not an Azure Kinect "
                            f"mode ({', '.join(known)})")


def _calibration_from_doc(doc: Any, path: Path) -> KinectCalibration:
    """BEHAVE's ``calibration.json`` -> :class:`KinectCalibration` (see module doc)."""
    if isinstance(doc, dict) and "CalibrationInformation" in doc:
        raise BehaveFormatError(f"{path}: is an Azure device calibration, not BEHAVE's "
                                "calibration.json (keys 'color', 'depth', 'depth_to_color')")
    if not isinstance(doc, dict):
        raise BehaveFormatError(f"{path}: expected a JSON object")
    color = _intrinsics_from_doc(doc.get("color"), path, "color")
    depth = _intrinsics_from_doc(doc.get("depth"), path, "depth")
    color_from_depth = _pose_from_doc(doc.get("depth_to_color"), path, "'depth_to_color'")
    if np.linalg.norm(color_from_depth[:3, 3]) > 1.0:
        # Metres cannot exceed ~0.05 for the colour-depth baseline: this file stores the SDK's mm.
        color_from_depth[:3, 3] /= 1000.0
    depth_mode = _mode_for((depth.width, depth.height), DEPTH_MODES, path, "depth")
    color_res = _mode_for((color.width, color.height), COLOR_RESOLUTIONS, path, "colour")
    serial = doc.get("serial")
    try:
        return KinectCalibration(depth=depth, color=color, color_from_depth=color_from_depth,
                                 depth_mode=depth_mode, color_resolution=color_res,
                                 serial="" if serial is None else str(serial))
    except ValueError as exc:
        raise BehaveFormatError(f"{path}: {exc}") from None


def _read_file(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise _Unusable(path, "missing") from None
    except OSError as exc:
        raise _Unusable(path, f"cannot read: {exc.strerror or exc}") from None


def _jpeg_complete(data: bytes, path: Path) -> None:
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        raise _Unusable(path, "not a JPEG (no SOI marker FFD8 at its start)")
    # 0xFFD9 cannot occur inside entropy-coded data (0xFF is stuffed there), so a file that does
    # not end with EOI was cut off; OpenCV would silently decode the rest as grey.
    if not data[-64:].rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise _Unusable(path, f"truncated JPEG (no EOI marker FFD9 at its end, {len(data)} "
                        "bytes)")


def _png_header(data: bytes, path: Path) -> tuple[int, int]:
    """(bit depth, colour type) of a complete PNG; _Unusable if not a PNG or cut off."""
    if len(data) < 33 or data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR":
        raise _Unusable(path, "not a PNG (no PNG signature and IHDR chunk)")
    if _PNG_IEND not in data[-64:]:
        raise _Unusable(path, f"truncated PNG (no IEND chunk at its end, {len(data)} bytes)")
    return data[24], data[25]


def _decode(data: bytes, flags: int, path: Path) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    if img is None:
        raise _Unusable(path, f"corrupt image, could not be decoded ({len(data)} bytes)")
    return img


def _read_image_bytes(path: Path) -> bytes:
    """The file's bytes, after checking its PNG header or that its JPEG is complete."""
    data = _read_file(path)
    if path.suffix.lower() == ".png":
        _png_header(data, path)
    else:
        _jpeg_complete(data, path)
    return data


def _image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR or a JPEG's frame header, without decoding."""
    if data[:8] == _PNG_SIGNATURE and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return _jpeg_size(data)


def _read_color_bytes(path: Path, calib: KinectCalibration, camera: Path) -> bytes:
    """A colour image's bytes, checked complete and of the calibration's size (not decoded).

    Raises _Unusable (missing, cut off, no image header) or BehaveFormatError (wrong size: the
    calibration in ``camera`` does not describe this image)."""
    data = _read_image_bytes(path)
    size = _image_size(data)
    if size is None:
        raise _Unusable(path, "not an image (no PNG IHDR or JPEG frame header)")
    w, h = calib.color.width, calib.color.height
    if size != (w, h):
        raise BehaveFormatError(f"{path}: colour image is {size[0]}x{size[1]}, calibration "
                                f"{camera} is for {w}x{h}")
    return data


def _decode_color(data: bytes, path: Path) -> np.ndarray:
    """Encoded colour image -> (H,W,3) uint8 RGB; _Unusable naming ``path`` if undecodable."""
    bgr = _decode(data, cv2.IMREAD_COLOR, path)
    if bgr.ndim != 3 or bgr.shape[2] != 3:
        raise _Unusable(path, f"colour image decoded as {bgr.shape}, expected (H, W, 3)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _read_depth(path: Path) -> np.ndarray:
    data = _read_file(path)
    bit_depth, colour_type = _png_header(data, path)
    if bit_depth != 16 or colour_type != 0:
        kind = _PNG_COLOUR_TYPES.get(colour_type, f"colour type {colour_type}")
        raise BehaveFormatError(f"{path}: depth PNG is {bit_depth}-bit {kind}, expected 16-bit "
                                "grey (uint16 millimetres)")
    depth = _decode(data, cv2.IMREAD_UNCHANGED, path)
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise BehaveFormatError(f"{path}: depth decoded as {depth.dtype} {depth.shape}, "
                                "expected (H, W) uint16")
    return depth


def _read_mask(path: Path) -> np.ndarray:
    return _decode(_read_image_bytes(path), cv2.IMREAD_GRAYSCALE, path) > 127


def _first_existing(folder: Path, names: Sequence[str]) -> Path | None:
    for n in names:
        p = folder / n
        if p.is_file():
            return p
    return None


# ================================================================ reader
@dataclass
class BehaveFrame:
    """One frame of a sequence: its time and every camera's images.

    Fits (``person/fit02/person_fit.pkl``, ``<object>/fit01/<object>_fit.pkl``) are read only
    when asked for, with :func:`couch.safe_pickle.safe_load_pickle`. Their parameters are in
    BEHAVE's world (Kinect 1's colour camera); ``BehaveSequence.world_from_behave`` maps them
    into ours.

    Attributes:
        time_s: seconds, from the folder name.
        images: one :class:`FrameImages` per camera (file ids ``k0``...).
        name: folder name, e.g. ``t0003.000``.
        path: the frame folder.
        category: the sequence's object category (``info.json`` ``cat``).
    """

    time_s: float
    images: list[FrameImages]
    name: str
    path: Path
    category: str

    def person_fit_path(self, save_name: str = PERSON_FIT) -> Path:
        """``person/<save_name>/person_fit.pkl`` of this frame (may not exist)."""
        return self.path / "person" / save_name / "person_fit.pkl"

    def object_fit_path(self, save_name: str = OBJECT_FIT) -> Path:
        """``<obj>/<save_name>/<obj>_fit.pkl``, ``obj`` as BEHAVE looks it up (``chair`` for any
        chair category, then the category itself); the first that exists, else the first."""
        paths = [self.path / n / save_name / f"{n}_fit.pkl"
                 for n in _object_folders(self.category)]
        return next((p for p in paths if p.is_file()), paths[0])

    def person_fit(self, save_name: str = PERSON_FIT) -> dict[str, Any] | None:
        """The SMPL-H fit (``pose``, ``betas``, ``trans`` ...) or None if the file is absent.

        Raises:
            BehaveFormatError: the pickle is unreadable or asks for anything but numpy arrays
                and plain containers.
        """
        return _load_fit(self.person_fit_path(save_name))

    def object_fit(self, save_name: str = OBJECT_FIT) -> dict[str, Any] | None:
        """The object fit (``angle`` axis-angle, ``trans``) or None if the file is absent."""
        return _load_fit(self.object_fit_path(save_name))


def _load_fit(path: Path) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        fit = safe_load_pickle(path)
    except UnsafePickleError as exc:
        raise BehaveFormatError(f"unsafe fit pickle: {exc}") from exc
    except (pickle.UnpicklingError, OSError) as exc:
        raise BehaveFormatError(f"{path}: unreadable fit pickle: {exc}") from exc
    if not isinstance(fit, dict):
        raise BehaveFormatError(f"{path}: fit pickle holds a {type(fit).__name__}, expected a "
                                "dict of arrays")
    return fit


@dataclass
class CameraFrame:
    """One camera's images of one frame as :meth:`BehaveSequence.iter_camera` streams them.

    Attributes:
        index: position of the frame in ``BehaveSequence.frame_names``.
        name: frame folder name (``t0003.000``); ``time_s`` its time in seconds.
        kinect: the camera's file id.
        color_path: the colour file (``k<k>.color.jpg``/``.png``), None if unusable.
        color_data: its bytes (complete, of the calibration's size; not yet decoded), or None.
        depth_mm: (H,W) uint16 colour-camera Z in millimetres, 0 = invalid (registered to the
            colour image, colour size), or None if missing/damaged.
    """

    index: int
    name: str
    time_s: float
    kinect: int
    color_path: Path | None
    color_data: bytes | None
    depth_mm: np.ndarray | None

    def color_rgb(self) -> np.ndarray | None:
        """The colour image decoded: (H,W,3) uint8 RGB, or None if the frame has none.

        Raises:
            BehaveFormatError: naming the file, if it cannot be decoded.
        """
        if self.color_data is None or self.color_path is None:
            return None
        return _decode_color(self.color_data, self.color_path)


class BehaveSequence:
    """An opened BEHAVE-style sequence; iterate it for :class:`BehaveFrame` one at a time.

    Each iteration reads the frame folders afresh; frames that cannot be used are skipped and
    recorded in :attr:`skipped` (reset at the start of each iteration, keeping the entries found
    when opening); ``strict=True`` raises :class:`BehaveFormatError` instead.

    Attributes:
        path: the sequence folder; ``name`` its name.
        info: ``info.json`` as stored (paths relative to the sequence folder).
        kinects: file ids ``0..N-1`` (BEHAVE: ``range(len(info['kinects']))``).
        calibrations: one :class:`KinectCalibration` per camera.
        behave_from_color: (4,4) per camera, as in ``config.json`` (BEHAVE world, +Y down).
        world_from_behave: (4,4) BEHAVE world -> our world (``couch_world.json``, or
            :data:`BEHAVE_Y_UP` when the folder has none).
        world_from_color: (4,4) per camera in OUR world (metres, +Y up; floor y = 0 when
            ``floor_aligned``).
        floor_aligned: whether ``world_from_behave`` came from ``couch_world.json``.
        frame_names: frame folder names sorted by time; ``frame_times`` (F,) float64 seconds.
        skipped: :class:`BehaveSkip` entries; ``warnings``: sequence-level remarks.
        config_path, intrinsics_path: the calibration folders ``info.json`` points to.
    """

    def __init__(self, path: str | os.PathLike, *, strict: bool = False) -> None:
        self.path = Path(path)
        self.name = self.path.name
        self.strict = strict
        self.warnings: list[str] = []
        if not self.path.is_dir():
            raise BehaveFormatError(f"{self.path}: not a sequence folder (does not exist or is "
                                    "not a directory)")
        info_path = self.path / "info.json"
        info = _read_json(info_path, "info.json")
        if not isinstance(info, dict):
            raise BehaveFormatError(f"{info_path}: expected a JSON object")
        for key in ("config", "intrinsic", "cat", "gender"):
            if not isinstance(info.get(key), str) or not info[key]:
                raise BehaveFormatError(f"{info_path}: key {key!r} must be a non-empty string, "
                                        f"got {info.get(key)!r}")
        kinects = info.get("kinects")
        if kinects is None:
            count = 3  # seq_utils.py kinect_count(): 3 when 'kinects' is absent
        elif isinstance(kinects, list) and kinects:
            count = len(kinects)
        else:
            raise BehaveFormatError(f"{info_path}: 'kinects' must be a non-empty list, got "
                                    f"{kinects!r}")
        self.info = info
        self.kinects = list(range(count))
        # BEHAVE joins these onto the sequence folder (os.path.join: absolute paths stay).
        self.config_path = self.path / info["config"]
        self.intrinsics_path = self.path / info["intrinsic"]

        self.calibrations: list[KinectCalibration] = []
        self.behave_from_color: list[np.ndarray] = []
        for k in self.kinects:
            cpath = self.intrinsics_path / str(k) / "calibration.json"
            calib = _calibration_from_doc(_read_json(cpath, "camera calibration"), cpath)
            apath = self.intrinsics_path / str(k) / AZURE_FILE
            if apath.is_file():
                doc = _read_json(apath, "Azure factory calibration")
                ci = doc.get("CalibrationInformation") if isinstance(doc, dict) else None
                if isinstance(ci, dict):
                    calib.extra = {key: ci[key] for key in ("InertialSensors", "Metadata")
                                   if key in ci} or None
            self.calibrations.append(calib)
            ppath = self.config_path / str(k) / "config.json"
            self.behave_from_color.append(
                _pose_from_doc(_read_json(ppath, "camera pose"), ppath, "camera pose"))
        wpath = self.config_path / WORLD_FILE
        if wpath.is_file():
            self.world_from_behave = _pose_from_doc(_read_json(wpath, "world transform"), wpath,
                                                    "world transform")
            self.floor_aligned = True
        else:
            self.world_from_behave = BEHAVE_Y_UP.copy()
            self.floor_aligned = False
            self.warnings.append(
                f"{wpath} is absent (a BEHAVE release folder): world_from_color uses BEHAVE's "
                "y-up flip of Kinect 1's colour camera; it is not levelled and the floor is not "
                "at y = 0")
        self.world_from_color = [self.world_from_behave @ b for b in self.behave_from_color]

        self._open_skips: list[BehaveSkip] = []
        frames: list[tuple[float, str]] = []
        with os.scandir(self.path) as it:
            entries = sorted(it, key=lambda e: e.name)
        for entry in entries:
            if not entry.is_dir():
                continue  # info.json and any other files
            t = parse_frame_name(entry.name)
            if t is None:
                skip = BehaveSkip(None, Path(entry.path),
                                  "folder name is not a frame time t%04d.%03d")
                if strict:
                    raise BehaveFormatError(f"{skip.path}: {skip.reason}")
                self._open_skips.append(skip)
            else:
                frames.append((t, entry.name))
        frames.sort()
        self.frame_names = [n for _, n in frames]
        self.frame_times = np.array([t for t, _ in frames], dtype=np.float64)
        self._times = {n: t for t, n in frames}
        self.skipped: list[BehaveSkip] = list(self._open_skips)

    # ---------------------------------------------------------------- properties
    @property
    def gender(self) -> str:
        return str(self.info["gender"])

    @property
    def category(self) -> str:
        """Object category (``info.json`` ``cat``, e.g. ``chairwood``)."""
        return str(self.info["cat"])

    @property
    def betas(self) -> np.ndarray | None:
        """``info.json`` ``beta`` as a float64 array, or None (absent, null or not numbers)."""
        beta = self.info.get("beta")
        if isinstance(beta, list) and beta and all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in beta):
            return np.asarray(beta, dtype=np.float64)
        return None

    def __len__(self) -> int:
        return len(self.frame_names)

    def __repr__(self) -> str:
        return (f"BehaveSequence({str(self.path)!r}, cameras={len(self.kinects)}, "
                f"frames={len(self)}, category={self.category!r})")

    # ---------------------------------------------------------------- frames
    def _color_bytes(self, folder: Path, k: int) -> tuple[Path, bytes]:
        """Camera ``k``'s colour file in ``folder`` and its checked bytes (not decoded)."""
        cpath = _first_existing(folder, [f"k{k}.color.jpg", f"k{k}.color.png"])
        if cpath is None:
            raise _Unusable(folder / f"k{k}.color.jpg", "missing")
        camera = self.intrinsics_path / str(k)
        return cpath, _read_color_bytes(cpath, self.calibrations[k], camera)

    def _depth(self, folder: Path, k: int) -> np.ndarray:
        """Camera ``k``'s registered depth in ``folder``, checked against the colour size."""
        dpath = folder / f"k{k}.depth.png"
        depth = _read_depth(dpath)
        h, w = self.calibrations[k].color.height, self.calibrations[k].color.width
        if depth.shape != (h, w):
            raise BehaveFormatError(f"{dpath}: depth is {depth.shape[1]}x{depth.shape[0]}, "
                                    f"expected {w}x{h} (registered to the colour image)")
        return depth

    def _read_frame(self, name: str, skipped: list[BehaveSkip]) -> BehaveFrame:
        folder = self.path / name
        images = []
        for k, calib in zip(self.kinects, self.calibrations, strict=True):
            cpath, data = self._color_bytes(folder, k)
            color = _decode_color(data, cpath)
            depth = self._depth(folder, k)
            h, w = calib.color.height, calib.color.width
            masks: list[np.ndarray | None] = []
            for candidates in ([f"k{k}.person_mask.png", f"k{k}.person_mask.jpg"],
                               [f"k{k}.obj_rend_mask.png", f"k{k}.obj_mask.png",
                                f"k{k}.obj_rend_mask.jpg", f"k{k}.obj_mask.jpg"]):
                mpath = _first_existing(folder, candidates)
                mask = None
                if mpath is not None:
                    try:
                        mask = _read_mask(mpath)
                        if mask.shape != (h, w):
                            raise _Unusable(mpath, f"mask is {mask.shape[1]}x{mask.shape[0]}, "
                                            f"expected {w}x{h}")
                    except _Unusable as exc:
                        if self.strict:
                            raise
                        skipped.append(BehaveSkip(name, mpath, f"mask dropped: {exc.reason}"))
                        mask = None
                masks.append(mask)
            images.append(FrameImages(color, depth, masks[0], masks[1]))
        return BehaveFrame(time_s=self._times[name], images=images, name=name, path=folder,
                           category=self.category)

    def read_frame(self, key: int | str) -> BehaveFrame:
        """One frame by index or folder name (random access).

        Raises:
            BehaveFormatError: the frame is incomplete or damaged (masks that cannot be read are
                dropped and recorded in :attr:`skipped` unless ``strict``).
            IndexError / KeyError: no such frame.
        """
        name = self.frame_names[key] if isinstance(key, int) else key
        if name not in self.frame_names:
            raise KeyError(f"{self.path}: no frame {name!r}")
        return self._read_frame(name, self.skipped)

    def __iter__(self) -> Iterator[BehaveFrame]:
        self.skipped = list(self._open_skips)
        for name in self.frame_names:
            try:
                frame = self._read_frame(name, self.skipped)
            except _Unusable as exc:
                if self.strict:
                    raise
                self.skipped.append(BehaveSkip(name, exc.path, f"frame skipped: {exc.reason}"))
                continue
            yield frame


    def iter_camera(self, kinect: int) -> Iterator[CameraFrame]:
        """Stream one camera's colour and depth, frame by frame (masks and fits are not read).

        Unlike :meth:`__iter__`, a frame's colour and depth are usable independently, as the
        images of a Kinect capture are: a missing or damaged one is recorded in :attr:`skipped`
        (reset when the iteration starts) and the frame comes with that image None; a frame
        with neither is skipped. The colour image is checked (complete file, size from its
        header) but decoded only by :meth:`CameraFrame.color_rgb`. ``strict`` raises instead.

        Args:
            kinect: the camera's file id (``k0`` -> 0), one of :attr:`kinects`.

        Raises:
            BehaveFormatError: an image of the wrong size or a depth PNG that is not 16-bit
                grey (the sequence is inconsistent, not merely damaged), or strict mode.
            ValueError: ``kinect`` is not one of :attr:`kinects`.
        """
        if kinect not in self.kinects:
            raise ValueError(f"{self.path}: no camera k{kinect} (cameras: "
                             f"{', '.join(f'k{k}' for k in self.kinects)})")
        self.skipped = list(self._open_skips)
        for index, name in enumerate(self.frame_names):
            folder = self.path / name
            cpath: Path | None = None
            data: bytes | None = None
            depth: np.ndarray | None = None
            try:
                cpath, data = self._color_bytes(folder, kinect)
            except _Unusable as exc:
                if self.strict:
                    raise
                self.skipped.append(BehaveSkip(name, exc.path, f"colour dropped: {exc.reason}"))
            try:
                depth = self._depth(folder, kinect)
            except _Unusable as exc:
                if self.strict:
                    raise
                self.skipped.append(BehaveSkip(name, exc.path, f"depth dropped: {exc.reason}"))
            if data is None and depth is None:
                continue
            yield CameraFrame(index=index, name=name, time_s=self._times[name], kinect=kinect,
                              color_path=cpath, color_data=data, depth_mm=depth)


def open_behave_sequence(path: str | os.PathLike, *, strict: bool = False) -> BehaveSequence:
    """Open a BEHAVE-style sequence folder (one with ``info.json``).

    Reads ``info.json``, every camera's calibration and pose (and ``couch_world.json`` if
    present) and lists the frame folders; images are read while iterating.

    Args:
        path: the sequence folder, e.g. ``.../sequences/Date03_Sub03_chairwood_sit``.
        strict: raise on anything that would otherwise be skipped.

    Raises:
        BehaveFormatError: missing/malformed ``info.json``, calibration or camera pose (the
            message names the file).
    """
    return BehaveSequence(path, strict=strict)
