"""`lab bench mle`: the IPJR paper's studies on our truss models, measured here.

- tetrahelix20   MLE vs EKF vs open loop on the 20-node tetrahelix, 1 m struts, sigma_L = 0.1 m,
                 sigma_M = 0.01 m (paper §6.3, Fig. 8).
- telescope84    the 84-node telescope truss on a FindLocallyOptimalSequence plan with the paper's
                 sigma_L^2 = 3.57e-7 m^2, sigma_M^2 = 6.25e-8 m^2 (Fig. 7); iSAM2 update time;
                 camera fusion (beyond the paper).
- sequencing45   random vs greedy vs local search from any / central starting triangles on the
                 45-node telescope truss (Table 1, Fig. 6); FindLocallyOptimalSequence run time on
                 45 and 84 nodes.
- enumerate10    every sequence of the 10-node telescope truss; optimal vs median, open loop vs MLE
                 (§6.4, Fig. 9).

Writes mle.json, mle.md and PNG plots to --out (default bench_out/mle) and prints the Markdown
(or the JSON with --json).  Top-level imports stay light: the CLI imports this module for --help.

Trials run through `lab.core.executor` (--workers N local processes, default all cores, or --scheduler
tcp://HOST:PORT for Dask), the four studies at once; the figures for a seed are the same whichever
runs them.  An interrupted study keeps its finished trials in --out/trials.jsonl and the same
command resumes from them.
"""

from __future__ import annotations

import argparse
import json
import math
import functools
import os
import time
from dataclasses import dataclass
from typing import Any

from lab.studies.bench_common import save_figure
from lab.core.executor import Study, Trial, add_executor_arguments, make_trials, open_study, trial_seed

SIGMA_L_PAPER = math.sqrt(3.57e-7)
SIGMA_M_PAPER = math.sqrt(6.25e-8)
STUDIES = ("tetrahelix20", "telescope84", "sequencing45", "enumerate10")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="fewer trials and runs (under 3 minutes)")
    parser.add_argument("--json", action="store_true", help="print the JSON instead of the Markdown table")
    parser.add_argument("--out", default=os.path.join("bench_out", "mle"), help="output directory (default bench_out/mle)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--only", choices=list(STUDIES), action="append",
                        help="run only this study (repeatable)")
    add_executor_arguments(parser)


def _stats(values) -> dict:
    import numpy as np

    v = np.asarray(values, dtype=float)
    finite = v[np.isfinite(v)]
    return {"n": int(len(v)), "mean": float(np.mean(v)) if len(v) else math.nan,
            "sd": float(np.std(v, ddof=1)) if len(v) > 1 else 0.0,
            "median": float(np.median(finite)) if len(finite) else math.nan,
            "min": float(np.min(finite)) if len(finite) else math.nan,
            "max": float(np.max(finite)) if len(finite) else math.nan,
            "non_finite": int(len(v) - len(finite))}


def _mc_summary(mc, k: int) -> dict:
    return {"trace_node10_m2": mc.trace_upto(k), "trace_total_m2": mc.trace, "node10_mse_m2": float(mc.node_mse[k - 1]),
            "estimate_error_total_m2": float(mc.estimate_mse.sum()), "trials": mc.trials, "failures": mc.failures,
            "redraws": mc.redraws, "node_mse_m2": [float(v) for v in mc.node_mse]}


# ------------------------------------------------------------------------------------------------
# Trials.  Module-level functions of a `Trial` (workers import them by name), returning JSON.
# Every Monte Carlo trial draws from its own seed (`trial_seed(seed, stream, index)`) instead of
# one generator running through all trials as `truss_simulation.monte_carlo` does, so that the
# figures are the same whichever worker runs which trial.  Estimators compared on the same
# assemblies share a stream: trial i of open loop, EKF and MLE simulates with the same seed.


@dataclass(frozen=True)
class AssemblySpec:
    """One simulated assembly: the truss by name (each worker builds it once), its plan, the estimator."""

    truss: str
    plan: Any                                  # estimation.truss_geometry.Plan (frozen, picklable)
    kind: str                                  # open_loop, ekf, mle, mle_camera
    sigma_L: float
    sigma_M: float
    options: tuple[tuple[str, Any], ...] = ()  # estimator keywords, e.g. (("sigma_px", 0.3),)


