"""IPJR truss assembly (`lab run truss NAME`): one step per node of the assembly plan.

For each step <f, (i, j, k)>: the lengths to command come from the current estimate of the base and
f's design position; each IPJR is centred, attached to its strut (the operator sets the strut
coarsely and measures it with the ruler: the paper's initial M_L), and runs the paper's length
controller over its own transport; the operator fixes the node; every strut between f and the
built structure is measured; the estimator (MLE, EKF or open loop) re-estimates every node.

In simulation the operator's hands and ruler are the simulated world's: the coarse strut length,
the fixing error (sigma_L) and the ruler's error (sigma_M) are drawn from the scenario's seed,
per step, so a step re-run after an interruption draws the same numbers.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from estimation.truss_geometry import DegenerateBaseError, Plan, Step, place_step
from estimation.truss_simulation import make_estimator
from lab.core.errors import UserError
from lab.core.files import read_json
from lab.core.recorder import messages as m
from lab.core.recorder import topics
from lab.core.structures.trusses import build_truss
from procedures.runner import RunContext, StepSpec
from procedures.setup import Bench

ESTIMATORS = {"mle": "mle", "ekf": "ekf", "open-loop": "open_loop"}
CENTRE_EXTENSION = 0.5        # fraction of the stroke the actuator is centred at before attaching
COARSE_SET_M = 0.015          # how close the operator sets a strut by hand before the IPJR takes over
_STREAM = 7100                # RNG stream of the simulated operator (per step: [seed, _STREAM, step])
_STREAM_IPJR = 7200           # RNG stream of the simulated IPJRs' noise (per step: [seed, _STREAM_IPJR, step, k])


def load_plan(path: str | Path) -> Plan:
    """A plan written by `lab plan truss NAME --json`."""
    doc = read_json(path, "plan")
    try:
        steps = [Step(int(s["node"]), tuple(int(b) for b in s.get("base", ()))) for s in doc["steps"]]
        return Plan(tuple(steps))
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"plan {path}: not a plan from `lab plan truss --json`: {exc}") from None


class TrussProcedure:
    name = "truss"

    def __init__(self, bench: Bench, structure: str, estimator: str = "mle", plan_file: str | None = None,
                 plan_seed: int = 0) -> None:
        if estimator not in ESTIMATORS:
            raise UserError(f"--estimator must be one of {', '.join(ESTIMATORS)}, got {estimator!r}")
        self.bench = bench
        self.structure = structure
        self.estimator_name = estimator
        self.model = build_truss(structure)
        if plan_file:
            self.plan_obj = load_plan(plan_file)
            from estimation.sequencing import validate_plan

            problems = validate_plan(self.model, self.plan_obj)
            if problems:
                raise UserError(f"plan {plan_file} does not fit {structure}: {problems[0]}")
        else:
            from estimation.sequencing import Planner

            self.plan_obj = Planner(self.model).locally_optimal(np.random.default_rng(plan_seed)).plan
        noise = bench.scenario.truss
        self.sigma_L, self.sigma_M = noise.sigma_length_m, noise.sigma_measure_m
        self.ipjr_names = sorted(bench.devices.ipjrs) if bench.devices else []
        if len(self.ipjr_names) < 3:
            raise UserError(f"rig {bench.rig.name!r} has {len(self.ipjr_names)} IPJRs; a tetrahedral truss needs 3")
        self._new_estimator()
        self.truth = np.full((self.model.n_nodes, 3), np.nan)   # simulation only
        self.records: list[dict[str, Any]] = []                  # per completed step, for checkpoints

    def _new_estimator(self) -> None:
        self.est = make_estimator(ESTIMATORS[self.estimator_name], self.model, self.plan_obj, self.sigma_L, self.sigma_M)

    # ---- the plan ------------------------------------------------------------------------------
    def plan(self) -> list[StepSpec]:
        return [StepSpec(k, f"node {s.node}", {"node": s.node, "base": list(s.base)})
                for k, s in enumerate(self.plan_obj.steps)]

    def dry_run_problems(self, steps: list[StepSpec]) -> list[str]:
        """Every strut must be reachable by an IPJR attached with its actuator centred and the strut
        set coarsely by hand; the plan must be buildable; the IPJRs must exist.  Nothing is sent
        to any device."""
        from estimation.sequencing import validate_plan

        problems = list(validate_plan(self.model, self.plan_obj))
        for name in self.ipjr_names:
            cfg = self.bench.rig.ipjrs[name]
            half = CENTRE_EXTENSION * cfg.stroke_m
            # the fixing error (sigma_L) comes after the IPJR lets go, so only the hand setting and
            # the controller's tolerance must fit in half the stroke from the centred actuator
            if COARSE_SET_M + cfg.tolerance_m > half:
                problems.append(f"{name}: half its {cfg.stroke_m * 1000:g} mm stroke cannot absorb the hand setting "
                                f"(+-{COARSE_SET_M * 1000:g} mm)")
        for s in self.plan_obj.steps:
            if len(s.base) > len(self.ipjr_names):
                problems.append(f"node {s.node} needs {len(s.base)} IPJRs, the rig has {len(self.ipjr_names)}")
            for b in s.base:
                length = float(np.linalg.norm(self.model.nodes[s.node] - self.model.nodes[b]))
                if not length > 0:
                    problems.append(f"strut {b}-{s.node}: zero nominal length")
        return problems

    # ---- one step ------------------------------------------------------------------------------
    def execute(self, spec: StepSpec, run: RunContext) -> None:
        step = self.plan_obj.steps[spec.index]
        rng = np.random.default_rng([self.bench.scenario.seed, _STREAM, spec.index])
        if self.bench.simulated:   # the actuators' noise is drawn per step too: a re-run step repeats it
            for k, name in enumerate(self.ipjr_names):
                self.bench.sim.world.ipjrs[name].reseed([self.bench.scenario.seed, _STREAM_IPJR, spec.index, k])
        rec = run.recorder
        commanded = np.asarray(self.est.lengths_to_command(step), dtype=float)
        achieved = []
        for k, (b, L) in enumerate(zip(step.base, commanded)):
            achieved.append(self._set_strut(run, rng, self.ipjr_names[k], b, step.node, float(L), spec.index))
        run.operator.confirm(f"Fix node {step.node} (struts to {', '.join(map(str, step.base)) or 'nothing'})")
        if self.bench.simulated:
            self._fix_in_world(step, achieved, rng)
        measured = self._measure(run, rng, step, spec.index)
        self.est.add_step(step, commanded, measured)
        self.records.append({"node": step.node, "commanded": commanded.tolist(),
                             "measured": [[f, i, v] for (f, i), v in measured.items()],
                             "truth": None if np.isnan(self.truth[step.node]).any() else self.truth[step.node].tolist()})
        self._log_estimate(rec, spec.index)

    def _set_strut(self, run: RunContext, rng: np.random.Generator, name: str, base: int, node: int,
                   length: float, index: int) -> float:
        ipjr = self.bench.devices.ipjrs[name]
        cfg = ipjr.config
        self.bench.moved.add(name)
        run.progress(f"node {node}: {name} on strut {base}-{node}")
        ext = ipjr.measure_extension()
        n = int(round((CENTRE_EXTENSION * cfg.stroke_m - ext) / cfg.step_m))
        if abs(n) >= 1:
            with run.move(f"{name} centring") as progress:
                ipjr.step(n, progress)
        coarse = length + rng.uniform(-COARSE_SET_M, COARSE_SET_M)
        ruler = coarse + rng.normal(0.0, self.sigma_M)
        if self.bench.simulated:
            self.bench.sim.world.ipjrs[name].attach(coarse)
        reading = run.operator.ask_length(
            f"Attach {name} to strut {base}-{node}, set the strut by hand to about {length * 1000:.1f} mm and "
            f"measure it (mm)", default_m=ruler if self.bench.simulated else None)
        ipjr.attach(reading)
        with run.move(f"{name} to {length * 1000:.1f} mm") as progress:
            result = ipjr.set_length(length, progress)
        run.recorder.log_record(topics.LENGTHS, m.LengthMeasurement(
            strut=f"{base}-{node}", node_a=base, node_b=node, device=name,
            nominal_m=float(np.linalg.norm(self.model.nodes[node] - self.model.nodes[base])),
            commanded_m=length, measured_m=result.length_m, sigma_m=cfg.tolerance_m))
        run.recorder.log_metric(f"ipjr/{name}/controller_moves", float(result.tries), "moves")
        return result.length_m

    def _fix_in_world(self, step: Step, achieved: list[float], rng: np.random.Generator) -> None:
        """The simulated node as fixed: each active strut at the length its IPJR really set, plus the
        fixing error sigma_L; where those struts cannot meet over the real base, the step is redone
        (the noise redrawn), as the operator would."""
        true_set = [self.bench.sim.world.ipjrs[self.ipjr_names[k]].strut_length_m() for k in range(len(step.base))]
        for name in self.ipjr_names[:len(step.base)]:
            self.bench.sim.world.ipjrs[name].detach()
        base = [self.truth[b] for b in step.base]
        for _ in range(100):
            lengths = np.asarray(true_set) + rng.normal(0.0, self.sigma_L, size=len(true_set))
            try:
                self.truth[step.node] = place_step(base, lengths)
                return
            except DegenerateBaseError:
                continue
        raise UserError(f"node {step.node}: the struts as set cannot meet over the built base")

    def _measure(self, run: RunContext, rng: np.random.Generator, step: Step, index: int) -> dict[tuple[int, int], float]:
        measured: dict[tuple[int, int], float] = {}
        for f, i in self.est.struts_to_measure(step):
            true = (float(np.linalg.norm(self.truth[f] - self.truth[i])) + rng.normal(0.0, self.sigma_M)
                    if self.bench.simulated else None)
            value = run.operator.ask_length(f"Measure strut {i}-{f} with the ruler (mm)", default_m=true)
            measured[(f, i)] = value
            run.recorder.log_record(topics.LENGTHS, m.LengthMeasurement(
                strut=f"{i}-{f}", node_a=i, node_b=f, device="ruler",
                nominal_m=float(np.linalg.norm(self.model.nodes[f] - self.model.nodes[i])),
                measured_m=value, sigma_m=self.sigma_M))
        return measured

    def _log_estimate(self, rec: Any, index: int) -> None:
        x = self.est.estimate()
        built = [n for n in self.plan_obj.order if not np.isnan(x[n]).any()]
        doc: dict[str, Any] = {"step": index, "estimate_m": {str(n): x[n].tolist() for n in built}}
        if hasattr(self.est, "covariances"):
            try:
                doc["covariance_trace_m2"] = {str(n): float(np.trace(c)) for n, c in self.est.covariances().items()}
            except Exception as exc:  # a covariance we can't compute is reported, not fatal
                doc["covariance_error"] = str(exc)
        rec.log_json("truss_estimate", doc)
        if self.bench.simulated and built:
            err = self._errors(built)
            rec.log_metric("truss/rms_node_error_m", float(np.sqrt(np.mean(np.square(err)))), "m")

    def _errors(self, nodes: list[int]) -> np.ndarray:
        return np.array([float(np.linalg.norm(self.truth[n] - self.est.nominal[n])) for n in nodes])

    # ---- checkpoints -------------------------------------------------------------------------
    def checkpoint(self) -> dict[str, Any]:
        state: dict[str, Any] = {"records": self.records,
                                 "truth": np.where(np.isnan(self.truth), None, self.truth).tolist()}
        if self.bench.simulated:   # simulation truth, like `truth`: where each actuator's rod is
            state["sim_extensions_m"] = {n: a.extension_m() for n, a in self.bench.sim.world.ipjrs.items()}
        return state

    def restore(self, state: dict[str, Any], steps_done: list[StepSpec], run: RunContext) -> None:
        """Replay the completed steps into a fresh estimator: same inputs, same estimate."""
        self._new_estimator()
        self.records = list(state.get("records", []))
        if len(self.records) != len(steps_done):
            raise ValueError(f"{len(self.records)} step records for {len(steps_done)} completed steps")
        truth = np.array([[np.nan if v is None else v for v in row] for row in state["truth"]], dtype=float)
        if truth.shape != self.truth.shape:
            raise ValueError(f"truth has shape {truth.shape}, the truss {self.truth.shape}")
        self.truth = truth
        if self.bench.simulated:
            for name, ext in state.get("sim_extensions_m", {}).items():
                self.bench.sim.world.ipjrs[name].set_extension(float(ext))
        for spec, rec in zip(steps_done, self.records):
            step = self.plan_obj.steps[spec.index]
            measured = {(int(f), int(i)): float(v) for f, i, v in rec["measured"]}
            self.est.add_step(step, rec["commanded"], measured)

    # ---- the end -------------------------------------------------------------------------------
    def summary(self, result: str, reason: str) -> dict[str, Any]:
        built = [r["node"] for r in self.records]
        nodes = []
        if self.bench.simulated:
            errs = self._errors(built) if built else np.array([])
            nodes = [{"id": n, "error_m": float(e)} for n, e in zip(built, errs)]
            est = self.est.estimate()
            for d, n in zip(nodes, built):
                d["estimate_error_m"] = float(np.linalg.norm(est[n] - self.truth[n]))
            rms = float(np.sqrt(np.mean(np.square(errs)))) if built else float("nan")
        else:
            cov = self.est.covariances() if hasattr(self.est, "covariances") else {}
            nodes = [{"id": n, "error_m": None, "sigma_m": float(math.sqrt(np.trace(cov[n]))) if n in cov else None}
                     for n in built]
            rms = None
        return {"result": result, "reason": reason, "structure": self.structure, "estimator": self.estimator_name,
                "nodes": nodes, "rms_node_error_m": rms, "steps": len(built),
                "sigma_length_m": self.sigma_L, "sigma_measure_m": self.sigma_M}

    def stop_devices(self) -> list[str]:
        return self.bench.stop_moved()

    def close(self) -> None:
        self.bench.close()
