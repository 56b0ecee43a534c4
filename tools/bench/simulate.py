"""Benchmark: simulator throughput, measured in one run on this machine.

Prints the seconds to simulate a session of ``--duration`` s with ``--cameras`` cameras at full
Azure resolution (NFOV unbinned depth, 720p colour, 30 fps) and its ratio to real time, and the
frames per second of ``--motion-only`` (ground-truth motion, no rendering), once per
``--workers`` count with its speed-up over the first (the same files each time).
Run: ``python -m couch.tools.bench.simulate [--workers 1,2] [--no-session]`` (about 5-10
minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from couch.tools.sim.session import SessionConfig, simulate_motion_dataset, simulate_session


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--sequences", type=int, default=10, help="for --motion-only")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", default="1",
                    help="comma-separated worker counts for --motion-only (e.g. 1,2)")
    ap.add_argument("--no-session", action="store_true", help="time --motion-only only")
    args = ap.parse_args(argv)
    counts = [int(w) for w in args.workers.split(",") if w.strip()]
    first = None
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            start = time.perf_counter()
            summary = simulate_motion_dataset(Path(tmp) / f"motion{n}", args.sequences,
                                              args.seed, progress=False, workers=n)
            motion_s = time.perf_counter() - start
            frames = summary["frames"]
            first = first or motion_s
            print(f"motion-only, {n} worker(s): {args.sequences} sequences, {frames} frames at "
                  f"30 fps in {motion_s:.1f} s = {frames / motion_s:.0f} frames/s "
                  f"({frames / 30 / motion_s:.1f}x real time; {first / motion_s:.2f}x the "
                  f"first count's speed)")
        if args.no_session:
            return
        start = time.perf_counter()
        simulate_session(Path(tmp) / "session", SessionConfig(
            duration=args.duration, cameras=args.cameras, seed=args.seed), progress=False)
        session_s = time.perf_counter() - start
    print(f"session: {args.duration:g} s, {args.cameras} cameras (640x576 depth, 1280x720 "
          f"colour, 30 fps) in {session_s:.1f} s = {session_s / args.duration:.1f}x real time "
          f"({session_s / (args.duration * 30 * args.cameras) * 1000:.0f} ms per camera-frame)")


if __name__ == "__main__":
    main()
