"""AprilTag 36h11 image renderer: the pixels a camera would see of a set of tags.

`render_tags` is a pure function (camera model + tag poses in, image out).  The simulated camera
calls it with the true camera pose, so detection, PnP and everything after them run on pixels.

What a pixel reads: the scene integrated over the pixel's square (a sensor collects every photon
landing on its area, it does not point-sample) after the lens's Gaussian blur.  Point-sampling an
interpolated texture instead (what `warpPerspective` does) shifts every edge by up to a tenth of
a pixel depending on where it falls within a pixel, and corner detectors read that shift as tag
tilt; see docs/fiducials.md.

How an image is made, tag by tag (painter's order, farthest first, so nearer tags hide farther ones;
tags with a corner behind the near plane or a face pointing away are skipped):
1. For every output pixel near the tag, where its centre's ray meets the tag plane, in *cell
   coordinates* (u right, v down the printed tag, one unit per cell of the 8x8 black square plus a
   one-cell white quiet zone): lens distortion first (the ideal-pinhole position of each distorted
   pixel, `cv2.undistortPoints`, cached per camera), then the inverse plane-to-image homography
   `K [r1 r2 t]`.
2. The pixel's value is the tag pattern weighted by the pixel's response: for a straight edge at
   signed distance d (pixels) the response is the unit square projected onto the edge normal (a
   trapezoid of widths |n_x|, |n_y|) convolved with the blur, whose cumulative distribution is
   closed-form; cell edges of constant u and of constant v are treated separably (exact along an
   edge, an approximation only within a blur width of a cell corner).  A one-cell ring outside the
   quiet zone is transparent, so the same weights give the tag's coverage (alpha) and the
   background shows through in proportion.
3. Gaussian pixel noise, then 8-bit BGR.

The background (a grey level, or an image of the frame that is blurred like the tags) is not
distorted: it is taken to be what the camera sees behind the tags.

Known limitations: no lighting or shading model (the tag's black and white levels are constant),
no motion blur, no rolling shutter, no occlusion by anything other than other tags (the truss is
drawn by `sim_devices.render_truss`, through `render_tags`'s overlay and the depth buffer
`render_grey` keeps), no vignetting;
a tag partly behind the camera is dropped whole rather than clipped; the blur is applied to each
tag and not across an occluding tag's outline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, Sequence

import cv2
import numpy as np
from scipy.special import ndtr

from lab.geometry import Pose3

__all__ = ["TagToRender", "render_tags", "render_grey", "tag_corners_px", "pixel_edge_response", "QUIET_ZONE_CELLS"]

# AprilTag 36h11: a 6x6 data grid inside a one-cell black border = 8 cells across the black square.
_CELLS = 8
# White margin around the black square, in cells.  The detector needs at least one; tags printed
# on a white card usually have about that.
QUIET_ZONE_CELLS = 1.0
_NEAR_PLANE_M = 0.02
# The pixel response tables are sampled this finely (px) and read at the nearest sample: an edge
# then lands within 5e-4 px of where it should.
_TABLE_STEP_PX = 0.001

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
    remap tables that turn it into the distorted output frame (None without distortion).  Shared
    with `sim_devices.charuco_render`."""

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


@lru_cache(maxsize=8)
def _ideal_coords(K_key: bytes, dist_key: bytes, width: int, height: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Ideal-pinhole pixel position of every distorted output pixel's centre (None: no distortion)."""
    c = _canvas(K_key, dist_key, width, height)
    if c.map_x is None:
        return None
    return c.map_x.astype(np.float64) - c.offset[0], c.map_y.astype(np.float64) - c.offset[1]


def _second_integral(x: np.ndarray, sigma: float) -> np.ndarray:
    """Second antiderivative of the Gaussian density of std `sigma` (0: of a unit step at 0)."""
    if sigma <= 0:
        return 0.5 * np.maximum(x, 0.0) ** 2
    z = x / sigma
    return 0.5 * ((x * x + sigma * sigma) * ndtr(z) + x * sigma * np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi))


def _first_integral(x: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return np.maximum(x, 0.0)
    z = x / sigma
    return x * ndtr(z) + sigma * np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)


