"""The simulated world: the design structure plus what really happened, seeded.

`SimWorld` holds every physical truth the device simulators act on and the camera sees:
- the turntable axis (rad), the Stewart platform's six legs (m) and the lift's height (m), moved
  by their controllers;
- the true rig (`TrueRig`): the rig file plus the rig's errors (`lab/core/rig_error.py`: the rig's
  `[sim.rig_error]`, or the scenario's `[rig_error]`), which the software is never told -- the
  camera mount, the Stewart base, the turntable's rotation axis (offset and tilt), each turntable
  tag's placement, the lens' focal length and principal point, the lift's travel direction, and a
  fresh repeatability error of the platform pose, of the turntable angle and of the lift's
  carriage at every move;
- the true camera pose, world_T_camera = lift(h) · world_T_base · base_T_platform(true legs) ·
  repeatability · platform_T_camera, all of them the true ones; lift(h) moves the base h along the
  lift's true (tilted) axis plus its repeatability error once the lift has moved (a lift that never
  moved leaves the base where the rig file says, as the 3x3x3 runs have it);
- the world frame is where the turntable plate sits at encoder zero, so the structure turns about
  the true axis: world_T_structure(a) = world_T_axis · Rz(a + repeatability) · axis_T_world ·
  world_T_structure_design(0);
- the BORG structure (`BorgTruth`): which modules are placed so far (their tags, and their struts
  and nodes: `BorgTruth.truss`, drawn in every frame by `sim_devices.render_truss`, in front of the
  tags they hide), per-module pose errors, partial deployments, displaced tags;
- the lab's lamp (`LIGHT_WORLD`), which shades the truss;
- each IPJR's actuator (`sim_devices.ipjr.IpjrActuator`), and the strut it is attached to;
- the camera as it really images (`TrueCamera`, `lab/core/imaging.py`: the rig's `[sim.camera]` and
  `[sim.tags]` with the scenario's `[camera]` / `[tags]` keys replacing theirs): the true lens
  (focal scale, principal point and a distortion that differs from the calibration file by
  `distortion_error_px` at the frame's corners), its depth of field, vignetting and the light
  across the frame (one gain map per world), shot and read noise; and every tag as printed and lit:
  its size off by its print scale (`printed_size_m`: `tags_in_view` gives the size as printed, the
  pose stays the tag's centre and corners' plane), its bow and its light level (`tag_look`).  The
  truss is imaged by the same camera: blurred for its depth, vignetted and lit by the gain map,
  and under the same noise as the tags.

Procedures use it in simulation to act as the operator (place a module, attach an IPJR) and to
score their estimates against the truth.  It never reads anything the drivers compute.

Seeding: every random part draws from its own generator, `default_rng([seed, k])`, so adding one
does not change the others' numbers.

Left out: errors of the Stewart joint positions and leg encoders (the platform's own kinematic
calibration), the structure's placement on the plate (the structure frame is the plate's), thermal
drift; of the imaging, what `sim_devices/render.py` leaves out (glare, shadows, motion blur, rolling
shutter, fixed-pattern noise), and light that changes as the structure turns (the light field is
fixed in the frame, each tag's level fixed per tag)."""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from lab.core.config import Rig
from lab.core.errors import UserError
from lab.core.geometry import Pose3, Rot3, to_xyzrpy
from lab.core.imaging import IDEAL, Imaging
from lab.core.rig_error import RigError
from lab.core.scenario import BorgFault, Scenario
from lab.core.structures.borg import BorgModel, build_borg
from sim_devices.ipjr import IpjrActuator
from sim_devices.motion import Axis
from sim_devices.render import (QUIET_ZONE_CELLS, Defocus, TagLook, distortion_with_error, draw_tags, lighting_field,
                                 vignetting_gain)
from sim_devices.stewart import platform_pose
from sim_devices.truss_geometry import TagCard, TrussOccluders, in_camera, truss_occluders

