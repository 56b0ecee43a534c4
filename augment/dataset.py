"""Augmented datasets: swap the chair of a processed session for library shapes (issue item 4).

Per (sequence, shape) pair, :func:`augment_sequence`:

1. finds the source chair's chair frame in the (levelled) world from its geometry
   (:func:`canonical_chair_frame`: seat region, its minimum-area rectangle for the yaw, the
   backrest for the front; rotation about +Y only, origin at the seat centre on the floor);
2. places the new shape (optionally uniformly scaled about that origin, so the floor stays at
   y = 0) at that chair frame, moved so that the sitter keeps their place
   (:func:`~couch.augment.transfer.sitter_shift`: seat fronts aligned, the inner edge of the
   armrest the hands held longest aligned, the pelvis kept inside the new seat);
3. moves every active contact of the source with
   :func:`~couch.augment.transfer.transfer_contacts` (source parts from the source chair, target
   parts from the new shape, both by :func:`~couch.augment.parts.segment_parts`; metric
   positions relative to the sitter); a contact that would move more than ``max_transfer``
   (a sofa's far armrest) is dropped;
4. turns the offsets (new − old) into smoothed IK targets (:func:`~couch.augment.ik
   .contact_targets`, window ``IKConfig.window`` = 30 frames) and re-poses the body
   (:func:`~couch.augment.ik.reposition`) with the feet planted where ``quality/floor_active``
   says, or else where the source's heel and toe are within 5 cm of the floor and slower than
   0.15 m/s, and body vertices pushed out of the new chair (its
   :class:`~couch.augment.sdf.SignedDistanceGrid`);
5. measures the body's penetration into the new chair (:func:`~couch.augment.ik.penetration`)
   and rejects the result when its 95th percentile over frames exceeds ``max_penetration``,
   when the 95th percentile of the reach error over the contact frames exceeds ``max_reach``
   (or its median half of it: the issue's 1 cm median / 2 cm 95th percentile),
   or when the largest joint step between frames exceeds ``max_jump`` times the source's.

:func:`augment_dataset` maps that over ``per_sequence`` seeded shape draws per processed file on a
local process pool and writes ``augmented.h5`` (one group per kept pair,
``/<source>__<shape>__<k>``, each holding the processed-session schema; read one with
:func:`couch.schema.read_session_group`) and ``summary.json`` (kept / rejected by reason, per-pair
statistics), both atomically.

The output's ``/object/vertices`` are the new mesh in its chair frame (metres, scaled) and
``/object/pose`` the world-from-chair placement; ``/joints`` are the source joints plus the change
of the (coarse) body model's joints, so they stay on the source's joint convention.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from collections import Counter
from collections.abc import Iterable, Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import trimesh
from tqdm import tqdm

from couch import __version__
from couch.atomic import atomic_path
from couch.augment.ik import IKConfig, contact_targets, penetration, reposition
from couch.augment.parts import PART_NAMES, segment_parts
from couch.augment.sdf import SignedDistanceGrid
from couch.augment.shapes import (
    _YAW_TO_BACK_NEG_Z,
    ShapeEntry,
    _back_direction,
    _seat_box,
    _seat_faces,
    _Skip,
    _surface_samples,
    load_shape_library,
)
from couch.augment.transfer import contact_parts, sitter_shift, transfer_contacts
from couch.body import CONTACT_NAMES, BodyModel
from couch.fitting import BodyParams, cached_model, foot_points, foot_skate, pose_body
from couch.geometry import apply_transform, invert_transform, make_transform
from couch.pool import finished, limited_threads, spawn_pool
from couch.schema import SCHEMA_VERSION, ProcessedSession, read_processed, write_session_group

__all__ = [
    "AugmentResult",
    "AugmentStats",
    "AugmentSummary",
    "augment_dataset",
    "augment_sequence",
    "canonical_chair_frame",
    "find_processed",
]

log = logging.getLogger(__name__)

MODEL_NAME = "couch-body-coarse"
"""Body model used for the IK, penetration and the statistics."""
PLANT_HEIGHT = 0.05
"""Fallback foot plant: heel and toe below this height (m) ..."""
PLANT_SPEED = 0.15
"""... and horizontally slower than this (m/s)."""
DATASET_NAME = "augmented.h5"
SUMMARY_NAME = "summary.json"


# --------------------------------------------------------------------------------------------
# Chair frame
# --------------------------------------------------------------------------------------------

def _min_area_axis(xz: np.ndarray) -> np.ndarray:
    """(2,) unit direction (in X/Z) of one side of the minimum-area rectangle around ``xz``."""
    xz = np.asarray(xz, dtype=np.float64)
    if len(xz) < 3 or np.linalg.matrix_rank(xz - xz.mean(0)) < 2:
        return np.array([1.0, 0.0])
    from scipy.spatial import ConvexHull

    hull = xz[ConvexHull(xz).vertices]
    edges = np.roll(hull, -1, axis=0) - hull
    angles = np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2)
    best, best_area = 0.0, np.inf
    for a in np.unique(np.round(angles, 9)):
        d = np.array([np.cos(a), np.sin(a)])
        n = np.array([-d[1], d[0]])
        area = np.ptp(hull @ d) * np.ptp(hull @ n)
        if area < best_area:
            best, best_area = a, area
    return np.array([np.cos(best), np.sin(best)])


def canonical_chair_frame(vertices_world: np.ndarray, faces: np.ndarray, *,
                          warn: bool = True) -> np.ndarray:
    """(4, 4) world-from-chair transform of a chair mesh placed in the levelled world.

    The chair frame is :mod:`couch.augment.shapes`'s (seat centred on x = z = 0, front +Z,
    backrest at -Z, floor y = 0). Found from the geometry alone: the seat region
    (``shapes._seat_faces``), the yaw of its minimum-area X/Z rectangle (mod 90°), and the side
    of that rectangle with the one-sided backrest (``shapes._back_direction``) as -Z. The
    rotation is about +Y only; the origin is the seat rectangle's centre at y = 0 (the floor).
    A seat without a backrest keeps the rectangle's first axis as +X (the front is then
    ambiguous; logged as a warning when ``warn``).

    Args:
        vertices_world: (V, 3) metres, world (Y up, floor y = 0).
        faces: (F, 3) int; a closed mesh gives the best results.
        warn: log a seat without a backrest (a stool) as a warning.

    Raises:
        ValueError: no seat (upward-facing surface) found.
    """
    v = np.asarray(vertices_world, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    mesh = trimesh.Trimesh(v, f, process=False)
    try:
        seat, seat_h = _seat_faces(mesh)
    except _Skip as exc:
        raise ValueError(f"canonical_chair_frame: {exc}") from exc
    d = _min_area_axis(v[np.unique(f[seat])][:, [0, 2]])
    x_axis = np.array([d[0], 0.0, d[1]])
    y_axis = np.array([0.0, 1.0, 0.0])
    rot = np.stack([x_axis, y_axis, np.cross(x_axis, y_axis)], axis=1)  # world from aligned
    aligned = v @ rot
    box = _seat_box(aligned, f, seat)
    centre = np.array([box[:, 0].mean(), 0.0, box[:, 1].mean()])
    aligned = aligned - centre
    samples, _, dA = _surface_samples(trimesh.Trimesh(aligned, f, process=False),
                                      np.random.default_rng(0))
    back = _back_direction(samples, dA, seat_h - float(centre[1]), _seat_box(aligned, f, seat))
    if back is None:
        if warn:
            log.warning("canonical_chair_frame: no backrest found; the chair's front is "
                        "ambiguous")
        back = (2, -1)
    turn = _YAW_TO_BACK_NEG_Z[back]  # chair from aligned
    out = np.eye(4)
    out[:3, :3] = rot @ turn.T
    out[:3, 3] = rot @ centre
    out[1, 3] = 0.0
    return out


# --------------------------------------------------------------------------------------------
# One sequence
# --------------------------------------------------------------------------------------------

@dataclasses.dataclass
class AugmentStats:
    """Measurements of one augmentation (lengths in metres unless named otherwise).

    ``reach_median``/``reach_p95``: reach error on contact frames with a target; ``skate_before``/
    ``skate_after``: mean foot skate (mm/frame) of the planted feet, source / result;
    ``jump_before``/``jump_after``: largest joint displacement between consecutive frames
    (m/frame); ``penetration_p95_before``/``penetration_p95``: 95th percentile over frames of
    the deepest body point inside the source / new chair; ``fallback_contacts``: transferred
    contact points that fell back to the nearest surface (part missing on the new chair);
    ``dropped_contacts``: (frame, part) contacts not made on the new chair because their
    transferred point lay over ``max_transfer`` from the sitter's; ``shift``: where the sitter
    sits on the new chair relative to the old (chair frame, m, :func:`~couch.augment.transfer
    .sitter_shift`); ``contact_frames``: active (frame, part) pairs kept; ``iterations``;
    ``seconds`` wall time.
    """

    reach_median: float = math.nan
    reach_p95: float = math.nan
    skate_before: float = math.nan
    skate_after: float = math.nan
    jump_before: float = math.nan
    jump_after: float = math.nan
    penetration_p95_before: float = math.nan
    penetration_p95: float = math.nan
    fallback_contacts: int = 0
    dropped_contacts: int = 0
    shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    contact_frames: int = 0
    iterations: int = 0
    seconds: float = 0.0


@dataclasses.dataclass(eq=False)
class AugmentResult:
    """What :func:`augment_sequence` returns: the augmented ``session`` (also when rejected, for
    inspection), its ``stats``, and ``rejected``: None, or ``"<kind>: <details>"`` with kind
    ``penetration``, ``reach`` or ``jump`` (``error`` from :func:`augment_dataset` when it
    raised)."""


    session: ProcessedSession | None
    stats: AugmentStats
    rejected: str | None
    shape_id: str
    scale: float


def _planted(session: ProcessedSession, feet: np.ndarray) -> np.ndarray:
    """(T, 2) left/right foot planted: ``quality/floor_active`` when present, else heel and toe
    near the floor and slow (``feet`` (T, 4, 3) LHeel, LBigToe, RHeel, RBigToe)."""
    n = session.num_frames
    floor = session.quality.get("floor_active")
    if floor is not None and np.shape(floor) == (n, 2):
        return np.asarray(floor, dtype=bool)
    speed = np.linalg.norm(np.diff(feet[..., [0, 2]], axis=0), axis=-1) * session.fps
    speed = np.vstack([speed, speed[-1:]]) if n > 1 else np.zeros((n, 4))
    ok = (feet[..., 1] < PLANT_HEIGHT) & (speed < PLANT_SPEED)
    return np.stack([ok[:, :2].all(1), ok[:, 2:].all(1)], axis=1)


def _skate(feet: np.ndarray, plant: np.ndarray) -> float:
    s = foot_skate(feet, np.repeat(plant, 2, axis=1))
    return float(s.mean()) if s.size else 0.0


def _jump(joints: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(joints, axis=0), axis=-1).max()) if len(joints) > 1 \
        else 0.0


def augment_sequence(session: ProcessedSession, shape: ShapeEntry, *, scale: float = 1.0,
                     rng: np.random.Generator | None = None, ik_config: IKConfig | None = None,
                     max_penetration: float = 0.02, max_reach: float = 0.02,
                     max_transfer: float = 0.25, max_jump: float = 1.1,
                     model: BodyModel | None = None) -> AugmentResult:
    """Swap the chair of ``session`` for ``shape`` (scaled by ``scale``) and re-pose the body.

    See the module doc for the steps. ``rng`` is accepted for API stability (every step is
    deterministic today); ``ik_config`` configures :func:`~couch.augment.ik.reposition` (its
    ``window`` is the offset falloff); ``max_penetration``/``max_reach`` (m) are the rejection
    thresholds on the 95th percentiles; ``max_transfer`` (m) how far a contact may move
    relative to the sitter before it is dropped; ``max_jump`` rejects a result whose largest
    frame-to-frame joint step exceeds this multiple of the source's; ``model`` defaults to the
    cached coarse body model.

    Returns:
        :class:`AugmentResult`; its session is named ``<source>__<shape id>`` with
        ``/object/name`` the shape id, ``quality/reach_error`` (T, 5) m (NaN without a target)
        and ``quality/penetration`` (T,) m.

    Raises:
        ValueError: the source chair or the shape has no seat.
    """
    del rng  # deterministic; kept for the seeded-pipeline signature
    start = time.perf_counter()
    cfg = ik_config or IKConfig()
    model = model or cached_model(MODEL_NAME)
    n = session.num_frames

    # 1-2. Chair frames: the source's from its geometry; the new shape placed at it.
    src_world = apply_transform(np.asarray(session.object_pose, np.float64),
                                np.asarray(session.object_vertices, np.float64))
    f_src = np.asarray(session.object_faces, np.int64)
    world_from_chair = canonical_chair_frame(src_world, f_src)
    chair_from_world = invert_transform(world_from_chair)
    v_src = apply_transform(chair_from_world, src_world)
    v_new = np.asarray(shape.vertices, np.float64) * float(scale)
    f_new = np.asarray(shape.faces, np.int64)

    # 3. Where the sitter sits on the new chair, then the contacts, part to part.
    act = np.asarray(session.contact_active, dtype=bool)
    src_points = np.asarray(session.contact_points, np.float64)
    new_points = np.full((n, act.shape[1], 3), np.nan)
    parts_src, parts_new = segment_parts(v_src, f_src), segment_parts(v_new, f_new)
    local = apply_transform(chair_from_world, src_points[act]) if act.any() \
        else np.zeros((0, 3))
    which = np.broadcast_to(np.arange(act.shape[1]), act.shape)[act]
    hands = np.isin(which, [CONTACT_NAMES.index("left_hand"), CONTACT_NAMES.index("right_hand")])
    held = Counter(PART_NAMES[c] for c in contact_parts(local[hands], parts_src,
                                                         (v_src, f_src)))
    pelvis = local[which == CONTACT_NAMES.index("pelvis")]
    shift = sitter_shift(parts_src, parts_new, dict(held),
                         float(np.median(pelvis[:, 0])) if len(pelvis) else None)
    world_from_chair = world_from_chair @ make_transform(np.eye(3), -shift)
    fallback = dropped = 0
    if act.any():
        tr = transfer_contacts(local, parts_src, (v_src, f_src), parts_new, (v_new, f_new),
                               shift=shift)
        new_points[act] = apply_transform(world_from_chair, tr.points)
        fallback = int(tr.fallback.sum())
        # A contact whose part is far from where the sitter now is (a sofa's other armrest)
        # is not made on the new chair: that hand stays as captured, off the chair.
        far = np.zeros_like(act)
        far[act] = tr.distance_moved > max_transfer
        dropped = int(far.sum())
        act = act & ~far
        new_points[far] = np.nan

    # 4. Targets and IK.
    params = BodyParams.from_processed(session)
    v0, j0 = pose_body(model, params)
    feet0 = foot_points(v0, model.keypoint_ids)
    plant = _planted(session, feet0)
    targets, ref = contact_targets(params, model, src_points, new_points, act, cfg.window)
    chair_world = apply_transform(world_from_chair, v_new)
    ik = reposition(params, model, targets, reference=ref, plant_feet=plant, config=cfg,
                    obstacle=SignedDistanceGrid.from_mesh(chair_world, f_new))
    v1, j1 = pose_body(model, ik.params)
    del v0

    # 5. Penetration and checks.
    pen = penetration(ik.params, model, chair_world, f_new)
    pen0 = penetration(params, model, src_world, f_src)
    reach = ik.reach_error[act & np.isfinite(targets[..., 0])]
    stats = AugmentStats(
        reach_median=float(np.median(reach)) if reach.size else math.nan,
        reach_p95=float(np.percentile(reach, 95)) if reach.size else math.nan,
        skate_before=_skate(feet0, plant),
        skate_after=_skate(foot_points(v1, model.keypoint_ids), plant),
        jump_before=_jump(j0), jump_after=_jump(j1),
        penetration_p95_before=float(np.percentile(pen0, 95)) if n else 0.0,
        penetration_p95=float(np.percentile(pen, 95)) if n else 0.0,
        fallback_contacts=fallback, dropped_contacts=dropped,
        shift=tuple(float(x) for x in shift), contact_frames=int(act.sum()),
        iterations=ik.iterations)
    rejected = None
    if stats.penetration_p95 > max_penetration:
        rejected = (f"penetration: 95th percentile {100 * stats.penetration_p95:.2f} cm > "
                    f"{100 * max_penetration:.2f} cm")
    elif reach.size and stats.reach_p95 > max_reach:
        rejected = (f"reach: 95th percentile {100 * stats.reach_p95:.2f} cm > "
                    f"{100 * max_reach:.2f} cm")
    elif reach.size and stats.reach_median > max_reach / 2:
        rejected = (f"reach: median {100 * stats.reach_median:.2f} cm > "
                    f"{50 * max_reach:.2f} cm")
    elif stats.jump_after > max_jump * stats.jump_before:
        rejected = (f"jump: largest joint step {100 * stats.jump_after:.1f} cm/frame > "
                    f"{max_jump:.2f} x the source's {100 * stats.jump_before:.1f} cm/frame")

    joints = np.asarray(session.joints, np.float64) + (j1 - j0)[:, :24]
    out = dataclasses.replace(
        session, session=f"{session.session}__{shape.id}",
        global_orient=ik.params.global_orient.astype(np.float32),
        body_pose=ik.params.body_pose.astype(np.float32),
        transl=ik.params.transl.astype(np.float32), joints=joints.astype(np.float32),
        object_name=shape.id, object_vertices=v_new.astype(np.float32),
        object_faces=f_new.astype(np.int32), object_pose=world_from_chair,
        object_frame_poses=np.repeat(world_from_chair[None], n, axis=0),
        contact_active=act.copy(), contact_points=new_points.astype(np.float32),
        quality={"reach_error": ik.reach_error.astype(np.float32),
                 "penetration": pen.astype(np.float32)},
        couch_version=__version__, schema_version=SCHEMA_VERSION)
    stats.seconds = time.perf_counter() - start
    return AugmentResult(session=out, stats=stats, rejected=rejected, shape_id=shape.id,
                         scale=float(scale))


# --------------------------------------------------------------------------------------------
# Dataset
# --------------------------------------------------------------------------------------------

@dataclasses.dataclass
class AugmentSummary:
    """What :func:`augment_dataset` did: ``kept`` pairs, ``rejected`` counts by reason kind,
    ``sequences`` one JSON-ready dict per (source, draw) with its group, shape, scale, reason
    and :class:`AugmentStats`; ``dataset``/``summary`` the files written; ``seconds``."""

    kept: int
    rejected: dict[str, int]
    sequences: list[dict[str, Any]]
    dataset: Path
    summary: Path
    seconds: float
    shapes: int = 0

    def text(self) -> str:
        """A short human-readable report (what the CLI prints)."""
        n_rej = sum(self.rejected.values())
        lines = [f"{self.kept} augmented sequences kept, {n_rej} rejected"
                 + (" (" + ", ".join(f"{v} {k}" for k, v in sorted(self.rejected.items())) + ")"
                    if n_rej else "") + f" in {self.seconds:.1f} s"]
        for s in self.sequences:
            if s["rejected"]:
                lines.append(f"  rejected {s['source']} x {s['shape']} (scale {s['scale']:.3f}):"
                             f" {s['rejected']}")
        lines.append(f"wrote {self.dataset} and {self.summary}")
        return "\n".join(lines)


def find_processed(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Processed-session files from ``paths``: each a file (taken as is) or a folder (every
    ``processed.h5`` below it). Raises ``FileNotFoundError`` naming a missing path or a folder
    without any ``processed.h5``."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_file():
            out.append(p)
        elif p.is_dir():
            found = sorted(p.rglob("processed.h5"))
            if not found:
                raise FileNotFoundError(f"{p}: no processed.h5 in this folder")
            out.extend(found)
        else:
            raise FileNotFoundError(f"{p}: no such file or folder")
    return list(dict.fromkeys(out))


def _task(session: ProcessedSession, shape: ShapeEntry, scale: float, seed: Sequence[int],
          ik_config: IKConfig | None, max_penetration: float, max_reach: float
          ) -> AugmentResult:
    """One (sequence, shape) pair; never raises (an error becomes a rejection)."""
    try:
        return augment_sequence(session, shape, scale=scale, rng=np.random.default_rng(seed),
                                ik_config=ik_config, max_penetration=max_penetration,
                                max_reach=max_reach)
    except Exception as exc:   # one bad pair must not stop the dataset
        log.exception("augmenting %s with %s failed", session.session, shape.id)
        return AugmentResult(session=None, stats=AugmentStats(), rejected=f"error: "
                             f"{type(exc).__name__}: {exc}", shape_id=shape.id, scale=scale)


def _group_name(source: str, shape_id: str, k: int) -> str:
    return f"{source}__{shape_id}__{k}".replace("/", "_")


def augment_dataset(processed: Sequence[str | os.PathLike], shapes_dir: str | os.PathLike,
                    output: str | os.PathLike, *, per_sequence: int = 4,
                    scale_range: tuple[float, float] = (0.9, 1.1), seed: int = 0,
                    workers: int | None = None, progress: bool = False,
                    cache_dir: str | os.PathLike | None = None,
                    ik_config: IKConfig | None = None, max_penetration: float = 0.02,
                    max_reach: float = 0.02) -> AugmentSummary:
    """Augment every processed session with ``per_sequence`` library shapes each.

    Per file ``i`` (in the given order) a generator seeded with ``(seed, i)`` draws
    ``per_sequence`` shapes (without replacement while the library has enough) and a uniform
    scale in ``scale_range`` for each; the pairs run through :func:`augment_sequence` on a
    ``ProcessPoolExecutor`` (spawned processes, one torch thread each) of ``workers`` processes
    (default ``min(2, os.cpu_count())``; 1 runs in this process). Kept pairs are written into
    ``output/augmented.h5``, group ``/<source>__<shape>__<k>`` each (the processed schema, plus
    attributes ``source_file``, ``shape``, ``category``, ``scale``), and ``output/summary.json``
    holds the kept / rejected counts and every pair's statistics; both are written atomically.

    ``cache_dir`` is the shape library's cache (see
    :func:`~couch.augment.shapes.load_shape_library`, which uses ``seed`` for the seat heights).

    Raises:
        couch.schema.SchemaError: a processed file is unreadable (message names it).
        FileNotFoundError: ``shapes_dir`` is not a folder.
        ValueError: bad arguments, or no usable shape in ``shapes_dir``.
    """
    start = time.perf_counter()
    if per_sequence < 1:
        raise ValueError(f"per_sequence must be >= 1, got {per_sequence}")
    lo, hi = (float(s) for s in scale_range)
    if not 0 < lo <= hi:
        raise ValueError(f"scale_range must be 0 < a <= b, got {scale_range}")
    workers = min(2, os.cpu_count() or 1) if workers is None else int(workers)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    files = [Path(p) for p in processed]
    sessions = [read_processed(p) for p in files]
    lib = load_shape_library(shapes_dir, cache_dir=cache_dir, seed=seed, progress=progress)
    if not lib.entries:
        raise ValueError(f"{shapes_dir}: no usable shapes ({lib.summary()})")

    tasks: list[tuple[int, int, ShapeEntry, float]] = []
    for i in range(len(files)):
        rng = np.random.default_rng([seed, i])
        picks = rng.choice(len(lib.entries), size=per_sequence,
                           replace=per_sequence > len(lib.entries))
        scales = rng.uniform(lo, hi, size=per_sequence)
        tasks += [(i, k, lib.entries[int(j)], float(s))
                  for k, (j, s) in enumerate(zip(picks, scales, strict=True))]

    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    dataset_path, summary_path = output / DATASET_NAME, output / SUMMARY_NAME
    records: list[dict[str, Any] | None] = [None] * len(tasks)
    used: set[str] = set()

    def record(index: int, result: AugmentResult, h5: h5py.File) -> None:
        i, k, shape, scale = tasks[index]
        source = sessions[i].session
        name = _group_name(source, shape.id, k)
        while name in used:
            name += "_"
        used.add(name)
        if result.rejected is None and result.session is not None:
            group = h5.create_group(name)
            write_session_group(group, dataclasses.replace(result.session, session=name))
            group.attrs.update(source_file=str(files[i]), shape=shape.id,
                               category=shape.category, scale=scale)
        records[index] = dict(group=name if result.rejected is None else None, source=source,
                              file=str(files[i]), shape=shape.id, category=shape.category,
                              draw=k, scale=scale, kept=result.rejected is None,
                              rejected=result.rejected,
                              stats=_finite(dataclasses.asdict(result.stats)))

    bar = tqdm(total=len(tasks), desc="augment", unit="seq", disable=not progress)
    args = (ik_config, max_penetration, max_reach)
    with atomic_path(dataset_path) as tmp, h5py.File(tmp, "w") as h5:
        h5.attrs.update(schema_version=SCHEMA_VERSION, couch_version=__version__,
                        kind="augmented", seed=seed, per_sequence=per_sequence,
                        scale_range=np.array([lo, hi]))
        if workers == 1:
            with limited_threads(1):  # as a pool worker runs them: the same file for any N
                for index, (i, k, shape, scale) in enumerate(tasks):
                    record(index, _task(sessions[i], shape, scale, (seed, i, k), *args), h5)
                    bar.update()
        else:
            with spawn_pool(workers) as pool:
                futures: dict[Future[AugmentResult], int] = {
                    pool.submit(_task, sessions[i], shape, scale, (seed, i, k), *args): index
                    for index, (i, k, shape, scale) in enumerate(tasks)}
                for fut in finished(futures):
                    record(futures[fut], fut.result(), h5)
                    bar.update()
    bar.close()

    seqs = [r for r in records if r is not None]
    kept = [r for r in seqs if r["kept"]]
    rejected = dict(Counter(r["rejected"].split(":", 1)[0] for r in seqs if not r["kept"]))
    aggregate = {key: _finite(float(np.median([r["stats"][key] for r in kept
                                               if r["stats"][key] is not None])))
                 if kept else None
                 for key in ("reach_median", "reach_p95", "penetration_p95", "seconds")}
    summary = AugmentSummary(kept=len(kept), rejected=rejected, sequences=seqs,
                             dataset=dataset_path, summary=summary_path,
                             seconds=time.perf_counter() - start, shapes=len(lib.entries))
    doc = dict(kept=len(kept), rejected=sum(rejected.values()), rejected_by_reason=rejected,
               sources=[str(f) for f in files], shapes_dir=str(shapes_dir),
               shapes=len(lib.entries), shapes_skipped=len(lib.skipped),
               per_sequence=per_sequence, scale_range=[lo, hi], seed=seed, workers=workers,
               max_penetration=max_penetration, max_reach=max_reach,
               median_of_kept=aggregate, seconds=summary.seconds, sequences=seqs,
               couch_version=__version__)
    with atomic_path(summary_path) as tmp:
        tmp.write_text(json.dumps(doc, indent=2) + "\n")
    return summary


def _finite(value: Any) -> Any:
    """JSON-safe: NaN/inf floats (also inside a dict) become None."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
