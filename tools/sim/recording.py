"""Recording a simulated session: what the rig's cameras and IMU suit write to disk.

Called by :func:`couch.tools.sim.session.simulate_session` once the sequence and its ground truth
exist. Cameras are hardware-synchronised (one master, the rest subordinate) and capture every
frame at the same instant on the Kinect master clock; each device stamps it on its own device
clock (a per-device offset from the master plus microsecond jitter), as real recordings do. The
IMU suit records on its own drifting clock.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from tqdm import tqdm

from couch.atomic import atomic_path
from couch.body import BodyModel
from couch.capture.azure_calibration import CameraIntrinsics, KinectCalibration
from couch.capture.azure_mkv import AzureMkvWriter
from couch.capture.behave import BehaveWriter, FrameImages
from couch.capture.charuco import BoardSpec, board_corners_3d
from couch.capture.mvnx import write_mvnx
from couch.capture.registration import project_points, register_depth_to_color
from couch.capture.xbus import write_device_map
from couch.geometry import apply_transform, invert_transform, make_transform
from couch.schema import ProcessedSession
from couch.tools.sim.chairs import make_room
from couch.tools.sim.clothing import (
    CLOTHING_FILE,
    bare,
    clothed_vertices,
    make_clothing,
    save_clothing,
)
from couch.tools.sim.ik import frame_from
from couch.tools.sim.imu import ImuConfig, body_track_from_model, simulate_mvnx, simulate_xbus
from couch.tools.sim.kinect import (
    LABEL_BACKGROUND,
    LABEL_CHAIR,
    LABEL_PERSON,
    DepthNoise,
    Light,
    SceneMesh,
    SimScene,
    board_mesh,
    build_scene,
    place_cameras,
    render_color,
    render_depth,
    skip_color,
    world_from_color,
)
from couch.tools.sim.motion import DENSE_HZ
from couch.tools.sim.truth import motion_in_world

if TYPE_CHECKING:
    from couch.tools.sim.session import SessionConfig, SimulatedSequence

# Garment groups by dominant joint: shirt on the torso and arms, trousers on the legs.
_SHIRT = ("spine1", "spine2", "spine3", "left_collar", "right_collar", "left_shoulder",
          "right_shoulder", "left_elbow", "right_elbow", "neck")
_TROUSERS = ("pelvis", "left_hip", "right_hip", "left_knee", "right_knee")
_SHOES = ("left_ankle", "right_ankle", "left_foot", "right_foot")


def _scaled(config: Any, scale: float, fields: tuple[str, ...]) -> Any:
    return dataclasses.replace(config, **{f: getattr(config, f) * scale for f in fields})


def depth_noise(scale: float) -> DepthNoise:
    """The default Azure-like depth artefacts, their magnitudes times ``scale`` (0: exact)."""
    if scale <= 0:
        return DepthNoise.none()
    return _scaled(DepthNoise(), scale, ("sigma_a", "sigma_b", "offset_std", "scale_std",
                                         "radial_std", "lateral_px", "dropout"))


def imu_config(scale: float, clock_offset: float, drift_ppm: float,
               misalignment: float = 1.0) -> ImuConfig:
    """The default IMU errors times ``scale`` (0: a perfect suit), on the given clock, the
    per-segment calibration error (``misalignment_deg``) times ``misalignment`` as well."""
    if scale <= 0:
        return ImuConfig.perfect(clock_offset=clock_offset, drift_ppm=drift_ppm)
    base = ImuConfig(clock_offset=clock_offset, drift_ppm=drift_ppm)
    base = dataclasses.replace(base, misalignment_deg=base.misalignment_deg * misalignment)
    return _scaled(base, scale, (
        "heading_drift_deg_per_min", "heading_walk_deg_per_sqrt_min", "misalignment_deg",
        "tilt_noise_deg", "heading_noise_deg", "position_walk_m_per_sqrt_min",
        "vertical_bias_std", "acc_noise_density", "gyro_noise_density", "acc_bias_std",
        "gyro_bias_std", "corrupt_rate", "truncate_rate", "drop_rate"))


def person_colors(model: BodyModel, rng: np.random.Generator) -> np.ndarray:
    """(V,3) RGB albedo: skin, a shirt, trousers and shoes, by each vertex's dominant joint."""
    dominant = model.weights.argmax(1).numpy()
    names = np.asarray(model.joint_names)[dominant]
    skin = np.array([rng.uniform(0.45, 0.9), rng.uniform(0.3, 0.7), rng.uniform(0.2, 0.55)])
    skin[1] = min(skin[1], skin[0] * 0.85)
    skin[2] = min(skin[2], skin[1] * 0.9)
    shirt, trousers = rng.uniform(0.05, 0.9, 3), rng.uniform(0.05, 0.5, 3)
    colors = np.tile(skin, (len(names), 1))
    colors[np.isin(names, _SHIRT)] = shirt
    colors[np.isin(names, _TROUSERS)] = trousers
    colors[np.isin(names, _SHOES)] = rng.uniform(0.05, 0.25) * np.ones(3)
    return colors


