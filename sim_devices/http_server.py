"""A small GET-only HTTP server for the simulated Raspberry Pi and camera (real HTTP on
127.0.0.1, `http.server.ThreadingHTTPServer`), with the faults of sim_devices/faults.py.

A route is `path -> handler(query: dict[str, str], stuck: bool) -> (status, content_type, body,
headers)` (`stuck`: an injected stuck-actuator fault applies to this request); a handler
raises `Refuse` for a protocol error, which becomes the JSON error of docs/protocols.md §5.

HTTP has no standing link to lose, so a device that moves (`stop` given) has the watchdog of
sim_devices/watchdog.py: every request feeds it, and a motion during which no request arrives for
longer than `Firmware.watchdog_s` is stopped."""

from __future__ import annotations

import json
import threading
import time
import urllib.parse
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Callable

from sim_devices.faults import FaultInjector
from sim_devices.line_server import E_INTERNAL, E_SYNTAX, E_UNKNOWN, Refuse
from sim_devices.watchdog import Firmware, Watchdog

Reply = tuple[int, str, bytes, dict[str, str]]
Route = Callable[[dict[str, str], bool], Reply]   # (query, stuck) -> reply

HTTP_STATUS = {10: 404, 11: 400, 12: 400, 20: 400, 30: 409, 31: 409, 40: 409, 50: 500}
HUNG_REQUEST_S = 10.0      # how long a `timeout` fault keeps a request open before dropping it
REQUEST_TIMEOUT_S = 5.0    # a client that does not finish sending its request in this time is dropped
MAX_CONNECTIONS = 32       # more at once are turned away with 503 (a Pi serves one host, not a crowd)
STOP_WAIT_S = 4.0          # stop() waits this long for requests under way (a frame being rendered) to end
MAX_TARGET = 2048          # bytes of path + query


def parse_query(query: str) -> dict[str, str]:
    """The query string as a dict; a malformed or repeated parameter is refused (`steps=5&steps=-1000`
    must not quietly mean either one)."""
    try:
        pairs = urllib.parse.parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query))
    except ValueError:
        raise Refuse(E_SYNTAX, f"malformed query {query[:80]!r}") from None
    out: dict[str, str] = {}
    for k, v in pairs:
        if k in out:
            raise Refuse(E_SYNTAX, f"parameter {k!r} given more than once")
        out[k] = v
    return out


def json_reply(obj: dict[str, Any], status: int = 200, headers: dict[str, str] | None = None) -> Reply:
    return status, "application/json", json.dumps(obj).encode(), headers or {}


def error_reply(code: int, text: str) -> Reply:
    return json_reply({"error": {"code": code, "text": text}}, HTTP_STATUS.get(code, 500))


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    block_on_close = False
    allow_reuse_address = True
    request_queue_size = 64

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self._active = 0                            # requests under way, each in its own thread
        self._idle = threading.Condition()

    def process_request(self, request: Any, client_address: Any) -> None:
        with self._idle:
            busy = self._active >= MAX_CONNECTIONS
            if not busy:
                self._active += 1
        if busy:                                    # every slot busy: refuse at once, hold no thread
            try:
                request.sendall(b"HTTP/1.0 503 Service Unavailable\r\nContent-Length: 0\r\n\r\n")
            except OSError:
                pass
            self.shutdown_request(request)
            return
        super().process_request(request, client_address)

    def handle_error(self, request: Any, client_address: Any) -> None:
        import sys

        if isinstance(sys.exc_info()[1], (ConnectionError, TimeoutError)):
            return   # the client went away (it timed out, or was killed): not the server's error
        super().handle_error(request, client_address)

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self._idle:
                self._active -= 1
                self._idle.notify_all()

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait for the requests under way to finish.  A request thread is a daemon; one still
        inside OpenCV (the camera's render) when the interpreter exits is killed inside C++ and
        aborts the whole process (`terminate called without an active exception`): a run aborted
        mid-frame exited with SIGABRT instead of its own exit code."""
        with self._idle:
            return self._idle.wait_for(lambda: self._active == 0, timeout_s)


class HttpDeviceServer:
    def __init__(self, name: str, routes: dict[str, Route], faults: FaultInjector, *,
                 is_moving: Callable[[], bool] = lambda: False, motion_paths: frozenset[str] = frozenset(),
                 on_link_lost: Callable[[], None] = lambda: None, host: str = "127.0.0.1", port: int = 0,
                 stop: Callable[[], None] | None = None, firmware: Firmware = Firmware()) -> None:
        self.name = name
        self.routes = routes
        self.faults = faults
        self._stop = threading.Event()
        self.watchdog = Watchdog(name, firmware.watchdog_s if stop is not None else 0.0, is_moving,
                                 stop or (lambda: None))
        outer = self

        class Handler(BaseHTTPRequestHandler):
            server_version = "lab-sim/1.0"
            protocol_version = "HTTP/1.0"
            timeout = REQUEST_TIMEOUT_S     # socket timeout: a half-sent request cannot hold a thread

            def log_message(self, fmt: str, *args: Any) -> None:  # quiet: the driver logs comms
                pass

            def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
                outer.watchdog.feed()          # the host is there, whatever it asks
                if len(self.path) > MAX_TARGET:
                    return self._send(error_reply(E_SYNTAX, f"request target longer than {MAX_TARGET} bytes"))
                parts = urllib.parse.urlsplit(self.path)
                try:
                    query = parse_query(parts.query)
                except Refuse as r:
                    return self._send(error_reply(r.code, r.text))
                fault = outer.faults.on_request(self.path, is_moving(), parts.path in motion_paths)
                if fault == "timeout":
                    outer._stop.wait(HUNG_REQUEST_S)
                    self.close_connection = True
                    return
                if fault == "disconnect":
                    on_link_lost()
                    self.close_connection = True
                    return
                if fault == "http_500":
                    return self._send(error_reply(E_INTERNAL, "injected fault: internal server error"))
                route = outer.routes.get(parts.path)
                if route is None:
                    reply = error_reply(E_UNKNOWN, f"unknown path {parts.path!r} (known: {', '.join(sorted(outer.routes))})")
                else:
                    try:
                        reply = route(query, fault == "stuck")
                    except Refuse as r:
                        reply = error_reply(r.code, r.text)
                    except Exception as exc:
                        reply = error_reply(E_INTERNAL, f"internal error: {type(exc).__name__}: {exc}")
                if fault == "garbled":
                    status, ctype, body, headers = reply
                    reply = (status, ctype, outer.faults.garble(body), headers)
                self._send(reply)

            def _send(self, reply: Reply) -> None:
                status, ctype, body, headers = reply
                self.send_response(status)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                for k, v in headers.items():
                    self.send_header(k, v)
                self.end_headers()
                self.wfile.write(body)

        try:
            self._httpd = _Server((host, port), Handler)
        except OSError as exc:
            raise OSError(exc.errno, f"{name}: cannot listen on {host}:{port}: {exc.strerror} "
                                     f"(is another `lab sim` running?)") from None
        self.host, self.port = self._httpd.server_address[:2]
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def start(self) -> HttpDeviceServer:
        self.watchdog.start()
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.05},
                                        name=f"{self.name}-http", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self.watchdog.stop()
        self._httpd.shutdown()
        self._httpd.server_close()
        if self._thread:
            self._thread.join(timeout=1.0)
        self._httpd.wait_idle(STOP_WAIT_S)


def now_s() -> float:
    return time.time()
