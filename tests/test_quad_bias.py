"""The edge fit's bias under a blur comparable to a tag's cells (estimation/quad_bias.py): on
noise-free renders with a 1.6 px lens the fit alone reads the black square small by tenths of a
pixel at 3 m, the same way on every edge; the model of the tag takes it off.  And a model that
does not fit (no quiet zone, a patch that is not the tag) changes nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.fiducials import DetectorConfig, TagDetector
from estimation.quad_bias import blur_bias, needs_correction
from lab.core.geometry import Pose3, Rot3
from sim_devices.render import render_grey, tag_corners_px

K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
W, H = 1280, 720
SIZE = 0.10


def _outward_offsets(c: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Each fitted edge's mean offset from the true edge along its outward normal (px)."""
    cen = t.mean(axis=0)
    out = []
    for i in range(4):
        a, b = t[i], t[(i + 1) % 4]
        u = (b - a) / np.linalg.norm(b - a)
        n = np.array([u[1], -u[0]])
        n = n if np.dot(n, (a + b) / 2 - cen) > 0 else -n
        out.append(0.5 * (np.dot(c[i] - a, n) + np.dot(c[(i + 1) % 4] - a, n)))
    return np.array(out)


def _scenes(distance_m: float, blur_px: float, n: int = 6):
    rng = np.random.default_rng(11)
    for k in range(n):
        pose = Pose3(Rot3.Rz(rng.uniform(0, 2 * math.pi)).compose(Rot3.Rx(math.pi + rng.uniform(0, 0.5))),
                     np.array([rng.uniform(-0.15, 0.15) * distance_m, rng.uniform(-0.1, 0.1) * distance_m, distance_m]))
        grey = render_grey(K, DIST, W, H, [(k, SIZE, pose)], blur_sigma_px=blur_px, background=(110.0, 30.0, 220.0)[k % 3])
        yield k, np.clip(np.rint(grey), 0, 255).astype(np.uint8), tag_corners_px(K, pose, SIZE, DIST)


def _offsets(correct: bool, distance_m: float, blur_px: float) -> np.ndarray:
    det = TagDetector(K, DIST, {i: SIZE for i in range(10)}, DetectorConfig(correct_blur_bias=correct))
    out = []
    for k, img, truth in _scenes(distance_m, blur_px):
        ids, corners = det.find(img)
        assert ids == [k]
        out.append(_outward_offsets(corners[0], truth))
    return np.concatenate(out)


@pytest.mark.parametrize("distance_m", [1.0, 3.0])
def test_a_blurred_tag_reads_its_true_size(distance_m):
    raw = _offsets(False, distance_m, 1.6)
    corrected = _offsets(True, distance_m, 1.6)
    # measured: fit alone -0.04 px (1 m: its passes stop short) and -0.19 px (3 m: the next cells'
    # blur in its windows); corrected -0.001 and -0.013, spread 0.006 and 0.026
    assert raw.mean() < -0.03
    assert abs(corrected.mean()) < 0.02 and np.abs(corrected).max() < 0.2
    assert np.abs(corrected).mean() < 0.5 * np.abs(raw).mean()


def test_a_sharp_tag_is_left_as_fitted():
    # the sim's default lens (0.6 px) at 2 m: the fit's windows clear the next edges; no model drawn
    det = TagDetector(K, DIST, {i: SIZE for i in range(10)})
    for k, img, truth in _scenes(2.0, 0.6, n=2):
        ids, corners = det.find(img)
        raw = TagDetector(K, DIST, {i: SIZE for i in range(10)}, DetectorConfig(correct_blur_bias=False)).find(img)[1]
        np.testing.assert_array_equal(corners, raw)
        assert np.abs(_outward_offsets(corners[0], truth)).max() < 0.01


def test_the_correction_is_refused_where_the_model_does_not_fit():
    # a "tag" patch of noise: the model's levels cannot match it, so nothing is taken off
    rng = np.random.default_rng(3)
    grey = rng.uniform(0, 255, (200, 200)).astype(np.float32)
    quad = np.array([[[80.0, 80.0], [112.0, 80.0], [112.0, 112.0], [80.0, 112.0]]])
    pattern = rng.random((1, 8, 8)) > 0.5
    assert needs_correction(quad, np.array([1.6]))[0]
    bias, sigma = blur_bias(grey, quad, quad, pattern)
    assert np.all(bias == 0.0) and np.isnan(sigma[0])


