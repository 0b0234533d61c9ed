"""Reach (issue 23): the default rig verifies BORG structures up to 10x10x10.  A turntable wider
than the near pedestal leaves room for puts the Stewart base on a station further back (the first
that leaves 0.65 m between the base and the rim: `mid` for N = 7, `back` for 8, `far` for 9 and
10), the lift's 5 m mast carries the camera to the top layers, and a dry run finds every module of
an 8x8x8 observable before anything moves."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

import lab.core.config as config
from lab.core.config import RigError, load_rig
from lab.core.structures.borg import SPACING_M, build_borg, turntable_radius_m


def test_the_base_stands_at_the_first_station_clear_of_the_turntable():
    rig = load_rig()
    assert [s.name for s in rig.stewart.stations] == ["near", "mid", "back", "far"] and rig.stewart.station == "near"
    for n in range(2, 11):
        at = rig.for_borg(n)
        radius = turntable_radius_m(n * SPACING_M)
        joints = np.array([at.stewart.world_T_base.transformFrom(j) for j in at.stewart.geometry.base_joints_m])
        clear = np.hypot(joints[:, 0], joints[:, 1]).min() - radius
        standoff = np.hypot(*at.stewart.world_T_base.translation()[:2]) - radius
        assert at.stewart.station == {7: "mid", 8: "back", 9: "far", 10: "far"}.get(n, "near"), n
        assert clear >= rig.stewart.clearance_m and standoff >= rig.stewart.rim_standoff_m, (n, clear, standoff)
        if n == 7:    # the near base clears its rim, but stands too close for the camera to see it
            near = np.array([rig.stewart.world_T_base.transformFrom(j) for j in rig.stewart.geometry.base_joints_m])
            assert np.hypot(near[:, 0], near[:, 1]).min() >= radius + rig.stewart.clearance_m
            assert np.hypot(*rig.stewart.world_T_base.translation()[:2]) < radius + rig.stewart.rim_standoff_m
        if n >= 8:    # the near pedestal would stand on this turntable
            near = np.array([rig.stewart.world_T_base.transformFrom(j) for j in rig.stewart.geometry.base_joints_m])
            assert np.hypot(near[:, 0], near[:, 1]).min() < radius + rig.stewart.clearance_m
    assert build_borg(4).turntable.radius_m == turntable_radius_m(4 * SPACING_M)
    # choosing is idempotent, and the rig file's pose is kept for the near station
    assert rig.for_borg(3).stewart.world_T_base.equals(rig.stewart.world_T_base, 0.0)
    assert rig.for_borg(9).for_borg(9).stewart.world_T_base.equals(rig.for_borg(9).stewart.world_T_base, 0.0)
    assert rig.for_borg(9).stewart.world_T_base.translation()[0] == pytest.approx(-4.45)


def _rig_text(tmp_path: Path, edit) -> Path:
    rig_dir = Path(config.default_rig_path()).parent
    (tmp_path / "sim_camera.json").write_bytes((rig_dir / "sim_camera.json").read_bytes())
    path = tmp_path / "rig.toml"
    path.write_text(edit((rig_dir / "sim.toml").read_text()))
    return path


@pytest.mark.parametrize("edit, match", [
    (lambda t: t.replace('name = "far"', 'name = "near"'), r"\[stewart\]\.stations: station name 'near' used twice"),
    (lambda t: t.replace('name = "far"', 'name = "far"\nheight_m = 1'), r"\[stewart\.stations\[2\]\]\.height_m: unknown key"),
    (lambda t: t.replace('world_T_base = { xyz_m = [-4.45, 0.0, 0.27]', 'world_T_base = { xyz_m = [-4.45, 0.0]'),
     r"\[stewart\.stations\[2\]\.world_T_base\]\.xyz_m: expected a list of 3 numbers"),
    (lambda t: t.replace("clearance_m = 0.05", "clearance_m = -1"), r"\[stewart\]\.clearance_m: must be >= 0"),
    (lambda t: t.replace("rim_standoff_m = 0.65", "rim_standoff_m = nan"), r"\[stewart\]\.rim_standoff_m: "),
])
def test_a_bad_station_is_one_line_naming_the_key(tmp_path, edit, match):
    with pytest.raises(RigError, match=match):
        load_rig(_rig_text(tmp_path, edit))


def _no_standoff(tmp_path: Path) -> Path:
    """The sim rig without its rim standoff: a 7x7x7's base stands at the near station, 0.33 m from
    the turntable's rim, where the rim tags pass under the camera's field."""
    return _rig_text(tmp_path, lambda t: t.replace("rim_standoff_m = 0.65", "rim_standoff_m = 0.0"))


def test_a_rig_survey_that_would_see_no_rim_tag_is_refused_before_anything_moves(lab, tmp_path):
    """Before, `lab calibrate rig --n 7` moved through all 288 survey views and then stopped: "no
    turntable tag was seen"; a run did the same at its first step."""
    rig = str(_no_standoff(tmp_path))
    code, out, err = lab.main("calibrate", "rig", "--rig", rig, "--n", "7", "--auto", "--speedup", "100",
                              "--out", str(tmp_path / "cal.json"), "--run-dir", str(tmp_path / "run"))
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "predicted to see no turntable tag from station 'near'" in err and "0.33 m from the rim" in err
    assert "rim_standoff_m" in err and "nothing moved" in err
    assert not (tmp_path / "cal.json").exists() and not (tmp_path / "run").exists()
    # the survey is refused whatever the modules: one module's plan keeps the check ~10 s shorter
    r = lab(["run", "borg", "--rig", rig, "--n", "7", "--dry-run", "--modules", "1"], timeout=600)
    assert "REFUSED: rig calibration: the rig survey's 288 views are predicted to see no turntable tag" in r.stdout


