"""Procedural human-chair motion on the bundled body model: walk up, turn, sit, act, leave.

The generator works in the chair's frame (chair at the origin, seat facing +Z, floor y = 0) and
builds every sequence from *targets*: footprints (planted feet never move), a pelvis trajectory,
torso lean, and wrist targets (palms on the chair, or on the thighs). Limbs reach their targets
with analytic two-bone IK on the shaped skeleton, so stance feet do not slide and hands land
exactly on the chair's surface. Poses are generated on a dense 120 Hz grid and resampled to any
clock (Kinect frames at 30 fps, MVN at 60 Hz) with slerp.

Interaction types and the COUCH dataset's mix (right hand 17.3%, left 14.0%, both 28.9%,
no contact 17.4%, free 15.2%, locomotion 7.2%) are in :data:`INTERACTION_MIX`; per-frame labels
are 0 (locomotion) while walking and the sequence's type from the turn at the chair onwards.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import torch
from scipy.ndimage import gaussian_filter1d, maximum_filter1d
from scipy.spatial.transform import Rotation, Slerp

from couch.body import JOINT_INDEX, BodyModel, sitting_pose
from couch.body.limits import clamp_to_limits
from couch.rotations import axis_angle_to_quat
from couch.tools.sim.ik import (
    Skeleton,
    align,
    axis_rotation,
    limb_rotations,
    local_from_global,
    normalize,
    steady_pole,
    transfer_twist,
    two_bone_ik,
    yaw_matrix,
)
from couch.tools.sim.quality import penetration_depth

# Schema labels (DESIGN.md /labels/interaction) and the COUCH dataset's proportions.
INTERACTION_LABEL = {"locomotion": 0, "right_hand": 1, "left_hand": 2, "both_hands": 3,
                     "no_contact": 4, "free": 5}
INTERACTION_MIX = {"right_hand": 0.173, "left_hand": 0.140, "both_hands": 0.289,
                   "no_contact": 0.174, "free": 0.152, "locomotion": 0.072}

DENSE_HZ = 120.0
# m/s: the fastest an elbow swings about its shoulder-wrist line (see ik.steady_pole)
ELBOW_SWING = 2.5
# How far the palm centre is first held above a contact point: fingers and thumb reach a little
# below the palm's plane. Only a first guess: how far the hand really is from the chair depends on
# the surface's curvature and the hand's tilt (a hold's median measured -1.4 to 3.6 cm), so each
# held palm is then moved along the contact normal until its closest vertex rests ``TOUCH_GAP``
# above the surface (:func:`_palm_gaps`).
PALM_HOVER = 0.016
# Where a resting palm's closest contact vertex ends up: on the surface, not pressed into it (the
# body model is rigid) and not hovering near the ground truth's 2 cm contact line.
TOUCH_GAP = 0.003
J = JOINT_INDEX


@dataclasses.dataclass
class SeatGeometry:
    """What the generator needs to know of a chair, in the chair frame (metres, +Z = facing).

    hand_targets: part name (``left_armrest``, ``right_seat``, ``left_back``, …) → candidate palm
    placements [(point (3,), outward surface normal (3,)), …]; "left" is the sitter's left (+X).
    """

    seat_height: float
    seat_center: np.ndarray
    seat_front_z: float
    back_front_z: float | None
    half_width: float
    hand_targets: dict[str, list[tuple[np.ndarray, np.ndarray]]]


@dataclasses.dataclass
class MotionConfig:
    """Knobs of the generator; ranges are sampled uniformly per sequence."""

    walk_speed: tuple[float, float] = (1.0, 1.3)  # m/s
    step_length: tuple[float, float] = (0.5, 0.62)  # m between consecutive footprints
    start_distance: tuple[float, float] = (2.0, 4.0)  # m from the chair
    sit_duration: tuple[float, float] = (1.3, 1.8)  # s from standing to seated
    seated_duration: tuple[float, float] = (2.0, 4.0)  # s when no total duration is asked
    stand_and_leave: float = 0.5  # probability of standing up and walking away
    beta_std: float = 1.0
    max_penetration: float = 0.018  # m; deeper sequences are rejected (MotionRejected)
    # m; a held palm whose closest vertex is further above the chair than this over its hold
    # (median) is rejected (MotionRejected): half the ground truth's 2 cm contact distance
    max_palm_gap: float = 0.01
    sitter_half_room: float = 0.3  # m from the pelvis to a seat's side edge, at the closest


@dataclasses.dataclass
class Motion:
    """A generated sequence on the dense grid (chair frame).

    time: (T,) s; global_rot: (T,3,3) pelvis world rotation; local_rot: (T,24,3,3) SMPL local
    rotations (index 0 equals global_rot); transl: (T,3) SMPL translation (pelvis joint −
    its rest position); labels: (T,) int8 per-frame interaction labels; hand_contacts: side →
    (start s, end s, contact point (3,), chair part) of palm contacts; phases: (name, start s,
    end s).
    """

    interaction: str
    betas: np.ndarray
    time: np.ndarray
    global_rot: np.ndarray
    local_rot: np.ndarray
    transl: np.ndarray
    labels: np.ndarray
    hand_contacts: dict[str, tuple[float, float, np.ndarray, str]]
    phases: list[tuple[str, float, float]]

    @property
    def duration(self) -> float:
        return float(self.time[-1])

    def sample(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Poses at arbitrary ``times`` (s, clipped to the sequence): global_orient (N,3) and
        body_pose (N,69) axis-angle, transl (N,3), labels (N,) int8."""
        t = np.clip(np.asarray(times, dtype=np.float64), self.time[0], self.time[-1])
        n, nj = len(t), self.local_rot.shape[1]
        rots = Rotation.from_matrix(self.local_rot.transpose(1, 0, 2, 3).reshape(-1, 3, 3))
        out = np.empty((nj, n, 3))
        for j in range(nj):
            out[j] = Slerp(self.time, rots[j * len(self.time):(j + 1) * len(self.time)])(
                t).as_rotvec()
        transl = np.stack([np.interp(t, self.time, self.transl[:, k]) for k in range(3)], -1)
        idx = np.clip(np.searchsorted(self.time, t), 0, len(self.time) - 1)
        return (out[0].astype(np.float32), out[1:].transpose(1, 0, 2).reshape(n, -1).astype(
            np.float32), transl.astype(np.float32), self.labels[idx])


# ----------------------------------------------------------------------------- timelines


def smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3 - 2 * u)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


@dataclasses.dataclass
class Footprint:
    pos: np.ndarray  # (3,) ankle target on the floor plane (y = ankle height)
    heading: float  # radians about +Y, 0 = +Z


@dataclasses.dataclass
class Step:
    foot: int  # 0 left, 1 right
    start: float
    end: float
    to: Footprint


class Timeline:
    """Per-foot planted/swing trajectories from a list of steps, evaluated on a time grid."""

    def __init__(self, start_feet: tuple[Footprint, Footprint]) -> None:
        self.start = start_feet
        self.steps: list[Step] = []

    def add(self, step: Step) -> None:
        """Append a step; its heading is unwrapped to within π of the foot's previous heading,
        so headings stay continuous and feet turn the short way."""
        prev = self.last(step.foot).heading
        step.to.heading = prev + float(wrap_angle(step.to.heading - prev))
        self.steps.append(step)

    def last(self, foot: int) -> Footprint:
        for s in reversed(self.steps):
            if s.foot == foot:
                return s.to
        return self.start[foot]

    def feet(self, t: np.ndarray, clearance: float) -> tuple[np.ndarray, np.ndarray]:
        """Ankle positions (2,T,3) and foot headings (2,T) at times ``t``."""
        pos = np.empty((2, len(t), 3))
        head = np.empty((2, len(t)))
        for foot in (0, 1):
            pos[foot] = self.start[foot].pos
            head[foot] = self.start[foot].heading
            prev = self.start[foot]
            for s in (s for s in self.steps if s.foot == foot):
                u = smoothstep((t - s.start) / (s.end - s.start))
                moving = t >= s.start
                dh = s.to.heading - prev.heading
                pos[foot] = np.where(moving[:, None], prev.pos + u[:, None] * (s.to.pos - prev.pos)
                                     , pos[foot])
                head[foot] = np.where(moving, prev.heading + u * dh, head[foot])
                lift = clearance * np.sin(np.pi * np.clip((t - s.start) / (s.end - s.start), 0, 1))
                pos[foot, :, 1] += np.where(moving & (t <= s.end), lift, 0.0)
                prev = s.to
        return pos, head


