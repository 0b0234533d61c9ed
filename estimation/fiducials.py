"""AprilTag 36h11 detection and single-view tag pose, with the pose ambiguity resolved and a
measurement covariance.

- Detection: OpenCV contrib's `ArucoDetector` with the AprilTag 36h11 dictionary finds candidate
  quads and their ids (accepting tags that touch the image border); each quad is then refined by
  fitting its four edges (`estimation.tag_quads.fit_quads`: unbiased to a few thousandths of a pixel
  on area-sampled images, lens distortion taken out) and checked: every edge fitted, straight (rms
  of its row crossings), corners near the detector's quad, the tag's 64 cells read back from
  the refined quad within `max_bit_errors` of the id's pattern, and nothing in front of it: no
  edge more than half occluded (`QuadFit.occluded`) and, for tags with a clear quiet zone (the
  lab's: `DetectorConfig.quiet_zone`), its whole black border and quiet zone reading black and
  white (`tag_quads.ring_deviation`), and no nearer tag's border reaching its black square
  (`partly_hidden`).  A tag failing a check is dropped: its corners are not to
  be trusted at the accuracy the pose and the graph assume (a strut across a tag's quiet zone
  moved its corners by up to 4 px before these checks: docs/fiducials.md, "Occlusion").
- Corners: OpenCV's pixel convention (pixel centres at integer coordinates) and aruco's order:
  the marker's top-left, top-right, bottom-right, bottom-left as OpenCV 4 draws it
  (`cv2.aruco.generateImageMarker`, which the simulator renders), matching `tag_object_points`.
  OpenCV 4's AprilTag markers are the AprilTag project's images turned 180 degrees, so on a tag
  printed from those images corner 0 is the printed bottom-right (docs/fiducials.md).
- Pose: `solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)` returns both solutions of the planar ambiguity.
  The one with the lower reprojection error wins when it is clearly lower (ratio >= 
  `ambiguity_ratio`); otherwise, if a predicted pose is known (design + odometry), the solution
  closer in rotation to the prediction wins; otherwise the lower-error one, marked ambiguous.
- Covariance (GTSAM tangent order: rotation, then translation; in the camera frame): a first-order
  model of a square of size s seen w pixels wide with corner noise sigma_px at distance d and
  viewing angle a: lateral sigma = d sigma_px / f, depth sigma = d^2 sigma_px sqrt2 / (f s),
  rotation about the line of sight sigma_px sqrt2 / w, tilt sigma_px sqrt2 d / (w s / 2) for a
  frontal view (perspective is all that shows it), better when seen obliquely; all scaled up by the
  observed reprojection residual when it is worse than sigma_px.

Poses are in the paper's tag frame (x right, y up, z out of the face): `camera_T_tag`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, Mapping, Sequence

import cv2
import numpy as np

from estimation.quad_bias import blur_bias
from estimation.tag_family import EXTENDED, dictionary, family_for
from estimation.tag_quads import code_bits, edge_blur_px, fit_quads, identify, read_bits, ring_deviation
from lab.core.geometry import Pose3, Rot3

__all__ = ["Detection", "DetectorConfig", "TagDetector", "tag_object_points", "refine_corners_by_edges",
           "apriltag_to_opencv_corners"]


@dataclass(frozen=True)
class Detection:
    tag_id: int
    corners_px: np.ndarray           # (4, 2): OpenCV/aruco order (top-left, top-right, bottom-right, bottom-left)
    camera_T_tag: Pose3              # paper tag frame
    covariance: np.ndarray           # 6x6, tangent order (rot, trans), body frame of the tag pose
    reprojection_px: float           # RMS of the chosen solution
    ambiguity_ratio: float           # reprojection error of the other solution / of the chosen one
    ambiguous: bool                  # the ratio test could not decide and no prediction settled it
    size_m: float

    @property
    def distance_m(self) -> float:
        return float(np.linalg.norm(self.camera_T_tag.translation()))


@dataclass(frozen=True)
class DetectorConfig:
    corner_sigma_px: float = 0.1      # corner noise floor assumed by the covariance model
    ambiguity_ratio: float = 2.0      # min error ratio for the reprojection test to decide alone
    min_side_px: float = 12.0         # smaller tags are too coarse to trust
    max_reprojection_px: float = 3.0  # worse fits are dropped (mis-detections, motion)
    # the refined quad's checks (a tag failing one is dropped)
    max_bit_errors: int = 2           # of the 64 cells (border included) read back from the refined quad
    # A nearer tag whose outer edge (its black square and, with `quiet_zone`, its one-cell quiet
    # zone) comes within this many cells of a tag's black square hides part of it, or of the band
    # the edge fit reads it in: that tag is dropped.  Neither ring nor bit check sees it, because
    # the nearer tag's white border stands in for the quiet zone: a tag half a cell under its
    # neighbour read its left edge 1.9 px off in three views, and its module passed `ok` 2.9 mm off
    # with a 1-sigma of 0.49 mm (docs/fiducials.md, "Occlusion").
    hidden_margin_cells: float | None = 0.5   # None: no such check (studies of what it prevents)
    max_edge_rms_px: float = 0.3      # row crossings about each fitted edge: a straight, clean edge
    max_corner_shift_px: float = 3.5  # from aruco's quad (or 20 % of the side, if larger): its
                                      # unrefined corners are up to ~3 px off on small photographed tags
    max_occluded_share: float = 0.5   # of an edge's rows found occluded (something in front of the
                                      # tag crossing it: tag_quads, docs/fiducials.md); the fit uses the
                                      # rest, and a tag with an edge hidden more than this is dropped
    # The lab's tags have a clear one-cell white quiet zone.  Relying on it: the edge fit takes an
    # edge whose quiet zone reads short of the tag's white as occluded, and the whole quiet zone's
    # ring must read white and the black border's ring black, within `max_ring_deviation` of the
    # tag's contrast, or something is in front of the tag (a strut) and it is dropped
    # (`tag_quads.ring_deviation`).  False: tags printed with less margin, photographs of other
    # people's tags (docs/fiducials.md, "Occlusion").
    quiet_zone: bool = True
    max_ring_deviation: float = 0.35
    # Take the edge fit's own bias off the corners of tags whose cells are small against the blur
    # (`estimation.quad_bias`: under a 1.6 px lens a 4 px cell's square reads 0.05-0.5 px small).
    # Needs the quiet zone (the model draws it).
    correct_blur_bias: bool = True
    # aruco's candidate search runs on a copy of the frame smoothed by a 3 x 3 bilateral filter of
    # this range sigma (grey levels; 0: off); the edge fit, the bits and every check read the frame
    # itself.  Why: on a noisy frame (the realistic default camera: read noise 7 grey levels plus shot
    # noise) aruco's three adaptive thresholds break the flat areas into some 2 x 10^5 speckle
    # contours a frame, and tracing them is most of aruco's time (40 ms of a 1280x720 frame here).  A
    # bilateral filter at ~3 sigma of that noise removes the speckle and keeps the tags' edges (150+
    # grey levels of contrast) and their thinnest foreshortened cells, where a Gaussian of 0.6 px lost
    # 6 of 386 tags of the README's main job.  Measured (docs/fiducials.md, "Time"): the main job's
    # 206 frames, aruco 40 -> 12-15 ms; of their 1158 tags 5 lost and 12 more found, all of them
    # turned ~80 deg (short sides 10-16 px), at the detector's limit either way.  Off for other
    # people's tags (photographs, `quiet_zone=False` studies): on JPEG-q35 copies of the photographs
    # it loses 5 of 54 tags (the filter keeps the compression's block edges and smooths the small
    # tags' cells).
    # None: 20 for the lab's tags (`quiet_zone`), 0 for others.
    candidate_filter_grey: float | None = None


CANDIDATE_FILTER_PX = 3        # `DetectorConfig.candidate_filter_grey`'s neighbourhood (px; spatial sigma half of it)
# ... and its range sigma for the lab's tags (grey levels: ~3 sigma of the default camera's noise)
CANDIDATE_FILTER_GREY = 20.0


@lru_cache(maxsize=64)
def tag_object_points(size_m: float) -> np.ndarray:
    """The black square's corners in aruco's corner order (top-left, top-right, bottom-right,
    bottom-left) for the IPPE_SQUARE solver, in the paper's tag frame: x right, y up, z out of the
    face -- so the solved pose needs no frame change."""
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]], dtype=np.float64)


def apriltag_to_opencv_corners(corners: np.ndarray) -> np.ndarray:
    """Corners as the AprilTag 3 library reports them (`apriltag_detection.p`, e.g. pupil-apriltags'
    `Detection.corners`) -> ours.  AprilTag puts pixel centres at half-integers (x + 0.5) and lists
    the corners counter-clockwise from the bottom-left of the tag as AprilTag prints it; OpenCV 4's
    marker of the same id is that image turned 180 degrees, so its top-left is AprilTag's
    bottom-right: ours = p[[1, 0, 3, 2]] - 0.5."""
    return np.asarray(corners, dtype=np.float64).reshape(4, 2)[[1, 0, 3, 2]] - 0.5


def refine_corners_by_edges(grey: np.ndarray, corners: np.ndarray, samples: int = 12) -> np.ndarray | None:
    """Sub-pixel corners of one tag as intersections of its black square's four fitted edges (see
    `estimation.tag_quads`); None when an edge could not be fitted.  `samples` is no longer used
    (every image row or column crossing an edge is), kept for callers."""
    fit = fit_quads(grey, np.asarray(corners, dtype=np.float64).reshape(1, 4, 2))
    if not fit.edges_fitted.all() or np.max(np.linalg.norm(fit.corners[0] - corners, axis=1)) > 2.5:
        return None
    return fit.corners[0]


def _rolled_like(quads: np.ndarray, rolled: np.ndarray) -> np.ndarray:
    """Each quad's corners cycled to the order of its refined, rolled counterpart (the one of the
    four cyclic orders closest to it)."""
    if len(quads) == 0:
        return quads
    options = np.stack([np.roll(quads, -r, axis=1) for r in range(4)])          # (4, N, 4, 2)
    best = np.argmin(np.linalg.norm(options - rolled[None], axis=3).sum(axis=2), axis=0)
    return options[best, np.arange(len(quads))]


def _overlaps(quads: np.ndarray, others: np.ndarray) -> np.ndarray:
    """Whether each of `quads`' (M, 4, 2) centres lies inside (or on) any of the convex `others`
    (N, 4, 2), either winding: on the same side of, or on, every edge.  One array pass for every
    pair; aruco's candidates are convex (it drops the others), and one `cv2.pointPolygonTest` a
    pair was ~1 ms of a photograph's 10 with 20 tags and 40 rejected quads."""
    if len(quads) == 0 or len(others) == 0:
        return np.zeros(len(quads), bool)
    c = quads.mean(axis=1)[:, None, None, :]                           # (M, 1, 1, 2)
    a = others[None]                                                   # (1, N, 4, 2)
    edge = np.roll(a, -1, axis=2) - a
    to = c - a
    cross = edge[..., 0] * to[..., 1] - edge[..., 1] * to[..., 0]       # (M, N, 4)
    inside = (cross >= 0).all(axis=2) | (cross <= 0).all(axis=2)
    return inside.any(axis=1)


