"""The rig calibration survey: turntable angles x Stewart poses that see the turntable tags, moved
to and photographed through the drivers, then solved by `estimation.rig_calibration`.

Used by `lab calibrate rig` and as the first step of a `lab run borg` whose rig has no calibration
file.  The plan is made for observability: the mount is seen only through platform rotations, so
the poses turn the platform about all three axes as far as the workspace allows while the camera
still looks down at the rim (the turntable tags sit below the structure); the focal length, which
trades against the mount along the optical axis, is seen through known changes of depth (the
platform's travel towards the tags) and rotations that sweep the tags across the image; the axis
is seen by turning the plate, so the angles cover the turntable's whole range.  Steps of 30 deg
bring every rim tag (30 deg apart) to the same three places in the image at every angle: near
and +-30 deg, all within 50 deg of incidence (an oblique tag's corners are biased).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from estimation.rig_calibration import CalibrationView, TagSighting
from estimation.rig_model import ViewMotion

_D = math.radians
# Relative to home: (x, y, z, roll, pitch, yaw); pitch 10 deg puts the near rim tags mid-image.
# Chosen by measurement (docs/calibration.md, "How the survey was chosen"): the camera mount's
# translation along the optical axis trades against the focal length (a 0.1 % focal error moves
# the camera 1.7 mm along its axis at the rim's distance), so the poses that pay are the ones that
# separate them: the platform's whole reach along x (towards / away from the tags, -0.12 to
# +0.18 m: a known change of depth), its whole roll (+-25 deg) and pitch (10 to 22 deg) reach, and
# yaw 25 deg with a sideways shift that keeps two tags in view.  Larger yaw or roll, or combined
# translations, leave the workspace or lose the tags (the rim tags are visible only within about
# 60 deg of incidence: three per view at most from the rig's camera position).  On the default sim
# rig (seed 0, 96 views each) this set gives the mount 0.42 mm off with sigma 0.26/0.20/0.32 mm
# where the first plan gave 1.05 mm and 0.49/0.28/0.51 mm; ordered for the shortest leg travel
# (a move takes as long as its largest leg change).
SURVEY_POSES: tuple[tuple[float, ...], ...] = (
    (-0.12, 0.0, 0.0, 0.0, _D(10), 0.0),
    (0.0, -0.12, 0.0, 0.0, _D(16), _D(-25)),
    (0.0, 0.0, 0.0, _D(25), _D(10), 0.0),
    (0.0, 0.0, 0.0, 0.0, _D(22), 0.0),
    (0.0, 0.0, 0.0, 0.0, _D(10), 0.0),
    (0.0, 0.0, 0.0, _D(-25), _D(10), 0.0),
    (0.0, 0.12, 0.0, 0.0, _D(16), _D(25)),
    (0.18, 0.0, 0.0, 0.0, _D(10), 0.0),
)
ANGLE_STEP_RAD = _D(30)


@dataclass(frozen=True)
class RigSurveyPlan:
    views: tuple[ViewMotion, ...]
    skipped: tuple[str, ...] = ()      # candidate poses the workspace refused, said once


def plan_rig_survey(reachable: Callable[[Sequence[float]], bool], turntable_limits_rad: tuple[float, float],
                    poses: Sequence[Sequence[float]] = SURVEY_POSES, angle_step_rad: float = ANGLE_STEP_RAD
                    ) -> RigSurveyPlan:
    """Every reachable survey pose at every turntable angle a full turn in `angle_step_rad` steps,
    within the limits; poses alternate direction from one angle to the next (shorter moves)."""
    lo, hi = turntable_limits_rad
    start = max(lo, -math.pi / 2)
    angles = [a for a in np.arange(start, start + 2 * math.pi - 1e-9, angle_step_rad) if lo <= a <= hi]
    ok = [tuple(float(v) for v in p) for p in poses if reachable(p)]
    skipped = tuple(f"platform pose {np.round(p, 3).tolist()} is outside the workspace" for p in poses
                    if tuple(float(v) for v in p) not in ok)
    views = []
    for i, a in enumerate(angles):
        for p in (ok if i % 2 == 0 else ok[::-1]):
            views.append(ViewMotion(float(a), p))
    return RigSurveyPlan(tuple(views), skipped)


def capture(bench: Any, run: Any, plan: RigSurveyPlan, detector: Any, *, seed: Sequence[int] = (),
            log_image: Callable[[Any, float], None] | None = None,
            on_view: Callable[[int, ViewMotion, list[Any]], None] | None = None) -> list[CalibrationView]:
    """Move to each planned view, grab, detect; returns what the solver needs.  In simulation the
    camera's noise (and the devices' repeatability) is reseeded per view from `seed` + the view
    index, so a re-run survey sees the same images."""
    devices = bench.devices
    tt, st, cam = devices.turntable, devices.stewart, devices.camera
    bench.moved.update({tt.name, st.name})
    out: list[CalibrationView] = []
    for k, view in enumerate(plan.views):
        with run.move(f"rig survey: turntable {math.degrees(view.turntable_rad):+.0f} deg") as progress:
            tt.move_to(view.turntable_rad, progress)
        with run.move("rig survey: Stewart platform") as progress:
            st.move_to(view.stewart_pose, progress)
        if bench.simulated:
            bench.sim.world.reseed_camera([*seed, k])
        frame = cam.grab()
        if log_image is not None:
            log_image(frame, frame.t_s)
        detections = detector.detect(frame.image)
        out.append(CalibrationView(view, tuple(TagSighting(d.tag_id, np.asarray(d.corners_px)) for d in detections)))
        if on_view is not None:
            on_view(k, view, detections)
    return out


def views_to_json(views: Sequence[CalibrationView]) -> list[dict[str, Any]]:
    return [{"turntable_rad": v.motion.turntable_rad, "stewart_pose": list(v.motion.stewart_pose),
             "sightings": [{"id": s.tag_id, "corners_px": np.asarray(s.corners_px).tolist()} for s in v.sightings]}
            for v in views]


def views_from_json(items: Sequence[dict[str, Any]]) -> list[CalibrationView]:
    return [CalibrationView(ViewMotion(float(v["turntable_rad"]), tuple(float(x) for x in v["stewart_pose"])),
                            tuple(TagSighting(int(s["id"]), np.asarray(s["corners_px"], float)) for s in v["sightings"]))
            for v in items]
