"""Linear blend skinning for SMPL-format body models: small pure functions over batched tensors.

Shapes: B batch, V vertices, J joints (24), K shape coefficients. Units: metres, radians.
Rotations are local (relative to the parent joint, in the rest frame), as in SMPL.
"""

from __future__ import annotations

import functools

import numpy as np
import torch


def blend_shapes(betas: torch.Tensor, shapedirs: torch.Tensor) -> torch.Tensor:
    """Shape offsets: ``betas`` (B,K) · ``shapedirs`` (V,3,K) → (B,V,3)."""
    return torch.einsum("bk,vik->bvi", betas, shapedirs)


def vertices_to_joints(regressor: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """Joint locations: ``regressor`` (J,V) applied to ``vertices`` (B,V,3) → (B,J,3)."""
    return torch.einsum("jv,bvi->bji", regressor, vertices)


@functools.lru_cache(maxsize=16)
def _kinematic_levels(parents: tuple[int, ...]
                      ) -> tuple[tuple[tuple[slice | torch.Tensor, torch.Tensor | None], ...],
                                 torch.Tensor | None]:
    """The joints by depth in the tree: per depth, the joints (a slice when they are
    consecutive, as SMPL's are) and each one's parent's place in the depth above (None when
    they are that depth's joints in order); and the permutation back to joint order (None when
    the depths' concatenation is already in joint order)."""
    n = len(parents)
    depth = [0] * n
    for j in range(1, n):  # parents precede their children
        depth[j] = depth[parents[j]] + 1
    levels = [[j for j in range(n) if depth[j] == d] for d in range(max(depth) + 1)]
    plan = []
    for d, joints in enumerate(levels):
        sel: slice | torch.Tensor = (slice(joints[0], joints[-1] + 1)
                                     if joints == list(range(joints[0], joints[-1] + 1))
                                     else torch.tensor(joints))
        gather = None
        if d:
            above = levels[d - 1]
            where = [above.index(parents[j]) for j in joints]
            gather = None if where == list(range(len(above))) else torch.tensor(where)
        plan.append((sel, gather))
    order = [j for joints in levels for j in joints]
    inverse = None if order == list(range(n)) else torch.tensor(np.argsort(order))
    return tuple(plan), inverse


def _joints_of(x: torch.Tensor, sel: slice | torch.Tensor) -> torch.Tensor:
    return x[:, sel] if isinstance(sel, slice) else x.index_select(1, sel.to(x.device))


def forward_kinematics(rot_mats: torch.Tensor, joints: torch.Tensor, parents: torch.Tensor,
                       transl: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward kinematics to skinning transforms.

    Args:
        rot_mats: (B,J,3,3) local joint rotations (joint 0 is the global orientation).
        joints: (B,J,3) rest joint locations.
        parents: (J,) parent index per joint, -1 for the root (joint 0, the only one);
            parents precede children.
        transl: (B,3) translation added to the whole body, or None.
    Returns:
        posed_joints: (B,J,3) joint locations after posing (root at its rest location, plus
            ``transl``).
        transforms: (B,J,3,4) ``[R_j | t_j]`` taking rest-pose points (in model coordinates) to
            posed ones for points rigidly attached to each joint: ``G_j · [I | −J_j]``, with
            R_j the joint's world rotation.
    """
    plan, inverse = _kinematic_levels(tuple(int(p) for p in parents.tolist()))
    offsets = torch.cat([joints[:, :1], joints[:, 1:] - joints[:, parents[1:]]], 1)[..., None]
    # a whole depth of the tree per product, 9 products for SMPL's 23 joints: with its
    # gradient a third faster than a product per joint
    rots: list[torch.Tensor] = []
    points: list[torch.Tensor] = []
    for sel, gather in plan:
        r, off = _joints_of(rot_mats, sel), _joints_of(offsets, sel)
        if not rots:
            rots.append(r)
            points.append(off[..., 0])
            continue
        above_r, above_p = rots[-1], points[-1]
        if gather is not None:
            g = gather.to(rot_mats.device)
            above_r, above_p = above_r.index_select(1, g), above_p.index_select(1, g)
        rots.append(above_r @ r)
        points.append(above_p + (above_r @ off)[..., 0])
    world, posed = torch.cat(rots, 1), torch.cat(points, 1)
    if inverse is not None:
        inv = inverse.to(rot_mats.device)
        world, posed = world.index_select(1, inv), posed.index_select(1, inv)
    if transl is not None:
        posed = posed + transl[:, None]
    # subtract the rotated rest location so each transform acts on rest-pose model coordinates
    t = posed - (world @ joints[..., None])[..., 0]
    return posed, torch.cat([world, t[..., None]], -1)


def rigid_transforms(rot_mats: torch.Tensor, joints: torch.Tensor,
                     parents: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward kinematics: :func:`forward_kinematics` without a translation, its transforms
    as (B,J,4,4) homogeneous matrices.

    Args:
        rot_mats: (B,J,3,3) local joint rotations (joint 0 is the global orientation).
        joints: (B,J,3) rest joint locations.
        parents: (J,) parent index per joint, -1 for the root; parents precede children.
    Returns:
        posed_joints: (B,J,3) joint locations after posing (root at its rest location).
        rel_transforms: (B,J,4,4) transforms taking rest-pose points (in model coordinates) to
            posed ones for points rigidly attached to each joint: ``G_j · [I | −J_j]``.
    """
    posed, transforms = forward_kinematics(rot_mats, joints, parents)
    b, nj = joints.shape[:2]
    bottom = joints.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(b, nj, 1, 4)
    return posed, torch.cat([transforms, bottom], dim=-2)


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
