"""``couch-simulate``: a synthetic capture session in the rig's real file formats, with truth.

Output folder (one session)::

    session.json            what the rig recorded: devices, files, sync modes
    kinect/<serial>.mkv     one Azure Kinect recording per camera (COLOR MJPG, DEPTH and IR b16g;
                            with --no-color DEPTH and IR only, as ``k4arecorder --color-mode
                            OFF``; with --no-ir the IR track is declared but empty)
    calibration/<serial>.mkv  ChArUco board captures, one frame per board pose (always colour)
    background/<serial>.mkv   the empty room (chair in place, nobody in view), a few frames
                            (--background-frames; none with 0; colourless with --no-color)
    imu/recording.mvnx      Xsens MVN export, 60 Hz on the IMU clock
    imu/xbus.bin            the raw Xbus MTData2 stream of the 17 sensors (+ device_map.json)
    chair_scan.obj          the chair as a 3D scanner delivers it (its own frame)
    ground_truth.h5         the processed-session schema on the Kinect master clock
    truth.json              everything else that is true: camera poses, clocks, chair pose, ...
    truth_clothing.npz      the clothing's static per-vertex parameters: with ground_truth.h5,
                            ``clothing.clothed_surface`` rebuilds the surface the cameras saw
    masks/<serial>/NNNNN.png  person masks in colour pixels (with --masks)

``--motion-only --sequences N`` writes N ground-truth motions (``motion_NNNNN.h5`` in the same
schema, each with its own subject, chair and interaction) without rendering: training data;
``--workers N`` draws them on N processes, each sequence from its own stream of the seed; a
stopped run goes on where it stopped when run again (``index.partial.jsonl`` lists the slots
finished, ``index.json`` replaces it at the end; ``--no-resume`` starts over).
Everything is deterministic given ``--seed``; ``--no-color`` skips rendering colour (most of
the simulation time) and leaves every depth frame, the calibration captures, the IMU and the
truth as the same seed writes them with colour; ``--no-ir`` leaves them as they are with IR.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
import time as wallclock
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from couch import __version__
from couch.atomic import atomic_path
from couch.body import BodyModel, load_body_model
from couch.fitting import cached_model
from couch.geometry import invert_transform, make_transform
from couch.pool import finished, limited_threads, spawn_pool
from couch.schema import write_processed
from couch.tools.sim.chairs import KINDS, Chair, make_chair, random_chair_spec, save_mesh, scan_pose
from couch.tools.sim.ik import yaw_matrix
from couch.tools.sim.motion import (
    INTERACTION_LABEL,
    Motion,
    generate_motion,
    sample_interaction,
)
from couch.tools.sim.recording import record_session
from couch.tools.sim.scene import chair_seat_geometry, load_chair
from couch.tools.sim.truth import ChairPlacement, ground_truth

HAND_INTERACTIONS = ("right_hand", "left_hand", "both_hands")
# Sessions shorter than this record a window (around sitting down) of a natural-length sequence.
MIN_FULL_DURATION = 8.0


@dataclasses.dataclass
class SessionConfig:
    """Options of one simulated session (the CLI's flags)."""

    duration: float = 8.0  # s of Kinect recording
    interaction: str | None = None  # None: drawn with the COUCH mix
    chair: str | None = None  # a kind (straight/armchair/sofa/stool), an OBJ/PLY path, or None
    cameras: int = 4
    noise: float = 1.0  # scales depth noise and IMU errors (0 = perfect sensors)
    clock_offset: float | None = None  # s: IMU clock reading at Kinect time 0 (None: random)
    drift_ppm: float = 40.0  # IMU clock rate error against the Kinect clock
    drop_rate: float = 0.0  # probability that a camera drops a frame
    fmt: str = "mkv"  # or "frames": BEHAVE-style per-frame folders
    seed: int = 0
    masks: bool = False
    fps: float = 30.0  # an Azure Kinect rate: 5, 15 or 30
    depth_mode: str = "NFOV_UNBINNED"  # or NFOV_2X2BINNED (320x288, for small fixtures)
    charuco_poses: int = 8
    background_frames: int = 3  # empty-room frames per camera (0: no background/ recording)
    jpeg_quality: int = 90
    model: str = "couch-body"
    color: bool = True  # False: depth-only kinect/ and background/ recordings (mkv, no masks)
    ir: bool = True  # False: MKVs whose IR track (declared, as k4arecorder does) holds no frames
    # Oracles (what a result would be with one error source gone; the random draws stay the
    # same, so the session is otherwise the one the defaults give):
    clothing: bool = True  # False: the cameras see the bare body (no garment, model-size hands)
    imu_misalignment: float = 1.0  # scales the suit's per-segment calibration error (0: none)


#: The :class:`SessionConfig` fields that take one error source away (their defaults keep it).
ORACLES = ("clothing", "imu_misalignment")


@dataclasses.dataclass
class SimulatedSequence:
    """One subject on one chair: the motion (chair frame) and where the chair stands."""

    motion: Motion
    chair: Chair
    chair_kind: str
    placement: ChairPlacement
    rejected: int  # draws thrown away by the plausibility checks


def _chair(rng: np.random.Generator, chair: str | None, interaction: str) -> tuple[Chair, str]:
    if chair is not None and Path(chair).suffix.lower() in (".obj", ".ply"):
        return load_chair(chair), Path(chair).stem
    kind = chair
    if kind is None:
        # a stool offers no hold for a supporting hand
        kinds = [k for k in KINDS if not (k == "stool" and interaction in HAND_INTERACTIONS)]
        kind = str(rng.choice(kinds))
    return make_chair(random_chair_spec(rng, kind)), kind


def _check_request(interaction: str | None, chair: str | None) -> None:
    """ValueError naming the flag when ``interaction`` or ``chair`` (a kind or a mesh file) is
    not one the simulator knows; None asks for a random one."""
    if interaction is not None and interaction not in INTERACTION_LABEL:
        raise ValueError(f"--interaction must be one of {list(INTERACTION_LABEL)}, "
                         f"got {interaction!r}")
    if chair is not None and Path(chair).suffix.lower() not in (".obj", ".ply") \
            and chair not in KINDS:
        raise ValueError(f"--chair must be one of {KINDS} or an .obj/.ply file, got {chair!r}")


class NoPlausibleSequence(ValueError):
    """Every draw of a sequence was rejected (an unlucky chair/subject, not a bad argument)."""


def simulate_sequence(rng: np.random.Generator, model: BodyModel, coarse: BodyModel, *,
                      interaction: str | None = None, chair: str | None = None,
                      duration: float | None = None, max_draws: int = 25,
                      ) -> SimulatedSequence:
    """Draw a chair and a plausible motion on it, retrying draws the checks reject."""
    _check_request(interaction, chair)
    interaction = interaction or sample_interaction(rng)
    last_error: Exception | None = None
    the_chair, kind = _chair(rng, chair, interaction)
    seat = chair_seat_geometry(the_chair.vertices, the_chair.faces, the_chair.landmarks,
                               the_chair.face_parts)
    for draw in range(max_draws):
        try:
            motion = generate_motion(model, seat, rng, interaction=interaction,
                                     duration=duration,
                                     chair_mesh=(the_chair.vertices, the_chair.faces),
                                     collision_model=coarse)
        except ValueError as e:  # unreachable targets or a rejected draw: try another subject
            last_error = e
            if chair is None and draw % 5 == 4:
                the_chair, kind = _chair(rng, None, interaction)
                seat = chair_seat_geometry(the_chair.vertices, the_chair.faces,
                                           the_chair.landmarks, the_chair.face_parts)
            continue
        yaw = rng.uniform(0, 2 * np.pi)
        world_from_chair = make_transform(yaw_matrix(np.array([yaw]))[0],
                                          [rng.uniform(-0.3, 0.3), 0.0, rng.uniform(-0.3, 0.3)])
        placement = ChairPlacement(name=kind, vertices=the_chair.vertices,
                                   faces=the_chair.faces, world_from_chair=world_from_chair,
                                   chair_from_scan=invert_transform(scan_pose(rng)))
        return SimulatedSequence(motion, the_chair, kind, placement, draw)
    raise NoPlausibleSequence(f"could not generate a plausible {interaction!r} sequence on this "
                              f"chair in {max_draws} draws (last: {last_error})")


def _motion_slot(i: int, stream: np.random.SeedSequence, out: Path, fps: float,
                 interaction: str | None, chair: str | None, duration: float | None,
                 max_draws: int) -> tuple[int, dict[str, Any]]:
    """Slot ``i`` of a ``--motion-only`` dataset, drawn from its own ``stream``: writes
    ``motion_{i:05d}.h5`` and returns ``(i, its index entry)``, or ``(i, {"sequence": i,
    "reason": ...})`` when every draw was rejected. The same stream gives the same file in any
    process (the body models are loaded once per process)."""
    model, coarse = cached_model("couch-body"), cached_model("couch-body-coarse")
    rng = np.random.default_rng(stream)
    try:
        seq = simulate_sequence(rng, model, coarse, interaction=interaction, chair=chair,
                                duration=duration, max_draws=max_draws)
    except NoPlausibleSequence as e:
        # One unlucky chair/subject draw must not throw away the whole dataset: the slot
        # is skipped, counted and named in index.json.
        return i, {"sequence": i, "reason": str(e)}
    times = np.arange(0.0, seq.motion.duration, 1.0 / fps)
    name = f"motion_{i:05d}"
    truth = ground_truth(name, seq.motion, times, seq.placement, model, coarse, fps=fps)
    write_processed(out / f"{name}.h5", truth)
    return i, {"file": f"{name}.h5", "interaction": seq.motion.interaction,
               "chair": seq.chair_kind, "frames": len(times),
               "duration_s": round(float(times[-1]), 3), "rejected_draws": seq.rejected}


#: Slots of a ``--motion-only`` folder finished so far, one JSON line each after a header line
#: with the request; ``index.json`` replaces it when every slot is done.
JOURNAL = "index.partial.jsonl"


def _done_slots(out: Path, request: dict[str, Any]) -> dict[int, dict[str, Any]]:
    """The slots of ``out`` an earlier run of the same ``request`` finished (written, or skipped
    after every draw was rejected), from its ``index.json`` and its :data:`JOURNAL`; a slot
    whose file is gone is not done. ValueError naming the file when the folder holds another
    request's sequences (another seed, rate, interaction, chair, duration or draw limit)."""
    done: dict[int, dict[str, Any]] = {}
    index, journal = out / "index.json", out / JOURNAL
    if index.is_file():
        try:
            summary = json.loads(index.read_text())
        except (OSError, ValueError) as e:
            raise ValueError(f"{index}: cannot read it ({e}); use --no-resume") from e
        if "request" not in summary:
            raise ValueError(f"{index}: written by a couch-simulate that did not record what "
                             "it was asked for; use --no-resume to draw the folder anew")
        _check_same_request(index, summary["request"], request)
        try:
            done.update({_slot_of(e): e for e in summary["sequences"]})
            done.update({e["sequence"]: e for e in summary["skipped"]})
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{index}: not an index couch-simulate wrote ({e!r}); "
                             "use --no-resume") from e
    if journal.is_file():
        header, entries = _read_journal(journal)
        if not isinstance(header, dict) or "request" not in header:
            raise ValueError(f"{journal}: no request header on its first line; use --no-resume")
        _check_same_request(journal, header["request"], request)
        done.update(entries)
    return {i: e for i, e in done.items() if "file" not in e or (out / e["file"]).is_file()}


