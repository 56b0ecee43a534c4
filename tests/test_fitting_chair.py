"""Chair registration (issue 8, item 1) on simulated sessions against the simulator's truth.

Sessions: 4 s at 5 fps (20 frames), 4 cameras NFOV 2x2 binned, depth only, one ChArUco pose,
the empty-room background recording; camera poses from truth.json (the calibration's accuracy
is tested elsewhere). Chairs and seeds: straight (seed 1), stool (seed 2), armchair (seed 5,
depth noise x1.5), sofa (seed 4). Requirements (issue 8): pose within 5 mm and 0.5 deg of the
truth and chamfer of the registered mesh to its points <= 0.5 cm.

The pose error is measured on the chair itself: the rotation angle, and the largest distance
between the scan's vertices placed by the estimate and by the truth (every point of the chair
within 5 mm). The translation of ``world_from_object`` at the scan frame's origin — an arbitrary
point up to ~1.7 m from the chair, where the rotation error is magnified — is printed too. A
stool is symmetric: poses that map its mesh onto itself are equivalent, and the error is the
smallest over them.

Run with ``-s`` to see the measured numbers.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

import couch.fitting.chair as chair_module
from couch.capture.depth_bias import floor_depth_bias
from couch.fitting.chair import (
    ChairClouds,
    ChairConfig,
    ChairRegistrationError,
    average_poses,
    chair_clouds,
    global_candidates,
    load_scan,
    pose_segments,
    register_chair,
    register_session_chair,
    rotation_angle_deg,
)
from couch.geometry import apply_transform, invert_transform, make_transform
from couch.schema import read_processed
from couch.tools.sim.session import SessionConfig, simulate_session

COMMON = dict(duration=4.0, fps=5.0, cameras=4, depth_mode="NFOV_2X2BINNED", charuco_poses=1,
              color=False)
SESSIONS = {
    "straight": dict(seed=1, chair="straight"),
    "stool": dict(seed=2, chair="stool"),
    "armchair": dict(seed=5, chair="armchair", noise=1.5, interaction="right_hand"),
    "sofa": dict(seed=4, chair="sofa"),
}


@pytest.fixture(scope="session")
def sim(tmp_path_factory):
    """``sim(name)`` → the simulated session, its chair clouds and registration, made once."""
    cache: dict[str, dict] = {}

    def get(name: str) -> dict:
        if name not in cache:
            root = tmp_path_factory.mktemp(f"chair_{name}")
            t0 = time.perf_counter()
            simulate_session(root, SessionConfig(**COMMON, **SESSIONS[name]), progress=False)
            t_sim = time.perf_counter() - t0
            info = json.loads((root / "truth.json").read_text())
            truth = read_processed(root / "ground_truth.h5")
            ext = {c["serial"]: np.array(c["world_from_depth"]) for c in info["cameras"]}
            t0 = time.perf_counter()
            clouds = chair_clouds(root, ext)
            t_clouds = time.perf_counter() - t0
            t0 = time.perf_counter()
            reg = register_chair(root / "chair_scan.obj", clouds)
            t_reg = time.perf_counter() - t0
            print(f"\n[{name}] {SESSIONS[name]} (+{COMMON}); simulated in {t_sim:.1f} s, chair "
                  f"clouds {t_clouds:.1f} s, registration {t_reg:.1f} s\n{reg.summary()}")
            cache[name] = {"root": root, "info": info, "truth": truth, "ext": ext,
                           "clouds": clouds, "reg": reg}
        return cache[name]

    return get


def _symmetries(vertices: np.ndarray, faces: np.ndarray, centre: np.ndarray,
                tol: float = 1e-3) -> list[np.ndarray]:
    """(4,4) object-frame transforms that map the mesh onto itself (identity included): turns
    about the vertical through ``centre`` — the object's vertical is found as the axis the
    candidate turns are tried about (every principal axis), kept when every vertex lands
    within ``tol`` of the surface."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)),
                        o3d.core.Tensor(faces.astype(np.uint32)))
    _, axes = np.linalg.eigh(np.cov((vertices - centre).T))
    found = [np.eye(4)]
    for axis in axes.T:
        for deg in (60, 72, 90, 120, 180, 240, 270, 288, 300):
            rot = o3d.geometry.get_rotation_matrix_from_axis_angle(axis * np.radians(deg))
            m = make_transform(rot, centre - rot @ centre)
            d = scene.compute_distance(o3d.core.Tensor(
                apply_transform(m, vertices).astype(np.float32))).numpy()
            if d.max() < tol:
                found.append(m)
    return found


