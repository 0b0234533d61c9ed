"""What a device URL names, whatever its spelling: the keys its ownership lock is taken under
(drivers/ownership.py).

- A serial port (a path, no `://`) is the character device it resolves to: `/dev/ttyUSB0`, its
  `/dev/serial/by-id/...` link and any other node of the same device all give `tty:MAJOR:MINOR`
  (its `st_rdev`); a path that does not exist (yet) is its `os.path.realpath`.
- A network endpoint (`socket://`, `rfc2217://`, `http://`, `https://`) is every address its host
  resolves to (`getaddrinfo`) with the port.  An address of this machine — loopback (all of
  127.0.0.0/8, ::1), the unspecified address, or one bound to a local interface — is `local`:
  `localhost`, `127.1`, `127.0.0.1` and `[::1]` are one device, because a server listening on any
  of them (or on all addresses) is the same server.  (Two servers on one port but different local
  addresses would be taken for one: a refusal too many, never a second owner.)  A name that
  resolves to several remote addresses (IPv4 and IPv6) gets one key per address, so a run that
  spells the device by one of them still meets the other's lock.  A name that does not resolve
  is its lower-case text (nothing can connect to it either).
- Anything else (`loop://`, `spy://`, ...) is its URL text.
"""

from __future__ import annotations

import ipaddress
import os
import socket
import stat
import urllib.parse
from dataclasses import dataclass

NETWORK_SCHEMES = {"socket": None, "rfc2217": None, "http": 80, "https": 443}


@dataclass(frozen=True)
class DeviceIdentity:
    keys: tuple[str, ...]     # lock keys, sorted (one per resolved address for a network name)
    label: str                # what the device is, for messages ("127.0.0.1:27101 on this machine")


def identify(url: str) -> DeviceIdentity:
    if "://" not in url:
        return _serial(url)
    parts = urllib.parse.urlsplit(url)
    scheme = parts.scheme.lower()
    if scheme not in NETWORK_SCHEMES or not parts.hostname:
        return DeviceIdentity((f"url:{url}",), url)
    try:
        port = parts.port or NETWORK_SCHEMES[scheme]
    except ValueError:
        port = None
    if port is None:
        return DeviceIdentity((f"url:{url}",), url)
    return _network(parts.hostname, port)


def _serial(path: str) -> DeviceIdentity:
    real = os.path.realpath(path)
    try:
        st = os.stat(real)
    except OSError:
        return DeviceIdentity((f"serial:{real}",), real)
    if stat.S_ISCHR(st.st_mode):
        major, minor = os.major(st.st_rdev), os.minor(st.st_rdev)
        return DeviceIdentity((f"tty:{major}:{minor}",), f"{real} (character device {major}:{minor})")
    return DeviceIdentity((f"serial:{real}",), real)


def _network(host: str, port: int) -> DeviceIdentity:
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError, OSError):
        name = host.lower()
        return DeviceIdentity((f"tcp:{name}:{port}",), f"{name}:{port} (unresolved)")
    addrs = sorted({_canonical(info[4][0]) for info in infos})
    keys = tuple(f"tcp:{a}:{port}" for a in addrs)
    if addrs == ["local"]:
        return DeviceIdentity(keys, f"port {port} on this machine")
    shown = [f"[{a}]" if ":" in a else a for a in addrs]
    return DeviceIdentity(keys, " / ".join(f"{a}:{port}" for a in shown))


def _canonical(address: str) -> str:
    """`local` for an address of this machine, else the address in its one normal spelling."""
    text, _, zone = address.partition("%")
    ip: ipaddress.IPv4Address | ipaddress.IPv6Address = ipaddress.ip_address(text)
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    if ip.is_loopback or ip.is_unspecified or _is_local(ip):
        return "local"
    return ip.compressed + (f"%{zone}" if zone else "")


def _is_local(ip: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    """Is the address bound to one of this machine's interfaces?  Binding a socket to it succeeds
    only then (no list of interfaces needed, and no packet is sent)."""
    family = socket.AF_INET6 if ip.version == 6 else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            s.bind((str(ip), 0))
        return True
    except OSError:
        return False
