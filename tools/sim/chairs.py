"""Parametric chairs, stools and sofas for the simulator, their geometric landmarks, a cluttered
room, a random scanner frame, and mesh I/O (OBJ/PLY and the ShapeNetCore v2 layout).

Chair frame (DESIGN.md): metres, +Y up, floor at y = 0, the seat centred on x = 0 and z = 0, the
chair faces +Z (a sitter looks towards +Z; the backrest is at -Z). "Left" is the sitter's left, +X.

Generated chairs are unions of boxes, rounded boxes and prisms. The union is an exact boolean
(pymeshlab's ``generate_boolean_union``, libigl/CGAL with exact arithmetic), which keeps flat faces
flat and sharp edges sharp, so the generated mesh agrees with its :class:`ChairSpec` to float
precision and stays light (a few hundred to ~2500 triangles). Each input face carries its part
label through the union as MeshLab "face quality", so labels are exact, not transferred by
proximity. Parts are laid out to overlap in volume or meet on exactly shared planes (never along
a single edge or nearly-coincident planes), which is what keeps every union manifold.

Landmarks (:func:`chair_landmarks`) are measured from the surface alone by ray casting (open3d's
``RaycastingScene``), so they also work for any chair-like mesh in the chair frame, e.g. a
ShapeNet chair after alpha-wrap repair.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial.transform import Rotation

from couch.atomic import atomic_path
from couch.geometry import apply_transform, make_transform

__all__ = [
    "BACK",
    "BASE",
    "CHAIR_SYNSET",
    "KINDS",
    "LEFT_ARMREST",
    "PART_NAMES",
    "RIGHT_ARMREST",
    "SEAT",
    "SHAPENET_FROM_CHAIR",
    "SOFA_SYNSET",
    "Chair",
    "ChairLandmarks",
    "ChairSpec",
    "ContactCandidate",
    "RoomObject",
    "chair_landmarks",
    "load_mesh",
    "make_chair",
    "make_room",
    "random_chair_spec",
    "save_mesh",
    "scan_pose",
    "to_scan_frame",
    "write_shapenet_layout",
]

KINDS = ("straight", "armchair", "sofa", "stool")
PART_NAMES = ("seat", "back", "left_armrest", "right_armrest", "base")
SEAT, BACK, LEFT_ARMREST, RIGHT_ARMREST, BASE = range(len(PART_NAMES))
"""Per-face labels of :attr:`Chair.face_parts`; ``base`` covers legs, stretchers and plinths."""

CHAIR_SYNSET = "03001627"
SOFA_SYNSET = "04256520"
_SYNSET_NAMES = {CHAIR_SYNSET: "chair", SOFA_SYNSET: "sofa,couch,lounge"}

SHAPENET_FROM_CHAIR = make_transform(np.diag([-1.0, 1.0, -1.0]), np.zeros(3))
"""ShapeNet axes from chair axes: both +Y up, but ShapeNet's front is -Z and ours +Z, so a
half turn about Y (it keeps handedness and face orientation)."""


# --------------------------------------------------------------------------------------------
# Specification
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ChairSpec:
    """Dimensions of a parametric chair, metres and degrees, in the chair frame.

    ``seat_height`` is the top of the seat surface above the floor; ``seat_width`` (along X) and
    ``seat_depth`` (along Z) are the usable seat: between the armrests and from the seat's front
    edge to the front face of the backrest. ``back_height`` is the top of the backrest above the
    seat (None: no backrest, the stool); ``back_tilt_deg`` leans it backwards (towards -Z).
    ``armrest_height`` is the armrest top above the seat (None for kinds without armrests),
    ``armrest_width`` its width along X (0 without armrests). For sofas ``seat_thickness`` is the
    seat cushion's thickness. The generated chair stands on y = 0 with its seat centred on
    x = z = 0. Use :meth:`for_kind` for real-furniture defaults and :func:`random_chair_spec`
    for variety; the fields after ``leg_thickness`` are style options.
    """

    kind: str
    seat_height: float
    seat_width: float
    seat_depth: float
    seat_thickness: float
    back_height: float | None
    back_tilt_deg: float
    back_thickness: float
    armrest_height: float | None
    armrest_width: float
    leg_thickness: float
    round_legs: bool = False
    """Chairs and stools: cylindrical instead of square legs (sofa legs are always round)."""
    leg_count: int = 4
    """Stools: 3 or 4 legs (the other kinds always have 4)."""
    leg_splay_deg: float = 0.0
    """Stools: legs lean outwards by this angle."""
    stretcher_height: float | None = None
    """Straight chairs: side rails between the legs; stools: a footrest ring. None: none."""
    back_gap: float = 0.0
    """Straight chairs: open gap between the seat and the back panel (0: a solid back)."""
    cushions: int = 1
    """Sofas: number of seat cushions across the width."""
    base: str = "plinth"
    """Sofas: ``"plinth"`` (a solid base down to the floor) or ``"legs"`` (short legs)."""
    base_clearance: float = 0.0
    """Sofas with ``base="legs"``: height of the base's underside above the floor."""
    rounding: float = 0.0
    """Sofas: edge radius of the upholstered parts (cushions, arms, back)."""

    def __post_init__(self) -> None:
        def need(ok: bool, what: str) -> None:
            if not ok:
                raise ValueError(f"ChairSpec({self.kind!r}): {what}")

        need(self.kind in KINDS, f"kind must be one of {KINDS}")
        for name in ("seat_height", "seat_width", "seat_depth", "seat_thickness",
                     "leg_thickness"):
            need(float(getattr(self, name)) > 0, f"{name} must be > 0")
        need(self.seat_thickness < self.seat_height - 0.05,
             "seat_thickness must leave at least 5 cm under the seat")
        need(self.leg_thickness <= min(self.seat_width, self.seat_depth) / 4,
             "leg_thickness must be at most a quarter of the seat width and depth")
        need((self.back_height is None) == (self.kind == "stool"),
             "back_height must be None for stools and only for stools")
        if self.back_height is not None:
            need(0.1 <= self.back_height <= 1.2, "back_height must be in [0.1, 1.2] m")
            need(0.0 <= self.back_tilt_deg <= 30.0, "back_tilt_deg must be in [0, 30]")
            need(self.back_thickness > 0, "back_thickness must be > 0")
        has_arms = self.kind in ("armchair", "sofa")
        need((self.armrest_height is not None) == has_arms,
             "armrest_height must be given for armchairs and sofas and None otherwise")
        if self.armrest_height is not None:
            need(0.05 < self.armrest_height < self.back_height - 0.05,
                 "armrest_height must be above 5 cm and 5 cm below the backrest top")
            need(self.armrest_width > 0, "armrest_width must be > 0")
        if self.stretcher_height is not None:
            need(0.05 < self.stretcher_height < self.seat_height - self.seat_thickness - 0.05,
                 "stretcher_height must lie between the floor and the seat, 5 cm clear")
        if self.kind == "straight":
            need(0.0 <= self.back_gap <= self.back_height - 0.12,
                 "back_gap must leave a back panel of at least 12 cm")
        if self.kind == "stool":
            need(self.leg_count in (3, 4), "stools have 3 or 4 legs")
            need(0.0 <= self.leg_splay_deg <= 15.0, "leg_splay_deg must be in [0, 15]")
        if self.kind == "sofa":
            need(self.cushions in (1, 2, 3), "cushions must be 1, 2 or 3")
            need(self.base in ("plinth", "legs"), "base must be 'plinth' or 'legs'")
            need(0.0 <= self.rounding <= 0.45 * min(self.seat_thickness, self.armrest_width,
                                                    self.back_thickness, 0.1),
                 "rounding must be below half the thinnest upholstered part (and 4.5 cm)")
            if self.base == "legs":
                need(0.03 <= self.base_clearance
                     <= self.seat_height - self.seat_thickness - 0.05,
                     "base_clearance must be >= 3 cm and leave 5 cm of base")

    @property
    def has_back(self) -> bool:
        return self.back_height is not None

    @property
    def has_armrests(self) -> bool:
        return self.armrest_height is not None

    @classmethod
    def for_kind(cls, kind: str, **overrides: object) -> ChairSpec:
        """Typical real furniture of ``kind`` (a dining chair, an office-style armchair, a
        two-cushion sofa, a counter stool), with any field overridden."""
        if kind not in _DEFAULTS:
            raise ValueError(f"unknown chair kind {kind!r}; expected one of {KINDS}")
        return cls(kind=kind, **{**_DEFAULTS[kind], **overrides})


