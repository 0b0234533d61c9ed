"""6-6 Stewart-platform kinematics: pure functions of the rig's geometry, no I/O.

Pose convention (the `lab stewart ik` command, docs/hardware.md): the pose of the platform relative
to its home pose, `home_T_platform`, as (x, y, z, roll, pitch, yaw) in metres and radians with
roll-pitch-yaw about the fixed base axes.  Home has the base's orientation, so
`base_T_platform = Pose3(R, home + p)` and leg i has length `|home + p + R·top_i − base_i|`.

- `inverse`: leg lengths of a pose, plus the workspace check (not inverted, leg lengths, joint
  angles) with the first violated limit named.
- `forward`: the pose from six leg lengths, by Newton's method on the inverse kinematics (Gauss-
  Newton on SE(3): rotation updated through the exponential map, so no Euler singularities)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from lab.core.config import StewartGeometry
from lab.core.geometry import Pose3, Rot3, from_xyzrpy, to_xyzrpy


@dataclass(frozen=True)
class IkResult:
    pose: np.ndarray                  # (6,) x y z roll pitch yaw, relative to home
    legs_m: np.ndarray                # (6,)
    reachable: bool
    reason: str                       # "" when reachable, else the first violated limit
    base_joint_angles_rad: np.ndarray      # (6,) leg vs base normal
    platform_joint_angles_rad: np.ndarray  # (6,) leg vs platform normal


MAX_TRANSLATION_M = 10.0     # no Stewart platform we drive reaches further; beyond it floats lose mm
_NAMES = ("x", "y", "z", "roll", "pitch", "yaw")


def pose_problem(pose: Pose3 | Sequence[float]) -> str:
    """Why a pose is not a pose at all ("" if it is one): a non-finite value, an angle outside
    [-pi, pi] (1e12 rad names no orientation anyone meant), a translation beyond 10 m."""
    if isinstance(pose, Pose3):
        if not np.all(np.isfinite(pose.matrix())):
            return "the pose has a non-finite entry"
        v = np.asarray(to_xyzrpy(pose), dtype=float)
    else:
        try:
            v = np.asarray(pose, dtype=float).reshape(6)
        except (TypeError, ValueError):
            return f"a pose is six numbers (x y z roll pitch yaw), got {pose!r}"
    for name, x in zip(_NAMES, v):
        if not math.isfinite(x):
            return f"{name} {x} is not a finite number"
    for name, x in zip(_NAMES[:3], v[:3]):
        if abs(x) > MAX_TRANSLATION_M:
            return f"{name} {x:.6g} m is outside [-{MAX_TRANSLATION_M:g}, {MAX_TRANSLATION_M:g}] m"
    for name, x in zip(_NAMES[3:], v[3:]):
        if abs(x) > math.pi + 1e-9:
            return f"{name} {x:.6g} rad is outside [-pi, pi] rad"
    return ""


def as_pose(pose: Pose3 | Sequence[float]) -> Pose3:
    return pose if isinstance(pose, Pose3) else from_xyzrpy(pose)


def describe(pose: Pose3 | Sequence[float]) -> str:
    if pose_problem(pose):
        return repr([float(x) for x in np.asarray(pose if not isinstance(pose, Pose3) else to_xyzrpy(pose),
                                                   dtype=float).reshape(-1)])
    v = to_xyzrpy(as_pose(pose))
    return ("(x {:.4f}, y {:.4f}, z {:.4f} m; roll {:.2f}, pitch {:.2f}, yaw {:.2f} deg)"
            .format(*v[:3], *np.degrees(v[3:])))


class StewartKinematics:
    def __init__(self, geometry: StewartGeometry) -> None:
        self.g = geometry
        self.base = np.asarray(geometry.base_joints_m, dtype=float)
        self.top = np.asarray(geometry.platform_joints_m, dtype=float)
        self.home = np.asarray(geometry.home_m, dtype=float)

    def base_T_platform(self, home_T_platform: Pose3 | Sequence[float]) -> Pose3:
        p = as_pose(home_T_platform)
        return Pose3(p.rotation(), self.home + p.translation())

    def legs_vectors(self, home_T_platform: Pose3 | Sequence[float]) -> np.ndarray:
        """(6, 3) vectors from each base joint to its platform joint, base frame."""
        bp = self.base_T_platform(home_T_platform)
        R = bp.rotation().matrix()
        return bp.translation() + self.top @ R.T - self.base

    def leg_lengths(self, home_T_platform: Pose3 | Sequence[float]) -> np.ndarray:
        return np.linalg.norm(self.legs_vectors(home_T_platform), axis=1)

    @property
    def home_legs_m(self) -> np.ndarray:
        return self.leg_lengths(Pose3())

    def inverse(self, home_T_platform: Pose3 | Sequence[float]) -> IkResult:
        bad = pose_problem(home_T_platform)
        if bad:
            nan6 = np.full(6, np.nan)
            raw = np.asarray(to_xyzrpy(home_T_platform), dtype=float) if isinstance(home_T_platform, Pose3) \
                else np.asarray(home_T_platform, dtype=float).reshape(-1)
            return IkResult(raw, nan6, False, bad, nan6, nan6)
        pose = as_pose(home_T_platform)
        v = self.legs_vectors(pose)
        legs = np.linalg.norm(v, axis=1)
        R = pose.rotation().matrix()
        n_plat = R[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            u = v / legs[:, None]
        base_ang = np.arccos(np.clip(u[:, 2], -1.0, 1.0))
        plat_ang = np.arccos(np.clip(u @ n_plat, -1.0, 1.0))
        reason = self._violation(pose, v, legs, base_ang, plat_ang)
        return IkResult(to_xyzrpy(pose), legs, not reason, reason, base_ang, plat_ang)

    def _violation(self, pose: Pose3, v: np.ndarray, legs: np.ndarray, base_ang: np.ndarray,
                   plat_ang: np.ndarray) -> str:
        g = self.g
        n_plat = pose.rotation().matrix()[:, 2]
        if n_plat[2] <= 0.0:
            return f"platform inverted (its normal points {math.degrees(math.acos(np.clip(n_plat[2], -1, 1))):.1f} deg from the base normal)"
        top_z = (self.base + v)[:, 2]
        if np.any(top_z <= self.base[:, 2]):
            i = int(np.argmin(top_z - self.base[:, 2]))
            return f"platform joint {i + 1} at or below the base plane (z {top_z[i]:.4f} m)"
        for i, length in enumerate(legs):
            if length < g.leg_min_m - 1e-12:
                return f"leg {i + 1} length {length:.4f} m below leg_min_m {g.leg_min_m:.4f} m"
            if length > g.leg_max_m + 1e-12:
                return f"leg {i + 1} length {length:.4f} m above leg_max_m {g.leg_max_m:.4f} m"
        for i, a in enumerate(base_ang):
            if a > g.base_joint_max_rad + 1e-12:
                return (f"base joint {i + 1} angle {math.degrees(a):.2f} deg above base_joint_max_deg "
                        f"{math.degrees(g.base_joint_max_rad):.2f} deg")
        for i, a in enumerate(plat_ang):
            if a > g.platform_joint_max_rad + 1e-12:
                return (f"platform joint {i + 1} angle {math.degrees(a):.2f} deg above platform_joint_max_deg "
                        f"{math.degrees(g.platform_joint_max_rad):.2f} deg")
        return ""

    def forward(self, legs_m: Sequence[float], guess: Pose3 | None = None, tol_m: float = 1e-10,
                max_iter: int = 50) -> Pose3:
        """home_T_platform whose legs have the given lengths (the assembly near `guess`, default home)."""
        L = np.asarray(legs_m, dtype=float).reshape(6)
        g0 = guess if guess is not None else Pose3()
        R = g0.rotation().matrix()
        p = self.home + g0.translation()
        for _ in range(max_iter):
            top_b = self.top @ R.T                      # R·top_i
            v = p + top_b - self.base
            lengths = np.linalg.norm(v, axis=1)
            r = lengths - L
            if np.max(np.abs(r)) < tol_m:
                return Pose3(Rot3(R), p - self.home)
            u = v / lengths[:, None]
            J = np.hstack([np.cross(top_b, u), u])      # d length / d(omega, dp)
            try:
                delta = np.linalg.solve(J, -r)
            except np.linalg.LinAlgError:
                raise ValueError("forward kinematics: singular configuration") from None
            R = Rot3.Expmap(delta[:3]).matrix() @ R
            p = p + delta[3:]
        raise ValueError(f"forward kinematics did not converge for legs {np.round(L, 6).tolist()} m "
                         f"(residual {np.max(np.abs(r)):.2e} m)")

    def ik_json(self, pose6: Sequence[float]) -> dict:
        """The `lab stewart ik --json` shape."""
        res = self.inverse(pose6)
        return {
            "pose": [float(x) if math.isfinite(float(x)) else str(float(x)) for x in pose6],
            "legs_m": [float(x) if math.isfinite(x) else None for x in res.legs_m],
            "reachable": bool(res.reachable),
            "reason": res.reason,
            "base_joints_m": self.base.tolist(),
            "top_joints_m": self.top.tolist(),
            "home_m": self.home.tolist(),
        }
