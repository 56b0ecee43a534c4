"""Azure Kinect factory calibration: the ``calibration.json`` a device stores, and the mode-specific
pixel intrinsics the Sensor SDK derives from it.

Conventions of the objects here
-------------------------------
* :class:`CameraIntrinsics` is OpenCV's pinhole + rational distortion model in **pixels** of one
  camera *mode* (e.g. depth NFOV_UNBINNED 640x576, colour 720P 1280x720). Pixel centres sit at
  integer coordinates (OpenCV), ``dist`` is OpenCV's order ``[k1, k2, p1, p2, k3, k4, k5, k6]``.
* :attr:`KinectCalibration.color_from_depth` is a (4,4) rigid transform in **metres** that maps a
  point in depth-camera coordinates into colour-camera coordinates (both cameras +Z forward,
  +X right, +Y down, as the SDK). The SDK itself works in millimetres; the JSON stores metres.

What the primary sources say (Azure-Kinect-Sensor-SDK, checked at commit 8bb59ca, 2022-09-01)
-----------------------------------------------------------------------------------------
``src/calibration/calibration.c`` (parser of the device JSON):
  * ``CalibrationInformation.Cameras[]`` is searched by ``Location``:
    ``CALIBRATION_CameraLocationD0`` (depth) and ``CALIBRATION_CameraLocationPV0`` (colour).
    Each camera needs ``Intrinsics`` {``ModelParameterCount``, ``ModelType``,
    ``ModelParameters``}, ``Rt`` {``Rotation`` (9), ``Translation`` (3)}, ``SensorWidth``,
    ``SensorHeight`` and ``MetricRadius``. ModelType strings include
    ``CALIBRATION_LensDistortionModelBrownConrady`` (retail devices) and
    ``CALIBRATION_LensDistortionModelRational6KT`` (early internal devices only).
  * ``Translation`` is metres (the SDK multiplies by 1000 into mm).
  * ``MetricRadius <= 0.0001`` means "not estimated" and is replaced by 1.7 (~120° FoV).
  * ``InertialSensors[]`` entries are found by ``SensorType``
    (``CALIBRATION_InertialSensorType_Gyro`` / ``_Accelerometer``) with ``BiasTemperatureModel``,
    ``BiasUncertainty``, ``MixingMatrixTemperatureModel``, ``ModelTypeMask``, ``Noise``, ``Rt``,
    ``SecondOrderScaling``, ``TemperatureBounds``, ``TemperatureC``.
``include/k4a/k4atypes.h`` (``k4a_calibration_intrinsic_parameters_t``): the 14 model parameters
  are ``cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, codx, cody, p2, p1`` (p2 before p1).
``src/transformation/mode_specific_calibration.c``: the JSON's cx, cy, fx, fy are "unitized and
  0-cornered" (divided by the calibration image size; (0,0) is the top-left *corner*). For a mode
  with {binned calibration resolution (Wb, Hb), crop offset (ox, oy), output (W, H)}::

      fx_px = fx * Wb            fy_px = fy * Hb
      cx_px = cx * Wb - ox - 0.5 cy_px = cy * Hb - oy - 0.5

  Depth (raw calibration must be 1024x1024): NFOV_2X2BINNED {512x512, (96,90), 320x288},
  NFOV_UNBINNED {1024x1024, (192,180), 640x576}, WFOV_2X2BINNED {512x512, (0,0), 512x512},
  WFOV_UNBINNED and PASSIVE_IR {1024x1024, (0,0), 1024x1024}.
  Colour: the raw calibration is for the 4:3 4096x3072 sensor; a *legacy* 16:9 (4096x2304)
  calibration is first converted to 4:3 with {4096x2304, (0,-384), 4096x3072} without the 0.5
  shift. The 16:9 modes are centre crops of a 4:3 binned image: 720P {1280x960, (0,120),
  1280x720}, 1080P {1920x1440, (0,180), 1920x1080}, 1440P {2560x1920, (0,240), 2560x1440},
  2160P {3840x2880, (0,360), 3840x2160}; the 4:3 modes are not cropped: 1536P {2048x1536, (0,0),
  2048x1536}, 3072P {4096x3072, (0,0), 4096x3072}.
  (LukeSchoen/OpenK4A was not available here; cansik/open-azure-kinect's
  ``openk4a/utils/_calibration_utils.py`` ports the same tables to Python, identically.)
``src/transformation/extrinsic_transformation.c`` + ``transformation.c``: each camera's ``Rt`` is
  "world_to_camera" with the depth camera as world (its Rt is the identity in real files), and
  ``source_to_target = world_to_target * inverse(world_to_source)``; so
  ``color_from_depth = Rt(PV0) @ inv(Rt(D0))``.
``src/transformation/intrinsic_transformation.c``: for Brown-Conrady the projection is
  ``x_d = x*(1+k1 r²+k2 r⁴+k3 r⁶)/(1+k4 r²+k5 r⁴+k6 r⁶) + 2 p1 x y + p2 (r² + 2x²)`` and
  ``y_d = ... + p1 (r² + 2y²) + 2 p2 x y``, ``u = fx x_d + cx`` — exactly OpenCV's rational model
  with ``dist = [k1, k2, p1, p2, k3, k4, k5, k6]`` (codx = cody = 0 for Brown-Conrady). Points with
  ``r² > metric_radius²`` are invalid. Rational6KT differs (no factor 2 on the tangential xy
  terms, a centre of distortion), so it cannot be expressed with OpenCV's model and is rejected.
A real device file (pyk4a ``tests/assets/recording.mkv`` attachment, serial 001514394512) has the
layout written by :meth:`KinectCalibration.to_json`: compact JSON, cameras D0 then PV0 with
``Purpose`` ``CALIBRATION_CameraPurposeDepth`` / ``CALIBRATION_CameraPurposePhotoVideo``,
``Shutter`` ``CALIBRATION_ShutterTypeUndefined``, ``ThermalAdjustmentParams.Params`` (12 zeros),
then ``InertialSensors`` (gyro, accelerometer) and ``Metadata`` (``SerialId``, ``FactoryCalDate``,
``Version``, ``DeviceName`` ``AzureKinect-PV``, ``Notes``).

Differences from the device: the SDK stores and computes in float32; this module computes in
float64 and writes float64 values, so ``from_json(to_json(c))`` reproduces ``c`` to ~1e-12.
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

__all__ = [
    "COLOR_RESOLUTIONS",
    "COLOR_SENSOR_SIZE",
    "DEPTH_MODES",
    "DEPTH_RANGE_M",
    "DEPTH_SENSOR_SIZE",
    "CameraIntrinsics",
    "KinectCalibration",
]

DEPTH_LOCATION = "CALIBRATION_CameraLocationD0"
COLOR_LOCATION = "CALIBRATION_CameraLocationPV0"
BROWN_CONRADY = "CALIBRATION_LensDistortionModelBrownConrady"
RATIONAL_6KT = "CALIBRATION_LensDistortionModelRational6KT"

#: Size (width, height) of the raw depth calibration image (the SDK rejects anything else).
DEPTH_SENSOR_SIZE = (1024, 1024)
#: Size (width, height) of the raw 4:3 colour calibration image.
COLOR_SENSOR_SIZE = (4096, 3072)
#: SDK's fallback when MetricRadius was not estimated (calibration.c).
DEFAULT_METRIC_RADIUS = 1.7


class ModeInfo(NamedTuple):
    """One row of ``mode_specific_calibration.c``: binned calibration size, crop, output size."""

    binned_width: int
    binned_height: int
    crop_x: int
    crop_y: int
    width: int
    height: int


#: Depth modes (``K4A_DEPTH_MODE`` tag strings) -> mode info.
DEPTH_MODES: dict[str, ModeInfo] = {
    "NFOV_2X2BINNED": ModeInfo(512, 512, 96, 90, 320, 288),
    "NFOV_UNBINNED": ModeInfo(1024, 1024, 192, 180, 640, 576),
    "WFOV_2X2BINNED": ModeInfo(512, 512, 0, 0, 512, 512),
    "WFOV_UNBINNED": ModeInfo(1024, 1024, 0, 0, 1024, 1024),
    "PASSIVE_IR": ModeInfo(1024, 1024, 0, 0, 1024, 1024),
}

#: Depth modes -> operating range (min, max) in metres of Z, from the Azure Kinect DK hardware
#: specification (15-95 % reflectivity); depth outside it comes back invalid (0).
DEPTH_RANGE_M: dict[str, tuple[float, float]] = {
    "NFOV_2X2BINNED": (0.5, 5.46),
    "NFOV_UNBINNED": (0.5, 3.86),
    "WFOV_2X2BINNED": (0.25, 2.88),
    "WFOV_UNBINNED": (0.25, 2.21),
}

#: Colour resolutions (the part after ``MJPG_`` in ``K4A_COLOR_MODE``) -> mode info.
COLOR_RESOLUTIONS: dict[str, ModeInfo] = {
    "720P": ModeInfo(1280, 960, 0, 120, 1280, 720),
    "1080P": ModeInfo(1920, 1440, 0, 180, 1920, 1080),
    "1440P": ModeInfo(2560, 1920, 0, 240, 2560, 1440),
    "1536P": ModeInfo(2048, 1536, 0, 0, 2048, 1536),
    "2160P": ModeInfo(3840, 2880, 0, 360, 3840, 2160),
    "3072P": ModeInfo(4096, 3072, 0, 0, 4096, 3072),
}

# Nominal IMU section in the layout of a retail device's factory file (values of the kind a real
# file holds: the IMU is mounted rotated ~90° against the depth camera). Written only when the
# calibration did not come from a real file, whose own sections are then kept.
_NOMINAL_INERTIAL_SENSORS: list[dict[str, Any]] = [
    {
        "BiasTemperatureModel": [0.0] * 12,
        "BiasUncertainty": [1e-4, 1e-4, 1e-4],
        "Id": "CALIBRATION_InertialSensorId_LSM6DSM",
        "MixingMatrixTemperatureModel": [1.0 if i in (0, 16, 32) else 0.0 for i in range(36)],
        "ModelTypeMask": 16,
        "Noise": [0.00095, 0.00095, 0.00095, 0.0, 0.0, 0.0],
        "Rt": {"Rotation": [0.0, 0.1084, -0.9941, -1.0, 0.0, 0.0, 0.0, 0.9941, 0.1084],
               "Translation": [0.0, 0.0, 0.0]},
        "SecondOrderScaling": [0.0] * 9,
        "SensorType": "CALIBRATION_InertialSensorType_Gyro",
        "TemperatureBounds": [5.0, 60.0],
        "TemperatureC": 0.0,
    },
    {
        "BiasTemperatureModel": [0.0] * 12,
        "BiasUncertainty": [0.01, 0.01, 0.01],
        "Id": "CALIBRATION_InertialSensorId_LSM6DSM",
        "MixingMatrixTemperatureModel": [1.0 if i in (0, 16, 32) else 0.0 for i in range(36)],
        "ModelTypeMask": 56,
        "Noise": [0.0107, 0.0107, 0.0107, 0.0, 0.0, 0.0],
        "Rt": {"Rotation": [0.0, 0.1084, -0.9941, -1.0, 0.0, 0.0, 0.0, 0.9941, 0.1084],
               "Translation": [-0.051, 0.0035, 0.0013]},
        "SecondOrderScaling": [0.0] * 9,
        "SensorType": "CALIBRATION_InertialSensorType_Accelerometer",
        "TemperatureBounds": [5.0, 60.0],
        "TemperatureC": 0.0,
    },
]


@dataclass
class CameraIntrinsics:
    """Pinhole + OpenCV rational distortion of one camera in one mode, in pixels.

    Attributes:
        width, height: image size of the mode in pixels (e.g. 640x576 for NFOV_UNBINNED depth).
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels, OpenCV convention (centre of the top-left pixel is
            (0, 0)).
        dist: (8,) float64, OpenCV rational model ``[k1, k2, p1, p2, k3, k4, k5, k6]``.
        metric_radius: largest valid radius on the z=1 plane (normalised, unitless); projections
            beyond it are invalid in the SDK.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: np.ndarray = field(default_factory=lambda: np.zeros(8))
    metric_radius: float = DEFAULT_METRIC_RADIUS

    def __post_init__(self) -> None:
        self.width = int(self.width)
        self.height = int(self.height)
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in (self.fx, self.fy, self.cx,
                                                                  self.cy))
        self.metric_radius = float(self.metric_radius)
        dist = np.array(self.dist, dtype=np.float64).reshape(-1)
        if dist.shape != (8,):
            raise ValueError(f"dist must have 8 coefficients [k1,k2,p1,p2,k3,k4,k5,k6], "
                             f"got shape {np.shape(self.dist)}")
        self.dist = dist
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        values = [self.fx, self.fy, self.cx, self.cy, self.metric_radius, *dist]
        if not all(math.isfinite(v) for v in values):
            raise ValueError("intrinsics contain a non-finite value")

    def K(self) -> np.ndarray:
        """(3,3) float64 camera matrix ``[[fx,0,cx],[0,fy,cy],[0,0,1]]`` in pixels."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraIntrinsics):
            return NotImplemented
        return (self.width, self.height, self.fx, self.fy, self.cx, self.cy,
                self.metric_radius) == (other.width, other.height, other.fx, other.fy, other.cx,
                                        other.cy, other.metric_radius) and bool(
            np.array_equal(self.dist, other.dist))


def _depth_mode_info(depth_mode: str) -> ModeInfo:
    try:
        return DEPTH_MODES[depth_mode]
    except (KeyError, TypeError):
        raise ValueError(f"unknown depth mode {depth_mode!r}; expected one of "
                         f"{sorted(DEPTH_MODES)}") from None


def _color_mode_info(color_resolution: str) -> ModeInfo:
    try:
        return COLOR_RESOLUTIONS[color_resolution]
    except (KeyError, TypeError):
        raise ValueError(f"unknown colour resolution {color_resolution!r}; expected one of "
                         f"{sorted(COLOR_RESOLUTIONS)}") from None


def _normalised_params(intr: CameraIntrinsics, mode: ModeInfo) -> list[float]:
    """Inverse of the SDK's mode-specific step: pixels of ``mode`` -> the JSON's 14 parameters."""
    k1, k2, p1, p2, k3, k4, k5, k6 = (float(v) for v in intr.dist)
    cx = (intr.cx + 0.5 + mode.crop_x) / mode.binned_width
    cy = (intr.cy + 0.5 + mode.crop_y) / mode.binned_height
    fx = intr.fx / mode.binned_width
    fy = intr.fy / mode.binned_height
    # codx, cody are 0 for Brown-Conrady; p2 precedes p1 in the device's order.
    return [cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, 0.0, 0.0, p2, p1]


def _pixel_intrinsics(params: list[float], mode: ModeInfo,
                      metric_radius: float) -> CameraIntrinsics:
    """The SDK's ``transformation_get_mode_specific_camera_calibration`` (pixelised output)."""
    cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, _codx, _cody, p2, p1 = params[:14]
    return CameraIntrinsics(
        width=mode.width, height=mode.height,
        fx=fx * mode.binned_width, fy=fy * mode.binned_height,
        cx=cx * mode.binned_width - mode.crop_x - 0.5,
        cy=cy * mode.binned_height - mode.crop_y - 0.5,
        dist=np.array([k1, k2, p1, p2, k3, k4, k5, k6]),
        metric_radius=metric_radius,
    )


