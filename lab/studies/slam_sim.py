"""Synthetic BORG surveys for the SF-GraphSLAM studies (`lab bench slam`, tests).

A `Survey` is what one study trial measures: the true tag poses (the design plus injected
structure faults), a camera path with the true and the *reported* camera pose of every view, and
per view the tag measurements `camera_T_tag` with their noise.  The estimators read only the
reported camera poses, the measurements and the design.

Noise (`PaperNoise`, the SF-GraphSLAM paper §3.1/§3.3 and Table 5):
- camera view noise: every measured tag pose gets Gaussian noise of sigma_m = 0.01 m per
  translation axis and sigma_rad = 0.01 * pi / 180 per rotation axis, times (1 + 0.1 d) where d
  is the camera-to-tag distance in metres (the paper's "0.1 camera distance noise multiplier,
  measured as a percentage increase in measured noise per metre from the camera" -- our reading:
  +10 % per metre, applied to both translation and rotation);
- camera pose noise: the reported camera pose differs from the true one by 0.05 m per axis and
  0.01 * pi / 180 rad per axis ("camera-reported ... noise, also known as camera pose error"),
  independently per view; the paper's odometry controls u_t are the reported relative motions;
- "random Gaussian noise" of 1e-5 m on the pose control update and on each measurement (Table 5).
Noise is isotropic per block, so the frame it is drawn in does not matter.

`RigNoise` is the other profile: the simulated bench as the procedure sees it (camera pose from
the rig's encoders, 1 mm / 0.05 deg; tag measurements drawn from the detector's own covariance
model at the view's distance and angle).  The verification study uses it: the paper's 5 cm camera
pose noise is ten times the 5 mm tolerance, so nothing could be verified under it.

Optionally (`measure_rendered`) a survey's views are rendered into real images with
`sim_devices.render` and measured by `estimation.fiducials.TagDetector` instead of drawn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable, Mapping, Sequence

import numpy as np

from estimation.fiducials import Detection
from lab.core.geometry import Pose3, Rot3, look_at
from lab.core.structures.borg import BorgModel

# The simulated bench's camera (lab/rigs/sim.toml [sim.camera]): 1280x720, 70 deg HFOV.
SIM_K = np.array([[914.0, 0.0, 639.5], [0.0, 914.0, 359.5], [0.0, 0.0, 1.0]])
SIM_DIST = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
SIM_SIZE_PX = (1280, 720)
# The sim rig's camera at home, in the world (turntable base) frame: 2.2 m in front of face 1 at
# angle 0, at the cube's mid-height, looking along +x.
RIG_CAMERA_EYE_WORLD = np.array([-2.95, 0.0, 0.75])


@dataclass(frozen=True)
class PaperNoise:
    view_sigma_m: float = 0.01
    view_sigma_rad: float = 0.01 * math.pi / 180.0
    distance_multiplier: float = 0.1          # +10 % of the view noise per metre from the camera
    camera_sigma_m: float = 0.05
    camera_sigma_rad: float = 0.01 * math.pi / 180.0
    random_sigma_m: float = 1e-5              # Table 5's "random Gaussian noise" (pose and means)

    def view_sigmas(self, distance_m: float, camera_T_tag: Pose3 | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(rotation sigmas (3,), translation sigmas (3,)) of one measurement, tag frame."""
        f = 1.0 + self.distance_multiplier * distance_m
        return np.full(3, self.view_sigma_rad * f), np.full(3, math.hypot(self.view_sigma_m * f, self.random_sigma_m))


@dataclass(frozen=True)
class RigNoise:
    """The simulated bench's noise as the procedure's estimator models it."""

    camera_sigma_m: float = 0.001
    camera_sigma_rad: float = math.radians(0.05)
    corner_sigma_px: float = 0.15
    random_sigma_m: float = 0.0

    def view_covariance(self, camera_T_tag: Pose3, size_m: float) -> np.ndarray:
        det = _rig_detector(self.corner_sigma_px)
        corners = project_corners(camera_T_tag, size_m)
        side = float(np.mean(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)))
        return det.measurement_covariance(camera_T_tag, size_m, side, self.corner_sigma_px)


