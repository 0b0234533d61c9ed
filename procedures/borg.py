"""BORG assemble-measure-verify (`lab run borg`): one step per module, in assembly order.

Each step: the operator places (or deploys) the module — in simulation the world does, with the
scenario's errors; the survey planned from the design moves the turntable and the Stewart platform
to views that see the new module's tags with their related tags; the camera grabs; the fiducial
detector reads the tags; SF-GraphSLAM takes the views incrementally (iSAM2); tags that don't fit the
design are eliminated; the module gets its verdict.  A verdict that is still `uncertain` (the
deviation within its own uncertainty of the tolerance) takes more views, planned from the graph's
covariance, up to the step's view budget; still open then, it stays `uncertain`.  A flag stops the
run (default), is noted and passed (`--on-flag continue`), or sends the operator to re-deploy and
re-measure (`retry`).

Everything is planned before the first move, so `--dry-run` checks every turntable angle, lift
height and Stewart pose of the whole procedure against the limits and the workspace, and lists
every module no candidate view of the rig can see.  A run with such modules is refused before
anything moves unless `--allow-unobservable` says to go on; then it warns at its start and those
modules come out `unverified`, naming why.
"""

from __future__ import annotations

import json
import math
import time
from collections import Counter
from dataclasses import replace
from functools import cached_property
from typing import Any, Callable

import numpy as np

from estimation.verification import Tolerance, Tolerances
from lab.core.config import MODULE_KINDS, VerificationConfig
from lab.core.errors import UserError
from lab.core.geometry import pose_error
from lab.core.recorder import messages as m
from lab.core.recorder import topics
from lab.core.structures.borg import BorgModel, build_borg
from lab.core.survey_budget import check_max_views, check_sigma_target_mm
from lab.core.verdicts import FLAGGED, OK, UNCERTAIN, UNVERIFIED, Bound, TruthError, Verdict
from procedures.console import BORG_HEADER, borg_row, confirm_views_line, console_of, more_views_line
from procedures.runner import RunContext, StepSpec, StopRun
from procedures.setup import Bench
from procedures.survey import CameraModel, PrecisionTarget, SurveyPlan, SurveyPlanner, View

ON_FLAG = ("stop", "continue", "retry")
MAX_RETRIES = 2
MAX_REPLANS = 2          # rounds of views re-planned for tags a step's views did not measure
# An `ok` read from few views can carry a 1-sigma of 1-1.6 mm (a tag seen small or oblique): honest,
# but an error of 1.5 mm passes with it.  Such a verdict takes more views, planned for the step's
# target as the first were, while its 1-sigma is above this multiple of the target: at most
# MAX_CONFIRMS rounds, none when no view is predicted to shrink the module's tag any further, and a
# second only when the first cut the 1-sigma by CONFIRM_GAIN (what a round cannot cut is the
# frame's share, or a camera's noise floor, which more views of the module hardly reduce: on a
# poor camera a second round took 0.71 mm to 0.71 and 0.56 to 0.48).
OK_SIGMA_FACTOR = 2.0
FLOOR_WINDOW = 8          # the floor a plan assumes: the median over this many modules measured last
MAX_CONFIRMS = 2
CONFIRM_GAIN = 0.25
_STREAM_CAMERA = 8200    # simulated camera noise per step: [seed, _STREAM_CAMERA, step, attempt]
# every tag's covariance is logged at the first round and then every FULL_COVARIANCE_EVERY rounds, or
# every (tags / FULL_COVARIANCE_PER_ROUND) rounds in a larger structure; between them, the module's
# (`_log_estimates`)
FULL_COVARIANCE_EVERY = 10
FULL_COVARIANCE_PER_ROUND = 20
IMAGE_FORMAT = "jpeg"    # logged images (detection runs on the lossless frame)


def needs_confirming(result: Verdict, target_m: float, confirms: int, confirmed_from: float | None) -> bool:
    """Whether an `ok` takes another round of views (OK_SIGMA_FACTOR): its 1-sigma is over that
    multiple of the step's target, fewer than MAX_CONFIRMS rounds were taken for it, and the last
    one (`confirmed_from`: the 1-sigma before it) cut the 1-sigma by CONFIRM_GAIN."""
    return (result.verdict == OK and result.sigma_m is not None and confirms < MAX_CONFIRMS
            and result.sigma_m > OK_SIGMA_FACTOR * target_m
            and (confirmed_from is None or result.sigma_m <= (1 - CONFIRM_GAIN) * confirmed_from))


def views_by_round(views: list[dict[str, Any]]) -> list[tuple[tuple[int, int, int], list[dict[str, Any]]]]:
    """A checkpoint's views grouped by round, ((step, attempt, round), views) in the order they were
    taken: what a resume replays (`BorgProcedure.replay_estimator`)."""
    by_round: dict[tuple[int, int, int], list[dict[str, Any]]] = {}
    for v in views:
        by_round.setdefault((v["step"], v["attempt"], v.get("round", 0)), []).append(v)
    return sorted(by_round.items(), key=lambda kv: kv[0])


class UnobservableModules(UserError):
    """Modules no candidate view of the rig sees: a run refuses to start (`lines` lists them)."""

    def __init__(self, message: str, lines: list[str]) -> None:
        super().__init__(message)
        self.lines = lines


