"""The rig inside the graph: the kinematic-chain factor and the tag-corner factor, against
numerical derivatives and against the chain composed by hand."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimation.fiducials import tag_object_points
from estimation.rig_model import (AXIS, BASE, INTRINSICS, LIFT, MOUNT, RigGeometry, ViewMotion, cal3_s2, chain_factor,
                                  corner_factor)
from lab.core.config import load_rig
from lab.core.geometry import Pose3, Rot3
from lab.core.structures.borg import build_borg

RIG = load_rig()
MODEL = build_borg(3)
K = np.array([[914.0, 0, 639.5], [0, 914.0, 359.5], [0, 0, 1]])
GEOM = RigGeometry.from_rig(RIG, MODEL.world_T_structure(0.0), K)
C = gtsam.symbol("c", 0)
T = gtsam.symbol("t", 0)


def _numerical(factor, values: gtsam.Values, key: int, d: int, eps: float = 1e-6) -> np.ndarray:
    base = factor.unwhitenedError(values)
    J = np.zeros((len(base), d))
    for i in range(d):
        v = gtsam.Values(values)
        delta = gtsam.VectorValues()
        dx = np.zeros(d)
        dx[i] = eps
        delta.insert(key, dx)
        J[:, i] = (factor.unwhitenedError(v.retract(delta)) - base) / eps
    return J


def _analytic(factor, values: gtsam.Values) -> list[np.ndarray]:
    A, _ = factor.linearize(values).jacobian()        # whitened: the noise's sqrt information applied
    out, col = [], 0
    for key in factor.keys():
        d = 5 if key == INTRINSICS else 6
        out.append(A[:, col:col + d])
        col += d
    return out


def _values(perturb: bool = True) -> gtsam.Values:
    rng = np.random.default_rng(3)
    v = gtsam.Values()
    small = (lambda s: Pose3.Expmap(rng.normal(0, s, 6))) if perturb else (lambda s: Pose3())
    v.insert(AXIS, Pose3(Rot3.RzRyRx(0.0004, -0.0003, 0.0), np.array([0.002, -0.0015, 0.0])))
    v.insert(BASE, RIG.stewart.world_T_base.compose(small(0.01)))
    v.insert(MOUNT, RIG.camera.platform_T_camera.compose(small(0.01)))
    return v


def test_the_chain_predicts_the_camera_as_composed_by_hand():
    motion = ViewMotion(0.7, (0.01, -0.02, 0.03, 0.02, -0.05, 0.04))
    v = _values()
    A, B, M = (v.atPose3(k) for k in (AXIS, BASE, MOUNT))
    world_T_structure = A.compose(Pose3(Rot3.Rz(0.7), np.zeros(3))).compose(A.inverse()).compose(
        MODEL.world_T_structure(0.0))
    by_hand = world_T_structure.inverse().compose(B).compose(Pose3(Rot3(), GEOM.home_m)).compose(
        Pose3.Expmap(np.zeros(6))).compose(gtsam.Pose3(Rot3.RzRyRx(0.02, -0.05, 0.04), np.array([0.01, -0.02, 0.03]))
                                           ).compose(M)
    assert GEOM.predict(motion, A, B, M).equals(by_hand, 1e-12)


def test_chain_factor_jacobians_match_numerical_derivatives():
    motion = ViewMotion(-1.2, (0.0, 0.04, -0.02, 0.0, 0.1, -0.05))
    v = _values()
    cam = GEOM.predict(motion, *(v.atPose3(k) for k in (AXIS, BASE, MOUNT))).compose(
        Pose3.Expmap(np.array([1e-4, -2e-4, 1e-4, 3e-4, -1e-4, 2e-4])))
    v.insert(C, cam)
    f = chain_factor(GEOM, motion, C, gtsam.noiseModel.Unit.Create(6))
    analytic = _analytic(f, v)
    for key, J in zip(f.keys(), analytic):
        assert J == pytest.approx(_numerical(f, v, key, 6), abs=2e-5)
    assert np.linalg.norm(f.unwhitenedError(v)) < 1e-3


LIFT_TRUE = Pose3(Rot3.RzRyRx(0.004, -0.003, 0.0), np.zeros(3))     # a lift 4 mrad off vertical (exaggerated)


def test_a_lifted_view_raises_the_stewart_base_along_the_lift_axis():
    """lift(h) moves the base h along L's z axis and nothing else: by hand, the base's translation
    plus h times the tilted axis; the prediction of an unlifted view is the four-key chain's."""
    v = _values()
    A, B, M = (v.atPose3(k) for k in (AXIS, BASE, MOUNT))
    h = 1.25
    motion = ViewMotion(0.4, (0.0, 0.03, 0.0, 0.0, 0.05, 0.0), h)
    axis = LIFT_TRUE.rotation().matrix()[:, 2]
    lifted_B = Pose3(B.rotation(), B.translation() + h * axis)
    by_hand = GEOM.predict(ViewMotion(0.4, motion.stewart_pose), A, lifted_B, M)
    assert GEOM.predict(motion, A, B, M, LIFT_TRUE).equals(by_hand, 1e-12)
    flat = ViewMotion(0.4, motion.stewart_pose, 0.0)
    assert GEOM.predict(flat, A, B, M, LIFT_TRUE).equals(GEOM.predict(flat, A, B, M), 0.0)
    assert list(chain_factor(GEOM, flat, C).keys()) == [AXIS, BASE, MOUNT, C]      # no lift variable