_DETECTORS: dict[float, object] = {}


def _rig_detector(corner_sigma_px: float):
    from estimation.fiducials import DetectorConfig, TagDetector

    if corner_sigma_px not in _DETECTORS:
        _DETECTORS[corner_sigma_px] = TagDetector(SIM_K, np.zeros(5), {}, DetectorConfig(corner_sigma_px=corner_sigma_px))
    return _DETECTORS[corner_sigma_px]


# ---- the truth ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class StructureFaults:
    """What really happened to the structure (all in structure axes).
    module_offsets: module -> (offset_m (3,), rotation rpy_rad (3,)) about the module's anchor;
    deployed_heights: deployable -> lift of its top tag above its bottom tag (m);
    displaced_tags: tag -> offset_m (3,) (a tag knocked off its spot)."""

    module_offsets: Mapping[str, tuple[Sequence[float], Sequence[float]]] = field(default_factory=dict)
    deployed_heights: Mapping[str, float] = field(default_factory=dict)
    displaced_tags: Mapping[int, Sequence[float]] = field(default_factory=dict)


def _correction(about: np.ndarray, offset_m: Sequence[float], rpy_rad: Sequence[float]) -> Pose3:
    R = Rot3.RzRyRx(*[float(a) for a in rpy_rad])
    p = np.asarray(about, dtype=float)
    return Pose3(R, p + np.asarray(offset_m, dtype=float) - R.matrix() @ p)


def true_tag_poses(model: BorgModel, faults: StructureFaults | None = None,
                   tags: Iterable[int] | None = None) -> dict[int, Pose3]:
    """structure_T_tag as built: the design with the faults applied."""
    f = faults or StructureFaults()
    out = {}
    for tid in (model.tags if tags is None else tags):
        spec = model.tags[tid]
        T = spec.structure_T_tag
        if spec.module != "turntable":
            m = model.module_by_name[spec.module]
            if m.kind == "deployable" and tid == m.tags[1] and spec.module in f.deployed_heights:
                drop = model.spacing_m - float(f.deployed_heights[spec.module])
                T = Pose3(T.rotation(), T.translation() - np.array([0.0, 0.0, drop]))
            if spec.module in f.module_offsets:
                off, rpy = f.module_offsets[spec.module]
                T = _correction(m.structure_T_module.translation(), off, rpy).compose(T)
        if tid in f.displaced_tags:
            T = Pose3(T.rotation(), T.translation() + np.asarray(f.displaced_tags[tid], dtype=float))
        out[tid] = T
    return out


# ---- cameras ---------------------------------------------------------------------------------------
def project_corners(camera_T_tag: Pose3, size_m: float, K: np.ndarray = SIM_K) -> np.ndarray:
    """The black square's corners in pixels (top-left, top-right, bottom-right, bottom-left), no
    distortion."""
    h = size_m / 2.0
    obj = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    M = camera_T_tag.matrix()
    pc = obj @ M[:3, :3].T + M[:3, 3]
    uv = pc[:, :2] / pc[:, 2:3]
    return uv @ K[:2, :2].T + K[:2, 2]


def visible(structure_T_camera: Pose3, structure_T_tag: Pose3, size_m: float, *, margin_px: float = 25.0,
            min_side_px: float = 16.0, max_angle_rad: float = math.radians(62.0), max_distance_m: float = 4.0) -> bool:
    """Would the sim camera read this tag? (In the image with a margin, big enough, facing it.)"""
    c_T_t = structure_T_camera.between(structure_T_tag)
    t = c_T_t.translation()
    d = float(np.linalg.norm(t))
    if d > max_distance_m or t[2] < 0.1:
        return False
    normal = c_T_t.rotation().matrix()[:, 2]
    if float(np.dot(normal, -t / d)) < math.cos(max_angle_rad):
        return False
    h = size_m / 2.0
    M = c_T_t.matrix()
    pc = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]]) @ M[:3, :3].T + M[:3, 3]
    if np.any(pc[:, 2] < 0.1):
        return False
    uv = project_corners(c_T_t, size_m)
    w, hgt = SIM_SIZE_PX
    if uv[:, 0].min() < margin_px or uv[:, 1].min() < margin_px or uv[:, 0].max() > w - margin_px \
            or uv[:, 1].max() > hgt - margin_px:
        return False
    return float(np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1).min()) >= min_side_px


