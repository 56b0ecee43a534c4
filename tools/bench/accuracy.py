"""Benchmark: ``couch-process`` accuracy against the simulator's truth on several sessions.

Issue 8 asks for its numbers "on simulator sessions with several seeds, chairs and noise
levels". This simulates such a set (:data:`SESSIONS`: every chair kind, every interaction type,
sensor noise 0.5-1.5x, 4 cameras with binned depth, no colour), processes each with nothing
given (our calibration, sync, fits, chair registration; the cache ignored), and prints per
session and pooled over all of them: the chair's rotation, centre and worst-vertex error, its
chamfer, the body's MPJPE, contact F1 per part (frames of all sessions pooled, with a 95 %
bootstrap interval over the sessions: :func:`f1_intervals`; a hand has a few dozen true contact
frames in eight sessions, so one session moves its F1 by several points), how far each
part's distance to the chair is off where the true part is near it, and its median sign (a fit
holding a part off the chair, or into it, rather than a noisy one: :func:`distance_errors`),
where the wrong contact frames lie (within a frame of a true contact's start or end, or not:
:func:`edge_errors`), how many true contacts were found at all (:func:`episode_counts`) and
which sessions hold most of each hand's wrong frames (:func:`most_wrong`), how far each
part's contact point on the chair is from the one the same contact rule puts on the true
motion, the feet's contacts with the floor (F1 against that rule on the true motion and
against a plain height threshold, and how far our planted foot point is from the true one),
interaction label accuracy, and how far the suit's, the per-frame fits' and the fused
motion's bones point from the truth's (:func:`bone_errors`: what the cameras correct).
Everything is compared in the simulator's world after the rigid transform that maps our camera
centres onto the true ones, so the calibration's error is in every number.

Run: ``python -m couch.tools.bench.accuracy [-o DIR] [--sessions N] [--fps F] [--duration S]
[--threads K] [--jobs J] [--seed-offset K [K ...]] [--set KEY=VALUE ...] [--sim-set KEY=VALUE
...] [--reuse]`` (several offsets pool their sessions; ``--set`` changes a processing setting as
``couch-process --set`` does, and ``--reuse`` with a kept ``-o`` folder re-runs only the stages
it changes; ``--sim-set`` simulates the sessions with a setting of the simulator changed, e.g.
the oracles ``clothing=false`` and ``imu_misalignment=0``, into their own ``-o`` folder;
``--jobs`` runs J sessions at a time in spawned processes, the printed pooled numbers the same
as one at a time). A session takes about 1-3 min to simulate and process at 15 fps, 8 s.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import tempfile
import time
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import torch

import couch
from couch.body import JOINT_INDEX
from couch.body.skeleton import CONTACT_NAMES
from couch.fitting import (
    FEET,
    BodyParams,
    ContactConfig,
    PipelineResult,
    ProcessConfig,
    cached_model,
    contact_runs,
    detect_contacts,
    mpjpe,
)
from couch.geometry import apply_transform, fit_rigid_transform
from couch.overrides import with_overrides
from couch.pool import finished, spawn_pool
from couch.rotations import rotation_angle
from couch.schema import ProcessedSession, read_processed
from couch.stats import bootstrap_interval
from couch.tools.sim.truth import CONTACT_DISTANCE

__all__ = ["BONES", "BONE_SOURCES", "FLOOR_PLAIN", "NEAR_CHAIR", "SESSIONS", "SessionAccuracy",
           "bone_errors", "contact_counts", "distance_errors", "edge_errors", "episode_counts",
           "f1_intervals", "most_wrong", "session_accuracy", "truth_from_ours"]

#: m: part-to-chair distances are compared where the true one is under this (the contact
#: flags enter at 2 cm and leave at 2.5).
NEAR_CHAIR = 0.04
HANDS = (CONTACT_NAMES.index("left_hand"), CONTACT_NAMES.index("right_hand"))
#: m: the plain floor truth: a true foot whose lowest point is this close to the floor is on it
#: (the simulator's chair truth distance, with no speed or duration rule)
FLOOR_PLAIN = CONTACT_DISTANCE
#: (name, parent joint, child joint): bones whose direction the suit, the per-frame fits and
#: the fused motion are scored on: the chain that carries each hand, and the spine and neck.
BONES: tuple[tuple[str, int, int], ...] = tuple(
    (name, JOINT_INDEX[a], JOINT_INDEX[b]) for name, a, b in (
        ("spine", "spine2", "spine3"), ("neck", "neck", "head"),
        ("left collar", "left_collar", "left_shoulder"),
        ("right collar", "right_collar", "right_shoulder"),
        ("left upper arm", "left_shoulder", "left_elbow"),
        ("right upper arm", "right_shoulder", "right_elbow"),
        ("left forearm", "left_elbow", "left_wrist"),
        ("right forearm", "right_elbow", "right_wrist"),
        ("left hand", "left_wrist", "left_hand"), ("right hand", "right_wrist", "right_hand")))
#: the motions :attr:`SessionAccuracy.bone_deg` scores, in its row order
BONE_SOURCES = ("suit", "per-frame fits", "fused")

#: (name, simulate_session settings): each chair kind, each interaction type, noise 0.5-1.5x;
#: seeds whose subject and chair the simulator draws within a few tries.
SESSIONS: list[tuple[str, dict[str, Any]]] = [
    ("armchair-right", dict(seed=5, chair="armchair", noise=1.5, interaction="right_hand")),
    ("straight-left", dict(seed=22, chair="straight", noise=1.0, interaction="left_hand")),
    ("sofa-both", dict(seed=23, chair="sofa", noise=1.0, interaction="both_hands")),
    ("stool-none", dict(seed=21, chair="stool", noise=0.5, interaction="no_contact")),
    ("armchair-both", dict(seed=57, chair="armchair", noise=1.0, interaction="both_hands")),
    ("straight-right", dict(seed=24, chair="straight", noise=1.5, interaction="right_hand")),
    ("sofa-left", dict(seed=21, chair="sofa", noise=0.5, interaction="left_hand")),
    ("armchair-free", dict(seed=21, chair="armchair", noise=1.0, interaction="free")),
]


@dataclasses.dataclass
class SessionAccuracy:
    """One processed session against its truth.

    Attributes:
        chair_deg: rotation error of the registered chair (degrees).
        chair_mm / chair_centre_mm: its worst scan vertex's / its centre's position error (mm).
        chair_surface_mm: its worst scan vertex's distance from the true surface (mm): small
            for a symmetric chair (a stool) registered turned by one of its symmetries, where
            the rotation and vertex errors are not.
        chair_ambiguous: the registration reported other turns fitting as well (symmetric).
        chamfer_cm: the registration's chamfer to the chair points (cm).
        mpjpe_cm: mean per-joint position error of the processed motion (cm).
        contacts: (5,3) int true positive, false positive and false negative frames per part
            (``CONTACT_NAMES`` order).
        labels: interaction label accuracy over the processed frames.
        time_ms: largest difference between the processed and the true frame times (ms).
        noise_mm: the processed motion's per-frame noise as the contact detector measured it
            (mm), and guard how much of its noise guards that asked for (``Contacts.guard``).
        distance_errors: per part, our part-to-chair distance − the true motion's (m;
            positive: ours farther from the chair) in the frames where the true one is under
            :data:`NEAR_CHAIR` (where flags are decided): a measure of contact accuracy that
            one frame more or less does not move, unlike F1 over a few dozen frames, and whose
            sign tells a fit that holds a part off the chair from one that is only noisy.
        edges: (5,) int per part: how many of its wrong frames (false positives and false
            negatives) lie within one frame of a true contact's start or end
            (:func:`edge_errors`): a contact found a frame early or late.
        episodes: (5,3) int per part: true contacts (runs of true frames), those of them
            that some frame of ours overlaps, and our contacts that overlap no true frame
            (:func:`episode_counts`).
        floor: (2,3) int per foot (left, right): true positive, false positive and false
            negative frames of our feet-on-the-floor flags against the same contact rule
            (``detect_contacts``: height, speed, hysteresis) run on the true motion, which
            tells the fit's error from the rule's choices; the simulator's truth has no floor
            contacts of its own.
        floor_plain: (2,3) the same against a plain threshold: the true foot's lowest point
            within :data:`FLOOR_PLAIN` of the floor, at any speed (a foot lifting off or
            landing counts there, not in the rule).
        floor_point_errors: (n,) m, distance of our planted foot's floor point to the true
            one's over the frames both flag (both feet).
        point_errors: per part, (n,) m, distance of our contact point on the chair to the one
            the contact rule puts on the true motion, over the frames both flag (the
            simulator's own points are each part's single closest chair point, which jumps
            across a seat; the rule's are patch centres, as ours).
        bone_deg: (3,B) degrees, each :data:`BONES` bone's direction against the truth's, mean
            over the frames, for the aligned suit, the per-frame fits and the fused motion
            (:data:`BONE_SOURCES`): how much of the suit's error the cameras take out.
    """

    chair_deg: float
    chair_mm: float
    chair_centre_mm: float
    chair_surface_mm: float
    chair_ambiguous: bool
    chamfer_cm: float
    mpjpe_cm: float
    contacts: np.ndarray
    labels: float
    time_ms: float
    noise_mm: float
    guard: float
    distance_errors: list[np.ndarray] = dataclasses.field(default_factory=list)
    edges: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros(len(CONTACT_NAMES), np.int64))
    episodes: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros((len(CONTACT_NAMES), 3), np.int64))
    floor: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((2, 3), np.int64))
    floor_plain: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros((2, 3), np.int64))
    floor_point_errors: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    point_errors: list[np.ndarray] = dataclasses.field(default_factory=list)
    bone_deg: np.ndarray = dataclasses.field(
        default_factory=lambda: np.full((len(BONE_SOURCES), len(BONES)), np.nan))

    @property
    def f1(self) -> np.ndarray:
        """(5,) contact F1 per part (1 where neither side has a contact frame)."""
        return f1_score(self.contacts)

    @property
    def true_frames(self) -> np.ndarray:
        """(5,) frames in which the truth has each part in contact."""
        return self.contacts[:, 0] + self.contacts[:, 2]

    def line(self, name: str) -> str:
        return (f"[{name}] chair rotation {self.chair_deg:.3f} deg, position (centre) error "
                f"{self.chair_centre_mm:.2f} mm, largest vertex error {self.chair_mm:.2f} mm "
                f"({self.chair_surface_mm:.2f} mm from the true surface), "
                f"chamfer {self.chamfer_cm:.3f} cm; MPJPE {self.mpjpe_cm:.2f} cm; contact F1 "
                + ", ".join(f"{n} {f:.2f} ({t} true frames)" for n, f, t in
                            zip(CONTACT_NAMES, self.f1, self.true_frames, strict=True))
                + ("; contact points off by " + " / ".join(
                    _cm(e) for e in self.point_errors[:3]) + " (pelvis / hands, mean)"
                   if self.point_errors else "")
                + "; feet on the floor F1 " + " / ".join(
                    f"{f:.2f}" for f in f1_score(self.floor))
                + f" ({self.floor[:, 0].sum() + self.floor[:, 2].sum()} true frames, the "
                f"point off by {_cm(self.floor_point_errors)} mean)"
                + f"; label accuracy {self.labels:.3f}; time stamps within {self.time_ms:.3f} ms"
                f"; motion noise {self.noise_mm:.1f} mm (guard {self.guard:.2f})"
                + ("; hand distance error near the chair (mean) " + " / ".join(
                    f"{_cm(np.abs(self.distance_errors[k]))}" for k in HANDS)
                   if self.distance_errors else ""))


def _interval(ci: np.ndarray) -> str:
    """" [low, high]" of a (2,) bootstrap interval, or "" where there is none (NaN)."""
    return f" [{ci[0]:.3f}, {ci[1]:.3f}]" if np.isfinite(ci).all() else ""


def _cm(errors: np.ndarray, q: float | None = None) -> str:
    if not len(errors):
        return "-"
    return f"{100 * (np.mean(errors) if q is None else np.percentile(errors, q)):.2f} cm"


def _paired(ours: np.ndarray, true: np.ndarray, dtype: type, what: str
            ) -> tuple[np.ndarray, np.ndarray]:
    """Both (T,K) arrays as ``dtype``, or a ValueError starting with ``what``."""
    ours, true = np.asarray(ours, dtype), np.asarray(true, dtype)
    if ours.shape != true.shape or ours.ndim != 2:
        raise ValueError(f"{what} {ours.shape} and {true.shape} must be the same (T,K)")
    return ours, true


def contact_counts(ours: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(K,3) int per part of (T,K) bool flags: true positive, false positive and false
    negative frames of ``ours`` against ``true``."""
    ours, true = _paired(ours, true, bool, "contact_counts: flags")
    return np.stack([(ours & true).sum(0), (ours & ~true).sum(0), (~ours & true).sum(0)],
                    1).astype(np.int64)


def distance_errors(ours: np.ndarray, true: np.ndarray, near: float = NEAR_CHAIR
                    ) -> list[np.ndarray]:
    """Per part k, ``ours[:, k] − true[:, k]`` (m; positive: ours farther) where
    ``true[:, k] < near``, from (T,K) part-to-chair distances (m) of the same frames."""
    ours, true = _paired(ours, true, np.float64, "distance_errors: distances")
    return [ours[m, k] - true[m, k] for k, m in enumerate((true < near).T)]


def edge_errors(ours: np.ndarray, true: np.ndarray, width: int = 1) -> np.ndarray:
    """(K,) int per part: frames where the (T,K) bool flags ``ours`` and ``true`` differ and
    ``true`` changes within ``width`` frames of them (a true contact's first or last frame, or
    a frame next to it): contacts found early or late rather than missed or invented."""
    ours, true = _paired(ours, true, bool, "edge_errors: flags")
    t = len(true)
    lo, hi = np.maximum(np.arange(t) - width, 0), np.minimum(np.arange(t) + width + 1, t)
    # the true flag is not constant over [k - width, k + width]: counts of True differ from
    # both 0 and the window's length
    c = np.concatenate([np.zeros((1, true.shape[1]), np.int64), np.cumsum(true, 0)])
    n = c[hi] - c[lo]
    edge = (n > 0) & (n < (hi - lo)[:, None])
    return ((ours != true) & edge).sum(0)


def episode_counts(ours: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(K,3) int per part of (T,K) bool flags: true contacts (runs of True in ``true``), how
    many of them some frame of ``ours`` overlaps, and runs of ``ours`` that overlap no true
    frame."""
    ours, true = _paired(ours, true, bool, "episode_counts: flags")
    out = np.zeros((true.shape[1], 3), np.int64)
    for k, a, b in contact_runs(true):
        out[k, 0] += 1
        out[k, 1] += bool(ours[a:b, k].any())
    for k, a, b in contact_runs(ours):
        out[k, 2] += not true[a:b, k].any()
    return out


def f1_score(counts: np.ndarray) -> np.ndarray:
    """(...,3) true positive, false positive, false negative counts → (...) F1 (1 when all
    three are 0: nothing to find and nothing found)."""
    tp, fp, fn = np.moveaxis(np.asarray(counts, np.float64), -1, 0)
    return np.where(tp + fp + fn > 0, 2 * tp / np.maximum(2 * tp + fp + fn, 1), 1.0)


def f1_intervals(counts: np.ndarray, *, level: float = 0.95, resamples: int = 2000,
                 seed: int = 0) -> np.ndarray:
    """(K,2) bootstrap interval (low, high) of each part's pooled F1, from (S,K,3) true
    positive, false positive, false negative counts of S sessions: sessions are resampled
    with replacement and their counts pooled (a session's frames are not independent of each
    other, so the session is the unit). NaN with fewer than two sessions."""
    c = np.asarray(counts, np.int64)
    if c.ndim != 3 or c.shape[2] != 3:
        raise ValueError(f"f1_intervals: counts must be (sessions, parts, 3), got {c.shape}")
    return np.array([bootstrap_interval(lambda i, k=k: float(f1_score(c[i, k].sum(0))),
                                        len(c), level=level, resamples=resamples, seed=seed)
                     for k in range(c.shape[1])]).reshape(c.shape[1], 2)


def most_wrong(labels: list[str], counts: np.ndarray, part: int, top: int = 3
               ) -> list[tuple[str, int]]:
    """The ``top`` sessions with the most wrong frames (false positives + negatives) of
    ``part``, from (S,K,3) true positive, false positive, false negative counts of the
    sessions ``labels``, most first (ties in session order), sessions without any left out: a
    pooled F1 below target is often one or two sessions, which is where to look."""
    c = np.asarray(counts, np.int64)
    if c.ndim != 3 or c.shape[2] != 3 or len(c) != len(labels):
        raise ValueError(f"most_wrong: counts must be ({len(labels)}, parts, 3), got {c.shape}")
    wrong = c[:, part, 1] + c[:, part, 2]
    order = np.argsort(-wrong, kind="stable")[:top]
    return [(labels[i], int(wrong[i])) for i in order if wrong[i] > 0]


def truth_from_ours(result: PipelineResult, info: dict[str, Any]) -> np.ndarray:
    """(4,4) our world → the simulator's world, from the cameras' centres (``info``: the
    session's truth.json)."""
    true = {c["serial"]: np.array(c["world_from_depth"]) for c in info["cameras"]}
    serials = [s for s in result.extrinsics.cameras if s in true]
    ours = np.array([result.extrinsics.world_from_depth(s)[:3, 3] for s in serials])
    return fit_rigid_transform(ours, np.array([true[s][:3, 3] for s in serials]))


def session_accuracy(result: PipelineResult, truth: ProcessedSession,
                     info: dict[str, Any], contact_model: str | None = None,
                     contacts: ContactConfig | None = None) -> SessionAccuracy:
    """The issue's end-to-end numbers of one processed session against the simulator's truth
    (``truth``: its ground_truth.h5; ``info``: its truth.json; ``contact_model``: the body
    model the run measured contacts on, ``ProcessConfig.contact_model``; ``contacts``: the
    run's contact rule, ``ProcessConfig.contacts``, which is also run on the true motion;
    None: their defaults)."""
    data = read_processed(result.processed)
    align = truth_from_ours(result, info)
    rows = data.quality["frame_rows"]
    errors: list[np.ndarray] = []
    floor = floor_plain = np.zeros((2, 3), np.int64)
    floor_points = np.zeros(0)
    point_errors: list[np.ndarray] = []
    if result.contacts is not None:
        # the true motion's distances as the detector measures ours (same body model, same
        # smoothing rule: none for a motion this clean), to its chair in its world, whose
        # floor is y = 0
        true_motion = BodyParams(betas=truth.betas, global_orient=truth.global_orient[rows],
                                 body_pose=truth.body_pose[rows], transl=truth.transl[rows])
        true_chair = apply_transform(truth.object_pose, truth.object_vertices.astype(np.float64))
        model = cached_model(contact_model or ProcessConfig().contact_model)
        true_c = detect_contacts(true_motion, model, true_chair, truth.object_faces,
                                 fps=data.fps, config=contacts)
        ours_c = result.contacts
        errors = distance_errors(ours_c.distance, true_c.distance, NEAR_CHAIR)
        floor = contact_counts(ours_c.floor_active, true_c.floor_active)
        floor_plain = contact_counts(ours_c.floor_active, true_c.floor_distance < FLOOR_PLAIN)
        both = ours_c.floor_active & true_c.floor_active
        floor_points = _point_errors(align, ours_c.floor_points[both],
                                     true_c.floor_points[both])
        both = ours_c.active & true_c.active
        point_errors = [_point_errors(align, ours_c.points[both[:, k], k],
                                      true_c.points[both[:, k], k])
                        for k in range(len(CONTACT_NAMES))]
    true_pose = np.array(info["chair"]["world_from_scan"])
    est = align @ data.object_pose
    v = data.object_vertices.astype(np.float64)
    act, true_act = data.contact_active, truth.contact_active[rows]
    centre = v.mean(0)[None]
    surface = o3d.t.geometry.RaycastingScene()
    surface.add_triangles(o3d.core.Tensor(apply_transform(true_pose, v).astype(np.float32)),
                          o3d.core.Tensor(data.object_faces.astype(np.uint32)))
    off = surface.compute_distance(o3d.core.Tensor(apply_transform(est, v).astype(np.float32)))
    return SessionAccuracy(
        chair_deg=float(np.degrees(rotation_angle(est[:3, :3].T @ true_pose[:3, :3]))),
        chair_mm=float(np.linalg.norm(apply_transform(est, v) - apply_transform(true_pose, v),
                                      axis=1).max() * 1e3),
        chair_centre_mm=float(np.linalg.norm(apply_transform(est, centre)
                                             - apply_transform(true_pose, centre)) * 1e3),
        chair_surface_mm=float(off.numpy().max() * 1e3),
        chair_ambiguous=bool(result.chair.ambiguous),
        chamfer_cm=float(result.chair.chamfer * 100),
        mpjpe_cm=float(mpjpe(apply_transform(align, data.joints.astype(np.float64)),
                             truth.joints[rows]).mean() * 100),
        contacts=contact_counts(act, true_act),
        labels=float((data.interaction == truth.interaction[rows]).mean()),
        time_ms=float(np.abs(data.time - truth.time[rows]).max() * 1e3),
        noise_mm=float(result.contacts.noise * 1e3) if result.contacts else float("nan"),
        guard=float(result.contacts.guard) if result.contacts else float("nan"),
        distance_errors=errors,
        edges=edge_errors(act, true_act),
        episodes=episode_counts(act, true_act),
        floor=floor,
        floor_plain=floor_plain,
        floor_point_errors=floor_points,
        point_errors=point_errors,
        bone_deg=np.stack([bone_errors(apply_transform(align, np.asarray(j, np.float64)),
                                       truth.joints[rows])
                           for j in (result.body.imu_joints, result.body.fit_joints,
                                     data.joints)]),
    )


def bone_errors(ours: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(B,) degrees: the angle between each :data:`BONES` bone's direction in ``ours`` and in
    ``true`` ((T,24,3) joints, one world), mean over the frames where ``ours`` has them (the
    per-frame fits are NaN on rows not fitted)."""
    par = [b[1] for b in BONES]
    child = [b[2] for b in BONES]
    a = ours[:, child] - ours[:, par]
    b = true[:, child] - true[:, par]
    cos = (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.nanmean(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), axis=0)


def _point_errors(align: np.ndarray, ours: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(n,) m between (n,3) points of ours (our world; ``align`` maps it to the truth's) and
    the truth's."""
    return np.linalg.norm(apply_transform(align, np.asarray(ours, np.float64)) - true, axis=-1)


def _one(name: str, settings: dict[str, Any], work: Path, fps: float, duration: float,
         overrides: tuple[str, ...] = (), reuse: bool = False,
         sim_overrides: tuple[str, ...] = (), workers: int | None = 1) -> SessionAccuracy | str:
    """One session simulated (unless ``work`` holds it), processed (``overrides``: ``--set``
    items on the default :class:`ProcessConfig`; ``reuse``: cached stage results whose inputs
    and settings are unchanged serve, else every stage runs) and measured; a string says why
    it could not be. ``sim_overrides``: ``--sim-set`` items on the session's
    :class:`~couch.tools.sim.session.SessionConfig`; a kept session simulated otherwise (in
    those settings or the oracles') is not measured. ``workers``: ``couch-process``'s."""
    from couch.tools.sim.session import (
        ORACLES,
        NoPlausibleSequence,
        SessionConfig,
        simulate_session,
    )

    root = work / name
    sim = with_overrides(SessionConfig(cameras=4, depth_mode="NFOV_2X2BINNED", color=False,
                                       charuco_poses=4, fps=fps, duration=duration,
                                       **settings), sim_overrides)
    if (root / "truth.json").exists():
        kept = json.loads((root / "truth.json").read_text()).get("config", {})
        fields = SessionConfig.__dataclass_fields__
        # what was asked, and the oracles whether asked or not (a default run in an oracle's
        # folder would measure the oracle)
        keys = dict.fromkeys([item.split("=", 1)[0] for item in sim_overrides]
                             + list(ORACLES))
        other = [key for key in keys if kept.get(key, fields[key].default) != getattr(sim, key)]
        if other:
            return (f"kept in {root} with other simulator settings ({', '.join(other)}); "
                    f"give --sim-set runs their own -o folder")
    else:
        try:
            simulate_session(root, sim, progress=False)
        except NoPlausibleSequence as e:
            return f"not simulated: {e}"
    config = with_overrides(ProcessConfig(), overrides)
    result = couch.process(root, work / f"{name}.out", config=config, force=not reuse,
                           report=False, workers=workers)
    if not result.ok:
        return f"processing failed at {result.fault[0]}: {result.fault[1]}"
    return session_accuracy(result, read_processed(root / "ground_truth.h5"),
                            json.loads((root / "truth.json").read_text()),
                            contact_model=config.contact_model, contacts=config.contacts)


def _timed(label: str, name: str, settings: dict[str, Any], work: Path, fps: float,
           duration: float, threads: int | None, overrides: tuple[str, ...] = (),
           reuse: bool = False, sim_overrides: tuple[str, ...] = (),
           workers: int | None = 1) -> tuple[str, SessionAccuracy | str, float]:
    """:func:`_one` in a worker process: (label, its result, seconds)."""
    if threads:
        torch.set_num_threads(threads)
    t0 = time.perf_counter()
    return (label, _one(name, settings, work, fps, duration, overrides, reuse, sim_overrides,
                        workers), time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-o", "--output", type=Path, default=None,
                    help="keep the simulated sessions and outputs here (re-used when present; "
                         "default: a temporary folder)")
    ap.add_argument("--sessions", type=int, default=len(SESSIONS),
                    help=f"the first N of the {len(SESSIONS)} sessions")
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--duration", type=float, default=8.0, help="seconds per session")
    ap.add_argument("--threads", type=int, default=None, help="torch threads")
    ap.add_argument("--jobs", type=int, default=1,
                    help="sessions simulated and processed at a time, each in its own process "
                         "(default 1: in this process)")
    ap.add_argument("--seed-offset", type=int, nargs="+", default=[0],
                    help="add this to every session's simulator seed: the same kinds of "
                         "session on other draws (held out from whatever was tuned on these); "
                         "several offsets pool their sessions")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="process with this setting changed (repeatable; couch-process --set)")
    ap.add_argument("--sim-set", action="append", default=[], metavar="KEY=VALUE",
                    help="simulate with this session setting changed (repeatable; a field of "
                         "the simulator's SessionConfig, e.g. clothing=false or "
                         "imu_misalignment=0: oracles for what one error source costs)")
    ap.add_argument("--reuse", action="store_true",
                    help="let cached stage results whose inputs and settings are unchanged "
                         "serve (with -o: e.g. calibration and chair when only body settings "
                         "are --set); default: every stage runs")
    args = ap.parse_args(argv)
    from couch.tools.sim.session import SessionConfig

    try:  # a bad key fails here, not in every job
        with_overrides(ProcessConfig(), args.set)
    except ValueError as exc:
        ap.error(str(exc))
    try:
        with_overrides(SessionConfig(), args.sim_set)
    except ValueError as exc:
        ap.error(str(exc).replace("--set ", "--sim-set ", 1))
    if not 1 <= args.sessions <= len(SESSIONS):
        ap.error(f"--sessions must be in 1..{len(SESSIONS)}")
    if args.jobs < 1:
        ap.error(f"--jobs must be at least 1, got {args.jobs}")
    if args.jobs > 1 and not args.threads:  # the cores shared out, not each job taking all
        args.threads = max(1, (os.cpu_count() or 1) // args.jobs)
    if args.threads:
        torch.set_num_threads(args.threads)
    results: dict[str, SessionAccuracy | str] = {}

    def report(label: str, a: SessionAccuracy | str, seconds: float) -> None:
        results[label] = a
        print(f"[{label}] {a}" if isinstance(a, str) else a.line(label) + f" ({seconds:.0f} s)",
              flush=True)

    with tempfile.TemporaryDirectory() as tmp:
        tasks = []
        for offset in args.seed_offset:
            work = args.output or Path(tmp)
            if offset:  # a kept folder is re-used by session name: other draws, other names
                work = work / f"seed{offset:+d}"
            work.mkdir(parents=True, exist_ok=True)
            for name, settings in SESSIONS[:args.sessions]:
                tasks.append((f"{name}{offset:+d}" if offset else name, name,
                              dict(settings, seed=settings["seed"] + offset), work, args.fps,
                              args.duration, args.threads, tuple(args.set), args.reuse,
                              tuple(args.sim_set),
                              # the sessions spread over the cores (--jobs), or one session does
                              1 if args.jobs > 1 else None))
        if args.jobs == 1:
            for task in tasks:
                report(*_timed(*task))
        else:
            # each task sets its own thread count (--threads)
            with spawn_pool(args.jobs, threads=None) as pool:
                futures: list[Future[tuple[str, SessionAccuracy | str, float]]] = [
                    pool.submit(_timed, *task) for task in tasks]
                for fut in finished(futures):
                    report(*fut.result())
    # pooled in the sessions' order whatever order they finished in (the intervals resample
    # sessions by index)
    labels = [task[0] for task in tasks]
    ok = [label for label in labels if not isinstance(results[label], str)]
    rows = [results[label] for label in ok]
    failed = [label for label in labels if isinstance(results[label], str)]
    offsets = ", ".join(str(o) for o in args.seed_offset)
    print(f"\n{len(rows)} sessions (seed offset {offsets}), {args.fps:g} fps, "
          f"{args.duration:g} s each "
          f"(torch threads {torch.get_num_threads()}, cores {os.cpu_count()})"
          + (f"; settings changed: {', '.join(args.set)}" if args.set else "")
          + (f"; simulated with {', '.join(args.sim_set)}" if args.sim_set else "")
          + (f"; {len(failed)} failed: {', '.join(failed)}" if failed else ""))
    if not rows:
        return 1
    per_session = np.stack([a.contacts for a in rows])  # (S,K,3)
    counts = per_session.sum(0)
    edges = np.sum([a.edges for a in rows], axis=0)
    episodes = np.sum([a.episodes for a in rows], axis=0)
    pooled = f1_score(counts)
    spread = f1_intervals(per_session)
    plain = [a for a in rows if not a.chair_ambiguous]
    if plain:
        print(f"chair: worst vertex {max(a.chair_mm for a in plain):.2f} mm, rotation "
              f"{max(a.chair_deg for a in plain):.3f} deg (largest of the {len(plain)} "
              f"sessions whose chair was not reported symmetric)")
    print(f"chair: worst vertex {max(a.chair_surface_mm for a in rows):.2f} mm from the true "
          f"surface, chamfer {max(a.chamfer_cm for a in rows):.2f} cm (largest of all)")
    print(f"body: MPJPE {np.mean([a.mpjpe_cm for a in rows]):.2f} cm mean, "
          f"{max(a.mpjpe_cm for a in rows):.2f} cm largest")
    for k, n in enumerate(CONTACT_NAMES):
        tp, fp, fn = counts[k]
        err = np.concatenate([a.distance_errors[k] for a in rows if a.distance_errors]
                             + [np.zeros(0)])
        near = (f"distance to the chair off by {_cm(np.abs(err))} mean, "
                f"{_cm(np.abs(err), 90)} 90th percentile, {100 * np.median(err):+.2f} cm "
                f"median signed (+: ours farther) over the {len(err)} frames it is truly under "
                f"{100 * NEAR_CHAIR:g} cm"
                if len(err) else f"never truly under {100 * NEAR_CHAIR:g} cm from the chair")
        pts = np.concatenate([a.point_errors[k] for a in rows if a.point_errors]
                             + [np.zeros(0)])
        if len(pts):
            near += (f"; contact point off by {_cm(pts)} mean, {_cm(pts, 90)} 90th percentile "
                     f"over the {len(pts)} frames both flag")
        print(f"contact {n:<10} F1 {pooled[k]:.3f}{_interval(spread[k])} (tp/fp/fn "
              f"{tp}/{fp}/{fn}; wrong frames within a frame of a true contact's start or end "
              f"{edges[k]}/{fp + fn}; true contacts found {episodes[k, 1]}/{episodes[k, 0]}, "
              f"invented {episodes[k, 2]}); {near}")
    floors = np.stack([a.floor for a in rows])  # (S,2,3)
    floor_counts = floors.sum(0)
    floor_f1 = f1_score(floor_counts)
    floor_ci = f1_intervals(floors)
    plain_counts = np.sum([a.floor_plain for a in rows], axis=0)
    points = np.concatenate([a.floor_point_errors for a in rows])
    for k, n in enumerate(FEET):
        tp, fp, fn = floor_counts[k]
        ptp, pfp, pfn = plain_counts[k]
        print(f"floor   {n:<10} F1 {floor_f1[k]:.3f}{_interval(floor_ci[k])} (tp/fp/fn "
              f"{tp}/{fp}/{fn}) against the "
              f"contact rule on the true motion; {f1_score(plain_counts[k]):.3f} (tp/fp/fn "
              f"{ptp}/{pfp}/{pfn}) against the true foot within {100 * FLOOR_PLAIN:g} cm of the "
              f"floor at any speed")
    print(f"floor: planted foot point off by {_cm(points)} mean, {_cm(points, 90)} 90th "
          f"percentile over the {len(points)} foot frames both flag")
    bones = np.nanmean([a.bone_deg for a in rows], axis=0)  # (3,B), sessions weighted alike
    print("bone directions off by (deg, mean over the sessions), " + " / ".join(BONE_SOURCES)
          + ": " + ", ".join(f"{name} " + " / ".join(f"{x:.1f}" for x in bones[:, i])
                             for i, (name, _, _) in enumerate(BONES)))
    for k in HANDS:
        worst = most_wrong(ok, per_session, k)
        if worst:
            print(f"{CONTACT_NAMES[k]}: most wrong frames in "
                  + ", ".join(f"{label} ({n})" for label, n in worst))
    low = int(np.argmin([a.labels for a in rows]))
    print(f"labels: accuracy {np.mean([a.labels for a in rows]):.3f} mean, "
          f"{rows[low].labels:.3f} lowest ({ok[low]})")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
