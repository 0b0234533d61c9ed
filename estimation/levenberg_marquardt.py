"""GTSAM's Levenberg-Marquardt, iterated from Python so that its Python factors read the
linearisation point in place instead of a copy of it.

GTSAM hands a Python `CustomFactor` the values to evaluate at as a `const Values &`, and pybind11
turns that into a Python object by copying it -- every variable of the graph, at every callback
(~0.1 us a variable: 0.2 ms a callback at 2,000 variables, against the ~10 us the corner factor
itself takes) -- unless that C++ object already has a Python wrapper, which it then passes as it
is.  `LevenbergMarquardtOptimizer.optimize()` linearises at values of its own, which have none.
Iterating it here, holding a wrapper of the values it is about to linearise at (`values()`, a
live view), makes each linearisation's callbacks read them in place.  The loop is GTSAM's own
`NonlinearOptimizer::defaultOptimize` (the same stopping rule, `checkConvergence`), so the steps,
the iterations and the result are the optimizer's own; only the error evaluations of a trial step
(at values GTSAM makes inside `iterate`) still copy.

The same holds for iSAM2: `SfGraphSlam` holds `ISAM2.getLinearizationPoint()` for its run."""

from __future__ import annotations

import math

import gtsam


def optimize(graph: gtsam.NonlinearFactorGraph, start: gtsam.Values,
             params: gtsam.LevenbergMarquardtParams) -> tuple[gtsam.Values, int]:
    """Levenberg-Marquardt from `start`: GTSAM's `optimize()`, step for step.  Returns the solution
    and the number of iterations."""
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
