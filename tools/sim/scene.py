"""The simulated set: a chair placed in a room, and what the motion generator needs to know of it.

``chair_seat_geometry`` turns any chair-like mesh (generated, or a user's OBJ/PLY in the chair
frame) into the :class:`~couch.tools.sim.motion.SeatGeometry` the generator plans with: seat and
backrest positions from the chair's landmarks plus a ray cast for the backrest's front face at
seat level (a reclined backrest leans further forward there than at shoulder height).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import open3d as o3d

from couch.tools.sim.chairs import PART_NAMES, Chair, ChairLandmarks, chair_landmarks, load_mesh
from couch.tools.sim.motion import SeatGeometry


class _Candidate(NamedTuple):
    part: str
    point: np.ndarray
    normal: np.ndarray


def _backrest_front_at_seat(vertices: np.ndarray, faces: np.ndarray,
                            lm: ChairLandmarks) -> float | None:
    """Largest z of the backrest's front face between 5 and 35 cm above the seat, near x = 0."""
    if lm.back_front is None:
        return None
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)),
                        o3d.core.Tensor(faces.astype(np.uint32)))
    xs, hs = np.meshgrid(np.linspace(-0.08, 0.08, 5), np.linspace(0.05, 0.35, 7))
    origins = np.stack([lm.seat_center[0] + xs.ravel(), lm.seat_height + hs.ravel(),
                        np.full(xs.size, lm.seat_center[2])], -1)
    rays = np.concatenate([origins, np.tile([0.0, 0.0, -1.0], (len(origins), 1))], 1)
    t = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    hit = np.isfinite(t) & (t < 1.0)
    if not hit.any():
        return float(lm.back_front[2])
    return float(lm.seat_center[2] - t[hit].min())


def _surface_candidates(vertices: np.ndarray, faces: np.ndarray, face_parts: np.ndarray,
                        per_part: int = 40) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Palm placements sampled on the upward-facing faces of each labelled part
    (deterministic; area-weighted)."""
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(normal, axis=1)
    normal = normal / np.maximum(2 * area[:, None], 1e-12)
    rng = np.random.default_rng(0)
    out = []
    for label, part in enumerate(PART_NAMES):
        sel = np.flatnonzero((face_parts == label) & (normal[:, 1] > 0.8) & (area > 0))
        if part == "base" or not len(sel):
            continue
        pick = rng.choice(sel, size=per_part, p=area[sel] / area[sel].sum())
        r = rng.random((per_part, 2))
        r = np.where(r.sum(1, keepdims=True) > 1, 1 - r, r)
        pts = tri[pick, 0] + r[:, :1] * (tri[pick, 1] - tri[pick, 0]) + r[:, 1:] * (
            tri[pick, 2] - tri[pick, 0])
        out += [(part, p, n) for p, n in zip(pts, normal[pick], strict=True)]
    return out


def chair_seat_geometry(vertices: np.ndarray, faces: np.ndarray,
                        landmarks: ChairLandmarks | None = None,
                        face_parts: np.ndarray | None = None) -> SeatGeometry:
    """Planning geometry of a chair mesh in the chair frame (seat facing +Z, floor y = 0).

    Palm targets are the landmarks' contact candidates, plus (when ``face_parts`` labels the
    faces, as for generated chairs) points sampled over each part's upward-facing surface.
    """
    lm = landmarks or chair_landmarks(vertices, faces)
    targets: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    candidates = [(c.part, c.point, c.normal) for c in lm.contacts]
    if face_parts is not None and np.any(face_parts >= 0):
        candidates += _surface_candidates(vertices, faces, face_parts)
    for part, point, normal in candidates:
        c = _Candidate(part, np.asarray(point, float), np.asarray(normal, float))
        if c.part in ("left_armrest", "right_armrest"):
            keys = [c.part]
        elif c.part in ("seat", "back"):
            # a candidate near the middle serves either hand
            keys = [f"{side}_{c.part}" for side, sign in (("left", 1), ("right", -1))
                    if sign * c.point[0] > -0.03]
        else:
            continue
        for key in keys:
            targets.setdefault(key, []).append((c.point, c.normal))
    return SeatGeometry(
        seat_height=float(lm.seat_height), seat_center=np.asarray(lm.seat_center, float),
        seat_front_z=float(lm.seat_front[2]),
        back_front_z=_backrest_front_at_seat(vertices, faces, lm),
        half_width=float(np.abs(vertices[:, 0]).max()), hand_targets=targets)


def load_chair(path: str) -> Chair:
    """A user's chair mesh (OBJ/PLY, chair frame: floor y = 0, seat facing +Z) as a Chair."""
    vertices, faces = load_mesh(path)
    lm = chair_landmarks(vertices, faces)
    return Chair(vertices=vertices, faces=faces, face_parts=np.full(len(faces), -1, np.int8),
                 landmarks=lm)
