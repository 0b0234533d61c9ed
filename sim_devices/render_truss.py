"""The truss in the simulated camera's image: struts and node bodies drawn over the tags they hide,
hidden by the tags in front of them.

`draw_truss` composites the occluders of `sim_devices.truss_geometry` (in the camera frame) into
the noise-free grey image `render.render_grey` made of the tags, in place, before the pixel noise
(`SimWorld.render` hands it to `render.render_tags` as its `overlay`).  Pure geometry and numpy;
the tag renderer's conventions throughout (OpenCV pixel centres at integers, the lens distortion
through the same cached map of ideal-pinhole pixel positions).

How a pixel reads a strut (a cylinder of radius r along the segment A-B):
- Coverage.  The cylinder's outline in the ideal (undistorted) image is two straight lines, the
  images of the two planes through the camera centre tangent to it, cut at each end across the
  axis.  A pixel's share inside is computed as the tags' is: the pixel's square projected on each
  line's normal convolved with the same Gaussian blur (`render.pixel_edge_response`, tabulated
  here for every edge direction), the two sides combined as a band (F(d1) + F(d2) - 1), the ends
  multiplied in.  Distances are measured in ideal pixels: near the frame's corners the barrel
  distortion makes an output pixel a few per cent larger or smaller than that, which changes how
  wide the blurred transition is, not where the edge is.
- Blur.  The lens's own, or with a `render.Defocus` (the world's camera with a focus distance)
  each strut's at its middle's depth and each node's at its centre's, as a tag's is at its
  centre's, rounded to 0.02 px so struts at nearly one depth share a pass; the truss is then lit
  by the frame's gain map (vignetting, the light across the frame) and takes the sensor's noise
  with the tags, in `render.render_tags`.
- Depth.  Where a strut pixel lands on a tag (the tags' depth buffer from `render_grey`, written
  where a tag covers more than half a pixel), the ray through the pixel is intersected with the
  cylinder and the strut is drawn only if that point is nearer than the tag plane; elsewhere
  nothing but farther truss is behind it.  Among themselves struts and nodes are drawn farthest
  first (painter's order by centre distance).  At a tag's outline (its quiet zone's outer edge, a
  pixel or less) a strut passing behind is hidden or shown whole rather than blended.
- Shade.  Anodised aluminium: a grey of `albedo` times the tags' white level, lit by ambient light
  plus one distant light (`light_camera`, a direction in the camera frame; the world gives it a
  lamp fixed in the lab) with Lambert's cosine; the surface normal across a strut is taken from
  the pixel's position between the two outline lines (the cross-section seen as from far away).
- Node bodies are spheres: the ray's closest approach to the centre against the radius, scaled to
  pixels at the sphere's distance (exact where the outline is, approximate in how wide the blur is
  off the optical axis), shaded with the normal where the ray meets the sphere.
- Struts are cut back to where they enter their node spheres, so a strut seen end-on does not
  show through its node.

Culling: struts are clipped to the view frustum (widened by the strut's radius and the blur's
reach) and the near plane; each strut is rasterised in a band of rows (or columns) around its
projected axis, as wide as its largest projected diameter plus the blur's reach; each node in its
bounding box.

Left out: shadows (the truss casts none, on tags or on itself), specular highlights, inter-
reflections, and the background behind the truss (the grey or image the tags are drawn on).
"""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np

from sim_devices.render import Defocus, _ideal_coords, pixel_edge_response
from sim_devices.truss_geometry import TrussOccluders

__all__ = ["draw_truss", "STRUT_ALBEDO", "AMBIENT", "DEFAULT_LIGHT_CAMERA"]

