"""`lab bench slam --only scaling`: how SF-GraphSLAM's cost grows with the structure, N = 3..8.

Each size is assembled module by module as a run measures it (three views per module, around its
face, 2.2 m out; corners drawn at their true projection plus 0.01 px noise, grown with obliquity;
the camera pose known to 0.1 mm / 0.005 deg), with semantic factors deciding as they become
decidable.  A tag a nearer tag hides is not seen (the survey planner's rule, `survey.unoccluded`;
the rendered camera hides it by painting the nearer tag over it).  Struts hide nothing (as in the
renderer), so a view of a larger structure reads tags further into it: 5.3 tags per view at N = 3,
17 at N = 8 (occlusion takes 0.7 of them).  Measured per size: tags, factors, views; the iSAM2 step (median, max); the marginal the
verdict reads (the new module's tag, per step, median); the batch Levenberg-Marquardt solve of the
whole graph from its initial values.  The growth is fitted as time ∝ tags^b (least squares in
log-log) over the sizes measured.

The camera is placed where it must be to see each module (a simulated survey, not the sim rig's
reach: what the rig can see of larger structures is the procedure's matter, not the estimator's).
"""

from __future__ import annotations

import math
import time

import numpy as np

SIZES = (3, 4, 5, 6, 7, 8)
REPEATS = 3
OCCLUSION = 0.25        # survey.SurveyConfig.occlusion_overlap


def _cameras(model, module) -> list:
    """Three views of a module's first tag: face-on and 0.8 m either side along the face, 2.2 m out."""
    from lab.studies import slam_sim as ss

    tag = model.tags[module.tags[0]].structure_T_tag
    R = tag.rotation().matrix()
    return ss.cameras_around(tag.translation(), R[:, 2], 2.2, [(0, 0, 0), tuple(0.8 * R[:, 0]), tuple(-0.8 * R[:, 0])])


def measure(n: int, observation: str, seed: int) -> dict:
    import gtsam

    from lab.studies import slam_sim as ss
    from lab.studies.bench_precision import PrecisionSetup, _sight
    from estimation.sf_graphslam import SfGraphSlam, SlamConfig
    from lab.core.geometry import Pose3, Rot3
    from lab.core.structures.borg import build_borg

    setup = PrecisionSetup()
    rng = np.random.default_rng([seed, n])
    model = build_borg(n)
    truth = ss.true_tag_poses(model, ss.StructureFaults(), list(model.tags))
    cfg = SlamConfig(observation=observation, corner_sigma_px=setup.graph_sigma_px,
                     camera_sigma_m=setup.camera_sigma_m, camera_sigma_rad=setup.camera_sigma_rad)
    slam = SfGraphSlam(model, cfg, camera=(ss.SIM_K, np.zeros(5)))
    present = list(model.turntable.tag_ids)
    # the turntable tags first, from the four sides: they anchor the structure frame
    for face in range(4):
        cam = ss.rig_camera(model, math.radians(90.0 * face), math.radians(-8.0))
        slam.add_view(cam, _sight(rng, ss.SIM_K, cam, cam, truth, present, model, setup, OCCLUSION))
    slam.update()
    steps, marginals = [], []
    for m in model.modules:
        present += list(m.tags)
        for cam in _cameras(model, m):
            reported = cam.compose(Pose3(Rot3.Expmap(rng.normal(0, setup.camera_sigma_rad, 3)),
                                         rng.normal(0, setup.camera_sigma_m, 3)))
            slam.add_view(reported, _sight(rng, ss.SIM_K, cam, reported, truth, present, model, setup, OCCLUSION))
        t0 = time.perf_counter()
        slam.update()
        steps.append(time.perf_counter() - t0)
        if slam.has_tag(m.tags[0]):
            t0 = time.perf_counter()
            slam.isam.marginalCovariance(slam.key(m.tags[0]))
            marginals.append(time.perf_counter() - t0)
    # the one-off solves are timed REPEATS times and the median kept: one timing of a 10 ms solve
    # on a shared machine moves a fitted exponent by a tenth
    batch_runs, marginal_runs = [], []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        slam.solve_batch()
        batch_runs.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        gtsam.Marginals(slam.graph, slam.estimate)
        marginal_runs.append(time.perf_counter() - t0)
    batch, all_marginals = float(np.median(batch_runs)), float(np.median(marginal_runs))
    return {"n": n, "observation": observation, "modules": len(model.modules), "tags": len(slam.tags),
            "factors": int(slam.graph.size()), "views": slam.n_views,
            "sightings_per_view": sum(slam.observations.values()) / max(slam.n_views, 1),
            "step_median_ms": float(np.median(steps) * 1000), "step_max_ms": float(np.max(steps) * 1000),
            "marginal_median_ms": float(np.median(marginals) * 1000) if marginals else None,
            "batch_ms": batch * 1000, "marginals_factorisation_ms": all_marginals * 1000}


