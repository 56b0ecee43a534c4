"""ChArUco calibration boards: the physical board, its printable image, and detection + pose.

Used by the simulator (to texture a board into synthetic views) and by the capture stage's camera
calibration, so both agree on one board and one board frame. OpenCV 5's object API only
(``cv2.aruco.CharucoBoard``, ``CharucoDetector.detectBoard``, ``board.matchImagePoints``,
``cv2.solvePnP``); the 4.x free functions are gone.

Board frame (OpenCV's ChArUco object frame), metres:
  * origin at the outer corner of the top-left chessboard square (the pattern's corner; the white
    margin of the physical board lies outside it, at negative coordinates);
  * +X along a row of squares (``squares_x`` of them), +Y down a column (``squares_y``), as the
    printed image is read (image u to the right, v down);
  * +Z = X × Y points *into* the board, away from a viewer who sees the printed side: the printed
    face is the plane z = 0 and faces −Z.
The inner chessboard corners (the ChArUco corners) are at ``((i + 1)·s, (j + 1)·s, 0)``, id
``j·(squares_x − 1) + i``, for ``i < squares_x − 1``, ``j < squares_y − 1`` (``s`` = square length).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

__all__ = [
    "BoardDetection",
    "BoardSpec",
    "board_corners_3d",
    "board_image",
    "camera_from_board",
    "detect_board",
    "make_board",
    "refine_saddle_points",
]


@dataclass(frozen=True)
class BoardSpec:
    """A printed ChArUco board.

    Attributes:
        squares_x: squares along +X (columns).
        squares_y: squares along +Y (rows).
        square_length: chessboard square side, metres.
        marker_length: ArUco marker side inside the white squares, metres (< square_length).
        dictionary: OpenCV predefined dictionary name, e.g. ``"DICT_5X5_100"``.
        margin: white border of the physical board around the pattern, metres.

    The default (6 × 8 squares of 10 cm, 7.5 cm 5x5 markers, 2 cm margin) is a 0.64 × 0.84 m board:
    squares stay >= ~20 px wide in a Kinect's 720p colour image (and ~17 px in NFOV depth/IR) up
    to 3 m, enough for the 5x5 markers to decode.
    """

    squares_x: int = 6
    squares_y: int = 8
    square_length: float = 0.10
    marker_length: float = 0.075
    dictionary: str = "DICT_5X5_100"
    margin: float = 0.02

    def __post_init__(self) -> None:
        if self.squares_x < 2 or self.squares_y < 2:
            raise ValueError(f"a ChArUco board needs >= 2x2 squares, got "
                             f"{self.squares_x}x{self.squares_y}")
        if not 0 < self.marker_length < self.square_length:
            raise ValueError(f"need 0 < marker_length < square_length, got "
                             f"{self.marker_length} and {self.square_length}")
        if self.margin < 0:
            raise ValueError(f"margin must be >= 0, got {self.margin}")
        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}")

    @property
    def size(self) -> tuple[float, float]:
        """Physical (width, height) of the board including its margin, metres."""
        return (self.squares_x * self.square_length + 2 * self.margin,
                self.squares_y * self.square_length + 2 * self.margin)


def make_board(spec: BoardSpec) -> cv2.aruco.CharucoBoard:
    """The OpenCV board object for ``spec`` (lengths in metres, so poses come out in metres)."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    return cv2.aruco.CharucoBoard((spec.squares_x, spec.squares_y), spec.square_length,
                                  spec.marker_length, dictionary)


def board_image(spec: BoardSpec, px_per_m: float) -> np.ndarray:
    """Printable image of the whole physical board, (H, W) uint8 (0 black, 255 white).

    ``H = round(size_y·px_per_m)``, ``W = round(size_x·px_per_m)``; the square length and margin
    must be whole numbers of pixels at ``px_per_m`` so that squares land on pixel boundaries.
    Pixel ``(u, v)`` (OpenCV convention: its centre at integer coordinates) shows the board-frame
    point ``((u + 0.5)/px_per_m − margin, (v + 0.5)/px_per_m − margin, 0)``.
    """
    square_px = spec.square_length * px_per_m
    margin_px = spec.margin * px_per_m
    if abs(square_px - round(square_px)) > 1e-6 or abs(margin_px - round(margin_px)) > 1e-6:
        raise ValueError(f"px_per_m={px_per_m} gives {square_px} px squares and {margin_px} px "
                         f"margins; both must be whole pixels")
    sq, mg = round(square_px), round(margin_px)
    width, height = spec.squares_x * sq + 2 * mg, spec.squares_y * sq + 2 * mg
    return make_board(spec).generateImage((width, height), marginSize=mg, borderBits=1)


