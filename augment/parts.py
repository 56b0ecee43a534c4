"""Part segmentation of a chair-like mesh in the chair frame, with a parametric frame per part.

Chair frame (``shapes.py``): metres, +Y up, floor y = 0, seat centred on x = z = 0, the seat
front facing +Z, the backrest at -Z. "Left" is the sitter's left, +X (SMPL's T-pose faces +Z
with its left hand at +X).

:func:`segment_parts` labels every face, from geometry alone, in this order (a face takes the
first part whose rule it meets):

1. ``seat``: the seat's top region (``shapes._seat_faces``: the largest upward-facing region at
   seat height) plus the seat slab under it: faces whose centroid lies within the top region's
   X/Z box (± :data:`BOX_MARGIN` along X, ± :data:`SEAT_MARGIN` along Z) and between the top
   and the slab's underside. The slab thickness is the median depth of the solid below the top
   (rays cast down from inside it), clamped to :data:`SEAT_THICKNESS_RANGE` (a sofa's cushion
   merges with its base).
2. ``backrest`` (only when ``shapes._back_direction`` finds a one-sided backrest at -Z): faces
   behind the backrest's front plane (a plane z = z0 + k·(y - seat height) fitted to the
   front-facing surface behind the seat's rear edge, + 1 cm), above the seat underside less
   3 cm, within the backrest's lateral extent (the X range of its upper quarter).
3. ``left_armrest`` / ``right_armrest``: the face-connected regions beside the seat (centroid
   beyond the seat box's +X / -X edge), outside the seat and backrest, that contain an armrest
   top (``shapes._armrest_tops``: upward-facing surface 0.12-0.38 m above the seat plane).
4. ``other``: everything else (legs, frame, base, plinth).

Part frames (:class:`PartFrame`), used for part-relative coordinates:

* seat, armrests: a 2D box on the part's top surface, horizontal: ``centre`` the box centre at
  the top height (area-weighted mean height of the top faces), ``u`` = +X, ``v`` = +Z (towards
  the front), ``normal`` = +Y, ``half_extents`` the box's half width (X) and half depth (Z).
* backrest: a 2D box on its front surface: ``u`` = +X, ``v`` up along the fitted front plane
  (unit (0, 1, k)/|·|, leaning back for k < 0), ``normal`` = the plane's unit normal pointing to
  the front (+Z side), ``centre`` on the plane at the middle of the front surface's extent,
  ``half_extents`` its half width (along u) and half height (along v).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
import trimesh

from couch.augment.shapes import (
    ARMREST_RISE,
    _armrest_tops,
    _back_direction,
    _seat_box,
    _seat_faces,
    _Skip,
    _surface_samples,
)

__all__ = [
    "BACKREST",
    "LEFT_ARMREST",
    "OTHER",
    "PART_NAMES",
    "RIGHT_ARMREST",
    "SEAT",
    "ChairParts",
    "PartFrame",
    "segment_parts",
]

PART_NAMES = ("seat", "backrest", "left_armrest", "right_armrest", "other")
SEAT, BACKREST, LEFT_ARMREST, RIGHT_ARMREST, OTHER = range(len(PART_NAMES))
"""Per-face label codes of :attr:`ChairParts.labels` (the same order as the simulator's
``tools/sim/chairs.py`` ``PART_NAMES``, whose ``back``/``base`` are ``backrest``/``other``)."""

SEAT_THICKNESS_RANGE = (0.015, 0.12)
"""The seat slab's thickness (m) is clamped to this range."""
BOX_MARGIN = 0.01
"""Slack (m) around the backrest plane and above the seat top when assigning faces."""
SEAT_MARGIN = 0.03
"""Slack (m) before and behind the seat top's Z range for the seat slab (covers a rounded front
edge); sideways the slack is :data:`BOX_MARGIN`, which keeps armrest posts out."""


