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
   A bowed tag (`TagLook.bow_m`) moves each pixel's point from where its ray meets the flat plane
   to where it meets the bowed surface, before step 2.  The blur is the lens's own, or with a
   `Defocus` the lens's own combined with the thin lens's circle of confusion at the tag's depth.
   A tag's black and white levels are times its light (`TagLook.gain`).
3. Whatever `render_tags`'s overlay draws into that noise-free image (the truss's struts and
   nodes, `sim_devices.render_truss`, in front of and behind the tags by the tags' depth buffer).
4. The scene's radiance (tags, truss and background alike) times a gain map (vignetting, the light
   across the frame), then sensor noise: photon shot noise (variance signal * 255 / full well,
   grey levels^2) and read noise, then 8-bit BGR.  (JPEG, when the camera sends it, is the camera's: `sim_devices.camera`.)

The background (a grey level, or an image of the frame that is blurred like the tags) is not
distorted: it is taken to be what the camera sees behind the tags.

Known limitations: no shading model beyond a tag's one light level (no glare, no specular
reflection, no shadows), no motion blur, no rolling shutter, no fixed-pattern noise or hot pixels,
no occlusion by anything other than other tags and the truss (the truss is drawn by
`sim_devices.render_truss`, through `render_tags`'s overlay and the depth buffer `render_grey`
keeps: the plane of each tag's corners, a bowed tag's bow left out of it); tags are drawn farthest
centre first, each where no tag drawn before is nearer (the depth buffer holds a pixel's depth
where a tag covers more than half of it, so the one-pixel seam where a card's edge lies over
another tag is blended with the background, not with that tag); a tag partly behind the
camera is dropped whole rather than clipped; the blur is applied to each tag at its centre's depth
(not per pixel across a steeply inclined tag) and not across an occluding tag's outline; the
background is blurred by the lens's own blur only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, Iterable, Mapping, Sequence

import cv2
import numpy as np
from scipy.special import ndtr

from lab.core.geometry import Pose3

__all__ = ["TagToRender", "TagLook", "Defocus", "render_tags", "render_grey", "tag_corners_px", "draw_tags", "pixel_edge_response",
           "sensor_readout", "vignetting_gain", "lighting_field", "distortion_with_error", "QUIET_ZONE_CELLS",
           "COC_DIAMETER_PER_SIGMA"]

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

# Defocus blurs are rounded to this (px) so that the per-tag blurs share response tables.
_DEFOCUS_STEP_PX = 0.005
# A defocus blur disc's diameter over the sigma of the Gaussian drawn for it: 4 matches the disc's
# second moment (a uniform disc of radius R has sigma R/2 along any axis), and the 10-90 % width of
# the edge it makes to within 10 %.
COC_DIAMETER_PER_SIGMA = 4.0


@dataclass(frozen=True)
class TagLook:
    """How one printed tag really is and is lit; the defaults are an ideal tag.

    gain: the light on the tag (its black and white levels are times this).  bow_m: how far the
    tag's centre stands off the plane of its corners, along its face normal (+: towards the
    camera side of the face); the surface is z = bow_m (1 - (mix x^2 + (1 - mix) y^2) / h^2) in
    the tag frame, h the black square's half-edge, so its four corners stay in the plane (the pose
    the tag's corners give is the tag's pose) while its middle bows: mix 1 bends it about the tag's
    y axis alone (a cylinder), 0.5 is a dome."""

    gain: float = 1.0
    bow_m: float = 0.0
    bow_mix: float = 0.5