_DEFAULTS: dict[str, dict[str, object]] = {
    # Dining chair: seat 45 cm high, 44 x 42 cm, back top ~90 cm from the floor.
    "straight": dict(seat_height=0.45, seat_width=0.44, seat_depth=0.42, seat_thickness=0.04,
                     back_height=0.45, back_tilt_deg=8.0, back_thickness=0.025,
                     armrest_height=None, armrest_width=0.0, leg_thickness=0.035),
    # Padded armchair: armrest tops ~66 cm from the floor.
    "armchair": dict(seat_height=0.44, seat_width=0.52, seat_depth=0.50, seat_thickness=0.07,
                     back_height=0.50, back_tilt_deg=10.0, back_thickness=0.06,
                     armrest_height=0.22, armrest_width=0.07, leg_thickness=0.045),
    # Sofa: 1.5 m of seat between 18 cm arms (1.86 m overall), 60 cm deep, seat 42 cm high.
    "sofa": dict(seat_height=0.42, seat_width=1.5, seat_depth=0.60, seat_thickness=0.14,
                 back_height=0.42, back_tilt_deg=12.0, back_thickness=0.20,
                 armrest_height=0.20, armrest_width=0.18, leg_thickness=0.05,
                 cushions=2, base="plinth", rounding=0.03),
    # Counter stool: seat 62 cm high, 35 cm across, footrest ring at 25 cm.
    "stool": dict(seat_height=0.62, seat_width=0.35, seat_depth=0.35, seat_thickness=0.04,
                  back_height=None, back_tilt_deg=0.0, back_thickness=0.0,
                  armrest_height=None, armrest_width=0.0, leg_thickness=0.03,
                  round_legs=True, leg_splay_deg=5.0, stretcher_height=0.25),
}


def random_chair_spec(rng: np.random.Generator, kind: str | None = None) -> ChairSpec:
    """A plausible random chair of ``kind`` (uniform over :data:`KINDS` when None), with ranges
    taken from real furniture (seat 0.40-0.49 m high for chairs and sofas, up to 0.78 m for
    bar stools; sofas 1.2-1.8 m between the arms, 0.55-0.68 m deep)."""
    if kind is None:
        kind = KINDS[int(rng.integers(len(KINDS)))]

    def u(lo: float, hi: float) -> float:
        return float(rng.uniform(lo, hi))

    if kind == "straight":
        back_height = u(0.35, 0.55)
        seat_height = u(0.43, 0.49)
        return ChairSpec(
            kind, seat_height=seat_height, seat_width=u(0.40, 0.50),
            seat_depth=u(0.38, 0.48), seat_thickness=u(0.03, 0.05), back_height=back_height,
            back_tilt_deg=u(3.0, 14.0), back_thickness=u(0.02, 0.04), armrest_height=None,
            armrest_width=0.0, leg_thickness=u(0.025, 0.045), round_legs=bool(rng.random() < 0.5),
            stretcher_height=u(0.12, 0.25) if rng.random() < 0.5 else None,
            back_gap=u(0.06, back_height - 0.2) if rng.random() < 0.5 else 0.0)
    if kind == "armchair":
        return ChairSpec(
            kind, seat_height=u(0.42, 0.48), seat_width=u(0.48, 0.58), seat_depth=u(0.45, 0.55),
            seat_thickness=u(0.05, 0.09), back_height=u(0.40, 0.60), back_tilt_deg=u(4.0, 16.0),
            back_thickness=u(0.04, 0.08), armrest_height=u(0.18, 0.26),
            armrest_width=u(0.05, 0.10), leg_thickness=u(0.035, 0.05),
            round_legs=bool(rng.random() < 0.5))
    if kind == "sofa":
        base = "legs" if rng.random() < 0.5 else "plinth"
        return ChairSpec(
            kind, seat_height=u(0.40, 0.46), seat_width=u(1.2, 1.8), seat_depth=u(0.55, 0.68),
            seat_thickness=u(0.10, 0.18), back_height=u(0.35, 0.50), back_tilt_deg=u(6.0, 18.0),
            back_thickness=u(0.15, 0.25), armrest_height=u(0.15, 0.25),
            armrest_width=u(0.12, 0.25), leg_thickness=u(0.04, 0.06),
            cushions=int(rng.integers(1, 4)), base=base,
            base_clearance=u(0.08, 0.15) if base == "legs" else 0.0, rounding=u(0.015, 0.04))
    if kind == "stool":
        seat_height = u(0.45, 0.78)
        width = u(0.30, 0.40)
        return ChairSpec(
            kind, seat_height=seat_height, seat_width=width,
            seat_depth=width if rng.random() < 0.7 else u(0.28, width),
            seat_thickness=u(0.03, 0.05), back_height=None, back_tilt_deg=0.0,
            back_thickness=0.0, armrest_height=None, armrest_width=0.0,
            leg_thickness=u(0.025, 0.04), round_legs=bool(rng.random() < 0.7),
            leg_count=3 if rng.random() < 0.3 else 4, leg_splay_deg=u(0.0, 8.0),
            stretcher_height=u(0.22, 0.35) * seat_height if seat_height > 0.55 else None)
    raise ValueError(f"unknown chair kind {kind!r}; expected one of {KINDS}")


# --------------------------------------------------------------------------------------------
# Primitives: (vertices (V, 3) float64, faces (F, 3) int64), closed and outward-oriented
# --------------------------------------------------------------------------------------------

_Mesh = tuple[np.ndarray, np.ndarray]

# trimesh.creation.box()'s corner signs and outward faces (vertex i has signs of bits 2, 1, 0).
_BOX_CORNERS = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=bool)
_BOX_FACES = np.array([[1, 3, 0], [4, 1, 0], [0, 3, 2], [2, 4, 0], [1, 7, 3], [5, 1, 4],
                       [5, 7, 1], [3, 7, 2], [6, 4, 2], [2, 7, 6], [6, 5, 4], [7, 5, 6]])


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    t = v[f]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def _oriented(v: np.ndarray, f: np.ndarray) -> _Mesh:
    f = np.asarray(f, dtype=np.int64)
    return v, (f if _signed_volume(v, f) > 0 else f[:, ::-1].copy())


def _box(lo: np.ndarray | tuple, hi: np.ndarray | tuple) -> _Mesh:
    """Axis-aligned box from its corners; corner coordinates are used bit-exactly, so boxes
    built from the same numbers share planes exactly (what the exact union needs)."""
    return np.where(_BOX_CORNERS, np.asarray(hi, float), np.asarray(lo, float)), _BOX_FACES.copy()


