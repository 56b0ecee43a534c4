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
   :func:`background_from_recordings`. The simulator has no empty-room recording, but its ChArUco
   calibration captures show the room with nobody in it (only the board, which moves between
   captures); the tests build the background from those captures *and* the session's frames.
2. :func:`foreground` — pixels in front of the background by more than a distance-dependent
   margin (``margin + margin_per_m2·z²``, following the ToF noise that grows with z²), compared
   with the 3x3 *nearest* background depth so that the lateral jitter of background depth edges
   (a chair leg against a wall) does not leak slivers; points within ``floor_tolerance`` of the
   floor plane y = 0 (world) removed; connected components (``cv2.connectedComponentsWithStats``)
   smaller than ``min_component`` of the image dropped. Flying pixels (mixed depths at depth
   edges, found by the 3x3 depth range relative to depth) and thin boundary noise (a
   morphological opening) are kept in the *mask* (at a silhouette such a pixel is as likely
   person as not, and opening erodes thin limbs) but excluded from ``reliable``, the pixels a
   point cloud may use.
3. Person vs chair (:func:`chair_pixels`, :func:`static_foreground`): foreground pixels within
   ``chair_distance`` of the registered chair mesh (open3d ``RaycastingScene.compute_distance``)
   are chair; so are, optionally, pixels that are foreground in (nearly) every frame of a long
   recording. The rest is the person.
4. :func:`mask_to_color` — a depth-pixel mask registered into the colour camera's pixels, to be
   compared with colour-pixel masks (the simulator's, BEHAVE's).

Frames and units: images are (H,W) in the depth camera's pixels unless named ``color``; depth is
uint16 millimetres of Z (0 = invalid); ``world_from_depth`` is the (4,4) pose of the depth camera
in the world (metres, Y up, floor y = 0; the camera is +X right, +Y down, +Z forward).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from couch.geometry import apply_transform, invert_transform

from .azure_calibration import KinectCalibration
from .azure_mkv import open_azure_mkv
from .registration import pixel_rays, project_points, register_depth_to_color

