"""Views that adapt (issue 23): a planned view that does not show the tags it was planned for is
followed, within the step's view budget, by views re-planned from the calibrated rig and the
graph's estimate of the structure, and the module gets a verdict; what was tried is in its reason."""

from __future__ import annotations

import math

from procedures.build import build_procedure
from lab.core.recorder import RunRecorder
from procedures import runner
from procedures.survey import SurveyPlan, View


def _run_with_plan_for_2d(tmp_path, plan_of):
    """A run of the 3x3x3's first two modules in which 2D's plan is `plan_of(proc, tags)`, each view
    "planned" to show both its tags; the procedure and 2D's tags, once the run has completed."""
    proc, bench, _ = build_procedure("borg", {"n": 3, "modules": 2, "no_rig_survey": True, "speedup": 100.0})
    try:
        tags = proc.model.module_by_name["2D"].tags
        views = plan_of(proc, tags)
        proc.surveys["2D"] = SurveyPlan("2D", views, [list(tags)] * len(views), [], None)
        outcome = runner.run(proc, tmp_path / "r", info={}, operator_auto=True, show_progress=False,
                             recorder_factory=lambda p: RunRecorder(p, "borg", {}))
    finally:
        proc.close()
    assert outcome.result == "completed", outcome
    return proc, tags


def test_a_planned_view_that_misses_is_re_planned_and_the_module_gets_a_verdict(tmp_path):
    def bad_plan(proc, tags):
        # a deliberately bad plan for 2D (face 1): one view of face 3, "planned" to show its tags
        bad = View(math.pi, (0.0,) * 6)
        assert not set(tags) & set(proc.planner.visible(bad, proc.model.tags))
        return [bad]

    proc, tags = _run_with_plan_for_2d(tmp_path, bad_plan)
    r = proc.results["2D"]
    assert r.verdict == "ok", (r.verdict, r.reason)
    assert set(r.tags_seen) == set(tags)
    views = [v for v in proc.views_done if v["module"] == "2D"]
    assert views[0]["turntable_rad"] == math.pi and not set(tags) & {d["id"] for d in views[0]["detections"]}
    again = [v for v in views if v["round"] >= 1]
    assert again and r.views == len(views) == 1 + len(again) <= proc.precision.max_views
    # the re-planned views are the ones that showed it
    assert set(tags) <= {d["id"] for v in again for d in v["detections"]}
    assert f"re-planned: tag {tags[0]} seen in 0 of 1 view(s), tag {tags[1]} seen in 0 of 1 view(s)" in r.reason
    assert "every tag of it measured" in r.reason
    # the module planned as usual is untouched by it
    assert "re-planned" not in proc.results["1P"].reason


def test_a_strut_across_the_line_of_sight_hides_a_point_and_one_behind_it_does_not():
    import numpy as np

    from procedures.survey import _segments_within

    cam = np.zeros(3)
    pts = np.array([[0.0, 0.0, 2.0], [0.3, 0.0, 2.0]])
    across = (np.array([[-1.0, 0.005, 1.0]]), np.array([[1.0, 0.005, 1.0]]))      # 5 mm off both sight lines' plane
    assert _segments_within(cam, pts, *across, radius=0.015).tolist() == [True, True]
    behind = (np.array([[-1.0, 0.0, 2.5]]), np.array([[1.0, 0.0, 2.5]]))
    assert _segments_within(cam, pts, *behind, radius=0.015).tolist() == [False, False]
    beside = (np.array([[0.1, -1.0, 1.0]]), np.array([[0.1, -0.05, 1.0]]))        # ends short of the lines
    assert _segments_within(cam, pts, *beside, radius=0.015).tolist() == [False, False]
    short = (np.array([[-1.0, 0.0, 1.0]]), np.array([[0.1, 0.0, 1.0]]))           # crosses only the first
    assert _segments_within(cam, pts, *short, radius=0.015).tolist() == [True, False]
    # the member a tag is mounted on, 2 cm behind its face, is not in front of it
    mount = (np.array([[-1.0, 0.0, 2.02]]), np.array([[1.0, 0.0, 2.02]]))
    assert _segments_within(cam, pts, *mount, radius=0.015).tolist() == [False, False]


