"""Shared test fixtures: the `lab` command (`lab`), a simulated bench on the fast test rig
(`bench`), a scratch run directory (`run_dir`), and one small rig calibration survey for the files
that start from a real calibration file (`rig_survey`)."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator, Sequence
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def python_signal_handlers() -> Iterator[None]:
    """Every test starts with Python's own SIGINT and SIGTERM handling.  A `lab` command run in this
    process owns its process's handlers (`lab run` ignores a late Ctrl-C once its run is closed,
    until it exits); left ignored, SIGINT stays ignored in every subprocess a later test starts, and
    a `lab sim`, a viewer or a study under test no longer stops on Ctrl-C."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    yield


class Lab:
    """The `lab` command as an operator types it.

    `lab(args)` runs it in a child process (its output captured as text, unless stdout or stderr
    is given) and returns the CompletedProcess; `lab.popen(args, ...)` starts one to signal or
    kill; `lab.main(*args)` runs it in this process, for speed, and returns (exit code, stdout,
    stderr)."""

    argv = (sys.executable, "-m", "lab")
    # what a machine without a display lacks: for `env(drop=...)`, where a viewer must not open a window
    NO_DISPLAY = ("DISPLAY", "WAYLAND_DISPLAY")

    @staticmethod
    def env(drop: Sequence[str] = (), **extra: str) -> dict[str, str]:
        """This environment, minus `drop`, plus `extra`, with this checkout first on the path: the
        child runs the code under test even where another copy of the package is installed."""
        env = {k: v for k, v in os.environ.items() if k not in drop}
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
        env.update(extra)
        return env

    def __call__(self, args: Sequence[str], *, timeout: float = 300, env: dict[str, str] | None = None,
                 **kw: Any) -> subprocess.CompletedProcess[str]:
        if "stdout" not in kw and "stderr" not in kw:
            kw["capture_output"] = True
        # the timeout turns a hung command into a failure instead of a stalled CI job
        env = self.env() if env is None else env
        return subprocess.run([*self.argv, *args], text=True, timeout=timeout, env=env, **kw)

    def popen(self, args: Sequence[str], *, env: dict[str, str] | None = None, **kw: Any) -> subprocess.Popen:
        return subprocess.Popen([*self.argv, *args], env=self.env() if env is None else env, **kw)

    @staticmethod
    def main(*args: str) -> tuple[int, str, str]:
        from lab.cli import main

        so, se = io.StringIO(), io.StringIO()
        with redirect_stdout(so), redirect_stderr(se):
            rc = main(list(args))
        return rc, so.getvalue(), se.getvalue()


@pytest.fixture(scope="session")
def lab() -> Lab:
    return Lab()


@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    """Where a test's run goes (`--out`): not yet made, as `lab run` wants a new directory."""
    return tmp_path / "run"


@pytest.fixture(scope="module")
def bench(request: pytest.FixtureRequest) -> Iterator[Any]:
    """A simulated bench on the fast test rig, 1000x faster than the devices, shared by a module's
    tests.  A module that needs another bench says so with start_sim_bench's keywords, e.g.
    `pytestmark = pytest.mark.sim_bench(pty=True)` to reach the serial devices on ptys."""
    from drivers.testing import fast_sim_rig
    from sim_devices.bench import start_sim_bench

    mark = request.node.get_closest_marker("sim_bench")
    options = {"speedup": 1000, **(mark.kwargs if mark else {})}
    with start_sim_bench(fast_sim_rig(), **options) as b:
        yield b


@pytest.fixture(scope="session")
def rig_survey(tmp_path_factory: pytest.TempPathFactory, lab: Lab) -> dict[str, Any]:
    """One small calibration of the default simulated rig through the CLI (45 deg turntable steps,
    devices 100x faster): the file, its recorded run and the command's --json report.  Each survey
    costs seconds, and the files that check the survey and those that start from its file need
    the same one."""
    d = tmp_path_factory.mktemp("rig_survey")
    out, run = d / "rig_calibration.json", d / "run"
    rc, stdout, err = lab.main("calibrate", "rig", "--auto", "--json", "--speedup", "100", "--angle-step-deg", "45",
                               "--out", str(out), "--run-dir", str(run))
    assert rc == 0, err
    return {"dir": d, "out": out, "run": run / "run.mcap", "result": json.loads(stdout)}
