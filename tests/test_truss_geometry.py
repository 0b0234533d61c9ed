"""F_f node placement: known tetrahedron, the handedness rule, degenerate bases, exact derivatives."""

import numpy as np
import pytest

from estimation.truss_geometry import (
    DegenerateBaseError,
    Plan,
    Step,
    build_positions,
    orient_base,
    place_node,
    place_step,
    plan_lengths,
    step_sensitivity,
    to_gauge,
)

REG = np.array([[0, 0, 0], [1, 0, 0], [0.5, np.sqrt(3) / 2, 0]], float)
APEX = np.array([0.5, np.sqrt(3) / 6, np.sqrt(2 / 3)])


def test_regular_tetrahedron_apex():
    np.testing.assert_allclose(place_node(*REG, 1.0, 1.0, 1.0), APEX, atol=1e-12)


def test_handedness_rule_picks_the_side_of_the_counterclockwise_base():
    # i -> j -> k counter-clockwise seen from +z: f above; swapping j and k mirrors it below
    up = place_node(REG[0], REG[1], REG[2], 1, 1, 1)
    down = place_node(REG[0], REG[2], REG[1], 1, 1, 1)
    assert up[2] > 0 and down[2] < 0
    np.testing.assert_allclose(up[:2], down[:2], atol=1e-12)
    nodes = np.vstack([REG, APEX, APEX * [1, 1, -1]])
    assert orient_base(nodes, 3, (0, 1, 2)) == (0, 1, 2)
    assert orient_base(nodes, 4, (0, 1, 2)) == (0, 2, 1)


def test_random_tetrahedra_satisfy_their_lengths():
    rng = np.random.default_rng(3)
    for _ in range(50):
        base = rng.normal(size=(3, 3))
        f_true = rng.normal(size=3)
        n = np.cross(base[1] - base[0], base[2] - base[0])
        if np.dot(f_true - base[0], n) < 0:
            base = base[[0, 2, 1]]
        L = np.linalg.norm(f_true - base, axis=1)
        np.testing.assert_allclose(place_node(*base, *L), f_true, atol=1e-9)


@pytest.mark.parametrize("base, lengths, what", [
    (np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float), (1, 1, 1.5), "colinear"),
    (np.array([[0, 0, 0], [0, 0, 0], [0, 1, 0]], float), (1, 1, 1), "coincide"),
    (REG, (0.1, 0.1, 1.0), "cannot meet"),
])
def test_degenerate_bases_raise(base, lengths, what):
    with pytest.raises(DegenerateBaseError, match=what):
        place_node(*base, *lengths)


def test_flat_node_is_refused_by_orientation():
    nodes = np.vstack([REG, [0.4, 0.3, 0.0]])
    with pytest.raises(DegenerateBaseError, match="plane"):
        orient_base(nodes, 3, (0, 1, 2))


def test_starting_triangle_gauge():
    np.testing.assert_allclose(place_step([], []), 0)
    np.testing.assert_allclose(place_step([np.zeros(3)], [2.0]), [2, 0, 0])
    p = place_step([np.zeros(3), np.array([1.0, 0, 0])], [1.0, 1.0])
    np.testing.assert_allclose(p, [0.5, np.sqrt(3) / 2, 0], atol=1e-12)


def test_step_sensitivity_matches_central_differences():
    rng = np.random.default_rng(7)
    base = REG + rng.normal(scale=0.05, size=(3, 3))
    L = np.array([1.0, 0.9, 1.1])
    xf = place_node(*base, *L)
    M, C = step_sensitivity(xf, list(base), L)
    h = 1e-6
    for b in range(3):
        for axis in range(3):
            up, dn = base.copy(), base.copy()
            up[b, axis] += h
            dn[b, axis] -= h
            fd = (place_node(*up, *L) - place_node(*dn, *L)) / (2 * h)
            np.testing.assert_allclose(M[b][:, axis], fd, atol=1e-7)
        Lu, Ld = L.copy(), L.copy()
        Lu[b] += h
        Ld[b] -= h
        np.testing.assert_allclose(C[:, b], (place_node(*base, *Lu) - place_node(*base, *Ld)) / (2 * h), atol=1e-7)


def test_plan_rejects_bad_orders_and_open_loop_rebuild_is_exact():
    with pytest.raises(ValueError, match="before they are built"):
        Plan.from_triangle((0, 1, 2), [(4, (0, 1, 3)), (3, (0, 1, 2))])
    nodes = np.vstack([REG, APEX])
    plan = Plan((Step(0), Step(1, (0,)), Step(2, (0, 1)), Step(3, orient_base(nodes, 3, (0, 1, 2)))))
    g = to_gauge(nodes, plan.triangle)
    np.testing.assert_allclose(build_positions(plan, plan_lengths(g, plan)), g, atol=1e-12)
    assert plan.times == {0: 1, 1: 2, 2: 3, 3: 4}
