"""Benchmark: augmented frames per second of :func:`couch.augment.augment_dataset`.

Simulates one sequence first (not timed: a right-hand sit-down on an armchair, the simulator's
motion and truth without rendering, ``--duration`` s at ``--fps``), writes it as a processed
session, then re-targets it onto ``--per-sequence`` shapes of the library (default the
committed ``fixtures/shapenet_mini``; its cleaned meshes are cached first, not timed) with
``--workers`` processes. Prints the frames processed per second of wall time (every sample, kept
or rejected, is a sequence's worth of frames through transfer, IK and the checks), the kept
frames per second, and each sample's own seconds on its one thread.

Run: ``python -m couch.tools.bench.augment [--shapes DIR] [--per-sequence K] [--workers N]``.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from couch.augment import augment_dataset, load_shape_library
from couch.body import load_body_model
from couch.schema import write_processed

FIXTURE_SHAPES = Path(__file__).resolve().parents[2] / "fixtures" / "shapenet_mini"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shapes", type=Path, default=FIXTURE_SHAPES, help="shape library folder")
    ap.add_argument("--per-sequence", type=int, default=4, help="shapes per sequence")
    ap.add_argument("--workers", type=int, default=2, help="processes (default 2)")
    ap.add_argument("--duration", type=float, default=8.0, help="simulated seconds")
    ap.add_argument("--fps", type=float, default=15.0, help="frame rate of the sequence")
    ap.add_argument("--seed", type=int, default=0, help="simulator and draw seed")
    args = ap.parse_args(argv)
    from couch.tools.sim.session import simulate_sequence
    from couch.tools.sim.truth import ground_truth

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        full, coarse = load_body_model("couch-body"), load_body_model("couch-body-coarse")
        seq = simulate_sequence(np.random.default_rng(args.seed), full, coarse,
                                interaction="right_hand", chair="armchair",
                                duration=args.duration)
        times = np.arange(0.0, seq.motion.duration, 1.0 / args.fps)
        truth = ground_truth("bench", seq.motion, times, seq.placement, full, coarse,
                             fps=args.fps)
        src = Path(tmp) / "bench" / "processed.h5"
        write_processed(src, truth)
        cache = Path(tmp) / "shapes"
        lib = load_shape_library(args.shapes, cache_dir=cache)  # cleaned once, not timed
        print(f"sequence: {truth.num_frames} frames at {args.fps:g} fps; {lib.summary()}")
        t0 = time.perf_counter()
        summary = augment_dataset([src], args.shapes, Path(tmp) / "out",
                                  per_sequence=args.per_sequence, seed=args.seed,
                                  workers=args.workers, cache_dir=cache)
        wall = time.perf_counter() - t0
    samples = len(summary.sequences)
    frames = samples * truth.num_frames
    per_sample = [s["stats"]["seconds"] for s in summary.sequences
                  if s.get("stats") and s["stats"].get("seconds")]
    print(summary.text())
    one = float(np.mean(per_sample)) if per_sample else float("nan")
    print(f"{samples} samples x {truth.num_frames} frames in {wall:.1f} s with {args.workers} "
          f"worker(s): {frames / wall:.2f} frames/s processed, "
          f"{summary.kept * truth.num_frames / wall:.2f} kept frames/s; one sample "
          f"{one:.1f} s on one thread ({truth.num_frames / one:.2f} frames/s); cores "
          f"{os.cpu_count()}, load average "
          f"{', '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
