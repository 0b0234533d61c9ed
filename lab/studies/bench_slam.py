"""`lab bench slam`: GraphSLAM vs SF-GraphSLAM (ours, GTSAM) vs the paper's own method (Powell),
Monte Carlo on synthetic surveys with the paper's noise (lab/studies/slam_sim.py).

Studies (the paper's §3 plus two of ours):
- deployable        module 2D's two tags from three camera positions (§3.1, Table 2)
- closeout_strut    6S's tag with 2D's bottom tag (§3.1, Table 5)
- closeout_square   1P's tag with 2D's bottom tag (§3.1, Table 5)
- partial_deploy    2D stopped at 0.40 m of 0.50 m lift (§3.2, Table 3): must be flagged every trial
- borg_face1        the face-1 tags of Table 4 (0, 9, 13, 14, 21, 22, 35); Powell speed-up
- tag_elimination   every face-1 tag, tag 17 displaced 0.3 m in y (§3.4): must be rejected every trial
- borg_full         all 48 tags of the 3x3x3 cube, a survey that sees every tag (turntable angles x
                    Stewart poses); full-cube batch time and iSAM2 time per assembly step
- borg_full_rendered  the same survey through pixels: every view rendered (sim_devices/render.py)
                    and read by the real detector, camera pose noise of the simulated bench
- verification      beyond the paper: one module really off its design by 0-15 mm or 0-3 deg, the
                    procedure's step-by-step flow on the simulated bench's noise; flag rate against
                    the size of the deviation, with and without semantic factors

Methods: `graphslam` and `sf_graphslam` are our estimator (SfGraphSlam, batch LM) without and with
semantic factors, with noise models that match the simulation (R = the camera pose noise, Q = the
view noise, S = our semantic sigma); `paper_powell` is the paper's J_SF-GraphSLAM with its Q, R, S
minimised by Powell from zeros (`paper_powell_graphslam`: J_GraphSLAM); `paper_gtsam` minimises
the same J terms with GTSAM (Lie-group residuals) and `paper_gtsam_exact` polishes that on the
paper's exact 6-vector residuals, so costs compare at equal J.

Writes slam.json, slam.md and PNG plots to --out (default bench_out/slam); prints the Markdown (or
the JSON with --json).  Top-level imports stay light: the CLI imports this module for --help.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

from lab.core.survey_budget import MAX_VIEWS, MAX_VIEWS_RANGE, SIGMA_TARGET_MM
from lab.core.verdicts import FLAGGED
from lab.studies.bench_common import save_figure

STUDIES = ("deployable", "closeout_strut", "closeout_square", "partial_deploy", "borg_face1", "tag_elimination",
           "borg_full", "borg_full_rendered", "verification", "precision", "scaling", "speed")
# scaling and speed only when asked for: they are a machine's capacity, not the method's
DEFAULT_STUDIES = STUDIES[:-2]
# (full, --quick) trial counts; the paper ran 50 (deployable) and 10 (close-outs)
TRIALS = {"deployable": (50, 20), "closeout_strut": (20, 10), "closeout_square": (20, 10), "partial_deploy": (50, 20),
          "borg_face1": (20, 3), "tag_elimination": (50, 20), "borg_full": (20, 5), "borg_full_rendered": (5, 1),
          "verification": (20, 4), "precision": (60, 12), "scaling": (1, 1), "speed": (1, 1)}
PARTIAL_HEIGHT_M = 0.40
DISPLACED_TAG, DISPLACEMENT_M = 17, (0.0, 0.3, 0.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="fewer trials (under 3 minutes)")
    parser.add_argument("--json", action="store_true", help="print the JSON instead of the Markdown table")
    parser.add_argument("--out", default=os.path.join("bench_out", "slam"), help="output directory (default bench_out/slam)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--only", choices=STUDIES, action="append", help="run only this study (repeatable)")
    parser.add_argument("--trials", type=int, default=None, help="trials per study (overrides the defaults)")
    parser.add_argument("--corner-sigma-px", type=float, default=None, metavar="PX",
                        help="precision: the true face-on corner noise (default 0.01; simulated runs measure 0.008)")
    parser.add_argument("--sigma-target-mm", type=float, default=None, metavar="MM",
                        help=f"precision: plan each step's views to this module 1-sigma (default {SIGMA_TARGET_MM:g}, "
                             f"as a run)")
    parser.add_argument("--max-views", type=int, default=None, metavar="N",
                        help=f"precision: view budget per step ({MAX_VIEWS_RANGE[0]}..{MAX_VIEWS_RANGE[1]}, "
                             f"default {MAX_VIEWS}, as a run)")
    from lab.core.executor import add_executor_arguments

    add_executor_arguments(parser)   # the precision study's trials (the others run here)
    parser.add_argument("--literal-powell", type=int, default=None, metavar="N",
                        help="borg_face1: time Powell on the loop form of J on N trials (default 2; --quick 0: "
                             "estimated from its evaluation count and the measured time per evaluation)")


# ---- shared helpers ------------------------------------------------------------------------------
def _rms(values) -> float:
    import numpy as np

    v = np.asarray(list(values), dtype=float)
    return float(math.sqrt(np.mean(v * v))) if len(v) else math.nan


class _Acc:
    """Errors of one method over a study's trials."""

    def __init__(self) -> None:
        self.tag_t: list[float] = []
        self.tag_r: list[float] = []
        self.tag_xyz: list[list[float]] = []
        self.pair_t: list[float] = []
        self.pair_r: list[float] = []
        self.pair_xyz: list[list[float]] = []
        self.seconds: list[float] = []
        self.costs: list[float] = []
        self.extra: dict[str, float | int] = {}

    def add(self, est: dict, survey, seconds: float, tags=None) -> None:
        from lab.core.geometry import pose_error

        tags = [t for t in (tags or survey.tags) if t in est]
        for t in tags:
            dt, dr = pose_error(est[t], survey.truth[t])
            self.tag_t.append(dt)
            self.tag_r.append(dr)
            self.tag_xyz.append(list(est[t].translation() - survey.truth[t].translation()))
        for a, b, _ in survey.related_pairs():
            if a in est and b in est and a in tags and b in tags:
                e, tr = est[a].between(est[b]), survey.truth[a].between(survey.truth[b])
                dt, dr = pose_error(e, tr)
                self.pair_t.append(dt)
                self.pair_r.append(dr)
                self.pair_xyz.append(list(e.translation() - tr.translation()))
        self.seconds.append(seconds)

    def count(self, key: str, n: int | float = 1) -> None:
        self.extra[key] = self.extra.get(key, 0) + n

    def summary(self) -> dict:
        import numpy as np

        out = {"trans_rmse_m": _rms(self.tag_t), "rot_rmse_rad": _rms(self.tag_r),
               "offset_trans_rmse_m": _rms(self.pair_t), "offset_rot_rmse_rad": _rms(self.pair_r),
               "solve_s": float(np.median(self.seconds)) if self.seconds else math.nan,
               "trials": len(self.seconds)}
        if self.tag_xyz:
            out["trans_rmse_xyz_m"] = [float(v) for v in np.sqrt(np.mean(np.square(self.tag_xyz), axis=0))]
        if self.pair_xyz:
            out["offset_trans_rmse_xyz_m"] = [float(v) for v in np.sqrt(np.mean(np.square(self.pair_xyz), axis=0))]
        if self.seconds:
            out["solve_s_max"] = float(np.max(self.seconds))
        if self.costs:
            out["cost_J_median"] = float(np.median(self.costs))
        out.update(self.extra)
        return out


