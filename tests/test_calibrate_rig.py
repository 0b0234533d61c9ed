"""`lab calibrate rig`: a survey of the turntable tags through the real drivers against the simulated
devices recovers every calibration variable the simulated world hides (camera mount, Stewart base,
turntable axis, focal length, principal point) within a few sigma; writes a file that
`load_rig_calibration` and a rig referencing it read back; records the run to MCAP; refuses a
survey that cannot see a parameter, naming it, writing nothing; refuses bad input in one line.

Small surveys (45 deg turntable steps, the simulated devices 100x faster) keep this file quick;
the full survey's figures are in docs/calibration.md."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from estimation.rig_model import nees
from lab.core.config import load_rig
from lab.core.geometry import Pose3, Rot3
from lab.core.recorder import topics
from lab.core.recorder.reader import iter_messages, read_summary
from lab.core.rig_calibration_file import load_rig_calibration
from lab.core.scenario import Scenario
from sim_devices.world import SimWorld

FAST = ["--auto", "--json", "--speedup", "100"]
# chi-square 99.9 % points: a sigma that covers its error keeps its NEES below these
CHI2_999 = {1: 10.83, 2: 13.82, 3: 16.27}


@pytest.fixture(scope="module")
def survey(rig_survey):
    """One small calibration of the default simulated rig through the CLI (tests/conftest.py),
    shared by several tests, with the simulated truth it is checked against."""
    rig = load_rig()
    truth = SimWorld(rig, Scenario(seed=rig.sim.seed))      # the same world the run's bench built
    return {**rig_survey, "truth": truth.true_rig, "K": truth.camera.K, "rig_error": truth.rig_error}


def _split_nees(est: Pose3, truth: Pose3, cov: np.ndarray) -> tuple[float, float]:
    """NEES of the rotation block and of the translation block (3 dof each)."""
    return nees(est, truth, cov, dims=(0, 1, 2)), nees(est, truth, cov, dims=(3, 4, 5))


def test_json_shape_and_truth_error(survey):
    r = survey["result"]
    assert r["result"] == "completed" and r["problems"] == [] and r["simulated"] is True
    assert r["written"] == str(survey["out"]) and Path(r["run"]).exists()
    assert r["views"] == r["planned_views"] > 0 and r["sightings"] >= 2 * r["views"]
    for name in ("platform_T_camera", "world_T_base", "world_T_axis"):
        e = r["estimates"][name]
        assert {"xyz_mm", "rpy_deg", "sigma_xyz_mm", "sigma_rpy_deg"} <= set(e)
        assert all(math.isfinite(v) and v > 0 for v in e["sigma_xyz_mm"][:2] + e["sigma_rpy_deg"][:2])
    assert set(r["estimates"]["camera"]["sigma"]) == {"fx_px", "fy_px", "cx_px", "cy_px"}
    te = r["truth_error"]
    assert {"camera_mount_m", "camera_mount_rad", "stewart_base_m", "stewart_base_rad", "turntable_axis_m"} <= set(te)
    assert all(math.isfinite(v) and v >= 0 for v in te.values())
    # SI units: millimetre-sized errors are thousandths, not units
    assert te["camera_mount_m"] < 0.005 and te["stewart_base_m"] < 0.01 and te["camera_mount_rad"] < 0.01
    assert 0 < r["residuals_px"]["rms"] < 0.5 and set(r["nees"]) >= {"platform_T_camera", "world_T_base"}


def test_each_variable_recovered_within_a_few_sigma(survey):
    """Every hidden error is found: the estimate is far closer to the truth than the rig file is, and
    its error lies inside its own 99.9 % uncertainty ellipsoid."""
    cal, tr, K, re = load_rig_calibration(survey["out"]), survey["truth"], survey["K"], survey["rig_error"]
    rig = load_rig()
    nominal = {"platform_T_camera": rig.camera.platform_T_camera, "world_T_base": rig.stewart.world_T_base}
    for name in ("platform_T_camera", "world_T_base"):
        est, truth, cov = getattr(cal, name), getattr(tr, name), cal.covariance[name]
        n_rot, n_xyz = _split_nees(est, truth, cov)
        assert n_rot < CHI2_999[3] and n_xyz < CHI2_999[3], (name, n_rot, n_xyz)
        err_m = np.linalg.norm(est.translation() - truth.translation())
        err_rad = np.linalg.norm(Rot3.Logmap(est.rotation().between(truth.rotation())))
        nom = nominal[name]
        nom_m = np.linalg.norm(nom.translation() - truth.translation())
        nom_rad = np.linalg.norm(Rot3.Logmap(nom.rotation().between(truth.rotation())))
        assert err_m < 0.4 * nom_m and err_rad < 0.2 * nom_rad, (name, err_m, nom_m, err_rad, nom_rad)
    # the axis: where it crosses the plate and its tilt (its yaw and height are the gauge)
    A, At = cal.world_T_axis, tr.world_T_axis
    assert nees(A, At, cal.covariance["world_T_axis"], dims=(3, 4)) < CHI2_999[2]
    assert nees(A, At, cal.covariance["world_T_axis"], dims=(0, 1)) < CHI2_999[2]
    assert np.linalg.norm(A.translation()[:2] - At.translation()[:2]) < 0.3 * np.linalg.norm(re.turntable_axis_offset_m)
    # the focal length and principal point
    sd = np.sqrt(np.diag(cal.covariance["K"]))
    for i, (a, b) in enumerate(((0, 0), (1, 1), (0, 2), (1, 2))):
        assert abs(cal.K[a, b] - K[a, b]) < 3.3 * sd[i], (a, b, cal.K[a, b], K[a, b], sd[i])
    assert abs(cal.K[0, 0] / K[0, 0] - 1) < 0.3 * abs(re.focal_scale - 1)
    assert np.linalg.norm(cal.K[:2, 2] - K[:2, 2]) < 0.5 * np.linalg.norm(re.principal_point_offset_px)


def test_file_read_back_and_a_rig_referencing_it_loads(survey, tmp_path):
    r, cal = survey["result"], load_rig_calibration(survey["out"])
    assert cal.views == r["estimates"]["views"] and cal.rms_px == pytest.approx(r["residuals_px"]["rms"])
    e = r["estimates"]["platform_T_camera"]
    assert np.allclose(cal.platform_T_camera.translation() * 1e3, e["xyz_mm"])
    assert np.allclose(np.sqrt(np.diag(cal.covariance["platform_T_camera"]))[3:] * 1e3, e["sigma_xyz_mm"])
    assert cal.turntable_tags and set(cal.turntable_tags) <= set(range(36, 48))
    # a rig file whose [calibration] table names the file (relative to the rig file's folder)
    sim = Path(load_rig().source)
    text = sim.read_text().replace('calibration = "sim_camera.json"', f'calibration = "{sim.parent / "sim_camera.json"}"')
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "rig.json").write_text(survey["out"].read_text())
    if "\n[calibration]\n" in text:
        text = text.replace("\n[calibration]\n", '\n[calibration]\nfile = "cal/rig.json"\n', 1)
    else:
        text += '\n[calibration]\nfile = "cal/rig.json"\n'
    (tmp_path / "rig.toml").write_text(text)
    rig = load_rig(tmp_path / "rig.toml")
    assert rig.calibration.file == tmp_path / "cal" / "rig.json"
    again = load_rig_calibration(rig.calibration.file)
    assert again.platform_T_camera.equals(cal.platform_T_camera, 1e-12)


def test_run_recorded_to_mcap(survey):
    s = read_summary(survey["run"])
    assert s.result == "completed" and s.start.procedure == "calibrate_rig"
    views = survey["result"]["views"]
    assert s.topic_counts[topics.CAMERA_IMAGE] == views
    assert s.topic_counts[topics.DETECTIONS] == views
    assert s.topic_counts[topics.CAMERA_CALIBRATION] == 1
    kinds = [json.loads(m.message.json) | {"_kind": m.message.kind} for m in iter_messages(survey["run"], topics.RECORDS)]
    commanded = [k for k in kinds if k["_kind"] == "rig_survey/view"]
    assert len(commanded) == views and all(len(k["stewart_pose"]) == 6 for k in commanded)
    result = [k for k in kinds if k["_kind"] == "rig_calibration/result"]
    assert len(result) == 1 and result[0]["problems"] == [] and result[0]["truth_error"]["camera_mount_m"] > 0
    assert [n for _, n in s.steps_completed][-1] == "solve"


def test_survey_without_platform_rotations_refused(lab, tmp_path, monkeypatch):
    """Translations alone cannot tell the camera mount's offset from the Stewart base's: refused,
    one line per parameter naming it, exit 2, nothing written, the run still recorded."""
    from procedures import rig_survey

    d = math.radians
    monkeypatch.setattr(rig_survey, "SURVEY_POSES", tuple(
        (x, y, 0.0, 0.0, d(10), 0.0) for x, y in ((-0.12, 0.0), (0.0, 0.0), (0.18, 0.0), (0.0, -0.12), (0.0, 0.12))))
    out = tmp_path / "rig_calibration.json"
    rc, so, err = lab.main("calibrate", "rig", *FAST, "--angle-step-deg", "90", "--out", str(out),
                           "--run-dir", str(tmp_path / "run"))
    assert rc == 2 and not out.exists()
    lines = [ln for ln in err.splitlines() if ln.startswith("lab: error: ")]
    mount = [ln for ln in lines if "platform_T_camera (camera mount)" in ln]
    assert {ln.split(":")[2].split()[-1] for ln in mount} >= {"x", "y", "z"}, lines
    assert all("platform rotations" in ln for ln in mount)
    assert lines[-1].startswith("lab: error: rig calibration not written")
    r = json.loads(so)
    assert r["written"] is None and r["problems"] and all("\n" not in p for p in r["problems"])
    s = read_summary(tmp_path / "run" / "run.mcap")
    assert s.result == "aborted" and "poorly conditioned" in s.stop.reason


@pytest.mark.parametrize("args, needle", [
    (["--rig", "no/such/rig.toml"], "no/such/rig.toml"),
    (["--scenario", "{bad}"], "rig_error"),
    (["--angle-step-deg", "0"], "--angle-step-deg"),
    (["--speedup", "-1"], "--speedup"),
])
def test_bad_input_one_line_exit_2(lab, tmp_path, args, needle):
    if "{bad}" in args:
        bad = tmp_path / "bad.toml"
        bad.write_text('seed = 1\n[rig_error]\ncamera_mount_offset_m = [0.004, -0.003]\n')
        args = [str(bad) if a == "{bad}" else a for a in args]
        needle = f"{bad}"
    out = tmp_path / "rig_calibration.json"
    rc, so, err = lab.main("calibrate", "rig", *FAST, "--out", str(out), *args)
    assert rc == 2 and so == "" and not out.exists()
    assert len(err.strip().splitlines()) == 1 and needle in err, err
    if "bad.toml" in needle:
        assert "camera_mount_offset_m" in err


def test_existing_out_not_replaced_without_force(lab, tmp_path):
    out = tmp_path / "rig_calibration.json"
    out.write_text("keep me")
    rc, _, err = lab.main("calibrate", "rig", *FAST, "--out", str(out))
    assert rc == 2 and out.read_text() == "keep me" and "--force" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("incidence_deg, kept", [(0, True), (30, True), (40, True), (70, False), (80, False)])
def test_oblique_sightings_left_out(incidence_deg, kept):
    """A tag's shortest over longest side is about cos(incidence) (less a few percent of perspective);
    below 0.65 it is dropped."""
    import cv2

    from estimation.fiducials import tag_object_points
    from estimation.rig_calibration_solve import CalibrationView, TagSighting, drop_oblique, side_ratio
    from estimation.rig_model import ViewMotion

    K = np.array([[914.0, 0, 639.5], [0, 914.0, 359.5], [0, 0, 1]])
    dist = np.array([-0.05, 0.01, 0, 0, 0])
    # a 10 cm tag 1.8 m straight ahead of the camera, turned about its vertical axis
    camera_T_tag = Pose3(Rot3.Ry(math.radians(180 - incidence_deg)), np.array([0.0, 0.0, 1.8]))
    pts = np.array([camera_T_tag.transformFrom(p) for p in tag_object_points(0.1)])
    px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)
    corners = px.reshape(4, 2)
    assert side_ratio(corners, K, dist) == pytest.approx(math.cos(math.radians(incidence_deg)), abs=0.04)
    views, dropped = drop_oblique([CalibrationView(ViewMotion(0.0, (0.0,) * 6), (TagSighting(36, corners),))], K, dist)
    assert dropped == (0 if kept else 1) and len(views[0].sightings) == (1 if kept else 0)


def test_a_calibration_run_is_not_resumed_as_something_else(lab, survey):
    """`lab resume` on a rig calibration's run directory must not start another procedure."""
    run_dir = survey["run"].parent
    rc, so, err = lab.main("resume", str(run_dir), "--auto")
    assert rc == 2 and so == ""
    assert len(err.strip().splitlines()) == 1 and "cannot be resumed" in err and "calibrate" in err, err


def test_a_borg_run_starts_from_the_calibration_file_and_skips_the_survey(lab, survey, run_dir):
    """With a calibration file matching the world, the run goes straight to the modules, its
    detector reads through the file's focal length and principal point, and the verdicts are the
    ideal rig's."""
    out = run_dir
    r = lab(["run", "borg", "--auto", "--quiet", "--modules", "3", "--speedup", "40", "--calibration",
             str(survey["out"]), "--out", str(out)])
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads((out / "summary.json").read_text())
    assert s["calibration"] == "file" and s["rig_survey"] is None
    assert [m["verdict"] for m in s["modules"]] == ["ok", "ok", "ok"]
    assert max(m["position_error_m"] for m in s["modules"]) < 0.004


def test_the_survey_measures_the_devices_repeatability_and_the_file_keeps_it(survey):
    from estimation.rig_calibration_solve import REPEATABILITY_SCALE_RANGE

    cal = load_rig_calibration(survey["out"])
    lo, hi = REPEATABILITY_SCALE_RANGE
    assert lo <= cal.repeatability_scale <= hi
    assert json.loads(survey["out"].read_text())["repeatability_scale"] == pytest.approx(cal.repeatability_scale)
