"""Issue 19, a simulated camera as bad as a real one: each imaging effect against its closed form
(shot noise, depth of field, vignetting and light, JPEG, the lens's distortion error, the tags'
print scale and bow), the keys of the rig and of a scenario, and that the software is told only
the calibration, never the true lens."""

from __future__ import annotations

import json
import math
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.special import ndtr

from lab.core.config import load_rig, parse_rig
from lab.core.errors import UserError
from lab.core.geometry import Pose3, Rot3
from lab.core.imaging import IDEAL, Imaging
from lab.core.scenario import Scenario, load_scenario, parse_scenario
from sim_devices.camera import encode_frame
from sim_devices.render import (COC_DIAMETER_PER_SIGMA, Defocus, TagLook, _marker_cells, distortion_with_error,
                                lighting_field, render_grey, render_tags, tag_corners_px, vignetting_gain)
from sim_devices.world import SimWorld

REPO = Path(__file__).resolve().parents[1]
RIG = load_rig()
W, H = 1280, 720
BLACK, WHITE, BG = 25.0, 225.0, 110.0
F = 914.0


def K_at(cx: float = 640.0, cy: float = 360.0, f: float = F) -> np.ndarray:
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def facing(t, tilt_x: float = 0.0) -> Pose3:
    """camera_T_tag for a tag at t whose face looks back at the camera, turned about its own x axis."""
    return Pose3(Rot3.Rx(np.pi + tilt_x), np.asarray(t, dtype=float))


def grey(tags, K=None, dist=None, **kw) -> np.ndarray:
    kw.setdefault("blur_sigma_px", 0.0)
    return render_grey(K_at() if K is None else K, dist, W, H, tags, background=BG, black_level=BLACK,
                       white_level=WHITE, **kw).astype(float)


def edge_by_row_sum(profile: np.ndarray, k0: int, white_first: bool) -> float:
    """Position (px) of a straight edge crossing `profile` (grey levels, pixels k0, k0 + 1, ...):
    area-integrating pixels normalised 0 (black) .. 1 (white) sum to the length on the white side."""
    white = np.sum((profile - BLACK) / (WHITE - BLACK))
    return (k0 - 0.5) + white if white_first else (k0 + len(profile) - 0.5) - white


def world(**camera) -> SimWorld:
    tags = {k: camera.pop(k) for k in ("print_scale_sigma", "flatness_m") if k in camera}
    sc = parse_scenario({"seed": 3, "camera": camera, "tags": tags}, "test")
    return SimWorld(RIG, sc, speedup=1000)


IDEAL_KEYS = dict(full_well_e=0, focus_distance_m=0, vignetting=0, lighting_variation=0, jpeg_quality=0,
                  distortion_error_px=0, print_scale_sigma=0, flatness_m=0)


# -- sensor noise ---------------------------------------------------------------------------------

@pytest.mark.parametrize("signal", [20.0, 110.0, 200.0])
def test_shot_noise_variance_grows_with_the_signal_as_the_closed_form(signal):
    read, full_well = 2.0, 8000.0
    img = render_tags(K_at(), None, W, H, [], background=signal, blur_sigma_px=0.0, noise_sigma=read,
                      full_well_e=full_well, rng=np.random.default_rng(1))[:, :, 0].astype(float)
    want = read ** 2 + signal * 255.0 / full_well + 1.0 / 12.0        # read + photons + 8-bit rounding
    assert abs(img.mean() - signal) < 0.05
    assert img.var() == pytest.approx(want, rel=0.03), (img.var(), want)
    # without a full well, the read noise alone (what the camera was before issue 19)
    flat = render_tags(K_at(), None, W, H, [], background=signal, blur_sigma_px=0.0, noise_sigma=read,
                       rng=np.random.default_rng(1))[:, :, 0].astype(float)
    assert flat.var() == pytest.approx(read ** 2 + 1.0 / 12.0, rel=0.03)


# -- depth of field -------------------------------------------------------------------------------