def _slam_config(semantic: bool, noise=None):
    from estimation.sf_graphslam import SlamConfig
    from lab.studies.slam_sim import PaperNoise

    n = noise or PaperNoise()
    return SlamConfig(semantic=semantic, camera_sigma_m=n.camera_sigma_m, camera_sigma_rad=n.camera_sigma_rad)


def paper_qrs_config():
    """Our estimator with the paper's Q, R, S (Eqs. 34-36) instead of noise models that match the
    simulation, and no robust kernel."""
    from estimation.sf_graphslam import SlamConfig

    return SlamConfig(semantic=True, observation_sigma_m=1.0, observation_sigma_rad=math.sqrt(0.1),
                      camera_sigma_m=math.sqrt(0.1), camera_sigma_rad=0.1, semantic_sigma_m=math.sqrt(0.1),
                      semantic_sigma_rad=math.sqrt(0.1), huber_k=None)


def run_ours(survey, semantic: bool, noise=None, config=None):
    """Our estimator on a survey, batch: returns (slam, seconds of decide_relations_batch)."""
    from estimation.sf_graphslam import SfGraphSlam

    slam = SfGraphSlam(survey.model, config or _slam_config(semantic, noise))
    for k, v in enumerate(survey.views):
        slam.add_view(v.reported_structure_T_camera, survey.detections(k))
    t0 = time.perf_counter()
    slam.decide_relations_batch()
    return slam, time.perf_counter() - t0


def _ours(acc: dict, survey, semantic: bool) -> object:
    name = "sf_graphslam" if semantic else "graphslam"
    slam, dt = run_ours(survey, semantic)
    acc.setdefault(name, _Acc()).add(slam.tag_estimates(), survey, dt)
    if semantic:
        a = acc[name]
        a.count("relations_tied", sum(r.tied for r in slam.relations.values()))
        a.count("relations_untied", len(slam.untied()))
    return slam


def _paper(acc: dict, survey, semantic: bool, *, powell: bool = True, gtsam: bool = True, exact: bool = False,
           suffix: str = "") -> dict:
    from lab.studies import paper_baseline as pb

    p = pb.problem_from_survey(survey, semantic=semantic)
    out = {}
    runs = []
    if gtsam:
        runs.append(("paper_gtsam", pb.solve_gtsam(p, "lie")))
        if exact:
            runs.append(("paper_gtsam_exact", pb.solve_gtsam(p, "lie+gn")))
    if powell:
        runs.append(("paper_powell", pb.solve_powell(p)))
    for name, sol in runs:
        a = acc.setdefault(name + suffix, _Acc())
        a.add(sol.tag_poses(p), survey, sol.seconds)
        a.costs.append(sol.cost)
        if sol.method == "powell":
            a.count("evaluations", sol.evaluations)
            a.count("not_converged", int(not sol.converged))
        out[name] = sol
    out["problem"] = p
    return out


def _finish(acc: dict) -> dict:
    out = {}
    for name, a in acc.items():
        s = a.summary()
        if "evaluations" in s:
            s["evaluations_mean"] = s.pop("evaluations") / max(s["trials"], 1)
        out[name] = s
    return out


# ---- the paper's small studies --------------------------------------------------------------------
def study_pair(kind: str, trials: int, seed: int) -> dict:
    """deployable / closeout_strut / closeout_square / partial_deploy: two tags, three camera positions."""
    import numpy as np

    from lab.studies import slam_sim as ss
    from lab.core.structures.borg import build_borg

    model = build_borg()
    tags = {"deployable": [1, 2], "partial_deploy": [1, 2], "closeout_strut": [1, 9], "closeout_square": [1, 0]}[kind]
    faults = ss.StructureFaults(deployed_heights={"2D": PARTIAL_HEIGHT_M}) if kind == "partial_deploy" else None
    rng = np.random.default_rng([seed, STUDIES.index(kind)])
    acc: dict = {}
    flagged = flagged_qrs = 0
    for _ in range(trials):
        sv = ss.make_survey(model, tags, ss.three_position_path(model, tags), rng, faults=faults)
        _ours(acc, sv, False)
        slam = _ours(acc, sv, True)
        if "2D" in slam.not_deployed():
            flagged += 1
        if kind in ("deployable", "partial_deploy"):
            q, dt = run_ours(sv, True, config=paper_qrs_config())
            acc.setdefault("sf_graphslam_paper_qrs", _Acc()).add(q.tag_estimates(), sv, dt)
            flagged_qrs += int("2D" in q.not_deployed())
        if kind == "partial_deploy":
            continue
        _paper(acc, sv, True, exact=kind == "deployable")
        if kind == "deployable":
            _paper(acc, sv, False, gtsam=False, suffix="_graphslam")
    out = _finish(acc)
    out["sf_graphslam"]["flagged_not_deployed"] = flagged
    if "sf_graphslam_paper_qrs" in out:
        out["sf_graphslam_paper_qrs"]["flagged_not_deployed"] = flagged_qrs
    if kind == "partial_deploy":
        out["sf_graphslam"]["true_lift_m"] = PARTIAL_HEIGHT_M
        out["graphslam"]["note"] = "GraphSLAM has no deployment check"
    return out


