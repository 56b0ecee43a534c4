"""Azure Kinect calibration.json parsing/writing and the SDK's mode-specific intrinsics.

Expected numbers are computed by hand from the formulas of the Sensor SDK's
``src/transformation/mode_specific_calibration.c`` (not from the module's tables), and the
distortion order is checked against a transcription of ``intrinsic_transformation.c``.
"""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from couch.capture.azure_calibration import (
    COLOR_RESOLUTIONS,
    DEPTH_MODES,
    CameraIntrinsics,
    KinectCalibration,
)

# The calibration.json of a retail Azure Kinect (serial 001514394512) as embedded in the
# k4arecorder file tests/assets/recording.mkv of etiennedub/pyk4a (MIT licence); the IMU section
# is shortened to the gyro entry.
REAL_JSON = json.dumps({"CalibrationInformation": {
    "Cameras": [
        {"Intrinsics": {"ModelParameterCount": 14, "ModelParameters": [
            0.51296979188919067, 0.51692354679107666, 0.4927808940410614, 0.49290284514427185,
            0.54793977737426758, -0.020971370860934258, -0.0026522316038608551,
            0.88967907428741455, 0.086130209267139435, -0.013910384848713875, 0, 0,
            -7.2104157879948616E-5, 2.0557534298859537E-5],
            "ModelType": "CALIBRATION_LensDistortionModelBrownConrady"},
         "Location": "CALIBRATION_CameraLocationD0", "Purpose": "CALIBRATION_CameraPurposeDepth",
         "MetricRadius": 1.7399997711181641,
         "Rt": {"Rotation": [1, 0, 0, 0, 1, 0, 0, 0, 1], "Translation": [0, 0, 0]},
         "SensorHeight": 1024, "SensorWidth": 1024,
         "Shutter": "CALIBRATION_ShutterTypeUndefined",
         "ThermalAdjustmentParams": {"Params": [0] * 12}},
        {"Intrinsics": {"ModelParameterCount": 14, "ModelParameters": [
            0.49984714388847351, 0.50661760568618774, 0.47796511650085449, 0.63742393255233765,
            0.33012130856513977, -2.4893965721130371, 1.453670859336853, 0.20891207456588745,
            -2.302915096282959, 1.3751275539398193, 0, 0, -0.00012944525224156678,
            -0.00016178244550246745],
            "ModelType": "CALIBRATION_LensDistortionModelBrownConrady"},
         "Location": "CALIBRATION_CameraLocationPV0",
         "Purpose": "CALIBRATION_CameraPurposePhotoVideo", "MetricRadius": 0,
         "Rt": {"Rotation": [0.99999922513961792, 0.0011817576596513391, -0.00044814043212682009,
                             -0.0011387512786313891, 0.99628061056137085, 0.0861603245139122,
                             0.0005482942215166986, -0.086159750819206238, 0.9962812066078186],
                "Translation": [-0.032083429396152496, -0.0022053730208426714,
                                0.0038836926687508821]},
         "SensorHeight": 3072, "SensorWidth": 4096,
         "Shutter": "CALIBRATION_ShutterTypeUndefined",
         "ThermalAdjustmentParams": {"Params": [0] * 12}}],
    "InertialSensors": [{"SensorType": "CALIBRATION_InertialSensorType_Gyro",
                         "Rt": {"Rotation": [1, 0, 0, 0, 1, 0, 0, 0, 1],
                                "Translation": [0, 0, 0]}}],
    "Metadata": {"SerialId": "001514394512", "FactoryCalDate": "11/9/2019 10:32:12 AM GMT",
                 "Version": {"Major": 1, "Minor": 2}, "DeviceName": "AzureKinect-PV",
                 "Notes": "PV0_max_radius_invalid"}}}, separators=(",", ":"))


def _doc() -> dict:
    return json.loads(REAL_JSON)


