"""How sharp and how clean an image of AprilTags is: the edge spread across a tag's black/white
border and the noise in its flat areas, measured the same way on photographs and on simulated
frames (`lab bench fiducials`, docs/fiducials.md "Image quality: photographs against the
simulator").  Pure functions of a grey image; the tags' corners come from the project's own
detector (`estimation.fiducials.TagDetector.find`).

Edge spread.  Each of the black square's four edges is crossed by the pixels around it; every
pixel centre's signed distance s (px, positive towards the white quiet zone) from the straight line
through the detector's two corners and its grey level are samples of the edge spread function
(ESF), at every sub-pixel phase at once (the slanted-edge method of ISO 12233).  Only the stretches
of an edge whose inner neighbour cell is black are used (so the dark side is two cells deep), away
from the tag's corners and from the neighbouring cells' edges.  The samples are fitted with

    I(s) = dark + (bright - dark) Phi((s - s0) / sigma) + (far - bright) Phi((s - s0 - q) / sigma)

Phi the normal CDF: a Gaussian-blurred step, plus the quiet zone's own outer border q px further
out (whatever lies beyond it, `far`), all six parameters free (s0 absorbs a corner a fraction of a
pixel off).  `sigma` is the edge's total spread, the pixel's own aperture included: a pixel
integrates the scene over its square, which projected on any edge normal has variance 1/12 px^2,
so a lens blur of b px (the simulator's `blur_px`) gives sigma = sqrt(b^2 + 1/12) (`blur_px` below
inverts that: the simulator blur that would draw the same edge).  The 10-90 % rise distance of a
Gaussian ESF is 2.563 sigma.  A tag's figure is the median over its accepted edges (an edge is
refused when the fit does not describe it: residual over 12 % of the contrast, or sigma at a bound).

Noise.  Pixels whose whole neighbourhood (2.5 sigma + 0.5 px around the pixel centre) lies in one
cell colour of the tag's known pattern (the black border and data cells, the white data cells and
the one-cell white quiet zone) are flat; on each side (black, white) a plane is fitted to them (so
uneven lighting across the tag is not counted as noise) and the noise is the standard deviation of
the residuals (for the plane's three parameters, n - 3 degrees of freedom), clipped at 4 robust
sigmas so that a speck of dirt does not count.  Reported in grey levels and as a fraction of the tag's contrast (white level minus
black level), which does not depend on exposure.

Valid for tags with cells of about 2.5 px or more (sides >= 20 px); the measurement's own error,
checked on rendered tags of known blur, is in tests/test_image_quality.py and docs/fiducials.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

__all__ = ["ESF_RISE_PER_SIGMA", "PIXEL_APERTURE_VAR", "EdgeFit", "TagQuality", "fit_edge_spread",
           "edge_samples", "flat_noise", "tag_pattern", "measure_tag", "measure_image", "summarise"]

# 10-90 % rise of a Gaussian ESF in units of its sigma: 2 * Phi^-1(0.9).
ESF_RISE_PER_SIGMA = 2.0 * 1.2815515655446004
# Variance of a unit pixel square projected on any direction (two uniforms, widths |cos|, |sin|).
PIXEL_APERTURE_VAR = 1.0 / 12.0
_CELLS = 8                      # AprilTag 36h11: the black square is 8 cells across
MAX_EDGE_RMS_OF_CONTRAST = 0.12
MIN_EDGE_SAMPLES = 20
MIN_CONTRAST_GREY = 20.0
SIGMA_BOUNDS_PX = (0.15, 4.0)
DEFAULT_MIN_SIDE_PX = 20.0
Q_CELLS = (0.6, 1.9)             # the quiet zone's width, cells (AprilTag's own images: 1)
# A tag's edge figure counts only when its cells are this many edge sigmas wide: below it the
# margins leave too little of an edge and the spread reads low (measured: 0.82 of the truth at 1.5).
MIN_CELL_SIGMAS = 2.0
EDGE_MARGIN_SIGMAS = 2.0


def _ndtr(x: np.ndarray) -> np.ndarray:
    from scipy.special import ndtr

    return ndtr(x)


@dataclass(frozen=True)
class EdgeFit:
    """One edge's spread function: `sigma_px` (pixel aperture included), `offset_px` (s0), the
    `dark` and `bright` levels, the fit's residual `rms` (grey levels) over `n` samples, and the
    `halo`: how far the profile (mean over 0.5 px bins) dips below the dark level or rises above the
    bright one within 2 px of the edge, as a fraction of the contrast.  A camera's sharpening
    (unsharp masking, in most JPEG pipelines) draws it; a plain blur cannot (0 up to the bins'
    noise)."""

    sigma_px: float
    offset_px: float
    dark: float
    bright: float
    rms: float
    n: int
    halo: float = 0.0               # sharpening's overshoot, fraction of the contrast (below)

    @property
    def rise_px(self) -> float:
        return ESF_RISE_PER_SIGMA * self.sigma_px

    @property
    def blur_px(self) -> float:
        """The Gaussian lens blur that, with the pixel's aperture, gives this spread."""
        return math.sqrt(max(self.sigma_px ** 2 - PIXEL_APERTURE_VAR, 0.0))