@pytest.mark.parametrize("h", [1.8, -0.4])
def test_lifted_chain_factor_jacobians_match_numerical_derivatives(h):
    motion = ViewMotion(2.1, (0.02, -0.01, 0.03, 0.05, -0.08, 0.1), h)
    v = _values()
    L = LIFT_TRUE.compose(Pose3.Expmap(np.array([0.001, -0.002, 0.003, 0.01, -0.02, 0.005])))
    v.insert(LIFT, L)
    cam = GEOM.predict(motion, *(v.atPose3(k) for k in (AXIS, BASE, MOUNT)), L).compose(
        Pose3.Expmap(np.array([-1e-4, 2e-4, 1e-4, -3e-4, 1e-4, 2e-4])))
    v.insert(C, cam)
    f = chain_factor(GEOM, motion, C, gtsam.noiseModel.Unit.Create(6))
    assert list(f.keys()) == [AXIS, BASE, MOUNT, C, LIFT]
    for key, J in zip(f.keys(), _analytic(f, v)):
        assert J == pytest.approx(_numerical(f, v, key, 6), abs=2e-5), gtsam.DefaultKeyFormatter(key)
    assert np.linalg.norm(f.unwhitenedError(v)) < 1e-3
    # the tilt is what the lift contributes: a tilt about x moves the camera along -y by ~h x tilt
    J_lift = _analytic(f, v)[4]
    assert np.abs(J_lift[:, :2]).max() > 0.5 * abs(h) and np.abs(J_lift[:, 3:]).max() < 1e-9


@pytest.mark.parametrize("turntable_rad", [0.0, -1.2, 2.9])
def test_the_one_chain_factor_with_a_lift_at_height_zero_is_the_chain_without_one(turntable_rad):
    """One factor serves rigs with and without a lift: given the lift's variable at h = 0 its error
    and its Jacobians on A, B, M, C are those of the chain without a lift term, and nothing of the
    lift's frame can move the camera."""
    motion = ViewMotion(turntable_rad, (0.0, 0.04, -0.02, 0.0, 0.1, -0.05), 0.0)
    v = _values()
    v.insert(LIFT, LIFT_TRUE.compose(Pose3.Expmap(np.array([0.001, -0.002, 0.003, 0.01, -0.02, 0.005]))))
    v.insert(C, GEOM.predict(motion, *(v.atPose3(k) for k in (AXIS, BASE, MOUNT))).compose(
        Pose3.Expmap(np.array([1e-4, -2e-4, 1e-4, 3e-4, -1e-4, 2e-4]))))
    unit = gtsam.noiseModel.Unit.Create(6)
    without = chain_factor(GEOM, motion, C, unit)
    with_lift = chain_factor(GEOM, motion, C, unit, lift_key=LIFT)
    assert list(without.keys()) == [AXIS, BASE, MOUNT, C] and list(with_lift.keys()) == [AXIS, BASE, MOUNT, C, LIFT]
    assert np.abs(with_lift.unwhitenedError(v) - without.unwhitenedError(v)).max() < 1e-12
    J_without, J_with = _analytic(without, v), _analytic(with_lift, v)
    for a, b in zip(J_without, J_with[:4]):
        assert np.abs(a - b).max() < 1e-12
    assert np.abs(J_with[4]).max() < 1e-12
    assert GEOM.predict(motion, *(v.atPose3(k) for k in (AXIS, BASE, MOUNT, LIFT))).equals(
        GEOM.predict(motion, *(v.atPose3(k) for k in (AXIS, BASE, MOUNT))), 0.0)


