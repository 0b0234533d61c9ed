"""The rig inside the factor graph: every view's camera pose is a function of the commanded turntable
angle and Stewart pose and of calibration variables the whole run shares.

    structure_T_camera(k) = structure_T_world(0) · A · Rz(-a_k) · A^-1 · lift(h_k) · B · H_k · M

(the letters are docs/sf_graphslam.md's; the code calls each by what it is, as below)

- A = `world_T_axis`: the turntable's true axis is A's z axis.  Only its tilt (rotation about x, y)
  and offset (x, y) are observable; its yaw and height are pinned at zero by a tight prior (they
  are the gauge of "where on the axis, at which encoder zero").  The world frame is where the plate
  sits at encoder zero, so structure_T_world(0) is the design's.
- B = `world_T_base` (Stewart base) at lift height 0, M = `platform_T_camera` (camera mount), both
  6-dof.
- Rz(-a_k) = `turn`: the view's turntable angle a_k, seen from the plate (which turned).
- lift(h) = L · Tz(h) · L^-1 (Tz(h) = `rise`), a pure translation by h along L's z axis: a rig with
  a lift carries the Stewart base along its travel, whose direction is L's z axis (L =
  `world_T_lift`; only its tilt is observable, its yaw and position are gauge, pinned by a tight
  prior).  A view at h = 0 has lift(0) = identity: its factor is the four-key one, and a run that
  never moves the lift has no L variable at all (its graph is the one it was before the lift existed).
- H_k = `base_T_platform` = home · stewart_pose_k: the platform pose the controller was told (legs
  are exact; their per-move repeatability is the chain factor's noise, with the turntable's).

`chain_factor` is one GTSAM `CustomFactor` per view on (A, B, M, C_k), and L for a lifted view (the
same factor: without a lift term its chain is the one above with lift(h) left out, not multiplied by
an identity, so a rig or a view without a lift pays nothing for it): the view's camera variable
stays, so tag observations remain plain C++ `BetweenFactorPose3`s and only one Python factor per
view is added.  Its noise is the devices' repeatability, propagated to the camera at the prior.

`corner_factor` is the reprojection of a tag's four corners through a pinhole camera whose
intrinsics (Cal3_S2) are a variable too: the rig calibration survey (`estimation.rig_calibration_solve`)
uses it to carry the focal length and principal point, which a pose measurement cannot separate
from the tag's depth.  Corners come undistorted with the camera file's distortion, so the
intrinsics here are the distortion-free part only.

Verification cannot buy a verdict with these variables: a module's tags are fresh variables with
no prior, so before their own semantic factors join they carry no information about A, B or M;
the calibration is fixed by the turntable tags and the modules already tied.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Sequence

import gtsam
import numpy as np

from lab.core.config import CalibrationConfig, Rig
from lab.core.geometry import Pose3, Rot3, from_xyzrpy
from lab.core.rig_calibration_file import RigCalibration

from estimation import corner_kernel

AXIS, BASE, MOUNT, INTRINSICS, LIFT = (gtsam.symbol(c, 0) for c in "abmkl")
# the true lens's radial distortion against the camera file's: (dk1, dk2), a 2-vector variable
DISTORTION = gtsam.symbol("d", 0)
_ABOUT_Z = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])    # a rotation about z, in GTSAM's tangent
GAUGE_SIGMA = 1e-7
# scratch the kernel writes no Jacobians into when none are wanted, and the lens of a factor without one
_J6, _J1, _J5, _NO_LENS = np.empty((8, 6)), np.empty((8, 1)), np.empty((8, 5)), np.zeros(0)


@dataclass(frozen=True)
class ViewMotion:
    """What the rig was told for one view."""

    turntable_rad: float
    stewart_pose: tuple[float, ...]     # (x, y, z, roll, pitch, yaw) relative to home
    lift_m: float = 0.0                 # the lift's height (0 without a lift)


@dataclass(frozen=True)
class RigGeometry:
    """What the estimator knows of the rig: the rig file's nominal poses and its uncertainties."""

    structure_T_world0: Pose3           # the design's structure frame at encoder zero, inverted
    home_m: np.ndarray
    nominal_world_T_base: Pose3
    nominal_platform_T_camera: Pose3
    K: np.ndarray                       # the camera file's intrinsics
    config: CalibrationConfig

    @staticmethod
    def from_rig(rig: Rig, world_T_structure0: Pose3, K: np.ndarray) -> RigGeometry:
        assert rig.stewart is not None and rig.camera is not None
        return RigGeometry(world_T_structure0.inverse(), np.asarray(rig.stewart.geometry.home_m, float),
                           rig.stewart.world_T_base, rig.camera.platform_T_camera, np.asarray(K, float),
                           rig.calibration)

    def base_T_platform(self, motion: ViewMotion) -> Pose3:
        """H_k: the platform where the controller was told to put it (home, then the commanded pose)."""
        return Pose3(Rot3(), self.home_m).compose(from_xyzrpy(motion.stewart_pose))

    @staticmethod
    def lifted(motion: ViewMotion, world_T_base: Pose3, world_T_lift: Pose3 | None = None) -> Pose3:
        """The Stewart base carried to the view's lift height along the lift's z axis."""
        if not motion.lift_m:
            return world_T_base
        world_T_lift = world_T_lift if world_T_lift is not None else Pose3()
        return world_T_lift.compose(rise(motion)).compose(world_T_lift.inverse()).compose(world_T_base)

    def predict(self, motion: ViewMotion, world_T_axis: Pose3, world_T_base: Pose3, platform_T_camera: Pose3,
                world_T_lift: Pose3 | None = None) -> Pose3:
        """structure_T_camera for a view, given calibration values."""
        return (self.structure_T_world0.compose(world_T_axis).compose(turn(motion)).compose(world_T_axis.inverse())
                .compose(self.lifted(motion, world_T_base, world_T_lift)).compose(self.base_T_platform(motion))
                .compose(platform_T_camera))

    def predict_nominal(self, motion: ViewMotion) -> Pose3:
        return self.predict(motion, Pose3(), self.nominal_world_T_base, self.nominal_platform_T_camera)

    # ---- priors ---------------------------------------------------------------------------------
    def priors(self, calibration: RigCalibration | None) -> tuple[dict[int, Pose3], dict[int, np.ndarray]]:
        """Prior means and covariances of A, B, M: a rig calibration file's, or the rig file's
        nominal values with the `[calibration]` table's sigmas."""
        c = self.config
        if calibration is not None:
            axis_cov = calibration.covariance["world_T_axis"].copy()
            axis_cov[[2, 5], :] = 0.0
            axis_cov[:, [2, 5]] = 0.0
            axis_cov[2, 2] = axis_cov[5, 5] = GAUGE_SIGMA ** 2
            means = {AXIS: calibration.world_T_axis, BASE: calibration.world_T_base, MOUNT: calibration.platform_T_camera}
            covs = {AXIS: axis_cov, BASE: calibration.covariance["world_T_base"],
                    MOUNT: calibration.covariance["platform_T_camera"]}
        else:
            # isotropic per block, so the same in the pose's own tangent as in its parent's axes
            means = {AXIS: Pose3(), BASE: self.nominal_world_T_base, MOUNT: self.nominal_platform_T_camera}
            covs = {AXIS: np.diag([c.turntable_axis_sigma_rad, c.turntable_axis_sigma_rad, GAUGE_SIGMA,
                                   c.turntable_axis_sigma_m, c.turntable_axis_sigma_m, GAUGE_SIGMA]) ** 2,
                    BASE: np.diag([c.stewart_base_sigma_rad] * 3 + [c.stewart_base_sigma_m] * 3) ** 2,
                    MOUNT: np.diag([c.camera_mount_sigma_rad] * 3 + [c.camera_mount_sigma_m] * 3) ** 2}
        return means, covs

    def lift_prior(self) -> tuple[Pose3, np.ndarray]:
        """The lift's axis: vertical, known to the [calibration] lift_axis_sigma in tilt; its yaw
        and position are gauge (they do not change lift(h))."""
        tilt = self.config.lift_axis_sigma_rad
        return Pose3(), np.diag([tilt, tilt, GAUGE_SIGMA, GAUGE_SIGMA, GAUGE_SIGMA, GAUGE_SIGMA]) ** 2

    def _stewart_term(self, platform_T_camera: Pose3) -> np.ndarray:
        """The Stewart platform's repeatability carried to the camera's tangent."""
        c = self.config
        platform_to_camera = platform_T_camera.inverse().AdjointMap()     # a platform twist, in the camera's tangent
        stewart_cov = np.diag([c.stewart_repeatability_rad] * 3 + [c.stewart_repeatability_m] * 3) ** 2
        return platform_to_camera @ stewart_cov @ platform_to_camera.T

    @functools.cached_property
    def _nominal_stewart_term(self) -> np.ndarray:
        """`_stewart_term` at the nominal mount: the same for every view of a run, so computed once
        (a run builds a chain factor per view; the same numbers bit for bit)."""
        term = self._stewart_term(self.nominal_platform_T_camera)
        term.flags.writeable = False
        return term

    def chain_noise(self, motion: ViewMotion, platform_T_camera: Pose3 | None = None) -> gtsam.noiseModel.Base:
        """The devices' repeatability, propagated to the camera pose (its tangent).  A lifted view
        adds the lift carriage's: a translation of the base, isotropic, so the same in the camera's
        axes."""
        c = self.config
        if platform_T_camera is None:
            platform_T_camera = self.nominal_platform_T_camera
            stewart_term = self._nominal_stewart_term
        else:
            stewart_term = self._stewart_term(platform_T_camera)
        axis_T_camera = self.nominal_world_T_base.compose(self.base_T_platform(motion)).compose(platform_T_camera)
        per_turn = -axis_T_camera.inverse().AdjointMap() @ _ABOUT_Z    # the camera's motion per rad of turntable error
        cov = (stewart_term
               + c.turntable_repeatability_rad ** 2 * np.outer(per_turn, per_turn) + np.eye(6) * 1e-12)
        if motion.lift_m:
            cov[3:, 3:] += np.eye(3) * c.lift_repeatability_m ** 2
        return gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T))


