"""The run's Cramér–Rao bound kept linearised across a run (estimation/bound.py) is the full rebuild
(`bound_graph` + `bound_covariances`) at every verdict: new views, a new corner sigma, a tag whose
truth moved (a module re-placed)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from test_slam_step_exact import GEOM, K, MODEL, _calibration, _steps

from estimation.bound import RunBound
from estimation.precision import bound_covariances
from estimation.sf_graphslam import SfGraphSlam, SlamConfig
from lab.core.geometry import Pose3, Rot3

NOISE = dict(chain_noise=GEOM.chain_noise, rig_prior_sigma=1e-7, turntable_tag_sigma_m=0.0005)


def _rebuilt(slam: SfGraphSlam, keys, sigma: float, truth: gtsam.Values) -> dict[int, np.ndarray]:
    return bound_covariances(slam.bound_graph(sigma, **NOISE), truth, keys)


def _same(got: dict[int, np.ndarray], want: dict[int, np.ndarray]) -> None:
    # round-off: to 1e-9 of each covariance's largest entry
    for k in want:
        assert np.abs(got[k] - want[k]).max() <= 1e-9 * np.abs(want[k]).max(), k


def _truth(slam: SfGraphSlam) -> gtsam.Values:
    # any point linearises both the same way; the estimate values every variable of the graph
    truth = gtsam.Values(slam.estimate)
    return truth


def test_the_incremental_bound_is_the_rebuilt_bound_step_by_step():
    slam = SfGraphSlam(MODEL, SlamConfig(observation="corners", corner_sigma_px=0.05, tag_scale_sigma=0.001),
                       rig=GEOM, calibration=_calibration(), camera=(K, np.zeros(5)))
    bound = RunBound(slam, **NOISE)
    keys = [slam.key(t) for t in (0, 1, 2)]
    for views, sigma in zip(_steps(), (0.05, 0.031)):
        for cam, dets, motion in views:
            slam.add_view(cam, dets, motion)
        slam.update(snapshot=[0, 1, 2])
        truth = _truth(slam)
        got = bound.covariances(keys, sigma, truth)
        want = _rebuilt(slam, keys, sigma, truth)
        _same(got, want)
    # the same views at another corner sigma: every corner factor takes it
    got = bound.covariances(keys, 0.2, truth)
    want = _rebuilt(slam, keys, 0.2, truth)
    _same(got, want)
    assert not np.allclose(got[keys[0]], bound_covariances(slam.bound_graph(0.031, **NOISE), truth, keys)[keys[0]])
    # a tag whose truth moved: its factors are linearised again where it now is
    moved = gtsam.Values(truth)
    moved.update(slam.key(1), truth.atPose3(slam.key(1)).compose(Pose3(Rot3.Rz(0.3), np.array([0.05, 0.0, 0.02]))))
    got = bound.covariances(keys, 0.2, moved)
    want = _rebuilt(slam, keys, 0.2, moved)
    _same(got, want)
    assert not np.allclose(want[keys[1]], _rebuilt(slam, keys, 0.2, truth)[keys[1]], rtol=1e-6)


def test_one_key_from_its_own_elimination_is_the_marginals_own():
    """A verdict asks for one key: eliminated last on its own (`GaussianFactorGraph.marginal`), not
    through `gtsam.Marginals`; the same covariance."""
    slam = SfGraphSlam(MODEL, SlamConfig(observation="corners", corner_sigma_px=0.05, tag_scale_sigma=0.001),
                       rig=GEOM, calibration=_calibration(), camera=(K, np.zeros(5)))
    bound = RunBound(slam, **NOISE)
    for cam, dets, motion in _steps()[0]:
        slam.add_view(cam, dets, motion)
    slam.update(snapshot=[0, 1, 2])
    truth = _truth(slam)
    keys = [slam.key(t) for t in (0, 1, 2)]
    both = bound.covariances(keys, 0.05, truth)             # through Marginals
    for k in keys:
        one = bound.covariances([k], 0.05, truth)[k]
        assert one == pytest.approx(both[k], rel=1e-9, abs=1e-15)
