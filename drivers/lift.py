"""Lift driver (docs/protocols.md §3a): the vertical stage under the Stewart base.

Heights are metres here and millimetres on the wire, 0 being the height at which the rig file's
Stewart base pose was measured.  The rig's soft limits (`[lift] min_m`, `max_m`) are checked
before anything is sent; the device's travel, speed and settling time are read once with
`LIMITS?` (a rig wider than the travel is refused) and give every move its timeout.  The stage has
an absolute encoder: no homing; `home()` moves back to 0."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.driver import LineActuator
from drivers.errors import MotionIncomplete, OutOfRange
from drivers.motion import (AxisHardware, AxisStatus, MotionPlan, Progress, link_drops, name_link_loss, read_limits,
                            sent_motion, wait_for_axis, within)
from drivers.wire import parse_fields, parse_float
from lab.core.config import LiftConfig

ARRIVAL_TOLERANCE_MM = 0.01


@dataclass(frozen=True)
class LiftStatus(AxisStatus):   # state IDLE, MOVING, FAULT
    height_m: float
    target_m: float


class Lift(LineActuator[AxisHardware]):
    kind = "lift"
    ident_prefix, what = "LIFT", "a lift"
    config: LiftConfig

    def _read_hardware(self) -> AxisHardware:
        return read_limits(self.name, self.link.request, ("min_mm", "max_mm", "speed_mm_s", "settle_s"),
                           (self.config.min_m * 1000.0, self.config.max_m * 1000.0), "mm", "[lift] min_m/max_m")

    def _report(self, hw: AxisHardware, st: LiftStatus) -> str:
        return (f"{st.state.lower()}, at {st.height_m * 1000:.3f} mm; hardware [{hw.min:g}, "
                f"{hw.max:g}] mm at {hw.speed:g} mm/s; fault {st.fault}")

    # -- queries ------------------------------------------------------------------------------
    def status(self) -> LiftStatus:
        req = "STATUS?"
        f = parse_fields(self.name, req, self.link.request(req), ("state", "pos_mm", "target_mm", "fault"))
        return LiftStatus(state=f["state"], height_m=parse_float(self.name, req, f["pos_mm"]) / 1000.0,
                          target_m=parse_float(self.name, req, f["target_mm"]) / 1000.0, fault=f["fault"])

    def position(self) -> float:
        """Current height, m."""
        return parse_float(self.name, "POS?", self.link.request("POS?")) / 1000.0

    @property
    def limits_m(self) -> tuple[float, float]:
        return self.config.min_m, self.config.max_m

    def check_height(self, height_m: float) -> None:
        """Refuse a height outside the rig's limits (no I/O: usable for --dry-run)."""
        if not within(height_m, self.limits_m):
            raise OutOfRange(self.name, "lift height", height_m, self.limits_m, "m", "rig [lift] min_m/max_m")

    # -- motion -------------------------------------------------------------------------------
    def move_to(self, height_m: float, progress: Progress | None = None) -> float:
        """Move to an absolute height (m) and wait until settled; returns the reached height."""
        self.check_height(height_m)
        return self._move(f"MOVE {height_m * 1000.0:.3f}", round(height_m * 1000.0, 3), progress)

    def home(self, progress: Progress | None = None) -> float:
        """Back to height 0 (where the rig file's Stewart base pose holds)."""
        return self._move("HOME", 0.0, progress)

    def _move(self, line: str, target_mm: float, progress: Progress | None) -> float:
        hw = self.hardware()
        start_mm = self.status().height_m * 1000.0
        plan = MotionPlan.of(f"to {target_mm:.3f} mm", target_mm - start_mm, hw.speed, hw.settle_s,
                             self.config.link.margin_s, self.name)
        drops = link_drops(self.link)
        sent_motion(self, lambda: self.link.request(line, idempotent=False), self.stop)
        final = wait_for_axis(self.name, plan, self.status, lambda st: st.height_m * 1000.0, target_mm, start_mm,
                              "mm", self.stop, progress)
        reached = final.height_m * 1000.0
        if abs(reached - target_mm) > ARRIVAL_TOLERANCE_MM:
            raise name_link_loss(MotionIncomplete(
                self.name, f"stopped at {reached:.3f} mm, short of the target {target_mm:.3f} mm "
                           f"(state {final.state}, fault {final.fault})"), self.link, drops)
        return reached / 1000.0
