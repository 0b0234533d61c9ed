"""A run's graph reads its corners through the intrinsics its rig survey estimated, and holds them
as a variable under the survey's joint prior (`SfGraphSlam.free_intrinsics`): the survey's
uncertainty about them reaches every tag's covariance, and the run's views refine them.  Held at
the survey's estimate instead, an N = 6 run's top layer came out 0.7 mm off at a NEES of 3.6
(docs/sf_graphslam.md, "The intrinsics")."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from estimation.rig_model import GAUGE_SIGMA, INTRINSICS
from estimation.sf_graphslam import SfGraphSlam, SlamConfig
from lab.core.geometry import Pose3
from test_slam_step_exact import GEOM, K, MODEL, _calibration, _view

TAGS = (0, 1, 2, 9, 13, 36, 37, 38, 47)
# the camera as it truly is: the survey's estimate (K) off by about its own 1-sigma (_calibration:
# 1 px in focal length, 0.5 px in the principal point)
TRUE_K = K + np.array([[1.0, 0.0, 0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 0.0]])


def _views(seed: int):
    """Three steps of two views of the 3x3x3's tags, the rig at its nominal geometry, the corners
    imaged through TRUE_K with 0.05 px noise (the graph is told K)."""
    rng = np.random.default_rng(seed)
    return [[_view(a, TAGS, rng, TRUE_K) for a in angles] for angles in ((-0.6, -0.3), (0.0, 0.3), (0.6, 0.9))]


def _survey(k_sigma: tuple[float, float] = (1.0, 0.5)) -> np.ndarray:
    """A survey's joint covariance that knows the rig to what a survey gives (axis, base and mount
    to 0.05-0.1 mrad and 0.1-0.3 mm, the turntable tags to their glue) and the intrinsics to
    `k_sigma` (focal length, principal point; px)."""
    cal = _calibration()
    joint = np.array(cal.joint_covariance)
    for at, rad, m in ((0, 1e-4, 1e-4), (6, 1e-4, 3e-4), (12, 5e-5, 1e-4)):
        joint[at:at + 6, at:at + 6] = np.diag([rad ** 2] * 3 + [m ** 2] * 3)
    joint[2, 2] = joint[5, 5] = GAUGE_SIGMA ** 2                # the axis frame's yaw and height: gauge
    f, c = k_sigma
    joint[18:23, 18:23] = np.diag([f ** 2, f ** 2, 1e-8, c ** 2, c ** 2])
    return joint


def _run(seed: int, free: bool, k_sigma: tuple[float, float] = (1.0, 0.5)) -> SfGraphSlam:
    cal = replace(_calibration(), joint_covariance=_survey(k_sigma))
    slam = SfGraphSlam(MODEL, SlamConfig(semantic=False, observation="corners", corner_sigma_px=0.05),
                       rig=GEOM, calibration=cal, camera=(K, np.zeros(5)))
    assert slam.free_intrinsics
    slam.free_intrinsics = free
    for views in _views(seed):
        for cam, dets, motion in views:
            slam.add_view(cam, dets, motion)
        slam.update()
    return slam


def _position_nees(slam: SfGraphSlam) -> np.ndarray:
    out = []
    for t in sorted(slam.tags):
        if MODEL.tags[t].module == "turntable":
            continue
        est, truth = slam.tag_pose(t), MODEL.tags[t].structure_T_tag
        e = est.rotation().unrotate(truth.translation() - est.translation())      # in the tag's frame
        cov = slam.tag_covariance(t)[3:, 3:]
        out.append(float(e @ np.linalg.solve(cov, e)))
    return np.array(out)


def test_the_corner_factors_read_the_intrinsics_variable_of_a_calibrated_run():
    slam = _run(0, free=True)
    corners = [slam.graph.at(i) for i in range(slam.graph.size())
               if isinstance(slam.graph.at(i), gtsam.CustomFactor) and slam.graph.at(i).dim() == 8]
    assert corners and all(INTRINSICS in f.keys() for f in corners)
    assert INTRINSICS not in list(slam._linear_keys())      # relinearised like any other variable


def test_a_survey_error_within_its_sigma_is_covered_not_read_as_exact():
    """Over several noise draws the structure tags' errors against the truth stay within their
    1-sigma with the intrinsics a variable; held at the survey's estimate they do not."""
    free = np.concatenate([_position_nees(_run(seed, free=True)) for seed in range(4)])
    held = np.concatenate([_position_nees(_run(seed, free=False)) for seed in range(4)])
    assert len(free) >= 20
    assert free.mean() < 6.0                      # 3 when the covariance is right (measured: 0.5)
    assert held.mean() > 9.0                      # measured: 18


def test_the_runs_views_refine_the_intrinsics_and_a_tight_prior_adds_nothing():
    slam = _run(0, free=True)
    prior = np.sqrt(np.diag(_survey()[18:23, 18:23]))
    sigma = np.sqrt(np.diag(slam.isam.marginalCovariance(INTRINSICS)))
    assert sigma[0] < 0.9 * prior[0] and sigma[3] < 0.9 * prior[3]
    # a survey that knew the intrinsics exactly: the same tag covariances as holding them
    tight_free, tight_held = _run(0, free=True, k_sigma=(1e-4, 1e-4)), _run(0, free=False, k_sigma=(1e-4, 1e-4))
    for t in sorted(tight_free.tags):
        assert tight_free.tag_covariance(t) == pytest.approx(tight_held.tag_covariance(t), rel=1e-3, abs=1e-14)


