"""``couch-select CANDIDATE... -o RUN``: keep the trained networks that synthesise best on
validation chairs.

The ``cpu`` recipe's trainings differ by seed more than by anything else tried (README,
*Results so far*: couch's ACE 1.71-2.60 cm on one test set over three trainings of the same
data, the baseline 3.95-5.06), and a network's validation loss does not rank trainings by how
they synthesise (each seed holds out other chairs for it). So train a few (``couch-train ...
--seed S``, one run folder each) and let this tool score them the way they will be used: every
candidate PoseNet paired with every candidate ControlNet (the two are trained apart, so any
pair is a COUCH), and every candidate baseline, each run closed loop through
:func:`couch.synthesis.evaluation.evaluate` on the same ``--chairs`` new simulated chairs x
``--trials`` trials. The pair with the lowest ACE and the baseline with the lowest ACE are
copied into ``RUN`` (``best.pt`` and ``stats.npz`` of each, with its ``log.csv`` and
``curves.png``; ContactNet from the chosen PoseNet's candidate, or the first that has one),
beside ``RUN/selection.md`` and ``RUN/selection.json``: every candidate's row, what was kept
and where it came from.

Both methods are chosen by the same rule on the same chairs, so a comparison of the selected
run stays fair; report it on chairs the selection did not see (``couch-eval --seed`` other
than this ``--seed``, 7 by default).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from couch.atomic import atomic_path
from couch.cli import parse_args
from couch.schema import SchemaError
from couch.synthesis import Synthesizer, format_table
from couch.synthesis.evaluation import evaluate
from couch.tools.evaluate import simulated_chairs

__all__ = ["Selection", "main", "select_networks"]

#: What a network folder of a selected run holds (inference needs the first two).
_KEPT_FILES = ("best.pt", "stats.npz", "log.csv", "curves.png")


@dataclass
class Selection:
    """What :func:`select_networks` kept.

    Attributes:
        pose, control, baseline, contact: the candidate run folder each network was copied
            from (``None``: no candidate had one).
        rows: every scored method's table row (``couch-eval``'s metrics), keyed
            ``"couch <pose run> + <control run>"`` and ``"baseline <run>"`` by the candidates'
            indices (``#0``, ``#1``... in the order given).
        settings: chairs, trials, seconds and seed of the scoring.
    """

    pose: Path | None
    control: Path | None
    baseline: Path | None
    contact: Path | None
    rows: dict[str, dict[str, float]] = field(default_factory=dict)
    settings: dict[str, float] = field(default_factory=dict)

    def sources(self) -> dict[str, Path | None]:
        """Network name -> the candidate run it was copied from."""
        return {"pose": self.pose, "control": self.control, "baseline": self.baseline,
                "contact": self.contact}


def _has(run: Path, net: str) -> bool:
    return (run / net / "best.pt").is_file() and (run / net / "stats.npz").is_file()


def _check_features(synths: dict[str, Synthesizer]) -> None:
    """Every method must read the features the chairs' scenes are built with (the first's)."""
    seen = {m: json.dumps(dataclasses.asdict(s.cfg), sort_keys=True, default=str)
            for m, s in synths.items()}
    first = next(iter(seen))
    for m, text in seen.items():
        if text != seen[first]:
            raise ValueError(f"{m} and {first} were trained on different features; select "
                             f"among runs trained on one feature cache")


def _copy_net(src: Path, dst: Path) -> None:
    """``src``'s inference files into the new folder ``dst``, whole or not at all."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.", dir=dst.parent))
    try:
        for name in _KEPT_FILES:
            if (src / name).is_file():
                shutil.copy2(src / name, tmp / name)
        tmp.rename(dst)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def select_networks(candidates: Sequence[str | Path], out: str | Path, *, chairs: int = 12,
                    trials: int = 16, seconds: float = 16.0, seed: int = 7,
                    progress: bool = True) -> Selection:
    """Score the candidates' networks on ``chairs`` new chairs and copy the best into ``out``.

    Args:
        candidates: ``couch-train`` run folders trained on the same features (at least one
            with ``pose`` and one with ``control``, or one with ``baseline``).
        out: the selected run's folder (created; it must not hold a network folder yet).
        chairs, trials, seconds, seed: the protocol of ``couch-eval`` on these (validation)
            chairs; each COUCH pair and each baseline runs the same trials.

    Returns:
        The :class:`Selection` (also written as ``out/selection.json`` and ``selection.md``).

    Raises:
        FileNotFoundError: a candidate folder is missing.
        ValueError: nothing to select, bad counts, or ``out`` already holds networks.
    """
    runs = [Path(c) for c in candidates]
    for r in runs:
        if not r.is_dir():
            raise FileNotFoundError(f"{r}: no such run folder")
    if chairs < 1 or trials < 1 or seconds <= 0:
        raise ValueError("chairs, trials and seconds must be positive")
    out = Path(out)
    if out.exists() and not out.is_dir():  # checked before the minutes of scoring
        raise ValueError(f"{out}: not a folder")
    taken = [n for n in ("pose", "control", "baseline", "contact") if (out / n).exists()]
    if taken:
        raise ValueError(f"{out}: already holds {', '.join(taken)}; choose a new folder")
    poses = [i for i, r in enumerate(runs) if _has(r, "pose")]
    controls = [i for i, r in enumerate(runs) if _has(r, "control")]
    baselines = [i for i, r in enumerate(runs) if _has(r, "baseline")]
    if not (poses and controls) and not baselines:
        raise ValueError(f"{', '.join(map(str, runs))}: no trained pose + control pair nor "
                         f"baseline (best.pt and stats.npz) to select from")
    # method name -> candidate indices: (PoseNet, ControlNet) for a pair, (baseline,) else
    picks = {f"couch #{p} + #{c}": (p, c) for p in poses for c in controls}
    picks.update({f"baseline #{b}": (b,) for b in baselines})
    with tempfile.TemporaryDirectory(prefix=".couch-select-") as tmp:
        synths: dict[str, Synthesizer] = {}
        for name, idx in picks.items():
            if len(idx) == 1:
                synths[name] = Synthesizer(runs[idx[0]], "baseline")
                continue
            # A run folder of symbolic links: the controller loads RUN/pose and RUN/control.
            pair = Path(tmp) / f"pair_{idx[0]}_{idx[1]}"
            pair.mkdir()
            for net, i in zip(("pose", "control"), idx, strict=True):
                (pair / net).symlink_to((runs[i] / net).resolve(), target_is_directory=True)
            synths[name] = Synthesizer(pair, "couch")
        _check_features(synths)
        rows, *_ = evaluate(synths, simulated_chairs(chairs, seed), trials=trials,
                            seconds=seconds, seed=seed, progress=progress)

    def best(prefix: str) -> str | None:
        names = [m for m in rows if m.startswith(prefix)]
        return min(names, key=lambda m: rows[m]["ACE cm"]) if names else None

    chosen_pair = best("couch ")
    chosen_base = best("baseline ")
    pose, control = picks[chosen_pair] if chosen_pair is not None else (None, None)
    baseline = picks[chosen_base][0] if chosen_base is not None else None
    contacts = [i for i, r in enumerate(runs) if _has(r, "contact")]
    contact = (pose if pose in contacts else contacts[0]) if contacts else None
    sel = Selection(*(runs[i] if i is not None else None
                      for i in (pose, control, baseline, contact)),
                    rows=rows, settings={"chairs": chairs, "trials": trials,
                                         "seconds": seconds, "seed": seed})
    out.mkdir(parents=True, exist_ok=True)
    for net, src in sel.sources().items():
        if src is not None:
            _copy_net(src / net, out / net)
    _write(out, runs, sel, chosen_pair, chosen_base)
    return sel


