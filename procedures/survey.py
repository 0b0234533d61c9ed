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
to decode, it faces the camera within `max_view_angle`, and no nearer tag's outline covers it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Iterable, Sequence

import numpy as np

from estimation.fiducials import tag_object_points
from estimation.precision import covariance_from_information, module_sigma, view_information
from lab.geometry import Pose3, from_xyzrpy
from lab.structures.borg import BorgModel


@dataclass(frozen=True)
class View:
    turntable_rad: float
    stewart_pose: tuple[float, ...]   # (x, y, z, roll, pitch, yaw) of the platform relative to home

    @property
    def label(self) -> str:
        x, y, z, r, p, w = self.stewart_pose
        return (f"turntable {np.degrees(self.turntable_rad):+.0f} deg, platform ({x * 1000:+.0f}, {y * 1000:+.0f}, "
                f"{z * 1000:+.0f}) mm ({np.degrees(r):+.0f}, {np.degrees(p):+.0f}, {np.degrees(w):+.0f}) deg")


@dataclass(frozen=True)
class SurveyConfig:
    margin_px: float = 25.0
    min_side_px: float = 16.0
    max_view_angle_rad: float = np.radians(62.0)
    max_distance_m: float = 4.0
    occlusion_overlap: float = 0.25       # fraction of a tag's box covered by a nearer tag's box
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
        return self.world_T_stewart_base.compose(home).compose(from_xyzrpy(view.stewart_pose)).compose(
            self.platform_T_camera)


@dataclass(frozen=True)
class PrecisionTarget:
    """What the accuracy pass aims at and what it assumes."""

    sigma_m: float = 0.00025              # the new module's position 1-sigma to reach
    max_views: int = 12                   # views per step, coverage views included
    corner_sigma_px: float = 0.02         # the graph's corner noise (SlamConfig.corner_sigma_px)
    # the camera pose as the graph knows it relative to the structure, per view (treated as
    # independent between views: the prediction is of the views' own contribution)
    camera_sigma_m: float = 0.0001
    camera_sigma_rad: float = np.radians(0.005)

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