def test_a_tag_planned_from_two_turntable_angles_and_seen_from_one_is_re_planned(tmp_path):
    """Its depth was to come from triangulation: views from one angle leave it to the tag's size
    (N = 7, 159D: `uncertain` at 2.4 mm where 0.25 mm was planned)."""
    def one_angle_and_a_miss(proc, tags):
        present = proc.model.tags
        seeing = [v for v in proc.planner.candidates if set(tags) <= set(proc.planner.visible(v, present))]
        angle = next(a for a in sorted({v.turntable_rad for v in seeing})
                     if sum(v.turntable_rad == a for v in seeing) >= 2)
        good = [v for v in seeing if v.turntable_rad == angle][:2]
        # ... and one "planned" from the far side, where 2D's face cannot be seen
        bad = View(angle + math.pi, (0.0,) * 6)
        assert not set(tags) & set(proc.planner.visible(bad, present))
        return good + [bad]

    proc, tags = _run_with_plan_for_2d(tmp_path, one_angle_and_a_miss)
    r = proc.results["2D"]
    views = [v for v in proc.views_done if v["module"] == "2D"]
    first_round = [v for v in views if v["round"] == 0]
    assert len(first_round) == 3 and all(set(tags) <= {d["id"] for d in v["detections"]} for v in first_round[:2])
    again = [v for v in views if v["round"] >= 1]
    assert again, r.reason
    angles = {round(v["turntable_rad"], 6) for v in views if set(tags) & {d["id"] for d in v["detections"]}}
    assert max(angles) - min(angles) >= proc.planner.config.min_angle_separation_rad, angles
    assert f"tag {tags[0]} seen in 2 of 3 view(s), all from one turntable angle" in r.reason, r.reason
    assert r.verdict == "ok", (r.verdict, r.reason)


def test_a_tag_seen_from_its_second_angle_only_too_obliquely_to_use_is_re_planned(tmp_path):
    """A detection the graph leaves out as too oblique (`rig_model.MIN_SIDE_RATIO`) measured nothing:
    it may not stand for the second turntable angle the plan counted on (at N = 6, 52S: `ok` 2.6 mm
    from the truth at a 1-sigma of 0.76 mm, its print scale and its depth left to one angle)."""
    import numpy as np

    from estimation.rig_model import MIN_SIDE_RATIO, side_ratio

    def face_on_and_too_oblique(proc, tags):
        present = proc.model.tags
        face_on = [v for v in proc.planner.candidates
                   if v.turntable_rad == 0.0 and set(tags) <= set(proc.planner.visible(v, present))][:1]
        # 2D's face turned ~50 deg further: still detected, but flatter than the graph takes
        oblique = [View(OBLIQUE_RAD, (0.0,) * 6), View(OBLIQUE_RAD, (0.0, 0.0, 0.0, 0.0, 0.0, 0.05))]
        return face_on + oblique

    proc, tags = _run_with_plan_for_2d(tmp_path, face_on_and_too_oblique)
    r = proc.results["2D"]
    views = [v for v in proc.views_done if v["module"] == "2D"]
    first_round = [v for v in views if v["round"] == 0]
    K, dist = proc.measure.slam.camera
    flat = [side_ratio(np.asarray(d["corners_px"], float), K, dist)
            for v in first_round[1:] for d in v["detections"] if d["id"] in tags]
    # the oblique views did detect the tags, every one of them too flat to use
    assert len(flat) == 4 and max(flat) < MIN_SIDE_RATIO, flat
    again = [v for v in views if v["round"] >= 1]
    assert again, r.reason
    assert f"tag {tags[0]} seen in 1 of 3 view(s)" in r.reason, r.reason
    assert r.verdict == "ok", (r.verdict, r.reason)


OBLIQUE_RAD = 0.85
