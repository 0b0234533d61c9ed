"""The compiled pass of the edge fit (estimation/edge_kernel.py) against its numpy reference
(`tag_quads._fit_pass_numpy`): every output of a pass, and the refined corners of the whole fit, to
1e-9 px, on rendered frames that take every branch: small tags (the coarse pass, the tag's own
levels), large ones (each edge's levels, the occlusion tests), a strut across an edge, a tag
running off the frame, a blurred lens, noise, with and without the lens and the quiet zone."""

from __future__ import annotations

import math

import numpy as np
import pytest

import estimation.tag_quads as tq
from lab.core.geometry import Pose3, Rot3
from sim_devices.render import render_grey, tag_corners_px

K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
W, H = 1280, 720
SIZE = 0.10


def _frame(seed: int, blur_px: float, noise: float, strut: bool):
    """Tags from 0.5 m (cells ~11 px) to 4 m (~3 px) and one running off the frame's left edge,
    with `noise` grey levels of noise and a dark bar over the nearest tag's edge."""
    rng = np.random.default_rng(seed)
    tags, truth = [], []
    spots = [(-0.2, -0.1, 0.5), (0.3, 0.2, 1.2), (-0.9, 0.4, 2.0), (1.0, -0.6, 3.0), (-0.3, 0.9, 4.0),
             (-0.74, 0.0, 1.0)]
    for k, (x, y, z) in enumerate(spots):
        pose = Pose3(Rot3.Rz(rng.uniform(0, 2 * math.pi)).compose(Rot3.Rx(math.pi + rng.uniform(-0.6, 0.6))),
                     np.array([x * z / 1.4, y * z / 2.5, z]))
        tags.append((k, SIZE, pose))
        truth.append(tag_corners_px(K, pose, SIZE, DIST))
    grey = render_grey(K, DIST, W, H, tags, blur_sigma_px=blur_px, background=110.0)
    if strut:
        c = truth[0]
        mid = 0.5 * (c[0] + c[1])
        grey[int(mid[1]) - 40:int(mid[1]) + 40, int(mid[0]) - 4:int(mid[0]) + 4] = 60.0
    grey = grey + rng.normal(0.0, noise, grey.shape)
    return np.clip(np.rint(grey), 0, 255).astype(np.float32), np.array(truth)


def _start(truth: np.ndarray, seed: int) -> np.ndarray:
    """Quads a detector might hand over: each corner up to 1.5 px off."""
    return truth + np.random.default_rng(seed).uniform(-1.5, 1.5, truth.shape)


def _same(a, b) -> None:
    for x, y in zip(a, b):
        x, y = np.asarray(x, float), np.asarray(y, float)
        assert x.shape == y.shape
        assert np.array_equal(np.isnan(x), np.isnan(y))
        assert np.allclose(np.nan_to_num(x), np.nan_to_num(y), rtol=0.0, atol=1e-9)


@pytest.mark.parametrize("blur_px, noise, strut", [(0.6, 0.0, False), (0.6, 7.0, True), (1.6, 7.0, True)])
@pytest.mark.parametrize("camera", [True, False])
@pytest.mark.parametrize("quiet_zone", [True, False])
def test_one_pass_gives_the_reference_passes_outputs(blur_px, noise, strut, camera, quiet_zone):
    grey, truth = _frame(3, blur_px, noise, strut)
    q = _start(truth, 4)
    cam = (K, DIST) if camera else None
    for coarse in (True, False):
        for check in (None, np.ones(len(q), bool)):
            got = tq._fit_pass(grey, q, cam, coarse, check, quiet_zone)
            want = tq._fit_pass_numpy(grey, q, cam, coarse, check, quiet_zone)
            _same(got, want)
            assert got[2].sum() >= 12          # most edges fitted: the comparison is not of empty passes


def test_the_struts_rows_are_left_out_the_same_way():
    grey, truth = _frame(5, 0.6, 2.0, True)
    q = _start(truth, 6)
    got = tq._fit_pass(grey, q, (K, DIST), False, np.ones(len(q), bool), True)
    want = tq._fit_pass_numpy(grey, q, (K, DIST), False, np.ones(len(q), bool), True)
    _same(got, want)
    assert got[5][0].max() > 0.1               # the bar covers a share of the near tag's edge


def test_the_whole_fit_gives_the_reference_corners(monkeypatch):
    grey, truth = _frame(7, 0.6, 7.0, True)
    q = _start(truth, 8)
    fast = tq.fit_quads(grey, q, (K, DIST))
    monkeypatch.setattr(tq, "_fit_pass", tq._fit_pass_numpy)
    slow = tq.fit_quads(grey, q, (K, DIST))
    _same((fast.corners, fast.edges_fitted, fast.rms_px, fast.corner_sigma_px, fast.occluded),
          (slow.corners, slow.edges_fitted, slow.rms_px, slow.corner_sigma_px, slow.occluded))
    ok = slow.edges_fitted.all(axis=1)
    assert ok.sum() >= 4 and np.abs(fast.corners[ok] - truth[ok]).max() < 0.5


def test_a_tag_too_small_for_a_row_is_left_as_it_came():
    q = np.array([[[100.0, 100.0], [104.0, 100.0], [104.0, 104.0], [100.0, 104.0]]])
    grey = np.full((H, W), 128.0, np.float32)
    _same(tq._fit_pass(grey, q, None, False), tq._fit_pass_numpy(grey, q, None, False))
