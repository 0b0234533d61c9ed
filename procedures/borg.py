"""BORG assemble-measure-verify (`lab run borg`): one step per module, in assembly order.

Each step: the operator places (or deploys) the module — in simulation the world does, with the
scenario's errors; the survey planned from the design moves the turntable and the Stewart platform
to views that see the new module's tags with their related tags; the camera grabs; the fiducial
detector reads the tags; SF-GraphSLAM takes the views incrementally (iSAM2); tags that don't fit the
design are eliminated; the module gets its verdict.  A flag stops the run (default), is noted and
passed (`--on-flag continue`), or sends the operator to re-deploy and re-measure (`retry`).

Everything is planned before the first move, so `--dry-run` checks every turntable angle and
Stewart pose of the whole procedure against the limits and the workspace.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from lab.errors import UserError
from lab.geometry import pose_error
from lab.recorder import messages as m
from lab.recorder import topics
from lab.structures.borg import BorgModel, build_borg
from procedures.runner import RunContext, StepSpec, StopRun
from procedures.setup import Bench
from procedures.survey import CameraModel, SurveyPlan, SurveyPlanner, View

ON_FLAG = ("stop", "continue", "retry")
MAX_RETRIES = 2
_STREAM_CAMERA = 8200    # simulated camera noise per step: [seed, _STREAM_CAMERA, step, attempt]
IMAGE_FORMAT = "jpeg"    # logged images (detection runs on the lossless frame)


@dataclass
class ModuleResult:
    name: str
    verdict: str = "unverified"
    reason: str = ""
    position_error_m: float | None = None     # estimate vs simulated truth (hardware: None)
    rotation_error_rad: float | None = None
    deviation_m: float | None = None          # estimate vs design
    deviation_rad: float | None = None
    sigma_position_m: float | None = None     # estimated 1-sigma position uncertainty
    tags_seen: list[int] = field(default_factory=list)
    attempts: int = 1

    def to_json(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items()}


class BorgProcedure:
    name = "borg"

    def __init__(self, bench: Bench, on_flag: str = "stop", n: int | None = None, max_modules: int | None = None,
                 estimator_config: Any = None, calibration: str | None = None, rig_survey: bool | None = None,
                 observation: str | None = None, uncalibrated: bool = False) -> None:
        """`calibration`: a rig calibration file (default: the rig's [calibration] file).
        `rig_survey`: begin with a rig calibration survey (default: when there is no calibration)."""
        if on_flag not in ON_FLAG:
            raise UserError(f"--on-flag must be one of {', '.join(ON_FLAG)}, got {on_flag!r}")
        rig = bench.rig
        missing = [k for k in ("turntable", "stewart", "camera") if getattr(rig, k) is None]
        if missing:
            raise UserError(f"rig {rig.name!r} has no {', '.join(missing)}: the BORG procedure needs a turntable, "
                            f"a Stewart platform and a camera")
        self.bench = bench
        self.on_flag = on_flag
        size = n if n is not None else (rig.sim.borg_n if rig.sim is not None else 3)
        if bench.simulated and bench.sim.world.borg is not None and bench.sim.world.borg.model.n != size:
            raise UserError(f"--n {size} differs from the simulated structure (borg_n = {bench.sim.world.borg.model.n})")
        self.model: BorgModel = build_borg(size)
        modules = list(self.model.modules)
        if max_modules is not None:
            if not 1 <= max_modules <= len(modules):
                raise UserError(f"--modules must be in 1..{len(modules)}, got {max_modules}")
            modules = modules[:max_modules]
        self.modules = modules
        self.intrinsics = bench.devices.camera.intrinsics
        if self.intrinsics is None:
            raise UserError(f"camera {rig.camera.name}: no calibration file; run `lab calibrate camera` first")
        from drivers.stewart_kinematics import StewartKinematics

        self.kinematics = StewartKinematics(rig.stewart.geometry)
        cam = CameraModel(self.intrinsics.K, self.intrinsics.width_px, self.intrinsics.height_px,
                          rig.stewart.world_T_base, rig.stewart.geometry.home_m, rig.camera.platform_T_camera)
        self.camera_model = cam
        self.planner = SurveyPlanner(self.model, cam, lambda p: self.kinematics.inverse(p).reachable,
                                     (rig.turntable.min_rad, rig.turntable.max_rad))
        placed: list[str] = []
        self.surveys: dict[str, SurveyPlan] = {}
        for mod in modules:
            placed.append(mod.name)
            self.surveys[mod.name] = self.planner.plan(mod.name, placed)
        from estimation.rig_model import RigGeometry
        from procedures.borg_measure import Measurement

        self.rig_geometry = RigGeometry.from_rig(rig, self.model.world_T_structure(0.0), self.intrinsics.K)
        self.rig_calibration = None
        cal_file = calibration or rig.calibration.file
        if cal_file is not None:
            from lab.rig_calibration import load_rig_calibration

            self.rig_calibration = load_rig_calibration(cal_file)
        self.rig_survey = (self.rig_calibration is None) if rig_survey is None else bool(rig_survey)
        self.uncalibrated = uncalibrated
        if uncalibrated:
            # the behaviour before rig calibration, kept for comparison: every camera pose held to
            # the rig file's kinematics at 1 mm / 0.05 deg, no calibration variables, no survey
            self.rig_survey = False
            self.rig_calibration = None
        self.rig_survey_result: dict[str, Any] | None = None
        self.rig_survey_views: list[dict[str, Any]] | None = None   # the survey's inputs, for resume
        self._row_header_shown = False
        self._rejected_reported: set[int] = set()
        estimator_config = dict(estimator_config or {})
        if observation is not None:
            estimator_config["observation"] = observation
        self.measure = Measurement(self.model, self.intrinsics, estimator_config, rig=self._rig_model(),
                                   calibration=self.rig_calibration)
        self.results: dict[str, ModuleResult] = {}
        self.views_done: list[dict[str, Any]] = []     # every view taken, for checkpoints / replay
        self.homed = False

    # ---- plan and dry run --------------------------------------------------------------------
    def plan(self) -> list[StepSpec]:
        first = [StepSpec(0, "rig calibration", {"rig_survey": len(self.rig_survey_plan.views)})] if self.rig_survey else []
        return first + [StepSpec(k + len(first), f"module {mod.name}",
                                 {"module": mod.name, "kind": mod.kind,
                                  "views": [v.label for v in self.surveys[mod.name].views]})
                        for k, mod in enumerate(self.modules)]

    @cached_property
    def rig_survey_plan(self):
        from procedures.rig_survey import plan_rig_survey

        rig = self.bench.rig
        # a turntable sweep per platform pose: the shortest survey for the same views
        return plan_rig_survey(lambda p: self.kinematics.inverse(np.asarray(p, float)).reachable,
                               (rig.turntable.min_rad, rig.turntable.max_rad), order="poses")

    def dry_run_problems(self, steps: list[StepSpec]) -> list[str]:
        tt, st = self.bench.devices.turntable, self.bench.devices.stewart
        problems = []
        for spec in steps:
            if "rig_survey" in spec.params:
                for v in self.rig_survey_plan.views:
                    for check, arg in ((tt.check_angle, v.turntable_rad), (st.check_pose, v.stewart_pose)):
                        try:
                            check(arg)
                        except Exception as exc:
                            problems.append(f"{spec.name}: {exc}")
                continue
            for v in self.surveys[spec.params["module"]].views:
                try:
                    tt.check_angle(v.turntable_rad)
                except Exception as exc:
                    problems.append(f"{spec.name}: {exc}")
                try:
                    st.check_pose(v.stewart_pose)
                except Exception as exc:
                    problems.append(f"{spec.name}: {exc}")
            if self.surveys[spec.params["module"]].unobservable:
                problems.append(f"{spec.name}: no planned view sees tags {self.surveys[spec.params['module']].unobservable}")
        return problems

    # ---- one step ------------------------------------------------------------------------------
    def execute(self, spec: StepSpec, run: RunContext) -> None:
        if not self.homed:
            self._home(run)
        if "rig_survey" in spec.params:
            self._calibrate_rig(spec, run)
            return
        module = self.model.module_by_name[spec.params["module"]]
        run.operator.confirm(f"{'Deploy' if module.kind == 'deployable' else 'Place'} module {module.name} "
                             f"({module.kind.replace('_', ' ')}, tags {', '.join(map(str, module.tags))})")
        if self.bench.simulated:
            self.bench.sim.world.borg.place(module.name)
        attempt = 0
        while True:
            attempt += 1
            result = self._survey_and_verify(spec, run, module.name, attempt)
            result.attempts = attempt
            self.results[module.name] = result
            self._log_verdict(run, spec.index, result)
            if result.verdict != "flagged" or self.on_flag == "continue":
                return
            if self.on_flag == "stop":
                raise StopRun(f"module {module.name} flagged: {result.reason}")
            if attempt > MAX_RETRIES:
                raise StopRun(f"module {module.name} still flagged after {MAX_RETRIES} re-deploys: {result.reason}")
            answer = run.operator.ask(f"Module {module.name} flagged ({result.reason}). Re-deploy it and measure again?",
                                      ("retry", "continue", "stop"), "retry")
            if answer == "stop":
                raise StopRun(f"module {module.name} flagged: {result.reason} (operator stopped)")
            if answer == "continue":
                return
            if self.bench.simulated:
                self._redeploy_in_world(module.name)
            self.measure.redeploy(module.name)

    def _home(self, run: RunContext) -> None:
        tt, st = self.bench.devices.turntable, self.bench.devices.stewart
        self.bench.moved.update({tt.name, st.name})
        with run.move("turntable homing") as progress:
            tt.ensure_homed(progress)
        with run.move("Stewart platform home") as progress:
            st.home(progress)
        K, dist = self.intrinsics.K, self.intrinsics.dist
        run.recorder.log_calibration(topics.CAMERA_CALIBRATION, K, dist, self.intrinsics.width_px,
                                     self.intrinsics.height_px, "camera")
        self.homed = True

    def _calibrate_rig(self, spec: StepSpec, run: RunContext) -> None:
        """No rig calibration to start from: survey the turntable tags first (the structure is not
        there yet) and solve for the axis, base, mount and intrinsics, as `lab calibrate rig` does.
        The solution, with its covariance, is the prior the run refines; a quantity the survey could
        not pin down keeps a wide covariance, which is honest, and is reported as a warning."""
        from procedures.borg_measure import Measurement
        from procedures.console import console_of
        from procedures.rig_survey import capture, views_to_json

        rec = run.recorder
        rec.log_text("info", "no rig calibration: surveying the turntable tags to calibrate the rig")
        views = capture(self.bench, run, self.rig_survey_plan, self.measure.detector,
                        seed=[self.bench.scenario.seed, _STREAM_CAMERA, spec.index],
                        log_image=lambda frame, t: rec.log_image(topics.CAMERA_IMAGE, frame.image, t, "camera",
                                                                 format=IMAGE_FORMAT), overlap=True)
        self.rig_survey_views = views_to_json(views)
        t0 = time.perf_counter()
        sol = self._solve_rig_survey(views)
        rec.log_metric("rig_calibration/solve_s", time.perf_counter() - t0, "s")
        for problem in sol.problems:
            rec.log_text("warning", f"rig calibration: {problem}")
        self.rig_survey_result = self._rig_survey_report(sol)
        rec.log_text("info", "rig calibration: " + json.dumps(self.rig_survey_result))
        console_of(run).line(_rig_survey_line(sol))
        self.measure = Measurement(self.model, self.intrinsics, self.measure.config, rig=self.rig_geometry,
                                   calibration=self.rig_calibration)

    def _solve_rig_survey(self, views: Any) -> Any:
        from estimation.rig_calibration import solve_rig

        tags = {t: (s.structure_T_tag, s.size_m) for t, s in self.model.tags.items() if s.module == "turntable"}
        sol = solve_rig(views, self.rig_geometry, self.intrinsics.dist, tags,
                        turntable_tags=self.model.turntable.tag_ids, rig_name=self.bench.rig.name)
        self.rig_calibration = sol.calibration
        return sol

    def _rig_model(self):
        return None if self.uncalibrated else self.rig_geometry

    def _rig_survey_report(self, sol: Any) -> dict[str, Any]:
        from estimation.rig_calibration import describe
        from procedures.rig_survey import against_truth

        out: dict[str, Any] = {"views": sol.calibration.views, "rms_px": sol.calibration.rms_px,
                               "problems": list(sol.problems), "estimate": describe(sol.calibration)}
        if self.bench.simulated:
            out["truth_error"], out["nees"] = against_truth(sol.calibration, self.bench.sim.world)
        return out

    def _redeploy_in_world(self, name: str) -> None:
        """The operator re-deploys: in simulation the module comes out as designed this time."""
        borg = self.bench.sim.world.borg
        mod = self.model.module_by_name[name]
        if mod.kind == "deployable":
            borg.set_deployed_height(name, None)
        borg.set_module_offset(name)

    def _survey_and_verify(self, spec: StepSpec, run: RunContext, name: str, attempt: int) -> ModuleResult:
        rec = run.recorder
        survey = self.surveys[name]
        views = []
        for k, view in enumerate(survey.views):
            frame, world_T_camera = self._capture(run, view, spec.index, attempt, k)
            t = frame.t_s
            rec.log_image(topics.CAMERA_IMAGE, frame.image, t, "camera", format=IMAGE_FORMAT)
            structure_T_camera = self.model.world_T_structure(view.turntable_rad).inverse().compose(world_T_camera)
            rec.log_transform("world", "structure", self.model.world_T_structure(view.turntable_rad), t)
            rec.log_transform("world", "camera", world_T_camera, t)
            detections = self.measure.detect(frame.image, structure_T_camera)
            rec.log_record(topics.DETECTIONS, self.measure.detections_message(detections, t))
            record = {"module": name, "step": spec.index, "attempt": attempt, "view": k,
                      "turntable_rad": view.turntable_rad, "stewart_pose": list(view.stewart_pose),
                      "structure_T_camera": structure_T_camera.matrix().tolist(),
                      "detections": self.measure.detections_to_json(detections)}
            views.append(record)
        self.views_done.extend(views)
        t0 = time.perf_counter()
        self.measure.add_step(name, views)
        solve_s = time.perf_counter() - t0
        rec.log_metric("slam/update_s", solve_s, "s")
        result = self.measure.verdict(name)
        self._log_estimates(run)
        for pose, cov in self.measure.camera_estimates():
            rec.log_pose(topics.estimate_topic("camera"), pose, "structure", covariance6x6=cov)
        if self.bench.simulated:
            self._truth_errors(result)
        return result

    def _capture(self, run: RunContext, view: View, step: int, attempt: int, k: int):
        devices = self.bench.devices
        tt, st, cam = devices.turntable, devices.stewart, devices.camera
        with run.move(f"turntable to {np.degrees(view.turntable_rad):+.0f} deg") as progress:
            tt.move_to(view.turntable_rad, progress)
        with run.move("Stewart platform") as progress:
            st.move_to(view.stewart_pose, progress)
        if self.bench.simulated:
            # the simulated camera's noise for this view depends only on (seed, step, attempt, view)
            self.bench.sim.world.reseed_camera([self.bench.scenario.seed, _STREAM_CAMERA, step, attempt, k])
        frame = cam.grab()
        world_T_camera = self.camera_model.world_T_camera(view)
        return frame, world_T_camera

    def _log_estimates(self, run: RunContext) -> None:
        estimates = self.measure.tag_estimates()
        if estimates:
            poses = {tid: p for tid, (p, _) in estimates.items()}
            covs = {tid: c for tid, (_, c) in estimates.items()}
            run.recorder.log_tag_estimates(poses, "structure", covariances=covs)

    def _log_verdict(self, run: RunContext, index: int, r: ModuleResult) -> None:
        run.recorder.log_record(topics.VERDICTS, m.module_verdict(
            r.name, r.verdict, r.reason,
            position_error_m=r.position_error_m if r.position_error_m is not None else float("nan"),
            rotation_error_rad=r.rotation_error_rad if r.rotation_error_rad is not None else float("nan"),
            step_index=index, tag_ids=list(self.model.module_by_name[r.name].tags),
            rejected_tag_ids=sorted(self.measure.rejected_tags)))
        run.recorder.log_text("info", f"module {r.name}: {r.verdict}{' - ' + r.reason if r.reason else ''}")
        # the console: the verdict row as soon as it is decided (the header before the first),
        # then what changed with it: tags rejected in this step, a re-measure
        from procedures.console import console_of

        console = console_of(run)
        if not self._row_header_shown:
            console.line(TABLE_HEADER)
            self._row_header_shown = True
        if r.attempts > 1:
            console.warn(f"module {r.name} re-deployed by the operator; measured again (attempt {r.attempts})")
        console.line(format_row(self._row(r)))
        new = sorted(self.measure.rejected_tags - self._rejected_reported)
        if new:
            console.warn(f"tag{'s' if len(new) > 1 else ''} {', '.join(map(str, new))} rejected as displaced "
                         f"(does not fit the design while the rest of the structure does)")
        self._rejected_reported = set(self.measure.rejected_tags)

    def _row(self, r: ModuleResult) -> dict[str, Any]:
        """A module's line of the summary (and of the table)."""
        tol = self.measure.tolerances.of(self.model.module_by_name[r.name].kind)
        return {"name": r.name, "verdict": r.verdict, "reason": r.reason,
                "position_error_m": r.position_error_m, "rotation_error_rad": r.rotation_error_rad,
                "deviation_m": r.deviation_m, "deviation_rad": r.deviation_rad,
                "sigma_position_m": r.sigma_position_m, "tolerance_m": tol.position_m,
                "tolerance_rad": tol.rotation_rad, "tags_seen": r.tags_seen, "attempts": r.attempts}

    def _truth_errors(self, r: ModuleResult) -> None:
        est = self.measure.module_estimate(r.name)
        if est is None:
            return
        truth = self.bench.sim.world.borg.structure_T_module(r.name)
        r.position_error_m, r.rotation_error_rad = pose_error(est, truth)

    # ---- checkpoints -------------------------------------------------------------------------
    def checkpoint(self) -> dict[str, Any]:
        return {"views": self.views_done, "results": {k: v.to_json() for k, v in self.results.items()},
                "placed": list(self.bench.sim.world.borg.placed) if self.bench.simulated else [],
                "homed": self.homed,
                # the survey's inputs, not its result: a resumed run solves them again and gets the
                # same calibration bit for bit (a rounded copy would move every later estimate)
                "rig_survey_views": self.rig_survey_views,
                "rig_survey": self.rig_survey_result}

    def restore(self, state: dict[str, Any], steps_done: list[StepSpec], run: RunContext) -> None:
        """Replay the completed steps' views into a fresh estimator, step by step as they happened,
        so the estimate (and every later verdict) is the one an uninterrupted run would have."""
        from procedures.borg_measure import Measurement
        from procedures.rig_survey import views_from_json

        if state.get("rig_survey_views") is not None:
            self.rig_survey_views = state["rig_survey_views"]
            self._solve_rig_survey(views_from_json(self.rig_survey_views))
            self.rig_survey_result = state.get("rig_survey")
        self.measure = Measurement(self.model, self.intrinsics, self.measure.config, rig=self._rig_model(),
                                   calibration=self.rig_calibration)
        self.views_done = list(state.get("views", []))
        by_step: dict[tuple[int, int], list[dict]] = {}
        for v in self.views_done:
            by_step.setdefault((v["step"], v["attempt"]), []).append(v)
        for (step, attempt), views in sorted(by_step.items()):
            if attempt > 1:
                self.measure.redeploy(views[0]["module"])
            self.measure.add_step(views[0]["module"], views, replay=True)
        self.results = {k: ModuleResult(**v) for k, v in state.get("results", {}).items()}
        if self.bench.simulated:
            for name in state.get("placed", []):
                self.bench.sim.world.borg.place(name)
            for name, r in self.results.items():
                if r.attempts > 1 and r.verdict != "flagged":
                    self._redeploy_in_world(name)
        self.homed = False   # a new session: home again before moving

    # ---- the end -------------------------------------------------------------------------------
    def summary(self, result: str, reason: str) -> dict[str, Any]:
        modules = []
        for mod in self.modules:
            r = self.results.get(mod.name)
            if r is None:
                continue
            modules.append(self._row(r))
        return {"result": result, "reason": reason, "structure": f"borg:{self.model.n}", "on_flag": self.on_flag,
                "calibration": ("none (rig file trusted)" if self.uncalibrated else
                                "survey" if self.rig_survey else "file" if self.rig_calibration is not None
                                else "nominal priors"),
                "observation": self.measure.slam.config.observation,
                "simulated": self.bench.simulated, "modules": modules,
                "rejected_tags": sorted(self.measure.rejected_tags), "steps": len(modules),
                "views": len(self.views_done), "rig_survey": self.rig_survey_result,
                "rig_calibration_file": str(self.bench.rig.calibration.file) if self.bench.rig.calibration.file else None}

    def stop_devices(self) -> list[str]:
        return self.bench.stop_moved()

    def close(self) -> None:
        self.bench.close()


TABLE_HEADER = (f"{'module':<7} {'verdict':<10} {'dev mm':>7} {'dev deg':>7} {'tol mm/deg':>10} {'1σ mm':>6} "
                f"{'err mm':>7} {'err deg':>7}  reason")
TABLE_LEGEND = ("dev: measured distance from the design, which the verdict judges (flagged beyond tol + 2σ, or not "
                "fully deployed); tol: tolerance; 1σ: estimated position uncertainty; err: estimate vs the simulated "
                "truth (blank on hardware)")


def _num(value: float | None, scale: float, digits: int) -> str:
    return "" if value is None else f"{value * scale:.{digits}f}"


def format_row(mod: dict[str, Any]) -> str:
    """One module's row: deviation from the design (mm, deg), tolerance, 1 sigma, truth error."""
    tol = ""
    if mod.get("tolerance_m") is not None and mod.get("tolerance_rad") is not None:
        tol = f"{mod['tolerance_m'] * 1000:g}/{np.degrees(mod['tolerance_rad']):g}"
    return (f"{mod['name']:<7} {mod['verdict']:<10} {_num(mod.get('deviation_m'), 1000, 2):>7} "
            f"{_num(mod.get('deviation_rad'), 180 / np.pi, 3):>7} {tol:>10} "
            f"{_num(mod.get('sigma_position_m'), 1000, 2):>6} {_num(mod.get('position_error_m'), 1000, 2):>7} "
            f"{_num(mod.get('rotation_error_rad'), 180 / np.pi, 3):>7}  {mod.get('reason', '')}").rstrip()


def _rig_survey_line(sol: Any) -> str:
    """One line for the operator: what the rig survey found and how well."""
    cal = sol.calibration
    sd = cal.sigmas()

    def worst(name: str) -> str:
        return f"{max(sd[name]['xyz_mm']):.2f} mm / {max(sd[name]['rot_deg']):.3f} deg"
    return (f"rig calibration from {cal.views} views (corner rms {cal.rms_px:.2f} px): 1 sigma mount "
            f"{worst('platform_T_camera')}, Stewart base {worst('world_T_base')}, focal "
            f"{100 * sd['K']['fx_px'] / cal.K[0, 0]:.3f} %" + ("" if sol.ok else f"; {len(sol.problems)} warning(s) above"))


def format_table(summary: dict[str, Any]) -> str:
    """The verification table printed at the end of `lab run borg` (and by `lab runs show`)."""
    lines = [TABLE_HEADER]
    lines += [format_row(mod) for mod in summary.get("modules", [])]
    counts = {v: sum(1 for mm in summary.get("modules", []) if mm["verdict"] == v) for v in ("ok", "flagged", "unverified")}
    lines.append(f"{counts['ok']} ok, {counts['flagged']} flagged, {counts['unverified']} unverified; "
                 f"rejected tags: {summary.get('rejected_tags', [])}")
    lines.append(TABLE_LEGEND)
    return "\n".join(lines)
