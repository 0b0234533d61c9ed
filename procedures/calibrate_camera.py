"""Camera intrinsic calibration with a ChArUco board, or a plain chessboard (docs/calibration.md).

The pieces, from pixels to the intrinsics file the camera driver reads:

- `BoardSpec` / `parse_board`: the printed board, as a one-line spec `COLSxROWS:SQUARE_MM:MARKER_MM[:DICT]`;
  `ChessboardSpec`: a plain chessboard, `chessboard:COLSxROWS:SQUARE_MM` (inner corners), for
  photographs taken without a ChArUco board (tests/data/chessboard: OpenCV's sample views).
- `BoardDetector`: `cv2.aruco.CharucoDetector` finds the markers, interpolates and sub-pixel refines
  the chessboard corners; `CharucoBoard.matchImagePoints` pairs them with board points.  A frame
  with too few corners, or corners on one line, is rejected with the reason.
  `ChessboardDetector`: `cv2.findChessboardCorners` (then `findChessboardCornersSB`), the whole
  board or nothing, corners refined by `cv2.cornerSubPix`.
- `calibrate`: `cv2.calibrateCameraExtended` on the usable views (k3 fixed unless asked: a mild lens
  does not need it and it over-fits), then views whose reprojection error stands out (an occluded
  corner, motion blur, a mis-refined corner) are dropped one at a time and the fit repeated.
  Reports the RMS reprojection error, each parameter's 1-sigma uncertainty (OpenCV's, scaled by the
  residual), per-view errors and tilts, image coverage, and warnings when the data cannot pin the
  model down (corners only in the middle, no tilted views, large uncertainty).
- `CalibrationSession`: one calibration run, frame by frame (detect, log to the run recorder), then
  `finish()`; `capture_live` fills a session from the rig's camera while prompting the operator.
- `compare_intrinsics`: a recovered model against a known one (the simulated camera's truth), in
  pixels over the whole image as well as parameter by parameter.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import cv2
import numpy as np

from drivers.camera import Intrinsics
from lab.core.errors import UserError

__all__ = [
    "DEFAULT_BOARD", "BoardSpec", "ChessboardSpec", "parse_board", "Detection", "BoardDetector",
    "ChessboardDetector", "make_detector", "ViewResult",
    "CalibrationResult", "NotEnoughViews", "calibrate", "coverage", "compare_intrinsics",
    "CalibrationSession", "read_frames", "capture_live", "IMAGE_SUFFIXES", "VIEW_HINTS",
]

# 9x6 squares of 30 mm (22 mm markers): 270 x 180 mm, fits A4 landscape with a margin.
DEFAULT_BOARD = "9x6:30:22:DICT_5X5_100"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
DEFAULT_MIN_CORNERS = 10
DEFAULT_MIN_FRAMES = 8
# A view is dropped when its RMS error exceeds both this and REJECT_FACTOR x the median view's.
REJECT_FLOOR_PX = 0.5
REJECT_FACTOR = 3.0
COVERAGE_GRID = (8, 6)          # image cells (across, down) for the coverage figure
PARAM_NAMES = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3")


def _dictionaries() -> dict[str, int]:
    return {name[len("DICT_"):].upper(): getattr(cv2.aruco, name) for name in dir(cv2.aruco)
            if name.startswith("DICT_") and isinstance(getattr(cv2.aruco, name), int)}


# ---- the board --------------------------------------------------------------------------------


@dataclass(frozen=True)
class BoardSpec:
    """A printed ChArUco board: `cols` x `rows` chessboard squares of `square_m`, with markers of
    `marker_m` from `dictionary` in the white squares.  `legacy`: the pre-4.6 OpenCV layout (boards
    with an even number of rows printed by old OpenCV versions)."""

    cols: int
    rows: int
    square_m: float
    marker_m: float
    dictionary: str = "DICT_5X5_100"
    legacy: bool = False
    kind = "charuco"            # the recorder's `<kind>_detection` records; not a field
    label = "ChArUco"

    @property
    def n_corners(self) -> int:
        return (self.cols - 1) * (self.rows - 1)

    @property
    def n_markers(self) -> int:
        return self.cols * self.rows // 2

    @property
    def size_m(self) -> tuple[float, float]:
        return self.cols * self.square_m, self.rows * self.square_m

    def text(self) -> str:
        s = f"{self.cols}x{self.rows}:{self.square_m * 1000:g}:{self.marker_m * 1000:g}:{self.dictionary}"
        return s + (":legacy" if self.legacy else "")

    def make(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(_dictionaries()[self.dictionary[len("DICT_"):]])
        board = cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, d)
        board.setLegacyPattern(self.legacy)
        return board


@dataclass(frozen=True)
class ChessboardSpec:
    """A plain chessboard: `cols` x `rows` *inner* corners (OpenCV's pattern size, so a board of
    10 x 7 squares is 9x6), squares of `square_m`.  No markers: the whole board must be in view,
    and its corners are numbered row by row from the one `findChessboardCorners` reports first
    (the board's symmetry leaves that choice open; each view's pose absorbs it, the intrinsics do
    not depend on it)."""

    cols: int
    rows: int
    square_m: float
    kind = "chessboard"
    label = "chessboard"

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    @property
    def size_m(self) -> tuple[float, float]:
        return (self.cols + 1) * self.square_m, (self.rows + 1) * self.square_m

    def text(self) -> str:
        return f"chessboard:{self.cols}x{self.rows}:{self.square_m * 1000:g}"

    def object_points(self) -> np.ndarray:
        """(cols * rows, 3) m, row by row, z = 0: the order findChessboardCorners reports."""
        i, j = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.column_stack([i.ravel(), j.ravel(), np.zeros(i.size)]) * self.square_m


CHESSBOARD_FORMAT = "chessboard:COLSxROWS:SQUARE_MM (inner corners), e.g. chessboard:9x6:25"


def _parse_chessboard(spec: str, parts: list[str]) -> ChessboardSpec:
    def bad(problem: str) -> UserError:
        return UserError(f"board spec {spec!r}: {problem}")

    if len(parts) != 3:
        raise bad(f"expected {CHESSBOARD_FORMAT}")
    try:
        cols, rows = (int(d) for d in parts[1].lower().split("x"))
    except ValueError:
        raise bad(f"inner corners {parts[1]!r}: expected {CHESSBOARD_FORMAT}") from None
    if not (2 <= cols <= 100 and 2 <= rows <= 100):
        raise bad(f"inner corners {cols}x{rows}: each side needs 2..100 inner corners")
    try:
        square_mm = float(parts[2])
    except ValueError:
        raise bad(f"square size {parts[2]!r} must be a number of millimetres; expected {CHESSBOARD_FORMAT}") from None
    if not (math.isfinite(square_mm) and square_mm > 0):
        raise bad(f"square size {parts[2]} mm must be positive")
    return ChessboardSpec(cols, rows, square_mm / 1000.0)


def parse_board(spec: str) -> BoardSpec | ChessboardSpec:
    """`COLSxROWS:SQUARE_MM:MARKER_MM[:DICT][:legacy]`, e.g. `9x6:30:22:DICT_5X5_100` (squares
    counted along the board's long and short side; sizes in millimetres as printed): a ChArUco
    board.  `chessboard:COLSxROWS:SQUARE_MM`, e.g. `chessboard:9x6:25`: a plain chessboard of
    COLS x ROWS inner corners."""
    fmt = f"expected COLSxROWS:SQUARE_MM:MARKER_MM[:DICT][:legacy], e.g. {DEFAULT_BOARD}, or {CHESSBOARD_FORMAT}"

    def bad(problem: str) -> UserError:
        return UserError(f"board spec {spec!r}: {problem}")

    parts = [p.strip() for p in str(spec).strip().split(":")]
    if parts[0].lower() == "chessboard":
        return _parse_chessboard(spec, parts)
    legacy = False
    if parts and parts[-1].lower() == "legacy":
        legacy = True
        parts = parts[:-1]
    if len(parts) not in (3, 4):
        raise bad(fmt)
    dims = parts[0].lower().split("x")
    try:
        cols, rows = (int(d) for d in dims)
    except ValueError:
        raise bad(f"squares {parts[0]!r}: {fmt}") from None
    if not (3 <= cols <= 100 and 3 <= rows <= 100):
        raise bad(f"squares {cols}x{rows}: each side needs 3..100 squares")
    try:
        square_mm, marker_mm = float(parts[1]), float(parts[2])
    except ValueError:
        raise bad(f"square and marker sizes must be numbers of millimetres; {fmt}") from None
    if not (math.isfinite(square_mm) and square_mm > 0):
        raise bad(f"square size {parts[1]} mm must be positive")
    if not (math.isfinite(marker_mm) and 0 < marker_mm < square_mm):
        raise bad(f"marker size {parts[2]} mm must be positive and smaller than the square ({square_mm:g} mm)")
    name = parts[3].upper() if len(parts) == 4 else "DICT_5X5_100"
    key = name[len("DICT_"):] if name.startswith("DICT_") else name
    dicts = _dictionaries()
    if key not in dicts:
        raise bad(f"unknown marker dictionary {parts[3]!r} (known: {', '.join('DICT_' + k for k in sorted(dicts))})")
    board = BoardSpec(cols, rows, square_mm / 1000.0, marker_mm / 1000.0, "DICT_" + key, legacy)
    size = cv2.aruco.getPredefinedDictionary(dicts[key]).bytesList.shape[0]
    if board.n_markers > size:
        raise bad(f"a {cols}x{rows} board needs {board.n_markers} markers but DICT_{key} has only {size}")
    return board


# ---- detection --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Detection:
    """The board as found in one frame.  `corners` (N, 2) px and `ids` (N,) are the chessboard
    corners; `object_points` (N, 3) m the same corners on the board.  `usable` says whether the
    frame can join the calibration; if not, `reason` says why."""

    label: str
    width_px: int
    height_px: int
    markers: int
    corners: np.ndarray
    ids: np.ndarray
    object_points: np.ndarray
    usable: bool
    reason: str = ""

    @property
    def n_corners(self) -> int:
        return int(len(self.ids))


class BoardDetector:
    def __init__(self, board: BoardSpec, min_corners: int = DEFAULT_MIN_CORNERS) -> None:
        if min_corners < 4:
            raise UserError(f"--min-corners {min_corners}: a view needs at least 4 corners to constrain a pose")
        self.spec = board
        self.board = board.make()
        # A board smaller than the threshold can still be used when every corner is seen.
        self.min_corners = min(int(min_corners), board.n_corners)
        params = cv2.aruco.CharucoParameters()
        params.tryRefineMarkers = True   # recover markers the first pass missed, from the board layout
        self._detector = cv2.aruco.CharucoDetector(self.board, params)

    def detect(self, image: np.ndarray, label: str) -> Detection:
        img = np.asarray(image)
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        h, w = img.shape[:2]
        ch_corners, ch_ids, _m_corners, m_ids = self._detector.detectBoard(img)
        markers = 0 if m_ids is None else len(m_ids)
        empty = (np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 3)))
        if ch_ids is None or len(ch_ids) == 0:
            reason = "no board markers found" if markers == 0 else f"{markers} markers but no chessboard corners"
            return Detection(label, w, h, markers, *empty, usable=False, reason=reason)
        obj, imgp = self.board.matchImagePoints(ch_corners, ch_ids)
        corners = np.asarray(imgp, dtype=np.float64).reshape(-1, 2)
        ids = np.asarray(ch_ids, dtype=int).ravel()
        obj = np.asarray(obj, dtype=np.float64).reshape(-1, 3)
        reason = ""
        if len(ids) < self.min_corners:
            reason = f"only {len(ids)} chessboard corners found (need at least {self.min_corners})"
        elif self.board.checkCharucoCornersCollinear(ch_ids):
            reason = f"the {len(ids)} corners found lie on one line"
        return Detection(label, w, h, markers, corners, ids, obj, usable=not reason, reason=reason)


# The sub-pixel window reaches this fraction of the shortest square side either side of a corner
# (clamped to CHESSBOARD_WINDOW_PX): clear of the neighbouring corners and their blur, where a
# lens's curvature of the edges is still small.  On OpenCV's sample photographs (tests/data/
# chessboard) a fixed 11 px half-window, what OpenCV's calibration sample uses, reaches past
# the shortest squares (19-22 px) and gives 0.41 px RMS; a quarter of the side gives 0.19 px.
CHESSBOARD_WINDOW_FRACTION = 0.25
CHESSBOARD_WINDOW_PX = (2, 11)


class ChessboardDetector:
    """A plain chessboard (`ChessboardSpec`): every inner corner or none.  `cv2.findChessboardCorners`
    (adaptive threshold, normalised image), failing that `cv2.findChessboardCornersSB`; the corners
    then refined by `cv2.cornerSubPix` with a half-window a quarter of the frame's shortest square."""

    def __init__(self, board: ChessboardSpec, min_corners: int = DEFAULT_MIN_CORNERS) -> None:
        if min_corners < 4:
            raise UserError(f"--min-corners {min_corners}: a view needs at least 4 corners to constrain a pose")
        self.spec = board
        self.min_corners = min(int(min_corners), board.n_corners)
        self._object = board.object_points()

    def detect(self, image: np.ndarray, label: str) -> Detection:
        img = np.asarray(image)
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        h, w = img.shape[:2]
        pattern = (self.spec.cols, self.spec.rows)
        found, c = cv2.findChessboardCorners(
            img, pattern, cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            found, c = cv2.findChessboardCornersSB(img, pattern, cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        if not found or c is None or len(c) != self.spec.n_corners:
            return Detection(label, w, h, 0, np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 3)), usable=False,
                             reason=f"no {self.spec.cols}x{self.spec.rows} chessboard found (every inner corner "
                                    f"must be in view)")
        grid = np.asarray(c, np.float64).reshape(self.spec.rows, self.spec.cols, 2)
        spacing = min(np.linalg.norm(np.diff(grid, axis=1), axis=2).min(),
                      np.linalg.norm(np.diff(grid, axis=0), axis=2).min())
        half = int(np.clip(int(CHESSBOARD_WINDOW_FRACTION * spacing), *CHESSBOARD_WINDOW_PX))
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
        c = cv2.cornerSubPix(img, np.asarray(c, np.float32).reshape(-1, 1, 2), (half, half), (-1, -1), crit)
        corners = np.asarray(c, np.float64).reshape(-1, 2)
        return Detection(label, w, h, 0, corners, np.arange(len(corners)), self._object.copy(), usable=True)


def make_detector(board: BoardSpec | ChessboardSpec, min_corners: int = DEFAULT_MIN_CORNERS):
    """The detector for `board`'s kind: `BoardDetector` (ChArUco) or `ChessboardDetector`."""
    if isinstance(board, ChessboardSpec):
        return ChessboardDetector(board, min_corners)
    return BoardDetector(board, min_corners)


# ---- calibration ------------------------------------------------------------------------------


class NotEnoughViews(UserError):
    pass


@dataclass(frozen=True)
class ViewResult:
    label: str
    corners: int
    status: str                 # "used" | "rejected" (detection) | "dropped" (reprojection outlier)
    reason: str = ""
    rms_px: float | None = None
    tilt_deg: float | None = None   # angle between the board's normal and the optical axis


@dataclass
class CalibrationResult:
    intrinsics: Intrinsics
    # OpenCV's figure (calibrateCamera's return value): sqrt(mean over every used corner of the
    # squared distance, in px, between the detected corner and its reprojection); per axis it is
    # this / sqrt(2).
    rms_px: float
    std: dict[str, float]            # 1-sigma of PARAM_NAMES (0 for a parameter held fixed)
    views: list[ViewResult]
    coverage: float                  # fraction of COVERAGE_GRID image cells holding a used corner
    board: BoardSpec | ChessboardSpec
    fit_k3: bool
    warnings: list[str] = field(default_factory=list)
    truth: dict[str, Any] | None = None    # compare_intrinsics against a known model (simulation)

    @property
    def used(self) -> list[ViewResult]:
        return [v for v in self.views if v.status == "used"]

    def to_json(self) -> dict[str, Any]:
        K = self.intrinsics.K
        return {
            "board": self.board.text(),
            "width_px": self.intrinsics.width_px, "height_px": self.intrinsics.height_px,
            "K": np.asarray(K).tolist(), "dist": np.asarray(self.intrinsics.dist).ravel().tolist(),
            "rms_reprojection_px": self.rms_px, "std_1sigma": self.std, "fit_k3": self.fit_k3,
            "coverage": self.coverage, "views_used": len(self.used),
            "views": [{"label": v.label, "corners": v.corners, "status": v.status, "reason": v.reason,
                       "rms_px": v.rms_px, "tilt_deg": v.tilt_deg} for v in self.views],
            "warnings": list(self.warnings), "truth": self.truth,
        }

    def report(self) -> list[str]:
        K, d, s = self.intrinsics.K, np.asarray(self.intrinsics.dist).ravel(), self.std
        n_rej = sum(v.status != "used" for v in self.views)
        tilts = [v.tilt_deg for v in self.used if v.tilt_deg is not None]
        lines = [
            f"views: {len(self.used)} used, {n_rej} rejected of {len(self.views)}; "
            f"corners cover {self.coverage:.0%} of the image; tilts {min(tilts):.0f}-{max(tilts):.0f} deg",
            f"RMS reprojection error: {self.rms_px:.3f} px",
            f"fx = {K[0, 0]:.2f} +- {s['fx_px']:.2f} px   fy = {K[1, 1]:.2f} +- {s['fy_px']:.2f} px",
            f"cx = {K[0, 2]:.2f} +- {s['cx_px']:.2f} px   cy = {K[1, 2]:.2f} +- {s['cy_px']:.2f} px",
            "dist (k1 k2 p1 p2 k3) = " + "  ".join(f"{d[i]:+.5f}+-{s[n]:.5f}" for i, n in
                                                   enumerate(("k1", "k2", "p1", "p2", "k3"))),
        ]
        for v in self.views:
            if v.status != "used":
                lines.append(f"  {v.status} {v.label}: {v.reason}")
        for w in self.warnings:
            lines.append(f"WARNING: {w}")
        if self.truth:
            t = self.truth
            Kt, dt = np.asarray(t["true_K"]), t["true_dist"]
            lines.append(
                f"truth (the simulated true lens): fx = {Kt[0, 0]:.2f} fy = {Kt[1, 1]:.2f} cx = {Kt[0, 2]:.2f} "
                f"cy = {Kt[1, 2]:.2f} px, dist = " + " ".join(f"{x:+.5f}" for x in dt))
            lines.append(
                f"vs truth: fx {t['fx_rel'] * 100:+.3f} %, fy {t['fy_rel'] * 100:+.3f} %, cx {t['cx_px']:+.2f} px, "
                f"cy {t['cy_px']:+.2f} px; whole model: max {t['model_max_px']:.3f} px, rms {t['model_rms_px']:.3f} px "
                f"over the image")
            n = t.get("nominal")
            if n:
                lines.append(
                    f"  (the maker's model, [sim.camera] as sim_camera.json holds it, vs truth: fx {n['fx_rel'] * 100:+.3f} %, "
                    f"cx {n['cx_px']:+.2f} px, cy {n['cy_px']:+.2f} px; whole model max {n['model_max_px']:.3f} px, "
                    f"rms {n['model_rms_px']:.3f} px)")
        return lines


def coverage(detections: Iterable[Detection], width: int, height: int, grid: tuple[int, int] = COVERAGE_GRID) -> float:
    """Fraction of the image's grid cells that hold at least one detected corner: distortion is
    largest at the edges, and only corners there can measure it."""
    gx, gy = grid
    hit = np.zeros((gy, gx), bool)
    for d in detections:
        if d.n_corners:
            i = np.clip((d.corners[:, 0] / width * gx).astype(int), 0, gx - 1)
            j = np.clip((d.corners[:, 1] / height * gy).astype(int), 0, gy - 1)
            hit[j, i] = True
    return float(hit.mean())


def _fit(views: Sequence[Detection], size: tuple[int, int], flags: int):
    obj = [v.object_points.astype(np.float32) for v in views]
    img = [v.corners.astype(np.float32).reshape(-1, 1, 2) for v in views]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    try:
        rms, K, dist, rvecs, _tvecs, std_in, _std_ex, per_view = cv2.calibrateCameraExtended(
            obj, img, size, None, None, flags=flags, criteria=crit)
    except cv2.error as exc:
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise UserError(f"OpenCV could not calibrate from these {len(views)} views ({msg}); "
                        f"take views from more varied positions and angles") from None
    return float(rms), K, dist.ravel(), rvecs, std_in.ravel(), per_view.ravel()


def calibrate(detections: Sequence[Detection], board: BoardSpec | ChessboardSpec, *, fit_k3: bool = False,
              min_frames: int = DEFAULT_MIN_FRAMES) -> CalibrationResult:
    """Intrinsics from the usable detections (all of one image size).  Raises NotEnoughViews when
    fewer than `min_frames` views are usable, saying why the others were rejected."""
    if min_frames < 3:
        raise UserError(f"--min-frames {min_frames}: a calibration needs at least 3 views of the board")
    if not detections:
        raise NotEnoughViews("no frames to calibrate from")
    sizes = {(d.width_px, d.height_px) for d in detections if d.width_px}   # 0: the frame did not decode
    if not sizes:
        raise NotEnoughViews(f"none of the {len(detections)} frames could be read as an image")
    if len(sizes) > 1:
        raise UserError(f"frames of different sizes ({', '.join(f'{w}x{h}' for w, h in sorted(sizes))}): "
                        f"one calibration is for one image size")
    size = sizes.pop()
    usable = [d for d in detections if d.usable]
    rejected = [ViewResult(d.label, d.n_corners, "rejected", d.reason) for d in detections if not d.usable]
    if len(usable) < min_frames:
        why: dict[str, int] = {}
        for d in detections:
            if not d.usable:
                key = "too few corners" if d.reason.startswith("only ") else d.reason
                why[key] = why.get(key, 0) + 1
        detail = "; ".join(f"{n} x {k}" for k, n in why.items())
        raise NotEnoughViews(
            f"{len(usable)} usable views of the board in {len(detections)} frames; a calibration needs at least "
            f"{min_frames} (--min-frames){' (not used: ' + detail + ')' if detail else ''}; show the whole board, "
            f"closer, from more positions and angles")

    flags = 0 if fit_k3 else cv2.CALIB_FIX_K3
    dropped: list[ViewResult] = []
    stuck = ""
    while True:
        rms, K, dist, rvecs, std_in, per_view = _fit(usable, size, flags)
        limit = max(REJECT_FLOOR_PX, REJECT_FACTOR * float(np.median(per_view)))
        worst = int(np.argmax(per_view))
        if per_view[worst] <= limit:
            break
        if len(usable) <= min_frames:
            stuck = f"view {usable[worst].label} stands out ({per_view[worst]:.2f} px, limit {limit:.2f} px) " \
                    f"but dropping it would leave fewer than {min_frames} views: take more views"
            break
        d = usable.pop(worst)
        dropped.append(ViewResult(d.label, d.n_corners, "dropped",
                                  f"reprojection error {per_view[worst]:.2f} px stands out (limit {limit:.2f} px)",
                                  float(per_view[worst])))

    tilts = [math.degrees(math.acos(min(1.0, abs(float(cv2.Rodrigues(r)[0][2, 2]))))) for r in rvecs]
    used = [ViewResult(d.label, d.n_corners, "used", "", float(e), t) for d, e, t in zip(usable, per_view, tilts)]
    order = {d.label: i for i, d in enumerate(detections)}
    views = sorted(used + rejected + dropped, key=lambda v: order.get(v.label, 0))
    std = {n: float(std_in[i]) if i < len(std_in) else 0.0 for i, n in enumerate(PARAM_NAMES)}
    cov = coverage(usable, *size)

    warnings: list[str] = [stuck] if stuck else []
    if rms > 1.0:
        warnings.append(f"RMS reprojection error {rms:.2f} px is high (expect well under 0.5 px): check focus, "
                        f"motion blur, a board that is not flat, or a wrong --board size")
    if cov < 0.5:
        warnings.append(f"corners cover only {cov:.0%} of the image: show the board near the edges and corners, "
                        f"where lens distortion is largest")
    if max(tilts) < 20.0:
        warnings.append(f"no view tilts the board more than {max(tilts):.0f} deg: tilt it 20-45 deg so the focal "
                        f"length is separated from the distance")
    for name, i in (("fx_px", 0), ("fy_px", 1)):
        if std[name] > 0.005 * K[i, i]:
            warnings.append(f"{name} uncertain by {std[name] / K[i, i]:.1%}: take more views, tilted and near the edges")
    for name, i in (("cx_px", 0), ("cy_px", 1)):
        if std[name] > 0.01 * size[i]:
            warnings.append(f"{name} uncertain by {std[name]:.1f} px: take more views from varied angles")

    source = f"lab calibrate camera, {len(used)} {board.label} views (board {board.text()}), RMS {rms:.3f} px"
    intr = Intrinsics(np.asarray(K, dtype=float), np.asarray(dist[:5], dtype=float), size[0], size[1], rms, source)
    return CalibrationResult(intr, rms, std, views, cov, board, fit_k3, warnings)


def compare_intrinsics(estimate: Intrinsics, truth: Intrinsics, grid: int = 24) -> dict[str, Any]:
    """How far `estimate` is from `truth`: parameter by parameter, and as the whole model in pixels
    (a pixel's ray under the true model, projected with the estimated one, over a grid covering the
    image; distortion coefficients trade off against each other, pixels do not)."""
    Ke, Kt = np.asarray(estimate.K, float), np.asarray(truth.K, float)
    de, dt = np.asarray(estimate.dist, float).ravel(), np.asarray(truth.dist, float).ravel()
    n = max(len(de), len(dt), 5)
    de, dt = np.pad(de, (0, n - len(de))), np.pad(dt, (0, n - len(dt)))
    w, h = truth.width_px, truth.height_px
    u, v = np.meshgrid(np.linspace(0, w - 1, grid), np.linspace(0, h - 1, grid))
    pix = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    rays = cv2.undistortPointsIter(pix, Kt, dt, None, None,
                                   (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)).reshape(-1, 2)
    pts = np.column_stack([rays, np.ones(len(rays))])
    proj, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), Ke, de)
    err = np.linalg.norm(proj.reshape(-1, 2) - pix.reshape(-1, 2), axis=1)
    return {
        "true_K": Kt.tolist(), "true_dist": dt[:5].tolist(),
        "fx_rel": float(Ke[0, 0] / Kt[0, 0] - 1.0), "fy_rel": float(Ke[1, 1] / Kt[1, 1] - 1.0),
        "cx_px": float(Ke[0, 2] - Kt[0, 2]), "cy_px": float(Ke[1, 2] - Kt[1, 2]),
        "dist_diff": (de - dt)[:5].tolist(),
        "model_max_px": float(err.max()), "model_rms_px": float(np.sqrt(np.mean(err ** 2))),
    }


