"""Beyond the IPJR paper: fuse camera observations of the nodes with the strut lengths in one
factor graph (the paper's conclusion: "external measurement systems, such as precise cameras, to
further improve the estimates").

Each node carries a target (a tag centre or the node ball) that fixed cameras see.  The camera
poses are unknown variables with a prior around where they were mounted (surveyed roughly); each
observation is a `GenericProjectionFactorCal3_S2` between a camera pose and a node point, added to
the same graph as the strut `RangeFactor3` priors and measurements, in the same starting-triangle
gauge.  Cameras have no scale of their own: the struts give scale, the cameras tie far-apart
nodes together directly and stop the error growing along long chains of tetrahedra.

`TrussCameraMLE` keeps the `TrussMLE` step API and adds `add_observation(camera, node, pixel)`;
in simulation `observe_truth` produces the observations of the new node from the true structure.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from estimation.truss_geometry import Plan, Step
from estimation.truss_mle import TrussMLE
from lab.core.geometry import look_at
from lab.core.structures.trusses import TrussModel

__all__ = ["CameraRig", "ring_rig", "TrussCameraMLE"]


@dataclass
class CameraRig:
    """Fixed cameras looking at the structure (poses in the gauge frame, OpenCV camera frame)."""

    world_T_cameras: list[gtsam.Pose3]
    K: gtsam.Cal3_S2
    width_px: int
    height_px: int
    sigma_px: float = 0.5  # target centre noise
    sigma_rot_rad: float = 0.01  # mounting prior
    sigma_pos_m: float = 0.05

    def project(self, world_T_camera: gtsam.Pose3, point: np.ndarray) -> np.ndarray | None:
        """Pixel of a point, or None when it is behind the camera or outside the image."""
        p_cam = world_T_camera.transformTo(np.asarray(point, dtype=float))
        if p_cam[2] <= 0.1:
            return None
        uv = np.asarray(gtsam.PinholeCameraCal3_S2(world_T_camera, self.K).project(point))
        if not (0 <= uv[0] < self.width_px and 0 <= uv[1] < self.height_px):
            return None
        return uv


def ring_rig(nominal: np.ndarray, n_cameras: int = 4, sigma_px: float = 0.5, focal_px: float = 3000.0,
             width_px: int = 4000, height_px: int = 3000, standoff: float = 1.6) -> CameraRig:
    """Cameras on a ring above the structure's best-fit plane, each seeing all of it."""
    c = nominal.mean(axis=0)
    _, _, vt = np.linalg.svd(nominal - c)
    normal = vt[2]
    radius = float(np.max(np.linalg.norm(nominal - c, axis=1)))
    u = vt[0]
    v = np.cross(normal, u)
    poses = []
    for k in range(n_cameras):
        a = 2 * np.pi * k / n_cameras
        eye = c + standoff * radius * normal + 0.8 * radius * (np.cos(a) * u + np.sin(a) * v)
        poses.append(look_at(eye, c, up=u if abs(np.dot(u, normal)) < 0.9 else v))
    K = gtsam.Cal3_S2(focal_px, focal_px, 0.0, width_px / 2, height_px / 2)
    return CameraRig(poses, K, width_px, height_px, sigma_px)


class TrussCameraMLE(TrussMLE):
    """MLE over strut lengths and camera observations of the nodes."""

    def __init__(self, model: TrussModel, plan: Plan, sigma_L: float, sigma_M: float, rig: CameraRig | None = None,
                 sigma_px: float | None = None, method: str = "isam2") -> None:
        super().__init__(model, plan, sigma_L, sigma_M, method)
        self.rig = rig or ring_rig(self.nominal, sigma_px=sigma_px if sigma_px is not None else 0.5)
        if sigma_px is not None:
            self.rig.sigma_px = sigma_px
        self.pixel_noise = gtsam.noiseModel.Isotropic.Sigma(2, self.rig.sigma_px)
        self.pose_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([self.rig.sigma_rot_rad] * 3 + [self.rig.sigma_pos_m] * 3))
        self._pending: list[tuple[int, int, np.ndarray]] = []
        self._cameras_added: set[int] = set()
        self._true_cameras: list[gtsam.Pose3] | None = None
        self.observations = 0

    @staticmethod
    def camera_key(k: int) -> int:
        return gtsam.symbol("c", k)

    def add_observation(self, camera: int, node: int, pixel: np.ndarray) -> None:
        """A camera's pixel measurement of a node's target; enters the graph with the next step."""
        if not 0 <= camera < len(self.rig.world_T_cameras):
            raise ValueError(f"camera {camera} is not in the rig (0..{len(self.rig.world_T_cameras) - 1})")
        self._pending.append((camera, node, np.asarray(pixel, dtype=float)))

    def observe_truth(self, step: Step, truth: np.ndarray, rng: np.random.Generator) -> None:
        """Simulation: every camera that sees the new node reports its pixel (+ noise)."""
        if self._true_cameras is None:  # where the cameras really are: planned pose + mounting error
            self._true_cameras = [
                p.retract(np.concatenate([rng.normal(0, self.rig.sigma_rot_rad, 3), rng.normal(0, self.rig.sigma_pos_m, 3)]))
                for p in self.rig.world_T_cameras]
        for k, pose in enumerate(self._true_cameras):
            uv = self.rig.project(pose, truth[step.node])
            if uv is not None:
                self.add_observation(k, step.node, uv + rng.normal(0, self.rig.sigma_px, 2))

    def _extra_for_step(self, step: Step) -> None:
        keep = []
        for camera, node, uv in self._pending:
            if node != step.node and node not in self._built_set:
                keep.append((camera, node, uv))
                continue
            key = self.camera_key(camera)
            if camera not in self._cameras_added:
                pose = self.rig.world_T_cameras[camera]
                self._add(gtsam.PriorFactorPose3(key, pose, self.pose_noise))
                self._new_values.insert(key, pose)
                self._cameras_added.add(camera)
            self._add(gtsam.GenericProjectionFactorCal3_S2(uv, self.pixel_noise, key, node, self.rig.K))
            self.observations += 1
        self._pending = keep

    def _all_values(self) -> gtsam.Values:
        values = super()._all_values()
        estimate = self.isam.calculateEstimate() if self.method == "isam2" else self.values
        for camera in self._cameras_added:
            key = self.camera_key(camera)
            if self._new_values.exists(key):
                values.insert(key, self._new_values.atPose3(key))
            elif estimate.exists(key):
                values.insert(key, estimate.atPose3(key))
        return values
