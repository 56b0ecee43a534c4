"""Benchmark: ``couch-process`` end to end, as a multiple of real time, with the time per stage.

Simulates a session first (not timed; default: 4 cameras, NFOV_2X2BINNED depth, 30 fps, 10 s,
depth only, seed 5), then runs :func:`couch.process` on it with the cache ignored (``force``)
and prints the wall time of every stage and of the steps inside it, the recording's duration
over the total wall time (goal >= 1.0x real time), the CPU time of this process and of the
worker processes (joined when the run ends) with the cores they kept busy on average, and the
load average.

Run: ``python -m couch.tools.bench.process [SESSION_DIR] [--duration S] [--fps F] [--threads K]
[--workers N] [--no-report] [--set KEY=VALUE ...]`` (``--set``: ``couch-process``'s, e.g.
``fit.fit_stride=3``; ``--workers``: ``couch-process``'s, default ``min(2, cores)``).
``--threads 1`` (or ``OMP_WAIT_POLICY=PASSIVE``) keeps torch's OpenMP threads from
spin-waiting on a machine other processes keep busy (see ``couch.tools.bench.fitting``).
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

import torch

import couch
from couch.fitting.pipeline import STAGES, ProcessConfig
from couch.overrides import with_overrides
from couch.schema import read_processed


def bench(session: Path, output: Path, report: bool, config: ProcessConfig | None = None,
          workers: int | None = None) -> None:
    """Process ``session`` into ``output`` (no cache) with ``config`` (None: the default) on
    ``workers`` processes (None: couch-process's default) and print the timings."""
    cpu0, kids0, t0 = time.process_time(), _children_cpu(), time.perf_counter()
    result = couch.process(session, output, force=True, report=report, config=config,
                           workers=workers)
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    kids = _children_cpu() - kids0  # the run's workers: joined when it ends
    if not result.ok:
        print(result.summary())
        raise SystemExit(f"processing failed at {result.fault[0]}: {result.fault[1]}")
    data = read_processed(result.processed)
    duration = data.duration + 1.0 / data.fps
    print(f"session {session}: {data.num_frames} frames at {data.fps:g} fps ({duration:.1f} s), "
          f"{len(result.calibration.cameras)} cameras")
    print(f"{'stage':<10} {'wall s':>8}  steps (s)")
    for name in STAGES:
        run = result.stages[name]
        steps = ", ".join(f"{k} {v:.1f}" for k, v in run.steps.items())
        print(f"{name:<10} {run.seconds:8.1f}  {steps}")
    report_s = wall - result.seconds
    if report:
        print(f"{'report':<10} {report_s:8.1f}")
    print(f"total: {wall:.1f} s wall, {cpu:.1f} s CPU (this process) for {duration:.1f} s of "
          f"recording: {duration / wall:.2f}x real time ({duration / result.seconds:.2f}x "
          f"without the report); {1e3 * wall / data.num_frames:.0f} ms per frame of "
          f"{len(result.calibration.cameras)} cameras")
    print(f"CPU: {cpu + kids:.1f} s in all, {kids:.1f} s of it in the workers: "
          f"{(cpu + kids) / wall:.2f} cores busy on average")
    print(f"torch threads {torch.get_num_threads()}, workers {workers or 'default'}, cores "
          f"{os.cpu_count()}, load average "
          f"{', '.join(f'{x:.1f}' for x in os.getloadavg())}")


def _children_cpu() -> float:
    """User + system CPU seconds of this process's finished children."""
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("session", nargs="?", type=Path, default=None,
                    help="a session folder (default: simulate one)")
    ap.add_argument("--duration", type=float, default=10.0, help="simulated seconds")
    ap.add_argument("--fps", type=float, default=30.0, help="simulated Kinect frame rate")
    ap.add_argument("--seed", type=int, default=5, help="simulator seed")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--workers", type=int, default=None,
                    help="couch-process --workers (default: its default, min(2, cores))")
    ap.add_argument("--no-report", action="store_true", help="leave the report out")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="change one setting of the processing config (repeatable; "
                         "couch-process's --set), e.g. fit.fit_stride=3")
    args = ap.parse_args(argv)
    try:
        config = with_overrides(ProcessConfig(), args.set)
    except ValueError as exc:
        ap.error(str(exc))
    if args.set:
        print("settings: " + ", ".join(args.set))
    if args.threads:
        torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        session = args.session
        if session is None:
            from couch.tools.sim.session import SessionConfig, simulate_session

            cfg = SessionConfig(duration=args.duration, fps=args.fps, cameras=4,
                                depth_mode="NFOV_2X2BINNED", seed=args.seed, color=False)
            print(f"simulating a session (not timed): {cfg.duration:g} s at {cfg.fps:g} fps, "
                  f"{cfg.cameras} cameras, {cfg.depth_mode}, depth only, seed {cfg.seed}")
            session = Path(tmp) / "session"
            simulate_session(session, cfg, progress=False)
        bench(session, Path(tmp) / "out", not args.no_report, config, args.workers)


if __name__ == "__main__":
    main()
