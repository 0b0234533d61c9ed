"""`levenberg_marquardt.optimize` is GTSAM's `LevenbergMarquardtOptimizer.optimize()` step for step:
the same iterations, the same lambdas tried, and the same solution to the last bit, with Python
factors in the graph (the reason it exists: their callbacks read the values in place) and without,
and through rejected steps.  Settings it leaves to GTSAM's optimizer give GTSAM's result."""

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
    """Every variable equal to the bit (poses, vectors and calibrations: what these graphs hold)."""
    assert a.size() == b.size() and list(a.keys()) == list(b.keys())
    reads = (lambda v, k: v.atPose3(k).matrix(), lambda v, k: v.atVector(k), lambda v, k: v.atCal3_S2(k).vector())
    for key in a.keys():
        for read in reads:
            try:
                x, y = read(a, key), read(b, key)
                break
            except RuntimeError:
                continue
        else:
            raise AssertionError(f"no read for {gtsam.DefaultKeyFormatter(key)}")
        assert np.array_equal(x, y), gtsam.DefaultKeyFormatter(key)


def _against_gtsam(graph: gtsam.NonlinearFactorGraph, start: gtsam.Values,
                   params: gtsam.LevenbergMarquardtParams) -> levenberg_marquardt.State:
    state = levenberg_marquardt.run(graph, start, params)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, start, params)
    theirs = opt.optimize()
    assert state.iterations == opt.iterations()
    # lambda is multiplied on every rejected step and divided (or scaled) on every accepted one:
    # the same lambda to the bit after the same iterations is the same sequence of trials
    assert state.lam == opt.lambda_()
    assert state.error == opt.error() == graph.error(theirs)
    _same(state.values, theirs)
    return state


@pytest.mark.parametrize("max_iterations", [1, 2, 100])
def test_the_python_loop_is_gtsams_optimize(max_iterations):
    slam = _slam()
    slam._initialise_pending()
    graph = slam.graph                     # the single corner factors and the chain factors: Python
    state = _against_gtsam(graph, slam.initial, _params(max_iterations))
    assert state.iterations >= 1 and state.error < graph.error(slam.initial)
    mine, iterations = levenberg_marquardt.optimize(graph, slam.initial, _params(max_iterations))
    assert iterations == state.iterations
    _same(mine, state.values)


def test_the_batch_graph_solves_as_gtsam_solves_it():
    slam = _slam()
    slam._initialise_pending()
    _against_gtsam(slam._batch_graph(), slam.initial, _params())


