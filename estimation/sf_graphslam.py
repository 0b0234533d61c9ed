"""GraphSLAM and SF-GraphSLAM on GTSAM (paper §2.5, design.md §5).

Variables: one camera pose per survey view and one pose per tag, all in the structure frame; with
a rig model (`rig=`), also the rig's calibration (turntable axis, Stewart base, camera mount:
estimation/rig_model.py), shared by every view of the run.
Factors, a few lines per type below:
- camera (noise R), one of two kinds:
  * with a rig model, a kinematic chain factor per view: the camera is a function of the commanded
    turntable angle and Stewart pose and of the calibration variables, up to the devices'
    repeatability.  The calibration starts from a rig calibration file or from the rig file's
    nominal values with wide priors, and every view refines it; the turntable tags get priors at
    their designed (or calibrated) poses, which fix the structure frame;
  * without one (studies), a prior at the camera pose from the rig's kinematics: the paper's
    first-pose anchor plus odometry g(u_t, x_{t-1}) with the same noise, without accumulating it;
- tag observation (noise Q from the detector: growing with distance, frontal tilt, residual; Huber
  kernel): BetweenFactorPose3(camera, tag, camera_T_tag);
- semantic (noise S), SF-GraphSLAM only: BetweenFactorPose3(tag a, tag b, designed tag_a_T_tag_b)
  for related tags (Table 1).  A semantic factor joins the graph only once the measured relative
  pose, from the graph without it, agrees with the design: a deployable pair must be kinematically
  valid and fully deployed (estimation/semantics.py); any other pair within `gate_m` / `gate_rad`
  of its design (widened to the noise's chi-square quantile at `gate_alpha` where the pair is measured worse).  So the design can sharpen an estimate the measurements already agree
  with, and never pull a real deviation back to the design: a failed gate drops that factor
  (the pair reverts to GraphSLAM) and is reported.
GraphSLAM is the same graph with `semantic=False`.

Solvers: iSAM2 (incremental, between assembly steps; relinearise threshold 0.001 in the tangent
units, 0.05 px for the intrinsics, every update) and batch Levenberg–Marquardt for studies.
Marginal covariances from iSAM2.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Iterable, Sequence

import gtsam
import numpy as np

from estimation.corner_noise import AbsoluteResiduals, CornerNoise
from estimation.fiducials import Detection, tag_object_points
from estimation import corner_kernel, levenberg_marquardt
from estimation.rig_model import (GAUGE_SIGMA, AXIS, BASE, DISTORTION, INTRINSICS, LIFT, MIN_SIDE_RATIO, MOUNT, OBLIQUE_EXPONENT, RigGeometry, ViewMotion, cal3_s2,
                                  CornerSighting, chain_factor, corner_factor, distortion_prior_sigmas, intrinsics_basis_many, radial_basis_many,
                                  refine_tag_pose, tag_prior_noise,
                                  undistort_px)
from estimation.semantics import DeployCheck, deployable_check
from estimation.view_batch import TAGS_PER_FACTOR, BatchCost, ViewBatch
from lab.core.geometry import Pose3, Rot3
from lab.core.rig_calibration_file import RigCalibration
from lab.core.structures.borg import BorgModel

OBSERVATIONS = ("corners", "corner-info", "pose")
C = gtsam.symbol_shorthand.C   # camera views
_T = gtsam.symbol_shorthand.T  # tags: T(tag id + GENERATION * generation)
_S = gtsam.symbol_shorthand.S  # each printed tag's scale error (SlamConfig.tag_scale_sigma)
GENERATION = 10_000             # a re-placed module's tags are new map elements
# tags per joint marginal in `tag_covariances`: each call walks the tree's shortcuts, and a joint's
# dense part grows as its cube.  Every tag of an N = 8 run at round 300 (418 tags), CPU from cold
# shortcuts: 64 a chunk 15.0 s, 128 8.6 s, 256 3.9-4.2 s, 512 7.8 s, all at once 8.6 s; at N = 5
# (147 tags) 0.2 s whichever
JOINT_CHUNK = 256
# Relinearisation thresholds by the kind of variable (its key's character: c camera, t tag, s print
# scale, a b m l the axis, base, mount and lift, d the lens's distortion correction, k the
# intrinsics), as iSAM2 takes them.  Every kind at `SlamConfig.relinearize_threshold` but the
# intrinsics, which are in pixels and are in every corner factor of a run: at 0.001 px the focal
# length passed the threshold in most steps and every live corner factor was called back again
# (an N = 8 replay's step 90th percentile 26 -> 94 ms at 0.002 px); 0.05 px changes a corner's
# Jacobians by 5e-5 of themselves.  A kind not listed here would be undefined behaviour in iSAM2's
# map lookup: `_value` refuses it.
INTRINSICS_RELINEARIZE_PX = 0.05
_KEY_DIMS = {"c": 6, "t": 6, "s": 1, "a": 6, "b": 6, "m": 6, "l": 6, "d": 2, "k": 5}
_K_CHR = chr(gtsam.Symbol(INTRINSICS).chr())
# the deployment check's fixed tolerances, widened by the pair's noise where it is measured worse
DEPLOY_LATERAL_MIN_M = 0.010
DEPLOY_ROTATION_MIN_RAD = math.radians(2.0)


@functools.lru_cache(maxsize=None)
def _thresholds(threshold: float) -> gtsam.ISAM2ThresholdMap:
    """iSAM2's relinearisation thresholds: `threshold` for every kind of variable, the intrinsics
    their own (INTRINSICS_RELINEARIZE_PX)."""
    out = gtsam.ISAM2ThresholdMap()
    for kind, dim in _KEY_DIMS.items():
        out.insert((kind, np.full(dim, INTRINSICS_RELINEARIZE_PX if kind == _K_CHR else threshold)))
    return out


def _tag_points(size_m: float) -> np.ndarray:
    """tag_object_points, one array per tag size (read only: the corner factors keep it)."""
    points = tag_object_points(size_m)
    points.flags.writeable = False
    return points


@functools.lru_cache(maxsize=None)
def _gate_k(dof: int, one_sided: bool, alpha: float) -> float:
    from scipy.special import chdtri, ndtri

    return float(-ndtri(alpha)) if one_sided else float(math.sqrt(chdtri(dof, alpha)))


@functools.lru_cache(maxsize=None)
def _robust_k(dof: int) -> float:
    """Huber threshold on a factor's whitened error norm: the 99 % point of its chi distribution.
    GTSAM's robust kernels act on the norm of the whole factor's error, and an 8-D corner error is
    ~2.8 sigma long on average: a 1-D constant (1.345, or twice it) down-weighted about half of all
    good sightings and inflated every marginal (a module's 1-sigma 0.67 mm where the bound is 0.41)."""
    from scipy.special import chdtri

    return float(math.sqrt(chdtri(dof, 0.01)))


@dataclass(frozen=True)
class SlamConfig:
    semantic: bool = True
    camera_sigma_m: float = 0.001            # R: kinematic camera pose, translation (1 sigma)
    camera_sigma_rad: float = math.radians(0.05)
    semantic_sigma_m: float = 0.0005         # S: how well a fully assembled module matches its design
    semantic_sigma_rad: float = math.radians(0.05)
    huber_k: float | None = 1.345           # None: plain Gaussian observation factors (the paper's)
    # Q: None takes each detection's own covariance (the detector's model); a value replaces it
    # with a fixed diagonal (studies: the paper's Q = diag(1 m^2 x3, 0.1 rad^2 x3) is 1 m / 0.316 rad)
    observation_sigma_m: float | None = None
    observation_sigma_rad: float | None = None
    gate_m: float = 0.005                    # a related pair farther than this from its design is not tied
    gate_rad: float = math.radians(1.0)     # widened by the noise where the pair is measured worse
    # The gates and the deployment check widen to the chi-square quantile of their dimension at this
    # false-alarm probability (1e-4: 3.7 sigma along one axis, 4.3 on a 2-D norm, 4.6 on a 3-D norm):
    # a good pair is wrongly left untied -- a good deployable wrongly flagged -- once in 10^4 checks.
    gate_alpha: float = 1e-4
    height_tol_m: float = 0.005              # deployable fully deployed within this of its design lift
    relinearize_threshold: float = 0.001
    min_observations: int = 2                # views of both tags before a relation is decided
    # How a tag sighting enters the graph: "pose" (the detector's IPPE pose with its covariance) or
    # "corners" (the reprojection of its four corners through the calibrated camera, as TagSLAM
    # does: a tag's tilt is then triangulated across views instead of read from one frontal view).
    # "corners" needs the camera (`camera=` K, dist); the IPPE pose still initialises the tag.
    # "corner-info": the IPPE pose with the corners' own information about it (the corner cost to
    # second order, in C++: ~100x faster batch solves; docs/sf_graphslam.md).
    observation: str = "pose"
    # the detector's face-on corner accuracy, grown with obliquity.  A run takes what its rig survey
    # (or calibration file) measured, else the rig's [verification] corner_sigma_px, and measures
    # it again from its own residuals (corner_noise)
    corner_sigma_px: float = 0.02
    # the tags' print scale error (relative, 1 sigma): with the corner model each tag gets a scale
    # variable with this prior, so a tag printed large is not read as a tag nearer the camera
    # (0: tags exactly their nominal size)
    tag_scale_sigma: float = 0.0


@dataclass
class RelationState:
    a: int
    b: int
    kind: str
    decided: bool = False
    tied: bool = False                       # the semantic factor is in the graph
    reason: str = ""                         # why it was not tied
    deploy: DeployCheck | None = None


class SfGraphSlam:
    """The factor graph of one BORG survey campaign (a whole procedure, or one study trial)."""

    def __init__(self, model: BorgModel, config: SlamConfig | None = None, *, rig: RigGeometry | None = None,
                 calibration: RigCalibration | None = None, camera: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.model = model
        self.config = config or SlamConfig()
        if self.config.observation not in OBSERVATIONS:
            raise ValueError(f"observation must be one of {', '.join(OBSERVATIONS)}, got {self.config.observation!r}")
        if self.config.observation != "pose" and camera is None:
            raise ValueError("the corner observation model needs the camera (K, dist)")
        self.camera = camera
        self._cal = cal3_s2(camera[0]) if camera is not None else None
        if self.config.observation != "pose":
            corner_kernel.warm()
        self.rig = rig
        self.calibration = calibration
        # A run reads its corners through the intrinsics its rig survey estimated, and the survey
        # knows them only to its covariance (at N = 6 up to 0.06 % in focal length and 0.4 px in
        # the principal point, which move a tag at the structure's far side by 0.4-0.8 mm).  With the
        # survey's joint prior the intrinsics are a variable of every corner factor: their
        # uncertainty reaches every tag's covariance, and the run's own views refine them.  Held at
        # the survey's estimate, the graph took it as exact and the mount absorbed its error: an
        # N = 6 run's top layer 0.7 mm off at a NEES of 3.6, its mount at a NEES of 3,000
        # (docs/sf_graphslam.md, "The intrinsics").
        self.free_intrinsics = (rig is not None and calibration is not None and calibration.joint_covariance is not None
                                and self.config.observation == "corners" and camera is not None)
        # the intrinsics the corners are undistorted through (fx, fy, s, u0, v0): with them a
        # variable, each corner factor reads its corners as undistorted through the estimate instead
        # (`rig_model.intrinsics_basis_many`)
        self._k_ref = np.asarray(cal3_s2(camera[0]).vector(), float) if camera is not None else None
        c = self.config
        self.camera_noise = gtsam.noiseModel.Diagonal.Sigmas(
            np.array([c.camera_sigma_rad] * 3 + [c.camera_sigma_m] * 3))
        self.semantic_noise = gtsam.noiseModel.Diagonal.Sigmas(
            np.array([c.semantic_sigma_rad] * 3 + [c.semantic_sigma_m] * 3))
        self.fixed_observation_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(
            [c.observation_sigma_rad or 0.0] * 3 + [c.observation_sigma_m or 0.0] * 3))
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(_thresholds(c.relinearize_threshold))
        params.relinearizeSkip = 1
        self.isam = gtsam.ISAM2(params)
        # iSAM2 hands each Python factor its linearisation point as a `const Values &`, which
        # pybind11 copies into a new Python object at every callback -- every variable of the run,
        # each time: ~0.1 us a variable, 0.2 ms a callback at 2,000 -- unless that C++ object already
        # has a Python wrapper, which it then passes instead.  Holding one (a live view of iSAM2's
        # point, which keeps iSAM2 alive) makes every callback read the point in place.
        self._theta = self.isam.getLinearizationPoint()
        self.graph = gtsam.NonlinearFactorGraph()       # everything, for batch solves
        self.initial = gtsam.Values()
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self.n_views = 0
        self.tags: set[int] = set()
        self.observations: dict[int, int] = {}           # tag -> number of views that saw it
        self.relations: dict[tuple[int, int], RelationState] = {
            (r.a, r.b): RelationState(r.a, r.b, r.kind) for r in model.relations}
        self._estimate: gtsam.Values | None = gtsam.Values()   # None: iSAM2's, not yet computed (`estimate`)
        self._batch_solved = False                       # the estimate came from solve_batch, not iSAM2
        self._batch_marginals: gtsam.Marginals | None = None
        # iSAM2 marginal blocks of the current estimate, (key, key) -> block, from one joint
        # marginal over every tag a step reads (`_prefetch`); emptied by every solve
        self._cov_blocks: dict[tuple[int, int], np.ndarray] = {}
        self._tag_estimates: tuple[gtsam.Values, dict[int, Pose3]] | None = None
        self.generation: dict[int, int] = {}             # tag -> how many times it was re-placed
        # tags whose module's verdict is still open: their relations wait, so that the design
        # cannot pull a module whose measurement is still being refined by extra views
        self.held: set[int] = set()
        # what each factor is, so that the bound can rebuild the graph with the true noise
        self.specs: list[tuple] = []
        # a new tag's sightings until the next solve gives it its initial value
        # (camera, detection, its undistorted corners, corner sigma, lens basis)
        self._pending: dict[int, list[tuple]] = {}
        # the corner noise measured from the run's own residuals (corner_noise): each corner factor's
        # graph index and obliquity scale, and the face-on residuals of those evaluated so far
        # (graph index, obliquity scale, camera, tag, scale key, undistorted corners, tag corners, lens basis)
        self._corner_factors: list[tuple] = []
        self._batch = gtsam.NonlinearFactorGraph()      # the batch solve's graph (`_batch_graph`), so far
        self._batch_others = gtsam.NonlinearFactorGraph()   # ... its factors other than the view factors
        # ... and its view factors, evaluated together (`view_batch.ViewBatch`)
        self._view_batch = None if self._cal is None else ViewBatch(self._cal)
        self._batch_upto = self._batch_corners = 0
        self._residuals_done = 0
        self._face_on: list[np.ndarray] = []            # each solve's new face-on residuals (px)
        self._face_on_abs = AbsoluteResiduals()
        self._corner_noise: CornerNoise | None = None
        self._corner_params = 0                          # variables the corners determine (6 per tag and view)
        # turntable tags whose prior is part of the calibration's joint prior (valued from the start)
        self._joint_tags: set[int] = set()
        # the keys a step reads marginals of (its module's tags and their relations' partners),
        # eliminated last by every solve until the module is released (`_last_groups`)
        self._last: list[int] = []
        # each tag's relations (their keys in `relations`), which name its partners too
        self._relations_of: dict[int, list[tuple[int, int]]] = {}
        for key in self.relations:
            for t in key:
                self._relations_of.setdefault(t, []).append(key)
        # the relations undecided with both tags in the graph, kept as tags arrive and relations
        # are decided: the gate reads these twice a step, and a pass over every relation of the
        # structure was 0.1 ms a read at N = 8.  Read in the structure's relation order.
        self._relation_order = {key: i for i, key in enumerate(self.relations)}
        self._open: set[tuple[int, int]] = set()
        # tags summarised out of iSAM2 (`settle`), with the estimate each had then; their keys,
        # and the cameras' and print scales' settled with them
        self.settled: dict[int, Pose3] = {}
        self._settled_keys: set[int] = set()
        # camera key -> the tag keys its sightings tie it to (`settle` settles a camera that saw
        # only settled tags)
        self._camera_tags: dict[int, set[int]] = {}
        if rig is not None:
            if calibration is not None and calibration.joint_covariance is not None:
                self._joint_prior(rig, calibration)
            else:
                means, covs = rig.priors(calibration)
                for key in (AXIS, BASE, MOUNT):
                    f = gtsam.PriorFactorPose3(key, means[key], gtsam.noiseModel.Gaussian.Covariance(covs[key]))
                    self._add(f, ("rig_prior", f, key, means[key]))
                    self._value(key, means[key])
            self.estimate = gtsam.Values(self.initial)

    def _joint_prior(self, rig: RigGeometry, cal: RigCalibration) -> None:
        """The rig survey's whole posterior over the axis, base, mount and turntable tags as one
        Gaussian factor (a LinearContainerFactor: the information matrix about the survey's
        estimate, in each pose's tangent, evaluated in C++).  Per-variable priors would drop the
        correlations, and the turntable tags' common error -- the frame every verdict is read in --
        would count once per tag."""
        means, _ = rig.priors(cal)
        blocks = cal.joint_blocks()
        tags = [int(name) for name, _ in blocks[5:]]
        keys = [AXIS, BASE, MOUNT, INTRINSICS, DISTORTION] + [self.key(t) for t in tags]
        values = ([means[AXIS], means[BASE], means[MOUNT], cal3_s2(cal.K), np.array(cal.distortion_correction, float)]
                  + [cal.turntable_tags[t] for t in tags])
        at = np.cumsum([0] + [size for _, size in blocks])
        cov = np.array(cal.joint_covariance, float)
        # the axis frame's yaw and height are gauge (rig_model.RigGeometry.priors)
        for i in (2, 5):
            cov[i, :] = cov[:, i] = 0.0
            cov[i, i] = GAUGE_SIGMA ** 2
        info = np.linalg.inv(0.5 * (cov + cov.T))
        lin = gtsam.GaussianFactorGraph()
        point = gtsam.Values()
        for i, (key, value) in enumerate(zip(keys, values)):
            point.insert(key, value)
            bi = slice(at[i], at[i + 1])
            lin.add(gtsam.HessianFactor(key, info[bi, bi], np.zeros(at[i + 1] - at[i]), 0.0))
            for j in range(i + 1, len(keys)):
                bj = slice(at[j], at[j + 1])
                lin.add(gtsam.HessianFactor(key, keys[j], np.zeros((at[i + 1] - at[i],) * 2), info[bi, bj],
                                            np.zeros(at[i + 1] - at[i]), np.zeros((at[j + 1] - at[j],) * 2),
                                            np.zeros(at[j + 1] - at[j]), 0.0))
        f = gtsam.LinearContainerFactor(gtsam.HessianFactor(lin), point)
        self._add(f, ("as_is", f))
        for key, value in zip(keys, values):
            self._value(key, value)
        self._joint_tags = set(tags)
        # The intrinsics are a variable of every corner factor (`free_intrinsics`), relinearised on
        # their own threshold (INTRINSICS_RELINEARIZE_PX): at the scalar one the focal length moved
        # past it in most updates and every corner factor was called back again.

    def _turntable_tag_prior(self, tag: int) -> None:
        """The turntable tags fix the structure frame: at their design poses, known to the rig's
        [calibration] turntable_tag_sigma, or where a rig calibration found them."""
        assert self.rig is not None
        cal = self.calibration
        if cal is not None and tag in cal.turntable_tags and tag in cal.turntable_tag_covariance:
            mean = cal.turntable_tags[tag]
            noise = gtsam.noiseModel.Gaussian.Covariance(cal.turntable_tag_covariance[tag])
        else:
            mean = self.model.tags[tag].structure_T_tag
            noise = tag_prior_noise(self.rig.config.turntable_tag_sigma_m, self.model.tags[tag].size_m)
        self._add(gtsam.PriorFactorPose3(self.key(tag), mean, noise), ("turntable_tag", self.key(tag), mean, noise,
                                                                        self.model.tags[tag].size_m))

    def predicted_camera(self, motion: ViewMotion) -> Pose3:
        """structure_T_camera for a view from the current calibration estimate."""
        assert self.rig is not None
        lift = self._pose(LIFT) if self._exists(LIFT) else self.rig.lift_prior()[0]
        return self.rig.predict(motion, *(self._pose(k) for k in (AXIS, BASE, MOUNT)), lift)

    def _lift_prior(self) -> None:
        """The lift's axis joins the graph with the first view taken off the lift's zero: a run
        that never moves the lift keeps the graph it had before there was one."""
        assert self.rig is not None
        if self.initial.exists(LIFT):
            return
        mean, cov = self.rig.lift_prior()
        f = gtsam.PriorFactorPose3(LIFT, mean, gtsam.noiseModel.Gaussian.Covariance(cov))
        self._add(f, ("rig_prior", f, LIFT, mean))
        self._value(LIFT, mean)

    def key(self, tag: int) -> int:
        return _T(tag + GENERATION * self.generation.get(tag, 0))

    def _distortion_key(self) -> bool:
        """The lens's radial distortion error: from the survey's joint prior, else a prior of the
        rig's [calibration] distortion_sigma_px at the frame's corners (first corner factor)."""
        assert self.rig is not None and self.camera is not None
        if not self.initial.exists(DISTORTION):
            f = gtsam.PriorFactorVector(DISTORTION, np.zeros(2), gtsam.noiseModel.Diagonal.Sigmas(
                distortion_prior_sigmas(self.rig.config.distortion_sigma_px, self.camera[0])))
            self._add(f, ("as_is", f))
            self._value(DISTORTION, np.zeros(2))
        return True

    def _scale_key(self, tag: int) -> int:
        """The tag's print scale variable (one per printed tag, so a re-placed module keeps it),
        with its prior the first time the tag is seen."""
        key = _S(tag)
        if not self.initial.exists(key):
            f = gtsam.PriorFactorVector(key, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, self.config.tag_scale_sigma))
            self._add(f, ("as_is", f))
            self._value(key, np.zeros(1))
        return key

    def replace_tags(self, tags: Iterable[int]) -> None:
        """The module carrying these tags was re-placed or re-deployed: what was seen of it before
        no longer describes it.  Its tags become new variables (the old ones keep their old
        observations, tied to nothing new) and their relations are decided afresh."""
        for t in tags:
            self.generation[t] = self.generation.get(t, 0) + 1
            self.tags.discard(t)
            self.settled.pop(t, None)
            self._tag_estimates = None
            self.observations.pop(t, None)
        for rel in self.relations.values():
            if rel.a in tags or rel.b in tags:
                rel.decided = rel.tied = False
                rel.reason = ""
                rel.deploy = None
        self._open = {key for key, rel in self.relations.items() if not rel.decided and self._both_live(key)}

    def _both_live(self, pair: tuple[int, int]) -> bool:
        """Both tags of a relation are in the graph and neither is settled: a relation to a settled
        tag is never decided (its partner's variable is no longer in the solver)."""
        return all(t in self.tags and t not in self.settled for t in pair)

    # ---- building the graph -------------------------------------------------------------------
    def add_view(self, structure_T_camera: Pose3 | None, detections: Sequence[Detection],
                 motion: ViewMotion | None = None) -> int:
        """A survey view: the camera pose from the kinematics (or, with a rig model, the commanded
        motion, through the calibration) and what the detector saw."""
        k = self.n_views
        self.n_views += 1
        self._tag_estimates = None
        if self.rig is not None:
            if motion is None:
                raise ValueError("a graph with a rig model needs each view's commanded motion")
            if motion.lift_m:
                self._lift_prior()
            structure_T_camera = self.predicted_camera(motion)
            self._add(chain_factor(self.rig, motion, C(k)), ("chain", motion, C(k)))
        else:
            assert structure_T_camera is not None
            f = gtsam.PriorFactorPose3(C(k), structure_T_camera, self.camera_noise)
            self._add(f, ("as_is", f))
        self._value(C(k), structure_T_camera)
        self._corner_params += 6
        c = self.config
        # a settled tag's sightings are not added: its variable is no longer in the solver
        detections = [d for d in detections if d.tag_id in self.model.tags and d.tag_id not in self.settled]
        if self.camera is not None and detections:
            # the view's corners undistorted, their obliquity and their lens basis in one pass each
            # (the same numbers as one tag at a time: undistort_px, undistorted_side_ratio, radial_basis)
            K = self.camera[0]
            raw = np.concatenate([np.asarray(d.corners_px, float).reshape(4, 2) for d in detections])
            undistorted = undistort_px(raw, *self.camera).reshape(-1, 4, 2)
            edges = np.roll(undistorted, -1, axis=1) - undistorted
            sides = np.sqrt(np.einsum("nij,nij->ni", edges, edges))
            top = sides.max(axis=1)
            ratios = np.where(top > 0, sides.min(axis=1) / np.where(top > 0, top, 1.0), 0.0)
            bases = radial_basis_many(undistorted, K) if c.observation == "corners" and self.rig is not None else None
            # the intrinsics a variable: the corners move with them (`intrinsics_basis_many`)
            k_bases = (intrinsics_basis_many(raw, *self.camera)
                       if c.observation == "corners" and self.free_intrinsics else None)
        ck = C(k)
        corners = c.observation == "corners"
        scales = corners and c.tag_scale_sigma > 0
        robust_k = _robust_k(8) if c.huber_k else None
        lensed: bool | None = None               # the lens variable, looked up (and made) at the first sighting
        for i, d in enumerate(detections):
            scale = 1.0
            u = None
            if self.camera is not None:
                u = undistorted[i]
                # an oblique sighting's corners are worse (rig_model.side_ratio); too flat, none
                ratio = float(ratios[i])
                if ratio < MIN_SIDE_RATIO:
                    continue
                scale = ratio ** -OBLIQUE_EXPONENT
            tk = self.key(d.tag_id)
            self._camera_tags.setdefault(ck, set()).add(tk)
            sk = self._scale_key(d.tag_id) if scales else None
            lens = None
            if corners:
                assert self.camera is not None and u is not None
                if lensed is None:
                    lensed = self.rig is not None and self._distortion_key()
                if lensed:
                    lens = (DISTORTION, bases[i])
            spec = ("corners", ck, tk, d.size_m, scale, sk, lens)
            if corners:
                local = _tag_points(d.size_m)
                k_basis = None if k_bases is None else (k_bases[i], self._k_ref)
                self._add(corner_factor(ck, tk, u, local, c.corner_sigma_px * scale, robust_k=robust_k,
                                        fixed=None if self.free_intrinsics else self._cal, scale_key=sk,
                                        distortion=lens, intrinsics_basis=k_basis), spec)
                # what the factor is built from, kept: the residual pass reads it, and the batch
                # solve builds one factor a view from it (`_batch_graph`)
                self._corner_factors.append((self.graph.size() - 1, scale, ck, tk, sk, u, local,
                                             None if lens is None else lens[1], c.corner_sigma_px * scale, robust_k,
                                             None if k_bases is None else k_bases[i]))
            else:
                if c.observation == "corner-info":
                    gauss = self._corner_information(d, c.corner_sigma_px * scale)
                elif c.observation_sigma_m is not None or c.observation_sigma_rad is not None:
                    gauss = self.fixed_observation_noise
                else:
                    gauss = gtsam.noiseModel.Gaussian.Covariance(0.5 * (d.covariance + d.covariance.T))
                # the pose model keeps the paper's Huber constant; the corner information model
                # takes the threshold of its 6-D whitened error (below)
                hk = _robust_k(6) if c.observation == "corner-info" else c.huber_k
                noise = (gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(hk), gauss)
                         if c.huber_k else gauss)
                self._add(gtsam.BetweenFactorPose3(C(k), self.key(d.tag_id), d.camera_T_tag, noise), spec)
            if d.tag_id not in self.tags:
                self._corner_params += 6
                self.tags.add(d.tag_id)
                for key in self._relations_of.get(d.tag_id, ()):
                    if not self.relations[key].decided and self._both_live(key):
                        self._open.add(key)
                self._pending[self.key(d.tag_id)] = []
                if d.tag_id in self._joint_tags:
                    self._pending.pop(self.key(d.tag_id))      # valued with the joint prior
                elif self.rig is not None and self.model.tags[d.tag_id].module == "turntable":
                    self._turntable_tag_prior(d.tag_id)
            if self.key(d.tag_id) in self._pending:
                self._pending[self.key(d.tag_id)].append((structure_T_camera, d, u, c.corner_sigma_px * scale,
                                                          None if lens is None else lens[1]))
            self.observations[d.tag_id] = self.observations.get(d.tag_id, 0) + 1
        return k

    def _corner_information(self, d: Detection, sigma_px: float) -> gtsam.noiseModel.Base:
        """The corner model folded into the single-view pose: the information J^T J / sigma^2 of the
        four corners' reprojection about camera_T_tag (J at the detector's pose, which minimises
        that view's reprojection error), so the pose factor's cost is the corner cost to second
        order, and a frontal tag's weak tilt stays weak.  A C++ BetweenFactorPose3: batch solves
        without a Python call per factor."""
        from estimation.precision import corner_jacobians

        assert self.camera is not None
        jac = corner_jacobians(Pose3(), d.camera_T_tag, self.camera[0], tag_object_points(d.size_m))
        if jac is None:
            return gtsam.noiseModel.Gaussian.Covariance(0.5 * (d.covariance + d.covariance.T))
        J = jac[0]
        return gtsam.noiseModel.Gaussian.Information(J.T @ J / sigma_px ** 2)

    def _initialise_pending(self) -> None:
        """Each new tag starts where the best of its sightings puts it: every sighting's IPPE pose
        is a candidate, scored by the reprojection error of the tag's corners in all its sightings
        so far.  One sighting's IPPE may have taken the wrong side of the planar ambiguity (a
        frontal tag's two solutions differ by a tilt of a few degrees, and noise can favour the
        wrong one); the other views settle it, and the corner model, which is not convex in the
        tilt, starts on the right side."""
        for key, sightings in self._pending.items():
            best = sightings[0][0].compose(sightings[0][1].camera_T_tag)
            if self.camera is not None and len(sightings) > 1:
                K, dist = self.camera
                candidates = [s[0].compose(s[1].camera_T_tag) for s in sightings]
                # every candidate against every sighting at once: (candidate, sighting, corner)
                camera_T_structure = np.array([s[0].inverse().matrix() for s in sightings])
                structure_T_tag = np.array([p.matrix() for p in candidates])
                camera_T_tag = np.einsum("sij,cjk->csik", camera_T_structure, structure_T_tag)
                local = np.array([_tag_points(s[1].size_m) for s in sightings])                # (s, 4, 3)
                uv = np.array([s[2] for s in sightings])                                        # (s, 4, 2)
                pts = np.einsum("csij,snj->csni", camera_T_tag[..., :3, :3], local) + camera_T_tag[..., None, :3, 3]
                z = pts[..., 2:3]
                behind = np.any(z[..., 0] <= 0, axis=(1, 2))
                proj = np.einsum("ij,csnj->csni", K, pts / np.where(z > 0, z, 1.0))[..., :2]
                cost = np.sum((proj - uv) ** 2, axis=(1, 2, 3))
                cost[behind] = math.inf
                best = candidates[int(np.argmin(cost))]
            if self.config.observation == "corners" and self.camera is not None and len({s[1].size_m for s in sightings}) == 1:
                best = self._refined(key, best, sightings)
            self._value(key, best)
        self._pending = {}

    def _refined(self, key: int, start: Pose3, sightings: list[tuple]) -> Pose3:
        """A new tag's start refined against its corners in the step's views (cameras where the
        rig puts them, its print scale and the lens correction at their current values): iSAM2
        then linearises its factors near the solution once, instead of at the IPPE pose and again
        in the pass after the first solve (`rig_model.refine_tag_pose`).  Refined until a step is
        below the relinearisation threshold: Gauss-Newton gains about two digits a step here, so
        what is left is far inside it (two steps from an IPPE pose)."""
        assert self._cal is not None
        tag = key - _T(0)
        scale_key = _S(tag % GENERATION)
        scale, scale_sigma = 0.0, 0.0
        if self._exists(scale_key):
            scale = float(self._vector(scale_key)[0])         # a re-placed tag's print: as measured
        elif self._new_values.exists(scale_key):
            scale_sigma = self.config.tag_scale_sigma                    # new: refined under its prior
        lens = None
        if all(s[4] is not None for s in sightings):
            d = self._vector(DISTORTION) if self._exists(DISTORTION) else self._new_values.atVector(DISTORTION)
            lens = (np.array([s[4] for s in sightings]), d)
        k = self._intrinsics()
        cal = np.array([k.fx(), k.fy(), k.skew(), k.px(), k.py()])
        pose, scale = refine_tag_pose(start, [s[0] for s in sightings], np.array([s[2] for s in sightings]),
                                      _tag_points(sightings[0][1].size_m), cal, np.array([s[3] for s in sightings]),
                                      scale, lens, scale_sigma, tolerance=self.config.relinearize_threshold)
        if scale_sigma > 0:
            self._new_values.update(scale_key, np.array([scale]))
            self.initial.update(scale_key, np.array([scale]))
        return pose

    def _intrinsics(self) -> gtsam.Cal3_S2:
        """The intrinsics the corners are read through now: the graph's estimate where they are a
        variable (`free_intrinsics`), else the camera's."""
        assert self._cal is not None
        if not self.free_intrinsics:
            return self._cal
        if self._estimate is not None and self._estimate.exists(INTRINSICS):
            return self._estimate.atCal3_S2(INTRINSICS)
        if self.isam.valueExists(INTRINSICS):
            return self.isam.calculateEstimateCal3_S2(INTRINSICS)
        return self.initial.atCal3_S2(INTRINSICS)

    def _add(self, factor, spec: tuple) -> None:
        self._new_factors.add(factor)
        self.graph.add(factor)
        self.specs.append(spec)

    def _value(self, key: int, value: Pose3 | gtsam.Cal3_S2 | np.ndarray) -> None:
        if chr(gtsam.Symbol(key).chr()) not in _KEY_DIMS:
            raise ValueError(f"variable {gtsam.Symbol(key)} is of a kind with no relinearisation threshold (_KEY_DIMS)")
        self._new_values.insert(key, value)
        self.initial.insert(key, value)

    def update(self, snapshot: Iterable[int] = (), hold: bool = False) -> dict[int, tuple[Pose3, np.ndarray | None]]:
        """Incremental solve (iSAM2) with what was added since the last update; then decide the
        semantic relations that became decidable, and solve again with the factors that passed.

        Returns the estimates (pose, marginal covariance) of the `snapshot` tags as they were
        *before* this update's semantic factors joined: verification reads those, so a module's own
        design relations can never pull its measured deviation back to the design.  With `hold`,
        the snapshot tags' relations wait until `release` (more views may still come for them)."""
        snapshot = list(snapshot)
        if hold:
            self.held.update(snapshot)
        partners = sorted({p for t in snapshot for key in self._relations_of.get(t, ()) for p in key}
                          - set(snapshot) - self.settled.keys())
        self._last = [self.key(t) for t in snapshot + partners]
        self._isam_step()
        self._prefetch([t for t in snapshot if self.has_tag(t)]
                       + ([t for rel in self._decidable() if self._reads_covariance(rel) for t in (rel.a, rel.b)]
                          if self.config.semantic else []))
        snap = {t: (self.tag_pose(t), self._marginal(t)) for t in snapshot if self.has_tag(t)}
        if self.config.semantic and self._decide_relations():
            self._isam_step()
        return snap

    def release(self, tags: Iterable[int]) -> None:
        """The held tags' module is decided: their relations may now be tied."""
        self.held.difference_update(tags)
        if self.config.semantic:
            self._prefetch([t for rel in self._decidable() if self._reads_covariance(rel) for t in (rel.a, rel.b)],
                           to_root=True)
        if self.config.semantic and self._decide_relations():
            self._isam_step()
        self._last = []

    # ---- settling what is built ---------------------------------------------------------------
    def settle(self, tags: Iterable[int]) -> int:
        """Summarise `tags` out of the incremental solver: tags of modules whose verdicts are
        final, well below the part of the structure still being measured.  Their variables, their
        print scales and every camera that saw only settled tags are marginalised out of iSAM2;
        what they told the rest of the graph is kept only as it bears on the rig's variables and
        the turntable tags (the frame every later view is placed in).

        Exact marginalisation alone leaves a dense factor over every live tag and camera the
        settled ones shared a view or a relation with: the large cliques that made a long run's
        step grow (docs/benchmarks.md, "What the Bayes tree holds").  That factor is
        Schur-complemented onto the rig and the turntable tags, which drops the live tags' ties to
        the settled ones: information is dropped, never made up, so at the same linearisation no
        covariance comes out smaller than the full graph's.  (A replayed run's 1-sigma is the full
        graph's within -4 % and +3 %: the held linearisation point below, the corner noise measured
        from the residuals of fewer sightings, and a view's nearest tags chosen among the live ones
        move it both ways.)  A settled tag
        keeps the estimate it had (`tag_pose`, `tag_estimates`); a later sighting of it is not
        added.  The variables the summary touches keep their linearisation point from then on
        (iSAM2's rule for marginal factors).  Returns how many tags were settled.
        (docs/sf_graphslam.md, "Settling what is built")"""
        if self._batch_solved:
            raise RuntimeError("settle works on the incremental solver's graph, not after a batch solve")
        isam = self.isam
        theta = isam.getLinearizationPoint()
        new = [t for t in dict.fromkeys(tags) if t in self.tags and t not in self.settled and t not in self.held
               and self.model.tags[t].module != "turntable" and self.has_tag(t)]
        if not new:
            return 0
        if self._new_factors.size() or self._new_values.size() or self._pending:
            raise RuntimeError("settle between solves: views are waiting for an update")
        keys: set[int] = set()
        for t in new:
            self.settled[t] = self.tag_pose(t)
            for g in range(self.generation.get(t, 0) + 1):
                key = _T(t + GENERATION * g)
                if theta.exists(key) and key not in self._settled_keys:
                    keys.add(key)
            if theta.exists(_S(t)):
                keys.add(_S(t))
        gone = self._settled_keys | keys
        for ck, seen in self._camera_tags.items():
            if ck not in gone and seen <= gone and theta.exists(ck):
                keys.add(ck)
        # the settled variables first in the elimination order, so that they are the tree's leaves
        # (iSAM2 marginalises only leaves); nothing relinearised
        groups, every, hold = gtsam.KeyGroupMap(), gtsam.KeyList(), gtsam.KeyList()
        for key in theta.keys():
            groups.insert2(key, 0 if key in keys else 1)
            every.push_back(key)
            hold.push_back(key)
        isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], constrainedKeys=groups, noRelinKeys=hold,
                    extraReelimKeys=every)
        first = isam.getFactorsUnsafe().size()
        leaves = gtsam.KeyList()
        for key in sorted(keys):
            leaves.push_back(key)
        isam.marginalizeLeaves(leaves)
        self._summarise_onto_frame(first)
        self._settled_keys |= keys
        for ck in [ck for ck in self._camera_tags if ck in keys]:
            del self._camera_tags[ck]
        self._open = {key for key in self._open if self._both_live(key)}
        self._estimate = None
        self._tag_estimates = None
        self._cov_blocks = {}
        return len(new)

    def _summarise_onto_frame(self, first: int) -> None:
        """Replace the marginal factors iSAM2's `marginalizeLeaves` added (indices from `first`)
        by their Schur complement onto the rig's variables and the turntable tags (`settle`).
        Eliminated by Cholesky, else by QR (3-6x slower on a large summary): a live camera that saw
        one settled tag keeps only 2 of its 6 directions in the marginal (the tag's pose absorbs the
        rest), a singular block Cholesky refuses."""
        isam = self.isam
        factors = isam.getFactorsUnsafe()
        added = [i for i in range(first, factors.size()) if factors.exists(i)]
        if not added:
            return
        point = isam.getLinearizationPoint()
        linear = gtsam.GaussianFactorGraph()
        involved: set[int] = set()
        for i in added:
            f = factors.at(i).linearize(point)
            linear.push_back(f)
            involved.update(f.keys())
        frame = {AXIS, BASE, MOUNT, INTRINSICS, DISTORTION, LIFT}
        frame.update(self.key(t) for t in self.tags if self.model.tags[t].module == "turntable")
        others = gtsam.Ordering()
        for key in sorted(involved - frame):
            others.push_back(key)
        if others.size() == 0:
            return                      # the summary is on the frame already
        summary = gtsam.NonlinearFactorGraph()
        if involved & frame:
            try:
                _, rest = linear.eliminatePartialMultifrontal(others)
            except RuntimeError:
                _, rest = linear.eliminatePartialMultifrontal(others, gtsam.EliminateQR)
            summary.add(gtsam.LinearContainerFactor(gtsam.HessianFactor(rest), point))
        isam.update(summary, gtsam.Values(), added, noRelinKeys=self._linear_keys())

    # ---- the bound ---------------------------------------------------------------------------
    def bound_graph(self, corner_sigma_px: float, upto: int | None = None, chain_noise=None,
                    rig_prior_sigma: float | None = None,
                    turntable_tag_sigma_m: float | None = None) -> gtsam.NonlinearFactorGraph:
        """The graph's first `upto` factors rebuilt with the true noise and no robust kernel:
        every tag sighting as its four corners (whichever observation model the estimate used: the
        bound is of the measurements, not of the model) with `corner_sigma_px` face-on, grown for
        obliquity as the graph's own, `chain_noise(motion)` for the rig chain
        (default the graph's own), the rig priors at `rig_prior_sigma` (m and rad: how wrong their
        means truly are; default the graph's own), the turntable tags' at `turntable_tag_sigma_m`,
        semantic factors as they are.  Linearised at the true values
        (`precision.bound_covariances`) it gives the Cramér–Rao bound."""
        if self.camera is None:
            raise ValueError("the bound needs the camera (K, dist)")
        g = gtsam.NonlinearFactorGraph()
        for spec in self.specs[:upto]:
            f = self.bound_factor(spec, corner_sigma_px, chain_noise, rig_prior_sigma, turntable_tag_sigma_m)
            if f is not None:
                g.add(f)
        return g

    def bound_factor(self, spec: tuple, corner_sigma_px: float, chain_noise=None, rig_prior_sigma: float | None = None,
                     turntable_tag_sigma_m: float | None = None) -> gtsam.NonlinearFactor | None:
        """One factor of `bound_graph`, from its spec (None: a kind the bound leaves out)."""
        kind = spec[0]
        if kind == "as_is":
            return spec[1]
        if kind == "rig_prior":
            _, f, key, mean = spec
            if rig_prior_sigma is None:
                return f
            return gtsam.PriorFactorPose3(key, mean, gtsam.noiseModel.Isotropic.Sigma(6, rig_prior_sigma))
        if kind == "turntable_tag":
            _, key, mean, noise, size = spec
            if turntable_tag_sigma_m is not None:
                noise = tag_prior_noise(turntable_tag_sigma_m, size)
            return gtsam.PriorFactorPose3(key, mean, noise)
        if kind == "chain":
            assert self.rig is not None
            return chain_factor(self.rig, spec[1], spec[2], chain_noise(spec[1]) if chain_noise else None)
        if kind == "corners":
            _, ck, tk, size, scale, sk, lens = spec
            # the measurement is irrelevant to the covariance; only the Jacobians at the truth count
            # (the lens's basis, read at the corners as measured, moves by < 1 px at the truth)
            return corner_factor(ck, tk, np.zeros((4, 2)), tag_object_points(size), corner_sigma_px * scale,
                                 robust_k=None, fixed=None if self.free_intrinsics else self._cal, scale_key=sk,
                                 distortion=lens)
        return None

    def _marginal(self, tag: int) -> np.ndarray | None:
        try:
            return self.tag_covariance(tag)
        except (RuntimeError, IndexError):
            return None

    def _linear_keys(self) -> gtsam.KeyList:
        """Variables every factor of the run graph is linear in: the lens's distortion correction
        (the corner factors subtract basis · d, a constant Jacobian), and the intrinsics where they
        are only in the survey's joint prior (a linear factor; not `free_intrinsics`).
        Relinearising them changes no Jacobian, only the right-hand side that iSAM2's delta
        already carries, so holding their linearisation point gives the same estimate and
        marginals to round-off -- and spares the update the re-elimination, from their cliques to
        the root, that each of their relinearisations cost.  Intrinsics in the corner factors are
        not linear there: held, the factors' residuals at the held point drifted from the
        estimate, their robust kernel read that as outliers, and the module's 1-sigma came out
        3-10x too wide."""
        keys = gtsam.KeyList()
        if self.rig is not None:
            for key in ((DISTORTION,) if self.free_intrinsics else (INTRINSICS, DISTORTION)):
                if self.initial.exists(key):
                    keys.push_back(key)
        return keys

    def _moved_past_threshold(self, held: gtsam.KeyList) -> bool:
        """Whether iSAM2's next update would relinearise anything: a variable, other than the
        `held` ones, whose linear delta reaches the relinearisation threshold in any component
        (ISAM2's own test: the intrinsics on their own threshold, everything else on the scalar
        one).  Counted on the whole delta vector, less
        the held variables' components: the same answer as zeroing the held ones in a copy of the
        delta and taking the maximum (what this did), without copying a VectorValues of every
        variable of the run (0.3-0.4 ms a step, growing with the run)."""
        delta = self.isam.getDelta()
        threshold = self.config.relinearize_threshold
        held = set(held)
        # the intrinsics are judged on their own threshold (INTRINSICS_RELINEARIZE_PX)
        own = INTRINSICS not in held and delta.exists(INTRINSICS)
        if own and bool(np.any(np.abs(delta.at(INTRINSICS)) >= INTRINSICS_RELINEARIZE_PX)):
            return True
        over = int(np.count_nonzero(np.abs(delta.vector()) >= threshold))
        if over == 0:
            return False
        held_over = sum(int(np.count_nonzero(np.abs(delta.at(key)) >= threshold))
                        for key in held | ({INTRINSICS} if own else set()) if delta.exists(key))
        return over > held_over

    def _last_groups(self, observed: bool) -> gtsam.KeyGroupMap | None:
        """iSAM2's ordering constraint for a solve while a module is measured: its tags and their
        relations' partners (`_last`) after everything else the new factors touch (`observed`:
        iSAM2's own default puts those last), so that they end in the Bayes tree's root clique.
        A marginal is the clique's joint marginalised to the key: for a root variable that is the
        root's conditional alone; for any other, the separator marginals of every clique on the
        way to the root, each a dense elimination as wide as the clique and its separator.  In
        a large structure the round's tags, cameras and the rig fill a root of hundreds of
        dimensions, and the verdict's marginal of a tag just below it cost up to 19 s at N = 9
        (and the release's joint marginal of a pair up to 40 s).  Ordering changes no estimate and
        no marginal but for round-off (tests/test_slam_step_exact.py)."""
        if not self._last:
            return None
        groups = gtsam.KeyGroupMap()
        last = set(self._last)
        if observed:
            for key in self._new_factors.keyVector():
                if key not in last:
                    groups.insert2(key, 1)
        for key in last:
            if self.initial.exists(key):
                groups.insert2(key, 2 if observed else 1)
        return groups

    def _isam_step(self) -> None:
        self._initialise_pending()
        new_variables = self._new_values.size() > 0
        linear = self._linear_keys()
        self.isam.update(self._new_factors, self._new_values, [], constrainedKeys=self._last_groups(True),
                         noRelinKeys=linear)
        if new_variables:
            # one more relinearisation pass: a tag starts from a single IPPE sighting, a degree or
            # so off in tilt, and the first update linearises its factors there.  Without the pass
            # the estimate moves but the Bayes tree -- and every marginal the verdict reads -- stays
            # at the start: a module's 1-sigma came out 0.59 mm where the bound at the truth is
            # 0.41.  Semantic factors alone start no variable far off: no pass (it was ~2 ms).
            # From a refined start (`_refined`) the first solve seldom moves anything past the
            # threshold; then the pass would relinearise nothing and leave the tree as it is, and
            # is not run (it cost ~0.3 ms doing so).
            if self._moved_past_threshold(linear):
                self.isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [],
                                 constrainedKeys=self._last_groups(False), noRelinKeys=linear)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._estimate = None
        self._batch_solved = False
        self._batch_marginals = None
        self._cov_blocks = {}
        self._collect_residuals()

    # ---- the corner noise, measured -----------------------------------------------------------
    def _collect_residuals(self) -> None:
        """The face-on reprojection residuals of the corner factors added since the last solve, at
        the estimate that first includes them (each factor once: O(new factors) per step).  The
        corner factors' own error (`rig_model._corner_error`), evaluated for the step's
        factors in one array pass instead of one Python callback each."""
        todo = self._corner_factors[self._residuals_done:]
        if not todo:
            return
        self._residuals_done = len(self._corner_factors)
        # a step's factors share their cameras and tags (a view's camera in each of its sightings):
        # each key's existence, pose and scale read once, not once a factor (~10 us a read from iSAM2)
        exists = {key: self._exists(key) for key in {k for f in todo for k in (f[2], f[3], f[4], DISTORTION)} - {None}}
        todo = [f for f in todo if exists[f[2]] and exists[f[3]] and (f[4] is None or exists[f[4]])
                and (f[7] is None or exists[DISTORTION])]
        if todo:
            assert self._cal is not None
            pose = {key: self._pose(key) for key in {k for f in todo for k in (f[2], f[3])}}
            scale = {key: 1.0 + float(self._vector(key)[0]) for key in {f[4] for f in todo} - {None}}
            m = np.array([pose[f[2]].between(pose[f[3]]).matrix() for f in todo])                   # (n, 4, 4)
            k = np.array([1.0 if f[4] is None else scale[f[4]] for f in todo])
            local = np.array([f[6] for f in todo]) * k[:, None, None]                              # (n, 4, 3)
            q = local @ np.swapaxes(m[:, :3, :3], 1, 2) + m[:, None, :3, 3]
            z = q[..., 2]
            behind = z <= 0
            iz = 1.0 / np.where(behind, 1.0, z)
            x, y = q[..., 0] * iz, q[..., 1] * iz
            cal = self._intrinsics()
            meas = np.array([f[5] for f in todo])                                                   # (n, 4, 2)
            e = np.empty((len(todo), 4, 2))
            e[..., 0] = cal.fx() * x + cal.skew() * y + cal.px() - meas[..., 0]
            e[..., 1] = cal.fy() * y + cal.py() - meas[..., 1]
            e[behind] = 1e3
            e = e.reshape(len(todo), 8)
            lensed = [i for i, f in enumerate(todo) if f[7] is not None]
            if lensed:
                e[lensed] -= np.array([todo[i][7] for i in lensed]) @ self._vector(DISTORTION)
            moved = [i for i, f in enumerate(todo) if f[10] is not None]
            if moved:
                e[moved] -= np.array([todo[i][10] for i in moved]) @ (np.asarray(cal.vector(), float) - self._k_ref)
            scales = np.array([f[1] for f in todo])
            face_on = (e / scales[:, None]).ravel()
            self._face_on.append(face_on)
            self._face_on_abs.add(face_on)
        if self._face_on:
            self._corner_noise = self._face_on_abs.corner_noise(self._corner_params, self.config.corner_sigma_px)

    def face_on_residuals(self) -> np.ndarray:
        """Every corner factor's residual components (px, face-on) at the estimate that first
        included it: what the measured corner noise is the scatter of."""
        return np.concatenate(self._face_on) if self._face_on else np.zeros(0)

    def corner_noise(self) -> CornerNoise | None:
        """The corner sigma the run's residuals imply (corner model only; None before any)."""
        return self._corner_noise

    def solve_batch(self, max_iterations: int = 100, warm_start: bool = False) -> gtsam.Values:
        """Levenberg–Marquardt over the whole graph from the initial values (studies), or from the
        last estimate with `warm_start` (every variable must have one)."""
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        # A relative error change of 1e-6 is converged for these problems (the RMSEs of the studies
        # agree with 1e-10 to three figures); the Huber kernel makes the last digits cost ~2x time.
        params.setRelativeErrorTol(1e-6)
        params.setAbsoluteErrorTol(1e-9)
        self._initialise_pending()
        start = self.estimate if warm_start else self.initial
        graph = self._batch_graph()
        if not self._view_factors():
            # the chain and corner factors are the graph's only Python factors
            python_factors = self.rig is not None or self.config.observation == "corners"
            self.estimate, _ = levenberg_marquardt.optimize(graph, start, params, python_factors=python_factors)
        else:
            batch = self._view_batch
            assert batch is not None
            batch.track(start)
            try:
                self.estimate, _ = levenberg_marquardt.optimize(graph, start, params,
                                                                BatchCost(graph, self._batch_others, batch))
            finally:
                batch.release()
        # marginals must now come from this estimate (iSAM2 has not seen these factors)
        self._batch_solved = True
        self._batch_marginals = None
        return self.estimate

    def _view_factors(self) -> bool:
        """Whether the batch takes the corner factors a view at a time (`_batch_graph`): the corner
        model with the intrinsics fixed (the view factors hold them constant)."""
        return self._cal is not None and self.config.observation == "corners" and not self.free_intrinsics

    def _batch_graph(self) -> gtsam.NonlinearFactorGraph:
        """The graph the batch solve takes: the run's graph with each view's corner factors
        gathered into view factors of up to `view_batch.TAGS_PER_FACTOR` tags
        (`rig_model.corner_view_factor`: the same error and whitened Jacobians, so the same solve
        to round-off), evaluated together (`view_batch.ViewBatch`).  Levenberg-Marquardt calls
        every Python factor back at each linearisation; one callback for several tags instead of
        one a tag, and the views' arithmetic in one compiled call, more than halve the 3x3x3
        survey's batch solve (docs/benchmarks.md, "Speed").  iSAM2 keeps the single factors (see
        the factor's note).  Kept between solves and extended by what was added since: a view's
        factors all come in its `add_view`, and the graph only grows."""
        if not self._view_factors():
            return self.graph
        corner = {f[0]: f for f in self._corner_factors[self._batch_corners:]}
        views: dict[tuple[int, bool, float | None], list[CornerSighting]] = {}
        for i in range(self._batch_upto, self.graph.size()):
            f = corner.get(i)
            if f is None:
                other = self.graph.at(i)
                self._batch.add(other)
                self._batch_others.add(other)
                continue
            _, _, ck, tk, sk, u, local, basis, sigma, robust_k, _ = f
            views.setdefault((ck, basis is not None, robust_k), []).append(CornerSighting(tk, sk, u, local, sigma, basis))
        assert self._view_batch is not None
        for (ck, lensed, robust_k), sightings in views.items():
            for a in range(0, len(sightings), TAGS_PER_FACTOR):
                self._batch.add(self._view_batch.add(ck, sightings[a:a + TAGS_PER_FACTOR], robust_k,
                                                     DISTORTION if lensed else None))
        self._batch_upto = self.graph.size()
        self._batch_corners = len(self._corner_factors)
        return self._batch

    def decide_relations_batch(self) -> int:
        """Batch counterpart of `update` for studies: solve, gate the relations, solve again."""
        self.solve_batch()
        added = self._decide_relations() if self.config.semantic else 0
        if added:
            # the semantic factors only sharpen the first solution: start there, not from scratch
            self.solve_batch(warm_start=True)
        return added

    # ---- the semantic gate -------------------------------------------------------------------
    def _decidable(self) -> list[RelationState]:
        """The relations `_decide_relations` reads now: undecided, both tags seen in enough views
        (a held deployable's deployment is read every round too; other held pairs wait)."""
        out = []
        for key in sorted(self._open, key=self._relation_order.__getitem__):
            rel = self.relations[key]
            if min(self.observations.get(rel.a, 0), self.observations.get(rel.b, 0)) < self.config.min_observations:
                continue
            if {rel.a, rel.b} & self.held and rel.kind != "deployable":
                continue
            out.append(rel)
        return out

    def _decide_relations(self) -> int:
        added = 0
        c = self.config
        for rel in self._decidable():
            if {rel.a, rel.b} & self.held:
                # the module's verdict is still open: whether it is deployed is part of the
                # measurement (read now, again with every round); the design waits
                if rel.kind == "deployable":
                    rel.deploy = self._deploy_check(rel)
                continue
            rel.decided = True
            self._open.discard((rel.a, rel.b))
            design = self.model.design_between(rel.a, rel.b)
            if rel.kind == "deployable":
                rel.deploy = self._deploy_check(rel)
                if not rel.deploy.deployed:
                    rel.reason = rel.deploy.reason
                    continue
            dt, dr = self._from_design(rel)
            # tie only what the measurements already agree with: within the gate, widened to the
            # noise's false-alarm quantile where the pair is measured worse than that.  (Three sigma of
            # the largest axis against a 3-D norm, as before, rejected ~3 % of good pairs.)  Within
            # the fixed gate the pair is tied whatever its sigma: its covariance is read only beyond it.
            if self._reads_covariance(rel, (dt, dr)):
                cov = self._relative_covariance(rel.a, rel.b)
                sig_t, sig_r = self._trans_sigma(cov), self._rot_sigma(cov)
            else:
                sig_t = sig_r = 0.0
            k3 = self._k(3)
            if dt > max(c.gate_m, k3 * sig_t) or dr > max(c.gate_rad, k3 * sig_r):
                rel.reason = (f"relative pose {dt * 1000:.1f} mm / {math.degrees(dr):.2f} deg from design "
                              f"(1 sigma {sig_t * 1000:.1f} mm / {math.degrees(sig_r):.2f} deg)")
                continue
            f = gtsam.BetweenFactorPose3(self.key(rel.a), self.key(rel.b), design, self.semantic_noise)
            self._add(f, ("as_is", f))
            rel.tied = True
            added += 1
        return added

    def _from_design(self, rel: RelationState) -> tuple[float, float]:
        """How far a pair's measured relative pose is from its design: the position offset (m) and
        the rotation (rad).  Positions are compared in the structure frame along the design's
        directions: a tag's tilt is its worst-measured quantity, and over a 0.5 m lever it would
        fake an offset."""
        design = self.model.design_between(rel.a, rel.b)
        pa, pb = self.tag_pose(rel.a), self.tag_pose(rel.b)
        design_a = self.model.tags[rel.a].structure_T_tag
        offset = (pb.translation() - pa.translation()) - design_a.rotation().rotate(design.translation())
        dt = float(np.linalg.norm(offset))
        dr = float(np.linalg.norm(Rot3.Logmap(design.rotation().between(pa.rotation().between(pb.rotation())))))
        return dt, dr

    def _reads_covariance(self, rel: RelationState, from_design: tuple[float, float] | None = None) -> bool:
        """Whether deciding `rel` now reads the pair's joint covariance.  A deployable's check does
        unless the module is valid and fully deployed within the fixed tolerances
        (`_deploy_check_fixed`).  A pair is tied when it is within max(gate, k sigma) of its
        design, so within the fixed gate (`gate_m`, `gate_rad`) the answer is the same whatever
        sigma is.  Either way the marginal -- the costliest part of a step in a large structure (a
        joint marginal of tags deep in the Bayes tree: 0.3-4 s at N = 8) -- is then not needed."""
        if rel.kind == "deployable" and not self._deploy_check_fixed(self._deploy_measured(rel)[3]).deployed:
            return True
        dt, dr = from_design if from_design is not None else self._from_design(rel)
        return dt > self.config.gate_m or dr > self.config.gate_rad

    def _deploy_measured(self, rel: RelationState) -> tuple[int, int, Pose3, Pose3]:
        """(bottom, top, the bottom tag's estimate, the measured B->T pose): the lift read from the
        tag *positions* in the structure frame, along the design's lift axis (a tag's tilt is its
        least well measured quantity, and over the 0.5 m lever it would fake a lateral offset)."""
        bottom, top = (rel.a, rel.b) if self._is_bottom(rel.a) else (rel.b, rel.a)
        design_b = self.model.tags[bottom].structure_T_tag
        pb, pt = self.tag_pose(bottom), self.tag_pose(top)
        lift_in_b = design_b.rotation().unrotate(pt.translation() - pb.translation())
        return bottom, top, pb, Pose3(pb.rotation().between(pt.rotation()), lift_in_b)

    def _deploy_check_fixed(self, measured: Pose3) -> DeployCheck:
        """The deployment check at its fixed tolerances alone (no noise): where it finds the module
        valid and fully deployed, widening the tolerances by the pair's noise cannot change a field
        of the answer -- every test that could fail compares against max(fixed, k sigma) >= fixed,
        and 'fully deployed' against spacing - max(fixed, k sigma) <= spacing - fixed."""
        return deployable_check(measured, self.model.spacing_m, height_tol_m=self.config.height_tol_m,
                                lateral_tol_m=DEPLOY_LATERAL_MIN_M, rotation_tol_rad=DEPLOY_ROTATION_MIN_RAD,
                                noise_m=0.0)

    def _deploy_check(self, rel: RelationState) -> DeployCheck:
        """The B->T deployment check (`_deploy_measured`).  The relative rotation is checked
        against the false-alarm quantile of what the pair's covariance allows.  A module valid and
        fully deployed within the fixed tolerances is that whatever its noise
        (`_deploy_check_fixed`): its covariance, a joint marginal that costs up to seconds in a
        large structure, is then not read."""
        bottom, top, pb, measured = self._deploy_measured(rel)
        fixed = self._deploy_check_fixed(measured)
        if fixed.deployed:
            return fixed
        design_b = self.model.tags[bottom].structure_T_tag
        cov = self._relative_covariance(bottom, top)
        if cov is not None:
            # the pair's position covariance, rotated from the bottom tag's estimated to its design frame
            Rbd = design_b.rotation().matrix().T @ pb.rotation().matrix()
            cov_t = Rbd @ cov[3:, 3:] @ Rbd.T
            lift_sigma = float(math.sqrt(max(cov_t[1, 1], 0.0)))
            lateral_sigma = float(math.sqrt(max(np.linalg.eigvalsh(cov_t[np.ix_([0, 2], [0, 2])]).max(), 0.0)))
        else:
            lift_sigma = lateral_sigma = 0.0
        # each test at the false-alarm quantile of its dimension (lift one-sided, lateral 2-D,
        # rotation 3-D): 3 sigma on the 2-D lateral norm alone flagged ~1 % of good deployables
        rot_tol = max(DEPLOY_ROTATION_MIN_RAD, self._k(3) * self._rot_sigma(cov))
        c = self.config
        return deployable_check(measured, self.model.spacing_m,
                                height_tol_m=max(c.height_tol_m, self._k(1, one_sided=True) * lift_sigma),
                                lateral_tol_m=max(DEPLOY_LATERAL_MIN_M, self._k(2) * lateral_sigma),
                                rotation_tol_rad=rot_tol, noise_m=lift_sigma)

    def _k(self, dof: int, one_sided: bool = False) -> float:
        """Threshold in sigmas for a `dof`-dimensional Gaussian error's norm at `gate_alpha`."""
        return _gate_k(dof, one_sided, self.config.gate_alpha)

    @staticmethod
    def _trans_sigma(cov: np.ndarray | None) -> float:
        return 0.0 if cov is None else float(math.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0)))

    @staticmethod
    def _rot_sigma(cov: np.ndarray | None) -> float:
        return 0.0 if cov is None else float(math.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)))

    def _is_bottom(self, tag: int) -> bool:
        m = self.model.module_by_name[self.model.tags[tag].module]
        return m.tags[0] == tag

    def _prefetch(self, tags: Iterable[int], to_root: bool = False) -> None:
        """The marginal blocks of every tag a step is about to read (the snapshot's tags, the pairs
        whose relations are decided), from one joint marginal of iSAM2.  Each marginal after an
        update recomputes the Bayes tree's shortcuts from the root down, ~1-2 ms whether it asks
        for one key or eight: asked one pair at a time, a step paid that 3-4 times.  With
        `to_root`, the tags are first re-eliminated into the root (`_to_root`)."""
        if self._batch_solved:
            return
        keys = list(dict.fromkeys(self.key(t) for t in tags if self.has_tag(t)))
        keys = [k for k in keys if (k, k) not in self._cov_blocks]
        if len(keys) < 2:
            return          # one key: marginalCovariance costs the same
        if to_root:
            self._to_root(keys)
        try:
            joint = self.isam.jointMarginalCovariance(keys)
        except (RuntimeError, IndexError):
            return
        for ka in keys:
            for kb in keys:
                self._cov_blocks[ka, kb] = joint.at(ka, kb)

    def _to_root(self, keys: list[int]) -> None:
        """Re-eliminate `keys` last, into the Bayes tree's root, relinearising nothing: the same
        linear system in another order, so the same estimate to round-off.  A related pair the
        step's views did not touch sits deep in the tree, and its joint marginal with the module's
        tags (at the root, `_last_groups`) walked every separator marginal on the way up: up to
        30 s at N = 9, against ~1 s for re-eliminating that path."""
        groups = gtsam.KeyGroupMap()
        extra, hold = gtsam.KeyList(), gtsam.KeyList()
        for key in keys:
            groups.insert2(key, 1)
            extra.push_back(key)
        every = self.isam.getLinearizationPoint().keys()
        for key in every:
            hold.push_back(key)
        self.isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], constrainedKeys=groups, noRelinKeys=hold,
                         extraReelimKeys=extra)
        self._estimate = None
        self._tag_estimates = None

    def _relative_covariance(self, a: int, b: int) -> np.ndarray | None:
        """Covariance of tag_a_T_tag_b (tangent of b's frame) from the pair's *joint* marginal.
        Tags seen from the same views share those cameras' pose errors, and that shared part
        cancels in their relative pose: summing the two marginals instead counted it twice, which
        under a noisy camera pose (the paper's 5 cm) widened the gate and the deployment check to
        +-12 cm, so a 10 cm short deployment passed as deployed."""
        ka, kb = self.key(a), self.key(b)
        try:
            if self._batch_solved:
                if self._batch_marginals is None:
                    self._batch_marginals = gtsam.Marginals(self.graph, self.estimate)
                joint = self._batch_marginals.jointMarginalCovariance([ka, kb])
                saa, sbb, sab = joint.at(ka, ka), joint.at(kb, kb), joint.at(ka, kb)
            elif (ka, kb) in self._cov_blocks:
                saa, sbb, sab = self._cov_blocks[ka, ka], self._cov_blocks[kb, kb], self._cov_blocks[ka, kb]
            else:
                joint = self.isam.jointMarginalCovariance([ka, kb])
                saa, sbb, sab = joint.at(ka, ka), joint.at(kb, kb), joint.at(ka, kb)
        except (RuntimeError, IndexError):
            return None
        rel = self.tag_pose(a).between(self.tag_pose(b))
        Ad = rel.inverse().AdjointMap()          # d(rel) = xi_b - Ad xi_a
        cov = Ad @ saa @ Ad.T + sbb - Ad @ sab - sab.T @ Ad.T
        return 0.5 * (cov + cov.T) + np.eye(6) * 1e-12

    # ---- results ---------------------------------------------------------------------------------
    @property
    def estimate(self) -> gtsam.Values:
        """Every variable's current estimate: iSAM2's, computed on the first read after a solve
        (a Values of every variable of the run, ~1 ms at 3,000), or the batch solve's."""
        if self._estimate is None:
            self._estimate = self.isam.calculateEstimate()
        return self._estimate

    @estimate.setter
    def estimate(self, values: gtsam.Values) -> None:
        self._estimate = values

    # One variable's estimate without computing every variable's: what a step reads after its solve
    # (its new factors' residuals, the verdict's tags, the next view's rig) is a few dozen of the
    # run's thousands.  iSAM2's value of one key is the same retraction of the same delta,
    # bit for bit.
    def _pose(self, key: int) -> Pose3:
        return self.isam.calculateEstimatePose3(key) if self._estimate is None else self._estimate.atPose3(key)

    def _vector(self, key: int) -> np.ndarray:
        return self.isam.calculateEstimateVector(key) if self._estimate is None else self._estimate.atVector(key)

    def _exists(self, key: int) -> bool:
        return self.isam.valueExists(key) if self._estimate is None else self._estimate.exists(key)

    def tag_pose(self, tag: int) -> Pose3:
        settled = self.settled.get(tag)
        return settled if settled is not None else self._pose(self.key(tag))

    def has_tag(self, tag: int) -> bool:
        return self._exists(self.key(tag))

    def tag_covariance(self, tag: int) -> np.ndarray:
        """Marginal covariance of a tag pose from the solver that made the current estimate, scaled
        by the a-posteriori variance factor when the corners proved noisier than the graph assumed
        (never scaled down: the survey's priors do not shrink with the corners)."""
        if self._batch_solved:
            if self._batch_marginals is None:
                self._batch_marginals = gtsam.Marginals(self.graph, self.estimate)
            cov = self._batch_marginals.marginalCovariance(self.key(tag))
        elif (key := self.key(tag), key) in self._cov_blocks:
            cov = self._cov_blocks[key, key]
        else:
            cov = self.isam.marginalCovariance(self.key(tag))
        noise = self.corner_noise()
        return cov * noise.covariance_scale if noise is not None else cov

    def tag_covariances(self, tags: Iterable[int]) -> dict[int, np.ndarray]:
        """`tag_covariance` of many tags (those whose marginal fails are left out).  After an iSAM2
        update every marginal recomputes the Bayes tree's shortcuts from the root down (~3 ms a tag
        at N = 5, whichever the tag); a joint marginal of JOINT_CHUNK tags pays that walk once for
        them all (the same blocks to 1e-10): every tag of an N = 5 run in 0.34 s, not 1.04 s."""
        wanted = [t for t in dict.fromkeys(tags) if self.has_tag(t)]
        raw: dict[int, np.ndarray] = {}
        todo: list[int] = []
        for t in wanted:
            key = self.key(t)
            if not self._batch_solved and (key, key) in self._cov_blocks:
                raw[t] = self._cov_blocks[key, key]
            else:
                todo.append(t)
        if not self._batch_solved and len(todo) > 1:
            for i in range(0, len(todo), JOINT_CHUNK):
                chunk = todo[i:i + JOINT_CHUNK]
                try:
                    joint = self.isam.jointMarginalCovariance([self.key(t) for t in chunk])
                except (RuntimeError, IndexError):
                    continue                      # one at a time below
                for t in chunk:
                    raw[t] = joint.at(self.key(t), self.key(t))
        noise = self.corner_noise()
        scale = noise.covariance_scale if noise is not None else 1.0
        out = {t: c * scale for t, c in raw.items()}
        for t in todo:
            if t not in out:
                try:
                    out[t] = self.tag_covariance(t)       # scaled there
                except RuntimeError:
                    pass
        return out

    def camera_pose(self, k: int) -> Pose3:
        return self._pose(C(k))

    def tag_estimates(self) -> dict[int, Pose3]:
        # read by tag elimination, the structure check and the log after every step: once per estimate
        if self._tag_estimates is None or self._tag_estimates[0] is not self.estimate:
            self._tag_estimates = (self.estimate, {t: self.tag_pose(t) for t in sorted(self.tags)
                                                   if t in self.settled or self.has_tag(t)})
        return dict(self._tag_estimates[1])

    def not_deployed(self) -> dict[str, DeployCheck]:
        """Deployables whose B->T pair failed the deployment check, by module name."""
        out = {}
        for rel in self.relations.values():
            if rel.kind == "deployable" and rel.deploy is not None and not rel.deploy.deployed:
                out[self.model.tags[rel.a].module] = rel.deploy
        return out

    def deployment_unread(self, tags: Iterable[int]) -> bool:
        """Whether these tags' deployable pair has had no deployment check read (False when they
        form no deployable pair)."""
        tags = set(tags)
        return any(rel.kind == "deployable" and {rel.a, rel.b} <= tags and rel.deploy is None
                   for rel in self.relations.values())

    def untied(self) -> list[RelationState]:
        return [r for r in self.relations.values() if r.decided and not r.tied]

    def total_error(self) -> float:
        return float(self.graph.error(self.estimate))
