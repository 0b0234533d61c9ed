"""Corner error under the simulated default camera's whole imaging, with one effect at a time taken
away.  Part of `lab bench fiducials`.

Why: the run's graph reads thousands of corners of the same tags from many views; a corner error
that is the same in every sighting of a part of the frame does not average away, and the graph
takes it for a property of the rig it can solve for (a focal length, a mount), ever more sure of
it the more views it has.  The corner study (`bench_fiducials_corners`) renders a plain camera; this
one renders the sim rig's (lab/rigs/sim.toml: read and shot noise, blur and depth of field,
vignetting and uneven light, each tag's bow, JPEG), through `SimWorld`'s own camera and tags, and
measures each corner against the renderer's projected truth.

Conditions: the default camera; without vignetting and uneven light; without the tags' bow;
noise-free (no read or shot noise, no JPEG); noise-free and without light or bow (the ideal
camera's floor).  Scenes: 6 tags a frame (the structure's 10 cm tags, printed as the world prints
them), each at 1.5-3.5 m (uniform), seen up to 60 deg off its normal, anywhere in the frame.  The
same poses and noise draws in every condition.  Metrics:
- `rms`: corner error (px), and near (1.5-2.5 m) / far (2.5-3.5 m);
- `outward`: the mean error along the direction from the principal point (px), in the frame's
  inner half and outer half (normalised radius under / over 0.4): a field the graph can read as a
  focal length;
- `focal`: its least-squares slope on the normalised radius (px: the focal length change the field
  mimics) with its standard error;
- `size near / far`: the mean error along each corner's direction from its tag's centre, over the
  tag's mean side (relative, 1e-4): a tag read large or small the same way at a distance, which a
  tag's print-scale variable cannot take up across views at different distances.
"""

from __future__ import annotations

import math
from typing import Any

CONDITIONS: dict[str, dict[str, Any]] = {
    "default": {},
    "no vignetting or uneven light": {"camera": {"vignetting": 0.0, "lighting_variation": 0.0}},
    "no bow": {"tags": {"flatness_m": 0.0}},
    "noise-free": {"camera": {"pixel_noise": 0.0, "full_well_e": 0, "jpeg_quality": 0}},
    "noise-free, no light or bow": {"camera": {"pixel_noise": 0.0, "full_well_e": 0, "jpeg_quality": 0,
                                               "vignetting": 0.0, "lighting_variation": 0.0},
                                    "tags": {"flatness_m": 0.0}},
}
TAGS_PER_FRAME = 6
DISTANCE_M = (1.5, 3.5)
MIN_APART_PX = 120.0


def _sightings(condition: dict[str, Any], frames: int, seed: int) -> list[dict[str, Any]]:
    import cv2
    import numpy as np

    from estimation.fiducials import TagDetector
    from lab.core.config import load_rig
    from lab.core.scenario import parse_scenario
    from lab.studies.fiducial_scenes import random_tag_pose
    from sim_devices.camera import encode_frame
    from sim_devices.render import render_tags, tag_corners_px
    from sim_devices.world import SimWorld

    world = SimWorld(load_rig(), parse_scenario({"seed": seed, **condition}), borg_n=3)
    cam = world.camera
    assert cam is not None and world.borg is not None
    ids = sorted(world.borg.model.tags)[:40]
    detector = TagDetector(cam.nominal_K, cam.nominal_dist, {t: world.borg.model.tags[t].size_m for t in ids})
    rng = np.random.default_rng([seed, 99])          # poses: the same in every condition
    noise = np.random.default_rng([seed, 7])         # and the noise draws
    out = []
    for _ in range(frames):
        placed: list[tuple[int, Any, float]] = []
        centres: list[np.ndarray] = []
        for t in rng.choice(ids, TAGS_PER_FRAME, replace=False):
            d = rng.uniform(*DISTANCE_M)
            size = world.borg.model.tags[int(t)].size_m
            while True:          # tags apart in the frame, so none hides another
                pose, _ = random_tag_pose(rng, cam.K, cam.width_px, cam.height_px, d, size)
                c = tag_corners_px(cam.K, pose, size, cam.dist).mean(axis=0)
                if all(np.linalg.norm(c - other) > MIN_APART_PX for other in centres):
                    break
            placed.append((int(t), pose, d))
            centres.append(c)
        img = render_tags(cam.K, cam.dist, cam.width_px, cam.height_px,
                          [(t, world.printed_size_m(t), p) for t, p, _ in placed], blur_sigma_px=cam.blur_px,
                          noise_sigma=cam.pixel_noise, rng=np.random.default_rng(noise.integers(2**62)),
                          defocus=cam.defocus(), looks={t: world.tag_look(t) for t, _, _ in placed}, gain=world.gain_map(),
                          full_well_e=cam.imaging.full_well_e)
        if cam.jpeg_quality > 0:
            buf, _ = encode_frame(img, cam.jpeg_quality)
            img = cv2.imdecode(np.frombuffer(buf, np.uint8), cv2.IMREAD_COLOR)
        found = {d.tag_id: d for d in detector.detect(img)}
        for t, p, d in placed:
            if t in found:
                out.append({"distance_m": d, "truth": tag_corners_px(cam.K, p, world.printed_size_m(t), cam.dist),
                            "corners": found[t].corners_px})
    return out


