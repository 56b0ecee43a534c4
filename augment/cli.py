"""``couch-augment``: swap the chairs of processed sessions for library shapes and re-pose the
bodies (:func:`couch.augment.dataset.augment_dataset`).

    couch-augment --shapes shapenet_chairs/ processed/ -o augmented/ --per-sequence 4

Exit status: 0 when at least one augmented sequence was kept, 1 when none was, 2 on bad
arguments or unreadable input (the message names the file).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from couch.augment.dataset import augment_dataset, find_processed
from couch.augment.ik import IKConfig
from couch.cli import parse_args
from couch.schema import SchemaError

__all__ = ["main"]


def _scale_range(text: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in text.split(","))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected 'a,b' (two numbers), got {text!r}") from exc
    if not 0 < a <= b:
        raise argparse.ArgumentTypeError(f"expected 0 < a <= b, got {text!r}")
    return a, b


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from exc
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {value}")
    return value


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="couch-augment",
        description="Augment processed sessions: place library chairs (ShapeNetCore v2 or a "
                    "folder of OBJ/PLY) at each session's chair, transfer the contacts part to "
                    "part, re-pose the body with IK, and write OUT/augmented.h5 (one group per "
                    "kept sequence) and OUT/summary.json (kept / rejected with reasons).")
    ap.add_argument("processed", nargs="+", metavar="PROCESSED",
                    help="processed.h5 files, or folders searched for processed.h5")
    ap.add_argument("--shapes", required=True, metavar="DIR", help="the shape library folder")
    ap.add_argument("-o", "--output", required=True, metavar="OUT", help="output folder")
    ap.add_argument("--per-sequence", type=_positive, default=4, metavar="K",
                    help="shapes drawn per sequence (default 4)")
    ap.add_argument("--scale-range", type=_scale_range, default=(0.9, 1.1), metavar="A,B",
                    help="uniform scale of each drawn shape, drawn in [A, B] (default 0.9,1.1)")
    ap.add_argument("--seed", type=int, default=0, help="seeds the draws and seat heights")
    ap.add_argument("--workers", type=_positive, default=None, metavar="N",
                    help="processes (default min(2, CPU count); 1: in this process)")
    ap.add_argument("--max-penetration", type=float, default=0.02, metavar="M",
                    help="reject when the 95th percentile of body-into-chair penetration "
                         "exceeds M metres (default 0.02)")
    ap.add_argument("--max-reach", type=float, default=0.02, metavar="M",
                    help="reject when the 95th percentile of the contact reach error exceeds "
                         "M metres (default 0.02)")
    ap.add_argument("--ik-iterations", type=_positive, default=IKConfig.iterations,
                    metavar="N", help=f"IK iterations (default {IKConfig.iterations})")
    ap.add_argument("--cache-dir", default=None,
                    help="shape cache folder (default ~/.cache/couch/shapes/<hash>)")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress bars or warnings")
    return ap


def main(argv: list[str] | None = None) -> int:
    """``couch-augment``: exit 0 when sequences were kept, 1 when none, 2 on bad arguments."""
    args = parse_args(_parser(), argv)
    if isinstance(args, int):  # --help or a usage error argparse printed
        return args
    logging.basicConfig(level=logging.ERROR if args.quiet else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")

    def fail(message: str) -> int:
        print(f"couch-augment: error: {message}", file=sys.stderr)
        return 2

    if not Path(args.shapes).is_dir():
        return fail(f"--shapes {args.shapes}: no such folder")
    try:
        files = find_processed(args.processed)
    except FileNotFoundError as exc:
        return fail(str(exc))
    try:
        summary = augment_dataset(
            files, args.shapes, args.output, per_sequence=args.per_sequence,
            scale_range=args.scale_range, seed=args.seed, workers=args.workers,
            progress=not args.quiet, cache_dir=args.cache_dir,
            ik_config=IKConfig(iterations=args.ik_iterations),
            max_penetration=args.max_penetration, max_reach=args.max_reach)
    except (SchemaError, ValueError, FileNotFoundError) as exc:
        return fail(str(exc))
    print(summary.text())
    if summary.kept == 0:
        print("couch-augment: no augmented sequence was kept", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
