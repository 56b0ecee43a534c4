"""Preview videos and contact sheets of human–chair motion (synthesised or captured).

A body mesh sequence, a chair mesh and hand-contact markers are ray-cast with
:func:`couch.tools.render.render` from one fixed camera that frames the whole sequence, over a
light grey floor quad at ``y = 0``; the frames go into an MP4 (:func:`write_mp4`, PyAV) and a PNG
contact sheet (:func:`contact_sheet`, :func:`write_png`). :func:`preview` does all of it.

World frame: metres, +Y up, floor at ``y = 0``. Cameras follow OpenCV (``K`` (3,3) pixels,
``world_from_camera`` (4,4), +Z forward, +Y down), as in :mod:`couch.tools.render`. Images are
RGB uint8 everywhere; conversion to OpenCV's BGR happens only inside :func:`write_png`.

Markers: ``contacts`` (K,3) are world target points (e.g. where the hands should touch the
chair), drawn as red spheres; ``hands`` (T,2,3) are the hands' current contact points, drawn as
blue spheres. Rows containing NaN are skipped (an inactive contact).
"""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np
import trimesh
from tqdm import tqdm

from couch.atomic import atomic_path
from couch.geometry import look_at
from couch.tools.render import Mesh, intrinsics, render

__all__ = [
    "BODY_COLOR", "CHAIR_COLOR", "CONTACT_COLOR", "FLOOR_COLOR", "HAND_COLOR", "MARKER_RADIUS",
    "contact_sheet", "framing_points", "preview", "preview_camera", "render_frames", "video_codec",
    "write_mp4", "write_png",
]

#: mesh colours, RGB in [0, 1]
BODY_COLOR = (0.87, 0.68, 0.56)
CHAIR_COLOR = (0.55, 0.36, 0.20)
FLOOR_COLOR = (0.93, 0.93, 0.95)
CONTACT_COLOR = (0.90, 0.08, 0.08)
HAND_COLOR = (0.12, 0.30, 0.95)
#: radius of the contact / hand marker spheres, metres
MARKER_RADIUS = 0.025

#: at most this many points go into the framing of the camera (vertices are strided beyond it)
_MAX_FRAMING_POINTS = 200_000


def _sphere_template() -> tuple[np.ndarray, np.ndarray]:
    s = trimesh.creation.icosphere(subdivisions=1, radius=MARKER_RADIUS)
    return np.asarray(s.vertices, dtype=np.float64), np.asarray(s.faces, dtype=np.int64)


def _spheres(centres: np.ndarray, color: tuple[float, float, float]) -> Mesh | None:
    """One mesh of marker spheres at the finite rows of ``centres`` (K,3); None if there are
    none."""
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    c = c[np.isfinite(c).all(1)]
    if len(c) == 0:
        return None
    v, f = _sphere_template()
    verts = (c[:, None, :] + v[None]).reshape(-1, 3)
    faces = (f[None] + len(v) * np.arange(len(c))[:, None, None]).reshape(-1, 3)
    return Mesh(verts, faces, color)


def _floor(points: np.ndarray) -> Mesh:
    """A square at y = 0 centred under ``points`` (N,3), at least 5 m across and twice as wide as
    their horizontal extent."""
    lo, hi = points.min(0), points.max(0)
    cx, cz = (lo[[0, 2]] + hi[[0, 2]]) / 2
    half = max(2.5, float(np.max(hi[[0, 2]] - lo[[0, 2]])))
    verts = np.array([[cx - half, 0.0, cz - half], [cx + half, 0.0, cz - half],
                      [cx + half, 0.0, cz + half], [cx - half, 0.0, cz + half]])
    return Mesh(verts, np.array([[0, 2, 1], [0, 3, 2]]), FLOOR_COLOR)


