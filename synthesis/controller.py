"""The runtime controller: trained PoseNet (+ ControlNet) driven frame by frame for a batch of
characters approaching one chair, sitting, and reaching a series of hand contacts.

Paper Sec. 4.5: the character approaches with the PoseNet alone; a hand's ControlNet input is
switched on once the character is within :attr:`FeatureConfig.control_radius` of that hand's
contact (the training features apply the same rule), and a "no contact" hand (NaN target) has
its control zeroed. ControlNet runs closed loop: the first active frame of a contact reads the
straight line from the hand to the contact, later frames read its own previous prediction (the
scheduled-sampling end state it was trained towards). The NSM+Control baseline runs in the same
loop with the raw contacts (``contact_inputs``) in place of ControlNet's C+, and the plain NSM
(the paper's Table 2) with no hand input at all: it walks to the same sit goal as the others
(:meth:`Scene.goals`, which moves along a sofa towards the asked contacts), and the series
advances and is scored, but the network is never told where the hands should go.

Everything is vectorised over the batch of characters (B); the loop runs over frames, as any
autoregressive controller must. Frames: world metres, +Y up, floor y = 0; the chair mesh is
given in its chair frame (DESIGN.md: seat centred on x = z = 0, facing +Z) and placed by
``world_from_chair``. Hand order is (left, right); the hands are SMPL joints 22/23.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from couch.body import (
    CONTACT_NAMES,
    JOINT_INDEX,
    PARENTS,
    load_body_model,
    rigid_transforms,
    standing_pose,
)
from couch.geometry import apply_transform, invert_transform, make_transform
from couch.rotations import matrix_to_6d, matrix_to_axis_angle, sixd_to_matrix
from couch.synthesis.data import feature_config_from_json
from couch.synthesis.features import (
    SIT,
    WALK,
    FeatureConfig,
    OccupancyGrid,
    advance_phase,
    control_in_root,
    control_line,
    control_near,
    ego_features,
    integrate_root,
    interaction_features,
    interaction_layer,
    relative_root,
    root_affine,
    root_transforms,
    root_update,
    tidy_future_trajectory,
    to_root,
    voxel_grid,
)
from couch.synthesis.foot_lock import FootLockConfig, lock_feet
from couch.synthesis.hand_ik import ArmRig, reach
from couch.synthesis.nets import first_linear
from couch.synthesis.plans import REPLAN_RADIUS, control_step
from couch.synthesis.precision import PRECISIONS, Precision, packed_copy
from couch.synthesis.train import (
    ENCODER_GROUPS,
    GATING_GROUPS,
    Which,
    load_trained,
    which_for,
)

__all__ = ["METHODS", "Scene", "SynthesisResult", "Synthesizer", "yaw_transform"]

#: Sideways distance (m) from the hips to a hand resting on the chair beside them (the
#: simulated and captured sitters' seat-edge and armrest contacts lie 22-31 cm out).
HAND_REACH_X = 0.25

#: Forward distance (m) from the hips to a hand resting on the seat ahead of them, and the seat
#: depth (m) a sitter keeps in front of the hips for the thighs: on a seat deeper than that, the
#: sit goal moves forward towards a seat contact asked farther ahead (:meth:`Scene.goals`).
#: An armrest hand rests at least ``ARMREST_REACH_Z`` ahead of the hips: for one asked farther
#: back the goal moves back, keeping ``SEAT_BACK_ROOM`` of seat behind the hips. Chosen on the
#: validation chairs (README, *Results so far*).
HAND_REACH_Z = 0.10
SEAT_FRONT_ROOM = 0.22
ARMREST_REACH_Z = 0.05
SEAT_BACK_ROOM = 0.20
#: A contact within this many metres of the seat's height is on the seat; one higher, on an
#: armrest (:meth:`Scene.goals`).
SEAT_CONTACT_BAND = 0.05

#: Synthesis methods: COUCH (ControlNet + PoseNet), the NSM+Control baseline and the plain NSM.
METHODS: tuple[str, ...] = ("couch", "baseline", "nsm")
#: The trained network each method's pose comes from (``couch-train --net``).
POSE_NET: dict[str, str] = {"couch": "pose", "baseline": "baseline", "nsm": "nsm"}

#: PoseNet's encoder of the chair's voxels (I), whose first layer the loop folds per scene.
INTERACTION_ENCODER = "I"

#: PoseNet's predictions the loop reads. The others (future goals, joint positions a second
#: ahead) are training targets only: their columns are cut from the last expert layer at load
#: (:meth:`PoseNet.select_outputs`), which the runtime would otherwise read every frame.
READ_OUTPUTS: tuple[str, ...] = (
    "next_joint_positions", "next_joint_rotations", "next_joint_velocities",
    "future_trajectory", "global_phase_update", "goal_relative_root", "next_contacts",
    "root_update")


def yaw_transform(x: float | np.ndarray, z: float | np.ndarray,
                  heading: float | np.ndarray) -> np.ndarray:
    """(..., 4, 4) root-like poses on the floor at (x, 0, z) whose forward (+Z) axis is turned
    by ``heading`` radians from world +Z towards +X."""
    update = np.stack(np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(z, np.float64),
                                          np.asarray(heading, np.float64)), -1)
    return integrate_root(np.eye(4), update)


@dataclasses.dataclass(eq=False)
class Scene:
    """One chair placed in the world, with everything the features read precomputed.

    vertices (V,3) / faces (F,3) in the chair frame; world_from_chair (4,4); occupancy (512,)
    and centres_world (512,3) of the 8^3 interaction voxels; grid the fine occupancy for E;
    goal (4,4) the sit goal root (seat centre on the floor, facing the chair's front);
    seat_half_width (m) half the seat's width along the chair's x (where a sitter may shift to);
    seat_height, seat_front, seat_back (m) the seat's top, its front and its rear edge
    (chair-frame y, z and z; NaN without a seat).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    world_from_chair: np.ndarray
    occupancy: np.ndarray
    centres_world: np.ndarray
    grid: OccupancyGrid
    goal: np.ndarray
    seat_half_width: float = 0.0
    seat_height: float = float("nan")
    seat_front: float = float("nan")
    seat_back: float = float("nan")

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, faces: np.ndarray, cfg: FeatureConfig,
                  world_from_chair: np.ndarray | None = None, name: str = "chair") -> Scene:
        """Precompute a chair (chair frame, metres) for synthesis."""
        v = np.asarray(vertices, np.float64)
        f = np.asarray(faces, np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4 or f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"{name}: expected (V,3) vertices and (F,3) faces, got "
                             f"{v.shape} and {f.shape}")
        pose = np.eye(4) if world_from_chair is None else np.asarray(world_from_chair, float)
        occupancy, centres, _ = voxel_grid(v, f, cfg.interaction_resolution,
                                           cfg.interaction_subsamples)
        grid = OccupancyGrid.from_mesh(v, f, pose, cfg.occupancy_voxel)
        goal, half, height, front, back = sit_goal(v, f)
        return cls(name, v, f, pose, occupancy, apply_transform(pose, centres), grid,
                   pose @ goal, half, height, front, back)

    def goals(self, series: np.ndarray) -> np.ndarray:
        """(B,4,4) world sit goals for (B,S,2,3) world contact series: the seat goal shifted
        along the seat so that the first set's contacts are where the sitter's hands rest,
        ``HAND_REACH_X`` to either side of the hips (a sofa's sitter sits by the armrest they
        hold), keeping 25 cm from the seat's ends; and forward on a deep seat so that the
        first set's frontmost seat contact is at most ``HAND_REACH_Z`` ahead of the hips,
        keeping ``SEAT_FRONT_ROOM`` of seat in front of them (a sofa's sitter reaching for the
        seat's front corner sits forward); then back so that its rearmost armrest contact
        (``SEAT_CONTACT_BAND`` or more above the seat) is at least ``ARMREST_REACH_Z`` ahead
        of the hips, keeping ``SEAT_BACK_ROOM`` of seat behind them (a hand on an armrest's
        middle rests beside a sitter sat back)."""
        first = apply_transform(invert_transform(self.world_from_chair),
                                np.asarray(series, np.float64)[:, 0])  # (B,2,3) chair frame
        finite = np.isfinite(first[..., 0])
        count = finite.sum(-1)
        goal_chair = invert_transform(self.world_from_chair) @ self.goal
        hips = first[..., 0] - np.array([HAND_REACH_X, -HAND_REACH_X])  # left hand is +x
        want = np.where(count > 0, np.where(finite, hips, 0.0).sum(-1)
                        / np.maximum(count, 1), goal_chair[0, 3])
        room = max(self.seat_half_width - 0.25, 0.0)
        shift = np.clip(want - goal_chair[0, 3], -room, room)
        out = np.repeat(goal_chair[None], len(first), 0)
        out[:, 0, 3] += shift
        if np.isfinite(self.seat_front):
            # the goal faces +z in the chair frame
            rise = np.nan_to_num(first[..., 1]) - self.seat_height
            on_seat = finite & (np.abs(rise) < SEAT_CONTACT_BAND)
            ahead = np.where(on_seat, first[..., 2], -np.inf).max(-1) - goal_chair[2, 3]
            room_z = max(self.seat_front - SEAT_FRONT_ROOM - goal_chair[2, 3], 0.0)
            out[:, 2, 3] += np.clip(ahead - HAND_REACH_Z, 0.0, room_z)
            above = finite & (rise >= SEAT_CONTACT_BAND)
            behind = np.where(above, first[..., 2], np.inf).min(-1) - out[:, 2, 3]
            back_z = np.minimum(self.seat_back + SEAT_BACK_ROOM - out[:, 2, 3], 0.0)
            out[:, 2, 3] += np.clip(behind - ARMREST_REACH_Z, back_z, 0.0)
        return self.world_from_chair @ out


