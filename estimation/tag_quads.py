"""Sub-pixel tag quads: the black square's four edges located to a few hundredths of a pixel, and
the tag's bits read back from the refined quad.

Edge location (`fit_quads`).  A camera pixel reads the scene integrated over its area, after a
blur that is symmetric about each point.  Across a straight dark-to-bright edge, the sum of a row
of pixels normalised to 0 (dark) .. 1 (bright) is then exactly the length of the row that lies on
the bright side: summing over pixels integrates the pixel box, and a box sums to the integral of
what it samples whatever the edge's sub-pixel phase (its spectrum is zero at every multiple of the
sampling frequency).  So along every image row (for edges steeper than 45 deg; columns for the
others) that crosses an edge, a window of pixels centred on the edge gives the crossing as
`window end - sum`, with no dependence on where the edge falls within a pixel and no model of the
blur; a straight line fitted through the crossings of all usable rows is the edge, and adjacent
edges intersect at the corners.  The 50 % crossing of an interpolated profile (what we used
before) is biased by up to 0.1 px depending on that phase, and a frontal tag read that way looks
tilted by a degree or more.

What keeps other structure out of the windows: they reach at most one cell minus 2.5 px across the
edge (the black border cell inside, the white quiet zone outside, clear of the next edges' blur),
symmetric about the current line so that truncated blur tails cancel and passes converge; rows
within a window's reach of a corner are left out.  The dark and bright levels are the edge's mean
half a cell inside and outside it, or its tag's black and white for cells under 4 px.  A window off
the image on the dark side loses its row; on the bright side (a tag touching the frame) the quiet
zone is taken to go on past the edge.  Tags with cells under 4.5 px start with a coarse pass (the
steepest dark-to-bright step within 1.5 cells), which pulls in a detector's corner 2-3 px off; fine
passes follow until no corner moves more than CONVERGED_PX.  An edge with fewer than `MIN_ROWS`
usable rows keeps the line it came with (and its quad is reported as not fully fitted).

Occlusion (a strut of the truss in front of a tag): from the second fine pass, an edge's dark and
bright levels are the medians of the image at its windows' two ends, and rows whose ends stray
from them (something crossing the edge), or, on tags with a clear quiet zone, whose quiet zone
darkens just past the window or whose edge reads short of the tag's contrast (something along
the edge), are left out with guard rows (`QuadFit.occluded`); `ring_deviation` reads the whole
black border and quiet zone against the tag's own black and white.  The tolerances follow the
frame: a row's at least OCCLUSION_NOISE_SIGMAS of its edge's own spread (a noisy camera), the
ring's samples clear of their cells' edges by RING_MIN_EDGE_SIGMAS of the tag's edge blur
(`edge_blur_px`: a blurred lens).  Constants OCCLUSION_* and RING_*; docs/fiducials.md,
"Occlusion".

Bit reading (`read_bits`, `identify`): the 8x8 cells and the quiet-zone ring around them sampled at
their centres through the quad's homography, sharpened, and thresholded halfway between planes
fitted to the black border and to the white ring, as the AprilTag library does; a detection is
then checked against the dictionary with a Hamming distance of our choosing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from scipy.special import ndtr

from estimation import edge_kernel
from estimation.tag_family import BASE, dictionary

__all__ = ["QuadFit", "fit_quads", "read_bits", "code_bits", "identify", "ring_deviation", "edge_blur_px", "MIN_ROWS"]

CELLS = 8                 # AprilTag 36h11: 6x6 data cells inside a one-cell black border
MIN_ROWS = 3              # an edge needs this many usable rows (or columns) to be refitted
MIN_CONTRAST = 8.0        # grey levels between the dark and bright sides of a usable edge
MAX_REACH_PX = 2.5        # window half-width across an edge (3 sigma of the sim's blur and pixel)
MIN_REACH_PX = 1.0
COARSE_SEARCH_PX = 3.0    # how far the first pass looks for an edge (a detector's corners can be 2-3 px off)
COARSE_SEARCH_CELLS = 1.5  # ... or 1.5 cells: the inner pattern's and quiet zone's edges step the other way
COARSE_BELOW_CELL_PX = 4.5  # tags with smaller cells start with a coarse pass
SHARPEN = 0.25            # Laplacian sharpening of the cell samples before reading bits (AprilTag's default)
CONVERGED_PX = 0.1        # a fine pass that moved no corner more than this ends a quad's refinement
MAX_DRIFT_PX = 4.0        # a quad whose corner runs further than this (or MAX_DRIFT_SIDES of its side)
MAX_DRIFT_SIDES = 0.25    # from where it started is lost, not refined (the detector's check is 3.5 px / 0.2)
EDGE_LEVELS_MIN_CELL_PX = 4.0   # smaller cells: an edge's dark/bright levels are its tag's
# Occlusion (docs/fiducials.md), looked for on edges whose cells are OCCLUSION_MIN_CELL_PX or more:
# a row is left out as occluded when its window's end samples differ from its edge's medians by
# more than OCCLUSION_TOLERANCE of the edge's contrast; where cells are OCCLUSION_ABSOLUTE_MIN_CELL_PX
# or more (windows reaching 2 px or more, clear of the edge's own blur), also when its quiet zone
# darkens by more than OCCLUSION_MAX_DROP of the tag's contrast OCCLUSION_FAR_PX past its window,
# and every row of an edge whose contrast at the windows' ends is below OCCLUSION_MIN_CONTRAST of
# the tag's.  OCCLUSION_GUARD_ROWS rows either side go with each.
OCCLUSION_TOLERANCE = 0.15
OCCLUSION_MIN_CELL_PX = 3.5
OCCLUSION_ABSOLUTE_MIN_CELL_PX = 4.0
OCCLUSION_MAX_DROP = 0.2
OCCLUSION_FAR_PX = 1.0
OCCLUSION_MIN_CONTRAST = 0.8
OCCLUSION_GUARD_ROWS = 3
# ... and, on a noisy frame (or a blurred one, whose windows' ends read less of the contrast), the
# tolerance is at least this many of the edge's own row-to-row spread (1.4826 MAD of the samples
# about their medians): noise alone then flags no row, and a strut (0.4 of the contrast and more
# over the quiet zone) still is
OCCLUSION_NOISE_SIGMAS = 4.5
RING_MIN_EDGE_PX = 0.9         # ... those at least this far from both edges of their cell,
RING_MIN_EDGE_SIGMAS = 1.15    # ... and this many of the tag's edge blur (`edge_blur_px`): at the
                               # sim's 0.6 px lens (edges 0.65-0.9 px) that is the 0.9 px above, and
                               # a clean sample loses at most ~0.13 of the contrast to a cell edge's
                               # blur whatever the lens
EDGE_BLUR_NEAR_PX = 0.5        # `edge_blur_px`: the contrast across an edge at +-this ...
RING_DEPTHS_CELLS = (0.3, 0.5)  # the perimeter check's samples, from the black square's edge (`ring_deviation`)


@dataclass(frozen=True)
class QuadFit:
    corners: np.ndarray        # (N, 4, 2) refined corners, input order
    edges_fitted: np.ndarray   # (N, 4) bool: edge i (corner i -> i+1) was refitted
    rms_px: np.ndarray         # (N, 4) rms of the row crossings about each fitted line (nan if not fitted)
    corner_sigma_px: np.ndarray  # (N, 4) each corner's standard error from its two lines' fits (nan: unfitted)
    occluded: np.ndarray = None  # (N, 4) share of each edge's rows left out as occluded (the last pass's)


def _lines_from_corners(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edge i of each quad as (a point on it, unit direction), edge i from corner i to i+1."""
    d = np.roll(q, -1, axis=1) - q
    return q.copy(), d / np.linalg.norm(d, axis=2, keepdims=True)


