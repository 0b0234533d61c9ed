"""A second Ctrl-C always aborts (issue 22, item 7): two SIGINT 50 ms apart while the run's main
thread is inside one long C call (an estimator update) reach Python as one handler call; counted
through the wakeup fd, they abort instead of being taken for a pause (once 1 in 5 trials).  One
Ctrl-C still asks for the pause.  In a child process, so the test's own signal handlers stay."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHILD = r"""
import hashlib, os, signal, sys, threading, time
from procedures.pause import PauseControl
from procedures.runner import SignalShield

shield = SignalShield()
shield.install()
pause = PauseControl(shield, True, say=lambda text: None)
pause.install()
count = int(sys.argv[1])

def kick():
    time.sleep(0.2)
    for k in range(count):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)

threading.Thread(target=kick).start()
try:
    hashlib.pbkdf2_hmac("sha256", b"x", b"y", 3_000_000)   # ~1 s in one C call: no handler runs inside
    time.sleep(0.05)
    print("pause" if pause.requested else "nothing", len(shield.signals))
except KeyboardInterrupt:
    print("abort", len(shield.signals))
finally:
    pause.restore()
    shield.restore()
"""


def _child(count: int) -> list[str]:
    r = subprocess.run([sys.executable, "-c", CHILD, str(count)], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout.split()


@pytest.mark.parametrize("trial", range(3))
def test_two_ctrl_c_inside_one_c_call_abort(trial):
    assert _child(2) == ["abort", "2"]


def test_one_ctrl_c_still_asks_for_the_pause():
    assert _child(1) == ["pause", "0"]
