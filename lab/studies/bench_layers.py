"""`lab bench layers`: is every module of a BORG verified, layer by layer, at every size the default
rig claims (issue 23)?  For N = 3..10 (`--sizes`; N = 9 and 10 print their tags in the extension of
AprilTag 36h11, `estimation.tag_family`) and seeds, a real `lab run borg --n N` on the
simulated bench (devices over their wire protocols, rendered frames, the real detector, the rig's
true errors and its own rig survey) with faults in every layer, each just beyond the 5 mm / 1 deg
tolerance -- a module 6 mm off (seeded direction), one turned 1.5 deg (seeded axis), a deployable
deployed to 0.35 m of 0.5 m -- and in every layer a good module 3 mm off (inside the tolerance by
more than the verdict's band).  Everything else is a good module as built.

Figures per N and per layer (a module's layer: the cell row its nodes' mean height lies in):
- modules `unverified` (for want of a view or otherwise), good modules flagged (false flags),
  faults flagged;
- good-module position error against the simulated truth (median, max; and the max over those
  passed `ok`), |error| / stated 1-sigma (median), position NEES (mean; 3 when the 1-sigma is
  right), views per module, modules whose views were re-planned;
- the stated 1-sigma of the good modules passed `ok` beside what their plans predicted and the
  Cramer-Rao bound of the views taken (medians): whether the plans' target is what the
  measurements reach;
- the NEES about each run's frame: the good modules' errors share one rigid motion per run, the
  frame the turntable tags realise (`error_frame`), a single draw that can lift one run's NEES
  far above 3 while the 1-sigma is honest; with it taken off, what is left is each module's own;
and per N: the run's wall time per module, its SLAM step (median), its peak memory, and the
largest common frame error of its runs (offset, rotation).

Trials run through `lab.core.executor` (--workers N, or --scheduler on a Dask cluster); finished trials
are journaled in --out/trials.jsonl, so the same command after an interruption resumes, and a
trial whose run was cut off goes on from that run's checkpoint (`lab resume`), as does a run that a
simulated device's timeout stopped (a camera starved of CPU by the runs beside it: up to
`MAX_RESUMES` times; the table counts them).  A full
study (N = 3..10 x 5 seeds) is days of CPU on two cores (one N = 8 run: an hour); `--quick` is N = 3 and 4, one seed.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lab.core.executor import Trial, add_executor_arguments
from lab.core.verdicts import FLAGGED, OK, UNCERTAIN, UNVERIFIED
from lab.studies.bench_common import (BorgRun, cell, graph_nees, median_metric, report_study, resume_borg, run_borg,
                                      run_trial_study, study_heading, unit_vector)

FAULT_OFFSET_M = 0.006                     # 1 mm beyond the 5 mm tolerance
FAULT_ROTATION_RAD = math.radians(1.5)     # 0.5 deg beyond 1 deg
FAULT_DEPLOYED_M = 0.35                    # of 0.5 m (the README job's 13D)
GOOD_OFFSET_M = 0.003                      # inside 5 mm by more than the band (2 x ~0.3 mm)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="N = 3 and 4, one seed")
    p.add_argument("--sizes", default=None, help="BORG sizes, comma-separated (default 3..10; --quick 3,4)")
    p.add_argument("--seeds", type=int, default=None, help="seeds per size (default 5; --quick 1)")
    p.add_argument("--first-seed", type=int, default=0, metavar="S",
                   help="the first seed (default 0): seeds S .. S+K-1, so a study can be added to "
                        "(the tables of several: --report A.json B.json)")
    p.add_argument("--speedup", type=float, default=100.0, help="simulated device speed-up (default 100)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    p.add_argument("--out", default="bench_out/layers", help="directory for the runs (default bench_out/layers)")
    p.add_argument("--report", metavar="JSON", nargs="+",
                   help="print the tables of an earlier (or interrupted) study's layers.json instead of running "
                        "one; of several studies' runs together when given several (each N and seed once)")
    add_executor_arguments(p)


def plan_faults(n: int, seed: int) -> dict[str, tuple[str, Any]]:
    """module -> (kind, value) for one trial: in every layer an offset fault, a rotation fault, a
    partial deployment (a deployable of the layer) and a good module 3 mm off; seeded picks."""
    from lab.core.structures.borg import build_borg

    model = build_borg(n)
    rng = np.random.default_rng([seed, n, 23])
    out: dict[str, tuple[str, Any]] = {}
    for layer in range(n):
        names = [m.name for m in model.modules if model.layer_of(m.name) == layer]
        deployables = [x for x in names if model.module_by_name[x].kind == "deployable"]
        if deployables:
            out[str(rng.choice(deployables))] = ("partial_deploy", FAULT_DEPLOYED_M)
        for kind in ("offset", "rotation", "good"):
            free = [x for x in names if x not in out]
            if not free:
                break
            pick = str(rng.choice(free))
            if kind == "offset":
                out[pick] = ("offset", [float(x) for x in FAULT_OFFSET_M * unit_vector(rng)])
            elif kind == "rotation":
                out[pick] = ("rotation", [float(x) for x in FAULT_ROTATION_RAD * unit_vector(rng)])
            else:
                out[pick] = ("good", [float(x) for x in GOOD_OFFSET_M * unit_vector(rng)])
    return out


def scenario(seed: int, faults: dict[str, tuple[str, Any]]) -> str:
    """The trial's scenario: its seed (the rig's own errors stay: [sim.rig_error]) and the faults."""
    lines = [f"seed = {seed}"]
    for module, (kind, value) in faults.items():
        if kind == "partial_deploy":
            lines += ["", "[[borg.fault]]", 'kind = "partial_deploy"', f'module = "{module}"', f"height_m = {value}"]
        else:
            key = "rotation_rad" if kind == "rotation" else "offset_m"
            lines += ["", "[[borg.fault]]", 'kind = "module_offset"', f'module = "{module}"', f"{key} = {value}"]
    return "\n".join(lines) + "\n"


# a simulated device that misses its timeout stops the run, as on a bench; a study's runs share the
# machine's cores with each other and anything else, and a camera starved of CPU misses its 3 s for
# a frame.  The study resumes such a run from its checkpoint, as an operator would, up to this often
MAX_RESUMES = 3


def _device_fault(summary: dict[str, Any]) -> bool:
    return summary.get("result") == "failed" and str(summary.get("reason", "")).startswith("DeviceTimeout")


def _earlier_attempt(run_dir: Path, n: int, scenario_file: Path, speedup: float) -> str | None:
    """An earlier attempt at this trial in `run_dir` (the study was interrupted, or its run stopped
    on a device's timeout): "completed" (the study stopped before journaling it), "resume" (a
    checkpoint to go on from), or None (start afresh)."""
    try:
        params = json.loads((run_dir / "run.json").read_text())["params"]
    except (OSError, ValueError, KeyError):
        return None
    if (params.get("n"), params.get("scenario"), params.get("speedup")) != (n, str(scenario_file), speedup):
        return None
    try:
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        summary = None
    if summary is not None and summary.get("result") == "completed":
        return "completed"
    # a run writes its summary "running" after every step: one killed with the study (or the machine)
    # left that; one interrupted (Ctrl-C, SIGTERM) says "aborted" and is resumable by design
    if summary is not None and summary.get("result") not in ("running", "aborted") and not _device_fault(summary):
        return None                  # stopped for a reason of its own: the trial is run again
    return "resume" if (run_dir / "checkpoint.json").exists() else None


def trial(out: Path, n: int, seed: int, speedup: float) -> dict[str, Any]:
    from lab.core.structures.borg import build_borg

    faults = plan_faults(n, seed)
    sc = out / f"scenario-n{n}-seed{seed}.toml"
    sc.write_text(scenario(seed, faults))
    run_dir, log = out / f"n{n}-seed{seed}", out / f"n{n}-seed{seed}.log"
    earlier = _earlier_attempt(run_dir, n, sc, speedup)
    resumed = 0
    if earlier == "completed":
        summary = json.loads((run_dir / "summary.json").read_text())
        run = BorgRun([], summary, 0.0, None, median_metric(run_dir / "run.mcap", "slam/update_s"))
    elif earlier == "resume":
        run, resumed = resume_borg(run_dir, log), 1
    else:
        run = run_borg(["--n", str(n), "--scenario", str(sc), "--speedup", str(speedup)], run_dir, log=log)
    # the wall time of a run this study did not start (finished, or cut off, before the study came
    # back to it) is not known: None (the journal keeps JSON's null, never NaN)
    wall: float | None = run.wall_s if earlier is None else None
    peak = run.peak_rss_mb
    while _device_fault(run.summary) and resumed < MAX_RESUMES:
        run = resume_borg(run_dir, log)
        resumed += 1
        wall = wall + run.wall_s if wall is not None else None
        peaks = [p for p in (peak, run.peak_rss_mb) if p is not None]
        peak = max(peaks) if peaks else None
    s = run.summary
    if s["result"] != "completed":
        raise RuntimeError(f"{' '.join(run.cmd)} ended {s['result']}: {s.get('reason', '')}")
    model = build_borg(n)
    rows = []
    for m in s["modules"]:
        kind = faults.get(m["name"], ("none", None))[0]
        rows.append({"name": m["name"], "layer": model.layer_of(m["name"]), "fault": kind not in ("none", "good"),
                     "verdict": m["verdict"], "views": m.get("views"),
                     "error_m": m.get("position_error_m"), "sigma_m": m.get("sigma_position_m"),
                     "replanned": "re-planned" in (m.get("reason") or ""), "nees": m.get("position_nees"),
                     # the 1-sigma its views were planned to give, and their Cramer-Rao bound
                     "planned_sigma_m": m.get("predicted_sigma_m"), "bound_m": m.get("bound_position_m")})
    frame = _frame(model, s["modules"], rows)
    # a resumed run's memory is its processes'
    return {"n": n, "seed": seed, "result": s["result"], "wall_s": wall, "modules": rows,
            "peak_rss_mb": peak, "views": s.get("views"), "resumed": resumed,
            "slam_update_s_median": run.slam_update_s_median, "graph_nees": graph_nees(s), **frame}


def _frame(model: Any, modules: list[dict[str, Any]], rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The run's common frame error over its good modules (`error_frame`): its size, and each good
    module's NEES about it (`nees_frame` in its row)."""
    from lab.studies.error_frame import fit_frame

    read = [(m, r) for m, r in zip(modules, rows) if not r["fault"] and m.get("position_error_vector_m") is not None
            and m.get("position_covariance_m2") is not None]
    fit = fit_frame([model.module_by_name[m["name"]].structure_T_module.translation() for m, _ in read],
                    [m["position_error_vector_m"] for m, _ in read], [m["position_covariance_m2"] for m, _ in read])
    if fit is None:
        return {"frame_offset_mm": None, "frame_rotation_mrad": None}
    for (_, r), v, e in zip(read, fit.nees_about_frame, fit.residuals_m):
        r["nees_frame"] = float(v)
        r["error_frame_m"] = float(np.linalg.norm(e))
    return {"frame_offset_mm": float(np.linalg.norm(fit.translation_m) * 1e3),
            "frame_rotation_mrad": float(np.linalg.norm(fit.rotation_rad) * 1e3)}


