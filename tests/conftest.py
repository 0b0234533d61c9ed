"""Shared test fixtures."""

from __future__ import annotations

import signal
from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True)
def python_signal_handlers() -> Iterator[None]:
    """Every test starts with Python's own SIGINT and SIGTERM handling.  A `lab` command run in this
    process owns its process's handlers (`lab run` ignores a late Ctrl-C once its run is closed,
    until it exits); left ignored, SIGINT stays ignored in every subprocess a later test starts, and
    a `lab sim`, a viewer or a study under test no longer stops on Ctrl-C."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    yield
