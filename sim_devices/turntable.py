"""Simulated turntable controller (docs/protocols.md §2), moving the world's turntable axis.

Known limitations: constant speed (no ramps); the encoder reads the true angle exactly (no
quantization, no index-mark error); power-up position is the world's initial angle and counts as
un-homed; homing just turns to 0."""

from __future__ import annotations

import math

from sim_devices.line_server import (E_NOT_HOMED, E_RANGE, LineDevice, Refuse, decimal, nargs)
from sim_devices.motion import Axis

MODEL, FIRMWARE = "LAB-RT1", "1.0"


class TurntableSim(LineDevice):
    name = "turntable"
    motion_verbs = frozenset({"MOVE", "HOME"})

    def __init__(self, axis: Axis, min_deg: float, max_deg: float, name: str = "turntable") -> None:
        super().__init__()
        self.name = name
        self.axis = axis                  # radians
        self.min_deg, self.max_deg = min_deg, max_deg
        self.homed = False
        self.homing = False
        self.fault = "none"
        self.commands.update({
            "ID?": self._id, "LIMITS?": self._limits, "HOME": self._home, "MOVE": self._move, "POS?": self._pos,
            "STATUS?": self._status, "STOP": self._stop, "CLEAR": self._clear,
        })

    # -- state ----------------------------------------------------------------------------------
    def is_moving(self) -> bool:
        moving = self.axis.moving()
        if not moving and self.homing:
            self.homing = False
            self.homed = True
        return moving

    def link_lost(self) -> None:
        with self.lock:
            self.axis.stop()
            self.homing = False

    def _deg(self) -> float:
        return math.degrees(float(self.axis.position()))

    def _state(self) -> str:
        if self.fault != "none":
            return "FAULT"
        if self.is_moving():
            return "HOMING" if self.homing else "MOVING"
        return "IDLE"

    # -- commands -------------------------------------------------------------------------------
    def _id(self, args: list[str]) -> str:
        nargs(args, 0, "ID?")
        return f"TURNTABLE {MODEL} {FIRMWARE}"

    def _limits(self, args: list[str]) -> str:
        nargs(args, 0, "LIMITS?")
        return (f"min_deg={self.min_deg:.3f} max_deg={self.max_deg:.3f} "
                f"speed_deg_s={math.degrees(self.axis.speed):.3f} settle_s={self.axis.settle_s:.3f}")

    def _home(self, args: list[str]) -> str:
        nargs(args, 0, "HOME")
        self._ready()
        self.homed = False
        self.homing = True
        self.axis.start(0.0, stuck=self.take_stuck())
        return ""

    def _move(self, args: list[str]) -> str:
        nargs(args, 1, "MOVE <deg>")
        deg = decimal(args[0], "angle")
        if not self.min_deg <= deg <= self.max_deg:
            raise Refuse(E_RANGE, f"angle {deg:.3f} deg outside [{self.min_deg:.3f}, {self.max_deg:.3f}] deg")
        self._ready()
        if not self.homed:
            raise Refuse(E_NOT_HOMED, "not homed: send HOME first")
        self.axis.start(math.radians(deg), stuck=self.take_stuck())
        return ""

    def _pos(self, args: list[str]) -> str:
        nargs(args, 0, "POS?")
        return f"{self._deg():.3f}"

    def _status(self, args: list[str]) -> str:
        nargs(args, 0, "STATUS?")
        state = self._state()
        return (f"state={state} pos_deg={self._deg():.3f} target_deg={math.degrees(float(self.axis.target())):.3f} "
                f"homed={int(self.homed)} fault={self.fault}")

    def _stop(self, args: list[str]) -> str:
        nargs(args, 0, "STOP")
        self.axis.stop()
        self.homing = False
        return ""

    def _clear(self, args: list[str]) -> str:
        nargs(args, 0, "CLEAR")
        self.fault = "none"
        return ""
