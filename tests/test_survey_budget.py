"""A step's survey target and view budget: one set of defaults and ranges for the rig file, the run
and the bench (lab/core/survey_budget.py)."""

from __future__ import annotations

import tomllib

import pytest

from lab.core.config import default_rig_path, parse_rig
from lab.core.errors import LabError
from lab.core.survey_budget import MAX_VIEWS, MAX_VIEWS_RANGE, SIGMA_TARGET_MM, SIGMA_TARGET_MM_MAX


def _rig(**verification):
    data = tomllib.loads(default_rig_path().read_text())
    data.setdefault("verification", {}).update(verification)
    return parse_rig(data, source="rig.toml", base_dir=default_rig_path().parent)


def test_the_rig_file_takes_the_defaults_and_the_ranges():
    ver = _rig().verification
    assert ver.sigma_target_m == pytest.approx(SIGMA_TARGET_MM * 1e-3) and ver.max_views == MAX_VIEWS
    lo, hi = MAX_VIEWS_RANGE
    assert _rig(max_views=lo).verification.max_views == lo and _rig(max_views=hi).verification.max_views == hi
    assert _rig(sigma_target_mm=SIGMA_TARGET_MM_MAX).verification.sigma_target_m == pytest.approx(SIGMA_TARGET_MM_MAX * 1e-3)
    for bad in ({"max_views": lo - 1}, {"max_views": hi + 1}, {"sigma_target_mm": SIGMA_TARGET_MM_MAX * 1.01}):
        with pytest.raises(LabError, match=next(iter(bad))):
            _rig(**bad)


@pytest.mark.parametrize("flag,value", [("--max-views", str(MAX_VIEWS_RANGE[1] + 1)), ("--max-views", "0"),
                                        ("--sigma-target-mm", "0"), ("--sigma-target-mm", "nan")])
def test_a_run_and_the_bench_refuse_the_same_values_in_the_same_words(lab, flag, value):
    run = lab(["run", "borg", flag, value, "--dry-run"])
    bench = lab(["bench", "slam", "--only", "precision", flag, value])
    assert run.returncode == bench.returncode == 2, (run.stderr, bench.stderr)
    assert run.stderr.strip().splitlines()[-1] == bench.stderr.strip().splitlines()[-1]
    assert flag in run.stderr


def test_the_smallest_budget_is_a_run_the_bench_can_plan():
    """The bench used to refuse budgets under 3 (its three coverage views); like a run's planner it
    takes the coverage views whatever the budget, so one view per step still plans and verifies."""
    from dataclasses import replace

    from lab.studies import bench_precision as bp

    out = bp.study(1, 0, replace(bp.PrecisionSetup(), max_views=MAX_VIEWS_RANGE[0]), ([0.0], []), "budget")
    assert out["good"]["checks"] > 0 and out["good"]["views_median"] >= 1
