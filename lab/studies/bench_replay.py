"""`lab bench replay RUN_DIR`: a BORG run's estimator run again from the run's own inputs, timed
part by part, and its verdicts checked against the run's.

A run's checkpoint keeps every input its estimator was given (the rig survey's views, each round's
detections with the camera pose the rig reported) so that `lab resume` can rebuild the estimate
exactly.  This replays them through the same path (`BorgProcedure.replay_estimator`, on the run's
procedure built from its run.json as `lab run` built it, offline: no device is claimed or sent a
byte) with this checkout's code, and reports:

- the CPU time of this process (not wall time: a replay beside other jobs still reads the work it
  did) of each round's step (the round's solve: its views' factors, iSAM2, the module's
  marginals), each module's verdict and its release (its relations tied once the verdict is
  final): totals, per-round median / p90 / max, the step by quarter of the run and the worst
  rounds; and inside them iSAM2's updates, its marginals and its estimate;
- every module's verdict, deviation and 1-sigma against the run's summary.json;
- for a simulated run, the replayed graph's own rig (mount, base, axis, lift, intrinsics) against the
  simulated world's true rig, each with its NEES, beside the run's (`rig_in_graph`): whether the
  graph's covariance still covers its rig after every view refined it, and what an estimator
  change does to that.

So a change to the estimator is measured on the very run that showed the problem (an N = 9 run
whose verdict marginals took 19 s), paired against the code before it (the same command on the
older commit), and a change that claims to be exact shows every verdict equal.  Left out: the
device moves and the camera (the detections are the run's, not detected again), the logging and
the checkpoints, the plan's accuracy pass; a run that was resumed replays as one run."""

from __future__ import annotations

import argparse
import json
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

PARTS = ("step", "verdict", "release")
INNER = ("update", "marginals", "estimate")
WORST = 8


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", metavar="RUN_DIR", help="a BORG run's directory (finished, or stopped with a checkpoint)")
    p.add_argument("--rounds", type=int, default=None, metavar="K", help="replay only the first K rounds")
    p.add_argument("--near-tags-per-view", type=int, default=None, metavar="K",
                   help="besides the module's own tags, put in the graph each view's sightings of the K tags nearest "
                        "the module (0: every sighting; default: the run's own, from its summary)")
    p.add_argument("--settle-after-layers", type=int, default=None, metavar="K",
                   help="settle each layer once a module K layers above it is released (0: never, the full graph; "
                        "default: the run's own, from its summary; a run from before settling: 0)")
    p.add_argument("--no-semantic", action="store_true",
                   help="leave the semantic factors out (no related pair tied to its design), to see what they do")
    p.add_argument("--json", action="store_true", help="print the figures (and every round's) as JSON")


@dataclass
class _Clock:
    """CPU seconds by (part, what) for the round being replayed."""

    part: str = ""
    rounds: list[dict[str, Any]] = field(default_factory=list)   # per round; "module" its module

    def add(self, what: str, seconds: float) -> None:
        row = self.rounds[-1]
        key = f"{self.part}.{what}" if self.part else what
        row[key] = row.get(key, 0.0) + seconds


class _TimedISAM2:
    """The estimator's iSAM2, its calls timed into the clock: where a part's CPU goes."""

    def __init__(self, isam: Any, clock: _Clock) -> None:
        self._isam = isam
        self._clock = clock

    def _timed(self, what: str, call: Callable[[], Any]) -> Any:
        t0 = time.process_time()
        try:
            return call()
        finally:
            self._clock.add(what, time.process_time() - t0)

    def update(self, *args: Any, **kwargs: Any) -> Any:
        result = self._timed("update", lambda: self._isam.update(*args, **kwargs))
        self._clock.add("reeliminated", float(result.getVariablesReeliminated()))
        self._clock.add("relinearized", float(result.getVariablesRelinearized()))
        return result

    def marginalCovariance(self, key: int) -> Any:  # noqa: N802 (GTSAM's name)
        return self._timed("marginals", lambda: self._isam.marginalCovariance(key))

    def jointMarginalCovariance(self, keys: Any) -> Any:  # noqa: N802
        return self._timed("marginals", lambda: self._isam.jointMarginalCovariance(keys))

    def calculateEstimate(self) -> Any:  # noqa: N802
        return self._timed("estimate", lambda: self._isam.calculateEstimate())

    def __getattr__(self, name: str) -> Any:
        return getattr(self._isam, name)


