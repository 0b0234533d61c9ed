"""The BORG truss design model: nodes, modules in assembly order, AprilTags and their relations.

N = 3 reproduces Table 1 of the SF-GraphSLAM paper exactly (36 module tags, 12 turntable tags,
module names 1P ... 27P, the relation lists verbatim).  The paper's layout figure is not in the
text; `docs/borg.md` explains how this layout was derived from Table 1 and §2.6.  Other N use the
same rules (body-centred checkerboard of deployables, close-out members on the remaining grid
edges) with generated names and IDs; see `docs/borg.md` for what they mean and don't.

Frames (lab/core/geometry.py): structure frame at the outer corner node of the first deployable (2D),
axes along the grid, z up.  Tag frame: x right, y up, z out of the face the tag is on.  Faces are
numbered as in the paper's Figure 6: face 1 is x = 0, and each following face is the one the
turntable brings in front of the camera after a further +90 deg turn (2: y = L, 3: x = L, 4: y = 0).
"""

from __future__ import annotations

import math

from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

import numpy as np

from lab.core.geometry import Pose3, Rot3, pose

ModuleKind = Literal["deployable", "closeout_strut", "closeout_square"]
RelationKind = Literal["deployable", "closeout_strut", "closeout_square", "node", "turntable"]

TAG_SIZE_M = 0.10
# Offset of a tag from the node it is anchored to, in the tag frame: left along the member, up on
# its bracket, proud of the strut.  Vertical members use the same offset turned a quarter turn in
# the face plane (the paper: "the same transform simply rotated").
TAG_OFFSET_HORIZONTAL = np.array([-0.15, 0.07, 0.02])
TAG_OFFSET_VERTICAL = np.array([-0.07, -0.15, 0.02])
TURNTABLE_TAG_HEIGHT_M = -0.06  # tag centres on the turntable rim, below the structure's base
TURNTABLE_MARGIN_M = 0.15       # rim radius beyond the structure's half-diagonal
SPACING_M = 0.5                 # the BORG's cell size (build_borg's default)


@dataclass(frozen=True)
class TagSpec:
    id: int
    label: str                 # the paper's "Opti name": "2D-B", "6S", "TT3", ...
    module: str                # module name, or "turntable"
    structure_T_tag: Pose3
    related: tuple[int, ...]   # Table 1's "tags with single mechanical relationship", in order
    face: int                  # 1..4, the face it is seen from
    size_m: float = TAG_SIZE_M


@dataclass(frozen=True)
class Module:
    name: str                  # "1P", "2D", "10CT", ...
    kind: ModuleKind
    tags: tuple[int, ...]      # deployables: (bottom tag, top tag)
    nodes: tuple[int, ...]     # node ids it joins
    edges: tuple[tuple[int, int], ...]  # struts it brings (node id pairs, i < j)
    structure_T_module: Pose3  # pose of its first tag's anchor frame: anchor node, face orientation
    face: int


@dataclass(frozen=True)
class Relation:
    a: int
    b: int
    kind: RelationKind


@dataclass(frozen=True)
class Turntable:
    center_xy_m: tuple[float, float]   # rotation axis in the structure frame
    radius_m: float
    tag_ids: tuple[int, ...]