@dataclass(frozen=True)
class Defocus:
    """A thin lens focused at `focus_distance_m` with aperture `f_number` and focal length
    `focal_length_m`: a point at depth d (m, along the optical axis) is a disc of diameter
    c = f^2 / (N (s - f)) |d - s| / d on the sensor, c fx / f pixels.  `sigma_px` draws it as a
    Gaussian of sigma c / COC_DIAMETER_PER_SIGMA, combined in quadrature with the lens's own blur
    (`blur_sigma_px`, what a point in focus gets)."""

    focus_distance_m: float
    f_number: float
    focal_length_m: float

    def coc_px(self, depth_m: float, fx_px: float) -> float:
        """Diameter of the blur disc of a point at `depth_m`, in pixels."""
        s, f, d = self.focus_distance_m, self.focal_length_m, float(depth_m)
        if not s > f:
            raise ValueError(f"focus distance {s} m must be beyond the focal length {f} m")
        return f * float(fx_px) / (self.f_number * (s - f)) * abs(d - s) / max(d, 1e-9)

    def sigma_px(self, depth_m: float, fx_px: float, blur_sigma_px: float) -> float:
        return math.hypot(float(blur_sigma_px), self.coc_px(depth_m, fx_px) / COC_DIAMETER_PER_SIGMA)


def vignetting_gain(width: int, height: int, fraction: float) -> np.ndarray:
    """(height, width) float32: 1 at the frame's centre falling as the squared radius to 1 - fraction
    at the centres of its four corner pixels."""
    xs = (np.arange(width, dtype=np.float32) - (width - 1) / 2.0) / max((width - 1) / 2.0, 1e-9)
    ys = (np.arange(height, dtype=np.float32) - (height - 1) / 2.0) / max((height - 1) / 2.0, 1e-9)
    a = (width - 1) ** 2 / float((width - 1) ** 2 + (height - 1) ** 2)   # share of the corner radius^2 along x
    r2 = a * xs[None, :] ** 2 + (1.0 - a) * ys[:, None] ** 2            # (r / r_corner)^2
    return (1.0 - float(fraction) * r2).astype(np.float32)


def lighting_field(width: int, height: int, variation: float, rng: np.random.Generator, waves: int = 4) -> np.ndarray:
    """(height, width) float32: a smooth seeded light level across the frame, 1 +- `variation` at
    most -- a few plane waves of at most one cycle across the frame, random in direction, phase and
    weight, their sum shifted to mean 0 and scaled to peak 1."""
    p = rng.uniform(-1.0, 1.0, waves)        # cycles across the frame's width
    q = rng.uniform(-1.0, 1.0, waves)        # ... and height
    phase = rng.uniform(0.0, 2 * math.pi, waves)
    weight = rng.normal(0.0, 1.0, waves)
    if variation <= 0:
        return np.ones((height, width), np.float32)
    x = np.arange(width, dtype=np.float64) / width
    y = np.arange(height, dtype=np.float64) / height
    field = np.zeros((height, width), np.float64)
    for k in range(waves):   # cos(a + b) = cos a cos b - sin a sin b: two outer products per wave
        ax, by = 2 * math.pi * p[k] * x + phase[k], 2 * math.pi * q[k] * y
        field += weight[k] * (np.cos(by)[:, None] * np.cos(ax)[None, :] - np.sin(by)[:, None] * np.sin(ax)[None, :])
    field -= field.mean()
    field /= max(float(np.abs(field).max()), 1e-12)
    return (1.0 + float(variation) * field).astype(np.float32)


def distortion_with_error(K: np.ndarray, dist: Sequence[float] | np.ndarray, width: int, height: int,
                          error_px: float, sign: float = 1.0, k2_share: float = 0.0) -> np.ndarray:
    """A lens's true distortion coefficients when its calibration file says `dist`: k1 and k2 moved
    so that the ideal points the calibration puts at the four corners of the frame land, on average,
    `error_px` pixels away (through K).  `sign` says outwards (+) or inwards (-), `k2_share` (0..1)
    how much of it is k2's (r^5) rather than k1's (r^3); the shift is radial and grows from the
    centre to the corners either way.  Distortion is linear in its coefficients, so the displacement
    is exact, not a first-order estimate."""
    K = np.asarray(K, dtype=float).reshape(3, 3)
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).ravel().copy()
    if d.size < 5:
        d = np.concatenate([d, np.zeros(5 - d.size)])
    if error_px == 0:
        return d
    corners = np.array([[0.0, 0.0], [width - 1.0, 0.0], [width - 1.0, height - 1.0], [0.0, height - 1.0]])
    xy = cv2.undistortPointsIter(corners.reshape(-1, 1, 2), K, d, None, None,
                                 (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)).reshape(-1, 2)
    r2 = (xy ** 2).sum(axis=1)
    r0 = float(np.sqrt(r2.mean()))
    reach = np.hypot(K[0, 0] * xy[:, 0], K[1, 1] * xy[:, 1])       # px per unit of radial scale change
    w = float(np.clip(k2_share, 0.0, 1.0))
    shape = (1.0 - w) * r2 + w * r2 ** 2 / r0 ** 2                  # the scale change per unit of kappa
    kappa = float(error_px) / float(np.mean(reach * shape))
    d[0] += math.copysign(1.0, sign) * (1.0 - w) * kappa
    d[1] += math.copysign(1.0, sign) * w * kappa / r0 ** 2
    return d