def turn(motion: ViewMotion) -> Pose3:
    """Rz(-a_k): the view's turntable angle, as the camera sees the plate turn under it."""
    return Pose3(Rot3.Rz(-motion.turntable_rad), np.zeros(3))


def rise(motion: ViewMotion) -> Pose3:
    """Tz(h_k): the view's lift height, along the lift frame's z axis."""
    return Pose3(Rot3(), np.array([0.0, 0.0, motion.lift_m]))


def chain_factor(geometry: RigGeometry, motion: ViewMotion, camera_key: int,
                 noise: gtsam.noiseModel.Base | None = None, *, lift_key: int | None = None) -> gtsam.CustomFactor:
    """e = Log(P^-1 · C) with P the chain's prediction of structure_T_camera C; Jacobians by the
    adjoint (checked against numerical derivatives in tests/test_rig_model.py).  Keys A, B, M, C;
    and L (`lift_key`, by default LIFT for a lifted view and none at h = 0).

    A right perturbation of a frame that appears as X · W · X^-1 (A about the turn, L about the
    rise) moves P by (Ad(after-first^-1) - Ad(after-second^-1)) of it.  Without a lift term the chain
    is the one with lift(h) left out, computed exactly as before the lift existed; with one at h = 0
    it gives the same error and Jacobians and a zero Jacobian on L (tests/test_rig_model.py)."""
    if lift_key is None and motion.lift_m:
        lift_key = LIFT
    structure_T_world0 = geometry.structure_T_world0
    turn_k = turn(motion)
    rise_k = rise(motion)
    base_T_platform = geometry.base_T_platform(motion)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
        world_T_axis = values.atPose3(AXIS)
        world_T_base = values.atPose3(BASE)
        platform_T_camera = values.atPose3(MOUNT)
        structure_T_camera = values.atPose3(camera_key)
        # each product is the chain after one letter: H M, (L^-1 ... M, Tz ... M,) A^-1 ... M, Rz ... M
        base_T_camera = base_T_platform.compose(platform_T_camera)
        if lift_key is None:
            axis_T_camera = world_T_axis.inverse().compose(world_T_base).compose(base_T_camera)
        else:
            world_T_lift = values.atPose3(lift_key)
            lift_T_camera = world_T_lift.inverse().compose(world_T_base).compose(base_T_camera)
            raised_lift_T_camera = rise_k.compose(lift_T_camera)
            axis_T_camera = world_T_axis.inverse().compose(world_T_lift).compose(raised_lift_T_camera)
        turned_axis_T_camera = turn_k.compose(axis_T_camera)  # the camera in the axis frame turned with the plate
        predicted = structure_T_world0.compose(world_T_axis).compose(turned_axis_T_camera)
        predicted_T_camera = predicted.inverse().compose(structure_T_camera)
        e = Pose3.Logmap(predicted_T_camera)
        if jacobians is not None:
            d_log = Pose3.LogmapDerivative(e)          # d Log(P^-1 C Exp(x)) / dx
            d_predicted = -d_log @ predicted_T_camera.inverse().AdjointMap()
            jacobians[0] = d_predicted @ (turned_axis_T_camera.inverse().AdjointMap()
                                          - axis_T_camera.inverse().AdjointMap())
            jacobians[1] = d_predicted @ base_T_camera.inverse().AdjointMap()
            jacobians[2] = d_predicted
            jacobians[3] = d_log
            if lift_key is not None:
                jacobians[4] = d_predicted @ (raised_lift_T_camera.inverse().AdjointMap()
                                              - lift_T_camera.inverse().AdjointMap())
        return e

    keys = [AXIS, BASE, MOUNT, camera_key] + ([] if lift_key is None else [lift_key])
    return gtsam.CustomFactor(noise or geometry.chain_noise(motion), keys, error)


