"""`lab bench slam --only scaling`: how SF-GraphSLAM's cost grows with the structure, N = 3..8.

Each size is assembled module by module as a run measures it (three views per module, around its
face, 2.2 m out; corners drawn at their true projection plus 0.01 px noise, grown with obliquity;
the camera pose known to 0.1 mm / 0.005 deg), with semantic factors deciding as they become
decidable.  A tag a nearer tag hides is not seen (the survey planner's rule, `survey.unoccluded`;
the rendered camera hides it by painting the nearer tag over it).  Struts hide nothing (as in the
renderer), so a view of a larger structure reads tags further into it: 5.3 tags per view at N = 3,
17 at N = 8 (occlusion takes 0.7 of them); as in a run, the graph takes the sightings of the
module's own tags and of the rig's `near_tags_per_view` (5) other tags nearest it
(`estimation.sightings`).  Measured per size: tags, factors, views; the step as
a run takes it (the round's solve with the module's tags held for its verdict, then their release
once it is final: median, max); the marginal the verdict reads (the new module's tag, after the
solve, per step, median); the batch Levenberg-Marquardt solve of the whole graph from its initial
values.  The growth is fitted as time ∝ tags^b (least squares in log-log) over the sizes measured.

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


class _TimedISAM2:
    """iSAM2 with its `update` calls timed: how much of a step is the solver itself (elimination,
    and linearising the factors it touches), and how much is the estimator's bookkeeping around it."""

    def __init__(self, isam) -> None:
        self._isam = isam
        self.seconds = 0.0
        self.reeliminated = 0          # variables the updates re-eliminated (the tree from the touched keys up)

    def update(self, *args, **kwargs):
        t0 = time.perf_counter()
        try:
            result = self._isam.update(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - t0
        self.reeliminated += result.getVariablesReeliminated()
        return result

    def __getattr__(self, name: str):
        return getattr(self._isam, name)


def measure(n: int, observation: str, seed: int, near_tags_per_view: int | None = None, batch: bool = True) -> dict:
    """One size's survey, timed (the module's docstring); without `batch` the one-off batch solve
    and marginals are not timed (minutes with the Python corner factor at N = 8)."""
    import gtsam

    from estimation.sightings import near_sightings
    from lab.core.config import VerificationConfig

    from lab.studies import slam_sim as ss
    from lab.studies.bench_precision import PrecisionSetup, _sight
    from estimation.sf_graphslam import SfGraphSlam, SlamConfig
    from lab.core.geometry import Pose3, Rot3
    from lab.core.structures.borg import build_borg

    setup = PrecisionSetup()
    # what a run's view gives the graph: the module's tags and the rig's nearest others
    near = VerificationConfig().near_tags_per_view if near_tags_per_view is None else near_tags_per_view
    rng = np.random.default_rng([seed, n])
    model = build_borg(n)
    truth = ss.true_tag_poses(model, ss.StructureFaults(), list(model.tags))
    cfg = SlamConfig(observation=observation, corner_sigma_px=setup.graph_sigma_px,
                     camera_sigma_m=setup.camera_sigma_m, camera_sigma_rad=setup.camera_sigma_rad)
    slam = SfGraphSlam(model, cfg, camera=(ss.SIM_K, np.zeros(5)))
    timed = slam.isam = _TimedISAM2(slam.isam)
    present = list(model.turntable.tag_ids)
    # the turntable tags first, from the four sides: they anchor the structure frame
    for face in range(4):
        cam = ss.rig_camera(model, math.radians(90.0 * face), math.radians(-8.0))
        slam.add_view(cam, _sight(rng, ss.SIM_K, cam, cam, truth, present, model, setup, OCCLUSION))
    slam.update()
    steps, solver, marginals, reeliminated = [], [], [], []
    read = sum(slam.observations.values())       # sightings the views read (the graph takes the near ones)
    for m in model.modules:
        present += list(m.tags)
        for cam in _cameras(model, m):
            reported = cam.compose(Pose3(Rot3.Expmap(rng.normal(0, setup.camera_sigma_rad, 3)),
                                         rng.normal(0, setup.camera_sigma_m, 3)))
            seen = _sight(rng, ss.SIM_K, cam, reported, truth, present, model, setup, OCCLUSION)
            read += len(seen)
            slam.add_view(reported, near_sightings(model, m.name, seen, near))
        # the run's step (procedures/borg_measure.py): the round's solve with the module's tags
        # held for its verdict (they end in the Bayes tree's root, and the snapshot's marginals
        # are read there), then its release once the verdict is final (its relations tied)
        timed.seconds = 0.0
        timed.reeliminated = 0
        t0 = time.perf_counter()
        slam.update(snapshot=m.tags, hold=True)
        step = time.perf_counter() - t0
        if slam.has_tag(m.tags[0]):
            t0 = time.perf_counter()
            slam.isam.marginalCovariance(slam.key(m.tags[0]))
            marginals.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        slam.release(m.tags)
        steps.append(step + time.perf_counter() - t0)
        solver.append(timed.seconds)
        reeliminated.append(timed.reeliminated)
    # the one-off solves are timed REPEATS times and the median kept: one timing of a 10 ms solve
    # on a shared machine moves a fitted exponent by a tenth
    batch_runs, marginal_runs = [], []
    for _ in range(REPEATS if batch else 0):
        t0 = time.perf_counter()
        slam.solve_batch()
        batch_runs.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        gtsam.Marginals(slam.graph, slam.estimate)
        marginal_runs.append(time.perf_counter() - t0)
    batch_s = float(np.median(batch_runs)) * 1000 if batch_runs else None
    # the first solve also builds the batch's view factors (`SfGraphSlam._batch_graph`: the corner
    # model's per-view factors, kept for later solves): a one-off solve costs that, reported beside
    batch_first = batch_runs[0] * 1000 if batch_runs else None
    all_marginals = float(np.median(marginal_runs)) * 1000 if marginal_runs else None
    return {"n": n, "observation": observation, "modules": len(model.modules), "tags": len(slam.tags),
            "factors": int(slam.graph.size()), "views": slam.n_views,
            "sightings_per_view": sum(slam.observations.values()) / max(slam.n_views, 1),
            "read_per_view": read / max(slam.n_views, 1), "near_tags_per_view": near,
            "step_median_ms": float(np.median(steps) * 1000), "step_max_ms": float(np.max(steps) * 1000),
            # the iSAM2 update calls alone within each step (with a Python factor, its callbacks too)
            "solver_median_ms": float(np.median(solver) * 1000), "solver_max_ms": float(np.max(solver) * 1000),
            "marginal_median_ms": float(np.median(marginals) * 1000) if marginals else None,
            # variables a step's updates re-eliminate, median over each quarter of the survey: how
            # the step's work grows as the structure does
            "reeliminated_by_quarter": [float(np.median(q)) for q in np.array_split(np.array(reeliminated, float), 4)
                                        if len(q)],
            "batch_ms": batch_s, "batch_first_ms": batch_first, "marginals_factorisation_ms": all_marginals}


def growth(rows: list[dict], key: str, against: str = "tags") -> float | None:
    """b in time ∝ tags^b (or factors^b), least squares in log-log."""
    pts = [(r[against], r[key]) for r in rows if r.get(key)]
    if len(pts) < 2:
        return None
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def study(sizes=SIZES, observations=("corner-info", "corners"), seed: int = 0, max_corner_n: int = 6) -> dict:
    """`corners` (the run's Python corner factor) stops at `max_corner_n` (`lab bench slam --only
    scaling`: 8 since stop 43, whose batch takes ~0.5 s at N = 8; it was minutes before the batch
    took one factor a view and its callbacks stopped copying the values: docs/benchmarks.md,
    "Speed")."""
    out: dict = {"sizes": list(sizes), "rows": {}, "growth": {}}
    for obs in observations:
        rows = [measure(n, obs, seed) for n in sizes if obs != "corners" or n <= max_corner_n]
        out["rows"][obs] = rows
        out["growth"][obs] = {k: growth(rows, k) for k in ("batch_ms", "step_median_ms", "marginal_median_ms",
                                                           "marginals_factorisation_ms", "factors")}
        out["growth"][obs]["batch_vs_factors"] = growth(rows, "batch_ms", against="factors")
    return out


def markdown(res: dict) -> list[str]:
    lines = ["| model | N | modules | tags | factors | views | tags per view (read / in the graph) | step median / max (ms) | "
             "verdict marginal (ms) | batch LM (ms) | all marginals (ms) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for obs, rows in res["rows"].items():
        for r in rows:
            lines.append(f"| {obs} | {r['n']} | {r['modules']} | {r['tags']} | {r['factors']} | {r['views']} | "
                         f"{r['read_per_view']:.1f} / {r['sightings_per_view']:.1f} | {r['step_median_ms']:.1f} / {r['step_max_ms']:.0f} | {r['marginal_median_ms']:.2f} | "
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


# ---- `lab bench slam --only speed`: the speed figures beside their targets and floors ----
# (median ms, max ms) of a step; ms of a batch solve (issue 21's targets)
SPEED_TARGETS = {"step": {3: (2.0, 10.0), 8: (10.0, 100.0)}, "batch": {3: 20.0, 8: 200.0}}


def linearisation_costs(repeats: int = 300) -> dict[str, float]:
    """Microseconds per linearisation of one factor, median of `repeats` linearisations of a graph
    of 20 copies: the run's two Python factors (the corner factor with fixed intrinsics, print
    scale and lens term, its arithmetic compiled; the kinematic chain), a Python factor with the
    corner factor's keys that computes nothing (the floor of a Python callback), against the C++
    factors a compiled model would use (a BetweenFactorPose3, the corner-info factor's type; four
    GenericProjectionFactorCal3_S2, one tag's corners)."""
    import gtsam

    from estimation.fiducials import tag_object_points
    from estimation.rig_model import (AXIS, BASE, DISTORTION, MOUNT, RigGeometry, ViewMotion, cal3_s2, chain_factor,
                                      corner_factor, radial_basis)
    from lab.core.config import load_rig
    from lab.core.geometry import Pose3, Rot3
    from lab.core.structures.borg import build_borg
    from lab.studies import slam_sim as ss

    C, T, S, P = (gtsam.symbol_shorthand.C, gtsam.symbol_shorthand.T, gtsam.symbol_shorthand.S,
                  gtsam.symbol_shorthand.P)
    cal = cal3_s2(ss.SIM_K)
    tag = Pose3(Rot3.RzRyRx(math.pi / 2, 0.0, -math.pi / 2), np.array([0.0, 0.2, 0.6]))
    cam = tag.compose(Pose3(Rot3.RzRyRx(math.pi, 0.2, 0.0), np.zeros(3))).compose(Pose3(Rot3(), np.array([0.0, 0.0, -2.0])))
    local = tag_object_points(0.1)
    pinhole = gtsam.PinholeCameraCal3_S2(cam, cal)
    uv = np.array([pinhole.project(tag.transformFrom(p)) for p in local])
    model = build_borg(3)
    geometry = RigGeometry.from_rig(load_rig(), model.world_T_structure(0.0), ss.SIM_K)
    motion = ViewMotion(0.3, (0.0, 0.0, 0.0, 0.0, 0.1, 0.0))
    values = gtsam.Values()
    for key, value in ((C(0), cam), (T(0), tag), (AXIS, Pose3()), (BASE, geometry.nominal_world_T_base),
                       (MOUNT, geometry.nominal_platform_T_camera)):
        values.insert(key, value)
    values.insert(S(0), np.zeros(1))
    values.insert(DISTORTION, np.zeros(2))
    for i, p in enumerate(local):
        values.insert(P(i), tag.transformFrom(p))
    noise6 = gtsam.noiseModel.Isotropic.Sigma(6, 0.01)
    noise2 = gtsam.noiseModel.Isotropic.Sigma(2, 0.02)
    noise8 = gtsam.noiseModel.Isotropic.Sigma(8, 0.02)
    nothing_e, nothing_J = np.zeros(8), [np.zeros((8, 6)), np.zeros((8, 6)), np.zeros((8, 1)), np.zeros((8, 2))]

    def _nothing(this, values, jacobians):
        if jacobians is not None:
            jacobians[0], jacobians[1], jacobians[2], jacobians[3] = nothing_J
        return nothing_e

    makers = {
        "corner factor (Python callback, compiled arithmetic)": lambda: [corner_factor(C(0), T(0), uv, local, 0.02, robust_k=3.0, fixed=cal,
                                                         scale_key=S(0), distortion=(DISTORTION, radial_basis(uv, ss.SIM_K)))],
        "chain factor (Python)": lambda: [chain_factor(geometry, motion, C(0))],
        # the floor of any Python factor: GTSAM's call into Python and back, the factor's own work nil
        "a Python factor that does nothing": lambda: [gtsam.CustomFactor(
            noise8, [C(0), T(0), S(0), DISTORTION], _nothing)],
        "BetweenFactorPose3 (C++)": lambda: [gtsam.BetweenFactorPose3(C(0), T(0), cam.between(tag), noise6)],
        "4 x GenericProjectionFactorCal3_S2 (C++)": lambda: [gtsam.GenericProjectionFactorCal3_S2(
            gtsam.Point2(*uv[i]), noise2, C(0), P(i), cal) for i in range(4)],
    }
    out = {}
    for name, make in makers.items():
        graph = gtsam.NonlinearFactorGraph()
        for _ in range(20):
            for f in make():
                graph.add(f)
        runs = []
        for _ in range(max(repeats // 20, 5)):
            t0 = time.perf_counter()
            graph.linearize(values)
            runs.append((time.perf_counter() - t0) / 20)
        out[name] = float(np.median(runs) * 1e6)
    return out


def speed(quick: bool = False, seed: int = 0) -> dict:
    """The speed figures of issue 21 on the scaling study's surveys (`measure`): a 3x3x3 run and
    an 8x8x8 study (N = 5 with `quick`), each step and the full batch solve in the run's own
    observation model (`corners`: the Python corner factor, one factor a view in the batch) and in
    `corner-info` (every factor in C++: the floor compiled factors would reach,
    bookkeeping included); the iSAM2 update alone (`solver_*`) is the floor without the
    estimator's Python bookkeeping around it."""
    large = 5 if quick else 8
    rows = [_median_survey(3, seed, SMALL_SURVEYS), measure(3, "corner-info", seed),
            measure(large, "corner-info", seed), measure(large, "corners", seed)]
    return {"rows": rows, "large_n": large, "linearisation_us": linearisation_costs()}


# the 3x3x3 survey in the run's model is ~80 steps of ~2 ms: one survey's median moves by 10-20 %
# from run to run on this machine, as much as the distance to its target, so it is surveyed
# SMALL_SURVEYS times (the same seed: the same graph) and the survey with the median step median kept
SMALL_SURVEYS = 5


def _median_survey(n: int, seed: int, surveys: int) -> dict:
    """`measure(n, "corners", seed)` `surveys` times; the row of the survey whose step median is
    the median, with every survey's step median (`step_median_ms_surveys`) beside it."""
    rows = [measure(n, "corners", seed, batch=(i == 0)) for i in range(surveys)]
    order = sorted(range(surveys), key=lambda i: rows[i]["step_median_ms"])
    row = dict(rows[order[surveys // 2]], batch_ms=rows[0]["batch_ms"], batch_first_ms=rows[0]["batch_first_ms"])
    row["step_median_ms_surveys"] = [rows[i]["step_median_ms"] for i in order]
    return row


def speed_markdown(res: dict) -> list[str]:
    by = {(r["n"], r["observation"]): r for r in res["rows"]}
    large = res["large_n"]
    lines = ["| figure | target | run's model (`corners`) | all factors in C++ (`corner-info`) | iSAM2 update alone (`corner-info`) | met |",
             "|---|---|---|---|---|---|"]
    for n in (3, large):
        target = SPEED_TARGETS["step"].get(n)
        run, cpp = by.get((n, "corners")), by[(n, "corner-info")]
        tgt = f"≤ {target[0]:g} / ≤ {target[1]:g}" if target else "(targets at N = 3 and 8)"
        run_s = f"{run['step_median_ms']:.1f} / {run['step_max_ms']:.0f}" if run else "not run"
        if run and run.get("step_median_ms_surveys"):
            spread = run["step_median_ms_surveys"]
            run_s += f" (the median of {len(spread)} surveys: {spread[0]:.1f}-{spread[-1]:.1f})"
        met = "–"
        if target and run:
            met = "yes" if run["step_median_ms"] <= target[0] and run["step_max_ms"] <= target[1] else "**no**"
        elif target:
            met = ("C++ model only" if cpp["step_median_ms"] <= target[0] and cpp["step_max_ms"] <= target[1] else "**no**")
        lines.append(f"| step, {n}×{n}×{n}, median / max (ms) | {tgt} | {run_s} | {cpp['step_median_ms']:.1f} / "
                     f"{cpp['step_max_ms']:.0f} | {cpp['solver_median_ms']:.1f} / {cpp['solver_max_ms']:.0f} | {met} |")
    for n in (3, large):
        target = SPEED_TARGETS["batch"].get(n)
        run, cpp = by.get((n, "corners")), by[(n, "corner-info")]
        met = "–"
        if target:
            # judged on the first solve, which builds the view factors: what a one-off batch costs
            first = run and (run.get("batch_first_ms") if run.get("batch_first_ms") is not None else run["batch_ms"])
            met = ("yes" if first is not None and first <= target else
                   ("C++ model only" if cpp["batch_ms"] <= target else "**no**"))
        run_s = "not run"
        if run and run["batch_ms"] is not None:
            run_s = f"{run['batch_ms']:.0f}"
            if run.get("batch_first_ms") is not None:
                run_s += f" (the first solve, building its view factors: {run['batch_first_ms']:.0f})"
        lines.append(f"| full batch LM, {n}×{n}×{n} (ms) | {'≤ %g' % target if target else '–'} | {run_s} | "
                     f"{cpp['batch_ms']:.0f} | – | {met} |")
    lines.append("")
    lines.append("Variables a step's updates re-eliminate, median by quarter of the survey: " + "; ".join(
        f"{r['n']}×{r['n']}×{r['n']} `{r['observation']}` " + " / ".join(f"{x:.0f}" for x in r["reeliminated_by_quarter"])
        for r in res["rows"] if r.get("reeliminated_by_quarter")) + ".")
    lines.append("One factor's linearisation (µs, median): " + ", ".join(
        f"{k} {v:.1f}" for k, v in res["linearisation_us"].items()) + ".")
    lines.append("")
    return lines
