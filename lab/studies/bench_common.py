"""Small pieces the benchmark modules share."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from lab.core.executor import Trial, open_study, without_executor_args
from lab.core.executor.journal import finite_values


def save_figure(fig, out_dir: str, name: str, dpi: int = 110) -> str:
    """Lay out, write and close a matplotlib figure; returns the file's path."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = os.path.join(out_dir, name)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def unit_vector(rng: np.random.Generator) -> np.ndarray:
    """A direction drawn uniformly on the sphere (a fault's seeded offset or rotation axis)."""
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def median_metric(path: Path, name: str) -> float:
    """The median of a run's metric (`slam/update_s`) from its MCAP; nan if it logged none."""
    from lab.core.runs import run_metrics

    vals = sorted(run_metrics(path).get(name, ("", []))[1])
    return vals[len(vals) // 2] if vals else float("nan")


@dataclass(frozen=True)
class BorgRun:
    cmd: list[str]
    summary: dict[str, Any]
    wall_s: float
    peak_rss_mb: float | None        # measured with a log only
    slam_update_s_median: float


def run_borg(args: Sequence[str], out: Path, log: Path | None = None) -> BorgRun:
    """One trial of a study: a real `lab run borg --auto --quiet --on-flag continue ARGS`, in a process
    of its own, into `out` (`--replace`: a trial re-run over an earlier study's directory starts
    afresh).  With `log` its output goes there and its peak resident memory is measured; without,
    a run that wrote no summary is reported with the tail of its stderr."""
    cmd = [sys.executable, "-m", "lab", "run", "borg", "--auto", "--quiet", "--on-flag", "continue", *args,
           "--out", str(out), "--replace"]
    return _borg_process(cmd, out, log, "w")


def resume_borg(out: Path, log: Path | None = None) -> BorgRun:
    """`lab resume OUT --auto`: an interrupted trial's run goes on from its last completed step
    (its output appended to `log`).  The BorgRun's wall time and peak memory are the resumed
    process's own."""
    return _borg_process([sys.executable, "-m", "lab", "resume", str(out), "--auto"], out, log, "a")


def _borg_process(cmd: list[str], out: Path, log: Path | None, mode: str) -> BorgRun:
    t0 = time.perf_counter()
    peak_mb = None
    if log is not None:
        with open(log, mode) as f:
            p = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
            _, status, usage = os.wait4(p.pid, 0)
        code, peak_mb = os.waitstatus_to_exitcode(status), usage.ru_maxrss / 1024.0
        failure = f"failed (exit {code}): see {log}"
    else:
        r = subprocess.run(cmd, capture_output=True, text=True)
        failure = f"failed: {r.stderr.strip()[-500:]}"
    wall = time.perf_counter() - t0
    if not (out / "summary.json").exists():
        raise RuntimeError(f"{' '.join(cmd)} {failure}")
    summary = json.loads((out / "summary.json").read_text())
    return BorgRun(cmd, summary, wall, peak_mb, median_metric(out / "run.mcap", "slam/update_s"))


def graph_nees(summary: dict[str, Any]) -> dict[str, float]:
    """A simulated run's graph, its own rig against the truth as the run ended: variable -> NEES
    (summary `rig_in_graph`; empty for a run from before it was reported)."""
    return {k: v["nees"] for k, v in (summary.get("rig_in_graph") or {}).items()}


def cell(value: Any, spec: str = ".2f") -> str:
    """A table cell of a study's markdown: the figure, or a dash where there is none."""
    return "—" if value is None else format(value, spec)


def study_heading(res: dict[str, Any]) -> str:
    """The line above a trial study's table: the command that made it, its runs and its time."""
    return f"`{res['command']}` ({res['runs']} runs, {res['wall_s']:.0f} s)"


def study_size(args: argparse.Namespace, quick_scales: str) -> tuple[int, int, list[float]]:
    """Seeds, modules per run and rig-error scales of a trial study (`lab bench trust`,
    `lab bench calibration`): the flags, else 2 x 9 modules with `quick_scales` under --quick,
    else 10 x 27 at 0, 1 and 2 times the default rig errors."""
    from lab.core.errors import UserError

    seeds = args.seeds if args.seeds is not None else (2 if args.quick else 10)
    modules = args.modules if args.modules is not None else (9 if args.quick else 27)
    try:
        scales = [float(x) for x in (args.scales or (quick_scales if args.quick else "0,1,2")).split(",")]
    except ValueError:
        raise UserError(f"--scales: expected numbers separated by commas, got {args.scales!r}") from None
    return seeds, modules, scales


def report_study(paths: str | Sequence[str], name: str, aggregate: Callable[[list[dict]], list[dict]],
                 to_markdown: Callable[[dict], str]) -> int:
    """`lab bench NAME --report FILE [FILE ...]`: the tables of a finished or interrupted study's
    NAME.json, or of several studies' trials together (the same trial in two files is refused: a
    seed counted twice would look like more evidence than there is)."""
    from lab.core.errors import UserError

    paths = [paths] if isinstance(paths, str) else list(paths)
    merged: dict[str, Any] | None = None
    seen: dict[tuple, str] = {}
    for path in paths:
        try:
            res = json.loads(Path(path).read_text())
            trials = res["trials"]
            keys = [tuple((k, t[k]) for k in _TRIAL_IDENTITY if k in t) for t in trials]
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise UserError(f"--report {path}: not a study's {name}.json ({exc})") from None
        for key in keys:
            if key in seen:
                raise UserError(f"--report {path}: its trial {_trial_name(key)} is also in {seen[key]}")
            seen[key] = path
        if merged is None:
            merged = res
        else:
            merged["trials"] = merged["trials"] + trials
            merged["runs"] = merged.get("runs", 0) + res.get("runs", len(trials))
            merged["wall_s"] = merged.get("wall_s", 0.0) + res.get("wall_s", 0.0)
            merged["command"] = f"{merged['command']}; {res['command']}"
    assert merged is not None
    try:
        merged["rows"] = aggregate(merged["trials"])
        text = to_markdown(merged)
    except (ValueError, KeyError, TypeError) as exc:
        raise UserError(f"--report {', '.join(paths)}: not a study's {name}.json ({exc})") from None
    print(text)
    return 0


# what names a trial in the studies' journals (layers: N and seed; trust: camera, scale and seed; ...)
_TRIAL_IDENTITY = ("n", "camera", "mode", "scale", "seed")


def _trial_name(key: tuple) -> str:
    return ", ".join(f"{'N' if k == 'n' else k} {v}" for k, v in key)


def run_trial_study(args: argparse.Namespace, name: str, runs: Sequence[Trial], trial: Callable[[Trial], dict],
                    params: dict[str, Any], aggregate: Callable[[list[dict]], list[dict]],
                    to_markdown: Callable[[dict], str], progress: Callable[[dict], str]) -> int:
    """Run a study's trials through `lab.core.executor` (workers or Dask; journaled, so the same command
    resumes), writing --out/NAME.json after every trial (an interrupted study's file has every
    finished one) and printing its tables (or, with --json, its figures) at the end.  `params`
    name the study (the journal's header, with the speed-up) and go into NAME.json; `progress`
    is the line said for a finished trial."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    finished: dict[str, dict[str, Any]] = {}
    argv = without_executor_args([a for a in sys.argv[3:] if a != "--json"])
    command = (f"lab bench {name} " + " ".join(argv)).strip()
    order = {t.key: i for i, t in enumerate(runs)}

    def result(study_executor: str) -> dict[str, Any]:
        trials = [finished[k] for k in sorted(finished, key=order.__getitem__)]
        return {"command": command, "runs": len(trials), "wall_s": time.perf_counter() - t0, **params,
                "rows": aggregate(trials), "trials": trials, "executor": study_executor}

    # a restored trial is an input: its numbers finite (these studies write null for "none"), so
    # a NaN typed into the journal is refused, not drawn
    with open_study(args, out, {"bench": name, **params, "speedup": args.speedup}, f"lab bench {name}",
                    validate=finite_values) as study:
        def done(t: Trial, r: dict[str, Any]) -> None:
            finished[t.key] = r
            (out / f"{name}.json").write_text(json.dumps(result(study.describe()), indent=1))
            if not args.json:
                study.say(progress(r))

        study.map(trial, list(runs), on_result=done)
        res = result(study.describe())
        (out / f"{name}.json").write_text(json.dumps(res, indent=1))
        study.finish()
    if args.json:
        print(json.dumps({k: v for k, v in res.items() if k != "trials"}, indent=1))
    else:
        print(to_markdown(res))
    return 0
