"""``python -m couch.tools.augment_eval``: the augmentation issue's "must show" numbers, measured
over several simulated source sequences re-targeted onto every shape of a library.

Sources: simulated sit-downs (the simulator's motion and ground truth, no rendering; ``--fps``,
``--duration``) with the interactions and chair kinds of :data:`CASES` (seeded). Each is
augmented with :func:`couch.augment.augment_dataset` onto every usable shape of ``--shapes``
(default the committed ``fixtures/shapenet_mini``) at scale 1, ``--workers`` processes. Printed:
one line per pair (reach, penetration, skate, jumps, dropped/fallback contacts, kept or the
rejection), the keep rate per target category, and over the kept pairs the issue's criteria:

- transferred contacts reached within 1 cm (median) and 2 cm (95th percentile);
- foot skate no worse than the source + 1 mm/frame;
- penetration 95th percentile < 2 cm;
- no frame-to-frame pose jump larger than the source's largest + 10 %.

``--json FILE`` also writes the per-pair records.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from couch.atomic import atomic_path
from couch.augment import augment_dataset, load_shape_library
from couch.body import load_body_model
from couch.schema import write_processed

FIXTURE_SHAPES = Path(__file__).resolve().parents[1] / "fixtures" / "shapenet_mini"
CASES: tuple[tuple[str, str, int], ...] = (
    ("right_hand", "armchair", 0), ("left_hand", "armchair", 1), ("left_hand", "sofa", 2),
    ("both_hands", "armchair", 3), ("no_contact", "straight", 4), ("right_hand", "sofa", 5),
)
"""(interaction, chair kind, seed) of the simulated sources."""


def simulate_sources(out: Path, cases: tuple[tuple[str, str, int], ...], fps: float,
                     duration: float) -> list[Path]:
    """Write one processed-schema file per case into ``out``; returns their paths."""
    from couch.tools.sim.session import simulate_sequence
    from couch.tools.sim.truth import ground_truth

    full, coarse = load_body_model("couch-body"), load_body_model("couch-body-coarse")
    paths = []
    for interaction, chair, seed in cases:
        seq = simulate_sequence(np.random.default_rng(seed), full, coarse,
                                interaction=interaction, chair=chair, duration=duration)
        times = np.arange(0.0, seq.motion.duration, 1.0 / fps)
        name = f"{interaction}_{chair}_{seed}"
        path = out / name / "processed.h5"
        write_processed(path, ground_truth(name, seq.motion, times, seq.placement, full,
                                           coarse, fps=fps))
        paths.append(path)
    return paths


def criteria(records: list[dict]) -> dict[str, float | bool]:
    """The issue's four criteria over kept records (``summary.json`` ``sequences`` entries)."""
    kept = [r["stats"] for r in records if r["kept"]]
    if not kept:
        return {"kept": 0}

    def col(key: str) -> np.ndarray:
        return np.array([np.nan if s[key] is None else s[key] for s in kept], float)

    reach_med, reach_p95 = col("reach_median"), col("reach_p95")
    skate = col("skate_after") - col("skate_before")
    jump = col("jump_after") / col("jump_before")
    pen = col("penetration_p95")
    return {
        "kept": len(kept),
        "reach_median_cm_worst": float(np.nanmax(reach_med) * 100),
        "reach_p95_cm_worst": float(np.nanmax(reach_p95) * 100),
        "skate_increase_mm_worst": float(np.nanmax(skate)),
        "penetration_p95_cm_worst": float(np.nanmax(pen) * 100),
        "jump_ratio_worst": float(np.nanmax(jump)),
        "all_met": bool(np.nanmax(reach_med) <= 0.01 and np.nanmax(reach_p95) <= 0.02
                        and np.nanmax(skate) <= 1.0 and np.nanmax(pen) < 0.02
                        and np.nanmax(jump) <= 1.1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shapes", type=Path, default=FIXTURE_SHAPES, help="shape library folder")
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--duration", type=float, default=8.0, help="simulated seconds per source")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None, help="write the per-pair records here")
    args = ap.parse_args(argv)
    lib_size = len(load_shape_library(args.shapes, seed=0).entries)
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        sources = simulate_sources(Path(tmp), CASES, args.fps, args.duration)
        sim_s = time.perf_counter() - start
        summary = augment_dataset(sources, args.shapes, Path(tmp) / "out",
                                  per_sequence=lib_size, scale_range=(1.0, 1.0), seed=0,
                                  workers=args.workers, progress=True)
        records = summary.sequences
    print(f"{len(sources)} sources simulated in {sim_s:.0f} s ({args.fps:g} fps, "
          f"{args.duration:g} s); {len(records)} pairs augmented in {summary.seconds:.0f} s "
          f"with {args.workers} workers")
    by_cat: dict[str, list[bool]] = defaultdict(list)
    for r in sorted(records, key=lambda r: (r["source"], r["shape"])):
        s = {k: (np.nan if v is None else v) for k, v in r["stats"].items()}
        by_cat[r["category"]].append(r["kept"])
        print(f"{r['source']:22s} -> {r['shape']:20s} {r['category']:9s} reach "
              f"{100 * s['reach_median']:5.2f}/{100 * s['reach_p95']:5.2f} cm, pen95 "
              f"{100 * s['penetration_p95']:4.2f} cm, skate {s['skate_before']:.2f}->"
              f"{s['skate_after']:.2f} mm, jump {s['jump_before']:.3f}->{s['jump_after']:.3f} m,"
              f" dropped {s['dropped_contacts']}, fallback {s['fallback_contacts']}: "
              f"{'kept' if r['kept'] else r['rejected']}")
    print("kept per target category: " + ", ".join(
        f"{c} {sum(v)}/{len(v)}" for c, v in sorted(by_cat.items())))
    crit = criteria(records)
    print("over kept pairs: " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else
                                           f"{k} {v}" for k, v in crit.items()))
    if args.json:
        with atomic_path(args.json) as t:
            t.write_text(json.dumps({"criteria": crit, "pairs": records}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
