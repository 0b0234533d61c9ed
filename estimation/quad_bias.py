"""The edge fit's own bias under a blur comparable to a tag's cells, measured on a model of the tag
and taken off its corners.

Why.  `tag_quads.fit_quads` locates an edge without a model of the blur, from windows that must
reach across the edge's blur but stay clear of the next cells' edges.  When the blur is a good part
of a cell (a 1.6 px lens, 4-5 px cells at 3 m) that is impossible: the inner pattern's edges and
the quiet zone's outer edge leak into the windows and into the dark and bright levels, the windows
are too short for the passes to converge, and the black square reads 0.05-0.2 px small, the same
way in every sighting of the tag at that distance.  Residuals cannot show such an error, so the
graph's 1sigma would not cover it.

How.  The tag is drawn as the camera would see it with the corners exactly where the fit put them:
its pattern (known once the tag is identified), its quiet zone and the background past it at the
levels measured around it, integrated over each pixel's area and blurred by a Gaussian whose sigma
makes the model's edges read as blurred as the photograph's (`tag_quads.edge_blur_px` on both,
matched in quadrature).  The same fit, from the same starting quad, run on the model reads it off
by the fit's bias at that size, blur and pattern; the corners less that bias are the estimate
(one parametric-bootstrap step: the bias varies little over the tenths of a pixel it corrects).

What the model leaves out: lens distortion across the tag (the model's edges are straight in the
image; the fit's are straight in the undistorted image, a difference of tenths of a pixel at most
over a near tag, whose cells are large enough to need no correction), light varying across the tag,
a lens whose blur is not Gaussian, and anything in front of the tag.  Tags whose cells keep the
windows clear of the next edges' blur (`needs_correction`) are left as fitted.
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np

from estimation.tag_quads import CELLS, MAX_REACH_PX, MIN_REACH_PX, _bilinear, edge_blur_px, fit_quads

__all__ = ["needs_correction", "blur_bias"]

SUPERSAMPLE = 4          # sub-pixels per pixel, each way
MARGIN_CELLS = 1         # background drawn past the quiet zone
# Tags are left as fitted where the fit's bias is under ~0.01 px: windows ending CLEAR_SIGMAS of the
# apparent blur clear of the next edge and reaching CONVERGE_SIGMAS of it across their own (a model
# fitted to a noisy patch adds a few thousandths of a pixel of its own)
CLEAR_SIGMAS = 3.0
CONVERGE_SIGMAS = 2.0
BACKGROUND_CELLS = 2.0   # the background level is read this far out from the black square (1 cell past the quiet zone)
SIGMA_RANGE = (0.7, 1.3)  # the blur is searched over these multiples of the edge's apparent blur ...
SIGMA_STEPS = 5           # ... at this many points, then a parabola through the best three
SIGMA_REFINE = 0.08       # a later round: three points this far either side of the sigma found
FIT_CELLS = 1.5           # levels and blur are fitted on pixels within this many cells of the black square
MIN_SIGMA_PX = 0.05
# The model must be the tag in the photograph: its pixels within FIT_CELLS of the black square
# matched to MAX_MISFIT of the contrast (rms; noise 8 and JPEG 70 leave ~0.05), and the bias it
# finds no more than MAX_BIAS_CELLS of a cell (0.55 px at most on 3.8 px cells under a 1.6 px blur;
# the first round's, drawn at the biased corners, is larger)
MAX_MISFIT = 0.15
MAX_BIAS_CELLS = 0.25


def _cell_px(q: np.ndarray) -> np.ndarray:
    """Each quad's smallest cell size (px) across its edges."""
    seg = np.roll(q, -1, axis=1) - q
    return np.linalg.norm(seg, axis=2).min(axis=1) / CELLS


def needs_correction(quads: np.ndarray, blur_px: np.ndarray) -> np.ndarray:
    """Tags whose edge windows end within CLEAR_SIGMAS of their apparent blur (`edge_blur_px`) from
    the next cells' edges, or reach less than CONVERGE_SIGMAS of it across their own edge (each
    fine pass then contracts a corner's error only ~0.3x, and the passes stop short)."""
    cell = _cell_px(quads)
    reach = np.clip(cell - 2.5, MIN_REACH_PX, MAX_REACH_PX)      # fit_quads' window half-width
    blur = np.asarray(blur_px)
    return ((cell - reach) < CLEAR_SIGMAS * blur) | (reach < CONVERGE_SIGMAS * blur)


