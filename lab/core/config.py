"""Rig files (TOML): which devices the bench has, where they answer (a transport URL) and their
limits.  Format and examples: docs/hardware.md.  The default rig is the simulated bench shipped as
package data (`lab/rigs/sim.toml`).

Every key is checked; a bad file gets a `RigError` naming the file, the key and the problem
(`rig sim.toml: [turntable].max_deg: expected a number, got 'lots'`).  Unknown keys are errors too,
so a typo cannot silently fall back to a default.

Everything here is data: loading a rig opens no port.  Units inside the returned objects are SI
(m, rad, s); the file uses the units named in its keys (`_deg`, `_m`, `_s`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, Iterator, Literal

import numpy as np

from lab.core.errors import UserError
from lab.core.files import read_toml
from lab.core.geometry import Pose3, from_xyzrpy
from lab.core import rig_error as rig_errors   # the record is RigError too, like this module's exception
from lab.core.imaging import RIG_CAMERA_KEYS, Imaging, parse_imaging
from lab.core.structures.borg import MAX_N
from lab.core.survey_budget import MAX_VIEWS, MAX_VIEWS_RANGE, SIGMA_TARGET_MM, SIGMA_TARGET_MM_MAX

DeviceKind = Literal["turntable", "stewart", "lift", "camera", "ipjr"]

DEFAULT_RIG = "sim.toml"


class RigError(UserError):
    """A rig file that cannot be used, with the key and the problem named."""


# --------------------------------------------------------------------------------------------
# The parsed rig


@dataclass(frozen=True)
class Link:
    """How to reach a device and how patient to be with it (docs/protocols.md §8)."""

    url: str
    reply_timeout_s: float = 0.5   # one request -> one reply
    retries: int = 2               # extra attempts, for queries only
    margin_s: float = 1.0          # added to every motion timeout computed from the physics


@dataclass(frozen=True)
class TurntableConfig:
    name: str
    link: Link
    min_rad: float
    max_rad: float


@dataclass(frozen=True)
class LiftConfig:
    """A vertical linear stage carrying the Stewart base (docs/hardware.md, "The lift"): at height
    0 the base sits where [stewart] world_T_base says; a height h raises it by h along the lift's
    axis (nominally world z; its true tilt is calibrated in the run's graph)."""

    name: str
    link: Link
    min_m: float                    # soft limits, checked before sending
    max_m: float


@dataclass(frozen=True)
class StewartGeometry:
    """A 6-6 Stewart platform.  Leg i joins base joint i (base frame) to platform joint i
    (platform frame).  At home the platform frame is the base frame shifted by `home_m`."""

    base_joints_m: np.ndarray       # (6, 3), base frame
    platform_joints_m: np.ndarray   # (6, 3), platform frame
    home_m: np.ndarray              # (3,), platform origin at home, base frame
    leg_min_m: float
    leg_max_m: float
    base_joint_max_rad: float       # max angle between a leg and the base normal
    platform_joint_max_rad: float   # max angle between a leg and the platform normal


@dataclass(frozen=True)
class Station:
    """A place the Stewart base (with its lift) can be bolted down: its pose in the world."""

    name: str
    world_T_base: Pose3


@dataclass(frozen=True)
class StewartConfig:
    name: str
    link: Link
    geometry: StewartGeometry
    world_T_base: Pose3             # where the base stands now: the pose of `station`
    # every place the base may stand ([stewart] world_T_base first, then [[stewart.stations]] in the
    # file's order) and which one it is at; a BORG run takes the first whose base joints all stand
    # `clearance_m` outside its turntable's rim and whose centre stands `rim_standoff_m` back from
    # it (Rig.for_borg)
    stations: tuple[Station, ...] = ()
    station: str = "near"
    clearance_m: float = 0.05
    # the rim tags stand on the rim's edge facing out, below the structure: from a base closer to
    # the rim than this they pass under the camera's field and the rig survey is blind
    rim_standoff_m: float = 0.0


@dataclass(frozen=True)
class CameraConfig:
    name: str
    url: str                        # device index ("0"), /dev/videoN, stream URL or snapshot URL
    calibration: Path | None        # intrinsics file (docs/hardware.md), resolved against the rig
    platform_T_camera: Pose3        # camera mount on the Stewart platform
    timeout_s: float = 2.0          # one frame


@dataclass(frozen=True)
class IpjrConfig:
    name: str
    link: Link
    stroke_m: float                 # actuator stroke (Firgelli L-16: 0.140 m)
    step_m: float                   # nominal length of one step (the paper: 0.138 mm)
    volts_retracted: float          # calibration: potentiometer volts at zero extension
    volts_extended: float           # ... and at full stroke
    tolerance_m: float = 0.0005     # length controller: done when |L - M| < tolerance (paper: 0.5 mm)
    max_tries: int = 8              # length controller: move-measure cycles before giving up
    samples: int = 4                # potentiometer readings averaged per measurement


DeviceConfig = TurntableConfig | StewartConfig | LiftConfig | CameraConfig | IpjrConfig


@dataclass(frozen=True)
class SimConfig:
    """The `[sim]` table: how the simulated bench behaves.  Present only in simulated rigs."""

    seed: int = 0
    speedup: float = 1.0
    borg_n: int = 3
    pty: bool = True                # also serve serial devices on pseudo-terminals (lab sim)
    turntable: dict[str, float] = field(default_factory=dict)
    stewart: dict[str, float] = field(default_factory=dict)
    camera: dict[str, Any] = field(default_factory=dict)
    ipjr: dict[str, float] = field(default_factory=dict)
    lift: dict[str, float] = field(default_factory=dict)
    rig_error: rig_errors.RigError = field(default_factory=rig_errors.RigError)   # the true bench vs this file
    imaging: Imaging = field(default_factory=Imaging)   # [sim.camera] / [sim.tags] imaging keys (lab/core/imaging.py)
    # what the simulated firmware does when its host goes (docs/protocols.md §1): stop a motion when
    # no request came for watchdog_s (wall clock; 0 = no watchdog), and when the link that
    # commanded it closes.  0 / false: an older firmware that finishes its move whatever happens.
    watchdog_s: float = 1.0
    stop_on_link_loss: bool = True


@dataclass(frozen=True)
class CalibrationConfig:
    """The `[calibration]` table: how well the rig file's geometry is known before any rig
    calibration (the priors the graph starts from), the devices' datasheet repeatability, and the
    rig calibration file `lab calibrate rig` wrote (docs/calibration.md).  SI units."""

    file: Path | None = None
    camera_mount_sigma_m: float = 0.010
    camera_mount_sigma_rad: float = math.radians(2.0)
    stewart_base_sigma_m: float = 0.020
    stewart_base_sigma_rad: float = math.radians(2.0)
    turntable_axis_sigma_m: float = 0.005
    turntable_axis_sigma_rad: float = math.radians(0.3)
    turntable_tag_sigma_m: float = 0.001
    focal_sigma: float = 0.01                 # relative
    principal_point_sigma_px: float = 5.0
    # how far the camera file's radial distortion may be from the true lens, as the displacement at
    # the frame's corners: the graph estimates the difference (two radial terms) with this prior
    distortion_sigma_px: float = 0.5
    stewart_repeatability_m: float = 0.00002
    stewart_repeatability_rad: float = math.radians(0.002)
    turntable_repeatability_rad: float = math.radians(0.005)
    # the lift (only with a [lift] table): how far its travel may be from world z before the run
    # calibrates it, and the datasheet repeatability of its carriage, per axis
    lift_axis_sigma_rad: float = math.radians(0.1)
    lift_repeatability_m: float = 0.00002


MODULE_KINDS = ("deployable", "closeout_strut", "closeout_square")


@dataclass(frozen=True)
class ToleranceConfig:
    position_m: float = 0.005
    rotation_rad: float = math.radians(1.0)


@dataclass(frozen=True)
class VerificationConfig:
    """The `[verification]` table: each module type's tolerance, how far clear of it (in the
    module's own sigmas) a verdict must be, and the survey's accuracy target and view budget per
    step.  A run's `--tolerance`, `--sigma-target-mm` and `--max-views` override it."""

    tolerances: dict[str, ToleranceConfig] = field(default_factory=lambda: {k: ToleranceConfig() for k in MODULE_KINDS})
    band_sigmas: float = 2.0
    # the planner adds views until the new module's predicted position 1-sigma is this small, within
    # the step's view budget (lab/core/survey_budget.py: why these defaults)
    sigma_target_m: float = SIGMA_TARGET_MM * 1e-3
    max_views: int = MAX_VIEWS
    # the detector's face-on corner accuracy on this rig's camera, what the graph assumes (measure
    # it: a simulated run reports corner_rms_px against the truth, `lab calibrate rig` its residual)
    corner_sigma_px: float = 0.02
    # how well the tags were printed: each tag's size is off by this relative error (1 sigma).  The
    # graph gives every tag a scale variable with this prior (measure a few printed tags with a
    # caliper; 0 = printed exactly)
    tag_scale_sigma: float = 0.001
    # besides the module's own tags, a view gives the graph its sightings of this many tags, those
    # nearest the module (design positions): a view of a large structure reads ~17 tags all over
    # it, which tell the module little (its neighbours and the rig chain place the camera) and each
    # re-eliminates its far corner of the Bayes tree (docs/sf_graphslam.md, "What a view gives the
    # graph"); 0 = every sighting
    near_tags_per_view: int = 5
    # a layer's tags are settled -- summarised out of the incremental solver onto the rig and the
    # turntable tags -- once the run measures a module this many layers above it: the step then
    # costs what the layers still being built cost, not the whole structure (docs/sf_graphslam.md,
    # "Settling what is built"); 0 = never (the full graph)
    settle_after_layers: int = 2


def _verification(t: "_Table") -> VerificationConfig:
    tolerances = {}
    for kind in MODULE_KINDS:
        k = t.table(kind, required=False)
        tolerances[kind] = ToleranceConfig(k.number("position_mm", default=5.0, positive=True, maximum=1000.0) * 1e-3,
                                           math.radians(k.number("rotation_deg", default=1.0, positive=True,
                                                                 maximum=90.0)))
        k.done()
    cfg = VerificationConfig(tolerances, t.number("band_sigmas", default=2.0, minimum=0.0, maximum=10.0),
                             t.number("sigma_target_mm", default=SIGMA_TARGET_MM, positive=True,
                                      maximum=SIGMA_TARGET_MM_MAX) * 1e-3,
                             t.integer("max_views", default=MAX_VIEWS, minimum=MAX_VIEWS_RANGE[0],
                                       maximum=MAX_VIEWS_RANGE[1]),
                             t.number("corner_sigma_px", default=0.02, positive=True, maximum=5.0),
                             t.number("tag_scale_percent", default=0.1, minimum=0.0, maximum=5.0) * 1e-2,
                             t.integer("near_tags_per_view", default=5, minimum=0, maximum=10000),
                             t.integer("settle_after_layers", default=2, minimum=0, maximum=1000))
    t.done()
    return cfg


# (key, default in the file's unit, SI factor, attribute)
_CALIBRATION_KEYS = (
    ("camera_mount_sigma_mm", 10.0, 1e-3, "camera_mount_sigma_m"),
    ("camera_mount_sigma_deg", 2.0, math.pi / 180, "camera_mount_sigma_rad"),
    ("stewart_base_sigma_mm", 20.0, 1e-3, "stewart_base_sigma_m"),
    ("stewart_base_sigma_deg", 2.0, math.pi / 180, "stewart_base_sigma_rad"),
    ("turntable_axis_sigma_mm", 5.0, 1e-3, "turntable_axis_sigma_m"),
    ("turntable_axis_sigma_deg", 0.3, math.pi / 180, "turntable_axis_sigma_rad"),
    ("turntable_tag_sigma_mm", 1.0, 1e-3, "turntable_tag_sigma_m"),
    ("focal_sigma_percent", 1.0, 1e-2, "focal_sigma"),
    ("principal_point_sigma_px", 5.0, 1.0, "principal_point_sigma_px"),
    ("distortion_sigma_px", 0.5, 1.0, "distortion_sigma_px"),
    ("stewart_repeatability_mm", 0.02, 1e-3, "stewart_repeatability_m"),
    ("stewart_repeatability_deg", 0.002, math.pi / 180, "stewart_repeatability_rad"),
    ("turntable_repeatability_deg", 0.005, math.pi / 180, "turntable_repeatability_rad"),
    ("lift_axis_sigma_deg", 0.1, math.pi / 180, "lift_axis_sigma_rad"),
    ("lift_repeatability_mm", 0.02, 1e-3, "lift_repeatability_m"),
)


def _calibration(t: "_Table", base_dir: Path | None) -> CalibrationConfig:
    values: dict[str, Any] = {}
    f = t.string("file", default="")
    if f:
        path = Path(f)
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        if not path.exists():
            raise t.error("file", f"no such file: {path} (write it with `lab calibrate rig`)")
        values["file"] = path
    for key, default, si, attr in _CALIBRATION_KEYS:
        values[attr] = t.number(key, default=default, positive=True, maximum=1e3) * si
    t.done()
    return CalibrationConfig(**values)


@dataclass(frozen=True)
class Rig:
    name: str
    source: str                                  # file path, or "<package>/sim.toml"
    turntable: TurntableConfig | None = None
    stewart: StewartConfig | None = None
    camera: CameraConfig | None = None
    ipjrs: dict[str, IpjrConfig] = field(default_factory=dict)
    sim: SimConfig | None = None
    description: str = ""
    data: dict[str, Any] = field(default_factory=dict)   # the file as read, for the run's start record
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    verification: VerificationConfig = field(default_factory=VerificationConfig)
    lift: LiftConfig | None = None

    @property
    def simulated(self) -> bool:
        return self.sim is not None

    def device_configs(self) -> Iterator[tuple[DeviceKind, DeviceConfig]]:
        """(kind, record) of every device, in a stable order (the order of `devices()`)."""
        if self.turntable:
            yield "turntable", self.turntable
        if self.stewart:
            yield "stewart", self.stewart
        if self.lift:
            yield "lift", self.lift
        if self.camera:
            yield "camera", self.camera
        for ipjr in self.ipjrs.values():
            yield "ipjr", ipjr

    def devices(self) -> Iterator[tuple[str, DeviceKind, str]]:
        """(name, kind, url) of every device, in a stable order."""
        for kind, cfg in self.device_configs():
            yield cfg.name, kind, cfg.url if isinstance(cfg, CameraConfig) else cfg.link.url

    def with_urls(self, urls: dict[str, str]) -> Rig:
        """The same rig with some devices reached at other URLs (e.g. a simulator on free ports)."""
        unknown = set(urls) - {n for n, _, _ in self.devices()}
        if unknown:
            raise KeyError(f"no device named {sorted(unknown)} in rig {self.name!r}")
        tt, sp, cam, lift = self.turntable, self.stewart, self.camera, self.lift
        if tt and tt.name in urls:
            tt = replace(tt, link=replace(tt.link, url=urls[tt.name]))
        if sp and sp.name in urls:
            sp = replace(sp, link=replace(sp.link, url=urls[sp.name]))
        if lift and lift.name in urls:
            lift = replace(lift, link=replace(lift.link, url=urls[lift.name]))
        if cam and cam.name in urls:
            cam = replace(cam, url=urls[cam.name])
        ipjrs = {n: replace(c, link=replace(c.link, url=urls[n])) if n in urls else c for n, c in self.ipjrs.items()}
        return replace(self, turntable=tt, stewart=sp, camera=cam, ipjrs=ipjrs, lift=lift)

    def with_links(self, **changes: Any) -> Rig:
        """Every serial/HTTP link with some fields changed (tests: shorter timeouts)."""
        tt, sp, lift = self.turntable, self.stewart, self.lift
        if tt:
            tt = replace(tt, link=replace(tt.link, **changes))
        if sp:
            sp = replace(sp, link=replace(sp.link, **changes))
        if lift:
            lift = replace(lift, link=replace(lift.link, **changes))
        ipjrs = {n: replace(c, link=replace(c.link, **changes)) for n, c in self.ipjrs.items()}
        return replace(self, turntable=tt, stewart=sp, ipjrs=ipjrs, lift=lift)

    def at_station(self, name: str) -> Rig:
        """The same rig with its Stewart base (and lift) standing at station `name`."""
        if self.stewart is None:
            raise KeyError(f"rig {self.name!r} has no Stewart platform")
        for st in self.stewart.stations:
            if st.name == name:
                return replace(self, stewart=replace(self.stewart, world_T_base=st.world_T_base, station=name))
        raise KeyError(f"rig {self.name!r} has no station {name!r} (have: "
                       f"{', '.join(s.name for s in self.stewart.stations)})")

    def station_for(self, turntable_radius_m: float) -> str:
        """The first station (in the file's order) whose base joints all stand `clearance_m` or more
        outside a turntable rim of this radius (centred on the world z axis) and whose centre stands
        `rim_standoff_m` or more outside it (the camera must see the rim's tags); the last one if
        none does (a run's planner then lists what that station cannot see)."""
        assert self.stewart is not None
        g, s = self.stewart.geometry, self.stewart
        for st in s.stations:
            joints = np.array([st.world_T_base.transformFrom(j) for j in g.base_joints_m])
            centre = st.world_T_base.translation()
            if (np.hypot(joints[:, 0], joints[:, 1]).min() >= turntable_radius_m + s.clearance_m
                    and math.hypot(centre[0], centre[1]) >= turntable_radius_m + s.rim_standoff_m):
                return st.name
        return self.stewart.stations[-1].name

    def for_borg(self, n: int) -> Rig:
        """The rig as it stands for a BORG of size `n`: its Stewart base at the station that clears
        that BORG's turntable (a rig with one station, or none, is itself)."""
        if self.stewart is None or len(self.stewart.stations) < 2:
            return self
        from lab.core.structures.borg import SPACING_M, turntable_radius_m

        return self.at_station(self.station_for(turntable_radius_m(n * SPACING_M)))

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "source": self.source, "simulated": self.simulated,
                "devices": [{"name": n, "kind": k, "url": u} for n, k, u in self.devices()],
                "file": self.data}


