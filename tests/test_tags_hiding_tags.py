"""A tag partly behind a nearer tag is dropped, not read with biased corners: the nearer tag's
white border stands in for the farther one's quiet zone, so neither the ring check nor the bits
see it (issue 19; at N = 5 such a tag's left edge read 1.9 px off in three views and its module
passed `ok` 2.9 mm off the truth with a 1-sigma of 0.49 mm)."""

from __future__ import annotations

import numpy as np
import pytest

from estimation.fiducials import DetectorConfig, TagDetector, grown_quad, partly_hidden
from lab.core.geometry import Pose3, Rot3
from sim_devices.render import render_tags, tag_corners_px

K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
W, H = 1280, 720
SIZE, CELL = 0.10, 0.10 / 8
FAR, NEAR = 2.2, 1.9


def facing(x: float, y: float, z: float) -> Pose3:
    return Pose3(Rot3.Rx(np.pi), np.array([x, y, z]))


def scene(cover_cells: float) -> tuple[np.ndarray, Pose3]:
    """Tag 5 at 2.2 m; tag 7 at 1.9 m to its left, its outer edge (quiet zone included) reaching
    `cover_cells` of tag 5's cells past tag 5's black edge (negative: short of it)."""
    far = facing(0.0, 0.0, FAR)
    u_edge = (-SIZE / 2 + cover_cells * CELL) / FAR          # normalised image x of the cover's edge
    near = facing(u_edge * NEAR - SIZE / 2 - CELL, 0.0, NEAR)
    img = render_tags(K, DIST, W, H, [(5, SIZE, far), (7, SIZE, near)], background=110.0, blur_sigma_px=0.8,
                      noise_sigma=2.0, rng=np.random.default_rng(0))
    return img, far


def detect(img: np.ndarray, margin: float | None = 0.5) -> dict[int, np.ndarray]:
    det = TagDetector(K, DIST, {5: SIZE, 7: SIZE}, DetectorConfig(hidden_margin_cells=margin))
    return {d.tag_id: d.corners_px for d in det.detect(img)}


def test_a_tag_a_fifth_of_a_cell_under_a_nearer_one_is_dropped_and_would_have_read_biased():
    img, far = scene(0.2)
    unchecked = detect(img, margin=None)
    assert 5 in unchecked and 7 in unchecked
    truth = tag_corners_px(K, far, SIZE, DIST)
    # what the check prevents: the covered edge read where the cover's white ends
    assert np.linalg.norm(unchecked[5] - truth, axis=1).max() > 0.5
    found = detect(img)
    assert 5 not in found and 7 in found


@pytest.mark.parametrize("gap_cells", [1.0, 2.0])
def test_a_nearer_tag_clear_of_the_black_square_leaves_it_alone(gap_cells):
    img, far = scene(-gap_cells)
    found = detect(img)
    assert 5 in found and 7 in found
    assert np.linalg.norm(found[5] - tag_corners_px(K, far, SIZE, DIST), axis=1).max() < 0.1


def test_tags_side_by_side_on_one_surface_never_hide_each_other():
    # quiet zones touching (one cell apart each): no overlap however close, whatever their distances
    a = np.array([[0.0, 0.0], [8.0, 0.0], [8.0, 8.0], [0.0, 8.0]]) * 5.0
    b = a + np.array([50.0, 0.0])
    assert partly_hidden([a, b], [2.0, 2.1], 1.0, 0.5) == set()
    assert partly_hidden([a, b + np.array([-6.0, 0.0])], [2.0, 2.1], 1.0, 0.5) == {1}
    # the grown square is the square's own homography: a cell of growth is a cell of the square
    assert np.allclose(grown_quad(a, 1.0), [[-5.0, -5.0], [45.0, -5.0], [45.0, 45.0], [-5.0, 45.0]], atol=1e-4)


def test_the_detector_says_which_tag_hid_the_one_it_dropped():
    img, _ = scene(0.2)
    found, behind = TagDetector(K, DIST, {5: SIZE, 7: SIZE}).detect_with_hidden(img)
    assert [d.tag_id for d in found] == [7] and behind == {5: 7}
    clear, none = TagDetector(K, DIST, {5: SIZE, 7: SIZE}).detect_with_hidden(scene(-1.0)[0])
    assert [d.tag_id for d in clear] == [5, 7] and none == {}


def test_a_run_names_the_tag_in_front_of_one_it_could_not_use():
    from procedures.borg import behind_note

    views = [{"hidden_behind": {"524": 523}}, {"hidden_behind": {}}, {"hidden_behind": {"524": 523, "17": 3}},
             {}]                                   # a view recorded before runs kept this
    assert behind_note(views, 524, {523: "396S", 524: "397S"}) == ", read in 2 more but partly behind tag 523 (396S)"
    assert behind_note(views, 17, {}) == ", read in 1 more but partly behind tag 3"
    assert behind_note(views, 99, {}) == ""


def test_of_two_overlapping_cards_the_one_on_top_is_kept_where_the_predicted_planes_say_which():
    # Neighbours on one face seen off-axis, one card 6 mm proud of the other's plane and over 0.2
    # of a cell of its black (N = 8 seed 2: 396S turned 1.5 deg pushed tag 523 under 524's card).
    # The card on top has the farther centre: the centres' distances drop it and keep the covered
    # one; the predicted planes (the graph's estimate of the misplaced module) say which is on top.
    under = facing(0.5, 0.0, 2.2)
    over = facing(0.5 + SIZE + CELL - 0.2 * CELL, 0.0, 2.194)
    assert np.linalg.norm(over.translation()) > np.linalg.norm(under.translation())
    img = render_tags(K, DIST, W, H, [(5, SIZE, under), (7, SIZE, over)], background=110.0, blur_sigma_px=0.8,
                      noise_sigma=2.0, rng=np.random.default_rng(0))
    det = TagDetector(K, DIST, {5: SIZE, 7: SIZE})
    unchecked = {d.tag_id: d.corners_px for d in TagDetector(K, DIST, {5: SIZE, 7: SIZE},
                                                              DetectorConfig(hidden_margin_cells=None)).detect(img)}
    # what is at stake: the covered edge reads off, the card on top reads true
    assert np.linalg.norm(unchecked[5] - tag_corners_px(K, under, SIZE, DIST), axis=1).max() > 0.3
    assert np.linalg.norm(unchecked[7] - tag_corners_px(K, over, SIZE, DIST), axis=1).max() < 0.1
    by_centres, behind = det.detect_with_hidden(img)
    assert [d.tag_id for d in by_centres] == [5] and behind == {7: 5}
    poses = {5: under, 7: over}
    by_planes, behind = det.detect_with_hidden(img, poses.get)
    assert [d.tag_id for d in by_planes] == [7] and behind == {5: 7}
    # planes within HIDDEN_ORDER_MIN_M of each other where the cards meet say nothing: the centres decide
    level = {5: under, 7: facing(*over.translation()[:2], 2.1995)}
    assert [d.tag_id for d in det.detect(img, level.get)] == [5]