STRUT_ALBEDO = 0.62            # clear anodised aluminium against the tags' white card
AMBIENT = 0.35                 # share of the light that is ambient (what a shadowed side still gets)
DEFAULT_LIGHT_CAMERA = (-0.3, -0.6, -0.74)   # towards the lamp: above and to the left of the camera
_NEAR_PLANE_M = 0.05
_TABLE_STEP_PX = 0.004
_ANGLE_BUCKETS = 46            # edge normal 0..45 deg off an image axis, 1 deg apart
_MIN_COVERAGE = 1e-3           # pixels a strut covers less than this are left alone
# With a `Defocus`, each strut's and node's blur is rounded to this (px), so that the struts and
# nodes at nearly one depth share one edge table and one pass (0.01 px off at most: an edge's
# 10-90 % width changes by 0.03 px)
_DEFOCUS_STEP_PX = 0.02


@lru_cache(maxsize=32)
def _edge_table(sigma_key: int) -> tuple[np.ndarray, float]:
    """`pixel_edge_response` for every edge direction (rows: the normal 0..45 deg off an image
    axis, 1 deg apart) on a uniform grid of distances: (table flattened, first distance)."""
    s = sigma_key / 1000.0
    reach = 0.72 + 5.0 * s
    d = np.arange(-reach, reach + _TABLE_STEP_PX, _TABLE_STEP_PX)
    rows = []
    for k in range(_ANGLE_BUCKETS):
        a = math.radians(k)
        r = pixel_edge_response(d, (math.cos(a), math.sin(a)), s).astype(np.float32)
        r[0], r[-1] = 0.0, 1.0
        rows.append(r)
    return np.stack(rows), float(d[0])


@lru_cache(maxsize=8)
def _ideal_extent(K_key: bytes, dist_key: bytes, width: int, height: int) -> tuple[float, float, float, float]:
    """The ideal-pinhole positions' range over the frame's pixels: x min, x max, y min, y max."""
    ideal = _ideal_coords(K_key, dist_key, width, height)
    if ideal is None:
        return 0.0, width - 1.0, 0.0, height - 1.0
    return float(ideal[0].min()), float(ideal[0].max()), float(ideal[1].min()), float(ideal[1].max())