def _board_poses(rng: np.random.Generator, rig: list[tuple[KinectCalibration, np.ndarray]],
                 centre: np.ndarray, count: int, spec: BoardSpec) -> list[np.ndarray]:
    """World-from-board poses held up around ``centre`` as an operator does for a multi-camera
    calibration: each faces between two neighbouring cameras in turn (with some tilt), close
    enough that both colour cameras see the whole pattern, so every pair of neighbours shares
    views and the calibration can link every camera to the others.

    A candidate pose is kept only when all ChArUco corners project inside both cameras' colour
    images (with a margin) and each camera sees the printed face at under 60° incidence; of the
    first 12 such candidates the one nearest to the cameras is used (after 200 candidates
    without one, the best-seen). Nearer boards give sharper corners and better-posed PnP.
    """
    cams = [pose for _, pose in rig]
    colours = [world_from_color(c, p) for c, p in rig]
    corners = board_corners_3d(spec)
    w, h = spec.size
    margin_px = 25.0
    poses = []
    # neighbours around the rig, by azimuth about the centre
    order = np.argsort([np.arctan2(c[0, 3] - centre[0], c[2, 3] - centre[2]) for c in cams])
    for k in range(count):
        pair = (order[k % len(cams)], order[(k + 1) % len(cams)])
        eyes = np.stack([cams[c][:3, 3] for c in pair])
        best, best_key = None, (-np.inf, 0.0)
        passed = 0
        for _ in range(200):
            # somewhere between the pair's tripods, pulled in towards the chair
            along = eyes[0] + rng.uniform(0.3, 0.7) * (eyes[1] - eyes[0])
            inward = (centre - along) * np.array([1.0, 0.0, 1.0])
            pos = along + rng.uniform(0.35, 0.8) * inward
            pos[1] = centre[1] + rng.uniform(0.0, 0.6)
            face = eyes.mean(axis=0) - pos
            face /= np.linalg.norm(face)
            tilt = rng.normal(0, 0.15, 3)
            face = face + tilt - (tilt @ face) * face
            face /= np.linalg.norm(face)
            # board +Z points into the board: away from the camera; +Y (down the columns) ≈ down
            rot = frame_from(-face, np.array([0.0, -1.0, 0.0]))  # columns: z, y, x
            z_axis, y_axis = rot[:, 0], rot[:, 1]
            r = np.stack([np.cross(y_axis, z_axis), y_axis, z_axis], axis=1)
            pose = make_transform(r, pos - r @ np.array([w / 2, h / 2, 0.0]))
            score = min(_board_visibility(pose, corners, rig[c][0].color, colours[c], margin_px)
                        for c in pair)
            # of the candidates both cameras see whole, the nearest to the farther camera
            key = (min(score, 0.0), -np.linalg.norm(eyes - pos, axis=1).max())
            if key > best_key:
                best, best_key = pose, key
            passed += score >= 0.0
            if passed >= 12:
                break
        poses.append(best)
    return poses