def grown_quad(corners: np.ndarray, cells: float) -> np.ndarray:
    """A tag's black square (4, 2) grown by `cells` of its 8 cells on every side, through the
    square's own homography (so under perspective too)."""
    unit = np.array([[-4.0, -4.0], [4.0, -4.0], [4.0, 4.0], [-4.0, 4.0]], dtype=np.float32)
    H = cv2.getPerspectiveTransform(unit, np.asarray(corners, dtype=np.float32).reshape(4, 2))
    out = cv2.perspectiveTransform((unit * (4.0 + cells) / 4.0).reshape(1, 4, 2), H)
    return out.reshape(4, 2).astype(np.float64)


HIDDEN_MIN_OVERLAP_CELLS2 = 0.25     # an overlap smaller than this (in the farther tag's cells) is a corner's graze


# Predicted planes closer than this where two tags overlap in the image do not say which is in
# front (a module just placed is predicted at its design pose, good to its tolerance at best):
# the centres' distances decide, as without predictions.
HIDDEN_ORDER_MIN_M = 0.002


def plane_order(plane_a: np.ndarray, plane_b: np.ndarray, ray: np.ndarray) -> bool | None:
    """Whether plane a (unit normal and offset in the camera frame, n.X = d) is nearer than plane b
    along the line of sight `ray` (a normalised image point, z = 1); None where the two lie within
    HIDDEN_ORDER_MIN_M of each other there and so say nothing.  `hidden_behind`'s order for two
    predicted tags, and the survey planner's prediction of it."""
    depth_a, depth_b = (p[3] / (p[:3] @ ray) for p in (plane_a, plane_b))
    if abs(depth_a - depth_b) > HIDDEN_ORDER_MIN_M:
        return bool(depth_a < depth_b)
    return None