# The lab's lamp: the direction towards it in the world frame (above the structure, on the
# camera's side); it shades the truss's struts and nodes (sim_devices.render_truss).
LIGHT_WORLD = np.array([-0.45, 0.25, 0.86]) / np.linalg.norm([-0.45, 0.25, 0.86])

# Independent random streams (the k in default_rng([seed, k])).
_STREAM_CAMERA, _STREAM_TT_TAGS, _STREAM_MOTION, _STREAM_LIFT, _STREAM_IPJR = 1, 2, 3, 4, 100
# issue 19's imaging: the lens's distortion error, the light across the frame, each printed tag
_STREAM_LENS, _STREAM_LIGHT, _STREAM_TAG_PRINT = 5, 6, 7


@dataclass(frozen=True)
class TrueRig:
    """The bench as it really is (what the rig file only approximates)."""

    world_T_base: Pose3 | None
    platform_T_camera: Pose3 | None
    world_T_axis: Pose3              # the turntable's rotation axis is this frame's z axis
    world_T_lift: Pose3 = Pose3()    # the lift travels along this frame's z axis

    def lift_direction(self) -> np.ndarray:
        return self.world_T_lift.rotation().matrix()[:, 2]


def true_rig(rig: Rig, e: RigError) -> TrueRig:
    """A mount off its nominal pose: turned by the roll-pitch-yaw about its own origin and moved by
    the offset, both in the parent frame's axes (the structure faults' `_correction`)."""
    base = cam = None
    if rig.stewart is not None:
        n = rig.stewart.world_T_base
        base = _correction(n.translation(), e.stewart_base_offset_m, e.stewart_base_rotation_rad).compose(n)
    if rig.camera is not None:
        n = rig.camera.platform_T_camera
        cam = _correction(n.translation(), e.camera_mount_offset_m, e.camera_mount_rotation_rad).compose(n)
    tx, ty = e.turntable_axis_tilt_rad
    dx, dy = e.turntable_axis_offset_m
    lx, ly = e.lift_axis_tilt_rad
    return TrueRig(base, cam, Pose3(Rot3.RzRyRx(tx, ty, 0.0), np.array([dx, dy, 0.0])),
                   Pose3(Rot3.RzRyRx(lx, ly, 0.0), np.zeros(3)))


def _correction(about: np.ndarray, offset_m: Iterable[float], rotation_rad: Iterable[float]) -> Pose3:
    """A rigid correction in structure axes: rotate by roll-pitch-yaw about the point `about`, then
    translate by `offset_m`.  Applied on the left of a structure_T_x pose."""
    R = Rot3.RzRyRx(*[float(a) for a in rotation_rad])
    p = np.asarray(about, dtype=float)
    return Pose3(R, p + np.asarray(list(offset_m), dtype=float) - R.matrix() @ p)


# a tag's card across, in black squares: the square (8 cells) and a quiet zone on each side
_CARD_PER_SQUARE = (8.0 + 2.0 * QUIET_ZONE_CELLS) / 8.0


