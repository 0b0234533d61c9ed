"""What a run tells the operator as it happens, on the console.

- Progress bars only where someone watches them: stderr is a terminal and `--quiet` is not given.
  Redirected to a file, a bar redraws itself as a new line hundreds of times a step (a full BORG run
  wrote ~2,000 lines of them); there one plain line per step is printed instead.
- Findings when they happen, not only in the final table: a procedure's verdict rows
  (`Console.line`), and warnings: every `log_text("warning"|"error", ...)` a procedure writes to the
  run's log (rig calibration problems, rejected tags, re-measures) and the drivers' retries and
  reconnects, which otherwise only reach the comms log.
- The tables: the BORG verification table (a module's row as soon as its verdict is decided, the
  whole table at the end) and the truss node table, both from the run's summary, which is also
  what `lab runs show` prints them from.

Everything goes to stdout (the bars to stderr), flushed line by line, so `lab run ... > run.txt`
reads in order.
"""

from __future__ import annotations

import math
import statistics
import sys
from dataclasses import dataclass, field
from typing import Any, Callable, TextIO

from lab.core.verdicts import tally

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


# ---- the tables ---------------------------------------------------------------------------------

BORG_HEADER = (f"{'module':<7} {'verdict':<10} {'dev mm':>7} {'dev deg':>7} {'tol mm/deg':>10} {'1σ mm':>6} "
               f"{'err mm':>7} {'err deg':>7}  reason")
BORG_LEGEND = ("dev: measured distance from the design, which the verdict judges (ok within tol - 2σ, flagged "
               "beyond tol + 2σ or not fully deployed, uncertain in between once the step's views are spent); "
               "tol: tolerance; 1σ: estimated position uncertainty; err: estimate vs the simulated truth "
               "(blank on hardware)")
TRUSS_LEGEND = ("error: the built node's distance from its design position; estimate error: the estimator's "
                "node position vs the built one (both against the simulated truth, blank on hardware)")
_DEG = 180 / math.pi


def _num(value: float | None, scale: float, digits: int) -> str:
    return "" if value is None else f"{value * scale:.{digits}f}"


def borg_row(mod: dict[str, Any]) -> str:
    """One module's row: deviation from the design (mm, deg), tolerance, 1 sigma, truth error."""
    tol = ""
    if mod.get("tolerance_m") is not None and mod.get("tolerance_rad") is not None:
        tol = f"{mod['tolerance_m'] * 1000:g}/{math.degrees(mod['tolerance_rad']):g}"
    return (f"{mod['name']:<7} {mod['verdict']:<10} {_num(mod.get('deviation_m'), 1000, 2):>7} "
            f"{_num(mod.get('deviation_rad'), _DEG, 3):>7} {tol:>10} "
            f"{_num(mod.get('sigma_position_m'), 1000, 2):>6} {_num(mod.get('position_error_m'), 1000, 2):>7} "
            f"{_num(mod.get('rotation_error_rad'), _DEG, 3):>7}  {mod.get('reason', '')}").rstrip()


def more_views_line(name: str, deviation_m: float | None, sigma_m: float | None, views: int) -> str:
    """An uncertain module about to be measured again."""
    return (f"  {name}: uncertain ({_num(deviation_m, 1000, 2)} mm, 1σ {_num(sigma_m, 1000, 2)} mm); "
            f"{views} more view(s)")


def confirm_views_line(name: str, sigma_m: float, target_m: float, views: int) -> str:
    """An `ok` module about to be measured again: its 1-sigma is far above the step's target."""
    return (f"  {name}: ok at 1σ {_num(sigma_m, 1000, 2)} mm, over twice the {_num(target_m, 1000, 2)} mm target; "
            f"{views} more view(s)")


def sigma_target_line(summary: dict[str, Any]) -> str | None:
    """How many measured modules reached the 1-sigma their views were planned for, beside what the
    plans predicted (their views' share with the floor the modules before them showed: where the
    floor is over the target, a plan stops short of it and says so).  None for a summary without a
    target (older runs) or without a measured module."""
    target = summary.get("sigma_target_m")
    measured = [m for m in summary.get("modules", []) if m.get("sigma_position_m") is not None]
    if target is None or not measured:
        return None
    sigmas = sorted(m["sigma_position_m"] for m in measured)
    met = sum(s <= target for s in sigmas)
    planned = sorted(m["predicted_sigma_m"] for m in measured if m.get("predicted_sigma_m") is not None)
    line = (f"1σ target {target * 1000:.2f} mm: reached by {met} of {len(measured)} measured modules "
            f"(1σ median {statistics.median(sigmas) * 1000:.2f} mm, largest {sigmas[-1] * 1000:.2f} mm")
    if planned:
        line += f"; the plans predicted {statistics.median(planned) * 1000:.2f} mm median"
    return line + ")"


def borg_table(summary: dict[str, Any]) -> str:
    """The verification table printed at the end of `lab run borg` (and by `lab runs show`)."""
    modules = summary.get("modules", [])
    counts = tally(mod["verdict"] for mod in modules)
    target = sigma_target_line(summary)
    return "\n".join([BORG_HEADER, *(borg_row(mod) for mod in modules),
                      ", ".join(f"{n} {v}" for v, n in counts.items())
                      + f"; rejected tags: {summary.get('rejected_tags', [])}",
                      *([target] if target else []), BORG_LEGEND])


def truss_table(summary: dict[str, Any]) -> str:
    """The node table printed at the end of `lab run truss` (and by `lab runs show`)."""
    lines = [TRUSS_LEGEND, f"{'node':>5} {'error (mm)':>11} {'estimate error (mm)':>20}"]
    for n in summary.get("nodes", []):
        e = n.get("error_m")
        ee = n.get("estimate_error_m")
        lines.append(f"{n['id']:>5} {'' if e is None else f'{e * 1000:.3f}':>11} "
                     f"{'' if ee is None else f'{ee * 1000:.3f}':>20}")
    rms = summary.get("rms_node_error_m")
    if rms is not None:
        lines.append(f"rms node error {rms * 1000:.3f} mm over {summary.get('steps')} nodes "
                     f"({summary.get('estimator')})")
    return "\n".join(lines)