def board_corners_3d(spec: BoardSpec) -> np.ndarray:
    """(N, 3) float64 ChArUco corners in the board frame (metres, z = 0), row-major by id."""
    return np.asarray(make_board(spec).getChessboardCorners(), dtype=np.float64).reshape(-1, 3)


class BoardDetection(NamedTuple):
    """Result of :func:`detect_board`.

    ids: (N,) int32 ChArUco corner ids; corners: (N, 2) float64 pixel positions (OpenCV convention,
    distorted image); rvec, tvec: (3,) float64 camera-from-board pose (Rodrigues vector; metres),
    or None when fewer than ``min_corners`` corners were found or they are collinear.
    """

    ids: np.ndarray
    corners: np.ndarray
    rvec: np.ndarray | None
    tvec: np.ndarray | None


def _marker_parameters() -> cv2.aruco.DetectorParameters:
    """ArUco marker detection tuned for a board far from a 720p camera: markers down to ~1 %
    of the image perimeter (OpenCV's default, 3 %, drops a 7.5 cm marker beyond ~2 m when the
    board is turned away), 8 px cells when reading the marker bits, and a finer sweep of
    adaptive-threshold windows."""
    p = cv2.aruco.DetectorParameters()
    p.minMarkerPerimeterRate = 0.01
    p.perspectiveRemovePixelPerCell = 8
    p.perspectiveRemoveIgnoredMarginPerCell = 0.2
    p.adaptiveThreshWinSizeMin = 3
    p.adaptiveThreshWinSizeMax = 33
    p.adaptiveThreshWinSizeStep = 4
    return p


