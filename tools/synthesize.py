"""``couch-synthesize RUN --chair MESH -o OUT``: synthesise approach-and-sit motions with hand
contacts from a trained run (``couch-train``), and write them with previews.

The chair mesh (OBJ/PLY) is read in the chair frame (metres, +Y up, floor y = 0, seat centred on
x = z = 0, facing +Z), which is also the world frame of the output. Contacts are given per hand
in that frame as ``x,y,z`` (``none`` for a hand without contact), the two hands separated by
``;`` (left first): ``--contacts "0.25,0.62,-0.05;none"``. Each ``--contacts`` (or each
ContactNet sample of ``--sample-contacts N``) is one character; with ``--series`` one character
follows them all in order. Starts are ``x,z,heading`` (heading in degrees from +Z towards +X);
the default stands 2.5 m in front of the chair facing it.

Writes ``OUT/synthesis.npz`` (the batch), ``OUT/<method>_<b>.h5`` (processed schema) per
character and ``OUT/<method>_<b>.mp4`` / ``.png`` previews of the first ``--preview`` ones.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from couch.body import load_body_model
from couch.cli import parse_args
from couch.geometry import apply_transform
from couch.schema import SchemaError
from couch.synthesis import (
    METHODS,
    PRECISIONS,
    Scene,
    SynthesisResult,
    Synthesizer,
    parse_which,
    sample_contacts,
    save_npz,
    write_processed_sessions,
)
from couch.tools.motion_preview import preview
from couch.tools.sim.chairs import load_mesh

__all__ = ["main", "parse_contacts", "parse_start", "render_previews"]


def _point(text: str, what: str) -> np.ndarray:
    text = text.strip()
    if text.lower() in ("none", "-", ""):
        return np.full(3, np.nan)
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise ValueError(f"{what}: expected x,y,z in metres or 'none', got {text!r}")
    return np.asarray(values)


def parse_contacts(text: str) -> np.ndarray:
    """``"x,y,z;x,y,z"`` (left;right, ``none`` for no contact) -> (2,3) with NaN rows."""
    parts = text.split(";")
    if len(parts) != 2:
        raise ValueError(f"--contacts: expected 'left;right' (each x,y,z or none), got {text!r}")
    return np.stack([_point(p, f"--contacts {text!r}") for p in parts])


def parse_start(text: str) -> np.ndarray:
    """``"x,z,heading_deg"`` -> (3,) x, z (m) and heading (radians)."""
    try:
        x, z, h = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--start: expected x,z,heading (m, m, degrees), got {text!r}") from None
    return np.array([x, z, np.deg2rad(h)])


def render_previews(result: SynthesisResult, out: Path, count: int, *, width: int = 480,
                    height: int = 360, progress: bool = False) -> list[Path]:
    """MP4 + PNG contact sheet of the first ``count`` characters; returns the written files."""
    model = load_body_model("couch-body")
    paths: list[Path] = []
    for b in range(min(count, len(result.root))):
        vertices = []
        for lo in range(0, result.num_frames, 256):  # bounded memory for long motions
            sl = slice(lo, lo + 256)
            with torch.no_grad():
                o = model(betas=result.betas[None], global_orient=result.global_orient[b, sl],
                          body_pose=result.body_pose[b, sl], transl=result.transl[b, sl])
            vertices.append(o.vertices.numpy())
        contacts = result.series[b].reshape(-1, 3)
        chair = result.scene
        files = preview(np.concatenate(vertices), model.faces,
                        apply_transform(chair.world_from_chair, chair.vertices), chair.faces,
                        out / f"{result.method}_{b:03d}", contacts=contacts,
                        hands=result.hands[b], fps=result.fps, width=width, height=height,
                        video_stride=2, progress=progress)
        paths.extend(files.values())
    return paths


def add_runtime_arguments(p: argparse.ArgumentParser) -> None:
    """``--precision`` and ``--which``: how a CLI that runs a trained run's networks loads
    them (``Synthesizer(precision=..., which=parse_which(...))``)."""
    p.add_argument("--precision", default="fp32", choices=PRECISIONS,
                   help="weights of the networks' large layers at run time: fp32 as trained, fp16 "
                        "(outputs within ~1e-4 m, ~1.6x faster at batch 1) or int8 (CPU only)")
    p.add_argument("--which", default="best",
                   help="checkpoints: best (lowest validation loss), last, an epoch N (kept "
                        "by couch-train --keep-epochs), or per network, e.g. "
                        "pose=14,baseline=10 (the others best)")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="couch-synthesize",
        description="Synthesise a character approaching a chair, sitting and touching it where "
                    "asked, with a trained couch-train run.")
    p.add_argument("run", help="couch-train output folder")
    p.add_argument("--chair", required=True, help="chair mesh (.obj/.ply) in the chair frame")
    p.add_argument("-o", "--output", required=True, help="output folder")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--contacts", action="append", default=[],
                     help="'x,y,z;x,y,z' left;right hand contact (chair frame, m; 'none' for "
                          "no contact); repeat for more characters (or a --series)")
    src.add_argument("--sample-contacts", type=int, metavar="N",
                     help="draw N contact sets from the run's ContactNet")
    p.add_argument("--series", action="store_true",
                   help="one character follows all contact sets in order")
    p.add_argument("--start", action="append", default=[],
                   help="x,z,heading_deg start on the floor (repeat per character)")
    p.add_argument("--method", default="couch", choices=list(METHODS))
    p.add_argument("--hand-ik", action="store_true",
                   help="couch: arm IK puts each palm on its contact as ControlNet's phase "
                        "says it arrives (the paper's suggested fitting; off: networks alone)")
    p.add_argument("--foot-lock", action="store_true",
                   help="hold planted feet by leg IK after synthesis (foot-skate clean-up)")
    p.add_argument("--seconds", type=float, default=16.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--preview", type=int, default=1, metavar="K",
                   help="render MP4/PNG previews of the first K characters (0: none)")
    p.add_argument("--device", default="cpu")
    add_runtime_arguments(p)
    p.add_argument("-q", "--quiet", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``couch-synthesize``; 0 on success, 2 on bad arguments or input."""
    args = parse_args(_parser(), argv)
    if isinstance(args, int):  # --help or a usage error argparse printed
        return args
    torch.set_num_threads(1)
    try:
        sets = ([parse_contacts(c) for c in args.contacts] if args.contacts
                else [np.full((2, 3), np.nan)])
        starts = [parse_start(s) for s in args.start]
        if args.seconds <= 0:
            raise ValueError(f"--seconds must be > 0, got {args.seconds}")
        syn = Synthesizer(args.run, args.method, which=parse_which(args.which),
                          device=args.device, hand_ik=args.hand_ik,
                          precision=args.precision, foot_lock=args.foot_lock)
        vertices, faces = load_mesh(args.chair)
        scene = Scene.from_mesh(vertices, faces, syn.cfg, name=Path(args.chair).stem)
        if args.sample_contacts is not None:
            sets = list(sample_contacts(args.run, scene, args.sample_contacts, seed=args.seed,
                                        device=args.device))
        series = np.stack(sets)[None] if args.series else np.stack(sets)[:, None]
        if not starts:
            goal = scene.goal
            starts = [np.array([goal[0, 3], goal[2, 3] + 2.5, np.pi])]
        if len(starts) not in (1, len(series)):
            raise ValueError(f"--start given {len(starts)} times for {len(series)} characters")
        start = np.broadcast_to(np.stack(starts), (len(series), 3))
        t0 = time.perf_counter()
        result = syn.synthesize(scene, start, series, args.seconds, progress=not args.quiet)
        seconds = time.perf_counter() - t0
        out = Path(args.output)
        out.mkdir(parents=True, exist_ok=True)
        written = [save_npz(result, out / "synthesis.npz"),
                   *write_processed_sessions(result, out)]
        written += render_previews(result, out, args.preview, progress=not args.quiet)
    except (FileNotFoundError, ValueError, SchemaError) as e:
        print(f"couch-synthesize: error: {e}", file=sys.stderr)
        return 2
    if not args.quiet:
        frames = result.num_frames * len(result.root)
        print(f"{len(result.root)} character(s) x {result.num_frames} frames in {seconds:.1f} s "
              f"({frames / seconds:.0f} frames/s); wrote {len(written)} files to {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
