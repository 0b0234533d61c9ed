"""Every file a user hands `lab` is refused in one line when it cannot be read: missing, a directory,
not UTF-8, not JSON / TOML.  The camera calibration and the plan once let a directory or a binary
file through as a traceback."""

from __future__ import annotations

import pytest

from drivers.camera import load_calibration
from lab.core.config import load_rig
from lab.core.errors import UserError
from lab.core.rig_calibration_file import load_rig_calibration
from lab.core.scenario import load_scenario
from procedures.truss import load_plan

LOADERS = {"camera calibration": load_calibration, "rig": load_rig, "rig calibration": load_rig_calibration,
           "scenario": load_scenario, "plan": load_plan}


def _bad(tmp_path, kind: str):
    if kind == "missing":
        return tmp_path / "nothing.json", "no such file"
    if kind == "directory":
        d = tmp_path / "a_dir"
        d.mkdir()
        return d, "cannot read it"
    p = tmp_path / "bad.file"
    if kind == "binary":
        p.write_bytes(b"\xff\xfe\x00 binary")
        return p, "not a text file"
    p.write_text("{[ neither json = nor toml")
    return p, "not valid"


@pytest.mark.parametrize("kind", ["missing", "directory", "binary", "garbled"])
@pytest.mark.parametrize("what", sorted(LOADERS))
def test_an_unreadable_file_is_one_line_naming_it(tmp_path, what, kind):
    path, says = _bad(tmp_path, kind)
    with pytest.raises(UserError) as e:
        LOADERS[what](path)
    msg = str(e.value)
    assert msg.startswith(f"{what} {path}: ") and says in msg and "\n" not in msg, msg


def test_the_cli_refuses_a_directory_as_camera_calibration_and_keeps_no_device(lab, tmp_path):
    rig = tmp_path / "rig.toml"
    from lab.core.config import default_rig_path

    rig.write_text(default_rig_path().read_text().replace('calibration = "sim_camera.json"',
                                                           f'calibration = "{tmp_path}"'))
    rc, out, err = lab.main("run", "borg", "--dry-run", "--rig", str(rig))
    assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert f"camera calibration {tmp_path}: cannot read it" in err, err
    # the devices claimed before the camera's driver refused its file are released with it: a
    # process that goes on (a test session, a notebook) must not keep owning the bench
    from drivers import ownership

    assert ownership.held_keys() == []
