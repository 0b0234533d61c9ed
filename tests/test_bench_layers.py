"""`lab bench layers` (issue 23): faults in every layer of every size, figures per layer.  CI checks
what the study asks of each run and how it counts; the study itself (real runs) is `slow`."""

from __future__ import annotations

import json

import pytest

from lab.core.structures.borg import build_borg
from lab.studies.bench_layers import (FAULT_DEPLOYED_M, FAULT_OFFSET_M, GOOD_OFFSET_M, aggregate, to_markdown,
                                      plan_faults, scenario)


@pytest.mark.parametrize("n", [3, 4])
def test_every_layer_gets_each_fault_kind_and_a_good_module_just_inside(n):
    model = build_borg(n)
    faults = plan_faults(n, seed=1)
    assert plan_faults(n, seed=1) == faults and plan_faults(n, seed=2) != faults      # seeded
    for layer in range(n):
        kinds = {k for name, (k, _) in faults.items() if model.layer_of(name) == layer}
        assert {"offset", "rotation", "good"} <= kinds, (layer, kinds)
        if any(m.kind == "deployable" and model.layer_of(m.name) == layer for m in model.modules):
            assert "partial_deploy" in kinds
    for name, (kind, value) in faults.items():
        if kind == "partial_deploy":
            assert model.module_by_name[name].kind == "deployable" and value == FAULT_DEPLOYED_M
        elif kind in ("offset", "good"):
            assert sum(x * x for x in value) ** 0.5 == pytest.approx(FAULT_OFFSET_M if kind == "offset" else GOOD_OFFSET_M)
    text = scenario(1, faults)
    assert text.startswith("seed = 1\n") and text.count("[[borg.fault]]") == len(faults)


def test_the_layer_of_a_module_is_the_cell_row_it_closes():
    model = build_borg(3)
    rows = {m.name: model.layer_of(m.name) for m in model.modules}
    assert rows["2D"] == rows["6S"] == rows["1P"] == 0            # a bottom cell, a base strut, the square on it
    assert rows["10CT"] == rows["12S"] == rows["15P"] == 1        # the centre cell, a middle strut and square
    assert rows["11D"] == rows["16S"] == 2 and rows["27P"] == 1      # 27P closes row 1 at z = 1 m


def test_the_figures_count_per_layer_and_per_size():
    mods = [{"name": "a", "layer": 0, "fault": False, "verdict": "ok", "views": 4, "error_m": 0.0002, "sigma_m": 0.0004,
             "replanned": False},
            {"name": "b", "layer": 0, "fault": True, "verdict": "flagged", "views": 5, "error_m": 0.001, "sigma_m": 0.0004,
             "replanned": True},
            {"name": "c", "layer": 1, "fault": False, "verdict": "unverified", "views": 6, "error_m": None,
             "sigma_m": None, "replanned": True},
            {"name": "d", "layer": 1, "fault": False, "verdict": "flagged", "views": 3, "error_m": 0.0008,
             "sigma_m": 0.0002, "replanned": False}]
    rows = aggregate([{"n": 2, "seed": 0, "wall_s": 40.0, "modules": mods, "peak_rss_mb": 300.0,
                       "slam_update_s_median": 0.01}])
    whole, l0, l1 = rows
    assert (whole["layer"], whole["modules"], whole["unverified"], whole["false_flags"], whole["good"]) == ("all", 4, 1, 1, 3)
    assert (whole["faults_caught"], whole["faults"], whole["replanned"]) == (1, 1, 2)
    assert whole["error_mm_max"] == pytest.approx(0.8) and whole["views_per_module"] == pytest.approx(4.5)
    assert whole["ok_error_mm_max"] == pytest.approx(0.2)
    assert whole["wall_s_per_module"] == pytest.approx(10.0) and whole["peak_rss_mb"] == 300.0
    assert (l0["modules"], l0["false_flags"], l0["faults_caught"]) == (2, 0, 1)
    assert (l1["unverified"], l1["false_flags"], l1["error_mm_median"]) == (1, 1, pytest.approx(0.8))
    assert l1["ratio_median"] == pytest.approx(4.0)
    # trials journaled before the NEES was kept: no NEES, no frame, and the table still prints
    assert whole["nees_mean"] is None and whole["frame_offset_mm_max"] is None
    assert "| 2 | all |" in to_markdown({"command": "lab bench layers", "runs": 1, "wall_s": 40.0, "rows": rows})