def _clip_segments(a: np.ndarray, b: np.ndarray, planes: np.ndarray, offsets: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Liang-Barsky: the parts s0..s1 (of 0..1) of segments a->b (S, 3) where every
    planes[i] . X + offsets[i] >= 0; (s0, s1, whether anything is left)."""
    ga = a @ planes.T + offsets               # (S, P)
    gb = b @ planes.T + offsets
    s0 = np.zeros(len(a))
    s1 = np.ones(len(a))
    ok = np.ones(len(a), bool)
    for i in range(len(offsets)):
        fa, fb = ga[:, i], gb[:, i]
        out_both = (fa < 0) & (fb < 0)
        ok &= ~out_both
        with np.errstate(divide="ignore", invalid="ignore"):
            s = fa / (fa - fb)
        entering = (fa < 0) & (fb >= 0)
        leaving = (fa >= 0) & (fb < 0)
        s0 = np.where(entering, np.maximum(s0, s), s0)
        s1 = np.where(leaving, np.minimum(s1, s), s1)
    ok &= s1 > s0
    return s0, s1, ok


def draw_truss(img: np.ndarray, depth: np.ndarray | None, K: np.ndarray, dist, occ: TrussOccluders, *,
               blur_sigma_px: float = 0.6, defocus: Defocus | None = None, white_level: float = 225.0,
               albedo: float = STRUT_ALBEDO, ambient: float = AMBIENT, light_camera=DEFAULT_LIGHT_CAMERA) -> None:
    """Composite the truss `occ` (camera frame) into the grey image `img` ((H, W) float32, in place),
    behind the tags where `depth` (the tags' depth buffer, +inf where there is no tag; None: no
    tags) says they are nearer.  `light_camera`: the direction towards the light, camera frame.
    blur_sigma_px: the lens's blur (px), everywhere, or at the focus distance with `defocus`: then
    each strut is blurred for its (clipped) middle's depth and each node for its centre's, as the
    tags are for their centres' (`render.Defocus`), rounded to _DEFOCUS_STEP_PX."""
    height, width = img.shape
    K = np.asarray(K, dtype=float).reshape(3, 3)
    d_coef = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).ravel()
    ideal = _ideal_coords(K.tobytes(), d_coef.tobytes(), int(width), int(height))
    light = np.asarray(light_camera, dtype=float)
    light = light / np.linalg.norm(light)
    r, R = occ.strut_radius_m, occ.node_radius_m

    def sigma_at(z: np.ndarray) -> np.ndarray:
        """Each depth's blur, rounded (no defocus: the lens's own, as given)."""
        if defocus is None:
            return np.full(np.shape(z), float(blur_sigma_px))
        s = np.array([defocus.sigma_px(max(float(zz), _NEAR_PLANE_M), K[0, 0], blur_sigma_px) for zz in np.ravel(z)])
        return np.round(s / _DEFOCUS_STEP_PX) * _DEFOCUS_STEP_PX

    # the largest blur anywhere on the truss (the depth of field's blur is largest at one end of
    # its depth range), for the frustum's margin
    max_sigma = float(blur_sigma_px)
    if defocus is not None:
        zs = np.concatenate([occ.strut_a[:, 2], occ.strut_b[:, 2], occ.node_centre[:, 2]])
        if zs.size:
            max_sigma = float(sigma_at(np.array([zs.min() - R, zs.max() + R])).max())
    cam = _Camera(K, d_coef, width, height, ideal, _edge_table(int(round(1000 * max_sigma))),
                  _REACH_BASE_PX + _REACH_SIGMAS * max_sigma)
    # the frustum of the frame in ideal pixels, widened by the blur's reach
    pad = cam.reach + 1.0
    xmin, xmax, ymin, ymax = _ideal_extent(K.tobytes(), d_coef.tobytes(), int(width), int(height))
    xmin, xmax, ymin, ymax = xmin - pad, xmax + pad, ymin - pad, ymax + pad
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    xl, xr, yt, yb = (xmin - cx) / fx, (xmax - cx) / fx, (ymin - cy) / fy, (ymax - cy) / fy
    planes = np.array([[1.0, 0.0, -xl], [-1.0, 0.0, xr], [0.0, 1.0, -yt], [0.0, -1.0, yb]])
    planes /= np.linalg.norm(planes, axis=1)[:, None]

    struts = None
    if occ.n_struts:
        a0, b0 = occ.strut_a, occ.strut_b
        length = np.linalg.norm(b0 - a0, axis=1)
        u = (b0 - a0) / np.maximum(length, 1e-12)[:, None]
        # cut back to where the strut enters its node spheres
        cut = math.sqrt(max(R * R - r * r, 0.0)) if occ.n_nodes else 0.0
        a0, b0 = a0 + cut * u, b0 - cut * u
        s0, s1, ok = _clip_segments(a0, b0, np.vstack([planes, [0.0, 0.0, 1.0]]),
                                    np.array([r, r, r, r, -_NEAR_PLANE_M]))
        ok &= length > 2 * cut + 1e-6
        A = (a0 + s0[:, None] * (b0 - a0))[ok]
        B = (a0 + s1[:, None] * (b0 - a0))[ok]
        struts = (A, B, s0[ok] > 0, s1[ok] < 1)
    nodes = None
    if occ.n_nodes:
        C = occ.node_centre
        inside = (C[:, 2] > _NEAR_PLANE_M + R) & np.all(C @ planes.T >= -R, axis=1)
        nodes = C[inside]
    # painter's order, farthest first: a rank per strut and per node
    dist_s = np.linalg.norm(0.5 * (struts[0] + struts[1]), axis=1) if struts is not None else np.zeros(0)
    dist_n = np.linalg.norm(nodes, axis=1) if nodes is not None else np.zeros(0)
    order = np.argsort(-np.concatenate([dist_s, dist_n]), kind="stable")
    rank = np.empty(len(order), np.int32)
    rank[order] = np.arange(len(order), dtype=np.int32)

    parts = []
    if struts is not None and len(struts[0]):
        rank_s = rank[:len(dist_s)]
        sig = sigma_at(0.5 * (struts[0][:, 2] + struts[1][:, 2]))
        for s_, g in _by_blur(sig):
            parts.append(_strut_pixels(cam.with_blur(s_), *(a[g] for a in struts), r, light, rank_s[g], depth))
    if nodes is not None and len(nodes):
        rank_n = rank[len(dist_s):]
        for s_, g in _by_blur(sigma_at(nodes[:, 2])):
            parts.append(_node_pixels(cam.with_blur(s_), nodes[g], R, light, rank_n[g], depth))
    if not parts:
        return
    idx = np.concatenate([p[0] for p in parts])
    rk = np.concatenate([p[1] for p in parts])
    cover = np.concatenate([p[2] for p in parts])
    light_share = np.concatenate([p[3] for p in parts])
    value = (white_level * albedo * (ambient + (1.0 - ambient) * np.maximum(light_share, 0.0))).astype(np.float32)
    _composite(img.reshape(-1), idx, rk, cover.astype(np.float32), value)


