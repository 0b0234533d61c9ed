"""The run's corner factor's arithmetic, compiled: the reprojection error of a tag's four corners and
its Jacobians, in one call, with the intrinsics fixed (a study's graph) or a variable (the rig
survey's, and a calibrated run's graph).

GTSAM's Python `CustomFactor` calls back into Python once per corner factor per relinearisation.
Written in numpy, the callback spent ~22 of its ~32 us in numpy's fixed cost per call on 4-row
arrays, not in arithmetic; compiled by numba the same algebra is a few hundred nanoseconds, and what
is left is the callback itself (reading the two poses out of `gtsam.Values`).  The numbers are
`rig_model.project_corners`' (tests/test_corner_kernel.py holds them to it), with a print scale
and a lens term; a corner on or behind the camera's plane is left to that function (the kernel says
so and computes nothing)."""

from __future__ import annotations

import numba
import numpy as np

# the layout of a factor's constants, one flat array so the call unpacks one argument, not six:
# the four measured corners (u, v each, px), the four corners in the tag frame as printed (x, y, z
# each, m), and minus the lens basis (8 rows of dk1, dk2)
MEAS, LOCAL, MINUS_BASIS, SIZE = 0, 8, 20, 36


def pack(meas: np.ndarray, local: np.ndarray, minus_basis: np.ndarray | None) -> np.ndarray:
    """The constants of one factor in the kernel's layout (`meas` (4, 2) undistorted corners in
    px; `local` (4, 3) m; `minus_basis` (8, 2) or none), or of several at once with a leading
    axis on each ((n, 4, 2), (n, 4, 3), (n, 8, 2) -> (n, SIZE): a view factor's tags)."""
    meas = np.asarray(meas, float)
    lead = meas.shape[:-2]
    c = np.zeros(lead + (SIZE,))
    c[..., MEAS:LOCAL] = meas.reshape(lead + (8,))
    c[..., LOCAL:MINUS_BASIS] = np.asarray(local, float).reshape(lead + (12,))
    if minus_basis is not None:
        c[..., MINUS_BASIS:SIZE] = np.asarray(minus_basis, float).reshape(lead + (16,))
    return c


