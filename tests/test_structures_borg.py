"""The BORG design model: Table 1 of the SF-GraphSLAM paper, counts for other N, tag geometry."""

import json

import numpy as np
import pytest

from lab.core.geometry import from_xyzquat, pose_error
from lab.core.structures.borg import build_borg, to_json

# Table 1 as printed in the paper (tag: opti name, related tags), typed in independently of the
# module under test so that a transcription slip in either shows up here.
PAPER_TABLE1 = """
0 1P 1 37 | 1 2D-B 0 2 9 36 | 2 2D-T 1 17 21 | 3 3D-B 4 10 39 | 4 3D-T 3 20 26 | 5 4D-B 6 11 42
6 4D-T 5 25 31 | 7 5D-B 8 12 45 | 8 5D-T 7 30 33 | 9 6S 1 37 | 10 7S 3 40 | 11 8S 5 43 | 12 9S 7 46
13 10CT-B 14 2 | 14 10CT-T 13 15 | 15 11D-B 16 17 21 | 16 11D-T 15 22 | 17 12S 2 15
18 13D-B 19 20 26 | 19 13D-T 18 27 | 20 14S 4 18 | 21 15P 2 15 | 22 16S 16 | 23 17D-B 24 25 31
24 17D-T 23 32 | 25 18S 6 23 | 26 19P 4 18 | 27 20S 19 | 28 21D-B 29 30 33 | 29 21D-T 28 34
30 22S 8 28 | 31 23P 6 23 | 32 24S 24 | 33 25P 8 28 | 34 26S 29 | 35 27P 16 | 36 TT1 1 37 47
37 TT2 0 9 36 38 | 38 TT3 37 39 | 39 TT3 3 38 40 | 40 TT4 10 39 41 | 41 TT5 40 42 | 42 TT5 5 41 43
43 TT6 11 42 44 | 44 TT7 43 45 | 45 TT7 7 44 46 | 46 TT8 12 45 47 | 47 TT1 36 46
"""


def _paper_rows():
    for row in PAPER_TABLE1.replace("\n", "|").split("|"):
        parts = row.split()
        if parts:
            yield int(parts[0]), parts[1], tuple(int(p) for p in parts[2:])


def test_table1_reproduced_exactly():
    model = build_borg(3)
    rows = list(_paper_rows())
    assert len(rows) == 48
    assert sorted(model.tags) == list(range(48))
    for tag_id, label, related in rows:
        tag = model.tags[tag_id]
        assert tag.label == label
        assert tag.related == related, tag_id
        expected_module = "turntable" if label.startswith("TT") else label.split("-")[0]
        assert tag.module == expected_module


def test_paper_module_set_and_order():
    model = build_borg(3)
    names = [m.name for m in model.modules]
    assert names == [f"{i}{s}" for i, s in enumerate(
        "P D D D D S S S S CT D S D S P S D S P S D S P S P S P".split(), start=1)]
    kinds = [m.kind for m in model.modules]
    assert kinds.count("deployable") == 9
    assert kinds.count("closeout_strut") == 12
    assert kinds.count("closeout_square") == 6
    assert len(model.module_tag_ids) == 36 and len(model.turntable.tag_ids) == 12
    for m in model.modules:
        assert len(m.tags) == (2 if m.kind == "deployable" else 1)


@pytest.mark.parametrize("n", [2, 3, 4, 5])
def test_counts_for_n(n):
    model = build_borg(n)
    deployables = ((n + 1) // 2) ** 3 + (n // 2) ** 3  # cells with all-even or all-odd indices
    kinds = [m.kind for m in model.modules]
    assert kinds.count("deployable") == deployables
    assert len(model.nodes) == (n + 1) ** 3
    assert len(model.tags) == 2 * deployables + (len(model.modules) - deployables) + 12
    free_edges = 3 * n * (n + 1) ** 2 - 12 * deployables
    if n == 3:
        # the paper's 12 struts and 6 squares close out 24 of the 36 gap edges (docs/borg.md)
        assert kinds.count("closeout_strut") + 2 * kinds.count("closeout_square") == 24
    else:
        assert kinds.count("closeout_strut") + 2 * kinds.count("closeout_square") == free_edges
        grid_edges = {(a, b) for a in range(len(model.nodes)) for b in range(a + 1, len(model.nodes))
                      if abs(np.linalg.norm(model.nodes[a] - model.nodes[b]) - model.spacing_m) < 1e-9}
        assert grid_edges <= set(model.edges), "every grid edge is closed out"
    # relations are symmetric pairs of existing tags, and no two tags overlap
    for r in model.relations:
        assert r.a in model.tags and r.b in model.tags and r.a < r.b
    pos = np.array([t.structure_T_tag.translation() for t in model.tags.values()])
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(len(pos))
    assert d.min() > 0.1


def test_tags_face_outward_and_deployable_relation_is_half_a_metre_up():
    model = build_borg(3)
    centre = np.array([0.75, 0.75, 0.75])
    for t in model.tags.values():
        T = t.structure_T_tag
        z_axis, y_axis = T.rotation().matrix()[:, 2], T.rotation().matrix()[:, 1]
        outward = T.translation() - centre
        outward[2] = 0.0
        assert np.dot(z_axis, outward) > 0, t.id
        assert np.allclose(y_axis, [0, 0, 1]), t.id
    for m in model.modules:
        if m.kind == "deployable":
            rel = model.design_between(*m.tags)
            # the paper's r = (0, 0, 0.5, 0, 0, 0): 0.5 m straight up, no rotation
            assert np.allclose(rel.translation(), [0, 0.5, 0]) and np.allclose(rel.rotation().matrix(), np.eye(3))


def test_origin_is_outer_corner_of_first_deployable():
    model = build_borg(3)
    first = model.module_by_name["2D"]
    assert np.allclose(model.nodes[min(first.nodes)], [0, 0, 0])
    assert np.all(model.nodes.min(axis=0) == 0)


def test_turntable_turns_faces_to_the_camera():
    model = build_borg(3)
    # a camera on the world -x axis looks at face 1 at angle 0 and at face k after (k-1) quarter turns
    for face in (1, 2, 3, 4):
        world_T_structure = model.world_T_structure((face - 1) * np.pi / 2)
        for t in model.tags.values():
            if t.face == face:
                normal = world_T_structure.compose(t.structure_T_tag).rotation().matrix()[:, 2]
                assert normal[0] < -0.5, (face, t.id)


def test_bad_n_is_refused():
    with pytest.raises(ValueError, match="N must be an integer from 2 to 10"):
        build_borg(1)
    with pytest.raises(ValueError, match="N must be an integer from 2 to 10"):
        build_borg(100)      # a size no turntable carries: refused, not built for minutes


def test_cli_json_round_trip(lab):
    out = lab(["structure", "borg", "--n", "3", "--json"], check=True).stdout
    data = json.loads(out)
    assert {"modules", "tags", "nodes", "edges"} <= set(data)
    assert len(data["tags"]) == 48 and len(data["modules"]) == 27 and len(data["nodes"]) == 64
    model = build_borg(3)
    for t in data["tags"]:
        assert set(t) >= {"id", "module", "pose", "related"}
        dt, dr = pose_error(from_xyzquat(t["pose"]), model.tags[t["id"]].structure_T_tag)
        assert dt < 1e-6 and dr < 1e-6
    assert to_json(model)["modules"][1] == {"name": "2D", "type": "deployable", "tags": [1, 2], "face": 1,
                                            "nodes": list(model.modules[1].nodes)}
