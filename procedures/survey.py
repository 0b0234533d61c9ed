"""Survey planning for a BORG assembly step: which turntable angles and Stewart poses see the new
module's tags together with tags they are related to.

The plan is made from the design (and the rig's kinematics), before anything moves, so that a dry
run can check every move of a whole procedure.  It is made in two passes: coverage (each new tag
seen from two turntable angles, with a related tag, a deployable's two tags together), then
accuracy: views are added, best first, until the new module's position 1-sigma predicted from the
information the views would carry (estimation/precision.py: corner Jacobians at the design pose,
the graph's corner noise, the camera pose's uncertainty) reaches `PrecisionTarget.sigma_m`, or the
view budget is spent.  `more_views` does the same during the run, starting from the module's
covariance in the graph, when its verdict came out `uncertain`.  Visibility is predicted, not guaranteed: a tag is
expected in a view when its four corners project into the image with a margin, it is large enough
to decode, it faces the camera within `max_view_angle`, and no nearer tag covers it: neither a
quarter of its image box (`occlusion_overlap`) nor, by the detector's own rule
(`estimation.fiducials.hidden_behind`), the band around its black square with its quiet zone -- a
nearer tag's white border across one corner is enough for the detector to drop the tag; which of
two such tags is in front is what the detector will judge (their predicted planes where they
meet, else their centres), not their depth along the optical axis.  A tag
read but seen flatter than the graph takes a sighting (`min_side_ratio`) still hides what is
behind it, but the plan does not count it as seen: the graph would measure nothing from it.

A rig with a lift (a vertical stage under the Stewart base) gives the candidates heights too: the
planner picks the fewest heights, from a grid over the lift's travel, that see every module of the
structure at its step (the base height first, so a structure the home height sees -- the 3x3x3
BORG on the sim rig -- never moves the lift).  A tag no candidate view sees is reported in the
step's `unobservable`, before anything moves.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Callable, Iterable, Sequence

import cv2
import numpy as np

from estimation.fiducials import (HIDDEN_MIN_OVERLAP_CELLS2, DetectorConfig, grown_quad, plane_order,
                                  tag_object_points)
from estimation.precision import covariance_from_information, module_sigma, view_information
from estimation.rig_model import MIN_SIDE_RATIO
from estimation.semantics import STRUT_END_DIAMETER_M as STRUT_DIAMETER_M
from lab.core.geometry import Pose3, Rot3, from_xyzrpy
from lab.core.structures.borg import BorgModel
from lab.core.survey_budget import MAX_VIEWS, SIGMA_TARGET_MM


def box_covers(lo: np.ndarray, hi: np.ndarray, rows: np.ndarray, overlap: float) -> np.ndarray:
    """(len(rows), N): whether tag j's image box covers more than `overlap` of tag rows[i]'s, for
    (N, 2) boxes `lo`..`hi` sorted nearest first (only nearer ones, earlier, cover)."""
    area = np.prod(hi[rows] - lo[rows], axis=1)
    inter = np.prod(np.clip(np.minimum(hi[rows, None], hi[None]) - np.maximum(lo[rows, None], lo[None]), 0, None),
                    axis=2)
    inter[np.arange(len(lo))[None, :] >= rows[:, None]] = 0.0     # only nearer ones (earlier) cover
    return inter > overlap * area[:, None]


def unoccluded(lo: np.ndarray, hi: np.ndarray, rows: np.ndarray, overlap: float) -> np.ndarray:
    """Which of `rows` no nearer tag hides: (N, 2) image boxes `lo`..`hi` sorted nearest first; a
    tag is hidden when one nearer tag's box covers more than `overlap` of its own (every nearer tag
    in the frame counts, hidden or not).  Boolean mask over `rows`."""
    return ~box_covers(lo, hi, rows, overlap).any(axis=1)


# the detector's hiding rule (`estimation.fiducials.hidden_behind`) as the run's detector applies it:
# a tag's quiet zone is one cell wide, and its black square counts grown by the detector's margin.
# Which of two overlapping tags is in front is decided as the run's detector decides it (it has
# every tag's predicted plane): the plane nearer along the line of sight through the overlap, where
# the two differ by more than `fiducials.HIDDEN_ORDER_MIN_M`, else the nearer centre.  Centres within
# _CENTRE_TIE_M of each other (the detector's come from single-view poses) count either way: each
# tag is counted hidden by the other (the safe side: the plan looks for other views)
_QUIET_CELLS = 1.0
_CENTRE_TIE_M = 0.005
_HIDDEN_MARGIN_CELLS = float(DetectorConfig().hidden_margin_cells or 0.0)
# how far past its black square's image box a grown square can reach, as a fraction of the box
# (a square grown by c of its 8 cells reaches c/8 of its side in the tag's plane; perspective is
# allowed to double that)
_OUTER_REACH = 2 * _QUIET_CELLS / 8
_INNER_REACH = 2 * _HIDDEN_MARGIN_CELLS / 8


@dataclass(frozen=True)
class View:
    turntable_rad: float
    stewart_pose: tuple[float, ...]   # (x, y, z, roll, pitch, yaw) of the platform relative to home
    lift_m: float = 0.0               # the lift's height; 0 is where the rig file's Stewart base was measured

    @property
    def label(self) -> str:
        x, y, z, r, p, w = self.stewart_pose
        # a view at the lift's zero reads as it did before there was a lift (the plans of runs that
        # never move it, and their records, stay the same)
        lift = f", lift {self.lift_m * 1000:+.0f} mm" if self.lift_m else ""
        return (f"turntable {np.degrees(self.turntable_rad):+.0f} deg, platform ({x * 1000:+.0f}, {y * 1000:+.0f}, "
                f"{z * 1000:+.0f}) mm ({np.degrees(r):+.0f}, {np.degrees(p):+.0f}, {np.degrees(w):+.0f}) deg{lift}")


@dataclass(frozen=True)
class SurveyConfig:
    margin_px: float = 25.0
    min_side_px: float = 16.0
    max_view_angle_rad: float = np.radians(62.0)
    # A tag counts as seen only if its image is no flatter than this (shortest side over longest):
    # the graph drops a sighting under `rig_model.MIN_SIDE_RATIO`, and a plan that counted one
    # re-planned the step once its views were taken (at N = 6, 12 % of the modules' own sightings
    # were that flat, and 116 of 117 re-plans were a second turntable angle the graph had dropped).
    # The margin is over 3x the scatter of the measured ratio about the predicted one (0.0044 at
    # N = 6: the errors of the tags and the rig that the plan cannot know).
    min_side_ratio: float = MIN_SIDE_RATIO + 0.015
    max_distance_m: float = 4.5
    occlusion_overlap: float = 0.25       # fraction of a tag's box covered by a nearer tag's box
    # A re-plan's prediction (`adapted`: the calibrated rig's camera, each tag where the graph
    # estimates it) is good to a pixel or two, and a view it gets wrong costs the module's last
    # views: a nearer tag's outer edge counts this much wider there, so that a view the prediction
    # leaves a tag clear in by less is not counted on.  At N = 9 the top layer's 401P (one tag,
    # 589, its first views all from one direction) was given five more views at one turntable
    # angle where the adapted prediction left 0.1 px between 589 and the front face's tag 542; the
    # detector dropped 589 in all five as partly behind 542, and 401P ended `uncertain` at a
    # 1-sigma of 5.1 mm.  Plans from the design keep the detector's exact rule (a margin there
    # changed most plans at N >= 8 and was not kept: docs/benchmarks.md, "The planner's margin on
    # the hiding rule").
    replan_hidden_clearance_px: float = 2.0
    angle_offsets_rad: tuple[float, ...] = tuple(np.radians([0.0, -25.0, 25.0, -10.0, 10.0, -18.0, 18.0, -32.0, 32.0]))
    stewart_poses: tuple[tuple[float, ...], ...] = (
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        (0.0, 0.04, 0.0, 0.0, 0.0, 0.0),
        (0.0, -0.04, 0.0, 0.0, 0.0, 0.0),
        (0.0, 0.0, 0.03, 0.0, 0.0, 0.0),
        (0.0, 0.0, -0.03, 0.0, 0.0, 0.0),
        (0.0, 0.0, 0.0, 0.0, np.radians(-6.0), 0.0),
        (0.0, 0.0, 0.0, 0.0, np.radians(6.0), 0.0),
    )
    views_per_step: int = 3
    min_angle_separation_rad: float = np.radians(20.0)
    min_sightings: int = 2                # each new tag in at least this many views
    # the grid the lift's heights are chosen from: a quarter of the camera's vertical field at the
    # structure (43 deg at ~2 m is ~1.6 m), so one grid height lands near every layer's best view
    lift_step_m: float = 0.25
    # wider looks, for tags the views above cannot see from any height (the far corners of a face
    # wider than the camera's field from the station: N >= 6 on the sim rig); used only then
    wide_angle_offsets_rad: tuple[float, ...] = tuple(np.radians([-40.0, 40.0, -48.0, 48.0]))
    wide_stewart_poses: tuple[tuple[float, ...], ...] = (
        (0.0, 0.0, 0.0, 0.0, 0.0, np.radians(20.0)),
        (0.0, 0.0, 0.0, 0.0, 0.0, np.radians(-20.0)),
        (0.0, 0.0, 0.0, 0.0, np.radians(12.0), 0.0),
        (0.0, 0.0, 0.0, 0.0, np.radians(-12.0), 0.0),
    )


@dataclass(frozen=True)
class CameraModel:
    """What the planner needs of the rig: intrinsics and the camera's pose for a view."""

    K: np.ndarray
    width_px: int
    height_px: int
    world_T_stewart_base: Pose3
    home_m: np.ndarray
    platform_T_camera: Pose3

    def world_T_camera(self, view: View) -> Pose3:
        home = Pose3(from_xyzrpy([*self.home_m, 0, 0, 0]))
        base = self.world_T_stewart_base
        if view.lift_m:
            # the lift carries the Stewart base straight up (nominally: its true axis is calibrated
            # in the graph, estimation/rig_model.py)
            base = Pose3(Rot3(), np.array([0.0, 0.0, view.lift_m])).compose(base)
        return base.compose(home).compose(from_xyzrpy(view.stewart_pose)).compose(self.platform_T_camera)


