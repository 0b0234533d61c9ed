"""Exclusive ownership across processes: an OS file lock (`fcntl.flock`) per owned thing — a device
(keyed by its port) or a run directory.

Why flock: the kernel drops the lock when the holder dies, however it dies (SIGKILL, power cut of
the process), so a stale lock can never keep a bench busy, and no clean-up code has to run.  The
lock file holds a one-line JSON note of who holds it (pid, command, run directory), so a refused
second run can say which run is in its way.

Device locks live in a per-user runtime directory (`$LAB_RUNTIME_DIR`, else `$XDG_RUNTIME_DIR/lab`,
else `/tmp/lab-<uid>`); a run directory's lock is the file `.lock` inside it."""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lab.errors import UserError

_holder: dict[str, Any] = {}


class Busy(UserError):
    """Someone else holds the lock: the message names the thing and the holder."""

    def __init__(self, what: str, holder: dict[str, Any]) -> None:
        self.what = what
        self.holder = holder
        super().__init__(f"{what} is in use by {describe_holder(holder)}; nothing was moved or stopped")


def set_holder(**info: Any) -> None:
    """What this process is (e.g. run="runs/demo"), written into every lock it takes from now on."""
    _holder.update({k: v for k, v in info.items() if v is not None})


def holder_info() -> dict[str, Any]:
    return {"pid": os.getpid(), "cmd": " ".join(os.path.basename(a) if i == 0 else a for i, a in enumerate(sys.argv)),
            **_holder}


def describe_holder(holder: dict[str, Any]) -> str:
    if not holder:
        return "another process (it left no note)"
    parts = [f"pid {holder.get('pid', '?')}"]
    if holder.get("run"):
        parts.append(f"run {holder['run']}")
    if holder.get("cmd"):
        parts.append(f"`{holder['cmd']}`")
    return ", ".join(parts)


def runtime_dir() -> Path:
    """The per-user directory for device locks (created 0700)."""
    base = os.environ.get("LAB_RUNTIME_DIR")
    if base:
        d = Path(base)
    elif os.environ.get("XDG_RUNTIME_DIR") and os.access(os.environ["XDG_RUNTIME_DIR"], os.W_OK):
        d = Path(os.environ["XDG_RUNTIME_DIR"]) / "lab"
    else:
        d = Path(tempfile.gettempdir()) / f"lab-{os.getuid()}"
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    return d


def device_lock_path(key: str) -> Path:
    """The lock file of a device key (a port URL): readable prefix + hash, so it is unique and legal."""
    safe = "".join(c if c.isalnum() else "_" for c in key)[:60]
    digest = hashlib.sha256(key.encode()).hexdigest()[:12]
    return runtime_dir() / f"{safe}-{digest}.lock"


@dataclass
class FileLock:
    path: Path
    what: str
    fd: int = -1

    def acquire(self) -> FileLock:
        """Take the lock now or raise `Busy` naming the holder (never waits)."""
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_note(fd)
            os.close(fd)
            raise Busy(self.what, holder) from None
        except OSError:
            os.close(fd)
            raise
        note = (json.dumps({"what": self.what, **holder_info()}) + "\n").encode()
        os.ftruncate(fd, 0)
        os.pwrite(fd, note, 0)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd >= 0:
            try:
                os.ftruncate(self.fd, 0)   # no note: nobody holds it
                fcntl.flock(self.fd, fcntl.LOCK_UN)
            finally:
                os.close(self.fd)
                self.fd = -1

    @property
    def held(self) -> bool:
        return self.fd >= 0

    def __enter__(self) -> FileLock:
        return self.acquire() if not self.held else self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _read_note(fd: int) -> dict[str, Any]:
    try:
        raw = os.pread(fd, 4096, 0).decode("utf-8", errors="replace").strip()
        value = json.loads(raw) if raw else {}
        return value if isinstance(value, dict) else {}
    except (OSError, ValueError):
        return {}


def read_holder(path: Path) -> dict[str, Any]:
    """Who holds a lock file now ({} if nobody or unknown)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return {}
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _read_note(fd)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return {}
    finally:
        os.close(fd)
