"""The AprilTag renderer draws each tag where the camera model puts it (lens distortion included),
nearer tags hide farther ones, tags it cannot see are not drawn, and the detector reads what it draws."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lab.core.geometry import Pose3, Rot3
from sim_devices.render import render_tags, tag_corners_px

K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.05, 0.0005, -0.0003, 0.0])  # stronger than the sim rig's, to make it show
W, H = 1280, 720
BLACK, WHITE, BG = 25.0, 225.0, 110.0


def facing(t, yaw=0.0, tilt=0.0) -> Pose3:
    """camera_T_tag for a tag at t (camera frame) whose face looks back at the camera."""
    R = Rot3.Rx(np.pi).compose(Rot3.Ry(tilt)).compose(Rot3.Rz(yaw))
    return Pose3(R, np.asarray(t, dtype=float))


def clean(tags, dist=DIST, **kw):
    return render_tags(K, dist, W, H, tags, background=BG, black_level=BLACK, white_level=WHITE,
                       blur_sigma_px=0.0, noise_sigma=0.0, **kw)[:, :, 0].astype(float)


def sample(img, px):
    """Bilinear grey level at sub-pixel positions."""
    from scipy.ndimage import map_coordinates

    return map_coordinates(img, [px[:, 1], px[:, 0]], order=1)


def plane_px(camera_T_tag: Pose3, xy: np.ndarray, dist=DIST) -> np.ndarray:
    M = camera_T_tag.matrix()
    rvec, _ = cv2.Rodrigues(M[:3, :3])
    pts = np.column_stack([xy, np.zeros(len(xy))])
    out, _ = cv2.projectPoints(pts, rvec, M[:3, 3].copy(), K, dist)
    return out.reshape(-1, 2)


def test_black_border_and_quiet_zone_land_where_the_distorted_camera_puts_them():
    # Near the image corner, where barrel distortion moves things by many pixels.
    T = facing([-0.55, -0.28, 1.0], yaw=0.3, tilt=0.4)
    size = 0.10
    img = clean([(7, size, T)])
    cell = size / 8
    # centres of the black border cells and of the white quiet-zone cells, on all four sides
    k = np.arange(-3.5, 4.0, 1.0) * cell
    ring = lambda r: np.concatenate([np.column_stack([k, np.full(8, r)]), np.column_stack([k, np.full(8, -r)]),
                                     np.column_stack([np.full(8, r), k]), np.column_stack([np.full(8, -r), k])])
    black = sample(img, plane_px(T, ring(3.5 * cell)))
    white = sample(img, plane_px(T, ring(4.5 * cell)))
    assert np.all(np.abs(black - BLACK) < 15), black
    assert np.all(np.abs(white - WHITE) < 15), white
    # without modelling distortion the same points would be several pixels off
    shift = np.linalg.norm(plane_px(T, ring(3.5 * cell)) - plane_px(T, ring(3.5 * cell), dist=np.zeros(5)), axis=1)
    assert shift.max() > 5.0


def test_nearer_tag_hides_farther_one_whatever_the_list_order():
    near = (1, 0.10, facing([0.0, 0.0, 1.0]))
    far = (2, 0.20, facing([0.02, 0.0, 2.0]))
    a, b = clean([near, far]), clean([far, near])
    assert np.array_equal(a, b)
    # the near tag's own pixels, undisturbed by the far tag behind it
    alone = clean([near])
    box = tag_corners_px(K, near[2], 0.10, DIST)
    x0, y0 = box.min(axis=0).astype(int) + 2
    x1, y1 = box.max(axis=0).astype(int) - 2
    assert np.allclose(a[y0:y1, x0:x1], alone[y0:y1, x0:x1], atol=1e-6)


def test_tags_behind_the_camera_or_facing_away_are_not_drawn():
    behind = (3, 0.10, facing([0.0, 0.0, -1.0]))
    away = (4, 0.10, Pose3(Rot3(), np.array([0.0, 0.0, 1.0])))  # its face (z) points away from the camera
    img = clean([behind, away])
    assert np.all(img == BG)


def test_the_detector_reads_every_rendered_tag_and_its_corners():
    rng = np.random.default_rng(3)
    tags = []
    for i, (x, y) in enumerate([(-0.6, -0.25), (0.0, -0.25), (0.6, -0.25), (-0.6, 0.25), (0.0, 0.25), (0.6, 0.25)]):
        tags.append((10 + i, 0.10, facing([x, y, 1.4 + 0.2 * i], yaw=rng.uniform(-3, 3), tilt=rng.uniform(-0.5, 0.5))))
    img = render_tags(K, DIST, W, H, tags, rng=rng)
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementWinSize = 6
    params.relativeCornerRefinmentWinSize = 0.5
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)
    corners, ids, _ = det.detectMarkers(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    assert ids is not None and sorted(ids.ravel().tolist()) == [t[0] for t in tags]
    truth = {tid: tag_corners_px(K, T, s, DIST) for tid, s, T in tags}
    err = np.concatenate([np.linalg.norm(c.reshape(4, 2) - truth[int(i)], axis=1) for c, i in zip(corners, ids.ravel())])
    assert np.sqrt(np.mean(err**2)) < 0.4, err


def test_same_generator_same_image_and_noise_has_the_requested_sigma():
    tags = [(5, 0.10, facing([0.1, 0.0, 1.2]))]
    a = render_tags(K, DIST, W, H, tags, blur_sigma_px=0.0, noise_sigma=3.0, rng=np.random.default_rng(9))
    b = render_tags(K, DIST, W, H, tags, blur_sigma_px=0.0, noise_sigma=3.0, rng=np.random.default_rng(9))
    assert np.array_equal(a, b)
    bg = a[:100, :100, 0].astype(float)  # background only
    assert 2.5 < bg.std() < 3.5 and abs(bg.mean() - 110.0) < 1.0


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="tag id 99999"):
        clean([(99999, 0.1, facing([0, 0, 1]))])
    with pytest.raises(ValueError, match="size must be positive"):
        clean([(1, 0.0, facing([0, 0, 1]))])
    with pytest.raises(ValueError, match="background image is 10x10"):
        render_tags(K, None, W, H, [], background=np.zeros((10, 10), np.uint8))


def frontal_K(edge_x: float, size: float = 0.10, distance: float = 1.0) -> np.ndarray:
    """Intrinsics that put a frontal tag's left black edge (tag centred on the axis) at column `edge_x`."""
    f = 914.0
    return np.array([[f, 0.0, edge_x + f * size / 2 / distance], [0.0, f, 359.5], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("edge_x, want", [(600.0, 0.5), (600.25, 0.75), (599.75, 0.25), (600.5, 1.0)])
def test_a_pixel_reads_the_share_of_its_area_the_quiet_zone_covers(edge_x, want):
    # No blur: the pixel centred on x = 600 spans 599.5..600.5; left of the black square's left edge
    # is the white quiet zone, so it reads white in proportion to the part of it left of the edge
    # (half-covered: half grey).  Point-sampling a warped texture reads 0 or 1 here, or an
    # interpolated value that depends on the texture's own grid.
    K = frontal_K(edge_x)
    T = facing([0.0, 0.0, 1.0])
    img = render_tags(K, None, W, H, [(3, 0.10, T)], background=BG, black_level=BLACK, white_level=WHITE,
                      blur_sigma_px=0.0, noise_sigma=0.0)[:, :, 0].astype(float)
    row = 360          # the tag's middle row: the left border cell is black all the way down
    assert abs(img[row, 600] - (BLACK + want * (WHITE - BLACK))) <= 0.5   # 8-bit rounding


@pytest.mark.parametrize("blur", [0.0, 0.6, 1.2])
def test_a_row_across_an_edge_sums_to_the_length_on_each_side(blur):
    """What the detector's edge fit relies on: across a straight edge, a row of area-integrating
    pixels normalised to 0 (black) .. 1 (white) sums to the length of the row on the white side,
    whatever the edge's sub-pixel position and the (symmetric) blur."""
    rng = np.random.default_rng(11)
    for _ in range(6):
        K = frontal_K(600.0 + rng.uniform(0, 1))
        T = facing([0.0, 0.0, 1.0], yaw=rng.uniform(-0.2, 0.2))     # tilted edges: phase varies by row
        img = render_tags(K, None, W, H, [(3, 0.10, T)], background=BG, black_level=BLACK, white_level=WHITE,
                          blur_sigma_px=blur, noise_sigma=0.0)[:, :, 0].astype(float)
        c = tag_corners_px(K, T, 0.10)
        # the left edge runs from corner 3 (bottom-left) to corner 0 (top-left)
        for row in range(330, 391, 6):
            t = (row - c[3, 1]) / (c[0, 1] - c[3, 1])
            x_edge = c[3, 0] + t * (c[0, 0] - c[3, 0])
            k0, k1 = int(round(x_edge)) - 5, int(round(x_edge)) + 5        # white .. black
            white_len = np.sum((img[row, k0:k1 + 1] - BLACK) / (WHITE - BLACK))
            # 8-bit rounding of 11 pixels can add up to ~0.01
            assert abs(white_len - (x_edge - (k0 - 0.5))) < 0.02, (row, white_len, x_edge - (k0 - 0.5))
