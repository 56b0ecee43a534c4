"""Benchmark: how much foot sliding the foot lock removes from a trained run's synthesis.

Synthesises the same characters twice with :class:`couch.synthesis.Synthesizer` (COUCH, or
``--method baseline``), without and with ``foot_lock``, and prints their foot sliding
(:func:`couch.synthesis.metrics.foot_sliding`, CHOIS's, mm/frame at 30 fps): the mean over the
characters, the ratio with / without, and how many characters slide more with the lock. The
lock is a post-process, so both runs take the same paths. Characters: ``--starts`` per chair on
``--chairs`` simulated chairs (straight, armchair, sofa and stool in turn), starts and hand
contacts drawn as ``couch-eval`` draws its trials (:func:`couch.synthesis.evaluation.trial_setup`),
``--seconds`` each.

Run: ``python -m couch.tools.bench.foot_lock RUN [--chairs 8] [--starts 4] [--seconds 16]
[--seed 0] [--method couch] [--threads 1]``.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from couch.synthesis import Scene, Synthesizer, foot_sliding
from couch.synthesis.evaluation import contact_candidates, trial_setup
from couch.tools.sim.chairs import KINDS, make_chair, random_chair_spec


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", help="trained run folder (couch-train's output)")
    ap.add_argument("--method", default="couch", choices=["couch", "baseline"])
    ap.add_argument("--chairs", type=int, default=8)
    ap.add_argument("--starts", type=int, default=4, help="characters per chair")
    ap.add_argument("--seconds", type=float, default=16.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = ap.parse_args(argv)
    if args.chairs < 1 or args.starts < 1 or not args.seconds > 0:
        ap.error("--chairs and --starts must be >= 1 and --seconds > 0")
    torch.set_num_threads(args.threads)
    plain = Synthesizer(args.run, args.method)
    locked = Synthesizer(args.run, args.method, foot_lock=True)
    rng = np.random.default_rng(args.seed)
    slide = {"without": [], "with": []}
    for c in range(args.chairs):
        kind = KINDS[c % len(KINDS)]
        chair = make_chair(random_chair_spec(rng, kind))
        scene = Scene.from_mesh(chair.vertices, chair.faces, plain.cfg, name=kind)
        starts, sets, _ = trial_setup(scene, contact_candidates(chair.vertices, chair.faces),
                                      args.starts, rng)
        for name, syn in (("without", plain), ("with", locked)):
            r = syn.synthesize(scene, starts, sets[:, None], seconds=args.seconds)
            slide[name] += [1e3 * foot_sliding(j, r.fps) for j in r.joints]
        print(f"chair {c + 1}/{args.chairs} ({kind}): "
              f"{np.mean(slide['without'][-args.starts:]):.3f} -> "
              f"{np.mean(slide['with'][-args.starts:]):.3f} mm/frame", flush=True)
    before, after = np.array(slide["without"]), np.array(slide["with"])
    ratio = f"{after.mean() / before.mean():.3f}x" if before.mean() > 0 else "no sliding"
    print(f"foot sliding over {len(before)} characters x {args.seconds:g} s ({args.method}): "
          f"{before.mean():.3f} mm/frame without the lock, {after.mean():.3f} with it "
          f"({ratio}); the lock adds sliding to {int((after > before + 1e-6).sum())} of "
          f"{len(before)} characters")


if __name__ == "__main__":
    main()