def metrics(sightings: list[dict[str, Any]], K) -> dict[str, Any]:
    """The condition's figures from its sightings (see the module's docstring)."""
    import numpy as np

    T = np.array([s["truth"] for s in sightings]).reshape(-1, 4, 2)
    E = np.array([s["corners"] for s in sightings]).reshape(-1, 4, 2) - T
    d = np.array([s["distance_m"] for s in sightings])
    v = T - np.asarray(K)[:2, 2]
    r = np.linalg.norm(v, axis=2)
    rn = r / float(np.asarray(K)[0, 0])
    out_err = np.sum(E * v / np.maximum(r, 1e-9)[..., None], axis=2)
    rms = lambda e: float(np.sqrt(np.mean(np.sum(e ** 2, axis=-1)))) if e.size else None  # noqa: E731
    near, far = d < 2.5, d >= 2.5
    x, y = rn.ravel(), out_err.ravel()
    slope = float(np.sum(x * y) / np.sum(x * x)) if x.size else None
    resid = y - (slope or 0.0) * x
    se = float(np.sqrt(np.sum(resid ** 2) / max(len(x) - 1, 1) / np.sum(x * x))) if x.size else None
    inner, outer = rn < 0.4, rn >= 0.4
    centre = T.mean(axis=1, keepdims=True)
    radial = T - centre
    radial /= np.linalg.norm(radial, axis=2, keepdims=True)
    side = np.linalg.norm(np.roll(T, -1, axis=1) - T, axis=2).mean(axis=1)
    size = np.sum(E * radial, axis=2).mean(axis=1) / side
    size_se = lambda m: (float(np.mean(size[m])), float(np.std(size[m]) / math.sqrt(max(m.sum(), 1))))  # noqa: E731
    mean_se = lambda m: (float(np.mean(out_err[m])), float(np.std(out_err[m]) / math.sqrt(max(m.sum(), 1))))  # noqa: E731
    return {"sightings": len(sightings), "rms_px": rms(E), "rms_near_px": rms(E[near]), "rms_far_px": rms(E[far]),
            "outward_inner_px": mean_se(inner), "outward_outer_px": mean_se(outer),
            "focal_px": slope, "focal_se_px": se, "size_near": size_se(near), "size_far": size_se(far)}


def imaging_study(frames: int, seed: int) -> dict[str, Any]:
    from lab.studies.fiducial_scenes import _camera

    K = _camera()[0]          # the sim rig's lens as its file states it: the principal point the field is about
    rows = []
    for name, cond in CONDITIONS.items():
        rows.append({"condition": name, **metrics(_sightings(cond, frames, seed), K)})
    return {"frames": frames, "tags_per_frame": TAGS_PER_FRAME, "distance_m": list(DISTANCE_M), "rows": rows}


def markdown(res: dict[str, Any]) -> list[str]:
    lines = [f"Corner error under the sim rig's whole imaging ({res['frames']} frames of {res['tags_per_frame']} tags "
             f"at {res['distance_m'][0]:g}-{res['distance_m'][1]:g} m, up to 60 deg off their normal; the same poses "
             "and noise in every condition). outward: the mean error away from the principal point in the frame's "
             "inner and outer half; focal: the focal-length change that field mimics (slope on the normalised radius).",
             " size: the tag read large (+) or small, relative, near / far.",
             "", "| condition | sightings | rms | near / far | outward inner | outward outer | focal | size near / far (1e-4) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        fmt = lambda v: f"{v[0]:+.4f} ± {v[1]:.4f}"  # noqa: E731
        lines.append(f"| {r['condition']} | {r['sightings']} | {r['rms_px']:.4f} | {r['rms_near_px']:.4f} / "
                     f"{r['rms_far_px']:.4f} | {fmt(r['outward_inner_px'])} | {fmt(r['outward_outer_px'])} | "
                     f"{r['focal_px']:+.4f} ± {r['focal_se_px']:.4f} | {r['size_near'][0] * 1e4:+.2f} ± "
                     f"{r['size_near'][1] * 1e4:.2f} / {r['size_far'][0] * 1e4:+.2f} ± {r['size_far'][1] * 1e4:.2f} |")
    return lines
