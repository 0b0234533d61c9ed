"""Waiting for a motion, the same way for every device: poll until idle, with a deadline from the
physics, and stop the device on every way out that is not success (timeout, link error, Ctrl-C).
Bluesky's invariant, small: whatever happens, what moved is stopped and the error says so.
Also what the single-axis controllers (turntable, lift; the Stewart's legs for `LIMITS?`) share:
their hardware limits read and checked against the rig, and their wait."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, ClassVar, TypeVar

from drivers.errors import (DeviceError, DeviceFault, DeviceTimeout, Disconnected, MotionIncomplete, OutOfRange,
                            ProtocolError, RigMismatch)
from drivers.wire import parse_fields, parse_float

Progress = Callable[[float], None]   # fraction done, 0..1

# No single move of any device we drive takes longer: a plan beyond it is a wrong speed (a rig or
# device reporting 0.001 deg/s) or a wrong distance, and is refused before anything is sent.
MAX_MOVE_S = 900.0


@dataclass(frozen=True)
class MotionPlan:
    """What the physics says about one move: how long it should take and how long we wait."""

    description: str      # "to 90.000 deg"
    expected_s: float     # distance / speed + settle
    timeout_s: float      # 1.5 x travel time + settle + margin

    @staticmethod
    def of(description: str, distance: float, speed: float, settle_s: float, margin_s: float,
           device: str = "") -> MotionPlan:
        travel = abs(distance) / speed if speed > 0 else 0.0
        expected = travel + settle_s
        if not (math.isfinite(expected) and expected <= MAX_MOVE_S):
            raise OutOfRange(device or "device", f"duration of the move {description}", expected, (0.0, MAX_MOVE_S), "s",
                             f"{abs(distance):.6g} at {speed:.6g} per s")
        return MotionPlan(description, expected, 1.5 * travel + settle_s + margin_s)


@dataclass(frozen=True)
class Poll:
    moving: bool
    fraction: float       # 0..1 progress estimate
    where: str            # "at 41.250 deg", for messages


def annotate(exc: BaseException, text: str) -> None:
    """Append to a device error's message (what the CLI prints), or add a note to any other."""
    if isinstance(exc, DeviceError):
        exc.message = f"{exc.message}; {text}"
        exc.args = (f"{exc.device}: {exc.message}",)
    else:
        exc.add_note(text)


def stop_quietly(device: str, stop: Callable[[], None]) -> str:
    """Try to stop; return what happened, in words, for the error message."""
    try:
        stop()
        return "motion stopped"
    except Exception as exc:  # the link may be the very thing that failed
        return f"STOP failed too ({exc}): the device may still be moving"


def send_motion(device: str, send: Callable[[], object], stop: Callable[[], None]) -> None:
    """Send a motion command.  A clean refusal (an error code below 50: syntax, range, not homed,
    busy, fault) moved nothing and is re-raised as is; any other failure (no reply, garbled
    reply, link lost, internal or HTTP 5xx error) leaves the command's fate unknown, so the device
    is stopped first and the error says so."""
    try:
        send()
    except DeviceFault as exc:
        if exc.code < 50:
            raise
        annotate(exc, stop_quietly(device, stop))
        raise
    except BaseException as exc:
        annotate(exc, stop_quietly(device, stop))
        raise


def sent_motion(driver: object, send: Callable[[], object], stop: Callable[[], None]) -> None:
    """`send_motion` that also marks the driver as having moved its device (`driver.moved`), which
    is what a clean-up may stop: a run never stops a device it did not move.  A clean refusal
    (error code below 50) moved nothing and leaves the mark as it was."""
    was = getattr(driver, "moved", False)
    driver.moved = True  # type: ignore[attr-defined]
    try:
        send_motion(getattr(driver, "name", "device"), send, stop)
    except DeviceFault as exc:
        if exc.code < 50:
            driver.moved = was  # type: ignore[attr-defined]
        raise


def link_drops(link: object) -> int:
    return int(getattr(link, "link_drops", 0))


def name_link_loss(exc: MotionIncomplete, link: object, drops_before: int) -> DeviceError:
    """A motion that ended short after the link dropped (and came back) was stopped by the link
    loss: say so, instead of blaming the motion."""
    if link_drops(link) > drops_before:
        return Disconnected(exc.device, f"link to {getattr(link, 'url', '?')} lost during the move ({exc.message}); "
                                        f"the device stops on link loss")
    return exc


