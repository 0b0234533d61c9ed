"""The step runner: runs a procedure's named steps under a run recorder, with progress, operator
prompts, Ctrl-C handling, dry runs, checkpoints and resume.

Invariants (Bluesky's `finally:`, not its machinery):
- every exit path stops every device that moved, writes the run's stop record and summary.json;
- a step's records are on disk (chunk ended, fsynced) before the next step starts, and so is the
  checkpoint that lets `lab resume RUN_DIR` re-run the interrupted step and keep everything before;
- steps are safe to repeat: a step re-run from its checkpoint gives the same result (simulated noise
  is seeded per step).
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Protocol

from lab.core.errors import LabError, UserError

RUN_FILE = "run.mcap"
RUN_INFO = "run.json"
CHECKPOINT = "checkpoint.json"
SUMMARY = "summary.json"


@dataclass(frozen=True)
class StepSpec:
    index: int                  # 0-based position in the plan
    name: str                   # e.g. "module 13D"
    params: dict[str, Any] = field(default_factory=dict)


class StopRun(LabError):
    """Raised by a step to end the run early on purpose (e.g. a flagged module with --on-flag stop).
    The run ends `aborted` with this reason; it is not a crash."""


class Procedure(Protocol):
    name: str

    def plan(self) -> list[StepSpec]: ...
    def dry_run_problems(self, steps: list[StepSpec]) -> list[str]: ...
    def execute(self, step: StepSpec, run: "RunContext") -> None: ...
    def checkpoint(self) -> dict[str, Any]: ...
    def restore(self, state: dict[str, Any], steps_done: list[StepSpec], run: "RunContext") -> None: ...
    def summary(self, result: str, reason: str) -> dict[str, Any]: ...
    def stop_devices(self) -> list[str]: ...
    def close(self) -> None: ...


class Operator:
    """Asks the operator; `auto` answers every prompt with its default (simulation, CI).
    Every question and answer goes to the run's /operator channel."""

    def __init__(self, auto: bool, recorder: Any = None, input_fn: Callable[[str], str] = input) -> None:
        self.auto = auto
        self.recorder = recorder
        self._input = input_fn

    def ask(self, question: str, choices: tuple[str, ...] = ("ok",), default: str | None = None) -> str:
        default = default if default is not None else choices[0]
        if self.auto:
            answer = default
        else:
            prompt = f"{question} [{'/'.join(c.upper() if c == default else c for c in choices)}] "
            while True:
                raw = self._input(prompt).strip().lower()
                answer = raw or default
                if answer in choices:
                    break
                print(f"please answer one of: {', '.join(choices)}", file=sys.stderr)
        if self.recorder is not None:
            self.recorder.log_prompt(question, answer, automatic=self.auto)
        return answer

    def ask_length(self, question: str, default_m: float | None = None) -> float:
        """A length the operator reads off a ruler, typed in millimetres (SI inside: returns metres).
        In simulation the world's reading is the default, which --auto accepts."""
        if self.auto:
            if default_m is None:
                raise UserError(f"--auto cannot answer {question!r}: only a simulated rig supplies readings")
            value = float(default_m)
            text = f"{value * 1000:.3f}"
        else:
            hint = f" [{default_m * 1000:.3f}]" if default_m is not None else ""
            while True:
                raw = self._input(f"{question}{hint} mm: ").strip()
                if not raw and default_m is not None:
                    value = float(default_m)
                    break
                try:
                    value = float(raw) / 1000.0
                except ValueError:
                    print(f"not a number of millimetres: {raw!r}", file=sys.stderr)
                    continue
                if value > 0 and value < 1e3:
                    break
                print(f"a length must be a positive number of millimetres, got {raw!r}", file=sys.stderr)
            text = f"{value * 1000:.3f}"
        if self.recorder is not None:
            self.recorder.log_prompt(question, f"{text} mm", automatic=self.auto)
        return value

    def confirm(self, instruction: str) -> None:
        """An instruction the operator acknowledges (place a module, attach IPJRs)."""
        answer = self.ask(instruction, ("done", "abort"), "done")
        if answer == "abort":
            raise StopRun(f"operator aborted at: {instruction}")


