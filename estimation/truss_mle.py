"""MLE assembly of IPJR trusses on GTSAM (IPJR paper §4, Table 2 MLEAssembly).

The state is every built node's position in the starting triangle's gauge frame (a at the origin,
b on +x, c in the xy-plane).  Each assembly step adds, as `gtsam.RangeFactor3` (Point3-Point3
range):
- one *prior* per active strut: the length the IPJR was commanded, noise sigma_L (the strut is
  fixed at commanded + N(0, sigma_L^2));
- one *measurement* per strut between the new node and any built node (the active struts and the
  passive, redundant ones), noise sigma_M.
Maximising the likelihood (eq. 21) is the least-squares problem GTSAM solves.  The 3-2-1 gauge is
a set of partial priors on a, b and c with zero precision along the free directions.

Step API, the one the IPJR procedure uses (design.md §1, "one IPJR step"):

    mle = TrussMLE(model, plan, sigma_L, sigma_M)
    for step in plan.steps:
        L = mle.lengths_to_command(step)           # from the current estimate of the base
        ... IPJRs set L, the operator fixes the node ...
        M = {edge: measured length for edge in mle.struts_to_measure(step)}
        mle.add_step(step, L, M)                   # re-estimates every node
    mle.estimate(), mle.covariances()

`method="isam2"` (default) updates incrementally (iSAM2, warm-started from the previous solution,
fluid relinearisation); `method="batch"` re-solves the whole graph with Levenberg-Marquardt from
the previous estimate (the paper's gradient ascent, for studies).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import gtsam
import numpy as np

from estimation.truss_geometry import DegenerateBaseError, Plan, Step, gauge_transform, place_step, to_gauge
from lab.core.structures.trusses import TrussModel

__all__ = ["TrussAssemblyFrame", "TrussMLE", "StepTiming"]


class TrussAssemblyFrame:
    """What every truss estimator shares: the plan, the design in the gauge frame, the commanded
    lengths rule (line 4 of MLEAssembly) and which struts get measured (line 6)."""

    def __init__(self, model: TrussModel, plan: Plan) -> None:
        self.model = model
        self.plan = plan
        self.nominal = to_gauge(model.nodes, plan.triangle)
        self.R, self.origin = gauge_transform(model.nodes, plan.triangle)
        self.built: list[int] = []
        self._built_set: set[int] = set()

    def current(self) -> np.ndarray:
        """Best current positions of built nodes (gauge frame, NaN for unbuilt); estimators override."""
        raise NotImplementedError

    def lengths_to_command(self, step: Step) -> np.ndarray:
        """L_fb = |X̄_f - X̂_b| for b in the base: put f at its design place on the base as built."""
        self._check_next(step)
        x = self.current()
        return np.array([np.linalg.norm(self.nominal[step.node] - x[b]) for b in step.base])

    def struts_to_measure(self, step: Step) -> list[tuple[int, int]]:
        """Struts between the new node and the structure (active and passive), as (f, other)."""
        nb = self.model.neighbours[step.node]
        out = [(step.node, b) for b in step.base]
        out += [(step.node, i) for i in self.built if i in nb and i not in step.base]
        return out

    def _check_next(self, step: Step) -> None:
        if step.node in self._built_set:
            raise ValueError(f"node {step.node} is already built")
        missing = [b for b in step.base if b not in self._built_set]
        if missing:
            raise ValueError(f"node {step.node}: base nodes {missing} are not built yet")

    def _mark_built(self, f: int) -> None:
        self.built.append(f)
        self._built_set.add(f)

    def to_design(self, x_gauge: np.ndarray) -> np.ndarray:
        """Gauge-frame positions expressed in the design frame (the starting triangle at its design pose)."""
        return x_gauge @ self.R + self.origin


@dataclass
class StepTiming:
    node: int
    n_nodes: int
    seconds: float
    iterations: int


class TrussMLE(TrussAssemblyFrame):
    """The MLE assembly estimator (see module docstring)."""

    def __init__(self, model: TrussModel, plan: Plan, sigma_L: float, sigma_M: float, method: str = "isam2",
                 relinearize_threshold: float | None = None, max_iterations: int = 10) -> None:
        super().__init__(model, plan)
        if not (sigma_L > 0 and sigma_M > 0):
            raise ValueError(f"sigma_L and sigma_M must be positive metres, got {sigma_L}, {sigma_M}")
        if method not in ("isam2", "batch"):
            raise ValueError(f"method must be 'isam2' or 'batch', got {method!r}")
        self.sigma_L, self.sigma_M, self.method = float(sigma_L), float(sigma_M), method
        self.max_iterations = max_iterations
        self.prior_noise = gtsam.noiseModel.Isotropic.Sigma(1, self.sigma_L)
        self.meas_noise = gtsam.noiseModel.Isotropic.Sigma(1, self.sigma_M)
        # The gauge is exact in the paper; a prior 100x tighter than any strut noise moves the
        # gauge by 1 % of sigma_M at most, and keeps the information matrix well conditioned
        # (1000x made iSAM2's Cholesky call near-flat tetrahedra "indeterminate").
        self._gauge_precision = 1.0 / (1e-2 * min(self.sigma_L, self.sigma_M)) ** 2
        self.graph = gtsam.NonlinearFactorGraph()
        self.values = gtsam.Values()
        self._x = np.full((model.n_nodes, 3), np.nan)
        self.timings: list[StepTiming] = []
        if method == "isam2":
            params = gtsam.ISAM2Params()
            # In metres: relinearise a node when its estimate moves by a tenth of the measurement noise.
            self._relin_threshold = (relinearize_threshold if relinearize_threshold is not None
                                     else 0.1 * self.sigma_M)
            params.setRelinearizeThreshold(self._relin_threshold)
            params.relinearizeSkip = 1
            self._isam_params = params
            self.isam = gtsam.ISAM2(params)
        self.fallbacks = 0  # iSAM2 updates that had to be redone by batch LM
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()

    # ---- the step API ------------------------------------------------------------------------
    def current(self) -> np.ndarray:
        return self._x

    def estimate(self) -> np.ndarray:
        """Estimated positions (N, 3) in the gauge frame; NaN rows for nodes not built yet."""
        return self._x.copy()

    def add_step(self, step: Step, commanded: Sequence[float], measured: dict[tuple[int, int], float]) -> StepTiming:
        """Record a built node: its commanded active-strut lengths and the measured struts, then
        re-estimate every node."""
        t0 = time.perf_counter()
        self._check_next(step)
        commanded = np.asarray(commanded, dtype=float)
        if len(commanded) != len(step.base):
            raise ValueError(f"node {step.node}: {len(step.base)} base struts but {len(commanded)} lengths")
        f = step.node
        for b, L in zip(step.base, commanded):
            self._add(gtsam.RangeFactor3(f, b, float(L), self.prior_noise))
        for (i, j), m in measured.items():
            if f not in (i, j):
                raise ValueError(f"measurement of strut ({i}, {j}) does not touch node {f}")
            other = j if i == f else i
            if other not in self._built_set:
                raise ValueError(f"measurement ({i}, {j}): node {other} is not built")
            self._add(gtsam.RangeFactor3(f, other, float(m), self.meas_noise))
        self._add_gauge(step)
        self._new_values.insert(f, self._initial_position(step, commanded, measured))
        self._extra_for_step(step)
        self._mark_built(f)
        iterations = self._solve()
        timing = StepTiming(f, len(self.built), time.perf_counter() - t0, iterations)
        self.timings.append(timing)
        return timing

    def covariances(self) -> dict[int, np.ndarray]:
        """Posterior marginal covariance (3x3, m^2, gauge frame) of every built node."""
        if self.method == "isam2":
            return {f: np.asarray(self.isam.marginalCovariance(f)) for f in self.built}
        marginals = gtsam.Marginals(self.graph, self.values)
        return {f: np.asarray(marginals.marginalCovariance(f)) for f in self.built}

    # ---- internals --------------------------------------------------------------------------
    def _add(self, factor) -> None:
        self._new_factors.add(factor)

    def _extra_for_step(self, step: Step) -> None:
        """Hook for fused estimators (camera observations of the new node)."""

    def _add_gauge(self, step: Step) -> None:
        slot = len(self.built)
        if slot >= 3:
            return
        p = self._gauge_precision
        precisions = {0: [p, p, p], 1: [0.0, p, p], 2: [0.0, 0.0, p]}[slot]
        noise = gtsam.noiseModel.Diagonal.Precisions(np.array(precisions))
        self._add(gtsam.PriorFactorPoint3(step.node, np.zeros(3), noise))

    def _initial_position(self, step: Step, commanded: np.ndarray, measured: dict[tuple[int, int], float]) -> np.ndarray:
        """F_f on the current estimate with the measured base struts (else the commanded ones):
        starts the solver on the right side of the base (no mirrored minimum)."""
        lengths = []
        for b, L in zip(step.base, commanded):
            m = measured.get((step.node, b), measured.get((b, step.node)))
            lengths.append(float(m) if m is not None else float(L))
        try:
            return place_step([self._x[b] for b in step.base], lengths)
        except DegenerateBaseError:
            return self.nominal[step.node].copy()

    def _solve(self) -> int:
        self.graph.push_back(self._new_factors)
        if self.method == "isam2":
            try:
                self.isam.update(self._new_factors, self._new_values)
                iterations = 1
                # Relinearise again while some variable sits further from its linearisation point
                # than the threshold: one update is enough at the paper's small noise; the
                # tetrahelix study's large noise needs a few Gauss-Newton steps.
                while iterations < self.max_iterations and \
                        np.max(np.abs(self.isam.getDelta().vector())) > self._relin_threshold:
                    self.isam.update()
                    iterations += 1
                estimate = self.isam.calculateEstimate()
            except RuntimeError:
                # Gauss-Newton stepped into a (nearly) flat tetrahedron, where a node is
                # indeterminate -- only seen with the tetrahelix study's 10 cm strut noise.  Solve
                # the whole graph with Levenberg-Marquardt and restart iSAM2 from that solution.
                estimate, iterations = self._levenberg_marquardt(self._all_values())
                self.fallbacks += 1
                try:
                    self.isam = gtsam.ISAM2(self._isam_params)
                    self.isam.update(self.graph, estimate)
                except RuntimeError:
                    # The optimum itself is flat (struts measured as barely meeting): stay with
                    # batch LM, whose damping copes, for the rest of this assembly.
                    self.method = "batch"
                    self.values = estimate
        else:
            self.values.insert(self._new_values)
            self.values, iterations = self._levenberg_marquardt(self.values)
            estimate = self.values
        self._x = self._read(estimate)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        return iterations

    def _all_values(self) -> gtsam.Values:
        values = gtsam.Values()
        for f in self.built:
            values.insert(f, self._new_values.atPoint3(f) if self._new_values.exists(f) else self._x[f])
        return values

    def _levenberg_marquardt(self, initial: gtsam.Values) -> tuple[gtsam.Values, int]:
        params = gtsam.LevenbergMarquardtParams()
        params.setRelativeErrorTol(1e-12)
        params.setAbsoluteErrorTol(1e-15)
        params.setMaxIterations(100)
        opt = gtsam.LevenbergMarquardtOptimizer(self.graph, initial, params)
        return opt.optimize(), int(opt.iterations())

    def _read(self, values: gtsam.Values) -> np.ndarray:
        x = np.full((self.model.n_nodes, 3), np.nan)
        for f in self.built:
            x[f] = values.atPoint3(f)
        return x