def _area_centroid(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(3,) area-weighted centroid of a mesh surface (on every symmetry axis)."""
    tri = vertices[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return (area[:, None] * tri.mean(1)).sum(0) / area.sum()


def _pose_errors(est: np.ndarray, truth: np.ndarray, vertices: np.ndarray,
                 faces: np.ndarray | None = None) -> dict[str, float]:
    """Rotation error (deg), largest vertex displacement and error at the chair's centre and
    at the scan origin (mm); with ``faces``, the smallest over the mesh's symmetries."""
    centre = vertices.mean(0)
    syms = [np.eye(4)] if faces is None else _symmetries(vertices, faces,
                                                         _area_centroid(vertices, faces))
    best = None
    for s in syms:
        t = truth @ s
        e = {"rot_deg": float(rotation_angle_deg(est, t)),
             "max_vertex_mm": float(np.linalg.norm(apply_transform(est, vertices)
                                                   - apply_transform(t, vertices), axis=1)
                                    .max() * 1e3),
             "centre_mm": float(np.linalg.norm(apply_transform(est, centre[None])
                                               - apply_transform(t, centre[None])) * 1e3),
             "origin_mm": float(np.linalg.norm(est[:3, 3] - t[:3, 3]) * 1e3),
             "symmetries": len(syms)}
        if best is None or e["max_vertex_mm"] < best["max_vertex_mm"]:
            best = e
    assert best is not None
    if faces is not None:
        # symmetry-proof: how far the estimate puts the scan's vertices from the true surface
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(apply_transform(truth, vertices).astype(np.float32)),
                            o3d.core.Tensor(faces.astype(np.uint32)))
        best["surface_mm"] = float(scene.compute_distance(o3d.core.Tensor(
            apply_transform(est, vertices).astype(np.float32))).numpy().max() * 1e3)
    return best


@pytest.mark.parametrize("name", list(SESSIONS))
def test_chair_pose_and_chamfer(sim, name):
    """Pose within 5 mm / 0.5 deg of the truth, chamfer <= 0.5 cm, one static segment."""
    s = sim(name)
    reg, truth = s["reg"], s["truth"]
    true_pose = np.array(s["info"]["chair"]["world_from_scan"])
    # the schema's /object/pose of the truth is the same transform as truth.json's
    assert np.allclose(truth.object_pose, true_pose, atol=1e-6)
    faces = truth.object_faces if name == "stool" else None
    err = _pose_errors(reg.world_from_object, true_pose, reg.vertices, faces)
    print(f"[{name}] rotation error {err['rot_deg']:.3f} deg; largest vertex error "
          f"{err['max_vertex_mm']:.2f} mm, at the chair's centre {err['centre_mm']:.2f} mm, at "
          f"the scan origin {err['origin_mm']:.2f} mm ({err['symmetries']} symmetric pose(s)); "
          f"chamfer {reg.chamfer * 100:.3f} cm (points->mesh "
          f"{reg.segments[0].chamfer_to_surface * 1e3:.2f} mm, seen mesh->points "
          f"{reg.segments[0].chamfer_to_points * 1e3:.2f} mm); ambiguous={reg.ambiguous} "
          f"{reg.ambiguity_deg}")
    if "surface_mm" in err and err["symmetries"] == 1 and reg.ambiguous:
        # a symmetric stool whose symmetry the test's search missed: every vertex of the
        # estimate must still lie on the true surface
        print(f"[{name}] estimate's vertices to the true surface: at most "
              f"{err['surface_mm']:.2f} mm")
        assert err["surface_mm"] <= 5.0
    else:
        assert err["rot_deg"] <= 0.5
        assert err["max_vertex_mm"] <= 5.0
    assert reg.chamfer <= 0.005
    assert len(reg.segments) == 1 and not reg.moved
    assert reg.used.sum() >= len(reg.frames) // 2
    # per-frame estimates are kept (schema /object/frame_poses), NaN only where rejected
    assert reg.frame_poses.shape == (len(reg.frames), 4, 4)
    assert np.isfinite(reg.frame_poses[reg.used]).all()
    assert reg.rotation_spread_deg < 0.5 and reg.translation_spread_mm < 5.0


