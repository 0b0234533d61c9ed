"""One owner per device across processes.

`claim(device, url)` takes an OS lock keyed by the device's port (`transport.port_key`: an HTTP
server is one device whatever the path; a serial URL is its path).  A second process asking for
the same port gets `DeviceBusy` naming the device and the run that holds it, before it has sent
a single byte, so it can neither move nor stop what another run is driving.  Within one process
claims are counted, so several driver objects on one port share the claim.  The kernel drops the
lock when the owning process dies, however it dies."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from drivers.transport import port_key
from lab.locks import Busy, FileLock, device_lock_path

_guard = threading.Lock()
_held: dict[str, tuple[FileLock, int]] = {}


class DeviceBusy(Busy):
    """A device owned by another process."""


def claim(device: str, url: str) -> str:
    """Own the device at `url` for this process (counted); returns the key to `release`."""
    key = port_key(url)
    with _guard:
        if key in _held:
            lock, n = _held[key]
            _held[key] = (lock, n + 1)
            return key
        lock = FileLock(device_lock_path(key), f"device {device} ({key})")
        try:
            lock.acquire()
        except Busy as exc:
            raise DeviceBusy(exc.what, exc.holder) from None
        _held[key] = (lock, 1)
        return key


def release(key: str) -> None:
    with _guard:
        if key not in _held:
            return
        lock, n = _held[key]
        if n > 1:
            _held[key] = (lock, n - 1)
            return
        del _held[key]
        lock.release()


def held_keys() -> list[str]:
    with _guard:
        return sorted(_held)


@dataclass
class Claims:
    """The claims of one rig's devices, released together."""

    keys: list[str] = field(default_factory=list)

    def take(self, device: str, url: str) -> None:
        self.keys.append(claim(device, url))

    def release_all(self) -> None:
        while self.keys:
            release(self.keys.pop())
