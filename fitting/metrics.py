"""Quality metrics of body fits and motion, shared by tests, reports and benchmarks.

Every metric takes plain arrays (frames first) in metres and seconds, world frame, and returns
per-frame values plus their summary, so a report can show where a sequence goes wrong:

* :func:`mpjpe` — mean per-joint position error against ground truth joints.
* :func:`surface_distances` / :func:`chamfer` — how well a fitted mesh explains a point cloud:
  points → surface (exact point-to-triangle, open3d) and surface → points (samples of the
  surface seen by the cameras, nearest point; with :class:`CameraView` s and the chair as an
  occluder, "seen" means inside a camera's image and not hidden by the body or the chair).
* :func:`foot_skate` — horizontal foot travel while a foot is marked in contact (mm per frame).
* :func:`jitter` — mean jerk magnitude of joint trajectories (m/s³).
* :func:`sync_error` — an estimated clock model against the true one (ms, ppm).
* :func:`foot_points` — the four foot points (heels and big toes) of posed vertices.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from couch.capture.azure_calibration import CameraIntrinsics
from couch.capture.registration import project_points
from couch.geometry import sample_surface

__all__ = [
    "FOOT_KEYPOINTS",
    "CameraView",
    "SurfaceDistances",
    "chamfer",
    "foot_points",
    "foot_skate",
    "jitter",
    "mpjpe",
    "surface_distances",
    "sync_error",
]

#: The four foot points of the foot-slide term and the skate metric, as body-model keypoints.
FOOT_KEYPOINTS = ("LHeel", "LBigToe", "RHeel", "RBigToe")


def _frames(a: np.ndarray, name: str, trailing: tuple[int | None, ...]) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 1 + len(trailing) or any(
            t is not None and s != t for s, t in zip(arr.shape[1:], trailing, strict=True)):
        want = ", ".join("T" if i == 0 else ("*" if t is None else str(t))
                         for i, t in enumerate((None, *trailing)))
        raise ValueError(f"{name} must be ({want}), got {arr.shape}")
    return arr


def mpjpe(pred: np.ndarray, true: np.ndarray, *, root_aligned: bool = False) -> np.ndarray:
    """Mean per-joint position error per frame.

    Args:
        pred, true: (T, J, 3) joint positions, metres, same frame and joint order.
        root_aligned: subtract each frame's joint 0 (pelvis) from both first (pose error
            without the global position).

    Returns:
        (T,) metres; ``.mean()`` is the sequence MPJPE.
    """
    p = _frames(pred, "pred", (None, 3))
    t = _frames(true, "true", (None, 3))
    if p.shape != t.shape:
        raise ValueError(f"pred {p.shape} and true {t.shape} differ")
    if root_aligned:
        p = p - p[:, :1]
        t = t - t[:, :1]
    return np.linalg.norm(p - t, axis=-1).mean(axis=1)


@dataclass(frozen=True)
class SurfaceDistances:
    """Distances between one frame's fitted surface and its point cloud, metres.

    Attributes:
        to_surface: (N,) each point's distance to the nearest point of the mesh (of a subset
            of the points with ``max_points``).
        to_points: (S,) distance from each surface sample to the nearest point (only samples
            the cameras could see, see :func:`surface_distances`).
    """

    to_surface: np.ndarray
    to_points: np.ndarray

    @property
    def chamfer(self) -> float:
        """Symmetric chamfer: the mean of the two directions' mean distances (metres)."""
        a = self.to_surface.mean() if len(self.to_surface) else np.nan
        b = self.to_points.mean() if len(self.to_points) else np.nan
        return float(np.nanmean([a, b]))


