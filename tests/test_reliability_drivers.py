"""Issue 11, driver layer: no NaN on the wire, bounded moves, stale replies never matched, HTTP
query replies validated inside the retry loop, one owner per device across processes, and a run
never stopping a device it did not move."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import threading

import numpy as np
import pytest

import drivers
from drivers.errors import DeviceTimeout, OutOfRange, WorkspaceError
from drivers.motion import MotionPlan
from drivers.ownership import DeviceBusy
from drivers.stewart import Stewart
from drivers.testing import ScriptedHttpDevice, ScriptedLineDevice, fast_sim_rig
from drivers.transport import LineTransport
from drivers.turntable import Turntable
from lab.core.comms import MemoryComms
from lab.core.config import load_rig



def _stewart(url: str) -> Stewart:
    cfg = load_rig(None).stewart
    return Stewart.open(cfg.__class__(cfg.name, cfg.link.__class__(url, 0.2, 0, 0.2), cfg.geometry, cfg.world_T_base))


@pytest.mark.parametrize("pose", [[0, 0, 0, math.nan, 0, 0], [math.inf, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 1e12]])
def test_a_pose_that_is_no_pose_never_reaches_the_wire(pose):
    with ScriptedLineDevice([]) as dev:            # no request at all may arrive
        st = _stewart(dev.url)
        with pytest.raises(WorkspaceError):
            st.move_to(pose)
        assert not st.moved


def test_ik_calls_a_wound_up_or_nan_pose_unreachable(lab):
    r = lab(["stewart", "ik", "0", "0", "0", "0", "0", "1e12", "--json"], timeout=60)
    doc = json.loads(r.stdout)
    assert doc["reachable"] is False and "yaw" in doc["reason"]
    r = lab(["stewart", "ik", "0", "0", "0", "nan", "0", "0", "--json"], timeout=60)
    assert r.returncode == 2 and "finite" in r.stderr       # refused in one line by the CLI


def test_non_finite_values_are_refused_by_the_transports():
    with ScriptedLineDevice([]) as dev:
        with pytest.raises(ValueError, match="not a finite number"):
            LineTransport("t", dev.url).request("LEGS nan 1 2 3 4 5", idempotent=False)
    with ScriptedHttpDevice([]) as dev:
        from drivers.transport import HttpTransport

        with pytest.raises(ValueError, match="not a finite number"):
            HttpTransport("ipjr", dev.url).get_json("/step", {"steps": float("inf")}, idempotent=False)


def test_a_move_longer_than_the_physics_bound_is_refused_before_sending():
    with pytest.raises(OutOfRange, match="duration of the move"):
        MotionPlan.of("to 90 deg", 90.0, 0.001, 0.1, 1.0, "turntable")


def test_a_late_reply_is_never_taken_for_the_next_requests():
    """A device answers POS? too late: the driver times out, then asks again; the late reply
    (tag #1) arrives first and must be discarded, the answer to #2 taken."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]

    def serve() -> None:
        conn, _ = srv.accept()
        f = conn.makefile("rb")
        first = f.readline()                 # "#1 POS?": not answered in time
        second = f.readline()                # "#2 POS?"
        conn.sendall(first.split(b" ")[0] + b" OK 11.000\n" + second.split(b" ")[0] + b" OK 22.000\n")
        f.readline()
        conn.close()

    threading.Thread(target=serve, daemon=True).start()
    comms = MemoryComms()
    link = LineTransport("turntable", f"socket://127.0.0.1:{port}", comms, reply_timeout_s=0.2, retries=0)
    with pytest.raises(DeviceTimeout):
        link.request("POS?")
    assert link.request("POS?") == "22.000"
    assert any("stale reply discarded" in r.note for r in comms.records)
    link.close()
    srv.close()


def test_a_garbled_http_query_reply_is_retried():
    with ScriptedHttpDevice([("/volts", 200, b"\xff\xfe garbage"), ("/volts", 200, '{"volts": 2.5}')]) as dev:
        from drivers.ipjr import Ipjr

        cfg = load_rig(None).ipjrs["ipjr1"]
        ipjr = Ipjr.open(cfg.__class__(**{**cfg.__dict__, "link": cfg.link.__class__(dev.url, 0.5, 2, 0.2)}))
        assert ipjr.volts() == 2.5
    with ScriptedHttpDevice([("/moving", 200, '{"moving": "perhaps"}'), ("/moving", 200, '{"moving": false}')]) as dev:
        ipjr = Ipjr.open(cfg.__class__(**{**cfg.__dict__, "link": cfg.link.__class__(dev.url, 0.5, 2, 0.2)}))
        assert ipjr.moving() is False


def test_a_second_process_is_refused_a_device_this_one_owns(tmp_path):
    rig = fast_sim_rig().with_urls({"turntable": "socket://127.0.0.1:1"})
    with drivers.connect(rig, only=["turntable"]) as devs:
        code = ("import drivers, sys; from drivers.testing import fast_sim_rig\n"
                "rig = fast_sim_rig().with_urls({'turntable': 'socket://127.0.0.1:1'})\n"
                "from lab.core.locks import set_holder\n"
                "try:\n    drivers.connect(rig, only=['turntable'])\nexcept Exception as e:\n"
                "    print(type(e).__name__, e); sys.exit(0)\nsys.exit(5)\n")
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stdout + r.stderr
        assert r.stdout.startswith("DeviceBusy") and "turntable" in r.stdout and "pid" in r.stdout
        assert devs.turntable is not None
    # released on close: this process may claim it again, and so may another
    with drivers.connect(rig, only=["turntable"]):
        pass


def test_same_process_claims_are_counted():
    rig = fast_sim_rig().with_urls({"turntable": "socket://127.0.0.1:2"})
    a = drivers.connect(rig, only=["turntable"])
    b = drivers.connect(rig, only=["turntable"])
    a.close()
    from drivers.ownership import held_keys

    assert "tcp:local:2" in held_keys()          # the device, not its spelling
    b.close()
    assert "tcp:local:2" not in held_keys()


def test_busy_error_is_a_user_error_naming_the_device():
    assert issubclass(DeviceBusy, Exception)
    from lab.core.errors import UserError

    assert issubclass(DeviceBusy, UserError)


def test_a_cleanly_refused_move_does_not_count_as_moved():
    status = b"OK state=IDLE pos_deg=0.000 target_deg=0.000 homed=1 fault=none\n"
    limits = b"OK min_deg=-360.000 max_deg=360.000 speed_deg_s=1000.000 settle_s=0.000\n"
    with ScriptedLineDevice([(b"LIMITS?\n", limits), (b"STATUS?\n", status),
                             (b"MOVE 10.000\n", b"ERR 31 busy: a motion is in progress\n")]) as dev:
        cfg = load_rig(None).turntable
        tt = Turntable.open(cfg.__class__(cfg.name, cfg.link.__class__(dev.url, 0.3, 0, 0.2), cfg.min_rad, cfg.max_rad))
        with pytest.raises(Exception, match="busy"):
            tt.move_to(math.radians(10))
        assert tt.moved is False


def test_stewart_legs_are_checked_again_just_before_the_wire():
    with ScriptedLineDevice([]) as dev:
        st = _stewart(dev.url)
        with pytest.raises(OutOfRange, match="leg 1 length"):
            st._move_legs(np.full(6, np.nan), "to nowhere", None)


def test_a_serial_ipjr_whose_link_keeps_dropping_says_so():
    """Found by the campaign: each move cut short by a dropped link, the controller ran out of
    tries and blamed the length; the link loss must be named."""
    from drivers.errors import Disconnected
    from sim_devices.bench import start_sim_bench

    with start_sim_bench(fast_sim_rig(0.1, 0.3), speedup=200) as bench:
        bench.inject("ipjr3", "disconnect", after_commands=0, count=0)
        with drivers.connect(bench.rig, only=["ipjr3"]) as devs:
            bench.world.ipjrs["ipjr3"].attach(0.8)
            ip = devs.ipjrs["ipjr3"]
            ip.attach(0.8)
            with pytest.raises(Disconnected, match="link to socket://.* lost during 2 moves in a row"):
                ip.set_length(0.8123)
        assert not bench.world.ipjrs["ipjr3"].moving()


def test_clean_up_stops_only_devices_the_driver_moved():
    from procedures.setup import Bench

    class Dev:
        def __init__(self, moved):
            self.moved, self.stops = moved, 0

        def stop(self):
            self.stops += 1

    class Devs(dict):
        pass

    b = Bench(rig=None, scenario=None)
    b.devices = Devs(turntable=Dev(False), stewart=Dev(True))
    b.moved = {"turntable", "stewart"}
    assert b.stop_moved() == ["stewart stopped"]
    assert b.devices["turntable"].stops == 0


def test_a_link_lost_while_homing_is_named_as_such():
    """The issue: a turntable `disconnect` during HOME reported 'homing ended without finding the
    index' instead of the lost link."""
    from drivers.errors import Disconnected
    from sim_devices.bench import start_sim_bench

    with start_sim_bench(fast_sim_rig(0.25, 0.2), speedup=20) as bench:
        with drivers.connect(bench.rig, only=["turntable"]) as devs:
            devs.turntable.move_to  # noqa: B018 (the driver exists)
            bench.inject("turntable", "disconnect")       # the first command while homing
            with pytest.raises(Disconnected, match="link to socket://.* lost during the move .*homing"):
                devs.turntable.home()
        assert not bench.world.turntable.moving()


def test_a_real_serial_port_is_opened_exclusively():
    """A device path (here a simulator's pseudo-terminal) is opened with an exclusive lock: a
    second opener is refused instead of talking over the first one's requests."""
    from drivers.errors import Disconnected
    from sim_devices.bench import start_sim_bench

    with start_sim_bench(fast_sim_rig(), speedup=200, pty=True) as bench:
        path = bench.pty_paths["turntable"]
        first = LineTransport("turntable", path, reply_timeout_s=0.5, retries=0)
        assert first.request("ID?").startswith("TURNTABLE")
        second = LineTransport("turntable", path, reply_timeout_s=0.5, retries=0)
        with pytest.raises(Disconnected, match="cannot open"):
            second.open()
        first.close()
        second.open()                 # free again once the first lets go
        assert second.request("ID?").startswith("TURNTABLE")
        second.close()
