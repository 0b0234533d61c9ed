"""First day on hardware: `lab rig check` validates a rig without connecting; the shipped template
validates before any calibration exists, and `lab calibrate camera` works with it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from lab.core.config import default_rig_path

TEMPLATE = default_rig_path().parent / "hardware_example.toml"


def test_the_template_checks_as_shipped_and_says_what_is_missing(lab) -> None:
    r = lab(["rig", "check", str(TEMPLATE)])
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "valid, hardware" in out and "nothing was connected" in out
    assert "camera     0" in out and "no calibration file yet" in out
    assert "to do: camera intrinsics: `lab calibrate camera --rig" in out
    assert "ready for: lab devices check, lab calibrate camera, lab run truss" in out
    assert "not yet: lab calibrate rig (needs the camera intrinsics), lab run borg (needs the camera intrinsics)" in out
    rep = json.loads(lab(["rig", "check", str(TEMPLATE), "--json"]).stdout)
    assert not rep["simulated"] and {d["device"] for d in rep["devices"]} == {"turntable", "stewart", "camera",
                                                                              "ipjr1", "ipjr2", "ipjr3"}


def test_bad_rigs_are_one_line_and_nothing_is_connected(lab, tmp_path: Path) -> None:
    text = TEMPLATE.read_text()
    cases = {
        "units": text.replace("max_deg = 360.0", 'max_deg = "lots"'),
        "named calibration missing": text.replace('# calibration = "camera_calibration.json"',
                                                  'calibration = "camera_calibration.json"'),
        "home outside the legs": text.replace("leg_max_m = 0.50", "leg_max_m = 0.41"),
    }
    for name, body in cases.items():
        assert body != text, name
        rig = tmp_path / f"{name.replace(' ', '_')}.toml"
        rig.write_text(body)
        r = lab(["rig", "check", str(rig)])
        assert r.returncode == 2, (name, r.stdout, r.stderr)
        assert r.stdout == "" and len(r.stderr.strip().splitlines()) == 1 and str(rig) in r.stderr, (name, r.stderr)
    assert lab(["rig", "check", str(tmp_path / "none.toml")]).returncode == 2


def test_calibrate_camera_works_with_the_template_and_the_rig_is_then_ready(lab, tmp_path: Path) -> None:
    frames = tmp_path / "frames"
    r = lab(["calibrate", "camera", "--sim", "10", "--save-frames", str(frames), "--out", str(tmp_path / "sim.json")])
    assert r.returncode == 0, r.stderr
    rig = tmp_path / "my_rig.toml"
    shutil.copyfile(TEMPLATE, rig)
    r = lab(["calibrate", "camera", "--rig", str(rig), "--frames", str(frames), "--out",
             str(tmp_path / "camera_calibration.json")])
    assert r.returncode == 0, r.stdout + r.stderr
    assert (tmp_path / "camera_calibration.json").is_file()
    rig.write_text(rig.read_text().replace('# calibration = "camera_calibration.json"',
                                           'calibration = "camera_calibration.json"'))
    r = lab(["rig", "check", str(rig)])
    assert r.returncode == 0, r.stderr
    assert "calibration " in r.stdout and "(1280x720 px)" in r.stdout
    assert "lab calibrate rig" in r.stdout.split("ready for:")[1] and "not yet" not in r.stdout


@pytest.mark.parametrize("rig", ["sim.toml"])
def test_the_simulated_rig_checks_too(lab, rig: str) -> None:
    r = lab(["rig", "check", str(default_rig_path().parent / rig)])
    assert r.returncode == 0 and "valid, simulated bench" in r.stdout and "lab run borg" in r.stdout