def _board_visibility(world_from_board: np.ndarray, corners: np.ndarray,
                      intrinsics: CameraIntrinsics, world_from_cam: np.ndarray,
                      margin_px: float) -> float:
    """How well one colour camera sees a board: >= 0 when every corner (N,3, board frame)
    projects at least ``margin_px`` inside the image and the face is seen at < 60° incidence;
    negative (the shortfall in pixels, or -1000 when seen edge-on/from behind) otherwise."""
    cam_from_board = invert_transform(world_from_cam) @ world_from_board
    to_board = cam_from_board[:3, 3] / np.linalg.norm(cam_from_board[:3, 3])
    # the printed face's normal is the board's -Z; the camera must look at it head-on enough
    if to_board @ cam_from_board[:3, 2] < np.cos(np.radians(60.0)):
        return -1000.0
    uv, valid = project_points(apply_transform(cam_from_board, corners), intrinsics)
    if not valid.all():
        return -1000.0
    inside = np.minimum.reduce([uv[:, 0], uv[:, 1], intrinsics.width - 1 - uv[:, 0],
                                intrinsics.height - 1 - uv[:, 1]])
    return float(inside.min() - margin_px)


BEHAVE_DATE = "Date01"


def behave_sequence_name(cfg: SessionConfig, seq: SimulatedSequence) -> str:
    """``<Date>_<Sub>_<object>_<action>`` as BEHAVE names its sequences."""
    return (f"{BEHAVE_DATE}_Sub{cfg.seed % 100:02d}_chair{seq.chair_kind}_"
            f"{seq.motion.interaction.replace('_', '')}")


def _writer_options(cfg: SessionConfig, device: int, calibration: bool = False
                    ) -> dict[str, Any]:
    """MKV writer settings: sync role, colour on or off, and seeded UIDs and a fixed creation
    date so that the same seed writes the same bytes. The ChArUco captures always record colour
    (the board is detected in it)."""
    start = _dt.datetime(2026, 1, 1, 12, 0, tzinfo=_dt.UTC) + _dt.timedelta(minutes=cfg.seed)
    options: dict[str, Any] = {
        "fps": round(cfg.fps), "wired_sync_mode": "MASTER" if device == 0 else "SUBORDINATE",
        "uid_seed": cfg.seed * 1000 + device * 2 + calibration,
        "creation_time": start - _dt.timedelta(minutes=5) if calibration else start}
    if not (cfg.color or calibration):
        options["color"] = False
    return options


