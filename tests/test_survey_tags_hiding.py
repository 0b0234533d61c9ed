"""The planner predicts the detector's own rule for a tag a nearer one hides: a nearer tag's quiet
zone across one corner of a farther tag's black square is enough for the detector to drop it
(`estimation.fiducials.partly_hidden`), though it covers far less than a quarter of the tag's image
box (the planner's rule before).  At N = 8 (seed 0) 362P's plan counted on five views of its tag
489 from turntable 180 deg where a nearer tag's border crossed that corner: none showed it, the
views the re-plan found all looked from one direction, and the module came out `uncertain` at a
1-sigma of 4.2 mm, 6.5 mm off the truth, where the plan had predicted 0.78 mm (issue 23)."""

from __future__ import annotations

import numpy as np

from drivers.stewart_kinematics import StewartKinematics
from lab.core.config import load_rig
from lab.core.structures.borg import build_borg
from procedures.survey import CameraModel, SurveyConfig, SurveyPlanner, View, unoccluded

K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])


def _planner(n: int, config=None, station: str | None = None) -> SurveyPlanner:
    rig = load_rig().for_borg(n) if station is None else load_rig().at_station(station)
    kin = StewartKinematics(rig.stewart.geometry)
    camera = CameraModel(K, 1280, 720, rig.stewart.world_T_base, rig.stewart.geometry.home_m,
                         rig.camera.platform_T_camera)
    return SurveyPlanner(build_borg(n), camera, lambda pose: kin.inverse(pose).reachable,
                         (rig.turntable.min_rad, rig.turntable.max_rad), config,
                         lift_limits_m=(rig.lift.min_m, rig.lift.max_m))


def _present_at(p: SurveyPlanner, module: str) -> set[int]:
    names = [m.name for m in p.model.modules]
    return set(p.model.turntable.tag_ids).union(*(p.model.module_by_name[n].tags
                                                   for n in names[:names.index(module) + 1]))


def test_a_nearer_tags_border_across_a_corner_hides_the_tag_from_the_plan():
    p = _planner(8, station="far")        # where the case was found (N = 8 stood far until stop 53)
    present = _present_at(p, "362P")
    hidden = View(np.pi, (0.0, -0.04, 0.0, 0.0, 0.0, 0.0), 2.25)
    clear = View(3.32, (0.0, -0.04, 0.0, 0.0, 0.0, 0.0), 2.25)      # the re-plan's: the tag was read there
    assert 489 not in p.visible(hidden, present)
    assert 489 in p.visible(clear, present)
    # the box rule alone would count on the hidden view (else this test shows nothing)
    g = p._geometry(hidden)
    idx = p.present_index(present)
    idx = idx[g.ok[idx]]
    idx = idx[np.lexsort((p._ids[idx], g.depth[idx]))]
    row = int(np.flatnonzero(p._ids[idx] == 489)[0])
    assert unoccluded(g.lo[idx], g.hi[idx], np.array([row]), p.config.occlusion_overlap)[0]


def test_a_tag_too_near_the_frames_edge_to_read_still_hides_what_is_behind_it():
    # N = 9, 401P's first planned view: its tag 589 lies under the front face's tag 532, whose top
    # is 8 px from the frame's edge (inside the margin: not readable, but there).  The plan counted
    # on the view; the detector read nothing of 589 (every seed)
    p = _planner(9)
    view = View(0.0, (0.0, 0.0, 0.03, 0.0, 0.0, 0.0), 2.5)
    present = _present_at(p, "401P")
    g = p._geometry(view)
    i532 = p._index[532]
    assert g.drawn[i532] and not g.ok[i532]
    assert 589 not in p.visible(view, present) and 532 not in p.visible(view, present)
    # without 532 the view would show 589 (else this test shows nothing)
    assert 589 in p.visible(view, present - {532})
    # and the assembly-order table (`_visible_at`) says the same
    step = [m.name for m in p.model.modules].index("401P") + 1
    assert 589 not in p._visible_at(view, step)


