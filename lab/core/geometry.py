"""Poses and frames: one pose type, `gtsam.Pose3`, everywhere inside `lab`.

Naming (docs/architecture.md §Frames): a pose is named `a_T_b`, the pose of frame b expressed in
frame a, so `a_T_b * b_T_c == a_T_c` and `a_T_b.transformFrom(p_b) == p_a`.

Frames used across the code:
- `world`     the lab; for BORG work it coincides with the turntable base at angle 0.
- `structure` BORG: origin at the outer corner node of the first deployable (2D), axes along the
              truss grid, z up.  Trusses: the starting-triangle frame.
- `tag`       x right, y up, z out of the tagged face (the paper's convention).  The AprilTag /
              OpenCV object frame (x right, y down, z into the face) differs by a half turn about x;
              `TAG_T_CV` converts.
- `camera`    OpenCV: x right, y down, z forward.
- `turntable` z up through the rotation axis.

Units are SI.  The papers' 6-vectors (x, y, z, roll, pitch, yaw), with roll-pitch-yaw about fixed
x, y, z axes (R = Rz(yaw) Ry(pitch) Rx(roll)), appear only at the edges: reports and the
paper-faithful baselines.  Covariances use GTSAM's tangent order: rotation first, then translation.
"""

from __future__ import annotations

from typing import Iterable, Sequence

import gtsam
import numpy as np

Pose3 = gtsam.Pose3
Rot3 = gtsam.Rot3
Point3 = np.ndarray

__all__ = [
    "Pose3",
    "Rot3",
    "pose",
    "identity",
    "from_xyzrpy",
    "to_xyzrpy",
    "from_matrix",
    "to_matrix",
    "from_quaternion",
    "to_quaternion",
    "from_xyzquat",
    "to_xyzquat",
    "look_at",
    "rot_z",
    "pose_error",
    "TAG_T_CV",
    "mean_pose",
]


def identity() -> Pose3:
    return Pose3()


def pose(R: np.ndarray | Rot3 | None = None, t: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0)) -> Pose3:
    """A pose from a rotation (3x3 matrix or Rot3, default identity) and a translation in metres."""
    if R is None:
        rot = Rot3()
    elif isinstance(R, Rot3):
        rot = R
    else:
        rot = Rot3(np.asarray(R, dtype=float))
    return Pose3(rot, np.asarray(t, dtype=float).reshape(3))


def from_xyzrpy(v: Sequence[float]) -> Pose3:
    """The papers' 6-vector (x, y, z, roll, pitch, yaw): metres, radians, fixed-axis x-y-z."""
    x, y, z, roll, pitch, yaw = (float(a) for a in v)
    return Pose3(Rot3.RzRyRx(roll, pitch, yaw), np.array([x, y, z]))


def to_xyzrpy(p: Pose3) -> np.ndarray:
    rpy = p.rotation().rpy()  # (roll, pitch, yaw) with R = Rz Ry Rx
    return np.concatenate([p.translation(), rpy])


def from_matrix(T: np.ndarray) -> Pose3:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"a homogeneous transform is 4x4, got {T.shape}")
    return Pose3(T)


def to_matrix(p: Pose3) -> np.ndarray:
    return p.matrix()


def from_quaternion(q_xyzw: Sequence[float], t: Sequence[float] = (0.0, 0.0, 0.0)) -> Pose3:
    """Quaternion in (qx, qy, qz, qw) order, the order of our JSON and of Foxglove/ROS."""
    qx, qy, qz, qw = (float(a) for a in q_xyzw)
    n = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if n < 1e-12:
        raise ValueError("zero quaternion")
    return Pose3(Rot3.Quaternion(qw / n, qx / n, qy / n, qz / n), np.asarray(t, dtype=float))


def to_quaternion(p: Pose3 | Rot3) -> np.ndarray:
    """(qx, qy, qz, qw) with qw >= 0."""
    rot = p.rotation() if isinstance(p, Pose3) else p
    w, x, y, z = rot.toQuaternion().coeffs()[[3, 0, 1, 2]]
    q = np.array([x, y, z, w])
    return -q if q[3] < 0 else q


def from_xyzquat(v: Sequence[float]) -> Pose3:
    """[x, y, z, qx, qy, qz, qw] -> Pose3 (the JSON shape of `lab structure`)."""
    return from_quaternion(v[3:7], v[0:3])


def to_xyzquat(p: Pose3) -> list[float]:
    return [*map(float, p.translation()), *map(float, to_quaternion(p))]


def rot_z(angle_rad: float) -> Pose3:
    return Pose3(Rot3.Rz(angle_rad), np.zeros(3))


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> Pose3:
    """world_T_camera for an OpenCV camera at `eye` looking at `target` (z forward, y down)."""
    eye_v = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye_v
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=float))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: view direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose3(Rot3(np.column_stack([x, y, z])), eye_v)


# The tag frame of the papers (x right, y up, z out of the face) and the AprilTag/OpenCV object
# frame (x right, y down, z into the face) differ by a half turn about x.
TAG_T_CV: Pose3 = Pose3(Rot3.Rx(np.pi), np.zeros(3))


def pose_error(estimate: Pose3, truth: Pose3) -> tuple[float, float]:
    """(translation error in m, rotation error angle in rad) of `estimate` against `truth`."""
    d = truth.between(estimate)
    return float(np.linalg.norm(estimate.translation() - truth.translation())), float(
        np.linalg.norm(Rot3.Logmap(d.rotation()))
    )


def mean_pose(poses: Iterable[Pose3]) -> Pose3:
    """Chordal-L2 mean of a few poses (translation mean, rotation projected back onto SO(3))."""
    ps = list(poses)
    if not ps:
        raise ValueError("mean of no poses")
    t = np.mean([p.translation() for p in ps], axis=0)
    M = np.sum([p.rotation().matrix() for p in ps], axis=0)
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return Pose3(Rot3(R), t)
