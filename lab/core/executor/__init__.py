"""Trials of a study through an executor: this process, local worker processes, or a Dask cluster.

A bench wires it in like this (lab/studies/bench_mle.py and lab/studies/bench_calibration.py do):

    from lab.core.executor import Study, Trial, add_executor_arguments, make_trials, open_study

    def one_trial(trial: Trial) -> dict:            # module level: workers import it by name
        rng = np.random.default_rng(trial.seed)     # the trial's own seed, never a worker's state
        return {"error_m": simulate(trial.spec, rng)}   # JSON values only (the journal stores them)

    def add_arguments(p):  ...; add_executor_arguments(p)   # --workers N | --scheduler tcp://HOST:PORT

    def run(args):
        with open_study(args, args.out, {"bench": "x", "seed": args.seed, "quick": args.quick}, "lab bench x") as study:
            trials = make_trials(args.seed, "x/errors", specs)          # keys "x/errors/0", ...
            results = study.map(one_trial, trials)                      # in trial order, journaled
            write(out, {..., "executor": study.describe()}); study.finish()   # finish: drop the journal

Results are the same whichever executor runs the trials; an interrupted study keeps its finished
trials in `OUT/trials.jsonl` and the same command resumes from them.  Cheap trials (milliseconds):
`study.map(fn, trials, batch_size="auto")`.  Independent parts of one bench at the same time:
`study.concurrently({"a": lambda: part_a(study), ...})`.  Compare two studies' JSON apart from
timings: `python -m lab.core.executor.compare A.json B.json` (`lab.core.executor.compare.strip_timings`).

This is kernel code: it imports nothing above `lab/`, and no numpy at import time (a worker sets
its thread variables before numpy loads)."""

from lab.core.executor.backends import (DaskCluster, InProcess, LocalProcesses, TrialExecutor, default_workers,
                                        make_executor)
from lab.core.executor.cli import add_executor_arguments, executor_from_args, open_study, without_executor_args
from lab.core.executor.journal import JOURNAL_NAME, Journal
from lab.core.executor.progress import Progress
from lab.core.executor.study import Study
from lab.core.executor.trials import Trial, make_trials, trial_seed

__all__ = ["DaskCluster", "InProcess", "JOURNAL_NAME", "Journal", "LocalProcesses", "Progress", "Study", "Trial",
           "TrialExecutor", "add_executor_arguments", "default_workers", "executor_from_args",
           "make_executor", "make_trials", "open_study", "trial_seed", "without_executor_args"]