@dataclass(frozen=True)
class PartFrame:
    """A part's 2D box on one of its surfaces (see module doc), chair frame, metres.

    ``centre`` (3,) the box centre on the surface; ``u``, ``v`` (3,) unit in-surface axes;
    ``normal`` (3,) unit, out of the surface; ``half_extents`` (2,) half sizes along u and v (m).
    Local coordinates of a point p: ``(a, b, w)`` with a = (p - centre)·u / half_extents[0],
    b = (p - centre)·v / half_extents[1] (in [-1, 1] on the box) and w = (p - centre)·normal
    the offset from the surface in metres.
    """

    centre: np.ndarray
    u: np.ndarray
    v: np.ndarray
    normal: np.ndarray
    half_extents: np.ndarray

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) chair-frame points → (N, 3) local ``(a, b, w)`` (a, b normalised, w metres)."""
        d = np.asarray(points, dtype=np.float64) - self.centre
        axes = np.stack([self.u, self.v, self.normal])            # (3, 3)
        return (d @ axes.T) / np.array([*self.half_extents, 1.0])

    def half_span(self) -> np.ndarray:
        """(3,) half sizes (m) of the box's extent along the chair frame's x, y and z."""
        return np.abs(self.u) * self.half_extents[0] + np.abs(self.v) * self.half_extents[1]

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """(N, 3) local ``(a, b, w)`` → (N, 3) chair-frame points (inverse of :meth:`to_local`)."""
        scaled = np.asarray(local, dtype=np.float64) * np.array([*self.half_extents, 1.0])
        axes = np.stack([self.u, self.v, self.normal])
        return self.centre + scaled @ axes


@dataclass(eq=False)
class ChairParts:
    """Part segmentation of one mesh (see module doc).

    ``labels`` (F,) int8 codes into ``names`` (:data:`PART_NAMES`), one per face; ``frames``
    the :class:`PartFrame` of each part found (keyed by name; ``other`` has none);
    ``seat_height`` the seat top's height (m) and ``seat_thickness`` the slab thickness used (m).
    """

    labels: np.ndarray
    frames: dict[str, PartFrame]
    seat_height: float
    seat_thickness: float
    names: tuple[str, ...] = field(default=PART_NAMES)

    def has(self, part: str) -> bool:
        """Whether ``part`` was found (it has faces and a frame)."""
        return part in self.frames

    def faces_of(self, part: str) -> np.ndarray:
        """Indices (K,) of the faces labelled ``part``."""
        return np.flatnonzero(self.labels == self.names.index(part))


def _box_frame(vertices: np.ndarray, faces: np.ndarray, top: np.ndarray,
               areas: np.ndarray, centroids: np.ndarray) -> PartFrame:
    """Horizontal box frame over the top faces ``top`` (K,): X/Z bounds of their vertices, at
    their area-weighted mean height."""
    xz = vertices[np.unique(faces[top])][:, [0, 2]]
    lo, hi = xz.min(0), xz.max(0)
    y = float(np.average(centroids[top, 1], weights=areas[top] + 1e-12))
    c = 0.5 * (lo + hi)
    return PartFrame(centre=np.array([c[0], y, c[1]]), u=np.array([1.0, 0.0, 0.0]),
                     v=np.array([0.0, 0.0, 1.0]), normal=np.array([0.0, 1.0, 0.0]),
                     half_extents=np.maximum(0.5 * (hi - lo), 1e-3))


def _seat_thickness(mesh: trimesh.Trimesh, seat: np.ndarray) -> float:
    """Median depth (m) of the solid under the seat top faces ``seat``, by rays cast down from
    1 mm below ~200 area-uniform points of the top; clamped to :data:`SEAT_THICKNESS_RANGE`."""
    rng = np.random.default_rng(0)
    sub = trimesh.Trimesh(mesh.vertices, mesh.faces[seat], process=False)
    pts, _, _ = _surface_samples(sub, rng, count=200)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32))
    rays = np.concatenate([pts - [0.0, 1e-3, 0.0], np.tile([0.0, -1.0, 0.0], (len(pts), 1))], 1)
    t = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    t = t[np.isfinite(t)] + 1e-3
    depth = float(np.median(t)) if len(t) else SEAT_THICKNESS_RANGE[0]
    return float(np.clip(depth, *SEAT_THICKNESS_RANGE))


def _back_plane(centroids: np.ndarray, normals: np.ndarray, areas: np.ndarray, seat_h: float,
                box: np.ndarray) -> tuple[float, float]:
    """(z0, k) of the backrest's front plane z = z0 + k·(y - seat_h): an area-weighted line fit
    to the front-facing (normal·Z > 0.5) faces above the seat (> 5 cm), behind its rear edge
    (+5 cm) in its central strip; (rear edge z, 0) when there are none."""
    (x0, z0), (x1, _) = box
    half = 0.5 * (x1 - x0)
    sel = ((normals[:, 2] > 0.5) & (centroids[:, 1] > seat_h + 0.05)
           & (centroids[:, 2] < z0 + 0.05) & (np.abs(centroids[:, 0] - 0.5 * (x0 + x1))
                                              < 0.6 * half))
    w = areas[sel]
    if w.sum() < 1e-4:
        return float(z0), 0.0
    dy, z = centroids[sel, 1] - seat_h, centroids[sel, 2]
    a = np.stack([np.ones_like(dy), dy], 1) * np.sqrt(w)[:, None]
    (c0, k), *_ = np.linalg.lstsq(a, z * np.sqrt(w), rcond=None)
    if np.ptp(dy) < 0.05:   # too short to fit a lean: vertical through the weighted mean
        return float(np.average(z, weights=w)), 0.0
    return float(c0), float(np.clip(k, -1.5, 0.5))


def _back_frame(vertices: np.ndarray, faces: np.ndarray, back: np.ndarray,
                normals: np.ndarray, z0: float, k: float, seat_h: float) -> PartFrame:
    """Box frame on the backrest's front surface (see module doc)."""
    n = np.array([0.0, -k, 1.0]) / np.hypot(1.0, k)
    v = np.array([0.0, 1.0, k]) / np.hypot(1.0, k)
    u = np.array([1.0, 0.0, 0.0])
    front = back[normals[back] @ n > 0.7]
    if len(front) == 0:
        front = back
    pts = vertices[np.unique(faces[front])]
    origin = np.array([0.0, seat_h, z0])            # a point on the plane
    a, b = (pts - origin) @ u, (pts - origin) @ v
    centre = origin + 0.5 * (a.min() + a.max()) * u + 0.5 * (b.min() + b.max()) * v
    half = np.maximum(0.5 * np.array([np.ptp(a), np.ptp(b)]), 1e-3)
    return PartFrame(centre=centre, u=u, v=v, normal=n, half_extents=half)


