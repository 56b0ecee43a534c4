"""Simulator chairs: clean labelled solids, landmarks that agree with the spec, room, I/O."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest
import trimesh

from couch.geometry import apply_transform, invert_transform
from couch.tools.sim.chairs import (
    KINDS,
    PART_NAMES,
    Chair,
    ChairSpec,
    chair_landmarks,
    load_mesh,
    make_chair,
    make_room,
    random_chair_spec,
    save_mesh,
    scan_pose,
    to_scan_frame,
    write_shapenet_layout,
)

EXPECTED_PARTS = {
    "straight": {"seat", "back", "base"},
    "armchair": set(PART_NAMES),
    "sofa": set(PART_NAMES),
    "stool": {"seat", "base"},
}


@pytest.fixture(scope="module")
def chairs() -> list[Chair]:
    """Per kind: the default chair and three random ones."""
    rng = np.random.default_rng(20240611)
    specs = [ChairSpec.for_kind(k) for k in KINDS]
    specs += [random_chair_spec(rng, k) for k in KINDS for _ in range(3)]
    return [make_chair(s) for s in specs]


def _closest(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Distance (N,) from points to the mesh surface and the closest face (N,), via open3d."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)),
                        o3d.core.Tensor(faces.astype(np.uint32)))
    ans = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    dist = np.linalg.norm(ans["points"].numpy() - points, axis=1)
    return dist, ans["primitive_ids"].numpy().astype(np.int64)


def test_spec_defaults_and_validation():
    for kind in KINDS:
        spec = ChairSpec.for_kind(kind)
        assert spec.has_back == (kind != "stool")
        assert spec.has_armrests == (kind in ("armchair", "sofa"))
    assert 0.43 <= ChairSpec.for_kind("straight").seat_height <= 0.47
    sofa = ChairSpec.for_kind("sofa")
    assert sofa.seat_depth >= 0.55 and 1.4 <= sofa.seat_width + 2 * sofa.armrest_width <= 2.2
    with pytest.raises(ValueError, match="kind"):
        ChairSpec.for_kind("throne")
    with pytest.raises(ValueError, match="back_height"):
        ChairSpec.for_kind("stool", back_height=0.4)
    with pytest.raises(ValueError, match="armrest_height"):
        ChairSpec.for_kind("armchair", armrest_height=None)
    with pytest.raises(ValueError, match="armrest_height"):
        ChairSpec.for_kind("sofa", armrest_height=0.6)
    rng = np.random.default_rng(0)
    assert {random_chair_spec(rng).kind for _ in range(40)} == set(KINDS)


def test_chairs_are_clean_labelled_solids(chairs):
    for chair in chairs:
        spec = chair.spec
        v, f = chair.vertices, chair.faces
        assert v.dtype == np.float64 and f.dtype == np.int64 and chair.face_parts.dtype == np.int8
        assert chair.face_parts.shape == (len(f),)
        mesh = trimesh.Trimesh(v, f, process=False)
        assert mesh.is_watertight and mesh.is_winding_consistent, spec
        assert mesh.volume > 0, f"inward-facing: {spec}"
        assert len(mesh.split(only_watertight=False)) == 1, spec
        o3d_mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v),
                                             o3d.utility.Vector3iVector(f))
        assert o3d_mesh.is_edge_manifold() and o3d_mesh.is_vertex_manifold(), spec
        assert len(f) <= 3000, f"{len(f)} faces is too heavy to ray cast per frame"
        assert abs(v[:, 1].min()) < 1e-9, "must stand on the floor"
        assert abs(v[:, 0].min() + v[:, 0].max()) < 1e-9, "must be centred on x = 0"
        labels = {PART_NAMES[p] for p in np.unique(chair.face_parts)}
        assert labels == EXPECTED_PARTS[spec.kind], spec
        # Labels sit where the parts are: left armrest at +X, backrest behind the seat.
        centroid = v[f].mean(axis=1)
        for part, sign in (("left_armrest", 1), ("right_armrest", -1)):
            if part in labels:
                assert np.all(sign * centroid[chair.part_faces(part), 0] > spec.seat_width / 2
                              - 1e-9)
        if "back" in labels:
            assert centroid[chair.part_faces("back"), 2].mean() < -spec.seat_depth / 2


def test_a_spec_builds_one_mesh_to_the_bit():
    # pymeshlab's union started a few faces at another corner from call to call (3-5 of a
    # sofa's faces over six builds in one process), which could flip a simulated draw
    spec = random_chair_spec(np.random.default_rng(11), "sofa")
    first = make_chair(spec)
    for _ in range(5):
        again = make_chair(spec)
        assert np.array_equal(again.vertices, first.vertices)
        assert np.array_equal(again.faces, first.faces)
        assert np.array_equal(again.face_parts, first.face_parts)


def test_landmarks_agree_with_spec(chairs):
    for chair in chairs:
        s, lm = chair.spec, chair.landmarks
        assert abs(lm.seat_height - s.seat_height) < 0.01, s
        assert abs(lm.seat_width - s.seat_width) < 0.01, s
        assert abs(lm.seat_depth - s.seat_depth) < 0.01, s
        assert np.allclose(lm.seat_center, [0.0, s.seat_height, 0.0], atol=0.01), s
        assert np.allclose(lm.seat_front, [0.0, s.seat_height, s.seat_depth / 2], atol=0.01), s
        assert lm.seat_normal[1] > 0.999
        if s.has_armrests:
            arm_top = s.seat_height + s.armrest_height
            assert abs(lm.left_armrest[1] - arm_top) < 0.01, s
            assert abs(lm.right_armrest[1] - arm_top) < 0.01, s
            assert lm.left_armrest[0] > s.seat_width / 2 > -s.seat_width / 2 > lm.right_armrest[0]
        else:
            assert lm.left_armrest is None and lm.right_armrest is None, s
        if s.has_back:
            assert abs(lm.back_top[1] - (s.seat_height + s.back_height)) < 0.01, s
            assert lm.back_top[2] < -s.seat_depth / 2 and abs(lm.back_top[0]) < 0.01
            assert lm.back_front[2] <= -s.seat_depth / 2 + 0.01
            assert s.seat_height + 0.1 < lm.back_front[1] < lm.back_top[1]
        else:
            assert lm.back_top is None and lm.back_front is None, s

        # Contact candidates lie on the surface of the part they name, normals outward.
        names = {c.name for c in lm.contacts}
        assert {"seat_front_left", "seat_front_right", "seat_front"} <= names, s
        assert ("left_armrest_top" in names) == s.has_armrests
        assert ("back_top" in names and "back_front" in names) == s.has_back
        points = np.array([c.point for c in lm.contacts])
        dist, face = _closest(chair.vertices, chair.faces, points)
        assert dist.max() < 1e-3, s
        for c, fid in zip(lm.contacts, face, strict=True):
            assert PART_NAMES[chair.face_parts[fid]] == c.part, (c.name, s)
            assert abs(np.linalg.norm(c.normal) - 1) < 1e-9
            # Outward: a step along the normal leaves the solid.
            outside = trimesh.Trimesh(chair.vertices, chair.faces, process=False).contains(
                (c.point + 0.003 * c.normal)[None])
            assert not outside[0], (c.name, s)


def test_landmarks_of_a_reordered_mesh_loaded_from_file(chairs, tmp_path):
    rng = np.random.default_rng(5)
    for chair in (c for c in chairs if c.spec.kind in ("armchair", "sofa")):
        perm = rng.permutation(len(chair.vertices))
        inverse = np.argsort(perm)
        faces = inverse[chair.faces][rng.permutation(len(chair.faces))]
        faces = np.roll(faces, 1, axis=1)   # same orientation, different first corner
        path = tmp_path / f"{chair.spec.kind}.obj"
        save_mesh(path, chair.vertices[perm], faces)
        v, f = load_mesh(path)
        assert not np.allclose(v[: len(perm) // 2], chair.vertices[: len(perm) // 2])
        a, b = chair.landmarks, chair_landmarks(v, f)
        assert abs(a.seat_height - b.seat_height) < 1e-4
        assert abs(a.seat_width - b.seat_width) < 1e-3 and abs(a.seat_depth - b.seat_depth) < 1e-3
        for name in ("seat_center", "seat_front", "left_armrest", "right_armrest", "back_top",
                     "back_front"):
            assert np.allclose(getattr(a, name), getattr(b, name), atol=2e-3), name


def test_landmarks_of_a_shapenet_style_part_soup():
    """Overlapping closed parts, never unioned (as ShapeNet meshes often are), built here with
    trimesh boxes: buried faces (the seat board inside the backrest, leg tops inside the seat)
    must not count as seat."""

    def box(lo, hi) -> trimesh.Trimesh:
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        return trimesh.creation.box(extents=hi - lo,
                                    transform=trimesh.transformations.translation_matrix(
                                        (lo + hi) / 2))

    parts = [box((-0.25, 0.42, -0.30), (0.25, 0.47, 0.22)),       # seat, runs into the back
             box((-0.33, 0.30, -0.32), (0.33, 1.02, -0.24)),       # backrest, top at 1.02
             box((0.25, 0.66, -0.26), (0.33, 0.69, 0.2)),          # left armrest, top at 0.69
             box((-0.33, 0.66, -0.26), (-0.25, 0.69, 0.2)),        # right armrest
             box((0.27, 0.42, 0.12), (0.31, 0.67, 0.16)),          # armrest posts
             box((-0.31, 0.42, 0.12), (-0.27, 0.67, 0.16))]
    parts += [box((x - 0.02, 0.0, z - 0.02), (x + 0.02, 0.45, z + 0.02))
              for x in (-0.2, 0.2) for z in (-0.2, 0.17)]
    soup = trimesh.util.concatenate(parts)
    lm = chair_landmarks(np.asarray(soup.vertices), np.asarray(soup.faces))
    assert abs(lm.seat_height - 0.47) < 1e-3
    assert abs(lm.seat_width - 0.50) < 3e-3 and abs(lm.seat_depth - 0.46) < 3e-3
    assert abs(lm.left_armrest[1] - 0.69) < 1e-3 and lm.left_armrest[0] > 0.25
    assert abs(lm.right_armrest[1] - 0.69) < 1e-3 and lm.right_armrest[0] < -0.25
    assert abs(lm.back_top[1] - 1.02) < 1e-3
    assert abs(lm.back_front[2] + 0.24) < 1e-3 and lm.back_front[1] > 0.6


def test_landmarks_reject_a_mesh_without_a_seat():
    v, f = trimesh.creation.box(extents=(0.5, 0.05, 0.5)).vertices, trimesh.creation.box().faces
    with pytest.raises(ValueError, match="upward-facing surface"):
        chair_landmarks(np.asarray(v), np.asarray(f))   # a 5 cm slab: no seat above 15 cm


def test_scan_frame(chairs):
    rng = np.random.default_rng(3)
    chair = chairs[1]
    for _ in range(5):
        t = scan_pose(rng)
        r = t[:3, :3]
        assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0)
        assert np.all(np.abs(t[:3, 3]) <= 1.0) and np.allclose(t[3], [0, 0, 0, 1])
        scanned = to_scan_frame(chair, t)
        assert scanned.faces is chair.faces and scanned.face_parts is chair.face_parts
        back = apply_transform(invert_transform(t), scanned.vertices)
        assert np.allclose(back, chair.vertices, atol=1e-12)
        lm = scanned.landmarks
        expected = apply_transform(t, chair.landmarks.left_armrest[None])[0]
        assert np.allclose(lm.left_armrest, expected)
        assert np.allclose(lm.seat_normal, r @ chair.landmarks.seat_normal)
        assert lm.seat_height == chair.landmarks.seat_height


def test_room_clutter_stays_clear_of_the_interaction_area():
    axis = np.column_stack([np.zeros(301), np.linspace(0.0, 3.0, 301), np.zeros(301)])
    for seed in range(6):
        objects = make_room(np.random.default_rng(seed), walls=seed % 2 == 1)
        floor = objects[0]
        assert floor.name == "floor" and np.isclose(floor.vertices[:, 1].max(), 0.0)
        names = [o.name for o in objects]
        assert {"table", "cabinet", "plant_pot", "plant"} <= set(names)
        assert any(n.startswith("wall") for n in names) == (seed % 2 == 1)
        for obj in objects[1:]:
            assert all(0.0 <= c <= 1.0 for c in obj.color)
            assert obj.vertices[:, 1].min() > -0.051
            if obj.name.startswith("wall"):
                continue
            assert trimesh.Trimesh(obj.vertices, obj.faces, process=False).is_watertight
            assert np.all(np.abs(obj.vertices[:, [0, 2]]) <= 3.0), obj.name
            # The closest approach to the vertical axis through the origin is horizontal.
            dist, _ = _closest(obj.vertices, obj.faces, axis)
            assert dist.min() >= 1.5, (seed, obj.name, dist.min())
    # Camera stands can be kept clear too.
    stand = (2.2, 0.0, 0.6)
    for seed in range(3):
        for obj in make_room(np.random.default_rng(seed), avoid=[stand])[1:]:
            assert np.hypot(obj.vertices[:, 0] - stand[0], obj.vertices[:, 2] - stand[1]).min() \
                >= stand[2]


def test_mesh_io_round_trip_and_errors(chairs, tmp_path):
    chair = chairs[0]
    for suffix, atol in ((".obj", 1e-9), (".ply", 1e-6)):
        path = save_mesh(tmp_path / f"chair{suffix}", chair.vertices, chair.faces)
        v, f = load_mesh(path)
        assert np.allclose(v, chair.vertices, atol=atol, rtol=0)
        assert np.array_equal(f, chair.faces)
        assert not list(tmp_path.glob(".*tmp*")), "atomic write left a temporary file"
    with pytest.raises(FileNotFoundError, match=r"missing\.obj"):
        load_mesh(tmp_path / "missing.obj")
    (tmp_path / "empty.obj").write_text("# nothing here\n")
    with pytest.raises(ValueError, match=r"empty\.obj"):
        load_mesh(tmp_path / "empty.obj")
    (tmp_path / "garbage.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement \xff")
    with pytest.raises(ValueError, match=r"garbage\.ply"):
        load_mesh(tmp_path / "garbage.ply")
    with pytest.raises(ValueError, match="unsupported"):
        save_mesh(tmp_path / "chair.stl", chair.vertices, chair.faces)


def _parse_obj(path) -> tuple[np.ndarray, np.ndarray]:
    """A plain OBJ reader independent of trimesh: v lines and (possibly v/vt/vn) f lines."""
    verts, faces = [], []
    for line in path.read_text().splitlines():
        tok = line.split()
        if tok and tok[0] == "v":
            verts.append([float(x) for x in tok[1:4]])
        elif tok and tok[0] == "f":
            faces.append([int(x.split("/")[0]) - 1 for x in tok[1:4]])
    return np.array(verts), np.array(faces)


def test_shapenet_layout_round_trip(chairs, tmp_path):
    chair = next(c for c in chairs if c.spec.kind == "armchair")
    model_dir = write_shapenet_layout(tmp_path, "03001627", "abc123", chair)
    assert model_dir == tmp_path / "03001627" / "abc123"
    models = model_dir / "models"
    meta = json.loads((models / "model_normalized.json").read_text())
    assert set(meta) == {"min", "max", "centroid", "id", "numVertices"}
    assert meta["id"] == "abc123" and meta["numVertices"] == len(chair.vertices)
    v_norm, faces = _parse_obj(models / "model_normalized.obj")
    assert np.array_equal(faces, chair.faces)
    vmin, vmax, centroid = (np.array(meta[k]) for k in ("min", "max", "centroid"))
    # Unit bounding-box diagonal, not centred on the origin (the centroid is the vertex mean).
    assert np.isclose(np.linalg.norm(v_norm.max(0) - v_norm.min(0)), 1.0, atol=1e-5)
    original = v_norm * np.linalg.norm(vmax - vmin) + centroid
    assert np.allclose(original.min(0), vmin, atol=1e-5)
    assert np.allclose(original.max(0), vmax, atol=1e-5)
    # ShapeNet's front is -Z: the backrest is at +Z there; our frame is a half turn about Y.
    back = chair.part_faces("back")
    assert original[faces[back]].mean(axis=(0, 1))[2] > 0.1
    recovered = original * np.array([-1.0, 1.0, -1.0])
    assert np.allclose(recovered, chair.vertices, atol=1e-5)
    # The file loads with the project's loader too, vertex order kept.
    v_loaded, _ = load_mesh(models / "model_normalized.obj")
    assert np.allclose(v_loaded, v_norm)

    write_shapenet_layout(tmp_path, "03001627", "def456", chairs[0])
    write_shapenet_layout(tmp_path, "04256520", "sofa1",
                          next(c for c in chairs if c.spec.kind == "sofa"))
    taxonomy = json.loads((tmp_path / "taxonomy.json").read_text())
    entries = {e["synsetId"]: e for e in taxonomy}
    assert entries["03001627"]["numInstances"] == 2 and entries["04256520"]["numInstances"] == 1
    assert entries["03001627"]["name"] == "chair" and entries["03001627"]["children"] == []
