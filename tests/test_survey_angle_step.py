"""The rig survey's turntable step grows finer with the turntable: a step of one rim-tag spacing
shows every view the rim in the same place, which leaves the Stewart base's rotation unseen once
a view holds a single rim tag (docs/calibration.md, "A bigger turntable: finer steps")."""

from __future__ import annotations

import math

import pytest

from lab.core.structures.borg import build_borg
from procedures.rig_survey import ANGLE_STEP_RAD, survey_angle_step


@pytest.mark.parametrize("n, deg", [(2, 30.0), (3, 30.0), (4, 15.0), (6, 15.0), (7, 10.0), (8, 10.0), (10, 7.5)])
def test_the_step_for_each_size(n, deg):
    assert math.degrees(survey_angle_step(build_borg(n).turntable.radius_m)) == pytest.approx(deg)


def test_the_step_divides_the_tag_spacing_and_keeps_the_3x3x3_arc():
    arc = build_borg(3).turntable.radius_m * ANGLE_STEP_RAD
    for n in range(2, 11):
        r = build_borg(n).turntable.radius_m
        step = survey_angle_step(r)
        assert (30.0 / math.degrees(step)) == pytest.approx(round(30.0 / math.degrees(step)))
        assert r * step <= arc * (1 + 1e-9)
        # and no coarser divisor would do
        coarser = [d for d in (30.0, 15.0, 10.0, 7.5, 6.0) if d > math.degrees(step) + 1e-9]
        assert all(r * math.radians(d) > arc for d in coarser)


def _survey_angles(n: int | None, tmp_path) -> list[float]:
    from procedures.calibrate_rig import RigCalibrationProcedure
    from procedures.setup import open_bench

    bench = open_bench(None, None, speedup=100, borg_n=n)
    try:
        proc = RigCalibrationProcedure(bench, tmp_path / "rig_calibration.json", borg_n=n)
        return sorted({v.turntable_rad for v in proc.survey_plan.views})
    finally:
        bench.close()


def test_calibrate_rig_surveys_the_turntable_of_its_size(lab, tmp_path):
    rc, out, err = lab.main("calibrate", "rig", "--n", "11", "--dry-run")
    assert rc == 2 and "--n 11" in err and len(err.strip().splitlines()) == 1
    for n, deg in ((None, 30.0), (5, 15.0)):
        angles = _survey_angles(n, tmp_path)
        steps = {round(math.degrees(b - a), 6) for a, b in zip(angles, angles[1:])}
        assert steps == {deg}, (n, steps)