@dataclass(frozen=True)
class RunSpec:
    out: str        # absolute: a Dask worker's working directory is its own
    n: int
    speedup: float


def layers_trial(t: Trial) -> dict[str, Any]:
    s: RunSpec = t.spec
    return trial(Path(s.out), s.n, t.seed, s.speedup)


def _mean(mods: list[dict[str, Any]], key: str) -> float | None:
    """The mean of a figure over the modules that have it (trials journaled before the NEES was
    kept have none: their modules are left out), None if none has."""
    values = [m[key] for m in mods if m.get(key) is not None]
    return float(np.mean(values)) if values else None


def _row(key: dict[str, Any], mods: list[dict[str, Any]]) -> dict[str, Any]:
    good = [m for m in mods if not m["fault"]]
    faults = [m for m in mods if m["fault"]]
    read = [m for m in good if m["error_m"] is not None]
    err = np.array([m["error_m"] for m in read], float)
    ratio = np.array([m["error_m"] / m["sigma_m"] for m in read if m["sigma_m"]], float)
    return {**key, "modules": len(mods), "unverified": sum(m["verdict"] == UNVERIFIED for m in mods),
            "uncertain": sum(m["verdict"] == UNCERTAIN for m in mods),
            "false_flags": sum(m["verdict"] == FLAGGED for m in good), "good": len(good),
            "faults_caught": sum(m["verdict"] == FLAGGED for m in faults), "faults": len(faults),
            "replanned": sum(m["replanned"] for m in mods),
            "error_mm_median": float(np.median(err) * 1e3) if err.size else None,
            "error_mm_max": float(err.max() * 1e3) if err.size else None,
            # the modules passed `ok`: what the verdict vouches for
            "ok_error_mm_max": max((m["error_m"] * 1e3 for m in read if m["verdict"] == OK), default=None),
            "ratio_median": float(np.median(ratio)) if ratio.size else None,
            "nees_mean": _mean(good, "nees"), "nees_frame_mean": _mean(good, "nees_frame"),
            "views_per_module": float(np.mean([m["views"] or 0 for m in mods])) if mods else None,
            # the good modules passed `ok`: the graph's 1-sigma, what their plans predicted, the bound
            **{f"{key}_mm_median": _median_mm([m for m in good if m["verdict"] == OK], key)
               for key in ("sigma_m", "planned_sigma_m", "bound_m")}}


