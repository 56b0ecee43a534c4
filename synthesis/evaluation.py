"""The COUCH evaluation protocol (paper Sec. 5) over any set of synthesis methods.

Per chair (held out from training): ``trials`` characters start at random points 2-4 m from
the seat, within ±120° of the chair's front, facing the chair ±45° (as the data's approaches
start), and are asked for a random contact set (left hand only, right hand only, or both)
drawn from the chair's contact candidates (armrest tops, the seat's front corners:
:func:`contact_candidates`; both hands on the same part and within :data:`HAND_SPAN` of each
other, as a seated person holds them); every method gets the same starts and contacts and runs for
``seconds`` (paper: 16 s). Metrics (:mod:`.metrics`):

- ACE (cm) and AP@3/5/7/9 cm (%): closest approach of each hand's surface (the body model's
  hand contact vertices, coarse body) to its contact, which is a point on the chair's surface
  where the palm should rest; "joint ACE" the same for the SMPL hand joints 22/23, which
  stay several centimetres off a touched surface (7.5 cm on average in the simulated data);
- sat (%): trials whose predicted pelvis contact is on at the end;
- APD of approach and sit segments: root-frame joint positions over the second before and the
  second after the sit onset (first predicted pelvis contact), over all trials;
- foot sliding (mm/frame, CHOIS weighting) and penetration (coarse body vertices against the
  chair's signed distance: mean per-frame max depth, cm, and % of frames deeper than 4 cm);
- contact APD of ContactNet samples (L chairs x N samples), per run: within each chair (the
  paper's) and pooled over the chairs, as one group ("pooled", which the ground truth's row
  also gives: a recording has one chair, so its per-chair diversity needs several recordings
  of the same chair, and pooled over chairs of different sizes the diversity is larger).

:func:`ground_truth_row` gives the same APDs of captured/simulated sequences for comparison.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Iterable, Mapping, Sequence

import numpy as np
import torch
from tqdm import tqdm

from couch.body import CONTACT_NAMES, JOINT_INDEX, load_body_model
from couch.geometry import apply_transform, invert_transform
from couch.schema import ProcessedSession
from couch.synthesis.controller import HAND_REACH_X, Scene, SynthesisResult, Synthesizer
from couch.synthesis.data import chair_id
from couch.synthesis.features import root_transforms, to_root
from couch.synthesis.metrics import (
    AP_THRESHOLDS,
    ace,
    apd,
    closest_hand_distances,
    closest_hand_offsets,
    contact_apd,
    contact_precision,
    foot_sliding,
    penetration,
)
from couch.synthesis.sampling import sample_contacts

__all__ = ["HAND_SPAN", "EvalChair", "contact_breakdown", "contact_candidates", "evaluate",
           "ground_truth_row", "miss_breakdown", "segment_apd", "trial_setup"]

HAND_JOINTS = (JOINT_INDEX["left_hand"], JOINT_INDEX["right_hand"])


@dataclasses.dataclass
class EvalChair:
    """A chair mesh in the chair frame (metres, +Y up, floor y = 0, facing +Z)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray


#: The widest two-hand contact set a trial asks for (m between the contacts): 95 % of the
#: simulated sitters' two-hand holds are narrower (0.77 m; median 0.44-0.54 m per chair kind).
#: Both armrests of a sofa 1.2-1.8 m wide are out of a seated person's reach together.
HAND_SPAN = 0.8


def contact_candidates(vertices: np.ndarray, faces: np.ndarray
                       ) -> dict[str, dict[str, list[np.ndarray]]]:
    """Chair-frame hand contact candidates per hand and part, from the part segmentation
    (:func:`couch.augment.segment_parts`): the armrest's top (centre and front) and the seat's
    front corner on that hand's side (+X is the sitter's left), 5 cm in from the front edge and
    at most ``HAND_REACH_X`` out from the centre: where the data's hands go (the paper samples
    its test contacts from the dataset; the simulated sitters touch the seat at its front
    corners, beside the thighs, and the armrests anywhere from their middle forwards).
    ``{"left": {"armrest": [...], "seat": [...]}, "right": {...}}`` (a part the chair lacks
    is absent)."""
    from couch.augment import segment_parts

    parts = segment_parts(vertices, faces)
    out: dict[str, dict[str, list[np.ndarray]]] = {"left": {}, "right": {}}
    for side, sign in (("left", 1.0), ("right", -1.0)):
        arm = parts.frames.get(f"{side}_armrest")
        if arm is not None:
            out[side]["armrest"] = [arm.centre, arm.to_world(np.array([[0.0, 0.6, 0.0]]))[0]]
        seat = parts.frames.get("seat")
        if seat is not None:
            half_x, _, half_z = seat.half_span()
            corner = seat.centre.copy()
            corner[0] += sign * min(0.85 * half_x, HAND_REACH_X)
            corner[2] += max(half_z - 0.05, 0.0)
            out[side]["seat"] = [corner]
    return out


