"""`lab bench slam --only precision`: how close verification gets to the physical limit, and what
it decides near the tolerance.

Each trial assembles the BORG cube's first modules up to the three targets (a close-out square
1P, a deployable 2D, a close-out strut 6S) as the procedure measures them: per step, three views
around the new module's face; each sighting enters SF-GraphSLAM as its four corners (corner model,
iSAM2); the module is verified on its own measurement; an `uncertain` verdict takes the next views,
chosen by the information they add about the module (estimation/precision.py), up to the step's
view budget.  One target carries a deviation (offset or rotation, random direction) of the size
the case names; every other module is good.

Measurements are drawn, not rendered: each corner is its true projection plus Gaussian noise of
`corner_sigma_px` face-on, grown with obliquity as the graph's model says (rig_model.side_ratio),
and the camera pose is known to `camera_sigma` per view (a calibrated rig).  So the figures isolate
the estimator and the planning loop; the detector's own error is measured on rendered images
(`lab bench fiducials`) and in real runs (`lab bench calibration --scales 0`, which reports the
same achieved-vs-bound figures from the simulated bench).

Figures per case: flag / uncertain / ok rates of the target; false flags and uncertain verdicts of
the good modules; good-module error against the truth and against the bound (the graph's marginal
linearised at the truth with the true noise); views per step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lab.core.survey_budget import MAX_VIEWS, SIGMA_TARGET_MM
from lab.core.verdicts import FLAGGED, UNCERTAIN, VERDICTS

# offsets (mm) and rotations (deg) around each tolerance, finer near it
CASES_DEFAULT = ([0.0, 4.0, 5.0, 5.5, 6.0, 6.5, 7.0, 8.0, 10.0], [0.5, 0.75, 1.0, 1.25, 1.5, 2.0])
CASES_TIGHT = ([0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0], [0.1, 0.2, 0.3, 0.4])
TARGETS = ("1P", "2D", "6S")


@dataclass(frozen=True)
class PrecisionSetup:
    corner_sigma_px: float = 0.01        # the true face-on corner noise (0.008 measured in simulated runs)
    graph_sigma_px: float = 0.02         # what the graph assumes (a rig's default [verification] corner_sigma_px)
    camera_sigma_m: float = 0.0001
    camera_sigma_rad: float = math.radians(0.005)
    views_per_step: int = 3
    sigma_target_m: float = SIGMA_TARGET_MM * 1e-3   # views are planned until the module's predicted 1-sigma is this
    max_views: int = MAX_VIEWS
    tolerance_m: float = 0.005
    tolerance_rad: float = math.radians(1.0)
    observation: str = "corners"         # how sightings enter the graph (SlamConfig.observation)


def _pool(model, face: int) -> list:
    """Candidate cameras around a face: turntable offsets x platform pitches."""
    from lab.studies import slam_sim as ss

    return [ss.rig_camera(model, math.radians(90.0 * (face - 1) + da), math.radians(p))
            for da in (-30, -24, -18, -12, -6, 0, 6, 12, 18, 24, 30) for p in (-8.0, 0.0, 8.0)]


def _sight(rng, K, cam_true, cam_reported, truth, tags, model, setup: PrecisionSetup,
           occlusion_overlap: float | None = None):
    """Detections (drawn corners) of the `tags` visible from the true camera.  With
    `occlusion_overlap`, a tag a nearer one hides (the survey planner's rule, `survey.unoccluded`)
    is not seen; without it the camera sees through the structure."""
    from lab.studies import slam_sim as ss
    from procedures.survey import unoccluded
    from estimation.fiducials import Detection, tag_object_points
    from estimation.rig_model import MIN_SIDE_RATIO, OBLIQUE_EXPONENT

    seen = []
    for tid in tags:
        size = model.tags[tid].size_m
        if not ss.visible(cam_true, truth[tid], size):
            continue
        c_T_t = cam_true.between(truth[tid])
        pts = (c_T_t.rotation().matrix() @ tag_object_points(size).T).T + c_T_t.translation()
        seen.append((float(pts[:, 2].mean()), tid, (K @ (pts / pts[:, 2:3]).T).T[:, :2]))
    if occlusion_overlap is not None and seen:
        seen.sort(key=lambda s: (s[0], s[1]))
        uv_all = np.array([s[2] for s in seen])
        keep = unoccluded(uv_all.min(axis=1), uv_all.max(axis=1), np.arange(len(seen)), occlusion_overlap)
        seen = [s for s, k in zip(seen, keep) if k]
    out = []
    for _, tid, uv in seen:
        size = model.tags[tid].size_m
        sides = np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1)
        ratio = sides.min() / sides.max()
        if ratio < MIN_SIDE_RATIO:
            continue
        corners = uv + rng.normal(0.0, setup.corner_sigma_px * ratio ** -OBLIQUE_EXPONENT, uv.shape)
        # the detector's single-view pose from the noisy corners (IPPE, the solution nearer the
        # prediction when the other is not clearly worse) and its covariance model, as in a run
        pose = _ippe(K, corners, size, cam_reported.between(truth[tid]))
        side = float(np.mean(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)))
        cov = ss._rig_detector(setup.corner_sigma_px).measurement_covariance(pose, size, side)
        out.append(Detection(tid, corners, pose, cov, 0.1, 10.0, False, size))
    return out


def _ippe(K, corners, size, predicted):
    import cv2

    from estimation.fiducials import tag_object_points
    from lab.core.geometry import Pose3, Rot3

    n, rvecs, tvecs, errs = cv2.solvePnPGeneric(tag_object_points(size), corners.astype(np.float64), K, None,
                                                flags=cv2.SOLVEPNP_IPPE_SQUARE)
    sols = [Pose3(Rot3(cv2.Rodrigues(r)[0]), np.asarray(t, float).ravel()) for r, t in zip(rvecs, tvecs)]
    e = np.asarray(errs, float).ravel()
    if len(sols) == 2 and e[1] < 2.0 * e[0]:
        return min(sols, key=lambda p: float(np.linalg.norm(Rot3.Logmap(p.rotation().between(predicted.rotation())))))
    return sols[0]


def trial(kind: str, size: float, target: str, seed: int, setup: PrecisionSetup, modules: list[str]) -> dict:
    """One assembly with one deviated target; returns per-module verdicts and errors."""
    import gtsam

    from lab.studies import slam_sim as ss
    from estimation.precision import (bound_covariances, covariance_from_information, module_sigma,
                                      view_information)
    from estimation.fiducials import tag_object_points
    from estimation.sf_graphslam import SfGraphSlam, SlamConfig
    from estimation.tag_elimination import eliminate_tags
    from estimation.verification import Tolerance, Tolerances, module_from_tag, verify_module
    from lab.core.geometry import Pose3, Rot3, pose_error
    from lab.core.structures.borg import build_borg

    rng = np.random.default_rng(seed)
    model = build_borg()
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    dev = (u * size / 1000.0, (0, 0, 0)) if kind == "offset" else ((0, 0, 0), u * math.radians(size))
    faults = ss.StructureFaults(module_offsets={target: dev} if size > 0 else {})
    tags_all = list(model.turntable.tag_ids) + [t for n in modules for t in model.module_by_name[n].tags]
    truth = ss.true_tag_poses(model, faults, tags_all)
    K = ss.SIM_K
    cfg = SlamConfig(observation=setup.observation, corner_sigma_px=setup.graph_sigma_px, camera_sigma_m=setup.camera_sigma_m,
                     camera_sigma_rad=setup.camera_sigma_rad)
    slam = SfGraphSlam(model, cfg, camera=(K, np.zeros(5)))
    tol = Tolerance(setup.tolerance_m, setup.tolerance_rad)
    tols = Tolerances(tol, tol, tol)
    cam_cov = np.diag([setup.camera_sigma_rad] * 3 + [setup.camera_sigma_m] * 3) ** 2
    true_cams: list[Pose3] = []
    present = list(model.turntable.tag_ids)
    rejected: set[int] = set()
    out = {}
    for name in modules:
        m = model.module_by_name[name]
        present = present + list(m.tags)
        pool = _pool(model, m.face)
        spec = model.tags[m.tags[0]]
        t_T_m = spec.structure_T_tag.inverse().compose(m.structure_T_module)
        corners = tag_object_points(spec.size_m)

        def pick(info, around: Pose3, candidates: list, n: int, target: float) -> list:
            """Greedy: the candidates that shrink the module's predicted sigma most, until `target`."""
            gains = {i: view_information(candidates[i], around, K, corners, setup.graph_sigma_px, cam_cov)
                     for i in range(len(candidates))}

            def sigma(g):
                cov = covariance_from_information(info + g)
                return math.inf if cov is None else module_sigma(t_T_m, cov).position_m
            chosen = []
            while gains and len(chosen) < n and sigma(np.zeros((6, 6))) > target:
                best = min(gains, key=lambda i: sigma(gains[i]))
                if not gains[best].any():
                    break
                info = info + gains.pop(best)
                chosen.append(candidates[best])
            return chosen
        # the coverage views: the face-on one and 18 deg either side, level; then the views that
        # bring the predicted sigma to the target (the planner's two passes, procedures/survey.py)
        first = [pool[3 * 5 + 1], pool[3 * 2 + 1], pool[3 * 8 + 1]][:setup.views_per_step]
        info0 = sum((view_information(c, spec.structure_T_tag, K, corners, setup.graph_sigma_px, cam_cov) for c in first),
                    np.zeros((6, 6)))
        rest = [c for c in pool if all(c is not f for f in first)]
        queue = first + pick(info0, spec.structure_T_tag, rest, setup.max_views - len(first), setup.sigma_target_m)
        used = list(queue)
        taken = 0
        while True:
            for cam in queue:
                reported = Pose3(Rot3.Expmap(rng.normal(0, setup.camera_sigma_rad, 3)),
                                 rng.normal(0, setup.camera_sigma_m, 3))
                reported = cam.compose(reported)
                slam.add_view(reported, _sight(rng, K, cam, reported, truth, present, model, setup))
                true_cams.append(cam)
                taken += 1
            snap = slam.update(snapshot=m.tags, hold=True)
            rejected.update(eliminate_tags(slam.tag_estimates(), model).rejected)
            est = {t: p for t, (p, _) in snap.items()}
            covs = {t: c for t, (_, c) in snap.items() if c is not None}
            v = verify_module(model, name, est, covariances=covs, rejected=rejected,
                              not_deployed=slam.not_deployed(), tolerances=tols)
            budget = setup.max_views - taken
            if v.verdict != UNCERTAIN or budget <= 0 or not v.tags_used:
                break
            # the next views: most information about the verdict tag, from what the graph knows,
            # aiming at the sigma that clears the band (never looser than the plan's target)
            tag = v.tags_used[0]
            if tag != m.tags[0] or tag not in covs:
                break
            gap = abs(v.deviation_m - setup.tolerance_m) if v.deviation_m is not None else 0.0
            target = min(setup.sigma_target_m, max(gap / (tol.band_sigmas + 0.5), 1e-5))
            rest = [c for c in pool if all(c is not u for u in used)]
            queue = pick(np.linalg.inv(covs[tag]), est[tag], rest, min(2, budget), target) or rest[:0]
            used += queue
            if not queue:
                break
        # the bound: the graph the verdict read, at the truth, with the true noise
        bound = None
        if v.tags_used:
            tag = v.tags_used[0]
            graph = slam.bound_graph(setup.corner_sigma_px)
            values = gtsam.Values()
            for key in graph.keyVector():
                sym = gtsam.Symbol(key)
                values.insert(key, true_cams[sym.index()] if chr(sym.chr()) == "c" else truth[sym.index()])
            try:
                cov_b = bound_covariances(graph, values, [slam.key(tag)])[slam.key(tag)]
                t_T_m = model.tags[tag].structure_T_tag.inverse().compose(m.structure_T_module)
                bound = module_sigma(t_T_m, cov_b)
            except RuntimeError:
                bound = None
        slam.release(m.tags)
        err = None
        if v.estimate is not None and v.tags_used:
            true_module = module_from_tag(model, name, v.tags_used[0], truth[v.tags_used[0]])
            err = pose_error(v.estimate, true_module)
        out[name] = {"verdict": v.verdict, "views": taken, "error_m": err[0] if err else None,
                     "error_rad": err[1] if err else None, "sigma_m": v.sigma_m,
                     "bound_m": bound.position_m if bound else None,
                     "bound_rms_m": bound.position_rms_m if bound else None,
                     "bound_rad": bound.rotation_rad if bound else None}
    return out


def precision_trial(t) -> dict:
    """One `lab.core.executor` trial: (kind, size, target, setup, modules) with the trial's own seed."""
    kind, size, target, setup, modules = t.spec
    return trial(kind, size, target, t.seed, setup, modules)


def study(trials: int, seed: int, setup: PrecisionSetup | None = None, cases=CASES_DEFAULT, label: str = "default",
          runner=None) -> dict:
    """Flag / uncertain rates against deviation size, false flags, accuracy against the bound.
    `runner` (a `lab.core.executor.Study`) runs the trials; without one they run here, one by one."""
    from lab.core.executor import InProcess, make_trials
    from lab.core.structures.borg import build_borg

    setup = setup or PrecisionSetup()
    model = build_borg()
    names = [m.name for m in model.modules]
    modules = names[:max(names.index(t) for t in TARGETS) + 1]
    offsets, rotations = cases
    case_list = [("offset", d) for d in offsets] + [("rotation", r) for r in rotations]
    specs = [(kind, size, TARGETS[k % len(TARGETS)], setup, modules) for kind, size in case_list for k in range(trials)]
    tr = make_trials(seed, f"precision/{label}", specs)
    results = runner.map(precision_trial, tr) if runner is not None else InProcess().map(precision_trial, tr)
    rows = []
    good = {"n": 0, "flagged": 0, "uncertain": 0, "errors_m": [], "errors_rad": [], "bound_rms_m": [],
            "bound_rad": [], "views": []}
    for ci, (kind, size) in enumerate(case_list):
        counts = dict.fromkeys(VERDICTS, 0)
        views = []
        for k in range(trials):
            target = TARGETS[k % len(TARGETS)]
            res = results[ci * trials + k]
            deviated = size > 0
            for name, r in res.items():
                if name == target and deviated:
                    counts[r["verdict"]] += 1
                    views.append(r["views"])
                    continue
                good["n"] += 1
                good["flagged"] += r["verdict"] == FLAGGED
                good["uncertain"] += r["verdict"] == UNCERTAIN
                good["views"].append(r["views"])
                if r["error_m"] is not None:
                    good["errors_m"].append(r["error_m"])
                    good["errors_rad"].append(r["error_rad"])
                if r["bound_rms_m"] is not None:
                    good["bound_rms_m"].append(r["bound_rms_m"])
                    good["bound_rad"].append(r["bound_rad"])
        if size > 0:
            rows.append({"kind": kind, "size": size, "trials": trials,
                         **{f"{v}_rate": c / trials for v, c in counts.items()},
                         "views_median": float(np.median(views)) if views else None})
    e = np.asarray(good["errors_m"])
    er = np.asarray(good["errors_rad"])
    b = np.asarray(good["bound_rms_m"])
    return {"label": label, "observation": setup.observation, "tolerance_mm": setup.tolerance_m * 1000, "tolerance_deg": math.degrees(setup.tolerance_rad),
            "corner_sigma_px": setup.corner_sigma_px, "graph_sigma_px": setup.graph_sigma_px,
            "camera_sigma_mm": setup.camera_sigma_m * 1000, "max_views": setup.max_views, "trials_per_case": trials,
            "cases": rows,
            "good": {"checks": good["n"], "false_flag_rate": good["flagged"] / max(good["n"], 1),
                     "uncertain_rate": good["uncertain"] / max(good["n"], 1),
                     "position_mm": _stats(e * 1000), "rotation_deg": _stats(np.degrees(er)),
                     "position_rmse_mm": float(np.sqrt(np.mean(e ** 2)) * 1000) if len(e) else None,
                     "bound_rms_mm": float(np.sqrt(np.mean(b ** 2)) * 1000) if len(b) else None,
                     "rmse_over_bound": float(np.sqrt(np.mean(e ** 2)) / np.sqrt(np.mean(b ** 2))) if len(b) else None,
                     "views_median": float(np.median(good["views"])) if good["views"] else None}}


def solve_times(seed: int, observation: str, setup: PrecisionSetup | None = None, views_per_step: int = 5,
                repeats: int = 3) -> dict:
    """The whole cube (27 modules, `views_per_step` views each, drawn corners): the iSAM2 step
    (median, max) as a run takes it, and the batch Levenberg-Marquardt solve of the full graph from
    its initial values (min over `repeats`)."""
    import time

    from lab.studies import slam_sim as ss
    from estimation.sf_graphslam import SfGraphSlam, SlamConfig
    from lab.core.geometry import Pose3, Rot3
    from lab.core.structures.borg import build_borg

    setup = setup or PrecisionSetup()
    rng = np.random.default_rng(seed)
    model = build_borg()
    truth = ss.true_tag_poses(model, ss.StructureFaults(), list(model.tags))
    cfg = SlamConfig(observation=observation, corner_sigma_px=setup.graph_sigma_px, camera_sigma_m=setup.camera_sigma_m,
                     camera_sigma_rad=setup.camera_sigma_rad)
    slam = SfGraphSlam(model, cfg, camera=(ss.SIM_K, np.zeros(5)))
    present = list(model.turntable.tag_ids)
    steps = []
    for m in model.modules:
        present += list(m.tags)
        pool = _pool(model, m.face)
        for cam in [pool[3 * 5 + 1], pool[3 * 2 + 1], pool[3 * 8 + 1], pool[3 * 5], pool[3 * 5 + 2]][:views_per_step]:
            reported = cam.compose(Pose3(Rot3.Expmap(rng.normal(0, setup.camera_sigma_rad, 3)),
                                         rng.normal(0, setup.camera_sigma_m, 3)))
            slam.add_view(reported, _sight(rng, ss.SIM_K, cam, reported, truth, present, model, setup))
        t0 = time.perf_counter()
        slam.update(snapshot=m.tags)
        steps.append(time.perf_counter() - t0)
    batch = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        slam.solve_batch()
        batch.append(time.perf_counter() - t0)
    return {"observation": observation, "factors": int(slam.graph.size()), "views": slam.n_views,
            "tags": len(slam.tags), "step_median_ms": float(np.median(steps) * 1000),
            "step_max_ms": float(np.max(steps) * 1000), "batch_ms": float(min(batch) * 1000)}


def _stats(v: np.ndarray) -> dict:
    if not len(v):
        return {}
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(np.max(v)), "n": int(len(v))}


