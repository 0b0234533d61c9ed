"""`lab calibrate camera`: ChArUco calibration recovers the simulated camera's true intrinsics from
rendered views, writes the file the camera driver reads, works from files and from a live snapshot
camera, records to MCAP, and refuses bad input with a clear message."""

from __future__ import annotations

import json
import shutil
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.camera import Frame, Intrinsics, load_calibration
from lab.cli import build_parser, main
from lab.core.config import load_rig
from lab.core.errors import UserError
from procedures.calibrate_camera import (DEFAULT_BOARD, DEFAULT_MIN_CORNERS, DEFAULT_MIN_FRAMES, BoardDetector,
                                  CalibrationSession, Detection, NotEnoughViews, calibrate, capture_live,
                                  parse_board)
from procedures.runner import Operator
from sim_devices.charuco_render import calibration_views, charuco_corners_px, render_charuco

BOARD = parse_board(DEFAULT_BOARD)


def _truth() -> Intrinsics:
    c = load_rig().sim.camera
    K = np.array([[c["fx_px"], 0.0, c["cx_px"]], [0.0, c["fy_px"], c["cy_px"]], [0.0, 0.0, 1.0]])
    return Intrinsics(K, np.asarray(c["dist"], float), c["width_px"], c["height_px"])


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    """One simulated calibration through the CLI (14 views, recorded), shared by several tests."""
    d = tmp_path_factory.mktemp("calib")
    out, frames, mcap = d / "cal.json", d / "frames", d / "run.mcap"
    import io
    from contextlib import redirect_stdout

    buf = io.StringIO()
    with redirect_stdout(buf):
        rc = main(["calibrate", "camera", "--sim", "14", "--seed", "3", "--out", str(out), "--json",
                   "--save-frames", str(frames), "--record", str(mcap)])
    assert rc == 0
    return {"dir": d, "out": out, "frames": frames, "mcap": mcap, "result": json.loads(buf.getvalue())}


def test_sim_recovers_the_true_camera(sim_run):
    r, nominal = sim_run["result"], _truth()
    t = r["truth"]
    # the truth is the world's true lens (the rig's focal scale, principal point offset and distortion
    # error), not the calibration file's model the frames are not rendered with
    truth = Intrinsics(np.array(t["true_K"]), np.array(t["true_dist"]), nominal.width_px, nominal.height_px)
    from sim_devices.world import SimWorld

    world = SimWorld(load_rig(), speedup=1000).camera
    np.testing.assert_array_equal(truth.K, world.K)
    np.testing.assert_array_equal(truth.dist, world.dist)
    assert not np.allclose(truth.K, nominal.K) and t["nominal"]["model_rms_px"] > 1.0
    assert r["views_used"] >= 12
    assert r["rms_reprojection_px"] < 0.5
    assert abs(t["fx_rel"]) < 0.01 and abs(t["fy_rel"]) < 0.01
    assert abs(t["cx_px"]) < 3.0 and abs(t["cy_px"]) < 3.0
    k1, k2 = r["dist"][:2]
    assert abs(k1 - truth.dist[0]) < 0.005 and abs(k2 - truth.dist[1]) < 0.01
    assert np.all(np.abs(r["dist"][2:4]) < 0.002)            # no tangential distortion in the truth
    assert t["model_max_px"] < 3.0                             # the whole model, anywhere in the image
    # The reported 1-sigma is honest: the truth lies within 4 sigma of each estimate.
    K = np.array(r["K"])
    for name, est, true in (("fx_px", K[0, 0], truth.K[0, 0]), ("fy_px", K[1, 1], truth.K[1, 1]),
                            ("cx_px", K[0, 2], truth.K[0, 2]), ("cy_px", K[1, 2], truth.K[1, 2]),
                            ("k1", r["dist"][0], truth.dist[0])):
        assert 0 < r["std_1sigma"][name] and abs(est - true) < 4 * r["std_1sigma"][name], name
    assert r["coverage"] > 0.8 and not r["warnings"]


