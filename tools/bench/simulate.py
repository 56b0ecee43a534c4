"""Benchmark: simulator throughput, measured in one run on this machine.

Prints the seconds to simulate a session of ``--duration`` s with ``--cameras`` cameras at full
Azure resolution (NFOV unbinned depth, 720p colour, 30 fps) and its ratio to real time, and the
frames per second of ``--motion-only`` (ground-truth motion, no rendering).
Run: ``python -m couch.tools.bench.simulate`` (about 5-10 minutes on 2 cores).
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
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        summary = simulate_motion_dataset(Path(tmp) / "motion", args.sequences, args.seed,
                                          progress=False)
        motion_s = time.perf_counter() - start
        start = time.perf_counter()
        simulate_session(Path(tmp) / "session", SessionConfig(
            duration=args.duration, cameras=args.cameras, seed=args.seed), progress=False)
        session_s = time.perf_counter() - start
    frames = summary["frames"]
    print(f"motion-only: {args.sequences} sequences, {frames} frames at 30 fps in "
          f"{motion_s:.1f} s = {frames / motion_s:.0f} frames/s "
          f"({frames / 30 / motion_s:.1f}x real time)")
    print(f"session: {args.duration:g} s, {args.cameras} cameras (640x576 depth, 1280x720 "
          f"colour, 30 fps) in {session_s:.1f} s = {session_s / args.duration:.1f}x real time "
          f"({session_s / (args.duration * 30 * args.cameras) * 1000:.0f} ms per camera-frame)")


if __name__ == "__main__":
    main()
