"""Turntable driver (docs/protocols.md §2): home, move to an angle, position, stop, limits.

Angles are radians here and degrees on the wire.  The rig's soft limits are checked before
anything is sent; the device's own (hardware) limits, speed and settling time are read once with
`LIMITS?` and give every move its timeout."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivers.driver import LineActuator
from drivers.errors import MotionIncomplete, OutOfRange
from drivers.motion import (AxisHardware, AxisStatus, MotionPlan, Progress, link_drops, name_link_loss, read_limits,
                            sent_motion, wait_for_axis, within)
from drivers.wire import parse_fields, parse_float
from lab.core.config import TurntableConfig

ARRIVAL_TOLERANCE_DEG = 0.01


@dataclass(frozen=True)
class TurntableStatus(AxisStatus):   # state IDLE, MOVING, HOMING, FAULT
    angle_rad: float
    target_rad: float
    homed: bool
    motion_states = ("MOVING", "HOMING")


class Turntable(LineActuator[AxisHardware]):
    kind = "turntable"
    ident_prefix, what = "TURNTABLE", "a turntable"
    config: TurntableConfig

    def _read_hardware(self) -> AxisHardware:
        return read_limits(self.name, self.link.request, ("min_deg", "max_deg", "speed_deg_s", "settle_s"),
                           (math.degrees(self.config.min_rad), math.degrees(self.config.max_rad)), "deg",
                           "[turntable] min_deg/max_deg")

    def _report(self, hw: AxisHardware, st: TurntableStatus) -> str:
        return (f"{st.state.lower()}, {'homed' if st.homed else 'NOT homed (HOME before moving)'}, "
                f"at {np.degrees(st.angle_rad):.3f} deg; hardware [{hw.min:g}, {hw.max:g}] deg at "
                f"{hw.speed:g} deg/s; fault {st.fault}")

    # -- queries ------------------------------------------------------------------------------
    def status(self) -> TurntableStatus:
        req = "STATUS?"
        f = parse_fields(self.name, req, self.link.request(req), ("state", "pos_deg", "target_deg", "homed", "fault"))
        return TurntableStatus(
            state=f["state"],
            angle_rad=math.radians(parse_float(self.name, req, f["pos_deg"])),
            target_rad=math.radians(parse_float(self.name, req, f["target_deg"])),
            homed=f["homed"] == "1",
            fault=f["fault"],
        )

    def position(self) -> float:
        """Current angle, rad."""
        return math.radians(parse_float(self.name, "POS?", self.link.request("POS?")))

    @property
    def limits_rad(self) -> tuple[float, float]:
        return self.config.min_rad, self.config.max_rad

    def check_angle(self, angle_rad: float) -> None:
        """Refuse an angle outside the rig's limits (no I/O: usable for --dry-run)."""
        if not within(angle_rad, self.limits_rad):
            lo, hi = self.limits_rad
            raise OutOfRange(self.name, "turntable angle", math.degrees(angle_rad), (math.degrees(lo), math.degrees(hi)),
                             "deg", "rig [turntable] min_deg/max_deg")

    # -- motion -------------------------------------------------------------------------------
    def home(self, progress: Progress | None = None) -> float:
        """Find the index mark; afterwards the angle is 0.  Returns the angle (rad)."""
        hw = self.hardware()
        st = self.status()
        # Before homing the reported angle may be anything: allow a full sweep of the travel.
        distance = abs(math.degrees(st.angle_rad)) if st.homed else hw.max - hw.min
        plan = MotionPlan.of("home", distance, hw.speed, hw.settle_s, self.config.link.margin_s, self.name)
        drops = link_drops(self.link)
        self._command("HOME")
        final = self._wait(plan, 0.0, math.degrees(st.angle_rad), progress)
        if not final.homed:
            raise name_link_loss(MotionIncomplete(self.name, f"homing ended without finding the index (at "
                                                             f"{math.degrees(final.angle_rad):.3f} deg)"),
                                 self.link, drops)
        return final.angle_rad

    def move_to(self, angle_rad: float, progress: Progress | None = None) -> float:
        """Move to an absolute angle (rad) and wait until settled; returns the reached angle."""
        self.check_angle(angle_rad)
        hw = self.hardware()
        start = self.status()
        target_deg = math.degrees(angle_rad)
        start_deg = math.degrees(start.angle_rad)
        plan = MotionPlan.of(f"to {target_deg:.3f} deg", target_deg - start_deg, hw.speed, hw.settle_s,
                             self.config.link.margin_s, self.name)
        drops = link_drops(self.link)
        self._command(f"MOVE {target_deg:.3f}")
        final = self._wait(plan, target_deg, start_deg, progress)
        reached = math.degrees(final.angle_rad)
        if abs(reached - target_deg) > ARRIVAL_TOLERANCE_DEG:
            raise name_link_loss(MotionIncomplete(
                self.name, f"stopped at {reached:.3f} deg, short of the target {target_deg:.3f} deg "
                           f"(state {final.state}, fault {final.fault})"), self.link, drops)
        return final.angle_rad

    def ensure_homed(self, progress: Progress | None = None) -> None:
        if not self.status().homed:
            self.home(progress)

    def _command(self, line: str) -> None:
        sent_motion(self, lambda: self.link.request(line, idempotent=False), self.stop)

    def _wait(self, plan: MotionPlan, target_deg: float, start_deg: float, progress: Progress | None) -> TurntableStatus:
        return wait_for_axis(self.name, plan, self.status, lambda st: math.degrees(st.angle_rad), target_deg, start_deg,
                             "deg", self.stop, progress)
