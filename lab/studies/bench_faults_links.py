"""`lab bench faults` section `links` (issue 22): one owner per physical device, and devices that
stop when their host goes.  Every case is a real run against the simulators.

- locks:     a process holds a device (commanding a move) under one spelling; a second `lab run`
             under another — `localhost`, `127.1`, `[::1]`, a symlink to the serial port — or with
             another XDG_RUNTIME_DIR / TMPDIR / LAB_RUNTIME_DIR, or as another user, must be refused
             in one line naming the device and the holder, and the holder's move must go on
             untouched; a process that skips the lock and opens the serial port anyway is refused
             by the exclusive open;
- host loss: a host process moving a device is SIGKILLed (its link closes) or SIGSTOPped (its link
             stays up, it falls silent) mid-move: a device with the protocol's firmware must stop
             short of the target (at once on link loss, within its watchdog otherwise; an HTTP
             device by its watchdog), a device of an older firmware (`[sim] watchdog_s = 0`,
             `stop_on_link_loss = false`) must finish the move;
- resume:    a `lab run borg` against a `lab sim` bench in another process is SIGKILLed while the
             turntable turns; the turntable must have stopped half-way (protocol firmware) or have
             finished the move (older firmware); `lab resume` must re-command the interrupted move,
             complete, hold every step once, and find what an uninterrupted run finds.

The builders return `CaseSpec`s (name, expected, check); bench_faults.py wraps them in its `Case`.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple

LAB = [sys.executable, "-m", "lab"]
ROOT = Path(__file__).resolve().parents[2]
SIM_RIG = ROOT / "lab" / "rigs" / "sim.toml"
OLD_FIRMWARE = {"watchdog_s": 0, "stop_on_link_loss": False}
BORG = ["run", "borg", "--auto", "--quiet", "--modules", "2", "--on-flag", "continue", "--no-rig-survey"]


class CaseSpec(NamedTuple):
    name: str
    expected: str
    check: Callable[[], str]          # "" when the case ends as expected, else what happened


# ---- rig files ------------------------------------------------------------------------------


def rig_text(urls: dict[str, str], sim: dict[str, Any] | None = None) -> str:
    """The packaged simulated rig with the devices at `urls`: with `sim` (extra [sim] keys, may be
    empty) a simulated rig for `lab sim`, without it the same bench as hardware."""
    out: list[str] = []
    device = ""
    for line in SIM_RIG.read_text().splitlines():
        header = re.match(r"^\[([\w.]+)\]", line)
        if header:
            device = header.group(1).split(".")[-1] if not header.group(1).startswith("sim") else ""
            if header.group(1) == "sim":
                if sim is None:
                    break
                out.append(line)
                out += [f"{k} = {json.dumps(v)}" for k, v in sim.items()]
                continue
        if device in urls and re.match(r"^url\s*=", line):
            line = f"url = {json.dumps(urls[device])}"
        out.append(line)
    return "\n".join(out) + "\n"


def write_rig(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    shutil.copy(SIM_RIG.parent / "sim_camera.json", path.parent / "sim_camera.json")
    return path


def fixed_ports(n: int) -> list[int]:
    """n free loopback ports below the kernel's ephemeral range (for a `lab sim` on fixed ports)."""
    from sim_devices.bench import ephemeral_port_range

    lo, _ = ephemeral_port_range()
    ports: list[int] = []
    start = 20000 + (os.getpid() * 37) % max(1, lo - 21000 - 10 * n)
    for port in range(start, lo):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        ports.append(port)
        if len(ports) == n:
            return ports
    raise RuntimeError("no free ports below the ephemeral range")


