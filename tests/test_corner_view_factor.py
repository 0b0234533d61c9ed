"""One factor for a view's corner factors (`rig_model.corner_view_factor`, issue 21): the batch solve
takes it in place of the single factors, so it must be them -- the same error (the tags' Huber
losses summed), the same whitened linear system, and the same solved estimate."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimation.fiducials import tag_object_points
from estimation.rig_model import (DISTORTION, INTRINSICS, CornerSighting, PoseTable, cal3_s2, corner_factor,
                                  corner_view_factor, radial_basis)
from estimation.sf_graphslam import SfGraphSlam, SlamConfig
from lab.core.geometry import Pose3, Rot3
from test_slam_step_exact import GEOM, K, MODEL, _calibration, _steps

C, T, S = gtsam.symbol_shorthand.C, gtsam.symbol_shorthand.T, gtsam.symbol_shorthand.S
CAL = cal3_s2(K)


def _view(seed: int, behind: bool):
    """One camera and five tags 1-2 m in front of it, each seen obliquely, the measured corners
    0.3 px off the projection -- and 30 px for two of them, beyond the Huber threshold -- with or
    without a sixth tag that has a corner behind the camera's plane."""
    rng = np.random.default_rng(seed)
    cam = Pose3(Rot3.RzRyRx(*rng.uniform(-0.3, 0.3, 3)), rng.uniform(-0.5, 0.5, 3))
    pinhole = gtsam.PinholeCameraCal3_S2(cam, CAL)
    tags, meas = [], []
    for i in range(5):
        toward = cam.transformFrom(np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), rng.uniform(1.0, 2.0)]))
        tag = Pose3(cam.rotation().compose(Rot3.RzRyRx(np.pi + rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6),
                                                         rng.uniform(-np.pi, np.pi))), toward)
        uv = np.array([pinhole.project(tag.transformFrom(p)) for p in tag_object_points(0.1)])
        uv += rng.normal(0.0, 30.0 if i in (1, 3) else 0.3, (4, 2))
        tags.append(tag)
        meas.append(uv)
    if behind:
        tag = cam.compose(Pose3(Rot3.Ry(1.2), np.array([0.0, 0.0, 0.03])))
        tags.append(tag)
        meas.append(np.array([[640.0, 360.0]] * 4) + rng.normal(0.0, 40.0, (4, 2)))
    return cam, tags, meas


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("lens", [False, True])
@pytest.mark.parametrize("robust", [False, True])
@pytest.mark.parametrize("behind", [False, True])
def test_a_view_factor_is_its_tags_corner_factors(seed, lens, robust, behind):
    cam, tags, meas = _view(seed, behind)
    robust_k = 3.0 if robust else None
    values = gtsam.Values()
    values.insert(C(0), cam)
    values.insert(DISTORTION, np.array([2e-3, -3e-4]) if lens else np.zeros(2))
    singles = gtsam.NonlinearFactorGraph()
    sightings = []
    for i, (tag, uv) in enumerate(zip(tags, meas)):
        values.insert(T(i), tag)
        scale_key = S(i) if i % 2 == 0 else None       # a tag without a scale variable too
        if scale_key is not None:
            values.insert(scale_key, np.array([0.0013 * (i - 1)]))
        basis = radial_basis(uv, K) if lens else None
        sigma = 0.05 * (1.0 + 0.3 * i)
        singles.add(corner_factor(C(0), T(i), uv, tag_object_points(0.1), sigma, robust_k=robust_k, fixed=CAL,
                                  scale_key=scale_key, distortion=(DISTORTION, basis) if lens else None))
        sightings.append(CornerSighting(T(i), scale_key, uv, tag_object_points(0.1), sigma, basis))
    view = corner_view_factor(C(0), sightings, CAL, robust_k, DISTORTION if lens else None)
    assert view.error(values) == pytest.approx(singles.error(values), rel=1e-12)
    ordering = gtsam.Ordering()
    for key in view.keys():
        ordering.push_back(key)
    one = gtsam.GaussianFactorGraph()
    one.push_back(view.linearize(values))
    h_view = one.augmentedHessian(ordering)
    h_singles = singles.linearize(values).augmentedHessian(ordering)
    assert np.abs(h_view - h_singles).max() <= 1e-9 * np.abs(h_singles).max()


def _linear(factor: gtsam.CustomFactor, values: gtsam.Values) -> tuple[float, np.ndarray]:
    one = gtsam.GaussianFactorGraph()
    one.push_back(factor.linearize(values))
    ordering = gtsam.Ordering()
    for key in factor.keys():
        ordering.push_back(key)
    return factor.error(values), one.augmentedHessian(ordering)


def _plain_view(seed: int) -> tuple[Pose3, list[Pose3], gtsam.Values, list[CornerSighting]]:
    """`_view` (a tag behind the camera included) as values and sightings, without scales or lens."""
    cam, tags, meas = _view(seed, True)
    values = gtsam.Values()
    values.insert(C(0), cam)
    sightings = []
    for i, (tag, uv) in enumerate(zip(tags, meas)):
        values.insert(T(i), tag)
        sightings.append(CornerSighting(T(i), None, uv, tag_object_points(0.1), 0.05, None))
    return cam, tags, values, sightings


