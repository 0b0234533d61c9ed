"""Fault injection for the simulated devices (docs/hardware.md §Fault injection).

A fault is armed on one device and fires on the commands that device receives:
- `timeout`:    the request is swallowed: not executed, no reply;
- `garbled`:    the request is executed but its reply is replaced by random non-ASCII bytes;
- `disconnect`: on a command that arrives while the device is moving (a dropped connection mid-move),
                the server closes the connection without replying.  A serial device stops (link
                loss is an emergency stop, unless its firmware lacks it: sim_devices/watchdog.py);
                an HTTP device keeps moving (HTTP has no standing link) until its watchdog sees
                the host silent;
- `stuck`:      motion commands are accepted but the actuator does not move (it stays "moving");
- `http_500`:   (HTTP devices) the request is not executed and gets HTTP 500.

`after_commands` commands pass untouched first; then the fault affects `count` commands (0 = every
command from then on).  For `disconnect` and `stuck` only the commands it can act on count
(commands while moving; motion commands)."""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

KINDS = ("timeout", "garbled", "disconnect", "stuck", "http_500")


@dataclass
class _Armed:
    kind: str
    after_commands: int
    count: int
    seen: int = 0       # commands counted since the fault was armed
    fired: int = 0

    def exhausted(self) -> bool:
        return self.count > 0 and self.fired >= self.count


class FaultInjector:
    """The armed faults of one device; thread-safe.  `log` records what fired, for tests."""

    def __init__(self, device: str, http: bool, seed: int = 0) -> None:
        self.device = device
        self.http = http
        self._lock = threading.Lock()
        self._armed: list[_Armed] = []
        self._rng = np.random.default_rng(seed)
        self.log: list[tuple[str, str]] = []   # (kind, request)

    def arm(self, kind: str, after_commands: int = 0, count: int = 1) -> None:
        if kind not in KINDS:
            raise ValueError(f"{self.device}: unknown fault kind {kind!r} (known: {', '.join(KINDS)})")
        if kind == "http_500" and not self.http:
            raise ValueError(f"{self.device}: http_500 needs an HTTP device; this one speaks the serial protocol")
        if after_commands < 0 or count < 0:
            raise ValueError(f"{self.device}: after_commands and count must be >= 0")
        with self._lock:
            self._armed.append(_Armed(kind, after_commands, count))

    def clear(self) -> None:
        with self._lock:
            self._armed.clear()

    def on_request(self, request: str, moving: bool, motion: bool) -> str | None:
        """Called for every request before it is executed: the fault to act out, or None.
        `moving`: the device is in motion; `motion`: the request starts a motion."""
        with self._lock:
            hit = None
            for f in self._armed:
                f.seen += 1
                if f.seen <= f.after_commands or f.exhausted() or hit is not None:
                    continue
                if f.kind == "disconnect" and not moving:
                    continue
                if f.kind == "stuck" and not motion:
                    continue
                f.fired += 1
                hit = f.kind
            if hit:
                self.log.append((hit, request))
            return hit

    def garble(self, reply: bytes) -> bytes:
        """Random bytes with the high bit set (never a newline), newline-terminated."""
        with self._lock:
            n = max(3, len(reply) - 1)
            junk = bytes(int(b) | 0x80 for b in self._rng.integers(0, 256, n))
        return junk + b"\n"
