"""Part-aware contact transfer from one chair to another (both in the chair frame, metres).

A contact point on the source chair's surface is moved to the "same place" on the target chair:

1. its part is the label (:func:`couch.augment.parts.segment_parts`) of the source face nearest
   to it;
2. it is expressed in that part's normalised frame (:class:`~couch.augment.parts.PartFrame`:
   ``(a, b)`` in [-1, 1] over the part's box, ``w`` the offset along the part normal in m);
3. the same ``(a, b, w)`` are placed in the target's frame of the same part;
4. that point is projected onto the target surface restricted to the faces of that part
   (closest point, open3d ``RaycastingScene``).

When the target lacks the part (an armrest contact onto a chair without armrests) or the point
lies on ``other`` (legs, frame, base), the result is the closest point on the whole target
surface to the source point and ``fallback`` is set.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import open3d as o3d

from couch.augment.parts import OTHER, PART_NAMES, ChairParts

__all__ = ["MeshLike", "TransferResult", "transfer_contacts"]


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


def transfer_contacts(points: np.ndarray, parts_src: ChairParts, mesh_src: MeshLike,
                      parts_dst: ChairParts, mesh_dst: MeshLike) -> TransferResult:
    """Move contact points from the source chair's surface to the target's, part by part.

    ``points`` (N, 3) contact points on (or within a few mm of) the source surface, chair
    frame, metres; ``parts_src``/``parts_dst`` the :func:`~couch.augment.parts.segment_parts`
    result of ``mesh_src``/``mesh_dst``. See the module doc for the mapping and the fallback.
    Vectorised over points (one closest-point query per part).
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
    _, face = _closest(v_src, f_src, pts)
    codes = parts_src.labels[face].astype(np.int8)
    fallback = np.ones(len(pts), dtype=bool)
    for code, name in enumerate(PART_NAMES):
        sel = codes == code
        if code == OTHER or not sel.any() or not (parts_src.has(name) and parts_dst.has(name)):
            continue
        target_faces = parts_dst.faces_of(name)
        if len(target_faces) == 0:
            continue
        local = parts_src.frames[name].to_local(pts[sel])
        guess = parts_dst.frames[name].to_world(local)
        out[sel], _ = _closest(v_dst, f_dst[target_faces], guess)
        fallback[sel] = False
    if fallback.any():
        out[fallback], _ = _closest(v_dst, f_dst, pts[fallback])
    return TransferResult(points=out, parts=codes, fallback=fallback,
                          distance_moved=np.linalg.norm(out - pts, axis=1))
