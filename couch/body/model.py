"""SMPL-format body models: the bundled free model, or a user's real SMPL file.

``load_body_model("couch-body")`` gives the bundled model (13,348 vertices; ``"couch-body-coarse"``
has 1,229); a path to a real SMPL ``.npz`` or ``.pkl`` gives that model. Code never assumes a
vertex count: everything it needs (faces, weights, regressor, contact vertex sets) comes from
the loaded model.
"""

from __future__ import annotations

import dataclasses
import json
import os
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse
import torch

from couch.body.lbs import lbs, rigid_transforms, vertices_to_joints
from couch.body.skeleton import JOINT_NAMES, NUM_BODY_JOINTS, NUM_JOINTS, contact_vertex_sets
from couch.rotations import axis_angle_to_matrix
from couch.safe_pickle import safe_load_pickle

BUNDLED_MODELS: dict[str, str] = {
    "couch-body": "couch_body.npz",
    "couch-body-coarse": "couch_body_coarse.npz",
}

# SMPL's own keypoint vertex ids (as published with smplx's vertex_ids.py) for the 6,890-vertex
# SMPL topology: only used for real SMPL files, which do not carry keypoint ids themselves.
SMPL_TOPOLOGY_KEYPOINTS: dict[str, int] = {
    "nose": 332, "reye": 6260, "leye": 2800, "rear": 4071, "lear": 583,
    "rthumb": 6191, "rindex": 5782, "rmiddle": 5905, "rring": 6016, "rpinky": 6133,
    "lthumb": 2746, "lindex": 2319, "lmiddle": 2445, "lring": 2556, "lpinky": 2673,
    "LBigToe": 3216, "LSmallToe": 3226, "LHeel": 3387, "RBigToe": 6617, "RSmallToe": 6624,
    "RHeel": 6787,
}
_SMPL_TOPOLOGY_VERTICES = 6890


class BodyModelError(ValueError):
    """A body model file is missing, unreadable or not SMPL-format (message names the file)."""


@dataclasses.dataclass
class BodyOutput:
    """Posed bodies, world frame (metres, Y up).

    vertices: (B,V,3); joints: (B,24,3) in SMPL order; joint_transforms: (B,24,4,4)
    world-from-joint rigid transforms (rotation = the joint's global orientation).
    """

    vertices: torch.Tensor
    joints: torch.Tensor
    joint_transforms: torch.Tensor


def bundled_model_dir() -> Path:
    """Folder holding the bundled ``.npz`` files and their ``MANIFEST.json``."""
    return Path(str(resources.files("couch.body") / "data"))


