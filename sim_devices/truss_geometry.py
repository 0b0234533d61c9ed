"""The BORG truss as solid things that hide tags: its struts and node bodies, where they really are.

`truss_occluders` turns the design model (`lab.core.structures.borg`), the modules placed so far and
their TRUE poses (a module offset, a deployable stopped short) into 3-D occluders in the
structure frame: every strut of a placed module as a cylinder between its two nodes, every node a
placed strut ends at as a sphere.  `sim_devices.render_truss` draws them in front of (and behind)
the tags.  Pure functions, SI units, poses as `lab.core.geometry.Pose3`.

Sizes:
- struts: 19.05 mm (3/4 in) diameter, the strut end that enters a node socket
  (`estimation.semantics.STRUT_END_DIAMETER_M`); the whole member is taken to be that size;
- node bodies: spheres of 50 mm diameter.  A node's socket has a 40 mm chamfered mouth
  (`estimation.semantics.SOCKET_MOUTH_M`), so the hub holding it is a little wider than that.

Where the struts run: the design's edges (`Module.edges`): a deployable's twelve cell edges, a
close-out strut's one edge, a close-out square's four sides and its diagonal.  An edge two modules
bring (a square's side that is a deployable's strut) and a node many modules share are drawn once:
a node where the first placed module that brings it puts it (assembly order: usually the
deployable the others are attached to), every strut between its two nodes as drawn, so the truss
stays connected.

The truth applied: a module offset moves and turns the nodes it is first to bring rigidly about
its anchor (`BorgTruth.set_module_offset`), and with them its struts; a deployable deployed to
height h < spacing has its top face lowered by spacing - h (the same drop as its top tag), its
four side struts shortened accordingly, and the members attached to its top nodes later follow
them.  A close-out member placed off its design pose thus moves its tag, but not the nodes the
modules before it brought (a few millimetres).  A few millimetres can still carry a strut through a
tag's card, which no real truss can do: a strut that would is moved clear of the card, behind it
(`_clear_of_cards`; the cards are the placed modules' tags, where they really are).

Left out: the tags' brackets and the tag cards' thickness; the turntable plate and the rim tags'
mounts; the Stewart platform, the lift and anything else of the rig; the hinges, knees and
latches of a deployable (a partly deployed one keeps straight, shorter side struts instead of
folding at its hinges); socket cups, plungers and fasteners (a node is a plain sphere); strut
ends that stop at a socket instead of at the node's centre (hidden inside the sphere anyway); a
tag knocked off its spot (`tag_displaced`) moves only the tag, not its member.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from lab.core.geometry import Pose3
from lab.core.structures.borg import BorgModel

__all__ = ["STRUT_DIAMETER_M", "NODE_DIAMETER_M", "TagCard", "TrussOccluders", "truss_occluders",
           "module_node_positions", "in_camera"]

STRUT_DIAMETER_M = 0.01905     # 3/4 in
NODE_DIAMETER_M = 0.050


@dataclass(frozen=True)
class TagCard:
    """A tag's card where it really is: the black square and its quiet zone, a flat square."""

    structure_T_tag: Pose3
    half_width_m: float


@dataclass(frozen=True)
class TrussOccluders:
    """Cylinders (struts) and spheres (nodes), in one frame (structure or camera)."""

    strut_a: np.ndarray          # (S, 3) one end of each strut's axis
    strut_b: np.ndarray          # (S, 3) the other end
    strut_radius_m: float
    node_centre: np.ndarray      # (M, 3)
    node_radius_m: float
    strut_edge: tuple[tuple[int, int], ...] = ()   # the design edge (node ids) of each strut
    node_id: tuple[int, ...] = ()                  # the design node id of each sphere

    @property
    def n_struts(self) -> int:
        return len(self.strut_a)

    @property
    def n_nodes(self) -> int:
        return len(self.node_centre)