_REACH_BASE_PX = 0.72          # a pixel's half-diagonal, and a little
_REACH_SIGMAS = 3.5            # the blur's tail beyond this many sigma is < 2.3e-4 of the contrast


def _by_blur(sigma: np.ndarray):
    """(blur, the indices of the elements with that blur) for each distinct blur in `sigma`."""
    sigma = np.asarray(sigma, dtype=float)
    keys = np.rint(sigma * 1000.0).astype(np.int64)
    for key in np.unique(keys):
        g = np.flatnonzero(keys == key)
        yield float(sigma[g[0]]), g


class _Camera:
    """What every strut and node needs of the camera and the frame."""

    def __init__(self, K, dist, width, height, ideal, table, reach) -> None:
        self.K, self.dist, self.width, self.height = K, dist, width, height
        self.ideal, self.table, self.reach = ideal, table, reach
        self.f = 0.5 * (K[0, 0] + K[1, 1])
        self.Kinv = np.linalg.inv(K)
        self.flat_table = table[0].reshape(-1)

    def with_blur(self, sigma_px: float) -> "_Camera":
        """This camera drawing with another blur (its edge table and reach)."""
        return _Camera(self.K, self.dist, self.width, self.height, self.ideal,
                       _edge_table(int(round(1000 * sigma_px))), _REACH_BASE_PX + _REACH_SIGMAS * sigma_px)

    def ideal_xy(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ideal-pinhole position of output pixels (flat indices)."""
        if self.ideal is None:
            y, x = np.divmod(idx, self.width)
            return x.astype(np.float64), y.astype(np.float64)
        return np.take(self.ideal[0], idx), np.take(self.ideal[1], idx)

    def to_ideal(self, P: np.ndarray) -> np.ndarray:
        p = P @ self.K.T
        return p[..., :2] / p[..., 2:3]

    def project(self, P: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) -> output pixels (..., 2), through the lens."""
        if not np.any(self.dist):
            return self.to_ideal(P)
        out, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist)
        return out.reshape(*P.shape[:-1], 2)

    def lookup(self, rowoff: np.ndarray, d: np.ndarray) -> np.ndarray:
        """The edge response at distances `d` (px) for edge directions given as offsets of their
        rows in the flattened table (row * row length)."""
        tab, d0 = self.table
        n = tab.shape[1]
        t = d * np.float32(1.0 / _TABLE_STEP_PX) + np.float32(0.5 - d0 / _TABLE_STEP_PX)
        np.clip(t, 0.0, n - 1.0, out=t)
        i = t.astype(np.int32)
        i += rowoff
        return np.take(self.flat_table, i)


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For runs of `counts`: each element's run and its position within the run."""
    total = int(counts.sum())
    run = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
    start = (np.cumsum(counts) - counts).astype(np.int32)
    return run, np.arange(total, dtype=np.int32) - np.repeat(start, counts)


