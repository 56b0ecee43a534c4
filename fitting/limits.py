"""A differentiable joint-limit penalty: :mod:`couch.body.limits` in torch.

Same definition as :func:`couch.body.limits.joint_limit_excess_deg`: each body joint's local
rotation is decomposed into intrinsic Euler angles in the joint's own order
(:data:`couch.body.limits.EULER_ORDERS`), of the two equivalent decompositions the one closer to
the joint's range counts, and an angle outside its range costs the square of the excess
(radians²). Zero inside every range, so a fit is free there. One difference: within 5° of
gimbal lock (a middle angle at ±90°) the numpy reading may re-split the first and third angles
to bring them into range (moving the rotation by under 1°); this penalty keeps the plain split,
so there it can push a fit off a pose the numpy reading calls legal (a penalty that re-split
would need the split chosen without breaking the gradient; not needed so far).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from couch.body.limits import EULER_ORDERS, JOINT_LIMITS_DEG
from couch.body.skeleton import JOINT_NAMES

__all__ = ["euler_angles", "joint_limit_excess", "joint_limit_penalty"]

_AXES = "XYZ"
_NAMES = JOINT_NAMES[1:]
# (23,3) axis indices of each joint's order, and the ranges in that order (radians).
_ORDER_IDX = np.array([[_AXES.index(a) for a in EULER_ORDERS[n]] for n in _NAMES])
_LOW = np.array([[JOINT_LIMITS_DEG[n][a][0] for a in o] for n, o in zip(_NAMES, _ORDER_IDX,
                                                                        strict=True)])
_HIGH = np.array([[JOINT_LIMITS_DEG[n][a][1] for a in o] for n, o in zip(_NAMES, _ORDER_IDX,
                                                                         strict=True)])
_LOW_RAD = np.deg2rad(_LOW)
_HIGH_RAD = np.deg2rad(_HIGH)
# an even permutation of XYZ (XYZ, YZX, ZXY) has parity +1
_PARITY = np.array([1.0 if tuple(o) in ((0, 1, 2), (1, 2, 0), (2, 0, 1)) else -1.0
                    for o in _ORDER_IDX])


def _safe_atan2(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """atan2 with a finite gradient at (0, 0) (gimbal lock): there it is 0."""
    zero = (y.abs() < 1e-12) & (x.abs() < 1e-12)
    return torch.atan2(torch.where(zero, torch.zeros_like(y), y),
                       torch.where(zero, torch.ones_like(x), x))


def euler_angles(rot: torch.Tensor) -> torch.Tensor:
    """Intrinsic Euler angles of body-joint rotations, each joint in its own order.

    Args:
        rot: (..., 23, 3, 3) local rotations of SMPL's body joints (1..23).

    Returns:
        (..., 23, 3) radians, angles in the joint's order (first = its hinge axis), the first
        decomposition (middle angle in [-π/2, π/2]) as scipy's ``as_euler`` gives it.
    """
    if rot.shape[-3:] != (23, 3, 3):
        raise ValueError(f"expected (..., 23, 3, 3) body-joint rotations, got {tuple(rot.shape)}")
    idx = torch.as_tensor(_ORDER_IDX, device=rot.device)
    i, j, k = idx[:, 0], idx[:, 1], idx[:, 2]
    s = torch.as_tensor(_PARITY, dtype=rot.dtype, device=rot.device)
    joint = torch.arange(23, device=rot.device)

    def el(r: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return rot[..., joint, r, c]

    # R = R_i(a) R_j(b) R_k(c):  R[i,k] = s sin b, R[j,k] = -s sin a cos b, R[k,k] = cos a cos b,
    # R[i,j] = -s cos b sin c, R[i,i] = cos b cos c.
    b = torch.asin(torch.clamp(s * el(i, k), -1.0 + 1e-7, 1.0 - 1e-7))
    a = _safe_atan2(-s * el(j, k), el(k, k))
    c = _safe_atan2(-s * el(i, j), el(i, i))
    return torch.stack([a, b, c], dim=-1)


def _wrap(a: torch.Tensor) -> torch.Tensor:
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


def joint_limit_excess(rot: torch.Tensor) -> torch.Tensor:
    """(..., 23, 3) radians by which each Euler angle leaves its range (0 inside).

    Of the two decompositions of each rotation, (a, b, c) and (a+π, π−b, c+π), the one with the
    smaller total excess counts (as in :mod:`couch.body.limits`).

    Args:
        rot: (..., 23, 3, 3) local body-joint rotations.
    """
    first = euler_angles(rot)
    a, b, c = first.unbind(-1)
    second = _wrap(torch.stack([a + math.pi, math.pi - b, c + math.pi], dim=-1))
    lo = torch.as_tensor(_LOW_RAD, dtype=rot.dtype, device=rot.device)
    hi = torch.as_tensor(_HIGH_RAD, dtype=rot.dtype, device=rot.device)
    ex1 = torch.relu(lo - first) + torch.relu(first - hi)
    ex2 = torch.relu(lo - second) + torch.relu(second - hi)
    use_second = (ex2.sum(-1) < ex1.sum(-1))[..., None]
    return torch.where(use_second, ex2, ex1)


def joint_limit_penalty(rot: torch.Tensor) -> torch.Tensor:
    """Sum over joints and axes of the squared excess (radians²), per leading index.

    Args:
        rot: (..., 23, 3, 3) local body-joint rotations.

    Returns:
        (...) penalty, differentiable; 0 for a pose inside every range.
    """
    return joint_limit_excess(rot).square().sum(dim=(-1, -2))