def test_stool_ambiguity_is_reported(sim):
    """A 4-legged round stool fits turned by 90 deg as well: the registration says so."""
    s = sim("stool")
    spec = s["info"]["chair"]["spec"]
    reg = s["reg"]
    print(f"[stool] legs {spec['leg_count']}, seat {spec['seat_width']:.3f} x "
          f"{spec['seat_depth']:.3f} m: ambiguous={reg.ambiguous} {reg.ambiguity_deg}")
    syms = _symmetries(reg.vertices, reg.faces, _area_centroid(reg.vertices, reg.faces))
    if len(syms) > 1:
        assert reg.ambiguous and any("ambiguous" in w for w in reg.warnings)


@pytest.mark.parametrize("name", ["straight", "armchair", "sofa"])
def test_floor_starts_alone_find_the_chair(sim, name):
    """Without RANSAC, the scan's stable resting poses on the floor, turned about the vertical,
    find the chair on their own (they rescued a simulated armchair on which RANSAC's four
    runs all fitted it tilted, 130 deg off, with an ICP fitness of 0.72 against the truth's
    0.94)."""
    s = sim(name)
    clouds = s["clouds"].clouds
    best = int(np.argmax([len(c) for c in clouds]))
    scan = load_scan(s["root"] / "chair_scan.obj")
    cands, _ = global_candidates(clouds[best], scan, ChairConfig(ransac_seeds=0))
    assert cands, "no candidate"
    truth = np.array(s["info"]["chair"]["world_from_scan"])
    err = _pose_errors(cands[0].pose, truth, scan.vertices)
    print(f"[{name}] floor starts alone: fitness {cands[0].fitness:.3f}, rotation "
          f"{err['rot_deg']:.2f} deg, worst vertex {err['max_vertex_mm']:.1f} mm")
    assert err["rot_deg"] < 1.0 and err["max_vertex_mm"] < 10.0
    # and nothing is found without either
    assert not global_candidates(clouds[best], scan, ChairConfig(ransac_seeds=0, yaw_step=0))[0]


def test_ransac_runs_only_where_no_floor_start_fits_and_stands(sim, monkeypatch):
    """In a world levelled on the floor the floor starts find the chair and RANSAC does not run
    (always running it finds the same pose); in one tilted by 20 deg and lifted 30 cm, where
    no floor start can fit and stand, RANSAC runs and finds the chair."""
    s = sim("straight")
    clouds = s["clouds"].clouds
    frame = clouds[int(np.argmax([len(c) for c in clouds]))]
    scan = load_scan(s["root"] / "chair_scan.obj")
    truth = np.array(s["info"]["chair"]["world_from_scan"])
    runs: list[int] = []
    real = chair_module._ransac_starts

    def spy(*args, **kwargs):
        runs.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(chair_module, "_ransac_starts", spy)
    level, _ = global_candidates(frame, scan)
    assert not runs
    always, _ = global_candidates(frame, scan, ChairConfig(ransac_always=True))
    assert runs
    for cands in (level, always):
        err = _pose_errors(cands[0].pose, truth, scan.vertices)
        assert err["rot_deg"] < 0.5 and err["max_vertex_mm"] < 5.0, err
    assert _pose_errors(always[0].pose, level[0].pose, scan.vertices)["max_vertex_mm"] < 0.1

    runs.clear()
    centre = apply_transform(truth, scan.centre[None])[0]
    tilt = make_transform(Rotation.from_euler("x", 20, degrees=True).as_matrix(), np.zeros(3))
    move = (make_transform(np.eye(3), centre + np.array([0.0, 0.3, 0.0])) @ tilt
            @ make_transform(np.eye(3), -centre))
    tilted = dataclasses.replace(frame, points=apply_transform(move, frame.points).astype(
        np.float32), normals=(frame.normals @ move[:3, :3].T).astype(np.float32))
    cands, _ = global_candidates(tilted, scan)
    assert runs, "RANSAC did not run where no floor start can stand"
    err = _pose_errors(cands[0].pose, move @ truth, scan.vertices)
    print(f"tilted world: fitness {cands[0].fitness:.3f}, rotation {err['rot_deg']:.3f} deg, "
          f"worst vertex {err['max_vertex_mm']:.2f} mm")
    assert err["rot_deg"] < 0.5 and err["max_vertex_mm"] < 5.0, err


