"""The rig calibration survey: turntable angles x Stewart poses that see the turntable tags, moved
to and photographed through the drivers, then solved by `estimation.rig_calibration_solve`.

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
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from estimation.rig_calibration_solve import CalibrationView, TagSighting
from estimation.rig_model import ViewMotion
from lab.core.structures.borg import SPACING_M, turntable_radius_m
from procedures.moves import Move, move_together

_D = math.radians
# Relative to home: (x, y, z, roll, pitch, yaw); pitch 10 deg puts the near rim tags mid-image.
# Chosen by measurement (docs/calibration.md, "How the survey was chosen").  Every view is a
# resection from three 10 cm tags 1.7-2.0 m away, so the camera mount's offset trades against
# the focal length (a 0.1 % focal error moves the camera 1.7 mm along its axis) and against the
# mount's rotation (a 0.01 deg rotation looks like a 0.3 mm sideways shift at that distance); only
# views at other depths tell them apart.  So: the platform's whole reach along x (towards / away
# from the tags, -0.12 to +0.18 m: known changes of depth), its whole roll (+-25 deg) and pitch
# (4 to 22 deg) reach, some of them combined with x, and yaw 25 deg with a sideways shift that
# keeps two tags in view.  Larger yaw or roll, or roll / yaw combined with x, leave the workspace
# or lose the tags (the rim tags are usable within about 60 deg of incidence: three per view at
# most from the rig's camera position).  On the default sim rig (8 seeds, 96 views each) this set
# gives the mount 0.38 mm rms where the first plan gave about 1 mm and the set before this one
# 0.55 mm.  Ordered for the shortest leg travel (a move takes as long as its largest leg change).
SURVEY_POSES: tuple[tuple[float, ...], ...] = (
    (0.0, 0.0, 0.0, _D(25), _D(10), 0.0),
    (0.0, -0.12, 0.0, 0.0, _D(16), _D(-25)),
    (0.18, 0.0, 0.0, 0.0, _D(10), 0.0),
    (0.09, 0.0, 0.0, 0.0, _D(22), 0.0),
    (0.0, 0.0, 0.0, _D(-25), _D(10), 0.0),
    (0.0, 0.12, 0.0, 0.0, _D(16), _D(25)),
    (-0.12, 0.0, 0.0, 0.0, _D(10), 0.0),
    (-0.06, 0.0, -0.05, 0.0, _D(4), 0.0),
)
ANGLE_STEP_RAD = _D(30)
# the rim arc between two survey angles on the 3x3x3's turntable (1.21 m: 0.63 m), which the poses
# above were tuned on (survey_angle_step)
_TUNED_ARC_M = turntable_radius_m(3 * SPACING_M) * ANGLE_STEP_RAD
# finer steps, each a divisor of the rim tags' 30 deg spacing
_FINER_STEPS_DEG = (15.0, 10.0, 7.5, 6.0, 5.0)


def survey_angle_step(rim_radius_m: float) -> float:
    """The turntable step of a rig survey for a rim of this radius: 30 deg (the rim tags' spacing) up
    to the 3x3x3's rim; on a bigger rim the largest divisor of 30 deg whose arc is no longer than
    the 3x3x3's.  A step of one tag spacing turns the next tag into the place the last one was: at
    one platform pose every view sees the rim in the same place, and where a view holds only one
    rim tag (a 5x5x5 from its near station, an 8x8x8 from its far one) the base's rotation is then
    hardly seen (1 sigma 0.1 deg, 1.9 mm off the truth at N = 5; 15 deg: 0.008 deg, 0.20 mm)."""
    if rim_radius_m * ANGLE_STEP_RAD <= _TUNED_ARC_M * (1 + 1e-9):
        return ANGLE_STEP_RAD
    for deg in _FINER_STEPS_DEG:
        if rim_radius_m * _D(deg) <= _TUNED_ARC_M * (1 + 1e-9):
            return _D(deg)
    return _D(_FINER_STEPS_DEG[-1])


@dataclass(frozen=True)
class RigSurveyPlan:
    views: tuple[ViewMotion, ...]
    skipped: tuple[str, ...] = ()      # candidate poses the workspace refused, said once
    order: str = "angles"              # "angles": every pose at one angle, then the next angle; "poses": the converse
    lift_m: float = 0.0                # every view at this lift height (survey_lift)


ORDERS = ("angles", "poses")


def plan_rig_survey(reachable: Callable[[Sequence[float]], bool], turntable_limits_rad: tuple[float, float],
                    poses: Sequence[Sequence[float]] = SURVEY_POSES, angle_step_rad: float = ANGLE_STEP_RAD,
                    order: str = "angles", lift_m: float = 0.0) -> RigSurveyPlan:
    """Every reachable survey pose at every turntable angle a full turn in `angle_step_rad` steps,
    within the limits.  `order="angles"`: all poses at one angle, then the next angle, the poses
    alternating direction (shorter moves); `order="poses"`: the turntable sweeps every angle at
    one pose, alternating direction, then the platform moves on.  The views are the same; the
    time is not: on the sim rig a 30 deg turn takes 0.3 s and the platform's average survey move
    0.45 s, so sweeping the turntable (88 turns, 7 platform moves) takes ~30 s where the other
    order (11 turns, 84 platform moves) takes ~41 s."""
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    lo, hi = turntable_limits_rad
    start = max(lo, -math.pi / 2)
    angles = [float(a) for a in np.arange(start, start + 2 * math.pi - 1e-9, angle_step_rad) if lo <= a <= hi]
    ok = [tuple(float(v) for v in p) for p in poses if reachable(p)]
    skipped = tuple(f"platform pose {np.round(p, 3).tolist()} is outside the workspace" for p in poses
                    if tuple(float(v) for v in p) not in ok)
    views = []
    if order == "angles":
        for i, a in enumerate(angles):
            for p in (ok if i % 2 == 0 else ok[::-1]):
                views.append(ViewMotion(a, p, lift_m))
    else:
        for i, p in enumerate(ok):
            for a in (angles if i % 2 == 0 else angles[::-1]):
                views.append(ViewMotion(a, p, lift_m))
    return RigSurveyPlan(tuple(views), skipped, order, lift_m)


def no_rim_seen(views: Sequence[CalibrationView]) -> str | None:
    """Why a survey's views cannot calibrate anything (no turntable tag seen in any), or None."""
    if any(v.sightings for v in views):
        return None
    return (f"no turntable tag was seen in {len(views)} views: is the camera looking at the turntable's rim "
            f"(rig file [camera] platform_T_camera, [stewart] world_T_base)?")


def predicted_blind(planner: Any, plan: RigSurveyPlan, station: str) -> str | None:
    """Why the survey planner expects no view of `plan` to see a turntable tag (the base stands too
    close to the rim, or the camera looks away from it), or None: said before anything moves,
    where `no_rim_seen` can only say it after the whole survey."""
    from procedures.survey import View

    rim = list(planner.model.turntable.tag_ids)
    if any(planner.visible(View(v.turntable_rad, tuple(v.stewart_pose), v.lift_m), rim) for v in plan.views):
        return None
    base = planner.camera.world_T_stewart_base.translation()
    standoff = math.hypot(base[0], base[1]) - planner.model.turntable.radius_m
    return (f"the rig survey's {len(plan.views)} views are predicted to see no turntable tag from station "
            f"{station!r}: its base stands {standoff:.2f} m from the rim of borg:{planner.model.n}'s turntable "
            f"(rig file [stewart] rim_standoff_m and [[stewart.stations]], docs/hardware.md \"Stations\")")


def survey_lift(planner: Any, plan: RigSurveyPlan) -> float:
    """The lift height for the rig survey: the poses above were chosen for the rim tags of the 3x3x3
    BORG's turntable seen from the lift's zero (two or three tags per view, 25 deg below the
    camera).  A bigger turntable's rim comes closer and further below the camera: from a lower
    height more views see two or more rim tags.  The height (on the planner's grid over the travel,
    `SurveyPlanner.lift_grid`) where most views see two or more, the nearest to the base on a tie;
    if none does anywhere, the one where most rim tags are seen at all.  0 without a lift.
    `planner`: a procedures.survey SurveyPlanner of the run's structure (it predicts visibility)."""
    if planner.lift_limits_m is None:
        return 0.0
    from procedures.survey import View

    heights, base = planner.lift_grid
    grid = sorted(heights, key=lambda h: (abs(h - base), h))
    rim = list(planner.model.turntable.tag_ids)

    def score(h: float) -> tuple[int, int]:
        seen = [len(planner.visible(View(v.turntable_rad, tuple(v.stewart_pose), h), rim)) for v in plan.views]
        return sum(n >= 2 for n in seen), sum(seen)
    scores = {h: score(h) for h in grid}
    best = max(s[0] for s in scores.values())
    if best > 0:
        return next(h for h in grid if scores[h][0] == best)
    most = max(s[1] for s in scores.values())
    return next(h for h in grid if scores[h][1] == most)


def capture(bench: Any, run: Any, plan: RigSurveyPlan, detector: Any, *, seed: Sequence[int] = (),
            log_image: Callable[[Any, float], None] | None = None,
            on_view: Callable[[int, ViewMotion, list[Any]], None] | None = None,
            previous: ViewMotion | None = None, overlap: bool = False) -> list[CalibrationView]:
    """Move to each planned view, grab, detect; returns what the solver needs.  In simulation the
    camera's noise (and the devices' repeatability) is reseeded per view from `seed` + the view
    index, so a re-run survey sees the same images.  `previous`: the view this survey continues
    from (the devices are there), or None to move to the first view whatever.  `overlap`: detect
    and call `log_image` / `on_view` in one worker thread while the devices move on to the next
    view (in view order; the callbacks must be thread-safe, as the run recorder is): 1-3 s of a
    96-view survey on a busy 2-core machine."""
    devices = bench.devices
    tt, st, cam = devices.turntable, devices.stewart, devices.camera
    bench.moved.update({tt.name, st.name})
    lift = getattr(devices, "lift", None)
    if lift is None and any(v.lift_m for v in plan.views):
        raise ValueError("the rig survey plan has views off the lift's zero and the rig has no lift")

    def process(k: int, view: ViewMotion, frame: Any) -> CalibrationView:
        if log_image is not None:
            log_image(frame, frame.t_s)
        detections = detector.detect(frame.image)
        if on_view is not None:
            on_view(k, view, detections)
        return CalibrationView(view, tuple(TagSighting(d.tag_id, np.asarray(d.corners_px)) for d in detections))

    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="rig-survey") if overlap else None
    pending: list[Future[CalibrationView]] = []
    out: list[CalibrationView] = []
    last = previous
    try:
        for k, view in enumerate(plan.views):
            # a device already where the view wants it is not commanded again: a move of zero still
            # costs its command, settling and polls (about 4 s of a 96-view survey at speed-up 10)
            # the devices this view moves move at once (procedures/moves.py), as a run's views do
            moves = []
            if lift is not None and (last is None or view.lift_m != last.lift_m):
                # asked first after a resume: a lift already there is not commanded (a move of zero
                # is still a move, and a lift that never moved is exactly where the rig file says)
                if last is not None or abs(lift.position() - view.lift_m) > 1e-5:
                    bench.moved.add(lift.name)
                    moves.append(Move(lift, f"rig survey: lift to {view.lift_m * 1000:+.0f} mm",
                                      lambda progress, h=view.lift_m: lift.move_to(h, progress)))
            if last is None or view.turntable_rad != last.turntable_rad:
                moves.append(Move(tt, f"rig survey: turntable {math.degrees(view.turntable_rad):+.0f} deg",
                                  lambda progress, a=view.turntable_rad: tt.move_to(a, progress)))
            if last is None or tuple(view.stewart_pose) != tuple(last.stewart_pose):
                moves.append(Move(st, "rig survey: Stewart platform",
                                  lambda progress, p=view.stewart_pose: st.move_to(p, progress)))
            move_together(run, moves)
            last = view
            if bench.simulated:
                bench.sim.world.reseed_camera([*seed, k])
            t0 = time.monotonic()
            frame = cam.grab()
            recorder = getattr(run, "recorder", None)
            if recorder is not None:
                recorder.log_metric("camera/grab_s", time.monotonic() - t0, "s")
            if pool is not None:
                pending.append(pool.submit(process, k, view, frame))
            else:
                out.append(process(k, view, frame))
        out.extend(f.result() for f in pending)      # a worker's exception is raised here
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    return out


