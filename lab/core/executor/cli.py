"""The command-line options every study shares: `--workers N` and `--scheduler tcp://HOST:PORT`."""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any, Callable

from lab.core.errors import UserError
from lab.core.executor.backends import MAX_WORKERS, TrialExecutor, check_scheduler, check_workers, make_executor
from lab.core.executor.journal import JOURNAL_NAME, Journal
from lab.core.executor.progress import Progress
from lab.core.executor.study import Study

EXECUTOR_FLAGS = ("--workers", "--scheduler")


def add_executor_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--workers", type=_workers, metavar="N",
                       help=f"run trials in N local processes (default: all cores; 1: in this process; up to {MAX_WORKERS})")
    group.add_argument("--scheduler", type=_scheduler, metavar="tcp://HOST:PORT",
                       help="run trials on a Dask distributed cluster (needs pip install -e '.[distributed]'; "
                            "docs/benchmarks.md)")


def executor_from_args(args: argparse.Namespace) -> TrialExecutor:
    return make_executor(getattr(args, "workers", None), getattr(args, "scheduler", None))


def open_study(args: argparse.Namespace, out_dir: str | os.PathLike, study: dict[str, Any], label: str,
               validate: Callable[[Any], str | None] | None = None) -> Study:
    """The executor of --workers / --scheduler, the journal `OUT/trials.jsonl` of this study
    (`study`: its parameters, JSON; a rerun with the same ones resumes; `validate`: what a restored
    result must be, lab.core.executor.journal.Journal), a progress bar."""
    executor = executor_from_args(args)
    try:
        journal = Journal(Path(out_dir) / JOURNAL_NAME, study, validate=validate)
    except BaseException:
        executor.close()
        raise
    return Study(executor, journal, Progress(label))


def without_executor_args(argv: list[str]) -> list[str]:
    """A command line minus --workers / --scheduler: what the results depend on (they are the same
    whichever executor ran them), for the `command` a study records."""
    out: list[str] = []
    skip = False
    for arg in argv:
        if skip:
            skip = False
        elif arg in EXECUTOR_FLAGS:
            skip = True
        elif not arg.startswith(tuple(f + "=" for f in EXECUTOR_FLAGS)):
            out.append(arg)
    return out


def _workers(text: str) -> int:
    try:
        return check_workers(int(text))
    except (ValueError, UserError):
        raise argparse.ArgumentTypeError(f"expected a whole number from 1 to {MAX_WORKERS}, got {text!r}") from None


def _scheduler(text: str) -> str:
    try:
        return check_scheduler(text)
    except UserError:
        raise argparse.ArgumentTypeError(f"expected tcp://HOST:PORT (a Dask scheduler's address), got {text!r}") from None
