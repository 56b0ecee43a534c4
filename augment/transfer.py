"""Part-aware contact transfer from one chair to another (both in the chair frame, metres).

A contact point on the source chair's surface is moved to the "same place" on the target chair:

1. its part is the label (:func:`couch.augment.parts.segment_parts`) of the source face nearest
   to it;
2. it is expressed in that part's normalised frame (:class:`~couch.augment.parts.PartFrame`:
   ``(a, b)`` in [-1, 1] over the part's box, ``w`` the offset along the part normal in m);
3. the same ``(a, b, w)`` are placed in the target's frame of the same part;
4. that point is projected onto the target surface restricted to the faces of that part
   (closest point, open3d ``RaycastingScene``).

When the target lacks the part or the point lies on ``other`` (legs, frame, base), the result is
the closest point on the whole target surface to the source point and ``fallback`` is set.

With a ``shift`` (the sitter's placement on the new chair, :func:`sitter_shift`), positions are
kept in metres instead: the source point moved by ``shift`` is expressed in the target part's
frame and clamped into the part's box (an armrest keeps its normalised position across its
width), so contacts stay where the sitter's body is rather than being stretched over a wider
seat. An armrest contact onto a chair without that armrest then goes to the seat's edge on the
same side (a hand that rested on an armrest rests beside the thigh), still flagged ``fallback``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import open3d as o3d

from couch.augment.parts import (
    LEFT_ARMREST,
    OTHER,
    PART_NAMES,
    RIGHT_ARMREST,
    ChairParts,
)

__all__ = ["MeshLike", "TransferResult", "contact_parts", "sitter_shift", "transfer_contacts"]

EDGE = 0.95
"""With a shift, transferred points are clamped to this fraction of a part's half extents."""
HIP_CLEARANCE = 0.2
"""m: a sitter's pelvis centre stays this far inside the new seat's side edges."""


class _HasMesh(Protocol):
    vertices: np.ndarray
    faces: np.ndarray


MeshLike = tuple[np.ndarray, np.ndarray] | _HasMesh
"""A triangle mesh: ``(vertices (V, 3), faces (F, 3))`` or any object with ``vertices`` and
``faces`` attributes (:class:`~couch.augment.shapes.ShapeEntry`, a simulator ``Chair``, a
``trimesh.Trimesh``)."""


@dataclass(eq=False)
class TransferResult:
    """Transferred contacts, chair frame of the target.

    ``points`` (N, 3) on the target surface (m); ``parts`` (N,) int8 codes into
    :data:`~couch.augment.parts.PART_NAMES` of the source part of each point; ``fallback`` (N,)
    bool, True where the point went to the nearest target surface point because its part is
    ``other`` or missing on the target; ``distance_moved`` (N,) |points - source points| (m).
    """

    points: np.ndarray
    parts: np.ndarray
    fallback: np.ndarray
    distance_moved: np.ndarray

    @property
    def part_names(self) -> list[str]:
        """The source part name of each point (N,)."""
        return [PART_NAMES[int(k)] for k in self.parts]


def _arrays(mesh: MeshLike) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(mesh, tuple):
        v, f = mesh
    else:
        v, f = mesh.vertices, mesh.faces
    return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)