def test_the_stated_1_sigma_is_told_beside_the_planned_one_and_the_bound():
    def mod(name, verdict, fault, sigma, planned, bound):
        return {"name": name, "layer": 0, "fault": fault, "verdict": verdict, "views": 4, "error_m": 0.0002,
                "sigma_m": sigma, "replanned": False, "planned_sigma_m": planned, "bound_m": bound}

    mods = [mod("a", "ok", False, 0.0004, 0.0002, 0.00035), mod("b", "ok", False, 0.0003, 0.0002, 0.00025),
            mod("c", "ok", True, 0.009, 0.009, 0.009),             # a fault passed `ok`: not a good module
            mod("d", "uncertain", False, 0.009, 0.009, 0.009)]     # not passed `ok`
    whole = aggregate([{"n": 2, "seed": 0, "wall_s": 1.0, "modules": mods, "peak_rss_mb": None,
                        "slam_update_s_median": 0.01}])[0]
    assert whole["sigma_m_mm_median"] == pytest.approx(0.35)
    assert whole["planned_sigma_m_mm_median"] == pytest.approx(0.2)
    assert whole["bound_m_mm_median"] == pytest.approx(0.3)
    text = to_markdown({"command": "lab bench layers", "runs": 1, "wall_s": 1.0, "rows": [whole]})
    assert "| 0.35 / 0.20 / 0.30 |" in text
    # trials journaled before the plans' 1-sigma was kept
    old = aggregate([{"n": 2, "seed": 0, "wall_s": 1.0, "peak_rss_mb": None, "slam_update_s_median": 0.01,
                      "modules": [{k: v for k, v in m.items() if k not in ("planned_sigma_m", "bound_m")} for m in mods]}])[0]
    assert old["planned_sigma_m_mm_median"] is None and old["sigma_m_mm_median"] == pytest.approx(0.35)


def test_the_nees_is_read_whole_and_about_each_runs_frame():
    mods = [{"name": n, "layer": 0, "fault": fault, "verdict": "ok", "views": 4, "error_m": 0.0002, "sigma_m": 0.0004,
             "replanned": False, "nees": nees, **({"nees_frame": nf} if nf is not None else {})}
            for n, fault, nees, nf in (("a", False, 6.0, 1.0), ("b", False, 9.0, 2.0), ("c", True, 30.0, None),
                                       ("d", False, None, None))]
    trial = {"n": 2, "wall_s": 40.0, "peak_rss_mb": None, "slam_update_s_median": 0.01}
    rows = aggregate([{**trial, "seed": 0, "modules": mods, "frame_offset_mm": 0.4, "frame_rotation_mrad": 0.2},
                      {**trial, "seed": 1, "modules": mods, "frame_offset_mm": 0.1, "frame_rotation_mrad": 0.3}])
    whole = rows[0]
    # good modules only: the fault's NEES is not an honesty figure
    assert whole["nees_mean"] == pytest.approx(7.5) and whole["nees_frame_mean"] == pytest.approx(1.5)
    assert (whole["frame_offset_mm_max"], whole["frame_rotation_mrad_max"]) == (0.4, 0.3)


def test_each_run_is_told_with_its_frame():
    from lab.studies.bench_layers import per_run

    mods = [{"name": "a", "layer": 0, "fault": False, "verdict": "ok", "views": 4, "error_m": 0.0009, "sigma_m": 0.0004,
             "replanned": False, "nees": 12.0, "nees_frame": 2.0, "error_frame_m": 0.0003},
            {"name": "b", "layer": 0, "fault": False, "verdict": "uncertain", "views": 9, "error_m": 0.002,
             "sigma_m": 0.004, "replanned": False, "nees": 0.5, "nees_frame": 0.4, "error_frame_m": 0.0019},
            {"name": "c", "layer": 0, "fault": True, "verdict": "ok", "views": 4, "error_m": 0.003, "sigma_m": 0.0004,
             "replanned": False, "nees": 50.0}]
    t = {"n": 3, "seed": 2, "modules": mods, "frame_offset_mm": 0.4, "frame_rotation_mrad": 0.2,
         "graph_nees": {"mount": 4.24, "base": 9.0, "intrinsics": 3.06}}
    p = per_run(t)
    # good modules only; the maxima over those passed `ok`
    assert (p["nees_mean"], p["nees_frame_mean"]) == (pytest.approx(6.25), pytest.approx(1.2))
    assert (p["ok_error_mm_max"], p["ok_error_frame_mm_max"]) == (pytest.approx(0.9), pytest.approx(0.3))
    text = to_markdown({"command": "lab bench layers", "runs": 1, "wall_s": 1.0, "rows": aggregate([
        {**t, "wall_s": 1.0, "peak_rss_mb": None, "slam_update_s_median": 0.01}]), "trials": [t]})
    assert "| 3 | 2 | 0.40 | 0.20 | 6.2 | 1.2 | 0.90 | 0.30 | 4.2 / 3.1 |" in text
    # a run journaled before the graph's own rig was reported shows dashes, not a failure
    assert per_run({k: v for k, v in t.items() if k != "graph_nees"})["graph_nees_mount"] is None


