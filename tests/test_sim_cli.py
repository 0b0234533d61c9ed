"""`lab sim` and `lab devices check` as a new user runs them (on free ports, so tests never
collide with a `lab sim` someone left running)."""

from __future__ import annotations

import json
import re
import signal
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

from lab.cli import main
from lab.core.config import default_rig_path

DEFAULT_PORTS = (27101, 27102, 27103, 27104, 27111, 27112, 27113)


def free_ports(n: int) -> list[int]:
    socks = []
    for _ in range(n):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        socks.append(s)
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def rig_on_free_ports(tmp_path: Path, **replace: str) -> Path:
    text = default_rig_path().read_text()
    for old, new in zip(DEFAULT_PORTS, free_ports(len(DEFAULT_PORTS))):
        text = text.replace(f"127.0.0.1:{old}", f"127.0.0.1:{new}")
    text = text.replace('calibration = "sim_camera.json"',
                        f'calibration = "{default_rig_path().parent / "sim_camera.json"}"')
    text = text.replace("speedup = 10.0", "speedup = 200.0")
    for old, new in replace.items():
        text = text.replace(old, new)
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return path


def test_lab_sim_serves_every_device_until_ctrl_c(lab, tmp_path):
    rig = rig_on_free_ports(tmp_path)
    proc = lab.popen(["sim", "--rig", str(rig), "--duration", "60"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                     text=True)
    try:
        lines = []
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("Ctrl-C stops"):
                break
        out = "".join(lines)
        urls = dict(re.findall(r"^\s+(\w+)\s+\w+\s+(\S+)", out, re.M))
        assert set(urls) >= {"turntable", "stewart", "lift", "camera", "ipjr1", "ipjr2", "ipjr3"}, out
        ptys = re.findall(r"pty (/dev/\S+)", out)
        assert len(ptys) == 4                                   # turntable, stewart, lift, ipjr3
        # a serial terminal's view of the turntable
        host, port = urls["turntable"].removeprefix("socket://").split(":")
        with socket.create_connection((host, int(port)), timeout=2) as s:
            s.sendall(b"ID?\r\n")
            assert s.makefile("rb").readline() == b"OK TURNTABLE LAB-RT1 1.0\n"
        # curl's view of an IPJR
        with urllib.request.urlopen(urls["ipjr1"] + "/volts", timeout=2) as r:
            assert set(json.loads(r.read())) == {"volts"}
        # and lab devices check, from another process, sees the running simulators
        check = lab(["devices", "check", "--rig", str(rig), "--json"], timeout=60)
        report = json.loads(check.stdout)
        assert check.returncode == 0 and report["simulator"] == "external"
        assert all(d["ok"] for d in report["devices"]), report
        proc.send_signal(signal.SIGINT)                          # Ctrl-C
        rest, err = proc.communicate(timeout=10)
        assert proc.returncode == 0 and "lab sim: stopped" in rest, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_devices_check_starts_the_simulators_when_nothing_answers(tmp_path, capsys):
    rig = rig_on_free_ports(tmp_path)
    assert main(["devices", "check", "--rig", str(rig), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["simulator"] == "in-process"
    assert [d["name"] for d in report["devices"]] == ["turntable", "stewart", "lift", "camera", "ipjr1", "ipjr2",
                                                      "ipjr3"]
    for d in report["devices"]:
        assert set(d) == {"name", "kind", "url", "ok", "detail"} and d["ok"], d
    assert "NOT homed" in report["devices"][0]["detail"]


def test_devices_check_without_simulators_says_nothing_answers(tmp_path, capsys):
    rig = rig_on_free_ports(tmp_path, **{"reply_timeout_s = 0.5": "reply_timeout_s = 0.2\nretries = 0",
                                         "retries = 2\n": "", "timeout_s = 3.0": "timeout_s = 0.3"})
    assert main(["devices", "check", "--rig", str(rig), "--json", "--no-start-sim"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["simulator"] == "not running"
    for d in report["devices"]:
        assert not d["ok"] and ("connection refused" in d["detail"] or "cannot connect" in d["detail"]), d


def test_a_bad_rig_file_is_one_line_naming_the_key(tmp_path, capsys):
    rig = rig_on_free_ports(tmp_path, **{"max_deg = 360.0\nreply": "max_deg = \"lots\"\nreply"})
    assert main(["devices", "check", "--rig", str(rig)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "[turntable].max_deg: expected a number in deg, got 'lots'" in err

