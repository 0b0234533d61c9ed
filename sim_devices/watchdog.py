"""What a simulated device does when its host goes (docs/protocols.md §1, "Host loss"): the two
firmware features that stop a motion nobody is watching any more.

- Link loss: the connection that commanded the motion closes (socket closed or reset, the
  pseudo-terminal hung up): the device stops at once.
- Watchdog: during a motion, the host has sent nothing for longer than `watchdog_s`: the device
  stops.  The only mechanism for HTTP, which has no standing link, and the backstop on a link that
  stays up while its host is frozen (a process stopped with SIGSTOP, a hung host).

`Firmware` says which of them a device has: the default is what docs/protocols.md asks of every
firmware; `watchdog_s = 0` and `stop_on_link_loss = false` ([sim] keys of a rig) make a device of
an older firmware that finishes the move it was given whatever happens to its host.

The watchdog is wall-clock time, not divided by the simulators' `speedup` as their speeds and
settling times are: what it watches is the host's request rate, and a driver polls a moving
device every 0.1 s or more often whatever the speed-up (drivers/motion.py)."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable

WATCHDOG_S = 1.0              # the protocol's watchdog timeout
MIN_WATCHDOG_S = 0.3          # shorter would bite a healthy host between two polls


@dataclass(frozen=True)
class Firmware:
    watchdog_s: float = WATCHDOG_S     # 0: no watchdog
    stop_on_link_loss: bool = True

    def __post_init__(self) -> None:
        if self.watchdog_s != 0 and not MIN_WATCHDOG_S <= self.watchdog_s <= 60.0:
            raise ValueError(f"watchdog_s must be 0 (none) or in [{MIN_WATCHDOG_S:g}, 60] s, got {self.watchdog_s}")


class Watchdog:
    """Stops a moving device whose host has been silent for longer than `timeout_s`.

    `feed()` on every request the host sends; a thread checks every few tens of milliseconds.
    `max_gap_s` is the longest silence seen while the device moved: what the driver's feed
    interval really is (tests compare it with the timeout)."""

    def __init__(self, name: str, timeout_s: float, is_moving: Callable[[], bool], stop: Callable[[], None],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.name = name
        self.timeout_s = timeout_s
        self._is_moving = is_moving
        self._stop_device = stop
        self._clock = clock
        self._lock = threading.Lock()
        self._last = clock()
        self._was_moving = False
        self._quit = threading.Event()
        self._thread: threading.Thread | None = None
        self.fired = 0
        self.max_gap_s = 0.0

    def feed(self) -> None:
        now = self._clock()
        moving = self._is_moving()
        with self._lock:
            if moving or self._was_moving:
                self.max_gap_s = max(self.max_gap_s, now - self._last)
            self._last = now
            self._was_moving = moving

    def start(self) -> Watchdog:
        if self.timeout_s > 0:
            self._thread = threading.Thread(target=self._run, name=f"{self.name}-watchdog", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._quit.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)

    def _run(self) -> None:
        period = min(0.05, self.timeout_s / 10)
        while not self._quit.wait(period):
            if not self._is_moving():
                with self._lock:
                    self._was_moving = False
                continue
            with self._lock:
                silent = self._clock() - self._last
            if silent > self.timeout_s:
                self._stop_device()
                with self._lock:
                    self.fired += 1
                    self._was_moving = False
