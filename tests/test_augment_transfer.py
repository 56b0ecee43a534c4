"""Part segmentation (couch.augment.parts) and part-aware contact transfer
(couch.augment.transfer).

Ground truth: the simulator's parametric chairs (``tools/sim/chairs.py``), whose ``face_parts``
carry exact part labels through the mesh union (seat / back / left armrest (+X) / right armrest
/ base, the same codes as :data:`couch.augment.parts.PART_NAMES`), and whose specs give the
armrest and seat geometry. Chairs are drawn with fixed seeds.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from couch.augment import (
    PART_NAMES,
    ChairParts,
    load_shape_library,
    segment_parts,
    sitter_shift,
    transfer_contacts,
)
from couch.tools.sim.chairs import Chair, make_chair, random_chair_spec

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "shapenet_mini"
IOU_FLOOR = {"straight": {"seat": 0.8, "backrest": 0.8},
             "armchair": {"seat": 0.8, "backrest": 0.8, "left_armrest": 0.7,
                          "right_armrest": 0.7},
             "sofa": {"seat": 0.8, "backrest": 0.8, "left_armrest": 0.7, "right_armrest": 0.7}}


def _chairs(kind: str, seed: int, count: int) -> list[Chair]:
    rng = np.random.default_rng(seed)
    return [make_chair(random_chair_spec(rng, kind)) for _ in range(count)]


@pytest.fixture(scope="module")
def armchairs() -> list[tuple[Chair, ChairParts]]:
    return [(c, segment_parts(c.vertices, c.faces)) for c in _chairs("armchair", 11, 2)]


@pytest.fixture(scope="module")
def straight() -> tuple[Chair, ChairParts]:
    c = _chairs("straight", 12, 1)[0]
    return c, segment_parts(c.vertices, c.faces)


def _surface_distance(chair: Chair, points: np.ndarray) -> np.ndarray:
    """Distance (N,) from ``points`` to the chair surface, by trimesh (rtree), independent of the
    open3d queries used by the transfer."""
    mesh = trimesh.Trimesh(chair.vertices, chair.faces, process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh, points)
    return dist


def _armrest_top_centre(chair: Chair, side: float) -> np.ndarray:
    """Centre (3,) of the visible top of the left (side=+1) / right (-1) armrest from the spec:
    across the arm's width, from the backrest's front face (leaning back by the tilt) to the
    seat front."""
    s = chair.spec
    assert s is not None and s.armrest_height is not None
    ah = s.armrest_height
    z_rear = -s.seat_depth / 2 - ah * math.tan(math.radians(s.back_tilt_deg))
    return np.array([side * (s.seat_width / 2 + s.armrest_width / 2), s.seat_height + ah,
                     0.5 * (z_rear + s.seat_depth / 2)])


@pytest.mark.parametrize(("kind", "seed"), [("straight", 1), ("armchair", 2), ("sofa", 3)])
def test_segmentation_matches_generator_parts(kind: str, seed: int) -> None:
    for chair in _chairs(kind, seed, 3):
        parts = segment_parts(chair.vertices, chair.faces)
        assert parts.labels.shape == (len(chair.faces),) and parts.labels.dtype == np.int8
        area = trimesh.Trimesh(chair.vertices, chair.faces, process=False).area_faces
        ious = {}
        for code, name in enumerate(PART_NAMES[:4]):
            ours, truth = parts.labels == code, chair.face_parts == code
            union = area[ours | truth].sum()
            if union > 0:
                ious[name] = float(area[ours & truth].sum() / union)
        print(kind, {k: round(v, 3) for k, v in ious.items()})
        for name, floor in IOU_FLOOR[kind].items():
            assert ious.get(name, 0.0) >= floor, (kind, name, ious)
        expected = {"seat", "backrest"} | (
            {"left_armrest", "right_armrest"} if kind != "straight" else set())
        assert set(parts.frames) == expected


def test_left_armrest_centre_maps_to_left_armrest_centre(
        armchairs: list[tuple[Chair, ChairParts]]) -> None:
    (a, pa), (b, pb) = armchairs
    for side, name in ((1.0, "left_armrest"), (-1.0, "right_armrest")):
        src = _armrest_top_centre(a, side)[None]
        res = transfer_contacts(src, pa, a, pb, b)
        err = float(np.linalg.norm(res.points[0] - _armrest_top_centre(b, side)))
        print(f"{name} centre A->B error {err * 100:.2f} cm, moved "
              f"{res.distance_moved[0] * 100:.1f} cm")
        assert res.part_names == [name] and not res.fallback[0]
        assert err < 0.015


def test_seat_contact_keeps_its_relative_position(
        armchairs: list[tuple[Chair, ChairParts]]) -> None:
    (a, pa), (b, pb) = armchairs
    sa, sb = a.spec, b.spec
    assert sa is not None and sb is not None
    # Front-left and back-right quarters of A's seat top.
    quarter = np.array([[0.25, 0.25], [-0.25, -0.25]])
    src = np.column_stack([quarter[:, 0] * sa.seat_width, np.full(2, sa.seat_height),
                           quarter[:, 1] * sa.seat_depth])
    want = np.column_stack([quarter[:, 0] * sb.seat_width, np.full(2, sb.seat_height),
                            quarter[:, 1] * sb.seat_depth])
    res = transfer_contacts(src, pa, a, pb, b)
    err = np.linalg.norm(res.points - want, axis=1)
    print("seat quarter errors (cm)", np.round(err * 100, 2))
    assert res.part_names == ["seat", "seat"] and not res.fallback.any()
    assert np.all(np.sign(res.points[:, [0, 2]]) == np.sign(quarter))
    assert err.max() < 0.01


def _surface_contacts(chair: Chair, parts: ChairParts, count: int, seed: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` area-uniform points (N, 3) on the seat, backrest and armrests, with the part
    code (N,) of their face."""
    mesh = trimesh.Trimesh(chair.vertices, chair.faces, process=False)
    keep = np.flatnonzero(parts.labels < PART_NAMES.index("other"))
    sub = mesh.submesh([keep], append=True)
    pts, face = trimesh.sample.sample_surface(sub, count, seed=seed)
    return pts, parts.labels[keep[face]]


