"""`lab bench fiducials`: AprilTag detection, corner accuracy and single-view pose, on rendered
images and on public photographs, against the AprilTag 3 C library where it is installed.

What it measures, on the simulated rig's camera (lab/rigs/sim.toml: 1280x720, f = 914 px, mild
barrel distortion, 2 grey levels of noise, 0.6 px blur) with the BORG tag (10 cm black square):
- time per 1280x720 frame: `TagDetector.detect` on a frame with 20 tags and on a frame with one,
  and the renderer's time for the same frames; ours against AprilTag 3 on the same 20-tag frames
  (`bench_fiducials_photos.timing_study`), and on the photographs (`photo_timing_study`);
- corner error against the renderer's projected truth, noise-free and with the sim's noise, and the
  tilt a single view of a frontal tag at 2 m reads (`bench_fiducials_corners`);
- detection on photographs (tests/data/photos) and rendered frames, each degraded (blur, JPEG,
  rotation, oblique, border-touching, small): recall, false ids and corner error, ours and
  AprilTag 3 side by side (`bench_fiducials_photos`);
- pose error against the ground truth at 0.5, 1, 1.5, 2, 2.5 and 3 m: tags anywhere in the field of
  view, seen from 0-60 deg off their normal, turned at random about it;
- the IPPE ambiguity: how often the wrong one of the two solutions gets through, with no prediction
  and with a predicted pose (the truth disturbed by 3 deg and 2 cm, about what design + kinematics
  give), counted as wrong only when the two solutions differ by more than 1 deg and the other one
  was the closer to the truth;
- covariance honesty: the normalised error e' S^-1 e of each pose against the detector's own
  covariance (6 on average if the covariance is right; larger means over-confident);
- image quality: edge spread across the tags' borders and noise in flat areas, the photographs
  against the default simulated frames (`image_quality`, `bench_fiducials_photos.quality_study`).

Writes fiducials.json, fiducials.md and PNG plots to --out (default bench_out/fiducials) and prints
the Markdown (or the JSON with --json).  Top-level imports stay light: the CLI imports this module
for --help.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

from lab.core.errors import UserError
from lab.studies.bench_common import save_figure
from lab.studies.fiducial_scenes import _camera, random_tag_pose, twenty_tag_frames

DISTANCES_M = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
MAX_VIEW_ANGLE_DEG = 60.0
PRIOR_ROT_DEG = 3.0
PRIOR_TRANS_M = 0.02
DIFFERENT_SOLUTIONS_DEG = 1.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="fewer trials (about 30 s)")
    parser.add_argument("--json", action="store_true", help="print the JSON instead of the Markdown table")
    parser.add_argument("--out", default=os.path.join("bench_out", "fiducials"),
                        help="output directory (default bench_out/fiducials)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--trials", type=int, default=None,
                        help="tag poses per distance (default 200, --quick 40)")
    parser.add_argument("--only", choices=["imaging"], default=None,
                        help="imaging: only the corner error under the sim rig's whole imaging, one effect at a "
                             "time taken away (--frames frames of 6 tags each)")
    parser.add_argument("--frames", type=int, default=None,
                        help="frames of the imaging study (default 300, --quick 20)")


# ---- the camera and the scene (random_tag_pose, tag_pose_on_ray: fiducial_scenes) ----------------
def _ippe_solutions(K, dist, corners, size_m):
    import cv2
    import numpy as np

    from estimation.fiducials import tag_object_points
    from lab.core.geometry import Pose3, Rot3

    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(tag_object_points(size_m), corners, K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    return [Pose3(Rot3(cv2.Rodrigues(r)[0]), np.asarray(t, float).reshape(3)) for r, t in zip(rvecs, tvecs)]


def _perturbed(rng, pose, rot_rad: float, trans_m: float):
    import numpy as np

    from lab.core.geometry import Pose3, Rot3

    w = rng.normal(size=3)
    w *= rot_rad / np.linalg.norm(w)
    d = rng.normal(size=3)
    d *= trans_m / np.linalg.norm(d)
    return pose.compose(Pose3(Rot3.Expmap(w), d))


# ---- studies ------------------------------------------------------------------------------------
def accuracy_study(trials: int, seed: int) -> dict:
    import numpy as np

    from estimation.fiducials import TagDetector
    from lab.core.geometry import Rot3, pose_error
    from sim_devices.render import render_tags

    K, dist, W, H, noise, blur = _camera()
    size = 0.10
    detector = TagDetector(K, dist, {0: size})
    rng = np.random.default_rng([seed, 1])
    rows = []
    for d in DISTANCES_M:
        t_err, r_err, nees, angles = [], [], [], []
        found = wrong = wrong_prior = ambiguous = differ = 0
        for _ in range(trials):
            truth, angle = random_tag_pose(rng, K, W, H, d, size)
            img = render_tags(K, dist, W, H, [(0, size, truth)], blur_sigma_px=blur, noise_sigma=noise, rng=rng)
            dets = detector.detect(img)
            if not dets:
                continue
            det = dets[0]
            found += 1
            et, er = pose_error(det.camera_T_tag, truth)
            t_err.append(et)
            r_err.append(er)
            angles.append(angle)
            xi = truth.localCoordinates(det.camera_T_tag)  # tangent (rot, trans) in the tag frame
            nees.append(float(xi @ np.linalg.solve(det.covariance, xi)))
            ambiguous += det.ambiguous
            sols = _ippe_solutions(K, dist, det.corners_px, size)
            if len(sols) == 2:
                gap = float(np.linalg.norm(Rot3.Logmap(sols[0].rotation().between(sols[1].rotation()))))
                if gap > math.radians(DIFFERENT_SOLUTIONS_DEG):
                    differ += 1
                    errs = [pose_error(s, truth)[1] for s in sols]
                    right = sols[int(np.argmin(errs))]
                    if pose_error(det.camera_T_tag, right)[1] > 1e-6:
                        wrong += 1
                    prior = _perturbed(rng, truth, math.radians(PRIOR_ROT_DEG), PRIOR_TRANS_M)
                    dp = detector.detect(img, predict=lambda tid, p=prior: p)
                    if dp and pose_error(dp[0].camera_T_tag, right)[1] > 1e-6:
                        wrong_prior += 1
        t = np.array(t_err)
        r = np.array(r_err)
        rows.append({
            "distance_m": d,
            "trials": trials,
            "detected": found,
            "trans_err_median_m": float(np.median(t)) if found else None,
            "trans_err_p95_m": float(np.percentile(t, 95)) if found else None,
            "rot_err_median_rad": float(np.median(r)) if found else None,
            "rot_err_p95_rad": float(np.percentile(r, 95)) if found else None,
            "nees_median": float(np.median(nees)) if found else None,
            "nees_mean": float(np.mean(nees)) if found else None,
            "ambiguous_pairs": differ,
            "wrong_solution_no_prior": wrong,
            "wrong_solution_with_prior": wrong_prior,
            "flagged_ambiguous": ambiguous,
            "_t": t.tolist(), "_r": r.tolist(), "_angle": angles,
        })
    return {"rows": rows, "tag_size_m": size, "max_view_angle_deg": MAX_VIEW_ANGLE_DEG}


def timing_study(frames: int, seed: int) -> dict:
    import numpy as np

    from estimation.fiducials import TagDetector
    from sim_devices.render import render_tags

    K, dist, W, H, noise, blur = _camera()
    size = 0.10
    rng = np.random.default_rng([seed, 3])
    detector = TagDetector(K, dist, {i: size for i in range(64)})
    one = []
    for _ in range(frames):
        pose, _ = random_tag_pose(rng, K, W, H, rng.uniform(1.5, 2.5), size, math.radians(40))
        t0 = time.perf_counter()
        img = render_tags(K, dist, W, H, [(0, size, pose)], blur_sigma_px=blur, noise_sigma=noise, rng=rng)
        one.append((img, time.perf_counter() - t0))
    out = {}
    detector.detect(one[0][0])                      # warm caches (the lens's undistortion map)
    for n_tags, scenes in ((1, one), (20, twenty_tag_frames(frames, seed))):
        det_t, n_found = [], []
        for img, _ in scenes:
            t0 = time.perf_counter()
            dets = detector.detect(img)
            det_t.append(time.perf_counter() - t0)
            n_found.append(len(dets))
        out[f"tags_{n_tags}"] = {
            "frames": frames,
            "detect_median_s": float(np.median(det_t)),
            "detect_p95_s": float(np.percentile(det_t, 95)),
            "render_median_s": float(np.median([t for _, t in scenes])),
            "found_mean": float(np.mean(n_found)),
            "tags": n_tags,
        }
    return out


# ---- output -------------------------------------------------------------------------------------
def _markdown(res: dict, command: str) -> str:
    from lab.studies import bench_fiducials_corners as corners
    from lab.studies import bench_fiducials_imaging as imaging
    from lab.studies import bench_fiducials_photos as photos

    acc, tim = res["accuracy"], res["timing"]
    lines = [f"`{command}` ({res['elapsed_s']:.0f} s)", ""]
    lines.append("| frame | tags found | detect + pose, median (p95) | render, median |")
    lines.append("|---|---|---|---|")
    for k, v in tim.items():
        lines.append(f"| 1280x720, {v['tags']} tag(s) | {v['found_mean']:.1f} | {v['detect_median_s'] * 1e3:.1f} ms "
                     f"({v['detect_p95_s'] * 1e3:.1f} ms) | {v['render_median_s'] * 1e3:.1f} ms |")
    lines.append("")
    lines += photos.markdown(res["photos"], res["rendered"], res["timing_vs_apriltag3"])
    lines.append("")
    lines += photos.photo_timing_markdown(res["timing_photos"])
    lines.append("")
    lines += corners.markdown(res["corners"], res["tilt"])
    lines.append("")
    lines += imaging.markdown(res["imaging"])
    lines.append("")
    lines += photos.quality_markdown(res["image_quality"])
    lines.append("")
    lines.append(f"Single-view pose error, {acc['tag_size_m'] * 100:.0f} cm tag anywhere in view, 0-{acc['max_view_angle_deg']:.0f} deg "
                 "off its normal; wrong IPPE solution = the other solution was the closer to the truth "
                 f"(only pairs differing by > {DIFFERENT_SOLUTIONS_DEG:.0f} deg count); prediction = truth disturbed by "
                 f"{PRIOR_ROT_DEG:.0f} deg / {PRIOR_TRANS_M * 100:.0f} cm; NEES = e' S^-1 e against the detector's covariance (6 if honest).")
    lines.append("")
    lines.append("| distance | detected | trans err median / p95 | rot err median / p95 | distinct pairs | wrong, no prediction | wrong, with prediction | NEES median / mean |")
    lines.append("|---|---|---|---|---|---|---|---|")
    for r in acc["rows"]:
        if not r["detected"]:
            lines.append(f"| {r['distance_m']:.1f} m | 0/{r['trials']} | | | | | | |")
            continue
        lines.append(
            f"| {r['distance_m']:.1f} m | {r['detected']}/{r['trials']} | {r['trans_err_median_m'] * 1e3:.1f} / {r['trans_err_p95_m'] * 1e3:.1f} mm "
            f"| {math.degrees(r['rot_err_median_rad']):.2f} / {math.degrees(r['rot_err_p95_rad']):.2f} deg "
            f"| {r['ambiguous_pairs']} | {r['wrong_solution_no_prior']} | {r['wrong_solution_with_prior']} "
            f"| {r['nees_median']:.1f} / {r['nees_mean']:.1f} |")
    return "\n".join(lines) + "\n"


def _plots(res: dict, out_dir: str) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = res["accuracy"]["rows"]
    paths = []
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for r in rows:
        if r["_t"]:
            axes[0].scatter(np.degrees(r["_angle"]), np.array(r["_t"]) * 1e3, s=6, label=f"{r['distance_m']:.1f} m")
            axes[1].scatter(np.degrees(r["_angle"]), np.degrees(r["_r"]), s=6, label=f"{r['distance_m']:.1f} m")
    axes[0].set(xlabel="viewing angle off the tag normal (deg)", ylabel="translation error (mm)", yscale="log")
    axes[1].set(xlabel="viewing angle off the tag normal (deg)", ylabel="rotation error (deg)", yscale="log")
    axes[0].legend(fontsize=7)
    fig.suptitle("Single-view AprilTag pose error on rendered images")
    paths.append(save_figure(fig, out_dir, "fiducials_error.png"))
    return paths


def run(args: argparse.Namespace) -> int:
    from lab.studies import bench_fiducials_corners as corners
    from lab.studies import bench_fiducials_imaging as imaging
    from lab.studies import bench_fiducials_photos as photos

    quick = bool(getattr(args, "quick", False))
    seed = int(getattr(args, "seed", 0) or 0)
    trials = getattr(args, "trials", None) or (40 if quick else 200)
    frames = 10 if quick else 40
    out_dir = getattr(args, "out", None) or os.path.join("bench_out", "fiducials")
    os.makedirs(out_dir, exist_ok=True)
    command = "lab bench fiducials" + (" --quick" if quick else "") + (f" --seed {seed}" if seed else "") + (
        f" --trials {args.trials}" if getattr(args, "trials", None) else "")
    imaging_frames = getattr(args, "frames", None)
    imaging_frames = (20 if quick else 300) if imaging_frames is None else int(imaging_frames)
    if imaging_frames < 1:
        raise UserError(f"--frames must be at least 1, got {imaging_frames}")
    if getattr(args, "only", None) == "imaging":
        command = (f"lab bench fiducials --only imaging --frames {imaging_frames}"
                   + (f" --seed {seed}" if seed else ""))
        t0 = time.perf_counter()
        study = imaging.imaging_study(imaging_frames, seed)
        study["elapsed_s"] = time.perf_counter() - t0
        study["command"] = command
        with open(os.path.join(out_dir, "imaging.json"), "w") as f:
            json.dump(study, f, indent=2)
        print(json.dumps(study, indent=2) if getattr(args, "json", False) else
              "\n".join([f"`{command}` ({study['elapsed_s']:.0f} s)", "", *imaging.markdown(study)]))
        return 0
    t0 = time.perf_counter()
    res = {"command": command, "timing": timing_study(frames, seed),
           "timing_vs_apriltag3": photos.timing_study(frames, seed),
           "timing_photos": photos.photo_timing_study(3 if quick else 7),
           "corners": corners.corner_study(24 if quick else 120, seed),
           "tilt": corners.tilt_study(20 if quick else 100, seed),
           "imaging": imaging.imaging_study(imaging_frames, seed),
           "photos": photos.photo_study(quick),
           "rendered": photos.render_study(2 if quick else 8, seed),
           "accuracy": accuracy_study(trials, seed),
           "image_quality": photos.quality_study(quick)}
    res["elapsed_s"] = time.perf_counter() - t0
    md = _markdown(res, command)
    plots = _plots(res, out_dir)
    public = json.loads(json.dumps(res))
    for r in public["accuracy"]["rows"]:
        for k in [k for k in r if k.startswith("_")]:
            del r[k]
    public["plots"] = plots
    with open(os.path.join(out_dir, "fiducials.json"), "w") as f:
        json.dump(public, f, indent=2)
    with open(os.path.join(out_dir, "fiducials.md"), "w") as f:
        f.write(md)
    print(json.dumps(public, indent=2) if getattr(args, "json", False) else md)
    return 0