def _closest(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Closest points (N, 3) on the triangles ``faces`` (K, 3) of ``vertices`` to ``points``
    (N, 3), and the index (N,) into ``faces`` of the triangle each lies on."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(vertices.astype(np.float32), faces.astype(np.uint32))
    ans = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    return (ans["points"].numpy().astype(np.float64),
            ans["primitive_ids"].numpy().astype(np.int64))


def contact_parts(points: np.ndarray, parts: ChairParts, mesh: MeshLike) -> np.ndarray:
    """(N,) int8 part codes (:data:`~couch.augment.parts.PART_NAMES`) of the faces nearest to
    ``points`` (N, 3) on ``mesh`` (chair frame, m), segmented as ``parts``."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0, np.int8)
    v, f = _arrays(mesh)
    return parts.labels[_closest(v, f, pts)[1]].astype(np.int8)


def _inner_edge(parts: ChairParts, name: str) -> float:
    """X (m) of an armrest box's edge facing the seat (left armrests lie at +X)."""
    fr = parts.frames[name]
    sign = -1.0 if name == "left_armrest" else 1.0
    return float(fr.centre[0] + sign * fr.half_extents[0])


def sitter_shift(parts_src: ChairParts, parts_dst: ChairParts, armrest_frames: dict[str, int],
                 seated_x: float | None = None) -> np.ndarray:
    """(3,) m, chair frame: where a sitter of the source chair sits on the target chair.

    Along Z the seat fronts are aligned (the knees and feet keep their relation to the front
    edge, so a deeper sofa does not swallow the shins). Along X the inner edges of the armrests
    the source's hands held are aligned: ``armrest_frames`` counts the hand-contact frames per
    armrest ("left_armrest", "right_armrest"); the one held longest counts, and both (the mean)
    when the other was held at least half as long. Armrests missing on either chair are
    ignored. Then the seated pelvis (``seated_x``, source chair frame) is kept
    :data:`HIP_CLEARANCE` inside the target seat's sides.
    """
    front_src = parts_src.frames["seat"].centre[2] + parts_src.frames["seat"].half_extents[1]
    front_dst = parts_dst.frames["seat"].centre[2] + parts_dst.frames["seat"].half_extents[1]
    held = {a: k for a, k in armrest_frames.items()
            if k > 0 and parts_src.has(a) and parts_dst.has(a)}
    used = [a for a, k in sorted(held.items()) if k >= 0.5 * max(held.values())]
    dx = float(np.mean([_inner_edge(parts_dst, a) - _inner_edge(parts_src, a) for a in used])
               ) if used else 0.0
    if seated_x is not None and np.isfinite(seated_x):
        seat = parts_dst.frames["seat"]
        lim = max(0.0, float(seat.half_extents[0]) - HIP_CLEARANCE)
        x = float(np.clip(seated_x + dx, seat.centre[0] - lim, seat.centre[0] + lim))
        dx = x - seated_x
    return np.array([dx, 0.0, float(front_dst - front_src)])


def _clamped(parts_dst: ChairParts, name: str, points: np.ndarray,
             across: np.ndarray | None = None) -> np.ndarray:
    """Points (N, 3) expressed in the target part's frame, clamped into its box (``across``
    (N,) replaces the normalised coordinate along u), back in the chair frame."""
    fr = parts_dst.frames[name]
    local = fr.to_local(points)
    local[:, :2] = np.clip(local[:, :2], -EDGE, EDGE)
    if across is not None:
        local[:, 0] = across
    return fr.to_world(local)


def transfer_contacts(points: np.ndarray, parts_src: ChairParts, mesh_src: MeshLike,
                      parts_dst: ChairParts, mesh_dst: MeshLike,
                      shift: np.ndarray | None = None) -> TransferResult:
    """Move contact points from the source chair's surface to the target's, part by part.

    ``points`` (N, 3) contact points on (or within a few mm of) the source surface, chair
    frame, metres; ``parts_src``/``parts_dst`` the :func:`~couch.augment.parts.segment_parts`
    result of ``mesh_src``/``mesh_dst``; ``shift`` (3,) m, optional: the sitter's placement
    (:func:`sitter_shift`) for metric transfer. See the module doc for the mapping and the
    fallback. Vectorised over points (one closest-point query per part).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    v_src, f_src = _arrays(mesh_src)
    v_dst, f_dst = _arrays(mesh_dst)
    if len(parts_src.labels) != len(f_src) or len(parts_dst.labels) != len(f_dst):
        raise ValueError("transfer_contacts: part labels and mesh faces differ in count "
                         f"(source {len(parts_src.labels)} vs {len(f_src)}, target "
                         f"{len(parts_dst.labels)} vs {len(f_dst)})")
    out = np.empty_like(pts)
    if len(pts) == 0:
        return TransferResult(out, np.zeros(0, np.int8), np.zeros(0, bool), np.zeros(0))
    codes = contact_parts(pts, parts_src, (v_src, f_src))
    fallback = np.ones(len(pts), dtype=bool)
    seat_edge = np.zeros(len(pts), dtype=bool)
    moved = None if shift is None else pts + np.asarray(shift, np.float64).reshape(1, 3)
    for code, name in enumerate(PART_NAMES):
        sel = codes == code
        if code == OTHER or not sel.any() or not parts_src.has(name):
            continue
        target_faces = parts_dst.faces_of(name) if parts_dst.has(name) else np.zeros(0, int)
        if len(target_faces) == 0:
            if moved is not None and code in (LEFT_ARMREST, RIGHT_ARMREST) \
                    and parts_dst.has("seat"):
                edge = np.full(int(sel.sum()), EDGE if code == LEFT_ARMREST else -EDGE)
                guess = _clamped(parts_dst, "seat", moved[sel], across=edge)
                out[sel], _ = _closest(v_dst, f_dst[parts_dst.faces_of("seat")], guess)
                fallback[sel] = False
                seat_edge[sel] = True
            continue
        if moved is None:
            local = parts_src.frames[name].to_local(pts[sel])
            guess = parts_dst.frames[name].to_world(local)
        elif code in (LEFT_ARMREST, RIGHT_ARMREST):
            across = parts_src.frames[name].to_local(pts[sel])[:, 0]
            guess = _clamped(parts_dst, name, moved[sel], across=np.clip(across, -EDGE, EDGE))
        else:
            guess = _clamped(parts_dst, name, moved[sel])
        out[sel], _ = _closest(v_dst, f_dst[target_faces], guess)
        fallback[sel] = False
    src = pts if moved is None else moved
    if fallback.any():
        out[fallback], _ = _closest(v_dst, f_dst, src[fallback])
    return TransferResult(points=out, parts=codes, fallback=fallback | seat_edge,
                          distance_moved=np.linalg.norm(out - src, axis=1))