def framing_points(body_vertices: np.ndarray, chair_vertices: np.ndarray,
                   contacts: np.ndarray | None = None, hands: np.ndarray | None = None
                   ) -> np.ndarray:
    """(N,3) finite world points that the default camera of :func:`render_frames` frames: the body
    vertices of every frame (strided to at most 200,000 points), the chair vertices and the
    finite contact / hand markers."""
    body = np.asarray(body_vertices, dtype=np.float64).reshape(-1, 3)
    step = max(1, -(-len(body) // _MAX_FRAMING_POINTS))
    parts = [body[::step], np.asarray(chair_vertices, dtype=np.float64).reshape(-1, 3)]
    for extra in (contacts, hands):
        if extra is not None:
            parts.append(np.asarray(extra, dtype=np.float64).reshape(-1, 3))
    pts = np.concatenate(parts)
    return pts[np.isfinite(pts).all(1)]


def preview_camera(points: np.ndarray, width: int, height: int, fov_y_deg: float = 45.0,
                   azimuth_deg: float = 30.0, elevation_deg: float = 20.0
                   ) -> tuple[np.ndarray, np.ndarray]:
    """A fixed camera that frames ``points``.

    Args:
        points: (N,3) world points, metres (non-finite rows are ignored).
        width, height: image size, pixels.
        fov_y_deg: vertical field of view, degrees.
        azimuth_deg: direction of the camera seen from the target, degrees around +Y measured
            from +Z (0: the camera is on the +Z side; 90: on the +X side).
        elevation_deg: degrees above the horizontal plane through the target.

    Returns:
        ``K`` (3,3) pixel intrinsics and ``world_from_camera`` (4,4) (OpenCV: +Z forward, +Y
        down), looking at the centre of the points' bounding box from far enough away that their
        bounding sphere (about that centre) fits both the vertical and the horizontal field of
        view, with a 5 % margin.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(1)]
    if len(pts) == 0:
        raise ValueError("preview_camera: no finite points to frame")
    if width <= 0 or height <= 0 or not 0 < fov_y_deg < 180:
        raise ValueError(f"preview_camera: bad image size {width}x{height} or field of view "
                         f"{fov_y_deg}")
    centre = (pts.min(0) + pts.max(0)) / 2
    radius = max(float(np.linalg.norm(pts - centre, axis=1).max()), 0.05)
    half_y = np.deg2rad(fov_y_deg) / 2
    half_x = np.arctan(np.tan(half_y) * width / height)
    distance = 1.05 * radius / np.sin(min(half_y, half_x))
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    direction = np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    # straight above / below: "up" in the image is the -Z side of the world (azimuth 0 view)
    up = (0.0, 1.0, 0.0) if abs(np.cos(el)) > 1e-6 else (
        -np.sin(az) * np.sign(np.sin(el)), 0.0, -np.cos(az) * np.sign(np.sin(el)))
    pose = look_at(centre + distance * direction, centre, up)
    return intrinsics(width, height, fov_y_deg), pose


def _check_mesh(vertices: np.ndarray, faces: np.ndarray, what: str, batched: bool
                ) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    ndim = 3 if batched else 2
    if v.ndim != ndim or v.shape[-1] != 3 or v.shape[-2] == 0 or (batched and len(v) == 0):
        shape = "(T,V,3) with T, V >= 1" if batched else "(V,3) with V >= 1"
        raise ValueError(f"{what} vertices must be {shape}, got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or f.min() < 0 or f.max() >= v.shape[-2]:
        raise ValueError(f"{what} faces must be (F,3) indices into its {v.shape[-2]} vertices")
    return v, f


def _put_label(image: np.ndarray, text: str) -> None:
    """Dark text with a light outline in the top-left corner of ``image`` (in place)."""
    h = image.shape[0]
    scale = max(0.3, h / 800)
    org = (max(3, h // 60), max(10, round(22 * scale / 0.6)))
    for color, thick in (((255, 255, 255), 3), ((20, 20, 20), 1)):
        cv2.putText(image, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, color, thick, cv2.LINE_AA)


def render_frames(body_vertices: np.ndarray, body_faces: np.ndarray, chair_vertices: np.ndarray,
                  chair_faces: np.ndarray, *, contacts: np.ndarray | None = None,
                  hands: np.ndarray | None = None, frames: np.ndarray | None = None,
                  width: int = 480, height: int = 360, labels: list[str] | None = None,
                  camera: tuple[np.ndarray, np.ndarray] | None = None,
                  progress: bool = False) -> np.ndarray:
    """Render frames of a body sequence beside a chair over a floor.

    Args:
        body_vertices: (T,V,3) world metres; body_faces: (F,3) int.
        chair_vertices: (C,3) world metres (static); chair_faces: (G,3) int.
        contacts: (K,3) world contact targets, drawn in every frame as red spheres of radius
            :data:`MARKER_RADIUS`; rows with NaN are skipped.
        hands: (T,2,3) the hands' current contact points per frame, drawn as blue spheres;
            rows with NaN are skipped.
        frames: (n,) indices into T to render (default: all, in order).
        width, height: image size, pixels.
        labels: n strings, one per rendered frame, written in the top-left corner (None: none).
        camera: ``(K (3,3), world_from_camera (4,4))``; default
            ``preview_camera(framing_points(...), width, height)`` over *all* T frames, so any
            subset of frames is rendered from the same camera.
        progress: show a tqdm bar.

    Returns:
        (n, height, width, 3) uint8 RGB.
    """
    body, body_f = _check_mesh(body_vertices, body_faces, "body", batched=True)
    chair, chair_f = _check_mesh(chair_vertices, chair_faces, "chair", batched=False)
    n_frames = len(body)
    if contacts is not None:
        contacts = np.asarray(contacts, dtype=np.float64)
        if contacts.ndim != 2 or contacts.shape[1] != 3:
            raise ValueError(f"contacts must be (K,3), got {contacts.shape}")
    if hands is not None:
        hands = np.asarray(hands, dtype=np.float64)
        if hands.shape != (n_frames, 2, 3):
            raise ValueError(f"hands must be ({n_frames},2,3), got {hands.shape}")
    idx = np.arange(n_frames) if frames is None else np.asarray(frames, dtype=np.int64).ravel()
    if np.any((idx < 0) | (idx >= n_frames)):
        raise ValueError(f"frames must index the {n_frames} body frames, got {idx.tolist()}")
    if labels is not None and len(labels) != len(idx):
        raise ValueError(f"{len(labels)} labels for {len(idx)} frames")
    pts = framing_points(body, chair, contacts, hands)
    k, pose = preview_camera(pts, width, height) if camera is None else camera
    static = [Mesh(chair, chair_f, CHAIR_COLOR), _floor(pts)]
    marks = None if contacts is None else _spheres(contacts, CONTACT_COLOR)
    if marks is not None:
        static.append(marks)
    out = np.empty((len(idx), height, width, 3), np.uint8)
    for i, t in enumerate(tqdm(idx, desc="render", unit="frame", disable=not progress)):
        meshes = [Mesh(body[t], body_f, BODY_COLOR), *static]
        hand_mesh = None if hands is None else _spheres(hands[t], HAND_COLOR)
        if hand_mesh is not None:
            meshes.append(hand_mesh)
        out[i] = render(meshes, k, pose, width, height).rgb
        if labels is not None:
            _put_label(out[i], labels[i])
    return out


def _check_images(images: np.ndarray, path: str | os.PathLike) -> np.ndarray:
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3 or 0 in images.shape:
        raise ValueError(f"{path}: expected non-empty (T,H,W,3) images, got {images.shape}")
    if images.dtype != np.uint8:
        raise ValueError(f"{path}: expected uint8 images, got {images.dtype}")
    return images


def video_codec() -> str:
    """``"libx264"`` if the installed PyAV can encode H.264 with it, else ``"mpeg4"``."""
    try:
        av.codec.Codec("libx264", "w")
    except ValueError:  # av.codec.codec.UnknownCodecError: not in this build of FFmpeg
        return "mpeg4"
    return "libx264"


def write_mp4(images: np.ndarray, path: str | os.PathLike, fps: float = 30.0) -> Path:
    """Encode (T,H,W,3) uint8 RGB ``images`` as an MP4 at ``fps`` frames per second, atomically.

    H.264 (libx264, yuv420p) when available, else MPEG-4 part 2. yuv420p needs even sizes: an odd
    width or height is padded by one replicated edge pixel. Returns ``path`` as a Path.
    """
    path = Path(path)
    images = _check_images(images, path)
    if not fps > 0:
        raise ValueError(f"{path}: fps must be positive, got {fps}")
    _, h, w, _ = images.shape
    pad_h, pad_w = h % 2, w % 2
    if pad_h or pad_w:
        images = np.pad(images, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
    codec = video_codec()
    with atomic_path(path) as tmp, av.open(str(tmp), mode="w", format="mp4") as container:
        stream = container.add_stream(codec, rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height = w + pad_w, h + pad_h
        stream.pix_fmt = "yuv420p"
        if codec == "libx264":
            stream.options = {"crf": "20", "preset": "medium"}
        else:
            stream.bit_rate = max(1_000_000, 8 * (w + pad_w) * (h + pad_h))
        for image in images:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode(None))
    return path


def contact_sheet(images: np.ndarray, columns: int = 4, background: int = 255) -> np.ndarray:
    """Tile (T,H,W,3) images row-major into one (rows*H, columns*W, 3) image,
    ``rows = ceil(T / columns)``; empty tiles are filled with ``background`` (grey level)."""
    images = _check_images(images, "contact_sheet")
    if columns < 1:
        raise ValueError(f"contact_sheet: columns must be >= 1, got {columns}")
    n, h, w, c = images.shape
    rows = -(-n // columns)
    tiles = np.full((rows * columns, h, w, c), background, np.uint8)
    tiles[:n] = images
    return tiles.reshape(rows, columns, h, w, c).transpose(0, 2, 1, 3, 4).reshape(
        rows * h, columns * w, c)


def write_png(image: np.ndarray, path: str | os.PathLike) -> Path:
    """Write an (H,W,3) uint8 RGB image as a PNG (cv2.imwrite, BGR), atomically; returns the
    path."""
    path = Path(path)
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] != 3 or 0 in image.shape or image.dtype != np.uint8:
        raise ValueError(f"{path}: expected non-empty (H,W,3) uint8, got {image.shape} "
                         f"{image.dtype}")
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(image[..., ::-1])):
            raise OSError(f"{path}: could not write PNG")
    return path


def preview(body_vertices: np.ndarray, body_faces: np.ndarray, chair_vertices: np.ndarray,
            chair_faces: np.ndarray, out_stem: str | os.PathLike, *,
            contacts: np.ndarray | None = None, hands: np.ndarray | None = None,
            fps: float = 30.0, sheet_frames: int = 8, width: int = 480, height: int = 360,
            video_stride: int = 1, columns: int = 4, progress: bool = True) -> dict[str, Path]:
    """Write ``<out_stem>.mp4`` and ``<out_stem>.png`` previews of a motion.

    The video holds every ``video_stride``-th frame at ``fps / video_stride`` frames per second
    (so it plays in real time); the PNG is a contact sheet (``columns`` wide) of ``sheet_frames``
    evenly spaced frames, first and last included (fewer if the sequence is shorter). Every frame
    is labelled with its index and time. Inputs as in :func:`render_frames` (``fps``: of the
    input sequence). Each needed frame is rendered once, all from the same camera.

    Returns:
        ``{"video": <stem>.mp4, "sheet": <stem>.png}``.
    """
    if video_stride < 1 or sheet_frames < 1:
        raise ValueError(f"video_stride and sheet_frames must be >= 1, got {video_stride} and "
                         f"{sheet_frames}")
    stem = Path(out_stem)
    n_frames = np.asarray(body_vertices).shape[0] if np.ndim(body_vertices) == 3 else 0
    if n_frames == 0:
        raise ValueError(f"{stem}: body_vertices must be non-empty (T,V,3), got "
                         f"{np.shape(body_vertices)}")
    video_idx = np.arange(0, n_frames, video_stride)
    sheet_idx = np.unique(np.round(np.linspace(0, n_frames - 1, min(sheet_frames, n_frames)))
                          .astype(np.int64))
    needed = np.union1d(video_idx, sheet_idx)
    images = render_frames(body_vertices, body_faces, chair_vertices, chair_faces,
                           contacts=contacts, hands=hands, frames=needed, width=width,
                           height=height, labels=[f"frame {t}  {t / fps:.2f} s" for t in needed],
                           progress=progress)
    video = write_mp4(images[np.searchsorted(needed, video_idx)],
                      stem.with_name(stem.name + ".mp4"), fps / video_stride)
    sheet = write_png(contact_sheet(images[np.searchsorted(needed, sheet_idx)], columns),
                      stem.with_name(stem.name + ".png"))
    return {"video": video, "sheet": sheet}
