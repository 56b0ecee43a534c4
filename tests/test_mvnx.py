"""MVNX writer/reader: round trip, the written file checked by a plain non-streaming XML parser,
partial configurations, bad files, frame conversion to couch's world, and the SMPL table.

Constants marked "real file" are values read from the public MVN 2019 export
andres-fr/blender-mvnx-io io_anim_mvnx_utest/data/test_mocap.mvnx (not committed). Set
COUCH_MVNX_SAMPLE to a local copy of it to also run the byte-identical round trip on it.
"""

from __future__ import annotations

import datetime as dt
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from couch import rotations as R
from couch.capture.mvnx import (
    FOOT_CONTACTS,
    MVN_JOINTS,
    MVN_SEGMENTS,
    MVN_SENSORS,
    MVN_TO_SMPL,
    NAMESPACE,
    MvnxError,
    MvnxMetadata,
    MvnxPose,
    MvnxRecording,
    couch_to_mvn_positions,
    couch_to_mvn_quaternions,
    missing_for_full_body,
    mvn_rec_date,
    mvn_timecode,
    mvn_to_couch_positions,
    mvn_to_couch_quaternions,
    read_mvnx,
    segment_points_from_pose,
    smpl_segment_indices,
    write_mvnx,
)

NS = "{" + NAMESPACE + "}"
XSD_FRAME_ORDER = [
    "orientation", "position", "velocity", "acceleration", "angularVelocity",
    "angularAcceleration", "footContacts", "sensorAcceleration", "sensorFreeAcceleration",
    "sensorAngularVelocity", "sensorMagneticField", "sensorOrientation", "jointAngle",
    "jointAngleXZY", "jointAngleErgo", "jointAngleErgoXZY", "centerOfMass",
]
START_MS = 1542082631842  # real file: ms of the first normal frame