def _random_calibration(rng: np.random.Generator, depth_mode: str, color_res: str,
                        ) -> KinectCalibration:
    d, c = DEPTH_MODES[depth_mode], COLOR_RESOLUTIONS[color_res]

    def intr(w: int, h: int) -> CameraIntrinsics:
        return CameraIntrinsics(width=w, height=h, fx=rng.uniform(0.4, 0.8) * w,
                                fy=rng.uniform(0.4, 0.8) * w, cx=w / 2 + rng.normal(0, 5),
                                cy=h / 2 + rng.normal(0, 5), dist=rng.normal(0, 0.1, 8),
                                metric_radius=rng.uniform(1.0, 2.0))

    a = rng.normal(0, 0.1, 3)
    rot, _ = cv2.Rodrigues(a)
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = [-0.032, -0.002, 0.004]
    return KinectCalibration(depth=intr(d.width, d.height), color=intr(c.width, c.height),
                             color_from_depth=t, depth_mode=depth_mode,
                             color_resolution=color_res, serial="000123456789")


def _assert_close(a: KinectCalibration, b: KinectCalibration) -> None:
    for x, y in ((a.depth, b.depth), (a.color, b.color)):
        assert (x.width, x.height) == (y.width, y.height)
        np.testing.assert_allclose([x.fx, x.fy, x.cx, x.cy, x.metric_radius],
                                   [y.fx, y.fy, y.cx, y.cy, y.metric_radius], rtol=0, atol=1e-9)
        np.testing.assert_allclose(x.dist, y.dist, rtol=0, atol=1e-15)
    np.testing.assert_allclose(a.color_from_depth, b.color_from_depth, rtol=0, atol=1e-15)
    assert (a.depth_mode, a.color_resolution, a.serial) == (b.depth_mode, b.color_resolution,
                                                            b.serial)


# ------------------------------------------------------------------ mode-specific intrinsics
def test_formats_md_example_nfov_unbinned():
    doc = _doc()
    doc["CalibrationInformation"]["Cameras"][0]["Intrinsics"]["ModelParameters"][:4] = [
        0.51297, 0.5, 0.49278, 0.49278]
    cal = KinectCalibration.from_json(json.dumps(doc), "NFOV_UNBINNED", "720P")
    assert (cal.depth.width, cal.depth.height) == (640, 576)
    assert cal.depth.fx == pytest.approx(504.6, abs=0.05)
    assert cal.depth.cx == pytest.approx(332.8, abs=0.05)
    # exactly: fx * 1024 and cx * 1024 - 192 (crop) - 0.5 (corner -> centre convention)
    assert cal.depth.fx == pytest.approx(0.49278 * 1024, abs=1e-9)
    assert cal.depth.cx == pytest.approx(0.51297 * 1024 - 192 - 0.5, abs=1e-9)


def test_real_device_json_nfov_unbinned_720p():
    cal = KinectCalibration.from_json(REAL_JSON)  # defaults: NFOV_UNBINNED, 720P
    p = _doc()["CalibrationInformation"]["Cameras"]
    dp, cp = p[0]["Intrinsics"]["ModelParameters"], p[1]["Intrinsics"]["ModelParameters"]
    d, c = cal.depth, cal.color
    assert (d.width, d.height, c.width, c.height) == (640, 576, 1280, 720)
    assert d.cx == pytest.approx(dp[0] * 1024 - 192 - 0.5, abs=1e-9)
    assert d.cy == pytest.approx(dp[1] * 1024 - 180 - 0.5, abs=1e-9)
    assert d.fx == pytest.approx(dp[2] * 1024, abs=1e-9)
    assert d.fy == pytest.approx(dp[3] * 1024, abs=1e-9)
    # 720P is the 1280x960 4:3 image cropped by 120 rows top and bottom.
    assert c.cx == pytest.approx(cp[0] * 1280 - 0.5, abs=1e-9)
    assert c.cy == pytest.approx(cp[1] * 960 - 120 - 0.5, abs=1e-9)
    assert c.fx == pytest.approx(cp[2] * 1280, abs=1e-9)
    assert c.fy == pytest.approx(cp[3] * 960, abs=1e-9)
    # OpenCV order [k1,k2,p1,p2,k3,k4,k5,k6] from the device's [..k1..k6, codx, cody, p2, p1]
    np.testing.assert_array_equal(
        d.dist, [dp[4], dp[5], dp[13], dp[12], dp[6], dp[7], dp[8], dp[9]])
    assert d.metric_radius == pytest.approx(1.7399997711181641)
    assert c.metric_radius == 1.7  # MetricRadius 0 = "not estimated" -> SDK default
    assert cal.serial == "001514394512"
    t = cal.color_from_depth
    np.testing.assert_allclose(t[:3, 3], [-0.032083429396152496, -0.0022053730208426714,
                                          0.0038836926687508821])
    assert t[0, 1] == pytest.approx(0.0011817576596513391)  # row-major rotation
    np.testing.assert_allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-6)


