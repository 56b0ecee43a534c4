"""Chair registration: the object's scan mesh placed in the world from the session's depth.

COUCH placed the chair by hand from multi-view keypoints; here it is automatic:

1. **chair clouds** (:func:`chair_clouds`) — the chair stands in every recording of a session,
   the empty room and the calibration captures included, so background subtraction never shows
   it as foreground (the segmentation's ``chair`` masks need the registered chair, which is
   what this module produces). What may be the chair is therefore everything each camera sees
   *except* the person (the segmentation's person mask, grown by a few pixels), the floor
   (y <= ``floor_tolerance``) and depth edges (flying pixels), lifted to points per camera
   (:func:`couch.capture.camera_clouds.camera_clouds`, the cameras spread over worker processes
   when given a pool) and joined per frame. The room's clutter stays in; the
   registration picks the chair out of it by shape. Each camera's systematic depth error
   (offset, scale, radial: a few millimetres on an Azure Kinect) is measured on the floor it
   sees and taken out of its depth first (:mod:`couch.capture.depth_bias`): the cameras disagreeing
   by a few millimetres on the chair pulled its pose 5 mm off on a simulated armchair.
2. **global registration** (:func:`global_candidates`) — the frame with the most points is cut
   into objects (DBSCAN on a coarse copy). The chair stands on the floor (y = 0 of a levelled
   calibration), so every object whose extent fits the scan's gets starts with the scan in
   each of its stable resting poses (``trimesh.poses.compute_stable_poses``) as tall as the
   object, turned about the vertical in ``yaw_step`` steps, on the floor at the object's
   centre, each refined by point-to-plane ICP. Only when none of those fits and stands (a
   world not levelled on the floor, a chair tipped against something) is every object also
   matched against samples of the scan with FPFH features + RANSAC (open3d, seeded through
   ``o3d.utility.random.seed``, several seeds; ``ransac_always`` runs it anyway): on every
   held-out session RANSAC's starts refined to the floor starts' pose, and on a
   near-symmetric armchair its four runs all fitted it tilted.
   RANSAC alone is 5-30 cm off and a symmetric shape (a stool) fits several ways, so every
   candidate is refined (screened at a coarse voxel first, the best few distinct ones at full
   resolution) and the best ICP fitness wins; candidates that fit as well with a rotation
   more than ``ambiguity_deg`` away are reported as an ambiguity. Only candidates standing on
   the floor (lowest point within ``floor_gap``) compete while any does: a boxy armchair fits
   a cabinet's corner as closely as itself (a held-out session was registered on one, 0.8 m
   up); a chair registered off the floor is warned about.
3. **per-frame ICP** (:func:`track_frame`) — every frame's points within ``crop_margin`` of the
   current pose (cloud → scan surface, point-to-plane, Tukey kernel; the finest stage alone,
   then coarse to fine if that is not good enough). A frame is rejected with its reason: too
   few points (the person in front of the chair), low fitness (share of those points within
   ``inlier_distance`` of the surface), high RMSE. A frame whose
   ICP fails but which has points is registered globally again: a chair that moved is found.
4. **segments and averaging** (:func:`pose_segments`, :func:`average_poses`) — the accepted poses
   in time order are split where the pose jumps by more than ``move_mm`` / ``move_deg`` and stays
   (``min_segment_frames`` in a row; a lone jump is an outlier frame), so a chair moved between
   two static periods gives two segments instead of an average of both. Within a segment: the
   chordal L2 mean of the rotations (``scipy`` ``Rotation.mean``) and the median translation,
   iterating with outlier rejection; the spread is the RMS angle / distance of the kept frames.
5. **chamfer** — the registered mesh against the union of the segment's chair points (those
   within ``chamfer_margin`` of the mesh), both directions, the mesh side counted where a
   camera could see it (:func:`couch.fitting.metrics.surface_distances`).

Frames and units: metres; the world of the extrinsics (Y up, floor y = 0); the scan in its own
frame. ``world_from_object`` is the schema's ``/object/pose``: scan-frame vertices → world
(the simulator's ``ChairPlacement.world_from_scan``).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time as wallclock
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation
from tqdm.auto import tqdm

from couch.capture.calibration import Extrinsics
from couch.capture.camera_clouds import camera_clouds, join_cameras, join_row
from couch.capture.depth_bias import DepthBias, unmeasured_warnings
from couch.capture.pointcloud import CloudConfig, FusedCloud
from couch.capture.segmentation import (
    CameraSegmentation,
    FrameSegmentation,
    SegmentationConfig,
    camera_points,
    depth_edges,
    empty_room_recording,
)
from couch.capture.session import session_files
from couch.fitting.metrics import CameraView, surface_distances
from couch.geometry import apply_transform, invert_transform, sample_surface
from couch.pool import Pool, pool_map
from couch.rotations import rotation_angle

__all__ = [
    "ChairClouds",
    "ChairConfig",
    "ChairRegistration",
    "ChairRegistrationError",
    "ChairScan",
    "ChairSegment",
    "FrameResult",
    "average_poses",
    "chair_clouds",
    "global_candidates",
    "load_scan",
    "pose_segments",
    "register_chair",
    "register_session_chair",
    "rotation_angle_deg",
    "session_scan_path",
    "track_frame",
]


class ChairRegistrationError(ValueError):
    """The chair cannot be registered (the message names the file or session and why)."""


@dataclasses.dataclass(frozen=True)
class ChairConfig:
    """Knobs of the chair registration (lengths in metres, angles in degrees).

    Attributes:
        person_dilate_px: the person mask is grown by this many pixels before its complement
            may be chair (its rim is mixed depth and half-person).
        edge_ratio: drop depth-edge pixels (see :func:`~couch.capture.segmentation.
            depth_edges`) with this ratio; None: keep them. Both sides of every edge is all
            of a thin leg or stretcher at binned resolution (it took the chair's legs out of
            the clouds and put 1 cm on the chamfer); the clouds' own plane-fit outlier test
            (:class:`~couch.capture.pointcloud.CloudConfig`) drops the flying pixels anyway.
        scan_spacing: mean spacing of the scan's surface samples (ICP target).
        max_scan_samples: at most this many samples.
        voxel: voxel of the global registration (FPFH radius 5x, normals from the data).
        cluster_eps: DBSCAN neighbour distance that cuts a frame into objects.
        min_extent, max_extent: an object may be the chair when its extent (bounding-box
            diagonal) is within these fractions of the scan's.
        ransac_seeds: RANSAC runs (seeds ``seed`` ...) per object; 0: none.
        ransac_always: run RANSAC even when a floor start already fits (``min_fitness``,
            ``max_rmse``, ``min_points``) and stands on the floor (``floor_gap``). By default
            RANSAC runs only where none does: on every held-out session its starts refined to
            the floor starts' pose, and it was two fifths of the global registration's time.
        ransac_iterations, ransac_confidence: RANSAC convergence.
        seed: base seed of the scan sampling and RANSAC.
        icp_distances: ICP max correspondence distances, coarse to fine. Tracking a static
            chair from the previous frame's pose runs the finest stage alone first (it starts
            within millimetres) and the whole ladder only when that is not good.
        icp_iterations: per stage.
        icp_max_points: ICP moves at most this many of a frame's cropped points (a seeded
            random subset; the fitness and RMSE still count every point): a sofa seen by four
            cameras gives ~40k, and their nearest-neighbour searches were the ICP's time.
        screen_voxel: global candidates (RANSAC's, the turned and shifted starts) are first
            run through the coarsest ICP stage on the frame and the scan downsampled to this
            voxel (m) and ranked by their fitness against the exact surface; only the best
            ``refine_top`` distinct ones get the full-resolution ICP. 0: refine every one.
        refine_top: see ``screen_voxel``; enough for every turn of a symmetric stool.
        screen_max_points: the screening uses at most this many of the downsampled points (a
            seeded random subset; 0: all): a sofa seen by four cameras keeps ~16k at 2 cm, and
            screening ~170 starts on them was a third of the global registration's time.
        yaw_step: degrees between the floor starts' turns about the vertical (0: no floor
            starts, for clouds whose world is not levelled on the floor).
        rest_height: a resting pose is a floor start for an object when its height is within
            this (m) of the object's top (see ``_floor_starts``).
        floor_gap: a pose whose lowest scan vertex is farther than this (m) above or below the
            floor (y = 0) does not stand on it; such candidates lose to any that does (a boxy
            armchair fits a cabinet's corner as closely as itself). None: no such test, for
            clouds whose world is not levelled on the floor.
        shift_search: the best global candidate is also refined from starts moved this far
            (m) along each of the scan's axes, both ways (ICP's basin is narrower than a
            repeated part's spacing); (): no search.
        crop_margin: a frame's points this near the posed scan are the chair's.
        inlier_distance: a point this near the surface is explained by the chair.
        min_points: a frame with fewer chair points is rejected (occluded).
        min_point_fraction: ... or with fewer than this share of the best frame's count.
        min_fitness: reject below this share of inliers among the cropped points.
        max_rmse: reject above this RMS inlier distance.
        ambiguity_fitness: candidates within this fitness of the best are equally good (then
            those explaining within this share of the most points of all frames are kept, and
            of those the one whose points lie closest to it wins) ...
        ambiguity_distance: ... those whose points' mean distance is within this share of the
            winner's are the ambiguity ...
        ambiguity_deg: ... when their rotation differs by more than this.
        move_mm, move_deg: a pose this far from its segment's starts a new segment ...
        min_segment_frames: ... when this many accepted frames in a row agree (else: outliers).
        outlier_deg, outlier_mm: floors of the averaging's rejection thresholds (3 robust
            sigmas otherwise).
        chamfer_margin: chair points for the chamfer: this near the registered mesh.
        seen_tolerance: a surface point up to this far behind the farthest depth a camera
            measured at its pixel counts as seen by it (depth noise).
        chamfer_voxel: the union of a segment's points is downsampled to this.
        chamfer_samples: surface samples of the mesh → points direction.
    """

    person_dilate_px: int = 3
    edge_ratio: float | None = None
    floor_tolerance: float = 0.02
    scan_spacing: float = 0.005
    max_scan_samples: int = 60000
    voxel: float = 0.02
    cluster_eps: float = 0.05
    min_extent: float = 0.3
    max_extent: float = 1.3
    ransac_seeds: int = 4
    ransac_always: bool = False
    ransac_iterations: int = 100000
    ransac_confidence: float = 0.999
    seed: int = 0
    icp_distances: tuple[float, ...] = (0.05, 0.02, 0.008)
    icp_iterations: int = 30
    icp_max_points: int = 10000
    screen_voxel: float = 0.02
    refine_top: int = 6
    screen_max_points: int = 4000
    yaw_step: float = 30.0
    rest_height: float = 0.05
    floor_gap: float | None = 0.05
    shift_search: tuple[float, ...] = (0.04, 0.08)
    crop_margin: float = 0.05
    inlier_distance: float = 0.008
    min_points: int = 300
    min_point_fraction: float = 0.4
    min_fitness: float = 0.7
    max_rmse: float = 0.005
    ambiguity_fitness: float = 0.02
    ambiguity_distance: float = 0.05
    ambiguity_deg: float = 5.0
    move_mm: float = 30.0
    move_deg: float = 3.0
    min_segment_frames: int = 2
    outlier_deg: float = 0.5
    outlier_mm: float = 5.0
    chamfer_margin: float = 0.03
    seen_tolerance: float = 0.02
    chamfer_voxel: float = 0.005
    chamfer_samples: int = 8000


# --------------------------------------------------------------------------- the scan


@dataclasses.dataclass(frozen=True)
class DistanceGrid:
    """Distances (m) to a surface at the nodes of a regular grid (the surface's frame).

    The distance to a surface moves no faster than the point does, so a point's distance is
    its nearest node's within :attr:`bound` (half the cell's diagonal): the nodes tell most
    points' side of a margin without the exact query, and which points need one.

    Attributes:
        origin: (3,) the first node. spacing: node spacing (m).
        values: (X,Y,Z) float32 distances of the nodes.
    """

    origin: np.ndarray
    spacing: float
    values: np.ndarray

    @property
    def bound(self) -> float:
        """Largest gap (m) between a point's distance and its nearest node's (float32's
        rounding included), for points inside the grid."""
        return self.spacing * np.sqrt(3.0) / 2 + 1e-4

    @classmethod
    def of(cls, scene: o3d.t.geometry.RaycastingScene, low: np.ndarray, high: np.ndarray,
           spacing: float = 0.03, pad: float = 0.08) -> DistanceGrid:
        """The grid over the box ``low``-``high`` (m) widened by ``pad`` on every side."""
        origin = np.asarray(low, np.float64) - pad
        shape = np.ceil((np.asarray(high, np.float64) + pad - origin) / spacing).astype(int) + 1
        axes = [origin[k] + spacing * np.arange(shape[k]) for k in range(3)]
        nodes = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        values = scene.compute_distance(o3d.core.Tensor(nodes.astype(np.float32))).numpy()
        return cls(origin, float(spacing), values.reshape(*shape))

    def nearest(self, points: np.ndarray) -> np.ndarray:
        """(N,) the distance at each of ``points``' (N,3) nearest node; NaN outside the grid."""
        idx = np.rint((points - self.origin) / self.spacing).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < self.values.shape), axis=1)
        out = np.full(len(points), np.nan, np.float32)
        i = idx[inside]
        out[inside] = self.values[i[:, 0], i[:, 1], i[:, 2]]
        return out