def hermite_path(p0: np.ndarray, h0: float, p1: np.ndarray, h1: float,
                 via: list[np.ndarray] | None = None, n: int = 400) -> np.ndarray:
    """Smooth planar path (n,2) in (x,z) through ``via`` points, leaving p0 along heading h0 and
    arriving at p1 along heading h1 (Catmull-Rom segments with end tangents)."""
    pts = [np.asarray(p0, float)] + [np.asarray(v, float) for v in (via or [])] + [
        np.asarray(p1, float)]
    tangents = []
    for i in range(len(pts)):
        if i == 0:
            d = np.array([np.sin(h0), np.cos(h0)])
        elif i == len(pts) - 1:
            d = np.array([np.sin(h1), np.cos(h1)])
        else:
            d = normalize(pts[i + 1] - pts[i - 1])
        seg = np.linalg.norm(pts[min(i + 1, len(pts) - 1)] - pts[max(i - 1, 0)])
        tangents.append(d * max(seg, 0.3) * 0.5)
    out = []
    per = max(2, n // (len(pts) - 1))
    for i in range(len(pts) - 1):
        s = np.linspace(0, 1, per, endpoint=i == len(pts) - 2)[:, None]
        h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
        h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
        out.append(h00 * pts[i] + h10 * tangents[i] + h01 * pts[i + 1] + h11 * tangents[i + 1])
    return np.concatenate(out)


def walk_steps(tl: Timeline, path: np.ndarray, t0: float, step_len: float, speed: float,
               half_width: float, ankle_h: float, final_heading: float | None = None) -> float:
    """Append alternating steps along ``path`` (n,2 in x,z) starting at time t0; returns the
    end time. The last step brings the trailing foot alongside the leading one."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    length = s[-1]
    n = max(1, int(np.ceil(length / step_len)))
    step_len = length / n
    step_time = step_len / speed
    swing = 0.8 * step_time  # a foot swings for 80% of one step period

    def footprint(at: float, foot: int, heading_override: float | None = None) -> Footprint:
        i = np.searchsorted(s, at).clip(1, len(s) - 1)
        d = path[i] - path[i - 1]
        heading = float(np.arctan2(d[0], d[1])) if heading_override is None else heading_override
        p = np.interp(at, s, path[:, 0]), np.interp(at, s, path[:, 1])
        lateral = np.array([np.cos(heading), -np.sin(heading)])  # the body's left, in (x, z)
        side = 1.0 if foot == 0 else -1.0
        x, z = np.array(p) + side * half_width * lateral
        return Footprint(np.array([x, ankle_h, z]), heading)

    # Lead with the foot that is further behind along the path.
    lead = 1
    t = t0
    for k in range(1, n + 1):
        foot = lead if k % 2 == 1 else 1 - lead
        last = k == n
        tl.add(Step(foot, t, t + swing, footprint(min(k * step_len, length), foot,
                                                  final_heading if last else None)))
        t += step_time
    trailing = 1 - tl.steps[-1].foot
    tl.add(Step(trailing, t, t + swing, footprint(length, trailing, final_heading)))
    return t + swing


def turn_steps(tl: Timeline, t0: float, final: tuple[Footprint, Footprint], direction: float,
               step_time: float) -> float:
    """Turn on the spot onto the ``final`` footprints in three steps; ``direction`` ±1 picks the
    way round (+1 turns left, counter-clockwise seen from above). Returns the end time."""
    left, right = tl.last(0), tl.last(1)
    start_heading = 0.5 * (left.heading + right.heading)
    total = float(wrap_angle(final[0].heading - start_heading))
    if abs(total) > 0.3 and np.sign(total) != direction:
        total += direction * 2 * np.pi
    end_heading = start_heading + total
    centre_start = 0.5 * (left.pos + right.pos)
    centre_end = 0.5 * (final[0].pos + final[1].pos)
    half = 0.5 * np.linalg.norm(final[0].pos - final[1].pos)
    t = t0
    # The foot on the side we turn towards steps first.
    first = 0 if direction > 0 else 1
    for k, frac in enumerate((0.5, 1.0, 1.0)):
        foot = first if k % 2 == 0 else 1 - first
        if frac < 1.0:
            h = start_heading + frac * total
            centre = centre_start + frac * (centre_end - centre_start)
            side = 1.0 if foot == 0 else -1.0
            lateral = np.array([np.cos(h), 0.0, -np.sin(h)])
            target = Footprint(centre + side * half * lateral, float(h))
        else:
            target = Footprint(final[foot].pos.copy(), end_heading)
        # explicit continuous headings: no unwrapping, the turn goes the way asked
        tl.steps.append(Step(foot, t, t + 0.8 * step_time, target))
        t += step_time
    return t - 0.2 * step_time


# ----------------------------------------------------------------------------- the generator


class _Body:
    """Rest measurements of one shaped body needed to place targets."""

    def __init__(self, model: BodyModel, betas: np.ndarray) -> None:
        with torch.no_grad():
            out = model(betas=torch.as_tensor(betas[None], dtype=model.dtype))
        v = out.vertices[0].double().numpy()
        self.rest = out.joints[0].double().numpy()
        self.sk = Skeleton(self.rest)
        sole = np.concatenate([model.contact_vertices["left_foot"],
                               model.contact_vertices["right_foot"]])
        self.ankle_h = float(self.rest[J["left_ankle"], 1] - v[sole, 1].min())
        self.leg = self.sk.bone_length(J["left_hip"], J["left_knee"]), self.sk.bone_length(
            J["left_knee"], J["left_ankle"])
        self.arm = self.sk.bone_length(J["left_shoulder"], J["left_elbow"]), self.sk.bone_length(
            J["left_elbow"], J["left_wrist"])
        self.hip_below_pelvis = float(self.rest[0, 1] - self.rest[J["left_hip"], 1])
        self.hip_half_width = float(abs(self.rest[J["left_hip"], 0]))
        # Seated (thighs level), how far the pelvis joint is above what rests on the seat: the
        # lowest point of the buttocks and the back of the thighs near the hips.
        with torch.no_grad():
            seated = model(betas=torch.as_tensor(betas[None], dtype=model.dtype),
                           body_pose=torch.as_tensor(sitting_pose()[None], dtype=model.dtype))
        sv = seated.vertices[0].double().numpy()
        sj = seated.joints[0].double().numpy()
        near_hips = sv[:, 2] < sj[J["left_hip"], 2] + 0.15
        self.seat_drop = float(sj[0, 1] - sv[near_hips, 1].min())
        self.buttock_back = float(self.rest[0, 2] - v[:, 2].min())
        self.thigh_radius = 0.075
        # Palm centre relative to the wrist in the rest (T-pose: palms down) frame, per side.
        self.palm_offset = {}
        for side in ("left", "right"):
            hand = v[model.contact_vertices[f"{side}_hand"]]
            w, k = self.rest[J[f"{side}_wrist"]], self.rest[J[f"{side}_hand"]]
            along = (hand[:, 0] - w[0]) / (k[0] - w[0])
            palm = hand[(along > 0.2) & (along < 0.9)]
            palm = palm[palm[:, 1] < np.percentile(palm[:, 1], 25)]
            self.palm_offset[side] = palm.mean(0) - w


def _hand_candidates(seat: SeatGeometry, side: str) -> list[tuple[str, np.ndarray, np.ndarray]]:
    options = [(p, np.asarray(point, float), normalize(np.asarray(normal, float)))
               for p in (f"{side}_armrest", f"{side}_seat", f"{side}_back")
               for point, normal in seat.hand_targets.get(p, [])]
    if not options:
        raise ValueError(f"chair offers no {side}-hand contact target")
    return options


def sample_interaction(rng: np.random.Generator) -> str:
    """An interaction type drawn with the COUCH dataset's proportions."""
    names = list(INTERACTION_MIX)
    p = np.array([INTERACTION_MIX[n] for n in names])
    return names[rng.choice(len(names), p=p / p.sum())]


def generate_motion(model: BodyModel, seat: SeatGeometry, rng: np.random.Generator, *,
                    interaction: str | None = None, duration: float | None = None,
                    betas: np.ndarray | None = None, config: MotionConfig | None = None,
                    chair_mesh: tuple[np.ndarray, np.ndarray] | None = None,
                    collision_model: BodyModel | None = None) -> Motion:
    """One human-chair sequence in the chair frame.

    Raises ValueError (no reachable hand target) or :class:`MotionRejected` (the settled body
    still penetrates the chair, or a held palm stays above its target) when this draw cannot
    be done; callers draw again.

    Args:
        model: the body model whose skeleton the poses are solved for (feet and hands reach
            their targets exactly with its bone lengths).
        seat: the chair's geometry and hand targets.
        interaction: one of :data:`INTERACTION_LABEL` (random with the COUCH mix when None).
        duration: total seconds wanted (the seated phase absorbs the slack; the start distance
            shrinks towards 1.2 m when time is short). None: natural length.
        betas: (10,) subject shape (random N(0, config.beta_std) when None).
        chair_mesh: the chair's watertight (vertices, faces) in the chair frame; when given, the
            body is settled out of any penetration after the targets are solved.
        collision_model: the (coarse, faster) body model used for that check; default ``model``.
    """
    cfg = config or MotionConfig()
    interaction = interaction or sample_interaction(rng)
    if interaction not in INTERACTION_LABEL:
        raise ValueError(f"unknown interaction {interaction!r}; one of {list(INTERACTION_LABEL)}")
    betas = np.clip(rng.normal(0, cfg.beta_std, 10), -2.5, 2.5) if betas is None else np.asarray(
        betas, float)
    body = _Body(model, betas)
    speed = rng.uniform(*cfg.walk_speed)
    step_len = rng.uniform(*cfg.step_length)
    leg = sum(body.leg)
    stand_h = body.ankle_h + 0.985 * leg + body.hip_below_pelvis
    walk_h = body.ankle_h + np.sqrt((0.985 * leg) ** 2 - (step_len / 2) ** 2) + (
        body.hip_below_pelvis)

    # Seated configuration: pelvis over the seat, feet planted in front of it.
    seat_c = np.asarray(seat.seat_center, float).copy()
    # One hand to put on a seat wider than one sitter (a sofa): the sitter sits anywhere along
    # it, half the time at an end, beside an armrest (which is then within reach), as people
    # sit on sofas. Other interactions and chairs are sat on in the middle and draw nothing
    # here, so their sequences are what they were.
    seat_x = [abs(p[0]) for k in ("left_seat", "right_seat") for p, _ in seat.hand_targets.get(
        k, [])]
    room = (max(seat_x) if seat_x else 0.0) - cfg.sitter_half_room
    if room > 0.1 and interaction in ("left_hand", "right_hand"):
        seat_c[0] += rng.choice([-1.0, 1.0]) * room * (1.0 if rng.random() < 0.5 else rng.random())
    if seat.back_front_z is not None:
        pelvis_z = seat.back_front_z + body.buttock_back + rng.uniform(0.02, 0.06)
    else:
        pelvis_z = seat_c[2] - 0.05
    # Sit forward enough for the knees to clear the seat's front edge: with the shin upright
    # the knee is at ankle height + shin length, so the thigh slopes and reaches less far.
    hip_y = seat.seat_height + body.seat_drop - body.hip_below_pelvis
    rise = body.ankle_h + body.leg[1] - hip_y
    reach_z = np.sqrt(max(body.leg[0] ** 2 - rise**2, 0.2**2))
    pelvis_z = max(pelvis_z, seat.seat_front_z + 0.09 - reach_z)
    pelvis_z = min(pelvis_z, seat.seat_front_z - 0.12)
    seated_pelvis = np.array([seat_c[0], seat.seat_height + body.seat_drop, pelvis_z])
    knee_z = seated_pelvis[2] + reach_z
    # Feet under or a little before the knees, and far enough from the seat's front edge that the
    # calves clear it while turning and standing (a calf reaches ~10 cm behind the ankle).
    feet_z = max(knee_z + rng.uniform(0.02, 0.1), seat.seat_front_z + 0.15)
    feet_apart = body.hip_half_width + rng.uniform(0.0, 0.06)
    sit_feet = (Footprint(np.array([seat_c[0] + feet_apart, body.ankle_h, feet_z]), 0.0),
                Footprint(np.array([seat_c[0] - feet_apart, body.ankle_h, feet_z]), 0.0))
    pre_sit = np.array([seat_c[0], stand_h, feet_z - 0.02])

    # Approach: start 2-4 m away (closer when time is short), walk to face the chair.
    walk_time_budget = None if duration is None else max(0.0, duration - 6.0)
    dist = rng.uniform(*cfg.start_distance)
    if walk_time_budget is not None:
        dist = float(np.clip(min(dist, 1.0 + walk_time_budget * speed * 0.8), 1.2, None))
    sit = interaction != "locomotion"
    approach = np.array([seat_c[0], feet_z + 0.08])
    angle = rng.uniform(-np.pi * 0.85, np.pi * 0.85)  # around the chair, mostly not behind
    start_xz = approach + dist * np.array([np.sin(angle), np.cos(angle)])
    start_heading = float(np.arctan2(*(approach - start_xz)) + rng.normal(0, 0.6))
    via = []
    if start_xz[1] < seat.seat_front_z + 0.3:  # beside or behind the chair: go round it
        side = np.sign(start_xz[0]) or 1.0
        via.append(np.array([side * (seat.half_width + 0.75), seat.seat_front_z + 0.9]))
    if not sit:  # walk past the chair instead of stopping at it
        end = approach + np.array([rng.choice([-1, 1]) * rng.uniform(1.5, 2.5),
                                   rng.uniform(0.5, 1.5)])
        via.append(approach + np.array([0.0, 0.4]))
        path = hermite_path(start_xz, start_heading, end, float(np.arctan2(*(end - via[-1]))),
                            via)
    else:
        via.append(approach + np.array([0.0, 0.6]))
        path = hermite_path(start_xz, start_heading, approach, np.pi, via)

    h0 = start_heading
    lateral0 = np.array([np.cos(h0), 0.0, -np.sin(h0)])
    start_centre = np.array([start_xz[0], body.ankle_h, start_xz[1]])
    tl = Timeline((Footprint(start_centre + feet_apart * lateral0, h0),
                   Footprint(start_centre - feet_apart * lateral0, h0)))
    t = 0.4
    phases = []
    t_walk_end = walk_steps(tl, path, t, step_len, speed, feet_apart, body.ankle_h,
                            final_heading=np.pi if sit else None)
    phases.append(("walk", 0.0, t_walk_end))
    t = t_walk_end
    hand_plan: dict[str, list[tuple[str, np.ndarray, np.ndarray]]] = {}
    if sit:
        t_turn_end = turn_steps(tl, t + 0.1, sit_feet, float(rng.choice([-1.0, 1.0])),
                                step_time=rng.uniform(0.45, 0.6))
        phases.append(("turn", t, t_turn_end))
        t_sit0 = t_turn_end + rng.uniform(0.0, 0.2)
        t_sit1 = t_sit0 + rng.uniform(*cfg.sit_duration)
        phases.append(("sit", t_sit0, t_sit1))
        sides = {"right_hand": ["right"], "left_hand": ["left"],
                 "both_hands": ["left", "right"]}.get(interaction, [])
        for side in sides:
            hand_plan[side] = _hand_candidates(seat, side)
        natural = rng.uniform(*cfg.seated_duration)
        leave = rng.random() < cfg.stand_and_leave
        if duration is not None:
            natural = max(1.0, duration - t_sit1 - (4.0 if leave else 0.0))
            if duration - t_sit1 - natural < 3.0:
                leave = False
                natural = max(1.0, duration - t_sit1)
        t_seated_end = t_sit1 + natural
        phases.append(("seated", t_sit1, t_seated_end))
        end = t_seated_end
        if leave:
            t_stand1 = t_seated_end + rng.uniform(1.2, 1.6)
            phases.append(("stand", t_seated_end, t_stand1))
            exit_angle = rng.uniform(-1.2, 1.2)
            exit_xz = pre_sit[[0, 2]] + rng.uniform(1.5, 2.5) * np.array(
                [np.sin(exit_angle), np.cos(exit_angle)])
            leave_path = hermite_path(pre_sit[[0, 2]], 0.0, exit_xz, exit_angle)
            t_leave_end = walk_steps(tl, leave_path, t_stand1 + 0.1, step_len, speed, feet_apart,
                                     body.ankle_h)
            phases.append(("leave", t_stand1, t_leave_end))
            end = t_leave_end + 0.3
    else:
        end = t_walk_end + 0.4
    if duration is not None:
        end = max(end, duration)

    time = np.arange(0.0, end + 1e-9, 1.0 / DENSE_HZ)
    args = (model, body, betas, interaction, seat, tl, time, phases, hand_plan, pre_sit,
            seated_pelvis, walk_h, stand_h, speed, step_len, int(rng.integers(2**31)))
    offset = np.zeros((len(time), 3))
    motion = _solve(*args, offset)
    # Re-solves keep the palm targets and their timing; only the body settles.
    fixed = {side: (part, point, None, t_on, t_off, PALM_HOVER) for side, (t_on, t_off, point,
             part) in motion.hand_contacts.items()}
    for side, (part, point, _, t_on, t_off, hover) in fixed.items():
        normal = next(nrm for p, pt, nrm in hand_plan[side] if p == part and np.allclose(
            pt, point))
        fixed[side] = (part, point, normal, t_on, t_off, hover)
    if chair_mesh is not None and sit:
        # Settle the body out of the chair: push the pelvis along the surface normal at the
        # deepest penetration, re-solve the limbs, repeat.
        for _ in range(4):
            push = _penetration_push(collision_model or model, motion, chair_mesh, seat, phases)
            if not push.any():
                break
            offset = np.clip(offset + push, -0.1, 0.1)
            motion = _solve(*args, offset, fixed or None)
        # Pushes for what lifting cannot mend (arms in armrests, held palms) make the descent
        # bounce; hold the pelvis at the height it is lifted to later instead.
        lifted = _descend_once(motion, offset, phases)
        if lifted is not offset:
            offset = lifted
            motion = _solve(*args, offset, fixed or None)
        # Rest each held palm on the chair: the hover that puts its closest vertex TOUCH_GAP
        # above the surface. Further passes absorb what the re-solved arm, wrist and shared
        # torso bend change (two hands move each other); the closest pass is kept.
        settled, planned = motion, fixed
        best, best_fixed, best_miss, best_gaps = motion, fixed, np.inf, {}
        for k in range(7 if fixed else 0):
            gaps = _palm_gaps(collision_model or model, motion, chair_mesh)
            miss = max(abs(g - TOUCH_GAP) for g in gaps.values())
            if miss < best_miss:
                best, best_fixed, best_miss, best_gaps = motion, fixed, miss, gaps
            if miss < 0.001 or k == 6:
                break
            fixed = {side: (*f[:5], float(np.clip(f[5] - (gaps[side] - TOUCH_GAP), -0.02, 0.05)))
                     for side, f in fixed.items()}
            motion = _solve(*args, offset, fixed)
        motion = best
        depth = max_penetration(collision_model or model, motion, chair_mesh)
        if depth > cfg.max_penetration and motion is not settled:
            # Resting the palms put a hand (or a palm rolling with the forearm) into the chair.
            # If the palms where the plan put them stay out, rest them part of the way (still
            # touching where the plan asked), else keep them where the plan put them; if even
            # those go in, the body does and the draw is rejected.
            depth = max_penetration(collision_model or model, settled, chair_mesh)
            motion = settled
            for share in (0.75, 0.5, 0.25) if depth <= cfg.max_penetration else ():
                part = _solve(*args, offset, {side: (*f[:5], planned[side][5] + share * (
                    f[5] - planned[side][5])) for side, f in best_fixed.items()})
                part_depth = max_penetration(collision_model or model, part, chair_mesh)
                if part_depth <= cfg.max_penetration:
                    motion = part
                    break
        if depth > cfg.max_penetration:
            raise MotionRejected(f"the body passes {100 * depth:.1f} cm into the chair "
                                 f"(limit {100 * cfg.max_penetration:.1f} cm)")
        # A palm the arm cannot bring down to its target (the pelvis held up over the descent
        # leaves the shoulder too high) touches for less of its hold than the plan says, or not
        # at all: the sequence's label would claim a support its motion does not show.
        gaps = best_gaps if motion is best else _palm_gaps(collision_model or model, motion,
                                                           chair_mesh)
        for side, gap in gaps.items():
            if gap > cfg.max_palm_gap:
                raise MotionRejected(f"the {side} palm stays {100 * gap:.1f} cm above its "
                                     f"target over its hold (limit "
                                     f"{100 * cfg.max_palm_gap:.1f} cm)")
    return motion


class MotionRejected(ValueError):
    """A generated sequence failed a plausibility check (the caller may draw another)."""


def max_penetration(model: BodyModel, motion: Motion, chair_mesh: tuple[np.ndarray, np.ndarray],
                    hz: float = 30.0) -> float:
    """Deepest penetration (m) of the body into the chair over the sequence, sampled at ``hz``."""
    ts = np.arange(0.0, motion.duration, 1.0 / hz)
    go, bp, tr, _ = motion.sample(ts)
    with torch.no_grad():
        v = model(betas=motion.betas[None], global_orient=go, body_pose=bp,
                  transl=tr).vertices.numpy()
    return float(penetration_depth(v, *chair_mesh).max())


def _palm_gaps(model: BodyModel, motion: Motion, chair_mesh: tuple[np.ndarray, np.ndarray],
               hz: float = 30.0) -> dict[str, float]:
    """Per held palm (side → m): the median over its hold (``t_on`` to ``t_off``, sampled at
    ``hz``) of its contact vertices' smallest signed distance to the watertight chair (negative
    inside), i.e. how far the hand's closest point is above the surface."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(chair_mesh[0].astype(np.float32)),
                        o3d.core.Tensor(chair_mesh[1].astype(np.uint32)))
    out = {}
    for side, (t_on, t_off, _point, _part) in motion.hand_contacts.items():
        ts = np.arange(t_on, max(t_off, t_on + 1e-6), 1.0 / hz)
        go, bp, tr, _ = motion.sample(ts)
        with torch.no_grad():
            v = model(betas=motion.betas[None], global_orient=go, body_pose=bp,
                      transl=tr).vertices[:, model.contact_vertices[f"{side}_hand"]].numpy()
        # a majority vote of 5 rays, as penetration_depth: one ray grazing an edge miscounts
        sd = scene.compute_signed_distance(o3d.core.Tensor(v.reshape(-1, 3).astype(np.float32)),
                                           nsamples=5).numpy().reshape(v.shape[:2])
        out[side] = float(np.median(sd.min(axis=1)))
    return out


def _penetration_push(model: BodyModel, motion: Motion, chair_mesh: tuple[np.ndarray, np.ndarray],
                      seat: SeatGeometry, phases: list[tuple[str, float, float]],
                      tol: float = 0.004) -> np.ndarray:
    """(T,3) pelvis displacement that lifts the body out of the seat and forward off the
    backrest (sampled at 15 Hz over the turn/sit/seated/stand phases).

    Each penetrating vertex is pushed out along a ray, up for the seat region and forward for
    the backrest; the ray's exit distance is how far it must move (the nearest-surface normal
    of a thin seat can point down, through the bottom).
    """
    spans = [(a, b) for name, a, b in phases if name in ("turn", "sit", "seated", "stand")]
    t0, t1 = min(a for a, _ in spans), max(b for _, b in spans)
    ts = np.arange(t0, t1, 1 / 15.0)
    go, bp, tr, _ = motion.sample(ts)
    with torch.no_grad():
        v = model(betas=motion.betas[None], global_orient=go, body_pose=bp,
                  transl=tr).vertices.double().numpy()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(chair_mesh[0].astype(np.float32)),
                        o3d.core.Tensor(chair_mesh[1].astype(np.uint32)))
    flat = v.reshape(-1, 3).astype(np.float32)
    inside = scene.compute_occupancy(o3d.core.Tensor(flat), nsamples=5).numpy().astype(bool)
    push_s = np.zeros((len(ts), 3))
    pts = flat[inside]
    frame = np.repeat(np.arange(len(ts)), v.shape[1])[inside]
    # Into the seat from above: lift. Into the backrest, or the seat's front face from in front
    # (calves, knees): forward.
    upward = (pts[:, 1] > seat.seat_height - 0.08) & (pts[:, 1] < seat.seat_height + 0.12) & (
        pts[:, 2] < seat.seat_front_z - 0.03)
    dirs = np.where(upward[:, None], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([pts, dirs], 1)))["t_hit"].numpy()
    exit_dist = np.where(np.isfinite(hit), hit, 0.0) + tol
    for axis, sel in ((1, upward), (2, ~upward)):
        need = np.zeros(len(ts))
        np.maximum.at(need, frame[sel], exit_dist[sel])
        push_s[:, axis] = need
    # Seated, the body rests on the seat: lower it onto the seat where it floats above.
    seated = [(a, b) for name, a, b in phases if name == "seated"]
    if seated:
        a, b = seated[0]
        on_seat = (ts >= a) & (ts <= b)
        lower = np.isin(model.weights.argmax(1).numpy(),
                        [J["pelvis"], J["left_hip"], J["right_hip"]])
        under = v[on_seat][:, lower].reshape(-1, 3).astype(np.float32)
        if len(under):
            down = np.tile(np.float32([0.0, -1.0, 0.0]), (len(under), 1))
            gap = scene.cast_rays(o3d.core.Tensor(np.concatenate([under, down], 1)))[
                "t_hit"].numpy().reshape(int(on_seat.sum()), -1)
            gap = np.where(np.isfinite(gap), gap, np.inf).min(axis=1)
            sink = np.where(np.isfinite(gap) & (gap > tol), gap - 0.002, 0.0)
            push_s[on_seat, 1] -= np.where(push_s[on_seat, 1] > 0, 0.0, sink)
    push = np.stack([np.interp(motion.time, ts, push_s[:, k], left=0, right=0)
                     for k in range(3)], -1)
    # widen, then smooth, so the correction ramps in and out instead of popping
    # keep the larger of lifting and lowering, not their average
    up = maximum_filter1d(np.maximum(push, 0), int(0.2 * DENSE_HZ), axis=0)
    dn = -maximum_filter1d(np.maximum(-push, 0), int(0.2 * DENSE_HZ), axis=0)
    push = np.where(up > 0, up, dn)
    out = gaussian_filter1d(push, 0.08 * DENSE_HZ, axis=0)
    return np.where(np.abs(out) > 1e-4, out, 0.0)


def _descend_once(motion: Motion, offset: np.ndarray, phases: list[tuple[str, float, float]],
                  min_change: float = 0.001, smooth: float = 0.05) -> np.ndarray:
    """The pelvis offset (T,3) whose pelvis, once it has started down into the seat, does not
    rise again before the seated phase ends (``offset`` itself when that changes the pelvis
    height by less than ``min_change`` m anywhere).

    The penetration push lifts the whole body where any vertex is in the chair (an arm passing
    through an armrest, a held palm the arm IK keeps at its target, a seat lower than planned),
    the seated pass lowers it where it floats, and the offset is clipped at 10 cm, so a pushed
    descent could go down, up by centimetres and down again. From the planned pelvis's highest
    point (where the descent starts) on, the height is held at the running maximum taken from
    the end (the height it will be lifted to later, so the body pauses instead of sinking and
    rising), but never above the descent's start (a lift past it would stand the body up on
    stretched legs; what a push that large left in the chair, the penetration check judges),
    then smoothed, which keeps it non-increasing (and rounds a lift's peak down by a few mm).

    Args:
        motion: the motion solved with ``offset``; its ``transl`` (T,3) m, chair frame, +Y up.
        offset: (T,3) m, the pelvis offset it was solved with.
        phases: the motion's ``(name, start s, end s)`` phases.
        min_change: m; smaller changes are not made, so a draw that does not bounce keeps
            its motion bit for bit.
        smooth: s, the smoothing's Gaussian sigma (its ramps take twice that).
    """
    sit, seated = _phase(phases, "sit"), _phase(phases, "seated")
    if sit is None or seated is None:
        return offset
    t, y = motion.time, motion.transl[:, 1]
    span = np.flatnonzero((t >= sit[0]) & (t <= seated[1]))
    top = span[0] + int(np.argmax(y[span] - offset[span, 1]))
    if y[span[-1]] >= y[top]:
        return offset  # a seat at hip height or above (a bar stool) is climbed onto
    seg = slice(top, span[-1] + 1)
    level = np.minimum(np.maximum.accumulate(y[seg][::-1])[::-1], y[top])
    if np.abs(level - y[seg]).max() < min_change:
        return offset
    held = gaussian_filter1d(level, smooth * DENSE_HZ, mode="nearest")
    # Smoothing moves the ends (down at the start, up at the end); blend them back onto the
    # pelvis outside with ramps that keep the height non-increasing.
    ramp = smoothstep(np.arange(len(held)) / (2 * smooth * DENSE_HZ))
    held += (y[top] - held[0]) * (1 - ramp)
    held -= (held[-1] - y[seg][-1]) * (1 - ramp[::-1])
    out = offset.copy()
    out[seg, 1] += held - y[seg]
    return out


def _phase(phases: list[tuple[str, float, float]], name: str) -> tuple[float, float] | None:
    for n, a, b in phases:
        if n == name:
            return a, b
    return None


def _solve(model, body: _Body, betas, interaction, seat: SeatGeometry, tl: Timeline,
           time: np.ndarray, phases, hand_plan, pre_sit, seated_pelvis, walk_h, stand_h, speed,
           step_len, seed: int, offset: np.ndarray, fixed: dict | None = None) -> Motion:
    rng = np.random.default_rng(seed)
    n = len(time)
    feet, feet_head = tl.feet(time, clearance=0.07)
    sit = _phase(phases, "sit")
    seated = _phase(phases, "seated")
    stand = _phase(phases, "stand")

    # Pelvis while on the feet: between the feet, smoothed; a bob at twice the step rate.
    mid = 0.5 * (feet[0] + feet[1])
    sigma = 0.12 * DENSE_HZ
    pelvis = gaussian_filter1d(mid, sigma, axis=0, mode="nearest")
    heading = gaussian_filter1d(feet_head.mean(0), sigma, mode="nearest")
    moving = gaussian_filter1d((np.linalg.norm(np.gradient(mid, axis=0), axis=1) * DENSE_HZ
                                > 0.05).astype(float), sigma, mode="nearest")
    step_rate = speed / step_len
    bob = 0.012 * np.cos(2 * np.pi * step_rate * time) * moving
    pelvis[:, 1] = stand_h + moving * (walk_h - stand_h) + bob
    pitch = np.deg2rad(4.0) * moving  # slight forward lean while walking
    spine = np.zeros(n)
    roll = np.zeros(n)

    # Sitting down and standing up: pelvis moves back and down while the torso leans forward.
    sit_w = np.zeros(n)
    if sit is not None:
        u_sit = smoothstep((time - sit[0]) / (sit[1] - sit[0]))
        u_up = 0.0 if stand is None else smoothstep((time - stand[0]) / (stand[1] - stand[0]))
        sit_w = u_sit * (1 - u_up)
        # The hips go down a little ahead of going back, so the knees travel forward over the
        # feet (as people sit) instead of back into the seat's front edge.
        back = smoothstep(sit_w)
        down = smoothstep(sit_w * 1.15)
        target = np.empty((n, 3))
        target[:, 0] = pre_sit[0] + back * (seated_pelvis[0] - pre_sit[0])
        target[:, 2] = pre_sit[2] + back * (seated_pelvis[2] - pre_sit[2])
        target[:, 1] = pre_sit[1] + down * (seated_pelvis[1] - pre_sit[1])
        w = smoothstep(np.clip(sit_w * 8, 0, 1)) if stand is None else np.where(
            time < 0.5 * (sit[1] + stand[0]), smoothstep(np.clip((time - sit[0]) * 4, 0, 1)),
            1 - smoothstep(np.clip((time - stand[1]) * 4 + 1, 0, 1)))
        pelvis = pelvis * (1 - w[:, None]) + target * w[:, None] + offset
        lean = np.sin(np.pi * np.clip(sit_w, 0, 1)) ** 1.5
        # Reaching for the chair while sitting down means bending further forward, and to the
        # side of a single supporting hand.
        reaching = interaction in ("right_hand", "left_hand", "both_hands")
        pitch = pitch * (1 - w) + np.deg2rad(32 if reaching else 28) * lean
        spine = spine + np.deg2rad(25 if reaching else 22) * lean
        side_sign = {"right_hand": 1.0, "left_hand": -1.0}.get(interaction, 0.0)
        roll = roll + side_sign * np.deg2rad(12) * lean
        seat_heading = float(np.interp(sit[0], time, feet_head.mean(0)))
        heading = heading * (1 - w) + w * seat_heading

    # Seated behaviour: small sway; free interaction leans back and crosses the legs.
    free_w = np.zeros(n)
    if seated is not None:
        in_seat = ((time >= seated[0]) & (time <= seated[1])).astype(float)
        in_seat = gaussian_filter1d(in_seat, 0.2 * DENSE_HZ)
        phase0 = rng.uniform(0, 2 * np.pi)
        spine += in_seat * np.deg2rad(3) * np.sin(2 * np.pi * 0.25 * time + phase0)
        if interaction == "free":
            a = seated[0] + 0.3 * (seated[1] - seated[0])
            b = seated[1] - 0.15 * (seated[1] - seated[0])
            free_w = smoothstep((time - a) / 0.8) * (1 - smoothstep((time - b) / 0.8))
            pitch -= np.deg2rad(rng.uniform(8, 14)) * free_w
            pelvis[:, 2] += 0.03 * free_w

    go = yaw_matrix(heading) @ axis_rotation("x", pitch)
    torso = [axis_rotation("x", spine / 3) @ axis_rotation("z", roll / 3)] * 3
    head_fix = -(pitch + spine) * 0.45

    def upper_body(extra: np.ndarray) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """Global rotations and positions with an extra world rotation (T,3,3) of the torso
        about spine1, the bend a person adds to reach the chair."""
        g = {0: go}
        g[J["spine1"]] = extra @ go @ torso[0]
        g[J["spine2"]] = g[J["spine1"]] @ torso[1]
        g[J["spine3"]] = g[J["spine2"]] @ torso[2]
        g[J["neck"]] = g[J["spine3"]] @ axis_rotation("x", head_fix)
        g[J["head"]] = g[J["neck"]] @ axis_rotation("x", head_fix)
        for side in ("left", "right"):
            g[J[f"{side}_collar"]] = g[J["spine3"]]
        pos = body.sk.forward(pelvis, g, [J["left_hip"], J["right_hip"], J["left_shoulder"],
                                          J["right_shoulder"], J["spine1"]])
        return g, pos

    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    g, pos = upper_body(eye)
    contact_plans: dict[str, tuple[dict, np.ndarray]] = {}
    if hand_plan and sit is not None:
        contact_plans, g, pos = _plan_contacts(body, hand_plan, time, sit, seated, stand, rng,
                                               upper_body, seated_pelvis, fixed)

    # Legs: ankles on their footprints; crossing the legs lifts the right ankle over the left knee.
    forward = np.stack([np.sin(heading), np.zeros(n), np.cos(heading)], -1)
    for foot, side in ((0, "left"), (1, "right")):
        hip = pos[J[f"{side}_hip"]]
        ankle = feet[foot].copy()
        foot_fwd = np.stack([np.sin(feet_head[foot]), np.zeros(n), np.cos(feet_head[foot])], -1)
        outward = (1 if side == "left" else -1) * np.cross([0.0, 1.0, 0.0], forward)
        pole = normalize(forward + foot_fwd) + 0.15 * outward
        if side == "right" and free_w.any():
            # cross the ankles: the right foot rests over the left one, a little ahead of it
            left_dir = np.cross([0.0, 1.0, 0.0], forward)
            over = feet[0] + np.array([0.0, 0.09, 0.0]) + 0.07 * forward + 0.02 * left_dir
            lift = smoothstep(free_w / 0.35)[:, None]  # lift first, then move across
            slide = smoothstep((free_w - 0.3) / 0.7)[:, None]
            ankle = ankle + slide * (over - ankle) * np.array([1.0, 0.0, 1.0]) + lift * (
                over - ankle) * np.array([0.0, 1.0, 0.0])
        knee, d_up, d_low, hinge = two_bone_ik(hip, ankle, pole, *body.leg)
        pos[J[f"{side}_knee"]] = knee
        rest_up = body.sk.rest[J[f"{side}_knee"]] - body.sk.rest[J[f"{side}_hip"]]
        rest_low = body.sk.rest[J[f"{side}_ankle"]] - body.sk.rest[J[f"{side}_knee"]]
        # twist from the knee's hinge axis, not the pole: seated, the thigh points along the
        # forward pole and a pole-based frame spins the leg 180° about the thigh
        g[J[f"{side}_hip"]], g[J[f"{side}_knee"]] = limb_rotations(
            rest_up, rest_low, np.array([0.0, 0.0, 1.0]), d_up, d_low, hinge)
        g[J[f"{side}_ankle"]] = yaw_matrix(feet_head[foot])
        if side == "right" and free_w.any():  # a crossed leg's foot hangs off the shin
            g[J["right_ankle"]] = _blend_rot(g[J["right_ankle"]], g[J["right_knee"]]
                                             @ axis_rotation("x", np.full(n, 0.3)), free_w)
        g[J[f"{side}_foot"]] = g[J[f"{side}_ankle"]]

    # Arms: a walking swing (procedural), or IK to the thighs / the chair when sitting.
    local_proc = _arm_swing(time, moving, step_rate)
    hand_contacts: dict[str, tuple[float, float, np.ndarray, str]] = {}
    ik_w = {s: np.zeros(n) for s in ("left", "right")}
    contact_info: dict[str, tuple[dict, np.ndarray, np.ndarray, np.ndarray]] = {}
    wrist_t = {}
    hand_rot = {}
    if sit is not None:
        for side, sign in (("left", 1.0), ("right", -1.0)):
            lateral = np.cross([0.0, 1.0, 0.0], forward) * sign
            hip, knee = pos[J[f"{side}_hip"]], pos[J[f"{side}_knee"]]
            # on top of the thigh (its front while standing), a little outside its midline
            thigh_up = normalize(np.cross(knee - hip, np.cross([0.0, 1.0, 0.0], forward)))
            thigh_pt = hip + 0.55 * (knee - hip) + body.thigh_radius * thigh_up - 0.01 * lateral
            fingers = forward
            rot_thigh = align(np.array([sign, 0, 0]), np.array([0, -1.0, 0]), fingers,
                              np.array([0, -1.0, 0]) + 0 * fingers)
            target = thigh_pt - (rot_thigh @ body.palm_offset[side])
            rot = rot_thigh
            w = sit_w.copy()
            if side in contact_plans:
                plan, c = contact_plans[side]
                contact_info[side] = (plan, c, target, rot)
                target = target * (1 - c[:, None]) + plan["wrist"] * c[:, None] + _hand_arc(c)
                rot = _blend_rot(rot, plan["rot"], c)
                w = np.maximum(w, c)
                hand_contacts[side] = (plan["t_on"], plan["t_off"], plan["point"], plan["part"])
            ik_w[side] = w
            wrist_t[side] = target
            hand_rot[side] = rot

    for side, sign in (("left", 1.0), ("right", -1.0)):
        sh, el, wr = J[f"{side}_shoulder"], J[f"{side}_elbow"], J[f"{side}_wrist"]
        if not ik_w[side].any():
            continue
        lateral = np.cross([0.0, 1.0, 0.0], forward) * sign
        pole = -forward * 0.8 + lateral * 0.45 - np.array([0, 0.3, 0])
        _, d_up, d_low, hinge = two_bone_ik(
            pos[sh], wrist_t[side],
            steady_pole(pos[sh], wrist_t[side], pole, *body.arm, DENSE_HZ, ELBOW_SWING), *body.arm)
        if side in contact_info:
            # Second pass: lay the palm along the forearm's direction on the surface, so the
            # wrist stays near neutral, then re-solve the arm for the moved wrist.
            plan, c, thigh_target, thigh_rot = contact_info[side]
            nrm = plan["normal"]
            # biased towards the part's natural finger direction, which keeps it defined when
            # the forearm is along the normal
            pref = plan["fingers"]
            along = normalize(d_low - (d_low @ nrm)[:, None] * nrm) + 0.25 * (pref - (
                pref @ nrm) * nrm)
            fingers = normalize(along)
            rot_c = align(np.array([sign, 0, 0]), np.array([0, -1.0, 0]), fingers,
                          np.broadcast_to(-nrm, (n, 3)))
            wrist_c = plan["point"] + plan["hover"] * nrm - rot_c @ body.palm_offset[side]
            wrist_t[side] = thigh_target * (1 - c[:, None]) + wrist_c * c[:, None] + _hand_arc(c)
            hand_rot[side] = _blend_rot(thigh_rot, rot_c, c)
            _, d_up, d_low, hinge = two_bone_ik(
                pos[sh], wrist_t[side],
                steady_pole(pos[sh], wrist_t[side], pole, *body.arm, DENSE_HZ, ELBOW_SWING),
                *body.arm)
        rest_up = body.sk.rest[el] - body.sk.rest[sh]
        rest_low = body.sk.rest[wr] - body.sk.rest[el]
        # twist from the elbow's hinge axis: the pole is no fixed frame for an arm reaching
        # down and back, where the bones pass along it (the forearm and hand flipped 180°)
        g_sh, g_el = limb_rotations(rest_up, rest_low, np.array([0.0, 0.0, -1.0]), d_up, d_low,
                                    hinge)
        ik_local = {
            sh: np.swapaxes(g[J[f"{side}_collar"]], -1, -2) @ g_sh,
            el: np.swapaxes(g_sh, -1, -2) @ g_el,
        }
        for j, loc in ik_local.items():
            local_proc[j] = _blend_rot(local_proc[j], loc, ik_w[side])
        if side in contact_info:
            # The wrist stays neutral (the hand follows the forearm) except while the palm is
            # on the chair, when it turns the palm onto the surface.
            plan, c = contact_info[side][:2]
            wrist_c = np.swapaxes(g_el, -1, -2) @ hand_rot[side]
            # Before the palm lands, turn towards the landing orientation, not towards what the
            # far-away forearm would need.
            on = min(int(np.searchsorted(time, plan["t_on"])), n - 1)
            wrist_c[:on] = wrist_c[on]
            local_proc[wr] = _blend_rot(local_proc[wr], wrist_c, c)

    for side in ("left", "right"):
        el, wr = J[f"{side}_elbow"], J[f"{side}_wrist"]
        # At most 95° of pronation goes into the forearm (the elbow's twist range is ±100°):
        # a palm landing flat while the arm hangs steeply needs more wrist twist for a moment,
        # and clamping a 150° forearm twist afterwards would swing the hand into the chair.
        local_proc[el], local_proc[wr] = transfer_twist(
            local_proc[el], local_proc[wr], body.sk.offset(wr), np.deg2rad(95))
    local = local_from_global(g, n)
    for j, loc in local_proc.items():
        local[:, j] = loc
    # Transitions (an arm swinging onto the chair) may pass outside anatomical ranges for a few
    # frames; clamp them. Held contacts and the legs are well inside and stay exactly as solved.
    body_aa = clamp_to_limits(Rotation.from_matrix(local[:, 1:].reshape(-1, 3, 3)).as_rotvec()
                              .reshape(n, -1))
    local[:, 1:] = Rotation.from_rotvec(body_aa.reshape(-1, 3)).as_matrix().reshape(n, 23, 3, 3)
    labels = np.full(n, INTERACTION_LABEL[interaction], dtype=np.int8)
    turn = _phase(phases, "turn")
    if interaction == "locomotion":
        labels[:] = 0
    else:
        start = turn[0] if turn else 0.0
        labels[time < start] = 0
        leave = _phase(phases, "leave")
        if leave is not None:
            labels[time > leave[0] + 0.5] = 0
    transl = pelvis - body.rest[0]
    return Motion(interaction=interaction, betas=betas.astype(np.float32), time=time,
                  global_rot=go, local_rot=local, transl=transl, labels=labels,
                  hand_contacts=hand_contacts, phases=phases)


# Reaching behind to the backrest needs more shoulder and forearm rotation than the analytic arm
# IK can pose within joint limits, so backrest palm targets are not used yet (weight 0).
_PART_WEIGHT = {"armrest": 0.6, "seat": 0.4, "back": 0.0}


def _contact_target(body: _Body, side: str, part: str, point: np.ndarray, normal: np.ndarray,
                    n: int, hips: np.ndarray, hover: float = PALM_HOVER) -> dict:
    """Wrist position (n,3) and hand rotation (n,3,3) that put the palm on ``point``, fingers
    pointing away from the sitter's hips (``hips`` (3,)), as a supporting hand does; the palm
    centre ``hover`` (m) above it along ``normal``."""
    sign = 1.0 if side == "left" else -1.0
    away = (point - hips) * np.array([1.0, 0.0, 1.0])
    f_dir = normalize(away) if np.linalg.norm(away) > 0.05 else np.array(
        [0.0, 0.0, -1.0 if part.endswith("back") else 1.0])
    rot = align(np.array([sign, 0, 0]), np.array([0, -1.0, 0]),
                np.broadcast_to(f_dir, (n, 3)), np.broadcast_to(-normal, (n, 3)))
    wrist = point + hover * normal - rot @ body.palm_offset[side]
    return {"part": part, "point": point, "normal": normal, "wrist": wrist, "rot": rot,
            "fingers": f_dir, "hover": hover}


def _plan_contacts(body: _Body, hand_plan: dict[str, list[tuple[str, np.ndarray, np.ndarray]]],
                   time: np.ndarray, sit: tuple[float, float], seated: tuple[float, float] | None,
                   stand: tuple[float, float] | None, rng: np.random.Generator, upper_body,
                   hips: np.ndarray, fixed: dict[str, tuple] | None = None
                   ) -> tuple[dict[str, tuple[dict, np.ndarray]], dict, dict]:
    """Choose a palm target per hand and bend the torso so the hands reach them.

    The palm lands during the second half of sitting down and stays until part-way through the
    seated phase. Where a target is beyond arm's reach the torso rotates about spine1 (leaning
    forward or sideways, as people do) by the least angle that brings the shoulders within
    reach, and while a hand moves onto the chair or off it by no more than while it is there;
    a choice that still cannot be reached is replaced by another candidate.
    Returns side → (target dict with t_on/t_off, contact weight (T,)), and the bent upper
    body's global rotations and positions.
    """
    n = len(time)
    end = stand[0] if stand is not None else time[-1]
    _, pos0 = upper_body(np.broadcast_to(np.eye(3), (n, 3, 3)))
    arm = sum(body.arm)
    slack = 0.15  # what a moderate extra bend of the torso can make up
    t_first = sit[0] + 0.35 * (sit[1] - sit[0])
    windows: dict[str, list[tuple[float, float] | None]] = {}
    for side, candidates in hand_plan.items():
        shoulder = pos0[J[f"{side}_shoulder"]]
        wins = []
        for part, point, _normal in candidates:
            under_thigh = part.endswith("seat") and abs(point[0] - hips[0]) < (
                body.hip_half_width + body.thigh_radius + 0.03) and point[2] < hips[2] + (
                body.leg[0])
            if part.endswith("back") and point[2] < hips[2] - 0.3:
                wins.append(None)  # a backrest far behind the sitter is not reached for
                continue
            # a palm where the thigh lands must be gone before the hips come down
            last = sit[0] + 0.8 * (sit[1] - sit[0]) if under_thigh else end
            near = (np.linalg.norm(point - shoulder, axis=1) < 0.9 * arm + slack) & (
                time >= t_first) & (time <= last)
            if not near.any():
                wins.append(None)
                continue
            first = int(np.argmax(near))
            stop = first + int(np.argmin(near[first:])) if not near[first:].all() else n - 1
            wins.append((float(time[first]), float(time[stop])) if time[stop] - time[first]
                        > (0.45 if under_thigh else 0.6) else None)
        windows[side] = wins
    for _attempt in range(12 if fixed is None else 1):
        plans: dict[str, tuple[dict, np.ndarray]] = {}
        # Both hands use the same kind of part (both armrests, or the seat either side): a
        # torso cannot lean towards an armrest on one side and the seat on the other.
        kinds = {c[0].split("_")[1] for side in hand_plan for c, w in zip(
            hand_plan[side], windows[side], strict=True) if w is not None}
        shared = [k for k in sorted(kinds) if _PART_WEIGHT[k] > 0 and all(
            any(w is not None and c[0].endswith(k) for c, w in zip(
                hand_plan[side], windows[side], strict=True)) for side in hand_plan)]
        kind = (str(rng.choice(shared, p=np.array([_PART_WEIGHT[k] for k in shared]) / sum(
            _PART_WEIGHT[k] for k in shared))) if len(hand_plan) > 1 and shared else None)
        for side, candidates in hand_plan.items():
            if fixed is not None:
                part, point, normal, t_on, t_off, hover = fixed[side]
                plan = _contact_target(body, side, part, point, normal, n, hips, hover)
                plan["t_on"], plan["t_off"] = t_on, t_off
                c = smoothstep((time - (t_on - 0.5)) / 0.5) * (
                    1 - smoothstep((time - t_off) / 0.5))
                plans[side] = (plan, c)
                continue
            scores = np.array([0.0 if w is None or (kind and not c[0].endswith(kind))
                               else _PART_WEIGHT[c[0].split("_")[1]]
                               for c, w in zip(candidates, windows[side], strict=True)])
            if scores.sum() <= 0:
                raise ValueError(f"no {side}-hand palm target on this chair is within reach")
            k = rng.choice(len(candidates), p=scores / scores.sum())
            part, point, normal = candidates[k]
            win_on, win_off = windows[side][k]
            plan = _contact_target(body, side, part, point, normal, n, hips)
            plan["t_on"] = float(win_on + rng.uniform(0.0, 0.3) * max(0.0, min(
                0.6, win_off - win_on - 0.45)))
            if part.endswith("seat"):
                # a hand on the seat supports the descent and lets go as the hips land
                plan["t_off"] = float(min(win_off, sit[0] + rng.uniform(0.92, 1.0) * (
                    sit[1] - sit[0])))
            else:
                hold = (seated[0] + rng.uniform(0.3, 0.7) * (seated[1] - seated[0])
                        if seated is not None else end)
                plan["t_off"] = float(min(win_off, hold))
            plan["t_off"] = max(plan["t_off"], plan["t_on"] + 0.45)
            c = smoothstep((time - (plan["t_on"] - 0.5)) / 0.5) * (
                1 - smoothstep((time - plan["t_off"]) / 0.5))
            plans[side] = (plan, c)
        extra = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        # lean until the target is within 0.9 arm lengths: a margin for the elbow (at the
        # least lean that reaches 0.94, armrest holds straightened the arm into the armrest)
        reach = 0.90 * sum(body.arm)
        for _ in range(3):
            for side, (plan, c) in plans.items():
                _, pos = upper_body(extra)
                pivot = pos[J["spine1"]]
                lever = pos[J[f"{side}_shoulder"]] - pivot
                radius = np.linalg.norm(lever, axis=1, keepdims=True)
                u0 = lever / radius
                u1 = normalize(plan["wrist"] - pivot)
                # smallest turn of the shoulder along the great circle towards the target
                # that brings it within reach (distance falls monotonically along it)
                full = Rotation.from_rotvec(normalize(np.cross(u0, u1)) * np.arccos(
                    np.clip((u0 * u1).sum(1), -1, 1))[:, None]).as_rotvec()
                frac = _least_turn(pivot, radius, u0, full, plan["wrist"], reach)
                # While the hand moves onto the chair (or off it) it is on its way from the
                # thigh, not at the target: the torso leans no further than it does while the
                # hand is there. (Bending c times the lean that would reach the target from the
                # still-high body swung the torso 60-90 deg mid-descent and back.)
                angle = np.linalg.norm(full, axis=1) * frac
                hold = c > 0.95
                angle = np.minimum(angle, angle[hold].max() if hold.any() else 0.0)
                turn = Rotation.from_rotvec(normalize(full) * (angle * c)[:, None]).as_matrix()
                extra = turn @ extra
        g, pos = upper_body(extra)
        bend = np.degrees(Rotation.from_matrix(extra).magnitude())
        reach_ok = all(
            np.all(np.linalg.norm(plan["wrist"] - pos[J[f"{side}_shoulder"]], axis=1)[c > 0.95]
                   < 0.995 * sum(body.arm)) for side, (plan, c) in plans.items())
        if (reach_ok and bend.max() < 45) or fixed is not None:
            return plans, g, pos
    raise ValueError(f"no reachable palm targets for {sorted(hand_plan)} on this chair")


def _least_turn(pivot: np.ndarray, radius: np.ndarray, u0: np.ndarray, full: np.ndarray,
                target: np.ndarray, reach: float, halvings: int = 12) -> np.ndarray:
    """(n,) least share in [0, 1] of the turn ``full`` (n,3 rotation vectors) that brings a
    shoulder at ``pivot + radius * u0`` ((n,3), (n,1), (n,3); m) within ``reach`` (m) of
    ``target`` (n,3): 0 where it already is, 1 where even the full turn does not. Bisected
    (the distance falls monotonically along the turn), not sampled: twentieths stepped the
    torso by up to 9 degrees between frames."""
    def reaches(f: np.ndarray) -> np.ndarray:
        shoulder = pivot + radius * Rotation.from_rotvec(full * f[:, None]).apply(u0)
        return np.linalg.norm(target - shoulder, axis=1) < reach

    n = len(full)
    lo, hi = np.zeros(n), np.ones(n)
    for _ in range(halvings):
        mid = 0.5 * (lo + hi)
        ok = reaches(mid)
        lo, hi = np.where(ok, lo, mid), np.where(ok, mid, hi)
    return np.where(reaches(np.zeros(n)), 0.0, hi)


def _hand_arc(c: np.ndarray, height: float = 0.12) -> np.ndarray:
    """(T,3) upward detour of a hand moving onto or off the chair (largest half-way), so it
    passes over armrests and backrest edges instead of through them."""
    return np.stack([np.zeros_like(c), 4 * height * c * (1 - c), np.zeros_like(c)], -1)


def _blend_rot(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per-frame slerp between rotation matrices a and b (T,3,3) with weights w (T,).

    Each run of consecutive frames blended part of the way (0 < w < 1) turns from a towards b
    the same way round from frame to frame: the shortest way changes sides where a and b pass
    180° apart, which swung a blended arm 127° in one 120 Hz frame. A run starts the shortest
    way; frames at w = 0 or 1 do not depend on the way.
    """
    w = np.clip(w, 0, 1)
    ra, rb = Rotation.from_matrix(np.broadcast_to(a, (len(w), 3, 3))), Rotation.from_matrix(
        np.broadcast_to(b, (len(w), 3, 3)))
    delta = (ra.inv() * rb).as_rotvec()  # angles in [0, pi]
    # the deltas' quaternions have w >= 0: a negative dot between neighbours is a side swap
    quat = axis_angle_to_quat(delta)
    partial = (w > 0) & (w < 1)
    swap = np.zeros(len(w), bool)
    swap[1:] = ((quat[1:] * quat[:-1]).sum(-1) < 0) & partial[1:] & partial[:-1]
    if swap.any():
        # swaps since the start of each part-way run (count never falls, so the running maximum
        # of its value at run starts is the latest start's)
        count = np.cumsum(swap)
        starts = partial & ~np.r_[False, partial[:-1]]
        odd = partial & ((count - np.maximum.accumulate(np.where(starts, count, 0))) % 2 == 1)
        # the other way round: angle - 2 pi about the same axis
        angle = np.linalg.norm(delta[odd], axis=-1)
        delta[odd] *= ((angle - 2 * np.pi) / np.maximum(angle, 1e-12))[:, None]
    return (ra * Rotation.from_rotvec(delta * w[:, None])).as_matrix()


def _arm_swing(time: np.ndarray, moving: np.ndarray, step_rate: float
               ) -> dict[int, np.ndarray]:
    """Local rotations of shoulders, elbows and wrists for relaxed arms swinging against the
    legs: each arm swings forward as the opposite foot does."""
    n = len(time)
    swing = np.deg2rad(18) * moving * np.sin(np.pi * step_rate * time)
    out = {}
    for side, sign in (("left", 1.0), ("right", -1.0)):
        s = swing if side == "left" else -swing
        down = axis_rotation("z", np.full(n, -sign * np.deg2rad(72)))
        out[J[f"{side}_shoulder"]] = axis_rotation("x", -s) @ down
        out[J[f"{side}_elbow"]] = axis_rotation("y", np.full(n, -sign * np.deg2rad(15))
                                                - sign * np.maximum(0, s) * 0.5)
        out[J[f"{side}_wrist"]] = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    return out


__all__ = [
    "DENSE_HZ", "INTERACTION_LABEL", "INTERACTION_MIX", "Motion", "MotionConfig", "MotionRejected",
    "SeatGeometry", "generate_motion", "max_penetration", "sample_interaction",
]
