"""Detection against the AprilTag 3 C library, side by side: public photographs (tests/data/photos)
and rendered frames, each also degraded (blur, JPEG, strong in-plane rotation, oblique view, tags
touching the border, tags ~14 px wide), and the time per 1280x720 frame with 20 tags.  Part of
`lab bench fiducials`.

Truth on a photograph: its tags as AprilTag 3 finds them on the original (tests/data/photos/
reference.json, at quad_decimate 1), plus the few only our detector finds there, each checked by
eye; a degraded variant's truth is that list carried through the degradation's known geometry
(rotation, homography, scaling, crop), keeping the tags wholly inside the frame and >= 12 px a
side.  Both detectors run on the variant:
- recall: truth tags found (same id, centre within half a side);
- false ids: detections of an id not in the photograph at all (a false positive for certain);
  `unmatched`: detections of a real id where no truth tag is (shown beside the recall if any: a
  tag the reference lacks, or a false positive of a real id; look);
- corner error: max over a tag's four corners of |corner - reference corner|, against AprilTag 3's
  corners on the original carried through the geometry (only for its tags), so AprilTag 3 on a
  degraded variant is measured against itself on the original.
On rendered frames the truth is exact: the renderer's projected corners.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from typing import Callable

PHOTO_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tests", "data",
                         "photos")
MIN_SIDE_PX = 12.0
BLUR_SIGMA_PX = 1.5
JPEG_QUALITY = 35
ROTATION_DEG = 40.0
OBLIQUE_SQUEEZE = 0.5      # the far side of the oblique warp is this fraction of the near side's height
SMALL_SIDE_PX = 14.0
BORDER_CROPS = 4           # crops per photograph that put one tag against the frame's border


@dataclass
class Variant:
    name: str
    image: "object"                                   # 2-D uint8
    warp: Callable                                    # (N, 2) original px -> variant px
    only: tuple[int, ...] | None = None               # truth tags (indices) to count, None: all inside


# ---- degradations -----------------------------------------------------------------------------
def _identity(p):
    return p


def blurred(g, sigma: float = BLUR_SIGMA_PX) -> Variant:
    import cv2

    return Variant(f"blur {sigma:g} px", cv2.GaussianBlur(g, (0, 0), sigma), _identity)


def jpeg(g, quality: int = JPEG_QUALITY) -> Variant:
    import cv2

    ok, buf = cv2.imencode(".jpg", g, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    return Variant(f"JPEG q{quality}", cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE), _identity)


def rotated(g, deg: float = ROTATION_DEG) -> Variant:
    """Turned in the image plane about the centre, on a canvas large enough to keep everything."""
    import cv2
    import numpy as np

    h, w = g.shape
    M = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), deg, 1.0)
    c, s = abs(M[0, 0]), abs(M[0, 1])
    W, H = int(math.ceil(w * c + h * s)), int(math.ceil(w * s + h * c))
    M[0, 2] += (W - w) / 2
    M[1, 2] += (H - h) / 2
    out = cv2.warpAffine(g, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return Variant(f"rotated {deg:g} deg", out, lambda p: np.asarray(p) @ M[:, :2].T + M[:, 2])


def oblique(g, squeeze: float = OBLIQUE_SQUEEZE) -> Variant:
    """The photograph seen from the side: foreshortened to 0.6 of its width with the far side
    `squeeze` of the near side's height (about 60 deg off the normal)."""
    import cv2
    import numpy as np

    h, w = g.shape
    src = np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])
    dh = (1 - squeeze) * (h - 1) / 2
    W = int(w * 0.6)
    dst = np.float32([[0, 0], [W - 1, dh], [W - 1, h - 1 - dh], [0, h - 1]])
    Hm = cv2.getPerspectiveTransform(src, dst)
    out = cv2.warpPerspective(g, Hm, (W, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def warp(p):
        q = np.column_stack([np.asarray(p), np.ones(len(p))]) @ Hm.T
        return q[:, :2] / q[:, 2:]
    return Variant("oblique (~60 deg)", out, warp)


def scaled(g, factor: float, name: str) -> Variant:
    """Downscaled by area averaging (a smaller image of the same scene, as a farther camera sees)."""
    import cv2
    import numpy as np

    h, w = g.shape
    W, H = max(1, round(w * factor)), max(1, round(h * factor))
    out = cv2.resize(g, (W, H), interpolation=cv2.INTER_AREA)
    sx, sy = W / w, H / h
    return Variant(name, out, lambda p: (np.asarray(p) + 0.5) * [sx, sy] - 0.5)


def border_crops(g, quads, n: int = BORDER_CROPS) -> list[Variant]:
    """Crops that put one tag's black square against the frame's edge (left, top, right, bottom in
    turn): the crop line half a pixel outside its outermost corner, so the quiet zone is gone."""
    import numpy as np

    h, w = g.shape
    out = []
    order = sorted(range(len(quads)), key=lambda i: -_side(quads[i]))
    for k, i in enumerate(order[:n]):
        q = quads[i]
        x0, y0, x1, y1 = 0, 0, w, h
        side = k % 4
        if side == 0:
            x0 = int(math.floor(q[:, 0].min() + 0.5))
        elif side == 1:
            y0 = int(math.floor(q[:, 1].min() + 0.5))
        elif side == 2:
            x1 = int(math.ceil(q[:, 0].max() + 0.5))
        else:
            y1 = int(math.ceil(q[:, 1].max() + 0.5))
        out.append(Variant("touching the border", np.ascontiguousarray(g[y0:y1, x0:x1]),
                           lambda p, x0=x0, y0=y0: np.asarray(p) - [x0, y0], only=(i,)))
    return out


def _side(q) -> float:
    import numpy as np

    return float(np.min(np.linalg.norm(np.roll(q, -1, axis=0) - q, axis=1)))


# ---- scoring ----------------------------------------------------------------------------------
def _match(found, truth) -> dict[int, int]:
    """found index -> truth index: same id, centre within half a side (nearest first)."""
    import numpy as np

    pairs = {}
    used = set()
    for j, (tid, q) in enumerate(truth):
        side = float(np.mean(np.linalg.norm(np.roll(q, -1, axis=0) - q, axis=1)))
        best = None
        for i, (fid, f) in enumerate(found):
            if i in used or fid != tid:
                continue
            d = float(np.linalg.norm(f.mean(axis=0) - q.mean(axis=0)))
            if d < 0.5 * side and (best is None or d < best[1]):
                best = (i, d)
        if best is not None:
            used.add(best[0])
            pairs[best[0]] = j
    return pairs


def score(found, truth, reference, ids_present, counted) -> dict:
    """found: [(id, corners)]; truth: [(id, corners)] in the variant; reference: {truth index:
    corners} to measure corners against; counted: truth indices that count for recall."""
    import numpy as np

    m = _match(found, truth)
    hit = {j for j in m.values()}
    errs = [float(np.max(np.linalg.norm(found[i][1] - reference[j], axis=1))) for i, j in m.items() if j in reference]
    return {"truth": len(counted), "found": len(hit & set(counted)),
            "false_ids": sum(1 for t, _ in found if t not in ids_present),
            "unmatched": sum(1 for i, (t, _) in enumerate(found) if i not in m and t in ids_present),
            "corner_err": errs}


def _summary(rows: list[dict]) -> dict:
    import numpy as np

    e = np.array([x for r in rows for x in r["corner_err"]])
    return {"truth": sum(r["truth"] for r in rows), "found": sum(r["found"] for r in rows),
            "false_ids": sum(r["false_ids"] for r in rows), "unmatched": sum(r["unmatched"] for r in rows),
            "corners": len(e),
            "err_median_px": float(np.median(e)) if len(e) else None,
            "err_p95_px": float(np.percentile(e, 95)) if len(e) else None,
            "err_max_px": float(np.max(e)) if len(e) else None,
            "over_1px": int(np.sum(e > 1.0))}


def _ours():
    import numpy as np

    from estimation.fiducials import DetectorConfig, TagDetector

    # every id: a photograph's tags are not ours (nor their margins: no quiet-zone ring check);
    # corners only, so the camera does not matter
    det = TagDetector(np.eye(3), np.zeros(5), {i: 1.0 for i in range(587)}, DetectorConfig(quiet_zone=False))
    return lambda g: list(zip(*det.find(g)))


def _apriltag3(decimate: float = 1.0):
    from lab.studies import apriltag3

    return lambda g: [(d.tag_id, d.corners_px) for d in apriltag3.detect(g, decimate)]


def _detectors() -> dict[str, Callable]:
    from lab.studies import apriltag3

    out = {"ours": _ours()}
    if apriltag3.available():
        out["AprilTag 3"] = _apriltag3(1.0)
    return out


# ---- photographs ------------------------------------------------------------------------------
def load_reference(photo_dir: str = PHOTO_DIR) -> dict | None:
    path = os.path.join(photo_dir, "reference.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return json.load(f)


def photo_variants(g, quads, quick: bool) -> list[Variant]:
    import numpy as np

    sides = [_side(q) for q in quads]
    out = [Variant("original", g, _identity), blurred(g), jpeg(g), rotated(g), oblique(g)]
    if sides:
        f = SMALL_SIDE_PX / float(np.median(sides))
        if f < 1:
            out.append(scaled(g, f, f"small (~{SMALL_SIDE_PX:g} px tags)"))
    out += border_crops(g, quads, 2 if quick else BORDER_CROPS)
    return out


def photo_study(quick: bool = False, photo_dir: str = PHOTO_DIR) -> dict:
    import cv2
    import numpy as np

    ref = load_reference(photo_dir)
    if ref is None:
        return {"skipped": f"no reference.json in {photo_dir}"}
    dets = _detectors()
    rows: dict[str, dict[str, list]] = {}
    for photo in ref["photos"]:
        g = cv2.imread(os.path.join(photo_dir, photo["file"]), cv2.IMREAD_GRAYSCALE)
        tags = [(t["id"], np.asarray(t["corners"], float)) for t in photo["tags"]]
        for v in photo_variants(g, [q for _, q in tags], quick):
            h, w = v.image.shape
            truth = [(t, v.warp(q)) for t, q in tags]
            inside = [j for j, (_, q) in enumerate(truth)
                      if q[:, 0].min() >= -0.5 and q[:, 1].min() >= -0.5 and q[:, 0].max() <= w - 0.5
                      and q[:, 1].max() <= h - 0.5 and _side(q) >= MIN_SIDE_PX]
            counted = [j for j in inside if v.only is None or j in v.only]
            reference = {j: truth[j][1] for j, t in enumerate(photo["tags"]) if t["source"] == "apriltag3"}
            for name, fn in dets.items():
                rows.setdefault(v.name, {}).setdefault(name, []).append(
                    score(fn(v.image), truth, reference, set(photo["ids"]), counted))
    return {"photos": [p["file"] for p in ref["photos"]], "reference": ref["made_with"],
            "detectors": list(dets), "min_side_px": MIN_SIDE_PX,
            "variants": {v: {d: _summary(r) for d, r in by.items()} for v, by in rows.items()}}


# ---- rendered frames --------------------------------------------------------------------------
def _border_pose(rng, K, dist, W: int, H: int, size: float, edge: int):
    """A tag whose black square touches frame edge `edge` (0 left, 1 right, 2 top, 3 bottom): its
    outermost corner within the edge pixel, the quiet zone beyond the frame."""
    import numpy as np

    from lab.studies.fiducial_scenes import tag_pose_on_ray
    from sim_devices.render import tag_corners_px

    d = rng.uniform(1.2, 2.8)
    a = math.acos(rng.uniform(math.cos(math.radians(50)), 1.0))
    phi, psi = rng.uniform(0, 2 * math.pi), rng.uniform(0, 2 * math.pi)
    uv = np.array([rng.uniform(0.3, 0.7) * W, rng.uniform(0.3, 0.7) * H])
    inset = rng.uniform(0.0, 0.9)
    for _ in range(3):    # move the tag until its outermost corner sits `inset` px inside the edge
        ray = np.linalg.solve(K, [uv[0], uv[1], 1.0])
        pose = tag_pose_on_ray(ray / np.linalg.norm(ray), d, a, phi, psi)
        c = tag_corners_px(K, pose, size, dist)
        uv += ([-0.5 + inset - c[:, 0].min(), 0.0], [W - 0.5 - inset - c[:, 0].max(), 0.0],
               [0.0, -0.5 + inset - c[:, 1].min()], [0.0, H - 0.5 - inset - c[:, 1].max()])[edge]
    return pose


def _render_case(rng, K, dist, W, H, noise, blur, case: str, n: int):
    """A frame for one degradation case: (grey image, [(id, truth corners)])."""
    import cv2
    import numpy as np

    from lab.studies.fiducial_scenes import tag_pose_on_ray
    from sim_devices.render import render_tags, tag_corners_px

    size = 0.10
    tags = []
    if case == "touching the border":
        tags.append((0, size, _border_pose(rng, K, dist, W, H, size, int(rng.integers(4)))))
    else:
        cols, rows = 4, math.ceil(n / 4)
        for i in range(n):
            d = K[0, 0] * size / SMALL_SIDE_PX if case.startswith("small") else rng.uniform(1.2, 2.8)
            a = (math.radians(70.0) if case.startswith("oblique")
                 else math.acos(rng.uniform(math.cos(math.radians(50)), 1.0)))
            u = (i % cols + 0.5 + rng.uniform(-0.25, 0.25)) * W / cols
            v = (i // cols + 0.5 + rng.uniform(-0.25, 0.25)) * H / rows
            ray = np.linalg.solve(K, [u, v, 1.0])
            tags.append((i, size, tag_pose_on_ray(ray / np.linalg.norm(ray), d, a, rng.uniform(0, 2 * math.pi),
                                                  rng.uniform(0, 2 * math.pi))))
    img = render_tags(K, dist, W, H, tags, blur_sigma_px=BLUR_SIGMA_PX if case.startswith("blur") else blur,
                      noise_sigma=noise, rng=rng)
    grey = img[:, :, 0].copy()
    if case.startswith("JPEG"):
        ok, buf = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        grey = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return grey, [(t, tag_corners_px(K, p, s, dist)) for t, s, p in tags]


RENDER_CASES = ("default", f"blur {BLUR_SIGMA_PX:g} px", f"JPEG q{JPEG_QUALITY}", "oblique (70 deg)",
                "touching the border", "small (~14 px tags)")


def render_study(frames: int, seed: int) -> dict:
    """The rendered counterpart: the sim camera, 10 cm tags at 1.2-2.8 m, 0-50 deg off their normal,
    turned at random about it (any in-plane rotation), per degradation case."""
    import numpy as np

    from lab.studies.fiducial_scenes import _camera

    K, dist, W, H, noise, blur = _camera()
    dets = _detectors()
    out = {}
    for case in RENDER_CASES:
        rng = np.random.default_rng([seed, 21, RENDER_CASES.index(case)])
        rows: dict[str, list] = {}
        n_frames = frames * (8 if case == "touching the border" else 1)
        for _ in range(n_frames):
            grey, truth = _render_case(rng, K, dist, W, H, noise, blur, case, 12)
            counted = [j for j, (_, q) in enumerate(truth) if _side(q) >= MIN_SIDE_PX]
            reference = {j: q for j, (_, q) in enumerate(truth)}
            for name, fn in dets.items():
                rows.setdefault(name, []).append(score(fn(grey), truth, reference, {t for t, _ in truth}, counted))
        out[case] = {d: _summary(r) for d, r in rows.items()}
    return {"cases": out, "detectors": list(dets), "noise_grey": noise, "blur_px": blur}


# ---- time per frame ---------------------------------------------------------------------------
def timing_study(frames: int, seed: int) -> dict:
    """ms per 1280x720 frame with 20 tags (the bench's timing scene), ours (and aruco's candidate
    search alone) and AprilTag 3, on the same frames, interleaved so that a busy machine slows
    them alike; wall clock and the process's CPU time (less disturbed by other jobs on the cores)."""
    import numpy as np

    from lab.studies import apriltag3
    from lab.studies.fiducial_scenes import _camera, twenty_tag_frames
    from estimation.fiducials import TagDetector

    K, dist, W, H, noise, blur = _camera()
    grey = [img[:, :, 0].copy() for img, _ in twenty_tag_frames(frames, seed)]
    det = TagDetector(K, dist, {i: 0.10 for i in range(64)})
    runs: dict[str, Callable] = {"ours: detect (corners + poses)": det.detect, "ours: corners only": det.find,
                                 "  of which aruco's candidate search": lambda g: det.candidates(g)[1]}
    if apriltag3.available():
        runs["AprilTag 3, quad_decimate 1"] = lambda g: apriltag3.detect(g, 1.0)
        runs["AprilTag 3, quad_decimate 2 (its default)"] = lambda g: apriltag3.detect(g, 2.0)
    wall: dict[str, list] = {k: [] for k in runs}
    cpu: dict[str, list] = {k: [] for k in runs}
    found: dict[str, list] = {k: [] for k in runs}
    for g in grey[:1]:
        for f in runs.values():
            f(g)                                                  # warm caches (the undistortion map)
    for g in grey:
        for k, f in runs.items():
            t0, c0 = time.perf_counter(), time.process_time()
            r = f(g)
            wall[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
            found[k].append(0 if r is None else len(r[0]) if isinstance(r, tuple) else len(r))
    return {k: {"median_ms": float(np.median(v) * 1e3), "min_ms": float(np.min(v) * 1e3),
                "cpu_median_ms": float(np.median(cpu[k]) * 1e3),
                "found_mean": float(np.mean(found[k])), "frames": len(v)} for k, v in wall.items()}


def photo_timing_study(repeats: int = 5, photo_dir: str = PHOTO_DIR) -> dict:
    """ms per photograph (tests/data/photos: 640x480 and 799x533, 1-23 tags each), ours as the
    photographs' studies run it (`_ours`: every id, no quiet zone), aruco's candidate search alone,
    and AprilTag 3 at its defaults (quad_decimate 2, one thread) and at quad_decimate 1; each photo
    `repeats` times, the detectors interleaved so that a busy machine slows them alike.  Per photo
    the median over the repeats; then the median and the sum over the photos."""
    import cv2
    import numpy as np

    from lab.studies import apriltag3
    from estimation.fiducials import DetectorConfig, TagDetector

    ref = load_reference(photo_dir)
    if ref is None:
        return {"skipped": f"no reference.json in {photo_dir}"}
    det = TagDetector(np.eye(3), np.zeros(5), {i: 1.0 for i in range(587)}, DetectorConfig(quiet_zone=False))
    runs: dict[str, Callable] = {"ours (corners, every check)": det.find,
                                 "  of which aruco's candidate search": lambda g: det.candidates(g)[1]}
    if apriltag3.available():
        runs["AprilTag 3, its defaults (quad_decimate 2, 1 thread)"] = lambda g: apriltag3.detect(g, 2.0)
        runs["AprilTag 3, quad_decimate 1"] = lambda g: apriltag3.detect(g, 1.0)
    photos = [cv2.imread(os.path.join(photo_dir, p["file"]), cv2.IMREAD_GRAYSCALE) for p in ref["photos"]]
    for g in photos:
        for f in runs.values():
            f(g)                                                  # warm up
    per: dict[str, list] = {k: [] for k in runs}
    cpu: dict[str, list] = {k: [] for k in runs}
    found: dict[str, list] = {k: [] for k in runs}
    for g in photos:
        wall = {k: [] for k in runs}
        proc = {k: [] for k in runs}
        for _ in range(repeats):
            for k, f in runs.items():
                t0, c0 = time.perf_counter(), time.process_time()
                r = f(g)
                wall[k].append(time.perf_counter() - t0)
                proc[k].append(time.process_time() - c0)
        for k, f in runs.items():
            per[k].append(float(np.median(wall[k])))
            cpu[k].append(float(np.median(proc[k])))
            r = f(g)
            found[k].append(0 if r is None else len(r[0]) if isinstance(r, tuple) else len(r))
    return {k: {"median_ms": float(np.median(v) * 1e3), "sum_ms": float(np.sum(v) * 1e3),
                "cpu_median_ms": float(np.median(cpu[k]) * 1e3), "per_photo_ms": [x * 1e3 for x in v],
                "found": found[k], "photos": len(v), "repeats": repeats} for k, v in per.items()}


def photo_timing_markdown(t: dict) -> list[str]:
    if "skipped" in t:
        return [f"Time per photograph: skipped ({t['skipped']})."]
    lines = ["Time per photograph (tests/data/photos, 640x480 and 799x533; median over the photos of each one's "
             "median of the repeats, interleaved; CPU: the process's own time, aruco's threads included):", "",
             "| detector | median | sum over the photos | CPU median | tags found, per photo |",
             "|---|---|---|---|---|"]
    for k, v in t.items():
        lines.append(f"| {k} | {v['median_ms']:.1f} ms | {v['sum_ms']:.1f} ms | {v['cpu_median_ms']:.1f} ms "
                     f"| {' '.join(str(n) for n in v['found'])} |")
    return lines


# ---- output -----------------------------------------------------------------------------------
def _cells(s: dict) -> str:
    err = (f"{s['err_median_px']:.2f} / {s['err_p95_px']:.2f} / {s['err_max_px']:.2f} ({s['over_1px']} > 1 px)"
           if s["corners"] else "")
    extra = f" (+{s['unmatched']} unmatched)" if s["unmatched"] else ""
    return f"{s['found']}/{s['truth']}{extra} | {s['false_ids']} | {err}"


def markdown(photos: dict, rendered: dict, timing: dict) -> list[str]:
    lines = []
    if "skipped" in photos:
        lines += [f"Photographs: skipped ({photos['skipped']}).", ""]
    else:
        dets = photos["detectors"]
        lines += [f"Photographs ({len(photos['photos'])}, tests/data/photos; reference: {photos['reference']}): "
                  f"recall on the tags >= {photos['min_side_px']:g} px wholly in the frame, false ids, and corner error "
                  "(max over a tag's corners, against AprilTag 3 on the original) median / p95 / max.", ""]
        head = " | ".join(f"{d}: found | false ids | corner err [px]" for d in dets)
        lines += [f"| variant | {head} |", "|---|" + "---|---|---|" * len(dets)]
        for v, by in photos["variants"].items():
            lines.append(f"| {v} | " + " | ".join(_cells(by[d]) for d in dets) + " |")
        if "AprilTag 3" not in dets:
            lines.append("\n(pupil-apriltags is not installed: `pip install -e '.[test]'` for the side-by-side.)")
        lines.append("")
    dets = rendered["detectors"]
    lines += [f"Rendered frames (sim camera, noise {rendered['noise_grey']:g} grey levels): recall, false ids, corner "
              "error against the projected truth median / p95 / max.", ""]
    head = " | ".join(f"{d}: found | false ids | corner err [px]" for d in dets)
    lines += [f"| case | {head} |", "|---|" + "---|---|---|" * len(dets)]
    for case, by in rendered["cases"].items():
        lines.append(f"| {case} | " + " | ".join(_cells(by[d]) for d in dets) + " |")
    lines += ["", "Time per 1280x720 frame with 20 tags (same frames, interleaved; CPU: the process's own time):", "",
              "| detector | median | min | CPU median | tags found |", "|---|---|---|---|---|"]
    for k, v in timing.items():
        lines.append(f"| {k} | {v['median_ms']:.1f} ms | {v['min_ms']:.1f} ms | {v['cpu_median_ms']:.1f} ms "
                     f"| {v['found_mean']:.1f} |")
    return lines


# ---- image quality: the photographs against the simulator's default frame ----------------------
SIM_TURNTABLE_DEG = (0.0, 20.0)      # the default rig's views of the 3x3x3 BORG, turntable at these angles


def sim_default_frames(n: int = len(SIM_TURNTABLE_DEG)) -> list:
    """Frames of the default simulated rig (lab/rigs/sim.toml, its [sim.camera] and scenario
    defaults) as its camera renders them (`SimWorld.render`): the whole BORG placed, the platform at
    home, the turntable at SIM_TURNTABLE_DEG; [(label, BGR image)]."""
    from lab.core.config import load_rig
    from sim_devices.world import SimWorld

    world = SimWorld(load_rig())
    world.borg.place_all()
    out = []
    for deg in SIM_TURNTABLE_DEG[:n]:
        world.turntable.set_position(math.radians(deg))
        out.append((f"sim default, turntable {deg:g} deg", world.render()))
    return out


def quality_study(quick: bool = False, photo_dir: str = PHOTO_DIR) -> dict:
    """Edge spread and flat-area noise (lab/studies/image_quality.py) of every photograph
    in tests/data/photos and of the default simulated frames, tags >= 20 px a side."""
    import cv2

    from lab.studies import image_quality as iq

    det = iq._detector()
    rows = []
    ref = load_reference(photo_dir)
    for photo in (ref["photos"] if ref else []):
        g = cv2.imread(os.path.join(photo_dir, photo["file"]), cv2.IMREAD_GRAYSCALE)
        rows.append({"image": photo["file"], "source": "photograph", **iq.measure_image(g, detector=det)})
    frames = sim_default_frames(1 if quick else len(SIM_TURNTABLE_DEG))
    sim_tags = []
    for label, img in frames:
        r = iq.measure_image(img, detector=det)
        rows.append({"image": label, "source": "simulator", **r})
        sim_tags += r["tags"]
    from lab.core.config import load_rig

    c = load_rig().sim.camera
    photo_tags = [t for r in rows if r["source"] == "photograph" for t in r["tags"]]
    return {"min_side_px": iq.DEFAULT_MIN_SIDE_PX, "rows": rows,
            "photographs": _pooled(photo_tags), "simulator": _pooled(sim_tags),
            "sim_camera": {"blur_px": float(c["blur_px"]), "pixel_noise": float(c["pixel_noise"])}}


def _pooled(tag_rows: list[dict]) -> dict:
    """The summary (`image_quality.summarise`'s keys) over tags already measured (their JSON)."""
    import numpy as np

    edge = [t for t in tag_rows if t["sigma_px"] is not None and not t["too_small"]]

    def med(key: str, rows: list[dict]) -> float | None:
        x = [t[key] for t in rows if t[key] is not None]
        return float(np.median(x)) if x else None

    sig = [t["sigma_px"] for t in edge]
    return {"tags_measured": len(tag_rows), "tags_with_edges": len(edge),
            "sigma_px": med("sigma_px", edge), "sigma_px_range": [min(sig), max(sig)] if sig else None,
            "rise_px": med("rise_px", edge), "blur_px": med("blur_px", edge), "halo": med("halo", edge),
            "contrast": med("contrast", tag_rows), "noise_dark": med("noise_dark", tag_rows),
            "noise_bright": med("noise_bright", tag_rows), "noise_dark_rel": med("noise_dark_rel", tag_rows),
            "noise_bright_rel": med("noise_bright_rel", tag_rows)}


def quality_markdown(q: dict) -> list[str]:
    def f(x, fmt="{:.2f}"):
        return "-" if x is None else fmt.format(x)

    def pct(x):
        return "-" if x is None else f"{100 * x:.1f} %"

    def cells(r: dict) -> str:
        rng = r["sigma_px_range"]
        found = f" of {r['tags_found']} found" if "tags_found" in r else ""
        return (f"{r['tags_with_edges']}/{r['tags_measured']}{found} | {f(r['sigma_px'])}"
                f"{' (' + f(rng[0]) + '-' + f(rng[1]) + ')' if rng else ''} | {f(r['rise_px'])} | {f(r['blur_px'])} | "
                f"{pct(r['halo'])} | {f(r['contrast'], '{:.0f}')} | {f(r['noise_dark'], '{:.1f}')} / "
                f"{f(r['noise_bright'], '{:.1f}')} | {pct(r['noise_dark_rel'])} / {pct(r['noise_bright_rel'])} |")

    c = q["sim_camera"]
    lines = [f"Image quality, photographs (tests/data/photos) against the default simulated frame ([sim.camera] "
             f"blur_px {c['blur_px']:g}, pixel_noise {c['pixel_noise']:g}): tags >= {q['min_side_px']:g} px a side; "
             "edge sigma = the Gaussian edge spread across the black square's border, pixel aperture included "
             "(median over tags; range), rise = its 10-90 % distance, blur = the simulator blur_px that draws "
             "the same edge, halo = sharpening's overshoot; noise = std in flat black / white areas, grey levels "
             "and % of the contrast.", "",
             "| image | tags: with edges / >= min side | edge sigma px | 10-90 % rise px | blur px | halo | contrast | "
             "noise black / white | noise / contrast |", "|---|---|---|---|---|---|---|---|---|"]
    for r in q["rows"]:
        lines.append(f"| {r['image']} | " + cells(r))
    lines.append("| **all photographs** | " + cells(q["photographs"]))
    lines.append("| **simulator** | " + cells(q["simulator"]))
    return lines
