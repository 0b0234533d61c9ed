"""Tetrahedral truss design models for IPJR assembly (IPJR paper §2, §5, Fig. 4).

Two families, named as strings so the CLI and plans can refer to them:

- ``tetrahelix:N[:edge_m]`` -- the tower of regular tetrahedra (Boerdijk-Coxeter helix): nodes
  0, 1, 2 form an equilateral triangle, node 3 is the apex above it, and every later node n joins
  n-1, n-2, n-3, placed as the mirror image of node n-4 through the plane of that shared face.
  Every strut has the nominal edge length (default 1 m).  It has exactly 3N-6 struts: no
  redundant strut, so no loop closure.
- ``telescope:N`` -- a double-layer tetrahedral ("octet") truss over a hexagonal patch, curved to
  an off-axis paraboloid like the optical bench of the paper's motivating 84-node telescope
  (Watson et al. 2002).  Top nodes lie on the paraboloid on a triangular lattice of 2 m spacing;
  each "up" triangle of the top layer has a bottom node under its centroid, offset along the
  surface normal so its three core struts are ~2 m; bottom nodes form their own triangular
  lattice; one diagonal strut splits each octahedron into tetrahedra (see `_telescope_full`).
  ``N`` keeps the innermost N nodes by horizontal distance from the patch centre, as the
  paper took its 10- and 45-node subsets of the 84-node truss.

Node ids are 0-based; the paper's "node k" is our id k-1 where it matters (docs say so).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from lab.core.errors import UserError

__all__ = [
    "TrussModel",
    "build_truss",
    "to_json",
    "tetrahelix",
    "telescope",
    "base_height_ratio",
    "is_buildable",
    "TRUSS_FORMS",
    "TELESCOPE_EDGE_M",
    "TELESCOPE_FOCAL_M",
    "TELESCOPE_VERTEX_OFFSET_M",
]

TRUSS_FORMS = ("tetrahelix:N[:edge_m] (N >= 4, e.g. tetrahelix:20 or tetrahelix:20:0.5)",
               "telescope:N (4 <= N <= 400, e.g. telescope:10, telescope:45, telescope:84)")

# Telescope design constants (IPJR paper §6.3: "edge lengths on the order of 2 m").  The focal
# length and off-axis offset are our choice: the paper says the surface is a paraboloid that is
# not symmetric about the patch, and gives no numbers.
TELESCOPE_EDGE_M = 2.0
TELESCOPE_FOCAL_M = 16.0
TELESCOPE_VERTEX_OFFSET_M = (-4.0, 0.0)  # paraboloid vertex (x, y) relative to the patch centre

# A float-base tetrahedron whose height is below this fraction of its longest strut is treated as
# degenerate: no unique node position, the covariance is unbounded.
DEGENERATE_RATIO = 1e-6


@dataclass(frozen=True)
class TrussModel:
    """A truss design: nominal node positions (N, 3) in metres and struts as sorted (i, j), i < j."""

    name: str
    nodes: np.ndarray
    edges: list[tuple[int, int]]
    kind: str = "truss"
    params: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        nodes = np.asarray(self.nodes, dtype=float)
        if nodes.ndim != 2 or nodes.shape[1] != 3:
            raise ValueError(f"nodes must be an (N, 3) array, got shape {nodes.shape}")
        edges = sorted({(min(int(i), int(j)), max(int(i), int(j))) for i, j in self.edges})
        for i, j in edges:
            if i == j or not (0 <= i < len(nodes) and 0 <= j < len(nodes)):
                raise ValueError(f"edge ({i}, {j}) does not join two distinct nodes of {len(nodes)}")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "edges", edges)

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @cached_property
    def nominal_lengths(self) -> np.ndarray:
        """Nominal strut lengths in metres, in the order of `edges`."""
        e = np.asarray(self.edges, dtype=int).reshape(-1, 2)
        return np.linalg.norm(self.nodes[e[:, 0]] - self.nodes[e[:, 1]], axis=1)

    @cached_property
    def neighbours(self) -> list[frozenset[int]]:
        """neighbours[i] = the nodes joined to i by a strut."""
        nb: list[set[int]] = [set() for _ in range(self.n_nodes)]
        for i, j in self.edges:
            nb[i].add(j)
            nb[j].add(i)
        return [frozenset(s) for s in nb]

    @cached_property
    def edge_set(self) -> frozenset[tuple[int, int]]:
        return frozenset(self.edges)

    def has_edge(self, i: int, j: int) -> bool:
        return (min(i, j), max(i, j)) in self.edge_set

    def length(self, i: int, j: int) -> float:
        """Nominal distance between nodes i and j (a strut or not)."""
        return float(np.linalg.norm(self.nodes[i] - self.nodes[j]))

    def to_json(self) -> dict:
        return to_json(self)


def to_json(model: TrussModel) -> dict:
    """The `lab structure truss NAME --json` shape (same keys as the BORG model's JSON)."""
    return {
        "name": model.name,
        "kind": model.kind,
        "params": dict(model.params),
        "modules": [],
        "tags": [],
        "nodes": [{"id": i, "position_m": [float(v) for v in p]} for i, p in enumerate(model.nodes)],
        "edges": [{"nodes": [i, j], "length_m": float(L)}
                  for (i, j), L in zip(model.edges, model.nominal_lengths)],
    }


def build_truss(name: str) -> TrussModel:
    """Parse a truss name ("tetrahelix:20", "tetrahelix:20:0.5", "telescope:84") into its model."""
    if not isinstance(name, str) or ":" not in name:
        raise UserError(f"unknown truss {name!r}; valid forms: " + "; ".join(TRUSS_FORMS))
    kind, _, rest = name.partition(":")
    parts = rest.split(":")
    try:
        if kind == "tetrahelix" and len(parts) in (1, 2):
            n = int(parts[0])
            edge = float(parts[1]) if len(parts) == 2 else 1.0
            return tetrahelix(n, edge)
        if kind == "telescope" and len(parts) == 1:
            return telescope(int(parts[0]))
    except ValueError as exc:
        raise UserError(f"bad truss {name!r}: {exc}; valid forms: " + "; ".join(TRUSS_FORMS)) from exc
    raise UserError(f"unknown truss {name!r}; valid forms: " + "; ".join(TRUSS_FORMS))


def tetrahelix(n: int, edge_m: float = 1.0) -> TrussModel:
    """The Boerdijk-Coxeter tower of n nodes with every strut `edge_m` long."""
    if not 4 <= n <= 400:
        raise ValueError(f"a tetrahelix is generated for 4 <= N <= 400 nodes, got {n}")
    if not (edge_m > 0 and np.isfinite(edge_m) and edge_m <= 100.0):
        raise ValueError(f"edge length must be a positive number of metres, got {edge_m}")
    a = float(edge_m)
    x = np.zeros((n, 3))
    x[1] = [a, 0.0, 0.0]
    x[2] = [a / 2, a * np.sqrt(3) / 2, 0.0]
    x[3] = [a / 2, a * np.sqrt(3) / 6, a * np.sqrt(2.0 / 3.0)]
    for k in range(4, n):
        p, q, r = x[k - 3], x[k - 2], x[k - 1]
        normal = np.cross(q - p, r - p)
        normal /= np.linalg.norm(normal)
        # Regular tetrahedra sharing a face: the new apex mirrors the old one through that face.
        x[k] = x[k - 4] - 2.0 * np.dot(x[k - 4] - p, normal) * normal
    edges = [(0, 1), (0, 2), (1, 2)] + [(k - d, k) for k in range(3, n) for d in (3, 2, 1)]
    return TrussModel(f"tetrahelix:{n}" + ("" if a == 1.0 else f":{edge_m:g}"), x, edges,
                      kind="tetrahelix", params={"n": n, "edge_m": a})


def _paraboloid(xy: np.ndarray, focal_m: float, vertex_xy: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Heights and unit upward normals of z = (|xy - v|^2 - |v|^2) / (4 F): through the origin."""
    v = np.asarray(vertex_xy, dtype=float)
    d = xy - v
    z = (np.sum(d * d, axis=1) - v @ v) / (4.0 * focal_m)
    grad = d / (2.0 * focal_m)
    normal = np.column_stack([-grad, np.ones(len(xy))])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return z, normal


def _telescope_full(rings: int, edge_m: float, focal_m: float,
                    vertex_xy: tuple[float, float]) -> tuple[np.ndarray, list[tuple[int, int]], np.ndarray]:
    """The full double-layer patch: top lattice points within `rings` hexagonal rings."""
    a = edge_m
    a1 = np.array([a, 0.0])
    a2 = np.array([a / 2, a * np.sqrt(3) / 2])
    top_ij = [(i, j) for i in range(-rings, rings + 1) for j in range(-rings, rings + 1)
              if max(abs(i), abs(j), abs(i + j)) <= rings]
    top_index = {ij: k for k, ij in enumerate(top_ij)}
    top_xy = np.array([i * a1 + j * a2 for i, j in top_ij])
    top_z, _ = _paraboloid(top_xy, focal_m, vertex_xy)
    top = np.column_stack([top_xy, top_z])

    # Bottom nodes: one under each complete "up" triangle (p, p + a1, p + a2).
    bottom_ij = [(i, j) for (i, j) in top_ij if (i + 1, j) in top_index and (i, j + 1) in top_index]
    h = a * np.sqrt(2.0 / 3.0)
    bottom = []
    for i, j in bottom_ij:
        tri = top[[top_index[(i, j)], top_index[(i + 1, j)], top_index[(i, j + 1)]]]
        c = tri.mean(axis=0)
        _, nrm = _paraboloid(c[None, :2], focal_m, vertex_xy)
        bottom.append(c - h * nrm[0])
    bottom = np.asarray(bottom)
    n_top = len(top)
    bottom_index = {ij: n_top + k for k, ij in enumerate(bottom_ij)}

    edges: set[tuple[int, int]] = set()
    for index in (top_index, bottom_index):  # in-layer triangular lattices
        for (i, j), k in index.items():
            for di, dj in ((1, 0), (0, 1), (-1, 1)):
                other = index.get((i + di, j + dj))
                if other is not None:
                    edges.add((min(k, other), max(k, other)))
    for (i, j), k in bottom_index.items():  # core struts to the three corners of the up triangle
        for ij in ((i, j), (i + 1, j), (i, j + 1)):
            t = top_index[ij]
            edges.add((min(k, t), max(k, t)))
    # One diagonal across every octahedron (top down-triangle over a bottom up-triangle), from the
    # bottom node under (p, p+a1, p+a2) to the top node p+a1+a2.  Without it an octet truss cannot
    # be assembled one node at a time: no node of an octahedron ever has 3 built neighbours.
    for (i, j), k in bottom_index.items():
        t = top_index.get((i + 1, j + 1))
        if t is not None and (i + 1, j) in bottom_index and (i, j + 1) in bottom_index:
            edges.add((min(k, t), max(k, t)))
    nodes = np.vstack([top, bottom])
    layer = np.array([0] * n_top + [1] * len(bottom))
    return nodes, sorted(edges), layer


def telescope(n: int, edge_m: float = TELESCOPE_EDGE_M, focal_m: float = TELESCOPE_FOCAL_M,
              vertex_xy: tuple[float, float] = TELESCOPE_VERTEX_OFFSET_M) -> TrussModel:
    """The innermost `n` nodes of the paraboloid double-layer telescope truss."""
    if not 4 <= n <= 400:
        raise ValueError(f"telescope trusses are generated for 4 <= N <= 400 nodes, got {n}")
    rings = 1
    while True:
        nodes, edges, layer = _telescope_full(rings, edge_m, focal_m, vertex_xy)
        if len(nodes) >= 2 * n:
            break
        rings += 1
    r = np.round(np.linalg.norm(nodes[:, :2], axis=1), 6)
    order = np.lexsort((np.arange(len(nodes)), r))  # by distance, ties by generation order
    keep = np.sort(order[:n])
    remap = {int(old): new for new, old in enumerate(keep)}
    sub_edges = [(remap[i], remap[j]) for i, j in edges if i in remap and j in remap]
    model = TrussModel(f"telescope:{n}", nodes[keep], sub_edges, kind="telescope",
                       params={"n": n, "edge_m": edge_m, "focal_m": focal_m,
                               "vertex_xy_m": list(vertex_xy),
                               "top_nodes": [int(remap[int(k)]) for k in keep if layer[k] == 0]})
    if not is_buildable(model):
        raise ValueError(f"telescope:{n} cannot be assembled one tetrahedron at a time "
                         f"(some node never gets 3 built neighbours); try another N")
    return model


def base_height_ratio(nodes: np.ndarray, f: int, base: tuple[int, ...]) -> float:
    """Height of node f above the plane of its base triple over the longest float-base strut.

    0 for a flat tetrahedron or a colinear base; sqrt(2/3) ~ 0.816 for a regular tetrahedron."""
    i, j, k = base
    n = np.cross(nodes[j] - nodes[i], nodes[k] - nodes[i])
    scale = max(np.linalg.norm(nodes[f] - nodes[b]) for b in base)
    nn = np.linalg.norm(n)
    if scale == 0 or nn <= 1e-12 * scale * scale:
        return 0.0
    return float(abs(np.dot(nodes[f] - nodes[i], n)) / nn / scale)


def _triangles(model: TrussModel) -> list[tuple[int, int, int]]:
    nb = model.neighbours
    return [(i, j, k) for i, j in model.edges for k in sorted(nb[i] & nb[j]) if k > j]


def is_buildable(model: TrussModel, min_ratio: float = DEGENERATE_RATIO) -> bool:
    """True when some starting triangle lets every node be added on a non-degenerate base triple."""
    nb = model.neighbours
    for tri in _triangles(model):
        built = set(tri)
        grew = True
        while grew and len(built) < model.n_nodes:
            grew = False
            for f in range(model.n_nodes):
                if f in built:
                    continue
                cand = sorted(nb[f] & built)
                if len(cand) >= 3 and any(base_height_ratio(model.nodes, f, b) >= min_ratio
                                          for b in itertools.combinations(cand, 3)):
                    built.add(f)
                    grew = True
        if len(built) == model.n_nodes:
            return True
    return False
