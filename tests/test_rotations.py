"""Rotation conversions: round trips (hypothesis), torch against scipy, 6D, slerp, gradients."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from couch import rotations as R

finite = st.floats(-1.0, 1.0, allow_nan=False, width=64)
quats = arrays(np.float64, (5, 4), elements=finite).filter(
    lambda q: np.all(np.linalg.norm(q, axis=1) > 0.1))
# axis-angle with |θ| < π (at exactly π the axis sign is ambiguous)
aas = arrays(np.float64, (5, 3), elements=st.floats(-1.7, 1.7, allow_nan=False, width=64))


def _same_rotation(a: np.ndarray, b: np.ndarray, tol: float = 1e-6) -> bool:
    return np.allclose(R.axis_angle_to_matrix(a), R.axis_angle_to_matrix(b), atol=tol)


@settings(max_examples=60, deadline=None)
@given(aas)
def test_axis_angle_round_trips_numpy_and_torch(aa):
    assert np.allclose(R.matrix_to_axis_angle(R.axis_angle_to_matrix(aa)), aa, atol=1e-7)
    assert np.allclose(R.quat_to_axis_angle(R.axis_angle_to_quat(aa)), aa, atol=1e-7)
    t = torch.as_tensor(aa)
    assert torch.allclose(R.matrix_to_axis_angle(R.axis_angle_to_matrix(t)), t, atol=1e-6)
    assert torch.allclose(R.quat_to_axis_angle(R.axis_angle_to_quat(t)), t, atol=1e-7)
    assert torch.allclose(R.sixd_to_axis_angle(R.axis_angle_to_6d(t)), t, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(quats)
def test_quaternion_round_trip_and_torch_matches_scipy(q):
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(q[:, :1] < 0, -q, q)
    m_ref = Rotation.from_quat(q, scalar_first=True).as_matrix()
    m_torch = R.quat_to_matrix(torch.as_tensor(q)).numpy()
    assert np.allclose(m_torch, m_ref, atol=1e-10)
    # equal up to sign (q and −q are one rotation; w >= 0 leaves the sign open only at w = 0)
    for q_back in (R.matrix_to_quat(torch.as_tensor(m_ref)).numpy(), R.matrix_to_quat(m_ref)):
        assert np.allclose(np.abs((q_back * q).sum(1)), 1.0, atol=1e-9)
        assert np.all(q_back[:, 0] >= 0)


@settings(max_examples=40, deadline=None)
@given(arrays(np.float64, (4, 6), elements=finite).filter(
    lambda d: np.all(np.linalg.norm(np.cross(d[:, :3], d[:, 3:]), axis=1) > 0.05)))
def test_6d_gives_rotations_and_is_identity_on_rotations(d6):
    m = R.sixd_to_matrix(d6)
    assert np.allclose(m @ np.swapaxes(m, -1, -2), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(m), 1.0)
    assert np.allclose(R.sixd_to_matrix(R.matrix_to_6d(m)), m, atol=1e-9)
    mt = R.sixd_to_matrix(torch.as_tensor(d6)).numpy()
    assert np.allclose(mt, m, atol=1e-9)


def test_matrix_to_quat_near_180_degrees_is_stable():
    aa = np.array([[np.pi - 1e-7, 0, 0], [0, 0, np.pi - 1e-9], [2.0, 2.0, 0.0]])
    m = torch.as_tensor(R.axis_angle_to_matrix(aa))
    assert torch.allclose(R.quat_to_matrix(R.matrix_to_quat(m)), m, atol=1e-7)


def test_batched_leading_dimensions_and_dtypes():
    aa = torch.randn(2, 7, 24, 3, dtype=torch.float32)
    m = R.axis_angle_to_matrix(aa)
    assert m.shape == (2, 7, 24, 3, 3) and m.dtype == torch.float32
    assert R.axis_angle_to_matrix(aa.numpy()).shape == (2, 7, 24, 3, 3)


def test_gradients_are_finite_at_identity():
    aa = torch.zeros(3, 3, dtype=torch.float64, requires_grad=True)
    R.axis_angle_to_matrix(aa).sum().backward()
    assert torch.isfinite(aa.grad).all()
    m = torch.eye(3, dtype=torch.float64).expand(2, 3, 3).clone().requires_grad_(True)
    R.matrix_to_axis_angle(m).sum().backward()
    assert torch.isfinite(m.grad).all()


def test_axis_angle_to_matrix_matches_rodrigues_by_hand():
    # 90 degrees about +Y takes +X to −Z (right-handed)
    m = R.axis_angle_to_matrix(torch.tensor([0.0, np.pi / 2, 0.0], dtype=torch.float64))
    assert torch.allclose(m @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                          torch.tensor([0.0, 0, -1], dtype=torch.float64), atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(quats, st.floats(0.0, 1.0))
def test_slerp_endpoints_constant_speed_and_numpy_matches_torch(q, t):
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    q0, q1 = q[:2], q[2:4]
    # 180 degrees apart, both ways round are shortest: slerp's midpoint is then not unique
    assume(np.all(np.abs((q0 * q1).sum(1)) > 1e-3))
    for a, b in ((q0, q1),):
        qt = R.slerp(a, b, t)
        m = R.quat_to_matrix(qt)
        total = R.rotation_angle(np.swapaxes(R.quat_to_matrix(a), -1, -2) @ R.quat_to_matrix(b))
        part = R.rotation_angle(np.swapaxes(R.quat_to_matrix(a), -1, -2) @ m)
        assert np.allclose(part, t * total, atol=1e-6)
        qt_torch = R.slerp(torch.as_tensor(a), torch.as_tensor(b), t).numpy()
        assert np.allclose(R.quat_to_matrix(qt_torch), m, atol=1e-6)
    assert np.allclose(R.quat_to_matrix(R.slerp(q0, q1, 0.0)), R.quat_to_matrix(q0), atol=1e-9)
    assert np.allclose(R.quat_to_matrix(R.slerp(q0, q1, 1.0)), R.quat_to_matrix(q1), atol=1e-9)


def test_quat_multiply_composes_like_matrices():
    rng = np.random.default_rng(0)
    a, b = Rotation.random(6, rng=rng), Rotation.random(6, rng=rng)
    qa, qb = a.as_quat(scalar_first=True), b.as_quat(scalar_first=True)
    for prod in (R.quat_multiply(qa, qb), R.quat_multiply(torch.as_tensor(qa),
                                                         torch.as_tensor(qb)).numpy()):
        assert np.allclose(R.quat_to_matrix(prod), a.as_matrix() @ b.as_matrix(), atol=1e-9)
