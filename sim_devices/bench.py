"""Start the whole simulated bench of a rig, in this process.

    with start_sim_bench(load_rig(), scenario) as bench:      # free ports by default
        devices = drivers.connect(bench.rig, sink)             # bench.rig: the rig with the served URLs
        bench.world.borg.place("1P")                           # act as the operator
        bench.inject("turntable", "timeout", after_commands=3) # fault injection for tests

Serial devices listen on loopback TCP (`socket://127.0.0.1:PORT`) and, with `pty=True`, also on a
pseudo-terminal; IPJRs over HTTP and the camera are real HTTP servers on 127.0.0.1.  `lab sim`
runs this on the rig's own ports until Ctrl-C."""

from __future__ import annotations

import threading
import urllib.parse
from dataclasses import dataclass, field
from typing import Callable

from lab.core.config import Rig, load_rig
from lab.core.errors import UserError
from lab.core.scenario import Scenario
from sim_devices.camera import camera_routes
from sim_devices.faults import FaultInjector
from sim_devices.http_server import HttpDeviceServer
from sim_devices.ipjr import IpjrSerialSim, ipjr_routes
from sim_devices.lift import LiftSim
from sim_devices.line_server import LineDevice, LineServer
from sim_devices.stewart import StewartSim
from sim_devices.turntable import TurntableSim
from sim_devices.watchdog import Firmware
from sim_devices.world import SimWorld


@dataclass
class SimBench:
    rig: Rig                                   # the rig, with the URLs actually served
    world: SimWorld
    urls: dict[str, str] = field(default_factory=dict)
    pty_paths: dict[str, str] = field(default_factory=dict)
    faults: dict[str, FaultInjector] = field(default_factory=dict)
    servers: dict[str, LineServer | HttpDeviceServer] = field(default_factory=dict)
    devices: dict[str, object] = field(default_factory=dict)   # the simulators, by rig name

    def inject(self, device: str, kind: str, after_commands: int = 0, count: int = 1) -> None:
        """Arm a fault on a device (sim_devices/faults.py says what each kind does)."""
        if device not in self.faults:
            raise KeyError(f"no simulated device named {device!r} (have: {', '.join(self.faults)})")
        self.faults[device].arm(kind, after_commands, count)

    def clear_faults(self, device: str | None = None) -> None:
        for name, f in self.faults.items():
            if device is None or name == device:
                f.clear()

    def drop_connections(self, device: str) -> None:
        """Close every TCP connection to a serial device (a cable pulled while idle)."""
        server = self.servers[device]
        if isinstance(server, LineServer):
            server.kick_clients()

    def stop(self) -> None:
        """Stop every server (in parallel: each waits out its own poll interval)."""
        threads = [threading.Thread(target=server.stop, daemon=True) for server in self.servers.values()]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=5.0)
        self.servers.clear()

    def __enter__(self) -> SimBench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def ephemeral_port_range() -> tuple[int, int]:
    """The kernel's ephemeral port range (outgoing connections take ports from it, so a server on
    a fixed port inside it can find the port taken): /proc on Linux, else the IANA range."""
    try:
        lo, hi = (int(x) for x in open("/proc/sys/net/ipv4/ip_local_port_range").read().split())
        return lo, hi
    except (OSError, ValueError):
        return 49152, 65535


def ports_in_ephemeral_range(rig: Rig) -> list[tuple[str, int]]:
    """(device, port) of every fixed port of a rig that lies in the ephemeral range."""
    lo, hi = ephemeral_port_range()
    out = []
    for name, _, url in rig.devices():
        port = urllib.parse.urlsplit(url).port
        if port is not None and lo <= port <= hi:
            out.append((name, port))
    return out


def _endpoint(name: str, url: str, ephemeral: bool, http: bool) -> tuple[str, int, str]:
    """(host, port to bind, path) from a device URL of a simulated rig."""
    parts = urllib.parse.urlsplit(url)
    want = "http" if http else "socket"
    if parts.scheme != want or not parts.hostname:
        example = "http://127.0.0.1:PORT" if http else "socket://127.0.0.1:PORT"
        raise UserError(f"simulated device {name}: url {url!r} must be {example} (a simulator listens on loopback)")
    if parts.port is None and not ephemeral:
        raise UserError(f"simulated device {name}: url {url!r} needs a port")
    return parts.hostname, 0 if ephemeral else int(parts.port or 0), parts.path


@dataclass(frozen=True)
class Spot:
    """Where a simulator is made: the rig's device entry and the world it simulates."""

    name: str
    kind: str
    url: str
    http: bool
    path: str
    world: SimWorld
    rig: Rig


@dataclass(frozen=True)
class Served:
    """A simulator reached over HTTP: how to start its server, the object tests drive (or None),
    and the path its URL ends with (the camera's snapshot)."""

    serve: Callable[[FaultInjector, str, int, Firmware], HttpDeviceServer]
    device: object | None = None
    url_path: str = ""


def _turntable(s: Spot) -> LineDevice:
    t = s.rig.sim.turntable
    assert s.world.turntable is not None
    return TurntableSim(s.world.turntable, t["min_deg"], t["max_deg"], s.name)


def _stewart(s: Spot) -> LineDevice:
    assert s.world.stewart_legs is not None and s.rig.stewart is not None
    g = s.rig.stewart.geometry
    margin = s.rig.sim.stewart["stroke_margin_mm"]
    return StewartSim(s.world.stewart_legs, g, g.leg_min_m * 1000 - margin, g.leg_max_m * 1000 + margin, s.name)


