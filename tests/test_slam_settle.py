"""Settling what is built (issue 21: a step whose cost does not grow with the run): tags of modules
the run has built well past are summarised out of iSAM2 onto the rig and the turntable tags.  The
live tags' estimates stay within a small part of their 1-sigma of the full graph's, their
covariances do not shrink, a
settled tag keeps its estimate and takes no new sighting, and a run settles a layer only once a
module enough layers above it is released."""

from __future__ import annotations

import json

import gtsam
import numpy as np
import pytest

from estimation.rig_model import AXIS, BASE, DISTORTION, INTRINSICS, LIFT, MOUNT
from estimation.sf_graphslam import SfGraphSlam, SlamConfig
from lab.core.geometry import Pose3
from procedures.borg_measure import Measurement
from test_slam_step_exact import GEOM, K, MODEL, TT, _calibration, _view

# three steps: the first module's tags, then those with the next ones, then the next ones alone
STEPS = (((-0.6, -0.3), (0, 9, 36, 37)), ((-0.2, 0.1), (0, 9, 1, 2, 37)), ((0.2, 0.5), (1, 2, 13, 38, 47, 0)))


def _views(seed: int = 0):
    rng = np.random.default_rng(seed)
    return [[_view(a, tags, rng) for a in angles] for angles, tags in STEPS]


def _slam() -> SfGraphSlam:
    return SfGraphSlam(MODEL, SlamConfig(observation="corners", corner_sigma_px=0.05, tag_scale_sigma=0.001),
                       rig=GEOM, calibration=_calibration(), camera=(K, np.zeros(5)))


def _run(settle_after: int | None, settle: tuple[int, ...] = (9,)) -> tuple[SfGraphSlam, dict[int, Pose3]]:
    """The three steps; with `settle_after` = i, `settle` is settled after step i's release.
    Returns the graph and the settled tags' estimates just before they were settled."""
    slam, before = _slam(), {}
    for i, views in enumerate(_views()):
        for cam, dets, motion in views:
            slam.add_view(cam, dets, motion)
        slam.update()
        slam.release(())
        if i == settle_after:
            before = {t: slam.tag_pose(t) for t in settle}
            assert slam.settle(settle) == len(settle)
    return slam, before


def test_a_settled_tag_leaves_the_solver_with_its_estimate_and_takes_no_new_sighting():
    slam, before = _run(1)
    assert 9 in slam.tags and not slam.isam.valueExists(slam.key(9))
    assert slam.tag_pose(9).equals(before[9], 1e-12)
    assert slam.tag_estimates()[9].equals(before[9], 1e-12)
    assert 9 not in slam.tag_covariances([9, 1])
    seen = slam.observations[9]
    size = slam.graph.size()
    cam, dets, motion = _views()[1][0]
    assert any(d.tag_id == 9 for d in dets)
    slam.add_view(cam, dets, motion)
    slam.update()
    assert slam.observations[9] == seen                        # the sighting of 9 was not added
    assert slam.graph.size() - size == 1 + len([d for d in dets if d.tag_id != 9])   # its chain and the others


def test_the_live_tags_stay_where_the_full_graph_puts_them_and_their_covariances_do_not_shrink():
    full, _ = _run(None)
    settled, _ = _run(1)
    live = sorted(t for t in full.tags if t != 9)
    assert len(live) >= 6
    for t in live:
        a, b = full.tag_pose(t), settled.tag_pose(t)
        ca, cb = full.isam.marginalCovariance(full.key(t)), settled.isam.marginalCovariance(settled.key(t))
        # what the settled tag told the live ones about the cameras they shared is gone: they move,
        # by a small fraction of their own uncertainty (0.01-0.04 of a sigma^2 here)
        d = gtsam.Pose3.Logmap(a.between(b))
        assert float(d @ np.linalg.solve(cb, d)) < 0.1, t
        # conservative up to the held linearisation point: (cb - ca) has no negative direction
        # beyond 1e-3 of ca's scale
        w = np.linalg.eigvalsh(cb - ca)
        assert w.min() >= -1e-3 * np.linalg.eigvalsh(ca).max(), (t, w.min())
        assert np.trace(cb) <= 1.5 * np.trace(ca)              # and not much larger here


