"""`lab bench calibration`: verdicts and accuracy of `lab run borg` against the size of the rig's
errors, with and without rig calibration, over seeds.

Each trial is a real `lab run borg` on the simulated bench (devices over their wire protocols,
rendered images, the real detector), with a scenario that sets the seed, the rig's true errors
(the sim rig's own `[sim.rig_error]` scaled by 0, 1, 2, ...: ideal to twice the default) and a set
of structure faults.  Modes:
- `calibrated`: what a run does by default with no calibration file: a rig calibration survey first,
  then the calibration refined in the graph with every view (corner observations);
- `calibrated-pose`: the same, with each tag sighting entering as the detector's single-view pose
  instead of its corners (`--observation pose`), to compare the two observation models;
- `uncalibrated`: the behaviour before rig calibration: the rig file trusted as exact (camera pose
  priors at 1 mm / 0.05 deg from its kinematics, single-view pose observations).
Figures: false flags on good modules, faults caught, good-module position and rotation error
against the simulated truth, the rig calibration's error against the truth and its NEES, the SLAM
step time and the run's wall time.

Trials run through `lab.core.executor`: --workers N runs N `lab run borg` at once (default: all cores;
each simulated bench listens on its own free loopback ports), --scheduler tcp://HOST:PORT on a Dask
cluster.  A trial's seed is the scenario's, so the figures do not depend on which ran it.  Finished
trials are journaled in --out/trials.jsonl: the same command after an interruption resumes.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lab.core.executor import Trial, add_executor_arguments
from lab.core.verdicts import FLAGGED, UNCERTAIN, UNVERIFIED
from lab.studies.bench_common import cell, report_study, run_borg, run_trial_study, study_heading, study_size

# Faults among the first 9 modules, so --quick sees them all: a partial deployment and a 15 mm
# offset must be flagged, a displaced tag rejected (its module unverified), a 2 mm offset passed.
FAULTS = """
[[borg.fault]]
kind = "partial_deploy"
module = "3D"
height_m = 0.35

[[borg.fault]]
kind = "module_offset"
module = "7S"
offset_m = [0.0, 0.015, 0.0]

[[borg.fault]]
kind = "tag_displaced"
tag = 12
offset_m = [0.0, 0.3, 0.0]