def _intersect(p: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Corner i = edge i-1 crossed with edge i."""
    pa, da = np.roll(p, 1, axis=1), np.roll(d, 1, axis=1)
    cross = da[..., 0] * d[..., 1] - da[..., 1] * d[..., 0]
    w = p - pa
    t = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / np.where(np.abs(cross) > 1e-9, cross, np.nan)
    return pa + t[..., None] * da


def _bilinear(g: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    H, W = g.shape
    x = np.clip(x, 0.0, W - 1.001)
    y = np.clip(y, 0.0, H - 1.001)
    x0 = x.astype(np.int64)
    y0 = y.astype(np.int64)
    fx, fy = x - x0, y - y0
    flat = g.ravel()
    i = y0 * W + x0
    return ((flat[i] * (1 - fx) + flat[i + 1] * fx) * (1 - fy)
            + (flat[i + W] * (1 - fx) + flat[i + W + 1] * fx) * fy)


def _fit_pass(grey: np.ndarray, q: np.ndarray, camera: tuple[np.ndarray, np.ndarray] | None, coarse: bool,
              check: np.ndarray | None = None, quiet_zone: bool = True
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`_fit_pass_numpy`, compiled (`estimation.edge_kernel`): the same outputs; grey float32."""
    H, W = grey.shape
    N = len(q)
    E = N * 4
    p_in, d_in = _lines_from_corners(_undistort(q, camera))
    geo = edge_kernel.edge_geometry(q, coarse, MIN_REACH_PX, MAX_REACH_PX, COARSE_SEARCH_PX, COARSE_SEARCH_CELLS)
    chk = np.zeros(N, bool) if check is None else np.asarray(check, bool)
    edge_of, pts, row_ok, occluded, lvl_ok = edge_kernel.crossings(grey, q, geo, coarse, chk, quiet_zone, _KERNEL_CONSTS)
    if edge_of.size == 0:   # quads too small for a single row clear of their corners
        return p_in, d_in, np.zeros((N, 4), bool), np.full((N, 4), np.nan), np.zeros((N, 4, 3)), np.zeros((N, 4))
    pts = _undistort(pts, camera, (H, W))
    centroid, theta, fitted, rms, stats, occ = edge_kernel.fit_lines(edge_of, pts, row_ok, occluded, lvl_ok, E,
                                                                     float(MIN_ROWS))
    dr = np.column_stack([np.cos(theta), np.sin(theta)])
    dr *= np.where(np.sum(dr * d_in.reshape(-1, 2), axis=1) < 0, -1.0, 1.0)[:, None]   # keep corner i -> i+1
    fitted = fitted.reshape(N, 4)
    p = np.where(fitted[..., None], centroid.reshape(N, 4, 2), p_in)
    d = np.where(fitted[..., None], dr.reshape(N, 4, 2), d_in)
    return p, d, fitted, np.where(fitted, rms.reshape(N, 4), np.nan), stats.reshape(N, 4, 3), occ.reshape(N, 4)


# the kernel's constants, in the order `edge_kernel.crossings` unpacks them
_KERNEL_CONSTS = np.array([MIN_ROWS, MIN_CONTRAST, OCCLUSION_TOLERANCE, OCCLUSION_NOISE_SIGMAS, OCCLUSION_MIN_CELL_PX,
                           OCCLUSION_ABSOLUTE_MIN_CELL_PX, OCCLUSION_MAX_DROP, OCCLUSION_FAR_PX,
                           OCCLUSION_MIN_CONTRAST, OCCLUSION_GUARD_ROWS, EDGE_LEVELS_MIN_CELL_PX], dtype=np.float64)


def _fit_pass_numpy(grey: np.ndarray, q: np.ndarray, camera: tuple[np.ndarray, np.ndarray] | None, coarse: bool,
                    check: np.ndarray | None = None, quiet_zone: bool = True
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One pass over every edge of every quad: each edge as a line (point, unit direction) in ideal
    pinhole pixels (image pixels without `camera`), whether it was fitted, the rms of its crossings
    about it (px), and its fit's statistics for `_corner_sigma` (N, 4, 3).  `coarse`: find each row's crossing as the steepest dark-to-bright step
    within a wider search (COARSE_SEARCH_PX), to pull in a detector's corner that is pixels off."""
    H, W = grey.shape
    flat = grey.ravel()
    N = len(q)
    E = N * 4
    p_in, d_in = _lines_from_corners(_undistort(q, camera))
    seg = np.roll(q, -1, axis=1) - q                                  # (N, 4, 2)
    length = np.linalg.norm(seg, axis=2)
    u = seg / length[..., None]
    n_out = np.stack([u[..., 1], -u[..., 0]], axis=2)                 # outward: clockwise quads, y down
    # one cell across each edge, measured along the adjacent edges
    prev_seg, next_seg = np.roll(seg, 1, axis=1), np.roll(seg, -1, axis=1)
    cell = np.minimum(np.abs(np.sum(prev_seg * n_out, axis=2)), np.abs(np.sum(next_seg * n_out, axis=2))) / CELLS
    # how far a window reaches across the edge: its end pixels (which see half a pixel farther)
    # must stay clear of the next cell's edge and its blur
    reach = np.clip(cell - 2.5, MIN_REACH_PX, MAX_REACH_PX)
    if coarse:   # the inner pattern's and the quiet zone's edges step the other way: no confusion
        reach = np.clip(COARSE_SEARCH_CELLS * cell, MIN_REACH_PX, COARSE_SEARCH_PX)
    cross2 = lambda a, b: a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]  # noqa: E731
    sin_end = np.maximum(np.minimum(np.abs(cross2(np.roll(u, 1, axis=1), u)), np.abs(cross2(u, np.roll(u, -1, axis=1)))), 0.3)

    rows_axis = np.abs(u[..., 1]) >= np.abs(u[..., 0])                # steep edges: scan image rows
    # scan coordinates: s along the scan (x for rows, y for columns), r the row/column index
    s_idx = np.where(rows_axis, 0, 1)
    r_idx = 1 - s_idx
    take = lambda a, i: np.take_along_axis(a, i[..., None], axis=2)[..., 0]  # noqa: E731
    q1 = np.roll(q, -1, axis=1)
    ps, pr, qs, qr = take(q, s_idx), take(q, r_idx), take(q1, s_idx), take(q1, r_idx)
    ns = take(n_out, s_idx)                                            # normal's scan component, |ns| >= 0.707
    A = reach / np.abs(ns)                                             # window half-width along the scan
    # rows kept clear of the corners: the window's reach, the blur of the adjacent edge, and a
    # little more on long edges (printed corners are rarely sharp)
    margin = (reach + 1.5) / sin_end + 0.02 * length                  # px along the edge
    ur = np.abs(take(u, r_idx))
    r_lo = np.ceil(np.minimum(pr, qr) + margin * ur)
    r_hi = np.floor(np.maximum(pr, qr) - margin * ur)
    count = np.maximum(r_hi - r_lo + 1, 0).astype(np.int64).ravel()
    edge_of = np.repeat(np.arange(E), count)
    if edge_of.size == 0:   # quads too small for a single row clear of their corners
        return p_in, d_in, np.zeros((N, 4), bool), np.full((N, 4), np.nan), np.zeros((N, 4, 3)), np.zeros((N, 4))
    start = np.repeat(np.cumsum(count) - count, count)
    r = r_lo.ravel()[edge_of] + (np.arange(edge_of.size) - start)
    slope = ((qs - ps) / np.where(qr != pr, qr - pr, np.nan)).ravel()
    s_line = ps.ravel()[edge_of] + (r - pr.ravel()[edge_of]) * slope[edge_of]
    Ae = A.ravel()[edge_of]
    sgn = np.sign(ns.ravel())[edge_of]
    centre = np.rint(np.nan_to_num(s_line))
    m_max = int(np.ceil(A.max() + 0.5))
    k = np.arange(-m_max, m_max + 1)
    s_pix = centre[:, None] + k[None, :]                               # (rows, 2 m_max + 1)
    # each pixel's overlap with the window [s_line - A, s_line + A]: a window symmetric about the
    # line, so truncated tails of the blur cancel and the passes converge on the edge
    lo = np.maximum(s_pix - 0.5, (s_line - Ae)[:, None])
    hi = np.minimum(s_pix + 0.5, (s_line + Ae)[:, None])
    wgt = np.clip(hi - lo, 0.0, 1.0)
    use_rows = rows_axis.ravel()[edge_of][:, None]
    ri = r.astype(np.int64)[:, None]
    si = s_pix.astype(np.int64)
    x = np.where(use_rows, si, ri)
    y = np.where(use_rows, ri, si)
    inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
    # a tag touching the frame: the quiet zone is taken to go on past the edge of the image (pixels
    # off the image on the bright side read bright); off the image on the dark side, the row is lost
    bright_side = (s_pix - s_line[:, None]) * sgn[:, None] > 0
    row_ok = np.all(inside | (wgt == 0) | bright_side, axis=1) & np.isfinite(s_line)
    vals = flat[np.clip(y, 0, H - 1) * W + np.clip(x, 0, W - 1)].astype(np.float64)
    # dark and bright levels of each edge: the image at the window's two ends (`reach` from the
    # line along the normal), the median over the edge's rows.  Sampled there rather than deeper
    # into the border and the quiet zone, an edge's levels see nothing the windows do not: a strut
    # or a background over the outer quiet zone cannot bias the crossings through the levels; and
    # for a symmetric blur the two ends sit symmetrically on the edge's profile, so their mid-level
    # is the edge's even where the profile has not flattened out yet.
    n_img = n_out.reshape(-1, 2)[edge_of]
    on_line = np.where(use_rows, np.column_stack([s_line, r]), np.column_stack([r, s_line]))
    reach_e = reach.ravel()[edge_of][:, None]
    p_dark = on_line - reach_e * n_img
    p_bright = on_line + reach_e * n_img
    in_img = lambda p: (p[:, 0] >= 0) & (p[:, 0] <= W - 1) & (p[:, 1] >= 0) & (p[:, 1] <= H - 1)  # noqa: E731
    lvl_ok = in_img(p_dark) & in_img(p_bright) & np.isfinite(s_line)
    v_dark = _bilinear(grey, p_dark[:, 0], p_dark[:, 1])
    v_bright = _bilinear(grey, p_bright[:, 0], p_bright[:, 1])
    # rows where something lies over the window (a strut in front of the tag crossing the edge):
    # left out of the levels and of the fit, with their neighbours
    dark_m, bright_m, bad = _odd_rows(edge_of, v_dark, v_bright, lvl_ok, E)
    chk = np.zeros(E, bool) if check is None else np.repeat(np.asarray(check, bool), 4)
    chk &= cell.ravel() >= OCCLUSION_MIN_CELL_PX
    bad &= chk[edge_of]
    chk &= cell.ravel() >= OCCLUSION_ABSOLUTE_MIN_CELL_PX
    if quiet_zone and chk.any():
        # Something over the quiet zone all along an edge (a strut parallel to it) looks to the test
        # above like a narrow quiet zone, and the windows then reach into it.  Against the tag's own
        # black and white (its cells): an edge whose contrast at the window's ends falls short, or
        # a row whose quiet zone darkens again just past its window, is occluded.  Only where cells
        # are OCCLUSION_ABSOLUTE_MIN_CELL_PX or more: with smaller cells the window's ends lie on
        # the edge's own blur (a clean edge seen obliquely reads 0.8 of the tag's contrast there),
        # and photographed tags' own margins fail these tests (docs/fiducials.md).
        t_dark, t_bright = np.full(N, np.nan), np.full(N, np.nan)
        quads = np.flatnonzero(chk.reshape(N, 4).any(axis=1))
        t_dark[quads], t_bright[quads] = _tag_levels(grey, q[quads])
        c_tag = np.repeat(t_bright - t_dark, 4)
        far = np.minimum(reach + OCCLUSION_FAR_PX, 0.75 * cell).ravel()[edge_of][:, None]
        p_far = on_line + far * n_img
        v_far = _bilinear(grey, p_far[:, 0], p_far[:, 1])
        with np.errstate(invalid="ignore"):
            bad |= chk[edge_of] & lvl_ok & in_img(p_far) & (v_bright - v_far > OCCLUSION_MAX_DROP * c_tag[edge_of])
            short = chk & (bright_m - dark_m < OCCLUSION_MIN_CONTRAST * c_tag)
        bad |= short[edge_of] & lvl_ok
    occluded = _dilate(bad, edge_of, OCCLUSION_GUARD_ROWS)
    n_lvl = np.bincount(edge_of, weights=(lvl_ok & ~occluded).astype(np.float64), minlength=E)
    # small cells put those samples inside the blur of the edge itself, and an edge along the image
    # border has none: such edges take their tag's levels, the two clusters of its cells' centres
    own = (n_lvl >= MIN_ROWS) & (cell.ravel() >= EDGE_LEVELS_MIN_CELL_PX)
    tag_dark, tag_bright = np.full(N, np.nan), np.full(N, np.nan)
    need = ~own.reshape(N, 4).all(axis=1)
    if need.any():
        tag_dark[need], tag_bright[need] = _tag_levels(grey, q[need])
    dark = np.where(own, dark_m, np.repeat(tag_dark, 4))
    bright = np.where(own, bright_m, np.repeat(tag_bright, 4))
    contrast = bright - dark
    with np.errstate(invalid="ignore", divide="ignore"):
        # an edge without contrast gives NaN, never inf (its rows are dropped below)
        fn = (vals - dark[edge_of, None]) / np.where(contrast > 0, contrast, np.nan)[edge_of, None]
        fn = np.where(inside, fn, 1.0)
    if coarse:
        step = sgn[:, None] * np.diff(fn, axis=1)                      # dark-to-bright steps, at k + 0.5
        step = np.where((wgt[:, 1:] > 0) & (wgt[:, :-1] > 0), step, -np.inf)
        j = np.clip(np.argmax(step, axis=1), 1, step.shape[1] - 2)
        rows_i = np.arange(len(j))
        y0, y1, y2 = step[rows_i, j - 1], step[rows_i, j], step[rows_i, j + 1]
        y0 = np.where(np.isfinite(y0), y0, y1)
        y2 = np.where(np.isfinite(y2), y2, y1)
        den = y0 - 2 * y1 + y2
        frac = np.where(den < -1e-9, 0.5 * (y0 - y2) / np.where(den < -1e-9, den, 1.0), 0.0)
        cross = s_pix[rows_i, j] + 0.5 + np.clip(frac, -0.5, 0.5)
        row_ok &= y1 >= 0.25
    else:
        bright_len = np.sum(wgt * fn, axis=1)                          # px of the window on the bright side
        cross = np.where(sgn > 0, s_line + Ae - bright_len, s_line - Ae + bright_len)
    row_ok &= np.abs(cross - s_line) <= Ae                             # the crossing lies within its window
    row_ok &= (contrast >= MIN_CONTRAST)[edge_of]
    row_ok &= ~occluded

    # the crossings as image points, then straight lines through them where straight lines are
    # straight: in the ideal pinhole image when the lens is known
    pts = np.where(use_rows, np.column_stack([cross, r]), np.column_stack([r, cross]))
    pts = _undistort(np.nan_to_num(pts), camera, (H, W))
    X, Y = pts[:, 0], pts[:, 1]
    keep = row_ok.copy()
    for _ in range(2):                                                 # fit, drop crossings > 3 rms off, refit
        w = keep.astype(np.float64)
        S1 = np.bincount(edge_of, w, E)
        fitted = S1 >= MIN_ROWS
        S1 = np.maximum(S1, 1.0)
        mx = np.bincount(edge_of, w * X, E) / S1
        my = np.bincount(edge_of, w * Y, E) / S1
        dx, dy = X - mx[edge_of], Y - my[edge_of]
        cxx = np.bincount(edge_of, w * dx * dx, E)
        cxy = np.bincount(edge_of, w * dx * dy, E)
        cyy = np.bincount(edge_of, w * dy * dy, E)
        theta = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)                 # the line's direction (total least squares)
        res = -dx * np.sin(theta)[edge_of] + dy * np.cos(theta)[edge_of]
        rms = np.sqrt(np.bincount(edge_of, w * res * res, E) / S1)
        keep = row_ok & (np.abs(res) <= np.maximum(3.0 * rms[edge_of], 0.1))
    pt = np.column_stack([mx, my])
    dr = np.column_stack([np.cos(theta), np.sin(theta)])
    dr *= np.where(np.sum(dr * d_in.reshape(-1, 2), axis=1) < 0, -1.0, 1.0)[:, None]   # keep corner i -> i+1
    fitted = fitted.reshape(N, 4)
    p = np.where(fitted[..., None], pt.reshape(N, 4, 2), p_in)
    d = np.where(fitted[..., None], dr.reshape(N, 4, 2), d_in)
    # the fitted line's standard error at distance T from its centroid is r sqrt(1/n + T^2 / (n var_t))
    # (r: the crossings' scatter with 2 dof spent, var_t: their spread along the line)
    t_along = dx * np.cos(theta)[edge_of] + dy * np.sin(theta)[edge_of]
    var_t = np.bincount(edge_of, w * t_along * t_along, E) / S1
    n = np.bincount(edge_of, w, E)
    r_eff = np.maximum(rms * np.sqrt(n / np.maximum(n - 2, 1)), 0.02)
    stats = np.stack([r_eff, n, var_t], axis=1).reshape(N, 4, 3)
    n_rows = np.bincount(edge_of, lvl_ok, E)
    occ_frac = np.bincount(edge_of, occluded & lvl_ok, E) / np.maximum(n_rows, 1)
    return p, d, fitted, np.where(fitted, rms.reshape(N, 4), np.nan), stats, occ_frac.reshape(N, 4)


