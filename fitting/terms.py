"""Objective terms of the body fit: small functions over frame-batched tensors.

Shapes: B frames, V mesh vertices, N cloud points, J = 24 joints. Units: metres and radians;
every data term is dimensionless (residuals over a robust scale ``sigma``), every term returns
one value per frame (B,), so frames stay independent unless a term couples them on purpose
(:func:`smoothness`).

Sign convention of the surface residuals: positive when the cloud lies *outside* the body
(along the outward normal), which is where clothing puts it.
"""

from __future__ import annotations

import torch

__all__ = [
    "bone_orientation_prior", "clothing_residual", "geman_mcclure", "smoothness",
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
    to_cam = cameras[None, None] - vertices[:, :, None]  # (B,V,C,3)
    return (torch.einsum("bvck,bvk->bvc", to_cam, normals) > 0).any(-1)


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
    r = ((cloud - body) * normal).sum(-1)
    return (weight * geman_mcclure(clothing_residual(r, margin), sigma)).sum(-1)


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
