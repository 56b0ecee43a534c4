"""Linear blend skinning of *selected* vertices, for fitting.

A fit only needs the vertices that take part in its terms (a few thousand per frame: the nearest
vertices of the cloud points and a sample of the visible surface), not the whole mesh; and with
one shape shared by all frames, the shaped rest mesh and rest joints are computed once per
iteration, not once per frame. :class:`Skinner` does both, with the same maths as
:func:`couch.body.lbs.lbs` (which it calls for forward kinematics), so ``Skinner`` and
``BodyModel.forward`` give the same vertices.

Without pose correctives, a posed vertex is Σ_j w_vj A_j [v; 1], linear in the frame's skinning
transforms A (3×4 each): so vertices are posed as products of the transforms side by side,
(B,3,J·4) (:meth:`Skinner.transform_matrix`), with weighted homogeneous rest positions,
(J·4,M): per frame for a selection (:meth:`Skinner.select`, :meth:`Skinner.vertices`), or one
(J·4,V) matrix for the whole mesh shared by all frames (:meth:`Skinner.rest_matrix`,
:meth:`Skinner.mesh`, :meth:`Skinner.posed_mesh`), a single large product that runs several
times faster per vertex than a per-frame one.

Shapes: B frames, V vertices, M selected vertices per frame, J = 24 joints. Metres.
"""

from __future__ import annotations

import dataclasses

import torch

from couch.body import BodyModel
from couch.body.lbs import blend_shapes, forward_kinematics, vertices_to_joints
from couch.fitting.terms import vertex_normals

__all__ = ["Posed", "Skinner"]


@dataclasses.dataclass
class Posed:
    """Posed skeletons of B frames.

    transforms: (B,J,12) flattened 3×4 skinning transforms (rest model coordinates → world,
    translation included); joints: (B,J,3) world joints; orient: (B,J,3,3) world rotations of
    the joints; pose_offsets: (B,V,3) pose-corrective offsets, or None for a model without them.
    """

    transforms: torch.Tensor
    joints: torch.Tensor
    orient: torch.Tensor
    pose_offsets: torch.Tensor | None