def _rt_matrix(rotation: list[float], translation: list[float]) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    t[:3, 3] = np.asarray(translation, dtype=np.float64)
    return t


def _invert_rigid(t: np.ndarray) -> np.ndarray:
    inv = np.eye(4)
    inv[:3, :3] = t[:3, :3].T
    inv[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return inv


@dataclass
class KinectCalibration:
    """Factory calibration of one Azure Kinect, made specific to the recording's modes.

    Attributes:
        depth: depth/IR camera intrinsics for ``depth_mode`` (e.g. 640x576 for NFOV_UNBINNED).
        color: colour camera intrinsics for ``color_resolution`` (e.g. 1280x720 for 720P).
        color_from_depth: (4,4) float64, metres; ``p_color = color_from_depth @ p_depth``.
        depth_mode: ``K4A_DEPTH_MODE`` string the depth intrinsics are for.
        color_resolution: colour resolution string (``720P``, ``1080P``, ...) of ``color``.
        serial: device serial number (``Metadata.SerialId`` in the JSON).
        extra: the JSON's ``InertialSensors`` and ``Metadata`` sections when parsed from a real
            file, so that :meth:`to_json` writes them back unchanged; ``None`` writes nominal ones.
    """

    depth: CameraIntrinsics
    color: CameraIntrinsics
    color_from_depth: np.ndarray = field(default_factory=lambda: np.eye(4))
    depth_mode: str = "NFOV_UNBINNED"
    color_resolution: str = "720P"
    serial: str = "000000000000"
    extra: dict[str, Any] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        t = np.array(self.color_from_depth, dtype=np.float64)
        if t.shape != (4, 4) or not np.all(np.isfinite(t)):
            raise ValueError(f"color_from_depth must be a finite (4,4) matrix, got shape "
                             f"{t.shape}")
        if not np.allclose(t[3], [0.0, 0.0, 0.0, 1.0]):
            raise ValueError(f"color_from_depth bottom row must be [0,0,0,1], got {t[3]}")
        self.color_from_depth = t
        dmode = _depth_mode_info(self.depth_mode)
        cmode = _color_mode_info(self.color_resolution)
        if (self.depth.width, self.depth.height) != (dmode.width, dmode.height):
            raise ValueError(f"depth intrinsics are {self.depth.width}x{self.depth.height} but "
                             f"depth mode {self.depth_mode} is {dmode.width}x{dmode.height}")
        if (self.color.width, self.color.height) != (cmode.width, cmode.height):
            raise ValueError(f"colour intrinsics are {self.color.width}x{self.color.height} but "
                             f"colour resolution {self.color_resolution} is "
                             f"{cmode.width}x{cmode.height}")
        self.serial = str(self.serial)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, KinectCalibration):
            return NotImplemented
        return (self.depth == other.depth and self.color == other.color
                and bool(np.array_equal(self.color_from_depth, other.color_from_depth))
                and (self.depth_mode, self.color_resolution, self.serial)
                == (other.depth_mode, other.color_resolution, other.serial))

    # ------------------------------------------------------------------ JSON writer
    def to_json(self) -> str:
        """The device's ``calibration.json`` text (compact, as stored in k4arecorder files).

        Intrinsics are normalised back to the raw sensor calibration (depth 1024x1024, colour
        4096x3072) as the device stores them; the depth camera's Rt is the identity and the
        colour camera's Rt is ``color_from_depth`` (rotation row-major, translation metres).
        """
        dmode = _depth_mode_info(self.depth_mode)
        cmode = _color_mode_info(self.color_resolution)
        r = self.color_from_depth[:3, :3]
        t = self.color_from_depth[:3, 3]

        def camera(location: str, purpose: str, intr: CameraIntrinsics, mode: ModeInfo,
                   rotation: list[float], translation: list[float],
                   sensor: tuple[int, int]) -> dict[str, Any]:
            return {
                "Intrinsics": {"ModelParameterCount": 14,
                               "ModelParameters": _normalised_params(intr, mode),
                               "ModelType": BROWN_CONRADY},
                "Location": location,
                "Purpose": purpose,
                "MetricRadius": intr.metric_radius,
                "Rt": {"Rotation": rotation, "Translation": translation},
                "SensorHeight": sensor[1],
                "SensorWidth": sensor[0],
                "Shutter": "CALIBRATION_ShutterTypeUndefined",
                "ThermalAdjustmentParams": {"Params": [0] * 12},
            }

        extra = self.extra or {}
        metadata = copy.deepcopy(extra.get("Metadata")) or {
            "SerialId": self.serial,
            "FactoryCalDate": "1/1/2020 12:00:00 AM GMT",
            "Version": {"Major": 1, "Minor": 2},
            "DeviceName": "AzureKinect-PV",
            "Notes": "",
        }
        metadata["SerialId"] = self.serial
        doc = {"CalibrationInformation": {
            "Cameras": [
                camera(DEPTH_LOCATION, "CALIBRATION_CameraPurposeDepth", self.depth, dmode,
                       [1, 0, 0, 0, 1, 0, 0, 0, 1], [0, 0, 0], DEPTH_SENSOR_SIZE),
                camera(COLOR_LOCATION, "CALIBRATION_CameraPurposePhotoVideo", self.color, cmode,
                       [float(v) for v in r.reshape(-1)], [float(v) for v in t],
                       COLOR_SENSOR_SIZE),
            ],
            "InertialSensors": copy.deepcopy(extra.get("InertialSensors",
                                                       _NOMINAL_INERTIAL_SENSORS)),
            "Metadata": metadata,
        }}
        return json.dumps(doc, separators=(",", ":"), allow_nan=False)

    # ------------------------------------------------------------------ JSON reader
    @classmethod
    def from_json(cls, text: str | bytes, depth_mode: str = "NFOV_UNBINNED",
                  color_resolution: str = "720P", *, source: str | None = None,
                  ) -> KinectCalibration:
        """Parse a device ``calibration.json`` and make it specific to the given modes.

        Args:
            text: the JSON text (str or UTF-8 bytes; a trailing NUL, as the device sends, is
                ignored).
            depth_mode: one of :data:`DEPTH_MODES` (``K4A_DEPTH_MODE`` tag strings).
            color_resolution: one of :data:`COLOR_RESOLUTIONS` (``720P``, ``1080P``, ...).
            source: where the text came from, used in error messages (e.g. the .mkv path).

        Raises:
            ValueError: naming ``source`` and what is wrong (invalid JSON, missing camera or
                key, unsupported lens model, unexpected sensor size, unknown mode).
        """
        where = f" in {source}" if source else ""
        dmode = _depth_mode_info(depth_mode)
        cmode = _color_mode_info(color_resolution)
        if isinstance(text, bytes | bytearray | memoryview):
            try:
                text = bytes(text).decode("utf-8")
            except UnicodeDecodeError as exc:
                raise ValueError(f"calibration JSON{where} is not UTF-8 text: {exc}") from None
        text = text.rstrip("\x00")
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"calibration JSON{where} is not valid JSON: {exc}") from None
        info = doc.get("CalibrationInformation") if isinstance(doc, dict) else None
        if not isinstance(info, dict):
            raise ValueError(f"calibration JSON{where} has no 'CalibrationInformation' object")
        cameras = info.get("Cameras")
        if not isinstance(cameras, list):
            raise ValueError(f"calibration JSON{where} has no 'CalibrationInformation.Cameras' "
                             f"list")

        def find(location: str, what: str) -> dict[str, Any]:
            for cam in cameras:
                if isinstance(cam, dict) and cam.get("Location") == location:
                    return cam
            found = [c.get("Location") for c in cameras if isinstance(c, dict)]
            raise ValueError(f"calibration JSON{where} has no {what} camera (Location "
                             f"{location!r}); cameras found: {found}")

        def numbers(obj: Any, n: int, what: str, at_least: bool = False) -> list[float]:
            ok = isinstance(obj, list) and (len(obj) >= n if at_least else len(obj) == n)
            if ok:
                ok = all(isinstance(v, int | float) and not isinstance(v, bool)
                         and math.isfinite(v) for v in obj[:n])
            if not ok:
                raise ValueError(f"calibration JSON{where}: {what} must be "
                                 f"{'at least ' if at_least else ''}{n} finite numbers, got "
                                 f"{obj!r:.200}")
            return [float(v) for v in obj[:n]]

        def camera(location: str, what: str) -> tuple[list[float], float, np.ndarray,
                                                      tuple[int, int]]:
            cam = find(location, what)
            intr = cam.get("Intrinsics")
            if not isinstance(intr, dict):
                raise ValueError(f"calibration JSON{where}: {what} camera has no 'Intrinsics'")
            model = intr.get("ModelType")
            if model != BROWN_CONRADY:
                hint = (" (early internal devices only; OpenCV's model cannot express it)"
                        if model == RATIONAL_6KT else "")
                raise ValueError(f"calibration JSON{where}: {what} camera lens model {model!r} "
                                 f"is not supported, expected {BROWN_CONRADY!r}{hint}")
            count = intr.get("ModelParameterCount")
            if not isinstance(count, int) or count < 14:
                raise ValueError(f"calibration JSON{where}: {what} camera ModelParameterCount "
                                 f"must be >= 14, got {count!r}")
            params = numbers(intr.get("ModelParameters"), 14,
                             f"{what} Intrinsics.ModelParameters", at_least=True)
            rt = cam.get("Rt")
            if not isinstance(rt, dict):
                raise ValueError(f"calibration JSON{where}: {what} camera has no 'Rt'")
            pose = _rt_matrix(numbers(rt.get("Rotation"), 9, f"{what} Rt.Rotation"),
                              numbers(rt.get("Translation"), 3, f"{what} Rt.Translation"))
            size = []
            for key in ("SensorWidth", "SensorHeight"):
                v = cam.get(key)
                if not isinstance(v, int | float) or isinstance(v, bool) or v <= 0:
                    raise ValueError(f"calibration JSON{where}: {what} camera {key} must be a "
                                     f"positive number, got {v!r}")
                size.append(int(v))
            radius = cam.get("MetricRadius")
            if not isinstance(radius, int | float) or isinstance(radius, bool):
                raise ValueError(f"calibration JSON{where}: {what} camera MetricRadius must be "
                                 f"a number, got {radius!r}")
            radius = float(radius)
            if radius <= 0.0001:
                radius = DEFAULT_METRIC_RADIUS  # calibration.c: "not estimated"
            return params, radius, pose, (size[0], size[1])

        d_params, d_radius, d_pose, d_size = camera(DEPTH_LOCATION, "depth")
        c_params, c_radius, c_pose, c_size = camera(COLOR_LOCATION, "colour")
        if d_size != DEPTH_SENSOR_SIZE:
            raise ValueError(f"calibration JSON{where}: depth SensorWidth x SensorHeight is "
                             f"{d_size[0]}x{d_size[1]}, the SDK requires 1024x1024")
        cw, ch = c_size
        if cw * 9 // 16 == ch:
            # Legacy 16:9 calibration: convert to 4:3 as the SDK does (no 0.5 shift here).
            legacy = ModeInfo(cw, ch, 0, -(cw * 3 // 4 - ch) // 2, cw, cw * 3 // 4)
            cx, cy, fx, fy = c_params[:4]
            c_params = [
                (cx * legacy.binned_width - legacy.crop_x) / legacy.width,
                (cy * legacy.binned_height - legacy.crop_y) / legacy.height,
                fx * legacy.binned_width / legacy.width,
                fy * legacy.binned_height / legacy.height,
                *c_params[4:],
            ]
        elif cw * 3 // 4 != ch:
            raise ValueError(f"calibration JSON{where}: colour sensor size {cw}x{ch} is neither "
                             f"4:3 nor 16:9")

        metadata = info.get("Metadata")
        serial = ""
        if isinstance(metadata, dict) and metadata.get("SerialId") is not None:
            serial = str(metadata["SerialId"])
        extra = {k: copy.deepcopy(info[k]) for k in ("InertialSensors", "Metadata") if k in info}
        return cls(
            depth=_pixel_intrinsics(d_params, dmode, d_radius),
            color=_pixel_intrinsics(c_params, cmode, c_radius),
            color_from_depth=c_pose @ _invert_rigid(d_pose),
            depth_mode=depth_mode,
            color_resolution=color_resolution,
            serial=serial,
            extra=extra or None,
        )