@numba.njit(cache=True, fastmath=False, nogil=True)
def corner_error(world_T_camera: np.ndarray, world_T_tag: np.ndarray, scale: float, lens: np.ndarray,
                 cal: np.ndarray, c: np.ndarray, want_jacobians: bool, want_calibration: bool, e: np.ndarray,
                 JC: np.ndarray, JT: np.ndarray, Js: np.ndarray, JK: np.ndarray) -> bool:
    """Fill e (8,), and with `want_jacobians` JC and JT (8, 6, GTSAM's tangent, rotation first),
    Js (8, 1), the Jacobian on the print scale, and with `want_calibration` JK (8, 5), on the
    intrinsics: the corner factor of `rig_model` at these 4x4 poses, a tag (1 + `scale`) times its
    printed size, the pinhole `cal` = (fx, fy, s, u0, v0), and the lens variable `lens` ((2,), or
    (0,) for none).  False, with nothing filled, if a corner is not in front of the camera."""
    # camera_T_tag = world_T_camera^-1 world_T_tag
    R = np.empty((3, 3))
    t = np.empty(3)
    for i in range(3):
        for j in range(3):
            R[i, j] = (world_T_camera[0, i] * world_T_tag[0, j] + world_T_camera[1, i] * world_T_tag[1, j]
                       + world_T_camera[2, i] * world_T_tag[2, j])
        t[i] = (world_T_camera[0, i] * (world_T_tag[0, 3] - world_T_camera[0, 3])
                + world_T_camera[1, i] * (world_T_tag[1, 3] - world_T_camera[1, 3])
                + world_T_camera[2, i] * (world_T_tag[2, 3] - world_T_camera[2, 3]))
    k = 1.0 + scale
    q = np.empty((4, 3))
    for p in range(4):
        lx, ly, lz = c[LOCAL + 3 * p], c[LOCAL + 3 * p + 1], c[LOCAL + 3 * p + 2]
        for i in range(3):
            q[p, i] = k * (R[i, 0] * lx + R[i, 1] * ly + R[i, 2] * lz) + t[i]
        if q[p, 2] <= 0.0:
            return False
    fx, fy, sk, u0, v0 = cal[0], cal[1], cal[2], cal[3], cal[4]
    has_lens = lens.shape[0] == 2
    for p in range(4):
        iz = 1.0 / q[p, 2]
        x, y = q[p, 0] * iz, q[p, 1] * iz
        ru, rv = 2 * p, 2 * p + 1
        e[ru] = fx * x + sk * y + (u0 - c[MEAS + ru])
        e[rv] = fy * y + (v0 - c[MEAS + rv])
        if has_lens:
            e[ru] += c[MINUS_BASIS + 2 * ru] * lens[0] + c[MINUS_BASIS + 2 * ru + 1] * lens[1]
            e[rv] += c[MINUS_BASIS + 2 * rv] * lens[0] + c[MINUS_BASIS + 2 * rv + 1] * lens[1]
        if want_jacobians and want_calibration:
            JK[ru, 0], JK[ru, 1], JK[ru, 2], JK[ru, 3], JK[ru, 4] = x, 0.0, y, 1.0, 0.0
            JK[rv, 0], JK[rv, 1], JK[rv, 2], JK[rv, 3], JK[rv, 4] = 0.0, y, 0.0, 0.0, 1.0
        if want_jacobians:
            # the normalised point against the camera's own motion (the interaction matrix), then
            # through the calibration
            xy = x * y
            ju0, ju1, ju2, ju3, ju4, ju5 = xy, -(1.0 + x * x), y, -iz, 0.0, x * iz
            jv0, jv1, jv2, jv3, jv4, jv5 = 1.0 + y * y, -xy, -x, 0.0, -iz, y * iz
            JC[ru, 0] = fx * ju0 + sk * jv0
            JC[ru, 1] = fx * ju1 + sk * jv1
            JC[ru, 2] = fx * ju2 + sk * jv2
            JC[ru, 3] = fx * ju3 + sk * jv3
            JC[ru, 4] = fx * ju4 + sk * jv4
            JC[ru, 5] = fx * ju5 + sk * jv5
            JC[rv, 0] = fy * jv0
            JC[rv, 1] = fy * jv1
            JC[rv, 2] = fy * jv2
            JC[rv, 3] = fy * jv3
            JC[rv, 4] = fy * jv4
            JC[rv, 5] = fy * jv5
    if not want_jacobians:
        return True
    # the tag moves camera_T_tag from the other side: JT = -JC Ad(camera_T_tag), with
    # Ad = [[R, 0], [[t]x R, R]] in GTSAM's (rotation, translation) order
    tR = np.empty((3, 3))
    for j in range(3):
        tR[0, j] = t[1] * R[2, j] - t[2] * R[1, j]
        tR[1, j] = t[2] * R[0, j] - t[0] * R[2, j]
        tR[2, j] = t[0] * R[1, j] - t[1] * R[0, j]
    for r in range(8):
        for j in range(3):
            JT[r, j] = -(JC[r, 0] * R[0, j] + JC[r, 1] * R[1, j] + JC[r, 2] * R[2, j]
                         + JC[r, 3] * tR[0, j] + JC[r, 4] * tR[1, j] + JC[r, 5] * tR[2, j])
            JT[r, 3 + j] = -(JC[r, 3] * R[0, j] + JC[r, 4] * R[1, j] + JC[r, 5] * R[2, j])
        # a corner moves with the tag's scale as with a tag-frame translation by its own position
        p = r // 2
        Js[r, 0] = (JT[r, 3] * c[LOCAL + 3 * p] + JT[r, 4] * c[LOCAL + 3 * p + 1]
                    + JT[r, 5] * c[LOCAL + 3 * p + 2])
    return True


