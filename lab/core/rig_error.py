"""The errors of a simulated rig: how the true bench differs from its rig file.

A real bench is never the rig file: the camera mount, the Stewart base, the turntable's axis, the
turntable tags and the lens are all known only to millimetres, tenths of a degree, tenths of a
percent, and every move lands a little off.  The simulated world (`sim_devices.world`) builds its
truth as the rig file plus a `RigError`; the software is never told it and must calibrate.

Written as `[sim.rig_error]` in a simulated rig (that bench's own particular errors) or as
`[rig_error]` in a scenario (which replaces the rig's: omitted keys are zero; `ideal = true`
means none).  Keys, units in their names (docs/scenarios.md):

    camera_mount_offset_m     error of platform_T_camera's translation, platform frame
    camera_mount_rotation_rad roll, pitch, yaw of the mount's rotation error, platform axes
    stewart_base_offset_m     error of world_T_base's translation, world frame
    stewart_base_rotation_rad roll, pitch, yaw of the base's rotation error, world axes
    turntable_axis_offset_m   where the true rotation axis crosses the plate, x y, world frame
    turntable_axis_tilt_rad   the true axis' tilt about world x and y
    focal_scale               true focal length / the calibration file's
    principal_point_offset_px true principal point - the calibration file's (u, v)
    turntable_tag_sigma_m     each turntable tag's placement error, 1 sigma per axis (seeded);
                              its rotation error is this over the tag's size (1 mm: 0.57 deg)
    stewart_repeatability_m   per-move random error of the platform pose, 1 sigma per axis
    stewart_repeatability_rad
    turntable_repeatability_rad  per-move random error of the turntable angle, 1 sigma
    lift_axis_tilt_rad        the lift's true travel direction, tilted from world z about x and y
                              (a height h moves the base h along it: h times the tilt sideways)
    lift_repeatability_m      per-move random error of the lift's carriage, 1 sigma per axis
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Callable

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class RigError:
    camera_mount_offset_m: Vec3 = (0.0, 0.0, 0.0)
    camera_mount_rotation_rad: Vec3 = (0.0, 0.0, 0.0)
    stewart_base_offset_m: Vec3 = (0.0, 0.0, 0.0)
    stewart_base_rotation_rad: Vec3 = (0.0, 0.0, 0.0)
    turntable_axis_offset_m: Vec2 = (0.0, 0.0)
    turntable_axis_tilt_rad: Vec2 = (0.0, 0.0)
    focal_scale: float = 1.0
    principal_point_offset_px: Vec2 = (0.0, 0.0)
    turntable_tag_sigma_m: float = 0.0
    stewart_repeatability_m: float = 0.0
    stewart_repeatability_rad: float = 0.0
    turntable_repeatability_rad: float = 0.0
    lift_axis_tilt_rad: Vec2 = (0.0, 0.0)
    lift_repeatability_m: float = 0.0

    @property
    def ideal(self) -> bool:
        return self == RigError()

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def scaled(self, k: float) -> RigError:
        """Every error times k (focal scale about 1): the benches sweep the size of a rig's errors."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "focal_scale":
                out[f.name] = 1.0 + k * (v - 1.0)
            elif isinstance(v, tuple):
                out[f.name] = tuple(k * x for x in v)
            else:
                out[f.name] = k * v
        return RigError(**out)

    def magnitudes(self) -> dict[str, float]:
        """The sizes a person reads: mm, degrees, percent, pixels."""
        def n(v) -> float:
            return math.sqrt(sum(x * x for x in v))
        return {"camera_mount_mm": n(self.camera_mount_offset_m) * 1e3,
                "camera_mount_deg": math.degrees(n(self.camera_mount_rotation_rad)),
                "stewart_base_mm": n(self.stewart_base_offset_m) * 1e3,
                "stewart_base_deg": math.degrees(n(self.stewart_base_rotation_rad)),
                "turntable_axis_mm": n(self.turntable_axis_offset_m) * 1e3,
                "turntable_axis_tilt_deg": math.degrees(n(self.turntable_axis_tilt_rad)),
                "focal_percent": (self.focal_scale - 1.0) * 100.0,
                "principal_point_px": n(self.principal_point_offset_px),
                "turntable_tag_mm": self.turntable_tag_sigma_m * 1e3,
                "lift_axis_tilt_deg": math.degrees(n(self.lift_axis_tilt_rad))}


_VECTORS = {"camera_mount_offset_m": 3, "camera_mount_rotation_rad": 3, "stewart_base_offset_m": 3,
            "stewart_base_rotation_rad": 3, "turntable_axis_offset_m": 2, "turntable_axis_tilt_rad": 2,
            "principal_point_offset_px": 2, "lift_axis_tilt_rad": 2}
