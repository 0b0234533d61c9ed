"""Moves of independent devices at once: the turntable turns while the platform moves (on a real
bench they share nothing but the step's time; the camera is 3 m from the structure), and the view
is taken only once every one of them has arrived.

Each device's move runs its own driver call in a thread of its own (its own link; the transports
hold a lock per port, so a STOP sent from here while its poll runs is safe).  The main thread only
waits, so Ctrl-C (the runner's SignalShield raises it there) reaches it at once.  What a failure
does is what it does for one device, for all of them:

- a device's fault, timeout or lost link: that driver has already stopped its own device; the
  others are stopped at once, their threads joined, and the first failure is the step's error, with
  what happened to the others appended ("; meanwhile stewart: motion stopped");
- KeyboardInterrupt (an abort): every device still moving is stopped, the threads joined, and the
  interrupt goes on with a note of what was stopped.

A device stopped by this module ends its own move short of the target; that MotionIncomplete is
the consequence, not the cause, and is not reported.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from drivers.motion import Progress, annotate, stop_quietly

# after a STOP, how long to wait for a device's move to notice and return (its poll interval is at
# most 0.1 s); a device whose STOP failed may poll on until its own timeout, so do not wait for it
JOIN_S = 5.0


@dataclass(frozen=True)
class Move:
    """One device's move: its driver (`name`, `stop()`), the progress bar's words, and the driver call
    that commands the move and waits until it has settled."""

    device: Any
    description: str
    go: Callable[[Progress | None], Any]


def move_together(run: Any, moves: Sequence[Move]) -> None:
    """Move every device of `moves` at once and return when all have arrived; raise the first
    failure after stopping the others.  `run`: the step's RunContext (its `move` progress bar)."""
    if not moves:
        return
    t0 = time.monotonic()
    if len(moves) == 1:
        with run.move(moves[0].description) as progress:
            moves[0].go(progress)
    else:
        with run.move(" + ".join(m.description for m in moves)) as progress:
            _together(moves, progress)
    recorder = getattr(run, "recorder", None)
    if recorder is not None:
        # the time the devices took (the hardware's share of a run; `lab runs show --timings`)
        recorder.log_metric("motion/move_s", time.monotonic() - t0, "s")


def _together(moves: Sequence[Move], progress: Progress) -> None:
    n = len(moves)
    fractions = [0.0] * n
    failures: list[tuple[int, BaseException]] = []      # in the order they happened
    finished = [False] * n
    lock = threading.Lock()
    changed = threading.Event()

    def report(i: int) -> Progress:
        def update(fraction: float) -> None:
            fractions[i] = fraction
            progress(min(fractions))
        return update

    def work(i: int) -> None:
        try:
            moves[i].go(report(i))
        except BaseException as exc:  # noqa: BLE001 -- handed to the main thread, which raises it
            with lock:
                failures.append((i, exc))
        finally:
            with lock:
                finished[i] = True
            changed.set()

    threads = [threading.Thread(target=work, args=(i,), name=f"move-{m.device.name}", daemon=True)
               for i, m in enumerate(moves)]
    try:
        for t in threads:
            t.start()
        while True:
            changed.wait(0.05)
            with lock:
                changed.clear()
                if failures or all(finished):
                    break
    except BaseException as exc:   # KeyboardInterrupt: the abort stops every device still moving
        annotate(exc, "while moving " + ", ".join(_stop_others(moves, finished, lock, threads, skip=None)))
        raise
    if failures:
        first_i, first = failures[0]
        stopped = _stop_others(moves, finished, lock, threads, skip=first_i)
        if stopped:
            annotate(first, "meanwhile " + ", ".join(stopped))
        raise first


def _stop_others(moves: Sequence[Move], finished: list[bool], lock: threading.Lock,
                 threads: Sequence[threading.Thread], skip: int | None) -> list[str]:
    """STOP every device whose move has not returned (but `skip`, already stopped by its driver),
    then join their threads; returns what happened to each, in words."""
    with lock:
        # a thread an abort kept from starting never commanded its device
        running = [i for i in range(len(moves)) if not finished[i] and i != skip and threads[i].ident is not None]
    said = [f"{moves[i].device.name}: {stop_quietly(moves[i].device.name, moves[i].device.stop)}" for i in running]
    for i in running:
        threads[i].join(JOIN_S)
    return said
