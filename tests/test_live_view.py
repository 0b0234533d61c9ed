"""`lab run ... --view`: the run streamed to Rerun as it happens, drawn by the same code as
`lab review`, so the live recording and the review of the finished run hold the same entities under
the same recording id.  The viewer here is a real `rerun` process on loopback that saves what it
receives; no window is opened.  (The live view's cost in wall time is a benchmark figure, in
docs/recording.md, not a timed test.)"""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
import urllib.parse
import warnings
from pathlib import Path

from rerun.chunk import RrdReader

from lab.core.review import review, rrd_entity_paths
from lab.core.viewer import free_port

SHORT_BORG = ["run", "borg", "--auto", "--no-rig-survey", "--modules", "2", "--speedup", "40"]


def _env(lab) -> dict[str, str]:
    return lab.env(drop=lab.NO_DISPLAY, RERUN_ANALYTICS="false")


def _listening(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return True
    except OSError:
        return False


def test_the_live_view_is_the_review_of_the_same_run(lab, run_dir, tmp_path: Path) -> None:
    port, rrd = free_port(), tmp_path / "live.rrd"
    receiver = subprocess.Popen([sys.executable, "-m", "rerun", "--port", str(port), "--bind", "127.0.0.1",
                                 "--save", str(rrd)], env=_env(lab), stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while not _listening(port):
            assert receiver.poll() is None and time.monotonic() < deadline, "the rerun receiver did not start"
            time.sleep(0.1)
        out = run_dir
        r = lab(SHORT_BORG + ["--view", f"127.0.0.1:{port}", "--out", str(out)], env=_env(lab))
        assert r.returncode == 0, r.stdout + r.stderr
        assert f"live view: sent to the Rerun viewer at rerun+http://127.0.0.1:{port}/proxy" in r.stdout
    finally:
        receiver.send_signal(signal.SIGINT)     # the receiver closes its file
        receiver.wait(timeout=30)
    rep = review(out / "run.mcap", tmp_path / "review.rrd")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")         # a streamed .rrd has no footer: read by a whole-file scan
        live = rrd_entity_paths(rrd)
        live_ids = [e.recording_id for e in RrdReader(rrd).recordings()]
    assert live_ids == [rep.recording_id]
    assert live == rrd_entity_paths(tmp_path / "review.rrd")
    for entity in ("/world/camera/image", "/world/camera/image/detections", "/world/structure/design/tags",
                   "/world/structure/estimate/tags", "/verdicts", "/plots/tag_error_mm/max", "/run/info"):
        assert entity in live, entity


def test_without_a_display_the_live_view_serves_the_web_viewer_and_stops_it_with_the_run(lab, run_dir) -> None:
    r = lab(SHORT_BORG + ["--view", "--out", str(run_dir)], env=_env(lab), stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stdout + r.stderr
    first = r.stdout.splitlines()[0]
    assert first.startswith("live view: serving the Rerun web viewer on loopback (no display")
    url = first.split("open ", 1)[1]
    web_port = urllib.parse.urlparse(url).port
    grpc_port = urllib.parse.urlparse(urllib.parse.parse_qs(urllib.parse.urlparse(url).query)["url"][0]).port
    assert "web viewer stopped with the run" in r.stdout
    assert "ERROR" not in r.stderr and "ERROR" not in r.stdout   # the SDK let go before the viewer stopped
    assert not _listening(web_port) and not _listening(grpc_port)   # nothing left behind


def test_a_view_url_nothing_answers_at_is_refused_before_the_run(lab, run_dir) -> None:
    port = free_port()
    r = lab(SHORT_BORG + ["--view", f"127.0.0.1:{port}", "--out", str(run_dir)], env=_env(lab), timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [f"lab: error: --view/--connect rerun+http://127.0.0.1:{port}/proxy: "
                                             f"no Rerun viewer answers there (start one with `rerun`, or leave out "
                                             f"the URL)"]
    assert not run_dir.exists()
