"""Contacts of the five schema parts with the chair (and of the feet with the floor), and the
per-frame interaction labels of DESIGN.md.

A part touches the chair when its body surface is close to the chair's surface *and* it is not
moving: a hand sweeping past an armrest comes as close as one resting on it, but only the resting
one is a contact. Both signals come from a fitted motion, whose per-frame noise (an IMU fit
jitters by centimetres) is larger than the gap that separates touching from hovering, so:

* the posed contact vertices are smoothed over time before measuring (a Gaussian of
  :attr:`ContactConfig.smooth` seconds), and speeds come from a longer smoothing;
* a contact *enters* only below the tight thresholds (distance and speed) and *leaves* only above
  the loose ones (hysteresis), so noise around one threshold does not make it flicker;
* gaps shorter than :attr:`ContactConfig.max_gap` are filled, each contact's edges are trimmed
  to where the part is within the entry distance, and runs shorter than
  :attr:`ContactConfig.min_duration` are dropped.

These guards cost an exact motion its short contacts (a palm that touches the chair for a frame
or two as it moves, a frame at each end of a half-second hold), so they are applied only as far
as the motion's own per-frame noise asks (:func:`motion_noise`, measured on the posed contact
vertices): the smoothing brings it down to :attr:`ContactConfig.noise_target`, and the speed
gate and the durations scale with the noise left after it (``guard`` of :func:`contact_flags`;
not the hysteresis band, which also holds a contact through a fit's systematic offset). A
fused session fit measures about a millimetre and is taken nearly frame by frame; an IMU-like
fit (2-3 cm) gets the full guards.

Every threshold is in metres, m/s or seconds and converted to frames with ``fps``, so the
same configuration serves 5, 15 and 30 fps recordings.

Interaction labels (``couch.schema.INTERACTION_LABELS``) follow COUCH's annotation: a recording
is locomotion (0) except during an *interaction episode*, which is a seated period (pelvis on the
chair) extended back to where the subject stopped walking and forward to where they walk off
again. An episode has one label from what happened in it: free interaction (5) when one foot was
lifted above the other while seated (crossed ankles or legs), else which hands supported the
body on the chair (1 right, 2 left, 3 both), else no hand contact (4). A supporting hand is on
the chair palm down and not on the lap (hands resting on the thighs brush the seat's sides;
hands hanging beside the hips as they come down brush it too, facing the thighs), or on the
chair while the torso leans towards it as the subject sits down. A palm-down hand below a
thigh's middle height is on the seat beside the thigh, not on the lap, though it touches both.

Feet on the floor are reported apart from the schema's chair contacts
(:attr:`Contacts.floor_active`): the schema's /contacts are contacts with the object.

World frame as everywhere (DESIGN.md): metres, Y up; the floor is ``y = floor_height``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import torch
from scipy.ndimage import gaussian_filter1d

from couch.body import CONTACT_NAMES, JOINT_INDEX, BodyModel
from couch.fitting.params import BodyParams
from couch.runs import drop_short_runs, fill_gaps, flip_runs, runs, trim_edges

__all__ = [
    "ChairSurface",
    "ContactConfig",
    "Contacts",
    "contact_flags",
    "detect_contacts",
    "drop_short_runs",
    "fill_gaps",
    "hysteresis",
    "interaction_labels",
    "motion_noise",
    "palm_down",
    "part_distances",
    "runs",
    "side_lean",
    "smoothing_sigma",
    "trim_edges",
    "walking",
]

FEET = ("left_foot", "right_foot")
LOCOMOTION, RIGHT_HAND, LEFT_HAND, BOTH_HANDS, NO_HAND, FREE = range(6)


@dataclasses.dataclass(frozen=True)
class ContactConfig:
    """Thresholds of contact detection and labelling (metres, m/s, seconds).

    The defaults were chosen on simulated motions (tests/test_fitting_contacts.py). Contact
    flags enter at 2 cm, the distance at which COUCH-style annotation (and the simulator's
    truth) calls a part touching, and leave at 2.5 cm (3 cm while the simulator's held palms
    sat anywhere from inside the chair to a few cm off it; with them resting on it, the wider
    band held unplanned hands lingering 2-3 cm from an armrest after a brush): wider hysteresis
    or longer minimum durations steady the flags of a noisy fit but lose the many short hand
    contacts (a palm lands, takes weight for a fraction of a second and lifts). The speed gate
    (0.5 / 1 m/s) only rejects parts passing by: a landing palm still moves a little when it
    first touches.
    The label's looser support test (5 / 7 cm, 0.2 s) tolerates an IMU-like fit's ~3.5 cm of
    hand error per frame and a session fit's palms, which sit 3-7 cm off the armrest they
    press on (the depth cameras barely see fingers).
    """

    enter_distance: float = 0.02  # m: a part may start touching closer than this ...
    leave_distance: float = 0.025  # m: ... and stops touching farther than this
    enter_speed: float = 0.5  # m/s: ... and may start touching only slower than this
    leave_speed: float = 1.0  # m/s: ... and stops touching faster than this
    # Smoothing is as strong as the motion's own per-frame noise asks (see :func:`motion_noise`):
    # a Gaussian that brings white noise of the measured size down to ``noise_target``, at
    # most these sigmas. Clean motion (a fused session fit, the simulator's truth) is measured
    # as it is: smoothing it blurs the edges of half-second palm holds by a frame each.
    smooth: float = 0.1  # s: largest Gaussian sigma on the vertex positions before measuring
    speed_smooth: float = 0.15  # s: ... and on part centres before differentiating (in proportion)
    noise_target: float = 0.01  # m: per-frame noise left after smoothing
    min_duration: float = 0.1  # s: shorter contacts are dropped (after gap filling)
    max_gap: float = 0.1  # s: shorter breaks inside a contact are filled
    floor_enter: float = 0.03  # m: foot-to-floor distance to start a floor contact ...
    floor_leave: float = 0.05  # m: ... and to end it (speeds as for the chair)
    # A contact point is the centre of the part's vertices within this of its closest (on the
    # chair: of their nearest chair points), not the single closest, which jumps across a
    # flat seat with a degree of pelvis tilt and between heel and toes on a flat sole. 2 cm is
    # the contact distance: the centre of what lies within touching range once the part
    # touches. On the accuracy bench's 30 sessions 1 cm left the seated pelvis's point 2.22 cm
    # mean (5.51 cm 90th percentile) from the one the same rule puts on the true motion, 2 cm
    # 1.31 (2.96), and the hands' points as close to the simulator's planned palm points
    # (README, *Processing a session*).
    point_patch: float = 0.02  # m
    # labels: a supporting hand is judged with looser thresholds than the contact flags (a
    # fitted palm pressing on an armrest hovers a few centimetres off it in many frames)
    support_enter: float = 0.05  # m
    support_leave: float = 0.07  # m
    support_min_duration: float = 0.2  # s
    walk_speed: float = 0.7  # m/s: a movement of the pelvis reaching this is walking ...
    stop_speed: float = 0.25  # m/s: ... from where its horizontal speed rises above this
    walk_smooth: float = 0.2  # s: Gaussian sigma on the pelvis track for those speeds
    # a recording that starts or ends mid-walk cuts the walk short of walk_speed: a movement
    # cut by the recording's first or last frame is walking from this speed on, unless the
    # pelvis drops (sitting down) or rises (standing up) by edge_walk_drop during it
    edge_walk_speed: float = 0.3  # m/s
    edge_walk_drop: float = 0.1  # m
    min_seated: float = 0.5  # s: a pelvis contact shorter than this is no episode
    merge_gap: float = 1.0  # s: seated periods closer than this are one episode
    min_hand: float = 0.3  # s: total supporting contact of a hand that makes a hand episode
    # s before the pelvis lands from which a hand's contact counts as support: a hand brushing
    # an armrest while the subject turns in front of the chair, or while rising, is not how
    # they sat (the COUCH types describe the sitting down and the seated period)
    support_before: float = 1.5
    # s: ... and only a touch that lasts to within this long of the landing, or later: a hand
    # that takes weight is on the chair as the pelvis goes down; an armrest brushed while
    # turning a second before and let go is no support. A palm on the seat where a thigh will
    # land leaves before the hips come down, up to ~0.55 s before the landing (0.5 missed one
    # such; 0.6-1.2 read the same labels on 128 simulated motions and sessions)
    support_gap: float = 0.7
    lap_distance: float = 0.03  # m: a hand this close to a thigh rests on the lap (0: no test)
    # A hand takes weight on the chair palm down: it supports only while its palm faces the
    # floor (the cosine of the palm's normal with straight down above this), and a palm-down
    # hand below a thigh's middle height presses on the seat beside it, not on the lap. A hand
    # hanging beside the hips as they come down (on its way to the lap, brushing the seat)
    # faces the thigh (cosine about 0-0.2); a palm on a seat or armrest faces the floor
    # (0.8-1). On simulated truth motions any value in [0.2, 0.7] reads the same labels.
    palm_down: float = 0.5
    support_lean: float = 6.0  # deg the torso leans towards a hand that takes weight
    foot_lift: float = 0.05  # m: a seated foot this far above the other is lifted (free)
    min_lift: float = 0.4  # s: a lift this long while seated makes the episode free

    def __post_init__(self) -> None:
        for name in ("enter_distance", "leave_distance", "enter_speed", "leave_speed",
                     "floor_enter", "floor_leave", "walk_speed", "stop_speed", "foot_lift",
                     "noise_target"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ContactConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("smooth", "speed_smooth", "min_duration", "max_gap", "walk_smooth",
                     "min_seated", "merge_gap", "min_hand", "support_before", "support_gap",
                     "min_lift", "point_patch",
                     "lap_distance",
                     "support_lean", "edge_walk_speed", "edge_walk_drop"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"ContactConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.leave_distance < self.enter_distance or self.leave_speed < self.enter_speed \
                or self.floor_leave < self.floor_enter:
            raise ValueError("ContactConfig: leave thresholds must not be below the enter "
                             "thresholds (hysteresis)")
        if not -1.0 <= self.palm_down <= 1.0:
            raise ValueError(f"ContactConfig.palm_down is a cosine in [-1, 1], got "
                             f"{self.palm_down}")
        if self.walk_speed < self.stop_speed:
            raise ValueError("ContactConfig: walk_speed must not be below stop_speed")


@dataclasses.dataclass
class Contacts:
    """Contacts and labels of a motion, world frame (metres, Y up), T frames at ``fps``.

    Attributes:
        names: the five parts, ``couch.body.CONTACT_NAMES`` order (the schema's /contacts/names).
        active: (T,5) bool, part touches the chair (the schema's /contacts/active).
        points: (T,5,3) float32 contact point on the chair surface, NaN where inactive
            (the schema's /contacts/points).
        labels: (T,) int8 interaction labels (the schema's /labels/interaction).
        distance: (T,5) float32 m, smoothed distance from the part's surface to the chair.
        speed: (T,5) float32 m/s, speed of the part's centre (smoothed).
        floor_active: (T,2) bool, left/right foot on the floor (never while on the chair).
        floor_points: (T,2,3) float32 contact point on the floor, NaN where inactive.
        floor_distance: (T,2) float32 m, height of the foot's lowest vertex above the floor.
        fps: frames per second.
        noise: m, the motion's per-frame noise as measured (:func:`motion_noise`).
        guard: in [0, 1], how much of the noise guards the chair contacts got
            (:func:`contact_flags`; 0: every frame's distance trusted as it is).
    """

    names: tuple[str, ...]
    active: np.ndarray
    points: np.ndarray
    labels: np.ndarray
    distance: np.ndarray
    speed: np.ndarray
    floor_active: np.ndarray
    floor_points: np.ndarray
    floor_distance: np.ndarray
    fps: float
    noise: float = 0.0
    guard: float = 1.0

    @property
    def num_frames(self) -> int:
        return len(self.active)


class ChairSurface:
    """The chair's triangle mesh in the world, ready for closest-point queries.

    Args:
        vertices: (V,3) metres, world frame (apply the object pose first).
        faces: (F,3) vertex indices.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise ValueError(f"chair mesh: vertices must be a non-empty (V,3) array, got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"chair mesh: faces must be a non-empty (F,3) array, got {f.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("chair mesh: vertices hold NaN or infinite values")
        if not np.issubdtype(f.dtype, np.integer) or f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"chair mesh: faces must index the {len(v)} vertices, got values in "
                             f"[{f.min()}, {f.max()}] ({f.dtype})")
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                                  o3d.core.Tensor(f.astype(np.uint32)))

    @classmethod
    def from_model(cls, chair: object) -> ChairSurface:
        """From anything with ``vertices``, ``faces`` and ``world_from_object`` (a
        ``couch.capture.segmentation.ChairModel``): the mesh moved into the world."""
        pose = np.asarray(chair.world_from_object, dtype=np.float64)  # type: ignore[attr-defined]
        v = np.asarray(chair.vertices, dtype=np.float64)  # type: ignore[attr-defined]
        return cls(v @ pose[:3, :3].T + pose[:3, 3], chair.faces)  # type: ignore[attr-defined]

    def closest(self, points: np.ndarray) -> np.ndarray:
        """(...,3) query points (m, world) → (...,3) float64 nearest points on the surface."""
        p = np.asarray(points, dtype=np.float32)
        q = self._scene.compute_closest_points(o3d.core.Tensor(p.reshape(-1, 3)))
        return q["points"].numpy().reshape(p.shape).astype(np.float64)


def motion_noise(positions: np.ndarray) -> float:
    """Robust per-frame noise (m) of (T,N,3) point tracks: the lower quartile of the absolute
    second differences over frames, points and axes, as the standard deviation of white noise
    (second differences of white noise σ have σ·√6, whose lower quartile is 0.3186 of that).
    The lower quartile, not the median: a motion's own accelerations add to the second
    differences wherever something moves, and at 5 fps they reach centimetres; a recording in
    which a quarter of the part coordinates rest at a time measures its noise there. The
    simulator's exact motions measure under 1.2 mm at 15-30 fps and mostly under 2.5 mm at
    5 fps (one with much movement 12 mm, where the median read 22 mm), an IMU-like fit (3° per
    bone, 1 cm) 1.8-3 cm. The quartile falls on the steadiest parts (resting feet, a seated
    pelvis), so it stands for the noise of the whole fit: a fit whose hands alone jitter would
    read as clean. Measured per part on fused session fits, the hands' second differences
    (1.3-4 mm at 15 fps) match the true motion's own (1.7-4 mm)."""
    p = np.asarray(positions, np.float64)
    if len(p) < 3:
        return 0.0
    second = np.abs(p[2:] - 2 * p[1:-1] + p[:-2])
    return float(np.quantile(second, 0.25) / (0.3186 * np.sqrt(6)))


def smoothing_sigma(noise: float, target: float, most: float, fps: float) -> float:
    """Gaussian sigma (s) that brings white noise of ``noise`` (m) per frame down to
    ``target`` (m), at most ``most`` s: a Gaussian of σ frames divides white noise by
    √(2√π σ) (:func:`_smoothed_noise`)."""
    frames = (noise / target) ** 2 / (2 * np.sqrt(np.pi))
    return float(min(most, frames / fps))


def _smoothed_noise(noise: float, sigma: float, fps: float) -> float:
    """White noise (m per frame) left after a Gaussian of ``sigma`` s (:func:`smoothing_sigma`
    inverted; a sigma under a frame's worth of the factor changes nothing)."""
    return noise / float(np.sqrt(max(1.0, 2 * np.sqrt(np.pi) * sigma * fps)))


def hysteresis(enter: np.ndarray, leave: np.ndarray, initial: bool = False) -> np.ndarray:
    """Two-threshold switch, vectorised over frames.

    Args:
        enter: (T,...) bool, the frame satisfies the (tight) conditions to start a contact.
        leave: (T,...) bool, the frame satisfies the (loose) conditions to end it; must not
            overlap ``enter``.
        initial: state before the first frame.

    Returns (T,...) bool: True from an ``enter`` frame until the next ``leave`` frame
    (exclusive); frames meeting neither keep the previous state.
    """
    enter = np.asarray(enter, bool)
    leave = np.asarray(leave, bool)
    if enter.shape != leave.shape:
        raise ValueError(f"hysteresis: enter {enter.shape} and leave {leave.shape} differ")
    if np.any(enter & leave):
        raise ValueError("hysteresis: a frame both enters and leaves (thresholds overlap)")
    t = len(enter)
    # The state of a frame is that of the last frame with an event: find it with a running max.
    idx = np.arange(t).reshape((t,) + (1,) * (enter.ndim - 1))
    last = np.maximum.accumulate(np.where(enter | leave, idx, -1), axis=0)
    state = np.take_along_axis(enter, np.maximum(last, 0), axis=0)
    return np.where(last >= 0, state, initial)


def _frames(seconds: float, fps: float) -> int:
    return round(seconds * fps)


def _smooth(x: np.ndarray, seconds: float, fps: float) -> np.ndarray:
    """Gaussian smoothing along axis 0 with sigma ``seconds`` (no-op below a third of a frame)."""
    sigma = seconds * fps
    return gaussian_filter1d(x, sigma, axis=0, mode="nearest") if sigma > 0.33 else x


def contact_flags(distance: np.ndarray, speed: np.ndarray, fps: float,
                  config: ContactConfig | None = None, enter: float | None = None,
                  leave: float | None = None, min_duration: float | None = None,
                  guard: float = 1.0) -> np.ndarray:
    """Contact flags from per-frame distances and speeds, thresholds in physical units.

    Args:
        distance: (T,K) m, distance of each part to the surface.
        speed: (T,K) m/s, speed of each part.
        fps: frame rate (durations in seconds become frames with it).
        config: thresholds (default :class:`ContactConfig`).
        enter, leave: distance thresholds (m) overriding ``config.enter_distance`` /
            ``config.leave_distance`` (the floor and the support test use their own).
        min_duration: s, overriding ``config.min_duration``.
        guard: in [0, 1], how much of the guards against a noisy motion to apply: the gap
            filling, the minimum duration and the speed gate (its thresholds divided by
            ``guard``) scale with it. 1 for a motion as noisy as ``config.noise_target`` or
            more; 0 for an exact one. The hysteresis band stays whole: it also absorbs a fit's
            systematic offset, which no noise measure sees (a fitted palm resting 2.0-2.2 cm
            off an armrest through a 16-frame hold the truth has within 2 cm).

    Returns (T,K) bool: hysteresis (enter when closer than ``enter`` and slower than
    ``enter_speed``; leave when farther than ``leave`` or faster than ``leave_speed``), then
    gaps up to ``max_gap`` filled, then each contact's first and last frames farther than
    ``enter`` trimmed (the hysteresis holds a contact through a noisy excursion inside it, not
    past where the part arrives and leaves), then runs shorter than ``min_duration`` dropped.
    """
    cfg = config or ContactConfig()
    distance = np.asarray(distance, np.float64)
    speed = np.asarray(speed, np.float64)
    if distance.shape != speed.shape or distance.ndim != 2:
        raise ValueError(f"contact_flags: distance and speed must both be (T,K), got "
                         f"{distance.shape} and {speed.shape}")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps}")
    enter_d = cfg.enter_distance if enter is None else enter
    leave_d = cfg.leave_distance if leave is None else leave
    if leave_d < enter_d:
        raise ValueError(f"contact_flags: leave distance {leave_d} m is below enter {enter_d} m")
    if not 0.0 <= guard <= 1.0:
        raise ValueError(f"contact_flags: guard must be in [0, 1], got {guard}")
    slow = np.inf if guard == 0 else cfg.enter_speed / guard
    fast = np.inf if guard == 0 else cfg.leave_speed / guard
    close = distance < enter_d
    on = hysteresis(close & (speed < slow), (distance > leave_d) | (speed > fast))
    on = trim_edges(fill_gaps(on, _frames(cfg.max_gap * guard, fps)), close)
    shortest = (cfg.min_duration if min_duration is None else min_duration) * guard
    return drop_short_runs(on, max(1, _frames(shortest, fps)))


# ----------------------------------------------------------------------- geometry


def _pose(model: BodyModel, params: BodyParams, ids: np.ndarray, batch: int = 256
          ) -> tuple[np.ndarray, np.ndarray]:
    """(T,len(ids),3) world positions of the vertices ``ids`` of the posed body and its (T,J,3)
    joints, float64 metres."""
    verts, joints = [], []
    betas = torch.as_tensor(params.betas[None], dtype=model.dtype)
    for a in range(0, params.num_frames, batch):
        sl = slice(a, a + batch)
        with torch.no_grad():
            out = model(betas=betas, global_orient=params.global_orient[sl],
                        body_pose=params.body_pose[sl], transl=params.transl[sl])
        verts.append(out.vertices[:, ids].cpu().numpy().astype(np.float64))
        joints.append(out.joints.cpu().numpy().astype(np.float64))
    return np.concatenate(verts), np.concatenate(joints)


def side_lean(joints: np.ndarray) -> np.ndarray:
    """(T,) radians the torso leans to the body's left (negative: right), from (T,24,3) SMPL
    joints: the pelvis-to-neck direction against the right-to-left hip axis."""
    lateral = joints[:, JOINT_INDEX["left_hip"]] - joints[:, JOINT_INDEX["right_hip"]]
    up = joints[:, JOINT_INDEX["neck"]] - joints[:, JOINT_INDEX["pelvis"]]
    cos = np.einsum("tc,tc->t", lateral, up) / (
        np.linalg.norm(lateral, axis=1) * np.linalg.norm(up, axis=1) + 1e-12)
    return np.arcsin(np.clip(cos, -1.0, 1.0))


def part_distances(verts: np.ndarray, owner: np.ndarray, chair: ChairSurface,
                   patch: float = ContactConfig.point_patch
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Distance of each part to the chair and the part's contact point on it.

    Args:
        verts: (T,N,3) m, world positions of the contact vertices of all parts.
        owner: (N,) int part index (0..K-1) of each vertex.
        chair: the chair surface.
        patch: m; the contact point is the centre of the chair points nearest to the part's
            vertices that are within ``patch`` of its nearest distance (then put back on the
            surface). A single nearest vertex jumps across a flat seat with a few degrees of
            pelvis tilt; the patch centre does not.

    Returns (T,K) float64 distance (m; the part's nearest vertex to the chair) and (T,K,3)
    float64 contact points on the chair surface.
    """
    closest = chair.closest(verts)
    dist = np.linalg.norm(closest - verts, axis=-1)  # (T,N)
    k = int(owner.max()) + 1
    # Per part: the other parts' vertices masked with +inf, all frames at once.
    masked = np.where(owner[None, None, :] == np.arange(k)[None, :, None], dist[:, None, :],
                      np.inf)  # (T,K,N)
    part_d = masked.min(axis=2)
    w = (masked <= part_d[..., None] + patch).astype(np.float64)
    centre = np.einsum("tkn,tnc->tkc", w, closest) / w.sum(axis=2)[..., None]
    return part_d, chair.closest(centre)


def _thigh_vertices(model: BodyModel) -> tuple[np.ndarray, np.ndarray]:
    """Vertex ids of the left and right thigh: skinned mostly to that hip joint (where a
    resting hand lies)."""
    weights = np.asarray(model.weights.detach().cpu().numpy() if torch.is_tensor(model.weights)
                         else model.weights)
    owner = weights.argmax(axis=1)
    return (np.flatnonzero(owner == JOINT_INDEX["left_hip"]),
            np.flatnonzero(owner == JOINT_INDEX["right_hip"]))


def palm_down(params: BodyParams) -> np.ndarray:
    """(T,2) cosine of the left/right palm's normal with straight down (world -Y): 1 for a
    palm flat on a seat, about 0 for a hand hanging beside the hips.

    SMPL's rest pose holds the arms out with the palms down, so the normal is the hand joint's
    world rotation applied to -Y; its downward component is that rotation's (1, 1) element."""
    hands = [JOINT_INDEX["left_hand"], JOINT_INDEX["right_hand"]]
    return params.bone_rotations()[:, hands, 1, 1]


def _hand_thigh_distance(left: np.ndarray, right: np.ndarray, thighs: np.ndarray,
                         chunk: int = 128) -> np.ndarray:
    """(T,2) m: nearest distance between the left/right hand's vertices (T,n,3) and the thigh
    vertices (T,m,3). Chunked over frames to bound memory (T·n·m distances)."""
    out = np.zeros((len(thighs), 2))
    for a in range(0, len(thighs), chunk):
        th = thighs[a:a + chunk, None]  # (t,1,m,3)
        for k, hand in enumerate((left, right)):
            d2 = ((hand[a:a + chunk, :, None] - th) ** 2).sum(-1)  # (t,n,m)
            out[a:a + chunk, k] = np.sqrt(d2.min(axis=(1, 2)))
    return out


# ----------------------------------------------------------------------- detection


def detect_contacts(params: BodyParams, model: BodyModel,
                    chair: ChairSurface | np.ndarray | object,
                    chair_faces: np.ndarray | None = None, *, fps: float, floor_height: float = 0.0,
                    config: ContactConfig | None = None) -> Contacts:
    """Contacts of the five parts with the chair, feet with the floor, and interaction labels.

    Args:
        params: the body motion (T frames; world metres, Y up), e.g. a session fit.
        model: its body model; ``model.contact_vertices[name]`` are the part's surface vertices
            (the coarse ``couch-body-coarse`` is ~10x faster and within millimetres).
        chair: the chair in the world: (V,3) vertices (m, world frame) with ``chair_faces``
            (F,3), a :class:`ChairSurface`, or a registered
            ``couch.capture.segmentation.ChairModel`` (mesh in its frame + world pose).
        chair_faces: (F,3) vertex indices when ``chair`` is a vertex array.
        fps: frame rate of ``params`` (thresholds in seconds become frames with it).
        floor_height: y of the floor (m).
        config: thresholds (defaults: :class:`ContactConfig`).

    Returns:
        :class:`Contacts` with T frames.
    """
    cfg = config or ContactConfig()
    if not isinstance(params, BodyParams):
        raise TypeError(f"params must be a BodyParams, got {type(params).__name__}")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps}")
    if not np.isfinite(floor_height):
        raise ValueError(f"floor_height must be finite, got {floor_height}")
    missing = [n for n in CONTACT_NAMES if n not in model.contact_vertices]
    if missing:
        raise ValueError(f"body model {getattr(model, 'name', '?')!r} has no contact vertices "
                         f"for {missing}")
    if isinstance(chair, ChairSurface):
        surface = chair
    elif hasattr(chair, "world_from_object"):
        surface = ChairSurface.from_model(chair)
    else:
        if chair_faces is None:
            raise ValueError("detect_contacts: chair vertices given without chair_faces")
        surface = ChairSurface(np.asarray(chair), chair_faces)
    t = params.num_frames
    if t == 0:
        raise ValueError("detect_contacts: the motion has no frames")

    sets = [np.asarray(model.contact_vertices[n]) for n in CONTACT_NAMES]
    ids = np.concatenate(sets)
    owner = np.concatenate([np.full(len(s), k) for k, s in enumerate(sets)])
    thighs = _thigh_vertices(model)
    raw, joints = _pose(model, params, np.concatenate([ids, *thighs]))  # (T,N+m,3)
    noise = motion_noise(raw[:, :len(ids)])
    sigma = smoothing_sigma(noise, cfg.noise_target, cfg.smooth, fps)
    # what per-frame noise is left after that smoothing, against what the guards were made for
    guard = min(1.0, _smoothed_noise(noise, sigma, fps) / cfg.noise_target)
    raw, thigh_v = raw[:, :len(ids)], _smooth(raw[:, len(ids):], sigma, fps)
    verts = _smooth(raw, sigma, fps)

    # Part centres move with the part; their speed tells resting from passing by. A longer
    # smoothing than for the distances, because differentiation amplifies per-frame noise.
    centres = np.stack([raw[:, owner == k].mean(1) for k in range(len(sets))], 1)  # (T,K,3)
    centres = _smooth(centres, sigma * cfg.speed_smooth / cfg.smooth if cfg.smooth > 0 else 0.0,
                      fps)
    speed = (np.linalg.norm(np.gradient(centres, axis=0), axis=-1) * fps if t > 1
             else np.zeros((t, len(sets))))

    distance, nearest = part_distances(verts, owner, surface, cfg.point_patch)
    active = contact_flags(distance, speed, fps, cfg, guard=guard)
    points = np.where(active[..., None], nearest, np.nan).astype(np.float32)

    # Feet on the floor: the lowest foot vertex's height; a foot on the chair is not on the
    # floor (the chair contact is the more specific one). The contact point is the centre of
    # the sole within ``point_patch`` of the lowest vertex: on a flat foot the lowest vertex
    # alone jumps between heel and toes (a mean 4.8 cm between ours and the truth's on the
    # accuracy bench's planted feet), the patch is the sole's middle, the toes as the heel
    # lifts.
    feet = [CONTACT_NAMES.index(f) for f in FEET]
    fd, fp = [], []
    for k in feet:
        foot = verts[:, owner == k]  # (T,n,3)
        y = foot[..., 1] - floor_height  # (T,n)
        low = y.min(axis=1)
        fd.append(np.maximum(low, 0.0))
        w = (y <= low[:, None] + cfg.point_patch).astype(np.float64)
        fp.append(np.einsum("tn,tnc->tc", w, foot) / w.sum(axis=1)[:, None])
    floor_distance = np.stack(fd, 1)
    floor_points = np.stack(fp, 1)
    floor_points[..., 1] = floor_height
    floor_active = contact_flags(floor_distance, speed[:, feet], fps, cfg, cfg.floor_enter,
                                 cfg.floor_leave) & ~active[:, feet]
    floor_points = np.where(floor_active[..., None], floor_points, np.nan).astype(np.float32)

    hands = [CONTACT_NAMES.index("left_hand"), CONTACT_NAMES.index("right_hand")]
    down = _smooth(palm_down(params), sigma, fps)  # (T,2)
    lap = None
    if cfg.lap_distance > 0:
        # A hand near the seat that touches a thigh rests on the lap (sitters put their hands
        # there), it does not hold on to the chair; unless it presses palm down on the seat
        # beside the thigh, below the thigh's middle (a two-hand sit on a sofa puts both palms
        # there, touching the thighs' sides as the hips come down).
        left, right = verts[:, owner == hands[0]], verts[:, owner == hands[1]]
        sides = np.split(thigh_v, [len(thighs[0])], axis=1)  # left, right thigh (T,m,3)
        per_thigh = np.stack([_hand_thigh_distance(left, right, th) for th in sides], 2)
        nearest_thigh = per_thigh.argmin(axis=2)  # (T,2) 0 left, 1 right thigh
        thigh_y = np.stack([th[..., 1].mean(1) for th in sides], 1)
        hand_y = np.stack([left[..., 1].mean(1), right[..., 1].mean(1)], 1)
        below = hand_y < np.take_along_axis(thigh_y, nearest_thigh, axis=1)
        seat_palm = below & (down > cfg.palm_down)
        lap = (per_thigh.min(axis=2) < cfg.lap_distance) & ~seat_palm
    near = contact_flags(distance[:, hands], speed[:, hands], fps, cfg, cfg.support_enter,
                         cfg.support_leave, cfg.support_min_duration)
    near &= down > cfg.palm_down  # weight goes through a palm facing the floor
    labels = interaction_labels(active, params.transl, floor_distance, fps, cfg, lap,
                                side_lean(joints), near)
    return Contacts(names=tuple(CONTACT_NAMES), active=active, points=points, labels=labels,
                    distance=distance.astype(np.float32), speed=speed.astype(np.float32),
                    floor_active=floor_active, floor_points=floor_points,
                    floor_distance=floor_distance.astype(np.float32), fps=float(fps),
                    noise=noise, guard=guard)


def walking(pelvis: np.ndarray, fps: float, config: ContactConfig | None = None) -> np.ndarray:
    """(T,) bool frames of locomotion from the (T,3) pelvis track (m, world, Y up).

    Sitting down moves the pelvis back by up to ~0.3 m at up to ~0.55 m/s, as fast as the end
    of a walk, so a speed threshold alone cannot tell them apart. A movement (horizontal speed
    above ``stop_speed``) is walking when it reaches ``walk_speed`` somewhere; all its frames
    are walking then, so the walk ends where the subject has (nearly) stopped. A movement cut
    by the recording's start or end needs only ``edge_walk_speed`` while the pelvis stays at
    one height (sitting down or standing up changes it).
    """
    cfg = config or ContactConfig()
    if len(pelvis) < 2:
        return np.zeros(len(pelvis), bool)
    horizontal = _smooth(np.asarray(pelvis, np.float64)[:, [0, 2]], cfg.walk_smooth, fps)
    speed = np.linalg.norm(np.gradient(horizontal, axis=0), axis=1) * fps
    s, e = runs(speed > cfg.stop_speed)
    height = np.asarray(pelvis, np.float64)[:, 1]
    fast = np.array([speed[a:b].max() >= cfg.walk_speed
                     or ((a == 0 or b == len(speed)) and speed[a:b].max() >= cfg.edge_walk_speed
                         and np.ptp(height[a:b]) < cfg.edge_walk_drop)
                     for a, b in zip(s, e, strict=True)], dtype=bool)
    return flip_runs(np.zeros(len(speed), bool), fast, s, e)


def _lasting(touch: np.ndarray, window: slice, reach: int) -> np.ndarray:
    """(K,) frames of the (T,K) ``touch`` flags inside ``window`` that belong to a run (within
    the window) lasting to frame ``reach`` or later."""
    out = np.zeros(touch.shape[1], np.int64)
    for k in range(touch.shape[1]):
        s, e = runs(touch[window, k])
        out[k] = (e - s)[e + window.start > reach].sum()
    return out


def interaction_labels(active: np.ndarray, pelvis: np.ndarray, foot_height: np.ndarray,
                       fps: float, config: ContactConfig | None = None,
                       hand_on_lap: np.ndarray | None = None, lean: np.ndarray | None = None,
                       hands_near: np.ndarray | None = None) -> np.ndarray:
    """Per-frame interaction labels (``couch.schema.INTERACTION_LABELS``).

    Args:
        active: (T,5) bool chair contacts in ``CONTACT_NAMES`` order.
        pelvis: (T,3) m, world track of the pelvis (SMPL ``transl`` serves: it differs from the
            pelvis joint by a constant).
        foot_height: (T,2) m, height of the left/right foot's lowest point above the floor.
        fps: frame rate.
        config: thresholds.
        hand_on_lap: (T,2) bool, left/right hand resting on a thigh (such a hand near the seat
            is not supporting on the chair); None: never.
        lean: (T,) radians the torso leans to the body's left (:func:`side_lean`); None: 0.
        hands_near: (T,2) bool, left/right hand on the chair as judged for support (looser
            thresholds than the contact flags); None: the hands' columns of ``active``.

    Returns (T,) int8: 0 outside interaction episodes. An episode is a seated period (pelvis
    contact) from where the approach walk stopped to where the next walk starts. Its label is
    5 when a foot was lifted off the floor while seated (crossed ankles or legs: a free
    interaction, whatever the hands do), else 1/2/3 when the right / left / both hands
    supported on the chair, else 4. A hand supports when it touches the chair for ``min_hand``
    s off the lap, or touches it that long (on the lap or not) while the torso leans towards it
    by ``support_lean`` as the subject sits down: a palm on the seat right beside the thigh
    touches both, and the weight it takes tilts the torso. Only touches from
    ``support_before`` s before the pelvis lands to its last seated frame count, and of those
    only the ones still on the chair ``support_gap`` s before the landing or later.
    """
    cfg = config or ContactConfig()
    active = np.asarray(active, bool)
    pelvis = np.asarray(pelvis, np.float64)
    foot_height = np.asarray(foot_height, np.float64)
    t = len(active)
    lap = np.zeros((t, 2), bool) if hand_on_lap is None else np.asarray(hand_on_lap, bool)
    lean = np.zeros(t) if lean is None else np.asarray(lean, np.float64)
    hand_cols = [CONTACT_NAMES.index("left_hand"), CONTACT_NAMES.index("right_hand")]
    hands = active[:, hand_cols] if hands_near is None else np.asarray(hands_near, bool)
    if active.shape != (t, len(CONTACT_NAMES)) or pelvis.shape != (t, 3) \
            or foot_height.shape != (t, 2) or lap.shape != (t, 2) or lean.shape != (t,) \
            or hands.shape != (t, 2):
        raise ValueError(f"interaction_labels: expected active (T,5), pelvis (T,3), foot_height "
                         f"(T,2), hand_on_lap (T,2), lean (T,), hands_near (T,2) with one T, got "
                         f"{active.shape}, {pelvis.shape}, {foot_height.shape}, {lap.shape}, "
                         f"{lean.shape}, {hands.shape}")
    labels = np.zeros(t, dtype=np.int8)
    if t < 2:
        return labels
    seated = fill_gaps(active[:, CONTACT_NAMES.index("pelvis")], _frames(cfg.merge_gap, fps))
    seated = drop_short_runs(seated, max(1, _frames(cfg.min_seated, fps)))
    walk_idx = np.flatnonzero(walking(pelvis, fps, cfg))
    off_lap = hands & ~lap  # (T,2) left, right
    min_hand = max(1, _frames(cfg.min_hand, fps))
    min_lift = max(1, _frames(cfg.min_lift, fps))
    for s, e in zip(*runs(seated), strict=True):
        # The episode reaches back to the end of the approach walk and on to the walk away.
        before = walk_idx[walk_idx < s]
        after = walk_idx[walk_idx >= e]
        ep = slice(before[-1] + 1 if len(before) else 0, after[0] if len(after) else t)
        # Crossing the legs or ankles lifts one foot above the other; both feet off the floor
        # together (a high seat, dangling legs) is no free interaction.
        lift = np.abs(foot_height[s:e, 0] - foot_height[s:e, 1]) > cfg.foot_lift
        lifted = drop_short_runs(lift, min_lift)
        # The lean while sitting down: the second before the pelvis lands and a little after.
        sit = slice(max(0, s - _frames(1.0, fps)), min(t, s + _frames(0.3, fps)))
        toward = np.array([1.0, -1.0]) * lean[sit].mean() >= np.deg2rad(cfg.support_lean)
        held = slice(max(ep.start, s - _frames(cfg.support_before, fps)), e)
        reach = s - _frames(cfg.support_gap, fps)
        left, right = (_lasting(off_lap, held, reach) >= min_hand) | (
            toward & (_lasting(hands, held, reach) >= min_hand))
        if lifted.any():
            code = FREE
        elif left and right:
            code = BOTH_HANDS
        elif right:
            code = RIGHT_HAND
        elif left:
            code = LEFT_HAND
        else:
            code = NO_HAND
        labels[ep] = code
    return labels
