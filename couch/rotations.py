"""Rotation conversions: axis-angle, unit quaternion (w, x, y, z), 3x3 matrix and 6D.

The one module that owns rotation conversions (DESIGN.md). Every function takes either a numpy
array or a torch tensor, batched over any leading dimensions, and returns the same kind:

- numpy inputs go through ``scipy.spatial.transform.Rotation`` (float64 out);
- torch inputs use the batched, differentiable implementations below (same dtype and device), so
  fitting and the networks can back-propagate through them on CPU or GPU.

Shapes: axis-angle ``(..., 3)`` (radians, axis times angle), quaternion ``(..., 4)`` scalar first,
matrix ``(..., 3, 3)`` acting on column vectors, 6D ``(..., 6)`` = the first two matrix columns
concatenated (Zhou et al., CVPR 2019: "On the continuity of rotation representations").
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
import torch
from scipy.spatial.transform import Rotation

Array = TypeVar("Array", np.ndarray, torch.Tensor)

# Below this angle (radians) the closed forms are replaced by Taylor series, so values and
# gradients stay finite at the identity.
_SMALL_ANGLE = 1e-6


def _scipy(x: np.ndarray, trailing: tuple[int, ...]) -> tuple[np.ndarray, tuple[int, ...]]:
    x = np.asarray(x, dtype=np.float64)
    if x.shape[x.ndim - len(trailing):] != trailing:
        raise ValueError(f"expected an array of shape (..., {', '.join(map(str, trailing))}), "
                         f"got {x.shape}")
    lead = x.shape[: x.ndim - len(trailing)]
    return x.reshape((-1, *trailing)), lead


def _check_torch(x: torch.Tensor, trailing: tuple[int, ...]) -> None:
    if tuple(x.shape[x.ndim - len(trailing):]) != trailing:
        raise ValueError(f"expected a tensor of shape (..., {', '.join(map(str, trailing))}), "
                         f"got {tuple(x.shape)}")


# ----------------------------------------------------------------------------- axis-angle


def axis_angle_to_quat(aa: Array) -> Array:
    """``(..., 3)`` axis-angle → ``(..., 4)`` unit quaternion (w, x, y, z), w >= 0."""
    if isinstance(aa, np.ndarray):
        flat, lead = _scipy(aa, (3,))
        q = Rotation.from_rotvec(flat).as_quat(scalar_first=True)
        return _positive_w(q).reshape((*lead, 4))
    _check_torch(aa, (3,))
    angle = torch.linalg.vector_norm(aa, dim=-1, keepdim=True)
    small = angle < _SMALL_ANGLE
    safe = torch.where(small, torch.ones_like(angle), angle)
    # sin(θ/2)/θ → 1/2 − θ²/48 near zero
    k = torch.where(small, 0.5 - angle * angle / 48.0, torch.sin(safe / 2) / safe)
    return torch.cat([torch.cos(angle / 2), aa * k], dim=-1)


def quat_to_axis_angle(q: Array) -> Array:
    """``(..., 4)`` quaternion (w, x, y, z; need not be unit) → ``(..., 3)`` axis-angle.

    The angle is in [0, π]."""
    if isinstance(q, np.ndarray):
        flat, lead = _scipy(q, (4,))
        return Rotation.from_quat(flat, scalar_first=True).as_rotvec().reshape((*lead, 3))
    _check_torch(q, (4,))
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    q = torch.where(q[..., :1] < 0, -q, q)
    w, v = q[..., :1], q[..., 1:]
    s = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    small = s < _SMALL_ANGLE
    safe_s = torch.where(small, torch.ones_like(s), s)
    # θ = 2·atan2(|v|, w); θ/|v| → 2/w near zero
    k = torch.where(small, 2.0 / w, 2.0 * torch.atan2(safe_s, w) / safe_s)
    return v * k


def axis_angle_to_matrix(aa: Array) -> Array:
    """``(..., 3)`` axis-angle → ``(..., 3, 3)`` rotation matrix."""
    if isinstance(aa, np.ndarray):
        flat, lead = _scipy(aa, (3,))
        return Rotation.from_rotvec(flat).as_matrix().reshape((*lead, 3, 3))
    return quat_to_matrix(axis_angle_to_quat(aa))


def matrix_to_axis_angle(m: Array) -> Array:
    """``(..., 3, 3)`` rotation matrix → ``(..., 3)`` axis-angle."""
    if isinstance(m, np.ndarray):
        flat, lead = _scipy(m, (3, 3))
        return Rotation.from_matrix(flat).as_rotvec().reshape((*lead, 3))
    return quat_to_axis_angle(matrix_to_quat(m))


# ----------------------------------------------------------------------------- quaternions


def _positive_w(q: np.ndarray) -> np.ndarray:
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_matrix(q: Array) -> Array:
    """``(..., 4)`` quaternion (w, x, y, z; normalised here) → ``(..., 3, 3)`` matrix."""
    if isinstance(q, np.ndarray):
        flat, lead = _scipy(q, (4,))
        return Rotation.from_quat(flat, scalar_first=True).as_matrix().reshape((*lead, 3, 3))
    _check_torch(q, (4,))
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape((*q.shape[:-1], 3, 3))


def matrix_to_quat(m: Array) -> Array:
    """``(..., 3, 3)`` rotation matrix → ``(..., 4)`` unit quaternion (w, x, y, z), w >= 0."""
    if isinstance(m, np.ndarray):
        flat, lead = _scipy(m, (3, 3))
        q = Rotation.from_matrix(flat).as_quat(scalar_first=True)
        return _positive_w(q).reshape((*lead, 4))
    _check_torch(m, (3, 3))
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # Four candidate quaternions, each scaled by 4·(its largest component); choosing the one with
    # the largest denominator avoids dividing by ~0 (Shepperd's method, batched and branch-free).
    four_sq = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22,
                           1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1)
    denom = 2 * torch.sqrt(torch.clamp(four_sq, min=1e-12))
    candidates = torch.stack([
        torch.stack([four_sq[..., 0], m21 - m12, m02 - m20, m10 - m01], dim=-1),
        torch.stack([m21 - m12, four_sq[..., 1], m10 + m01, m02 + m20], dim=-1),
        torch.stack([m02 - m20, m10 + m01, four_sq[..., 2], m12 + m21], dim=-1),
        torch.stack([m10 - m01, m20 + m02, m21 + m12, four_sq[..., 3]], dim=-1),
    ], dim=-2) / denom[..., None]
    best = four_sq.argmax(dim=-1)
    q = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: Array, b: Array) -> Array:
    """Hamilton product ``a ⊗ b`` of ``(..., 4)`` quaternions (w, x, y, z): rotate by b, then a."""
    if isinstance(a, np.ndarray):
        fa, lead = _scipy(a, (4,))
        fb, _ = _scipy(np.broadcast_to(b, a.shape), (4,))
        ra = Rotation.from_quat(fa, scalar_first=True)
        rb = Rotation.from_quat(fb, scalar_first=True)
        return (ra * rb).as_quat(scalar_first=True).reshape((*lead, 4))
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], dim=-1)


def slerp(q0: Array, q1: Array, t: Array | float) -> Array:
    """Spherical linear interpolation of ``(..., 4)`` unit quaternions (w, x, y, z).

    ``t`` is a scalar or broadcasts against ``q0[..., 0]``; t=0 gives q0, t=1 gives q1 (up to
    sign). Takes the short way round (q1 is flipped into q0's hemisphere).
    """
    if isinstance(q0, np.ndarray):
        f0, lead = _scipy(q0, (4,))
        f1, _ = _scipy(np.broadcast_to(q1, q0.shape), (4,))
        tt = np.broadcast_to(np.asarray(t, dtype=np.float64), lead).reshape(-1)
        r0 = Rotation.from_quat(f0, scalar_first=True)
        delta = (r0.inv() * Rotation.from_quat(f1, scalar_first=True)).as_rotvec()
        out = r0 * Rotation.from_rotvec(delta * tt[:, None])
        return _positive_w(out.as_quat(scalar_first=True)).reshape((*lead, 4))
    t = torch.as_tensor(t, dtype=q0.dtype, device=q0.device)[..., None]
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    theta = torch.acos(dot)
    near = theta < 1e-4
    safe = torch.where(near, torch.ones_like(theta), theta)
    w0 = torch.where(near, 1 - t, torch.sin((1 - t) * safe) / torch.sin(safe))
    w1 = torch.where(near, t, torch.sin(t * safe) / torch.sin(safe))
    q = w0 * q0 + w1 * q1
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)


# ----------------------------------------------------------------------------- 6D


def matrix_to_6d(m: Array) -> Array:
    """``(..., 3, 3)`` → ``(..., 6)``: first column then second column."""
    if isinstance(m, np.ndarray):
        return np.concatenate([m[..., :, 0], m[..., :, 1]], axis=-1)
    return torch.cat([m[..., :, 0], m[..., :, 1]], dim=-1)


_YZX, _ZXY = [1, 2, 0], [2, 0, 1]


def sixd_to_matrix(d6: Array) -> Array:
    """``(..., 6)`` → ``(..., 3, 3)`` by Gram-Schmidt; any non-degenerate 6-vector is valid."""
    if isinstance(d6, np.ndarray):
        a1, a2 = d6[..., :3], d6[..., 3:]
        # sqrt of the sum of squares: np.linalg.norm's dispatch costs more than its maths here
        b1 = a1 / np.sqrt((a1 * a1).sum(-1, keepdims=True))
        b2 = a2 - (b1 * a2).sum(-1, keepdims=True) * b1
        b2 = b2 / np.sqrt((b2 * b2).sum(-1, keepdims=True))
        out = np.empty((*d6.shape[:-1], 3, 3), np.result_type(d6, np.float32))
        out[..., 0], out[..., 1] = b1, b2
        # b1 x b2 written out: np.cross's axis handling costs more than the arithmetic on the
        # runtime's one-character arrays, where this is called every frame
        out[..., 2] = b1[..., _YZX] * b2[..., _ZXY] - b1[..., _ZXY] * b2[..., _YZX]
        return out
    _check_torch(d6, (6,))
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = torch.nn.functional.normalize(a1, dim=-1)
    b2 = torch.nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    return torch.stack([b1, b2, torch.linalg.cross(b1, b2, dim=-1)], dim=-1)


def axis_angle_to_6d(aa: Array) -> Array:
    """``(..., 3)`` axis-angle → ``(..., 6)``."""
    return matrix_to_6d(axis_angle_to_matrix(aa))


def sixd_to_axis_angle(d6: Array) -> Array:
    """``(..., 6)`` → ``(..., 3)`` axis-angle."""
    return matrix_to_axis_angle(sixd_to_matrix(d6))


def rotation_angle(m: Array) -> Array:
    """Angle in radians ``(...)`` of ``(..., 3, 3)`` rotation matrices (e.g. of ``R_a^T R_b``)."""
    if isinstance(m, np.ndarray):
        # scipy orthonormalises first: arccos of the trace of a float32 rotation near the
        # identity would report ~1e-3 rad of noise.
        flat, lead = _scipy(m, (3, 3))
        return Rotation.from_matrix(flat).magnitude().reshape(lead)
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    return torch.acos(torch.clamp((trace - 1) / 2, -1.0, 1.0))
