"""Tetrahedral truss design models: the tetrahelix tower and the paraboloid telescope truss."""

import itertools

import numpy as np
import pytest

from lab.core.errors import UserError
from lab.core.structures.trusses import base_height_ratio, build_truss, is_buildable, to_json


@pytest.mark.parametrize("name, edge", [("tetrahelix:20", 1.0), ("tetrahelix:7:0.5", 0.5)])
def test_tetrahelix_every_strut_is_nominal_and_each_node_joins_previous_three(name, edge):
    m = build_truss(name)
    n = m.n_nodes
    assert len(m.edges) == 3 * n - 6  # minimally rigid: no redundant strut
    np.testing.assert_allclose(m.nominal_lengths, edge, atol=1e-12)
    for k in range(3, n):
        assert {j for j in m.neighbours[k] if j < k} == {k - 1, k - 2, k - 3}
    # regular tetrahedra: every 4 consecutive nodes are mutually one edge apart
    for k in range(n - 3):
        quad = m.nodes[k:k + 4]
        d = [np.linalg.norm(quad[a] - quad[b]) for a, b in itertools.combinations(range(4), 2)]
        np.testing.assert_allclose(d, edge, atol=1e-12)
    # a helix, not a zig-zag in a plane: nodes 4 apart are distinct
    assert np.linalg.norm(m.nodes[4] - m.nodes[0]) > 0.1 * edge


@pytest.mark.parametrize("n", [10, 45, 84])
def test_telescope_sizes_are_buildable_on_a_paraboloid(n):
    m = build_truss(f"telescope:{n}")
    assert m.n_nodes == n
    assert len(m.edges) > 3 * n - 6  # redundant struts give the MLE its loop closures
    assert is_buildable(m)
    assert 1.9 < np.median(m.nominal_lengths) < 2.2  # "edge lengths on the order of 2 m"
    top = np.asarray(m.params["top_nodes"])
    F = m.params["focal_m"]
    v = np.asarray(m.params["vertex_xy_m"])
    xy = m.nodes[top, :2]
    z = (np.sum((xy - v) ** 2, axis=1) - v @ v) / (4 * F)
    np.testing.assert_allclose(m.nodes[top, 2], z, atol=1e-9)
    # innermost nodes: every kept node is at least as close to the centre as the next size adds
    r = np.linalg.norm(m.nodes[:, :2], axis=1)
    bigger = build_truss(f"telescope:{n + 12}")
    r_big = np.sort(np.linalg.norm(bigger.nodes[:, :2], axis=1))
    assert r.max() <= r_big[-1]


def test_telescope_subsets_nest():
    small, big = build_truss("telescope:10"), build_truss("telescope:45")
    for p in small.nodes:
        assert np.min(np.linalg.norm(big.nodes - p, axis=1)) < 1e-9


def test_base_height_ratio_flags_flat_tetrahedra():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 1.0], [0.3, 0.3, 0.0]], float)
    assert base_height_ratio(x, 3, (0, 1, 2)) > 0.5
    assert base_height_ratio(x, 4, (0, 1, 2)) == 0.0


@pytest.mark.parametrize("bad", ["tetrahelix", "cube:8", "tetrahelix:3", "tetrahelix:x", "telescope:2",
                                 "telescope:10:2", "tetrahelix:5:-1"])
def test_bad_names_raise_user_error_listing_the_forms(bad):
    with pytest.raises(UserError, match="tetrahelix:N"):
        build_truss(bad)


def test_to_json_shape():
    m = build_truss("tetrahelix:5")
    j = to_json(m)
    assert j["modules"] == [] and j["tags"] == []
    assert [n["id"] for n in j["nodes"]] == list(range(5))
    assert len(j["edges"]) == 9
    assert j["edges"][0]["nodes"] == [0, 1] and j["edges"][0]["length_m"] == pytest.approx(1.0)
    assert m.to_json() == j
