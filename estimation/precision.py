"""How well a module's pose can be known: its 1-sigma from a tag's covariance, the information a
view of a tag would add before the view is taken, and the Cramér–Rao bound of a whole survey.

- A module is read from one of its tags through a lever arm (`tag_T_module`, 0.15–0.5 m): a tag
  tilted by dr moves the module by dr × lever, so the module's position sigma is the tag's
  covariance propagated through that arm, not the tag's position sigma alone.
- The information a view adds about a tag is J^T W J with J the Jacobian of the tag's four corner
  projections with respect to the tag pose, and W the inverse of the pixel noise plus the view's
  camera-pose uncertainty carried into pixels.  The survey planner sums these to predict a
  module's sigma before moving (procedures/survey.py); views are treated as independent, so a
  camera error shared between views (the calibration) is not averaged down in the prediction --
  the graph's own marginal, after the views, is what the verdict uses.
- The bound: the marginal covariance of the graph linearised at the true values with the true
  noise (Gaussian, no robust kernel): the Cramér–Rao bound of the linearised problem, the best
  1-sigma any unbiased estimator of the same measurements can reach.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import gtsam
import numpy as np

from lab.core.geometry import Pose3


@dataclass(frozen=True)
class ModuleSigma:
    position_m: float      # 1 sigma along the worst direction of the module's anchor position
    rotation_rad: float    # 1 sigma about the worst axis
    position_rms_m: float = math.nan   # sqrt(trace): the expected RMS of the 3-D position error
    rotation_rms_rad: float = math.nan


def module_sigma(tag_T_module: Pose3, tag_covariance: np.ndarray) -> ModuleSigma:
    """1-sigma of structure_T_module = structure_T_tag · tag_T_module from the tag's covariance
    (GTSAM tangent: rotation then translation, in the tag frame)."""
    cov = 0.5 * (np.asarray(tag_covariance, float) + np.asarray(tag_covariance, float).T)
    lever = tag_T_module.translation()
    # d(position of the module, tag frame) = -[lever]x dθ + dt; the norm is frame-free
    J = np.hstack([-_skew(lever), np.eye(3)])
    pos = J @ cov @ J.T
    return ModuleSigma(float(math.sqrt(max(np.linalg.eigvalsh(pos).max(), 0.0))),
                       float(math.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0))),
                       float(math.sqrt(max(np.trace(pos), 0.0))), float(math.sqrt(max(np.trace(cov[:3, :3]), 0.0))))


def module_position_covariance(structure_T_tag: Pose3, tag_T_module: Pose3, tag_covariance: np.ndarray) -> np.ndarray:
    """3x3 covariance of the module anchor's position, in the structure frame (for NEES against
    a truth, and for the 1-sigma along any direction)."""
    cov = 0.5 * (np.asarray(tag_covariance, float) + np.asarray(tag_covariance, float).T)
    J = np.hstack([-_skew(tag_T_module.translation()), np.eye(3)])
    R = structure_T_tag.rotation().matrix()
    return R @ (J @ cov @ J.T) @ R.T


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def corner_jacobians(structure_T_camera: Pose3, structure_T_tag: Pose3, K: np.ndarray,
                     tag_corners_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(d uv / d tag, d uv / d camera, uv): the 8x6 Jacobians of the four corner projections and
    the projections (4x2); None when a corner is behind the camera."""
    cal = gtsam.Cal3_S2(float(K[0, 0]), float(K[1, 1]), float(K[0, 1]), float(K[0, 2]), float(K[1, 2]))
    cam = gtsam.PinholeCameraCal3_S2(structure_T_camera, cal)
    JT, JC, uv = np.zeros((8, 6)), np.zeros((8, 6)), np.zeros((4, 2))
    Hp, Hl = np.zeros((3, 6), order="F"), np.zeros((3, 3), order="F")
    Dp, Dpt, Dk = np.zeros((2, 6), order="F"), np.zeros((2, 3), order="F"), np.zeros((2, 5), order="F")
    for i, local in enumerate(np.asarray(tag_corners_m, float)):
        p = structure_T_tag.transformFrom(local, Hp, Hl)
        try:
            uv[i] = cam.project(p, Dp, Dpt, Dk)
        except RuntimeError:
            return None
        JT[2 * i:2 * i + 2] = Dpt @ Hp
        JC[2 * i:2 * i + 2] = Dp
    return JT, JC, uv


def view_information(structure_T_camera: Pose3, structure_T_tag: Pose3, K: np.ndarray, tag_corners_m: np.ndarray,
                     sigma_px: float, camera_covariance: np.ndarray | None = None) -> np.ndarray:
    """Information (6x6, tag tangent) one sighting of a tag adds about its pose: `sigma_px` is the
    face-on corner noise, grown with obliquity as the graph grows it (rig_model.side_ratio); a
    sighting the graph would leave out as too oblique adds nothing."""
    from estimation.rig_model import MIN_SIDE_RATIO, OBLIQUE_EXPONENT

    jac = corner_jacobians(structure_T_camera, structure_T_tag, K, tag_corners_m)
    if jac is None:
        return np.zeros((6, 6))
    JT, JC, uv = jac
    sides = np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1)
    ratio = float(sides.min() / sides.max()) if sides.max() > 0 else 0.0
    if ratio < MIN_SIDE_RATIO:
        return np.zeros((6, 6))
    noise = np.eye(8) * (sigma_px * ratio ** -OBLIQUE_EXPONENT) ** 2
    if camera_covariance is not None:
        noise = noise + JC @ camera_covariance @ JC.T
    return JT.T @ np.linalg.solve(noise, JT)


def covariance_from_information(info: np.ndarray) -> np.ndarray | None:
    """The covariance of an information matrix, None while some direction is unobserved."""
    info = 0.5 * (info + info.T)
    w = np.linalg.eigvalsh(info)
    if w.min() <= 1e-9 * max(w.max(), 1e-30):
        return None
    return np.linalg.inv(info)


def bound_covariances(graph: gtsam.NonlinearFactorGraph, truth: gtsam.Values, keys: Sequence[int]) -> dict[int, np.ndarray]:
    """Marginal covariances of `keys` of a graph built with the true noise, linearised at `truth`
    (the Cramér–Rao bound of the linearised problem)."""
    marginals = gtsam.Marginals(graph, truth)
    return {k: marginals.marginalCovariance(k) for k in keys}