_SAMPLES = 8                   # each strut's axis is projected through the lens at this many segments


def _strut_pixels(cam: _Camera, A, B, a_clipped, b_clipped, r: float, light, rank, depth):
    """Every strut's pixels at once: (flat index, rank, coverage, cosine towards the light)."""
    S = len(A)
    L = np.linalg.norm(B - A, axis=1)
    u = (B - A) / L[:, None]
    perp = A - np.sum(A * u, axis=1)[:, None] * u          # from the camera to each axis line, across it
    D = np.linalg.norm(perp, axis=1)
    ok = D > 1.5 * r                                        # not (almost) inside the strut
    e1 = perp / D[:, None]
    e2 = np.cross(u, e1)
    c = (r / D)[:, None]
    s_ = np.sqrt(np.maximum(1.0 - c * c, 0.0))
    # the two planes through the camera tangent to each cylinder, as image lines a x + b y + c = 0
    # in ideal pixels, signed positive inside (towards the axis' image)
    lines = []
    mid_px = np.column_stack([cam.to_ideal(0.5 * (A + B)), np.ones(S)])
    for n in (c * e1 + s_ * e2, c * e1 - s_ * e2):
        l_ = n @ cam.Kinv
        l_ /= np.hypot(l_[:, 0], l_[:, 1])[:, None]
        l_ *= np.where(np.sum(l_ * mid_px, axis=1) < 0, -1.0, 1.0)[:, None]
        lines.append(l_)
    lx, ly = np.abs(lines[0][:, 0]), np.abs(lines[0][:, 1])
    row = np.rint(np.degrees(np.arctan2(np.minimum(lx, ly), np.maximum(lx, ly) + 1e-300))).astype(np.int32)
    pa, pb = cam.to_ideal(A), cam.to_ideal(B)
    along = pb - pa
    la = np.linalg.norm(along, axis=1)
    along = np.where(la[:, None] > 1e-9, along / np.maximum(la, 1e-9)[:, None], np.column_stack([lines[0][:, 1], -lines[0][:, 0]]))
    far = 1e6
    ca = -np.sum(pa * along, axis=1) + np.where(a_clipped, far, 0.0)   # e_a = along . p + ca
    cb = np.sum(pb * along, axis=1) + np.where(b_clipped, far, 0.0)    # e_b = cb - along . p

    # the band of output pixels around each projected axis, scanned along its dominant image axis
    t = np.linspace(0.0, 1.0, _SAMPLES + 1)
    poly = cam.project(A[:, None, :] + t[None, :, None] * (B - A)[:, None, :])     # (S, m + 1, 2)
    half = cam.f * r / np.maximum(np.minimum(A[:, 2], B[:, 2]), 1e-6) * 1.05 + cam.reach + 0.5
    dd = poly[:, -1] - poly[:, 0]
    x_major = np.abs(dd[:, 0]) >= np.abs(dd[:, 1])
    mj = np.where(x_major[:, None], poly[..., 0], poly[..., 1])
    mn = np.where(x_major[:, None], poly[..., 1], poly[..., 0])
    o = np.argsort(mj, axis=1)
    mj, mn = np.take_along_axis(mj, o, axis=1), np.take_along_axis(mn, o, axis=1)
    n_major = np.where(x_major, cam.width, cam.height)
    n_minor = np.where(x_major, cam.height, cam.width)
    lo = np.maximum(np.floor(mj[:, 0] - half), 0).astype(np.int64)
    hi = np.minimum(np.ceil(mj[:, -1] + half), n_major - 1).astype(np.int64)
    counts = np.where(ok, np.maximum(hi - lo + 1, 0), 0)
    sr, pos = _expand(counts)                               # scan lines: their strut, their place
    if sr.size == 0:
        return _empty()
    cmaj = lo[sr] + pos
    # the axis' minor coordinate on each scan line, interpolated along its polyline
    m1 = _SAMPLES + 1
    keys = (np.arange(S)[:, None] * 1e6 + mj).ravel()
    j = np.searchsorted(keys, sr * 1e6 + cmaj, side="right") - 1
    j = np.clip(j, sr * m1, sr * m1 + _SAMPLES - 1)
    mjf, mnf = mj.ravel(), mn.ravel()
    x0, x1 = mjf[j], mjf[j + 1]
    frac = np.clip((cmaj - x0) / np.where(x1 - x0 > 1e-9, x1 - x0, 1.0), 0.0, 1.0)
    centre = mnf[j] + frac * (mnf[j + 1] - mnf[j])
    cos_m = np.abs(np.where(x_major, dd[:, 0], dd[:, 1])) / np.maximum(np.hypot(dd[:, 0], dd[:, 1]), 1e-9)
    hw = (half / np.maximum(cos_m, 0.5))[sr]
    m0 = np.maximum(np.floor(centre - hw), 0).astype(np.int64)
    m1_ = np.minimum(np.ceil(centre + hw), n_minor[sr] - 1).astype(np.int64)
    counts = m1_ - m0 + 1
    live = np.flatnonzero(counts > 0)                       # scan lines that cross the frame
    if live.size == 0:
        return _empty()
    sr, cmaj, m0, m1_, counts = sr[live], cmaj[live], m0[live], m1_[live], counts[live]
    # Each scan line's pixels are consecutive along its minor axis; the ideal-pinhole position is
    # taken as linear along that short run (from the line's middle pixel and its neighbours: the
    # lens' curvature over ten pixels moves it by ~0.01 px), so every per-pixel quantity below is
    # a line's base value plus j times its slope, j the pixel's place from the middle.
    mid = m0 + (counts - 1) // 2
    xm = x_major[sr]
    step = np.where(xm, cam.width, 1)                       # flat-index step along the minor axis
    base_idx = np.where(xm, mid * cam.width + cmaj, cmaj * cam.width + mid)
    lo_n = np.where(mid > 0, -1, 0)
    hi_n = np.where(mid < n_minor[sr] - 1, 1, 0)
    gx0, gy0 = cam.ideal_xy(base_idx)
    gxa, gya = cam.ideal_xy(base_idx + lo_n * step)
    gxb, gyb = cam.ideal_xy(base_idx + hi_n * step)
    span = np.maximum(hi_n - lo_n, 1)
    dgx, dgy = (gxb - gxa) / span, (gyb - gya) / span

    def linear(coef: np.ndarray, const: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(base, slope) per scan line of coef_x gx + coef_y gy + const."""
        cx_, cy_ = coef[sr, 0], coef[sr, 1]
        return cx_ * gx0 + cy_ * gy0 + const[sr], cx_ * dgx + cy_ * dgy

    l0, l1 = lines
    b1, k1 = linear(l0, l0[:, 2])
    b2, k2 = linear(l1, l1[:, 2])
    bt, kt = linear(along, np.zeros(S))
    # scan lines that come within the blur's reach of a (real) end: e_a = t + ca, e_b = cb - t
    jlo, jhi = (m0 - mid).astype(np.float64), (m1_ - mid).astype(np.float64)
    t_min = bt + np.minimum(jlo * kt, jhi * kt)
    t_max = bt + np.maximum(jlo * kt, jhi * kt)
    near_end = (t_min + ca[sr] < cam.reach) | (cb[sr] - t_max < cam.reach)

    rep = lambda a: np.repeat(a.astype(np.float32), counts)   # noqa: E731  (per line -> per pixel)
    line_of, pos = _expand(counts)
    j = (pos - np.repeat((counts - 1) // 2, counts)).astype(np.float32)
    d1 = rep(b1) + j * rep(k1)
    d2 = rep(b2) + j * rep(k2)
    rowoff = np.repeat(row[sr] * cam.table[0].shape[1], counts)
    cover = cam.lookup(rowoff, d1) + cam.lookup(rowoff, d2) - 1.0
    np.clip(cover, 0.0, 1.0, out=cover)
    ends = np.flatnonzero(np.repeat(near_end, counts))
    if ends.size:
        t_ = (bt[line_of[ends]] + j[ends] * kt[line_of[ends]]).astype(np.float32)
        cover[ends] *= (cam.lookup(rowoff[ends], t_ + ca[sr[line_of[ends]]].astype(np.float32))
                        * cam.lookup(rowoff[ends], cb[sr[line_of[ends]]].astype(np.float32) - t_))
    sel = np.flatnonzero(cover >= _MIN_COVERAGE)
    line_of, j, cover, d1, d2 = line_of[sel], j[sel], cover[sel], d1[sel], d2[sel]
    k = sr[line_of]                                         # each pixel's strut
    idx = base_idx[line_of] + j.astype(np.int64) * step[line_of]
    if depth is not None:
        tag_z = np.take(depth.reshape(-1), idx)
        on = np.flatnonzero(np.isfinite(tag_z))
        if on.size:
            kk = k[on]
            gxo, gyo = cam.ideal_xy(idx[on])
            v = np.column_stack([gxo, gyo, np.ones(on.size)]) @ cam.Kinv.T
            v /= np.linalg.norm(v, axis=1, keepdims=True)
            Ak, uk = A[kk], u[kk]
            b = np.sum(v * uk, axis=1)
            dv = -np.sum(v * Ak, axis=1)                    # v . (O - A), the camera at O = 0
            e = -np.sum(uk * Ak, axis=1)
            den = np.maximum(1.0 - b * b, 1e-9)
            sc = (b * e - dv) / den                         # the closest approach, along the ray
            tc = (e - b * dv) / den                         # ... and along the axis
            gap = Ak + tc[:, None] * uk - sc[:, None] * v
            rho2 = np.sum(gap * gap, axis=1)
            z = (sc - np.sqrt(np.maximum(r * r - rho2, 0.0) / den)) * v[:, 2]
            cover[on[z >= tag_z[on]]] = 0.0
    # the normal across the strut from the pixel's place between its outline lines: w = +1 on line
    # 0 (the tangent plane c e1 + s e2 touches at axis - r (c e1 + s e2): outward normal ~ -e2),
    # -1 on line 1 (~ +e2), 0 over the axis (towards the camera, -e1): the cross-section as seen
    # from afar
    w = np.clip((d2 - d1) / np.maximum(d1 + d2, 1e-6), -1.0, 1.0)
    cos_l = -w * (e2 @ light).astype(np.float32)[k] - np.sqrt(1.0 - w * w) * (e1 @ light).astype(np.float32)[k]
    return idx, rank[k], cover, cos_l


def _node_pixels(cam: _Camera, C: np.ndarray, R: float, light, rank, depth):
    """Every node sphere's pixels at once: (flat index, rank, coverage, cosine towards the light)."""
    c_px = cam.project(C)
    dcen = np.linalg.norm(C, axis=1)
    # the outline is an ellipse up to 1 / cos(off-axis angle) longer than the on-axis circle
    cos_off = C[:, 2] / dcen
    rad = cam.f * R / np.sqrt(np.maximum(dcen * dcen - R * R, 1e-12)) / np.maximum(cos_off, 0.3) * 1.05 + cam.reach + 0.5
    x0 = np.maximum(np.floor(c_px[:, 0] - rad), 0).astype(np.int64)
    x1 = np.minimum(np.ceil(c_px[:, 0] + rad), cam.width - 1).astype(np.int64)
    y0 = np.maximum(np.floor(c_px[:, 1] - rad), 0).astype(np.int64)
    y1 = np.minimum(np.ceil(c_px[:, 1] + rad), cam.height - 1).astype(np.int64)
    nx = np.maximum(x1 - x0 + 1, 0)
    ny = np.where(nx > 0, np.maximum(y1 - y0 + 1, 0), 0)
    node_of_row, ry = _expand(ny)
    if node_of_row.size == 0:
        return _empty()
    row_of, px_ = _expand(nx[node_of_row])
    k = node_of_row[row_of]
    idx = (y0[k] + ry[row_of]) * cam.width + x0[k] + px_
    gx, gy = cam.ideal_xy(idx)
    K = cam.K
    qx = ((gx - K[0, 2]) / K[0, 0]).astype(np.float32)       # the ray (qx, qy, 1) through each pixel
    qy = ((gy - K[1, 2]) / K[1, 1]).astype(np.float32)
    inv_q = 1.0 / np.sqrt(qx * qx + qy * qy + 1.0)
    Cf = C.astype(np.float32)
    cxk, cyk, czk = Cf[k, 0], Cf[k, 1], Cf[k, 2]
    tc = (qx * cxk + qy * cyk + czk) * inv_q                # the ray's closest approach to the centre
    rho = np.sqrt(np.maximum(dcen.astype(np.float32)[k] ** 2 - tc * tc, 0.0))
    cover = cam.lookup(np.zeros(len(k), np.int32), (R - rho) * np.float32(cam.f) / np.maximum(tc, 1e-6))
    sel = np.flatnonzero(cover >= _MIN_COVERAGE)
    idx, k, cover, qx, qy, inv_q, tc, rho = idx[sel], k[sel], cover[sel], qx[sel], qy[sel], inv_q[sel], tc[sel], rho[sel]
    z = (tc - np.sqrt(np.maximum(R * R - rho * rho, 0.0))) * inv_q        # where the ray meets the sphere
    if depth is not None:
        cover = np.where(z < np.take(depth.reshape(-1), idx), cover, 0.0)
    nx, ny, nz = qx * z - Cf[k, 0], qy * z - Cf[k, 1], z - Cf[k, 2]
    return idx, rank[k], cover, (nx * light[0] + ny * light[1] + nz * light[2]) / np.float32(R)


def _empty():
    return np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0), np.zeros(0)


