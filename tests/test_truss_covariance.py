"""Open-loop covariance trace: exact Jacobian against the paper's central differences."""

import numpy as np
import pytest

from estimation.sequencing import Planner, all_central_triangles
from estimation.truss_covariance import (
    finite_difference_jacobian,
    jacobian_in_gauge,
    node_covariances,
    node_traces,
    trace,
)
from estimation.truss_geometry import Plan, orient_base
from lab.core.structures.trusses import build_truss


def _helix_plan(n):
    m = build_truss(f"tetrahelix:{n}")
    return m, Plan.from_triangle((0, 1, 2), [(k, orient_base(m.nodes, k, (k - 3, k - 2, k - 1))) for k in range(3, n)])


def test_exact_jacobian_matches_central_differences_tetrahelix():
    m, plan = _helix_plan(12)
    J = jacobian_in_gauge(m.nodes, plan)
    fd = finite_difference_jacobian(m.nodes, plan, h=1e-6)
    assert np.abs(J).max() > 1.0  # lever arms: derivatives well above 1 m/m
    np.testing.assert_allclose(J, fd, atol=1e-7)


def test_exact_jacobian_matches_central_differences_telescope_greedy():
    m = build_truss("telescope:20")
    planner = Planner(m)
    plan = planner.greedy(all_central_triangles(m)[0]).plan
    np.testing.assert_allclose(jacobian_in_gauge(m.nodes, plan), finite_difference_jacobian(m.nodes, plan, 1e-6),
                               atol=1e-6)


def test_tetrahelix20_trace_reproduces_the_paper_open_loop_figure():
    # IPJR paper §6.3: open-loop trace 28.76 m^2 for 1 m struts, sigma_L = 0.1 m
    m, plan = _helix_plan(20)
    assert trace(m.nodes, plan, 0.1) == pytest.approx(28.76, abs=0.01)
    per_node = node_traces(m.nodes, plan, 0.1)
    assert per_node[0] == 0 and np.all(np.diff(per_node) > 0)  # error grows along the tower


def test_node_covariances_are_gauge_consistent():
    m, plan = _helix_plan(8)
    cov = node_covariances(m.nodes, plan, 0.01)
    np.testing.assert_allclose(cov[0], 0)  # node a fixed
    np.testing.assert_allclose(cov[1][1:, :], 0, atol=1e-18)  # b moves along x only
    assert cov[1][0, 0] == pytest.approx(1e-4)
    np.testing.assert_allclose(cov[2][2, :], 0, atol=1e-18)  # c stays in the xy-plane
    np.testing.assert_allclose(np.trace(cov, axis1=1, axis2=2), node_traces(m.nodes, plan, 0.01), rtol=1e-12)