def _far_start(starts: tuple[float, ...] = (2.0, 2.5, -3.0, 1.6)) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Residuals atan(x) started where a Gauss-Newton step overshoots (|x| > 1.39: the step lands
    further out), tied by a weak difference factor: lambda must grow before a step is taken."""
    graph = gtsam.NonlinearFactorGraph()
    unit = gtsam.noiseModel.Unit.Create(1)

    def arctan(key: int):
        def error(this, values, jacobians):
            x = values.atVector(key)[0]
            if jacobians is not None:
                jacobians[0] = np.array([[1.0 / (1.0 + x * x)]])
            return np.array([np.arctan(x)])
        return gtsam.CustomFactor(unit, [key], error)

    values = gtsam.Values()
    for key, x in enumerate(starts):
        graph.add(arctan(key))
        values.insert(key, np.array([x]))
        if key:
            graph.add(gtsam.BetweenFactorVector(key - 1, key, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, 10.0)))
    return graph, values


def test_rejected_steps():
    graph, values = _far_start()
    params = _params()
    params.setlambdaInitial(1e-9)          # too little damping at first: GTSAM must back off
    state = _against_gtsam(graph, values, params)
    assert state.inner > state.iterations   # some lambdas were rejected
    assert state.error < 1e-6 * graph.error(values)


def test_a_rejected_step_that_changes_little_ends_the_search():
    """A rejected step whose cost change is below the relative tolerance stops the lambda search
    (GTSAM does not try a larger lambda), and the unchanged error ends the solve."""
    graph, values = _far_start((50.0,))   # on atan's flat tail: the step lands at -3,800, as far up
    params = _params()
    params.setlambdaInitial(1e-9)
    params.setRelativeErrorTol(0.05)       # ... the cost rises by 2.6 %: rejected, and small
    state = _against_gtsam(graph, values, params)
    assert state.iterations == 0 and state.inner == 0 and state.error == graph.error(values)


@pytest.mark.parametrize("setting", ["diagonal damping", "adaptive lambda factor"])
def test_parameters_it_does_not_reproduce_go_to_gtsam(setting):
    graph, values = _far_start()
    params = _params()
    params.setlambdaInitial(1e-9)
    if setting == "diagonal damping":
        params.setDiagonalDamping(True)
    else:
        params.setUseFixedLambdaFactor(False)
    mine, iterations = levenberg_marquardt.optimize(graph, values, params)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    theirs = opt.optimize()
    assert iterations == opt.iterations()
    _same(mine, theirs)


def test_a_graph_already_at_its_minimum_takes_no_iteration():
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.1)))
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3())
    solution, iterations = levenberg_marquardt.optimize(graph, values, _params())
    assert iterations == 0 and solution.atPose3(0).equals(gtsam.Pose3(), 0.0)


def test_an_indeterminate_damped_system_raises_lambda_as_gtsam_does():
    """Two poses tied only to each other, damped at lambda 1e-300: elimination finds the system
    indeterminate until lambda has grown, as in GTSAM."""
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.BetweenFactorPose3(0, 1, gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 0.0, 0.0])),
                                       gtsam.noiseModel.Isotropic.Sigma(6, 0.1)))
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3())
    values.insert(1, gtsam.Pose3(gtsam.Rot3.Rx(0.3), np.array([0.5, 0.2, 0.0])))
    params = _params()
    params.setlambdaInitial(1e-300)
    damped = gtsam.GaussianFactorGraph()
    damped.push_back(graph.linearize(values))
    for prior in levenberg_marquardt.State(graph, values, params)._damping_priors():
        damped.push_back(prior)
    with pytest.raises(RuntimeError, match="ndetermina"):
        damped.optimize(gtsam.Ordering.ColamdNonlinearFactorGraph(graph))
    state = _against_gtsam(graph, values, params)
    assert state.inner > 100 and state.error < 1e-12


def test_the_cost_evaluates_every_point_and_the_graph_only_through_it():
    """The contract `view_batch.BatchCost` relies on: every error and linearisation goes through
    the cost, and a factor is called only with the values the cost was last handed (the same
    Python object), so what the cost computed there is what the graph is evaluated at."""
    graph, values = _far_start()
    last: list[gtsam.Values] = []
    calls = [0, 0]

    def check(this, v, jacobians):
        calls[0] += 1
        calls[1] += v is last[-1]
        if jacobians is not None:
            jacobians[0] = np.zeros((1, 1))
        return np.zeros(1)

    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(1), [0], check))

    class Seen:
        def error(self, v):
            last.append(v)
            return graph.error(v)

        def linearize(self, v):
            last.append(v)
            return graph.linearize(v)

    params = _params()
    params.setlambdaInitial(1e-9)
    state = levenberg_marquardt.run(graph, values, params, Seen())
    assert calls[0] > 10 and calls[1] == calls[0]
    assert len(last) > state.inner
    _same(state.values, levenberg_marquardt.run(graph, values, params).values)


def test_a_graph_of_cpp_factors_solves_the_same_either_way():
    """`python_factors=False` hands a C++-only graph to GTSAM's optimizer: the same solution."""
    graph = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.05)
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), noise))
    values = gtsam.Values()
    rng = np.random.default_rng(7)
    step = gtsam.Pose3(gtsam.Rot3.Rz(0.4), np.array([1.0, 0.0, 0.1]))
    for i in range(1, 8):
        graph.add(gtsam.BetweenFactorPose3(i - 1, i, step, noise))
        values.insert(i - 1, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.3, 3)), rng.normal(0, 1.0, 3)))
    values.insert(7, gtsam.Pose3())
    theirs, n_theirs = levenberg_marquardt.optimize(graph, values, _params(), python_factors=False)
    state = _against_gtsam(graph, values, _params())
    assert n_theirs == state.iterations >= 2
    _same(theirs, state.values)