def test_a_lifted_chain_adds_the_lifts_repeatability():
    flat, lifted = ViewMotion(0.0, (0.0,) * 6), ViewMotion(0.0, (0.0,) * 6, 1.0)
    d = GEOM.chain_noise(lifted).covariance() - GEOM.chain_noise(flat).covariance()
    assert np.allclose(d[3:, 3:], np.eye(3) * GEOM.config.lift_repeatability_m ** 2, atol=1e-18)
    assert np.allclose(d[:3, :], 0.0, atol=1e-18)


def test_corner_factor_jacobians_match_numerical_derivatives_and_reproject_exactly():
    v = gtsam.Values()
    cam = Pose3(Rot3.RzRyRx(-np.pi / 2 + 0.1, 0.05, -np.pi / 2 + 0.2), np.array([-2.0, 0.1, 0.7]))
    tag = Pose3(Rot3.RzRyRx(np.pi / 2, 0.0, -np.pi / 2 + 0.3), np.array([0.0, 0.2, 0.6]))
    v.insert(C, cam)
    v.insert(T, tag)
    v.insert(INTRINSICS, cal3_s2(K))
    local = tag_object_points(0.1)
    pinhole = gtsam.PinholeCameraCal3_S2(cam, cal3_s2(K))
    corners = np.array([pinhole.project(tag.transformFrom(p)) for p in local])
    f = corner_factor(C, T, corners, local, 0.1, robust_k=None)
    assert np.abs(f.unwhitenedError(v)).max() < 1e-9
    bumped = corners + 0.5
    f = corner_factor(C, T, bumped, local, 0.1, robust_k=None)
    analytic = _analytic(f, v)
    for key, J in zip(f.keys(), analytic):
        d = 5 if key == INTRINSICS else 6
        num = _numerical(f, v, key, d, eps=1e-6 if d == 6 else 1e-4)
        assert J * 0.1 == pytest.approx(num, rel=1e-3, abs=1e-2)     # unwhitened: sigma 0.1 px


def test_corner_factor_with_fixed_intrinsics_matches_numerical_derivatives():
    v = gtsam.Values()
    cam = Pose3(Rot3.RzRyRx(-np.pi / 2 - 0.05, 0.1, -np.pi / 2 + 0.15), np.array([-2.2, -0.1, 0.8]))
    tag = Pose3(Rot3.RzRyRx(np.pi / 2 + 0.1, -0.05, -np.pi / 2 + 0.4), np.array([0.1, 0.3, 0.5]))
    v.insert(C, cam)
    v.insert(T, tag)
    local = tag_object_points(0.1)
    K2 = np.array([[920.0, 0.3, 641.0], [0, 918.0, 358.0], [0, 0, 1]])
    pinhole = gtsam.PinholeCameraCal3_S2(cam, cal3_s2(K2))
    corners = np.array([pinhole.project(tag.transformFrom(p)) for p in local])
    f = corner_factor(C, T, corners - 0.3, local, 0.1, robust_k=None, fixed=cal3_s2(K2))
    assert list(f.keys()) == [C, T]
    assert f.unwhitenedError(v) == pytest.approx(np.full(8, 0.3), abs=1e-9)
    for key, J in zip(f.keys(), _analytic(f, v)):
        assert J * 0.1 == pytest.approx(_numerical(f, v, key, 6), rel=1e-3, abs=1e-2)