def study_borg_face1(trials: int, seed: int, literal_trials: int) -> tuple[dict, dict]:
    import numpy as np

    from lab.studies import paper_baseline as pb
    from lab.studies import slam_sim as ss
    from lab.core.structures.borg import build_borg

    model = build_borg()
    tags = list(ss.FACE1_TABLE4_TAGS)
    rng = np.random.default_rng([seed, STUDIES.index("borg_face1")])
    acc: dict = {}
    rows = []
    literal: list[dict] = []
    per_tag: dict[str, dict[int, list[float]]] = {}
    for trial in range(trials):
        sv = ss.make_survey(model, tags, ss.face_path(model, tags, distance_m=2.7), rng)
        missing = [t for t in tags if t not in sv.sightings()]
        if missing:
            raise RuntimeError(f"borg_face1 survey does not see tags {missing}")
        g = _ours(acc, sv, False)
        sf = _ours(acc, sv, True)
        sols = _paper(acc, sv, True, exact=True)
        p = sols["problem"]
        in_gtsam = pb.solve_gtsam(p, "euler")     # the exact polish inside GTSAM (CustomFactors), for its time
        row = {"J_powell": sols["paper_powell"].cost, "J_gtsam": sols["paper_gtsam"].cost,
               "J_gtsam_exact": sols["paper_gtsam_exact"].cost, "powell_s": sols["paper_powell"].seconds,
               "gtsam_s": sols["paper_gtsam"].seconds, "gtsam_exact_s": sols["paper_gtsam_exact"].seconds,
               "sf_graphslam_s": acc["sf_graphslam"].seconds[-1], "powell_nfev": sols["paper_powell"].evaluations,
               "gtsam_euler_s": in_gtsam.seconds, "J_gtsam_euler": in_gtsam.cost}
        # the loop form of J, one evaluation at a time, as the paper computed it
        y = sols["paper_powell"].y
        n_eval = 30
        t0 = time.perf_counter()
        for _ in range(n_eval):
            pb.j_literal(y, p)
        row["literal_eval_s"] = (time.perf_counter() - t0) / n_eval
        t0 = time.perf_counter()
        for _ in range(n_eval):
            pb.cost(y, p)
        row["vector_eval_s"] = (time.perf_counter() - t0) / n_eval
        if trial < literal_trials:
            sol = pb.solve_powell(p, literal=True)
            literal.append({"seconds": sol.seconds, "J": sol.cost, "nfev": sol.evaluations})
            row["powell_literal_s"] = sol.seconds
            row["J_powell_literal"] = sol.cost
        rows.append(row)
        for name, est in (("graphslam", g.tag_estimates()), ("sf_graphslam", sf.tag_estimates()),
                          ("paper_powell", sols["paper_powell"].tag_poses(p))):
            for t in tags:
                per_tag.setdefault(name, {}).setdefault(t, []).append(
                    float(np.linalg.norm(est[t].translation() - sv.truth[t].translation())))
    out = _finish(acc)
    med = lambda k: float(np.median([r[k] for r in rows]))   # noqa: E731
    powell_literal_s = (float(np.median([r["seconds"] for r in literal])) if literal
                        else med("powell_nfev") * med("literal_eval_s"))
    rel = [(r["J_gtsam"] - r["J_powell"]) / r["J_powell"] for r in rows]
    rel_exact = [(r["J_gtsam_exact"] - r["J_powell"]) / r["J_powell"] for r in rows]
    speed = {
        "trials": trials,
        "powell_s_median": med("powell_s"), "powell_evaluations_median": med("powell_nfev"),
        "powell_literal_s": powell_literal_s, "powell_literal_measured_trials": len(literal),
        "literal_eval_s": med("literal_eval_s"), "vector_eval_s": med("vector_eval_s"),
        "paper_gtsam_s_median": med("gtsam_s"), "paper_gtsam_exact_s_median": med("gtsam_exact_s"),
        "sf_graphslam_s_median": med("sf_graphslam_s"),
        "speedup_gtsam_vs_powell_literal": powell_literal_s / med("gtsam_s"),
        "speedup_gtsam_vs_powell_vectorised": med("powell_s") / med("gtsam_s"),
        "speedup_gtsam_exact_vs_powell_literal": powell_literal_s / med("gtsam_exact_s"),
        "speedup_gtsam_exact_vs_powell_vectorised": med("powell_s") / med("gtsam_exact_s"),
        "paper_gtsam_euler_s_median": med("gtsam_euler_s"),
        "speedup_gtsam_euler_vs_powell_literal": powell_literal_s / med("gtsam_euler_s"),
        "gtsam_euler_J_le_powell_trials": int(sum(r["J_gtsam_euler"] <= r["J_powell"] * (1 + 1e-12) for r in rows)),
        "J_rel_diff_gtsam_vs_powell": {"median": float(np.median(rel)), "max": float(np.max(rel)), "min": float(np.min(rel))},
        "J_rel_diff_gtsam_exact_vs_powell": {"median": float(np.median(rel_exact)), "max": float(np.max(rel_exact)),
                                             "min": float(np.min(rel_exact))},
        "gtsam_exact_J_le_powell_trials": int(sum(r["J_gtsam_exact"] <= r["J_powell"] * (1 + 1e-12) for r in rows)),
        "gtsam_J_le_powell_trials": int(sum(r["J_gtsam"] <= r["J_powell"] * (1 + 1e-12) for r in rows)),
        "literal_runs": literal,
        "per_tag_trans_rmse_m": {name: {str(t): _rms(v) for t, v in d.items()} for name, d in per_tag.items()},
    }
    return out, speed


