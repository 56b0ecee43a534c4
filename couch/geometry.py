"""Rigid transforms (building, inverting, applying, fitting and averaging 4x4 poses), mesh
surface sampling and analytic two-bone limb IK.

Transforms are ``(..., 4, 4)`` float arrays mapping column vectors of the source frame into the
target frame (``world_from_object`` maps object coordinates into world coordinates), metres.
numpy only: these serve registration and averaging on CPU; networks use :mod:`couch.rotations`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
from scipy.spatial.transform import Rotation

from couch.rotations import rotation_angle


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` rotation and ``(..., 3)`` translation → ``(..., 4, 4)`` transform."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    lead = rotation.shape[:-2]
    if lead != translation.shape[:-1]:  # broadcast_shapes costs more than the rest per call
        lead = np.broadcast_shapes(lead, translation.shape[:-1])
    out = np.zeros((*lead, 4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def invert_transform(transform: np.ndarray) -> np.ndarray:
    """Inverse of rigid ``(..., 4, 4)`` transforms (uses R^T, not a general inverse)."""
    r = np.swapaxes(transform[..., :3, :3], -1, -2)
    return make_transform(r, -np.einsum("...ij,...j->...i", r, transform[..., :3, 3]))


def apply_transform(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``(..., 4, 4)`` transforms to ``(..., N, 3)`` points → ``(..., N, 3)``."""
    return (np.einsum("...ij,...nj->...ni", transform[..., :3, :3], points)
            + transform[..., None, :3, 3])


