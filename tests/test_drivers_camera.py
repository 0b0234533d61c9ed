"""Camera driver: the calibration file, snapshot frames from the simulated camera (real AprilTag
pixels where the true pose says), and OpenCV capture."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from drivers.camera import Camera, Intrinsics, is_snapshot_url, load_calibration, save_calibration
from drivers.errors import Disconnected, RigMismatch
from drivers.testing import fast_sim_rig
from lab.core.errors import UserError
from sim_devices.bench import start_sim_bench
from sim_devices.render import tag_corners_px

# the bench (tests/conftest.py) with every module placed: tags for the camera to see
pytestmark = pytest.mark.sim_bench(place_all=True)

_PARAMS = cv2.aruco.DetectorParameters()
_PARAMS.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
DETECTOR = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), _PARAMS)


def test_calibration_round_trip_and_errors(tmp_path):
    intr = Intrinsics.from_fov(640, 480, 60.0, [-0.1, 0.02, 0.001, 0.0, 0.0])
    path = save_calibration(tmp_path / "cam" / "calibration.json", intr, camera="cam0", source="test")
    back = load_calibration(path)
    assert np.allclose(back.K, intr.K) and np.allclose(back.dist, intr.dist)
    assert (back.width_px, back.height_px) == (640, 480) and back.hfov_deg == pytest.approx(60.0)
    data = json.loads(path.read_text())
    assert data["format"] == "lab-camera-calibration" and data["camera"] == "cam0"
    for key, value, problem in [("K", [[1, 0], [0, 1]], "3x3"), ("dist", [0.1, 0.2, 0.3], "4, 5, 8, 12 or 14"),
                                ("width_px", 0, "positive integer"), ("format", "yaml", "expected 'lab-camera-calibration'")]:
        bad = dict(data, **{key: value})
        p = tmp_path / f"bad_{key}.json"
        p.write_text(json.dumps(bad))
        with pytest.raises(UserError, match=f"{key}: .*{problem}"):
            load_calibration(p)


def test_snapshot_urls_are_recognised():
    assert is_snapshot_url("http://127.0.0.1:27103/frame.png")
    assert not is_snapshot_url("http://cam.local/video.mjpg") and not is_snapshot_url("0")


def test_sim_frames_show_real_tags_where_the_true_pose_puts_them(bench):
    cam = Camera(bench.rig.camera)
    f1, f2 = cam.grab(), cam.grab()
    assert f2.seq > f1.seq and f2.t_s >= f1.t_s
    corners, ids, _ = DETECTOR.detectMarkers(f2.image)
    seen = {int(i) for i in ids.ravel()}
    assert {0, 1, 2, 9, 15, 17, 21, 35} <= seen              # face 1 from the home pose
    K, dist = bench.world.camera.K, bench.world.camera.dist     # the true lens, not the calibration file's
    truth = {tid: (size, T) for tid, size, T in bench.world.tags_in_view()}   # the size as printed
    # aruco finds them; the project's detector reads their corners to a few hundredths of a pixel
    # (aruco's own subpixel corners wander ~0.5 px on the realistic camera's noise)
    from estimation.fiducials import TagDetector

    found = TagDetector(K, dist, {tid: size for tid, (size, _) in truth.items()}).detect(f2.image)
    assert {d.tag_id for d in found} >= {0, 1, 2, 9, 15, 21, 35}
    for d in found:
        size, T = truth[d.tag_id]
        want = tag_corners_px(K, T, size, dist)
        assert np.max(np.linalg.norm(d.corners_px.reshape(4, 2) - want, axis=1)) < 0.5   # px


def test_only_placed_modules_are_seen():
    with start_sim_bench(fast_sim_rig(), speedup=1000) as b:
        cam = Camera(b.rig.camera)
        _, ids, _ = DETECTOR.detectMarkers(cam.grab().image)
        assert ids is None or set(ids.ravel()) <= set(b.world.borg.model.turntable.tag_ids)
        b.world.borg.place("1P")
        _, ids, _ = DETECTOR.detectMarkers(cam.grab().image)
        assert 0 in set(ids.ravel())            # 1P's tag


def test_frame_size_must_match_the_calibration(bench, tmp_path):
    path = save_calibration(tmp_path / "small.json", Intrinsics.from_fov(640, 480, 60))
    cam = Camera(dataclasses.replace(bench.rig.camera, calibration=path))
    with pytest.raises(RigMismatch, match=r"frame is 1280x720 px but the calibration .* is for 640x480 px"):
        cam.grab()


def test_opencv_capture_from_a_video_file(tmp_path):
    path = str(tmp_path / "clip.avi")
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 10, (320, 240))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write video")
    for k in range(3):
        writer.write(np.full((240, 320, 3), 60 * k, np.uint8))
    writer.release()
    cfg = dataclasses.replace(fast_sim_rig().camera, url=path, calibration=None)
    cam = Camera(cfg)
    frame = cam.grab()
    assert frame.image.shape == (240, 320, 3) and frame.seq == 1
    cam.grab(), cam.grab()
    with pytest.raises(Disconnected, match="returned no frame"):
        cam.grab()                                       # end of the clip
    cam.close()
    with pytest.raises(Disconnected, match="OpenCV cannot open camera"):
        Camera(dataclasses.replace(cfg, url=str(tmp_path / "none.avi"))).grab()


def test_closing_a_capture_waits_for_a_read_under_way(monkeypatch):
    """A read that times out (or a run aborted mid-read) leaves a thread inside VideoCapture.read:
    close() lets it finish before releasing (releasing under it is undefined in OpenCV, and a daemon
    thread inside OpenCV at interpreter exit aborts the process)."""
    import threading
    import time

    from drivers import camera as cam_mod
    from drivers.errors import DeviceTimeout

    events: list[str] = []

    class SlowCapture:
        def __init__(self, source):
            pass

        def isOpened(self):  # noqa: N802 (OpenCV's naming)
            return True

        def read(self):
            time.sleep(0.4)
            events.append("read done")
            return True, np.zeros((4, 4, 3), np.uint8)

        def release(self):
            events.append("released")

    monkeypatch.setattr(cv2, "VideoCapture", SlowCapture)
    cap = cam_mod._Capture("cam0", "video.mp4", lambda record: None, timeout_s=0.05)
    with pytest.raises(DeviceTimeout):
        cap.read()
    cap.close()
    assert events == ["read done", "released"]
    assert not any(t.is_alive() for t in threading.enumerate() if t is cap._worker)