@numba.njit(cache=True, fastmath=False, nogil=True)
def view_errors(world_T_camera: np.ndarray, world_T_tags: np.ndarray, scales: np.ndarray, lens: np.ndarray,
                cal: np.ndarray, c: np.ndarray, inverse_sigma: np.ndarray, huber_k: float, want_jacobians: bool,
                e: np.ndarray, J: np.ndarray, columns: np.ndarray, ok: np.ndarray) -> int:
    """`corner_error` for every tag one view reads, whitened (`whiten_rows`), into one factor's
    error e (8 n,) and, with `want_jacobians`, its Jacobian J (8 n, columns; zero where a row's
    tag is not the column's variable): the camera in columns 0-5; `columns[i]` = (first column of
    tag i's pose (6), of its print scale (1; -1 for none)), `columns[n, 0]` the lens's (2; -1 for
    none).  The intrinsics are fixed.  Returns how many tags have a corner not in front of the
    camera (`ok[i]` False): their rows are left to the caller (`project_corners`' path)."""
    JC, JT, Js, JK = np.empty((8, 6)), np.empty((8, 6)), np.empty((8, 1)), np.empty((8, 5))
    ei = np.empty(8)
    n = world_T_tags.shape[0]
    lens_column = columns[n, 0]
    missing = 0
    for i in range(n):
        ok[i] = corner_error(world_T_camera, world_T_tags[i], scales[i], lens, cal, c[i], want_jacobians, False,
                             ei, JC, JT, Js, JK)
        if not ok[i]:
            missing += 1
            continue
        r0 = 8 * i
        for r in range(8):
            e[r0 + r] = ei[r]
        if want_jacobians:
            tc, sc = columns[i, 0], columns[i, 1]
            for r in range(8):
                for j in range(6):
                    J[r0 + r, j] = JC[r, j]
                    J[r0 + r, tc + j] = JT[r, j]
                if sc >= 0:
                    J[r0 + r, sc] = Js[r, 0]
                if lens_column >= 0:
                    J[r0 + r, lens_column] = c[i, MINUS_BASIS + 2 * r]
                    J[r0 + r, lens_column + 1] = c[i, MINUS_BASIS + 2 * r + 1]
        whiten_rows(e, J, r0, inverse_sigma[i], huber_k, want_jacobians)
    return missing