def test_an_edge_off_focus_is_the_erf_profile_of_the_thin_lens_blur():
    lens = Defocus(focus_distance_m=1.2, f_number=1.4, focal_length_m=0.02)
    blur, depth = 0.5, 0.9
    coc = 0.02 ** 2 / (1.4 * (1.2 - 0.02)) * abs(depth - 1.2) / depth * F / 0.02     # sensor m -> px
    assert lens.coc_px(depth, F) == pytest.approx(coc)
    sigma = math.hypot(blur, coc / COC_DIAMETER_PER_SIGMA)
    assert sigma > 1.5 * blur                               # the test can tell the two apart
    assert lens.sigma_px(1.2, F, blur) == pytest.approx(blur)  # in focus: the lens's own blur
    img = grey([(3, 0.10, facing([0.0, 0.0, depth]))], blur_sigma_px=blur, defocus=lens)
    x_edge = 640.0 - F * 0.05 / depth                        # the black square's left edge
    xs = np.arange(int(x_edge) - 6, int(x_edge) + 8)
    black = (WHITE - img[360, xs]) / (WHITE - BLACK)         # share of black, middle row of the border cell

    def model(s, e):   # a pixel's area over the Gaussian-blurred step: G(u) = u Phi(u/s) + s phi(u/s)
        G = lambda u: u * ndtr(u / s) + s * np.exp(-0.5 * (u / s) ** 2) / math.sqrt(2 * math.pi)
        return G(xs + 0.5 - e) - G(xs - 0.5 - e)

    fit = least_squares(lambda p: model(*p) - black, [1.0, x_edge]).x
    assert fit[0] == pytest.approx(sigma, rel=0.015), (fit, sigma)
    assert fit[1] == pytest.approx(x_edge, abs=0.01)
    assert np.abs(model(sigma, x_edge) - black).max() < 0.005
    assert np.abs(model(blur, x_edge) - black).max() > 0.02   # the focus blur alone does not fit


def test_the_world_blurs_each_tag_for_its_depth_and_focus_zero_is_infinite_depth_of_field():
    cam = world(focus_distance_m=2.2, f_number=2.8).camera
    lens = cam.defocus()
    assert lens.focal_length_m == pytest.approx(cam.K[0, 0] * RIG.sim.imaging.pixel_pitch_um * 1e-6)
    assert lens.sigma_px(0.5, cam.K[0, 0], 0.6) > lens.sigma_px(1.5, cam.K[0, 0], 0.6) > 0.6
    assert world(focus_distance_m=0).camera.defocus() is None


# -- vignetting and light -------------------------------------------------------------------------

