"""The paper's method as a baseline (lab/studies/paper_baseline.py): the sums of Algorithms 1-9 over
Euler 6-vectors, the same sums written as the paper's loops, the same terms on GTSAM, and Powell
from zeros on a small instance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lab.studies import paper_baseline as pb
from lab.studies import slam_sim as ss
from lab.core.geometry import Pose3, from_xyzrpy, pose_error, to_xyzrpy
from lab.core.structures.borg import build_borg


@pytest.fixture(scope="module")
def model():
    return build_borg()


@pytest.fixture(scope="module")
def deployable(model):
    """The paper's deployable test: module 2D's two tags from three camera positions."""
    rng = np.random.default_rng(7)
    return ss.make_survey(model, [1, 2], ss.three_position_path(model, [1, 2]), rng)


@pytest.fixture(scope="module")
def face(model):
    rng = np.random.default_rng(8)
    tags = [0, 1, 2, 9, 13, 14, 21]
    return ss.make_survey(model, tags, ss.face_path(model, tags, distance_m=2.7), rng)


def true_state(survey, p: pb.PaperProblem) -> np.ndarray:
    """The truth as the paper's state: first reported camera's frame, 6-vectors."""
    state_T_world = p.world_T_state.inverse()
    cams = [to_xyzrpy(state_T_world.compose(v.true_structure_T_camera)) for v in survey.views]
    tags = [to_xyzrpy(state_T_world.compose(survey.truth[t])) for t in p.tags]
    return np.concatenate(cams + tags)


def test_compose6_is_pose_composition():
    rng = np.random.default_rng(0)
    a = np.column_stack([rng.normal(size=(5, 3)), rng.uniform(-3, 3, (5, 3)) * [1, 0.45, 1]])
    b = np.column_stack([rng.normal(size=(5, 3)), rng.uniform(-3, 3, (5, 3)) * [1, 0.45, 1]])
    got = pb.compose6(a, b)
    for i in range(5):
        want = from_xyzrpy(a[i]).compose(from_xyzrpy(b[i]))
        assert pose_error(from_xyzrpy(got[i]), want)[0] < 1e-12
        assert pose_error(from_xyzrpy(got[i]), want)[1] < 1e-9


@pytest.mark.parametrize("op", ["add", "compose"])
@pytest.mark.parametrize("alg8", ["eq27", "literal"])
def test_vectorised_sums_equal_the_papers_loops(face, op, alg8):
    p = pb.problem_from_survey(face, semantic=True, semantic_op=op, alg8=alg8)
    rng = np.random.default_rng(1)
    for y in (np.zeros(p.n_state), true_state(face, p), rng.normal(0, 0.5, p.n_state)):
        assert pb.cost(y, p) == pytest.approx(pb.j_literal(y, p), rel=1e-10, abs=1e-12)


def test_graphslam_sum_has_no_semantic_term_and_sf_adds_a_nonnegative_one(face):
    p_g = pb.problem_from_survey(face, semantic=False)
    p_sf = pb.problem_from_survey(face, semantic=True)
    assert len(p_g.sem_t) == 0 and len(p_sf.sem_t) > 0
    y = np.random.default_rng(2).normal(0, 0.3, p_sf.n_state)
    assert pb.cost(y, p_g) == pytest.approx(pb.j_graphslam(y, p_sf))
    assert pb.j_sf_graphslam(y, p_sf) - pb.j_graphslam(y, p_sf) == pytest.approx(pb.sum_semantic_estimate(y, p_sf))
    assert pb.sum_semantic_estimate(y, p_sf) > 0


def test_algorithm8_terms_eq27_and_literal_indentation():
    obs = [[1, 2, 9], [1, 2], [2, 9]]
    related = {1: (0, 2, 9, 36), 2: (1, 17, 21), 9: (1, 37)}
    eq27 = pb.semantic_terms(obs, [1, 2, 9], related, "eq27")
    # every ordered related pair seen together, once per view
    assert sorted(eq27) == sorted([(0, 1, 2, 1), (0, 1, 9, 1), (0, 2, 1, 1), (0, 9, 1, 1), (1, 1, 2, 1), (1, 2, 1, 1)])
    literal = pb.semantic_terms(obs, [1, 2, 9], related, "literal")
    # the last related K per J only, weighted by the number of later re-adds (T - t)
    assert sorted(literal) == sorted([(0, 1, 9, 3), (0, 2, 1, 3), (0, 9, 1, 3), (1, 1, 2, 2), (1, 2, 1, 2)])


def test_the_truth_costs_little_and_zeros_cost_much(deployable):
    p = pb.problem_from_survey(deployable, semantic=True)
    y = true_state(deployable, p)
    assert pb.cost(y, p) < 0.1 * pb.cost(np.zeros(p.n_state), p)
    # a deployable at its design: the relationship term vanishes at the truth, in both readings
    for op in ("add", "compose"):
        q = pb.problem_from_survey(deployable, semantic=True, semantic_op=op)
        assert pb.sum_semantic_estimate(y, q) < 1e-20


def test_the_euler_graph_is_exactly_the_papers_cost(face):
    p = pb.problem_from_survey(face, semantic=True)
    y = true_state(face, p) + np.random.default_rng(3).normal(0, 0.01, p.n_state)
    graph = pb.euler_graph(p)
    assert 2.0 * graph.error(pb.euler_values(p, y)) == pytest.approx(pb.cost(y, p), rel=1e-10)
    r, J = pb.residuals(y, p, jacobian=True)
    assert r @ r == pytest.approx(pb.cost(y, p), rel=1e-10)
    dy = np.random.default_rng(4).normal(0, 1e-6, p.n_state)
    assert np.max(np.abs(pb.residuals(y + dy, p) - r - J @ dy)) < 1e-9


def test_gtsam_lie_form_is_close_and_the_exact_polish_is_no_worse(face):
    p = pb.problem_from_survey(face, semantic=True)
    lie = pb.solve_gtsam(p, "lie")
    gn = pb.solve_gtsam(p, "lie+gn")
    euler = pb.solve_gtsam(p, "euler")
    assert gn.cost <= lie.cost
    assert euler.cost == pytest.approx(gn.cost, rel=1e-7)
    assert (lie.cost - gn.cost) / gn.cost < 2e-2       # the two residual forms agree to first order
    # the first camera is the state's origin
    assert np.linalg.norm(gn.y[:3]) < 0.2


def test_powell_from_zeros_reaches_no_lower_cost_than_gtsam(deployable):
    """The paper's optimiser on a small instance (30 variables): it converges, to the same tags,
    at a cost no lower than GTSAM's exact solution of the same J."""
    p = pb.problem_from_survey(deployable, semantic=True)
    powell = pb.solve_powell(p)
    exact = pb.solve_gtsam(p, "lie+gn")
    assert powell.converged and powell.evaluations > 100
    assert powell.cost >= exact.cost * (1 - 1e-9)
    assert powell.cost <= exact.cost * 1.01
    tp, te = powell.tag_poses(p), exact.tag_poses(p)
    for t in p.tags:
        assert pose_error(tp[t], te[t])[0] < 5e-3
    # the semantic term held the related-tag offset to the design
    off = tp[1].between(tp[2])
    assert pose_error(off, deployable.truth[1].between(deployable.truth[2]))[0] < 5e-3


def test_powell_on_the_loop_form_takes_the_same_steps(deployable):
    p = pb.problem_from_survey(deployable, semantic=False)
    fast = pb.solve_powell(p, options={"maxfev": 300})
    slow = pb.solve_powell(p, options={"maxfev": 300}, literal=True)
    assert fast.cost == pytest.approx(slow.cost, rel=1e-8)


def test_solution_poses_are_in_the_structure_frame(deployable):
    p = pb.problem_from_survey(deployable, semantic=False)
    sol = pb.solve_gtsam(p, "lie")
    for t, pose in sol.tag_poses(p).items():
        # the camera pose noise is 5 cm per axis: the absolute error is of that size, not metres
        assert pose_error(pose, deployable.truth[t])[0] < 0.25
    cams = sol.camera_poses(p)
    assert len(cams) == 3 and isinstance(cams[0], Pose3)
    assert math.isfinite(sol.cost)
