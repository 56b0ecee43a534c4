"""A tiny ShapeNetCore v2 look-alike built from the simulator's parametric chairs, with broken
models that a shape loader must skip or repair: the fixture of ``couch.augment.shapes``.

Layout written under ``out_dir`` (formats.md, "ShapeNetCore v2")::

    taxonomy.json                                   chair, sofa and table synsets
    expected.json                                   {model_id: what a loader should make of it}
    03001627/<modelId>/models/model_normalized.{obj,mtl,json}   chairs
    04256520/<modelId>/models/model_normalized.{obj,mtl,json}   sofas
    04379243/table_box/models/...                   another synset, to be ignored

Good models (normalised as ShapeNet does: front -Z, unit bounding-box diagonal, ``.json`` with
``min``/``max``/``centroid`` of the original metric mesh): ``straight_0``-``straight_2``
(``straight_2`` turned a quarter turn about Y, so its front is +X: geometry must find it),
``armchair_0``, ``armchair_1``, ``sofa_0``, ``sofa_1``. Broken ones: ``broken_empty`` (an OBJ
without vertices), ``broken_nan`` (NaN vertex coordinates), ``repairable_straight`` (duplicated
faces and vertices plus a one-triangle hole: repair makes it watertight, so it is kept),
``wrong_scale_bench`` (a sofa stretched to a ~10 m bench: implausible at any seat height),
``flat_plate`` (a 1 m × 1 m × 1 cm slab: its top is the only seat, which makes it ~40 m wide
at a chair's seat height, so it is implausible too).

Regenerate the committed fixture with::

    python -m couch.tools.sim.shapenet_mini fixtures/shapenet_mini
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
from pathlib import Path

import numpy as np

from couch.atomic import atomic_path
from couch.tools.sim.chairs import (
    CHAIR_SYNSET,
    SOFA_SYNSET,
    Chair,
    ChairSpec,
    make_chair,
    random_chair_spec,
    write_shapenet_layout,
)

__all__ = ["TABLE_SYNSET", "main", "make_shapenet_mini"]

TABLE_SYNSET = "04379243"
_NAMES = {CHAIR_SYNSET: "chair", SOFA_SYNSET: "sofa,couch,lounge", TABLE_SYNSET: "table"}


def _quarter_turn(chair: Chair) -> Chair:
    """``chair`` turned +90° about Y: its front (+Z) ends up at +X."""
    rot = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    return dataclasses.replace(chair, vertices=chair.vertices @ rot.T)


def _box_chair(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> Chair:
    """A closed box from ``lo`` to ``hi`` (m) wrapped as a :class:`Chair` without spec or
    landmarks (:func:`write_shapenet_layout` needs only the vertices and faces)."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])], dtype=np.float64)
    # Vertex i has bits (x, y, z) = (i >> 2, i >> 1, i) & 1; outward-oriented triangles.
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]],
                     dtype=np.int64)
    return Chair(vertices=corners, faces=faces, face_parts=np.full(12, -1, np.int8),
                 landmarks=None)   # type: ignore[arg-type]


def _write_raw(root: Path, synset: str, model_id: str, obj_text: str, meta: dict) -> None:
    models = root / synset / model_id / "models"
    with atomic_path(models / "model_normalized.obj") as tmp:
        tmp.write_text(obj_text)
    with atomic_path(models / "model_normalized.json") as tmp:
        tmp.write_text(json.dumps(meta))