def _write(out: Path, runs: list[Path], sel: Selection, pair: str | None,
           base: str | None) -> None:
    names = "\n".join(f"- #{i}: `{r}`" for i, r in enumerate(runs))
    kept = "\n".join(f"- {net}: `{src}`" for net, src in sel.sources().items()
                     if src is not None)
    s = sel.settings
    text = (f"couch-select: {s['chairs']} chairs x {s['trials']} trials x {s['seconds']:g} s "
            f"(seed {s['seed']}); the lowest ACE kept: {pair or '-'}, {base or '-'}\n\n"
            f"Candidates:\n\n{names}\n\n{format_table(sel.rows)}\n\nKept:\n\n{kept}\n")
    with atomic_path(out / "selection.md") as tmp:
        tmp.write_text(text)
    doc = {"candidates": [str(r) for r in runs], "settings": sel.settings, "rows": sel.rows,
           "chosen": {"couch": pair, "baseline": base},
           "sources": {net: (str(src) if src is not None else None)
                       for net, src in sel.sources().items()}}
    with atomic_path(out / "selection.json") as tmp:
        tmp.write_text(json.dumps(doc, indent=2, default=float) + "\n")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="couch-select", description=__doc__.split("\n\n")[0])
    p.add_argument("candidates", nargs="+", help="couch-train run folders (e.g. one per seed)")
    p.add_argument("-o", "--output", required=True, help="the selected run's folder (new)")
    p.add_argument("--chairs", type=int, default=12, help="validation chairs (simulated)")
    p.add_argument("--trials", type=int, default=16, help="trials per chair")
    p.add_argument("--seconds", type=float, default=16.0)
    p.add_argument("--seed", type=int, default=7,
                   help="validation chairs' seed: report the selected run on another one")
    p.add_argument("-q", "--quiet", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``couch-select``; 0 on success, 2 on bad arguments or input."""
    args = parse_args(_parser(), argv)
    if isinstance(args, int):  # --help or a usage error argparse printed
        return args
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    try:
        sel = select_networks(args.candidates, args.output, chairs=args.chairs,
                              trials=args.trials, seconds=args.seconds, seed=args.seed,
                              progress=not args.quiet)
    except (OSError, ValueError, SchemaError) as e:
        print(f"couch-select: error: {e}", file=sys.stderr)
        return 2
    print(format_table(sel.rows))
    print(f"\nkept in {args.output} ({time.perf_counter() - t0:.0f} s): pose {sel.pose}, "
          f"control {sel.control}, baseline {sel.baseline}, contact {sel.contact}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
