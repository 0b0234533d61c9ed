"""`lab sim`, `lab devices check`, `lab stewart ik`: the hardware layer from the command line
(docs/hardware.md)."""

from __future__ import annotations

import argparse
import json
import math
import signal
import socket
import sys
import threading
import urllib.parse

from lab.core.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="start every simulated device of a rig and print their URLs (Ctrl-C stops)",
                       description="Start the simulated bench: serial devices on loopback TCP (and pseudo-"
                                   "terminals), IPJRs and the camera as HTTP servers on 127.0.0.1.  Talk to them "
                                   "with `lab devices check`, a serial terminal or curl (docs/protocols.md §9).")
    p.add_argument("--rig", help="rig file (default: the packaged simulated rig)")
    p.add_argument("--scenario", help="scenario file: seed, structure and device faults (docs/scenarios.md)")
    p.add_argument("--speedup", type=float, help="run devices this many times faster than real (default: the rig's)")
    p.add_argument("--no-pty", action="store_true", help="do not also serve serial devices on pseudo-terminals")
    p.add_argument("--empty", action="store_true", help="start with no BORG module placed (default: all placed)")
    p.add_argument("--n", type=int, default=None, help="BORG size on the turntable (default: the rig's [sim] borg_n)")
    p.add_argument("--duration", type=float, help=argparse.SUPPRESS)  # tests: stop after this many seconds
    p.set_defaults(func=_sim)

    d = sub.add_parser("devices", help="device checks")
    dsub = d.add_subparsers(dest="devices_cmd", metavar="COMMAND")
    dsub.required = True
    c = dsub.add_parser("check", help="connect to every device of the rig and report its state (moves nothing)",
                        description="Connect to every device of the rig, read its identity, limits and state, and "
                                    "report.  With a simulated rig and nothing answering, the simulators are "
                                    "started in this process for the check (say --no-start-sim to just report).")
    c.add_argument("--rig", help="rig file (default: the packaged simulated rig)")
    c.add_argument("--json", action="store_true", help='print {"devices": [{"name", "kind", "url", "ok", "detail"}]}')
    c.add_argument("--no-start-sim", action="store_true",
                   help="with a simulated rig, do not start the simulators when nothing answers")
    c.set_defaults(func=_check)

    s = sub.add_parser("stewart", help="Stewart-platform kinematics")
    ssub = s.add_subparsers(dest="stewart_cmd", metavar="COMMAND")
    ssub.required = True
    ik = ssub.add_parser("ik", help="leg lengths and workspace check for a platform pose (no device needed)",
                         description="Inverse kinematics of the rig's Stewart platform.  The pose is the platform "
                                     "relative to its home pose: X Y Z in metres, ROLL PITCH YAW in radians about "
                                     "the fixed base axes.")
    for name in ("x", "y", "z", "roll", "pitch", "yaw"):
        ik.add_argument(name, type=float, metavar=name.upper())
    ik.add_argument("--rig", help="rig file (default: the packaged simulated rig)")
    ik.add_argument("--json", action="store_true", help="print the JSON shape of docs/hardware.md")
    ik.set_defaults(func=_ik)


# ------------------------------------------------------------------------------------------------
def _load(rig_path: str | None):
    from lab.core.config import load_rig

    return load_rig(rig_path)


