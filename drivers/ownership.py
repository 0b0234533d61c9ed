"""One owner per physical device across every process of every user on the machine.

`claim(device, url)` takes an OS lock per key of what the device is (drivers/device_identity.py:
a serial port's character device, a network endpoint's resolved addresses and port), in the
machine-wide lock directory (lab/core/locks.py).  A second process asking for the same device, however
it spells it (`localhost`, `127.1`, a `/dev/serial/by-id/...` link) and whatever its environment,
gets `DeviceBusy` naming the device and the run that holds it, before it has sent a single byte,
so it can neither move nor stop what another run is driving.  Within one process claims are
counted, so several driver objects on one device share the claim.  The kernel drops the lock when
the owning process dies, however it dies."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from drivers.device_identity import identify
from lab.core.locks import Busy, FileLock, describe_holder, device_lock_path

_guard = threading.Lock()
_held: dict[str, tuple[FileLock, int]] = {}


class DeviceBusy(Busy):
    """A device owned by another process."""

    def __init__(self, what: str, holder: dict) -> None:
        super().__init__(what, holder)
        theirs = holder.get("what")
        if isinstance(theirs, str) and theirs and theirs != what:   # the holder spelled it otherwise
            self.args = (f"{what} is in use by {describe_holder(holder)}, which holds it as {theirs}; "
                         f"nothing was moved or stopped",)


def claim(device: str, url: str) -> list[str]:
    """Own the device at `url` for this process (counted); returns the keys to `release`."""
    ident = identify(url)
    what = f"device {device} ({url}" + (f": {ident.label})" if ident.label != url else ")")
    taken: list[str] = []
    with _guard:
        try:
            for key in ident.keys:
                if key in _held:
                    lock, n = _held[key]
                    _held[key] = (lock, n + 1)
                else:
                    lock = FileLock(device_lock_path(key), what, shared=True)
                    try:
                        lock.acquire()
                    except Busy as exc:
                        raise DeviceBusy(exc.what, exc.holder) from None
                    _held[key] = (lock, 1)
                taken.append(key)
        except BaseException:
            for key in taken:
                _release(key)
            raise
    return taken


def release(key: str) -> None:
    with _guard:
        _release(key)


def _release(key: str) -> None:
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
        self.keys.extend(claim(device, url))

    def release_all(self) -> None:
        while self.keys:
            release(self.keys.pop())
