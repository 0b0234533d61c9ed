"""The first plan of a module counts only on views whose lines of sight to its tags clear the
struts built so far: at N = 4 the top layer's strut brackets sit behind the struts in front of
them from many views the tags-only visibility model would pick (issue 23)."""

from __future__ import annotations

import numpy as np

from drivers.stewart_kinematics import StewartKinematics
from lab.core.config import load_rig
from lab.core.structures.borg import build_borg
from procedures.survey import CameraModel, SurveyPlanner

RIG = load_rig()
K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])
KIN = StewartKinematics(RIG.stewart.geometry)
CAMERA = CameraModel(K, 1280, 720, RIG.stewart.world_T_base, RIG.stewart.geometry.home_m, RIG.camera.platform_T_camera)


def _planner(n: int) -> SurveyPlanner:
    """The default rig's planner (near station) for an n x n x n BORG."""
    return SurveyPlanner(build_borg(n), CAMERA, lambda pose: KIN.inverse(pose).reachable,
                         (RIG.turntable.min_rad, RIG.turntable.max_rad), lift_limits_m=(RIG.lift.min_m, RIG.lift.max_m))


def test_a_first_plan_does_not_count_on_a_view_a_strut_crosses():
    p = _planner(4)
    names = [m.name for m in p.model.modules]
    module = "102S"
    placed = names[:names.index(module) + 1]
    tag = p.model.module_by_name[module].tags[0]
    struts = p._struts(placed)
    # the tags-only model would count on views a strut crosses (else this test shows nothing)
    present = p.present_index(set(p.model.turntable.tag_ids).union(*(p.model.module_by_name[n].tags for n in placed)))
    tags_only = [v for v in p._seeing(p._facing(module), [tag]) if tag in p.visible(v, present)]
    assert p._behind_struts(tag, tags_only, struts).any()
    plan = p.plan(module, placed)
    counted = [v for v, seen in zip(plan.views, plan.expected) if tag in seen]
    assert counted, "the plan still sees the tag from somewhere"
    assert not p._behind_struts(tag, counted, struts).any()


def _hub_hides(cam: np.ndarray, pts: np.ndarray, hubs: np.ndarray, normal: np.ndarray, centre: np.ndarray) -> bool:
    """One line and one hub at a time: a hub in front of the face within its radius plus the
    margin of a line from the camera to a face point, on the line's first SIGHT_FRONT."""
    from procedures.survey import NODE_DIAMETER_M, SIGHT_FRONT, STRUT_MARGIN_M

    r = NODE_DIAMETER_M / 2 + STRUT_MARGIN_M
    for hub in hubs:
        if (hub - centre) @ normal <= r:
            continue
        for q in pts:
            d = (q - cam) * SIGHT_FRONT
            t = min(max((hub - cam) @ d / (d @ d), 0.0), 1.0)
            if np.linalg.norm(hub - cam - t * d) < r:
                return True
    return False


def test_the_struts_pruned_by_the_central_line_give_the_answer_of_every_strut():
    from procedures.survey import STRUT_DIAMETER_M, STRUT_MARGIN_M, _face_grid, _segments_within

    p = _planner(4)
    placed = [m.name for m in p.model.modules]
    a, b = p._struts(placed)
    hidden = 0
    for module in ("102S", "71D", "41P", "1D"):
        for tag in p.model.module_by_name[module].tags:
            views = p._seeing(p._facing(module), [tag])
            fast = p._behind_struts(tag, views, (a, b))
            h = p.model.tags[tag].size_m / 2
            pose = p.structure_T_tag(tag)
            R = pose.rotation().matrix()
            pts = _face_grid(h) @ R.T + pose.translation()
            hubs = np.unique(np.vstack([a, b]), axis=0)
            slow = [bool(_segments_within(p.structure_T_camera(v).translation(), pts, a, b,
                                          STRUT_DIAMETER_M / 2 + STRUT_MARGIN_M).any())
                    or _hub_hides(p.structure_T_camera(v).translation(), pts, hubs, R[:, 2], pose.translation())
                    for v in views]
            assert fast.tolist() == slow
            hidden += sum(slow)
    assert hidden > 0


