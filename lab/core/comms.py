"""The comms log: every byte a driver sends or receives, as records a sink can store.

Drivers call a `CommsSink` (any callable taking a `CommsRecord`); the run recorder provides one that
writes to the run's `/comms` channel, tests use `MemoryComms`.  The transport base class owns the
call so that no driver can skip it."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Literal

Direction = Literal["tx", "rx", "event"]


@dataclass(frozen=True)
class CommsRecord:
    device: str          # rig name of the device, e.g. "turntable", "ipjr1"
    url: str             # transport URL, e.g. "socket://127.0.0.1:5001", "http://127.0.0.1:8101"
    direction: Direction  # tx = to the device, rx = from it, event = transport event (timeout, reconnect)
    data: bytes
    t_s: float = field(default_factory=time.time)
    note: str = ""


CommsSink = Callable[[CommsRecord], None]


def null_sink(record: CommsRecord) -> None:
    """A sink that drops everything (for one-off CLI queries with no run to log into)."""


class MemoryComms:
    """A thread-safe in-memory sink, for tests and for `lab devices check --json` detail."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.records: list[CommsRecord] = []

    def __call__(self, record: CommsRecord) -> None:
        with self._lock:
            self.records.append(record)

    def exchanged(self, device: str | None = None) -> list[tuple[str, bytes]]:
        with self._lock:
            return [(r.direction, r.data) for r in self.records if device is None or r.device == device]