def test_written_file_is_what_the_camera_driver_loads(sim_run):
    cal = load_calibration(sim_run["out"])
    r = sim_run["result"]
    assert (cal.width_px, cal.height_px) == (1280, 720)
    np.testing.assert_allclose(cal.K, r["K"])
    np.testing.assert_allclose(cal.dist, r["dist"])
    assert cal.rms_reprojection_px == pytest.approx(r["rms_reprojection_px"])
    assert "ChArUco" in json.loads(sim_run["out"].read_text())["source"]


def test_frames_dir_gives_the_same_calibration(lab, sim_run, tmp_path):
    out = tmp_path / "again.json"
    rc, stdout, _ = lab.main("calibrate", "camera", "--frames", str(sim_run["frames"]), "--out", str(out))
    assert rc == 0 and "RMS reprojection error" in stdout and f"wrote {out}" in stdout
    np.testing.assert_allclose(load_calibration(out).K, sim_run["result"]["K"], atol=1e-6)


def test_recorded_run_holds_frames_detections_and_result(sim_run):
    from lab.core.recorder import topics
    from lab.core.recorder.reader import iter_messages, read_summary

    s = read_summary(sim_run["mcap"])
    assert s.result == "completed"
    assert s.topic_counts[topics.CAMERA_IMAGE] == 14
    assert s.steps_completed[-1][1] == "calibrate" and len(s.steps_completed) == 15
    cal = [m.message for m in iter_messages(sim_run["mcap"], topics.CAMERA_CALIBRATION)]
    assert len(cal) == 1 and cal[0].width == 1280
    assert list(cal[0].K)[0] == pytest.approx(sim_run["result"]["K"][0][0])
    kinds = [json.loads(m.message.json) for m in iter_messages(sim_run["mcap"], topics.RECORDS)
             if m.message.kind == "camera_calibration"]
    assert kinds and kinds[0]["views_used"] == sim_run["result"]["views_used"]


def test_renderer_puts_corners_where_the_true_camera_projects_them():
    truth, board = _truth(), BOARD.make()
    rng = np.random.default_rng(5)
    views = calibration_views(truth.K, truth.dist, truth.width_px, truth.height_px, board, 3, rng)
    det = BoardDetector(BOARD)
    errs = []
    for v in views:
        img = render_charuco(truth.K, truth.dist, truth.width_px, truth.height_px, board, v, rng=rng)
        d = det.detect(img, "v")
        assert d.usable
        errs.append(d.corners - charuco_corners_px(truth.K, truth.dist, board, v)[d.ids])
    e = np.linalg.norm(np.concatenate(errs), axis=1)
    assert np.median(e) < 0.15 and e.max() < 0.8


def _synthetic(views, truth, board, noise=0.1, seed=0) -> list[Detection]:
    """Detections from exact projections plus noise (no rendering): fast checks of the maths."""
    rng = np.random.default_rng(seed)
    obj = np.asarray(board.getChessboardCorners(), float).reshape(-1, 3)
    out = []
    for i, v in enumerate(views):
        px = charuco_corners_px(truth.K, truth.dist, board, v)
        ok = (px[:, 0] > 2) & (px[:, 0] < truth.width_px - 2) & (px[:, 1] > 2) & (px[:, 1] < truth.height_px - 2)
        ids = np.flatnonzero(ok)
        out.append(Detection(f"s{i}", truth.width_px, truth.height_px, 20, px[ids] + rng.normal(0, noise, (len(ids), 2)),
                             ids, obj[ids], True))
    return out