def partly_hidden(corners: Sequence[np.ndarray], distances: Sequence[float], quiet_cells: float,
                  margin_cells: float) -> set[int]:
    """Indices of the tags a nearer one covers (`hidden_behind`'s keys)."""
    return set(hidden_behind(corners, distances, quiet_cells, margin_cells))


def hidden_behind(corners: Sequence[np.ndarray], distances: Sequence[float], quiet_cells: float,
                  margin_cells: float, planes: np.ndarray | None = None,
                  undistort: Callable[[np.ndarray], np.ndarray] | None = None) -> dict[int, int]:
    """Each tag a nearer one covers -> a tag that covers it (indices into `corners`): the nearer
    tag's outer edge (black square grown by `quiet_cells`) overlaps the other's black square grown
    by `margin_cells` by more than `HIDDEN_MIN_OVERLAP_CELLS2` of its cells (a nearer tag grazing
    a corner of that band, 0.04 of a cell, left the corners unbiased to 0.002 px on a noise-free
    render).  Tags on one flat surface, as designed, never overlap in an image, so an overlap
    means one stands in front of the other: which one, where they meet.

    With `planes` ((n, 4): each tag's predicted plane in the camera frame, unit normal and offset,
    n.X = d; NaN where not predicted) and `undistort` (pixels (k, 2) -> normalised image points),
    the plane nearer along the line of sight through the overlap's centre, when the two differ
    there by more than HIDDEN_ORDER_MIN_M; otherwise the nearer centre.  The centres are right for
    tags at different depths, not for neighbours on one face whose cards a misplaced module pushed
    together: seen from below, the higher reads farther whichever card is on top (N = 8: a clean
    tag dropped in all twelve of its views; one view's poses cannot tell the planes apart, the
    graph's estimate of the misplaced module can: docs/fiducials.md, "Tags hiding tags")."""
    n = len(corners)
    if n < 2:
        return {}
    outer = [grown_quad(c, quiet_cells).astype(np.float32) for c in corners]
    inner = [grown_quad(c, margin_cells).astype(np.float32) for c in corners]
    cell_area = [abs(cv2.contourArea(np.asarray(c, dtype=np.float32).reshape(4, 2))) / 64.0 for c in corners]
    lo = np.array([o.min(axis=0) for o in outer])
    hi = np.array([o.max(axis=0) for o in outer])
    known = np.zeros(n, bool) if planes is None or undistort is None else np.isfinite(planes).all(axis=1)
    out: dict[int, int] = {}
    for i in range(n):
        for j in range(n):
            if i == j or (distances[j] >= distances[i] and not (known[i] and known[j])):
                continue
            if np.any(lo[j] > hi[i]) or np.any(lo[i] > hi[j]):
                continue            # boxes apart: nothing to intersect
            area, shared = cv2.intersectConvexConvex(outer[j], inner[i])
            if area <= HIDDEN_MIN_OVERLAP_CELLS2 * cell_area[i]:
                continue
            j_in_front = distances[j] < distances[i]
            if known[i] and known[j]:
                assert planes is not None and undistort is not None
                x, y = undistort(np.asarray(shared, np.float64).reshape(-1, 2).mean(axis=0)[None]).reshape(2)
                by_planes = plane_order(planes[j], planes[i], np.array([x, y, 1.0]))
                if by_planes is not None:
                    j_in_front = by_planes
            if j_in_front:
                out[i] = j
                break
    return out