def record_session(out: Path, cfg: SessionConfig, seq: SimulatedSequence,
                   truth: ProcessedSession, model: BodyModel, rng_rig: np.random.Generator,
                   rng_imu: np.random.Generator, rng_noise: np.random.Generator,
                   motion_offset: float = 0.0, progress: bool = True) -> dict[str, Any]:
    """Write kinect/, calibration/, background/, imu/ (and masks/) and truth_clothing.npz under
    ``out``; return their truth.

    With ``cfg.color`` False the kinect/ and background/ recordings are depth-only and their
    colour is never rendered; :func:`skip_color` consumes the colour frames' random draws
    instead, so every depth frame (and the calibration captures) is the same as with colour."""
    times = truth.time
    n = len(times)
    chair_pos = seq.placement.world_from_chair[:3, 3]
    target = chair_pos + np.array([0.0, 0.8, 0.0])
    rig = place_cameras(rng_rig, cfg.cameras, target=tuple(target))
    if cfg.depth_mode != "NFOV_UNBINNED":  # same devices, another depth mode
        rig = [(KinectCalibration.from_json(c.to_json(), depth_mode=cfg.depth_mode), pose)
               for c, pose in rig]
    cams = [pose for _, pose in rig]
    room = make_room(rng_rig, avoid=[(p[0, 3], p[2, 3], 0.5) for p in cams])
    light = Light.random(rng_rig)
    noise = depth_noise(cfg.noise)

    statics = [SceneMesh(o.vertices, o.faces, label=LABEL_BACKGROUND, color=o.color,
                         texture="floor" if o.name == "floor" else None) for o in room]
    wood = tuple(rng_rig.uniform([0.35, 0.2, 0.1], [0.7, 0.5, 0.3]))
    chair_mesh = SceneMesh(seq.placement.world_vertices, seq.placement.faces, label=LABEL_CHAIR,
                           color=wood, texture="wood", texture_coords=seq.placement.vertices)

    # Devices: device 0 is the sync master; subordinates' device clocks started at other times.
    offsets = [0.0, *list(rng_rig.uniform(0.2, 4.0, cfg.cameras - 1))]
    devices = []
    for i, (calib, pose) in enumerate(rig):
        jitter = np.round(rng_rig.normal(0.0, 40.0, n)).astype(np.int64)
        stamps = np.round((times + offsets[i]) * 1e6).astype(np.int64) + jitter
        dropped = np.flatnonzero(rng_rig.random(n) < cfg.drop_rate)
        devices.append({"calib": calib, "pose": pose, "stamps": stamps,
                        "dropped": set(dropped.tolist()), "jitter": jitter})

    clothing = make_clothing(model, seq.motion.betas, rng_rig)
    if not cfg.clothing:
        clothing = bare(clothing)
    save_clothing(out / CLOTHING_FILE, clothing, cfg.model)
    colors = person_colors(model, rng_rig)
    rest = model(betas=seq.motion.betas[None]).vertices[0].detach().double().numpy()
    params = {"global_orient": truth.global_orient, "body_pose": truth.body_pose,
              "transl": truth.transl}
    frames_mode = cfg.fmt == "frames"
    if frames_mode:
        behave = BehaveWriter(out, behave_sequence_name(cfg, seq), BEHAVE_DATE,
                              [d["calib"] for d in devices],
                              [world_from_color(d["calib"], d["pose"]) for d in devices],
                              gender="neutral", object_category=f"chair{seq.chair_kind}",
                              betas=seq.motion.betas, jpeg_quality=cfg.jpeg_quality)
        writers = []
    else:
        (out / "kinect").mkdir(parents=True, exist_ok=True)
        writers = [AzureMkvWriter(out / "kinect" / f"{d['calib'].serial}.mkv", d["calib"],
                                  **_writer_options(cfg, i)) for i, d in enumerate(devices)]
    skipped_frames = []
    chunk = 16
    try:
        for a in tqdm(range(0, n, chunk), desc="rendering", unit="x16 frames",
                      disable=not progress):
            sl = slice(a, min(n, a + chunk))
            clothed = clothed_vertices(clothing, model, seq.motion.betas, params, sl)
            for j, k in enumerate(range(sl.start, sl.stop)):
                person = SceneMesh(clothed[j], model.faces, label=LABEL_PERSON,
                                   vertex_colors=colors, texture="fabric",
                                   texture_coords=rest, smooth=True)
                scene = build_scene([*statics, chair_mesh, person])
                if frames_mode and any(k in d["dropped"] for d in devices):
                    # BEHAVE keeps only frames every camera delivered (its sync step drops the
                    # rest), so a drop in one camera loses the frame
                    skipped_frames.append(k)
                    continue
                images = []
                for i, dev in enumerate(devices):
                    if k in dev["dropped"]:
                        continue
                    depth = render_depth(scene, dev["calib"], dev["pose"], noise, rng_noise,
                                         ir=cfg.ir and not frames_mode)
                    if not cfg.color:  # mkv only, without masks (simulate_session checks)
                        skip_color(dev["calib"], rng_noise)
                        writers[i].write(int(dev["stamps"][k]), depth_mm=depth.depth_mm,
                                         ir=depth.ir)
                        continue
                    color = render_color(scene, dev["calib"], dev["pose"], light, rng_noise,
                                         cfg.jpeg_quality)
                    if frames_mode:
                        images.append(FrameImages(
                            color.rgb, register_depth_to_color(depth.depth_mm, dev["calib"]),
                            color.person_mask, color.chair_mask))
                    else:
                        writers[i].write(int(dev["stamps"][k]), color_jpeg=color.jpeg,
                                         depth_mm=depth.depth_mm, ir=depth.ir)
                    if cfg.masks:
                        path = out / "masks" / dev["calib"].serial / f"{k:05d}.png"
                        path.parent.mkdir(parents=True, exist_ok=True)
                        with atomic_path(path) as tmp:
                            cv2.imwrite(str(tmp), color.person_mask.astype(np.uint8) * 255)
                if frames_mode:
                    behave.write_frame(float(truth.time[k]), images)
    finally:
        for writer in writers:
            writer.close()

    # ChArUco captures for extrinsic calibration: the board alone in the room.
    spec = BoardSpec()
    boards = _board_poses(rng_rig, rig, chair_pos + np.array([0.0, 0.6, 0.0]),
                          cfg.charuco_poses, spec)
    (out / "calibration").mkdir(exist_ok=True)
    for i, dev in enumerate(devices):
        with AzureMkvWriter(out / "calibration" / f"{dev['calib'].serial}.mkv", dev["calib"],
                            **_writer_options(cfg, i, calibration=True)) as w:
            for b, pose in enumerate(boards):
                scene = build_scene([*statics, chair_mesh, board_mesh(spec, pose)])
                depth = render_depth(scene, dev["calib"], dev["pose"], noise, rng_noise,
                                     ir=cfg.ir)
                color = render_color(scene, dev["calib"], dev["pose"], light, rng_noise,
                                     cfg.jpeg_quality)
                w.write(round((b + offsets[i]) * 1e6), color_jpeg=color.jpeg,
                        depth_mm=depth.depth_mm, ir=depth.ir)

    # The empty room (the chair in place, nobody in view) before the subject walked in.
    background = _record_background(out / "background", cfg, devices, offsets,
                                    build_scene([*statics, chair_mesh]), noise, light, rng_noise)

    imu = _record_imu(out / "imu", cfg, seq, model, rng_imu, motion_offset,
                      float(truth.time[0]))

    session = {
        "name": truth.session,
        "format": cfg.fmt,
        "behave_sequence": behave_sequence_name(cfg, seq) if frames_mode else None,
        "kinect": [{"serial": d["calib"].serial,
                    "file": None if frames_mode else f"kinect/{d['calib'].serial}.mkv",
                    "calibration_capture": f"calibration/{d['calib'].serial}.mkv",
                    "background": background[i],
                    "sync": "MASTER" if i == 0 else "SUBORDINATE"}
                   for i, d in enumerate(devices)],
        "imu": {"mvnx": "imu/recording.mvnx", "xbus": "imu/xbus.bin",
                "device_map": "imu/device_map.json"},
        "chair_scan": "chair_scan.obj",
        "board": dataclasses.asdict(spec),
    }
    with atomic_path(out / "session.json") as tmp:
        tmp.write_text(json.dumps(session, indent=2) + "\n")
    return {
        "cameras": [{
            "serial": d["calib"].serial, "world_from_depth": d["pose"].tolist(),
            "world_from_color": world_from_color(d["calib"], d["pose"]).tolist(),
            "device_clock_offset_s": float(offsets[i]),
            "timestamp_jitter_us_std": 40.0,
            "dropped_frames": sorted(d["dropped"]),
        } for i, d in enumerate(devices)],
        "frames_not_written": skipped_frames,
        "kinect_time_of_frame": "frame k is captured at ground_truth.h5 /time[k] (the master "
                                "clock); device timestamp = that + device_clock_offset_s + "
                                "jitter",
        "board_poses_world_from_board": [p.tolist() for p in boards],
        "light": dataclasses.asdict(light),
        "depth_noise": dataclasses.asdict(noise),
        "imu": imu,
        "clothing": {"hand_scale": clothing.hand_scale, "foot_scale": clothing.foot_scale,
                     "max_offset_m": float(np.linalg.norm(clothing.rest_offset, axis=1).max())},
    }


