"""``make demo``: the furthest-along main job. For now: pose the bundled body sitting on a box seat
and write a front + side preview PNG (later issues replace this with the full pipeline)."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh

from couch.atomic import atomic_path
from couch.body import load_body_model, sitting_pose
from couch.geometry import look_at
from couch.tools.render import Mesh, intrinsics, render


def seated_body(model_name: str, betas: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Vertices (V,3) of the body seated with its soles on the floor, and its seat height (m)."""
    model = load_body_model(model_name)
    with torch.no_grad():
        out = model(betas=None if betas is None else betas[None],
                    body_pose=torch.as_tensor(sitting_pose())[None])
    v = out.vertices[0].numpy().astype(np.float64)
    soles = np.concatenate([model.contact_vertices["left_foot"],
                            model.contact_vertices["right_foot"]])
    v[:, 1] -= v[soles, 1].min()
    seat = float(v[model.contact_vertices["pelvis"], 1].min())
    return v, seat


def preview(vertices: np.ndarray, faces: np.ndarray, seat_height: float, size: int = 512
            ) -> np.ndarray:
    """Front and side views (H, 2H, 3) uint8 RGB of the body, its box seat and the floor."""
    hips = vertices[:, 2].min()
    seat = trimesh.creation.box(extents=(0.45, seat_height, 0.42))
    seat.apply_translation((0.0, seat_height / 2, hips + 0.21))
    floor = trimesh.creation.box(extents=(3.0, 0.01, 3.0))
    floor.apply_translation((0.0, -0.005, 0.0))
    meshes = [Mesh(vertices, faces, (0.85, 0.66, 0.55)),
              Mesh(seat.vertices, seat.faces, (0.45, 0.32, 0.22)),
              Mesh(floor.vertices, floor.faces, (0.8, 0.8, 0.82))]
    centre = np.array([0.0, 0.65, vertices[:, 2].mean()])
    k = intrinsics(size, size, 45.0)
    views = [render(meshes, k, look_at(centre + offset, centre), size, size).rgb
             for offset in (np.array([0.4, 0.5, 2.6]), np.array([2.7, 0.5, 0.0]))]
    return np.concatenate(views, axis=1)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("-o", "--out", type=Path, default=Path("out/demo_sitting.png"))
    ap.add_argument("--model", default="couch-body", help="bundled name or SMPL .npz/.pkl path")
    ap.add_argument("--size", type=int, default=512, help="pixels per view")
    args = ap.parse_args(argv)
    vertices, seat_height = seated_body(args.model)
    image = preview(vertices, load_body_model(args.model).faces, seat_height, args.size)
    with atomic_path(args.out) as tmp:
        if not cv2.imwrite(str(tmp), image[..., ::-1]):
            raise OSError(f"{args.out}: could not write PNG")
    print(f"wrote {args.out} (seat height {seat_height:.2f} m, front and side views)")


if __name__ == "__main__":
    main()
