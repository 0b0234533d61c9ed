"""The CI slice of `lab bench faults`: device faults, bad input and protocol abuse (the kill,
signal and sharing sections run subprocess runs and are in the full campaign and in
tests/test_reliability_runs.py)."""

from __future__ import annotations

from lab.cli import main
from lab.studies.bench_faults import campaign


def test_the_quick_slice_of_the_fault_campaign_has_no_bad_case(tmp_path):
    report = campaign(quick=True, only=["devices", "inputs", "protocol"], work=tmp_path, lab_main=main)
    assert report.cases >= 25
    assert report.bad == [], report.bad
    assert report.ok == report.cases
