"""How bad the simulated camera's pictures are: its imaging keys, their units and bounds (issue 19).

One set of keys, read from two places with the same checks:
- a simulated rig's `[sim.camera]` and `[sim.tags]` (that bench's camera and its printed tags);
- a scenario's `[camera]` and `[tags]`, which replace the rig's value key by key: a key the
  scenario leaves out keeps the rig's value (a scenario with only `pixel_noise = 6` keeps the rig's
  blur, shot noise, vignetting, ...).

Keys (units in their names; what the renderer does with each: `sim_devices/render.py`,
`sim_devices/world.py`):

    [camera]
    pixel_noise          read noise, grey levels (std), signal-independent
    blur_px              the lens's Gaussian blur sigma, px, at the focus distance
    full_well_e          electrons at white (255): photon shot noise of variance signal*255/full_well_e
                         grey levels^2 on top of the read noise; 0 = no shot noise
    focus_distance_m     where the lens is focused; blur grows away from it (thin lens, f_number,
                         the focal length fx * pixel_pitch_um); 0 = everything in focus (blur_px
                         everywhere, the ideal camera's infinite depth of field)
    f_number             aperture (N): the circle of confusion scales as 1/N
    vignetting           fraction of brightness lost at the frame's corners (radial quadratic falloff)
    lighting_variation   uneven light: a smooth field across the frame within +-this fraction, and
                         each tag's own light level within +-this fraction (seeded)
    jpeg_quality         the camera sends JPEG at this quality (1..100), as an IP camera does;
                         0 = lossless PNG
    distortion_error_px  the true lens's distortion differs from its calibration file by this
                         displacement at the frame's corners (seeded sign and k1/k2 mix)
    pixel_pitch_um       (rig only) the sensor's pixel size: focal length = fx * pitch

    [tags]
    print_scale_sigma    each printed tag's size is off by this relative error, 1 sigma (seeded per tag)
    flatness_m           each tag's surface bows by this much at its centre, relative to the plane of
                         its corners (seeded sign and shape per tag)

All off (`IDEAL` below, every effect 0) is the camera the simulator had before issue 19: the
ideal camera a study compares against."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any, Callable

__all__ = ["Imaging", "IDEAL", "SCENARIO_CAMERA_KEYS", "RIG_CAMERA_KEYS", "TAG_KEYS", "check", "parse_imaging",
           "scenario_tables"]


@dataclass(frozen=True)
class Imaging:
    """Every imaging parameter of a simulated camera; the defaults are the ideal camera (what a rig
    file written before issue 19 gets: read noise 2 grey levels, blur 0.6 px, nothing else)."""

    pixel_noise: float = 2.0
    blur_px: float = 0.6
    full_well_e: float = 0.0
    focus_distance_m: float = 0.0
    f_number: float = 2.8
    vignetting: float = 0.0
    lighting_variation: float = 0.0
    jpeg_quality: int = 0
    distortion_error_px: float = 0.0
    pixel_pitch_um: float = 3.45
    print_scale_sigma: float = 0.0
    flatness_m: float = 0.0

    def with_overrides(self, overrides: dict[str, Any]) -> Imaging:
        """These values, with the given keys (None: keep) replaced."""
        return replace(self, **{k: v for k, v in overrides.items() if v is not None})

    @property
    def ideal(self) -> bool:
        """No effect beyond read noise and a fixed blur."""
        return (self.full_well_e == 0 and self.focus_distance_m == 0 and self.vignetting == 0
                and self.lighting_variation == 0 and self.jpeg_quality == 0 and self.distortion_error_px == 0
                and self.print_scale_sigma == 0 and self.flatness_m == 0)

    def focal_length_m(self, fx_px: float) -> float:
        """The lens's focal length: fx (px) times the pixel pitch."""
        return float(fx_px) * self.pixel_pitch_um * 1e-6


IDEAL = Imaging()

SCENARIO_CAMERA_KEYS = ("pixel_noise", "blur_px", "full_well_e", "focus_distance_m", "f_number", "vignetting",
                        "lighting_variation", "jpeg_quality", "distortion_error_px")