@dataclasses.dataclass
class ChairScan:
    """The object's scan mesh (its own frame, metres) and what the registration uses of it.

    Attributes:
        path: the file (for messages), or None.
        vertices: (V,3) float64; faces: (F,3) int64.
        samples: (S,3) float64 area-uniform surface samples; normals: (S,3) their faces' unit
            normals.
        extent: bounding-box diagonal (m).
    """

    path: Path | None
    vertices: np.ndarray
    faces: np.ndarray
    samples: np.ndarray
    normals: np.ndarray
    extent: float

    @property
    def name(self) -> str:
        return str(self.path) if self.path is not None else "the chair scan"

    @property
    def centre(self) -> np.ndarray:
        """(3,) area centroid of the surface, scan frame (on every symmetry axis, unlike the
        bounding box's centre in the scan's arbitrary frame)."""
        return self.samples.mean(0)

    def scene(self) -> o3d.t.geometry.RaycastingScene:
        """A ray-casting scene of the mesh (scan frame) for exact point-to-surface distances."""
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                            o3d.core.Tensor(self.faces.astype(np.uint32)))
        return scene

    @functools.cached_property
    def distance_grid(self) -> DistanceGrid:
        """The surface's distances on a coarse grid (3 cm) over its bounding box
        (:class:`DistanceGrid`, built once: 0.4 s for a scan 1.7 m across)."""
        return DistanceGrid.of(self.scene(), self.vertices.min(0), self.vertices.max(0))

    @functools.cached_property
    def resting_rotations(self) -> np.ndarray:
        """(K,3,3) rotations (scan → world, Y up) of the scan's stable resting poses on a
        plane, most probable first (``trimesh.poses.compute_stable_poses`` about the area
        centroid; a chair's upright pose need not be the most probable)."""
        import trimesh  # here: the pool's workers, which import this module, never need it

        mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        # its probabilities (unused) take square roots of rounding-negative numbers
        with np.errstate(invalid="ignore"):
            poses, _ = trimesh.poses.compute_stable_poses(mesh, center_mass=self.centre)
        z_to_y = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # trimesh rests on z = 0
        return np.einsum("ij,njk->nik", z_to_y, np.asarray(poses)[:, :3, :3])

    def target(self, voxel: float = 0.0) -> o3d.geometry.PointCloud:
        """The samples with normals as an open3d cloud (the ICP target, scan frame); with
        ``voxel`` > 0 downsampled to that voxel (m; normals averaged per voxel)."""
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.samples))
        pcd.normals = o3d.utility.Vector3dVector(self.normals)
        if voxel > 0:
            pcd = pcd.voxel_down_sample(voxel)
            pcd.normalize_normals()
        return pcd


