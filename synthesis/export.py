"""Writing synthesised motions: one ``.npz`` of the whole batch and the processed-session schema
(``couch.schema``) per character, so the rest of couch (``couch-inspect``, augmentation,
training) reads synthesised motion like captured motion.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from couch.atomic import atomic_path
from couch.body import CONTACT_NAMES, JOINT_INDEX
from couch.schema import ProcessedSession, write_processed
from couch.synthesis.controller import SynthesisResult

__all__ = ["interaction_labels", "save_npz", "to_processed", "write_processed_sessions"]

def interaction_labels(result: SynthesisResult) -> np.ndarray:
    """(B,T) int8 schema interaction labels: 0 locomotion before the first predicted sit, then
    by the active contact set's hands (1 right, 2 left, 3 both, 4 no hand contact)."""
    left = np.isfinite(result.targets[..., 0, 0])
    right = np.isfinite(result.targets[..., 1, 0])
    by_hands = np.select([left & right, left, right], [3, 2, 1], default=4)
    seated = np.maximum.accumulate(result.contacts[..., CONTACT_NAMES.index("pelvis")] > 0.5,
                                   axis=1)
    return np.where(seated, by_hands, 0).astype(np.int8)


def to_processed(result: SynthesisResult, index: int, name: str | None = None
                 ) -> ProcessedSession:
    """Character ``index`` of ``result`` as a :class:`ProcessedSession` (time from 0 at ``fps``;
    the chair in its chair frame posed by the scene's ``world_from_chair``; contacts are the
    controller's predicted labels, with the SMPL joint of the same name as each point)."""
    t = result.num_frames
    active = result.contacts[index] > 0.5
    joints = result.joints[index]
    points = joints[:, [JOINT_INDEX[n] for n in CONTACT_NAMES]]
    points = np.where(active[..., None], points, np.nan)
    scene = result.scene
    return ProcessedSession(
        session=name or f"{result.method}_{index:03d}", fps=float(result.fps),
        time=np.arange(t) / result.fps, betas=result.betas.astype(np.float32),
        global_orient=result.global_orient[index].astype(np.float32),
        body_pose=result.body_pose[index].astype(np.float32),
        transl=result.transl[index].astype(np.float32), joints=joints.astype(np.float32),
        object_name=scene.name, object_vertices=scene.vertices.astype(np.float32),
        object_faces=scene.faces.astype(np.int32), object_pose=scene.world_from_chair,
        object_frame_poses=np.repeat(scene.world_from_chair[None], t, 0),
        contact_active=active, contact_points=points.astype(np.float32),
        interaction=interaction_labels(result)[index])


def write_processed_sessions(result: SynthesisResult, out_dir: str | os.PathLike) -> list[Path]:
    """``<out_dir>/<method>_<b>.h5`` for every character (processed schema); returns paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for b in range(len(result.root)):
        session = to_processed(result, b)
        path = out / f"{session.session}.h5"
        write_processed(path, session)
        paths.append(path)
    return paths


def save_npz(result: SynthesisResult, path: str | os.PathLike) -> Path:
    """The whole batch as one ``.npz`` (atomically; arrays only, loads with
    ``allow_pickle=False``): SMPL parameters (B,T,...) and betas, joints, roots, hands,
    targets, control flags, the series asked for, global phase, predicted contact labels,
    the chair (chair frame) and its pose, fps and method."""
    path = Path(path)
    arrays = {k: getattr(result, k) for k in (
        "global_orient", "body_pose", "transl", "betas", "joints", "root", "hands", "targets",
        "control_on", "series", "series_index", "global_phase", "contacts")}
    arrays.update(fps=np.float64(result.fps), method=np.str_(result.method),
                  contact_names=np.array(CONTACT_NAMES),
                  chair_vertices=result.scene.vertices, chair_faces=result.scene.faces,
                  world_from_chair=result.scene.world_from_chair,
                  chair_name=np.str_(result.scene.name))
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path