def test_a_re_plan_does_not_count_on_a_tag_predicted_clear_of_a_nearer_one_by_less_than_the_clearance():
    # N = 9, turntable 25 deg: the design has 401P's tag 589 under the nearer tag 542's quiet zone.
    # The run's adapted prediction (its calibrated camera, 589 where the graph had it) left 0.1 px
    # between them; the detector dropped 589 as partly behind 542 in all five views planned there
    # (seed 2).  Here 589 predicted 8 mm along the face, ~1.7 px clear of 542 by the detector's
    # exact rule: a plan does not count on that
    from gtsam import Point3, Pose3

    view = View(0.4363323129985824, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0), 2.75)
    seen = {}
    for clearance in (0.0, 2.0):
        p = _planner(9, SurveyConfig(replan_hidden_clearance_px=clearance))
        design = p.model.tags[589].structure_T_tag
        moved = Pose3(design.rotation(), Point3(*(design.translation() + np.array([0.0, -0.008, 0.0]))))
        adapted = p.adapted(p.structure_T_camera, {589: moved})
        seen[clearance] = 589 in adapted.visible(view, _present_at(p, "401P"))
    assert seen == {0.0: True, 2.0: False}
    assert SurveyConfig().replan_hidden_clearance_px == 2.0


def test_a_plan_orders_two_cards_on_one_face_as_the_detector_does():
    # N = 10 seed 4: 639S, placed 2.8 mm up, put its tag 888's card over the quiet zone of 640S's
    # tag 889, 12 cm above it on the same face.  The re-plan took the tag nearer along the optical
    # axis to be in front and predicted 889 clear six times; the detector, whose predicted planes
    # agree there, keeps the card with the nearer centre (888, seen from below) and dropped 889
    # every time.  Here: a face leaning 3 deg toward a camera that looks level, the upper tag
    # 6 mm nearer along the axis and 12 mm farther from the camera; the plan must see what the
    # detector on the rendered frame reads.
    from estimation.fiducials import TagDetector
    from lab.core.geometry import Pose3, Rot3
    from sim_devices.render import render_tags

    p = _planner(3)
    upper_id, lower_id = sorted(p.model.tags)[:2]
    size = p.model.tags[upper_id].size_m
    assert p.model.tags[lower_id].size_m == size
    view = p.candidates[0]
    s_T_c = p.structure_T_camera(view)
    camera, forward = s_T_c.translation(), s_T_c.rotation().matrix()[:, 2]
    assert abs(forward[2]) < 1e-9                                   # the camera looks level
    lean = np.radians(3.0)
    up = np.array([0.0, 0.0, 1.0])
    across = np.cross(up, -forward)
    face_up = np.cos(lean) * up - np.sin(lean) * forward           # the top leans toward the camera
    normal = np.cross(across, face_up)
    rot = Rot3(np.column_stack([across, face_up, normal]))
    upper_at = camera + 1.6 * forward + 0.3 * up
    poses = {upper_id: Pose3(rot, upper_at), lower_id: Pose3(rot, upper_at - (0.12 - 0.0028) * face_up)}
    adapted = p.adapted(p.structure_T_camera, poses)
    g = adapted._geometry(view)
    iu, il = adapted._index[upper_id], adapted._index[lower_id]
    # what makes the case: the optical axis and the centres put different tags in front
    assert g.depth[iu] < g.depth[il] and g.centre_m[iu] > g.centre_m[il]

    c_T_s = s_T_c.inverse()
    seen_as = {t: c_T_s.compose(pose) for t, pose in poses.items()}
    img = render_tags(K, None, 1280, 720, [(t, size, pose) for t, pose in seen_as.items()], background=110.0,
                      blur_sigma_px=0.8, noise_sigma=2.0, rng=np.random.default_rng(1))
    det = TagDetector(K, np.zeros(5), {upper_id: size, lower_id: size})
    read, behind = det.detect_with_hidden(img, seen_as.get)
    assert [d.tag_id for d in read] == [lower_id] and behind == {upper_id: lower_id}
    assert adapted.visible(view, {upper_id, lower_id}) == [lower_id]