class BorgTruth:
    """The BORG truss as built so far."""

    def __init__(self, model: BorgModel) -> None:
        self.model = model
        self.placed: list[str] = []
        self._module_fix: dict[str, Pose3] = {}
        self._height: dict[str, float] = {}
        self._tag_fix: dict[int, Pose3] = {}
        self._placement: dict[int, Pose3] = {}     # as glued: not a fault, part of the rig's error
        self._lock = threading.RLock()
        # the truss drawn for a state (the placed modules, the truth's changes so far): a camera
        # takes several frames of each, and drawing a 10x10x10 takes ~0.1 s
        self._changes = 0
        self._truss: tuple[tuple[tuple[str, ...], int], TrussOccluders] | None = None

    def set_tag_placement(self, tag: int, error: Pose3) -> None:
        """Where a tag was really glued: `error` composed on the right of its design pose."""
        self._placement[tag] = error
        self._changes += 1

    # -- what the operator does ---------------------------------------------------------------------
    def _module(self, name: str):
        try:
            return self.model.module_by_name[name]
        except KeyError:
            raise UserError(f"no BORG module named {name!r} (known: {', '.join(m.name for m in self.model.modules)})") from None

    def place(self, name: str) -> None:
        """The operator places (and deploys) a module: its tags become visible."""
        self._module(name)
        with self._lock:
            if name not in self.placed:
                self.placed.append(name)

    def place_all(self) -> None:
        for m in self.model.modules:
            self.place(m.name)

    def remove(self, name: str) -> None:
        with self._lock:
            if name in self.placed:
                self.placed.remove(name)

    def is_placed(self, name: str) -> bool:
        return name in self.placed

    # -- what went wrong ------------------------------------------------------------------------------
    def set_module_offset(self, name: str, offset_m: Iterable[float] = (0, 0, 0),
                          rotation_rad: Iterable[float] = (0, 0, 0)) -> None:
        """The whole module sits off its design pose: translated by offset_m (structure axes) and
        rotated by roll-pitch-yaw (structure axes) about its anchor point."""
        m = self._module(name)
        self._module_fix[name] = _correction(m.structure_T_module.translation(), offset_m, rotation_rad)
        self._changes += 1

    def set_deployed_height(self, name: str, height_m: float | None) -> None:
        """A deployable stopped short: its top (T) tag sits height_m above its bottom (B) tag
        instead of the node spacing.  None restores full deployment."""
        m = self._module(name)
        if m.kind != "deployable":
            raise UserError(f"module {name} is a {m.kind}, not a deployable: it has no deployed height")
        self._changes += 1
        if height_m is None:
            self._height.pop(name, None)
            return
        if not 0.0 < height_m <= self.model.spacing_m:
            raise UserError(f"deployed height of {name} must be in (0, {self.model.spacing_m}] m, got {height_m} m")
        self._height[name] = float(height_m)

    def displace_tag(self, tag: int, offset_m: Iterable[float] = (0, 0, 0),
                     rotation_rad: Iterable[float] = (0, 0, 0)) -> None:
        """A tag knocked off its spot: moved by offset_m (structure axes), rotated about its centre."""
        if tag not in self.model.tags:
            raise UserError(f"no tag {tag} on this BORG structure (ids 0..{max(self.model.tags)})")
        about = self.model.tags[tag].structure_T_tag.translation()
        self._tag_fix[tag] = _correction(about, offset_m, rotation_rad)
        self._changes += 1

    def apply(self, faults: Iterable[BorgFault]) -> None:
        for f in faults:
            if f.kind == "partial_deploy":
                assert f.module is not None
                self.set_deployed_height(f.module, f.height_m)
            elif f.kind == "tag_displaced":
                assert f.tag is not None
                self.displace_tag(f.tag, f.offset_m, f.rotation_rad)
            elif f.kind == "module_offset":
                assert f.module is not None
                self.set_module_offset(f.module, f.offset_m, f.rotation_rad)
            else:
                raise UserError(f"unknown BORG fault kind {f.kind!r}")

    # -- the truth ------------------------------------------------------------------------------------
    def deployed_height_m(self, name: str) -> float:
        return self._height.get(name, self.model.spacing_m)

    def structure_T_module(self, name: str) -> Pose3:
        m = self._module(name)
        fix = self._module_fix.get(name, Pose3())
        return fix.compose(m.structure_T_module)

    def structure_T_tag(self, tag: int) -> Pose3:
        spec = self.model.tags[tag]
        T = spec.structure_T_tag
        if tag in self._placement:
            T = T.compose(self._placement[tag])
        if spec.module != "turntable":
            m = self.model.module_by_name[spec.module]
            if m.kind == "deployable" and len(m.tags) == 2 and tag == m.tags[1] and spec.module in self._height:
                drop = self.model.spacing_m - self._height[spec.module]
                T = Pose3(T.rotation(), T.translation() - np.array([0.0, 0.0, drop]))
            T = self._module_fix.get(spec.module, Pose3()).compose(T)
        if tag in self._tag_fix:
            T = self._tag_fix[tag].compose(T)
        return T

    def truss(self) -> TrussOccluders:
        """The struts and node bodies of the modules placed so far, where they really are
        (structure frame; `sim_devices.truss_geometry`)."""
        with self._lock:
            placed = tuple(self.placed)
            if self._truss is not None and self._truss[0] == (placed, self._changes):
                return self._truss[1]
            cards = [TagCard(self.structure_T_tag(t), self.model.tags[t].size_m / 2.0 * _CARD_PER_SQUARE)
                     for n in placed for t in self.model.module_by_name[n].tags]
            occ = truss_occluders(self.model, placed, {n: self.structure_T_module(n) for n in placed},
                                  {n: self.deployed_height_m(n) for n in placed}, cards=cards)
            self._truss = ((placed, self._changes), occ)
            return occ

    def visible_tag_ids(self) -> list[int]:
        """Tags that exist right now: the turntable's and those of placed modules."""
        with self._lock:
            ids = list(self.model.turntable.tag_ids)
            for name in self.placed:
                ids.extend(self.model.module_by_name[name].tags)
        return ids


