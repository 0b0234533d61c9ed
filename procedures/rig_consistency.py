"""Does what the camera sees agree with the rig calibration as a whole?  A BORG run asks after every
round of views, so that a wrong rig (a device moved since the survey, a file that is not this
bench's) stops the run with that said, instead of its error being taken for the structure's:
every module `unverified` with its tags "rejected as displaced", or flagged for a deviation the
rig made.

Two tests, each on something the structure cannot explain:
- the turntable's rim tags are part of the rig calibration: the camera must see them where the
  calibration puts them, through the calibrated chain (turntable axis, Stewart base, platform
  pose, camera mount, intrinsics).  A calibration that fits sees them a tenth of a pixel off
  (the default rig: median 0.1 px, its corner noise and the calibration's own uncertainty);
  `MAX_TURNTABLE_PX` is 30 times that.  One tag off is that tag's business (the run's tag
  elimination takes it out); the median over the round's rim sightings is the rig's.
- most of the structure cannot be wrong at once in shape: when more than half of the structure's
  tags (at least `MIN_STRUCTURE_TAGS`) lie beyond the tag elimination's cutoff from the best rigid
  fit of the design to them alone, the measurement is distorted, not the truss.  A structure
  placed off its spot on the turntable moves rigidly and fits; a few bad modules are a minority.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from estimation.fiducials import tag_object_points
from estimation.rig_model import RigGeometry, ViewMotion
from estimation.tag_elimination import eliminate_tags
from lab.core.geometry import Pose3
from lab.core.rig_calibration_file import RigCalibration
from lab.core.structures.borg import BorgModel

# 3 px at the rim's 2.2 m is 7 mm: a rig that far off puts every module's verdict off by about its
# 5 mm tolerance; a fitting calibration's median is 0.1 px
MAX_TURNTABLE_PX = 3.0
MIN_TURNTABLE_SIGHTINGS = 3         # fewer say too little about the rig as a whole
MIN_STRUCTURE_TAGS = 3


@dataclass(frozen=True)
class RigDisagreement:
    """What did not fit, said for the operator."""

    reason: str


def turntable_disagreement(views: Sequence[Mapping[str, Any]], geometry: RigGeometry, calibration: RigCalibration,
                           dist: np.ndarray, source: str) -> RigDisagreement | None:
    """The rim tags the round's views saw against where `calibration` puts them (views: the run's
    view records, with `turntable_rad`, `stewart_pose`, `lift_m` and `detections`)."""
    import cv2

    d = np.asarray(dist, float).ravel().copy()
    d[:2] += np.asarray(calibration.distortion_correction, float)   # the lens the calibration found
    errors: list[float] = []
    tags: set[int] = set()
    for v in views:
        seen = [x for x in v["detections"] if int(x["id"]) in calibration.turntable_tags]
        if not seen:
            continue
        motion = ViewMotion(float(v["turntable_rad"]), tuple(float(x) for x in v["stewart_pose"]),
                            float(v.get("lift_m", 0.0)))
        camera_T_structure = geometry.predict(motion, calibration.world_T_axis, calibration.world_T_base,
                                              calibration.platform_T_camera).inverse()
        for x in seen:
            tid = int(x["id"])
            T = camera_T_structure.compose(calibration.turntable_tags[tid])
            pts = tag_object_points(float(x["size_m"])) @ T.rotation().matrix().T + T.translation()
            if np.any(pts[:, 2] <= 0):
                errors.append(float("inf"))         # the calibration puts it behind the camera
            else:
                uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), calibration.K, d)
                errors.append(float(np.linalg.norm(uv.reshape(-1, 2) - np.asarray(x["corners_px"], float),
                                                   axis=1).mean()))
            tags.add(tid)
    if len(errors) < MIN_TURNTABLE_SIGHTINGS:
        return None
    median = float(np.median(errors))
    if median <= MAX_TURNTABLE_PX:
        return None
    return RigDisagreement(
        f"the camera disagrees with the rig calibration as a whole: the turntable tags "
        f"{', '.join(map(str, sorted(tags)))} appear a median {median:.1f} px from where {source} puts them "
        f"({len(errors)} sightings; a fitting calibration is within {MAX_TURNTABLE_PX:g} px). The rig or its "
        f"calibration is wrong (a device moved since the survey, or the file is not this bench's), not the "
        f"structure: survey the rig again with `lab calibrate rig`")


def structure_disagreement(estimates: Mapping[int, Pose3], model: BorgModel, cutoff_m: float,
                           source: str) -> RigDisagreement | None:
    """Most of the structure's estimated tags off the design's shape (rim tags left out)."""
    tags = {t: p for t, p in estimates.items() if t in model.tags and model.tags[t].module != "turntable"}
    if len(tags) < MIN_STRUCTURE_TAGS:
        return None
    fit = eliminate_tags(tags, model, cutoff_m=cutoff_m, max_remove=len(tags))
    off = sorted(t for t, d in fit.distances_m.items() if d > cutoff_m)
    if len(off) < MIN_STRUCTURE_TAGS or 2 * len(off) <= len(tags):
        return None
    return RigDisagreement(
        f"the camera disagrees with the rig calibration as a whole: {len(off)} of the structure's {len(tags)} tags "
        f"measured ({', '.join(map(str, off[:8]))}{'...' if len(off) > 8 else ''}) are more than "
        f"{cutoff_m * 1e3:.0f} mm off the design's shape, which no rigid placement explains. The rig or its "
        f"calibration ({source}) is wrong, not the structure: check the rig and survey it again with "
        f"`lab calibrate rig`")
