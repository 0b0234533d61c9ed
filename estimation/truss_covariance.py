"""Open-loop error model of an assembly plan (IPJR paper §2.3-2.5): Sigma_X = sigma_L^2 J J^T with
J = dF_V/dL_E at the nominal lengths, and the metric Tr Sigma_X = sigma_L^2 sum (dX/dL)^2 (eq. 17).

The paper approximated J by central differences (§2.5, 2 * (3N-6) open-loop builds).  Here J is
exact: forward propagation of the local implicit derivatives of F_f (truss_geometry), one small
solve per step, J_f = sum_b M_fb J_b + C_f on the node's own columns.  Central differences stay
as a test oracle (`finite_difference_jacobian`).

Everything is computed in the design frame with the starting triangle's gauge expressed as
constraint rows; the trace is frame-independent, and per-node covariances can be rotated into
the gauge frame (`node_covariances(..., frame="gauge")`) to compare with simulations.
"""

from __future__ import annotations

import math

import numpy as np

from estimation.truss_geometry import (
    DegenerateBaseError,
    Plan,
    build_positions,
    gauge_rows,
    gauge_transform,
    plan_lengths,
    step_sensitivity,
)

__all__ = [
    "LocalSensitivities",
    "plan_jacobian",
    "trace",
    "node_traces",
    "node_covariances",
    "finite_difference_jacobian",
    "jacobian_in_gauge",
]


class LocalSensitivities:
    """(M, C) of every step at the nominal geometry, cached: a floating step's derivatives depend
    only on (f, base), so sequencing reuses them across thousands of candidate plans."""

    def __init__(self, nodes: np.ndarray) -> None:
        self.nodes = np.asarray(nodes, dtype=float)
        self._floating: dict[tuple[int, tuple[int, ...]], tuple[np.ndarray, np.ndarray] | None] = {}
        self._triangle: dict[tuple[tuple[int, int, int], int], tuple[np.ndarray, np.ndarray]] = {}

    def floating(self, f: int, base: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        key = (f, base)
        hit = self._floating.get(key, False)
        if hit is False:
            x = self.nodes
            lengths = [np.linalg.norm(x[f] - x[b]) for b in base]
            try:
                hit = step_sensitivity(x[f], [x[b] for b in base], lengths)
            except DegenerateBaseError:
                hit = None
            self._floating[key] = hit
        if hit is None:
            raise DegenerateBaseError(f"node {f} on base {base} is degenerate")
        return hit

    def triangle(self, tri: tuple[int, int, int], slot: int) -> tuple[np.ndarray, np.ndarray]:
        key = (tri, slot)
        hit = self._triangle.get(key)
        if hit is None:
            x = self.nodes
            pos = [x[v] for v in tri]
            f = tri[slot]
            base = tri[:slot]
            if slot == 0:
                hit = (np.zeros((0, 3, 3)), np.zeros((3, 0)))
            else:
                lengths = [np.linalg.norm(x[f] - x[b]) for b in base]
                hit = step_sensitivity(x[f], [x[b] for b in base], lengths, gauge_rows(pos, slot))
            self._triangle[key] = hit
        return hit

    def step(self, plan: Plan, k: int) -> tuple[np.ndarray, np.ndarray]:
        s = plan.steps[k]
        return self.triangle(plan.triangle, k) if k < 3 else self.floating(s.node, s.base)


def plan_jacobian(nodes: np.ndarray, plan: Plan, sens: LocalSensitivities | None = None,
                  n_nodes: int | None = None) -> np.ndarray:
    """J with shape (N, 3, 3N'-6): row block per node (design frame), one column per active strut
    in plan order.  Nodes the plan does not build have zero rows."""
    sens = sens or LocalSensitivities(nodes)
    n = n_nodes if n_nodes is not None else len(nodes)
    ncols = len(plan.active_edges)
    J = np.zeros((n, 3, ncols))
    col = 0
    for k, s in enumerate(plan.steps):
        M, C = sens.step(plan, k)
        nb = len(s.base)
        if nb:
            J[s.node] = np.tensordot(M, J[list(s.base)], axes=([0, 2], [0, 1]))
            J[s.node, :, col:col + nb] += C
        col += nb
    return J


def node_traces(nodes: np.ndarray, plan: Plan, sigma_L: float = 1.0,
                sens: LocalSensitivities | None = None) -> np.ndarray:
    """Per-node E|X_f - X̄_f|^2 under open-loop assembly (inf where a step is degenerate)."""
    try:
        J = plan_jacobian(nodes, plan, sens)
    except DegenerateBaseError:
        return np.full(len(nodes), math.inf)
    return sigma_L ** 2 * np.einsum("nij,nij->n", J, J)


def trace(nodes: np.ndarray, plan: Plan, sigma_L: float = 1.0, sens: LocalSensitivities | None = None) -> float:
    """Tr Sigma_X of the plan (eq. 17), in m^2 when sigma_L is in m; inf for a degenerate step."""
    return float(np.sum(node_traces(nodes, plan, sigma_L, sens)))


def node_covariances(nodes: np.ndarray, plan: Plan, sigma_L: float = 1.0, frame: str = "gauge",
                     sens: LocalSensitivities | None = None) -> np.ndarray:
    """Per-node 3x3 open-loop covariances, in the starting triangle's gauge frame ("gauge") or the
    design frame ("design")."""
    J = plan_jacobian(nodes, plan, sens)
    cov = sigma_L ** 2 * np.einsum("nik,njk->nij", J, J)
    if frame == "design":
        return cov
    if frame != "gauge":
        raise ValueError(f"frame must be 'gauge' or 'design', got {frame!r}")
    R, _ = gauge_transform(np.asarray(nodes, float), plan.triangle)
    return np.einsum("ab,nbc,dc->nad", R, cov, R)


def finite_difference_jacobian(nodes: np.ndarray, plan: Plan, h: float = 5e-7) -> np.ndarray:
    """Central-difference J in the gauge frame (the paper's eq. 19; a test oracle only)."""
    from estimation.truss_geometry import to_gauge

    nominal = to_gauge(np.asarray(nodes, float), plan.triangle)
    L = plan_lengths(nominal, plan)
    n = len(nodes)
    J = np.zeros((n, 3, len(L)))
    for c in range(len(L)):
        up, down = L.copy(), L.copy()
        up[c] += h
        down[c] -= h
        J[:, :, c] = (build_positions(plan, up, n) - build_positions(plan, down, n)) / (2 * h)
    return J


def jacobian_in_gauge(nodes: np.ndarray, plan: Plan, sens: LocalSensitivities | None = None) -> np.ndarray:
    """The exact J rotated into the gauge frame (comparable with `finite_difference_jacobian`)."""
    R, _ = gauge_transform(np.asarray(nodes, float), plan.triangle)
    return np.einsum("ab,nbk->nak", R, plan_jacobian(nodes, plan, sens))
