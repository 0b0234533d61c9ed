"""Corner accuracy of the detector on rendered images, against the renderer's projected truth, and
the tilt a single view of a frontal tag reads.  Part of `lab bench fiducials`.

Why these two: the pose code (IPPE, the corner reprojection factor) trusts the corners to about
0.1 px; a systematic corner error that depends on where an edge falls within a pixel (its sub-pixel
phase) does not average away over views of a static tag, and a frontal tag's tilt is seen only
through the perspective difference of its near and far edges (hundredths of a pixel at 2 m), so
corner bias turns straight into tilt.

Conditions: the simulated rig's camera (lab/rigs/sim.toml), a 10 cm tag at 1, 2 and 3 m seen
0, 30 and 60 deg off its normal, anywhere in the image, turned at random about its normal (so the
edges' sub-pixel phases are random); noise-free (no pixel noise, the sim's 0.6 px blur) and with
the sim's default noise (2 grey levels).  Metrics per condition, over every corner:
- `rms`: root mean square of the corner error vector [px];
- `radial bias`: the mean error along the tag centre -> corner direction [px] (a detector that
  reads the black square too small or too large shows it here);
- `mean`: length of the mean error vector [px];
- `crlb`: the noise-alone floor for that view (the Cramér-Rao bound of a straight-edge fit of the
  four sides, `corner_crlb_px`), so a noisy rms can be read against what noise allows.
"""

from __future__ import annotations

import math

DISTANCES_M = (1.0, 2.0, 3.0)
ANGLES_DEG = (0.0, 30.0, 60.0)
TAG_SIZE_M = 0.10
TAGS_PER_FRAME = 6          # tags per rendered frame, spread over the image (saves renders)
TILT_DISTANCE_M = 2.0


def _camera():
    from lab.studies.fiducial_scenes import _camera as cam

    return cam()