def _read_journal(journal: Path) -> tuple[Any, dict[int, dict[str, Any]]]:
    """A :data:`JOURNAL`'s first line (parsed; None if it is not JSON) and its slots' entries,
    a line that is not ``[slot, {...}]`` skipped (the last line of a run killed while writing
    it)."""
    lines = journal.read_text().splitlines()
    try:
        header = json.loads(lines[0]) if lines else None
    except ValueError:
        header = None
    entries: dict[int, dict[str, Any]] = {}
    for line in lines[1:]:
        try:
            i, entry = json.loads(line)
            if isinstance(entry, dict):
                entries[int(i)] = entry
        except (ValueError, TypeError):
            continue
    return header, entries


def _listed_files(out: Path) -> set[str]:
    """The motion files ``out``'s index and journal name, whatever request drew them (read
    leniently: this only decides which files a new draw replaces)."""
    names: list[Any] = []
    try:
        names += [e.get("file") for e in json.loads((out / "index.json").read_text())
                  ["sequences"]]
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        pass
    if (out / JOURNAL).is_file():
        names += [e.get("file") for e in _read_journal(out / JOURNAL)[1].values()]
    return {n for n in names if isinstance(n, str) and re.fullmatch(r"motion_\d{5}\.h5", n)}


def _slot_of(entry: dict[str, Any]) -> int:
    """The slot number of an index entry that names its file (``motion_00042.h5`` -> 42)."""
    return int(Path(entry["file"]).stem.split("_")[-1])


