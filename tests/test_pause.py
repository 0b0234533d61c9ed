"""Pause: an operator at a terminal presses Ctrl-C once, the run stops at the end of the step under
way (devices stopped, checkpoint written) and asks resume / abort; a second Ctrl-C aborts as
before.  Driven for real: `lab run borg` on the simulated bench with a pseudo-terminal as its
terminal, the test typing the operator's answers."""

from __future__ import annotations

import json
import os
import pty
import re
import select
import signal
import time
from pathlib import Path

from lab.core.recorder import topics
from lab.core.recorder.reader import iter_messages
from procedures.pause import interactive

DEPLOY_PROMPT = re.compile(r"(Deploy|Place) module (\S+) .*\[DONE/abort\] $")


class Operator:
    """A run under a pseudo-terminal: read what it prints, type answers."""

    def __init__(self, lab, args: list[str]) -> None:
        master, slave = pty.openpty()
        self.proc = lab.popen(args, stdin=slave, stdout=slave, stderr=slave, close_fds=True)
        os.close(slave)
        self.master = master
        self.text = ""

    def read_until(self, pattern: re.Pattern[str] | str, timeout: float = 120) -> re.Match[str]:
        rx = re.compile(pattern) if isinstance(pattern, str) else pattern
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            m = rx.search(self._tail())
            if m:
                self._consumed = len(self.text)
                return m
            ready, _, _ = select.select([self.master], [], [], 0.2)
            if ready:
                try:
                    self.text += os.read(self.master, 65536).decode(errors="replace")
                except OSError:   # the run exited: its side of the terminal is closed
                    break
        raise AssertionError(f"{rx.pattern!r} not seen; output:\n{self.text[-3000:]}")

    _consumed = 0

    def _tail(self) -> str:
        return self.text[self._consumed:].replace("\r", "\n")

    def type(self, answer: str) -> None:
        os.write(self.master, (answer + "\n").encode())

    def finish(self, timeout: float = 120) -> int:
        """Answer every remaining placement prompt until the run exits."""
        deadline = time.monotonic() + timeout
        while self.proc.poll() is None and time.monotonic() < deadline:
            ready, _, _ = select.select([self.master], [], [], 0.2)
            if ready:
                try:
                    self.text += os.read(self.master, 65536).decode(errors="replace")
                except OSError:
                    break
                if re.search(r"\[DONE/abort\] $", self._tail()):
                    self._consumed = len(self.text)
                    self.type("")
        rc = self.proc.wait(timeout=30)
        while select.select([self.master], [], [], 0.2)[0]:   # what it printed last (an abort's message)
            try:
                chunk = os.read(self.master, 65536)
            except OSError:
                break
            if not chunk:
                break
            self.text += chunk.decode(errors="replace")
        os.close(self.master)
        return rc


def _args(out: Path) -> list[str]:
    return ["run", "borg", "--no-rig-survey", "--modules", "3", "--speedup", "20", "--out", str(out)]


def test_ctrl_c_pauses_at_the_end_of_the_step_and_resume_carries_on(lab, tmp_path: Path) -> None:
    out = tmp_path / "run"
    op = Operator(lab, _args(out))
    try:
        assert op.read_until(DEPLOY_PROMPT).group(2) == "1P"
        op.type("")
        assert op.read_until(DEPLOY_PROMPT).group(2) == "2D"
        op.type("")
        op.proc.send_signal(signal.SIGINT)                     # Ctrl-C while 2D is being measured
        op.read_until("pause requested")
        op.read_until(r"Paused after module 2D\. Resume or abort\? \[RESUME/abort\] $")
        ckpt = json.loads((out / "checkpoint.json").read_text())
        assert ckpt["steps_completed"] == 2 and ckpt["last_step"] == "module 2D"   # checkpointed
        assert op.proc.poll() is None                          # paused, not ended
        op.type("resume")
        rc = op.finish()
    finally:
        if op.proc.poll() is None:
            op.proc.kill()
    assert rc == 0, op.text[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["result"] == "completed" and [m["name"] for m in summary["modules"]] == ["1P", "2D", "3D"]
    prompts = [r.message for r in iter_messages(out / "run.mcap", topics.OPERATOR)]
    assert any(p.question.startswith("Paused after module 2D") and p.answer == "resume" for p in prompts)
    logs = [r.message.message for r in iter_messages(out / "run.mcap", topics.LOG)]
    paused = next(t for t in logs if t.startswith("paused after module 2D"))
    assert "turntable stopped" in paused and "stewart stopped" in paused            # motion stopped
    # the STOPs went out between 2D's end and 3D's start
    seq = [(r.topic, r.message) for r in iter_messages(out / "run.mcap", (topics.RUN_STEP, topics.COMMS))]
    end_2d = next(i for i, (t, m) in enumerate(seq) if t == topics.RUN_STEP and m.name == "module 2D" and m.phase == "end")
    start_3d = next(i for i, (t, m) in enumerate(seq) if t == topics.RUN_STEP and m.name == "module 3D" and m.phase == "start")
    stops = [m.device for t, m in seq[end_2d:start_3d] if t == topics.COMMS and m.direction == "tx" and re.match(r"(#\d+ )?STOP\b", m.text)]
    assert sorted(stops) == ["stewart", "turntable"]


def test_abort_at_the_pause_ends_the_run_resumable_and_a_second_ctrl_c_aborts_at_once(lab, tmp_path: Path) -> None:
    out = tmp_path / "run"
    op = Operator(lab, _args(out))
    try:
        op.read_until(DEPLOY_PROMPT)
        op.type("")
        op.proc.send_signal(signal.SIGINT)
        op.read_until(r"Resume or abort\? \[RESUME/abort\] $")
        op.type("abort")
        rc = op.finish()
    finally:
        if op.proc.poll() is None:
            op.proc.kill()
    assert rc == 3, op.text[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["result"] == "aborted" and summary["reason"].startswith("aborted by the operator at the pause after module 1P")
    assert json.loads((out / "checkpoint.json").read_text())["steps_completed"] == 1   # lab resume takes it on

    out2 = tmp_path / "run2"
    op = Operator(lab, _args(out2))
    try:
        op.read_until(DEPLOY_PROMPT)
        op.type("")
        op.proc.send_signal(signal.SIGINT)
        op.read_until("pause requested")
        op.proc.send_signal(signal.SIGINT)                     # the second Ctrl-C: abort now
        rc = op.finish()
    finally:
        if op.proc.poll() is None:
            op.proc.kill()
    assert rc == 3, op.text[-3000:]
    summary = json.loads((out2 / "summary.json").read_text())
    assert summary["result"] == "aborted" and "interrupted by the operator during module 1P" in summary["reason"]


def test_only_a_terminal_without_auto_pauses() -> None:
    class Stdin:
        def __init__(self, tty: bool) -> None:
            self.tty = tty

        def isatty(self) -> bool:
            return self.tty

    assert interactive(False, Stdin(True))
    assert not interactive(True, Stdin(True))       # --auto: the first Ctrl-C aborts, as before
    assert not interactive(False, Stdin(False))     # no terminal: nobody to answer