def test_contacts_land_on_the_target_part_surface(
        armchairs: list[tuple[Chair, ChairParts]]) -> None:
    (a, pa), (b, pb) = armchairs
    pts, codes = _surface_contacts(a, pa, 400, seed=0)
    res = transfer_contacts(pts, pa, a, pb, b)
    assert res.points.shape == (400, 3) and not res.fallback.any()
    np.testing.assert_array_equal(res.parts, codes)
    dist = _surface_distance(b, res.points)
    print(f"on-surface distance max {dist.max() * 1e3:.3f} mm; moved median "
          f"{np.median(res.distance_moved) * 100:.1f} cm")
    assert dist.max() < 1e-3
    # Each point lands on a face of its own part on the target.
    mesh_b = trimesh.Trimesh(b.vertices, b.faces, process=False)
    _, _, face_b = trimesh.proximity.closest_point(mesh_b, res.points)
    assert np.mean(pb.labels[face_b] == codes) > 0.98


def test_armrest_contact_onto_chair_without_armrests_falls_back(
        armchairs: list[tuple[Chair, ChairParts]], straight: tuple[Chair, ChairParts]) -> None:
    (a, pa), _ = armchairs
    s, ps = straight
    assert not ps.has("left_armrest") and not ps.has("right_armrest")
    src = np.stack([_armrest_top_centre(a, 1.0), _armrest_top_centre(a, -1.0),
                    pa.frames["seat"].centre])
    res = transfer_contacts(src, pa, a, ps, s)
    np.testing.assert_array_equal(res.fallback, [True, True, False])
    assert res.part_names == ["left_armrest", "right_armrest", "seat"]
    assert _surface_distance(s, res.points).max() < 1e-3
    assert res.points[0, 0] > 0 > res.points[1, 0]   # the nearest point keeps the side


def test_leg_contact_falls_back_to_nearest_surface(
        armchairs: list[tuple[Chair, ChairParts]]) -> None:
    (a, pa), (b, pb) = armchairs
    mesh = trimesh.Trimesh(a.vertices, a.faces, process=False)
    leg = np.flatnonzero((pa.labels == PART_NAMES.index("other"))
                         & (mesh.triangles_center[:, 1] < 0.2))[0]
    src = mesh.triangles_center[[leg]]
    res = transfer_contacts(src, pa, a, pb, b)
    assert res.fallback[0] and res.part_names == ["other"]
    assert _surface_distance(b, res.points)[0] < 1e-3


def test_identity_transfer_moves_nothing(armchairs: list[tuple[Chair, ChairParts]]) -> None:
    (a, pa), _ = armchairs
    pts, _ = _surface_contacts(a, pa, 300, seed=1)
    res = transfer_contacts(pts, pa, a, pa, a)
    print(f"identity: max moved {res.distance_moved.max() * 1e3:.4f} mm")
    assert not res.fallback.any()
    assert res.distance_moved.max() < 1e-3


def test_shapenet_library_chair_as_target(tmp_path: Path,
                                          armchairs: list[tuple[Chair, ChairParts]]) -> None:
    lib = load_shape_library(FIXTURE, cache_dir=tmp_path, seed=0)
    target = lib.by_category("armchair")[0]
    pt = segment_parts(target.vertices, target.faces)
    assert {"seat", "backrest", "left_armrest", "right_armrest"} <= set(pt.frames)
    (a, pa), _ = armchairs
    src = np.stack([_armrest_top_centre(a, 1.0), _armrest_top_centre(a, -1.0),
                    pa.frames["seat"].centre, pa.frames["backrest"].centre])
    res = transfer_contacts(src, pa, a, pt, target)
    assert not res.fallback.any()
    mesh = trimesh.Trimesh(target.vertices, target.faces, process=False)
    _, dist, face = trimesh.proximity.closest_point(mesh, res.points)
    assert dist.max() < 1e-3
    np.testing.assert_array_equal(pt.labels[face], res.parts)
    left, right, seat, back = res.points
    assert left[0] > 0 > right[0]                          # sitter's left is +X
    assert abs(seat[1] - target.seat_height) < 0.02 and np.hypot(seat[0], seat[2]) < 0.05
    assert back[2] < seat[2] and back[1] > seat[1]         # backrest behind, above the seat


