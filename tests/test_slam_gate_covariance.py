"""The semantic gate and the deployment check read a pair's joint covariance only where it can
change the answer (issue 21): a pair within the fixed gate (gate_m, gate_rad) is tied whatever its
sigma, since the gate is max(gate, k sigma), and a deployable valid and fully deployed within the
fixed tolerances is that whatever its sigma.  Skipping those marginals must decide every relation
as reading them did and leave the estimate as it was; a pair beyond the fixed gate, and a
deployable short of it, still reads it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.sf_graphslam import SfGraphSlam, SlamConfig
from lab.core.geometry import Pose3, Rot3
from lab.core.structures.borg import build_borg
from lab.studies import slam_sim as ss
from lab.studies.bench_precision import PrecisionSetup, _sight
from lab.studies.bench_scaling import _cameras

MODULES = 12


class _NeverDeployed:
    deployed = False


_never_deployed = _NeverDeployed()


def _assemble(always_read: bool, offset_m: float = 0.0, lift_m: float | None = None):
    """The scaling study's 3x3x3 survey (`bench_scaling.measure`), its first modules, with the
    module 6S placed `offset_m` off its design (so one pair is beyond the fixed gate) and 2D
    deployed to `lift_m`."""
    setup = PrecisionSetup()
    rng = np.random.default_rng([7, 3])
    model = build_borg(3)
    faults = ss.StructureFaults(module_offsets={"6S": ((0.0, offset_m, 0.0), (0.0, 0.0, 0.0))},
                                deployed_heights={} if lift_m is None else {"2D": lift_m})
    truth = ss.true_tag_poses(model, faults, list(model.tags))
    slam = SfGraphSlam(model, SlamConfig(observation="corner-info", corner_sigma_px=setup.graph_sigma_px,
                                         camera_sigma_m=setup.camera_sigma_m, camera_sigma_rad=setup.camera_sigma_rad),
                       camera=(ss.SIM_K, np.zeros(5)))
    reads: list[tuple[int, int]] = []
    own = slam._relative_covariance

    def counted(a: int, b: int):
        reads.append((a, b))
        return own(a, b)

    slam._relative_covariance = counted
    if always_read:
        slam._reads_covariance = lambda rel, from_design=None: True
        slam._deploy_check_fixed = lambda measured: _never_deployed
    present = list(model.turntable.tag_ids)
    for face in range(4):
        cam = ss.rig_camera(model, math.radians(90.0 * face), math.radians(-8.0))
        slam.add_view(cam, _sight(rng, ss.SIM_K, cam, cam, truth, present, model, setup, 0.25))
    slam.update()
    for m in model.modules[:MODULES]:
        present += list(m.tags)
        for cam in _cameras(model, m):
            reported = cam.compose(Pose3(Rot3.Expmap(rng.normal(0, setup.camera_sigma_rad, 3)),
                                         rng.normal(0, setup.camera_sigma_m, 3)))
            slam.add_view(reported, _sight(rng, ss.SIM_K, cam, reported, truth, present, model, setup, 0.25))
        slam.update()
    return slam, reads


@pytest.mark.parametrize("offset_m, lift_m", [(0.0, None), (0.012, None), (0.0, 0.40)])
def test_skipping_the_covariance_within_the_fixed_tolerances_decides_as_reading_it(offset_m, lift_m):
    fast, fast_reads = _assemble(False, offset_m, lift_m)
    ref, ref_reads = _assemble(True, offset_m, lift_m)
    # repr: a fully deployed module just over its spacing has theta nan, and nan != nan
    states = {k: (r.decided, r.tied, r.reason, repr(r.deploy)) for k, r in fast.relations.items()}
    assert states == {k: (r.decided, r.tied, r.reason, repr(r.deploy)) for k, r in ref.relations.items()}
    assert sum(r.tied for r in fast.relations.values()) >= 5
    # the estimate is the same (the semantic factors joined in the same order)
    for t in ref.tags:
        assert np.array_equal(fast.tag_pose(t).matrix(), ref.tag_pose(t).matrix())
    # fewer marginals read; those read were beyond the fixed gate or deployables
    assert len(fast_reads) < len(ref_reads)
    for a, b in fast_reads:
        rel = fast.relations.get((a, b)) or fast.relations[(b, a)]
        assert fast._reads_covariance(rel)
    deployables = [r for r in fast.relations.values() if r.kind == "deployable" and r.deploy is not None]
    assert deployables
    if lift_m is not None:
        # the short deployable read its covariance and was found not deployed
        short = [r for r in deployables if not r.deploy.deployed]
        assert short and "not fully deployed" in short[0].deploy.reason
        assert any({a, b} == {short[0].a, short[0].b} for a, b in fast_reads)
    if offset_m:
        # the displaced module's pair is beyond the gate: it read its covariance and was not tied
        untied = [r for r in fast.relations.values() if r.decided and not r.tied]
        assert untied and all("1 sigma" in r.reason for r in untied)
