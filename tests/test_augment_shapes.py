"""Shape library (couch.augment.shapes) on the committed ShapeNet-layout fixture.

The fixture is ``fixtures/shapenet_mini`` (regenerate: ``python -m couch.tools.sim.shapenet_mini
fixtures/shapenet_mini``): 8 usable chairs/sofas from the simulator's parametric generator (one
turned a quarter turn, one with duplicated faces and a hole) and 4 broken models.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from couch.augment import ShapeLibrary, load_shape_library
from couch.augment import shapes as shapes_mod
from couch.augment.shapes import SEAT_HEIGHT_RANGE
from couch.tools.sim.chairs import make_chair, random_chair_spec, save_mesh
from couch.tools.sim.shapenet_mini import make_shapenet_mini

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "shapenet_mini"
EXPECTED = json.loads((FIXTURE / "expected.json").read_text())


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> tuple[ShapeLibrary, Path]:
    cache = tmp_path_factory.mktemp("shape_cache")
    return load_shape_library(FIXTURE, cache_dir=cache, seed=0), cache


def _first_hits_down(mesh: trimesh.Trimesh, xz: np.ndarray) -> np.ndarray:
    """Height (N,) of the first surface hit by rays cast straight down at ``xz`` (N, 2)."""
    origins = np.column_stack([xz[:, 0], np.full(len(xz), 5.0), xz[:, 1]])
    dirs = np.tile([0.0, -1.0, 0.0], (len(xz), 1))
    locs, ray_idx, _ = mesh.ray.intersects_location(origins, dirs, multiple_hits=True)
    top = np.full(len(xz), np.nan)
    for i in range(len(xz)):
        ys = locs[ray_idx == i, 1]
        if len(ys):
            top[i] = ys.max()
    return top


def test_kept_and_skipped_with_reasons(library: tuple[ShapeLibrary, Path]) -> None:
    lib, _ = library
    kept = {k for k, e in EXPECTED.items() if e["expect"] == "kept"}
    assert {e.id for e in lib.entries} == kept
    assert len(lib.entries) == 8
    reasons = {sid: reason.split(":", 1)[0] for sid, reason in lib.skipped}
    assert reasons == {"broken_empty": "empty", "broken_nan": "non-finite",
                       "wrong_scale_bench": "implausible size",
                       "flat_plate": "implausible size"}
    assert "table_box" not in reasons   # other synsets are ignored
    summary = lib.summary()
    assert "4 straight, 2 armchair, 2 sofa" in summary
    assert "1 empty" in summary and "1 non-finite" in summary
    assert "2 implausible size" in summary


def test_categories_match_generator(library: tuple[ShapeLibrary, Path]) -> None:
    lib, _ = library
    for e in lib.entries:
        assert e.category == EXPECTED[e.id]["category"], e.id


def test_repaired_mesh_is_watertight(library: tuple[ShapeLibrary, Path]) -> None:
    lib, _ = library
    entry = next(e for e in lib.entries if e.id == "repairable_straight")
    notes = " ".join(entry.repaired)
    assert "duplicate faces" in notes and "closed holes" in notes
    for e in lib.entries:
        mesh = trimesh.Trimesh(e.vertices, e.faces, process=False)
        assert mesh.is_watertight, e.id
        assert mesh.volume > 0, e.id
        assert e.vertices.dtype == np.float64 and e.faces.dtype == np.int64


def test_metric_frame_seat_floor_front(library: tuple[ShapeLibrary, Path]) -> None:
    lib, _ = library
    for e in lib.entries:
        family = "sofa" if e.category == "sofa" else "chair"
        lo, hi = SEAT_HEIGHT_RANGE[family]
        assert lo <= e.seat_height <= hi, e.id
        assert abs(e.vertices[:, 1].min()) < 1e-9, e.id           # floor at y = 0
        mesh = trimesh.Trimesh(e.vertices, e.faces, process=False)
        # The seat surface is at the drawn height: rays down over the middle of the seat.
        gx, gz = np.meshgrid(np.linspace(-0.2, 0.2, 5) * e.seat_width,
                             np.linspace(-0.2, 0.2, 5) * e.seat_depth)
        tops = _first_hits_down(mesh, np.column_stack([gx.ravel(), gz.ravel()]))
        assert np.nanmedian(tops) == pytest.approx(e.seat_height, abs=0.01), e.id
        # Metric size agrees with the generator's spec up to the seat-height rescale.
        spec = EXPECTED[e.id]["spec"]
        ratio = e.seat_height / spec["seat_height"]
        assert e.seat_width == pytest.approx(spec["seat_width"] * ratio, rel=0.05), e.id
        # Backrest behind the seat (-Z): the surface well above the seat lies at z < 0.
        v = e.vertices
        high = v[v[:, 1] > e.seat_height + 0.25]
        assert high[:, 2].mean() < -0.1 * e.seat_depth, e.id
        assert e.has_back


def test_reproducible_and_seed_dependent(library: tuple[ShapeLibrary, Path],
                                         tmp_path: Path) -> None:
    lib, _ = library
    again = load_shape_library(FIXTURE, cache_dir=tmp_path / "a", seed=0)
    other = load_shape_library(FIXTURE, cache_dir=tmp_path / "b", seed=1, limit=4)
    for a, b in zip(lib.entries, again.entries, strict=True):
        assert a.id == b.id and a.seat_height == b.seat_height
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
    assert len(other.entries) + len(other.skipped) == 4
    by_id = {e.id: e for e in lib.entries}
    assert any(e.seat_height != by_id[e.id].seat_height for e in other.entries)


def test_cache_hit(library: tuple[ShapeLibrary, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    lib, cache = library
    assert not any(e.from_cache for e in lib.entries)
    assert len(list(cache.glob("*.h5"))) == 12  # 8 shapes and 4 skips (records)

    def no_processing(*args: object, **kwargs: object) -> None:
        raise AssertionError("the cache should have been used")

    monkeypatch.setattr(shapes_mod, "_process", no_processing)
    cached = load_shape_library(FIXTURE, cache_dir=cache, seed=0)
    assert all(e.from_cache for e in cached.entries)
    assert cached.skipped == lib.skipped
    for a, b in zip(lib.entries, cached.entries, strict=True):
        assert (a.id, a.category, a.seat_height, a.scale, a.repaired) == (
            b.id, b.category, b.seat_height, b.scale, b.repaired)
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)


def test_default_cache_outside_root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    lib = load_shape_library(FIXTURE, seed=0, limit=2)
    assert len(lib.entries) + len(lib.skipped) == 2
    assert list((tmp_path / "xdg" / "couch" / "shapes").glob("*/*.h5"))
    assert not (FIXTURE / ".couch_cache").exists()


def test_plain_folder_of_meshes(tmp_path: Path) -> None:
    """OBJ/PLY files in couch's own frame (front +Z, metres): the front comes from geometry."""
    rng = np.random.default_rng(3)
    chair = make_chair(random_chair_spec(rng, "armchair"))
    sofa = make_chair(random_chair_spec(rng, "sofa"))
    save_mesh(tmp_path / "meshes" / "a" / "armchair.ply", chair.vertices, chair.faces)
    save_mesh(tmp_path / "meshes" / "sofa.obj", sofa.vertices, sofa.faces)
    (tmp_path / "meshes" / "garbage.obj").write_text("v 1 2\nf 1 2 3 4 oops\n")
    (tmp_path / "meshes" / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    (tmp_path / "meshes" / "flat.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 0 1\nv 1 0 1\nf 1 2 3\nf 2 4 3\n")
    lib = load_shape_library(tmp_path / "meshes", cache_dir=tmp_path / "cache", seed=0)
    got = {e.id: e for e in lib.entries}
    assert set(got) == {"a/armchair", "sofa"}
    reasons = {sid: reason.split(":", 1)[0] for sid, reason in lib.skipped}
    assert set(reasons) == {"garbage", "points", "flat"}
    assert reasons["points"] == "no faces" and reasons["flat"] == "degenerate"
    assert got["a/armchair"].category == "armchair" and got["sofa"].category == "sofa"
    for e, src in ((got["a/armchair"], chair), (got["sofa"], sofa)):
        # Already facing +Z: only scaled and shifted, neither turned nor mirrored.
        assert np.ptp(e.vertices, axis=0) == pytest.approx(
            np.ptp(src.vertices, axis=0) * e.scale, abs=1e-5)
        high = e.vertices[e.vertices[:, 1] > e.seat_height + 0.25]
        assert high[:, 2].mean() < 0 and e.has_back


def test_multi_part_mesh_is_alpha_wrapped(tmp_path: Path) -> None:
    """ShapeNet-style: intersecting closed parts, never unioned, plus an open part."""
    def box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> trimesh.Trimesh:
        lo_, hi_ = np.array(lo), np.array(hi)
        return trimesh.creation.box(extents=hi_ - lo_,
                                    transform=trimesh.transformations.translation_matrix(
                                        (lo_ + hi_) / 2))

    parts = [box((-0.23, 0.40, -0.21), (0.23, 0.45, 0.21)),       # seat
             box((-0.23, 0.42, -0.23), (0.23, 0.92, -0.19))]      # back (in couch axes)
    parts += [box((x - 0.02, 0.0, z - 0.02), (x + 0.02, 0.43, z + 0.02))
              for x in (-0.2, 0.2) for z in (-0.18, 0.18)]
    mesh = trimesh.util.concatenate(parts)
    save_mesh(tmp_path / "meshes" / "parts.obj", mesh.vertices, mesh.faces[:-1])
    lib = load_shape_library(tmp_path / "meshes", cache_dir=tmp_path / "cache", seed=0)
    assert not lib.skipped
    (e,) = lib.entries
    assert any("alpha wrap" in note for note in e.repaired)
    assert trimesh.Trimesh(e.vertices, e.faces, process=False).is_watertight
    assert e.category == "straight" and e.has_back
    high = e.vertices[e.vertices[:, 1] > e.seat_height + 0.25]
    assert high[:, 2].mean() < 0


def test_fixture_matches_generator(tmp_path: Path) -> None:
    expected = make_shapenet_mini(tmp_path / "mini", seed=0)
    assert expected == EXPECTED
    committed = sorted(p.relative_to(FIXTURE) for p in FIXTURE.rglob("*") if p.is_file())
    fresh = sorted(p.relative_to(tmp_path / "mini") for p in (tmp_path / "mini").rglob("*")
                   if p.is_file())
    assert committed == fresh
    for rel in committed:
        if rel.suffix != ".obj":
            continue
        a = trimesh.load(FIXTURE / rel, force="mesh", process=False)
        b = trimesh.load(tmp_path / "mini" / rel, force="mesh", process=False)
        va, vb = np.asarray(a.vertices), np.asarray(b.vertices)
        assert va.shape == vb.shape, rel
        np.testing.assert_allclose(va, vb, atol=1e-4, err_msg=str(rel))
        # The boolean union may triangulate a coplanar region differently from run to run:
        # compare the surfaces, not the face lists.
        assert len(a.faces) == len(b.faces), rel
        if not np.isfinite(va).all():   # broken_nan
            continue
        assert a.area == pytest.approx(b.area, rel=1e-6), rel
        if a.is_watertight:
            assert b.is_watertight and a.volume == pytest.approx(b.volume, rel=1e-6), rel