def module_node_positions(model: BorgModel, name: str, structure_T_module: Pose3 | None = None,
                          deployed_height_m: float | None = None) -> dict[int, np.ndarray]:
    """Where module `name`'s nodes really are (structure frame): its design nodes, a deployable's
    top face lowered when it is deployed to `deployed_height_m` < spacing, then the whole moved by
    the module's true pose `structure_T_module` against its design one (None: the design)."""
    m = model.module_by_name[name]
    pts = {int(i): np.array(model.nodes[i], dtype=float) for i in m.nodes}
    if m.kind == "deployable" and deployed_height_m is not None and deployed_height_m < model.spacing_m:
        bottom = min(p[2] for p in pts.values())
        drop = model.spacing_m - float(deployed_height_m)
        for i, p in pts.items():
            if p[2] > bottom + 1e-9:
                pts[i] = p - np.array([0.0, 0.0, drop])
    if structure_T_module is not None:
        fix = structure_T_module.compose(m.structure_T_module.inverse()).matrix()
        for i, p in pts.items():
            pts[i] = fix[:3, :3] @ p + fix[:3, 3]
    return pts


def truss_occluders(model: BorgModel, placed: Sequence[str],
                    structure_T_module: Mapping[str, Pose3] | None = None,
                    deployed_height_m: Mapping[str, float] | None = None,
                    *, cards: Sequence[TagCard] = (), strut_diameter_m: float = STRUT_DIAMETER_M,
                    node_diameter_m: float = NODE_DIAMETER_M) -> TrussOccluders:
    """The struts and nodes of the modules `placed` (in placement order), in the structure frame,
    each module at its true pose (`structure_T_module`, default the design) and deployed height
    (`deployed_height_m`, default full).  Each node once, where the first placed module bringing
    it puts it; each edge once, between its nodes.  A strut that would cross one of the `cards` (the
    placed modules' tags where they really are) is moved off it, to the side its axis is on, by as
    much as it would cross (`_clear_of_cards`)."""
    poses = structure_T_module or {}
    heights = deployed_height_m or {}
    node_at: dict[int, np.ndarray] = {}
    edges: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    for name in placed:
        m = model.module_by_name[name]
        pts = module_node_positions(model, name, poses.get(name), heights.get(name))
        for e in m.edges:
            key = (min(e), max(e))
            if key not in edges:
                for i in e:
                    node_at.setdefault(int(i), pts[i])
                edges[key] = (node_at[e[0]], node_at[e[1]])
    keys = tuple(edges)
    a = np.array([edges[k][0] for k in keys]).reshape(-1, 3)
    b = np.array([edges[k][1] for k in keys]).reshape(-1, 3)
    _clear_of_cards(a, b, strut_diameter_m / 2.0, cards)
    nodes = tuple(sorted(node_at))
    c = np.array([node_at[i] for i in nodes]).reshape(-1, 3)
    return TrussOccluders(a, b, strut_diameter_m / 2.0, c, node_diameter_m / 2.0, keys, nodes)


def in_camera(occ: TrussOccluders, camera_T_structure: Pose3) -> TrussOccluders:
    """The same occluders in the camera frame."""
    M = camera_T_structure.matrix()
    R, t = M[:3, :3], M[:3, 3]
    return TrussOccluders(occ.strut_a @ R.T + t, occ.strut_b @ R.T + t, occ.strut_radius_m,
                          occ.node_centre @ R.T + t, occ.node_radius_m, occ.strut_edge, occ.node_id)


# samples along a strut for its nearest approach to a card: a 0.7 m diagonal in 1.75 mm steps
_SAMPLES = 401
_CLEARANCE_M = 1e-4