def _esf(p: np.ndarray, s: np.ndarray, far_step: bool) -> np.ndarray:
    dark, bright, s0, sigma = p[:4]
    out = dark + (bright - dark) * _ndtr((s - s0) / sigma)
    if far_step:
        far, q = p[4], p[5]
        out = out + (far - bright) * _ndtr((s - s0 - q) / sigma)
    return out


def fit_edge_spread(s: np.ndarray, values: np.ndarray, *,
                    far_step_px: tuple[float, float] | None = None) -> EdgeFit | None:
    """Fit a Gaussian-blurred dark-to-bright step to samples (`s` px, positive on the bright side;
    `values` grey levels).  `far_step_px` (q_min, q_max): the bright band ends q px beyond the edge
    (a tag's quiet zone), where another step to an unknown level begins; None: the bright side goes
    on.  None when there are too few samples or no dark-to-bright step."""
    from scipy.optimize import least_squares

    s = np.asarray(s, float).ravel()
    v = np.asarray(values, float).ravel()
    if len(s) < MIN_EDGE_SAMPLES:
        return None
    dark_side = s < -0.5
    near = (s > 0.5) & (s < (far_step_px[0] if far_step_px else np.inf))
    lo = float(np.median(v[dark_side])) if np.any(dark_side) else float(v.min())
    hi = float(np.median(v[near])) if np.any(near) else float(v.max())
    if hi - lo < MIN_CONTRAST_GREY / 2:
        return None
    span = float(np.ptp(v)) + 1.0
    x0 = [lo, hi, 0.0, 1.0]
    lb = [lo - span, lo, -2.0, SIGMA_BOUNDS_PX[0]]
    ub = [hi, hi + span, 2.0, SIGMA_BOUNDS_PX[1]]
    far = far_step_px is not None
    if far:
        q_lo, q_hi = far_step_px
        beyond = s > q_hi
        x0 += [float(np.median(v[beyond])) if np.any(beyond) else hi, 0.5 * (q_lo + q_hi)]
        lb += [-255.0, q_lo]
        ub += [510.0, q_hi]
    x0 = np.clip(x0, np.asarray(lb) + 1e-9, np.asarray(ub) - 1e-9)
    try:
        r = least_squares(lambda p: _esf(p, s, far) - v, x0, bounds=(lb, ub), x_scale="jac")
    except (ValueError, np.linalg.LinAlgError):
        return None
    p = r.x
    rms = float(np.sqrt(np.mean(r.fun ** 2)))
    return EdgeFit(float(p[3]), float(p[2]), float(p[0]), float(p[1]), rms, len(s),
                   _halo(s - p[2], v, float(p[0]), float(p[1]), far_step_px[0] if far else np.inf))