def _tag_poses(rng, K, W, H, distance_m: float, angle_rad: float, n: int):
    """`n` poses of tags at `distance_m`, each exactly `angle_rad` off its normal (in a random
    direction, turned at random about it), one in each cell of a grid over the image so that they
    do not overlap."""
    import numpy as np

    from lab.studies.fiducial_scenes import tag_pose_on_ray

    cols = 3
    rows = max(1, math.ceil(n / cols))
    reach = K[0, 0] * TAG_SIZE_M / distance_m        # a tag's width with its quiet zone, about
    out = []
    for i in range(n):
        cx = (i % cols + 0.5) * W / cols + rng.uniform(-1, 1) * max(0.0, W / cols / 2 - reach)
        cy = (i // cols + 0.5) * H / rows + rng.uniform(-1, 1) * max(0.0, H / rows / 2 - reach)
        ray = np.linalg.solve(K, [cx, cy, 1.0])
        ray /= np.linalg.norm(ray)
        out.append(tag_pose_on_ray(ray, distance_m, angle_rad, rng.uniform(0, 2 * math.pi),
                                   rng.uniform(0, 2 * math.pi)))
    return out


def corner_crlb_px(side_px: float, contrast: float, noise_sigma: float, blur_sigma_px: float) -> float:
    """Noise-alone floor of a corner's rms error [px] when the corners are intersections of straight
    edges fitted to the image: per unit edge length, the Fisher information about an edge's offset is
    C^2 / sigma^2 * integral(psf^2) (the PSF across the edge: the pixel box and the blur, taken as a
    Gaussian of the same variance); a line of length L fitted with it has variance 4 / (L I) at its
    ends, and a corner, two such lines crossing at about a right angle, twice that."""
    if noise_sigma <= 0:
        return 0.0
    s = math.sqrt(blur_sigma_px ** 2 + 1.0 / 12.0)
    info = contrast ** 2 / noise_sigma ** 2 / (2.0 * math.sqrt(math.pi) * s)
    return math.sqrt(8.0 / (side_px * info))


def corner_study(trials: int, seed: int) -> dict:
    """Corner error against the projected truth, per distance x angle x noise."""
    import numpy as np

    from estimation.fiducials import TagDetector
    from sim_devices.render import render_tags, tag_corners_px

    K, dist, W, H, noise, blur = _camera()
    detector = TagDetector(K, dist, {i: TAG_SIZE_M for i in range(TAGS_PER_FRAME)})
    rows = []
    for noisy in (False, True):
        rng = np.random.default_rng([seed, 11])   # the same poses with and without noise
        for d in DISTANCES_M:
            for a in ANGLES_DEG:
                errs, radial, missed, sides = [], [], 0, []
                for _ in range(max(1, math.ceil(trials / TAGS_PER_FRAME))):
                    poses = _tag_poses(rng, K, W, H, d, math.radians(a), TAGS_PER_FRAME)
                    tags = [(i, TAG_SIZE_M, p) for i, p in enumerate(poses)]
                    img = render_tags(K, dist, W, H, tags, blur_sigma_px=blur, noise_sigma=noise if noisy else 0.0,
                                      rng=rng)
                    found = {det.tag_id: det for det in detector.detect(img)}
                    for i, p in enumerate(poses):
                        truth = tag_corners_px(K, p, TAG_SIZE_M, dist)
                        sides.append(float(np.mean(np.linalg.norm(np.roll(truth, -1, 0) - truth, axis=1))))
                        if i not in found:
                            missed += 1
                            continue
                        e = found[i].corners_px - truth
                        out = truth - truth.mean(axis=0)
                        out /= np.linalg.norm(out, axis=1, keepdims=True)
                        errs.append(e)
                        radial.append(np.sum(e * out, axis=1))
                e = np.concatenate(errs) if errs else np.zeros((0, 2))
                r = np.concatenate(radial) if radial else np.zeros(0)
                side = float(np.mean(sides))
                rows.append({
                    "noise": "default" if noisy else "none", "distance_m": d, "angle_deg": a,
                    "tags": len(errs) + missed, "detected": len(errs), "side_px": side,
                    "rms_px": float(np.sqrt(np.mean(np.sum(e ** 2, axis=1)))) if len(e) else None,
                    "max_px": float(np.max(np.linalg.norm(e, axis=1))) if len(e) else None,
                    "radial_bias_px": float(np.mean(r)) if len(r) else None,
                    "mean_px": float(np.linalg.norm(e.mean(axis=0))) if len(e) else None,
                    # the mean side already carries the foreshortening; the contrast is the
                    # renderer's default black and white levels
                    "crlb_px": corner_crlb_px(side, 200.0, noise if noisy else 0.0, blur),
                })
    return {"rows": rows, "tag_size_m": TAG_SIZE_M, "blur_px": blur, "noise_grey": noise}


def tilt_study(trials: int, seed: int) -> dict:
    """A frontal tag at 2 m near the image centre, at random sub-pixel offsets and turns about its
    normal: the angle between the detected and the true tag normal, from one view.  Three images of
    each pose: the sim's default noise, noise-free, and noise-free without the 8-bit rounding (what
    the edge fit leaves once the sensor's quantisation is taken away)."""
    import numpy as np

    from estimation.fiducials import TagDetector
    from lab.core.geometry import Pose3, Rot3
    from sim_devices.render import render_grey, render_tags

    K, dist, W, H, noise, blur = _camera()
    detector = TagDetector(K, dist, {0: TAG_SIZE_M})
    out = {}
    for kind in ("default", "none", "unrounded"):
        rng = np.random.default_rng([seed, 12])
        tilts, missed = [], 0
        for _ in range(trials):
            x, y = rng.uniform(-0.05, 0.05, size=2)
            t = np.array([x, y, TILT_DISTANCE_M])
            # facing the camera: tag z along -t, turned at random about it
            z = -t / np.linalg.norm(t)
            x0 = np.cross([0.0, 1.0, 0.0], z)
            x0 /= np.linalg.norm(x0)
            y0 = np.cross(z, x0)
            psi = rng.uniform(0, 2 * math.pi)
            xa = math.cos(psi) * x0 + math.sin(psi) * y0
            truth = Pose3(Rot3(np.column_stack([xa, np.cross(z, xa), z])), t)
            tags = [(0, TAG_SIZE_M, truth)]
            if kind == "unrounded":
                grey = render_grey(K, dist, W, H, tags, blur_sigma_px=blur)
                # the detector's candidates come from the rounded image; the fit reads the float one
                ids, quads = detector.find(np.clip(np.rint(grey), 0, 255).astype(np.uint8))
                if not ids:
                    missed += 1
                    continue
                corners, ok = detector.refine(grey, ids, quads)
                n_est = _normal_from_corners(K, dist, corners[0], truth)
            else:
                img = render_tags(K, dist, W, H, tags, blur_sigma_px=blur,
                                  noise_sigma=noise if kind == "default" else 0.0, rng=rng)
                dets = detector.detect(img, predict=lambda tid, p=truth: p)
                if not dets:
                    missed += 1
                    continue
                n_est = dets[0].camera_T_tag.rotation().matrix()[:, 2]
            tilts.append(math.degrees(math.acos(min(1.0, abs(float(n_est @ z))))))
        a = np.array(tilts)
        out[kind] = {
            "trials": trials, "detected": len(tilts),
            "median_deg": float(np.median(a)) if len(a) else None,
            "p95_deg": float(np.percentile(a, 95)) if len(a) else None,
            "max_deg": float(np.max(a)) if len(a) else None,
        }
    return {"distance_m": TILT_DISTANCE_M, "tag_size_m": TAG_SIZE_M, **out}


def _normal_from_corners(K, dist, corners, truth):
    """The tag normal IPPE reads from `corners`, the solution nearer the truth (as a prediction
    would settle it)."""
    import cv2

    from estimation.fiducials import tag_object_points

    n, rvecs, _, _ = cv2.solvePnPGeneric(tag_object_points(TAG_SIZE_M), corners, K, dist,
                                         flags=cv2.SOLVEPNP_IPPE_SQUARE)
    z = truth.rotation().matrix()[:, 2]
    normals = [cv2.Rodrigues(r)[0][:, 2] for r in rvecs[:n]]
    return max(normals, key=lambda v: float(v @ z))


def markdown(corners: dict, tilt: dict) -> list[str]:
    lines = [f"Corner error on rendered images against the projected truth ({corners['tag_size_m'] * 100:.0f} cm tag, "
             f"sim camera, blur {corners['blur_px']:.1f} px; noise: none or the sim's {corners['noise_grey']:.0f} grey "
             "levels); crlb = the noise-alone floor of a straight-edge fit.", "",
             "| noise | distance | angle | side | detected | rms | max | radial bias | mean | crlb |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in corners["rows"]:
        if not r["detected"]:
            lines.append(f"| {r['noise']} | {r['distance_m']:.0f} m | {r['angle_deg']:.0f} deg | {r['side_px']:.0f} px "
                         f"| 0/{r['tags']} | | | | | |")
            continue
        lines.append(f"| {r['noise']} | {r['distance_m']:.0f} m | {r['angle_deg']:.0f} deg | {r['side_px']:.0f} px "
                     f"| {r['detected']}/{r['tags']} | {r['rms_px']:.3f} | {r['max_px']:.3f} | {r['radial_bias_px']:+.3f} "
                     f"| {r['mean_px']:.3f} | {r['crlb_px']:.3f} |")
    lines.append("")
    parts = []
    names = {"none": "noise-free", "default": "default noise", "unrounded": "noise-free without 8-bit rounding"}
    for k in ("none", "unrounded", "default"):
        v = tilt[k]
        if v["detected"]:
            parts.append(f"{names[k]}: median {v['median_deg']:.2f} deg, "
                         f"p95 {v['p95_deg']:.2f} deg, max {v['max_deg']:.2f} deg ({v['detected']}/{v['trials']} detected)")
    lines.append(f"Single-view tilt error of a frontal tag at {tilt['distance_m']:.0f} m (angle between the detected and "
                 "the true normal; random sub-pixel offsets and turns): " + "; ".join(parts) + ".")
    return lines
