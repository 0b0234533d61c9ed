"""What a rig calibration file must mean, not only its shape: the checks `lab rig check` and a BORG
run make before anything moves (docs/hardware.md, "Rig calibration file").

Two kinds:
- `check_covariance`: every covariance in the file is finite, symmetric, positive definite, sanely
  conditioned, and claims a 1-sigma a survey could have measured (`SIGMA_RANGE`).  The reader
  (lab/core/rig_calibration_file.py) applies it to each one as it parses the file.
- `check_fits_rig`: the values are physically possible and close to the rig file's nominal
  geometry -- the rough-measurement bounds of `lab.core.rig_error.ROUGH`, the one place they are
  stated -- and the file was made for this rig.

The conditioning bound, `MAX_CONDITION`, applies to the correlation matrix (the covariance scaled
to unit variances), because the raw matrix mixes rad^2, m^2 and px^2 and a good survey's spans
1e12 in those units (the turntable axis' gauge directions, 1e-7, beside the focal length's
0.1 px).  A run enters the joint covariance as one Gaussian prior, i.e. factors its inverse; in
double precision (16 digits) a condition number of 1e10 still leaves 6 significant digits in that
inverse.  The default rig's full survey writes a joint correlation matrix conditioned near 1.2e5,
so the bound is five orders above anything a survey writes, and refuses a matrix whose inverse
would be round-off (a 1e44 one, a near-duplicate row).
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from lab.core.errors import UserError
from lab.core.geometry import Pose3, Rot3
from lab.core.rig_error import ROUGH

MAX_CONDITION = 1e10
# Each 1-sigma a file may claim, by unit: below, a quantity "known" better than a nanometre or a
# nanoradian (the gauge directions the writer pins at 1e-7 are well above); above, known worse
# than the rough measurement it should improve on -- no calibration at all.
SIGMA_RANGE: dict[str, tuple[float, float]] = {
    "rad": (1e-9, ROUGH.stewart_base_rad),
    "m": (1e-9, ROUGH.stewart_base_m),
    "px": (1e-9, 100.0),
    "1": (1e-9, 1.0),            # the radial distortion correction's terms (dimensionless)
}
POSE_UNITS = ("rad",) * 3 + ("m",) * 3       # GTSAM's tangent order: rotation, then translation
SYMMETRY_TOLERANCE = 1e-6                    # of the correlation: a writer's rounding, not an asymmetry


def check_covariance(cov: np.ndarray, units: Sequence[str], where: str, src: str) -> None:
    """One line naming the file, the key and what is wrong, else nothing."""
    def bad(problem: str) -> UserError:
        return UserError(f"rig calibration {src}: {where}: {problem}")

    C = np.asarray(cov, dtype=float)
    n = len(units)
    if C.shape != (n, n) or not np.all(np.isfinite(C)):
        raise bad(f"expected a finite {n}x{n} matrix")
    d = np.diag(C)
    if np.any(d <= 0):
        k = int(np.argmin(d))
        raise bad(f"variance [{k}][{k}] is {d[k]:g}: a covariance's diagonal must be positive (an all-zero or "
                  f"negative one claims an exactness no survey has)")
    s = np.sqrt(d)
    R = C / np.outer(s, s)
    asym = np.abs(R - R.T)
    if asym.max() > SYMMETRY_TOLERANCE:
        i, j = np.unravel_index(int(np.argmax(asym)), asym.shape)
        raise bad(f"not symmetric: [{i}][{j}] = {C[i, j]:g} but [{j}][{i}] = {C[j, i]:g}")
    R = 0.5 * (R + R.T)
    ev = np.linalg.eigvalsh(R)
    if ev[0] <= 0:
        raise bad(f"not positive definite (smallest eigenvalue of its correlation matrix {ev[0]:.3g}): no "
                  f"Gaussian has it")
    cond = float(ev[-1] / ev[0])
    if cond > MAX_CONDITION:
        raise bad(f"condition number {cond:.3g} of its correlation matrix exceeds {MAX_CONDITION:.0e}: its inverse, "
                  f"which the run uses, would be round-off")
    for k, (sigma, unit) in enumerate(zip(s, units)):
        lo, hi = SIGMA_RANGE[unit]
        if not lo <= sigma <= hi:
            raise bad(f"1 sigma [{k}] is {sigma:.3g} {'' if unit == '1' else unit}: outside [{lo:g}, {hi:g}]"
                      f"{'' if unit == '1' else ' ' + unit} (not a survey's uncertainty; check the unit)")


def _logmap(R: Rot3) -> np.ndarray:
    return np.asarray(Rot3.Logmap(R), dtype=float)


def _near(name: str, what: str, est: Pose3, nominal: Pose3, bound_m: float, bound_rad: float, src: str,
          axes: Sequence[int] = (0, 1, 2), rot_axes: Sequence[int] = (0, 1, 2), origin: str = "the rig file's",
          why: str = "a file for another bench, a flipped frame, or a unit typo") -> None:
    dt = np.asarray(est.translation(), float) - np.asarray(nominal.translation(), float)
    dr = _logmap(nominal.rotation().inverse().compose(est.rotation()))
    for k in axes:
        if abs(dt[k]) > bound_m:
            raise UserError(f"rig calibration {src}: {name}.xyz_m[{k}]: {what} is {dt[k] * 1e3:+.0f} mm from {origin}, "
                            f"beyond the {bound_m * 1e3:.0f} mm a rough measurement can be off "
                            f"(docs/hardware.md): {why}")
    for k in rot_axes:
        if abs(dr[k]) > bound_rad:
            raise UserError(f"rig calibration {src}: {name}.rpy_deg: {what} is turned {math.degrees(dr[k]):+.1f} deg "
                            f"about its {'xyz'[k]} axis from {origin}, beyond the "
                            f"{math.degrees(bound_rad):.1f} deg a rough measurement can be off (docs/hardware.md): {why}")


def check_for_rig(cal: Any, rig: Any, camera: Any, model: Any, src: str) -> None:
    """`check_fits_rig` against a rig (lab.core.config.Rig), its camera file's intrinsics (K, width_px,
    height_px; None: the camera is not calibrated yet, its part is skipped) and the BORG design whose
    rim tags the file located (lab.core.structures.borg.BorgModel)."""
    tags = {t: model.tags[t].structure_T_tag for t in model.turntable.tag_ids}
    check_fits_rig(cal, rig_name=rig.name, world_T_base=rig.stewart.world_T_base,
                   platform_T_camera=rig.camera.platform_T_camera, K=None if camera is None else camera.K,
                   width_px=0 if camera is None else camera.width_px, height_px=0 if camera is None else camera.height_px,
                   turntable_tags=tags, src=src, structure=f"borg:{model.n}")


def check_fits_rig(cal: Any, *, rig_name: str, world_T_base: Pose3, platform_T_camera: Pose3, K: np.ndarray | None,
                   width_px: int, height_px: int, turntable_tags: Mapping[int, Pose3], src: str,
                   structure: str = "the structure") -> None:
    """The calibration `cal` (lab.core.rig_calibration_file.RigCalibration) is for this rig and close to its
    nominal geometry: the rig file's poses, the camera file's K and frame size (K None: not
    checked), the design's rim tags (structure frame).  One line naming the file, key and value,
    else nothing."""
    if not cal.rig:
        raise UserError(f"rig calibration {src}: rig: missing; `lab calibrate rig` names the rig it surveyed, and a "
                        f"file that does not cannot be matched to rig {rig_name!r}")
    if cal.rig != rig_name:
        raise UserError(f"rig calibration {src}: rig: made for rig {cal.rig!r}, not this rig {rig_name!r}; survey this "
                        f"bench with `lab calibrate rig`")
    if K is not None:
        _camera_fits(cal, np.asarray(K, float), width_px, height_px, src)
    _near("platform_T_camera", "the camera mount", cal.platform_T_camera, platform_T_camera, ROUGH.camera_mount_m,
          ROUGH.camera_mount_rad, src)
    _near("world_T_base", "the Stewart base", cal.world_T_base, world_T_base, ROUGH.stewart_base_m,
          ROUGH.stewart_base_rad, src)
    # the axis frame: only where it crosses the plate (x, y) and its tilt (about x, y) mean anything
    _near("world_T_axis", "the turntable axis", cal.world_T_axis, Pose3(), ROUGH.turntable_axis_m,
          ROUGH.turntable_axis_rad, src, axes=(0, 1), rot_axes=(0, 1))
    for tid, pose in sorted(cal.turntable_tags.items()):
        if tid not in turntable_tags:
            raise UserError(f"rig calibration {src}: turntable_tags.{tid}: not a turntable tag of {structure} "
                            f"(those are {min(turntable_tags)}..{max(turntable_tags)}): a file for another structure")
        _near(f"turntable_tags.{tid}", f"tag {tid}", pose, turntable_tags[tid], ROUGH.turntable_tag_m,
              ROUGH.turntable_tag_rad, src, origin=f"where the design of {structure} puts it",
              why="a tag come loose, or a file made for a structure of another size")


def _camera_fits(cal: Any, K0: np.ndarray, width_px: int, height_px: int, src: str) -> None:
    lo, hi = ROUGH.focal_scale
    for key, k, f0 in (("fx_px", 0, K0[0, 0]), ("fy_px", 1, K0[1, 1])):
        f = float(cal.K[k, k])
        if not (f > 0 and lo <= f / f0 <= hi):
            raise UserError(f"rig calibration {src}: camera.{key}: {f:g} px is not within {lo:g}..{hi:g} times the "
                            f"camera file's {f0:.1f} px (a focal length is positive and a focus change moves it by "
                            f"percent, not more)")
    for key, k, size in (("cx_px", 0, width_px), ("cy_px", 1, height_px)):
        c, c0 = float(cal.K[k, 2]), K0[k, 2]
        if not 0 <= c <= size:
            raise UserError(f"rig calibration {src}: camera.{key}: {c:g} px is outside the {width_px}x{height_px} "
                            f"frame")
        if abs(c - c0) > ROUGH.principal_point_px:
            raise UserError(f"rig calibration {src}: camera.{key}: {c:.1f} px is {c - c0:+.1f} px from the camera "
                            f"file's {c0:.1f}, beyond {ROUGH.principal_point_px:g} px")
    # the lens correction, as the displacement it makes at the frame's corner
    r = math.hypot(max(K0[0, 2], width_px - K0[0, 2]) / K0[0, 0], max(K0[1, 2], height_px - K0[1, 2]) / K0[1, 1])
    dk1, dk2 = cal.distortion_correction
    corner_px = abs(K0[0, 0] * r * (dk1 * r ** 2 + dk2 * r ** 4))
    if corner_px > ROUGH.principal_point_px:
        raise UserError(f"rig calibration {src}: distortion_correction: [{dk1:g}, {dk2:g}] moves the frame's corner "
                        f"{corner_px:.0f} px from the camera file's lens, beyond {ROUGH.principal_point_px:g} px: not "
                        f"the same lens")
