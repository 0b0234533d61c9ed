"""MLE assembly, the EKF and open-loop baselines, camera fusion, and the plan/bench commands."""

import json

import numpy as np
import pytest

from estimation.sequencing import Planner, all_central_triangles
from estimation.truss_ekf import TrussEKF
from estimation.truss_fusion import TrussCameraMLE
from estimation.truss_geometry import Plan, orient_base
from estimation.truss_mle import TrussMLE
from estimation.truss_simulation import monte_carlo, simulate_assembly
from lab.core.structures.trusses import build_truss

SL, SM = np.sqrt(3.57e-7), np.sqrt(6.25e-8)


def _helix(n):
    m = build_truss(f"tetrahelix:{n}")
    return m, Plan.from_triangle((0, 1, 2), [(k, orient_base(m.nodes, k, (k - 3, k - 2, k - 1))) for k in range(3, n)])


@pytest.fixture(scope="module")
def telescope20():
    m = build_truss("telescope:20")
    planner = Planner(m)
    return m, planner.greedy(all_central_triangles(m)[0]).plan


def test_mle_beats_open_loop_on_a_seeded_run_tetrahelix():
    m, plan = _helix(10)
    ol = monte_carlo(m, plan, "open_loop", 0.1, 0.01, 40, seed=3)
    ekf = monte_carlo(m, plan, "ekf", 0.1, 0.01, 40, seed=3)
    mle = monte_carlo(m, plan, "mle", 0.1, 0.01, 40, seed=3)
    assert mle.trace < 0.5 * ol.trace
    assert ekf.trace < ol.trace
    assert mle.estimate_mse.sum() < ol.estimate_mse.sum()


def test_mle_beats_open_loop_on_the_telescope_with_paper_noise(telescope20):
    m, plan = telescope20
    ol = monte_carlo(m, plan, "open_loop", SL, SM, 8, seed=1)
    mle = monte_carlo(m, plan, "mle", SL, SM, 8, seed=1)
    assert mle.trace < 0.6 * ol.trace


def test_isam2_matches_batch_levenberg_marquardt(telescope20):
    m, plan = telescope20
    runs = [simulate_assembly(m, plan, "mle", SL, SM, np.random.default_rng(5), method=meth) for meth in ("isam2", "batch")]
    np.testing.assert_allclose(runs[0].truth, runs[1].truth, atol=1e-6)
    np.testing.assert_allclose(runs[0].estimate, runs[1].estimate, atol=1e-6)


def test_step_api_commands_from_the_estimate_and_refuses_bad_steps():
    m, plan = _helix(6)
    mle = TrussMLE(m, plan, 0.01, 0.001)
    s0, s1, s2, s3 = plan.steps[:4]
    with pytest.raises(ValueError, match="not built"):
        mle.lengths_to_command(s3)
    assert mle.lengths_to_command(s0).size == 0
    mle.add_step(s0, [], {})
    np.testing.assert_allclose(mle.lengths_to_command(s1), [1.0])
    mle.add_step(s1, [1.0], {(1, 0): 1.02})
    # precision-weighted: prior 1.0 m (sigma_L 1 cm) and measurement 1.02 m (sigma_M 1 mm)
    expected = (1.0 / 0.01 ** 2 + 1.02 / 0.001 ** 2) / (1 / 0.01 ** 2 + 1 / 0.001 ** 2)
    assert mle.estimate()[1] == pytest.approx([expected, 0, 0], abs=1e-6)
    L = mle.lengths_to_command(s2)
    assert L[1] == pytest.approx(np.linalg.norm(mle.nominal[2] - mle.estimate()[1]))
    with pytest.raises(ValueError, match="already built"):
        mle.add_step(s1, [1.0], {})
    with pytest.raises(ValueError, match="does not touch"):
        mle.add_step(s2, L, {(0, 1): 1.0})
    assert mle.struts_to_measure(s2) == [(2, 0), (2, 1)]


def test_mle_covariances_shrink_with_measurements_and_respect_the_gauge(telescope20):
    m, plan = telescope20
    rng = np.random.default_rng(0)
    mle = TrussMLE(m, plan, SL, SM)
    simulate_assembly(m, plan, "mle", SL, SM, rng, estimator=mle)
    cov = mle.covariances()
    assert np.trace(cov[plan.triangle[0]]) < 1e-3 * SL ** 2  # the origin node: only the tight gauge prior
    floating = [s.node for s in plan.steps[3:]]
    for f in floating:
        assert np.all(np.linalg.eigvalsh(cov[f]) > 0)
        assert np.trace(cov[f]) < 3 * SL ** 2 * 10  # far below open loop's growth


def test_ekf_agrees_with_mle_when_noise_is_small(telescope20):
    m, plan = telescope20
    a = simulate_assembly(m, plan, "ekf", 1e-5, 1e-6, np.random.default_rng(2))
    b = simulate_assembly(m, plan, "mle", 1e-5, 1e-6, np.random.default_rng(2))
    np.testing.assert_allclose(a.estimate, b.estimate, atol=2e-7)
    assert isinstance(TrussEKF(m, plan, 1e-5, 1e-6).covariances(), dict)


def test_camera_fusion_improves_the_estimate():
    m, plan = _helix(12)
    errs = {}
    for kind, kw in (("mle", {}), ("mle_camera", {"sigma_px": 0.5})):
        rng = np.random.default_rng(11)
        e = []
        for _ in range(6):
            run = simulate_assembly(m, plan, kind, 0.05, 0.01, rng, **kw)
            e.append(run.estimate_sq_errors.sum())
        errs[kind] = np.mean(e)
    assert errs["mle_camera"] < 0.5 * errs["mle"]
    est = TrussCameraMLE(m, plan, 0.05, 0.01)
    with pytest.raises(ValueError, match="camera 9"):
        est.add_observation(9, 0, [0, 0])


def test_lab_plan_truss_json(capsys):
    from lab.cli import main

    assert main(["plan", "truss", "tetrahelix:10", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["truss"] == "tetrahelix:10"
    assert len(doc["steps"]) == 10 and doc["trace_m2"] > 0
    built = set()
    for step in doc["steps"]:
        assert set(step["base"]) <= built
        built.add(step["node"])
    assert sorted(sum(doc["layers"], [])) == list(range(10))
    assert main(["plan", "truss", "nonsense:3"]) == 2


def test_bench_mle_small_instance(tmp_path):
    from lab.studies import bench_mle

    s = bench_mle.study_tetrahelix20(trials=6, seed=0)
    assert s["open_loop"]["analytic_trace_total_m2"] == pytest.approx(28.76, abs=0.01)
    for kind in ("open_loop", "ekf", "mle"):
        assert set(s[kind]) >= {"trace_node10_m2", "trace_total_m2"}
    md = bench_mle.markdown({"tetrahelix20": s}, "lab bench mle")
    assert "tetrahelix:20" in md
    files = bench_mle._plots({"tetrahelix20": s}, str(tmp_path))
    assert files and all((tmp_path / f.split("/")[-1]).stat().st_size > 1000 for f in files)