def _halo(s: np.ndarray, v: np.ndarray, dark: float, bright: float, bright_until: float = np.inf,
          reach_px: float = 2.0, bin_px: float = 0.5, min_per_bin: int = 4) -> float:
    """Largest excursion of the binned profile beyond the dark (before the edge) or the bright
    level (after it), within `reach_px`, as a fraction of bright - dark.  The levels are the
    plateaus' medians beyond `reach_px` where there are samples there (the fit's levels lean
    towards an overshoot), else the fit's."""
    far_dark = s < -reach_px - 0.5
    far_bright = (s > reach_px + 0.5) & (s < bright_until)
    if far_dark.sum() >= 5:
        dark = float(np.median(v[far_dark]))
    if far_bright.sum() >= 5:
        bright = float(np.median(v[far_bright]))
    worst = 0.0
    edges = np.arange(-reach_px, reach_px + 1e-9, bin_px)
    for lo in edges[:-1]:
        m = (s >= lo) & (s < lo + bin_px)
        if m.sum() < min_per_bin:
            continue
        mean = float(v[m].mean())
        worst = max(worst, dark - mean if lo + bin_px <= 0 else mean - bright if lo >= 0 else 0.0)
    return worst / (bright - dark) if bright > dark else 0.0


def flat_noise(values: np.ndarray, xy: np.ndarray | None = None) -> float | None:
    """Noise (grey levels, 1 sigma) of samples of one flat surface: the standard deviation of the
    residuals from a plane fitted over their positions `xy` (N, 2) px, so that a lighting gradient
    is not counted (n - 3 degrees of freedom; without `xy`, about the mean, n - 1), residuals beyond
    4 robust sigmas left out.  None for fewer than 10 samples."""
    v = np.asarray(values, float).ravel()
    n = len(v)
    if n < 10:
        return None
    if xy is None:
        r, k = v - v.mean(), 1
    else:
        A = np.column_stack([np.ones(n), np.asarray(xy, float).reshape(n, 2)])
        coef, *_ = np.linalg.lstsq(A, v, rcond=None)
        r, k = v - A @ coef, 3
    # The median absolute deviation alone is no use on 8-bit levels (a noise of 2 levels gives a
    # MAD of exactly 1, read as 1.48); it only sets the clip that keeps specks and dirt out of a
    # plain standard deviation (at 4 sigma a Gaussian loses nothing measurable).
    scale = 1.4826 * float(np.median(np.abs(r - np.median(r)))) + 0.5
    keep = np.abs(r - np.median(r)) <= 4.0 * scale
    rk = r[keep]
    return float(np.sqrt(np.sum((rk - rk.mean()) ** 2) / max(len(rk) - k, 1)))


# ---- tags ------------------------------------------------------------------------------------


def tag_pattern(tag_id: int) -> np.ndarray:
    """The 8 x 8 cells of AprilTag 36h11 `tag_id` as OpenCV 4 draws it (1 white, 0 black; row 0
    along the edge from the detector's corner 0 to corner 1)."""
    import cv2

    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    return (cv2.aruco.generateImageMarker(d, int(tag_id), _CELLS, borderBits=1) > 127).astype(np.uint8)


