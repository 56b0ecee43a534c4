"""Command-line entry points of the capture stage.

``couch-calibrate SESSION_DIR [--out FILE] [--given FILE] [--reference SERIAL]
[--floor-frames N]``: multi-camera extrinsics of a recorded session
(:func:`couch.capture.calibration.calibrate_session`), written to ``SESSION_DIR/extrinsics.json``
by default, with a per-camera report of reprojection errors and board frames.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from .azure_mkv import KinectFormatError
from .calibration import CalibrationError, Extrinsics, calibrate_session

__all__ = ["calibrate_main", "format_report"]


def format_report(ext: Extrinsics) -> str:
    """A human-readable table of an :class:`Extrinsics`: per camera its position in the world
    (metres), reprojection error (pixels) and board frames used/seen; then the floor fit."""
    lines = [f"{'camera':<14} {'x':>7} {'y':>7} {'z':>7} {'reproj mean':>12} {'max':>7} "
             f"{'frames used/seen':>17}"]
    for serial in ext.serials:
        cam = ext.cameras[serial]
        x, y, z = cam.world_from_color[:3, 3]
        mark = " (reference)" if serial == ext.reference else ""

        def px(v: float) -> str:
            return "-" if math.isnan(v) else f"{v:.3f}"

        lines.append(f"{serial:<14} {x:7.3f} {y:7.3f} {z:7.3f} "
                     f"{px(cam.reprojection_mean_px):>12} {px(cam.reprojection_max_px):>7} "
                     f"{cam.frames_used:>8}/{cam.frames_seen:<8}{mark}")
    if ext.floor is not None:
        lines.append(f"floor: plane fit rms {ext.floor.rms_m * 1000:.1f} mm over "
                     f"{ext.floor.inliers} points; world +Y up, floor at y = 0")
    rms = ext.method.get("reprojection_rms_px")
    if rms is not None:
        lines.append(f"joint refinement: {ext.method.get('corners')} corners in "
                     f"{ext.method.get('frames_refined')} frames, rms {rms:.3f} px")
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="couch-calibrate",
        description="Multi-camera extrinsics of a session from its ChArUco board captures "
                    "(calibration/<serial>.mkv), levelled with the floor seen in "
                    "kinect/<serial>.mkv: world +Y up, floor at y = 0.")
    ap.add_argument("session", type=Path, help="the session folder (with session.json)")
    ap.add_argument("--out", type=Path, default=None,
                    help="where to write extrinsics.json (default: SESSION/extrinsics.json)")
    ap.add_argument("--given", type=Path, default=None,
                    help="use these extrinsics instead of calibrating (checked against the "
                         "session's cameras, then written to --out)")
    ap.add_argument("--reference", default=None,
                    help="reference camera serial (default: the first, the sync master)")
    ap.add_argument("--floor-frames", type=int, default=1,
                    help="depth frames per camera for the floor fit (default 1)")
    return ap


def calibrate_main(argv: list[str] | None = None) -> int:
    """``couch-calibrate``: 0 on success (report on stdout), 1 with a message on stderr when the
    session cannot be calibrated (never saw the board, disconnected cameras, unreadable
    recordings or extrinsics file)."""
    args = _parser().parse_args(argv)
    prog = "couch-calibrate"
    if not args.session.is_dir():
        print(f"{prog}: {args.session} is not a folder", file=sys.stderr)
        return 1
    if args.floor_frames < 1:
        print(f"{prog}: --floor-frames must be >= 1, got {args.floor_frames}", file=sys.stderr)
        return 1
    out = args.out if args.out is not None else args.session / "extrinsics.json"
    try:
        ext = calibrate_session(args.session, given=args.given, output=out,
                                reference=args.reference, floor_frames=args.floor_frames)
    except (CalibrationError, KinectFormatError, OSError) as err:
        print(f"{prog}: {err}", file=sys.stderr)
        return 1
    print(format_report(ext))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(calibrate_main())
