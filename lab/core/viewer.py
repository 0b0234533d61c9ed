"""Where a Rerun recording goes: a local viewer, the web viewer served on loopback, a viewer that
is already running, or an .rrd file.  `lab review` (and the live view of `lab run --view`) use it.

Why not `RecordingStream.spawn()` everywhere: without a display the spawned native viewer dies
(winit cannot open a window), the SDK waits for it to bind its port and the command hangs.  Why not
the SDK's own `serve_grpc()` for the web viewer: it listens on every interface (0.0.0.0); a lab
machine should not publish its runs to the network by default.  The `rerun` CLI takes `--bind`,
so the web viewer and its gRPC proxy are served by a `rerun --serve-web --bind 127.0.0.1` child
process, and the recording is streamed into that proxy with `connect_grpc`.  The proxy buffers what
it received, so a browser opened later still sees the whole run.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lab.core.errors import LabError, UserError

LOOPBACK = "127.0.0.1"
START_TIMEOUT_S = 30.0          # the rerun CLI starts in ~0.5 s; a loaded CI machine is slower
PROXY_MEMORY_LIMIT = "2GiB"     # what the proxy buffers for late browsers (a full BORG run is ~60 MB)


def has_display(env: dict[str, str] | None = None) -> bool:
    """Can a native viewer open a window here?  Linux/BSD need an X or Wayland display; macOS and
    Windows always have one."""
    env = os.environ if env is None else env
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"))


def free_port(host: str = LOOPBACK) -> int:
    """A port nothing listens on now (the OS picks it; the rerun CLI binds it a moment later)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _listening(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


@dataclass
class WebViewer:
    """A `rerun --serve-web` child process bound to loopback."""
    process: subprocess.Popen
    grpc_port: int
    web_port: int
    log_path: Path

    @property
    def grpc_url(self) -> str:
        return f"rerun+http://{LOOPBACK}:{self.grpc_port}/proxy"

    @property
    def url(self) -> str:
        """What to open in a browser: the web viewer, told where the data is."""
        return f"http://{LOOPBACK}:{self.web_port}/?url={urllib.parse.quote(self.grpc_url, safe='')}"

    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self) -> None:
        """Stop the server and anything it started (its own process group)."""
        import signal

        if self.process.poll() is None:
            _signal_group(self.process, signal.SIGTERM)
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                _signal_group(self.process, signal.SIGKILL)
                self.process.wait(timeout=5)


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)      # start_new_session: its pid is its group's id
    except (ProcessLookupError, PermissionError, AttributeError):
        try:
            proc.send_signal(sig)
        except ProcessLookupError:
            pass


def rerun_command() -> list[str]:
    """The rerun CLI binary itself.  Not `python -m rerun`: that wrapper runs the binary as its own
    child, and stopping the wrapper would leave the binary (and its ports) behind."""
    import importlib.util
    import shutil

    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin:
        exe = Path(spec.origin).parent / ("rerun.exe" if sys.platform == "win32" else "rerun")
        if exe.is_file():
            return [str(exe)]
    found = shutil.which("rerun")
    if found:
        return [found]
    raise UserError("the Rerun viewer (the rerun CLI from rerun-sdk) is not installed: pip install rerun-sdk")


