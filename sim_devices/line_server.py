"""The device side of the serial line protocol (docs/protocols.md §1), served on a loopback TCP
socket (`socket://127.0.0.1:PORT`, what pyserial's `serial_for_url` opens) and optionally on a
pseudo-terminal (a real tty path a serial terminal such as picocom or miniterm can open).

`LineDevice` parses request lines and dispatches verbs; a device simulator subclasses it and
registers its commands.  `LineServer` moves bytes: it splits lines, applies injected faults,
and writes replies.  Several TCP clients may connect at once (unlike a real serial port); they
share the one device.

Host loss (docs/protocols.md §1, sim_devices/watchdog.py): a motion belongs to the link that
commanded it (a TCP connection, or the pty).  When that link closes — the client closed or reset
its socket, or every holder of the pty closed it (the kernel reports a hang-up) — the device stops
at once; while the device moves, that link's requests feed the watchdog, which stops the device if
they cease for longer than `Firmware.watchdog_s`.  Other clients (a person at a terminal checking
`STATUS?`) neither keep a motion alive nor stop it by leaving.  `Firmware` can take either
behaviour away (an older firmware).

Known limitations: a pseudo-terminal cannot be unplugged by the server, so on a pty the `disconnect`
fault stops the device (if its firmware stops on link loss) and swallows the request (like
`timeout`) instead of closing the link."""

from __future__ import annotations

import errno
import os
import re
import select
import socket
import threading
import tty
from typing import Callable

from sim_devices.faults import FaultInjector
from sim_devices.watchdog import Firmware, Watchdog

MAX_LINE = 128
MAX_CLIENTS = 8          # TCP clients at once (a serial port has one); more are closed at once

E_UNKNOWN, E_SYNTAX, E_TOO_LONG, E_RANGE, E_NOT_HOMED, E_BUSY, E_FAULT, E_INTERNAL = 10, 11, 12, 20, 30, 31, 40, 50

_TAGGED = re.compile(r"^(#\d{1,4}) (.*)$")   # `#17 POS?`: the reply echoes the tag (docs/protocols.md §1)
_DECIMAL = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)$")
_INTEGER = re.compile(r"^[+-]?\d+$")


class Refuse(Exception):
    """A request the device answers with `ERR <code> <text>`."""

    def __init__(self, code: int, text: str) -> None:
        super().__init__(text)
        self.code = code
        self.text = text


def decimal(token: str, what: str) -> float:
    if not _DECIMAL.match(token):
        raise Refuse(E_SYNTAX, f"{what} {token!r} is not a decimal number")
    return float(token)


def integer(token: str, what: str) -> int:
    if not _INTEGER.match(token):
        raise Refuse(E_SYNTAX, f"{what} {token!r} is not an integer")
    return int(token)


def nargs(args: list[str], n: int, usage: str) -> None:
    if len(args) != n:
        raise Refuse(E_SYNTAX, f"expected {n} argument{'s' if n != 1 else ''}: {usage}")


class LineDevice:
    """Verb dispatch: subclasses fill `self.commands` with VERB -> handler(args) -> payload."""

    name = "device"
    motion_verbs: frozenset[str] = frozenset()

    def __init__(self) -> None:
        self.commands: dict[str, Callable[[list[str]], str]] = {}
        self.lock = threading.RLock()

    def is_moving(self) -> bool:
        return False

    def _ready(self) -> None:
        """Refuse a motion command while a fault is latched or a motion is in progress (the
        firmware rule of every serial device in docs/protocols.md); devices without faults pass."""
        fault = getattr(self, "fault", "none")
        if fault != "none":
            raise Refuse(E_FAULT, f"fault {fault} latched: send CLEAR after finding the cause")
        if self.is_moving():
            raise Refuse(E_BUSY, "busy: a motion is in progress (send STOP first)")

    def link_lost(self) -> None:
        """The host connection dropped: stop (our firmware treats it as an emergency stop)."""

    def is_motion(self, line: str) -> bool:
        parts = line.split()
        return bool(parts) and parts[0].upper() in self.motion_verbs

    def handle(self, line: str, stuck: bool = False) -> str:
        """One request line (no terminator) -> one reply line (no terminator)."""
        parts = line.split()
        verb, args = parts[0].upper(), parts[1:]
        fn = self.commands.get(verb)
        if fn is None:
            return f"ERR {E_UNKNOWN} unknown command {parts[0]!r} (try ID?, STATUS?, LIMITS?)"
        try:
            with self.lock:
                self._stuck_next = stuck
                payload = fn(args)
        except Refuse as r:
            return f"ERR {r.code} {r.text}"
        except Exception as exc:  # a simulator bug must still produce one reply line
            return f"ERR {E_INTERNAL} internal error: {type(exc).__name__}: {exc}".replace("\n", " ")
        return "OK" if payload == "" else f"OK {payload}"

    _stuck_next = False

    def take_stuck(self) -> bool:
        """For motion handlers: should this motion be stuck (an injected fault)?"""
        s, self._stuck_next = self._stuck_next, False
        return s