def make_shapenet_mini(out_dir: str | os.PathLike, seed: int = 0) -> dict[str, dict]:
    """Write the fixture (module doc) into ``out_dir`` (replacing synset folders already there).

    Returns ``{model_id: {"synset", "expect": "kept" | "skipped", "category" | "reason",
    ["spec": ChairSpec fields]}}``, also written as ``expected.json``. Deterministic in ``seed``.
    """
    root = Path(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    for synset in _NAMES:
        if (root / synset).is_dir():
            shutil.rmtree(root / synset)
    rng = np.random.default_rng(seed)
    expected: dict[str, dict] = {}

    def good(synset: str, model_id: str, chair: Chair, category: str) -> None:
        write_shapenet_layout(root, synset, model_id, chair)
        expected[model_id] = {"synset": synset, "expect": "kept", "category": category,
                              "spec": dataclasses.asdict(chair.spec) if chair.spec else None}

    for i in range(3):
        chair = make_chair(random_chair_spec(rng, "straight"))
        good(CHAIR_SYNSET, f"straight_{i}", _quarter_turn(chair) if i == 2 else chair,
             "straight")
    for i in range(2):
        good(CHAIR_SYNSET, f"armchair_{i}", make_chair(random_chair_spec(rng, "armchair")),
             "armchair")
    for i in range(2):
        good(SOFA_SYNSET, f"sofa_{i}", make_chair(random_chair_spec(rng, "sofa")), "sofa")

    # Repairable: duplicated faces and vertices, and a one-triangle hole in a leg.
    chair = make_chair(random_chair_spec(rng, "straight"))
    v, f = chair.vertices, chair.faces
    dup = rng.choice(len(f), size=20, replace=False)
    hole = int(np.argmin(v[f].mean(1)[:, 1]))     # a triangle on a leg's bottom
    extra_v = v[f[dup[:5]]].reshape(-1, 3)          # 5 faces re-drawn on copied vertices
    extra_f = len(v) + np.arange(15).reshape(5, 3)
    faces = np.concatenate([np.delete(f, hole, axis=0), f[dup], extra_f])
    broken = dataclasses.replace(chair, vertices=np.concatenate([v, extra_v]), faces=faces)
    write_shapenet_layout(root, CHAIR_SYNSET, "repairable_straight", broken)
    expected["repairable_straight"] = {"synset": CHAIR_SYNSET, "expect": "kept",
                                       "category": "straight",
                                       "spec": dataclasses.asdict(chair.spec)}

    # Wrong scale: a sofa stretched along X into a ~10 m bench.
    sofa = make_chair(ChairSpec.for_kind("sofa", cushions=3))
    stretch = 10.0 / float(np.ptp(sofa.vertices[:, 0]))
    bench = dataclasses.replace(sofa, vertices=sofa.vertices * [stretch, 1.0, 1.0])
    write_shapenet_layout(root, SOFA_SYNSET, "wrong_scale_bench", bench)
    expected["wrong_scale_bench"] = {"synset": SOFA_SYNSET, "expect": "skipped",
                                     "reason": "implausible size"}

    # Flat plate: its top, the only upward surface, is at 100% of its 1 cm height.
    write_shapenet_layout(root, CHAIR_SYNSET, "flat_plate",
                          _box_chair((-0.5, 0.0, -0.5), (0.5, 0.01, 0.5)))
    expected["flat_plate"] = {"synset": CHAIR_SYNSET, "expect": "skipped",
                                  "reason": "implausible size"}

    # Empty OBJ and NaN coordinates, written by hand.
    _write_raw(root, CHAIR_SYNSET, "broken_empty", "# couch: an empty model\n",
               {"id": "broken_empty", "numVertices": 0})
    expected["broken_empty"] = {"synset": CHAIR_SYNSET, "expect": "skipped", "reason": "empty"}
    chair = make_chair(random_chair_spec(rng, "straight"))
    v = chair.vertices / np.linalg.norm(np.ptp(chair.vertices, axis=0))
    v[rng.choice(len(v), size=3, replace=False)] = np.nan
    lines = ["# couch: NaN vertices"] + [f"v {x:f} {y:f} {z:f}" for x, y, z in v]
    lines += [f"f {a} {b} {c}" for a, b, c in chair.faces + 1]
    _write_raw(root, CHAIR_SYNSET, "broken_nan", "\n".join(lines) + "\n",
               {"id": "broken_nan", "numVertices": len(v)})
    expected["broken_nan"] = {"synset": CHAIR_SYNSET, "expect": "skipped",
                              "reason": "non-finite"}

    # Another synset: must be ignored by a chair loader.
    write_shapenet_layout(root, TABLE_SYNSET, "table_box",
                          _box_chair((-0.6, 0.0, -0.4), (0.6, 0.75, 0.4)))

    taxonomy = []
    for synset, name in _NAMES.items():
        count = sum(1 for p in (root / synset).iterdir()
                    if (p / "models" / "model_normalized.obj").is_file())
        taxonomy.append({"synsetId": synset, "name": name, "children": [],
                         "numInstances": count})
    with atomic_path(root / "taxonomy.json") as tmp:
        tmp.write_text(json.dumps(taxonomy, indent=1))
    with atomic_path(root / "expected.json") as tmp:
        tmp.write_text(json.dumps(expected, indent=1, sort_keys=True))
    return expected


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m couch.tools.sim.shapenet_mini",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    expected = make_shapenet_mini(args.out_dir, seed=args.seed)
    kept = sum(e["expect"] == "kept" for e in expected.values())
    print(f"{args.out_dir}: {kept} usable models, {len(expected) - kept} broken ones")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