def refine_saddle_points(image_gray: np.ndarray, corners: np.ndarray, *, sigma: float = 1.0,
                         radius: int = 2, iterations: int = 3,
                         max_shift_px: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel chessboard corners as saddle points of the smoothed image (Chen & Zhang, "A new
    sub-pixel detector for X-corners in camera calibration targets", WSCG 2005).

    ``cv2.cornerSubPix`` (which ChArUco detection uses) carries ~0.05 px of systematic error even
    on ideal, area-sampled corners, and on a board seen at 2 m it shrinks the pattern by ~0.03 %:
    a millimetre-level bias in every camera's distance to the board. A weighted quadratic fitted
    to the Gaussian-smoothed intensities around each corner, whose stationary point is the
    corner, is ~10x more accurate (0.005 px on ideal corners) and unbiased in scale.

    Args:
        image_gray: (H, W) uint8 or float image.
        corners: (N, 2) float pixel positions to refine (OpenCV convention: pixel centres at
            integers), e.g. from ``CharucoDetector.detectBoard``.
        sigma: Gaussian smoothing (pixels) that turns the corner into a smooth saddle.
        radius: half-size (pixels) of the (2r+1)² fitting window; small, so that the markers
            inside the white squares stay out of it.
        iterations: re-centre the window on the estimate this many times.
        max_shift_px: a corner moving farther than this from its input is kept as given.

    Returns:
        refined (N, 2) float64, and (N,) bool of the corners that were refined (the others,
        near the image border, not saddle-shaped, or moving too far, are returned unchanged).
    """
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    img = np.asarray(image_gray)
    if img.ndim != 2:
        raise ValueError(f"refine_saddle_points expects an (H, W) image, got {img.shape}")
    if len(pts) == 0:
        return pts.copy(), np.zeros(0, bool)
    smooth = cv2.GaussianBlur(img.astype(np.float32), (0, 0), sigma)
    dy, dx = np.mgrid[-radius:radius + 1, -radius:radius + 1].reshape(2, -1)
    weight = np.exp(-(dx ** 2 + dy ** 2) / (2.0 * (0.7 * radius) ** 2))
    design = np.stack([dx * dx, dx * dy, dy * dy, dx, dy, np.ones_like(dx)], 1).astype(float)
    solve = np.linalg.pinv(design * weight[:, None])                 # (6, K): weighted LSQ
    h, w = img.shape
    est = pts.copy()
    ok = np.ones(len(pts), bool)
    for _ in range(iterations):
        # The window is centred on the current estimate (bilinear samples): a window centred on
        # the nearest pixel instead is lopsided around the corner and biases the fit ~0.1 px.
        ok &= ((est[:, 0] >= radius) & (est[:, 0] <= w - 2 - radius)
               & (est[:, 1] >= radius) & (est[:, 1] <= h - 2 - radius))
        centre = np.where(ok[:, None], est, float(radius))
        x = centre[:, 0, None] + dx[None]
        y = centre[:, 1, None] + dy[None]
        x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
        fx, fy = x - x0, y - y0
        patch = ((1 - fy) * ((1 - fx) * smooth[y0, x0] + fx * smooth[y0, x0 + 1])
                 + fy * ((1 - fx) * smooth[y0 + 1, x0] + fx * smooth[y0 + 1, x0 + 1]))
        a, b, c, d, e, _ = ((patch * weight[None]) @ solve.T).T
        # f = a x² + b xy + c y² + d x + e y + const: stationary point where ∇f = 0;
        # a saddle has a negative Hessian determinant 4ac - b².
        det = 4.0 * a * c - b * b
        ok &= det < 0
        safe = np.where(ok, det, -1.0)
        step = np.stack([(b * e - 2.0 * c * d) / safe, (b * d - 2.0 * a * e) / safe], 1)
        ok &= np.all(np.abs(step) <= 1.0, axis=1)
        est = np.where(ok[:, None], centre + step, est)
    ok &= np.linalg.norm(est - pts, axis=1) <= max_shift_px
    return np.where(ok[:, None], est, pts), ok


def detect_board(image_gray: np.ndarray, spec: BoardSpec, K: np.ndarray | None = None,
                 dist: np.ndarray | None = None, min_corners: int = 6) -> BoardDetection:
    """Detect the ChArUco corners of ``spec`` in an image and estimate the board pose.

    Args:
        image_gray: (H, W) uint8 image (a colour (H, W, 3) BGR image is converted).
        spec: the board.
        K: (3, 3) camera matrix in pixels; None detects corners only (no pose).
        dist: OpenCV distortion vector (4, 5, 8, 12 or 14 values) or None for none.
        min_corners: fewest corners for a pose.

    Returns:
        :class:`BoardDetection`; ``ids``/``corners`` are empty when nothing was found. Corners
        are OpenCV's, refined by :func:`refine_saddle_points`. The pose is
        camera-from-board (``p_cam = R(rvec)·p_board + tvec``) from ``solvePnP`` (IPPE for a planar
        target, then Levenberg-Marquardt refinement on all corners).
    """
    image = np.asarray(image_gray)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8:
        raise ValueError(f"detect_board expects a uint8 image, got {image.dtype}")
    board = make_board(spec)
    params = cv2.aruco.CharucoParameters()
    # A second pass looks for markers the first one missed where the board says they must be:
    # on oblique boards at 2-3 m this recovers about half again as many corners.
    params.tryRefineMarkers = True
    if K is not None:
        # With the camera model the detector interpolates corners through the distortion.
        params.cameraMatrix = np.asarray(K, dtype=np.float64)
        params.distCoeffs = (np.zeros(5) if dist is None
                             else np.asarray(dist, dtype=np.float64).reshape(-1))
    detector = cv2.aruco.CharucoDetector(board, params, _marker_parameters())
    corners, ids, _, _ = detector.detectBoard(image)
    if ids is None or corners is None or len(ids) == 0:
        return BoardDetection(np.zeros(0, np.int32), np.zeros((0, 2)), None, None)
    ids = ids.reshape(-1).astype(np.int32)
    corners_px, _ = refine_saddle_points(image, corners.reshape(-1, 2))
    corners = corners_px.astype(np.float32).reshape(-1, 1, 2)
    if K is None or len(ids) < min_corners or board.checkCharucoCornersCollinear(ids):
        return BoardDetection(ids, corners_px, None, None)
    obj, img = board.matchImagePoints(corners, ids)
    K = np.asarray(K, dtype=np.float64)
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, d, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return BoardDetection(ids, corners_px, None, None)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, d, rvec, tvec)
    return BoardDetection(ids, corners_px, rvec.reshape(3), tvec.reshape(3))


def camera_from_board(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(4, 4) camera-from-board transform (metres) from a Rodrigues ``rvec`` and ``tvec``."""
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))[0]
    out[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return out