def test_a_variable_of_a_kind_without_a_relinearisation_threshold_is_refused():
    """iSAM2 looks each variable's threshold up by its key's character: a kind the map lacks would
    read past its end, so the graph refuses it when the variable is made."""
    slam = SfGraphSlam(MODEL, SlamConfig(observation="corners"), camera=(K, np.zeros(5)))
    with pytest.raises(ValueError, match="relinearisation threshold"):
        slam._value(gtsam.symbol("x", 0), Pose3())


def _distorted(points: np.ndarray, K_true: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Pixels of normalised `points` (n, 2) through a lens `dist` and the pinhole `K_true`."""
    import cv2

    p3 = np.column_stack([points, np.ones(len(points))])
    px, _ = cv2.projectPoints(p3, np.zeros(3), np.zeros(3), K_true, dist)
    return px.reshape(-1, 2)


def test_corners_undistorted_through_the_survey_move_with_the_intrinsics_as_undistorting_through_them_would():
    # A tag near the frame's corner through the sim's lens (k1 = -0.05: ~20 px of distortion
    # there), undistorted through a survey's K.  Read through intrinsics 0.5-1 px away, the basis
    # gives the corners undistortion through those gives, to a hundredth of what it corrects.
    from estimation.rig_model import intrinsics_basis_many, undistort_px

    dist = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
    norm = np.array([[-0.62, -0.33], [-0.57, -0.33], [-0.57, -0.28], [-0.62, -0.28]])
    raw = _distorted(norm, TRUE_K, dist)
    B = intrinsics_basis_many(raw[None], K, dist)[0]
    K2 = K + np.array([[0.8, 0.0, -0.6], [0.0, -1.0, 0.7], [0.0, 0.0, 0.0]])
    delta = np.array([0.8, -1.0, 0.0, -0.6, 0.7])               # fx, fy, s, u0, v0
    moved = undistort_px(raw, K2, dist).ravel() - undistort_px(raw, K, dist).ravel()
    predicted = B @ delta
    assert np.abs(predicted).max() > 0.01                     # the distortion's share is not nothing
    # to first order (OpenCV's undistortion iterates to ~1e-4 px near the frame's corner)
    assert np.abs(moved - predicted).max() < 0.01 * np.abs(moved).max()


def test_a_corner_factor_with_the_intrinsics_basis_reads_its_corners_through_the_estimate():
    # The factor's error and its Jacobian on the intrinsics, against the exact model: the pinhole
    # prediction less the raw corners undistorted through the intrinsics being evaluated.
    from estimation.rig_model import INTRINSICS as KEY, cal3_s2, corner_factor, intrinsics_basis_many, undistort_px
    from estimation.fiducials import tag_object_points

    dist = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
    cam, tag = gtsam.symbol("c", 0), gtsam.symbol("t", 0)
    camera = Pose3()
    T = Pose3(gtsam.Rot3.Rx(np.pi + 0.2), np.array([-1.3, -0.7, 2.2]))
    local = tag_object_points(0.1)
    pin = np.array([(T.transformFrom(p)[:2] / T.transformFrom(p)[2]) for p in local])
    raw = _distorted(pin, TRUE_K, dist)
    u = undistort_px(raw, K, dist)
    k_ref = np.array([K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]])
    f = corner_factor(cam, tag, u, local, 0.1, robust_k=None, intrinsics_basis=(intrinsics_basis_many(raw[None], K, dist)[0], k_ref))
    v = gtsam.Values()
    v.insert(cam, camera)
    v.insert(tag, T)

    def exact(kvec: np.ndarray) -> np.ndarray:
        Kx = np.array([[kvec[0], kvec[2], kvec[3]], [0.0, kvec[1], kvec[4]], [0.0, 0.0, 1.0]])
        return ((Kx[:2, :2] @ pin.T).T + Kx[:2, 2] - undistort_px(raw, Kx, dist)).ravel()

    kv = k_ref + np.array([0.9, 0.9, 0.0, 0.4, -0.6])
    v.insert(KEY, cal3_s2(np.array([[kv[0], kv[2], kv[3]], [0.0, kv[1], kv[4]], [0.0, 0.0, 1.0]])))
    e = f.unwhitenedError(v)
    assert np.abs(e - exact(kv)).max() < 1e-4
    # the skew is left out: the basis holds it a property of the pinhole alone (OpenCV normalises
    # without it), so its column is the pinhole's, not the exact model's
    J = f.linearize(v).jacobian()[0][:, 12:17] * 0.1         # whitened by the sigma: back to px
    num = np.column_stack([(exact(kv + h) - exact(kv - h)) / 2e-3 for h in np.eye(5)[[0, 1, 3, 4]] * 1e-3])
    assert np.abs(J[:, [0, 1, 3, 4]] - num).max() < 1e-3