def sit_goal(vertices: np.ndarray, faces: np.ndarray
             ) -> tuple[np.ndarray, float, float, float, float]:
    """Chair-frame sit goal: (4,4) root pose at the seat's centre (:func:`couch.augment.
    segment_parts`) on the floor, facing +Z; the seat's half width along x, its top's height
    (y), its front edge and its rear edge (z), all m. Falls back to the origin, 0 and NaNs if
    no seat is found."""
    from couch.augment import segment_parts  # heavy (trimesh, open3d); only needed here

    centre, half = np.zeros(3), 0.0
    height = front = back = float("nan")
    try:
        parts = segment_parts(vertices, faces)
        if parts.has("seat"):
            seat = parts.frames["seat"]
            centre = seat.centre
            span = seat.half_span()
            half, height = float(span[0]), float(centre[1])
            front, back = float(centre[2] + span[2]), float(centre[2] - span[2])
    except ValueError:
        pass
    return yaw_transform(centre[0], centre[2], 0.0), half, height, front, back


def walk_when_far(future: np.ndarray, root: np.ndarray, goal: np.ndarray, radius: float
                  ) -> np.ndarray:
    """The future trajectory (B,K,12) with its action labels (last 3) set to walk for the
    characters whose root (B,4,4) is farther than ``radius`` m (horizontally) from its goal
    (B,4,4); unchanged for the others, and for all with ``radius`` <= 0.

    Far from the chair the approach is the user's command, as NSM's action input is: fed its
    own labels, PoseNet once drifted into idle 3 m away and never arrived.
    """
    if radius <= 0:
        return future
    far = np.hypot(*(root[:, [0, 2], 3] - goal[:, [0, 2], 3]).T) > radius
    out = np.array(future)
    out[far, :, 9:] = np.eye(3)[WALK]
    return out


