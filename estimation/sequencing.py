"""Assembly sequencing for IPJR trusses (IPJR paper §3, Table 2).

The paper's algorithms, by name: `three_cliques`, `random_sequence` (Q = "any" / "minsteps"),
`possible_next_nodes`, `all_central_triangles`, `greedy_assembly`, `adjacent_sequences`,
`assembly_local_search`, `find_locally_optimal_sequence`; plus `enumerate_plans` (all sequences of
a small truss, §6.4) and `validate_plan`.

Speed (the paper's §7 asks for it: "reduce the number of times the covariance is calculated"):
- traces use the exact forward-propagated Jacobian (truss_covariance), unit sigma_L, with every
  step's local derivatives cached;
- greedy steps add ||J_f||^2 of one node, evaluated for all candidates in one batched product;
- local search scores a base swap at node f without rebuilding: the new rows of f's descendants
  are J_d + P_df D (P_df the 3x3 transfer from f to d, D the change of J_f), so the trace change is
  2 <G_f, D> + <D, Q_f D> with G_f = sum_d P_df^T J_d and Q_f = sum_d P_df^T P_df, computed once
  per descent step for all f together;
- a change of starting triangle keeps the floating steps, so the 6 orderings of one triangle
  share one propagation (the triangle's columns are disjoint from the rest).
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field
from typing import Iterator, Sequence

import numpy as np

from estimation.truss_covariance import LocalSensitivities, plan_jacobian
from estimation.truss_geometry import DEGENERATE_RATIO, DegenerateBaseError, Plan, Step, height_ratio
from lab.core.structures.trusses import TrussModel

__all__ = [
    "three_cliques",
    "ordered_triangles",
    "possible_next_nodes",
    "random_sequence",
    "parallel_length",
    "all_central_triangles",
    "greedy_assembly",
    "adjacent_sequences",
    "assembly_local_search",
    "find_locally_optimal_sequence",
    "enumerate_plans",
    "validate_plan",
    "plan_trace",
    "Planner",
    "SearchResult",
]


# --------------------------------------------------------------------------------------------
# Topology


def three_cliques(model: TrussModel, edges: Sequence[tuple[int, int]] | None = None) -> list[tuple[int, int, int]]:
    """All triangles (i < j < k) of the strut graph (or of `edges`), via adjacency lists: O(N)."""
    if edges is None:
        nb = model.neighbours
        edge_list = model.edges
    else:
        sets: list[set[int]] = [set() for _ in range(model.n_nodes)]
        edge_list = sorted({(min(i, j), max(i, j)) for i, j in edges})
        for i, j in edge_list:
            sets[i].add(j)
            sets[j].add(i)
        nb = sets
    return [(i, j, k) for i, j in edge_list for k in sorted(nb[i] & nb[j]) if k > j]


def ordered_triangles(tri: Sequence[int]) -> list[tuple[int, int, int]]:
    """The 6 orderings of a triangle: each is a distinct gauge (a fixed, b on an axis, c in a plane)."""
    return [tuple(p) for p in itertools.permutations(tri)]  # type: ignore[misc]


class _Geometry:
    """Oriented, non-degenerate bases of each node, cached (pure function of the design)."""

    def __init__(self, model: TrussModel, min_ratio: float = DEGENERATE_RATIO) -> None:
        self.model = model
        self.min_ratio = min_ratio
        self._base: dict[tuple[int, frozenset[int]], tuple[int, int, int] | None] = {}

    def oriented(self, f: int, base: Sequence[int]) -> tuple[int, int, int] | None:
        key = (f, frozenset(base))
        hit = self._base.get(key, False)
        if hit is False:
            i, j, k = sorted(base)
            x = self.model.nodes
            r = height_ratio(x[f], x[i], x[j], x[k])
            hit = None if abs(r) < self.min_ratio else ((i, j, k) if r > 0 else (i, k, j))
            self._base[key] = hit
        return hit


def possible_next_nodes(model: TrussModel, made: set[int] | frozenset[int], candidates: Sequence[int] | None = None,
                        geometry: _Geometry | None = None) -> list[Step]:
    """Every step (f, B) that can be added: f not made, B a non-degenerate 3-subset of f's made
    neighbours, ordered by the handedness rule."""
    geometry = geometry or _Geometry(model)
    nb = model.neighbours
    if candidates is None:
        candidates = sorted({j for i in made for j in nb[i]} - set(made))
    out: list[Step] = []
    for f in candidates:
        if f in made:
            continue
        built = sorted(nb[f] & made)
        if len(built) < 3:
            continue
        for b in itertools.combinations(built, 3):
            o = geometry.oriented(f, b)
            if o is not None:
                out.append(Step(f, o))
    return out


def random_sequence(model: TrussModel, triangle: Sequence[int], mode: str = "any",
                    rng: np.random.Generator | None = None, geometry: _Geometry | None = None) -> Plan | None:
    """RandomSequence: "any" adds one random possible step at a time; "minsteps" floods, adding
    every possible node at once (one random base each), so its layers are the fewest possible.
    None when the truss cannot be completed from this triangle ("No Assembly Sequence")."""
    if mode not in ("any", "minsteps"):
        raise ValueError(f"mode must be 'any' or 'minsteps', got {mode!r}")
    rng = rng or np.random.default_rng()
    geometry = geometry or _Geometry(model)
    a, b, c = (int(v) for v in triangle)
    if not (model.has_edge(a, b) and model.has_edge(a, c) and model.has_edge(b, c)):
        raise ValueError(f"{tuple(triangle)} is not a triangle of struts")
    steps = [Step(a), Step(b, (a,)), Step(c, (a, b))]
    made = {a, b, c}
    while len(made) < model.n_nodes:
        s_next = possible_next_nodes(model, made, geometry=geometry)
        if not s_next:
            return None
        if mode == "any":
            chosen = [s_next[int(rng.integers(len(s_next)))]]
        else:
            by_node: dict[int, list[Step]] = {}
            for s in s_next:
                by_node.setdefault(s.node, []).append(s)
            chosen = [opts[int(rng.integers(len(opts)))] for _, opts in sorted(by_node.items())]
        steps.extend(chosen)
        made.update(s.node for s in chosen)
    return Plan(tuple(steps))


def parallel_length(plan: Plan) -> int:
    """||P||: the number of parallel assembly layers (max t)."""
    return max(plan.times.values())


def all_central_triangles(model: TrussModel, rng: np.random.Generator | None = None,
                          geometry: _Geometry | None = None) -> list[tuple[int, int, int]]:
    """AllCentralTriangles: the ordered starting triangles whose stepwise-minimal sequence has the
    fewest layers.  (Layers do not depend on the order within a triangle, so each unordered
    triangle is flooded once.)"""
    rng = rng or np.random.default_rng(0)
    geometry = geometry or _Geometry(model)
    best, central = math.inf, []
    for tri in three_cliques(model):
        p = random_sequence(model, tri, "minsteps", rng, geometry)
        if p is None:
            continue
        n = parallel_length(p)
        if n < best:
            best, central = n, [tri]
        elif n == best:
            central.append(tri)
    return [o for tri in central for o in ordered_triangles(tri)]


def validate_plan(model: TrussModel, plan: Plan) -> list[str]:
    """Everything wrong with a plan for this truss ([] when it is valid): every node placed once,
    on a base of built neighbours, ordered by the handedness rule, not degenerate."""
    problems = []
    order = plan.order
    if sorted(order) != list(range(model.n_nodes)):
        problems.append(f"plan places nodes {sorted(order)}, the truss has 0..{model.n_nodes - 1}")
    a, b, c = plan.triangle
    for i, j in ((a, b), (a, c), (b, c)):
        if not model.has_edge(i, j):
            problems.append(f"starting triangle edge ({i}, {j}) is not a strut")
    x = model.nodes
    for s in plan.steps[3:]:
        for bnode in s.base:
            if not model.has_edge(s.node, bnode):
                problems.append(f"node {s.node}: base node {bnode} is not joined to it by a strut")
        r = height_ratio(x[s.node], *(x[v] for v in s.base))
        if abs(r) < DEGENERATE_RATIO:
            problems.append(f"node {s.node}: base {s.base} is degenerate (height ratio {r:.2e})")
        elif r < 0:
            problems.append(f"node {s.node}: base {s.base} is ordered against the handedness rule")
    return problems


def plan_trace(model: TrussModel, plan: Plan, sigma_L: float = 1.0, sens: LocalSensitivities | None = None) -> float:
    """Open-loop trace of a plan (m^2 for sigma_L in m); inf when a step is degenerate."""
    try:
        J = plan_jacobian(model.nodes, plan, sens)
    except DegenerateBaseError:
        return math.inf
    return float(sigma_L ** 2 * np.sum(J * J))


# --------------------------------------------------------------------------------------------
# Greedy assembly


@dataclass
class SearchResult:
    """A plan with its open-loop trace per unit sigma_L^2 and how the search got there."""

    plan: Plan
    trace_unit: float
    history: list[float] = field(default_factory=list)  # unit traces after each descent step
    seconds: float = 0.0
    evaluated: int = 0

    def trace(self, sigma_L: float) -> float:
        return self.trace_unit * sigma_L ** 2


class Planner:
    """Sequencing on one truss, with the local derivatives and base geometry cached."""

    def __init__(self, model: TrussModel, min_ratio: float = DEGENERATE_RATIO) -> None:
        self.model = model
        self.geometry = _Geometry(model, min_ratio)
        self.sens = LocalSensitivities(model.nodes)
        self.ncols = 3 * model.n_nodes - 6

    # -- helpers ---------------------------------------------------------------------------
    def _sens(self, f: int, base: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray] | None:
        try:
            return self.sens.floating(f, base)
        except DegenerateBaseError:
            return None

    def trace_unit(self, plan: Plan) -> float:
        return plan_trace(self.model, plan, 1.0, self.sens)

    # -- GreedyAssembly ----------------------------------------------------------------------
    def greedy(self, triangle: Sequence[int]) -> SearchResult | None:
        """GreedyAssembly: from the triangle, repeatedly add the possible step whose node adds the
        least trace (earlier nodes' errors do not depend on later steps, so that is the partial
        structure's least trace)."""
        t0 = time.perf_counter()
        a, b, c = (int(v) for v in triangle)
        n = self.model.n_nodes
        J = np.zeros((n, 3, self.ncols))
        steps = [Step(a), Step(b, (a,)), Step(c, (a, b))]
        col = 0
        total = 0.0
        for k, s in enumerate(steps):
            M, C = self.sens.triangle((a, b, c), k)
            nb = len(s.base)
            if nb:
                J[s.node] = np.tensordot(M, J[list(s.base)], axes=([0, 2], [0, 1]))
                J[s.node, :, col:col + nb] += C
            col += nb
            total += float(np.sum(J[s.node] ** 2))
        made = {a, b, c}
        evaluated = 0
        while len(made) < n:
            cands = [(s, self._sens(s.node, s.base)) for s in possible_next_nodes(self.model, made, geometry=self.geometry)]
            cands = [(s, mc) for s, mc in cands if mc is not None]
            if not cands:
                return None
            Ms = np.stack([mc[0] for _, mc in cands])  # (K, 3, 3, 3)
            Cs = np.stack([mc[1] for _, mc in cands])  # (K, 3, 3)
            Jb = J[np.array([s.base for s, _ in cands])]  # (K, 3, 3, ncols)
            prop = np.einsum("kbij,kbjc->kic", Ms, Jb)
            scores = np.einsum("kic,kic->k", prop, prop) + np.einsum("kij,kij->k", Cs, Cs)
            evaluated += len(cands)
            best = int(np.argmin(scores))
            s, (M, C) = cands[best]
            J[s.node] = prop[best]
            J[s.node, :, col:col + 3] += C
            col += 3
            total += float(scores[best])
            steps.append(s)
            made.add(s.node)
        return SearchResult(Plan(tuple(steps)), total, [total], time.perf_counter() - t0, evaluated)

    # -- AdjacentSequences --------------------------------------------------------------------
    def _descendants(self, plan: Plan) -> dict[int, set[int]]:
        children: dict[int, list[int]] = {s.node: [] for s in plan.steps}
        for s in plan.steps:
            for b in s.base:
                children[b].append(s.node)
        desc: dict[int, set[int]] = {}
        for s in reversed(plan.steps):
            d: set[int] = set()
            for ch in children[s.node]:
                d.add(ch)
                d |= desc[ch]
            desc[s.node] = d
        return desc

    def _rebuild_from_edges(self, active: Sequence[tuple[int, int]], triangle: tuple[int, int, int]) -> Plan | None:
        """The unique plan that uses exactly the struts `active` from another starting triangle
        (RandomSequence on E_A), or None if that triangle cannot build it."""
        n = self.model.n_nodes
        nb: list[set[int]] = [set() for _ in range(n)]
        for i, j in active:
            nb[i].add(j)
            nb[j].add(i)
        a, b, c = triangle
        steps = [Step(a), Step(b, (a,)), Step(c, (a, b))]
        made = {a, b, c}
        frontier = True
        while len(made) < n and frontier:
            frontier = False
            layer = []
            for f in range(n):
                if f in made:
                    continue
                built = nb[f] & made
                if len(built) > 3:
                    return None
                if len(built) == 3:
                    o = self.geometry.oriented(f, tuple(built))
                    if o is None:
                        return None
                    layer.append(Step(f, o))
            if layer:
                frontier = True
                steps.extend(layer)
                made.update(s.node for s in layer)
        return Plan(tuple(steps)) if len(made) == n else None

    def base_swaps(self, plan: Plan) -> list[Step]:
        """Single-step changes: node f on another base drawn from the nodes that do not depend on f."""
        desc = self._descendants(plan)
        nb = self.model.neighbours
        out = []
        for s in plan.steps[3:]:
            independent = nb[s.node] - desc[s.node] - {s.node}
            for b in itertools.combinations(sorted(independent), 3):
                o = self.geometry.oriented(s.node, b)
                if o is not None and o != s.base:
                    out.append(Step(s.node, o))
        return out

    def triangle_swaps(self, plan: Plan) -> list[Plan]:
        """Plans with the same active struts E_A and another starting triangle."""
        active = [(min(i, j), max(i, j)) for i, j in plan.active_edges]
        out = []
        for tri in three_cliques(self.model, active):
            base_plan = None
            for o in ordered_triangles(tri):
                if o == plan.triangle:
                    continue
                if base_plan is None:
                    base_plan = self._rebuild_from_edges(active, o)
                    if base_plan is None:
                        break
                out.append(Plan((Step(o[0]), Step(o[1], (o[0],)), Step(o[2], (o[0], o[1])),
                                 *base_plan.steps[3:])))
        return out

    def adjacent(self, plan: Plan) -> list[Plan]:
        """AdjacentSequences: every plan one base swap or one starting-triangle change away."""
        out = self.triangle_swaps(plan)
        for s in self.base_swaps(plan):
            out.append(_replace_step(plan, s))
        return out

    # -- AssemblyLocalSearch --------------------------------------------------------------------
    def _swap_scores(self, plan: Plan, J: np.ndarray, swaps: list[Step]) -> np.ndarray:
        """Exact trace change of each base swap (see module docstring), all at once."""
        n = self.model.n_nodes
        # Transfer matrices P[d, f] = dX_d / dX_f along the plan's DAG, forward in plan order.
        P = np.zeros((n, n, 3, 3))
        eye = np.eye(3)
        for k, s in enumerate(plan.steps):
            if k >= 3:
                M, _ = self.sens.floating(s.node, s.base)
                P[s.node] = np.einsum("bij,bfjk->fik", M, P[list(s.base)])
            P[s.node, s.node] = eye
        G = np.einsum("dfji,djc->fic", P, J)  # sum_d P_df^T J_d
        Q = np.einsum("dfji,dfjk->fik", P, P)  # sum_d P_df^T P_df
        col_of = {}
        col = 0
        for s in plan.steps:
            col_of[s.node] = col
            col += len(s.base)
        scores = np.full(len(swaps), math.inf)
        by_node: dict[int, list[int]] = {}
        for idx, s in enumerate(swaps):
            by_node.setdefault(s.node, []).append(idx)
        for f, idxs in by_node.items():
            old = plan.base_of[f]
            M0, C0 = self.sens.floating(f, old)
            J0 = np.tensordot(M0, J[list(old)], axes=([0, 2], [0, 1]))
            c = col_of[f]
            J0[:, c:c + 3] += C0
            valid = [(i, self._sens(f, swaps[i].base)) for i in idxs]
            valid = [(i, mc) for i, mc in valid if mc is not None]
            if not valid:
                continue
            Ms = np.stack([mc[0] for _, mc in valid])
            Jb = J[np.array([swaps[i].base for i, _ in valid])]
            Jn = np.einsum("kbij,kbjc->kic", Ms, Jb)
            Jn[:, :, c:c + 3] += np.stack([mc[1] for _, mc in valid])
            D = Jn - J0[None]
            delta = 2.0 * np.einsum("ic,kic->k", G[f], D) + np.einsum("kic,ij,kjc->k", D, Q[f], D)
            for (i, _), dv in zip(valid, delta):
                scores[i] = dv
        return scores

    def _triangle_scores(self, cands: list[Plan]) -> np.ndarray:
        """Unit traces of triangle-changed plans; the 6 orderings of a triangle share their floating
        steps, so one propagation with the triangle's 9 seed columns serves all of them."""
        out = np.full(len(cands), math.inf)
        groups: dict[tuple, list[int]] = {}
        for i, p in enumerate(cands):
            groups.setdefault((frozenset(p.triangle), tuple(p.steps[3:])), []).append(i)
        n = self.model.n_nodes
        for (tri_set, floating), idxs in groups.items():
            tri_nodes = sorted(tri_set)
            # Columns: 9 seeds (3 per triangle node), then the floating steps' own struts.
            ncols = 9 + 3 * len(floating)
            K = np.zeros((n, 3, ncols))
            for t, v in enumerate(tri_nodes):
                K[v, :, 3 * t:3 * t + 3] = np.eye(3)
            col = 9
            try:
                for s in floating:
                    M, C = self.sens.floating(s.node, s.base)
                    K[s.node] = np.tensordot(M, K[list(s.base)], axes=([0, 2], [0, 1]))
                    K[s.node, :, col:col + 3] += C
                    col += 3
            except DegenerateBaseError:
                continue
            own = float(np.sum(K[:, :, 9:] ** 2))
            T = K[:, :, :9]  # dX / dX_triangle
            for i in idxs:
                tri = cands[i].triangle
                # J of the triangle nodes in this ordering (3 triangle length columns).
                Jt = np.zeros((3, 3, 3))  # [triangle node slot, xyz, length column]
                col = 0
                for slot in range(3):
                    M, C = self.sens.triangle(tri, slot)
                    base_slots = [tri.index(b) for b in tri[:slot]]
                    if slot:
                        Jt[slot] = np.tensordot(M, Jt[base_slots], axes=([0, 2], [0, 1]))
                        Jt[slot, :, col:col + slot] += C
                    col += slot
                # Stack the triangle J by sorted node order to match the seed columns.
                S = np.concatenate([Jt[tri.index(v)] for v in tri_nodes], axis=0)  # (9, 3)
                prop = np.einsum("nic,ck->nik", T, S)
                out[i] = float(np.sum(prop ** 2)) + own
        return out

    def local_search(self, start: Plan, max_iter: int = 1000) -> SearchResult:
        """AssemblyLocalSearch (steepest descent): move to the best adjacent plan while it lowers
        the trace."""
        t0 = time.perf_counter()
        plan = start
        J = plan_jacobian(self.model.nodes, plan, self.sens)
        best = float(np.sum(J * J))
        history = [best]
        evaluated = 0
        for _ in range(max_iter):
            swaps = self.base_swaps(plan)
            swap_scores = self._swap_scores(plan, J, swaps) if swaps else np.zeros(0)
            tri_plans = self.triangle_swaps(plan)
            tri_scores = self._triangle_scores(tri_plans) if tri_plans else np.zeros(0)
            evaluated += len(swaps) + len(tri_plans)
            cand_plan, cand_trace = None, best
            if len(swap_scores):
                i = int(np.argmin(swap_scores))
                if best + swap_scores[i] < cand_trace * (1 - 1e-12):
                    cand_plan, cand_trace = _replace_step(plan, swaps[i]), best + float(swap_scores[i])
            if len(tri_scores):
                i = int(np.argmin(tri_scores))
                if tri_scores[i] < cand_trace * (1 - 1e-12):
                    cand_plan, cand_trace = tri_plans[i], float(tri_scores[i])
            if cand_plan is None:
                break
            plan = cand_plan
            J = plan_jacobian(self.model.nodes, plan, self.sens)
            best = float(np.sum(J * J))  # exact recompute: no drift from the incremental scores
            history.append(best)
        return SearchResult(plan, best, history, time.perf_counter() - t0, evaluated)

    def locally_optimal(self, rng: np.random.Generator | None = None,
                        triangles: Sequence[tuple[int, int, int]] | None = None) -> SearchResult:
        """FindLocallyOptimalSequence: a random central triangle, greedy assembly, local search."""
        t0 = time.perf_counter()
        rng = rng or np.random.default_rng(0)
        central = list(triangles) if triangles is not None else all_central_triangles(self.model, rng, self.geometry)
        order = rng.permutation(len(central))
        for idx in order:  # a central triangle greedy cannot complete is skipped
            g = self.greedy(central[int(idx)])
            if g is not None:
                r = self.local_search(g.plan)
                r.history = g.history + r.history[1:]
                r.seconds = time.perf_counter() - t0
                r.evaluated += g.evaluated
                return r
        raise DegenerateBaseError(f"no central triangle of {self.model.name} can be completed")


def _replace_step(plan: Plan, new: Step) -> Plan:
    """The plan with node f on a new base, re-ordered topologically (stable: by old position)."""
    base_of = dict(plan.base_of)
    base_of[new.node] = new.base
    pos = plan.position
    placed = set(plan.triangle)
    steps = list(plan.steps[:3])
    pending = sorted((s.node for s in plan.steps[3:]), key=pos.__getitem__)
    while pending:
        rest = []
        progressed = False
        for f in pending:
            if all(b in placed for b in base_of[f]):
                steps.append(Step(f, base_of[f]))
                placed.add(f)
                progressed = True
            else:
                rest.append(f)
        if not progressed:
            raise ValueError(f"replacing the base of {new.node} by {new.base} makes a cycle")
        pending = rest
    return Plan(tuple(steps))


# Function forms with the paper's names ---------------------------------------------------------


def greedy_assembly(model: TrussModel, triangle: Sequence[int], planner: Planner | None = None) -> Plan | None:
    r = (planner or Planner(model)).greedy(triangle)
    return None if r is None else r.plan


def adjacent_sequences(model: TrussModel, plan: Plan, planner: Planner | None = None) -> list[Plan]:
    return (planner or Planner(model)).adjacent(plan)


def assembly_local_search(model: TrussModel, plan: Plan, planner: Planner | None = None) -> SearchResult:
    return (planner or Planner(model)).local_search(plan)


def find_locally_optimal_sequence(model: TrussModel, rng: np.random.Generator | None = None,
                                  planner: Planner | None = None) -> SearchResult:
    return (planner or Planner(model)).locally_optimal(rng)


# --------------------------------------------------------------------------------------------
# Exhaustive enumeration (small trusses)


def enumerate_plans(model: TrussModel, triangles: Sequence[tuple[int, int, int]] | None = None,
                    planner: Planner | None = None, limit: int = 5_000_000) -> Iterator[tuple[Plan, float]]:
    """Every distinct plan (ordered triangle + one base per node, as a set of steps: the paper's
    parallel equivalence) with its unit trace.  Each step set is produced once, in its
    lexicographically smallest topological order: a node may be added only if no smaller
    unbuilt node could have been added earlier with the base it finally gets."""
    planner = planner or Planner(model)
    n = model.n_nodes
    if triangles is None:
        triangles = [o for tri in three_cliques(model) for o in ordered_triangles(tri)]
    nb = model.neighbours
    count = 0
    for tri in triangles:
        a, b, c = tri
        J = np.zeros((n, 3, 3 * n - 6))
        col = 0
        steps0 = [Step(a), Step(b, (a,)), Step(c, (a, b))]
        for k, s in enumerate(steps0):
            M, C = planner.sens.triangle(tuple(tri), k)
            if k:
                J[s.node] = np.tensordot(M, J[list(s.base)], axes=([0, 2], [0, 1]))
                J[s.node, :, col:col + k] += C
            col += k
        tri_trace = float(np.sum(J[[a, b, c]] ** 2))
        # built_before[p] = set of nodes built before position p (floating positions only)
        steps: list[Step] = []
        sets_before: list[frozenset[int]] = []

        def dfs(made: frozenset[int], total: float, col: int) -> Iterator[tuple[Plan, float]]:
            nonlocal count
            if len(made) == n:
                count += 1
                if count > limit:
                    raise RuntimeError(f"more than {limit} plans; enumeration is for small trusses")
                yield Plan(tuple(steps0 + steps)), total
                return
            for f in range(n):
                if f in made:
                    continue
                built = sorted(nb[f] & made)
                if len(built) < 3:
                    continue
                for bset in itertools.combinations(built, 3):
                    o = planner.geometry.oriented(f, bset)
                    if o is None:
                        continue
                    # canonical order: at the last position where a larger node was chosen, f with
                    # this base must not already have been addable (else f would come first there)
                    ok = True
                    for p in range(len(steps) - 1, -1, -1):
                        if steps[p].node > f:
                            if set(bset) <= sets_before[p]:
                                ok = False
                            break
                    if not ok:
                        continue
                    mc = planner._sens(f, o)
                    if mc is None:
                        continue
                    M, C = mc
                    J[f] = np.tensordot(M, J[list(o)], axes=([0, 2], [0, 1]))
                    J[f, :, col:col + 3] += C
                    add = float(np.sum(J[f] ** 2))
                    steps.append(Step(f, o))
                    sets_before.append(made)
                    yield from dfs(made | {f}, total + add, col + 3)
                    steps.pop()
                    sets_before.pop()
                    J[f] = 0.0

        yield from dfs(frozenset(tri), tri_trace, col)
