"""A module's plan predicts the 1-sigma the graph will state (issue 23): its views' share at the
corner noise the graph reads them with (the rig survey's measurement, not the rig file's
assumption), combined with the floor no view of the module reduces (the frame and the rig, which
the run measures from its own verdicts), and it stops adding views that cannot help."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from drivers.stewart_kinematics import StewartKinematics
from lab.core.config import load_rig
from lab.core.structures.borg import build_borg
from procedures.build import build_procedure
from procedures.survey import MIN_VIEW_GAIN, CameraModel, PrecisionTarget, SurveyPlan, SurveyPlanner

RIG = load_rig()
K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])
KIN = StewartKinematics(RIG.stewart.geometry)
CAMERA = CameraModel(K, 1280, 720, RIG.stewart.world_T_base, RIG.stewart.geometry.home_m, RIG.camera.platform_T_camera)
MODULE = "5D"


def _planner() -> tuple[SurveyPlanner, list[str]]:
    p = SurveyPlanner(build_borg(3), CAMERA, lambda pose: KIN.inverse(pose).reachable,
                      (RIG.turntable.min_rad, RIG.turntable.max_rad), lift_limits_m=(RIG.lift.min_m, RIG.lift.max_m))
    names = [m.name for m in p.model.modules]
    return p, names[:names.index(MODULE) + 1]


def _own(p: SurveyPlanner, plan: SurveyPlan, target: PrecisionTarget) -> float:
    return p.predicted_sigma(MODULE, p.plan_information(plan, target))


def test_a_plan_predicts_its_views_share_with_the_floor_and_stops_where_views_cannot_help():
    p, placed = _planner()
    target = PrecisionTarget(corner_sigma_px=0.031)
    free = p.plan(MODULE, placed, target)
    assert free.floor_sigma_m == 0.0 and free.corner_sigma_px == 0.031
    # the accuracy pass added views to reach the target: else this test shows nothing
    assert free.predicted_sigma_m <= target.sigma_m < p.plan(MODULE, placed, replace(target, sigma_m=1.0)).predicted_sigma_m
    floored = replace(target, floor_sigma_m=0.3e-3)           # above the target: no number of views reaches it
    plan = p.plan(MODULE, placed, floored)
    assert plan.floor_sigma_m == 0.3e-3
    assert math.isclose(plan.predicted_sigma_m, math.hypot(_own(p, plan, floored), 0.3e-3), rel_tol=1e-9)
    assert plan.predicted_sigma_m > floored.sigma_m and len(plan.views) < min(len(free.views), floored.max_views)
    # the best view left would have shrunk the prediction by less than MIN_VIEW_GAIN
    sight = p._sight(MODULE, placed, set(p.model.tags), p._seeing(p._facing(MODULE), p.model.module_by_name[MODULE].tags))
    info = p.plan_information(plan, floored)
    gains = [p._view_information(MODULE, v, sight, floored) for v in sight if v not in plan.views]
    best = min(floored.total_sigma(p.predicted_sigma(MODULE, info + g)) for g in gains if g.any())
    assert best > (1 - MIN_VIEW_GAIN) * plan.predicted_sigma_m


def test_the_graphs_covariance_already_holds_the_floor_so_more_views_ignore_it():
    p, placed = _planner()
    target = PrecisionTarget(corner_sigma_px=0.031)
    cov = np.diag([np.radians(0.05) ** 2] * 3 + [0.0006 ** 2] * 3)
    a = p.more_views(MODULE, placed, [], cov, target, 6)
    b = p.more_views(MODULE, placed, [], cov, replace(target, floor_sigma_m=0.3e-3), 6)
    assert a.views and a.views == b.views and a.predicted_sigma_m == b.predicted_sigma_m


def test_the_run_plans_at_the_measured_corner_noise_and_the_floor_its_verdicts_showed():
    proc, bench, _ = build_procedure("borg", {"n": 3, "modules": 6, "no_rig_survey": True, "speedup": 100.0})
    try:
        name = proc.modules[4].name
        first = proc.surveys[name]
        assert first.corner_sigma_px == proc.precision.corner_sigma_px and first.floor_sigma_m == 0.0
        assert proc._plan_of(name) is first                      # nothing measured since: kept
        # the rig survey measured the corners noisier than the rig file assumed
        proc._take_measured(proc.measure.config, 2.0 * first.corner_sigma_px, float("nan"))
        assert proc.measure.config["corner_sigma_px"] == proc.precision.corner_sigma_px == 2.0 * first.corner_sigma_px
        noisier = proc._plan_of(name)
        assert noisier.corner_sigma_px == 2.0 * first.corner_sigma_px and noisier.predicted_sigma_m > first.predicted_sigma_m
        # the floor: the median of the last FLOOR_WINDOW modules' (stated^2 - own views' share^2)
        proc._floor_m2 = [1.0] * 5 + [(0.1e-3) ** 2, (0.2e-3) ** 2, (0.2e-3) ** 2] + [(0.3e-3) ** 2] * 5
        assert math.isclose(proc._planning().floor_sigma_m, 0.3e-3)
        floored = proc._plan_of(name)
        assert floored.floor_sigma_m == proc._planning().floor_sigma_m and floored.predicted_sigma_m >= 0.3e-3
        assert proc.checkpoint()["plan_floor_m2"] == proc._floor_m2
        # a plan made without an accuracy pass (a test's, or a re-plan's) is the run's to keep
        planted = SurveyPlan(name, first.views, first.expected, [], None)
        proc.surveys[name] = planted
        assert proc._plan_of(name) is planted
    finally:
        proc.close()