def _record_background(out: Path, cfg: SessionConfig, devices: list[dict[str, Any]],
                       offsets: list[float], scene: SimScene, noise: DepthNoise, light: Light,
                       rng: np.random.Generator) -> list[str | None]:
    """Write ``cfg.background_frames`` frames of the empty room per camera to
    ``out/<serial>.mkv`` (as k4arecorder would: COLOR + DEPTH, or DEPTH alone without
    ``cfg.color``, at the session's rate, recorded 10 minutes before the session); return each
    camera's path relative to the session folder (None per camera when no frames are asked
    for)."""
    if cfg.background_frames <= 0:
        return [None] * len(devices)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, dev in enumerate(devices):
        options = _writer_options(cfg, i)
        options.update(uid_seed=cfg.seed * 1000 + 500 + i,
                       creation_time=options["creation_time"] - _dt.timedelta(minutes=10))
        with AzureMkvWriter(out / f"{dev['calib'].serial}.mkv", dev["calib"], **options) as w:
            for b in range(cfg.background_frames):
                depth = render_depth(scene, dev["calib"], dev["pose"], noise, rng, ir=cfg.ir)
                stamp = round((b / cfg.fps + offsets[i]) * 1e6)
                if not cfg.color:
                    skip_color(dev["calib"], rng)
                    w.write(stamp, depth_mm=depth.depth_mm, ir=depth.ir)
                    continue
                color = render_color(scene, dev["calib"], dev["pose"], light, rng,
                                     cfg.jpeg_quality)
                w.write(stamp, color_jpeg=color.jpeg, depth_mm=depth.depth_mm, ir=depth.ir)
        paths.append(f"{out.name}/{dev['calib'].serial}.mkv")
    return paths