def study_tag_elimination(trials: int, seed: int) -> dict:
    import numpy as np

    from lab.studies import slam_sim as ss
    from estimation.tag_elimination import eliminate_tags
    from lab.core.structures.borg import build_borg

    model = build_borg()
    tags = ss.face1_tags(model)
    faults = ss.StructureFaults(displaced_tags={DISPLACED_TAG: DISPLACEMENT_M})
    rng = np.random.default_rng([seed, STUDIES.index("tag_elimination")])
    acc: dict = {}
    counts = {m: {"rejected_displaced": 0, "false_rejections": 0, "max_clean_distance_m": 0.0} for m in ("graphslam", "sf_graphslam")}
    for _ in range(trials):
        sv = ss.make_survey(model, tags, ss.face_path(model, tags, distance_m=2.7), rng, faults=faults)
        for semantic in (False, True):
            name = "sf_graphslam" if semantic else "graphslam"
            slam = _ours(acc, sv, semantic)
            res = eliminate_tags(slam.tag_estimates(), model, base_tag=1)
            c = counts[name]
            c["rejected_displaced"] += int(DISPLACED_TAG in res.rejected)
            c["false_rejections"] += len([t for t in res.rejected if t != DISPLACED_TAG])
            c["max_clean_distance_m"] = max(c["max_clean_distance_m"],
                                            max(d for t, d in res.distances_m.items() if t != DISPLACED_TAG))
            if semantic:
                untied = {frozenset((r.a, r.b)) for r in slam.untied()}
                acc[name].count("displaced_pairs_untied", sum(frozenset((DISPLACED_TAG, k)) in untied
                                                              for k in model.tags[DISPLACED_TAG].related))
    out = _finish(acc)
    for name, c in counts.items():
        out[name].update(c)
        out[name]["cutoff_m"] = 0.05
    return out


def study_borg_full(trials: int, seed: int) -> tuple[dict, dict]:
    """All 48 tags, batch; then the incremental (iSAM2) assembly of the whole cube, step by step."""
    import numpy as np

    from lab.studies import slam_sim as ss
    from estimation.sf_graphslam import SfGraphSlam
    from lab.core.structures.borg import build_borg

    model = build_borg()
    tags = sorted(model.tags)
    rng = np.random.default_rng([seed, STUDIES.index("borg_full")])
    cams = ss.full_survey_path(model)
    acc: dict = {}
    lm_only = []
    for _ in range(trials):
        sv = ss.make_survey(model, tags, cams, rng)
        seen = sv.sightings()
        short = [t for t in tags if seen.get(t, 0) < 2]
        if short:
            raise RuntimeError(f"borg_full survey sees tags {short} fewer than twice")
        _ours(acc, sv, False)
        _ours(acc, sv, True)
        slam = SfGraphSlam(model, _slam_config(True))
        for k, v in enumerate(sv.views):
            slam.add_view(v.reported_structure_T_camera, sv.detections(k))
        t0 = time.perf_counter()
        slam.solve_batch()
        lm_only.append(time.perf_counter() - t0)
    out = _finish(acc)
    # incremental: the assembly order, three views per step, iSAM2 update per step
    a_cams, a_steps, a_present = ss.assembly_path(model)
    step_times: list[list[float]] = []
    inc = _Acc()
    for trial in range(max(1, min(trials, 5))):
        sv = ss.make_survey(model, tags, a_cams, rng, steps=a_steps, present=a_present)
        slam = SfGraphSlam(model, _slam_config(True))
        times = []
        for i, m in enumerate(model.modules):
            for k, v in enumerate(sv.views):
                if v.step == i:
                    slam.add_view(v.reported_structure_T_camera, sv.detections(k))
            t0 = time.perf_counter()
            slam.update(snapshot=m.tags)
            times.append(time.perf_counter() - t0)
        step_times.append(times)
        inc.add(slam.tag_estimates(), sv, float(np.sum(times)))
        inc.count("relations_tied", sum(r.tied for r in slam.relations.values()))
        inc.count("relations_untied", len(slam.untied()))
        inc.count("relations_undecided", sum(not r.decided for r in slam.relations.values()))
    st = np.asarray(step_times)
    timing = {
        "views": len(cams), "variables": len(cams) + len(tags),
        "batch_lm_s_median": float(np.median(lm_only)), "batch_lm_s_max": float(np.max(lm_only)),
        "batch_with_gating_s_median": out["sf_graphslam"]["solve_s"],
        "isam2_step_s_median": float(np.median(st)), "isam2_step_s_p95": float(np.percentile(st, 95)),
        "isam2_step_s_max": float(np.max(st)), "isam2_steps": int(st.shape[1]), "isam2_runs": int(st.shape[0]),
        "isam2_step_s_by_step_median": [float(v) for v in np.median(st, axis=0)],
        "assembly_views": len(a_cams),
        "isam2_final": inc.summary(),
    }
    return out, timing


def study_borg_full_rendered(trials: int, seed: int) -> dict:
    import numpy as np

    from lab.studies import slam_sim as ss
    from lab.core.structures.borg import build_borg

    model = build_borg()
    tags = sorted(model.tags)
    rng = np.random.default_rng([seed, STUDIES.index("borg_full_rendered")])
    cams = ss.full_survey_path(model)
    acc: dict = {}
    seen = []
    for _ in range(trials):
        sv = ss.measure_rendered(ss.make_survey(model, tags, cams, rng, noise=ss.RigNoise()), rng)
        seen.append(sum(len(v.observations) for v in sv.views))
        for semantic in (False, True):
            slam, dt = run_ours(sv, semantic, ss.RigNoise())
            name = "sf_graphslam" if semantic else "graphslam"
            acc.setdefault(name, _Acc()).add(slam.tag_estimates(), sv, dt)
            if semantic:
                acc[name].count("relations_tied", sum(r.tied for r in slam.relations.values()))
                acc[name].count("relations_untied", len(slam.untied()))
    out = _finish(acc)
    for s in out.values():
        s["noise"] = "rig (rendered images, detector covariance)"
        s["detections_per_trial"] = float(np.mean(seen))
    return out


# ---- beyond the paper: does verification see a real deviation? ----------------------------------------
OFFSETS_MM = (0.0, 2.5, 5.0, 7.5, 10.0, 15.0)
ROTATIONS_DEG = (0.5, 1.0, 1.5, 2.0, 3.0)
TARGETS = ("2D", "6S", "1P")      # a deployable, a close-out strut, a close-out square


