"""Rig calibration from a survey of tags at known (roughly known) places: the turntable axis, the
Stewart base, the camera mount, the camera's focal length and principal point, and the turntable
tags as glued, in one GTSAM graph (`lab calibrate rig`, and the first step of a `lab run borg`
that has no calibration file).

1. Each view's camera pose from all its tags' corners at their design poses (OpenCV `solvePnP`).
2. An initial Stewart base and camera mount from OpenCV's `calibrateRobotWorldHandEye` on those
   poses and the commanded platform poses (the turntable axis starts at its nominal place).
3. Refinement in GTSAM (Levenberg–Marquardt): per view a kinematic chain factor
   (estimation/rig_model.py), per tag sighting the reprojection of its four corners through a
   pinhole whose intrinsics are a variable; priors from the rig's `[calibration]` table (nominal
   poses, wide), the camera file's intrinsics and the turntable tags' design poses.
4. Marginal covariances, the corner residuals, and a conditioning check: a quantity the survey
   could not pin down to its limit is named, with what the survey lacked.

Two things keep the covariances honest (measured on rendered surveys, docs/calibration.md):
- tags seen too obliquely are left out: their corners are biased (0.09-0.12 px rms error up to 50 deg
  incidence, 0.15 at 50-60, 0.37 at 60-70, 1.3 px at 70-80), and a biased corner is not noise a
  sigma can cover.  The image says how oblique a tag is: the ratio of its shortest to its longest
  side (undistorted) is about cos(incidence); below `min_side_ratio` (0.65, about 50-60 deg of
  incidence in the rig survey) the sighting is dropped; above it a corner's sigma grows as the
  ratio^-2 (measured: 0.09 px face-on, 0.15 px near the limit).
- the corner noise is measured, not assumed: each pass's whitened residuals give the
  a-posteriori variance factor (chi2 / degrees of freedom), and the next pass uses the corner
  sigma it implies, so the marginals reflect how well the corners were really found; the turntable
  tags' glue scatter and their apparent scale scatter are measured the same way (variance
  components of their prior groups), and the lens's radial distortion error and each turntable
  tag's print scale are variables, so what the camera file and the printer got wrong is estimated
  rather than read as a rig error.
The calibration keeps the joint posterior (lab/core/rig_calibration_file.py): a run takes it as one prior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import cv2
import gtsam
import numpy as np

from estimation import levenberg_marquardt
from estimation.fiducials import tag_object_points
from estimation.rig_model import (AXIS, BASE, DISTORTION, INTRINSICS, LIFT, MIN_SIDE_RATIO, MOUNT, OBLIQUE_EXPONENT,
                                  RigGeometry, distortion_prior_sigmas, radial_basis,
                                  ViewMotion, cal3_s2, chain_factor, corner_factor, nees, side_ratio, tag_prior_noise,
                                  undistort_px)
from lab.core.geometry import Pose3, Rot3, to_xyzrpy
from lab.core.rig_calibration_file import RigCalibration

C = gtsam.symbol_shorthand.C
T = gtsam.symbol_shorthand.T
S = gtsam.symbol_shorthand.S   # a turntable tag's print scale
_CAMERA_CHR = gtsam.Symbol(C(0)).chr()


@dataclass(frozen=True)
class TagSighting:
    tag_id: int
    corners_px: np.ndarray            # (4, 2) as detected (distorted), aruco order


@dataclass(frozen=True)
class CalibrationView:
    motion: ViewMotion
    sightings: tuple[TagSighting, ...]


@dataclass(frozen=True)
class Limits:
    """The largest 1-sigma a usable calibration may have (docs/calibration.md).  Past these a
    calibration would not be worth more than the rig file's nominal values to a run (which refines
    it anyway): the survey could not see that quantity."""

    mount_m: float = 0.0015
    mount_rad: float = math.radians(0.05)
    base_m: float = 0.002
    base_rad: float = math.radians(0.05)
    axis_m: float = 0.001
    axis_rad: float = math.radians(0.03)
    focal_rel: float = 0.002
    principal_point_px: float = 2.0


@dataclass
class RigSolution:
    calibration: RigCalibration
    residuals_px: np.ndarray               # per corner, |reprojection error|
    problems: list[str] = field(default_factory=list)   # poorly conditioned quantities, one line each
    initial: dict[str, Pose3] = field(default_factory=dict)
    iterations: int = 0
    oblique_dropped: int = 0               # sightings left out as too oblique (min_side_ratio)
    corner_sigma_px: float = float("nan")  # the corner noise the final pass used (measured)
    turntable_tag_sigma_m: float = float("nan")  # the turntable tags' glue scatter the final pass used (measured)
    tag_scale_sigma: float = float("nan")        # the tags' apparent scale scatter the final pass used (measured)
    repeatability_scale: float = float("nan")    # the devices' repeatability against their datasheet (measured)

    @property
    def ok(self) -> bool:
        return not self.problems


# corner noise grows with obliquity: measured 0.09 px rms (ratio ~0.9) to 0.15 px (ratio ~0.7)
# never trust corners better than this, whatever the residuals say: the detector reaches 0.008 px on the
# simulated camera (docs/fiducials.md); a 0.05 px floor, set for the old detector, made the
# calibration's covariance 60x too wide in variance (NEES 0.1 against 6)
CORNER_SIGMA_FLOOR_PX = 0.01


def drop_oblique(views: Sequence[CalibrationView], K: np.ndarray, dist: np.ndarray,
                 min_side_ratio: float = MIN_SIDE_RATIO) -> tuple[list[CalibrationView], int]:
    """The views with their too-oblique sightings left out, and how many were."""
    out, dropped = [], 0
    for v in views:
        keep = tuple(s for s in v.sightings if side_ratio(s.corners_px, K, dist) >= min_side_ratio)
        dropped += len(v.sightings) - len(keep)
        out.append(CalibrationView(v.motion, keep))
    return out, dropped


def view_pose_pnp(sightings: Sequence[TagSighting], tags: Mapping[int, tuple[Pose3, float]], K: np.ndarray,
                  dist: np.ndarray) -> Pose3 | None:
    """structure_T_camera from every corner of a view's tags at their design poses."""
    obj, img = [], []
    for s in sightings:
        if s.tag_id not in tags:
            continue
        pose, size = tags[s.tag_id]
        obj.extend(pose.transformFrom(p) for p in tag_object_points(size))
        img.extend(np.asarray(s.corners_px, float))
    if len(obj) < 4:
        return None
    obj_a, img_a = np.asarray(obj, np.float64), np.asarray(img, np.float64)
    flag = cv2.SOLVEPNP_IPPE if len(obj) == 4 else cv2.SOLVEPNP_SQPNP
    ok, rvec, tvec = cv2.solvePnP(obj_a, img_a, K, np.asarray(dist, float), flags=flag)
    if not ok:
        return None
    if len(obj) > 4:
        rvec, tvec = cv2.solvePnPRefineLM(obj_a, img_a, K, np.asarray(dist, float), rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    return Pose3(Rot3(R), tvec.ravel()).inverse()


def hand_eye(views: Sequence[CalibrationView], cameras: Sequence[Pose3 | None], geometry: RigGeometry
             ) -> tuple[Pose3, Pose3] | None:
    """(world_T_base, platform_T_camera) by OpenCV's robot-world/hand-eye calibration (Shah's
    method), from the views' camera poses in the world (turntable axis nominal)."""
    R_w2c, t_w2c, R_b2g, t_b2g = [], [], [], []
    for v, s_T_c in zip(views, cameras):
        if s_T_c is None:
            continue
        world_T_structure = geometry.structure_T_world0.inverse()
        world_T_camera = Pose3(Rot3.Rz(v.motion.turntable_rad), np.zeros(3)).compose(world_T_structure).compose(s_T_c)
        if v.motion.lift_m:        # back down the (nominally vertical) lift: the base at height 0
            world_T_camera = Pose3(Rot3(), np.array([0.0, 0.0, -v.motion.lift_m])).compose(world_T_camera)
        cw = world_T_camera.inverse()
        gb = geometry.base_T_platform(v.motion).inverse()
        R_w2c.append(cw.rotation().matrix())
        t_w2c.append(cw.translation().reshape(3, 1))
        R_b2g.append(gb.rotation().matrix())
        t_b2g.append(gb.translation().reshape(3, 1))
    if len(R_w2c) < 3:
        return None
    try:
        R_b2w, t_b2w, R_g2c, t_g2c = cv2.calibrateRobotWorldHandEye(R_w2c, t_w2c, R_b2g, t_b2g)
    except cv2.error:
        # degenerate motions (e.g. no platform rotation: "determinant(R) is null"): no start from
        # OpenCV; the caller starts from the nominal rig and the conditioning check says what's missing
        return None
    B = Pose3(Rot3(R_b2w), np.asarray(t_b2w).ravel())
    M = Pose3(Rot3(R_g2c), np.asarray(t_g2c).ravel()).inverse()
    return B, M


def solve_rig(views: Sequence[CalibrationView], geometry: RigGeometry, dist: np.ndarray,
              tags: Mapping[int, tuple[Pose3, float]], *, turntable_tags: Sequence[int] = (),
              corner_sigma_px: float = 0.15, limits: Limits | None = None, rig_name: str = "",
              max_iterations: int = 60, passes: int = 4, min_side_ratio: float = MIN_SIDE_RATIO,
              measure_corner_sigma: bool = True, oblique_exponent: float = OBLIQUE_EXPONENT,
              tag_scale_sigma: float = 0.0) -> RigSolution:
    """Calibrate the rig from `views`.  `tags`: every tag that may be seen, id -> (design
    structure_T_tag, size); `turntable_tags` among them get a pose variable with a design prior
    (the rig's turntable_tag_sigma), the others are held at their design poses by a tight prior.
    `corner_sigma_px` is the first pass's corner noise; with `measure_corner_sigma` later passes
    use the one the residuals imply.  Sightings flatter than `min_side_ratio` are left out; the
    others' corner sigma grows as side_ratio ** -oblique_exponent (`corner_sigma_px` is face-on).
    `tag_scale_sigma`: each turntable tag's print scale is a variable with this prior (relative),
    so a tag printed large does not pull the rig toward it (its uncertainty reaches the covariance)."""
    limits = limits or Limits()
    K0 = geometry.K
    views, dropped = drop_oblique(views, K0, dist, min_side_ratio)
    scale = {(k, s.tag_id): side_ratio(s.corners_px, K0, dist) ** -oblique_exponent
             for k, v in enumerate(views) for s in v.sightings}
    cams = [view_pose_pnp(v.sightings, tags, K0, dist) for v in views]
    he = hand_eye(views, cams, geometry)
    B0, M0 = he if he is not None else (geometry.nominal_world_T_base, geometry.nominal_platform_T_camera)
    means, covs = geometry.priors(None)
    K_und = K0
    est = None
    sigma = corner_sigma_px
    glue = geometry.config.turntable_tag_sigma_m
    repeat = 1.0
    for k in range(max(1, passes)):
        graph, values, seen, n_views = _build(views, geometry, dist, tags, turntable_tags, sigma, K_und,
                                              means, covs, B0, M0, est, scale, glue, tag_scale_sigma, repeat)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(1e-8)
        params.setAbsoluteErrorTol(1e-10)
        est, iterations = levenberg_marquardt.optimize(graph, values, params)
        # the lens distortion acts on the true camera's normalised coordinates: undistort again
        # through the intrinsics just estimated (0.25 % of focal length moves a corner at the
        # image edge by ~0.1 px, as much as the corner noise)
        K_und = est.atCal3_S2(INTRINSICS).K()
        if measure_corner_sigma and k + 1 < passes:
            sigma = _measured_corner_sigma(views, est, K_und, dist, tags, sigma, scale)
            glue = _measured_glue_sigma(graph, est, tags, set(turntable_tags) & seen, glue)
            if tag_scale_sigma > 0:
                tag_scale_sigma = _measured_scale_sigma(graph, est, set(turntable_tags) & seen, tag_scale_sigma)
            repeat = _measured_repeatability_scale(graph, est, repeat)
    assert est is not None
    marg = gtsam.Marginals(graph, est)
    cal = est.atCal3_S2(INTRINSICS)
    K = cal.K()
    kcov5 = marg.marginalCovariance(INTRINSICS)          # fx, fy, s, u0, v0
    idx = [0, 1, 3, 4]
    cov = {"world_T_axis": marg.marginalCovariance(AXIS), "world_T_base": marg.marginalCovariance(BASE),
           "platform_T_camera": marg.marginalCovariance(MOUNT), "K": kcov5[np.ix_(idx, idx)]}
    tt = set(turntable_tags)
    tag_poses = {t: est.atPose3(T(t)) for t in sorted(seen & tt)}
    tag_covs = {t: marg.marginalCovariance(T(t)) for t in tag_poses}
    # the run's prior is this joint covariance, not the marginals (lab/core/rig_calibration_file.py)
    joint = marg.jointMarginalCovariance(gtsam.KeyVector([AXIS, BASE, MOUNT, INTRINSICS, DISTORTION,
                                                          *(T(t) for t in tag_poses)])).fullMatrix()
    residuals = _residuals(views, est, K_und, dist, tags)
    calibration = RigCalibration(est.atPose3(MOUNT), est.atPose3(BASE), est.atPose3(AXIS), K, cov, tag_poses,
                                 tag_covs, float(np.sqrt(np.mean(residuals ** 2))) if residuals.size else float("nan"),
                                 n_views, rig_name, joint_covariance=0.5 * (joint + joint.T), corner_sigma_px=sigma,
                                 distortion_correction=tuple(float(x) for x in est.atVector(DISTORTION)),
                                 tag_scale_sigma=tag_scale_sigma if tag_scale_sigma > 0 else float("nan"),
                                 repeatability_scale=repeat if measure_corner_sigma else float("nan"))
    problems = conditioning_problems(calibration, views, limits)
    return RigSolution(calibration, residuals, problems, {"world_T_base": B0, "platform_T_camera": M0},
                       iterations, dropped, sigma, glue, tag_scale_sigma,
                       repeat if measure_corner_sigma else float("nan"))


def _measured_corner_sigma(views, est, K_und, dist, tags, sigma, scale) -> float:
    """The corner sigma the residuals imply: per-axis rms of the corner residuals over the degrees
    of freedom they leave (observations minus the variables they determine: each view's camera
    is fixed by its chain and counts nothing extra, each tag seen and the calibration count).
    Huber-downweighted corners are counted as they are: this is the noise the fit saw."""
    r = _residuals(views, est, K_und, dist, tags, scale)
    if r.size == 0:
        return sigma
    n_obs = 2 * r.size
    n_tags = sum(1 for t in tags if est.exists(T(t)))
    n_params = 6 * 3 + 4 + 6 * n_tags
    dof = max(1, n_obs - n_params)
    s = float(np.sqrt(np.sum(r ** 2) / dof))
    return max(CORNER_SIGMA_FLOOR_PX, s)


# the glue scatter is never taken as smaller than this: a tag's place is not known better than its
# print (and a perfect fit must not make the frame exact)
GLUE_SIGMA_FLOOR_M = 2e-5


def _measured_glue_sigma(graph: gtsam.NonlinearFactorGraph, est: gtsam.Values, tags: Mapping[int, tuple[Pose3, float]],
                         turntable_tags: set[int], sigma_m: float) -> float:
    """The turntable tags' glue scatter their estimates imply (variance component estimation of
    the prior group): sigma^2 <- sigma^2 * v'Pv / r, with v each tag's estimate against its design
    pose, P the prior's information and r = n - tr(P Sigma_post) the group's redundancy.  A rig
    whose tags are glued better than the rig file says gets a frame known as well as that; a worse
    one, an honestly wider frame.  Only the scatter between tags is seen: the tags' common error
    (the frame's yaw and height) is what the prior then carries, at the measured scatter."""
    if not turntable_tags:
        return sigma_m
    marg = gtsam.Marginals(graph, est)
    vpv = r = 0.0
    for t in sorted(turntable_tags):
        design, size = tags[t]
        info = np.diag(1.0 / np.array([sigma_m / size] * 3 + [sigma_m] * 3) ** 2)
        v = Pose3.Logmap(design.between(est.atPose3(T(t))))
        vpv += float(v @ info @ v)
        r += 6.0 - float(np.trace(info @ marg.marginalCovariance(T(t))))
    if r <= 0.5:
        return sigma_m
    return max(GLUE_SIGMA_FLOOR_M, sigma_m * math.sqrt(vpv / r))


# a tag's apparent scale is never taken as known better than this (relative)
SCALE_SIGMA_FLOOR = 1e-4


def _measured_scale_sigma(graph: gtsam.NonlinearFactorGraph, est: gtsam.Values, turntable_tags: set[int],
                          sigma: float) -> float:
    """The scatter of the tags' apparent scale, as the turntable tags show it (variance component
    estimation of the scale group, as for the glue).  What a view reads as a tag's size is its
    print scale times the detector's own scale bias, which grows with blur (a blurred black square
    reads a little small or large, alike in every view of it): residuals cannot show either, a
    scale variable can, and its prior must be as wide as the two together."""
    tags = [t for t in sorted(turntable_tags) if est.exists(S(t))]
    if not tags:
        return sigma
    marg = gtsam.Marginals(graph, est)
    vpv = sum(float(est.atVector(S(t))[0]) ** 2 for t in tags) / sigma ** 2
    r = sum(1.0 - float(marg.marginalCovariance(S(t))[0, 0]) / sigma ** 2 for t in tags)
    if r <= 0.5:
        return sigma
    return max(SCALE_SIGMA_FLOOR, sigma * math.sqrt(vpv / r))


# the devices are never taken as repeating better than this share of their datasheet (a survey of a
# rig that happened to repeat perfectly must not make every later view exact), nor worse than this
REPEATABILITY_SCALE_RANGE = (0.1, 20.0)


def scaled_noise(noise: gtsam.noiseModel.Base, k: float) -> gtsam.noiseModel.Base:
    """A Gaussian noise model with every sigma times k."""
    if k == 1.0:
        return noise
    return gtsam.noiseModel.Gaussian.Covariance(np.asarray(noise.covariance()) * k * k)


def with_repeatability_scale(geometry: RigGeometry, k: float) -> RigGeometry:
    """The rig as the estimator knows it, its devices' repeatability times k (as a survey measured
    it against the datasheet); k nan or 1: unchanged."""
    if not math.isfinite(k) or k == 1.0:
        return geometry
    c = geometry.config
    return replace(geometry, config=replace(
        c, stewart_repeatability_m=c.stewart_repeatability_m * k, stewart_repeatability_rad=c.stewart_repeatability_rad * k,
        turntable_repeatability_rad=c.turntable_repeatability_rad * k, lift_repeatability_m=c.lift_repeatability_m * k))


def _measured_repeatability_scale(graph: gtsam.NonlinearFactorGraph, est: gtsam.Values, k: float) -> float:
    """How the devices repeat against their datasheet, as the survey's views show it (variance
    component estimation of the chain factors' group, as for the glue): k^2 <- k^2 v'Pv / r, with
    v'Pv each chain factor's whitened residual and r = sum(6 - tr(P J Sigma J')) its redundancy,
    Sigma the joint posterior of the factor's variables.  Every view's camera is a variable that its
    corners pin down, so what its chain prediction misses beyond their noise is the devices'.  A
    rig file whose repeatability is optimistic would otherwise make the survey, and every run after
    it, too sure of the rig (mount NEES 15-23 at twice the datasheet's repeatability)."""
    marg = gtsam.Marginals(graph, est)
    vpv = r = 0.0
    for i in range(graph.size()):
        f = graph.at(i)
        if not isinstance(f, gtsam.CustomFactor) or f.dim() != 6 or not any(gtsam.Symbol(key).chr() == _CAMERA_CHR
                                                                            for key in f.keys()):
            continue
        lin = f.linearize(est)
        A, b = lin.jacobian()
        keys = gtsam.KeyVector(list(f.keys()))
        sigma = marg.jointMarginalCovariance(keys).fullMatrix()
        vpv += float(b @ b)
        r += 6.0 - float(np.trace(A @ sigma @ A.T))
    if r <= 0.5:
        return k
    lo, hi = REPEATABILITY_SCALE_RANGE
    return float(np.clip(k * math.sqrt(vpv / r), lo, hi))


def _build(views, geometry, dist, tags, turntable_tags, corner_sigma_px, K_und, means, covs, B0, M0, start,
           scale=None, glue_sigma_m=None, tag_scale_sigma=0.0, repeatability_scale=1.0):
    """The calibration graph; `start` (a previous solution) seeds the values."""
    K0 = geometry.K
    cfg = geometry.config
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for key in (AXIS, BASE, MOUNT):
        graph.add(gtsam.PriorFactorPose3(key, means[key], gtsam.noiseModel.Gaussian.Covariance(covs[key])))
    values.insert(AXIS, Pose3())
    values.insert(BASE, B0)
    values.insert(MOUNT, M0)
    if any(v.motion.lift_m for v in views):
        # a survey from a lift height: the base is calibrated at height 0 through the lift's axis,
        # whose tilt one height cannot see -- its prior's uncertainty goes into the base's
        mean, cov = geometry.lift_prior()
        graph.add(gtsam.PriorFactorPose3(LIFT, mean, gtsam.noiseModel.Gaussian.Covariance(cov)))
        values.insert(LIFT, mean)
    f = float(K0[0, 0])
    graph.add(gtsam.PriorFactorCal3_S2(INTRINSICS, cal3_s2(K0), gtsam.noiseModel.Diagonal.Sigmas(np.array(
        [cfg.focal_sigma * f, cfg.focal_sigma * f, 1e-6, cfg.principal_point_sigma_px, cfg.principal_point_sigma_px]))))
    values.insert(INTRINSICS, cal3_s2(K0))
    # the lens: the camera file's distortion is known to [calibration] distortion_sigma_px at the corners
    graph.add(gtsam.PriorFactorVector(DISTORTION, np.zeros(2), gtsam.noiseModel.Diagonal.Sigmas(
        distortion_prior_sigmas(cfg.distortion_sigma_px, K0))))
    values.insert(DISTORTION, np.zeros(2))
    tt = set(turntable_tags)
    seen: set[int] = set()
    n_views = 0
    for k, v in enumerate(views):
        usable = [s for s in v.sightings if s.tag_id in tags]
        if not usable:
            continue
        n_views += 1
        graph.add(chain_factor(geometry, v.motion, C(k), scaled_noise(geometry.chain_noise(v.motion), repeatability_scale)))
        values.insert(C(k), geometry.predict(v.motion, Pose3(), B0, M0))
        for s in usable:
            pose, size = tags[s.tag_id]
            if s.tag_id not in seen:
                seen.add(s.tag_id)
                glue = cfg.turntable_tag_sigma_m if glue_sigma_m is None else glue_sigma_m
                sig = glue if s.tag_id in tt else 1e-6
                graph.add(gtsam.PriorFactorPose3(T(s.tag_id), pose, tag_prior_noise(sig, size)))
                values.insert(T(s.tag_id), pose)
                if s.tag_id in tt and tag_scale_sigma > 0:
                    graph.add(gtsam.PriorFactorVector(S(s.tag_id), np.zeros(1),
                                                      gtsam.noiseModel.Isotropic.Sigma(1, tag_scale_sigma)))
                    values.insert(S(s.tag_id), np.zeros(1))
            sk = S(s.tag_id) if s.tag_id in tt and tag_scale_sigma > 0 else None
            u = undistort_px(s.corners_px, K_und, dist)
            graph.add(corner_factor(C(k), T(s.tag_id), u, tag_object_points(size),
                                    corner_sigma_px * (scale or {}).get((k, s.tag_id), 1.0), scale_key=sk,
                                    distortion=(DISTORTION, radial_basis(u, K_und))))
    if start is not None:
        values = gtsam.Values(start)
    return graph, values, seen, n_views


def _residuals(views: Sequence[CalibrationView], est: gtsam.Values, K_und: np.ndarray, dist: np.ndarray,
               tags: Mapping[int, tuple[Pose3, float]], scale: Mapping[tuple[int, int], float] | None = None
               ) -> np.ndarray:
    """|reprojection error| of every corner, px (divided by its sighting's sigma scale if given)."""
    cam_model = est.atCal3_S2(INTRINSICS)
    out = []
    for k, v in enumerate(views):
        if not est.exists(C(k)):
            continue
        cam = gtsam.PinholeCameraCal3_S2(est.atPose3(C(k)), cam_model)
        for s in v.sightings:
            if s.tag_id not in tags or not est.exists(T(s.tag_id)):
                continue
            pose = est.atPose3(T(s.tag_id))
            meas = undistort_px(s.corners_px, K_und, dist)
            if est.exists(DISTORTION):
                meas = meas + (radial_basis(meas, K_und) @ est.atVector(DISTORTION)).reshape(4, 2)
            w = (scale or {}).get((k, s.tag_id), 1.0)
            printed = 1.0 + float(est.atVector(S(s.tag_id))[0]) if est.exists(S(s.tag_id)) else 1.0
            for p, m in zip(printed * tag_object_points(tags[s.tag_id][1]), meas):
                out.append(float(np.linalg.norm(cam.project(pose.transformFrom(p)) - m)) / w)
    return np.asarray(out)


def _span_deg(views: Sequence[CalibrationView], i: int) -> float:
    vals = [math.degrees(v.motion.stewart_pose[i]) for v in views]
    return (max(vals) - min(vals)) if vals else 0.0


def conditioning_problems(cal: RigCalibration, views: Sequence[CalibrationView], limits: Limits) -> list[str]:
    """Each quantity whose 1-sigma exceeds its limit, with what the survey lacked."""
    problems = []
    span = f"platform roll / pitch / yaw spans {_span_deg(views, 3):.0f} / {_span_deg(views, 4):.0f} / " \
           f"{_span_deg(views, 5):.0f} deg"
    angles = [math.degrees(v.motion.turntable_rad) for v in views]
    tt_span = f"turntable angles span {max(angles) - min(angles):.0f} deg" if angles else "no views"
    checks = (
        ("platform_T_camera", "camera mount", limits.mount_m, limits.mount_rad,
         f"the mount is seen through platform rotations: it needs them about at least two axes ({span})"),
        ("world_T_base", "Stewart base", limits.base_m, limits.base_rad,
         f"the base is seen through the platform's motion and the turntable tags ({span}; {tt_span})"),
        ("world_T_axis", "turntable axis", limits.axis_m, limits.axis_rad,
         f"the axis is seen by turning the structure: it needs views over a wide turntable range ({tt_span})"),
    )
    for name, label, lim_m, lim_rad, why in checks:
        sd = np.sqrt(np.clip(np.diag(cal.covariance[name]), 0.0, None))
        dims = [0, 1, 3, 4] if name == "world_T_axis" else range(6)
        for i in dims:
            is_rot = i < 3
            lim = lim_rad if is_rot else lim_m
            if sd[i] > lim:
                comp = ("roll", "pitch", "yaw", "x", "y", "z")[i]
                value = f"{math.degrees(sd[i]):.3f} deg" if is_rot else f"{sd[i] * 1000:.2f} mm"
                limit = f"{math.degrees(lim):.3f} deg" if is_rot else f"{lim * 1000:.2f} mm"
                problems.append(f"{name} ({label}) {comp}: 1 sigma {value} exceeds {limit}; {why}")
    ksd = np.sqrt(np.clip(np.diag(cal.covariance["K"]), 0.0, None))
    f = float(cal.K[0, 0])
    for i, comp in enumerate(("fx", "fy")):
        if ksd[i] / f > limits.focal_rel:
            problems.append(f"camera {comp}: 1 sigma {100 * ksd[i] / f:.2f} % exceeds {100 * limits.focal_rel:.2f} %; "
                            f"the focal length needs tags at several depths across the image")
    for i, comp in ((2, "cx"), (3, "cy")):
        if ksd[i] > limits.principal_point_px:
            problems.append(f"camera {comp}: 1 sigma {ksd[i]:.2f} px exceeds {limits.principal_point_px:.2f} px; "
                            f"the principal point needs platform rotations and tags across the image")
    return problems


def truth_error(cal: RigCalibration, *, world_T_base: Pose3, platform_T_camera: Pose3, world_T_axis: Pose3,
                K: np.ndarray | None = None) -> dict[str, float]:
    """Errors of a calibration against a known truth (simulation): metres and radians."""
    def split(est: Pose3, truth: Pose3) -> tuple[float, float]:
        d = est.between(truth)
        return float(np.linalg.norm(truth.translation() - est.translation())), float(
            np.linalg.norm(Rot3.Logmap(d.rotation())))
    mm, mr = split(cal.platform_T_camera, platform_T_camera)
    bm, br = split(cal.world_T_base, world_T_base)
    # the axis: where it crosses the plate (x, y) and its tilt; its yaw and height are gauge
    axis_m = float(np.linalg.norm(cal.world_T_axis.translation()[:2] - world_T_axis.translation()[:2]))
    za, zt = cal.world_T_axis.rotation().matrix()[:, 2], world_T_axis.rotation().matrix()[:, 2]
    axis_rad = float(math.acos(min(1.0, float(za @ zt))))
    out = {"camera_mount_m": mm, "camera_mount_rad": mr, "stewart_base_m": bm, "stewart_base_rad": br,
           "turntable_axis_m": axis_m, "turntable_axis_rad": axis_rad}
    if K is not None:
        out["focal_rel"] = float(abs(cal.K[0, 0] / K[0, 0] - 1.0))
        out["principal_point_px"] = float(np.linalg.norm(cal.K[:2, 2] - K[:2, 2]))
    return out


def nees_report(cal: RigCalibration, *, world_T_base: Pose3, platform_T_camera: Pose3) -> dict[str, float]:
    """Normalised estimation error squared of the mount and the base (6-dof each: expect ~6)."""
    return {name: nees(getattr(cal, name), truth, cal.covariance[name])
            for name, truth in (("platform_T_camera", platform_T_camera), ("world_T_base", world_T_base))}


def describe(cal: RigCalibration) -> dict[str, object]:
    """The estimates with their sigmas, for `--json` and the console."""
    s = cal.sigmas()
    out: dict[str, object] = {}
    for name in ("platform_T_camera", "world_T_base", "world_T_axis"):
        x = to_xyzrpy(getattr(cal, name))
        out[name] = {"xyz_mm": [float(v * 1e3) for v in x[:3]], "rpy_deg": [math.degrees(v) for v in x[3:]],
                     "sigma_xyz_mm": s[name]["xyz_mm"], "sigma_rpy_deg": s[name]["rot_deg"]}
    out["camera"] = {"fx_px": float(cal.K[0, 0]), "fy_px": float(cal.K[1, 1]), "cx_px": float(cal.K[0, 2]),
                     "cy_px": float(cal.K[1, 2]), "sigma": s["K"]}
    out["rms_px"] = cal.rms_px
    out["views"] = cal.views
    return out
