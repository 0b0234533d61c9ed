"""`lab review` works anywhere: without a display it serves the web viewer on loopback and prints
its URL instead of hanging on a native viewer that cannot open a window; each run has its own
recording id; a saved layout (blueprint) travels with the recording."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
import urllib.parse
import urllib.request
import warnings
from pathlib import Path

import pytest
from rerun.chunk import RrdReader

from lab.cli import main as lab_main
from lab.core.review import review, rrd_entity_paths
from lab.core.viewer import check_connect_url, choose_mode, has_display, rerun_command
from test_review import _write_run


def _view_names(rrd: Path) -> list[set[str]]:
    """The view names of each blueprint stored in an .rrd."""
    reader = RrdReader(rrd)
    out = []
    for entry in reader.blueprints():
        names: set[str] = set()
        for chunk in reader.store(store=entry).stream():
            batch = chunk.to_record_batch()
            if "ViewBlueprint:display_name" in batch.schema.names:
                names.update(v[0] for v in batch.column("ViewBlueprint:display_name").to_pylist() if v)
        out.append(names)
    return out


def test_without_a_display_review_serves_the_web_viewer_on_loopback_and_stops_on_ctrl_c(lab, tmp_path: Path) -> None:
    run = tmp_path / "run.mcap"
    _write_run(run)
    proc = lab.popen(["review", str(run)], env=lab.env(drop=lab.NO_DISPLAY), cwd=tmp_path, text=True,
                     stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        lines: list[str] = []
        deadline = time.monotonic() + 90
        url = ""
        while time.monotonic() < deadline and proc.poll() is None:
            line = proc.stdout.readline()
            lines.append(line)
            if "open http://" in line:
                url = line.split("open ", 1)[1].strip()
                break
        assert url, f"no URL printed; output: {''.join(lines)}{proc.stderr.read() if proc.poll() is not None else ''}"
        out = "".join(lines)
        assert "no display" in out and "recording id: lab-run-" in out
        assert url.startswith("http://127.0.0.1:") and "proxy" in url
        with urllib.request.urlopen(url, timeout=20) as resp:   # the web viewer's page is really served
            assert resp.status == 200 and b"<html" in resp.read(4096).lower()
        # and so is the run: what a browser would get from the proxy, saved by a rerun client
        grpc_url = urllib.parse.parse_qs(urllib.parse.urlparse(url).query)["url"][0]
        got = tmp_path / "from_proxy.rrd"
        review(run, tmp_path / "direct.rrd")
        want = rrd_entity_paths(tmp_path / "direct.rrd")
        client = subprocess.Popen([*rerun_command(), "--bind", "127.0.0.1", "--connect", grpc_url, "--save", str(got)],
                                  env=lab.env(drop=lab.NO_DISPLAY), stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        have: set[str] = set()
        try:   # the client saves for as long as the proxy serves: wait for the whole run, then stop it
            deadline = time.monotonic() + 60
            while have != want and time.monotonic() < deadline:
                time.sleep(0.5)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")     # a streamed .rrd has no footer yet
                    try:
                        have = rrd_entity_paths(got)
                    except Exception:
                        pass
        finally:
            client.send_signal(signal.SIGINT)
            client.wait(timeout=30)
        assert have == want
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
        assert "ERROR" not in proc.stderr.read()      # no severed-connection complaints at exit
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_without_a_display_save_returns_promptly(lab, tmp_path: Path) -> None:
    run, rrd = tmp_path / "run.mcap", tmp_path / "out" / "run.rrd"
    rrd.parent.mkdir()
    _write_run(run)
    r = lab(["review", str(run), "--save", str(rrd)], env=lab.env(drop=lab.NO_DISPLAY), timeout=120)
    assert r.returncode == 0, r.stderr
    assert f"wrote {rrd}" in r.stdout and rrd.stat().st_size > 0


def test_the_mode_follows_the_display() -> None:
    assert not has_display({}) or sys.platform in ("darwin", "win32")
    assert has_display({"DISPLAY": ":0"}) and has_display({"WAYLAND_DISPLAY": "wayland-0"})
    if sys.platform not in ("darwin", "win32"):
        assert choose_mode(None, None, False, {}) == "web"
        assert choose_mode(None, None, False, {"DISPLAY": ":0"}) == "spawn"
    assert choose_mode("x.rrd", None, False, {}) == "save"
    assert choose_mode(None, "127.0.0.1:9876", False, {"DISPLAY": ":0"}) == "connect"
    assert choose_mode(None, None, True, {"DISPLAY": ":0"}) == "web"
    assert check_connect_url("127.0.0.1:9876") == "rerun+http://127.0.0.1:9876/proxy"


def test_each_run_has_its_own_recording_id(tmp_path: Path) -> None:
    a, b = tmp_path / "a" / "run.mcap", tmp_path / "b" / "run.mcap"
    for p in (a, b):
        p.parent.mkdir()
        _write_run(p)
    ra = review(a, tmp_path / "a.rrd")
    rb = review(b, tmp_path / "b.rrd")
    again = review(a, tmp_path / "a2.rrd")
    assert ra.recording_id != rb.recording_id           # two runs opened together stay apart
    assert ra.recording_id == again.recording_id        # the same run is the same recording
    assert [e.recording_id for e in RrdReader(tmp_path / "b.rrd").recordings()] == [rb.recording_id]


def test_the_saved_recording_carries_its_layout(tmp_path: Path) -> None:
    run, rrd = tmp_path / "run.mcap", tmp_path / "run.rrd"
    _write_run(run)
    review(run, rrd)
    layouts = _view_names(rrd)
    assert layouts, "no blueprint in the .rrd"
    final = [names for names in layouts if "strut length error (mm)" not in names]
    assert final, f"no layout without the empty strut-length tab: {layouts}"
    assert {"structure", "camera", "verdicts", "tag error (mm)", "verdict position error (mm)",
            "reprojection error (px)", "metrics", "steps", "run"} <= final[0]


def test_bad_review_input_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run.mcap"
    _write_run(run)
    assert lab_main(["review", str(tmp_path / "missing.mcap")]) == 2
    assert lab_main(["review", str(run), "--save", str(tmp_path / "nodir" / "x.rrd")]) == 2
    assert lab_main(["review", str(run), "--connect", "http://x:1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("lab: error: ") for line in err), err