def _odd_rows(edge_of: np.ndarray, v_dark: np.ndarray, v_bright: np.ndarray, ok: np.ndarray,
              n_edges: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each edge's median dark and bright samples (over its rows with both in the image; NaN for
    fewer than MIN_ROWS), and its rows whose samples differ from those medians by more than
    OCCLUSION_TOLERANCE of the contrast, or OCCLUSION_NOISE_SIGMAS of the edge's own spread if
    that is more: something in front of the tag (or a stain, a shadow's edge) crosses the edge
    there."""
    R = len(edge_of)
    cnt = np.bincount(edge_of, ok, n_edges).astype(np.int64)
    rows = np.bincount(edge_of, minlength=n_edges)
    start = np.cumsum(rows) - rows

    def median(v: np.ndarray) -> np.ndarray:
        if R == 0:
            return np.full(n_edges, np.nan)
        # per edge (edge_of is sorted): its usable rows first, by value.  One argsort of a single
        # key, each edge's values shifted into a band of its own and the unusable rows past them,
        # is ~20x faster than a three-key lexsort; the values are grey levels, so the shift costs
        # at most ~1e-10 of a grey level of resolution (ties that close may swap)
        use = ok & np.isfinite(v)      # NaN only on edges without a median (fewer than MIN_ROWS rows)
        k = np.where(use, v, 0.0)
        lo = float(k.min())
        span = float(k.max()) - lo + 1.0
        order = np.argsort(np.where(use, k - lo, span) + edge_of * (2.0 * span), kind="stable")
        m = v[order[np.clip(start + np.maximum(cnt - 1, 0) // 2, 0, R - 1)]]
        return np.where(cnt >= MIN_ROWS, m, np.nan)

    dark_m, bright_m = median(v_dark), median(v_bright)
    if R == 0:
        return dark_m, bright_m, np.zeros(0, bool)
    tol = OCCLUSION_TOLERANCE * (bright_m - dark_m)
    bad = np.zeros(R, bool)
    with np.errstate(invalid="ignore"):
        for v, m in ((v_dark, dark_m), (v_bright, bright_m)):
            dev = np.abs(v - m[edge_of])
            spread = 1.4826 * median(np.where(ok, dev, 0.0))
            t = np.fmax(tol, OCCLUSION_NOISE_SIGMAS * spread)[edge_of]
            bad |= ok & (tol[edge_of] > 0) & (dev > t)
    return dark_m, bright_m, bad


def _dilate(bad: np.ndarray, edge_of: np.ndarray, k_max: int) -> np.ndarray:
    """`bad` rows and the `k_max` rows either side of each on the same edge (an occluder's blurred
    outline reaches past the rows it covers)."""
    out = bad.copy()
    for k in range(1, min(k_max, len(bad) - 1) + 1):
        same = edge_of[k:] == edge_of[:-k]
        out[:-k] |= bad[k:] & same
        out[k:] |= bad[:-k] & same
    return out


def _corner_sigma(p: np.ndarray, d: np.ndarray, corners: np.ndarray, stats: np.ndarray) -> np.ndarray:
    """(N, 4) standard error of each corner: its two lines' errors at the corner, over the sine of
    the angle between them."""
    r, n, var_t = stats[..., 0], np.maximum(stats[..., 1], 1), np.maximum(stats[..., 2], 1e-9)

    idx = np.arange(4)
    prev = (idx - 1) % 4
    s_this = r * np.sqrt(1.0 / n + np.sum((corners - p) * d, axis=-1) ** 2 / (n * var_t))
    s_prev = (r[:, prev] * np.sqrt(1.0 / n[:, prev] + np.sum((corners - p[:, prev]) * d[:, prev], axis=-1) ** 2
                                   / (n[:, prev] * var_t[:, prev])))
    sin = np.abs(d[:, prev, 0] * d[..., 1] - d[:, prev, 1] * d[..., 0])
    return np.sqrt(s_this ** 2 + s_prev ** 2) / np.maximum(sin, 0.2)


@lru_cache(maxsize=4)
def _undistort_map(K_key: bytes, dist_key: bytes, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Ideal pinhole x and y of every pixel centre of a (height, width) image, each flattened:
    interpolating them is faster than undistorting each point and exact to ~1e-5 px."""
    K = np.frombuffer(K_key, dtype=np.float64).reshape(3, 3)
    dist = np.frombuffer(dist_key, dtype=np.float64)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    out = cv2.undistortPointsIter(pix, K, dist, None, K, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9))
    out = out.reshape(-1, 2)
    return np.ascontiguousarray(out[:, 0]), np.ascontiguousarray(out[:, 1])