DISCONNECT = object()
PTY = "pty"          # the pseudo-terminal's link (TCP links are their sockets)


class LineServer:
    def __init__(self, device: LineDevice, faults: FaultInjector, host: str = "127.0.0.1", port: int = 0,
                 pty: bool = False, firmware: Firmware = Firmware()) -> None:
        self.device = device
        self.faults = faults
        self.firmware = firmware
        self.watchdog = Watchdog(device.name, firmware.watchdog_s, self._moving, self._emergency_stop)
        self._host: object | None = None     # the link that commanded the motion under way
        self._host_lock = threading.Lock()
        self.link_losses = 0                 # motions stopped because their link closed (tests)
        self._stop = threading.Event()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._sock.bind((host, port))
        except OSError as exc:
            self._sock.close()
            raise OSError(exc.errno, f"{device.name}: cannot listen on {host}:{port}: {exc.strerror} "
                                     f"(is another `lab sim` running?)") from None
        self._sock.listen(8)
        self._sock.settimeout(0.05)
        self.host, self.port = self._sock.getsockname()[:2]
        self._clients: set[socket.socket] = set()
        self._threads: list[threading.Thread] = []
        self.pty_path: str | None = None
        self._pty_fds: tuple[int, int] | None = None
        if pty:
            master, slave = os.openpty()
            tty.setraw(slave)          # no echo, no line editing: bytes as a serial port delivers them
            self.pty_path = os.ttyname(slave)
            # the server keeps only the master: with no slave descriptor of its own, the kernel
            # reports a hang-up on the master when the host closes the port (or dies)
            os.close(slave)
            self._pty_fds = (master,)

    @property
    def url(self) -> str:
        return f"socket://{self.host}:{self.port}"

    def start(self) -> LineServer:
        self.watchdog.start()
        self._spawn(self._accept_loop, f"{self.device.name}-accept")
        if self._pty_fds:
            self._spawn(self._pty_loop, f"{self.device.name}-pty")
        return self

    def _spawn(self, fn: Callable[..., None], name: str, *args: object) -> None:
        t = threading.Thread(target=fn, args=args, name=name, daemon=True)
        t.start()
        self._threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        self.watchdog.stop()
        try:
            self._sock.close()
        except OSError:
            pass
        for c in list(self._clients):
            _close(c)
        for t in self._threads:
            t.join(timeout=1.0)
        if self._pty_fds:
            for fd in self._pty_fds:
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._pty_fds = None

    def kick_clients(self) -> None:
        """Drop every TCP connection (tests: a cable pulled between moves)."""
        for c in list(self._clients):
            _close(c)

    # -- host loss -------------------------------------------------------------------------------
    def _moving(self) -> bool:
        return self.device.is_moving()

    def _emergency_stop(self) -> None:
        with self._host_lock:
            self._host = None
        self.device.link_lost()

    def _heard(self, link: object) -> None:
        """A request arrived on `link`: the motion's link (or any, with no motion owned) feeds the
        watchdog."""
        with self._host_lock:
            mine = self._host is None or self._host is link
        if mine:
            self.watchdog.feed()

    def _commanded(self, link: object) -> None:
        """`link` started a motion (the device accepted it): the motion is that link's."""
        with self._host_lock:
            self._host = link
        self.watchdog.feed()

    def _link_closed(self, link: object) -> None:
        """`link` closed: if it commanded the motion under way, the host is gone: stop."""
        with self._host_lock:
            if self._host is not link:
                return
            self._host = None
        if self.firmware.stop_on_link_loss and self.device.is_moving():
            self.device.link_lost()
            self.link_losses += 1

    # -- request handling, shared by socket and pty ---------------------------------------------
    def respond(self, raw: bytes, link: object = None) -> bytes | None | object:
        """One received line (terminator stripped) -> reply bytes, None (no reply), or DISCONNECT."""
        self._heard(link)
        if len(raw) + 1 > MAX_LINE:
            return f"ERR {E_TOO_LONG} request longer than {MAX_LINE} bytes\n".encode()
        text = raw.decode("ascii", errors="replace").rstrip("\r")
        tag = ""
        m = _TAGGED.match(text)
        if m:
            tag, text = m.group(1) + " ", m.group(2)
        if not text.strip():
            return None
        motion = self.device.is_motion(text)
        fault = self.faults.on_request(text, self.device.is_moving(), motion)
        if fault == "timeout":
            return None
        if fault == "disconnect":
            if self.firmware.stop_on_link_loss:
                self.device.link_lost()
            return DISCONNECT
        answer = self.device.handle(text, stuck=(fault == "stuck"))
        if motion and answer.startswith("OK"):
            self._commanded(link)
        reply = (tag + answer + "\n").encode("ascii", errors="replace")
        if fault == "garbled":
            return self.faults.garble(reply)
        return reply

    def _lines(self, buf: bytearray, chunk: bytes, overflow: list[bool]) -> list[bytes | None]:
        """Split received bytes into lines; an over-long line yields None (-> ERR 12) once."""
        out: list[bytes | None] = []
        buf.extend(chunk)
        while True:
            i = buf.find(b"\n")
            if i < 0:
                if len(buf) >= MAX_LINE:
                    overflow[0] = True
                    buf.clear()
                return out
            line = bytes(buf[:i])
            del buf[: i + 1]
            if overflow[0]:
                overflow[0] = False
                out.append(None)
            else:
                out.append(line)

    def _reply_for(self, line: bytes | None, link: object) -> bytes | None | object:
        if line is None:
            self._heard(link)
            return f"ERR {E_TOO_LONG} request longer than {MAX_LINE} bytes\n".encode()
        return self.respond(line, link)

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            if len(self._clients) >= MAX_CLIENTS:
                _close(conn)
                continue
            conn.settimeout(0.05)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._clients.add(conn)
            self._spawn(self._client_loop, f"{self.device.name}-client", conn)

    def _client_loop(self, conn: socket.socket) -> None:
        buf, overflow = bytearray(), [False]
        try:
            while not self._stop.is_set():
                try:
                    chunk = conn.recv(4096)
                except socket.timeout:
                    continue
                except OSError:
                    break
                if not chunk:
                    break
                for line in self._lines(buf, chunk, overflow):
                    reply = self._reply_for(line, conn)
                    if reply is DISCONNECT:
                        return
                    if reply:
                        conn.sendall(reply)  # type: ignore[arg-type]
        except OSError:
            pass
        finally:
            self._clients.discard(conn)
            _close(conn)
            self._link_closed(conn)

    def _pty_loop(self) -> None:
        """Serve the pty.  With no host holding the port open the master reports a hang-up
        (POLLHUP) at every poll; a poll that times out means a host has it open."""
        assert self._pty_fds is not None
        master = self._pty_fds[0]
        poller = select.poll()
        poller.register(master, select.POLLIN)
        buf, overflow = bytearray(), [False]
        held = False          # a host has the port open
        while not self._stop.is_set():
            try:
                events = poller.poll(50)
            except (OSError, ValueError):
                return
            if not events:
                held = True
                continue
            ev = events[0][1]
            if ev & select.POLLNVAL:
                return
            chunk = b""
            if ev & select.POLLIN:
                try:
                    chunk = os.read(master, 4096)
                except OSError as exc:
                    if exc.errno != errno.EIO:      # EIO: the host side is closed
                        return
            if chunk:
                held = True
                for line in self._lines(buf, chunk, overflow):
                    reply = self._reply_for(line, PTY)
                    if reply is DISCONNECT or not reply:
                        continue
                    try:
                        os.write(master, reply)  # type: ignore[arg-type]
                    except OSError:
                        pass   # the host closed the port meanwhile: the hang-up is handled below
                continue
            if ev & (select.POLLHUP | select.POLLERR):
                if held:
                    held = False
                    buf.clear()
                    self._link_closed(PTY)
                self._stop.wait(0.02)


def _close(conn: socket.socket) -> None:
    try:
        conn.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        conn.close()
    except OSError:
        pass
