"""The measuring half of a BORG step: detections -> SF-GraphSLAM update -> tag elimination ->
verdict.  Keeps the estimator state of a whole run and serialises what it consumed, so that a
resumed run replays the same inputs in the same order and reaches the same estimate."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from estimation.fiducials import Detection, TagDetector
from estimation.rig_model import RigGeometry, ViewMotion
from estimation.sf_graphslam import SfGraphSlam, SlamConfig
from estimation.sightings import near_sightings
from lab.core.rig_calibration_file import RigCalibration
from estimation.tag_elimination import eliminate_tags, warm as warm_tag_elimination
from estimation.verification import Tolerances, verify_module
from lab.core.geometry import Pose3, from_xyzquat, to_xyzquat
from lab.core.recorder import messages as m
from lab.core.structures.borg import BorgModel
from lab.core.verdicts import Verdict


class Measurement:
    def __init__(self, model: BorgModel, intrinsics: Any, config: dict[str, Any] | None = None, *,
                 rig: RigGeometry | None = None, calibration: RigCalibration | None = None) -> None:
        self.model = model
        self.config = dict(config or {})
        self.rig = rig
        self.calibration = calibration
        # the detector reads through the calibrated camera: a rig calibration corrects the focal
        # length and principal point of the camera file (its distortion stays)
        K = calibration.K if calibration is not None else intrinsics.K
        self.detector = TagDetector(K, intrinsics.dist, {t: s.size_m for t, s in model.tags.items()})
        self.slam = SfGraphSlam(model, SlamConfig(semantic=self.config.get("semantic", True),
                                                  observation=self.config.get("observation", "corners"),
                                                  corner_sigma_px=float(self.config.get("corner_sigma_px",
                                                                                        SlamConfig.corner_sigma_px)),
                                                  tag_scale_sigma=float(self.config.get("tag_scale_sigma",
                                                                                        SlamConfig.tag_scale_sigma))),
                                rig=rig, calibration=calibration, camera=(K, np.asarray(intrinsics.dist, float)))
        self.detector_camera = (np.asarray(K, float), np.asarray(intrinsics.dist, float))
        self.tolerances = Tolerances()
        self.cutoff_m = float(self.config.get("elimination_cutoff_m", 0.05))
        warm_tag_elimination()        # the kernel loads (or compiles) now, not in the first step
        # 0: every sighting of a view goes into the graph (`near_sightings`)
        self.near_tags_per_view = int(self.config.get("near_tags_per_view", 0))
        # 0: nothing is settled, the graph stays whole (`settle_built`)
        self.settle_after_layers = int(self.config.get("settle_after_layers", 0))
        self.settled_below = 0             # the layers below this one are settled
        self._top_layer = -1               # the highest layer a verdict has been released for
        self.sightings = [0, 0]            # (put in the graph, detected) over the run's views
        self.rejected_tags: set[int] = set()
        self.placed: list[str] = []
        self._verdicts: dict[str, Verdict] = {}
        # each module's tags as measured in its own step, before its semantic factors joined
        self._measured: dict[str, dict[int, tuple[Pose3, np.ndarray | None]]] = {}
        self._estimated_tags: dict[int, Pose3] = {}     # the graph's tags as this round began

    # ---- detection ---------------------------------------------------------------------------
    def detect(self, image: np.ndarray, structure_T_camera: Pose3 | None = None
               ) -> tuple[list[Detection], dict[int, int]]:
        """Tags in `image`, and those read but dropped as partly behind another (tag -> the tag in
        front of it); with the camera's pose from the kinematics, each tag's pose is predicted (the
        graph's estimate as the round began, else the design), which settles IPPE ambiguities and
        says which of two overlapping tags is in front (`fiducials.hidden_behind`)."""
        if structure_T_camera is None:
            return self.detector.detect_with_hidden(image)
        camera_T_structure = structure_T_camera.inverse()
        estimated = self._estimated_tags

        def predict(tid: int) -> Pose3 | None:
            pose = estimated.get(tid)
            if pose is None:
                spec = self.model.tags.get(tid)
                pose = None if spec is None else spec.structure_T_tag
            return None if pose is None else camera_T_structure.compose(pose)
        return self.detector.detect_with_hidden(image, predict)

    @staticmethod
    def detections_to_json(detections: list[Detection]) -> list[dict[str, Any]]:
        return [{"id": d.tag_id, "corners_px": d.corners_px.tolist(), "pose": to_xyzquat(d.camera_T_tag),
                 "covariance": d.covariance.tolist(), "reprojection_px": d.reprojection_px,
                 "ambiguity_ratio": d.ambiguity_ratio if math.isfinite(d.ambiguity_ratio) else 1e9,
                 "ambiguous": d.ambiguous, "size_m": d.size_m} for d in detections]

    @staticmethod
    def detections_from_json(items: list[dict[str, Any]]) -> list[Detection]:
        return [Detection(int(d["id"]), np.asarray(d["corners_px"]), from_xyzquat(d["pose"]),
                          np.asarray(d["covariance"]), float(d["reprojection_px"]), float(d["ambiguity_ratio"]),
                          bool(d["ambiguous"]), float(d["size_m"])) for d in items]

    @staticmethod
    def detections_message(detections: list[Detection], t_s: float) -> Any:
        return m.TagDetections(timestamp=m.timestamp(t_s), frame_id="camera", detections=[
            m.tag_detection(d.tag_id, d.corners_px, d.camera_T_tag, d.covariance, d.reprojection_px,
                            d.ambiguity_ratio if math.isfinite(d.ambiguity_ratio) else 0.0) for d in detections])

    # ---- one step ------------------------------------------------------------------------------
    def add_step(self, module: str, views: list[dict[str, Any]],
                 detections: list[list[Detection]] | None = None) -> None:
        """A step's views (or a further round of them for the same module).  The module's tags are
        held out of the semantic relations until `finish`: its verdict is read from the
        measurement alone, however many rounds of views it takes.  `detections`: each view's
        `detections_from_json(view["detections"])`, when the caller has parsed them already.
        The same as `begin_round`, `add_view` for each view, `end_round`."""
        if detections is None:
            detections = [self.detections_from_json(v["detections"]) for v in views]
        self.begin_round(module)
        for v, seen in zip(views, detections, strict=True):
            self.add_view(v, seen)
        self.end_round(module)

    def begin_round(self, module: str) -> None:
        """A round of views of `module` begins: `add_view` each as it is detected, then `end_round`."""
        if module not in self.placed:
            self.placed.append(module)
        self.last_views = []
        # read here, on the caller's thread: the round's views are detected on a worker while
        # nothing changes the graph until `end_round`
        self._estimated_tags = self.slam.tag_estimates()

    def add_view(self, view: dict[str, Any], detections: list[Detection]) -> None:
        """One view of the round into the graph (its camera, its factors, its new tags' sightings),
        not yet solved: a run adds each while the devices move to the next view."""
        structure_T_camera = Pose3(np.asarray(view["structure_T_camera"]))
        motion = ViewMotion(float(view["turntable_rad"]), tuple(float(x) for x in view["stewart_pose"]),
                            float(view.get("lift_m", 0.0)))
        # a settled tag's sighting cannot join the graph: the nearest tags are chosen from the others
        near = self.near_sightings(view["module"], [d for d in detections if d.tag_id not in self.slam.settled])
        self.sightings[0] += len(near)
        self.sightings[1] += len(detections)
        self.last_views.append(self.slam.add_view(structure_T_camera, near,
                                                  motion=motion if self.rig is not None else None))

    def near_sightings(self, module: str, detections: list[Detection]) -> list[Detection]:
        """The sightings a view of `module` gives the graph (`estimation.sightings.near_sightings`,
        with the run's `near_tags_per_view`)."""
        return near_sightings(self.model, module, detections, self.near_tags_per_view)

    def end_round(self, module: str) -> None:
        """The round's views solved: the module's tags measured, tags off the design rejected."""
        self._measured[module] = self.slam.update(snapshot=self.model.module_by_name[module].tags, hold=True)
        self._eliminate()

    def finish(self, module: str) -> None:
        """The module's verdict is final: its relations to the design may now be tied; the layers
        the run has now built well past are settled (`settle_built`)."""
        self.slam.release(self.model.module_by_name[module].tags)
        self.settle_built(module)

    def settle_built(self, module: str) -> int:
        """Settle (`SfGraphSlam.settle`) every released module of the layers `settle_after_layers`
        or more below the highest layer released so far, `module`'s included.  The verdicts of
        those modules are final; their tags' estimates stay as they were; the step's cost then
        follows the layers still being measured, not the whole structure (docs/sf_graphslam.md,
        "Settling what is built").  Returns how many tags it settled now."""
        if self.settle_after_layers <= 0:
            return 0
        self._top_layer = max(self._top_layer, self.model.layer_of(module))
        below = self._top_layer - self.settle_after_layers + 1
        if below <= 0:
            return 0
        if below > self.settled_below:
            self.settled_below = below
        done = set(self._verdicts) | {module}
        tags = [t for name in self.placed if name in done and self.model.layer_of(name) < self.settled_below
                for t in self.model.module_by_name[name].tags if t not in self.slam.settled]
        return self.slam.settle(tags) if tags else 0

    def verdict_tags(self, module: str) -> tuple[int, ...]:
        v = self._verdicts.get(module)
        return () if v is None else v.tags_used

    def verdict_tag_covariance(self, module: str) -> np.ndarray | None:
        """The covariance of the tag the verdict reads the module from, as measured."""
        v = self._verdicts.get(module)
        if v is None or not v.tags_used:
            return None
        return self._measured.get(module, {}).get(v.tags_used[0], (None, None))[1]

    def redeploy(self, module: str) -> None:
        """The operator re-placed / re-deployed `module`: measure it afresh."""
        tags = self.model.module_by_name[module].tags
        self.slam.replace_tags(tags)
        self.rejected_tags.difference_update(tags)
        self._measured.pop(module, None)

    def _eliminate(self) -> None:
        # a settled tag was judged while its layer was measured, and its estimate no longer moves:
        # the search is over the tags still in the solver (it is O(tags^2): 9 ms a step late in an
        # N = 8 run over every tag)
        settled = self.slam.settled
        estimates = {t: p for t, p in self.slam.tag_estimates().items() if t not in settled}
        explained = {}
        for name, check in self.slam.not_deployed().items():
            top = self.model.module_by_name[name].tags[1]
            explained[top] = self.model.tags[top].structure_T_tag.rotation().matrix()[:, 1]
        result = eliminate_tags(estimates, self.model, cutoff_m=self.cutoff_m, explained_axes=explained)
        self.rejected_tags.update(result.rejected)

    # ---- results -----------------------------------------------------------------------------------
    def verdict(self, module: str) -> Verdict:
        """The module's verdict from its own step's measurement (the procedure adds its views,
        attempts and, in simulation, the truth)."""
        measured = self._measured.get(module, {})
        estimates = {t: p for t, (p, _) in measured.items()}
        covs = {t: c for t, (_, c) in measured.items() if c is not None}
        v = verify_module(self.model, module, estimates, covariances=covs, rejected=self.rejected_tags,
                          not_deployed=self.slam.not_deployed(), tolerances=self.tolerances,
                          deployment_unread={module} if self.deployment_unread(module) else frozenset())
        self._verdicts[module] = v
        return v

    def deployment_unread(self, module: str) -> bool:
        """A deployable whose deployment check (its B -> T pair) has not been read yet."""
        return self.slam.deployment_unread(self.model.module_by_name[module].tags)

    def camera_estimates(self) -> list[tuple[Pose3, np.ndarray | None]]:
        """The estimated camera poses (structure frame) of the last step's views, with covariances."""
        from estimation.sf_graphslam import C

        out = []
        for k in getattr(self, "last_views", []):
            try:
                cov = self.slam.isam.marginalCovariance(C(k))
            except RuntimeError:
                cov = None
            out.append((self.slam.camera_pose(k), cov))
        return out

    def tag_estimates(self, covariance_of: set[int] | None = None) -> dict[int, tuple[Pose3, np.ndarray | None]]:
        """Every tag's estimate, with its marginal covariance (only the tags `covariance_of`, if given)."""
        poses = self.slam.tag_estimates()
        covs = self.slam.tag_covariances(poses if covariance_of is None else [t for t in poses if t in covariance_of])
        return {t: (p, covs.get(t)) for t, p in poses.items()}