class BorgProcedure:
    name = "borg"

    def __init__(self, bench: Bench, on_flag: str = "stop", n: int | None = None, max_modules: int | None = None,
                 estimator_config: Any = None, calibration: str | None = None, rig_survey: bool | None = None,
                 observation: str | None = None, uncalibrated: bool = False,
                 tolerances: list[str] | None = None, sigma_target_mm: float | None = None,
                 max_views: int | None = None, allow_unobservable: bool = False) -> None:
        """`calibration`: a rig calibration file (default: the rig's [calibration] file).
        `rig_survey`: begin with a rig calibration survey (default: when there is no calibration).
        `tolerances` ("KIND=MM,DEG"), `sigma_target_mm`, `max_views`: override the rig's
        [verification] table.  `allow_unobservable`: run even if the rig cannot see some modules
        (they are reported `unverified`); otherwise `check_observable` refuses the run."""
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
        # a lift gives the planner heights to look from (none when the lift's zero sees it all)
        lift = (rig.lift.min_m, rig.lift.max_m) if rig.lift is not None else None
        self.planner = SurveyPlanner(self.model, cam, lambda p: self.kinematics.inverse(p).reachable,
                                     (rig.turntable.min_rad, rig.turntable.max_rad), lift_limits_m=lift)
        ver = rig.verification
        self.tolerances = parse_tolerances(tolerances or [], ver)
        if sigma_target_mm is not None:
            check_sigma_target_mm(sigma_target_mm)
        if max_views is not None:
            check_max_views(max_views)
        estimator_config = dict(estimator_config or {})
        # the graph's corner noise: as given, else what the rig calibration measured, else the rig's
        # [verification] value until a survey measures it
        self._corner_sigma_given = "corner_sigma_px" in estimator_config
        self._tag_scale_given = "tag_scale_sigma" in estimator_config
        estimator_config.setdefault("corner_sigma_px", ver.corner_sigma_px)
        estimator_config.setdefault("tag_scale_sigma", ver.tag_scale_sigma)
        estimator_config.setdefault("near_tags_per_view", ver.near_tags_per_view)
        estimator_config.setdefault("settle_after_layers", ver.settle_after_layers)
        corner_sigma = float(estimator_config["corner_sigma_px"])
        self.precision = PrecisionTarget(sigma_m=sigma_target_mm * 1e-3 if sigma_target_mm is not None else ver.sigma_target_m,
                                         max_views=max_views if max_views is not None else ver.max_views,
                                         corner_sigma_px=corner_sigma)
        self.allow_unobservable = bool(allow_unobservable)
        self._unobservable_warned = False
        self._lift_at: float | None = None       # where the lift is known to be (None: not asked yet)
        # where the turntable and the platform were last sent and arrived (None: not known, e.g. after
        # homing, a resume or a move that did not finish): a view that wants them there again does
        # not command them (a move of zero still costs its command, polls and settling)
        self._turntable_at: float | None = None
        self._stewart_at: tuple[float, ...] | None = None
        from estimation.rig_model import RigGeometry
        from procedures.borg_measure import Measurement

        self.rig_geometry = RigGeometry.from_rig(rig, self.model.world_T_structure(0.0), self.intrinsics.K)
        self._datasheet_geometry = self.rig_geometry      # the rig file's repeatability, before a survey measures it
        self.rig_calibration = None
        # what the run's rig geometry comes from, for a rig that disagrees with the camera
        self.calibration_source = f"the rig file {rig.source}'s nominal geometry"
        cal_file = calibration or rig.calibration.file
        if cal_file is not None:
            from lab.core.rig_calibration_file import load_rig_calibration
            from lab.core.rig_calibration_check import check_for_rig

            self.rig_calibration = load_rig_calibration(cal_file)
            # its meaning, before anything moves: a file for another bench or structure, or values
            # no survey of this one could give, would otherwise be blamed on the structure
            check_for_rig(self.rig_calibration, rig, self.intrinsics, self.model, str(cal_file))
            self.calibration_source = f"calibration {cal_file}"
            self._take_measured(estimator_config, self.rig_calibration.corner_sigma_px,
                                self.rig_calibration.tag_scale_sigma, self.rig_calibration.repeatability_scale)
        # each module's views, planned from the design with the corner noise the graph will read its
        # sightings with: the calibration file's, when there is one (a survey's measurement comes
        # later, and the modules not yet measured are planned again with it: `_plan_of`)
        self.surveys: dict[str, SurveyPlan] = {}
        placed: list[str] = []
        for mod in modules:
            placed.append(mod.name)
            self.surveys[mod.name] = self.planner.plan(mod.name, placed, self.precision)
        # modules whose tags no candidate view sees (at their step, with what is placed in front)
        self.unobservable = {name: plan.unobservable for name, plan in self.surveys.items() if plan.unobservable}
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
        self._plan_notes: dict[str, str] = {}            # module -> why its plan was made again before its views
        # each measured module's floor (m^2): its stated 1-sigma squared less what its own views
        # were predicted to give (`_plan_floor`); the plans of the modules after it combine their
        # views' share with the recent ones' median
        self._floor_m2: list[float] = []
        if observation is not None:
            estimator_config["observation"] = observation
        self.measure = Measurement(self.model, self.intrinsics, estimator_config, rig=self._rig_model(),
                                   calibration=self.rig_calibration)
        self.measure.tolerances = self.tolerances
        self.results: dict[str, Verdict] = {}
        self.views_done: list[dict[str, Any]] = []     # every view taken, for checkpoints / replay
        self._true_cameras: list[Any] = []             # simulation: each graph view's true camera, for the bound
        self._corner_sq: list[float] = []              # simulation: squared corner errors against the truth
        self._run_bound: tuple[tuple, Any] | None = None  # simulation: (what it is of, estimation.bound.RunBound)
        self._rounds_since_full: int | None = None    # rounds since every tag's covariance was logged
        self._views_encoded: Any = None                # the checkpoint's views, each encoded once
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
        from procedures.rig_survey import plan_rig_survey, survey_angle_step, survey_lift

        rig = self.bench.rig
        # a bigger turntable's rim in finer turntable steps (survey_angle_step)
        step = survey_angle_step(self.model.turntable.radius_m)
        # a turntable sweep per platform pose: the shortest survey for the same views
        plan = plan_rig_survey(lambda p: self.kinematics.inverse(np.asarray(p, float)).reachable,
                               (rig.turntable.min_rad, rig.turntable.max_rad), angle_step_rad=step, order="poses")
        # a bigger turntable's rim is seen from lower down (0 for the 3x3x3's, and without a lift)
        lift = survey_lift(self.planner, plan)
        if not lift:
            return plan
        return plan_rig_survey(lambda p: self.kinematics.inverse(np.asarray(p, float)).reachable,
                               (rig.turntable.min_rad, rig.turntable.max_rad), angle_step_rad=step, order="poses",
                               lift_m=lift)

    def unobservable_lines(self) -> list[str]:
        """One line per module the rig cannot observe: which tags, where."""
        out = []
        for name, tags in self.unobservable.items():
            m = self.model.module_by_name[name]
            where = ", ".join(f"{t} at z {self.model.tags[t].structure_T_tag.translation()[2]:.2f} m" for t in tags)
            out.append(f"module {name} ({m.kind.replace('_', ' ')}, face {m.face}): no candidate view of rig "
                       f"{self.bench.rig.name!r} sees tag{'s' if len(tags) > 1 else ''} {where}")
        return out

    @cached_property
    def rig_survey_blind(self) -> str | None:
        """Why the run's rig survey would see no turntable tag, or None (no survey, or it sees some)."""
        if not self.rig_survey:
            return None
        from procedures.rig_survey import predicted_blind

        return predicted_blind(self.planner, self.rig_survey_plan, self.bench.rig.stewart.station)

    @cached_property
    def tags_beyond_family(self) -> str | None:
        """Why the structure's tags cannot be printed in the detector's largest tag family, or None."""
        from estimation.tag_family import EXTENDED, family_name, family_size

        ids = sorted(self.model.tags)
        n_ids = family_size(EXTENDED)
        if not ids or ids[-1] < n_ids:
            return None
        return (f"borg:{self.model.n} has {len(ids)} tags, ids {ids[0]}..{ids[-1]}, and the largest tag family is "
                f"{family_name(EXTENDED)}, ids 0..{n_ids - 1} (docs/hardware.md, \"Tags\")")

    def check_observable(self) -> None:
        """Before anything moves: refuse a structure whose tags the tag family cannot print, a run
        the rig cannot see all of, unless told to go on, and one whose rig survey cannot see the
        turntable (nothing would calibrate the rig)."""
        if self.tags_beyond_family:
            raise UserError(f"{self.tags_beyond_family}; nothing moved")
        if self.rig_survey_blind:
            raise UserError(f"{self.rig_survey_blind}; nothing moved")
        if self.unobservable and not self.allow_unobservable:
            raise UnobservableModules(
                f"rig {self.bench.rig.name!r} cannot observe {len(self.unobservable)} of the {len(self.modules)} "
                f"modules of borg:{self.model.n} planned (listed above); nothing moved. Give the rig a lift "
                f"(docs/hardware.md, \"The lift\"), or run with --allow-unobservable to assemble them anyway "
                f"(reported unverified)", self.unobservable_lines())

    def dry_run_notes(self, steps: list[StepSpec]) -> list[str]:
        """What the plans made before anything moves amount to: their views, and the tags they
        measure from one turntable angle only (depth then rests on the tag's size, not on
        triangulation: a plan's weakness an operator can see before the run)."""
        sep = self.planner.config.min_angle_separation_rad
        planned = [self.surveys[s.params["module"]] for s in steps if "module" in s.params]
        if not planned:
            return []
        views = sum(len(p.views) for p in planned)
        one = sorted(t for p in planned for t in self.model.module_by_name[p.module].tags
                     if 0 < _angles_apart([v.turntable_rad for v, seen in zip(p.views, p.expected) if t in seen], sep) < 2)
        tags = sum(len(self.model.module_by_name[p.module].tags) for p in planned)
        survey = f", the rig survey {len(self.rig_survey_plan.views)}" if self.rig_survey else ""
        return [f"{views} views planned for {len(planned)} modules ({views / len(planned):.2f} a module){survey}",
                f"{len(one)} of {tags} tags planned from one turntable angle only"
                + (f" (tags {', '.join(map(str, one[:12]))}{', ...' if len(one) > 12 else ''})" if one else "")]

    def dry_run_warnings(self, steps: list[StepSpec]) -> list[str]:
        if not self.allow_unobservable:
            return []
        return [f"{line}: it will be unverified (--allow-unobservable)" for line in self.unobservable_lines()]

    def dry_run_problems(self, steps: list[StepSpec]) -> list[str]:
        tt, st, lift = self.bench.devices.turntable, self.bench.devices.stewart, self.bench.devices.lift
        problems = [self.tags_beyond_family] if self.tags_beyond_family else []
        for spec in steps:
            if "rig_survey" in spec.params:
                if self.rig_survey_blind:
                    problems.append(f"{spec.name}: {self.rig_survey_blind}")
                if self.rig_survey_plan.lift_m:
                    try:
                        if lift is None:
                            raise UserError(f"the rig survey needs a lift and rig {self.bench.rig.name!r} has none")
                        lift.check_height(self.rig_survey_plan.lift_m)
                    except Exception as exc:
                        problems.append(f"{spec.name}: {exc}")
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
                if v.lift_m:
                    try:
                        if lift is None:
                            raise UserError(f"view {v.label} needs a lift and rig {self.bench.rig.name!r} has none")
                        lift.check_height(v.lift_m)
                    except Exception as exc:
                        problems.append(f"{spec.name}: {exc}")
        if not self.allow_unobservable:
            problems += self.unobservable_lines()
        return problems

    # ---- one step ------------------------------------------------------------------------------
    def execute(self, spec: StepSpec, run: RunContext) -> None:
        if not self._unobservable_warned:
            # allowed to run (check_observable refused it otherwise): say so before the first move
            for line in self.unobservable_lines():
                run.recorder.log_text("warning", f"{line}: it will be unverified")
            self._unobservable_warned = True
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
            self.results[module.name] = result
            self._log_verdict(run, spec.index, result)
            if result.verdict != FLAGGED or self.on_flag == "continue":
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
        from procedures.setup import lift_to_zero

        # any height but 0 among the candidates (a further round of views may use one too)
        uses_lift = any(self.planner.lift_heights) or (self.rig_survey and bool(self.rig_survey_plan.lift_m))
        lift_to_zero(self.bench, run, always=uses_lift)
        self._lift_at = 0.0 if self.bench.devices.lift is not None else None
        self._turntable_at, self._stewart_at = None, None
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
        from procedures.rig_survey import capture, no_rim_seen, views_to_json

        rec = run.recorder
        rec.log_text("info", "no rig calibration: surveying the turntable tags to calibrate the rig")
        views = capture(self.bench, run, self.rig_survey_plan, self.measure.detector,
                        seed=[self.bench.scenario.seed, _STREAM_CAMERA, spec.index],
                        log_image=lambda frame, t: rec.log_image(topics.CAMERA_IMAGE, frame.image, t, "camera",
                                                                 format=IMAGE_FORMAT), overlap=True)
        if self.bench.devices.lift is not None:
            self._lift_at = self.rig_survey_plan.lift_m
        if self.rig_survey_plan.views:
            last = self.rig_survey_plan.views[-1]
            self._turntable_at, self._stewart_at = last.turntable_rad, tuple(last.stewart_pose)
        self.rig_survey_views = views_to_json(views)
        # a survey that saw no rim tag calibrates nothing: going on with the rig file's priors
        # alone left every module of an N = 7 run `uncertain` (1 sigma ~21 mm) until iSAM2 stopped
        why = no_rim_seen(views)
        if why:
            raise StopRun(f"rig calibration: {why}")
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
        self.measure.tolerances = self.tolerances       # the run's tolerances, not the defaults

    def _solve_rig_survey(self, views: Any) -> Any:
        from estimation.rig_calibration_solve import solve_rig

        tags = {t: (s.structure_T_tag, s.size_m) for t, s in self.model.tags.items() if s.module == "turntable"}
        sol = solve_rig(views, self.rig_geometry, self.intrinsics.dist, tags,
                        turntable_tags=self.model.turntable.tag_ids, rig_name=self.bench.rig.name,
                        tag_scale_sigma=float(self.measure.config.get("tag_scale_sigma", 0.0)))
        self.rig_calibration = sol.calibration
        self.calibration_source = "the run's rig survey"
        self._take_measured(self.measure.config, sol.corner_sigma_px, sol.tag_scale_sigma, sol.repeatability_scale)
        return sol

    def _take_measured(self, config: dict[str, Any], corner_sigma_px: float, tag_scale_sigma: float,
                       repeatability_scale: float = float("nan")) -> None:
        """What the rig survey measured replaces the rig file's assumptions (unless given): the
        corner noise, the tags' scale scatter, and the devices' repeatability (the run's chain
        factors)."""
        from estimation.rig_calibration_solve import with_repeatability_scale

        self.rig_geometry = with_repeatability_scale(self._datasheet_geometry, repeatability_scale)
        if not self._corner_sigma_given and math.isfinite(corner_sigma_px):
            config["corner_sigma_px"] = float(corner_sigma_px)
            # the plans predict each view's share with the graph's corner noise: planned with the
            # rig file's assumption (0.02 px) where the survey measured 0.031, a 3x3x3's plans
            # promised 0.23 mm median that the same views give 0.28 mm at the measured noise
            self.precision = replace(self.precision, corner_sigma_px=float(corner_sigma_px))
        if not self._tag_scale_given and math.isfinite(tag_scale_sigma) and config.get("tag_scale_sigma", 0) > 0:
            config["tag_scale_sigma"] = float(tag_scale_sigma)

    def _rig_model(self):
        return None if self.uncalibrated else self.rig_geometry

    def _rig_survey_report(self, sol: Any) -> dict[str, Any]:
        from estimation.rig_calibration_solve import describe
        from procedures.rig_survey import against_truth

        out: dict[str, Any] = {"views": sol.calibration.views, "rms_px": sol.calibration.rms_px,
                               "problems": list(sol.problems), "estimate": describe(sol.calibration),
                               "measured": {"corner_sigma_px": sol.corner_sigma_px,
                                            "turntable_tag_sigma_m": sol.turntable_tag_sigma_m,
                                            "tag_scale_sigma": sol.tag_scale_sigma,
                                            "repeatability_scale": sol.repeatability_scale}}
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

    def _survey_and_verify(self, spec: StepSpec, run: RunContext, name: str, attempt: int) -> Verdict:
        """The planned views, then -- while the step's view budget allows -- further rounds: views
        re-planned from the calibrated rig and the graph's estimate of the structure when a tag of
        the module that the views were planned to show was not measured (out of frame, hidden, too
        oblique, unreadable), and views planned from the module's covariance in the graph while its
        verdict is `uncertain`, or `ok` with a 1-sigma over `OK_SIGMA_FACTOR` times the step's
        target (`needs_confirming`).  The last round's verdict, with what only the procedure
        knows (and what the re-planning tried), is the module's record."""
        plan = self._checked_plan(name, self._plan_of(name), run)
        taken: list[View] = []
        replans: list[str] = []          # what each re-plan was for and what it tried
        rnd = confirms = 0
        confirmed_from: float | None = None      # the ok's 1-sigma before the last confirming round
        own_info = np.zeros((6, 6))       # the views' own information, as planned (`_plan_floor`)
        while True:
            result = self._measure_round(spec, run, name, attempt, rnd, plan.views, len(taken))
            taken += plan.views
            own_info += self.planner.plan_information(plan, self.precision)
            budget = self.precision.max_views - len(taken)
            missing = self._missing_tags(name, result, plan)
            if missing and budget > 0 and len(replans) < MAX_REPLANS:
                replan = self._replan(name, missing, taken, budget)
                what = ", ".join(f"tag {t} seen in {self._sightings(name, t)} of {len(taken)} view(s)"
                                 + (", all from one turntable angle" if self._sightings(name, t)
                                    and self._directions_short(name, t, plan) else "")
                                 + self._behind_note(name, t)
                                 for t in missing)
                if replan.views:
                    replans.append(f"{what}; {len(replan.views)} more planned from the calibrated rig and the "
                                   f"estimated structure")
                    console_of(run).line(f"{name}: {what}, fewer than planned; {len(replan.views)} more view(s), "
                                         f"re-planned")
                    plan = replan
                    rnd += 1
                    continue
                replans.append(f"{what}, and no other reachable view is predicted to show it")
            confirm = needs_confirming(result, self.precision.sigma_m, confirms, confirmed_from)
            if not (result.verdict == UNCERTAIN or confirm) or budget <= 0:
                break
            placed = self.measure.placed
            # from the calibrated rig and the estimated structure, avoiding where its tags were missed;
            # an uncertain one aims past the plan's target, at what the band needs
            plan = self._adapted_planner(name).more_views(name, placed, taken,
                                                          self.measure.verdict_tag_covariance(name),
                                                          self.precision if confirm else self._round_target(result),
                                                          budget)
            if not plan.views:
                break
            rnd += 1
            if confirm:
                confirms, confirmed_from = confirms + 1, result.sigma_m
                console_of(run).line(confirm_views_line(name, result.sigma_m, self.precision.sigma_m, len(plan.views)))
            else:
                console_of(run).line(more_views_line(name, result.deviation_m, result.sigma_m, len(plan.views)))
        if name in self._plan_notes:
            note = self._plan_notes.pop(name)
            result = replace(result, reason=f"{result.reason}; {note}" if result.reason else note)
        if replans:
            still = self._missing_tags(name, result, self.surveys[name])
            outcome = (f"tag {', '.join(map(str, still))} still short of views"
                       + "".join(self._behind_note(name, t) for t in still) if still
                       else "every tag of it measured")
            note = f"re-planned: {'; '.join(replans)}; {outcome} after {len(taken)} view(s)"
            result = replace(result, reason=f"{result.reason}; {note}" if result.reason else note)
        reason = result.reason
        if result.verdict == UNVERIFIED and name in self.unobservable:
            tags = ", ".join(map(str, self.unobservable[name]))
            reason = f"the rig cannot observe it (no candidate view sees tag {tags}); {reason}".rstrip("; ")
        result = replace(result, reason=reason, views=len(taken), attempts=attempt,
                         predicted_sigma_m=self.surveys[name].predicted_sigma_m)
        self._plan_floor(name, result, own_info)
        if self.bench.simulated:
            # the bound of the graph the verdict read, before the module's relations join
            result = replace(result, truth=self._truth_error(result), bound=self._bound(name))
        self.measure.finish(name)
        return result

    def _planning(self) -> PrecisionTarget:
        """What a module's plan aims at: the run's target, at the graph's corner noise, with the
        floor the modules measured last showed (none before the first is measured)."""
        recent = self._floor_m2[-FLOOR_WINDOW:]
        return replace(self.precision, floor_sigma_m=math.sqrt(float(np.median(recent))) if recent else 0.0)

    def _plan_of(self, name: str) -> SurveyPlan:
        """The module's plan from the design, made again when what its accuracy pass assumed has
        changed since (the rig survey measured the corner noise; the measured modules showed the
        floor): the same coverage, the accuracy pass as the module's sightings will be read."""
        plan = self.surveys[name]
        want = self._planning()
        if plan.corner_sigma_px is not None and (plan.corner_sigma_px, plan.floor_sigma_m) != (want.corner_sigma_px,
                                                                                             want.floor_sigma_m):
            names = [m.name for m in self.modules]           # placed by its step, as the design has it
            plan = self.planner.plan(name, names[:names.index(name) + 1], want)
            self.surveys[name] = plan
        return plan

    def _plan_floor(self, name: str, result: Verdict, own_info: np.ndarray) -> None:
        """The module's floor, from its verdict: its stated 1-sigma squared less the share its own
        views were predicted to give (`own_info`, the information of every view taken, as planned,
        at the graph's corner noise).  What is left is what no view of it reduced: the frame and
        the rig, which grow with the height (0 at the bottom of a 10x10x10 to 0.31 mm at its top
        layer), and whatever the views missed of what they were planned to show."""
        if result.sigma_m is None or not math.isfinite(result.sigma_m):
            return
        own = self.planner.predicted_sigma(name, own_info)
        if math.isfinite(own):
            self._floor_m2.append(max(result.sigma_m ** 2 - own ** 2, 0.0))

    def _checked_plan(self, name: str, plan: SurveyPlan, run: RunContext) -> SurveyPlan:
        """The module's plan, made before anything moved from the design, checked against the
        deployables the run has since measured short: their top faces stand lower, and the struts
        to them cross lines of sight the design leaves clear.  Where they hide a sighting of the
        module's tags that the plan counts on, the module is planned again before its views are
        taken, from the calibrated rig and the structure as estimated (`_adapted_planner`), with
        the whole view budget: spent on the design's views, the budget would leave none for the
        re-plan after they miss (at N = 7, 227S's 12 views all crossed by a strut of 186D,
        deployed to 0.35 m of 0.5 m: `unverified`).  A run with every deployable deployed keeps
        its plans as they were."""
        short = self._short_deployables()
        if not short or not plan.views:
            return plan
        placed = list(self.measure.placed) + ([] if name in self.measure.placed else [name])
        struts = self.planner.adapted(self.planner.structure_T_camera, {}, None, None, short)
        hidden = struts.hidden_by_struts(name, placed, plan.views, plan.expected)
        if not hidden:
            return plan
        again = self._adapted_planner(name).plan(name, placed, self._planning())
        if not again.views:
            return plan
        lowered = ", ".join(m for m in placed if m in short)
        note = (f"{len(hidden)} planned sighting(s) of tag {', '.join(str(t) for t in sorted({t for _, t in hidden}))} "
                f"behind the struts of {lowered}, measured short")
        console_of(run).line(f"{name}: {note}; {len(again.views)} view(s) re-planned before any was taken")
        self._plan_notes[name] = f"planned again before its views: {note}"
        self.surveys[name] = again
        return again

    def _short_deployables(self) -> dict[str, float]:
        """Deployables the graph measured short of their lift: module -> measured lift (m).  One
        flagged for its top plane's tilt or offset stands at its full height, its struts where the
        design has them to a few mm."""
        slam = self.measure.slam
        return {m: check.height_m for m, check in slam.not_deployed().items()
                if check.height_m < self.model.spacing_m - slam.config.height_tol_m}

    def _missing_tags(self, name: str, result: Verdict, plan: SurveyPlan | None) -> list[int]:
        """Tags of the module the step's views should have measured and did not: a tag the round's
        views were planned to show (`plan`; None, or a verdict with no tag at all: every tag of it)
        that is not in the graph's measurement of the module (never detected, or only too
        obliquely to use), or that fewer of the step's views showed than the plan counted on and
        than the coverage needs (`SurveyConfig.min_sightings`: one sighting leaves its depth to
        one view).  A tag rejected as displaced is measured: another view would not move it --
        unless it is a deployable's whose deployment is unread, which another view can read."""
        tags = self.model.module_by_name[name].tags
        expected = set(tags) if plan is None or result.verdict == UNVERIFIED else \
            {t for seen in plan.expected for t in seen}
        need = self.planner.config.min_sightings
        unread = self.measure.deployment_unread(name)
        out = []
        for t in tags:
            displaced = t in self.measure.rejected_tags
            if t not in expected or (displaced and not unread):
                continue
            planned = sum(t in seen for seen in plan.expected) if plan is not None else need
            # the deployment check reads each tag in `need` views, however many the plan counted on
            want = need if displaced else min(planned, need)
            if t not in result.tags_seen or self._sightings(name, t) < want or self._directions_short(name, t, plan):
                out.append(t)
        return out

    def _directions_short(self, name: str, tag: int, plan: SurveyPlan | None) -> bool:
        """Whether the step's views saw `tag` from fewer turntable angles than the plan counted on
        (up to `min_sightings`): its depth was to come from triangulation, and views from one
        angle leave it to the size of a 10 cm tag at 3-4 m (at N = 7, 159D's tag 224 was planned
        from two angles and seen from one, in 5 of the 11 views: `uncertain` at a 1-sigma of
        2.4 mm where 0.25 mm was planned)."""
        if plan is None:
            return False
        sep = self.planner.config.min_angle_separation_rad
        need = min(_angles_apart([v.turntable_rad for v, seen in zip(plan.views, plan.expected) if tag in seen], sep),
                   self.planner.config.min_sightings)
        seen = [v["turntable_rad"] for v in self._step_views(name) if self._used(v, tag)]
        return _angles_apart(seen, sep) < need

    def _sightings(self, name: str, tag: int) -> int:
        """How many of this step's views (every round) measured `tag`: detected it face-on enough
        for the graph to use (`_used`)."""
        return sum(self._used(v, tag) for v in self._step_views(name))

    def _used(self, view: dict[str, Any], tag: int) -> bool:
        """Whether `view` (a view record) gives the graph a sighting of `tag`: detected, and its
        undistorted quadrilateral no flatter than the graph takes (`rig_model.MIN_SIDE_RATIO`).  A
        detection the graph leaves out as too oblique measured nothing: counted as a sighting, it
        hid a missing direction (at N = 6, 52S's tag seen from two turntable angles, one of them
        at a side ratio of 0.61: both its measured views from one angle, its print scale and its
        depth left to the scale's prior, 2.6 mm off at a 1-sigma of 0.76 mm, and no re-plan)."""
        from estimation.rig_model import MIN_SIDE_RATIO, side_ratio

        for d in view["detections"]:
            if d["id"] == tag:
                camera = self.measure.slam.camera
                return camera is None or side_ratio(np.asarray(d["corners_px"], float), *camera) >= MIN_SIDE_RATIO
        return False

    @cached_property
    def _module_of_tag(self) -> dict[int, str]:
        return {t: spec.module for t, spec in self.model.tags.items()}

    def _behind_note(self, name: str, tag: int) -> str:
        return behind_note(self._step_views(name), tag, self._module_of_tag)

    def _step_views(self, name: str) -> list[dict[str, Any]]:
        """The views of this step's current attempt, every round."""
        views: list[dict[str, Any]] = []
        for v in reversed(self.views_done):
            if v["module"] != name or (views and v["attempt"] != views[0]["attempt"]):
                break
            views.append(v)
        return views[::-1]

    def _adapted_planner(self, name: str):
        """The planner's candidates judged from what the run has learnt -- each view's camera where
        the graph's current calibration of the rig puts it (turntable axis, Stewart base, lift,
        camera mount), the calibrated intrinsics, every tag the graph has estimated where it
        estimates it (so the structure as built hides what it really hides), the rest where the
        design has them, a deployable measured short with its top face where it was measured -- and
        not counting on a view near one that missed a tag of the module."""
        from estimation.rig_model import ViewMotion

        slam = self.measure.slam
        if slam.rig is not None:
            def camera(view: View):
                return slam.predicted_camera(ViewMotion(view.turntable_rad, view.stewart_pose, view.lift_m))
        else:
            camera = self.planner.structure_T_camera
        tags = self.model.module_by_name[name].tags
        missed: dict[int, list[View]] = {}
        for v in self._step_views(name):
            view = View(float(v["turntable_rad"]), tuple(float(x) for x in v["stewart_pose"]), float(v["lift_m"]))
            for t in tags:
                if not self._used(v, t):
                    missed.setdefault(t, []).append(view)
        return self.planner.adapted(camera, slam.tag_estimates(), self.measure.detector_camera[0], missed,
                                    self._short_deployables())

    def _replan(self, name: str, missing: list[int], taken: list[View], budget: int) -> SurveyPlan:
        """Views for `missing` tags, none of `taken`, at most `budget`, from the adapted planner:
        the coverage pass for them, then the accuracy pass from what the graph knows of the module."""
        cov = self.measure.verdict_tag_covariance(name)
        info = None
        if cov is not None and self.measure.verdict_tags(name)[:1] == self.model.module_by_name[name].tags[:1]:
            info = np.linalg.inv(cov)
        return self._adapted_planner(name).plan(name, self.measure.placed, replace(self.precision, max_views=budget),
                                                exclude=taken, want=missing, info=info, fallback=False)

    def _bound(self, name: str) -> Bound | None:
        """Simulation: the best 1-sigma any estimator could give this module from the same views --
        the graph's marginal linearised at the true poses with the detector's true corner noise
        (measured against the truth over the run so far)."""
        slam = self.measure.slam
        tags = self.measure.verdict_tags(name)
        if (not tags or len(self._true_cameras) != slam.n_views or any(c is None for c in self._true_cameras)
                or not self._corner_sq or slam.camera is None):
            return None
        import gtsam

        from estimation.bound import RunBound
        from estimation.precision import module_sigma
        from estimation.rig_model import AXIS, BASE, INTRINSICS, LIFT, MOUNT, cal3_s2
        from estimation.sf_graphslam import GENERATION

        world = self.bench.sim.world
        sigma_px = float(np.sqrt(np.mean(self._corner_sq)))
        e = world.rig_error
        floor = 1e-7    # "exact" as a Gaussian the solver can still factor
        true_geometry = replace(self.rig_geometry, config=replace(
            self.rig_geometry.config, stewart_repeatability_m=max(e.stewart_repeatability_m, floor),
            stewart_repeatability_rad=max(e.stewart_repeatability_rad, floor),
            turntable_repeatability_rad=max(e.turntable_repeatability_rad, floor),
            lift_repeatability_m=max(e.lift_repeatability_m, floor)))
        # priors with the true noise: a rig file that is exact (an ideal rig) is an exact prior; a
        # calibration's covariance is its own honest statement of how wrong it is
        exact_rig = self.rig_calibration is None and self.rig_survey_result is None and e == type(e)()
        # the turntable tags: where a calibration located them, its covariance is what is known of
        # them; from the design, they are as wrong as they were truly glued
        calibrated = self.rig_calibration is not None or self.rig_survey_result is not None
        # one incremental bound per graph and true rig noise: each factor linearised at the truth
        # once, not the whole graph again at every verdict (estimation/bound.py)
        params = (slam, e, exact_rig, calibrated)
        if self._run_bound is None or self._run_bound[0] != params:
            self._run_bound = (params, RunBound(slam, chain_noise=true_geometry.chain_noise,
                                                rig_prior_sigma=floor if exact_rig else None,
                                                turntable_tag_sigma_m=None if calibrated
                                                else max(e.turntable_tag_sigma_m, floor)))
        truth = gtsam.Values()
        rig = {AXIS: world.true_rig.world_T_axis, BASE: world.true_rig.world_T_base,
               MOUNT: world.true_rig.platform_T_camera, LIFT: world.true_rig.world_T_lift,
               INTRINSICS: cal3_s2(world.camera.K)}
        for key in slam.graph.keyVector():
            sym = gtsam.Symbol(key)
            ch, idx = chr(sym.chr()), sym.index()
            if key in rig:
                truth.insert(key, rig[key])
            elif ch == "c":
                truth.insert(key, self._true_cameras[idx])
            elif ch == "t":
                truth.insert(key, world.borg.structure_T_tag(idx % GENERATION))
            elif ch == "d":
                truth.insert(key, np.zeros(2))   # the lens correction enters linearly: any value
            elif ch == "s":
                # a tag's print scale: the Jacobians hardly depend on it (1e-3 of their size)
                truth.insert(key, np.zeros(1))
        tag = tags[0]
        try:
            cov = self._run_bound[1].covariances([slam.key(tag)], sigma_px, truth)[slam.key(tag)]
        except RuntimeError:
            return None
        m = self.model.module_by_name[name]
        ms = module_sigma(self.model.tags[tag].structure_T_tag.inverse().compose(m.structure_T_module), cov)
        return Bound(ms.position_m, ms.rotation_rad, ms.position_rms_m)

    def _take_truth(self, record: dict[str, Any]) -> None:
        from lab.core.geometry import Pose3

        truth = record.get("truth")
        if truth is None:
            self._true_cameras.append(None)
            return
        self._true_cameras.append(Pose3(np.asarray(truth["structure_T_camera"])))
        self._corner_sq += truth["corner_sq_px2"]

    def _round_target(self, r: Verdict) -> PrecisionTarget:
        """For an uncertain module: the sigma at which its deviation would clear the tolerance's
        band on one side or the other, if the estimate stays where it is (never looser than the plan's)."""
        tol = self.tolerances.of(self.model.module_by_name[r.module].kind)
        need = self.precision.sigma_m
        if r.deviation_m is not None:
            gap = abs(r.deviation_m - tol.position_m)
            need = min(need, max(gap / (tol.band_sigmas + 0.5), 1e-5))
        return replace(self.precision, sigma_m=need)

    def _measure_round(self, spec: StepSpec, run: RunContext, name: str, attempt: int, rnd: int,
                       views_planned: list[View], first_k: int) -> Verdict:
        from concurrent.futures import Future, ThreadPoolExecutor

        rec = run.recorder
        # a view's frame is detected, logged and added to the graph (unsolved) in one worker thread
        # while the devices move on to the next view (in view order; the recorder is thread-safe,
        # and nothing else touches the graph until the round's solve): the round then costs its
        # moves, one detection and the solve, not its moves plus every detection and every view's
        # factors.  A failure part-way stops the run, whose resume rebuilds the graph from its
        # checkpoint, so a round's views never stay in the graph unsolved.
        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="borg-detect")
        pending: list[Future[tuple[dict[str, Any], float]]] = []
        self.measure.begin_round(name)
        try:
            for j, view in enumerate(views_planned):
                k = first_k + j
                frame, world_T_camera = self._capture(run, view, spec.index, attempt, k)
                # truth, for scoring and the bound only (the estimator never reads it), taken now:
                # the world moves on with the devices
                truth = self._truth_at_capture() if self.bench.simulated else None
                pending.append(pool.submit(self._view_into_graph, rec, view, frame, world_T_camera, truth,
                                           {"module": name, "step": spec.index, "attempt": attempt, "round": rnd,
                                            "view": k}))
            done = [f.result() for f in pending]        # a worker's exception is raised here
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
        views = [record for record, _ in done]
        for record in views:
            self._take_truth(record)
        self.views_done.extend(views)
        self._check_rig_agrees(views)
        t0 = time.perf_counter()
        self.measure.end_round(name)
        solve_s = time.perf_counter() - t0
        self._check_structure_fits()
        rec.log_metric("slam/update_s", solve_s, "s")
        rec.log_metric("slam/views_s", sum(s for _, s in done), "s")
        result = self.measure.verdict(name)
        self._log_estimates(run, set(self.model.module_by_name[name].tags))
        for pose, cov in self.measure.camera_estimates():
            rec.log_pose(topics.estimate_topic("camera"), pose, "structure", covariance6x6=cov)
        return result

    def _truth_at_capture(self) -> dict[str, Any]:
        world = self.bench.sim.world
        return {"structure_T_camera": world.world_T_structure().inverse().compose(world.world_T_camera()),
                "camera": world.camera, "tags": world.tags_in_view()}

    def _view_into_graph(self, rec: Any, view: View, frame: Any, world_T_camera: Any,
                         truth: dict[str, Any] | None, ids: dict[str, Any]) -> tuple[dict[str, Any], float]:
        """`_view_record`, then the view into the graph, unsolved: the record, and the seconds the
        graph took (the round's `slam/views_s`)."""
        record, detections = self._view_record(rec, view, frame, world_T_camera, truth, ids)
        t0 = time.perf_counter()
        self.measure.add_view(record, detections)
        return record, time.perf_counter() - t0

    def _view_record(self, rec: Any, view: View, frame: Any, world_T_camera: Any, truth: dict[str, Any] | None,
                     ids: dict[str, Any]) -> tuple[dict[str, Any], list[Any]]:
        """Detect one view's frame, log it, and make its record (what the checkpoint and a resume
        read), with the detections the graph takes parsed back from that record: the same numbers
        a resume reads (the pose goes through its quaternion), parsed here, while the devices
        move, rather than in the SLAM step."""
        t = frame.t_s
        rec.log_image(topics.CAMERA_IMAGE, frame.image, t, "camera", format=IMAGE_FORMAT)
        world_T_structure = self.model.world_T_structure(view.turntable_rad)
        structure_T_camera = world_T_structure.inverse().compose(world_T_camera)
        rec.log_transform("world", "structure", world_T_structure, t)
        rec.log_transform("world", "camera", world_T_camera, t)
        detections, behind = self.measure.detect(frame.image, structure_T_camera)
        rec.log_record(topics.DETECTIONS, self.measure.detections_message(detections, t))
        record = {**ids, "turntable_rad": view.turntable_rad, "stewart_pose": list(view.stewart_pose),
                  "lift_m": view.lift_m,
                  "structure_T_camera": structure_T_camera.matrix().tolist(),
                  "detections": self.measure.detections_to_json(detections),
                  # read but not used, partly behind another tag: what a verdict says of a tag it missed
                  "hidden_behind": {str(t): by for t, by in sorted(behind.items())}}
        if truth is not None:
            # kept in the view's record so that a resumed run can still score its later steps
            record["truth"] = {"structure_T_camera": truth["structure_T_camera"].matrix().tolist(),
                               "corner_sq_px2": _corner_errors_sq(truth["camera"], truth["tags"], detections,
                                                                  self.measure.detector_camera)}
        return record, self.measure.detections_from_json(record["detections"])

    def _check_rig_agrees(self, views: list[dict[str, Any]]) -> None:
        """Before the round's views are solved: the rim tags where the calibration puts them, else
        the run stops naming the rig, not the structure (procedures/rig_consistency.py)."""
        if self.rig_calibration is None or self.uncalibrated:
            return
        from procedures.rig_consistency import turntable_disagreement

        bad = turntable_disagreement(views, self.rig_geometry, self.rig_calibration, self.intrinsics.dist,
                                     self.calibration_source)
        if bad is not None:
            raise StopRun(bad.reason)

    def _check_structure_fits(self) -> None:
        """After the update: most of the structure off the design's shape is the rig's doing."""
        from procedures.rig_consistency import structure_disagreement

        bad = structure_disagreement(self.measure.slam.tag_estimates(), self.model, self.measure.cutoff_m,
                                     self.calibration_source)
        if bad is not None:
            raise StopRun(bad.reason)

    def _capture(self, run: RunContext, view: View, step: int, attempt: int, k: int):
        from procedures.moves import Move, move_together

        devices = self.bench.devices
        tt, st, cam, lift = devices.turntable, devices.stewart, devices.camera, devices.lift
        if lift is None and view.lift_m:
            raise UserError(f"view {view.label} needs a lift and rig {self.bench.rig.name!r} has none")
        # the devices that must move for this view move at once (procedures/moves.py): a failure of
        # one stops the others; where each is is known again only once all have arrived
        moves = []
        if lift is not None and view.lift_m != self._lift_at:
            self.bench.moved.add(lift.name)
            moves.append(Move(lift, f"lift to {view.lift_m * 1000:+.0f} mm",
                              lambda progress: lift.move_to(view.lift_m, progress)))
        if view.turntable_rad != self._turntable_at:
            moves.append(Move(tt, f"turntable to {np.degrees(view.turntable_rad):+.0f} deg",
                              lambda progress: tt.move_to(view.turntable_rad, progress)))
        if tuple(view.stewart_pose) != self._stewart_at:
            moves.append(Move(st, "Stewart platform", lambda progress: st.move_to(view.stewart_pose, progress)))
        if moves:
            self._lift_at, self._turntable_at, self._stewart_at = None, None, None
            move_together(run, moves)
            self._lift_at = view.lift_m if lift is not None else None
            self._turntable_at, self._stewart_at = view.turntable_rad, tuple(view.stewart_pose)
        if self.bench.simulated:
            # the simulated camera's noise for this view depends only on (seed, step, attempt, view)
            self.bench.sim.world.reseed_camera([self.bench.scenario.seed, _STREAM_CAMERA, step, attempt, k])
        t0 = time.monotonic()
        frame = cam.grab()
        run.recorder.log_metric("camera/grab_s", time.monotonic() - t0, "s")
        world_T_camera = self.camera_model.world_T_camera(view)
        return frame, world_T_camera

    def _log_estimates(self, run: RunContext, module_tags: set[int]) -> None:
        """Every tag's estimated pose every round; the covariances of the module's tags (the
        verdict's, read already), and of every tag at the first round and then every
        FULL_COVARIANCE_EVERY rounds, or every tags / FULL_COVARIANCE_PER_ROUND rounds when that is
        more.  Each covariance is a marginal of the whole graph, recomputed after every update (the
        rig at the Bayes tree's root moves each round), at a cost that grows with the graph: logging
        those of every tag a round saw, as before, was 36 % of an N = 9 run's CPU (~3 ms a tag at
        N = 5, each round's views seeing 15-100 tags); spaced so, a full set costs about
        FULL_COVARIANCE_PER_ROUND marginals a round on average at any size."""
        n_tags = len(self.measure.slam.tag_estimates())
        every = max(FULL_COVARIANCE_EVERY, math.ceil(n_tags / FULL_COVARIANCE_PER_ROUND))
        full = self._rounds_since_full is None or self._rounds_since_full + 1 >= every
        self._rounds_since_full = 0 if full else self._rounds_since_full + 1
        estimates = self.measure.tag_estimates(None if full else module_tags)
        # a settled tag's estimate no longer moves and has no marginal in the solver: its last
        # logged pose and covariance stand (docs/sf_graphslam.md, "Settling what is built")
        settled = self.measure.slam.settled
        estimates = {t: e for t, e in estimates.items() if t not in settled}
        if estimates:
            poses = {tid: p for tid, (p, _) in estimates.items()}
            covs = {tid: c for tid, (_, c) in estimates.items() if c is not None}
            run.recorder.log_tag_estimates(poses, "structure", covariances=covs)

    def _log_verdict(self, run: RunContext, index: int, r: Verdict) -> None:
        run.recorder.log_record(topics.VERDICTS, m.verdict_message(
            r, index, self.model.module_by_name[r.module].tags, sorted(self.measure.rejected_tags)))
        run.recorder.log_text("info", f"module {r.module}: {r.verdict}{' - ' + r.reason if r.reason else ''}")
        # the console: the verdict row as soon as it is decided (the header before the first),
        # then what changed with it: tags rejected in this step, a re-measure
        console = console_of(run)
        if not self._row_header_shown:
            console.line(BORG_HEADER)
            self._row_header_shown = True
        if r.attempts > 1:
            console.warn(f"module {r.module} re-deployed by the operator; measured again (attempt {r.attempts})")
        console.line(borg_row(r.summary_row()))
        new = sorted(self.measure.rejected_tags - self._rejected_reported)
        if new:
            console.warn(f"tag{'s' if len(new) > 1 else ''} {', '.join(map(str, new))} rejected as displaced "
                         f"(does not fit the design while the rest of the structure does)")
        self._rejected_reported = set(self.measure.rejected_tags)

    def _truth_error(self, r: Verdict) -> TruthError | None:
        """Simulation: the module's estimate against where the world really put it."""
        if r.estimate is None:
            return None
        truth = self.bench.sim.world.borg.structure_T_module(r.module)
        position_m, rotation_rad = pose_error(r.estimate, truth)
        e = r.estimate.translation() - truth.translation()
        nees = None if r.position_covariance is None else float(e @ np.linalg.solve(r.position_covariance, e))
        return TruthError(position_m, rotation_rad, tuple(float(x) for x in e), nees)

    # ---- checkpoints -------------------------------------------------------------------------
    def checkpoint(self) -> dict[str, Any]:
        from procedures.runner import EncodedList

        if self._views_encoded is None or self._views_encoded.items is not self.views_done:
            self._views_encoded = EncodedList(self.views_done)
        return {"views": self._views_encoded, "results": {k: v.checkpoint_json() for k, v in self.results.items()},
                "placed": list(self.bench.sim.world.borg.placed) if self.bench.simulated else [],
                "homed": self.homed,
                # the survey's inputs, not its result: a resumed run solves them again and gets the
                # same calibration bit for bit (a rounded copy would move every later estimate)
                "rig_survey_views": self.rig_survey_views,
                "rig_survey": self.rig_survey_result,
                # the measured modules' floors: a resumed run plans the rest as this one would
                "plan_floor_m2": list(self._floor_m2)}

    def restore(self, state: dict[str, Any], steps_done: list[StepSpec], run: RunContext) -> None:
        """Replay the completed steps' views into a fresh estimator, step by step as they happened,
        so the estimate (and every later verdict) is the one an uninterrupted run would have."""
        self.views_done = list(state.get("views", []))
        self._floor_m2 = [float(x) for x in state.get("plan_floor_m2", [])]
        self._true_cameras, self._corner_sq = [], []
        for v in self.views_done:
            self._take_truth(v)
        self.replay_estimator(state)
        self.results = {k: self._restored_result(k, v) for k, v in state.get("results", {}).items()}
        if self.bench.simulated:
            for name in state.get("placed", []):
                self.bench.sim.world.borg.place(name)
            for name, r in self.results.items():
                if r.attempts > 1 and r.verdict != FLAGGED:
                    self._redeploy_in_world(name)
        self.homed = False   # a new session: home again before moving

    def replay_estimator(self, state: dict[str, Any], timed: Callable[[str, Callable[[], Any]], Any] | None = None,
                         rounds: int | None = None) -> None:
        """A fresh estimator given a checkpoint's inputs as the run gave them: the rig survey's views
        solved again, then each round's views, each module's verdict once its last round is in, and
        its release.  `timed(part, call)` runs each part ("survey", "step", "verdict", "release"):
        `lab bench replay` times them; `rounds` stops after that many (a replay's first part)."""
        from procedures.borg_measure import Measurement
        from procedures.rig_survey import views_from_json

        timed = timed or (lambda _part, call: call())
        if state.get("rig_survey_views") is not None:
            self.rig_survey_views = state["rig_survey_views"]
            timed("survey", lambda: self._solve_rig_survey(views_from_json(self.rig_survey_views)))
            self.rig_survey_result = state.get("rig_survey")
        self.measure = Measurement(self.model, self.intrinsics, self.measure.config, rig=self._rig_model(),
                                   calibration=self.rig_calibration)
        self.measure.tolerances = self.tolerances
        order = views_by_round(state.get("views", []))
        for i, ((step, attempt, rnd), views) in enumerate(order[:rounds]):
            module = views[0]["module"]
            if attempt > 1 and rnd == 0:
                self.measure.redeploy(module)
            timed("step", lambda: self.measure.add_step(module, views))
            if i + 1 == len(order) or order[i + 1][0][:2] != (step, attempt):
                # as the live run did once the step's verdict was final (a step cut off mid-way is
                # re-run from its start, so every replayed step was finished)
                timed("verdict", lambda: self.measure.verdict(module))
                timed("release", lambda: self.measure.finish(module))

    def _restored_result(self, name: str, d: dict[str, Any]) -> Verdict:
        """A completed step's verdict from the checkpoint, with this run's tolerance for its type (a
        module outside the plan has none: the summary lists only planned modules)."""
        mod = self.model.module_by_name.get(name)
        if mod is None:
            return Verdict.from_checkpoint(d, None, None)
        tol = self.measure.tolerances.of(mod.kind)
        return Verdict.from_checkpoint(d, tol.position_m, tol.rotation_rad)

    # ---- the end -------------------------------------------------------------------------------
    def summary(self, result: str, reason: str) -> dict[str, Any]:
        modules = [self.results[mod.name].summary_row() for mod in self.modules if mod.name in self.results]
        return {"result": result, "reason": reason, "structure": f"borg:{self.model.n}", "on_flag": self.on_flag,
                "calibration": ("none (rig file trusted)" if self.uncalibrated else
                                "survey" if self.rig_survey else "file" if self.rig_calibration is not None
                                else "nominal priors"),
                "observation": self.measure.slam.config.observation,
                "simulated": self.bench.simulated, "modules": modules,
                # the module 1-sigma each step's views were planned for (`borg_table` says how many reached it)
                "sigma_target_m": self.precision.sigma_m,
                "rejected_tags": sorted(self.measure.rejected_tags), "steps": len(modules),
                "views": len(self.views_done), "rig_survey": self.rig_survey_result,
                # simulation: the detector's corner error against the truth (per coordinate), the
                # noise the bound assumes
                "corner_rms_px": float(np.sqrt(np.mean(self._corner_sq))) if self._corner_sq else None,
                # the corner noise the run's own residuals imply, and what the graph assumed
                "corner_noise": noise.to_json() if (noise := self.measure.slam.corner_noise()) is not None else None,
                # what the graph took of the views' sightings (Measurement.near_sightings); a
                # resumed run counts those it replayed too
                "sightings": {"near_tags_per_view": self.measure.near_tags_per_view, "in_graph": self.measure.sightings[0],
                              "detected": self.measure.sightings[1]},
                # the layers summarised out of the incremental solver (Measurement.settle_built)
                "settled": {"after_layers": self.measure.settle_after_layers, "tags": len(self.measure.slam.settled),
                            "layers_below": self.measure.settled_below},
                "rig_calibration_file": str(self.bench.rig.calibration.file) if self.bench.rig.calibration.file else None,
                # simulation, once the run has ended: the graph's rig against the truth (its NEES)
                "rig_in_graph": self._rig_in_graph() if result != "running" else None}

    def _rig_in_graph(self) -> dict[str, Any] | None:
        if not self.bench.simulated or self.measure.slam.rig is None:
            return None
        from procedures.rig_survey import graph_against_truth

        return graph_against_truth(self.measure.slam, self.bench.sim.world)

    def stop_devices(self) -> list[str]:
        return self.bench.stop_moved()

    def close(self) -> None:
        self.bench.close()


