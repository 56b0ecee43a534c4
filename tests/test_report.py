"""The QA report (couch.tools.report): summary numbers, strict JSON, plots, HTML, previews.

Results are built by hand (no pipeline run): small synthetic stage records, a failed run, and
previews over the committed fixture's recordings and over a depth-only recording written here.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from couch.body import CONTACT_NAMES
from couch.capture.azure_mkv import AzureMkvWriter, open_azure_mkv
from couch.capture.calibration import CameraExtrinsics, Extrinsics
from couch.fitting.chair import ChairRegistration, ChairSegment
from couch.fitting.contacts import Contacts
from couch.fitting.pipeline import (
    STAGES,
    BodyResult,
    CalibrationResult,
    PipelineResult,
    StageRun,
)
from couch.schema import INTERACTION_LABELS
from couch.tools.report import PLOTS, preview_frames, write_report

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "sessions" / "sim_fixture"
FPS = 5.0
# an OpenCV camera at (0, 1, -2.5) looking along world +Z (Y up in the world, +Y down in it)
CAMERA_POSE = np.array([[-1.0, 0, 0, 0], [0, -1, 0, 1.0], [0, 0, 1, -2.5], [0, 0, 0, 1]])


# --------------------------------------------------------------------------- synthetic records


def _body(t: int, serials: list[str], stamps: np.ndarray | None = None,
          transl: np.ndarray | None = None) -> BodyResult:
    """A body record of ``t`` rows standing at ``transl`` (default: 2.5 m in front of
    CAMERA_POSE), with some NaN chamfers, fallbacks and IMU gaps."""
    rng = np.random.default_rng(0)
    time = 1.5 + np.arange(t) / FPS
    chamfer = 0.01 + 0.002 * rng.random(t)
    chamfer[1 % t] = np.nan
    fit_chamfer = chamfer.copy()
    fit_chamfer[2 % t] = np.nan
    fallback = np.zeros(t, bool)
    fallback[2 % t] = True
    imu_filled = np.zeros(t, bool)
    imu_filled[3:5] = True
    where = np.array([0.0, 1.2, 0.0]) if transl is None else transl
    if stamps is None:
        stamps = np.full((t, len(serials)), -1, np.int64)
    kinect_h = 1.7 + 0.01 * np.sin(time)
    kinect_h[0] = np.nan
    imu_time = np.linspace(time[0] - 1, time[-1] + 1, 5 * t)
    return BodyResult(
        time=time, rows=np.arange(t), fps=FPS, betas=np.zeros(10, np.float32),
        global_orient=np.zeros((t, 3), np.float32), body_pose=np.zeros((t, 69), np.float32),
        transl=np.tile(where, (t, 1)).astype(np.float32), joints=np.zeros((t, 24, 3)),
        fit_joints=np.zeros((t, 24, 3)), imu_joints=np.zeros((t, 24, 3)),
        fit_chamfer=fit_chamfer, chamfer=chamfer, reliability=np.full((t, 24), 0.75),
        fallback=fallback, imu_filled=imu_filled, foot_contact=np.zeros((t, 4), bool),
        fitted=np.ones(t, bool),
        points=np.full(t, 1000), cameras_present=stamps >= 0, camera_serials=list(serials),
        frame_timestamp_us=np.asarray(stamps, np.int64), sync_time=time,
        sync_kinect_height=kinect_h, sync_imu_time=imu_time,
        sync_imu_height=1.6 + 0.01 * np.sin(imu_time),
        clock_offset_ms=-310.25, clock_drift_ppm=1.5, clock_offset_std_ms=2.0,
        clock_correlation=0.99, clock_confident=True, clock_summary="offset -0.31 s",
        heading_deg=-108.0, alignment_residual_m=np.nan, shape_source="clouds",
        summary="", seconds={"fit": 1.0}, warnings=[])


def _chair(n: int = 6) -> ChairRegistration:
    """A unit box chair at the origin; frame 1 rejected (NaN pose), frame 2 not averaged."""
    v = np.array([[x, y, z] for x in (0, 0.5) for y in (0, 0.5) for z in (0, 0.5)], float)
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    pose = np.eye(4)
    poses = np.repeat(pose[None], n, axis=0)
    poses[:, 0, 3] += np.linspace(0, 0.002, n)
    poses[1] = np.nan
    used = np.ones(n, bool)
    used[[1, 2]] = False
    seg = ChairSegment(first=0, last=n - 1, start_time=1.5, end_time=1.5 + (n - 1) * 0.4,
                       world_from_object=pose, frames=np.flatnonzero(used),
                       rotation_spread_deg=0.01, translation_spread_mm=0.5, chamfer=0.004)
    return ChairRegistration(
        scan=Path("chair_scan.obj"), vertices=v, faces=f, world_from_object=pose,
        frames=np.arange(0, 2 * n, 2), time=1.5 + np.arange(n) * 0.4, frame_poses=poses,
        fitness=np.linspace(0.9, 0.95, n), rmse=np.full(n, 0.003), points=np.full(n, 500),
        method=["track"] * n, used=used,
        rejected=[(1, "too few points: 12 near the chair (need 500)"),
                  (2, "averaging outlier: far from the segment's mean pose")],
        segments=[seg], rotation_spread_deg=0.01, translation_spread_mm=0.5, chamfer=0.004,
        ambiguous=False, ambiguity_deg=[], seconds={"icp": 2.0}, warnings=[])


def _contacts(t: int) -> Contacts:
    active = np.zeros((t, 5), bool)
    active[t // 2:, 0] = True
    active[t // 2: t // 2 + 2, 1:3] = True
    floor = np.zeros((t, 2), bool)
    floor[:, 0] = True
    floor[: t // 3, 1] = True
    labels = np.full(t, 5, np.int8)
    labels[: t // 4] = 0
    labels[t // 2: t // 2 + 2] = 3
    return Contacts(names=CONTACT_NAMES, active=active,
                    points=np.full((t, 5, 3), np.nan, np.float32), labels=labels,
                    distance=np.zeros((t, 5), np.float32), speed=np.zeros((t, 5), np.float32),
                    floor_active=floor, floor_points=np.full((t, 2, 3), np.nan, np.float32),
                    floor_distance=np.zeros((t, 2), np.float32), fps=FPS)


def _extrinsics(serials: list[str], pose: np.ndarray = CAMERA_POSE) -> Extrinsics:
    cams = {s: CameraExtrinsics(s, pose.copy(), pose.copy(), reprojection_mean_px=0.25 + k,
                                reprojection_max_px=np.nan) for k, s in enumerate(serials)}
    return Extrinsics(cameras=cams, reference=serials[0])


def _result(session: Path, body: BodyResult | None, chair: ChairRegistration | None,
            contacts: Contacts | None, extrinsics: Extrinsics | None,
            fault: tuple[str, str] | None = None) -> PipelineResult:
    stages = {s: StageRun(s, status="ran", seconds=1.0, steps={"x": 0.5}) for s in STAGES}
    serials = list(extrinsics.cameras) if extrinsics is not None else ["000000000001"]
    cal = CalibrationResult(cameras=serials, dropped=[("999", "missing")],
                            extrinsics_json="{}", warnings=["camera 999 left out: missing"])
    res = PipelineResult(session=session, output=session / "processed", processed=None,
                         stages=stages, calibration=cal, extrinsics=extrinsics, chair=chair,
                         body=body, contacts=contacts, warnings=["calibrate: camera 999 <x>"])
    if fault is not None:
        res.fault = fault
        res.stages[fault[0]].status, res.stages[fault[0]].error = "failed", fault[1]
        for s in STAGES[STAGES.index(fault[0]) + 1:]:
            res.stages[s] = StageRun(s)
    return res


def _assert_png(path: Path) -> np.ndarray:
    assert path.is_file() and path.stat().st_size > 0, path
    img = cv2.imread(str(path))
    assert img is not None and img.size > 0, path
    return img


# --------------------------------------------------------------------------- tests


def test_summary_numbers_plots_and_html(tmp_path: Path) -> None:
    t = 20
    session = tmp_path / "session"  # no recordings: previews get a note per tile
    session.mkdir()
    body, chair, contacts = _body(t, ["A1"]), _chair(), _contacts(t)
    res = _result(session, body, chair, contacts, _extrinsics(["A1"]))
    index = write_report(res, tmp_path / "report", previews=0)
    out = tmp_path / "report"
    assert index == out / "index.html" and index.is_file()

    text = (out / "summary.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    doc = json.loads(text)
    assert doc["ok"] is True and doc["fault"] is None
    assert doc["session"] == str(session)
    assert doc["stages"]["body"] == {"status": "ran", "seconds": 1.0, "steps": {"x": 0.5},
                                     "error": None}
    assert doc["calibration"]["dropped"] == [{"serial": "999", "reason": "missing"}]
    assert doc["calibration"]["reprojection_mean_px"] == {"A1": 0.25}
    assert doc["calibration"]["reprojection_max_px"] == {"A1": None}
    assert doc["sync"]["clock_offset_ms"] == pytest.approx(-310.25)
    assert doc["sync"]["alignment_residual_m"] is None

    b = doc["body"]
    assert b["frames"] == t and b["fps"] == FPS
    assert b["duration_s"] == pytest.approx(t / FPS)
    assert b["chamfer_cm"]["mean"] == pytest.approx(np.nanmean(body.chamfer) * 100)
    assert b["fit_chamfer_cm"]["median"] == pytest.approx(np.nanmedian(body.fit_chamfer) * 100)
    assert b["reliability_mean"] == pytest.approx(0.75)
    assert b["fallback_frames"] == 1 and b["imu_gap_frames"] == 2
    assert b["shape_source"] == "clouds"

    c = doc["chair"]
    assert c["frames_registered"] == 6 and c["frames_used"] == 4
    assert c["rejected"] == {"too few points": 1, "averaging outlier": 1}
    assert c["chamfer_cm"] == pytest.approx(0.4)
    assert c["world_from_object"] == np.eye(4).tolist()
    assert len(c["segments"]) == 1 and c["segments"][0]["frames"] == 4
    assert c["moved"] is False and c["ambiguous"] is False

    k = doc["contacts"]
    assert k["active_frames"] == {n: int(contacts.active[:, j].sum())
                                  for j, n in enumerate(CONTACT_NAMES)}
    assert k["floor_frames"] == {"left_foot": t,
                                 "right_foot": int(contacts.floor_active[:, 1].sum())}
    assert set(k["labels"]) == set(INTERACTION_LABELS.values())
    assert sum(k["labels"].values()) == t
    assert k["labels"]["both hands"] == 2 and k["labels"]["locomotion"] == t // 4

    assert doc["report"]["plots"] == list(PLOTS) and doc["report"]["notes"] == []
    for name in PLOTS:
        _assert_png(out / name)
    page = index.read_text()
    assert "OK" in page and 'class="fault"' not in page
    for name in PLOTS:
        assert f'src="{name}"' in page
    assert "camera 999 &lt;x&gt;" in page and "<x>" not in page
    assert "<script" not in page and "http" not in page
    assert not list(out.glob(".*tmp*"))  # atomic writes leave no temporary files


def test_failed_result_reports_what_ran(tmp_path: Path) -> None:
    out = tmp_path / "report"
    # an earlier, complete report in the same folder: its plots must not survive
    ok = _result(tmp_path, _body(10, ["A1"]), _chair(), _contacts(10), _extrinsics(["A1"]))
    write_report(ok, out, previews=0)
    assert (out / "sync.png").is_file()

    message = 'chair_scan.obj: bad mesh <faces> & "NaN" vertices'
    res = _result(tmp_path, None, None, None, _extrinsics(["A1"]), fault=("chair", message))
    res.traceback = "Traceback (most recent call last):\n  File <x>\nValueError: boom"
    index = write_report(res, out)
    doc = json.loads((out / "summary.json").read_text())
    assert doc["ok"] is False
    assert doc["fault"] == {"stage": "chair", "message": message}
    assert doc["stages"]["chair"]["status"] == "failed"
    assert doc["stages"]["body"]["status"] == "not run"
    assert doc["calibration"]["cameras"] == ["A1"]
    for section in ("sync", "body", "chair", "contacts"):
        assert doc[section] is None
    assert doc["report"]["plots"] == [] and doc["report"]["previews"] == []
    for name in PLOTS:
        assert not (out / name).exists()
    page = index.read_text()
    assert "FAILED" in page and 'class="fault"' in page
    assert "bad mesh &lt;faces&gt; &amp; &quot;NaN&quot; vertices" in page
    assert "<faces>" not in page
    assert "<pre>Traceback (most recent call last):\n  File &lt;x&gt;" in page


def test_preview_frames_prefer_contacts() -> None:
    t = 20
    contacts = _contacts(t)
    res = _result(Path("."), _body(t, ["A1"]), None, contacts, None)
    picks = preview_frames(res, 4)
    assert len(picks) == 4 and picks == sorted(picks)
    # the stretch [10, 15) holds the frames with three contacts
    assert any(contacts.active[i].sum() == 3 for i in picks)
    assert preview_frames(res, 0) == []
    assert preview_frames(_result(Path("."), None, None, None, None), 4) == []
    assert len(preview_frames(_result(Path("."), _body(2, ["A1"]), None, None, None), 4)) == 2


def test_previews_depth_only_and_missing_recording(tmp_path: Path) -> None:
    """A depth-only recording gets a grey depth tile with the body over it; a camera without a
    recording gets a note tile; the report does not fail."""
    calib = open_azure_mkv(next((FIXTURE / "kinect").glob("*.mkv"))).calibration
    session = tmp_path / "session"
    (session / "kinect").mkdir(parents=True)
    h, w = calib.depth.height, calib.depth.width
    stamps = [1_000_000, 1_200_000, 1_400_000]
    with AzureMkvWriter(session / "kinect" / "D1.mkv", calib, fps=5, color=False) as rec:
        for ts in stamps:
            rec.write(ts, depth_mm=np.full((h, w), 3000, np.uint16))
    (session / "session.json").write_text(json.dumps({"name": "depth", "kinect": [
        {"serial": "D1", "file": "kinect/D1.mkv"}, {"serial": "GONE", "file": "kinect/x.mkv"}]}))
    t = 3
    table = np.stack([np.array(stamps), np.array([5, 6, 7])], axis=1)
    res = _result(session, _body(t, ["D1", "GONE"], table), _chair(3), None,
                  _extrinsics(["D1", "GONE"]))
    write_report(res, tmp_path / "report", previews=2)
    doc = json.loads((tmp_path / "report" / "summary.json").read_text())
    shown = doc["report"]["previews"]
    assert len(shown) == 2
    notes = doc["report"]["notes"]
    assert len(notes) == 2 and all("GONE" in n for n in notes)
    img = _assert_png(tmp_path / "report" / shown[0])  # BGR: [D1 tile | note tile]
    th, tw = round(h * 0.5), round(w * 0.5)
    assert img.shape == (th, 2 * tw, 3)
    b, _, r = (int(x) for x in img[th // 2, tw // 2])
    assert b > r + 40  # the body (blue) blended over grey depth at the image centre
    page = (tmp_path / "report" / "index.html").read_text()
    assert all(f'src="{p}"' in page for p in shown)


def test_previews_on_the_fixture_session(tmp_path: Path) -> None:
    """Colour previews of the committed fixture's four cameras, one of them broken."""
    from couch.capture.calibration import calibrate_session

    ext = calibrate_session(FIXTURE)
    serials = list(ext.cameras)
    recordings = {s: FIXTURE / "kinect" / f"{s}.mkv" for s in serials}
    stamps = np.stack([[c.timestamp_us for c in open_azure_mkv(recordings[s])][:6]
                       for s in serials], axis=1)
    broken = tmp_path / "broken.mkv"
    broken.write_bytes(b"not a recording")
    session = tmp_path / "session"
    session.mkdir()
    (session / "session.json").write_text(json.dumps({"name": "fixture", "kinect": [
        {"serial": s, "file": str(broken if k == 3 else recordings[s].resolve())}
        for k, s in enumerate(serials)]}))
    # the body standing 2.5 m in front of the first colour camera, on the floor
    pose = ext.cameras[serials[0]].world_from_color
    where = pose[:3, 3] + 2.5 * pose[:3, 2]
    where[1] = 1.2
    body = _body(6, serials, stamps, transl=where)
    res = _result(session, body, _chair(6), _contacts(6), ext)
    write_report(res, tmp_path / "report", previews=2)
    doc = json.loads((tmp_path / "report" / "summary.json").read_text())
    assert len(doc["report"]["previews"]) == 2
    notes = doc["report"]["notes"]
    assert len(notes) == 2 and all(serials[3] in n and "unreadable" in n for n in notes)
    for p in doc["report"]["previews"]:
        img = _assert_png(tmp_path / "report" / p)
        assert img.shape == (720, 1280, 3)  # 2x2 tiles of the colour image at half size