_SCALARS = ("focal_scale", "turntable_tag_sigma_m", "stewart_repeatability_m", "stewart_repeatability_rad",
            "turntable_repeatability_rad", "lift_repeatability_m")
KEYS = tuple(_VECTORS) + _SCALARS


@dataclass(frozen=True)
class RoughBounds:
    """How far a bench may be from its rig file and still be "known roughly" (docs/hardware.md,
    "Measuring the mount poses roughly"): beyond these a value is not a measurement error but a
    mistake -- a unit typo, a flipped frame, a file for another bench.  The one statement of these
    bounds: a simulated rig's errors (`[sim.rig_error]`) and a rig calibration file's values
    (lab/core/rig_calibration_check.py) are both held to them.  Per component; SI units."""

    camera_mount_m: float = 0.1
    camera_mount_rad: float = 0.2
    stewart_base_m: float = 0.2
    stewart_base_rad: float = 0.2
    turntable_axis_m: float = 0.05
    turntable_axis_rad: float = 0.05
    focal_scale: tuple[float, float] = (0.9, 1.1)     # true focal length / the camera file's
    principal_point_px: float = 50.0
    # each rim tag from its design spot: the run's tag elimination takes a tag further off than
    # its 5 cm cutoff as displaced, so a calibration cannot put one there and be believed
    turntable_tag_m: float = 0.05
    turntable_tag_rad: float = 0.2
    turntable_tag_sigma_m: float = 0.02               # the scatter of the glue, 1 sigma
    lift_axis_rad: float = 0.05


ROUGH = RoughBounds()
# Beyond these the rig is not "known roughly" but wrong: a typo in a unit, most likely.
_BOUNDS = {"camera_mount_offset_m": ROUGH.camera_mount_m, "camera_mount_rotation_rad": ROUGH.camera_mount_rad,
           "stewart_base_offset_m": ROUGH.stewart_base_m, "stewart_base_rotation_rad": ROUGH.stewart_base_rad,
           "turntable_axis_offset_m": ROUGH.turntable_axis_m, "turntable_axis_tilt_rad": ROUGH.turntable_axis_rad,
           "principal_point_offset_px": ROUGH.principal_point_px, "turntable_tag_sigma_m": ROUGH.turntable_tag_sigma_m,
           "stewart_repeatability_m": 0.005, "stewart_repeatability_rad": 0.01, "turntable_repeatability_rad": 0.01,
           "lift_axis_tilt_rad": ROUGH.lift_axis_rad, "lift_repeatability_m": 0.005}


def parse_rig_error(table: Any, error: Callable[[str, str], Exception]) -> RigError:
    """A `[rig_error]` / `[sim.rig_error]` table.  `error(key, problem)` makes the caller's
    one-line error naming its file and key.  Omitted keys are zero; `ideal = true` means none."""
    if not isinstance(table, dict):
        raise error("", f"expected a table, got {table!r}")
    allowed = set(KEYS) | {"ideal"}
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise error(unknown[0], f"unknown key (allowed: ideal, {', '.join(KEYS)})")
    ideal = table.get("ideal", False)
    if not isinstance(ideal, bool):
        raise error("ideal", f"expected true or false, got {ideal!r}")
    if ideal:
        others = sorted(set(table) - {"ideal"})
        if others:
            raise error(others[0], "ideal = true means no rig error: leave the other keys out")
        return RigError()
    values: dict[str, Any] = {}
    for key, n in _VECTORS.items():
        if key not in table:
            continue
        v = table[key]
        if not (isinstance(v, list) and len(v) == n and all(
                not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) for x in v)):
            raise error(key, f"expected a list of {n} finite numbers, got {v!r}")
        if max(abs(x) for x in v) > _BOUNDS[key]:
            raise error(key, f"{v} is beyond {_BOUNDS[key]} per component: not a rig known roughly (check the unit)")
        values[key] = tuple(float(x) for x in v)
    for key in _SCALARS:
        if key not in table:
            continue
        v = table[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise error(key, f"expected a finite number, got {v!r}")
        if key == "focal_scale":
            lo, hi = ROUGH.focal_scale
            if not lo <= v <= hi:
                raise error(key, f"must be in [{lo}, {hi}] (true focal length / calibrated), got {v}")
        elif not 0.0 <= v <= _BOUNDS[key]:
            raise error(key, f"must be in [0, {_BOUNDS[key]}], got {v}")
        values[key] = float(v)
    return RigError(**values)