def sit_when_near(future: np.ndarray, root: np.ndarray, goal: np.ndarray, radius: float,
                  offsets: np.ndarray, facing: float = np.pi / 4) -> np.ndarray:
    """The future trajectory (B,K,12) whose action labels (last 3) are blended towards sit for
    the characters within ``radius`` m (horizontally) of their goal (B,4,4) and turned within
    ``facing`` radians of its heading: the weight of sample k is its offset (frames, (K,)
    ``offsets`` >= 0) over the last one, so the command is "seated within the next second".
    Unchanged for the others, and for all with ``radius`` <= 0.

    In the data, a sitter that close and turned sits within 0.6 s (median; 99 % within 1.7 s);
    left to its own labels, PoseNet sometimes stood there idle for the rest of the trial.
    """
    if radius <= 0:
        return future
    rel = root_update(goal, root)  # (dx, dz, dyaw) of the root in the goal's frame
    near = (np.hypot(rel[:, 0], rel[:, 1]) < radius) & (np.abs(rel[:, 2]) < facing)
    w = (np.asarray(offsets, np.float64) / max(float(np.max(offsets)), 1.0))[None, :, None]
    out = np.array(future)
    out[near, :, 9:] = (1 - w) * out[near, :, 9:] + w * np.eye(3)[SIT]
    return out


@dataclasses.dataclass
class SynthesisResult:
    """B synthesised motions of T frames at ``fps`` (world frame, metres, radians).

    goal (B,4,4) each character's sit goal root; root (B,T,4,4) world_from_root; joints
    (B,T,24,3) from the SMPL parameters (forward kinematics of the bundled body's rest
    skeleton); global_orient (B,T,3), body_pose (B,T,69) axis-angle, transl (B,T,3), betas
    (10,) (the mean shape); hands (B,T,2,3) the hand joints 22/23 the controller steered;
    targets (B,T,2,3) each frame's active contact per hand (NaN: none); control_on (B,T,2)
    whether the hand's control was on; series (B,S,2,3) the contact sets asked for, in order;
    series_index (B,T) which set was active; global_phase (B,T); contacts (B,T,5) predicted
    contact labels (pelvis, hands, feet; 0..1).
    """

    method: str
    fps: float
    scene: Scene
    goal: np.ndarray
    root: np.ndarray
    joints: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    betas: np.ndarray
    hands: np.ndarray
    targets: np.ndarray
    control_on: np.ndarray
    series: np.ndarray
    series_index: np.ndarray
    global_phase: np.ndarray
    contacts: np.ndarray

    @property
    def num_frames(self) -> int:
        return int(self.root.shape[1])


@dataclasses.dataclass
class _State:
    """Per-character controller state, every array batch-first (B)."""

    root: np.ndarray  # (B,4,4)
    goal: np.ndarray  # (B,4,4) sit goal root
    jpos: np.ndarray  # (B,22,3) root frame
    jrot: np.ndarray  # (B,22,6) root frame
    jvel: np.ndarray  # (B,22,3) m/s, root frame
    future: np.ndarray  # (B,7,12) trajectory samples at offsets >= 0, relative to root
    phase: np.ndarray  # (B,) global phase
    hist_root: np.ndarray  # (B,H,4,4) the last H roots, oldest first (H = -min offset)
    hist_action: np.ndarray  # (B,H,3)
    hist_hphase: np.ndarray  # (B,H,2) hands' local phases
    line: np.ndarray  # (B,2,7,3) ControlNet's fed-back control input
    c_phase: np.ndarray  # (B,2,7) last predicted local phases
    on: np.ndarray  # (B,2) bool, control was on last frame
    lstm: tuple[torch.Tensor, torch.Tensor] | None
    index: np.ndarray  # (B,) int, active contact set
    since: np.ndarray  # (B,) frames since that set became active
    held: np.ndarray  # (B,) frames all its hands have been within reach
    ik_offset: np.ndarray | None = None  # (B,22,3) world displacement hand IK gave last frame
    hands: np.ndarray | None = None  # (B,2,3) world hand joints of the current pose


