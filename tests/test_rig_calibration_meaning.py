"""A rig calibration file is checked for meaning, not only shape (issue 22, item 3): `lab rig check`
and `lab run borg` refuse, in one line naming the file and key and before anything moves, a file
whose values no survey of this bench could give or whose covariances are not covariances, or one
made on another rig; and a run whose camera disagrees with a plausible-looking calibration stops
saying the rig is wrong instead of blaming the structure.

The file every case starts from is a real one: a small survey of the default simulated rig (45 deg
turntable steps, devices 100x faster), so the writer's own output is held to the same checks."""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from lab.core.config import default_rig_path
from lab.core.rig_calibration_check import MAX_CONDITION, check_covariance
from lab.core.errors import UserError

FAST = ["--auto", "--quiet", "--speedup", "100"]


@pytest.fixture(scope="module")
def good(rig_survey) -> dict:
    return json.loads(rig_survey["out"].read_text())


def _rig_with(tmp_path: Path, data: dict) -> Path:
    """A copy of the default rig whose [calibration] file is `data`."""
    src = default_rig_path()
    shutil.copy(src.parent / "sim_camera.json", tmp_path / "sim_camera.json")
    (tmp_path / "cal.json").write_text(json.dumps(data))
    text = src.read_text().replace("[lift]", '[calibration]\nfile = "cal.json"\n\n[lift]', 1)
    rig = tmp_path / "rig.toml"
    rig.write_text(text)
    return rig


def _set(path: str, value):
    def f(d):
        *keys, last = path.split(".")
        for k in keys:
            d = d[k] if not isinstance(d, list) else d[int(k)]
        if isinstance(d, list):
            d[int(last)] = value
        else:
            d[last] = value
    return f


def _cov(path: str, make):
    def f(d):
        node = d
        for k in path.split("."):
            node = node[k]
        n = len(node["covariance"] if "covariance" in node else node)
        m = make(n)
        if "covariance" in node:
            node["covariance"] = m
        else:
            raise AssertionError(path)
    return f


def _joint(make):
    def f(d):
        d["joint_covariance"] = make(len(d["joint_covariance"]), np.asarray(d["joint_covariance"]))
    return f


BAD = [
    # (case, mutation, what the one line must name)
    ("fx negative", _set("camera.fx_px", -916.0), "camera.fx_px"),
    ("fx zero", _set("camera.fx_px", 0.0), "camera.fx_px"),
    ("fx 20 % off", _set("camera.fx_px", 1100.0), "camera.fx_px"),
    ("cx off the frame", _set("camera.cx_px", 50000.0), "camera.cx_px"),
    ("cy 80 px off", _set("camera.cy_px", 440.0), "camera.cy_px"),
    ("base 100 m away", _set("world_T_base.xyz_m.0", -102.95), "world_T_base.xyz_m[0]"),
    ("mount upside down", _set("platform_T_camera.rpy_deg.0", 90.0), "platform_T_camera.rpy_deg"),
    ("axis 10 cm off", _set("world_T_axis.xyz_m.1", 0.1), "world_T_axis.xyz_m[1]"),
    ("turntable tag 50 m off", _set("turntable_tags.37.xyz_m.0", 50.0), "turntable_tags.37.xyz_m[0]"),
    ("another rig", _set("rig", "some-other-bench"), "rig: made for rig 'some-other-bench'"),
    ("no rig", _set("rig", ""), "rig: missing"),
    ("zero mount covariance", _cov("platform_T_camera", lambda n: np.zeros((n, n)).tolist()),
     "platform_T_camera.covariance"),
    ("negative base covariance", _cov("world_T_base", lambda n: (-1e-6 * np.eye(n)).tolist()),
     "world_T_base.covariance"),
    ("all-zero joint covariance", _joint(lambda n, J: np.zeros((n, n)).tolist()), "joint_covariance"),
    ("non-symmetric joint", _joint(lambda n, J: (J + np.triu(np.full((n, n), 1e-3), 1) * np.sqrt(np.outer(
        np.diag(J), np.diag(J)))).tolist()), "not symmetric"),
    ("joint not positive definite", _joint(lambda n, J: _indefinite(J).tolist()), "not positive definite"),
    ("joint 1e12-conditioned", _joint(lambda n, J: _ill(J, 1e12).tolist()), "condition number"),
    # conditioned 1e44 by its diagonal: sigmas of 1e22 and 1e-22 px, which no survey gives
    ("intrinsics 1e44-conditioned", _cov("camera", lambda n: np.diag([1e22, 1e-22, 0.01, 0.03]).tolist()),
     "camera.covariance: 1 sigma"),
    ("tag covariance 1e-30", _cov("turntable_tags.36", lambda n: (1e-60 * np.eye(n)).tolist()),
     "turntable_tags.36.covariance"),
]


def _indefinite(J: np.ndarray) -> np.ndarray:
    """The same diagonal, but a correlation beyond 1: symmetric, not a covariance."""
    s = np.sqrt(np.diag(J))
    out = J.copy()
    out[0, 1] = out[1, 0] = 1.5 * s[0] * s[1]
    return out


