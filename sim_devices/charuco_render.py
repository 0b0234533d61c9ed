"""ChArUco board renderer: the pixels a camera would see of a printed calibration board.

`render_charuco` is a pure function (camera model + board pose in, image out), the calibration
counterpart of `sim_devices.render.render_tags`, and built the same way:

1. The board image comes from `cv2.aruco.CharucoBoard.generateImage` (so the squares and markers are
   exactly the ones OpenCV's detector expects), with a white paper margin around it, at about one
   texture pixel per image pixel so the warp neither aliases nor wastes time.
2. It is drawn into the *ideal pinhole* canvas with the exact plane-to-image homography `K [r1 r2 t]`,
   warped only inside the board's bounding box; an alpha mask warped the same way anti-aliases the
   paper's edge into the background.  Each pixel is point-sampled at its centre, or (`supersample`
   S, what the imaged camera uses) the scene is drawn on an S x S finer grid and each pixel is the
   mean of its S x S samples, as a sensor integrates over its area: point-sampling through the
   texture's and the lens's bilinear interpolation puts edges up to ~0.1 px off depending on their
   phase within a pixel, an error no real sensor makes and the corner detector reads.
3. Lens distortion is applied with the same padded canvas and `cv2.remap` tables that
   `render_tags` uses (imported from `sim_devices.render`, not copied), so a board and a tag bend
   identically for the same camera.
4. Gaussian blur: the lens's own, or with a `Defocus` (the camera's depth of field) the lens's own
   combined with the thin lens's circle of confusion at the depth of the board's centre.
5. The sensor: without any of issue 19's imaging (no defocus, gain, shot noise or light level) the
   Gaussian read noise and 8-bit truncation the renderer always had (the ideal camera renders as
   it did); with them, `sim_devices.render.sensor_readout`, the AprilTag renderer's own last step
   (the gain map of vignetting and the light across the frame, photon shot and read noise,
   rounding).

`calibration_views` picks the board poses an operator would be told to show: the board near every
part of the frame (centre, edges, corners, where distortion is strongest), tilted 10-35 degrees
about both axes (a fronto-parallel board cannot separate focal length from distance), rolled in
the plane and at a spread of distances, never seen more obliquely than 60 degrees (beyond that
OpenCV's ChArUco corners go wrong by pixels, and an operator would not hold it so).
`calibration_session` renders such a set with an ideal camera (a fixed blur, read noise);
`imaged_calibration_session` with a simulated rig's true camera (`sim_devices.world.TrueCamera`:
its true lens, depth of field, vignetting, light, shot and read noise, and JPEG as the camera
sends it), the same imaging the world's AprilTag frames get.

Board frame (OpenCV's): origin at the board's top-left corner as printed, x right, y down, z into
the board, in metres; `camera_T_board` is the board's pose in the OpenCV camera frame.

Known limitations: the paper is perfectly flat and the print perfectly to scale (the rig's
`print_scale_sigma` and `flatness_m` are its AprilTags', not this board's); the light on the board
is one level per view (times the frame's gain map), with no shading, glare or shadow; the defocus
blur is the board centre's, not per pixel across a tilted board; no motion blur or rolling
shutter; nothing occludes the board; a board partly behind the camera is not drawn at all.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Sequence

import cv2
import numpy as np

from lab.core.geometry import Pose3, Rot3
from sim_devices.camera import encode_frame
from sim_devices.render import _canvas  # the shared ideal-canvas + distortion remap tables
from sim_devices.render import Defocus, sensor_readout
from sim_devices.world import TrueCamera

__all__ = ["render_charuco", "charuco_corners_px", "calibration_views", "calibration_session",
           "imaged_calibration_session", "board_size_m", "PAPER_MARGIN_SQUARES", "IMAGED_SUPERSAMPLE"]

# The imaged camera's pixels integrate the scene over their area, sampled 2 x 2 per pixel.  Measured
# (default rig, 8 x 30 views, docs/calibration.md): the detected corners' error against the true
# projections is 0.19 px (rms, 2-D) point-sampled, 0.123 px at 2 x 2, 0.119 at 4 x 4; the
# calibration's RMS 0.159, 0.104, 0.106 px.  2 x 2 is converged and costs 4x the pixels.
IMAGED_SUPERSAMPLE = 2
# White paper around the printed squares, in squares (a printed board always has some).
PAPER_MARGIN_SQUARES = 0.5
_NEAR_PLANE_M = 0.02


def board_size_m(board: cv2.aruco.CharucoBoard) -> tuple[float, float]:
    """Width and height of the squared area of the board, in metres."""
    nx, ny = board.getChessboardSize()
    s = board.getSquareLength()
    return nx * s, ny * s


def _board_key(board: cv2.aruco.CharucoBoard) -> tuple:
    d = board.getDictionary()
    return (tuple(board.getChessboardSize()), float(board.getSquareLength()), float(board.getMarkerLength()),
            int(d.markerSize), d.bytesList.tobytes(), tuple(int(i) for i in np.ravel(board.getIds())),
            bool(board.getLegacyPattern()))


_boards: dict[tuple, cv2.aruco.CharucoBoard] = {}


# Texture resolutions: the projected square size rounded up to one of these, so a session of views
# reuses a few textures (each up to a few MB) instead of caching one per pixel size.
_TEXTURE_PX_PER_SQUARE = (8, 10, 12, 14, 16, 20, 24, 28, 32, 40, 48, 56, 64, 80, 96, 112, 128, 160)


@lru_cache(maxsize=8)
def _texture(key: tuple, px_per_square: int) -> np.ndarray:
    """The board with its paper margin at `px_per_square`, float32 in [0, 1]."""
    board = _boards[key]
    nx, ny = board.getChessboardSize()
    img = board.generateImage((nx * px_per_square, ny * px_per_square), marginSize=0, borderBits=1)
    m = int(round(PAPER_MARGIN_SQUARES * px_per_square))
    img = cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_CONSTANT, value=255)
    return img.astype(np.float32) / 255.0


def charuco_corners_px(K: np.ndarray, dist: Sequence[float] | np.ndarray | None, board: cv2.aruco.CharucoBoard,
                       camera_T_board: Pose3) -> np.ndarray:
    """The true image positions of every chessboard corner (charuco id order), lens distortion
    included: what a perfect detector would report."""
    obj = np.asarray(board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
    M = camera_T_board.matrix()
    rvec, _ = cv2.Rodrigues(M[:3, :3])
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).ravel()
    pts, _ = cv2.projectPoints(obj, rvec, M[:3, 3].copy(), np.asarray(K, dtype=float), d)
    return pts.reshape(-1, 2)


def _radiance(K: np.ndarray, d: np.ndarray, width: int, height: int, board: cv2.aruco.CharucoBoard,
              camera_T_board: Pose3, background: float, black: float, white: float) -> np.ndarray:
    """The board in front of the background as the lens bends it, each pixel point-sampled at its
    centre, before any blur: (height, width) float32, 1 = grey level 255."""
    canvas = _canvas(K.tobytes(), d.tobytes(), int(width), int(height))
    img = np.full((canvas.height, canvas.width), background / 255.0, dtype=np.float32)
    Kc = K.copy()
    Kc[0, 2] += canvas.offset[0]
    Kc[1, 2] += canvas.offset[1]

    M = camera_T_board.matrix()
    R, t = M[:3, :3], M[:3, 3]
    bw, bh = board_size_m(board)
    s = board.getSquareLength()
    margin = PAPER_MARGIN_SQUARES * s
    paper = np.array([[-margin, -margin, 0], [bw + margin, -margin, 0], [bw + margin, bh + margin, 0],
                      [-margin, bh + margin, 0]])
    paper_cam = paper @ R.T + t
    # The printed face is the board's -z side: it is seen when the camera lies on that side.
    faces_camera = float(R[:, 2] @ t) > 0.0
    if faces_camera and np.all(paper_cam[:, 2] > _NEAR_PLANE_M):
        H_plane = Kc @ np.column_stack([R[:, 0], R[:, 1], t])  # board plane (x, y) -> ideal canvas pixel
        c = np.column_stack([paper[:, :2], np.ones(4)]) @ H_plane.T
        c = c[:, :2] / c[:, 2:3]
        x0 = max(int(np.floor(c[:, 0].min())) - 1, 0)
        y0 = max(int(np.floor(c[:, 1].min())) - 1, 0)
        x1 = min(int(np.ceil(c[:, 0].max())) + 2, canvas.width)
        y1 = min(int(np.ceil(c[:, 1].max())) + 2, canvas.height)
        if x1 > x0 and y1 > y0:
            # Texture resolution about the largest projected square size.
            nx, ny = board.getChessboardSize()
            side_px = max(np.linalg.norm(c[1] - c[0]) / (nx + 2 * PAPER_MARGIN_SQUARES),
                          np.linalg.norm(c[3] - c[0]) / (ny + 2 * PAPER_MARGIN_SQUARES))
            ppsq = next((p for p in _TEXTURE_PX_PER_SQUARE if p >= side_px), _TEXTURE_PX_PER_SQUARE[-1])
            key = _board_key(board)
            _boards.setdefault(key, board)
            tex = _texture(key, ppsq)
            # Texture pixel (u, v) centre -> board plane point; generateImage puts pixel centres at
            # (i + 0.5) / scale, the paper margin shifts the origin.
            m_px = int(round(PAPER_MARGIN_SQUARES * ppsq))
            k = s / ppsq
            A = np.array([[k, 0.0, (0.5 - m_px) * k], [0.0, k, (0.5 - m_px) * k], [0.0, 0.0, 1.0]])
            shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
            H = shift @ H_plane @ A
            size = (x1 - x0, y1 - y0)
            patch = cv2.warpPerspective(tex, H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                        borderValue=1.0)
            alpha = cv2.warpPerspective(np.ones(tex.shape, np.float32), H, size, flags=cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
            roi = img[y0:y1, x0:x1]
            roi += alpha * (black + (white - black) * patch - roi)

    if canvas.map_x is not None:
        return cv2.remap(img, canvas.map_x, canvas.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return img[: int(height), : int(width)]


def render_charuco(
    K: np.ndarray,
    dist: Sequence[float] | np.ndarray | None,
    width: int,
    height: int,
    board: cv2.aruco.CharucoBoard,
    camera_T_board: Pose3,
    *,
    background: float = 110.0,
    black_level: float = 25.0,
    white_level: float = 225.0,
    blur_sigma_px: float = 0.6,
    noise_sigma: float = 2.0,
    rng: np.random.Generator | None = None,
    defocus: Defocus | None = None,
    gain: np.ndarray | None = None,
    full_well_e: float = 0.0,
    light: float = 1.0,
    supersample: int = 1,
) -> np.ndarray:
    """Render a ChArUco board seen by a camera.

    K: 3x3 intrinsics; dist: OpenCV distortion coefficients (k1, k2, p1, p2[, k3...]) or None;
    board: the printed board; camera_T_board: its pose (board frame above).  Levels are gray values
    (0-255), noise_sigma the read noise in gray levels, blur_sigma_px the lens's blur (at the focus
    distance if `defocus` is given: then the board is blurred for its centre's depth).  light: the
    light on the board (its black and white levels are times this); gain: (height, width) factors
    on the scene's radiance (vignetting, the light across the frame); full_well_e: electrons at
    white, adding photon shot noise (0: none) -- the sensor of `sim_devices.render.sensor_readout`.
    supersample: S > 1 renders the scene on an S x S finer grid and averages each pixel's S x S
    samples, as a sensor integrates over its pixel's area; 1 point-samples each pixel at its centre
    (through two bilinear interpolations, the texture's and the lens's: edges land up to ~0.1 px
    off depending on their phase, which the corner detector reads, docs/calibration.md).
    Without defocus, gain, shot noise, light and supersampling the image and the draws from `rng`
    are what they were before those existed.  A board facing away or crossing the near plane
    leaves only the background.  Returns (height, width, 3) uint8 BGR.
    """
    if int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample must be a positive integer, got {supersample!r}")
    S = int(supersample)
    imaged = defocus is not None or gain is not None or full_well_e > 0 or light != 1.0 or S > 1
    K = np.asarray(K, dtype=float).reshape(3, 3)
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).ravel()
    black, white = light * black_level / 255.0, light * white_level / 255.0
    if S == 1:
        img = _radiance(K, d, width, height, board, camera_T_board, background, black, white)
    else:
        # the fine grid: pixel (i, j) covers fine pixels S i .. S i + S - 1, so a point at x (px)
        # is at S (x + 1/2) - 1/2 on it
        Ks = K.copy()
        Ks[:2, :] *= S
        Ks[0, 2] = S * (K[0, 2] + 0.5) - 0.5
        Ks[1, 2] = S * (K[1, 2] + 0.5) - 0.5
        fine = _radiance(Ks, d, width * S, height * S, board, camera_T_board, background, black, white)
        img = cv2.resize(fine, (int(width), int(height)), interpolation=cv2.INTER_AREA)
    blur = blur_sigma_px
    if defocus is not None:
        M = camera_T_board.matrix()
        bw, bh = board_size_m(board)
        depth = float((M[:3, :3] @ np.array([bw / 2.0, bh / 2.0, 0.0]) + M[:3, 3])[2])
        blur = defocus.sigma_px(max(depth, _NEAR_PLANE_M), K[0, 0], blur_sigma_px)
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    img *= 255.0
    if imaged:
        return sensor_readout(np.ascontiguousarray(img, dtype=np.float32), gain=gain, noise_sigma=noise_sigma,
                              full_well_e=full_well_e, rng=rng)
    if noise_sigma > 0:
        g = rng if rng is not None else np.random.default_rng()
        img += g.standard_normal(img.shape, dtype=np.float32) * np.float32(noise_sigma)
    return cv2.cvtColor(np.clip(img, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    return Rot3.RzRyRx(rx, ry, rz).matrix()


def calibration_views(
    K: np.ndarray,
    dist: Sequence[float] | np.ndarray | None,
    width: int,
    height: int,
    board: cv2.aruco.CharucoBoard,
    n: int,
    rng: np.random.Generator,
    *,
    fill: tuple[float, float] = (0.35, 0.7),
    tilt_deg: tuple[float, float] = (10.0, 35.0),
    max_obliquity_deg: float = 60.0,
    min_square_px: float = 14.0,
    min_visible: float = 0.6,
) -> list[Pose3]:
    """`n` board poses (camera_T_board) like a good calibration session: the board's centre walks a
    3x3 grid over the frame (jittered), each view tilted `tilt_deg` about both board axes with
    alternating signs and rolled up to 30 degrees, at a distance where the board spans `fill` of
    the frame width.

    A view is kept when at least `min_visible` of the chessboard corners land inside the frame,
    the board is seen no more obliquely than `max_obliquity_deg` (angle between its normal and the
    line of sight to its centre: at grazing angles the squares collapse and the detector's corners
    go wrong by pixels) and no square edge projects shorter than `min_square_px`."""
    if n <= 0:
        raise ValueError(f"number of views must be positive, got {n}")
    K = np.asarray(K, dtype=float).reshape(3, 3)
    bw, bh = board_size_m(board)
    nx, ny = board.getChessboardSize()
    obj = np.asarray(board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
    grid_ids = np.arange(len(obj)).reshape(ny - 1, nx - 1)
    centre = np.array([bw / 2.0, bh / 2.0, 0.0])
    grid = [(0.5, 0.5), (0.2, 0.2), (0.8, 0.8), (0.8, 0.2), (0.2, 0.8), (0.5, 0.2), (0.5, 0.8), (0.2, 0.5),
            (0.8, 0.5)]
    Kinv = np.linalg.inv(K)
    cos_max = np.cos(np.radians(max_obliquity_deg))
    views: list[Pose3] = []
    for i in range(n):
        for _attempt in range(200):
            gx, gy = grid[i % len(grid)]
            u = (gx + rng.uniform(-0.08, 0.08)) * width
            v = (gy + rng.uniform(-0.08, 0.08)) * height
            z = K[0, 0] * bw / (rng.uniform(*fill) * width)
            sx = 1.0 if (i // 2) % 2 == 0 else -1.0
            sy = 1.0 if i % 2 == 0 else -1.0
            rx = sx * np.radians(rng.uniform(*tilt_deg))
            ry = sy * np.radians(rng.uniform(*tilt_deg))
            rz = np.radians(rng.uniform(-30.0, 30.0))
            R = _rotation(rx, ry, rz)
            p_centre = Kinv @ np.array([u, v, 1.0]) * z
            t = p_centre - R @ centre
            cam = Pose3(Rot3(R), t)
            pts = obj @ R.T + t
            if np.any(pts[:, 2] < 0.1) or float(R[:, 2] @ t) <= 0.0:
                continue
            if float(R[:, 2] @ p_centre) / np.linalg.norm(p_centre) < cos_max:
                continue
            # Both the ideal and the distorted projection must be in the frame: far outside it the
            # distortion polynomial can fold a point back in.
            inside = np.ones(len(obj), bool)
            for px in (charuco_corners_px(K, None, board, cam), charuco_corners_px(K, dist, board, cam)):
                inside &= (px[:, 0] >= 8) & (px[:, 0] < width - 8) & (px[:, 1] >= 8) & (px[:, 1] < height - 8)
            g = px[grid_ids]
            shortest = min(np.linalg.norm(np.diff(g, axis=0), axis=2).min(initial=np.inf),
                           np.linalg.norm(np.diff(g, axis=1), axis=2).min(initial=np.inf))
            if inside.mean() >= min_visible and shortest >= min_square_px:
                views.append(cam)
                break
        else:
            raise ValueError(f"could not place view {i} of the board inside a {width}x{height} frame; "
                             f"is the board too big or too small for this camera?")
    return views


def calibration_session(
    K: np.ndarray,
    dist: Sequence[float] | np.ndarray | None,
    width: int,
    height: int,
    board: cv2.aruco.CharucoBoard,
    n: int,
    rng: np.random.Generator,
    *,
    blur_sigma_px: float = 0.6,
    noise_sigma: float = 2.0,
) -> list[tuple[Pose3, np.ndarray]]:
    """`n` views of the board as `calibration_views` places them, rendered: (camera_T_board, BGR
    image) each."""
    views = calibration_views(K, dist, width, height, board, n, rng)
    return [(v, render_charuco(K, dist, width, height, board, v, blur_sigma_px=blur_sigma_px,
                               noise_sigma=noise_sigma, rng=rng)) for v in views]


def imaged_calibration_session(
    camera: TrueCamera,
    board: cv2.aruco.CharucoBoard,
    n: int,
    rng: np.random.Generator,
    *,
    gain: np.ndarray | None = None,
    light_rng: np.random.Generator | None = None,
) -> list[tuple[Pose3, np.ndarray]]:
    """`n` views of the board as `calibration_views` places them, rendered by a simulated rig's true
    camera (`sim_devices.world.true_camera`: `camera.K`, `camera.dist` the true lens) with its whole
    imaging (`camera.imaging`, lab/core/imaging.py): the lens's blur and depth of field at the board's
    distance, `gain` (the frame's vignetting and light, `sim_devices.world.camera_gain_map`), the
    board's own light level in each view (1 + lighting_variation * U(-1, 1), drawn from `light_rng`:
    an operator moves the board under the room's lamps), photon shot and read noise, then the frame
    as the camera sends it: JPEG at `jpeg_quality` (`sim_devices.camera.encode_frame`), decoded
    again (what a detector reads).  Pixels integrate over their area (`IMAGED_SUPERSAMPLE`).
    (camera_T_board, BGR image) each.

    With the ideal camera's imaging (`Imaging.ideal` but for the lens's distortion error and the
    tags' keys; no gain) this is `calibration_session` with the camera's K, dist, blur and read
    noise, image for image."""
    im = camera.imaging
    w, h = camera.width_px, camera.height_px
    # the tags' print keys are not this board's, and the lens's distortion error is in camera.dist
    if im.with_overrides({"print_scale_sigma": 0.0, "flatness_m": 0.0, "distortion_error_px": 0.0}).ideal \
            and gain is None:
        return calibration_session(camera.K, camera.dist, w, h, board, n, rng, blur_sigma_px=camera.blur_px,
                                   noise_sigma=camera.pixel_noise)
    views = calibration_views(camera.K, camera.dist, w, h, board, n, rng)
    lights = (light_rng if light_rng is not None else np.random.default_rng()).uniform(-1.0, 1.0, len(views))
    out = []
    for v, u in zip(views, lights):
        img = render_charuco(camera.K, camera.dist, w, h, board, v, blur_sigma_px=camera.blur_px,
                             noise_sigma=camera.pixel_noise, rng=rng, defocus=camera.defocus(), gain=gain,
                             full_well_e=im.full_well_e, light=1.0 + im.lighting_variation * float(u),
                             supersample=IMAGED_SUPERSAMPLE)
        if im.jpeg_quality > 0:
            body, _ = encode_frame(img, im.jpeg_quality)
            img = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
        out.append((v, img))
    return out
