"""The simulated subject's visible surface: the body model plus clothes, and hands and feet that
are not quite the model's.

DESIGN.md ("Simulator honesty"): a simulator that renders exactly the model the fitter fits makes
every accuracy number flattering. So cameras see a clothed surface: a smooth per-subject
displacement of 0.5–3 cm (loosest on the torso and thighs, none on the face), folds that move
with the joints, and hands and feet scaled a few percent about the wrist/ankle. Ground truth stays
the underlying body.

What the depth cameras saw is still recoverable: a session stores the clothing's static
per-vertex parameters in ``truth_clothing.npz`` (:func:`save_clothing`), and
:func:`clothed_surface` re-poses the body of ``ground_truth.h5`` and dresses it exactly as the
recorder did, for tests that measure a point cloud against the visible (clothed) surface.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from couch.atomic import atomic_path
from couch.body import JOINT_INDEX, BodyModel, load_body_model
from couch.geometry import vertex_normals
from couch.schema import read_processed

#: The session file holding the clothing's static parameters (arrays only, no pickles).
CLOTHING_FILE = "truth_clothing.npz"

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


def bare(clothing: Clothing) -> Clothing:
    """The same subject undressed: no garment or folds, hands and feet at the model's size (an
    oracle for what the clothes cost; drawn as usual first, so the random streams are kept)."""
    return dataclasses.replace(clothing, rest_offset=np.zeros_like(clothing.rest_offset),
                               fold_amp=np.zeros_like(clothing.fold_amp), hand_scale=1.0,
                               foot_scale=1.0)


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


def body_vertices(model: BodyModel, betas: np.ndarray, params: dict[str, np.ndarray],
                  frames: slice | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Posed body vertices (T,V,3) and joint transforms (T,24,4,4), float64 world metres, of
    ``frames`` (a slice or (T,) indices) of ``params`` (``global_orient`` (N,3), ``body_pose``
    (N,69), ``transl`` (N,3)) for shape ``betas`` (K,)."""
    with torch.no_grad():
        out = model(betas=betas[None], global_orient=params["global_orient"][frames],
                    body_pose=params["body_pose"][frames], transl=params["transl"][frames])
    return out.vertices.double().numpy(), out.joint_transforms.double().numpy()


def clothed_vertices(clothing: Clothing, model: BodyModel, betas: np.ndarray,
                     params: dict[str, np.ndarray], frames: slice | np.ndarray) -> np.ndarray:
    """(T,V,3) float64 world metres: the clothed surface the cameras see in ``frames`` of
    ``params`` (see :func:`body_vertices`); what the recorder renders."""
    verts, transforms = body_vertices(model, betas, params, frames)
    return dress(clothing, model, verts, transforms, np.asarray(params["body_pose"])[frames])


def save_clothing(path: str | os.PathLike, clothing: Clothing, model_name: str) -> None:
    """Write ``clothing`` (and the body model's name it belongs to) as an npz, atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(
            fh, rest_offset=clothing.rest_offset, fold_amp=clothing.fold_amp,
            fold_phase=clothing.fold_phase, fold_joint=clothing.fold_joint.astype(np.int64),
            hand_scale=np.float64(clothing.hand_scale),
            foot_scale=np.float64(clothing.foot_scale), model=np.str_(model_name))


def load_clothing(path: str | os.PathLike) -> tuple[Clothing, str]:
    """The clothing of :func:`save_clothing` and the body model name (``allow_pickle=False``).

    Raises:
        ValueError: the file is missing a key or its arrays disagree in vertex count (naming
            the file).
    """
    keys = ("rest_offset", "fold_amp", "fold_phase", "fold_joint", "hand_scale", "foot_scale",
            "model")
    with np.load(path, allow_pickle=False) as z:
        missing = [k for k in keys if k not in z]
        if missing:
            raise ValueError(f"{path}: missing arrays {missing}; not a simulator clothing file")
        data = {k: z[k] for k in keys}
    n = len(data["rest_offset"])
    if data["rest_offset"].shape != (n, 3) or any(
            data[k].shape != (n,) for k in ("fold_amp", "fold_phase", "fold_joint")):
        raise ValueError(f"{path}: clothing arrays disagree in shape: "
                         f"{ {k: data[k].shape for k in keys[:4]} }")
    clothing = Clothing(rest_offset=data["rest_offset"], fold_amp=data["fold_amp"],
                        fold_phase=data["fold_phase"], fold_joint=data["fold_joint"],
                        hand_scale=float(data["hand_scale"]),
                        foot_scale=float(data["foot_scale"]))
    return clothing, str(data["model"])


def clothed_surface(session_dir: str | os.PathLike,
                    frames: Sequence[int] | np.ndarray | None = None,
                    model: BodyModel | None = None, chunk: int = 64) -> np.ndarray:
    """The clothed surface the simulator rendered in ``frames`` of a session.

    Re-poses the body of ``ground_truth.h5`` (shape, pose and translation per frame) and dresses
    it with the session's ``truth_clothing.npz``, as the recorder did.

    Args:
        session_dir: a ``couch-simulate`` session folder.
        frames: (T,) indices into ``ground_truth.h5``'s frames; None = all.
        model: the body model the session was rendered with; None = the one named in the
            clothing file. Its faces are the surface's triangles.
        chunk: frames posed at once (bounds memory).

    Returns:
        (T,V,3) float64 world metres (Y up, floor y = 0) of the body model's vertices.
    """
    session_dir = Path(session_dir)
    path = session_dir / CLOTHING_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no clothing truth (a session written by an older "
                                "couch-simulate?)")
    clothing, name = load_clothing(path)
    model = model or load_body_model(name)
    if model.weights.shape[0] != len(clothing.rest_offset):
        raise ValueError(f"{path}: clothing has {len(clothing.rest_offset)} vertices, the body "
                         f"model {model.weights.shape[0]}")
    truth = read_processed(session_dir / "ground_truth.h5")
    params = {"global_orient": truth.global_orient, "body_pose": truth.body_pose,
              "transl": truth.transl}
    idx = np.arange(truth.num_frames) if frames is None else np.asarray(frames, dtype=np.intp)
    if idx.size and (idx.min() < 0 or idx.max() >= truth.num_frames):
        raise IndexError(f"{session_dir}: frames must lie in 0..{truth.num_frames - 1}")
    parts = [clothed_vertices(clothing, model, truth.betas, params, idx[a:a + chunk])
             for a in range(0, len(idx), chunk)]
    return np.concatenate(parts) if parts else np.zeros((0, len(clothing.rest_offset), 3))
