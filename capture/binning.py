"""Software 2x2 binning of full-resolution Azure Kinect depth, as the binned depth modes do.

The camera's ``NFOV_2X2BINNED`` / ``WFOV_2X2BINNED`` modes read the sensor in 2x2 blocks:
half the resolution, a quarter of the pixels, a longer range. A recording made at full
resolution (``NFOV_UNBINNED`` / ``WFOV_UNBINNED``) can be read the same way: binned pixel
``(u, v)`` is the block of full-resolution pixels ``(2u, 2v)`` to ``(2u+1, 2v+1)`` (the
modes' crops and calibration sizes are exactly 2x apart, so the binned mode's intrinsics from
the same ``calibration.json`` describe the block's centre), and most of processing a session
costs per pixel or per point.

A block's depth is the mean of its valid pixels when at least ``min_valid`` are valid and
they agree (the nearest and farthest within ``tolerance`` times the nearest, plus a noise
floor); a block across a depth edge (a hand before the armrest, the body before the room) is
invalid rather than a depth between the two surfaces, which no surface has (the segmentation
treats invalid pixels at the person's rim as its own). The IR image is the mean of the block.
The sensor's own range stays the full-resolution mode's: binning in software averages what was
measured, it does not reach farther.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BINNED_MODES", "bin_depth", "bin_ir"]

#: Full-resolution depth modes -> the binned mode whose pixel grid and intrinsics their 2x2
#: blocks have.
BINNED_MODES: dict[str, str] = {"NFOV_UNBINNED": "NFOV_2X2BINNED",
                                "WFOV_UNBINNED": "WFOV_2X2BINNED"}


def _quarters(image: np.ndarray) -> tuple[np.ndarray, ...]:
    """The four (H/2, W/2) pixels of every 2x2 block of an (H, W) image, as strided views."""
    h, w = image.shape
    if h % 2 or w % 2:
        raise ValueError(f"2x2 binning needs an even image size, got {w}x{h}")
    return image[0::2, 0::2], image[0::2, 1::2], image[1::2, 0::2], image[1::2, 1::2]


def bin_depth(depth_mm: np.ndarray, *, min_valid: int = 2, tolerance: float = 0.02,
              floor_mm: float = 5.0) -> np.ndarray:
    """(H/2, W/2) uint16 depth (mm, 0 = invalid) of an (H, W) uint16 full-resolution image.

    A block is the mean of its valid (non-zero) pixels, rounded to the millimetre, where at
    least ``min_valid`` of its four are valid and their spread (farthest minus nearest) is at
    most ``tolerance`` times the nearest plus ``floor_mm``; else 0."""
    q = _quarters(np.asarray(depth_mm, dtype=np.uint16))
    n = sum((x > 0).astype(np.uint8) for x in q)
    total = sum(x.astype(np.int32) for x in q)
    far = np.maximum(np.maximum(q[0], q[1]), np.maximum(q[2], q[3]))
    # an invalid 0 minus 1 wraps to 65535 (uint16), above every valid depth minus 1: it is no
    # block's nearest, and a block with none valid comes back to 0
    near = np.minimum(np.minimum(q[0] - 1, q[1] - 1), np.minimum(q[2] - 1, q[3] - 1)) + 1
    near = near.astype(np.float32)
    ok = (n >= min_valid) & (far - near <= tolerance * near + floor_mm)
    mean = (2 * total + n) // np.maximum(2 * n, 1)  # rounded half up, in integers
    return np.where(ok, mean, 0).astype(np.uint16)


def bin_ir(ir: np.ndarray) -> np.ndarray:
    """(H/2, W/2) uint16: the mean of each 2x2 block of an (H, W) uint16 IR image."""
    q = _quarters(np.asarray(ir, dtype=np.uint16))
    return ((sum(x.astype(np.int32) for x in q) + 2) // 4).astype(np.uint16)
