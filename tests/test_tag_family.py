"""The tag families: 36h11 up to N = 8, its extension to 1024 codes for N = 9 and 10 -- the first 587
codes unchanged, the rest far enough apart, generated the same way by the renderer and the
detector, and read back from rendered frames with the right ids and corners."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from estimation.fiducials import TagDetector
from estimation.tag_family import BASE, EXTENDED, dictionary, family_for, family_size
from lab.core.geometry import Pose3, Rot3
from lab.core.structures.borg import build_borg
from sim_devices.render import render_tags, tag_corners_px

K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
SIZE = 0.10
# sha256 of the extension's codes as OpenCV 4 generates them: the lab prints these tags
EXTENDED_SHA256 = "fb4a8e1d652cdf793ac4b413a0c2e3f31edaa34e9d061daea07c5e1b59610e39"


def test_each_borg_reads_the_smallest_family_that_prints_it():
    assert [family_for(max(build_borg(n).tags)) for n in (3, 8, 9, 10)] == [BASE, BASE, EXTENDED, EXTENDED]
    assert family_for(family_size(EXTENDED)) is None


def test_the_extension_keeps_36h11_and_a_hamming_distance_of_nine():
    ext, base = dictionary(EXTENDED), dictionary(BASE)
    assert hashlib.sha256(ext.bytesList.tobytes()).hexdigest() == EXTENDED_SHA256
    assert np.array_equal(ext.bytesList[:587], base.bytesList)
    bits = np.array([ext.getBitsFromByteList(ext.bytesList[i:i + 1], 6).ravel() for i in range(1024)], bool)
    nearest = 36
    for r in range(4):
        turned = np.array([np.rot90(b.reshape(6, 6), r).ravel() for b in bits])
        d = (bits[587:, None, :] != turned[None]).sum(-1)                 # (new code, any code turned r)
        if r == 0:
            d[np.arange(437), np.arange(587, 1024)] = 36                   # a code against itself
        nearest = min(nearest, int(d.min()))
    assert nearest >= 9, nearest


@pytest.mark.parametrize("ids", [(3, 600, 925), (590, 1000, 17)])
def test_tags_beyond_36h11_are_drawn_and_read_with_their_ids_and_corners(ids):
    def facing(x: float, turn: float) -> Pose3:
        return Pose3(Rot3.Rx(math.pi).compose(Rot3.Rz(math.radians(turn))), np.array([x, 0.05, 1.2]))

    truth = {t: facing(x, turn) for t, x, turn in zip(ids, (-0.4, 0.0, 0.4), (10.0, 80.0, -35.0))}
    frame = render_tags(K, DIST, 1280, 720, [(t, SIZE, T) for t, T in truth.items()], rng=np.random.default_rng(1))
    detector = TagDetector(K, DIST, {i: SIZE for i in range(1024)})
    assert detector.family == EXTENDED
    dets = detector.detect(frame)
    assert [d.tag_id for d in dets] == sorted(ids)
    for d in dets:
        err = np.linalg.norm(d.corners_px - tag_corners_px(K, truth[d.tag_id], SIZE, DIST), axis=1)
        assert err.max() < 0.5, (d.tag_id, err)


def test_a_structure_that_fits_36h11_is_read_in_36h11_alone_and_no_extension_code_passes_for_one_of_its_tags():
    T = Pose3(Rot3.Rx(math.pi), np.array([0.0, 0.0, 1.2]))
    frame = render_tags(K, DIST, 1280, 720, [(700, SIZE, T)], rng=np.random.default_rng(2))
    detector = TagDetector(K, DIST, {i: SIZE for i in range(550)})
    assert detector.family == BASE
    assert detector.detect(frame) == []
