"""The survey planner with a lift: the heights it picks, what they make observable, and the
visibility rules it applies (checked against a plain one-tag-at-a-time reading of them)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from drivers.stewart_kinematics import StewartKinematics
from estimation.fiducials import HIDDEN_MIN_OVERLAP_CELLS2, HIDDEN_ORDER_MIN_M, grown_quad
from lab.core.config import load_rig
from lab.core.structures.borg import build_borg
from procedures.survey import CameraModel, SurveyPlanner, View

RIG = load_rig()
K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])
KIN = StewartKinematics(RIG.stewart.geometry)
CAMERA = CameraModel(K, 1280, 720, RIG.stewart.world_T_base, RIG.stewart.geometry.home_m, RIG.camera.platform_T_camera)
TURNTABLE = (RIG.turntable.min_rad, RIG.turntable.max_rad)
LIFT = (RIG.lift.min_m, RIG.lift.max_m)


def planner(n: int, lift: tuple[float, float] | None = LIFT) -> SurveyPlanner:
    return SurveyPlanner(build_borg(n), CAMERA, lambda p: KIN.inverse(p).reachable, TURNTABLE, lift_limits_m=lift)


def unobservable(p: SurveyPlanner) -> dict[str, list[int]]:
    placed, out = [], {}
    for m in p.model.modules:
        placed.append(m.name)
        plan = p.plan(m.name, placed)
        if plan.unobservable:
            out[m.name] = plan.unobservable
    return out


def test_the_3x3x3_cube_never_moves_the_lift():
    """The home height sees all of it: the planner with a lift has exactly the candidates (and so
    the plans) it had without one."""
    with_lift, without = planner(3), planner(3, None)
    assert with_lift.lift_heights == (0.0,)
    assert with_lift.candidates == without.candidates
    placed = []
    for m in with_lift.model.modules:
        placed.append(m.name)
        assert with_lift.plan(m.name, placed).views == without.plan(m.name, placed).views


def test_a_5x5x5_needs_the_lift_and_sees_every_module_with_it():
    lifted, fixed = planner(5), planner(5, None)
    assert len(lifted.lift_heights) > 1 and 0.0 in lifted.lift_heights
    assert max(lifted.lift_heights) >= 0.75                    # the top layer, 2.5 m up, near face-on
    assert unobservable(lifted) == {}
    hidden = unobservable(fixed)
    top = [m.name for m in fixed.model.modules if m.structure_T_module.translation()[2] >= 2.0]
    # the top layer is out of the fixed camera's sight; from its one height, struts in front also
    # hide some inner modules' tags (50CT's, 1 m in from face 1), which other heights see past
    assert hidden and set(hidden) & set(top)
    # a module the fixed rig cannot see is planned from a lifted view
    name = next(iter(hidden))
    placed = [m.name for m in lifted.model.modules[:[m.name for m in lifted.model.modules].index(name) + 1]]
    assert any(v.lift_m > 0 for v in lifted.plan(name, placed).views)


def test_heights_come_from_the_lifts_travel():
    low = planner(5, (0.0, 0.3))
    assert set(low.lift_heights) <= {0.0, 0.25}
    assert unobservable(low)                                   # a short lift cannot reach the top


def test_a_view_label_names_the_lift_only_when_it_is_used():
    pose = (0.0, 0.04, 0.0, 0.0, 0.0, 0.0)
    assert "lift" not in View(0.5, pose).label
    assert View(0.5, pose, 1.0).label.endswith(", lift +1000 mm")


def _visible_one_by_one(p: SurveyPlanner, view: View, present: list[int]) -> tuple[list[int], dict[int, float]]:
    """The documented rules, one tag at a time: near enough, facing the camera within the view
    angle, all corners in front and inside the image by the margin, sides long enough to decode;
    nearest first, hidden when a nearer tag with any of its image in the frame (readable or not)
    covers more than the overlap fraction of its box, or when another such tag's quiet zone,
    widened by the re-plan's clearance (none in a plan from the design), crosses the band around
    its black square and the detector would put that tag in front; seen
    only when its image is no flatter than `min_side_ratio` (a flatter one still hides others).
    Also each readable tag's depth (its corners' mean, the order `visible` reports)."""
    c = p.config
    s_T_c = p.structure_T_camera(view)
    c_T_s = s_T_c.inverse().matrix()
    boxes = []
    for tid in present:
        T = p.model.tags[tid].structure_T_tag
        to_cam = s_T_c.translation() - T.translation()
        d = np.linalg.norm(to_cam)
        if d > c.max_distance_m or T.rotation().matrix()[:, 2] @ to_cam / d < np.cos(c.max_view_angle_rad):
            continue
        h = p.model.tags[tid].size_m / 2
        corners = [T.transformFrom(np.array([x, y, 0.0])) for x, y in ((-h, -h), (h, -h), (h, h), (-h, h))]
        pc = np.array([c_T_s[:3, :3] @ q + c_T_s[:3, 3] for q in corners])
        if np.any(pc[:, 2] < 0.1):
            continue
        uv = np.array([(K @ (q / q[2]))[:2] for q in pc])
        if (uv.max(axis=0) < 0).any() or uv[:, 0].min() > 1280 or uv[:, 1].min() > 720:
            continue                                      # wholly off the frame: hides nothing
        readable = not ((uv.min(axis=0) < c.margin_px).any() or uv[:, 0].max() > 1280 - c.margin_px
                        or uv[:, 1].max() > 720 - c.margin_px
                        or np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1).min() < c.min_side_px)
        normal = c_T_s[:3, :3] @ T.rotation().matrix()[:, 2]
        centre = pc.mean(axis=0)
        boxes.append((pc[:, 2].mean(), tid, uv.min(axis=0), uv.max(axis=0), uv, readable,
                       float(np.linalg.norm(centre)), np.array([*normal, normal @ centre])))
    boxes.sort(key=lambda b: (b[0], b[1]))

    def in_front(a, b, overlap):
        # the detector's order with both planes predicted: the nearer plane along the line of
        # sight through the overlap, else the nearer centre (a tie within 5 mm: either way)
        ray = np.linalg.solve(K, [*np.asarray(overlap, float).reshape(-1, 2).mean(axis=0), 1.0])
        da, db = (x[7][3] / (x[7][:3] @ ray) for x in (a, b))
        return da < db if abs(da - db) > HIDDEN_ORDER_MIN_M else a[6] < b[6] + 0.005

    seen, kept = [], []
    for this in boxes:
        _, tid, lo, hi, uv, readable = this[:6]
        covered = max((np.prod(np.clip(np.minimum(hi, h2) - np.maximum(lo, l2), 0, None)) for l2, h2, _ in kept),
                      default=0.0)
        # the detector's rule (fiducials.partly_hidden): a nearer tag's quiet zone across the band
        # around this one's black square, the quiet zone widened by the clearance (in its own cells)
        band = grown_quad(uv, 0.5).astype(np.float32)
        cell = abs(cv2.contourArea(uv.astype(np.float32))) / 64.0

        def outer(q):
            side = np.linalg.norm(np.roll(q, -1, axis=0) - q, axis=1).mean() / 8.0
            clearance = c.replan_hidden_clearance_px if p._camera_of is not None else 0.0
            return grown_quad(q, 1.0 + clearance / side).astype(np.float32)

        def crosses(other) -> bool:
            area, overlap = cv2.intersectConvexConvex(outer(other[4]), band)
            return area > HIDDEN_MIN_OVERLAP_CELLS2 * cell and in_front(other, this, overlap)

        crossed = any(crosses(other) for other in boxes if other[1] != tid)
        kept.append((lo, hi, uv))
        # a tag seen flatter than the graph takes still hides the others, but is not counted seen
        sides = np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1)
        flat = sides.min() < c.min_side_ratio * sides.max()
        if readable and covered <= c.occlusion_overlap * np.prod(hi - lo) and not crossed and not flat:
            seen.append(tid)
    return seen, {tid: depth for depth, tid, *_ in boxes}


@pytest.mark.parametrize("n", [3, 4, 9])
def test_visibility_follows_the_rules_tag_by_tag(n):
    p = planner(n)
    rng = np.random.default_rng(n)
    everything = sorted(p.model.tags)
    for k in rng.choice(len(p.candidates), 40, replace=False):
        view = p.candidates[int(k)]
        present = [t for t in everything if rng.random() < 0.7]
        got, (want, depth) = p.visible(view, present), _visible_one_by_one(p, view, present)
        # the same tags, nearest first; tags at the same depth to round-off (placed symmetrically)
        # may come in either order
        assert sorted(got) == sorted(want)
        assert all(depth[a] <= depth[b] + 1e-9 for a, b in zip(got, got[1:])), (got, want)
