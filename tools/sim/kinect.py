"""Simulated Azure Kinect cameras: what N devices around a chair would record, frame by frame.

Each device is a :class:`~couch.capture.azure_calibration.KinectCalibration` (depth NFOV_UNBINNED
640x576 + colour 720P 1280x720, both with OpenCV rational distortion, and the factory
``color_from_depth``) plus a pose ``world_from_depth`` (4, 4): world is metres, +Y up, floor
y = 0; the cameras are OpenCV-style (+Z forward, +X right, +Y down in the image).

Images are made by ray casting (open3d ``RaycastingScene``) with one ray per pixel *centre through
the lens distortion*: pixel ``(u, v)`` (OpenCV convention, centre of the top-left pixel at (0, 0))
is undistorted with ``cv2.undistortPoints`` (run to convergence, see :func:`undistorted_grid`), so
projecting any surface point with ``cv2.projectPoints`` and the calibration lands on the pixel
that saw it. The capture stage can therefore calibrate and back-project with the calibration it
reads from ``calibration.json`` alone.

Per frame: ``scene = build_scene(meshes)`` once, then :func:`render_depth` / :func:`render_color`
for every camera. Depth carries the artefacts of a time-of-flight sensor (:class:`DepthNoise`):
distance-dependent axial noise, a per-device systematic bias, lateral edge jitter, flying pixels,
grazing-angle / out-of-range / random invalid pixels and the NFOV field-of-view cut. Colour is
shaded (Lambertian + ambient, cast shadows), textured (procedural wood / fabric / floor patterns
and image textures such as a ChArUco board) and carries optical blur, vignetting, white-balance
differences, sensor noise and JPEG compression (:class:`ColorNoise`). Every frame also returns
noise-free ground truth (metric depth, per-pixel mesh labels, person/chair masks).

Calibrations are modelled on two retail devices' factory files (serials 001514394512 and
000573600112): their depth lenses differ in coefficients but agree to ~0.2 px in distortion;
the depth principal point sits ~55 px below the image centre (the NFOV crop is not centred on the
optical axis); the colour camera is ~32 mm to the side and its axis ~5-6° above the depth axis.
"""

from __future__ import annotations

import functools
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import open3d as o3d
from scipy import ndimage
from scipy.spatial.transform import Rotation

from couch.capture.azure_calibration import DEPTH_RANGE_M, CameraIntrinsics, KinectCalibration
from couch.capture.charuco import BoardSpec, board_image
from couch.capture.registration import UNDISTORT_CRITERIA
from couch.geometry import invert_transform, look_at, make_transform, vertex_normals

__all__ = [
    "LABEL_BACKGROUND",
    "LABEL_BOARD",
    "LABEL_CHAIR",
    "LABEL_NONE",
    "LABEL_PERSON",
    "TEXTURES",
    "ColorFrame",
    "ColorNoise",
    "DepthFrame",
    "DepthNoise",
    "Light",
    "PlanarTexture",
    "SceneMesh",
    "SimScene",
    "board_mesh",
    "build_scene",
    "device_depth_bias",
    "perturb_calibration",
    "place_cameras",
    "random_calibration",
    "render_color",
    "render_depth",
    "skip_color",
    "undistorted_grid",
    "world_from_color",
]

LABEL_NONE = -1
LABEL_BACKGROUND = 0
LABEL_PERSON = 1
LABEL_CHAIR = 2
LABEL_BOARD = 3

#: Procedural texture kinds of :attr:`SceneMesh.texture` (index 0 = none).
TEXTURES = (None, "wood", "fabric", "floor")

# --------------------------------------------------------------------------------------------
# Scene description
# --------------------------------------------------------------------------------------------

@dataclass(eq=False)
class PlanarTexture:
    """An image mapped onto a plane, e.g. the printed side of a calibration board.

    Attributes:
        image: (H, W) or (H, W, 3) image, uint8 (0-255) or float in [0, 1]; RGB.
        world_from_plane: (4, 4) pose of the plane frame in the world (metres); the image lies in
            the plane's z = 0.
        px_per_m: texels per metre.
        origin: plane-frame (x, y) of the image's top-left *corner*: texel ``(u, v)``'s centre is
            at ``(origin_x + (u + 0.5)/px_per_m, origin_y + (v + 0.5)/px_per_m, 0)``.
        tolerance: hits within this distance (m) of the plane and inside the image get the
            texture; the rest of the mesh keeps its own colour.
    """

    image: np.ndarray
    world_from_plane: np.ndarray
    px_per_m: float
    origin: tuple[float, float] = (0.0, 0.0)
    tolerance: float = 1e-3

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        img = img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else img.astype(np.float32)
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"texture image must be (H,W) or (H,W,3), got {img.shape}")
        self.image = np.ascontiguousarray(img)
        self.world_from_plane = np.asarray(self.world_from_plane, dtype=np.float64)
        if self.world_from_plane.shape != (4, 4):
            raise ValueError("world_from_plane must be (4,4)")


@dataclass(eq=False)
class SceneMesh:
    """One triangle mesh of the scene with its semantic label and appearance.

    Attributes:
        vertices: (V, 3) world positions, metres.
        faces: (F, 3) vertex indices.
        label: 0 background/room, 1 person, 2 chair, 3 calibration board (``LABEL_*``).
        color: (3,) RGB albedo in [0, 1] used when no per-vertex/per-face colours are given.
        vertex_colors: optional (V, 3) RGB in [0, 1], interpolated over faces.
        face_colors: optional (F, 3) RGB in [0, 1] (ignored if ``vertex_colors`` is given).
        texture: procedural pattern multiplying the colour: ``"wood"``, ``"fabric"``,
            ``"floor"`` or None.
        texture_coords: optional (V, 3) positions (metres) at which the procedural texture is
            evaluated, e.g. the body's rest-pose or the chair's own-frame vertices, so patterns
            stick to a moving surface; default: ``vertices`` (world).
        planar_texture: optional image texture on a plane (the ChArUco board).
        smooth: shade with interpolated vertex normals (bodies) instead of face normals.
    """

    vertices: np.ndarray
    faces: np.ndarray
    label: int = LABEL_BACKGROUND
    color: tuple[float, float, float] = (0.7, 0.7, 0.7)
    vertex_colors: np.ndarray | None = None
    face_colors: np.ndarray | None = None
    texture: str | None = None
    texture_coords: np.ndarray | None = None
    planar_texture: PlanarTexture | None = None
    smooth: bool = False

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        if len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise ValueError("faces index outside vertices")
        if self.texture not in TEXTURES:
            raise ValueError(f"unknown texture {self.texture!r}; expected one of {TEXTURES}")
        for name, n in (("vertex_colors", len(self.vertices)), ("face_colors", len(self.faces)),
                        ("texture_coords", len(self.vertices))):
            value = getattr(self, name)
            if value is not None and np.shape(value) != (n, 3):
                raise ValueError(f"{name} must be ({n}, 3), got {np.shape(value)}")


