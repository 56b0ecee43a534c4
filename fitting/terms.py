"""Objective terms of the body fit: small functions over frame-batched tensors.

Shapes: B frames, V mesh vertices, N cloud points, J = 24 joints. Units: metres and radians;
every data term is dimensionless (residuals over a robust scale ``sigma``), every term returns
one value per frame (B,), so frames stay independent unless a term couples them on purpose
(:func:`smoothness`).

Sign convention of the surface residuals: positive when the cloud lies *outside* the body
(along the outward normal), which is where clothing puts it.
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = [
    "bone_orientation_prior", "clothing_residual", "geman_mcclure", "plane_cost", "smoothness",
    "surface_cost", "vertex_normals", "visible_vertices",
]


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(B,V,3) unit area-weighted vertex normals of meshes (B,V,3) with faces (F,3) long."""
    tri = vertices[:, faces]  # (B,F,3,3)
    fn = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0], dim=-1)
    vn = torch.zeros_like(vertices)
    for k in range(3):
        vn.index_add_(1, faces[:, k], fn)
    return torch.nn.functional.normalize(vn, dim=-1)


def visible_vertices(vertices: torch.Tensor, normals: torch.Tensor,
                     cameras: torch.Tensor | None) -> torch.Tensor:
    """(B,V) bool: the vertex's normal faces at least one camera centre (C,3), i.e. the side
    the cameras could have seen (self-occlusion is not tested). All True without cameras."""
    if cameras is None:
        return torch.ones(vertices.shape[:2], dtype=torch.bool, device=vertices.device)
    # (c - v) · n > 0  <=>  c · n > v · n: no (B,V,C,3) of vectors to the cameras; (C,3) @
    # (B,3,V) is one product without a copy when the meshes are views of (B,3,V) tensors
    # (as Skinner.posed_mesh gives them)
    facing = cameras.to(normals.dtype) @ normals.transpose(-1, -2)  # (B,C,V)
    return (facing > (vertices * normals).sum(-1)[:, None]).any(1)


def geman_mcclure(r: torch.Tensor, sigma: float) -> torch.Tensor:
    """Robust cost x²/(1 + x²) of x = r/sigma: ~x² for small residuals, at most 1."""
    x2 = (r / sigma).square()
    return x2 / (1.0 + x2)


def clothing_residual(r: torch.Tensor, margin: float) -> torch.Tensor:
    """Signed surface residual (positive: cloud outside the body) with a clothing allowance:
    a point up to ``margin`` metres outside the body costs nothing, one inside the body costs
    in full (clothes only add to the body), farther out costs the excess over ``margin``."""
    if margin <= 0:
        return r
    return r - torch.clamp(r, 0.0, margin)


def surface_cost(cloud: torch.Tensor, body: torch.Tensor, normal: torch.Tensor,
                 weight: torch.Tensor, *, sigma: float, margin: float = 0.0) -> torch.Tensor:
    """Robust point-to-plane cost of paired cloud points and body vertices, both directions.

    For cloud → body pairs ``normal`` is the body vertex's normal (point-to-plane ICP); for
    visible body → cloud pairs it is the point's normal (facing the camera that saw it), or the
    vertex normal when the cloud has none. Either way it points out of the body, so the residual
    ``r = (cloud − body) · normal`` is positive where the cloud lies outside the body.

    Args:
        cloud: (B,K,3) cloud point of each pair; body: (B,K,3) its body vertex (differentiable).
        normal: (B,K,3) unit normals, held fixed between correspondence searches.
        weight: (B,K) each pair's weight (0: the pair does not count; 1/count of the valid
            pairs for a mean, as :func:`couch.fitting.body.find_pairs` sets them).
        sigma: robust scale (m); margin: clothing allowance (m), see :func:`clothing_residual`.

    Returns:
        (B,) Σ weight · Geman-McClure(residual) per frame.
    """
    return plane_cost(normal.transpose(1, 2), (cloud * normal).sum(-1), body.transpose(1, 2),
                      weight, sigma=sigma, margin=margin)


