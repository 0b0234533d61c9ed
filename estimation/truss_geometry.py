"""Node placement F_f for IPJR truss assembly (IPJR paper §2, eq. 1 and the appendix), its exact
derivatives, and the assembly-plan vocabulary the other truss modules share.

A floating node f is placed from its base triple (i, j, k) and three strut lengths by
trilateration.  The two mirror solutions are told apart by the paper's handedness rule: walking
i -> j -> k is counter-clockwise seen from f, i.e. f lies on the side of (Xj - Xi) x (Xk - Xi).
A base triple is therefore ordered; `orient_base` orders one from the design geometry.

The first three nodes (the starting triangle a, b, c) fix the frame -- the "3-2-1 gauge": a at
the origin, b on +x, c in the xy-plane with y > 0.  In the design frame the same gauge is
expressed by constraint rows (b moves only along a->b, c only within the plane a-b-c), so the
derivatives below work in any frame.

Derivatives are exact, by implicit differentiation of the strut constraints
|Xf - Xb|^2 = Lb^2:  (Xf - Xb) . (dXf - dXb) = Lb dLb, plus the gauge rows g . dXf = 0.
With A the matrix of those rows, dXf = A^-1 [L dL + (Xf - Xb) . dXb].
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Iterable, Sequence

import numpy as np

from lab.core.errors import LabError

__all__ = [
    "DegenerateBaseError",
    "DEGENERATE_RATIO",
    "Step",
    "Plan",
    "place_node",
    "place_step",
    "orient_base",
    "height_ratio",
    "gauge_rows",
    "step_sensitivity",
    "gauge_transform",
    "to_gauge",
    "build_positions",
    "plan_lengths",
]

# Below this height / longest-strut ratio a float-base tetrahedron is flat: no unique position.
DEGENERATE_RATIO = 1e-6


class DegenerateBaseError(LabError):
    """A base cannot place a node: colinear base, flat tetrahedron, or lengths that cannot close."""


# --------------------------------------------------------------------------------------------
# Plans


@dataclass(frozen=True)
class Step:
    """One assembly step <f, B_f>: node f placed on its ordered base (0 to 3 nodes)."""

    node: int
    base: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "node", int(self.node))
        object.__setattr__(self, "base", tuple(int(b) for b in self.base))


@dataclass(frozen=True)
class Plan:
    """An assembly sequence: the starting triangle (a, (), (a,), (a, b)) then floating steps, in an
    order where every base is built before its float.  Two plans with the same steps are the same
    plan whatever their order (the paper's parallel equivalence, eq. 8)."""

    steps: tuple[Step, ...]

    def __post_init__(self) -> None:
        steps = tuple(s if isinstance(s, Step) else Step(*s) for s in self.steps)
        object.__setattr__(self, "steps", steps)
        if len(steps) < 3:
            raise ValueError("a plan needs at least its starting triangle (3 steps)")
        a, b, c = steps[0].node, steps[1].node, steps[2].node
        if steps[0].base != () or steps[1].base != (a,) or set(steps[2].base) != {a, b} or len(steps[2].base) != 2:
            raise ValueError(f"a plan must start with a triangle: (a, ()), (b, (a,)), (c, (a, b)); got {steps[:3]}")
        built: set[int] = set()
        for s in steps:
            if s.node in built:
                raise ValueError(f"node {s.node} is placed twice")
            missing = [b for b in s.base if b not in built]
            if missing:
                raise ValueError(f"step {s.node} uses base nodes {missing} before they are built")
            if len(s.base) != len(set(s.base)):
                raise ValueError(f"step {s.node} has a repeated base node: {s.base}")
            if len(built) >= 3 and len(s.base) != 3:
                raise ValueError(f"floating node {s.node} needs a base triple, got {s.base}")
            built.add(s.node)

    @classmethod
    def from_triangle(cls, triangle: Sequence[int], floating: Iterable[tuple[int, Sequence[int]]]) -> "Plan":
        a, b, c = (int(v) for v in triangle)
        return cls((Step(a), Step(b, (a,)), Step(c, (a, b)), *(Step(f, tuple(B)) for f, B in floating)))

    @property
    def triangle(self) -> tuple[int, int, int]:
        return (self.steps[0].node, self.steps[1].node, self.steps[2].node)

    @property
    def order(self) -> list[int]:
        return [s.node for s in self.steps]

    @cached_property
    def base_of(self) -> dict[int, tuple[int, ...]]:
        return {s.node: s.base for s in self.steps}

    @cached_property
    def position(self) -> dict[int, int]:
        """Index of each node's step in this plan."""
        return {s.node: k for k, s in enumerate(self.steps)}

    @cached_property
    def active_edges(self) -> list[tuple[int, int]]:
        """The struts set by IPJRs (E_A), in plan order: one column of the Jacobian each."""
        return [(b, s.node) for s in self.steps for b in s.base]

    @cached_property
    def times(self) -> dict[int, int]:
        """Parallel assembly time t_f = 1 + max t over the base (eq. 6); triangle at t = 1, 2, 3."""
        t: dict[int, int] = {}
        for k, s in enumerate(self.steps):
            t[s.node] = k + 1 if k < 3 else 1 + max(t[b] for b in s.base)
        return t

    @cached_property
    def layers(self) -> list[list[int]]:
        """The parallel assembly sequence P: nodes grouped by t (eq. 7)."""
        out: dict[int, list[int]] = {}
        for s in self.steps:
            out.setdefault(self.times[s.node], []).append(s.node)
        return [sorted(out[t]) for t in sorted(out)]

    def key(self) -> frozenset:
        """Order-free identity: the triangle (ordered, it fixes the gauge) and the step set."""
        return frozenset([("triangle", self.triangle), *((s.node, s.base) for s in self.steps[3:])])

    def to_json(self) -> dict:
        return {
            "starting_triangle": list(self.triangle),
            "steps": [{"node": s.node, "base": list(s.base), "t": self.times[s.node]} for s in self.steps],
            "layers": self.layers,
        }


# --------------------------------------------------------------------------------------------
# F_f


def height_ratio(xf: np.ndarray, xi: np.ndarray, xj: np.ndarray, xk: np.ndarray) -> float:
    """Signed height of f above plane (i, j, k) (positive on the handed side) over the longest
    float-base strut; 0 for a colinear base."""
    n = np.cross(xj - xi, xk - xi)
    scale = max(np.linalg.norm(xf - xi), np.linalg.norm(xf - xj), np.linalg.norm(xf - xk))
    nn = np.linalg.norm(n)
    if scale == 0.0 or nn <= 1e-12 * scale * scale:
        return 0.0
    return float(np.dot(xf - xi, n) / nn / scale)


def orient_base(nodes: np.ndarray, f: int, base: Sequence[int]) -> tuple[int, int, int]:
    """Order a base triple so that the design position of f is on its right-hand side."""
    i, j, k = (int(b) for b in base)
    r = height_ratio(nodes[f], nodes[i], nodes[j], nodes[k])
    if abs(r) < DEGENERATE_RATIO:
        raise DegenerateBaseError(f"node {f} is (nearly) in the plane of base {tuple(base)}: "
                                  f"height/strut = {abs(r):.2e} < {DEGENERATE_RATIO:g}")
    return (i, j, k) if r > 0 else (i, k, j)


def place_node(xi: np.ndarray, xj: np.ndarray, xk: np.ndarray, li: float, lj: float, lk: float) -> np.ndarray:
    """F_f: the position at distances (li, lj, lk) from (xi, xj, xk), on the handed side."""
    xi, xj, xk = (np.asarray(v, dtype=float) for v in (xi, xj, xk))
    d_vec = xj - xi
    d = np.linalg.norm(d_vec)
    scale = max(d, li, lj, lk)
    if d <= DEGENERATE_RATIO * scale:
        raise DegenerateBaseError(f"base nodes i and j coincide (|Xj - Xi| = {d:.3g} m)")
    ex = d_vec / d
    w = xk - xi
    ix = float(np.dot(ex, w))
    wy = w - ix * ex
    jy = np.linalg.norm(wy)
    if jy <= DEGENERATE_RATIO * scale:
        raise DegenerateBaseError(f"base triple is colinear (k is {jy:.3g} m off the line i-j)")
    ey = wy / jy
    ez = np.cross(ex, ey)
    x = (li * li - lj * lj + d * d) / (2.0 * d)
    y = (li * li - lk * lk + ix * ix + jy * jy - 2.0 * ix * x) / (2.0 * jy)
    z2 = li * li - x * x - y * y
    if z2 < (DEGENERATE_RATIO * scale) ** 2:
        if z2 < 0:
            raise DegenerateBaseError(f"strut lengths ({li:.6g}, {lj:.6g}, {lk:.6g}) m cannot meet "
                                      f"over this base (z^2 = {z2:.3g} m^2)")
        raise DegenerateBaseError(f"node would lie in the base plane (height {np.sqrt(z2):.3g} m)")
    return xi + x * ex + y * ey + np.sqrt(z2) * ez


def place_step(base_positions: Sequence[np.ndarray], lengths: Sequence[float]) -> np.ndarray:
    """Place a node in the 3-2-1 gauge frame from 0 to 3 base nodes (the starting triangle cases:
    origin; on +x from a; in the xy-plane, y > 0, from a and b)."""
    nb = len(base_positions)
    if nb == 0:
        return np.zeros(3)
    if nb == 1:
        return np.asarray(base_positions[0], dtype=float) + np.array([float(lengths[0]), 0.0, 0.0])
    if nb == 2:
        xa, xb = (np.asarray(v, dtype=float) for v in base_positions)
        la, lb = (float(v) for v in lengths)
        e = xb - xa
        e[2] = 0.0
        d = np.linalg.norm(e)
        if d <= DEGENERATE_RATIO * max(la, lb, d):
            raise DegenerateBaseError("the first two nodes of the starting triangle coincide")
        e /= d
        x = (la * la - lb * lb + d * d) / (2.0 * d)
        y2 = la * la - x * x
        if y2 <= (DEGENERATE_RATIO * max(la, lb, d)) ** 2:
            raise DegenerateBaseError(f"starting triangle lengths ({la:.6g}, {lb:.6g}, {d:.6g}) m do not close")
        perp = np.array([-e[1], e[0], 0.0])
        return xa + x * e + np.sqrt(y2) * perp
    return place_node(*base_positions, *lengths)


# --------------------------------------------------------------------------------------------
# Exact local sensitivities


def gauge_rows(triangle_positions: Sequence[np.ndarray], slot: int) -> np.ndarray:
    """Directions in which starting-triangle node number `slot` (0, 1, 2) may not move."""
    if slot == 0:
        return np.eye(3)
    xa, xb = triangle_positions[0], triangle_positions[1]
    ex = (xb - xa) / np.linalg.norm(xb - xa)
    if slot == 1:
        helper = np.eye(3)[np.argmin(np.abs(ex))]
        n1 = np.cross(ex, helper)
        n1 /= np.linalg.norm(n1)
        return np.vstack([n1, np.cross(ex, n1)])
    n = np.cross(xb - xa, triangle_positions[2] - xa)
    return (n / np.linalg.norm(n))[None, :]


def step_sensitivity(xf: np.ndarray, base_positions: Sequence[np.ndarray], lengths: Sequence[float],
                     constraint_rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact derivatives of a placed node: (M, C) with dXf = sum_b M[b] dXb + C dL.

    M has shape (nb, 3, 3), C (3, nb).  `constraint_rows` are the gauge rows of starting-triangle
    nodes (see `gauge_rows`); floating nodes have none.  Raises DegenerateBaseError where the
    derivative does not exist."""
    nb = len(base_positions)
    u = np.asarray([xf - xb for xb in base_positions], dtype=float).reshape(nb, 3)
    rows = u if constraint_rows is None else np.vstack([u, constraint_rows])
    if rows.shape[0] != 3:
        raise ValueError(f"{nb} struts and {rows.shape[0] - nb} gauge rows do not fix 3 coordinates")
    norms = np.linalg.norm(rows, axis=1)
    vol = abs(np.linalg.det(rows)) / np.prod(norms) if np.all(norms > 0) else 0.0
    if vol < DEGENERATE_RATIO:
        raise DegenerateBaseError(f"degenerate placement (normalised volume {vol:.2e})")
    a_inv = np.linalg.inv(rows)
    cols = a_inv[:, :nb]  # (3, nb)
    C = cols * np.asarray(lengths, dtype=float)[None, :]
    M = np.einsum("ib,bj->bij", cols, u)  # M[b] = A^-1 e_b u_b^T
    return M, C


# --------------------------------------------------------------------------------------------
# Frames and the open-loop map F_V


def gauge_transform(nodes: np.ndarray, triangle: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """(R, origin) with p_gauge = R @ (p_design - origin): a at 0, b on +x, c in xy with y > 0."""
    a, b, c = triangle
    ex = nodes[b] - nodes[a]
    ex = ex / np.linalg.norm(ex)
    w = nodes[c] - nodes[a]
    ey = w - np.dot(w, ex) * ex
    ey = ey / np.linalg.norm(ey)
    ez = np.cross(ex, ey)
    return np.vstack([ex, ey, ez]), nodes[a].copy()


def to_gauge(nodes: np.ndarray, triangle: Sequence[int]) -> np.ndarray:
    """Design positions expressed in the starting triangle's gauge frame."""
    R, o = gauge_transform(nodes, triangle)
    return (nodes - o) @ R.T


def plan_lengths(nodes: np.ndarray, plan: Plan) -> np.ndarray:
    """Nominal active-strut lengths L_E, in the plan's column order."""
    e = np.asarray(plan.active_edges, dtype=int)
    return np.linalg.norm(nodes[e[:, 0]] - nodes[e[:, 1]], axis=1)


def build_positions(plan: Plan, lengths: np.ndarray, n_nodes: int | None = None) -> np.ndarray:
    """F_V: the gauge-frame structure built open loop from the active strut lengths (eq. 11).
    Unbuilt nodes stay at 0 (§2.3)."""
    n = n_nodes if n_nodes is not None else max(plan.order) + 1
    x = np.zeros((n, 3))
    col = 0
    for s in plan.steps:
        nb = len(s.base)
        x[s.node] = place_step([x[b] for b in s.base], lengths[col:col + nb])
        col += nb
    return x
