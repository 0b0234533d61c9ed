"""`lab bench faults [--quick] [--json]`: the fault campaign of issue 11, in the repository.

Each case does one thing to the lab and says what must follow; the bench prints how many cases
were tried, how many ended as expected, and names every one that did not.  Sections:

- devices:   every device x every fault kind it can suffer x when it strikes (after 0..8 commands)
             x how long (once, for good), on a fresh simulated bench: the operation must recover
             or end in an error that names the device and the fault, with the device not moving;
- kill:      SIGKILL a truss (and, in the full run, a BORG) run at several moments, `lab resume`:
             the resumed summary must equal the uninterrupted one and the log hold every step once;
- signals:   SIGINT twice (0 to 50 ms apart) or SIGINT then SIGTERM: exit 3, stop record and
             summary.json agree, no half-written file; then resume completes;
- inputs:    a corpus of malformed scenarios, rigs, run directories and arguments: exit 2 and one
             line on stderr, no traceback;
- protocol:  abuse of the simulated servers over raw sockets and HTTP: refused, the device does
             not move, the server still answers;
- sharing:   a second run against a bench another process owns, and two runs on one --out: the
             second is refused naming the device or directory and its holder; the first is unharmed;
- links:     one owner per device whatever its spelling, environment or user; devices that stop when
             their host goes (or finish, on an older firmware), and `lab resume` after either
             (lab/studies/bench_faults_links.py).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from lab.studies.bench_faults_links import link_cases

LAB = [sys.executable, "-m", "lab"]
ROOT = Path(__file__).resolve().parents[2]
SIM_RIG = ROOT / "lab" / "rigs" / "sim.toml"
TRUSS = ["run", "truss", "tetrahelix:6", "--auto", "--quiet"]
BORG = ["run", "borg", "--auto", "--quiet", "--modules", "4", "--on-flag", "continue",
        "--scenario", str(ROOT / "docs" / "scenarios" / "structure_faults.toml")]


@dataclass
class Case:
    name: str
    expected: str
    check: Callable[[], str]          # "" when the case ends as expected, else what happened


@dataclass
class Report:
    cases: int = 0
    ok: int = 0
    bad: list[dict[str, str]] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)

    def add(self, case: Case) -> None:
        self.cases += 1
        try:
            got = case.check()
        except Exception as exc:  # the case itself blew up: that is a finding, not a crash of the bench
            got = f"{type(exc).__name__}: {exc}"
        if got:
            self.bad.append({"case": case.name, "expected": case.expected, "got": got[:400]})
        else:
            self.ok += 1


# ---- devices x fault kinds x timings --------------------------------------------------------

SERIAL_KINDS = ("timeout", "garbled", "disconnect", "stuck")
HTTP_KINDS = SERIAL_KINDS + ("http_500",)
# what an error caused by each fault must say (any one of the words), so the operator knows
WORDS = {
    "timeout": ("no reply", "not finished within", "timeout", "no frame"),
    "garbled": ("not ASCII", "not JSON", "neither OK nor ERR", "control characters", "tag", "not an image",
                "not a number", "is not", "garbled", "lacks"),
    "disconnect": ("lost", "link", "connect", "refused"),
    "stuck": ("not finished within", "did not move", "stuck", "diverging"),
    "http_500": ("500", "internal"),
}


def _fast_rig():
    import dataclasses

    from lab.core.config import load_rig

    rig = load_rig(SIM_RIG).with_links(reply_timeout_s=0.1, margin_s=0.3, retries=2)
    cam = dataclasses.replace(rig.camera, timeout_s=0.5) if rig.camera else None
    return dataclasses.replace(rig, camera=cam)


def _device_case(device: str, kind: str, after: int, count: int) -> Case:
    when = "for good" if count == 0 else f"x{count}"
    return Case(f"devices/{device}/{kind}/after {after} {when}",
                "recovery, or an error naming the device and the fault; device not moving",
                lambda: _run_device_case(device, kind, after, count))


def _operation(device: str, devs: Any, bench: Any) -> Callable[[], None]:
    if device == "turntable":
        return lambda: (devs.turntable.home(), devs.turntable.move_to(math.radians(40.0)))
    if device == "stewart":
        return lambda: devs.stewart.move_to([0.01, -0.01, 0.005, 0.02, 0.0, 0.03])
    if device == "lift":
        return lambda: (devs.lift.move_to(0.8), devs.lift.home())
    if device == "camera":
        return lambda: devs.camera.grab()

    def ipjr() -> None:
        bench.world.ipjrs[device].attach(0.800)
        ip = devs.ipjrs[device]
        ip.attach(0.800)
        ip.set_length(0.8123)
    return ipjr


def _moving(bench: Any, device: str) -> bool:
    w = bench.world
    if device == "turntable":
        return bool(w.turntable.moving())
    if device == "stewart":
        return bool(w.stewart_legs.moving())
    if device == "lift":
        return bool(w.lift.moving())
    if device in w.ipjrs:
        return bool(w.ipjrs[device].moving())
    return False


def _run_device_case(device: str, kind: str, after: int, count: int) -> str:
    import drivers
    from drivers.errors import DeviceError
    from sim_devices.bench import start_sim_bench

    with start_sim_bench(_fast_rig(), speedup=200) as bench:
        bench.inject(device, kind, after_commands=after, count=count)
        with drivers.connect(bench.rig, only=[device]) as devs:
            error: BaseException | None = None
            try:
                _operation(device, devs, bench)()
            except DeviceError as exc:
                error = exc
            except Exception as exc:
                return f"unnamed error {type(exc).__name__}: {exc}"
            deadline = time.monotonic() + 3.0
            while _moving(bench, device) and time.monotonic() < deadline:
                time.sleep(0.02)
            still = _moving(bench, device)
            fired = [k for k, _ in bench.faults[device].log]
        if error is None:
            return f"device still moving after a recovered operation (faults fired: {fired})" if still else ""
        msg = str(error)
        if getattr(error, "device", None) != device:
            return f"error names {getattr(error, 'device', None)!r}, not {device}: {msg}"
        if not fired:
            return f"failed although no fault fired: {msg}"
        if not any(w.lower() in msg.lower() for k in set(fired) for w in WORDS[k]):
            return f"error does not name the fault ({', '.join(sorted(set(fired)))}): {msg}"
        if still and "may still be moving" not in msg:
            return f"device left moving and the error does not say so: {msg}"
        return ""


def device_cases(quick: bool) -> list[Case]:
    from lab.core.config import load_rig

    rig = load_rig(SIM_RIG)
    timings = [(0, 1), (2, 1), (5, 0)] if quick else [(a, c) for a in (0, 1, 2, 3, 5, 8) for c in (1, 0)]
    devices = ["turntable", "ipjr1", "ipjr3"] if quick else [n for n, _, _ in rig.devices()]
    cases = []
    for name, _, url in rig.devices():
        if name not in devices:
            continue
        kinds = HTTP_KINDS if url.startswith("http") else SERIAL_KINDS
        if quick:
            kinds = kinds[:2] if name != "ipjr1" else ("garbled", "http_500")
        for kind in kinds:
            for after, count in timings:
                cases.append(_device_case(name, kind, after, count))
    return cases


# ---- kill and resume, double signals --------------------------------------------------------


def _lab(args: list[str], timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(LAB + args, capture_output=True, text=True, timeout=timeout)


def _steps_done(out: Path) -> int:
    try:
        return int(json.loads((out / "checkpoint.json").read_text())["steps_completed"])
    except (OSError, ValueError, KeyError):
        return 0


def _wait(out: Path, n: int, proc: subprocess.Popen, timeout: float = 300) -> bool:
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        if _steps_done(out) >= n:
            return True
        time.sleep(0.01)
    return False


def _step_ends(path: Path) -> list[int]:
    from lab.core.recorder import topics
    from lab.core.recorder.reader import iter_messages

    return [r.message.index for r in iter_messages(path) if r.topic == topics.RUN_STEP and r.message.phase == "end"]


def _sent_motion(path: Path) -> bool:
    """Did the run command any motion (so its clean-up must have stopped something)?"""
    from lab.core.recorder import topics
    from lab.core.recorder.reader import iter_messages

    return any(r.message.direction == "tx" and (b" STEP " in r.message.data or b"/step?" in r.message.data)
               for r in iter_messages(path, topics.COMMS))


def _same(a: Any, b: Any, rel: float = 1e-9) -> bool:
    """Equal, floats to `rel`: the Cramér-Rao bound of a resumed run is recomputed from the
    replayed views in another order of summation (it differs in the 15th digit)."""
    if isinstance(a, float) and isinstance(b, float):
        return a == b or abs(a - b) <= rel * max(abs(a), abs(b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k], rel) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y, rel) for x, y in zip(a, b))
    return a == b


def _same_summary(kind: str, a: dict, b: dict) -> str:
    keys = ("nodes", "rms_node_error_m", "steps") if kind == "truss" else ("modules", "rejected_tags")
    for k in keys:
        if not _same(a.get(k), b.get(k)):
            return f"summary.{k} differs from the uninterrupted run's"
    return ""


class Reference:
    """Uninterrupted runs, made once and shared by the cases that compare against them."""

    def __init__(self, work: Path) -> None:
        self.work = work
        self._done: dict[str, dict] = {}
        self._ends: dict[str, list[int]] = {}

    def get(self, kind: str) -> dict:
        if kind not in self._done:
            out = self.work / f"ref-{kind}"
            args = (TRUSS + ["--speedup", "20"]) if kind == "truss" else (BORG + ["--speedup", "20"])
            r = _lab(args + ["--out", str(out)])
            if r.returncode != 0:
                raise RuntimeError(f"reference {kind} run failed: {r.stderr.strip()[-300:]}")
            self._done[kind] = json.loads((out / "summary.json").read_text())
            self._ends[kind] = _step_ends(out / "run.mcap")
        return self._done[kind]

    def step_ends(self, kind: str) -> list[int]:
        """The uninterrupted run's step ends (a BORG run's rig survey is a step of its own)."""
        self.get(kind)
        return self._ends[kind]


def _kill_case(ref: Reference, work: Path, kind: str, after_steps: int, delay_s: float) -> Case:
    name = f"kill/{kind}/SIGKILL after step {after_steps}" + (f" +{delay_s:g}s" if delay_s else "")

    def check() -> str:
        out = work / name.replace("/", "_").replace(" ", "_").replace("+", "")
        args = (TRUSS + ["--speedup", "2"]) if kind == "truss" else (BORG + ["--speedup", "5"])
        p = subprocess.Popen(LAB + args + ["--out", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if not _wait(out, after_steps, p):
            p.kill()
            return f"the run never completed {after_steps} steps (exit {p.wait()})"
        time.sleep(delay_s)
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=30)
        r = _lab(["resume", str(out), "--auto"])
        if r.returncode != 0:
            return f"resume exited {r.returncode}: {(r.stderr or r.stdout).strip()[-300:]}"
        summary = json.loads((out / "summary.json").read_text())
        if summary.get("result") != "completed":
            return f"resumed run ended {summary.get('result')}: {summary.get('reason')}"
        ends, want = _step_ends(out / "run.mcap"), ref.step_ends(kind)
        if ends != want or want != list(range(len(want))):
            return f"resumed log holds step ends {ends}, not 0..{len(want) - 1} once each as the uninterrupted run"
        return _same_summary(kind, ref.get(kind), summary)

    return Case(name, "resume completes; summary equal to the uninterrupted run; every step once in the log", check)


def _signal_case(ref: Reference, work: Path, after_steps: int, second: int, gap_s: float) -> Case:
    label = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}[second]
    name = f"signals/truss/SIGINT then {label} {gap_s * 1000:g} ms later, after step {after_steps}"

    def check() -> str:
        from lab.core.recorder.reader import read_summary

        out = work / name.replace("/", "_").replace(" ", "_")
        p = subprocess.Popen(LAB + TRUSS + ["--speedup", "2", "--out", str(out)], stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
        if not _wait(out, after_steps, p):
            p.kill()
            return "the run never got there"
        p.send_signal(signal.SIGINT)
        time.sleep(gap_s)
        p.send_signal(second)
        time.sleep(gap_s)
        p.send_signal(signal.SIGINT)
        text, _ = p.communicate(timeout=60)
        if p.returncode != 3:
            return f"exit {p.returncode}, not 3: {text.strip()[-200:]}"
        summary = json.loads((out / "summary.json").read_text())
        stop = read_summary(out / "run.mcap").stop
        if stop is None or summary.get("result") != stop.result or summary.get("result") != "aborted":
            return f"summary.json says {summary.get('result')}, the stop record {stop.result if stop else None}"
        if summary.get("reason") != stop.reason:
            return f"reasons differ: {summary.get('reason')!r} / {stop.reason!r}"
        if _sent_motion(out / "run.mcap") and "stopped" not in summary.get("reason", ""):
            return f"devices were commanded to move but the reason names none stopped: {summary.get('reason')!r}"
        if list(out.glob("*.tmp")):
            return f"half-written files left: {[p.name for p in out.glob('*.tmp')]}"
        r = _lab(["resume", str(out), "--auto"])
        if r.returncode != 0:
            return f"resume exited {r.returncode}: {r.stderr.strip()[-200:]}"
        return _same_summary("truss", ref.get("truss"), json.loads((out / "summary.json").read_text()))

    return Case(name, "exit 3, stop record and summary.json agree (aborted, devices stopped), no .tmp; resume "
                      "gives the uninterrupted summary", check)


def kill_cases(ref: Reference, work: Path, quick: bool) -> list[Case]:
    if quick:
        return [_kill_case(ref, work, "truss", 2, 0.0)]
    cases = [_kill_case(ref, work, "truss", k, d) for k in (1, 2, 3, 4, 5) for d in (0.0, 0.3)]
    cases += [_kill_case(ref, work, "borg", k, 0.0) for k in (1, 2, 3)]
    return cases


def signal_cases(ref: Reference, work: Path, quick: bool) -> list[Case]:
    if quick:
        return [_signal_case(ref, work, 2, signal.SIGINT, 0.004)]
    return [_signal_case(ref, work, k, sig, gap) for k, sig, gap in
            ((1, signal.SIGINT, 0.0), (2, signal.SIGINT, 0.004), (3, signal.SIGINT, 0.05),
             (2, signal.SIGTERM, 0.004), (4, signal.SIGTERM, 0.0), (3, signal.SIGINT, 0.2))]


# ---- bad inputs -----------------------------------------------------------------------------


def _cli_one_line(lab_main: Callable[[list[str]], Any], argv: list[str]) -> str:
    """Run `lab ARGV` in this process (`lab_main`: the CLI's entry point, passed down by the command
    running the campaign): "" if it exits 2 with one line on stderr and no traceback."""
    err, out = io.StringIO(), io.StringIO()
    code: Any
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            code = lab_main(argv)
        except SystemExit as exc:
            code = exc.code
        except Exception as exc:
            return f"uncaught {type(exc).__name__}: {exc}"
    lines = [ln for ln in err.getvalue().splitlines() if ln.strip()]
    if code != 2:
        return f"exit {code}: {(err.getvalue() or out.getvalue()).strip()[-200:]}"
    if "Traceback" in err.getvalue():
        return "traceback on stderr"
    if len(lines) != 1 and not lines[-1].startswith("lab: error:") and "usage:" not in err.getvalue():
        return f"{len(lines)} lines on stderr: {lines[:3]}"
    return ""


SCENARIOS = {
    "nan sigma": "[truss]\nsigma_length_m = nan\n",
    "inf sigma": "[truss]\nsigma_measure_m = inf\n",
    "huge sigma": "[truss]\nsigma_length_m = 1e9\n",
    "negative sigma": "[truss]\nsigma_length_m = -1e-3\n",
    "negative pixel noise": "[camera]\npixel_noise = -5\n",
    "nan blur": "[camera]\nblur_px = nan\n",
    "borg not a table": "borg = 5\n",
    "fault list of numbers": "[borg]\nfault = [1, 2]\n",
    "device not a table": 'device = "x"\n',
    "offset with nan": '[[borg.fault]]\nkind = "module_offset"\nmodule = "2D"\noffset_m = [0, nan, 0]\n',
    "huge deploy height": '[[borg.fault]]\nkind = "partial_deploy"\nmodule = "13D"\nheight_m = 1e6\n',
    "negative seed": "seed = -1\n",
    "bool seed": "seed = true\n",
    "unknown key": "sed = 3\n",
    "bad toml": "seed = = 3\n",
    "fault count huge": '[[device.fault]]\ndevice = "turntable"\nkind = "timeout"\ncount = 10000000000\n',
    "unknown fault kind": '[[device.fault]]\ndevice = "turntable"\nkind = "melt"\n',
    "fault on no device": '[[device.fault]]\ndevice = "toaster"\nkind = "timeout"\n',
}
RIG_EDITS = {
    "slow turntable": ("speed_deg_s = 10.0", "speed_deg_s = 0.001"),
    "infinite speedup": ("speedup = 10.0", "speedup = inf"),
    "nan leg limit": ("leg_max_m =", "leg_max_m = nan #"),
    "unknown key": ("[turntable]", "[turntable]\nspeed = 3"),
    "string number": ("speed_deg_s = 10.0", 'speed_deg_s = "fast"'),
    "bad toml": ("[turntable]", "[turntable"),
    "zero retries bound": ("[turntable]", "[turntable]\nretries = 1000"),
}


def input_cases(lab_main: Callable[[list[str]], Any], work: Path, quick: bool) -> list[Case]:
    d = work / "inputs"
    d.mkdir(parents=True, exist_ok=True)
    cases: list[Case] = []

    def case(name: str, argv: list[str]) -> None:
        cases.append(Case(f"inputs/{name}", "exit 2, one line on stderr, no traceback",
                          lambda: _cli_one_line(lab_main, argv)))

    out = str(d / "never")
    for name, text in SCENARIOS.items():
        p = d / f"sc-{name.replace(' ', '_')}.toml"
        p.write_text(text)
        case(f"scenario {name}", ["run", "truss", "tetrahelix:6", "--auto", "--scenario", str(p), "--out", out])
    blob = d / "blob.toml"
    blob.write_bytes(bytes(range(256)) * 4)
    case("scenario binary file", ["run", "truss", "tetrahelix:6", "--scenario", str(blob), "--out", out])
    case("scenario missing", ["run", "truss", "tetrahelix:6", "--scenario", str(d / "nope.toml"), "--out", out])
    case("rig binary file", ["run", "truss", "tetrahelix:6", "--rig", str(blob), "--out", out])
    case("rig is a directory", ["run", "truss", "tetrahelix:6", "--rig", str(d), "--out", out])
    text = SIM_RIG.read_text()
    shutil.copy(SIM_RIG.parent / "sim_camera.json", d / "sim_camera.json")
    for name, (old, new) in RIG_EDITS.items():
        p = d / f"rig-{name.replace(' ', '_')}.toml"
        p.write_text(text.replace(old, new, 1))
        case(f"rig {name}", ["run", "truss", "tetrahelix:6", "--rig", str(p), "--out", out])
    for v in ("inf", "nan", "0", "-1", "1e9"):
        case(f"--speedup {v}", ["run", "truss", "tetrahelix:6", "--speedup", v, "--out", out])
    case("borg --n 100", ["structure", "borg", "--n", "100"])
    case("borg --spacing nan", ["structure", "borg", "--spacing", "nan"])
    case("tetrahelix:100000", ["structure", "truss", "tetrahelix:100000"])
    case("run tetrahelix:100000", ["run", "truss", "tetrahelix:100000", "--auto", "--out", out])
    case("telescope:100000", ["plan", "truss", "telescope:100000"])
    case("stewart ik nan", ["stewart", "ik", "0", "0", "0", "nan", "0", "0"])
    f = d / "a-file"
    f.write_text("x")
    case("--out is a file", ["run", "truss", "tetrahelix:6", "--auto", "--out", str(f)])
    case("--out under a file", ["run", "truss", "tetrahelix:6", "--auto", "--out", str(f / "sub")])
    taken = d / "taken"
    taken.mkdir(exist_ok=True)
    (taken / "run.json").write_text(json.dumps({"procedure": "truss", "params": {"name": "tetrahelix:6"}}))
    case("--out holds a run", ["run", "truss", "tetrahelix:6", "--auto", "--out", str(taken)])
    other = d / "other"
    other.mkdir(exist_ok=True)
    (other / "notes.txt").write_text("mine")
    case("--out holds other files", ["run", "truss", "tetrahelix:6", "--auto", "--out", str(other)])
    for name, files in {
        "garbage run.json": {"run.json": "{not json"},
        "run.json a list": {"run.json": "[1]"},
        "unknown procedure": {"run.json": '{"procedure": "bake", "params": {}}'},
        "garbage checkpoint": {"checkpoint.json": "\x00garbage"},
        "checkpoint steps 99": {"checkpoint.json": '{"steps_completed": 99, "state": {}}'},
        "checkpoint steps -1": {"checkpoint.json": '{"steps_completed": -1, "state": {}}'},
        "checkpoint beyond the logs": {"checkpoint.json": '{"steps_completed": 3, "state": {}}'},
        "checkpoint state not a table": {"checkpoint.json": '{"steps_completed": 0, "state": 5}'},
        "completed run": {"summary.json": '{"result": "completed"}'},
    }.items():
        rd = d / f"rd-{name.replace(' ', '_')}"
        rd.mkdir(exist_ok=True)
        (rd / "run.json").write_text(json.dumps({"procedure": "truss", "params": {"name": "tetrahelix:6"}}))
        for fn, content in files.items():
            (rd / fn).write_text(content)
        case(f"resume {name}", ["resume", str(rd), "--auto"])
    case("resume no such dir", ["resume", str(d / "nowhere"), "--auto"])
    case("resume a file", ["resume", str(f), "--auto"])
    case("recover not mcap", ["recover", str(f)])
    case("recover missing", ["recover", str(d / "none.mcap")])
    if quick:
        keep = {"inputs/scenario nan sigma", "inputs/scenario borg not a table", "inputs/rig slow turntable",
                "inputs/--speedup inf", "inputs/--out holds a run", "inputs/resume garbage checkpoint",
                "inputs/resume checkpoint steps 99", "inputs/tetrahelix:100000"}
        cases = [c for c in cases if c.name in keep]
    return cases


# ---- protocol abuse -------------------------------------------------------------------------


def _line_exchange(url: str, payload: bytes, wait_s: float = 0.3) -> bytes:
    host, port = url.split("//")[1].split(":")
    with socket.create_connection((host, int(port)), timeout=2) as s:
        s.sendall(payload)
        s.settimeout(wait_s)
        data = b""
        try:
            while True:
                chunk = s.recv(4096)
                if not chunk:
                    break
                data += chunk
        except socket.timeout:
            pass
    return data


def _http(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=3) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()
    except (urllib.error.URLError, OSError) as e:
        return -1, str(e).encode()


def _abuse_case(name: str, device: str, act: Callable[[Any], str]) -> Case:
    def check() -> str:
        from sim_devices.bench import start_sim_bench

        with start_sim_bench(_fast_rig(), speedup=200) as bench:
            before = _position(bench, device)
            problem = act(bench)
            if problem:
                return problem
            time.sleep(0.05)
            if _moving(bench, device) or _position(bench, device) != before:
                return "the device moved"
            if not _healthy(bench, device):
                return "the server no longer answers a plain query"
        return ""

    return Case(f"protocol/{name}", "refused or ignored; the device does not move; the server still answers", check)


def _position(bench: Any, device: str) -> Any:
    w = bench.world
    if device == "turntable":
        return float(w.turntable.position())
    if device == "stewart":
        return tuple(float(x) for x in w.stewart_legs.position())
    if device == "lift":
        return float(w.lift.position())
    return float(w.ipjrs[device].extension_m())


def _healthy(bench: Any, device: str) -> bool:
    url = bench.urls[device]
    if url.startswith("http"):
        return _http(url + "/id")[0] == 200
    return b"OK" in _line_exchange(url, b"#5 ID?\n")


def _expect_line(payload: bytes, want: bytes | None) -> Callable[[Any], str]:
    def act(bench: Any) -> str:
        reply = _line_exchange(bench.urls["turntable"], payload)
        if want is not None and want not in reply:
            return f"reply {reply[:120]!r} lacks {want!r}"
        return ""
    return act


def _expect_http(target: str, statuses: tuple[int, ...], device: str = "ipjr1") -> Callable[[Any], str]:
    def act(bench: Any) -> str:
        status, body = _http(bench.urls[device] + target)
        return "" if status in statuses else f"HTTP {status}: {body[:120]!r}"
    return act


def _many_clients(bench: Any) -> str:
    from sim_devices.line_server import MAX_CLIENTS

    host, port = bench.urls["turntable"].split("//")[1].split(":")
    socks = [socket.create_connection((host, int(port))) for _ in range(MAX_CLIENTS + 6)]
    time.sleep(0.2)
    for s in socks:
        s.close()
    time.sleep(0.2)
    return ""


def _half_open_http(bench: Any) -> str:
    from sim_devices.http_server import MAX_CONNECTIONS

    host, port = bench.urls["ipjr1"].split("//")[1].split(":")
    socks = []
    for _ in range(MAX_CONNECTIONS + 8):
        s = socket.create_connection((host, int(port)))
        s.sendall(b"GET /volts HTTP/1.0\r\n")
        socks.append(s)
    time.sleep(0.5)
    status, _ = _http(bench.urls["ipjr1"] + "/volts")
    for s in socks:
        s.close()
    if status != 503:
        return f"with every slot held by a half-sent request, a new one got HTTP {status}, not 503"
    time.sleep(0.3)
    return ""


def _stale_reply(bench: Any) -> str:
    """A client that sends two tagged requests must get each reply under its own tag."""
    reply = _line_exchange(bench.urls["turntable"], b"#7 POS?\n#8 ID?\n")
    lines = reply.split(b"\n")
    if not (lines[0].startswith(b"#7 OK") and lines[1].startswith(b"#8 OK TURNTABLE")):
        return f"replies not matched to their tags: {reply[:120]!r}"
    return ""


def protocol_cases(quick: bool) -> list[Case]:
    line = [
        ("serial over-long line", b"MOVE " + b"9" * 300 + b"\n", b"ERR 12"),
        ("serial binary garbage", bytes(range(1, 10)) + b"\xff\xfe\n", b"ERR"),
        ("serial empty lines", b"\n\n\r\n", None),
        ("serial unknown verb", b"FLY 3\n", b"ERR 10"),
        ("serial MOVE nan", b"MOVE nan\n", b"ERR 11"),
        ("serial MOVE inf", b"MOVE inf\n", b"ERR 11"),
        ("serial MOVE 1e9", b"MOVE 1e9\n", b"ERR"),
        ("serial MOVE out of range", b"MOVE 99999\n", b"ERR"),
        ("serial MOVE two args", b"MOVE 1 2\n", b"ERR 11"),
        ("serial tag too long", b"#123456 MOVE 10\n", b"ERR"),
        ("serial half a line then gone", b"MOVE 10", None),
        ("serial NUL bytes", b"\x00\x00MOVE 10\x00\n", b"ERR"),
    ]
    cases = [_abuse_case(n, "turntable", _expect_line(p, w)) for n, p, w in line]
    stewart = [("serial LEGS nan", b"LEGS nan 1 1 1 1 1\n"), ("serial LEGS five", b"LEGS 400 400 400 400 400\n"),
               ("serial LEGS beyond stroke", b"LEGS 9999 9999 9999 9999 9999 9999\n")]
    cases += [_abuse_case(n, "stewart", lambda b, p=p: (
        "" if b"ERR" in _line_exchange(b.urls["stewart"], p) else "accepted")) for n, p in stewart]
    http = [
        ("http duplicate steps", "/step?steps=5&steps=-1000", (400,)),
        ("http malformed query", "/step?steps", (400,)),
        ("http empty pairs", "/step?steps=5&&", (400,)),
        ("http steps nan", "/step?steps=nan", (400,)),
        ("http steps huge", "/step?steps=99999999999", (400,)),
        ("http steps text", "/step?steps=abc", (400,)),
        ("http extra parameter", "/step?steps=5&speed=9", (400,)),
        ("http unknown path", "/launch", (404,)),
        ("http params on a query", "/volts?x=1", (400,)),
        ("http long target", "/step?steps=" + "1" * 3000, (400, 414)),
    ]
    cases += [_abuse_case(n, "ipjr1", _expect_http(t, s)) for n, t, s in http]
    cases.append(_abuse_case("serial many clients", "turntable", _many_clients))
    cases.append(_abuse_case("http half-open requests", "ipjr1", _half_open_http))
    cases.append(_abuse_case("serial tags kept apart", "turntable", _stale_reply))
    if quick:
        keep = {"protocol/http duplicate steps", "protocol/serial MOVE nan", "protocol/serial tags kept apart",
                "protocol/http malformed query"}
        cases = [c for c in cases if c.name in keep]
    return cases


# ---- two runs, one bench --------------------------------------------------------------------


def _free_port_below_ephemeral() -> int:
    from sim_devices.bench import ephemeral_port_range

    lo, _ = ephemeral_port_range()
    for port in range(max(1025, lo - 9000), lo - 100, 7):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
                return port
            except OSError:
                continue
    raise RuntimeError("no free port")


def _shared_rig(work: Path) -> tuple[Path, Path]:
    """A simulated rig on free fixed ports (for `lab sim`) and the same devices as hardware."""
    text = SIM_RIG.read_text()
    import re

    base = _free_port_below_ephemeral()
    ports = iter(range(base, base + 200))

    def fresh(m: re.Match) -> str:
        port = next(ports)
        while True:
            with socket.socket() as s:
                try:
                    s.bind(("127.0.0.1", port))
                    break
                except OSError:
                    port = next(ports)
        return f"127.0.0.1:{port}"

    text = re.sub(r"127\.0\.0\.1:\d+", fresh, text)
    sim = work / "shared-sim.toml"
    sim.write_text(text)
    hw = work / "shared-hw.toml"
    hw.write_text(text.split("\n[sim]")[0])
    shutil.copy(SIM_RIG.parent / "sim_camera.json", work / "sim_camera.json")
    return sim, hw


def sharing_cases(work: Path, quick: bool) -> list[Case]:
    def busy_bench() -> str:
        sim_rig, hw_rig = _shared_rig(work)
        sim = subprocess.Popen(LAB + ["sim", "--rig", str(sim_rig), "--no-pty"], stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
        try:
            time.sleep(2.0)
            if sim.poll() is not None:
                return f"lab sim did not start: {sim.stdout.read()[-200:]}"
            first_out, second_out = work / "first", work / "second"
            for d in (first_out, second_out):
                shutil.rmtree(d, ignore_errors=True)
            first = subprocess.Popen(LAB + ["run", "borg", "--rig", str(hw_rig), "--auto", "--quiet", "--modules", "2",
                                            "--on-flag", "continue", "--out", str(first_out)],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            if not _wait(first_out, 0, first, 60) or not (first_out / "run.json").exists():
                deadline = time.time() + 60
                while not (first_out / "run.json").exists() and time.time() < deadline and first.poll() is None:
                    time.sleep(0.05)
            second = _lab(["run", "borg", "--rig", str(hw_rig), "--auto", "--quiet", "--modules", "2", "--out",
                           str(second_out)], timeout=120)
            text, _ = first.communicate(timeout=600)
            if second.returncode != 2 or "in use by pid" not in second.stderr or str(first_out) not in second.stderr:
                return f"second run: exit {second.returncode}: {second.stderr.strip()[-200:]}"
            if first.returncode != 0:
                return f"first run harmed: exit {first.returncode}: {text.strip()[-200:]}"
            return ""
        finally:
            sim.send_signal(signal.SIGINT)
            try:
                sim.wait(timeout=20)
            except subprocess.TimeoutExpired:
                sim.kill()

    def held_devices() -> str:
        _, hw_rig = _shared_rig(work)
        holder = subprocess.Popen([sys.executable, "-c", (
            "import time, drivers; from lab.core.config import load_rig; from lab.core.locks import set_holder\n"
            f"set_holder(run='holder-run'); d = drivers.connect(load_rig({str(hw_rig)!r}))\n"
            "print('held', flush=True); time.sleep(120)\n")], stdout=subprocess.PIPE, text=True)
        try:
            if holder.stdout.readline().strip() != "held":
                return "holder did not start"
            r = _lab(["run", "borg", "--rig", str(hw_rig), "--auto", "--quiet", "--out", str(work / "refused")],
                     timeout=120)
            if r.returncode != 2 or "holder-run" not in r.stderr or "nothing was moved or stopped" not in r.stderr:
                return f"exit {r.returncode}: {r.stderr.strip()[-200:]}"
            return ""
        finally:
            holder.kill()
            holder.wait()

    def one_out() -> str:
        out = work / "one-out"
        shutil.rmtree(out, ignore_errors=True)
        p = subprocess.Popen(LAB + TRUSS + ["--speedup", "2", "--out", str(out)], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
        try:
            if not _wait(out, 1, p):
                return "first run never started"
            r = _lab(TRUSS + ["--out", str(out), "--replace"])
            if r.returncode != 2 or f"pid {p.pid}" not in r.stderr:
                return f"second run on the same --out: exit {r.returncode}: {r.stderr.strip()[-200:]}"
            p.wait(timeout=300)
            if p.returncode != 0:
                return f"first run harmed: exit {p.returncode}"
            return ""
        finally:
            if p.poll() is None:
                p.kill()

    cases = [Case("sharing/devices held by another run", "exit 2 naming the device and the holding run", held_devices),
             Case("sharing/two runs on one --out", "the second refused naming the first's pid; the first completes",
                  one_out)]
    if not quick:
        cases.append(Case("sharing/two borg runs on one lab sim bench",
                          "the second refused naming the busy device and the first run; the first completes",
                          busy_bench))
    return cases


# ---- the command ----------------------------------------------------------------------------


SECTIONS = ("devices", "kill", "signals", "inputs", "protocol", "sharing",
            "links",           # lab/studies/bench_faults_links.py
            "input-meaning")   # lab/studies/bench_faults_inputs.py


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="a small slice (about 40 cases, a minute)")
    p.add_argument("--json", action="store_true", help='print {"cases", "ok", "bad": [{"case", "expected", "got"}]}')
    p.add_argument("--only", choices=SECTIONS, action="append", help="run only these sections (repeatable)")
    p.add_argument("--keep", metavar="DIR", help="keep the runs in DIR (default: a temporary directory)")


def _input_meaning_cases(lab_main: Callable[[list[str]], Any], work: Path, quick: bool) -> list[Any]:
    from lab.studies.bench_faults_inputs import cases

    return cases(work, quick, lab_main)


def campaign(quick: bool, only: list[str] | None = None, work: Path | None = None,
             progress: Callable[[str], None] = lambda s: None, *, lab_main: Callable[[list[str]], Any]) -> Report:
    """The campaign's cases, section by section.  `lab_main`: the CLI's entry point (`lab.cli.main`,
    `args.lab_main` under `lab bench faults`), which the inputs sections run in this process; a
    study sits below the CLI and does not import it."""
    tmp = None
    if work is None:
        tmp = tempfile.TemporaryDirectory(prefix="lab-faults-")
        work = Path(tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    report = Report()
    ref = Reference(work)
    builders: dict[str, Callable[[], list[Case]]] = {
        "devices": lambda: device_cases(quick),
        "kill": lambda: kill_cases(ref, work, quick),
        "signals": lambda: signal_cases(ref, work, quick),
        "inputs": lambda: input_cases(lab_main, work, quick),
        "protocol": lambda: protocol_cases(quick),
        "sharing": lambda: sharing_cases(work, quick),
        "links": lambda: [Case(*spec) for spec in link_cases(work, quick)],
        "input-meaning": lambda: _input_meaning_cases(lab_main, work, quick),
    }
    try:
        for section in SECTIONS:
            if only and section not in only:
                continue
            t0 = time.perf_counter()
            cases = builders[section]()
            for c in cases:
                progress(c.name)
                report.add(c)
            report.seconds[section] = round(time.perf_counter() - t0, 1)
    finally:
        if tmp is not None:
            tmp.cleanup()
    return report


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    show = (lambda s: print(f"  {s}", file=sys.stderr, flush=True)) if not args.json and os.isatty(2) else (lambda s: None)
    report = campaign(bool(args.quick), args.only, Path(args.keep) if args.keep else None, show,
                      lab_main=args.lab_main)
    wall = time.perf_counter() - t0
    if args.json:
        print(json.dumps({"cases": report.cases, "ok": report.ok, "bad": report.bad, "seconds": report.seconds,
                          "wall_s": round(wall, 1)}, indent=1))
    else:
        print(f"lab bench faults{' --quick' if args.quick else ''}: {report.cases} cases tried, {report.ok} ok, "
              f"{len(report.bad)} bad ({wall:.0f} s; " + ", ".join(f"{k} {v:g} s" for k, v in report.seconds.items())
              + ")")
        for b in report.bad:
            print(f"  BAD {b['case']}: expected {b['expected']}; got {b['got']}")
    return 0 if not report.bad else 1