@pytest.mark.parametrize(("mode", "size", "scale", "crop"), [
    ("NFOV_2X2BINNED", (320, 288), 512, (96, 90)),
    ("NFOV_UNBINNED", (640, 576), 1024, (192, 180)),
    ("WFOV_2X2BINNED", (512, 512), 512, (0, 0)),
    ("WFOV_UNBINNED", (1024, 1024), 1024, (0, 0)),
    ("PASSIVE_IR", (1024, 1024), 1024, (0, 0)),
])
def test_depth_modes(mode, size, scale, crop):
    cal = KinectCalibration.from_json(REAL_JSON, mode, "720P")
    dp = _doc()["CalibrationInformation"]["Cameras"][0]["Intrinsics"]["ModelParameters"]
    assert (cal.depth.width, cal.depth.height) == size
    assert cal.depth.cx == pytest.approx(dp[0] * scale - crop[0] - 0.5, abs=1e-9)
    assert cal.depth.cy == pytest.approx(dp[1] * scale - crop[1] - 0.5, abs=1e-9)
    assert cal.depth.fy == pytest.approx(dp[3] * scale, abs=1e-9)


@pytest.mark.parametrize(("res", "size", "binned", "crop_y"), [
    ("720P", (1280, 720), (1280, 960), 120),
    ("1080P", (1920, 1080), (1920, 1440), 180),
    ("1440P", (2560, 1440), (2560, 1920), 240),
    ("1536P", (2048, 1536), (2048, 1536), 0),
    ("2160P", (3840, 2160), (3840, 2880), 360),
    ("3072P", (4096, 3072), (4096, 3072), 0),
])
def test_color_resolutions(res, size, binned, crop_y):
    cal = KinectCalibration.from_json(REAL_JSON, "NFOV_UNBINNED", res)
    cp = _doc()["CalibrationInformation"]["Cameras"][1]["Intrinsics"]["ModelParameters"]
    assert (cal.color.width, cal.color.height) == size
    assert cal.color.cx == pytest.approx(cp[0] * binned[0] - 0.5, abs=1e-9)
    assert cal.color.cy == pytest.approx(cp[1] * binned[1] - crop_y - 0.5, abs=1e-9)
    assert cal.color.fy == pytest.approx(cp[3] * binned[1], abs=1e-9)


def test_legacy_16_9_color_calibration_is_converted_to_4_3():
    doc = _doc()
    cam = doc["CalibrationInformation"]["Cameras"][1]
    cam["SensorHeight"] = 2304
    cam["Intrinsics"]["ModelParameters"][:4] = [0.5, 0.52, 0.48, 0.85]
    cal = KinectCalibration.from_json(json.dumps(doc), "NFOV_UNBINNED", "720P")
    # SDK: 16:9 {4096x2304, crop (0,-384), out 4096x3072} unitized, then 720P pixelised.
    cy43 = (0.52 * 2304 + 384) / 3072
    fy43 = 0.85 * 2304 / 3072
    assert cal.color.cy == pytest.approx(cy43 * 960 - 120 - 0.5, abs=1e-9)
    assert cal.color.fy == pytest.approx(fy43 * 960, abs=1e-9)
    assert cal.color.cx == pytest.approx(0.5 * 1280 - 0.5, abs=1e-9)