def test_screening_runs_on_a_capped_subset(sim, monkeypatch):
    """The global candidates are screened on at most ``screen_max_points`` of an object's
    downsampled points (a sofa's ~16k made the screening a third of the registration); the
    best candidate, refined on the whole frame, lands where the uncapped screening's does."""
    s = sim("sofa")
    clouds = s["clouds"].clouds
    frame = clouds[int(np.argmax([len(c) for c in clouds]))]
    scan = load_scan(s["root"] / "chair_scan.obj")
    sizes: list[int] = []
    real = chair_module.track_frame

    def spy(cloud, *args, **kwargs):
        sizes.append(len(cloud.points))
        return real(cloud, *args, **kwargs)

    monkeypatch.setattr(chair_module, "track_frame", spy)
    full, _ = global_candidates(frame, scan, ChairConfig(screen_max_points=0))
    screened_full = [n for n in sizes if n < len(frame.points)]
    sizes.clear()
    capped, _ = global_candidates(frame, scan, ChairConfig(screen_max_points=300))
    screened = [n for n in sizes if n < len(frame.points)]
    print(f"screened on {max(screened_full)} points at most uncapped, {max(screened)} capped")
    assert max(screened_full) > 300 and screened and max(screened) <= 300
    truth = np.array(s["info"]["chair"]["world_from_scan"])
    for cands in (full, capped):
        err = _pose_errors(cands[0].pose, truth, scan.vertices)
        assert err["rot_deg"] < 0.5 and err["max_vertex_mm"] < 5.0, err
    assert _pose_errors(capped[0].pose, full[0].pose, scan.vertices)["max_vertex_mm"] < 1.0


def test_the_distance_grid_crops_the_points_the_exact_distances_do(sim):
    """The crops of the ICP stages and the chamfer read the scan's coarse distance grid, then
    the exact distances at the centres of the cells the undecided points fall in, and query
    exact distances only near the margin: the same points as all exact distances, for points
    on the chair, near it and across the room, at the true pose and off it, with any cell."""
    s = sim("straight")
    scan = load_scan(s["root"] / "chair_scan.obj")
    grid, scene = scan.distance_grid, scan.scene()
    rng = np.random.default_rng(4)
    surface = scan.samples[rng.choice(len(scan.samples), 3000)]
    local = np.concatenate([surface + rng.normal(0, 0.01, surface.shape),
                            surface + rng.normal(0, 0.05, surface.shape),
                            rng.uniform(scan.vertices.min(0) - 0.2, scan.vertices.max(0) + 0.2,
                                        (3000, 3))])
    exact = chair_module._distances(scene, local)
    near = grid.nearest(local)
    inside = np.isfinite(near)
    assert inside.mean() > 0.5 and np.abs(near - exact)[inside].max() <= grid.bound
    truth = np.array(s["info"]["chair"]["world_from_scan"])
    off = truth @ make_transform(Rotation.from_euler("y", 7, degrees=True).as_matrix(),
                                 [0.03, 0.0, -0.02])
    frame = s["clouds"].clouds[0].points
    for pose in (truth, off):
        for points in (apply_transform(pose, local), np.asarray(frame, np.float64)):
            for margin in (0.03, 0.05):
                exact = chair_module._evaluate(points, scan, scene, pose, margin)[0]
                assert 0 < exact.sum() < len(points)
                for cell in (0.005, 0.015, 0.04):
                    crop = chair_module._crop(points, scan, scene, pose, margin, cell)
                    assert np.array_equal(crop, exact), (margin, cell)


def test_same_result_twice(sim):
    """Deterministic: the seeded global registration gives the same pose again."""
    s = sim("straight")
    again = register_chair(s["root"] / "chair_scan.obj", s["clouds"])
    assert np.allclose(again.world_from_object, s["reg"].world_from_object, atol=1e-9)


def _moved(clouds: ChairClouds, motion: np.ndarray, start: int) -> ChairClouds:
    """The clouds with every point of frames ``start``... moved rigidly by (4,4) ``motion``
    (the chair pushed to another place; the rest of the room moving along does not matter
    to the registration, which crops around the chair)."""
    out = []
    for i, c in enumerate(clouds.clouds):
        if i >= start:
            c = type(c)(points=apply_transform(motion, c.points).astype(np.float32),
                        normals=(c.normals @ motion[:3, :3].T).astype(np.float32),
                        camera=c.camera, time=c.time)
        out.append(c)
    return ChairClouds(clouds.session, clouds.frames, clouds.time, out, clouds.views,
                       clouds.warnings)