# ---- a calibration run ------------------------------------------------------------------------


class CalibrationSession:
    """One calibration: frames go in one at a time (each detected at once, so a live operator
    hears whether it counted), `finish()` calibrates.  With a `recorder` (lab.core.recorder.RunRecorder)
    every frame is a step with its image and detection, and the result a final step with the
    intrinsics as foxglove.CameraCalibration."""

    def __init__(self, board: BoardSpec | ChessboardSpec, *, min_corners: int = DEFAULT_MIN_CORNERS,
                 recorder: Any = None, camera: str = "camera") -> None:
        self.board = board
        self.detector = make_detector(board, min_corners)
        self.recorder = recorder
        self.camera = camera
        self.detections: list[Detection] = []
        self._steps = 0

    @property
    def usable(self) -> int:
        return sum(d.usable for d in self.detections)

    def covered(self) -> float:
        if not self.detections:
            return 0.0
        d0 = self.detections[0]
        return coverage([d for d in self.detections if d.usable], d0.width_px, d0.height_px)

    def add(self, label: str, image: np.ndarray | None, t_s: float | None = None, unreadable: str = "") -> Detection:
        """Detect the board in one frame (`image` None: the frame could not be read, `unreadable`
        says why)."""
        if image is None:
            d = Detection(label, 0, 0, 0, np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 3)), False,
                          unreadable or "cannot be read as an image")
            self.detections.append(d)
            return d
        if self.detections:
            first = next((x for x in self.detections if x.width_px), None)
            if first and (image.shape[1], image.shape[0]) != (first.width_px, first.height_px):
                raise UserError(f"frame {label} is {image.shape[1]}x{image.shape[0]} px but {first.label} is "
                                f"{first.width_px}x{first.height_px} px: one calibration is for one image size")
        self._steps += 1
        if self.recorder is None:
            d = self.detector.detect(image, label)
        else:
            from lab.core.recorder import topics

            with self.recorder.step(f"view {self._steps}", self._steps, {"frame": label}):
                self.recorder.log_image(topics.CAMERA_IMAGE, image, t_s, self.camera)
                d = self.detector.detect(image, label)
                self.recorder.log_json(f"{self.board.kind}_detection", {
                    "frame": label, "markers": d.markers, "corners": d.corners.round(3).tolist(),
                    "ids": d.ids.tolist(), "usable": d.usable, "reason": d.reason}, t_s)
        self.detections.append(d)
        return d

    def finish(self, *, fit_k3: bool = False, min_frames: int = DEFAULT_MIN_FRAMES,
               truth: Intrinsics | None = None, nominal: Intrinsics | None = None) -> CalibrationResult:
        """Calibrate.  truth (simulation): the camera's true lens, which the result is compared with
        (`compare_intrinsics`, in `result.truth`); nominal: the model the camera's maker states (the
        simulated rig's calibration file), compared with the same truth under `truth["nominal"]`,
        so the report says how much the calibration improved on it."""
        if self.recorder is None:
            return self._finish(fit_k3, min_frames, truth, nominal)
        from lab.core.recorder import topics

        self._steps += 1
        with self.recorder.step("calibrate", self._steps, {"fit_k3": fit_k3, "min_frames": min_frames}):
            result = self._finish(fit_k3, min_frames, truth, nominal)
            i = result.intrinsics
            self.recorder.log_calibration(topics.CAMERA_CALIBRATION, i.K, i.dist, i.width_px, i.height_px,
                                          self.camera)
            self.recorder.log_metric("calibration/rms_reprojection_px", result.rms_px, "px")
            self.recorder.log_json("camera_calibration", result.to_json())
            for w in result.warnings:
                self.recorder.log_text("warning", w)
        return result

    def _finish(self, fit_k3: bool, min_frames: int, truth: Intrinsics | None,
                nominal: Intrinsics | None = None) -> CalibrationResult:
        result = calibrate(self.detections, self.board, fit_k3=fit_k3, min_frames=min_frames)
        if truth is not None:
            result.truth = compare_intrinsics(result.intrinsics, truth)
            if nominal is not None:
                n = compare_intrinsics(nominal, truth)
                result.truth["nominal"] = {k: v for k, v in n.items() if k not in ("true_K", "true_dist")}
        return result


