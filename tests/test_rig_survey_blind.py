"""A run whose rig survey sees no turntable tag stops and says so, instead of going on with the rig
file's priors alone (an N = 7 run did: every module `uncertain` at a 1-sigma of ~21 mm, until iSAM2
stopped on an indeterminate system at module 90)."""

from __future__ import annotations

from procedures.build import build_procedure
from lab.core.recorder import RunRecorder
from procedures import rig_survey, runner


def test_a_run_whose_survey_sees_no_rim_tag_stops_naming_the_camera(tmp_path, monkeypatch):
    real = rig_survey.capture

    def blind(*a, **k):
        # the survey as taken, every sighting gone (a camera that does not look at the rim)
        return [rig_survey.CalibrationView(v.motion, ()) for v in real(*a, **k)]

    monkeypatch.setattr(rig_survey, "capture", blind)
    proc, bench, _ = build_procedure("borg", {"n": 3, "modules": 1, "speedup": 100.0})
    try:
        assert proc.rig_survey
        outcome = runner.run(proc, tmp_path / "r", info={}, operator_auto=True, show_progress=False,
                             recorder_factory=lambda p: RunRecorder(p, "borg", {}))
    finally:
        proc.close()
    assert outcome.result != "completed"
    assert "no turntable tag was seen" in outcome.reason and "platform_T_camera" in outcome.reason
    assert not proc.results                   # no module was measured against the priors alone


def test_no_rim_seen_only_when_no_view_saw_one():
    from estimation.rig_calibration_solve import CalibrationView
    from estimation.rig_model import ViewMotion

    m = ViewMotion(0.0, (0.0,) * 6)
    assert rig_survey.no_rim_seen([CalibrationView(m, ()), CalibrationView(m, ())]).startswith(
        "no turntable tag was seen in 2 views")
    assert rig_survey.no_rim_seen([CalibrationView(m, ()), CalibrationView(m, (object(),))]) is None
