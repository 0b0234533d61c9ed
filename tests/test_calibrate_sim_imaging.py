"""`lab calibrate camera --sim` images the board with the simulated rig's true camera (issue 19):
the world's true lens, its depth of field, vignetting and light, shot and read noise, JPEG, and
pixels that integrate over their area; the ideal camera still renders as it did; and the result is
compared with the true lens, not the calibration file."""

from __future__ import annotations

import io
import json
from contextlib import redirect_stdout

import cv2
import numpy as np
import pytest

from lab.cli import main
from lab.core.config import load_rig
from procedures.calibrate_camera import DEFAULT_BOARD, BoardDetector, parse_board
from sim_devices.camera import encode_frame
from sim_devices.charuco_render import (board_size_m, calibration_session, calibration_views, charuco_corners_px,
                                        imaged_calibration_session, render_charuco)
from sim_devices.world import SimWorld, camera_gain_map, true_camera

RIG = load_rig()
SPEC = parse_board(DEFAULT_BOARD)
BOARD = SPEC.make()
IDEAL_CAMERA = dict(full_well_e=0, focus_distance_m=0, vignetting=0, lighting_variation=0, jpeg_quality=0,
                    distortion_error_px=0)


def session(n: int = 2, seed: int = 4, **camera) -> list[tuple[object, np.ndarray]]:
    """n views as `--sim` renders them, with the rig's imaging and these keys replaced."""
    cam = true_camera(RIG, RIG.sim.imaging.with_overrides(camera), RIG.sim.rig_error, 0)
    return imaged_calibration_session(cam, BOARD, n, np.random.default_rng([seed, 0xCA1]),
                                      gain=camera_gain_map(cam, 0), light_rng=np.random.default_rng([seed, 0xCA1, 1]))


def grey(img: np.ndarray) -> np.ndarray:
    return img[:, :, 0].astype(float)


def test_the_sim_camera_is_the_worlds_true_camera():
    world = SimWorld(RIG, speedup=1000).camera
    cam = true_camera(RIG, RIG.sim.imaging, RIG.sim.rig_error, RIG.sim.seed)
    assert np.array_equal(cam.K, world.K) and np.array_equal(cam.dist, world.dist) and cam.imaging == world.imaging
    # the rig's lens error: focal scale, principal point, a distortion the calibration file does not hold
    e = RIG.sim.rig_error
    assert cam.K[0, 0] == pytest.approx(cam.nominal_K[0, 0] * e.focal_scale)
    assert cam.K[0, 2] - cam.nominal_K[0, 2] == pytest.approx(e.principal_point_offset_px[0])
    assert not np.allclose(cam.dist, cam.nominal_dist)


def test_flat_area_noise_is_the_rigs_read_and_shot_noise():
    """Frames differ from the same frame without noise (same views, light, gain) by the sensor's
    noise: variance read^2 + signal * 255 / full_well, plus the two 8-bit roundings."""
    quiet = dict(pixel_noise=0.0, full_well_e=0, jpeg_quality=0)
    clean = grey(session(**quiet)[0][1])
    flat = (cv2.dilate(clean, np.ones((7, 7))) - cv2.erode(clean, np.ones((7, 7)))) <= 1.0
    white, black = flat & (clean > 150), flat & (clean < 60)
    assert white.sum() > 20000 and black.sum() > 20000
    for read, full_well in ((5.0, 0), (10.0, 0), (5.0, 3000)):   # black (~20) is not clipped at 0
        noisy = grey(session(pixel_noise=read, full_well_e=full_well, jpeg_quality=0)[0][1])
        for mask in (white, black):
            diff, signal = (noisy - clean)[mask], clean[mask]
            want = read ** 2 + (signal.mean() * 255.0 / full_well if full_well else 0.0) + 2.0 / 12.0
            assert diff.var() == pytest.approx(want, rel=0.08), (read, full_well, diff.var(), want)
    # the rig's own: read noise 7 and a 3000 e- full well, so white is noisier than black
    rig = grey(session(jpeg_quality=0)[0][1]) - clean
    assert rig[white].std() > rig[black].std() + 0.5


def test_the_frames_are_the_cameras_jpeg_at_its_quality():
    raw = session(jpeg_quality=0)
    for q in (90, 50):
        sent = session(jpeg_quality=q)
        for (_, r), (_, s) in zip(raw, sent):
            body, kind = encode_frame(r, q)
            assert kind == "image/jpeg"
            assert np.array_equal(s, cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR))
            assert not np.array_equal(s, r)
    assert not np.array_equal(session(jpeg_quality=90)[0][1], session(jpeg_quality=50)[0][1])


