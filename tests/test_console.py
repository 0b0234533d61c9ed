"""The console tells the story as it happens: with output redirected (not a terminal) a run prints
one plain line per step and no progress bars; each module's verdict row when it is decided;
warnings (device retries, rejected tags, re-measures) when they occur; tables with a legend."""

from __future__ import annotations

import io
import re
import subprocess
from pathlib import Path

from lab.core.imaging import IDEAL, scenario_tables
from procedures.console import Console, ConsoleRecorder, borg_table, sigma_target_line


SCENARIO = """seed = 3
[[borg.fault]]
kind = "partial_deploy"        # 2D comes out short: flagged, re-deployed, measured again
module = "2D"
height_m = 0.30
[[borg.fault]]
kind = "tag_displaced"         # tag 6 knocked off: rejected
tag = 6
offset_m = [0.0, 0.3, 0.0]
[[device.fault]]
device = "camera"              # one HTTP 500 on a frame: retried
kind = "http_500"
after_commands = 3
count = 1

""" + scenario_tables(IDEAL)   # the ideal camera: this file is about what the console prints (a first
# module read on the realistic camera without a survey is `uncertain`, 1-sigma 2.4 mm, and takes more views)


def _run_redirected(lab, args: list[str], out_file: Path) -> int:
    with open(out_file, "w") as f:   # stdout and stderr both a file: not a terminal
        return lab(args, stdout=f, stderr=subprocess.STDOUT, timeout=600).returncode


def test_a_redirected_borg_run_prints_steps_verdicts_and_warnings_as_they_happen(lab, tmp_path: Path, run_dir: Path) -> None:
    sc = tmp_path / "sc.toml"
    sc.write_text(SCENARIO)
    out = tmp_path / "out.txt"
    rc = _run_redirected(lab, ["run", "borg", "--auto", "--no-rig-survey", "--modules", "4", "--on-flag", "retry",
                               "--speedup", "40", "--scenario", str(sc), "--out", str(run_dir)], out)
    text = out.read_text()
    lines = text.splitlines()
    assert rc in (0, 3), text
    assert "\r" not in text and "%|" not in text and "\x1b[" not in text   # no progress bars
    steps = [ln for ln in lines if re.match(r"^step \d/4 module ", ln)]
    assert [s.split()[-1] for s in steps] == ["1P", "2D", "3D", "4D"]
    table_at = max(i for i, ln in enumerate(lines) if ln.startswith("module  verdict"))
    live = lines[:table_at]
    # 2D's first verdict, flagged, is printed in its step, before the next step starts
    first_2d = next(i for i, ln in enumerate(live) if ln.startswith("2D ") and "flagged" in ln)
    assert lines.index(steps[1]) < first_2d < lines.index(steps[2])
    assert "not fully deployed" in live[first_2d]
    assert any(ln.startswith("warning: camera: retry 1/") for ln in live)
    assert any(ln.startswith("warning: module 2D re-deployed") for ln in live)
    assert any(ln.startswith("warning: tag 6 rejected as displaced") for ln in live)
    # the final table: deviation (mm, deg), tolerance, 1 sigma, truth error, and its legend
    header = lines[table_at]
    for column in ("dev mm", "dev deg", "tol mm/deg", "1σ mm", "err mm", "err deg"):
        assert column in header
    assert re.match(r"^1P\s+ok\s+\d+\.\d\d\s+\d+\.\d{3}\s+5/1\s+\d+\.\d\d", lines[table_at + 1])
    assert any(ln.startswith("dev: measured distance from the design") for ln in lines[table_at:])
    # what the run's 1-sigma came to against the target its views were planned for
    assert any(re.match(r"^1σ target 0\.25 mm: reached by \d+ of \d+ measured modules \(1σ median", ln)
               for ln in lines[table_at:])
    assert len(lines) < 40


def test_the_table_says_how_many_modules_reached_the_planned_1_sigma() -> None:
    def mod(name, sigma, predicted):
        return {"name": name, "verdict": "ok", "sigma_position_m": sigma, "predicted_sigma_m": predicted}

    summary = {"sigma_target_m": 0.00025, "rejected_tags": [],
               "modules": [mod("1P", 0.0002, 0.00021), mod("2D", 0.00033, 0.00024), mod("3D", 0.00041, 0.00022),
                           {"name": "4S", "verdict": "unverified"}]}
    line = sigma_target_line(summary)
    assert line == ("1σ target 0.25 mm: reached by 1 of 3 measured modules (1σ median 0.33 mm, largest 0.41 mm; "
                    "the plans predicted 0.22 mm median)")
    assert line in borg_table(summary).splitlines()
    assert sigma_target_line({k: v for k, v in summary.items() if k != "sigma_target_m"}) is None   # older runs
    assert sigma_target_line({"sigma_target_m": 0.00025, "modules": [{"name": "4S", "verdict": "unverified"}]}) is None


def test_a_redirected_truss_run_prints_a_line_per_step_and_explains_its_table(lab, tmp_path: Path, run_dir: Path) -> None:
    out = tmp_path / "out.txt"
    rc = _run_redirected(lab, ["run", "truss", "tetrahelix:6", "--auto", "--speedup", "40",
                               "--out", str(run_dir)], out)
    text = out.read_text()
    assert rc == 0, text
    assert "\r" not in text and "%|" not in text
    lines = text.splitlines()
    steps = [ln for ln in lines if re.match(r"^step \d+/\d+ ", ln)]
    assert steps and len(steps) == int(steps[0].split()[1].split("/")[1])
    assert any(ln.startswith("error: the built node's distance from its design position") for ln in lines)


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_bars_only_on_a_terminal_and_warnings_from_the_log() -> None:
    assert Console(True, out=io.StringIO(), err=_Tty()).bars
    assert not Console(True, out=io.StringIO(), err=io.StringIO()).bars
    assert Console(True, out=io.StringIO(), err=io.StringIO()).plain_steps
    assert not Console(False, out=io.StringIO(), err=io.StringIO()).plain_steps      # --quiet

    out = io.StringIO()
    console = Console(True, out=out, err=io.StringIO())
    logged = []

    class Rec:
        def log_text(self, level, text, t_s=None):
            logged.append((level, text))

        step_indices_ended = {0}

    rec = ConsoleRecorder(Rec(), console)
    rec.log_text("info", "quiet detail")
    rec.log_text("warning", "rig calibration: mount z poorly determined")
    console.step(2, 10, "module 3D")
    assert rec.step_indices_ended == {0}             # everything else reaches the recorder itself
    assert logged == [("info", "quiet detail"), ("warning", "rig calibration: mount z poorly determined")]
    assert out.getvalue().splitlines() == ["warning: rig calibration: mount z poorly determined",
                                           "step  3/10 module 3D"]