def _hand_pairs(candidates: Mapping[str, Mapping[str, list[np.ndarray]]]
                ) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """Two-hand contact sets a seated person can hold, per part: a left and a right candidate
    of the same part (the simulated sitters put both hands on the armrests or both on the
    seat: a torso does not lean towards an armrest on one side and the seat on the other) at
    most :data:`HAND_SPAN` apart."""
    out: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for part in sorted(set(candidates["left"]) & set(candidates["right"])):
        pairs = [(a, b) for a in candidates["left"][part] for b in candidates["right"][part]
                 if np.linalg.norm(a - b) <= HAND_SPAN]
        if pairs:
            out[part] = pairs
    return out


def trial_setup(scene: Scene, candidates: Mapping[str, Mapping[str, list[np.ndarray]]],
                trials: int, rng: np.random.Generator
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random starts (trials, 3) (x, z, heading), contact sets (trials, 2, 3) in the world and
    the part each contact is on (trials, 2) (``"armrest"``, ``"seat"``; ``""``: none asked).

    A third of the trials ask for the left hand, a third the right, a third both. A one-hand
    contact is any of that hand's ``candidates`` (:func:`contact_candidates`); a two-hand set
    is drawn from a part both hands have, then from its pairs within :data:`HAND_SPAN` (a
    chair with no such pair gets a one-hand trial instead)."""
    goal = scene.goal
    angle = rng.uniform(-2 * np.pi / 3, 2 * np.pi / 3, trials)  # around the chair's front
    radius = rng.uniform(2.0, 4.0, trials)
    front = scene.world_from_chair[:3, 2]
    base = np.arctan2(front[0], front[2])
    x = goal[0, 3] + radius * np.sin(base + angle)
    z = goal[2, 3] + radius * np.cos(base + angle)
    # Facing the chair give or take 45 degrees, as the captured (and simulated) approaches
    # start: turning on the spot from facing away is not in the data.
    towards = np.arctan2(goal[0, 3] - x, goal[2, 3] - z)
    starts = np.stack([x, z, towards + rng.uniform(-np.pi / 4, np.pi / 4, trials)], -1)
    sets = np.full((trials, 2, 3), np.nan)
    parts = np.full((trials, 2), "", dtype=object)
    single = {side: [(part, p) for part, points in candidates[side].items() for p in points]
              for side in ("left", "right")}
    pairs = _hand_pairs(candidates)
    kinds = rng.integers(0, 3, trials)  # 0 left, 1 right, 2 both
    for i, kind in enumerate(kinds):
        if kind == 2 and pairs:
            part = list(pairs)[rng.integers(len(pairs))]
            chosen = [(part, c) for c in pairs[part][rng.integers(len(pairs[part]))]]
        else:
            h = int(kind) if kind < 2 else int(rng.integers(2))
            side = ("left", "right")[h]
            if not single[side]:
                continue
            chosen = [None, None]
            chosen[h] = single[side][rng.integers(len(single[side]))]
        for h, c in enumerate(chosen):
            if c is not None:
                parts[i, h] = c[0]
                sets[i, h] = (scene.world_from_chair @ np.append(c[1], 1.0))[:3]
    return starts, sets, parts


def _sit_onsets(result: SynthesisResult) -> np.ndarray:
    """(B,) first frame with predicted pelvis contact (-1: never sat)."""
    sat = result.contacts[..., CONTACT_NAMES.index("pelvis")] > 0.5
    return np.where(sat.any(1), sat.argmax(1), -1)


def segment_apd(joints: Sequence[np.ndarray], onsets: Sequence[int], fps: float,
                seconds: float = 1.0) -> tuple[float, float]:
    """APD of approach (``seconds`` before each sit onset) and sit (``seconds`` from it)
    segments: root-frame joint positions (:func:`couch.synthesis.features.root_transforms`)
    flattened per segment. ``joints``: sequences of (T,24,3) world joints; ``onsets`` their sit
    onset frames (-1: none). NaN where fewer than two sequences have the segment."""
    n = round(seconds * fps)
    approach, sit = [], []
    for j, s in zip(joints, onsets, strict=True):
        local = to_root(j[:, :22], root_transforms(j))
        if s >= n:
            approach.append(local[s - n:s].reshape(-1))
        if 0 <= s and s + n <= len(j):
            sit.append(local[s:s + n].reshape(-1))
    return (apd(np.stack(approach)) if len(approach) > 1 else float("nan"),
            apd(np.stack(sit)) if len(sit) > 1 else float("nan"))


def _body_metrics(result: SynthesisResult, sets: np.ndarray, sdf, model
                  ) -> tuple[float, float, np.ndarray]:
    """Penetration (mean depth m, % frames over 4 cm) and the hand surface points (B,T,2,3)
    closest to each asked contact (NaN where none was asked), from the posed coarse body."""
    depth, over = [], []
    batch, frames = result.root.shape[:2]
    palms = np.full((batch, frames, 2, 3), np.nan)
    for b in range(batch):
        with torch.no_grad():
            v = model(betas=result.betas[None], global_orient=result.global_orient[b],
                      body_pose=result.body_pose[b], transl=result.transl[b]).vertices.numpy()
        p = penetration(v, sdf, result.scene.world_from_chair)
        depth.append(p["mean_depth_m"])
        over.append(p["frames_over_pct"])
        for h, side in enumerate(("left_hand", "right_hand")):
            if np.isfinite(sets[b, h]).all():
                hand = v[:, model.contact_vertices[side]].astype(np.float64)  # (T,K,3)
                near = np.linalg.norm(hand - sets[b, h], axis=-1).argmin(1)
                palms[b, :, h] = hand[np.arange(frames), near]
    return float(np.mean(depth)), float(np.mean(over)), palms


def evaluate(synthesizers: Mapping[str, Synthesizer], chairs: Sequence[EvalChair], *,
             trials: int = 8, seconds: float = 16.0, seed: int = 0,
             contact_samples: int = 0, progress: bool = True
             ) -> tuple[dict[str, dict[str, float]], dict[str, np.ndarray], np.ndarray,
                        dict[str, dict[str, np.ndarray]]]:
    """Run the protocol. Returns (table rows ``{method: {metric: value}}``, raw per-trial
    closest hand-surface distances ``{method: (chairs*trials, 2)}`` in m, what each asked
    contact was (chairs*trials, 2): ``"<chair kind> <part>"``, the kind being the chair's name
    without a trailing ``_<number>`` (``"sofa armrest"``; ``""``: none asked), for
    :func:`contact_breakdown`, and where each hand missed, for :func:`miss_breakdown`:
    ``{method: {"offset": (chairs*trials, 2, 3) the closest hand surface point minus its
    contact in the chair frame (m, +Y up, +Z the chair's front), "seated": (chairs*trials, 2)
    1.0 if the character's pelvis had sat by that frame, else 0.0}}``, NaN where none asked).

    ``contact_samples`` > 0 also samples that many ContactNet contact sets per chair from each
    method's run and reports their contact APD (cm), within each chair and pooled.
    """
    from couch.augment import SignedDistanceGrid

    coarse = load_body_model("couch-body-coarse")
    rng = np.random.default_rng(seed)
    dists: dict[str, list[np.ndarray]] = {m: [] for m in synthesizers}
    joint_dists: dict[str, list[np.ndarray]] = {m: [] for m in synthesizers}
    joints: dict[str, list[np.ndarray]] = {m: [] for m in synthesizers}
    offsets: dict[str, list[np.ndarray]] = {m: [] for m in synthesizers}
    seated: dict[str, list[np.ndarray]] = {m: [] for m in synthesizers}
    onsets: dict[str, list[np.ndarray]] = {m: [] for m in synthesizers}
    extra: dict[str, dict[str, list[float]]] = {m: {"skate": [], "pen": [], "over": [],
                                                    "sat": []} for m in synthesizers}
    sampled: dict[str, list[np.ndarray]] = {m: [] for m in synthesizers}
    labels: list[np.ndarray] = []
    first = next(iter(synthesizers.values()))
    for chair in tqdm(chairs, desc="chairs", disable=not progress):
        scene = Scene.from_mesh(chair.vertices, chair.faces, first.cfg, name=chair.name)
        starts, sets, parts = trial_setup(
            scene, contact_candidates(chair.vertices, chair.faces), trials, rng)
        kind = re.sub(r"_\d+$", "", chair.name)
        labels.append(np.where(parts == "", "", kind + " " + parts.astype(str)))
        sdf = SignedDistanceGrid.from_mesh(chair.vertices, chair.faces)
        for method, syn in synthesizers.items():
            r = syn.synthesize(scene, starts, sets[:, None], seconds)
            d, o, palms = _body_metrics(r, sets, sdf, coarse)
            off, frame = closest_hand_offsets(palms, sets)
            dists[method].append(np.linalg.norm(off, axis=-1))
            # row vectors times world_from_chair's rotation: into the chair frame
            offsets[method].append(off @ scene.world_from_chair[:3, :3])
            onset = _sit_onsets(r)[:, None]
            seated[method].append(np.where(frame >= 0, (onset >= 0) & (frame >= onset), np.nan))
            joint_dists[method].append(closest_hand_distances(
                r.joints[:, :, list(HAND_JOINTS)], sets))
            joints[method] += list(r.joints)
            onsets[method].append(onset[:, 0])
            extra[method]["skate"] += [foot_sliding(j, r.fps) for j in r.joints]
            extra[method]["pen"].append(d)
            extra[method]["over"].append(o)
            extra[method]["sat"] += list(r.contacts[:, -1, CONTACT_NAMES.index("pelvis")] > 0.5)
            if contact_samples:
                run = syn.run_dir
                sampled[method].append(sample_contacts(run, scene, contact_samples, seed=seed))
    rows: dict[str, dict[str, float]] = {}
    raw: dict[str, np.ndarray] = {}
    for method, syn in synthesizers.items():
        d = np.concatenate(dists[method])
        raw[method] = d
        ap = contact_precision(d, AP_THRESHOLDS)
        a_apd, s_apd = segment_apd(joints[method], list(np.concatenate(onsets[method])),
                                   syn.cfg.fps)
        row = {"ACE cm": 100 * ace(d)}
        row.update({f"AP@{round(k * 100)} %": 100 * v for k, v in ap.items()})
        row["joint ACE cm"] = 100 * ace(np.concatenate(joint_dists[method]))
        row.update({"sat %": 100 * float(np.mean(extra[method]["sat"])),
                    "APD approach": a_apd, "APD sit": s_apd,
                    "skate mm/frame": 1000 * float(np.mean(extra[method]["skate"])),
                    "pen. depth cm": 100 * float(np.mean(extra[method]["pen"])),
                    "pen. >4 cm %": float(np.mean(extra[method]["over"]))})
        if contact_samples:
            samples = np.stack(sampled[method])  # (L, N, 2, 3)
            row["contact APD cm"] = 100 * contact_apd(samples)
            row["contact APD pooled cm"] = 100 * contact_apd(samples.reshape(1, -1, 2, 3))
        rows[method] = row
    misses = {m: {"offset": np.concatenate(offsets[m]), "seated": np.concatenate(seated[m])}
              for m in synthesizers}
    return rows, raw, np.concatenate(labels), misses


def _by_label(labels: np.ndarray, methods: Iterable[str],
              cells: Callable[[str, np.ndarray], dict[str, float]]
              ) -> dict[str, dict[str, float]]:
    """One row per kind of asked contact (``labels`` (N, 2), sorted, ``""`` skipped): ``{"n":
    count}`` then each method's ``cells(method, sel)`` for the hands of that kind (``sel``
    (N, 2) bool)."""
    labels = np.asarray(labels).astype(str)
    out: dict[str, dict[str, float]] = {}
    for label in sorted(set(labels.ravel()) - {""}):
        sel = labels == label
        row: dict[str, float] = {"n": float(sel.sum())}
        for method in methods:
            row.update(cells(method, sel))
        out[label] = row
    return out


def contact_breakdown(distances: Mapping[str, np.ndarray], labels: np.ndarray,
                      threshold: float = 0.05) -> dict[str, dict[str, float]]:
    """ACE (cm) and AP@``threshold`` (%) per kind of asked contact: where a method misses.

    ``distances``: method → (N, 2) closest hand distances (m, NaN: none asked), ``labels``
    (N, 2) what each contact was (:func:`evaluate`'s third output). Returns ``{label: {"n":
    count, "<method> ACE cm": ..., "<method> AP@5 %": ...}}``, labels sorted."""
    k = round(threshold * 100)

    def cells(method: str, sel: np.ndarray) -> dict[str, float]:
        d = np.asarray(distances[method], np.float64)[sel]
        return {f"{method} ACE cm": 100 * ace(d),
                f"{method} AP@{k} %": 100 * contact_precision(d, [threshold])[threshold]}

    return _by_label(labels, distances, cells)


def miss_breakdown(misses: Mapping[str, Mapping[str, np.ndarray]], labels: np.ndarray
                   ) -> dict[str, dict[str, float]]:
    """Where the hands stop, per kind of asked contact: medians over the asked hands of the
    closest hand surface point's height above its contact (cm, chair up; negative: below the
    surface point) and its distance from it in the chair's horizontal plane (cm), and the
    share of closest approaches made with the pelvis already seated (%).

    ``misses``: :func:`evaluate`'s fourth output; ``labels`` its third. Returns ``{label: {"n":
    count, "<method> up cm": ..., "<method> across cm": ..., "<method> seated %": ...}}``,
    labels sorted. A palm ~1 cm above a seat's contact reads "up 1"; one that lands short of
    an armrest's contact on its top reads as "across".
    """
    def cells(method: str, sel: np.ndarray) -> dict[str, float]:
        names = [f"{method} up cm", f"{method} across cm", f"{method} seated %"]
        off = np.asarray(misses[method]["offset"], np.float64)[sel]  # (n, 3)
        found = np.isfinite(off).all(-1)
        if not found.any():
            return dict.fromkeys(names, np.nan)
        off, sat = off[found], np.asarray(misses[method]["seated"], np.float64)[sel][found]
        values = (np.median(off[:, 1]), np.median(np.hypot(off[:, 0], off[:, 2])), np.mean(sat))
        return {name: 100 * float(v) for name, v in zip(names, values, strict=True)}

    return _by_label(labels, misses, cells)


def ground_truth_row(sessions: Sequence[ProcessedSession], fps: float = 30.0
                     ) -> dict[str, float]:
    """The APDs of recorded/simulated sequences (resampled to ``fps``), with the same segment
    definitions (sit onset = first pelvis contact), their mean foot sliding (mm/frame at
    ``fps``, as the methods' rows) and the contact APD of their hand contacts (chair frame):
    per chair over the sequences that share one (the same name and mesh), NaN when no chair
    has two; and pooled over all sequences as one group."""
    from couch.synthesis.features import canonical_chair, hand_targets, resample

    joints, onsets, contacts, chairs = [], [], [], []
    for s in sessions:
        s = canonical_chair(s)
        chairs.append(chair_id(s.object_name, s.object_vertices))
        if abs(s.fps - fps) > 1e-6:
            s = resample(s, fps)
        j = np.asarray(s.joints, np.float64)
        sat = np.asarray(s.contact_active)[:, CONTACT_NAMES.index("pelvis")]
        joints.append(j)
        onsets.append(int(sat.argmax()) if sat.any() else -1)
        per_hand = []
        for name in ("left_hand", "right_hand"):
            i = CONTACT_NAMES.index(name)
            tgt, mask = hand_targets(np.asarray(s.contact_active)[:, i],
                                     np.asarray(s.contact_points)[:, i].astype(np.float64))
            per_hand.append(tgt[np.flatnonzero(mask)[0]] if mask.any() else np.full(3, np.nan))
        chair_from_world = invert_transform(np.asarray(s.object_pose, np.float64))
        contacts.append(apply_transform(chair_from_world, np.stack(per_hand)))
    a_apd, s_apd = segment_apd(joints, onsets, fps)
    # The data's own foot sliding: the floor under the methods' skate figures.
    skate = 1000 * float(np.mean([foot_sliding(j, fps) for j in joints]))
    sets = np.stack(contacts)  # (S, 2, 3)
    groups = [sets[[i for i, c in enumerate(chairs) if c == key]] for key in sorted(set(chairs))]
    # as contact_apd: the mean over chairs with two or more complete (both-hand) sets
    per_chair = [v for v in (contact_apd(g[None]) for g in groups if len(g) >= 2)
                 if np.isfinite(v)]
    return {"APD approach": a_apd, "APD sit": s_apd, "skate mm/frame": skate,
            "contact APD cm": 100 * float(np.mean(per_chair)) if per_chair else float("nan"),
            "contact APD pooled cm": 100 * contact_apd(sets[None])}

