"""What the simulated serial controllers share (turntable, Stewart, lift, the IPJR's Arduino): each
drives one motor (a `sim_devices.motion.Axis`, or the IPJR's actuator), answers `ID?` with its
model, `STOP` and `CLEAR`, latches a fault, reports `STATUS?` state IDLE / MOVING / FAULT, and
stops when its host goes (`link_lost`).  Each device's own verbs, units and replies stay in its
module.

The simulators' side only: the drivers never import this (a protocol bug must not hide in code
both sides share)."""

from __future__ import annotations

from typing import Callable, Protocol

from sim_devices.line_server import E_RANGE, LineDevice, Refuse, decimal, nargs
from sim_devices.motion import Axis


class Motor(Protocol):
    def moving(self) -> bool: ...
    def stop(self) -> None: ...


class Controller(LineDevice):
    """A serial controller of one motor.  `ident` is its whole `ID?` reply; `commands` its own
    verbs, added to ID?, STOP and CLEAR."""

    fault = "none"          # the latched fault ("none" or a one-word reason), cleared by CLEAR

    def __init__(self, name: str, motor: Motor, ident: str,
                 commands: dict[str, Callable[[list[str]], str]]) -> None:
        super().__init__()
        self.name = name
        self.motor = motor
        self.ident = ident
        self.commands.update({"ID?": self._id, "STOP": self._stop, "CLEAR": self._clear, **commands})

    # -- state ----------------------------------------------------------------------------------
    def is_moving(self) -> bool:
        return self.motor.moving()

    def link_lost(self) -> None:
        self.motor.stop()

    def stop_motion(self) -> None:
        """What STOP does."""
        self.motor.stop()

    def state(self) -> str:
        """STATUS?'s state."""
        if self.fault != "none":
            return "FAULT"
        return "MOVING" if self.is_moving() else "IDLE"

    def _start(self, target: float | object) -> str:
        """Begin an accepted motion to `target` (refused while a fault is latched or a motion is under way)."""
        self._ready()
        self.motor.start(target, stuck=self.take_stuck())  # type: ignore[attr-defined]
        return ""

    # -- commands -------------------------------------------------------------------------------
    def _id(self, args: list[str]) -> str:
        nargs(args, 0, "ID?")
        return self.ident

    def _stop(self, args: list[str]) -> str:
        nargs(args, 0, "STOP")
        self.stop_motion()
        return ""

    def _clear(self, args: list[str]) -> str:
        nargs(args, 0, "CLEAR")
        self.fault = "none"
        return ""


class AxisController(Controller):
    """A single-axis position controller (turntable, lift): MOVE to a position within its travel,
    HOME, POS?, LIMITS?, STATUS?; positions in its wire unit (`unit`, `to_wire` from the axis's SI
    value), `what` the position is called in a refusal ("angle", "height")."""

    motion_verbs = frozenset({"MOVE", "HOME"})
    unit: str
    what: str

    def __init__(self, name: str, axis: Axis, ident: str, travel: tuple[float, float]) -> None:
        super().__init__(name, axis, ident, {"LIMITS?": self._limits, "HOME": self._home, "MOVE": self._move,
                                             "POS?": self._pos, "STATUS?": self._status})
        self.axis = axis
        self.travel = travel              # min, max in the wire unit

    def to_wire(self, value: float | object) -> float:
        raise NotImplementedError

    def _move_to(self, value: float) -> str:
        """An accepted MOVE (in range, in the wire unit)."""
        raise NotImplementedError

    def _status_extra(self) -> str:
        """Fields of STATUS? between the target and the fault, each followed by a space."""
        return ""

    def _limits(self, args: list[str]) -> str:
        nargs(args, 0, "LIMITS?")
        return limits_reply(self.unit, *self.travel, self.to_wire(self.axis.speed), self.axis.settle_s)

    def _move(self, args: list[str]) -> str:
        nargs(args, 1, f"MOVE <{self.unit}>")
        value = decimal(args[0], self.what)
        check_range(self.what, value, *self.travel, self.unit)
        return self._move_to(value)

    def _home(self, args: list[str]) -> str:
        raise NotImplementedError

    def _pos(self, args: list[str]) -> str:
        nargs(args, 0, "POS?")
        return f"{self.to_wire(self.axis.position()):.3f}"

    def _status(self, args: list[str]) -> str:
        nargs(args, 0, "STATUS?")
        state = self.state()
        u = self.unit
        return (f"state={state} pos_{u}={self.to_wire(self.axis.position()):.3f} "
                f"target_{u}={self.to_wire(self.axis.target()):.3f} {self._status_extra()}fault={self.fault}")


def limits_reply(unit: str, lo: float, hi: float, speed: float, settle_s: float) -> str:
    """`LIMITS?` of a single-axis controller: travel, speed (unit per s) and settling time."""
    return f"min_{unit}={lo:.3f} max_{unit}={hi:.3f} speed_{unit}_s={speed:.3f} settle_s={settle_s:.3f}"


def check_range(what: str, value: float, lo: float, hi: float, unit: str) -> None:
    """Refuse (ERR 20) a commanded value outside the hardware's travel."""
    if not lo <= value <= hi:
        raise Refuse(E_RANGE, f"{what} {value:.3f} {unit} outside [{lo:.3f}, {hi:.3f}] {unit}")