def cameras_around(target: Sequence[float], normal: Sequence[float], distance_m: float,
                   offsets_m: Sequence[Sequence[float]]) -> list[Pose3]:
    """structure_T_camera for cameras `distance_m` out along `normal` from `target`, shifted by each
    offset (structure axes) and looking at the target (the paper's few-position camera paths)."""
    tgt = np.asarray(target, dtype=float)
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    return [look_at(tgt + distance_m * n + np.asarray(o, dtype=float), tgt) for o in offsets_m]


def rig_camera(model: BorgModel, turntable_rad: float, pitch_rad: float = 0.0, yaw_rad: float = 0.0,
               lift_m: float = 0.0) -> Pose3:
    """structure_T_camera of the sim rig's camera at a turntable angle, tilted by a Stewart pose
    (pitch up positive, yaw left positive, lift up)."""
    eye = RIG_CAMERA_EYE_WORLD + np.array([0.0, 0.0, lift_m])
    ahead = np.array([math.cos(pitch_rad) * math.cos(yaw_rad), math.cos(pitch_rad) * math.sin(yaw_rad), math.sin(pitch_rad)])
    world_T_camera = look_at(eye, eye + ahead)
    return model.world_T_structure(turntable_rad).inverse().compose(world_T_camera)


def full_survey_path(model: BorgModel, angle_offsets_deg: Sequence[float] = (-25.0, 0.0, 25.0),
                     pitches_deg: Sequence[float] = (-8.0, 0.0, 8.0)) -> list[Pose3]:
    """Turntable angles (each face, +- offsets) x Stewart poses (camera pitch): a survey that sees
    every tag of the cube from several views."""
    out = []
    for face in range(4):
        for da in angle_offsets_deg:
            for p in pitches_deg:
                out.append(rig_camera(model, math.radians(90.0 * face + da), math.radians(p)))
    return out


# ---- measurements ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Observation:
    tag: int
    camera_T_tag: Pose3            # as measured
    covariance: np.ndarray         # 6x6, GTSAM tangent order (rot, trans), tag frame

    @property
    def sigma_m(self) -> float:
        return float(math.sqrt(np.max(np.diag(self.covariance)[3:])))


@dataclass
class SurveyView:
    true_structure_T_camera: Pose3
    reported_structure_T_camera: Pose3
    observations: list[Observation]
    step: int = 0                  # the assembly step (module index) this view belongs to


@dataclass
class Survey:
    model: BorgModel
    tags: list[int]                        # the tags of the study (the map's state)
    truth: dict[int, Pose3]                # structure_T_tag as built
    views: list[SurveyView]
    faults: StructureFaults = field(default_factory=StructureFaults)
    control_noise: list[Pose3] = field(default_factory=list)   # the paper's extra noise on u_t

    def observed_tags(self) -> list[int]:
        return sorted({o.tag for v in self.views for o in v.observations})

    def sightings(self) -> dict[int, int]:
        out: dict[int, int] = {}
        for v in self.views:
            for o in v.observations:
                out[o.tag] = out.get(o.tag, 0) + 1
        return out

    def related_pairs(self) -> list[tuple[int, int, str]]:
        seen = set(self.observed_tags())
        return [(r.a, r.b, r.kind) for r in self.model.relations if r.a in seen and r.b in seen]

    def detections(self, k: int) -> list[Detection]:
        """View k's measurements as the detector would hand them to SF-GraphSLAM."""
        out = []
        for o in self.views[k].observations:
            size = self.model.tags[o.tag].size_m
            out.append(Detection(o.tag, project_corners(o.camera_T_tag, size), o.camera_T_tag, o.covariance,
                                 0.0, float("inf"), False, size))
        return out

    def controls(self) -> list[Pose3]:
        """The paper's u_t (t >= 1): the reported motion from view t-1 to view t."""
        rep = [v.reported_structure_T_camera for v in self.views]
        out = []
        for t in range(1, len(rep)):
            u = rep[t - 1].between(rep[t])
            if self.control_noise:
                u = u.compose(self.control_noise[t - 1])
            out.append(u)
        return out