def _undistort(pts: np.ndarray, camera: tuple[np.ndarray, np.ndarray] | None,
               shape: tuple[int, int] | None = None) -> np.ndarray:
    """Image pixels -> ideal pinhole pixels of the same camera (unchanged without a camera).  With
    the image's `shape`, through the cached map of the whole frame."""
    if camera is None or not np.any(camera[1]) or np.size(pts) == 0:
        return np.asarray(pts, dtype=np.float64)
    K, dist = camera
    K = np.ascontiguousarray(K, dtype=np.float64)
    dist = np.ascontiguousarray(dist, dtype=np.float64).ravel()
    p = np.asarray(pts, np.float64).reshape(-1, 2)
    if shape is not None:
        H, W = shape
        inside = (p[:, 0] >= 0) & (p[:, 0] <= W - 1) & (p[:, 1] >= 0) & (p[:, 1] <= H - 1)
        if inside.all():
            mx, my = _undistort_map(K.tobytes(), dist.tobytes(), W, H)
            x0 = np.minimum(p[:, 0].astype(np.int64), W - 2)
            y0 = np.minimum(p[:, 1].astype(np.int64), H - 2)
            fx = p[:, 0] - x0
            fy = p[:, 1] - y0
            i = y0 * W + x0
            out = np.empty_like(p)
            for c, m in enumerate((mx, my)):
                a, b = np.take(m, i), np.take(m, i + 1)
                cc, d = np.take(m, i + W), np.take(m, i + W + 1)
                out[:, c] = (a + (b - a) * fx) * (1 - fy) + (cc + (d - cc) * fx) * fy
            return out.reshape(np.shape(pts))
    out = cv2.undistortPointsIter(p.reshape(-1, 1, 2), K, dist, None, K,
                                  (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9))
    return out.reshape(np.shape(pts))


