"""All the bench's devices from a rig file: `connect(rig, sink) -> Devices`, and `check(rig)`
(what `lab devices check` prints)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Generic, Iterable, TypeVar

from drivers.camera import Camera
from drivers.driver import Driver
from drivers.errors import DeviceError
from drivers.ipjr import Ipjr
from drivers.lift import Lift
from drivers.ownership import Claims
from drivers.stewart import Stewart
from drivers.turntable import Turntable
from lab.core.comms import CommsSink, null_sink
from lab.core.config import Rig
from lab.core.errors import LabError


# every kind of driver, by the kind the rig file names it (each driver says its own)
DRIVERS: dict[str, type[Driver]] = {d.kind: d for d in (Turntable, Stewart, Lift, Camera, Ipjr)}


D = TypeVar("D", bound=Driver)


class _OfKind(Generic[D]):
    """`Devices.turntable` and the like: the rig's open driver of that class, or None."""

    def __init__(self, cls: type[D]) -> None:
        self.cls = cls

    def __get__(self, devices: Any, owner: type) -> D | None:
        return next((d for d in devices.drivers.values() if isinstance(d, self.cls)), None)


class Devices:
    """The open drivers of one rig.  A context manager: on exit every device that can move is
    stopped if the block raised, and every link is closed."""

    def __init__(self, rig: Rig, claims: Claims | None = None) -> None:
        self.rig = rig
        self.claims = claims if claims is not None else Claims()   # this process owns these devices until close()
        self.drivers: dict[str, Driver] = {}                        # by name, in the rig's device order

    def add(self, driver: Driver) -> None:
        self.drivers[driver.name] = driver

    turntable = _OfKind(Turntable)
    stewart = _OfKind(Stewart)
    lift = _OfKind(Lift)
    camera = _OfKind(Camera)

    @property
    def ipjrs(self) -> dict[str, Ipjr]:
        return {n: d for n, d in self.drivers.items() if isinstance(d, Ipjr)}

    def all(self) -> list[tuple[str, Any]]:
        """In the rig's device order (Rig.devices)."""
        return list(self.drivers.items())

    def __getitem__(self, name: str) -> Any:
        if name in self.drivers:
            return self.drivers[name]
        raise KeyError(f"no device named {name!r} in rig {self.rig.name!r}")

    def stop_all(self) -> dict[str, str]:
        """Stop every device that can move (best effort, each independently); what happened, by name."""
        outcome: dict[str, str] = {}
        for name, dev in self.all():
            if not dev.moves:
                continue
            try:
                dev.stop()
                outcome[name] = "stopped"
            except Exception as exc:
                outcome[name] = f"STOP failed: {exc}"
        return outcome

    def close(self) -> None:
        try:
            for _, dev in self.all():
                try:
                    dev.close()
                except Exception:
                    pass
        finally:
            self.claims.release_all()

    def __enter__(self) -> Devices:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is not None:
                self.stop_all()
        finally:
            self.close()


def connect(rig: Rig, sink: CommsSink = null_sink, only: Iterable[str] | None = None, *, claim: bool = True) -> Devices:
    """Driver objects for the rig's devices (all, or the names in `only`).  Opening is lazy: no
    byte is sent until the first request, so this cannot fail on an unplugged device.

    Every device is claimed first (drivers/ownership.py): if another process owns one, this raises
    `DeviceBusy` naming it and its holder, having sent nothing to any device."""
    wanted = set(only) if only is not None else None
    unknown = (wanted or set()) - {n for n, _, _ in rig.devices()}
    if unknown:
        raise KeyError(f"no device named {sorted(unknown)} in rig {rig.name!r}")

    def want(name: str) -> bool:
        return wanted is None or name in wanted

    devs = Devices(rig)
    if claim:
        try:
            for name, _, url in rig.devices():
                if want(name):
                    devs.claims.take(name, url)
        except BaseException:
            devs.claims.release_all()
            raise
    try:
        for kind, cfg in rig.device_configs():
            if want(cfg.name):
                devs.add(DRIVERS[kind].open(cfg, sink))
    except BaseException:
        # a driver refused its configuration (a camera calibration that cannot be read): the
        # drivers opened so far are closed and every claim goes with them, or this process would
        # own the devices until it exits
        devs.close()
        raise
    return devs


@dataclass(frozen=True)
class DeviceReport:
    name: str
    kind: str
    url: str
    ok: bool
    detail: str

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "url": self.url, "ok": self.ok, "detail": self.detail}


def check(rig: Rig, sink: CommsSink = null_sink) -> list[DeviceReport]:
    """Connect to every device of the rig and read its state (moves nothing)."""
    reports = []
    with connect(rig, sink) as devs:
        for (name, kind, url), (_, dev) in zip(rig.devices(), devs.all()):
            try:
                reports.append(DeviceReport(name, kind, url, True, dev.check()))
            except (LabError, OSError, ValueError) as exc:
                msg = exc.message if isinstance(exc, DeviceError) else str(exc)
                reports.append(DeviceReport(name, kind, url, False, msg))
    return reports