@dataclass(frozen=True)
class TrueCamera:
    """The camera as it really is.  K and dist are the true lens (the rig's focal scale, principal
    point offset and distortion error applied), never told to the software: the calibration file
    and the camera's /intrinsics.json hold `nominal_K`, `nominal_dist` ([sim.camera] as written)."""

    K: np.ndarray
    dist: np.ndarray
    width_px: int
    height_px: int
    pixel_noise: float
    blur_px: float
    imaging: Imaging = IDEAL
    nominal_K: np.ndarray | None = None
    nominal_dist: np.ndarray | None = None

    @property
    def jpeg_quality(self) -> int:
        return self.imaging.jpeg_quality

    def defocus(self) -> Defocus | None:
        """The lens's depth of field (None: everything in focus)."""
        im = self.imaging
        if im.focus_distance_m <= 0:
            return None
        return Defocus(im.focus_distance_m, im.f_number, im.focal_length_m(float(self.K[0, 0])))


def true_camera(rig: Rig, imaging: Imaging, rig_error: RigError, seed: int) -> TrueCamera:
    """The simulated rig's camera as it really is: `[sim.camera]`'s lens with the rig error's focal
    scale and principal point offset, its distortion moved by `imaging.distortion_error_px` (sign
    and k1/k2 share from the lens's own stream of `seed`), imaging as given.  The world's camera,
    and the one `lab calibrate camera --sim` renders its board with."""
    assert rig.sim is not None
    c = rig.sim.camera
    f = rig_error.focal_scale
    du, dv = rig_error.principal_point_offset_px
    K0 = np.array([[c["fx_px"], 0.0, c["cx_px"]], [0.0, c["fy_px"], c["cy_px"]], [0.0, 0.0, 1.0]])
    K = np.array([[c["fx_px"] * f, 0.0, c["cx_px"] + du], [0.0, c["fy_px"] * f, c["cy_px"] + dv],
                  [0.0, 0.0, 1.0]])
    dist0 = np.asarray(c["dist"], dtype=float)
    dist = dist0
    if imaging.distortion_error_px > 0:
        lens = np.random.default_rng([seed, _STREAM_LENS])
        sign, share = (1.0 if lens.random() < 0.5 else -1.0), float(lens.uniform(0.0, 1.0))
        dist = distortion_with_error(K0, dist0, int(c["width_px"]), int(c["height_px"]),
                                     imaging.distortion_error_px, sign, share)
    f_m = imaging.focal_length_m(float(K[0, 0]))
    if imaging.focus_distance_m and imaging.focus_distance_m < 2 * f_m:
        raise UserError(f"camera focus distance {imaging.focus_distance_m} m is within twice the focal "
                        f"length ({2 * f_m:g} m): a lens cannot focus there")
    return TrueCamera(K, dist, int(c["width_px"]), int(c["height_px"]), imaging.pixel_noise,
                      imaging.blur_px, imaging, K0, dist0)