@dataclass(eq=False)
class SimScene:
    """A frame's geometry ready for ray casting (build with :func:`build_scene`; reuse it for all
    cameras of the frame). Arrays concatenate all meshes; ``face_offset[g]`` is the first global
    face of mesh (open3d geometry id) ``g``."""

    raycaster: o3d.t.geometry.RaycastingScene
    meshes: list[SceneMesh]
    face_offset: np.ndarray      # (M+1,) int64
    faces: np.ndarray            # (F, 3) int64, global vertex indices
    face_colors: np.ndarray      # (F, 3) float32 RGB of flat-coloured faces
    vertex_colors: np.ndarray    # (V, 3) float32 RGB (meshes with per-vertex colours)
    face_interp: np.ndarray      # (F,) bool: colour interpolated from vertex_colors
    face_texture: np.ndarray     # (F,) int8 index into TEXTURES
    tex_coords: np.ndarray       # (V, 3) float32
    face_own_coords: np.ndarray  # (F,) bool: the mesh has its own texture_coords
    vertex_normals: np.ndarray   # (V, 3) float32 (zeros for flat-shaded meshes)
    face_smooth: np.ndarray      # (F,) bool
    mesh_label: np.ndarray       # (M,) int8


def build_scene(meshes: list[SceneMesh]) -> SimScene:
    """Put ``meshes`` into one open3d ``RaycastingScene`` (its BVH is built on the first cast)
    and gather their appearance into flat arrays."""
    raycaster = o3d.t.geometry.RaycastingScene()
    counts_v = np.array([len(m.vertices) for m in meshes], dtype=np.int64)
    counts_f = np.array([len(m.faces) for m in meshes], dtype=np.int64)
    v_off = np.concatenate([[0], np.cumsum(counts_v)])
    f_off = np.concatenate([[0], np.cumsum(counts_f)])
    faces, fcolors, vcolors, interp, tex, coords, own, normals, smooth = ([] for _ in range(9))
    for i, m in enumerate(meshes):
        gid = raycaster.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)),
                                      o3d.core.Tensor(m.faces.astype(np.uint32)))
        if gid != i:
            raise RuntimeError(f"open3d gave geometry id {gid} to mesh {i}")
        faces.append(m.faces + v_off[i])
        if m.face_colors is not None and m.vertex_colors is None:
            fcolors.append(np.asarray(m.face_colors, dtype=np.float32))
        else:
            fcolors.append(np.broadcast_to(np.asarray(m.color, np.float32), (len(m.faces), 3)))
        vcolors.append(np.zeros((len(m.vertices), 3), np.float32) if m.vertex_colors is None
                       else np.asarray(m.vertex_colors, dtype=np.float32))
        interp.append(np.full(len(m.faces), m.vertex_colors is not None))
        tex.append(np.full(len(m.faces), TEXTURES.index(m.texture), dtype=np.int8))
        coords.append(m.vertices if m.texture_coords is None
                      else np.asarray(m.texture_coords, dtype=np.float64))
        own.append(np.full(len(m.faces), m.texture_coords is not None))
        normals.append(vertex_normals(m.vertices, m.faces).astype(np.float32) if m.smooth
                       else np.zeros((len(m.vertices), 3), np.float32))
        smooth.append(np.full(len(m.faces), m.smooth))

    def cat(parts: list[np.ndarray], shape: tuple[int, ...], dtype: type) -> np.ndarray:
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)

    return SimScene(
        raycaster=raycaster, meshes=list(meshes), face_offset=f_off,
        faces=cat(faces, (0, 3), np.int64), face_colors=cat(fcolors, (0, 3), np.float32),
        vertex_colors=cat(vcolors, (0, 3), np.float32), face_interp=cat(interp, (0,), bool),
        face_texture=cat(tex, (0,), np.int8), tex_coords=cat(coords, (0, 3), np.float32),
        face_own_coords=cat(own, (0,), bool),
        vertex_normals=cat(normals, (0, 3), np.float32), face_smooth=cat(smooth, (0,), bool),
        mesh_label=np.array([m.label for m in meshes], dtype=np.int8))


def board_mesh(spec: BoardSpec, world_from_board: np.ndarray, thickness: float = 0.005,
               px_per_m: float = 2000.0) -> SceneMesh:
    """A printed ChArUco board as a thin box (label 3) with its image on the printed face.

    The printed face is the board frame's z = 0 plane (see :mod:`couch.capture.charuco`: +Z
    points into the board, so the face is seen from the −Z side); the box extends to
    z = ``thickness`` behind it and covers the board's margin. ``px_per_m`` is the texture
    resolution: 2000 (0.5 mm texels) stays finer than a 720p pixel beyond ~0.3 m.
    """
    w, h = spec.size
    x0, y0 = -spec.margin, -spec.margin
    corners = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=np.float64)
    local = np.array([x0, y0, 0.0]) + corners * np.array([w, h, thickness])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    world_from_board = np.asarray(world_from_board, dtype=np.float64)
    verts = local @ world_from_board[:3, :3].T + world_from_board[:3, 3]
    tex = PlanarTexture(board_image(spec, px_per_m), world_from_board, px_per_m,
                        origin=(x0, y0))
    return SceneMesh(verts, faces, label=LABEL_BOARD, color=(0.95, 0.95, 0.95),
                     planar_texture=tex)


# --------------------------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------------------------

# Factory calibrations of two retail devices (calibration.json ModelParameters order: cx, cy, fx,
# fy, k1..k6, codx, cody, p2, p1; normalised by the 1024x1024 / 4096x3072 sensor) and their
# colour Rt: the base of random_calibration's per-device variation.
_REAL_DEVICES = (
    {"depth": [0.51296979, 0.51692355, 0.49278089, 0.49290284, 0.54793978, -0.02097137,
               -0.00265223, 0.88967907, 0.08613021, -0.01391038, 0, 0, -7.2104158e-5,
               2.0557534e-5],
     "color": [0.49984714, 0.50661761, 0.47796512, 0.63742393, 0.33012131, -2.48939657,
               1.45367086, 0.20891207, -2.30291510, 1.37512755, 0, 0, -1.2944525e-4,
               -1.6178245e-4],
     "tilt_deg": 4.94, "translation": [-0.03208343, -0.00220537, 0.00388369]},
    {"depth": [0.50127333, 0.50319624, 0.49252400, 0.49259248, 6.08414602, 4.37549114,
               0.23618598, 6.40873337, 6.41829586, 1.22029209, 0, 0, 6.5029337e-5,
               -5.5295703e-5],
     "color": [0.49866253, 0.50206763, 0.47818887, 0.63736248, 0.58438081, -2.49424911,
               1.36028302, 0.46475524, -2.33624649, 1.30115962, 0, 0, -1.7650700e-4,
               6.5308169e-4],
     "tilt_deg": 5.87, "translation": [-0.03202272, -0.00207925, 0.00393461]},
)


def _intrinsics_from_params(p: list[float], size: tuple[int, int], binned: tuple[int, int],
                            crop: tuple[int, int], metric_radius: float) -> CameraIntrinsics:
    cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, _, _, p2, p1 = p
    return CameraIntrinsics(width=size[0], height=size[1], fx=fx * binned[0], fy=fy * binned[1],
                            cx=cx * binned[0] - crop[0] - 0.5, cy=cy * binned[1] - crop[1] - 0.5,
                            dist=np.array([k1, k2, p1, p2, k3, k4, k5, k6]),
                            metric_radius=metric_radius)


