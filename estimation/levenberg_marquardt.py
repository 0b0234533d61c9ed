"""GTSAM's Levenberg-Marquardt, iterated from Python so that its Python factors read the values they
are evaluated at in place instead of a copy of them.

GTSAM hands a Python `CustomFactor` the values to evaluate at as a `const Values &`, and pybind11
turns that into a Python object by copying it -- every variable of the graph, at every callback
(~0.1 us a variable: 0.2 ms a callback at 2,000 variables, against the ~10 us the corner factor
itself takes) -- unless that C++ object already has a Python wrapper, which it then passes as it
is.  `LevenbergMarquardtOptimizer` linearises at, and evaluates its trial steps at, values of its
own, which have none.

`optimize` is therefore GTSAM's optimizer written out in Python around GTSAM's own linear algebra:
`NonlinearOptimizer::defaultOptimize`'s loop and stopping rule (`checkConvergence`), and
`LevenbergMarquardtOptimizer::iterate` / `tryLambda` with its default damping (one isotropic prior
a variable, sigma `1/sqrt(lambda)`), its default lambda policy (a fixed factor up on a rejected
step, down on a taken one) and its model-fidelity test, the nonlinear graph's COLAMD ordering
computed once, and multifrontal Cholesky.  Every value it linearises at or evaluates is a Python
object, so no callback copies.  It takes the same steps in the same order: its iterations, its
lambda and its result are GTSAM's to the last bit (`tests/test_levenberg_marquardt.py` holds it to
`LevenbergMarquardtOptimizer.optimize()`, through rejected steps).

Settings it does not reproduce (diagonal damping, the adaptive lambda factor, another linear
solver or ordering type) go to GTSAM's optimizer as they are (`_gtsam_optimize`, whose trial
steps still copy).  An ordering set on the parameters is not read (the wrapper does not expose
it), so callers leave it unset; nor is `minModelFidelity`, so GTSAM's default (1e-3) is used.

The same holds for iSAM2: `SfGraphSlam` holds `ISAM2.getLinearizationPoint()` for its run."""

from __future__ import annotations

import math
import sys
from typing import Protocol

import gtsam
import numpy as np

# LevenbergMarquardtParams::minModelFidelity's default, not exposed by the Python wrapper
MIN_MODEL_FIDELITY = 1e-3


class Cost(Protocol):
    """What the optimizer evaluates: a graph's error and its linearisation at a point.  A
    `gtsam.NonlinearFactorGraph` is one; `view_batch.BatchCost` evaluates a batch graph's view
    factors together."""

    def error(self, values: gtsam.Values) -> float: ...

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph: ...


def optimize(graph: gtsam.NonlinearFactorGraph, start: gtsam.Values, params: gtsam.LevenbergMarquardtParams,
             cost: Cost | None = None, python_factors: bool = True) -> tuple[gtsam.Values, int]:
    """Levenberg-Marquardt from `start`: GTSAM's `optimize()`, step for step.  Returns the solution
    and the number of iterations.  `cost` evaluates the graph's error and linearisation (default:
    the graph's own; it must be the graph's to round-off); settings that go to GTSAM's optimizer
    do not use it.  A graph of C++ factors only (`python_factors` False) has no copies to avoid and
    goes to GTSAM's optimizer, which builds its damping without a Python call a variable (the same
    result)."""
    if (not python_factors or params.getDiagonalDamping() or not params.getUseFixedLambdaFactor()
            or params.getOrderingType() != "COLAMD" or params.getLinearSolverType() != "MULTIFRONTAL_CHOLESKY"):
        return _gtsam_optimize(graph, start, params)
    state = run(graph, start, params, cost)
    return state.values, state.iterations


def run(graph: gtsam.NonlinearFactorGraph, start: gtsam.Values, params: gtsam.LevenbergMarquardtParams,
        cost: Cost | None = None) -> State:
    """`NonlinearOptimizer::defaultOptimize` over `State`; the final state (`optimize`'s
    parameters only)."""
    state = State(graph, start, params, cost)
    new_error = state.error
    if new_error <= params.getErrorTol() or state.iterations >= params.getMaxIterations():
        return state
    while True:
        current_error = new_error
        state.iterate()
        new_error = state.error
        if (state.iterations >= params.getMaxIterations()
                or gtsam.checkConvergence(params, current_error, new_error) or not math.isfinite(current_error)):
            return state


