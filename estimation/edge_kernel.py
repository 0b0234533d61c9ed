"""One pass of the edge fit (`tag_quads.fit_quads`), compiled: every row's window, the edges'
levels, the occlusion tests, the crossings, and the straight lines through them.

Why.  Written in numpy (`tag_quads._fit_pass_numpy`, the readable form, kept as the reference),
one pass made ~100 array calls whatever the number of tags: ~1.5 ms a pass for four tags as for
twenty, and a frame takes 4 passes on the photograph and 6-7 more on the blur-bias model's image.
The pass is arithmetic over a few thousand rows of 7-11 pixels; compiled by numba it is a loop.

The numbers are `_fit_pass_numpy`'s: the same operations in the same order, rows summed one after
another as `np.bincount` sums them (a window's pixels are summed in order, where numpy's pairwise
sum may round the last bit differently).  tests/test_edge_kernel.py holds the two together on
rendered frames, noisy, blurred and occluded, to 1e-9 px.  The lens is the caller's: the crossings
come out in image pixels, the caller undistorts them (`tag_quads._undistort`), and the lines are
fitted in a second call.

Constants are passed in, not imported, so the kernel reads them from `tag_quads` where they are
explained; CELLS, the tag's 8x8 grid, is written here too (`tag_quads` imports this module, not
the other way round)."""

from __future__ import annotations

import math

import numba
import numpy as np

