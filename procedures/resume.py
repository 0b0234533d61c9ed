"""Run directories and resume: who owns a run directory, what may be written into one, and how an
interrupted run's completed steps are carried into the resumed run's log without ever losing or
inventing one.

A run directory holds `run.json` (how to rebuild the procedure), `checkpoint.json` (the state
after the last completed step), `summary.json`, `run.mcap` (the current log) and, after resumes,
`run.part1.mcap`, `run.part2.mcap`, ... (earlier logs, moved aside).  Resume

1. reads `run.json` and `checkpoint.json` (one-line error if either is not what `lab run` wrote);
2. indexes every log part and finds, for each step the checkpoint says is done, a part holding
   that step complete (start and end records); if any is missing it refuses, naming the steps;
3. writes the resumed log to `run.resume.mcap`, copies every completed step from its part, and
   only then renames it to `run.mcap` — a kill during the copy leaves the parts untouched and the
   half copy under a name the next resume deletes."""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lab.core.errors import UserError
from lab.core.locks import FileLock
from lab.core.recorder import messages as m
from lab.core.recorder import topics
from lab.core.recorder.reader import ScanState, iter_messages

RUN_FILE = "run.mcap"
RESUME_FILE = "run.resume.mcap"
RUN_INFO = "run.json"
CHECKPOINT = "checkpoint.json"
SUMMARY = "summary.json"
LOCK = ".lock"
PROCEDURES = ("borg", "truss")
_PART = re.compile(r"^run\.part(\d+)\.mcap$")
_RUN_FILES = (RUN_FILE, RESUME_FILE, RUN_INFO, CHECKPOINT, SUMMARY)
_SKIP = {topics.RUN_START, topics.RUN_STOP, topics.STRUCTURE}


# ---- ownership and the --out directory ------------------------------------------------------


def lock_run_dir(run_dir: Path) -> FileLock:
    """Own a run directory for this process (one owner: a second run or resume on it is refused,
    naming the holder)."""
    return FileLock(run_dir / LOCK, f"run directory {run_dir}").acquire()


def run_files(run_dir: Path) -> list[Path]:
    """The files of a run in `run_dir` (what --replace removes)."""
    if not run_dir.is_dir():
        return []
    out = [run_dir / n for n in _RUN_FILES if (run_dir / n).exists()]
    out += sorted(p for p in run_dir.iterdir() if _PART.match(p.name))
    out += sorted(p for p in run_dir.iterdir() if p.name.endswith(".json.tmp") or p.name.endswith(".recovered.mcap"))
    return out


def prepare_out_dir(run_dir: Path, replace: bool) -> FileLock:
    """Check `--out`, create it and take its lock.  Refused (one line): a file, a path that cannot
    be created or written, a directory holding another run (unless `replace`), a directory
    holding other things."""
    if run_dir.exists() and not run_dir.is_dir():
        raise UserError(f"--out {run_dir}: is a file, not a directory")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {run_dir}: cannot create the run directory: {exc.strerror or exc}") from None
    if not os.access(run_dir, os.W_OK | os.X_OK):
        raise UserError(f"--out {run_dir}: not writable")
    lock = lock_run_dir(run_dir)
    try:
        existing = run_files(run_dir)
        if existing and not replace:
            raise UserError(f"--out {run_dir} already holds a run ({existing[0].name}); pass --replace to "
                            f"overwrite it, or `lab resume {run_dir}` to continue it")
        others = [p for p in run_dir.iterdir() if p.name != LOCK and p not in existing]
        if others:
            raise UserError(f"--out {run_dir} is not empty and holds no run ({others[0].name}); choose a new "
                            f"or empty directory")
        for p in existing:
            p.unlink()
    except BaseException:
        lock.release()
        raise
    return lock


# ---- run.json and checkpoint.json -----------------------------------------------------------


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg}); the run cannot be resumed "
                        f"from it") from None
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file; the run cannot be resumed from it") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read it: {exc.strerror or exc}") from None


