"""Benchmark: synthesis frames per second of the runtime controller, one character and a batch.

Runs :class:`couch.synthesis.Synthesizer` (COUCH: ControlNet + PoseNet; ``--method baseline``
for NSM+Control) on an armchair with a left-armrest contact, the characters starting within
the control radius so that ControlNet runs on every frame (the costlier case). Prints frames per
second (characters x frames / wall time, features, networks and state update included; the
SMPL conversion after the loop not) for a batch of 1 and of ``--batch``, and their ratio to real
time (30 fps). Each is timed ``--repeats`` times in one process: the median is the number to
quote, the best and worst show the spread (on a shared 2-core machine, where the networks' weights
compete for the memory bus and cache, runs of the same command vary by 10-20 %).

Without ``--run`` it first trains a throwaway run (not timed): the ``paper`` preset's network
sizes for one epoch on two simulated sequences, so the timing is that of the paper's networks
(speed does not depend on how well they are trained).

Each weight precision of the runtime (``Synthesizer(precision=...)``: fp32 as trained, fp16,
int8; ``--precision`` picks some) is timed, and the largest joint difference its motion has from
the fp32 motion is printed beside it.

Run: ``python -m couch.tools.bench.synthesis [--run RUN] [--batch 64] [--seconds 4]
[--repeats 5] [--precision fp32,fp16,int8] [--threads 1]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np
import torch

from couch.synthesis import PRECISIONS, Scene, Synthesizer, train
from couch.tools.sim.chairs import make_chair, random_chair_spec
from couch.tools.sim.session import simulate_motion_dataset


def _throwaway_run(folder: str) -> str:
    simulate_motion_dataset(f"{folder}/data", 2, seed=11, progress=False)
    train([f"{folder}/data"], f"{folder}/run", net="all", preset="paper", epochs=1,
          progress=False)
    return f"{folder}/run"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", help="trained run (default: a 1-epoch paper-size throwaway run)")
    ap.add_argument("--method", default="couch", choices=["couch", "baseline"])
    ap.add_argument("--hand-ik", action="store_true", help="couch with runtime hand IK")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--seconds", type=float, default=4.0, help="synthesised seconds per run")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per batch size")
    ap.add_argument("--precision", default=",".join(PRECISIONS),
                    help="comma-separated runtime weight precisions to time")
    args = ap.parse_args(argv)
    precisions = [p.strip() for p in args.precision.split(",") if p.strip()]
    bad = [p for p in precisions if p not in PRECISIONS]
    if bad:
        ap.error(f"unknown precision(s) {bad}; choose from {', '.join(PRECISIONS)}")
    if args.repeats < 1:
        ap.error(f"--repeats must be at least 1, got {args.repeats}")
    torch.set_num_threads(args.threads)
    chair = make_chair(random_chair_spec(np.random.default_rng(4), "armchair"))
    left = np.asarray(chair.landmarks.left_armrest)
    series = np.array([[left, [np.nan] * 3]])
    with tempfile.TemporaryDirectory() as tmp:
        run = args.run or _throwaway_run(tmp)
        print(f"run {run} ({args.method}); {args.seconds:g} s per run, {args.threads} thread(s)")
        reference = None
        for precision in precisions:
            syn = Synthesizer(run, args.method, hand_ik=args.hand_ik, precision=precision)
            scene = Scene.from_mesh(chair.vertices, chair.faces, syn.cfg)
            syn.synthesize(scene, np.array([[0.2, 1.0, np.pi]]), series, 0.5)  # warm-up
            for batch in (1, args.batch):
                starts = np.tile([0.2, 1.0, np.pi], (batch, 1))
                times = []
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    r = syn.synthesize(scene, starts, series, args.seconds)
                    times.append(time.perf_counter() - t0)
                assert r.control_on[..., 0].mean() > 0.5 or args.method == "baseline"
                rates = batch * r.num_frames / np.array(times)
                fps, dt = float(np.median(rates)), float(np.median(times))
                diff = ""
                if batch == 1:
                    if precision == "fp32":
                        reference = r.joints
                    elif reference is not None:
                        diff = (f"; joints within {100 * np.abs(r.joints - reference).max():.2f}"
                                f" cm of fp32's")
                print(f"{precision} batch {batch:3d}: {fps:8.0f} frames/s = "
                      f"{fps / syn.cfg.fps:6.1f}x real time (median of {args.repeats}; "
                      f"{rates.min():.0f}-{rates.max():.0f}; {dt:.2f} s for {r.num_frames} "
                      f"frames){diff}")


if __name__ == "__main__":
    main()