@functools.lru_cache(maxsize=8)
def _truss(name: str):
    from lab.core.structures.trusses import build_truss

    return build_truss(name)


@functools.lru_cache(maxsize=8)
def _planner(name: str):
    # cached per process: its caches hold derivatives of the design, the same whoever asks first
    from estimation.sequencing import Planner

    return Planner(_truss(name))


def assembly_trial(trial: Trial) -> dict:
    """`simulate_assembly` with the trial's seed: errors in plan order, or failed (struts never met)."""
    import numpy as np

    from estimation.truss_geometry import DegenerateBaseError
    from estimation.truss_simulation import simulate_assembly

    s: AssemblySpec = trial.spec
    t0 = time.perf_counter()
    try:
        run = simulate_assembly(_truss(s.truss), s.plan, s.kind, s.sigma_L, s.sigma_M,
                                np.random.default_rng(trial.seed), **dict(s.options))
    except DegenerateBaseError:
        return {"failed": True, "seconds": time.perf_counter() - t0}
    order = s.plan.order
    return {"failed": False, "redraws": run.redraws, "errors_m": (run.truth - run.nominal)[order].tolist(),
            "estimate_sq_errors_m2": run.estimate_sq_errors[order].tolist(), "update_seconds": list(run.update_seconds),
            "seconds": time.perf_counter() - t0}


def plan_trial(trial: Trial) -> dict:
    """FindLocallyOptimalSequence on a truss (spec: its name) from the study's seed, timed on a
    fresh planner (cold caches, as a user's first call)."""
    import numpy as np

    from estimation.sequencing import Planner

    t0 = time.perf_counter()
    r = Planner(_truss(trial.spec)).locally_optimal(np.random.default_rng(trial.seed))
    return {"plan": r.plan.to_json(), "trace_unit": r.trace_unit, "history_unit": r.history,
            "seconds": time.perf_counter() - t0}


def sequencing_trial(trial: Trial) -> dict:
    """One run of the sequencing study from a starting triangle (spec: (truss, triangle)): a random
    sequence, greedy assembly, local search from the greedy plan (traces per unit sigma_L^2)."""
    import numpy as np

    from estimation.sequencing import random_sequence

    name, tri = trial.spec
    planner = _planner(name)
    p = random_sequence(planner.model, tri, "any", np.random.default_rng(trial.seed), planner.geometry)
    out: dict = {"random_unit": planner.trace_unit(p) if p is not None else math.inf}
    g = planner.greedy(tri)
    if g is not None:
        r = planner.local_search(g.plan)
        out.update(greedy_unit=g.trace_unit, local_unit=r.trace_unit, history_unit=r.history,
                   final_triangle=list(r.plan.triangle))
    return out


def _plan_from_json(doc: dict):
    from estimation.truss_geometry import Plan, Step

    return Plan(tuple(Step(s["node"], tuple(s["base"])) for s in doc["steps"]))


def _monte_carlo(study: Study, seed: int, stream: str, runs: dict[str, AssemblySpec],
                 trials: int) -> tuple[dict[str, Any], dict[str, float]]:
    """{label: MonteCarlo} of `trials` assemblies per spec, and {label: the trials' summed seconds};
    all in one map (no worker idles between estimators); trial i of every label draws from seed
    `trial_seed(seed, stream, i)`."""
    import numpy as np

    from estimation.truss_simulation import MonteCarlo

    seeds = [trial_seed(seed, stream, i) for i in range(trials)]
    batch = [Trial(f"{stream}/{label}/{i}", seeds[i], spec) for label, spec in runs.items() for i in range(trials)]
    results = study.map(assembly_trial, batch, batch_size="auto")
    out, seconds = {}, {}
    for j, (label, spec) in enumerate(runs.items()):
        rs = results[j * trials:(j + 1) * trials]
        ok = [r for r in rs if not r["failed"]]
        if not ok:
            raise RuntimeError(f"every one of {trials} {spec.kind} trials failed to close")
        e = np.asarray([r["errors_m"] for r in ok])
        mc = MonteCarlo(spec.kind, trials, len(rs) - len(ok), sum(r["redraws"] for r in ok),
                        np.mean(np.sum(e ** 2, axis=2), axis=0), np.einsum("tni,tnj->nij", e, e) / len(e),
                        np.mean([r["estimate_sq_errors_m2"] for r in ok], axis=0),
                        [t for r in ok for t in r["update_seconds"]])
        out[label] = mc
        seconds[label] = sum(r["seconds"] for r in rs)   # the trials' own time, summed: one core's worth
    return out, seconds