def _verify_run(model, modules, sv, semantic: bool, after_tie: bool = False) -> dict[str, str]:
    """The procedure's measuring flow (procedures/borg_measure.py): per step, add the views, update
    iSAM2 with the module's tags as the snapshot, eliminate displaced tags, verify the module on the
    snapshot.  `after_tie` verifies on the estimate after the module's own semantic factors joined
    instead (the counterfactual that shows why the snapshot matters)."""
    from estimation.sf_graphslam import SfGraphSlam
    from lab.studies.slam_sim import RigNoise
    from estimation.tag_elimination import eliminate_tags
    from estimation.verification import verify_module

    slam = SfGraphSlam(model, _slam_config(semantic, RigNoise()))
    rejected: set[int] = set()
    verdicts = {}
    for i, name in enumerate(modules):
        for k, v in enumerate(sv.views):
            if v.step == i:
                slam.add_view(v.reported_structure_T_camera, sv.detections(k))
        snap = slam.update(snapshot=model.module_by_name[name].tags)
        explained = {model.module_by_name[n].tags[1]: model.tags[model.module_by_name[n].tags[1]].structure_T_tag.rotation().matrix()[:, 1]
                     for n in slam.not_deployed()}
        rejected.update(eliminate_tags(slam.tag_estimates(), model, explained_axes=explained).rejected)
        if after_tie:
            snap = {t: (slam.tag_pose(t), slam._marginal(t)) for t in model.module_by_name[name].tags if slam.has_tag(t)}
        est = {t: p for t, (p, _) in snap.items()}
        covs = {t: c for t, (_, c) in snap.items() if c is not None}
        verdicts[name] = verify_module(model, name, est, covariances=covs, rejected=rejected,
                                       not_deployed=slam.not_deployed()).verdict
    return verdicts, slam.tag_estimates()


def study_verification(trials: int, seed: int) -> dict:
    import numpy as np

    from lab.studies import slam_sim as ss
    from lab.core.structures.borg import build_borg

    model = build_borg()
    names = [m.name for m in model.modules]
    last = max(names.index(t) for t in TARGETS)
    modules = names[:last + 1]
    tags = sorted(list(model.turntable.tag_ids) + [t for n in modules for t in model.module_by_name[n].tags])
    cams, steps, present = ss.assembly_path(model, modules)
    rng = np.random.default_rng([seed, STUDIES.index("verification")])
    methods = {"graphslam": (False, False), "sf_graphslam": (True, False), "sf_graphslam_verify_after_tie": (True, True)}
    cases = [("offset", d) for d in OFFSETS_MM] + [("rotation", r) for r in ROTATIONS_DEG]
    flags = {m: {f"{kind}:{size:g}": 0 for kind, size in cases} for m in methods}
    false_flags = {m: 0 for m in methods}
    good_checks = 0
    acc: dict = {}
    for kind, size in cases:
        for trial in range(trials):
            target = TARGETS[trial % len(TARGETS)]
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
            off = (u * size / 1000.0, (0, 0, 0)) if kind == "offset" else ((0, 0, 0), u * math.radians(size))
            faults = ss.StructureFaults(module_offsets={target: off})
            sv = ss.make_survey(model, tags, cams, rng, noise=ss.RigNoise(), faults=faults, steps=steps, present=present)
            for m, (semantic, after) in methods.items():
                t0 = time.perf_counter()
                verdicts, est = _verify_run(model, modules, sv, semantic, after)
                dt = (time.perf_counter() - t0) / len(modules)
                acc.setdefault(m, _Acc()).add(est, sv, dt)
                flags[m][f"{kind}:{size:g}"] += int(verdicts[target] == FLAGGED)
                false_flags[m] += sum(v == FLAGGED for n, v in verdicts.items() if n != target)
            good_checks += len(modules) - 1
    out = _finish(acc)
    for m in methods:
        out[m].update({"noise": "rig", "solve_s_is": "per assembly step (update + elimination + verdict)",
                       "trials_per_case": trials, "targets": list(TARGETS), "modules": len(modules),
                       "flag_rate": {k: v / trials for k, v in flags[m].items()},
                       "false_flag_rate_good_modules": false_flags[m] / max(good_checks, 1)})
    return out


# ---- output -------------------------------------------------------------------------------------------
def _fmt(v) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "–"
        return f"{v:.3g}"
    return str(v)


def study_precision(trials: int, seed: int, args: argparse.Namespace) -> dict:
    from lab.core.executor import open_study

    fingerprint = {"bench": "slam/precision", "seed": seed, "trials": trials,
                   **{k: getattr(args, k, None) for k in ("corner_sigma_px", "sigma_target_mm", "max_views")}}
    with open_study(args, args.out, fingerprint, "lab bench slam --only precision") as runner:
        out = _study_precision(trials, seed, args, runner)
        out["executor"] = runner.describe()
        runner.finish()
    return out


def _study_precision(trials: int, seed: int, args: argparse.Namespace, runner) -> dict:
    """Verdicts near the tolerance and accuracy against the bound (lab/studies/bench_precision.py),
    at the default tolerance and at 1 mm / 0.2 deg."""
    import math
    from dataclasses import replace

    from lab.core.errors import UserError
    from lab.core.survey_budget import check_max_views, check_sigma_target_mm
    from lab.studies import bench_precision as bp

    setup = bp.PrecisionSetup()
    if args.corner_sigma_px is not None:
        if not (math.isfinite(args.corner_sigma_px) and 0 < args.corner_sigma_px <= 5):
            raise UserError(f"--corner-sigma-px must be in (0, 5], got {args.corner_sigma_px}")
        setup = replace(setup, corner_sigma_px=args.corner_sigma_px)
    if args.sigma_target_mm is not None:     # the same ranges as a run's (lab/core/survey_budget.py)
        setup = replace(setup, sigma_target_m=check_sigma_target_mm(args.sigma_target_mm) / 1000)
    if args.max_views is not None:
        setup = replace(setup, max_views=check_max_views(args.max_views))
    tight = replace(setup, tolerance_m=0.001, tolerance_rad=math.radians(0.2))
    out = {"default": bp.study(trials, seed, setup, bp.CASES_DEFAULT, "default", runner),
           "tight": bp.study(trials, seed + 1, tight, bp.CASES_TIGHT, "tight", runner)}
    # the other observation models on the same trials (same seeds), at the default tolerance
    for obs in ("corner-info", "pose"):
        out[f"default-{obs}"] = bp.study(trials, seed, replace(setup, observation=obs), bp.CASES_DEFAULT,
                                         f"default-{obs}", runner)
    out["timing"] = [bp.solve_times(seed, obs, setup) for obs in ("corners", "corner-info", "pose")]
    return out