# AprilTag 36h11 has 587 codes; a structure with more tags is printed in the lab's extension of it
# to 1024 (docs/hardware.md, "Tags"), made here as OpenCV makes it: its first 587 codes are 36h11's
_BASE_CODES, _EXTENDED_CODES = 587, 1024


@lru_cache(maxsize=2)
def _dictionary(extended: bool) -> cv2.aruco.Dictionary:
    base = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    return cv2.aruco.extendDictionary(_EXTENDED_CODES, 6, base, 0) if extended else base


def draw_tags(ids: Iterable[int]) -> None:
    """Draw these tags now, once: a structure printed in the extension of 36h11 would otherwise pay
    its generation (~4 s) in its first frame, past a camera client's timeout."""
    for tag_id in ids:
        _marker_cells(int(tag_id))


@lru_cache(maxsize=1024)
def _marker_cells(tag_id: int) -> np.ndarray:
    """The tag at one pixel per cell, quiet zone included, as float32 in [0, 1]."""
    if not 0 <= tag_id < _EXTENDED_CODES:
        raise ValueError(f"tag id {tag_id} is outside the printed tags' 0..{_EXTENDED_CODES - 1}")
    img = cv2.aruco.generateImageMarker(_dictionary(tag_id >= _BASE_CODES), int(tag_id), _CELLS, borderBits=1)
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