__all__ = [
    "BackgroundModel",
    "CameraSegmentation",
    "ChairModel",
    "FrameSegmentation",
    "SegmentationConfig",
    "SegmentationError",
    "background_from_recordings",
    "camera_points",
    "chair_pixels",
    "depth_edges",
    "foreground",
    "mask_to_color",
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
    open_px: int = 3  # opening of the reliable (point cloud) pixels (px); 1 = none
    grow_px: int = 1  # the mask grows this far into soles near the floor (px)
    min_component: float = 5e-4  # smallest kept component, fraction of the image's pixels
    chair_distance: float = 0.02  # m from the chair mesh within which foreground is chair
    static_fraction: float = 0.95  # foreground in this fraction of frames = static (chair)
    static_min_frames: int = 30  # too few frames cannot tell a still person from the chair


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
        d = np.stack(stack).astype(np.float32) / 1000.0  # (T,H,W) metres
        valid = d > 0
        n_valid = valid.sum(axis=0)
        # k-th farthest valid depth: something in front of the room in all but k-1 frames is
        # still seen past, yet one noisy frame alone does not make the background
        k = np.maximum(cfg.far_support, np.round(cfg.far_fraction * n_valid)).astype(np.intp)
        d[~valid] = -np.inf
        d = -np.sort(-d, axis=0)  # descending along time
        far = np.take_along_axis(d, np.minimum(k, len(d))[None] - 1, axis=0)[0]
        # "no return" is the farthest reading of all (beyond range, mostly): a pixel that gave
        # none in a good share of the frames has no room in range, whatever the other frames saw
        # (the board, a passer-by); sporadic dropouts at a grazing rim do not count
        n_invalid = len(d) - n_valid
        out_of_range = n_invalid >= np.maximum(k, cfg.out_of_range_fraction * len(d))
        depth = np.where(out_of_range | (n_valid < k), np.inf, far).astype(np.float32)
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


def _depth_frames(path: Path) -> Iterator[np.ndarray | None]:
    rec = open_azure_mkv(path)
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
            models.append(BackgroundModel.from_frames(_depth_frames(Path(p)), config))
        except SegmentationError as e:
            raise SegmentationError(f"{p}: {e}") from None
    return BackgroundModel.combine(models)


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


def _keep_large_components(mask: np.ndarray, min_pixels: int) -> np.ndarray:
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_pixels
    keep[0] = False  # label 0 is the background of the mask
    return keep[labels]


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
        mask: (H,W) bool foreground silhouette (floor removed, small components dropped,
            then grown by ``grow_px`` into adjacent soles).
        reliable: (H,W) bool, the foreground before growing, without the pixels on depth
            edges (flying pixels) and opened (thin boundary noise): the pixels whose depth a
            point cloud may trust; none is within ``floor_tolerance`` of the floor.
    """
    cfg = config or SegmentationConfig()
    if depth_mm.shape != background.depth.shape:
        raise SegmentationError(f"depth image {depth_mm.shape} does not match the background "
                                f"{background.depth.shape}")
    pts = camera_points(depth_mm, calib)
    z = pts[..., 2]
    with np.errstate(invalid="ignore"):
        margin = cfg.margin + cfg.margin_per_m2 * z * z
        nearer = z < background.near - margin  # NaN (invalid) compares False
        # height above the floor: the world Y row of the pose applied to every point
        r, t = world_from_depth[1, :3].astype(np.float32), np.float32(world_from_depth[1, 3])
        above = (pts @ r + t) > cfg.floor_tolerance
    mask = _keep_large_components(nearer & above,
                                  max(1, round(cfg.min_component * nearer.size)))
    # what a point cloud may use: no depth-edge (flying) pixels, no thin boundary noise. The
    # silhouette keeps both: opening it costs more IoU at thin limbs than the noise does.
    reliable = mask & ~depth_edges(depth_mm, cfg.edge_ratio)
    if cfg.open_px > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (cfg.open_px, cfg.open_px))
        reliable = cv2.morphologyEx(reliable.astype(np.uint8), cv2.MORPH_OPEN,
                                    kernel).astype(bool)
    if cfg.grow_px > 0:
        # The silhouette, not the point cloud, also owns the soles: pixels nearer than the floor
        # behind them but within floor_tolerance of it, where they touch a kept part.
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                           (2 * cfg.grow_px + 1, 2 * cfg.grow_px + 1))
        near_mask = cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)
        mask |= near_mask & nearer & ~above
    return mask, reliable


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

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) float32 unsigned distance (m) of (N,3) world points to the chair surface."""
        if len(points) == 0:
            return np.zeros(0, np.float32)
        q = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
        return self._scene.compute_distance(q).numpy()


def chair_pixels(mask: np.ndarray, depth_mm: np.ndarray, calib: KinectCalibration,
                 world_from_depth: np.ndarray, chair: ChairModel, distance: float,
                 ) -> np.ndarray:
    """(H,W) bool: the pixels of ``mask`` whose 3-D point lies within ``distance`` (m) of the
    registered chair mesh. Only the masked pixels are queried (open3d ``compute_distance``)."""
    out = np.zeros_like(mask, dtype=bool)
    sel = mask & (depth_mm > 0)
    if not np.any(sel):
        return out
    pts = camera_points(depth_mm, calib)[sel].astype(np.float64)
    world = apply_transform(np.asarray(world_from_depth, np.float64), pts)
    out[sel] = chair.distance(world) < distance
    return out


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
                  blur_px: float = 0.5) -> np.ndarray:
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
                  *, index: int = 0, timestamp_us: int = 0) -> FrameSegmentation:
    """Foreground, then chair (near the chair mesh, or in the ``static`` (H,W) mask), then the
    person = the rest. See :func:`foreground` for the arguments."""
    cfg = config or SegmentationConfig()
    fg, reliable = foreground(depth_mm, background, calib, world_from_depth, cfg)
    is_chair = np.zeros_like(fg)
    if chair is not None:
        is_chair |= chair_pixels(fg, depth_mm, calib, world_from_depth, chair,
                                 cfg.chair_distance)
    if static is not None:
        is_chair |= static & fg
    person = fg & ~is_chair
    # the chair may have cut the person into pieces: drop the crumbs it left
    person = _keep_large_components(person, max(1, round(cfg.min_component * person.size)))
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
    """

    serial: str
    calibration: KinectCalibration
    world_from_depth: np.ndarray
    background: BackgroundModel
    frames: list[FrameSegmentation]
    skipped: list[tuple[int, str]]


def segment_recording(path: str | os.PathLike, world_from_depth: np.ndarray,
                      background: BackgroundModel | None = None, *,
                      background_paths: Iterable[str | os.PathLike] = (),
                      include_session: bool = True, chair: ChairModel | None = None,
                      config: SegmentationConfig | None = None) -> CameraSegmentation:
    """Segment every depth frame of one camera's Azure Kinect MKV recording.

    Args:
        path: the recording.
        world_from_depth: (4,4) world pose of this camera's depth camera (from calibration).
        background: a ready model; else one is built from ``background_paths`` and (with
            ``include_session``, or when there are no ``background_paths``) the recording itself,
            combined with :meth:`BackgroundModel.combine`.
        background_paths: recordings of the same camera with nobody in view (empty room,
            calibration captures).
        include_session: also use the recording's own frames for the background (helps where
            the empty-room frames had something in front, e.g. the ChArUco board).
        chair: the registered chair, if known.
        config: thresholds.

    Raises:
        SegmentationError: the file has no DEPTH stream, or no frame with valid depth.
        KinectFormatError: the file is not a readable Azure Kinect recording.
    """
    cfg = config or SegmentationConfig()
    path = Path(path)
    rec = open_azure_mkv(path)
    if "DEPTH" not in rec.tracks:
        raise SegmentationError(f"{path}: the recording has no DEPTH stream (depth mode "
                                f"{rec.depth_mode}); segmentation needs depth")
    calib = rec.calibration
    world_from_depth = np.asarray(world_from_depth, dtype=np.float64)
    if world_from_depth.shape != (4, 4):
        raise SegmentationError(f"{path}: world_from_depth must be (4, 4), got "
                                f"{world_from_depth.shape}")
    captures = [(c.index, c.timestamp_us, c.depth_mm) for c in rec]
    skipped: list[tuple[int, str]] = [(s.capture_index if s.capture_index is not None else -1,
                                       f"{s.track}: {s.reason}") for s in rec.skipped]
    usable = []
    for index, stamp, depth in captures:
        if depth is None:
            skipped.append((index, "no depth image in this capture"))
        elif not np.any(depth):
            skipped.append((index, "depth image is all zeros (invalid)"))
        else:
            usable.append((index, stamp, depth))
    if not usable:
        raise SegmentationError(f"{path}: none of its {len(captures)} captures has valid depth "
                                f"(all missing or all zeros)")
    if background is None:
        # each recording's own k-th farthest depth, then the farthest of them (combine)
        models = [background_from_recordings(background_paths, cfg)] if background_paths else []
        if include_session or not models:
            models.append(BackgroundModel.from_frames([d for _, _, d in usable], cfg))
        background = BackgroundModel.combine(models)
    static = None
    if chair is None and len(usable) >= cfg.static_min_frames:
        fgs = np.stack([foreground(d, background, calib, world_from_depth, cfg)[0]
                        for _, _, d in usable])
        static = static_foreground(fgs, cfg)
    frames = [segment_frame(d, background, calib, world_from_depth, chair, static, cfg,
                            index=i, timestamp_us=s) for i, s, d in usable]
    if skipped:
        log.warning("%s: skipped %d capture(s) without usable depth", path, len(skipped))
    return CameraSegmentation(serial=rec.serial or path.stem, calibration=calib,
                              world_from_depth=world_from_depth, background=background,
                              frames=frames, skipped=skipped)
