"""Person and chair segmentation of Azure Kinect depth images against a static background.

COUCH segmented people in the colour images with Detectron2 and fixed the masks by hand; here
the depth camera does it without manual work: the room is static, so whatever stands in front of
the room's depth is foreground, and the chair (static, its scan registered in the world) is told
apart from the person geometrically.

Pipeline per camera (everything vectorised over pixels):

1. :class:`BackgroundModel` — a robust per-pixel background depth from frames with nobody in view
   (or from a recording in which the person moves): the k-th farthest valid depth of each pixel
   (k = max(2, 10 % of its valid frames)), so that whatever stands in a pixel in all but k-1
   frames does not enter the background while a single noisy frame cannot make it either; a
   percentile would need the room to show in a fixed share of the frames, which a board held
   in a few of six captures already breaks. Pixels that are invalid in
   most frames (beyond the sensor's range, dark NFOV corners) get an infinite background: anything
   measured there is in front of the room. Which frames to use is the caller's choice; see
   :func:`background_from_recordings`. Best is a short recording of the empty room (the chair in
   place, nobody in view; the simulator writes ``background/<serial>.mkv``, found by
   :func:`empty_room_recording`): :func:`segment_recording` then builds the background from it
   alone. Without one, the ChArUco calibration captures (nobody in view; the board moves
   between captures) *and* the session's own frames (the person moves) are combined.
2. :func:`foreground` — *seeds*: pixels in front of the background by more than a
   distance-dependent margin (``margin + margin_per_m2·z²``, following the ToF noise that grows
   with z²), compared with the 3x3 *nearest* background depth so that the lateral jitter of
   background depth edges (a chair leg against a wall) does not leak slivers, and more than
   ``floor_tolerance`` above the floor plane y = 0 (world). Hysteresis grows the seeds (by at
   most ``grow_px``) through pixels in front of their *own* background by ``weak_fraction`` of
   the margin, at any height: the soles on the floor, a palm on the armrest, the body just past
   the edge of a backrest in front of it. Connected components smaller than ``min_component``
   of the image are dropped unless they are at least ``min_part`` and within ``part_distance``
   (3-D) of a kept one (a hand seen between the chair's legs). Invalid pixels (no return) next
   to the mask where the room is in range join it — the rim of a body seen at too grazing an
   angle for the sensor, a dropout — and so do invalid holes and notches that a 3x3 closing
   fills. Flying pixels (mixed depths at depth edges: a 3x3 depth range large relative to
   depth, and fewer than ``edge_support`` neighbours within ``edge_support_ratio`` of the
   pixel's own depth, :func:`flying_pixels`; a thin limb's pixels all touch an edge but have
   their limb around them) and thin boundary noise (a morphological opening) are kept in the
   *mask* (at a
   silhouette such a pixel is as likely person as not, and opening erodes thin limbs) but
   excluded from ``reliable``, the seeds a point cloud may use. Everything after the seeds runs
   on the bounding box of the grown seeds.
3. Person vs chair (:func:`chair_pixels`, :func:`static_foreground`): foreground pixels within
   ``chair_distance`` of the registered chair mesh (open3d ``RaycastingScene.compute_distance``,
   only for points inside the chair's bounding box) are chair — except where the background
   itself shows the chair (:func:`room_on_chair`: the empty room was captured with the chair in
   place), where foreground stands in front of it and is the person; so are, optionally, pixels
   that are foreground in (nearly) every frame of a long recording. The rest is the person.
4. :func:`mask_to_color` — a depth-pixel mask registered into the colour camera's pixels, to be
   compared with colour-pixel masks (the simulator's, BEHAVE's).

Measured on simulated sessions (tests/test_capture_segmentation.py, settings there): person-mask
IoU in colour pixels >= 0.96 in every frame with an empty-room background, >= 0.95 without.

Frames and units: images are (H,W) in the depth camera's pixels unless named ``color``; depth is
uint16 millimetres of Z (0 = invalid); ``world_from_depth`` is the (4,4) pose of the depth camera
in the world (metres, Y up, floor y = 0; the camera is +X right, +Y down, +Z forward).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
from collections.abc import Callable, Collection, Iterable, Iterator
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from couch.geometry import apply_transform, invert_transform

from .azure_calibration import DEPTH_RANGE_M, KinectCalibration
from .azure_mkv import open_azure_mkv
from .registration import pixel_rays, project_points, register_depth_to_color
from .session import SessionLayoutError, session_files

__all__ = [
    "BackgroundModel",
    "CameraSegmentation",
    "ChairModel",
    "FrameSegmentation",
    "SegmentationConfig",
    "SegmentationError",
    "background_from_recordings",
    "camera_foreground",
    "camera_points",
    "chair_pixels",
    "depth_edges",
    "empty_room_recording",
    "flying_pixels",
    "foreground",
    "mask_to_color",
    "room_on_chair",
    "segment_frame",
    "segment_recording",
    "static_foreground",
]

log = logging.getLogger(__name__)


class SegmentationError(ValueError):
    """Input that cannot be segmented (the message names the file or frame and what was
    expected)."""


@dataclasses.dataclass(frozen=True)
class SegmentationConfig:
    """Knobs of the depth segmentation. Lengths in metres.

    The margin follows the Azure Kinect's axial noise, σ(z) ≈ 1.4 mm + 0.18 mm·z² (z in m) head-on
    and more at oblique incidence: ``margin + margin_per_m2·z²`` is ~10σ, so the person's surface
    is rarely lost while the background's noise never passes.
    """

    far_fraction: float = 0.1  # background = the k-th farthest valid depth of a pixel, k =
    far_support: int = 2  # max(far_support, far_fraction · its number of valid frames)
    out_of_range_fraction: float = 0.25  # invalid in this share of frames: no room in range
    margin: float = 0.01  # m, foreground must be this much nearer than the background ...
    margin_per_m2: float = 0.002  # ... plus this times z² (z in metres)
    floor_tolerance: float = 0.02  # m above the floor plane y = 0 that still counts as floor
    edge_ratio: float = 0.03  # 3x3 depth range / depth above which a pixel sits on an edge
    # ... where it is a flying (mixed) depth unless this many of its 8 neighbours lie within
    # edge_support_ratio · depth of it (its own surface)
    edge_support: int = 3
    edge_support_ratio: float = 0.01
    open_px: int = 3  # opening of the reliable (point cloud) pixels (px); 1 = none
    weak_fraction: float = 0.5  # hysteresis: connected to the foreground, this share of the
    #                              margin suffices, at any height (soles, a palm on the chair)
    grow_px: int = 4  # ... within this many pixels of the seeds
    rim_px: int = 1  # invalid pixels this near the foreground where the room is in range join it
    min_component: float = 5e-4  # smallest kept component, fraction of the image's pixels ...
    min_part: float = 6e-5  # ... or this, if within part_distance of one that large
    part_distance: float = 0.3  # m (3-D)
    chair_distance: float = 0.02  # m from the chair mesh within which foreground is chair
    static_fraction: float = 0.95  # foreground in this fraction of frames = static (chair)
    static_min_frames: int = 30  # too few frames cannot tell a still person from the chair
    static_max_frames: int = 300  # the share is counted on at most this many usable captures,
    #                               evenly spaced (a 95 % share to ±1.3 %; 0: on all of them)
    max_background_frames: int = 30  # a recording's own background: at most this many of its
    #                                  frames, evenly spaced
    # 2: full-resolution recordings are read binned 2x2, as the camera's binned modes
    # (couch.capture.binning): a quarter of the pixels for every per-pixel step. 1: as recorded
    depth_binning: int = 1

    def __post_init__(self) -> None:
        if self.depth_binning not in (1, 2):
            raise ValueError(f"SegmentationConfig.depth_binning must be 1 or 2, got "
                             f"{self.depth_binning!r}")


@dataclasses.dataclass
class BackgroundModel:
    """Per-pixel background depth of one camera.

    Attributes:
        depth: (H,W) float32 metres of Z, the background's (k-th farthest) depth; ``inf`` where
            the room is out of range or never seen (anything measured there is foreground).
        near: (H,W) float32 metres, the 3x3 minimum of ``depth``: the nearest background a
            laterally jittered depth edge can show in a pixel.
        frames: number of frames it was built from.
    """

    depth: np.ndarray
    near: np.ndarray
    frames: int

    @functools.cached_property
    def in_range(self) -> np.ndarray:
        """(H,W) bool: pixels where the room is in the sensor's range (finite ``depth``)."""
        return np.isfinite(self.depth)

    @classmethod
    def from_frames(cls, frames: Iterable[np.ndarray | None],
                    config: SegmentationConfig | None = None) -> BackgroundModel:
        """Build the model from depth frames of one camera (uint16 mm, (H,W) each).

        ``None`` and all-zero frames (a dropped or blank depth image) are skipped. Raises
        :class:`SegmentationError` if fewer than one frame with valid depth remains or the
        frames disagree in shape.
        """
        cfg = config or SegmentationConfig()
        stack = []
        for k, f in enumerate(frames):
            if f is None or not np.any(f):
                continue
            if stack and f.shape != stack[0].shape:
                raise SegmentationError(f"background frame {k} has shape {f.shape}, the first "
                                        f"had {stack[0].shape}")
            stack.append(np.asarray(f, dtype=np.uint16))
        if not stack:
            raise SegmentationError("no depth frame with valid pixels to build a background from")
        a = np.stack(stack, axis=-1)  # (H,W,T) mm, time contiguous; 0 (invalid) sorts first
        t = a.shape[-1]
        n_valid = np.count_nonzero(a, axis=-1)
        # k-th farthest valid depth: something in front of the room in all but k-1 frames is
        # still seen past, yet one noisy frame alone does not make the background
        k = np.maximum(cfg.far_support, np.round(cfg.far_fraction * n_valid)).astype(np.intp)
        k = np.minimum(k, t)
        # ascending, the k-th farthest sits at t - k: partition at just the positions used
        a = np.partition(a, np.arange(t - k.max(), t - k.min() + 1), axis=-1)
        far = np.take_along_axis(a, (t - k)[..., None], axis=-1)[..., 0]
        # "no return" is the farthest reading of all (beyond range, mostly): a pixel that gave
        # none in a good share of the frames has no room in range, whatever the other frames saw
        # (the board, a passer-by); sporadic dropouts at a grazing rim do not count
        n_invalid = t - n_valid
        out_of_range = n_invalid >= np.maximum(k, cfg.out_of_range_fraction * t)
        depth = np.where(out_of_range | (n_valid < k), np.float32(np.inf),
                         far.astype(np.float32) * np.float32(1e-3)).astype(np.float32)
        # erode = 3x3 minimum; inf (no background) never wins over a measured neighbour
        near = cv2.erode(depth, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
        return cls(depth=depth, near=near, frames=len(stack))


    @classmethod
    def combine(cls, models: Iterable[BackgroundModel]) -> BackgroundModel:
        """The farthest background any of ``models`` (of one camera, built from different
        recordings) saw at each pixel.

        Each recording may have something static in front of the room at some pixels (the
        ChArUco board held in one place, a person sitting through a short clip); another
        recording that saw past it reveals the room.
        """
        models = list(models)
        if not models:
            raise SegmentationError("no background models to combine")
        shape = models[0].depth.shape
        if any(m.depth.shape != shape for m in models):
            raise SegmentationError(f"background models of different shapes: "
                                    f"{[m.depth.shape for m in models]}")
        # inf (nothing in range) is the farthest of all: a recording that saw no surface in
        # range at a pixel saw past whatever another one had there
        depth = np.stack([m.depth for m in models]).max(axis=0).astype(np.float32)
        near = cv2.erode(depth, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
        return cls(depth=depth, near=near, frames=sum(m.frames for m in models))


def _depth_frames(path: Path, depth_binning: int = 1) -> Iterator[np.ndarray | None]:
    rec = open_azure_mkv(path, depth_binning=depth_binning, streams=("DEPTH",))
    if "DEPTH" not in rec.tracks:
        raise SegmentationError(f"{path}: the recording has no DEPTH stream")
    for cap in rec:
        yield cap.depth_mm


def background_from_recordings(paths: Iterable[str | os.PathLike],
                               config: SegmentationConfig | None = None) -> BackgroundModel:
    """A :class:`BackgroundModel` from every depth frame of one camera's MKV recordings.

    Pass an empty-room recording when there is one. Without one, pass recordings in which the
    room is empty in at least ``far_support`` frames (and ``far_fraction``) at every pixel:
    e.g. the ChArUco calibration captures (nobody in view, the board moves) together with the
    session itself (the person moves). A person who never leaves a pixel is in the background:
    that pixel will miss in the masks.
    """
    paths = list(paths)
    models = []
    for p in paths:
        try:
            models.append(BackgroundModel.from_frames(
                _depth_frames(Path(p), (config or SegmentationConfig()).depth_binning), config))
        except SegmentationError as e:
            raise SegmentationError(f"{p}: {e}") from None
    return BackgroundModel.combine(models)


def empty_room_recording(session_dir: str | os.PathLike, serial: str) -> Path | None:
    """The empty-room recording of camera ``serial`` in a session folder, or None if it has none.

    ``session.json``'s ``kinect[].background`` when the manifest names one (null: none), else
    ``background/<serial>.mkv`` if that file exists.

    Raises:
        SegmentationError: the manifest names a file that does not exist.
    """
    root = Path(session_dir)
    try:
        cam = session_files(root).camera(serial)
    except SessionLayoutError as exc:
        raise SegmentationError(str(exc)) from None
    if cam is not None:
        if cam.background is not None and not cam.background.is_file():
            raise SegmentationError(f"{root / 'session.json'}: camera {serial}'s background "
                                    f"recording {cam.background} does not exist")
        return cam.background
    path = root / "background" / f"{serial}.mkv"
    return path if path.is_file() else None


def camera_points(depth_mm: np.ndarray, calib: KinectCalibration) -> np.ndarray:
    """(H,W,3) float32 camera-frame points (metres) of every depth pixel; NaN where invalid."""
    rays = pixel_rays(calib.depth)
    z = depth_mm.astype(np.float32) / 1000.0
    z[depth_mm == 0] = np.nan
    pts = np.empty((*depth_mm.shape, 3), np.float32)
    pts[..., :2] = rays * z[..., None]
    pts[..., 2] = z
    return pts


def depth_edges(depth_mm: np.ndarray, ratio: float) -> np.ndarray:
    """(H,W) bool: pixels whose 3x3 neighbourhood spans a depth range above ``ratio``·depth,
    i.e. both sides of every depth discontinuity, where ToF sensors return flying (mixed) depths;
    also every pixel next to an invalid one (its neighbourhood is incomplete)."""
    z = depth_mm.astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    hi = cv2.dilate(z, kernel, borderType=cv2.BORDER_REPLICATE)
    lo_in = np.where(z > 0, z, np.float32(np.inf))
    lo = cv2.erode(lo_in, kernel, borderType=cv2.BORDER_REPLICATE)
    near_invalid = cv2.erode((z > 0).astype(np.uint8), kernel) == 0
    return ((hi - lo) > ratio * z) | near_invalid


def flying_pixels(depth_mm: np.ndarray, ratio: float, support_ratio: float,
                  min_support: int) -> np.ndarray:
    """(H,W) bool: the :func:`depth_edges` pixels that no surface of their own backs, i.e. with
    fewer than ``min_support`` of their 8 neighbours within ``support_ratio``·depth of their
    depth. A flying (mixed) depth lies between the two surfaces it mixes and so near neither;
    a pixel of a limb seen a few pixels wide in front of a far background (a hand at 2.5 m
    is 4-6 binned pixels) touches the edge everywhere but has its own limb around it."""
    z = depth_mm.astype(np.float32)
    p = np.pad(z, 1)
    h, w = z.shape
    tol = np.float32(support_ratio) * z
    support = np.zeros((h, w), np.int32)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            if dy == 1 and dx == 1:
                continue
            nb = p[dy:dy + h, dx:dx + w]
            support += (nb > 0) & (np.abs(nb - z) <= tol)
    return depth_edges(depth_mm, ratio) & (support < min_support)


@dataclasses.dataclass(frozen=True)
class _View:
    """One camera's per-pixel constants, computed once per recording.

    Attributes:
        calib: the device.
        world_from_depth: (4,4) float64 world pose of the depth camera (metres).
        rays: (H,W,2) float32 normalised ray (x, y) of every pixel (NaN: invalid).
        rise: (H,W) float32 world height gained per metre of Z along each ray (NaN: invalid),
            so that a pixel's height above the floor is ``z·rise + height``.
        height: the camera's height (m).
    """

    calib: KinectCalibration
    world_from_depth: np.ndarray
    rays: np.ndarray
    rise: np.ndarray
    height: np.float32

    @classmethod
    def of(cls, calib: KinectCalibration, world_from_depth: np.ndarray) -> _View:
        pose = np.asarray(world_from_depth, dtype=np.float64)
        rays = pixel_rays(calib.depth)
        row = pose[1]
        rise = (row[0] * rays[..., 0] + row[1] * rays[..., 1] + row[2]).astype(np.float32)
        return cls(calib, pose, rays.astype(np.float32), rise, np.float32(row[3]))

    def points(self, depth_mm: np.ndarray, sel: np.ndarray) -> np.ndarray:
        """(N,3) float32 camera-frame points (m) of the ``sel`` (H,W) pixels."""
        z = depth_mm[sel].astype(np.float32) * np.float32(1e-3)
        return np.column_stack([self.rays[sel] * z[:, None], z])

    def points_at(self, depth_mm: np.ndarray, flat: np.ndarray) -> np.ndarray:
        """(N,3) float32 camera-frame points (m) of the pixels at (N,) flat (row-major)
        indices of the (H,W) image."""
        rows, cols = np.divmod(flat, depth_mm.shape[1])
        z = depth_mm[rows, cols].astype(np.float32) * np.float32(1e-3)
        return np.column_stack([self.rays[rows, cols] * z[:, None], z])

    def crop(self, box: tuple[slice, slice]) -> _View:
        """The view of the pixels ``box`` (row and column slices) only."""
        return dataclasses.replace(self, rays=self.rays[box], rise=self.rise[box])

    def world(self, points: np.ndarray) -> np.ndarray:
        """(N,3) float32 world points of (N,3) camera-frame points."""
        pose = self.world_from_depth.astype(np.float32)
        return points @ pose[:3, :3].T + pose[:3, 3]


def _keep_components(mask: np.ndarray, depth_mm: np.ndarray, view: _View,
                     config: SegmentationConfig, image_size: int | None = None) -> np.ndarray:
    """(H,W) bool: the 8-connected components of ``mask`` of at least ``min_component`` of the
    image (``image_size`` pixels; default: ``mask.size``), and the smaller ones of at least
    ``min_part`` of it that come within ``part_distance`` (3-D) of those: a hand seen between
    the chair's legs stays, a speck of noise across the room goes."""
    size = image_size or mask.size
    n, labels = cv2.connectedComponents(mask.view(np.uint8), connectivity=8)
    if n == 1:
        return np.zeros(mask.shape, dtype=bool)
    area = np.bincount(labels[mask], minlength=n)
    area[0] = 0  # label 0 is the background of the mask
    big = area >= max(1, round(config.min_component * size))
    small = ~big & (area >= max(1, round(config.min_part * size)))
    if big.any() and small.any():
        valid = (depth_mm > 0).ravel()
        flat = labels.ravel()
        at_big = np.flatnonzero(big[flat] & valid)
        at_big = at_big[::max(1, len(at_big) // 4000)]  # a sample of ~4000 points suffices
        at_small = np.flatnonzero(small[flat] & valid)
        tree = cKDTree(view.points_at(depth_mm, at_big))
        d, _ = tree.query(view.points_at(depth_mm, at_small),
                          distance_upper_bound=config.part_distance)
        big[flat[at_small][np.isfinite(d)]] = True
    return big[labels]


def _box(mask: np.ndarray, pad: int) -> tuple[slice, slice] | None:
    """The bounding box of ``mask``'s (H,W) pixels grown by ``pad``, as slices; None if empty."""
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))
    if w == 0:
        return None
    return (slice(max(0, y - pad), y + h + pad), slice(max(0, x - pad), x + w + pad))


def foreground(depth_mm: np.ndarray, background: BackgroundModel, calib: KinectCalibration,
               world_from_depth: np.ndarray, config: SegmentationConfig | None = None,
               ) -> tuple[np.ndarray, np.ndarray]:
    """Foreground of one depth frame (see the module doc, step 2).

    Args:
        depth_mm: (H,W) uint16 mm Z-depth of the depth camera.
        background: that camera's model.
        calib: the device's calibration.
        world_from_depth: (4,4) world pose of the depth camera (metres, Y up, floor y = 0).
        config: thresholds.

    Returns:
        mask: (H,W) bool foreground silhouette: pixels nearer than the background by the
            margin and above the floor (seeds), grown by hysteresis (up to ``grow_px``)
            through pixels nearer by ``weak_fraction`` of the margin at any height (soles, a
            palm on the chair), in components of at least ``min_component`` of the image (or
            ``min_part`` near one); then the invalid pixels within ``rim_px`` of it where the
            room is in range (a grazing rim, a dropout) and the invalid holes it encloses.
        reliable: (H,W) bool, the seeds in the mask without the pixels on depth edges (flying
            pixels) and opened (thin boundary noise): the pixels whose depth a point cloud may
            trust; none is within ``floor_tolerance`` of the floor.
    """
    return camera_foreground(background, calib, world_from_depth, config)(depth_mm)


def camera_foreground(background: BackgroundModel, calib: KinectCalibration,
                      world_from_depth: np.ndarray, config: SegmentationConfig | None = None,
                      *, reliable: bool = True
                      ) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """:func:`foreground` for many frames of one camera: its per-pixel constants computed
    once (a tenth of a frame's cost each time otherwise).

    Args:
        background, calib, world_from_depth, config: as :func:`foreground`.
        reliable: also compute the ``reliable`` pixels; False: that array comes back all False
            (the silhouette alone costs ~30 % less: no flying-pixel test, no opening).

    Returns:
        ``fg(depth_mm)`` → ``(mask, reliable)`` of one (H,W) uint16 frame, as :func:`foreground`.
    """
    view = _View.of(calib, world_from_depth)
    cfg = config or SegmentationConfig()

    def fg(depth_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if depth_mm.shape != background.depth.shape:
            raise SegmentationError(f"depth image {depth_mm.shape} does not match the "
                                    f"background {background.depth.shape}")
        return _foreground(depth_mm, background, view, cfg, reliable)

    return fg


def _foreground(depth_mm: np.ndarray, background: BackgroundModel, view: _View,
                cfg: SegmentationConfig, reliable: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`foreground` with the camera's constants precomputed; ``reliable`` False leaves
    the second array all False (see :func:`camera_foreground`)."""
    z = depth_mm.astype(np.float32) * np.float32(1e-3)
    valid = depth_mm > 0
    margin = np.float32(cfg.margin) + np.float32(cfg.margin_per_m2) * z * z
    # how far in front of the room (inf: no room in range); seeds against the nearest room in
    # the 3x3 neighbourhood (a jittering depth edge of the room is no seed), their neighbours
    # against the pixel's own room (a person seen just past the chair's edge)
    with np.errstate(invalid="ignore"):  # NaN rise of invalid rays compares False
        seeds = valid & (background.near - z > margin) & (
            z * view.rise + view.height > np.float32(cfg.floor_tolerance))
    weak = valid & (background.depth - z > np.float32(cfg.weak_fraction) * margin)
    # hysteresis, within grow_px of the seeds: a biased background (few frames) cannot leak
    region = seeds.view(np.uint8)
    allowed = (weak | seeds).view(np.uint8)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    for _ in range(cfg.grow_px):
        region = cv2.dilate(region, cross) & allowed
    # the rest only where the grown seeds are (with room for the morphology below)
    mask = np.zeros(depth_mm.shape, dtype=bool)
    rel_out = np.zeros(depth_mm.shape, dtype=bool)
    box = _box(region, max(cfg.rim_px, cfg.open_px) + 2)
    if box is None:
        return mask, rel_out
    crop = view.crop(box)
    d = depth_mm[box]
    m = _keep_components(region.view(bool)[box], d, crop, cfg, depth_mm.size)
    if reliable:
        # what a point cloud may use: no depth-edge (flying) pixels, no thin boundary noise.
        # The silhouette keeps both: opening it costs more IoU at thin limbs than the noise does.
        rel = m & seeds[box] & ~flying_pixels(d, cfg.edge_ratio, cfg.edge_support_ratio,
                                               cfg.edge_support)
        if cfg.open_px > 1:
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (cfg.open_px, cfg.open_px))
            rel = cv2.morphologyEx(rel.view(np.uint8), cv2.MORPH_OPEN, kernel).view(bool)
        rel_out[box] = rel
    if cfg.rim_px > 0:
        # No return where the room gave one: something is in front of it. Next to the
        # foreground that is its rim, seen at too grazing an angle for the sensor (or a dropout).
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                           (2 * cfg.rim_px + 1, 2 * cfg.rim_px + 1))
        m8 = m.view(np.uint8)
        near_mask = cv2.dilate(m8, kernel).view(bool)
        # where the room is out of range too, only the holes and notches that closing fills
        closed = cv2.morphologyEx(m8, cv2.MORPH_CLOSE, kernel).view(bool)
        m = m | ((d == 0) & ((near_mask & background.in_range[box]) | closed))
    mask[box] = m
    return mask, rel_out


@dataclasses.dataclass
class ChairModel:
    """The chair as registered in the world: a triangle mesh in its own frame and its pose.

    Attributes:
        vertices: (V,3) metres in the object (scan) frame.
        faces: (F,3) int vertex indices.
        world_from_object: (4,4) pose (the processed schema's ``/object/pose``).
    """

    vertices: np.ndarray
    faces: np.ndarray
    world_from_object: np.ndarray

    def __post_init__(self) -> None:
        world = apply_transform(np.asarray(self.world_from_object, np.float64),
                                np.asarray(self.vertices, np.float64))
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(world.astype(np.float32)),
                                  o3d.core.Tensor(np.asarray(self.faces, np.uint32)))
        self._bounds = (world.min(axis=0).astype(np.float32), world.max(axis=0).astype(np.float32))

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(3,), (3,) float32 world corners of the chair's axis-aligned bounding box (m)."""
        return self._bounds

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) float32 unsigned distance (m) of (N,3) world points to the chair surface."""
        if len(points) == 0:
            return np.zeros(0, np.float32)
        q = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
        return self._scene.compute_distance(q).numpy()

    def __reduce__(self) -> tuple[type, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        # the ray-casting scene does not pickle: a worker process rebuilds it from the mesh
        return (ChairModel, (self.vertices, self.faces, self.world_from_object))


def chair_pixels(mask: np.ndarray, depth_mm: np.ndarray, calib: KinectCalibration,
                 world_from_depth: np.ndarray, chair: ChairModel, distance: float,
                 ) -> np.ndarray:
    """(H,W) bool: the pixels of ``mask`` whose 3-D point lies within ``distance`` (m) of the
    registered chair mesh. Only the masked pixels inside the chair's bounding box (grown by
    ``distance``) are queried (open3d ``compute_distance``)."""
    return _chair_pixels(mask, depth_mm, _View.of(calib, world_from_depth), chair, distance)


@dataclasses.dataclass
class _ChairMemo:
    """One camera's last exact distance to the chair per pixel, over a pass through its frames.

    A pixel's point moves ``|Δz| · |(x, y, 1)|`` when its depth changes by Δz, and its distance
    to the chair by no more, so a pixel whose depth stayed near the one last measured is on
    the same side of the threshold without a new query (the chair's own pixels, static but
    for the sensor's noise, were most of the queries: 1.6 of 4.9 s of a camera's 900 person
    clouds).

    Attributes:
        depth_mm: (H,W) the depth last measured at (0: never).
        distance: (H,W) float32 its distance (m) to the chair.
        stretch: (H,W) float32 metres the point moves per millimetre of depth.
    """

    depth_mm: np.ndarray
    distance: np.ndarray
    stretch: np.ndarray

    @classmethod
    def of(cls, view: _View) -> _ChairMemo:
        shape = view.rays.shape[:2]
        stretch = 1e-3 * np.sqrt(1.0 + np.square(view.rays).sum(-1))
        return cls(np.zeros(shape, np.int32), np.zeros(shape, np.float32),
                   np.nan_to_num(stretch, nan=np.inf).astype(np.float32))


def _chair_pixels(mask: np.ndarray, depth_mm: np.ndarray, view: _View, chair: ChairModel,
                  distance: float, memo: _ChairMemo | None = None) -> np.ndarray:
    out = np.zeros(mask.shape, dtype=bool)
    sel = mask & (depth_mm > 0)
    if not np.any(sel):
        return out
    world = view.world(view.points(depth_mm, sel))
    lo, hi = chair.bounds
    inside = np.flatnonzero(np.all((world > lo - distance) & (world < hi + distance), axis=1))
    memo = memo if memo is not None else _ChairMemo.of(view)  # a lone frame: every pixel asks
    rows, cols = np.nonzero(sel)
    rows, cols = rows[inside], cols[inside]
    z = depth_mm[rows, cols].astype(np.int32)
    was = memo.depth_mm[rows, cols]
    # the bound, plus float32's rounding of the points and the distances
    slack = np.abs(z - was) * memo.stretch[rows, cols] + 1e-4
    last = memo.distance[rows, cols]
    sure = (was > 0) & ((last + slack < distance) | (last - slack >= distance))
    ask = ~sure
    exact = chair.distance(world[inside[ask]])
    near = np.zeros(len(world), dtype=bool)
    near[inside[sure]] = last[sure] < distance
    near[inside[ask]] = exact < distance
    memo.depth_mm[rows[ask], cols[ask]] = z[ask]
    memo.distance[rows[ask], cols[ask]] = exact
    out[sel] = near
    return out


def room_on_chair(background: BackgroundModel, calib: KinectCalibration,
                  world_from_depth: np.ndarray, chair: ChairModel, distance: float,
                  ) -> np.ndarray:
    """(H,W) bool: pixels whose background depth lies within ``distance`` (m) of the chair
    mesh, where the chair is part of the room (the empty room was captured with the chair in
    place). Foreground there stands in front of the chair (a palm on the armrest), so it is
    never chair."""
    finite = background.in_range
    depth_mm = np.rint(np.where(finite, background.depth, 0) * 1000)
    return chair_pixels(finite, np.clip(depth_mm, 0, 65535).astype(np.uint16), calib,
                        world_from_depth, chair, distance)


def static_foreground(masks: np.ndarray, config: SegmentationConfig | None = None,
                      ) -> np.ndarray:
    """(H,W) bool: pixels in the foreground of at least ``static_fraction`` of the (T,H,W)
    ``masks`` — the static chair. All False when T < ``static_min_frames``: in a short clip a
    seated person is as static as the chair."""
    cfg = config or SegmentationConfig()
    masks = np.asarray(masks, dtype=bool)
    if len(masks) < cfg.static_min_frames:
        return np.zeros(masks.shape[1:], dtype=bool)
    return masks.mean(axis=0) >= cfg.static_fraction


def mask_to_color(mask: np.ndarray, depth_mm: np.ndarray, calib: KinectCalibration,
                  blur_px: float = 1.0) -> np.ndarray:
    """Register a depth-pixel mask of a surface into the colour camera's pixels.

    The masked depth alone is registered with the SDK's rule (:func:`register_depth_to_color`),
    which gives the surface's colour-camera depth inside its silhouette but leaves a band of
    about one depth pixel along it empty (quads across discontinuities are dropped). Every colour
    pixel within that reach of the surface takes the nearest surface depth (a 2-D minimum
    filter), is back-projected with it, moved into the depth camera and looked up in the
    slightly blurred, bilinearly interpolated depth mask (>= 0.5: inside). Because the
    surface's own depth is used, the parallax between the two cameras is exact on the surface
    and the silhouette is resolved below a depth pixel. What lies in front of the surface in
    the depth camera's view (the chair before a leg) is outside ``mask`` and stays outside.

    Args:
        mask: (H,W) bool in depth pixels.
        depth_mm: (H,W) uint16 mm depth of the same frame.
        calib: the device (depth and colour intrinsics, ``color_from_depth``).
        blur_px: Gaussian sigma (depth pixels) smoothing the mask's staircase before lookup.

    Returns:
        (Hc,Wc) bool mask in colour pixels.
    """
    cw, ch = calib.color.width, calib.color.height
    out = np.zeros((ch, cw), dtype=bool)
    surface = np.where(mask, depth_mm, 0).astype(np.uint16)
    if not np.any(surface):
        return out
    reg = register_depth_to_color(surface, calib).astype(np.float32)
    reg[reg == 0] = np.inf
    # reach: 1.5 depth pixels in colour pixels, at least 2
    reach = max(2, int(np.ceil(1.5 * calib.color.fx / calib.depth.fx)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
    z = cv2.erode(reg, kernel)  # nearest surface depth around each colour pixel (mm)
    cand = np.isfinite(z)
    rays = pixel_rays(calib.color)[cand]  # (N,2)
    zc = z[cand].astype(np.float64) / 1000.0
    pts_c = np.column_stack([rays * zc[:, None], zc])
    pts_d = apply_transform(invert_transform(calib.color_from_depth), pts_c)
    uv, ok = project_points(pts_d, calib.depth)
    uv = np.where(ok[:, None], uv, -10.0).astype(np.float32)  # invalid → outside (0 border)
    soft = mask.astype(np.float32)
    if blur_px > 0:
        soft = cv2.GaussianBlur(soft, (0, 0), blur_px)
    # bilinear lookup at the (N,) positions: remap wants a 2-D map, so fold N into rows
    n = len(uv)
    width = 1024
    rows = -(-n // width)
    maps = np.full((rows * width, 2), -10.0, np.float32)
    maps[:n] = uv
    maps = maps.reshape(rows, width, 2)
    vals = cv2.remap(soft, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0.0).reshape(-1)[:n]
    out[cand] = vals >= 0.5
    return out


@dataclasses.dataclass
class FrameSegmentation:
    """Segmentation of one depth frame of one camera (depth-camera pixels).

    Attributes:
        index: capture index in the recording.
        timestamp_us: the capture's device timestamp (µs).
        depth_mm: (H,W) uint16 the frame's depth.
        person: (H,W) bool person mask.
        chair: (H,W) bool chair mask (foreground that is chair).
        person_reliable: (H,W) bool ``person`` without depth-edge (flying) pixels.
        chair_reliable: (H,W) bool likewise for ``chair``.
    """

    index: int
    timestamp_us: int
    depth_mm: np.ndarray
    person: np.ndarray
    chair: np.ndarray
    person_reliable: np.ndarray
    chair_reliable: np.ndarray


def segment_frame(depth_mm: np.ndarray, background: BackgroundModel, calib: KinectCalibration,
                  world_from_depth: np.ndarray, chair: ChairModel | None = None,
                  static: np.ndarray | None = None, config: SegmentationConfig | None = None,
                  *, room_chair: np.ndarray | None = None, index: int = 0,
                  timestamp_us: int = 0) -> FrameSegmentation:
    """Foreground, then chair (near the chair mesh but not in front of a room that already
    shows the chair there (``room_chair`` (H,W), see :func:`room_on_chair`), or in the
    ``static`` (H,W) mask), then the person = the rest. See :func:`foreground` for the
    arguments."""
    cfg = config or SegmentationConfig()
    if depth_mm.shape != background.depth.shape:
        raise SegmentationError(f"depth image {depth_mm.shape} does not match the background "
                                f"{background.depth.shape}")
    view = _View.of(calib, world_from_depth)
    fg = _foreground(depth_mm, background, view, cfg)
    return _split(depth_mm, fg, view, chair, static, room_chair, cfg, index, timestamp_us)


def _split(depth_mm: np.ndarray, fg: tuple[np.ndarray, np.ndarray], view: _View,
           chair: ChairModel | None, static: np.ndarray | None, room_chair: np.ndarray | None,
           cfg: SegmentationConfig, index: int, timestamp_us: int,
           memo: _ChairMemo | None = None) -> FrameSegmentation:
    """:func:`segment_frame` from the frame's ``(mask, reliable)`` foreground (``memo``: the
    camera's chair distances so far, in a pass over its frames)."""
    mask, reliable = fg
    is_chair = np.zeros_like(mask)
    if chair is not None:
        cand = mask if room_chair is None else mask & ~room_chair
        is_chair |= _chair_pixels(cand, depth_mm, view, chair, cfg.chair_distance, memo)
    if static is not None:
        is_chair |= static & mask
    person = mask
    box = _box(mask, 1)
    if box is not None and is_chair[box].any():
        # the chair may have cut the person into pieces: drop the crumbs it left
        person = np.zeros_like(mask)
        person[box] = _keep_components(mask[box] & ~is_chair[box], depth_mm[box],
                                       view.crop(box), cfg, mask.size)
    return FrameSegmentation(index=index, timestamp_us=timestamp_us, depth_mm=depth_mm,
                             person=person, chair=is_chair, person_reliable=person & reliable,
                             chair_reliable=is_chair & reliable)


@dataclasses.dataclass
class CameraSegmentation:
    """All frames of one camera's recording.

    Attributes:
        serial: device serial (from the recording, else the file stem).
        calibration: the device's calibration.
        world_from_depth: (4,4) the depth camera's world pose used.
        background: the background model used.
        frames: one :class:`FrameSegmentation` per usable capture, in recording order.
        skipped: ``(capture index, reason)`` of captures without usable depth (dropped depth
            image, all zeros), counted rather than silently lost.
        depth_range: (min, max) metres of Z the camera measures in its recorded mode
            (``DEPTH_RANGE_M``; a full-resolution recording read binned keeps its own), or
            None for a mode without one.
    """

    serial: str
    calibration: KinectCalibration
    world_from_depth: np.ndarray
    background: BackgroundModel
    frames: list[FrameSegmentation]
    skipped: list[tuple[int, str]]
    depth_range: tuple[float, float] | None = None


def segment_recording(path: str | os.PathLike, world_from_depth: np.ndarray,
                      background: BackgroundModel | None = None, *,
                      empty_room: str | os.PathLike | None = None,
                      background_paths: Iterable[str | os.PathLike] = (),
                      include_session: bool = True, chair: ChairModel | None = None,
                      config: SegmentationConfig | None = None,
                      timestamps: Collection[int] | Callable[[np.ndarray], Collection[int]]
                      | None = None) -> CameraSegmentation:
    """Segment the depth frames of one camera's Azure Kinect MKV recording.

    Args:
        path: the recording.
        world_from_depth: (4,4) world pose of this camera's depth camera (from calibration).
        background: a ready model; else one is built from ``empty_room`` alone when given,
            otherwise from ``background_paths`` and (with ``include_session``, or when there
            are no ``background_paths``) the recording itself, combined with
            :meth:`BackgroundModel.combine`.
        empty_room: a recording of this camera of the room with nobody in view (the chair in
            place), e.g. :func:`empty_room_recording`; None: fall back to the above.
        background_paths: recordings of the same camera with nobody in view (empty room,
            calibration captures).
        include_session: also use the recording's own frames (at most
            ``max_background_frames``, evenly spaced) for the background (helps where the
            calibration captures had something in front, e.g. the ChArUco board).
        chair: the registered chair, if known.
        config: thresholds.
        timestamps: device timestamps (µs) of the captures to segment, or a function of the
            (N,) int64 timestamps of the usable captures (in recording order) that returns
            them; None: every capture. The background (``include_session``) and the static
            chair (no ``chair``; counted on at most ``static_max_frames`` captures) still come
            from the usable captures, whichever are asked for, and ``skipped`` lists the whole
            recording's unusable captures; ``frames`` holds only those asked
            for, and only their depth is held in memory (the recording is read two or three
            times instead).

    Raises:
        SegmentationError: the file has no DEPTH stream, no frame with valid depth, or depth
            images of another size than the background's.
        KinectFormatError: the file is not a readable Azure Kinect recording.
    """
    cfg = config or SegmentationConfig()
    path = Path(path)
    rec = open_azure_mkv(path, depth_binning=cfg.depth_binning, streams=("DEPTH",))
    if "DEPTH" not in rec.tracks:
        raise SegmentationError(f"{path}: the recording has no DEPTH stream (depth mode "
                                f"{rec.depth_mode}); segmentation needs depth")
    calib = rec.calibration
    world_from_depth = np.asarray(world_from_depth, dtype=np.float64)
    if world_from_depth.shape != (4, 4):
        raise SegmentationError(f"{path}: world_from_depth must be (4, 4), got "
                                f"{world_from_depth.shape}")
    # the recording is read in passes and only the frames needed are held: a long session's
    # decoded depth does not fit in memory (reading a capture again costs ~0.2 ms)
    usable: list[tuple[int, int]] = []  # (capture index, device timestamp) with valid depth
    invalid: list[tuple[int, str]] = []
    shape = None
    captures = 0
    for c in rec:
        captures += 1
        depth = c.depth_mm
        if depth is None:
            invalid.append((c.index, "no depth image in this capture"))
        elif not np.any(depth):
            invalid.append((c.index, "depth image is all zeros (invalid)"))
        else:
            usable.append((c.index, c.timestamp_us))
            shape = shape or depth.shape
    skipped: list[tuple[int, str]] = [(s.capture_index if s.capture_index is not None else -1,
                                       f"{s.track}: {s.reason}") for s in rec.skipped] + invalid
    if not usable:
        raise SegmentationError(f"{path}: none of its {captures} captures has valid depth "
                                f"(all missing or all zeros)")
    stamps = np.array([t for _, t in usable], np.int64)
    if callable(timestamps):
        timestamps = timestamps(stamps)
    asked = None if timestamps is None else {int(t) for t in timestamps}
    wanted = {i for i, t in usable if asked is None or t in asked}
    if background is None and empty_room is not None:
        background = background_from_recordings([empty_room], cfg)

    def check(bg: BackgroundModel) -> BackgroundModel:
        if bg.depth.shape != shape:
            raise SegmentationError(f"{path}: depth images {shape} do not match the "
                                    f"background {bg.depth.shape}")
        return bg

    if background is not None:
        check(background)
    sampled: set[int] = set()
    models = []
    if background is None:
        # each recording's own k-th farthest depth, then the farthest of them (combine)
        models = [background_from_recordings(background_paths, cfg)] if background_paths else []
        if include_session or not models:
            step = max(1, -(-len(usable) // cfg.max_background_frames))  # ceil
            sampled = {i for i, _ in usable[::step]}
    static_needed = chair is None and len(usable) >= cfg.static_min_frames
    counted: set[int] = set()  # the captures whose foreground the static chair is counted on
    if static_needed:
        step = (max(1, -(-len(usable) // cfg.static_max_frames)) if cfg.static_max_frames > 0
                else 1)
        counted = {i for i, _ in usable[::step]}
    view = _View.of(calib, world_from_depth)
    depths: dict[int, np.ndarray] = {}  # capture index -> depth, of the frames segmented
    fg_of: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    count = np.zeros(shape, np.int64) if static_needed else None

    def pass_over(collect: bool, foregrounds: bool) -> None:
        """One read of the recording: the depths of the frames asked for (and the background
        samples) with ``collect``; the ``counted`` frames' foregrounds counted with
        ``foregrounds`` (the wanted ones' kept)."""
        bg_frames = []
        for c in rec:
            counts = foregrounds and c.index in counted
            if c.index in wanted or c.index in sampled or counts:
                depth = c.depth_mm
                if depth is None or not np.any(depth):
                    continue
                if collect and c.index in sampled:
                    bg_frames.append(depth)
                if collect and c.index in wanted:
                    depths[c.index] = depth
                if counts:
                    # the static count reads the silhouette alone
                    fg = _foreground(depth, background, view, cfg, c.index in wanted)
                    np.add(count, fg[0], out=count)
                    if c.index in wanted:
                        fg_of[c.index] = fg
        if bg_frames:
            models.append(BackgroundModel.from_frames(bg_frames, cfg))

    # the static chair is what stays in the foreground over the whole recording: every
    # frame's foreground, against a background known before the pass or made by it
    pass_over(collect=True, foregrounds=static_needed and background is not None)
    if background is None:
        background = check(BackgroundModel.combine(models))
        if static_needed:
            pass_over(collect=False, foregrounds=True)
    # as static_foreground: the share of the counted frames in the foreground
    static = count / len(counted) >= cfg.static_fraction if count is not None else None
    room_chair = None if chair is None else room_on_chair(background, calib, world_from_depth,
                                                          chair, cfg.chair_distance)
    frames = []
    memo = _ChairMemo.of(view) if chair is not None else None
    for i, t in usable:
        if i in wanted:
            d = depths[i]
            fg = fg_of[i] if i in fg_of else _foreground(d, background, view, cfg)
            frames.append(_split(d, fg, view, chair, static, room_chair, cfg, i, t, memo))
    if skipped:
        log.warning("%s: skipped %d capture(s) without usable depth", path, len(skipped))
    return CameraSegmentation(serial=rec.serial or path.stem, calibration=calib,
                              world_from_depth=world_from_depth, background=background,
                              frames=frames, skipped=skipped,
                              depth_range=DEPTH_RANGE_M.get(rec.depth_mode))