class BodyModel(torch.nn.Module):
    """Batched LBS body model with SMPL's 24-joint skeleton.

    Buffers (move with ``.to(device, dtype)``): ``v_template`` (V,3), ``shapedirs`` (V,3,K),
    ``posedirs`` (P,V*3) or absent, ``J_regressor`` (24,V), ``weights`` (V,24), ``parents`` (24,).
    Plain attributes: ``faces`` (F,3) int64 numpy, ``joint_names``, ``keypoint_ids``
    (name -> vertex id), ``contact_vertices`` (contact part -> vertex ids), ``name``, ``credits``.
    """

    v_template: torch.Tensor
    shapedirs: torch.Tensor
    J_regressor: torch.Tensor
    weights: torch.Tensor
    parents: torch.Tensor

    def __init__(self, arrays: dict[str, np.ndarray], *, name: str, num_betas: int = 10,
                 keypoint_ids: dict[str, int] | None = None, credits: str = "") -> None:
        super().__init__()
        self.name = name
        self.credits = credits
        self.faces = np.asarray(arrays["f"], dtype=np.int64)
        self.joint_names = JOINT_NAMES
        self.num_betas = num_betas
        self.register_buffer("v_template", torch.as_tensor(arrays["v_template"]))
        self.register_buffer("shapedirs", torch.as_tensor(arrays["shapedirs"][:, :, :num_betas]))
        self.register_buffer("J_regressor", torch.as_tensor(arrays["J_regressor"]))
        self.register_buffer("weights", torch.as_tensor(arrays["weights"]))
        self.register_buffer("parents", torch.as_tensor(arrays["parents"], dtype=torch.long))
        posedirs = arrays.get("posedirs")
        self.posedirs: torch.Tensor | None
        if posedirs is not None and np.any(posedirs):
            # (V,3,P) → (P, V*3), the layout lbs() multiplies with.
            self.register_buffer("posedirs", torch.as_tensor(
                posedirs.reshape(-1, posedirs.shape[-1]).T.copy()))
        else:
            self.posedirs = None
        self.keypoint_ids = dict(keypoint_ids or {})
        rest_joints = arrays["J_regressor"] @ arrays["v_template"]
        self.contact_vertices = contact_vertex_sets(arrays["v_template"], arrays["weights"],
                                                    rest_joints)

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        return self.v_template.dtype

    @property
    def device(self) -> torch.device:
        return self.v_template.device

    def _tensor(self, x: Any) -> torch.Tensor:
        return torch.as_tensor(x, dtype=self.dtype, device=self.device)

    def rest_joints(self, betas: torch.Tensor | np.ndarray) -> torch.Tensor:
        """(B,K) betas → (B,24,3) rest-pose (T-pose) joints, pelvis near the origin."""
        betas = self._betas(betas, len(betas))
        v = self.v_template + torch.einsum("bk,vik->bvi", betas, self.shapedirs)
        return vertices_to_joints(self.J_regressor, v)

    def _betas(self, betas: Any, batch: int) -> torch.Tensor:
        if betas is None:
            return torch.zeros(batch, self.num_betas, dtype=self.dtype, device=self.device)
        betas = self._tensor(betas)
        if betas.ndim == 1 or len(betas) == 1:
            betas = betas.reshape(1, -1).expand(batch, -1)
        if betas.shape[-1] > self.num_betas:
            raise ValueError(f"{self.name}: got {betas.shape[-1]} betas, the model has "
                             f"{self.num_betas}")
        pad = self.num_betas - betas.shape[-1]
        return torch.nn.functional.pad(betas, (0, pad)) if pad else betas

    def _rotations(self, pose: Any, joints: int, batch: int, what: str) -> torch.Tensor:
        """Axis-angle (B,J*3)/(B,J,3) or matrices (B,J,3,3) → (B,J,3,3)."""
        if pose is None:
            eye = torch.eye(3, dtype=self.dtype, device=self.device)
            return eye.expand(batch, joints, 3, 3)
        pose = self._tensor(pose)
        if pose.ndim >= 3 and pose.shape[-2:] == (3, 3) and pose.numel() == batch * joints * 9:
            return pose.reshape(batch, joints, 3, 3)
        if pose.numel() == batch * joints * 3:
            return axis_angle_to_matrix(pose.reshape(batch, joints, 3))
        raise ValueError(f"{what}: expected axis-angle ({batch},{joints * 3}) or matrices "
                         f"({batch},{joints},3,3), got {tuple(pose.shape)}")

    def forward(self, betas: Any = None, global_orient: Any = None, body_pose: Any = None,
                transl: Any = None) -> BodyOutput:
        """Pose and shape bodies.

        Args (any may be omitted; tensors or arrays, cast to the model's dtype and device):
            betas: (B,K), (1,K) or (K,) shape coefficients (one shape broadcasts over the
                batch), K <= num_betas (zero-padded).
            global_orient: (B,3) axis-angle or (B,3,3) matrices: the pelvis's world rotation.
            Poses and translations are always batched (leading B), even for B = 1.
            body_pose: (B,69) / (B,23,3) axis-angle or (B,23,3,3) matrices, SMPL joint order.
            transl: (B,3) world translation, metres, added to every vertex and joint.
        """
        batch, rot = self._batch_rotations(betas, global_orient, body_pose, transl)
        vertices, joints, transforms = lbs(
            self._betas(betas, batch), rot, self.v_template, self.shapedirs, self.posedirs,
            self.J_regressor, self.parents, self.weights)
        if transl is not None:
            t = self._tensor(transl).reshape(batch, 1, 3)
            vertices = vertices + t
            joints, transforms = self._translated(joints, transforms, t)
        return BodyOutput(vertices=vertices, joints=joints, joint_transforms=transforms)

    def skeleton(self, betas: Any = None, global_orient: Any = None, body_pose: Any = None,
                 transl: Any = None) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward`'s ``joints`` (B,24,3) and ``joint_transforms`` (B,24,4,4) without
        skinning the mesh: forward kinematics of the shaped rest joints (pose correctives move
        vertices, never joints), for callers that need only the skeleton over long motions."""
        batch, rot = self._batch_rotations(betas, global_orient, body_pose, transl)
        rest = self.rest_joints(self._betas(betas, batch))
        joints, transforms = rigid_transforms(rot, rest, self.parents)
        transforms = transforms.clone()
        transforms[..., :3, 3] = joints
        if transl is not None:
            joints, transforms = self._translated(joints, transforms,
                                                  self._tensor(transl).reshape(batch, 1, 3))
        return joints, transforms

    def _batch_rotations(self, betas: Any, global_orient: Any, body_pose: Any, transl: Any
                         ) -> tuple[int, torch.Tensor]:
        """The batch size and the (B,24,3,3) local rotations of :meth:`forward`'s arguments."""
        given = [x for x in (transl, global_orient, body_pose) if x is not None]
        if given:
            batch = len(given[0])
        else:
            batch = len(betas) if betas is not None and np.ndim(betas) == 2 else 1
        rot = torch.cat([self._rotations(global_orient, 1, batch, "global_orient"),
                         self._rotations(body_pose, NUM_BODY_JOINTS, batch, "body_pose")], dim=1)
        return batch, rot

    @staticmethod
    def _translated(joints: torch.Tensor, transforms: torch.Tensor, t: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        transforms = transforms.clone()
        transforms[..., :3, 3] += t
        return joints + t, transforms


def _read_arrays(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise BodyModelError(f"{path}: no such body model file")
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except ValueError as e:  # object arrays need pickle: refuse them
            raise BodyModelError(f"{path}: holds pickled objects, which are never loaded "
                                 f"({e}); convert it to plain arrays") from e
        except (OSError, EOFError) as e:
            raise BodyModelError(f"{path}: not a readable .npz ({e})") from e
    if path.suffix == ".pkl":
        data = safe_load_pickle(path)
        if not isinstance(data, dict):
            raise BodyModelError(f"{path}: expected a dict of arrays, got {type(data).__name__}")
        return data
    raise BodyModelError(f"{path}: unknown body model format (expected .npz or .pkl, or one of "
                         f"{', '.join(BUNDLED_MODELS)})")


def _validate(raw: dict[str, Any], path: Path) -> dict[str, np.ndarray]:
    missing = [k for k in ("v_template", "f", "shapedirs", "J_regressor", "weights",
                           "kintree_table") if k not in raw]
    if missing:
        raise BodyModelError(f"{path}: missing SMPL keys {missing}")
    out: dict[str, np.ndarray] = {}
    for k in ("v_template", "shapedirs", "weights", "posedirs"):
        if k in raw:
            out[k] = np.asarray(raw[k], dtype=np.float32)
    reg = raw["J_regressor"]
    out["J_regressor"] = np.asarray(reg.toarray() if scipy.sparse.issparse(reg) else reg,
                                    dtype=np.float32)
    out["f"] = np.asarray(raw["f"], dtype=np.int64)
    nv = out["v_template"].shape[0]
    checks = {
        "v_template": (nv, 3), "f": (out["f"].shape[0], 3),
        "shapedirs": (nv, 3, out["shapedirs"].shape[-1]), "J_regressor": (NUM_JOINTS, nv),
        "weights": (nv, NUM_JOINTS),
    }
    for k, shape in checks.items():
        if out[k].shape != shape:
            extra = (" (only the 24-joint SMPL layout is supported, not SMPL-H/SMPL-X)"
                     if k in ("J_regressor", "weights") else "")
            raise BodyModelError(f"{path}: '{k}' has shape {out[k].shape}, expected {shape}"
                                 f"{extra}")
    if "posedirs" in out and out["posedirs"].shape[:2] != (nv, 3):
        raise BodyModelError(f"{path}: 'posedirs' has shape {out['posedirs'].shape}, expected "
                             f"({nv}, 3, 207)")
    if out["f"].min() < 0 or out["f"].max() >= nv:
        raise BodyModelError(f"{path}: face indices outside 0..{nv - 1}")
    parents = np.asarray(raw["kintree_table"], dtype=np.int64)[0].copy()
    parents[0] = -1  # SMPL stores the root's parent as 2**32 - 1
    if parents.shape != (NUM_JOINTS,) or np.any(parents[1:] >= np.arange(1, NUM_JOINTS)):
        raise BodyModelError(f"{path}: 'kintree_table' is not a 24-joint tree with parents "
                             "before children")
    out["parents"] = parents
    return out


def load_body_model(name_or_path: str | os.PathLike = "couch-body", *, num_betas: int = 10,
                    dtype: torch.dtype = torch.float32,
                    device: str | torch.device = "cpu") -> BodyModel:
    """Load a body model.

    Args:
        name_or_path: a bundled name (``couch-body``, ``couch-body-coarse``), or a path to an
            SMPL-format ``.npz`` (read with ``allow_pickle=False``) or an official SMPL ``.pkl``
            (read by :func:`couch.safe_pickle.safe_load_pickle`, which never executes code).
        num_betas: shape coefficients to use (at most what the file has).
        dtype, device: of the returned model's buffers (float32 or float64; CPU or CUDA).
    Raises:
        BodyModelError: naming the file and what is wrong with it.
    """
    name = str(name_or_path)
    path = bundled_model_dir() / BUNDLED_MODELS[name] if name in BUNDLED_MODELS else Path(name)
    raw = _read_arrays(path)
    arrays = _validate(raw, path)
    if num_betas > arrays["shapedirs"].shape[-1]:
        raise BodyModelError(f"{path}: has {arrays['shapedirs'].shape[-1]} shape directions, "
                             f"{num_betas} were asked for")
    if "keypoint_names" in raw and "keypoint_vertex_ids" in raw:
        keypoints = dict(zip(map(str, raw["keypoint_names"]),
                             map(int, raw["keypoint_vertex_ids"]), strict=True))
    elif arrays["v_template"].shape[0] == _SMPL_TOPOLOGY_VERTICES:
        keypoints = dict(SMPL_TOPOLOGY_KEYPOINTS)
    else:
        keypoints = {}
    credits = str(raw["credits"]) if "credits" in raw else ""
    model = BodyModel(arrays, name=name if name in BUNDLED_MODELS else path.stem,
                      num_betas=num_betas, keypoint_ids=keypoints, credits=credits)
    return model.to(device=device, dtype=dtype)


def bundled_manifest() -> dict[str, Any]:
    """The bundled models' ``MANIFEST.json``: SHA-256, generator versions, measured errors."""
    return json.loads((bundled_model_dir() / "MANIFEST.json").read_text())