def segment_parts(vertices: np.ndarray, faces: np.ndarray) -> ChairParts:
    """Label each face of a chair-frame mesh as seat / backrest / armrest / other.

    ``vertices`` (V, 3) metres, ``faces`` (F, 3) int, in the chair frame (module doc); a closed,
    outward-oriented mesh (e.g. :class:`ShapeEntry` or a simulator ``Chair``) gives the best
    results. Returns :class:`ChairParts` with ``labels`` (F,) int8 and a frame per part found.
    Raises ``ValueError`` when no seat (upward-facing surface) is found.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    try:
        seat_top, seat_h = _seat_faces(mesh)
    except _Skip as exc:
        raise ValueError(f"segment_parts: {exc}") from exc
    c, n, areas = mesh.triangles_center, mesh.face_normals, mesh.area_faces
    box = _seat_box(vertices, faces, seat_top)
    (x0, z0), (x1, z1) = box
    m = BOX_MARGIN
    labels = np.full(len(faces), OTHER, dtype=np.int8)
    frames: dict[str, PartFrame] = {}

    # 1. Seat: the top region and the slab under it.
    thick = _seat_thickness(mesh, seat_top)
    bottom = seat_h - thick
    ms = SEAT_MARGIN
    in_box = ((c[:, 0] > x0 - m) & (c[:, 0] < x1 + m) & (c[:, 2] > z0 - ms)
              & (c[:, 2] < z1 + ms))
    seat = in_box & (c[:, 1] > bottom - 0.005) & (c[:, 1] < seat_h + m)
    seat[seat_top] = True
    labels[seat] = SEAT
    frames["seat"] = _box_frame(vertices, faces, seat_top, areas, c)
    free = ~seat

    # 2. Backrest: behind the fitted front plane, within its lateral extent.
    rng = np.random.default_rng(0)
    pts, _, dA = _surface_samples(mesh, rng, count=20000)
    if _back_direction(pts, dA, seat_h, box) == (2, -1):
        pz0, k = _back_plane(c, n, areas, seat_h, box)
        behind = free & (c[:, 2] < pz0 + k * (c[:, 1] - seat_h) + m) & (c[:, 1] > bottom - 0.03)
        ymax = float(c[behind, 1].max()) if behind.any() else seat_h
        upper = behind & (c[:, 1] > seat_h + 0.75 * (ymax - seat_h))
        if upper.any():
            xs = vertices[np.unique(faces[upper])][:, 0]
            back = behind & (c[:, 0] > xs.min() - 0.005) & (c[:, 0] < xs.max() + 0.005)
            if back.any():
                labels[back] = BACKREST
                free &= ~back
                frames["backrest"] = _back_frame(vertices, faces, np.flatnonzero(back), n,
                                                 pz0, k, seat_h)

    # 3. Armrests: lateral regions that hold an armrest top.
    seeds = _armrest_tops(c, n, seat_h, box)
    for code, name, side, seed in ((LEFT_ARMREST, "left_armrest", c[:, 0] > x1 - 0.005,
                                    seeds[0]),
                                   (RIGHT_ARMREST, "right_armrest", c[:, 0] < x0 + 0.005,
                                    seeds[1])):
        cand = np.flatnonzero(free & side)
        seed = free & side & seed
        if not seed.any() or areas[seed].sum() < 0.002:
            continue
        comps = trimesh.graph.connected_components(mesh.face_adjacency, nodes=cand,
                                                   min_len=1, engine="scipy")
        arm = np.concatenate([np.asarray(cc, dtype=np.int64) for cc in comps
                              if seed[np.asarray(cc, dtype=np.int64)].any()])
        labels[arm] = code
        free[arm] = False
        rise = c[arm, 1] - seat_h
        top = arm[(n[arm, 1] > 0.7) & (rise > ARMREST_RISE[0]) & (rise < ARMREST_RISE[1])]
        frames[name] = _box_frame(vertices, faces, top if len(top) else arm[seed[arm]],
                                  areas, c)
    return ChairParts(labels=labels, frames=frames, seat_height=float(seat_h),
                      seat_thickness=thick)