# ------------------------------------------------------------------------------------------------
# Studies.  Each takes the `Study` its trials run in (default: this process, no journal).


def study_tetrahelix20(trials: int, seed: int, study: Study | None = None) -> dict:
    from estimation.truss_covariance import node_traces
    from estimation.truss_geometry import Plan, orient_base

    study = study or Study()
    m = _truss("tetrahelix:20")
    plan = Plan.from_triangle((0, 1, 2), [(k, orient_base(m.nodes, k, (k - 3, k - 2, k - 1))) for k in range(3, 20)])
    sL, sM = 0.1, 0.01
    analytic = node_traces(m.nodes, plan, sL)
    out: dict = {"truss": m.name, "sigma_L_m": sL, "sigma_M_m": sM, "trials": trials,
                 "paper_total_m2": {"open_loop": 28.76, "mle": 1.39, "ekf": 2.41}}
    kinds = ("open_loop", "ekf", "mle")
    mcs, trial_secs = _monte_carlo(study, seed, "tetrahelix20", {k: AssemblySpec(m.name, plan, k, sL, sM) for k in kinds},
                             trials)
    for kind in kinds:
        out[kind] = _mc_summary(mcs[kind], 10)
        out[kind]["trial_seconds"] = trial_secs[kind]
    out["open_loop"]["analytic_trace_node10_m2"] = float(analytic[:10].sum())
    out["open_loop"]["analytic_trace_total_m2"] = float(analytic.sum())
    out["open_loop"]["analytic_node_mse_m2"] = [float(v) for v in analytic]
    o, e, l = out["open_loop"], out["ekf"], out["mle"]
    out["checks"] = {
        "mle_le_ekf_le_open_loop_node10": bool(l["trace_node10_m2"] <= e["trace_node10_m2"] <= o["trace_node10_m2"]),
        "mle_le_ekf_le_open_loop_total": bool(l["trace_total_m2"] <= e["trace_total_m2"] <= o["trace_total_m2"]),
        "open_loop_over_mle_node10": o["trace_node10_m2"] / l["trace_node10_m2"],
        "open_loop_over_mle_total": o["trace_total_m2"] / l["trace_total_m2"],
    }
    return out