class SurveyPlanner:
    def __init__(self, model: BorgModel, camera: CameraModel, reachable, turntable_limits_rad: tuple[float, float],
                 config: SurveyConfig | None = None) -> None:
        """`reachable(stewart_pose6) -> bool` is the Stewart workspace check (IK + limits)."""
        self.model = model
        self.camera = camera
        self.config = config or SurveyConfig()
        lo, hi = turntable_limits_rad
        views = []
        for face in range(4):
            for off in self.config.angle_offsets_rad:
                a = face * np.pi / 2 + off
                if not lo <= a <= hi:
                    a = a - 2 * np.pi if lo <= a - 2 * np.pi <= hi else a
                if not lo <= a <= hi:
                    continue
                for sp in self.config.stewart_poses:
                    if reachable(sp):
                        views.append(View(float(a), tuple(float(v) for v in sp)))
        if not views:
            raise ValueError("no candidate survey view is reachable with this rig")
        self.candidates = views

    @cached_property
    def _tag_corners(self) -> dict[int, np.ndarray]:
        out = {}
        for t in self.model.tags.values():
            h = t.size_m / 2
            local = np.array([[-h, -h, 0, 1], [h, -h, 0, 1], [h, h, 0, 1], [-h, h, 0, 1]])
            out[t.id] = (t.structure_T_tag.matrix() @ local.T).T[:, :3]
        return out

    def structure_T_camera(self, view: View) -> Pose3:
        return self.model.world_T_structure(view.turntable_rad).inverse().compose(self.camera.world_T_camera(view))

    def visible(self, view: View, present: Iterable[int]) -> list[int]:
        """Tags of `present` predicted readable in `view`, nearest first."""
        c = self.config
        s_T_c = self.structure_T_camera(view)
        c_T_s = s_T_c.inverse().matrix()
        cam_pos = s_T_c.translation()
        K = self.camera.K
        boxes = []
        for tid in present:
            spec = self.model.tags[tid]
            normal = spec.structure_T_tag.rotation().matrix()[:, 2]
            to_cam = cam_pos - spec.structure_T_tag.translation()
            dist = float(np.linalg.norm(to_cam))
            if dist > c.max_distance_m or np.dot(normal, to_cam) / dist < np.cos(c.max_view_angle_rad):
                continue
            pc = (c_T_s[:3, :3] @ self._tag_corners[tid].T).T + c_T_s[:3, 3]
            if np.any(pc[:, 2] < 0.1):
                continue
            uv = (K @ (pc / pc[:, 2:3]).T).T[:, :2]
            if (uv[:, 0].min() < c.margin_px or uv[:, 1].min() < c.margin_px
                    or uv[:, 0].max() > self.camera.width_px - c.margin_px
                    or uv[:, 1].max() > self.camera.height_px - c.margin_px):
                continue
            sides = np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1)
            if sides.min() < c.min_side_px:
                continue
            boxes.append((float(pc[:, 2].mean()), tid, uv.min(axis=0), uv.max(axis=0)))
        boxes.sort()
        seen: list[int] = []
        kept: list[tuple[np.ndarray, np.ndarray]] = []
        for _, tid, lo, hi in boxes:
            area = float(np.prod(hi - lo))
            covered = max((float(np.prod(np.clip(np.minimum(hi, h2) - np.maximum(lo, l2), 0, None))) for l2, h2 in kept),
                          default=0.0)
            kept.append((lo, hi))
            if covered <= c.occlusion_overlap * area:
                seen.append(tid)
        return seen

    def plan(self, module: str, placed_modules: Sequence[str], precision: PrecisionTarget | None = None) -> SurveyPlan:
        """Views for the step that placed `module`; `placed_modules` includes it."""
        model = self.model
        present = set(model.turntable.tag_ids)
        for name in placed_modules:
            present.update(model.module_by_name[name].tags)
        new = list(model.module_by_name[module].tags)
        related = {t: [r for r in _related(model, t) if r in present and r not in new] for t in new}
        sight = {v: self.visible(v, present) for v in self._facing(module)}
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

        for distinct in (True, False):
            while len(chosen) < self.config.views_per_step:
                def score(v: View) -> tuple[float, float]:
                    s = set(sight[v])
                    gain = sum(1.0 for t in new if need_count[t] > 0 and t in s and fresh(t, v, distinct))
                    gain += sum(2.0 for t in new if need_pair[t] and t in s and s.intersection(related[t]))
                    if need_together and all(t in s for t in new):
                        gain += 2.0
                    # prefer views that also see many tags (better conditioned), then small motions
                    return gain, len(s) * 0.01 - abs(v.turntable_rad) * 1e-3
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
        if not chosen:  # nothing sees the new tags: still look, from the face the module is on
            face = model.module_by_name[module].face
            chosen = [min(self.candidates, key=lambda v: (abs(v.turntable_rad - (face - 1) * np.pi / 2),
                                                          np.abs(v.stewart_pose).sum()))]
        predicted = None
        if precision is not None:
            extra, predicted = self._accurate(module, [v for v in sight if v not in chosen], sight, precision,
                                              self._information(module, chosen, sight, precision),
                                              precision.max_views - len(chosen))
            chosen += extra
        chosen.sort(key=lambda v: (v.turntable_rad, v.stewart_pose))
        expected = [sight[v] if v in sight else self.visible(v, present) for v in chosen]
        seen_new = set().union(*map(set, expected)) if expected else set()
        return SurveyPlan(module, chosen, expected, [t for t in new if t not in seen_new], predicted)

    def more_views(self, module: str, placed_modules: Sequence[str], taken: Sequence[View],
                   tag_covariance: np.ndarray | None, precision: PrecisionTarget, budget: int) -> SurveyPlan:
        """Views to add, at most `budget`, for a module whose verdict is still open: the accuracy
        pass again, starting from its verdict tag's covariance in the graph."""
        present = set(self.model.turntable.tag_ids)
        for name in placed_modules:
            present.update(self.model.module_by_name[name].tags)
        sight = {v: self.visible(v, present) for v in self._facing(module) if v not in taken}
        info = np.zeros((6, 6)) if tag_covariance is None else np.linalg.inv(tag_covariance)
        views, predicted = self._accurate(module, list(sight), sight, precision, info, budget)
        views.sort(key=lambda v: (v.turntable_rad, v.stewart_pose))
        return SurveyPlan(module, views, [sight[v] for v in views], [], predicted)

    # ---- accuracy ------------------------------------------------------------------------------
    def _facing(self, module: str) -> list[View]:
        """Candidates that can see the module's face at all (the others only cost time to check)."""
        face = self.model.module_by_name[module].face
        if not 1 <= face <= 4:
            return list(self.candidates)
        centre = (face - 1) * np.pi / 2
        return [v for v in self.candidates
                if abs((v.turntable_rad - centre + np.pi) % (2 * np.pi) - np.pi) <= np.radians(70.0)]

    def _verdict_tag(self, module: str) -> int:
        return self.model.module_by_name[module].tags[0]

    def _view_information(self, module: str, view: View, sight: dict[View, list[int]],
                          precision: PrecisionTarget) -> np.ndarray:
        tag = self._verdict_tag(module)
        if tag not in sight.get(view, ()):
            return np.zeros((6, 6))
        spec = self.model.tags[tag]
        return view_information(self.structure_T_camera(view), spec.structure_T_tag, self.camera.K,
                                tag_object_points(spec.size_m), precision.corner_sigma_px,
                                precision.camera_covariance)

    def _information(self, module: str, views: Sequence[View], sight: dict[View, list[int]],
                     precision: PrecisionTarget) -> np.ndarray:
        return sum((self._view_information(module, v, sight, precision) for v in views), np.zeros((6, 6)))

    def predicted_sigma(self, module: str, info: np.ndarray) -> float:
        cov = covariance_from_information(info)
        if cov is None:
            return float("inf")
        tag = self._verdict_tag(module)
        m = self.model.module_by_name[module]
        tag_T_module = self.model.tags[tag].structure_T_tag.inverse().compose(m.structure_T_module)
        return module_sigma(tag_T_module, cov).position_m

    def _accurate(self, module: str, candidates: list[View], sight: dict[View, list[int]],
                  precision: PrecisionTarget, info: np.ndarray, budget: int) -> tuple[list[View], float]:
        """Greedy: the view that shrinks the predicted sigma most, until the target or the budget."""
        gains = {v: self._view_information(module, v, sight, precision) for v in candidates}
        gains = {v: g for v, g in gains.items() if g.any()}
        chosen: list[View] = []
        sigma = self.predicted_sigma(module, info)
        while sigma > precision.sigma_m and len(chosen) < budget and gains:
            best = min(gains, key=lambda v: (self.predicted_sigma(module, info + gains[v]), abs(v.turntable_rad)))
            info = info + gains.pop(best)
            chosen.append(best)
            sigma = self.predicted_sigma(module, info)
        return chosen, sigma


def _related(model: BorgModel, tag: int) -> list[int]:
    out = []
    for r in model.relations:
        if r.a == tag:
            out.append(r.b)
        elif r.b == tag:
            out.append(r.a)
    return out