@pytest.mark.slow      # CI keeps the 8x8x8's (the same station); this one guards the planner's reach
def test_a_dry_run_finds_every_module_of_a_7x7x7_observable_from_the_middle_station(lab):
    """The near base is too close to a 7x7x7's rim (above); from the middle one, 0.4 m further
    back, every module is seen, and in half the views the far station took (1.6 m from the face,
    not 2.7 m: 774 views planned at stop 53, 1520 from the far station)."""
    r = lab(["run", "borg", "--n", "7", "--dry-run"], timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "dry run of borg: 236 steps planned" in r.stdout
    assert "REFUSED" not in r.stdout and "unobservable" not in r.stdout + r.stderr
    views = re.search(r"(\d+) views planned for 235 modules", r.stdout)
    assert views and int(views[1]) <= 235 * 4


def test_a_dry_run_finds_every_module_of_an_8x8x8_observable(lab):
    """Before issue 23 the same dry run refused 95 of the 410 modules (the near pedestal 0.95 m
    from the face, the camera below the top layers)."""
    r = lab(["run", "borg", "--n", "8", "--dry-run"], timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "dry run of borg: 411 steps planned" in r.stdout       # the rig survey + 410 modules
    assert "all planned moves are within limits" in r.stdout
    # what the plans amount to: their views, and the few tags measured from one angle only (the
    # top layer's strut brackets; 6 at stop 47)
    views = re.search(r"(\d+) views planned for 410 modules \((\d+\.\d+) a module\), the rig survey 288", r.stdout)
    assert views and 410 * 3 <= int(views[1]) <= 410 * 12
    one = re.search(r"(\d+) of 538 tags planned from one turntable angle only", r.stdout)
    assert one and int(one[1]) <= 12
    assert "REFUSED" not in r.stdout and "unobservable" not in r.stdout + r.stderr


@pytest.mark.slow
def test_a_dry_run_finds_every_module_of_a_10x10x10_observable(lab):
    """The rig sees every module of a 10x10x10, and its 926 tags are printed in the extension of
    AprilTag 36h11 (before it, 36h11's 587 ids refused the run: a real one had stopped at its first
    frame with tag 914)."""
    r = lab(["run", "borg", "--n", "10", "--dry-run"], timeout=1200)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "dry run of borg: 665 steps planned" in r.stdout
    assert "REFUSED" not in r.stdout and "unobservable" not in r.stdout + r.stderr


def test_a_structure_with_more_tags_than_the_largest_family_is_refused_before_anything_moves():
    from types import SimpleNamespace

    from lab.core.structures.borg import build_borg
    from procedures.borg import BorgProcedure

    beyond = BorgProcedure.tags_beyond_family.func
    assert beyond(SimpleNamespace(model=build_borg(10))) is None           # 926 tags, ids 0..925
    too_many = SimpleNamespace(n=12, tags=dict.fromkeys(range(1100)))     # no BORG of N <= 10 has as many
    why = beyond(SimpleNamespace(model=too_many))
    assert why is not None and "1100 tags, ids 0..1099" in why and "1024 codes" in why and "ids 0..1023" in why


def test_borg_sizes_beyond_ten_are_one_line(lab):
    code, out, err = lab.main("run", "borg", "--n", "11", "--dry-run")
    assert code == 2 and "2 to 10" in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.slow
def test_a_9x9x9_calibrates_on_its_turntable_tags_printed_in_the_extension(lab, tmp_path):
    """The turntable's tags are numbered last: 618..629 at N = 9, all beyond 36h11's 587 codes."""
    r = lab(["run", "borg", "--n", "9", "--modules", "2", "--auto", "--on-flag", "continue", "--speedup", "100",
             "--quiet", "--out", str(tmp_path / "n9")], timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "2 ok, 0 flagged, 0 uncertain, 0 unverified" in r.stdout
