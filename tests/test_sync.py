"""Sync stage: cameras on the master clock, the IMU clock, IMU poses resampled.

Unit tests on synthetic inputs (exact answers known) and accuracy tests on simulator sessions
generated here (``couch-simulate`` settings stated in :data:`SESSIONS`), compared with the
simulator's ``truth.json`` (device clock offsets, dropped frames, IMU clock) and
``ground_truth.h5`` (frame times). Requirements (issue 7): IMU clock offset error < 3 ms, drift
error < 20 ppm.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import expit

from couch.body import NUM_JOINTS
from couch.capture.azure_mkv import AzureMkvWriter, open_azure_mkv
from couch.capture.imu import ImuMotion, local_rotations
from couch.sync import (
    AFTER,
    BEFORE,
    IN_GAP,
    OK,
    ClockModel,
    SyncError,
    estimate_clock,
    head_features,
    imu_sample_times,
    refine_clock,
    resample_imu,
    sync_kinect,
    sync_session,
)
from couch.tools.sim.session import SessionConfig, simulate_session

# --------------------------------------------------------------------------- synthetic helpers


def head_path(t: np.ndarray, events: tuple[float, ...] = (8.0,)) -> np.ndarray:
    """(N, 3) a plausible head-top path: walking (bobbing at 2 Hz, moving along x) until the
    first event, sitting down there (-0.45 m over ~1.5 s), standing up at each further event."""
    # walking at ~1 m/s, slowing down smoothly (over ~0.5 s) to stop at the first event
    walked = events[0] - 0.25 * np.logaddexp(0.0, (events[0] - t) / 0.25)
    x = walked
    z = 0.3 * np.sin(0.4 * walked)
    sit = np.zeros_like(t)
    for k, e in enumerate(events):
        s = expit((t - e) / 0.25)
        sit += s if k % 2 == 0 else -s
    walking = expit(-(t - events[0] + 0.5) / 0.2)
    y = 1.65 - 0.45 * sit + walking * 0.02 * np.sin(2 * np.pi * 2.0 * t)
    # a small seated sway so that the still parts are not perfectly flat
    y += 0.004 * np.sin(2 * np.pi * 0.25 * t)
    return np.column_stack([x, y, z])


def kinect_view(t_kinect: np.ndarray, rng: np.random.Generator, noise: float = 0.003
                ) -> np.ndarray:
    return head_path(t_kinect) + rng.normal(0.0, noise, (len(t_kinect), 3))


# --------------------------------------------------------------------------- Kinect clock


def _rig(rng: np.random.Generator, n: int = 240, fps: float = 30.0,
         offsets: tuple[float, ...] = (0.0, 1.234567, 3.21),
         drops: tuple[tuple[int, ...], ...] = ((0, 1, 50), (0, 10, 11), (239,)),
         static: bool = False):
    """Synthetic hardware-synced rig: per device (timestamps µs, head-top content)."""
    t = 3.7 + np.arange(n) / fps  # master clock of the capture instants: walk, then sit
    path = head_path(t) if not static else np.tile([0.1, 1.2, 0.3], (n, 1))
    stamps, content, kept = [], [], []
    for c, off in enumerate(offsets):
        keep = np.setdiff1d(np.arange(n), drops[c])
        jitter = np.round(rng.normal(0, 40.0, len(keep))).astype(np.int64)
        stamps.append(np.round((t[keep] + off) * 1e6).astype(np.int64) + jitter)
        bias = rng.normal(0, 0.05, 3) * [1, 0.05, 1]  # horizontal: seen from its side
        content.append(path[keep] + bias + rng.normal(0, 0.003, (len(keep), 3)))
        kept.append(keep)
    return t, stamps, content, kept


def test_kinect_offsets_and_frame_table_with_first_frames_dropped():
    """Master and a subordinate both lose their first frame(s): the content settles it."""
    rng = np.random.default_rng(0)
    t, stamps, content, kept = _rig(rng)
    ks = sync_kinect(stamps, serials=["m", "a", "b"], content=content, fps=30.0,
                     content_bias_axes=(0, 2))
    assert not ks.ambiguous.any(), ks.summary()
    np.testing.assert_allclose(ks.device_offset_s, [0.0, 1.234567, 3.21], atol=20e-6)
    # every frame of every device at its true capture instant
    for c in range(3):
        np.testing.assert_allclose(ks.frame_times(c), t[kept[c]], atol=20e-6)
    # rows start at the first instant any device captured (frame 0 was lost by m and a only)
    assert ks.n_rows == 240
    assert list(ks.frame_table[0]) == [-1, -1, 0]
    assert list(ks.first_row) == [2, 1, 0]
    np.testing.assert_array_equal(ks.dropped_rows(0), [50])
    np.testing.assert_array_equal(ks.dropped_rows(1), [10, 11])
    assert ks.period_s == pytest.approx(1 / 30.0, rel=1e-6)


def test_kinect_without_content_falls_back_to_equal_start_and_says_so():
    rng = np.random.default_rng(1)
    _, stamps, _, _ = _rig(rng)
    ks = sync_kinect(stamps, serials=["m", "a", "b"], fps=30.0)
    assert ks.ambiguous[1:].all()
    assert any("no content" in w for w in ks.warnings)
    # with first frames dropped, the equal-start prior is off by whole frames: flagged, not hidden
    assert ks.device_offset_s[1] == pytest.approx(1.234567 - 1 / 30.0, abs=1e-4)


def test_kinect_static_content_is_ambiguous_not_wrong():
    rng = np.random.default_rng(2)
    _, stamps, content, _ = _rig(rng, static=True)
    ks = sync_kinect(stamps, content=content, fps=30.0)
    assert ks.ambiguous[1:].all()
    assert "does not settle" in " ".join(ks.warnings) or "no content" in " ".join(ks.warnings)


def test_kinect_bad_timestamps_name_the_recording():
    rng = np.random.default_rng(3)
    _, stamps, _, _ = _rig(rng)
    bad = stamps[1].copy()
    bad[5], bad[6] = bad[6], bad[5]
    with pytest.raises(SyncError, match=r"cam1\.mkv.*not strictly increasing"):
        sync_kinect([stamps[0], bad], sources=["cam0.mkv", "cam1.mkv"], fps=30.0)
    # a free-running camera (its own crystal, 300 ppm off) drifts off the rig's frame grid
    master = 5_000_000 + np.cumsum(np.full(3000, 33333))
    free = 9_000_000 + np.cumsum(np.full(3000, 33343))
    with pytest.raises(SyncError, match=r"cam2\.mkv.*not hardware-synchronised"):
        sync_kinect([master, free], sources=["cam0.mkv", "cam2.mkv"], fps=30.0)


# --------------------------------------------------------------------------- IMU clock (synthetic)


def _imu_side(clock: ClockModel, t_start: float, t_end: float, rate: float = 60.0
              ) -> tuple[np.ndarray, np.ndarray]:
    """Suit samples k/rate on the IMU clock covering Kinect [t_start, t_end]."""
    tau = np.arange(math.floor(clock.to_other(t_start) * rate),
                    math.ceil(clock.to_other(t_end) * rate) + 1) / rate
    return tau, head_path(clock.to_kinect(tau))


@pytest.mark.parametrize("offset,drift", [(-0.734, 40.0), (2.5, -60.0)])
def test_estimate_clock_synthetic(offset, drift):
    """Coarse search over the whole overlap, then the fine fit, from 20 s at 15 fps with 3 mm
    of noise: the offset within the requirement (3 ms at Kinect time 0, the clock's
    definition), the drift held near 0 by its prior (20 s cannot measure it)."""
    rng = np.random.default_rng(4)
    truth = ClockModel(offset, drift)
    t = 1.0 + np.arange(0, 20.0, 1 / 15.0)
    tau, top = _imu_side(truth, 0.0, 22.0)
    feats = head_features(t, kinect_view(t, rng))
    est = estimate_clock(t, feats, tau, top, features=head_features)
    assert est.confident, est.summary()
    assert abs(est.clock.offset_s - offset) < 3e-3
    t_ref = est.reference_time_s
    assert abs(est.clock.to_other(t_ref) - truth.to_other(t_ref)) < 3e-3
    assert abs(est.clock.drift_ppm) < 50.0
    assert est.correlation > 0.9
    assert abs(est.coarse_offset_s - offset) < 0.05


def test_refine_clock_measures_drift_over_a_long_recording():
    """A sit and a stand 190 s apart: the drift is measured (the prior does not hold it
    back)."""
    rng = np.random.default_rng(5)
    truth = ClockModel(0.35, 45.0)
    t = 1.0 + np.arange(0, 210.0, 1 / 15.0)

    def path(tt: np.ndarray) -> np.ndarray:
        return head_path(tt, events=(8.0, 200.0))

    tau = np.arange(0, math.ceil(truth.to_other(215.0) * 60)) / 60.0
    feats = head_features(t, path(t) + rng.normal(0, 0.001, (len(t), 3)))
    est = refine_clock(t, feats, tau, path(truth.to_kinect(tau)),
                       ClockModel(0.35 + 0.02, 0.0), features=head_features)
    assert abs(est.clock.drift_ppm - 45.0) < 10.0, est.summary()
    assert abs(est.clock.offset_s - 0.35) < 1e-3


def test_estimate_clock_no_overlap_names_the_streams():
    rng = np.random.default_rng(6)
    truth = ClockModel(-0.5, 0.0)
    t = 1.0 + np.arange(0, 15.0, 1 / 15.0)
    tau, top = _imu_side(truth, 0.0, 17.0)
    feats = head_features(t, kinect_view(t, rng))
    # a prior window 60 s away from any offset at which the recordings overlap
    with pytest.raises(SyncError, match=r"k\.mkv.*imu/rec\.mvnx.*do not overlap"):
        estimate_clock(t, feats, tau, top, features=head_features,
                       initial=ClockModel(60.0), search_s=5.0,
                       names=("k.mkv", "imu/rec.mvnx"))
    # a fine fit started where nothing overlaps
    with pytest.raises(SyncError, match=r"share only 0 usable frames"):
        refine_clock(t, feats, tau, top, ClockModel(100.0), features=head_features)


def test_estimate_clock_flat_signal_is_an_error():
    t = np.arange(0, 15.0, 1 / 15.0)
    still = np.tile([0.0, 1.3, 0.0], (len(t), 1))
    tau = np.arange(0, 16.0, 1 / 60.0)
    with pytest.raises(SyncError, match="no motion"):
        estimate_clock(t, head_features(t, still), tau, np.tile([0.0, 1.3, 0.0], (len(tau), 1)),
                       features=head_features)


def test_estimate_clock_periodic_signal_is_low_confidence():
    """A pure 1 Hz oscillation matches every whole period equally: flagged, not trusted."""
    t = np.arange(0, 20.0, 1 / 15.0)

    def osc(tt: np.ndarray) -> np.ndarray:
        return np.column_stack([0 * tt, 1.2 + 0.05 * np.sin(2 * np.pi * tt), 0 * tt])

    tau = np.arange(0, 21.0, 1 / 60.0)
    est = estimate_clock(t, head_features(t, osc(t)), tau, osc(tau - 0.3),
                         features=head_features)
    assert not est.confident
    assert any("ambiguous" in w for w in est.warnings)


def test_imu_sample_times_snap_whole_milliseconds():
    k = np.arange(0, 600)
    motion = _imu_motion(np.round(k / 60.0 * 1000) / 1000)
    np.testing.assert_allclose(imu_sample_times(motion), k / 60.0, atol=1e-12)
    jittery = _imu_motion(k / 60.0 + np.where(k % 7 == 0, 3e-3, 0.0))
    np.testing.assert_array_equal(imu_sample_times(jittery), jittery.time)


# --------------------------------------------------------------------------- resampling


def _imu_motion(time: np.ndarray, rot: np.ndarray | None = None,
                pos: np.ndarray | None = None) -> ImuMotion:
    n = len(time)
    rot = np.tile(np.eye(3), (n, NUM_JOINTS, 1, 1)) if rot is None else rot
    pos = np.zeros((n, NUM_JOINTS, 3)) if pos is None else pos
    from couch.rotations import matrix_to_axis_angle

    aa = matrix_to_axis_angle(local_rotations(rot))
    contacts = np.zeros((n, 4), dtype=bool)
    contacts[: n // 2] = True
    return ImuMotion(time=np.asarray(time, float), unix_ms=np.zeros(n, np.int64),
                     global_orient=aa[:, 0], body_pose=aa[:, 1:].reshape(n, 69),
                     joint_rotations=rot, joint_positions=pos, foot_contacts=contacts,
                     foot_contact_labels=("a", "b", "c", "d"), frame_rate=60.0,
                     configuration="FullBody")


def _spinning(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every joint turning at its own constant angular velocity; positions linear in time."""
    axes = np.random.default_rng(7).normal(size=(NUM_JOINTS, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    rates = np.linspace(0.5, 6.0, NUM_JOINTS)  # rad/s, up to 0.1 rad per 60 Hz sample
    rv = t[:, None, None] * (rates[:, None] * axes)[None]
    rot = Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(len(t), NUM_JOINTS, 3, 3)
    pos = t[:, None, None] * np.linspace(0.1, 2.0, NUM_JOINTS * 3).reshape(NUM_JOINTS, 3)
    return rot, pos


def test_resample_slerp_is_exact_for_constant_angular_velocity():
    tau = np.arange(0, 240) / 60.0
    rot, pos = _spinning(tau)
    motion = _imu_motion(tau, rot, pos)
    clock = ClockModel(offset_s=-0.4, drift_ppm=35.0)
    t = clock.to_kinect(np.linspace(0.05, 3.9, 97))  # Kinect times inside the IMU recording
    res = resample_imu(motion, clock, t)
    assert res.valid.all()
    want_rot, want_pos = _spinning(clock.to_other(t))
    angle = Rotation.from_matrix((np.swapaxes(res.joint_rotations, -1, -2)
                                  @ want_rot).reshape(-1, 3, 3)).magnitude()
    assert angle.max() < 1e-9
    np.testing.assert_allclose(res.joint_positions, want_pos, atol=1e-9)
    # local rotations and axis-angle follow the global ones
    from couch.rotations import axis_angle_to_matrix

    local = axis_angle_to_matrix(np.concatenate([res.global_orient[:, None],
                                                 res.body_pose.reshape(-1, 23, 3)], axis=1))
    np.testing.assert_allclose(local, local_rotations(res.joint_rotations), atol=1e-9)


def test_resample_flags_outside_and_gaps_instead_of_extrapolating():
    tau = np.arange(0, 120) / 60.0
    keep = np.ones(120, dtype=bool)
    keep[40] = False  # one lost sample: bridged
    keep[70:80] = False  # ten lost samples: a gap
    rot, pos = _spinning(tau[keep])
    motion = _imu_motion(tau[keep], rot, pos)
    t = np.array([-0.5, -1e-3, 0.0, 40.5 / 60, 75 / 60, 68.5 / 60, 1.0 + 59 / 60, 2.5])
    res = resample_imu(motion, ClockModel(0.0), t, source="imu/rec.mvnx")
    np.testing.assert_array_equal(res.status, [BEFORE, BEFORE, OK, OK, IN_GAP, OK, OK, AFTER])
    assert np.isnan(res.joint_positions[~res.valid]).all()
    assert np.isnan(res.joint_rotations[~res.valid]).all()
    assert np.isfinite(res.joint_positions[res.valid]).all()
    assert not res.foot_contacts[~res.valid].any()
    assert res.foot_contacts[2].all()
    assert "imu/rec.mvnx: 4 of 8" in res.summary() and "1 in a gap" in res.summary()
    assert res.counts() == {"ok": 4, "before the IMU recording": 2,
                            "after the IMU recording": 1, "in a gap of the IMU recording": 1}


# --------------------------------------------------------------------------- simulator sessions

#: Every simulated session: 5 fps, NFOV 2x2 binned depth, 10 % of frames dropped per camera,
#: one ChArUco pose (the camera poses come from truth.json: the sync is under test here,
#: calibration is tested in test_capture_calibration), default noise (the IMU errors of
#: ImuConfig: 0.5° tilt / 1° heading noise, 3° misalignment, heading and position drift).
COMMON = dict(fps=5.0, depth_mode="NFOV_2X2BINNED", drop_rate=0.1, charuco_poses=1,
              background_frames=3)
SESSIONS = {
    # walk in, sit on a stool, stand up and leave, seen by two cameras
    "a": dict(seed=1, duration=12.0, cameras=2, clock_offset=-0.9, drift_ppm=40.0),
    # the suit started before the cameras (positive offset), its clock running slow; recorded
    # depth-only (the sync reads depth alone, and depth is the same as with colour)
    "b": dict(seed=7, duration=12.0, cameras=2, clock_offset=0.35, drift_ppm=-60.0,
              interaction="no_contact", chair="straight", color=False),
}
#: A long session for the drift: it shows only over a long lever (20 ppm is 2 ms over 100 s),
#: here between walking in and sitting at the start and standing up and leaving at the end.
#: Depth-only (the sync reads depth alone): rendering colour would take ~10 minutes. One camera:
#: the lever is in time, and two-camera sync is what sessions a and b test.
LONG = dict(seed=1, duration=120.0, cameras=1, clock_offset=-0.6, drift_ppm=45.0, color=False)


def _truth(root: Path) -> dict:
    return json.loads((root / "truth.json").read_text())


def _frame_times(root: Path) -> np.ndarray:
    """(T,) the master-clock time of every simulated capture instant (ground_truth.h5)."""
    with h5py.File(root / "ground_truth.h5") as f:
        return f["time"][:]


def _extrinsics(root: Path) -> dict[str, np.ndarray]:
    return {c["serial"]: np.array(c["world_from_depth"]) for c in _truth(root)["cameras"]}


@pytest.fixture(scope="session")
def sim(tmp_path_factory):
    """``sim(name)`` → (session folder, its SessionSync), generated and synced once."""
    cache: dict[str, tuple[Path, object]] = {}

    def get(name: str):
        if name not in cache:
            spec = LONG if name == "long" else SESSIONS[name]
            root = tmp_path_factory.mktemp(f"sync_{name}")
            simulate_session(root, SessionConfig(**COMMON, **spec), progress=False)
            cache[name] = (root, sync_session(root, extrinsics=_extrinsics(root)))
        return cache[name]

    return get


def _check_frames(root: Path, kinect, rows_of_truth: list[np.ndarray]) -> None:
    """Every frame of every camera at its true capture instant; offsets as simulated."""
    truth = _truth(root)
    time = _frame_times(root)
    for c, cam in enumerate(truth["cameras"]):
        c_sync = kinect.serials.index(cam["serial"])
        np.testing.assert_allclose(kinect.frame_times(c_sync), time[rows_of_truth[c]],
                                   atol=1e-4, err_msg=cam["serial"])
        assert kinect.device_offset_s[c_sync] == pytest.approx(cam["device_clock_offset_s"],
                                                               abs=1e-4)


def test_sim_kinect_frames_on_the_master_clock(sim):
    root, ss = sim("a")
    truth = _truth(root)
    n = len(_frame_times(root))
    kept = [np.setdiff1d(np.arange(n), cam["dropped_frames"]) for cam in truth["cameras"]]
    _check_frames(root, ss.kinect, kept)
    # the frame table marks exactly the simulator's dropped frames (inside each recording);
    # row 0 is the first instant any camera recorded
    k0 = min(k[0] for k in kept)
    for c, cam in enumerate(truth["cameras"]):
        lost = np.asarray(cam["dropped_frames"], dtype=int)
        lost = lost[(lost > kept[c][0]) & (lost < kept[c][-1])]
        np.testing.assert_array_equal(ss.kinect.dropped_rows(ss.kinect.serials.index(
            cam["serial"])), lost - k0)


def _rewrite_without_first(src: Path, dst: Path, skip: int) -> None:
    """Copy a k4arecorder file without its first ``skip`` captures (as if dropped)."""
    rec = open_azure_mkv(src)
    with AzureMkvWriter(dst, rec.calibration, fps=rec.fps, wired_sync_mode=rec.wired_sync_mode,
                        subordinate_delay_ns=rec.subordinate_delay_ns,
                        depth_delay_ns=rec.depth_delay_ns, uid_seed=1) as w:
        for k, cap in enumerate(rec):
            if k >= skip:
                w.write(cap.timestamp_us, color_jpeg=cap.color_jpeg, depth_mm=cap.depth_mm,
                        ir=cap.ir)


def test_sim_kinect_first_frames_dropped_on_master_and_subordinate(sim, tmp_path):
    """The master loses its first frame, the subordinate its first three: whole-frame shifts
    the timestamps cannot see, settled by the head-top content."""
    from couch.sync import session_tracks, sync_tracks

    root, _ = sim("a")
    truth = _truth(root)
    copy = tmp_path / "session"
    copy.mkdir()
    for item in ("session.json", "background", "truth.json", "ground_truth.h5"):
        (copy / item).symlink_to(root / item)
    (copy / "kinect").mkdir()
    skips = [1, 3]
    n = len(_frame_times(root))
    kept = []
    for cam, skip in zip(truth["cameras"], skips, strict=True):
        name = f"{cam['serial']}.mkv"
        _rewrite_without_first(root / "kinect" / name, copy / "kinect" / name, skip)
        kept.append(np.setdiff1d(np.arange(n), cam["dropped_frames"])[skip:])
    kinect = sync_tracks(session_tracks(copy, _extrinsics(root)))
    assert not kinect.ambiguous.any(), kinect.summary()
    _check_frames(root, kinect, kept)
    k0 = min(k[0] for k in kept)
    assert [int(kinect.first_row[kinect.serials.index(cam["serial"])]) for cam in
            truth["cameras"]] == [int(k[0] - k0) for k in kept]
    assert max(k[0] for k in kept) - k0 >= 2  # the shifts were real: 2+ frames apart


@pytest.mark.parametrize("name", list(SESSIONS))
def test_sim_imu_clock_offset(sim, name):
    """Requirement: IMU clock offset error < 3 ms (at Kinect time 0, truth.json's definition)."""
    root, ss = sim(name)
    clock = _truth(root)["imu"]
    est = ss.imu_clock
    err_ms = 1e3 * (est.clock.offset_s - clock["clock_offset_s"])
    print(f"\n[{name}] {SESSIONS[name]}: offset error {err_ms:+.3f} ms, drift "
          f"{est.clock.drift_ppm:+.1f} ppm (true {clock['drift_ppm']:+.1f}); {est.summary()}")
    assert abs(err_ms) < 3.0, est.summary()
    if not SESSIONS[name].get("color", True):  # the sync ran on depth-only recordings
        assert all("COLOR" not in open_azure_mkv(p).tracks
                   for p in [*root.glob("kinect/*.mkv"), *root.glob("background/*.mkv")])
    # the resampled suit follows the true motion on the Kinect clock: its pelvis height
    # (MVN's floor is y = 0 too, up to a ~1 cm bias) tracks the ground truth's
    res = ss.resampled
    with h5py.File(root / "ground_truth.h5") as f:
        time, joints = f["time"][:], f["joints"][:]
    rows = np.searchsorted(time, res.time[res.valid] - 1e-4)
    assert res.valid.sum() > 0.8 * len(res.time)
    dy = res.joint_positions[res.valid, 0, 1] - joints[rows, 0, 1]
    assert np.std(dy) < 0.01


@pytest.mark.slow  # ~1.5 minutes: simulating the 2-minute session (depth only, one camera)
def test_sim_imu_clock_drift_long_session(sim):
    """Requirement: drift error < 20 ppm (and offset < 3 ms) over a 2-minute session."""
    root, ss = sim("long")
    clock = _truth(root)["imu"]
    est = ss.imu_clock
    err_ms = 1e3 * (est.clock.offset_s - clock["clock_offset_s"])
    err_ppm = est.clock.drift_ppm - clock["drift_ppm"]
    print(f"\n[long] {LONG}: offset error {err_ms:+.3f} ms, drift error {err_ppm:+.1f} ppm; "
          f"{est.summary()}")
    assert abs(err_ppm) < 20.0, est.summary()
    assert abs(err_ms) < 3.0, est.summary()


def test_sim_imu_without_overlap_names_the_files(sim):
    """The suit's recording cut to a stretch the cameras did not see: a clear error."""
    from couch.sync import sync_imu

    root, ss = sim("a")
    imu = ss.imu
    keep = imu.time < 2.0  # 2 s: less than the minimum overlap
    cut = dataclasses.replace(imu, **{f: getattr(imu, f)[keep] for f in (
        "time", "unix_ms", "global_orient", "body_pose", "joint_rotations", "joint_positions",
        "foot_contacts")})
    with pytest.raises(SyncError, match=r"kinect/.*\.mkv.*recording\.mvnx.*do not overlap"):
        sync_imu(ss.kinect, ss.tracks, cut, imu_name=str(root / "imu" / "recording.mvnx"))


def test_refine_imu_on_fitted_joints():
    """The fitting stage's entry: fitted joints (here the truth plus 5 mm of noise, 2 s
    without a fit) refine a clock that is 40 ms off, whatever MVN's heading and origin."""
    from couch.sync import refine_imu

    rng = np.random.default_rng(8)
    truth = ClockModel(-0.25, 30.0)
    offsets = rng.normal(0, 0.3, (NUM_JOINTS, 3))

    def joints(t: np.ndarray) -> np.ndarray:
        return head_path(t)[:, None, :] + offsets[None]

    tau = np.arange(0, math.ceil(truth.to_other(22.0) * 60)) / 60.0
    heading = Rotation.from_euler("y", 70, degrees=True).as_matrix()
    motion = _imu_motion(tau, pos=joints(truth.to_kinect(tau)) @ heading.T + [1.0, 0.0, -2.0])
    t = 1.0 + np.arange(0, 20.0, 1 / 15.0)
    fitted = joints(t) + rng.normal(0, 0.005, (len(t), NUM_JOINTS, 3))
    keep = (np.arange(len(t)) < 100) | (np.arange(len(t)) > 130)  # 2 s without a fit
    est = refine_imu(t[keep], fitted[keep], motion, ClockModel(-0.25 + 0.04, 0.0))
    t_ref = est.reference_time_s
    assert abs(est.clock.to_other(t_ref) - truth.to_other(t_ref)) < 1e-3, est.summary()
    assert abs(est.clock.offset_s - truth.offset_s) < 3e-3, est.summary()


def test_estimate_clock_complex_channels_ignore_a_rotation():
    """Horizontal velocity as a complex channel (x + iz) matches up to a rotation and scale:
    the suit's frame may be turned by any heading."""
    rng = np.random.default_rng(9)
    truth = ClockModel(0.8, 0.0)

    def velocity(t: np.ndarray, x: np.ndarray) -> np.ndarray:
        f = np.full(x.shape[:-1], np.nan, dtype=complex)
        v = (x[..., 2:, :] - x[..., :-2, :]) / (t[2:] - t[:-2])[:, None]
        f[..., 1:-1] = v[..., 0] + 1j * v[..., 2]
        return f[..., None]

    t = 1.0 + np.arange(0, 20.0, 1 / 15.0)
    tau = np.arange(0, math.ceil(truth.to_other(22.0) * 60)) / 60.0
    turn = Rotation.from_euler("y", 123, degrees=True).as_matrix()
    other = head_path(truth.to_kinect(tau)) @ turn.T
    feats = velocity(t, kinect_view(t, rng))
    est = estimate_clock(t, feats, tau, other, features=velocity)
    assert abs(est.clock.to_other(10.0) - truth.to_other(10.0)) < 3e-3, est.summary()
    assert abs(abs(est.gains[0]) - 1.0) < 0.05 and np.iscomplexobj(est.gains)
