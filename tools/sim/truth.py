"""Ground truth of a simulated sequence in the processed-session schema (DESIGN.md).

Contacts are measured on the posed (unclothed) body, not copied from the motion plan: a part
touches the chair in a frame when any of its contact vertices is within ``CONTACT_DISTANCE`` of
the chair surface, and its contact point is the chair-surface point nearest to that part.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import torch

from couch import __version__
from couch.body import CONTACT_NAMES, BodyModel
from couch.geometry import apply_transform, invert_transform
from couch.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from couch.schema import ProcessedSession
from couch.tools.sim.motion import Motion

CONTACT_DISTANCE = 0.02  # metres


@dataclasses.dataclass
class ChairPlacement:
    """The chair as the simulator knows it: mesh in the chair frame (seat facing +Z, floor y=0),
    the same mesh as a scanner delivers it (its own frame), and the transforms between them and
    the world. ``world_from_chair`` places the chair in the room; the schema's /object/pose is
    ``world_from_scan = world_from_chair @ chair_from_scan``."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    world_from_chair: np.ndarray
    chair_from_scan: np.ndarray

    @property
    def world_from_scan(self) -> np.ndarray:
        return self.world_from_chair @ self.chair_from_scan

    @property
    def scan_vertices(self) -> np.ndarray:
        return apply_transform(invert_transform(self.chair_from_scan), self.vertices)

    @property
    def world_vertices(self) -> np.ndarray:
        return apply_transform(self.world_from_chair, self.vertices)


def motion_in_world(motion: Motion, times: np.ndarray, world_from_chair: np.ndarray,
                    rest_pelvis: np.ndarray) -> dict[str, np.ndarray]:
    """SMPL parameters at ``times`` moved from the chair frame into the world.

    SMPL rotates the body about its rest pelvis joint ``rest_pelvis`` (3,), so a rigid move
    (R, t) of the body maps transl to R·(transl + J0) + t − J0.
    """
    go, bp, tr, labels = motion.sample(times)
    rot = world_from_chair[:3, :3]
    go_w = matrix_to_axis_angle(rot @ axis_angle_to_matrix(go.astype(np.float64)))
    tr_w = (tr + rest_pelvis) @ rot.T + world_from_chair[:3, 3] - rest_pelvis
    return {"global_orient": go_w.astype(np.float32), "body_pose": bp,
            "transl": tr_w.astype(np.float32), "labels": labels}


def measure_contacts(model: BodyModel, betas: np.ndarray, params: dict[str, np.ndarray],
                     chair_world_vertices: np.ndarray, chair_faces: np.ndarray,
                     chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame contacts of the five schema parts with the chair.

    Returns active (T,5) bool and points (T,5,3) float32 (world, NaN where inactive).
    """
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(chair_world_vertices.astype(np.float32)),
                        o3d.core.Tensor(chair_faces.astype(np.uint32)))
    sets = [model.contact_vertices[name] for name in CONTACT_NAMES]
    ids = np.concatenate(sets)
    owner = np.concatenate([np.full(len(s), k) for k, s in enumerate(sets)])
    n = len(params["transl"])
    active = np.zeros((n, len(CONTACT_NAMES)), dtype=bool)
    points = np.full((n, len(CONTACT_NAMES), 3), np.nan, dtype=np.float32)
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        with torch.no_grad():
            v = model(betas=betas[None], global_orient=params["global_orient"][a:b],
                      body_pose=params["body_pose"][a:b], transl=params["transl"][a:b]
                      ).vertices[:, ids].numpy()
        q = scene.compute_closest_points(o3d.core.Tensor(v.reshape(-1, 3).astype(np.float32)))
        closest = q["points"].numpy().reshape(v.shape)
        dist = np.linalg.norm(closest - v, axis=-1)
        for k in range(len(CONTACT_NAMES)):
            d = dist[:, owner == k]
            best = d.argmin(axis=1)
            near = d[np.arange(len(d)), best] < CONTACT_DISTANCE
            active[a:b, k] = near
            pts = closest[:, owner == k][np.arange(len(d)), best]
            points[a:b, k][near] = pts[near]
    return active, points


def ground_truth(session: str, motion: Motion, times: np.ndarray, chair: ChairPlacement,
                 model: BodyModel, contact_model: BodyModel | None = None,
                 fps: float = 30.0, motion_offset: float = 0.0) -> ProcessedSession:
    """The processed-session truth of ``motion`` sampled at Kinect ``times`` (s).

    ``model`` (the full body) gives the joints; ``contact_model`` (default: the same; the coarse
    model is ~10x faster and its surface is within millimetres) measures the contacts. Kinect
    time t shows the motion at t + ``motion_offset`` (a recording that starts mid-sequence).
    """
    rest_pelvis = model.rest_joints(motion.betas[None])[0, 0].double().numpy()
    params = motion_in_world(motion, np.asarray(times) + motion_offset, chair.world_from_chair,
                             rest_pelvis)
    betas = torch.as_tensor(motion.betas[None], dtype=model.dtype)
    with torch.no_grad():
        joints = model.skeleton(betas=betas, global_orient=params["global_orient"],
                                body_pose=params["body_pose"], transl=params["transl"])[0].numpy()
    active, points = measure_contacts(contact_model or model, motion.betas, params,
                                      chair.world_vertices, chair.faces)
    pose = chair.world_from_scan
    return ProcessedSession(
        session=session, fps=fps, time=np.asarray(times, dtype=np.float64),
        betas=motion.betas.astype(np.float32), global_orient=params["global_orient"],
        body_pose=params["body_pose"], transl=params["transl"], joints=joints.astype(np.float32),
        object_name=chair.name, object_vertices=chair.scan_vertices.astype(np.float32),
        object_faces=chair.faces.astype(np.int32), object_pose=pose,
        object_frame_poses=np.repeat(pose[None], len(times), axis=0),
        contact_active=active, contact_points=points, interaction=params["labels"],
        couch_version=__version__,
    )
