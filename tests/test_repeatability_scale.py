"""The rig survey measures how its devices repeat (estimation/rig_calibration_solve.py,
`_measured_repeatability_scale`): variance component estimation of the chain factors' group.  A
rig file whose datasheet repeatability is half the truth would otherwise make the survey, and every
run after it, too sure of the rig (camera-mount NEES 15-23 against 6 at twice the datasheet)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimation.rig_calibration_solve import REPEATABILITY_SCALE_RANGE, _measured_repeatability_scale, with_repeatability_scale
from lab.core.geometry import Pose3

C = gtsam.symbol_shorthand.C


def _survey_like(true_over_assumed: float, n: int = 400, seed: int = 1):
    """n cameras, each predicted by a 'chain' (a 6-D CustomFactor to its nominal pose, noise
    `assumed`) and pinned down by its 'corners' (a prior 20x tighter, at the truth); the truth is
    off the nominal by `true_over_assumed` x the assumed noise."""
    rng = np.random.default_rng(seed)
    assumed = np.array([1e-4] * 3 + [2e-5] * 3)
    graph, est = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k in range(n):
        nominal = Pose3()
        truth = nominal.expmap(rng.normal(0, 1, 6) * assumed * true_over_assumed)

        def chain(this, values, jac, nominal=nominal):
            x = values.atPose3(this.keys()[0])
            if jac is not None:
                jac[0] = np.eye(6)
            return nominal.localCoordinates(x)

        graph.add(gtsam.CustomFactor(gtsam.noiseModel.Diagonal.Sigmas(assumed), [C(k)], chain))
        graph.add(gtsam.PriorFactorPose3(C(k), truth, gtsam.noiseModel.Diagonal.Sigmas(assumed / 20)))
        est.insert(C(k), truth)
    est = gtsam.LevenbergMarquardtOptimizer(graph, est).optimize()
    return graph, est


@pytest.mark.parametrize("true_over_assumed", [0.5, 1.0, 2.0])
def test_the_chain_groups_scale_is_measured(true_over_assumed):
    graph, est = _survey_like(true_over_assumed)
    k = _measured_repeatability_scale(graph, est, 1.0)
    assert k == pytest.approx(true_over_assumed, rel=0.08)


def test_a_perfect_rig_is_held_at_the_floor_and_the_run_takes_the_scale():
    graph, est = _survey_like(0.0, n=50)
    assert _measured_repeatability_scale(graph, est, 1.0) == REPEATABILITY_SCALE_RANGE[0]
    from estimation.rig_model import RigGeometry
    from lab.core.config import load_rig

    rig = load_rig()
    g = RigGeometry.from_rig(rig, Pose3(), np.eye(3))
    g2 = with_repeatability_scale(g, 1.5)
    assert g2.config.stewart_repeatability_m == pytest.approx(1.5 * g.config.stewart_repeatability_m)
    assert g2.config.turntable_repeatability_rad == pytest.approx(1.5 * g.config.turntable_repeatability_rad)
    assert with_repeatability_scale(g, float("nan")) is g