def test_a_run_taken_as_it_was_found_leaves_the_time_per_module_to_the_others():
    mod = {"name": "a", "layer": 0, "fault": False, "verdict": "ok", "views": 4, "error_m": 0.0002,
           "sigma_m": 0.0004, "replanned": False}
    trial = {"n": 2, "modules": [mod], "peak_rss_mb": None, "slam_update_s_median": 0.01}
    rows = aggregate([{**trial, "seed": 0, "wall_s": None}, {**trial, "seed": 1, "wall_s": 12.0}])
    assert rows[0]["wall_s_per_module"] == pytest.approx(12.0)
    assert aggregate([{**trial, "seed": 0, "wall_s": None}])[0]["wall_s_per_module"] is None


def _study_file(path, seeds):
    mod = {"name": "a", "layer": 0, "fault": False, "verdict": "ok", "views": 4, "error_m": 0.0002,
           "sigma_m": 0.0004, "replanned": False}
    trials = [{"n": 3, "seed": s, "modules": [{**mod, "error_m": 0.0001 * (s + 1)}], "peak_rss_mb": None,
               "slam_update_s_median": 0.01, "wall_s": 10.0} for s in seeds]
    path.write_text(json.dumps({"command": f"lab bench layers --first-seed {seeds[0]}", "runs": len(trials),
                                "wall_s": 10.0 * len(trials), "trials": trials}))
    return str(path)


def test_studies_added_to_each_other_are_told_together_each_seed_once(lab, tmp_path):
    a, b = _study_file(tmp_path / "a.json", [0, 1]), _study_file(tmp_path / "b.json", [2])
    code, out, err = lab.main("bench", "layers", "--report", a, b)
    assert code == 0, err
    # three runs over both files; the largest error is seed 2's, from the second file
    assert "(3 runs, 30 s)" in out and "| 3 | all | 3 | 3 |" in out and "/ 0.30 |" in out
    code, out, err = lab.main("bench", "layers", "--report", a, _study_file(tmp_path / "c.json", [1, 2]))
    assert code == 2 and "N 3, seed 1 is also in" in err and len(err.strip().splitlines()) == 1, err


def test_a_study_can_start_at_a_later_seed(lab, tmp_path, monkeypatch):
    import lab.studies.bench_layers as layers

    seen = []
    monkeypatch.setattr(layers, "run_trial_study", lambda args, name, runs, *rest: seen.extend(runs) or 0)
    assert lab.main("bench", "layers", "--sizes", "3", "--seeds", "2", "--first-seed", "3",
                    "--out", str(tmp_path))[0] == 0
    assert [t.key for t in seen] == ["n3-seed3", "n3-seed4"]


@pytest.mark.parametrize("args, match", [(["--sizes", "3,11"], "--sizes must be in 2..10"),
                                         (["--sizes", "3,x"], "--sizes: expected integers"),
                                         (["--seeds", "0"], "--seeds >= 1"),
                                         (["--speedup", "0"], "--speedup must be in"),
                                         (["--first-seed", "-1"], "--first-seed must be 0 or more")])
def test_bad_input_is_one_line_exit_2(lab, args, match):
    code, out, err = lab.main("bench", "layers", *args)
    assert code == 2 and match in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.slow