def _distort(pts: np.ndarray, camera: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """Ideal pinhole pixels -> image pixels."""
    if camera is None or not np.any(camera[1]) or pts.size == 0:
        return pts
    K, dist = camera
    shape = pts.shape
    xy = (np.asarray(pts, np.float64).reshape(-1, 2) - K[:2, 2]) / np.diag(K)[:2]
    obj = np.column_stack([xy, np.ones(len(xy))])
    out, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, dist)
    return out.reshape(shape)


def fit_quads(grey: np.ndarray, quads: np.ndarray, camera: tuple[np.ndarray, np.ndarray] | None = None,
              passes: int = 3, quiet_zone: bool = True) -> QuadFit:
    """Refine the quads (N, 4, 2; corners clockwise in the image as aruco returns them) of tags in a
    grey image (2-D, any numeric type) by fitting each edge: a coarse pass first for small tags
    (their windows are too short to pull in a corner a pixel or two off), then up to `passes` fine
    ones, until no corner moves more than CONVERGED_PX; see the module's docstring.  With
    `camera` = (K, dist) the edges are fitted as straight lines in the undistorted image (lens
    distortion bends them by tenths of a pixel over a near tag).  Rows an occluder crosses are left
    out (`QuadFit.occluded`); `quiet_zone`: the tags have a clear one-cell quiet zone, so an edge
    whose quiet zone reads short of the tag's white is occluded too (not for tags printed with
    less margin)."""
    q = np.asarray(quads, dtype=np.float64).reshape(-1, 4, 2)
    g = np.ascontiguousarray(grey, dtype=np.float32)
    N = len(q)
    rms = np.full((N, 4), np.nan)
    sigma = np.full((N, 4), np.nan)
    occluded = np.zeros((N, 4))
    fitted_any = np.zeros((N, 4), bool)
    cur = q.copy()
    side = np.linalg.norm(np.roll(q, -1, axis=1) - q, axis=2).min(axis=1) if N else np.zeros(0)
    coarse_first = side / CELLS < COARSE_BELOW_CELL_PX
    active = np.ones(N, bool)
    lost = np.zeros(N, bool)

    def step(idx: np.ndarray, coarse: bool, check: np.ndarray | None = None) -> np.ndarray:
        """One pass over the quads `idx`; how far each one's corners moved."""
        p, d, fitted, rms_pass, stats, occ_pass = _fit_pass(g, cur[idx], camera, coarse, check, quiet_zone)
        occluded[idx] = occ_pass
        rms[idx] = np.where(fitted, rms_pass, rms[idx])
        fitted_any[idx] |= fitted
        ideal = _intersect(p, d)
        nxt = _distort(ideal, camera)
        meet = np.all(np.isfinite(nxt), axis=(1, 2))      # lines that no longer meet: keep the quad
        nxt = np.where(meet[:, None, None], nxt, cur[idx])
        all_fit = fitted.all(axis=1) & meet
        s = np.full(fitted.shape, np.nan)
        s[all_fit] = _corner_sigma(p[all_fit], d[all_fit], ideal[all_fit], stats[all_fit])
        sigma[idx] = s
        # a quad whose lines run away from where it started (a blurred, noisy or hidden tag whose
        # edges lose their rows) would grow with every pass, and with it the rows read along its
        # edges, to gigabytes: it keeps its last quad and is reported not fitted
        away = np.max(np.linalg.norm(nxt - q[idx], axis=2), axis=1) > np.maximum(MAX_DRIFT_PX, MAX_DRIFT_SIDES * side[idx])
        nxt[away] = cur[idx][away]
        fitted_any[idx[away]] = False
        lost[idx[away]] = True
        moved = np.where(away, 0.0, np.max(np.linalg.norm(nxt - cur[idx], axis=2), axis=1))
        cur[idx] = nxt
        return moved

    if coarse_first.any():
        step(np.flatnonzero(coarse_first), True)
    # rows crossed by an occluder are looked for from the second fine pass on, once the windows sit
    # on the edges (before that a line pixels off makes every row look odd): a quad converged in its
    # first pass gets a second one
    checked = np.zeros(N, bool)
    for _ in range(max(passes, 2)):
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        check = checked[idx].copy()
        moved = step(idx, False, check)
        checked[idx] = True
        active &= ~lost
        active[idx[(moved < CONVERGED_PX) & check]] = False   # converged: the fine pass contracts the error 10-1000x
    fitted = fitted_any & ~lost[:, None]
    return QuadFit(cur, fitted, rms, sigma, occluded)