def test_moved_chair_gives_two_segments(sim):
    """The chair pushed 45 cm and turned 20 deg half-way: two static segments, each at its
    own true pose, not one average of both."""
    s = sim("straight")
    true_pose = np.array(s["info"]["chair"]["world_from_scan"])
    centre = apply_transform(true_pose, 0.5 * (s["reg"].vertices.min(0)
                                              + s["reg"].vertices.max(0))[None])[0]
    rot = o3d.geometry.get_rotation_matrix_from_axis_angle(np.array([0, np.radians(20), 0]))
    motion = make_transform(rot, centre - rot @ centre + np.array([0.4, 0.0, 0.2]))
    half = len(s["clouds"].clouds) // 2
    # the second half of the views' "farthest depth" is not moved: the chamfer's visibility
    # is approximate here, only poses and segments are checked
    reg = register_chair(s["root"] / "chair_scan.obj", _moved(s["clouds"], motion, half))
    print(f"[moved] {reg.summary()}")
    assert reg.moved and len(reg.segments) == 2
    first, second = reg.segments
    assert first.last < half <= second.first
    for seg, truth in ((first, true_pose), (second, motion @ true_pose)):
        err = _pose_errors(seg.world_from_object, truth, reg.vertices)
        print(f"[moved] segment {seg.first}-{seg.last}: rotation {err['rot_deg']:.3f} deg, "
              f"largest vertex error {err['max_vertex_mm']:.2f} mm")
        assert err["rot_deg"] <= 0.5 and err["max_vertex_mm"] <= 5.0
    assert any("moved" in w for w in reg.warnings)


def test_a_cabinet_that_fits_the_armchair_is_not_the_chair(tmp_path):
    """A held-out bench draw (armchair-right+4000: seed 4005, 8 s at 15 fps, 40 frames): its
    boxy armchair fits a cabinet of the room's clutter, 0.8-1.4 m up, about as closely as
    itself and explains more points there, and was registered on it (151 deg, 2.8 m off)
    until candidates that do not stand on the floor lost to those that do."""
    root = tmp_path / "session"
    simulate_session(root, SessionConfig(**dict(COMMON, duration=8.0, fps=15.0,
                                                charuco_poses=4), **SESSIONS["armchair"] | {
        "seed": 4005}), progress=False)
    info = json.loads((root / "truth.json").read_text())
    ext = {c["serial"]: np.array(c["world_from_depth"]) for c in info["cameras"]}
    clouds = chair_clouds(root, ext, step=3)
    true_pose = np.array(info["chair"]["world_from_scan"])
    # without the floor test this draw fooled the registration in 2 of 3 simulations (the
    # simulator is not bit-repeatable, see the README's *Repeatability*), so only the rule's
    # result is asserted
    reg = register_chair(root / "chair_scan.obj", clouds)
    err = _pose_errors(reg.world_from_object, true_pose, reg.vertices)
    print(f"[cabinet] {err['rot_deg']:.3f} deg, {err['max_vertex_mm']:.2f} mm")
    assert err["rot_deg"] <= 0.5 and err["max_vertex_mm"] <= 5.0
    assert not any("floor" in w for w in reg.warnings)


def test_a_chair_off_the_floor_is_reported(sim):
    """The only chair-shaped points lifted 0.9 m (the chair's own, moved): registered where
    they are, with a warning that the chair does not stand on the floor."""
    s = sim("straight")
    lift = make_transform(np.eye(3), np.array([0.0, 0.9, 0.0]))
    reg = register_chair(s["root"] / "chair_scan.obj", _moved(s["clouds"], lift, 0))
    assert _pose_errors(reg.world_from_object, lift @ np.array(
        s["info"]["chair"]["world_from_scan"]), reg.vertices)["max_vertex_mm"] <= 5.0
    assert any("does not stand on the floor: its lowest point is +90" in w
               for w in reg.warnings), reg.warnings


