"""`levenberg_marquardt.optimize` is GTSAM's `LevenbergMarquardtOptimizer.optimize()` step for step:
the same iterations and the same solution to the last bit, with Python factors in the graph (the
reason it exists: their callbacks read the point in place) and without."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimation import levenberg_marquardt
from test_corner_view_factor import _slam


def _params(max_iterations: int = 100) -> gtsam.LevenbergMarquardtParams:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-6)
    params.setAbsoluteErrorTol(1e-9)
    return params


def _same(a: gtsam.Values, b: gtsam.Values) -> None:
    assert a.size() == b.size()
    for key in a.keys():
        if gtsam.Symbol(key).chr() in (ord("c"), ord("t"), ord("a"), ord("b"), ord("m")):
            assert np.array_equal(a.atPose3(key).matrix(), b.atPose3(key).matrix())


@pytest.mark.parametrize("max_iterations", [1, 2, 100])
def test_the_python_loop_is_gtsams_optimize(max_iterations):
    slam = _slam()
    slam._initialise_pending()
    graph = slam.graph                     # the single corner factors and the chain factors: Python
    mine, iterations = levenberg_marquardt.optimize(graph, slam.initial, _params(max_iterations))
    opt = gtsam.LevenbergMarquardtOptimizer(graph, slam.initial, _params(max_iterations))
    theirs = opt.optimize()
    assert iterations == opt.iterations() >= 1
    _same(mine, theirs)
    assert graph.error(mine) < graph.error(slam.initial)


def test_a_graph_already_at_its_minimum_takes_no_iteration():
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.1)))
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3())
    solution, iterations = levenberg_marquardt.optimize(graph, values, _params())
    assert iterations == 0 and solution.atPose3(0).equals(gtsam.Pose3(), 0.0)