def _watertight(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Every edge shared by exactly two faces, with coincident vertices merged (OBJ writers
    split vertices per part or per normal) and the faces that merging collapses dropped (two
    coincident vertices of one surface, e.g. where a profile's radius reaches zero, leave
    zero-area slivers that are no hole)."""
    _, ids = np.unique(np.round(vertices, 9), axis=0, return_inverse=True)
    f = ids.reshape(-1)[faces]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    edges = edges[edges[:, 0] != edges[:, 1]]
    if not len(edges):
        return False
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def load_scan(source: str | os.PathLike | tuple[np.ndarray, np.ndarray],
              config: ChairConfig | None = None, *, require_watertight: bool = True
              ) -> ChairScan:
    """Read and check the chair's scan mesh (OBJ/PLY, or (vertices, faces) arrays).

    Raises:
        ChairRegistrationError: missing or unreadable file, no triangles, non-finite vertices,
            degenerate (zero area), not watertight (with ``require_watertight``), or a size no
            chair has in metres (over 5 m across: millimetres or centimetres, probably; under
            5 cm). The message names the file.
    """
    cfg = config or ChairConfig()
    if isinstance(source, tuple):
        path, (v, f) = None, source
        name = "the chair scan"
    else:
        path = Path(source)
        name = str(path)
        if not path.is_file():
            raise ChairRegistrationError(f"{path}: no such chair scan file")
        if path.suffix.lower() not in (".obj", ".ply", ".stl", ".off"):
            raise ChairRegistrationError(f"{path}: a chair scan must be .obj/.ply/.stl/.off")
        # open3d reports a bad file on stderr and returns an empty mesh: checked below
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh = o3d.io.read_triangle_mesh(str(path))
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    v = np.asarray(v, dtype=np.float64)
    f = np.asarray(f, dtype=np.int64)
    if v.ndim != 2 or v.shape[1:] != (3,) or f.ndim != 2 or f.shape[1:] != (3,):
        raise ChairRegistrationError(f"{name}: expected vertices (V,3) and faces (F,3), got "
                                     f"{v.shape} and {f.shape}")
    if not len(v) or not len(f):
        raise ChairRegistrationError(f"{name}: the chair scan is empty ({len(v)} vertices, "
                                     f"{len(f)} triangles)")
    if f.min() < 0 or f.max() >= len(v):
        raise ChairRegistrationError(f"{name}: face indices out of range 0..{len(v) - 1}")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise ChairRegistrationError(f"{name}: {int(bad.sum())} of {len(v)} vertices are NaN or "
                                     f"infinite (first: vertex {int(np.flatnonzero(bad)[0])})")
    extent = float(np.linalg.norm(v.max(0) - v.min(0)))
    if extent > 5.0:
        raise ChairRegistrationError(
            f"{name}: the chair scan is {extent:.4g} units across; the scan must be in metres "
            f"and no chair is over 5 m (in millimetres it would be {extent / 1000:.3g} m, in "
            f"centimetres {extent / 100:.3g} m)")
    if extent < 0.05:
        raise ChairRegistrationError(f"{name}: the chair scan is only {extent:.4g} m across; the "
                                     f"scan must be in metres (wrong units?)")
    if require_watertight and not _watertight(v, f):
        raise ChairRegistrationError(f"{name}: the chair scan is not watertight (some edges are "
                                     f"not shared by exactly two triangles: holes or a "
                                     f"non-manifold surface); repair it (e.g. pymeshlab "
                                     f"generate_alpha_wrap) first")
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                axis=1)
    keep = area > 1e-12
    if not keep.any():
        raise ChairRegistrationError(f"{name}: every triangle of the chair scan has zero area")
    n = int(min(cfg.max_scan_samples, max(2000, area.sum() / cfg.scan_spacing ** 2)))
    samples, normals = sample_surface(v, f[keep], n, cfg.seed)
    return ChairScan(path, v, f, samples, normals, extent)


def session_scan_path(session_dir: str | os.PathLike) -> Path:
    """The session's chair scan (:attr:`couch.capture.session.SessionFiles.chair_scan`:
    ``session.json``'s ``chair_scan`` entry, else ``chair_scan.obj`` / ``.ply``).

    Raises:
        ChairRegistrationError: the session has none.
    """
    files = session_files(session_dir)
    if files.chair_scan is None:
        raise ChairRegistrationError(f"{files.root}: the session has no chair scan "
                                     f"(chair_scan.obj, or session.json \"chair_scan\")")
    return files.chair_scan


# --------------------------------------------------------------------------- chair clouds


@dataclasses.dataclass
class ChairClouds:
    """What may be the chair in frames of a session (everything but the person and the floor).

    Attributes:
        session: the session folder.
        frames: (T,) int rows of the frame table (with a ``KinectSync``), else the index of
            each camera's usable frame.
        time: (T,) float64 seconds (Kinect master clock with a ``KinectSync``, else the first
            camera's device clock).
        clouds: T fused clouds (world).
        views: the C depth cameras (world), their ``background`` the farthest depth each pixel
            measured over these frames (the chair is part of the room's background, so the
            empty room cannot serve) and ``margin`` ``-seen_tolerance``: a chair surface point
            counts as seen when some frame measured no nearer than it (:func:`register_chair`'s
            chamfer).
        warnings: skipped captures per camera.
        depth_bias: per camera, the depth error taken out of its depth (None: not measured).
        serials: the cameras' serials, in that order.
    """

    session: Path
    frames: np.ndarray
    time: np.ndarray
    clouds: list[FusedCloud]
    views: list[CameraView]
    warnings: list[str]
    depth_bias: list[DepthBias | None] = dataclasses.field(default_factory=list)
    serials: list[str] = dataclasses.field(default_factory=list)


def scene_mask(frame: FrameSegmentation, segmentation: CameraSegmentation,
               config: ChairConfig | None = None, depth: np.ndarray | None = None
               ) -> np.ndarray:
    """(H,W) bool: depth pixels of one frame that may be the chair — valid depth, not the
    (grown) person, above the floor (world y > ``floor_tolerance``), optionally not a depth
    edge (``edge_ratio``). ``depth``: the frame's depth corrected (default: as recorded)."""
    cfg = config or ChairConfig()
    depth = frame.depth_mm if depth is None else depth
    k = 2 * cfg.person_dilate_px + 1
    person = cv2.dilate(frame.person.view(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    mask = (depth > 0) & ~person
    if cfg.edge_ratio is not None:
        mask &= ~depth_edges(depth, cfg.edge_ratio)
    pts = camera_points(depth, segmentation.calibration)
    pose = segmentation.world_from_depth
    with np.errstate(invalid="ignore"):
        height = pts @ pose[1, :3].astype(np.float32) + np.float32(pose[1, 3])
        mask &= height > cfg.floor_tolerance  # NaN (invalid) compares False
    return mask


def chair_clouds(session_dir: str | os.PathLike, extrinsics: Extrinsics | dict[str, np.ndarray],
                 *, frames: Sequence[int] | np.ndarray | None = None, step: int = 1,
                 kinect: object | None = None, tracks: Sequence[object] | None = None,
                 config: ChairConfig | None = None,
                 segmentation: SegmentationConfig | None = None,
                 cloud: CloudConfig | None = None, progress: bool = False,
                 pool: Pool = None) -> ChairClouds:
    """Clouds of what may be the chair, per frame (see the module doc, step 1).

    Mirrors :func:`couch.fitting.session.session_clouds`: every camera's recording is
    segmented once (background from its empty-room recording when there is one, else its
    calibration capture and its own frames; its depth error measured over all its frames) and
    each frame's masked points joined over cameras.

    Args:
        session_dir: the session.
        extrinsics: camera poses (:class:`Extrinsics` or serial → (4,4) world_from_depth).
        frames: which frames (rows of ``kinect.frame_table``, or per-camera frame indices);
            None: every ``step``-th.
        step: see ``frames``.
        kinect, tracks: ``SessionSync.kinect`` / ``.tracks`` to fuse frames by the master
            clock's rows; None: the k-th usable frame of every camera forms frame k (the chair
            is static and the person is removed per camera, so the cameras' time offsets
            matter only for ``time``).
        config: the chair stage's knobs (person growth, floor height).
        segmentation, cloud: capture-stage configs.
        progress: progress bars.
        pool: where the cameras' recordings are segmented and lifted to points
            (:func:`couch.capture.camera_clouds.camera_clouds`, one camera per task,
            :func:`couch.pool.spawn_pool`); None: one after another here. The clouds are the
            same either way.

    Raises:
        ChairRegistrationError: no camera has a recording or extrinsics.
    """
    files = session_files(session_dir)
    cfg = config or ChairConfig()
    seg_cfg = segmentation or SegmentationConfig()
    serials = (list(kinect.serials) if kinect is not None  # type: ignore[attr-defined]
               else [c.serial for c in files.cameras if c.recording is not None])
    if not serials:
        raise ChairRegistrationError(f"{files.root}: the session has no camera recordings")
    cloud = cloud or CloudConfig()
    sel = None
    if kinect is not None:
        table = kinect.frame_table  # type: ignore[attr-defined]
        by_serial = {t.serial: t.timestamp_us for t in tracks or ()}  # type: ignore[attr-defined]
        sel = (np.arange(0, len(table), max(1, int(step))) if frames is None
               else np.asarray(frames, int))
    tasks = []
    for c, serial in enumerate(serials):
        cam = files.camera(serial)
        if cam is None or cam.recording is None:
            raise ChairRegistrationError(f"{files.root}: no recording for camera {serial}")
        try:
            pose = (extrinsics.world_from_depth(serial) if isinstance(extrinsics, Extrinsics)
                    else np.asarray(extrinsics[serial], np.float64))
        except KeyError:
            raise ChairRegistrationError(f"{files.root}: no extrinsics for camera "
                                         f"{serial}") from None
        task = dict(recording=cam.recording, world_from_depth=pose,
                    empty_room=empty_room_recording(files.root, serial),
                    background_paths=[p for p in (cam.calibration_capture,) if p is not None],
                    segmentation=seg_cfg, cloud=cloud,
                    mask=functools.partial(scene_mask, config=cfg),
                    # the static chair and the depth error come from every frame
                    bias_on_all=True, person_dilate_px=cfg.person_dilate_px, far=True)
        if sel is not None:
            k = table[sel, c]
            task["timestamps"] = np.asarray(by_serial[serial])[k[k >= 0]]
        elif frames is not None:  # frame k of every camera: its k-th usable frame
            task["indices"] = np.asarray(frames, int)
        else:
            task["step"] = max(1, int(step))
        tasks.append(task)
    parts = pool_map(pool, camera_clouds, tasks,
                     desc="chair segmentation" if progress else None, unit="camera")
    warnings = [f"{p.recording}: {p.skipped} capture(s) without usable depth skipped"
                for p in parts if p.skipped]
    if cloud.depth_bias:
        warnings += unmeasured_warnings(serials, [p.depth_bias for p in parts])
    clouds, times = [], []
    if sel is not None:
        stamps = [np.asarray(by_serial[s]) for s in serials]
        for r in sel:
            t = float(kinect.time[r])  # type: ignore[attr-defined]
            clouds.append(join_row(parts, table[r], stamps, t))
            times.append(t)
    else:
        count = min(len(p.timestamps) for p in parts)
        sel = (np.arange(0, count * max(1, int(step)), max(1, int(step))) if frames is None
               else np.asarray(frames, int))
        for j in range(count):
            t = parts[0].timestamps[j] * 1e-6
            clouds.append(join_cameras(parts, [j] * len(parts), t))
            times.append(t)
    # CameraView hides points behind its background by more than -margin: here the farthest
    # measurement (0 where never valid: never seen), so a chair surface the person covered in
    # every frame does not count as missed
    views = [CameraView(p.world_from_depth, p.calibration.depth,
                        p.far.astype(np.float32) * np.float32(1e-3), margin=-cfg.seen_tolerance,
                        depth_range=p.depth_range,
                        max_incidence_deg=80.0) for p in parts]
    return ChairClouds(files.root, sel, np.asarray(times), clouds, views, warnings,
                       [p.depth_bias for p in parts], list(serials))


# --------------------------------------------------------------------------- registration


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle(s) (degrees) of the rotation between the (...,3,3) rotation parts of ``a`` and
    ``b`` (4x4 or 3x3)."""
    ra, rb = np.asarray(a)[..., :3, :3], np.asarray(b)[..., :3, :3]
    return np.degrees(rotation_angle(np.swapaxes(ra, -1, -2) @ rb))


@dataclasses.dataclass
class FrameResult:
    """One frame's registration.

    Attributes:
        pose: (4,4) world_from_object (scan → world), or None when ICP could not run.
        fitness: share of the cropped points within ``inlier_distance`` of the surface.
        rmse: RMS distance (m) of those inliers.
        points: points cropped (within ``crop_margin`` of the posed scan).
        method: ``track`` (ICP from the previous pose) or ``global`` (re-detected).
    """

    pose: np.ndarray | None
    fitness: float
    rmse: float
    points: int
    method: str = "track"


def _in_box(points: np.ndarray, scan: ChairScan, world_from_object: np.ndarray,
            margin: float) -> tuple[np.ndarray, np.ndarray]:
    """(M,3) the scan-frame points of ``points`` (N,3, world) within ``margin`` of the scan's
    bounding box, and (M,) their indices: the ray-casting need not see the room."""
    local = apply_transform(invert_transform(world_from_object), points)
    near = np.flatnonzero(np.all((local >= scan.vertices.min(0) - margin)
                                 & (local <= scan.vertices.max(0) + margin), axis=1))
    return local[near], near


def _distances(scene: o3d.t.geometry.RaycastingScene, local: np.ndarray) -> np.ndarray:
    return scene.compute_distance(o3d.core.Tensor(local.astype(np.float32))).numpy()


def _evaluate(points: np.ndarray, scan: ChairScan, scene: o3d.t.geometry.RaycastingScene,
              world_from_object: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """(N,) bool points within ``margin`` of the posed scan and (M,) their exact distances
    (m) to its surface."""
    local, near = _in_box(points, scan, world_from_object, margin)
    d = np.full(len(points), np.inf)
    if len(near):
        d[near] = _distances(scene, local)
    crop = d < margin
    return crop, d[crop]


def _crop(points: np.ndarray, scan: ChairScan, scene: o3d.t.geometry.RaycastingScene,
          world_from_object: np.ndarray, margin: float, cell: float = 0.015) -> np.ndarray:
    """:func:`_evaluate`'s crop alone, the same points: the scan's distance grid tells the
    points clearly nearer or farther than ``margin``, the exact distances only the rest (the
    exact queries were a third of the chair registration's time). Of those, the exact
    distance at the centre of each ``cell`` (m) they fall in decides the points within the
    cell's half diagonal of it, the same bound as the grid's: a margin narrower than the grid's
    bound (the chamfer's 3 cm) leaves most of a chair's points undecided, and they crowd into
    few cells."""
    local, near = _in_box(points, scan, world_from_object, margin)
    crop = np.zeros(len(points), bool)
    grid = scan.distance_grid
    g = grid.nearest(local)
    crop[near[g < margin - grid.bound]] = True
    unsure = np.flatnonzero(~(np.abs(g - margin) > grid.bound))  # NaN (off the grid) included
    if not len(unsure):
        return crop
    u = local[unsure]
    low = u.min(0)
    key = np.floor((u - low) / cell).astype(np.int64)
    span = key.max(0) + 1
    _, first, inv = np.unique((key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2],
                              return_index=True, return_inverse=True)
    centre = _distances(scene, low + (key[first] + 0.5) * cell)[inv]
    bound = cell * np.sqrt(3.0) / 2 + 1e-4  # float32's rounding included, as the grid's
    inside = centre < margin - bound
    again = ~(np.abs(centre - margin) > bound)
    if again.any():
        inside[again] = _distances(scene, u[again]) < margin
    crop[near[unsure]] = inside
    return crop


def track_frame(cloud: FusedCloud, scan: ChairScan, init: np.ndarray,
                config: ChairConfig | None = None,
                scene: o3d.t.geometry.RaycastingScene | None = None,
                target: o3d.geometry.PointCloud | None = None,
                stages: Sequence[float] | None = None) -> FrameResult:
    """Point-to-plane ICP of one frame's chair points onto the scan, from pose ``init``.

    The frame's points near the posed scan (``crop_margin``, re-cropped at every stage) go to
    the scan's samples (their normals), with a Tukey kernel at each stage's distance so that a
    hand on the armrest or a crumb of the person does not pull.

    Args:
        cloud: the frame (world). scan: the chair. init: (4,4) world_from_object to start at.
        scene, target: ``scan.scene()`` / ``scan.target()`` when the caller has them.
        stages: ICP max correspondence distances (m), coarse to fine (default
            ``config.icp_distances``).

    Returns:
        :class:`FrameResult` (``pose`` None when too few points were near).
    """
    cfg = config or ChairConfig()
    scene = scene or scan.scene()
    target = target or scan.target()
    pts = np.asarray(cloud.points, np.float64)
    pose = np.asarray(init, np.float64)
    stages = cfg.icp_distances if stages is None else tuple(stages)
    margin = max(cfg.crop_margin, stages[0])
    for dist in stages:
        crop = _crop(pts, scan, scene, pose, margin)
        if crop.sum() < max(cfg.min_points // 3, 10):
            return FrameResult(None, 0.0, np.inf, int(crop.sum()))
        idx = np.flatnonzero(crop)
        if len(idx) > cfg.icp_max_points:
            idx = np.random.default_rng(cfg.seed).choice(idx, cfg.icp_max_points, replace=False)
        source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[idx]))
        est = o3d.pipelines.registration.TransformationEstimationPointToPlane(
            o3d.pipelines.registration.TukeyLoss(k=dist))
        res = o3d.pipelines.registration.registration_icp(
            source, target, dist, invert_transform(pose), est,
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=cfg.icp_iterations))
        pose = invert_transform(np.asarray(res.transformation))
        margin = max(cfg.crop_margin, dist)
    crop, d = _evaluate(pts, scan, scene, pose, cfg.crop_margin)
    n = int(crop.sum())
    inl = d < cfg.inlier_distance
    fitness = float(inl.mean()) if n else 0.0
    rmse = float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else np.inf
    return FrameResult(pose, fitness, rmse, n)


def _objects(cloud: FusedCloud, scan: ChairScan, cfg: ChairConfig
             ) -> tuple[list[np.ndarray], float]:
    """Index arrays of the objects of a frame whose extent may be the chair's, and the largest
    object's extent (m) for messages."""
    pcd = cloud.to_open3d()
    if not len(pcd.points):
        return [], 0.0
    pts = np.asarray(pcd.points)
    # cluster a coarse copy, then give every point its voxel's label
    coarse, _, members = pcd.voxel_down_sample_and_trace(
        cfg.voxel / 2, pts.min(0) - 1e-3, pts.max(0) + 1e-3)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        labels = np.asarray(coarse.cluster_dbscan(cfg.cluster_eps, min_points=3))
    point_label = np.full(len(pts), -1)
    for lab, idx in zip(labels, members, strict=True):
        point_label[np.asarray(idx)] = lab
    out, largest = [], 0.0
    for lab in range(labels.max() + 1 if len(labels) else 0):
        idx = np.flatnonzero(point_label == lab)
        if len(idx) < cfg.min_points:
            continue
        ext = float(np.linalg.norm(pts[idx].max(0) - pts[idx].min(0)))
        largest = max(largest, ext)
        if cfg.min_extent * scan.extent <= ext <= cfg.max_extent * scan.extent:
            out.append(idx)
    return out, largest


def _fpfh(pcd: o3d.geometry.PointCloud, voxel: float
          ) -> tuple[o3d.geometry.PointCloud, o3d.pipelines.registration.Feature]:
    down = pcd.voxel_down_sample(voxel)
    if not down.has_normals():
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    feat = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
    return down, feat


def _ranked(found: list[FrameResult]) -> list[FrameResult]:
    return sorted(found, key=lambda r: (-round(r.fitness, 3), r.rmse))


def _refined(cloud: FusedCloud, scan: ChairScan,
             groups: Sequence[tuple[np.ndarray | None, Sequence[np.ndarray]]], cfg: ChairConfig,
             scene: o3d.t.geometry.RaycastingScene, target: o3d.geometry.PointCloud,
             coarse: o3d.geometry.PointCloud | None = None) -> list[FrameResult]:
    """ICP of the scan from (4,4) starts, best first (``method`` global).

    ``groups``: (indices of the frame's points the starts are about, e.g. one object's; None:
    all, and the starts) pairs. With ``screen_voxel``, every start is screened through the
    coarsest stage on its group's points downsampled to that voxel against ``coarse`` (the
    scan's target at twice that voxel), and the best ``refine_top`` distinct screened poses (over
    1 cm or 1 deg apart) are refined on the whole frame at full resolution from there: the
    full ICP of every start was most of the registration's time, and most of them land on the
    same few poses. Without it every start gets the full ICP."""
    screen = cfg.screen_voxel > 0 and len(cfg.icp_distances) > 1
    if not screen:
        starts = [p for _, inits in groups for p in inits]
    else:
        coarse = coarse if coarse is not None else scan.target(2 * cfg.screen_voxel)
        screened = []
        for idx, inits in groups:
            if not len(inits):
                continue
            pcd = cloud.to_open3d() if idx is None else o3d.geometry.PointCloud(
                o3d.utility.Vector3dVector(cloud.points[idx].astype(np.float64)))
            down = np.asarray(pcd.voxel_down_sample(cfg.screen_voxel).points, np.float32)
            if 0 < cfg.screen_max_points < len(down):
                down = down[np.sort(np.random.default_rng(cfg.seed).choice(
                    len(down), cfg.screen_max_points, replace=False))]
            small = FusedCloud(down, np.zeros_like(down), np.zeros(len(down), np.int8),
                               cloud.time)
            screened += [r for r in (track_frame(small, scan, p, cfg, scene, coarse,
                                                 cfg.icp_distances[:1]) for p in inits)
                         if r.pose is not None]
        starts = []
        for r in _ranked(screened):
            if len(starts) == cfg.refine_top:
                break
            if all(not _near(r.pose, q, scan.centre, 0.01, 1.0) for q in starts):
                starts.append(r.pose)
    stages = cfg.icp_distances[1:] if screen else cfg.icp_distances
    found = [track_frame(cloud, scan, p, cfg, scene, target, stages) for p in starts]
    return _ranked([dataclasses.replace(r, method="global") for r in found if r.pose is not None])



def global_candidates(cloud: FusedCloud, scan: ChairScan, config: ChairConfig | None = None,
                      scene: o3d.t.geometry.RaycastingScene | None = None,
                      target: o3d.geometry.PointCloud | None = None,
                      coarse: o3d.geometry.PointCloud | None = None
                      ) -> tuple[list[FrameResult], float]:
    """Global registrations of the scan in one frame, best first (see the module doc, step 2).

    Args:
        coarse: ``scan.target(2 * config.screen_voxel)`` when the caller has it.

    Returns:
        (candidates refined by ICP, sorted by fitness then RMSE; the extent (m) of the largest
        object in the frame, for messages).
    """
    cfg = config or ChairConfig()
    scene = scene or scan.scene()
    target = target or scan.target()
    objects, largest = _objects(cloud, scan, cfg)
    # an object too sparse for the features at ``voxel`` is not the chair
    objects = [idx for idx in objects if len(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        cloud.points[idx].astype(np.float64))).voxel_down_sample(cfg.voxel).points) >= 10]
    found = _refined(cloud, scan, [(idx, _floor_starts(scan, cloud.points[idx], cfg))
                                   for idx in objects], cfg, scene, target, coarse)
    # RANSAC only where the floor starts find nothing that fits and stands (a world not
    # levelled on the floor, a chair tipped against something, in none of its resting poses):
    # where they do, RANSAC's starts land on the same pose (every held-out session) and were two
    # fifths of the global registration
    if objects and cfg.ransac_seeds > 0 and (cfg.ransac_always or not any(
            _good(r, cfg) and _stands(scan, r, cfg) for r in found)):
        found = _ranked(found + _refined(cloud, scan, _ransac_starts(cloud, scan, objects, cfg),
                                         cfg, scene, target, coarse))
    return found, largest


def _ransac_starts(cloud: FusedCloud, scan: ChairScan, objects: Sequence[np.ndarray],
                   cfg: ChairConfig) -> list[tuple[np.ndarray, list[np.ndarray]]]:
    """(object's indices, (4,4) poses) of FPFH + RANSAC, ``ransac_seeds`` runs per object."""
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan.samples))
    src.normals = o3d.utility.Vector3dVector(scan.normals)
    src_down, src_feat = _fpfh(src, cfg.voxel)
    reg = o3d.pipelines.registration
    groups: list[tuple[np.ndarray, list[np.ndarray]]] = []
    for idx in objects:
        part = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
            cloud.points[idx].astype(np.float64)))
        part.normals = o3d.utility.Vector3dVector(cloud.normals[idx].astype(np.float64))
        tgt_down, tgt_feat = _fpfh(part, cfg.voxel)
        # the feature matching is the same for every run (open3d's feature-matching RANSAC
        # repeats it, about half of a run's time): match once, run RANSAC on the matches
        matches = reg.correspondences_from_features(src_feat, tgt_feat, False)
        inits = []
        for k in range(cfg.ransac_seeds):
            # open3d's RANSAC draws from its own global generator: seed it per run
            o3d.utility.random.seed(cfg.seed + k)
            res = reg.registration_ransac_based_on_correspondence(
                src_down, tgt_down, matches, 1.5 * cfg.voxel,
                reg.TransformationEstimationPointToPoint(False), 3,
                [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                 reg.CorrespondenceCheckerBasedOnDistance(1.5 * cfg.voxel)],
                reg.RANSACConvergenceCriteria(cfg.ransac_iterations, cfg.ransac_confidence))
            if res.fitness > 0:
                inits.append(np.asarray(res.transformation))
        groups.append((idx, inits))
    return groups


