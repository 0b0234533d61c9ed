"""The common frame error of a run's modules (lab/studies/error_frame.py): a rigid motion shared by
every module is found, and what is left is scored against each module's own covariance."""

from __future__ import annotations

import numpy as np
import pytest

from lab.studies.error_frame import fit_frame


def _modules(rng, count=200, sigma=3e-4):
    positions = rng.uniform(0.0, 3.5, (count, 3))
    cov = np.array([np.diag(rng.uniform(0.5, 1.5, 3) * sigma) ** 2 for _ in range(count)])
    own = np.array([rng.multivariate_normal(np.zeros(3), c) for c in cov])
    return positions, cov, own


def test_a_common_offset_and_rotation_are_found_and_the_rest_scored_on_its_own():
    rng = np.random.default_rng(3)
    positions, cov, own = _modules(rng)
    t, w = np.array([3e-4, -5e-5, 2.6e-4]), np.array([1.5e-5, 1.6e-4, -1.3e-4])
    q = positions - positions.mean(axis=0)
    errors = t + np.cross(w, q) + own
    fit = fit_frame(positions, errors, cov)
    assert fit is not None
    assert np.allclose(fit.translation_m, t, atol=4e-5) and np.allclose(fit.rotation_rad, w, atol=3e-5)
    # with the frame in, one run's NEES is far from 3; about the frame, each module's own error is
    nees = np.einsum("ni,ni->n", errors, np.linalg.solve(cov, errors[..., None])[..., 0])
    assert nees.mean() > 6.0
    assert fit.nees_about_frame.mean() == pytest.approx(3.0, abs=0.6)


def test_no_common_motion_leaves_the_nees_as_it_was():
    rng = np.random.default_rng(4)
    positions, cov, own = _modules(rng)
    fit = fit_frame(positions, own, cov)
    assert np.linalg.norm(fit.translation_m) < 1e-4 and np.linalg.norm(fit.rotation_rad) < 1e-4
    nees = np.einsum("ni,ni->n", own, np.linalg.solve(cov, own[..., None])[..., 0])
    # six parameters fitted out of 600 coordinates take ~1 % of the sum
    assert fit.nees_about_frame.sum() == pytest.approx(nees.sum(), rel=0.05)
    assert fit.nees_about_frame.sum() < nees.sum()


def test_fewer_than_three_modules_have_no_frame():
    assert fit_frame([[0, 0, 0], [1, 0, 0]], [[0, 0, 0], [0, 0, 0]], [np.eye(3)] * 2) is None