@lru_cache(maxsize=4)
def code_bits(family: str = BASE) -> np.ndarray:
    """(n_ids, 8, 8) bool: every code of a tag family (`estimation.tag_family`) as printed, border
    included, True where the cell is white, in the dictionary's own orientation (corner 0 at
    top-left)."""
    d = dictionary(family)
    n = d.bytesList.shape[0]
    side = d.markerSize + 2
    return np.stack([cv2.aruco.generateImageMarker(d, i, side, borderBits=1) > 127 for i in range(n)])


def _unit_square_to_quads(q: np.ndarray, uv1: np.ndarray) -> np.ndarray:
    """Points (P, 3: u, v, 1) of the unit square mapped into every quad (N, 4, 2) by the homography
    taking its corners (0,0), (1,0), (1,1), (0,1) to the quad's (`edge_kernel.square_to_quad`, the
    one the compiled edge fit samples tags through): (N, P, 2)."""
    h = edge_kernel.squares_to_quads(np.ascontiguousarray(q, dtype=np.float64))[:, :, None]
    u, v = uv1[None, :, 0], uv1[None, :, 1]
    with np.errstate(divide="ignore", invalid="ignore"):     # a degenerate quad maps to nan
        X = h[:, 0] * u + h[:, 1] * v + h[:, 2]
        Y = h[:, 3] * u + h[:, 4] * v + h[:, 5]
        Z = h[:, 6] * u + h[:, 7] * v + 1.0
        return np.stack([X / Z, Y / Z], axis=2)