BORDER_EDGE_PX = 0.5     # an edge whose ends both lie this near the frame's outermost pixel centres ...
# ... and whose middle lies on or past them


def along_border(corners: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Which quads (N, 4, 2) have an edge along the frame's edge: both its ends within
    BORDER_EDGE_PX of the outermost pixel centres of one side (or past them) and its middle on or
    past them.  Its bright side is off the frame, and the fit's assumption there (the quiet zone
    goes on) read a frontal tag's edge 0.1 px off with its ends on the last row's centres, 0.3 px
    half a pixel past them, and 1.2 px at N = 8 (a tag's bottom edge from 0.4 px inside row 719 to
    0.8 px past it, in eight views); half a pixel inside, 0.03 px.  A tag with only a corner at the
    border keeps its edges' bright sides in the frame (0.02-0.05 px: docs/fiducials.md)."""
    c = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
    h, w = shape[:2]
    # each corner's distance inside the outermost pixel centres of each side (negative: past them)
    inside = np.stack([c[..., 0], w - 1 - c[..., 0], c[..., 1], h - 1 - c[..., 1]], axis=-1)   # (N, 4, 4)
    nxt = np.roll(inside, -1, axis=1)                             # an edge: corner i and corner i + 1
    return ((inside <= BORDER_EDGE_PX) & (nxt <= BORDER_EDGE_PX) & (inside + nxt <= 0.0)).any(axis=(1, 2))