def _rows(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``x[index]`` for (N,C) ``x`` and an index of any shape -> (*index.shape, C), by
    ``index_select``: the gradient of ``x[index]`` is summed with parallel atomic adds on a
    CPU with several threads, in a different order each time (a fit then differs from run to
    run in the last bits, ~1e-7 in the betas), while ``index_select``'s is summed in order."""
    return x.index_select(0, index.reshape(-1)).view(*index.shape, x.shape[1])


class Skinner:
    """Poses a body model's vertices (all, or a per-frame selection) for one shared shape."""

    def __init__(self, model: BodyModel) -> None:
        self.model = model
        self.faces = torch.as_tensor(model.faces, device=model.device)
        # (J,V) weights, joint-major: the products below built from them come out contiguous
        self.weights_t = model.weights.T.contiguous()

    @property
    def num_vertices(self) -> int:
        return self.model.num_vertices

    def rest(self, betas: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Shaped rest mesh (V,3) and rest joints (J,3) of shape ``betas`` (K,)."""
        m = self.model
        v_shaped = m.v_template + blend_shapes(betas[None], m.shapedirs)[0]
        return v_shaped, vertices_to_joints(m.J_regressor, v_shaped[None])[0]

    def pose(self, local: torch.Tensor, rest_joints: torch.Tensor, transl: torch.Tensor
             ) -> Posed:
        """Forward kinematics of B frames.

        Args:
            local: (B,J,3,3) local rotations (joint 0 = global orientation).
            rest_joints: (J,3) from :meth:`rest`.
            transl: (B,3) world translations.
        """
        m = self.model
        b, nj = local.shape[:2]
        joints, rel = forward_kinematics(local, rest_joints.expand(b, nj, 3), m.parents, transl)
        offsets = None
        if m.posedirs is not None:
            eye = torch.eye(3, dtype=local.dtype, device=local.device)
            feature = (local[:, 1:] - eye).flatten(1)
            offsets = (feature @ m.posedirs).view(b, -1, 3)
        # world rotation of each joint: the rotation part of its skinning transform
        return Posed(transforms=rel.reshape(b, nj, 12), joints=joints,
                     orient=rel[..., :3], pose_offsets=offsets)

    def posed_mesh(self, posed: Posed, v_shaped: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """All posed vertices (B,V,3) and their normals (B,V,3): the rest mesh's vertex normals
        turned by each vertex's blended rotation (the usual LBS normal approximation; a few
        degrees off near bent joints, and far cheaper than re-deriving them from the faces).

        Without pose correctives both are one matrix product shared by all frames,
        (B·3,J·4) @ (J·4,V) (:meth:`rest_matrix`), returned as (B,V,3) views of (B,3,V)
        tensors: a single large product runs several times faster than blending a 3×4
        transform per vertex and frame."""
        m = self.model
        b, nj = posed.transforms.shape[:2]
        rest_n = vertex_normals(v_shaped[None], self.faces)[0]
        if posed.pose_offsets is None:
            t = self.transform_matrix(posed)  # (B,3,J·4)
            verts = self.mesh(t, self.rest_matrix(v_shaped))
            # rotations only: Σ_j w_vj R_j n_v as (B·3,J·3) @ (J·3,V)
            rot = t.view(b, 3, nj, 4)[..., :3].reshape(b * 3, nj * 3)
            rn = (self.weights_t[:, None, :] * rest_n.T[None]).reshape(nj * 3, -1)
            normals = (rot @ rn).view(b, 3, -1)
            # unit length; a sum over the short leading axis (vector_norm over it is slow)
            normals = normals * normals.square().sum(1, keepdim=True).clamp_min(1e-24).rsqrt()
            return verts.transpose(1, 2), normals.transpose(1, 2)
        v = v_shaped.expand(b, -1, -1) + posed.pose_offsets
        blended = (m.weights @ posed.transforms).view(b, -1, 3, 4)
        verts = (blended[..., :3] * v[..., None, :]).sum(-1) + blended[..., 3]
        normals = torch.nn.functional.normalize(
            (blended[..., :3] * rest_n[:, None, :]).sum(-1), dim=-1)
        return verts, normals

    def rest_matrix(self, v_shaped: torch.Tensor) -> torch.Tensor:
        """(J·4,V) skinning weights times homogeneous rest positions, w_vj · [v_v, 1], of all
        vertices: the right factor of :meth:`mesh` (the whole mesh's :meth:`select`, shared by
        all frames)."""
        w = self.weights_t  # (J,V)
        vh = torch.cat([v_shaped.T, torch.ones_like(v_shaped[:, :1]).T])  # (4,V)
        return (w[:, None] * vh[None]).flatten(0, 1)

    @staticmethod
    def transform_matrix(posed: Posed) -> torch.Tensor:
        """(B,3,J·4) the frames' skinning transforms side by side, [A_0 … A_J-1] (rows: world
        xyz), the left factor of :meth:`mesh` and :meth:`vertices`."""
        b, nj = posed.transforms.shape[:2]
        return posed.transforms.view(b, nj, 3, 4).permute(0, 2, 1, 3).reshape(b, 3, nj * 4)

    @staticmethod
    def mesh(transform: torch.Tensor, rest_matrix: torch.Tensor) -> torch.Tensor:
        """(B,3,V) all posed vertices, xyz first, of a model without pose correctives:
        ``transform`` (B,3,J·4) from :meth:`transform_matrix` times ``rest_matrix`` (J·4,V)
        from :meth:`rest_matrix`, one (B·3,J·4) @ (J·4,V) product for all frames."""
        b = transform.shape[0]
        return (transform.reshape(b * 3, -1) @ rest_matrix).view(b, 3, -1)

    def select(self, v_shaped: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """(B,J·4,M) skinning weights times homogeneous rest positions, w_vj · [v_v, 1], of the
        vertices ``index`` (B,M): gathered once, posed many times by one matrix product
        (:meth:`vertices` with ``selected``). Laid out with M last, the fastest layout for
        that product on CPU."""
        w = self.model.weights[index].transpose(1, 2)  # (B,J,M), gathered as rows of J
        v = _rows(v_shaped, index).permute(0, 2, 1)  # (B,3,M)
        vh = torch.cat([v, torch.ones_like(v[:, :1])], dim=1)  # (B,4,M)
        # written into a contiguous (B,J,4,M): the product would otherwise take the gathered
        # weights' transposed layout, and the flatten below would copy it
        out = w.new_empty(w.shape[0], w.shape[1], 4, w.shape[2])
        torch.mul(w[:, :, None], vh[:, None], out=out)
        return out.flatten(1, 2)

    def vertices(self, posed: Posed, v_shaped: torch.Tensor,
                 index: torch.Tensor | None = None, selected: torch.Tensor | None = None
                 ) -> torch.Tensor:
        """Posed vertices: all (B,V,3), or the selection ``index`` (B,M) → (B,M,3).

        ``selected``: :meth:`select` of the same ``index`` (then ``v_shaped`` is not read for
        the selection), for a model without pose correctives.
        """
        m = self.model
        b = posed.transforms.shape[0]
        if index is not None and selected is not None and posed.pose_offsets is None:
            # Σ_j w_j A_j [v; 1] as one product: (B,3,J·4) @ (B,J·4,M)
            return torch.bmm(self.transform_matrix(posed), selected).transpose(1, 2)
        if index is None:
            w, v = m.weights, v_shaped.expand(b, -1, -1)
            if posed.pose_offsets is not None:
                v = v + posed.pose_offsets
            blended = (w @ posed.transforms).view(b, -1, 3, 4)
        else:
            w, v = m.weights[index], _rows(v_shaped, index)
            if posed.pose_offsets is not None:
                v = v + torch.gather(posed.pose_offsets, 1, index[..., None].expand(-1, -1, 3))
            blended = torch.bmm(w, posed.transforms).view(b, -1, 3, 4)
        return (blended[..., :3] * v[..., None, :]).sum(-1) + blended[..., 3]
