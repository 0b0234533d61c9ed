"""Scenario files (TOML): what goes wrong in a simulated run — seed, noise, structure faults,
device faults.  Format and examples: docs/scenarios.md.  Every key is checked; a bad file gets an
error naming the key and the problem."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lab.core.errors import UserError
from lab.core.files import read_toml
from lab.core.imaging import parse_imaging
from lab.core.rig_error import RigError, parse_rig_error

BORG_FAULT_KINDS = ("partial_deploy", "tag_displaced", "module_offset")
DEVICE_FAULT_KINDS = ("timeout", "garbled", "disconnect", "stuck", "http_500")


@dataclass(frozen=True)
class BorgFault:
    kind: str                                   # one of BORG_FAULT_KINDS
    module: str | None = None                   # partial_deploy, module_offset
    tag: int | None = None                      # tag_displaced
    height_m: float | None = None               # partial_deploy: true deployed height
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)      # structure frame
    rotation_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)  # roll, pitch, yaw about fixed axes


@dataclass(frozen=True)
class DeviceFault:
    device: str                 # rig name: "turntable", "stewart", "camera", "ipjr1", ...
    kind: str                   # one of DEVICE_FAULT_KINDS
    after_commands: int = 0     # the fault starts after this many commands to that device
    count: int = 1              # how many commands it affects (0 = from then on)


@dataclass(frozen=True)
class TrussNoise:
    sigma_length_m: float = 5.975e-4   # sqrt(3.57e-7 m^2): the IPJR paper's struts
    sigma_measure_m: float = 2.5e-4    # sqrt(6.25e-8 m^2): the paper's ruler


@dataclass(frozen=True)
class CameraNoise:
    """A scenario's `[camera]` and `[tags]` keys (`lab/core/imaging.py`); None: the rig's own value
    (`[sim.camera]`, `[sim.tags]`), so a scenario changes only what it names."""

    pixel_noise: float | None = None         # read noise, grey levels, std
    blur_px: float | None = None             # Gaussian blur sigma at the focus distance, px
    full_well_e: float | None = None         # electrons at white (0: no shot noise)
    focus_distance_m: float | None = None    # 0: everything in focus
    f_number: float | None = None
    vignetting: float | None = None          # fraction of brightness lost at the frame's corners
    lighting_variation: float | None = None  # uneven light across the frame and from tag to tag
    jpeg_quality: int | None = None          # 0: lossless PNG
    distortion_error_px: float | None = None # true lens vs its calibration file, at the corners
    print_scale_sigma: float | None = None   # [tags]: each printed tag's relative size error
    flatness_m: float | None = None          # [tags]: each tag's bow at its centre

    def overrides(self) -> dict[str, Any]:
        """The keys this scenario sets: {key: value}."""
        from dataclasses import asdict

        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass(frozen=True)
class Scenario:
    seed: int = 0
    borg_faults: tuple[BorgFault, ...] = ()
    device_faults: tuple[DeviceFault, ...] = ()
    truss: TrussNoise = field(default_factory=TrussNoise)
    camera: CameraNoise = field(default_factory=CameraNoise)
    source: str = "<default>"
    rig_error: RigError | None = None     # None: the rig's own [sim.rig_error]

    def to_dict(self) -> dict[str, Any]:
        from dataclasses import asdict

        return asdict(self)


def _err(source: str, key: str, problem: str) -> UserError:
    return UserError(f"scenario {source}: {key}: {problem}")


# Bounds on what a scenario may ask of the simulator: beyond them a run is meaningless (a 1e9 m
# strut error) or never ends, so they are refused rather than run.
MAX_OFFSET_M = 1.0            # structure faults: offsets and displacements
MAX_ROTATION_RAD = 3.2        # a little over pi: any orientation, never a wound-up angle
MAX_SIGMA_M = 1.0             # truss strut / ruler noise (the IPJR paper studies 0.1 m on 1 m struts)
MAX_FAULT_COMMANDS = 1_000_000


def _vec3(source: str, key: str, value: Any, bound: float = MAX_OFFSET_M) -> tuple[float, float, float]:
    if not (isinstance(value, list) and len(value) == 3 and all(
            not isinstance(v, bool) and isinstance(v, (int, float)) for v in value)):
        raise _err(source, key, f"expected a list of 3 numbers, got {value!r}")
    for v in value:
        if not math.isfinite(v) or abs(v) > bound:
            raise _err(source, key, f"every value must be a finite number within +-{bound:g}, got {value!r}")
    return tuple(float(v) for v in value)  # type: ignore[return-value]


def _number(source: str, key: str, value: Any, *, positive: bool = False, minimum: float | None = None,
            maximum: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _err(source, key, f"expected a finite number, got {value!r}")
    if positive and value <= 0:
        raise _err(source, key, f"must be > 0, got {value!r}")
    if minimum is not None and value < minimum:
        raise _err(source, key, f"must be >= {minimum:g}, got {value!r}")
    if maximum is not None and value > maximum:
        raise _err(source, key, f"must be <= {maximum:g}, got {value!r}")
    return float(value)


def _table(source: str, key: str, value: Any) -> dict:
    if not isinstance(value, dict):
        raise _err(source, key, f"expected a table, got {value!r}")
    return value


def _tables(source: str, key: str, value: Any) -> list[dict]:
    """An array of tables (`[[borg.fault]]`)."""
    if not isinstance(value, list):
        raise _err(source, key, f"expected an array of tables ([[{key}]]), got {value!r}")
    return [_table(source, f"{key}[{i}]", v) for i, v in enumerate(value)]


def _check_keys(source: str, where: str, table: dict, allowed: set[str]) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise _err(source, f"{where}.{unknown[0]}" if where else unknown[0],
                   f"unknown key (allowed: {', '.join(sorted(allowed))})")


def parse_scenario(data: dict[str, Any], source: str = "<dict>") -> Scenario:
    _check_keys(source, "", data, {"seed", "borg", "truss", "device", "camera", "tags", "rig_error"})
    seed = data.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
        raise _err(source, "seed", f"expected a non-negative integer, got {seed!r}")

    borg_faults = []
    borg = _table(source, "borg", data.get("borg", {}))
    _check_keys(source, "borg", borg, {"fault"})
    for i, f in enumerate(_tables(source, "borg.fault", borg.get("fault", []))):
        where = f"borg.fault[{i}]"
        kind = f.get("kind")
        if kind not in BORG_FAULT_KINDS:
            raise _err(source, f"{where}.kind", f"expected one of {', '.join(BORG_FAULT_KINDS)}, got {kind!r}")
        if kind == "partial_deploy":
            _check_keys(source, where, f, {"kind", "module", "height_m"})
            if "module" not in f or "height_m" not in f:
                raise _err(source, where, "partial_deploy needs module and height_m")
            borg_faults.append(BorgFault(kind, module=str(f["module"]),
                                         height_m=_number(source, f"{where}.height_m", f["height_m"], positive=True,
                                                           maximum=MAX_OFFSET_M)))
        elif kind == "tag_displaced":
            _check_keys(source, where, f, {"kind", "tag", "offset_m", "rotation_rad"})
            tag = f.get("tag")
            if isinstance(tag, bool) or not isinstance(tag, int):
                raise _err(source, f"{where}.tag", f"expected a tag id (integer), got {tag!r}")
            borg_faults.append(BorgFault(kind, tag=tag, offset_m=_vec3(source, f"{where}.offset_m", f.get("offset_m")),
                                         rotation_rad=_vec3(source, f"{where}.rotation_rad",
                                                            f.get("rotation_rad", [0, 0, 0]), MAX_ROTATION_RAD)))
        else:
            _check_keys(source, where, f, {"kind", "module", "offset_m", "rotation_rad"})
            if "module" not in f:
                raise _err(source, where, "module_offset needs module")
            borg_faults.append(BorgFault(kind, module=str(f["module"]),
                                         offset_m=_vec3(source, f"{where}.offset_m", f.get("offset_m", [0, 0, 0])),
                                         rotation_rad=_vec3(source, f"{where}.rotation_rad",
                                                            f.get("rotation_rad", [0, 0, 0]), MAX_ROTATION_RAD)))

    device_faults = []
    dev = _table(source, "device", data.get("device", {}))
    _check_keys(source, "device", dev, {"fault"})
    for i, f in enumerate(_tables(source, "device.fault", dev.get("fault", []))):
        where = f"device.fault[{i}]"
        _check_keys(source, where, f, {"device", "kind", "after_commands", "count"})
        if not isinstance(f.get("device"), str):
            raise _err(source, f"{where}.device", "expected a device name from the rig")
        if f.get("kind") not in DEVICE_FAULT_KINDS:
            raise _err(source, f"{where}.kind", f"expected one of {', '.join(DEVICE_FAULT_KINDS)}, got {f.get('kind')!r}")
        after = f.get("after_commands", 0)
        count = f.get("count", 1)
        for key, v in (("after_commands", after), ("count", count)):
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= MAX_FAULT_COMMANDS:
                raise _err(source, f"{where}.{key}", f"expected a non-negative integer, got {v!r}")
        device_faults.append(DeviceFault(f["device"], f["kind"], after, count))

    truss = _table(source, "truss", data.get("truss", {}))
    _check_keys(source, "truss", truss, {"sigma_length_m", "sigma_measure_m"})
    tn = TrussNoise(
        sigma_length_m=_number(source, "truss.sigma_length_m", truss.get("sigma_length_m", TrussNoise.sigma_length_m), positive=True,
                               maximum=MAX_SIGMA_M),
        sigma_measure_m=_number(source, "truss.sigma_measure_m", truss.get("sigma_measure_m", TrussNoise.sigma_measure_m), positive=True,
                                maximum=MAX_SIGMA_M),
    )
    # [camera] and [tags]: only the keys given; the rest stay the rig's ([sim.camera], [sim.tags])
    cn = CameraNoise(**parse_imaging(data.get("camera", {}), data.get("tags", {}),
                                     lambda key, problem: _err(source, key, problem)))
    rig_error = None
    if "rig_error" in data:
        rig_error = parse_rig_error(data["rig_error"], lambda key, problem: _err(
            source, f"rig_error.{key}" if key else "rig_error", problem))
    return Scenario(seed, tuple(borg_faults), tuple(device_faults), tn, cn, source, rig_error)


def load_scenario(path: str | Path | None) -> Scenario:
    """Read a scenario file; None gives the default (seed 0, no faults, the papers' noise)."""
    if path is None:
        return Scenario()
    return parse_scenario(read_toml(path, "scenario"), str(path))