def test_the_quick_study_verifies_every_layer(lab, tmp_path):
    r = lab(["bench", "layers", "--quick", "--json", "--out", str(tmp_path / "layers")], timeout=3600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    rows = json.loads(r.stdout)["rows"]
    whole = [row for row in rows if row["layer"] == "all"]
    assert [row["n"] for row in whole] == [3, 4]
    for row in rows:
        # every module gets a view and a verdict, and no good one is flagged; the accuracy target
        # (good-module error <= 1 mm at every N and layer) is the study's figure, in
        # docs/benchmarks.md with the command, not a test's: it is missed by up to 0.2 mm at N = 4-5
        assert row["unverified"] == 0 and row["false_flags"] == 0, row
        assert row["error_mm_max"] is None or row["error_mm_max"] > 0, row
    # each run says how its graph's own mount and intrinsics ended against the truth
    trials = json.loads((tmp_path / "layers" / "layers.json").read_text())["trials"]
    assert len(trials) == 2
    for t in trials:
        assert {"mount", "intrinsics"} <= set(t["graph_nees"]) and all(v >= 0 for v in t["graph_nees"].values()), t


def _attempt(tmp_path, n=3, speedup=100.0, summary=None, checkpoint=True):
    from lab.studies import bench_layers as bl

    run_dir, sc = tmp_path / f"n{n}-seed0", tmp_path / f"scenario-n{n}-seed0.toml"
    run_dir.mkdir()
    (run_dir / "run.json").write_text(json.dumps({"params": {"n": n, "scenario": str(sc), "speedup": speedup}}))
    if summary is not None:
        (run_dir / "summary.json").write_text(json.dumps(summary))
    if checkpoint:
        (run_dir / "checkpoint.json").write_text("{}")
    return bl._earlier_attempt(run_dir, 3, sc, 100.0)


@pytest.mark.parametrize("kw, expected", [
    ({}, "resume"),                                                          # killed: no summary yet
    ({"summary": {"result": "running"}}, "resume"),                         # killed after a step
    ({"summary": {"result": "aborted", "reason": "interrupted by the operator"}}, "resume"),
    ({"summary": {"result": "failed", "reason": "DeviceTimeout: camera: no reply"}}, "resume"),
    ({"summary": {"result": "completed"}}, "completed"),                    # the study stopped before journaling it
    ({"summary": {"result": "failed", "reason": "UserError: bad scenario"}}, None),
    ({"checkpoint": False}, None),
    ({"n": 4}, None), ({"speedup": 10.0}, None)])                           # another trial's run: start afresh
def test_a_trial_goes_on_from_an_earlier_attempt_of_its_own_only(tmp_path, kw, expected):
    assert _attempt(tmp_path, **kw) == expected


def test_a_run_stopped_by_a_device_timeout_is_resumed_and_says_so(tmp_path, monkeypatch):
    from lab.studies import bench_common, bench_layers as bl

    model = build_borg(2)
    done = {"result": "completed", "views": 3, "modules": [
        {"name": m.name, "verdict": "ok", "views": 3, "position_error_m": 1e-4, "sigma_position_m": 2e-4, "reason": ""}
        for m in model.modules]}
    timeout = {"result": "failed", "reason": "DeviceTimeout: camera: no reply to GET /frame.jpg within 3 s"}
    calls = []
    monkeypatch.setattr(bl, "run_borg", lambda args, out, log=None: calls.append("run")
                        or bench_common.BorgRun(["run"], timeout, 50.0, 400.0, 0.01))
    replies = iter([timeout, done])
    monkeypatch.setattr(bl, "resume_borg", lambda out, log=None: calls.append("resume")
                        or bench_common.BorgRun(["resume"], next(replies), 20.0, 600.0, 0.02))
    r = bl.trial(tmp_path, 2, 0, 100.0)
    assert calls == ["run", "resume", "resume"] and r["resumed"] == 2
    assert r["wall_s"] == pytest.approx(90.0) and r["peak_rss_mb"] == 600.0 and len(r["modules"]) == len(model.modules)
    row = bl.aggregate([r])[0]
    assert row["resumed"] == 2 and "| 1 (2 resumed) |" in bl.to_markdown({"rows": [row], "command": "c", "runs": 1,
                                                                          "wall_s": 1.0})


@pytest.mark.parametrize("summary", [{"result": "completed"}, {"result": "running"}])
def test_a_trial_of_a_run_the_study_did_not_start_has_no_wall_time_and_journals(tmp_path, monkeypatch, summary):
    """A run found finished, or resumed from where an earlier study left it: its wall time is not
    known.  The trial says None (JSON null), which the study's journal takes back: NaN it refused."""
    from lab.core.executor.journal import finite_values
    from lab.studies import bench_common, bench_layers as bl

    model = build_borg(2)
    done = {"result": "completed", "views": 3, "modules": [
        {"name": m.name, "verdict": "ok", "views": 3, "position_error_m": 1e-4, "sigma_position_m": 2e-4, "reason": ""}
        for m in model.modules]}
    run_dir = tmp_path / "n2-seed0"
    run_dir.mkdir()
    (run_dir / "run.json").write_text(json.dumps({"params": {"n": 2, "scenario": str(tmp_path / "scenario-n2-seed0.toml"),
                                                             "speedup": 100.0}}))
    (run_dir / "summary.json").write_text(json.dumps(done if summary["result"] == "completed" else summary))
    (run_dir / "checkpoint.json").write_text("{}")
    monkeypatch.setattr(bl, "median_metric", lambda path, name: 0.01)
    monkeypatch.setattr(bl, "resume_borg", lambda out, log=None: bench_common.BorgRun(["resume"], done, 20.0, 600.0, 0.02))
    r = bl.trial(tmp_path, 2, 0, 100.0)
    assert r["wall_s"] is None and finite_values(r) is None
    assert "wall time unknown" in bl._progress(r)