def _angles_apart(angles: list[float], separation: float) -> int:
    """How many of `angles` (rad) stand at least `separation` from each other, counted from the
    smallest up (the planner's test of distinct turntable angles)."""
    count, last = 0, -math.inf
    for a in sorted(angles):
        if a - last >= separation:
            count, last = count + 1, a
    return count


def parse_tolerances(items: list[str], config: VerificationConfig) -> Tolerances:
    """The rig's [verification] tolerances with `--tolerance KIND=MM,DEG` overrides."""
    tol = {k: Tolerance(t.position_m, t.rotation_rad, config.band_sigmas) for k, t in config.tolerances.items()}
    for item in items:
        kind, eq, value = item.partition("=")
        kinds = list(MODULE_KINDS) if kind.strip() == "all" else [kind.strip()]
        parts = value.split(",")
        if not eq or any(k not in MODULE_KINDS for k in kinds) or len(parts) != 2:
            raise UserError(f"--tolerance {item!r}: expected KIND=MM,DEG with KIND one of {', '.join(MODULE_KINDS)} "
                            f"or all, e.g. closeout_square=5,1")
        try:
            mm, deg = (float(p) for p in parts)
        except ValueError:
            raise UserError(f"--tolerance {item!r}: {value!r} is not two numbers (MM,DEG)") from None
        if not (math.isfinite(mm) and math.isfinite(deg) and 0 < mm <= 1000 and 0 < deg <= 90):
            raise UserError(f"--tolerance {item!r}: needs 0 < MM <= 1000 and 0 < DEG <= 90")
        for k in kinds:
            tol[k] = Tolerance(mm * 1e-3, math.radians(deg), config.band_sigmas)
    return Tolerances(**tol)