def _rounded_box(lo: np.ndarray | tuple, hi: np.ndarray | tuple, radius: float,
                 segments: int = 3) -> _Mesh:
    """Box with edges and corners rounded by ``radius`` (convex hull of eight sphere octants).
    Points on the flat faces take ``lo``/``hi`` exactly, so the flat faces lie on those planes."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    r = min(radius, 0.49 * float(np.min(hi - lo)))
    if r <= 1e-6:
        return _box(lo, hi)
    ang = np.linspace(0.0, np.pi / 2, segments + 1)
    th, ph = np.meshgrid(ang, ang, indexing="ij")
    d = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], -1).reshape(-1, 3)
    d[np.abs(d) < 1e-12] = 0.0
    d[np.abs(d - 1.0) < 1e-12] = 1.0
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    dirs = (signs[:, None, :] * d[None]).reshape(-1, 3)
    centre = np.where(np.repeat(signs, len(d), axis=0) > 0, hi - r, lo + r)
    pts = np.where(dirs == 1.0, hi, np.where(dirs == -1.0, lo, centre + r * dirs))
    hull = trimesh.convex.convex_hull(np.unique(pts, axis=0))
    return _oriented(np.asarray(hull.vertices, float), np.asarray(hull.faces))


def _prism(bottom_xz: tuple[float, float], top_xz: tuple[float, float], rx: float, rz: float,
           y0: float, y1: float, sections: int, phase: float = 0.0,
           top_scale: float = 1.0) -> _Mesh:
    """Prism (a cylinder for many ``sections``) with horizontal caps at exactly ``y0`` < ``y1``;
    the cap centres may differ (a leaning leg). ``rx``/``rz``: radii along X/Z (ellipse)."""
    th = phase + 2.0 * np.pi * np.arange(sections) / sections
    ring = np.stack([rx * np.cos(th), rz * np.sin(th)], axis=1)
    n = sections
    v = np.zeros((2 * n + 2, 3))
    v[:n, [0, 2]] = np.asarray(bottom_xz, float) + ring
    v[n:2 * n, [0, 2]] = np.asarray(top_xz, float) + top_scale * ring
    v[:n, 1], v[n:2 * n, 1] = y0, y1
    v[2 * n] = (bottom_xz[0], y0, bottom_xz[1])
    v[2 * n + 1] = (top_xz[0], y1, top_xz[1])
    k = np.arange(n)
    k1 = (k + 1) % n
    f = np.concatenate([
        np.stack([k, n + k1, k1], 1), np.stack([k, n + k, n + k1], 1),
        np.stack([np.full(n, 2 * n), k, k1], 1),
        np.stack([np.full(n, 2 * n + 1), n + k1, n + k], 1),
    ])
    return _oriented(v, f)


def _cylinder(p0: np.ndarray, p1: np.ndarray, radius: float, sections: int = 10) -> _Mesh:
    m = trimesh.creation.cylinder(radius=radius, segment=np.stack([p0, p1]), sections=sections)
    return _oriented(np.asarray(m.vertices, float), np.asarray(m.faces))


def _rot_x_back(tilt: float) -> np.ndarray:
    """Rotation taking local +Y to (0, cos, -sin): leans a part backwards (towards -Z)."""
    c, s = math.cos(tilt), math.sin(tilt)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])


def _union(parts: list[tuple[_Mesh, int]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact boolean union of closed parts → (vertices (V, 3), faces (F, 3), labels (F,) int8).

    Labels ride through each union as MeshLab per-face quality, so every output face keeps the
    label of the part face it came from.
    """
    import pymeshlab

    (v, f), label = parts[0]
    q = np.full(len(f), float(label))
    for (pv, pf), plabel in parts[1:]:
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(v, np.asarray(f, np.int32), f_scalar_array=q))
        ms.add_mesh(pymeshlab.Mesh(pv, np.asarray(pf, np.int32),
                                   f_scalar_array=np.full(len(pf), float(plabel))))
        ms.generate_boolean_union(first_mesh=0, second_mesh=1, transfer_face_quality=True)
        m = ms.current_mesh()
        v, f, q = m.vertex_matrix(), _first_corner_lowest(m.face_matrix()), m.face_scalar_array()
    return (np.ascontiguousarray(v, np.float64), np.ascontiguousarray(f, np.int64),
            np.rint(q).astype(np.int8))


def _first_corner_lowest(faces: np.ndarray) -> np.ndarray:
    """(F, 3) faces each rotated to start at its lowest vertex index, the winding kept.

    pymeshlab's union gives the same vertices, faces and face order on every call but starts a
    few faces of a chair at another corner from call to call (very likely an ordering by memory
    address inside the library). Everything downstream that reads corners in order (surface
    samples from barycentric weights, normals to the last bit) then differs, and a
    rejection-sampled draw can flip; with one corner order per face a seed builds one mesh."""
    f = np.asarray(faces)
    shift = np.argmin(f, axis=1)[:, None]
    return np.take_along_axis(f, (shift + np.arange(3)) % 3, axis=1)


def _solid_problems(v: np.ndarray, f: np.ndarray) -> list[str]:
    """Why ``(v, f)`` is not one closed, consistently outward-oriented manifold (empty: it is)."""
    mesh = trimesh.Trimesh(v, f, process=False)
    problems = []
    if not mesh.is_watertight:
        problems.append("not watertight")
    if not mesh.is_winding_consistent:
        problems.append("inconsistent winding")
    elif mesh.volume <= 0:
        problems.append("inward-facing normals")
    n_comp = len(trimesh.graph.connected_components(mesh.face_adjacency,
                                                    nodes=np.arange(len(f)), min_len=1))
    if n_comp != 1:
        problems.append(f"{n_comp} connected components")
    return problems


# --------------------------------------------------------------------------------------------
# Chair builders: each returns [(part mesh, label)], seat first
# --------------------------------------------------------------------------------------------

def _back_parts(s: ChairSpec, x_half: float, bottom_y: float, rounding: float = 0.0,
                gap: float = 0.0, post_width: float = 0.0) -> list[_Mesh]:
    """Backrest leaning back by ``back_tilt_deg`` with its front face through the seat's rear
    top edge (z = -D/2, y = H), from ``bottom_y`` up to exactly ``H + back_height``.

    With ``gap`` > 0 it is an open frame: two side posts (slightly thicker than the panel, so
    their faces never nearly coincide with the panel's) and a panel starting ``gap`` above the
    seat.
    """
    h, d, bt = s.seat_height, s.seat_depth, s.back_thickness
    tilt = math.radians(s.back_tilt_deg)
    rot, pivot = _rot_x_back(tilt), np.array([0.0, h, -d / 2])
    u0 = (h - bottom_y) / math.cos(tilt)

    def build(length: float) -> list[_Mesh]:
        # Local frame: x across, y up the backrest, z out of its front face (front face z = 0).
        if gap <= 0:
            boxes = [((-x_half, -u0, -bt), (x_half, length, 0.0))]
        else:
            g, pw = gap / math.cos(tilt), post_width
            boxes = [((-x_half + pw / 2, g, -bt), (x_half - pw / 2, length, 0.0))]
            for sx in (-1.0, 1.0):
                xs = sorted((sx * x_half, sx * (x_half - pw)))
                boxes.append(((xs[0], -u0, -bt - 0.003), (xs[1], length - 0.01, 0.003)))
        out = []
        for lo, hi in boxes:
            v, f = _rounded_box(lo, hi, rounding)
            out.append((v @ rot.T + pivot, f))
        return out

    target = h + float(s.back_height)
    length = float(s.back_height) / math.cos(tilt)
    meshes = build(length)
    # One correction makes the top exact for rounded boxes too: the top moves along the tilted
    # axis, so its height changes by Δlength·cos(tilt).
    top = max(float(v[:, 1].max()) for v, _ in meshes)
    if abs(top - target) > 1e-12:
        meshes = build(length + (target - top) / math.cos(tilt))
    return meshes


def _chair_legs(s: ChairSpec, x_half: float, z_front: float, z_rear: float) -> list[_Mesh]:
    """Four vertical legs centred at (±x_half, z_front/z_rear), floor to mid-seat."""
    top, lt = s.seat_height - s.seat_thickness / 2, s.leg_thickness
    legs = []
    for x in (-x_half, x_half):
        for z in (z_front, z_rear):
            if s.round_legs:
                legs.append(_prism((x, z), (x, z), lt / 2, lt / 2, 0.0, top, 12))
            else:
                legs.append(_box((x - lt / 2, 0.0, z - lt / 2), (x + lt / 2, top, z + lt / 2)))
    return legs


def _seat_and_legs(s: ChairSpec) -> list[tuple[_Mesh, int]]:
    h, w, d, t, lt = (s.seat_height, s.seat_width, s.seat_depth, s.seat_thickness,
                      s.leg_thickness)
    tilt = math.radians(s.back_tilt_deg)
    # The seat runs on behind the backrest's front face into a solid backrest, so the two cross
    # transversally instead of meeting along an edge. An open back's posts stand 3 mm proud of
    # that face, so there the seat can end on it (else it would show through the gap).
    e = 0.0 if s.back_gap > 0 else s.back_thickness / (2 * math.cos(tilt))
    parts: list[tuple[_Mesh, int]] = [(_box((-w / 2, h - t, -d / 2 - e), (w / 2, h, d / 2)), SEAT)]
    # Rear legs stay 1.5 cm clear of the backrest's lower front edge (+3 mm posts).
    rear_inset = 0.018 + (t + 0.015) * math.tan(tilt)
    x_c, z_f, z_r = w / 2 - 0.01 - lt / 2, d / 2 - 0.01 - lt / 2, -d / 2 + rear_inset + lt / 2
    parts += [(leg, BASE) for leg in _chair_legs(s, x_c, z_f, z_r)]
    if s.stretcher_height is not None:
        y, a = s.stretcher_height, 0.3 * lt
        for x in (-x_c, x_c):
            parts.append((_box((x - a, y - a, z_r), (x + a, y + a, z_f)), BASE))
    return parts