def _perturb(rng: np.random.Generator, p: Pose3, sig_rad: np.ndarray | float, sig_m: np.ndarray | float) -> Pose3:
    dr = rng.normal(0.0, 1.0, 3) * sig_rad
    dt = rng.normal(0.0, 1.0, 3) * sig_m
    return Pose3(p.rotation().compose(Rot3.Expmap(dr)), p.translation() + dt)


def _draw_gaussian(rng: np.random.Generator, p: Pose3, cov: np.ndarray) -> Pose3:
    """p retracted by a tangent-space (rot, trans; body frame) sample of `cov`."""
    L = np.linalg.cholesky(0.5 * (cov + cov.T) + np.eye(6) * 1e-18)
    return p.retract(L @ rng.normal(0.0, 1.0, 6))


def make_survey(model: BorgModel, tags: Sequence[int], cameras: Sequence[Pose3], rng: np.random.Generator, *,
                noise: PaperNoise | RigNoise | None = None, faults: StructureFaults | None = None,
                steps: Sequence[int] | None = None, present: Sequence[Sequence[int]] | None = None,
                require_visible: bool = True) -> Survey:
    """Measure `tags` (those visible) from each true camera pose.  `present[k]` limits view k to
    the tags placed by then (an assembly in progress); `steps[k]` labels view k's assembly step."""
    noise = noise or PaperNoise()
    faults = faults or StructureFaults()
    truth = true_tag_poses(model, faults, tags)
    views = []
    for k, cam in enumerate(cameras):
        rep = _perturb(rng, cam, noise.camera_sigma_rad, noise.camera_sigma_m)
        obs = []
        allowed = set(present[k]) if present is not None else set(tags)
        for tid in tags:
            if tid not in allowed:
                continue
            size = model.tags[tid].size_m
            # visibility from the design pose: a tag is detected the same whether or not it moved a little
            if require_visible and not visible(cam, truth[tid], size):
                continue
            c_T_t = cam.between(truth[tid])
            if isinstance(noise, PaperNoise):
                sr, sm = noise.view_sigmas(float(np.linalg.norm(c_T_t.translation())))
                cov = np.diag(np.concatenate([sr ** 2, sm ** 2]))
                meas = _perturb(rng, c_T_t, sr, sm)
            else:
                cov = noise.view_covariance(c_T_t, size)
                meas = _draw_gaussian(rng, c_T_t, cov)
            obs.append(Observation(tid, meas, cov))
        views.append(SurveyView(cam, rep, obs, int(steps[k]) if steps is not None else 0))
    rnd = noise.random_sigma_m
    control_noise = [_perturb(rng, Pose3(), 0.0, rnd) for _ in range(max(len(cameras) - 1, 0))] if rnd > 0 else []
    return Survey(model, list(tags), truth, views, faults, control_noise)


def measure_rendered(survey: Survey, rng: np.random.Generator, *, pixel_noise: float = 2.0, blur_px: float = 0.6,
                     use_prediction: bool = True) -> Survey:
    """The same survey measured through pixels: each view is rendered from its true camera pose
    with the sim camera (sim_devices.render) and read by the real detector; the reported camera
    pose predicts the tags to settle IPPE ambiguities, as the procedure does."""
    from estimation.fiducials import TagDetector
    from sim_devices.render import render_tags

    w, h = SIM_SIZE_PX
    sizes = {t: survey.model.tags[t].size_m for t in survey.tags}
    det = TagDetector(SIM_K, SIM_DIST, sizes)
    views = []
    for v in survey.views:
        tags = [(t, sizes[t], v.true_structure_T_camera.between(survey.truth[t])) for t in survey.tags]
        img = render_tags(SIM_K, SIM_DIST, w, h, tags, blur_sigma_px=blur_px, noise_sigma=pixel_noise, rng=rng)
        cam_T_s = v.reported_structure_T_camera.inverse()
        predict = (lambda tid: cam_T_s.compose(survey.model.tags[tid].structure_T_tag)) if use_prediction else None
        obs = [Observation(d.tag_id, d.camera_T_tag, d.covariance) for d in det.detect(img, predict)]
        views.append(SurveyView(v.true_structure_T_camera, v.reported_structure_T_camera, obs, v.step))
    return Survey(survey.model, survey.tags, survey.truth, views, survey.faults, survey.control_noise)


