"""A depth camera's systematic depth error, measured on the floor and taken out of its depth.

A time-of-flight camera's depth carries a per-device systematic error of a few millimetres (the
Azure Kinect's spec: < 11 mm + 0.1 % of distance): an offset, a scale and a term growing
towards the image corners. Cameras disagreeing by that much on a surface pull whatever is
fitted to their fused points towards the camera that measures it nearer: on a simulated
armchair every frame's registered pose was 5 mm off (worst vertex 6.6 mm, 1.0 mm corrected).

The floor is the one surface every camera sees and whose position the calibration fixes (world
y = 0, +Y up; :func:`couch.capture.calibration.level_with_floor`), so each camera's error is
fitted to the floor pixels of a few of its frames (:func:`floor_depth_bias`) and taken out of
its depth images before they become points (:meth:`DepthBias.correct`). The floor plane itself
is fitted to all cameras' points, so what is measured is each camera's error relative to their
common floor: what makes them disagree.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import cv2
import numpy as np

from .azure_calibration import KinectCalibration
from .registration import pixel_rays
from .segmentation import CameraSegmentation

__all__ = ["DepthBias", "floor_depth_bias", "recording_depth_bias", "unmeasured_warnings"]


@dataclasses.dataclass(frozen=True)
class DepthBias:
    """A camera's systematic depth error: it measures ``z·(1 + scale) + offset + radial·r²``
    for a surface at Z-depth ``z`` (metres; r² = x² + y² of the pixel's normalised ray).

    Attributes:
        offset: metres. scale: unitless. radial: metres per unit r².
        pixels: floor pixels it was measured on; rms: their residual after it (m).
    """

    offset: float
    scale: float
    radial: float
    pixels: int
    rms: float

    def report(self) -> dict[str, float]:
        """The error as a QA record: offset and radial term in mm, scale in parts per
        thousand, the floor pixels and their residual (mm)."""
        return {"offset_mm": 1e3 * self.offset, "scale_ppt": 1e3 * self.scale,
                "radial_mm": 1e3 * self.radial, "pixels": float(self.pixels),
                "rms_mm": 1e3 * self.rms}

    def corrector(self, calib: KinectCalibration) -> Callable[[np.ndarray], np.ndarray]:
        """A function taking (H,W) uint16 mm depth of this camera to the depth with the error
        taken out (0 stays 0); the per-pixel terms are computed once, here."""
        r2 = np.nan_to_num(np.square(pixel_rays(calib.depth)).sum(-1))
        gain = np.float32(1.0 / (1.0 + self.scale))
        shift = (-(self.offset + self.radial * r2) * 1000.0 / (1.0 + self.scale)).astype(
            np.float32)

        def correct(depth_mm: np.ndarray) -> np.ndarray:
            true = depth_mm.astype(np.float32) * gain + shift
            out = np.rint(np.clip(true, 0, 65535)).astype(np.uint16)
            out[depth_mm == 0] = 0
            return out

        return correct

    def correct(self, depth_mm: np.ndarray, calib: KinectCalibration) -> np.ndarray:
        """(H,W) uint16 mm depth of this camera with the error taken out (0 stays 0); for
        many frames of one camera, :meth:`corrector` once."""
        return self.corrector(calib)(depth_mm)


def floor_depth_bias(depths: Sequence[np.ndarray], calib: KinectCalibration,
                     world_from_depth: np.ndarray, band: float = 0.03,
                     min_pixels: int = 2000) -> DepthBias | None:
    """One camera's systematic depth error, measured on the floor (world y = 0, +Y up).

    Every valid pixel of ``depths`` ((H,W) uint16 mm; pixels of anything else zeroed by the
    caller, e.g. the person) whose point lies within ``band`` of the floor is compared with
    the Z-depth at which its ray meets the floor; offset, scale and radial terms are fitted
    to the differences by least squares, dropping 3-sigma outliers twice.

    Returns:
        :class:`DepthBias`, or None with fewer than ``min_pixels`` floor pixels, a floor seen
        over less than 0.5 m of depth (scale and offset are then one), or an offset over 3 cm
        (the world is not levelled on the floor).
    """
    rays = pixel_rays(calib.depth)
    pose = np.asarray(world_from_depth, np.float64)
    down = rays @ pose[1, :2] + pose[1, 2]  # world dy per metre of Z along each ray
    z_floor = -pose[1, 3] / np.where(down < -0.05, down, np.nan)  # Z where the ray meets y=0
    r2 = np.square(rays).sum(-1)
    res, zt, rr = [], [], []
    for d in depths:
        z = d.astype(np.float64) * 1e-3
        ok = (d > 0) & np.isfinite(z_floor)
        height = (z - z_floor) * down  # the point's world height
        ok &= np.abs(height) < band
        res.append((z - z_floor)[ok])
        zt.append(z_floor[ok])
        rr.append(r2[ok])
    res, zt, rr = np.concatenate(res), np.concatenate(zt), np.concatenate(rr)
    if len(res) < min_pixels or np.ptp(zt) < 0.5:
        return None
    a = np.stack([np.ones_like(zt), zt, rr], axis=1)
    keep = np.ones(len(res), bool)
    for _ in range(3):
        x, *_ = np.linalg.lstsq(a[keep], res[keep], rcond=None)
        err = res - a @ x
        keep = np.abs(err) < 3 * 1.4826 * np.median(np.abs(err[keep])) + 1e-4
    if abs(x[0]) > 0.03:
        return None
    return DepthBias(float(x[0]), float(x[1]), float(x[2]), int(keep.sum()),
                     float(np.sqrt(np.mean(err[keep] ** 2))))


def recording_depth_bias(segmentation: CameraSegmentation, frames: int = 5,
                         person_dilate_px: int = 3) -> DepthBias | None:
    """:func:`floor_depth_bias` of one camera's segmented recording: ``frames`` of its frames
    spread over the recording, the person (mask grown by ``person_dilate_px``) left out."""
    seg = segmentation
    if not seg.frames or frames < 1:
        return None
    picks = np.unique(np.linspace(0, len(seg.frames) - 1, frames).round().astype(int))
    k = 2 * person_dilate_px + 1
    depths = []
    for i in picks:
        f = seg.frames[int(i)]
        person = cv2.dilate(f.person.view(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        depths.append(np.where(person, 0, f.depth_mm).astype(np.uint16))
    return floor_depth_bias(depths, seg.calibration, seg.world_from_depth)


def unmeasured_warnings(serials: Sequence[str], biases: Sequence[DepthBias | None]) -> list[str]:
    """A warning for each camera whose depth error could not be measured (``None``)."""
    return [f"camera {serial}: too little floor in view to measure its depth error; its "
            f"depth is used as recorded"
            for serial, b in zip(serials, biases, strict=True) if b is None]