def camera_gain_map(cam: TrueCamera, seed: int) -> np.ndarray | None:
    """The scene radiance's factor per pixel of `cam`'s frame: vignetting times the light across
    the frame (from the light's own stream of `seed`); None when both are off."""
    im = cam.imaging
    if im.vignetting == 0 and im.lighting_variation == 0:
        return None
    g = vignetting_gain(cam.width_px, cam.height_px, im.vignetting)
    if im.lighting_variation > 0:
        g *= lighting_field(cam.width_px, cam.height_px, im.lighting_variation,
                            np.random.default_rng([seed, _STREAM_LIGHT]))
    return g


class SimWorld:
    def __init__(self, rig: Rig, scenario: Scenario | None = None, *, speedup: float | None = None,
                 borg_n: int | None = None) -> None:
        """`borg_n`: the size of the BORG this simulation is of (a run's `--n`); default the rig's
        [sim] borg_n.  The world simulates the run's structure, whatever size the rig file names."""
        if rig.sim is None:
            raise UserError(f"rig {rig.name!r} has no [sim] table: it describes real hardware, not a simulation")
        self.rig = rig
        self.scenario = scenario or Scenario(seed=rig.sim.seed)
        self.seed = self.scenario.seed
        self.speedup = float(speedup if speedup is not None else rig.sim.speedup)
        if not self.speedup > 0:
            raise UserError(f"speed-up must be positive, got {self.speedup}")
        sim = rig.sim
        self._lock = threading.RLock()
        self.started_s = time.time()
        self.rig_error = self.scenario.rig_error if self.scenario.rig_error is not None else sim.rig_error
        self.true_rig = true_rig(rig, self.rig_error)
        # per-move repeatability: a fresh error whenever an axis has started a move since the last
        # look (and at every reseed, so a re-run step sees the same rig as the first time)
        self._motion_rng = np.random.default_rng([self.seed, _STREAM_MOTION])
        self._tt_repeat: tuple[int, float] | None = None
        self._stewart_repeat: tuple[int, Pose3] | None = None
        # the lift's own stream: a rig without one (or a run that never moves it) draws exactly the
        # numbers it drew before the lift existed
        self._lift_rng = np.random.default_rng([self.seed, _STREAM_LIFT])
        self._lift_repeat: tuple[int, np.ndarray] | None = None

        # -- the turntable and the structure on it
        self.turntable: Axis | None = None
        if rig.turntable:
            t = sim.turntable
            self.turntable = Axis(0.0, math.radians(t["speed_deg_s"]) * self.speedup, t["settle_s"] / self.speedup)
        self.borg: BorgTruth | None = None
        if rig.turntable or rig.camera:
            n = sim.borg_n if borg_n is None else borg_n
            try:
                model = build_borg(n)
            except ValueError as exc:
                raise UserError(str(exc)) from None
            self.borg = BorgTruth(model)
            if rig.camera:
                draw_tags(model.tags)
            sig = self.rig_error.turntable_tag_sigma_m
            if sig > 0:
                rng = np.random.default_rng([self.seed, _STREAM_TT_TAGS])
                for tid in self.borg.model.turntable.tag_ids:
                    rot_sig = sig / self.borg.model.tags[tid].size_m
                    self.borg.set_tag_placement(tid, Pose3(Rot3.Expmap(rng.normal(0.0, rot_sig, 3)),
                                                           rng.normal(0.0, sig, 3)))
            self.borg.apply(self.scenario.borg_faults)

        # -- the lift under the Stewart base: at 0 at power-up (an absolute encoder: no homing)
        self.lift: Axis | None = None
        if rig.lift:
            lf = sim.lift
            self.lift = Axis(0.0, lf["speed_mm_s"] / 1000.0 * self.speedup, lf["settle_s"] / self.speedup)

        # -- the Stewart platform
        self.stewart_legs: Axis | None = None
        self._last_platform = np.zeros(6)
        if rig.stewart:
            g = rig.stewart.geometry
            home_legs = np.linalg.norm(g.home_m + g.platform_joints_m - g.base_joints_m, axis=1)
            s = sim.stewart
            self.stewart_legs = Axis(home_legs, s["speed_mm_s"] / 1000.0 * self.speedup, s["settle_s"] / self.speedup)

        # -- the camera
        self.camera: TrueCamera | None = None
        self._camera_rng = np.random.default_rng([self.seed, _STREAM_CAMERA])
        self._gain: np.ndarray | None = None
        self._looks: dict[int, TagLook] = {}
        self._print_scale: dict[int, float] = {}
        if rig.camera:
            # the rig's imaging, with the keys the scenario names replaced (lab/core/imaging.py)
            imaging = sim.imaging.with_overrides(self.scenario.camera.overrides())
            self.camera = true_camera(rig, imaging, self.rig_error, self.seed)
            if self.borg is not None:
                self._draw_tag_prints(imaging)

        # -- the IPJRs
        self.ipjrs: dict[str, IpjrActuator] = {}
        p = sim.ipjr
        for k, (name, cfg) in enumerate(rig.ipjrs.items()):
            rng = np.random.default_rng([self.seed, _STREAM_IPJR + k])
            axis = Axis(min(p["start_extension_m"], cfg.stroke_m), p["speed_mm_s"] / 1000.0 * self.speedup,
                        p["settle_s"] / self.speedup)
            self.ipjrs[name] = IpjrActuator(
                name, stroke_m=cfg.stroke_m, step_m=cfg.step_m, axis=axis,
                volts_retracted=cfg.volts_retracted + rng.normal(0.0, p["calibration_sigma_v"]),
                volts_extended=cfg.volts_extended + rng.normal(0.0, p["calibration_sigma_v"]),
                volts_noise_v=p["volts_noise_v"], step_scale=1.0 + rng.normal(0.0, p["step_scale_sigma"]),
                move_sigma_m=p["move_sigma_m"], rng=rng)

    def _draw_tag_prints(self, imaging: Imaging) -> None:
        """Each tag as printed and lit: its size error, its bow, its light, from its own seeded stream
        (one per tag id, so a tag is the same tag whatever else the world holds).  Every draw is
        made whatever the keys, so changing one key does not change the others' numbers."""
        assert self.borg is not None
        for tid in self.borg.model.tags:
            rng = np.random.default_rng([self.seed, _STREAM_TAG_PRINT, tid])
            scale, light, bow_sign, mix = rng.normal(), rng.uniform(-1.0, 1.0), rng.random(), rng.random()
            self._print_scale[tid] = 1.0 + imaging.print_scale_sigma * float(np.clip(scale, -4.0, 4.0))
            look = TagLook(gain=1.0 + imaging.lighting_variation * float(light),
                           bow_m=imaging.flatness_m * (1.0 if bow_sign < 0.5 else -1.0), bow_mix=float(mix))
            if look.gain != 1.0 or look.bow_m != 0.0:
                self._looks[tid] = look

    def tag_look(self, tag: int) -> TagLook:
        """How tag `tag` is printed and lit (its light level, its bow); an ideal tag by default."""
        return self._looks.get(tag, TagLook())

    def printed_size_m(self, tag: int) -> float:
        """The true edge of tag `tag`'s black square: its design size times its print scale."""
        assert self.borg is not None
        return self.borg.model.tags[tag].size_m * self._print_scale.get(tag, 1.0)

    def gain_map(self) -> np.ndarray | None:
        """The scene radiance's factor per pixel (vignetting times the light across the frame), made
        once per world; None when both are off."""
        cam = self.camera
        assert cam is not None
        im = cam.imaging
        if im.vignetting == 0 and im.lighting_variation == 0:
            return None
        with self._lock:
            if self._gain is None:
                self._gain = camera_gain_map(cam, self.seed)
            return self._gain

    # -- truth queries ------------------------------------------------------------------------------
    def turntable_angle_rad(self) -> float:
        """The plate's true angle: the encoder's plus this move's repeatability error."""
        if not self.turntable:
            return 0.0
        with self._lock:
            moves = self.turntable.moves
            if self._tt_repeat is None or self._tt_repeat[0] != moves:
                self._tt_repeat = (moves, float(self._motion_rng.normal(0.0, self.rig_error.turntable_repeatability_rad)))
            return float(self.turntable.position()) + self._tt_repeat[1]

    def _stewart_repeatability(self) -> Pose3:
        assert self.stewart_legs is not None
        e = self.rig_error
        with self._lock:
            moves = self.stewart_legs.moves
            if self._stewart_repeat is None or self._stewart_repeat[0] != moves:
                self._stewart_repeat = (moves, Pose3(Rot3.Expmap(self._motion_rng.normal(0.0, e.stewart_repeatability_rad, 3)),
                                                     self._motion_rng.normal(0.0, e.stewart_repeatability_m, 3)))
            return self._stewart_repeat[1]

    def lift_offset_m(self) -> np.ndarray:
        """Where the lift has really carried the Stewart base from the rig file's pose: the height
        along the true (tilted) axis, plus this move's repeatability error.  Zero for a lift that
        has not moved since power-up."""
        if self.lift is None or self.lift.moves == 0:
            return np.zeros(3)
        h = float(self.lift.position())
        with self._lock:
            moves = self.lift.moves
            if self._lift_repeat is None or self._lift_repeat[0] != moves:
                self._lift_repeat = (moves, self._lift_rng.normal(0.0, self.rig_error.lift_repeatability_m, 3))
            return h * self.true_rig.lift_direction() + self._lift_repeat[1]

    def home_T_platform(self) -> Pose3:
        """The platform's true pose relative to home, from the true leg lengths."""
        if self.stewart_legs is None or self.rig.stewart is None:
            return Pose3()
        legs = np.asarray(self.stewart_legs.position())
        with self._lock:
            pose = platform_pose(self.rig.stewart.geometry, legs, self._last_platform)
            self._last_platform = to_xyzrpy(pose)
        return pose

    def world_T_camera(self) -> Pose3:
        if self.rig.camera is None:
            raise UserError(f"rig {self.rig.name!r} has no camera")
        platform_T_camera = self.true_rig.platform_T_camera
        assert platform_T_camera is not None
        if self.rig.stewart is None:
            return platform_T_camera  # a fixed camera: its mount pose is in the world frame
        g = self.rig.stewart.geometry
        hp = self.home_T_platform()
        base_T_platform = Pose3(hp.rotation(), g.home_m + hp.translation()).compose(self._stewart_repeatability())
        world_T_base = self.true_rig.world_T_base
        assert world_T_base is not None
        if self.lift is not None and self.lift.moves:
            world_T_base = Pose3(Rot3(), self.lift_offset_m()).compose(world_T_base)
        return world_T_base.compose(base_T_platform).compose(platform_T_camera)

    def world_T_structure(self) -> Pose3:
        """The structure turns with the plate about the true axis; at encoder zero it sits where
        the design puts it (that defines the world frame)."""
        assert self.borg is not None
        A = self.true_rig.world_T_axis
        at_zero = self.borg.model.world_T_structure(0.0)
        return A.compose(Pose3(Rot3.Rz(self.turntable_angle_rad()), np.zeros(3))).compose(A.inverse()).compose(at_zero)

    def world_T_tag(self, tag: int) -> Pose3:
        assert self.borg is not None
        return self.world_T_structure().compose(self.borg.structure_T_tag(tag))

    def tags_in_view(self) -> list[tuple[int, float, Pose3]]:
        """(id, size, camera_T_tag) of every tag that exists now (the renderer culls the rest): the
        size as printed (`printed_size_m`), the pose the tag's centre and corners' plane's."""
        if self.borg is None:
            return []
        return self._tags_seen_from(self.world_T_camera().inverse().compose(self.world_T_structure()))

    def _tags_seen_from(self, camera_T_structure: Pose3) -> list[tuple[int, float, Pose3]]:
        """(id, size as printed, camera_T_tag) of every tag that exists now, seen from a camera at
        `camera_T_structure` (what `tags_in_view` and `render` give for the camera's true pose)."""
        assert self.borg is not None
        return [(tid, self.printed_size_m(tid), camera_T_structure.compose(self.borg.structure_T_tag(tid)))
                for tid in self.borg.visible_tag_ids()]

    def reseed_camera(self, seed: Any) -> None:
        """Restart the camera's noise stream (e.g. from [seed, stream, step, view]), so that a
        procedure step re-run after an interruption sees the same noise as the first time."""
        with self._lock:
            self._camera_rng = np.random.default_rng(seed)
            # this view's repeatability errors are drawn afresh from the same seed
            self._motion_rng = np.random.default_rng([*np.atleast_1d(seed).tolist(), _STREAM_MOTION])
            self._lift_rng = np.random.default_rng([*np.atleast_1d(seed).tolist(), _STREAM_LIFT])
            self._tt_repeat = self._stewart_repeat = self._lift_repeat = None

    def render(self) -> np.ndarray:
        """The image the camera's sensor reads now (BGR uint8), before the camera encodes it (JPEG at
        the camera's jpeg_quality: `sim_devices.camera.encode_frame`): the tags that exist, and the
        truss built so far in front of and behind them (always: a real camera cannot look through
        struts), both through the same lens, light and noise."""
        from sim_devices.render import render_tags

        cam = self.camera
        if cam is None:
            raise UserError(f"rig {self.rig.name!r} has no camera")
        with self._lock:
            rng = np.random.default_rng(self._camera_rng.integers(2**63))
        imaging = dict(blur_sigma_px=cam.blur_px, noise_sigma=cam.pixel_noise, rng=rng, defocus=cam.defocus(),
                       looks=self._looks or None, gain=self.gain_map(), full_well_e=cam.imaging.full_well_e)
        if self.borg is None:
            return render_tags(cam.K, cam.dist, cam.width_px, cam.height_px, [], **imaging)
        camera_T_world = self.world_T_camera().inverse()
        camera_T_structure = camera_T_world.compose(self.world_T_structure())
        return render_tags(cam.K, cam.dist, cam.width_px, cam.height_px, self._tags_seen_from(camera_T_structure),
                           overlay=self._truss_overlay(camera_T_structure, camera_T_world), **imaging)

    def _truss_overlay(self, camera_T_structure: Pose3, camera_T_world: Pose3):
        """`render_tags`'s overlay that draws the truss built so far as the camera sees it from
        there (None: nothing built), through the true lens and its depth of field, lit by the lamp."""
        from sim_devices.render_truss import draw_truss

        cam = self.camera
        assert cam is not None and self.borg is not None
        truss = in_camera(self.borg.truss(), camera_T_structure)
        if truss.n_struts == 0 and truss.n_nodes == 0:
            return None
        light = camera_T_world.rotation().matrix() @ LIGHT_WORLD
        defocus = cam.defocus()

        def overlay(grey: np.ndarray, depth: np.ndarray) -> None:
            draw_truss(grey, depth, cam.K, cam.dist, truss, blur_sigma_px=cam.blur_px, defocus=defocus,
                       light_camera=light)

        return overlay

