"""The compiled corner factor (`estimation.corner_kernel`, through `rig_model.corner_factor`) gives
`project_corners`' error and Jacobians in every variant a run or the rig survey builds: intrinsics
fixed or a variable, with and without the print scale and the lens term, and on the fallback path
of a corner behind the camera."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimation.fiducials import tag_object_points
from estimation.rig_model import DISTORTION, INTRINSICS, cal3_s2, corner_factor, project_corners, radial_basis
from lab.core.geometry import Pose3, Rot3

K = np.array([[914.0, 0.3, 639.5], [0, 913.0, 359.5], [0, 0, 1]])
C, T, S = gtsam.symbol_shorthand.C, gtsam.symbol_shorthand.T, gtsam.symbol_shorthand.S
LOCAL = tag_object_points(0.1)


def _case(seed: int, behind: bool = False):
    """A camera about 1-2 m from a tag that it sees at a random oblique angle (or, `behind`, a tag
    with a corner behind the camera's plane); measured corners a few px off the projection."""
    rng = np.random.default_rng(seed)
    tag = Pose3(Rot3.RzRyRx(*rng.uniform(-np.pi, np.pi, 3)), rng.uniform(-1.0, 1.0, 3))
    tilt = Rot3.RzRyRx(np.pi + rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-np.pi, np.pi))
    distance = 0.03 if behind else rng.uniform(1.0, 2.0)
    cam = tag.compose(Pose3(tilt, np.zeros(3))).compose(Pose3(Rot3(), np.array([0.0, 0.0, -distance])))
    if behind:
        cam = cam.compose(Pose3(Rot3.Ry(1.2), np.zeros(3)))
    meas = np.array([[640.0, 360.0]] * 4) + rng.normal(0.0, 40.0, (4, 2))
    return cam, tag, meas


def _values(cam, tag, scale: float, lens: np.ndarray) -> gtsam.Values:
    v = gtsam.Values()
    v.insert(INTRINSICS, cal3_s2(K))
    v.insert(C(0), cam)
    v.insert(T(0), tag)
    v.insert(S(0), np.array([scale]))
    v.insert(DISTORTION, lens)
    return v


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("with_scale, with_lens", [(False, False), (True, False), (False, True), (True, True)])
@pytest.mark.parametrize("free", [False, True])
def test_the_compiled_factor_is_project_corners(seed, with_scale, with_lens, free):
    cam, tag, meas = _case(seed)
    cal = cal3_s2(K)
    basis = radial_basis(meas, K)
    scale, lens = 0.0021 * (seed - 2), np.array([3e-3, -4e-4]) * (seed - 3)
    f = corner_factor(C(0), T(0), meas, LOCAL, 0.1, intrinsics_key=INTRINSICS, robust_k=None,
                      fixed=None if free else cal, scale_key=S(0) if with_scale else None,
                      distortion=(DISTORTION, basis) if with_lens else None)
    values = _values(cam, tag, scale, lens)
    k = 1.0 + (scale if with_scale else 0.0)
    e, JC, JT, JK = project_corners(cam, tag, k * LOCAL, np.asarray(cal.vector()), meas, want_calibration=True)
    if with_lens:
        e = e - basis @ lens
    assert np.abs(f.unwhitenedError(values) - e).max() < 1e-9
    A, b = f.linearize(values).jacobian()
    expected = [JC, JT] + ([JK] if free else [])
    if with_scale:
        expected.append(np.sum(JT[:, 3:] * np.repeat(LOCAL, 2, axis=0), axis=1, keepdims=True))
    if with_lens:
        expected.append(-basis)
    expected = np.hstack(expected) / 0.1
    assert A.shape == expected.shape
    assert np.abs(A - expected).max() <= 1e-12 * np.abs(expected).max()
    assert np.abs(b + e / 0.1).max() < 1e-9


@pytest.mark.parametrize("free", [False, True])
def test_a_corner_behind_the_camera_takes_the_reference_path(free):
    cam, tag, meas = _case(1, behind=True)
    cal = cal3_s2(K)
    e_ref, *_ = project_corners(cam, tag, LOCAL, np.asarray(cal.vector()), meas)
    assert (e_ref == 1e3).any(), "the case must put a corner behind the camera"
    f = corner_factor(C(0), T(0), meas, LOCAL, 0.1, intrinsics_key=INTRINSICS, robust_k=None,
                      fixed=None if free else cal, scale_key=S(0), distortion=(DISTORTION, radial_basis(meas, K)))
    values = _values(cam, tag, 0.0, np.zeros(2))
    assert np.abs(f.unwhitenedError(values) - e_ref).max() < 1e-9
    A, _ = f.linearize(values).jacobian()
    assert np.isfinite(A).all()
    behind_rows = np.repeat(e_ref == 1e3, 1)
    assert not A[behind_rows, :12].any()