def _median_mm(mods: list[dict[str, Any]], key: str) -> float | None:
    """The median of a figure over the modules that have it, in mm (None if none has: trials
    journaled before it was kept)."""
    values = [m[key] for m in mods if m.get(key) is not None]
    return float(np.median(values) * 1e3) if values else None


def aggregate(trials: list[dict[str, Any]]) -> list[dict[str, Any]]:
    rows = []
    for n in sorted({t["n"] for t in trials}):
        ts = [t for t in trials if t["n"] == n]
        mods = [m for t in ts for m in t["modules"]]
        whole = _row({"n": n, "layer": "all", "runs": len(ts)}, mods)
        # a run the study took as it found it has no wall time: the median of the others
        timed = [t["wall_s"] / max(len(t["modules"]), 1) for t in ts
                 if t["wall_s"] is not None and math.isfinite(t["wall_s"])]
        whole.update({"wall_s_per_module": float(np.median(timed)) if timed else None,
                      "slam_update_ms_median": float(np.median([t["slam_update_s_median"] for t in ts]) * 1e3),
                      "peak_rss_mb": max((float(t["peak_rss_mb"]) for t in ts if t["peak_rss_mb"] is not None),
                                         default=None),
                      "resumed": sum(t.get("resumed", 0) for t in ts),
                      # the largest common frame error of a run (None: no run measured one)
                      "frame_offset_mm_max": max((t["frame_offset_mm"] for t in ts if t.get("frame_offset_mm") is not None),
                                                 default=None),
                      "frame_rotation_mrad_max": max((t["frame_rotation_mrad"] for t in ts
                                                      if t.get("frame_rotation_mrad") is not None), default=None)})
        rows.append(whole)
        for layer in range(n):
            rows.append(_row({"n": n, "layer": layer, "runs": len(ts)}, [m for m in mods if m["layer"] == layer]))
    return rows