def _floor_starts(scan: ChairScan, points: np.ndarray, cfg: ChairConfig) -> list[np.ndarray]:
    """(4,4) poses of the scan resting on the floor (y = 0) in each stable pose as tall as the
    object's ``points`` (N,3) (their top within ``rest_height`` below or twice that above the
    pose's: flying pixels may rise over the chair, an occluder may hide its top), turned about
    the vertical by multiples of ``yaw_step``, its bounding box centred (x, z) on theirs."""
    if cfg.yaw_step <= 0 or not len(points):
        return []
    mid = (points.max(0) + points.min(0)) / 2
    top = float(points[:, 1].max())
    out = []
    for rest in scan.resting_rotations:
        height = np.ptp(scan.vertices @ rest[1])
        if not top - cfg.rest_height <= height <= top + 2 * cfg.rest_height:
            continue
        for yaw in np.arange(0.0, 360.0, cfg.yaw_step):
            rot = Rotation.from_euler("y", yaw, degrees=True).as_matrix() @ rest
            v = scan.vertices @ rot.T
            pose = np.eye(4)
            pose[:3, :3] = rot
            pose[:3, 3] = (mid[0] - (v[:, 0].max() + v[:, 0].min()) / 2, -v[:, 1].min(),
                           mid[2] - (v[:, 2].max() + v[:, 2].min()) / 2)
            out.append(pose)
    return out