def test_a_bad_view_is_dropped_and_the_rest_still_calibrate():
    truth, board = _truth(), BOARD.make()
    views = calibration_views(truth.K, truth.dist, truth.width_px, truth.height_px, board, 12,
                              np.random.default_rng(2))
    dets = _synthetic(views, truth, board)
    bad = dets[4]
    dets[4] = Detection(bad.label, bad.width_px, bad.height_px, bad.markers,
                        bad.corners + np.random.default_rng(9).normal(0, 3.0, bad.corners.shape),
                        bad.ids, bad.object_points, True)
    r = calibrate(dets, BOARD)
    status = {v.label: v.status for v in r.views}
    assert status["s4"] == "dropped" and sum(s == "used" for s in status.values()) == 11
    assert "stands out" in next(v.reason for v in r.views if v.label == "s4")
    assert abs(r.intrinsics.K[0, 0] / truth.K[0, 0] - 1) < 0.005 and r.rms_px < 0.3
    # Too few views to spare one: it stays, and the operator is told.
    kept = calibrate(dets, BOARD, min_frames=12)
    assert all(v.status == "used" for v in kept.views)
    assert any("s4 stands out" in w and "take more views" in w for w in kept.warnings)


def test_frontal_views_in_the_middle_draw_warnings():
    from lab.core.geometry import Pose3, Rot3

    truth, board = _truth(), BOARD.make()
    bw, bh = BOARD.size_m
    views = [Pose3(Rot3.RzRyRx(0.05 * np.sin(i), 0.05 * np.cos(i), 0.1 * i), np.array([-bw / 2 + 0.01 * i, -bh / 2, 0.9]))
             for i in range(10)]
    r = calibrate(_synthetic(views, truth, board), BOARD)
    text = " ".join(r.warnings)
    assert "cover only" in text and "tilt" in text


def test_too_few_usable_frames_is_a_clear_error(lab, tmp_path, sim_run):
    frames = tmp_path / "frames"
    frames.mkdir()
    for p in sorted(sim_run["frames"].iterdir())[:3]:
        shutil.copy(p, frames / p.name)
    blank = np.full((720, 1280, 3), 110, np.uint8)
    for i in range(5):
        cv2.imwrite(str(frames / f"blank-{i}.png"), blank)
    (frames / "broken.png").write_bytes(b"not a png")
    out = tmp_path / "cal.json"
    rc, _, err = lab.main("calibrate", "camera", "--frames", str(frames), "--out", str(out))
    assert rc == 2
    assert "3 usable views of the board in 9 frames" in err and f"at least {DEFAULT_MIN_FRAMES}" in err
    assert "5 x no board markers found" in err and "1 x cannot be read as an image" in err
    assert not out.exists()
    rc, _, err = lab.main("calibrate", "camera", "--sim", "4", "--out", str(out))
    assert rc == 2 and "4 usable views" in err and not out.exists()


def test_a_frame_showing_a_corner_of_the_board_is_rejected():
    truth, board = _truth(), BOARD.make()
    views = calibration_views(truth.K, truth.dist, truth.width_px, truth.height_px, board, 1, np.random.default_rng(1))
    img = render_charuco(truth.K, truth.dist, truth.width_px, truth.height_px, board, views[0],
                         rng=np.random.default_rng(0))
    whole = BoardDetector(BOARD).detect(img, "whole")
    assert whole.usable and whole.n_corners >= DEFAULT_MIN_CORNERS
    x, y = np.percentile(whole.corners[:, 0], 25), np.percentile(whole.corners[:, 1], 40)
    part = img.copy()
    part[:, int(x):] = 110
    part[int(y):, :] = 110                                    # only one corner region of the board is left
    d = BoardDetector(BOARD).detect(part, "part")
    assert not d.usable and d.n_corners < DEFAULT_MIN_CORNERS
    assert d.reason == f"only {d.n_corners} chessboard corners found (need at least {DEFAULT_MIN_CORNERS})"
    # A board with fewer corners than the threshold is usable when all of them are seen.
    assert BoardDetector(BOARD, min_corners=100).min_corners == BOARD.n_corners


