"""The input-meaning section of `lab bench faults` (issue 22, item 8): its quick slice has no bad
case, covers every kind of case the issue lists, and a case that should be refused but is not is
reported bad (the section can fail)."""

from __future__ import annotations

from lab.cli import main
from lab.studies import bench_faults_inputs as section
from lab.studies.bench_faults import SECTIONS, campaign


def test_the_quick_slice_of_the_input_meaning_section_has_no_bad_case(tmp_path):
    assert "input-meaning" in SECTIONS
    report = campaign(quick=True, only=["input-meaning"], work=tmp_path, lab_main=main)
    assert report.bad == [], report.bad
    assert report.cases == report.ok >= 20


def test_every_kind_of_case_is_in_the_full_section(tmp_path):
    names = [c.name for c in section.cases(tmp_path, quick=False, lab_main=main)]
    for kind in ("calibration/rig check", "calibration/run borg", "calibration/the camera disagrees", "paths/",
                 "catalogue/runs show", "catalogue/lab runs with a FIFO", "catalogue/review", "journal/", "ctrl-c/"):
        assert any(kind in n for n in names), kind
    assert len(names) == len(set(names))


def test_a_case_that_is_not_refused_is_reported(tmp_path):
    # `lab rig check` on the default rig is valid: as a case that expects a refusal it must fail
    got = section._one_line(main, ["rig", "check", str(section.SIM_RIG)], "anything")
    assert got.startswith("exit 0")
    # and a journal that was not edited is used: the journal case says so
    assert section._journal_case(tmp_path, "untouched", lambda text: text, "x") == "the edited journal was used"