@dataclass(frozen=True)
class BorgModel:
    n: int
    spacing_m: float
    nodes: np.ndarray                       # (M, 3) design node positions, structure frame
    edges: tuple[tuple[int, int], ...]      # every strut of every module
    modules: tuple[Module, ...]             # assembly order
    tags: dict[int, TagSpec]
    turntable: Turntable
    relations: tuple[Relation, ...] = field(default=())

    @cached_property
    def module_by_name(self) -> dict[str, Module]:
        return {m.name: m for m in self.modules}

    def module_tags(self, name: str) -> tuple[int, ...]:
        return self.module_by_name[name].tags

    # Each tag's design as arrays, read once: tag elimination fits the estimates to them after every
    # step, and reading ~200 designed poses through their wrappers each time cost ~0.2 ms of it
    @cached_property
    def tag_positions(self) -> dict[int, np.ndarray]:
        """Tag -> its designed position (structure frame)."""
        return {t: tag.structure_T_tag.translation() for t, tag in self.tags.items()}

    @cached_property
    def tag_T_structure(self) -> dict[int, np.ndarray]:
        """Tag -> the inverse of its designed pose, 4x4."""
        return {t: tag.structure_T_tag.inverse().matrix() for t, tag in self.tags.items()}

    def layer_of(self, name: str) -> int:
        """The cell row a module belongs to: where the mean height of its nodes lies (a horizontal
        member on top of row k, z = (k + 1) s, closes row k)."""
        return self._layers[name]

    @cached_property
    def _layers(self) -> dict[str, int]:
        # computed once: a run asks for every placed module's layer at every release (settling),
        # 4 ms a release at N = 10 when each was a mean over its nodes
        out = {}
        for m in self.modules:
            z = float(np.mean(self.nodes[list(m.nodes), 2]))
            out[m.name] = int(min(max(math.floor(z / self.spacing_m - 1e-6), 0), self.n - 1))
        return out

    def design_between(self, a: int, b: int) -> Pose3:
        """Designed relative pose tag_a_T_tag_b."""
        return self.tags[a].structure_T_tag.between(self.tags[b].structure_T_tag)

    def related_pairs(self) -> list[tuple[int, int]]:
        return [(r.a, r.b) for r in self.relations]

    def world_T_structure(self, turntable_angle_rad: float) -> Pose3:
        """World = turntable base frame: origin on the rotation axis at the turntable top, z up.
        At angle 0 the structure's x axis is the world x axis."""
        cx, cy = self.turntable.center_xy_m
        return Pose3(Rot3.Rz(turntable_angle_rad), np.zeros(3)).compose(pose(None, (-cx, -cy, 0.0)))

    @property
    def module_tag_ids(self) -> list[int]:
        return [t for m in self.modules for t in m.tags]

    @property
    def size_m(self) -> float:
        return self.n * self.spacing_m


# --- Table 1 of the SF-GraphSLAM paper, verbatim -------------------------------------------------
TABLE1: dict[int, tuple[str, tuple[int, ...]]] = {
    0: ("1P", (1, 37)), 1: ("2D-B", (0, 2, 9, 36)), 2: ("2D-T", (1, 17, 21)),
    3: ("3D-B", (4, 10, 39)), 4: ("3D-T", (3, 20, 26)), 5: ("4D-B", (6, 11, 42)),
    6: ("4D-T", (5, 25, 31)), 7: ("5D-B", (8, 12, 45)), 8: ("5D-T", (7, 30, 33)),
    9: ("6S", (1, 37)), 10: ("7S", (3, 40)), 11: ("8S", (5, 43)), 12: ("9S", (7, 46)),
    13: ("10CT-B", (14, 2)), 14: ("10CT-T", (13, 15)), 15: ("11D-B", (16, 17, 21)),
    16: ("11D-T", (15, 22)), 17: ("12S", (2, 15)), 18: ("13D-B", (19, 20, 26)),
    19: ("13D-T", (18, 27)), 20: ("14S", (4, 18)), 21: ("15P", (2, 15)), 22: ("16S", (16,)),
    23: ("17D-B", (24, 25, 31)), 24: ("17D-T", (23, 32)), 25: ("18S", (6, 23)),
    26: ("19P", (4, 18)), 27: ("20S", (19,)), 28: ("21D-B", (29, 30, 33)),
    29: ("21D-T", (28, 34)), 30: ("22S", (8, 28)), 31: ("23P", (6, 23)), 32: ("24S", (24,)),
    33: ("25P", (8, 28)), 34: ("26S", (29,)), 35: ("27P", (16,)),
    36: ("TT1", (1, 37, 47)), 37: ("TT2", (0, 9, 36, 38)), 38: ("TT3", (37, 39)),
    39: ("TT3", (3, 38, 40)), 40: ("TT4", (10, 39, 41)), 41: ("TT5", (40, 42)),
    42: ("TT5", (5, 41, 43)), 43: ("TT6", (11, 42, 44)), 44: ("TT7", (43, 45)),
    45: ("TT7", (7, 44, 46)), 46: ("TT8", (12, 45, 47)), 47: ("TT1", (36, 46)),
}