@pytest.mark.parametrize("spec, words", [
    ("9x6", "COLSxROWS:SQUARE_MM:MARKER_MM"),
    ("9 by 6:30:22", "squares"),
    ("9x6:30:40", "smaller than the square (30 mm)"),
    ("9x6:-3:2", "must be positive"),
    ("9x6:30:abc", "numbers of millimetres"),
    ("2x6:30:22", "3..100 squares"),
    ("9x6:30:22:DICT_NOPE", "unknown marker dictionary 'DICT_NOPE'"),
    ("20x20:30:20:4X4_50", "needs 200 markers but DICT_4X4_50 has only 50"),
])
def test_bad_board_spec_names_the_problem(spec, words):
    with pytest.raises(UserError, match="board spec") as e:
        parse_board(spec)
    assert words in str(e.value)


def test_board_spec_forms():
    b = parse_board("12x8:25:18.5:aprilTag_36h11:legacy")
    assert (b.cols, b.rows, b.square_m, b.marker_m, b.dictionary, b.legacy) == (12, 8, 0.025, 0.0185,
                                                                                   "DICT_APRILTAG_36H11", True)
    assert parse_board(b.text()) == b
    assert parse_board("9x6:30:22") == BOARD


def test_cli_bad_input_is_one_line(lab, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no images here")
    cases = [
        (["--board", "9x6:30:40", "--sim", "3"], "board spec '9x6:30:40'"),
        (["--frames", str(empty)], f"frames directory {empty}: no image files"),
        (["--frames", str(tmp_path / "missing")], "no such directory"),
        ([], "is simulated: its camera shows the BORG bench"),
        (["--sim", "0"], "--sim 0"),
        (["--save-frames", str(tmp_path / "f"), "--frames", str(empty)], "--save-frames"),
        (["--scenario", str(tmp_path / "sc.toml"), "--frames", str(empty)], "--scenario sets up the simulated camera"),
    ]
    for extra, words in cases:
        rc, _, err = lab.main("calibrate", "camera", "--out", str(tmp_path / "c.json"), *extra)
        assert rc == 2 and words in err and err.count("\n") == 1, (extra, err)
    existing = tmp_path / "have.json"
    existing.write_text("{}")
    rc, _, err = lab.main("calibrate", "camera", "--sim", "3", "--out", str(existing))
    assert rc == 2 and "already exists" in err and "--force" in err


def test_help_defaults_match_the_procedure():
    from lab.cli import calibrate as cli

    assert (cli._HELP_BOARD, cli._HELP_MIN_CORNERS, cli._HELP_MIN_FRAMES) == (
        DEFAULT_BOARD, DEFAULT_MIN_CORNERS, DEFAULT_MIN_FRAMES)
    assert "calibrate" in build_parser().format_help()


def test_printed_board_is_to_scale_and_detectable(lab, tmp_path):
    out = tmp_path / "board.png"
    rc, stdout, _ = lab.main("calibrate", "board", "--out", str(out), "--dpi", "100")
    assert rc == 0 and "270 x 180 mm" in stdout
    img = cv2.imread(str(out))
    d = BoardDetector(BOARD).detect(img, "print")
    assert d.n_corners == BOARD.n_corners
    # Square pitch on the page: 30 mm at 100 dpi.
    step = np.median(np.linalg.norm(np.diff(d.corners[np.argsort(d.ids)][:8], axis=0), axis=1))
    assert step == pytest.approx(30 / 25.4 * 100, rel=0.02)


# ---- live capture ---------------------------------------------------------------------------


class _SnapshotCamera:
    """A snapshot camera on 127.0.0.1 serving the given PNG files in turn at /frame.png."""

    def __init__(self, pngs: list[bytes]) -> None:
        self.pngs, self.n = pngs, 0
        outer = self

        class H(BaseHTTPRequestHandler):
            def log_message(self, *a):  # quiet
                pass

            def do_GET(self):  # noqa: N802
                if self.path.startswith("/id"):
                    body, ctype = b'{"model": "test-snapshot", "width_px": 1280, "height_px": 720}', "application/json"
                else:
                    body, ctype = outer.pngs[outer.n % len(outer.pngs)], "image/png"
                    outer.n += 1
                self.send_response(200)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), H)
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}/frame.png"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def _rig_file(tmp_path: Path, url: str) -> Path:
    p = tmp_path / "rig.toml"
    p.write_text(f'[rig]\nname = "bench camera"\n\n[camera]\nurl = "{url}"\n'
                 f'platform_T_camera = {{ xyz_m = [0.0, 0.0, 0.08], rpy_deg = [-90.0, 0.0, -90.0] }}\n'
                 f'timeout_s = 2.0\n')
    return p