def pixel_edge_response(d: np.ndarray, normal: tuple[float, float], blur_sigma_px: float) -> np.ndarray:
    """Fraction of a pixel's response on the near side of a straight edge `d` px from the pixel's
    centre along the unit `normal` (the cumulative distribution of the response across the edge):
    the unit square projected on the normal is box(|n_x|) * box(|n_y|), convolved with a Gaussian
    blur.  No blur: the area of the pixel on that side, e.g. 0.5 for an edge through the centre,
    0.75 for an axis-aligned edge a quarter pixel beyond it."""
    a, b = sorted((abs(float(normal[0])), abs(float(normal[1]))), reverse=True)
    n = math.hypot(a, b)
    a, b = a / n, b / n
    d = np.asarray(d, dtype=float)
    s = float(blur_sigma_px)
    if b < 1e-3:   # the trapezoid is a box of width a: first differences
        return (_first_integral(d + a / 2, s) - _first_integral(d - a / 2, s)) / a
    p, q = (a + b) / 2, (a - b) / 2
    return (_second_integral(d + p, s) - _second_integral(d + q, s) - _second_integral(d - q, s)
            + _second_integral(d - p, s)) / (a * b)


@lru_cache(maxsize=512)
def _response_table(a_key: int, sigma_key: int) -> tuple[np.ndarray, float, float]:
    """`pixel_edge_response` tabulated on a uniform grid for an edge normal at angle atan(b/a)
    (a_key: |n_x| in hundredths) and a blur (sigma_key: thousandths of a px): (values, first d,
    reach), so a lookup is an index, not a search."""
    a = a_key / 100.0
    b = math.sqrt(max(0.0, 1.0 - a * a))
    s = sigma_key / 1000.0
    # beyond 5 sigma past the pixel's projected half-width the response is 1 - 3e-7
    reach = (a + b) / 2 + 5.0 * s + 0.01
    d = np.arange(-reach, reach + _TABLE_STEP_PX, _TABLE_STEP_PX)
    r = pixel_edge_response(d, (a, b), s).astype(np.float32)
    r[0], r[-1] = 0.0, 1.0
    return r, float(d[0]), reach


def _lookup(table, x: np.ndarray) -> np.ndarray:
    """The tabulated response at distances `x` (px), at the nearest sample (half a table step, 5e-4
    px, is far below anything a detector resolves)."""
    r, d0 = table[0], table[1]
    t = (x - d0) * (1.0 / _TABLE_STEP_PX) + 0.5
    np.clip(t, 0.0, len(r) - 1.0, out=t)
    return np.take(r, t.astype(np.int32))


def _axis_weights(f: np.ndarray, inv_g: np.ndarray, table, k: int) -> np.ndarray:
    """(2k + 1, P) weights of the cells at offsets -k..k from each pixel's own cell along one axis:
    the share of the pixel's response falling in each.  f: position within the own cell (0..1),
    inv_g: pixels per cell across this axis's edges."""
    offsets = np.arange(-k, k + 2, dtype=np.float32)[:, None]
    return np.diff(_lookup(table, (offsets - f[None, :]) * inv_g[None, :]), axis=0)