def _background(grey: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """The level past each tag's quiet zone: the median of points BACKGROUND_CELLS out from the
    black square, a quarter cell apart all round."""
    N = len(quads)
    off = BACKGROUND_CELLS / CELLS
    s = np.arange(-off, 1 + off + 1e-9, 0.25 / CELLS)
    lo, hi = np.full_like(s, -off), np.full_like(s, 1 + off)
    uv = np.concatenate([np.column_stack([s, lo]), np.column_stack([s, hi]),
                         np.column_stack([lo, s]), np.column_stack([hi, s])])
    out = np.empty(N)
    for k in range(N):
        Hm = cv2.getPerspectiveTransform(np.float32([[0, 0], [1, 0], [1, 1], [0, 1]]), np.float32(quads[k]))
        p = cv2.perspectiveTransform(uv[None].astype(np.float64), Hm)[0]
        inside = (p[:, 0] >= 0) & (p[:, 1] >= 0) & (p[:, 0] <= grey.shape[1] - 1) & (p[:, 1] <= grey.shape[0] - 1)
        out[k] = np.median(_bilinear(grey, p[inside, 0], p[inside, 1])) if inside.any() else np.nan
    return out


def _bases(shape: tuple[int, int], q: np.ndarray, pattern: np.ndarray, pad: int
           ) -> tuple[int, int, np.ndarray] | None:
    """One tag's model before the lens's blur, as four images of its patch (x0, y0, (4, h, w)):
    black, white (cells and quiet zone), the background past it (each pixel's share of its area),
    and the pixels within FIT_CELLS of the black square (where the levels and the blur are
    fitted).  The pattern is drawn on SUPERSAMPLE x SUPERSAMPLE sub-pixels from a texture of about
    one texel per sub-pixel, interpolated linearly (a cell edge a ramp symmetric about it), then
    averaged over each pixel's area: a pixel's box exactly, where one sample per pixel (a
    triangle filter) read a sharp lens's edges up to 0.04 px off."""
    H, W = shape
    m = MARGIN_CELLS
    side = CELLS + 2 + 2 * m
    Hu = cv2.getPerspectiveTransform(np.float32([[0, 0], [1, 0], [1, 1], [0, 1]]), np.float32(q))
    reach = (1 + m) / CELLS
    outline = cv2.perspectiveTransform(np.array([[[-reach, -reach], [1 + reach, -reach], [1 + reach, 1 + reach],
                                                  [-reach, 1 + reach]]], np.float64), Hu)[0]
    x0 = max(int(math.floor(outline[:, 0].min())) - pad, 0)
    y0 = max(int(math.floor(outline[:, 1].min())) - pad, 0)
    x1 = min(int(math.ceil(outline[:, 0].max())) + pad, W - 1)
    y1 = min(int(math.ceil(outline[:, 1].max())) + pad, H - 1)
    if x1 <= x0 or y1 <= y0:
        return None
    w, h = x1 - x0 + 1, y1 - y0 + 1
    s = SUPERSAMPLE
    T = max(1, int(float(np.linalg.norm(np.roll(q, -1, axis=0) - q, axis=1).min()) * s / CELLS))  # texels >= 1 sub-pixel
    cells = np.zeros((side, side), np.float32)                      # 0 background, 1 white, 2 black
    cells[m:m + CELLS + 2, m:m + CELLS + 2] = 1.0
    cells[m + 1:m + 1 + CELLS, m + 1:m + 1 + CELLS] = np.where(pattern, 1.0, 2.0)
    idx = np.repeat(np.repeat(cells, T, axis=0), T, axis=1)
    near = np.zeros_like(idx)
    k0, k1 = int(round((m + 1 - FIT_CELLS) * T)), int(round((m + 1 + CELLS + FIT_CELLS) * T))
    near[k0:k1, k0:k1] = 1.0
    # texture coordinates (texel centres at integers) of the black square's corners
    src = ((np.float32([[0, 0], [CELLS, 0], [CELLS, CELLS], [0, CELLS]]) + m + 1) * T - 0.5).astype(np.float32)
    # ... and on the sub-pixel grid of the patch (pixel x0's left edge at sub-pixel -0.5)
    Ht = cv2.getPerspectiveTransform(src, ((q - [x0 - 0.5, y0 - 0.5]) * s - 0.5).astype(np.float32))
    tex = np.stack([idx == 2, idx == 1, near > 0], axis=2).astype(np.float32)
    fine = cv2.warpPerspective(tex, Ht, (w * s, h * s), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=(0.0, 0.0, 0.0))
    warped = cv2.resize(fine, (w, h), interpolation=cv2.INTER_AREA)          # each pixel's area
    out = np.empty((4, h, w), np.float32)
    out[0], out[1], out[3] = warped[..., 0], warped[..., 1], warped[..., 2]
    out[2] = 1.0 - out[0] - out[1]                                   # the background: the rest
    return x0, y0, out


def _fit_levels(y: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, float]:
    """Black, white and background levels making the blurred bases' pixels (3, n) best match the
    photograph's (n,) (normal equations: three unknowns), and the rms of what is left."""
    levels = _solve_levels(A @ A.T, A @ y)
    r = y - levels @ A
    return levels, float(np.sqrt(np.mean(r * r)))


def _solve_levels(AtA: np.ndarray, Aty: np.ndarray) -> np.ndarray:
    """The levels from their normal equations (least squares where the bases are degenerate)."""
    try:
        return np.linalg.solve(AtA, Aty)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(AtA, Aty, rcond=None)[0]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _normal_equations(blurred: np.ndarray, at: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`_fit_levels`' normal equations (3x3 and 3) over the pixels `at` (flat indices) of the
    blurred bases (h, w, 3), without gathering them first: the gather and the products were a
    dozen numpy calls on a few thousand pixels, ten times a tag."""
    flat = blurred.reshape(-1, 3)
    AtA = np.zeros((3, 3))
    Aty = np.zeros(3)
    for k in range(len(at)):
        a0, a1, a2 = np.float64(flat[at[k], 0]), np.float64(flat[at[k], 1]), np.float64(flat[at[k], 2])
        AtA[0, 0] += a0 * a0
        AtA[0, 1] += a0 * a1
        AtA[0, 2] += a0 * a2
        AtA[1, 1] += a1 * a1
        AtA[1, 2] += a1 * a2
        AtA[2, 2] += a2 * a2
        Aty[0] += a0 * y[k]
        Aty[1] += a1 * y[k]
        Aty[2] += a2 * y[k]
    AtA[1, 0], AtA[2, 0], AtA[2, 1] = AtA[0, 1], AtA[0, 2], AtA[1, 2]
    return AtA, Aty


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _misfit(blurred: np.ndarray, at: np.ndarray, y: np.ndarray, levels: np.ndarray) -> float:
    """The rms of the photograph's pixels `at` less the model's at `levels`."""
    flat = blurred.reshape(-1, 3)
    ss = 0.0
    for k in range(len(at)):
        m = levels[0] * flat[at[k], 0] + levels[1] * flat[at[k], 1] + levels[2] * flat[at[k], 2]
        ss += (y[k] - m) ** 2
    return math.sqrt(ss / len(at))


def _fit_levels_at(y: np.ndarray, blurred: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, float]:
    """`_fit_levels` on the pixels `at` of the blurred bases (h, w, 3), compiled."""
    levels = _solve_levels(*_normal_equations(blurred, at, y))
    return levels, _misfit(blurred, at, y, levels)


def blur_bias(grey: np.ndarray, corners: np.ndarray, initial: np.ndarray, patterns: np.ndarray,
              quiet_zone: bool = True, rounds: int = 2, blur_px: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """The edge fit's bias (see `_bias_at`), the model drawn first at the fitted corners, then at
    the corners less the bias found (the model's blur and levels are fitted to the photograph at
    its corners, and fit better where the corners are right).  `blur_px`: the photograph's
    `edge_blur_px` at `corners`, if the caller has it already."""
    q = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
    g = np.ascontiguousarray(grey, dtype=np.float32)
    # the photograph's edge blur, read once at the fitted corners (every round's model matches it)
    if blur_px is not None:
        seen = np.asarray(blur_px, dtype=np.float64)
    else:
        seen = edge_blur_px(g, q) if len(q) else np.zeros(0)
    bias, sigma = _bias_at(g, seen, q, initial, patterns, quiet_zone, np.full(len(q), np.nan))
    for _ in range(rounds - 1):
        bias, sigma = _bias_at(g, seen, q - bias, initial, patterns, quiet_zone, sigma)
    # one larger than MAX_BIAS_CELLS of a cell is the model's failure, not the fit's
    wild = np.max(np.linalg.norm(bias, axis=2), axis=1) > MAX_BIAS_CELLS * _cell_px(q) if len(q) else np.zeros(0, bool)
    bias[wild] = 0.0
    sigma[wild] = np.nan
    return bias, sigma


def _bias_at(g: np.ndarray, seen: np.ndarray, corners: np.ndarray, initial: np.ndarray, patterns: np.ndarray,
             quiet_zone: bool, start_sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The edge fit's bias at each tag (N, 4, 2; zero where `needs_correction` is False) and the
    blur sigma the model matched (N,; nan where not needed).  g: the photograph (float32); seen: its
    edge blur at the fitted quads (`edge_blur_px`, N,); corners: where the model is drawn (corner 0
    = the marker's top-left); initial: the quads the fit started from, in the same corner order;
    patterns: the tags' cells (N, 8, 8; True = white)."""
    q = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
    N = len(q)
    bias = np.zeros_like(q)
    sigma = np.full(N, np.nan)
    if N == 0:
        return bias, sigma
    todo = np.flatnonzero(needs_correction(q, seen) & np.isfinite(seen))
    if len(todo) == 0:
        return bias, sigma
    # Each tag's model is drawn on a canvas its neighbours' models do not reach: drawn on one
    # canvas, a neighbour's patch (its quiet zone, background and blur margin) painted over a
    # tag's own model where two tags lie within a few cells in the image, and the fit on the model
    # read that tag's facing edge wherever the neighbour's model put something like an edge: clean
    # tags "corrected" up to 0.8 px off (docs/fiducials.md, "When the blur is comparable to a cell").
    canvases: list[np.ndarray] = []
    taken: list[list[tuple[int, int, int, int]]] = []       # the patches drawn on each canvas
    layer = np.full(N, -1)
    done = []
    for k in todo:
        guess = max(float(seen[k]), MIN_SIGMA_PX)
        pad = int(math.ceil(4 * SIGMA_RANGE[1] * guess)) + 2
        made = _bases(g.shape, q[k], np.asarray(patterns[k], bool), pad)
        if made is None:
            continue
        x0, y0, base = made
        h, w = base.shape[1:]
        mask = base[3] > 0.5
        y = g[y0:y0 + h, x0:x0 + w][mask].astype(np.float64)
        # the blur: the sigma whose model matches the patch best, by a parabola through the fits'
        # residuals at SIGMA_STEPS multiples of the edge's apparent blur (or of the sigma a
        # previous round found)
        if np.isfinite(start_sigma[k]):
            trial = start_sigma[k] * np.linspace(1 - SIGMA_REFINE, 1 + SIGMA_REFINE, 3)
        else:
            trial = guess * np.linspace(*SIGMA_RANGE, SIGMA_STEPS)
        rms = []
        three = np.ascontiguousarray(np.moveaxis(base[:3], 0, 2))
        at = np.flatnonzero(mask)
        for sg in trial:
            blurred = cv2.GaussianBlur(three, (0, 0), sg, borderType=cv2.BORDER_REPLICATE)
            rms.append(_fit_levels_at(y, blurred, at)[1])
        j = int(np.clip(np.argmin(rms), 1, len(trial) - 2))
        a, b_, c = rms[j - 1], rms[j], rms[j + 1]
        den = a - 2 * b_ + c
        step = 0.5 * (a - c) / den if den > 0 else 0.0
        best = float(trial[j] + np.clip(step, -1, 1) * (trial[1] - trial[0]))
        blurred = cv2.GaussianBlur(three, (0, 0), best, borderType=cv2.BORDER_REPLICATE)
        levels, misfit = _fit_levels_at(y, blurred, at)
        contrast = levels[1] - levels[0]
        if not (contrast > 0 and misfit <= MAX_MISFIT * contrast):
            continue                                    # not the tag the model draws: leave it as fitted
        box = (x0, y0, x0 + w, y0 + h)
        j = next((i for i, boxes in enumerate(taken) if not any(_meet(box, o) for o in boxes)), len(taken))
        if j == len(taken):
            canvases.append(np.zeros_like(g))
            taken.append([])
        canvases[j][y0:y0 + h, x0:x0 + w] = blurred @ levels.astype(np.float32)
        taken[j].append(box)
        layer[k] = j
        sigma[k] = best
        done.append(k)
    start = np.asarray(initial, dtype=np.float64).reshape(-1, 4, 2)
    for j, model in enumerate(canvases):
        these = np.flatnonzero(layer == j)
        fit = fit_quads(model, start[these], None, quiet_zone=quiet_zone)
        b = fit.corners - q[these]
        # bias = what the fit reads on a model drawn at `corners`, less them
        ok = np.all(np.isfinite(b), axis=(1, 2)) & fit.edges_fitted.all(axis=1)
        bias[these[ok]] = b[ok]
    return bias, sigma


def _meet(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    """Whether two patches (x0, y0, x1, y1; x1, y1 past the end) share a pixel."""
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]