def fit_rigid_transform(source: np.ndarray, target: np.ndarray,
                        weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rigid transform (Kabsch) taking ``(N, 3)`` source onto ``(N, 3)`` target.

    Returns the ``(4, 4)`` transform ``T`` minimising ``Σ w_i |T·s_i − t_i|²``; needs N >= 3
    non-collinear points.
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3:
        raise ValueError(f"source and target must both be (N, 3); got {source.shape} and "
                         f"{target.shape}")
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    cs, ct = w @ source, w @ target
    rot, _ = Rotation.align_vectors(target - ct, source - cs, weights=w)
    r = rot.as_matrix()
    return make_transform(r, ct - r @ cs)


def average_transforms(transforms: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Average of ``(N, 4, 4)`` rigid transforms → ``(4, 4)``.

    Rotation: the chordal L2 mean (scipy's ``Rotation.mean``, the quaternion eigenvector method);
    translation: the weighted arithmetic mean. ``weights`` ``(N,)`` are non-negative confidences.
    """
    transforms = np.asarray(transforms, dtype=np.float64)
    if transforms.ndim != 3 or transforms.shape[1:] != (4, 4) or len(transforms) == 0:
        raise ValueError(f"expected (N, 4, 4) transforms with N >= 1, got {transforms.shape}")
    w = np.ones(len(transforms)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(transforms),) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("weights must be (N,), non-negative and not all zero")
    r = Rotation.from_matrix(transforms[:, :3, :3]).mean(weights=w).as_matrix()
    return make_transform(r, (w / w.sum()) @ transforms[:, :3, 3])


def transform_distance(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation angle (radians) and translation distance (metres) between ``(..., 4, 4)`` poses."""
    rel = np.swapaxes(a[..., :3, :3], -1, -2) @ b[..., :3, :3]
    return rotation_angle(rel), np.linalg.norm(a[..., :3, 3] - b[..., :3, 3], axis=-1)


def look_at(eye: np.ndarray, target: np.ndarray,
            up: np.ndarray | tuple[float, float, float] = (0.0, 1.0, 0.0)) -> np.ndarray:
    """``(4, 4)`` world-from-camera pose of an OpenCV-convention camera (+Z forward, +Y down,
    +X right in the image) at ``eye`` looking at ``target``; ``up`` is the world's up direction."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to 'up'")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return make_transform(np.stack([right, down, forward], axis=1), eye)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(…,V,3) area-weighted unit vertex normals of meshes sharing ``faces`` (F,3)."""
    vertices = np.asarray(vertices)
    faces = np.asarray(faces, dtype=np.int64)
    nv, nf = vertices.shape[-2], len(faces)
    flat = vertices.reshape(-1, nv, 3)
    # Summing face normals into their vertices is a product with the (V,F) incidence matrix
    # (np.add.at is several times slower).
    incidence = scipy.sparse.csr_matrix(
        (np.ones(3 * nf, dtype=flat.dtype), (faces.T.reshape(-1), np.tile(np.arange(nf), 3))),
        shape=(nv, nf))
    out = np.empty(flat.shape, dtype=np.result_type(flat.dtype, np.float32))
    # Chunks of meshes, vertex-major (V,n,3) so the face gathers read contiguous rows: the
    # intermediates stay a few MB instead of 3x(F,T,3) for a whole session.
    chunk = 16
    for s in range(0, len(flat), chunk):
        vt = np.ascontiguousarray(flat[s:s + chunk].transpose(1, 0, 2))
        a = vt[faces[:, 1]] - vt[faces[:, 0]]
        b = vt[faces[:, 2]] - vt[faces[:, 0]]
        fn = np.empty_like(a)  # a × b written out: np.cross copies through moveaxis, ~15x slower
        fn[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
        fn[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
        fn[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
        out[s:s + chunk] = (incidence @ fn.reshape(nf, -1)).reshape(vt.shape).transpose(1, 0, 2)
    out /= np.maximum(np.linalg.norm(out, axis=-1, keepdims=True), 1e-12)
    return out.reshape(vertices.shape)


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``(n, 3)`` area-uniform random points on a triangle mesh and ``(n, 3)`` the unit normals
    of their faces (winding order: counter-clockwise seen from outside is outward).

    Args:
        vertices: ``(V, 3)``; faces: ``(F, 3)`` int, at least one with non-zero area.
        n: number of samples; seed: of the random generator (reproducible samples).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    # corners gathered one column at a time and the cross product written out: contiguous
    # arrays, the same numbers as np.cross on a (F,3,3) gather at a third of the time
    a = v[f[:, 0]]
    e1, e2 = v[f[:, 1]] - a, v[f[:, 2]] - a
    cross = np.stack([e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1],
                      e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
                      e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]], axis=1)
    area = np.linalg.norm(cross, axis=1)
    if not area.sum() > 0:
        raise ValueError("sample_surface: the mesh has no area")
    rng = np.random.default_rng(seed)
    face = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = rng.random((2, n, 1))
    s = np.sqrt(r1)
    corner = v[f[face]]  # (n,3,3)
    points = (1 - s) * corner[:, 0] + s * (1 - r2) * corner[:, 1] + s * r2 * corner[:, 2]
    return points, cross[face] / area[face, None]


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis (zero vectors stay zero)."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12)


def two_bone_ik(root: np.ndarray, target: np.ndarray, pole: np.ndarray, len_upper: float,
                len_lower: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Middle-joint position of a two-bone chain reaching ``target`` from ``root``.

    Args:
        root, target, pole: (T,3); the middle joint bends towards ``pole`` (a direction).
    Returns:
        middle (T,3), the unit directions of the upper and lower bones (T,3) each, and the
        unit hinge axis (T,3) of the chain's plane, ``root→target × bend direction``: it is
        perpendicular to both bones, so (unlike ``pole``, which can line up with a bone) it
        fixes their twist without ambiguity.
        Targets out of reach are clamped to 99.9% of full extension along the same line.
    """
    to_target = target - root
    dist = np.linalg.norm(to_target, axis=-1, keepdims=True)
    e = to_target / np.maximum(dist, 1e-9)
    d = np.clip(dist, abs(len_upper - len_lower) + 1e-4, 0.999 * (len_upper + len_lower))
    cos_a = np.clip((len_upper**2 + d**2 - len_lower**2) / (2 * len_upper * d), -1, 1)
    bend = normalize(pole - (pole * e).sum(-1, keepdims=True) * e)
    middle = root + len_upper * (cos_a * e + np.sqrt(1 - cos_a**2) * bend)
    end = root + e * d
    hinge = normalize(np.cross(e, bend))
    return middle, normalize(middle - root), normalize(end - middle), hinge
