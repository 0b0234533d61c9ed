"""The SLAM studies' ingredients: the paper's noise model as simulated (lab/studies/slam_sim.py),
SF-GraphSLAM's gate under that noise (the shared camera error cancels in a related pair; good
pairs are tied, a partial deployment is caught), and `lab bench slam` on a tiny instance (its JSON
shape, its outputs, its bad-input errors).  The figures themselves are measured by the bench."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from lab.studies import bench_slam
from lab.studies import slam_sim as ss
from estimation.sf_graphslam import SfGraphSlam
from lab.core.errors import UserError
from lab.core.structures.borg import build_borg

REQUIRED = {"trans_rmse_m", "rot_rmse_rad", "offset_trans_rmse_m", "offset_rot_rmse_rad", "solve_s"}


@pytest.fixture(scope="module")
def model():
    return build_borg()


def test_paper_noise_grows_ten_percent_per_metre_and_camera_poses_are_off_by_5cm(model):
    rng = np.random.default_rng(0)
    tag = model.tags[1].structure_T_tag
    for d in (1.0, 3.0):
        cams = ss.cameras_around(tag.translation(), tag.rotation().matrix()[:, 2], d, [[0.0, 0.0, 0.0]] * 400)
        sv = ss.make_survey(model, [1], cams, rng)
        err = np.array([v.true_structure_T_camera.between(tag).translation() - v.observations[0].camera_T_tag.translation()
                        for v in sv.views])
        want = 0.01 * (1 + 0.1 * d)
        assert np.std(err, axis=0) == pytest.approx([want] * 3, rel=0.15)
        assert sv.views[0].observations[0].sigma_m == pytest.approx(want, rel=1e-3)
        cam_err = np.array([v.reported_structure_T_camera.translation() - v.true_structure_T_camera.translation()
                            for v in sv.views])
        assert np.std(cam_err, axis=0) == pytest.approx([0.05] * 3, rel=0.15)


def test_structure_faults_move_the_right_tags(model):
    f = ss.StructureFaults(module_offsets={"6S": ((0.01, 0.0, 0.0), (0.0, 0.0, 0.0))}, deployed_heights={"2D": 0.4},
                           displaced_tags={17: (0.0, 0.3, 0.0)})
    truth = ss.true_tag_poses(model, f)
    d = {t: truth[t].translation() - model.tags[t].structure_T_tag.translation() for t in truth}
    np.testing.assert_allclose(d[9], [0.01, 0, 0], atol=1e-12)
    np.testing.assert_allclose(d[2], [0, 0, -0.1], atol=1e-12)
    np.testing.assert_allclose(d[1], 0, atol=1e-12)
    np.testing.assert_allclose(d[17], [0, 0.3, 0], atol=1e-12)
    assert all(np.allclose(v, 0) for t, v in d.items() if t not in (2, 9, 17))


def test_the_full_survey_sees_every_tag_at_least_twice(model):
    cams = ss.full_survey_path(model)
    seen = {t: sum(ss.visible(c, s.structure_T_tag, s.size_m) for c in cams) for t, s in model.tags.items()}
    assert min(seen.values()) >= 2, {t: n for t, n in seen.items() if n < 2}


def test_a_rendered_survey_is_measured_by_the_real_detector(model):
    """slam_sim.measure_rendered: the views rendered from the true camera, read by TagDetector (with
    the reported camera predicting the tags), and SF-GraphSLAM on what it found."""
    from lab.core.geometry import pose_error

    rng = np.random.default_rng(5)
    tags = [0, 1, 2, 9]
    drawn = ss.make_survey(model, tags, ss.face_path(model, tags, distance_m=2.2), rng, noise=ss.RigNoise())
    sv = ss.measure_rendered(drawn, rng)
    assert sv.sightings() == drawn.sightings()            # the detector reads every tag predicted visible
    for v in sv.views:
        for o in v.observations:
            assert pose_error(o.camera_T_tag, v.true_structure_T_camera.between(sv.truth[o.tag]))[0] < 0.02
            assert o.covariance.shape == (6, 6)
    slam, _ = bench_slam.run_ours(sv, semantic=True, noise=ss.RigNoise())
    est = slam.tag_estimates()
    assert max(pose_error(est[t], sv.truth[t])[0] for t in tags) < 0.005
    assert {(r.a, r.b) for r in slam.relations.values() if r.tied} == {(0, 1), (1, 2), (1, 9)}


def _deployable(model, seed, height=None):
    faults = ss.StructureFaults(deployed_heights={"2D": height}) if height else None
    sv = ss.make_survey(model, [1, 2], ss.three_position_path(model, [1, 2]), np.random.default_rng(seed), faults=faults)
    slam, _ = bench_slam.run_ours(sv, semantic=True)
    return sv, slam


def test_a_related_pairs_covariance_cancels_the_shared_camera_error(model):
    sv, _ = _deployable(model, 1)
    slam = SfGraphSlam(model, bench_slam._slam_config(True))
    for k, v in enumerate(sv.views):
        slam.add_view(v.reported_structure_T_camera, sv.detections(k))
    slam.solve_batch()
    marginal = math.sqrt(np.linalg.eigvalsh(slam.tag_covariance(1)[3:, 3:]).max())
    relative = math.sqrt(np.linalg.eigvalsh(slam._relative_covariance(1, 2)[3:, 3:]).max())
    assert marginal > 0.025                # the 5 cm camera pose noise, over three views
    assert relative < 0.4 * marginal       # the pair's own measurement noise (~1 cm) only


def test_good_deployables_are_tied_and_partial_ones_caught_under_the_papers_noise(model):
    for seed in range(30):
        _, slam = _deployable(model, 100 + seed)
        assert [(r.a, r.b) for r in slam.relations.values() if r.tied] == [(1, 2)], slam.untied()[0].reason
    for seed, h in enumerate((0.42, 0.40, 0.35, 0.30)):      # >= 8 cm short: 7 sigma of the lift noise
        _, slam = _deployable(model, 200 + seed, h)
        nd = slam.not_deployed()
        assert "2D" in nd and nd["2D"].height_m == pytest.approx(h, abs=0.04)
        assert not any(r.tied for r in slam.relations.values())


def test_slam_config_takes_the_papers_q_r_s(model):
    """SlamConfig can run the paper's Eqs. 34-36: a fixed Q replaces each detection's covariance,
    R and S are the camera and semantic sigmas, and no robust kernel."""
    cfg = bench_slam.paper_qrs_config()
    sv = ss.make_survey(model, [1, 2], ss.three_position_path(model, [1, 2]), np.random.default_rng(3))
    slam = SfGraphSlam(model, cfg)
    slam.add_view(sv.views[0].reported_structure_T_camera, sv.detections(0))
    factors = [slam.graph.at(i) for i in range(slam.graph.size())]
    prior, obs = factors[0], factors[1]
    np.testing.assert_allclose(prior.noiseModel().sigmas(), [0.1] * 3 + [math.sqrt(0.1)] * 3)
    np.testing.assert_allclose(obs.noiseModel().sigmas(), [math.sqrt(0.1)] * 3 + [1.0] * 3)
    assert "Robust" not in type(obs.noiseModel()).__name__
    assert slam.semantic_noise.sigmas() == pytest.approx([math.sqrt(0.1)] * 6)


def _args(tmp_path, **kw) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    bench_slam.add_arguments(p)
    args = p.parse_args([])
    args.out = str(tmp_path)
    for k, v in kw.items():
        setattr(args, k, v)
    return args


def test_bench_writes_the_json_shape_markdown_and_plots(tmp_path, capsys):
    args = _args(tmp_path, only=["closeout_square", "borg_full", "verification"], trials=1, json=True)
    assert bench_slam.run(args) == 0
    printed = json.loads(capsys.readouterr().out)
    saved = json.loads((tmp_path / "slam.json").read_text())
    assert printed == saved
    studies = saved["studies"]
    assert set(studies) == {"closeout_square", "borg_full", "verification"}
    for study, methods in studies.items():
        assert {"graphslam", "sf_graphslam"} <= set(methods), study
        for name, m in methods.items():
            assert REQUIRED <= set(m), (study, name)
    assert {"paper_powell", "paper_gtsam"} <= set(studies["closeout_square"])
    t = saved["timing"]
    assert t["isam2_steps"] == 27 and t["batch_lm_s_median"] > 0
    assert studies["borg_full"]["sf_graphslam"]["offset_trans_rmse_m"] < studies["borg_full"]["graphslam"]["offset_trans_rmse_m"]
    v = studies["verification"]["sf_graphslam"]["flag_rate"]
    assert v["offset:0"] == 0.0 and v["offset:15"] == 1.0
    md = (tmp_path / "slam.md").read_text()
    assert "#### borg_full" in md and "| iSAM2 step ≤ 10 ms |" in md
    assert {p.name for p in tmp_path.glob("*.png")} == {"slam_rmse.png", "slam_isam2_steps.png", "slam_verification.png"}


def test_bench_refuses_bad_counts(tmp_path):
    with pytest.raises(UserError, match="--trials must be at least 1, got 0"):
        bench_slam.run(_args(tmp_path, trials=0))
    with pytest.raises(UserError, match="--literal-powell must be >= 0"):
        bench_slam.run(_args(tmp_path, literal_powell=-1))


def test_lab_bench_slam_is_on_the_command_line(lab):
    out = lab(["bench", "slam", "--help"], timeout=60)
    assert out.returncode == 0 and "--quick" in out.stdout and "--only" in out.stdout
    bad = lab(["bench", "slam", "--trials", "0", "--out", "/tmp/lab-test-slam"], timeout=60)
    assert bad.returncode == 2 and "--trials must be at least 1" in bad.stderr


def test_a_tag_behind_a_nearer_one_is_hidden_and_one_beside_it_is_not():
    from procedures.survey import unoccluded

    # nearest first: a near tag, one mostly behind it, one beside it, one just touched at its edge
    lo = np.array([[100.0, 100.0], [110.0, 105.0], [300.0, 100.0], [190.0, 100.0]])
    hi = lo + 100.0
    keep = unoccluded(lo, hi, np.arange(4), 0.25)
    assert keep.tolist() == [True, False, True, True]
    # the same boxes with the depths reversed: now the second hides the first, never the other way
    assert unoccluded(lo[::-1], hi[::-1], np.arange(4), 0.25).tolist() == [True, True, True, False]
    # only the rows asked about are judged, but every nearer tag still covers them
    assert unoccluded(lo, hi, np.array([1, 2]), 0.25).tolist() == [False, True]


def test_the_scaling_study_sees_a_structure_as_the_rendered_camera_does():
    """Occlusion on: a view of the 4x4x4 reads fewer tags than a camera that sees through it, and
    the study's rows carry what the growth is fitted on."""
    from lab.studies import bench_scaling
    from lab.studies.bench_precision import PrecisionSetup, _sight

    model = build_borg(4)
    truth = ss.true_tag_poses(model, ss.StructureFaults(), list(model.tags))
    setup = PrecisionSetup()
    tags = [t for m in [model.turntable, *model.modules[:20]] for t in (m.tag_ids if m is model.turntable else m.tags)]
    # the third view of the 20th module: two far tags behind nearer ones
    cam = bench_scaling._cameras(model, model.modules[19])[2]
    through = _sight(np.random.default_rng(0), ss.SIM_K, cam, cam, truth, tags, model, setup)
    hidden = _sight(np.random.default_rng(0), ss.SIM_K, cam, cam, truth, tags, model, setup, bench_scaling.OCCLUSION)
    lost = {d.tag_id for d in through} - {d.tag_id for d in hidden}
    assert len(lost) == 2 and {d.tag_id for d in hidden} < {d.tag_id for d in through}
    depth = {d.tag_id: d.camera_T_tag.translation()[2] for d in through}
    assert min(depth[t] for t in lost) > min(depth.values())
    res = bench_scaling.study(sizes=(3, 4), observations=("corner-info",))
    rows = res["rows"]["corner-info"]
    assert [r["n"] for r in rows] == [3, 4] and rows[0]["tags"] < rows[1]["tags"]
    assert all(r["batch_ms"] > 0 and 1 < r["sightings_per_view"] < 30 for r in rows)
    g = res["growth"]["corner-info"]
    assert g["batch_ms"] is not None and g["batch_vs_factors"] is not None
    assert any("batch ∝ factors^" in line for line in bench_scaling.markdown(res))