class State:
    """`LevenbergMarquardtOptimizer`'s state and its `iterate`: the values, their error, lambda and
    its factor, and the counts GTSAM keeps (`iterations`, `inner`: every lambda tried)."""

    def __init__(self, graph: gtsam.NonlinearFactorGraph, start: gtsam.Values,
                 params: gtsam.LevenbergMarquardtParams, cost: Cost | None = None) -> None:
        self.graph = graph
        self.params = params
        self.cost: Cost = graph if cost is None else cost
        self.values = gtsam.Values(start)
        self.error = self.cost.error(self.values)
        self.lam: float = params.getlambdaInitial()
        self.factor = params.getlambdaFactor()
        self.iterations = 0
        self.inner = 0
        self.ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(graph)
        # the damping: a prior on every variable (`buildDampedSystem`), made once and given each
        # lambda's sigma in place (half the cost of new factors: ~2 us a variable a lambda); each is
        # made with one identity, zero vector and unit model a dimension (`_damping_priors` gives
        # every prior its own model before its first use; ~8 us a variable less than new ones)
        dims = sorted(self.values.dims().items())
        sizes = {dim for _, dim in dims}
        shared = {dim: (np.eye(dim), np.zeros(dim), gtsam.noiseModel.Unit.Create(dim)) for dim in sizes}
        self._priors = [gtsam.JacobianFactor(key, *shared[dim]) for key, dim in dims]
        self._sigmas = {dim: np.ones(dim) for dim in sizes}       # one array a dimension, shared
        self._prior_sigmas = [self._sigmas[dim] for _, dim in dims]
        self._damped_at: float | None = None

    def iterate(self) -> None:
        linear = self.cost.linearize(self.values)
        while not self._try_lambda(linear):
            pass

    def _damping_priors(self) -> list[gtsam.JacobianFactor]:
        """Every variable's prior of sigma 1/sqrt(lambda), GTSAM's `buildDampedSystem` (which sets
        sigma = 1/sqrt(lambda) the same way).  The factors are reused: each damped system is
        solved before the next lambda retunes them."""
        if self._damped_at != self.lam:
            sigma = 1.0 / math.sqrt(self.lam)
            for sigmas in self._sigmas.values():
                sigmas.fill(sigma)
            for prior, sigmas in zip(self._priors, self._prior_sigmas):
                prior.setModel(False, sigmas)
            self._damped_at = self.lam
        return self._priors

    def _try_lambda(self, linear: gtsam.GaussianFactorGraph) -> bool:
        """`LevenbergMarquardtOptimizer::tryLambda`: True once a step was taken or the search
        for one is over."""
        damped = gtsam.GaussianFactorGraph()
        damped.push_back(linear)
        for prior in self._damping_priors():
            damped.push_back(prior)
        success, stop = False, False
        try:
            delta = damped.optimize(self.ordering)
        except RuntimeError as e:  # IndeterminantLinearSystemException
            if "ndetermina" not in str(e):   # "Indeterminate linear system detected ..."
                raise
            delta = None
        if delta is not None:
            old_linear = linear.error(gtsam.VectorValues.Zero(delta))
            linear_change = old_linear - linear.error(delta)
            if linear_change >= 0:
                new_values = self.values.retract(delta)
                new_error = self.cost.error(new_values)
                change = self.error - new_error
                if linear_change > sys.float_info.epsilon * old_linear:
                    fidelity = change / linear_change
                    success = fidelity > MIN_MODEL_FIDELITY
                if abs(change) < self.params.getRelativeErrorTol() * self.error:
                    stop = True
        if success:
            self.lam = max(self.params.getlambdaLowerBound(), self.lam / self.factor)
            self.values, self.error = new_values, new_error
            self.iterations += 1
            self.inner += 1
            return True
        if not stop:
            self.lam *= self.factor
            self.inner += 1
            return self.lam >= self.params.getlambdaUpperBound()
        return True


def _gtsam_optimize(graph: gtsam.NonlinearFactorGraph, start: gtsam.Values,
                    params: gtsam.LevenbergMarquardtParams) -> tuple[gtsam.Values, int]:
    """GTSAM's optimizer, iterated from here holding each point it linearises at (its trial
    steps' error evaluations still copy)."""
    opt = gtsam.LevenbergMarquardtOptimizer(graph, start, params)
    new_error = opt.error()
    if new_error <= params.getErrorTol() or opt.iterations() >= params.getMaxIterations():
        return gtsam.Values(opt.values()), int(opt.iterations())
    while True:
        current_error = new_error
        # a wrapper of the point `iterate` linearises at, dropped before anything else can read it:
        # `iterate` replaces the optimizer's state, and these values with it
        point = opt.values()
        opt.iterate()
        del point
        new_error = opt.error()
        if (opt.iterations() >= params.getMaxIterations()
                or gtsam.checkConvergence(params, current_error, new_error) or not math.isfinite(current_error)):
            return gtsam.Values(opt.values()), int(opt.iterations())
