"""Assembly sequencing: validity of every plan the algorithms produce, and the search's claims."""

import numpy as np
import pytest

from estimation.sequencing import (
    Planner,
    _replace_step,
    all_central_triangles,
    enumerate_plans,
    parallel_length,
    possible_next_nodes,
    random_sequence,
    three_cliques,
    validate_plan,
)
from estimation.truss_covariance import plan_jacobian
from estimation.truss_geometry import Plan, Step
from lab.core.structures.trusses import build_truss


@pytest.fixture(scope="module")
def t20():
    m = build_truss("telescope:20")
    return m, Planner(m)


def _assert_valid(m, plan):
    assert validate_plan(m, plan) == []
    built = set(plan.triangle)
    for s in plan.steps[3:]:
        assert len(s.base) == 3 and set(s.base) <= built  # every floating node has a built base triple
        built.add(s.node)
    assert built == set(range(m.n_nodes))


def test_validate_plan_catches_bad_plans(t20):
    m, planner = t20
    plan = planner.greedy(all_central_triangles(m)[0]).plan
    f = plan.steps[5]
    flipped = Plan(plan.steps[:5] + (Step(f.node, (f.base[0], f.base[2], f.base[1])),) + plan.steps[6:])
    assert any("handedness" in p for p in validate_plan(m, flipped))
    short = Plan(plan.steps[:-1])
    assert any("places nodes" in p for p in validate_plan(m, short))


def test_three_cliques_and_possible_next_nodes():
    m = build_truss("tetrahelix:6")
    assert three_cliques(m) == [(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3), (1, 2, 4), (1, 3, 4), (2, 3, 4),
                                (2, 3, 5), (2, 4, 5), (3, 4, 5)]
    nxt = possible_next_nodes(m, {0, 1, 2})
    assert [s.node for s in nxt] == [3]


@pytest.mark.parametrize("mode", ["any", "minsteps"])
def test_random_sequences_are_valid(t20, mode):
    m, planner = t20
    rng = np.random.default_rng(0)
    for tri in three_cliques(m)[:15]:
        p = random_sequence(m, tri, mode, rng, planner.geometry)
        if p is not None:
            _assert_valid(m, p)


def test_minsteps_has_fewest_layers_and_central_triangles_minimise_them(t20):
    m, planner = t20
    rng = np.random.default_rng(1)
    central = all_central_triangles(m, rng)
    assert central and len(central) % 6 == 0
    best = parallel_length(random_sequence(m, central[0], "minsteps", rng))
    for tri in three_cliques(m):
        p = random_sequence(m, tri, "minsteps", rng)
        if p is not None:
            assert parallel_length(p) >= best
            anyp = random_sequence(m, tri, "any", rng)
            assert parallel_length(anyp) >= parallel_length(p)


def test_layers_follow_t_rule():
    m = build_truss("tetrahelix:7")
    p = random_sequence(m, (0, 1, 2), "any")
    assert p.layers == [[0], [1], [2], [3], [4], [5], [6]]


def test_greedy_then_local_search_lowers_the_trace_and_stays_valid(t20):
    m, planner = t20
    rng = np.random.default_rng(2)
    tri = three_cliques(m)[-1]
    g = planner.greedy(tri)
    _assert_valid(m, g.plan)
    assert g.trace_unit == pytest.approx(planner.trace_unit(g.plan), rel=1e-12)
    r = planner.local_search(g.plan)
    _assert_valid(m, r.plan)
    assert r.trace_unit <= g.trace_unit
    assert r.trace_unit == pytest.approx(planner.trace_unit(r.plan), rel=1e-12)
    assert all(b <= a for a, b in zip(r.history, r.history[1:]))
    # a local minimum: no adjacent plan is better
    for p in planner.adjacent(r.plan):
        _assert_valid(m, p)
        assert planner.trace_unit(p) >= r.trace_unit * (1 - 1e-9)
    # random sequences from the same triangle are worse than greedy
    rnd = [planner.trace_unit(random_sequence(m, tri, "any", rng)) for _ in range(5)]
    assert min(rnd) > g.trace_unit


def test_incremental_swap_scores_equal_full_recomputation(t20):
    m, planner = t20
    plan = planner.greedy(all_central_triangles(m)[0]).plan
    J = plan_jacobian(m.nodes, plan, planner.sens)
    T = float(np.sum(J * J))
    swaps = planner.base_swaps(plan)
    scores = planner._swap_scores(plan, J, swaps)
    for s, d in list(zip(swaps, scores))[::7]:
        assert T + d == pytest.approx(planner.trace_unit(_replace_step(plan, s)), rel=1e-9)
    tri = planner.triangle_swaps(plan)
    for p, t in list(zip(tri, planner._triangle_scores(tri)))[::5]:
        assert t == pytest.approx(planner.trace_unit(p), rel=1e-9)


def test_enumeration_counts_the_paper_10_node_telescope():
    # IPJR paper §6.4: "The 10-node telescope truss ... has 12,708 distinct assembly sequences"
    m = build_truss("telescope:10")
    planner = Planner(m)
    traces = []
    keys = set()
    for plan, t in enumerate_plans(m, planner=planner):
        traces.append(t)
        keys.add(plan.key())
    assert len(traces) == len(keys) == 12708
    best = planner.locally_optimal(np.random.default_rng(0))
    assert best.trace_unit >= min(traces) * (1 - 1e-12)