def _corner_errors_sq(cam: Any, tags_in_view: list, detections: list,
                      camera: tuple[np.ndarray, np.ndarray]) -> list[float]:
    """Simulation: squared pixel errors (u and v apart) of the detected corners against the true
    projection (`cam`: the world's true camera, `tags_in_view`: its (id, size, camera_T_tag) when
    the frame was taken), each sighting's scaled to face-on by the graph's obliquity model; too
    oblique sightings, which the graph leaves out, are left out here too."""
    import cv2

    from estimation.fiducials import tag_object_points
    from estimation.rig_model import MIN_SIDE_RATIO, OBLIQUE_EXPONENT, side_ratio

    truth = {tid: (size, pose) for tid, size, pose in tags_in_view}
    out: list[float] = []
    for d in detections:
        if d.tag_id not in truth:
            continue
        size, camera_T_tag = truth[d.tag_id]
        rvec, _ = cv2.Rodrigues(camera_T_tag.rotation().matrix())
        uv, _ = cv2.projectPoints(tag_object_points(size), rvec, camera_T_tag.translation(), cam.K, cam.dist)
        err = uv.reshape(-1, 2) - np.asarray(d.corners_px).reshape(-1, 2)
        ratio = side_ratio(d.corners_px, *camera)
        if np.abs(err).max() < 3.0 and ratio >= MIN_SIDE_RATIO:   # a displaced tag is not a corner error
            out += ((err * ratio ** OBLIQUE_EXPONENT) ** 2).ravel().tolist()   # per coordinate, as the factor's sigma
    return out


