"""Scenario files (TOML): what goes wrong in a simulated run — seed, noise, structure faults,
device faults.  Format and examples: docs/scenarios.md.  Every key is checked; a bad file gets an
error naming the key and the problem."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lab.errors import UserError
from lab.rig_error import RigError, parse_rig_error

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
    pixel_noise: float = 2.0       # grey levels, std
    blur_px: float = 0.6           # Gaussian blur sigma


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


def _vec3(source: str, key: str, value: Any) -> tuple[float, float, float]:
    if not (isinstance(value, list) and len(value) == 3 and all(isinstance(v, (int, float)) for v in value)):
        raise _err(source, key, f"expected a list of 3 numbers, got {value!r}")
    return tuple(float(v) for v in value)  # type: ignore[return-value]


def _number(source: str, key: str, value: Any, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _err(source, key, f"expected a number, got {value!r}")
    if positive and value <= 0:
        raise _err(source, key, f"must be > 0, got {value!r}")
    return float(value)


def _check_keys(source: str, where: str, table: dict, allowed: set[str]) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise _err(source, f"{where}.{unknown[0]}" if where else unknown[0],
                   f"unknown key (allowed: {', '.join(sorted(allowed))})")


def parse_scenario(data: dict[str, Any], source: str = "<dict>") -> Scenario:
    _check_keys(source, "", data, {"seed", "borg", "truss", "device", "camera", "rig_error"})
    seed = data.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise _err(source, "seed", f"expected a non-negative integer, got {seed!r}")

    borg_faults = []
    borg = data.get("borg", {})
    _check_keys(source, "borg", borg, {"fault"})
    for i, f in enumerate(borg.get("fault", [])):
        where = f"borg.fault[{i}]"
        kind = f.get("kind")
        if kind not in BORG_FAULT_KINDS:
            raise _err(source, f"{where}.kind", f"expected one of {', '.join(BORG_FAULT_KINDS)}, got {kind!r}")
        if kind == "partial_deploy":
            _check_keys(source, where, f, {"kind", "module", "height_m"})
            if "module" not in f or "height_m" not in f:
                raise _err(source, where, "partial_deploy needs module and height_m")
            borg_faults.append(BorgFault(kind, module=str(f["module"]),
                                         height_m=_number(source, f"{where}.height_m", f["height_m"], positive=True)))
        elif kind == "tag_displaced":
            _check_keys(source, where, f, {"kind", "tag", "offset_m", "rotation_rad"})
            tag = f.get("tag")
            if isinstance(tag, bool) or not isinstance(tag, int):
                raise _err(source, f"{where}.tag", f"expected a tag id (integer), got {tag!r}")
            borg_faults.append(BorgFault(kind, tag=tag, offset_m=_vec3(source, f"{where}.offset_m", f.get("offset_m")),
                                         rotation_rad=_vec3(source, f"{where}.rotation_rad",
                                                            f.get("rotation_rad", [0, 0, 0]))))
        else:
            _check_keys(source, where, f, {"kind", "module", "offset_m", "rotation_rad"})
            if "module" not in f:
                raise _err(source, where, "module_offset needs module")
            borg_faults.append(BorgFault(kind, module=str(f["module"]),
                                         offset_m=_vec3(source, f"{where}.offset_m", f.get("offset_m", [0, 0, 0])),
                                         rotation_rad=_vec3(source, f"{where}.rotation_rad",
                                                            f.get("rotation_rad", [0, 0, 0]))))

    device_faults = []
    dev = data.get("device", {})
    _check_keys(source, "device", dev, {"fault"})
    for i, f in enumerate(dev.get("fault", [])):
        where = f"device.fault[{i}]"
        _check_keys(source, where, f, {"device", "kind", "after_commands", "count"})
        if not isinstance(f.get("device"), str):
            raise _err(source, f"{where}.device", "expected a device name from the rig")
        if f.get("kind") not in DEVICE_FAULT_KINDS:
            raise _err(source, f"{where}.kind", f"expected one of {', '.join(DEVICE_FAULT_KINDS)}, got {f.get('kind')!r}")
        after = f.get("after_commands", 0)
        count = f.get("count", 1)
        for key, v in (("after_commands", after), ("count", count)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise _err(source, f"{where}.{key}", f"expected a non-negative integer, got {v!r}")
        device_faults.append(DeviceFault(f["device"], f["kind"], after, count))

    truss = data.get("truss", {})
    _check_keys(source, "truss", truss, {"sigma_length_m", "sigma_measure_m"})
    tn = TrussNoise(
        sigma_length_m=_number(source, "truss.sigma_length_m", truss.get("sigma_length_m", TrussNoise.sigma_length_m), positive=True),
        sigma_measure_m=_number(source, "truss.sigma_measure_m", truss.get("sigma_measure_m", TrussNoise.sigma_measure_m), positive=True),
    )
    cam = data.get("camera", {})
    _check_keys(source, "camera", cam, {"pixel_noise", "blur_px"})
    cn = CameraNoise(
        pixel_noise=_number(source, "camera.pixel_noise", cam.get("pixel_noise", CameraNoise.pixel_noise)),
        blur_px=_number(source, "camera.blur_px", cam.get("blur_px", CameraNoise.blur_px)),
    )
    rig_error = None
    if "rig_error" in data:
        rig_error = parse_rig_error(data["rig_error"], lambda key, problem: _err(
            source, f"rig_error.{key}" if key else "rig_error", problem))
    return Scenario(seed, tuple(borg_faults), tuple(device_faults), tn, cn, source, rig_error)


def load_scenario(path: str | Path | None) -> Scenario:
    """Read a scenario file; None gives the default (seed 0, no faults, the papers' noise)."""
    if path is None:
        return Scenario()
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise UserError(f"scenario {p}: no such file") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"scenario {p}: not valid TOML: {exc}") from None
    return parse_scenario(data, str(p))
