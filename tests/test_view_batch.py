"""The batch solve's view factors evaluated together (`view_batch.ViewBatch`, issue 21): each view's
factor must hand GTSAM exactly the rows its own `corner_view_factor` computes -- prepared or not,
with print scales, the lens, Huber and a tag behind the camera -- and the batch solve must be the
per-view factors' solve to the bit."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimation import levenberg_marquardt
from estimation.fiducials import tag_object_points
from estimation.rig_model import DISTORTION, CornerSighting, corner_view_factor, radial_basis
from estimation.view_batch import TAGS_PER_FACTOR, BatchCost, ViewBatch
from lab.core.geometry import Pose3, Rot3
from test_corner_view_factor import CAL, K, _slam, _view
from test_levenberg_marquardt import _params, _same

C, T, S = gtsam.symbol_shorthand.C, gtsam.symbol_shorthand.T, gtsam.symbol_shorthand.S


def _views(lens: bool):
    """Four views (each `_view`, two with a tag behind the camera) of their own tags, every other
    tag with a print scale, into one values: each view's (camera key, sightings, robust k)."""
    values = gtsam.Values()
    values.insert(DISTORTION, np.array([2e-3, -3e-4]) if lens else np.zeros(2))
    views = []
    for v in range(4):
        cam, tags, meas = _view(10 + v, behind=v % 2 == 1)
        values.insert(C(v), cam)
        sightings = []
        for i, (tag, uv) in enumerate(zip(tags, meas)):
            key = T(10 * v + i)
            values.insert(key, tag)
            scale_key = S(10 * v + i) if i % 2 == 0 else None
            if scale_key is not None:
                values.insert(scale_key, np.array([0.0011 * (i - 1)]))
            sightings.append(CornerSighting(key, scale_key, uv, tag_object_points(0.1), 0.05 * (1.0 + 0.2 * i),
                                            radial_basis(uv, K) if lens else None))
        views.append((C(v), sightings, 3.0 if v != 2 else None))
    return values, views


def _rows(factor: gtsam.CustomFactor, values: gtsam.Values) -> tuple[float, np.ndarray]:
    return factor.error(values), factor.linearize(values).augmentedInformation()


@pytest.mark.parametrize("lens", [False, True])
def test_each_view_factor_of_a_batch_is_its_own_view_factor_to_the_bit(lens):
    values, views = _views(lens)
    batch = ViewBatch(CAL)
    lens_key = DISTORTION if lens else None
    ours = [batch.add(ck, s, k, lens_key) for ck, s, k in views]
    theirs = [corner_view_factor(ck, s, CAL, k, lens_key) for ck, s, k in views]

    def same(v: gtsam.Values) -> None:
        for a, b in zip(ours, theirs):
            ea, ha = _rows(a, v)
            eb, hb = _rows(b, v)
            assert ea == eb and np.array_equal(ha, hb)

    same(values)                                   # never prepared: each computes its own rows
    batch.track(values)
    batch.prepare(values, True)
    same(values)                                   # the batch's rows
    assert batch.error(values) == pytest.approx(sum(f.error(values) for f in theirs), rel=1e-13)
    assert batch.values is values and not batch.jacobians
    same(values)                                   # errors prepared only: linearised by the factor
    moved = gtsam.Values(values)                   # other values while the batch holds these
    moved.update(C(1), values.atPose3(C(1)).compose(Pose3(Rot3.Rz(0.01), np.array([0.02, 0.0, 0.0]))))
    moved.update(S(20), np.array([0.004]))
    batch.prepare(values, True)
    same(moved)
    assert _rows(ours[1], moved)[0] != _rows(ours[1], values)[0]
    batch.track(moved)
    batch.prepare(moved, True)
    same(moved)
    batch.release()
    same(values)


def test_a_batch_refuses_values_without_a_print_scale_its_views_read():
    values, views = _views(False)
    batch = ViewBatch(CAL)
    for ck, s, k in views:
        batch.add(ck, s, k)
    values.erase(S(20))
    batch.track(values)
    with pytest.raises(ValueError, match="print-scale variable is not in the values"):
        batch.prepare(values, False)


def test_a_view_added_after_a_solve_began_waits_for_the_next():
    values, views = _views(False)
    batch = ViewBatch(CAL)
    for ck, s, k in views[:3]:
        batch.add(ck, s, k)
    batch.track(values)
    batch.prepare(values, False)
    late = batch.add(*views[3])
    with pytest.raises(RuntimeError, match="track the values again"):
        batch.prepare(values, False)
    # still the right rows, from the factor itself
    assert _rows(late, values)[0] == _rows(corner_view_factor(views[3][0], views[3][1], CAL, views[3][2]), values)[0]
    batch.track(values)
    batch.prepare(values, True)
    reference = corner_view_factor(views[3][0], views[3][1], CAL, views[3][2])
    assert np.array_equal(_rows(late, values)[1], _rows(reference, values)[1])


def test_the_batch_solve_is_the_per_view_factors_solve_to_the_bit():
    """The run graph's batch (the rig, print scales, the lens, Huber; views of up to eight tags
    split into factors of three): `solve_batch` through the view batch against
    Levenberg-Marquardt over one `corner_view_factor` a factor."""
    slam = _slam()
    slam._initialise_pending()
    start = gtsam.Values(slam.initial)
    graph = slam._batch_graph()
    per_view = gtsam.NonlinearFactorGraph()
    per_view.push_back(slam._batch_others)
    for layout in slam._view_batch.layouts:
        per_view.add(corner_view_factor(layout.camera_key, layout.sightings, slam._cal, layout.huber_k or None,
                                        layout.lens_key))
    assert per_view.size() == graph.size()
    layouts = slam._view_batch.layouts
    assert max(len(x.sightings) for x in layouts) <= TAGS_PER_FACTOR
    assert len({x.camera_key for x in layouts}) < len(layouts)      # views split across factors
    assert any(s.scale_key is not None for x in slam._view_batch.layouts for s in x.sightings)
    assert any(x.lens_key is not None for x in slam._view_batch.layouts)
    cost = BatchCost(graph, slam._batch_others, slam._view_batch)
    slam._view_batch.track(start)
    assert cost.error(start) == pytest.approx(per_view.error(start), rel=1e-13)
    slam._view_batch.release()
    reference = levenberg_marquardt.run(per_view, start, _params())
    assert reference.iterations >= 2
    _same(slam.solve_batch(), reference.values)
