"""All the bench's devices from a rig file: `connect(rig, sink) -> Devices`, and `check(rig)`
(what `lab devices check` prints)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Iterable

import numpy as np

from drivers.camera import Camera
from drivers.errors import DeviceError
from drivers.ipjr import Ipjr
from drivers.lift import Lift
from drivers.ownership import Claims
from drivers.stewart import Stewart
from drivers.turntable import Turntable
from lab.core.comms import CommsSink, null_sink
from lab.core.config import Rig
from lab.core.errors import LabError
from lab.core.geometry import to_xyzrpy


@dataclass
class Devices:
    """The open drivers of one rig.  A context manager: on exit every device that can move is
    stopped if the block raised, and every link is closed."""

    rig: Rig
    turntable: Turntable | None = None
    stewart: Stewart | None = None
    camera: Camera | None = None
    ipjrs: dict[str, Ipjr] = field(default_factory=dict)
    claims: Claims = field(default_factory=Claims)   # this process owns these devices until close()
    lift: Lift | None = None

    def all(self) -> list[tuple[str, Any]]:
        """In the rig's device order (Rig.devices)."""
        out: list[tuple[str, Any]] = []
        for dev in (self.turntable, self.stewart, self.lift, self.camera):
            if dev is not None:
                out.append((dev.name, dev))
        out.extend(self.ipjrs.items())
        return out

    def __getitem__(self, name: str) -> Any:
        for n, dev in self.all():
            if n == name:
                return dev
        raise KeyError(f"no device named {name!r} in rig {self.rig.name!r}")

    def stop_all(self) -> dict[str, str]:
        """Stop every device that can move (best effort, each independently); what happened, by name."""
        outcome: dict[str, str] = {}
        for name, dev in self.all():
            if dev.kind == "camera":
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
    if rig.turntable and want(rig.turntable.name):
        devs.turntable = Turntable.open(rig.turntable, sink)
    if rig.stewart and want(rig.stewart.name):
        devs.stewart = Stewart.open(rig.stewart, sink)
    if rig.lift and want(rig.lift.name):
        devs.lift = Lift.open(rig.lift, sink)
    if rig.camera and want(rig.camera.name):
        devs.camera = Camera.open(rig.camera, sink)
    for name, cfg in rig.ipjrs.items():
        if want(name):
            devs.ipjrs[name] = Ipjr.open(cfg, sink)
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


def _check_one(dev: Any) -> str:
    """Identify the device, read its limits and state; moves nothing.  Returns the detail line."""
    if dev.kind == "turntable":
        ident = dev.identify()
        hw = dev.hardware()
        st = dev.status()
        return (f"{ident}; {st.state.lower()}, {'homed' if st.homed else 'NOT homed (HOME before moving)'}, "
                f"at {np.degrees(st.angle_rad):.3f} deg; hardware [{hw.min_deg:g}, {hw.max_deg:g}] deg at "
                f"{hw.speed_deg_s:g} deg/s; fault {st.fault}")
    if dev.kind == "stewart":
        ident = dev.identify()
        hw = dev.hardware()
        st = dev.status()
        pose = np.round(to_xyzrpy(dev.pose()), 6) + 0.0  # no '-0.0000'
        return (f"{ident}; {st.state.lower()}; platform at x {pose[0]:+.4f} y {pose[1]:+.4f} z {pose[2]:+.4f} m, "
                f"roll {np.degrees(pose[3]):+.2f} pitch {np.degrees(pose[4]):+.2f} yaw {np.degrees(pose[5]):+.2f} deg "
                f"from home; legs [{hw.min_mm:g}, {hw.max_mm:g}] mm at {hw.speed_mm_s:g} mm/s; fault {st.fault}")
    if dev.kind == "lift":
        ident = dev.identify()
        hw = dev.hardware()
        st = dev.status()
        return (f"{ident}; {st.state.lower()}, at {st.height_m * 1000:.3f} mm; hardware [{hw.min_mm:g}, "
                f"{hw.max_mm:g}] mm at {hw.speed_mm_s:g} mm/s; fault {st.fault}")
    if dev.kind == "camera":
        ident = dev.identify()
        t0 = time.monotonic()
        frame = dev.grab()
        ms = (time.monotonic() - t0) * 1000
        cal = (f"calibration {dev.config.calibration.name} ({dev.intrinsics.hfov_deg:.1f} deg HFOV)"
               if dev.intrinsics else "NO calibration file (set [camera] calibration)")
        return f"{ident}; frame {frame.image.shape[1]}x{frame.image.shape[0]} in {ms:.0f} ms; {cal}"
    if dev.kind == "ipjr":
        ident = dev.identify()
        hw = dev.hardware()
        st = dev.status()
        v = dev.volts()
        return (f"{ident}; {st['state']}; potentiometer {v:.3f} V = extension {dev.extension_from_volts(v) * 1000:.2f} mm "
                f"of {hw.stroke_mm:g} mm; step {hw.step_mm:g} mm; fault {st['fault']}")
    raise ValueError(f"unknown device kind {dev.kind!r}")


def check(rig: Rig, sink: CommsSink = null_sink) -> list[DeviceReport]:
    """Connect to every device of the rig and read its state (moves nothing)."""
    reports = []
    with connect(rig, sink) as devs:
        for (name, kind, url), (_, dev) in zip(rig.devices(), devs.all()):
            try:
                reports.append(DeviceReport(name, kind, url, True, _check_one(dev)))
            except (LabError, OSError, ValueError) as exc:
                msg = exc.message if isinstance(exc, DeviceError) else str(exc)
                reports.append(DeviceReport(name, kind, url, False, msg))
    return reports
