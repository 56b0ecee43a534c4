"""The simulated subject's visible surface: the body model plus clothes, and hands and feet that
are not quite the model's.

DESIGN.md ("Simulator honesty"): a simulator that renders exactly the model the fitter fits makes
every accuracy number flattering. So cameras see a clothed surface: a smooth per-subject
displacement of 0.5–3 cm (loosest on the torso and thighs, none on the face), folds that move
with the joints, and hands and feet scaled a few percent about the wrist/ankle. Ground truth stays
the underlying body.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from couch.body import JOINT_INDEX, BodyModel
from couch.geometry import vertex_normals

# Looseness (0..1) of clothing per dominant joint: 1 = loosest (3 cm), 0 = skin.
_LOOSENESS = {
    "pelvis": 1.0, "spine1": 1.0, "spine2": 1.0, "spine3": 0.9, "left_hip": 0.9,
    "right_hip": 0.9, "left_collar": 0.6, "right_collar": 0.6, "left_shoulder": 0.6,
    "right_shoulder": 0.6, "left_knee": 0.45, "right_knee": 0.45, "left_elbow": 0.35,
    "right_elbow": 0.35, "neck": 0.15, "left_ankle": 0.2, "right_ankle": 0.2,
}


@dataclasses.dataclass
class Clothing:
    """One subject's clothing: rest-space offsets and moving folds.

    rest_offset: (V,3) metres, added in the rest pose (garment thickness along the rest normal,
    plus the hand/foot scaling); fold_amp: (V,) metres; fold_phase: (V,) radians;
    fold_joint: (V,) joint whose flexion drives each vertex's folds.
    """

    rest_offset: np.ndarray
    fold_amp: np.ndarray
    fold_phase: np.ndarray
    fold_joint: np.ndarray
    hand_scale: float
    foot_scale: float


def _smooth_field(points: np.ndarray, rng: np.random.Generator, wavelengths=(0.12, 0.35),
                  n: int = 24) -> np.ndarray:
    """A smooth random scalar field in [0, 1] over (V,3) points (random Fourier features)."""
    k_dir = rng.normal(size=(n, 3))
    k_dir /= np.linalg.norm(k_dir, axis=1, keepdims=True)
    k = k_dir * (2 * np.pi / rng.uniform(*wavelengths, size=(n, 1)))
    f = np.cos(points @ k.T + rng.uniform(0, 2 * np.pi, n)).sum(1) / np.sqrt(n / 2)
    return 0.5 * (1 + np.tanh(f))


def make_clothing(model: BodyModel, betas: np.ndarray, rng: np.random.Generator) -> Clothing:
    """Random clothing for one subject of shape ``betas`` (model's rest pose)."""
    import torch

    with torch.no_grad():
        out = model(betas=torch.as_tensor(np.asarray(betas)[None], dtype=model.dtype))
    v = out.vertices[0].double().numpy()
    joints = out.joints[0].double().numpy()
    normals = vertex_normals(v, model.faces)
    weights = model.weights.double().numpy()
    dominant = weights.argmax(1)
    loose = np.zeros(len(v))
    for name, value in _LOOSENESS.items():
        loose[dominant == JOINT_INDEX[name]] = value
    # Blend looseness across segment borders so the garment has no steps.
    loose = weights @ np.array([loose[dominant == j].mean() if np.any(dominant == j) else 0.0
                                for j in range(weights.shape[1])])
    thickness = loose * (0.01 + 0.02 * _smooth_field(v, rng))
    offset = thickness[:, None] * normals

    hand_scale = float(rng.uniform(0.93, 1.07))
    foot_scale = float(rng.uniform(0.94, 1.06))
    for side in ("left", "right"):
        for centre, parts, scale in (
            ("wrist", ("wrist", "hand"), hand_scale), ("ankle", ("ankle", "foot"), foot_scale)):
            w = weights[:, [JOINT_INDEX[f"{side}_{p}"] for p in parts]].sum(1, keepdims=True)
            c = joints[JOINT_INDEX[f"{side}_{centre}"]]
            offset += w * (scale - 1.0) * (v - c)

    fold_amp = loose * rng.uniform(0.003, 0.008)
    fold_phase = 2 * np.pi * _smooth_field(v, rng, wavelengths=(0.04, 0.09))
    parents_for_folds = {"spine1": "left_hip", "pelvis": "left_hip"}
    fold_joint = np.array([JOINT_INDEX.get(parents_for_folds.get(model.joint_names[d], ""), d)
                           for d in dominant])
    return Clothing(offset, fold_amp, fold_phase, fold_joint, hand_scale, foot_scale)


def dress(clothing: Clothing, model: BodyModel, vertices: np.ndarray,
          joint_transforms: np.ndarray, body_pose: np.ndarray) -> np.ndarray:
    """Clothed surfaces of posed bodies.

    Args:
        vertices: (T,V,3) posed body vertices (world).
        joint_transforms: (T,24,4,4) world-from-joint transforms of the same poses.
        body_pose: (T,69) axis-angle, drives the folds (more flexion, deeper folds).
    Returns:
        (T,V,3) clothed vertices.
    """
    weights = model.weights.double().numpy()
    rot = np.einsum("vj,tjab->tvab", weights, joint_transforms[..., :3, :3])
    posed_offset = np.einsum("tvab,vb->tva", rot, clothing.rest_offset)
    flex = np.linalg.norm(np.asarray(body_pose, dtype=np.float64).reshape(len(vertices), 23, 3),
                          axis=-1)
    flex = np.concatenate([np.zeros((len(vertices), 1)), flex], axis=1)  # pelvis: no flexion
    fold = clothing.fold_amp * np.sin(clothing.fold_phase + 3.0 * flex[:, clothing.fold_joint])
    normals = vertex_normals(vertices + posed_offset, model.faces)
    return vertices + posed_offset + fold[..., None] * normals