# --- Faces ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Face:
    corner: np.ndarray   # the bottom node of the face's right-hand corner column
    left: np.ndarray     # unit vector along the face, leftwards for a viewer outside
    normal: np.ndarray   # outward unit normal

    def point(self, u: float, w: float, z: float) -> np.ndarray:
        """Face-local (u leftwards along the face, w inwards, z up) -> structure frame."""
        return self.corner + u * self.left - w * self.normal + np.array([0.0, 0.0, z])

    @property
    def R(self) -> np.ndarray:
        """structure_R_tag for a tag on this face: x right, y up, z out."""
        return np.column_stack([-self.left, [0.0, 0.0, 1.0], self.normal])


def _faces(L: float) -> dict[int, _Face]:
    e = np.eye(3)
    return {
        1: _Face(np.array([0.0, 0.0, 0.0]), e[1], -e[0]),
        2: _Face(np.array([0.0, L, 0.0]), e[0], e[1]),
        3: _Face(np.array([L, L, 0.0]), -e[1], e[0]),
        4: _Face(np.array([L, 0.0, 0.0]), -e[0], -e[1]),
    }


def _tag_pose(face: _Face, anchor: np.ndarray, vertical: bool) -> Pose3:
    offset = TAG_OFFSET_VERTICAL if vertical else TAG_OFFSET_HORIZONTAL
    return pose(face.R, anchor + face.R @ offset)


def _anchor_frame(face: _Face, anchor: np.ndarray) -> Pose3:
    return pose(face.R, anchor)


class _Grid:
    def __init__(self, n: int, s: float) -> None:
        self.n, self.s = n, s
        k = n + 1
        idx = np.array([(i, j, l) for l in range(k) for j in range(k) for i in range(k)], dtype=float)
        self.nodes = idx * s

    def node(self, p: np.ndarray) -> int:
        ijk = np.rint(np.asarray(p) / self.s).astype(int)
        if np.any(ijk < 0) or np.any(ijk > self.n) or not np.allclose(ijk * self.s, p, atol=1e-9):
            raise ValueError(f"{p} is not a grid node")
        k = self.n + 1
        return int(ijk[0] + k * (ijk[1] + k * ijk[2]))

    def cell_nodes(self, ci: int, cj: int, ck: int) -> tuple[int, ...]:
        s = self.s
        return tuple(
            self.node(np.array([ci + a, cj + b, ck + c]) * s) for c in (0, 1) for b in (0, 1) for a in (0, 1)
        )

    def cell_edges(self, ci: int, cj: int, ck: int) -> tuple[tuple[int, int], ...]:
        corners = [np.array([ci + a, cj + b, ck + c]) for c in (0, 1) for b in (0, 1) for a in (0, 1)]
        out = []
        for p in corners:
            for axis in range(3):
                q = p.copy()
                q[axis] += 1
                if q[axis] <= [ci, cj, ck][axis] + 1:
                    out.append(self._edge(p * self.s, q * self.s))
        return tuple(sorted(out))

    def _edge(self, p: np.ndarray, q: np.ndarray) -> tuple[int, int]:
        a, b = self.node(p), self.node(q)
        return (a, b) if a < b else (b, a)

    def square(self, corners: list[np.ndarray]) -> tuple[tuple[int, ...], tuple[tuple[int, int], ...]]:
        """Four corners in order around the square: its nodes, four sides and one diagonal."""
        ids = tuple(self.node(c) for c in corners)
        sides = [self._edge(corners[i], corners[(i + 1) % 4]) for i in range(4)]
        sides.append(self._edge(corners[0], corners[2]))
        return ids, tuple(sorted(sides))