@lru_cache(maxsize=2)
def _buffers(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel scratch (rank, coverage) for `_composite`, kept between frames: -1 and 0 except
    while a composite runs (it resets what it touched)."""
    return np.full(size, -1, np.int32), np.zeros(size, np.float32)


def _composite(flat: np.ndarray, idx: np.ndarray, rank: np.ndarray, cover: np.ndarray, value: np.ndarray) -> None:
    """Lay each (pixel, rank) sample over the image, lower ranks first where samples share a pixel:
    peel off the highest rank at each pixel until none is left, then composite the layers from the
    last peeled (the lowest ranks) to the first.  A sample under one that covers its pixel whole
    is dropped."""
    if np.count_nonzero(cover == 0.0):
        keep = np.flatnonzero(cover > 0.0)
        idx, rank, cover, value = idx[keep], rank[keep], cover[keep], value[keep]
    owner, over = _buffers(flat.size)
    layers = []
    rest = None
    touched = []
    while True:
        i, r = (idx, rank) if rest is None else (idx[rest], rank[rest])
        if not i.size:
            break
        np.maximum.at(owner, i, r)
        top = np.take(owner, i) == r
        lay = np.flatnonzero(top) if rest is None else rest[top]
        layers.append(lay)
        owner[i] = -1
        below = np.flatnonzero(~top) if rest is None else rest[~top]
        if rest is None:                 # what the nearest layer leaves showing, per pixel
            over[idx[lay]] = cover[lay]
            touched.append(idx[lay])
            below = below[np.take(over, idx[below]) < 0.999]
        rest = below
    for t in touched:
        over[t] = 0.0
    for lay in reversed(layers):
        i = idx[lay]
        px = np.take(flat, i)
        flat[i] = px + cover[lay] * (value[lay] - px)