# --------------------------------------------------------------------------------------------
# Loading


def default_rig_path() -> Path:
    return Path(str(resources.files("lab.rigs").joinpath(DEFAULT_RIG)))


def load_rig(path: str | Path | None = None) -> Rig:
    """Read and check a rig file; None (or "sim") gives the packaged simulated rig."""
    if path is None or str(path) == "sim":
        p = default_rig_path()
    else:
        p = Path(path)
    return parse_rig(read_toml(p, "rig", RigError), source=str(p), base_dir=p.parent)


def parse_rig(data: dict[str, Any], source: str = "<dict>", base_dir: Path | None = None) -> Rig:
    top = _Table(source, "", data)
    rig_t = top.table("rig", required=False)
    name = rig_t.string("name", default=Path(source).stem if source != "<dict>" else "rig")
    description = rig_t.string("description", default="")
    rig_t.done()

    names: dict[str, str] = {}

    def claim(dev_name: str, key: str) -> str:
        if dev_name in names:
            raise RigError(f"rig {source}: {key}: device name {dev_name!r} already used by {names[dev_name]}")
        names[dev_name] = key
        return dev_name

    turntable = None
    if "turntable" in data:
        t = top.table("turntable")
        nm = claim(t.string("name", default="turntable"), "[turntable]")
        link = _link(t)
        lo = t.number("min_deg", unit="deg")
        hi = t.number("max_deg", unit="deg")
        if not lo < hi:
            raise t.error("max_deg", f"must be greater than min_deg ({lo} deg), got {hi} deg")
        t.done()
        turntable = TurntableConfig(nm, link, math.radians(lo), math.radians(hi))

    stewart = None
    if "stewart" in data:
        s = top.table("stewart")
        nm = claim(s.string("name", default="stewart"), "[stewart]")
        link = _link(s)
        geometry = _stewart_geometry(s)
        world_T_base = s.pose("world_T_base")
        station = s.string("station", default="near")
        clearance = s.number("clearance_m", default=0.05, minimum=0.0, maximum=10.0, unit="m")
        standoff = s.number("rim_standoff_m", default=0.0, minimum=0.0, maximum=10.0, unit="m")
        stations = [Station(station, world_T_base)] + _stations(s)
        names_seen: set[str] = set()
        for st in stations:
            if st.name in names_seen or not st.name:
                raise s.error("stations", f"station name {st.name!r} {'used twice' if st.name else 'is empty'}")
            names_seen.add(st.name)
        s.done()
        stewart = StewartConfig(nm, link, geometry, world_T_base, tuple(stations), station, clearance, standoff)

    lift = None
    if "lift" in data:
        lt = top.table("lift")
        nm = claim(lt.string("name", default="lift"), "[lift]")
        link = _link(lt)
        lo = lt.number("min_m", minimum=-10.0, maximum=10.0, unit="m")
        hi = lt.number("max_m", minimum=-10.0, maximum=10.0, unit="m")
        if not lo < hi:
            raise lt.error("max_m", f"must be greater than min_m ({lo} m), got {hi} m")
        lt.done()
        lift = LiftConfig(nm, link, lo, hi)

    camera = None
    if "camera" in data:
        c = top.table("camera")
        nm = claim(c.string("name", default="camera"), "[camera]")
        url = c.string("url")
        cal = c.string("calibration", default="")
        cal_path = None
        if cal:
            cal_path = Path(cal)
            if not cal_path.is_absolute() and base_dir is not None:
                cal_path = base_dir / cal_path
            if not cal_path.exists():
                raise c.error("calibration", f"no such file: {cal_path}")
        platform_T_camera = c.pose("platform_T_camera")
        timeout_s = c.number("timeout_s", default=2.0, positive=True, maximum=60.0, unit="s")
        c.done()
        camera = CameraConfig(nm, url, cal_path, platform_T_camera, timeout_s)

    ipjrs: dict[str, IpjrConfig] = {}
    if "ipjr" in data:
        group = top.table("ipjr")
        for key in group.keys():
            i = group.table(key)
            nm = claim(key, f"[ipjr.{key}]")
            link = _link(i)
            stroke = i.number("stroke_m", positive=True, unit="m")
            step = i.number("step_m", positive=True, unit="m")
            if step >= stroke:
                raise i.error("step_m", f"must be smaller than stroke_m ({stroke} m), got {step} m")
            v0 = i.number("volts_retracted", unit="V")
            v1 = i.number("volts_extended", unit="V")
            if v0 == v1:
                raise i.error("volts_extended", f"must differ from volts_retracted ({v0} V)")
            tol = i.number("tolerance_m", default=0.0005, positive=True, unit="m")
            if tol < step / 2:
                raise i.error("tolerance_m", f"{tol} m is below half a step ({step / 2} m): the controller could never settle")
            tries = i.integer("max_tries", default=8, minimum=1, maximum=100)
            samples = i.integer("samples", default=4, minimum=1, maximum=100)
            i.done()
            ipjrs[nm] = IpjrConfig(nm, link, stroke, step, v0, v1, tol, tries, samples)
        group.done()

    sim = None
    if "sim" in data:
        sim = _sim(top.table("sim"))
    calibration = _calibration(top.table("calibration", required=False), base_dir)
    verification = _verification(top.table("verification", required=False))

    top.done()
    if not names:
        raise RigError(f"rig {source}: no devices: add at least one of [turntable], [stewart], [camera], [ipjr.NAME]")
    return Rig(name, source, turntable, stewart, camera, ipjrs, sim, description, data, calibration, verification,
               lift)


