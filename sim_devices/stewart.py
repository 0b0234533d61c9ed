"""Simulated Stewart-platform controller (docs/protocols.md §3), moving the world's six legs, and
the simulator's own forward kinematics (where the platform really is, for the camera).

The forward kinematics here is written independently of `drivers/stewart_kinematics.py` (least
squares over the x, y, z, roll, pitch, yaw 6-vector with scipy, not Newton on SE(3)), so a
kinematics bug on either side shows up as a disagreement instead of cancelling out.

Known limitations: the legs interpolate linearly in leg space (the platform's path between poses
is not a straight line, as on many real controllers); the true geometry equals the rig file's (no
joint-position errors); leg encoders are exact."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from lab.core.config import StewartGeometry
from lab.core.geometry import Pose3, from_xyzrpy, to_xyzrpy
from sim_devices.controller import Controller, check_range, limits_reply
from sim_devices.line_server import E_SYNTAX, Refuse, decimal, nargs
from sim_devices.motion import Axis

MODEL, FIRMWARE = "LAB-HEX6", "1.0"


def leg_lengths(geometry: StewartGeometry, x: np.ndarray) -> np.ndarray:
    """Leg lengths for the 6-vector x (pose relative to home, fixed-axis roll-pitch-yaw)."""
    T = from_xyzrpy(x)
    R = T.rotation().matrix()
    tops = geometry.home_m + T.translation() + geometry.platform_joints_m @ R.T
    return np.linalg.norm(tops - geometry.base_joints_m, axis=1)


def platform_pose(geometry: StewartGeometry, legs_m: np.ndarray, guess: np.ndarray | None = None) -> Pose3:
    """home_T_platform for measured leg lengths (the assembly nearest `guess`)."""
    x0 = np.zeros(6) if guess is None else np.asarray(guess, dtype=float)
    sol = least_squares(lambda x: leg_lengths(geometry, x) - legs_m, x0, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    return from_xyzrpy(sol.x)


class StewartSim(Controller):
    motion_verbs = frozenset({"LEGS", "HOME"})

    def __init__(self, legs: Axis, geometry: StewartGeometry, min_mm: float, max_mm: float,
                 name: str = "stewart") -> None:
        super().__init__(name, legs, f"STEWART {MODEL} {FIRMWARE}", {
            "LIMITS?": self._limits, "LEGS": self._legs, "LEGS?": self._legs_q, "HOME": self._home,
            "STATUS?": self._status})
        self.legs = legs                  # metres
        self.geometry = geometry
        self.min_mm, self.max_mm = min_mm, max_mm
        self.home_mm = np.linalg.norm(geometry.home_m + geometry.platform_joints_m - geometry.base_joints_m, axis=1) * 1000

    def _limits(self, args: list[str]) -> str:
        nargs(args, 0, "LIMITS?")
        return limits_reply("mm", self.min_mm, self.max_mm, self.legs.speed * 1000, self.legs.settle_s)

    def _legs(self, args: list[str]) -> str:
        if len(args) != 6:
            raise Refuse(E_SYNTAX, f"expected 6 leg lengths in mm, got {len(args)}: LEGS l1 l2 l3 l4 l5 l6")
        mm = [decimal(a, f"leg {i + 1} length") for i, a in enumerate(args)]
        for i, v in enumerate(mm):
            check_range(f"leg {i + 1} length", v, self.min_mm, self.max_mm, "mm")
        return self._start(np.array(mm) / 1000.0)

    def _legs_q(self, args: list[str]) -> str:
        nargs(args, 0, "LEGS?")
        return " ".join(f"{v * 1000:.3f}" for v in np.asarray(self.legs.position()))

    def _home(self, args: list[str]) -> str:
        nargs(args, 0, "HOME")
        return self._start(self.home_mm / 1000.0)

    def _status(self, args: list[str]) -> str:
        nargs(args, 0, "STATUS?")
        return f"state={self.state()} fault={self.fault}"


def pose_vector(pose: Pose3) -> np.ndarray:
    return to_xyzrpy(pose)
