"""Simulated lift controller (docs/protocols.md §3a): a vertical linear stage under the Stewart
base, moving the world's lift axis (metres; millimetres on the wire).

The stage reads an absolute linear encoder, so it needs no homing: power-up position is the
world's (0, where the rig file's Stewart base pose was measured) and `HOME` simply moves back to 0.

Known limitations: constant speed (no ramps); the encoder reads the commanded axis exactly (the
carriage's true position -- the travel's tilt, a fresh repeatability error per move -- is the
world's business, sim_devices/world.py); no brake, no load-dependent speed."""

from __future__ import annotations

from sim_devices.line_server import E_RANGE, LineDevice, Refuse, decimal, nargs
from sim_devices.motion import Axis

MODEL, FIRMWARE = "LAB-LZ1", "1.0"


class LiftSim(LineDevice):
    name = "lift"
    motion_verbs = frozenset({"MOVE", "HOME"})

    def __init__(self, axis: Axis, min_mm: float, max_mm: float, name: str = "lift") -> None:
        super().__init__()
        self.name = name
        self.axis = axis                  # metres
        self.min_mm, self.max_mm = min_mm, max_mm
        self.fault = "none"
        self.commands.update({
            "ID?": self._id, "LIMITS?": self._limits, "HOME": self._home, "MOVE": self._move, "POS?": self._pos,
            "STATUS?": self._status, "STOP": self._stop, "CLEAR": self._clear,
        })

    def is_moving(self) -> bool:
        return self.axis.moving()

    def link_lost(self) -> None:
        self.axis.stop()

    def _mm(self, metres: float) -> float:
        return float(metres) * 1000.0

    # -- commands -------------------------------------------------------------------------------
    def _id(self, args: list[str]) -> str:
        nargs(args, 0, "ID?")
        return f"LIFT {MODEL} {FIRMWARE}"

    def _limits(self, args: list[str]) -> str:
        nargs(args, 0, "LIMITS?")
        return (f"min_mm={self.min_mm:.3f} max_mm={self.max_mm:.3f} speed_mm_s={self.axis.speed * 1000:.3f} "
                f"settle_s={self.axis.settle_s:.3f}")

    def _home(self, args: list[str]) -> str:
        nargs(args, 0, "HOME")
        self._ready()
        self.axis.start(0.0, stuck=self.take_stuck())
        return ""

    def _move(self, args: list[str]) -> str:
        nargs(args, 1, "MOVE <mm>")
        mm = decimal(args[0], "height")
        if not self.min_mm <= mm <= self.max_mm:
            raise Refuse(E_RANGE, f"height {mm:.3f} mm outside [{self.min_mm:.3f}, {self.max_mm:.3f}] mm")
        self._ready()
        self.axis.start(mm / 1000.0, stuck=self.take_stuck())
        return ""

    def _pos(self, args: list[str]) -> str:
        nargs(args, 0, "POS?")
        return f"{self._mm(self.axis.position()):.3f}"

    def _status(self, args: list[str]) -> str:
        nargs(args, 0, "STATUS?")
        state = "FAULT" if self.fault != "none" else ("MOVING" if self.is_moving() else "IDLE")
        return (f"state={state} pos_mm={self._mm(self.axis.position()):.3f} "
                f"target_mm={self._mm(self.axis.target()):.3f} fault={self.fault}")

    def _stop(self, args: list[str]) -> str:
        nargs(args, 0, "STOP")
        self.axis.stop()
        return ""

    def _clear(self, args: list[str]) -> str:
        nargs(args, 0, "CLEAR")
        self.fault = "none"
        return ""