def _clear_of_cards(a: np.ndarray, b: np.ndarray, radius_m: float, cards: Sequence[TagCard]) -> None:
    """Move, in place, each strut a[s]-b[s] whose surface would cross one of `cards` to just clear of it.

    A card is glued to the outside of its module's members, and a member cannot pass through it.
    The truth here holds every module rigid at its own pose while a strut runs between node bodies
    its neighbours placed: a module turned 1.5 degrees moves a node some millimetres.  In 13 of 80
    seeded layer studies (`lab bench layers`, N = 3..10, seeds 0-9) that ran a strut 0.3-5.1 mm
    through a tag's card (14 tags: 13 by their own module's strut, 1 by a neighbour's) -- a sliver
    no real truss shows, across the quiet zone from every direction, which left the tag unreadable
    (N = 9 seed 1: 235P `unverified`).  The strut is moved along the line from the card to its axis
    (the card's normal where the axis passes over it), to the side of the card its axis is on:
    behind a card glued on it, in front of one it lies on.  Left out: a strut whose axis runs
    through a card (none in those studies) goes to the side its middle is on, however far.
    """
    if not cards or not len(a):
        return
    M = np.array([c.structure_T_tag.matrix() for c in cards])
    R, t = M[:, :3, :3], M[:, :3, 3]
    hw = np.array([c.half_width_m for c in cards])
    # the (card, strut) pairs whose axis comes within reach of the card's disc: first the struts
    # whose box, grown by that reach, holds the card's centre (a 10x10x10: 926 cards, 3846 struts)
    reach = hw * math.sqrt(2.0) + radius_m
    lo, hi = np.minimum(a, b) - reach.max(), np.maximum(a, b) + reach.max()
    inside = np.ones((len(cards), len(a)), dtype=bool)
    for k in range(3):
        inside &= (t[:, None, k] >= lo[None, :, k]) & (t[:, None, k] <= hi[None, :, k])
    ci, si = np.nonzero(inside)
    d = b[si] - a[si]
    w = t[ci] - a[si]
    s = np.clip((w * d).sum(1) / np.maximum((d * d).sum(1), 1e-12), 0.0, 1.0)
    near = np.linalg.norm(w - s[:, None] * d, axis=1) < reach[ci]
    ci, si = ci[near], si[near]
    crossing = _nearest(a[si], b[si], R[ci], t[ci], hw[ci])[2].min(axis=0) < radius_m
    for c, i in zip(ci[crossing], si[crossing]):       # a few a study: one at a time, each on the moved strut
        for _ in range(3):                              # a move may bring another stretch nearest
            p, q, gap = (x[:, 0] for x in _nearest(a[i:i + 1], b[i:i + 1], R[c:c + 1], t[c:c + 1], hw[c:c + 1]))
            j = int(np.argmin(gap))
            if gap[j] >= radius_m:
                break
            if gap[j] > 1e-9:
                away = (p[j] - q[j]) / gap[j]
            else:                                       # the axis meets the card: the side its middle is on
                away = np.array([0.0, 0.0, 1.0 if p[0, 2] + p[-1, 2] >= 0.0 else -1.0])
            shift = R[c] @ ((radius_m - gap[j] + _CLEARANCE_M) * away)
            a[i] += shift
            b[i] += shift


_U = np.linspace(0.0, 1.0, _SAMPLES)[:, None, None]


def _nearest(a: np.ndarray, b: np.ndarray, R: np.ndarray, t: np.ndarray,
             hw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points along each strut a[k]-b[k] in its card's frame (R[k], t[k]: the card is |x|, |y| <=
    hw[k], z = 0), the card's nearest point to each, and their distance: (samples, P, 3) twice and
    (samples, P)."""
    la = np.einsum("pij,pi->pj", R, a - t)
    lb = np.einsum("pij,pi->pj", R, b - t)
    p = la[None] + _U * (lb - la)[None]
    q = np.concatenate([np.clip(p[..., :2], -hw[None, :, None], hw[None, :, None]), np.zeros(p.shape[:2] + (1,))],
                       axis=2)
    return p, q, np.linalg.norm(p - q, axis=2)
