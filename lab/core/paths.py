"""Output paths checked before anything runs: a command that will write a file or a directory at
its end (a calibration after a survey, a run's log) finds out first, in one line naming the flag
and the path, that it could not -- not after the devices have moved for half a minute.

The test is the one that matters: actually creating (and removing) a probe file where the output
will go.  Permission bits say too little (root passes every `access()` test, and `/proc` or a
read-only mount refuse anyway)."""

from __future__ import annotations

import os
from pathlib import Path

from lab.core.errors import UserError


def _probe(directory: Path, flag: str, path: Path) -> None:
    """Create and remove a file in `directory`: the writer will be able to do the same."""
    probe = directory / f".lab-probe-{os.getpid()}"
    try:
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    except OSError as exc:
        raise UserError(f"{flag} {path}: cannot write in {directory} ({exc.strerror or exc})") from None
    os.close(fd)
    try:
        probe.unlink()
    except OSError:
        pass


def _existing_ancestor(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_output_file(path: str | Path, flag: str, *, make_parents: bool = False) -> Path:
    """`path` can be written as a regular file: not a directory or a device, its folder an existing
    directory (or, with `make_parents`, one that can be made) that accepts a new file."""
    p = Path(path)
    if p.is_dir():
        raise UserError(f"{flag} {p}: is a directory; give a file name")
    if p.exists() and not p.is_file():
        raise UserError(f"{flag} {p}: is not a regular file")
    parent = p.parent if str(p.parent) else Path(".")
    if parent.exists() and not parent.is_dir():
        raise UserError(f"{flag} {p}: {parent} is a file, not a directory")
    if not parent.exists():
        if not make_parents:
            raise UserError(f"{flag} {p}: no such directory {parent}")
        check_output_dir(parent, flag)
        return p
    _probe(parent, flag, p)
    return p


def check_output_dir(path: str | Path, flag: str) -> Path:
    """`path` is, or can be made, a directory that accepts new files: neither it nor any existing
    parent is a file, and the nearest existing one is writable."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UserError(f"{flag} {p}: is a file, not a directory")
    base = _existing_ancestor(p)
    if not base.is_dir():
        raise UserError(f"{flag} {p}: {base} is a file, not a directory")
    _probe(base, flag, p)
    return p