def _turned(scan: ChairScan, start: np.ndarray) -> list[np.ndarray]:
    """(4,4) pose ``start`` turned about each principal axis of the scan (through its centre)
    by the first turns of 2-, 3-, 4- and 5-fold symmetries."""
    c = scan.centre
    _, axes = np.linalg.eigh(np.cov((scan.samples - c).T))
    out = []
    for axis in axes.T:
        for deg in (72, 90, 120, 180):
            rot = Rotation.from_rotvec(np.radians(deg) * axis).as_matrix()
            turn = np.eye(4)
            turn[:3, :3], turn[:3, 3] = rot, c - rot @ c
            out.append(start @ turn)
    return out


def _shifted(scan: ChairScan, start: np.ndarray, cfg: ChairConfig) -> list[np.ndarray]:
    """(4,4) pose ``start`` moved by ``shift_search`` along each of the scan's principal axes,
    both ways: a chair made of repeated parts (an armrest like the seat's edge, a row of
    slats) holds ICP a few centimetres off, beyond its coarsest correspondence distance."""
    _, axes = np.linalg.eigh(np.cov((scan.samples - scan.centre).T))
    out = []
    for axis in axes.T:
        for step in cfg.shift_search:
            for sign in (-1.0, 1.0):
                move = np.eye(4)
                move[:3, 3] = sign * step * axis
                out.append(start @ move)
    return out