def _bowed(X: np.ndarray, Y: np.ndarray, gx: np.ndarray, gy: np.ndarray, K: np.ndarray, R: np.ndarray,
           look: TagLook, half_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray meets the bowed tag, given where it meets the flat plane (X, Y, tag
    frame, m).  The ray in the tag frame is o + l e (e = R^T K^-1 (gx, gy, 1)); on the flat plane it
    is at p0, and it meets the surface z(p) where p = p0 + z(p) e_xy / e_z: a fixed point, found by
    iterating (each step shrinks the error by the surface's slope times the ray's obliquity, 1e-2 or
    less for a tag bowed by a few tenths of a millimetre: three steps leave 1e-6 of the bow)."""
    A = R.T @ np.linalg.inv(K)
    ez = A[2, 0] * gx + A[2, 1] * gy + A[2, 2]
    ez = np.where(np.abs(ez) > 1e-12, ez, np.nan)
    rx = (A[0, 0] * gx + A[0, 1] * gy + A[0, 2]) / ez
    ry = (A[1, 0] * gx + A[1, 1] * gy + A[1, 2]) / ez
    a, b = look.bow_mix / half_m ** 2, (1.0 - look.bow_mix) / half_m ** 2
    # the shape holds on the card; beyond it (where rays near the plane's horizon meet it kilometres
    # off) the surface is held at the card edge's height, so the iteration stays bounded there
    reach = 2.0 * half_m
    x, y = X, Y
    for _ in range(3):
        cx, cy = np.clip(x, -reach, reach), np.clip(y, -reach, reach)
        z = look.bow_m * (1.0 - a * cx * cx - b * cy * cy)
        x, y = X + z * rx, Y + z * ry
    return x, y


_DEPTH_TIE_M = 1e-4    # a tag this little behind one drawn before still shows (coplanar neighbours)


def _draw_tag(img: np.ndarray, ideal: tuple[np.ndarray, np.ndarray] | None, K: np.ndarray, dist: np.ndarray,
              tag_id: int, size_m: float, M: np.ndarray, black: float, white: float, blur: float,
              look: TagLook | None, depth: np.ndarray) -> None:
    """Composite one tag into `img` (grey levels, float32), in place, but not where `depth` says a
    tag drawn before is nearer; keep the tag plane's depth (m along the optical axis; the plane of
    its corners, a bow left out) in `depth` where the tag covers more than half a pixel and is
    nearer than what it holds."""
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
    if look is not None and look.bow_m:              # a bowed tag's middle may stand out of its outline
        pad += int(math.ceil(abs(look.bow_m) * max(K[0, 0], K[1, 1]) / max(float(t[2]) - half, _NEAR_PLANE_M)))
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
    X = (Hinv[0, 0] * gx + Hinv[0, 1] * gy + Hinv[0, 2]) / w
    Y = (Hinv[1, 0] * gx + Hinv[1, 1] * gy + Hinv[1, 2]) / w
    if look is not None and look.bow_m:
        X, Y = _bowed(X, Y, gx, gy, K, R, look, size_m / 2.0)
    u = np.nan_to_num((X + half) / cell_m, nan=-1e3)
    v = np.nan_to_num((half - Y) / cell_m, nan=-1e3)
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
    # the ray through each ideal pixel meets the tag plane n.X = n.t at this z
    n_ = R[:, 2]
    ray = n_[0] * (gx - K[0, 2]) / K[0, 0] + n_[1] * (gy - K[1, 2]) / K[1, 1] + n_[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(ray * float(n_ @ t) > 0, float(n_ @ t) / ray, np.inf)
    # where a tag drawn before is nearer (two cards overlapping: the one whose centre is nearer
    # may lie behind where they meet), this one is behind it
    droi = depth[y0:y1, x0:x1]
    behind = z > droi + _DEPTH_TIE_M
    if behind.any():
        acc_a = np.where(behind, 0.0, acc_a)
        acc_s = np.where(behind, 0.0, acc_s)
    roi = img[y0:y1, x0:x1]
    roi *= 1.0 - acc_a
    roi += acc_s
    np.minimum(droi, np.where(acc_a > 0.5, z, np.inf).astype(np.float32), out=droi)


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
    defocus: Defocus | None = None,
    looks: Mapping[int, TagLook] | None = None,
    depth: np.ndarray | None = None,
) -> np.ndarray:
    """The noise-free image `render_tags` starts from, in grey levels, before the light's gain,
    noise and rounding to 8 bits: (height, width) float32.  Studies use it to tell the sensor's
    quantisation from the rest.  defocus: blur each tag by its depth (`Defocus`; None: blur_sigma_px
    everywhere); looks: tag id -> `TagLook` (its light, its bow; absent ids are ideal tags).
    `depth`: a (height, width) float32 array the caller filled with +inf; each tag drawn writes its
    plane's depth (m along the optical axis) where it covers more than half a pixel, the nearest
    kept (what `sim_devices.render_truss` tests the truss against)."""
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

    if depth is None:       # the tags' own depth test needs one
        depth = np.full((height, width), np.inf, np.float32)
    for _, tag_id, size_m, M in sorted(visible, key=lambda v: -v[0]):
        look = looks.get(tag_id) if looks else None
        blur = blur_sigma_px
        if defocus is not None:
            blur = round(defocus.sigma_px(M[2, 3], K[0, 0], blur_sigma_px) / _DEFOCUS_STEP_PX) * _DEFOCUS_STEP_PX
        g = 1.0 if look is None else look.gain
        _draw_tag(img, ideal, K, d, tag_id, size_m, M, black_level * g, white_level * g, blur, look, depth)
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
    defocus: Defocus | None = None,
    looks: Mapping[int, TagLook] | None = None,
    gain: np.ndarray | None = None,
    full_well_e: float = 0.0,
    overlay: Callable[[np.ndarray, np.ndarray], None] | None = None,
) -> np.ndarray:
    """Render AprilTag 36h11 tags seen by a camera.

    K: 3x3 intrinsics; dist: OpenCV distortion coefficients (k1, k2, p1, p2[, k3...]) or None;
    tags: (tag id, black-square edge in m, camera_T_tag) with the tag frame x right, y up, z out of
    the face.  background: a gray level (0-255) or an image of the frame's size.  blur_sigma_px is
    the lens's blur (Gaussian sigma, px), at the focus distance if `defocus` is given (then each
    tag is blurred for its depth, `Defocus`); looks: per tag id, its light and bow (`TagLook`).
    `overlay(grey, depth)`, if given, draws more of the scene (the truss: `sim_devices.render_truss`)
    into the noise-free grey image in place, against the tags' depth buffer (`render_grey`), before
    the gain and the noise: it is lit and vignetted as the tags are.
    gain: (height, width) factors on the scene's radiance (vignetting, uneven light), before the
    noise.  noise_sigma: the read noise, grey levels; full_well_e: electrons at white (255), adding
    photon shot noise of variance signal * 255 / full_well_e grey levels^2 (0: none).  Returns an
    (height, width, 3) uint8 BGR image.  Without defocus, looks, gain and shot noise, and with no
    overlay or one that draws nothing, the image and the draws from `rng` are what they were before
    those existed.
    """
    depth = None if overlay is None else np.full((height, width), np.inf, np.float32)
    img = render_grey(K, dist, width, height, tags, background=background, black_level=black_level,
                      white_level=white_level, blur_sigma_px=blur_sigma_px, defocus=defocus, looks=looks,
                      depth=depth)
    if overlay is not None:
        overlay(img, depth)
    return sensor_readout(img, gain=gain, noise_sigma=noise_sigma, full_well_e=full_well_e, rng=rng)


def sensor_readout(img: np.ndarray, *, gain: np.ndarray | None = None, noise_sigma: float = 2.0,
                   full_well_e: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """What the sensor reads of a noise-free frame `img` ((height, width) float32 grey levels;
    modified in place): times the `gain` map (vignetting, uneven light), then photon shot noise of
    variance signal * 255 / full_well_e grey levels^2 (0: none) and the read noise `noise_sigma`,
    rounded to 8 bits.  Returns (height, width, 3) uint8 BGR.  The AprilTag renderer's and the
    ChArUco board renderer's (`sim_devices.charuco_render`) last step."""
    if gain is not None:
        if gain.shape != img.shape:
            raise ValueError(f"gain map is {gain.shape[1]}x{gain.shape[0]}, the frame is {img.shape[1]}x{img.shape[0]}")
        img *= gain
    if full_well_e < 0:
        raise ValueError(f"full well must be >= 0 electrons, got {full_well_e}")
    if noise_sigma > 0 or full_well_e > 0:
        g = rng if rng is not None else np.random.default_rng()
        # cv2.randn is ~4x faster than numpy's normal for a full frame; seeding it from `rng`
        # keeps the image a function of the inputs (it does reseed OpenCV's global RNG).
        noise = np.empty(img.shape, np.float32)
        cv2.setRNGSeed(int(g.integers(2**31 - 1)))
        if full_well_e > 0:
            # photons: Poisson, variance = mean electrons, drawn as its normal limit (a white pixel
            # holds thousands); in grey levels signal * 255 / full_well, plus the read noise's
            cv2.randn(noise, 0.0, 1.0)
            sd = np.maximum(img, 0.0)
            sd *= np.float32(255.0 / full_well_e)
            sd += np.float32(float(noise_sigma) ** 2)
            np.sqrt(sd, out=sd)
            noise *= sd
        else:
            cv2.randn(noise, 0.0, float(noise_sigma))
        img += noise
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)  # round, not truncate: 110 must stay 110
    return cv2.cvtColor(out, cv2.COLOR_GRAY2BGR)