def views_to_json(views: Sequence[CalibrationView]) -> list[dict[str, Any]]:
    return [{"turntable_rad": v.motion.turntable_rad, "stewart_pose": list(v.motion.stewart_pose),
             "lift_m": v.motion.lift_m,
             "sightings": [{"id": s.tag_id, "corners_px": np.asarray(s.corners_px).tolist()} for s in v.sightings]}
            for v in views]


def views_from_json(items: Sequence[dict[str, Any]]) -> list[CalibrationView]:
    return [CalibrationView(ViewMotion(float(v["turntable_rad"]), tuple(float(x) for x in v["stewart_pose"]),
                                       float(v.get("lift_m", 0.0))),
                            tuple(TagSighting(int(s["id"]), np.asarray(s["corners_px"], float)) for s in v["sightings"]))
            for v in items]


def against_truth(calibration: Any, world: Any) -> tuple[dict[str, float], dict[str, float]]:
    """(errors, NEES) of a calibration against the simulated world's true rig: the mount and the
    base over 6 dof, the axis over its tilt and where it crosses the plate (yaw and height are the
    gauge).  Simulation only: the estimator never sees this."""
    from estimation.rig_calibration_solve import nees_report, truth_error
    from estimation.rig_model import nees

    tr = world.true_rig
    errors = truth_error(calibration, world_T_base=tr.world_T_base, platform_T_camera=tr.platform_T_camera,
                         world_T_axis=tr.world_T_axis, K=world.camera.K)
    scores = nees_report(calibration, world_T_base=tr.world_T_base, platform_T_camera=tr.platform_T_camera)
    scores["world_T_axis"] = nees(calibration.world_T_axis, tr.world_T_axis, calibration.covariance["world_T_axis"],
                                  dims=(0, 1, 3, 4))
    return errors, scores