def _sdk_project(intr: CameraIntrinsics, xy: np.ndarray) -> np.ndarray:
    """Brown-Conrady projection transcribed from the SDK's intrinsic_transformation.c."""
    k1, k2, p1, p2, k3, k4, k5, k6 = intr.dist
    x, y = xy[:, 0], xy[:, 1]
    rs = x * x + y * y
    a = 1 + k1 * rs + k2 * rs**2 + k3 * rs**3
    b = 1 + k4 * rs + k5 * rs**2 + k6 * rs**3
    d = a / b
    xd = x * d + (rs + 2 * x * x) * p2 + 2 * x * y * p1
    yd = y * d + (rs + 2 * y * y) * p1 + 2 * x * y * p2
    return np.stack([xd * intr.fx + intr.cx, yd * intr.fy + intr.cy], axis=1)


def test_opencv_model_matches_sdk_projection():
    cal = KinectCalibration.from_json(REAL_JSON)
    rng = np.random.default_rng(3)
    for intr in (cal.depth, cal.color):
        xy = rng.uniform(-0.6, 0.6, (200, 2))
        pts = np.concatenate([xy, np.ones((200, 1))], axis=1)
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), intr.K(), intr.dist)
        np.testing.assert_allclose(uv.reshape(-1, 2), _sdk_project(intr, xy), atol=1e-6)


# ------------------------------------------------------------------ writer / round trip
@pytest.mark.parametrize("depth_mode", sorted(DEPTH_MODES))
@pytest.mark.parametrize("color_res", ["720P", "1536P", "2160P"])
def test_round_trip(depth_mode, color_res):
    cal = _random_calibration(np.random.default_rng(len(depth_mode) + len(color_res)),
                              depth_mode, color_res)
    back = KinectCalibration.from_json(cal.to_json(), depth_mode, color_res)
    _assert_close(cal, back)


def test_real_json_round_trip_keeps_imu_and_metadata():
    cal = KinectCalibration.from_json(REAL_JSON)
    out = json.loads(cal.to_json())["CalibrationInformation"]
    ref = _doc()["CalibrationInformation"]
    assert out["Metadata"] == ref["Metadata"]
    assert out["InertialSensors"] == ref["InertialSensors"]
    for got, want in zip(out["Cameras"], ref["Cameras"], strict=True):
        np.testing.assert_allclose(got["Intrinsics"]["ModelParameters"],
                                   want["Intrinsics"]["ModelParameters"], rtol=0, atol=1e-15)
        np.testing.assert_allclose(got["Rt"]["Rotation"], want["Rt"]["Rotation"], atol=1e-15)
    _assert_close(cal, KinectCalibration.from_json(cal.to_json()))


def test_to_json_layout():
    rng = np.random.default_rng(0)
    cal = _random_calibration(rng, "NFOV_UNBINNED", "720P")
    cal.depth.dist = np.array([0.1, 0.2, 0.003, 0.004, 0.5, 0.6, 0.7, 0.8])
    doc = json.loads(cal.to_json())
    info = doc["CalibrationInformation"]
    d, c = info["Cameras"]
    assert d["Location"] == "CALIBRATION_CameraLocationD0"
    assert d["Purpose"] == "CALIBRATION_CameraPurposeDepth"
    assert c["Location"] == "CALIBRATION_CameraLocationPV0"
    assert c["Purpose"] == "CALIBRATION_CameraPurposePhotoVideo"
    assert (d["SensorWidth"], d["SensorHeight"]) == (1024, 1024)
    assert (c["SensorWidth"], c["SensorHeight"]) == (4096, 3072)
    assert d["Intrinsics"]["ModelType"] == "CALIBRATION_LensDistortionModelBrownConrady"
    assert d["Intrinsics"]["ModelParameterCount"] == 14
    p = d["Intrinsics"]["ModelParameters"]
    assert len(p) == 14
    # k1..k6, codx, cody, p2, p1
    assert p[4:] == [0.1, 0.2, 0.5, 0.6, 0.7, 0.8, 0.0, 0.0, 0.004, 0.003]
    assert p[0] == pytest.approx((cal.depth.cx + 0.5 + 192) / 1024)
    assert p[2] == pytest.approx(cal.depth.fx / 1024)
    assert 0.4 < p[0] < 0.6 and 0.2 < p[2] < 0.6  # normalised, as the device stores them
    assert d["Rt"] == {"Rotation": [1, 0, 0, 0, 1, 0, 0, 0, 1], "Translation": [0, 0, 0]}
    np.testing.assert_allclose(np.reshape(c["Rt"]["Rotation"], (3, 3)),
                               cal.color_from_depth[:3, :3])
    np.testing.assert_allclose(c["Rt"]["Translation"], cal.color_from_depth[:3, 3])
    assert d["MetricRadius"] == cal.depth.metric_radius
    types = {s["SensorType"] for s in info["InertialSensors"]}
    assert types == {"CALIBRATION_InertialSensorType_Gyro",
                     "CALIBRATION_InertialSensorType_Accelerometer"}
    assert info["Metadata"]["SerialId"] == "000123456789"


