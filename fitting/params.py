"""SMPL parameters of a sequence, in the processed schema's shapes (DESIGN.md).

:class:`BodyParams` is what the fitters take as their initial pose (the synced IMU pose, or any
other guess) and what they return.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from couch.body.skeleton import NUM_BODY_JOINTS, PARENTS

__all__ = ["BodyParams"]

NUM_BETAS = 10


@dataclasses.dataclass(frozen=True)
class BodyParams:
    """Per-frame SMPL parameters (world frame: metres, Y up), float32.

    Attributes:
        global_orient: (T,3) axis-angle of the pelvis in the world.
        body_pose: (T,69) axis-angle local rotations of the 23 body joints, SMPL order.
        transl: (T,3) metres, world translation.
        betas: (10,) shape coefficients shared by every frame.
    """

    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    betas: np.ndarray

    def __post_init__(self) -> None:
        def arr(name: str, shape: tuple[int, ...]) -> None:
            a = np.asarray(getattr(self, name), dtype=np.float32)
            if a.ndim != len(shape) or any(s != -1 and a.shape[i] != s
                                           for i, s in enumerate(shape)):
                want = ", ".join("T" if s == -1 else str(s) for s in shape)
                raise ValueError(f"BodyParams.{name} must be ({want}), got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"BodyParams.{name} holds NaN or infinite values")
            object.__setattr__(self, name, a)

        arr("global_orient", (-1, 3))
        arr("body_pose", (-1, 3 * NUM_BODY_JOINTS))
        arr("transl", (-1, 3))
        arr("betas", (NUM_BETAS,))
        t = {len(self.global_orient), len(self.body_pose), len(self.transl)}
        if len(t) != 1:
            raise ValueError(f"BodyParams: frame counts differ: global_orient "
                             f"{self.global_orient.shape}, body_pose {self.body_pose.shape}, "
                             f"transl {self.transl.shape}")

    @property
    def num_frames(self) -> int:
        return len(self.transl)

    def frames(self, index: slice | np.ndarray | list[int]) -> BodyParams:
        """The parameters of a subset of frames (same betas)."""
        return BodyParams(self.global_orient[index], self.body_pose[index], self.transl[index],
                          self.betas)

    def bone_rotations(self) -> np.ndarray:
        """(T, 24, 3, 3) world orientation of every bone (SMPL's kinematic chain composed)."""
        t = self.num_frames
        aa = np.concatenate([self.global_orient, self.body_pose], 1).reshape(t * 24, 3)
        local = Rotation.from_rotvec(aa.astype(np.float64)).as_matrix().reshape(t, 24, 3, 3)
        world = np.zeros_like(local)
        for j in range(24):  # along the chain: a parent comes before its children
            world[:, j] = local[:, j] if j == 0 else world[:, PARENTS[j]] @ local[:, j]
        return world

    def with_bone_rotations(self, world: np.ndarray) -> BodyParams:
        """The same translation and shape with (T, 24, 3, 3) world bone orientations."""
        t = self.num_frames
        local = np.array(world, dtype=np.float64)
        for j in range(1, 24):
            local[:, j] = np.swapaxes(world[:, PARENTS[j]], -1, -2) @ world[:, j]
        aa = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_rotvec().reshape(t, 24, 3)
        return BodyParams(aa[:, 0], aa[:, 1:].reshape(t, 69), self.transl, self.betas)

    def with_betas(self, betas: np.ndarray) -> BodyParams:
        """The same poses with another shape."""
        return dataclasses.replace(self, betas=np.asarray(betas, dtype=np.float32))

    @classmethod
    def from_processed(cls, session: object) -> BodyParams:
        """From a :class:`couch.schema.ProcessedSession` (e.g. ``ground_truth.h5``)."""
        return cls(session.global_orient, session.body_pose, session.transl,  # type: ignore[attr-defined]
                   session.betas)  # type: ignore[attr-defined]
