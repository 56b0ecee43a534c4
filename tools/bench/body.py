"""Benchmark: batched LBS time of the bundled body models (batch 1 and 64, full and coarse).

Run: ``python -m couch.tools.bench.body`` (or ``make bench``). Prints milliseconds per call
(median of repeats, after warm-up) and the per-body speed-up of batch 64 over batch 1, all
measured in this one run on this machine.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from couch.body import load_body_model, sitting_pose


def time_call(fn, repeats: int) -> float:
    """Median seconds of ``fn()`` over ``repeats`` runs after two warm-up calls."""
    for _ in range(2):
        fn()
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t)
    return statistics.median(samples)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)
    dtype = getattr(torch, args.dtype)
    rng = np.random.default_rng(0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {args.dtype}, "
          f"{args.device}")
    print(f"{'model':<20}{'vertices':>9}{'batch 1 ms':>12}{'batch 64 ms':>13}"
          f"{'per-body speed-up':>19}")
    for name in ("couch-body", "couch-body-coarse"):
        model = load_body_model(name, dtype=dtype, device=args.device)
        results = {}
        for batch in (1, 64):
            pose = torch.as_tensor(np.tile(sitting_pose(), (batch, 1))
                                   + rng.normal(0, 0.1, (batch, 69)), dtype=dtype)
            betas = torch.as_tensor(rng.normal(0, 1, (batch, 10)), dtype=dtype)
            orient = torch.as_tensor(rng.normal(0, 0.3, (batch, 3)), dtype=dtype)

            def run(pose=pose, betas=betas, orient=orient, model=model):
                with torch.no_grad():
                    model(betas=betas, global_orient=orient, body_pose=pose)
                if args.device.startswith("cuda"):
                    torch.cuda.synchronize()

            results[batch] = time_call(run, args.repeats)
        speedup = results[1] * 64 / results[64]
        print(f"{name:<20}{model.num_vertices:>9}{results[1] * 1e3:>12.2f}"
              f"{results[64] * 1e3:>13.2f}{speedup:>18.1f}x")


if __name__ == "__main__":
    main()