def _draw_tag(img: np.ndarray, ideal: tuple[np.ndarray, np.ndarray] | None, K: np.ndarray, dist: np.ndarray,
              tag_id: int, size_m: float, M: np.ndarray, black: float, white: float, blur: float,
              depth: np.ndarray | None = None) -> None:
    """Composite one tag into `img` (grey levels, float32), in place; with `depth`, also keep the
    tag plane's depth (m along the optical axis) where the tag covers more than half a pixel and is
    nearer than what `depth` holds."""
    height, width = img.shape
    R, t = M[:3, :3], M[:3, 3]
    cells = _marker_cells(tag_id)                          # (n, n): quiet zone + black square
    n = cells.shape[0]
    q = (n - _CELLS) / 2                                   # quiet-zone cells on each side
    cell_m = size_m / _CELLS
    half = size_m / 2 + q * cell_m
    # the tag's outline (quiet zone included), distorted, for its bounding box
    s = np.linspace(-half, half, 9)
    outline = np.concatenate([np.column_stack([s, np.full(9, half)]), np.column_stack([s, np.full(9, -half)]),
                              np.column_stack([np.full(9, half), s]), np.column_stack([np.full(9, -half), s])])
    rvec, _ = cv2.Rodrigues(R)
    px, _ = cv2.projectPoints(np.column_stack([outline, np.zeros(len(outline))]), rvec, t.copy(), K, dist)
    px = px.reshape(-1, 2)
    pad = int(math.ceil(0.71 + 5.0 * blur)) + 1      # the pixel response's reach, and a pixel
    x0 = max(int(np.floor(px[:, 0].min())) - pad, 0)
    y0 = max(int(np.floor(px[:, 1].min())) - pad, 0)
    x1 = min(int(np.ceil(px[:, 0].max())) + pad + 1, width)
    y1 = min(int(np.ceil(px[:, 1].max())) + pad + 1, height)
    if x1 - x0 < 2 or y1 - y0 < 2:
        return
    if ideal is None:
        gx, gy = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    else:
        gx, gy = ideal[0][y0:y1, x0:x1], ideal[1][y0:y1, x0:x1]
    # ideal pixel -> tag plane (x right, y up) -> cell coordinates (u right, v down, 0 at the quiet
    # zone's top-left corner)
    Hinv = np.linalg.inv(K @ np.column_stack([R[:, 0], R[:, 1], t]))
    w = Hinv[2, 0] * gx + Hinv[2, 1] * gy + Hinv[2, 2]
    # rays beyond the plane's horizon (w <= 0 for a plane in front) do not meet it: park them far off
    w = np.where(w > 1e-12, w, np.nan)
    u = np.nan_to_num(((Hinv[0, 0] * gx + Hinv[0, 1] * gy + Hinv[0, 2]) / w + half) / cell_m, nan=-1e3)
    v = np.nan_to_num((half - (Hinv[1, 0] * gx + Hinv[1, 1] * gy + Hinv[1, 2]) / w) / cell_m, nan=-1e3)
    du_y, du_x = np.gradient(u)
    dv_y, dv_x = np.gradient(v)
    g_u = np.hypot(du_x, du_y)                             # cells per pixel across edges of constant u
    g_v = np.hypot(dv_x, dv_y)
    # one response table per axis for the whole tag: the edges' directions vary by a few degrees
    # across a tag, which changes the (symmetric) response shape negligibly
    cu, cv_ = u.shape[0] // 2, u.shape[1] // 2
    tab_u = _response_table(int(round(100 * abs(du_x[cu, cv_]) / max(g_u[cu, cv_], 1e-12))), int(round(1000 * blur)))
    tab_v = _response_table(int(round(100 * abs(dv_x[cu, cv_]) / max(g_v[cu, cv_], 1e-12))), int(round(1000 * blur)))
    # cells within the response's reach: the largest cells-per-pixel over the tag itself (a tag seen
    # nearly edge-on has huge ones near the plane's horizon; more than the tag's width is pointless)
    on_tag = (u > -1.0) & (u < n + 1.0) & (v > -1.0) & (v < n + 1.0)
    if not on_tag.any():
        return
    k = int(math.ceil(max(tab_u[2] * float(g_u[on_tag].max()), tab_v[2] * float(g_v[on_tag].max()))))
    k = min(max(k, 1), n)
    # premultiplied pattern (shade * alpha, alpha) in a transparent ring 2k + 1 cells wide: a pixel
    # farther off the tag than that is clamped into the ring, where all its 2k + 1 cells are clear
    ring = 2 * k + 1
    nn = n + 2 * ring
    white_cells = np.zeros((nn, nn), np.float32)
    white_cells[ring:ring + n, ring:ring + n] = cells
    shape = u.shape
    u = u.ravel().astype(np.float32)
    v = v.ravel().astype(np.float32)
    inv_gu = 1.0 / np.maximum(g_u.ravel(), 1e-9).astype(np.float32)
    inv_gv = 1.0 / np.maximum(g_v.ravel(), 1e-9).astype(np.float32)
    iu0 = np.floor(u)
    iv0 = np.floor(v)
    wu = _axis_weights(u - iu0, inv_gu, tab_u, k)   # (2k+1, P)
    wv = _axis_weights(v - iv0, inv_gv, tab_v, k)
    iu = np.clip(iu0.astype(np.int32) + ring, k, nn - 1 - k)
    iv = np.clip(iv0.astype(np.int32) + ring, k, nn - 1 - k)
    offsets = (np.arange(-k, k + 1)[:, None] * nn + np.arange(-k, k + 1)[None, :]).reshape(-1, 1)   # (b, a)
    index = (iv * nn + iu)[None, :] + offsets                                             # (K2, P)
    weights = (wv[:, None, :] * wu[None, :, :]).reshape(index.shape)
    on_white = np.einsum("kp,kp->p", weights, np.take(white_cells.ravel(), index))
    # coverage by the tag (quiet zone included): the response's share inside 0 <= u, v <= n, the
    # same separable weights summed over the tag's cells
    cover = ((_lookup(tab_u, (n - u) * inv_gu) - _lookup(tab_u, -u * inv_gu))
             * (_lookup(tab_v, (n - v) * inv_gv) - _lookup(tab_v, -v * inv_gv)))
    acc_a = cover.reshape(shape)
    acc_s = (black * cover + (white - black) * on_white).reshape(shape)
    roi = img[y0:y1, x0:x1]
    roi *= 1.0 - acc_a
    roi += acc_s
    if depth is not None:   # the ray through each ideal pixel meets the tag plane n.X = n.t at this z
        n_ = R[:, 2]
        ray = n_[0] * (gx - K[0, 2]) / K[0, 0] + n_[1] * (gy - K[1, 2]) / K[1, 1] + n_[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where((acc_a > 0.5) & (ray * float(n_ @ t) > 0), float(n_ @ t) / ray, np.inf)
        droi = depth[y0:y1, x0:x1]
        np.minimum(droi, z.astype(np.float32), out=droi)


def render_grey(
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
    depth: np.ndarray | None = None,
) -> np.ndarray:
    """The noise-free image `render_tags` starts from, in grey levels, before noise and rounding to
    8 bits: (height, width) float32.  Studies use it to tell the sensor's quantisation from the
    rest.  `depth`: a (height, width) float32 array the caller filled with +inf; each tag drawn
    writes its plane's depth (m along the optical axis) where it covers more than half a pixel,
    the nearest kept (what `sim_devices.render_truss` tests the truss against)."""
    K = np.asarray(K, dtype=float).reshape(3, 3)
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if blur_sigma_px < 0:
        raise ValueError(f"blur must be >= 0, got {blur_sigma_px} px")
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).ravel()
    ideal = _ideal_coords(K.tobytes(), d.tobytes(), int(width), int(height))
    if np.isscalar(background):
        img = np.full((height, width), float(background), dtype=np.float32)
    else:
        bg = np.asarray(background)
        if bg.ndim == 3:
            bg = cv2.cvtColor(bg.astype(np.uint8), cv2.COLOR_BGR2GRAY)
        if bg.shape != (height, width):
            raise ValueError(f"background image is {bg.shape[1]}x{bg.shape[0]}, the frame is {width}x{height}")
        img = bg.astype(np.float32)
        if blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)

    visible: list[tuple[float, int, float, np.ndarray]] = []
    for tag_id, size_m, camera_T_tag in tags:
        if size_m <= 0:
            raise ValueError(f"tag {tag_id}: size must be positive, got {size_m} m")
        _marker_cells(int(tag_id))  # a bad id is named even when the tag is out of view
        M = camera_T_tag.matrix()
        R, t = M[:3, :3], M[:3, 3]
        if float(R[:, 2] @ t) >= 0.0:  # the face's normal points away from the camera
            continue
        half = size_m / 2.0 * (_CELLS + 2 * np.ceil(QUIET_ZONE_CELLS)) / _CELLS
        corners = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]]) @ R.T + t
        if np.any(corners[:, 2] < _NEAR_PLANE_M):
            continue
        visible.append((float(np.linalg.norm(t)), int(tag_id), float(size_m), M))

    for _, tag_id, size_m, M in sorted(visible, key=lambda v: -v[0]):
        _draw_tag(img, ideal, K, d, tag_id, size_m, M, black_level, white_level, blur_sigma_px, depth)
    return img


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
    overlay: Callable[[np.ndarray, np.ndarray], None] | None = None,
) -> np.ndarray:
    """Render AprilTag 36h11 tags seen by a camera.

    K: 3x3 intrinsics; dist: OpenCV distortion coefficients (k1, k2, p1, p2[, k3...]) or None;
    tags: (tag id, black-square edge in m, camera_T_tag) with the tag frame x right, y up, z out of
    the face.  background: a gray level (0-255) or an image of the frame's size.  noise_sigma is in
    gray levels; blur_sigma_px is the defocus blur (Gaussian sigma, px).  `overlay(grey, depth)`,
    if given, draws more of the scene (the truss: `sim_devices.render_truss`) into the noise-free
    grey image in place, against the tags' depth buffer (`render_grey`), before the noise.
    Returns an (height, width, 3) uint8 BGR image.
    """
    depth = None if overlay is None else np.full((height, width), np.inf, np.float32)
    img = render_grey(K, dist, width, height, tags, background=background, black_level=black_level,
                      white_level=white_level, blur_sigma_px=blur_sigma_px, depth=depth)
    if overlay is not None:
        overlay(img, depth)
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