def test_average_poses_rejects_outliers():
    """Robust averaging: 2 wild poses among 20 noisy ones are dropped, the spread reported."""
    rng = np.random.default_rng(0)
    base = make_transform(o3d.geometry.get_rotation_matrix_from_axis_angle(
        np.array([0.1, 1.0, -0.2])), np.array([0.3, 0.1, -0.2]))
    poses = []
    for k in range(22):
        noise = 0.002 if k < 20 else 0.3  # rad (0.11 deg noise; outliers 17 deg)
        r = o3d.geometry.get_rotation_matrix_from_axis_angle(rng.normal(0, noise, 3))
        poses.append(base @ make_transform(r, rng.normal(0, 0.001 if k < 20 else 0.1, 3)))
    avg, keep, spread_r, spread_t = average_poses(np.array(poses))
    assert keep[:20].sum() >= 18 and not keep[20:].any()
    assert rotation_angle_deg(avg, base) < 0.1
    assert np.linalg.norm(avg[:3, 3] - base[:3, 3]) < 1e-3
    assert 0.05 < spread_r < 0.5 and 0.5 < spread_t < 5.0
    # a lone jump is an outlier, a lasting one a new segment
    seq = np.array([base] * 5 + [poses[20]] + [base] * 4 + [poses[21]] * 5)
    labels, outliers = pose_segments(seq)
    assert outliers == [5]
    assert list(labels) == [0] * 5 + [-1] + [0] * 4 + [1] * 5


# --------------------------------------------------------------------------- bad scans


def _write_obj(path: Path, v: np.ndarray, f: np.ndarray) -> Path:
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in v] + [f"f {a + 1} {b + 1} {c + 1}"
                                                         for a, b, c in f]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def bad_scans(sim, tmp_path_factory):
    s = sim("straight")
    truth = s["truth"]
    v, f = truth.object_vertices.astype(np.float64), truth.object_faces.astype(np.int64)
    d = tmp_path_factory.mktemp("bad_scans")
    nan = v.copy()
    nan[7] = np.nan
    empty = d / "empty.obj"
    empty.write_text("# nothing\n")
    return {
        "empty": (empty, "empty"),
        "not_watertight": (_write_obj(d / "holes.obj", v, f[10:]), "not watertight"),
        "nan": (_write_obj(d / "nan.obj", nan, f), "NaN"),
        "millimetres": (_write_obj(d / "mm.obj", v * 1000.0, f), "millimetres"),
        "garbage": ((d / "garbage.obj"), "empty"),
        "missing": (d / "missing.obj", "no such"),
    }


@pytest.mark.parametrize("kind", ["empty", "not_watertight", "nan", "millimetres", "garbage",
                                  "missing"])
def test_bad_scan_gives_clear_error(sim, bad_scans, kind):
    s = sim("straight")
    path, words = bad_scans[kind]
    if kind == "garbage":
        path.write_bytes(b"\x00\xff binary junk \x13\x37" * 50)
    with pytest.raises(ChairRegistrationError) as e:
        register_chair(path, s["clouds"])
    print(f"[bad scan {kind}] {e.value}")
    assert str(path) in str(e.value) and words in str(e.value)
    # the session entry point checks the scan before reading any recording
    with pytest.raises(ChairRegistrationError, match=words):
        register_session_chair(s["root"], s["ext"], scan=path)


def test_coincident_vertices_of_one_surface_are_no_hole():
    """A watertight box whose edge a-b runs through a second vertex a' at a's position (zero-area
    slivers a-a'-x, a'-a-y): the simulator's stool had such a pair where a profile closes. Merged
    by position, the slivers collapse and the box is watertight; a real hole still fails."""
    trimesh = pytest.importorskip("trimesh")
    box = trimesh.creation.box((0.4, 0.45, 0.4))
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    a, b = f[0, 0], f[0, 1]
    x = f[0, 2]
    other = next(i for i, t in enumerate(f) if i and a in t and b in t)
    y = next(int(k) for k in f[other] if k not in (a, b))
    v2 = np.vstack([v, v[a]])
    a2 = len(v)
    faces = [t for i, t in enumerate(f.tolist()) if i not in (0, other)]
    faces += [[a2, b, x], [a, a2, x]]  # face 0 (a, b, x) split at a'
    faces += [[b, a2, y], [a2, a, y]]  # the neighbour (b, a, y), wound the other way round
    f2 = np.array(faces)
    assert trimesh.Trimesh(v2, f2, process=False).is_watertight
    scan = load_scan((v2, f2))
    assert len(scan.faces) == 14
    with pytest.raises(ChairRegistrationError, match="not watertight"):
        load_scan((v2, f2[1:]))