def study_telescope84(trials: int, fusion_trials: int, seed: int, study: Study | None = None) -> dict:
    import numpy as np

    from estimation.truss_covariance import LocalSensitivities, node_traces

    study = study or Study()
    m = _truss("telescope:84")
    # the plan is a trial too: a worker plans while the others run another study's trials
    res = study.map(plan_trial, [Trial("telescope84/plan", seed, m.name)])[0]
    plan = _plan_from_json(res["plan"])
    sL, sM = SIGMA_L_PAPER, SIGMA_M_PAPER
    sens = LocalSensitivities(m.nodes)
    analytic = node_traces(m.nodes, plan, sL, sens)[plan.order]
    # Perfect-knowledge floor: even with an exact estimate, each node keeps the error of its own
    # three struts relative to its base (sigma_L^2 ||C_f||^2).
    floor = sum(float(np.sum(sens.step(plan, k)[1] ** 2)) for k in range(len(plan.steps))) * sL ** 2
    out: dict = {"truss": m.name, "sigma_L2_m2": sL ** 2, "sigma_M2_m2": sM ** 2, "trials": trials,
                 "sequence": {"trace_m2": res["trace_unit"] * sL ** 2, "layers": len(plan.layers),
                              "seconds": res["seconds"], "descent_steps": len(res["history_unit"]) - 2},
                 "paper_m2": {"open_loop": 1.55e-3, "mle": 2.28e-4, "ekf": 2.29e-4},
                 "perfect_estimate_floor_m2": floor}
    n = m.n_nodes
    kinds = ("open_loop", "ekf", "mle")
    mcs, trial_secs = _monte_carlo(study, seed, "telescope84", {k: AssemblySpec(m.name, plan, k, sL, sM) for k in kinds},
                             trials)
    for kind in kinds:
        mc = mcs[kind]
        s = out[kind] = _mc_summary(mc, 10)
        s["trace_m2"] = mc.trace
        s["trial_seconds"] = trial_secs[kind]
        if kind != "open_loop":
            secs = np.asarray(mc.update_seconds)
            last = secs[n - 1::n] * 1e3  # the update that adds node 84 (84 nodes in the graph)
            s["update_ms_median"] = float(np.median(secs) * 1e3)
            s["update_ms_at_84_median"] = float(np.median(last))
            s["update_ms_at_84_p95"] = float(np.percentile(last, 95))
            s["update_ms_max"] = float(np.max(secs) * 1e3)
    out["open_loop"]["analytic_trace_m2"] = float(analytic.sum())
    out["open_loop"]["analytic_node_mse_m2"] = [float(v) for v in analytic]
    fusion = {"cameras": 4, "camera": "4000x3000 px, f = 3000 px, ring above the truss; pose prior 0.01 rad, 5 cm",
              "trials": fusion_trials}
    runs = {"mle_only": AssemblySpec(m.name, plan, "mle", sL, sM)}
    for px in (1.0, 0.3, 0.1):
        runs[f"sigma_px_{px:g}"] = AssemblySpec(m.name, plan, "mle_camera", sL, sM, (("sigma_px", px),))
    fmc, _ = _monte_carlo(study, seed, "telescope84/fusion", runs, fusion_trials)
    fusion["mle_only"] = {"trace_m2": fmc["mle_only"].trace,
                          "estimate_error_total_m2": float(fmc["mle_only"].estimate_mse.sum())}
    for px in (1.0, 0.3, 0.1):
        mc = fmc[f"sigma_px_{px:g}"]
        fusion[f"sigma_px_{px:g}"] = {"trace_m2": mc.trace, "estimate_error_total_m2": float(mc.estimate_mse.sum()),
                                      "update_ms_median": float(np.median(mc.update_seconds) * 1e3),
                                      "node_mse_m2": [float(v) for v in mc.node_mse]}
    out["fusion"] = fusion
    out["checks"] = {"update_84_le_10ms": bool(out["mle"]["update_ms_at_84_median"] <= 10.0),
                     "mle_le_open_loop": bool(out["mle"]["trace_m2"] <= out["open_loop"]["trace_m2"])}
    return out


def study_sequencing45(runs: int, seed: int, study: Study | None = None) -> dict:
    import numpy as np

    from estimation.sequencing import all_central_triangles, ordered_triangles, three_cliques

    study = study or Study()
    m = _truss("telescope:45")
    planner = _planner(m.name)
    rng = np.random.default_rng(seed)   # central triangles and the starting triangles drawn: here
    s2 = SIGMA_L_PAPER ** 2
    all_tris = [o for t in three_cliques(m) for o in ordered_triangles(t)]
    t0 = time.perf_counter()
    central = all_central_triangles(m, rng, planner.geometry)
    central_s = time.perf_counter() - t0
    central_set = set(central)
    out: dict = {"truss": m.name, "sigma_L2_m2": s2, "runs_per_condition": runs,
                 "starting_triangles": len(all_tris), "central_triangles": len(central),
                 "paper": {"starting_triangles": 1260, "central_triangles": 72,
                           "greedy_any_m2": [7.92e-4, 2.06e-4], "greedy_central_m2": [5.08e-4, 2.88e-4],
                           "local_any_m2": [6.18e-4, 1.15e-4], "local_central_m2": [4.94e-4, 2.70e-5]}}
    pools = {"any": all_tris, "central": central}
    starts = {label: [pool[int(i)] for i in rng.choice(len(pool), size=runs, replace=len(pool) < runs)]
              for label, pool in pools.items()}
    # the two FindLocallyOptimalSequence timings first: the longest trials, started while the runs queue
    trials = [Trial("sequencing45/flos84", seed, "telescope:84"), Trial("sequencing45/flos45", seed, m.name)]
    for label, tris in starts.items():
        trials += make_trials(seed, f"sequencing45/{label}", [(m.name, tri) for tri in tris])
    results = study.map(_sequencing_dispatch, trials)
    r84, r45, done = results[0], results[1], results[2:]
    for j, label in enumerate(pools):
        rs = done[j * runs:(j + 1) * runs]
        ok = [r for r in rs if "greedy_unit" in r]
        greedy = np.asarray([r["greedy_unit"] * s2 for r in ok])
        local = np.asarray([r["local_unit"] * s2 for r in ok])
        out[f"random_{label}"] = _stats([r["random_unit"] * s2 for r in rs])
        out[f"greedy_{label}"] = _stats(greedy)
        out[f"local_{label}"] = _stats(local)
        steps = [len(r["history_unit"]) - 1 for r in ok]
        out[f"local_{label}"]["descent_steps_mean"] = float(np.mean(steps)) if steps else math.nan
        out[f"local_{label}"]["improvement_factor_mean"] = float(np.mean(greedy / local))
        out[f"local_{label}"]["moved_to_central_triangle"] = sum(
            1 for tri, r in zip(starts[label], rs)
            if "greedy_unit" in r and tuple(r["final_triangle"]) in central_set and tri not in central_set)
        out[f"histories_{label}"] = [[h * s2 for h in r["history_unit"]] for r in ok]
    out["find_locally_optimal_seconds_45"] = r45["seconds"]
    out["find_locally_optimal_trace_45_m2"] = r45["trace_unit"] * s2
    out["all_central_triangles_seconds_45"] = central_s
    out["find_locally_optimal_seconds_84"] = r84["seconds"]
    out["find_locally_optimal_trace_84_m2"] = r84["trace_unit"] * s2
    out["checks"] = {"flos_45_le_30s": out["find_locally_optimal_seconds_45"] <= 30.0,
                     "flos_84_le_300s": out["find_locally_optimal_seconds_84"] <= 300.0}
    return out


