"""What every driver is, once: a device of a rig that says what kind it is, opens lazily from its
rig record, identifies itself, reads its hardware record once and reports its own check (what
`lab devices check` prints).  `drivers/devices.py` asks these and never switches on the kind.

- `Driver`: every device (the camera too): `kind`, `moves`, `name`, `config`, `check()`, `close()`.
- `Actuator`: a device that moves (IPJRs): the hardware record read once, the `moved` flag a
  clean-up reads, `stop()` / `clear()`.
- `LineActuator`: an actuator on the serial line protocol (turntable, Stewart, lift): opened over a
  `LineTransport`, identified by its `ID?` reply, stopped with `STOP`, cleared with `CLEAR`.

Only the skeleton lives here: each device's protocol (its requests, replies and units) stays in its
own module."""

from __future__ import annotations

from typing import Any, ClassVar, Generic, Self, TypeVar

from drivers.errors import ProtocolError
from drivers.transport import HttpTransport, LineTransport
from lab.core.comms import CommsSink, null_sink

HardwareT = TypeVar("HardwareT")


def line_transport(config: Any, sink: CommsSink) -> LineTransport:
    """The serial line to the device a rig record (`name`, `link`) names."""
    link = config.link
    return LineTransport(config.name, link.url, sink, reply_timeout_s=link.reply_timeout_s, retries=link.retries)


def http_transport(config: Any, sink: CommsSink) -> HttpTransport:
    """The HTTP link to the device a rig record (`name`, `link`) names."""
    link = config.link
    return HttpTransport(config.name, link.url, sink, reply_timeout_s=link.reply_timeout_s, retries=link.retries)


def identify_line(name: str, link: LineTransport, prefix: str, what: str) -> str:
    """`ID?` on the line protocol; a reply not starting with `prefix` is the wrong device."""
    ident = link.request("ID?")
    if not ident.startswith(prefix):
        raise ProtocolError(name, f"ID? says {ident!r}: this is not {what} (check the rig URL)")
    return ident


class Driver:
    """One device of a rig."""

    kind: ClassVar[str]           # the rig's name for this kind of device ("turntable", ...)
    moves: ClassVar[bool] = True  # whether a clean-up must stop it
    name: str
    config: Any

    @classmethod
    def open(cls, config: Any, sink: CommsSink = null_sink) -> Self:
        """The driver for a rig record; lazy: no byte is sent until the first request."""
        raise NotImplementedError

    def identify(self) -> str:
        raise NotImplementedError

    def check(self) -> str:
        """Identify the device, read its limits and state; moves nothing.  The detail line of
        `lab devices check`."""
        raise NotImplementedError

    def stop(self) -> None:
        """Stop any motion (a device that does not move has nothing to stop)."""

    def close(self) -> None:
        raise NotImplementedError


class Actuator(Driver, Generic[HardwareT]):
    """A device that moves: its hardware record (travel, speed, settling) is read once."""

    def __init__(self, config: Any, link: Any) -> None:
        self.config = config
        self.name = config.name
        self.link = link
        self._hw: HardwareT | None = None
        self.moved = False      # a motion command has been sent by this driver (what a clean-up may stop)

    def hardware(self) -> HardwareT:
        """The device's travel, speed and settling time (read once), checked against the rig."""
        if self._hw is None:
            self._hw = self._read_hardware()
        return self._hw

    def _read_hardware(self) -> HardwareT:
        raise NotImplementedError

    def status(self) -> Any:
        raise NotImplementedError

    def check(self) -> str:
        ident = self.identify()
        hw = self.hardware()
        return f"{ident}; {self._report(hw, self.status())}"

    def _report(self, hardware: HardwareT, status: Any) -> str:
        """The check's words for the hardware record and the status just read (and whatever else
        the device reads to report itself)."""
        raise NotImplementedError

    def clear(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        self.link.close()


class LineActuator(Actuator[HardwareT]):
    """An actuator on the serial line protocol (docs/protocols.md §1)."""

    ident_prefix: ClassVar[str]   # what its `ID?` reply starts with ("TURNTABLE")
    what: ClassVar[str]           # what it is, for the wrong-device error ("a turntable")
    link: LineTransport

    @classmethod
    def open(cls, config: Any, sink: CommsSink = null_sink) -> Self:
        return cls(config, line_transport(config, sink))

    def identify(self) -> str:
        return identify_line(self.name, self.link, self.ident_prefix, self.what)

    def stop(self) -> None:
        self.link.request("STOP", idempotent=True)

    def clear(self) -> None:
        self.link.request("CLEAR", idempotent=True)
