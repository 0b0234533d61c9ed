"""lab/studies/image_quality.py: the edge-spread fit recovers a known blur from edges drawn in
closed form (a lone slanted edge, and a whole tag found by the project's detector), the noise
figure recovers a known noise on a flat patch under uneven light, and the bench's section measures
the photographs and the simulator's default frame side by side."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtr

from lab.studies import image_quality as iq


def _slanted_edge(sigma: float, angle_deg: float, noise: float, rng, size: int = 40, dark: float = 30.0,
                  bright: float = 200.0) -> tuple[np.ndarray, np.ndarray]:
    """A straight dark-to-bright edge through the patch centre, blurred by a Gaussian of `sigma`
    px and sampled at pixel centres (closed form: dark + (bright - dark) Phi(d / sigma)); returns
    (s, values) with s the pixel centres' signed distance from the edge."""
    y, x = np.mgrid[0:size, 0:size].astype(float)
    a = math.radians(angle_deg)
    d = (x - size / 2 + 0.3) * math.cos(a) + (y - size / 2 - 0.2) * math.sin(a)
    img = dark + (bright - dark) * ndtr(d / sigma) + rng.normal(0.0, noise, d.shape)
    near = np.abs(d) < 6.0
    return d[near], img[near]


@pytest.mark.parametrize("sigma", [0.5, 0.8, 1.5])
def test_edge_fit_recovers_a_known_blur(sigma):
    rng = np.random.default_rng(1)
    s, v = _slanted_edge(sigma, 7.0, 2.0, rng)
    fit = iq.fit_edge_spread(s + 0.4, v)          # the nominal edge 0.4 px off: s0 takes it
    assert fit is not None
    assert fit.sigma_px == pytest.approx(sigma, rel=0.10)
    assert fit.offset_px == pytest.approx(0.4, abs=0.1)
    assert fit.rise_px == pytest.approx(2.563 * fit.sigma_px, rel=1e-3)
    assert fit.halo < 0.03                         # a plain blur has no overshoot


def test_edge_fit_sees_sharpening_as_a_halo_and_ignores_a_flat_patch():
    import cv2

    rng = np.random.default_rng(2)
    y, x = np.mgrid[0:40, 0:40].astype(float)
    d = (x - 20.3) * math.cos(0.12) + (y - 19.8) * math.sin(0.12)
    img = 30.0 + 170.0 * ndtr(d / 1.0)
    sharp = img + 1.0 * (img - cv2.GaussianBlur(img, (0, 0), 1.5))          # unsharp mask
    near = np.abs(d) < 6
    fit = iq.fit_edge_spread(d[near], sharp[near])
    assert fit is not None and fit.halo > 0.05
    flat = iq.fit_edge_spread(d[near], 100.0 + rng.normal(0, 2, near.sum()))
    assert flat is None                            # no step to fit


def test_flat_noise_recovers_a_known_noise_under_uneven_light():
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:30, 0:30].astype(float)
    light = 100.0 + 1.2 * x - 0.8 * y                                        # 36 levels across
    patch = np.rint(light + rng.normal(0.0, 2.5, light.shape))             # 8-bit
    xy = np.column_stack([x.ravel(), y.ravel()])
    want = math.sqrt(2.5 ** 2 + 1 / 12)                                      # + rounding
    assert iq.flat_noise(patch.ravel(), xy) == pytest.approx(want, rel=0.10)
    assert patch.std() > 3 * want                  # what a plain std would say
    speck = patch.copy()
    speck[5, 5] = 255.0
    assert iq.flat_noise(speck.ravel(), xy) == pytest.approx(want, rel=0.10)
    assert iq.flat_noise(patch.ravel()[:5]) is None