@dataclass
class TagQuality:
    tag_id: int
    side_px: float                  # the shortest side of the black square
    edges: list[EdgeFit] = field(default_factory=list)
    sigma_px: float | None = None   # median over the accepted edges
    dark: float | None = None       # black and white levels (medians of the flat pixels)
    bright: float | None = None
    noise_dark: float | None = None
    noise_bright: float | None = None
    n_dark: int = 0
    n_bright: int = 0
    too_small: bool = False         # cells under MIN_CELL_SIGMAS edge sigmas: sigma_px not trusted

    @property
    def contrast(self) -> float | None:
        return None if self.dark is None or self.bright is None else self.bright - self.dark

    def to_json(self) -> dict[str, Any]:
        c = self.contrast
        return {"tag_id": self.tag_id, "side_px": self.side_px, "edges": len(self.edges),
                "sigma_px": self.sigma_px, "too_small": self.too_small,
                "halo": float(np.median([f.halo for f in self.edges])) if self.edges else None,
                "rise_px": None if self.sigma_px is None else ESF_RISE_PER_SIGMA * self.sigma_px,
                "blur_px": None if self.sigma_px is None else
                math.sqrt(max(self.sigma_px ** 2 - PIXEL_APERTURE_VAR, 0.0)),
                "dark": self.dark, "bright": self.bright, "contrast": c,
                "noise_dark": self.noise_dark, "noise_bright": self.noise_bright,
                "noise_dark_rel": None if self.noise_dark is None or not c else self.noise_dark / c,
                "noise_bright_rel": None if self.noise_bright is None or not c else self.noise_bright / c,
                "flat_px": [self.n_dark, self.n_bright]}


# edge e: (corner index start, end) and the cell coordinates (n inward from the edge, a along it)
_EDGES = ((0, 1), (1, 2), (2, 3), (3, 0))