def test_corner_factor_with_a_print_scale_matches_numerical_derivatives():
    S = gtsam.symbol("s", 0)
    v = gtsam.Values()
    cam = Pose3(Rot3.RzRyRx(-np.pi / 2 - 0.05, 0.1, -np.pi / 2 + 0.15), np.array([-2.2, -0.1, 0.8]))
    tag = Pose3(Rot3.RzRyRx(np.pi / 2 + 0.1, -0.05, -np.pi / 2 + 0.4), np.array([0.1, 0.3, 0.5]))
    v.insert(C, cam)
    v.insert(T, tag)
    v.insert(S, np.array([0.002]))
    local = tag_object_points(0.1)
    pinhole = gtsam.PinholeCameraCal3_S2(cam, cal3_s2(K))
    # a tag printed 0.2 % large reprojects exactly through the scale variable
    corners = np.array([pinhole.project(tag.transformFrom(1.002 * p)) for p in local])
    f = corner_factor(C, T, corners, local, 0.1, robust_k=None, fixed=cal3_s2(K), scale_key=S)
    assert list(f.keys()) == [C, T, S]
    assert np.abs(f.unwhitenedError(v)).max() < 1e-9
    f = corner_factor(C, T, corners + 0.4, local, 0.1, robust_k=None, fixed=cal3_s2(K), scale_key=S)
    for key, J in zip(f.keys(), _analytic_sized(f, v, {S: 1})):
        d = 1 if key == S else 6
        assert J * 0.1 == pytest.approx(_numerical(f, v, key, d, eps=1e-7 if d == 1 else 1e-6), rel=1e-3, abs=1e-2)


def _analytic_sized(factor, values: gtsam.Values, sizes: dict[int, int]) -> list[np.ndarray]:
    A, _ = factor.linearize(values).jacobian()
    out, col = [], 0
    for key in factor.keys():
        d = sizes.get(key, 5 if key == INTRINSICS else 6)
        out.append(A[:, col:col + d])
        col += d
    return out


def test_corner_factor_corrects_the_lenss_radial_distortion_error():
    """Corners undistorted through a camera file whose k1, k2 are off by (dk1, dk2) reproject
    through the factor's correction to first order, and its Jacobian is the basis."""
    import cv2

    from estimation.rig_model import DISTORTION, distortion_prior_sigmas, radial_basis, undistort_px

    v = gtsam.Values()
    cam = Pose3()
    tag = Pose3(Rot3.Rx(np.pi), np.array([1.3, 0.7, 2.0]))      # facing the camera, near the frame's corner
    v.insert(C, cam)
    v.insert(T, tag)
    local = tag_object_points(0.1)
    file_dist = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
    dk = distortion_prior_sigmas(0.3, K)            # a lens 0.3 px off at the corners in each term
    true_dist = file_dist + np.r_[dk, 0.0, 0.0, 0.0]
    pts = np.array([cam.transformTo(tag.transformFrom(p)) for p in local])
    raw, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, true_dist)
    meas = undistort_px(raw.reshape(4, 2), K, file_dist)
    v.insert(DISTORTION, np.zeros(2))
    f0 = corner_factor(C, T, meas, local, 0.1, robust_k=None, fixed=cal3_s2(K),
                       distortion=(DISTORTION, radial_basis(meas, K)))
    assert list(f0.keys()) == [C, T, DISTORTION]
    before = np.abs(f0.unwhitenedError(v)).max()
    v.update(DISTORTION, np.r_[dk])
    after = np.abs(f0.unwhitenedError(v)).max()
    assert before > 0.05 and after < 0.1 * before
    for key, J in zip(f0.keys(), _analytic_sized(f0, v, {DISTORTION: 2})):
        d = 2 if key == DISTORTION else 6
        assert J * 0.1 == pytest.approx(_numerical(f0, v, key, d, eps=1e-8 if d == 2 else 1e-6), rel=1e-3, abs=1e-2)
