"""Issue 11, bad input: every malformed scenario, rig, size, speed or speed-up gets one line naming
the file, the key and the problem, exit 2 (never a traceback, never a run that does not end)."""

from __future__ import annotations

from pathlib import Path

import pytest

from lab.cli import main as lab_main
from lab.core.config import load_rig

SIM = Path(__file__).resolve().parents[1] / "lab" / "rigs" / "sim.toml"


def _one_line(capsys, argv: list[str]) -> str:
    assert lab_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


@pytest.mark.parametrize("text,key", [
    ("[truss]\nsigma_length_m = nan\n", "truss.sigma_length_m"),
    ("[truss]\nsigma_length_m = inf\n", "truss.sigma_length_m"),
    ("[truss]\nsigma_length_m = 1e9\n", "truss.sigma_length_m"),
    ("[truss]\nsigma_measure_m = -0.001\n", "truss.sigma_measure_m"),
    ("[camera]\npixel_noise = -5\n", "camera.pixel_noise"),
    ("[camera]\nblur_px = nan\n", "camera.blur_px"),
    ("borg = 5\n", "borg"),
    ("[borg]\nfault = [1, 2]\n", "borg.fault[0]"),
    ("device = \"x\"\n", "device"),
    ('[[borg.fault]]\nkind = "module_offset"\nmodule = "2D"\noffset_m = [0, nan, 0]\n', "offset_m"),
    ('[[borg.fault]]\nkind = "partial_deploy"\nmodule = "13D"\nheight_m = 1e6\n', "height_m"),
    ('[[device.fault]]\ndevice = "turntable"\nkind = "timeout"\ncount = 10000000000\n', "count"),
])
def test_bad_scenarios_are_one_line_errors(tmp_path, capsys, text, key):
    sc = tmp_path / "bad.toml"
    sc.write_text(text)
    line = _one_line(capsys, ["run", "truss", "tetrahelix:6", "--auto", "--quiet", "--scenario", str(sc),
                              "--out", str(tmp_path / "out")])
    assert str(sc) in line and key in line
    assert not (tmp_path / "out").exists()        # refused before anything: no run directory left


def test_a_binary_scenario_or_rig_is_one_line(tmp_path, capsys):
    blob = tmp_path / "blob.toml"
    blob.write_bytes(bytes(range(256)))
    assert "not a text file" in _one_line(capsys, ["run", "truss", "tetrahelix:6", "--scenario", str(blob),
                                                   "--out", str(tmp_path / "o")])
    assert "not a text file" in _one_line(capsys, ["run", "truss", "tetrahelix:6", "--rig", str(blob),
                                                   "--out", str(tmp_path / "o")])


@pytest.mark.parametrize("old,new,key", [
    ("speed_deg_s = 10.0", "speed_deg_s = 0.001", "speed_deg_s"),
    ("speedup = 10.0", "speedup = inf", "speedup"),
])
def test_rig_speeds_are_bounded(tmp_path, old, new, key):
    text = SIM.read_text()
    assert old in text
    rig = tmp_path / "rig.toml"
    rig.write_text(text.replace(old, new, 1))
    (tmp_path / "sim_camera.json").write_text((SIM.parent / "sim_camera.json").read_text())
    with pytest.raises(Exception) as err:
        load_rig(rig)
    assert key in str(err.value) and str(rig) in str(err.value)


@pytest.mark.parametrize("argv,word", [
    (["structure", "borg", "--n", "100"], "BORG size"),
    (["structure", "truss", "tetrahelix:100000"], "tetrahelix"),
    (["run", "borg", "--n", "100", "--auto", "--dry-run"], "--n 100"),
])
def test_sizes_are_bounded(capsys, argv, word):
    assert word in _one_line(capsys, argv)


@pytest.mark.parametrize("value", ["inf", "nan", "0", "-3", "1e9"])
def test_speedup_is_bounded(capsys, value):
    with pytest.raises(SystemExit) as e:
        lab_main(["run", "truss", "tetrahelix:6", "--speedup", value])
    assert e.value.code == 2
    assert "--speedup" in capsys.readouterr().err


def test_the_bounds_admit_every_shipped_scenario_and_the_papers_noise():
    from lab.core.scenario import load_scenario, parse_scenario

    for f in (Path(__file__).resolve().parents[1] / "docs" / "scenarios").glob("*.toml"):
        load_scenario(f)
    s = parse_scenario({"truss": {"sigma_length_m": 0.1, "sigma_measure_m": 0.01}})   # the IPJR paper's study
    assert s.truss.sigma_length_m == 0.1