def _explained(clouds: Sequence[FusedCloud], scan: ChairScan,
               scene: o3d.t.geometry.RaycastingScene, pose: np.ndarray, cfg: ChairConfig
               ) -> tuple[int, float]:
    """Points of all ``clouds`` within ``inlier_distance`` of the scan posed at ``pose``, and
    the mean distance (m) of all their points within ``crop_margin`` of it, each counted at
    most ``inlier_distance`` (a truncated mean, as MSAC scores a model: NaN without points)."""
    total, near = 0, []
    for c in clouds:
        pts = np.asarray(c.points, np.float64)
        if len(pts):
            _, d = _evaluate(pts, scan, scene, pose, cfg.crop_margin)
            total += int(np.count_nonzero(d < cfg.inlier_distance))
            near.append(np.minimum(d, cfg.inlier_distance))
    d = np.concatenate(near) if near else np.zeros(0)
    return total, float(d.mean()) if len(d) else float("nan")


def _floor_gap(scan: ChairScan, pose: np.ndarray) -> float:
    """Height (m) of the lowest scan vertex above the floor (y = 0) at ``pose``."""
    return float((scan.vertices @ pose[1, :3] + pose[1, 3]).min())


def _standing(found: list[FrameResult], scan: ChairScan, cfg: ChairConfig
              ) -> list[FrameResult]:
    """The candidates that stand on the floor (``floor_gap``), in their order; all of them
    when none does or the test is off (the caller reports it)."""
    if cfg.floor_gap is None:
        return found
    on = [r for r in found if _stands(scan, r, cfg)]
    return on or found


def _stands(scan: ChairScan, r: FrameResult, cfg: ChairConfig) -> bool:
    """The candidate's lowest point within ``floor_gap`` of the floor (True when the test is
    off)."""
    return cfg.floor_gap is None or abs(_floor_gap(scan, r.pose)) <= cfg.floor_gap


def _good(r: FrameResult, cfg: ChairConfig) -> bool:
    return (r.pose is not None and r.points >= cfg.min_points and r.fitness >= cfg.min_fitness
            and r.rmse <= cfg.max_rmse)


def _near(a: np.ndarray, b: np.ndarray, centre: np.ndarray, metres: float, deg: float) -> bool:
    """Poses within ``metres`` and ``deg``, the translation measured at the object's centre (a
    rotation about a far origin is not a move of the chair)."""
    ca, cb = apply_transform(a, centre[None])[0], apply_transform(b, centre[None])[0]
    return bool(np.linalg.norm(ca - cb) <= metres and rotation_angle_deg(a, b) <= deg)


def _close(a: np.ndarray, b: np.ndarray, cfg: ChairConfig, centre: np.ndarray) -> bool:
    """Poses within the move thresholds (``move_mm``, ``move_deg``)."""
    return _near(a, b, centre, cfg.move_mm * 1e-3, cfg.move_deg)