def test_a_view_factor_reads_a_pose_table_only_while_it_holds_the_values_evaluated():
    cam, tags, values, sightings = _plain_view(1)
    table = PoseTable()
    plain = corner_view_factor(C(0), sightings, CAL, 3.0)
    tabled = corner_view_factor(C(0), sightings, CAL, 3.0, table=table)
    error = _linear(plain, values)[0]

    def same(v: gtsam.Values) -> None:
        e, h = _linear(plain, v)
        te, th = _linear(tabled, v)
        assert te == e and np.array_equal(th, h)

    table.track(values)
    same(values)                                   # tracked, nothing loaded: the factor reads the values
    table.load(values)
    assert _linear(tabled, values)[0] == error      # read from the table, to the bit
    same(values)
    moved = gtsam.Values(values)                   # other values (a tag moved 1 cm) with the table loaded
    moved.update(T(2), tags[2].compose(Pose3(Rot3(), np.array([0.01, 0.0, 0.0]))))
    same(moved)
    assert _linear(tabled, moved)[0] != error       # ... were read, not the table's
    table.load(moved)
    same(moved)
    same(values)                                   # the loaded values' copy is not the values
    # a pose added ahead of every other moves every row: the factor re-reads them
    values.insert(0, Pose3())
    table.track(values)
    table.load(values)
    same(values)
    with pytest.raises(ValueError, match="pose table of 8 poses"):
        table.load(moved)
    table.clear()
    same(values)


def test_a_view_factors_reused_buffers_do_not_reach_what_gtsam_holds():
    """The factor reuses its error and Jacobian arrays between calls: a linearisation GTSAM holds
    must not change when the factor is called again elsewhere."""
    cam, tags, values, sightings = _plain_view(2)
    view = corner_view_factor(C(0), sightings, CAL, 3.0)
    first = view.linearize(values)
    held = first.augmentedInformation().copy()
    moved = gtsam.Values(values)
    moved.update(C(0), cam.compose(Pose3(Rot3.Rz(0.02), np.array([0.03, 0.0, 0.0]))))
    second = view.linearize(moved)
    assert not np.array_equal(second.augmentedInformation(), held)
    assert np.array_equal(first.augmentedInformation(), held)
    assert view.error(values) != view.error(moved)
    assert np.array_equal(view.linearize(values).augmentedInformation(), held)


def test_a_view_factor_refuses_a_tag_twice_and_a_lens_it_has_no_basis_for():
    cam, tags, meas = _view(0, False)
    s = CornerSighting(T(0), None, meas[0], tag_object_points(0.1), 0.05, None)
    with pytest.raises(ValueError, match="each tag once"):
        corner_view_factor(C(0), [s, s], CAL, None)
    with pytest.raises(ValueError, match="lens"):
        corner_view_factor(C(0), [s], CAL, None, DISTORTION)


def _slam(free_intrinsics: bool = False) -> SfGraphSlam:
    """The step tests' run graph (the rig, the survey's joint prior, print scales, the lens,
    Huber): two steps of two views, nothing solved yet.  The view factors hold the intrinsics
    constant: by default these are held at the camera's, as a study's graph does; a run's graph
    (`free_intrinsics`) has them as a variable of every corner factor."""
    slam = SfGraphSlam(MODEL, SlamConfig(observation="corners", corner_sigma_px=0.05, tag_scale_sigma=0.001),
                       rig=GEOM, calibration=_calibration(), camera=(K, np.zeros(5)))
    assert slam.free_intrinsics
    slam.free_intrinsics = free_intrinsics
    for views in _steps():
        for cam, dets, motion in views:
            slam.add_view(cam, dets, motion)
    return slam


def test_a_graph_whose_intrinsics_are_a_variable_solves_its_single_factors():
    slam = _slam(free_intrinsics=True)
    slam._initialise_pending()
    assert slam._batch_graph() is slam.graph
    assert all(INTRINSICS in slam.graph.at(i).keys() for i in range(slam.graph.size())
               if isinstance(slam.graph.at(i), gtsam.CustomFactor) and slam.graph.at(i).dim() == 8)


def test_the_batch_solve_with_view_factors_is_the_solve_with_the_single_factors():
    slam = _slam()
    slam._initialise_pending()                           # every tag valued, as the solve does first
    batch = slam._batch_graph()
    assert batch.size() < slam.graph.size()              # the corner factors went into view factors
    assert batch.error(slam.initial) == pytest.approx(slam.graph.error(slam.initial), rel=1e-12)
    estimate = slam.solve_batch()
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-6)
    params.setAbsoluteErrorTol(1e-9)
    reference = gtsam.LevenbergMarquardtOptimizer(slam.graph, slam.initial, params).optimize()
    tags = sorted(slam.tags)
    assert len(tags) >= 5
    for t in tags:
        a, b = estimate.atPose3(slam.key(t)), reference.atPose3(slam.key(t))
        assert np.abs(a.translation() - b.translation()).max() <= 1e-9
        assert np.abs(a.rotation().logmap(b.rotation())).max() <= 1e-9
    # the graph only grows: a later solve extends the view factors with the new views alone
    size = batch.size()
    for cam, dets, motion in _steps(1)[0]:
        slam.add_view(cam, dets, motion)
    slam._initialise_pending()
    grown = slam._batch_graph()
    assert grown.size() > size
    assert grown.error(slam.initial) == pytest.approx(slam.graph.error(slam.initial), rel=1e-12)
    # ... and solves as the single factors do, its pose table tracking the new poses
    table = slam._view_batch.table
    generation = table.generation
    estimate = slam.solve_batch()
    assert table.generation == generation + 1 and table.values is None
    reference = gtsam.LevenbergMarquardtOptimizer(slam.graph, slam.initial, params).optimize()
    for t in sorted(slam.tags):
        a, b = estimate.atPose3(slam.key(t)), reference.atPose3(slam.key(t))
        assert np.abs(a.translation() - b.translation()).max() <= 1e-9
