"""AprilTag 36h11 image renderer: the pixels a camera would see of a set of tags.

`render_tags` is a pure function (camera model + tag poses in, image out).  The simulated camera
calls it with the true camera pose, so detection, PnP and everything after them run on pixels.

How an image is made:
1. Each tag (black square of edge `size_m`, 8x8 cells, plus a white quiet zone) is drawn from
   `cv2.aruco.generateImageMarker` into an *ideal pinhole* canvas with the exact plane-to-image
   homography `K [r1 r2 t]`, warped only inside the tag's bounding box (that keeps 20 tags in a
   1280x720 frame well under the frame budget).  An alpha mask warped the same way anti-aliases
   the tag edge into the background.
2. Tags are drawn in painter's order (farthest first) so nearer tags occlude farther ones.  Tags
   with any corner behind the near plane, or whose face points away from the camera, are skipped.
3. Lens distortion is then applied to the whole canvas with one `cv2.remap`: for every pixel of
   the distorted image we look up where its ray lands in the ideal canvas (`cv2.undistortPoints`,
   cached per camera), so straight tag edges bend exactly as OpenCV's distortion model says.
   With barrel distortion the corners of the distorted frame see outside the ideal frame, so the
   ideal canvas is padded to cover them.
4. Gaussian blur (defocus) and Gaussian pixel noise, then 8-bit BGR.

Known limitations: no lighting or shading model (the tag's black and white levels are constant),
no motion blur, no rolling shutter, no occlusion by anything other than other tags, no vignetting;
a tag partly behind the camera is dropped whole rather than clipped.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import cv2
import numpy as np

from lab.geometry import Pose3

__all__ = ["TagToRender", "render_tags", "tag_corners_px", "QUIET_ZONE_CELLS"]

# AprilTag 36h11: a 6x6 data grid inside a one-cell black border = 8 cells across the black square.
_CELLS = 8
# White margin around the black square, in cells.  The detector needs at least one; tags printed
# on a white card usually have about that.
QUIET_ZONE_CELLS = 1.0
_NEAR_PLANE_M = 0.02

TagToRender = tuple[int, float, Pose3]  # (tag id, black-square edge in m, camera_T_tag)


@lru_cache(maxsize=1)
def _dictionary() -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)


@lru_cache(maxsize=1024)
def _marker_cells(tag_id: int) -> np.ndarray:
    """The tag at one pixel per cell, quiet zone included, as float32 in [0, 1]."""
    n_ids = _dictionary().bytesList.shape[0]
    if not 0 <= tag_id < n_ids:
        raise ValueError(f"tag id {tag_id} is outside AprilTag 36h11's 0..{n_ids - 1}")
    img = cv2.aruco.generateImageMarker(_dictionary(), int(tag_id), _CELLS, borderBits=1)
    q = int(np.ceil(QUIET_ZONE_CELLS))
    img = cv2.copyMakeBorder(img, q, q, q, q, cv2.BORDER_CONSTANT, value=255)
    return (img.astype(np.float32) / 255.0)


@lru_cache(maxsize=4096)
def _marker_texture(tag_id: int, px_per_cell: int) -> np.ndarray:
    cells = _marker_cells(tag_id)
    side = cells.shape[0] * px_per_cell
    return cv2.resize(cells, (side, side), interpolation=cv2.INTER_NEAREST)


def tag_corners_px(K: np.ndarray, camera_T_tag: Pose3, size_m: float, dist: np.ndarray | None = None) -> np.ndarray:
    """The black square's corners in pixels, in the detector's order (as printed: top-left,
    top-right, bottom-right, bottom-left), with lens distortion if `dist` is given."""
    h = size_m / 2.0
    obj = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    M = camera_T_tag.matrix()
    rvec, _ = cv2.Rodrigues(M[:3, :3])
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=float)
    pts, _ = cv2.projectPoints(obj, rvec, M[:3, 3].copy(), np.asarray(K, dtype=float), d)
    return pts.reshape(4, 2)


@dataclass(frozen=True)
class _Canvas:
    """The ideal (undistorted) canvas: its size, its pixel offset against the output frame, and the
    remap tables that turn it into the distorted output frame (None without distortion)."""

    width: int
    height: int
    offset: tuple[int, int]
    map_x: np.ndarray | None
    map_y: np.ndarray | None


@lru_cache(maxsize=8)
def _canvas(K_key: bytes, dist_key: bytes, width: int, height: int) -> _Canvas:
    K = np.frombuffer(K_key, dtype=float).reshape(3, 3)
    dist = np.frombuffer(dist_key, dtype=float)
    if not np.any(dist):
        return _Canvas(width, height, (0, 0), None, None)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    ideal = cv2.undistortPointsIter(
        pix, K, dist, None, K, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-6)
    ).reshape(height, width, 2)
    pad_x0 = int(np.ceil(max(0.0, -ideal[..., 0].min()))) + 2
    pad_y0 = int(np.ceil(max(0.0, -ideal[..., 1].min()))) + 2
    pad_x1 = int(np.ceil(max(0.0, ideal[..., 0].max() - (width - 1)))) + 2
    pad_y1 = int(np.ceil(max(0.0, ideal[..., 1].max() - (height - 1)))) + 2
    map_x = (ideal[..., 0] + pad_x0).astype(np.float32)
    map_y = (ideal[..., 1] + pad_y0).astype(np.float32)
    return _Canvas(width + pad_x0 + pad_x1, height + pad_y0 + pad_y1, (pad_x0, pad_y0), map_x, map_y)


def _background(background: float | np.ndarray, canvas: _Canvas, width: int, height: int) -> np.ndarray:
    if np.isscalar(background):
        return np.full((canvas.height, canvas.width), float(background) / 255.0, dtype=np.float32)
    bg = np.asarray(background)
    if bg.ndim == 3:
        bg = cv2.cvtColor(bg.astype(np.uint8), cv2.COLOR_BGR2GRAY)
    if bg.shape != (height, width):
        raise ValueError(f"background image is {bg.shape[1]}x{bg.shape[0]}, the frame is {width}x{height}")
    ox, oy = canvas.offset
    out = cv2.copyMakeBorder(
        bg.astype(np.float32) / 255.0,
        oy,
        canvas.height - height - oy,
        ox,
        canvas.width - width - ox,
        cv2.BORDER_REPLICATE,
    )
    return out


def render_tags(
    K: np.ndarray,
    dist: Sequence[float] | np.ndarray | None,
    width: int,
    height: int,
    tags: Sequence[TagToRender],
    *,
    background: float | np.ndarray = 110.0,
    black_level: float = 25.0,
    white_level: float = 225.0,
    blur_sigma_px: float = 0.6,
    noise_sigma: float = 2.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Render AprilTag 36h11 tags seen by a camera.

    K: 3x3 intrinsics; dist: OpenCV distortion coefficients (k1, k2, p1, p2[, k3...]) or None;
    tags: (tag id, black-square edge in m, camera_T_tag) with the tag frame x right, y up, z out of
    the face.  background: a gray level (0-255) or an image of the frame's size.  noise_sigma is in
    gray levels; blur_sigma_px is the defocus blur.  Returns an (height, width, 3) uint8 BGR image.
    """
    K = np.asarray(K, dtype=float).reshape(3, 3)
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).ravel()
    canvas = _canvas(K.tobytes(), d.tobytes(), int(width), int(height))
    img = _background(background, canvas, width, height)

    # Intrinsics of the ideal canvas (its origin is shifted by the padding).
    Kc = K.copy()
    Kc[0, 2] += canvas.offset[0]
    Kc[1, 2] += canvas.offset[1]

    visible: list[tuple[float, int, float, np.ndarray]] = []
    for tag_id, size_m, camera_T_tag in tags:
        if size_m <= 0:
            raise ValueError(f"tag {tag_id}: size must be positive, got {size_m} m")
        M = camera_T_tag.matrix()
        R, t = M[:3, :3], M[:3, 3]
        if float(R[:, 2] @ t) >= 0.0:  # the face's normal points away from the camera
            continue
        half = size_m / 2.0 * (_CELLS + 2 * np.ceil(QUIET_ZONE_CELLS)) / _CELLS
        corners = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]]) @ R.T + t
        if np.any(corners[:, 2] < _NEAR_PLANE_M):
            continue
        visible.append((float(np.linalg.norm(t)), int(tag_id), float(half), M))

    black = black_level / 255.0
    white = white_level / 255.0
    for _, tag_id, half, M in sorted(visible, key=lambda v: -v[0]):
        R, t = M[:3, :3], M[:3, 3]
        # Plane (x, y) -> ideal canvas pixel.
        H_plane = Kc @ np.column_stack([R[:, 0], R[:, 1], t])
        corners = np.array([[-half, half, 1], [half, half, 1], [half, -half, 1], [-half, -half, 1]]) @ H_plane.T
        corners = corners[:, :2] / corners[:, 2:3]
        x0 = max(int(np.floor(corners[:, 0].min())) - 1, 0)
        y0 = max(int(np.floor(corners[:, 1].min())) - 1, 0)
        x1 = min(int(np.ceil(corners[:, 0].max())) + 2, canvas.width)
        y1 = min(int(np.ceil(corners[:, 1].max())) + 2, canvas.height)
        if x1 <= x0 or y1 <= y0:
            continue
        # Texture resolution about the projected cell size, so the warp neither aliases nor wastes.
        n_cells = _marker_cells(tag_id).shape[0]
        side_px = max(np.linalg.norm(corners[1] - corners[0]), np.linalg.norm(corners[3] - corners[0]))
        ppc = int(np.clip(np.ceil(side_px / n_cells), 2, 64))
        tex = _marker_texture(tag_id, ppc)
        n = tex.shape[0]
        s = 2.0 * half / n
        # Texture pixel (u, v) centre -> plane point (x right, y up).
        A = np.array([[s, 0.0, -half + 0.5 * s], [0.0, -s, half - 0.5 * s], [0.0, 0.0, 1.0]])
        shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        H = shift @ H_plane @ A
        size = (x1 - x0, y1 - y0)
        patch = cv2.warpPerspective(tex, H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
        alpha = cv2.warpPerspective(
            np.ones((n, n), np.float32), H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0
        )
        alpha[alpha > 0.999] = 1.0  # warp weights leave 1 - 1e-4 inside: no see-through tags
        roi = img[y0:y1, x0:x1]
        shade = black + (white - black) * patch
        roi *= 1.0 - alpha  # (not roi += alpha*(shade-roi): that leaves float dust where alpha == 1)
        roi += alpha * shade

    if canvas.map_x is not None:
        img = cv2.remap(img, canvas.map_x, canvas.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    img *= 255.0
    if noise_sigma > 0:
        g = rng if rng is not None else np.random.default_rng()
        # cv2.randn is ~4x faster than numpy's normal for a full frame; seeding it from `rng`
        # keeps the image a function of the inputs (it does reseed OpenCV's global RNG).
        noise = np.empty(img.shape, np.float32)
        cv2.setRNGSeed(int(g.integers(2**31 - 1)))
        cv2.randn(noise, 0.0, float(noise_sigma))
        img += noise
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)  # round, not truncate: 110 must stay 110
    return cv2.cvtColor(out, cv2.COLOR_GRAY2BGR)
