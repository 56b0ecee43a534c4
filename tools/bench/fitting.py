"""Benchmark: the batched body fit against a frame-by-frame loop, and its throughput.

On one simulated session: person clouds from the capture pipeline (calibration, segmentation,
fusion; not timed), the subject's shape from :func:`couch.fitting.shape.fit_shape` (timed
separately), then the same frames fitted with the same settings twice: batched
(:func:`couch.fitting.body.fit_bodies`, frames as the batch dimension) and one frame at a time
(:func:`couch.fitting.body.fit_bodies_frame_by_frame`). Prints both wall times, their ratio
(goal >= 10x), both fits' errors (MPJPE against ``ground_truth.h5`` joints, chamfer to the
person cloud), and the batched fit's throughput as a multiple of real time (seconds of recording
fitted per second), all measured in this one run.

The initial pose is the ground truth perturbed as an IMU would be (:func:`imu_like_init`): every
bone's world orientation rotated by a random few degrees, independently per bone (IMU sensors
err per segment), and the root translation moved by a few cm.

Run: ``python -m couch.tools.bench.fitting [SESSION_DIR] [--frames N] [--threads K]``. Default
session (simulated first, not timed): 4 cameras, NFOV_2X2BINNED depth, 30 fps, 2 s, 4 ChArUco
poses, default noise (1.0) and clothing, seed 3.

Reading the numbers: wall and CPU time are both printed, with the load average. On a machine
that other processes keep busy, torch's OpenMP threads spin-wait for each other and every small
operation slows down, the one-frame fit (many small operations) far more than the batched one,
which inflates the ratio: compare ``--threads 1``, or run with ``OMP_WAIT_POLICY=PASSIVE``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from couch.capture.calibration import calibrate_session
from couch.capture.pointcloud import FusedCloud, fuse_clouds
from couch.capture.segmentation import ChairModel, segment_recording
from couch.fitting import (
    BodyFitConfig,
    BodyParams,
    ShapeFitConfig,
    fit_bodies,
    fit_bodies_frame_by_frame,
    fit_shape,
    mpjpe,
)
from couch.fitting.body import evaluate_fit
from couch.geometry import apply_transform, fit_rigid_transform
from couch.schema import ProcessedSession, read_processed

#: The default session's simulator settings (printed with the results).
DEFAULT_SESSION = {"duration": 2.0, "fps": 30.0, "cameras": 4, "depth_mode": "NFOV_2X2BINNED",
                   "charuco_poses": 4, "seed": 3}


def imu_like_init(params: BodyParams, seed: int, deg: float = 3.0, cm: float = 2.0
                  ) -> BodyParams:
    """Ground-truth parameters perturbed like an IMU's: each bone's *world* orientation rotated
    by a random rotation with N(0, ``deg``²) degrees per axis, independently per bone and frame
    (so errors do not compound down the chain), and the translation moved by N(0, ``cm``²) cm
    per axis; betas unchanged. Seeded by ``seed``."""
    rng = np.random.default_rng(seed)
    t = params.num_frames
    noise = Rotation.from_rotvec(np.deg2rad(rng.normal(0.0, deg, (t * 24, 3)))).as_matrix()
    out = params.with_bone_rotations(params.bone_rotations() @ noise.reshape(t, 24, 3, 3))
    transl = params.transl + rng.normal(0.0, cm / 100.0, (t, 3))
    return dataclasses.replace(out, transl=transl)


@dataclasses.dataclass
class SessionClouds:
    """A simulated session's person clouds in the simulator's world frame.

    clouds: one :class:`FusedCloud` per frame of ``ground_truth.h5``; cameras: (C,3) depth
    camera centres; truth: the ground truth; calibration_error_mm: mean distance between the
    calibrated camera centres (mapped into the true world) and the true ones.
    """

    clouds: list[FusedCloud]
    cameras: np.ndarray
    truth: ProcessedSession
    calibration_error_mm: float


def session_clouds(session: str | Path) -> SessionClouds:
    """Person clouds of every frame of a ``couch-simulate`` session through the capture stage:
    :func:`calibrate_session` (ChArUco + floor), :func:`segment_recording` (backgrounds from the
    calibration captures; the chair's true mesh and pose stand in for the registered scan) and
    :func:`fuse_clouds`.

    The calibrated world has its own heading and origin (the reference camera's), as the
    IMU's has its own: relating them is the sync stage's job. Here the clouds are mapped into
    the simulator's world by the rigid transform that best aligns the calibrated camera poses
    with the true ones, so the calibration's own errors stay in the clouds.
    Assumes no dropped frames (capture index = frame).
    """
    root = Path(session)
    info = json.loads((root / "truth.json").read_text())
    truth = read_processed(root / "ground_truth.h5")
    ext = calibrate_session(root)
    true_pose = {c["serial"]: np.asarray(c["world_from_depth"]) for c in info["cameras"]}
    serials = [c["serial"] for c in info["cameras"]]
    # camera centres and a point 1 m along each optical axis, calibrated vs true
    def marks(poses: list[np.ndarray]) -> np.ndarray:
        return np.concatenate([[p[:3, 3] for p in poses], [p[:3, 3] + p[:3, 2] for p in poses]])

    calib = [ext.world_from_depth(s) for s in serials]
    true_from_calib = fit_rigid_transform(marks(calib), marks([true_pose[s] for s in serials]))
    poses = [true_from_calib @ p for p in calib]
    err = np.linalg.norm(np.array([p[:3, 3] for p in poses])
                         - np.array([true_pose[s][:3, 3] for s in serials]), axis=1).mean()
    chair = ChairModel(truth.object_vertices, truth.object_faces, truth.object_pose)
    segs = [segment_recording(root / "kinect" / f"{s}.mkv", pose,
                              background_paths=[root / "calibration" / f"{s}.mkv"], chair=chair)
            for s, pose in zip(serials, poses, strict=True)]
    by_frame = [{f.index: f for f in seg.frames} for seg in segs]
    clouds = []
    for k in range(truth.num_frames):
        fr = [bf.get(k) for bf in by_frame]
        clouds.append(fuse_clouds([f.depth_mm if f else None for f in fr],
                                  [f.person_reliable if f else None for f in fr],
                                  [s.calibration for s in segs], poses,
                                  time=float(truth.time[k])))
    cameras = np.array([apply_transform(p, np.zeros((1, 3)))[0] for p in poses])
    return SessionClouds(clouds, cameras, truth, float(err) * 1000.0)


def _errors(name: str, params: BodyParams, sc: SessionClouds, cfg: BodyFitConfig) -> str:
    fallback = np.zeros(params.num_frames, bool)
    joints, ch, _, _ = evaluate_fit(params, sc.clouds, sc.cameras, cfg, fallback)
    return (f"{name:<16} MPJPE {mpjpe(joints, sc.truth.joints).mean() * 100:5.2f} cm   "
            f"chamfer {np.nanmean(ch) * 100:5.2f} cm")


def bench(session: Path, frames: int | None, config: BodyFitConfig, seed: int = 0) -> None:
    """Run the benchmark on one session folder and print the results."""
    load = os.getloadavg()
    t0 = time.perf_counter()
    sc = session_clouds(session)
    fps = float(sc.truth.fps)
    n = sc.truth.num_frames if frames is None else min(frames, sc.truth.num_frames)
    print(f"session {session}: {sc.truth.num_frames} frames at {fps:g} fps, "
          f"{len(sc.cameras)} cameras; clouds from the capture stage in "
          f"{time.perf_counter() - t0:.1f} s (not timed below); calibration error "
          f"{sc.calibration_error_mm:.1f} mm; "
          f"{np.mean([len(c) for c in sc.clouds]):.0f} points per frame on average")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; fit: "
          f"{config.coarse_iters} coarse + {config.fine_iters} full-model iterations, "
          f"{config.points} points per frame")
    init = imu_like_init(BodyParams.from_processed(sc.truth), seed)
    init = init.with_betas(np.zeros(10))
    clouds = sc.clouds[:n]
    init_n = init.frames(slice(0, n))

    t = time.perf_counter()
    shape = fit_shape(sc.clouds, init, cameras=sc.cameras,
                      config=ShapeFitConfig(body=config))
    shape_s = time.perf_counter() - t
    init_n = init_n.with_betas(shape.betas)
    quiet = dataclasses.replace(config, errors=False)
    cpu = time.process_time()
    batched = fit_bodies(clouds, init_n, cameras=sc.cameras, config=quiet)
    batched_cpu = time.process_time() - cpu
    cpu = time.process_time()
    single = fit_bodies_frame_by_frame(clouds, init_n, cameras=sc.cameras, config=quiet)
    single_cpu = time.process_time() - cpu

    print(f"shape fit ({len(shape.frames)} frames): {shape_s:.1f} s")
    for name, fit, c in (("batched", batched, batched_cpu),
                         ("frame-by-frame", single, single_cpu)):
        print(f"{name + ' fit of ' + str(n) + ' frames:':<34}{fit.seconds:7.2f} s wall "
              f"({fit.seconds / n * 1000:6.1f} ms/frame), {c:7.2f} s CPU")
    print(f"ratio frame-by-frame / batched: {single.seconds / batched.seconds:.1f}x wall, "
          f"{single_cpu / batched_cpu:.1f}x CPU (goal >= 10x)")
    seconds_of_recording = n / fps
    print(f"throughput (batched fit): {n / batched.seconds:.1f} frames/s = "
          f"{seconds_of_recording / batched.seconds:.2f}x real time at {fps:g} fps; with the "
          f"shape fit: {seconds_of_recording / (batched.seconds + shape_s):.2f}x")
    print(f"load average (1 min) before / after: {load[0]:.1f} / {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} CPUs")
    with torch.no_grad():
        print(_errors("initial (IMU)", init_n, sc, config))
        print(_errors("batched", batched.params, sc, config))
        print(_errors("frame-by-frame", single.params, sc, config))
        print(_errors("true body", BodyParams.from_processed(sc.truth).frames(slice(0, n)), sc,
                      config))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("session", nargs="?", type=Path, default=None,
                    help="a couch-simulate session folder (default: simulate one)")
    ap.add_argument("--frames", type=int, default=None, help="fit only the first N frames")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the IMU-like perturbation")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    config = BodyFitConfig()
    if args.session is not None:
        bench(args.session, args.frames, config, args.seed)
        return
    from couch.tools.sim.session import SessionConfig, simulate_session

    print(f"simulating a session (not timed): {DEFAULT_SESSION}")
    with tempfile.TemporaryDirectory() as tmp:
        simulate_session(Path(tmp), SessionConfig(**DEFAULT_SESSION), progress=False)
        bench(Path(tmp), args.frames, config, args.seed)


if __name__ == "__main__":
    main()
