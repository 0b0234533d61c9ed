"""Stewart-platform driver (docs/protocols.md §3): the camera carrier.

The controller only moves legs; this driver owns the kinematics: a pose is turned into six leg
lengths (inverse kinematics), checked against the workspace (not inverted, leg lengths, joint
angles) and refused before anything is sent if unreachable; the reported pose is the forward
kinematics of the measured legs.

Poses are `home_T_platform` (a Pose3, or the 6-vector x y z roll pitch yaw in m and rad, roll-pitch-
yaw about the fixed base axes), relative to the home pose; `world_T_camera` composes the rig's
mounting: world_T_base * base_T_platform * platform_T_camera."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from drivers.driver import LineActuator
from drivers.errors import DeviceFault, MotionIncomplete, OutOfRange, ProtocolError, WorkspaceError
from drivers.motion import (AxisHardware, AxisStatus, MotionPlan, Poll, Progress, link_drops, name_link_loss, read_limits,
                            sent_motion, wait_until_idle)
from drivers.stewart_kinematics import IkResult, StewartKinematics, as_pose, describe
from drivers.transport import LineTransport
from drivers.wire import parse_fields, parse_floats
from lab.core.config import StewartConfig
from lab.core.geometry import Pose3, to_xyzrpy

ARRIVAL_TOLERANCE_MM = 0.01


class Stewart(LineActuator[AxisHardware]):
    kind = "stewart"
    ident_prefix, what = "STEWART", "a Stewart controller"
    config: StewartConfig

    def __init__(self, config: StewartConfig, transport: LineTransport) -> None:
        super().__init__(config, transport)
        self.kinematics = StewartKinematics(config.geometry)
        self._last_pose = Pose3()

    def _read_hardware(self) -> AxisHardware:
        g = self.config.geometry
        return read_limits(self.name, self.link.request, ("min_mm", "max_mm", "speed_mm_s", "settle_s"),
                           (g.leg_min_m * 1000, g.leg_max_m * 1000), "mm", "[stewart] leg_min_m/leg_max_m",
                           rig="rig leg limits", travel="stroke")

    def _report(self, hw: AxisHardware, st: AxisStatus) -> str:
        pose = np.round(to_xyzrpy(self.pose()), 6) + 0.0  # no '-0.0000'
        return (f"{st.state.lower()}; platform at x {pose[0]:+.4f} y {pose[1]:+.4f} z {pose[2]:+.4f} m, "
                f"roll {np.degrees(pose[3]):+.2f} pitch {np.degrees(pose[4]):+.2f} yaw {np.degrees(pose[5]):+.2f} deg "
                f"from home; legs [{hw.min:g}, {hw.max:g}] mm at {hw.speed:g} mm/s; fault {st.fault}")

    # -- pure: no I/O ---------------------------------------------------------------------------
    def ik(self, pose: Pose3 | Sequence[float]) -> IkResult:
        return self.kinematics.inverse(pose)

    def check_pose(self, pose: Pose3 | Sequence[float]) -> np.ndarray:
        """Leg lengths (m) of a reachable pose; WorkspaceError naming the limit otherwise."""
        res = self.kinematics.inverse(pose)
        if not res.reachable:
            raise WorkspaceError(self.name, describe(pose), res.reason)
        return res.legs_m

    def world_T_camera(self, pose: Pose3 | Sequence[float], platform_T_camera: Pose3) -> Pose3:
        return self.config.world_T_base.compose(self.kinematics.base_T_platform(pose)).compose(platform_T_camera)

    # -- queries --------------------------------------------------------------------------------
    def status(self) -> AxisStatus:
        """State IDLE, MOVING or FAULT."""
        req = "STATUS?"
        f = parse_fields(self.name, req, self.link.request(req), ("state", "fault"))
        return AxisStatus(f["state"], f["fault"])

    def legs(self) -> np.ndarray:
        """Measured leg lengths, m."""
        return np.array(parse_floats(self.name, "LEGS?", self.link.request("LEGS?"), 6)) / 1000.0

    def pose(self) -> Pose3:
        """The platform's pose (home_T_platform), by forward kinematics of the measured legs."""
        legs = self.legs()
        try:
            self._last_pose = self.kinematics.forward(legs, guess=self._last_pose)
        except ValueError as exc:
            raise ProtocolError(self.name, f"measured legs {np.round(legs * 1000, 3).tolist()} mm: {exc}") from None
        return self._last_pose

    # -- motion ---------------------------------------------------------------------------------
    def move_to(self, pose: Pose3 | Sequence[float], progress: Progress | None = None) -> Pose3:
        """Move the platform to a pose relative to home (checked first); returns the reported pose."""
        legs_m = self.check_pose(pose)
        target = as_pose(pose)
        return self._move_legs(legs_m, f"to {describe(target)}", progress)

    def home(self, progress: Progress | None = None) -> Pose3:
        return self.move_to(Pose3(), progress)

    def _move_legs(self, legs_m: np.ndarray, description: str, progress: Progress | None) -> Pose3:
        g = self.config.geometry
        legs_m = np.asarray(legs_m, dtype=float).reshape(6)
        for i, x in enumerate(legs_m):   # the last check before the wire, whatever the caller did
            if not (math.isfinite(x) and g.leg_min_m - 1e-9 <= x <= g.leg_max_m + 1e-9):
                raise OutOfRange(self.name, f"leg {i + 1} length", x * 1000, (g.leg_min_m * 1000, g.leg_max_m * 1000),
                                 "mm", "rig [stewart] leg_min_m/leg_max_m")
        hw = self.hardware()
        start = self.legs()
        target_mm = np.round(legs_m * 1000.0, 3)
        plan = MotionPlan.of(description, float(np.max(np.abs(target_mm - start * 1000.0))), hw.speed,
                             hw.settle_s, self.config.link.margin_s, self.name)
        drops = link_drops(self.link)
        line = "LEGS " + " ".join(f"{x:.3f}" for x in target_mm)
        sent_motion(self, lambda: self.link.request(line, idempotent=False), self.stop)
        span = float(np.max(np.abs(target_mm / 1000.0 - start))) or 1.0

        def poll() -> Poll:
            st = self.status()
            if st.state == "FAULT":
                raise DeviceFault(self.name, 40, f"fault {st.fault}", description)
            if not st.moving:
                return Poll(False, 1.0, "idle")
            now = self.legs()
            return Poll(True, 1.0 - float(np.max(np.abs(target_mm / 1000.0 - now))) / span,
                        f"legs at {np.round(now * 1000, 3).tolist()} mm")

        wait_until_idle(self.name, plan, poll, self.stop, progress)
        reached = self.legs()
        err = np.abs(reached * 1000.0 - target_mm)
        if np.max(err) > ARRIVAL_TOLERANCE_MM:
            i = int(np.argmax(err))
            raise name_link_loss(MotionIncomplete(
                self.name, f"stopped short of the target {description}: leg {i + 1} at "
                           f"{reached[i] * 1000:.3f} mm, commanded {target_mm[i]:.3f} mm"), self.link, drops)
        return self.pose()