def _record_imu(out: Path, cfg: SessionConfig, seq: SimulatedSequence, model: BodyModel,
                rng: np.random.Generator, motion_offset: float, first: float) -> dict[str, Any]:
    """Write imu/recording.mvnx, imu/xbus.bin and imu/device_map.json; return the clock and
    error truth. The suit sees the motion from Kinect time ``first`` (the first frame) on;
    Kinect time t shows the motion at t + ``motion_offset``."""
    out.mkdir(parents=True, exist_ok=True)
    rest_pelvis = model.rest_joints(seq.motion.betas[None])[0, 0].double().numpy()
    dense = first + np.arange(0.0, cfg.duration + 0.5, 1.0 / DENSE_HZ)  # Kinect clock
    params = motion_in_world(seq.motion, dense + motion_offset, seq.placement.world_from_chair,
                             rest_pelvis)
    track = body_track_from_model(model, dense, params["global_orient"], params["body_pose"],
                                  params["transl"], seq.motion.betas)
    offset = cfg.clock_offset if cfg.clock_offset is not None else -float(
        rng.uniform(0.2, 1.5))
    config = imu_config(cfg.noise, offset, cfg.drift_ppm, cfg.imu_misalignment)
    state = rng.bit_generator.state
    rec, truth = simulate_mvnx(track, config, rng)
    write_mvnx(out / "recording.mvnx", rec)
    # the Xbus stream is the same suit in the same session: replay the same random draws
    rng.bit_generator.state = state
    stream, device_map, xtruth = simulate_xbus(track, config, rng)
    with atomic_path(out / "xbus.bin") as tmp:
        tmp.write_bytes(stream)
    write_device_map(out / "device_map.json", device_map)
    return {
        "clock": "t_imu = (1 + drift_ppm * 1e-6) * t_kinect + clock_offset",
        "clock_offset_s": float(truth.clock_offset), "drift_ppm": float(truth.drift_ppm),
        "clock_scale": float(truth.clock_scale),
        "heading_offset_deg": float(np.degrees(truth.heading_offset)),
        "samples": len(rec.time_ms),
        "xbus_messages": len(xtruth.msg_state),
        "xbus_damaged": int(np.count_nonzero(xtruth.damaged)),
        "xbus_dropped": int(np.count_nonzero(xtruth.dropped)),
        "errors": {k: v for k, v in dataclasses.asdict(config).items()
                   if isinstance(v, int | float)},
    }