def test_the_speed_section_reports_each_figure_with_its_target_and_floors():
    from lab.studies import bench_scaling

    # the small survey in the run's model is taken several times and its median survey kept
    kept = bench_scaling._median_survey(3, 0, 3)
    spread = kept["step_median_ms_surveys"]
    assert len(spread) == 3 and spread == sorted(spread) and kept["step_median_ms"] == spread[1]
    assert kept["batch_ms"] > 0 and kept["batch_first_ms"] > 0 and kept["observation"] == "corners"
    rows = [kept, bench_scaling.measure(3, "corner-info", 0)]
    for r in rows:
        # the iSAM2 update alone is part of the step, never more than it
        assert 0 < r["solver_median_ms"] <= r["step_median_ms"] and r["solver_max_ms"] <= r["step_max_ms"]
        # every step re-eliminates at least its new variables, counted by quarter of the survey
        assert len(r["reeliminated_by_quarter"]) == 4 and min(r["reeliminated_by_quarter"]) >= 1
    lin = bench_scaling.linearisation_costs(repeats=40)
    corner = lin["corner factor (Python callback, compiled arithmetic)"]
    assert lin["BetweenFactorPose3 (C++)"] < lin["a Python factor that does nothing"] < corner
    # a run-model survey's steps without its batch solve
    stepped = bench_scaling.measure(3, "corners", 0, batch=False)
    assert stepped["batch_ms"] is None and stepped["step_median_ms"] > 0
    res = {"rows": rows + [dict(rows[1], n=5), dict(stepped, n=5)], "large_n": 5, "linearisation_us": lin}
    md = "\n".join(bench_scaling.speed_markdown(res))
    assert "| step, 3×3×3, median / max (ms) | ≤ 2 / ≤ 10 |" in md
    assert f"(the median of 3 surveys: {spread[0]:.1f}-{spread[2]:.1f})" in md
    assert "| full batch LM, 3×3×3 (ms) | ≤ 20 |" in md
    # the batch's first solve, which builds the view factors, is reported beside the later ones
    assert f"(the first solve, building its view factors: {kept['batch_first_ms']:.0f})" in md
    assert f"| step, 5×5×5, median / max (ms) | (targets at N = 3 and 8) | {stepped['step_median_ms']:.1f} /" in md
    assert "| full batch LM, 5×5×5 (ms) | – | not run |" in md
    assert "step, 5×5×5" in md and "corner factor (Python callback, compiled arithmetic)" in md
    assert "re-eliminate, median by quarter of the survey: 3×3×3 `corners` " in md


def test_the_scaling_study_takes_each_step_as_a_run_does(monkeypatch):
    """Each module's round is solved with its tags held for the verdict and released after it, as
    `procedures/borg_measure.py` does: the study times the step the runs pay, not a bare update."""
    from estimation.sf_graphslam import SfGraphSlam
    from lab.studies import bench_scaling

    snapshots, released = [], []
    update, release = SfGraphSlam.update, SfGraphSlam.release

    def spy_update(self, snapshot=(), hold=False):
        snapshots.append((tuple(snapshot), hold))
        return update(self, snapshot, hold)

    def spy_release(self, tags):
        released.append(tuple(tags))
        assert set(tags) <= self.held
        return release(self, tags)

    monkeypatch.setattr(SfGraphSlam, "update", spy_update)
    monkeypatch.setattr(SfGraphSlam, "release", spy_release)
    row = bench_scaling.measure(3, "corner-info", 0)
    model = build_borg(3)
    held = [(tuple(m.tags), True) for m in model.modules]
    assert [s for s in snapshots if s[1]] == held and released == [m for m, _ in held]
    assert row["step_median_ms"] > 0
