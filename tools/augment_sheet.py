"""``python -m couch.tools.augment_sheet PROCESSED --shapes DIR -o sheet.png``: one sequence
re-targeted onto several chairs, as a contact sheet.

The first tile is the source frame (its body and chair); each further tile is the same frame
after :func:`couch.augment.augment_sequence` put the body onto another shape of the library
(shapes taken round-robin over the categories so the sheet shows straight chairs, armchairs and
sofas). Active contacts are drawn as dots (red: hands, blue: pelvis, green: feet); a tile's
caption says the shape, its category, the 95th-percentile reach error and whether the sample
was kept or why it was rejected. The frame shown is the one with the most hand contacts
(``--frame`` to choose). Rendering: :func:`couch.tools.render.render`, a camera in front of the
chair and to its left (the chair's frame from :func:`couch.augment.canonical_chair_frame`),
looking at the seat.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from couch.atomic import atomic_path
from couch.augment import (
    ShapeEntry,
    augment_sequence,
    canonical_chair_frame,
    load_shape_library,
)
from couch.body import CONTACT_NAMES
from couch.fitting import BodyParams, cached_model, pose_body
from couch.geometry import apply_transform, look_at
from couch.schema import ProcessedSession, SchemaError, read_processed
from couch.tools.render import Mesh, intrinsics, render

#: dot colours (BGR for OpenCV) of the contact parts, CONTACT_NAMES order
_DOTS = {"pelvis": (220, 120, 30), "left_hand": (40, 40, 230), "right_hand": (40, 40, 230),
         "left_foot": (60, 180, 60), "right_foot": (60, 180, 60)}


def pick_frame(session: ProcessedSession) -> int:
    """The frame with the most active hand contacts (ties: the most contacts of any part)."""
    hands = [CONTACT_NAMES.index("left_hand"), CONTACT_NAMES.index("right_hand")]
    score = session.contact_active[:, hands].sum(1) * 10 + session.contact_active.sum(1)
    return int(np.argmax(score))


def pick_shapes(entries: list[ShapeEntry], count: int) -> list[ShapeEntry]:
    """Up to ``count`` shapes, round-robin over the categories (sorted by id within each)."""
    by_cat: dict[str, list[ShapeEntry]] = {}
    for e in sorted(entries, key=lambda e: e.id):
        by_cat.setdefault(e.category, []).append(e)
    out: list[ShapeEntry] = []
    while len(out) < count and any(by_cat.values()):
        for cat in sorted(by_cat):
            if by_cat[cat] and len(out) < count:
                out.append(by_cat[cat].pop(0))
    return out


def render_tile(session: ProcessedSession, frame: int, caption: str, size: int = 360
                ) -> np.ndarray:
    """(size, size, 3) uint8 BGR: the body and chair of ``session`` at ``frame``."""
    model = cached_model("couch-body")
    verts, _ = pose_body(model, BodyParams.from_processed(session).frames(slice(frame,
                                                                                frame + 1)))
    chair = apply_transform(session.object_pose, session.object_vertices.astype(np.float64))
    # /object/pose of a processed session is the scan's frame: find the chair's own (front +Z)
    pose = canonical_chair_frame(chair, session.object_faces)
    seat = apply_transform(pose, np.array([[0.0, 0.45, 0.0]]))[0]
    eye = apply_transform(pose, np.array([[1.3, 1.4, 2.1]]))[0]
    cam = look_at(eye, seat)
    k = intrinsics(size, size, 50.0)
    img = render([Mesh(verts[0], model.faces, (0.55, 0.7, 0.9)),
                  Mesh(chair, session.object_faces, (0.85, 0.6, 0.35))], k, cam, size,
                 size).rgb[..., ::-1].copy()
    pts = session.contact_points[frame]
    cam_pts = apply_transform(np.linalg.inv(cam), np.nan_to_num(pts))
    for name, p, active in zip(CONTACT_NAMES, cam_pts, session.contact_active[frame],
                               strict=True):
        if active and p[2] > 0:
            uv = (k @ p)[:2] / p[2]
            cv2.circle(img, (int(uv[0]), int(uv[1])), 5, _DOTS[name], -1, cv2.LINE_AA)
    for i, line in enumerate(caption.split("\n")):
        cv2.putText(img, line, (6, 18 + 16 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (20, 20, 20),
                    1, cv2.LINE_AA)
    return img


def contact_sheet(session: ProcessedSession, shapes: list[ShapeEntry], frame: int | None = None,
                  size: int = 360, columns: int = 4) -> tuple[np.ndarray, list[str]]:
    """The sheet (BGR uint8) and one line per shape (what happened to its sample)."""
    f = pick_frame(session) if frame is None else frame
    if not 0 <= f < session.num_frames:
        raise ValueError(f"frame {f} is outside the sequence's {session.num_frames} frames")
    tiles = [render_tile(session, f, f"source: {session.object_name}\nframe {f}", size)]
    lines = []
    for shape in shapes:
        res = augment_sequence(session, shape)
        status = "kept" if res.rejected is None else f"rejected ({res.rejected.split(':')[0]})"
        lines.append(f"{shape.id} ({shape.category}): {status}, reach p95 "
                     f"{res.stats.reach_p95 * 100:.2f} cm, penetration p95 "
                     f"{res.stats.penetration_p95 * 100:.2f} cm")
        if res.session is not None:
            tiles.append(render_tile(res.session, f, f"{shape.id} ({shape.category})\n{status}, "
                                     f"reach p95 {res.stats.reach_p95 * 100:.1f} cm", size))
    while len(tiles) % columns:
        tiles.append(np.full_like(tiles[0], 255))
    rows = [np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)]
    return np.vstack(rows), lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m couch.tools.augment_sheet",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("processed", help="a processed.h5 (or a simulator ground_truth.h5)")
    ap.add_argument("--shapes", required=True, help="shape library folder (ShapeNet layout)")
    ap.add_argument("-o", "--output", required=True, help="PNG to write")
    ap.add_argument("--count", type=int, default=6, help="shapes (default 6)")
    ap.add_argument("--frame", type=int, default=None, help="frame to show")
    ap.add_argument("--cache-dir", default=None, help="shape cache folder")
    args = ap.parse_args(argv)
    try:
        session = read_processed(args.processed)
    except SchemaError as exc:
        print(f"augment_sheet: {exc}", file=sys.stderr)
        return 2
    if not Path(args.shapes).is_dir():
        print(f"augment_sheet: {args.shapes}: no such folder", file=sys.stderr)
        return 2
    lib = load_shape_library(args.shapes, cache_dir=args.cache_dir)
    shapes = pick_shapes(lib.entries, args.count)
    if not shapes:
        print(f"augment_sheet: {args.shapes}: no usable shape ({lib.summary()})", file=sys.stderr)
        return 1
    sheet, lines = contact_sheet(session, shapes, args.frame)
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", sheet)
    if not ok:
        print(f"augment_sheet: cannot encode {out} as PNG", file=sys.stderr)
        return 1
    with atomic_path(out) as tmp:
        tmp.write_bytes(buf.tobytes())
    print("\n".join(lines))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