def to_markdown(res: dict) -> str:
    lines = [f"Command: `{res['command']}` — {res['wall_s']:.0f} s on this machine, seed {res['seed']}.", ""]
    lines.append("Noise (the paper's §3.1): camera view 0.01 m and 0.01° per axis, +10 %/m of distance; camera pose "
                 "0.05 m and 0.01° per axis; 1e-5 m random noise on controls and measurements. Errors are RMS over "
                 "trials and tags of the translation error norm / rotation angle; offsets are the related tag pairs' "
                 "relative poses. `solve_s` is the median solve time.")
    lines.append("")
    studies = res["studies"]
    for study, methods in studies.items():
        if study in ("verification", "precision", "scaling", "speed"):
            continue
        lines.append(f"#### {study}")
        lines.append("")
        noise = next((m.get("noise") for m in methods.values() if m.get("noise")), None)
        if noise:
            lines.append(f"Noise: {noise}.")
            lines.append("")
        lines.append("| method | trans RMSE [m] | rot RMSE [rad] | offset trans RMSE [m] | offset rot RMSE [rad] | solve [s] | notes |")
        lines.append("|---|---|---|---|---|---|---|")
        for name, s in methods.items():
            notes = []
            for key in ("flagged_not_deployed", "relations_untied", "rejected_displaced", "false_rejections",
                        "cost_J_median", "not_converged", "evaluations_mean", "trials"):
                if key in s:
                    notes.append(f"{key} {_fmt(s[key])}")
            lines.append(f"| {name} | {_fmt(s['trans_rmse_m'])} | {_fmt(s['rot_rmse_rad'])} | "
                         f"{_fmt(s['offset_trans_rmse_m'])} | {_fmt(s['offset_rot_rmse_rad'])} | {_fmt(s['solve_s'])} | "
                         f"{', '.join(notes)} |")
        lines.append("")
    if "verification" in studies:
        v = studies["verification"]
        lines.append("#### verification (beyond the paper): flag rate of a module really off its design")
        lines.append("")
        keys = list(v["sf_graphslam"]["flag_rate"])
        lines.append("| method | " + " | ".join(k.replace("offset:", "").replace("rotation:", "") +
                                                 (" mm" if k.startswith("offset") else " deg") for k in keys) +
                     " | false flags (good modules) |")
        lines.append("|---|" + "---|" * (len(keys) + 1))
        for name, s in v.items():
            lines.append(f"| {name} | " + " | ".join(f"{s['flag_rate'][k]:.2f}" for k in keys) +
                         f" | {s['false_flag_rate_good_modules']:.3f} |")
        lines.append("")
        lines.append("Tolerance 5 mm / 1° with a 2σ guard band (estimation/verification.py). Noise: the simulated "
                     "bench's (camera pose 1 mm / 0.05°, tag views drawn from the detector's covariance model), not the "
                     "paper's: its 5 cm camera pose noise is ten times the tolerance. Targets: "
                     + ", ".join(TARGETS) + f", one per trial, assembled in order with the modules before them. "
                     f"Tag RMSE there: SF {v['sf_graphslam']['trans_rmse_m'] * 1000:.2f} mm, "
                     f"GraphSLAM {v['graphslam']['trans_rmse_m'] * 1000:.2f} mm.")
        lines.append("")
    if "scaling" in studies:
        from lab.studies.bench_scaling import markdown as scaling_md

        lines.append("#### scaling: SF-GraphSLAM cost against structure size")
        lines.append("")
        lines.extend(scaling_md(studies["scaling"]))
    if "speed" in studies:
        from lab.studies.bench_scaling import speed_markdown

        lines.append("#### speed: the SLAM step and batch solve against issue 21's targets, with their floors")
        lines.append("")
        lines.extend(speed_markdown(studies["speed"]))
    if "precision" in studies:
        from lab.studies.bench_precision import markdown as precision_md

        lines.append("#### precision: verdicts near the tolerance, accuracy against the bound (corner model)")
        lines.append("")
        lines.extend(precision_md(studies["precision"]))
    lines.extend(_targets_md(res))
    return "\n".join(lines)


