"""Transports: one transaction per request under a per-port lock, replies parsed, timeouts,
retries for queries only, reconnect after a dropped link, every byte in the comms log."""

from __future__ import annotations

import math
import threading
import time

import pytest

from drivers.errors import DeviceFault, DeviceTimeout, Disconnected, ProtocolError
from drivers.testing import ScriptedHttpDevice, ScriptedLineDevice
from drivers.transport import HttpTransport, LineTransport, open_transport, parse_reply, port_lock
from lab.core.comms import MemoryComms


def test_parse_reply_shapes():
    assert parse_reply("d", "X?", b"OK\n") == ""
    assert parse_reply("d", "X?", b"OK 1 2 3\r\n") == "1 2 3"
    with pytest.raises(DeviceFault) as err:
        parse_reply("d", "MOVE 1", b"ERR 20 angle 400.000 deg outside [-360.000, 360.000] deg\n")
    assert err.value.code == 20 and err.value.text.startswith("angle 400.000 deg")
    for bad in (b"\xff\xfe\n", b"HELLO\n", b"ERR x y\n", b"OK \x07\n"):
        with pytest.raises(ProtocolError):
            parse_reply("d", "X?", bad)


def test_queries_are_retried_after_a_timeout_and_commands_are_not():
    comms = MemoryComms()
    with ScriptedLineDevice([(b"POS?\n", None), (b"POS?\n", b"OK 1.000\n")]) as dev:
        link = LineTransport("tt", dev.url, comms, reply_timeout_s=0.1, retries=2)
        assert link.request("POS?") == "1.000"
    assert any("retry 1/2" in r.note for r in comms.records if r.direction == "event")

    with ScriptedLineDevice([(b"MOVE 1.000\n", None)]) as dev:   # exactly one MOVE may be sent
        link = LineTransport("tt", dev.url, MemoryComms(), reply_timeout_s=0.1, retries=2)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match=r"no reply to 'MOVE 1.000' within 0.1 s"):
            link.request("MOVE 1.000")
        assert time.monotonic() - t0 < 0.5


def test_a_device_that_never_answers_gives_up_after_bounded_retries():
    with ScriptedLineDevice([(b"ID?\n", None)] * 3) as dev:
        link = LineTransport("tt", dev.url, MemoryComms(), reply_timeout_s=0.1, retries=2)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match=r"gave up after 3 attempts"):
            link.request("ID?")
        assert time.monotonic() - t0 < 1.0


def test_a_late_reply_is_discarded_not_taken_for_the_next_one():
    comms = MemoryComms()
    # The first reply arrives only with the second request (too late); the third is the real answer.
    with ScriptedLineDevice([(b"POS?\n", None), (b"POS?\n", b"OK 1.000\n"), (b"ID?\n", b"OK TURNTABLE X 1\n")]) as dev:
        link = LineTransport("tt", dev.url, comms, reply_timeout_s=0.1, retries=1)
        assert link.request("POS?") == "1.000"
        assert link.request("ID?") == "TURNTABLE X 1"


def test_nothing_answering_is_a_clear_disconnected_error():
    link = LineTransport("turntable", "socket://127.0.0.1:9", MemoryComms(), reply_timeout_s=0.1, retries=0)
    with pytest.raises(Disconnected, match="connection refused .*lab sim"):
        link.request("ID?")
    http = HttpTransport("ipjr1", "http://127.0.0.1:9", MemoryComms(), reply_timeout_s=0.1, retries=0)
    with pytest.raises(Disconnected, match="cannot connect"):
        http.get_json("/volts", idempotent=True)


def test_comms_log_has_every_byte_with_device_and_url():
    comms = MemoryComms()
    with ScriptedLineDevice([(b"ID?\n", b"OK TURNTABLE X 1\n")]) as dev:
        LineTransport("turntable", dev.url, comms).request("ID?")
    wire = [r for r in comms.records if r.direction != "event"]
    assert [(r.direction, r.data) for r in wire] == [("tx", b"#1 ID?\n"), ("rx", b"#1 OK TURNTABLE X 1\n")]
    assert all(r.device == "turntable" and r.url == dev.url for r in comms.records)

    comms = MemoryComms()
    with ScriptedHttpDevice([("/volts", 200, '{"volts": 1.25}')]) as dev:
        assert HttpTransport("ipjr1", dev.url, comms, reply_timeout_s=2).get_json("/volts", idempotent=True) == {"volts": 1.25}
    tx = [r.data for r in comms.records if r.direction == "tx"]
    rx = [r.data for r in comms.records if r.direction == "rx"]
    assert tx[0].startswith(b"GET /volts HTTP/1.1\r\nHost: 127.0.0.1:") and tx[0].endswith(b"\r\n\r\n")
    assert rx[0].startswith(b"HTTP/1.0 200 OK\r\n") and rx[0].endswith(b'{"volts": 1.25}')


def test_http_5xx_is_retried_for_reads_only():
    with ScriptedHttpDevice([("/volts", 500, "oops"), ("/volts", 200, '{"volts": 1.0}')]) as dev:
        assert HttpTransport("ipjr1", dev.url, reply_timeout_s=2).get_json("/volts", idempotent=True) == {"volts": 1.0}
    with ScriptedHttpDevice([("/step?steps=3", 500, '{"error": {"code": 50, "text": "boom"}}')]) as dev:
        with pytest.raises(DeviceFault, match="boom"):
            HttpTransport("ipjr1", dev.url, reply_timeout_s=2).get_json("/step", {"steps": 3}, idempotent=False)


def test_one_lock_per_port():
    a = open_transport("a", "socket://127.0.0.1:1")
    b = open_transport("b", "socket://127.0.0.1:1")
    c = open_transport("c", "http://127.0.0.1:8/x")
    assert a.lock is b.lock and a.lock is port_lock("socket://127.0.0.1:1")
    assert c.lock is port_lock("http://127.0.0.1:8/other") and c.lock is not a.lock


def test_threads_sharing_a_port_never_get_each_others_replies(bench):
    link = LineTransport("turntable", bench.urls["turntable"], MemoryComms())
    errors: list[str] = []

    def worker(query: str, prefix: str) -> None:
        for _ in range(40):
            reply = link.request(query)
            if not reply.startswith(prefix):
                errors.append(f"{query} -> {reply}")

    threads = [threading.Thread(target=worker, args=a) for a in
               [("ID?", "TURNTABLE"), ("POS?", "0.000"), ("LIMITS?", "min_deg="), ("STATUS?", "state=")]]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert not errors


def test_a_dropped_link_is_reopened_by_the_next_query(bench):
    comms = MemoryComms()
    link = LineTransport("turntable", bench.urls["turntable"], comms, reply_timeout_s=0.25, retries=2)
    assert link.request("POS?") == "0.000"
    bench.drop_connections("turntable")
    time.sleep(0.05)
    assert link.request("POS?") == "0.000"          # recovered
    notes = " | ".join(r.note for r in comms.records if r.direction == "event")
    assert "link lost" in notes and notes.count("opened") >= 2


def test_rig_timeouts_reach_the_transport(bench):
    rig = bench.rig
    import drivers

    with drivers.connect(rig) as devs:
        assert devs.turntable.link.reply_timeout_s == pytest.approx(0.25)
        assert devs.turntable.position() == pytest.approx(0.0)
        assert math.isfinite(devs.ipjrs["ipjr1"].volts())