def growth(rows: list[dict], key: str, against: str = "tags") -> float | None:
    """b in time ∝ tags^b (or factors^b), least squares in log-log."""
    pts = [(r[against], r[key]) for r in rows if r.get(key)]
    if len(pts) < 2:
        return None
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def study(sizes=SIZES, observations=("corner-info", "corners"), seed: int = 0, max_corner_n: int = 6) -> dict:
    """`corners` (a Python factor per sighting) stops at `max_corner_n`: past it a batch solve
    takes minutes, which is the finding."""
    out: dict = {"sizes": list(sizes), "rows": {}, "growth": {}}
    for obs in observations:
        rows = [measure(n, obs, seed) for n in sizes if obs != "corners" or n <= max_corner_n]
        out["rows"][obs] = rows
        out["growth"][obs] = {k: growth(rows, k) for k in ("batch_ms", "step_median_ms", "marginal_median_ms",
                                                           "marginals_factorisation_ms", "factors")}
        out["growth"][obs]["batch_vs_factors"] = growth(rows, "batch_ms", against="factors")
    return out


def markdown(res: dict) -> list[str]:
    lines = ["| model | N | modules | tags | factors | views | tags per view | iSAM2 step median / max (ms) | "
             "verdict marginal (ms) | batch LM (ms) | all marginals (ms) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for obs, rows in res["rows"].items():
        for r in rows:
            lines.append(f"| {obs} | {r['n']} | {r['modules']} | {r['tags']} | {r['factors']} | {r['views']} | "
                         f"{r['sightings_per_view']:.1f} | {r['step_median_ms']:.1f} / {r['step_max_ms']:.0f} | {r['marginal_median_ms']:.2f} | "
                         f"{r['batch_ms']:.0f} | {r['marginals_factorisation_ms']:.0f} |")
    lines.append("")
    for obs, g in res["growth"].items():
        parts = [f"{k.replace('_ms', '')} ∝ tags^{v:.2f}" for k, v in g.items()
                 if v is not None and k != "batch_vs_factors"]
        if g.get("batch_vs_factors") is not None:
            parts.append(f"batch ∝ factors^{g['batch_vs_factors']:.2f}")
        lines.append(f"Growth, {obs}: " + ", ".join(parts) + ".")
    lines.append("")
    return lines


def plot(res: dict, out_dir: str) -> str | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    from lab.studies.bench_common import save_figure

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for obs, rows in res["rows"].items():
        tags = [r["tags"] for r in rows]
        for key, style in (("batch_ms", "o-"), ("step_median_ms", "s--"), ("marginals_factorisation_ms", "^:")):
            ax.loglog(tags, [r[key] for r in rows], style, label=f"{obs}: {key.replace('_ms', '')}")
    t = np.array([min(r["tags"] for rows in res["rows"].values() for r in rows),
                  max(r["tags"] for rows in res["rows"].values() for r in rows)], float)
    ax.loglog(t, 5.0 * (t / t[0]) ** 1.5, "k-", lw=0.6, label="∝ tags^1.5")
    ax.set_xlabel("tags in the graph")
    ax.set_ylabel("time [ms]")
    ax.set_title("SF-GraphSLAM cost against structure size (N = 3..8)")
    ax.legend(fontsize=7)
    return save_figure(fig, out_dir, "slam_scaling.png")
