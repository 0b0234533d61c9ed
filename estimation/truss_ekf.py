"""EKF assembly, the estimator of the earlier IPJR work (Komendera & Correll 2014), as the IPJR
paper describes it (§4, §6.3, §7): an online filter whose state is the built nodes' positions.

Per step (our reading; the 2014 paper itself is not in our sources):
- predict: augment the state with the new node placed by F_f on the current estimate of its base
  with the commanded lengths; its covariance is the linearised propagation of the base covariance
  and of the strut noise sigma_L (cross-covariances with the rest of the structure kept);
- update: only the latest measurements -- the struts between the new node and the structure --
  each |X_f - X_i| + N(0, sigma_M^2), linearised at the prediction; one EKF update (Joseph form).
Earlier priors and measurements are never re-linearised: that is what separates it from the MLE,
and why it drifts when strut errors make the geometry non-linear (the "stunted tower" of §6.3).
"""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from estimation.truss_geometry import Step, place_step, step_sensitivity
from estimation.truss_mle import StepTiming, TrussAssemblyFrame
from lab.core.structures.trusses import TrussModel

__all__ = ["TrussEKF"]

_GAUGE_ROWS = {1: np.array([[0.0, 1, 0], [0, 0, 1]]), 2: np.array([[0.0, 0, 1]])}


class TrussEKF(TrussAssemblyFrame):
    """Same step API as `TrussMLE`: lengths_to_command, struts_to_measure, add_step, estimate."""

    def __init__(self, model: TrussModel, plan, sigma_L: float, sigma_M: float) -> None:
        super().__init__(model, plan)
        if not (sigma_L > 0 and sigma_M > 0):
            raise ValueError(f"sigma_L and sigma_M must be positive metres, got {sigma_L}, {sigma_M}")
        self.sigma_L, self.sigma_M = float(sigma_L), float(sigma_M)
        self.slot: dict[int, int] = {}
        self.x = np.zeros(0)
        self.P = np.zeros((0, 0))
        self._xfull = np.full((model.n_nodes, 3), np.nan)
        self.timings: list[StepTiming] = []

    def current(self) -> np.ndarray:
        return self._xfull

    def estimate(self) -> np.ndarray:
        return self._xfull.copy()

    def covariances(self) -> dict[int, np.ndarray]:
        return {f: self.P[3 * s:3 * s + 3, 3 * s:3 * s + 3].copy() for f, s in self.slot.items()}

    def add_step(self, step: Step, commanded: Sequence[float], measured: dict[tuple[int, int], float]) -> StepTiming:
        t0 = time.perf_counter()
        self._check_next(step)
        commanded = np.asarray(commanded, dtype=float)
        f = step.node
        n_slot = len(self.built)
        base_pos = [self._xfull[b] for b in step.base]
        xf = place_step(base_pos, commanded)

        # Predict: augment state and covariance.
        k = 3 * n_slot
        P = np.zeros((k + 3, k + 3))
        P[:k, :k] = self.P
        if step.base:
            rows = _GAUGE_ROWS.get(n_slot)
            M, C = step_sensitivity(xf, base_pos, commanded, rows)
            G = np.zeros((3, k))  # dX_f / d(state)
            for b, Mb in zip(step.base, M):
                s = self.slot[b]
                G[:, 3 * s:3 * s + 3] += Mb
            cross = G @ self.P
            P[k:, :k] = cross
            P[:k, k:] = cross.T
            P[k:, k:] = G @ self.P @ G.T + self.sigma_L ** 2 * C @ C.T
        self.x = np.concatenate([self.x, xf])
        self.P = P
        self.slot[f] = n_slot
        self._mark_built(f)

        # Update with the latest measurements only.
        if measured:
            z, h, H = [], [], []
            for (i, j), m in measured.items():
                other = j if i == f else i
                if f not in (i, j) or other not in self.slot:
                    raise ValueError(f"measurement ({i}, {j}) must join node {f} to a built node")
                d = self.x[3 * self.slot[f]:3 * self.slot[f] + 3] - self.x[3 * self.slot[other]:3 * self.slot[other] + 3]
                r = np.linalg.norm(d)
                row = np.zeros(len(self.x))
                row[3 * self.slot[f]:3 * self.slot[f] + 3] = d / r
                row[3 * self.slot[other]:3 * self.slot[other] + 3] = -d / r
                z.append(m)
                h.append(r)
                H.append(row)
            H = np.asarray(H)
            R = self.sigma_M ** 2 * np.eye(len(z))
            S = H @ self.P @ H.T + R
            K = np.linalg.solve(S, H @ self.P).T
            self.x = self.x + K @ (np.asarray(z) - np.asarray(h))
            IKH = np.eye(len(self.x)) - K @ H
            self.P = IKH @ self.P @ IKH.T + K @ R @ K.T
        for node, s in self.slot.items():
            self._xfull[node] = self.x[3 * s:3 * s + 3]
        timing = StepTiming(f, len(self.built), time.perf_counter() - t0, 1)
        self.timings.append(timing)
        return timing