def _sequencing_dispatch(trial: Trial) -> dict:
    # one map for the study's two kinds of trial: a truss name is a FindLocallyOptimalSequence timing
    return plan_trial(trial) if isinstance(trial.spec, str) else sequencing_trial(trial)


def study_enumerate10(trials: int, seed: int, study: Study | None = None) -> dict:
    import numpy as np

    from estimation.sequencing import enumerate_plans

    study = study or Study()
    m = _truss("telescope:10")
    planner = _planner(m.name)
    t0 = time.perf_counter()
    plans = list(enumerate_plans(m, planner=planner))
    secs = time.perf_counter() - t0
    traces = np.array([t for _, t in plans])
    order = np.argsort(traces, kind="stable")
    best = plans[int(order[0])][0]
    median = plans[int(order[len(order) // 2])][0]
    sL, sM = SIGMA_L_PAPER, SIGMA_M_PAPER
    out: dict = {"truss": m.name, "sequences": len(plans), "enumeration_seconds": secs, "trials": trials,
                 "paper": {"sequences": 12708, "optimal_open_loop_m2": 2.84e-5, "median_open_loop_m2": 5.98e-5,
                           "optimal_mle_m2": 1.56e-5, "median_mle_m2": 1.86e-5}}
    runs = {f"{label}/{kind}": AssemblySpec(m.name, plan, kind, sL, sM)
            for label, plan in (("optimal", best), ("median", median)) for kind in ("open_loop", "mle")}
    mcs, _ = _monte_carlo(study, seed, "enumerate10", runs, trials)
    for label, plan in (("optimal", best), ("median", median)):
        out[label] = {"open_loop_trace_m2": planner.trace_unit(plan) * sL ** 2,
                      "open_loop_mc_trace_m2": mcs[f"{label}/open_loop"].trace,
                      "mle_trace_m2": mcs[f"{label}/mle"].trace, "plan": plan.to_json()}
    out["median_over_optimal_open_loop"] = out["median"]["open_loop_trace_m2"] / out["optimal"]["open_loop_trace_m2"]
    out["median_over_optimal_mle"] = out["median"]["mle_trace_m2"] / out["optimal"]["mle_trace_m2"]
    return out


# ------------------------------------------------------------------------------------------------


def _plots(studies: dict, out_dir: str) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    files = []
    if "tetrahelix20" in studies:
        s = studies["tetrahelix20"]
        fig, ax = plt.subplots(1, 2, figsize=(11, 4))
        x = np.arange(1, 21)
        # node 1 is the gauge origin (zero error by definition): plots start at node 2
        ax[0].semilogy(x[1:], s["open_loop"]["analytic_node_mse_m2"][1:], "k--", label="open loop (analytic)")
        for kind, c in (("open_loop", "tab:red"), ("ekf", "tab:green"), ("mle", "tab:orange")):
            ax[0].semilogy(x[1:], s[kind]["node_mse_m2"][1:], "o-", color=c, ms=3, label=f"{kind} (MC)")
            ax[1].semilogy(x[1:], np.cumsum(s[kind]["node_mse_m2"])[1:], "o-", color=c, ms=3, label=kind)
        ax[1].semilogy(x[1:], np.cumsum(s["open_loop"]["analytic_node_mse_m2"])[1:], "k--", label="open loop (analytic)")
        ax[0].set(title=f"tetrahelix:20 error per node, σL=0.1 m, σM=0.01 m ({s['trials']} trials)",
                  xlabel="node (assembly order)", ylabel="E|X - X̄|² [m²]")
        ax[1].set(title="trace against node count", xlabel="nodes built", ylabel="trace [m²]")
        for a in ax:
            a.grid(True, which="both", alpha=0.3)
            a.legend(fontsize=8)
        files.append(save_figure(fig, out_dir, "tetrahelix20.png"))
    if "telescope84" in studies:
        s = studies["telescope84"]
        fig, ax = plt.subplots(1, 2, figsize=(11, 4))
        x = np.arange(1, 85)
        ax[0].semilogy(x[1:], s["open_loop"]["analytic_node_mse_m2"][1:], "k--", label="open loop (analytic)")
        series = [("open_loop", "tab:red", s["open_loop"]["node_mse_m2"]), ("ekf", "tab:green", s["ekf"]["node_mse_m2"]),
                  ("mle", "tab:orange", s["mle"]["node_mse_m2"]),
                  ("mle + cameras 0.1 px", "tab:blue", s["fusion"]["sigma_px_0.1"]["node_mse_m2"])]
        for label, c, v in series:
            ax[0].semilogy(x[1:], v[1:], ".-", color=c, ms=3, label=label)
            ax[1].plot(x, np.cumsum(v) * 1e6, color=c, label=label)
        ax[1].plot(x, np.cumsum(s["open_loop"]["analytic_node_mse_m2"]) * 1e6, "k--", label="open loop (analytic)")
        ax[0].set(title="telescope:84 error per node (paper σL², σM²)", xlabel="node (assembly order)",
                  ylabel="E|X - X̄|² [m²]")
        ax[1].set(title="trace against node count", xlabel="nodes built", ylabel="trace [mm²]")
        for a in ax:
            a.grid(True, alpha=0.3)
            a.legend(fontsize=8)
        files.append(save_figure(fig, out_dir, "telescope84.png"))
    if "sequencing45" in studies:
        s = studies["sequencing45"]
        fig, ax = plt.subplots(figsize=(6, 4))
        for label, style in (("any", "--"), ("central", "-")):
            hs = s.get(f"histories_{label}") or []
            if not hs:
                continue
            L = max(len(h) for h in hs)
            padded = np.array([h + [h[-1]] * (L - len(h)) for h in hs])
            ax.plot(np.arange(L), padded.mean(axis=0) * 1e4, style, label=f"greedy from {label} triangles")
        ax.set(title="telescope:45 steepest-descent trace trajectory", xlabel="descent step", ylabel="trace [1e-4 m²]")
        ax.grid(True, alpha=0.3)
        ax.legend()
        files.append(save_figure(fig, out_dir, "sequencing45.png"))
    return files


def _fmt(v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    if isinstance(v, float) and math.isinf(v):
        return "inf"
    return f"{v:.3g}"


def markdown(studies: dict, command: str) -> str:
    lines = [f"Command: `{command}`", ""]
    if "tetrahelix20" in studies:
        s = studies["tetrahelix20"]
        lines += [f"### tetrahelix:20 — 1 m struts, σL = 0.1 m, σM = 0.01 m, {s['trials']} trials", "",
                  "| | trace nodes 1–10 [m²] | trace all 20 nodes [m²] | paper (all 20) [m²] | estimate error [m²] | trials lost / struts reset |",
                  "|---|---|---|---|---|---|",
                  f"| open loop (analytic) | {_fmt(s['open_loop']['analytic_trace_node10_m2'])} | {_fmt(s['open_loop']['analytic_trace_total_m2'])} | 28.76 | | |"]
        for kind in ("open_loop", "ekf", "mle"):
            r = s[kind]
            lines.append(f"| {kind} (Monte Carlo) | {_fmt(r['trace_node10_m2'])} | {_fmt(r['trace_total_m2'])} | "
                         f"{s['paper_total_m2'][kind]} | {_fmt(r['estimate_error_total_m2'])} | {r['failures']} / {r['redraws']} |")
        c = s["checks"]
        lines += ["", f"Open loop / MLE: {c['open_loop_over_mle_node10']:.1f} over nodes 1–10, "
                  f"{c['open_loop_over_mle_total']:.1f} over all 20 nodes (target ≥ 15); "
                  f"MLE ≤ EKF ≤ open loop: {c['mle_le_ekf_le_open_loop_node10']} (nodes 1–10), "
                  f"{c['mle_le_ekf_le_open_loop_total']} (all nodes).", ""]
    if "telescope84" in studies:
        s = studies["telescope84"]
        lines += [f"### telescope:84 — σL² = 3.57e-7 m², σM² = 6.25e-8 m², {s['trials']} trials", "",
                  f"Plan: FindLocallyOptimalSequence, {s['sequence']['layers']} parallel layers, "
                  f"{s['sequence']['seconds']:.1f} s.", "",
                  "| | trace [m²] | paper [m²] | MLE/EKF update, median [ms] | update adding node 84, median / p95 [ms] |",
                  "|---|---|---|---|---|",
                  f"| open loop (analytic) | {_fmt(s['open_loop']['analytic_trace_m2'])} | 1.55e-3 | | |",
                  f"| open loop (Monte Carlo) | {_fmt(s['open_loop']['trace_m2'])} | | | |"]
        for kind in ("ekf", "mle"):
            r = s[kind]
            lines.append(f"| {kind} | {_fmt(r['trace_m2'])} | {s['paper_m2'][kind]:.3g} | {r['update_ms_median']:.2f} | "
                         f"{r['update_ms_at_84_median']:.2f} / {r['update_ms_at_84_p95']:.2f} |")
        lines.append(f"| perfect-estimate floor | {_fmt(s['perfect_estimate_floor_m2'])} | | | |")
        f = s["fusion"]
        lines += ["", f"Camera fusion (beyond the paper; {f['cameras']} cameras, {f['camera']}; {f['trials']} trials):", "",
                  "| | built-structure trace [m²] | estimate error [m²] |", "|---|---|---|",
                  f"| struts only (MLE) | {_fmt(f['mle_only']['trace_m2'])} | {_fmt(f['mle_only']['estimate_error_total_m2'])} |"]
        for px in (1.0, 0.3, 0.1):
            r = f[f"sigma_px_{px:g}"]
            lines.append(f"| struts + cameras, σ = {px:g} px | {_fmt(r['trace_m2'])} | {_fmt(r['estimate_error_total_m2'])} |")
        lines.append("")
    if "sequencing45" in studies:
        s = studies["sequencing45"]
        p = s["paper"]
        lines += [f"### telescope:45 sequencing — σL² = 3.57e-7 m², {s['runs_per_condition']} runs per condition", "",
                  f"{s['starting_triangles']} ordered starting triangles, {s['central_triangles']} central "
                  f"(paper: {p['starting_triangles']}, {p['central_triangles']}).", "",
                  "| sequence | mean ± sd [m²] | median [m²] | paper mean ± sd [m²] |", "|---|---|---|---|"]
        for key, name, paper in (("random_any", "random, any triangle", "degenerate"),
                                 ("random_central", "random, central triangle", "degenerate"),
                                 ("greedy_any", "greedy, any triangle", "7.92e-4 ± 2.06e-4"),
                                 ("greedy_central", "greedy, central triangle", "5.08e-4 ± 2.88e-4"),
                                 ("local_any", "local search from greedy, any", "6.18e-4 ± 1.15e-4"),
                                 ("local_central", "local search from greedy, central", "4.94e-4 ± 2.70e-5")):
            r = s[key]
            lines.append(f"| {name} | {_fmt(r['mean'])} ± {_fmt(r['sd'])} | {_fmt(r['median'])} | {paper} |")
        la, lc = s["local_any"], s["local_central"]
        lines += ["", f"Descent steps (mean): {la['descent_steps_mean']:.2f} from any, {lc['descent_steps_mean']:.2f} from central "
                  f"(paper 14.28, 6.96); improvement over greedy ×{la['improvement_factor_mean']:.2f} / ×{lc['improvement_factor_mean']:.2f} "
                  f"(paper 1.25 / 1.03); descents from a non-central triangle that ended on a central one: {la['moved_to_central_triangle']}.",
                  "", f"FindLocallyOptimalSequence: {s['find_locally_optimal_seconds_45']:.1f} s on 45 nodes "
                  f"(target ≤ 30 s, trace {_fmt(s['find_locally_optimal_trace_45_m2'])} m²), "
                  f"{s['find_locally_optimal_seconds_84']:.1f} s on 84 nodes (target ≤ 300 s, trace "
                  f"{_fmt(s['find_locally_optimal_trace_84_m2'])} m²).", ""]
    if "enumerate10" in studies:
        s = studies["enumerate10"]
        lines += [f"### telescope:10 — all {s['sequences']} sequences (paper: 12,708), enumerated in {s['enumeration_seconds']:.1f} s; {s['trials']} trials", "",
                  "| sequence | open loop (analytic) [m²] | open loop (MC) [m²] | MLE [m²] | paper open loop / MLE [m²] |", "|---|---|---|---|---|"]
        for label, paper in (("optimal", "2.84e-5 / 1.56e-5"), ("median", "5.98e-5 / 1.86e-5")):
            r = s[label]
            lines.append(f"| {label} | {_fmt(r['open_loop_trace_m2'])} | {_fmt(r['open_loop_mc_trace_m2'])} | {_fmt(r['mle_trace_m2'])} | {paper} |")
        lines += ["", f"Median / optimal: ×{s['median_over_optimal_open_loop']:.2f} open loop, ×{s['median_over_optimal_mle']:.2f} with MLE "
                  "(paper ×2.1 / ×1.19).", ""]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    quick = bool(getattr(args, "quick", False))
    seed = int(getattr(args, "seed", 0))
    only = set(getattr(args, "only", None) or STUDIES)
    out_dir = getattr(args, "out", os.path.join("bench_out", "mle"))
    if seed < 0:
        from lab.core.errors import UserError

        raise UserError(f"--seed must be 0 or more, got {seed}")
    os.makedirs(out_dir, exist_ok=True)
    t_all = time.perf_counter()
    # the journal's study: what the figures depend on (not --workers / --scheduler)
    fingerprint = {"bench": "mle", "quick": quick, "seed": seed, "only": sorted(only)}
    with open_study(args, out_dir, fingerprint, "lab bench mle") as study:
        parts = {
            # the two with a long serial trial (a FindLocallyOptimalSequence on 84 nodes) first
            "telescope84": lambda: study_telescope84(20 if quick else 100, 10 if quick else 50, seed, study),
            "sequencing45": lambda: study_sequencing45(5 if quick else 50, seed, study),
            "tetrahelix20": lambda: study_tetrahelix20(200 if quick else 1000, seed, study),
            "enumerate10": lambda: study_enumerate10(200 if quick else 1000, seed, study),
        }
        done = study.concurrently({name: part for name, part in parts.items() if name in only})
        studies: dict = {name: done[name] for name in STUDIES if name in done}
        command = "lab bench mle" + (" --quick" if quick else "") + (f" --seed {seed}" if seed else "") + \
            "".join(f" --only {name}" for name in STUDIES if name in only and len(only) < len(STUDIES))
        result = {"studies": studies, "quick": quick, "seed": seed, "seconds": time.perf_counter() - t_all,
                  "command": command, "executor": study.describe()}
        with open(os.path.join(out_dir, "mle.json"), "w") as fh:
            json.dump(result, fh, indent=1, default=float)
        study.finish()
    md = markdown(studies, command) + f"\nTotal {result['seconds']:.0f} s ({result['executor']}).\n"
    with open(os.path.join(out_dir, "mle.md"), "w") as fh:
        fh.write(md)
    plots = _plots(studies, out_dir)
    if getattr(args, "json", False):
        print(json.dumps(result, default=float))
    else:
        print(md)
        print("wrote " + ", ".join([os.path.join(out_dir, "mle.json"), os.path.join(out_dir, "mle.md"), *plots]))
    return 0