def test_a_hub_and_a_strut_between_the_old_grid_rows_hide_a_tag():
    """N = 7, from the far station (where a 7x7x7 was surveyed until stop 53; the case is kept for
    the geometry): 160D's tag 226 stands half a cell behind face 2.  The run's
    frames showed the face's node hub under its black square from (turntable 295 deg, lift 1.75 m)
    and the face's strut across its lower half from (288 deg, 1.5 m), and the detector rightly
    read neither; the planner had counted on both (hubs were not modelled, and a 3 x 3 grid of
    lines passed either side of the strut), so the module was seen from one direction only and
    came out `uncertain` at 1-sigma 3.6 mm after 12 views."""
    from procedures.survey import View

    rig = load_rig().for_borg(7).at_station("far")
    camera = CameraModel(K, 1280, 720, rig.stewart.world_T_base, rig.stewart.geometry.home_m, rig.camera.platform_T_camera)
    p = SurveyPlanner(build_borg(7), camera, lambda pose: KIN.inverse(pose).reachable,
                      (rig.turntable.min_rad, rig.turntable.max_rad), lift_limits_m=(rig.lift.min_m, rig.lift.max_m))
    names = [m.name for m in p.model.modules]
    placed = names[:names.index("160D") + 1]
    hub = View(np.radians(295.0), (0.0,) * 6, 1.75)
    strut = View(np.radians(288.0), (0.0, 0.0, 0.03, 0.0, 0.0, 0.0), 1.5)
    clear = View(np.radians(245.0), (0.0, -0.04, 0.0, 0.0, 0.0, 0.0), 1.75)   # the run read it from here
    step = len(placed)
    assert all(226 in p._visible_at(v, step) for v in (hub, strut, clear))     # tags alone: all three
    a, b = p._struts(placed)
    assert p._behind_nodes(226, [hub, strut, clear], np.unique(np.vstack([a, b]), axis=0)).tolist() == [True, False, False]
    assert p._behind_struts(226, [hub, strut, clear], (a, b)).tolist() == [True, True, False]


def test_a_tag_few_candidate_views_see_gets_the_lifts_other_views_for_its_accuracy():
    """N = 6's close-out strut 135S: its tag is seen from 2 of the candidate views, which leave its
    predicted 1-sigma over the target; the plan and the further views look over the rest of the
    lift's travel and the wider looks (they stopped at those 2 views, and 135S came out `uncertain`
    at a 1-sigma of 1-2 mm in three seeds of five).  Since the plan counts only sightings the graph
    measures (`SurveyConfig.min_side_ratio`), its 2 views reach the target at the corner noise of a
    clean camera; a real calibration's 0.1 px does not."""
    from procedures.survey import PrecisionTarget

    p = _planner(6)
    names = [m.name for m in p.model.modules]
    module = "135S"
    placed = names[:names.index(module) + 1]
    tag = p.model.module_by_name[module].tags[0]
    assert len(p._seeing(p._facing(module), [tag])) == 2          # else this test shows nothing
    target = PrecisionTarget(corner_sigma_px=0.1)
    plan = p.plan(module, placed, target)
    assert len(plan.views) > 2 and any(v not in p.candidates for v in plan.views)
    two = p._information(module, [v for v in plan.views if v in p.candidates], p._sight(
        module, placed, set(p.model.tags), list(plan.views)), target)
    assert plan.predicted_sigma_m < p.predicted_sigma(module, two)
    more = p.more_views(module, placed, plan.views, np.diag([np.radians(0.3) ** 2] * 3 + [0.001 ** 2] * 3),
                        target, target.max_views - len(plan.views))
    assert more.views and not set(more.views) & set(plan.views)
