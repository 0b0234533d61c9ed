"""What a view gives the graph: the module's own tags' sightings and those of the rig's
`near_tags_per_view` other tags nearest it (procedures/borg_measure.py, `Measurement.near_sightings`)."""

from __future__ import annotations

import numpy as np
import pytest

from estimation.fiducials import Detection
from lab.core.config import VerificationConfig
from lab.core.geometry import Pose3
from lab.core.structures.borg import build_borg
from procedures.borg_measure import Measurement


class _Camera:
    K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])
    dist = np.zeros(5)


def _seen(tag: int) -> Detection:
    return Detection(tag, np.zeros((4, 2)), Pose3(), np.eye(6), 0.1, 10.0, False, 0.1)


def _gap(model, module: str, tag: int) -> float:
    own = [model.tags[t].structure_T_tag.translation() for t in model.module_by_name[module].tags]
    return min(float(np.linalg.norm(p - model.tags[tag].structure_T_tag.translation())) for p in own)


@pytest.mark.parametrize("k", [5, 2])
def test_a_view_gives_the_graph_its_modules_tags_and_the_k_nearest_others(k):
    model = build_borg(5)
    module = model.modules[60].name
    mine = list(model.module_by_name[module].tags)
    others = sorted((t for t in model.tags if t not in mine), key=lambda t: (_gap(model, module, t), t))
    m = Measurement(model, _Camera(), {"near_tags_per_view": k})
    # in the detector's order (not by distance): far ones first, the module's own last, an unknown id
    # (the estimator's to refuse)
    seen = [_seen(t) for t in others[20:30] + others[:k + 3] + mine] + [_seen(99999)]
    got = [d.tag_id for d in m.near_sightings(module, seen)]
    assert got == others[:k] + mine + [99999]
    # a view that reads no more than k others gives them all
    few = [_seen(t) for t in others[40:40 + k] + mine]
    assert m.near_sightings(module, few) == few


def test_zero_gives_every_sighting_and_a_run_takes_five():
    model = build_borg(4)
    seen = [_seen(t) for t in model.tags]
    m = Measurement(model, _Camera(), {"near_tags_per_view": 0})
    assert m.near_sightings(model.modules[-1].name, seen) == seen
    assert Measurement(model, _Camera()).near_tags_per_view == 0        # the estimator alone: every sighting
    assert VerificationConfig().near_tags_per_view == 5                   # a run: the rig's [verification]