def _rig_survey_line(sol: Any) -> str:
    """One line for the operator: what the rig survey found and how well."""
    cal = sol.calibration
    sd = cal.sigmas()

    def worst(name: str) -> str:
        return f"{max(sd[name]['xyz_mm']):.2f} mm / {max(sd[name]['rot_deg']):.3f} deg"
    return (f"rig calibration from {cal.views} views (corner rms {cal.rms_px:.2f} px): 1 sigma mount "
            f"{worst('platform_T_camera')}, Stewart base {worst('world_T_base')}, focal "
            f"{100 * sd['K']['fx_px'] / cal.K[0, 0]:.3f} %" + ("" if sol.ok else f"; {len(sol.problems)} warning(s) above"))


def behind_note(views: list[dict[str, Any]], tag: int, module_of: dict[int, str]) -> str:
    """What hid `tag` in `views` where it was read but dropped as partly behind another tag (the
    views' "hidden_behind", `fiducials.hidden_behind`): ", read in 12 more but partly behind tag
    523 (396S)", or nothing."""
    by = Counter(v.get("hidden_behind", {}).get(str(tag)) for v in views)
    by.pop(None, None)
    if not by:
        return ""
    front = ", ".join(f"{t} ({module_of[t]})" if t in module_of else str(t) for t, _ in by.most_common())
    return f", read in {sum(by.values())} more but partly behind tag {front}"
