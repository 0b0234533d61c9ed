"""Every output path and value of a command is checked before the first motion (issue 22, item 4):
`lab calibrate rig --out` / `--run-dir` that cannot be written, under a file or under /proc, and a
`--speedup` the simulated devices cannot do, are one line and exit 2 within a second or two,
before the bench moves and without leaving a run directory."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from lab.core.config import load_rig
from lab.core.errors import UserError
from lab.core.paths import check_output_dir, check_output_file
from procedures.setup import min_speedup

SURVEY = ["calibrate", "rig", "--auto", "--quiet", "--speedup", "100", "--angle-step-deg", "90"]


def _run(lab, *argv: str) -> tuple[int, str, str, float]:
    """`lab.main` and how long it took: a refusal must come before the bench moves, within seconds."""
    t0 = time.monotonic()
    rc, out, err = lab.main(*argv)
    return rc, out, err, time.monotonic() - t0


@pytest.fixture
def afile(tmp_path) -> Path:
    f = tmp_path / "f"
    f.write_text("x")
    return f


@pytest.mark.parametrize("case", ["out under a file", "out under /proc", "out in a missing folder", "run-dir a file",
                                  "run-dir under /proc", "run-dir under a file"])
def test_calibrate_rig_paths_refused_before_the_survey(lab, tmp_path, afile, case):
    args = {"out under a file": ["--out", str(afile / "c.json")],
            "out under /proc": ["--out", "/proc/c.json"],
            "out in a missing folder": ["--out", str(tmp_path / "nope" / "c.json")],
            "run-dir a file": ["--out", str(tmp_path / "c.json"), "--run-dir", str(afile)],
            "run-dir under /proc": ["--out", str(tmp_path / "c.json"), "--run-dir", "/proc/lab-run"],
            "run-dir under a file": ["--out", str(tmp_path / "c.json"), "--run-dir", str(afile / "run")]}[case]
    before = set(tmp_path.iterdir())
    rc, out, err, dt = _run(lab, *SURVEY, *args)
    assert rc == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert ("--out" in err) if "out " in case else ("--run-dir" in err)
    assert dt < 10                     # the survey takes 20-30 s at this speed: it never started
    assert set(tmp_path.iterdir()) == before


@pytest.mark.parametrize("argv", [["calibrate", "board", "--out", "/proc/b.png"],
                                  ["calibrate", "camera", "--sim", "3", "--out", "/proc/c.json"],
                                  ["calibrate", "camera", "--sim", "3", "--out", "X/c.json"],
                                  ["calibrate", "camera", "--sim", "3", "--out", "c.json", "--record", "/proc/r.mcap"]])
def test_other_outputs_refused_in_one_line(lab, tmp_path, afile, argv):
    argv = [a.replace("X", str(afile)) for a in argv]
    argv = [str(tmp_path / a) if a == "c.json" else a for a in argv]
    rc, out, err, _ = _run(lab, *argv)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err


@pytest.mark.parametrize("argv", [["run", "borg", "--auto", "--quiet", "--modules", "1"],
                                  ["calibrate", "rig", "--auto", "--quiet"]])
def test_a_speedup_the_devices_cannot_do_is_refused_before_the_run(lab, tmp_path, argv):
    out = tmp_path / "run"
    flag = "--out" if argv[0] == "run" else "--run-dir"
    rc, _, err, dt = _run(lab, *argv, "--speedup", "1e-9", flag, str(out), *(["--out", str(tmp_path / "c.json")]
                                                                              if argv[0] == "calibrate" else []))
    assert rc == 2 and "--speedup 1e-09" in err and "slowest" in err, err
    assert not out.exists() and dt < 10


def test_the_slowest_speedup_is_what_the_devices_can_do():
    rig = load_rig()
    slowest = min_speedup(rig)
    # the default rig's turntable: 10 deg/s, and no simulated device slower than 1 deg/s
    assert slowest.factor == pytest.approx(0.1)
    assert "turntable" in slowest.why


def test_path_checks(tmp_path, afile):
    check_output_file(tmp_path / "x.json", "--out")
    check_output_dir(tmp_path / "a" / "b", "--run-dir")
    assert not (tmp_path / "a").exists()                 # checking makes nothing
    assert list(tmp_path.iterdir()) == [afile]           # and leaves no probe behind
    for bad in (tmp_path, afile / "x", Path("/proc/x.json")):
        with pytest.raises(UserError):
            check_output_file(bad, "--out")
    for bad in (afile, afile / "run", Path("/proc/run")):
        with pytest.raises(UserError):
            check_output_dir(bad, "--run-dir")


def test_a_rig_whose_own_speedup_is_too_slow_is_refused_naming_its_key(lab, tmp_path):
    import shutil

    from lab.core.config import default_rig_path

    src = default_rig_path()
    shutil.copy(src.parent / "sim_camera.json", tmp_path / "sim_camera.json")
    rig = tmp_path / "slow.toml"
    rig.write_text(src.read_text().replace("speedup = 10.0", "speedup = 0.001", 1))
    out = tmp_path / "run"
    rc, _, err, _ = _run(lab, "run", "truss", "tetrahelix:6", "--auto", "--rig", str(rig), "--out", str(out))
    assert rc == 2 and "[sim] speedup 0.001" in err and str(rig) in err, err
    assert not out.exists()
    rc, _, err, _ = _run(lab, "sim", "--rig", str(rig), "--speedup", "1e-9")
    assert rc == 2 and "--speedup 1e-09" in err, err
