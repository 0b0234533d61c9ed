"""Python factors read iSAM2's linearisation point in place (issue 21): pybind11 copies a C++
`Values` into a new Python object at every callback unless the object already has a Python wrapper,
and the run's graph holds one (`SfGraphSlam._theta`).  If a GTSAM or pybind11 upgrade stopped
passing the held wrapper, every callback would copy the run's every variable again: these fail."""

from __future__ import annotations

import gtsam
import numpy as np

from test_corner_view_factor import _slam


def _isam_with_probe(hold: bool):
    """An iSAM2 over a chain of poses tied by Python factors that record the values object they
    are handed; with `hold`, a wrapper of iSAM2's linearisation point is held throughout."""
    params = gtsam.ISAM2Params()
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    held = isam.getLinearizationPoint() if hold else None
    seen = []

    def between(a: int, b: int) -> gtsam.CustomFactor:
        def error(this, values, jacobians):
            seen.append(values)
            e = values.atPose3(a).localCoordinates(values.atPose3(b)) - np.array([0, 0, 0, 0.1, 0, 0])
            if jacobians is not None:
                jacobians[0], jacobians[1] = -np.eye(6), np.eye(6)
            return e
        return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(6, 0.01), [a, b], error)

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
    values.insert(0, gtsam.Pose3())
    isam.update(graph, values)
    for k in range(1, 6):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(between(k - 1, k))
        values.insert(k, gtsam.Pose3(gtsam.Rot3(), np.array([0.1 * k + 0.01, 0.0, 0.0])))
        isam.update(graph, values)
    return isam, held, seen


def test_a_held_linearisation_point_is_what_the_python_factors_read():
    isam, held, seen = _isam_with_probe(hold=True)
    assert len(seen) >= 5 and all(v is held for v in seen)
    assert held is isam.getLinearizationPoint()


def test_without_it_every_callback_gets_a_copy():
    # a copy keeps the variables there were when it was made; a view of iSAM2's point would show all
    isam, _, seen = _isam_with_probe(hold=False)
    sizes = sorted({v.size() for v in seen})
    assert len(seen) >= 5 and sizes[0] < isam.getLinearizationPoint().size() and len(sizes) >= 4


def test_the_run_graph_holds_its_isam2_point():
    slam = _slam()
    slam.update()
    assert slam._theta is slam.isam.getLinearizationPoint()
    assert slam._theta.size() == slam.estimate.size()
