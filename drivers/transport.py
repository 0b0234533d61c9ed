"""Transports: how a driver's request reaches a device and its reply comes back.

Opened by URL so one driver runs on hardware and in simulation (docs/protocols.md §1, §8):
- `LineTransport`: the ASCII line protocol over anything pyserial's `serial_for_url` opens:
  `/dev/ttyUSB0`, a pseudo-terminal path, `socket://127.0.0.1:PORT`, `loop://`.
- `HttpTransport`: GET requests to `http://HOST:PORT` (the IPJR's Raspberry Pi, camera snapshots).

Both share the base class `Transport`, which owns what no driver may skip:
- one lock per port (shared by every transport object opened on the same URL), held for a whole
  request + reply transaction;
- the comms log: every byte sent (`tx`) and received (`rx`), and every timeout, retry and
  reconnect (`event`), goes to the `CommsSink`;
- bounded retries, for idempotent requests only, with reconnect on a dropped link;
- no value that is not a finite number reaches a device (`nan`, `inf` are refused before sending).

On the serial line every request carries a tag (`#17 POS?`) that the device echoes (`#17 OK 1.0`),
so a late reply to an earlier request that timed out is recognised and discarded, never taken for
the reply to the request in flight (docs/protocols.md §1).
"""

from __future__ import annotations

import hashlib
import http.client
import json
import socket
import threading
import time
import urllib.parse
from dataclasses import dataclass, field
from typing import Any, Callable, TypeVar

import serial

from drivers.errors import DeviceError, DeviceFault, DeviceTimeout, Disconnected, ProtocolError
from lab.core.comms import CommsRecord, CommsSink, null_sink

MAX_LINE = 128            # bytes, docs/protocols.md §1
MAX_TAG = 9999            # request tags run 1..MAX_TAG and wrap
RECONNECT_BACKOFF_S = (0.05, 0.2, 0.5)
_NON_FINITE = {"nan", "+nan", "-nan", "inf", "+inf", "-inf", "infinity", "+infinity", "-infinity"}


def refuse_non_finite(device: str, what: str, tokens: list[str]) -> None:
    """A request carrying `nan` or `inf` is a bug upstream; it never reaches a device."""
    for t in tokens:
        low = t.strip().lower()
        if low in _NON_FINITE:
            raise ValueError(f"{device}: refusing to send {what!r}: {t!r} is not a finite number")

_locks_guard = threading.Lock()
_port_locks: dict[str, threading.RLock] = {}


