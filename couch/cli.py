"""Command-line entry points of the core (``couch-inspect``) and the argument parsing that
couch-train, -augment, -eval, -select and -synthesize share (:func:`parse_args`)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import numpy as np

from couch.geometry import transform_distance
from couch.schema import INTERACTION_LABELS, ProcessedSession, SchemaError, read_processed


def summarize(s: ProcessedSession) -> str:
    """Human summary of a processed session: frames, duration, contacts per part, object."""
    lines = [
        f"session        {s.session}",
        f"schema         v{s.schema_version} (written by couch {s.couch_version})",
        f"frames         {s.num_frames} at {s.fps:g} fps, {s.duration:.2f} s "
        f"({s.time[0]:.3f} .. {s.time[-1]:.3f} s, Kinect clock)",
        f"body           betas[:3] = {np.array2string(s.betas[:3], precision=2)}, "
        f"pelvis travel {np.linalg.norm(np.diff(s.joints[:, 0], axis=0), axis=1).sum():.2f} m",
    ]
    # processed.h5 leaves rows the chair was not registered on NaN
    estimated = np.isfinite(s.object_frame_poses).all(axis=(1, 2))
    angle, _ = transform_distance(s.object_pose[None], s.object_frame_poses[estimated])
    spread = f", per-frame spread {np.degrees(np.median(angle)):.2f} deg" if len(angle) else ""
    where = np.array2string(s.object_pose[:3, 3], precision=2)
    lines.append(f"object         {s.object_name}: {len(s.object_vertices)} vertices, "
                 f"{len(s.object_faces)} faces, at {where} m{spread}")
    lines.append("contacts       part          frames   share")
    for i, name in enumerate(s.contact_names):
        n = int(s.contact_active[:, i].sum())
        lines.append(f"               {name:<13} {n:>6}  {100 * n / max(s.num_frames, 1):5.1f}%")
    lines.append("interaction    label                 frames")
    counts = np.bincount(s.interaction.astype(np.int64), minlength=len(INTERACTION_LABELS))
    for label, n in enumerate(counts):
        if n:
            lines.append(f"               {label} {INTERACTION_LABELS[label]:<19} {n:>6}")
    if s.quality:
        lines.append("quality        " + ", ".join(
            f"{k} {np.shape(v)}" for k, v in sorted(s.quality.items())))
    return "\n".join(lines)


def parse_args(parser: argparse.ArgumentParser, argv: Sequence[str] | None
               ) -> argparse.Namespace | int:
    """``parser.parse_args(argv)``, or the exit code argparse chose (0 after ``--help``, 2 after
    a usage error it has already printed), so that a ``main`` can return it instead of raising
    ``SystemExit`` from inside a caller's process (tests, notebooks)."""
    try:
        return parser.parse_args(argv)
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else 2


def inspect_main(argv: list[str] | None = None) -> int:
    """``couch-inspect FILE``: print a summary; exit 1 with a clear message on an invalid file."""
    ap = argparse.ArgumentParser(prog="couch-inspect", description="Summarise a couch "
                                 "processed session (processed.h5 or ground_truth.h5).")
    ap.add_argument("file", help="processed.h5 or ground_truth.h5")
    args = ap.parse_args(argv)
    try:
        session = read_processed(args.file)
    except SchemaError as e:
        print(f"couch-inspect: invalid file: {e}", file=sys.stderr)
        return 1
    print(summarize(session))
    return 0


if __name__ == "__main__":
    sys.exit(inspect_main())
