"""Simulated turntable controller (docs/protocols.md §2), moving the world's turntable axis.

Known limitations: constant speed (no ramps); the encoder reads the true angle exactly (no
quantization, no index-mark error); power-up position is the world's initial angle and counts as
un-homed; homing just turns to 0."""

from __future__ import annotations

import math

from sim_devices.controller import AxisController
from sim_devices.line_server import E_NOT_HOMED, Refuse, nargs
from sim_devices.motion import Axis

MODEL, FIRMWARE = "LAB-RT1", "1.0"


class TurntableSim(AxisController):
    unit, what = "deg", "angle"

    def __init__(self, axis: Axis, min_deg: float, max_deg: float, name: str = "turntable") -> None:
        super().__init__(name, axis, f"TURNTABLE {MODEL} {FIRMWARE}", (min_deg, max_deg))   # the axis in radians
        self.homed = False
        self.homing = False

    def to_wire(self, radians: float | object) -> float:
        return math.degrees(float(radians))   # type: ignore[arg-type]

    # -- state ----------------------------------------------------------------------------------
    def is_moving(self) -> bool:
        moving = self.axis.moving()
        if not moving and self.homing:
            self.homing = False
            self.homed = True
        return moving

    def link_lost(self) -> None:
        with self.lock:
            self.stop_motion()

    def stop_motion(self) -> None:
        # A homing run that already ended counts, whether or not anyone asked STATUS? since: a
        # real controller latches its home when the motion ends, not when it is polled.
        self.is_moving()
        self.axis.stop()
        self.homing = False

    def state(self) -> str:
        state = super().state()
        return "HOMING" if state == "MOVING" and self.homing else state

    # -- commands -------------------------------------------------------------------------------
    def _home(self, args: list[str]) -> str:
        nargs(args, 0, "HOME")
        self._ready()
        self.homed = False
        self.homing = True
        self.axis.start(0.0, stuck=self.take_stuck())
        return ""

    def _move_to(self, deg: float) -> str:
        self._ready()
        if not self.homed:
            raise Refuse(E_NOT_HOMED, "not homed: send HOME first")
        self.axis.start(math.radians(deg), stuck=self.take_stuck())
        return ""

    def _status_extra(self) -> str:
        return f"homed={int(self.homed)} "
