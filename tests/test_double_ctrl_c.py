"""A second Ctrl-C always aborts (issue 22, item 7): two SIGINT 50 ms apart while the run's main
thread is inside one long C call (an estimator update) reach Python as one handler call; counted
through the wakeup fd, they abort instead of being taken for a pause (once 1 in 5 trials).  One
Ctrl-C still asks for the pause.  In a child process, so the test's own signal handlers stay."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from lab.studies.bench_faults_inputs import CTRL_C_CHILD as CHILD

ROOT = Path(__file__).resolve().parents[1]


def _child(count: int) -> list[str]:
    r = subprocess.run([sys.executable, "-c", CHILD, str(count)], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout.split()


@pytest.mark.parametrize("trial", range(3))
def test_two_ctrl_c_inside_one_c_call_abort(trial):
    assert _child(2) == ["abort", "2"]


def test_one_ctrl_c_still_asks_for_the_pause():
    assert _child(1) == ["pause", "0"]