CELLS = 8


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _bilinear(g: np.ndarray, x: float, y: float) -> float:
    H, W = g.shape
    x = min(max(x, 0.0), W - 1.001)
    y = min(max(y, 0.0), H - 1.001)
    x0 = int(x)
    y0 = int(y)
    fx, fy = x - x0, y - y0
    return ((g[y0, x0] * (1 - fx) + g[y0, x0 + 1] * fx) * (1 - fy)
            + (g[y0 + 1, x0] * (1 - fx) + g[y0 + 1, x0 + 1] * fx) * fy)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _lower_median(v: np.ndarray, use: np.ndarray, lo: int, hi: int, min_rows: int) -> float:
    """The lower median of v[lo:hi] where `use` (np.nan below `min_rows` values), as
    `tag_quads._odd_rows` takes it."""
    n = 0
    for i in range(lo, hi):
        if use[i]:
            n += 1
    if n < min_rows:
        return np.nan
    buf = np.empty(n)
    n = 0
    for i in range(lo, hi):
        if use[i]:
            buf[n] = v[i]
            n += 1
    buf.sort()
    return buf[(n - 1) // 2]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def square_to_quad(q: np.ndarray) -> np.ndarray:
    """The homography taking the unit square's corners (0,0), (1,0), (1,1), (0,1) to the quad's
    (4, 2), in closed form (Heckbert 1989): (h0..h7), x = (h0 u + h1 v + h2) / (h6 u + h7 v + 1),
    y = (h3 u + h4 v + h5) / (the same); nan for a degenerate quad."""
    x0, y0, x1, y1, x2, y2, x3, y3 = q[0, 0], q[0, 1], q[1, 0], q[1, 1], q[2, 0], q[2, 1], q[3, 0], q[3, 1]
    sx, sy = x0 - x1 + x2 - x3, y0 - y1 + y2 - y3
    dx1, dx2, dy1, dy2 = x1 - x2, x3 - x2, y1 - y2, y3 - y2
    den = dx1 * dy2 - dx2 * dy1
    hg = (sx * dy2 - dx2 * sy) / den
    hh = (dx1 * sy - sx * dy1) / den
    return np.array([x1 - x0 + hg * x1, x3 - x0 + hh * x3, x0, y1 - y0 + hg * y1, y3 - y0 + hh * y3, y0, hg, hh])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def squares_to_quads(q: np.ndarray) -> np.ndarray:
    """`square_to_quad` of every quad (N, 4, 2): (N, 8)."""
    out = np.empty((q.shape[0], 8))
    for k in range(q.shape[0]):
        out[k] = square_to_quad(q[k])
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def tag_levels(g: np.ndarray, q: np.ndarray) -> tuple[float, float]:
    """One tag's black and white (`tag_quads._tag_levels`): Otsu's two clusters of its 64 cell
    centres, sampled through the homography of the unit square onto the quad (4, 2)."""
    h = square_to_quad(q)
    s = np.empty(CELLS * CELLS)
    for r in range(CELLS):
        for c in range(CELLS):
            u, v = (c + 0.5) / CELLS, (r + 0.5) / CELLS
            X = h[0] * u + h[1] * v + h[2]
            Y = h[3] * u + h[4] * v + h[5]
            Z = h[6] * u + h[7] * v + 1.0
            s[r * CELLS + c] = _bilinear(g, X / Z, Y / Z)
    s.sort()
    n = len(s)
    total = 0.0
    for i in range(n):
        total += s[i]
    best, best_k, best_m0, best_m1 = -1.0, 1, 0.0, 0.0
    csum = 0.0
    for k in range(1, n):
        csum += s[k - 1]
        m0 = csum / k
        m1 = (total - csum) / (n - k)
        score = k * (n - k) * (m1 - m0) ** 2
        if score > best:
            best, best_k, best_m0, best_m1 = score, k, m0, m1
    return best_m0, best_m1


@numba.njit(cache=True, nogil=True, error_model="numpy")
def edge_geometry(q: np.ndarray, coarse: bool, min_reach: float, max_reach: float, coarse_px: float,
                  coarse_cells: float) -> np.ndarray:
    """Per edge (N * 4, 12; edge i from corner i to i + 1): the cell across it, the windows' reach
    across it, its outward normal (2), whether its rows are image rows (1.0) or columns, the
    windows' half-width along the scan, the normal's sign along the scan, its first and last row,
    its first corner's scan and row coordinates, and the slope of scan on row."""
    N = q.shape[0]
    out = np.zeros((N * 4, 12))
    for k in range(N):
        for e in range(4):
            a, b = q[k, e], q[k, (e + 1) % 4]
            pa, nb = q[k, (e + 3) % 4], q[k, (e + 2) % 4]
            sx, sy = b[0] - a[0], b[1] - a[1]
            length = math.sqrt(sx * sx + sy * sy)
            ux, uy = sx / length, sy / length
            nx, ny = uy, -ux
            px_, py_ = a[0] - pa[0], a[1] - pa[1]                 # the previous edge's vector
            qx_, qy_ = nb[0] - b[0], nb[1] - b[1]                 # the next edge's
            cell = min(abs(px_ * nx + py_ * ny), abs(qx_ * nx + qy_ * ny)) / CELLS
            if coarse:
                reach = min(max(coarse_cells * cell, min_reach), coarse_px)
            else:
                reach = min(max(cell - 2.5, min_reach), max_reach)
            lp = math.sqrt(px_ * px_ + py_ * py_)
            lq = math.sqrt(qx_ * qx_ + qy_ * qy_)
            upx, upy = px_ / lp, py_ / lp
            uqx, uqy = qx_ / lq, qy_ / lq
            sin_end = max(min(abs(upx * uy - upy * ux), abs(ux * uqy - uy * uqx)), 0.3)
            rows_axis = abs(uy) >= abs(ux)
            if rows_axis:
                ps, pr, qs, qr, ns, ur = a[0], a[1], b[0], b[1], nx, abs(uy)
            else:
                ps, pr, qs, qr, ns, ur = a[1], a[0], b[1], b[0], ny, abs(ux)
            margin = (reach + 1.5) / sin_end + 0.02 * length
            r_lo = math.ceil(min(pr, qr) + margin * ur)
            r_hi = math.floor(max(pr, qr) - margin * ur)
            slope = (qs - ps) / (qr - pr) if qr != pr else np.nan
            o = out[k * 4 + e]
            o[0], o[1], o[2], o[3] = cell, reach, nx, ny
            o[4] = 1.0 if rows_axis else 0.0
            o[5] = reach / abs(ns)
            o[6] = 1.0 if ns > 0 else (-1.0 if ns < 0 else 0.0)
            o[7], o[8] = r_lo, r_hi
            o[9], o[10], o[11] = ps, pr, slope
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def crossings(g: np.ndarray, q: np.ndarray, geo: np.ndarray, coarse: bool, check: np.ndarray,
              quiet_zone: bool, consts: np.ndarray):
    """Every row's crossing (image px) and what the line fit needs of it; see `_fit_pass_numpy`.
    Returns (edge_of (R,), points (R, 2), row_ok (R,), occluded (R,), lvl_ok (R,))."""
    (min_rows, min_contrast, tol_frac, noise_sigmas, occ_min_cell, occ_abs_min_cell, max_drop, far_px,
     min_contrast_share, guard, edge_levels_min_cell) = (consts[0], consts[1], consts[2], consts[3], consts[4],
                                                         consts[5], consts[6], consts[7], consts[8],
                                                         int(consts[9]), consts[10])
    H, W = g.shape
    N = q.shape[0]
    E = N * 4
    count = np.zeros(E, np.int64)
    m_max_f = 0.0
    for e in range(E):
        count[e] = max(int(geo[e, 8] - geo[e, 7] + 1), 0)
        m_max_f = max(m_max_f, geo[e, 5])
    R = int(count.sum())
    edge_of = np.empty(R, np.int64)
    start = np.zeros(E + 1, np.int64)
    for e in range(E):
        start[e + 1] = start[e] + count[e]
        edge_of[start[e]:start[e + 1]] = e
    pts = np.zeros((R, 2))
    row_ok = np.zeros(R, np.bool_)
    occluded = np.zeros(R, np.bool_)
    lvl_ok = np.zeros(R, np.bool_)
    if R == 0:
        return edge_of, pts, row_ok, occluded, lvl_ok
    m_max = int(math.ceil(m_max_f + 0.5))
    L = 2 * m_max + 1
    vals = np.zeros((R, L))
    wgt = np.zeros((R, L))
    inside = np.zeros((R, L), np.bool_)
    s_line = np.empty(R)
    rr = np.empty(R)
    v_dark = np.empty(R)
    v_bright = np.empty(R)
    p_on = np.empty((R, 2))
    for e in range(E):
        cell, reach, nx, ny, rows_axis = geo[e, 0], geo[e, 1], geo[e, 2], geo[e, 3], geo[e, 4] > 0.5
        Ae, sgn, r_lo, ps, pr, slope = geo[e, 5], geo[e, 6], geo[e, 7], geo[e, 9], geo[e, 10], geo[e, 11]
        for i in range(start[e], start[e + 1]):
            r = r_lo + (i - start[e])
            sl = ps + (r - pr) * slope
            s_line[i] = sl
            rr[i] = r
            centre = np.rint(sl if math.isfinite(sl) else 0.0)
            ok = math.isfinite(sl)
            for j in range(L):
                sp = centre + (j - m_max)
                lo = max(sp - 0.5, sl - Ae)
                hi = min(sp + 0.5, sl + Ae)
                w = min(max(hi - lo, 0.0), 1.0)
                wgt[i, j] = w
                xi, yi = (int(sp), int(r)) if rows_axis else (int(r), int(sp))
                ins = xi >= 0 and xi < W and yi >= 0 and yi < H
                inside[i, j] = ins
                if not (ins or w == 0 or (sp - sl) * sgn > 0):
                    ok = False
                vals[i, j] = g[min(max(yi, 0), H - 1), min(max(xi, 0), W - 1)]
            row_ok[i] = ok
            ox, oy = (sl, r) if rows_axis else (r, sl)
            p_on[i, 0], p_on[i, 1] = ox, oy
            dx, dy = ox - reach * nx, oy - reach * ny
            bx, by = ox + reach * nx, oy + reach * ny
            lvl_ok[i] = (dx >= 0 and dx <= W - 1 and dy >= 0 and dy <= H - 1 and bx >= 0 and bx <= W - 1
                         and by >= 0 and by <= H - 1 and math.isfinite(sl))
            v_dark[i] = _bilinear(g, dx, dy)
            v_bright[i] = _bilinear(g, bx, by)
    # each edge's median levels and its odd rows (`_odd_rows`)
    dark_m = np.full(E, np.nan)
    bright_m = np.full(E, np.nan)
    bad = np.zeros(R, np.bool_)
    dev = np.empty(R)
    for e in range(E):
        a, b = start[e], start[e + 1]
        dark_m[e] = _lower_median(v_dark, lvl_ok, a, b, min_rows)
        bright_m[e] = _lower_median(v_bright, lvl_ok, a, b, min_rows)
        tol = tol_frac * (bright_m[e] - dark_m[e])
        for side in range(2):
            v = v_dark if side == 0 else v_bright
            m = dark_m[e] if side == 0 else bright_m[e]
            for i in range(a, b):
                dev[i] = abs(v[i] - m) if lvl_ok[i] else 0.0
            spread = 1.4826 * _lower_median(dev, lvl_ok, a, b, min_rows)
            t = spread * noise_sigmas if math.isnan(tol) else (tol if math.isnan(spread) else
                                                              max(tol, noise_sigmas * spread))
            for i in range(a, b):
                if lvl_ok[i] and tol > 0 and dev[i] > t:
                    bad[i] = True
    # occlusion tests on edges of cells large enough, and the tag levels where an edge needs them
    t_dark = np.full(N, np.nan)
    t_bright = np.full(N, np.nan)
    have = np.zeros(N, np.bool_)
    for e in range(E):
        k = e // 4
        cell = geo[e, 0]
        chk = check[k] and cell >= occ_min_cell
        if not chk:
            for i in range(start[e], start[e + 1]):
                bad[i] = False
        if quiet_zone and chk and cell >= occ_abs_min_cell:
            if not have[k]:
                t_dark[k], t_bright[k] = tag_levels(g, q[k])
                have[k] = True
            c_tag = t_bright[k] - t_dark[k]
            reach, nx, ny = geo[e, 1], geo[e, 2], geo[e, 3]
            far = min(reach + far_px, 0.75 * cell)
            short = bright_m[e] - dark_m[e] < min_contrast_share * c_tag
            for i in range(start[e], start[e + 1]):
                fx, fy = p_on[i, 0] + far * nx, p_on[i, 1] + far * ny
                in_far = fx >= 0 and fx <= W - 1 and fy >= 0 and fy <= H - 1
                if lvl_ok[i] and in_far and v_bright[i] - _bilinear(g, fx, fy) > max_drop * c_tag:
                    bad[i] = True
                if short and lvl_ok[i]:
                    bad[i] = True
    for e in range(E):   # `_dilate`: `guard` rows either side of a bad one, on the same edge
        a, b = start[e], start[e + 1]
        for i in range(a, b):
            if bad[i]:
                for j in range(max(a, i - guard), min(b, i + guard + 1)):
                    occluded[j] = True
    # an edge's own levels where it has enough clean rows and cells large enough; else its tag's
    dark = dark_m.copy()
    bright = bright_m.copy()
    own = np.zeros(E, np.bool_)
    for e in range(E):
        n_lvl = 0
        for i in range(start[e], start[e + 1]):
            if lvl_ok[i] and not occluded[i]:
                n_lvl += 1
        own[e] = n_lvl >= min_rows and geo[e, 0] >= edge_levels_min_cell
    for k in range(N):
        if own[4 * k] and own[4 * k + 1] and own[4 * k + 2] and own[4 * k + 3]:
            continue
        if not have[k]:
            t_dark[k], t_bright[k] = tag_levels(g, q[k])
            have[k] = True
        for e in range(4 * k, 4 * k + 4):
            if not own[e]:
                dark[e], bright[e] = t_dark[k], t_bright[k]
    fn = np.empty(L)
    step = np.empty(L - 1)
    for e in range(E):
        contrast = bright[e] - dark[e]
        Ae, sgn, rows_axis = geo[e, 5], geo[e, 6], geo[e, 4] > 0.5
        for i in range(start[e], start[e + 1]):
            sl = s_line[i]
            for j in range(L):
                if not inside[i, j]:
                    fn[j] = 1.0
                elif contrast > 0:
                    fn[j] = (vals[i, j] - dark[e]) / contrast
                else:
                    fn[j] = np.nan
            centre = np.rint(sl if math.isfinite(sl) else 0.0)
            if coarse:
                best_j, best = 0, -np.inf
                for j in range(L - 1):
                    if wgt[i, j + 1] > 0 and wgt[i, j] > 0:
                        step[j] = sgn * (fn[j + 1] - fn[j])
                    else:
                        step[j] = -np.inf
                    if step[j] > best:
                        best, best_j = step[j], j
                j = min(max(best_j, 1), L - 3)
                y0, y1, y2 = step[j - 1], step[j], step[j + 1]
                if not math.isfinite(y0):
                    y0 = y1
                if not math.isfinite(y2):
                    y2 = y1
                den = y0 - 2 * y1 + y2
                frac = 0.5 * (y0 - y2) / den if den < -1e-9 else 0.0
                cross = centre + (j - m_max) + 0.5 + min(max(frac, -0.5), 0.5)
                if not (y1 >= 0.25):
                    row_ok[i] = False
            else:
                bright_len = 0.0
                for j in range(L):
                    bright_len += wgt[i, j] * fn[j]
                cross = sl + Ae - bright_len if sgn > 0 else sl - Ae + bright_len
            if not (abs(cross - sl) <= Ae) or not (contrast >= min_contrast) or occluded[i]:
                row_ok[i] = False
            c = cross if math.isfinite(cross) else 0.0
            if rows_axis:
                pts[i, 0], pts[i, 1] = c, rr[i]
            else:
                pts[i, 0], pts[i, 1] = rr[i], c
    return edge_of, pts, row_ok, occluded, lvl_ok


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fit_lines(edge_of: np.ndarray, pts: np.ndarray, row_ok: np.ndarray, occluded: np.ndarray, lvl_ok: np.ndarray,
              E: int, min_rows: float) -> tuple:
    """Total-least-squares lines through each edge's crossings (`pts` undistorted), fitted, the
    crossings more than 3 rms (or 0.1 px) off dropped, refitted.  Returns per edge: centroid (E, 2),
    angle (E,), fitted (E,), rms (E,), the fit's statistics for `_corner_sigma` (E, 3) and the share
    of its rows occluded (E,)."""
    R = len(edge_of)
    keep = row_ok.copy()
    S1 = np.zeros(E)
    mx = np.zeros(E)
    my = np.zeros(E)
    theta = np.zeros(E)
    rms = np.zeros(E)
    fitted = np.zeros(E, np.bool_)
    for it in range(2):
        S1[:] = 0.0
        sx = np.zeros(E)
        sy = np.zeros(E)
        for i in range(R):
            if keep[i]:
                e = edge_of[i]
                S1[e] += 1.0
                sx[e] += pts[i, 0]
                sy[e] += pts[i, 1]
        for e in range(E):
            fitted[e] = S1[e] >= min_rows
            S1[e] = max(S1[e], 1.0)
            mx[e] = sx[e] / S1[e]
            my[e] = sy[e] / S1[e]
        cxx = np.zeros(E)
        cxy = np.zeros(E)
        cyy = np.zeros(E)
        for i in range(R):
            if keep[i]:
                e = edge_of[i]
                dx, dy = pts[i, 0] - mx[e], pts[i, 1] - my[e]
                cxx[e] += dx * dx
                cxy[e] += dx * dy
                cyy[e] += dy * dy
        ss = np.zeros(E)
        for e in range(E):
            theta[e] = 0.5 * math.atan2(2.0 * cxy[e], cxx[e] - cyy[e])
        for i in range(R):
            if keep[i]:
                e = edge_of[i]
                res = -(pts[i, 0] - mx[e]) * math.sin(theta[e]) + (pts[i, 1] - my[e]) * math.cos(theta[e])
                ss[e] += res * res
        for e in range(E):
            rms[e] = math.sqrt(ss[e] / S1[e])
        if it == 0:
            nxt = np.zeros(R, np.bool_)
            for i in range(R):
                e = edge_of[i]
                res = -(pts[i, 0] - mx[e]) * math.sin(theta[e]) + (pts[i, 1] - my[e]) * math.cos(theta[e])
                nxt[i] = row_ok[i] and abs(res) <= max(3.0 * rms[e], 0.1)
            keep = nxt
    stats = np.zeros((E, 3))
    vt = np.zeros(E)
    n = np.zeros(E)
    n_rows = np.zeros(E)
    n_occ = np.zeros(E)
    for i in range(R):
        e = edge_of[i]
        if keep[i]:
            t = (pts[i, 0] - mx[e]) * math.cos(theta[e]) + (pts[i, 1] - my[e]) * math.sin(theta[e])
            vt[e] += t * t
            n[e] += 1.0
        if lvl_ok[i]:
            n_rows[e] += 1.0
            if occluded[i]:
                n_occ[e] += 1.0
    occ = np.zeros(E)
    for e in range(E):
        stats[e, 0] = max(rms[e] * math.sqrt(n[e] / max(n[e] - 2, 1.0)), 0.02)
        stats[e, 1] = n[e]
        stats[e, 2] = vt[e] / S1[e]
        occ[e] = n_occ[e] / max(n_rows[e], 1.0)
    centroid = np.empty((E, 2))
    centroid[:, 0] = mx
    centroid[:, 1] = my
    return centroid, theta, fitted, rms, stats, occ
