"""`lab calibrate rig`: survey the turntable tags over many Stewart poses and turntable angles,
solve for the rig's calibration (camera mount, Stewart base, turntable axis, focal length and
principal point, the turntable tags as glued) and write the rig calibration file the rig's
`[calibration] file` key references (docs/calibration.md).

A procedure run through the step runner like `lab run borg`: one step homes the devices and
surveys at the first platform pose (the turntable sweeping every angle), one step per further
platform pose, a last step solves.  Every exit path stops the devices that moved and closes the
MCAP run with its stop record.  The run records the camera intrinsics, every image, every view's
commanded motion and the nominal camera pose it implies, every view's detections, and the result
(the calibration with its uncertainties, the conditioning problems, in simulation the errors
against the truth).

The survey sees only the turntable's rim tags: before assembly nothing else on the bench is at a
known place, and a module's tags (if any were placed) are not used because they are not where the
design puts them until SF-GraphSLAM has verified them.

A poorly conditioned calibration is refused: the solve step ends the run (`aborted`, the reason
naming each parameter), nothing is written, and `lab calibrate rig` prints one line per problem
and exits 2.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lab.core.errors import UserError
from lab.core.recorder import topics
from procedures.runner import RunContext, StepSpec, StopRun
from procedures.setup import Bench

_STREAM_CAMERA = 8300     # simulated camera noise per view: [seed, _STREAM_CAMERA, step, view]
IMAGE_FORMAT = "jpeg"     # logged images (detection runs on the lossless frame)


@dataclass
class RigCalibrationOutcome:
    """What the solve found; `written` only when the calibration was well conditioned."""

    solution: Any = None                       # estimation.rig_calibration_solve.RigSolution
    truth_error: dict[str, float] | None = None
    nees: dict[str, float] | None = None
    written: Path | None = None
    solve_s: float = 0.0
    problems: list[str] = field(default_factory=list)


class RigCalibrationProcedure:
    name = "calibrate_rig"

    def __init__(self, bench: Bench, out: Path, *, plan: Any = None, limits: Any = None,
                 angle_step_rad: float | None = None, borg_n: int | None = None) -> None:
        from drivers.stewart_kinematics import StewartKinematics
        from estimation.rig_model import RigGeometry
        from lab.core.structures.borg import build_borg
        from procedures import rig_survey

        rig = bench.rig
        missing = [k for k in ("turntable", "stewart", "camera") if getattr(rig, k) is None]
        if missing:
            raise UserError(f"rig {rig.source}: no [{'], ['.join(missing)}]: the rig calibration surveys the turntable "
                            f"tags with the camera on the Stewart platform")
        self.intrinsics = bench.devices.camera.intrinsics
        if self.intrinsics is None:
            raise UserError(f"rig {rig.source}: [camera] calibration: no camera calibration file; run "
                            f"`lab calibrate camera` first (docs/calibration.md)")
        self.bench = bench
        self.out = Path(out)
        self.limits = limits
        # the turntable tags' design poses come from the BORG model the rig is calibrated for (its
        # turntable grows with N; the bench stands the base at that BORG's station: open_bench)
        size = borg_n if borg_n is not None else rig.sim.borg_n if rig.sim is not None else 3
        self.model = build_borg(size)
        self.kinematics = StewartKinematics(rig.stewart.geometry)
        step = (rig_survey.survey_angle_step(self.model.turntable.radius_m) if angle_step_rad is None
                else float(angle_step_rad))
        self.survey_plan = plan if plan is not None else rig_survey.plan_rig_survey(
            lambda p: self.kinematics.inverse(np.asarray(p, float)).reachable, (rig.turntable.min_rad, rig.turntable.max_rad),
            poses=rig_survey.SURVEY_POSES, angle_step_rad=step, order="poses")
        from procedures.survey import CameraModel, SurveyPlanner

        i = self.intrinsics
        planner = SurveyPlanner(self.model, CameraModel(i.K, i.width_px, i.height_px, rig.stewart.world_T_base,
                                                        rig.stewart.geometry.home_m, rig.camera.platform_T_camera),
                                lambda p: self.kinematics.inverse(p).reachable, (rig.turntable.min_rad, rig.turntable.max_rad),
                                lift_limits_m=None if rig.lift is None else (rig.lift.min_m, rig.lift.max_m))
        if plan is None and rig.lift is not None:
            # a bigger turntable's rim is seen from lower down (rig_survey.survey_lift)
            lift = rig_survey.survey_lift(planner, self.survey_plan)
            if lift:
                self.survey_plan = rig_survey.plan_rig_survey(
                    lambda p: self.kinematics.inverse(np.asarray(p, float)).reachable,
                    (rig.turntable.min_rad, rig.turntable.max_rad), poses=rig_survey.SURVEY_POSES, angle_step_rad=step,
                    order="poses", lift_m=lift)
        if not self.survey_plan.views:
            raise UserError(f"rig {rig.source}: no survey pose is inside the Stewart workspace at any turntable angle "
                            f"within [turntable] min_deg..max_deg")
        blind = rig_survey.predicted_blind(planner, self.survey_plan, rig.stewart.station)
        if blind:
            raise UserError(f"rig {rig.source}: {blind}; nothing moved")
        self.geometry = RigGeometry.from_rig(rig, self.model.world_T_structure(0.0), self.intrinsics.K)
        self.turntable_tags = tuple(self.model.turntable.tag_ids)
        self.tags = {t: (self.model.tags[t].structure_T_tag, self.model.tags[t].size_m) for t in self.turntable_tags}
        # one step per run of views at one platform pose (or one turntable angle, whichever the plan
        # holds still)
        def key(v: Any) -> Any:
            return tuple(v.stewart_pose) if self.survey_plan.order == "poses" else v.turntable_rad
        self.groups: list[list[int]] = []
        for k, v in enumerate(self.survey_plan.views):
            if self.groups and key(self.survey_plan.views[self.groups[-1][-1]]) == key(v):
                self.groups[-1].append(k)
            else:
                self.groups.append([k])
        self.views: list[Any] = []                 # CalibrationView, in plan order
        self.sightings = 0
        self.homed = False
        self.result = RigCalibrationOutcome()

    # ---- plan and dry run --------------------------------------------------------------------
    def plan(self) -> list[StepSpec]:
        def name(i: int, g: list[int]) -> str:
            v = self.survey_plan.views[g[0]]
            if self.survey_plan.order == "poses":
                x = v.stewart_pose
                return (f"survey at platform pose {i + 1}/{len(self.groups)} (xyz {x[0]:+.2f} {x[1]:+.2f} {x[2]:+.2f} m, "
                        f"rpy {math.degrees(x[3]):+.0f} {math.degrees(x[4]):+.0f} {math.degrees(x[5]):+.0f} deg)")
            return f"survey at turntable {math.degrees(v.turntable_rad):+.0f} deg"
        steps = [StepSpec(i, name(i, g), {"views": len(g)}) for i, g in enumerate(self.groups)]
        steps.append(StepSpec(len(steps), "solve", {"views": len(self.survey_plan.views)}))
        return steps

    def dry_run_problems(self, steps: list[StepSpec]) -> list[str]:
        tt, st = self.bench.devices.turntable, self.bench.devices.stewart
        problems = []
        for v in self.survey_plan.views:
            for check, arg in ((tt.check_angle, v.turntable_rad), (st.check_pose, v.stewart_pose)):
                try:
                    check(arg)
                except Exception as exc:
                    problems.append(str(exc))
        return problems

    # ---- steps -------------------------------------------------------------------------------
    def execute(self, spec: StepSpec, run: RunContext) -> None:
        if spec.index < len(self.groups):
            if not self.homed:
                self._home(run)
            self._survey(spec, run, self.groups[spec.index])
        else:
            self._solve(run)

    def _home(self, run: RunContext) -> None:
        tt, st = self.bench.devices.turntable, self.bench.devices.stewart
        run.operator.confirm("Clear the turntable (only its rim tags may be in view) and the space around the "
                             "Stewart platform: the rig calibration survey is about to move both")
        self.bench.moved.update({tt.name, st.name})
        with run.move("turntable homing") as progress:
            tt.ensure_homed(progress)
        with run.move("Stewart platform home") as progress:
            st.home(progress)
        from procedures.setup import lift_to_zero

        lift_to_zero(self.bench, run)           # the survey's views are at the lift's zero
        i = self.intrinsics
        run.recorder.log_calibration(topics.CAMERA_CALIBRATION, i.K, i.dist, i.width_px, i.height_px, "camera")
        run.recorder.log_json("rig_survey/plan", {
            "views": [{"turntable_rad": v.turntable_rad, "stewart_pose": list(v.stewart_pose)} for v in self.survey_plan.views],
            "skipped": list(self.survey_plan.skipped), "lift_m": self.survey_plan.lift_m})
        for s in self.survey_plan.skipped:
            run.recorder.log_text("info", f"rig survey: {s}")
        self.homed = True

    def _survey(self, spec: StepSpec, run: RunContext, indices: list[int]) -> None:
        from estimation.fiducials import TagDetector
        from procedures.borg_measure import Measurement
        from procedures.rig_survey import RigSurveyPlan, capture

        rec = run.recorder
        # the detector reads through the camera file; only the turntable tags are ours here
        detector = TagDetector(self.intrinsics.K, self.intrinsics.dist, {t: s for t, (_, s) in self.tags.items()})
        last_t = [0.0]

        def log_image(frame: Any, t_s: float) -> None:
            last_t[0] = t_s
            rec.log_image(topics.CAMERA_IMAGE, frame.image, t_s, "camera", format=IMAGE_FORMAT)

        def on_view(k: int, view: Any, detections: list[Any]) -> None:
            t = last_t[0]
            nominal = self.model.world_T_structure(0.0).compose(self.geometry.predict_nominal(view))
            rec.log_transform("world", "structure", self.model.world_T_structure(view.turntable_rad), t)
            rec.log_transform("world", "camera", nominal, t)     # as the rig file has it, not calibrated
            rec.log_json("rig_survey/view", {"view": indices[k], "turntable_rad": view.turntable_rad,
                                             "stewart_pose": list(view.stewart_pose),
                                             "tags": [d.tag_id for d in detections]}, t)
            rec.log_record(topics.DETECTIONS, Measurement.detections_message(detections, t))

        sub = RigSurveyPlan(tuple(self.survey_plan.views[k] for k in indices))
        # the devices are where the previous step's last view left them (not after a resume: homed anew)
        previous = self.survey_plan.views[indices[0] - 1] if indices[0] > 0 and self.views else None
        views = capture(self.bench, run, sub, detector, seed=[self.bench.scenario.seed, _STREAM_CAMERA, spec.index],
                        log_image=log_image, on_view=on_view, previous=previous, overlap=True)
        del self.views[indices[0]:]       # a re-run step replaces what it took before
        self.views.extend(views)
        n = sum(len(v.sightings) for v in views)
        rec.log_metric("rig_survey/tags_per_view", n / max(1, len(views)))
        if n == 0:
            rec.log_text("warning", f"{spec.name}: no turntable tag seen in {len(views)} views")

    def _solve(self, run: RunContext) -> None:
        from estimation.rig_calibration_solve import Limits, solve_rig
        from procedures.rig_survey import against_truth, no_rim_seen

        rec = run.recorder
        self.sightings = sum(len(v.sightings) for v in self.views)
        why = no_rim_seen(self.views)
        if why:
            raise StopRun(why)
        t0 = time.perf_counter()
        sol = solve_rig(self.views, self.geometry, self.intrinsics.dist, self.tags, turntable_tags=self.turntable_tags,
                        limits=self.limits or Limits(), rig_name=self.bench.rig.name)
        r = self.result
        r.solve_s = time.perf_counter() - t0
        r.solution = sol
        r.problems = list(sol.problems)
        rec.log_metric("rig_calibration/solve_s", r.solve_s, "s")
        rec.log_metric("rig_calibration/rms_px", sol.calibration.rms_px, "px")
        if self.bench.simulated:
            r.truth_error, r.nees = against_truth(sol.calibration, self.bench.sim.world)
            for k, v in r.truth_error.items():
                rec.log_metric(f"rig_calibration/truth_error/{k}", v, "m" if k.endswith("_m") else
                               "rad" if k.endswith("_rad") else "")
        rec.log_json("rig_calibration/result", {"calibration": sol.calibration.to_json(), "problems": r.problems,
                                                "truth_error": r.truth_error, "nees": r.nees,
                                                "residuals_px": residual_stats(sol.residuals_px)})
        for p in r.problems:
            rec.log_text("error", f"rig calibration refused: {p}")
        if r.problems:
            raise StopRun(f"rig calibration poorly conditioned, not written: {'; '.join(r.problems)}")
        self.out.parent.mkdir(parents=True, exist_ok=True)
        sol.calibration.save(self.out)
        r.written = self.out
        rec.log_text("info", f"wrote {self.out}")

    # ---- checkpoints (a rig calibration is re-run, not resumed: it is a minute's work) ---------
    def checkpoint(self) -> dict[str, Any]:
        return {"views": len(self.views)}

    def restore(self, state: dict[str, Any], steps_done: list[StepSpec], run: RunContext) -> None:
        raise UserError("a rig calibration is not resumed: run `lab calibrate rig` again")

    # ---- the end -------------------------------------------------------------------------------
    def summary(self, result: str, reason: str) -> dict[str, Any]:
        return summary_json(self, result, reason)

    def stop_devices(self) -> list[str]:
        return self.bench.stop_moved()

    def close(self) -> None:
        self.bench.close()


def residual_stats(residuals_px: np.ndarray) -> dict[str, float]:
    r = np.asarray(residuals_px, float)
    if not r.size:
        return {"corners": 0, "rms": float("nan"), "p95": float("nan"), "max": float("nan")}
    return {"corners": int(r.size), "rms": float(np.sqrt(np.mean(r ** 2))), "p95": float(np.percentile(r, 95)),
            "max": float(r.max())}


def summary_json(proc: RigCalibrationProcedure, result: str, reason: str) -> dict[str, Any]:
    """summary.json, and the body of `lab calibrate rig --json`."""
    from estimation.rig_calibration_solve import describe

    r = proc.result
    out: dict[str, Any] = {"result": result, "reason": reason, "simulated": proc.bench.simulated,
                           "rig": proc.bench.rig.source, "views": len(proc.views),
                           "planned_views": len(proc.survey_plan.views), "sightings": sum(len(v.sightings) for v in proc.views),
                           "written": str(r.written) if r.written is not None else None, "problems": r.problems}
    if r.solution is not None:
        out["estimates"] = describe(r.solution.calibration)
        out["residuals_px"] = residual_stats(r.solution.residuals_px)
        out["solve_s"] = r.solve_s
    if r.truth_error is not None:
        out["truth_error"] = r.truth_error
        out["nees"] = r.nees
    return out
