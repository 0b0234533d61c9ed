"""The SF-GraphSLAM paper's own method, as published: J_GraphSLAM and J_SF-GraphSLAM as the sums of
Algorithms 1-9 over Euler 6-vectors, minimised by `scipy.optimize.minimize(method="Powell")` from
an all-zero state (paper §2.8).  It is the baseline `lab bench slam` compares our GTSAM
estimator against; nothing in the procedure uses it.

State (Algorithms 3, 5, 8): y = [x_0 .. x_{T-1}, y_tag_1 .. y_tag_M], each a 6-vector
(x, y, z, roll, pitch, yaw) -- metres and radians, R = Rz(yaw) Ry(pitch) Rx(roll) (lab.core.geometry).
The world frame is the first camera's: Algorithm 3 compares x_0 with zeros ("the camera is
supposed to have an initial state of zero").

Readings of the text (docs/sf_graphslam.md discusses them):
- Algorithm 2, initial_state_estimate = x0^T Omega0^-1 x0 with "Input: N/A" and Omega0 = inf
  (Eq. 20): a constant (0); the anchor is Algorithm 3's t = 0 term, x_0^T R^-1 x_0.
- Algorithms 4 and 6 write `*`: g = x_{t-1} * u_t and h = x_t * z are rigid-body compositions
  of the poses the 6-vectors stand for ("applying the known robot control u_t to the last known
  robot position"), converted back to 6-vectors.
- Algorithm 9 writes `+`: s = y_K + relationship(J, K) is plain vector addition.  Eq. 30's
  relationship (0, 0, 0.5, 0, 0, 0) for a deployable is "a perfect 0.5 m transform along the
  z-axis": the lift along the world's vertical, not along the tag's z (which points out of the
  face) -- so the relationship is the design difference of the two 6-vectors in the state's frame,
  r(J, K) = e(design_J) - e(design_K).  `semantic_op="compose"` is the other reading,
  s = y_K * (design K->J), for comparison; for tags of equal orientation (every Table 1 pair on
  one face) the two agree to first order.
- Differences of 6-vectors (`x_t - g(...)`, `y_J - h(...)`, `y_J - s(...)`) wrap their angle
  components into [-pi, pi): without that a tag at yaw = 180 deg would be charged 2 pi for a
  correct estimate.  It is the one liberty we take with the literal sums.
- Algorithm 8 sums, per time step t, every tag J and every related tag K (Table 1) both observed
  at t: one term per ordered pair (J, K), so each related pair enters twice per view -- Eq. 27's
  triple sum over t, k, i, which Algorithm 7 says it mirrors.  Read with its indentation, the
  pseudo-code would instead keep only the last related K per J (line 25 sits after the K loop) and
  re-add the running per-tag sum at every t (lines 28-30), weighting view t by (T - t);
  `alg8="literal"` builds that variant.
- Q, R, S are Eqs. 34-36 (variances, translation first).

`solve_powell` is the paper's optimiser.  `solve_gtsam` minimises the same terms with GTSAM
(Levenberg-Marquardt on the Lie-group form of each residual: same weights, same factors, the
residuals agree with the 6-vector ones to first order), so the two can be compared at the paper's
own cost J.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np

from lab.core.geometry import Pose3, from_xyzrpy, to_xyzrpy

DOF = 6

# Eqs. 34-36: diagonal covariances (variances), in the 6-vector order x, y, z, roll, pitch, yaw.
Q_PAPER = np.diag([1.0, 1.0, 1.0, 0.1, 0.1, 0.1])
R_PAPER = np.diag([0.1, 0.1, 0.1, 0.01, 0.01, 0.01])
S_PAPER = np.diag([0.1, 0.1, 0.1, 0.1, 0.1, 0.1])


@dataclass(frozen=True)
class PaperProblem:
    """Everything the paper's J needs, as 6-vectors in the first camera's frame."""

    n_cameras: int
    tags: tuple[int, ...]                        # state order of the tags after the cameras
    controls: np.ndarray                         # (T-1, 6): u_t for t = 1 .. T-1
    obs_t: np.ndarray                            # (N,) camera index of each measurement
    obs_j: np.ndarray                            # (N,) tag index (into `tags`)
    obs_z: np.ndarray                            # (N, 6) measured camera->tag pose
    sem_t: np.ndarray                            # (S,) semantic terms: time step,
    sem_j: np.ndarray                            #      tag J (the one predicted),
    sem_k: np.ndarray                            #      related tag K,
    sem_w: np.ndarray                            #      how many times the term is counted
    sem_r: np.ndarray                            # (S, 6) relationship(J, K): e(J) - e(K) ("add") ...
    sem_pose: np.ndarray                         # (S, 6) ... or design K->J as a 6-vector ("compose")
    semantic: bool
    semantic_op: Literal["add", "compose"] = "add"
    alg8: Literal["eq27", "literal"] = "eq27"
    Q: np.ndarray = field(default_factory=lambda: Q_PAPER.copy())
    R: np.ndarray = field(default_factory=lambda: R_PAPER.copy())
    S: np.ndarray = field(default_factory=lambda: S_PAPER.copy())
    world_T_state: Pose3 = field(default_factory=Pose3)   # structure_T_(first reported camera)

    @property
    def n_state(self) -> int:
        return DOF * (self.n_cameras + len(self.tags))


# ---- 6-vector algebra, vectorised --------------------------------------------------------------
def _rot(e: np.ndarray) -> np.ndarray:
    """(n, 6) 6-vectors -> (n, 3, 3) rotations Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = e[:, 3], e[:, 4], e[:, 5]
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    R = np.empty((len(e), 3, 3))
    R[:, 0, 0] = cy * cp
    R[:, 0, 1] = cy * sp * sr - sy * cr
    R[:, 0, 2] = cy * sp * cr + sy * sr
    R[:, 1, 0] = sy * cp
    R[:, 1, 1] = sy * sp * sr + cy * cr
    R[:, 1, 2] = sy * sp * cr - cy * sr
    R[:, 2, 0] = -sp
    R[:, 2, 1] = cp * sr
    R[:, 2, 2] = cp * cr
    return R


