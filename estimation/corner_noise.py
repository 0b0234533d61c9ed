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
    n = int(r.size)
    if n <= parameters or n == 0:
        return CornerNoise(graph_sigma_px, graph_sigma_px, n, parameters)
    scatter = _MAD_TO_SIGMA * float(np.median(np.abs(r)))
    return CornerNoise(scatter * float(np.sqrt(n / (n - parameters))), graph_sigma_px, n, parameters)
