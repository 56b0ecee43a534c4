"""Benchmark: couch-train's memory and epoch time with its rows in memory and streamed.

Trains one network (``--net pose`` by default; ``baseline`` and ``control`` too) for two epochs
twice, each in a fresh process: once with the rows copied into memory (the default) and once
streamed from ``features.h5`` (``couch-train --stream ROWS``). PoseNet's and the baseline's
first epoch is one-step pairs and the second closed loop (``rollout_epochs=1``), the two kinds
of epoch their presets train. Prints each mode's peak resident memory (the process's
``ru_maxrss``), its mean over the training (sampled every 0.5 s), the seconds of each epoch
(``log.csv``) and the whole call's wall time, then the streamed / in-memory ratios.

Data: ``DATA...`` as ``couch-train`` takes it; ``--cache FILE`` reuses a ``features.h5``
already built from the same DATA (symlinked into each throwaway run, so nothing is
recomputed or written beside it). Without DATA it first simulates ``--sequences`` motion
sequences (not timed), a size at which both modes fit anywhere; the numbers that matter come
from a large cache, e.g. 857 simulated sequences (README, *Training*).

Run: ``python -m couch.tools.bench.training [DATA...] [--cache RUN/features.h5]
[--net pose] [--preset cpu] [--stream 16384] [--sequences 6]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from couch.synthesis import preset_config, train


def _rss_gb() -> float:
    with open(f"/proc/{os.getpid()}/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**30


def _child(args: argparse.Namespace) -> None:
    """One training in this process; prints a JSON line of what it measured."""
    cfg = preset_config(args.net, args.preset, epochs=2)
    extra = ({"rollout_epochs": 1, "rollout": cfg.rollout or 8}
             if args.net in ("pose", "baseline") else {})
    cfg = dataclasses.replace(cfg, stream_rows=args.stream, **extra)
    samples: list[float] = []
    done = threading.Event()

    def sample() -> None:
        while not done.wait(0.5):
            samples.append(_rss_gb())

    watcher = threading.Thread(target=sample, daemon=True)
    watcher.start()
    t0 = time.perf_counter()
    result = train(args.data, args.run, net=args.net, preset=args.preset, progress=False,
                   configs={args.net: cfg}, resume=False)
    wall = time.perf_counter() - t0
    done.set()
    watcher.join()
    r = result.nets[args.net]
    print(json.dumps({"seconds": [h["seconds"] for h in r.history], "wall": wall,
                      "peak_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
                      "mean_gb": sum(samples) / max(1, len(samples)),
                      "train_loss": r.train_loss}))


def _measure(data: list[str], cache: str | None, run: Path, args: argparse.Namespace,
             stream: int) -> dict:
    run.mkdir(parents=True)
    if cache:
        (run / "features.h5").symlink_to(Path(cache).resolve())
    cmd = [sys.executable, "-m", "couch.tools.bench.training", *data, "--child", "--run",
           str(run), "--net", args.net, "--preset", args.preset, "--stream", str(stream)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"training ({'streamed' if stream else 'in memory'}) failed:\n"
                         f"{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", nargs="*", help="couch-train's DATA (default: simulate)")
    ap.add_argument("--cache", help="a features.h5 built from DATA, reused")
    ap.add_argument("--net", default="pose", choices=["pose", "baseline", "control"])
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--stream", type=int, default=16384, help="rows per streamed block")
    ap.add_argument("--sequences", type=int, default=6, help="simulated without DATA")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--run", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        _child(args)
        return
    if args.stream < 1:
        ap.error(f"--stream must be at least 1 row, got {args.stream}")
    if args.cache and not args.data:
        ap.error("--cache needs the DATA it was built from")
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if not data:
            from couch.tools.sim.session import simulate_motion_dataset

            simulate_motion_dataset(f"{tmp}/data", args.sequences, seed=11, progress=False)
            data = [f"{tmp}/data"]
        results = {}
        for name, rows in (("in memory", 0), ("streamed", args.stream)):
            results[name] = r = _measure(data, args.cache, Path(tmp) / name.replace(" ", "_"),
                                         args, rows)
            epochs = ", ".join(f"{s:.1f}" for s in r["seconds"])
            print(f"{args.net} ({args.preset}) {name:9s}: peak {r['peak_gb']:.2f} GB, mean "
                  f"{r['mean_gb']:.2f} GB; epochs {epochs} s; call {r['wall']:.1f} s", flush=True)
    mem, st = results["in memory"], results["streamed"]
    per_epoch = ", ".join(f"{b / a:.2f}x" for a, b in zip(mem["seconds"], st["seconds"],
                                                          strict=True))
    print(f"streamed / in memory: peak {st['peak_gb'] / mem['peak_gb']:.2f}x, mean "
          f"{st['mean_gb'] / mem['mean_gb']:.2f}x, epoch time {per_epoch}, call "
          f"{st['wall'] / mem['wall']:.2f}x ({args.stream} rows a block)")


if __name__ == "__main__":
    main()
