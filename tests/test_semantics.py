"""The semantic models: the deployable's kinematic validity check (paper §2.5.9, theta in
[4.69, 90] deg) with a fully deployed module at the theta = 90 deg boundary, and the close-out
capture / final-assembly zones derived from the node geometry (§2.5.10–2.5.11)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.semantics import (
    CAPTURE_AXIAL_M,
    CAPTURE_LATERAL_M,
    FINAL_LATERAL_M,
    PLUNGER_TRAVEL_M,
    closeout_zone,
    deployable_check,
)
from lab.core.geometry import Pose3, Rot3

SPACING = 0.5


def lift(h, lateral=(0.0, 0.0), rot=(0.0, 0.0, 0.0)) -> Pose3:
    """bottom_T_top: y is the lift direction of the bottom tag's frame."""
    return Pose3(Rot3.RzRyRx(*rot), np.array([lateral[0], h, lateral[1]]))


def test_fully_deployed_module_sits_at_theta_90_and_passes():
    c = deployable_check(lift(SPACING), SPACING)
    assert c.valid and c.deployed and c.reason == ""
    assert c.theta_deg == pytest.approx(90.0)


@pytest.mark.parametrize("dh", [-0.003, +0.003, +0.004])
def test_measurement_noise_at_the_boundary_does_not_make_a_good_module_invalid(dh):
    # theta = 90 deg is the upper end of the valid range: a lift measured a little long must not
    # read as impossible (over-extended), nor a little short as partly deployed
    c = deployable_check(lift(SPACING + dh), SPACING, height_tol_m=0.005)
    assert c.valid and c.deployed, c.reason


def test_noise_widens_the_over_extension_bound():
    long = lift(SPACING + 0.012)
    assert not deployable_check(long, SPACING, height_tol_m=0.005).valid
    assert deployable_check(long, SPACING, height_tol_m=0.005, noise_m=0.005).valid  # 3 sigma = 15 mm


def test_partial_deployment_is_valid_but_not_deployed_with_its_theta():
    c = deployable_check(lift(0.35), SPACING)
    assert c.valid and not c.deployed
    assert c.theta_deg == pytest.approx(math.degrees(math.asin(0.35 / SPACING)), abs=1e-6)
    assert "not fully deployed" in c.reason and "350.0 mm" in c.reason


@pytest.mark.parametrize(
    "pose, words",
    [
        (lift(0.5 * SPACING * 2 * math.sin(math.radians(4.0))), "theta"),   # below 4.69 deg: tighter than stowed
        (lift(SPACING + 0.03), "over-extended"),
        (lift(SPACING, lateral=(0.02, 0.0)), "off the lift axis"),
        (lift(SPACING, rot=(0.0, math.radians(5.0), 0.0)), "turned"),
    ],
)
def test_kinematically_impossible_pairs_are_invalid_and_say_why(pose, words):
    c = deployable_check(pose, SPACING)
    assert not c.valid and not c.deployed
    assert words in c.reason


def test_theta_bounds_are_the_papers():
    lo = 2 * (SPACING / 2) * math.sin(math.radians(4.69))
    assert deployable_check(lift(lo + 1e-4), SPACING).valid
    assert not deployable_check(lift(lo - 1e-4), SPACING).valid


def test_zone_sizes_follow_from_the_node_geometry():
    assert CAPTURE_LATERAL_M == pytest.approx((0.040 - 0.01905) / 2)
    assert FINAL_LATERAL_M == pytest.approx((0.0254 - 0.01905) / 2)
    assert FINAL_LATERAL_M < CAPTURE_LATERAL_M and PLUNGER_TRAVEL_M < CAPTURE_AXIAL_M


@pytest.mark.parametrize(
    "offset, rot_deg, zone",
    [
        ((0.0, 0.0, 0.0), 0.0, "final assembly"),
        ((0.002, 0.0, 0.0), 0.0, "final assembly"),        # inside the bore's 3.2 mm clearance
        ((0.006, 0.0, 0.0), 0.0, "captured"),              # in the mouth, not in the bore
        ((0.0, 0.0, 0.005), 0.0, "captured"),              # pushed in past the plungers' travel
        ((0.0, 0.0, 0.0), 0.8, "captured"),                # 0.8 deg over 0.5 m = 7 mm at the far end
        ((0.012, 0.0, 0.0), 0.0, "outside capture"),
        ((0.0, 0.0, 0.020), 0.0, "outside capture"),
    ],
)
def test_closeout_strut_zones(offset, rot_deg, zone):
    axis = np.array([0.0, 0.0, 1.0])   # the member's axis in its design frame
    d = Pose3(Rot3.Ry(math.radians(rot_deg)), np.array(offset))
    z = closeout_zone(d, axis, lever_m=0.5)
    assert z.zone == zone, z.describe()
    assert zone in z.describe()