def _build_straight(s: ChairSpec) -> list[tuple[_Mesh, int]]:
    parts = _seat_and_legs(s)
    back = _back_parts(s, s.seat_width / 2, s.seat_height - s.seat_thickness - 0.015,
                       gap=s.back_gap, post_width=s.leg_thickness)
    return parts + [(m, BACK) for m in back]


def _build_armchair(s: ChairSpec) -> list[tuple[_Mesh, int]]:
    h, w, d, t = s.seat_height, s.seat_width, s.seat_depth, s.seat_thickness
    ah, aw, bt = float(s.armrest_height), s.armrest_width, s.back_thickness
    tilt = math.radians(s.back_tilt_deg)
    parts = _seat_and_legs(s)
    parts += [(m, BACK) for m in _back_parts(s, w / 2 + aw, h - t - 0.015)]
    at = float(np.clip(0.2 * ah, 0.025, 0.05))
    # The arm's rear end sits mid-way through the (tilted) backrest at the arm's height.
    z_rear = -d / 2 - (ah - at / 2) * math.tan(tilt) - bt / (2 * math.cos(tilt))
    pw = min(aw, s.leg_thickness)
    for label, (x0, x1), (p0, p1) in (
            (LEFT_ARMREST, (w / 2, w / 2 + aw), (w / 2, w / 2 + pw)),
            (RIGHT_ARMREST, (-w / 2 - aw, -w / 2), (-w / 2 - pw, -w / 2))):
        parts.append((_box((x0, h + ah - at, z_rear), (x1, h + ah, d / 2)), label))
        # Front post: flush against the seat's side face (an exactly shared plane).
        parts.append((_box((p0, h - t, d / 2 - 0.03 - pw), (p1, h + ah - at / 2, d / 2 - 0.03)),
                      label))
    return parts


def _build_sofa(s: ChairSpec) -> list[tuple[_Mesh, int]]:
    h, w, d, ct = s.seat_height, s.seat_width, s.seat_depth, s.seat_thickness
    ah, aw, bt, r = float(s.armrest_height), s.armrest_width, s.back_thickness, s.rounding
    yb = s.base_clearance if s.base == "legs" else 0.0
    z_back = -d / 2 - 0.75 * bt
    parts: list[tuple[_Mesh, int]] = []
    # Cushions reach into the arms and the back beyond their rounding radius, so the visible
    # seat top stays flat right up to them; neighbours overlap by less than the radius, leaving
    # a shallow seam. The odd factors keep the rounded facets of neighbouring parts from
    # meeting exactly (two mirrored facet columns on one line make the union non-manifold).
    out_ext, seam_ext = max(1.3 * r, 0.01), max(0.37 * r, 0.004)
    seams = -w / 2 + w * np.arange(s.cushions + 1) / s.cushions
    for i in range(s.cushions):
        x0 = seams[i] - (out_ext if i == 0 else seam_ext)
        x1 = seams[i + 1] + (out_ext if i == s.cushions - 1 else seam_ext)
        parts.append((_rounded_box((x0, h - ct, -d / 2 - out_ext), (x1, h, d / 2), r), SEAT))
    inset = r + 0.01   # the base ends inside the arms' flat faces, clear of their rounding
    parts.append((_box((-w / 2 - aw + inset, yb, z_back + inset),
                       (w / 2 + aw - inset, h - ct + 0.01, d / 2 - 0.02)), BASE))
    parts.append((_rounded_box((w / 2, yb, z_back), (w / 2 + aw, h + ah, d / 2 + 0.025), r),
                  LEFT_ARMREST))
    parts.append((_rounded_box((-w / 2 - aw, yb, z_back), (-w / 2, h + ah, d / 2 + 0.025), r),
                  RIGHT_ARMREST))
    back_bottom = max(yb + 0.02, h - ct - 0.05)
    # The back ends half-way into the arms, crossing their flat tops, not their rounding.
    parts += [(m, BACK) for m in _back_parts(s, w / 2 + aw / 2, back_bottom, rounding=r)]
    if s.base == "legs":
        lr = s.leg_thickness / 2
        # Under the base's corners (and its middle on long sofas), tops inside the base.
        xl = w / 2 + aw - inset - 0.01 - lr
        for x in [xl, -xl] + ([0.0] if w > 1.6 else []):
            for z in (d / 2 - 0.03 - lr, z_back + inset + 0.01 + lr):
                parts.append((_prism((x, z), (x, z), lr, lr, 0.0, yb + 0.02, 12), BASE))
    return parts


def _build_stool(s: ChairSpec) -> list[tuple[_Mesh, int]]:
    h, w, d, t, lt = (s.seat_height, s.seat_width, s.seat_depth, s.seat_thickness,
                      s.leg_thickness)
    parts: list[tuple[_Mesh, int]] = [
        (_prism((0.0, 0.0), (0.0, 0.0), w / 2, d / 2, h - t, h, 32), SEAT)]
    top_y = h - t / 2
    n = s.leg_count
    # Four legs on the diagonals; three legs with one at the front.
    phi = 2 * np.pi * np.arange(n) / n + (np.pi / 4 if n == 4 else np.pi / 2)
    radial = np.stack([np.cos(phi), np.sin(phi)], 1)
    tops = 0.62 * radial * np.array([w / 2, d / 2])
    bottoms = tops + radial * top_y * math.tan(math.radians(s.leg_splay_deg))
    sections, rad, phase = (12, lt / 2, 0.0) if s.round_legs else (4, lt / math.sqrt(2), np.pi / 4)
    for b, tp in zip(bottoms, tops, strict=True):
        parts.append((_prism(tuple(b), tuple(tp), rad, rad, 0.0, top_y, sections, phase), BASE))
    if s.stretcher_height is not None:
        a = (top_y - s.stretcher_height) / top_y
        ring = tops + (bottoms - tops) * a
        ring3 = np.column_stack([ring[:, 0], np.full(n, s.stretcher_height), ring[:, 1]])
        for i in range(n):
            parts.append((_cylinder(ring3[i], ring3[(i + 1) % n], 0.3 * lt), BASE))
    return parts


_BUILDERS = {"straight": _build_straight, "armchair": _build_armchair, "sofa": _build_sofa,
             "stool": _build_stool}


# --------------------------------------------------------------------------------------------
# Landmarks
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class ContactCandidate:
    """A point a palm can be placed on: ``part`` (one of :data:`PART_NAMES`), a ``name``,
    ``point`` (3,) on the surface (metres) and the outward unit ``normal`` (3,) of the face there.

    Names: ``seat_front_left``, ``seat_front_right`` (front corners), ``seat_front``,
    ``seat_left``, ``seat_right`` (side midpoints), all 5 cm in from the edges;
    ``{left,right}_armrest_top`` (the palm target) and ``{left,right}_armrest_front`` (5 cm from
    the armrest's front end); ``back_top``, ``back_top_left``, ``back_top_right`` (5 cm in from
    the backrest's ends, at most half a seat width from the centre) and ``back_front``.
    Candidates whose surface cannot be found are left out.
    """

    part: str
    name: str
    point: np.ndarray
    normal: np.ndarray


@dataclass(frozen=True, eq=False)
class ChairLandmarks:
    """Geometric landmarks of a chair, metres, in the frame of the mesh they were measured on.

    Points are (3,) float64. ``seat_height`` is the seat top above the floor, ``seat_width``
    (X) and ``seat_depth`` (Z) the extent of the usable seat top (between the armrests, up to
    the backrest); these scalars are frame-independent. ``seat_center`` / ``seat_front`` lie at
    seat-top height at the centre / front-edge midpoint of that extent; ``seat_normal`` is the
    seat plane's upward normal. ``left_armrest`` / ``right_armrest`` (the sitter's left is +X)
    are palm targets on the armrest tops, ``back_top`` the backrest's highest point above the
    seat centre line and ``back_front`` a point on the backrest's front face at roughly shoulder
    height; each None when the part is absent. ``contacts`` lists palm candidates per part.
    """

    seat_height: float
    seat_center: np.ndarray
    seat_front: np.ndarray
    seat_normal: np.ndarray
    seat_width: float
    seat_depth: float
    left_armrest: np.ndarray | None
    right_armrest: np.ndarray | None
    back_top: np.ndarray | None
    back_front: np.ndarray | None
    contacts: tuple[ContactCandidate, ...] = field(default_factory=tuple)

    def contacts_for(self, part: str) -> list[ContactCandidate]:
        """The contact candidates on ``part`` (one of :data:`PART_NAMES`)."""
        if part not in PART_NAMES:
            raise ValueError(f"unknown part {part!r}; expected one of {PART_NAMES}")
        return [c for c in self.contacts if c.part == part]

    def transformed(self, transform: np.ndarray) -> ChairLandmarks:
        """The same landmarks with points and normals mapped by a rigid ``(4, 4)`` transform
        (new frame from current frame); the scalar measurements are unchanged."""
        transform = np.asarray(transform, dtype=np.float64)
        rot = transform[:3, :3]

        def pt(p: np.ndarray | None) -> np.ndarray | None:
            return None if p is None else apply_transform(transform, p[None])[0]

        return dataclasses.replace(
            self, seat_center=pt(self.seat_center), seat_front=pt(self.seat_front),
            seat_normal=rot @ self.seat_normal, left_armrest=pt(self.left_armrest),
            right_armrest=pt(self.right_armrest), back_top=pt(self.back_top),
            back_front=pt(self.back_front),
            contacts=tuple(dataclasses.replace(c, point=pt(c.point), normal=rot @ c.normal)
                           for c in self.contacts))