def test_session_entry_point(sim):
    """``register_session_chair`` (clouds every 2nd frame) agrees with the full run."""
    s = sim("straight")
    reg = register_session_chair(s["root"], s["ext"], step=2)
    assert len(reg.frames) == (len(s["clouds"].frames) + 1) // 2
    assert rotation_angle_deg(reg.world_from_object, s["reg"].world_from_object) < 0.3
    assert invert_transform(reg.world_from_object) is not None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_floor_depth_bias_corrects_other_surfaces(seed):
    """A camera's systematic depth error (the simulator's offset, scale and radial terms,
    three times the Azure Kinect-like default so that it dominates), measured on the floor
    alone, takes the error out of a box's depth at chair distance as well."""
    import trimesh

    from couch.tools.sim import kinect

    rng = np.random.default_rng(seed)
    (calib, pose), = kinect.place_cameras(rng, 1, target=(0.0, 0.4, 0.0))
    floor = kinect.SceneMesh([[-6, 0, -6], [6, 0, -6], [6, 0, 6], [-6, 0, 6]],
                             [[0, 2, 1], [0, 3, 2]])
    box = trimesh.creation.box((0.5, 0.8, 0.5))
    box.apply_translation((0.0, 0.4, 0.0))
    scene = kinect.build_scene([floor, kinect.SceneMesh(box.vertices, box.faces,
                                                        label=kinect.LABEL_CHAIR)])
    noise = kinect.DepthNoise(offset_std=0.006, scale_std=0.0012, radial_std=0.0015)
    frames = [kinect.render_depth(scene, calib, pose, noise, rng) for _ in range(3)]
    on_box = [f.label == kinect.LABEL_CHAIR for f in frames]
    bias = floor_depth_bias([np.where(b, 0, f.depth_mm).astype(np.uint16)
                             for f, b in zip(frames, on_box, strict=True)], calib, pose)
    assert bias is not None and bias.pixels > 2000
    raw, fixed = [], []
    for f, b in zip(frames, on_box, strict=True):
        sel = b & (f.depth_mm > 0) & ~f.flying
        raw.append(f.depth_mm[sel] * 1e-3 - f.depth_true[sel])
        fixed.append(bias.correct(f.depth_mm, calib)[sel] * 1e-3 - f.depth_true[sel])
    raw_err, fixed_err = (abs(float(np.median(np.concatenate(e)))) * 1e3 for e in (raw, fixed))
    true = kinect.device_depth_bias(calib, noise)
    print(f"[seed {seed}] true offset/scale/radial {true[0] * 1e3:.2f} mm / {true[1]:.5f} / "
          f"{true[2] * 1e3:.2f} mm; measured {bias.offset * 1e3:.2f} / {bias.scale:.5f} / "
          f"{bias.radial * 1e3:.2f} on {bias.pixels} floor pixels (rms {bias.rms * 1e3:.2f} "
          f"mm); box depth error {raw_err:.2f} mm as recorded, {fixed_err:.2f} mm corrected")
    assert fixed_err < 0.7
    assert fixed_err < raw_err or raw_err < 0.7


def _sampled_stool(tmp_path, frames: int, legs: int = 3, round_legs: bool = False
                   ) -> tuple[Path, np.ndarray, np.ndarray, list]:
    """A stool (by default the held-out bench stool below: three square legs turned by 120 deg
    fit its points within millimetres): its scan, faces, a true pose, and its surface sampled
    at that pose in ``frames`` clouds of 6000 points with 1.5 mm of noise."""
    from couch.capture.pointcloud import FusedCloud
    from couch.tools.sim.chairs import ChairSpec, make_chair, save_mesh

    spec = ChairSpec(kind="stool", seat_height=0.5998, seat_width=0.3056, seat_depth=0.3056,
                     seat_thickness=0.0448, back_height=None, back_tilt_deg=0.0,
                     back_thickness=0.0, armrest_height=None, armrest_width=0.0,
                     leg_thickness=0.0255, round_legs=round_legs, leg_count=legs,
                     leg_splay_deg=4.26, stretcher_height=0.148)
    chair = make_chair(spec)
    scan = save_mesh(tmp_path / "stool.obj", chair.vertices, chair.faces)
    c, s = np.cos(np.radians(25.0)), np.sin(np.radians(25.0))
    truth = make_transform(np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]), [0.3, 0.0, 1.2])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(chair.vertices),
                                     o3d.utility.Vector3iVector(chair.faces))
    rng = np.random.default_rng(0)
    clouds = []
    for k in range(frames):
        o3d.utility.random.seed(k)
        pcd = mesh.sample_points_uniformly(6000, use_triangle_normal=True)
        p = apply_transform(truth, np.asarray(pcd.points)) + rng.normal(0, 0.0015, (6000, 3))
        n = np.asarray(pcd.normals) @ truth[:3, :3].T
        clouds.append(FusedCloud(p.astype(np.float32), n.astype(np.float32),
                                 np.zeros(6000, np.int8), float(k)))
    return scan, np.asarray(chair.faces), truth, clouds