@dataclass
class RunContext:
    run_dir: Path
    recorder: Any
    operator: Operator
    step: StepSpec | None = None
    progress: Callable[[str], None] = lambda text: None
    show_progress: bool = True
    console: Any = None         # procedures.console.Console: lines and warnings for the operator

    @contextmanager
    def move(self, description: str) -> Iterator[Callable[[float], None]]:
        """A progress bar for one device move; yields the driver's `progress(fraction)` callback."""
        from tqdm import tqdm

        self.progress(description)
        with tqdm(total=100, desc=f"  {description}", unit="%", leave=False, position=1, file=sys.stderr,
                  disable=not self.show_progress, bar_format="{desc}: {percentage:3.0f}%|{bar}|") as bar:
            def update(fraction: float) -> None:
                bar.n = int(round(100 * min(1.0, max(0.0, fraction))))
                bar.refresh()

            yield update
            update(1.0)


class EncodedList:
    """A list a checkpoint holds that only grows at its end (every view taken so far): each item is
    encoded to JSON once, at the first checkpoint that writes it, so a checkpoint costs a step its new
    items and a copy, not the encoding of all of them (at N = 7 the checkpoint reached 34 MB; encoding
    it whole after every step was O(views^2) over a run).  Items must not change once written."""

    def __init__(self, items: list[Any]) -> None:
        self.items = items
        self._encoded: list[str] = []

    def encoded(self) -> str:
        for item in self.items[len(self._encoded):]:
            self._encoded.append(json.dumps(item, separators=(",", ":"), default=_json_default))
        return "[" + ",".join(self._encoded) + "]"


