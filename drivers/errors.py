"""Typed device errors.  Each names the device; range errors name the value, the limit and the
unit, so the one line the CLI prints is enough to act on."""

from __future__ import annotations

from typing import Sequence

from lab.core.errors import LabError, UserError


class DeviceError(LabError):
    """Something went wrong talking to, or moving, a device."""

    def __init__(self, device: str, message: str) -> None:
        self.device = device
        self.message = message
        super().__init__(f"{device}: {message}")


class DeviceTimeout(DeviceError):
    """No (complete) reply in time, or a motion that did not finish in the time its physics allows."""


class DeviceFault(DeviceError):
    """The device answered with an error (`ERR <code> <text>` or an HTTP error status)."""

    def __init__(self, device: str, code: int, text: str, request: str = "") -> None:
        self.code = code
        self.text = text
        self.request = request
        where = f" to {request!r}" if request else ""
        super().__init__(device, f"device error {code}{where}: {text}")


class ProtocolError(DeviceError):
    """A reply that does not follow docs/protocols.md (garbled bytes, wrong shape)."""


class Disconnected(DeviceError):
    """The link is down: nothing answers at the URL, or the connection dropped."""


class MotionIncomplete(DeviceError):
    """A motion ended (device idle) short of its target: stopped by a link loss, a STOP or a fault."""


class OutOfRange(DeviceError, UserError):
    """A command refused before anything was sent: the value is outside the limits."""

    def __init__(self, device: str, quantity: str, value: float, limits: Sequence[float], unit: str,
                 detail: str = "") -> None:
        self.quantity = quantity
        self.value = value
        self.limits = tuple(limits)
        self.unit = unit
        lo, hi = self.limits
        msg = f"{quantity} {value:.6g} {unit} is outside the limits [{lo:.6g}, {hi:.6g}] {unit}"
        if detail:
            msg += f" ({detail})"
        DeviceError.__init__(self, device, msg + "; nothing was sent")


LimitError = OutOfRange


class WorkspaceError(DeviceError, UserError):
    """A Stewart-platform pose outside the workspace (leg length, joint angle, inverted).  Raised
    by the workspace check, before anything is sent."""

    def __init__(self, device: str, pose_desc: str, reason: str) -> None:
        self.reason = reason
        super().__init__(device, f"pose {pose_desc} is unreachable: {reason}; nothing was sent")


class LengthControlError(DeviceError):
    """The IPJR length controller did not converge (diverged or ran out of tries); the actuator
    has been stopped.  `history` holds (steps commanded, measured length m) per try."""

    def __init__(self, device: str, message: str, history: list[tuple[int, float]]) -> None:
        self.history = history
        super().__init__(device, message)


class RigMismatch(DeviceError, UserError):
    """The rig file and the device disagree (e.g. rig limits wider than the hardware's)."""