def test_vignetting_loses_the_key_at_the_frame_corners():
    g = vignetting_gain(W, H, 0.3)
    assert g[[0, 0, -1, -1], [0, -1, 0, -1]] == pytest.approx([0.7] * 4, abs=1e-6)
    assert g.max() == pytest.approx(1.0, abs=1e-3) and g[:, 0].max() > 0.7     # brightest mid-frame
    w = world(**{**IDEAL_KEYS, "pixel_noise": 0, "vignetting": 0.3})
    img = w.render()[:, :, 0]
    assert img[[0, 0, -1, -1], [0, -1, 0, -1]].tolist() == [round(BG * 0.7)] * 4   # background 110 -> 77
    assert abs(int(img[H // 2, 3]) - round(BG * g[H // 2, 3])) <= 1


def test_the_light_varies_smoothly_within_the_key_and_from_tag_to_tag():
    field = lighting_field(W, H, 0.1, np.random.default_rng(4))
    assert np.abs(field - 1).max() == pytest.approx(0.1, rel=1e-5) and abs(field.mean() - 1) < 1e-3
    assert np.abs(np.diff(field, axis=1)).max() < 0.1 * 2 * math.pi / W * 4     # at most a cycle a frame
    assert not np.array_equal(field, lighting_field(W, H, 0.1, np.random.default_rng(5)))
    w = world(lighting_variation=0.1)
    gains = np.array([w.tag_look(t).gain for t in w.borg.model.tags])
    assert np.all(np.abs(gains - 1) <= 0.1) and gains.std() > 0.03
    # a tag's black and white levels are its light times the print's
    T = facing([0.0, 0.0, 1.0])
    img = grey([(3, 0.10, T)], looks={3: TagLook(gain=0.9)})
    cell = 0.10 / 8
    assert img[360, round(640 - F * 3.5 * cell)] == pytest.approx(0.9 * BLACK, abs=0.01)   # the border
    assert img[360, round(640 - F * 4.5 * cell)] == pytest.approx(0.9 * WHITE, abs=0.01)   # the quiet zone


# -- JPEG -----------------------------------------------------------------------------------------

def test_jpeg_zero_is_lossless_png_and_the_ideal_camera_renders_as_before():
    img = render_tags(K_at(), None, W, H, [(3, 0.10, facing([0.1, 0.0, 1.0]))], rng=np.random.default_rng(2))
    body, kind = encode_frame(img, 0)
    assert kind == "image/png" and np.array_equal(cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR), img)
    body, kind = encode_frame(img, 90)
    back = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
    assert kind == "image/jpeg" and body[:2] == b"\xff\xd8"
    assert not np.array_equal(back, img) and np.abs(back.astype(float) - img).mean() < 2.0
    # the ideal camera: the world renders exactly what the renderer made before issue 19's imaging.
    # A tag-only scene (nothing placed: the turntable's tags, no truss in view) is the plain
    # renderer's frame, byte for byte; with the cube placed the truss is drawn too (always, as a
    # real camera sees it), and the frame is the plain renderer's with the world's truss overlay
    # and nothing else: no defocus, no tag looks, no gain map, no shot noise
    w = world(**IDEAL_KEYS)
    assert w.camera.imaging.ideal and w.camera.jpeg_quality == 0
    c = w.camera
    for placed in (False, True):
        if placed:
            w.borg.place_all()
        w.reseed_camera(11)
        got = w.render()
        w.reseed_camera(11)
        rng = np.random.default_rng(w._camera_rng.integers(2**63))
        c_T_w = w.world_T_camera().inverse()
        overlay = w._truss_overlay(c_T_w.compose(w.world_T_structure()), c_T_w)
        assert (overlay is None) == (not placed)
        before = render_tags(c.K, c.dist, c.width_px, c.height_px, w.tags_in_view(), blur_sigma_px=c.blur_px,
                             noise_sigma=c.pixel_noise, rng=rng, overlay=overlay)
        assert np.array_equal(got, before)
        assert len(w.tags_in_view()) == (len(w.borg.model.tags) if placed else len(w.borg.model.turntable.tag_ids))


def test_the_camera_serves_jpeg_with_its_content_type_and_png_when_lossless():
    from sim_devices.bench import start_sim_bench

    for q, kind in ((90, "image/jpeg"), (0, "image/png")):
        # JPEG's error is measured on a clean sensor (read noise 2, 8000 e-): a noisier one loses
        # more to JPEG (its noise is what the compression drops), which this check is not about
        sc = parse_scenario({"camera": {"jpeg_quality": q, "pixel_noise": 2.0, "full_well_e": 8000}}, "test")
        with start_sim_bench(RIG, sc, speedup=1000) as b:
            b.world.reseed_camera(4)
            sensor = b.world.render()
            b.world.reseed_camera(4)
            with urllib.request.urlopen(b.urls["camera"], timeout=5) as r:
                assert r.headers["Content-Type"] == kind
                got = cv2.imdecode(np.frombuffer(r.read(), np.uint8), cv2.IMREAD_COLOR)
        assert np.array_equal(got, sensor) == (q == 0)
        assert np.abs(got.astype(float) - sensor).mean() < 2.0


# -- the lens's distortion error ------------------------------------------------------------------

def test_the_true_lens_moves_the_frame_corners_by_the_distortion_error():
    c = RIG.sim.camera
    K0 = np.array([[c["fx_px"], 0.0, c["cx_px"]], [0.0, c["fy_px"], c["cy_px"]], [0.0, 0.0, 1.0]])
    d0 = np.asarray(c["dist"], dtype=float)
    corners = np.array([[0.0, 0.0], [W - 1.0, 0.0], [W - 1.0, H - 1.0], [0.0, H - 1.0]])
    ideal = cv2.undistortPointsIter(corners.reshape(-1, 1, 2), K0, d0, None, None,
                                    (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)).reshape(-1, 3 - 1)
    pts = np.column_stack([ideal, np.ones(4)])

    def moved(dist):
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K0, dist)
        return np.linalg.norm(uv.reshape(-1, 2) - corners, axis=1)

    assert moved(d0).max() < 1e-6                       # the calibration puts them at the corners
    signs = set()
    for seed in range(6):
        sc = parse_scenario({"seed": seed, "camera": {"distortion_error_px": 0.3}}, "test")
        w = SimWorld(RIG, sc, speedup=1000)
        assert moved(w.camera.dist) == pytest.approx([0.3] * 4, abs=1e-6)
        assert w.camera.nominal_dist.tolist() == d0.tolist()
        signs.add(np.sign(w.camera.dist[0] - d0[0]))
    assert signs == {-1.0, 1.0}                          # seeded: outwards or inwards
    for share in (0.0, 0.5, 1.0):
        assert moved(distortion_with_error(K0, d0, W, H, 2.0, -1.0, share)) == pytest.approx([2.0] * 4, abs=1e-6)
    assert np.array_equal(world(distortion_error_px=0).camera.dist, d0)


def test_a_tag_near_the_corner_is_rendered_where_the_true_lens_puts_it():
    K0 = K_at(639.5, 359.5)
    d0 = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
    true = distortion_with_error(K0, d0, W, H, 3.0, 1.0, 0.3)
    T = facing([-0.75, -0.38, 1.2])                     # near the top-left corner
    img = grey([(3, 0.10, T)], K=K0, dist=true)
    # the black square's left edge, at the middle of the tag's left side, in the distorted image
    mid = np.array([[-0.05, 0.0, 0.0]])
    at = lambda dist: cv2.projectPoints(mid, cv2.Rodrigues(T.rotation().matrix())[0], T.translation(), K0,
                                        dist)[0].reshape(2)
    want, calibrated = at(true), at(d0)
    row, k0 = int(round(want[1])), int(round(want[0])) - 5
    got = edge_by_row_sum(img[row, k0:k0 + 11], k0, white_first=True)
    assert got == pytest.approx(want[0], abs=0.05)
    assert abs(got - calibrated[0]) > 1.5                 # where the calibration file would put it


# -- printed tags: scale and bow ------------------------------------------------------------------

def test_a_tag_printed_larger_spreads_its_corners_by_the_print_scale():
    def width(size):
        img = grey([(3, size, facing([0.0, 0.0, 1.0]))])
        xl, xr = 640 - F * size / 2, 640 + F * size / 2
        l0, r0 = int(round(xl)) - 4, int(round(xr)) - 4
        return (edge_by_row_sum(img[360, r0:r0 + 9], r0, white_first=False)
                - edge_by_row_sum(img[360, l0:l0 + 9], l0, white_first=True))

    assert width(0.10 * 1.01) / width(0.10) == pytest.approx(1.01, abs=2e-4)
    # the world: every tag's printed size off by its own seeded scale, its centre pose unchanged
    exact, printed = world(print_scale_sigma=0.0), world(print_scale_sigma=0.001)
    for w in (exact, printed):
        w.borg.place_all()
    a = {t: (s, T) for t, s, T in exact.tags_in_view()}
    b = {t: (s, T) for t, s, T in printed.tags_in_view()}
    scale = np.array([b[t][0] / a[t][0] for t in a])
    assert all(a[t][0] == exact.borg.model.tags[t].size_m for t in a)
    assert 0.0006 < (scale - 1).std() < 0.0015 and len(set(scale)) == len(scale)
    assert all(np.allclose(a[t][1].matrix(), b[t][1].matrix()) for t in a)
    assert printed.borg.structure_T_tag(0).equals(exact.borg.structure_T_tag(0), 1e-12)


def _centre_edge_tag() -> int:
    """A tag whose cells just above and below its centre differ across two columns: a horizontal
    edge through the tag's centre."""
    for tid in range(200):
        c = _marker_cells(tid)
        if c[4, 4] == c[4, 5] != c[5, 4] == c[5, 5]:
            return tid
    raise AssertionError("no tag with an edge through its centre")


@pytest.mark.parametrize("bow", [0.001, -0.001])
def test_a_bowed_tag_moves_its_centre_as_projected_and_keeps_its_corners(bow):
    tid = _centre_edge_tag()
    K = K_at()
    T = facing([0.0, 0.0, 0.5], tilt_x=0.9)              # turned 52 deg about its x axis: the bow shows
    look = TagLook(bow_m=bow, bow_mix=1.0)                # bent about y: the left and right edges stay flat
    flat, bowed = grey([(tid, 0.10, T)], K=K), grey([(tid, 0.10, T)], K=K, looks={tid: look})
    rvec = cv2.Rodrigues(T.rotation().matrix())[0]
    proj = lambda p: cv2.projectPoints(np.array([p], float), rvec, T.translation(), K, None)[0].reshape(2)
    c0, c1 = proj([0.0, 0.0, 0.0]), proj([0.0, 0.0, bow])   # the centre, flat and on the bowed surface
    assert abs(c1[1] - c0[1]) > 0.8                        # a shift worth measuring (px)
    white_first = _marker_cells(tid)[4, 4] > 0.5          # above the centre (image up: tag +y) white?
    centre = []
    for img, c in ((flat, c0), (bowed, c1)):
        k0 = int(round(c[1])) - 6
        col = img[k0:k0 + 13, 640]
        centre.append(edge_by_row_sum(col, k0, white_first))
    assert centre[0] == pytest.approx(c0[1], abs=0.03)
    assert centre[1] - centre[0] == pytest.approx(c1[1] - c0[1], abs=0.03)
    # the left edge (x = -h, where this bow is zero) is where it was, row by row
    left = tag_corners_px(K, T, 0.10)[[0, 3]]
    for row in (int(left[:, 1].min()) + 5, int(round(c0[1])), int(left[:, 1].max()) - 5):
        k0 = int(round(left[0, 0])) - 5
        a = edge_by_row_sum(flat[row, k0:k0 + 11], k0, True)
        assert edge_by_row_sum(bowed[row, k0:k0 + 11], k0, True) == pytest.approx(a, abs=0.01)


def test_the_world_bows_each_tag_by_the_flatness_with_a_seeded_sign():
    w = world(flatness_m=0.0002)
    bows = np.array([w.tag_look(t).bow_m for t in w.borg.model.tags])
    assert set(np.abs(bows).round(10)) == {0.0002} and (bows > 0).any() and (bows < 0).any()
    assert world(flatness_m=0.0002).tag_look(5) == w.tag_look(5)                     # seeded
    assert world(flatness_m=0).tag_look(5).bow_m == 0.0
    assert world(flatness_m=0, lighting_variation=0).tag_look(5) == TagLook()      # an ideal tag


# -- keys ---------------------------------------------------------------------------------------------

def test_the_scenario_keys_are_read_exactly_and_an_omitted_key_keeps_the_rigs(tmp_path):
    p = tmp_path / "cam.toml"
    p.write_text("[camera]\nfull_well_e = 9000\nfocus_distance_m = 1.8\nf_number = 4\nvignetting = 0.2\n"
                 "lighting_variation = 0.05\njpeg_quality = 75\ndistortion_error_px = 0.5\n"
                 "[tags]\nprint_scale_sigma = 0.002\nflatness_m = 0.0003\n")
    got = SimWorld(RIG, load_scenario(p), speedup=1000).camera.imaging
    assert got == RIG.sim.imaging.with_overrides(dict(
        full_well_e=9000.0, focus_distance_m=1.8, f_number=4.0, vignetting=0.2, lighting_variation=0.05,
        jpeg_quality=75, distortion_error_px=0.5, print_scale_sigma=0.002, flatness_m=0.0003))
    p.write_text("[camera]\npixel_noise = 6\n")
    w = SimWorld(RIG, load_scenario(p), speedup=1000)
    assert w.camera.imaging == RIG.sim.imaging.with_overrides({"pixel_noise": 6.0})
    assert w.camera.blur_px == RIG.sim.imaging.blur_px and w.camera.pixel_noise == 6.0
    assert SimWorld(RIG, Scenario(), speedup=1000).camera.imaging == RIG.sim.imaging     # no scenario keys


def test_the_sim_rig_has_the_realistic_camera_and_the_example_scenario_the_ideal_one():
    assert RIG.sim.imaging == Imaging(pixel_noise=7.0, blur_px=0.6, full_well_e=3000.0, focus_distance_m=2.2,
                                      f_number=2.8, vignetting=0.3, lighting_variation=0.1, jpeg_quality=90,
                                      distortion_error_px=0.3, pixel_pitch_um=3.45, print_scale_sigma=0.001,
                                      flatness_m=0.0002)
    ideal = SimWorld(RIG, load_scenario(REPO / "docs" / "scenarios" / "ideal_camera.toml"), speedup=1000)
    assert ideal.camera.imaging.ideal
    assert ideal.camera.imaging == IDEAL.with_overrides({"pixel_noise": 2.0, "blur_px": 0.6})


@pytest.mark.parametrize("text,key", [
    ("[camera]\nfull_well_e = -1\n", "camera.full_well_e"),
    ("[camera]\nfull_well_e = 10\n", "camera.full_well_e"),
    ("[camera]\nfocus_distance_m = nan\n", "camera.focus_distance_m"),
    ("[camera]\nfocus_distance_m = 0.01\n", "camera.focus_distance_m"),
    ("[camera]\nf_number = 0\n", "camera.f_number"),
    ("[camera]\nvignetting = 1.5\n", "camera.vignetting"),
    ("[camera]\nlighting_variation = inf\n", "camera.lighting_variation"),
    ("[camera]\njpeg_quality = 90.5\n", "camera.jpeg_quality"),
    ("[camera]\njpeg_quality = 101\n", "camera.jpeg_quality"),
    ("[camera]\njpeg_quality = true\n", "camera.jpeg_quality"),
    ("[camera]\ndistortion_error_px = \"big\"\n", "camera.distortion_error_px"),
    ("[camera]\npixel_pitch_um = 3\n", "camera.pixel_pitch_um"),        # the rig's, not a scenario's
    ("[tags]\nprint_scale_sigma = 0.5\n", "tags.print_scale_sigma"),
    ("[tags]\nflatness_m = -0.001\n", "tags.flatness_m"),
    ("[tags]\nbow = 1\n", "tags.bow"),
    ("tags = 3\n", "tags"),
])
def test_a_bad_imaging_key_is_one_line_naming_the_file_and_the_key(tmp_path, text, key):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(UserError) as e:
        load_scenario(p)
    msg = str(e.value)
    assert msg.startswith(f"scenario {p}: {key}: ") and "\n" not in msg, msg


@pytest.mark.parametrize("old,new,key", [
    ("vignetting = 0.3 ", "vignetting = 2 ", "[sim].camera.vignetting"),
    ("jpeg_quality = 90 ", "jpeg_quality = -1 ", "[sim].camera.jpeg_quality"),
    ("flatness_m = 0.0002 ", "flatness_m = 1 ", "[sim].tags.flatness_m"),
    ("focus_distance_m = 2.2 ", "focus_distance_m = 0.006 ", "[sim].camera.focus_distance_m"),
])
def test_a_bad_rig_imaging_key_is_named(old, new, key):
    import tomllib

    from lab.core.config import RigError, default_rig_path

    text = default_rig_path().read_text()
    assert old in text
    with pytest.raises(RigError) as e:
        parse_rig(tomllib.loads(text.replace(old, new)), "sim.toml", default_rig_path().parent)
    assert key in str(e.value) and "\n" not in str(e.value), str(e.value)


# -- what the software is told ----------------------------------------------------------------------

def test_the_software_sees_the_calibration_file_never_the_true_lens():
    from drivers.camera import Camera, load_calibration
    from sim_devices.bench import start_sim_bench

    cal = json.loads((REPO / "lab" / "rigs" / "sim_camera.json").read_text())
    with start_sim_bench(RIG, speedup=1000) as b:
        base = b.urls["camera"].rsplit("/", 1)[0]
        with urllib.request.urlopen(base + "/intrinsics.json", timeout=2) as r:
            served = json.loads(r.read())
        true = b.world.camera
        driver = Camera(b.rig.camera).intrinsics
    assert served["K"] == cal["K"] and served["dist"] == cal["dist"]
    assert np.array_equal(driver.K, cal["K"]) and np.array_equal(driver.dist, cal["dist"])
    assert load_calibration(RIG.camera.calibration).K.tolist() == cal["K"]
    # the lens the frames are rendered with is not the file's: focal scale, principal point, distortion
    assert not np.allclose(true.K, cal["K"]) and not np.allclose(true.dist, cal["dist"])
    assert "true" not in json.dumps(served).replace("not the true lens", "")


def test_scenario_tables_set_every_imaging_key_whatever_the_rigs_defaults():
    import tomllib

    from lab.core.imaging import scenario_tables

    poor = IDEAL.with_overrides({"pixel_noise": 8.0, "jpeg_quality": 70, "flatness_m": 0.001})
    for im in (IDEAL, poor):
        w = SimWorld(RIG, parse_scenario(tomllib.loads("seed = 1\n" + scenario_tables(im)), "test"), speedup=1000)
        assert w.camera.imaging == im.with_overrides({"pixel_pitch_um": w.camera.imaging.pixel_pitch_um})
    assert SimWorld(RIG, parse_scenario(tomllib.loads(scenario_tables(IDEAL)), "t"), speedup=1000).camera.imaging.ideal