def _lift(s: Spot) -> LineDevice:
    assert s.world.lift is not None
    return LiftSim(s.world.lift, s.rig.sim.lift["min_mm"], s.rig.sim.lift["max_mm"], s.name)


def _ipjr(s: Spot) -> LineDevice | Served:
    act = s.world.ipjrs[s.name]
    if not s.http:
        return IpjrSerialSim(act)
    # HTTP has no standing link to lose: a dropped request leaves the actuator moving, until the
    # watchdog sees the host silent
    return Served(lambda faults, host, port, firmware: HttpDeviceServer(
        s.name, ipjr_routes(act), faults, is_moving=act.moving, motion_paths=frozenset({"/step"}), host=host,
        port=port, stop=act.stop, firmware=firmware).start(), act)


def _camera(s: Spot) -> Served:
    if not s.path or s.path == "/":
        raise UserError(f"simulated camera {s.name}: url {s.url!r} needs a snapshot path, e.g. /frame.jpg")
    return Served(lambda faults, host, port, firmware: HttpDeviceServer(
        s.name, camera_routes(s.world, s.name, s.path), faults, host=host, port=port).start(), None, s.path)


# each kind of device and what simulates it: a line device (the serial protocol, on a socket and a
# pty) or an HTTP server
SIMULATORS: dict[str, Callable[[Spot], LineDevice | Served]] = {
    "turntable": _turntable, "stewart": _stewart, "lift": _lift, "ipjr": _ipjr, "camera": _camera}


def start_sim_bench(rig: Rig | None = None, scenario: Scenario | None = None, *, speedup: float | None = None,
                    ephemeral_ports: bool = True, pty: bool = False, place_all: bool = False,
                    borg_n: int | None = None, firmware: Firmware | None = None) -> SimBench:
    """Start a simulator for every device of a simulated rig (default: the packaged sim rig).

    ephemeral_ports: listen on free ports (tests, procedures) instead of the rig's own (lab sim).
    pty: also serve each serial device on a pseudo-terminal.  place_all: start with every BORG
    module placed (lab sim), instead of an empty turntable (a procedure places them).  borg_n: the
    size of the BORG on the turntable (default: the rig's [sim] borg_n).  firmware: what the
    devices do when their host goes (default: the rig's [sim] watchdog_s and stop_on_link_loss).
    The Stewart base stands at the rig's station for that BORG (`Rig.for_borg`: the near one
    unless the turntable is too wide for it), truly and as the software is told."""
    rig = rig or load_rig(None)
    if rig.sim is not None:
        rig = rig.for_borg(rig.sim.borg_n if borg_n is None else borg_n)
    world = SimWorld(rig, scenario, speedup=speedup, borg_n=borg_n)
    bench = SimBench(rig, world)
    sim = rig.sim
    assert sim is not None
    firmware = firmware or Firmware(sim.watchdog_s, sim.stop_on_link_loss)
    try:
        for name, kind, url in rig.devices():
            http = url.startswith("http")
            host, port, path = _endpoint(name, url, ephemeral_ports, http)
            faults = FaultInjector(name, http=http, seed=world.seed)
            bench.faults[name] = faults
            build = SIMULATORS.get(kind)
            if build is None:
                raise UserError(f"no simulator for device {name} of kind {kind}")
            sim_device = build(Spot(name, kind, url, http, path, world, rig))
            if isinstance(sim_device, LineDevice):
                if http:
                    raise UserError(f"simulated device {name}: a {kind} speaks the serial protocol; use a socket:// URL")
                server: LineServer | HttpDeviceServer = LineServer(sim_device, faults, host, port, pty=pty,
                                                                   firmware=firmware).start()
                bench.devices[name] = sim_device
                if server.pty_path:
                    bench.pty_paths[name] = server.pty_path
            else:
                server = sim_device.serve(faults, host, port, firmware)
                if sim_device.device is not None:
                    bench.devices[name] = sim_device.device
            bench.urls[name] = server.url + (sim_device.url_path if isinstance(sim_device, Served) else "")
            bench.servers[name] = server
        for i, f in enumerate(world.scenario.device_faults):
            if f.device not in bench.faults:
                raise UserError(f"scenario {world.scenario.source}: device.fault[{i}].device: no device "
                                f"{f.device!r} in rig {rig.name!r} (have: {', '.join(bench.faults)})")
            try:
                bench.faults[f.device].arm(f.kind, f.after_commands, f.count)
            except ValueError as exc:
                raise UserError(f"scenario {world.scenario.source}: device.fault[{i}]: {exc}") from None
    except BaseException:
        bench.stop()
        raise
    if place_all and world.borg is not None:
        world.borg.place_all()
    bench.rig = _untold(rig.with_urls(bench.urls))
    return bench


def _untold(rig: Rig) -> Rig:
    """The rig as the software gets it: the bench's true errors stay in the world."""
    from dataclasses import replace

    from lab.core.rig_error import RigError

    if rig.sim is None:
        return rig
    data = dict(rig.data)
    if isinstance(data.get("sim"), dict):
        data["sim"] = {k: v for k, v in data["sim"].items() if k != "rig_error"}
    return replace(rig, sim=replace(rig.sim, rig_error=RigError()), data=data)