def start_web_viewer(timeout_s: float = START_TIMEOUT_S) -> WebViewer:
    """Start the web viewer and its gRPC proxy on loopback; return once both ports accept."""
    grpc_port, web_port = free_port(), free_port()
    log = Path(tempfile.mkstemp(prefix="lab-rerun-", suffix=".log")[1])
    cmd = [*rerun_command(), "--serve-web", "--bind", LOOPBACK, "--port", str(grpc_port),
           "--web-viewer-port", str(web_port), "--server-memory-limit", PROXY_MEMORY_LIMIT]
    env = dict(os.environ, RERUN_ANALYTICS="false")   # no first-run banner on the operator's terminal
    with open(log, "wb") as out:
        # its own session: the operator's Ctrl-C is ours to handle (a run pauses on it; we stop the
        # server ourselves); and on Linux it is told to go when we do, even by SIGKILL
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=env,
                                start_new_session=True, preexec_fn=_die_with_parent)
    viewer = WebViewer(proc, grpc_port, web_port, log)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            tail = log.read_text(errors="replace").strip().splitlines()[-1:] or ["no output"]
            raise LabError(f"the Rerun web viewer exited at start (code {proc.returncode}): {tail[0]}")
        if _listening(LOOPBACK, grpc_port) and _listening(LOOPBACK, web_port):
            return viewer
        time.sleep(0.1)
    viewer.stop()
    raise LabError(f"the Rerun web viewer did not listen on {LOOPBACK}:{web_port} within {timeout_s:.0f} s "
                   f"(its output: {log})")


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the parent dies (Linux prctl PR_SET_PDEATHSIG)."""
    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        try:
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, int(signal.SIGTERM))   # 1 = PR_SET_PDEATHSIG
        except OSError:
            pass


@dataclass
class Sink:
    """Where a recording went, in words for the operator."""
    kind: str                     # "save" | "spawn" | "web" | "connect" | "none"
    description: str
    web: WebViewer | None = None


def choose_mode(save: str | Path | None, connect: str | None, web: bool, env: dict[str, str] | None = None) -> str:
    if save is not None:
        return "save"
    if connect:
        return "connect"
    if web or not has_display(env):
        return "web"
    return "spawn"


def check_connect_url(url: str) -> str:
    """A viewer URL as the SDK takes it: rerun+http(s)://host:port/proxy, or a bare host:port."""
    if "://" not in url:
        url = f"rerun+http://{url}/proxy"
    try:
        parsed = urllib.parse.urlparse(url)
    except ValueError as exc:        # an unclosed "[" (IPv6) and the like
        raise UserError(f"--view/--connect {url!r}: not a URL ({exc}); expected rerun+http://HOST:PORT/proxy or "
                        f"HOST:PORT") from None
    if parsed.scheme not in ("rerun+http", "rerun+https", "rerun") or not parsed.hostname:
        raise UserError(f"--view/--connect {url!r}: expected rerun+http://HOST:PORT/proxy or HOST:PORT")
    try:
        parsed.port
    except ValueError:
        raise UserError(f"--view/--connect {url!r}: the port is not a number in 0..65535") from None
    return url


def check_viewer_answers(url: str) -> str:
    """A viewer URL that something listens at (checked before a run starts, so a mistyped --view
    is one line and nothing moves, not a minute of flushing into nothing at the end)."""
    url = check_connect_url(url)
    parsed = urllib.parse.urlparse(url)
    port = parsed.port or (443 if parsed.scheme.endswith("s") else 80)
    if not _listening(parsed.hostname or LOOPBACK, port):
        raise UserError(f"--view/--connect {url}: no Rerun viewer answers there (start one with `rerun`, "
                        f"or leave out the URL)")
    return url


def attach(rec: Any, mode: str, *, blueprint: Any = None, save: str | Path | None = None,
           connect: str | None = None) -> Sink:
    """Point the recording stream `rec` at its sink (before anything is logged, so nothing is lost)."""
    if mode == "save":
        from lab.core.paths import check_output_file

        out = check_output_file(save, "--save")  # type: ignore[arg-type]
        rec.save(out, default_blueprint=blueprint)
        return Sink("save", f"wrote {out}")
    if mode == "connect":
        url = check_viewer_answers(connect or "")
        rec.connect_grpc(url, default_blueprint=blueprint)
        return Sink("connect", f"sent to the Rerun viewer at {url}")
    if mode == "web":
        viewer = start_web_viewer()
        rec.connect_grpc(viewer.grpc_url, default_blueprint=blueprint)
        why = "" if has_display() else " (no display: DISPLAY and WAYLAND_DISPLAY are unset)"
        return Sink("web", f"serving the Rerun web viewer on loopback{why}: open {viewer.url}", viewer)
    if mode == "spawn":
        rec.spawn(port=free_port(), default_blueprint=blueprint)
        return Sink("spawn", "sent to a local Rerun viewer")
    return Sink("none", "not sent anywhere")


def wait_for_interrupt(viewer: WebViewer) -> None:
    """Keep the web viewer up until Ctrl-C / SIGTERM (or until it exits by itself), then stop it."""
    import signal

    def _term(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, _term)
    try:
        while viewer.alive():
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)
        viewer.stop()
        try:
            viewer.log_path.unlink()
        except OSError:
            pass


__all__ = ["has_display", "free_port", "WebViewer", "start_web_viewer", "Sink", "choose_mode", "attach",
           "check_connect_url", "check_viewer_answers", "wait_for_interrupt"]