def _rpy(R: np.ndarray) -> np.ndarray:
    pitch = -np.arcsin(np.clip(R[:, 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    return np.column_stack([roll, pitch, yaw])


def compose6(a: np.ndarray, b: np.ndarray, Rb: np.ndarray | None = None) -> np.ndarray:
    """a * b for (n, 6) 6-vectors: the pose b expressed in a, as a 6-vector."""
    Ra = _rot(a)
    Rb = _rot(b) if Rb is None else Rb
    t = a[:, :3] + np.einsum("nij,nj->ni", Ra, b[:, :3])
    return np.column_stack([t, _rpy(Ra @ Rb)])


def _wrap(d: np.ndarray) -> np.ndarray:
    d = d.copy()
    d[:, 3:] = (d[:, 3:] + math.pi) % (2.0 * math.pi) - math.pi
    return d


def _quad(d: np.ndarray, cov: np.ndarray, w: np.ndarray | None = None) -> float:
    inv = 1.0 / np.diag(cov)
    q = (d * d) @ inv
    return float(q.sum() if w is None else (q * w).sum())


# ---- Algorithms 1-9 ----------------------------------------------------------------------------------
def initial_state_estimate() -> float:
    """Algorithm 2: x0^T Omega0^-1 x0 with Omega0 = inf (Eq. 20) and no input -- a constant."""
    return 0.0


def sum_pose_estimate(y: np.ndarray, p: PaperProblem) -> float:
    """Algorithm 3 with Algorithm 4's g = x_{t-1} * u_t."""
    x = y[: DOF * p.n_cameras].reshape(-1, DOF)
    total = _quad(_wrap(x[:1]), p.R)                       # t = 0: against zeros
    if p.n_cameras > 1:
        g = compose6(x[:-1], p.controls, p._controls_R)    # type: ignore[attr-defined]
        total += _quad(_wrap(x[1:] - g), p.R)
    return total


def sum_measurement_estimate(y: np.ndarray, p: PaperProblem) -> float:
    """Algorithm 5 with Algorithm 6's h = x_t * z."""
    x = y[: DOF * p.n_cameras].reshape(-1, DOF)
    tags = y[DOF * p.n_cameras:].reshape(-1, DOF)
    h = compose6(x[p.obs_t], p.obs_z, p._obs_R)            # type: ignore[attr-defined]
    return _quad(_wrap(tags[p.obs_j] - h), p.Q)


def sum_semantic_estimate(y: np.ndarray, p: PaperProblem) -> float:
    """Algorithm 8 with Algorithm 9's s = y_K + relationship(J, K)."""
    if len(p.sem_t) == 0:
        return 0.0
    tags = y[DOF * p.n_cameras:].reshape(-1, DOF)
    if p.semantic_op == "add":
        s = tags[p.sem_k] + p.sem_r
    else:
        s = compose6(tags[p.sem_k], p.sem_pose, p._sem_R)  # type: ignore[attr-defined]
    return _quad(_wrap(tags[p.sem_j] - s), p.S, p.sem_w)


def j_graphslam(y: np.ndarray, p: PaperProblem) -> float:
    """Algorithm 1."""
    return initial_state_estimate() + sum_pose_estimate(y, p) + sum_measurement_estimate(y, p)


def j_sf_graphslam(y: np.ndarray, p: PaperProblem) -> float:
    """Algorithm 7."""
    return j_graphslam(y, p) + sum_semantic_estimate(y, p)


def cost(y: np.ndarray, p: PaperProblem) -> float:
    """The objective of the problem's method: J_SF-GraphSLAM if `p.semantic`, else J_GraphSLAM."""
    return j_sf_graphslam(y, p) if p.semantic else j_graphslam(y, p)


# ---- building a problem -----------------------------------------------------------------------------
def _e(p: Pose3) -> np.ndarray:
    return to_xyzrpy(p)


def semantic_terms(obs_by_t: Sequence[Sequence[int]], tags: Sequence[int], related: dict[int, tuple[int, ...]],
                   alg8: Literal["eq27", "literal"] = "eq27") -> list[tuple[int, int, int, int]]:
    """(t, J, K, weight) terms of Algorithm 8 (tag ids, not indices)."""
    T = len(obs_by_t)
    out = []
    for t, seen_list in enumerate(obs_by_t):
        seen = set(seen_list)
        for j in tags:                                    # AprilTags_Desired, in order
            if j not in seen:
                continue
            ks = [k for k in tags if k != j and k in related.get(j, ()) and k in seen]
            if not ks:
                continue
            if alg8 == "eq27":
                out.extend((t, j, k, 1) for k in ks)
            else:
                # line 25 after the K loop: only the last K's sem_diff is added; lines 28-30 re-add
                # the running sum at every later t as well: weight T - t
                out.append((t, j, ks[-1], T - t))
    return out


def problem_from_survey(survey, *, semantic: bool, semantic_op: Literal["add", "compose"] = "add",
                        alg8: Literal["eq27", "literal"] = "eq27", exclude_pairs: Sequence[tuple[int, int]] = (),
                        Q: np.ndarray = Q_PAPER, R: np.ndarray = R_PAPER, S: np.ndarray = S_PAPER) -> PaperProblem:
    """The paper's problem for a `lab.studies.slam_sim.Survey`: state frame = first reported camera."""
    model = survey.model
    views = survey.views
    tags = tuple(t for t in survey.tags if any(o.tag == t for v in views for o in v.observations))
    index = {t: i for i, t in enumerate(tags)}
    controls = np.array([_e(u) for u in survey.controls()]).reshape(-1, DOF)
    obs_t, obs_j, obs_z = [], [], []
    for t, v in enumerate(views):
        for o in v.observations:
            if o.tag in index:
                obs_t.append(t)
                obs_j.append(index[o.tag])
                obs_z.append(_e(o.camera_T_tag))
    world_T_state = views[0].reported_structure_T_camera
    state_T_world = world_T_state.inverse()
    design = {t: state_T_world.compose(model.tags[t].structure_T_tag) for t in tags}
    excluded = {frozenset(p) for p in exclude_pairs}
    related = {t: tuple(k for k in model.tags[t].related if frozenset((t, k)) not in excluded) for t in tags}
    terms = semantic_terms([[o.tag for o in v.observations] for v in views], tags, related, alg8) if semantic else []
    sem_r = np.array([_wrap((_e(design[j]) - _e(design[k]))[None])[0] for _, j, k, _ in terms]).reshape(-1, DOF)
    sem_pose = np.array([_e(design[k].between(design[j])) for _, j, k, _ in terms]).reshape(-1, DOF)
    p = PaperProblem(len(views), tags, controls, np.array(obs_t, dtype=int), np.array(obs_j, dtype=int),
                     np.array(obs_z).reshape(-1, DOF), np.array([t for t, *_ in terms], dtype=int),
                     np.array([index[j] for _, j, _, _ in terms], dtype=int),
                     np.array([index[k] for _, _, k, _ in terms], dtype=int),
                     np.array([w for *_, w in terms], dtype=float), sem_r, sem_pose, semantic, semantic_op, alg8,
                     np.asarray(Q, dtype=float), np.asarray(R, dtype=float), np.asarray(S, dtype=float), world_T_state)
    _cache(p)
    object.__setattr__(p, "_related", {index[t]: tuple(index[k] for k in related[t] if k in index) for t in tags})
    object.__setattr__(p, "_design_e", {index[t]: _e(design[t]) for t in tags})
    object.__setattr__(p, "_design", {index[t]: design[t] for t in tags})
    return p


def _cache(p: PaperProblem) -> None:
    # rotations of the constant 6-vectors, computed once (the optimiser calls J ~10^5 times)
    object.__setattr__(p, "_controls_R", _rot(p.controls) if len(p.controls) else np.zeros((0, 3, 3)))
    object.__setattr__(p, "_obs_R", _rot(p.obs_z))
    object.__setattr__(p, "_sem_R", _rot(p.sem_pose) if len(p.sem_pose) else np.zeros((0, 3, 3)))


# ---- the same sums as loops, line by line (what the paper ran) ---------------------------------
def _pose_of(v: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = _rot(v[None])[0]
    M[:3, 3] = v[:3]
    return M


def _vec_of(M: np.ndarray) -> np.ndarray:
    return np.concatenate([M[:3, 3], _rpy(M[None, :3, :3])[0]])


def _wrap1(d: np.ndarray) -> np.ndarray:
    return _wrap(d[None])[0]


def j_literal(y: np.ndarray, p: PaperProblem) -> float:
    """Algorithms 1-9 written as loops over time steps, desired tags and related tags, one pose
    conversion at a time -- the paper's implementation style.  Equal to `cost` (tests check it);
    the bench times Powell with it to measure the speed-up against the method as published."""
    dof = DOF
    Rinv, Qinv, Sinv = (np.linalg.inv(m) for m in (p.R, p.Q, p.S))
    n = p.n_cameras
    observed: list[dict[int, np.ndarray]] = [dict() for _ in range(n)]
    for t, j, z in zip(p.obs_t, p.obs_j, p.obs_z):
        observed[int(t)][int(j)] = z
    desired = range(len(p.tags))
    # Algorithm 2
    total = initial_state_estimate()
    # Algorithm 3 (+ 4)
    for t in range(n):
        xt = y[t * dof:t * dof + dof]
        if t == 0:
            pose_diff = xt - np.zeros(dof)
        else:
            xp = y[(t - 1) * dof:(t - 1) * dof + dof]
            g = _vec_of(_pose_of(xp) @ _pose_of(p.controls[t - 1]))
            pose_diff = xt - g
        pose_diff = _wrap1(pose_diff)
        total += float(pose_diff @ Rinv @ pose_diff)
    # Algorithm 5 (+ 6)
    base = n * dof
    for t in range(n):
        xt = y[t * dof:t * dof + dof]
        for j in desired:
            if j in observed[t]:
                y_j = y[base + j * dof:base + j * dof + dof]
                h = _vec_of(_pose_of(xt) @ _pose_of(observed[t][j]))
                meas_diff = _wrap1(y_j - h)
                total += float(meas_diff @ Qinv @ meas_diff)
    if not p.semantic:
        return total
    # Algorithm 8 (+ 9)
    related = p._related           # type: ignore[attr-defined]
    design_e = p._design_e         # type: ignore[attr-defined]
    design = p._design             # type: ignore[attr-defined]
    sum_sem_diff = {j: 0.0 for j in desired}
    sum_sem_est = 0.0
    for t in range(n):
        for j in desired:
            last = None
            for k in desired:
                if k in related.get(j, ()) and j in observed[t] and k in observed[t]:
                    y_j = y[base + j * dof:base + j * dof + dof]
                    y_k = y[base + k * dof:base + k * dof + dof]
                    if p.semantic_op == "add":
                        s = y_k + _wrap1(design_e[j] - design_e[k])
                    else:
                        s = _vec_of(_pose_of(y_k) @ design[k].between(design[j]).matrix())
                    sem_diff = _wrap1(y_j - s)
                    if p.alg8 == "eq27":
                        sum_sem_est += float(sem_diff @ Sinv @ sem_diff)
                    else:
                        last = sem_diff
            if p.alg8 == "literal" and last is not None:
                sum_sem_diff[j] += float(last @ Sinv @ last)
        if p.alg8 == "literal":
            for j in desired:
                sum_sem_est += sum_sem_diff[j]
    return total + sum_sem_est


def _literal_cost(y: np.ndarray, p: PaperProblem) -> float:
    return j_literal(y, p)


# ---- solutions ------------------------------------------------------------------------------------------
@dataclass
class PaperSolution:
    y: np.ndarray
    cost: float
    seconds: float
    method: str
    evaluations: int = 0
    iterations: int = 0
    converged: bool = True
    message: str = ""

    def tag_poses(self, p: PaperProblem) -> dict[int, Pose3]:
        """structure_T_tag of every state tag (the state frame is the first reported camera's)."""
        tags = self.y[DOF * p.n_cameras:].reshape(-1, DOF)
        return {t: p.world_T_state.compose(from_xyzrpy(tags[i])) for i, t in enumerate(p.tags)}

    def camera_poses(self, p: PaperProblem) -> list[Pose3]:
        x = self.y[: DOF * p.n_cameras].reshape(-1, DOF)
        return [p.world_T_state.compose(from_xyzrpy(v)) for v in x]


def solve_powell(p: PaperProblem, *, options: dict | None = None, x0: np.ndarray | None = None,
                 literal: bool = False) -> PaperSolution:
    """The paper's optimiser: scipy Powell (default options) from an array of zeros the length of
    the state.  `literal` evaluates J with the loop form (as slow as the paper's); otherwise with
    the vectorised form (same values)."""
    from scipy.optimize import minimize

    y0 = np.zeros(p.n_state) if x0 is None else np.asarray(x0, dtype=float)
    t0 = time.perf_counter()
    res = minimize(_literal_cost if literal else cost, y0, args=(p,), method="Powell", options=options)
    dt = time.perf_counter() - t0
    return PaperSolution(np.asarray(res.x), float(res.fun), dt, "powell-literal" if literal else "powell",
                         int(res.nfev), int(res.nit), bool(res.success), str(res.message))


def _noise_sigmas(cov6: np.ndarray, w: float = 1.0, tangent_order: bool = True) -> np.ndarray:
    d = np.diag(cov6) / w
    return np.sqrt(np.concatenate([d[3:], d[:3]]) if tangent_order else d)


def solve_gtsam(p: PaperProblem, form: Literal["lie", "euler", "lie+gn"] = "lie") -> PaperSolution:
    """The same sum of terms on GTSAM, Levenberg-Marquardt from the odometry and first sightings.

    form="lie": Pose3 variables; anchor prior (R), odometry (R), measurements (Q) and one semantic
    factor per Algorithm 8 term (S / weight) as BetweenFactorPose3 -- GTSAM's residuals (Lie-group
    logarithms) agree with the paper's 6-vector differences to first order, so the optimum is the
    paper's up to second-order terms.
    form="euler": then polished on the paper's exact residuals (6-vector variables, CustomFactors),
    so that 2 x the graph's error *is* the paper's J (tests check it).
    form="lie+gn": polished instead by `polish_gauss_newton` (the same exact residuals, numpy).

    Returns the state as 6-vectors and the paper's J at it."""
    import gtsam

    C = gtsam.symbol_shorthand.C
    T = gtsam.symbol_shorthand.T

    def noise(cov6: np.ndarray, w: float = 1.0):
        return gtsam.noiseModel.Diagonal.Sigmas(_noise_sigmas(cov6, w))

    t0 = time.perf_counter()
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    nR, nQ = noise(p.R), noise(p.Q)
    graph.add(gtsam.PriorFactorPose3(C(0), Pose3(), nR))
    cams = [Pose3()]
    for t in range(1, p.n_cameras):
        u = from_xyzrpy(p.controls[t - 1])
        graph.add(gtsam.BetweenFactorPose3(C(t - 1), C(t), u, nR))
        cams.append(cams[-1].compose(u))
    for t, c in enumerate(cams):
        values.insert(C(t), c)
    for t, j, z in zip(p.obs_t, p.obs_j, p.obs_z):
        zp = from_xyzrpy(z)
        graph.add(gtsam.BetweenFactorPose3(C(int(t)), T(int(j)), zp, nQ))
        if not values.exists(T(int(j))):
            values.insert(T(int(j)), cams[int(t)].compose(zp))
    for j, k, w, rel in zip(p.sem_j, p.sem_k, p.sem_w, p.sem_pose):
        graph.add(gtsam.BetweenFactorPose3(T(int(k)), T(int(j)), from_xyzrpy(rel), noise(p.S, float(w))))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(100)
    est = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    y = np.concatenate([to_xyzrpy(est.atPose3(C(t))) for t in range(p.n_cameras)]
                       + [to_xyzrpy(est.atPose3(T(i))) for i in range(len(p.tags))])
    if form == "euler":
        y = _polish_euler(p, y)
    elif form == "lie+gn":
        y = polish_gauss_newton(p, y)
    dt = time.perf_counter() - t0
    return PaperSolution(y, cost(y, p), dt, f"gtsam-{form}")


def euler_graph(p: PaperProblem):
    """The paper's J as a GTSAM graph over 6-vector variables (keys 0..T-1 cameras, then tags):
    every term of Algorithms 3, 5 and 8 a CustomFactor whose whitened residual is the paper's
    wrapped 6-vector difference; 2 x graph.error(values) == J."""
    import gtsam

    n = p.n_cameras

    def sig(cov6: np.ndarray, w: float = 1.0):
        return gtsam.noiseModel.Diagonal.Sigmas(_noise_sigmas(cov6, w, tangent_order=False))

    def compose_factor(key_a: int, key_out: int, b: np.ndarray, Rb: np.ndarray, model):
        """residual = wrap(v_out - v_a * b)"""
        eye = np.eye(DOF)
        steps = np.vstack([eye, -eye]) * 1e-6
        bb = np.repeat(b[None], 2 * DOF + 1, axis=0)
        RR = np.repeat(Rb[None], 2 * DOF + 1, axis=0)

        def err(this, values, H):
            a = values.atVector(key_a)
            o = values.atVector(key_out)
            if H is None:
                return _wrap((o - compose6(a[None], bb[:1], RR[:1])[0])[None])[0]
            out = compose6(np.vstack([a[None], a[None] + steps]), bb, RR)
            d = _wrap(out[1:DOF + 1] - out[DOF + 1:])          # central differences, wrapped
            H[0] = -(d / 2e-6).T
            H[1] = np.eye(DOF)
            return _wrap((o - out[0])[None])[0]
        return gtsam.CustomFactor(model, [key_a, key_out], err)

    def add_factor(key_j: int, key_k: int, r: np.ndarray, model):
        def err(this, values, H):
            d = values.atVector(key_j) - values.atVector(key_k) - r
            if H is not None:
                H[0] = np.eye(DOF)
                H[1] = -np.eye(DOF)
            return _wrap(d[None])[0]
        return gtsam.CustomFactor(model, [key_j, key_k], err)

    def prior_factor(key: int, model):
        def err(this, values, H):
            if H is not None:
                H[0] = np.eye(DOF)
            return _wrap(values.atVector(key)[None])[0]
        return gtsam.CustomFactor(model, [key], err)

    g = gtsam.NonlinearFactorGraph()
    nR, nQ = sig(p.R), sig(p.Q)
    g.add(prior_factor(0, nR))
    for t in range(1, n):
        g.add(compose_factor(t - 1, t, p.controls[t - 1], p._controls_R[t - 1], nR))   # type: ignore[attr-defined]
    for i, (t, j) in enumerate(zip(p.obs_t, p.obs_j)):
        g.add(compose_factor(int(t), n + int(j), p.obs_z[i], p._obs_R[i], nQ))          # type: ignore[attr-defined]
    for i, (j, k, w) in enumerate(zip(p.sem_j, p.sem_k, p.sem_w)):
        if p.semantic_op == "add":
            g.add(add_factor(n + int(j), n + int(k), p.sem_r[i], sig(p.S, float(w))))
        else:
            g.add(compose_factor(n + int(k), n + int(j), p.sem_pose[i], p._sem_R[i], sig(p.S, float(w))))  # type: ignore[attr-defined]
    return g


def euler_values(p: PaperProblem, y: np.ndarray):
    import gtsam

    v = gtsam.Values()
    for i in range(p.n_cameras + len(p.tags)):
        v.insert(i, np.asarray(y[DOF * i:DOF * i + DOF], dtype=float))
    return v


def _polish_euler(p: PaperProblem, y: np.ndarray) -> np.ndarray:
    import gtsam

    # from the Lie-form optimum the exact one is a Gauss-Newton step or two away
    params = gtsam.GaussNewtonParams()
    params.setRelativeErrorTol(1e-10)
    params.setMaxIterations(10)
    est = gtsam.GaussNewtonOptimizer(euler_graph(p), euler_values(p, y), params).optimize()
    out = np.concatenate([est.atVector(i) for i in range(p.n_cameras + len(p.tags))])
    return out if cost(out, p) <= cost(y, p) else y


def _d_compose_da(a: np.ndarray, b: np.ndarray, Rb: np.ndarray, h: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """a * b for (n, 6) rows and its Jacobian d(a * b)/da (n, 6, 6) by central differences,
    all rows at once."""
    n = len(a)
    steps = np.vstack([np.eye(DOF), -np.eye(DOF)]) * h
    A = (a[:, None, :] + steps[None]).reshape(-1, DOF)
    out = compose6(np.vstack([a, A]), np.vstack([b, np.repeat(b, 2 * DOF, axis=0)]),
                   np.concatenate([Rb, np.repeat(Rb, 2 * DOF, axis=0)]))
    f0 = out[:n]
    f = out[n:].reshape(n, 2 * DOF, DOF)
    d = (f[:, :DOF] - f[:, DOF:])
    d[..., 3:] = (d[..., 3:] + math.pi) % (2.0 * math.pi) - math.pi
    return f0, np.transpose(d / (2.0 * h), (0, 2, 1))


def residuals(y: np.ndarray, p: PaperProblem, jacobian: bool = False):
    """The paper's whitened residual vector (J = |r|^2) and, optionally, its Jacobian (dense)."""
    n = p.n_cameras
    x = y[: DOF * n].reshape(-1, DOF)
    tags = y[DOF * n:].reshape(-1, DOF)
    blocks = []                       # (residual (m, 6), whitening (6,) or (m, 6), [(var index (m,), d/dvar (m, 6, 6))])
    eye = np.broadcast_to(np.eye(DOF), (1, DOF, DOF))
    wR = 1.0 / np.sqrt(np.diag(p.R))
    wQ = 1.0 / np.sqrt(np.diag(p.Q))
    wS = 1.0 / np.sqrt(np.diag(p.S))
    blocks.append((_wrap(x[:1]), wR, [(np.array([0]), eye)]))
    if n > 1:
        g, dg = _d_compose_da(x[:-1], p.controls, p._controls_R)          # type: ignore[attr-defined]
        m = n - 1
        blocks.append((_wrap(x[1:] - g), wR, [(np.arange(1, n), np.repeat(eye, m, 0)), (np.arange(0, n - 1), -dg)]))
    hx, dh = _d_compose_da(x[p.obs_t], p.obs_z, p._obs_R)                 # type: ignore[attr-defined]
    blocks.append((_wrap(tags[p.obs_j] - hx), wQ, [(n + p.obs_j, np.repeat(eye, len(hx), 0)), (p.obs_t, -dh)]))
    if len(p.sem_t):
        w = np.sqrt(p.sem_w)[:, None] * wS[None]
        m = len(p.sem_t)
        if p.semantic_op == "add":
            blocks.append((_wrap(tags[p.sem_j] - tags[p.sem_k] - p.sem_r), w,
                           [(n + p.sem_j, np.repeat(eye, m, 0)), (n + p.sem_k, -np.repeat(eye, m, 0))]))
        else:
            sk, ds = _d_compose_da(tags[p.sem_k], p.sem_pose, p._sem_R)    # type: ignore[attr-defined]
            blocks.append((_wrap(tags[p.sem_j] - sk), w,
                           [(n + p.sem_j, np.repeat(eye, m, 0)), (n + p.sem_k, -ds)]))
    r = np.concatenate([(res * w).reshape(-1) for res, w, _ in blocks])
    if not jacobian:
        return r
    Jm = np.zeros((len(r), p.n_state))
    row = 0
    for res, w, parts in blocks:
        m = len(res)
        W = np.broadcast_to(w, (m, DOF))
        rows = row + np.arange(m)[:, None] * DOF + np.arange(DOF)[None]        # (m, 6)
        for var, D in parts:
            cols = var[:, None] * DOF + np.arange(DOF)[None]                    # (m, 6)
            # within one part every (row, column) is distinct, so plain fancy indexing accumulates
            Jm[rows[:, :, None], cols[:, None, :]] += D * W[:, :, None]
        row += m * DOF
    return r, Jm


def polish_gauss_newton(p: PaperProblem, y: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Gauss-Newton on the paper's exact residuals (vectorised numpy), from a nearby solution
    such as GTSAM's: each step is kept only if it lowers J."""
    best, best_cost = np.asarray(y, dtype=float), cost(y, p)
    for _ in range(iterations):
        r, Jm = residuals(best, p, jacobian=True)
        step = np.linalg.solve(Jm.T @ Jm, -(Jm.T @ r))
        cand = best + step
        c = cost(cand, p)
        if not c < best_cost:
            break
        converged = best_cost - c <= 1e-12 * best_cost
        best, best_cost = cand, c
        if converged:
            break
    return best