def _edge_coords(e: int, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if e == 0:
        return v, u
    if e == 1:
        return _CELLS - u, v
    if e == 2:
        return _CELLS - v, u
    return u, v


def _inner_cell(P: np.ndarray, e: int, k: int) -> int:
    """The colour of the data cell next to border cell k (1..6) along edge e."""
    return int((P[1, k], P[k, _CELLS - 2], P[_CELLS - 2, k], P[k, 1])[e])


def _tag_pixels(grey: np.ndarray, corners: np.ndarray, reach_cells: float):
    """Pixel centres (x, y), grey levels and cell coordinates (u, v) of every pixel within
    `reach_cells` of the black square."""
    import cv2

    cells = np.array([[0, 0], [_CELLS, 0], [_CELLS, _CELLS], [0, _CELLS]], np.float64)
    H = cv2.getPerspectiveTransform(cells.astype(np.float32), np.asarray(corners, np.float32))
    r = reach_cells
    box = np.array([[-r, -r], [_CELLS + r, -r], [_CELLS + r, _CELLS + r], [-r, _CELLS + r]], np.float64)
    outline = cv2.perspectiveTransform(box.reshape(-1, 1, 2), H).reshape(-1, 2)
    h, w = grey.shape
    x0, y0 = (max(0, int(math.floor(outline[:, i].min()))) for i in (0, 1))
    x1, y1 = min(w - 1, int(math.ceil(outline[:, 0].max()))), min(h - 1, int(math.ceil(outline[:, 1].max())))
    if x1 <= x0 or y1 <= y0:
        return None
    ys, xs = np.mgrid[y0:y1 + 1, x0:x1 + 1]
    xy = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
    uv = cv2.perspectiveTransform(xy.reshape(-1, 1, 2), np.linalg.inv(H)).reshape(-1, 2)
    inside = (np.abs(uv - _CELLS / 2) <= _CELLS / 2 + r).all(axis=1)
    xy, uv = xy[inside], uv[inside]
    return xy, grey[xy[:, 1].astype(int), xy[:, 0].astype(int)].astype(np.float64), uv


def edge_samples(xy: np.ndarray, values: np.ndarray, uv: np.ndarray, corners: np.ndarray, pattern: np.ndarray,
                 e: int, *, margin_px: float, outer_cells: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Samples across edge `e` (0: corner 0 -> 1, ... 3: corner 3 -> 0) of a tag: (s px, positive
    outwards, grey level) for the pixels from `outer_cells` outside the edge to `margin_px` short of
    the next possible transition inside (the inner neighbour cells' far side, two cells in), where
    nothing but the black border and black inner cells lies within `margin_px` along the edge (no
    white inner cell, no corner of the tag: the orthogonal edges' quiet zone)."""
    n, a = _edge_coords(e, uv[:, 0], uv[:, 1])
    i0, i1 = _EDGES[e]
    p0, p1 = np.asarray(corners[i0], float), np.asarray(corners[i1], float)
    cell = float(np.linalg.norm(p1 - p0)) / _CELLS
    m = margin_px / cell                                          # in cells
    # the colour of the cell next to the border, along the edge: border cells at both ends
    inner = np.array([0] + [_inner_cell(pattern, e, k) for k in range(1, _CELLS - 1)] + [0])
    white_at = np.flatnonzero(inner)
    gap = np.full(len(a), np.inf)                                 # along-edge distance to a white inner cell
    for k in white_at:
        gap = np.minimum(gap, np.maximum(np.maximum(k - a, a - (k + 1)), 0.0))
    keep = (n > -outer_cells) & (n < 2.0 - m) & (a > m) & (a < _CELLS - m) & (gap > m)
    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    normal = np.array([d[1], -d[0]])         # one of the two normals; point it away from the centre
    if (np.asarray(corners, float).mean(axis=0) - p0) @ normal > 0:
        normal = -normal
    s = (xy[keep] - p0) @ normal
    return s, values[keep]


def _flat_masks(pattern: np.ndarray, uv: np.ndarray, margin_cells: float) -> tuple[np.ndarray, np.ndarray]:
    """Which pixels (cell coordinates `uv`) have only black, or only white, within `margin_cells`
    (a square neighbourhood) in the tag's pattern with its one-cell white quiet zone."""
    import cv2

    F = 16
    ext = np.full((_CELLS + 4, _CELLS + 4), 128, np.uint8)        # beyond the quiet zone: unknown
    ext[1:-1, 1:-1] = 255                                         # the quiet zone
    ext[2:-2, 2:-2] = pattern * 255
    up = cv2.resize(ext, None, fx=F, fy=F, interpolation=cv2.INTER_NEAREST)
    k = 2 * int(math.ceil(margin_cells * F)) + 1
    kernel = np.ones((k, k), np.uint8)
    lo, hi = cv2.erode(up, kernel, borderValue=128), cv2.dilate(up, kernel, borderValue=128)
    iu = np.clip(np.floor((uv[:, 0] + 2) * F).astype(int), 0, up.shape[1] - 1)
    iv = np.clip(np.floor((uv[:, 1] + 2) * F).astype(int), 0, up.shape[0] - 1)
    a, b = lo[iv, iu], hi[iv, iu]
    return (b == 0), (a == 255)


def measure_tag(grey: np.ndarray, corners: np.ndarray, tag_id: int) -> TagQuality:
    """Edge spread and flat-area noise of one detected tag (`corners` (4, 2) in the detector's
    order and pixel convention)."""
    corners = np.asarray(corners, float).reshape(4, 2)
    side = float(np.min(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)))
    q = TagQuality(int(tag_id), side)
    got = _tag_pixels(np.asarray(grey), corners, 2.2)
    if got is None:
        return q
    xy, values, uv = got
    pattern = tag_pattern(tag_id)
    cell = float(np.mean(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1))) / _CELLS
    # Margins grow with the blur: a first pass assumes a sharp image, later ones the edges'
    # median spread so far (the fit is refused where too little is left clear of other edges).
    sigma_guess = 0.5
    for _ in range(3):
        fits = []
        for e in range(4):
            s, v = edge_samples(xy, values, uv, corners, pattern, e, margin_px=EDGE_MARGIN_SIGMAS * sigma_guess + 0.5)
            n_dark = int(np.sum(s < -0.5))
            fit = fit_edge_spread(s, v, far_step_px=(Q_CELLS[0] * cell, Q_CELLS[1] * cell))
            if fit is None or n_dark < MIN_EDGE_SAMPLES // 2:
                continue
            at_bound = not (SIGMA_BOUNDS_PX[0] * 1.05 < fit.sigma_px < SIGMA_BOUNDS_PX[1] * 0.95)
            contrast = fit.bright - fit.dark
            if at_bound or contrast < MIN_CONTRAST_GREY or fit.rms > MAX_EDGE_RMS_OF_CONTRAST * contrast:
                continue
            fits.append(fit)
        if not fits:
            break
        q.edges = fits
        new = float(np.median([f.sigma_px for f in fits]))
        if abs(new - sigma_guess) < 0.05 * new:
            break
        sigma_guess = new
    if q.edges:
        q.sigma_px = float(np.median([f.sigma_px for f in q.edges]))
        if cell < MIN_CELL_SIGMAS * q.sigma_px:
            q.too_small = True
    sigma = q.sigma_px if q.sigma_px is not None else 1.0
    dark, bright = _flat_masks(pattern, uv, (2.5 * sigma + 0.5) / cell)
    q.n_dark, q.n_bright = int(dark.sum()), int(bright.sum())
    if q.n_dark >= 10:
        q.dark = float(np.median(values[dark]))
        q.noise_dark = flat_noise(values[dark], xy[dark])
    if q.n_bright >= 10:
        q.bright = float(np.median(values[bright]))
        q.noise_bright = flat_noise(values[bright], xy[bright])
    return q


def _detector():
    from estimation.fiducials import TagDetector

    # every id; corners only, so the camera model does not matter
    return TagDetector(np.eye(3), np.zeros(5), {i: 1.0 for i in range(587)})


def measure_image(grey: np.ndarray, *, min_side_px: float = DEFAULT_MIN_SIDE_PX, detector: Any = None) -> dict:
    """Every tag the detector finds in `grey` whose black square is at least `min_side_px` on its
    shortest side, measured (`measure_tag`), and the image's summary (`summarise`)."""
    import cv2

    g = np.asarray(grey)
    if g.ndim == 3:
        g = cv2.cvtColor(g, cv2.COLOR_BGR2GRAY)
    det = detector or _detector()
    ids, quads = det.find(g)
    tags = []
    for tid, c in zip(ids, quads):
        side = float(np.min(np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)))
        if side >= min_side_px:
            tags.append(measure_tag(g, c, tid))
    return {"width_px": int(g.shape[1]), "height_px": int(g.shape[0]), "tags_found": len(ids),
            "min_side_px": min_side_px, **summarise(tags), "tags": [t.to_json() for t in tags]}


def summarise(tags: Sequence[TagQuality]) -> dict:
    """Medians over tags (each tag one vote): edge sigma, rise, equivalent blur, noise in grey
    levels and as a fraction of contrast; the spread of the edge sigma over tags (min, max)."""
    rows = [t.to_json() for t in tags]
    edge_rows = [r for r in rows if r["sigma_px"] is not None and not r["too_small"]]

    def med(key: str) -> float | None:
        x = [r[key] for r in (edge_rows if key in ("sigma_px", "rise_px", "blur_px", "halo") else rows)
             if r[key] is not None]
        return float(np.median(x)) if x else None

    sig = [r["sigma_px"] for r in edge_rows]
    return {"tags_measured": len(rows), "tags_with_edges": len(sig), "edges": sum(r["edges"] for r in edge_rows),
            "tags_too_small": sum(r["too_small"] for r in rows),
            "side_px_median": med("side_px"),
            "sigma_px": med("sigma_px"), "sigma_px_range": [min(sig), max(sig)] if sig else None,
            "rise_px": med("rise_px"), "blur_px": med("blur_px"), "halo": med("halo"), "contrast": med("contrast"),
            "noise_dark": med("noise_dark"), "noise_bright": med("noise_bright"),
            "noise_dark_rel": med("noise_dark_rel"), "noise_bright_rel": med("noise_bright_rel")}