def test_live_auto_grabs_from_the_rig_camera_and_records(lab, sim_run, tmp_path):
    frames = sorted(sim_run["frames"].iterdir())
    blank = cv2.imencode(".png", np.full((720, 1280, 3), 110, np.uint8))[1].tobytes()
    cam = _SnapshotCamera([blank] + [p.read_bytes() for p in frames[:10]])  # the board arrives late
    try:
        rig = _rig_file(tmp_path, cam.url)
        out, mcap = tmp_path / "cam.json", tmp_path / "live.mcap"
        rc, stdout, _ = lab.main("calibrate", "camera", "--rig", str(rig), "--auto", "--interval-s", "0",
                                 "--count", "10", "--out", str(out), "--record", str(mcap))
    finally:
        cam.close()
    assert rc == 0 and cam.n == 11
    assert "frame 1 not used: no board markers found" in stdout and "view 10/10" in stdout
    assert 'calibration = "cam.json"' in stdout              # the rig file sits next to it
    cal, truth = load_calibration(out), _truth()
    assert abs(cal.K[0, 0] / truth.K[0, 0] - 1) < 0.01
    from lab.core.recorder import topics
    from lab.core.recorder.reader import read_summary

    s = read_summary(mcap)
    assert s.result == "completed" and s.topic_counts[topics.CAMERA_IMAGE] == 11
    assert s.topic_counts[topics.COMMS] >= 11               # the driver's HTTP exchanges are in the run


def test_live_without_a_board_gives_up_and_says_why(lab, tmp_path):
    blank = cv2.imencode(".png", np.full((720, 1280, 3), 110, np.uint8))[1].tobytes()
    cam = _SnapshotCamera([blank])
    try:
        rig = _rig_file(tmp_path, cam.url)
        rc, stdout, err = lab.main("calibrate", "camera", "--rig", str(rig), "--auto", "--interval-s", "0",
                                   "--count", "3", "--min-frames", "3", "--out", str(tmp_path / "c.json"))
    finally:
        cam.close()
    assert rc == 2 and cam.n == 9                             # 3 x count grabs, then stop
    assert "stopped after 9 frames with 0 usable views" in stdout
    assert "9 x no board markers found" in err


def test_operator_prompts_capture_skip_done(sim_run):
    imgs = [cv2.imread(str(p)) for p in sorted(sim_run["frames"].iterdir())[:3]]

    class FakeCamera:
        n = 0

        def grab(self) -> Frame:
            self.n += 1
            return Frame(imgs[(self.n - 1) % 3], float(self.n), self.n, "camera")

    answers = iter(["", "skip", "capture", "done"])
    asked: list[str] = []

    def answer(prompt: str) -> str:
        asked.append(prompt)
        return next(answers)

    session, cam = CalibrationSession(BOARD), FakeCamera()
    capture_live(session, cam, Operator(False, input_fn=answer), count=5, say=lambda s: None)
    assert cam.n == 2 and session.usable == 2 and len(asked) == 4
    assert "view 1/5: hold the board in the centre" in asked[0] and "[CAPTURE/skip/done]" in asked[0]
    with pytest.raises(NotEnoughViews, match="2 usable views"):
        session.finish()