def to_markdown(res: dict[str, Any]) -> str:
    lines = [study_heading(res), "",
             "| N | layer | runs | modules | unverified | uncertain | false flags | faults flagged | re-planned | "
             "error median / max (mm) | max of `ok` (mm) | \\|err\\|/1σ median | NEES mean (3) | NEES about the run's frame | "
             "frame offset (mm) / rotation (mrad), worst run | 1σ / planned / bound, `ok` median (mm) | "
             "views / module | run s / module | SLAM step (ms) | peak memory (MB) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        whole = r["layer"] == "all"
        runs = f"{r['runs']} ({r['resumed']} resumed)" if r.get("resumed") else str(r["runs"])
        lines.append(
            f"| {r['n']} | {r['layer']} | {runs} | {r['modules']} | {r['unverified']} | {r['uncertain']} | "
            f"{r['false_flags']}/{r['good']} | {r['faults_caught']}/{r['faults']} | {r['replanned']} | "
            f"{cell(r['error_mm_median'])} / {cell(r['error_mm_max'])} | {cell(r.get('ok_error_mm_max'))} | {cell(r['ratio_median'])} | "
            f"{cell(r.get('nees_mean'), '.1f')} | {cell(r.get('nees_frame_mean'), '.1f')} | "
            f"{cell(r.get('frame_offset_mm_max') if whole else None)} / {cell(r.get('frame_rotation_mrad_max') if whole else None)} | "
            f"{cell(r.get('sigma_m_mm_median'))} / {cell(r.get('planned_sigma_m_mm_median'))} / "
            f"{cell(r.get('bound_m_mm_median'))} | "
            f"{cell(r['views_per_module'], '.1f')} | {cell(r.get('wall_s_per_module') if whole else None, '.1f')} | "
            f"{cell(r.get('slam_update_ms_median') if whole else None, '.1f')} | "
            f"{cell(r.get('peak_rss_mb') if whole else None, '.0f')} |")
    lines += ["", "Per run (good modules): the frame all of its modules share, the NEES whole and about that frame, "
              "the largest error of a module passed `ok`, whole and about the frame; and the NEES of the graph's own "
              "camera mount and intrinsics as the run ended:", "",
              "| N | seed | frame offset (mm) | frame rotation (mrad) | NEES mean (3) | NEES about the frame | "
              "max of `ok` (mm) | max of `ok` about the frame (mm) | graph NEES mount (6) / intrinsics (4) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for t in res.get("trials", []):
        p = per_run(t)
        lines.append(f"| {p['n']} | {p['seed']} | {cell(p['frame_offset_mm'])} | {cell(p['frame_rotation_mrad'])} | "
                     f"{cell(p['nees_mean'], '.1f')} | {cell(p['nees_frame_mean'], '.1f')} | "
                     f"{cell(p['ok_error_mm_max'])} | {cell(p['ok_error_frame_mm_max'])} | "
                     f"{cell(p['graph_nees_mount'], '.1f')} / {cell(p['graph_nees_intrinsics'], '.1f')} |")
    return "\n".join(lines)


def per_run(t: dict[str, Any]) -> dict[str, Any]:
    """One run's honesty figures: its frame, its good modules' NEES whole and about the frame, and
    the largest error of a good module passed `ok`, whole and about the frame (None where the trial
    was journaled before these were kept)."""
    good = [m for m in t["modules"] if not m["fault"]]
    ok = [m for m in good if m["verdict"] == OK and m["error_m"] is not None]
    about = [m["error_frame_m"] for m in ok if m.get("error_frame_m") is not None]
    return {"n": t["n"], "seed": t["seed"], "frame_offset_mm": t.get("frame_offset_mm"),
            "frame_rotation_mrad": t.get("frame_rotation_mrad"),
            "nees_mean": _mean(good, "nees"), "nees_frame_mean": _mean(good, "nees_frame"),
            "ok_error_mm_max": max((m["error_m"] * 1e3 for m in ok), default=None),
            "ok_error_frame_mm_max": max(about) * 1e3 if about else None,
            "graph_nees_mount": (t.get("graph_nees") or {}).get("mount"),
            "graph_nees_intrinsics": (t.get("graph_nees") or {}).get("intrinsics")}


def _progress(r: dict[str, Any]) -> str:
    mods = r["modules"]
    good = [m for m in mods if not m["fault"]]
    err = np.array([m["error_m"] for m in good if m["error_m"] is not None], float)
    return (f"  N {r['n']} seed {r['seed']}: {len(mods)} modules, "
            f"{sum(m['verdict'] == UNVERIFIED for m in mods)} unverified, "
            f"{sum(m['verdict'] == FLAGGED for m in good)} false flags, faults "
            f"{sum(m['verdict'] == FLAGGED for m in mods if m['fault'])}/{sum(m['fault'] for m in mods)}, "
            f"error max {err.max() * 1e3 if err.size else float('nan'):.2f} mm, "
            f"frame {cell(r.get('frame_offset_mm'))} mm / {cell(r.get('frame_rotation_mrad'))} mrad, "
            f"{'wall time unknown' if r['wall_s'] is None else format(r['wall_s'], '.0f') + ' s'}")


def run(args: argparse.Namespace) -> int:
    from lab.core.errors import UserError
    from lab.core.structures.borg import MAX_N

    if args.report:
        return report_study(args.report, "layers", aggregate, to_markdown)
    text = args.sizes or ("3,4" if args.quick else ",".join(map(str, range(3, MAX_N + 1))))
    try:
        sizes = [int(x) for x in text.split(",")]
    except ValueError:
        raise UserError(f"--sizes: expected integers separated by commas, got {text!r}") from None
    seeds = args.seeds if args.seeds is not None else (1 if args.quick else 5)
    if not sizes or any(not 2 <= n <= MAX_N for n in sizes) or seeds < 1:
        raise UserError(f"--sizes must be in 2..{MAX_N}, --seeds >= 1")
    if args.first_seed < 0:
        raise UserError(f"--first-seed must be 0 or more, got {args.first_seed}")
    if not (math.isfinite(args.speedup) and 1 <= args.speedup <= 1000):
        raise UserError(f"--speedup must be in [1, 1000], got {args.speedup}")
    out = Path(args.out).resolve()
    runs = [Trial(f"n{n}-seed{seed}", seed, RunSpec(str(out), n, args.speedup)) for n in sizes
            for seed in range(args.first_seed, args.first_seed + seeds)]
    params: dict[str, Any] = {"sizes": sizes, "seeds": seeds}
    if args.first_seed:
        # only when set, so a study journaled before the flag existed still resumes
        params["first_seed"] = args.first_seed
    return run_trial_study(args, "layers", runs, layers_trial, params,
                           aggregate, to_markdown, _progress)