MAX_N = 10  # the largest BORG a lab turntable carries (the rig's borg_n has the same bound)


def build_borg(n: int = 3, spacing_m: float = SPACING_M) -> BorgModel:
    """The design model of an N x N x N BORG truss (N >= 2) on a turntable."""
    if int(n) != n or not 2 <= n <= MAX_N:
        raise ValueError(f"BORG size N must be an integer from 2 to {MAX_N}, got {n!r}")
    if not (math.isfinite(spacing_m) and 0 < spacing_m <= 10.0):
        raise ValueError(f"node spacing must be a positive number of metres up to 10, got {spacing_m!r} m")
    n = int(n)
    if n == 3:
        return _build_table1(spacing_m)
    return _build_general(n, spacing_m)


# --- N = 3: Table 1 ------------------------------------------------------------------------------
def _build_table1(s: float) -> BorgModel:
    L = 3 * s
    grid = _Grid(3, s)
    faces = _faces(L)
    modules: list[Module] = []
    poses: dict[int, Pose3] = {}
    tag_face: dict[int, int] = {}
    corner_cells = {1: (0, 0), 2: (0, 2), 3: (2, 2), 4: (2, 0)}

    def add(name: str, kind: ModuleKind, face_no: int, tags: list[tuple[int, np.ndarray, bool]],
            nodes: tuple[int, ...], edges: tuple[tuple[int, int], ...]) -> None:
        f = faces[face_no]
        for tag_id, anchor, vertical in tags:
            poses[tag_id] = _tag_pose(f, anchor, vertical)
            tag_face[tag_id] = face_no
        modules.append(Module(name, kind, tuple(t for t, _, _ in tags), nodes, edges,
                              _anchor_frame(f, tags[0][1]), face_no))

    def deployable(name: str, face_no: int, cell: tuple[int, int, int], tag_b: int, tag_t: int) -> None:
        f = faces[face_no]
        if face_no == 1 and cell == (1, 1, 1):  # the centre cell, seen through face 1
            anchor_b = f.point(s, s, s)
        else:
            anchor_b = f.point(0.0, 0.0, cell[2] * s)
        add(name, "deployable", face_no,
            [(tag_b, anchor_b, False), (tag_t, anchor_b + [0.0, 0.0, s], False)],
            grid.cell_nodes(*cell), grid.cell_edges(*cell))

    def hstrut(name: str, face_no: int, z: float, tag: int) -> None:
        f = faces[face_no]
        a, b = f.point(s, 0.0, z), f.point(2 * s, 0.0, z)
        add(name, "closeout_strut", face_no, [(tag, a, False)], (grid.node(a), grid.node(b)),
            (grid._edge(a, b),))

    def vstrut(name: str, face_no: int, tag: int) -> None:
        f = faces[face_no]
        a, b = f.point(s, 0.0, s), f.point(s, 0.0, 2 * s)
        add(name, "closeout_strut", face_no, [(tag, b, True)], (grid.node(a), grid.node(b)),
            (grid._edge(a, b),))

    def hsquare(name: str, face_no: int, z: float, tag: int) -> None:
        f = faces[face_no]
        c = [f.point(s, 0.0, z), f.point(2 * s, 0.0, z), f.point(2 * s, s, z), f.point(s, s, z)]
        nodes, edges = grid.square(c)
        add(name, "closeout_square", face_no, [(tag, c[0], False)], nodes, edges)

    def vsquare(name: str, face_no: int, tag: int) -> None:
        f = faces[face_no]
        c = [f.point(0.0, 0.0, s), f.point(0.0, 0.0, 2 * s), f.point(0.0, s, 2 * s), f.point(0.0, s, s)]
        nodes, edges = grid.square(c)
        add(name, "closeout_square", face_no, [(tag, c[1], True)], nodes, edges)

    def corner_cell(face_no: int, layer: int) -> tuple[int, int, int]:
        ci, cj = corner_cells[face_no]
        return (ci, cj, layer)

    hsquare("1P", 1, s, 0)
    for face_no, (name, tb) in enumerate([("2D", 1), ("3D", 3), ("4D", 5), ("5D", 7)], start=1):
        deployable(name, face_no, corner_cell(face_no, 0), tb, tb + 1)
    for face_no, (name, tag) in enumerate([("6S", 9), ("7S", 10), ("8S", 11), ("9S", 12)], start=1):
        hstrut(name, face_no, 0.0, tag)
    deployable("10CT", 1, (1, 1, 1), 13, 14)
    deployable("11D", 1, corner_cell(1, 2), 15, 16)
    vstrut("12S", 1, 17)
    deployable("13D", 2, corner_cell(2, 2), 18, 19)
    vstrut("14S", 2, 20)
    vsquare("15P", 1, 21)
    hstrut("16S", 1, L, 22)
    deployable("17D", 3, corner_cell(3, 2), 23, 24)
    vstrut("18S", 3, 25)
    vsquare("19P", 2, 26)
    hstrut("20S", 2, L, 27)
    deployable("21D", 4, corner_cell(4, 2), 28, 29)
    vstrut("22S", 4, 30)
    vsquare("23P", 3, 31)
    hstrut("24S", 3, L, 32)
    vsquare("25P", 4, 33)
    hstrut("26S", 4, L, 34)
    hsquare("27P", 1, 2 * s, 35)

    turntable, tt_poses = _turntable(L, first_id=36, face_of=lambda k: 1 + k // 3)
    poses.update(tt_poses)
    for k, tid in enumerate(turntable.tag_ids):
        tag_face[tid] = 1 + k // 3

    module_of = {t: m.name for m in modules for t in m.tags}
    tags = {
        tid: TagSpec(tid, label, module_of.get(tid, "turntable"), poses[tid], related, tag_face[tid])
        for tid, (label, related) in TABLE1.items()
    }
    assert [m.name for m in modules] == [
        "1P", "2D", "3D", "4D", "5D", "6S", "7S", "8S", "9S", "10CT", "11D", "12S", "13D", "14S",
        "15P", "16S", "17D", "18S", "19P", "20S", "21D", "22S", "23P", "24S", "25P", "26S", "27P"]
    return _finish(3, s, grid, modules, tags, turntable)


def turntable_radius_m(size_m: float) -> float:
    """The rim radius of the turntable under a BORG `size_m` wide: its corners plus a margin."""
    return float(size_m / np.sqrt(2) + TURNTABLE_MARGIN_M)


def _turntable(L: float, first_id: int, face_of) -> tuple[Turntable, dict[int, Pose3]]:
    """Twelve rim tags, three per face: under the face's right-hand column, its middle, its left.
    Angles (about the axis, from +x) run 210, 180, ..., -120 deg: ids increase clockwise."""
    c = np.array([L / 2, L / 2, 0.0])
    radius = turntable_radius_m(L)
    poses = {}
    ids = tuple(range(first_id, first_id + 12))
    for k, tid in enumerate(ids):
        phi = np.deg2rad(210.0 - 30.0 * k)
        out = np.array([np.cos(phi), np.sin(phi), 0.0])
        up = np.array([0.0, 0.0, 1.0])
        R = np.column_stack([np.cross(up, out), up, out])
        poses[tid] = pose(R, c + radius * out + [0.0, 0.0, TURNTABLE_TAG_HEIGHT_M])
    return Turntable((L / 2, L / 2), float(radius), ids), poses


def _relation_kind(a: TagSpec, b: TagSpec, kinds: dict[str, ModuleKind]) -> RelationKind:
    if a.module == "turntable" or b.module == "turntable":
        return "turntable"
    if a.module == b.module:
        return "deployable"
    ka, kb = kinds[a.module], kinds[b.module]
    if "closeout_strut" in (ka, kb):
        return "closeout_strut"
    if "closeout_square" in (ka, kb):
        return "closeout_square"
    return "node"


def _finish(n: int, s: float, grid: _Grid, modules: list[Module], tags: dict[int, TagSpec],
            turntable: Turntable) -> BorgModel:
    kinds = {m.name: m.kind for m in modules}
    pairs: dict[tuple[int, int], RelationKind] = {}
    for t in tags.values():
        for r in t.related:
            key = (min(t.id, r), max(t.id, r))
            pairs.setdefault(key, _relation_kind(tags[key[0]], tags[key[1]], kinds))
    relations = tuple(Relation(a, b, k) for (a, b), k in sorted(pairs.items()))
    edges = tuple(sorted({e for m in modules for e in m.edges}))
    return BorgModel(n, s, grid.nodes, edges, tuple(modules), dict(sorted(tags.items())), turntable, relations)


# --- other N: the same rules, generated --------------------------------------------------------------
def _build_general(n: int, s: float) -> BorgModel:
    """Deployables on the body-centred checkerboard (cells whose indices are all even or all odd),
    in layers bottom to top; every grid edge no deployable brings is closed out, by a close-out
    square where two such edges face each other across a square whose other two sides are
    deployable struts, else by a close-out strut.  Names follow the paper's scheme (assembly
    number + D / CT / S / P), tag ids follow assembly order, turntable tags come last."""
    L = n * s
    grid = _Grid(n, s)
    faces = _faces(L)
    dep_cells = [(i, j, k) for k in range(n) for j in range(n) for i in range(n)
                 if len({i % 2, j % 2, k % 2}) == 1]
    covered: set[tuple[int, int]] = set()
    for c in dep_cells:
        covered.update(grid.cell_edges(*c))
    all_edges = set()
    for ci in range(n):
        for cj in range(n):
            for ck in range(n):
                all_edges.update(grid.cell_edges(ci, cj, ck))
    free = sorted(all_edges - covered, key=lambda e: (grid.nodes[e[0]][2] + grid.nodes[e[1]][2], e))

    # Pair free edges into squares: two parallel free edges one spacing apart whose connecting
    # sides are both deployable struts.
    squares: list[tuple[tuple[int, int], tuple[int, int]]] = []
    used: set[tuple[int, int]] = set()
    free_set = set(free)
    for e in free:
        if e in used:
            continue
        p, q = grid.nodes[e[0]], grid.nodes[e[1]]
        axis = int(np.argmax(np.abs(q - p)))
        for d in range(3):
            if d == axis:
                continue
            for sign in (1.0, -1.0):
                off = np.zeros(3)
                off[d] = sign * s
                p2, q2 = p + off, q + off
                try:
                    e2 = grid._edge(p2, q2)
                    s1, s2 = grid._edge(p, p2), grid._edge(q, q2)
                except ValueError:
                    continue
                if e2 in free_set and e2 not in used and s1 in covered and s2 in covered:
                    squares.append((e, e2))
                    used.update((e, e2))
                    break
            if e in used:
                break
    struts = [e for e in free if e not in used]

    def nearest_face(p: np.ndarray) -> int:
        c = np.array([L / 2, L / 2])
        d = p[:2] - c
        return {(-1, 0): 1, (0, 1): 2, (1, 0): 3, (0, -1): 4}[
            (int(np.sign(d[0])) if abs(d[0]) >= abs(d[1]) else 0,
             int(np.sign(d[1])) if abs(d[1]) > abs(d[0]) else 0)] if np.any(np.abs(d) > 1e-9) else 1

    def rightmost(face_no: int, pts: list[np.ndarray]) -> np.ndarray:
        f = faces[face_no]
        return min(pts, key=lambda p: (float(np.dot(p - f.corner, f.left)), float(np.dot(p, f.normal)) * -1, p[2]))

    items: list[tuple[float, str, object]] = []
    for c in dep_cells:
        items.append((c[2] * s, "D", c))
    for sq in squares:
        items.append((min(grid.nodes[sq[0][0]][2], grid.nodes[sq[1][0]][2]) + 1e-3, "P", sq))
    for e in struts:
        items.append((min(grid.nodes[e[0]][2], grid.nodes[e[1]][2]) + 2e-3, "S", e))
    items.sort(key=lambda it: it[0])

    modules: list[Module] = []
    tags: dict[int, TagSpec] = {}
    next_tag = 0
    centre_cell = ((n - 1) // 2,) * 3 if n % 2 == 1 else None
    for number, (_, kind, obj) in enumerate(items, start=1):
        if kind == "D":
            c = obj  # type: ignore[assignment]
            nodes_ = grid.cell_nodes(*c)
            pts = [grid.nodes[i] for i in nodes_]
            face_no = nearest_face(np.mean(pts, axis=0))
            f = faces[face_no]
            bottom = [p for p in pts if abs(p[2] - c[2] * s) < 1e-9]
            anchor = rightmost(face_no, [p for p in bottom if abs(np.dot(p - f.corner, -f.normal) -
                                                              min(np.dot(b - f.corner, -f.normal) for b in bottom)) < 1e-9])
            name = f"{number}{'CT' if c == centre_cell else 'D'}"
            tb, tt = next_tag, next_tag + 1
            next_tag += 2
            for tid, a, suffix in ((tb, anchor, "B"), (tt, anchor + [0, 0, s], "T")):
                tags[tid] = TagSpec(tid, f"{name}-{suffix}", name, _tag_pose(f, a, False), (), face_no)
            modules.append(Module(name, "deployable", (tb, tt), nodes_, grid.cell_edges(*c),
                                  _anchor_frame(f, anchor), face_no))
        else:
            edges_ = [obj] if kind == "S" else list(obj)  # type: ignore[list-item]
            pts = [grid.nodes[i] for e in edges_ for i in e]
            face_no = nearest_face(np.mean(pts, axis=0))
            f = faces[face_no]
            outer = max(float(np.dot(p, f.normal)) for p in pts)
            front = [p for p in pts if abs(float(np.dot(p, f.normal)) - outer) < 1e-9]
            vertical = all(abs(grid.nodes[e[0]][2] - grid.nodes[e[1]][2]) > 1e-9 for e in edges_)
            if vertical:
                anchor = max(front, key=lambda p: (p[2], -float(np.dot(p - f.corner, f.left))))
                anchor = rightmost(face_no, [p for p in front if abs(p[2] - anchor[2]) < 1e-9])
            else:
                anchor = rightmost(face_no, front)
            name = f"{number}{kind}"
            tid = next_tag
            next_tag += 1
            # Two members can share their right-hand front node; the later one's tag then moves to
            # its next front node (then further up its bracket) so that no two tags overlap.
            order = sorted(front, key=lambda p: (float(np.dot(p - anchor, f.left)) < -1e-9,
                                                 float(np.dot(p - anchor, f.left)), -p[2] if vertical else p[2]))
            candidates = [_tag_pose(f, a, vertical) for a in order]
            candidates += [pose(f.R, c.translation() + [0.0, 0.0, 0.12 * k]) for k in (1, 2) for c in candidates[:1]]
            tag_pose = next((c for c in candidates if all(
                np.linalg.norm(c.translation() - t.structure_T_tag.translation()) > 1.2 * TAG_SIZE_M
                for t in tags.values())), candidates[0])
            tags[tid] = TagSpec(tid, name, name, tag_pose, (), face_no)
            if kind == "S":
                e = edges_[0]
                mod_edges: tuple[tuple[int, int], ...] = (e,)
                mod_nodes = e
            else:
                (a0, a1), (b0, b1) = edges_
                pa0, pa1, pb0, pb1 = (grid.nodes[i] for i in (a0, a1, b0, b1))
                mod_nodes, mod_edges = grid.square([pa0, pa1, pb1, pb0])
            modules.append(Module(name, "closeout_strut" if kind == "S" else "closeout_square", (tid,),
                                  tuple(mod_nodes), mod_edges, _anchor_frame(f, anchor), face_no))

    turntable, tt_poses = _turntable(L, first_id=next_tag, face_of=lambda k: 1 + k // 3)
    for k, tid in enumerate(turntable.tag_ids):
        tags[tid] = TagSpec(tid, f"TT{k + 1}", "turntable", tt_poses[tid], (), 1 + k // 3)

    # Relations: B-T of each deployable; a close-out member to the nearest tag of each module it
    # shares a node with; turntable tags to their ring neighbours and to base modules above them.
    rel: dict[int, list[int]] = {t: [] for t in tags}

    def link(a: int, b: int) -> None:
        if b not in rel[a]:
            rel[a].append(b)
        if a not in rel[b]:
            rel[b].append(a)

    node_sets = {m.name: set(m.nodes) for m in modules}
    for m in modules:
        if m.kind == "deployable":
            link(*m.tags)
    for m in modules:
        if m.kind == "deployable":
            continue
        me = tags[m.tags[0]].structure_T_tag.translation()
        for other in modules:
            if other is m or not (node_sets[m.name] & node_sets[other.name]):
                continue
            best = min(other.tags, key=lambda t: np.linalg.norm(tags[t].structure_T_tag.translation() - me))
            link(m.tags[0], best)
    ring = list(turntable.tag_ids)
    base_tags = [m.tags[0] for m in modules if min(grid.nodes[i][2] for i in m.nodes) < 1e-9]
    for k, tid in enumerate(ring):
        link(tid, ring[(k + 1) % len(ring)])
        p = tags[tid].structure_T_tag.translation()
        best = min(base_tags, key=lambda t: np.linalg.norm(tags[t].structure_T_tag.translation() - p))
        link(tid, best)
    tags = {t: TagSpec(s_.id, s_.label, s_.module, s_.structure_T_tag, tuple(rel[t]), s_.face)
            for t, s_ in tags.items()}
    return _finish(n, s, grid, modules, tags, turntable)


def to_json(model: BorgModel) -> dict:
    """The `lab structure borg --json` shape."""
    from lab.core.geometry import to_xyzquat

    return {
        "structure": f"borg:{model.n}",
        "spacing_m": model.spacing_m,
        "modules": [{"name": m.name, "type": m.kind, "tags": list(m.tags), "face": m.face,
                     "nodes": list(m.nodes)} for m in model.modules],
        "tags": [{"id": t.id, "label": t.label, "module": t.module, "face": t.face, "size_m": t.size_m,
                  "pose": [round(v, 9) for v in to_xyzquat(t.structure_T_tag)], "related": list(t.related)}
                 for t in model.tags.values()],
        "relations": [{"tags": [r.a, r.b], "kind": r.kind} for r in model.relations],
        "nodes": [{"id": i, "position_m": [round(float(v), 9) for v in p]} for i, p in enumerate(model.nodes)],
        "edges": [{"nodes": [a, b], "length_m": round(float(np.linalg.norm(model.nodes[a] - model.nodes[b])), 9)}
                  for a, b in model.edges],
        "turntable": {"center_xy_m": list(model.turntable.center_xy_m), "radius_m": model.turntable.radius_m,
                      "tags": list(model.turntable.tag_ids)},
    }