@dataclass(frozen=True)
class PrecisionTarget:
    """What the accuracy pass aims at and what it assumes."""

    sigma_m: float = SIGMA_TARGET_MM * 1e-3   # the new module's position 1-sigma to reach
    max_views: int = MAX_VIEWS                # views per step, coverage views included
    corner_sigma_px: float = 0.02         # the graph's corner noise (SlamConfig.corner_sigma_px)
    # the camera pose as the graph knows it relative to the structure, per view (treated as
    # independent between views: the prediction is of the views' own contribution)
    camera_sigma_m: float = 0.0001
    camera_sigma_rad: float = np.radians(0.005)
    # the module position 1-sigma no view of the module reduces: the structure frame the turntable
    # tags fix and the rig's calibration, common to every view (the run measures it from its own
    # verdicts: `procedures.borg`, `_plan_floor`).  A plan predicts its views' share combined with it.
    floor_sigma_m: float = 0.0

    def total_sigma(self, own_sigma_m: float) -> float:
        """The module's predicted 1-sigma: its own views' share and the floor, independent."""
        return float(np.hypot(own_sigma_m, self.floor_sigma_m))

    @property
    def camera_covariance(self) -> np.ndarray:
        return np.diag([self.camera_sigma_rad] * 3 + [self.camera_sigma_m] * 3) ** 2


@dataclass
class SurveyPlan:
    module: str
    views: list[View]
    expected: list[list[int]]              # predicted visible tags per view
    unobservable: list[int] = field(default_factory=list)   # new tags no candidate view sees
    predicted_sigma_m: float | None = None  # the module's position 1-sigma the views should give
    # what that prediction assumed (None: no accuracy pass): the corner noise and the floor
    corner_sigma_px: float | None = None
    floor_sigma_m: float | None = None


@dataclass(frozen=True)
class _ViewGeometry:
    """Every tag of the structure as one view would see it, tag by tag (index = position in
    `SurveyPlanner._ids`): readable on its own (facing, in the image with the margin, big enough),
    its mean depth and its image box.  Which of them a step has placed, and which of those a nearer
    one covers, is decided per step (`SurveyPlanner.visible`)."""

    ok: np.ndarray          # (T,) bool: readable
    # (T,) bool: facing the camera with some of its image in the frame: what can hide a tag behind
    # it, readable or not (at N = 9 tag 532, 8 px from the top of the frame and so not readable by
    # the margin, stood over 401P's tag 589 in the view planned to see it)
    drawn: np.ndarray
    measured: np.ndarray    # (T,) bool: readable and no flatter than `min_side_ratio` (what a plan counts)
    depth: np.ndarray       # (T,) m
    lo: np.ndarray          # (T, 2) px
    hi: np.ndarray          # (T, 2) px
    # the tags facing the view (row `row[t]`, -1 for the rest): their black squares' corners in
    # the image, for the detector's hiding rule
    row: np.ndarray         # (T,) int
    quad: np.ndarray        # (F, 4, 2) px
    centre_m: np.ndarray    # (T,) m: each tag's centre's distance from the camera (NaN: not facing)
    plane: np.ndarray       # (T, 4): its plane in the camera frame, unit normal and offset (n.X = d)