def cal3_s2(K: np.ndarray) -> gtsam.Cal3_S2:
    return gtsam.Cal3_S2(float(K[0, 0]), float(K[1, 1]), float(K[0, 1]), float(K[0, 2]), float(K[1, 2]))


def radial_basis(corners_px: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(8, 2): how the four undistorted corners move per unit of (dk1, dk2), the true lens's radial
    terms minus the camera file's.  To first order an undistorted point through the file's model
    is off the true one by -f x_n (dk1 r^2 + dk2 r^4) (x_n, r normalised, from the corner itself)."""
    u = np.asarray(corners_px, float).reshape(4, 2)
    f = np.array([K[0, 0], K[1, 1]])
    xn = (u - np.array([K[0, 2], K[1, 2]])) / f
    r2 = np.sum(xn ** 2, axis=1, keepdims=True)
    G = np.zeros((8, 2))
    G[:, 0] = (-f * xn * r2).ravel()
    G[:, 1] = (-f * xn * r2 ** 2).ravel()
    return G


# the step of `intrinsics_basis_many`'s central differences (px): the undistortion is smooth in K
# (OpenCV's fixed-point iteration leaves up to ~1e-4 px near the frame's corners, but an error that
# changes smoothly with K and cancels in the difference); over 1 px of K the first-order reading is
# within 1 % of undistorting again (tests/test_free_intrinsics.py)
_K_STEP_PX = 0.01


def intrinsics_basis_many(corners_px: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(n, 8, 5): how each tag's corners as `undistort_px` gives them (raw (n, 4, 2) through K and
    `dist`) move per unit of the intrinsics (fx, fy, s, u0, v0), by central differences.  A graph
    whose intrinsics are a variable reads the corners it was given, undistorted through the
    survey's K, as if undistorted through its own estimate: to first order they are the corners
    plus this basis times the difference (`corner_factor`'s `intrinsics_basis`).  Without it, the
    distortion removed through the survey's K stays in every corner however far the estimate moves,
    the same way in every sighting: a spring back to the survey's intrinsics that the graph grows
    surer of with every view (docs/sf_graphslam.md, "The intrinsics")."""
    raw = np.asarray(corners_px, float).reshape(-1, 2)
    K = np.asarray(K, float)
    out = np.zeros((len(raw) // 4, 8, 5))
    # fx, fy, u0, v0 in K; the skew's column stays zero: OpenCV normalises without it and puts it
    # back only in the output pinhole, so its difference would be the skew's whole pinhole term
    # and cancel the factor's own, where the skew is a (zero) property of the pinhole alone
    for j, (r, c) in ((0, (0, 0)), (1, (1, 1)), (3, (0, 2)), (4, (1, 2))):
        lo, hi = K.copy(), K.copy()
        lo[r, c] -= _K_STEP_PX
        hi[r, c] += _K_STEP_PX
        out[:, :, j] = ((undistort_px(raw, hi, dist) - undistort_px(raw, lo, dist)) / (2 * _K_STEP_PX)).reshape(-1, 8)
    return out


def radial_basis_many(corners_px: np.ndarray, K: np.ndarray) -> np.ndarray:
    """`radial_basis` of many tags' corners at once: (n, 4, 2) -> (n, 8, 2), the same numbers."""
    u = np.asarray(corners_px, float).reshape(-1, 4, 2)
    f = np.array([K[0, 0], K[1, 1]])
    xn = (u - np.array([K[0, 2], K[1, 2]])) / f
    r2 = np.sum(xn ** 2, axis=2, keepdims=True)
    G = np.empty((len(u), 8, 2))
    G[:, :, 0] = (-f * xn * r2).reshape(-1, 8)
    G[:, :, 1] = (-f * xn * r2 ** 2).reshape(-1, 8)
    return G


def distortion_prior_sigmas(sigma_px: float, K: np.ndarray) -> np.ndarray:
    """Prior sigmas of (dk1, dk2) that move a point at the frame's corner by `sigma_px` each (the
    corner taken where the principal point is the frame's centre)."""
    rc = math.hypot(K[0, 2] / K[0, 0], K[1, 2] / K[1, 1])
    f = 0.5 * (K[0, 0] + K[1, 1])
    return np.array([sigma_px / (f * rc ** 3), sigma_px / (f * rc ** 5)])


def _cal_vector(K: gtsam.Cal3_S2) -> np.ndarray:
    return np.asarray(K.vector(), float)       # fx, fy, s, u0, v0


def project_corners(world_T_camera: Pose3, world_T_tag: Pose3, local: np.ndarray, cal: np.ndarray,
                    meas: np.ndarray, want_jacobians: bool = True, want_calibration: bool = False
                    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """Reprojection error (8,) of a tag's four corners (`local`, (4, 3) in the tag frame as
    printed) through the pinhole `cal` = (fx, fy, s, u0, v0), and its Jacobians against the camera
    pose and the tag pose (GTSAM's tangent, rotation first) and, with `want_calibration`, the
    calibration.  All four corners in one pass of numpy: the graph calls this once per corner
    factor per relinearisation, and a loop of gtsam's per-point projections costs twice as much.
    A corner behind the camera gets a large flat error and no gradient, as gtsam's does."""
    camera_T_tag = world_T_camera.between(world_T_tag)
    m = camera_T_tag.matrix()
    q = local @ m[:3, :3].T + m[:3, 3]                   # (4, 3) corners in the camera frame
    z = q[:, 2]
    ok = z > 0
    iz = np.where(ok, 1.0 / np.where(ok, z, 1.0), 0.0)
    x, y = q[:, 0] * iz, q[:, 1] * iz
    fx, fy, sk, u0, v0 = cal
    e = np.empty(8)
    e[0::2] = fx * x + sk * y + u0 - meas[:, 0]
    e[1::2] = fy * y + v0 - meas[:, 1]
    if not ok.all():
        e[np.repeat(~ok, 2)] = 1e3
    if not want_jacobians:
        return e, None, None, None
    # the normalised image point against the camera's own motion (the classic interaction
    # matrix), then through the calibration; the tag moves the relative pose camera_T_tag from
    # the other side, so its Jacobian is the camera's through -Ad(camera_T_tag)
    xy = x * y
    Ju = np.stack([xy, -(1.0 + x * x), y, -iz, np.zeros(4), x * iz], axis=1)
    Jv = np.stack([1.0 + y * y, -xy, -x, np.zeros(4), -iz, y * iz], axis=1)
    JC = np.empty((8, 6))
    JC[0::2] = fx * Ju + sk * Jv
    JC[1::2] = fy * Jv
    if not ok.all():
        JC[np.repeat(~ok, 2)] = 0.0
    JT = -JC @ camera_T_tag.AdjointMap()
    JK = None
    if want_calibration:
        JK = np.zeros((8, 5))
        JK[0::2, 0], JK[0::2, 2], JK[0::2, 3] = x, y, 1.0
        JK[1::2, 1], JK[1::2, 4] = y, 1.0
        JK[np.repeat(~ok, 2)] = 0.0
    return e, JC, JT, JK


def corner_factor(camera_key: int, tag_key: int, corners_px: np.ndarray, tag_corners_m: np.ndarray,
                  sigma_px: float, intrinsics_key: int = INTRINSICS,
                  robust_k: float | None = 3.0, fixed: gtsam.Cal3_S2 | None = None,
                  scale_key: int | None = None, distortion: tuple[int, np.ndarray] | None = None,
                  intrinsics_basis: tuple[np.ndarray, np.ndarray] | None = None) -> gtsam.CustomFactor:
    """Reprojection error (8-vector, px) of a tag's four corners.  `corners_px`: (4, 2)
    undistorted measurements in pixels of the nominal pinhole; `tag_corners_m`: (4, 3) the
    corners in the tag frame, in the same order.  With `fixed` intrinsics the factor is on the
    camera and the tag only (a run: the intrinsics come from the rig calibration).  With
    `scale_key` the tag as printed is (1 + s) times its nominal size, s a 1-vector variable (a
    printer's scale error moves a tag seen from one side along the line of sight by s x distance).
    With `distortion` = (key, radial_basis(corners)) the measured corners are corrected by the
    lens's radial distortion error, a 2-vector variable shared by every sighting.  With
    `intrinsics_basis` = (B, K_ref) (variable intrinsics only: `intrinsics_basis_many`) the
    corners were undistorted through K_ref, and move by B (K - K_ref) with the intrinsics K: the
    lens's distortion acts on normalised coordinates, which the intrinsics define."""
    meas = np.asarray(corners_px, dtype=float).reshape(4, 2)
    if intrinsics_basis is not None and fixed is not None:
        raise ValueError("an intrinsics basis needs the intrinsics as a variable (fixed= was given)")
    local = np.asarray(tag_corners_m, dtype=float).reshape(4, 3)
    noise: gtsam.noiseModel.Base = gtsam.noiseModel.Isotropic.Sigma(8, sigma_px)
    if robust_k:
        noise = gtsam.noiseModel.Robust.Create(_huber(robust_k), noise)
    fixed_K = None if fixed is None else _cal_vector(fixed)
    lens_basis = None if distortion is None else np.asarray(distortion[1], float)

    error = _corner_error(camera_key, tag_key, None if fixed is not None else intrinsics_key, meas, local, fixed_K,
                          scale_key, None if distortion is None else (distortion[0], lens_basis), intrinsics_basis)
    keys = [camera_key, tag_key] if fixed is not None else [camera_key, tag_key, intrinsics_key]
    if scale_key is not None:
        keys.append(scale_key)
    if distortion is not None:
        keys.append(distortion[0])
    return gtsam.CustomFactor(noise, keys, error)


@dataclass(frozen=True)
class CornerSighting:
    """One tag's corners in one view, as `corner_factor` takes them (intrinsics fixed)."""

    tag_key: int
    scale_key: int | None
    corners_px: np.ndarray            # (4, 2) undistorted, px
    tag_corners_m: np.ndarray         # (4, 3) in the tag frame, nominal size
    sigma_px: float
    lens_basis: np.ndarray | None     # (8, 2) radial_basis of the corners, with the lens variable


class PoseTable:
    """Every pose of one `gtsam.Values` as an (n, 4, 4) array, read in one call
    (`gtsam.utilities.extractPose3`), for factors that read many poses a callback.

    A view factor reads its camera and each of its tags, two pybind11 calls a pose (~1 us each):
    in an 8x8x8 batch solve, 62,000 reads.  The batch solve (`view_batch.ViewBatch`) `load`s each
    values it is about to evaluate the graph at; a factor given the table reads from it only when
    the values it is called with *are* the loaded ones (the same Python object: GTSAM passes the
    caller's wrapper through), and reads the values itself otherwise, so a stale or foreign table
    can cost time, never correctness.  The values must not change while loaded (an optimizer's do
    not).  `track` fixes which poses the table holds (a solve's start); a factor re-reads its rows
    when that changes."""

    def __init__(self) -> None:
        self.keys = np.zeros(0, np.uint64)
        self.row: dict[int, int] = {}
        self.generation = 0
        self.values: gtsam.Values | None = None
        self.poses = np.zeros((0, 4, 4))

    def track(self, values: gtsam.Values) -> None:
        """Hold the poses of `values` (their keys, in `extractPose3`'s order) from now on."""
        keys = np.array(gtsam.utilities.allPose3s(values).keys(), dtype=np.uint64)
        self.values = None
        if not np.array_equal(keys, self.keys):
            self.keys = keys
            self.row = {int(k): i for i, k in enumerate(keys)}
            self.generation += 1
            self.poses = np.zeros((len(keys), 4, 4))
            self.poses[:, 3, 3] = 1.0

    def load(self, values: gtsam.Values) -> None:
        """Read every pose of `values`, which hold the tracked poses."""
        flat = gtsam.utilities.extractPose3(values)
        if flat.shape[0] != len(self.keys):
            raise ValueError(f"a pose table of {len(self.keys)} poses loaded with values holding {flat.shape[0]}")
        self.poses[:, :3, :3] = flat[:, :9].reshape(-1, 3, 3)
        self.poses[:, :3, 3] = flat[:, 9:]
        self.values = values

    def clear(self) -> None:
        self.values = None


@dataclass(frozen=True)
class ViewLayout:
    """What `corner_kernel.view_errors` needs of one view factor besides the values: its keys and
    the column each key's block starts at, the kernel's `columns` and each tag's packed constants,
    1/sigma and key (`corner_view_factor`, `view_batch.ViewBatch`)."""

    camera_key: int
    sightings: tuple[CornerSighting, ...]
    keys: tuple[int, ...]              # the camera, each tag and its scale (if any), the lens (if any)
    starts: tuple[int, ...]            # the column each key's block starts at, then the width
    columns: np.ndarray                # (n + 1, 2) `view_errors`' columns
    consts: np.ndarray                 # (n, corner_kernel.SIZE)
    inverse_sigma: np.ndarray          # (n,)
    huber_k: float                     # <= 0: no kernel
    lens_key: int | None

    @property
    def width(self) -> int:
        return int(self.starts[-1])

    @property
    def tag_keys(self) -> list[int]:
        return [s.tag_key for s in self.sightings]


def view_layout(camera_key: int, sightings: Sequence[CornerSighting], robust_k: float | None,
                lens_key: int | None = None) -> ViewLayout:
    """One view's `ViewLayout` (the checks `corner_view_factor` states).  Plain Python for the
    columns: a batch builds thousands of these (2,760 at N = 8) before its first solve."""
    n = len(sightings)
    if n == 0 or any(s.lens_basis is not None for s in sightings) != (lens_key is not None):
        raise ValueError("a view factor needs its sightings, and a lens key exactly when they carry a lens basis")
    consts = corner_kernel.pack(np.array([s.corners_px for s in sightings], float).reshape(n, 4, 2),
                                np.array([s.tag_corners_m for s in sightings], float).reshape(n, 4, 3),
                                None if lens_key is None else
                                -np.array([s.lens_basis for s in sightings], float).reshape(n, 8, 2))
    # the factor's columns: the camera (6), then each tag's pose (6) and print scale (1), the lens (2)
    keys, starts, columns = [camera_key], [0], []
    at = 6
    for s in sightings:
        keys.append(s.tag_key)
        starts.append(at)
        tag_at = at
        at += 6
        if s.scale_key is None:
            columns.append((tag_at, -1))
        else:
            keys.append(s.scale_key)
            starts.append(at)
            columns.append((tag_at, at))
            at += 1
    if lens_key is None:
        columns.append((-1, -1))
    else:
        keys.append(lens_key)
        starts.append(at)
        columns.append((at, -1))
        at += 2
    starts.append(at)
    if len(set(keys)) != len(keys):
        raise ValueError("a view factor reads each tag once")
    return ViewLayout(camera_key, tuple(sightings), tuple(keys), tuple(starts), np.array(columns, np.int64), consts,
                      np.array([1.0 / s.sigma_px for s in sightings]), float(robust_k) if robust_k else 0.0,
                      lens_key)


def corner_view_factor(camera_key: int, sightings: Sequence[CornerSighting], fixed: gtsam.Cal3_S2,
                       robust_k: float | None, lens_key: int | None = None,
                       table: PoseTable | None = None) -> gtsam.CustomFactor:
    """The `corner_factor`s of one view's tags as one factor: the same error, the same whitened
    Jacobians row for row (each tag's Huber kernel applied to its own 8 rows), so a solve of the
    graph with it is the solve with the single factors (to round-off).  For the batch solve, whose
    Levenberg-Marquardt calls every factor back at every linearisation and error evaluation: one
    Python callback a view instead of one a tag, the tags' arithmetic in one compiled call
    (`corner_kernel.view_errors`).  Not for iSAM2: a variable that moves past the threshold would
    relinearise every tag of its views, and the factor ties the view's tags to each other in the
    Bayes tree.  With `table` the poses are read from it when it holds the values being evaluated
    (`PoseTable`)."""
    layout = view_layout(camera_key, sightings, robust_k, lens_key)
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(8 * len(layout.sightings)), list(layout.keys),
                              view_error_function(layout, fixed, table))


def view_error_function(layout: ViewLayout, fixed: gtsam.Cal3_S2, table: PoseTable | None = None):
    """`corner_view_factor`'s error function (GTSAM's `CustomFactor` callback) for `layout`."""
    sightings, camera_key, lens_key = layout.sightings, layout.camera_key, layout.lens_key
    n = len(sightings)
    consts, inverse_sigma, columns, huber_k = layout.consts, layout.inverse_sigma, layout.columns, layout.huber_k
    starts = layout.starts
    cal = _cal_vector(fixed)
    tag_keys = layout.tag_keys
    scale_keys = [(i, s.scale_key) for i, s in enumerate(sightings) if s.scale_key is not None]
    world_T_tags = np.empty((n, 4, 4))
    scales = np.zeros(n)
    ok = np.empty(n, np.bool_)
    view_errors = corner_kernel.view_errors
    camera_from_table = np.empty((4, 4), order="F")   # the layout `Pose3.matrix()` gives: one compiled kernel
    rows = np.zeros(n, np.int64)
    seen = [-1, 0]                                    # the table generation `rows` are of, the camera's row
    # one error and one Jacobian buffer a factor, reused: GTSAM copies both out as the callback
    # returns (the returned vector, and each `jacobians[j] = ...` into its own matrix), and every call
    # rewrites every block that is not structurally zero
    e = np.empty(8 * n)
    J = np.zeros((8 * n, layout.width))
    blocks = [J[:, starts[j]:starts[j + 1]] for j in range(len(layout.keys))]

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
        if table is not None and table.values is values:
            if seen[0] != table.generation:
                rows[:] = [table.row[k] for k in tag_keys]
                seen[:] = table.generation, table.row[camera_key]
            table.poses.take(rows, 0, world_T_tags)
            camera = camera_from_table
            camera[:] = table.poses[seen[1]]
        else:
            camera = values.atPose3(camera_key).matrix()
            for i, key in enumerate(tag_keys):
                world_T_tags[i] = values.atPose3(key).matrix()
        for i, key in scale_keys:
            scales[i] = values.atVector(key)[0]
        d = _NO_LENS if lens_key is None else values.atVector(lens_key)
        want = jacobians is not None
        if view_errors(camera, world_T_tags, scales, d, cal, consts, inverse_sigma, huber_k, want,
                       e, J, columns, ok):
            behind_rows(layout, values, scales, d, cal, ok, e, J, want)
        if want:
            for j, block in enumerate(blocks):
                jacobians[j] = block
        return e

    return error


def behind_rows(layout: ViewLayout, values: gtsam.Values, scales: np.ndarray, d: np.ndarray, cal: np.ndarray,
                ok: np.ndarray, e: np.ndarray, J: np.ndarray, want: bool) -> None:
    """The rows `view_errors` left to its caller (`ok` False: a corner on or behind the camera's
    plane), each by `_behind`."""
    n = len(layout.sightings)
    for i in np.flatnonzero(~ok):
        _behind(layout.sightings[i], values.atPose3(layout.camera_key), values.atPose3(layout.sightings[i].tag_key),
                scales[i], d, cal, layout.consts[i], layout.columns[i], layout.columns[n, 0], layout.inverse_sigma[i],
                layout.huber_k, e, J, 8 * i, want)


def _behind(s: CornerSighting, world_T_camera: Pose3, world_T_tag: Pose3, scale: float, d: np.ndarray,
            cal: np.ndarray, consts: np.ndarray, columns: np.ndarray, lens_column: int, inverse_sigma: float,
            huber_k: float, e: np.ndarray, J: np.ndarray, r0: int, want: bool) -> None:
    """A view factor's rows of a tag with a corner on or behind the camera's plane: `corner_factor`'s
    path for it (`project_corners`' large flat error, no gradient), whitened as the kernel's rows."""
    local = np.asarray(s.tag_corners_m, float).reshape(4, 3)
    minus_basis = consts[corner_kernel.MINUS_BASIS:].reshape(8, 2)
    ei, JC, JT, _ = project_corners(world_T_camera, world_T_tag, (1.0 + scale) * local, cal,
                                    np.asarray(s.corners_px, float).reshape(4, 2), want_jacobians=want)
    rows = slice(r0, r0 + 8)
    e[rows] = ei + minus_basis @ d if lens_column >= 0 else ei
    if want:
        J[rows, :6] = JC
        J[rows, columns[0]:columns[0] + 6] = JT
        if columns[1] >= 0:
            J[rows, columns[1]] = (JT[:, 3:] * local.repeat(2, axis=0)).sum(axis=1)
        if lens_column >= 0:
            J[rows, lens_column:lens_column + 2] = minus_basis
    corner_kernel.whiten_rows(e, J, r0, inverse_sigma, huber_k, want)


@functools.lru_cache(maxsize=None)
def _huber(k: float) -> gtsam.noiseModel.mEstimator.Base:
    """One Huber kernel per threshold, shared by the factors that use it (it holds only k)."""
    return gtsam.noiseModel.mEstimator.Huber.Create(k)


def _corner_error(camera_key: int, tag_key: int, intrinsics_key: int | None, meas: np.ndarray, local: np.ndarray,
                  cal: np.ndarray | None, scale_key: int | None, lens: tuple[int, np.ndarray] | None,
                  intrinsics_basis: tuple[np.ndarray, np.ndarray] | None = None):
    """The corner factor's error function: with the intrinsics fixed at `cal` (a study's graph, a
    run's without a survey prior) or read from the variable `intrinsics_key` (the rig survey, and a
    calibrated run's graph and its bound: `SfGraphSlam.free_intrinsics`), the same error and
    Jacobians as `project_corners`, computed by the compiled `estimation.corner_kernel`.  GTSAM
    calls it back once per corner factor per relinearisation; in numpy the fixed cost per call on
    4-row arrays, not the arithmetic, was what such a callback spent its time on (32 us a
    linearisation, 10 of them the callback and its reads of the values).  A corner behind the
    camera takes `project_corners`'s path (a large flat error and no gradient).  The intrinsics
    basis (`corner_factor`), where given, is applied after either: e - B (K - K_ref), JK - B."""
    lens_key = None if lens is None else lens[0]
    k_basis, k_ref = ((None, None) if intrinsics_basis is None else
                      (np.asarray(intrinsics_basis[0], float).reshape(8, 5), np.asarray(intrinsics_basis[1], float)))
    minus_basis = None if lens is None else -np.asarray(lens[1], float)
    constants = corner_kernel.pack(meas, local, minus_basis)
    kernel = corner_kernel.corner_error
    no_lens = _NO_LENS
    free = intrinsics_key is not None

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
        world_T_camera, world_T_tag = values.atPose3(camera_key), values.atPose3(tag_key)
        scale = 0.0 if scale_key is None else values.atVector(scale_key)[0]
        d = no_lens if lens_key is None else values.atVector(lens_key)
        K = _cal_vector(values.atCal3_S2(intrinsics_key)) if free else cal
        e = np.empty(8)
        want = jacobians is not None
        JC, JT, Js = (np.empty((8, 6)), np.empty((8, 6)), np.empty((8, 1))) if want else (_J6, _J6, _J1)
        JK = np.empty((8, 5)) if want and free else _J5
        if not kernel(world_T_camera.matrix(), world_T_tag.matrix(), scale, d, K, constants, want, free, e,
                      JC, JT, Js, JK):
            e, JC, JT, JK = project_corners(world_T_camera, world_T_tag, (1.0 + scale) * local, K, meas,
                                            want_jacobians=want, want_calibration=free)
            if lens_key is not None:
                e = e + minus_basis @ d
            if want:
                Js = (JT[:, 3:] * local.repeat(2, axis=0)).sum(axis=1)[:, None]
        if k_basis is not None:
            e = e - k_basis @ (K - k_ref)
            if want:
                JK = JK - k_basis
        if want:
            jacobians[0], jacobians[1] = JC, JT
            j = 2
            if free:
                jacobians[2] = JK
                j = 3
            if scale_key is not None:
                jacobians[j] = Js
                j += 1
            if lens_key is not None:
                jacobians[j] = minus_basis
        return e

    return error


def refine_tag_pose(structure_T_tag: Pose3, cameras: Sequence[Pose3], corners_px: np.ndarray, local: np.ndarray,
                    cal: np.ndarray, sigmas_px: np.ndarray, scale: float = 0.0, lens: tuple | None = None,
                    scale_sigma: float = 0.0, iterations: int = 5, tolerance: float = 1e-8) -> tuple[Pose3, float]:
    """The tag pose (and, with `scale_sigma`, its print scale under that zero-mean prior) that best
    reprojects its corners into the given views, the cameras held where they are: Gauss-Newton on
    the corner factors' own error (`_corner_error`, intrinsics fixed: undistorted corners `corners_px`
    (n, 4, 2), each view's sigma, the lens correction `lens` = (bases (n, 8, 2), d) applied), from
    `structure_T_tag` and `scale`, until a step is below `tolerance` (rad, m).  A new tag's
    starting value for the graph: one sighting's IPPE pose is a degree or so off in tilt, and iSAM2
    would linearise the tag's factors there and again after the first solve; from here the first
    linearisation is already within the relinearisation threshold of the solution (the cameras
    move by a fraction of it).  A view with a corner behind it stops the refinement where it is.
    Each step's normal equations are built and solved in one compiled call
    (`corner_kernel.tag_step`; ~0.15 ms a tag in numpy, most of it numpy's cost per call); the
    numpy form stays as `_refine_tag_pose_numpy`."""
    cal = np.asarray(cal, float)
    n = len(cameras)
    nominal = np.array(local, float).reshape(4, 3)           # a writable copy: numba types a read-only array apart
    target = _refine_target(corners_px, cal, lens, n)
    weight = 1.0 / np.asarray(sigmas_px, float)
    camera_T_structure = np.array([c.inverse().matrix() for c in cameras])
    step = np.empty(7 if scale_sigma > 0 else 6)
    tag = structure_T_tag
    for _ in range(iterations):
        if not corner_kernel.tag_step(camera_T_structure, tag.matrix(), scale, nominal, target, weight, cal,
                                      scale_sigma, step):
            break
        tag, scale, done = _take_step(tag, scale, step, tolerance)
        if done:
            break
    return tag, scale


def _refine_target(corners_px: np.ndarray, cal: np.ndarray, lens: tuple | None, n: int) -> np.ndarray:
    """`refine_tag_pose`'s measured corners (n, 4, 2) less the principal point and the lens correction."""
    target = np.asarray(corners_px, float).reshape(n, 4, 2) - np.asarray(cal, float)[3:5]
    if lens is not None:
        bases, d = lens
        target = target - (np.asarray(bases) @ np.asarray(d, float)).reshape(n, 4, 2)
    return np.ascontiguousarray(target)


def _take_step(tag: Pose3, scale: float, step: np.ndarray, tolerance: float) -> tuple[Pose3, float, bool]:
    """A Gauss-Newton step (6, or 7 with the print scale) applied; True once it is below `tolerance`:
    what is left is of the order of its square."""
    if len(step) == 7:
        scale += float(step[6])
    return tag.retract(step[:6]), scale, bool(np.abs(step).max() < tolerance)


def _refine_tag_pose_numpy(structure_T_tag: Pose3, cameras: Sequence[Pose3], corners_px: np.ndarray, local: np.ndarray,
                    cal: np.ndarray, sigmas_px: np.ndarray, scale: float = 0.0, lens: tuple | None = None,
                    scale_sigma: float = 0.0, iterations: int = 5, tolerance: float = 1e-8) -> tuple[Pose3, float]:
    """`refine_tag_pose` in numpy, one array pass a step: the readable form, and the reference the
    compiled step is tested against (tests/test_slam_step_exact.py)."""
    fx, fy, sk = (float(c) for c in cal[:3])
    to_px = np.array([[fx, 0.0], [sk, fy]])
    n = len(cameras)
    nominal_rows = np.repeat(np.asarray(local, float).reshape(4, 3), 2, axis=0)      # (8, 3)
    target = _refine_target(corners_px, cal, lens, n)
    w = (1.0 / np.asarray(sigmas_px, float)).repeat(8)
    camera_T_structure = np.array([c.inverse().matrix() for c in cameras])
    after, before = [1, 2, 0], [2, 0, 1]
    Jq = np.zeros((n, 4, 2, 3))                  # d(pixel) / d(point in the camera frame)
    A = np.empty((8 * n, 7 if scale_sigma > 0 else 6))
    tag = structure_T_tag
    for _ in range(iterations):
        m = camera_T_structure @ tag.matrix()                             # (n, 4, 4) camera_T_tag
        R = m[:, :3, :3]
        p = (1.0 + scale) * nominal_rows                                  # (8, 3): each row's corner
        q = p[::2] @ np.swapaxes(R, 1, 2) + m[:, None, :3, 3]             # (n, 4, 3)
        if q[..., 2].min() <= 0.0:
            break
        iz = 1.0 / q[..., 2]
        uv = (q[..., :2] * iz[..., None]) @ to_px
        e = (uv - target).reshape(-1) * w
        Jq[..., 0, 0], Jq[..., 0, 1], Jq[..., 1, 1] = fx * iz, sk * iz, fy * iz
        Jq[..., 0, 2], Jq[..., 1, 2] = -uv[..., 0] * iz, -uv[..., 1] * iz
        # a right perturbation (w, v) of the tag moves a corner by R (v - p x w): the tag's Jacobian
        # is [p x (Jq R), Jq R] row by row (project_corners' -JC Ad(camera_T_tag))
        JqR = Jq.reshape(n, 8, 3) @ R                                      # (n, 8, 3)
        A[:, :3] = (p[:, after] * JqR[..., before] - p[:, before] * JqR[..., after]).reshape(-1, 3)
        A[:, 3:6] = JqR.reshape(-1, 3)
        if scale_sigma > 0:
            A[:, 6] = np.sum(JqR * nominal_rows, axis=2).reshape(-1)       # the corners grow with the scale
        A *= w[:, None]
        H, g = A.T @ A, A.T @ e
        if scale_sigma > 0:
            H[6, 6] += 1.0 / scale_sigma ** 2
            g[6] += scale / scale_sigma ** 2
        step = np.linalg.solve(H, -g)
        tag, scale, done = _take_step(tag, scale, step, tolerance)
        if done:
            break
    return tag, scale


def undistort_px(corners_px: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Corners with the lens distortion removed, in pixels of the pinhole K."""
    import cv2

    pts = np.asarray(corners_px, dtype=np.float64).reshape(-1, 1, 2)
    return cv2.undistortPoints(pts, K, np.asarray(dist, float), P=K).reshape(-1, 2)


# A tag seen obliquely has shorter, blurrier edges: its corners are worse.  Below MIN_SIDE_RATIO
# (about 50-60 deg of incidence) a sighting is left out; above it a corner's sigma grows as the
# side ratio ** -OBLIQUE_EXPONENT (measured in the rig survey: 0.09 px face-on, 0.15 px near the limit).
MIN_SIDE_RATIO = 0.65
OBLIQUE_EXPONENT = 2.0


def side_ratio(corners_px: np.ndarray, K: np.ndarray, dist: np.ndarray) -> float:
    """Shortest over longest side of a tag's undistorted quadrilateral: ~cos(incidence)."""
    return undistorted_side_ratio(undistort_px(np.asarray(corners_px, float), K, dist))


def undistorted_side_ratio(u: np.ndarray) -> float:
    """`side_ratio` of corners already undistorted, (4, 2)."""
    d = np.diff(u, axis=0, append=u[:1])
    sides = np.sqrt(np.einsum("ij,ij->i", d, d))
    top = sides.max()
    return float(sides.min() / top) if top > 0 else 0.0


def tag_prior_noise(sigma_m: float, size_m: float) -> gtsam.noiseModel.Base:
    """A tag's placement prior: sigma_m per axis, and sigma_m over its size (rad) per rotation axis."""
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_m / size_m] * 3 + [sigma_m] * 3))


def tangent_error(estimate: Pose3, truth: Pose3) -> np.ndarray:
    """truth's deviation from the estimate in the estimate's tangent (for NEES)."""
    return Pose3.Logmap(estimate.between(truth))


def nees(estimate: Pose3, truth: Pose3, cov: np.ndarray, dims: Sequence[int] = range(6)) -> float:
    d = list(dims)
    e = tangent_error(estimate, truth)[d]
    return float(e @ np.linalg.solve(cov[np.ix_(d, d)], e))