def _ill(J: np.ndarray, cond: float) -> np.ndarray:
    """Same diagonal, correlation matrix with this condition number (two rows nearly the same)."""
    s = np.sqrt(np.diag(J))
    R = np.eye(len(J))
    R[0, 1] = R[1, 0] = 1 - 2 / cond
    return R * np.outer(s, s)


def test_the_surveys_own_file_is_valid(lab, tmp_path, good):
    rc, out, err = lab.main("rig", "check", str(_rig_with(tmp_path, good)))
    assert rc == 0, err
    assert "valid" in out


@pytest.mark.parametrize("case, mutate, names", BAD, ids=[b[0] for b in BAD])
def test_lab_rig_check_refuses_in_one_line(lab, tmp_path, good, case, mutate, names):
    data = copy.deepcopy(good)
    mutate(data)
    rc, out, err = lab.main("rig", "check", str(_rig_with(tmp_path, data)))
    assert rc == 2, (case, out)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "cal.json" in lines[0] and names in lines[0], (case, err)
    assert "Traceback" not in err


@pytest.mark.parametrize("case, mutate, names", [BAD[0], BAD[5], BAD[8], BAD[9], BAD[13]],
                         ids=[BAD[k][0] for k in (0, 5, 8, 9, 13)])
def test_lab_run_borg_refuses_before_anything_moves(lab, tmp_path, good, case, mutate, names):
    data = copy.deepcopy(good)
    mutate(data)
    cal = tmp_path / "c.json"
    cal.write_text(json.dumps(data))
    out = tmp_path / "run"
    rc, _, err = lab.main("run", "borg", *FAST, "--modules", "1", "--calibration", str(cal), "--out", str(out))
    assert rc == 2 and names in err, err
    assert not out.exists()                     # refused before the run began: nothing moved, nothing written


def test_a_calibration_that_disagrees_with_the_camera_stops_the_run_naming_the_rig(lab, tmp_path, good):
    """Within every bound, but the Stewart base 15 cm off where it is: the rim tags show it."""
    data = copy.deepcopy(good)
    data["world_T_base"]["xyz_m"][1] += 0.15
    cal = tmp_path / "c.json"
    cal.write_text(json.dumps(data))
    rc, out, err = lab.main("run", "borg", *FAST, "--modules", "2", "--calibration", str(cal), "--out",
                            str(tmp_path / "r"))
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert rc == 3 and summary["result"] == "aborted"
    assert "disagrees with the rig calibration" in summary["reason"] and "not the structure" in summary["reason"]
    assert str(cal) in summary["reason"]
    assert summary["modules"] == []            # no module blamed for it


def test_the_same_run_with_the_good_file_completes(lab, tmp_path, good):
    cal = tmp_path / "c.json"
    cal.write_text(json.dumps(good))
    rc, out, err = lab.main("run", "borg", *FAST, "--modules", "2", "--calibration", str(cal), "--out",
                            str(tmp_path / "r"))
    assert rc == 0, err
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert [m["verdict"] for m in summary["modules"]] == ["ok", "ok"]


def test_most_of_the_structure_off_its_shape_is_the_rigs():
    from lab.core.geometry import Pose3, Rot3
    from lab.core.structures.borg import build_borg
    from procedures.rig_consistency import structure_disagreement

    model = build_borg(3)
    design = {t: model.tags[t].structure_T_tag for t in range(12)}
    assert structure_disagreement(design, model, 0.05, "x") is None
    # the whole structure moved rigidly (placed off its spot): fits, not the rig
    shift = Pose3(Rot3.Rz(0.05), np.array([0.08, -0.05, 0.0]))
    assert structure_disagreement({t: shift.compose(p) for t, p in design.items()}, model, 0.05, "x") is None
    # a minority of tags off (a bad module): the structure's business
    few = dict(design)
    for t in (0, 1, 2):
        few[t] = Pose3(few[t].rotation(), few[t].translation() + [0.0, 0.2, 0.0])
    assert structure_disagreement(few, model, 0.05, "x") is None
    # most of them off in different directions: no rigid placement explains it
    rng = np.random.default_rng(0)
    most = {t: Pose3(p.rotation(), p.translation() + rng.normal(0, 0.3, 3)) for t, p in design.items()}
    bad = structure_disagreement(most, model, 0.05, "calibration c.json")
    assert bad is not None and "not the structure" in bad.reason and "c.json" in bad.reason


def test_the_condition_bound_is_on_the_correlation_not_the_units():
    # a survey's covariance spans rad^2, m^2 and px^2: 1e12 in raw units, fine
    C = np.diag([1e-14, 1e-8, 0.01, 1e-2])
    check_covariance(C, ("rad", "m", "px", "px"), "x", "f")
    R = np.eye(2)
    R[0, 1] = R[1, 0] = 1 - 1e-12                      # correlation condition 2e12
    with pytest.raises(UserError, match="condition number"):
        check_covariance(R * 1e-6, ("m", "m"), "x", "f")
    R[0, 1] = R[1, 0] = 1 - 4 / MAX_CONDITION          # just inside
    check_covariance(R * 1e-6, ("m", "m"), "x", "f")
