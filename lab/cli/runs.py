"""`lab runs [--root DIR] [--json]` and `lab runs show RUN [--timings]`: the catalogue of past runs
(lab/core/runs.py)."""

from __future__ import annotations

import argparse
import json


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("runs", help="list past runs (id, procedure, rig, start, duration, result, counts)",
                       description="List the runs under the runs root, read from their own files. The root: "
                                   "--root, else $LAB_RUNS, else `runs = \"DIR\"` in ~/.config/lab/config.toml "
                                   "($LAB_CONFIG), else ./runs.")
    _common(p)
    p.set_defaults(func=_list)
    rsub = p.add_subparsers(dest="runs_command", metavar="show")
    s = rsub.add_parser("show", help="a run's summary and its verdict (or node) table")
    s.add_argument("run", metavar="RUN", help="a run id from `lab runs`, a run directory or its run.mcap")
    s.add_argument("--timings", action="store_true",
                   help="also the run's metrics from run.mcap: count, median, 90th percentile, max of each and "
                        "the total of times (slam/update_s: the estimator's time per BORG step; motion/move_s: "
                        "the devices' moves; camera/grab_s: the camera's frames)")
    _common(s)
    s.set_defaults(func=_show)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--root", metavar="DIR", default=argparse.SUPPRESS,
                   help="runs root (default: $LAB_RUNS, the user config's runs, else ./runs)")
    p.add_argument("--json", action="store_true", default=argparse.SUPPRESS, help="machine-readable output")


def _root(args: argparse.Namespace):
    from pathlib import Path

    from lab.core.runs import runs_root

    return Path(args.root) if getattr(args, "root", None) else runs_root()[0]


def _list(args: argparse.Namespace) -> int:
    from lab.core.runs import format_list, list_runs

    root = _root(args)
    entries = list_runs(root)
    if getattr(args, "json", False):
        print(json.dumps({"root": str(root), "runs": [e.to_json() for e in entries]}, indent=1))
        return 0
    if not entries:
        print(f"no runs under {root}")
        return 0
    print(format_list(entries))
    print(f"{len(entries)} run{'s' if len(entries) != 1 else ''} under {root}; `lab runs show ID` for one")
    return 0


def _show(args: argparse.Namespace) -> int:
    from lab.core.errors import UserError
    from lab.core.runs import format_duration, read_run, resolve_run

    root = _root(args)
    run_dir = resolve_run(args.run, root)
    entry = read_run(run_dir, root)
    from lab.core.runs import read_summary_file

    sf = read_summary_file(run_dir)
    summary = sf.summary
    damaged = f"{run_dir / 'summary.json'}: {sf.problem}" if sf.problem not in ("", "missing") else ""
    if damaged and getattr(args, "json", False):
        raise UserError(f"{damaged}: the run's summary is damaged (`lab runs show {args.run}` without --json shows "
                        f"what run.mcap says)")
    timings = None
    if getattr(args, "timings", False):
        from dataclasses import asdict

        from lab.core.runs import RUN_FILE, metric_stats, run_metrics

        mcap = run_dir / RUN_FILE
        timings = metric_stats(run_metrics(mcap)) if mcap.exists() else []
        if getattr(args, "json", False):
            timings = [asdict(m) for m in timings]
    if getattr(args, "json", False):
        out = {"run": entry.to_json(), "summary": summary}
        if timings is not None:
            out["timings"] = timings
        print(json.dumps(out, indent=1))
        return 0
    print(f"run {entry.id}  ({run_dir})")
    print(f"procedure {entry.procedure or '?'}  structure {entry.structure or '?'}  rig {entry.rig or '?'}")
    print(f"started {entry.start or '?'}  duration {format_duration(entry.duration_s)}  "
          f"steps completed {entry.steps_completed}")
    print(f"result {entry.result}{' - ' + entry.reason if entry.reason else ''}")
    if entry.argv:
        print("command: lab " + " ".join(entry.argv[1:]))
    if damaged:
        # the run's own record (above, from run.mcap) stands; the tables cannot be trusted
        raise UserError(f"{damaged}: the run's summary is damaged, so no table is shown (the lines above are from "
                        f"run.mcap)")
    if summary is None:
        if entry.result in ("completed", "aborted", "failed"):
            print(f"no summary.json: the run ended {entry.result} and wrote one, so it was deleted or moved since")
        elif entry.result == "running":
            print("no summary.json yet: the run has not finished its first step")
        else:
            print("no summary.json (the run stopped before its first step ended)")
        return 0
    print()
    from procedures.console import borg_table, truss_table

    if isinstance(summary.get("modules"), list):
        print(borg_table(summary))
    elif isinstance(summary.get("nodes"), list):
        print(truss_table(summary))
    else:
        print(json.dumps({k: v for k, v in summary.items() if k not in ("result", "reason")}, indent=1)[:4000])
    if timings is not None:
        from lab.core.runs import format_metrics

        print()
        print(format_metrics(timings) if timings else "no metrics in run.mcap")
    return 0
