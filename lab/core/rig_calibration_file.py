"""A rig calibration: where the camera mount, the Stewart base and the turntable axis really are,
the camera's corrected focal length and principal point, the turntable tags as glued, each with
its uncertainty.  Written by `lab calibrate rig`, referenced from the rig's `[calibration] file`,
read by `lab run borg` as the prior of the calibration it refines (docs/calibration.md).

Frames (docs/architecture.md): `world` is where the turntable plate sits at encoder zero;
`world_T_axis` is a frame whose z axis is the turntable's true rotation axis -- only its tilt
(rotation about x and y) and where it crosses the plate (x, y) mean anything; its yaw and height
are fixed at zero by convention.  Covariances are 6x6 in GTSAM's tangent order (rotation, then
translation) at the estimate; the intrinsics' is 4x4 over (fx, fy, cx, cy).

The marginals alone would lose what matters most: the survey locates the three rig poses and the
turntable tags together, so their errors are correlated (the tags' glue errors move the frame they
all define; a shift of the base trades against a shift of the mount; the focal length against
the distance to everything).  `joint_covariance` keeps the whole covariance over `JOINT_POSES`
(6x6 blocks in the same tangent order), the intrinsics (5: fx, fy, skew, cx, cy, GTSAM's Cal3_S2),
the lens's radial distortion correction (2: dk1, dk2), then each turntable tag in id order (6 each), and a run takes it as one prior: twelve tags'
marginals used as independent priors count the frame's common error twelve times (a module's
1-sigma 3x too small), and intrinsics held exact hide the focal length's share.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lab.core.errors import UserError
from lab.core.files import read_json
from lab.core.geometry import Pose3, from_xyzrpy, to_xyzrpy
from lab.core.rig_calibration_check import POSE_UNITS, check_covariance

FORMAT = "lab.rig_calibration/1"
POSES = ("platform_T_camera", "world_T_base", "world_T_axis")
JOINT_POSES = ("world_T_axis", "world_T_base", "platform_T_camera")   # the joint covariance's first blocks


@dataclass(frozen=True)
class RigCalibration:
    platform_T_camera: Pose3
    world_T_base: Pose3
    world_T_axis: Pose3
    K: np.ndarray                                   # 3x3, the camera file's distortion still applies
    covariance: dict[str, np.ndarray]               # POSES -> 6x6, "K" -> 4x4 (fx, fy, cx, cy)
    turntable_tags: dict[int, Pose3] = field(default_factory=dict)         # structure frame
    turntable_tag_covariance: dict[int, np.ndarray] = field(default_factory=dict)
    rms_px: float = float("nan")                    # corner reprojection RMS of the solve
    views: int = 0
    rig: str = ""
    created: str = ""
    # over JOINT_POSES, "K" (5), then sorted(turntable_tags); None: marginals only
    joint_covariance: np.ndarray | None = None
    # the face-on corner noise the survey's residuals implied: a run's graph starts from it
    corner_sigma_px: float = float("nan")
    # the true lens's radial terms minus the camera file's (dk1, dk2), as the survey found them
    distortion_correction: tuple[float, float] = (0.0, 0.0)
    # the scatter of the tags' apparent scale (print and detector), as the survey measured it
    tag_scale_sigma: float = float("nan")
    # the devices' repeatability against the rig file's datasheet values, as the survey measured it
    # (a run's chain factors take theirs times this)
    repeatability_scale: float = float("nan")

    def joint_blocks(self) -> tuple[tuple[str | int, int], ...]:
        """What the joint covariance's blocks are, in order, with their sizes."""
        return joint_blocks(self.turntable_tags)

    def sigmas(self) -> dict[str, dict[str, float]]:
        """1-sigma of each quantity in the units a person reads (mm, deg, px)."""
        out: dict[str, dict[str, float]] = {}
        for name in POSES:
            d = np.sqrt(np.clip(np.diag(self.covariance[name]), 0.0, None))
            out[name] = {"rot_deg": [math.degrees(x) for x in d[:3]], "xyz_mm": [x * 1e3 for x in d[3:]]}  # type: ignore[dict-item]
        k = np.sqrt(np.clip(np.diag(self.covariance["K"]), 0.0, None))
        out["K"] = {"fx_px": float(k[0]), "fy_px": float(k[1]), "cx_px": float(k[2]), "cy_px": float(k[3])}
        return out

    def to_json(self) -> dict[str, Any]:
        def pose(p: Pose3, cov: np.ndarray | None) -> dict[str, Any]:
            x = to_xyzrpy(p)
            d: dict[str, Any] = {"xyz_m": [float(v) for v in x[:3]], "rpy_deg": [math.degrees(v) for v in x[3:]]}
            if cov is not None:
                d["covariance"] = np.asarray(cov, float).tolist()
            return d
        return {
            "format": FORMAT, "rig": self.rig, "created": self.created or time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "views": self.views, "rms_px": self.rms_px,
            **({"corner_sigma_px": self.corner_sigma_px} if math.isfinite(self.corner_sigma_px) else {}),
            "distortion_correction": [float(x) for x in self.distortion_correction],
            **({"tag_scale_sigma": self.tag_scale_sigma} if math.isfinite(self.tag_scale_sigma) else {}),
            **({"repeatability_scale": self.repeatability_scale} if math.isfinite(self.repeatability_scale) else {}),
            **{name: pose(getattr(self, name), self.covariance[name]) for name in POSES},
            "camera": {"fx_px": float(self.K[0, 0]), "fy_px": float(self.K[1, 1]), "cx_px": float(self.K[0, 2]),
                       "cy_px": float(self.K[1, 2]), "covariance": np.asarray(self.covariance["K"], float).tolist()},
            "turntable_tags": {str(t): pose(p, self.turntable_tag_covariance.get(t))
                               for t, p in sorted(self.turntable_tags.items())},
            "sigmas": self.sigmas(),
            **({"joint_covariance": np.asarray(self.joint_covariance, float).tolist()}
               if self.joint_covariance is not None else {}),
        }

    def save(self, path: str | Path) -> Path:
        p = Path(path)
        tmp = p.with_name(p.name + ".tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=1) + "\n")
        tmp.replace(p)
        return p


def _measured(data: dict[str, Any], key: str, maximum: float, unit: str, src: str) -> float:
    """An optional measured sigma of the file: a number in (0, maximum], or nan when absent."""
    if key not in data:
        return float("nan")
    try:
        value = float(data[key])
        if not (math.isfinite(value) and 0 < value <= maximum):
            raise ValueError
    except (TypeError, ValueError):
        raise UserError(f"rig calibration {src}: {key}: expected a number in (0, {maximum:g}]{unit}, "
                        f"got {data[key]!r}") from None
    return value


def joint_blocks(turntable_tags: Any) -> tuple[tuple[str | int, int], ...]:
    return (*((name, 6) for name in JOINT_POSES), ("K", 5), ("distortion", 2),
            *((int(t), 6) for t in sorted(turntable_tags)))


def joint_units(turntable_tags: Any) -> tuple[str, ...]:
    """The unit of each row of the joint covariance (lab.core.rig_calibration_check.SIGMA_RANGE's keys)."""
    units: list[str] = []
    for name, _ in joint_blocks(turntable_tags):
        units += ["px"] * 5 if name == "K" else ["1"] * 2 if name == "distortion" else list(POSE_UNITS)
    return tuple(units)


def _pose(d: Any, where: str, src: str) -> tuple[Pose3, np.ndarray | None]:
    try:
        xyz = [float(v) for v in d["xyz_m"]]
        rpy = [math.radians(float(v)) for v in d["rpy_deg"]]
        if len(xyz) != 3 or len(rpy) != 3 or not all(map(math.isfinite, xyz + rpy)):
            raise ValueError
        cov = None
        if "covariance" in d:
            cov = np.asarray(d["covariance"], dtype=float)
            if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
                raise ValueError
    except (KeyError, TypeError, ValueError):
        raise UserError(f"rig calibration {src}: {where}: expected {{xyz_m: [3], rpy_deg: [3], covariance: 6x6}}") from None
    if cov is not None:
        check_covariance(cov, POSE_UNITS, f"{where}.covariance", src)
    return from_xyzrpy([*xyz, *rpy]), cov


def load_rig_calibration(path: str | Path) -> RigCalibration:
    return rig_calibration_from_json(read_json(path, "rig calibration"), str(path))


def rig_calibration_from_json(data: Any, p: str = "<json>") -> RigCalibration:
    """The record from its JSON form (a file, or a run's checkpoint)."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise UserError(f"rig calibration {p}: format: expected {FORMAT!r} (written by `lab calibrate rig`)")
    poses, covs = {}, {}
    for name in POSES:
        if name not in data:
            raise UserError(f"rig calibration {p}: {name}: missing")
        poses[name], c = _pose(data[name], name, p)
        if c is None:
            raise UserError(f"rig calibration {p}: {name}.covariance: missing")
        covs[name] = c
    cam = data.get("camera")
    try:
        K = np.array([[float(cam["fx_px"]), 0.0, float(cam["cx_px"])], [0.0, float(cam["fy_px"]), float(cam["cy_px"])],
                      [0.0, 0.0, 1.0]])
        covs["K"] = np.asarray(cam["covariance"], dtype=float)
        if covs["K"].shape != (4, 4) or not np.all(np.isfinite(K)) or not np.all(np.isfinite(covs["K"])):
            raise ValueError
    except (KeyError, TypeError, ValueError):
        raise UserError(f"rig calibration {p}: camera: expected fx_px, fy_px, cx_px, cy_px and a 4x4 covariance") from None
    for key, value in (("fx_px", K[0, 0]), ("fy_px", K[1, 1]), ("cx_px", K[0, 2]), ("cy_px", K[1, 2])):
        # a focal length is positive; a principal point is on the image, whose pixels count from 0
        if not (value > 0 if key.startswith("f") else value >= 0):
            raise UserError(f"rig calibration {p}: camera.{key}: {value:g} px is not physically possible "
                            f"({'a focal length is positive' if key.startswith('f') else 'pixels count from 0'})")
    check_covariance(covs["K"], ("px",) * 4, "camera.covariance", p)
    tags, tag_covs = {}, {}
    for k, v in (data.get("turntable_tags") or {}).items():
        try:
            tid = int(k)
        except ValueError:
            raise UserError(f"rig calibration {p}: turntable_tags.{k}: not a tag id") from None
        tags[tid], c = _pose(v, f"turntable_tags.{k}", p)
        if c is not None:
            tag_covs[tid] = c
    try:
        dk = tuple(float(x) for x in data.get("distortion_correction", (0.0, 0.0)))
        if len(dk) != 2 or not all(map(math.isfinite, dk)):
            raise ValueError
    except (TypeError, ValueError):
        raise UserError(f"rig calibration {p}: distortion_correction: expected [dk1, dk2], got "
                        f"{data.get('distortion_correction')!r}") from None
    corner_sigma = _measured(data, "corner_sigma_px", 5.0, " px", p)
    tag_scale = _measured(data, "tag_scale_sigma", 0.05, "", p)
    repeat = _measured(data, "repeatability_scale", 20.0, "", p)
    joint = None
    if "joint_covariance" in data:
        n = sum(size for _, size in joint_blocks(tags))
        try:
            joint = np.asarray(data["joint_covariance"], dtype=float)
            if joint.shape != (n, n) or not np.all(np.isfinite(joint)):
                raise ValueError
        except (TypeError, ValueError):
            raise UserError(f"rig calibration {p}: joint_covariance: expected a finite {n}x{n} matrix "
                            f"(the rig poses, the intrinsics and {len(tags)} turntable tags)") from None
        check_covariance(joint, joint_units(tags), "joint_covariance", p)
    rms, views = data.get("rms_px", float("nan")), data.get("views", 0)
    if isinstance(rms, bool) or not isinstance(rms, (int, float, type(None))) or (rms is not None and rms < 0):
        raise UserError(f"rig calibration {p}: rms_px: expected a non-negative number, got {rms!r}")
    if isinstance(views, bool) or not isinstance(views, int) or views < 0:
        raise UserError(f"rig calibration {p}: views: expected a count of views, got {views!r}")
    return RigCalibration(poses["platform_T_camera"], poses["world_T_base"], poses["world_T_axis"], K, covs, tags,
                          tag_covs, float("nan") if rms is None else float(rms), views,
                          str(data.get("rig", "")), str(data.get("created", "")), joint, corner_sigma, dk, tag_scale,
                          repeat)
