"""The corner noise a run's own residuals imply (variance component estimation, one group).

A graph's marginals are only as honest as the corner sigma it was built with.  A constant has to
match a camera nobody measured; instead the residuals say how well the corners really fit: the
a-posteriori variance factor s0^2 = (residual scatter)^2 * n / (n - p) over the graph's sigma^2,
with n residual components and p the variables they determine.  The scatter is robust (1.4826 x
the median absolute residual): a tag hidden behind a strut or knocked off its place must not make
every other tag look noisy.

What it cannot see: a bias common to every sighting of a tag (a tag printed 0.1 % large, a blur
that shrinks every tag alike) leaves no residual; those enter the error budget as their own terms
(docs/sf_graphslam.md, "the error budget of a verdict").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# the consistency of the MAD with a Gaussian's sigma
_MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class CornerNoise:
    sigma_px: float          # measured face-on corner sigma (per coordinate)
    graph_sigma_px: float    # what the graph's factors assume
    residuals: int           # residual components counted (n)
    parameters: int          # variables they determine (p)

    @property
    def variance_factor(self) -> float:
        return (self.sigma_px / self.graph_sigma_px) ** 2

    @property
    def covariance_scale(self) -> float:
        """What the graph's marginals are multiplied by: the variance factor where the corners
        proved worse than assumed, 1 where they proved better (conservative: a prior from the rig
        survey does not shrink with the corners)."""
        return max(1.0, self.variance_factor)

    def to_json(self) -> dict[str, float | int]:
        return {"sigma_px": self.sigma_px, "graph_sigma_px": self.graph_sigma_px, "residuals": self.residuals,
                "parameters": self.parameters, "variance_factor": self.variance_factor}


def measured_corner_noise(residuals_px: np.ndarray, parameters: int, graph_sigma_px: float) -> CornerNoise:
    """`residuals_px`: every residual component (face-on px), `parameters`: the variables they
    determine.  Fewer residuals than parameters: the graph's own sigma stands (nothing measured)."""
    r = np.asarray(residuals_px, float).ravel()
    r = r[np.isfinite(r)]
    return corner_noise_from_median(float(np.median(np.abs(r))) if r.size else 0.0, int(r.size), parameters,
                                    graph_sigma_px)


def corner_noise_from_median(median_abs_px: float, n: int, parameters: int, graph_sigma_px: float) -> CornerNoise:
    """`measured_corner_noise` from the median absolute residual of `n` finite components."""
    if n <= parameters or n == 0:
        return CornerNoise(graph_sigma_px, graph_sigma_px, n, parameters)
    scatter = _MAD_TO_SIGMA * median_abs_px
    return CornerNoise(scatter * float(np.sqrt(n / (n - parameters))), graph_sigma_px, n, parameters)


class AbsoluteResiduals:
    """The absolute values of a run's residual components as they arrive, kept sorted, so that
    each step's median is read, not recomputed: a median over every residual of the run at each
    step grew with the run (0.5 ms a step by the end of an 8x8x8, more under load).  Adding k
    components to n costs a sort of k and one memmove of n.  The median is np.median's, bit for bit
    (the middle one, or the mean of the middle two); non-finite components are left out, as
    `measured_corner_noise` leaves them."""

    def __init__(self) -> None:
        self._sorted = np.zeros(0)

    def add(self, residuals_px: np.ndarray) -> None:
        r = np.asarray(residuals_px, float).ravel()
        a = np.sort(np.abs(r[np.isfinite(r)]))
        self._sorted = np.insert(self._sorted, np.searchsorted(self._sorted, a), a)

    def __len__(self) -> int:
        return int(self._sorted.size)

    def median(self) -> float:
        s, n = self._sorted, self._sorted.size
        if n == 0:
            return 0.0
        return float(s[n // 2]) if n % 2 else float((s[n // 2 - 1] + s[n // 2]) / 2)

    def corner_noise(self, parameters: int, graph_sigma_px: float) -> CornerNoise:
        return corner_noise_from_median(self.median(), len(self), parameters, graph_sigma_px)