def _grid_samples(grey: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """(N, 10, 10) grey levels at the cell centres of each quad's 8x8 cells and of the ring of
    quiet-zone cells around them (corner 0 = the marker's top-left, row by row), bilinear."""
    q = np.asarray(quads, dtype=np.float64).reshape(-1, 4, 2)
    n = CELLS + 2
    c = (np.arange(-1, CELLS + 1) + 0.5) / CELLS
    gu, gv = np.meshgrid(c, c)                                         # u right, v down
    uv1 = np.column_stack([gu.ravel(), gv.ravel(), np.ones(n * n)])
    pts = _unit_square_to_quads(q, uv1)
    return _bilinear(np.asarray(grey, dtype=np.float32), pts[..., 0], pts[..., 1]).reshape(len(q), n, n)


def _cell_samples(grey: np.ndarray, quads: np.ndarray, sharpen: float = 0.0) -> np.ndarray:
    """(N, 64) grey levels at the 8x8 cell centres of each quad (corner 0 = the marker's top-left,
    row by row).  `sharpen` > 0 subtracts that much of each sample's Laplacian over the grid,
    undoing some of the blur that mixes neighbouring cells on small tags, as the AprilTag library's
    decode_sharpening does."""
    v = _grid_samples(grey, quads)
    if sharpen > 0:
        lap = 4 * v[:, 1:-1, 1:-1] - v[:, :-2, 1:-1] - v[:, 2:, 1:-1] - v[:, 1:-1, :-2] - v[:, 1:-1, 2:]
        return (v[:, 1:-1, 1:-1] + sharpen * lap).reshape(len(v), -1)
    return v[:, 1:-1, 1:-1].reshape(len(v), -1)


@lru_cache(maxsize=1)
def _ring_models() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares planes over the 10x10 grid: (black ring index, its pseudo-inverse, white ring
    index, its pseudo-inverse, the 8x8 cells' design) for a + b u + c v fitted to the black border
    cells and to the white quiet-zone cells."""
    n = CELLS + 2
    i, j = np.meshgrid(np.arange(n), np.arange(n))
    design = np.column_stack([np.ones(n * n), i.ravel() - n / 2, j.ravel() - n / 2])
    ring = (i == 0) | (j == 0) | (i == n - 1) | (j == n - 1)
    border = ((i == 1) | (j == 1) | (i == n - 2) | (j == n - 2)) & ~ring
    inner = ~ring
    white_idx, black_idx = np.flatnonzero(ring.ravel()), np.flatnonzero(border.ravel())
    return (black_idx, np.linalg.pinv(design[black_idx]), white_idx, np.linalg.pinv(design[white_idx]),
            design[np.flatnonzero(inner.ravel())])


def _otsu(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of `v`: (threshold, dark cluster mean, bright cluster mean), the split maximising
    the between-cluster variance."""
    n = v.shape[1]
    srt = np.sort(v, axis=1)
    k = np.arange(1, n)
    csum = np.cumsum(srt, axis=1)[:, :-1]
    total = csum[:, -1:] + srt[:, -1:]
    m0 = csum / k
    m1 = (total - csum) / (n - k)
    best = np.argmax(k * (n - k) * (m1 - m0) ** 2, axis=1)
    i = np.arange(len(v))
    return 0.5 * (srt[i, best] + srt[i, best + 1]), m0[i, best], m1[i, best]


def _tag_levels(grey: np.ndarray, quads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each tag's black and white: the means of the dark and bright clusters of its cell centres."""
    if len(quads) == 0:
        return np.zeros(0), np.zeros(0)
    _, dark, bright = _otsu(_cell_samples(grey, quads))
    return dark, bright


def read_bits(grey: np.ndarray, quads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample the 8x8 cells of each quad (N, 4, 2; corner 0 = the marker's top-left) at their
    centres, sharpened (SHARPEN), and threshold each halfway between a plane fitted to the black
    border cells and one fitted to the white quiet-zone cells around them (the AprilTag library's
    way: light falls unevenly across a tag); where the quiet zone does not read white (no margin,
    off the image), halfway between the 64 cells' own dark and bright clusters.  Returns (bits
    (N, 8, 8) bool, True = white; contrast (N,) grey levels between black and white)."""
    q = np.asarray(quads, dtype=np.float64).reshape(-1, 4, 2)
    N = len(q)
    if N == 0:
        return np.zeros((0, CELLS, CELLS), bool), np.zeros(0)
    grid = _grid_samples(grey, q)
    lap = 4 * grid[:, 1:-1, 1:-1] - grid[:, :-2, 1:-1] - grid[:, 2:, 1:-1] - grid[:, 1:-1, :-2] - grid[:, 1:-1, 2:]
    v = (grid[:, 1:-1, 1:-1] + SHARPEN * lap).reshape(N, -1)
    black_idx, black_pinv, white_idx, white_pinv, inner = _ring_models()
    flat = grid.reshape(N, -1)
    black = (flat[:, black_idx] @ black_pinv.T) @ inner.T              # (N, 64) modelled black
    white = (flat[:, white_idx] @ white_pinv.T) @ inner.T
    thr_model = 0.5 * (black + white)
    thr_otsu, dark, bright = _otsu(v)
    ring_ok = (flat[:, white_idx].mean(axis=1) - flat[:, black_idx].mean(axis=1)) > 0.5 * (bright - dark)
    thr = np.where(ring_ok[:, None], thr_model, thr_otsu[:, None])
    return (v > thr).reshape(N, CELLS, CELLS), bright - dark


def identify(grey: np.ndarray, quads: np.ndarray, codes: np.ndarray, allowed: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which marker each quad (N, 4, 2; clockwise, any starting corner) shows: its cells read with
    each of the four corners as the top-left, against the patterns `codes` (n_ids, 8, 8) of the ids
    in `allowed`.  Returns (id, corners rolled so corner 0 is the marker's top-left, cells that
    disagree with that id's pattern, of 64)."""
    q = np.asarray(quads, dtype=np.float64).reshape(-1, 4, 2)
    N = len(q)
    allowed = np.asarray(allowed, dtype=np.int64)
    if N == 0 or allowed.size == 0:
        return np.zeros(N, np.int64), q, np.full(N, CELLS * CELLS)
    weights = (np.uint64(1) << np.arange(CELLS * CELLS, dtype=np.uint64))
    packed = (codes[allowed].reshape(len(allowed), -1).astype(np.uint64) * weights).sum(axis=1)
    best_err = np.full(N, CELLS * CELLS + 1)
    best_id = np.zeros(N, np.int64)
    best_q = q.copy()
    for r in range(4):
        qr = np.roll(q, -r, axis=1)
        bits, _ = read_bits(grey, qr)
        word = (bits.reshape(N, -1).astype(np.uint64) * weights).sum(axis=1)
        err = np.bitwise_count(word[:, None] ^ packed[None, :])          # (N, n_allowed)
        j = np.argmin(err, axis=1)
        e = err[np.arange(N), j]
        better = e < best_err
        best_err = np.where(better, e, best_err)
        best_id = np.where(better, allowed[j], best_id)
        best_q[better] = qr[better]
    return best_id, best_q, best_err


@lru_cache(maxsize=1)
def _ring_points() -> tuple[np.ndarray, ...]:
    """Unit-square points (u right, v down; the black square is 0..1) a quarter cell apart along
    the black border and along the quiet zone, at RING_DEPTHS_CELLS from the black square's edge
    (inwards for the border, outwards for the quiet zone), and for each: whether it is a quiet-zone
    point, the side it samples (0 top, 1 right, 2 bottom, 3 left: edge i runs from corner i to
    corner i + 1), its distance (cells) from the nearer edge of its ring cell across the side, the
    side whose edge is nearest along it (at the corner it is closer to) and its distance (cells)
    from that: the black square's edge for a border point, inf for a quiet-zone point.

    The quiet zone's run stops at the black square's corners: the four quiet cells diagonally
    beyond them are not sampled.  No edge's fit reads them, and a strut across one alone leaves
    the corners where they are (rendered, a strut's edge 0.65 cell from the black corner: 0.009-
    0.025 px, as without it; random struts about the tag, 1400 scenes on the old and default
    cameras and 700 on the poor one: 26 more tags kept, none more than 0.1 px off because of the
    strut that was not so without this); sampling them dropped such tags: a deployable's bottom
    tag at N = 7, clean but for a strut across that cell, was dropped in 11 of 12 views and its
    module left `uncertain` at a 1σ of 14 mm."""
    pts, quiet, side, margin, adj, along = [], [], [], [], [], []
    for outward, sign in ((False, -1.0), (True, 1.0)):
        for depth in RING_DEPTHS_CELLS:
            off = sign * depth / CELLS                        # from the edge, in unit-square units
            reach = (CELLS / 2 + (depth if outward else -depth)) / CELLS
            s = np.arange(-reach, reach + 1e-9, 0.25 / CELLS) + 0.5
            t = np.abs(s - 0.5) * CELLS                      # cells from the side's middle
            if outward:
                s, t = s[t <= CELLS / 2], t[t <= CELLS / 2]  # not past the corners (above)
            for e in range(4):   # top (v = 0), right (u = 1), bottom (v = 1), left (u = 0)
                line = np.full_like(s, (0.0, 1.0, 1.0, 0.0)[e] + (-off, off, off, -off)[e])
                uv = np.column_stack([s, line]) if e in (0, 2) else np.column_stack([line, s])
                pts.append(uv)
                quiet.append(np.full(len(s), outward))
                side.append(np.full(len(s), e))
                margin.append(np.full(len(s), min(depth, 1.0 - depth)))
                adj.append(np.where(s < 0.5, 3, 1) if e in (0, 2) else np.where(s < 0.5, 0, 2))
                along.append(np.full(len(s), np.inf) if outward else CELLS / 2 - t)
    p = np.concatenate(pts)
    return (np.column_stack([p, np.ones(len(p))]), np.concatenate(quiet), np.concatenate(side),
            np.concatenate(margin), np.concatenate(adj), np.concatenate(along))


def edge_blur_px(grey: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Each tag's edge blur (N,): the sigma (px) of the Gaussian edge whose contrast across its
    black square's edges at +-EDGE_BLUR_NEAR_PX is the share it is at +-r of the contrast at
    +-r, r = one cell less 2.5 px (1 to 2.5 px: clear of the next cell's edge), the medians over
    nine points along the middle half of each side.  The lens's blur, the pixel's area and the
    bilinear sampling together, as the ring's samples see them: 0.65-0.9 px on the sim's default
    frames (lens blur 0.6 px), 1.4-1.7 px with a 1.6 px lens.  Noise and a nearer cell edge bias
    it little; it is a scale for the checks, not a measurement."""
    q = np.asarray(quads, dtype=np.float64).reshape(-1, 4, 2)
    N = len(q)
    if N == 0:
        return np.zeros(0)
    g = np.asarray(grey, dtype=np.float32)
    seg = np.roll(q, -1, axis=1) - q
    u = seg / np.maximum(np.linalg.norm(seg, axis=2, keepdims=True), 1e-9)
    n_out = np.stack([u[..., 1], -u[..., 0]], axis=2)
    cell = np.minimum(np.abs(np.sum(np.roll(seg, 1, axis=1) * n_out, axis=2)),
                      np.abs(np.sum(np.roll(seg, -1, axis=1) * n_out, axis=2))).min(axis=1) / CELLS
    far = np.clip(cell - 2.5, MIN_REACH_PX, MAX_REACH_PX)                       # (N,)
    t = np.linspace(0.25, 0.75, 9)
    on = q[:, :, None, :] + t[None, None, :, None] * seg[:, :, None, :]        # (N, 4, 9, 2)
    normal = n_out[:, :, None, :]

    def across(r) -> np.ndarray:
        a, b = on + r * normal, on - r * normal
        va = _bilinear(g, a[..., 0].ravel(), a[..., 1].ravel())
        vb = _bilinear(g, b[..., 0].ravel(), b[..., 1].ravel())
        return np.median((va - vb).reshape(N, -1), axis=1)

    near_c = across(EDGE_BLUR_NEAR_PX)
    far_c = across(far[:, None, None, None])
    share = np.clip(near_c / np.maximum(far_c, 1e-6), 0.0, 1.0)
    # (2 Phi(near / s) - 1) / (2 Phi(far / s) - 1) = share, decreasing in s: bisect on log s
    lo, hi = np.full(N, math.log(0.1)), np.full(N, math.log(10.0))
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        s = np.exp(mid)
        f = (2 * ndtr(EDGE_BLUR_NEAR_PX / s) - 1) / (2 * ndtr(far / s) - 1)
        lo, hi = np.where(f > share, mid, lo), np.where(f > share, hi, mid)
    return np.exp(0.5 * (lo + hi))


def ring_deviation(grey: np.ndarray, quads: np.ndarray, blur_px: np.ndarray | None = None) -> np.ndarray:
    """How far each tag's black border and white quiet zone stray from its own black and white,
    along the whole perimeter (N,): the largest shortfall of a sample, as a fraction of the
    tag's contrast (the two clusters of its 64 cells' centres).  A clean tag reads ~0; something
    in front of it crossing the border or the quiet zone (a strut), a quiet zone narrower than a
    cell or a shadow's edge reads more.  Points a quarter cell apart along the ring, at
    RING_DEPTHS_CELLS from the black square's edge on either side, those in the image (a tag may
    run off the frame) and at least RING_MIN_EDGE_PX, or RING_MIN_EDGE_SIGMAS of the tag's edge
    blur (`edge_blur_px`) if that is more, from every edge of their ring cell (on a small tag, one
    seen very obliquely or through a blurred lens, the blur of a cell's edges meets in its middle);
    quads (N, 4, 2), corner 0 the marker's top-left; `blur_px`: their `edge_blur_px` if the caller
    has it already."""
    q = np.asarray(quads, dtype=np.float64).reshape(-1, 4, 2)
    if len(q) == 0:
        return np.zeros(0)
    uv1, quiet, side, margin, adj, along = _ring_points()
    pts = _unit_square_to_quads(q, uv1)
    H, W = np.shape(grey)
    v = _bilinear(np.asarray(grey, dtype=np.float32), pts[..., 0], pts[..., 1])
    inside = (pts[..., 0] >= 0) & (pts[..., 0] <= W - 1) & (pts[..., 1] >= 0) & (pts[..., 1] <= H - 1)
    # each side's cell across it: the adjacent sides' extent along its normal, over 8
    seg = np.roll(q, -1, axis=1) - q
    u = seg / np.linalg.norm(seg, axis=2, keepdims=True)
    n_out = np.stack([u[..., 1], -u[..., 0]], axis=2)
    across = np.minimum(np.abs(np.sum(np.roll(seg, 1, axis=1) * n_out, axis=2)),
                        np.abs(np.sum(np.roll(seg, -1, axis=1) * n_out, axis=2))) / CELLS     # (N, 4)
    blur = edge_blur_px(grey, q) if blur_px is None else np.asarray(blur_px, dtype=np.float64)
    clear = np.maximum(RING_MIN_EDGE_PX, RING_MIN_EDGE_SIGMAS * blur)[:, None]   # (N, 1)
    inside &= (across[:, side] * margin[None, :] >= clear) & (across[:, adj] * along[None, :] >= clear)
    dark, bright = _tag_levels(grey, q)
    contrast = np.maximum(bright - dark, 1e-6)[:, None]
    short = np.where(quiet[None, :], bright[:, None] - v, v - dark[:, None]) / contrast
    return np.where(inside, short, -np.inf).max(axis=1, initial=0.0)
