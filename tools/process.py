"""``couch-process SESSION [-o OUT]``: a raw session to ``processed.h5`` and a QA report.

The pipeline itself is :func:`couch.fitting.pipeline.run_pipeline` (calibrate → chair → body →
contacts, each stage cached); this module adds the report (:func:`couch.tools.report.
write_report`) and the command line. ``couch.process`` is :func:`process`.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from couch.capture.calibration import Extrinsics
from couch.fitting.pipeline import (
    STAGES,
    PipelineResult,
    ProcessConfig,
    ProcessError,
    run_pipeline,
)
from couch.overrides import with_overrides

log = logging.getLogger(__name__)


def process(session_dir: str | os.PathLike, output: str | os.PathLike | None = None, *,
            stages: str | Sequence[str] | None = None, frames: str | tuple[int, int] | None = None,
            device: str | None = None, config: ProcessConfig | None = None,
            extrinsics: Extrinsics | str | os.PathLike | None = None, force: bool = False,
            report: bool = True, progress: bool = False, workers: int | None = None
            ) -> PipelineResult:
    """Process one session folder: ``processed.h5``, ``report/`` and ``cache/`` in ``output``.

    Args:
        session_dir: the raw session folder (``couch-simulate``'s layout / ``session.json``).
        output: the output folder; None: ``<session_dir>/processed``.
        stages: run up to the last stage named (of ``calibrate, chair, body, contacts``;
            comma-separated or a list; None: all). Stages up to it come from the cache when
            their inputs and config are unchanged.
        frames: ``(start, stop)`` or ``"start:stop"`` rows of the Kinect frame table to fit.
        device: torch device of the body fits (``cpu``, ``cuda``).
        config: :class:`~couch.fitting.pipeline.ProcessConfig`.
        extrinsics: camera poses to use instead of calibrating (``extrinsics.json`` path or
            :class:`~couch.capture.calibration.Extrinsics`).
        force: recompute every stage (the cache is rewritten).
        report: write ``report/`` (HTML page, plots, previews, ``summary.json``).
        progress: progress bars.
        workers: processes for the per-camera and per-frame work (1: none spawned; None:
            ``min(2, CPU count)``); the results do not depend on it.

    Returns:
        The :class:`~couch.fitting.pipeline.PipelineResult`. A session that cannot be processed
        does not raise: ``result.fault`` names the stage and the reason, and the report says
        what ran.

    Raises:
        ProcessError: the session folder does not exist, an unknown stage, a bad frame range,
            ``workers`` < 1.
    """
    result = run_pipeline(session_dir, output, stages=stages, frames=frames, device=device,
                          config=config, extrinsics=extrinsics, force=force, progress=progress,
                          workers=workers)
    if report:
        from couch.tools.report import write_report  # matplotlib only when a report is made

        result.report = write_report(result, result.output / "report", progress=progress)
    return result


def main(argv: list[str] | None = None) -> int:
    """``couch-process``: exit 0 when processed, 1 when a stage failed, 2 on bad arguments."""
    ap = argparse.ArgumentParser(
        prog="couch-process",
        description="Process a raw capture session (Azure Kinect MKV + Xsens MVNX + chair scan) "
                    "into processed.h5 (SMPL body, registered chair, contacts, labels) with an "
                    "HTML QA report. Stage results are cached in OUT/cache so a re-run resumes.")
    ap.add_argument("session", help="the session folder")
    ap.add_argument("-o", "--output", help="output folder (default: SESSION/processed)")
    ap.add_argument("--stages", default=None,
                    help=f"run up to the last stage named, comma-separated, of {', '.join(STAGES)}"
                         f" (default: all)")
    ap.add_argument("--frames", default=None, metavar="START:STOP",
                    help="rows of the Kinect frame table to fit (default: all the IMU covers)")
    ap.add_argument("--device", default=None, help="torch device of the body fits (cpu, cuda)")
    ap.add_argument("--extrinsics", default=None,
                    help="an extrinsics.json to use instead of calibrating")
    ap.add_argument("--chair-frames", type=int, default=None, metavar="N",
                    help="register the chair on N frames spread over the session (default 40; "
                         "0: every frame)")
    ap.add_argument("--fit-stride", type=int, default=None, metavar="K",
                    help="fit the body to the cameras on every K-th frame, the suit's motion "
                         "carrying the frames between (default 1: every frame; K times less "
                         "per-frame work; same as --set fit.fit_stride=K)")
    ap.add_argument("--depth-binning", type=int, default=None, choices=(1, 2),
                    help="2: read full-resolution depth (NFOV/WFOV unbinned) binned 2x2, as the "
                         "camera's binned modes do: about a third less time on such recordings; "
                         "binned recordings are read as they are (default 1; same as --set "
                         "fit.segmentation.depth_binning=2)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="change one setting of the processing config (repeatable), e.g. "
                         "fit.body.clothing_margin=0.005 or contacts.enter_distance=0.025; the "
                         "keys are ProcessConfig's fields, dotted (stages whose settings "
                         "change are recomputed, the others come from the cache)")
    ap.add_argument("--workers", type=int, default=None, metavar="N",
                    help="processes for the per-camera and per-frame work (default min(2, CPU "
                         "count); 1: none spawned); the results do not depend on it")
    ap.add_argument("--force", action="store_true", help="ignore cached stage results")
    ap.add_argument("--no-report", action="store_true", help="do not write report/")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress bars or warnings")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR if args.quiet else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    config = ProcessConfig()
    if args.chair_frames is not None:
        if args.chair_frames < 0:
            ap.error("--chair-frames must be >= 0")
        config = ProcessConfig(chair_frames=args.chair_frames)
    if args.fit_stride is not None:
        if args.fit_stride < 1:
            ap.error("--fit-stride must be >= 1")
        config = dataclasses.replace(config, fit=dataclasses.replace(
            config.fit, fit_stride=args.fit_stride))
    overrides = list(args.set)
    if args.depth_binning not in (None, config.fit.depth_binning):
        # first, so that a --set of the same key wins; the default left as it is (its key)
        overrides.insert(0, f"fit.segmentation.depth_binning={args.depth_binning}")
    try:
        config = with_overrides(config, overrides)
    except ValueError as exc:
        ap.error(str(exc))
    if args.workers is not None and args.workers < 1:
        ap.error("--workers must be >= 1")
    if args.extrinsics is not None and not Path(args.extrinsics).is_file():
        ap.error(f"--extrinsics {args.extrinsics}: no such file")
    try:
        result = process(args.session, args.output, stages=args.stages, frames=args.frames,
                         device=args.device, config=config, extrinsics=args.extrinsics,
                         force=args.force, report=not args.no_report, progress=not args.quiet,
                         workers=args.workers)
    except ProcessError as exc:
        print(f"couch-process: {exc}", file=sys.stderr)
        return 2
    print(result.summary())
    if result.fault is not None:
        stage, message = result.fault
        print(f"couch-process: failed at stage {stage}: {message}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