def read_frames(directory: str | Path) -> list[tuple[str, np.ndarray | None]]:
    """Every image file in `directory` (sorted by name), as (file name, BGR image or None if it
    does not decode)."""
    d = Path(directory)
    if not d.exists():
        raise UserError(f"frames directory {d}: no such directory")
    if not d.is_dir():
        raise UserError(f"frames directory {d}: not a directory")
    files = sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise UserError(f"frames directory {d}: no image files ({' '.join(IMAGE_SUFFIXES)})")
    return [(p.name, cv2.imread(str(p), cv2.IMREAD_COLOR)) for p in files]


# ---- live capture -----------------------------------------------------------------------------

# Where to hold the board, in turn: every part of the frame, tilted, so that distortion (largest
# at the edges) and focal length (needs tilt) are both measured.
VIEW_HINTS = (
    "in the centre, facing the camera, filling about half the frame",
    "top-left corner, tilted about 30 deg",
    "bottom-right corner, tilted about 30 deg the other way",
    "top-right corner, tilted about 30 deg",
    "bottom-left corner, tilted about 30 deg",
    "top edge, tilted away at the top",
    "bottom edge, tilted away at the bottom",
    "left edge, turned about 30 deg",
    "right edge, turned about 30 deg the other way",
    "in the centre, closer, tilted about 40 deg",
)