def _tag_image(tag_id: int, side_px: float, angle_deg: float, sigma: float, noise: float, rng,
               size: int = 120, background: float = 90.0) -> np.ndarray:
    """An AprilTag (with its one-cell white quiet zone) turned `angle_deg`, blurred by a Gaussian
    of `sigma` px, point-sampled: closed form, every cell a square whose blurred image is a product
    of two normal-CDF differences in the tag's own axes (a Gaussian is the same in any axes)."""
    cells = np.ones((10, 10))
    cells[1:9, 1:9] = iq.tag_pattern(tag_id)
    cell = side_px / 8.0
    y, x = np.mgrid[0:size, 0:size].astype(float)
    a = math.radians(angle_deg)
    cx = cy = size / 2 + 0.37
    u = ((x - cx) * math.cos(a) + (y - cy) * math.sin(a)) / cell + 5.0      # tag cells, 0..10
    v = (-(x - cx) * math.sin(a) + (y - cy) * math.cos(a)) / cell + 5.0
    sc = sigma / cell
    img = np.full(x.shape, background)
    whole_u = ndtr((10 - u) / sc) - ndtr((0 - u) / sc)
    whole_v = ndtr((10 - v) / sc) - ndtr((0 - v) / sc)
    img -= background * whole_u * whole_v                                     # the card hides the background
    dark, bright = 30.0, 210.0
    for i in range(10):
        wv = ndtr((i + 1 - v) / sc) - ndtr((i - v) / sc)
        for j in range(10):
            wu = ndtr((j + 1 - u) / sc) - ndtr((j - u) / sc)
            img += (bright if cells[i, j] else dark) * wu * wv
    img += rng.normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def test_a_whole_tag_found_by_the_detector_gives_its_blur_and_noise():
    rng = np.random.default_rng(4)
    img = _tag_image(5, 48.0, 17.0, 1.0, 3.0, rng)
    r = iq.measure_image(img)
    assert r["tags_found"] == 1 and r["tags_with_edges"] == 1, r
    t = r["tags"][0]
    assert t["tag_id"] == 5 and t["edges"] >= 3
    assert t["sigma_px"] == pytest.approx(1.0, rel=0.10)          # point-sampled: no pixel aperture
    noise = math.sqrt(3.0 ** 2 + 1 / 12)
    assert t["noise_dark"] == pytest.approx(noise, rel=0.15)
    assert t["noise_bright"] == pytest.approx(noise, rel=0.15)
    assert t["contrast"] == pytest.approx(180.0, abs=5)
    assert t["noise_dark_rel"] == pytest.approx(noise / 180.0, rel=0.15)
    # a sharper copy of the same tag reads sharper: the figure follows the image, not the tag
    sharp = iq.measure_image(_tag_image(5, 48.0, 17.0, 0.5, 3.0, np.random.default_rng(4)))
    assert sharp["tags"][0]["sigma_px"] == pytest.approx(0.5, rel=0.12)


def test_tags_under_the_minimum_side_are_not_measured():
    img = _tag_image(5, 16.0, 10.0, 0.6, 1.0, np.random.default_rng(5), size=60)
    r = iq.measure_image(img, min_side_px=20)
    assert r["tags_found"] == 1 and r["tags_measured"] == 0 and r["sigma_px"] is None


def test_bench_section_measures_photographs_and_the_simulator_side_by_side():
    from lab.studies import bench_fiducials_photos as photos

    q = photos.quality_study(quick=True)
    names = [r["image"] for r in q["rows"]]
    assert any(n.startswith("nasa_") for n in names) and any(n.startswith("duckietown_") for n in names)
    assert names[-1].startswith("sim default")
    assert q["photographs"]["tags_with_edges"] >= 10 and q["simulator"]["tags_with_edges"] >= 5
    for side in ("photographs", "simulator"):
        s = q[side]
        assert 0.2 < s["sigma_px"] < 3.0 and s["noise_dark"] > 0 and 0 < s["noise_dark_rel"] < 0.5
    md = "\n".join(photos.quality_markdown(q))
    assert "| **all photographs** |" in md and "| **simulator** |" in md