def average_poses(poses: np.ndarray, config: ChairConfig | None = None,
                  centre: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Robust average of (N,4,4) rigid poses of a static object.

    Rotation: chordal L2 mean (``Rotation.mean``); translation: the median; frames farther than
    max(floor, 3 robust sigmas) from the average in angle or in the object's ``centre`` (3,)
    (object frame; default the origin) are dropped and the average is taken again, until
    nothing changes.

    Returns:
        (pose (4,4); kept (N,) bool; rotation spread: RMS angle (deg) of the kept poses from
        the mean; translation spread: RMS distance (mm) of their centres from the average's).
    """
    cfg = config or ChairConfig()
    p = np.asarray(poses, np.float64)
    c = np.zeros(3) if centre is None else np.asarray(centre, np.float64)
    rots = Rotation.from_matrix(p[:, :3, :3])
    keep = np.ones(len(p), bool)
    for _ in range(10):
        mean = rots[keep].mean()
        t = np.median(p[keep, :3, 3], axis=0)
        avg = np.eye(4)
        avg[:3, :3], avg[:3, 3] = mean.as_matrix(), t
        ang = np.degrees((mean.inv() * rots).magnitude())
        # each frame's object centre against the average's
        pc = np.einsum("nij,j->ni", p[:, :3, :3], c) + p[:, :3, 3]
        dist = np.linalg.norm(pc - (avg[:3, :3] @ c + t), axis=1) * 1e3
        thr_r = max(cfg.outlier_deg, 3 * 1.4826 * np.median(ang[keep]))
        thr_t = max(cfg.outlier_mm, 3 * 1.4826 * np.median(dist[keep]))
        new = (ang <= thr_r) & (dist <= thr_t)
        if not new.any() or np.array_equal(new, keep):
            break
        keep = new
    spread_r = float(np.sqrt(np.mean(ang[keep] ** 2)))
    spread_t = float(np.sqrt(np.mean(dist[keep] ** 2)))
    return avg, keep, spread_r, spread_t


def pose_segments(poses: np.ndarray, config: ChairConfig | None = None,
                  centre: np.ndarray | None = None) -> tuple[np.ndarray, list[int]]:
    """Split a time-ordered sequence of (N,4,4) poses into static periods.

    A pose joins the current segment when it is within ``move_mm`` / ``move_deg`` of the
    segment's first pose; otherwise, when it and the next ``min_segment_frames - 1`` poses agree
    with each other, a new segment starts there; otherwise it is an outlier.

    Returns:
        (label (N,) int: segment index, -1 for outliers; the outliers' indices).
    """
    cfg = config or ChairConfig()
    p = np.asarray(poses, np.float64)
    c = np.zeros(3) if centre is None else np.asarray(centre, np.float64)
    labels = np.full(len(p), -1)
    ref: np.ndarray | None = None
    seg = -1
    for i in range(len(p)):
        if ref is not None and _close(p[i], ref, cfg, c):
            labels[i] = seg
            continue
        run = p[i:i + cfg.min_segment_frames]
        if len(run) >= cfg.min_segment_frames and all(_close(q, p[i], cfg, c) for q in run):
            seg += 1
            ref = p[i]
            labels[i] = seg
        elif ref is None and len(run) < cfg.min_segment_frames:
            # too short a sequence to confirm anything: the first pose starts the only segment
            seg, ref, labels[i] = 0, p[i], 0
    return labels, [int(i) for i in np.flatnonzero(labels < 0)]


@dataclasses.dataclass
class ChairSegment:
    """A static period of the chair.

    Attributes:
        first, last: positions (into the registration's frames) of its first and last accepted
            frame; start_time, end_time: their times (s).
        world_from_object: (4,4) the robust average.
        frames: positions of the frames averaged (outliers of the averaging left out).
        rotation_spread_deg, translation_spread_mm: see :func:`average_poses`.
        chamfer: metres, symmetric chamfer of the posed mesh to the segment's chair points.
        chamfer_to_surface, chamfer_to_points: its two directions' means (m).
    """

    first: int
    last: int
    start_time: float
    end_time: float
    world_from_object: np.ndarray
    frames: np.ndarray
    rotation_spread_deg: float
    translation_spread_mm: float
    chamfer: float = np.nan
    chamfer_to_surface: float = np.nan
    chamfer_to_points: float = np.nan


@dataclasses.dataclass
class ChairRegistration:
    """The chair in the session's world. T = frames registered.

    Attributes:
        scan: the scan file (or None).
        vertices, faces: the scan mesh (its own frame; the schema's /object/vertices, faces).
        world_from_object: (4,4) the schema's /object/pose (scan → world): the longest
            segment's average.
        frames: (T,) the frames (as in :class:`ChairClouds`); time: (T,) s.
        frame_poses: (T,4,4) per-frame ICP estimates (the schema's /object/frame_poses; NaN
            where the frame was rejected).
        fitness, rmse, points: (T,) per frame (see :class:`FrameResult`).
        method: (T,) ``track``/``global``/``""`` per frame.
        used: (T,) bool frames that entered an average.
        rejected: (position, reason) of each frame left out.
        segments: the static periods (one unless the chair moved).
        rotation_spread_deg, translation_spread_mm, chamfer: of the main segment.
        ambiguous: other poses fit about as well (a symmetric chair); ambiguity_deg: their
            rotation from the chosen one (deg).
        seconds: wall time per step.
        warnings: what may be wrong.
        depth_errors: serial -> the depth error measured on the floor and taken out of that
            camera's depth before registering (:meth:`DepthBias.report`); a camera that saw
            too little floor is missing (and named in ``warnings``).
    """

    scan: Path | None
    vertices: np.ndarray
    faces: np.ndarray
    world_from_object: np.ndarray
    frames: np.ndarray
    time: np.ndarray
    frame_poses: np.ndarray
    fitness: np.ndarray
    rmse: np.ndarray
    points: np.ndarray
    method: list[str]
    used: np.ndarray
    rejected: list[tuple[int, str]]
    segments: list[ChairSegment]
    rotation_spread_deg: float
    translation_spread_mm: float
    chamfer: float
    ambiguous: bool
    ambiguity_deg: list[float]
    seconds: dict[str, float]
    warnings: list[str]
    depth_errors: dict[str, dict[str, float]] = dataclasses.field(default_factory=dict)

    @property
    def moved(self) -> bool:
        """The chair stood in more than one place."""
        return len(self.segments) > 1

    @property
    def world_vertices(self) -> np.ndarray:
        """(V,3) the scan mesh in the world."""
        return apply_transform(self.world_from_object, self.vertices)

    def summary(self) -> str:
        """A few lines: where the chair is and how sure."""
        lines = [f"chair {self.scan}: {int(self.used.sum())}/{len(self.frames)} frames used, "
                 f"{len(self.segments)} segment(s); spread {self.rotation_spread_deg:.3f} deg, "
                 f"{self.translation_spread_mm:.2f} mm; chamfer {self.chamfer * 100:.3f} cm; "
                 f"mean fitness {np.nanmean(self.fitness):.3f}, rmse "
                 f"{np.nanmean(np.where(np.isfinite(self.rmse), self.rmse, np.nan)) * 1e3:.2f} mm"]
        for s in self.segments:
            lines.append(f"  segment {s.start_time:.2f}-{s.end_time:.2f} s: {len(s.frames)} "
                         f"frames, spread {s.rotation_spread_deg:.3f} deg / "
                         f"{s.translation_spread_mm:.2f} mm, chamfer {s.chamfer * 100:.3f} cm")
        reasons: dict[str, int] = {}
        for _, why in self.rejected:
            key = why.split(":")[0]
            reasons[key] = reasons.get(key, 0) + 1
        if reasons:
            lines.append("  rejected: " + ", ".join(f"{v} {k}" for k, v in reasons.items()))
        lines.append("  time: " + ", ".join(f"{k} {v:.1f} s" for k, v in self.seconds.items()))
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def register_chair(scan: ChairScan | str | os.PathLike, clouds: ChairClouds | Sequence[FusedCloud],
                   *, views: Sequence[CameraView] | None = None,
                   config: ChairConfig | None = None, progress: bool = False
                   ) -> ChairRegistration:
    """Register the chair's scan in every frame, find its static periods and average them.

    Args:
        scan: the scan (:func:`load_scan`) or its file.
        clouds: :func:`chair_clouds` output, or T clouds (world) in time order.
        views: the depth cameras, for the chamfer's visibility (default: ``clouds.views``;
            None: every mesh sample counts, an overestimate).
        config: see :class:`ChairConfig`.
        progress: progress bar over frames.

    Raises:
        ChairRegistrationError: a bad scan (see :func:`load_scan`), no points, no object of the
            scan's size in the points (wrong units?), or no frame in which it fits.
    """
    cfg = config or ChairConfig()
    sec: dict[str, float] = {}
    t0 = wallclock.perf_counter()
    if not isinstance(scan, ChairScan):
        scan = load_scan(scan, cfg)
    depth_errors: dict[str, dict[str, float]] = {}
    if isinstance(clouds, ChairClouds):
        views = clouds.views if views is None else views
        frames, times, cl = clouds.frames, clouds.time, list(clouds.clouds)
        where = str(clouds.session)
        if clouds.depth_bias:  # clouds made by chair_clouds carry one per camera
            names = clouds.serials or [f"camera {k}" for k in range(len(clouds.depth_bias))]
            depth_errors = {name: bias.report() for name, bias
                            in zip(names, clouds.depth_bias, strict=True) if bias is not None}
    else:
        cl = list(clouds)
        frames, times = np.arange(len(cl)), np.array([c.time for c in cl], np.float64)
        where = "the clouds"
    n = len(cl)
    counts = np.array([len(c) for c in cl])
    if not n or not counts.any():
        raise ChairRegistrationError(f"{where}: no points that could be the chair in any frame")
    scene, target = scan.scene(), scan.target()
    coarse = scan.target(2 * cfg.screen_voxel) if cfg.screen_voxel > 0 else None
    sec["scan"] = wallclock.perf_counter() - t0

    # global registration on the frame that sees the most
    t0 = wallclock.perf_counter()
    best = int(np.argmax(counts))
    cands, largest = global_candidates(cl[best], scan, cfg, scene, target, coarse)
    if not cands:
        raise ChairRegistrationError(
            f"{scan.name}: no object in {where} (frame {int(frames[best])}) has the scan's size "
            f"({scan.extent:.3g} m across) and matches it (the largest object there is "
            f"{largest:.3g} m across): is the scan in metres and of this chair?")
    # a symmetric chair (a stool) fits turned about one of its axes as well, and RANSAC's
    # runs need not find those turns: try them from the best candidate, keep the best ICP
    # the chair stands on the floor: a pose that does not loses to any that does, before the
    # turns of the best are tried and before the rivals below are judged by the points they
    # explain (a boxy armchair explained a cabinet's corner better than itself)
    cands = _standing(cands, scan, cfg)
    cands = _standing(_ranked(cands + _refined(
        cl[best], scan, [(None, _turned(scan, cands[0].pose) + _shifted(scan, cands[0].pose,
                                                                         cfg))],
        cfg, scene, target, coarse)), scan, cfg)
    top = cands[0]
    if not _good(top, cfg):
        raise ChairRegistrationError(
            f"{scan.name}: the scan does not fit the points of {where} (frame "
            f"{int(frames[best])}: best fitness {top.fitness:.2f}, rmse {top.rmse * 1e3:.1f} mm, "
            f"{top.points} points): is the scan of this chair and in metres?")
    # candidates as good as the best but turned: a symmetric chair, or a nearly symmetric one
    # whose telling part (a stool's leg) the person hides in this frame. The chair is static,
    # so every frame's points judge them: the turns that explain about as many points as the
    # most stay in (a turn that puts a hidden leg where there is none explains fewer), and of
    # those the one the points lie closest to wins. A count cannot tell the turns of a nearly
    # symmetric stool apart (three square legs turned by 120 degrees differ by millimetres),
    # their distances can; the turns that fit about as closely are the ambiguity reported.
    rivals = [top] + [c for c in cands[1:]
                      if c.fitness >= top.fitness - cfg.ambiguity_fitness and _good(c, cfg)
                      and rotation_angle_deg(c.pose, top.pose) > cfg.ambiguity_deg]
    ambiguity: list[float] = []
    if len(rivals) > 1:
        explained, spread = np.array([_explained(cl, scan, scene, c.pose, cfg)
                                      for c in rivals]).T
        level = np.flatnonzero(explained >= (1 - cfg.ambiguity_fitness) * explained.max())
        win = int(level[np.argmin(spread[level])])
        top = rivals[win]
        ambiguity = sorted({round(float(rotation_angle_deg(rivals[k].pose, top.pose)), 1)
                            for k in level
                            if spread[k] <= (1 + cfg.ambiguity_distance) * spread[win]
                            and rotation_angle_deg(rivals[k].pose, top.pose) > cfg.ambiguity_deg})
    sec["global"] = wallclock.perf_counter() - t0

    # per-frame ICP from the previous accepted pose; re-detect where it fails
    t0 = wallclock.perf_counter()
    results: list[FrameResult] = []
    pose = top.pose
    for i in tqdm(range(n), desc="chair ICP", unit="frame", disable=not progress):
        # a static chair: the last pose is within millimetres, the finest stage is enough
        r = track_frame(cl[i], scan, pose, cfg, scene, target, cfg.icp_distances[-1:])
        if not _good(r, cfg):
            r = track_frame(cl[i], scan, pose, cfg, scene, target)
        if not _good(r, cfg) and counts[i] >= cfg.min_points and i != best:
            again, _ = global_candidates(cl[i], scan, cfg, scene, target, coarse)
            again = _standing(again, scan, cfg)
            if again and _good(again[0], cfg) and again[0].fitness > r.fitness:
                r = again[0]
        if i == best and not _good(r, cfg):
            r = top
        if _good(r, cfg):
            pose = r.pose
        results.append(r)
    sec["icp"] = wallclock.perf_counter() - t0

    # rejection, segments, averages
    t0 = wallclock.perf_counter()
    pts = np.array([r.points for r in results])
    fit = np.array([r.fitness for r in results])
    rmse = np.array([r.rmse for r in results])
    enough = max(cfg.min_points, cfg.min_point_fraction * pts.max())
    rejected: list[tuple[int, str]] = []
    ok = np.zeros(n, bool)
    for i, r in enumerate(results):
        if r.pose is None or r.points < enough:
            rejected.append((i, f"too few points: {r.points} near the chair (need "
                                f"{enough:.0f}; occluded?)"))
        elif r.fitness < cfg.min_fitness:
            rejected.append((i, f"low fitness: {r.fitness:.2f} < {cfg.min_fitness}"))
        elif r.rmse > cfg.max_rmse:
            rejected.append((i, f"high rmse: {r.rmse * 1e3:.1f} mm > {cfg.max_rmse * 1e3:.1f}"))
        else:
            ok[i] = True
    if not ok.any():
        raise ChairRegistrationError(f"{scan.name}: the chair fits no frame of {where} well "
                                     f"enough ({len(rejected)} frames rejected, first: "
                                     f"{rejected[0][1]})")
    frame_poses = np.full((n, 4, 4), np.nan)
    for i in np.flatnonzero(ok):
        frame_poses[i] = results[i].pose
    idx = np.flatnonzero(ok)
    labels, outliers = pose_segments(frame_poses[idx], cfg, scan.centre)
    for j in outliers:
        rejected.append((int(idx[j]), "pose outlier: the pose jumped for this frame only"))
    used = np.zeros(n, bool)
    segments: list[ChairSegment] = []
    for s in range(labels.max() + 1):
        members = idx[labels == s]
        avg, keep, sr, st = average_poses(frame_poses[members], cfg, scan.centre)
        for i in members[~keep]:
            rejected.append((int(i), "averaging outlier: far from the segment's mean pose"))
        used[members[keep]] = True
        segments.append(ChairSegment(int(members[0]), int(members[-1]),
                                     float(times[members[0]]), float(times[members[-1]]), avg,
                                     members[keep], sr, st))
    rejected.sort()
    sec["average"] = wallclock.perf_counter() - t0

    # chamfer per segment on the union of its frames' chair points
    t0 = wallclock.perf_counter()
    for s in segments:
        union = np.concatenate([np.asarray(cl[i].points, np.float64) for i in s.frames])
        crop = _crop(union, scan, scene, s.world_from_object, cfg.chamfer_margin)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(union[crop]))
        if cfg.chamfer_voxel > 0:
            pcd = pcd.voxel_down_sample(cfg.chamfer_voxel)
        sd = surface_distances(apply_transform(s.world_from_object, scan.vertices), scan.faces,
                               np.asarray(pcd.points),
                               visible_from=list(views) if views else None,
                               samples=cfg.chamfer_samples, seed=cfg.seed)
        s.chamfer = sd.chamfer
        s.chamfer_to_surface = float(sd.to_surface.mean()) if len(sd.to_surface) else np.nan
        s.chamfer_to_points = float(sd.to_points.mean()) if len(sd.to_points) else np.nan
    sec["chamfer"] = wallclock.perf_counter() - t0

    main = max(segments, key=lambda s: len(s.frames))
    warnings = []
    if len(segments) > 1:
        warnings.append("the chair moved: " + "; ".join(
            f"{s.start_time:.2f}-{s.end_time:.2f} s ({len(s.frames)} frames)" for s in segments)
            + f"; /object/pose is the longest period's ({main.start_time:.2f}-"
              f"{main.end_time:.2f} s)")
    if ambiguity:
        warnings.append(f"ambiguous orientation: poses turned by {ambiguity} deg fit the points "
                        f"as well (a symmetric chair); kept the best-fitting one")
    if views is None:
        warnings.append("no camera views: the chamfer counts the whole mesh, seen or not")
    gap = _floor_gap(scan, main.world_from_object)
    if cfg.floor_gap is not None and abs(gap) > cfg.floor_gap:
        warnings.append(f"the registered chair does not stand on the floor: its lowest point is "
                        f"{100 * gap:+.1f} cm from it (no pose found that fits and stands); "
                        f"check the scan and the calibration's floor")
    return ChairRegistration(
        scan=scan.path, vertices=scan.vertices, faces=scan.faces,
        world_from_object=main.world_from_object, frames=np.asarray(frames),
        time=np.asarray(times, np.float64), frame_poses=frame_poses, fitness=fit, rmse=rmse,
        points=pts, method=[r.method if r.pose is not None else "" for r in results],
        used=used, rejected=rejected, segments=segments,
        rotation_spread_deg=main.rotation_spread_deg,
        translation_spread_mm=main.translation_spread_mm, chamfer=main.chamfer,
        ambiguous=bool(ambiguity), ambiguity_deg=list(ambiguity), seconds=sec,
        warnings=warnings, depth_errors=depth_errors)


def register_session_chair(session_dir: str | os.PathLike,
                           extrinsics: Extrinsics | dict[str, np.ndarray], *,
                           scan: str | os.PathLike | None = None,
                           frames: Sequence[int] | np.ndarray | None = None, step: int = 1,
                           config: ChairConfig | None = None,
                           segmentation: SegmentationConfig | None = None,
                           cloud: CloudConfig | None = None, progress: bool = False,
                           pool: Pool = None) -> ChairRegistration:
    """:func:`chair_clouds` then :func:`register_chair` on a session folder (the scan from the
    session unless ``scan`` is given). The scan is checked first, so a bad scan fails fast.
    ``pool``: :func:`chair_clouds`'s."""
    cfg = config or ChairConfig()
    t0 = wallclock.perf_counter()
    the_scan = load_scan(scan if scan is not None else session_scan_path(session_dir), cfg)
    clouds = chair_clouds(session_dir, extrinsics, frames=frames, step=step, config=cfg,
                          segmentation=segmentation, cloud=cloud, progress=progress, pool=pool)
    took = wallclock.perf_counter() - t0
    reg = register_chair(the_scan, clouds, config=cfg, progress=progress)
    reg.seconds = {"clouds": took, **reg.seconds}
    reg.warnings = clouds.warnings + reg.warnings
    return reg