def capture_live(session: CalibrationSession, camera: Any, operator: Any, count: int, *, interval_s: float = 1.0,
                 max_attempts: int | None = None, say: Callable[[str], None] = print) -> None:
    """Grab frames from `camera` (drivers.camera.Camera) until `count` usable views are in the
    session.  Interactive: before each grab the operator is told where to hold the board and
    answers capture / skip / done.  `operator.auto`: no prompts, a frame every `interval_s` (the
    operator keeps moving the board).  Stops after `max_attempts` grabs (default 3 x count) so an
    absent board cannot keep it waiting forever."""
    if count < 1:
        raise UserError(f"--count {count}: need at least one view")
    attempts = max_attempts if max_attempts is not None else 3 * count
    tried = 0
    while session.usable < count and tried < attempts:
        hint = VIEW_HINTS[session.usable % len(VIEW_HINTS)]
        k = session.usable + 1
        if not operator.auto:
            answer = operator.ask(f"view {k}/{count}: hold the board {hint}", ("capture", "skip", "done"), "capture")
            if answer == "done":
                break
            if answer == "skip":
                tried += 1
                continue
        elif tried:
            time.sleep(interval_s)
        tried += 1
        frame = camera.grab()
        d = session.add(f"live-{tried:03d}", frame.image, frame.t_s)
        if d.usable:
            say(f"view {k}/{count}: {d.n_corners} corners; corners now cover {session.covered():.0%} of the image")
        else:
            say(f"frame {tried} not used: {d.reason}")
    if session.usable < count:
        say(f"stopped after {tried} frames with {session.usable} usable views (asked for {count})")
