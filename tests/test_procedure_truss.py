"""`lab run truss` end to end on simulated IPJRs (HTTP and serial), plus the runner's exit paths:
abort with Ctrl-C, resume, SIGKILL, device faults, dry run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from lab.core.recorder import topics
from lab.core.recorder.reader import iter_messages, read_summary


def _step_events(path):
    return [(r.message.index, r.message.phase) for r in iter_messages(path) if r.topic == topics.RUN_STEP]


def _scenario(tmp_path: Path, text: str) -> str:
    p = tmp_path / "scenario.toml"
    p.write_text(text)
    return str(p)


def test_tetrahelix_mle_run_completes_and_logs_every_step(lab, run_dir):
    out = run_dir
    r = lab(["run", "truss", "tetrahelix:6", "--auto", "--quiet", "--out", str(out)])
    assert r.returncode == 0, r.stdout + r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["result"] == "completed" and summary["estimator"] == "mle"
    assert summary["steps"] == 6 and sorted(n["id"] for n in summary["nodes"]) == list(range(6))
    # the paper's strut noise (0.6 mm): nodes end within a few sigma of the design
    assert 0 < summary["rms_node_error_m"] < 5e-3
    assert max(n["estimate_error_m"] for n in summary["nodes"]) < 2e-3
    events = _step_events(out / "run.mcap")
    assert events == [(i, p) for i in range(6) for p in ("start", "end")]
    msgs = list(iter_messages(out / "run.mcap"))
    lengths = [r.message for r in msgs if r.topic == topics.LENGTHS]
    ipjr_lengths = [m for m in lengths if m.device.startswith("ipjr")]
    # starting triangle 0 + 1 + 2 struts, then 3 per floating node
    assert len(ipjr_lengths) == 3 + 3 * 3
    for m in ipjr_lengths:  # every IPJR reached its commanded length within the paper's 0.5 mm
        assert abs(m.measured_m - m.commanded_m) < 0.5e-3
    comms = {r.message.device for r in msgs if r.topic == topics.COMMS}
    assert {"ipjr1", "ipjr2", "ipjr3"} <= comms   # HTTP and serial IPJRs both talked over their wires
    assert read_summary(out / "run.mcap").stop.result == "completed"


def test_mle_beats_open_loop_on_the_same_seed(lab, tmp_path):
    sc = _scenario(tmp_path, "seed = 11\n[truss]\nsigma_length_m = 0.02\nsigma_measure_m = 0.001\n")
    rms = {}
    for est in ("mle", "open-loop"):
        out = tmp_path / est
        r = lab(["run", "truss", "tetrahelix:8", "--auto", "--quiet", "--speedup", "40", "--estimator", est,
                 "--scenario", sc, "--out", str(out)])
        assert r.returncode == 0, r.stdout + r.stderr
        rms[est] = json.loads((out / "summary.json").read_text())["rms_node_error_m"]
    assert rms["mle"] < rms["open-loop"]


def test_dry_run_moves_nothing(tmp_path):
    from procedures.build import build_procedure
    from procedures import runner

    proc, bench, _ = build_procedure("truss", {"name": "tetrahelix:6", "estimator": "mle"})
    try:
        before = {n: a.extension_m() for n, a in bench.sim.world.ipjrs.items()}
        assert runner.dry_run(proc) == 0
        assert {n: a.extension_m() for n, a in bench.sim.world.ipjrs.items()} == before
        assert not bench.moved
    finally:
        proc.close()


def test_ctrl_c_stops_and_resume_completes(lab, run_dir):
    out = run_dir
    p = lab.popen(["run", "truss", "tetrahelix:8", "--auto", "--quiet", "--speedup", "4", "--out", str(out)],
                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 60
    ckpt = out / "checkpoint.json"
    while time.time() < deadline and not (ckpt.exists() and json.loads(ckpt.read_text())["steps_completed"] >= 3):
        time.sleep(0.02)
    p.send_signal(signal.SIGINT)
    text, _ = p.communicate(timeout=60)
    assert p.returncode == 3, text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["result"] == "aborted" and "interrupted" in summary["reason"]
    assert "stopped" in summary["reason"]          # the devices that moved were stopped
    done = json.loads(ckpt.read_text())["steps_completed"]
    assert done < 8
    stop = read_summary(out / "run.mcap").stop
    assert stop.result == "aborted"

    r = lab(["resume", str(out), "--auto"])
    assert r.returncode == 0, r.stdout + r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["result"] == "completed" and summary["steps"] == 8
    # the resumed log holds every step exactly once: the kept ones and the re-run rest
    assert _step_events(out / "run.mcap") == [(i, p) for i in range(8) for p in ("start", "end")]
    assert (out / "run.part1.mcap").exists()
    assert lab(["resume", str(out)]).returncode == 2       # nothing left to resume


def test_sigkill_loses_no_completed_step(lab, run_dir):
    out = run_dir
    p = lab.popen(["run", "truss", "tetrahelix:8", "--auto", "--quiet", "--speedup", "1", "--out", str(out)],
                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ckpt = out / "checkpoint.json"
    deadline = time.time() + 60
    while time.time() < deadline and not (ckpt.exists() and json.loads(ckpt.read_text())["steps_completed"] >= 3):
        time.sleep(0.05)
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=10)
    done = json.loads(ckpt.read_text())["steps_completed"]
    ends = [i for i, phase in _step_events(out / "run.mcap") if phase == "end"]
    assert ends[:done] == list(range(done))


def test_ipjr_fault_fails_the_run_with_a_clear_reason(lab, run_dir, tmp_path):
    sc = _scenario(tmp_path, '[[device.fault]]\ndevice = "ipjr1"\nkind = "stuck"\nafter_commands = 0\ncount = 0\n')
    out = run_dir
    r = lab(["run", "truss", "tetrahelix:6", "--auto", "--quiet", "--scenario", sc, "--out", str(out)])
    assert r.returncode == 1, r.stdout + r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["result"] == "failed"
    assert "ipjr1" in summary["reason"] and "stopped" in summary["reason"]
    assert read_summary(out / "run.mcap").stop.result == "failed"


def test_bad_inputs_are_refused_in_one_line(lab, tmp_path):
    r = lab(["run", "truss", "nonsense:3", "--auto", "--out", str(tmp_path / "x")])
    assert r.returncode == 2 and "nonsense" in r.stderr and "Traceback" not in r.stderr
    bad = _scenario(tmp_path, "seed = -1\n")
    r = lab(["run", "truss", "tetrahelix:6", "--auto", "--scenario", bad, "--out", str(tmp_path / "y")])
    assert r.returncode == 2 and "seed" in r.stderr and "Traceback" not in r.stderr