def predicted_planes(poses: Sequence[Pose3 | None]) -> np.ndarray:
    """(n, 4): each predicted camera_T_tag's plane in the camera frame (unit normal, offset: n.X =
    d), NaN where there is no prediction."""
    out = np.full((len(poses), 4), np.nan)
    for k, pose in enumerate(poses):
        if pose is not None:
            normal = pose.rotation().matrix()[:, 2]
            out[k] = (*normal, float(normal @ pose.translation()))
    return out


class TagDetector:
    """Detects AprilTag 36h11 tags and estimates their poses.  `sizes` gives the black-square
    edge per tag id (unknown ids are ignored: they are not ours).  Ids beyond 36h11's 587 are read
    in the lab's extension of it (`estimation.tag_family`); a detector whose ids fit 36h11 reads
    36h11 alone, at its larger Hamming distance."""

    def __init__(self, K: np.ndarray, dist: np.ndarray | Sequence[float], sizes: Mapping[int, float],
                 config: DetectorConfig | None = None) -> None:
        self.K = np.asarray(K, dtype=np.float64)
        self.dist = np.asarray(dist, dtype=np.float64).reshape(-1)
        self.sizes = dict(sizes)
        self.config = config or DetectorConfig()
        params = cv2.aruco.DetectorParameters()
        # our edge fit replaces aruco's corner refinement (cornerSubPix reads a dark square ~0.4 px
        # small); tags touching the image border are kept (its default drops them within 3 px)
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        params.minDistanceToBorder = 0
        # aruco reads bits from its coarse quad and misses tags the AprilTag library reads; let it
        # propose with up to its dictionary's 5 corrected bits and decide on our own read of the
        # refined quad (`max_bit_errors`)
        params.errorCorrectionRate = 1.0
        self.family = family_for(max(self.sizes, default=0)) or EXTENDED
        self._detector = cv2.aruco.ArucoDetector(dictionary(self.family), params)
        self._codes = code_bits(self.family)
        self._allowed = np.array(sorted(t for t in self.sizes if 0 <= t < len(self._codes)), dtype=np.int64)

    def detect(self, image: np.ndarray,
               predict: Callable[[int], Pose3 | None] | None = None) -> list[Detection]:
        """Tags in `image` (BGR or grey).  `predict(tag_id)` may return the expected camera_T_tag
        (from the design and the camera's kinematics) to settle ambiguous poses."""
        return self.detect_with_hidden(image, predict)[0]

    def detect_with_hidden(self, image: np.ndarray, predict: Callable[[int], Pose3 | None] | None = None
                           ) -> tuple[list[Detection], dict[int, int]]:
        """`detect`, and the tags read but dropped as partly behind another (`hidden_behind`, which
        orders two overlapping tags by `predict`'s planes where it can): tag id -> the id of a tag
        in front of it (what a run says of a tag it could not use)."""
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        out: list[Detection] = []
        for tid, c in zip(*self.find(grey)):
            det = self._pose(tid, c, predict)
            if det is not None:
                out.append(det)
        behind: dict[int, int] = {}
        if self.config.hidden_margin_cells is not None:
            hidden = hidden_behind([d.corners_px for d in out],
                                   [float(np.linalg.norm(d.camera_T_tag.translation())) for d in out],
                                   1.0 if self.config.quiet_zone else 0.0, self.config.hidden_margin_cells,
                                   None if predict is None else predicted_planes([predict(d.tag_id) for d in out]),
                                   self.normalised)
            behind = {out[i].tag_id: out[j].tag_id for i, j in hidden.items()}
            out = [d for i, d in enumerate(out) if i not in hidden]
        out.sort(key=lambda d: d.tag_id)
        return out, behind

    def normalised(self, px: np.ndarray) -> np.ndarray:
        """Pixels (k, 2) as normalised image points (k, 2), the lens's distortion taken out."""
        return cv2.undistortPoints(np.asarray(px, np.float64).reshape(-1, 1, 2), self.K, self.dist).reshape(-1, 2)

    def find(self, grey: np.ndarray) -> tuple[list[int], np.ndarray]:
        """Our tags' ids and refined corners (N, 4, 2) in a grey image, every check passed, before
        any pose: aruco's decoded quads, and the quads it found but could not decode that our own
        read of the refined quad identifies."""
        cfg = self.config
        corners, ids, rejected = self.candidates(grey)
        ids = [] if ids is None else [int(t) for t in ids.reshape(-1)]
        mine = [i for i, t in enumerate(ids) if t in self.sizes]
        quads = np.array([corners[i].reshape(4, 2) for i in mine], dtype=np.float64).reshape(-1, 4, 2)
        ids = [ids[i] for i in mine]
        # aruco reads the bits off its own coarse quad and gives up on small, blurred or
        # compressed tags that the AprilTag library reads; the refined quad reads them better
        rej = np.array([r.reshape(4, 2) for r in rejected], dtype=np.float64).reshape(-1, 4, 2)
        if len(rej) and self._allowed.size:
            sides = np.linalg.norm(np.roll(rej, -1, axis=1) - rej, axis=2)
            fresh = ~_overlaps(rej, quads)
            # aruco's unrefined quads read a tag ~1 px small: the side check proper comes later
            rej = rej[(sides.min(axis=1) >= cfg.min_side_px - 2.0) & fresh]
        else:
            rej = rej[:0]
        n = len(quads)
        everything = np.concatenate([quads, rej])
        if len(everything) == 0:
            return [], np.zeros((0, 4, 2))
        fit = fit_quads(grey, everything, (self.K, self.dist), quiet_zone=cfg.quiet_zone)
        ok = self._fit_ok(fit, everything)
        keep = ok[:n] & (self._bit_errors(grey, fit.corners[:n], quads, ids) <= cfg.max_bit_errors)
        found_ids = [t for t, good in zip(ids, keep) if good]
        found = [fit.corners[:n][keep]]
        started = [quads[keep]]
        if ok[n:].any():
            tid, rolled, errors = identify(grey, fit.corners[n:][ok[n:]], self._codes, self._allowed)
            good = errors <= cfg.max_bit_errors
            found_ids += [int(t) for t in tid[good]]
            found.append(rolled[good])
            started.append(_rolled_like(rej[ok[n:]][good], rolled[good]))
        corners = np.concatenate(found).reshape(-1, 4, 2)
        initial = np.concatenate(started).reshape(-1, 4, 2)
        if len(corners):
            on_border = along_border(corners, grey.shape)
            found_ids = [t for t, b in zip(found_ids, on_border) if not b]
            corners, initial = corners[~on_border], initial[~on_border]
        if cfg.quiet_zone and len(corners):
            blur = edge_blur_px(grey, corners)              # read once: the ring's scale and the bias model's
            clear = ring_deviation(grey, corners, blur) <= cfg.max_ring_deviation
            found_ids = [t for t, c in zip(found_ids, clear) if c]
            corners, initial, blur = corners[clear], initial[clear], blur[clear]
            if cfg.correct_blur_bias and len(corners):      # the model draws the quiet zone
                bias, _ = blur_bias(grey, corners, initial, self._codes[np.asarray(found_ids)], cfg.quiet_zone,
                                    blur_px=blur)
                corners = corners - bias
        return found_ids, corners

    def candidates(self, grey: np.ndarray) -> tuple:
        """aruco's decoded quads, their ids and its rejected quads (`detectMarkers`' three outputs),
        searched for on the frame smoothed as `DetectorConfig.candidate_filter_grey` says."""
        search = grey
        smooth = self.config.candidate_filter_grey
        if smooth is None:
            smooth = CANDIDATE_FILTER_GREY if self.config.quiet_zone else 0.0
        if smooth > 0 and grey.dtype == np.uint8:
            search = cv2.bilateralFilter(grey, CANDIDATE_FILTER_PX, smooth, CANDIDATE_FILTER_PX / 2)
        return self._detector.detectMarkers(search)

    def refine(self, grey: np.ndarray, ids: Sequence[int], quads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Edge-fitted corners of quads of known ids and whether each passed every check."""
        fit = fit_quads(grey, quads, (self.K, self.dist), quiet_zone=self.config.quiet_zone)
        errors = self._bit_errors(grey, fit.corners, quads, ids)
        ok = self._fit_ok(fit, quads) & (errors <= self.config.max_bit_errors)
        if self.config.quiet_zone and len(quads):
            ok &= ring_deviation(grey, fit.corners) <= self.config.max_ring_deviation
        return fit.corners, ok

    def _bit_errors(self, grey: np.ndarray, refined: np.ndarray, quads: np.ndarray, ids: Sequence[int]) -> np.ndarray:
        """Cells (of 64) that disagree with each id's pattern, read from the refined quad or from
        aruco's, whichever reads better: on a 12-15 px tag a cell is 1.5-2 px and a few tenths of a
        pixel of either quad's error can flip one."""
        if len(ids) == 0:
            return np.zeros(0, dtype=int)
        codes = self._codes[np.asarray(ids)]
        errors = np.count_nonzero(read_bits(grey, refined)[0] != codes, axis=(1, 2))
        again = np.flatnonzero(errors > self.config.max_bit_errors)
        if len(again):
            errors[again] = np.minimum(errors[again],
                                       np.count_nonzero(read_bits(grey, quads[again])[0] != codes[again], axis=(1, 2)))
        return errors

    def _fit_ok(self, fit, quads: np.ndarray) -> np.ndarray:
        """Every edge fitted and straight, and no corner far from where the detector put it."""
        cfg = self.config
        side = np.mean(np.linalg.norm(np.roll(fit.corners, -1, axis=1) - fit.corners, axis=2), axis=1)
        shift = np.max(np.linalg.norm(fit.corners - quads, axis=2), axis=1)
        with np.errstate(invalid="ignore"):
            return (fit.edges_fitted.all(axis=1)
                    & (fit.occluded <= cfg.max_occluded_share).all(axis=1)
                    & (np.nanmax(np.where(fit.edges_fitted, fit.rms_px, np.inf), axis=1) <= cfg.max_edge_rms_px)
                    & (shift <= np.maximum(cfg.max_corner_shift_px, 0.2 * side)))

    def _pose(self, tid: int, corners: np.ndarray, predict) -> Detection | None:
        cfg = self.config
        size = self.sizes[tid]
        sides = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
        if sides.min() < cfg.min_side_px:
            return None
        obj = tag_object_points(size)
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, corners, self.K, self.dist,
                                                    flags=cv2.SOLVEPNP_IPPE_SQUARE)
        if n == 0:
            return None
        errs = np.asarray(errs, dtype=float).reshape(-1)
        order = np.argsort(errs)
        ratio = float(errs[order[1]] / max(errs[order[0]], 1e-9)) if n > 1 else float("inf")
        # with these object points the solved frame already is the paper's tag frame
        pose = lambda i: Pose3(Rot3(cv2.Rodrigues(rvecs[i])[0]), np.asarray(tvecs[i], dtype=float).reshape(3))  # noqa: E731
        best_i = int(order[0])
        ambiguous = False
        if n > 1 and ratio < cfg.ambiguity_ratio:
            expected = predict(tid) if predict is not None else None
            if expected is not None:
                def rot_dist(i: int) -> float:
                    return float(np.linalg.norm(Rot3.Logmap(expected.rotation().between(pose(i).rotation()))))
                best_i = min(range(n), key=rot_dist)
            else:
                ambiguous = True
        best_e = float(errs[best_i])
        if best_e > cfg.max_reprojection_px:
            return None
        best = pose(best_i)
        cov = self._covariance(best, size, sides.mean(), best_e)
        return Detection(tid, corners, best, cov, best_e, ratio, ambiguous, size)

    def measurement_covariance(self, camera_T_tag: Pose3, size_m: float, side_px: float,
                               reprojection_px: float = 0.0) -> np.ndarray:
        """The covariance model alone, for a tag seen at `camera_T_tag` with sides of `side_px`
        (studies draw synthetic measurements from the same model the detector reports)."""
        return self._covariance(camera_T_tag, size_m, side_px, reprojection_px)

    def _covariance(self, camera_T_tag: Pose3, size: float, side_px: float, reproj_px: float) -> np.ndarray:
        f = 0.5 * (self.K[0, 0] + self.K[1, 1])
        s_px = max(self.config.corner_sigma_px, reproj_px)
        M = camera_T_tag.matrix()
        R, t = M[:3, :3], M[:3, 3]
        d = float(np.sqrt(t @ t))
        los = t / max(d, 1e-9)
        # viewing angle between the tag normal and the line of sight
        cos_a = max(abs(float(R[:, 2] @ los)), 0.2)
        lateral = d * s_px / f
        depth = d * d * s_px * math.sqrt(2.0) / (f * size)
        rot = s_px * math.sqrt(2.0) / max(side_px, 1.0)          # about the line of sight
        # tilt (about in-plane axes) shows only through perspective: the near and far edges differ
        # by side * (size / 2) * sin(tilt) / d, so a frontal tag's tilt is poorly determined
        tilt = s_px * math.sqrt(2.0) * d / (max(side_px, 1.0) * 0.5 * size)
        # camera-frame translation covariance (depth along the line of sight), then into the tag frame
        L = np.outer(los, los)
        cov_t_cam = lateral ** 2 * (np.identity(3) - L) + depth ** 2 * L
        cov_t = R.T @ cov_t_cam @ R
        # rotation: tilt about the tag's in-plane axes is the weak direction when foreshortened
        sin_a = math.sqrt(max(0.0, 1.0 - cos_a * cos_a))
        tilt = 1.0 / math.hypot(1.0 / tilt, sin_a / (rot / cos_a))    # oblique views see tilt better
        cov = np.zeros((6, 6))
        cov[0, 0] = cov[1, 1] = tilt ** 2
        cov[2, 2] = rot ** 2
        cov[3:, 3:] = cov_t
        cov[3, 3] += 1e-10
        cov[4, 4] += 1e-10
        cov[5, 5] += 1e-10
        return cov
