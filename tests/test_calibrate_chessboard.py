"""`lab calibrate camera --board chessboard:COLSxROWS:SQUARE_MM` on real photographs: OpenCV's
sample chessboard views (tests/data/chessboard) calibrate to OpenCV's own published focal length
with a reprojection RMS of a real camera, the RMS is OpenCV's per-corner figure, and a bad spec is
one line naming the value."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from lab.core.errors import UserError
from procedures.calibrate_camera import ChessboardSpec, CalibrationSession, parse_board, read_frames

DATA = Path(__file__).parent / "data" / "chessboard"
# OpenCV's own calibration of the left camera, shipped beside the photographs (left_intrinsics.yml
# in opencv-doc 4.6.0's examples/data: fx = fy = 535.916 px, aspect ratio fixed, k3 fitted).
OPENCV_LEFT_FX_PX = 535.9


def test_left_camera_calibrates_to_opencvs_focal_length_with_a_real_rms(lab, tmp_path):
    out, mcap = tmp_path / "left.json", tmp_path / "left.mcap"
    rc, stdout, err = lab.main("calibrate", "camera", "--frames", str(DATA), "--board", "chessboard:9x6:25",
                               "--out", str(out), "--json", "--record", str(mcap))
    assert rc == 0, err
    r = json.loads(stdout)
    assert r["board"] == "chessboard:9x6:25" and r["views_used"] == 13 and r["width_px"] == 640
    # A real camera's corners: well above the simulator's 0.12-0.16 px, well under 0.5 px.
    assert 0.1 < r["rms_reprojection_px"] < 0.4
    K = np.asarray(r["K"])
    assert K[0, 0] == pytest.approx(OPENCV_LEFT_FX_PX, rel=0.01)
    assert K[1, 1] == pytest.approx(OPENCV_LEFT_FX_PX, rel=0.01)
    assert K[0, 2] == pytest.approx(342.3, abs=3) and K[1, 2] == pytest.approx(235.6, abs=4)
    assert np.asarray(r["dist"])[0] < -0.2          # the lens's strong barrel distortion
    assert "13 chessboard views" in json.loads(out.read_text())["source"]

    from lab.core.recorder import topics
    from lab.core.recorder.reader import iter_messages

    kinds = [m.message.kind for m in iter_messages(mcap, topics.RECORDS)]
    assert kinds.count("chessboard_detection") == 13 and "camera_calibration" in kinds


def test_the_rms_is_opencvs_per_corner_figure():
    """sqrt(mean squared corner distance), not per axis: re-derived from the detections with the
    calibrated model (each view's pose re-solved), it must agree."""
    session = CalibrationSession(parse_board("chessboard:9x6:25"))
    for name, image in read_frames(DATA / "right"):
        assert session.add(name, image).usable, name
    result = session.finish()
    K, dist = result.intrinsics.K, result.intrinsics.dist
    sq, n = 0.0, 0
    for d in session.detections:
        ok, rvec, tvec = cv2.solvePnP(d.object_points, d.corners, K, dist)
        proj, _ = cv2.projectPoints(d.object_points, rvec, tvec, K, dist)
        sq += float(np.sum((proj.reshape(-1, 2) - d.corners) ** 2))
        n += len(d.corners)
    assert result.rms_px == pytest.approx(np.sqrt(sq / n), rel=0.02)
    assert not result.rms_px == pytest.approx(np.sqrt(sq / n / 2), rel=0.1)   # per axis would be 0.71x
    assert 0.1 < result.rms_px < 0.4


@pytest.mark.parametrize("spec, words", [
    ("chessboard:9x6", "'chessboard:9x6': expected chessboard:COLSxROWS:SQUARE_MM"),
    ("chessboard:9x6:abc", "square size 'abc' must be a number of millimetres"),
    ("chessboard:9by6:25", "inner corners '9by6'"),
    ("chessboard:1x6:25", "inner corners 1x6: each side needs 2..100"),
    ("chessboard:9x6:0", "square size 0 mm must be positive"),
])
def test_bad_chessboard_spec_is_one_line_naming_the_value(lab, spec, words, tmp_path):
    rc, _, err = lab.main("calibrate", "camera", "--frames", str(DATA), "--board", spec,
                          "--out", str(tmp_path / "c.json"))
    assert rc == 2 and words in err and err.count("\n") == 1, err
    assert not (tmp_path / "c.json").exists()


def test_chessboard_spec_round_trips_and_charuco_specs_are_unchanged():
    b = parse_board("Chessboard:9x6:25")
    assert b == ChessboardSpec(9, 6, 0.025) and parse_board(b.text()) == b
    assert b.n_corners == 54 and b.object_points()[10].tolist() == pytest.approx([0.025, 0.025, 0.0])
    assert parse_board("9x6:30:22").text() == "9x6:30:22:DICT_5X5_100"
    with pytest.raises(UserError, match="or chessboard:COLSxROWS:SQUARE_MM"):
        parse_board("9x6")


def test_a_board_not_in_the_photographs_is_rejected_frame_by_frame(lab, tmp_path):
    frames = tmp_path / "three"
    frames.mkdir()
    for f in ("left01.jpg", "left02.jpg", "left03.jpg"):
        shutil.copy(DATA / f, frames / f)
    rc, stdout, err = lab.main("calibrate", "camera", "--frames", str(frames), "--board", "chessboard:10x7:25",
                               "--min-frames", "3", "--out", str(tmp_path / "c.json"))
    assert rc == 2
    assert stdout.count("not used: no 10x7 chessboard found") == 3
    assert "0 usable views" in err and err.count("\n") == 1


def test_sim_and_board_printing_refuse_a_chessboard_in_one_line(lab, tmp_path):
    rc, _, err = lab.main("calibrate", "camera", "--sim", "3", "--board", "chessboard:9x6:25",
                          "--out", str(tmp_path / "c.json"))
    assert rc == 2 and "--sim renders ChArUco boards only" in err and err.count("\n") == 1
    rc, _, err = lab.main("calibrate", "board", "--board", "chessboard:9x6:25", "--out", str(tmp_path / "b.png"))
    assert rc == 2 and "prints ChArUco boards only" in err and err.count("\n") == 1
