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
        self.label = label
        self._lock = threading.Lock()
        self._bar: Any = None
        self.total = 0
        self.done = 0

    def add(self, total: int, done: int = 0) -> None:
        """`total` more trials, `done` of them already finished (restored from a journal)."""
        with self._lock:
            self.total += total
            self.done += done
            if not self.enabled:
                return
            if self._bar is None:
                # made at the first trials: tqdm drawn with a total of 0 does not redraw when it grows
                from tqdm import tqdm

                self._bar = tqdm(total=self.total, initial=self.done, desc=self.label, unit="trial", file=sys.stderr,
                                 leave=False, dynamic_ncols=True)
            else:
                self._bar.total = self.total
                self._bar.update(done)
                self._bar.refresh()

    def update(self, n: int) -> None:
        with self._lock:
            self.done += n
            if self._bar is not None:
                self._bar.update(n)

    def write(self, text: str) -> None:
        """A line on stdout for the user, above the bar when there is one (so the bar does not tear it)."""
        with self._lock:
            if self._bar is not None:
                from tqdm import tqdm

                tqdm.write(text, file=sys.stdout)
                sys.stdout.flush()
            else:
                print(text, flush=True)

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