def replay(run_dir: Path, rounds: int | None = None, near_tags_per_view: int | None = None,
           settle_after_layers: int | None = None, semantic: bool = True) -> dict[str, Any]:
    """Replay the run in `run_dir` (its first `rounds` rounds; with the estimator's
    `near_tags_per_view` and `settle_after_layers`, default the run's, and its semantic factors
    unless `semantic` is false); the figures `to_markdown` prints."""
    from lab.core.errors import UserError
    from procedures.resume import load_run
    from procedures.borg import views_by_round
    from procedures.build import build_procedure

    info, ckpt = load_run(run_dir, completed=True)
    if info["procedure"] != "borg":
        raise UserError(f"{run_dir}: a {info['procedure']} run; `lab bench replay` replays BORG runs")
    state = ckpt.get("state") or {}
    views = state.get("views") or []
    if not views:
        raise UserError(f"{run_dir / 'checkpoint.json'}: no view of a module was taken; nothing to replay")
    if rounds is not None and rounds < 1:
        raise UserError(f"--rounds must be at least 1, got {rounds}")
    if near_tags_per_view is not None and near_tags_per_view < 0:
        raise UserError(f"--near-tags-per-view must be 0 (every sighting) or more, got {near_tags_per_view}")
    if settle_after_layers is not None and settle_after_layers < 0:
        raise UserError(f"--settle-after-layers must be 0 (never) or more, got {settle_after_layers}")
    summary_path = run_dir / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    wall0, cpu0 = time.perf_counter(), time.process_time()
    proc, bench, structure = build_procedure("borg", info["params"], offline=True)
    if near_tags_per_view is None:
        # as the run did: a run from before the count existed (no `sightings` in its summary) put
        # every sighting in the graph
        near_tags_per_view = int((summary.get("sightings") or {}).get("near_tags_per_view", 0))
    proc.measure.config["near_tags_per_view"] = near_tags_per_view
    if settle_after_layers is None:
        # as the run did: a run from before settling (no `settled` in its summary) kept the whole graph
        settle_after_layers = int((summary.get("settled") or {}).get("after_layers", 0))
    proc.measure.config["settle_after_layers"] = settle_after_layers
    proc.measure.config["semantic"] = semantic
    clock = _Clock()
    verdicts: dict[str, Any] = {}
    survey_s = 0.0

    def timed(part: str, call: Callable[[], Any]) -> Any:
        nonlocal survey_s
        t0 = time.process_time()
        if part == "survey":
            result = call()
            survey_s += time.process_time() - t0
            return result
        slam = proc.measure.slam
        if not isinstance(slam.isam, _TimedISAM2):
            slam.isam = _TimedISAM2(slam.isam, clock)
        if part == "step":
            clock.rounds.append({})
        clock.part = part
        try:
            result = call()
        finally:
            clock.part = ""
            clock.add(part, time.process_time() - t0)
        if part == "verdict":
            verdicts[result.module] = result
        return result

    try:
        modules = [taken[0]["module"] for _, taken in views_by_round(views)]
        proc.replay_estimator(state, timed, rounds=rounds)
        rig_truth = rig_against_truth(proc.measure.slam, bench.rig, bench.scenario, info["params"].get("n"))
    finally:
        bench.close()
    for row, module in zip(clock.rounds, modules):
        row["module"] = module
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    return {"run_dir": str(run_dir), "structure": structure, "rounds": len(clock.rounds), "rounds_in_run": len(modules),
            "modules": len({r["module"] for r in clock.rounds}), "survey_s": survey_s, "cpu_s": cpu, "wall_s": wall,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "near_tags_per_view": proc.measure.near_tags_per_view, "sightings_in_graph": proc.measure.sightings[0],
            "settle_after_layers": proc.measure.settle_after_layers, "settled_tags": len(proc.measure.slam.settled),
            "sightings": proc.measure.sightings[1],
            "semantic": semantic, "per_round": clock.rounds,
            "against_summary": compare(verdicts, summary.get("modules", [])),
            "rig_in_graph": rig_truth, "rig_in_graph_run": summary.get("rig_in_graph")}


