"""The verdict names and their tally: the one spelling the estimator, the procedures, the log, the
runs catalogue and the review all read (what each name means: estimation/verification.py)."""

from __future__ import annotations

from typing import Iterable

OK = "ok"
FLAGGED = "flagged"
UNCERTAIN = "uncertain"
UNVERIFIED = "unverified"
# in the order a tally is printed
VERDICTS = (OK, FLAGGED, UNCERTAIN, UNVERIFIED)


def tally(verdicts: Iterable[str]) -> dict[str, int]:
    """How many of each verdict, every name present (0 where none), in VERDICTS order."""
    seen = list(verdicts)
    return {v: seen.count(v) for v in VERDICTS}

