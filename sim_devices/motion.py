"""A simulated actuator: constant-speed motion as a function of wall time (no thread needed).

Speeds and settling times are wall-clock values: a simulator running `speedup` times faster than
the hardware simply is a faster device, and says so in its `LIMITS?` reply, so the drivers'
physics-based timeouts scale with it.

Known limitations: no acceleration ramps (constant speed, instant start and stop), no backlash,
no following error; a multi-axis move (the Stewart legs) interpolates linearly in joint space."""

from __future__ import annotations

import threading
import time
from typing import Callable

import numpy as np


class Axis:
    """One actuator or a coordinated set (a vector position); all components arrive together."""

    def __init__(self, position: float | np.ndarray, speed: float, settle_s: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if speed <= 0:
            raise ValueError(f"speed must be positive, got {speed}")
        self.speed = float(speed)
        self.settle_s = float(settle_s)
        self._clock = clock
        self._lock = threading.RLock()
        self._start = np.array(position, dtype=float)
        self._target = self._start.copy()
        self._t0 = clock()
        self._travel_s = 0.0
        self._moving = False
        self.stuck = False             # a stuck actuator: accepts moves, never gets anywhere
        self.moves = 0                 # moves started: each lands with its own repeatability error

    def _value(self, x: np.ndarray) -> float | np.ndarray:
        return float(x) if x.ndim == 0 else x.copy()

    def _now_pos(self, now: float) -> np.ndarray:
        if not self._moving or self.stuck:
            return self._start
        if self._travel_s <= 0:
            return self._target
        f = min(1.0, (now - self._t0) / self._travel_s)
        return self._start + f * (self._target - self._start)

    def _settle(self, now: float) -> None:
        if self._moving and not self.stuck and now >= self._t0 + self._travel_s + self.settle_s:
            self._start = self._target.copy()
            self._moving = False

    def position(self) -> float | np.ndarray:
        with self._lock:
            now = self._clock()
            self._settle(now)
            return self._value(self._now_pos(now))

    def target(self) -> float | np.ndarray:
        with self._lock:
            return self._value(self._target)

    def moving(self) -> bool:
        """Still travelling or settling (a stuck actuator keeps trying until stopped)."""
        with self._lock:
            self._settle(self._clock())
            return self._moving

    def start(self, target: float | np.ndarray, stuck: bool = False) -> float:
        """Begin a move; returns its travel time (s, wall clock)."""
        with self._lock:
            now = self._clock()
            self._settle(now)
            self._start = self._now_pos(now).copy()
            self._target = np.array(target, dtype=float)
            self._travel_s = float(np.max(np.abs(self._target - self._start))) / self.speed
            self._t0 = now
            self._moving = True
            self.stuck = stuck
            self.moves += 1
            return self._travel_s

    def stop(self) -> None:
        with self._lock:
            now = self._clock()
            self._settle(now)
            pos = self._now_pos(now).copy()
            self._start = pos
            self._target = pos.copy()
            self._moving = False
            self.stuck = False

    def set_position(self, position: float | np.ndarray) -> None:
        """Put the actuator somewhere without moving it there (world set-up)."""
        with self._lock:
            self._start = np.array(position, dtype=float)
            self._target = self._start.copy()
            self._moving = False
