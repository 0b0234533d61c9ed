"""Issue 11, simulated servers: request timeouts, bounded connections, duplicate or malformed
parameters refused, fixed ports outside the ephemeral range, tagged serial replies."""

from __future__ import annotations

import socket
import time
import urllib.error
import urllib.request

import pytest

from drivers.testing import fast_sim_rig
from lab.core.config import load_rig
from sim_devices import http_server
from sim_devices.bench import ephemeral_port_range, ports_in_ephemeral_range, start_sim_bench


@pytest.fixture(scope="module")
def bench():
    with start_sim_bench(fast_sim_rig(), speedup=200) as b:
        yield b


def _get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


@pytest.mark.parametrize("query", ["steps=5&steps=-1000", "steps=5&&", "steps", "steps=5&x=1"])
def test_duplicate_or_malformed_parameters_are_refused_and_nothing_moves(bench, query):
    act = bench.world.ipjrs["ipjr1"]
    before = act.extension_m()
    status, body = _get(f"{bench.urls['ipjr1']}/step?{query}")
    assert status == 400, body
    time.sleep(0.05)
    assert act.extension_m() == before and not act.moving()


def test_an_unfinished_request_does_not_hold_a_thread_for_ever(bench, monkeypatch):
    host, port = bench.urls["ipjr2"].split("//")[1].split(":")
    socks = []
    for _ in range(http_server.MAX_CONNECTIONS + 10):     # more half-open requests than slots
        s = socket.create_connection((host, int(port)))
        s.sendall(b"GET /volts HTTP/1.0\r\n")               # never finished
        socks.append(s)
    time.sleep(0.5)
    extra = socket.create_connection((host, int(port)), timeout=5)
    extra.sendall(b"GET /volts HTTP/1.0\r\n\r\n")
    assert extra.recv(100).startswith(b"HTTP/1.0 503")       # turned away at once, no thread held
    for s in socks:
        s.close()
    deadline = time.time() + http_server.REQUEST_TIMEOUT_S + 3
    while time.time() < deadline:                            # slots come back
        status, _ = _get(f"{bench.urls['ipjr2']}/volts")
        if status == 200:
            break
        time.sleep(0.2)
    assert status == 200


def test_the_line_server_echoes_request_tags(bench):
    host, port = bench.urls["turntable"].split("//")[1].split(":")
    with socket.create_connection((host, int(port)), timeout=2) as s:
        s.sendall(b"#42 ID?\nID?\n")
        data = b""
        while data.count(b"\n") < 2:
            data += s.recv(200)
    tagged, plain = data.split(b"\n")[:2]
    assert tagged.startswith(b"#42 OK TURNTABLE") and plain.startswith(b"OK TURNTABLE")


def test_ephemeral_range_check_finds_ports_inside_it():
    lo, hi = ephemeral_port_range()
    rig = fast_sim_rig().with_urls({"turntable": f"socket://127.0.0.1:{lo}", "stewart": f"socket://127.0.0.1:{lo - 1}"})
    risky = dict(ports_in_ephemeral_range(rig))
    assert risky.get("turntable") == lo and "stewart" not in risky


def test_the_packaged_sim_rig_listens_outside_the_ephemeral_range():
    assert ports_in_ephemeral_range(load_rig(None)) == []


def test_stop_waits_for_a_request_under_way():
    """A request thread is a daemon: one still rendering (inside OpenCV) when the interpreter exits
    is killed inside C++ and aborts the process, so a run aborted mid-frame exited with SIGABRT.
    stop() must return only once the request under way has ended."""
    import threading

    from sim_devices.faults import FaultInjector

    started, finished = threading.Event(), threading.Event()

    def slow(query, stuck):
        started.set()
        time.sleep(0.6)
        finished.set()
        return 200, "text/plain", b"done", {}

    server = http_server.HttpDeviceServer("slow", {"/slow": slow}, FaultInjector("slow", http=True)).start()
    client = threading.Thread(target=_get, args=(f"{server.url}/slow",), daemon=True)
    client.start()
    assert started.wait(5)
    server.stop()
    assert finished.is_set()
    client.join(5)
