"""Reading the user's files: every way a read can fail becomes one line naming the file and what it
was meant to be (a missing file, a directory, no permission, not UTF-8, not JSON or TOML), never a
traceback.  Each loader then checks its own keys."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

from lab.core.errors import UserError


def read_text(path: str | Path, what: str, error: type[UserError] = UserError) -> str:
    """The file's text; `what` names it in the error ("camera calibration", "scenario")."""
    p = Path(path)
    try:
        return p.read_text()
    except FileNotFoundError:
        raise error(f"{what} {p}: no such file") from None
    except UnicodeDecodeError:
        raise error(f"{what} {p}: not a text file (not UTF-8)") from None
    except OSError as exc:
        raise error(f"{what} {p}: cannot read it: {exc.strerror or exc}") from None


def read_json(path: str | Path, what: str, error: type[UserError] = UserError) -> Any:
    text = read_text(path, what, error)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"{what} {path}: not valid JSON: {exc}") from None


def read_toml(path: str | Path, what: str, error: type[UserError] = UserError) -> dict[str, Any]:
    text = read_text(path, what, error)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{what} {path}: not valid TOML: {exc}") from None
