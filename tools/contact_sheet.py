"""``couch-contact-sheet SESSION_DIR``: one frame of every camera, colour beside depth (and IR
where the recording has it), as a PNG.

Reads the recordings back through the capture stage's own reader
(:func:`couch.capture.frames.open_kinect_stream`), so what it shows is what the pipeline will see.
Depth is colour-mapped over 0.5–4 m (black = invalid); IR is grey from 0 to the image's 99th
percentile. A depth-only recording (no COLOR track, e.g. ``couch-simulate --no-color``) gets a
grey "no colour track" panel in place of colour.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from couch.atomic import atomic_path
from couch.capture.azure_mkv import KinectFormatError
from couch.capture.frames import open_kinect_stream


def colorize_depth(depth_mm: np.ndarray, near: float = 500.0, far: float = 4000.0) -> np.ndarray:
    """(H,W) uint16 millimetres → (H,W,3) uint8 RGB (turbo colour map; invalid pixels black)."""
    scaled = np.clip((depth_mm.astype(np.float32) - near) / (far - near), 0, 1)
    rgb = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    return np.where(depth_mm[..., None] > 0, rgb, 0).astype(np.uint8)


def scale_ir(ir: np.ndarray) -> np.ndarray:
    """(H,W) uint16 IR → (H,W,3) uint8 grey, 0 to the image's 99th percentile white (the few
    brightest pixels, close or shiny, would otherwise leave the rest of it black)."""
    top = max(float(np.percentile(ir, 99)), 1.0)
    grey = np.clip(ir.astype(np.float32) * (255.0 / top), 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=-1)


def _fit(image: np.ndarray, height: int) -> np.ndarray:
    w = round(image.shape[1] * height / image.shape[0])
    return cv2.resize(image, (w, height), interpolation=cv2.INTER_AREA)


def _no_color_panel(depth_shape: tuple[int, int], height: int) -> np.ndarray:
    """(height, W, 3) uint8 grey placeholder, as wide as the fitted depth image, that says the
    recording has no colour (a blank would look like a failed decode)."""
    width = round(depth_shape[1] * height / depth_shape[0])
    panel = np.full((height, width, 3), 90, np.uint8)
    for text, y in (("no colour track", height // 2 - 6), ("(depth-only recording)",
                                                            height // 2 + 18)):
        cv2.putText(panel, text, (10, y), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (230, 230, 230), 1)
    return panel


def contact_sheet(recordings: list[Path], frame: int, row_height: int = 240) -> np.ndarray:
    """(H,W,3) uint8 RGB: one row per recording, its colour, depth and (when the capture has
    one) IR images of ``frame`` (a placeholder panel instead of colour for a recording without
    a COLOR track)."""
    rows = []
    for path in recordings:
        stream = open_kinect_stream(path)
        found = None
        for f in stream:
            # a colour frame that does not decode is counted in stream.skipped: take the next
            if f.index >= frame and f.depth_mm is not None and (
                    not stream.has_color or f.color_rgb() is not None):
                found = f
                break
        if found is None:
            wanted = "colour and depth" if stream.has_color else "depth"
            raise KinectFormatError(f"{path}: no capture with {wanted} at or after frame "
                                    f"{frame}")
        rgb = found.color_rgb()
        color = (_fit(rgb, row_height) if rgb is not None
                 else _no_color_panel(found.depth_mm.shape, row_height))
        panels = [color, _fit(colorize_depth(found.depth_mm), row_height)]
        if found.ir is not None:
            panels.append(_fit(scale_ir(found.ir), row_height))
        gap = np.full((row_height, 6, 3), 255, np.uint8)
        row = np.concatenate([p for panel in panels for p in (panel, gap)][:-1], 1)
        label = f"{stream.serial}  t={found.timestamp_us / 1e6:.3f}s"
        cv2.putText(row, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 3)
        cv2.putText(row, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1)
        rows.append(row)
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 6), (0, width - r.shape[1]), (0, 0)), constant_values=255)
            for r in rows]
    return np.concatenate(rows, 0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="couch-contact-sheet", description=__doc__.split("\n")[0])
    ap.add_argument("session_dir", type=Path)
    ap.add_argument("-o", "--out", type=Path, default=None,
                    help="PNG path (default: SESSION_DIR/contact_sheet.png)")
    ap.add_argument("--frame", type=int, default=0, help="capture index")
    ap.add_argument("--folder", default="kinect", help="kinect or calibration")
    args = ap.parse_args(argv)
    recordings = sorted((args.session_dir / args.folder).glob("*.mkv"))
    if not recordings:
        print(f"couch-contact-sheet: no .mkv files in {args.session_dir / args.folder}",
              file=sys.stderr)
        return 1
    try:
        sheet = contact_sheet(recordings, args.frame)
    except (KinectFormatError, OSError) as e:
        print(f"couch-contact-sheet: {e}", file=sys.stderr)
        return 1
    out = args.out or args.session_dir / "contact_sheet.png"
    with atomic_path(out) as tmp:
        if not cv2.imwrite(str(tmp), sheet[..., ::-1]):
            raise OSError(f"{out}: could not write PNG")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