def test_a_quad_that_runs_away_is_lost_not_refined(monkeypatch):
    """fit_quads' drift guard: a quad whose corners would move further than MAX_DRIFT_PX (or
    MAX_DRIFT_SIDES of its side) from where it started keeps a quad within that reach and is
    reported not fitted.  Without it a poor-camera run's quad grew pass after pass until reading its
    edges' rows asked for 19.7 GiB.  Here the guard is tightened so that an honest walk of 5.5 px
    to a square's true edges trips it."""
    import cv2

    from estimation import tag_quads

    g = np.full((200, 200), 220, np.float32)
    g[50:150, 50:150] = 25
    g = cv2.GaussianBlur(g, (0, 0), 1.0)
    q = np.array([[[53.5, 53.5], [145.5, 53.5], [145.5, 145.5], [53.5, 145.5]]])
    free = tag_quads.fit_quads(g, q)
    assert free.edges_fitted.all() and np.linalg.norm(free.corners - q, axis=2).max() > 5.0
    monkeypatch.setattr(tag_quads, "MAX_DRIFT_PX", 2.0)
    monkeypatch.setattr(tag_quads, "MAX_DRIFT_SIDES", 0.0)
    held = tag_quads.fit_quads(g, q)
    assert not held.edges_fitted.any()
    assert np.linalg.norm(held.corners - q, axis=2).max() <= 2.0


def test_the_compiled_level_fit_gives_the_reference_levels_and_misfit():
    """The blur search's level fit, compiled (`_fit_levels_at`), against the numpy one it replaced
    in the loop (`_fit_levels`), on a rendered tag's model, to 1e-9 relative (products taken in
    float32 miss it by ~1e-8)."""
    import cv2

    from estimation.quad_bias import _bases, _fit_levels, _fit_levels_at
    from estimation.tag_quads import code_bits

    k, img, truth = next(_scenes(2.0, 1.6, 1))
    x0, y0, base = _bases(img.shape, truth, code_bits()[k], 8)
    h, w = base.shape[1:]
    mask = base[3] > 0.5
    y = img[y0:y0 + h, x0:x0 + w][mask].astype(np.float64)
    three = np.ascontiguousarray(np.moveaxis(base[:3], 0, 2))
    for sigma in (0.8, 1.6, 2.4):
        blurred = cv2.GaussianBlur(three, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
        want, want_rms = _fit_levels(y, blurred[mask].T.astype(np.float64))
        got, got_rms = _fit_levels_at(y, blurred, np.flatnonzero(mask))
        assert np.allclose(got, want, rtol=1e-9, atol=0.0)
        assert got_rms == pytest.approx(want_rms, rel=1e-9)
        assert want[1] - want[0] > 120.0          # white over black: the model is the tag's


@pytest.mark.parametrize("z, blur, gap_cells", [(3.2, 0.7, 0.3), (3.2, 0.7, 0.6), (2.8, 0.7, 1.5)])
def test_neighbours_close_in_the_image_are_each_corrected_on_their_own_model(z, blur, gap_cells):
    # Two clean tags side by side on one face, their cards `gap_cells` apart, 3.6-4.1 px cells:
    # both need the correction.  Drawn on one canvas, one tag's model painted over its
    # neighbour's facing edge, and the neighbour was "corrected" 0.5-0.8 px off in these three
    # (both were fitted right); 8 of 64 such pairs were before (docs/fiducials.md).
    cell = SIZE / 8
    left = Pose3(Rot3.Rx(math.pi), np.array([-0.06, 0.0, z]))
    right = Pose3(Rot3.Rx(math.pi), np.array([-0.06 + SIZE + 2 * cell + gap_cells * cell, 0.0, z + 0.002]))
    grey = render_grey(K, DIST, W, H, [(3, SIZE, left), (4, SIZE, right)], blur_sigma_px=blur, background=110.0)
    det = TagDetector(K, DIST, {3: SIZE, 4: SIZE})
    for seed in range(2):
        img = np.clip(np.rint(grey + np.random.default_rng(seed).normal(0.0, 2.0, grey.shape)), 0, 255).astype(np.uint8)
        found = {d.tag_id: d.corners_px for d in det.detect(img)}
        assert set(found) == {3, 4}
        for tid, pose in ((3, left), (4, right)):
            assert np.linalg.norm(found[tid] - tag_corners_px(K, pose, SIZE, DIST), axis=1).max() < 0.1