def test_the_board_is_blurred_for_its_distance_from_the_focus():
    cam = true_camera(RIG, RIG.sim.imaging, RIG.sim.rig_error, 0)
    view = calibration_views(cam.K, cam.dist, cam.width_px, cam.height_px, BOARD, 1, np.random.default_rng(2))[0]
    M = view.matrix()
    bw, bh = board_size_m(BOARD)
    depth = float((M[:3, :3] @ np.array([bw / 2, bh / 2, 0.0]) + M[:3, 3])[2])
    D = cam.defocus()
    sigma = D.sigma_px(depth, cam.K[0, 0], cam.blur_px)
    assert depth < 0.6 and sigma > cam.blur_px + 0.1          # a board held at 0.3-0.6 m, focus at 2.2 m
    kw = dict(noise_sigma=0.0, supersample=2, light=0.9)
    with_dof = render_charuco(cam.K, cam.dist, cam.width_px, cam.height_px, BOARD, view, blur_sigma_px=cam.blur_px,
                              defocus=D, **kw)
    fixed = render_charuco(cam.K, cam.dist, cam.width_px, cam.height_px, BOARD, view, blur_sigma_px=sigma, **kw)
    assert np.array_equal(with_dof, fixed)


def test_pixels_integrating_their_area_put_corners_nearer_the_truth():
    cam = true_camera(RIG, RIG.sim.imaging, RIG.sim.rig_error, 0)
    views = calibration_views(cam.K, cam.dist, cam.width_px, cam.height_px, BOARD, 6, np.random.default_rng([0, 0xCA1]))
    det = BoardDetector(SPEC)
    rms = {}
    for S in (1, 2):
        errs = []
        for v in views:
            img = render_charuco(cam.K, cam.dist, cam.width_px, cam.height_px, BOARD, v, noise_sigma=0.0, supersample=S)
            d = det.detect(img, "v")
            errs.append(d.corners - charuco_corners_px(cam.K, cam.dist, BOARD, v)[d.ids])
        rms[S] = float(np.sqrt((np.concatenate(errs) ** 2).sum(axis=1).mean()))
    assert rms[2] < 0.12 and rms[2] < 0.7 * rms[1], rms
    with pytest.raises(ValueError, match="supersample"):
        render_charuco(cam.K, cam.dist, 64, 48, BOARD, views[0], supersample=0)


def test_the_ideal_camera_renders_as_before():
    """With every imaging effect off, `--sim` renders what `calibration_session` always did (the
    ideal camera: fixed blur, read noise, point-sampled), image for image."""
    cam = true_camera(RIG, RIG.sim.imaging.with_overrides(IDEAL_CAMERA), RIG.sim.rig_error, 0)
    assert camera_gain_map(cam, 0) is None and cam.imaging.flatness_m > 0   # the rig's tags keys: not the board's
    got = imaged_calibration_session(cam, BOARD, 3, np.random.default_rng(9), light_rng=np.random.default_rng(1))
    before = calibration_session(cam.K, cam.dist, cam.width_px, cam.height_px, BOARD, 3, np.random.default_rng(9),
                                 blur_sigma_px=cam.blur_px, noise_sigma=cam.pixel_noise)
    for (p, a), (q, b) in zip(got, before):
        assert np.array_equal(a, b) and np.allclose(p.matrix(), q.matrix())


@pytest.fixture(scope="module")
def sim_report(tmp_path_factory):
    d = tmp_path_factory.mktemp("simimg")
    buf = io.StringIO()
    with redirect_stdout(buf):
        rc = main(["calibrate", "camera", "--sim", "10", "--seed", "1", "--out", str(d / "c.json")])
    assert rc == 0
    return buf.getvalue()


def test_the_report_compares_with_the_true_lens(sim_report, tmp_path):
    cam = SimWorld(RIG, speedup=1000).camera
    line = next(x for x in sim_report.splitlines() if x.startswith("truth (the simulated true lens)"))
    assert f"fx = {cam.K[0, 0]:.2f}" in line and f"cx = {cam.K[0, 2]:.2f}" in line
    assert "vs truth: fx" in sim_report and "the maker's model" in sim_report
    # the scenario's camera keys replace the rig's, its [rig_error] the rig's
    sc = tmp_path / "sc.toml"
    sc.write_text("seed = 0\n[camera]\njpeg_quality = 0\n[rig_error]\nideal = true\n")
    buf = io.StringIO()
    with redirect_stdout(buf):
        assert main(["calibrate", "camera", "--sim", "9", "--scenario", str(sc), "--json", "--out",
                     str(tmp_path / "c.json")]) == 0
    t = json.loads(buf.getvalue())["truth"]
    assert t["true_K"][0][0] == RIG.sim.camera["fx_px"] and t["nominal"]["model_max_px"] > 0.1   # the lens error stays
