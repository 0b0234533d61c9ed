"""Pause: on an interactive run the first Ctrl-C asks for a pause instead of an abort.

The run carries on to the next safe point, the end of the step under way (every move of a step
waits for the device to arrive, so between steps nothing is moving, and the step's records and
checkpoint are on disk). There every device that moved is sent STOP once more, and the operator is
asked: resume, or abort. A second Ctrl-C (before the safe point or at the question) aborts exactly
as before pause existed: the step runner's SignalShield takes it from there. SIGTERM always aborts.

Non-interactive runs keep the old behaviour, the first Ctrl-C aborts: there is nobody at a terminal
to answer (stdin not a terminal), or the operator chose `--auto`.

This is a layer in front of the SignalShield's SIGINT handler, not a change to it, so the shield's
promise (any number of signals ends like one) is untouched.

Two Ctrl-C are two, however close: Python runs a signal's handler only when the main thread is
back in the interpreter, so two SIGINT that arrive while it is inside one long C call (an iSAM2
update, a JPEG encode) ran the handler once, and a double Ctrl-C became a pause.  The C-level
handler also writes one byte per signal delivered to the wakeup fd (`signal.set_wakeup_fd`); the
handler counts the SIGINT bytes there, so the second one aborts even when its handler never runs.
"""

from __future__ import annotations

import signal
import sys
from dataclasses import dataclass, field
from typing import Any, Callable

PAUSE_CHOICES = ("resume", "abort")


class PauseAbort(KeyboardInterrupt):
    """The operator chose abort at a pause: the run ends aborted, with this as its reason."""


def interactive(operator_auto: bool, stdin: Any = None) -> bool:
    """Is someone at a terminal to answer a pause?"""
    stdin = sys.stdin if stdin is None else stdin
    try:
        return not operator_auto and bool(stdin.isatty())
    except (AttributeError, ValueError):
        return False


@dataclass
class PauseControl:
    shield: Any                                   # procedures.runner.SignalShield
    enabled: bool
    say: Callable[[str], None] = field(default=lambda text: print(text, file=sys.stderr, flush=True))
    requested: bool = False
    pauses: int = 0
    _previous: Any = None
    _wakeup: tuple[int, int] | None = None       # (read end, write end) of the wakeup pipe
    _previous_wakeup: int = -1

    def install(self) -> None:
        """Take SIGINT in front of the shield (which must be installed already)."""
        import os
        import threading

        if not self.enabled or threading.current_thread() is not threading.main_thread():
            return
        self._previous = signal.getsignal(signal.SIGINT)
        r, w = os.pipe()
        os.set_blocking(r, False)
        os.set_blocking(w, False)
        self._wakeup = (r, w)
        self._previous_wakeup = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
        signal.signal(signal.SIGINT, self._handle)

    def restore(self) -> None:
        import os

        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            self._previous = None
        if self._wakeup is not None:
            signal.set_wakeup_fd(self._previous_wakeup)
            for fd in self._wakeup:
                os.close(fd)
            self._wakeup = None

    def _sigints_delivered(self) -> int:
        """SIGINT delivered since the last look (each wrote its number to the wakeup pipe)."""
        import os

        if self._wakeup is None:
            return 1
        n = 0
        while True:
            try:
                data = os.read(self._wakeup[0], 512)
            except (BlockingIOError, InterruptedError):
                break
            if not data:
                break
            n += data.count(int(signal.SIGINT))
        return max(n, 1)

    def _handle(self, signum: int, frame: Any) -> None:
        shield = self.shield
        twice = self._sigints_delivered() >= 2         # two Ctrl-C, one handler call
        if twice and not self.requested:
            shield.signals.append(signum)              # the one whose handler never ran
        if (twice or self.requested or shield.cleanup or getattr(shield, "_raised", False)
                or getattr(shield, "_held", 0)):
            # the second Ctrl-C, or one during clean-up or a checkpoint write: the shield's rules
            # (held() defers it until the write is complete)
            self._previous(signum, frame) if callable(self._previous) else None
            return
        self.requested = True
        self.say("\npause requested: the run stops after the step under way (Ctrl-C again aborts now)")

    def at_safe_point(self, step_name: str, stop_devices: Callable[[], list[str]], operator: Any,
                      recorder: Any) -> None:
        """Called by the runner after a step's checkpoint is written.  If a pause was requested: stop
        what moved, ask resume / abort, and either return (resume) or raise KeyboardInterrupt (abort,
        handled by the runner like a Ctrl-C: result aborted, the run resumable)."""
        if not self.requested:
            return
        stopped = stop_devices()
        self.pauses += 1
        note = f"paused after {step_name}" + (f" ({', '.join(stopped)})" if stopped else "")
        if recorder is not None:
            recorder.log_text("info", note)
            recorder.sync()
        self.say(f"{note}; the checkpoint is written, `lab resume` can also take it from here")
        answer = operator.ask(f"Paused after {step_name}. Resume or abort?", PAUSE_CHOICES, "resume")
        self.requested = False
        if answer == "abort":
            raise PauseAbort(f"aborted by the operator at the pause after {step_name}")
        if recorder is not None:
            recorder.log_text("info", f"resumed after the pause after {step_name}")
        self.say("resuming")
