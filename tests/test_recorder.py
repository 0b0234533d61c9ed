"""The MCAP run recorder: every record decodes with the standard mcap reader, a start and a stop
record on every exit path, and nothing of a finished step is lost when the writer is killed."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from lab.cli import main as lab_main
from lab.core.comms import CommsRecord
from lab.core.errors import UserError
from lab.core.geometry import from_xyzrpy, look_at
from lab.core.recorder import RunRecorder, iter_messages, messages as m, read_summary, recover, topics


def _standard_read(path: Path) -> list[tuple[str, str, object]]:
    """(topic, schema name, decoded message) with mcap's own reader and decoder, CRCs checked."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()], validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes, "file must be chunked and indexed"
        return [(ch.topic, sc.name, msg) for sc, ch, _, msg in reader.iter_decoded_messages(log_time_order=False)]


def _write_everything(path: Path) -> dict[str, object]:
    """One of every kind of record; returns a few values to compare after reading back."""
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    cam = look_at([2.0, -1.0, 1.5], [0.5, 0.5, 0.5])
    tag = from_xyzrpy([0.1, 0.2, 0.3, 0.01, -0.02, 0.03])
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6])
    img = np.zeros((48, 64, 3), np.uint8)
    img[10:20, 10:30] = (0, 0, 255)
    with RunRecorder(path, "roundtrip", {"n": 3, "arr": np.arange(3)}, rig={"camera": "sim"},
                     scenario={"seed": 7}, structure="borg:3") as rec:
        with rec.step("everything", 0, {"k": 1}):
            rec.comms_sink(CommsRecord("turntable", "socket://127.0.0.1:5001", "tx", b"MOVE 90.000\n", 1.5e9))
            rec.comms_sink(CommsRecord("turntable", "socket://127.0.0.1:5001", "rx", b"OK 90.000\n", 1.5e9 + 0.01))
            rec.log_image(topics.CAMERA_IMAGE, img, 1.5e9, "camera")
            rec.log_image("/camera/jpeg", img, 1.5e9, "camera", format="jpeg")
            rec.log_calibration(topics.CAMERA_CALIBRATION, K, [0.1, -0.2, 0.0, 0.0, 0.05], 640, 480, "camera", 1.5e9)
            rec.log_transform("world", "camera", cam, 1.5e9)
            rec.log_pose(topics.estimate_topic("camera"), cam, "world", 1.5e9, cov)
            rec.log_tag_estimates({17: tag, 3: tag}, "structure", 1.5e9, {17: cov})
            rec.log_structure("tiny", np.eye(3), [(0, 1), (1, 2)],
                              [m.DesignTag(id=17, label="x", module="2D", pose=m.pose_to_proto(tag), size_m=0.1)])
            rec.log_text("warning", "a warning")
            rec.log_metric("residual/total", 0.25, "m")
            rec.log_prompt("place module 2D", "done", automatic=True)
            rec.log_json("summary", {"modules": 1})
            rec.log_record(topics.DETECTIONS, m.TagDetections(
                frame_id="camera", detections=[m.tag_detection(17, [[1, 2], [3, 4], [5, 6], [7, 8]], tag, cov, 0.3)]))
            rec.log_record(topics.VERDICTS, m.module_verdict("2D", "flagged", "tag 1 displaced", 0.004, 0.01,
                                                             step_index=0, tag_ids=[1, 2], rejected_tag_ids=[1]))
            rec.log_record(topics.LENGTHS, m.LengthMeasurement(strut="0-1", node_a=0, node_b=1, device="ipjr1",
                                                               nominal_m=1.0, commanded_m=1.0, measured_m=1.0004))
    return {"K": K, "cam": cam, "tag": tag, "cov": cov}


