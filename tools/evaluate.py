"""``couch-eval RUN -o OUT``: the COUCH evaluation protocol (paper Sec. 5) for a trained run.

COUCH (ControlNet + PoseNet) and the NSM+Control baseline of the same run (``couch-train --net
all`` trains both on the same data; ``--baseline-run`` takes it from another run) are driven by
:func:`couch.synthesis.evaluation.evaluate` on held-out chairs: ``--chairs N`` new chairs drawn
by the simulator (armchair, straight, sofa in turn; never seen in training), or every OBJ/PLY of
``--chair-dir`` (in the chair frame). ``--data`` adds a ground-truth row (APDs of those
sequences). Writes ``OUT/eval.md`` (the table, bootstrap intervals, and ACE / AP@5 per kind of
asked contact: chair kind and part), ``OUT/eval.json`` (rows, intervals, that breakdown and
the settings) and ``OUT/trials.npz`` (every trial's closest hand distances per method, for
paired comparisons across runs: see :func:`load_trials`). ``--methods ...,nsm`` also drives the
plain NSM of the run (``couch-train --net nsm``: the pose network with no contact input, the
paper's Table 2's first row), and every other method's ACE reduction against it is given beside
the one against the baseline.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from couch.atomic import atomic_path
from couch.cli import parse_args
from couch.schema import SchemaError
from couch.synthesis import (
    Synthesizer,
    contact_intervals,
    format_intervals,
    format_table,
    parse_which,
)
from couch.synthesis.data import find_sequences, load_sequence
from couch.synthesis.evaluation import (
    EvalChair,
    contact_breakdown,
    evaluate,
    ground_truth_row,
    miss_breakdown,
)
from couch.tools.sim.chairs import load_mesh, make_chair, random_chair_spec
from couch.tools.synthesize import add_runtime_arguments

__all__ = ["load_trials", "main", "simulated_chairs"]

_KINDS = ("armchair", "straight", "sofa")
#: A method name ending in this runs that method with ``Synthesizer(hand_ik=True)``.
IK_SUFFIX = "+ik"


def simulated_chairs(count: int, seed: int) -> list[EvalChair]:
    """``count`` new parametric chairs (kinds in turn) from ``seed``."""
    rng = np.random.default_rng([seed, 7919])  # a stream no training simulation uses
    out = []
    for i in range(count):
        kind = _KINDS[i % len(_KINDS)]
        c = make_chair(random_chair_spec(rng, kind))
        out.append(EvalChair(f"{kind}_{i:02d}", c.vertices, c.faces))
    return out


def save_trials(path: Path, raw: dict[str, np.ndarray], labels: np.ndarray,
                chairs: Sequence[str], trials: int,
                misses: dict[str, dict[str, np.ndarray]] | None = None) -> None:
    """Write ``trials.npz``: ``distance/<method>`` (N, 2) closest hand-surface distance to
    each asked contact (m; NaN: none asked), ``labels`` (N, 2) what was asked (``"<chair
    kind> <part>"``), ``chair`` (N,) the chair's name; N = chairs x trials, chair-major; with
    ``misses`` (:func:`~couch.synthesis.evaluation.evaluate`'s fourth output) also
    ``offset/<method>`` (N, 2, 3) where the closest hand point was relative to its contact
    (chair frame, m) and ``seated/<method>`` (N, 2) whether the pelvis had sat by then."""
    arrays = {f"distance/{m}": np.asarray(d, np.float64) for m, d in raw.items()}
    for m, miss in (misses or {}).items():
        arrays.update({f"{k}/{m}": np.asarray(v, np.float64) for k, v in miss.items()})
    with atomic_path(path) as tmp:
        np.savez(tmp, labels=np.asarray(labels).astype(str),
                 chair=np.repeat(np.asarray(chairs, dtype=str), trials), **arrays)


def load_trials(path: str | Path) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """``(distances {method: (N, 2)}, labels (N, 2), chair (N,))`` from a ``couch-eval``
    output folder or its ``trials.npz``. Two evaluations with the same ``--chairs``,
    ``--trials`` and ``--seed`` ran the same trials, so their distances pair up row by row,
    e.g. for :func:`couch.synthesis.contact_intervals` of one run's method against another's.
    """
    p = Path(path)
    p = p / "trials.npz" if p.is_dir() else p
    try:
        with np.load(p, allow_pickle=False) as z:
            dist = {k.removeprefix("distance/"): z[k] for k in z.files
                    if k.startswith("distance/")}
            if dist and "labels" in z.files and "chair" in z.files:
                return dist, z["labels"], z["chair"]
    except FileNotFoundError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise ValueError(f"{p}: cannot read ({e})") from e
    raise ValueError(f"{p}: not a couch-eval trials.npz (distance/<method>, labels, chair)")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="couch-eval", description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="couch-train output folder")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--baseline-run", help="run with the baseline net (default: RUN)")
    p.add_argument("--methods", default="couch,couch+ik,baseline",
                   help="comma-separated: couch, baseline, couch+ik (couch with hand IK), nsm "
                        "(the plain NSM, trained with couch-train --net nsm)")
    p.add_argument("--chairs", type=int, default=6, help="held-out simulated chairs")
    p.add_argument("--chair-dir", help="evaluate on these chair meshes instead")
    p.add_argument("--trials", type=int, default=8, help="trials per chair")
    p.add_argument("--seconds", type=float, default=16.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--contact-samples", type=int, default=16,
                   help="ContactNet samples per chair for contact APD (0: skip)")
    p.add_argument("--data", nargs="*", default=[], help="ground-truth sequences for APD")
    add_runtime_arguments(p)
    p.add_argument("--foot-lock", action="store_true",
                   help="every method: hold planted feet by leg IK after synthesis (a "
                        "post-process; off: the networks' own feet)")
    p.add_argument("-q", "--quiet", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``couch-eval``; 0 on success, 2 on bad arguments or input."""
    args = parse_args(_parser(), argv)
    if isinstance(args, int):  # --help or a usage error argparse printed
        return args
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    try:
        if args.trials < 1 or args.seconds <= 0 or (args.chairs < 1 and not args.chair_dir):
            raise ValueError("--trials, --seconds and --chairs must be positive")
        methods = [m.strip() for m in args.methods.split(",") if m.strip()]
        which = parse_which(args.which)
        synths = {m: Synthesizer(args.baseline_run if m == "baseline" and args.baseline_run
                                 else args.run, m.removesuffix(IK_SUFFIX), which=which,
                                 hand_ik=m.endswith(IK_SUFFIX), precision=args.precision,
                                 foot_lock=args.foot_lock)
                  for m in methods}
        if args.chair_dir:
            paths = sorted(p for p in Path(args.chair_dir).iterdir()
                           if p.suffix.lower() in (".obj", ".ply"))
            if not paths:
                raise ValueError(f"{args.chair_dir}: no .obj/.ply chair meshes")
            chairs = [EvalChair(p.stem, *load_mesh(p)) for p in paths]
        else:
            chairs = simulated_chairs(args.chairs, args.seed)
        rows, raw, labels, misses = evaluate(
            synths, chairs, trials=args.trials, seconds=args.seconds, seed=args.seed,
            contact_samples=args.contact_samples, progress=not args.quiet)
        breakdown = contact_breakdown(raw, labels)
        where = miss_breakdown(misses, labels)
        intervals = contact_intervals(raw, "baseline" if "baseline" in raw else None,
                                      seed=args.seed)
        if "nsm" in raw:  # the paper's Table 2 also compares with the plain NSM
            for m, stats in contact_intervals(raw, "nsm", seed=args.seed).items():
                if "ACE reduction %" in stats:
                    intervals[m]["ACE reduction vs NSM %"] = stats["ACE reduction %"]
        if args.data:
            sessions = [load_sequence(r) for r in find_sequences(args.data)]
            rows["ground truth"] = ground_truth_row(sessions)
    except (FileNotFoundError, ValueError, SchemaError) as e:
        print(f"couch-eval: error: {e}", file=sys.stderr)
        return 2
    table = (format_table(rows) + "\n\n" + format_intervals(intervals, len(chairs) * args.trials)
             + "\n\nPer kind of asked contact (chair kind, part; n hands):\n\n"
             + format_table(breakdown, first="contact")
             + "\n\nWhere the hands stop (medians per kind of asked contact: the closest hand "
               "point's height above its contact along the chair's up, its distance from it "
               "across, and the share of closest approaches made already seated):\n\n"
             + format_table(where, first="contact"))
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    settings = {k: v for k, v in vars(args).items() if k not in ("output", "quiet")}
    header = (f"couch-eval: {len(chairs)} chairs x {args.trials} trials x {args.seconds:g} s "
              f"(seed {args.seed}, {args.precision} weights"
              f"{', feet locked' if args.foot_lock else ''}), "
              f"{time.perf_counter() - t0:.0f} s\n\n")
    with atomic_path(out / "eval.md") as tmp:
        tmp.write_text(header + table + "\n")
    with atomic_path(out / "eval.json") as tmp:
        tmp.write_text(json.dumps({"settings": settings, "rows": rows,
                                   "intervals": intervals, "breakdown": breakdown,
                                   "where": where}, indent=2, default=float) + "\n")
    save_trials(out / "trials.npz", raw, labels, [c.name for c in chairs], args.trials,
                misses)
    print(header + table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
