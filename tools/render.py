"""Software rendering of triangle meshes by ray casting (open3d), for previews and contact sheets.

Cameras follow OpenCV: intrinsics ``K`` (3,3) in pixels, pose ``world_from_camera`` (4,4) with
+Z forward and +Y down. Works headless on CPU (no OpenGL context needed).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d


@dataclasses.dataclass
class Mesh:
    """vertices (V,3) world metres, faces (F,3) int, colour (3,) RGB in [0, 1]."""

    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[float, float, float] = (0.7, 0.7, 0.7)


@dataclasses.dataclass
class RenderResult:
    """rgb (H,W,3) uint8; depth (H,W) float32 metres along the optical axis (inf = no hit);
    mesh_id (H,W) int32 index into the rendered mesh list (-1 = background)."""

    rgb: np.ndarray
    depth: np.ndarray
    mesh_id: np.ndarray


def intrinsics(width: int, height: int, fov_y_deg: float) -> np.ndarray:
    """(3,3) pinhole intrinsics with square pixels and the principal point at the centre."""
    f = 0.5 * height / np.tan(np.deg2rad(fov_y_deg) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])


def render(meshes: list[Mesh], k: np.ndarray, world_from_camera: np.ndarray, width: int,
           height: int, background: tuple[int, int, int] = (235, 235, 240)) -> RenderResult:
    """Ray-cast ``meshes`` from one camera; Lambertian shading under a head light plus ambient."""
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, dtype=np.float32)),
                            o3d.core.Tensor(np.asarray(m.faces, dtype=np.uint32)))
    extrinsic = np.linalg.inv(world_from_camera)
    rays = scene.create_rays_pinhole(o3d.core.Tensor(k), o3d.core.Tensor(extrinsic), width, height)
    hit = scene.cast_rays(rays)
    t = hit["t_hit"].numpy()
    ids = hit["geometry_ids"].numpy().astype(np.int64)
    normals = hit["primitive_normals"].numpy()
    dirs = rays.numpy()[..., 3:]
    valid = np.isfinite(t)
    dirs_unit = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    # A head light plus a sky light from +Y; abs() lights both sides of a face, so meshes with
    # inconsistent winding still shade sensibly.
    lambert = 0.7 * np.abs((normals * dirs_unit).sum(-1)) + 0.3 * np.abs(normals[..., 1])
    colors = np.array([m.color for m in meshes] + [(0, 0, 0)], dtype=np.float32)
    ids = np.where(valid, ids, len(meshes))
    shade = (0.25 + 0.75 * lambert)[..., None] * colors[ids]
    rgb = np.where(valid[..., None], np.clip(shade * 255, 0, 255), background).astype(np.uint8)
    # t is along the (unnormalised) ray direction, whose z component is 1 in camera coordinates.
    depth = np.where(valid, t, np.inf).astype(np.float32)
    return RenderResult(rgb=rgb, depth=depth,
                        mesh_id=np.where(valid, ids, -1).astype(np.int32))