def _radial_ok(intr: CameraIntrinsics) -> bool:
    """The lens model maps radius monotonically out to beyond the image corners (a jittered
    rational model could fold over, and undistortion would then be ambiguous)."""
    k1, k2, _, _, k3, k4, k5, k6 = intr.dist
    r = np.linspace(0.0, intr.metric_radius, 1000)
    r2 = r * r
    rd = r * (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    corner = max(np.hypot(x - intr.cx, y - intr.cy) for x in (-0.5, intr.width - 0.5)
                 for y in (-0.5, intr.height - 0.5)) / min(intr.fx, intr.fy)
    beyond = np.flatnonzero(rd >= 1.02 * corner)
    return bool(len(beyond) and np.all(np.diff(rd[: beyond[0] + 1]) > 0))


def random_calibration(rng: np.random.Generator, serial: str | None = None) -> KinectCalibration:
    """A plausible factory calibration of one Azure Kinect (depth NFOV_UNBINNED, colour 720P).

    One of two real devices' calibrations (see module doc), varied as devices vary: focal lengths
    ±0.2 %, principal points by a few pixels, the lens profile by ~0.5 px at the image edge, the
    colour camera's mounting by ~0.3 mm and ~0.3° (its ~5-6° tilt relative to the depth camera
    kept).
    ``serial``: 12 digits (random if None).
    """
    base = _REAL_DEVICES[int(rng.integers(len(_REAL_DEVICES)))]
    for _ in range(100):
        def vary(p: list[float], f_rel: float, c_abs: float, k1_std: float) -> list[float]:
            p = list(p)
            f = p[2] * (1 + rng.normal(0, f_rel))
            p[3] = p[3] / p[2] * f * (1 + rng.normal(0, 2e-4))
            p[2] = f
            p[0] += rng.normal(0, c_abs)
            p[1] += rng.normal(0, c_abs)
            # The rational model's coefficients are strongly correlated (numerator and
            # denominator nearly cancel), so only k1 is varied: by ~0.5 px at the image edge.
            p[4] += rng.normal(0, k1_std)
            p[12:14] = [t + rng.normal(0, 3e-5) for t in p[12:14]]
            return p

        depth = _intrinsics_from_params(vary(base["depth"], 2e-3, 0.005, 2e-3), (640, 576),
                                        (1024, 1024), (192, 180), 1.74)
        color = _intrinsics_from_params(vary(base["color"], 2e-3, 0.002, 3e-4), (1280, 720),
                                        (1280, 960), (0, 120), 1.7)
        if _radial_ok(depth) and _radial_ok(color):
            break
    else:  # pragma: no cover - the jitter is far too small for this
        raise RuntimeError("could not draw a monotonic lens model")
    # The colour axis points base["tilt_deg"] above the depth axis: R = Rx(-tilt) in the SDK's
    # color-from-depth rotation (row 1 col 2 = +sin tilt, as in the devices' files).
    angles = np.deg2rad([-base["tilt_deg"] + rng.normal(0, 0.3), rng.normal(0, 0.1),
                         rng.normal(0, 0.1)])
    rot = Rotation.from_euler("xyz", angles).as_matrix()
    trans = np.asarray(base["translation"]) + rng.normal(0, 3e-4, 3)
    if serial is None:
        serial = f"{int(rng.integers(0, 10**10)):010d}12"
    return KinectCalibration(depth=depth, color=color, color_from_depth=make_transform(rot, trans),
                             depth_mode="NFOV_UNBINNED", color_resolution="720P", serial=serial)


def perturb_calibration(calib: KinectCalibration, rng: np.random.Generator,
                        focal_rel: float = 5e-4, center_px: float = 0.3,
                        rotation_deg: float = 0.05, translation_m: float = 5e-4,
                        ) -> KinectCalibration:
    """The device's *true* optics, given the factory calibration it reports.

    A factory calibration is itself an estimate. To keep accuracy measurements honest, a
    simulator may render with ``perturb_calibration(reported, rng)`` and write ``reported`` to
    ``calibration.json``. Each focal length moves by N(0, ``focal_rel``) relative, each principal
    point by N(0, ``center_px``) px, and ``color_from_depth`` by N(0, ``rotation_deg``) per axis
    and N(0, ``translation_m``) per axis (distortion is kept). These defaults (~0.3 px, ~0.5 mm)
    are assumptions of the order of published reprojection errors, not measured device data.
    """
    def intrinsics(intr: CameraIntrinsics) -> CameraIntrinsics:
        return CameraIntrinsics(
            width=intr.width, height=intr.height,
            fx=intr.fx * (1 + rng.normal(0, focal_rel)),
            fy=intr.fy * (1 + rng.normal(0, focal_rel)),
            cx=intr.cx + rng.normal(0, center_px), cy=intr.cy + rng.normal(0, center_px),
            dist=intr.dist.copy(), metric_radius=intr.metric_radius)

    delta = make_transform(
        Rotation.from_euler("xyz", rng.normal(0, rotation_deg, 3), degrees=True).as_matrix(),
        rng.normal(0, translation_m, 3))
    return KinectCalibration(depth=intrinsics(calib.depth), color=intrinsics(calib.color),
                             color_from_depth=delta @ calib.color_from_depth,
                             depth_mode=calib.depth_mode,
                             color_resolution=calib.color_resolution, serial=calib.serial,
                             extra=calib.extra)


def world_from_color(calib: KinectCalibration, world_from_depth: np.ndarray) -> np.ndarray:
    """(4, 4) pose of the colour camera: ``world_from_depth @ inv(color_from_depth)``."""
    return np.asarray(world_from_depth, dtype=np.float64) @ invert_transform(
        calib.color_from_depth)


def place_cameras(rng: np.random.Generator, n: int = 4,
                  target: tuple[float, float, float] = (0.0, 0.8, 0.0),
                  radius: tuple[float, float] = (2.0, 3.0),
                  height: tuple[float, float] = (1.2, 2.0),
                  ) -> list[tuple[KinectCalibration, np.ndarray]]:
    """``n`` devices on tripods around ``target`` (world, metres), each aimed at it.

    Azimuths are evenly spread (random start) with ±15° jitter; horizontal distance and height
    are uniform in ``radius`` and ``height``; the depth camera looks at the target give or take
    ~3 cm and is rolled by up to ~2° (a hand-levelled tripod). Every device gets its own
    :func:`random_calibration` and a distinct serial.

    Returns:
        list of ``(calibration, world_from_depth)``, the latter (4, 4) float64.
    """
    if n < 1:
        raise ValueError(f"need at least one camera, got n={n}")
    target_v = np.asarray(target, dtype=np.float64)
    start = rng.uniform(0, 2 * np.pi)
    spacing = 2 * np.pi / n
    jitter = min(np.deg2rad(15.0), 0.3 * spacing)
    serials: set[str] = set()
    out = []
    for i in range(n):
        az = start + i * spacing + rng.uniform(-jitter, jitter)
        r, h = rng.uniform(*radius), rng.uniform(*height)
        eye = np.array([target_v[0] + r * np.sin(az), h, target_v[2] + r * np.cos(az)])
        pose = look_at(eye, target_v + rng.normal(0, 0.03, 3))
        roll = Rotation.from_rotvec([0.0, 0.0, np.deg2rad(rng.uniform(-2, 2))]).as_matrix()
        pose[:3, :3] = pose[:3, :3] @ roll
        while True:
            calib = random_calibration(rng)
            if calib.serial not in serials:
                break
        serials.add(calib.serial)
        out.append((calib, pose))
    return out


@functools.lru_cache(maxsize=32)
def _grid_cached(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                 dist: tuple[float, ...]) -> tuple[np.ndarray, ...]:
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    xy = cv2.undistortPoints(pix, k, np.asarray(dist), None, None, None, UNDISTORT_CRITERIA)
    xy = xy.reshape(height, width, 2)
    xy1 = np.concatenate([xy, np.ones((height, width, 1))], axis=-1).astype(np.float32)
    inv_norm = (1.0 / np.linalg.norm(xy1, axis=-1)).astype(np.float32)
    r2 = (xy[..., 0] ** 2 + xy[..., 1] ** 2).astype(np.float32)
    for a in (xy, xy1, inv_norm, r2):
        a.setflags(write=False)
    return xy, xy1, inv_norm, r2


def undistorted_grid(intr: CameraIntrinsics) -> np.ndarray:
    """(H, W, 2) float64 normalised coordinates ``(x, y)`` (on the z = 1 plane of the camera)
    of every pixel centre, i.e. the ray ``(x, y, 1)`` each pixel sees through the lens.

    ``cv2.undistortPoints`` with its iteration run to convergence (reprojection error < 1e-6 px;
    the default 5 iterations leave ~3 px in a Kinect depth image's corners). Cached per
    intrinsics (~0.2 s depth, ~0.5 s colour on first use); read-only.
    """
    return _grid(intr)[0]


def _grid(intr: CameraIntrinsics) -> tuple[np.ndarray, ...]:
    """Cached per intrinsics: xy (H,W,2) float64, (x,y,1) (H,W,3) float32, 1/|(x,y,1)| (H,W)
    float32 and x²+y² (H,W) float32."""
    return _grid_cached(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy,
                        tuple(float(d) for d in intr.dist))


def _cast(scene: SimScene, origin: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
    """Cast rays from one ``origin`` (3,) along ``dirs`` (..., 3) (world); numpy results with
    ``t`` in units of each direction's length (inf = miss)."""
    shape = dirs.shape[:-1]
    rays = np.empty((*shape, 6), dtype=np.float32)
    rays[..., :3] = origin
    rays[..., 3:] = dirs
    hit = scene.raycaster.cast_rays(o3d.core.Tensor.from_numpy(rays.reshape(-1, 6)))
    return {
        "t": hit["t_hit"].numpy().reshape(shape),
        "gid": hit["geometry_ids"].numpy().reshape(shape),
        "pid": hit["primitive_ids"].numpy().reshape(shape),
        "uv": hit["primitive_uvs"].numpy().reshape(*shape, 2),
        "normal": hit["primitive_normals"].numpy().reshape(*shape, 3),
    }


def _camera_rays(intr: CameraIntrinsics, world_from_camera: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Origin (3,), float32 world directions (H, W, 3) whose camera-frame z is 1, and the
    (H, W, 2) float64 normalised grid."""
    xy, xy1, _, _ = _grid(intr)
    dirs = xy1 @ world_from_camera[:3, :3].T.astype(np.float32)
    return world_from_camera[:3, 3].copy(), dirs, xy


# --------------------------------------------------------------------------------------------
# Depth
# --------------------------------------------------------------------------------------------

@dataclass
class DepthNoise:
    """Time-of-flight depth artefacts (Azure Kinect NFOV unbinned). Lengths in metres.

    Axial noise: Gaussian with ``σ(z) = (sigma_a + sigma_b·z²) / cos(θ)^incidence_exponent``
    (z the Z-depth, θ the incidence angle): 1.5 / 2.1 / 3.0 mm at 1 / 2 / 3 m head-on, well inside
    the public spec (random error std <= 17 mm); weaker IR return at oblique incidence adds noise.

    Systematic error: per device (seeded by its serial, so identical every frame; see
    :func:`device_depth_bias`): ``offset + scale·z + radial·r²`` (r² = x² + y² of the pixel's
    normalised ray, up to ~2 in the corners), each drawn from N(0, std) and clipped at ±2.5 std:
    at most ~5 mm + 0.1 % of distance + 2.5 mm at the corners (spec: < 11 mm + 0.1 %).

    Lateral jitter: each pixel samples the surface at a sub-pixel offset N(0, lateral_px) (linear
    interpolation on smooth surfaces, nearest across depth edges): jagged silhouettes.

    Flying pixels: a pixel with a 4-neighbour more than ``edge_jump`` nearer/farther becomes, with
    probability ``flying_prob``, a mix ``w·z + (1−w)·z_neighbour`` with w ~ U(0, 1).

    Invalid (0): nothing hit; incidence beyond ``max_incidence_deg``; measured Z outside
    ``depth_range`` (default: the depth mode's operating range, ``DEPTH_RANGE_M``); a random
    ``dropout`` fraction; and, with ``fov_cut`` > 0, the corners the NFOV
    illuminator leaves dark: ``|u−W/2|/(W/2) + |v−H/2|/(H/2) > fov_cut`` (an octagon).
    """

    sigma_a: float = 0.00135
    sigma_b: float = 0.00018
    incidence_exponent: float = 0.5
    offset_std: float = 0.002
    scale_std: float = 0.0004
    radial_std: float = 0.0005
    lateral_px: float = 0.25
    flying_prob: float = 0.3
    edge_jump: float = 0.04
    max_incidence_deg: float = 80.0
    depth_range: tuple[float, float] | None = None  # None: the depth mode's (DEPTH_RANGE_M)
    dropout: float = 0.002
    fov_cut: float = 1.6

    @classmethod
    def none(cls) -> DepthNoise:
        """No noise, bias, jitter, flying pixels, dropout or FOV cut: the exact Z-depth rounded to
        millimetres. The device's validity rules (range, grazing angle) still apply."""
        return cls(sigma_a=0.0, sigma_b=0.0, offset_std=0.0, scale_std=0.0, radial_std=0.0,
                   lateral_px=0.0, flying_prob=0.0, dropout=0.0, fov_cut=0.0)

    def sigma(self, z: np.ndarray | float) -> np.ndarray:
        """Head-on axial noise std (m) at Z-depth ``z`` (m)."""
        return self.sigma_a + self.sigma_b * np.square(z)


def device_depth_bias(calib: KinectCalibration, noise: DepthNoise) -> tuple[float, float, float]:
    """The device's systematic depth error ``(offset m, scale, radial m)``: the measured depth is
    ``z·(1 + scale) + offset + radial·r²``. Deterministic in the serial number."""
    rng = np.random.default_rng(zlib.crc32(calib.serial.encode()))
    draws = np.clip(rng.standard_normal(3), -2.5, 2.5)
    return (float(draws[0] * noise.offset_std), float(draws[1] * noise.scale_std),
            float(draws[2] * noise.radial_std))


@dataclass(eq=False)
class DepthFrame:
    """One depth image of one device.

    Attributes:
        depth_mm: (H, W) uint16 millimetres of Z-depth in the depth-camera frame, 0 = invalid:
            what the device records.
        depth_true: (H, W) float32 metres, the exact Z-depth of the surface each pixel centre's
            ray hits (NaN: no surface), before any noise or invalidation.
        label: (H, W) int8 ``label`` of the mesh hit by the exact ray (-1: none).
        flying: (H, W) bool, pixels replaced by flying (mixed) depths.
        ir: (H, W) uint16 active-IR intensity in the same pixels (:func:`render_depth` with
            ``ir``), None without.
    """

    depth_mm: np.ndarray
    depth_true: np.ndarray
    label: np.ndarray
    flying: np.ndarray
    ir: np.ndarray | None = None


#: IR counts of a white surface (albedo 1) facing the camera 1 m away: the simulator's
#: surfaces 2-3 m away then read tens to a few hundred counts. The albedos are the colour
#: albedos (their RGB mean), a stand-in for the surfaces' 850 nm reflectance.
IR_GAIN = 3000.0


def _active_ir(scene: SimScene, hit: dict[str, np.ndarray], origin: np.ndarray,
               dirs: np.ndarray, intr: CameraIntrinsics, rot: np.ndarray, cos: np.ndarray,
               fov_cut: float) -> np.ndarray:
    """(H, W) float32 noise-free active-IR intensity: the camera's own illuminator, so
    ``IR_GAIN · albedo · cos(incidence) / range²`` (range along the ray, metres), dark outside
    the NFOV illuminator's octagon (``fov_cut``, see :class:`DepthNoise`) and where nothing was
    hit, from the pixel centres' exact rays (the depth's lateral jitter is not applied).
    ``cos`` (H, W) |cos| of the incidence angle."""
    h, w = dirs.shape[:2]
    grid = _grid(intr)
    surf = _surface(scene, hit, origin, dirs, grid[0], rot)
    inv_len = grid[2].reshape(-1)[surf.idx]  # 1/|ray| of a ray whose camera z is 1
    rng_m = hit["t"].reshape(-1)[surf.idx] / inv_len
    out = np.zeros(h * w, np.float32)
    out[surf.idx] = (np.float32(IR_GAIN) * surf.albedo.mean(axis=1) * cos.reshape(-1)[surf.idx]
                     / np.square(rng_m))
    out = out.reshape(h, w)
    if fov_cut > 0:
        out[~_illuminated(h, w, fov_cut)] = 0.0
    return out


def _illuminated(h: int, w: int, fov_cut: float) -> np.ndarray:
    """(H, W) bool: inside the NFOV illuminator's octagon,
    ``|u−W/2|/(W/2) + |v−H/2|/(H/2) <= fov_cut`` (see :class:`DepthNoise`)."""
    u = np.abs(np.arange(w) - (w - 1) / 2) / (w / 2)
    v = np.abs(np.arange(h) - (h - 1) / 2) / (h / 2)
    return (u[None] + v[:, None]) <= fov_cut


def render_depth(scene: SimScene, calib: KinectCalibration, world_from_depth: np.ndarray,
                 noise: DepthNoise | None = None, rng: np.random.Generator | None = None,
                 *, ir: bool = False) -> DepthFrame:
    """Render one device's depth image (see :class:`DepthNoise` for the artefacts).

    Args:
        scene: the frame's :func:`build_scene`.
        calib: the device (``calib.depth`` intrinsics are used).
        world_from_depth: (4, 4) pose of the depth camera, metres.
        noise: artefacts; None = ``DepthNoise()`` defaults.
        rng: randomness for this frame (noise, jitter, dropout, flying pixels).
        ir: also render the active-IR image (:attr:`DepthFrame.ir`, see :func:`_active_ir`),
            with shot noise (std = √counts) unless ``noise`` has no axial noise. Its noise comes
            from its own generator, seeded by the depth image's bytes, so that ``rng`` draws
            what it draws without IR and every other image of a session stays as it was.
    """
    noise = DepthNoise() if noise is None else noise
    rng = np.random.default_rng() if rng is None else rng
    intr = calib.depth
    h, w = intr.height, intr.width
    origin, dirs, _ = _camera_rays(intr, np.asarray(world_from_depth, dtype=np.float64))
    hit = _cast(scene, origin, dirs)
    t = hit["t"]
    found = np.isfinite(t)
    label = np.full((h, w), LABEL_NONE, np.int8)
    label[found] = scene.mesh_label[hit["gid"][found]]
    # |cos| of the incidence angle: face winding is not trusted.
    cos_m = np.abs(np.einsum("hwk,hwk->hw", hit["normal"], dirs)) * _grid(intr)[2]
    z_true = np.where(found, t, np.float32(np.nan))
    z = np.where(found, t, np.float32(0.0))
    cos_m[~found] = 0.0
    ir_clean = (_active_ir(scene, hit, origin, dirs, intr,
                           np.asarray(world_from_depth, np.float64)[:3, :3], cos_m,
                           noise.fov_cut) if ir else None)

    if noise.lateral_px > 0:
        mu = np.arange(w, dtype=np.float32)[None] + np.float32(noise.lateral_px) * (
            rng.standard_normal((h, w), dtype=np.float32))
        mv = np.arange(h, dtype=np.float32)[:, None] + np.float32(noise.lateral_px) * (
            rng.standard_normal((h, w), dtype=np.float32))
        iu = np.clip(np.rint(mu), 0, w - 1).astype(np.intp)
        iv = np.clip(np.rint(mv), 0, h - 1).astype(np.intp)
        z_lin = cv2.remap(z, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        # Interpolating across an edge would invent surfaces; there the pixel lands on one side.
        kernel = np.ones((3, 3), np.uint8)
        smooth = (cv2.dilate(z, kernel) - cv2.erode(z, kernel) < noise.edge_jump) & (z > 0)
        z = np.where(smooth, z_lin, z[iv, iu])
        cos_m = cos_m[iv, iu]

    flying = np.zeros((h, w), dtype=bool)
    if noise.flying_prob > 0:
        # The 4-neighbour with the largest depth jump (both surfaces hit) is the one mixed in.
        p = np.pad(z, 1)
        biggest = np.zeros((h, w), np.float32)
        other = np.zeros((h, w), np.float32)
        for nb in (p[1:-1, :-2], p[1:-1, 2:], p[:-2, 1:-1], p[2:, 1:-1]):
            jump = np.where(nb > 0, np.abs(nb - z), 0.0)
            larger = jump > biggest
            biggest = np.where(larger, jump, biggest)
            other = np.where(larger, nb, other)
        flying = (biggest > noise.edge_jump) & (z > 0)
        flying &= rng.random((h, w), dtype=np.float32) < noise.flying_prob
        mix = rng.random((h, w), dtype=np.float32)
        z = np.where(flying, mix * z + (1 - mix) * other, z)

    offset, scale, radial = device_depth_bias(calib, noise)
    z_meas = z * np.float32(1 + scale) + np.float32(offset)
    if radial != 0:
        z_meas += np.float32(radial) * _grid(intr)[3]
    cos_lim = np.float32(np.cos(np.deg2rad(noise.max_incidence_deg)))
    if noise.sigma_a > 0 or noise.sigma_b > 0:
        sigma = noise.sigma(z).astype(np.float32)
        if noise.incidence_exponent:
            sigma /= np.maximum(cos_m, max(cos_lim, 1e-3)) ** np.float32(
                noise.incidence_exponent)
        z_meas += sigma * rng.standard_normal((h, w), dtype=np.float32)

    valid = (z > 0) & (cos_m >= cos_lim)
    lo, hi = (noise.depth_range if noise.depth_range is not None
              else DEPTH_RANGE_M[calib.depth_mode])
    valid &= (z_meas >= lo) & (z_meas <= hi)
    if noise.dropout > 0:
        valid &= rng.random((h, w), dtype=np.float32) >= noise.dropout
    if noise.fov_cut > 0:
        valid &= _illuminated(h, w, noise.fov_cut)
    depth_mm = np.where(valid, np.clip(np.rint(z_meas * 1000.0), 0, 65535), 0).astype(np.uint16)
    ir_counts = None
    if ir_clean is not None:
        if noise.sigma_a > 0 or noise.sigma_b > 0:
            shot = np.random.default_rng(zlib.crc32(depth_mm)).standard_normal(
                (h, w), dtype=np.float32)
            ir_clean += np.sqrt(ir_clean) * shot
        ir_counts = np.clip(np.rint(ir_clean), 0, 65535).astype(np.uint16)
    return DepthFrame(depth_mm=depth_mm, depth_true=z_true, label=label,
                      flying=flying & valid, ir=ir_counts)


# --------------------------------------------------------------------------------------------
# Colour
# --------------------------------------------------------------------------------------------

@dataclass
class Light:
    """Scene lighting for the colour cameras.

    Attributes:
        direction: (3,) world direction *towards* the light (a distant key light), normalised on
            use.
        diffuse: key light strength (Lambertian).
        ambient: uniform fill light strength.
        color: RGB tint of the light.
        shadows: cast shadows of the key light (one extra ray per lit pixel).
    """

    direction: tuple[float, float, float] = (0.35, 1.0, 0.45)
    diffuse: float = 0.75
    ambient: float = 0.35
    color: tuple[float, float, float] = (1.0, 0.97, 0.93)
    shadows: bool = True

    @classmethod
    def random(cls, rng: np.random.Generator) -> Light:
        """A ceiling-ish key light from a random azimuth, elevation 45-80°, warm to neutral."""
        az, el = rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(45, 80))
        warm = rng.uniform(0.0, 0.1)
        return cls(direction=(np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)),
                   diffuse=rng.uniform(0.6, 0.85), ambient=rng.uniform(0.25, 0.45),
                   color=(1.0, 1.0 - 0.3 * warm, 1.0 - warm))


@dataclass
class ColorNoise:
    """Colour-camera imperfections (values on a 0-1 intensity scale).

    Attributes:
        blur_px: Gaussian optical blur sigma, pixels.
        vignetting: relative brightness loss in the image corners.
        white_balance_std: per-device per-channel gain spread (seeded by serial).
        exposure_std: per-frame global gain spread (auto exposure).
        read_std: signal-independent noise std.
        shot: signal-dependent noise, ``std = sqrt(read_std² + shot·I)``.
    """

    blur_px: float = 0.6
    vignetting: float = 0.2
    white_balance_std: float = 0.03
    exposure_std: float = 0.02
    read_std: float = 0.006
    shot: float = 0.0004

    @classmethod
    def none(cls) -> ColorNoise:
        """A perfect sensor (still JPEG-compressed in :attr:`ColorFrame.jpeg`)."""
        return cls(blur_px=0.0, vignetting=0.0, white_balance_std=0.0, exposure_std=0.0,
                   read_std=0.0, shot=0.0)


@dataclass(eq=False)
class ColorFrame:
    """One colour image of one device (colour-camera pixels, 1280x720 for 720P).

    Attributes:
        rgb: (H, W, 3) uint8 RGB sensor image before compression.
        jpeg: the same image as JPEG bytes (what an MJPG recording stores; decoding gives the
            lossy version).
        person_mask, chair_mask: (H, W) bool ground truth (label 1 / 2 under the pixel centre).
        label: (H, W) int8 mesh label under each pixel centre (-1: none).
        depth_true: (H, W) float32 exact Z-depth in the colour-camera frame, metres (NaN: none).
    """

    rgb: np.ndarray
    jpeg: bytes
    person_mask: np.ndarray
    chair_mask: np.ndarray
    label: np.ndarray
    depth_true: np.ndarray


_BACKGROUND_RGB = np.array([0.22, 0.22, 0.24], dtype=np.float32)
# Sub-pixel sample offsets for image textures (4x4 stratified): board edges then look like a
# real camera's area-integrated pixels, which OpenCV's sub-pixel corner refinement relies on.
_SUBSAMPLES = np.stack(np.meshgrid((np.arange(4) + 0.5) / 4 - 0.5,
                                   (np.arange(4) + 0.5) / 4 - 0.5), -1).reshape(-1, 2)


def _hash01(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) for integer pairs (e.g. floor planks)."""
    n = (ix.astype(np.int64) * 73856093) ^ (iy.astype(np.int64) * 19349663) ^ (seed * 83492791)
    n = (n ^ (n >> 13)) * 1274126177
    return ((n ^ (n >> 16)) & 0xFFFF).astype(np.float32) / 65535.0


@functools.cache
def _noise_volume() -> np.ndarray:
    """(64, 64, 64) float32 smooth periodic noise, zero mean, unit std (a fixed pattern: the
    same seed every run, so textures never depend on hidden state)."""
    raw = np.random.default_rng(20220801).random((64, 64, 64)).astype(np.float32)
    vol = ndimage.gaussian_filter(raw, 1.2, mode="wrap")
    return ((vol - vol.mean()) / vol.std()).astype(np.float32)


def _noise(q: np.ndarray) -> np.ndarray:
    """Smooth noise (≈ N(0, 1), features ~3 units across) at (N, 3) points, trilinear."""
    return ndimage.map_coordinates(_noise_volume(), q.T.astype(np.float32), order=1,
                                   mode="grid-wrap")


def _texture_gain(kind: int, q: np.ndarray) -> np.ndarray:
    """(N,) brightness multiplier of procedural texture ``TEXTURES[kind]`` at (N, 3) points (m).

    Feature sizes are centimetres, coarse enough not to alias at 720p from 1-4 m."""
    name = TEXTURES[kind]
    if name == "wood":
        # Growth rings about the texture frame's Y axis, warped; plus a little blotchiness.
        warp = 0.35 * _noise(q * np.array([6.0, 1.5, 6.0]))
        rings = 0.5 + 0.5 * np.sin(2 * np.pi * (25.0 * np.hypot(q[:, 0], q[:, 2]) + warp))
        return (0.8 + 0.2 * rings + 0.04 * _noise(q * 10.0)).astype(np.float32)
    if name == "fabric":
        return (0.9 + 0.08 * _noise(q * 40.0) + 0.06 * _noise(q * 4.0)).astype(np.float32)
    if name == "floor":
        # Planks 18 cm x 1.2 m along X with staggered joints, one tone each, grain, dark seams.
        row = np.floor(q[:, 2] / 0.18)
        x = q[:, 0] + 0.4 * row
        col = np.floor(x / 1.2)
        tone = 0.82 + 0.3 * _hash01(row, col, 31)
        grain = 1.0 + 0.06 * _noise(np.stack([x * 3.0, q[:, 1] * 3.0, q[:, 2] * 60.0], 1))
        fz, fx = q[:, 2] - 0.18 * row, x - 1.2 * col
        seam = (np.minimum(fz, 0.18 - fz) < 0.002) | (np.minimum(fx, 1.2 - fx) < 0.002)
        return np.where(seam, 0.45, tone * grain).astype(np.float32)
    return np.ones(len(q), np.float32)


def _planar_texture(pt: PlanarTexture, origin: np.ndarray, rot: np.ndarray, xy: np.ndarray,
                    dxy_du: np.ndarray, dxy_dv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area-sampled texture colour (N, 3) of N pixels whose exact rays hit a textured mesh, and a
    (N,) mask of those that hit the textured plane (the rest keep the mesh colour).

    Each pixel is sampled at 4x4 sub-pixel rays (its normalised coordinates ``xy`` (N, 2) moved
    along the local derivatives ``dxy_du``/``dxy_dv``), intersected with the plane analytically."""
    plane = pt.world_from_plane
    normal, p0 = plane[:3, 2], plane[:3, 3]
    xs = (xy[:, None, :] + _SUBSAMPLES[None, :, 0:1] * dxy_du[:, None, :]
          + _SUBSAMPLES[None, :, 1:2] * dxy_dv[:, None, :])                       # (N, S, 2)
    d = xs[..., 0:1] * rot[:, 0] + xs[..., 1:2] * rot[:, 1] + rot[:, 2]          # (N, S, 3)
    denom = d @ normal
    t = ((p0 - origin) @ normal) / np.where(np.abs(denom) < 1e-12, 1e-12, denom)
    local = (origin + t[..., None] * d - p0) @ plane[:3, :3]                      # (N, S, 3)
    tu = ((local[..., 0] - pt.origin[0]) * pt.px_per_m - 0.5).astype(np.float32)
    tv = ((local[..., 1] - pt.origin[1]) * pt.px_per_m - 0.5).astype(np.float32)
    n, s = tu.shape
    # cv2.remap wants 2D maps well below 32k on a side: lay the samples out in rows of 1024.
    total = n * s
    cols = 1024
    rows = max(1, -(-total // cols))
    mu = np.full(rows * cols, -1.0, np.float32)
    mv = np.full(rows * cols, -1.0, np.float32)
    mu[:total], mv[:total] = tu.reshape(-1), tv.reshape(-1)
    sampled = cv2.remap(pt.image, mu.reshape(rows, cols), mv.reshape(rows, cols),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    color = sampled.reshape(-1, 3)[:total].reshape(n, s, 3).mean(axis=1)
    # The central ray decides whether the pixel is on the printed face at all.
    centre = local.mean(axis=1)
    hgt, wid = pt.image.shape[:2]
    cu = (centre[:, 0] - pt.origin[0]) * pt.px_per_m
    cv_ = (centre[:, 1] - pt.origin[1]) * pt.px_per_m
    on = ((np.abs(centre[:, 2]) < pt.tolerance) & (cu >= 0) & (cu <= wid) & (cv_ >= 0)
          & (cv_ <= hgt))
    return color, on


def _device_gains(serial: str, std: float) -> np.ndarray:
    rng = np.random.default_rng(zlib.crc32(serial.encode()) ^ 0x5EED)
    return (1.0 + std * np.clip(rng.standard_normal(3), -2.5, 2.5)).astype(np.float32)


def _shadow_visibility(scene: SimScene, origin: np.ndarray, t: np.ndarray, idx: np.ndarray,
                       gid: np.ndarray, dirs: np.ndarray, geo: np.ndarray, to_light: np.ndarray,
                       lit: np.ndarray, width: int) -> np.ndarray:
    """(N,) float32 1/0: whether each hit pixel sees the key light (cast shadows).

    Shadow rays are cast for every second pixel in both directions; a pixel takes the answer of
    the sample at the top-left of its 2x2 cell when that sample is lit and on the same mesh, and
    casts its own ray otherwise (silhouettes stay exact; shadow edges are ~2 px steps, well under
    the penumbra of a real lamp). ``idx`` (N,) flat pixel indices of the hits, ``t`` (H·W,) hit
    distances, ``dirs``/``geo`` (N, 3) ray directions and camera-facing face normals, ``lit``
    (N,) pixels facing the light."""
    vis = np.ones(len(idx), np.float32)
    lit &= geo @ to_light > 0
    vis[~lit] = 0.0
    u, v = idx % width, idx // width
    coarse = lit & (u % 2 == 0) & (v % 2 == 0)

    def occluded(sel: np.ndarray) -> np.ndarray:
        rays = np.empty((len(sel), 6), np.float32)
        # Start just off the surface so a ray does not re-hit its own triangle.
        rays[:, :3] = (origin.astype(np.float32) + t[idx[sel], None] * dirs[sel]
                       + np.float32(2e-3) * geo[sel])
        rays[:, 3:] = to_light
        return scene.raycaster.test_occlusions(o3d.core.Tensor.from_numpy(rays)).numpy()

    first = np.flatnonzero(coarse)
    vis[first[occluded(first)]] = 0.0
    # Where is each pixel's representative sample among the hits (-1: not a hit)?
    slot = np.full(int(idx.max()) + 1 if len(idx) else 0, -1, np.int64)
    slot[idx] = np.arange(len(idx))
    rep = slot[np.minimum((v - v % 2) * width + (u - u % 2), len(slot) - 1)]
    ok = (rep >= 0) & lit
    ok[ok] &= coarse[rep[ok]] & (gid[rep[ok]] == gid[ok])
    rest = np.flatnonzero(lit & ~coarse & ~ok)
    vis[rest[occluded(rest)]] = 0.0
    shared = np.flatnonzero(lit & ~coarse & ok)
    vis[shared] = vis[rep[shared]]
    return vis


def _color_draws(intr: CameraIntrinsics, noise: ColorNoise, rng: np.random.Generator,
                 ) -> tuple[float, np.ndarray | None]:
    """Every random number one colour frame uses, in the order :func:`render_color` has always
    drawn them: the exposure draw (a standard normal) and, when the sensor is noisy, the
    (H, W, 3) float32 standard-normal sensor-noise field (None otherwise).

    They depend on the image size and ``noise`` only, never on the scene, so that
    :func:`skip_color` can consume exactly the same draws without rendering.
    """
    exposure = float(rng.standard_normal())
    sensor = None
    if noise.read_std > 0 or noise.shot > 0:
        sensor = rng.standard_normal((intr.height, intr.width, 3), dtype=np.float32)
    return exposure, sensor


def skip_color(calib: KinectCalibration, rng: np.random.Generator,
               noise: ColorNoise | None = None) -> None:
    """Advance ``rng`` exactly as :func:`render_color` on this device would, without rendering.

    A depth-only recording shares its generator with the depth noise; consuming the colour
    frame's draws keeps every later depth frame identical to the one a colour recording of the
    same seed gets. The draws cost about a tenth of a colour render (~35 ms for 720P: NumPy's
    normal sampler rejects a variable number of raw draws, so the generator cannot simply be
    ``advance``-d past them).

    Args:
        calib: the device (``calib.color`` sets the noise field's size).
        rng: the generator :func:`render_color` would have been given.
        noise: as passed to :func:`render_color`; None = ``ColorNoise()`` defaults.
    """
    _color_draws(calib.color, ColorNoise() if noise is None else noise, rng)


class _Surface(NamedTuple):
    """What the hit pixels of one image see: flat indices ``idx`` (N,) of the pixels whose ray
    hit a mesh, their scene geometry ids ``gid`` and scene face indices ``face`` (N,),
    barycentric coordinates ``bary`` (N, 3), ray directions ``dirs`` (N, 3) and albedo (N, 3)
    float32 RGB in [0, 1]; ``of`` gathers the hit pixels' values from an (H, W, ...) array."""

    idx: np.ndarray
    gid: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    dirs: np.ndarray
    albedo: np.ndarray
    of: Callable[[np.ndarray], np.ndarray]


def _surface(scene: SimScene, hit: dict[str, np.ndarray], origin: np.ndarray,
             dirs: np.ndarray, xy: np.ndarray, rot: np.ndarray) -> _Surface:
    """The albedo under each pixel of a ray cast (:func:`_cast` of ``dirs`` (H, W, 3) from
    ``origin``; ``xy`` (H, W, 2) the normalised grid, ``rot`` (3, 3) world_from_camera's
    rotation): each mesh's colours times its procedural texture, or its planar image texture
    (area-sampled). The colour and the IR renders share it."""
    h, w = dirs.shape[:2]
    t = hit["t"].reshape(-1)
    idx = np.flatnonzero(np.isfinite(t))
    everything = len(idx) == h * w   # a closed room: skip the gathers

    def hits(a: np.ndarray) -> np.ndarray:
        """(N, ...) values of the hit pixels from a per-pixel (H, W, ...) array."""
        flat = a.reshape(h * w, *a.shape[2:])
        return flat if everything else flat[idx]

    gid = hits(hit["gid"])
    face = scene.face_offset[gid] + hits(hit["pid"])
    uv = hits(hit["uv"])
    bary = np.empty((len(idx), 3), np.float32)
    bary[:, 1:] = uv
    bary[:, 0] = 1 - uv[:, 0] - uv[:, 1]

    albedo = scene.face_colors[face]
    interp = np.flatnonzero(scene.face_interp[face])
    if len(interp):
        corners = scene.vertex_colors[scene.faces[face[interp]]]                # (n, 3, 3)
        albedo[interp] = np.matmul(bary[interp, None, :], corners)[:, 0]
    flat_dirs = hits(dirs)
    kinds = scene.face_texture[face]
    textured = np.flatnonzero(kinds)
    if len(textured):
        # Texture-space positions: the hit point itself for world-textured meshes (cheaper than
        # interpolating), else the interpolated texture_coords.
        q = np.empty((len(textured), 3), np.float32)
        own = scene.face_own_coords[face[textured]]
        sel = textured[~own]
        q[~own] = origin.astype(np.float32) + t[idx[sel], None] * flat_dirs[sel]
        sel = textured[own]
        q[own] = np.matmul(bary[sel, None, :], scene.tex_coords[scene.faces[face[sel]]])[:, 0]
        gain = np.empty(len(textured), np.float32)
        tkind = kinds[textured]
        for kind in np.unique(tkind):
            m = tkind == kind
            gain[m] = _texture_gain(int(kind), q[m])
        albedo[textured] *= gain[:, None]
    for g, mesh in enumerate(scene.meshes):
        if mesh.planar_texture is None:
            continue
        sel = np.flatnonzero(gid == g)
        if not len(sel):
            continue
        pu, pv = idx[sel] % w, idx[sel] // w
        u0, u1 = np.maximum(pu - 1, 0), np.minimum(pu + 1, w - 1)
        v0, v1 = np.maximum(pv - 1, 0), np.minimum(pv + 1, h - 1)
        dxy_du = (xy[pv, u1] - xy[pv, u0]) / (u1 - u0)[:, None]
        dxy_dv = (xy[v1, pu] - xy[v0, pu]) / (v1 - v0)[:, None]
        color, on = _planar_texture(mesh.planar_texture, origin, rot, xy[pv, pu],
                                    dxy_du, dxy_dv)
        albedo[sel[on]] = color[on]
    return _Surface(idx, gid, face, bary, flat_dirs, albedo, hits)


def render_color(scene: SimScene, calib: KinectCalibration, world_from_depth: np.ndarray,
                 light: Light | None = None, rng: np.random.Generator | None = None,
                 jpeg_quality: int = 90, *, noise: ColorNoise | None = None) -> ColorFrame:
    """Render one device's colour image (720P: 1280x720) and its ground-truth masks.

    The colour camera sits at ``world_from_depth @ inv(calib.color_from_depth)`` and sees through
    ``calib.color``'s distortion. Albedo comes from each mesh's colours times its procedural
    texture, or its planar image texture (area-sampled); shading is ambient + Lambertian key light
    with optional cast shadows; then blur, vignetting, per-device white balance, per-frame
    exposure, sensor noise (:class:`ColorNoise`) and JPEG at ``jpeg_quality``.

    Args:
        scene: the frame's :func:`build_scene`.
        calib: the device (``calib.color`` intrinsics, ``calib.color_from_depth``).
        world_from_depth: (4, 4) pose of the device's depth camera, metres.
        light: lighting; None = ``Light()``.
        rng: randomness for this frame (exposure, sensor noise).
        jpeg_quality: 0-100 for :attr:`ColorFrame.jpeg`.
        noise: sensor imperfections; None = ``ColorNoise()`` defaults.
    """
    light = Light() if light is None else light
    noise = ColorNoise() if noise is None else noise
    rng = np.random.default_rng() if rng is None else rng
    intr = calib.color
    h, w = intr.height, intr.width
    pose = world_from_color(calib, world_from_depth)
    origin, dirs, xy = _camera_rays(intr, pose)
    hit = _cast(scene, origin, dirs)
    t = hit["t"].reshape(-1)
    surf = _surface(scene, hit, origin, dirs, xy, pose[:3, :3])
    idx, gid, face, bary, flat_dirs, albedo = (surf.idx, surf.gid, surf.face, surf.bary,
                                               surf.dirs, surf.albedo)
    hits = surf.of

    geo = hits(hit["normal"])
    # Face the camera: winding is not trusted, and only the front of a surface is ever seen.
    geo *= -np.sign(np.einsum("nk,nk->n", geo, flat_dirs) + np.float32(1e-12))[:, None]
    normal = geo
    smooth = np.flatnonzero(scene.face_smooth[face])
    if len(smooth):
        normal = geo.copy()
        vn = scene.vertex_normals[scene.faces[face[smooth]]]                       # (n, 3, 3)
        ns = np.matmul(bary[smooth, None, :], vn)[:, 0]
        ns *= np.sign(np.einsum("nk,nk->n", ns, geo[smooth]))[:, None]
        normal[smooth] = ns / np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), 1e-9)
    to_light = np.asarray(light.direction, dtype=np.float64)
    to_light = (to_light / np.linalg.norm(to_light)).astype(np.float32)
    lambert = np.clip(normal @ to_light, 0.0, None)
    if light.shadows:
        lambert *= _shadow_visibility(scene, origin, t, idx, gid, flat_dirs, geo, to_light,
                                      lambert > 0, w)
    shade = np.float32(light.ambient) + np.float32(light.diffuse) * lambert
    img = np.empty((h * w, 3), np.float32)
    img[:] = _BACKGROUND_RGB
    albedo *= shade[:, None]
    albedo *= np.asarray(light.color, dtype=np.float32)
    img[idx] = albedo
    img = img.reshape(h, w, 3)

    if noise.blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), noise.blur_px)
    exposure, sensor = _color_draws(intr, noise, rng)
    gain = _device_gains(calib.serial, noise.white_balance_std)
    gain *= np.float32(1.0 + noise.exposure_std * exposure)
    if noise.vignetting > 0:
        r2 = _grid(intr)[3]
        img *= (1.0 - np.float32(noise.vignetting / r2.max()) * r2)[..., None]
    img *= gain
    if sensor is not None:
        std = np.sqrt(np.float32(noise.read_std**2) + np.float32(noise.shot)
                      * np.maximum(img, 0.0))
        img += std * sensor
    rgb = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:  # pragma: no cover - OpenCV's JPEG encoder does not fail on uint8 images
        raise RuntimeError("JPEG encoding failed")
    label = np.full(h * w, LABEL_NONE, np.int8)
    label[idx] = scene.mesh_label[gid]
    label = label.reshape(h, w)
    depth = np.full(h * w, np.nan, np.float32)
    depth[idx] = t[idx]
    return ColorFrame(rgb=rgb, jpeg=buf.tobytes(), person_mask=label == LABEL_PERSON,
                      chair_mask=label == LABEL_CHAIR, label=label, depth_true=depth.reshape(h, w))