def test_a_nearly_symmetric_stool_is_registered_at_its_own_turn(tmp_path):
    """Three square legs turned by 120 deg fit a stool's points within millimetres, and about
    as many points lie within ``inlier_distance`` either way (a held-out bench stool, this
    spec, was registered turned by 120 deg, reported ambiguous, 5.35 mm off its true surface):
    the turn whose points lie closest wins, and it is no ambiguity. The points: the scan's
    surface sampled at its true pose in 3 frames, 1.5 mm of noise."""
    scan, _, truth, clouds = _sampled_stool(tmp_path, 3)
    reg = register_chair(scan, clouds)
    err = _pose_errors(reg.world_from_object, truth, reg.vertices)
    print(f"[near-symmetric stool] rotation error {err['rot_deg']:.3f} deg, largest vertex "
          f"error {err['max_vertex_mm']:.2f} mm; ambiguous={reg.ambiguous} {reg.ambiguity_deg}")
    assert err["rot_deg"] <= 0.5 and err["max_vertex_mm"] <= 5.0
    assert not reg.ambiguous


def test_a_frame_that_loses_the_chair_after_a_choice_of_turns(tmp_path):
    """A frame late in the session whose points are not the chair (here clutter, the last of 24)
    is re-detected and rejected, also after the first frame's turns of a symmetric stool were
    weighed against each other (the table's stool, seed 21, failed with an IndexError there:
    the turns' point counts had replaced the frames')."""
    scan, faces, truth, clouds = _sampled_stool(tmp_path, 24, legs=4, round_legs=True)
    rng = np.random.default_rng(1)
    clutter = rng.uniform([-0.2, 0.0, 0.8], [0.8, 1.0, 1.8], (6000, 3)).astype(np.float32)
    normals = rng.normal(size=(6000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    clouds[23] = dataclasses.replace(clouds[23], points=clutter,
                                    normals=normals.astype(np.float32))
    reg = register_chair(scan, clouds)
    err = _pose_errors(reg.world_from_object, truth, reg.vertices, faces)
    print(f"[symmetric stool, clutter in frame 23] {err['surface_mm']:.2f} mm from the true "
          f"surface; ambiguous={reg.ambiguous} {reg.ambiguity_deg}; rejected {reg.rejected}")
    assert reg.ambiguous  # the turns were weighed
    assert err["surface_mm"] <= 5.0
    assert 23 in [i for i, _ in reg.rejected]


def test_a_pool_of_workers_gives_the_same_chair_clouds(sim):
    """Two spawned workers, each segmenting and lifting whole cameras, give the chair clouds,
    views and depth errors of one process, every 3rd frame of each camera (no frame table)."""
    from couch.pool import spawn_pool

    s = sim("straight")
    ref = chair_clouds(s["root"], s["ext"], step=3)
    with spawn_pool(2) as pool:
        cc = chair_clouds(s["root"], s["ext"], step=3, pool=pool)
    assert np.array_equal(cc.frames, ref.frames) and np.array_equal(cc.time, ref.time)
    assert np.array_equal(cc.frames, s["clouds"].frames[::3])
    for ours, theirs in zip(cc.clouds, ref.clouds, strict=True):
        assert np.array_equal(ours.points, theirs.points)
        assert np.array_equal(ours.camera, theirs.camera)
    for ours, theirs in zip(cc.views, ref.views, strict=True):
        assert np.array_equal(ours.background, theirs.background)
    assert [b.report() if b else None for b in cc.depth_bias] == \
        [b.report() if b else None for b in ref.depth_bias]
    # every 3rd frame of the full run's clouds: the same points
    for ours, theirs in zip(cc.clouds, s["clouds"].clouds[::3], strict=True):
        assert np.array_equal(ours.points, theirs.points)
