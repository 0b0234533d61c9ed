"""A step's survey: the module 1-sigma its views are planned to reach and its view budget.  The
defaults and the ranges accepted by a rig file's `[verification]` table, `lab run borg
--sigma-target-mm / --max-views` and `lab bench slam`, stated once.  Light on purpose (no numpy):
the CLI's help text reads it."""

from __future__ import annotations

import math

from lab.core.errors import UserError

# at 0.25 mm a module 1 mm past a 5 mm tolerance (or 2 mm past 1 mm) is 4 sigma clear of it
SIGMA_TARGET_MM = 0.25
SIGMA_TARGET_MM_MAX = 100.0       # beyond it no survey is planned for accuracy at all
# views per step, the coverage views included (those are taken whatever the budget: a module is
# seen from two turntable angles before any accuracy is aimed at)
MAX_VIEWS = 12
MAX_VIEWS_RANGE = (1, 200)


def check_sigma_target_mm(value: float, name: str = "--sigma-target-mm") -> float:
    if not (math.isfinite(value) and 0 < value <= SIGMA_TARGET_MM_MAX):
        raise UserError(f"{name} must be in (0, {SIGMA_TARGET_MM_MAX:g}] mm, got {value}")
    return float(value)


def check_max_views(value: int, name: str = "--max-views") -> int:
    lo, hi = MAX_VIEWS_RANGE
    if not lo <= value <= hi:
        raise UserError(f"{name} must be in {lo}..{hi}, got {value}")
    return int(value)