def _lab(args: list[str], env: dict[str, str] | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(LAB + args, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


# ---- the simulated world, seen from the bench ------------------------------------------------


def _axis(bench: Any, device: str) -> Any:
    w = bench.world
    return {"turntable": w.turntable, "stewart": w.stewart_legs, "lift": w.lift}.get(device) or w.ipjrs[device].axis


def _distance(a: Any, b: Any) -> float:
    import numpy as np

    return float(np.max(np.abs(np.asarray(a, dtype=float) - np.asarray(b, dtype=float))))


# ---- processes that hold or move a device -----------------------------------------------------

# A process that owns one device and moves it as a run does (the driver polls it while it moves):
# argv = rig, device, how far (deg for the turntable, m for the lift and the Stewart's z, IPJR steps).
_MOVER = r"""
import math, sys, threading, time
import drivers
from lab.core.config import load_rig
from lab.core.locks import set_holder

set_holder(run="holder-run")
rig, name = load_rig(sys.argv[1]), sys.argv[2]
devs = drivers.connect(rig, only=[name])
dev = devs[name]
if name == "turntable":
    dev.home()
    move = lambda: dev.move_to(math.radians(float(sys.argv[3])))
elif name == "lift":
    move = lambda: dev.move_to(float(sys.argv[3]))
elif name == "stewart":
    move = lambda: dev.move_to([0.0, 0.0, float(sys.argv[3]), 0.0, 0.0, 0.0])
else:
    move = lambda: dev.step(int(sys.argv[3]))
threading.Thread(target=move, daemon=True).start()
time.sleep(0.3)
print("moving", flush=True)
time.sleep(600)
"""

# how far each device is sent (wire-ish units the mover takes): 2-4 s of motion at speedup 1
_MOVES = {"turntable": "30", "lift": "0.3", "stewart": "0.06", "ipjr1": "250", "ipjr3": "250"}


def _start_mover(rig: Path, device: str, amount: str | None = None) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", _MOVER, str(rig), device, amount or _MOVES[device]],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=str(ROOT))
    line = p.stdout.readline().strip() if p.stdout else ""
    if line != "moving":
        p.kill()
        _, err = p.communicate(timeout=10)
        raise RuntimeError(f"the holder did not start moving {device}: {err.strip()[-300:]}")
    return p


def _end(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.kill()
    p.wait(timeout=10)


# ---- one owner per device -----------------------------------------------------------------------


def _refused(r: subprocess.CompletedProcess, device: str, holder: str) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    if r.returncode != 2:
        return f"the second run was not refused: exit {r.returncode}: {(r.stderr or r.stdout).strip()[-200:]}"
    if len(lines) != 1 or "Traceback" in r.stderr:
        return f"refused in {len(lines)} lines, not one: {lines[:3]}"
    if f"device {device}" not in lines[0] or holder not in lines[0] or "nothing was moved" not in lines[0]:
        return f"the refusal does not name device {device} and the holder ({holder}): {lines[0]}"
    return ""


def _lock_case(work: Path, label: str, spell: Callable[[Any], dict[str, str]], *, env: dict[str, str] | None = None,
               device: str = "turntable", pty: bool = False) -> CaseSpec:
    """The holder owns `device` under the bench's own URLs; a second `lab run borg` whose rig spells
    the bench by `spell(bench)` (and runs with `env`) must be refused, the holder's move untouched."""

    def check() -> str:
        from sim_devices.bench import start_sim_bench

        d = work / re.sub(r"\W+", "_", label)
        with start_sim_bench(speedup=1, pty=pty) as bench:
            urls = dict(bench.urls)
            if pty:
                urls[device] = bench.pty_paths[device]
            first = write_rig(d / "first.toml", rig_text(urls))
            second = write_rig(d / "second" / "second.toml", rig_text({**urls, **spell(bench)}))
            holder = _start_mover(first, device, "300" if device == "turntable" else None)
            try:
                axis = _axis(bench, device)
                target = axis.target()
                r = _lab(BORG + ["--rig", str(second), "--out", str(d / "run")], env=env)
                problem = _refused(r, device, "holder-run")
                if problem:
                    return problem
                if not axis.moving() or _distance(axis.target(), target) > 1e-9:
                    return "the holder's move was disturbed (the device stopped or got another target)"
                return ""
            finally:
                _end(holder)

    return CaseSpec(f"links/locks/{label}", "second run refused in one line naming the device and the holder; "
                                            "the holder's move goes on", check)


def _exclusive_open_case(work: Path) -> CaseSpec:
    """A process that skips the lock (not `lab`) and opens the serial port by another name while a
    run has it open must be refused by the OS's exclusive open."""

    def check() -> str:
        from drivers.errors import Disconnected
        from drivers.transport import LineTransport
        from sim_devices.bench import start_sim_bench

        d = work / "exclusive"
        d.mkdir(parents=True, exist_ok=True)
        with start_sim_bench(speedup=1, pty=True) as bench:
            path = bench.pty_paths["turntable"]
            alias = d / "ttyTURNTABLE"
            alias.unlink(missing_ok=True)
            alias.symlink_to(path)
            holder = _start_mover(write_rig(d / "first.toml", rig_text({**bench.urls, "turntable": path})),
                                  "turntable", "300")
            try:
                link = LineTransport("turntable", str(alias), reply_timeout_s=0.3, retries=0)
                try:
                    link.open()
                except Disconnected as exc:
                    return "" if "exclusive" in exc.message or "lock" in exc.message else f"refused, but: {exc}"
                link.close()
                return "a second opener of the serial port (through a symlink) was let in"
            finally:
                _end(holder)

    return CaseSpec("links/locks/serial exclusive open through a symlink",
                    "the OS refuses a second opener that skipped the lock", check)


def _as_user(uid: int, act: Callable[[], str], hold_s: float = 0.0) -> tuple[int, Callable[[], str]]:
    """Fork a process that becomes user `uid` and runs `act` (it returns "ok ..." or a problem);
    with hold_s it then stays alive that long (holding what it took).  Returns (pid, result):
    result() waits for the child's first report.  This process must hold no device claim: a forked
    child would share its lock instead of asking for one."""
    from drivers.ownership import held_keys

    assert not held_keys(), f"fork with device claims held: {held_keys()}"
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:   # the child: no Python objects of the parent's threads are touched
        try:
            os.close(r)
            os.setgroups([])
            os.setgid(uid)
            os.setuid(uid)
            try:
                text = act()
            except BaseException as exc:  # noqa: BLE001 (reported to the parent)
                text = f"{type(exc).__name__}: {exc}"
            os.write(w, text.encode()[:4000])
            os.close(w)
            time.sleep(hold_s)
        finally:
            os._exit(0)
    os.close(w)

    def result() -> str:
        with os.fdopen(r, "rb") as f:
            return f.read(4000).decode(errors="replace")

    return pid, result


def _other_user_cases(work: Path) -> list[CaseSpec]:
    """Only where this process may become another user (root): a lock taken by one user must
    refuse the other, both ways round."""
    if os.getuid() != 0:
        return []
    try:
        import pwd

        nobody = pwd.getpwnam("nobody").pw_uid
    except (ImportError, KeyError):
        return []

    def other_refused() -> str:
        from drivers.ownership import claim
        from sim_devices.bench import start_sim_bench

        with start_sim_bench(speedup=1) as bench:
            url = bench.urls["turntable"].replace("127.0.0.1", "localhost")
            holder = _start_mover(write_rig(work / "users-a" / "first.toml", rig_text(bench.urls)), "turntable", "300")
            try:
                def try_claim() -> str:
                    try:
                        claim("turntable", url)
                    except Exception as exc:
                        return f"refused {exc}"
                    return "claimed"

                pid, result = _as_user(nobody, try_claim)
                text = result()
                os.waitpid(pid, 0)
                if not text.startswith("refused") or "holder-run" not in text or "device turntable" not in text:
                    return f"user nobody, asking for the device root's run holds: {text}"
                return ""
            finally:
                _end(holder)

    def root_refused() -> str:
        from drivers.ownership import claim
        from sim_devices.bench import start_sim_bench

        with start_sim_bench(speedup=1) as bench:
            url = bench.urls["turntable"]

            def take() -> str:
                claim("turntable", url)
                return "ok held"

            pid, result = _as_user(nobody, take, hold_s=60)
            try:
                text = result()
                if text != "ok held":
                    return f"user nobody could not take the device lock: {text}"
                second = write_rig(work / "users-b" / "second.toml",
                                   rig_text({**bench.urls, "turntable": url.replace("127.0.0.1", "127.1")}))
                r = _lab(BORG + ["--rig", str(second), "--out", str(work / "users-b" / "run")])
                return _refused(r, "turntable", "of user nobody")
            finally:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)

    return [CaseSpec("links/locks/another user holds, root asks", "refused naming the other user's process",
                     root_refused),
            CaseSpec("links/locks/root holds, another user asks", "refused naming the holder", other_refused)]


def lock_cases(work: Path, quick: bool) -> list[CaseSpec]:
    def host(name: str) -> Callable[[Any], dict[str, str]]:
        return lambda bench: {"turntable": bench.urls["turntable"].replace("127.0.0.1", name)}

    def symlink(bench: Any) -> dict[str, str]:
        link = work / "tty-by-id" / "usb-LAB_RT1-if00-port0"
        link.parent.mkdir(parents=True, exist_ok=True)
        link.unlink(missing_ok=True)
        link.symlink_to(bench.pty_paths["turntable"])
        return {"turntable": str(link)}

    spellings = ["localhost", "127.1"] if quick else ["127.0.0.1", "localhost", "LOCALHOST", "127.1", "[::1]",
                                                      "0.0.0.0"]
    cases = [_lock_case(work, f"spelled {h}", host(h)) for h in spellings]
    cases.append(_lock_case(work, "serial port through a by-id symlink", symlink, pty=True))
    envs = {"XDG_RUNTIME_DIR": {"XDG_RUNTIME_DIR": str(work / "xdg")},
            "TMPDIR": {"TMPDIR": str(work / "tmpdir")},
            "LAB_RUNTIME_DIR": {"LAB_RUNTIME_DIR": str(work / "lab-runtime")}}
    envs["all three"] = {k: v for e in envs.values() for k, v in e.items()}
    for d in envs.values():
        for path in d.values():
            Path(path).mkdir(parents=True, exist_ok=True)
    for label, env in (envs.items() if not quick else [("all three", envs["all three"])]):
        cases.append(_lock_case(work, f"another {label}", host("localhost"), env=env))
    if not quick:
        cases.append(_lock_case(work, "http ipjr spelled localhost", lambda b: {
            "ipjr1": b.urls["ipjr1"].replace("127.0.0.1", "localhost")}, device="ipjr1"))
    cases.append(_exclusive_open_case(work))
    cases += _other_user_cases(work)
    return cases


# ---- host loss --------------------------------------------------------------------------------


def _host_loss_case(work: Path, device: str, action: str, old: bool, pty: bool = False) -> CaseSpec:
    via = " over its pty" if pty else ""
    firmware = "older firmware" if old else "protocol firmware"
    name = f"links/host loss/{device}{via}/{action}/{firmware}"
    expected = "the device finishes its move" if old else "the device stops short of the target"

    def check() -> str:
        from sim_devices.bench import start_sim_bench
        from sim_devices.watchdog import WATCHDOG_S, Firmware

        fw = Firmware(0, False) if old else Firmware()
        d = work / re.sub(r"\W+", "_", name)
        with start_sim_bench(speedup=1, pty=pty, firmware=fw) as bench:
            urls = dict(bench.urls)
            if pty:
                urls[device] = bench.pty_paths[device]
            host = _start_mover(write_rig(d / "rig.toml", rig_text(urls)), device)
            axis = _axis(bench, device)
            try:
                if not axis.moving():
                    return "the host's move did not start"
                target = axis.target()
                os.kill(host.pid, signal.SIGKILL if action == "SIGKILL" else signal.SIGSTOP)
                t0 = time.monotonic()
                # a closed link stops a serial device at once; silence (a frozen host, or HTTP)
                # stops it within the watchdog
                at_once = action == "SIGKILL" and not bench.urls[device].startswith("http")
                budget = (0.3 if at_once else WATCHDOG_S + 0.4)
                if old:
                    time.sleep(budget + 0.2)
                    if not axis.moving():
                        return f"an older firmware's device stopped {_distance(axis.position(), target):.4g} short"
                    deadline = time.monotonic() + 10.0
                    while axis.moving() and time.monotonic() < deadline:
                        time.sleep(0.02)
                    off = _distance(axis.position(), target)
                    return "" if not axis.moving() and off < 1e-9 else f"did not finish: {off:.4g} from the target"
                while axis.moving() and time.monotonic() - t0 < budget + 0.5:
                    time.sleep(0.01)
                took = time.monotonic() - t0
                if axis.moving():
                    return f"still moving {took:.2f} s after its host was {action} ({expected} within {budget:g} s)"
                if took > budget:
                    return f"stopped only {took:.2f} s after its host was {action} (allowed {budget:g} s)"
                off = _distance(axis.position(), target)
                if off < 1e-6:
                    return "the device reached the target: nothing was stopped"
                where = axis.position()
                time.sleep(0.3)
                if _distance(axis.position(), where) > 1e-12:
                    return "the device moved again after stopping"
                return ""
            finally:
                _end(host)

    return CaseSpec(name, f"host {action} mid-move: {expected}", check)


def host_loss_cases(work: Path, quick: bool) -> list[CaseSpec]:
    if quick:
        plan = [("turntable", "SIGKILL", False, False), ("turntable", "SIGKILL", True, False),
                ("turntable", "SIGKILL", False, True), ("turntable", "SIGSTOP", False, False),
                ("ipjr1", "SIGKILL", False, False), ("ipjr1", "SIGKILL", True, False)]
    else:
        plan = [(dev, action, old, pty) for dev, pty in (("turntable", False), ("turntable", True), ("stewart", False),
                                                        ("lift", False), ("ipjr3", False), ("ipjr1", False))
                for action in ("SIGKILL", "SIGSTOP") for old in (False, True)]
    return [_host_loss_case(work, *p) for p in plan]


# ---- kill a run mid-move, resume ---------------------------------------------------------------


class _Sim:
    """`lab sim` in its own process, on fixed free ports, as a real bench is another machine."""

    def __init__(self, d: Path, old: bool, speedup: float) -> None:
        names = ["turntable", "stewart", "lift", "camera", "ipjr1", "ipjr2", "ipjr3"]
        ports = dict(zip(names, fixed_ports(len(names))))
        urls = {n: (f"http://127.0.0.1:{p}" if n.startswith("ipjr") and n != "ipjr3" else f"socket://127.0.0.1:{p}")
                for n, p in ports.items()}
        urls["camera"] = f"http://127.0.0.1:{ports['camera']}/frame.jpg"
        self.urls = urls
        self.sim_rig = write_rig(d / "sim.toml", rig_text(urls, OLD_FIRMWARE if old else {}))
        self.hw_rig = write_rig(d / "hw.toml", rig_text(urls))
        self.proc = subprocess.Popen(LAB + ["sim", "--rig", str(self.sim_rig), "--no-pty", "--speedup", f"{speedup:g}"],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"lab sim did not start: {self.proc.stdout.read()[-300:] if self.proc.stdout else ''}")
            try:
                if self.ask("ID?").startswith("OK TURNTABLE"):
                    return
            except OSError:
                time.sleep(0.1)
        raise RuntimeError("lab sim did not answer within 30 s")

    def ask(self, line: str) -> str:
        """One request to the turntable over a link of its own (it neither feeds nor owns a run's
        motion: docs/protocols.md §1)."""
        host, port = self.urls["turntable"].split("//")[1].split(":")
        with socket.create_connection((host, int(port)), timeout=2) as s:
            s.sendall(f"{line}\n".encode())
            data = b""
            while not data.endswith(b"\n"):
                chunk = s.recv(4096)
                if not chunk:
                    break
                data += chunk
        return data.decode().strip()

    def status(self) -> dict[str, str]:
        return dict(kv.split("=", 1) for kv in self.ask("STATUS?").split()[1:])

    def close(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _steps_done(out: Path) -> int:
    try:
        return int(json.loads((out / "checkpoint.json").read_text())["steps_completed"])
    except (OSError, ValueError, KeyError):
        return 0


def _step_ends(path: Path) -> list[int]:
    from lab.core.recorder import topics
    from lab.core.recorder.reader import iter_messages

    return [r.message.index for r in iter_messages(path) if r.topic == topics.RUN_STEP and r.message.phase == "end"]


def _findings(summary: dict) -> dict:
    """What a BORG run finds: each module's verdict, and the tags it rejected."""
    return {"modules": [(m.get("name"), m.get("verdict")) for m in summary.get("modules", [])],
            "rejected_tags": summary.get("rejected_tags"), "result": summary.get("result")}


def _sent(path: Path, device_url: str) -> list[str]:
    from lab.core.recorder import topics
    from lab.core.recorder.reader import iter_messages

    out = []
    for r in iter_messages(path, topics.COMMS):
        if r.message.direction == "tx" and r.message.url == device_url:
            out.append(r.message.data.decode("ascii", errors="replace").strip())
    return out


class Reference:
    """One uninterrupted BORG run against a fresh `lab sim`, shared by the resume cases."""

    def __init__(self, work: Path, speedup: float) -> None:
        self.work = work
        self.speedup = speedup
        self._found: dict | None = None

    def findings(self) -> dict:
        if self._found is None:
            d = self.work / "links-reference"
            sim = _Sim(d, old=False, speedup=self.speedup)
            try:
                r = _lab(BORG + ["--rig", str(sim.hw_rig), "--out", str(d / "run")])
            finally:
                sim.close()
            if r.returncode != 0:
                raise RuntimeError(f"the uninterrupted reference run failed: {r.stderr.strip()[-300:]}")
            self._found = _findings(json.loads((d / "run" / "summary.json").read_text()))
        return self._found


SPEEDUP = 5.0        # lab sim's: a turntable move of tens of degrees lasts a fraction of a second


def resume_case(work: Path, ref: Reference, old: bool) -> CaseSpec:
    kind = "older firmware: finishes the move" if old else "protocol firmware: stops half-way"
    name = f"links/resume/run SIGKILLed while the turntable turns, {kind}"

    def check() -> str:
        d = work / ("resume-old" if old else "resume-new")
        shutil.rmtree(d, ignore_errors=True)
        sim = _Sim(d, old, ref.speedup)
        out = d / "run"
        try:
            run = subprocess.Popen(LAB + BORG + ["--rig", str(sim.hw_rig), "--out", str(out)],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
            try:
                # after the first step is on disk, wait for a turntable move with a long way to go
                deadline = time.monotonic() + 240
                caught: dict[str, str] | None = None
                while time.monotonic() < deadline and run.poll() is None:
                    if _steps_done(out) >= 1:
                        st = sim.status()
                        if st["state"] == "MOVING" and abs(float(st["target_deg"]) - float(st["pos_deg"])) > 15:
                            caught = st
                            break
                    time.sleep(0.005)
                if caught is None:
                    return f"never caught the turntable mid-move after step 1 (run exit {run.poll()})"
                run.send_signal(signal.SIGKILL)
                run.wait(timeout=30)
            finally:
                if run.poll() is None:
                    run.kill()
                    run.wait()
            target = float(caught["target_deg"])
            time.sleep(0.2)
            after = sim.status()
            if old:
                deadline = time.monotonic() + 20
                while after["state"] != "IDLE" and time.monotonic() < deadline:
                    time.sleep(0.05)
                    after = sim.status()
                if abs(float(after["pos_deg"]) - target) > 0.001:
                    return f"older firmware: the turntable stopped at {after['pos_deg']} deg, not the target {target:.3f}"
            else:
                if after["state"] != "IDLE":
                    return f"the turntable is still {after['state']} 0.2 s after its run was killed"
                if abs(float(after["pos_deg"]) - target) < 1.0:
                    return f"the turntable went on to {after['pos_deg']} deg (target {target:.3f}) after its run died"
            stopped_at = after["pos_deg"]
            r = _lab(["resume", str(out), "--auto"])
            if r.returncode != 0:
                return f"resume exited {r.returncode}: {(r.stderr or r.stdout).strip()[-300:]}"
            summary = json.loads((out / "summary.json").read_text())
            if summary.get("result") != "completed":
                return f"resumed run ended {summary.get('result')}: {summary.get('reason')}"
            ends = _step_ends(out / "run.mcap")
            if ends != [0, 1]:
                return f"the resumed log holds step ends {ends}, not 0, 1 once each"
            moves = [c for c in _sent(out / "run.mcap", sim.urls["turntable"]) if " MOVE " in f" {c} "]
            if not any(c.endswith(f"MOVE {target:.3f}") for c in moves):
                return (f"the resumed run never re-commanded the interrupted move to {target:.3f} deg (from "
                        f"{stopped_at} deg); it sent {moves[-6:]}")
            got, want = _findings(summary), ref.findings()
            if got != want:
                return f"findings differ from the uninterrupted run's: {got} vs {want}"
            return ""
        finally:
            sim.close()

    return CaseSpec(name, "the turntable " + ("finished the move" if old else "stopped short") + "; resume re-commands "
                    "the move, completes, every step once, findings of the uninterrupted run", check)


def resume_cases(work: Path, quick: bool, speedup: float = SPEEDUP) -> list[CaseSpec]:
    ref = Reference(work, speedup)
    return [resume_case(work, ref, old=False), resume_case(work, ref, old=True)]


def link_cases(work: Path, quick: bool) -> list[CaseSpec]:
    """Every case of the section, in order: locks, host loss, resume."""
    return lock_cases(work, quick) + host_loss_cases(work, quick) + resume_cases(work, quick)