def _link(t: _Table) -> Link:
    url = t.string("url")
    if not url.strip():
        raise t.error("url", "must not be empty")
    return Link(
        url=url,
        reply_timeout_s=t.number("reply_timeout_s", default=0.5, positive=True, maximum=60.0, unit="s"),
        retries=t.integer("retries", default=2, minimum=0, maximum=10),
        margin_s=t.number("margin_s", default=1.0, minimum=0.0, maximum=600.0, unit="s"),
    )


def _ring(radius: float, half_angle_deg: float, centres_deg: tuple[float, float, float], z: float,
          pairs_first: bool) -> np.ndarray:
    """Six joints in three pairs on a circle: pair k at centre_k -/+ half angle.  `pairs_first`
    orders each pair (-, +), otherwise legs are arranged so neighbouring pairs share a leg."""
    angles = []
    for c in centres_deg:
        angles.extend([c - half_angle_deg, c + half_angle_deg])
    if not pairs_first:
        angles = angles[1:] + angles[:1]
    a = np.radians(angles)
    return np.column_stack([radius * np.cos(a), radius * np.sin(a), np.full(6, z)])


def stewart_joints(base_radius_m: float, base_half_angle_deg: float, platform_radius_m: float,
                   platform_half_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The classic symmetric 6-6 layout: base joint pairs centred at 0, 120, 240 deg, platform
    pairs at 60, 180, 300 deg; leg i runs from a base joint to the nearer joint of the
    neighbouring platform pair, so the legs cross in the familiar zig-zag."""
    base = _ring(base_radius_m, base_half_angle_deg, (0.0, 120.0, 240.0), 0.0, pairs_first=False)
    plat = _ring(platform_radius_m, platform_half_angle_deg, (60.0, 180.0, 300.0), 0.0, pairs_first=True)
    return base, plat


def _stations(s: "_Table") -> list[Station]:
    """`[[stewart.stations]]`: further places the base can stand, each `name` and `world_T_base`."""
    items = s._get("stations", [])
    if not isinstance(items, list):
        s._bad("stations", "an array of tables ([[stewart.stations]])", items)
    out = []
    for i, item in enumerate(items):
        t = _Table(s.source, f"stewart.stations[{i}]", item)
        out.append(Station(t.string("name"), t.pose("world_T_base")))
        t.done()
    return out


def _stewart_geometry(s: _Table) -> StewartGeometry:
    explicit = "base_joints_m" in s.data or "platform_joints_m" in s.data
    if explicit:
        base = s.matrix("base_joints_m", rows=6, cols=3)
        plat = s.matrix("platform_joints_m", rows=6, cols=3)
    else:
        base, plat = stewart_joints(
            s.number("base_radius_m", positive=True, unit="m"),
            s.number("base_half_angle_deg", minimum=0.0, maximum=59.0, unit="deg"),
            s.number("platform_radius_m", positive=True, unit="m"),
            s.number("platform_half_angle_deg", minimum=0.0, maximum=59.0, unit="deg"),
        )
    home = np.array([0.0, 0.0, s.number("home_height_m", positive=True, unit="m")])
    lo = s.number("leg_min_m", positive=True, unit="m")
    hi = s.number("leg_max_m", positive=True, unit="m")
    if not lo < hi:
        raise s.error("leg_max_m", f"must be greater than leg_min_m ({lo} m), got {hi} m")
    home_legs = np.linalg.norm(home + plat - base, axis=1)
    for i, length in enumerate(home_legs):
        if not lo <= length <= hi:
            raise s.error("home_height_m", f"at home leg {i + 1} is {length:.4f} m long, outside "
                                           f"[leg_min_m, leg_max_m] = [{lo}, {hi}] m")
    return StewartGeometry(
        base_joints_m=base,
        platform_joints_m=plat,
        home_m=home,
        leg_min_m=lo,
        leg_max_m=hi,
        base_joint_max_rad=math.radians(s.number("base_joint_max_deg", minimum=0.0, maximum=90.0, unit="deg")),
        platform_joint_max_rad=math.radians(s.number("platform_joint_max_deg", minimum=0.0, maximum=90.0, unit="deg")),
    )


_SIM_DEVICE_KEYS: dict[str, dict[str, tuple[float, float]]] = {
    # key: (default, minimum) -- physical parameters of the simulated devices (docs/hardware.md)
    "turntable": {"speed_deg_s": (10.0, 1.0), "settle_s": (0.3, 0.0), "min_deg": (-360.0, -1e4),
                  "max_deg": (360.0, -1e4)},
    "stewart": {"speed_mm_s": (20.0, 1.0), "settle_s": (0.2, 0.0), "stroke_margin_mm": (10.0, 0.0)},
    "ipjr": {"speed_mm_s": (10.0, 1.0), "settle_s": (0.1, 0.0), "volts_noise_v": (0.002, 0.0),
             "step_scale_sigma": (0.02, 0.0), "move_sigma_m": (0.00005, 0.0), "calibration_sigma_v": (0.005, 0.0),
             "start_extension_m": (0.07, 0.0)},
    # hardware travel (mm, as LIMITS? reports it), top speed, settling (a tall column sways)
    "lift": {"speed_mm_s": (100.0, 1.0), "settle_s": (0.5, 0.0), "min_mm": (-600.0, -1e4), "max_mm": (2600.0, -1e4)},
}
# A simulated device slower than this never finishes a run (a 0.001 deg/s turntable), one faster is
# no instrument: refused with the key named.  `--speedup` has the same ceiling.
_SIM_MAXIMA = {"speed_deg_s": 720.0, "speed_mm_s": 1000.0, "settle_s": 60.0, "min_deg": 1e4, "max_deg": 1e4,
               "min_mm": 1e4, "max_mm": 1e4,
               "stroke_margin_mm": 100.0, "volts_noise_v": 1.0, "step_scale_sigma": 0.5, "move_sigma_m": 0.01,
               "calibration_sigma_v": 1.0, "start_extension_m": 1.0}
MAX_SPEEDUP = 1000.0
# the same bounds, for what derives from them (the slowest --speedup a rig's devices allow)
SIM_DEVICE_KEYS, SIM_MAXIMA = _SIM_DEVICE_KEYS, _SIM_MAXIMA
_SIM_CAMERA_KEYS = {"width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "dist", *RIG_CAMERA_KEYS}


def _sim(t: _Table) -> SimConfig:
    seed = t.integer("seed", default=0, minimum=0)
    speedup = t.number("speedup", default=1.0, positive=True, maximum=MAX_SPEEDUP)
    borg_n = t.integer("borg_n", default=3, minimum=2, maximum=MAX_N)
    pty = t.boolean("pty", default=True)
    watchdog_s = t.number("watchdog_s", default=1.0, minimum=0.0, maximum=60.0, unit="s")
    if 0 < watchdog_s < 0.3:   # shorter would bite a healthy host between two polls (sim_devices/watchdog.py)
        raise t.error("watchdog_s", f"must be 0 (no watchdog) or at least 0.3 s, got {watchdog_s} s")
    stop_on_link_loss = t.boolean("stop_on_link_loss", default=True)
    sections: dict[str, dict[str, Any]] = {}
    for dev, keys in _SIM_DEVICE_KEYS.items():
        sub = t.table(dev, required=False)
        sections[dev] = {k: sub.number(k, default=d, minimum=m, maximum=_SIM_MAXIMA.get(k)) for k, (d, m) in keys.items()}
        sub.done()
    cam = t.table("camera", required=False)
    camera: dict[str, Any] = {}
    for k in ("width_px", "height_px"):
        camera[k] = cam.integer(k, default=1280 if k == "width_px" else 720, minimum=16)
    for k, d in (("fx_px", 914.0), ("fy_px", 914.0)):
        camera[k] = cam.number(k, default=d, positive=True)
    camera["cx_px"] = cam.number("cx_px", default=(camera["width_px"] - 1) / 2.0)
    camera["cy_px"] = cam.number("cy_px", default=(camera["height_px"] - 1) / 2.0)
    camera["dist"] = cam.vector("dist", n=None, default=[0.0, 0.0, 0.0, 0.0, 0.0])
    # the imaging keys (lab/core/imaging.py): omitted ones are the ideal camera's, as before issue 19
    given = parse_imaging({k: cam._get(k, None) for k in RIG_CAMERA_KEYS if k in cam.data},
                          t._get("tags", {}), lambda key, problem: t.error(key, problem),
                          camera_keys=RIG_CAMERA_KEYS)
    cam.done()
    imaging = Imaging().with_overrides(given)
    camera["pixel_noise"], camera["blur_px"] = imaging.pixel_noise, imaging.blur_px
    f_m = imaging.focal_length_m(camera["fx_px"])
    if imaging.focus_distance_m and imaging.focus_distance_m < 2 * f_m:
        raise t.error("camera.focus_distance_m", f"must be 0 (everything in focus) or beyond twice the focal length "
                                                 f"({2 * f_m:g} m = 2 fx pixel_pitch_um), got {imaging.focus_distance_m}")
    rig_error = rig_errors.parse_rig_error(t._get("rig_error", {}), lambda key, problem: t.error(
        f"rig_error.{key}" if key else "rig_error", problem))
    t.done()
    if not sections["lift"]["min_mm"] < sections["lift"]["max_mm"]:
        raise t.error("lift.max_mm", f"must be greater than lift.min_mm ({sections['lift']['min_mm']} mm)")
    return SimConfig(seed, speedup, borg_n, pty, sections["turntable"], sections["stewart"], camera,
                     sections["ipjr"], sections["lift"], rig_error, imaging, watchdog_s, stop_on_link_loss)


# --------------------------------------------------------------------------------------------
# A checked view of one TOML table


_MISSING = object()


class _Table:
    def __init__(self, source: str, where: str, data: Any) -> None:
        self.source, self.where = source, where
        if not isinstance(data, dict):
            raise RigError(f"rig {source}: {self._name()}: expected a table, got {data!r}")
        self.data: dict[str, Any] = data
        self._used: set[str] = set()

    def _name(self, key: str | None = None) -> str:
        if key is None:
            return f"[{self.where}]" if self.where else "top level"
        return f"[{self.where}].{key}" if self.where else key

    def error(self, key: str, problem: str) -> RigError:
        return RigError(f"rig {self.source}: {self._name(key)}: {problem}")

    def keys(self) -> list[str]:
        self._used.update(self.data)
        return list(self.data)

    def _get(self, key: str, default: Any) -> Any:
        self._used.add(key)
        if key in self.data:
            return self.data[key]
        if default is _MISSING:
            raise self.error(key, "missing (required)")
        return default

    def table(self, key: str, required: bool = True) -> _Table:
        value = self._get(key, _MISSING if required else {})
        return _Table(self.source, f"{self.where}.{key}" if self.where else key, value) if isinstance(value, dict) \
            else self._bad(key, "a table", value)

    def _bad(self, key: str, expected: str, value: Any):
        raise self.error(key, f"expected {expected}, got {value!r}")

    def string(self, key: str, default: Any = _MISSING) -> str:
        value = self._get(key, default)
        if not isinstance(value, str):
            self._bad(key, "a string", value)
        return value

    def boolean(self, key: str, default: Any = _MISSING) -> bool:
        value = self._get(key, default)
        if not isinstance(value, bool):
            self._bad(key, "true or false", value)
        return value

    def number(self, key: str, default: Any = _MISSING, *, positive: bool = False, minimum: float | None = None,
               maximum: float | None = None, unit: str = "") -> float:
        value = self._get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self._bad(key, "a number" + (f" in {unit}" if unit else ""), value)
        u = f" {unit}" if unit else ""
        if positive and value <= 0:
            raise self.error(key, f"must be > 0{u}, got {value}{u}")
        if minimum is not None and value < minimum:
            raise self.error(key, f"must be >= {minimum}{u}, got {value}{u}")
        if maximum is not None and value > maximum:
            raise self.error(key, f"must be <= {maximum}{u}, got {value}{u}")
        return float(value)

    def integer(self, key: str, default: Any = _MISSING, *, minimum: int | None = None,
                maximum: int | None = None) -> int:
        value = self._get(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            self._bad(key, "an integer", value)
        if minimum is not None and value < minimum:
            raise self.error(key, f"must be >= {minimum}, got {value}")
        if maximum is not None and value > maximum:
            raise self.error(key, f"must be <= {maximum}, got {value}")
        return int(value)

    def vector(self, key: str, n: int | None, default: Any = _MISSING) -> list[float]:
        value = self._get(key, default)
        ok = isinstance(value, list) and all(
            not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) for v in value)
        if not ok or (n is not None and len(value) != n):
            self._bad(key, f"a list of {n if n is not None else ''} numbers".replace("  ", " "), value)
        return [float(v) for v in value]

    def matrix(self, key: str, rows: int, cols: int) -> np.ndarray:
        value = self._get(key, _MISSING)
        if not (isinstance(value, list) and len(value) == rows and all(
                isinstance(r, list) and len(r) == cols and all(
                    not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) for v in r)
                for r in value)):
            self._bad(key, f"{rows} lists of {cols} numbers", value)
        return np.array(value, dtype=float)

    def pose(self, key: str) -> Pose3:
        """A pose written `{ xyz_m = [x, y, z], rpy_deg = [roll, pitch, yaw] }` (fixed axes x, y, z)."""
        sub = self.table(key)
        xyz = sub.vector("xyz_m", 3)
        rpy = sub.vector("rpy_deg", 3, default=[0.0, 0.0, 0.0])
        sub.done()
        return from_xyzrpy([*xyz, *np.radians(rpy)])

    def done(self) -> None:
        unknown = sorted(set(self.data) - self._used)
        if unknown:
            known = ", ".join(sorted(self._used)) or "none"
            raise self.error(unknown[0], f"unknown key (known here: {known})")