def rig_against_truth(slam: Any, rig: Any, scenario: Any, borg_n: int | None) -> dict[str, Any] | None:
    """(A simulated run only.)  The replayed graph's rig variables against the true rig of the
    world the run simulated, rebuilt from its rig and scenario (`procedures.rig_survey.
    graph_against_truth`, as the run's summary reports it); None for a real bench's run or an
    uncalibrated one (no rig in the graph)."""
    if rig.sim is None or slam.rig is None:
        return None
    from procedures.rig_survey import graph_against_truth
    from sim_devices.world import SimWorld

    return graph_against_truth(slam, SimWorld(rig, scenario, borg_n=borg_n))


def compare(verdicts: dict[str, Any], rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The replayed verdicts against the run's summary rows: how many equal, the largest deviation
    difference (position, m; rotation, rad) and the largest relative 1-sigma difference, and the
    modules that differ."""
    by_name = {r["name"]: r for r in rows}
    differ, dev, dev_rad, sig, compared = [], 0.0, 0.0, 0.0, 0
    ratios: list[float] = []
    for name, v in verdicts.items():
        r = by_name.get(name)
        if r is None:
            continue
        compared += 1
        if v.verdict != r["verdict"]:
            differ.append({"module": name, "run": r["verdict"], "replay": v.verdict})
        if v.deviation_m is not None and r.get("deviation_m") is not None:
            dev = max(dev, abs(v.deviation_m - r["deviation_m"]))
        if v.deviation_rad is not None and r.get("deviation_rad") is not None:
            dev_rad = max(dev_rad, abs(v.deviation_rad - r["deviation_rad"]))
        if v.sigma_m is not None and r.get("sigma_position_m"):
            sig = max(sig, abs(v.sigma_m - r["sigma_position_m"]) / r["sigma_position_m"])
            ratios.append(v.sigma_m / r["sigma_position_m"])
    return {"compared": compared, "in_summary": len(rows), "verdicts_differ": differ,
            "max_deviation_diff": dev, "max_rotation_diff": dev_rad, "max_sigma_rel_diff": sig,
            # the replay's 1-sigma over the run's: min / median / max
            "sigma_ratio": [float(np.min(ratios)), float(np.median(ratios)), float(np.max(ratios))] if ratios else None}


def _near(k: int) -> str:
    return "every sighting" if k <= 0 else f"the module's own tags' and each view's {k} other tags nearest it"


def _settled(res: dict[str, Any]) -> str:
    k = res.get("settle_after_layers", 0)
    if not k:
        return "Nothing settled (the whole graph in the solver)."
    return (f"A layer settled once a module {k} layer{'s' if k > 1 else ''} above it was released: "
            f"{res.get('settled_tags', 0):,} tags settled.")


def _ms(xs: list[float]) -> str:
    if not xs:
        return "–"
    a = np.asarray(xs) * 1e3
    return f"{np.median(a):.0f} / {np.percentile(a, 90):.0f} / {a.max():.0f}"


def to_markdown(res: dict[str, Any], command: str) -> list[str]:
    rows = res["per_round"]
    total = {k: sum(r.get(k, 0.0) for r in rows) for k in {k for r in rows for k in r if k != "module"}}
    lines = [f"Command: `{command}` — {res['rounds']} of {res['rounds_in_run']} rounds ({res['modules']} modules) of "
             f"{res['structure']}, replayed in {res['wall_s']:.0f} s ({res['cpu_s']:.0f} s CPU, the procedure's "
             f"plans and the survey's solve ({res['survey_s']:.1f} s) included); peak memory "
             f"{res['peak_rss_mb']:.0f} MB.  Sightings in the graph: {res['sightings_in_graph']:,} of "
             f"{res['sightings']:,} ({_near(res['near_tags_per_view'])}).  {_settled(res)}", "",
             "| part | CPU total (s) | per round median / p90 / max (ms) | of it iSAM2 updates (s) | marginals (s) | "
             "estimate (s) | variables re-eliminated |", "|---|---|---|---|---|---|---|"]
    for part in PARTS:
        per = [r.get(part, 0.0) for r in rows if part in r]
        inner = [f"{total.get(f'{part}.{w}', 0.0):.2f}" for w in INNER]
        lines.append(f"| {part} | {total.get(part, 0.0):.2f} | {_ms(per)} | {' | '.join(inner)} | "
                     f"{int(total.get(f'{part}.reeliminated', 0)):,} |")
    steps = [r.get("step", 0.0) for r in rows]

    def by_quarter(xs: list[float], scale: float = 1.0) -> str:
        # the quarters the speed study takes (bench_scaling): every round in one, none dropped
        return " / ".join(f"{np.median(part) * scale:.0f}" for part in np.array_split(np.asarray(xs, float), 4)
                          if len(part))

    # what grows with the run: the variables each step's updates re-eliminate (the Bayes tree from
    # the touched tags to the root), with those past the relinearisation threshold among them
    reelim = [r.get("step.reeliminated", 0.0) for r in rows]
    relin = [r.get("step.relinearized", 0.0) for r in rows]
    lines += ["", f"Step CPU median by quarter of the run: {by_quarter(steps, 1e3)} ms; variables its iSAM2 updates "
                  f"re-eliminate, median by quarter: {by_quarter(reelim)} (relinearised: {by_quarter(relin)}).", "",
              "Worst rounds (step + verdict + release):", "",
              "| round | module | step (ms) | of it marginals (ms) | verdict (ms) | release (ms) |", "|---|---|---|---|---|---|"]
    cost = [r.get("step", 0.0) + r.get("verdict", 0.0) + r.get("release", 0.0) for r in rows]
    for i in sorted(range(len(rows)), key=lambda i: -cost[i])[:WORST]:
        r = rows[i]
        lines.append(f"| {i} | {r['module']} | {r.get('step', 0.0) * 1e3:.0f} | {r.get('step.marginals', 0.0) * 1e3:.0f} | "
                     f"{r.get('verdict', 0.0) * 1e3:.0f} | {r.get('release', 0.0) * 1e3:.0f} |")
    c = res["against_summary"]
    same = c["compared"] - len(c["verdicts_differ"])
    lines += ["", f"Against the run's summary: {same} of {c['compared']} verdicts the same "
                  f"({c['in_summary']} modules in it); deviations within {c['max_deviation_diff']:.1e} m and "
                  f"{c.get('max_rotation_diff', 0.0):.1e} rad, "
                  f"1σ within {c['max_sigma_rel_diff']:.1e} relative"
                  + (f" (replay / run: min {c['sigma_ratio'][0]:.4f}, median {c['sigma_ratio'][1]:.4f}, "
                     f"max {c['sigma_ratio'][2]:.4f})." if c.get("sigma_ratio") else ".")]
    for d in c["verdicts_differ"]:
        lines.append(f"- {d['module']}: the run said {d['run']}, the replay {d['replay']}")
    lines += _rig_lines(res)
    return lines


def _rig_lines(res: dict[str, Any]) -> list[str]:
    """The graph's rig against the simulated truth at the replay's end, beside the run's (in the
    order `graph_against_truth` gives its parts)."""
    mine, run = res.get("rig_in_graph"), res.get("rig_in_graph_run") or {}
    if not mine:
        return []
    names = list(mine)
    semantic = "" if res.get("semantic", True) else ", semantic factors left out"
    lines = ["", f"The graph's own rig against the simulated truth where the replay ended{semantic} (NEES of its "
                 "marginal; expected about its dof):", "",
             "| | " + " | ".join(f"{n} ({mine[n]['dof']})" for n in names) + " |", "|---|" + "---|" * len(names),
             "| replay | " + " | ".join(f"{mine[n]['nees']:.1f}" for n in names) + " |"]
    if run:
        lines.append("| the run, at its end | " + " | ".join(f"{run[n]['nees']:.1f}" if n in run else "–" for n in names) + " |")
    return lines


def run(args: argparse.Namespace) -> int:
    import shlex
    import sys

    res = replay(Path(args.run_dir), args.rounds, args.near_tags_per_view, args.settle_after_layers,
                 semantic=not args.no_semantic)
    if args.json:
        print(json.dumps(res, default=float))
    else:
        command = "lab bench replay " + " ".join(shlex.quote(a) for a in sys.argv[3:])
        print("\n".join(to_markdown(res, command)))
    return 0