def load_run(run_dir: Path, completed: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
    """(run.json info, checkpoint) of an interrupted run (or, with `completed`, of any run: `lab
    bench replay` reads finished ones), checked; a one-line UserError otherwise."""
    if not run_dir.is_dir():
        raise UserError(f"{run_dir}: no such run directory")
    info_path, ckpt_path = run_dir / RUN_INFO, run_dir / CHECKPOINT
    if not info_path.exists():
        raise UserError(f"{run_dir} is not a run directory (no {RUN_INFO})")
    info = _read_json(info_path)
    if not isinstance(info, dict):
        raise UserError(f"{info_path}: expected a JSON object, got {type(info).__name__}")
    if info.get("procedure") == "calibrate_rig":
        raise UserError(f"{info_path}: a rig calibration run cannot be resumed; run `lab calibrate rig` again "
                        f"(the survey takes under a minute)")
    if info.get("procedure") not in PROCEDURES:
        raise UserError(f"{info_path}: procedure: expected one of {', '.join(PROCEDURES)}, got {info.get('procedure')!r}")
    if not isinstance(info.get("params"), dict):
        raise UserError(f"{info_path}: params: expected a JSON object, got {info.get('params')!r}")
    if info["procedure"] == "truss" and not isinstance(info["params"].get("name"), str):
        raise UserError(f"{info_path}: params.name: expected the truss name, got {info['params'].get('name')!r}")
    ckpt: Any = {"steps_completed": 0, "state": {}}
    if ckpt_path.exists():
        ckpt = _read_json(ckpt_path)
        if not isinstance(ckpt, dict):
            raise UserError(f"{ckpt_path}: expected a JSON object, got {type(ckpt).__name__}")
        n = ckpt.get("steps_completed")
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise UserError(f"{ckpt_path}: steps_completed: expected a non-negative integer, got {n!r}")
        if not isinstance(ckpt.get("state"), dict):
            raise UserError(f"{ckpt_path}: state: expected a JSON object, got {ckpt.get('state')!r}")
    summary_path = run_dir / SUMMARY
    if summary_path.exists():
        try:
            summary = json.loads(summary_path.read_text())
        except (ValueError, OSError):
            summary = {}   # a torn summary says nothing; the checkpoint and the logs decide
        if isinstance(summary, dict) and summary.get("result") == "completed" and not completed:
            raise UserError(f"{run_dir}: the run completed; nothing to resume")
    return info, ckpt


# ---- the logs -------------------------------------------------------------------------------


@dataclass
class PartIndex:
    """Which steps a log part holds complete, and where: step index -> (first, last) message
    ordinal of its segment (from after the previous step's end to its own end record)."""

    path: Path
    order: int                     # parts in age order; run.mcap is the newest
    steps: dict[int, tuple[int, int]] = field(default_factory=dict)
    scan: ScanState = field(default_factory=ScanState)


def log_parts(run_dir: Path) -> list[Path]:
    """Every log of the run, oldest first: run.part1.mcap, run.part2.mcap, ..., run.mcap."""
    parts = sorted((int(mt.group(1)), p) for p in run_dir.iterdir() if (mt := _PART.match(p.name)))
    out = [p for _, p in parts]
    if (run_dir / RUN_FILE).exists():
        out.append(run_dir / RUN_FILE)
    return out


def index_part(path: Path, order: int) -> PartIndex:
    idx = PartIndex(path, order)
    seg_start = 0
    open_start: dict[int, int] = {}
    try:
        for k, rm in enumerate(iter_messages(path, state=idx.scan)):
            if rm.topic != topics.RUN_STEP or not isinstance(rm.message, m.StepEvent):
                continue
            ev = rm.message
            if ev.phase == "start":
                open_start[ev.index] = k
            elif ev.phase == "end" and ev.index in open_start:
                idx.steps[ev.index] = (seg_start, k)
                seg_start = k + 1
            else:
                seg_start = k + 1
    except UserError:
        pass   # not an MCAP file at all: it holds no steps
    return idx


@dataclass(frozen=True)
class CopyPlan:
    """Where each completed step's records come from."""

    steps_completed: int
    sources: list[tuple[PartIndex, int, int]]   # (part, first step, last step), in step order

    def remap(self, old: Path, new: Path) -> None:
        for part, _, _ in self.sources:
            if part.path == old:
                part.path = new


def plan_copy(run_dir: Path, steps_completed: int, n_steps: int) -> CopyPlan:
    """Check the logs against the checkpoint: every step it calls done must be complete in some
    part (the newest such part is used).  Refuses in one line when they disagree."""
    ckpt = run_dir / CHECKPOINT
    if steps_completed > n_steps:
        raise UserError(f"{ckpt}: steps_completed {steps_completed} is more than the {n_steps} steps of the run's "
                        f"plan; refusing to resume from it")
    parts = [index_part(p, i) for i, p in enumerate(log_parts(run_dir))]
    chosen: list[PartIndex] = []
    missing: list[int] = []
    for i in range(steps_completed):
        have = [p for p in parts if i in p.steps]
        if not have:
            missing.append(i)
        else:
            chosen.append(have[-1])
    if missing:
        held = sorted({i for p in parts for i in p.steps})
        logs = ", ".join(p.path.name for p in parts) or "no log at all"
        raise UserError(f"{ckpt} says steps 0-{steps_completed - 1} are done, but the run's logs ({logs}) lack "
                        f"step{'s' if len(missing) > 1 else ''} {_ranges(missing)}"
                        f"{' (they hold ' + _ranges(held) + ')' if held else ''}; refusing to resume a run whose "
                        f"log would miss completed steps (recover the missing log or start a new run)")
    sources: list[tuple[PartIndex, int, int]] = []
    for i, part in enumerate(chosen):
        if sources and sources[-1][0] is part and sources[-1][2] == i - 1:
            sources[-1] = (part, sources[-1][1], i)
        else:
            sources.append((part, i, i))
    return CopyPlan(steps_completed, sources)


def _ranges(xs: list[int]) -> str:
    out: list[str] = []
    for x in sorted(xs):
        if out and isinstance(out[-1], str) and out[-1].endswith(f"-{x - 1}"):
            out[-1] = out[-1].rsplit("-", 1)[0] + f"-{x}"
        elif out and out[-1] == str(x - 1):
            out[-1] = f"{x - 1}-{x}"
        else:
            out.append(str(x))
    return ", ".join(out)


def archive_previous_log(run_dir: Path) -> Path | None:
    """Move the interrupted run's log aside as the next `run.partK.mcap` and delete a half copy a
    killed resume left (its records are all still in the parts)."""
    leftover = run_dir / RESUME_FILE
    if leftover.exists():
        leftover.unlink()
    old = run_dir / RUN_FILE
    if not old.exists():
        return None
    k = 1 + max((int(mt.group(1)) for p in run_dir.iterdir() if (mt := _PART.match(p.name))), default=0)
    part = run_dir / f"run.part{k}.mcap"
    os.replace(old, part)
    _fsync_dir(run_dir)
    return part


def copy_completed_steps(plan: CopyPlan, recorder: Any) -> int:
    """Copy every completed step's records into `recorder`, part by part as planned; returns how
    many records were copied.  Raises if a part no longer yields what its index promised."""
    copied = 0
    for part, first, last in plan.sources:
        lo, hi = part.steps[first][0], part.steps[last][1]
        ends = 0
        for k, rm in enumerate(iter_messages(part.path)):
            if k < lo:
                continue
            if k > hi:
                break
            if rm.topic in _SKIP:
                continue
            recorder.copy_message(rm.topic, rm.message, rm.log_time_ns)
            copied += 1
            if rm.topic == topics.RUN_STEP and isinstance(rm.message, m.StepEvent) and rm.message.phase == "end":
                ends += 1
        if ends < last - first + 1:
            raise UserError(f"{part.path}: changed while resuming: steps {first}-{last} no longer complete")
    return copied


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def finish_copy(recorder: Any, run_dir: Path) -> None:
    """The copy is complete and on disk: give the resumed log its real name (atomically)."""
    recorder.sync()
    recorder.rename(run_dir / RUN_FILE)
    _fsync_dir(run_dir)


__all__ = ["lock_run_dir", "prepare_out_dir", "load_run", "plan_copy", "copy_completed_steps", "archive_previous_log",
           "finish_copy", "log_parts", "index_part", "CopyPlan", "run_files"]