def _atomic_write_json(path: Path, value: Any, *, readable: bool = True) -> None:
    """`readable=False` for the checkpoint, which only a resume reads and which grows with every
    view: without indent the C encoder writes it in one call (the indented encoder is Python, ~90 ms
    a step for the README job's 1.8 MB checkpoint by the end).  An `EncodedList` goes in as its
    items' JSON, encoded once each."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    spliced: list[str] = []

    def default(o: Any) -> Any:
        if isinstance(o, EncodedList):
            spliced.append(o.encoded())
            return f"\0{len(spliced) - 1}\0"       # a placeholder no other string holds
        return _json_default(o)

    text = json.dumps(value, indent=1 if readable else None, separators=None if readable else (",", ":"),
                      default=default)
    for i, raw in enumerate(spliced):
        text = text.replace(json.dumps(f"\0{i}\0"), raw, 1)
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if hasattr(o, "__dataclass_fields__"):
        from dataclasses import asdict

        return asdict(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


@dataclass
class RunOutcome:
    result: str          # completed | aborted | failed
    reason: str
    summary: dict[str, Any]
    run_dir: Path

    @property
    def exit_code(self) -> int:
        return {"completed": 0, "aborted": 3, "failed": 1}[self.result]


def dry_run(procedure: Procedure) -> int:
    """Check every planned move against limits and the workspace; move nothing."""
    steps = procedure.plan()
    problems = procedure.dry_run_problems(steps)
    # what a run would go on with but should say (a procedure may have none)
    warnings = getattr(procedure, "dry_run_warnings", lambda steps: [])(steps)
    print(f"dry run of {procedure.name}: {len(steps)} steps planned")
    for note in getattr(procedure, "dry_run_notes", lambda steps: [])(steps):
        print(f"  {note}")
    for w in warnings:
        print(f"  WARNING: {w}")
    for p in problems:
        print(f"  REFUSED: {p}")
    print("all planned moves are within limits" if not problems else
          f"{len(problems)} problem{'s' if len(problems) > 1 else ''}: the run would be refused")
    return 0 if not problems else 2


def run(procedure: Procedure, run_dir: Path, *, info: dict[str, Any], operator_auto: bool,
        recorder_factory: Callable[[Path], Any], resume: dict[str, Any] | None = None,
        show_progress: bool = True, restored: bool = False, console: Any = None) -> RunOutcome:
    """Run `procedure` into `run_dir`.  `info` (procedure name, its CLI parameters, rig, scenario)
    is written to run.json so that `lab resume` can rebuild the procedure.  `resume` is a loaded
    checkpoint: its completed steps are kept and the interrupted one runs again (`restored`: the
    caller has already restored the procedure's state from it, before anything was archived).

    Signals: the first Ctrl-C or SIGTERM aborts the run; from then on (and during every clean-up)
    further ones are noted and ignored, so any number of them ends exactly like one: every device
    that moved stopped, the stop record and summary.json written and consistent.

    `console` (procedures.console.Console): progress bars only on a terminal, else one plain line
    per step; default: one built from `show_progress`."""
    from tqdm import tqdm

    from procedures.console import Console

    console = console if console is not None else Console(show_progress)

    run_dir.mkdir(parents=True, exist_ok=True)
    steps = procedure.plan()
    start = 0 if resume is None else int(resume["steps_completed"])
    if start > len(steps):
        raise UserError(f"{run_dir / CHECKPOINT}: steps_completed {start} is more than the {len(steps)} steps planned")
    if resume is not None and not restored:
        restore_state(procedure, resume, steps[:start], run_dir)
    if resume is None:
        _atomic_write_json(run_dir / RUN_INFO, info)
    shield = SignalShield()
    shield.install()
    from procedures.pause import PauseAbort, PauseControl, interactive

    pause = PauseControl(shield, interactive(operator_auto), say=console.line)   # first Ctrl-C: pause
    pause.install()
    recorder = None
    result, reason, tb = "completed", "", ""
    ctx = RunContext(run_dir, None, Operator(operator_auto, None), show_progress=console.bars, console=console)
    bar = tqdm(total=len(steps), initial=start, desc=procedure.name, unit="step",
               disable=not console.bars, file=sys.stderr, leave=True)
    try:
        try:
            recorder = recorder_factory(run_dir / RUN_FILE)
            ctx.recorder = recorder
            ctx.operator.recorder = recorder
            if resume is not None:
                recorder.log_text("info", f"resumed at step {start} of {len(steps)}")
            for step in steps[start:]:
                ctx.step = step
                console.step(step.index, len(steps), step.name)
                bar.set_postfix_str(step.name)
                ctx.progress = bar.set_postfix_str
                with recorder.step(step.name, step.index, step.params):
                    procedure.execute(step, ctx)
                with shield.held():   # a checkpoint is written whole or not at all
                    # the summary first: a run killed between the two still has a summary of every
                    # step its checkpoint holds (killed just after the first step's checkpoint, a
                    # run had none)
                    _atomic_write_json(run_dir / SUMMARY, procedure.summary("running", ""))
                    _atomic_write_json(run_dir / CHECKPOINT, {
                        "steps_completed": step.index + 1, "last_step": step.name,
                        "state": procedure.checkpoint(), "time": time.time()}, readable=False)
                bar.update(1)
                if step is not steps[-1]:
                    pause.at_safe_point(step.name, procedure.stop_devices, ctx.operator, recorder)
        except KeyboardInterrupt as exc:
            result = "aborted"
            reason = (str(exc) if isinstance(exc, PauseAbort) else
                      f"interrupted by the operator during {ctx.step.name if ctx.step else 'start-up'}")
            tb = traceback.format_exc()
        except StopRun as exc:
            result, reason = "aborted", str(exc)
        except Exception as exc:  # a device fault or a bug: stop, record, report
            result, reason = "failed", f"{type(exc).__name__}: {exc}"
            tb = traceback.format_exc()
    finally:
        shield.cleanup = True   # from here on no signal interrupts: the clean-up must finish
        try:
            bar.close()
            stopped = _stop_all(procedure)
            if result == "aborted" and shield.signals:   # every signal, those during the clean-up too
                reason = f"{reason} ({shield.describe()})"
            if stopped:
                reason = f"{reason} (stopped: {', '.join(stopped)})" if reason else reason
            if result == "completed" and recorder is not None:
                missing = sorted(set(range(len(steps))) - recorder.step_indices_ended)
                if missing:
                    result, reason = "failed", (f"the log lacks the records of step(s) {missing[:10]}"
                                                f"{'...' if len(missing) > 10 else ''}; not calling the run completed")
            if result == "completed" and shield.signals:
                reason = f"completed before the interrupt took effect ({shield.describe()})"
            summary = procedure.summary(result, reason)
            summary.setdefault("result", result)
            summary.setdefault("reason", reason)
            if recorder is not None:
                try:
                    recorder.log_json("summary", summary)
                except Exception:
                    pass
                recorder.stop(result, reason, tb)
            _atomic_write_json(run_dir / SUMMARY, summary)
            _remove_stale_tmp(run_dir)
            procedure.close()
        finally:
            pause.restore()
            shield.restore()
    return RunOutcome(result, reason, summary, run_dir)


def restore_state(procedure: Procedure, resume: dict[str, Any], steps_done: list[StepSpec], run_dir: Path) -> None:
    """Rebuild the procedure's state from a checkpoint; a state that does not fit the run is the
    checkpoint's fault, said in one line, before anything has moved."""
    try:
        procedure.restore(resume["state"], steps_done, None)  # type: ignore[arg-type]
    except LabError:
        raise
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        raise UserError(f"{run_dir / CHECKPOINT}: state does not fit this run ({type(exc).__name__}: {exc}); "
                        f"refusing to resume from it") from None


class SignalShield:
    """SIGINT and SIGTERM for the length of a run: the first one raises KeyboardInterrupt (abort);
    any later one, or any during clean-up or inside `held()`, is counted and otherwise ignored."""

    def __init__(self) -> None:
        self.signals: list[int] = []
        self.cleanup = False
        self._held = 0
        self._pending = False
        self._raised = False
        self._previous: dict[int, Any] = {}

    def install(self) -> None:
        if not _main_thread():
            return
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.getsignal(sig)
            signal.signal(sig, self._handle)

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: Any) -> None:
        self.signals.append(signum)
        if self.cleanup or self._raised:
            return
        if self._held:
            self._pending = True
            return
        self._raised = True
        raise KeyboardInterrupt(f"signal {signum}")

    @contextmanager
    def held(self) -> Iterator[None]:
        """Defer a signal until the block is done (then raise it)."""
        self._held += 1
        try:
            yield
        finally:
            self._held -= 1
        if self._pending and not self._held and not self._raised and not self.cleanup:
            self._pending = False
            self._raised = True
            raise KeyboardInterrupt("signal deferred")

    def describe(self) -> str:
        names = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}
        n = len(self.signals)
        kinds = sorted({names.get(s, str(s)) for s in self.signals})
        return f"{n} signal{'s' if n != 1 else ''}: {', '.join(kinds)}"


def _remove_stale_tmp(run_dir: Path) -> None:
    for p in run_dir.glob("*.json.tmp"):
        try:
            p.unlink()
        except OSError:
            pass


def _stop_all(procedure: Procedure) -> list[str]:
    """Stop every device that moved; a failure to stop one must not keep the others moving."""
    try:
        return procedure.stop_devices()
    except Exception as exc:  # pragma: no cover - reported, never raised over the original error
        print(f"lab: warning: stopping devices failed: {exc}", file=sys.stderr)
        return []


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def load_resume(run_dir: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """(run.json info, checkpoint) of an interrupted run, checked (procedures/resume.py)."""
    from procedures.resume import load_run

    return load_run(run_dir)
