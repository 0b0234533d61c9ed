"""Module verdicts from an estimate: `ok`, `flagged` (with a reason), `uncertain` or `unverified`.

A module's pose is estimated from its usable tags (not rejected, estimated): the tag's estimated
pose times the designed tag-to-module transform (a deployable's bottom tag places it; its top tag
only if the bottom one is unusable and the module is deployed).  It is compared with the design:
- `unverified`: no usable tag (none seen, or every one rejected as displaced);
- `flagged`: a deployable that is not fully deployed (or kinematically impossible), or a pose
  outside the tolerance for its type (default 5 mm and 1 deg) by more than `band_sigmas` of its
  own 1-sigma uncertainty (so measurement noise alone does not flag a good module); for close-out
  members the reason names the zone (final assembly / captured / outside capture,
  estimation/semantics.py);
- `ok`: inside the tolerance by more than `band_sigmas` of its uncertainty, in position and in
  rotation;
- `uncertain`: neither -- the deviation is within its own uncertainty band of the tolerance, so the
  measurement cannot tell; or a deployable with a tag rejected as displaced whose deployment was
  not read (`deployment_unread`: its two tags not yet seen in the views the check needs), because
  a top tag 15 cm low is what a deployable stopped at 0.35 m of 0.5 m looks like.  The procedure
  takes more views and asks again; a module still uncertain when the view budget is spent is
  reported so, never passed as `ok`.
The 1-sigma is the module's, not its tag's: the tag's covariance carried through the lever arm
from the tag to the module's anchor (estimation/precision.py), where a tag's tilt shows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from estimation.precision import module_position_covariance, module_sigma
from estimation.semantics import DeployCheck, closeout_zone
from lab.core.geometry import Pose3, pose_error
from lab.core.structures.borg import BorgModel
from lab.core.verdicts import FLAGGED, OK, UNCERTAIN, UNVERIFIED, Verdict


@dataclass(frozen=True)
class Tolerance:
    position_m: float = 0.005
    rotation_rad: float = math.radians(1.0)
    # decided only when the deviation is this many of its own sigmas clear of the tolerance: at 2,
    # a good module's noise reaches the band in 2.3 % of readings along one axis, and those are
    # re-measured (`uncertain`) rather than flagged
    band_sigmas: float = 2.0

    def describe(self) -> str:
        return f"{self.position_m * 1000:g} mm / {math.degrees(self.rotation_rad):g} deg"


@dataclass(frozen=True)
class Tolerances:
    deployable: Tolerance = Tolerance()
    closeout_strut: Tolerance = Tolerance()
    closeout_square: Tolerance = Tolerance()

    def of(self, kind: str) -> Tolerance:
        return getattr(self, kind)


def module_from_tag(model: BorgModel, module: str, tag: int, structure_T_tag: Pose3) -> Pose3:
    m = model.module_by_name[module]
    tag_T_module = model.tags[tag].structure_T_tag.inverse().compose(m.structure_T_module)
    return structure_T_tag.compose(tag_T_module)


def verify_module(model: BorgModel, module: str, estimates: Mapping[int, Pose3], *,
                  covariances: Mapping[int, np.ndarray] | None = None, rejected: set[int] | frozenset[int] = frozenset(),
                  not_deployed: Mapping[str, DeployCheck] | None = None,
                  tolerances: Tolerances | None = None,
                  deployment_unread: set[str] | frozenset[str] = frozenset()) -> Verdict:
    """The module's verdict record (lab/core/verdicts.py), with the tolerance it was judged by and
    the tags of it that were measured.  `deployment_unread`: deployables whose deployment check
    has not been read yet (by default none: every deployable counts as read)."""
    m = model.module_by_name[module]
    tol = (tolerances or Tolerances()).of(m.kind)
    judged: dict[str, Any] = {"tolerance_m": tol.position_m, "tolerance_rad": tol.rotation_rad,
              "tags_seen": tuple(t for t in m.tags if t in estimates)}
    covs = covariances or {}
    usable = [t for t in m.tags if t in estimates and t not in rejected]
    rejected_here = [t for t in m.tags if t in rejected]
    if not usable:
        why = (f"tag {', '.join(map(str, rejected_here))} rejected as displaced" if rejected_here
               else "no tag of it was seen")
        return Verdict(module, UNVERIFIED, why, None, None, None, None, (), **judged)
    deploy = (not_deployed or {}).get(module)
    if m.kind == "deployable" and deploy is not None:
        est = module_from_tag(model, module, m.tags[0], estimates[m.tags[0]]) if m.tags[0] in usable else None
        dev = pose_error(est, m.structure_T_module) if est is not None else (None, None)
        return Verdict(module, FLAGGED, deploy.reason, est, dev[0], dev[1], None, tuple(usable), **judged)
    tag = usable[0]
    est = module_from_tag(model, module, tag, estimates[tag])
    unread = m.kind == "deployable" and bool(rejected_here) and module in deployment_unread
    dt, dr = pose_error(est, m.structure_T_module)
    cov = covs.get(tag)
    if cov is not None:
        tag_T_module = model.tags[tag].structure_T_tag.inverse().compose(m.structure_T_module)
        ms = module_sigma(tag_T_module, cov)
        sigma, sigma_r = ms.position_m, ms.rotation_rad
        pos_cov = module_position_covariance(estimates[tag], tag_T_module, cov)
    else:
        sigma, sigma_r, pos_cov = None, None, None
    note = f" (tag {', '.join(map(str, rejected_here))} rejected as displaced)" if rejected_here else ""
    k = tol.band_sigmas
    sp, sr = sigma or 0.0, sigma_r or 0.0
    # A deviation is a finding when it exceeds the tolerance by more than the band of its own
    # uncertainty; it passes when it is inside by as much; in between the measurement cannot tell.
    over = dt - k * sp > tol.position_m or dr - k * sr > tol.rotation_rad
    inside = dt + k * sp <= tol.position_m and dr + k * sr <= tol.rotation_rad
    if unread and not over:
        # a displaced tag on a deployable whose deployment is unread: the module may be deployed
        # short; never `ok` on the other tag alone (an N = 6 study passed three 0.35 m deployments)
        reason = (f"tag {', '.join(map(str, rejected_here))} rejected as displaced and its deployment not yet "
                  f"read (both tags in too few views)")
        return Verdict(module, UNCERTAIN, reason, est, dt, dr, sigma, tuple(usable), sigma_r, pos_cov, **judged)
    if inside:
        return Verdict(module, OK, note.strip(" ()"), est, dt, dr, sigma, tuple(usable), sigma_r, pos_cov, **judged)
    if not over:
        reason = (f"within its uncertainty of the tolerance: {dt * 1000:.2f} mm (1σ {sp * 1000:.2f} mm), "
                  f"{math.degrees(dr):.2f} deg (1σ {math.degrees(sr):.2f} deg), tolerance {tol.describe()}")
        return Verdict(module, UNCERTAIN, reason + note, est, dt, dr, sigma, tuple(usable), sigma_r, pos_cov, **judged)
    reason = (f"out of tolerance: {dt * 1000:.1f} mm (tolerance {tol.position_m * 1000:.1f} mm), "
              f"{math.degrees(dr):.2f} deg (tolerance {math.degrees(tol.rotation_rad):.2f} deg)")
    if m.kind in ("closeout_strut", "closeout_square"):
        design_T_est = m.structure_T_module.between(est)
        p = [model.nodes[i] for i in m.nodes]
        axis_structure = p[1] - p[0]
        axis = m.structure_T_module.rotation().matrix().T @ axis_structure
        lever = max(float(np.linalg.norm(q - m.structure_T_module.translation())) for q in p)
        reason += "; " + closeout_zone(design_T_est, axis, lever).describe()
    return Verdict(module, FLAGGED, reason + note, est, dt, dr, sigma, tuple(usable), sigma_r, pos_cov, **judged)