def graph_against_truth(slam: Any, world: Any) -> dict[str, dict[str, Any]]:
    """(Simulation only: the estimator never sees this.)  The run graph's rig variables as they
    stand, against the simulated world's true rig: each one's error and NEES.
    - The mount and the base: over their 6 dof (expect ~6).
    - The axis: its tilt and where it crosses the plate (4 dof; its yaw and height are gauge).
    - The lift: its tilt (2 dof).
    - The intrinsics: fx, fy, cx, cy (4 dof).
    The survey's NEES (`against_truth`) says whether the survey's covariance covers its error; this
    says whether the graph still does after every view has refined the rig.  The marginals are
    scaled as the graph scales a tag's (by the corner noise's variance factor where the corners
    proved noisier than assumed).  A variable whose marginal fails is left out."""
    from estimation.rig_model import AXIS, BASE, INTRINSICS, LIFT, MOUNT, nees, tangent_error

    noise = slam.corner_noise()
    scale = noise.covariance_scale if noise is not None else 1.0
    tr = world.true_rig
    out: dict[str, dict[str, Any]] = {}
    poses = (("mount", MOUNT, tr.platform_T_camera, range(6)), ("base", BASE, tr.world_T_base, range(6)),
             ("axis", AXIS, tr.world_T_axis, (0, 1, 3, 4)), ("lift", LIFT, tr.world_T_lift, (0, 1)))
    estimate = slam.estimate
    for name, key, truth, dims in poses:
        if truth is None or not estimate.exists(key):
            continue
        try:
            cov = slam.isam.marginalCovariance(key) * scale
        except (RuntimeError, IndexError):
            continue
        e = tangent_error(estimate.atPose3(key), truth)
        out[name] = {"error_rad": [float(x) for x in e[:3]], "error_m": [float(x) for x in e[3:]],
                     "nees": nees(estimate.atPose3(key), truth, cov, dims), "dof": len(list(dims))}
    if estimate.exists(INTRINSICS):
        try:
            cov = slam.isam.marginalCovariance(INTRINSICS) * scale
        except (RuntimeError, IndexError):
            cov = None
        if cov is not None:
            K = world.camera.K
            idx = [0, 1, 3, 4]                      # fx, fy, cx, cy of (fx, fy, skew, cx, cy)
            e = np.asarray(estimate.atCal3_S2(INTRINSICS).vector(), float)[idx] - np.array(
                [K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
            c = np.asarray(cov, float)[np.ix_(idx, idx)]
            out["intrinsics"] = {"error_px": [float(x) for x in e], "sigma_px": [float(x) for x in np.sqrt(np.diag(c))],
                                 "nees": float(e @ np.linalg.solve(c, e)), "dof": 4}
    return out
