"""The part of a run's module errors that is one rigid motion: the frame the turntable tags realise.

Every module of a run is read in the structure frame that the turntable tags fix, and their glue
(the rig's `turntable_tag_sigma`, 0.5 mm a tag by default) moves that frame by a translation and
a small rotation shared by every module of the run.  A run's good modules' error vectors, fitted
by least squares as e_i = t + w x (p_i - centroid), split into that common motion and what is left
(the views of each module).  The common part is a single draw per run: one run's NEES can sit far
above 3 while its 1-sigma is honest, and the NEES about the fitted frame shows whether the rest is.
Scoring only (the truth is the simulator's): nothing here reaches the estimator."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


@dataclass(frozen=True)
class FrameFit:
    translation_m: np.ndarray       # t: the common offset, at the modules' centroid
    rotation_rad: np.ndarray        # w: the common small rotation (axis x angle)
    nees_about_frame: np.ndarray    # each module's NEES with the common motion taken off
    residuals_m: np.ndarray         # (N, 3) each module's error with the common motion taken off


def fit_frame(positions_m: Sequence[Sequence[float]], errors_m: Sequence[Sequence[float]],
              covariances_m2: Sequence[Sequence[Sequence[float]]]) -> FrameFit | None:
    """The rigid motion common to the modules' position errors (positions: where each module is,
    errors: estimate - truth, covariances: each module's stated 3x3), or None for fewer than 3
    modules (a rotation needs three points off a line)."""
    p = np.asarray(positions_m, float).reshape(-1, 3)
    e = np.asarray(errors_m, float).reshape(-1, 3)
    cov = np.asarray(covariances_m2, float).reshape(-1, 3, 3)
    if len(p) < 3:
        return None
    q = p - p.mean(axis=0)
    a = np.zeros((len(q), 3, 6))
    a[:, :, :3] = np.eye(3)
    # w x q = -[q]x w
    a[:, 0, 4], a[:, 0, 5] = q[:, 2], -q[:, 1]
    a[:, 1, 3], a[:, 1, 5] = -q[:, 2], q[:, 0]
    a[:, 2, 3], a[:, 2, 4] = q[:, 1], -q[:, 0]
    x, *_ = np.linalg.lstsq(a.reshape(-1, 6), e.ravel(), rcond=None)
    r = e - (a @ x)
    nees = np.einsum("ni,ni->n", r, np.linalg.solve(cov, r[..., None])[..., 0])
    return FrameFit(x[:3], x[3:], nees, r)
