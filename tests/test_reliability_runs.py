"""Issue 11, runs: resume that cannot lie, one owner per run directory and per device, --out and
--replace, shielded clean-up under repeated signals, IPJR noise per step."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lab.core.recorder import topics
from lab.core.recorder.reader import iter_messages, read_summary

TRUSS = ["run", "truss", "tetrahelix:6", "--auto", "--quiet", "--speedup", "20"]


def _ends(path: Path) -> list[int]:
    return [r.message.index for r in iter_messages(path) if r.topic == topics.RUN_STEP and r.message.phase == "end"]


def _wait_steps(out: Path, n: int, timeout: float = 120) -> None:
    ckpt = out / "checkpoint.json"
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            if json.loads(ckpt.read_text())["steps_completed"] >= n:
                return
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.02)
    raise AssertionError(f"{out}: {n} steps not completed in time")


def _one_line_error(r) -> str:
    assert r.returncode == 2, r.stdout + r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    return lines[0]


@pytest.fixture(scope="module")
def reference(lab, tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("ref") / "run"
    r = lab(TRUSS + ["--out", str(out)])
    assert r.returncode == 0, r.stdout + r.stderr
    return json.loads((out / "summary.json").read_text())


@pytest.fixture(scope="module")
def killed(lab, tmp_path_factory) -> Path:
    """A truss run killed (SIGKILL) after 3 of its 6 steps, made once: five tests start from it."""
    out = tmp_path_factory.mktemp("killed") / "run"
    p = lab.popen(TRUSS + ["--speedup", "2", "--out", str(out)], stdout=subprocess.DEVNULL,
                  stderr=subprocess.DEVNULL)
    _wait_steps(out, 3)
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=10)
    return out


@pytest.fixture()
def interrupted(killed, run_dir) -> Path:
    """A truss run killed (SIGKILL) after 3 of its 6 steps: a copy of `killed` of the test's own,
    which it resumes, cuts or edits."""
    shutil.copytree(killed, run_dir)
    return run_dir


def test_killed_and_resumed_truss_run_equals_the_uninterrupted_one(lab, interrupted, reference):
    r = lab(["resume", str(interrupted), "--auto"])
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads((interrupted / "summary.json").read_text())
    assert s["result"] == "completed"
    assert s["rms_node_error_m"] == reference["rms_node_error_m"]      # bit for bit: noise drawn per step
    assert s["nodes"] == reference["nodes"]
    assert _ends(interrupted / "run.mcap") == list(range(6))


def test_a_log_cut_by_a_kill_during_resume_copy_is_repaired_from_the_parts(lab, interrupted):
    """The issue's case: run.part1.mcap intact, run.mcap cut at 40 % (a kill during the copy of an
    old-style resume).  Resume must take every completed step from a part that holds it."""
    done = json.loads((interrupted / "checkpoint.json").read_text())["steps_completed"]
    full = interrupted / "run.mcap"
    os.replace(full, interrupted / "run.part1.mcap")
    data = (interrupted / "run.part1.mcap").read_bytes()
    full.write_bytes(data[: int(0.4 * len(data))])
    r = lab(["resume", str(interrupted), "--auto"])
    assert r.returncode == 0, r.stdout + r.stderr
    assert json.loads((interrupted / "summary.json").read_text())["result"] == "completed"
    assert _ends(interrupted / "run.mcap") == list(range(6))
    assert done >= 3
    assert read_summary(interrupted / "run.mcap").stop.steps_completed == 6


def test_a_missing_log_is_refused_not_papered_over(lab, interrupted):
    (interrupted / "run.mcap").unlink()
    line = _one_line_error(lab(["resume", str(interrupted), "--auto"]))
    assert "lack" in line and "checkpoint.json" in line
    assert not (interrupted / "run.part1.mcap").exists()       # nothing was touched


def test_a_checkpoint_claiming_more_than_the_plan_is_refused(lab, interrupted):
    ck = interrupted / "checkpoint.json"
    doc = json.loads(ck.read_text())
    doc["steps_completed"] = 99
    ck.write_text(json.dumps(doc))
    line = _one_line_error(lab(["resume", str(interrupted), "--auto"]))
    assert "steps_completed 99" in line
    doc["steps_completed"] = 5          # within the plan but beyond the logs (3 or 4 steps)
    ck.write_text(json.dumps(doc))
    line = _one_line_error(lab(["resume", str(interrupted), "--auto"]))
    assert "lack" in line


@pytest.mark.parametrize("name,text", [("run.json", "{not json"), ("checkpoint.json", "\x00\x01garbage"),
                                       ("run.json", "[1, 2]"), ("checkpoint.json", '{"steps_completed": "three"}')])
def test_garbage_run_files_are_one_line_errors(lab, tmp_path, name, text):
    d = tmp_path / "run"
    d.mkdir()
    (d / "run.json").write_text(json.dumps({"procedure": "truss", "params": {"name": "tetrahelix:6"}}))
    (d / name).write_text(text)
    line = _one_line_error(lab(["resume", str(d), "--auto"]))
    assert name in line


def test_out_is_checked_and_an_existing_run_needs_replace(lab, run_dir, tmp_path, reference):
    f = tmp_path / "afile"
    f.write_text("x")
    assert "is a file" in _one_line_error(lab(TRUSS + ["--out", str(f)]))
    assert "cannot create" in _one_line_error(lab(TRUSS + ["--out", str(f / "sub")]))
    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        assert "ro" in _one_line_error(lab(TRUSS + ["--out", str(ro / "x")]))
    out = run_dir
    assert lab(TRUSS + ["--out", str(out)]).returncode == 0
    line = _one_line_error(lab(TRUSS + ["--out", str(out)]))
    assert "--replace" in line
    r = lab(TRUSS + ["--out", str(out), "--replace"])
    assert r.returncode == 0, r.stderr
    assert json.loads((out / "summary.json").read_text())["rms_node_error_m"] == reference["rms_node_error_m"]


def test_two_runs_on_one_out_directory_one_is_refused(lab, run_dir):
    out = run_dir
    p = lab.popen(TRUSS + ["--speedup", "2", "--out", str(out)], stdout=subprocess.DEVNULL,
                  stderr=subprocess.DEVNULL)
    try:
        _wait_steps(out, 1)
        line = _one_line_error(lab(TRUSS + ["--out", str(out), "--replace"]))
        assert "in use by pid" in line and str(p.pid) in line
        line = _one_line_error(lab(["resume", str(out), "--auto"]))
        assert "in use by pid" in line
    finally:
        p.send_signal(signal.SIGINT)
        p.wait(timeout=60)
    assert json.loads((out / "run.json").read_text())["argv"][-1] == str(out)


def test_a_second_run_on_a_busy_bench_moves_and_stops_nothing(lab, tmp_path):
    rig = tmp_path / "rig.toml"
    text = (Path(__file__).resolve().parents[1] / "lab" / "rigs" / "sim.toml").read_text()
    rig.write_text(text.split("\n[sim]")[0])            # the same devices, driven as hardware
    shutil.copy(Path(__file__).resolve().parents[1] / "lab" / "rigs" / "sim_camera.json", tmp_path)
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time, drivers; from lab.core.config import load_rig; from lab.core.locks import set_holder\n"
        f"set_holder(run='first-run'); d = drivers.connect(load_rig({str(rig)!r}))\n"
        "print('held', flush=True); time.sleep(60)\n")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        r = lab(["run", "borg", "--rig", str(rig), "--auto", "--quiet", "--out", str(tmp_path / "second")])
        line = _one_line_error(r)
        assert "turntable" in line and "first-run" in line and f"pid {holder.pid}" in line
        assert "nothing was moved or stopped" in line
    finally:
        holder.kill()
        holder.wait()


def test_repeated_interrupts_end_like_one(lab, tmp_path):
    """SIGINT, then SIGINT and SIGTERM again during the clean-up: exit 3, every moved device
    stopped, the stop record and summary.json say the same, no half-written file left."""
    for gap in (0.004, 0.05):
        out = tmp_path / f"run{gap}"
        p = lab.popen(TRUSS + ["--speedup", "2", "--out", str(out)], stdout=subprocess.PIPE,
                      stderr=subprocess.STDOUT, text=True)
        _wait_steps(out, 2)
        p.send_signal(signal.SIGINT)
        time.sleep(gap)
        p.send_signal(signal.SIGINT)
        time.sleep(gap)
        p.send_signal(signal.SIGTERM)
        text, _ = p.communicate(timeout=60)
        assert p.returncode == 3, text
        s = json.loads((out / "summary.json").read_text())
        stop = read_summary(out / "run.mcap").stop
        assert s["result"] == stop.result == "aborted"
        assert "stopped" in s["reason"] and s["reason"] == stop.reason
        assert not list(out.glob("*.tmp"))
        r = lab(["resume", str(out), "--auto"])
        assert r.returncode == 0, r.stdout + r.stderr
        assert _ends(out / "run.mcap") == list(range(6))


class _Proc:
    """A procedure whose step is interrupted by a signal and whose clean-up is interrupted again
    between the STOPs of its three devices (the issue: a second Ctrl-C during the STOP loop)."""

    name = "fake"

    def __init__(self):
        self.stopped: list[str] = []

    def plan(self):
        from procedures.runner import StepSpec

        return [StepSpec(i, f"s{i}") for i in range(3)]

    def dry_run_problems(self, steps):
        return []

    def execute(self, step, run):
        if step.index == 1:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)

    def checkpoint(self):
        return {}

    def restore(self, state, steps_done, run):
        pass

    def summary(self, result, reason):
        return {"result": result, "reason": reason}

    def stop_devices(self):
        out = []
        for name in ("a", "b", "c"):
            if name == "b":
                os.kill(os.getpid(), signal.SIGINT)     # and again, and a SIGTERM, mid-clean-up
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
            self.stopped.append(name)
            out.append(f"{name} stopped")
        return out

    def close(self):
        pass


def test_signals_during_the_clean_up_cannot_skip_a_stop(tmp_path):
    from lab.core.recorder import RunRecorder
    from procedures import runner

    proc = _Proc()
    outcome = runner.run(proc, tmp_path / "r", info={}, operator_auto=True, show_progress=False,
                         recorder_factory=lambda p: RunRecorder(p, "fake", {}))
    assert outcome.exit_code == 3 and outcome.result == "aborted"
    assert proc.stopped == ["a", "b", "c"]
    s = json.loads((tmp_path / "r" / "summary.json").read_text())
    stop = read_summary(tmp_path / "r" / "run.mcap").stop
    assert s["result"] == stop.result == "aborted" and s["reason"] == stop.reason
    assert "3 signals" in s["reason"] and "c stopped" in s["reason"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler   # handlers given back


def test_a_resume_killed_during_its_copy_leaves_a_half_copy_the_next_resume_drops(lab, interrupted):
    """What a kill during the (new) copy leaves: the old log already moved to run.part1.mcap, a
    half-written run.resume.mcap, no run.mcap.  The next resume must complete from the part."""
    os.replace(interrupted / "run.mcap", interrupted / "run.part1.mcap")
    data = (interrupted / "run.part1.mcap").read_bytes()
    (interrupted / "run.resume.mcap").write_bytes(data[: len(data) // 3])
    r = lab(["resume", str(interrupted), "--auto"])
    assert r.returncode == 0, r.stdout + r.stderr
    assert not (interrupted / "run.resume.mcap").exists()
    assert _ends(interrupted / "run.mcap") == list(range(6))


def test_a_checkpoints_views_encoded_once_read_back_as_encoded_whole(tmp_path):
    """The checkpoint's view list is encoded a view at a time across checkpoints (runner.EncodedList):
    the file reads back as the whole list encoded at once, at every write, indented or not."""
    import json

    import numpy as np

    from procedures.runner import EncodedList, _atomic_write_json, _json_default

    views: list = []
    encoded = EncodedList(views)
    for step in range(3):
        views.extend({"view": step * 2 + i, "pose": np.eye(4) * (i + 1), "detections": [{"id": i, "c": [0.5, 1e-17]}],
                      "note": "\\0" + str(i)} for i in range(2))
        for readable in (False, True):
            path = tmp_path / f"c{step}{readable}.json"
            _atomic_write_json(path, {"state": {"views": encoded, "after": [1, 2]}, "time": 3.5}, readable=readable)
            want = json.loads(json.dumps({"state": {"views": views, "after": [1, 2]}, "time": 3.5},
                                         default=_json_default))
            assert json.loads(path.read_text()) == want