[[borg.fault]]
kind = "module_offset"
module = "8S"
offset_m = [0.002, 0.0, 0.0]
"""
EXPECT = {"3D": FLAGGED, "7S": FLAGGED, "9S": UNVERIFIED}
MODES = {"calibrated": [], "calibrated-pose": ["--observation", "pose"],
         "uncalibrated": ["--uncalibrated", "--observation", "pose"]}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="2 seeds x 9 modules x rig errors 0 and 2x default")
    p.add_argument("--seeds", type=int, default=None, help="seeds per configuration (default 10; --quick 2)")
    p.add_argument("--modules", type=int, default=None, help="modules per run (default 27; --quick 9)")
    p.add_argument("--scales", default=None, help="rig-error sizes, times the default (default 0,1,2)")
    p.add_argument("--modes", default="calibrated,uncalibrated",
                   help="comma-separated: calibrated, calibrated-pose, uncalibrated (default calibrated,uncalibrated)")
    p.add_argument("--speedup", type=float, default=100.0, help="simulated device speed-up (default 100)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    p.add_argument("--out", default="bench_out/calibration", help="directory for the runs (default bench_out/calibration)")
    p.add_argument("--report", metavar="JSON", help="print the tables of an earlier (or interrupted) study's "
                                                   "calibration.json instead of running one")
    add_executor_arguments(p)


def _scenario(seed: int, scale: float) -> str:
    from lab.core.config import load_rig

    e = load_rig().sim.rig_error.scaled(scale)
    lines = [f"seed = {seed}", "", "[rig_error]"]
    if e.ideal:
        lines.append("ideal = true")
    else:
        for k, v in e.to_dict().items():
            lines.append(f"{k} = {list(v) if isinstance(v, tuple) else v}")
    return "\n".join(lines) + "\n" + FAULTS


def trial(out: Path, seed: int, scale: float, mode: str, modules: int, speedup: float) -> dict[str, Any]:
    sc = out / f"scenario-x{scale:g}-seed{seed}.toml"
    sc.write_text(_scenario(seed, scale))
    run = run_borg(["--scenario", str(sc), "--modules", str(modules), "--speedup", str(speedup), *MODES[mode]],
                   out / f"{mode}-x{scale:g}-seed{seed}")
    s = run.summary
    if s["result"] == "aborted":
        # a Ctrl-C at the terminal reaches the run too: an interrupted run is not a finished trial
        raise RuntimeError(f"{' '.join(run.cmd)} was interrupted: {s.get('reason', '')}")
    mods = s["modules"]
    good = [m for m in mods if m["name"] not in EXPECT]
    res: dict[str, Any] = {
        "seed": seed, "scale": scale, "mode": mode, "result": s["result"], "wall_s": run.wall_s,
        "good": len(good), "false_flags": sum(m["verdict"] == FLAGGED for m in good),
        "false_flagged": [m["name"] for m in good if m["verdict"] == FLAGGED],
        # a good module the run could not decide (uncertain) or could not see (unverified)
        "undecided": sum(m["verdict"] in (UNCERTAIN, UNVERIFIED) for m in good),
        "faults_caught": sum(1 for m in mods if m["name"] in EXPECT and m["verdict"] == EXPECT[m["name"]]),
        "faults": sum(1 for m in mods if m["name"] in EXPECT),
        "position_errors_m": [m["position_error_m"] for m in good if m["position_error_m"] is not None],
        "rotation_errors_rad": [m["rotation_error_rad"] for m in good if m["rotation_error_rad"] is not None],
        # the Cramér-Rao bound of each good module's views (expected RMS of its position error)
        "bound_rms_m": [m["bound_position_rms_m"] for m in good if m.get("bound_position_rms_m") is not None],
        "views": s.get("views"),
        "corner_rms_px": s.get("corner_rms_px"),
        "slam_update_s_median": run.slam_update_s_median,
    }
    survey = s.get("rig_survey")
    if survey:
        res["calibration_truth_error"] = survey.get("truth_error")
        res["calibration_nees"] = survey.get("nees")
        res["calibration_problems"] = survey.get("problems")
    return res


@dataclass(frozen=True)
class RunSpec:
    """One `lab run borg` of the study; the trial's seed is the scenario's seed."""

    out: str        # absolute: a Dask worker's working directory is its own
    scale: float
    mode: str
    modules: int
    speedup: float


def calibration_trial(t: Trial) -> dict[str, Any]:
    s: RunSpec = t.spec
    return trial(Path(s.out), t.seed, s.scale, s.mode, s.modules, s.speedup)


def _aggregate(trials: list[dict[str, Any]]) -> list[dict[str, Any]]:
    groups: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for t in trials:
        groups.setdefault((t["mode"], t["scale"]), []).append(t)
    rows = []
    for (mode, scale), ts in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1])):
        pos = np.concatenate([t["position_errors_m"] for t in ts]) if ts else np.array([])
        rot = np.concatenate([t["rotation_errors_rad"] for t in ts]) if ts else np.array([])
        good = sum(t["good"] for t in ts)
        row: dict[str, Any] = {
            "mode": mode, "rig_error_scale": scale, "runs": len(ts), "good_modules": good,
            "false_flags": sum(t["false_flags"] for t in ts),
            "false_flag_rate": sum(t["false_flags"] for t in ts) / max(good, 1),
            "faults_caught": f"{sum(t['faults_caught'] for t in ts)}/{sum(t['faults'] for t in ts)}",
            "position_error_mm_median": float(np.median(pos) * 1e3) if pos.size else None,
            "position_error_mm_max": float(pos.max() * 1e3) if pos.size else None,
            "rotation_error_deg_median": float(np.degrees(np.median(rot))) if rot.size else None,
            "rotation_error_deg_max": float(np.degrees(rot.max())) if rot.size else None,
            "undecided": sum(t.get("undecided", 0) for t in ts),
            "position_rmse_over_bound": _rmse_over_bound(ts),
            "slam_update_ms_median": float(np.median([t["slam_update_s_median"] for t in ts]) * 1e3),
            "wall_s_median": float(np.median([t["wall_s"] for t in ts])),
        }
        cal = [t["calibration_truth_error"] for t in ts if t.get("calibration_truth_error")]
        if cal:
            for name in ("camera_mount", "stewart_base", "turntable_axis"):
                vals = [c[f"{name}_m"] * 1e3 for c in cal]
                row[f"{name}_mm_max"], row[f"{name}_mm_median"] = max(vals), float(np.median(vals))
            for name in ("camera_mount", "stewart_base"):
                vals = [math.degrees(c[f"{name}_rad"]) for c in cal]
                row[f"{name}_deg_max"], row[f"{name}_deg_median"] = max(vals), float(np.median(vals))
            row["focal_percent_max"] = max(c.get("focal_rel", 0.0) for c in cal) * 100
            nees = [t["calibration_nees"] for t in ts if t.get("calibration_nees")]
            for key in ("platform_T_camera", "world_T_base"):
                row[f"nees_{key}_mean"] = float(np.mean([n[key] for n in nees]))
        rows.append(row)
    return rows


def _rmse_over_bound(ts: list[dict[str, Any]]) -> float | None:
    """Achieved position RMSE over the RMS of the bound, over the runs' good modules that have one."""
    pos = np.concatenate([t["position_errors_m"] for t in ts if t.get("bound_rms_m")
                          and len(t["bound_rms_m"]) == len(t["position_errors_m"])] or [np.array([])])
    bound = np.concatenate([t["bound_rms_m"] for t in ts if t.get("bound_rms_m")
                            and len(t["bound_rms_m"]) == len(t["position_errors_m"])] or [np.array([])])
    if not pos.size or not bound.size:
        return None
    return float(np.sqrt(np.mean(pos ** 2)) / np.sqrt(np.mean(bound ** 2)))


