"""Linear blend skinning for SMPL-format body models: small pure functions over batched tensors.

Shapes: B batch, V vertices, J joints (24), K shape coefficients. Units: metres, radians.
Rotations are local (relative to the parent joint, in the rest frame), as in SMPL.
"""

from __future__ import annotations

import torch


def blend_shapes(betas: torch.Tensor, shapedirs: torch.Tensor) -> torch.Tensor:
    """Shape offsets: ``betas`` (B,K) · ``shapedirs`` (V,3,K) → (B,V,3)."""
    return torch.einsum("bk,vik->bvi", betas, shapedirs)


def vertices_to_joints(regressor: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """Joint locations: ``regressor`` (J,V) applied to ``vertices`` (B,V,3) → (B,J,3)."""
    return torch.einsum("jv,bvi->bji", regressor, vertices)


def rigid_transforms(rot_mats: torch.Tensor, joints: torch.Tensor,
                     parents: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward kinematics.

    Args:
        rot_mats: (B,J,3,3) local joint rotations (joint 0 is the global orientation).
        joints: (B,J,3) rest joint locations.
        parents: (J,) parent index per joint, -1 for the root; parents precede children.
    Returns:
        posed_joints: (B,J,3) joint locations after posing (root at its rest location).
        rel_transforms: (B,J,4,4) transforms taking rest-pose points (in model coordinates) to
            posed ones for points rigidly attached to each joint: ``G_j · [I | −J_j]``.
    """
    b, nj = joints.shape[:2]
    rel_joints = joints.clone()
    rel_joints[:, 1:] -= joints[:, parents[1:]]
    local = torch.cat([rot_mats, rel_joints[..., None]], dim=-1)
    bottom = joints.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(b, nj, 1, 4)
    local = torch.cat([local, bottom], dim=-2)
    # unbind, not local[:, j]: each indexing's backward would zero a whole (B,J,4,4) gradient
    # (over a long sequence that was a third of the fusion's time)
    parts = local.unbind(1)
    chain = [parts[0]]
    for j in range(1, nj):
        chain.append(chain[int(parents[j])] @ parts[j])
    world = torch.stack(chain, dim=1)
    posed_joints = world[..., :3, 3]
    # Subtract the rotated rest location so each transform acts on rest-pose model coordinates.
    offset = torch.einsum("bjik,bjk->bji", world[..., :3, :3], joints)
    rel = world.clone()
    rel[..., :3, 3] = posed_joints - offset
    return posed_joints, rel


def lbs(betas: torch.Tensor, rot_mats: torch.Tensor, v_template: torch.Tensor,
        shapedirs: torch.Tensor, posedirs: torch.Tensor | None, regressor: torch.Tensor,
        parents: torch.Tensor, weights: torch.Tensor
        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pose and shape a body.

    Args:
        betas: (B,K) shape coefficients.
        rot_mats: (B,J,3,3) local rotations, joint 0 = global orientation.
        v_template: (V,3) template in the rest pose.
        shapedirs: (V,3,K) shape directions.
        posedirs: (P,V*3) pose-corrective directions over the flattened (R_j − I) of joints
            1..J-1 (P = 9·(J−1)), or None for a model without pose correctives.
        regressor: (J,V) joint regressor.
        parents: (J,) parent table.
        weights: (V,J) skinning weights, rows summing to 1.
    Returns:
        vertices (B,V,3), joints (B,J,3), joint world transforms (B,J,4,4) (rotation and posed
        joint location; before any global translation).
    """
    v_shaped = v_template + blend_shapes(betas, shapedirs)
    joints_rest = vertices_to_joints(regressor, v_shaped)
    if posedirs is not None:
        eye = torch.eye(3, dtype=rot_mats.dtype, device=rot_mats.device)
        pose_feature = (rot_mats[:, 1:] - eye).flatten(1)
        v_shaped = v_shaped + (pose_feature @ posedirs).view(v_shaped.shape)
    posed_joints, rel = rigid_transforms(rot_mats, joints_rest, parents)
    # Blend the 3x4 part only; the bottom row of every transform is (0,0,0,1).
    b, nj = rot_mats.shape[:2]
    blended = (weights @ rel[..., :3, :].reshape(b, nj, 12)).view(b, -1, 3, 4)
    vertices = (blended[..., :3] * v_shaped[..., None, :]).sum(-1) + blended[..., 3]
    world = rel.clone()
    world[..., :3, 3] = posed_joints
    return vertices, posed_joints, world
