"""`lab run borg|truss` and `lab resume RUN_DIR`: operator-run procedures (procedures/)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from lab.core.survey_budget import MAX_VIEWS, MAX_VIEWS_RANGE, SIGMA_TARGET_MM, SIGMA_TARGET_MM_MAX


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run an assembly procedure (simulated devices with the default rig)")
    rsub = p.add_subparsers(dest="procedure", metavar="PROCEDURE")
    rsub.required = True

    b = rsub.add_parser("borg", help="BORG assemble-measure-verify: place each module, survey, SF-GraphSLAM, verify")
    _common(b)
    b.add_argument("--on-flag", choices=("stop", "continue", "retry"), default="stop",
                   help="when a module is flagged: stop the run (default), continue, or ask for a re-deploy and re-measure")
    b.add_argument("--n", type=int, default=None,
                   help="BORG size, 2..10 (default: the rig's [sim] borg_n, else 3); a simulated rig simulates this size")
    b.add_argument("--modules", type=int, default=None, metavar="K",
                   help="assemble only the first K modules (a short run)")
    b.add_argument("--calibration", metavar="FILE",
                   help="rig calibration file from `lab calibrate rig` (default: the rig's [calibration] file; "
                        "without one the run begins with a rig calibration survey)")
    b.add_argument("--no-rig-survey", action="store_true",
                   help="without a calibration file, start from the rig file's nominal geometry and its wide "
                        "priors instead of a calibration survey (the run still refines the calibration)")
    b.add_argument("--uncalibrated", action="store_true",
                   help="trust the rig file's geometry exactly, as before rig calibration existed (for comparison "
                        "in benchmarks; a real rig is never that well known)")
    b.add_argument("--observation", choices=("corners", "corner-info", "pose"), default=None,
                   help="how a tag sighting enters SF-GraphSLAM: its four corners' reprojection (default) or the "
                        "detector's single-view pose")
    b.add_argument("--tolerance", action="append", default=None, metavar="KIND=MM,DEG",
                   help="a module type's tolerance, e.g. closeout_square=5,1 (KIND: deployable, closeout_strut, "
                        "closeout_square or all; repeatable; default: the rig's [verification] table, else 5 mm, 1 deg)")
    b.add_argument("--sigma-target-mm", type=float, default=None, metavar="MM",
                   help="plan each step's views until the new module's predicted position 1-sigma is this small "
                        f"(in (0, {SIGMA_TARGET_MM_MAX:g}] mm; default: the rig's [verification] sigma_target_mm, "
                        f"else {SIGMA_TARGET_MM:g})")
    b.add_argument("--allow-unobservable", action="store_true",
                   help="run even if the rig cannot see some modules (listed at the start; reported unverified) "
                        "instead of refusing before anything moves")
    b.add_argument("--max-views", type=int, default=None, metavar="N",
                   help=f"view budget per step, extra views for an uncertain verdict included "
                        f"({MAX_VIEWS_RANGE[0]}..{MAX_VIEWS_RANGE[1]}; default: the rig's [verification] max_views, "
                        f"else {MAX_VIEWS})")
    b.set_defaults(func=_run_borg)

    t = rsub.add_parser("truss", help="IPJR truss assembly with MLE / EKF / open-loop correction")
    t.add_argument("name", help="truss, as in `lab structure truss`: tetrahelix:20, telescope:45, ...")
    _common(t)
    t.add_argument("--estimator", choices=("mle", "ekf", "open-loop"), default="mle")
    t.add_argument("--plan", metavar="FILE", help="assembly plan from `lab plan truss NAME --json` (default: plan now)")
    t.add_argument("--plan-seed", type=int, default=0, help="seed of the sequence search when planning now")
    t.set_defaults(func=_run_truss)

    r = sub.add_parser("resume", help="resume an interrupted run: re-run the interrupted step, keep everything before")
    r.add_argument("run_dir", metavar="RUN_DIR")
    r.add_argument("--auto", action="store_true", help="answer operator prompts automatically (simulation)")
    r.add_argument("--view", nargs="?", const="auto", metavar="URL",
                   help="show the resumed run in Rerun as it happens (as for lab run; the original run's --view "
                        "is not reused: its viewer may be long gone)")
    r.set_defaults(func=_resume)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", metavar="FILE", help="rig file (default: the simulated bench, lab/rigs/sim.toml)")
    p.add_argument("--scenario", metavar="FILE", help="simulation scenario: seed, noise, faults (docs/scenarios.md)")
    p.add_argument("--out", metavar="DIR",
                   help="run directory (default: <runs root>/<procedure>-<time>; the root is $LAB_RUNS, the user "
                        "config's runs, else ./runs)")
    p.add_argument("--auto", action="store_true", help="answer operator prompts automatically (simulation)")
    p.add_argument("--dry-run", action="store_true", help="check every planned move against limits; move nothing")
    p.add_argument("--speedup", type=_speedup, default=None,
                   help="simulated devices move this many times faster (0 < S <= 1000)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--view", nargs="?", const="auto", metavar="URL",
                   help="show the run in Rerun as it happens, as `lab review` shows it afterwards: a local viewer "
                        "where there is a display, else the web viewer on 127.0.0.1 (URL printed); with URL "
                        "(rerun+http://HOST:PORT/proxy or HOST:PORT) a viewer that is already running")
    p.add_argument("--replace", action="store_true",
                   help="--out may hold an earlier run: delete its files and start afresh (refused otherwise)")


def _speedup(text: str) -> float:
    import math

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and 0 < value <= 1000):
        raise argparse.ArgumentTypeError(f"must be a number in (0, 1000], got {text!r}")
    return value


def _out_dir(args: argparse.Namespace, procedure: str) -> Path:
    """--out, else a new directory under the runs root ($LAB_RUNS, the user config's `runs`, else
    ./runs; lab/core/runs.py), named for the procedure and the time."""
    if args.out:
        return Path(args.out)
    from lab.core.runs import runs_root

    root, _ = runs_root()
    return root / f"{procedure}-{time.strftime('%Y%m%d-%H%M%S')}"


# the options that name a file: run.json keeps them absolute, so that `lab resume` and `lab bench
# replay` find the same files from any directory (a relative path would be read from theirs)
_FILE_OPTIONS = ("rig", "scenario", "calibration", "plan")


def _params(args: argparse.Namespace) -> dict[str, Any]:
    params = {k: v for k, v in vars(args).items() if k not in ("func", "command", "procedure") and not k.startswith("_")}
    for key in _FILE_OPTIONS:
        value = params.get(key)
        if isinstance(value, str) and Path(value).is_file():
            params[key] = str(Path(value).resolve())
    return params


def _run_borg(args: argparse.Namespace) -> int:
    return _execute("borg", _params(args))


def _run_truss(args: argparse.Namespace) -> int:
    return _execute("truss", _params(args))


def _execute(procedure: str, params: dict[str, Any], resume_dir: Path | None = None) -> int:
    """A new run (resume_dir None) or a resume.  Everything that can refuse — the run directory,
    its lock, run.json and checkpoint.json, the logs against the checkpoint, the devices' owners —
    refuses before any device moves and before any file of the run is touched."""
    import signal

    from lab.core.locks import set_holder
    from lab.core.recorder import RunRecorder
    from procedures.console import Console, ConsoleRecorder
    from procedures import resume as rs
    from procedures import runner
    from procedures.build import build_procedure

    dry = bool(params.get("dry_run"))
    if params.get("view") not in (None, "auto") and not dry:
        from lab.core.viewer import check_viewer_answers

        check_viewer_answers(params["view"])      # a URL nothing answers at: one line, before anything
    run_dir = resume_dir or _out_dir(argparse.Namespace(**params), procedure)
    created = not run_dir.exists()
    lock = None
    if not dry:
        lock = rs.lock_run_dir(run_dir) if resume_dir is not None else rs.prepare_out_dir(run_dir, bool(params.get("replace")))
        set_holder(run=str(run_dir))
    try:
        resume_state = None
        if resume_dir is not None:
            _, resume_state = rs.load_run(resume_dir)
        proc, bench, structure = build_procedure(procedure, params)
        if dry:
            try:
                return runner.dry_run(proc)
            finally:
                proc.close()
        if procedure == "borg":
            _check_observable(proc)
        plan = None
        try:
            if resume_state is not None:
                steps = proc.plan()
                done = int(resume_state["steps_completed"])
                plan = rs.plan_copy(resume_dir, done, len(steps))
                runner.restore_state(proc, resume_state, steps[:done], resume_dir)
                old = run_dir / rs.RUN_FILE
                part = rs.archive_previous_log(resume_dir)
                if part is not None:
                    plan.remap(old, part)
        except BaseException:
            proc.close()
            raise
        info = {"procedure": procedure, "params": params, "structure": structure, "argv": sys.argv}
        console = Console(show_progress=not params.get("quiet"))
        live: list[Any] = []          # the live view, once the recorder exists (--view)

        def recorder_factory(path: Path) -> RunRecorder:
            target = path if plan is None else run_dir / rs.RESUME_FILE
            rec = RunRecorder(target, procedure, params, rig=bench.rig.data, scenario=bench.scenario.to_dict(),
                              structure=structure)
            bench.relay.target = console.comms_tap(rec.comms_sink)   # retries and reconnects printed too
            if params.get("view"):
                from lab.core.live import LiveView

                view = LiveView(params["view"], rec.run_id, ["world/camera/image"] if procedure == "borg" else [])
                rec.add_listener(view.feed)
                live.append(view)
                console.line(f"live view: {view.sink.description}")
            rec.log_design(structure, proc.model)
            if plan is not None:
                copied = rs.copy_completed_steps(plan, rec)
                rec.log_text("info", f"resumed: {copied} records of {plan.steps_completed} completed steps kept, from "
                                     f"{', '.join(sorted({p.path.name for p, _, _ in plan.sources})) or 'no log'}")
                rs.finish_copy(rec, run_dir)   # only a complete copy is called run.mcap
            return ConsoleRecorder(rec, console)   # warnings printed as they are logged

        outcome = runner.run(proc, run_dir, info=info, operator_auto=bool(params.get("auto")),
                             recorder_factory=recorder_factory, resume=resume_state,
                             show_progress=not params.get("quiet"), restored=resume_state is not None,
                             console=console)
        # the run is closed: a late Ctrl-C must not turn its exit code into 130
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        _print_outcome(procedure, outcome)
        if live:
            _close_live(live[0], run_dir)
        return outcome.exit_code
    finally:
        if lock is not None:
            lock.release()
            _remove_if_unused(run_dir, created)


def _check_observable(proc: Any) -> None:
    """Modules the rig cannot see: refused (one line each on stderr, then the error; nothing moved)
    unless --allow-unobservable, when the run lists them as warnings at its start."""
    from procedures.borg import UnobservableModules

    try:
        proc.check_observable()
    except UnobservableModules as exc:
        for line in exc.lines:
            print(f"unobservable: {line}", file=sys.stderr)
        proc.close()
        raise


def _close_live(view: Any, run_dir: Path) -> None:
    """Finish the live view.  A web viewer stays up for an operator at a terminal until Ctrl-C; a
    run without a terminal (CI, a script) must end, so there it stops with the run."""
    import signal

    from lab.core.viewer import wait_for_interrupt

    rep = view.close(run_dir / "run.mcap")
    if rep.problem:
        print(f"warning: live view: the viewer stopped receiving ({rep.problem}); the run is complete in "
              f"{run_dir / 'run.mcap'}: `lab review` it")
    web = rep.sink.web
    if web is None:
        return
    if sys.stdin.isatty():
        print(f"live view: the web viewer stays up until Ctrl-C: {web.url}", flush=True)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        wait_for_interrupt(web)
    else:
        web.stop()
        print(f"live view: web viewer stopped with the run; `lab review {run_dir / 'run.mcap'}` shows it again")


def _remove_if_unused(run_dir: Path, created: bool) -> None:
    """A run refused before it started leaves no directory behind it created."""
    try:
        if created and {p.name for p in run_dir.iterdir()} <= {".lock"}:
            (run_dir / ".lock").unlink(missing_ok=True)
            run_dir.rmdir()
    except OSError:
        pass


def _print_outcome(procedure: str, outcome) -> None:
    s = outcome.summary
    print()
    from procedures.console import borg_table, truss_table

    print(borg_table(s) if procedure == "borg" else truss_table(s))
    print(f"result: {outcome.result}{' - ' + outcome.reason if outcome.reason else ''}")
    print(f"run: {outcome.run_dir / 'run.mcap'}   summary: {outcome.run_dir / 'summary.json'}")


def _resume(args: argparse.Namespace) -> int:
    from procedures import resume as rs

    run_dir = Path(args.run_dir)
    info, ckpt = rs.load_run(run_dir)
    params = dict(info["params"])
    if args.auto:
        params["auto"] = True
    params["view"] = args.view
    print(f"resuming {info['procedure']} in {run_dir} at step {ckpt['steps_completed']}"
          f" ({ckpt.get('last_step', 'none')} was the last completed)")
    return _execute(info["procedure"], params, resume_dir=run_dir)