@numba.njit(cache=True, fastmath=False, nogil=True)
def batch_view_errors(poses: np.ndarray, camera_rows: np.ndarray, tag_rows: np.ndarray, scale_rows: np.ndarray,
                      scales: np.ndarray, lens: np.ndarray, lensed: np.ndarray, cal: np.ndarray, c: np.ndarray,
                      inverse_sigma: np.ndarray, huber_k: np.ndarray, want_jacobians: bool, e: np.ndarray,
                      J: np.ndarray, columns: np.ndarray, first_tag: np.ndarray, first_J: np.ndarray,
                      ok: np.ndarray) -> int:
    """`view_errors` for every view of a batch in one call (`view_batch.ViewBatch`).  `poses`
    (m, 4, 4) every pose of the values; view v reads the camera `poses[camera_rows[v]]` and the
    sightings `first_tag[v]` to `first_tag[v + 1]` of the per-sighting arrays (`tag_rows` into
    `poses`, `scale_rows` into `scales` (-1: none), `c`, `inverse_sigma`, `ok`), the lens if
    `lensed[v]`, its kernel `huber_k[v]`; its error is e[8 first_tag[v]:8 first_tag[v + 1]], its
    Jacobian J[first_J[v]:first_J[v + 1]] column-major (the layout GTSAM's matrices have: each key's
    block is handed over as one contiguous copy), and its `columns` rows first_tag[v] + v on.
    Returns how many sightings have a corner not in front of their camera."""
    missing = 0
    no_lens = lens[:0]
    for v in range(camera_rows.shape[0]):
        t0, t1 = first_tag[v], first_tag[v + 1]
        n = t1 - t0
        tags = np.empty((n, 4, 4))
        sc = np.zeros(n)
        for i in range(n):
            tags[i] = poses[tag_rows[t0 + i]]
            if scale_rows[t0 + i] >= 0:
                sc[i] = scales[scale_rows[t0 + i]]
        Jv = J[first_J[v]:first_J[v + 1]].reshape(((first_J[v + 1] - first_J[v]) // (8 * n), 8 * n)).T
        missing += view_errors(poses[camera_rows[v]], tags, sc, lens if lensed[v] else no_lens, cal, c[t0:t1],
                               inverse_sigma[t0:t1], huber_k[v], want_jacobians, e[8 * t0:8 * t1], Jv,
                               columns[t0 + v:t1 + v + 1], ok[t0:t1])
    return missing


@numba.njit(cache=True, fastmath=False, nogil=True)
def whiten_rows(e: np.ndarray, J: np.ndarray, r0: int, inverse_sigma: float, huber_k: float,
                 want_jacobians: bool) -> None:
    """One tag's 8 rows (from r0) as GTSAM whitens a corner factor with the noise
    `Robust(Huber(huber_k), Isotropic(8, sigma))` (`huber_k` <= 0: no kernel): divided by sigma,
    then, beyond k, scaled by sqrt(k / r) for a linearisation (GTSAM's block reweighting, r the
    whitened 8-vector's norm), and for an error alone by sqrt(2 rho(r)) / r, so that the factor's
    0.5 |e|^2 is the sum of its tags' Huber losses rho, as the single factors' GTSAM error is."""
    norm2 = 0.0
    for r in range(8):
        e[r0 + r] *= inverse_sigma
        norm2 += e[r0 + r] * e[r0 + r]
    g = 1.0
    if huber_k > 0.0:
        norm = np.sqrt(norm2)
        if norm > huber_k:
            if want_jacobians:
                g = np.sqrt(huber_k / norm)
            else:
                g = np.sqrt(2.0 * (huber_k * norm - 0.5 * huber_k * huber_k)) / norm
    if g != 1.0:
        for r in range(8):
            e[r0 + r] *= g
    if want_jacobians:
        f = inverse_sigma * g
        for r in range(8):
            for j in range(J.shape[1]):
                J[r0 + r, j] *= f


@numba.njit(cache=True, fastmath=False, nogil=True)
def tag_step(camera_T_structure: np.ndarray, structure_T_tag: np.ndarray, scale: float, nominal: np.ndarray,
             target: np.ndarray, weight: np.ndarray, cal: np.ndarray, scale_sigma: float, step: np.ndarray) -> bool:
    """One Gauss-Newton step of `rig_model.refine_tag_pose`: the tag's (and with `scale_sigma` > 0
    its print scale's) normal equations over every view's four corners, solved, into `step` (6 or
    7: GTSAM's tangent, rotation first, then the scale).  `camera_T_structure` (n, 4, 4) the views,
    `nominal` (4, 3) the corners in the tag frame as designed, `target` (n, 4, 2) the measured
    corners less the principal point (and the lens correction), `weight` (n,) 1/sigma of each
    view.  False, with nothing solved, if a corner is not in front of a camera."""
    fx, fy, sk = cal[0], cal[1], cal[2]
    k = 7 if scale_sigma > 0.0 else 6
    H = np.zeros((k, k))
    g = np.zeros(k)
    a = np.empty(7)
    m = np.empty((3, 4))
    grow = 1.0 + scale
    for v in range(camera_T_structure.shape[0]):
        for i in range(3):
            for j in range(4):
                m[i, j] = (camera_T_structure[v, i, 0] * structure_T_tag[0, j]
                           + camera_T_structure[v, i, 1] * structure_T_tag[1, j]
                           + camera_T_structure[v, i, 2] * structure_T_tag[2, j]
                           + camera_T_structure[v, i, 3] * structure_T_tag[3, j])
        w = weight[v]
        for c in range(4):
            p0, p1, p2 = grow * nominal[c, 0], grow * nominal[c, 1], grow * nominal[c, 2]
            qx = m[0, 0] * p0 + m[0, 1] * p1 + m[0, 2] * p2 + m[0, 3]
            qy = m[1, 0] * p0 + m[1, 1] * p1 + m[1, 2] * p2 + m[1, 3]
            qz = m[2, 0] * p0 + m[2, 1] * p1 + m[2, 2] * p2 + m[2, 3]
            if qz <= 0.0:
                return False
            iz = 1.0 / qz
            x, y = qx * iz, qy * iz
            uv = (x * fx + y * sk, y * fy)
            for r in range(2):
                # d(pixel r) / d(point in the camera frame), then through R
                j0 = (fx if r == 0 else 0.0) * iz
                j1 = (sk if r == 0 else fy) * iz
                j2 = -uv[r] * iz
                J0 = j0 * m[0, 0] + j1 * m[1, 0] + j2 * m[2, 0]
                J1 = j0 * m[0, 1] + j1 * m[1, 1] + j2 * m[2, 1]
                J2 = j0 * m[0, 2] + j1 * m[1, 2] + j2 * m[2, 2]
                # a right perturbation (w, v) of the tag moves the corner by R (v - p x w)
                a[0] = (p1 * J2 - p2 * J1) * w
                a[1] = (p2 * J0 - p0 * J2) * w
                a[2] = (p0 * J1 - p1 * J0) * w
                a[3], a[4], a[5] = J0 * w, J1 * w, J2 * w
                a[6] = (J0 * nominal[c, 0] + J1 * nominal[c, 1] + J2 * nominal[c, 2]) * w
                e = (uv[r] - target[v, c, r]) * w
                for i in range(k):
                    g[i] += a[i] * e
                    for j in range(k):
                        H[i, j] += a[i] * a[j]
    if k == 7:
        H[6, 6] += 1.0 / scale_sigma ** 2
        g[6] += scale / scale_sigma ** 2
    # H is symmetric positive definite: Cholesky, then the two triangular solves of H step = -g
    L = np.zeros((k, k))
    for i in range(k):
        for j in range(i + 1):
            t = H[i, j]
            for q in range(j):
                t -= L[i, q] * L[j, q]
            if i == j:
                if t <= 0.0:
                    return False
                L[i, i] = np.sqrt(t)
            else:
                L[i, j] = t / L[j, j]
    y = np.empty(k)
    for i in range(k):
        t = -g[i]
        for q in range(i):
            t -= L[i, q] * y[q]
        y[i] = t / L[i, i]
    for i in range(k - 1, -1, -1):
        t = y[i]
        for q in range(i + 1, k):
            t -= L[q, i] * step[q]
        step[i] = t / L[i, i]
    return True


def warm() -> None:
    """Load (or, the first time on a machine, compile) the kernels now: ~0.2 s from numba's cache,
    ~2 s to compile, which a graph pays at construction rather than in its first timed step.  The
    poses in the column-major layout `gtsam.Pose3.matrix()` hands out: numba compiles once per
    array layout."""
    eye = np.asfortranarray(np.eye(4))
    tag = eye.copy(order="F")
    tag[2, 3] = 1.0
    local = np.array([[-0.05, 0.05, 0.0], [0.05, 0.05, 0.0], [0.05, -0.05, 0.0], [-0.05, -0.05, 0.0]])
    c = pack(np.zeros((4, 2)), local, None)
    cal = np.array([900.0, 900.0, 0.0, 640.0, 360.0])
    for want_calibration in (False, True):
        corner_error(eye, tag, 0.0, np.zeros(2), cal, c, True, want_calibration, np.empty(8), np.empty((8, 6)),
                     np.empty((8, 6)), np.empty((8, 1)), np.empty((8, 5)))
    # a batch solve's view factor (`rig_model.corner_view_factor`), with and without Jacobians
    tags = np.empty((1, 4, 4))
    tags[0] = tag
    columns = np.array([[6, 12], [-1, -1]], np.int64)
    for want in (False, True):
        view_errors(eye, tags, np.zeros(1), np.zeros(2), cal, c[None, :], np.ones(1), 1.0, want, np.empty(8),
                    np.zeros((8, 13)), columns, np.empty(1, np.bool_))
    # every view of a batch at once (`view_batch.ViewBatch`), the poses in a table's row-major layout
    poses = np.empty((2, 4, 4))
    poses[0], poses[1] = np.eye(4), tag
    one, none = np.zeros(1, np.int64), np.full(1, -1, np.int64)
    for want in (False, True):
        batch_view_errors(poses, one, one + 1, none, np.zeros(0), np.zeros(2), np.zeros(1, np.bool_), cal,
                          c[None, :], np.ones(1), np.ones(1), want, np.empty(8), np.zeros(8 * 13), columns,
                          np.array([0, 1], np.int64), np.array([0, 8 * 13], np.int64), np.empty(1, np.bool_))
    # a new tag's refined start (`rig_model.refine_tag_pose`), the tag as `Pose3.matrix()` gives it
    camera_T_structure = np.empty((1, 4, 4))
    camera_T_structure[0] = np.eye(4)
    tag_step(camera_T_structure, tag, 0.0, local, np.zeros((1, 4, 2)), np.ones(1), cal, 0.001, np.empty(7))