def test_what_is_settled_stays_only_as_a_summary_on_the_rig_and_the_turntable_tags():
    slam, _ = _run(1, settle=(0, 9))
    frame = {AXIS, BASE, MOUNT, INTRINSICS, DISTORTION, LIFT} | {slam.key(t) for t in TT}
    factors = slam.isam.getFactorsUnsafe()
    settled = {slam.key(0), slam.key(9)}
    summaries = 0
    for i in range(factors.size()):
        if not factors.exists(i):
            continue
        keys = set(factors.at(i).keys())
        assert not keys & settled
        if isinstance(factors.at(i), gtsam.LinearContainerFactor):
            summaries += 1
            assert keys <= frame
    assert summaries >= 1
    # the relations to a settled tag are never decided
    assert all(9 not in key and 0 not in key for key in slam._open)


def test_a_held_or_unseen_or_turntable_tag_is_not_settled():
    slam = _slam()
    for cam, dets, motion in _views()[0]:
        slam.add_view(cam, dets, motion)
    slam.update(snapshot=[0], hold=True)
    assert slam.settle([0, 36, 13]) == 0           # held, turntable, never seen
    slam.release([0])
    assert slam.settle([0]) == 1 and slam.settle([0]) == 0


class _Slam:
    def __init__(self) -> None:
        self.settled: dict[int, None] = {}
        self.calls: list[list[int]] = []

    def settle(self, tags):
        tags = list(tags)
        self.calls.append(tags)
        self.settled.update(dict.fromkeys(tags))
        return len(tags)


def _measurement(after: int) -> Measurement:
    m = Measurement.__new__(Measurement)
    m.model, m.slam, m.settle_after_layers = MODEL, _Slam(), after
    m.settled_below, m._top_layer, m._verdicts, m.placed = 0, -1, {}, []
    return m


@pytest.mark.parametrize("after", [1, 2])
def test_a_run_settles_a_layer_once_a_module_enough_layers_above_it_is_released(after):
    m = _measurement(after)
    layer = {mod.name: MODEL.layer_of(mod.name) for mod in MODEL.modules}
    for mod in MODEL.modules:
        m.placed.append(mod.name)
        m._verdicts[mod.name] = None
        m.settle_built(mod.name)
        top = max(layer[n] for n in m.placed)
        # every released module of a layer `after` or more below the highest released is settled,
        # and nothing else
        want = {t for n in m.placed if layer[n] <= top - after for t in MODEL.module_by_name[n].tags}
        assert set(m.slam.settled) == want, mod.name
    assert m.settled_below == max(layer.values()) - after + 1


def test_a_run_that_settles_nothing_never_calls_settle():
    m = _measurement(0)
    for mod in MODEL.modules:
        m.placed.append(mod.name)
        m.settle_built(mod.name)
    assert m.slam.calls == []


def test_a_run_that_settled_a_layer_replays_to_the_bit(lab, run_dir):
    """A resumed run rebuilds its estimate through the replay path: with a layer settled on the way,
    the replay's verdicts, deviations and 1-sigma are the live run's, bit for bit.  11D is the
    3x3x3's first module of layer 2: its release settles layer 0."""
    r = lab(["run", "borg", "--auto", "--quiet", "--no-rig-survey", "--modules", "11", "--on-flag", "continue",
             "--speedup", "100", "--out", str(run_dir)])
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["settled"]["after_layers"] == 2 and s["settled"]["layers_below"] == 1 and s["settled"]["tags"] >= 10, s
    r = lab(["bench", "replay", str(run_dir), "--json"])
    assert r.returncode == 0, r.stdout + r.stderr
    res = json.loads(r.stdout)
    c = res["against_summary"]
    assert res["settled_tags"] == s["settled"]["tags"]
    assert c["compared"] == 11 and not c["verdicts_differ"]
    assert c["max_deviation_diff"] == 0.0 and c["max_rotation_diff"] == 0.0 and c["max_sigma_rel_diff"] == 0.0
