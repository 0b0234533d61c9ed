"""Simulated lift controller (docs/protocols.md §3a): a vertical linear stage under the Stewart
base, moving the world's lift axis (metres; millimetres on the wire).

The stage reads an absolute linear encoder, so it needs no homing: power-up position is the
world's (0, where the rig file's Stewart base pose was measured) and `HOME` simply moves back to 0.

Known limitations: constant speed (no ramps); the encoder reads the commanded axis exactly (the
carriage's true position -- the travel's tilt, a fresh repeatability error per move -- is the
world's business, sim_devices/world.py); no brake, no load-dependent speed."""

from __future__ import annotations

from sim_devices.controller import AxisController
from sim_devices.line_server import nargs
from sim_devices.motion import Axis

MODEL, FIRMWARE = "LAB-LZ1", "1.0"


class LiftSim(AxisController):
    unit, what = "mm", "height"

    def __init__(self, axis: Axis, min_mm: float, max_mm: float, name: str = "lift") -> None:
        super().__init__(name, axis, f"LIFT {MODEL} {FIRMWARE}", (min_mm, max_mm))   # the axis in metres

    def to_wire(self, metres: float | object) -> float:
        return float(metres) * 1000.0   # type: ignore[arg-type]

    def _home(self, args: list[str]) -> str:
        nargs(args, 0, "HOME")
        return self._start(0.0)

    def _move_to(self, mm: float) -> str:
        return self._start(mm / 1000.0)
