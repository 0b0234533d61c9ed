"""The small things of issue 12: --version, a help text that is not cut mid-sentence, suggestions for
mistyped commands, choices and flags, one-line errors for a bad --plot path and for end of input at
a prompt, and a calibration board page that is a real A4 sheet."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from lab.cli import DESCRIPTION, build_parser, main as lab_main
from test_calibrate import _rig_file, _SnapshotCamera



def _one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    with pytest.raises(SystemExit) as e:
        lab_main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        lab_main(["--version"])
    assert e.value.code == 0
    assert re.fullmatch(r"lab \(truss-lab\) \d+\.\d+\.\d+.*", capsys.readouterr().out.strip())


def test_help_says_whole_sentences() -> None:
    text = build_parser().format_help()
    assert DESCRIPTION.endswith(".") and " ".join(DESCRIPTION.split()) in " ".join(text.split())
    assert "exposes" not in text     # the old description was the docstring's first line, cut mid-sentence


@pytest.mark.parametrize("argv,prog,hint", [
    (["reveiw", "x.mcap"], "lab", "did you mean 'review'?"),
    (["run", "brog"], "lab run", "did you mean 'borg'?"),
    (["run", "borg", "--atuo"], "lab run borg", "did you mean --auto?"),
    (["run", "borg", "--on-flag", "contine"], "lab run borg", "did you mean 'continue'?"),
    (["structure", "borg", "--jsno"], "lab structure borg", "did you mean --json?"),
])
def test_a_mistyped_command_choice_or_flag_gets_a_suggestion_in_one_line(capsys, argv, prog, hint) -> None:
    line = _one_line_error(capsys, argv)
    assert line.startswith(f"{prog}: error: ") and hint in line and f"see `{prog} --help`" in line


def test_a_plot_into_a_missing_directory_is_one_line(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert lab_main(["structure", "borg", "--n", "2", "--plot", str(tmp_path / "nodir" / "x.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"lab: error: --plot {tmp_path / 'nodir' / 'x.png'}: no such directory {tmp_path / 'nodir'}"]


def test_end_of_input_at_a_calibration_prompt_is_one_line(lab, tmp_path: Path) -> None:
    blank = cv2.imencode(".png", np.full((720, 1280, 3), 110, np.uint8))[1].tobytes()
    cam = _SnapshotCamera([blank])
    try:
        rig = _rig_file(tmp_path, cam.url)
        r = lab(["calibrate", "camera", "--rig", str(rig), "--out", str(tmp_path / "c.json")], stdin=subprocess.DEVNULL,
                timeout=120)
    finally:
        cam.close()
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines() == [
        "lab: error: end of input while waiting for an answer; answer at a terminal, or use --auto where the "
        "command has it"]
    assert not (tmp_path / "c.json").exists()


def test_the_default_board_is_printed_on_an_a4_page(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "board.pdf"
    assert lab_main(["calibrate", "board", "--out", str(out)]) == 0
    assert "page 297 x 210 mm (A4 landscape)" in capsys.readouterr().out
    box = re.search(rb"MediaBox \[ *0 0 ([\d.]+) ([\d.]+) *\]", out.read_bytes())
    w_mm, h_mm = (float(v) / 72 * 25.4 for v in box.groups())
    assert abs(w_mm - 297) < 0.3 and abs(h_mm - 210) < 0.3
    assert lab_main(["calibrate", "board", "--out", str(tmp_path / "nodir" / "b.pdf")]) == 2


def test_a_run_keeps_the_files_it_was_given_by_their_absolute_path(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """run.json's params name the scenario, rig and calibration files absolutely, so that `lab resume`
    and `lab bench replay` read the same files from another directory; a path that names no file
    stays as typed (the run's own error names it)."""
    from lab.cli.run import _params

    monkeypatch.chdir(tmp_path)
    (tmp_path / "s.toml").write_text("seed = 1\n")
    (tmp_path / "cal.json").write_text("{}")
    args = build_parser().parse_args(["run", "borg", "--scenario", "s.toml", "--calibration", "cal.json",
                                      "--rig", "missing.toml", "--out", "runs/x"])
    params = _params(args)
    assert params["scenario"] == str(tmp_path / "s.toml") and params["calibration"] == str(tmp_path / "cal.json")
    assert params["rig"] == "missing.toml" and params["out"] == "runs/x"