def _targets_md(res: dict) -> list[str]:
    st = res["studies"]
    out = ["#### Targets", "", "| target | measured | met |", "|---|---|---|"]
    if "deployable" in st:
        d = st["deployable"]
        r = d["sf_graphslam"]["offset_trans_rmse_m"] / d["graphslam"]["offset_trans_rmse_m"]
        rp = d["paper_powell"]["offset_trans_rmse_m"] / d["paper_powell_graphslam"]["offset_trans_rmse_m"]
        out.append(f"| deployable: SF offset trans RMSE ≤ 0.05 × GraphSLAM's | {r:.4f} (paper's own method here: "
                   f"{rp:.3f}; paper: 0.019–0.029) | {'yes' if r <= 0.05 else 'no'} |")
    if "timing" in res:
        t = res["timing"]
        out.append(f"| full cube batch ≤ 50 ms | LM {t['batch_lm_s_median'] * 1000:.1f} ms median "
                   f"(max {t['batch_lm_s_max'] * 1000:.1f}); with gating + marginals + re-solve "
                   f"{t['batch_with_gating_s_median'] * 1000:.1f} ms | "
                   f"{'yes' if t['batch_with_gating_s_median'] <= 0.05 else ('LM only' if t['batch_lm_s_median'] <= 0.05 else 'no')} |")
        fin = t["isam2_final"]
        out.append(f"| iSAM2 step ≤ 10 ms | median {t['isam2_step_s_median'] * 1000:.1f} ms, p95 "
                   f"{t['isam2_step_s_p95'] * 1000:.1f} ms, max {t['isam2_step_s_max'] * 1000:.1f} ms over the "
                   f"{t['isam2_steps']}-step assembly ({t['assembly_views']} views; at the end tag RMSE "
                   f"{fin['trans_rmse_m'] * 1000:.1f} mm, offsets {fin['offset_trans_rmse_m'] * 1000:.2f} mm, "
                   f"{fin['relations_tied'] // max(fin['trials'], 1)} relations tied, "
                   f"{fin['relations_undecided'] // max(fin['trials'], 1)} undecided) | "
                   f"{'yes' if t['isam2_step_s_p95'] <= 0.01 else ('median' if t['isam2_step_s_median'] <= 0.01 else 'no')} |")
    if "speedup" in res:
        s = res["speedup"]
        lit = "measured" if s["powell_literal_measured_trials"] else "estimated: evaluations × time per evaluation"
        out.append(f"| borg_face1 ≥ 10,000× faster than Powell at equal or lower J | GTSAM (Lie) "
                   f"{s['speedup_gtsam_vs_powell_literal']:,.0f}× vs Powell on the paper's loop-form J ({lit}), "
                   f"{s['speedup_gtsam_vs_powell_vectorised']:,.0f}× vs Powell on our vectorised J; its J is "
                   f"{s['J_rel_diff_gtsam_vs_powell']['median']:+.1e} relative to Powell's (median). GTSAM then "
                   f"Gauss–Newton on the paper's exact residuals: {s['speedup_gtsam_exact_vs_powell_literal']:,.0f}× / "
                   f"{s['speedup_gtsam_exact_vs_powell_vectorised']:,.0f}×, J ≤ Powell's in "
                   f"{s['gtsam_exact_J_le_powell_trials']}/{s['trials']} trials (exact polish inside GTSAM with "
                   f"CustomFactors: {s['speedup_gtsam_euler_vs_powell_literal']:,.0f}×) | "
                   f"{'yes' if s['speedup_gtsam_exact_vs_powell_literal'] >= 1e4 and s['gtsam_exact_J_le_powell_trials'] == s['trials'] else ('Lie form only' if s['speedup_gtsam_vs_powell_literal'] >= 1e4 else 'no')} |")
    if "partial_deploy" in st:
        p = st["partial_deploy"]["sf_graphslam"]
        out.append(f"| partial deployment flagged every trial | {p['flagged_not_deployed']}/{p['trials']} | "
                   f"{'yes' if p['flagged_not_deployed'] == p['trials'] else 'no'} |")
    if "tag_elimination" in st:
        e = st["tag_elimination"]["sf_graphslam"]
        out.append(f"| displaced tag rejected every trial | {e['rejected_displaced']}/{e['trials']} "
                   f"(false rejections {e['false_rejections']}) | "
                   f"{'yes' if e['rejected_displaced'] == e['trials'] else 'no'} |")
    if "precision" in st:
        d, t = st["precision"]["default"], st["precision"]["tight"]
        tm = {x["observation"]: x for x in st["precision"].get("timing", [])}

        def rate(study, kind, size):
            return next((r["flagged_rate"] for r in study["cases"] if r["kind"] == kind and r["size"] == size), None)

        def row(name, value, ok, fmt="{:.1%}"):
            out.append(f"| {name} | {fmt.format(value) if value is not None else 'n/a'} | "
                       f"{'yes' if value is not None and ok(value) else 'no'} |")
        row("precision: 6 mm offset flagged (tol 5 mm) >= 95 %", rate(d, "offset", 6.0), lambda v: v >= 0.95)
        row("precision: 1.5 deg rotation flagged (tol 1 deg) >= 95 %", rate(d, "rotation", 1.5), lambda v: v >= 0.95)
        row("precision: 2 mm offset flagged (tol 1 mm / 0.2 deg) >= 95 %", rate(t, "offset", 2.0), lambda v: v >= 0.95)
        for label, study in (("tol 5 mm", d), ("tol 1 mm", t)):
            g = study["good"]
            row(f"precision: false flags, good modules ({label}) <= 0.5 %", g["false_flag_rate"], lambda v: v <= 0.005,
                "{:.2%}")
        g = d["good"]
        row("precision: good-module position error median <= 0.3 mm", g["position_mm"].get("median"),
            lambda v: v <= 0.3, "{:.3f} mm")
        row("precision: good-module position error max <= 0.6 mm", g["position_mm"].get("max"), lambda v: v <= 0.6,
            "{:.3f} mm")
        row("precision: good-module rotation error median <= 0.1 deg", g["rotation_deg"].get("median"),
            lambda v: v <= 0.1, "{:.3f} deg")
        row("precision: good-module rotation error max <= 0.25 deg", g["rotation_deg"].get("max"), lambda v: v <= 0.25,
            "{:.3f} deg")
        row("precision: achieved RMSE / bound <= 1.3", g["rmse_over_bound"], lambda v: v <= 1.3, "{:.2f}")
        if "corners" in tm:
            row("full-cube batch solve, corner model <= 50 ms", tm["corners"]["batch_ms"], lambda v: v <= 50, "{:.0f} ms")
            row("SLAM step median, corner model <= 10 ms", tm["corners"]["step_median_ms"], lambda v: v <= 10,
                "{:.1f} ms")
        if "corner-info" in tm:
            row("full-cube batch solve, corner-info model <= 50 ms", tm["corner-info"]["batch_ms"], lambda v: v <= 50,
                "{:.1f} ms")
    if "scaling" in st:
        b = st["scaling"]["growth"].get("corner-info", {}).get("batch_ms")
        out.append(f"| scaling: batch solve grows no faster than tags^1.5 (N = 3..8, corner-info) | "
                   f"tags^{b:.2f} | {'yes' if b is not None and b <= 1.5 else 'no'} |" if b is not None else
                   "| scaling: batch solve growth | n/a | no |")
    if "verification" in st:
        v = st["verification"]
        beyond = [k for k in v["sf_graphslam"]["flag_rate"] if (k.startswith("offset") and float(k.split(':')[1]) >= 15)
                  or (k.startswith("rotation") and float(k.split(':')[1]) >= 3)]
        hidden = sum(v["sf_graphslam"]["flag_rate"][k] < v["graphslam"]["flag_rate"][k] for k in v["sf_graphslam"]["flag_rate"])
        out.append(f"| semantic factors never hide a real deviation | SF flag rate below GraphSLAM's in {hidden} of "
                   f"{len(v['sf_graphslam']['flag_rate'])} cases; at 15 mm / 3 deg: "
                   + ", ".join(f"{k} {v['sf_graphslam']['flag_rate'][k]:.2f}" for k in beyond)
                   + f" | {'yes' if hidden == 0 else 'no'} |")
    out.append("")
    return out


