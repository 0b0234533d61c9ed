"""Simulated IPJR assembly (MLEAssembly lines 4-6 in simulation) with the open-loop, EKF and MLE
estimators, and the Monte Carlo figures the paper reports.

Per step: the estimator gives the lengths to command; the true node is placed by F_f on the true
base with the commanded lengths plus N(0, sigma_L^2) (the strut as fixed); every strut between the
new node and the structure is measured with N(0, sigma_M^2); the estimator takes them.  Open loop
commands the nominal lengths and never updates.  A trial's error is the built (true) structure
minus the design, both in the gauge frame; the Monte Carlo trace is the mean over trials of the
summed squared node errors (the paper's "trace" of a simulated assembly).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from estimation.truss_geometry import DegenerateBaseError, Plan, Step, place_step
from estimation.truss_mle import TrussAssemblyFrame, TrussMLE
from lab.core.structures.trusses import TrussModel

_MAX_REDRAWS = 100

__all__ = ["OpenLoop", "make_estimator", "simulate_assembly", "AssemblyRun", "monte_carlo", "MonteCarlo"]


class OpenLoop(TrussAssemblyFrame):
    """No estimation: command the design lengths; the 'estimate' stays the design."""

    def __init__(self, model: TrussModel, plan: Plan, sigma_L: float = 0.0, sigma_M: float = 0.0) -> None:
        super().__init__(model, plan)
        self.timings: list = []

    def current(self) -> np.ndarray:
        return self.nominal

    def estimate(self) -> np.ndarray:
        x = np.full_like(self.nominal, np.nan)
        x[self.built] = self.nominal[self.built]
        return x

    def add_step(self, step: Step, commanded, measured) -> None:
        self._check_next(step)
        self._mark_built(step.node)


def make_estimator(kind: str, model: TrussModel, plan: Plan, sigma_L: float, sigma_M: float, **kw) -> TrussAssemblyFrame:
    if kind == "open_loop":
        return OpenLoop(model, plan)
    if kind == "mle":
        return TrussMLE(model, plan, sigma_L, sigma_M, **kw)
    if kind == "ekf":
        from estimation.truss_ekf import TrussEKF

        return TrussEKF(model, plan, sigma_L, sigma_M)
    if kind == "mle_camera":
        from estimation.truss_fusion import TrussCameraMLE

        return TrussCameraMLE(model, plan, sigma_L, sigma_M, **kw)
    raise ValueError(f"unknown estimator {kind!r}: open_loop, mle, ekf, mle_camera")


@dataclass
class AssemblyRun:
    truth: np.ndarray  # (N, 3) built structure, gauge frame
    estimate: np.ndarray  # (N, 3) final estimate (the design for open loop)
    nominal: np.ndarray  # (N, 3) design, gauge frame
    update_seconds: list[float] = field(default_factory=list)
    redraws: int = 0  # steps whose struts could not meet and were set again

    @property
    def node_sq_errors(self) -> np.ndarray:
        return np.sum((self.truth - self.nominal) ** 2, axis=1)

    @property
    def estimate_sq_errors(self) -> np.ndarray:
        return np.sum((self.estimate - self.truth) ** 2, axis=1)


def simulate_assembly(model: TrussModel, plan: Plan, kind: str, sigma_L: float, sigma_M: float,
                      rng: np.random.Generator, estimator: TrussAssemblyFrame | None = None,
                      on_step: Callable[[Step, TrussAssemblyFrame], None] | None = None, **kw) -> AssemblyRun:
    """One simulated assembly; raises DegenerateBaseError if the struts as fixed cannot close."""
    est = estimator or make_estimator(kind, model, plan, sigma_L, sigma_M, **kw)
    truth = np.full((model.n_nodes, 3), np.nan)
    seconds = []
    redraws = 0
    for step in plan.steps:
        commanded = est.lengths_to_command(step)
        for attempt in range(_MAX_REDRAWS + 1):
            actual = commanded + rng.normal(0.0, sigma_L, size=len(commanded))
            try:
                truth[step.node] = place_step([truth[b] for b in step.base], actual)
                break
            except DegenerateBaseError:
                # The struts as set cannot meet over the real base: in the lab the IPJRs stall and
                # the step is redone, so the strut noise is redrawn (a truncated Gaussian).
                if attempt == _MAX_REDRAWS:
                    raise
                redraws += 1
        measured = {}
        for f, i in est.struts_to_measure(step):
            measured[(f, i)] = float(np.linalg.norm(truth[f] - truth[i]) + rng.normal(0.0, sigma_M))
        if hasattr(est, "observe_truth"):
            est.observe_truth(step, truth, rng)  # camera fusion: images of the new node
        t = est.add_step(step, commanded, measured)
        if t is not None:
            seconds.append(t.seconds)
        if on_step:
            on_step(step, est)
    return AssemblyRun(truth, est.estimate(), est.nominal.copy(), seconds, redraws)


@dataclass
class MonteCarlo:
    kind: str
    trials: int
    failures: int  # trials abandoned: a step's struts never met (after redraws)
    redraws: int  # steps whose struts could not meet and were set again (all trials)
    node_mse: np.ndarray  # (N,) mean squared error of each node, in plan order
    node_cov: np.ndarray  # (N, 3, 3) sample covariance of each node's error, plan order
    estimate_mse: np.ndarray  # (N,) mean squared estimation error (estimate - truth), plan order
    update_seconds: list[float]

    def trace_upto(self, k: int) -> float:
        """Summed MSE of the first k nodes in plan order ('the trace at node k')."""
        return float(np.sum(self.node_mse[:k]))

    @property
    def trace(self) -> float:
        return float(np.sum(self.node_mse))


def monte_carlo(model: TrussModel, plan: Plan, kind: str, sigma_L: float, sigma_M: float, trials: int,
                seed: int = 0, **kw) -> MonteCarlo:
    """Repeat `simulate_assembly`; per-node statistics are reported in plan order."""
    rng = np.random.default_rng(seed)
    order = plan.order
    errs, est_errs, seconds = [], [], []
    failures = redraws = 0
    for _ in range(trials):
        try:
            run = simulate_assembly(model, plan, kind, sigma_L, sigma_M, rng, **kw)
        except DegenerateBaseError:
            failures += 1
            continue
        redraws += run.redraws
        errs.append((run.truth - run.nominal)[order])
        est_errs.append(run.estimate_sq_errors[order])
        seconds.extend(run.update_seconds)
    if not errs:
        raise RuntimeError(f"every one of {trials} {kind} trials failed to close")
    e = np.asarray(errs)
    return MonteCarlo(kind, trials, failures, redraws, np.mean(np.sum(e ** 2, axis=2), axis=0),
                      np.einsum("tni,tnj->nij", e, e) / len(e), np.mean(est_errs, axis=0), seconds)