def test_intrinsics_helpers_and_validation():
    intr = CameraIntrinsics(640, 576, 504.6, 504.7, 332.8, 348.8)
    np.testing.assert_array_equal(intr.K(), [[504.6, 0, 332.8], [0, 504.7, 348.8], [0, 0, 1]])
    assert intr.dist.shape == (8,) and intr.dist.dtype == np.float64
    with pytest.raises(ValueError, match="8 coefficients"):
        CameraIntrinsics(640, 576, 500, 500, 320, 288, dist=np.zeros(5))
    with pytest.raises(ValueError, match="focal"):
        CameraIntrinsics(640, 576, -1, 500, 320, 288)
    cal = KinectCalibration.from_json(REAL_JSON)
    with pytest.raises(ValueError, match="depth mode NFOV_2X2BINNED is 320x288"):
        KinectCalibration(cal.depth, cal.color, depth_mode="NFOV_2X2BINNED")
    with pytest.raises(ValueError, match=r"\(4,4\)"):
        KinectCalibration(cal.depth, cal.color, color_from_depth=np.eye(3))


# ------------------------------------------------------------------ bad input
def _mutated(fn) -> str:
    doc = _doc()
    fn(doc)
    return json.dumps(doc)


@pytest.mark.parametrize(("text", "match"), [
    ("{not json", "not valid JSON"),
    ("[]", "CalibrationInformation"),
    (json.dumps({"CalibrationInformation": {}}), "Cameras"),
    (_mutated(lambda d: d["CalibrationInformation"]["Cameras"].pop(1)),
     "colour camera.*CALIBRATION_CameraLocationPV0"),
    (_mutated(lambda d: d["CalibrationInformation"]["Cameras"].pop(0)),
     "depth camera.*CALIBRATION_CameraLocationD0"),
    (_mutated(lambda d: d["CalibrationInformation"]["Cameras"][0]["Intrinsics"].update(
        ModelType="CALIBRATION_LensDistortionModelRational6KT")), "not supported"),
    (_mutated(lambda d: d["CalibrationInformation"]["Cameras"][0]["Intrinsics"].update(
        ModelParameters=[0.5] * 10)), "ModelParameters must be at least 14"),
    (_mutated(lambda d: d["CalibrationInformation"]["Cameras"][1]["Rt"].update(
        Translation=[0, 0])), "colour Rt.Translation"),
    (_mutated(lambda d: d["CalibrationInformation"]["Cameras"][0].update(SensorWidth=512)),
     "1024x1024"),
    (_mutated(lambda d: d["CalibrationInformation"]["Cameras"][1].pop("MetricRadius")),
     "MetricRadius"),
])
def test_malformed_json_raises_clear_error(text, match):
    with pytest.raises(ValueError, match=match) as err:
        KinectCalibration.from_json(text, source="cam0.mkv")
    assert "cam0.mkv" in str(err.value)


def test_unknown_modes():
    with pytest.raises(ValueError, match="unknown depth mode 'NFOV'"):
        KinectCalibration.from_json(REAL_JSON, "NFOV", "720P")
    with pytest.raises(ValueError, match="unknown colour resolution '720p'"):
        KinectCalibration.from_json(REAL_JSON, "NFOV_UNBINNED", "720p")


def test_bytes_with_trailing_nul_accepted():
    cal = KinectCalibration.from_json(REAL_JSON.encode() + b"\x00")
    assert math.isclose(cal.depth.fx, 0.4927808940410614 * 1024)
