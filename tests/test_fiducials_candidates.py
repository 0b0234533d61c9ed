"""aruco's candidate search on a bilateral-filtered copy of the frame (`DetectorConfig.
candidate_filter_grey`): on a noisy frame it finds every tag the unfiltered search finds, with the
same corners (the edge fit reads the frame itself), and it is off for other people's tags."""

from __future__ import annotations

import math

import numpy as np

from estimation.fiducials import DetectorConfig, TagDetector
from lab.core.geometry import Pose3, Rot3
from sim_devices.render import render_tags, tag_corners_px

K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
W, H = 1280, 720
SIZE = 0.10


def _frame(seed: int) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Twelve tags 1.3-2.8 m away, up to 60 deg off their normal, with the realistic camera's read
    noise (7 grey levels: the noise that makes aruco's thresholds speckle)."""
    rng = np.random.default_rng(seed)
    tags, truth = [], {}
    for i in range(12):
        u, v = 140 + (i % 4) * 330, 130 + (i // 4) * 230
        ray = np.linalg.solve(K, [u, v, 1.0])
        ray /= np.linalg.norm(ray)
        R = Rot3.Rx(math.pi).compose(Rot3.Ry(math.radians(rng.uniform(-60, 60)))).compose(
            Rot3.Rz(rng.uniform(0, 2 * math.pi)))
        pose = Pose3(R, ray * rng.uniform(1.3, 2.8))
        tags.append((i, SIZE, pose))
        truth[i] = tag_corners_px(K, pose, SIZE, DIST)
    img = render_tags(K, DIST, W, H, tags, noise_sigma=7.0, rng=rng)
    return (img if img.ndim == 2 else img[:, :, 0]).copy(), truth


def test_the_filtered_search_loses_no_tag_on_a_noisy_frame():
    sizes = {i: SIZE for i in range(12)}
    filtered = TagDetector(K, DIST, sizes)
    plain = TagDetector(K, DIST, sizes, DetectorConfig(candidate_filter_grey=0.0))
    for seed in range(3):
        grey, truth = _frame(seed)
        ids_f, c_f = filtered.find(grey)
        ids_p, c_p = plain.find(grey)
        assert set(ids_p) <= set(ids_f), (seed, sorted(ids_p), sorted(ids_f))
        assert len(ids_f) == 12                      # measured: all twelve, either way
        for t, c in zip(ids_f, c_f):
            # every tag found, filtered or not, has its corners from the frame itself
            assert np.linalg.norm(c - truth[t], axis=1).max() < 0.5, (seed, t)


def test_the_filter_is_off_for_tags_without_a_quiet_zone(monkeypatch):
    import cv2

    calls = []
    real = cv2.bilateralFilter
    monkeypatch.setattr(cv2, "bilateralFilter", lambda *a, **k: calls.append(1) or real(*a, **k))
    grey, _ = _frame(0)
    TagDetector(K, DIST, {i: SIZE for i in range(12)}, DetectorConfig(quiet_zone=False)).find(grey)
    assert not calls
    TagDetector(K, DIST, {i: SIZE for i in range(12)}).find(grey)
    assert calls


def test_a_rejected_quad_overlaps_a_found_one_as_opencv_says():
    """`_overlaps` (every rejected quad's centre against every found quad in one array pass) is
    `cv2.pointPolygonTest` of each pair, for convex quads of either winding."""
    import cv2

    from estimation.fiducials import _overlaps

    rng = np.random.default_rng(0)
    compared = inside = 0
    for _ in range(200):
        found = []
        for _ in range(int(rng.integers(0, 6))):
            centre, radius = rng.uniform(0, 100, 2), rng.uniform(5, 30)
            angles = np.sort(rng.uniform(0, 2 * math.pi, 4))[::int(rng.choice([-1, 1]))]
            found.append(centre + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1))
        found = np.array(found).reshape(-1, 4, 2)
        rejected = rng.uniform(0, 100, (int(rng.integers(0, 20)), 4, 2))
        got = _overlaps(rejected, found)
        want = [any(cv2.pointPolygonTest(f.astype(np.float32), tuple(float(x) for x in r.mean(axis=0)), False) >= 0
                    for f in found) for r in rejected]
        assert got.tolist() == want
        compared += len(rejected)
        inside += int(got.sum())
    assert compared > 1000 and 100 < inside < compared - 100