def _sim(args: argparse.Namespace) -> int:
    from lab.core.scenario import load_scenario
    from procedures.setup import check_speedup
    from sim_devices.bench import ephemeral_port_range, ports_in_ephemeral_range, start_sim_bench

    rig = _load(args.rig)
    if not rig.simulated:
        raise UserError(f"rig {rig.source} has no [sim] table: it describes real hardware, there is nothing to simulate")
    check_speedup(args.speedup, rig)          # what its simulated devices can do, too
    risky = ports_in_ephemeral_range(rig)
    if risky:   # an outgoing connection may hold such a port: "Address already in use", now or later
        lo, hi = ephemeral_port_range()
        print(f"lab sim: warning: rig {rig.source}: port{'s' if len(risky) > 1 else ''} "
              f"{', '.join(f'{p} ({n})' for n, p in risky)} lie in the kernel's ephemeral range {lo}-{hi}; "
              f"choose ports below {lo}", file=sys.stderr)
    scenario = load_scenario(args.scenario) if args.scenario else None
    try:
        bench = start_sim_bench(rig, scenario, speedup=args.speedup, ephemeral_ports=False,
                                pty=rig.sim.pty and not args.no_pty, place_all=not args.empty, borg_n=args.n)
    except OSError as exc:
        raise UserError(str(exc.strerror or exc)) from None
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    old = signal.signal(signal.SIGTERM, on_signal)
    try:
        world = bench.world
        sim = rig.sim
        stops = (["when its link closes"] if sim.stop_on_link_loss else []) + (
            [f"after {sim.watchdog_s:g} s without a request (watchdog)"] if sim.watchdog_s else [])
        host_loss = f"; a move stops {' or '.join(stops)}" if stops else "; a move goes on when its host goes"
        print(f"lab sim: rig {rig.name} ({rig.source}); seed {world.seed}; devices {world.speedup:g}x faster than real"
              + host_loss + (f"; scenario {scenario.source}" if scenario else ""))
        width = max(len(n) for n, _, _ in rig.devices())
        for name, kind, _ in rig.devices():
            pty = f"   pty {bench.pty_paths[name]}" if name in bench.pty_paths else ""
            print(f"  {name:<{width}}  {kind:<9}  {bench.urls[name]}{pty}")
        if world.borg is not None:
            print(f"  BORG {world.borg.model.n}x{world.borg.model.n}x{world.borg.model.n}: "
                  f"{len(world.borg.placed)} of {len(world.borg.model.modules)} modules placed")
        rig_arg = f" --rig {args.rig}" if args.rig else ""
        print("Try:")
        print(f"  lab devices check{rig_arg}")
        serial_dev = next((n for n, k, u in rig.devices() if u.startswith("socket://")), None)
        if serial_dev:
            print(f"  python -m serial.tools.miniterm --eol LF {bench.urls[serial_dev]} 115200")
            if serial_dev in bench.pty_paths:
                print(f"  picocom -b 115200 --omap crlf --imap lfcrlf --echo {bench.pty_paths[serial_dev]}")
        http_dev = next((n for n, k, u in rig.devices() if k == "ipjr" and u.startswith("http://")), None)
        if http_dev:
            print(f"  curl -s {bench.urls[http_dev]}/volts")
        cam = next((n for n, k, _ in rig.devices() if k == "camera"), None)
        if cam:
            print(f"  curl -s -o {bench.urls[cam].rsplit('/', 1)[-1] or 'frame'} {bench.urls[cam]}")
        print("Ctrl-C stops.", flush=True)
        try:
            stop.wait(args.duration)
        except KeyboardInterrupt:
            pass
    finally:
        signal.signal(signal.SIGTERM, old)
        bench.stop()
    print("lab sim: stopped", flush=True)
    return 0


def _answers(url: str, timeout_s: float = 0.3) -> bool:
    """Does anything accept a TCP connection at this device URL?  (Serial paths: does it exist.)"""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme in ("socket", "http", "https") and parts.hostname:
        port = parts.port or (80 if parts.scheme == "http" else 443)
        try:
            with socket.create_connection((parts.hostname, port), timeout=timeout_s):
                return True
        except OSError:
            return False
    return True


def _check(args: argparse.Namespace) -> int:
    import drivers

    rig = _load(args.rig)
    simulator = "none"
    bench = None
    if rig.simulated:
        simulator = "external"
        if not any(_answers(url) for _, _, url in rig.devices()):
            if args.no_start_sim:
                simulator = "not running"
            else:
                from sim_devices.bench import start_sim_bench

                try:
                    bench = start_sim_bench(rig, ephemeral_ports=False, place_all=True)
                except OSError as exc:
                    raise UserError(f"nothing answers at the rig's URLs and the simulators cannot start: {exc.strerror}")
                simulator = "in-process"
                if not args.json:
                    print(f"lab devices check: nothing answered at rig {rig.name}'s URLs, so the simulators were "
                          f"started in this process for the check (run `lab sim` to keep them up)", file=sys.stderr)
    try:
        reports = drivers.check(rig)
    finally:
        if bench is not None:
            bench.stop()
    if args.json:
        print(json.dumps({"devices": [r.to_json() for r in reports], "rig": rig.name, "simulator": simulator}, indent=2))
    else:
        print(f"rig {rig.name} ({rig.source})" + (f"; simulator: {simulator}" if rig.simulated else ""))
        width = max(len(r.name) for r in reports)
        for r in reports:
            print(f"  {'ok  ' if r.ok else 'FAIL'}  {r.name:<{width}}  {r.kind:<9}  {r.url}\n        {r.detail}")
        bad = [r.name for r in reports if not r.ok]
        print(f"{len(reports) - len(bad)} of {len(reports)} devices ok" + (f"; failing: {', '.join(bad)}" if bad else ""))
    return 0 if all(r.ok for r in reports) else 1


def _ik(args: argparse.Namespace) -> int:
    from drivers.stewart_kinematics import StewartKinematics

    rig = _load(args.rig)
    if rig.stewart is None:
        raise UserError(f"rig {rig.source} has no [stewart] table")
    pose = [args.x, args.y, args.z, args.roll, args.pitch, args.yaw]
    if not all(math.isfinite(v) for v in pose):
        raise UserError(f"pose values must be finite numbers, got {pose}")
    out = StewartKinematics(rig.stewart.geometry).ik_json(pose)
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print("pose (m, rad): " + " ".join(f"{v:.6g}" for v in pose))
        print("legs (m):      " + " ".join("-" if v is None else f"{v:.6f}" for v in out["legs_m"]))
        print("reachable" if out["reachable"] else f"UNREACHABLE: {out['reason']}")
    return 0  # computed; reachability is in the output
