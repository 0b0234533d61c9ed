"""The semantic models of SF-GraphSLAM (paper §2.5.8–2.5.11): when may a designed relative pose
between two related tags be trusted as a factor, and what does a measured one say about the module.

Deployable relation (§2.5.9).  Half of the deployable is a planar linkage; with theta1 = theta4 =
theta (the paper's simplification) the top node E sits at height h = 2 L_half sin(theta) above the
bottom plane, where L_half is half a side strut (L_half = spacing / 2; our reading of Eq. 33 with
theta measured from the bottom plane, so theta = 90 deg is fully deployed, the paper's upper
bound, and theta = 4.69 deg its stowed lower bound).  A measured B->T relative pose is
*kinematically valid* when it is a pure lift along the tag's up axis (lateral offsets and rotation
within the measurement noise) with theta in [4.69, 90] deg; the module is *fully deployed* when h
is within the height tolerance of the design.  Only a fully deployed pair gets the semantic factor;
a valid partial deployment reverts to GraphSLAM for that pair and the module is reported not fully
deployed.

Close-out strut and square relations (§2.5.10–2.5.11).  Zones derived from our node geometry
(docs/sf_graphslam.md): a strut end (diameter 19.05 mm) enters a node socket (bore 25.4 mm) through a
chamfered mouth (40 mm); ball plungers engage a hole in the strut end over +-2 mm of axial travel.
- capture zone: the end is inside the mouth: lateral <= (40 - 19.05) / 2 = 10.5 mm, axial <= 12 mm;
- final-assembly zone: the end is in the bore with the plungers engaged: lateral <=
  (25.4 - 19.05) / 2 = 3.2 mm, axial <= 2 mm, rotation <= 3.2 mm over the member's 0.5 m = 0.36 deg.
A close-out square has four such ends; its zones are those of its worst corner, which for a rigid
square is its pose error at the corner farthest from the tag (the lever arm is the square's
diagonal, 0.71 m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lab.core.geometry import Pose3, Rot3

THETA_MIN_RAD = math.radians(4.69)
THETA_MAX_RAD = math.radians(90.0)

STRUT_END_DIAMETER_M = 0.01905
SOCKET_BORE_M = 0.0254
SOCKET_MOUTH_M = 0.040
CAPTURE_AXIAL_M = 0.012
PLUNGER_TRAVEL_M = 0.002

CAPTURE_LATERAL_M = (SOCKET_MOUTH_M - STRUT_END_DIAMETER_M) / 2.0       # 10.5 mm
FINAL_LATERAL_M = (SOCKET_BORE_M - STRUT_END_DIAMETER_M) / 2.0          # 3.2 mm


@dataclass(frozen=True)
class DeployCheck:
    height_m: float            # measured B->T lift
    theta_rad: float           # nan when no theta fits (over-extended)
    lateral_m: float           # B->T offset across the lift direction
    rotation_rad: float        # B->T relative rotation
    valid: bool                # kinematically possible
    deployed: bool             # fully deployed (within tolerance)
    reason: str                # "" when deployed

    @property
    def theta_deg(self) -> float:
        return math.degrees(self.theta_rad)


def deployable_check(measured_b_T_t: Pose3, spacing_m: float, *, height_tol_m: float = 0.005,
                     lateral_tol_m: float = 0.010, rotation_tol_rad: float = math.radians(2.0),
                     noise_m: float = 0.0) -> DeployCheck:
    """The kinematic validity and deployment check of a measured bottom->top tag pose (bottom tag
    frame: y is the lift direction).  `noise_m` (1 sigma of the measured height) widens the
    over-extension bound so that noise never makes a good module invalid."""
    t = measured_b_T_t.translation()
    h = float(t[1])
    lateral = float(math.hypot(t[0], t[2]))
    rot = float(np.linalg.norm(Rot3.Logmap(measured_b_T_t.rotation())))
    l_half = spacing_m / 2.0
    ratio = h / (2.0 * l_half)
    over = h - spacing_m
    theta = math.asin(min(1.0, max(-1.0, ratio))) if ratio <= 1.0 + 1e-12 else float("nan")
    reasons = []
    if over > max(height_tol_m, 3.0 * noise_m):
        reasons.append(f"over-extended: lift {h * 1000:.1f} mm > {spacing_m * 1000:.0f} mm")
        theta = float("nan")
    elif not THETA_MIN_RAD <= (theta if not math.isnan(theta) else THETA_MAX_RAD) <= THETA_MAX_RAD:
        reasons.append(f"theta {math.degrees(theta):.1f} deg outside [4.69, 90] deg")
    if lateral > lateral_tol_m:
        reasons.append(f"top plane {lateral * 1000:.1f} mm off the lift axis")
    if rot > rotation_tol_rad:
        reasons.append(f"top plane turned {math.degrees(rot):.2f} deg")
    valid = not reasons
    deployed = valid and h >= spacing_m - height_tol_m
    if valid and not deployed:
        reason = (f"not fully deployed: lift {h * 1000:.1f} mm of {spacing_m * 1000:.0f} mm "
                  f"(theta {math.degrees(theta):.1f} deg)")
    else:
        reason = "; ".join(reasons)
    return DeployCheck(h, theta, lateral, rot, valid, deployed, reason)


@dataclass(frozen=True)
class ZoneCheck:
    lateral_m: float
    axial_m: float
    rotation_rad: float
    captured: bool
    final: bool

    @property
    def zone(self) -> str:
        return "final assembly" if self.final else ("captured" if self.captured else "outside capture")

    def describe(self) -> str:
        return (f"{self.zone} zone (lateral {self.lateral_m * 1000:.1f} mm, axial {self.axial_m * 1000:.1f} mm, "
                f"rotation {math.degrees(self.rotation_rad):.2f} deg)")


def closeout_zone(design_T_estimate: Pose3, member_axis: np.ndarray, lever_m: float) -> ZoneCheck:
    """Zone of a close-out member whose estimated pose differs from its design by
    `design_T_estimate` (in the member's design frame); `member_axis` is the member's axis in that
    frame, `lever_m` the distance from the tag to the farthest end (rotation moves that end most)."""
    axis = np.asarray(member_axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    rot = float(np.linalg.norm(Rot3.Logmap(design_T_estimate.rotation())))
    t = design_T_estimate.translation()
    axial = abs(float(np.dot(t, axis)))
    lateral = float(np.linalg.norm(t - np.dot(t, axis) * axis)) + lever_m * math.sin(rot)
    captured = lateral <= CAPTURE_LATERAL_M and axial <= CAPTURE_AXIAL_M
    final = lateral <= FINAL_LATERAL_M and axial <= PLUNGER_TRAVEL_M
    return ZoneCheck(lateral, axial, rot, captured, final)
