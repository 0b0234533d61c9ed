"""Progress of a study: a bar on stderr where someone watches it (a terminal), nothing otherwise.

As in `procedures/console.py`: redirected to a file a bar redraws itself as hundreds of lines, and
`--json` output on stdout must stay clean.  One bar per study; its total grows as each batch of
trials is handed to the executor (studies that plan their later trials from earlier results do
not know the total up front)."""

from __future__ import annotations

import sys
import threading
from typing import Any


class Progress:
    def __init__(self, label: str, enabled: bool | None = None) -> None:
        self.enabled = _isatty(sys.stderr) if enabled is None else enabled
        self._lock = threading.Lock()
        self._bar: Any = None
        self.total = 0
        self.done = 0
        if self.enabled:
            from tqdm import tqdm

            self._bar = tqdm(total=0, desc=label, unit="trial", file=sys.stderr, leave=False, dynamic_ncols=True)

    def add(self, total: int, done: int = 0) -> None:
        """`total` more trials, `done` of them already finished (restored from a journal)."""
        with self._lock:
            self.total += total
            self.done += done
            if self._bar is not None:
                self._bar.total = self.total
                self._bar.update(done)

    def update(self, n: int) -> None:
        with self._lock:
            self.done += n
            if self._bar is not None:
                self._bar.update(n)

    def close(self) -> None:
        with self._lock:
            if self._bar is not None:
                self._bar.close()
                self._bar = None


def _isatty(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False