class Synthesizer:
    """Loads a trained run (``couch-train`` output) and synthesises motions with it.

    Args:
        run_dir: the run folder. ``method`` "couch" needs its ``pose`` and ``control`` nets,
            "baseline" its ``baseline`` net, "nsm" its ``nsm`` net. ``which``: their checkpoints,
            "best", "last" or an epoch number (kept by ``couch-train --keep-epochs``), or per
            network (``{"pose": 14, "control": "best"}``; see
            :func:`couch.synthesis.train.parse_which`).
        hold: seconds a contact set is held (all its hands within ``reach`` m) before the next
            set of a series starts; ``timeout``: seconds after which it starts anyway.
        blend_radius: bidirectional control (NSM, which COUCH's goal-relative root output is
            for): within this many metres of the sit goal the next root is blended from the
            ego-centric update towards the network's goal-relative prediction of it, with weight
            (sit action) x (1 - distance / radius); 0 turns it off.
        walk_radius: farther than this (m) from the sit goal, the predicted trajectory's
            action labels are set to walk before they are fed back (the approach is the
            command, as NSM's action input); 0 leaves them to the network.
        sit_radius: nearer than this (m) to the sit goal and turned to within 45 degrees of
            its heading, the predicted trajectory's action labels are blended towards sit
            before they are fed back (:func:`sit_when_near`: the sit is the command there, as
            the walk is far away); 0 leaves them to the network.
        replan: ControlNet reads its own last plan of each hand as its next input (as at
            the end of its scheduled-sampling training); where that plan's present sample is more
            than this many metres from the hand, it reads the straight line from the hand to
            the contact instead, as when the control switches on (:func:`replan_lost`); 0
            never replans.
        hand_ik: "couch" only: each frame, two-bone arm IK moves each controlled palm the
            fraction (ControlNet's local phase of that hand, or PoseNet's probability that the
            pelvis is on the seat if higher) of the way onto its contact
            (:mod:`couch.synthesis.hand_ik`; the fitting the paper's appendix suggests and
            leaves out of its evaluation). Off by default: the networks alone.
        precision: the networks' large layers at run time (:mod:`couch.synthesis.precision`,
            CPU only): "fp32" as trained; "fp16" (joints within ~0.1 mm of fp32's over 4 s,
            2.4x the frames/s of one character; its evaluation equals fp32's); "int8" (within
            ~0.3 cm, 3.5x; it changes the motion: over 384 evaluation trials as many contacts
            reached, but fewer trials sat and the feet slid more).
        foot_lock: after synthesis, keep each planted foot in place by leg IK (on a leash: a
            foot the network moves on is dragged after it; :mod:`couch.synthesis.foot_lock`; a
            post-process the networks do not see, so the path and the hands are
            unchanged). Off by default: the networks alone. True uses the default plant rule
            and leash; a :class:`~couch.synthesis.foot_lock.FootLockConfig` sets them (a
            character whose ankles stand higher than SMPL's ~7 cm needs a higher ``height``).
    """

    def __init__(self, run_dir: str | Path, method: str = "couch", *, which: Which = "best",
                 device: str = "cpu", hold: float = 1.0, reach: float = 0.05,
                 timeout: float = 5.0, blend_radius: float = 1.0, walk_radius: float = 2.0,
                 sit_radius: float = 0.4, replan: float = REPLAN_RADIUS,
                 hand_ik: bool = False, precision: Precision = "fp32",
                 foot_lock: bool | FootLockConfig = False) -> None:
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
        if hand_ik and method != "couch":
            raise ValueError(f"hand_ik weights the IK by ControlNet's phases: method 'couch' "
                             f"only, not {method!r}")
        self.method, self.device = method, torch.device(device)
        if precision not in PRECISIONS:
            raise ValueError(f"unknown precision {precision!r}; choose from "
                             f"{', '.join(PRECISIONS)}")
        if precision != "fp32" and self.device.type != "cpu":
            raise ValueError(f"precision {precision!r} runs fbgemm's CPU kernels; on "
                             f"{self.device} use fp32")
        self.run_dir = Path(run_dir)
        net = POSE_NET[method]
        self.pose_net, self.pose_stats, meta = load_trained(run_dir, net, which_for(which, net),
                                                            device)
        self.precision = precision
        self.cfg = feature_config_from_json(json.dumps(meta["feature_config"]))
        self.groups_out = list(meta["groups_out"])
        self.widths = {g: int(self.pose_stats.mean[g].size) for g in self.groups_out}
        self._setup_io(net)
        self.pose_net = packed_copy(self.pose_net, precision)
        offsets = self.cfg.trajectory_offsets
        self._past_offsets = offsets[offsets < 0]  # the trajectory's past samples (frames)
        self._future_offsets = offsets[self.cfg.future_samples]
        self.control_net, self.control_line_end = None, 0.0
        if method == "couch":
            self.control_net, self.control_stats, control_meta = load_trained(
                run_dir, "control", which_for(which, "control"), device)
            # ControlNet's own features: a run may pair it with another run's PoseNet
            self.control_line_end = feature_config_from_json(
                json.dumps(control_meta["feature_config"])).control_line_end
            self.control_net = packed_copy(self.control_net, precision)
        self.hold, self.reach, self.timeout = hold, reach, timeout
        self.blend_radius, self.walk_radius = blend_radius, walk_radius
        self.sit_radius, self.replan = sit_radius, replan
        self.hand_ik = hand_ik
        self.foot_lock = FootLockConfig() if foot_lock is True else foot_lock or None
        self._body_setup()

    def _setup_io(self, net: str) -> None:
        """PoseNet's input and output plumbing, once: per encoder input (and gating feature)
        its groups with their normalisation concatenated, and the read predictions' columns
        (the others cut from the net) with their denormalisation."""
        stats = self.pose_stats
        inputs = {**ENCODER_GROUPS[net], **{g: (g,) for g in GATING_GROUPS[net]}}
        # The interaction encoder's first layer is affine in the root pose for a given chair
        # (features.interaction_layer): folded per scene, its (512, 2048) weights are not read
        # every frame, nor I built and normalised.
        if inputs.pop(INTERACTION_ENCODER) != ("interaction",):
            raise ValueError(f"{self.run_dir}: encoder {INTERACTION_ENCODER} must read the "
                             f"interaction group alone")
        encoder = self.pose_net.encoders[INTERACTION_ENCODER]
        layer = encoder[first_linear(encoder)]
        self._interaction = (layer.weight.detach().double().cpu().numpy(),
                             layer.bias.detach().double().cpu().numpy(),
                             stats.mean["interaction"], stats.std["interaction"])
        self._folded: tuple[Scene, np.ndarray] | None = None
        self._inputs = {name: (names, np.concatenate([stats.mean[g] for g in names]),
                               np.concatenate([stats.std[g] for g in names]))
                        for name, names in inputs.items()}
        ends = dict(zip(self.groups_out, np.cumsum([self.widths[g] for g in self.groups_out]),
                        strict=True))
        read = [g for g in self.groups_out if g in READ_OUTPUTS]
        columns: list[int] = []
        self._outputs: dict[str, slice] = {}
        for g in read:
            self._outputs[g] = slice(len(columns), len(columns) + self.widths[g])
            columns.extend(range(int(ends[g]) - self.widths[g], int(ends[g])))
        self.pose_net.select_outputs(columns)
        self._out_mean = np.concatenate([stats.mean[g] for g in read])
        self._out_std = np.concatenate([stats.std[g] for g in read])

    def _interaction_first(self, scene: Scene, root: np.ndarray) -> torch.Tensor:
        """(B, width) the interaction encoder's first layer for roots (B,4,4) in ``scene``:
        its folded map (computed once per scene) times :func:`root_affine`."""
        if self._folded is None or self._folded[0] is not scene:
            self._folded = (scene, interaction_layer(scene.occupancy, scene.centres_world,
                                                     *self._interaction))
        return torch.as_tensor((root_affine(root) @ self._folded[1].T).astype(np.float32),
                               device=self.device)

    def _pose_inputs(self, groups: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        """PoseNet's normalised inputs (:func:`couch.synthesis.train.pose_inputs` of the
        normalised groups) from the raw feature groups, each (B, ...), but the interaction
        encoder's (see :meth:`_interaction_first`)."""
        batch = len(next(iter(groups.values())))
        out = {}
        for name, (names, mean, std) in self._inputs.items():
            x = np.concatenate([groups[g].reshape(batch, -1) for g in names], -1)
            out[name] = torch.as_tensor(((x - mean) / std).astype(np.float32),
                                        device=self.device)
        return out

    # ------------------------------------------------------------------ body helpers

    def _body_setup(self) -> None:
        model = load_body_model("couch-body")
        self.betas = np.zeros(10, np.float32)
        rest = model.rest_joints(torch.zeros(1, 10, dtype=model.dtype))[0].double()
        self.rest = rest.numpy()  # (24,3)
        self.parents = torch.as_tensor(np.asarray(PARENTS), dtype=torch.long)
        wrists = [JOINT_INDEX["left_wrist"], JOINT_INDEX["right_wrist"]]
        self.wrists = np.array(wrists)
        # Hand joints 22/23 hang off the wrists by their rest offsets (rotated by the wrists).
        self.hand_offsets = self.rest[list(self.cfg.hand_joints)] - self.rest[wrists]
        template = model.v_template.double().numpy()
        palms = [template[model.contact_vertices[f"{side}_hand"]].mean(0)
                 for side in ("left", "right")]
        self.arm_rig = ArmRig(rest=self.rest, palm=np.stack(palms) - self.rest[wrists])
        out = model(global_orient=np.zeros((1, 3)), body_pose=standing_pose()[None])
        joints = out.joints[0].detach().double().numpy()
        joints[:, 1] -= out.vertices[0, :, 1].min().item()  # feet on the floor
        rots = out.joint_transforms[0, :, :3, :3].detach().double().numpy()
        root = root_transforms(joints)
        self.init_jpos = to_root(joints[:self.cfg.num_joints], root)
        self.init_jrot = matrix_to_6d(root[:3, :3].T @ rots[:self.cfg.num_joints])

    def _hands(self, root: np.ndarray, jpos: np.ndarray, jrot: np.ndarray) -> np.ndarray:
        """(B,2,3) world hand joints from root (B,4,4) and root-frame J (B,22,3)/(B,22,6)."""
        wrist_rot = sixd_to_matrix(jrot[:, self.wrists])  # (B,2,3,3) root frame
        local = jpos[:, self.wrists] + np.einsum("bhij,hj->bhi", wrist_rot, self.hand_offsets)
        return apply_transform(root, local)

    def smpl(self, root: np.ndarray, jpos: np.ndarray, jrot: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """SMPL parameters from (N,4,4) roots and root-frame J: global_orient (N,3), body_pose
        (N,69) (hand joints 22/23 at rest), transl (N,3) and FK joints (N,24,3), all world."""
        n = len(root)
        rel = sixd_to_matrix(np.asarray(jrot, np.float64))  # (N,22,3,3)
        world = np.einsum("nij,nkjl->nkil", root[:, :3, :3], rel)
        parent = np.asarray(PARENTS[1:self.cfg.num_joints])
        local = np.einsum("nkji,nkjl->nkil", world[:, parent], world[:, 1:])
        body = np.zeros((n, 23, 3))
        body[:, :self.cfg.num_joints - 1] = matrix_to_axis_angle(local)
        global_orient = matrix_to_axis_angle(world[:, 0])
        pelvis = apply_transform(root, jpos[:, :1])[:, 0]
        transl = pelvis - self.rest[0]
        rots = np.concatenate([world[:, :1], local, np.broadcast_to(np.eye(3), (n, 2, 3, 3))],
                              axis=1)
        fk, _ = rigid_transforms(torch.as_tensor(rots),
                                 torch.as_tensor(self.rest).expand(n, -1, -1), self.parents)
        return global_orient, body.reshape(n, 69), transl, fk.numpy() + transl[:, None]

    # ------------------------------------------------------------------ the loop

    def _initial_state(self, goal: np.ndarray, starts: np.ndarray, batch: int) -> _State:
        cfg = self.cfg
        root = yaw_transform(starts[:, 0], starts[:, 1], starts[:, 2])
        h = int(-cfg.trajectory_offsets.min())
        fut = cfg.trajectory_offsets[cfg.future_samples]
        # The first second's trajectory walks straight at the goal at 1 m/s: the network's own
        # prediction takes over after one frame.
        to_goal = to_root(goal[:, None, :3, 3], root)[:, 0]  # (B,3)
        heading = np.arctan2(to_goal[:, 0], to_goal[:, 2])
        dist = np.minimum(np.hypot(to_goal[:, 0], to_goal[:, 2])[:, None], fut[None] / cfg.fps)
        future_root = root[:, None] @ yaw_transform(dist * np.sin(heading)[:, None],
                                                    dist * np.cos(heading)[:, None],
                                                    heading[:, None] * np.ones_like(dist))
        walk = np.broadcast_to(np.eye(3)[1], (batch, len(fut), 3))
        future = np.concatenate([relative_root(root[:, None], future_root), walk], -1)
        idle = np.broadcast_to(np.eye(3)[0], (batch, h, 3)).copy()
        state = _State(
            root=root, goal=goal,
            jpos=np.broadcast_to(self.init_jpos, (batch, *self.init_jpos.shape)).copy(),
            jrot=np.broadcast_to(self.init_jrot, (batch, *self.init_jrot.shape)).copy(),
            jvel=np.zeros((batch, cfg.num_joints, 3)), future=future, phase=np.zeros(batch),
            hist_root=np.repeat(root[:, None], h, 1), hist_action=idle,
            hist_hphase=np.zeros((batch, h, 2)),
            line=np.zeros((batch, 2, cfg.control_samples, 3)),
            c_phase=np.zeros((batch, 2, cfg.control_samples)), on=np.zeros((batch, 2), bool),
            lstm=None, index=np.zeros(batch, np.int64), since=np.zeros(batch, np.int64),
            held=np.zeros(batch, np.int64))
        state.hands = self._hands(root, state.jpos, state.jrot)
        return state

    def _control(self, s: _State, hands: np.ndarray, targets: np.ndarray, mask: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """ControlNet step: C+ (B,2,7,3) and phases (B,2,7), zero for hands whose control is
        off; resets the LSTM of characters whose control just switched on."""
        cfg, batch = self.cfg, len(hands)
        net = self.control_net
        assert net is not None
        straight = control_line(hands, np.where(mask[..., None], targets, 0.0), mask, s.root,
                                cfg.control_samples, self.control_line_end)
        if s.lstm is None:
            s.lstm = net.initial_state(batch, self.device)
        past = s.hist_hphase[:, s.hist_hphase.shape[1] + self._past_offsets]
        pos, ph, s.lstm = control_step(
            net, self.control_stats, s.lstm, s.jpos, straight=straight, plan=s.line,
            phases=s.c_phase, past_phases=past, on=s.on, mask=mask, replan=self.replan,
            device=self.device)
        s.line, s.c_phase = pos, ph
        return pos, ph

    def _state_features(self, scene: Scene, s: _State, interaction: bool = True
                        ) -> dict[str, np.ndarray]:
        """PoseNet's J, T, G, I, E and global phase of the current state, as training builds
        them (:func:`couch.synthesis.features.sequence_features`), each (B, ...); without I
        unless ``interaction`` (the loop folds it into the network's first layer)."""
        cfg, batch = self.cfg, len(s.root)
        # T: past samples from the history, the present and future from the last prediction.
        past_idx = s.hist_root.shape[1] + self._past_offsets
        past_roots = s.hist_root[:, past_idx]
        traj = np.concatenate([
            np.concatenate([relative_root(s.root[:, None], past_roots),
                            s.hist_action[:, past_idx]], -1), s.future], 1)  # (B,13,12)
        fut_rel = s.future[..., :9]
        fut_roots = s.root[:, None] @ make_transform(sixd_to_matrix(fut_rel[..., 3:]),
                                                     fut_rel[..., :3])
        sample_roots = np.concatenate([past_roots, fut_roots], 1)
        goals = np.concatenate([relative_root(sample_roots, s.goal[:, None]),
                                np.broadcast_to(np.eye(3)[SIT], (batch, len(traj[0]), 3))], -1)
        out = {"joint_positions": s.jpos, "joint_rotations": s.jrot,
               "joint_velocities": s.jvel, "trajectory": traj, "goals": goals,
               "ego": ego_features(scene.grid, s.root, cfg), "global_phase": s.phase[:, None]}
        if interaction:
            out["interaction"] = interaction_features(scene.occupancy, scene.centres_world,
                                                      s.root)
        return out

    def _next_root(self, s: _State, out: dict[str, np.ndarray]) -> np.ndarray:
        """(B,4,4) next world roots: the ego-centric root update, pulled near the goal towards
        the goal-relative prediction of the same root. The ego-centric update integrates its
        small errors over the approach; the goal-relative one is trained on where the data's
        roots were relative to their goal, so close to it, it pins the sitter to the seat the
        way the data sat."""
        ego = integrate_root(s.root, out["root_update"])
        if self.blend_radius <= 0 or "goal_relative_root" not in out:
            return ego
        rel = out["goal_relative_root"]
        inverse = s.goal @ make_transform(sixd_to_matrix(rel[:, 3:9]), rel[:, :3])
        dist = np.hypot(*(s.root[:, [0, 2], 3] - s.goal[:, [0, 2], 3]).T)
        # Gated by the sit action as ROAM's l-NSM does: while walking and turning in front of
        # the chair the goal-relative prediction pulls towards where the data stood, not sat.
        sit = np.clip(s.future[:, 0, 9 + SIT], 0.0, 1.0)
        w = sit * np.clip(1.0 - dist / self.blend_radius, 0.0, 1.0)
        # The fraction w of the step from ego to inverse: positions linearly, yaw the short way.
        return integrate_root(ego, w[:, None] * root_update(ego, inverse))

    def _step(self, scene: Scene, s: _State, series: np.ndarray) -> dict[str, np.ndarray]:
        cfg, batch = self.cfg, len(s.root)
        rows = np.arange(batch)
        targets = series[rows, s.index]  # (B,2,3)
        has = np.all(np.isfinite(targets), -1)
        mask = has & control_near(s.root, np.where(has[..., None], targets, np.inf),
                                  cfg.control_radius)
        hands = s.hands
        safe = np.where(mask[..., None], targets, 0.0)

        groups = self._state_features(scene, s, interaction=False)
        if self.method == "couch":
            pos, ph = self._control(s, hands, targets, mask)
            groups["control_root_positions"] = control_in_root(pos, to_root(safe, s.root), mask)
            groups["control_phases"] = ph
            hand_phase = ph[..., 0]
        elif self.method == "nsm":
            hand_phase = np.zeros(mask.shape)  # no hand input: its history stays empty
        else:
            rel = np.where(mask[..., None], to_root(safe, s.root), 0.0)
            groups["contact_inputs"] = np.concatenate([rel.reshape(batch, 6), mask], -1)
            groups["hand_mask"] = mask.astype(np.float64)
            hand_phase = mask.astype(np.float64)
        with torch.no_grad():
            pred, _ = self.pose_net(self._pose_inputs(groups), {
                INTERACTION_ENCODER: self._interaction_first(scene, s.root)})
        pred = pred.cpu().numpy().astype(np.float64) * self._out_std + self._out_mean
        out = {g: pred[:, columns] for g, columns in self._outputs.items()}

        # Advance: history, root, J, trajectory, phase.
        s.hist_root = np.concatenate([s.hist_root[:, 1:], s.root[:, None]], 1)
        s.hist_action = np.concatenate([s.hist_action[:, 1:], s.future[:, :1, 9:]], 1)
        s.hist_hphase = np.concatenate([s.hist_hphase[:, 1:], hand_phase[:, None]], 1)
        s.root = self._next_root(s, out)
        s.jpos = out["next_joint_positions"].reshape(batch, -1, 3)
        s.jrot = out["next_joint_rotations"].reshape(batch, -1, 6)
        s.jvel = out["next_joint_velocities"].reshape(batch, -1, 3)
        if self.hand_ik:
            # The contacts in the new root's frame, which the predicted pose is expressed in.
            goals = np.where(mask[..., None], to_root(safe, s.root), 0.0)
            # ControlNet's phase times the hand in; once PoseNet has the pelvis on the seat the
            # asked contact is held whatever the phase (ControlNet's phase stayed near 0.3 in
            # a fifth of the evaluation's trials, leaving seated palms ~10 cm off).
            seated_p = np.clip(out["next_contacts"][:, CONTACT_NAMES.index("pelvis")], 0.0, 1.0)
            weight = np.maximum(hand_phase, seated_p[:, None])
            rot, moved = reach(s.jpos[:, 0], sixd_to_matrix(s.jrot), goals,
                               weight * mask, self.arm_rig)
            s.jrot = matrix_to_6d(rot)
            delta = np.zeros_like(s.jpos)
            for j, d in moved.items():
                delta[:, j] = d
            s.jpos = s.jpos + delta
            # The fed-back velocities are those of the joints as moved: PoseNet's plus the
            # change of the IK displacement since the last frame (world, into the new root).
            world = np.einsum("bij,bkj->bki", s.root[:, :3, :3], delta)
            prev = np.zeros_like(world) if s.ik_offset is None else s.ik_offset
            s.jvel = s.jvel + cfg.fps * np.einsum("bji,bkj->bki", s.root[:, :3, :3],
                                                  world - prev)
            s.ik_offset = world
        fut = tidy_future_trajectory(out["future_trajectory"].reshape(batch, -1, 12))
        s.future = sit_when_near(walk_when_far(fut, s.root, s.goal, self.walk_radius), s.root,
                                 s.goal, self.sit_radius, self._future_offsets)
        seated = (out["next_contacts"][:, CONTACT_NAMES.index("pelvis")] > 0.5) | (
            fut[:, 0, 9 + SIT] > 0.5)
        s.phase = advance_phase(s.phase, out["global_phase_update"][:, 0], seated)
        s.on = mask

        # Series: the next contact set once this one was held (or timed out).
        new_hands = s.hands = self._hands(s.root, s.jpos, s.jrot)
        close = np.linalg.norm(new_hands - safe, axis=-1) <= self.reach
        all_close = mask.any(-1) & np.all(close | ~mask, -1)
        s.held = np.where(all_close, s.held + 1, s.held)
        s.since = np.where(mask.any(-1), s.since + 1, s.since)
        done = (s.held >= self.hold * cfg.fps) | (s.since >= self.timeout * cfg.fps)
        advance = done & (s.index < series.shape[1] - 1)
        s.index = np.where(advance, s.index + 1, s.index)
        s.held = np.where(advance, 0, s.held)
        s.since = np.where(advance, 0, s.since)
        s.on = s.on & ~advance[:, None]  # a new set starts from its straight line
        return {"root": s.root, "jpos": s.jpos, "jrot": s.jrot, "hands": new_hands,
                "targets": np.where(has[..., None], targets, np.nan), "on": mask,
                "index": s.index, "phase": s.phase,
                "contacts": np.clip(out["next_contacts"], 0.0, 1.0)}

    def synthesize(self, scene: Scene, starts: np.ndarray, series: np.ndarray,
                   seconds: float = 16.0, progress: bool = False) -> SynthesisResult:
        """Run B characters for ``seconds``.

        Args:
            scene: the chair (:meth:`Scene.from_mesh`, built with ``self.cfg``).
            starts: (B,3) start (x, z, heading) on the floor, world metres / radians (heading
                turns +Z towards +X).
            series: (B,S,2,3) or (S,2,3) contact sets in world metres, followed in order; a
                NaN row is a "no contact" hand.
        """
        starts = np.atleast_2d(np.asarray(starts, np.float64))
        series = np.asarray(series, np.float64)
        if series.ndim == 3:
            series = np.broadcast_to(series, (len(starts), *series.shape))
        if starts.shape[1:] != (3,) or series.shape[2:] != (2, 3) or len(series) != len(starts):
            raise ValueError(f"starts must be (B,3) and series (B,S,2,3); got {starts.shape} "
                             f"and {series.shape}")
        frames = round(seconds * self.cfg.fps)
        if frames < 1:
            raise ValueError(f"seconds must give at least one frame, got {seconds}")
        goal = scene.goals(series)
        state = self._initial_state(goal, starts, len(starts))
        steps = []
        for _ in tqdm(range(frames), desc="synthesis", unit="frame", disable=not progress):
            steps.append({k: np.copy(v) for k, v in self._step(scene, state, series).items()})
        stack = {k: np.stack([st[k] for st in steps], 1) for k in steps[0]}
        b, t = stack["root"].shape[:2]
        if self.foot_lock:
            stack["jpos"], stack["jrot"], _ = lock_feet(stack["root"], stack["jpos"],
                                                        stack["jrot"], self.rest, self.cfg.fps,
                                                        self.foot_lock)
        flat = [stack[k].reshape(b * t, *stack[k].shape[2:]) for k in ("root", "jpos", "jrot")]
        go, bp, tr, joints = self.smpl(*flat)
        return SynthesisResult(
            method=self.method, fps=self.cfg.fps, scene=scene, goal=goal, root=stack["root"],
            joints=joints.reshape(b, t, -1, 3), global_orient=go.reshape(b, t, 3),
            body_pose=bp.reshape(b, t, 69), transl=tr.reshape(b, t, 3), betas=self.betas,
            hands=stack["hands"], targets=stack["targets"], control_on=stack["on"],
            series=np.array(series), series_index=stack["index"],
            global_phase=stack["phase"], contacts=stack["contacts"])