@pytest.fixture(scope="module")
def sofa() -> tuple[Chair, ChairParts]:
    c = _chairs("sofa", 13, 1)[0]
    return c, segment_parts(c.vertices, c.faces)


def test_sitter_shift_keeps_the_held_armrest_and_the_seat_front(
        armchairs: list[tuple[Chair, ChairParts]], sofa: tuple[Chair, ChairParts]) -> None:
    """A right-armrest sitter moves with the sofa's right armrest; fronts align (from specs)."""
    (a, pa), _ = armchairs
    s, ps = sofa
    shift = sitter_shift(pa, ps, {"right_armrest": 40, "left_armrest": 5}, seated_x=-0.05)
    # the inner faces of the right armrests, from the generator's specs: -seat_width / 2
    expect_dx = -s.spec.seat_width / 2 + a.spec.seat_width / 2
    assert shift[0] == pytest.approx(expect_dx, abs=0.02)
    assert shift[1] == 0.0
    assert shift[2] == pytest.approx((s.spec.seat_depth - a.spec.seat_depth) / 2, abs=0.02)
    # both armrests held about as long: the mean, i.e. no sideways move between symmetric chairs
    both = sitter_shift(pa, ps, {"right_armrest": 40, "left_armrest": 30}, seated_x=0.0)
    assert abs(both[0]) < 0.02
    # the pelvis stays inside the seat however far the armrest asks
    far = sitter_shift(ps, pa, {"left_armrest": 10}, seated_x=0.3)
    half = pa.frames["seat"].half_extents[0]
    assert abs(0.3 + far[0]) <= half - 0.2 + 1e-9


def test_metric_transfer_onto_a_sofa(armchairs: list[tuple[Chair, ChairParts]],
                                     sofa: tuple[Chair, ChairParts]) -> None:
    """With the sitter's shift, a right-armrest contact lands on the sofa's right armrest at the
    same depth relative to the seat front, and a seat contact keeps its place under the sitter
    (metres, not stretched over the sofa's width)."""
    (a, pa), _ = armchairs
    s, ps = sofa
    arm = _armrest_top_centre(a, -1.0)
    seat = pa.frames["seat"].centre + np.array([-0.05, 0.0, 0.02])
    shift = sitter_shift(pa, ps, {"right_armrest": 40}, seated_x=-0.05)
    res = transfer_contacts(np.stack([arm, seat]), pa, a, ps, s, shift=shift)
    assert not res.fallback.any()
    assert res.part_names == ["right_armrest", "seat"]
    mesh = trimesh.Trimesh(s.vertices, s.faces, process=False)
    _, dist, face = trimesh.proximity.closest_point(mesh, res.points)
    assert dist.max() < 1e-3
    np.testing.assert_array_equal(s.face_parts[face], [PART_NAMES.index("right_armrest"),
                                                       PART_NAMES.index("seat")])
    # relative to the sitter (source point + shift) the seat contact moved only vertically, and
    # the armrest contact kept its depth (it moves across to the wider armrest's middle and up)
    moved = res.points - (np.stack([arm, seat]) + shift)
    assert np.abs(moved[1, [0, 2]]).max() < 0.01
    assert abs(moved[0, 2]) < 0.01
    # without the shift the seat contact is stretched over the sofa's width
    plain = transfer_contacts(seat[None], pa, a, ps, s)
    assert abs(plain.points[0, 0]) > abs(res.points[1, 0] - shift[0]) + 0.05


def test_metric_transfer_armrest_onto_straight_chair_goes_to_seat_edge(
        armchairs: list[tuple[Chair, ChairParts]], straight: tuple[Chair, ChairParts]) -> None:
    (a, pa), _ = armchairs
    s, ps = straight
    src = np.stack([_armrest_top_centre(a, 1.0), _armrest_top_centre(a, -1.0)])
    shift = sitter_shift(pa, ps, {"left_armrest": 10, "right_armrest": 10}, seated_x=0.0)
    res = transfer_contacts(src, pa, a, ps, s, shift=shift)
    assert res.fallback.all()
    mesh = trimesh.Trimesh(s.vertices, s.faces, process=False)
    _, dist, face = trimesh.proximity.closest_point(mesh, res.points)
    assert dist.max() < 1e-3
    assert (s.face_parts[face] == PART_NAMES.index("seat")).all()
    seat = ps.frames["seat"]
    edge = seat.half_extents[0]
    assert res.points[0, 0] > seat.centre[0] + 0.8 * edge     # the left (+X) edge
    assert res.points[1, 0] < seat.centre[0] - 0.8 * edge     # the right edge
    assert np.allclose(res.points[:, 1], seat.centre[1], atol=0.02)