def port_key(url: str) -> str:
    """The identity of a physical port: an HTTP server is one port whatever the path."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme in ("http", "https"):
        return f"{parts.scheme}://{parts.hostname}:{parts.port or (443 if parts.scheme == 'https' else 80)}"
    return url


def port_lock(url: str) -> threading.RLock:
    key = port_key(url)
    with _locks_guard:
        return _port_locks.setdefault(key, threading.RLock())


T = TypeVar("T")


class Transport:
    """Base of every transport: the lock, the comms log, the retry loop."""

    def __init__(self, device: str, url: str, sink: CommsSink = null_sink, *, reply_timeout_s: float = 0.5,
                 retries: int = 2) -> None:
        self.device = device
        self.url = url
        self.sink = sink
        self.reply_timeout_s = reply_timeout_s
        self.retries = retries
        self.lock = port_lock(url)
        self.link_drops = 0        # times the link was found lost (a motion's clean-up names it)

    # -- the comms log ------------------------------------------------------------------------
    def _log(self, direction: str, data: bytes, note: str = "") -> None:
        try:
            self.sink(CommsRecord(self.device, self.url, direction, bytes(data), time.time(), note))  # type: ignore[arg-type]
        except Exception:  # a broken log must not break the device link; the recorder reports it
            pass

    def event(self, note: str) -> None:
        self._log("event", b"", note)

    # -- retries ------------------------------------------------------------------------------
    def _with_retries(self, what: str, idempotent: bool, once: Callable[[], T]) -> T:
        attempts = 1 + (self.retries if idempotent else 0)
        last: DeviceError | None = None
        for attempt in range(attempts):
            if attempt:
                self.event(f"retry {attempt}/{attempts - 1} of {what!r} after: {last.message if last else ''}")
            try:
                return once()
            except DeviceFault as exc:
                if idempotent and exc.code >= 500 and attempt + 1 < attempts:  # HTTP 5xx: server trouble
                    last = exc
                    continue
                raise
            except (DeviceTimeout, ProtocolError, Disconnected) as exc:
                last = exc
                if isinstance(exc, Disconnected):
                    self.link_drops += 1
                    self.close()
                    if attempt + 1 < attempts:
                        time.sleep(RECONNECT_BACKOFF_S[min(attempt, len(RECONNECT_BACKOFF_S) - 1)])
        assert last is not None
        if attempts > 1:
            raise type(last)(self.device, f"{last.message} (gave up after {attempts} attempts)")
        raise last

    def close(self) -> None:
        """Release the link (it reopens on the next request)."""


# ----------------------------------------------------------------------------------------------
# Serial line protocol


def parse_reply(device: str, request: str, raw: bytes) -> str:
    """`OK[ payload]` -> payload; `ERR <code> <text>` -> DeviceFault; anything else -> ProtocolError."""
    try:
        line = raw.decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError(device, f"reply to {request!r} is not ASCII: {raw!r}") from None
    line = line.rstrip("\n").rstrip("\r")
    if not line.isprintable():
        raise ProtocolError(device, f"reply to {request!r} has control characters: {raw!r}")
    if line == "OK":
        return ""
    if line.startswith("OK "):
        return line[3:]
    if line.startswith("ERR "):
        parts = line.split(" ", 2)
        if len(parts) >= 2 and parts[1].isdigit():
            return _raise_fault(device, int(parts[1]), parts[2] if len(parts) > 2 else "", request)
    raise ProtocolError(device, f"reply to {request!r} is neither OK nor ERR: {raw!r}")


def _raise_fault(device: str, code: int, text: str, request: str) -> str:
    raise DeviceFault(device, code, text, request)


class LineTransport(Transport):
    """One request line -> one reply line, over a pyserial URL."""

    def __init__(self, device: str, url: str, sink: CommsSink = null_sink, *, reply_timeout_s: float = 0.5,
                 retries: int = 2, baudrate: int = 115200) -> None:
        super().__init__(device, url, sink, reply_timeout_s=reply_timeout_s, retries=retries)
        self.baudrate = baudrate
        self._port: serial.SerialBase | None = None

    def open(self) -> None:
        with self.lock:
            if self._port is not None:
                return
            try:
                # a real port (a device path, not a URL) is opened exclusively (flock): a second
                # process cannot talk over this one's requests
                extra = {"exclusive": True} if "://" not in self.url else {}
                self._port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=self.reply_timeout_s,
                                                   write_timeout=self.reply_timeout_s, **extra)
            except (serial.SerialException, OSError, ValueError) as exc:
                self.event(f"open failed: {exc}")
                raise Disconnected(self.device, f"cannot open {self.url}: {_why(exc)}") from None
            self.event("opened")

    def close(self) -> None:
        with self.lock:
            if self._port is not None:
                _close_port(self._port)
                self._port = None
                self.event("closed")

    @property
    def is_open(self) -> bool:
        return self._port is not None

    def __del__(self) -> None:
        port = getattr(self, "_port", None)
        if port is not None:
            _close_port(port)

    def request(self, line: str, *, idempotent: bool | None = None) -> str:
        """Send one request line, return the reply's payload (the text after `OK `).

        `idempotent` defaults to "is a query" (ends in `?`); only idempotent requests are retried."""
        if "\n" in line or "\r" in line:
            raise ValueError(f"a request is one line, got {line!r}")
        if len(line) + len(f"#{MAX_TAG} ") + 1 > MAX_LINE:
            raise ValueError(f"request {line!r} is longer than {MAX_LINE} bytes with its tag")
        refuse_non_finite(self.device, line, line.split()[1:])
        if idempotent is None:
            idempotent = line.endswith("?")
        with self.lock:
            return self._with_retries(line, idempotent, lambda: self._exchange(line))

    _seq = 0

    def _next_tag(self) -> str:
        self._seq = self._seq % MAX_TAG + 1
        return f"#{self._seq}"

    def _exchange(self, line: str) -> str:
        self.open()
        port = self._port
        assert port is not None
        tag = self._next_tag()
        data = f"{tag} {line}\n".encode("ascii")
        deadline = time.monotonic() + self.reply_timeout_s
        try:
            stale = bytearray()
            while port.in_waiting and len(stale) < 4096:
                stale += port.read(port.in_waiting)
            if stale:  # a late reply to an earlier request that timed out: not ours
                self._log("rx", bytes(stale), "stale input discarded")
            self._log("tx", data)
            port.write(data)
            port.flush()
            while True:
                port.timeout = max(0.001, deadline - time.monotonic())
                raw = port.read_until(b"\n", MAX_LINE)
                if not raw.endswith(b"\n"):
                    break
                got, _, rest = raw.partition(b" ")
                if got == tag.encode():
                    break
                if _is_tag(got):  # a reply to an earlier request (it timed out): not this one's
                    self._log("rx", raw, f"stale reply discarded (tag {got.decode()}, expected {tag})")
                    continue
                break  # untagged or garbled: reported below
        except (serial.SerialException, OSError) as exc:
            self.event(f"link lost: {exc}")
            raise Disconnected(self.device, f"connection to {self.url} lost during {line!r}: {_why(exc)}") from None
        finally:
            if self._port is not None:
                try:
                    self._port.timeout = self.reply_timeout_s
                except Exception:
                    pass
        if raw:
            self._log("rx", raw)
        if not raw.endswith(b"\n"):
            if len(raw) >= MAX_LINE:
                raise ProtocolError(self.device, f"reply to {line!r} longer than {MAX_LINE} bytes: {raw[:40]!r}...")
            self.event(f"timeout: no complete reply to {line!r} within {self.reply_timeout_s:g} s")
            got_text = f" (got {raw!r})" if raw else ""
            raise DeviceTimeout(self.device, f"no reply to {line!r} within {self.reply_timeout_s:g} s{got_text}")
        got, _, rest = raw.partition(b" ")
        if got != tag.encode():
            parse_reply(self.device, line, raw)   # garbled bytes are reported as such
            raise ProtocolError(self.device, f"reply to {line!r} does not carry its tag {tag}: {raw!r}")
        return parse_reply(self.device, line, rest)


def _is_tag(token: bytes) -> bool:
    return len(token) >= 2 and token[:1] == b"#" and token[1:].isdigit() and len(token) <= 1 + len(str(MAX_TAG))


def _close_port(port: serial.SerialBase) -> None:
    sock = getattr(port, "_socket", None)
    if isinstance(sock, socket.socket):
        # pyserial's socket:// close() sleeps 0.3 s "in case of quick reconnects"; a reconnect
        # here is already paced by RECONNECT_BACKOFF_S, so close the socket directly.
        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        sock.close()
        port._socket = None  # type: ignore[attr-defined]
        port.is_open = False
        return
    try:
        port.close()
    except Exception:
        pass


def _why(exc: BaseException) -> str:
    text = str(exc)
    if "Connection refused" in text or isinstance(exc, ConnectionRefusedError):
        return "connection refused (nothing answers there: is the device on, or `lab sim` running?)"
    return text or type(exc).__name__


# ----------------------------------------------------------------------------------------------
# HTTP


@dataclass
class HttpReply:
    status: int
    reason: str
    headers: dict[str, str]
    body: bytes
    elapsed_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def json(self, device: str, what: str) -> dict[str, Any]:
        try:
            value = json.loads(self.body.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise ProtocolError(device, f"reply to {what} is not JSON: {self.body[:80]!r}") from None
        if not isinstance(value, dict):
            raise ProtocolError(device, f"reply to {what} is not a JSON object: {value!r}")
        return value


class _LoggedConnection(http.client.HTTPConnection):
    """An HTTPConnection that hands every byte it sends to a callback (the comms log)."""

    def __init__(self, host: str, port: int | None, timeout: float, on_send: Callable[[bytes], None]) -> None:
        super().__init__(host, port, timeout=timeout)
        self._on_send = on_send

    def send(self, data: Any) -> None:  # http.client sends the head (and any body) through here
        self._on_send(bytes(data))
        super().send(data)


_TEXT_TYPES = ("application/json", "text/")


class HttpTransport(Transport):
    """GET requests to one HTTP server; a fresh connection per request (devices close them)."""

    def __init__(self, device: str, url: str, sink: CommsSink = null_sink, *, reply_timeout_s: float = 0.5,
                 retries: int = 2) -> None:
        super().__init__(device, url, sink, reply_timeout_s=reply_timeout_s, retries=retries)
        parts = urllib.parse.urlsplit(url)
        if parts.scheme != "http" or not parts.hostname:
            raise ValueError(f"{device}: expected an http://HOST:PORT URL, got {url!r}")
        self.host = parts.hostname
        self.port = parts.port or 80
        self.base_path = parts.path.rstrip("/")

    def get(self, path: str, params: dict[str, Any] | None = None, *, idempotent: bool,
            timeout_s: float | None = None, check: Callable[[HttpReply], None] | None = None) -> HttpReply:
        """One GET; a 5xx is raised as DeviceFault (code = HTTP status) and retried if idempotent.
        Other statuses are returned for the caller to interpret.  `check` (raising ProtocolError)
        runs inside the retry loop."""
        target = self._target(path, params)

        def once() -> HttpReply:
            reply = self._exchange(target, timeout_s or self.reply_timeout_s)
            if check is not None:
                check(reply)
            return reply

        with self.lock:
            return self._with_retries(f"GET {target}", idempotent, once)

    def _target(self, path: str, params: dict[str, Any] | None) -> str:
        target = (self.base_path + path) if path.startswith("/") else f"{self.base_path}/{path}"
        if params:
            refuse_non_finite(self.device, f"GET {path}", [str(v) for v in params.values()])
            target += "?" + urllib.parse.urlencode(params)
        return target

    def get_json(self, path: str, params: dict[str, Any] | None = None, *, idempotent: bool,
                 timeout_s: float | None = None,
                 check: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
        """A GET whose 200 reply is a JSON object; an error status becomes DeviceFault with the
        device's error code and text (docs/protocols.md §5).  The reply is parsed and `check`ed
        (raising ProtocolError) inside the retry loop, so a garbled reply to a query is retried
        like a lost one."""
        target = self._target(path, params)
        what = f"GET {path}" + (f"?{urllib.parse.urlencode(params)}" if params else "")

        def once() -> dict[str, Any]:
            reply = self._exchange(target, timeout_s or self.reply_timeout_s)
            value = self._json_of(reply, what)
            if check is not None:
                check(value)
            return value

        with self.lock:
            return self._with_retries(f"GET {target}", idempotent, once)

    def _json_of(self, reply: HttpReply, what: str) -> dict[str, Any]:
        if reply.status == 200:
            return reply.json(self.device, what)
        code, text = reply.status, reply.reason
        try:
            err = json.loads(reply.body.decode("utf-8")).get("error", {})
            code, text = int(err.get("code", code)), str(err.get("text", text))
        except (ValueError, AttributeError, UnicodeDecodeError):
            pass
        raise DeviceFault(self.device, code, f"{text} (HTTP {reply.status})", what)

    def _exchange(self, target: str, timeout_s: float) -> HttpReply:
        conn = _LoggedConnection(self.host, self.port, timeout_s, lambda b: self._log("tx", b))
        t0 = time.monotonic()
        try:
            conn.putrequest("GET", target, skip_accept_encoding=True)
            conn.putheader("Accept", "application/json, image/png, */*")
            conn.putheader("Connection", "close")
            conn.endheaders()
            resp = conn.getresponse()
            body = resp.read()
        except (socket.timeout, TimeoutError):
            self.event(f"timeout: no reply to GET {target} within {timeout_s:g} s")
            raise DeviceTimeout(self.device, f"no reply to GET {target} within {timeout_s:g} s") from None
        except ConnectionRefusedError as exc:
            self.event(f"connect failed: {exc}")
            raise Disconnected(self.device, f"cannot connect to {self.url}: {_why(exc)}") from None
        except (http.client.RemoteDisconnected, http.client.IncompleteRead, ConnectionError, OSError) as exc:
            self.event(f"link lost: {exc!r}")
            raise Disconnected(self.device, f"connection to {self.url} lost during GET {target}: "
                                            f"{exc or type(exc).__name__}") from None
        except http.client.HTTPException as exc:
            self.event(f"bad HTTP reply: {exc!r}")
            raise ProtocolError(self.device, f"reply to GET {target} is not valid HTTP: {exc!r}") from None
        finally:
            conn.close()
        headers = {k: v for k, v in resp.getheaders()}
        head = f"HTTP/{resp.version / 10:.1f} {resp.status} {resp.reason}\r\n" + "".join(
            f"{k}: {v}\r\n" for k, v in resp.getheaders()) + "\r\n"
        ctype = headers.get("Content-Type", "")
        if ctype.startswith(_TEXT_TYPES) or not body:
            self._log("rx", head.encode("latin-1") + body)
        else:
            digest = hashlib.sha256(body).hexdigest()
            self._log("rx", head.encode("latin-1"), f"body: {len(body)} bytes {ctype} sha256={digest}")
        reply = HttpReply(resp.status, resp.reason, headers, body, time.monotonic() - t0)
        if reply.status >= 500:
            text = reply.reason
            try:
                text = json.loads(body.decode("utf-8"))["error"]["text"]
            except Exception:
                pass
            raise DeviceFault(self.device, reply.status, f"{text} (HTTP {reply.status})", f"GET {target}")
        return reply


def open_transport(device: str, url: str, sink: CommsSink = null_sink, *, reply_timeout_s: float = 0.5,
                   retries: int = 2) -> Transport:
    """A transport for a URL: `http://...` -> HttpTransport, anything else -> LineTransport."""
    if url.startswith("http://") or url.startswith("https://"):
        return HttpTransport(device, url, sink, reply_timeout_s=reply_timeout_s, retries=retries)
    return LineTransport(device, url, sink, reply_timeout_s=reply_timeout_s, retries=retries)