# ---- the studies' camera paths and tag sets --------------------------------------------------------
FACE1_TABLE4_TAGS = (0, 9, 13, 14, 21, 22, 35)          # the paper's face-1 study (Table 4)


def face1_tags(model: BorgModel) -> list[int]:
    """Every module tag on face 1 (the tag-elimination study)."""
    return sorted(t for t, s in model.tags.items() if s.face == 1 and s.module != "turntable")


def module_centre(model: BorgModel, tags: Iterable[int]) -> np.ndarray:
    return np.mean([model.tags[t].structure_T_tag.translation() for t in tags], axis=0)


def three_position_path(model: BorgModel, tags: Sequence[int], distance_m: float = 2.0,
                        spread_m: float = 0.3) -> list[Pose3]:
    """The paper's deployable test: the camera moves between three positions in front of the
    tags' face, all looking at the tags' centre."""
    c = module_centre(model, tags)
    normal = model.tags[tags[0]].structure_T_tag.rotation().matrix()[:, 2]
    side = np.cross([0.0, 0.0, 1.0], normal)
    return cameras_around(c, normal, distance_m, [-spread_m * side, 0.0 * side, spread_m * side])


def face_path(model: BorgModel, tags: Sequence[int], distance_m: float = 2.2) -> list[Pose3]:
    """A few views of a face's tag group (centre, left, right, up, down) from about 2.2 m."""
    c = module_centre(model, tags)
    normal = model.tags[tags[0]].structure_T_tag.rotation().matrix()[:, 2]
    side = np.cross([0.0, 0.0, 1.0], normal)
    up = np.array([0.0, 0.0, 1.0])
    offs = [0 * up, -0.4 * side, 0.4 * side, 0.25 * up, -0.25 * up]
    return cameras_around(c, normal, distance_m, offs)


def assembly_path(model: BorgModel, modules: Sequence[str] | None = None,
                  angle_offsets_deg: Sequence[float] = (-20.0, 0.0, 20.0),
                  pitches_deg: Sequence[float] = (-8.0, 0.0, 8.0)) -> tuple[list[Pose3], list[int], list[list[int]]]:
    """An assembly in progress, surveyed as the procedure does: after each module is placed, one
    view per turntable offset around its face, each at the camera pitch that sees most of the new
    module's tags and, among those, most of the tags they are related to (so that their relations
    can be decided).  Returns (cameras, step of each view, tags present in each view)."""
    names = list(modules) if modules is not None else [m.name for m in model.modules]
    cams: list[Pose3] = []
    steps: list[int] = []
    present: list[list[int]] = []
    placed = list(model.turntable.tag_ids)
    for i, name in enumerate(names):
        m = model.module_by_name[name]
        placed = placed + list(m.tags)
        related = {r for t in m.tags for r in model.tags[t].related if r in placed and r not in m.tags}
        for da in angle_offsets_deg:
            best = None
            for p in pitches_deg:
                cam = rig_camera(model, math.radians(90.0 * (m.face - 1) + da), math.radians(p))
                seen = [visible(cam, model.tags[t].structure_T_tag, model.tags[t].size_m) for t in m.tags]
                seen_rel = [visible(cam, model.tags[t].structure_T_tag, model.tags[t].size_m) for t in related]
                n = (sum(seen), sum(seen_rel))
                if best is None or n > best[0] or (n == best[0] and abs(p) < abs(best[2])):
                    best = (n, cam, p)
            assert best is not None
            cams.append(best[1])
            steps.append(i)
            present.append(list(placed))
    return cams, steps, present