def test_round_trip_every_message_type_decodes_with_the_mcap_reader(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    ref = _write_everything(path)
    got = _standard_read(path)
    by_topic: dict[str, list] = {}
    for topic, schema, msg in got:
        by_topic.setdefault(topic, []).append((schema, msg))
    # Every one of our message types and every Foxglove schema we use appears and decodes.
    schemas = {s for _, s, _ in got}
    ours = {cls.DESCRIPTOR.full_name for cls in m.MESSAGE_TYPES} - {"lab.TagDetection", "lab.DesignTag"}
    assert ours <= schemas, ours - schemas  # (TagDetection, DesignTag only travel inside others)
    assert {"foxglove.CompressedImage", "foxglove.CameraCalibration", "foxglove.FrameTransform",
            "foxglove.PoseInFrame", "foxglove.PosesInFrame", "foxglove.Log"} <= schemas
    start = by_topic[topics.RUN_START][0][1]
    assert start.procedure == "roundtrip" and start.structure == "borg:3"
    assert json.loads(start.params_json) == {"n": 3, "arr": [0, 1, 2]}
    assert json.loads(start.rig_json) == {"camera": "sim"} and json.loads(start.scenario_json) == {"seed": 7}
    assert "mcap" in start.versions and start.versions["python"].startswith("3.")
    assert got[0][0] == topics.RUN_START and got[-1][0] == topics.RUN_STOP
    assert by_topic[topics.RUN_STOP][0][1].result == "completed"
    assert [e.phase for _, e in by_topic[topics.RUN_STEP]] == ["start", "end"]
    tx = by_topic[topics.COMMS][0][1]
    assert (tx.device, tx.direction, tx.data, tx.text) == ("turntable", "tx", b"MOVE 90.000\n", "MOVE 90.000\n")
    # The image survives encoding (PNG is lossless).
    import cv2

    png = by_topic[topics.CAMERA_IMAGE][0][1]
    assert png.format == "png"
    decoded = cv2.imdecode(np.frombuffer(png.data, np.uint8), cv2.IMREAD_COLOR)
    assert decoded.shape == (48, 64, 3) and tuple(decoded[15, 15]) == (0, 0, 255)
    cal = by_topic[topics.CAMERA_CALIBRATION][0][1]
    assert cal.distortion_model == "plumb_bob" and np.allclose(np.reshape(cal.K, (3, 3)), ref["K"])
    assert (cal.width, cal.height) == (640, 480) and np.allclose(np.reshape(cal.P, (3, 4))[:, :3], ref["K"])
    tf = by_topic[topics.TF][0][1]
    assert (tf.parent_frame_id, tf.child_frame_id) == ("world", "camera")
    assert np.allclose([tf.translation.x, tf.translation.y, tf.translation.z], ref["cam"].translation())
    est = by_topic[topics.estimate_topic("camera") + topics.COVARIANCE_SUFFIX][0][1]
    assert est.entity == "camera" and np.allclose(np.reshape(est.covariance, (6, 6)), ref["cov"])
    tags = by_topic[topics.TAG_ESTIMATES][0][1]
    assert [e.entity for e in tags.estimates] == ["tag/3", "tag/17"]  # ascending id, like /estimate/tags
    assert len(tags.estimates[1].covariance) == 36 and len(tags.estimates[0].covariance) == 0
    assert len(by_topic[topics.TAG_POSES][0][1].poses) == 2
    det = by_topic[topics.DETECTIONS][0][1].detections[0]
    assert det.tag_id == 17 and list(det.corners_px) == [1, 2, 3, 4, 5, 6, 7, 8]
    verdict = by_topic[topics.VERDICTS][0][1]
    assert (verdict.verdict, list(verdict.rejected_tag_ids)) == ("flagged", [1])
    assert by_topic[topics.LOG][0][1].level == 3  # WARNING
    assert by_topic[topics.METRICS][0][1].step_index == 0
    assert json.loads(by_topic[topics.RECORDS][0][1].json) == {"modules": 1}
    assert by_topic[topics.OPERATOR][0][1].automatic is True
    # Our reader gives the same records as our own classes.
    ours_read = list(iter_messages(path))
    assert [r.topic for r in ours_read] == [t for t, _, _ in got]
    v = next(r.message for r in ours_read if r.topic == topics.VERDICTS)
    assert isinstance(v, m.ModuleVerdict) and v.reason == "tag 1 displaced"
    assert m.pose_from_proto(tags.estimates[1].pose).equals(ref["tag"], 1e-9)


def test_pose_and_covariance_helpers_round_trip() -> None:
    p = from_xyzrpy([1.0, -2.0, 0.5, 0.3, -0.2, 2.9])
    assert m.pose_from_proto(m.pose_to_proto(p)).equals(p, 1e-12)
    cov = np.arange(36, dtype=float).reshape(6, 6)
    assert np.array_equal(m.covariance_from_list(m.covariance_to_list(cov)), cov)
    assert m.covariance_from_list([]) is None
    with pytest.raises(ValueError, match="6x6"):
        m.covariance_to_list(np.eye(3))
    with pytest.raises(ValueError, match="verdict must be one of"):
        m.module_verdict("2D", "great")
    assert m.tag_id_of(m.tag_entity(42)) == 42 and m.tag_id_of("camera") is None


def test_stop_record_on_normal_exit(tmp_path: Path) -> None:
    path = tmp_path / "ok.mcap"
    with RunRecorder(path, "p", {}) as rec:
        for i in range(3):
            with rec.step(f"s{i}", i):
                rec.log_text("info", str(i))
    s = read_summary(path)
    assert s.scan.complete and s.start.procedure == "p"
    assert (s.stop.result, s.stop.steps_completed) == ("completed", 3)
    assert s.steps_completed == [(0, "s0"), (1, "s1"), (2, "s2")] and s.interrupted_step is None


def test_stop_record_failed_with_traceback_on_exception(tmp_path: Path) -> None:
    path = tmp_path / "fail.mcap"

    def move_turntable() -> None:
        raise RuntimeError("turntable did not reach 90.000 deg within 12.0 s")

    with pytest.raises(RuntimeError, match="turntable"):
        with RunRecorder(path, "p", {}) as rec:
            with rec.step("ok step", 0):
                pass
            with rec.step("moving", 1):
                move_turntable()
    s = read_summary(path)
    assert s.stop.result == "failed"
    assert "RuntimeError: turntable did not reach 90.000 deg" in s.stop.reason
    assert "move_turntable" in s.stop.traceback and "Traceback" in s.stop.traceback
    assert s.steps_completed == [(0, "ok step")]
    assert s.steps_failed == [(1, "moving", "RuntimeError: turntable did not reach 90.000 deg within 12.0 s")]
    assert s.stop.steps_completed == 1


def test_stop_record_aborted_on_keyboard_interrupt(tmp_path: Path) -> None:
    path = tmp_path / "abort.mcap"
    with pytest.raises(KeyboardInterrupt):
        with RunRecorder(path, "p", {}) as rec:
            with rec.step("waiting for operator", 0):
                raise KeyboardInterrupt
    s = read_summary(path)
    assert s.scan.complete
    assert s.stop.result == "aborted" and "KeyboardInterrupt" in s.stop.reason
    assert s.steps_failed and s.steps_failed[0][:2] == (0, "waiting for operator")


def test_stop_is_idempotent_and_closes_the_run(tmp_path: Path) -> None:
    path = tmp_path / "twice.mcap"
    rec = RunRecorder(path, "p", {})
    rec.stop("aborted", "operator said stop")
    rec.stop("failed", "second call is ignored")
    rec.__exit__(None, None, None)
    assert rec.stopped and rec.stop_record.result == "aborted"
    with pytest.raises(RuntimeError, match="stopped"):
        rec.log_text("info", "too late")
    rec.comms_sink(CommsRecord("ipjr1", "http://127.0.0.1:8101", "tx", b"GET /stop"))  # a late driver: no raise
    assert rec.dropped_after_stop == 1
    stops = [r for r in iter_messages(path) if r.topic == topics.RUN_STOP]
    assert len(stops) == 1 and stops[0].message.reason == "operator said stop"
    with pytest.raises(ValueError, match="run result must be one of"):
        RunRecorder(tmp_path / "bad.mcap", "p", {}).stop("success")


def test_bad_input_is_refused_with_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "bad.mcap"
    with RunRecorder(path, "p", {}) as rec:
        with pytest.raises(ValueError, match=r"K must be 3x3, got shape \(2, 2\)"):
            rec.log_calibration(topics.CAMERA_CALIBRATION, np.eye(2), [], 640, 480, "camera")
        with pytest.raises(ValueError, match="distortion must have"):
            rec.log_calibration(topics.CAMERA_CALIBRATION, np.eye(3), [0.1] * 6, 640, 480, "camera")
        with pytest.raises(ValueError, match="image dtype must be uint8"):
            rec.log_image(topics.CAMERA_IMAGE, np.zeros((4, 4), np.float32), None, "camera")
        with pytest.raises(ValueError, match="log level must be one of"):
            rec.log_text("loud", "x")
        rec.log_text("info", "fine")
        with pytest.raises(ValueError, match="carries foxglove.Log, cannot write a lab.JsonRecord"):
            rec.log_record(topics.LOG, m.JsonRecord(kind="x", json="{}"))
        with pytest.raises(RuntimeError, match="do not nest"):
            with rec.step("a", 0):
                with rec.step("b", 1):
                    pass
    with pytest.raises(UserError, match="already exists"):
        RunRecorder(path, "p", {})


def test_a_finished_step_is_on_disk_before_the_next_begins(tmp_path: Path) -> None:
    """Read the file while the writer is still open: everything of the finished steps is there."""
    path = tmp_path / "live.mcap"
    rec = RunRecorder(path, "p", {}, sync_interval_s=1e9)
    for i in range(2):
        with rec.step(f"s{i}", i):
            rec.log_record(topics.VERDICTS, m.module_verdict(f"M{i}", "ok"))
    between = tmp_path / "between.mcap"
    shutil.copyfile(path, between)  # after a step's end, before anything else happens
    assert [r.message.module for r in iter_messages(between, topics.VERDICTS)] == ["M0", "M1"]
    assert read_summary(between).steps_completed == [(0, "s0"), (1, "s1")]
    with rec.step("s2", 2):
        rec.log_record(topics.VERDICTS, m.module_verdict("M2", "ok"))  # still in memory: step not over
        copy = tmp_path / "copy.mcap"
        shutil.copyfile(path, copy)
    rec.stop("completed")
    s = read_summary(copy)
    assert not s.scan.complete and s.stop is None and s.result == "unknown"
    assert s.steps_completed == [(0, "s0"), (1, "s1")] and s.interrupted_step == (2, "s2")
    assert [r.message.module for r in iter_messages(copy, topics.VERDICTS)] == ["M0", "M1"]


KILLED_WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from lab.core.recorder import RunRecorder, topics, messages as m
    rec = RunRecorder(sys.argv[1], "killed", {"steps": 100}, structure="borg:3", sync_interval_s=1e9)
    img = (np.arange(120 * 160) % 251).astype(np.uint8).reshape(120, 160)
    for i in range(100):
        with rec.step(f"step {i}", i, {"i": i}):
            for j in range(4):
                rec.log_record(topics.VERDICTS, m.module_verdict(f"M{i}", "ok", reason=f"{i}.{j}"))
            rec.log_image(topics.CAMERA_IMAGE, img, None, "camera")
            if i == int(sys.argv[2]) and sys.argv[3] == "inside":
                print("waiting", flush=True)
                time.sleep(120)
        print(f"done {i}", flush=True)
        if i + 1 == int(sys.argv[2]) and sys.argv[3] == "between":
            print("waiting", flush=True)  # e.g. an operator prompt between two steps
            time.sleep(120)
""")


@pytest.mark.parametrize("where", ["inside", "between"])
def test_sigkill_mid_run_loses_nothing_of_the_completed_steps(tmp_path: Path, where: str) -> None:
    """SIGKILL the writer inside step 4, or after step 3 ended and before step 4 started."""
    path = tmp_path / "killed.mcap"
    n_done = 4
    proc = subprocess.Popen([sys.executable, "-c", KILLED_WRITER, str(path), str(n_done), where],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        lines = []
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line.strip())
            if line.startswith("waiting"):
                break
        assert lines[-1:] == ["waiting"], (lines, proc.stderr.read() if proc.poll() is not None else "")
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()

    def check(recorded: list, s) -> None:
        reasons = [r.message.reason for r in recorded if r.topic == topics.VERDICTS]
        for i in range(n_done):  # every message of every completed step is there
            assert [x for x in reasons if x.startswith(f"{i}.")] == [f"{i}.{j}" for j in range(4)]
        images = [r for r in recorded if r.topic == topics.CAMERA_IMAGE]
        assert len(images) >= n_done and all(len(r.message.data) > 100 for r in images)
        assert s.steps_completed == [(i, f"step {i}") for i in range(n_done)]
        assert s.interrupted_step == ((n_done, f"step {n_done}") if where == "inside" else None)

    # Directly: the footer-less file reads up to its last complete chunk.
    s = read_summary(path)
    assert not s.scan.complete and s.stop is None and s.start.procedure == "killed"
    check(list(iter_messages(path)), s)

    # After `lab recover`: a complete file the standard reader opens, with a stop record saying so.
    assert lab_main(["recover", str(path)]) == 0
    out = tmp_path / "killed.recovered.mcap"
    std = _standard_read(out)
    assert std[-1][0] == topics.RUN_STOP
    stop = std[-1][2]
    assert stop.result == "failed" and stop.recovered and stop.steps_completed == n_done
    assert (f"step {n_done} step {n_done} was running" in stop.reason) == (where == "inside")
    s2 = read_summary(out)
    assert s2.scan.complete
    check(list(iter_messages(out)), s2)
    assert lab_main(["recover", str(path)]) == 2  # output exists: refused, not overwritten


def test_recover_drops_a_torn_tail_and_keeps_the_rest(tmp_path: Path) -> None:
    path = tmp_path / "torn.mcap"
    rec = RunRecorder(path, "p", {}, sync_interval_s=1e9)
    for i in range(3):
        with rec.step(f"s{i}", i):
            rec.log_record(topics.VERDICTS, m.module_verdict(f"M{i}", "ok"))
    size_after_3 = path.stat().st_size
    with rec.step("s3", 3):
        rec.log_record(topics.VERDICTS, m.module_verdict("M3", "ok", reason="x" * 5000))
    rec.sync()
    full = path.read_bytes()
    rec.stop("completed")
    torn = tmp_path / "torn_copy.mcap"
    cut = size_after_3 + (len(full) - size_after_3) // 2 + 40  # inside the last chunk
    torn.write_bytes(full[:cut])
    rep = recover(torn, tmp_path / "fixed.mcap")
    assert rep.steps_completed == 3 and rep.dropped_bytes > 0 and not rep.was_complete
    assert rep.interrupted_step == "3 s3"
    mods = [r.message.module for r in iter_messages(rep.path_out, topics.VERDICTS)]
    assert mods == ["M0", "M1", "M2"]
    # A file that is already complete and intact is left alone: nothing written.
    rep2 = recover(path, tmp_path / "same.mcap")
    assert rep2.intact and rep2.was_complete and rep2.had_stop and rep2.steps_completed == 4
    assert not (tmp_path / "same.mcap").exists()
    notes = tmp_path / "notes.txt"
    notes.write_text("hello")
    with pytest.raises(UserError, match="not an MCAP file"):
        recover(notes, tmp_path / "x.mcap")