def _unit_quats(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    q = rng.normal(size=(*shape, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def make_recording(n: int = 5, sensors: tuple[str, ...] = MVN_SENSORS,
                   configuration: str = "FullBody", seed: int = 0) -> MvnxRecording:
    """A small recording with every optional element filled, values rounded to the file's
    6 decimals so a round trip can be compared exactly."""
    rng = np.random.default_rng(seed)
    s, ns, j = len(MVN_SEGMENTS), len(sensors), len(MVN_JOINTS)
    r6 = lambda a: np.round(a, 6)  # noqa: E731
    identity_pos = r6(rng.uniform(-0.7, 1.5, (s, 3)))
    calibration = {
        "identity": MvnxPose(np.tile([1.0, 0, 0, 0], (s, 1)), identity_pos),
        "tpose": MvnxPose(r6(_unit_quats(rng, (s,))), r6(rng.normal(size=(s, 3)))),
        "tpose-isb": MvnxPose(r6(_unit_quats(rng, (s,))), r6(rng.normal(size=(s, 3)))),
        "npose": MvnxPose(r6(_unit_quats(rng, (s,))), r6(rng.normal(size=(s, 3)))),
    }
    time_ms = np.array([0, 17, 33, 50, 67, 83, 100, 117][:n], dtype=np.int64)
    if n > 8:
        time_ms = np.round(np.arange(n) * 1000 / 60).astype(np.int64)
    unix_ms = START_MS + time_ms
    rec = MvnxRecording(
        frame_rate=60.0, segment_labels=list(MVN_SEGMENTS), sensor_labels=list(sensors),
        time_ms=time_ms, unix_ms=unix_ms, timecode=mvn_timecode(unix_ms, 60),
        orientation=r6(_unit_quats(rng, (n, s))), position=r6(rng.normal(size=(n, s, 3))),
        velocity=r6(rng.normal(size=(n, s, 3))), acceleration=r6(rng.normal(size=(n, s, 3))),
        angular_velocity=r6(rng.normal(size=(n, s, 3))),
        angular_acceleration=r6(rng.normal(size=(n, s, 3))),
        foot_contacts=rng.random((n, 4)) < 0.5,
        sensor_acceleration=r6(rng.normal(size=(n, ns, 3))),
        sensor_free_acceleration=r6(rng.normal(size=(n, ns, 3))),
        sensor_angular_velocity=r6(rng.normal(size=(n, ns, 3))),
        sensor_magnetic_field=r6(rng.normal(size=(n, ns, 3))),
        sensor_orientation=r6(_unit_quats(rng, (n, ns))),
        joint_angle=r6(rng.uniform(-90, 90, (n, j, 3))),
        joint_angle_xzy=r6(rng.uniform(-90, 90, (n, j, 3))),
        joint_angle_ergo=r6(rng.uniform(-90, 90, (n, 4, 3))),
        joint_angle_ergo_xzy=r6(rng.uniform(-90, 90, (n, 4, 3))),
        center_of_mass=r6(rng.normal(size=(n, 3))),
        calibration=calibration,
        metadata=MvnxMetadata(subject_label="sim subject", rec_date=mvn_rec_date(START_MS),
                              original_filename="C:\\data\\take & \"01\".mvn",
                              configuration=configuration, comment="a <synthetic> take",
                              security_code="0badc0de"),
    )
    rec.segment_points = {k: {p: np.round(v, 6) for p, v in pts.items()} for k, pts in
                          segment_points_from_pose(calibration["identity"],
                                                   rec.segment_labels).items()}
    return rec


def assert_same_recording(a: MvnxRecording, b: MvnxRecording, atol: float = 1e-9) -> None:
    assert a.frame_rate == b.frame_rate
    assert a.segment_labels == b.segment_labels and a.sensor_labels == b.sensor_labels
    assert np.array_equal(a.time_ms, b.time_ms) and np.array_equal(a.unix_ms, b.unix_ms)
    assert a.timecode == b.timecode
    for name in ("orientation", "position", "velocity", "acceleration", "angular_velocity",
                 "angular_acceleration", "sensor_acceleration", "sensor_free_acceleration",
                 "sensor_angular_velocity", "sensor_magnetic_field", "sensor_orientation",
                 "joint_angle", "joint_angle_xzy", "joint_angle_ergo", "joint_angle_ergo_xzy",
                 "center_of_mass"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.shape == y.shape, name
            np.testing.assert_allclose(x, y, atol=atol, err_msg=name)
    assert np.array_equal(a.foot_contacts, b.foot_contacts)
    assert list(a.calibration) == list(b.calibration)
    for k in a.calibration:
        np.testing.assert_allclose(a.calibration[k].orientation, b.calibration[k].orientation,
                                   atol=atol)
        np.testing.assert_allclose(a.calibration[k].position, b.calibration[k].position,
                                   atol=atol)
    assert [list(p) for p in a.segment_points.values()] == \
        [list(p) for p in b.segment_points.values()]
    for seg in a.segment_points:
        for label, v in a.segment_points[seg].items():
            np.testing.assert_allclose(v, b.segment_points[seg][label], atol=atol)
    assert list(map(tuple, a.joints)) == list(map(tuple, b.joints))
    assert list(map(tuple, a.ergonomic_joints)) == list(map(tuple, b.ergonomic_joints))
    assert list(a.foot_contact_labels) == list(b.foot_contact_labels)


# --------------------------------------------------------------------------- round trip


def test_write_read_round_trip(tmp_path: Path) -> None:
    rec = make_recording()
    path = tmp_path / "take.mvnx"
    write_mvnx(path, rec)
    back = read_mvnx(path)
    assert_same_recording(rec, back)
    m = back.metadata
    assert (m.subject_label, m.configuration, m.original_filename, m.comment,
            m.security_code, m.rec_date) == (
        "sim subject", "FullBody", "C:\\data\\take & \"01\".mvn", "a <synthetic> take",
        "0badc0de", "Tue Nov 13 04:17:11.842 2018")
    assert back.truncation is None and m.ignored_elements == ()
    assert np.array_equal(back.frame_index, np.arange(rec.n_frames))
    assert not list(tmp_path.glob(".*tmp*")), "atomic write left a temporary file"
    # writing what was read gives the same bytes
    write_mvnx(tmp_path / "again.mvnx", back)
    assert (tmp_path / "again.mvnx").read_bytes() == path.read_bytes()


def test_written_file_parsed_independently(tmp_path: Path) -> None:
    """A plain, non-streaming ElementTree parse of the output, checked against real exports."""
    rec = make_recording(n=4)
    path = tmp_path / "take.mvnx"
    write_mvnx(path, rec)
    text = path.read_text(encoding="utf-8")
    assert text.startswith('<?xml version="1.0" encoding="UTF-8"?>\n<!-- ')
    assert "\r" not in text and text.endswith("</mvnx>\n")
    assert "\n\t\t\t<frame time=" in text and "\n\t\t\t\t<orientation>" in text
    assert '<sensor label="Pelvis"/>' in text and "<comment></comment>" in text

    root = ET.parse(path).getroot()
    assert root.tag == NS + "mvnx" and root.get("version") == "4"
    assert root.get("{http://www.w3.org/2001/XMLSchema-instance}schemaLocation") == \
        f"{NAMESPACE} http://www.xsens.com/mvn/mvnx/schema.xsd"
    assert [c.tag for c in root] == [NS + "mvn", NS + "comment", NS + "subject",
                                     NS + "securityCode"]
    assert root.find(NS + "mvn").get("version") == "2019.0.0"
    assert root.find(NS + "securityCode").get("code") == "0badc0de"
    subject = root.find(NS + "subject")
    assert list(subject.attrib) == ["label", "torsoColor", "frameRate", "segmentCount",
                                    "recDate", "originalFilename", "configuration",
                                    "userScenario"]
    assert subject.get("frameRate") == "60" and subject.get("segmentCount") == "23"
    assert subject.get("originalFilename") == rec.metadata.original_filename
    assert [c.tag.removeprefix(NS) for c in subject] == [
        "comment", "segments", "sensors", "joints", "ergonomicJointAngles",
        "footContactDefinition", "frames"]

    segments = subject.find(NS + "segments")
    assert [(s.get("label"), s.get("id")) for s in segments] == \
        [(label, str(i + 1)) for i, label in enumerate(MVN_SEGMENTS)]
    pelvis_points = segments[0].find(NS + "points")
    assert [p.get("label") for p in pelvis_points] == ["pHipOrigin", "jL5S1", "jRightHip",
                                                      "jLeftHip"]
    jl5s1 = pelvis_points[1].find(NS + "pos_b").text
    assert re.fullmatch(r"-?\d+\.\d{6} -?\d+\.\d{6} -?\d+\.\d{6}", jl5s1)
    ident = rec.calibration["identity"].position
    np.testing.assert_allclose(np.array(jl5s1.split(), float), ident[1] - ident[0], atol=1e-6)
    assert [s.get("label") for s in subject.find(NS + "sensors")] == list(MVN_SENSORS)
    joints = subject.find(NS + "joints")
    assert [(j.get("label"), j.find(NS + "connector1").text, j.find(NS + "connector2").text)
            for j in joints] == list(MVN_JOINTS)
    assert joints[0].find(NS + "connector1").text == "Pelvis/jL5S1"
    assert [(c.get("label"), c.get("index"))
            for c in subject.find(NS + "footContactDefinition")] == \
        [(label, str(i)) for i, label in enumerate(FOOT_CONTACTS)]

    frames = subject.find(NS + "frames")
    assert frames.attrib == {"segmentCount": "23", "sensorCount": "17", "jointCount": "22"}
    types = [f.get("type") for f in frames]
    assert types == ["identity", "tpose", "tpose-isb", "npose"] + ["normal"] * 4
    for f in frames[:4]:
        assert f.get("index") is None and (f.get("time"), f.get("tc"), f.get("ms")) == \
            ("0", "00:00:00:00", "0")
        assert [c.tag.removeprefix(NS) for c in f] == ["orientation", "position"]
    counts = {"orientation": 92, "position": 69, "velocity": 69, "acceleration": 69,
              "angularVelocity": 69, "angularAcceleration": 69, "footContacts": 4,
              "sensorAcceleration": 51, "sensorFreeAcceleration": 51,
              "sensorAngularVelocity": 51, "sensorMagneticField": 51, "sensorOrientation": 68,
              "jointAngle": 66, "jointAngleXZY": 66, "jointAngleErgo": 12,
              "jointAngleErgoXZY": 12, "centerOfMass": 3}
    fields = {"orientation": "orientation", "position": "position", "velocity": "velocity",
              "sensorFreeAcceleration": "sensor_free_acceleration",
              "sensorOrientation": "sensor_orientation", "jointAngle": "joint_angle",
              "centerOfMass": "center_of_mass"}
    for k, f in enumerate(frames[4:]):
        assert list(f.attrib) == ["time", "index", "tc", "ms", "type"]
        assert f.get("index") == str(k) and f.get("time") == str(rec.time_ms[k])
        assert f.get("ms") == str(START_MS + rec.time_ms[k])
        assert re.fullmatch(r"\d\d:\d\d:\d\d:\d\d", f.get("tc"))
        assert [c.tag.removeprefix(NS) for c in f] == XSD_FRAME_ORDER
        for child in f:
            name = child.tag.removeprefix(NS)
            tokens = child.text.split(" ")
            assert len(tokens) == counts[name], name
            if name == "footContacts":
                assert set(tokens) <= {"0", "1"}
                assert [t == "1" for t in tokens] == rec.foot_contacts[k].tolist()
            else:
                assert all(re.fullmatch(r"-?\d+\.\d{6}", t) for t in tokens), name
            if name in fields:
                np.testing.assert_allclose(np.array(tokens, float),
                                           getattr(rec, fields[name])[k].ravel(), atol=1e-9)
    assert frames[4].get("tc") == "04:17:11:50"  # real file: first frame's tc for this ms


def test_writer_derives_points_from_identity_and_checks_shapes(tmp_path: Path) -> None:
    rec = make_recording(n=2)
    rec.segment_points = {}
    write_mvnx(tmp_path / "a.mvnx", rec)
    back = read_mvnx(tmp_path / "a.mvnx")
    assert list(back.segment_points["T8"]) == ["jT9T8", "jT1C7", "jRightT4Shoulder",
                                               "jLeftT4Shoulder"]
    rec.calibration = {}
    with pytest.raises(ValueError, match="no points"):
        write_mvnx(tmp_path / "b.mvnx", rec)
    rec = make_recording(n=2)
    rec.velocity = rec.velocity[:, :5]
    with pytest.raises(ValueError, match=r"velocity.*expected \(2, 23, 3\)"):
        write_mvnx(tmp_path / "c.mvnx", rec)
    assert not (tmp_path / "c.mvnx").exists()


def test_progress_bar_reads_the_same(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rec = make_recording(n=2)
    write_mvnx(tmp_path / "p.mvnx", rec)
    assert_same_recording(rec, read_mvnx(tmp_path / "p.mvnx", progress=True))
    assert "p.mvnx" in capsys.readouterr().err


def test_minimal_recording_without_optional_elements(tmp_path: Path) -> None:
    full = make_recording(n=3)
    rec = MvnxRecording(frame_rate=120, segment_labels=full.segment_labels, sensor_labels=[],
                        time_ms=full.time_ms[:3], unix_ms=full.unix_ms[:3],
                        timecode=full.timecode[:3], orientation=full.orientation[:3],
                        position=full.position[:3], segment_points=full.segment_points,
                        ergonomic_joints=[], foot_contact_labels=[])
    write_mvnx(tmp_path / "m.mvnx", rec)
    root = ET.parse(tmp_path / "m.mvnx").getroot()
    subject = root.find(NS + "subject")
    assert subject.get("frameRate") == "120" and subject.find(NS + "sensors") is None
    back = read_mvnx(tmp_path / "m.mvnx")
    assert back.velocity is None and back.foot_contacts is None and back.sensor_labels == []
    np.testing.assert_allclose(back.orientation, rec.orientation)


# --------------------------------------------------------------------------- real structure


REAL_STYLE = """<?xml version="1.0" encoding="UTF-8"?>
<mvnx version="4" xmlns="http://www.xsens.com/mvn/mvnx">
\t<mvn version="2018.0.0" build="b"/>
\t<comment>older export</comment>
\t<subject label="s" torsoColor="#e96417" frameRate="60" segmentCount="2" recDate="d"
\t         originalFilename="f" configuration="Custom" userScenario="singleLevel">
\t\t<comment></comment>
\t\t<segments>
\t\t\t<segment label="Pelvis" id="1"><points>
\t\t\t\t<point label="pHipOrigin"><pos_s>0.000000 0.000000 0.000000</pos_s></point>
\t\t\t\t<point label="jL5S1"><pos_s>-0.000220 0.000000 0.114960</pos_s></point>
\t\t\t</points></segment>
\t\t\t<segment label="L5" id="2"><points>
\t\t\t\t<point label="jL5S1"><pos_s>0 0 0</pos_s></point>
\t\t\t</points></segment>
\t\t</segments>
\t\t<sensors><sensor label="Pelvis"/></sensors>
\t\t<joints><joint label="jL5S1"><connector1>Pelvis/jL5S1</connector1>
\t\t\t<connector2>L5/jL5S1</connector2></joint></joints>
\t\t<frames segmentCount="2" sensorCount="1" jointCount="1">
\t\t\t<frame time="0" tc="00:00:00:00" ms="0" type="identity">
\t\t\t\t<orientation>1 0 0 0 1 0 0 0</orientation>
\t\t\t\t<position>0 0 0.865664 -0.000220 0 0.980624</position>
\t\t\t</frame>
\t\t\t<frame time="0" tc="00:00:00:00" ms="0" type="npose">
\t\t\t\t<orientation>1 0 0 0 1 0 0 0</orientation>
\t\t\t\t<position>0 0 0.9 0 0 1.0</position>
\t\t\t</frame>
\t\t\t<frame time="0" index="0" tc="04:17:11:50" ms="1542082631842" type="normal">
\t\t\t\t<orientation>1 0 0 0 0.5 0.5 0.5 0.5</orientation>
\t\t\t\t<position>0 0 1 0 0 1.1</position>
\t\t\t\t<footContacts>1 0 0 1</footContacts>
\t\t\t\t<sensorOrientation>1 0 0 0</sensorOrientation>
\t\t\t\t<jointAngle>1.5 -2 3</jointAngle>
\t\t\t\t<centerOfMass>0.1 0.2 0.3 0 0 0 0 0 0</centerOfMass>
\t\t\t\t<marker>1</marker>
\t\t\t</frame>
\t\t\t<frame time="17" index="1" tc="04:17:11:51" ms="1542082631859" type="normal">
\t\t\t\t<orientation>1 0 0 0 0.5 0.5 0.5 0.5</orientation>
\t\t\t\t<position>0 0 1 0 0 1.2</position>
\t\t\t\t<footContacts>0 0 0 0</footContacts>
\t\t\t\t<sensorOrientation>0 1 0 0</sensorOrientation>
\t\t\t\t<jointAngle>0 0 0</jointAngle>
\t\t\t\t<centerOfMass>0.1 0.2 0.4 0 0 0 0 0 0</centerOfMass>
\t\t\t</frame>
\t\t</frames>
\t</subject>
\t<securityCode code="87b44419"/>
</mvnx>
"""


def test_reader_accepts_older_and_custom_layouts(tmp_path: Path) -> None:
    """pos_s points, an npose calibration frame, no index on calibration frames, no
    footContactDefinition / ergonomic angles, unmodelled elements, a 9-value centerOfMass."""
    path = tmp_path / "old.mvnx"
    path.write_text(REAL_STYLE, encoding="utf-8")
    rec = read_mvnx(path)
    assert rec.segment_labels == ["Pelvis", "L5"] and rec.sensor_labels == ["Pelvis"]
    assert rec.metadata.point_tag == "pos_s" and rec.metadata.ignored_elements == ("marker",)
    np.testing.assert_allclose(rec.segment_points["Pelvis"]["jL5S1"], [-0.00022, 0, 0.11496])
    assert list(rec.calibration) == ["identity", "npose"]
    assert rec.orientation.shape == (2, 2, 4) and rec.time_ms.tolist() == [0, 17]
    assert rec.foot_contacts.tolist() == [[True, False, False, True], [False] * 4]
    assert rec.center_of_mass.shape == (2, 9) and rec.joint_angle.shape == (2, 1, 3)
    assert rec.velocity is None
    gap = missing_for_full_body(rec)
    assert not gap.complete and "Head" in gap.missing_segments and "T8" in gap.missing_sensors
    # written again (pos_s kept) and re-read, it is the same recording
    write_mvnx(tmp_path / "again.mvnx", rec)
    assert "<pos_s>" in (tmp_path / "again.mvnx").read_text()
    assert_same_recording(rec, read_mvnx(tmp_path / "again.mvnx"))


@pytest.mark.skipif(not os.environ.get("COUCH_MVNX_SAMPLE"),
                    reason="set COUCH_MVNX_SAMPLE to a local copy of the public MVN 2019 sample")
def test_real_mvn_sample_round_trips_byte_identical(tmp_path: Path) -> None:
    real = Path(os.environ["COUCH_MVNX_SAMPLE"])
    rec = read_mvnx(real)
    assert rec.metadata.configuration == "UpperBody" and len(rec.sensor_labels) == 11
    assert rec.n_frames == 112 and list(rec.calibration) == ["identity", "tpose", "tpose-isb"]
    assert mvn_timecode(rec.unix_ms, rec.frame_rate) == rec.timecode
    write_mvnx(tmp_path / "copy.mvnx", rec)
    assert (tmp_path / "copy.mvnx").read_bytes() == real.read_bytes()


# --------------------------------------------------------------------------- partial config


def test_partial_upper_body_configuration(tmp_path: Path) -> None:
    upper = MVN_SENSORS[:11]
    rec = make_recording(n=3, sensors=upper, configuration="UpperBody")
    write_mvnx(tmp_path / "upper.mvnx", rec)
    frames = ET.parse(tmp_path / "upper.mvnx").getroot().find(f"{NS}subject/{NS}frames")
    assert frames.get("sensorCount") == "11" and frames.get("segmentCount") == "23"
    back = read_mvnx(tmp_path / "upper.mvnx")
    assert back.sensor_labels == list(upper)
    assert back.sensor_free_acceleration.shape == (3, 11, 3)
    assert back.sensor_orientation.shape == (3, 11, 4)
    assert back.orientation.shape == (3, 23, 4)
    gap = missing_for_full_body(back)
    assert not gap.complete and gap.missing_segments == ()
    assert gap.missing_sensors == ("RightUpperLeg", "RightLowerLeg", "RightFoot",
                                   "LeftUpperLeg", "LeftLowerLeg", "LeftFoot")
    assert gap.unmeasured_segments == ("RightUpperLeg", "RightLowerLeg", "RightFoot",
                                       "RightToe", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot",
                                       "LeftToe")
    assert str(gap).startswith("UpperBody lacks for a full-body fit")
    full = missing_for_full_body(make_recording(n=1))
    assert full.complete and "complete" in str(full)


def test_sensor_count_must_match_labels(tmp_path: Path) -> None:
    rec = make_recording(n=2, sensors=MVN_SENSORS[:11])
    write_mvnx(tmp_path / "a.mvnx", rec)
    text = (tmp_path / "a.mvnx").read_text().replace('sensorCount="11"', 'sensorCount="17"')
    (tmp_path / "a.mvnx").write_text(text)
    with pytest.raises(MvnxError, match=r"a\.mvnx.*sensorCount=17 but the header lists 11"):
        read_mvnx(tmp_path / "a.mvnx")


# --------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> tuple[MvnxRecording, bytes]:
    rec = make_recording(n=6)
    path = tmp_path_factory.mktemp("mvnx") / "good.mvnx"
    write_mvnx(path, rec)
    return rec, path.read_bytes()


def _frame_start(data: bytes, index: int) -> int:
    return data.index(f' index="{index}" tc='.encode())


def test_truncated_file_raises_and_can_be_recovered(tmp_path: Path, written) -> None:
    rec, data = written
    cut = _frame_start(data, 3) + 300  # inside frame index 3
    path = tmp_path / "cut.mvnx"
    path.write_bytes(data[:cut])
    with pytest.raises(MvnxError) as info:
        read_mvnx(path)
    msg = str(info.value)
    assert str(path) in msg and "line" in msg and "ends early" in msg
    assert "last complete frame: frame index 2" in msg and "3 normal frames read" in msg
    back = read_mvnx(path, recover_truncated=True)
    assert back.n_frames == 3 and "kept the 3 complete normal frames" in back.truncation
    np.testing.assert_allclose(back.position, rec.position[:3])
    assert back.timecode == rec.timecode[:3]


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(fraction=st.floats(0.0, 1.0))
def test_any_cut_gives_mvnx_error_or_a_prefix(tmp_path: Path, written, fraction: float) -> None:
    rec, data = written
    cut = int(fraction * len(data))
    path = tmp_path / "cut.mvnx"
    path.write_bytes(data[:cut])
    complete = cut >= len(data) - 1  # only the final newline missing
    if complete:
        assert read_mvnx(path).n_frames == rec.n_frames
        return
    with pytest.raises(MvnxError, match=re.escape(str(path))):
        read_mvnx(path)
    try:
        back = read_mvnx(path, recover_truncated=True)
    except MvnxError:
        return  # cut before the first complete frame
    k = back.n_frames
    assert k < rec.n_frames and back.truncation
    np.testing.assert_allclose(back.orientation, rec.orientation[:k])


def test_malformed_xml_names_line(tmp_path: Path, written) -> None:
    _, data = written
    start = _frame_start(data, 1)
    bad = data[:start] + data[start:].replace(b"</position>", b"</positon>", 1)
    path = tmp_path / "bad.mvnx"
    path.write_bytes(bad)
    line = bad[:bad.index(b"</positon>")].count(b"\n") + 1
    with pytest.raises(MvnxError, match=rf"bad\.mvnx: line {line}, column \d+: malformed XML "
                                        r"\(mismatched tag\); last complete frame: frame "
                                        r"index 0"):
        read_mvnx(path)
    with pytest.raises(MvnxError, match="malformed"):
        read_mvnx(path, recover_truncated=True)  # damage is not a cut: no recovery


def _replace_in_frame(data: bytes, index: int, old: bytes, new: bytes) -> bytes:
    start = _frame_start(data, index)
    return data[:start] + data[start:].replace(old, new, 1)


def test_wrong_element_size_names_frame_and_expectation(tmp_path: Path, written) -> None:
    _, data = written
    path = tmp_path / "size.mvnx"
    path.write_bytes(_replace_in_frame(data, 4, b"<orientation>", b"<orientation>0.5 "))
    with pytest.raises(MvnxError, match=r"frame index 4 .*<orientation> has 93 values, "
                                        r"expected 92 \(4 × segmentCount 23\)"):
        read_mvnx(path)
    path.write_bytes(_replace_in_frame(data, 2, b"<footContacts>", b"<footContacts>1 "))
    with pytest.raises(MvnxError, match=r"frame index 2 .*<footContacts> has 5 values, "
                                        "expected 4"):
        read_mvnx(path)
    path.write_bytes(_replace_in_frame(data, 1, b"<centerOfMass>", b"<centerOfMass>x "))
    with pytest.raises(MvnxError, match=r"frame index 1 .*<centerOfMass> holds 'x'"):
        read_mvnx(path)


def test_inconsistent_or_missing_elements(tmp_path: Path, written) -> None:
    _, data = written
    path = tmp_path / "x.mvnx"
    start = _frame_start(data, 3)
    a = data.index(b"<velocity>", start)
    b = data.index(b"</velocity>", start) + len(b"</velocity>")
    path.write_bytes(data[:a] + data[b:])
    with pytest.raises(MvnxError, match=r"frame index 3 .*differ from earlier frames.*"
                                        "missing: \\['velocity'\\]"):
        read_mvnx(path)
    a = data.index(b"<position>", start)
    b = data.index(b"</position>", start) + len(b"</position>")
    path.write_bytes(data[:a] + data[b:])
    with pytest.raises(MvnxError, match=r"frame index 3 .*missing <position>"):
        read_mvnx(path)


@pytest.mark.parametrize(("content", "expected"), [
    (b"", "file ends before the <mvnx> root element"),
    (b"\x00\x01binary junk", "not an XML document"),
    (b'<?xml version="1.0"?><svg xmlns="http://www.w3.org/2000/svg"/>', "not an MVNX file"),
    (b'<mvnx xmlns="http://www.xsens.com/mvn/mvnx" version="4"><mvn version="x" build="y"/>'
     b"</mvnx>", "no <frames> element"),
])
def test_not_mvnx(tmp_path: Path, content: bytes, expected: str) -> None:
    path = tmp_path / "other.xml"
    path.write_bytes(content)
    with pytest.raises(MvnxError, match=re.escape(expected)) as info:
        read_mvnx(path)
    assert str(path) in str(info.value)


# --------------------------------------------------------------------------- helpers


def test_frame_conversion_to_couch_world() -> None:
    forward, left, up = np.eye(3)  # MVN: X forward, Y left, Z up
    assert mvn_to_couch_positions(forward).tolist() == [0, 0, 1]  # couch: Z forward
    assert mvn_to_couch_positions(left).tolist() == [1, 0, 0]  # X left
    assert mvn_to_couch_positions(up).tolist() == [0, 1, 0]  # Y up
    rng = np.random.default_rng(3)
    q = _unit_quats(rng, (7, 5))
    p = rng.normal(size=(7, 5, 3))
    # rotating then converting == converting then rotating
    rotated = np.einsum("...ij,...j->...i", R.quat_to_matrix(q), p)
    q_ours = mvn_to_couch_quaternions(q)
    rotated_ours = np.einsum("...ij,...j->...i", R.quat_to_matrix(q_ours),
                             mvn_to_couch_positions(p))
    np.testing.assert_allclose(rotated_ours, mvn_to_couch_positions(rotated), atol=1e-12)
    np.testing.assert_allclose(couch_to_mvn_positions(mvn_to_couch_positions(p)), p)
    np.testing.assert_allclose(couch_to_mvn_quaternions(q_ours), q)
    # a quarter turn about MVN's up axis (heading) is a turn about couch's Y
    yaw = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(R.quat_to_axis_angle(mvn_to_couch_quaternions(yaw)),
                               [0, np.pi / 2, 0], atol=1e-12)


def test_smpl_table() -> None:
    from couch.body import JOINT_NAMES

    assert tuple(MVN_TO_SMPL) == JOINT_NAMES
    assert set(MVN_TO_SMPL.values()) <= set(MVN_SEGMENTS)
    idx = smpl_segment_indices(MVN_SEGMENTS)
    assert idx.shape == (24,) and MVN_SEGMENTS[idx[JOINT_NAMES.index("spine2")]] == "T12"
    assert MVN_SEGMENTS[idx[JOINT_NAMES.index("left_wrist")]] == "LeftHand"
    no_t12 = [s for s in MVN_SEGMENTS if s != "T12"]
    assert no_t12[smpl_segment_indices(no_t12)[JOINT_NAMES.index("spine2")]] == "L3"
    with pytest.raises(ValueError, match="left_knee←LeftLowerLeg"):
        smpl_segment_indices([s for s in MVN_SEGMENTS if s != "LeftLowerLeg"])


def test_time_helpers_match_real_file() -> None:
    # real file: frame index 0, 8 and 110 (60 Hz)
    ms = [1542082631842, 1542082631976, 1542082633675]
    assert mvn_timecode(ms, 60) == ["04:17:11:50", "04:17:11:58", "04:17:13:40"]
    cet = dt.timezone(dt.timedelta(hours=1))
    assert mvn_rec_date(1542082631827, cet) == "Tue Nov 13 05:17:11.827 2018"


def test_segment_points_from_identity_pose_match_real_file() -> None:
    # real file: identity positions of Pelvis, L5, RightUpperLeg and Pelvis' pos_b points
    pos = np.zeros((23, 3))
    pos[0] = [0, 0, 0.865664]
    pos[1] = [-0.00022, 0, 0.980624]
    pos[15] = [0.00011, -0.095115, 0.866745]
    pose = MvnxPose(np.tile([1.0, 0, 0, 0], (23, 1)), pos)
    pts = segment_points_from_pose(pose, MVN_SEGMENTS)
    np.testing.assert_allclose(pts["Pelvis"]["jL5S1"], [-0.00022, 0, 0.11496], atol=1e-9)
    np.testing.assert_allclose(pts["Pelvis"]["jRightHip"], [0.00011, -0.095115, 0.001081],
                               atol=2e-6)
    assert next(iter(pts["Pelvis"])) == "pHipOrigin" and not pts["L5"]["jL5S1"].any()