class _Caster:
    """Ray queries on a triangle mesh (open3d ``RaycastingScene``) with float64 face normals."""

    def __init__(self, v: np.ndarray, f: np.ndarray) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                                 o3d.core.Tensor(f.astype(np.uint32)))
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        self.normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    def _rays(self, origins: np.ndarray, direction: np.ndarray) -> object:
        rays = np.empty((len(origins), 6), np.float32)
        rays[:, :3], rays[:, 3:] = origins, direction
        return self._o3d.core.Tensor(rays)

    def all_hits(self, origins: np.ndarray, direction: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every hit of rays from ``(N, 3)`` origins along one unit direction →
        (ray index (H,), distance (H,), face index (H,))."""
        ans = self.scene.list_intersections(self._rays(origins, direction))
        return (ans["ray_ids"].numpy().astype(np.int64), ans["t_hit"].numpy().astype(np.float64),
                ans["primitive_ids"].numpy().astype(np.int64))

    def down_hits(self, origins: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every hit of vertical rays cast down from ``(N, 3)`` origins → ray index (H,),
        height y (H,), face normal (H, 3) and whether the surface is exposed (H,) bool.

        Exposed means the winding number just above the hit is zero: the sum, over the hits
        above it on its ray, of +1 for entering (upward-facing) and -1 for leaving faces. It is
        always true for a proper closed mesh; on ShapeNet-style meshes made of overlapping closed
        parts it rejects part faces buried inside other parts (a seat board's top inside the
        backrest, a sofa frame under its cushions).
        """
        ray, t, face = self.all_hits(origins, _DOWN)
        order = np.lexsort((t, ray))
        ray, t, face = ray[order], t[order], face[order]
        n = self.normals[face]
        sign = np.where(n[:, 1] > 0, 1, -1)
        csum = np.cumsum(sign)
        start = np.searchsorted(ray, ray, side="left")
        above = csum - sign - (csum[start] - sign[start])
        return ray, origins[ray, 1] - t, n, above <= 0

    def first_hits(self, origins: np.ndarray, direction: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit per ray → (distance (N,), inf on a miss; face index (N,), -1 on a miss)."""
        ans = self.scene.cast_rays(self._rays(origins, direction))
        t = ans["t_hit"].numpy().astype(np.float64)
        face = ans["primitive_ids"].numpy().astype(np.int64)
        face[~np.isfinite(t)] = -1
        return t, face


_DOWN = np.array([0.0, -1.0, 0.0])
_BACKWARD = np.array([0.0, 0.0, -1.0])
_UP_COS = 0.9          # faces within ~26° of horizontal count as tops
_SEAT_RANGE = (0.15, 1.0)
_INSET = 0.05          # palm centre inset from an edge


def _largest_component(mask: np.ndarray, weight: np.ndarray, closing: int = 0) -> np.ndarray:
    """The 8-connected component of ``mask`` (optionally closed by ``closing`` cells first, to
    bridge cushion seams) holding the most ``weight`` cells; returned intersected with ``mask``."""
    grown = mask
    if closing:
        grown = ndimage.binary_closing(np.pad(mask, closing), np.ones((3, 3), bool),
                                       iterations=closing)[closing:-closing, closing:-closing]
    lab, n = ndimage.label(grown, np.ones((3, 3), bool))
    if n == 0:
        return np.zeros_like(mask)
    score = ndimage.sum_labels(weight & mask, lab, index=np.arange(1, n + 1))
    return (lab == 1 + int(np.argmax(score))) & mask


def _mode_height(y: np.ndarray, lo: float, hi: float) -> float | None:
    """Centre of the most populated 1 cm height bin (smoothed over ±1 bin), or None."""
    if len(y) == 0:
        return None
    edges = np.arange(lo, hi + 0.01, 0.01)
    hist, _ = np.histogram(y, edges)
    smooth = np.convolve(hist, np.ones(3), mode="same")
    return float(edges[int(np.argmax(smooth))] + 0.005)


def chair_landmarks(vertices: np.ndarray, faces: np.ndarray, *,
                    resolution: float = 0.005) -> ChairLandmarks:
    """Measure :class:`ChairLandmarks` of any chair-like mesh in the chair frame by ray casting.

    ``vertices`` (V, 3) metres, chair frame (+Y up, floor y = 0, facing +Z); ``faces`` (F, 3)
    consistently oriented (a globally inward-oriented mesh is flipped; repair non-manifold
    ShapeNet meshes first). ``resolution``: spacing of the vertical ray grid, metres.

    Method: a grid of vertical rays collects every exposed upward-facing surface (all hits, not
    just the first, so a seat under an overhanging armrest still counts; faces buried inside
    other parts of a ShapeNet-style part soup are rejected by the winding number along the
    ray). The seat is the most extensive such surface between 0.15 and 1.0 m: a plane is fitted
    to its flat part and its connected region (closed over cushion seams) gives the extent, each
    edge refined by a fine line of rays. Armrests are the dominant upward surfaces 6-50 cm above
    the seat, beside it (|x - cx| > 0.3 W) and over its depth; the backrest is whatever rises
    more than 12 cm above the seat behind its rear edge (its top refined on a fine line of rays),
    and a horizontal ray along the centre line finds its front face. Candidate points are
    snapped onto the surface by ray casts and carry the hit face's normal.

    Accuracy: heights of flat tops are exact to float32 ray precision (< 0.1 mm); a sloping
    backrest top to within ~0.1 mm; seat extents of sharp-edged seats to ~0.1 mm. A rounded
    edge counts as seat until it tilts past 60° or drops 2.5 cm, so rounded seats measure up to
    ~0.15 x the edge radius short per side (≤ 6 mm for the generated sofas).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"expected vertices (V, 3) and faces (F >= 1, 3); got {v.shape} and "
                         f"{f.shape}")
    if f.min() < 0 or f.max() >= len(v) or not np.all(np.isfinite(v)):
        raise ValueError("faces index missing vertices or vertices are not finite")
    span = v.max(0) - v.min(0)
    if max(span[0], span[2]) > 5.0:
        raise ValueError(f"mesh spans {span[0]:.3g} x {span[2]:.3g} horizontally; expected a "
                         "chair in metres")
    if _signed_volume(v, f) < 0:
        f = f[:, ::-1]
    caster = _Caster(v, f)
    res = float(resolution)
    lo, hi = v.min(0), v.max(0)
    xs = lo[0] - 2 * res + res * (np.arange(int(np.ceil((hi[0] - lo[0]) / res)) + 4) + 0.5)
    zs = lo[2] - 2 * res + res * (np.arange(int(np.ceil((hi[2] - lo[2]) / res)) + 4) + 0.5)
    nx, nz = len(xs), len(zs)
    top = hi[1] + 0.1
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    origins = np.column_stack([gx.ravel(), np.full(gx.size, top), gz.ravel()])
    ray, hy, hn, exposed = caster.down_hits(origins)
    hix, hiz = ray // nz, ray % nz
    hx, hz = xs[hix], zs[hiz]
    up = exposed & (hn[:, 1] > _UP_COS)
    first = np.full(nx * nz, -np.inf)
    np.maximum.at(first, ray, hy)
    first = first.reshape(nx, nz)

    def cells(sel: np.ndarray) -> np.ndarray:
        m = np.zeros((nx, nz), bool)
        m[hix[sel], hiz[sel]] = True
        return m

    def snap(x: float, z: float, y_ref: float | None, tol: float = 0.03
             ) -> tuple[np.ndarray, np.ndarray] | None:
        """Surface point below (x, z): the upward hit nearest ``y_ref``, or the top hit."""
        _, y, n, vis = caster.down_hits(np.array([[x, top, z]]))
        if len(y) == 0:
            return None
        if y_ref is None:
            i = int(np.argmax(y))
        else:
            ok = vis & (n[:, 1] > 0.3) & (np.abs(y - y_ref) <= tol)
            if not ok.any():
                return None
            i = int(np.flatnonzero(ok)[np.argmin(np.abs(y[ok] - y_ref))])
        return np.array([x, y[i], z]), n[i].copy()

    # ---- seat: dominant upward surface, plane fit, connected region -----------------------
    sel = up & (hy > _SEAT_RANGE[0]) & (hy < _SEAT_RANGE[1])
    h0 = _mode_height(hy[sel], *_SEAT_RANGE)
    if h0 is None:
        raise ValueError(f"no upward-facing surface between {_SEAT_RANGE[0]} and "
                         f"{_SEAT_RANGE[1]} m: is this a chair in the chair frame (metres, +Y "
                         "up, floor at y = 0)?")
    seed = sel & (np.abs(hy - h0) <= 0.015)
    region = _largest_component(cells(seed), cells(seed))
    in_region = region[hix, hiz]
    plane = np.array([0.0, 0.0, h0])
    fit = seed & in_region
    close_cells = max(1, round(0.02 / res))
    for _ in range(3):
        if fit.sum() >= 3:
            a_mat = np.column_stack([hx[fit], hz[fit], np.ones(fit.sum())])
            plane = np.linalg.lstsq(a_mat, hy[fit], rcond=None)[0]
        resid = hy - (plane[0] * hx + plane[1] * hz + plane[2])
        # Growing the region accepts steeper facets than the seed (a rounded front edge still
        # counts as seat until it has dropped 2.5 cm); the plane is fitted to the flat part.
        near = exposed & (hn[:, 1] > 0.5) & (resid >= -0.025) & (resid <= 0.015)
        region = _largest_component(cells(near), cells(near & up & (np.abs(resid) <= 0.003)),
                                    closing=close_cells)
        in_region = region[hix, hiz]
        fit = up & near & in_region & (np.abs(resid) <= 0.003)
    ix, iz = np.nonzero(region)

    def on_seat(px: np.ndarray, pz: np.ndarray) -> np.ndarray:
        r, y, n, vis = caster.down_hits(np.column_stack([px, np.full(len(px), top), pz]))
        dy = y - (plane[0] * px[r] + plane[1] * pz[r] + plane[2])
        ok = vis & (n[:, 1] > 0.5) & (dy >= -0.025) & (dy <= 0.015)
        return np.bincount(r[ok], minlength=len(px)) > 0

    def edge(k: int, axis: int, sign: float) -> float:
        """Sub-cell edge of the seat beyond region cell k, along ``axis`` (0: x, 1: z)."""
        p0 = np.array([xs[ix[k]], zs[iz[k]]])
        steps = sign * np.linspace(0.0, res, 41)
        pts = np.repeat(p0[None], len(steps), axis=0)
        pts[:, axis] += steps
        inside = on_seat(pts[:, 0], pts[:, 1])
        n_in = len(steps) if inside.all() else int(np.argmin(inside))
        if n_in == 0:   # the cell centre itself is off the seat: keep the cell estimate
            return float(p0[axis] + sign * res / 2)
        return float(p0[axis] + sign * res * (n_in - 0.5) / (len(steps) - 1))

    def outer_edge(on_edge: np.ndarray, other: np.ndarray, axis: int, sign: float) -> float:
        """Refine at a few cells spread along the extreme row/column (the middle, where a round
        seat bulges, and either side of it, in case the middle is a cushion seam); keep the
        outermost."""
        k = np.flatnonzero(on_edge)
        k = k[np.argsort(other[k])]
        picks = np.unique(k[(np.array([0.25, 0.5, 0.75]) * (len(k) - 1)).round().astype(int)])
        return sign * max(sign * edge(int(j), axis, sign) for j in picks)

    x0 = outer_edge(ix == ix.min(), iz, 0, -1.0)
    x1 = outer_edge(ix == ix.max(), iz, 0, 1.0)
    z0 = outer_edge(iz == iz.min(), ix, 1, -1.0)
    z1 = outer_edge(iz == iz.max(), ix, 1, 1.0)
    cx, cz, width, depth = (x0 + x1) / 2, (z0 + z1) / 2, x1 - x0, z1 - z0

    def seat_y(x: float, z: float) -> float:
        return float(plane[0] * x + plane[1] * z + plane[2])

    seat_h = seat_y(cx, cz)
    seat_normal = np.array([-plane[0], 1.0, -plane[1]])
    seat_normal /= np.linalg.norm(seat_normal)
    contacts: list[ContactCandidate] = []

    def snap_seat(x: float, z: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Like ``snap`` on the seat, sliding sideways off a cushion seam if it lands in one."""
        for dx in (0.0, 0.02, -0.02, 0.04, -0.04):
            hit = snap(x + dx, z, seat_y(x + dx, z))
            if hit is not None and hit[1] @ seat_normal > 0.95:
                return hit
        return snap(x, z, seat_y(x, z))

    def add(part: int, name: str, hit: tuple[np.ndarray, np.ndarray] | None) -> None:
        if hit is not None:
            contacts.append(ContactCandidate(PART_NAMES[part], name, hit[0], hit[1]))

    # Seat corners: the region cells furthest towards front-left / front-right, inset inwards.
    rx, rz = xs[ix], zs[iz]
    for name, sx in (("seat_front_left", 1.0), ("seat_front_right", -1.0)):
        k = int(np.argmax(sx * (rx - cx) / width + (rz - cz) / depth))
        px = rx[k] - sx * min(_INSET, 0.2 * width)
        pz = rz[k] - min(_INSET, 0.2 * depth)
        add(SEAT, name, snap_seat(px, pz))
    inset_d, inset_w = min(_INSET, 0.2 * depth), min(_INSET, 0.2 * width)
    add(SEAT, "seat_front", snap_seat(cx, z1 - inset_d))
    row = region[:, int(np.argmin(np.abs(zs - cz)))]
    if row.any():
        for name, x in (("seat_left", xs[row].max() - inset_w), ("seat_right",
                                                                 xs[row].min() + inset_w)):
            add(SEAT, name, snap_seat(x, cz))

    # ---- armrests: dominant upward surfaces beside the seat, over its depth -----------------
    band = up & (hy >= seat_h + 0.06) & (hy <= seat_h + 0.5)
    window = (hz >= z0 + 0.1 * depth) & (hz <= z1 + 0.05)
    armrests: dict[int, np.ndarray | None] = {}
    for label, sx in ((LEFT_ARMREST, 1.0), (RIGHT_ARMREST, -1.0)):
        armrests[label] = None
        side = band & (sx * (hx - cx) > 0.3 * width)
        h_arm = _mode_height(hy[side & window], seat_h + 0.06, seat_h + 0.5)
        if h_arm is None:
            continue
        at_h = side & (np.abs(hy - h_arm) <= 0.015)
        comp = _largest_component(cells(at_h), cells(at_h & window))
        in_comp = at_h & comp[hix, hiz]
        over = in_comp & window
        if over.sum() * res * res < 0.002:   # less than ~20 cm² of top: a rail, not an armrest
            continue
        h_arm = float(np.median(hy[over]))
        mid = over & (hz >= z0) & (hz <= z1)
        mid = mid if mid.any() else over
        px, pz = float(np.median(hx[mid])), float((hz[mid].min() + hz[mid].max()) / 2)
        hit = snap(px, pz, h_arm, tol=0.02)
        if hit is None:   # e.g. a slotted armrest: fall back to the nearest measured top
            k = np.flatnonzero(mid)[np.argmin(np.hypot(hx[mid] - px, hz[mid] - pz))]
            hit = (np.array([hx[k], hy[k], hz[k]]), hn[k].copy())
        armrests[label] = hit[0]
        name = PART_NAMES[label]
        add(label, f"{name}_top", hit)
        zf = float(hz[in_comp].max()) - _INSET
        add(label, f"{name}_front", snap(px, zf, h_arm, tol=0.02))

    # ---- backrest: what rises > 12 cm above the seat behind its rear edge -------------------
    back_top = back_front = None
    zone_z = (zs <= z0 + 0.05) & (zs >= z0 - 0.8)
    zone_x = np.abs(xs - cx) <= 0.4 * width
    zone_first = np.where(zone_z[None, :], first, -np.inf)
    col_max = zone_first.max(axis=1)
    rising = col_max > seat_h + 0.12
    if (rising & zone_x).any():
        ic = int(np.argmin(np.abs(xs - cx)))
        x_top = cx
        if not rising[ic]:
            cand = np.flatnonzero(rising & zone_x)
            ic = int(cand[np.argmin(np.abs(xs[cand] - cx))])
            x_top = float(xs[ic])
        zt = float(zs[int(np.argmax(zone_first[ic]))])
        # Refine the top on a fine line of rays: the top face may slope (a tilted backrest).
        fine_z = zt + np.linspace(-res, res, 21)
        tt, fc = caster.first_hits(
            np.column_stack([np.full(21, x_top), np.full(21, top), fine_z]), _DOWN)
        k = int(np.argmin(tt))
        if np.isfinite(tt[k]):
            back_top = np.array([x_top, top - tt[k], fine_z[k]])
            add(BACK, "back_top", (back_top, caster.normals[fc[k]].copy()))
        else:
            back_top = np.array([xs[ic], col_max[ic], zt])
        # Top corners: the contiguous run of columns reaching near the top, inset, capped at
        # the seat's width (a sofa back also spans the arms).
        high = col_max >= back_top[1] - 0.05
        lab, _ = ndimage.label(high)
        run = np.flatnonzero(lab == lab[ic]) if high[ic] else np.array([ic])
        for name, x in (("back_top_left", min(xs[run].max() - _INSET, cx + width / 2 - _INSET)),
                        ("back_top_right", max(xs[run].min() + _INSET, cx - width / 2 + _INSET))):
            j = int(np.argmin(np.abs(xs - x)))
            add(BACK, name, snap(x, float(zs[int(np.argmax(zone_first[j]))]), None))
        # Front face at about shoulder height (0.45 m above the seat, lower on short backs):
        # horizontal rays along the centre line; gaps in an open back are skipped.
        y_q = seat_h + min(0.45, 0.8 * (back_top[1] - seat_h))
        ys = np.arange(seat_h + 0.08, back_top[1] - 0.02, 0.01)
        if len(ys):
            org = np.column_stack([np.full(len(ys), cx), ys, np.full(len(ys), hi[2] + 0.1)])
            tt, fc = caster.first_hits(org, _BACKWARD)
            zh = org[:, 2] - tt
            ok = np.isfinite(tt) & (zh <= z0 + 0.05)
            ok[ok] &= caster.normals[fc[ok], 2] > 0.3
            if ok.any():
                k = int(np.flatnonzero(ok)[np.argmin(np.abs(ys[ok] - y_q))])
                back_front = np.array([cx, ys[k], zh[k]])
                add(BACK, "back_front", (back_front, caster.normals[fc[k]].copy()))

    return ChairLandmarks(
        seat_height=seat_h, seat_center=np.array([cx, seat_h, cz]),
        seat_front=np.array([cx, seat_y(cx, z1), z1]), seat_normal=seat_normal,
        seat_width=float(width), seat_depth=float(depth), left_armrest=armrests[LEFT_ARMREST],
        right_armrest=armrests[RIGHT_ARMREST], back_top=back_top, back_front=back_front,
        contacts=tuple(contacts))


# --------------------------------------------------------------------------------------------
# Chairs
# --------------------------------------------------------------------------------------------

@dataclass(eq=False)
class Chair:
    """One closed, outward-oriented, manifold triangle mesh in the chair frame (metres, +Y up,
    floor y = 0, facing +Z) with semantic parts and landmarks.

    ``vertices`` (V, 3) float64; ``faces`` (F, 3) int64; ``face_parts`` (F,) int8 indices into
    :data:`PART_NAMES` (-1: unknown, e.g. a loaded mesh); ``landmarks`` measured on this mesh in
    this frame; ``spec`` the
    parameters it was generated from (None for a loaded mesh).
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_parts: np.ndarray
    landmarks: ChairLandmarks
    spec: ChairSpec | None = None

    def part_faces(self, part: str) -> np.ndarray:
        """Indices (K,) of the faces labelled ``part``."""
        return np.flatnonzero(self.face_parts == PART_NAMES.index(part))


def make_chair(spec: ChairSpec) -> Chair:
    """Build the chair described by ``spec`` as one watertight labelled mesh (see module doc)."""
    v, f, labels = _union(_BUILDERS[spec.kind](spec))
    problems = _solid_problems(v, f)
    if problems:
        raise RuntimeError(f"make_chair: the union for {spec} is {', '.join(problems)}")
    return Chair(vertices=v, faces=f, face_parts=labels, landmarks=chair_landmarks(v, f),
                 spec=spec)


# --------------------------------------------------------------------------------------------
# Scanner frame
# --------------------------------------------------------------------------------------------

def scan_pose(rng: np.random.Generator, max_translation: float = 1.0) -> np.ndarray:
    """Random rigid ``(4, 4)`` scan-from-chair transform: a uniformly random rotation and a
    translation uniform in ±``max_translation`` metres per axis (a 3D scanner's arbitrary frame)."""
    rot = Rotation.random(rng=rng).as_matrix()
    return make_transform(rot, rng.uniform(-max_translation, max_translation, 3))


def to_scan_frame(chair: Chair, transform: np.ndarray) -> Chair:
    """``chair`` with vertices and landmark points/normals mapped by the ``(4, 4)``
    scan-from-chair ``transform``; faces, labels and spec are shared."""
    transform = np.asarray(transform, dtype=np.float64)
    return dataclasses.replace(chair, vertices=apply_transform(transform, chair.vertices),
                               landmarks=chair.landmarks.transformed(transform))


# --------------------------------------------------------------------------------------------
# Room
# --------------------------------------------------------------------------------------------

@dataclass(eq=False)
class RoomObject:
    """A background mesh in the world frame (metres, +Y up, floor y = 0): ``vertices`` (V, 3),
    ``faces`` (F, 3) outward-oriented, nominal ``color`` RGB in [0, 1]."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[float, float, float]


def _table(rng: np.random.Generator) -> list[tuple[str, _Mesh, tuple[float, float, float]]]:
    length, width, height = rng.uniform(1.0, 1.5), rng.uniform(0.6, 0.9), rng.uniform(0.72, 0.76)
    top = _box((-length / 2, height - 0.03, -width / 2), (length / 2, height, width / 2))
    parts = [(top, 0)]
    for sx in (-1, 1):
        for sz in (-1, 1):
            x, z = sx * (length / 2 - 0.08), sz * (width / 2 - 0.08)
            parts.append((_box((x - 0.025, 0.0, z - 0.025), (x + 0.025, height - 0.015,
                                                            z + 0.025)), 0))
    v, f, _ = _union(parts)
    return [("table", (v, f), (0.55, 0.38, 0.22))]


def _cabinet(rng: np.random.Generator) -> list[tuple[str, _Mesh, tuple[float, float, float]]]:
    w, d, h = rng.uniform(0.4, 1.0), rng.uniform(0.35, 0.55), rng.uniform(0.8, 1.9)
    return [("cabinet", _box((-w / 2, 0.0, -d / 2), (w / 2, h, d / 2)), (0.86, 0.85, 0.82))]


def _plant(rng: np.random.Generator) -> list[tuple[str, _Mesh, tuple[float, float, float]]]:
    r, h = rng.uniform(0.12, 0.22), rng.uniform(0.3, 0.45)
    pot = _prism((0.0, 0.0), (0.0, 0.0), 0.8 * r, 0.8 * r, 0.0, h, 24, top_scale=1.25)
    leaves = trimesh.creation.icosphere(subdivisions=2, radius=rng.uniform(0.25, 0.4))
    leaves.apply_translation((0.0, h + 0.8 * leaves.bounds[1, 1], 0.0))
    return [("plant_pot", pot, (0.72, 0.36, 0.22)),
            ("plant", (np.asarray(leaves.vertices, float), np.asarray(leaves.faces)),
             (0.2, 0.5, 0.2))]


def _storage_box(rng: np.random.Generator) -> list[tuple[str, _Mesh, tuple[float, float, float]]]:
    w, d, h = rng.uniform(0.3, 0.6, 3)
    return [("box", _box((-w / 2, 0.0, -d / 2), (w / 2, h, d / 2)), (0.62, 0.5, 0.35))]


def make_room(rng: np.random.Generator, size: tuple[float, float] = (6.0, 6.0), *,
              clearance: float = 1.5, walls: bool = False,
              avoid: Sequence[tuple[float, float, float]] = ()) -> list[RoomObject]:
    """A floor slab and background clutter around the interaction area, world frame.

    The floor is a 5 cm slab (top at y = 0) of ``size`` (X, Z) metres centred on the origin,
    where the chair stands. A table, a cabinet, a potted plant and 0-2 boxes are placed with
    random yaw so that no part of them comes within ``clearance`` metres (horizontally) of the
    origin, nor overlaps another object or leaves the floor; an object that does not fit after
    200 tries is left out. ``walls`` adds 2.6 m walls just outside the floor's edges.
    ``avoid``: further discs ``(x, z, radius)`` the clutter must stay out of (camera stands).
    """
    sx, sz = float(size[0]), float(size[1])
    if sx <= 0 or sz <= 0:
        raise ValueError(f"room size must be positive, got {size}")
    objects = [RoomObject("floor", *_box((-sx / 2, -0.05, -sz / 2), (sx / 2, 0.0, sz / 2)),
                          color=(0.55, 0.5, 0.45))]
    if walls:
        wall_color = (0.9, 0.89, 0.86)
        for name, lo, hi in (
                ("wall_back", (-sx / 2 - 0.1, -0.05, -sz / 2 - 0.1), (sx / 2 + 0.1, 2.6, -sz / 2)),
                ("wall_front", (-sx / 2 - 0.1, -0.05, sz / 2), (sx / 2 + 0.1, 2.6, sz / 2 + 0.1)),
                ("wall_left", (sx / 2, -0.05, -sz / 2), (sx / 2 + 0.1, 2.6, sz / 2)),
                ("wall_right", (-sx / 2 - 0.1, -0.05, -sz / 2), (-sx / 2, 2.6, sz / 2))):
            objects.append(RoomObject(name, *_box(lo, hi), color=wall_color))
    groups = [_table(rng), _cabinet(rng), _plant(rng)]
    groups += [_storage_box(rng) for _ in range(int(rng.integers(0, 3)))]
    placed: list[tuple[np.ndarray, float]] = []
    for group in groups:
        # Footprint radius about the group's vertical axis: conservative for clearance tests.
        radius = max(float(np.hypot(m[0][:, 0], m[0][:, 2]).max()) for _, m, _ in group)
        half = np.array([sx / 2, sz / 2]) - radius - 0.05
        if np.any(half <= 0):
            continue
        for _ in range(200):
            p = rng.uniform(-half, half)
            if np.hypot(*p) < clearance + radius + 0.02:
                continue
            if any(np.hypot(*(p - q)) < radius + rq + 0.05 for q, rq in placed):
                continue
            if any(np.hypot(p[0] - ax, p[1] - az) < radius + ar for ax, az, ar in avoid):
                continue
            yaw = Rotation.from_rotvec([0.0, rng.uniform(0, 2 * np.pi), 0.0]).as_matrix()
            pose = make_transform(yaw, np.array([p[0], 0.0, p[1]]))
            for name, (v, f), color in group:
                objects.append(RoomObject(name, apply_transform(pose, v), f.copy(), color))
            placed.append((p, radius))
            break
    return objects


# --------------------------------------------------------------------------------------------
# Mesh I/O
# --------------------------------------------------------------------------------------------

_MESH_SUFFIXES = (".obj", ".ply")


def save_mesh(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write a triangle mesh as OBJ or PLY (binary), by ``path``'s suffix, atomically.

    ``vertices`` (V, 3) and ``faces`` (F, 3) are written as given (no merging or reordering);
    OBJ keeps 10 decimals; PLY is binary with float32 coordinates (trimesh's choice: ~0.1 µm at
    metre scale).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in _MESH_SUFFIXES:
        raise ValueError(f"{path}: unsupported mesh format {suffix!r}; use .obj or .ply")
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64),
                           process=False)
    if suffix == ".obj":
        data = trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_color=False,
                                               include_texture=False, digits=10,
                                               header="couch").encode()
    else:
        data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", include_attributes=False)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def load_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read an OBJ or PLY triangle mesh → (vertices (V, 3) float64, faces (F, 3) int64), vertex
    order kept. Multi-object OBJ files are concatenated. Errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    suffix = path.suffix.lower()
    if suffix not in _MESH_SUFFIXES:
        raise ValueError(f"{path}: unsupported mesh format {suffix!r}; expected .obj or .ply")
    try:
        mesh = trimesh.load(path, file_type=suffix[1:], force="mesh", process=False,
                            maintain_order=True)
    except Exception as exc:   # trimesh raises many types for malformed files
        raise ValueError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: no triangles found (expected a triangle mesh)")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{path}: vertex coordinates are not all finite")
    return v, np.asarray(mesh.faces, dtype=np.int64)


def write_shapenet_layout(root: str | os.PathLike, synset_id: str, model_id: str, chair: Chair,
                          *, name: str | None = None) -> Path:
    """Write ``chair`` as ShapeNetCore v2 does; returns ``<root>/<synsetId>/<modelId>``.

    The "original" model is the chair turned into ShapeNet axes (+Y up, front -Z: a half turn
    about Y, :data:`SHAPENET_FROM_CHAIR`), in metres. ``models/model_normalized.obj`` holds
    ``(v - centroid) / |max - min|`` printed with ``%f`` like ShapeNet's own normalize script;
    ``models/model_normalized.json`` holds ``min``, ``max``, ``centroid`` (the vertex mean) and
    ``numVertices`` of the original and the ``id``; ``models/model_normalized.mtl`` one grey
    material. ``<root>/taxonomy.json`` gets (or updates) the synset's entry with the number of
    models now under it. Vertex order is the chair's.
    """
    root = Path(root)
    model_dir = root / synset_id / model_id
    v = apply_transform(SHAPENET_FROM_CHAIR, chair.vertices)
    vmin, vmax, centroid = v.min(0), v.max(0), v.mean(0)
    v_norm = (v - centroid) / np.linalg.norm(vmax - vmin)
    lines = ["# couch synthetic chair in the ShapeNetCore v2 layout",
             "mtllib model_normalized.mtl", f"o {model_id}"]
    lines += [f"v {x:f} {y:f} {z:f}" for x, y, z in v_norm]
    lines.append("usemtl material_0")
    lines += [f"f {a} {b} {c}" for a, b, c in chair.faces + 1]
    models = model_dir / "models"
    with atomic_path(models / "model_normalized.obj") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    with atomic_path(models / "model_normalized.mtl") as tmp:
        tmp.write_text("newmtl material_0\nKa 0 0 0\nKd 0.6 0.6 0.6\nKs 0 0 0\nd 1\n")
    meta = {"max": vmax.tolist(), "centroid": centroid.tolist(), "id": model_id,
            "numVertices": len(v), "min": vmin.tolist()}
    with atomic_path(models / "model_normalized.json") as tmp:
        tmp.write_text(json.dumps(meta))

    tax_path = root / "taxonomy.json"
    taxonomy = []
    if tax_path.exists():
        try:
            taxonomy = json.loads(tax_path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{tax_path}: not valid JSON ({exc})") from exc
        if not isinstance(taxonomy, list):
            raise ValueError(f"{tax_path}: expected a JSON list of synset entries")
    count = sum(1 for p in (root / synset_id).iterdir()
                if (p / "models" / "model_normalized.obj").is_file())
    entry = next((e for e in taxonomy if e.get("synsetId") == synset_id), None)
    if entry is None:
        entry = {"synsetId": synset_id, "name": name or _SYNSET_NAMES.get(synset_id, synset_id),
                 "children": [], "numInstances": 0}
        taxonomy.append(entry)
    elif name:
        entry["name"] = name
    entry["numInstances"] = count
    with atomic_path(tax_path) as tmp:
        tmp.write_text(json.dumps(taxonomy, indent=1))
    return model_dir
