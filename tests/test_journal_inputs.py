"""A study's journal is read like any input (issue 22, item 7): a NaN typed into trials.jsonl, or
any value changed since the study wrote it, is refused in one line naming the file, the line and
the trial -- not drawn into the study's tables and figures with exit 0."""

from __future__ import annotations

import argparse
import io
import json
from contextlib import redirect_stderr, redirect_stdout

import pytest

from lab.core.errors import UserError
from lab.core.executor import Journal, make_trials
from lab.core.executor.journal import finite_values
from lab.studies.bench_common import run_trial_study


def double(trial):                      # a study's trial function (module level: workers import it)
    return {"value": 2.0 * trial.spec, "none": None}


def _study(tmp_path, *, json_out: bool = True) -> tuple[int, str]:
    args = argparse.Namespace(out=str(tmp_path), json=json_out, workers=1, scheduler=None, speedup=1.0)
    so = io.StringIO()
    with redirect_stdout(so), redirect_stderr(io.StringIO()):
        rc = run_trial_study(args, "demo", make_trials(0, "t", [1, 2, 3]), double, {"x": 1},
                             lambda ts: [{"sum": sum(t["value"] for t in ts)}], lambda r: str(r), lambda r: "")
    return rc, so.getvalue()


def _interrupted_journal(tmp_path) -> Journal:
    """The journal an interrupted run of the demo study leaves: two trials finished."""
    j = Journal(tmp_path / "trials.jsonl", {"bench": "demo", "x": 1, "speedup": 1.0})
    j.append("t/0", {"value": 2.0, "none": None})
    j.append("t/1", {"value": 4.0, "none": None})
    j.close()
    return j


def test_a_resumed_study_uses_its_journal(tmp_path):
    _interrupted_journal(tmp_path)
    rc, out = _study(tmp_path)
    assert rc == 0 and json.loads(out)["rows"] == [{"sum": 12.0}]


@pytest.mark.parametrize("edit", ['"value": NaN', '"value": Infinity', '"value": 5.0'])
def test_an_edited_journal_line_is_refused_naming_it(tmp_path, edit):
    j = _interrupted_journal(tmp_path)
    text = j.path.read_text().replace('"value": 4.0', edit, 1)
    j.path.write_text(text)
    with pytest.raises(UserError, match=r"trials.jsonl line 3 \(trial t/1\): not what the study wrote"):
        _study(tmp_path)
    assert j.path.exists()                      # refused, not set aside: the user decides


def test_a_nan_with_a_matching_checksum_is_still_not_a_result(tmp_path):
    """Values checked too: a line rewritten whole, checksum and all, must still be a result."""
    from lab.core.executor.journal import _line

    j = _interrupted_journal(tmp_path)
    lines = j.path.read_text().splitlines()
    lines[2] = _line("t/1", {"value": float("nan"), "none": None}).strip()
    j.path.write_text("\n".join(lines) + "\n")
    with pytest.raises(UserError, match=r"line 3 \(trial t/1\): result.value is nan"):
        _study(tmp_path)


def test_a_journal_without_checksums_is_set_aside(tmp_path, capsys):
    path = tmp_path / "trials.jsonl"
    path.write_text(json.dumps({"study": {"s": 1}}) + "\n" + json.dumps({"key": "k", "result": float("nan")}) + "\n")
    assert Journal(path, {"s": 1}).finished() == {}
    assert "another version" in capsys.readouterr().err


def test_finite_values_names_the_path():
    assert finite_values({"a": [1.0, {"b": float("inf")}]}) == "result.a[1].b is inf"
    assert finite_values({"a": None, "b": [1, 2.5]}) is None