def wait_until_idle(device: str, plan: MotionPlan, poll: Callable[[], Poll], stop: Callable[[], None],
                    progress: Progress | None = None) -> Poll:
    """Poll until the device is idle; stop it and raise if that takes longer than the plan allows
    or if anything goes wrong while waiting."""
    interval = min(0.1, max(0.005, plan.expected_s / 20.0))
    deadline = time.monotonic() + plan.timeout_s
    last: Poll | None = None
    try:
        while True:
            last = poll()
            if progress is not None:
                progress(min(1.0, max(0.0, last.fraction)))
            if not last.moving:
                return last
            if time.monotonic() > deadline:
                outcome = stop_quietly(device, stop)
                raise DeviceTimeout(device, f"move {plan.description} not finished within {plan.timeout_s:.3g} s "
                                            f"(expected {plan.expected_s:.3g} s), {last.where}; {outcome}")
            time.sleep(interval)
    except DeviceTimeout as exc:
        if "not finished within" in exc.message:
            raise
        annotate(exc, f"while moving {plan.description}: " + stop_quietly(device, stop))
        raise
    except (DeviceError, KeyboardInterrupt) as exc:
        annotate(exc, f"while moving {plan.description}: " + stop_quietly(device, stop))
        raise


def within(value: float, limits: tuple[float, float]) -> bool:
    """A finite value inside the rig's soft limits (a rounding's worth of slack)."""
    lo, hi = limits
    return math.isfinite(value) and lo - 1e-12 <= value <= hi + 1e-12


@dataclass(frozen=True)
class AxisHardware:
    """A single-axis controller's hardware record, its `LIMITS?` reply in its wire unit (mm, deg):
    travel, speed, settling time."""

    min: float
    max: float
    speed: float          # unit per s
    settle_s: float
    unit: str


def read_limits(device: str, request: Callable[[str], str], keys: tuple[str, str, str, str],
                rig_range: tuple[float, float], unit: str, fix: str, *, rig: str = "rig limits",
                travel: str = "travel") -> AxisHardware:
    """A controller's `LIMITS?` (min, max, speed per s, settle s; wire units, named by `keys`),
    checked against the rig's soft limits `rig_range` (the same units): a rig wider than the
    hardware's travel is a RigMismatch naming the rig keys to `fix`, a speed <= 0 a ProtocolError."""
    req = "LIMITS?"
    f = parse_fields(device, req, request(req), keys)
    lo_hw, hi_hw, speed, settle = (parse_float(device, req, f[k]) for k in keys)
    lo, hi = rig_range
    if lo < lo_hw - 1e-9 or hi > hi_hw + 1e-9:
        raise RigMismatch(device, f"{rig} [{lo:g}, {hi:g}] {unit} exceed the hardware {travel} "
                                  f"[{lo_hw:g}, {hi_hw:g}] {unit}: fix {fix}")
    if speed <= 0:
        raise ProtocolError(device, f"LIMITS? reports speed {speed} {unit}/s")
    return AxisHardware(lo_hw, hi_hw, speed, settle, unit)


@dataclass(frozen=True)
class AxisStatus:
    """A line controller's `STATUS?`: its state (IDLE, MOVING, FAULT, ...) and its fault ("none" or a
    one-word reason); a device's own status adds its position."""

    state: str
    fault: str
    motion_states: ClassVar[tuple[str, ...]] = ("MOVING",)

    @property
    def moving(self) -> bool:
        return self.state in self.motion_states


S = TypeVar("S", bound=AxisStatus)


def wait_for_axis(device: str, plan: MotionPlan, status: Callable[[], S], position: Callable[[S], float],
                  target: float, start: float, unit: str, stop: Callable[[], None],
                  progress: Progress | None = None) -> S:
    """`wait_until_idle` for a single-axis controller (turntable, lift): its STATUS? polled, a
    FAULT state raised as a DeviceFault, progress the share of the way from `start` to `target`
    (`position(status)` in the same wire units); returns the last status."""
    span = abs(target - start) or 1.0
    holder: list[S] = []

    def poll() -> Poll:
        st = status()
        holder.append(st)
        pos = position(st)
        if st.state == "FAULT":
            raise DeviceFault(device, 40, f"fault {st.fault} at {pos:.3f} {unit}", plan.description)
        return Poll(st.moving, 1.0 - abs(target - pos) / span, f"at {pos:.3f} {unit}")

    wait_until_idle(device, plan, poll, stop, progress)
    return holder[-1]
