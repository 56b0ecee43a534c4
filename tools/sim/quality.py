"""Plausibility measures of (simulated) human-chair motion: foot slide, penetration, joint limits.

These check the simulator's own output against the issue's thresholds (stance feet slide < 1 cm,
penetration into the chair < 2 cm, joint limits respected); they take arrays, not simulator
objects, so tests can apply them to any motion.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from couch.body import JOINT_INDEX
from couch.body.limits import joint_limit_excess_deg


def stance_slide(ankle: np.ndarray, rest_height: float, tol: float = 0.005) -> np.ndarray:
    """Horizontal slide (m) of one foot over each stance.

    Args:
        ankle: (T,3) ankle joint positions (world, Y up).
        rest_height: ankle height when the foot is flat on the floor.
    Returns:
        (S,) for each stance (a run of frames with the ankle within ``tol`` of its rest height),
        the largest horizontal distance from where the stance began.
    """
    planted = ankle[:, 1] < rest_height + tol
    edges = np.flatnonzero(np.diff(np.r_[0, planted.astype(int), 0]))
    slides = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        xz = ankle[a:b][:, [0, 2]]
        slides.append(np.linalg.norm(xz - xz[0], axis=1).max())
    return np.asarray(slides)


def foot_slide(joints: np.ndarray, tol: float = 0.005) -> float:
    """Worst stance slide (m) of either foot; ``joints`` (T,24,3). A foot's flat height is its
    lowest ankle height in the sequence."""
    worst = 0.0
    for name in ("left_ankle", "right_ankle"):
        a = joints[:, JOINT_INDEX[name]]
        s = stance_slide(a, float(a[:, 1].min()), tol)
        worst = max(worst, float(s.max()) if len(s) else 0.0)
    return worst


def penetration_depth(vertices: np.ndarray, mesh_vertices: np.ndarray, mesh_faces: np.ndarray
                      ) -> np.ndarray:
    """(T,) deepest penetration (m, >= 0) of body ``vertices`` (T,V,3) into a watertight mesh."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh_vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh_faces.astype(np.uint32)))
    pts = o3d.core.Tensor(vertices.reshape(-1, 3).astype(np.float32))
    # a majority vote of 5 rays: one ray grazing an edge of the mesh miscounts inside/outside
    sd = scene.compute_signed_distance(pts, nsamples=5).numpy().reshape(vertices.shape[:2])
    return np.maximum(-sd, 0.0).max(axis=1)


def joint_limit_excess(body_pose: np.ndarray) -> float:
    """Largest excursion (degrees) of any joint beyond its anatomical range."""
    return float(joint_limit_excess_deg(body_pose).max())