@dataclasses.dataclass(frozen=True)
class CameraView:
    """What one depth camera sees: its world pose, intrinsics and, optionally, the static scene
    in front of it (for the visibility of surface samples).

    Attributes:
        world_from_camera: (4,4) world pose of the depth camera (metres).
        intrinsics: its :class:`~couch.capture.azure_calibration.CameraIntrinsics`.
        background: (H,W) metres of Z of the empty room per pixel (``inf``: nothing in range),
            e.g. the segmentation's :attr:`~couch.capture.segmentation.BackgroundModel.depth`:
            a point behind it (furniture, a wall, the chair) is hidden. None: not tested.
        margin: how far in front of the background a point must be to count as seen (metres;
            the segmentation cuts the person off where it touches the room).
        depth_range: (min, max) metres of Z the camera measures (e.g. ``DEPTH_RANGE_M`` of its
            depth mode), or None.
        max_incidence_deg: surface seen more obliquely than this returns no depth (a
            time-of-flight camera invalidates grazing returns), or None: no limit.
    """

    world_from_camera: np.ndarray
    intrinsics: CameraIntrinsics
    background: np.ndarray | None = None
    margin: float = 0.03
    depth_range: tuple[float, float] | None = None
    max_incidence_deg: float | None = None

    @property
    def centre(self) -> np.ndarray:
        return np.asarray(self.world_from_camera, np.float64)[:3, 3]

    def in_view(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: world points (N,3) that project inside the image, within the depth range
        and in front of the background (those given)."""
        pose = np.asarray(self.world_from_camera, np.float64)
        cam = (np.asarray(points, np.float64) - pose[:3, 3]) @ pose[:3, :3]
        uv, ok = project_points(cam, self.intrinsics)
        w, h = self.intrinsics.width, self.intrinsics.height
        px = np.where(ok[:, None], np.round(np.nan_to_num(uv)), -1).astype(np.int64)
        ok &= (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        if self.depth_range is not None:
            ok &= (cam[:, 2] >= self.depth_range[0]) & (cam[:, 2] <= self.depth_range[1])
        if self.background is not None:
            bg = np.asarray(self.background)[px[ok, 1], px[ok, 0]]
            ok[ok] = cam[ok, 2] < bg - self.margin
        return ok


Occluders = tuple[np.ndarray, np.ndarray] | o3d.t.geometry.RaycastingScene


def occluder_scene(occluders: Occluders) -> o3d.t.geometry.RaycastingScene:
    """A ray-casting scene of ``(vertices (W,3), faces (G,3))`` (or the scene itself): build it
    once for a static occluder and pass it to every frame's :func:`surface_distances`."""
    if isinstance(occluders, o3d.t.geometry.RaycastingScene):
        return occluders
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(occluders[0], np.float32)),
                        o3d.core.Tensor(np.asarray(occluders[1], np.uint32)))
    return scene


def surface_distances(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, *,
                      visible_from: np.ndarray | Sequence[CameraView] | None = None,
                      occluders: Occluders | None = None,
                      samples: int = 4000, seed: int = 0,
                      max_points: int | None = None,
                      tree: cKDTree | None = None) -> SurfaceDistances:
    """Point cloud ↔ mesh distances of one frame.

    Args:
        vertices: (V, 3) posed mesh, metres, world; faces: (F, 3) int.
        points: (N, 3) the frame's (segmented) point cloud, world.
        visible_from: (C, 3) camera centres, world, or C :class:`CameraView`: only surface
            samples that some camera sees (unoccluded by the mesh itself or the ``occluders``,
            and with views inside that camera's image) count in the surface → points
            direction, since the cameras never saw the rest. None: every sample counts.
        occluders: (vertices (W,3), faces (G,3)) of other surfaces in the scene (the chair) that
            hide parts of the body from the cameras, or their :func:`occluder_scene`; used only
            for the visibility.
        samples: surface samples (area-uniform) for the surface → points direction.
        seed: sampling seed (of the samples and of the points' subset).
        max_points: the points → surface direction on at most this many of the points (a
            seeded random subset; None or 0: all). Its mean is then an estimate (to ~0.1 mm
            for 4000 of a body's points), at a fraction of the cost of the exact distances;
            the other direction always searches every point (fewer would leave the surface
            farther from its nearest one).
        tree: ``cKDTree`` of the points (as float32) when the caller has it, for that search.

    Returns:
        :class:`SurfaceDistances`.
    """
    v = np.asarray(vertices, dtype=np.float32)
    f = np.asarray(faces, dtype=np.uint32)
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(f))
    query = pts
    if max_points and len(pts) > max_points:
        query = pts[np.sort(np.random.default_rng([1, seed]).choice(len(pts), max_points,
                                                                    replace=False))]
    to_surface = (scene.compute_distance(o3d.core.Tensor(query)).numpy().astype(np.float64)
                  if len(query) else np.zeros(0))
    sample, normal = sample_surface(v.astype(np.float64), f.astype(np.int64), samples, seed)
    if visible_from is not None:
        # a separate scene: adding the occluder to the body's would rebuild the body's BVH
        scenes = [scene] if occluders is None else [scene, occluder_scene(occluders)]
        sample = sample[_visible(scenes, sample, normal, visible_from)]
    tree = tree if tree is not None else cKDTree(pts) if len(pts) else None
    to_points = (tree.query(sample)[0] if len(pts) and len(sample)
                 else np.full(len(sample), np.nan))
    return SurfaceDistances(to_surface, np.asarray(to_points, dtype=np.float64))