def _check_same_request(path: Path, theirs: dict[str, Any], ours: dict[str, Any]) -> None:
    differ = [k for k in ours if k in theirs and theirs[k] != ours[k]]
    if differ:
        said = ", ".join(f"{k} {theirs[k]!r} (now {ours[k]!r})" for k in differ)
        raise ValueError(f"{path}: this folder holds sequences drawn with {said}; use another "
                         "folder, or --no-resume to draw it anew")


def simulate_motion_dataset(out_dir: str | Path, sequences: int, seed: int = 0,
                            duration: float | None = None, fps: float = 30.0,
                            interaction: str | None = None, chair: str | None = None,
                            progress: bool = True, max_draws: int = 25,
                            workers: int = 1, resume: bool = True) -> dict[str, Any]:
    """``--motion-only``: ground-truth motions, no rendering. Returns the index it writes.

    Slot ``i`` draws from the ``i``-th stream spawned from ``seed``, so the files do not
    depend on ``workers``: with more than one, the slots run on a pool of that many spawned
    processes (one torch thread each), which on N cores is about N times as fast; with one,
    here on one thread of each library likewise (:func:`couch.pool.limited_threads`), since
    the thread count can change a draw's last bits and with them a marginal decision.
    A slot whose ``max_draws`` draws are all rejected is skipped and listed under ``"skipped"``
    (sequence number and reason); bad arguments still raise ``ValueError``.

    Each finished slot is appended to ``index.partial.jsonl`` as it ends, so with ``resume`` a
    run that was stopped goes on where it stopped (the slots already written or skipped are
    kept), and a finished folder asked for more ``sequences`` draws only the new ones: slot
    ``i``'s stream does not depend on ``sequences``, so the folder is the one a single run
    writes. ``ValueError`` if the folder holds another request's sequences. Files the
    folder's last index listed and the new one does not (another request's, drawn over with
    ``resume=False``; slots past a smaller ``sequences``) are deleted and named under
    ``"removed"``; files no index listed are left alone."""
    if workers < 1:
        raise ValueError(f"--workers must be >= 1, got {workers}")
    _check_request(interaction, chair)  # once before any work, not once per slot
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    request = {"seed": seed, "fps": fps, "interaction": interaction, "chair": chair,
               "duration": duration, "max_draws": max_draws}
    done = {i: e for i, e in _done_slots(out, request).items() if i < sequences} \
        if resume else {}
    previous = _listed_files(out)
    todo = [i for i in range(sequences) if i not in done]
    streams = np.random.SeedSequence(seed).spawn(sequences)
    args = (out, fps, interaction, chair, duration, max_draws)
    start = wallclock.perf_counter()
    slots: list[tuple[int, dict[str, Any]]] = sorted(done.items())
    journal = out / JOURNAL
    with atomic_path(journal) as tmp:  # the slots kept, then one line per slot as it ends
        tmp.write_text("".join(json.dumps(line) + "\n"
                               for line in [{"request": request}, *map(list, slots)]))
    bar = tqdm(total=sequences, initial=len(done), desc="sequences", disable=not progress)
    with journal.open("a") as log:
        def finish(slot: tuple[int, dict[str, Any]]) -> None:
            slots.append(slot)
            log.write(json.dumps(list(slot)) + "\n")
            log.flush()
            bar.update()

        if workers == 1 or len(todo) < 2:
            with limited_threads(1):  # as a pool worker runs them: the same files for any N
                for i in todo:
                    finish(_motion_slot(i, streams[i], *args))
        else:
            with spawn_pool(min(workers, len(todo))) as pool:
                # a failed slot or Ctrl-C cancels the slots not yet started
                for fut in finished(pool.submit(_motion_slot, i, streams[i], *args)
                                    for i in todo):
                    finish(fut.result())
    bar.close()
    slots.sort(key=lambda s: s[0])
    index = [s for _, s in slots if "file" in s]
    skipped = [s for _, s in slots if "file" not in s]
    # Training reads every motion_*.h5 it finds, so a file the last index listed and this one
    # does not (another request's, with --no-resume; a slot past a smaller --sequences) goes.
    listed = {s["file"] for s in index}
    stale = [out / f for f in sorted(previous - listed) if (out / f).is_file()]
    for f in stale:
        f.unlink()
    summary = {"couch_version": __version__, "seed": seed, "fps": fps, "request": request,
               "sequences": index, "skipped": skipped,
               "frames": sum(s["frames"] for s in index), "resumed": len(done),
               "removed": sorted(f.name for f in stale),
               "seconds": round(wallclock.perf_counter() - start, 2)}
    with atomic_path(out / "index.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
    journal.unlink()
    return summary


def _config_record(cfg: SessionConfig) -> dict[str, Any]:
    """``cfg`` for truth.json. ``color``, ``ir``, ``clothing`` and ``imu_misalignment`` appear
    only when not at their defaults, so that sessions keep the exact bytes they had before the
    options existed (the committed fixture)."""
    record = dataclasses.asdict(cfg)
    for key in ("color", "ir", *ORACLES):
        if record[key] == SessionConfig.__dataclass_fields__[key].default:
            del record[key]
    return record


def _session_name(cfg: SessionConfig, kind: str, interaction: str) -> str:
    return f"sim{cfg.seed:04d}_{kind}_{interaction}"


def simulate_session(out_dir: str | Path, cfg: SessionConfig,
                     progress: bool = True) -> dict[str, Any]:
    """Write one full session (see the module docstring); returns the truth.json content."""
    if cfg.fmt not in ("mkv", "frames"):
        raise ValueError(f"--format must be mkv or frames, got {cfg.fmt!r}")
    if cfg.background_frames < 0:
        raise ValueError(f"--background-frames must be >= 0, got {cfg.background_frames}")
    if not cfg.color and cfg.fmt != "mkv":
        raise ValueError("--no-color needs --format mkv (BEHAVE frame folders store colour "
                         "images, and depth registered to them)")
    if not cfg.color and cfg.masks:
        raise ValueError("--masks are person masks in the colour images; they need colour "
                         "(drop --no-color)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ss = np.random.SeedSequence(cfg.seed).spawn(4)
    rng_motion, rng_rig, rng_imu, rng_noise = (np.random.default_rng(s) for s in ss)
    model = load_body_model(cfg.model)
    coarse = load_body_model("couch-body-coarse")
    # A short recording is a window of a natural-length sequence, around sitting down.
    short = cfg.duration < MIN_FULL_DURATION
    seq = simulate_sequence(rng_motion, model, coarse, interaction=cfg.interaction,
                            chair=cfg.chair, duration=None if short else cfg.duration)
    offset = 0.0
    if seq.motion.duration > cfg.duration:
        # the hips land 60% into the recording
        landed = next((b for p, _, b in seq.motion.phases if p == "sit"), 0.0)
        offset = float(np.clip(landed - 0.6 * cfg.duration, 0.0,
                               seq.motion.duration - cfg.duration))
    n = round(cfg.duration * cfg.fps)
    # The master's device clock is the Kinect clock; it was running before the recording began.
    first = float(rng_noise.uniform(0.3, 2.0))
    times = first + np.arange(n) / cfg.fps
    name = _session_name(cfg, seq.chair_kind, seq.motion.interaction)
    truth = ground_truth(name, seq.motion, times, seq.placement, model, coarse, fps=cfg.fps,
                         motion_offset=offset - first)
    write_processed(out / "ground_truth.h5", truth)
    save_mesh(out / "chair_scan.obj", seq.placement.scan_vertices, seq.placement.faces)
    info = record_session(out, cfg, seq, truth, model, rng_rig, rng_imu, rng_noise,
                          offset - first, progress)
    info.update({
        "couch_version": __version__, "session": name, "seed": cfg.seed,
        "config": _config_record(cfg),
        "chair": {"kind": seq.chair_kind,
                  "world_from_chair": seq.placement.world_from_chair.tolist(),
                  "chair_from_scan": seq.placement.chair_from_scan.tolist(),
                  "world_from_scan": seq.placement.world_from_scan.tolist(),
                  "spec": dataclasses.asdict(seq.chair.spec) if seq.chair.spec else None},
        "motion": {"interaction": seq.motion.interaction, "rejected_draws": seq.rejected,
                   "motion_time_at_first_frame_s": offset,
                   "kinect_time_of_first_frame_s": first,
                   "phases": [[p, round(a, 4), round(b, 4)] for p, a, b in seq.motion.phases],
                   "hand_contacts": {s: {"start": a, "end": b, "point_chair": list(map(float, p)),
                                         "part": part}
                                     for s, (a, b, p, part) in seq.motion.hand_contacts.items()}},
    })
    with atomic_path(out / "truth.json") as tmp:
        tmp.write_text(json.dumps(info, indent=2) + "\n")
    return info


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="couch-simulate", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("out_dir", type=Path)
    d = SessionConfig()
    ap.add_argument("--duration", type=float, default=d.duration, help="seconds")
    ap.add_argument("--interaction", choices=list(INTERACTION_LABEL), default=None,
                    help="default: drawn with the COUCH dataset's mix")
    ap.add_argument("--chair", default=None,
                    help=f"one of {', '.join(KINDS)}, or an .obj/.ply in the chair frame")
    ap.add_argument("--cameras", type=int, default=d.cameras)
    ap.add_argument("--noise", type=float, default=d.noise,
                    help="scale of depth noise and IMU errors (0: perfect sensors)")
    ap.add_argument("--clock-offset", type=float, default=None,
                    help="IMU clock reading (s) at Kinect time 0; default random")
    ap.add_argument("--drift-ppm", type=float, default=d.drift_ppm)
    ap.add_argument("--drop-rate", type=float, default=d.drop_rate,
                    help="probability that a camera drops a frame")
    ap.add_argument("--format", dest="fmt", choices=["mkv", "frames"], default=d.fmt,
                    help="mkv: one Azure Kinect recording per camera; frames: BEHAVE-style "
                         "per-frame folders (colour JPEG, depth registered to colour, masks)")
    ap.add_argument("--fps", type=float, choices=[5.0, 15.0, 30.0], default=d.fps,
                    help="Kinect frame rate")
    ap.add_argument("--depth-mode", choices=["NFOV_UNBINNED", "NFOV_2X2BINNED"],
                    default=d.depth_mode)
    ap.add_argument("--charuco-poses", type=int, default=d.charuco_poses,
                    help="board poses in the calibration captures")
    ap.add_argument("--background-frames", type=int, default=d.background_frames,
                    help="frames of the empty room per camera (background/<serial>.mkv) for "
                         "background subtraction; 0: none")
    ap.add_argument("--jpeg-quality", type=int, default=d.jpeg_quality)
    ap.add_argument("--masks", action="store_true", help="also write person masks (PNG)")
    ap.add_argument("--no-color", dest="color", action="store_false",
                    help="depth-only kinect/ and background/ recordings (no COLOR track, as "
                         "k4arecorder --color-mode OFF): colour is not rendered, which is most "
                         "of the time; depth is the same as with colour (mkv only; the "
                         "calibration/ captures keep colour)")
    ap.add_argument("--no-ir", dest="ir", action="store_false",
                    help="leave the MKVs' IR tracks empty (declared, with no frames): smaller "
                         "files, a little faster; depth and colour are the same either way")
    ap.add_argument("--no-clothing", dest="clothing", action="store_false",
                    help="an oracle: the cameras see the bare body (no garment; hands and feet "
                         "at the body model's size), every random draw as with clothes")
    ap.add_argument("--imu-misalignment", type=float, default=d.imu_misalignment,
                    help="scale of the suit's per-segment calibration error on top of --noise "
                         "(0: an oracle suit calibrated exactly; the draws stay the same)")
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--motion-only", action="store_true",
                    help="write ground-truth motion only (no rendering), --sequences of them")
    ap.add_argument("--sequences", type=int, default=1)
    ap.add_argument("--workers", type=int, default=1, metavar="N",
                    help="with --motion-only: draw the sequences on N processes (one per "
                         "core; the files are the same for any N)")
    ap.add_argument("--no-resume", dest="resume", action="store_false",
                    help="with --motion-only: draw every sequence anew, deleting the motion "
                         "files the folder's index listed that this draw does not write (by "
                         "default a folder an earlier run of the same request began goes on "
                         "where it stopped)")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    args = ap.parse_args(argv)
    try:
        if args.motion_only:
            summary = simulate_motion_dataset(
                args.out_dir, args.sequences, args.seed, None if args.duration == d.duration
                else args.duration, fps=args.fps, interaction=args.interaction,
                chair=args.chair, progress=not args.quiet, workers=args.workers,
                resume=args.resume)
            kept = f" ({summary['resumed']} slots kept from before)" if summary["resumed"] else ""
            if summary["removed"]:
                kept += (f"; removed {len(summary['removed'])} motion files the index does not "
                         "list")
            print(f"wrote {len(summary['sequences'])} sequences, {summary['frames']} frames, "
                  f"to {args.out_dir} in {summary['seconds']} s{kept}")
            for s in summary["skipped"]:
                print(f"skipped sequence {s['sequence']}: {s['reason']}", file=sys.stderr)
            return 0
        cfg = SessionConfig(**{k: v for k, v in vars(args).items()
                               if k in SessionConfig.__dataclass_fields__})
        info = simulate_session(args.out_dir, cfg, progress=not args.quiet)
    except (ValueError, OSError) as e:
        print(f"couch-simulate: {e}", file=sys.stderr)
        return 1
    print(f"wrote session {info['session']} ({info['motion']['interaction']}, "
          f"{cfg.cameras} cameras, {cfg.duration:g} s) to {args.out_dir}")
    return 0


__all__ = ["HAND_INTERACTIONS", "ORACLES", "SessionConfig", "SimulatedSequence",
           "main", "simulate_motion_dataset", "simulate_sequence", "simulate_session"]


if __name__ == "__main__":
    sys.exit(main())