def to_markdown(res: dict[str, Any]) -> str:
    lines = [study_heading(res), "",
             "| mode | rig error | runs | false flags | uncertain or unverified | faults caught | "
             "pos. error median / max (mm) | RMSE / bound | rot. error median / max (deg) | SLAM step median (ms) | "
             "run wall median (s) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        lines.append(f"| {r['mode']} | {r['rig_error_scale']:g}x default | {r['runs']} | "
                     f"{r['false_flags']}/{r['good_modules']} ({100 * r['false_flag_rate']:.1f} %) | "
                     f"{r.get('undecided', 0)} | "
                     f"{r['faults_caught']} | {cell(r['position_error_mm_median'])} / {cell(r['position_error_mm_max'])} | "
                     f"{cell(r.get('position_rmse_over_bound'))} | "
                     f"{cell(r['rotation_error_deg_median'], '.3f')} / {cell(r['rotation_error_deg_max'], '.3f')} | "
                     f"{r['slam_update_ms_median']:.1f} | {r['wall_s_median']:.0f} |")
    cal_rows = [r for r in res["rows"] if "camera_mount_mm_max" in r]
    if cal_rows:
        lines += ["", "Rig calibration survey against the simulated truth (largest over the runs):", "",
                  "| rig error | mount mm median / max | mount deg median / max | base mm median / max | "
                  "base deg median / max | axis mm max | focal % max | mean NEES mount / base (dim 6) |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in cal_rows:
            lines.append(f"| {r['rig_error_scale']:g}x | {r['camera_mount_mm_median']:.2f} / {r['camera_mount_mm_max']:.2f} | "
                         f"{r['camera_mount_deg_median']:.3f} / {r['camera_mount_deg_max']:.3f} | "
                         f"{r['stewart_base_mm_median']:.2f} / {r['stewart_base_mm_max']:.2f} | "
                         f"{r['stewart_base_deg_median']:.3f} / {r['stewart_base_deg_max']:.3f} | "
                         f"{r['turntable_axis_mm_max']:.2f} | {r['focal_percent_max']:.3f} | "
                         f"{r['nees_platform_T_camera_mean']:.1f} / {r['nees_world_T_base_mean']:.1f} |")
    return "\n".join(lines)


def _progress(r: dict[str, Any]) -> str:
    pe = max(r["position_errors_m"], default=float("nan")) * 1e3
    return (f"  {r['mode']:<15} x{r['scale']:g} seed {r['seed']}: {r['false_flags']} false flags of "
            f"{r['good']}, faults {r['faults_caught']}/{r['faults']}, max position error {pe:.2f} mm")


def run(args: argparse.Namespace) -> int:
    from lab.core.errors import UserError

    if args.report:
        return report_study(args.report, "calibration", _aggregate, to_markdown)
    seeds, modules, scales = study_size(args, quick_scales="0,2")
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    bad = [m for m in modes if m not in MODES]
    if bad or not modes:
        raise UserError(f"--modes: expected some of {', '.join(MODES)}, got {args.modes!r}")
    if not 1 <= modules <= 27 or seeds < 1 or any(not 0 <= s <= 2.5 for s in scales):
        raise UserError("--modules must be in 1..27, --seeds >= 1, --scales in [0, 2.5]")
    out = Path(args.out).resolve()
    # seed by seed across every configuration: with fewer workers than trials, an interrupted study
    # still covers every configuration
    runs = [Trial(f"{mode}-x{scale:g}-seed{seed}", seed, RunSpec(str(out), scale, mode, modules, args.speedup))
            for seed in range(seeds) for scale in scales for mode in modes]
    return run_trial_study(args, "calibration", runs, calibration_trial,
                           {"seeds": seeds, "modules": modules, "scales": scales, "modes": modes},
                           _aggregate, to_markdown, _progress)