def _visible(scenes: Sequence[o3d.t.geometry.RaycastingScene], pts: np.ndarray,
             normals: np.ndarray, cameras: np.ndarray | Sequence[CameraView]) -> np.ndarray:
    """(n,) bool: nothing of the scenes lies between the point and at least one camera (and,
    for a :class:`CameraView`, the point is inside its image, in its range, in front of its
    background and not seen more obliquely than its incidence limit)."""
    seen = np.zeros(len(pts), bool)
    views = (list(cameras) if len(cameras) and isinstance(cameras[0], CameraView)
             else [None] * len(cameras))
    centres = (np.array([v.centre for v in views]) if views and views[0] is not None
               else np.asarray(cameras, np.float64).reshape(-1, 3))
    for cam, view in zip(centres, views, strict=True):
        # rays only for the points no camera before saw and this one could (the ray casts
        # were the visibility's cost)
        idx = np.flatnonzero(~seen)
        p = pts[idx]
        d = cam - p
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        if view is not None:
            ok = view.in_view(p)
            if view.max_incidence_deg is not None:
                cos = np.abs(np.einsum("ij,ij->i", d, normals[idx]))
                ok &= cos >= np.cos(np.deg2rad(view.max_incidence_deg))
            idx, p, d, dist = idx[ok], p[ok], d[ok], dist[ok]
        if not len(idx):
            continue
        # start just off the surface towards the camera, so the sample's own face is not hit
        origin = p + 1e-4 * d
        rays = o3d.core.Tensor(np.concatenate([origin, d], axis=1).astype(np.float32))
        hit = np.min([sc.cast_rays(rays)["t_hit"].numpy() for sc in scenes], axis=0)
        seen[idx[~(hit < dist - 1e-3)]] = True
    return seen


def chamfer(vertices: np.ndarray, faces: np.ndarray, clouds: list[np.ndarray], *,
            visible_from: np.ndarray | Sequence[CameraView] | None = None,
            occluders: Occluders | None = None,
            samples: int = 4000) -> np.ndarray:
    """Per-frame symmetric chamfer distance (metres) of fitted meshes to their point clouds.

    Args:
        vertices: (T, V, 3) posed meshes; faces: (F, 3).
        clouds: T point clouds, (N_t, 3) each (their sizes differ, hence a list).
        visible_from, occluders: what the cameras could see (see :func:`surface_distances`).
        samples: surface samples per frame.

    Returns:
        (T,) chamfer per frame (NaN for a frame with no points).
    """
    verts = _frames(vertices, "vertices", (None, 3))
    if len(clouds) != len(verts):
        raise ValueError(f"{len(verts)} meshes but {len(clouds)} clouds")
    # Clouds differ in size per frame, so frames go one at a time through open3d's BVH.
    occluders = occluder_scene(occluders) if occluders is not None else None
    return np.array([surface_distances(v, faces, c, visible_from=visible_from,
                                       occluders=occluders, samples=samples, seed=t).chamfer
                     if len(c) else np.nan for t, (v, c) in enumerate(zip(verts, clouds,
                                                                          strict=True))])


def foot_points(vertices: np.ndarray, keypoint_ids: dict[str, int]) -> np.ndarray:
    """(T, 4, 3) heel and big-toe positions (``FOOT_KEYPOINTS`` order) of (T, V, 3) vertices,
    from a body model's ``keypoint_ids``."""
    missing = [k for k in FOOT_KEYPOINTS if k not in keypoint_ids]
    if missing:
        raise ValueError(f"the body model has no keypoint(s) {', '.join(missing)}")
    v = _frames(vertices, "vertices", (None, 3))
    return v[:, [keypoint_ids[k] for k in FOOT_KEYPOINTS]]


def foot_skate(feet: np.ndarray, contact: np.ndarray) -> np.ndarray:
    """Horizontal foot travel between consecutive frames in which a foot point is in contact.

    Args:
        feet: (T, K, 3) foot point positions, metres, world (Y up).
        contact: (T, K) bool, the point is on the floor (e.g. the IMU's foot contacts).

    Returns:
        (M,) millimetres per frame, one value per (frame pair, point) in contact in both frames;
        ``.mean()`` is the skate. Empty when no point is in contact twice in a row.
    """
    f = _frames(feet, "feet", (None, 3))
    c = np.asarray(contact, dtype=bool)
    if c.shape != f.shape[:2]:
        raise ValueError(f"contact {c.shape} must be (T, K) = {f.shape[:2]}")
    step = np.linalg.norm((f[1:] - f[:-1])[..., [0, 2]], axis=-1)
    both = c[1:] & c[:-1]
    return 1000.0 * step[both]


def jitter(positions: np.ndarray, fps: float) -> np.ndarray:
    """Jerk magnitude of trajectories: the third finite difference times ``fps³``.

    Args:
        positions: (T, J, 3) metres (T >= 4).
        fps: frames per second.

    Returns:
        (T-3,) mean over joints of |jerk|, m/s³.
    """
    p = _frames(positions, "positions", (None, 3))
    if len(p) < 4:
        raise ValueError(f"jitter needs >= 4 frames, got {len(p)}")
    jerk = np.diff(p, n=3, axis=0) * fps ** 3
    return np.linalg.norm(jerk, axis=-1).mean(axis=1)


def sync_error(offset_s: float, drift_ppm: float, true_offset_s: float,
               true_drift_ppm: float) -> tuple[float, float]:
    """(|offset error| in ms, |drift error| in ppm) of an estimated clock model
    ``t_other = (1 + drift·1e-6)·t_kinect + offset`` against the true one."""
    return abs(offset_s - true_offset_s) * 1000.0, abs(drift_ppm - true_drift_ppm)
