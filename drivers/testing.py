"""Test helpers: scripted fake devices that check a driver's exact bytes (PyMeasure's
`expected_protocol`, but over the real transports: a loopback socket for the line protocol, a
real HTTP server for GET APIs), and a fast simulated rig.

This module is part of the package, not of its tests, on purpose: it is the public helper for
anyone writing a driver, here or in their own code, as PyMeasure ships `expected_protocol` for
its instruments.  Write down the exchange the device's manual specifies, run the driver against it,
and leaving the `with` block fails the test if the driver sent anything else, in another order,
or left a request out (docs/hardware.md, "Writing a driver: test it against a scripted device").

    with ScriptedLineDevice([(b"POS?\\n", b"OK 90.000\\n")]) as dev:
        tt = Turntable(cfg, LineTransport("turntable", dev.url))
        assert tt.position() == pytest.approx(math.pi / 2)
    # leaving the block asserts every expected request arrived, in order, and nothing else

A reply of None sends nothing (the driver must time out); any bytes may be sent (garbled).
Request tags (`#17 `, docs/protocols.md §1) are stripped before comparing and put in front of the
scripted reply."""

from __future__ import annotations

import socket
import threading
import urllib.parse
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Self, Sequence

from lab.core.config import Rig, load_rig


class ScriptError(AssertionError):
    pass


class _Script:
    """What both scripted devices share: the exchanges expected in order (each's first element is
    the request), what arrived, what was wrong; served on a thread while the block runs, checked
    when it ends without an error."""

    def __init__(self, exchanges: Sequence[tuple[Any, ...]]) -> None:
        self.exchanges = list(exchanges)
        self.received: list[Any] = []
        self.problems: list[str] = []
        self._i = 0
        self._thread: threading.Thread

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._shut_down()
        if exc_type is None:
            self.verify()

    def _shut_down(self) -> None:
        raise NotImplementedError

    def verify(self) -> None:
        if self._i < len(self.exchanges):
            self.problems.append(f"expected requests never sent: {[x[0] for x in self.exchanges[self._i:]]}")
        if self.problems:
            raise ScriptError("; ".join(self.problems))


class ScriptedLineDevice(_Script):
    """Expects request lines in order; answers each with its scripted reply bytes."""

    def __init__(self, exchanges: Sequence[tuple[bytes, bytes | None]]) -> None:
        super().__init__(exchanges)
        self._stop = threading.Event()
        self._sock = socket.socket()
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.listen(4)
        self._sock.settimeout(0.02)
        self.url = f"socket://127.0.0.1:{self._sock.getsockname()[1]}"
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            conn.settimeout(0.02)
            buf = b""
            with conn:
                while not self._stop.is_set():
                    try:
                        chunk = conn.recv(4096)
                    except socket.timeout:
                        continue
                    except OSError:
                        break
                    if not chunk:
                        break
                    buf += chunk
                    while b"\n" in buf:
                        line, buf = buf.split(b"\n", 1)
                        line += b"\n"
                        tag, line = _untag(line)
                        self.received.append(line)
                        if self._i >= len(self.exchanges):
                            self.problems.append(f"unexpected extra request {line!r}")
                            continue
                        want, reply = self.exchanges[self._i]
                        self._i += 1
                        if line != want:
                            self.problems.append(f"request {self._i}: expected {want!r}, got {line!r}")
                        if reply is not None:
                            conn.sendall(tag + reply)

    def _shut_down(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._sock.close()


def _untag(line: bytes) -> tuple[bytes, bytes]:
    """(`#17 `, `POS?\n`) from a tagged request line; scripts are written without tags, and the
    scripted reply goes back with the request's tag, as a device does (docs/protocols.md §1)."""
    head, sep, rest = line.partition(b" ")
    if sep and head[:1] == b"#" and head[1:].isdigit():
        return head + b" ", rest
    return b"", line


class ScriptedHttpDevice(_Script):
    """Expects GET targets (path + query) in order; answers (status, JSON text or bytes)."""

    def __init__(self, exchanges: Sequence[tuple[str, int, bytes | str]]) -> None:
        super().__init__(exchanges)
        outer = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.0"

            def log_message(self, *args: Any) -> None:
                pass

            def do_GET(self) -> None:  # noqa: N802
                outer.received.append(self.path)
                if outer._i >= len(outer.exchanges):
                    outer.problems.append(f"unexpected extra request GET {self.path}")
                    self.send_error(599)
                    return
                want, status, body = outer.exchanges[outer._i]
                outer._i += 1
                if urllib.parse.unquote(self.path) != urllib.parse.unquote(want):
                    outer.problems.append(f"request {outer._i}: expected GET {want}, got GET {self.path}")
                data = body.encode() if isinstance(body, str) else body
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

        self._httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self._httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self._httpd.server_address[1]}"
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)

    def _shut_down(self) -> None:
        self._httpd.shutdown()
        self._httpd.server_close()


def fast_sim_rig(reply_timeout_s: float = 0.25, margin_s: float = 0.2, retries: int = 2) -> Rig:
    """The packaged simulated rig with short link timeouts, for tests that inject faults."""
    return load_rig(None).with_links(reply_timeout_s=reply_timeout_s, margin_s=margin_s, retries=retries)
