"""What a run tells the operator as it happens, on the console.

- Progress bars only where someone watches them: stderr is a terminal and `--quiet` is not given.
  Redirected to a file, a bar redraws itself as a new line hundreds of times a step (a full BORG run
  wrote ~2,000 lines of them); there one plain line per step is printed instead.
- Findings when they happen, not only in the final table: a procedure's verdict rows
  (`Console.line`), and warnings: every `log_text("warning"|"error", ...)` a procedure writes to the
  run's log (rig calibration problems, rejected tags, re-measures) and the drivers' retries and
  reconnects, which otherwise only reach the comms log.

Everything goes to stdout (the bars to stderr), flushed line by line, so `lab run ... > run.txt`
reads in order.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Any, Callable, TextIO

# comms events worth an operator's attention (drivers/transport.py writes them as `event` notes)
COMMS_WARNINGS = ("retry ", "reconnect", "link ")


@dataclass
class Console:
    show_progress: bool = True            # False with --quiet: no bars and no per-step lines
    out: TextIO = field(default_factory=lambda: sys.stdout)
    err: TextIO = field(default_factory=lambda: sys.stderr)

    @property
    def bars(self) -> bool:
        """Progress bars: only on a terminal, and not with --quiet."""
        return self.show_progress and _isatty(self.err)

    @property
    def plain_steps(self) -> bool:
        """One plain line per step instead of bars (output redirected)."""
        return self.show_progress and not _isatty(self.err)

    def line(self, text: str) -> None:
        """A line for the operator; above the bars when they are drawn, so they don't tear it."""
        if self.bars:
            from tqdm import tqdm

            tqdm.write(text, file=self.out)
            self.out.flush()
        else:
            print(text, file=self.out, flush=True)

    def warn(self, text: str) -> None:
        self.line(f"warning: {text}")

    def step(self, index: int, total: int, name: str) -> None:
        """A step starts: its plain line when there are no bars."""
        if self.plain_steps:
            width = len(str(total))
            self.line(f"step {index + 1:>{width}}/{total} {name}")

    def comms_tap(self, sink: Callable[[Any], None]) -> Callable[[Any], None]:
        """A comms sink that forwards every record to `sink` and prints retries and reconnects."""
        def tap(record: Any) -> None:
            sink(record)
            note = getattr(record, "note", "") or ""
            if getattr(record, "direction", "") == "event" and note.startswith(COMMS_WARNINGS):
                self.warn(f"{record.device}: {note}")
        return tap


class ConsoleRecorder:
    """The run's recorder as procedures see it: every call goes to the recorder; warning and error
    log lines are printed as well, when they are written.  (A wrapper, not a recorder feature, so
    that a recorder used without a console stays silent.)"""

    def __init__(self, recorder: Any, console: Console) -> None:
        self._recorder = recorder
        self._console = console

    def __getattr__(self, name: str) -> Any:
        return getattr(self._recorder, name)

    def log_text(self, level: str | int, text: str, t_s: float | None = None) -> None:
        self._recorder.log_text(level, text, t_s)
        if isinstance(level, str) and level.lower() in ("warning", "warn"):
            self._console.warn(text)
        elif (isinstance(level, str) and level.lower() in ("error", "fatal")) or (isinstance(level, int) and level >= 4):
            self._console.line(f"error: {text}")


def console_of(run: Any) -> Console:
    """The console of a RunContext (a default one where a caller built the context without it)."""
    c = getattr(run, "console", None)
    return c if isinstance(c, Console) else Console(show_progress=False)


def _isatty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False