class SurveyPlanner:
    def __init__(self, model: BorgModel, camera: CameraModel, reachable, turntable_limits_rad: tuple[float, float],
                 config: SurveyConfig | None = None, lift_limits_m: tuple[float, float] | None = None) -> None:
        """`reachable(stewart_pose6) -> bool` is the Stewart workspace check (IK + limits).
        `lift_limits_m`: the lift's travel (the rig's [lift] min_m, max_m), None without a lift."""
        self.model = model
        self.camera = camera
        self.config = config or SurveyConfig()
        ids = sorted(model.tags)
        self._ids = np.array(ids)
        self._index = {t: i for i, t in enumerate(ids)}
        self._geometry_cache: dict[View, _ViewGeometry] = {}
        self._camera_of: Callable[[View], Pose3] | None = None    # an adapted planner's camera poses
        self._tag_poses: dict[int, Pose3] = {}                     # ... and tag poses (else the design)
        self._missed: dict[int, list[View]] = {}                   # ... and where tags were not seen
        self._deployed: dict[str, float] = {}                      # ... and deployables measured short
        self._facing_cache: dict[int, list[View]] = {}
        self._cover_cache: dict[View, np.ndarray] = {}
        self._ok_cache: dict[int, tuple[Sequence[View], np.ndarray]] = {}
        self._reachable = reachable
        self._turntable_limits = turntable_limits_rad
        c = self.config
        self._standard = self._cross(c.angle_offsets_rad, c.stewart_poses)
        if not self._standard:
            raise ValueError("no candidate survey view is reachable with this rig")
        self.lift_limits_m = lift_limits_m
        self.view_sets = self._choose_view_sets()
        self.lift_heights: tuple[float, ...] = tuple(sorted({h for h, _ in self.view_sets}))
        candidates: dict[View, None] = {}
        for h in self.lift_heights:
            for v in (self._wide if (h, True) in self.view_sets else self._standard):
                candidates[self._at(v, h)] = None
        self.candidates = list(candidates)

    def _cross(self, offsets: Sequence[float], poses: Sequence[Sequence[float]]) -> list[View]:
        """Turntable angles (each face's centre plus `offsets`, within the limits) x reachable poses."""
        lo, hi = self._turntable_limits
        views = []
        for face in range(4):
            for off in offsets:
                a = face * np.pi / 2 + off
                if not lo <= a <= hi:
                    a = a - 2 * np.pi if lo <= a - 2 * np.pi <= hi else a
                if not lo <= a <= hi:
                    continue
                for sp in poses:
                    if self._reachable(sp):
                        views.append(View(float(a), tuple(float(v) for v in sp)))
        return views

    @cached_property
    def _wide(self) -> list[View]:
        """The standard candidates, then the wider ones (further turns, platform yaw and pitch)."""
        c = self.config
        offsets = list(c.angle_offsets_rad) + [o for o in c.wide_angle_offsets_rad if o not in c.angle_offsets_rad]
        poses = list(c.stewart_poses) + [p for p in c.wide_stewart_poses if p not in c.stewart_poses]
        standard = set(self._standard)
        extra = [v for v in self._cross(offsets, poses) if v not in standard]
        return self._standard + extra

    @staticmethod
    def _at(view: View, lift_m: float) -> View:
        return view if lift_m == 0.0 else View(view.turntable_rad, view.stewart_pose, lift_m)

    @cached_property
    def _tag_corners(self) -> np.ndarray:
        """(T, 4, 3): each tag's corners in the structure frame."""
        out = np.zeros((len(self._ids), 4, 3))
        for i, tid in enumerate(self._ids):
            t = self.model.tags[int(tid)]
            h = t.size_m / 2
            local = np.array([[-h, -h, 0, 1], [h, -h, 0, 1], [h, h, 0, 1], [-h, h, 0, 1]])
            out[i] = (self.structure_T_tag(int(tid)).matrix() @ local.T).T[:, :3]
        return out

    @cached_property
    def _tag_frames(self) -> tuple[np.ndarray, np.ndarray]:
        """(T, 3) centres and (T, 3) normals in the structure frame."""
        poses = [self.structure_T_tag(int(t)) for t in self._ids]
        return (np.array([p.translation() for p in poses]), np.array([p.rotation().matrix()[:, 2] for p in poses]))

    def structure_T_camera(self, view: View) -> Pose3:
        if self._camera_of is not None:
            return self._camera_of(view)
        return self.model.world_T_structure(view.turntable_rad).inverse().compose(self.camera.world_T_camera(view))

    def structure_T_tag(self, tag: int) -> Pose3:
        """Where the planner expects the tag: the design's pose, or (an adapted planner) the
        estimate it was given."""
        pose = self._tag_poses.get(tag)
        return pose if pose is not None else self.model.tags[tag].structure_T_tag

    def adapted(self, structure_T_camera: Callable[[View], Pose3], tag_poses: dict[int, Pose3],
                K: np.ndarray | None = None, missed: dict[int, list[View]] | None = None,
                deployed_m: dict[str, float] | None = None) -> "SurveyPlanner":
        """The same candidates (heights, turntable angles, platform poses), judged from what a run
        has learnt: each view's camera where the calibrated rig puts it (`structure_T_camera`,
        e.g. the graph's current calibration), the tags where the graph estimates them
        (`tag_poses`; the design for the others) and the calibrated intrinsics `K`.  `missed`:
        tag -> views taken that were expected to show it and did not; a candidate from nearly the
        same place (the same lift height, the turntable within `MISSED_TURN_RAD`) is not counted
        on to show it either (what hid it -- a strut, glare, an edge of the frame the prediction
        puts just inside -- is likely to hide it again).  `deployed_m`: deployables the graph
        measured short, module -> measured lift (m): their top faces, and the struts to them, stand
        that much lower than the design's (`_struts`), and hide what they hide there."""
        import copy

        out = copy.copy(self)
        for name in ("_tag_corners", "_tag_frames"):
            out.__dict__.pop(name, None)
        out._camera_of = structure_T_camera
        out._tag_poses = dict(tag_poses)
        out._missed = {t: list(v) for t, v in (missed or {}).items() if v}
        out._deployed = {m: float(h) for m, h in (deployed_m or {}).items() if 0.0 < h < self.model.spacing_m}
        if K is not None:
            out.camera = replace(self.camera, K=np.asarray(K, float))
        out._geometry_cache, out._cover_cache, out._ok_cache = {}, {}, {}
        return out

    def _geometry(self, view: View) -> _ViewGeometry:
        g = self._geometry_cache.get(view)
        if g is not None:
            return g
        c = self.config
        s_T_c = self.structure_T_camera(view)
        c_T_s = s_T_c.inverse().matrix()
        centres, normals = self._tag_frames
        to_cam = s_T_c.translation() - centres
        dist = np.linalg.norm(to_cam, axis=1)
        facing = (dist <= c.max_distance_m) & (np.einsum("ij,ij->i", normals, to_cam) / dist >= np.cos(c.max_view_angle_rad))
        # only the tags facing the camera can be read: project those (the others' rows stay NaN)
        f = np.flatnonzero(facing)
        pc = self._tag_corners[f] @ c_T_s[:3, :3].T + c_T_s[:3, 3]
        front = np.all(pc[:, :, 2] >= 0.1, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (pc / pc[:, :, 2:3]) @ self.camera.K.T
        uv = uv[:, :, :2]
        row = np.full(len(facing), -1)
        row[f] = np.arange(len(f))
        lo_f, hi_f = uv.min(axis=1), uv.max(axis=1)
        inside = ((lo_f[:, 0] >= c.margin_px) & (lo_f[:, 1] >= c.margin_px)
                  & (hi_f[:, 0] <= self.camera.width_px - c.margin_px)
                  & (hi_f[:, 1] <= self.camera.height_px - c.margin_px))
        side = np.linalg.norm(np.roll(uv, -1, axis=1) - uv, axis=2)
        sides, longest = side.min(axis=1), side.max(axis=1)
        ok = np.zeros(len(facing), bool)
        ok[f] = front & inside & (sides >= c.min_side_px)
        drawn = np.zeros(len(facing), bool)
        drawn[f] = (front & (hi_f[:, 0] >= 0) & (hi_f[:, 1] >= 0) & (lo_f[:, 0] <= self.camera.width_px)
                    & (lo_f[:, 1] <= self.camera.height_px))
        measured = ok.copy()
        measured[f] &= sides >= c.min_side_ratio * longest
        depth = np.full(len(facing), np.nan)
        depth[f] = pc[:, :, 2].mean(axis=1)
        lo, hi = np.full((len(facing), 2), np.nan), np.full((len(facing), 2), np.nan)
        lo[f], hi[f] = lo_f, hi_f
        centre_c = pc.mean(axis=1)
        centre_m = np.full(len(facing), np.nan)
        centre_m[f] = np.linalg.norm(centre_c, axis=1)
        plane = np.full((len(facing), 4), np.nan)
        normal_c = normals[f] @ c_T_s[:3, :3].T
        plane[f] = np.column_stack([normal_c, np.einsum("ij,ij->i", normal_c, centre_c)])
        g = _ViewGeometry(ok, drawn, measured, depth, lo, hi, row, uv, centre_m, plane)
        self._geometry_cache[view] = g
        return g

    def _covers(self, g: _ViewGeometry, idx: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(len(rows), len(idx)): whether tag idx[j] hides tag idx[rows[i]], `idx` sorted nearest
        first: a nearer one's (earlier in `idx`) image box covers more than `occlusion_overlap` of
        the other's, or, by the detector's rule (`fiducials.hidden_behind`, which drops such a
        tag), any tag's outer edge overlaps the other's black square grown by the detector's margin
        by more than `HIDDEN_MIN_OVERLAP_CELLS2` of its cells and the detector would judge it in
        front (`_in_front`: for two cards on one face that is not the nearer along the optical axis)."""
        lo, hi = g.lo[idx], g.hi[idx]
        covers = box_covers(lo, hi, rows, self.config.occlusion_overlap)
        # the detector's rule, on the pairs whose boxes, grown past what the quiet zone and the
        # margin can add under any perspective the candidates see, still meet
        size = hi - lo
        clear = self.config.replan_hidden_clearance_px if self._camera_of is not None else 0.0
        o_lo, o_hi = lo - _OUTER_REACH * size - 2 * clear, hi + _OUTER_REACH * size + 2 * clear
        i_lo, i_hi = lo[rows] - _INNER_REACH * size[rows], hi[rows] + _INNER_REACH * size[rows]
        itself = np.arange(len(idx))[None, :] == rows[:, None]
        touch = (np.all(o_lo[None] < i_hi[:, None], axis=2) & np.all(i_lo[:, None] < o_hi[None], axis=2)
                 & ~itself & ~covers)
        for i, j in zip(*np.nonzero(touch)):
            near, far = g.quad[g.row[idx[j]]], g.quad[g.row[idx[rows[i]]]]
            band = grown_quad(far, _HIDDEN_MARGIN_CELLS).astype(np.float32)
            cells = _QUIET_CELLS
            if clear:
                # the clearance in the nearer tag's cells (its side / 8), grown in its own plane as the
                # quiet zone is
                cell_px = float(np.linalg.norm(np.roll(near, -1, axis=0) - near, axis=1).mean()) / 8.0
                cells += clear / max(cell_px, 1e-9)
            shared, poly = cv2.intersectConvexConvex(grown_quad(near, cells).astype(np.float32), band)
            if (shared > HIDDEN_MIN_OVERLAP_CELLS2 * abs(cv2.contourArea(far.astype(np.float32))) / 64.0
                    and self._in_front(g, idx[j], idx[rows[i]], np.asarray(poly, np.float64).reshape(-1, 2))):
                covers[i, j] = True
        return covers

    def _in_front(self, g: _ViewGeometry, a: int, b: int, overlap: np.ndarray) -> bool:
        """Whether the run's detector may judge tag `a` in front of tag `b` where they overlap
        (`overlap`: the polygon, px): as `fiducials.hidden_behind` with both planes predicted, the
        plane nearer along the line of sight through the overlap's centre (`fiducials.plane_order`),
        else the nearer centre, a tie within _CENTRE_TIE_M either way."""
        by_planes = plane_order(g.plane[a], g.plane[b], np.linalg.solve(self.camera.K, [*overlap.mean(axis=0), 1.0]))
        if by_planes is not None:
            return by_planes
        return bool(g.centre_m[a] < g.centre_m[b] + _CENTRE_TIE_M)

    def present_index(self, present: Iterable[int]) -> np.ndarray:
        """`present` (tag ids) as sorted indices into the planner's tag table, for `visible`."""
        return np.array(sorted(self._index[t] for t in present), dtype=int)

    def visible(self, view: View, present: Iterable[int] | np.ndarray, among: Iterable[int] | None = None) -> list[int]:
        """Tags of `present` predicted read in `view` and measured by the graph (no flatter than
        `min_side_ratio`), nearest first (only those of `among`, if given: the others, and the
        flatter ones, still hide what is behind them).  `present` may be tag ids or, for a
        caller asking about many views, `present_index(ids)` once."""
        g = self._geometry(view)
        idx = present if isinstance(present, np.ndarray) else np.array([self._index[t] for t in present], dtype=int)
        idx = idx[g.drawn[idx]] if len(idx) else idx
        if not len(idx):
            return []
        # nearest first (ties by id); a tag is hidden when a nearer tag's box covers more than
        # `occlusion_overlap` of its own (every nearer tag in the frame counts, hidden, unreadable
        # or not)
        idx = idx[np.lexsort((self._ids[idx], g.depth[idx]))]
        rows = np.flatnonzero(g.ok[idx])
        if among is not None:
            wanted = set(among)
            rows = rows[[int(self._ids[idx[r]]) in wanted for r in rows]]
        if not len(rows):
            return []
        keep = ~self._covers(g, idx, rows).any(axis=1) & g.measured[idx[rows]]
        return [int(t) for t in self._ids[idx[rows[keep]]]]

    def _ok(self, views: Sequence[View]) -> np.ndarray:
        """(V, T): which tags each of `views` could read and measure on its own (before occlusion)."""
        if not views:
            return np.zeros((0, len(self._ids)), bool)
        return np.stack([self._geometry(v).measured for v in views])

    def _seeing(self, views: Sequence[View], tags: Iterable[int], ok: np.ndarray | None = None) -> list[View]:
        """Those of `views` in which at least one of `tags` could be read (the others cannot see
        them whatever is in front: the only ones worth the occlusion test)."""
        idx = [self._index[t] for t in tags]
        if ok is None:
            # the candidates facing one face are asked about at every step: their table is kept
            key = id(views)
            hit = self._ok_cache.get(key)
            if hit is None or hit[0] is not views:
                hit = (views, self._ok(views))
                if any(views is f for f in self._facing_cache.values()):
                    self._ok_cache[key] = hit
            ok = hit[1]
        return [views[i] for i in np.flatnonzero(ok[:, idx].any(axis=1))] if idx else []

    @cached_property
    def _step_of(self) -> np.ndarray:
        """(T,): the assembly step at which each tag appears (0: the turntable's, k: the k-th module's)."""
        out = np.zeros(len(self._ids), int)
        for k, m in enumerate(self.model.modules, start=1):
            out[[self._index[t] for t in m.tags]] = k
        return out

    @cached_property
    def _tag_face(self) -> np.ndarray:
        """(T,): the face whose views may see each tag (its module's; 0: any, the turntable's)."""
        out = np.zeros(len(self._ids), int)
        for m in self.model.modules:
            out[[self._index[t] for t in m.tags]] = self._face_of(m.name)
        return out

    def _cover(self, view: View) -> np.ndarray:
        """(T,): for each tag `view` could read, the first assembly step at which a nearer tag in the
        frame covers it (`visible`'s occlusion rule), a step past the last where none does.  With it
        a view's visible tags at any step of the assembly order are one comparison: readable, placed
        (`_step_of` <= step) and not yet covered (`_cover` > step)."""
        c = self._cover_cache.get(view)
        if c is not None:
            return c
        g = self._geometry(view)
        never = len(self.model.modules) + 1
        c = np.full(len(self._ids), never, int)
        idx = np.flatnonzero(g.drawn)
        if len(idx):
            idx = idx[np.lexsort((self._ids[idx], g.depth[idx]))]        # nearest first, as `visible`
            rows = np.flatnonzero(g.ok[idx])                              # the readable ones, covered by any
            covers = self._covers(g, idx, rows)
            steps = np.where(covers, self._step_of[idx][None, :], never)
            c[idx[rows]] = steps.min(axis=1)
        self._cover_cache[view] = c
        return c

    def _visible_at(self, view: View, step: int) -> list[int]:
        """`visible(view, present)` for the tags present at assembly step `step` (the turntable's
        and the first `step` modules'), from `_cover`: the same tags, nearest first."""
        g = self._geometry(view)
        idx = np.flatnonzero(g.measured & (self._step_of <= step) & (self._cover(view) > step))
        idx = idx[np.lexsort((self._ids[idx], g.depth[idx]))]
        return [int(t) for t in self._ids[idx]]

    def _step_of_placed(self, placed_modules: Sequence[str]) -> int | None:
        """The assembly step `placed_modules` stands for, if it is the assembly order's first
        modules (a run's steps); None otherwise."""
        k = len(placed_modules)
        order = self.model.modules
        if k <= len(order) and all(order[i].name == n for i, n in enumerate(placed_modules)):
            return k
        return None

    # ---- which views: heights and wider looks ------------------------------------------------------
    @cached_property
    def lift_grid(self) -> tuple[list[float], float]:
        """The lift heights a view may be taken at (`lift_step_m` apart over the travel, ascending)
        and the base height (0, or the nearest end of the travel); ([0], 0) without a lift."""
        if self.lift_limits_m is None:
            return [0.0], 0.0
        lo, hi = self.lift_limits_m
        base = min(max(0.0, lo), hi)
        step = self.config.lift_step_m
        return sorted({base, *(float(round(h, 6)) for h in np.arange(base, hi + 1e-9, step)),
                       *(float(round(h, 6)) for h in np.arange(base, lo - 1e-9, -step))}), base

    @cached_property
    def _other_views(self) -> list[View]:
        """The views of the lift's travel that are not candidates: the wider looks at the chosen
        heights, then the standard and wider views at the heights not chosen."""
        chosen = set(self.candidates)
        out = [self._at(v, h) for h in self.lift_heights for v in self._wide]
        out += [self._at(v, h) for h in self.lift_grid[0] if h not in self.lift_heights for v in self._wide]
        return [v for v in dict.fromkeys(out) if v not in chosen]

    def _choose_view_sets(self) -> tuple[tuple[float, bool], ...]:
        """(lift height, wide) sets of candidate views: the fewest that see every module's tags at
        the module's own step (with the tags placed so far in front of them).  First the standard
        views at the base height (0, or the nearest end of the lift's travel); then, greedily, the
        standard views at whichever grid height sees most of the tags still unseen (the nearer one
        to the base on a tie); then, for what even those cannot see (the corners of a face wider
        than the camera's field from the station), the wider views (further turns, platform yaw
        and pitch) at whichever chosen or grid height sees most.  A structure the standard views
        at the base see (the 3x3x3 BORG on the sim rig) gets exactly those.  Then the same two
        passes for tags seen but not well (not twice from turntable angles `min_angle_separation`
        apart).  The turntable's tags count as a first step (their relations to the base modules
        tie the structure frame)."""
        grid, base = self.lift_grid
        # the turntable's tags first: they tie the structure frame to the rig (a run without a rig
        # calibration has nothing else), and a turntable wider than the camera's field below the
        # home height (N >= 4 on the sim rig) needs a lower look at them
        present = set(self.model.turntable.tag_ids)
        steps: list[tuple[str, list[int], set[int]]] = [("", list(self.model.turntable.tag_ids), present)]
        for m in self.model.modules:
            present = present | set(m.tags)
            steps.append((m.name, list(m.tags), present))
        need = {t for _, tags, _ in steps for t in tags}
        cache: dict[tuple[float, bool], dict[int, list[float]]] = {}

        def sightings(group: tuple[float, bool]) -> dict[int, list[float]]:
            """Tag -> the turntable angles of the group's views that see it at its step."""
            if group not in cache:
                h, wide = group
                views = [self._at(v, h) for v in (self._wide if wide else self._standard)]
                # each view: which tags it reads at their own step (nothing placed later in front)
                own = np.stack([self._geometry(v).measured & (self._cover(v) > self._step_of) for v in views])
                facing = np.stack([self._facing_mask(f, views) for f in range(5)])
                angles_of = np.array([v.turntable_rad for v in views])
                out: dict[int, list[float]] = {}
                for _, tags, _ in steps:
                    for t in tags:
                        i = self._index[t]
                        seen = np.flatnonzero(own[:, i] & facing[self._tag_face[i]])
                        if len(seen):
                            out[t] = [float(a) for a in angles_of[seen]]
                cache[group] = out
            return cache[group]

        def well(angles: list[float]) -> bool:
            # as the coverage pass wants it: seen twice, from turntable angles far enough apart
            # to triangulate its depth
            return len(angles) >= self.config.min_sightings and \
                max(angles) - min(angles) >= self.config.min_angle_separation_rad

        chosen = [(base, False)]
        angles: dict[int, list[float]] = {t: list(a) for t, a in sightings(chosen[0]).items()}

        def grow(gain_now: Callable[[], Callable[[tuple[float, bool]], int] | None]) -> None:
            """Greedily add the standard heights, then the wider looks, while one gains something;
            `gain_now()` gives the gain of a candidate given what is chosen so far, or None when
            nothing is left to gain (no candidate height is then evaluated: most structures stop here)."""
            for wide in (False, True):
                while True:
                    gain = gain_now()
                    if gain is None:
                        return
                    gains = {(h, wide): gain((h, wide)) for h in grid if (h, wide) not in chosen}
                    best = max(gains, key=lambda g: (gains[g], -abs(g[0] - base)), default=None)
                    if best is None or gains[best] == 0:
                        break
                    chosen.append(best)
                    for t, a in sightings(best).items():
                        angles.setdefault(t, []).extend(a)

        def unseen() -> Callable[[tuple[float, bool]], int] | None:
            rest = need - set(angles)
            return (lambda g: len(set(sightings(g)) & rest)) if rest else None

        def seen_once() -> Callable[[tuple[float, bool]], int] | None:
            weak = {t for t in need if t in angles and not well(angles[t])}
            if not weak:
                return None
            return lambda g: sum(1 for t in weak if well(angles[t] + sightings(g).get(t, [])))

        # seen at all: the standard views at other heights, then the wider ones
        grow(unseen)
        # then seen well (twice, far enough apart): a tag seen only from one turntable angle (the
        # bracket of a top strut above the structure) gets a height, or a wider look, that does
        grow(seen_once)
        return tuple(chosen)

    def plan(self, module: str, placed_modules: Sequence[str], precision: PrecisionTarget | None = None, *,
             exclude: Iterable[View] = (), info: np.ndarray | None = None, fallback: bool = True,
             want: Iterable[int] | None = None) -> SurveyPlan:
        """Views for the step that placed `module`; `placed_modules` includes it.  `exclude`: views
        not to use (a re-plan's: those already taken); `info`: what is already known of the
        module's verdict tag (information, 6x6) for the accuracy pass; `fallback`: with no view
        predicted to see the module, still look from its face (a re-plan returns no view);
        `want`: the module's tags the coverage pass is for (default all of them)."""
        model = self.model
        present = set(model.turntable.tag_ids)
        for name in placed_modules:
            present.update(model.module_by_name[name].tags)
        new = list(model.module_by_name[module].tags)
        if want is not None:
            new = [t for t in new if t in set(want)]
        related = {t: [r for r in _related(model, t) if r in present and r not in new] for t in new}
        # only views that can read one of the new tags can gain anything (coverage or accuracy)
        excluded = set(exclude)
        sight = self._sight(module, placed_modules, present,
                            [v for v in self._seeing(self._facing(module), new) if v not in excluded])
        hidden = [t for t in new if not any(t in seen for seen in sight.values())]
        if hidden:
            # The heights were chosen for the tags-only visibility model; struts in front can hide a
            # tag from every one of them (the top layer's inner tags of a 10x10x10 from the lift's
            # 4.0 m: at 4.5 m the camera looks over the struts).  The rest of the lift's travel
            # and the wider looks, for those tags only.
            others = [v for v in self._other_views if v not in excluded]
            more = self._sight(module, placed_modules, present,
                               self._seeing(self._facing(module, others), hidden))
            sight.update({v: seen for v, seen in more.items() if set(seen) & set(hidden)})
        # requirements: each new tag seen min_sightings times; each new tag seen with a related tag;
        # the new module's tags seen together (deployables: B and T in one view)
        need_count = {t: self.config.min_sightings for t in new}
        need_pair = {t: bool(related[t]) for t in new}
        need_together = len(new) > 1
        seen_from: dict[int, list[float]] = {t: [] for t in new}
        chosen: list[View] = []

        def fresh(t: int, v: View, distinct: bool) -> bool:
            # a second sighting from another turntable angle triangulates the tag's depth
            return not distinct or all(abs(v.turntable_rad - a) >= self.config.min_angle_separation_rad
                                       for a in seen_from[t])

        # the turntable angles each new tag can be measured from: a first sighting is best taken
        # where a second, far enough round, can follow (`partners`)
        angles_of = {t: [v.turntable_rad for v, seen in sight.items() if t in seen] for t in new}
        sep = self.config.min_angle_separation_rad

        def partners(t: int, v: View) -> bool:
            return any(abs(a - v.turntable_rad) >= sep for a in angles_of[t])

        for distinct in (True, False):
            while len(chosen) < min(self.config.views_per_step, precision.max_views if precision else np.inf):
                def score(v: View) -> tuple[float, int, float]:
                    s = set(sight[v])
                    gain = sum(1.0 for t in new if need_count[t] > 0 and t in s and fresh(t, v, distinct))
                    gain += sum(2.0 for t in new if need_pair[t] and t in s and s.intersection(related[t]))
                    if need_together and all(t in s for t in new):
                        gain += 2.0
                    # among equal gains: the views after which a tag seen for the first time can
                    # still be seen from another angle (at N = 5, 9D's tags first seen from the
                    # middle of the 32 deg its candidates span got no second angle), then those
                    # that see many tags (better conditioned), then small motions
                    ahead = sum(1 for t in new if distinct and not seen_from[t] and t in s and partners(t, v))
                    return gain, ahead, len(s) * 0.01 - abs(v.turntable_rad) * 1e-3
                best = max((v for v in sight if v not in chosen), key=score, default=None)
                if best is None or score(best)[0] <= 0:
                    break
                s = set(sight[best])
                for t in new:
                    if t in s:
                        if fresh(t, best, distinct):
                            need_count[t] -= 1
                        seen_from[t].append(best.turntable_rad)
                        if s.intersection(related[t]):
                            need_pair[t] = False
                if need_together and all(t in s for t in new):
                    need_together = False
                chosen.append(best)
        if not chosen and fallback:  # nothing sees the new tags: still look, from the face the module is on
            face = model.module_by_name[module].face
            chosen = [min(self.candidates, key=lambda v: (abs(v.turntable_rad - (face - 1) * np.pi / 2),
                                                          np.abs(v.stewart_pose).sum(), abs(v.lift_m)))]
        predicted = None
        if precision is not None:
            known = self._information(module, chosen, sight, precision)
            extra, predicted, stalled = self._accurate(module, [v for v in sight if v not in chosen], sight, precision,
                                                       known if info is None else known + info,
                                                       precision.max_views - len(chosen))
            chosen += extra
            if predicted > precision.sigma_m and len(chosen) < precision.max_views and not stalled:
                extra, predicted, _ = self._accurate_beyond(module, placed_modules, present, new, chosen, sight,
                                                            precision, info, excluded)
                chosen += extra
        chosen.sort(key=_order)
        expected = [sight[v] if v in sight else self.visible(v, present) for v in chosen]
        seen_new = set().union(*map(set, expected)) if expected else set()
        return SurveyPlan(module, chosen, expected, [t for t in new if t not in seen_new], predicted,
                          corner_sigma_px=None if precision is None else precision.corner_sigma_px,
                          floor_sigma_m=None if precision is None else precision.floor_sigma_m)

    def more_views(self, module: str, placed_modules: Sequence[str], taken: Sequence[View],
                   tag_covariance: np.ndarray | None, precision: PrecisionTarget, budget: int) -> SurveyPlan:
        """Views to add, at most `budget`, for a module whose verdict is still open: the accuracy
        pass again, starting from its verdict tag's covariance in the graph."""
        present = set(self.model.turntable.tag_ids)
        for name in placed_modules:
            present.update(self.model.module_by_name[name].tags)
        taken_set = set(taken)
        sight = self._sight(module, placed_modules, present,
                            [v for v in self._seeing(self._facing(module), self.model.module_by_name[module].tags)
                             if v not in taken_set])
        info = np.zeros((6, 6)) if tag_covariance is None else np.linalg.inv(tag_covariance)
        # the graph's covariance holds the floor already (as information: these more views are
        # predicted to shrink it too, as before the floor was known)
        precision = replace(precision, floor_sigma_m=0.0)
        views, predicted, _ = self._accurate(module, list(sight), sight, precision, info, budget)
        if predicted > precision.sigma_m and len(views) < budget:
            tags = list(self.model.module_by_name[module].tags)
            extra, predicted, _ = self._accurate_beyond(module, placed_modules, present, tags, views, sight,
                                                        replace(precision, max_views=budget), info, taken_set)
            views += extra
        views.sort(key=_order)
        return SurveyPlan(module, views, [sight[v] for v in views], [], predicted, precision.corner_sigma_px,
                          precision.floor_sigma_m)

    def _accurate_beyond(self, module: str, placed_modules: Sequence[str], present: set[int], tags: list[int],
                         chosen: list[View], sight: dict[View, list[int]], precision: PrecisionTarget,
                         info: np.ndarray | None, excluded: set[View]) -> tuple[list[View], float, bool]:
        """When the candidate views cannot reach the target (a tag few of them see: at N = 6 the
        close-out struts 135S and 137S, tag in 2 of 1288 facing views, came out `uncertain` at a
        1-sigma of 1-2 mm and no further view was planned): the accuracy pass again over the rest of
        the lift's travel and the wider looks (`_other_views`), from what the chosen views give.
        `sight` gains the views found; returns `_accurate`'s (views added, predicted sigma, stalled)."""
        others = [v for v in self._other_views if v not in excluded and v not in sight]
        more = self._sight(module, placed_modules, present, self._seeing(self._facing(module, others), tags))
        sight.update({v: seen for v, seen in more.items() if set(seen) & set(tags)})
        known = self._information(module, chosen, sight, precision)
        if info is not None:
            known = known + info
        return self._accurate(module, [v for v in more if v in sight and v not in chosen], sight, precision, known,
                              precision.max_views - len(chosen))

    def _sight(self, module: str, placed_modules: Sequence[str], present: set[int],
               views: Sequence[View]) -> dict[View, list[int]]:
        """View -> the present tags it is predicted to read, for `views`.  The module's own tags are
        checked against the struts built so far too (`hidden_by_struts`): the visibility model has
        tags hiding tags, and a strut across a tag's face hides it as surely (at N >= 4 the top
        layer's strut brackets sit behind the struts in front of them from many views)."""
        step = self._step_of_placed(placed_modules)
        if step is not None:
            out = {v: self._visible_at(v, step) for v in views}
        else:
            present_idx = self.present_index(present)
            out = {v: self.visible(v, present_idx) for v in views}
        if self._missed:
            out = {v: [t for t in seen if not self._missed_near(t, v)] for v, seen in out.items()}
        for v, tag in self.hidden_by_struts(module, placed_modules, list(out), list(out.values())):
            out[v] = [t for t in out[v] if t != tag]
        return out

    def hidden_by_struts(self, module: str, placed_modules: Sequence[str], views: Sequence[View],
                         expected: Sequence[Sequence[int]]) -> list[tuple[View, int]]:
        """(view, tag) of the module's sightings `expected` in `views` (a plan's) that the struts
        built so far hide (`_behind_struts`, with this planner's struts: a deployable measured short
        where it was measured, `adapted(deployed_m=...)`)."""
        segments = self._struts(placed_modules)
        out: list[tuple[View, int]] = []
        if not len(segments[0]):
            return out
        for tag in self.model.module_by_name[module].tags:
            of = [v for v, seen in zip(views, expected) if tag in seen]
            if of:
                out += [(v, tag) for v, hidden in zip(of, self._behind_struts(tag, of, segments)) if hidden]
        return out

    def _struts(self, placed_modules: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """(S, 3) starts and ends of the struts the placed modules brought: at the design's nodes,
        but a deployable measured short (`adapted(deployed_m=...)`) has its top face lowered by what
        it lacks, and every strut to those nodes goes there (a node stands where the first module
        that brought it put it).  At N = 7, 186D deployed to 0.35 m swung a diagonal of its face
        across tag 317 of 227S, above it, in each of the 12 views planned from the design."""
        edges = {e for name in placed_modules for e in self.model.module_by_name[name].edges}
        if not edges:
            return np.zeros((0, 3)), np.zeros((0, 3))
        e = np.array(sorted(edges))
        nodes = self.model.nodes
        if self._deployed and any(name in self._deployed for name in placed_modules):
            nodes = nodes.copy()
            claimed: set[int] = set()
            for name in placed_modules:
                m = self.model.module_by_name[name]
                fresh = [int(i) for i in m.nodes if int(i) not in claimed]
                claimed.update(fresh)
                height = self._deployed.get(name)
                if height is None or not fresh:
                    continue
                bottom = min(float(self.model.nodes[i][2]) for i in m.nodes)
                top = [i for i in fresh if self.model.nodes[i][2] > bottom + 1e-9]
                nodes[top, 2] -= self.model.spacing_m - height
        return nodes[e[:, 0]], nodes[e[:, 1]]

    def _behind_struts(self, tag: int, views: Sequence[View], segments: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """(V,) whether a strut or a node hub crosses the line of sight from each view to the tag's
        face (`_face_grid`: points over its black square, corners included): a strut or hub
        across a tag's code or border leaves nothing the detector can decode (`_behind_nodes`).
        A 10x10x10 has ~3800 struts and a tag's lines pass near a handful: first the struts near
        each view's line to the tag's centre (within a strut's reach plus the tag's half-diagonal,
        short of the tag as the lines to its face are: no other strut can cross a line to the
        face), then only those, against the lines of the views they are near."""
        a, b = segments
        if not len(a) or not len(views):
            return np.zeros(len(views), bool)
        cams = np.array([self.structure_T_camera(v).translation() for v in views])   # (V, 3)
        out = self._behind_nodes(tag, views, np.unique(np.vstack([a, b]), axis=0), cams)
        h = self.model.tags[tag].size_m / 2
        radius = STRUT_DIAMETER_M / 2 + STRUT_MARGIN_M
        pose = self.structure_T_tag(tag)
        R = pose.rotation().matrix()
        # a line from a camera in front of the tag to its face stays in front of the face's plane:
        # a strut wholly more than its reach behind that plane cannot come near one (~90 % of
        # them: tags face out of the structure)
        ahead = np.maximum((a - pose.translation()) @ R[:, 2], (b - pose.translation()) @ R[:, 2]) > -radius
        if not ahead.any():
            return out
        a, b = a[ahead], b[ahead]
        pts = _face_grid(h) @ R.T + pose.translation()          # (P, 3)
        centre = np.broadcast_to(pose.translation(), cams.shape)
        near = _lines_near_segments(cams, centre, a, b, radius + h * np.sqrt(2.0))   # (V, S)
        rows = np.flatnonzero(near.any(axis=1))
        if len(rows):
            cols = near[rows].any(axis=0)
            starts = np.repeat(cams[rows], len(pts), axis=0)
            ends = np.tile(pts, (len(rows), 1))
            hit = _lines_near_segments(starts, ends, a[cols], b[cols], radius).any(axis=1)
            out[rows] |= hit.reshape(len(rows), len(pts)).any(axis=1)
        return out

    def _behind_nodes(self, tag: int, views: Sequence[View], nodes: np.ndarray,
                      cams: np.ndarray | None = None) -> np.ndarray:
        """(V,) whether a node hub (a sphere of NODE_DIAMETER_M at each node of the struts built)
        stands on the line of sight from each view to a point of the tag's face (the grid of
        `_behind_struts`).  A hub is 2.6 times a strut's width: at N = 7, 160D's tag 226, inset
        half a cell behind face 2, was hidden by the hub of the face's node below it from the
        views planned to see it a second time (the strut beside the hub passed clear).  `cams`:
        the views' camera positions in the structure frame, if the caller has them."""
        out = np.zeros(len(views), bool)
        radius = NODE_DIAMETER_M / 2 + STRUT_MARGIN_M
        pose = self.structure_T_tag(tag)
        R = pose.rotation().matrix()
        nodes = nodes[(nodes - pose.translation()) @ R[:, 2] > radius]      # only hubs in front of the face
        if not len(nodes) or not len(views):
            return out
        h = self.model.tags[tag].size_m / 2
        if cams is None:
            cams = np.array([self.structure_T_camera(v).translation() for v in views])     # (V, 3)

        def near(ends: np.ndarray, hubs: np.ndarray, r: float) -> np.ndarray:
            """(V, P, N) whether the line from each camera to each of `ends` (V, P, 3), on its
            first SIGHT_FRONT, passes within `r` of each hub."""
            d = (ends - cams[:, None, :]) * SIGHT_FRONT
            rel = hubs[None, :, :] - cams[:, None, :]                                   # (V, N, 3)
            t = np.clip(np.einsum("vpi,vni->vpn", d, rel) / np.einsum("vpi,vpi->vp", d, d)[:, :, None], 0.0, 1.0)
            gap = rel[:, None, :, :] - t[..., None] * d[:, :, None, :]
            return np.einsum("vpni,vpni->vpn", gap, gap) < r ** 2

        # first the hubs near a line to the tag's centre (within a hub's reach plus the tag's
        # half-diagonal), then only those against the lines to the face's points
        centre = np.broadcast_to(pose.translation(), (len(views), 1, 3))
        cols = near(centre, nodes, radius + h * np.sqrt(2.0))[:, 0, :].any(axis=0)
        if not cols.any():
            return out
        pts = _face_grid(h) @ R.T + pose.translation()
        return near(np.broadcast_to(pts, (len(views), *pts.shape)), nodes[cols], radius).any(axis=(1, 2))

    def _missed_near(self, tag: int, view: View) -> bool:
        return any(abs(view.lift_m - m.lift_m) < self.config.lift_step_m / 2
                   and abs((view.turntable_rad - m.turntable_rad + np.pi) % (2 * np.pi) - np.pi) < MISSED_TURN_RAD
                   for m in self._missed.get(tag, ()))

    # ---- accuracy ------------------------------------------------------------------------------
    def _facing(self, module: str, candidates: Sequence[View] | None = None) -> list[View]:
        """Candidates that can see the module's face at all (the others only cost time to check)."""
        candidates = self.candidates if candidates is None else candidates
        if candidates is self.candidates:
            face = self._face_of(module)
            if face not in self._facing_cache:
                self._facing_cache[face] = [v for v, f in zip(candidates, self._facing_mask(face, candidates)) if f]
            return self._facing_cache[face]
        return [v for v, f in zip(candidates, self._facing_mask(self._face_of(module), candidates)) if f]

    def _face_of(self, module: str) -> int:
        face = self.model.module_by_name[module].face
        return face if 1 <= face <= 4 else 0

    @staticmethod
    def _facing_mask(face: int, views: Sequence[View]) -> np.ndarray:
        """Which of `views` turn face `face` (1..4; 0: any) toward the camera, within 70 degrees."""
        if not 1 <= face <= 4:
            return np.ones(len(views), bool)
        centre = (face - 1) * np.pi / 2
        a = np.array([v.turntable_rad for v in views], float)
        return np.abs((a - centre + np.pi) % (2 * np.pi) - np.pi) <= np.radians(70.0)

    def _verdict_tag(self, module: str) -> int:
        return self.model.module_by_name[module].tags[0]

    def _view_information(self, module: str, view: View, sight: dict[View, list[int]],
                          precision: PrecisionTarget) -> np.ndarray:
        tag = self._verdict_tag(module)
        if tag not in sight.get(view, ()):
            return np.zeros((6, 6))
        spec = self.model.tags[tag]
        return view_information(self.structure_T_camera(view), self.structure_T_tag(tag), self.camera.K,
                                tag_object_points(spec.size_m), precision.corner_sigma_px,
                                precision.camera_covariance)

    def _information(self, module: str, views: Sequence[View], sight: dict[View, list[int]],
                     precision: PrecisionTarget) -> np.ndarray:
        return sum((self._view_information(module, v, sight, precision) for v in views), np.zeros((6, 6)))

    def plan_information(self, plan: SurveyPlan, precision: PrecisionTarget) -> np.ndarray:
        """The information (6x6) `plan`'s views give its module's verdict tag, each view with the
        tags it was planned to show: what a run sets against the 1-sigma its graph then states."""
        return self._information(plan.module, plan.views, dict(zip(plan.views, plan.expected)), precision)

    def predicted_sigma(self, module: str, info: np.ndarray) -> float:
        cov = covariance_from_information(info)
        if cov is None:
            return float("inf")
        tag = self._verdict_tag(module)
        m = self.model.module_by_name[module]
        tag_T_module = self.model.tags[tag].structure_T_tag.inverse().compose(m.structure_T_module)
        return module_sigma(tag_T_module, cov).position_m

    def _predicted_sigmas(self, module: str, infos: np.ndarray) -> np.ndarray:
        """`predicted_sigma` of each of a stack of information matrices (C, 6, 6), in one pass:
        the same arithmetic (estimation.precision's covariance_from_information, module_sigma)."""
        info = 0.5 * (infos + np.swapaxes(infos, 1, 2))
        w = np.linalg.eigvalsh(info)
        observed = w.min(axis=1) > 1e-9 * np.maximum(w.max(axis=1), 1e-30)
        cov = np.linalg.inv(np.where(observed[:, None, None], info, np.eye(6)))
        cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
        tag = self._verdict_tag(module)
        m = self.model.module_by_name[module]
        lever = self.model.tags[tag].structure_T_tag.inverse().compose(m.structure_T_module).translation()
        J = np.hstack([-np.array([[0.0, -lever[2], lever[1]], [lever[2], 0.0, -lever[0]], [-lever[1], lever[0], 0.0]]),
                       np.eye(3)])
        pos = J @ cov @ J.T
        out = np.sqrt(np.maximum(np.linalg.eigvalsh(pos).max(axis=1), 0.0))
        return np.where(observed, out, np.inf)

    def _accurate(self, module: str, candidates: list[View], sight: dict[View, list[int]],
                  precision: PrecisionTarget, info: np.ndarray, budget: int) -> tuple[list[View], float, bool]:
        """Greedy: the view that shrinks the predicted sigma (the views' share with the floor) most,
        until the target, the budget, or -- with a floor -- a view that would shrink it by less than
        MIN_VIEW_GAIN: where the floor is most of the sigma, more views of the module cannot help
        (the top layers of a 10x10x10: a floor of 0.31 mm against the 0.25 mm target).  Returns
        (views, predicted sigma, stalled: stopped for that)."""
        gains = {v: self._view_information(module, v, sight, precision) for v in candidates}
        gains = {v: g for v, g in gains.items() if g.any()}
        chosen: list[View] = []
        sigma = precision.total_sigma(self.predicted_sigma(module, info))
        while sigma > precision.sigma_m and len(chosen) < budget and gains:
            views = list(gains)
            sigmas = self._predicted_sigmas(module, info + np.stack([gains[v] for v in views]))
            i = min(range(len(views)), key=lambda i: (sigmas[i], abs(views[i].turntable_rad)))
            if precision.floor_sigma_m > 0 and precision.total_sigma(float(sigmas[i])) > (1 - MIN_VIEW_GAIN) * sigma:
                return chosen, sigma, True
            best = views[i]
            info = info + gains.pop(best)
            chosen.append(best)
            sigma = precision.total_sigma(self.predicted_sigma(module, info))
        return chosen, sigma, False


# a view is planned for accuracy only if it shrinks the module's predicted 1-sigma by this fraction
# (with a floor known: without one, every view shrinks it as 1/sqrt(views))
MIN_VIEW_GAIN = 0.10
MISSED_TURN_RAD = np.radians(10.0)    # a view this close in turntable angle to one that missed a tag
STRUT_MARGIN_M = 0.005                # a line of sight this much clear of a strut's surface still counts as hidden
# the node hubs the struts meet at (the design's; the simulated truss draws the same size)
NODE_DIAMETER_M = 0.050
SIGHT_FRONT = 0.97                    # a strut crossing the last 3 % of a line of sight is the tag's own bracket


def _face_grid(half: float) -> np.ndarray:
    """(25, 3) points over a tag's black square (its frame, corners included), 2.5 cm apart on a
    10 cm tag: closer than the band a strut hides on the face (its diameter plus twice the
    margin, 2.9 cm, more at a slant), so no strut across the face passes between them.  A 3 x 3
    grid let a strut cross a tag's lower half unseen (N = 7, 160D's tag 226 from below)."""
    ticks = np.linspace(-half, half, 5)
    return np.array([[x, y, 0.0] for x in ticks for y in ticks])


def _segments_within(cam: np.ndarray, pts: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """(P,) whether the sight line from `cam` to each of `pts` passes within `radius` of one of the
    segments a[i]-b[i] (S, 3) strictly between the camera and the point."""
    return _lines_near_segments(np.broadcast_to(cam, pts.shape), pts, a, b, radius).any(axis=1)


def _lines_near_segments(starts: np.ndarray, ends: np.ndarray, a: np.ndarray, b: np.ndarray,
                         radius: float, front: float = SIGHT_FRONT) -> np.ndarray:
    """(L, S) whether the sight line from starts[l] to ends[l] (L, 3) passes within `radius` of the
    segment a[s]-b[s] (S, 3), at a point of the line short of `front` of the way to its end: the
    closest approach of two segments, clamped to both, on the line's first `front` (only what
    stands in front of a tag hides it, not the strut its own bracket sits on)."""
    d1 = (ends - starts) * front                      # (L, 3) the lines, short of their ends
    d2 = b - a                                        # (S, 3) struts
    aa = np.einsum("li,li->l", d1, d1)[:, None]       # (L, 1)
    ee = np.einsum("si,si->s", d2, d2)[None, :]       # (1, S)
    bb = d1 @ d2.T                                    # (L, S)
    sa = starts @ a.T                                 # (L, S)
    cc = np.einsum("li,li->l", d1, starts)[:, None] - d1 @ a.T           # d1 . (start - a)
    ff = starts @ d2.T - np.einsum("si,si->s", d2, a)[None, :]          # d2 . (start - a)
    den = aa * ee - bb ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        sc = np.where(den > 1e-12, (bb * ff - cc * ee) / den, 0.0)
    sc = np.clip(sc, 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = np.clip((bb * sc + ff) / ee, 0.0, 1.0)
    sc = np.clip(np.where(aa > 0, (bb * tc - cc) / aa, 0.0), 0.0, 1.0)
    # |start + sc d1 - (a + tc d2)|^2 expanded, with r = start - a: no (L, S, 3) array
    rr = np.einsum("li,li->l", starts, starts)[:, None] - 2.0 * sa + np.einsum("si,si->s", a, a)[None, :]
    dist2 = rr + sc ** 2 * aa + tc ** 2 * ee + 2.0 * sc * cc - 2.0 * tc * ff - 2.0 * sc * tc * bb
    return dist2 < radius ** 2


def _order(v: View) -> tuple:
    """A step's views by lift height, then turntable angle, then platform pose: the lift, the
    slowest axis to settle with a platform on it, climbs once per step."""
    return (v.lift_m, v.turntable_rad, v.stewart_pose)


def _related(model: BorgModel, tag: int) -> list[int]:
    out = []
    for r in model.relations:
        if r.a == tag:
            out.append(r.b)
        elif r.b == tag:
            out.append(r.a)
    return out
