"""Exclusive ownership across processes: an OS file lock (`fcntl.flock`) per owned thing — a device
(keyed by what it is, drivers/device_identity.py) or a run directory.

Why flock: the kernel drops the lock when the holder dies, however it dies (SIGKILL, power cut of
the process), so a stale lock can never keep a bench busy, and no clean-up code has to run.  The
lock file holds a one-line JSON note of who holds it (pid, user, command, run directory), so a
refused second run can say which run is in its way.

Device locks live in ONE machine-wide directory, the same for every process of every user whatever
its environment (`device_lock_dir`): `/run/lock/lab` when `/run/lock` is the world-writable sticky
directory the FHS keeps for device lock files (Debian, Ubuntu and most systemd machines), else
`/tmp/lab-locks`.  The choice depends only on `/run/lock`'s mode bits, which every user sees alike,
never on `$TMPDIR`, `$XDG_RUNTIME_DIR` or who is asking: a cron job, a second terminal or a second
user that picked another directory would not see the first run's lock and would move its devices.
`/run/lock` is preferred to `/tmp` because services may get a private `/tmp` (systemd's PrivateTmp)
but never a private `/run/lock`.  There is deliberately no environment override: tests keep apart
by using different devices (free ports), not different lock directories.  The directory is mode
1777 (anyone may add a lock, nobody may delete another's) and every device lock file is created
mode 0666, so another user can open and flock it; it is opened with O_NOFOLLOW, so a symlink
planted there cannot redirect it.

A run directory's lock is the file `.lock` inside it (mode 0600, the run's owner's business)."""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import stat
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lab.core.errors import UserError

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
    return {"pid": os.getpid(), "user": _user(os.getuid()),
            "cmd": " ".join(os.path.basename(a) if i == 0 else a for i, a in enumerate(sys.argv)), **_holder}


def _user(uid: int) -> str:
    try:
        import pwd

        return pwd.getpwuid(uid).pw_name
    except (ImportError, KeyError):
        return str(uid)


def describe_holder(holder: dict[str, Any]) -> str:
    if not holder:
        return "another process (it left no note)"
    parts = [f"pid {holder.get('pid', '?')}"]
    if holder.get("user") and holder["user"] != _user(os.getuid()):
        parts[0] += f" of user {holder['user']}"
    if holder.get("run"):
        parts.append(f"run {holder['run']}")
    if holder.get("cmd"):
        parts.append(f"`{holder['cmd']}`")
    return ", ".join(parts)


RUN_LOCK = Path("/run/lock")                 # the FHS's machine-wide lock directory
FALLBACK_LOCK_DIR = Path("/tmp/lab-locks")   # a fixed path: never $TMPDIR, which differs per environment


def device_lock_dir() -> Path:
    """The machine-wide directory of device locks (created mode 1777 if missing); a one-line
    UserError if it cannot be used."""
    d = RUN_LOCK / "lab" if _sticky_world_writable(RUN_LOCK) else FALLBACK_LOCK_DIR
    for _ in range(50):
        try:
            try:
                os.mkdir(d, 0o1777)
                os.chmod(d, 0o1777)      # mkdir's mode is cut by the umask
            except FileExistsError:
                pass
            st = os.lstat(d)
        except OSError as exc:
            raise UserError(f"device lock directory {d}: cannot create it: {exc.strerror or exc}") from None
        if not stat.S_ISDIR(st.st_mode):
            raise UserError(f"device lock directory {d} is not a directory (a symlink or file is in its place); "
                            f"remove it so that every run shares one lock directory")
        if stat.S_IMODE(st.st_mode) == 0o1777 or os.access(d, os.W_OK | os.X_OK):
            if stat.S_IMODE(st.st_mode) != 0o1777 and st.st_uid == os.getuid():
                os.chmod(d, 0o1777)  # ours but narrowed (its creator died between mkdir and chmod)
            return d
        time.sleep(0.01)   # another user's process may be between its mkdir and its chmod
    raise UserError(f"device lock directory {d} is not writable by this user (mode {stat.S_IMODE(st.st_mode):o}, "
                    f"owner uid {st.st_uid}); its owner should `chmod 1777 {d}`")


def _sticky_world_writable(d: Path) -> bool:
    try:
        st = os.stat(d)
    except OSError:
        return False
    return stat.S_ISDIR(st.st_mode) and (st.st_mode & 0o1777) == 0o1777


def device_lock_path(key: str) -> Path:
    """The lock file of a device key (drivers/device_identity.py): readable prefix + hash, so it is
    unique and a legal file name."""
    safe = "".join(c if c.isalnum() else "_" for c in key)[:60]
    digest = hashlib.sha256(key.encode()).hexdigest()[:12]
    return device_lock_dir() / f"{safe}-{digest}.lock"


@dataclass
class FileLock:
    path: Path
    what: str
    fd: int = -1
    shared: bool = False     # a device lock in the machine-wide directory: any user may flock the file

    def _open(self) -> int:
        if not self.shared:
            return os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        flags = os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC
        try:
            fd = os.open(self.path, os.O_RDWR | flags, 0o666)
        except PermissionError:
            # another user's file we may not write (its mode narrowed by hand, or its creator died
            # before its fchmod): flock works on a read-only descriptor too; only our note is lost
            fd = os.open(self.path, os.O_RDONLY | flags, 0o666)
        try:
            if os.fstat(fd).st_uid == os.getuid():
                os.fchmod(fd, 0o666)     # the umask cut the creation mode
        except OSError:
            pass
        return fd

    def acquire(self) -> FileLock:
        """Take the lock now or raise `Busy` naming the holder (never waits)."""
        while True:
            try:
                fd = self._open()
            except OSError as exc:
                if not self.shared:
                    raise
                raise UserError(f"{self.what}: cannot open its lock file {self.path}: {exc.strerror or exc}") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _read_note(fd)
                os.close(fd)
                raise Busy(self.what, holder) from None
            except OSError:
                os.close(fd)
                raise
            # The holder before us may have deleted the file as it let go (release unlinks it):
            # then we locked an orphan inode, and must lock the file now at the path instead.
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        note = (json.dumps({"what": self.what, **holder_info()}) + "\n").encode()
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, note, 0)
        except OSError:
            pass   # a read-only descriptor (see _open): locked all the same, without a note
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd >= 0:
            try:
                # unlink while still holding it, so lock files do not pile up; a process that
                # opened the old file meanwhile notices (acquire's inode check) and retries
                try:
                    os.unlink(self.path)
                except OSError:
                    pass
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