def markdown(res: dict) -> list[str]:
    lines = []
    timing = res.get("timing")
    if timing:
        lines += ["### Solve times, full cube (27 modules, 5 views each, drawn corners)", "",
                  "| observation | factors | iSAM2 step median / max (ms) | batch LM from scratch (ms) |",
                  "|---|---|---|---|"]
        lines += [f"| {t['observation']} | {t['factors']} | {t['step_median_ms']:.1f} / {t['step_max_ms']:.0f} | "
                  f"{t['batch_ms']:.1f} |" for t in timing]
        lines.append("")
    for key, s in res.items():
        if key in ("timing", "executor"):
            continue
        g = s["good"]
        lines += [f"### Precision, {s.get('observation', 'corners')} model, tolerance {s['tolerance_mm']:g} mm / "
                  f"{s['tolerance_deg']:g} deg "
                  f"(corners {s['corner_sigma_px']:g} px, camera {s['camera_sigma_mm']:g} mm, budget {s['max_views']} views, "
                  f"{s['trials_per_case']} trials per case)", "",
                  "| deviation | flagged | uncertain | ok | views (median) |", "|---|---|---|---|---|"]
        for r in s["cases"]:
            unit = "mm" if r["kind"] == "offset" else "deg"
            lines.append(f"| {r['kind']} {r['size']:g} {unit} | {r['flagged_rate']:.1%} | {r['uncertain_rate']:.1%} | "
                         f"{r['ok_rate']:.1%} | {r['views_median']:g} |")
        p, rr = g["position_mm"], g["rotation_deg"]
        lines += ["", f"Good modules ({g['checks']} verdicts): false flags {g['false_flag_rate']:.2%}, uncertain "
                  f"{g['uncertain_rate']:.2%}; position error median {p.get('median', math.nan):.3f} mm, max "
                  f"{p.get('max', math.nan):.3f} mm; rotation median {rr.get('median', math.nan):.3f} deg, max "
                  f"{rr.get('max', math.nan):.3f} deg; RMSE {g['position_rmse_mm']:.3f} mm against a bound of "
                  f"{g['bound_rms_mm']:.3f} mm RMS (ratio {g['rmse_over_bound']:.2f}); views per step "
                  f"{g['views_median']:g} (median).", ""]
    return lines