def plane_cost(normal: torch.Tensor, offset: torch.Tensor, body: torch.Tensor,
               weight: torch.Tensor, *, sigma: float, margin: float = 0.0) -> torch.Tensor:
    """:func:`surface_cost` with each pair's plane precomputed and xyz first: the residual is
    ``offset − normal · body`` with ``offset = normal · cloud``, fixed between correspondence
    searches, so an iteration spends one product and a three-row sum per pair.

    Args:
        normal: (B,3,K) unit normals; offset: (B,K) metres, normal · cloud point.
        body: (B,3,K) the pairs' body vertices (differentiable).
        weight: (B,K) each pair's weight (0: the pair does not count).
        sigma: robust scale (m); margin: clothing allowance (m), see :func:`clothing_residual`.

    Returns:
        (B,) Σ weight · Geman-McClure(residual) per frame.

    The gradient reaches ``body`` through a hand-written backward (one product per pair instead
    of autograd's chain of some ten element-wise passes over the pairs, ~3x faster); when
    ``normal``, ``offset`` or ``weight`` need a gradient too, plain autograd is used.
    """
    if not (normal.requires_grad or offset.requires_grad or weight.requires_grad):
        return _PlaneCost.apply(normal, offset, body, weight, sigma, margin)
    r = offset - (body * normal).sum(1)
    return (weight * geman_mcclure(clothing_residual(r, margin), sigma)).sum(-1)


class _PlaneCost(torch.autograd.Function):
    """:func:`plane_cost` with its gradient w.r.t. ``body`` only. With e the clothing residual
    and c = e², the cost per pair is w·c/(c + σ²) and its derivative by the residual
    w·2eσ²/(c + σ²)² (the clothing band, where e = 0, has zero derivative either way); the
    residual's derivative by the body vertex is −normal."""

    @staticmethod
    def forward(ctx: Any, normal: torch.Tensor, offset: torch.Tensor, body: torch.Tensor,
                weight: torch.Tensor, sigma: float, margin: float) -> torch.Tensor:
        e = clothing_residual(offset - (body * normal).sum(1), margin)
        c = e * e
        denom = c + sigma * sigma
        ctx.save_for_backward(normal, weight * e / denom.square() * (2.0 * sigma * sigma))
        return (weight * (c / denom)).sum(-1)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        normal, slope = ctx.saved_tensors
        return None, None, normal * (slope * -grad[:, None])[:, None], None, None, None


def bone_orientation_prior(orient: torch.Tensor, orient0: torch.Tensor, sigma: float,
                           weights: torch.Tensor | None = None) -> torch.Tensor:
    """Keeps every bone's world orientation near the initial (IMU) one.

    Args:
        orient: (B,J,3,3) world rotations of the joints (e.g. ``joint_transforms[..., :3, :3]``).
        orient0: (B,J,3,3) the initial ones.
        sigma: expected error of the initial orientations (radians).
        weights: (J,) per-joint weights (default 1).

    Returns:
        (B,) Σ_j w_j (θ_j/σ)², with θ² ≈ ‖R − R0‖²_F / 2 (chordal, smooth at θ = 0).
    """
    chord = (orient - orient0).square().sum(dim=(-1, -2)) / 2.0  # (B,J) ≈ θ²
    if weights is not None:
        chord = chord * weights
    return chord.sum(-1) / sigma ** 2


def smoothness(local: torch.Tensor, transl: torch.Tensor, sigma_rot: float,
               sigma_transl: float) -> torch.Tensor:
    """Temporal smoothness of consecutive frames (the only term that couples frames).

    Args:
        local: (B,J,3,3) local joint rotations of B consecutive frames; transl: (B,3).
        sigma_rot: radians, sigma_transl: metres, the expected frame-to-frame change.

    Returns:
        (B,) cost, the pair (t, t+1) charged to frame t (0 for the last frame).
    """
    if len(local) < 2:
        return local.new_zeros(len(local))
    rot = (local[1:] - local[:-1]).square().sum(dim=(-1, -2, -3)) / 2.0 / sigma_rot ** 2
    tr = (transl[1:] - transl[:-1]).square().sum(-1) / sigma_transl ** 2
    return torch.cat([rot + tr, local.new_zeros(1)])
