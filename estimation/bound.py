"""The Cramér–Rao bound of a run's verdicts, kept linearised across the run.

`SfGraphSlam.bound_graph` rebuilds the whole graph with the true noise and `precision.
bound_covariances` linearises it at the truth: every factor of the run again at every verdict, one
Python corner factor built and called back per tag sighting.  That is O(sightings) per verdict and
O(sightings^2) over a run: at N = 8 it was a seventh of the run's CPU by module 80 of 410 and
growing.  The bound changes from one verdict to the next only by the new views' factors and by the
corner noise, which scales every corner factor alike.  So each factor is linearised once, at the
truth, and kept (a corner factor at unit face-on noise, whose noise model is then set to the
corner sigma of the verdict); a factor is linearised again only if the truth of one of its
variables has moved (a module re-placed: its tags' old keys read the tag's new true pose, as
`bound_graph` does).  The same linear graph in the same factor order, so the same ordering and the
same marginals as the full rebuild, to round-off (tests/test_bound.py).
"""

from __future__ import annotations

from typing import Callable

import gtsam
import numpy as np

from estimation.sf_graphslam import SfGraphSlam


class RunBound:
    """`bound_graph` + `bound_covariances` of one run's graph, incremental.  The noise arguments are
    `bound_graph`'s and fixed for the object's life (a run's true rig noise does not change)."""

    def __init__(self, slam: SfGraphSlam, chain_noise: Callable | None = None, rig_prior_sigma: float | None = None,
                 turntable_tag_sigma_m: float | None = None) -> None:
        self.slam = slam
        self._noise = (chain_noise, rig_prior_sigma, turntable_tag_sigma_m)
        self._linear: list[gtsam.GaussianFactor | None] = []       # per spec, in spec order
        self._corners: set[int] = set()                             # the corner factors' spec indices
        self._keys: list[tuple[int, ...]] = []                      # per spec, the variables it touches
        self._at: dict[int, np.ndarray] = {}                        # pose key -> the truth it was linearised at
        self._graph = gtsam.GaussianFactorGraph()
        self._sigma: float | None = None

    def covariances(self, keys: list[int], corner_sigma_px: float, truth: gtsam.Values) -> dict[int, np.ndarray]:
        """Marginal covariances of `keys` at `truth` (every variable of the run's graph valued)
        with `corner_sigma_px` face-on: `bound_covariances(slam.bound_graph(corner_sigma_px,
        ...), truth, keys)`."""
        moved = self._moved(truth)
        if moved:
            redo = [i for i, ks in enumerate(self._keys) if moved.intersection(ks)]
            for i in redo:
                self._linearise(i, truth)
            self._graph = gtsam.GaussianFactorGraph()
            for f in self._linear:
                if f is not None:
                    self._graph.push_back(f)
        for i in range(len(self._linear), len(self.slam.specs)):
            self._linear.append(None)
            self._keys.append(())
            self._linearise(i, truth)
            if self._linear[i] is not None:
                self._graph.push_back(self._linear[i])
        if corner_sigma_px != self._sigma or moved:
            # new corner factors took the last sigma (`_linearise`); every one takes this one
            for i in self._corners:
                self._linear[i].setModel(False, np.full(self._linear[i].rows(), corner_sigma_px))
        self._sigma = corner_sigma_px
        if len(keys) == 1:
            # one key (a verdict's): eliminate everything else, the key last, and invert what is
            # left; Marginals factors the whole graph and then walks its Bayes tree from the root to
            # the key: 2.1x the time on an N = 5 run's graph, the same covariance to 1e-11
            (k,) = keys
            return {k: np.linalg.inv(self._graph.marginal(gtsam.KeyVector([k])).hessian()[0])}
        marginals = gtsam.Marginals(self._graph, gtsam.VectorValues())
        return {k: marginals.marginalCovariance(k) for k in keys}

    def _linearise(self, i: int, truth: gtsam.Values) -> None:
        spec = self.slam.specs[i]
        corner = spec[0] == "corners"
        # a corner factor at 1 px face-on (its obliquity's growth whitened into the linearisation):
        # its noise model is then set to the verdict's corner sigma
        f = self.slam.bound_factor(spec, 1.0, *self._noise)
        if f is None:
            self._linear[i] = None
            return
        keys = tuple(f.keys())
        self._keys[i] = keys
        lin = f.linearize(truth)
        if corner:
            self._corners.add(i)
            lin.setModel(False, np.full(lin.rows(), self._sigma if self._sigma is not None else 1.0))
        self._linear[i] = lin
        for k in keys:
            if k not in self._at:
                v = _pose(truth, k)
                if v is not None:
                    self._at[k] = v

    def _moved(self, truth: gtsam.Values) -> set[int]:
        """Pose variables whose truth is not the one their factors were linearised at."""
        out = set()
        for k, at in self._at.items():
            if not np.array_equal(truth.atPose3(k).matrix(), at):
                out.add(k)
                self._at[k] = truth.atPose3(k).matrix()
        return out


def _pose(values: gtsam.Values, key: int) -> np.ndarray | None:
    """A pose variable's value as a matrix; None for the vector and calibration variables (the lens
    correction and print scales, valued at zero: they enter linearly)."""
    try:
        return values.atPose3(key).matrix()
    except RuntimeError:
        return None
