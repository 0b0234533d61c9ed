"""The journal of a study: every finished trial's result, one JSON line each, appended the moment
it arrives, so an interrupted study (Ctrl-C, a kill, a lost machine) keeps what it finished and a
rerun of the same command picks up where it stopped.

The first line names the study (its parameters, not how it is run: a study interrupted on two
local workers may be resumed on a Dask cluster).  A journal of another study is set aside, not
mixed in.  A last line cut short by a kill is dropped on reading.  The study deletes its journal
once its own output file is written (`finish`): a finished study is re-measured, not replayed.

A journal is read like any input: what it restores goes into a study's tables and figures as if
measured now.  Each line carries the CRC-32 of what the study wrote, so a line edited since (a NaN
typed in, a number changed) is refused in one line naming the file, the line and the trial,
not taken for a measurement; a study may also check each restored result's values (`validate`)."""

from __future__ import annotations

import json
import math
import os
import sys
import threading
import zlib
from pathlib import Path
from typing import Any, Callable

from lab.core.errors import UserError

JOURNAL_NAME = "trials.jsonl"
JOURNAL_FORMAT = 2          # 2: each line with its CRC-32


def _crc(key: str, result: Any) -> int:
    return zlib.crc32(json.dumps({"key": key, "result": result}, sort_keys=True).encode())


def _line(key: str, result: Any) -> str:
    return json.dumps({"key": key, "result": result, "crc": _crc(key, result)}) + "\n"


def finite_values(result: Any, where: str = "result") -> str | None:
    """The first number in `result` that is not finite (NaN, Infinity: not JSON, never a
    measurement of the studies that use this check, which write null for "none"), or None."""
    if isinstance(result, float) and not math.isfinite(result):
        return f"{where} is {result}"
    if isinstance(result, dict):
        for k, v in result.items():
            bad = finite_values(v, f"{where}.{k}")
            if bad:
                return bad
    elif isinstance(result, list):
        for i, v in enumerate(result):
            bad = finite_values(v, f"{where}[{i}]")
            if bad:
                return bad
    return None


class Journal:
    def __init__(self, path: str | os.PathLike, study: dict[str, Any], *, say: bool = True,
                 validate: Callable[[Any], str | None] | None = None) -> None:
        self.path = Path(path)
        self.study = json.loads(json.dumps(study))   # the header as it reads back, for comparison
        self.validate = validate
        self._lock = threading.Lock()
        self._fh: Any = None
        self._finished: dict[str, Any] = self._read(say)

    @property
    def restored(self) -> int:
        """Trials finished by an earlier, interrupted run of this study."""
        return len(self._finished)

    def finished(self) -> dict[str, Any]:
        with self._lock:
            return dict(self._finished)

    def append(self, key: str, result: Any) -> None:
        line = _line(key, result)
        with self._lock:
            if self._fh is None:
                self._open()
            self._fh.write(line)
            self._fh.flush()   # in the OS's hands: a killed process loses nothing written
            self._finished[key] = result

    def close(self) -> None:
        with self._lock:
            if self._fh is not None:
                self._fh.close()
                self._fh = None

    def finish(self) -> None:
        """The study is complete and its output written: the journal has served."""
        self.close()
        self.path.unlink(missing_ok=True)

    # ---------------------------------------------------------------------------------------------

    def _read(self, say: bool) -> dict[str, Any]:
        try:
            lines = self.path.read_text().splitlines()
        except FileNotFoundError:
            return {}
        except (OSError, UnicodeDecodeError) as exc:
            self._set_aside(f"unreadable ({exc})", say)
            return {}
        entries: dict[str, Any] = {}
        try:
            header = json.loads(lines[0]) if lines else None
        except json.JSONDecodeError:
            header = None
        if not isinstance(header, dict) or header.get("study") != self.study:
            self._set_aside("of another study" if isinstance(header, dict) else "not a journal", say)
            return {}
        if header.get("journal") != JOURNAL_FORMAT:
            self._set_aside("written by another version of lab (its lines carry no checksum)", say)
            return {}
        for n, line in enumerate(lines[1:], start=2):
            try:
                entry = json.loads(line)
                key, result = entry["key"], entry["result"]
            except (json.JSONDecodeError, KeyError, TypeError):
                break   # a line cut short by a kill: everything before it is good
            fix = "delete that line to measure the trial again, or the file to start afresh"
            if entry.get("crc") != _crc(key, result):
                raise UserError(f"{self.path} line {n} (trial {key}): not what the study wrote (its checksum does "
                                f"not match: edited or damaged since); {fix}")
            problem = self.validate(result) if self.validate is not None else None
            if problem:
                raise UserError(f"{self.path} line {n} (trial {key}): {problem}: not a result of this study; {fix}")
            entries[key] = result
        if entries and say:
            print(f"resuming: {len(entries)} finished trials from {self.path} (delete it to start afresh)",
                  file=sys.stderr, flush=True)
        return entries

    def _set_aside(self, why: str, say: bool) -> None:
        old = self.path.with_name(self.path.name + ".old")
        os.replace(self.path, old)
        if say:
            print(f"note: {self.path} is {why}; moved to {old.name}, starting afresh", file=sys.stderr, flush=True)

    def _open(self) -> None:
        # Rewritten whole (atomically) before the first append: drops a cut-short last line, which an
        # append would otherwise glue the next entry onto.
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.name + ".tmp")
        with open(tmp, "w") as fh:
            fh.write(json.dumps({"study": self.study, "journal": JOURNAL_FORMAT}) + "\n")
            for key, result in self._finished.items():
                fh.write(_line(key, result))
        os.replace(tmp, self.path)
        self._fh = open(self.path, "a")