RIG_CAMERA_KEYS = SCENARIO_CAMERA_KEYS + ("pixel_pitch_um",)
TAG_KEYS = ("print_scale_sigma", "flatness_m")

def scenario_tables(imaging: Imaging) -> str:
    """A scenario's `[camera]` and `[tags]` tables that set every imaging key to `imaging`'s value
    (e.g. `scenario_tables(IDEAL)`: the ideal camera, whatever the rig's defaults)."""
    def table(name: str, keys: tuple[str, ...]) -> list[str]:
        return [f"[{name}]"] + [f"{k} = {getattr(imaging, k)!r}" for k in keys]
    return "\n".join(table("camera", SCENARIO_CAMERA_KEYS) + [""] + table("tags", TAG_KEYS)) + "\n"


# (minimum, maximum, unit) of each key; beyond them a value is a unit mistake or a camera no one
# would use, refused with the key named.
_BOUNDS: dict[str, tuple[float, float, str]] = {
    "pixel_noise": (0.0, 100.0, " grey levels"),
    "blur_px": (0.0, 20.0, " px"),
    "full_well_e": (0.0, 1e7, " electrons"),
    "focus_distance_m": (0.0, 1000.0, " m"),
    "f_number": (0.5, 64.0, ""),
    "vignetting": (0.0, 0.95, ""),
    "lighting_variation": (0.0, 0.5, ""),
    "jpeg_quality": (0, 100, ""),
    "distortion_error_px": (0.0, 50.0, " px"),
    "pixel_pitch_um": (0.5, 50.0, " um"),
    "print_scale_sigma": (0.0, 0.05, ""),
    "flatness_m": (0.0, 0.01, " m"),
}
MIN_FULL_WELL_E = 100.0        # below it a "white" pixel is 10 % noise: a typo, not a sensor
MIN_FOCUS_DISTANCE_M = 0.05


def check(key: str, value: Any) -> float | int:
    """The checked value of one key, or ValueError(the problem, in a phrase)."""
    lo, hi, unit = _BOUNDS[key]
    if key == "jpeg_quality":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"expected an integer 0..100 (0 = lossless PNG), got {value!r}")
    elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"expected a finite number, got {value!r}")
    if not lo <= value <= hi:
        raise ValueError(f"must be within [{lo:g}, {hi:g}]{unit}, got {value!r}")
    if key == "full_well_e" and 0 < value < MIN_FULL_WELL_E:
        raise ValueError(f"must be 0 (no shot noise) or >= {MIN_FULL_WELL_E:g} electrons, got {value!r}")
    if key == "focus_distance_m" and 0 < value < MIN_FOCUS_DISTANCE_M:
        raise ValueError(f"must be 0 (everything in focus) or >= {MIN_FOCUS_DISTANCE_M:g} m, got {value!r}")
    return int(value) if key == "jpeg_quality" else float(value)


def parse_imaging(camera: Any, tags: Any, error: Callable[[str, str], Exception], *,
                  camera_keys: tuple[str, ...] = SCENARIO_CAMERA_KEYS,
                  camera_where: str = "camera", tags_where: str = "tags") -> dict[str, Any]:
    """The keys given in a `[camera]` and a `[tags]` table, checked: {key: value} (omitted keys are
    absent).  `error(key, problem)` makes the caller's one-line error naming its file and key (keys
    as `camera.full_well_e`, `tags.flatness_m`, with the table names given)."""
    out: dict[str, Any] = {}
    for where, table, keys in ((camera_where, camera, camera_keys), (tags_where, tags, TAG_KEYS)):
        if not isinstance(table, dict):
            raise error(where, f"expected a table, got {table!r}")
        unknown = sorted(set(table) - set(keys))
        if unknown:
            raise error(f"{where}.{unknown[0]}", f"unknown key (allowed: {', '.join(keys)})")
        for key in keys:
            if key in table:
                try:
                    out[key] = check(key, table[key])
                except ValueError as exc:
                    raise error(f"{where}.{key}", str(exc)) from None
    return out


assert {f.name for f in fields(Imaging)} == set(RIG_CAMERA_KEYS) | set(TAG_KEYS)