def _plots(res: dict, out_dir: str) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    files = []
    st = res["studies"]
    if "scaling" in st:
        from lab.studies.bench_scaling import plot as scaling_plot

        f = scaling_plot(st["scaling"], out_dir)
        if f:
            files.append(f)
    names = [s for s in st if s not in ("verification", "precision", "scaling", "speed")]
    if names:
        methods = ["graphslam", "sf_graphslam", "paper_powell"]
        fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
        for ax, key, label in ((axes[0], "trans_rmse_m", "tag translation RMSE [m]"),
                               (axes[1], "offset_trans_rmse_m", "related-tag offset translation RMSE [m]")):
            w = 0.27
            for i, m in enumerate(methods):
                vals = [st[s].get(m, {}).get(key, math.nan) for s in names]
                ax.bar(np.arange(len(names)) + (i - 1) * w, vals, w, label=m)
            ax.set_yscale("log")
            ax.set_xticks(np.arange(len(names)))
            ax.set_xticklabels(names, rotation=30, ha="right")
            ax.set_ylabel(label)
            ax.grid(axis="y", alpha=0.3)
        axes[0].legend()
        files.append(save_figure(fig, out_dir, "slam_rmse.png"))
    if "timing" in res:
        t = res["timing"]
        fig, ax = plt.subplots(figsize=(7, 3.5))
        y = np.asarray(t["isam2_step_s_by_step_median"]) * 1000
        ax.plot(np.arange(1, len(y) + 1), y, "o-")
        ax.axhline(10, color="r", ls="--", label="target 10 ms")
        ax.set_xlabel("assembly step (module)")
        ax.set_ylabel("iSAM2 update [ms]")
        ax.set_title("borg_full: SF-GraphSLAM update per assembly step (median over runs)")
        ax.legend()
        files.append(save_figure(fig, out_dir, "slam_isam2_steps.png"))
    if "verification" in st:
        v = st["verification"]
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for m in ("graphslam", "sf_graphslam", "sf_graphslam_verify_after_tie"):
            fr = v[m]["flag_rate"]
            for ax, kind in ((axes[0], "offset"), (axes[1], "rotation")):
                ks = [k for k in fr if k.startswith(kind)]
                ax.plot([float(k.split(":")[1]) for k in ks], [fr[k] for k in ks], "o-", label=m)
        axes[0].axvline(5, color="k", ls=":", label="tolerance")
        axes[1].axvline(1, color="k", ls=":")
        axes[0].set_xlabel("module offset [mm]")
        axes[1].set_xlabel("module rotation [deg]")
        for ax in axes:
            ax.set_ylabel("flag rate")
            ax.set_ylim(-0.05, 1.05)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=8)
        files.append(save_figure(fig, out_dir, "slam_verification.png"))
    return files


def _json_safe(v):
    """NaN -> null (strict JSON), numpy scalars -> Python."""
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if hasattr(v, "item") and not isinstance(v, (str, bytes)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def run(args: argparse.Namespace) -> int:
    from lab.core.errors import UserError

    only = list(args.only or DEFAULT_STUDIES)
    if args.trials is not None and args.trials < 1:
        raise UserError(f"--trials must be at least 1, got {args.trials}")
    literal = args.literal_powell if args.literal_powell is not None else (0 if args.quick else 2)
    if literal < 0:
        raise UserError(f"--literal-powell must be >= 0, got {literal}")
    os.makedirs(args.out, exist_ok=True)
    import scipy.special  # noqa: F401  -- the gates' quantiles: load it before anything is timed

    def n(study: str) -> int:
        return args.trials if args.trials is not None else TRIALS[study][1 if args.quick else 0]

    cmd = ("lab bench slam" + (" --quick" if args.quick else "") + "".join(f" --only {s}" for s in (args.only or []))
           + (f" --trials {args.trials}" if args.trials is not None else "")
           + "".join(f" --{k.replace('_', '-')} {getattr(args, k)}" for k in ("corner_sigma_px", "sigma_target_mm",
                                                                             "max_views")
                     if getattr(args, k, None) is not None))
    res: dict = {"studies": {}, "seed": args.seed, "quick": bool(args.quick), "command": cmd}
    t_all = time.perf_counter()
    for study in only:
        t0 = time.perf_counter()
        if study in ("deployable", "closeout_strut", "closeout_square", "partial_deploy"):
            res["studies"][study] = study_pair(study, n(study), args.seed)
        elif study == "borg_face1":
            res["studies"][study], res["speedup"] = study_borg_face1(n(study), args.seed, min(literal, n(study)))
        elif study == "tag_elimination":
            res["studies"][study] = study_tag_elimination(n(study), args.seed)
        elif study == "borg_full":
            res["studies"][study], res["timing"] = study_borg_full(n(study), args.seed)
        elif study == "borg_full_rendered":
            res["studies"][study] = study_borg_full_rendered(n(study), args.seed)
        elif study == "verification":
            res["studies"][study] = study_verification(n(study), args.seed)
        elif study == "precision":
            res["studies"][study] = study_precision(n(study), args.seed, args)
        elif study == "scaling":
            from lab.studies import bench_scaling

            sizes = (3, 4, 5) if args.quick else bench_scaling.SIZES
            res["studies"][study] = bench_scaling.study(sizes, seed=args.seed, max_corner_n=4 if args.quick else 8)
        elif study == "speed":
            from lab.studies import bench_scaling

            res["studies"][study] = bench_scaling.speed(quick=bool(args.quick), seed=args.seed)
        res.setdefault("study_wall_s", {})[study] = time.perf_counter() - t0
    res["wall_s"] = time.perf_counter() - t_all
    md = to_markdown(res)
    res = _json_safe(res)
    with open(os.path.join(args.out, "slam.json"), "w") as f:
        json.dump(res, f, indent=1)
    with open(os.path.join(args.out, "slam.md"), "w") as f:
        f.write(md + "\n")
    plots = _plots(res, args.out)
    if args.json:
        print(json.dumps(res, indent=1))
    else:
        print(md)
        print(f"\nwrote {os.path.join(args.out, 'slam.json')}, slam.md and {len(plots)} plots")
    return 0
