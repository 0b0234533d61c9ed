"""The SLAM step's shortcuts give the estimate the plain graph gives (issue 21): the corner factor's
fast error function against the reference Python factor (`project_corners`), the variables held
at their linearisation point because every factor is linear in them, the marginals read from one
joint marginal, the residuals evaluated in one array pass, and a new tag's refined start."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimation.fiducials import Detection, tag_object_points
from estimation.rig_model import (AXIS, BASE, DISTORTION, GAUGE_SIGMA, INTRINSICS, MOUNT, RigGeometry, ViewMotion, _cal_vector,
                                  _refine_tag_pose_numpy, cal3_s2, corner_factor, project_corners, radial_basis,
                                  refine_tag_pose)
from estimation.sf_graphslam import INTRINSICS_RELINEARIZE_PX, SfGraphSlam, SlamConfig
from lab.core.config import load_rig
from lab.core.geometry import Pose3, Rot3
from lab.core.rig_calibration_file import RigCalibration
from lab.core.structures.borg import build_borg

RIG = load_rig()
MODEL = build_borg(3)
K = np.array([[914.0, 0.1, 639.5], [0, 913.0, 359.5], [0, 0, 1]])
GEOM = RigGeometry.from_rig(RIG, MODEL.world_T_structure(0.0), K)
TT = list(MODEL.turntable.tag_ids)
C, T, S = gtsam.symbol_shorthand.C, gtsam.symbol_shorthand.T, gtsam.symbol_shorthand.S


def _reference_corner_factor(camera_key, tag_key, meas, local, sigma, cal, scale_key, lens):
    """The corner factor as it was written first: `project_corners` (one numpy pass, the
    derivation in its docstring), the scale and lens terms added after."""
    local_rows = np.repeat(local, 2, axis=0)

    def error(this, values, jacobians):
        k = 1.0 + float(values.atVector(scale_key)[0])
        e, JC, JT, _ = project_corners(values.atPose3(camera_key), values.atPose3(tag_key), k * local, cal, meas,
                                       want_jacobians=jacobians is not None)
        e = e - lens[1] @ values.atVector(lens[0])
        if jacobians is not None:
            jacobians[0], jacobians[1] = JC, JT
            jacobians[2] = np.sum(JT[:, 3:] * local_rows, axis=1, keepdims=True)
            jacobians[3] = -lens[1]
        return e

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(8, sigma), [camera_key, tag_key, scale_key, lens[0]],
                              error)


def _small_survey(seed: int = 0):
    """Three cameras around one tag printed 0.15 % large, corners with 0.05 px noise."""
    rng = np.random.default_rng(seed)
    tag = Pose3(Rot3.RzRyRx(np.pi / 2, 0.0, -np.pi / 2 + 0.3), np.array([0.0, 0.2, 0.6]))
    local = tag_object_points(0.1)
    cams = [tag.compose(Pose3(Rot3.RzRyRx(np.pi, yaw, 0.0), np.zeros(3))).compose(Pose3(Rot3(), np.array([0.0, 0.0, -2.0])))
            for yaw in (-0.35, 0.0, 0.4)]
    meas = []
    for cam in cams:
        pinhole = gtsam.PinholeCameraCal3_S2(cam, cal3_s2(K))
        meas.append(np.array([pinhole.project(tag.transformFrom(1.0015 * p)) for p in local])
                    + rng.normal(0.0, 0.05, (4, 2)))
    return tag, cams, local, meas


def _solved(fast: bool):
    """The small survey's graph with the fast or the reference corner factor, solved to the last digit."""
    tag, cams, local, meas = _small_survey()
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    cal = cal3_s2(K)
    for i, (cam, uv) in enumerate(zip(cams, meas)):
        lens = (DISTORTION, radial_basis(uv, K))
        if fast:
            graph.add(corner_factor(C(i), T(0), uv, local, 0.05, robust_k=None, fixed=cal, scale_key=S(0),
                                    distortion=lens))
        else:
            graph.add(_reference_corner_factor(C(i), T(0), uv, local, 0.05, _cal_vector(cal), S(0), lens))
        graph.add(gtsam.PriorFactorPose3(C(i), cam, gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
        values.insert(C(i), cam)
    graph.add(gtsam.PriorFactorVector(S(0), np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, 0.001)))
    graph.add(gtsam.PriorFactorVector(DISTORTION, np.zeros(2), gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-4]))))
    values.insert(T(0), tag.retract(np.array([0.01, -0.02, 0.005, 0.002, -0.001, 0.003])))
    values.insert(S(0), np.zeros(1))
    values.insert(DISTORTION, np.array([2e-4, -1e-5]))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-16)
    return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize(), graph, values


def test_the_fast_corner_factor_gives_the_reference_factors_error_and_estimate():
    est, graph, values = _solved(fast=True)
    ref, ref_graph, _ = _solved(fast=False)
    for i in range(3):
        # the error and its Jacobians at the start and at the solution, factor by factor
        for at in (values, est):
            f, r = graph.at(2 * i), ref_graph.at(2 * i)
            assert f.unwhitenedError(at) == pytest.approx(r.unwhitenedError(at), abs=1e-9)
            Af, bf = f.linearize(at).jacobian()
            Ar, br = r.linearize(at).jacobian()
            assert np.abs(Af - Ar).max() <= 1e-9 * np.abs(Ar).max() and np.abs(bf - br).max() < 1e-9
    assert np.abs(est.atPose3(T(0)).translation() - ref.atPose3(T(0)).translation()).max() < 1e-9
    assert np.abs(gtsam.Rot3.Logmap(est.atPose3(T(0)).rotation().between(ref.atPose3(T(0)).rotation()))).max() < 1e-9
    assert est.atVector(S(0))[0] == pytest.approx(ref.atVector(S(0))[0], abs=1e-9)
    # the tag moved: the comparison is of a solve, not of the start
    assert np.abs(est.atPose3(T(0)).translation() - values.atPose3(T(0)).translation()).max() > 1e-4


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("scale_sigma", [0.0, 0.001])
@pytest.mark.parametrize("lens", [False, True])
def test_the_compiled_refinement_is_the_numpy_one(seed, scale_sigma, lens):
    """`refine_tag_pose`'s compiled steps (`corner_kernel.tag_step`) against its numpy form, step
    for step: the same pose and scale to round-off, from a start a degree and centimetres off, with
    and without the print scale and the lens term, each view its own sigma."""
    tag, cams, local, meas = _small_survey(seed)
    rng = np.random.default_rng(seed)
    start = tag.retract(rng.normal(0.0, 0.02, 6))
    cal = _cal_vector(cal3_s2(K))
    sigmas = np.array([0.05, 0.07, 0.1])
    lens_term = (np.array([radial_basis(uv, K) for uv in meas]), np.array([2e-3, -3e-4])) if lens else None
    for iterations in (1, 5):
        a = refine_tag_pose(start, cams, np.array(meas), local, cal, sigmas, 0.0005, lens_term, scale_sigma,
                            iterations=iterations)
        b = _refine_tag_pose_numpy(start, cams, np.array(meas), local, cal, sigmas, 0.0005, lens_term, scale_sigma,
                                   iterations=iterations)
        assert np.abs(a[0].translation() - b[0].translation()).max() < 1e-12
        assert np.abs(gtsam.Rot3.Logmap(a[0].rotation().between(b[0].rotation()))).max() < 1e-12
        assert a[1] == pytest.approx(b[1], abs=1e-15)
        assert np.abs(a[0].translation() - start.translation()).max() > 1e-3     # it did move


def test_a_refinement_with_a_camera_behind_the_tag_stays_where_it_started():
    tag, cams, local, meas = _small_survey(0)
    behind = tag.compose(Pose3(Rot3(), np.array([0.0, 0.0, 0.5])))        # looking away from the tag
    got, scale = refine_tag_pose(tag, cams + [behind], np.array(meas + [meas[0]]), local, _cal_vector(cal3_s2(K)),
                                 np.full(4, 0.05))
    assert got.equals(tag, 0.0) and scale == 0.0


def test_a_tag_refined_against_fixed_cameras_is_the_least_squares_tag():
    tag, cams, local, meas = _small_survey(1)
    start = tag.retract(np.array([0.02, -0.015, 0.01, 0.003, -0.002, 0.004]))
    got, scale = refine_tag_pose(start, cams, np.array(meas), local, _cal_vector(cal3_s2(K)), np.full(3, 0.05),
                                 scale_sigma=0.001)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for i, (cam, uv) in enumerate(zip(cams, meas)):
        graph.add(corner_factor(C(i), T(0), uv, local, 0.05, robust_k=None, fixed=cal3_s2(K), scale_key=S(0)))
        graph.add(gtsam.NonlinearEqualityPose3(C(i), cam))
        values.insert(C(i), cam)
    graph.add(gtsam.PriorFactorVector(S(0), np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, 0.001)))
    values.insert(T(0), start)
    values.insert(S(0), np.zeros(1))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-16)
    lm = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    assert np.abs(got.translation() - lm.atPose3(T(0)).translation()).max() < 1e-9
    assert np.abs(gtsam.Rot3.Logmap(got.rotation().between(lm.atPose3(T(0)).rotation()))).max() < 1e-9
    assert scale == pytest.approx(lm.atVector(S(0))[0], abs=1e-9)


def _calibration() -> RigCalibration:
    """The rig survey's posterior as a run graph gets it: a joint covariance over the axis, base,
    mount, intrinsics, lens and the turntable tags (independent blocks here)."""
    means, covs = GEOM.priors(None)
    n = 18 + 5 + 2 + 6 * len(TT)
    joint = np.zeros((n, n))
    joint[:6, :6], joint[6:12, 6:12], joint[12:18, 12:18] = covs[AXIS], covs[BASE], covs[MOUNT]
    for i in (2, 5):
        joint[i, i] = GAUGE_SIGMA ** 2
    joint[18:23, 18:23] = np.diag([1.0, 1.0, 1e-8, 0.25, 0.25])
    joint[23:25, 23:25] = np.diag([1e-6, 1e-7])
    for i, t in enumerate(TT):
        joint[25 + 6 * i:31 + 6 * i, 25 + 6 * i:31 + 6 * i] = np.diag([0.01 ** 2] * 3 + [0.0005 ** 2] * 3)
    marg = {"world_T_axis": joint[:6, :6], "world_T_base": joint[6:12, 6:12], "platform_T_camera": joint[12:18, 12:18],
            "K": joint[np.ix_([18, 19, 21, 22], [18, 19, 21, 22])]}
    tags = {t: MODEL.tags[t].structure_T_tag for t in TT}
    tag_covs = {t: joint[25 + 6 * i:31 + 6 * i, 25 + 6 * i:31 + 6 * i] for i, t in enumerate(TT)}
    return RigCalibration(means[MOUNT], means[BASE], means[AXIS], K, marg, tags, tag_covs, 0.05, 10, "sim",
                          joint_covariance=joint, corner_sigma_px=0.05)


def _steps(seed: int = 0):
    """Two steps of two views each, the rig where its nominal geometry puts it: each tag's
    corners with 0.05 px noise, its IPPE pose a few tenths of a degree off."""
    rng = np.random.default_rng(seed)
    return [[_view(a, (0, 1, 2, 9, 13, 36, 37, 38, 47), rng) for a in angles] for angles in ((-0.6, -0.3), (0.0, 0.3))]


def _view(turntable_rad: float, tags, rng, imaging_K: np.ndarray = K):
    """One view at this turntable angle (the rig at its nominal geometry): the camera, the
    detections of those of `tags` that face it (corners imaged through `imaging_K` with 0.05 px
    noise, IPPE a few tenths of a degree off), the motion."""
    motion = ViewMotion(turntable_rad, (0.0, 0.0, 0.0, 0.0, 0.1047, 0.0))
    cam = GEOM.predict_nominal(motion)
    pinhole = gtsam.PinholeCameraCal3_S2(cam, cal3_s2(imaging_K))
    dets = []
    for t in tags:
        spec = MODEL.tags[t]
        ct = cam.between(spec.structure_T_tag)
        if float(ct.rotation().matrix()[:, 2] @ ct.translation()) >= 0:
            continue
        uv = np.array([pinhole.project(spec.structure_T_tag.transformFrom(p))
                       for p in tag_object_points(spec.size_m)]) + rng.normal(0.0, 0.05, (4, 2))
        ippe = ct.compose(Pose3(Rot3.Expmap(rng.normal(0.0, 0.005, 3)), rng.normal(0.0, 0.001, 3)))
        dets.append(Detection(t, uv, ippe, np.eye(6) * 1e-4, 0.05, 10.0, False, spec.size_m))
    return cam, dets, motion


def _run(hold_linear: bool = True) -> SfGraphSlam:
    slam = SfGraphSlam(MODEL, SlamConfig(observation="corners", corner_sigma_px=0.05, tag_scale_sigma=0.001),
                       rig=GEOM, calibration=_calibration(), camera=(K, np.zeros(5)))
    if not hold_linear:
        slam._linear_keys = gtsam.KeyList
    for views in _steps():
        for cam, dets, motion in views:
            slam.add_view(cam, dets, motion)
        slam.update(snapshot=[0, 1, 2])
    return slam


def test_holding_the_linear_variables_changes_no_estimate_and_no_marginal():
    held, free = _run(), _run(hold_linear=False)
    assert list(held._linear_keys()) and not list(free._linear_keys())
    assert held.tags == free.tags and len(held.tags) >= 8
    for t in held.tags:
        a, b = held.tag_pose(t), free.tag_pose(t)
        assert np.abs(a.translation() - b.translation()).max() < 1e-9
        assert np.abs(gtsam.Rot3.Logmap(a.rotation().between(b.rotation()))).max() < 1e-9
        assert held.tag_covariance(t) == pytest.approx(free.tag_covariance(t), rel=1e-6, abs=1e-15)


def test_a_steps_marginals_from_one_joint_marginal_are_isam2s_own():
    slam = _run()
    slam._prefetch([0, 1, 2, 36, 37])
    assert (slam.key(0), slam.key(36)) in slam._cov_blocks
    for t in (0, 1, 2, 36, 37):
        assert slam.tag_covariance(t) == pytest.approx(slam.isam.marginalCovariance(slam.key(t)), rel=1e-9, abs=1e-15)
    got = slam._relative_covariance(0, 36)
    slam._cov_blocks = {}
    assert got == pytest.approx(slam._relative_covariance(0, 36), rel=1e-9, abs=1e-15)


def test_many_tags_covariances_from_joint_marginals_are_each_tags_own(monkeypatch):
    """`tag_covariances` (joint marginals in chunks, the logged covariances) gives each tag's
    `tag_covariance`, scaled alike, for chunks smaller than the tags and for a prefetched tag."""
    from estimation import sf_graphslam

    slam = _run()
    tags = sorted(slam.tags)
    each = {t: slam.tag_covariance(t) for t in tags}
    monkeypatch.setattr(sf_graphslam, "JOINT_CHUNK", 3)
    slam._prefetch([tags[0], tags[1]])
    got = slam.tag_covariances(tags + [tags[0], 999_999])       # a repeat and an unknown tag
    assert sorted(got) == tags
    for t in tags:
        assert got[t] == pytest.approx(each[t], rel=1e-9, abs=1e-15)


def test_the_residuals_in_one_pass_are_the_corner_factors_own():
    # no semantic factors: the residuals are read at the estimate that first includes their factors
    slam = SfGraphSlam(MODEL, SlamConfig(semantic=False, observation="corners", corner_sigma_px=0.05,
                                         tag_scale_sigma=0.001),
                       rig=GEOM, calibration=_calibration(), camera=(K, np.zeros(5)))
    for cam, dets, motion in _steps()[0]:
        slam.add_view(cam, dets, motion)
    slam.update()
    own = np.concatenate([np.asarray(slam.graph.at(f[0]).unwhitenedError(slam.estimate)) / f[1]
                          for f in slam._corner_factors])
    assert len(own) > 40 and slam.face_on_residuals() == pytest.approx(own, abs=1e-9)


def test_the_relinearisation_check_without_a_copy_is_the_copied_deltas():
    """`_moved_past_threshold` counts over the whole delta less the held variables' components; it
    answers as zeroing the held variables in a copy of the delta and taking the maximum did, the
    intrinsics (unless held) judged on their own threshold as iSAM2 judges them."""
    slam = _run()

    def copied(held) -> bool:
        delta = gtsam.VectorValues(slam.isam.getDelta())
        own = INTRINSICS not in set(held) and delta.exists(INTRINSICS)
        intrinsics_over = own and float(np.abs(delta.at(INTRINSICS)).max()) >= INTRINSICS_RELINEARIZE_PX
        zero = gtsam.VectorValues()
        for key in set(held) | ({INTRINSICS} if own else set()):
            if delta.exists(key):
                zero.insert(key, np.zeros(delta.at(key).size))
        if zero.size():
            delta.update(zero)
        v = delta.vector()
        return intrinsics_over or (v.size > 0 and float(np.abs(v).max()) >= slam.config.relinearize_threshold)

    held = slam._linear_keys()
    assert list(held)
    for threshold in (1e-12, 1e-6, 1e-3, 1.0):
        slam.config = SlamConfig(**{**slam.config.__dict__, "relinearize_threshold": threshold})
        for keys in (held, gtsam.KeyList()):
            assert slam._moved_past_threshold(keys) == copied(keys)
    # both answers occur (the check is not vacuous)
    slam.config = SlamConfig(**{**slam.config.__dict__, "relinearize_threshold": 1e-12})
    assert slam._moved_past_threshold(held)
    slam.config = SlamConfig(**{**slam.config.__dict__, "relinearize_threshold": 1.0})
    assert not slam._moved_past_threshold(held)


def test_the_chain_noise_at_the_nominal_mount_is_computed_once_to_the_same_bits():
    motion = ViewMotion(0.4, (0.01, -0.02, 0.005, 0.02, 0.1, -0.03))
    cached = GEOM.chain_noise(motion).covariance()
    again = GEOM.chain_noise(motion).covariance()
    explicit = GEOM.chain_noise(motion, GEOM.nominal_platform_T_camera).covariance()
    assert np.array_equal(cached, explicit) and np.array_equal(cached, again)
    moved = GEOM.nominal_platform_T_camera.compose(Pose3(Rot3.Rz(0.2), np.array([0.01, 0.0, 0.0])))
    assert not np.array_equal(GEOM.chain_noise(motion, moved).covariance(), cached)


def _root_frontals(slam: SfGraphSlam, tmp_path) -> list[str]:
    """The Bayes tree's root clique's variables in elimination order (its dot label)."""
    import re

    path = tmp_path / "tree.dot"
    slam.isam.saveGraph(str(path))
    labels = re.findall(r'label="([^"]*)"', path.read_text())
    (root,) = [label for label in labels if ":" not in label]          # the root has no separator
    return [k.strip() for k in root.split(",")]


def test_the_modules_tags_go_last_in_the_tree_and_change_no_estimate_and_no_marginal(tmp_path):
    """A step's snapshot tags and their relations' partners are eliminated last (the root of the
    Bayes tree), so that their marginals come from the root clique alone; the estimate and the
    marginals are the free ordering's to round-off."""
    last, free = _run(), _run()
    free._last_groups = lambda observed: None
    for views in _steps(1):
        for slam in (last, free):
            for cam, dets, motion in views:
                slam.add_view(cam, dets, motion)
    for slam in (last, free):
        slam.update(snapshot=[36, 37, 38], hold=True)
    assert last.tags == free.tags
    for t in last.tags:
        a, b = last.tag_pose(t), free.tag_pose(t)
        assert np.abs(a.translation() - b.translation()).max() < 1e-9
        assert np.abs(gtsam.Rot3.Logmap(a.rotation().between(b.rotation()))).max() < 1e-9
        assert last.tag_covariance(t) == pytest.approx(free.tag_covariance(t), rel=1e-6, abs=1e-15)
    wanted = {gtsam.DefaultKeyFormatter(k) for k in last._last}
    assert {gtsam.DefaultKeyFormatter(last.key(t)) for t in (36, 37, 38)} <= wanted
    root = _root_frontals(last, tmp_path)
    tail = root[len(root) - len(wanted & set(root)):]
    assert set(tail) == wanted & set(root) and {"t36", "t37", "t38"} <= set(tail)
    # the check has teeth: left to itself iSAM2 puts them elsewhere
    assert not {"t36", "t37", "t38"} <= set(_root_frontals(free, tmp_path))
    last.release([36, 37, 38])
    assert last._last == []


def test_a_pair_brought_to_the_root_keeps_its_estimate_and_its_joint_marginal(tmp_path):
    """`_to_root` re-eliminates a pair into the root, relinearising nothing: every estimate and
    the pair's joint marginal are what they were, to round-off.  (In this small graph every tag is
    at the root already: the pair is a tag and the first view's camera, which is not.)"""
    slam = _run()
    a, b = C(0), slam.key(0)
    assert "c0" not in _root_frontals(slam, tmp_path)
    before = {t: slam.tag_pose(t) for t in slam.tags}
    joint = slam.isam.jointMarginalCovariance([a, b])
    blocks = [joint.at(a, a), joint.at(a, b), joint.at(b, b)]
    slam._to_root([a, b])
    assert {"c0", "t0"} == set(_root_frontals(slam, tmp_path)[-2:])
    for t, pose in before.items():
        assert np.abs(slam.tag_pose(t).translation() - pose.translation()).max() < 1e-12
        assert np.abs(gtsam.Rot3.Logmap(slam.tag_pose(t).rotation().between(pose.rotation()))).max() < 1e-12
    joint = slam.isam.jointMarginalCovariance([a, b])
    for got, want in zip([joint.at(a, a), joint.at(a, b), joint.at(b, b)], blocks):
        assert got == pytest.approx(want, rel=1e-9, abs=1e-15)


def test_the_relations_the_gate_reads_are_those_a_pass_over_every_relation_finds():
    """`_decidable` reads the relations kept open as tags arrive and relations are decided, not
    every relation of the structure; the list, in its order, must be the full pass's, through
    steps, held tags, a release and a re-placed module."""

    def every(slam: SfGraphSlam) -> list:
        out = []
        for rel in slam.relations.values():
            if rel.decided or rel.a not in slam.tags or rel.b not in slam.tags:
                continue
            if min(slam.observations.get(rel.a, 0), slam.observations.get(rel.b, 0)) < slam.config.min_observations:
                continue
            if {rel.a, rel.b} & slam.held and rel.kind != "deployable":
                continue
            out.append(rel)
        return out

    slam = SfGraphSlam(MODEL, SlamConfig(observation="corners", corner_sigma_px=0.05, tag_scale_sigma=0.001),
                       rig=GEOM, calibration=_calibration(), camera=(K, np.zeros(5)))
    read = []
    for i, views in enumerate(_steps() + _steps(seed=1)):
        for cam, dets, motion in views:
            slam.add_view(cam, dets, motion)
            assert slam._decidable() == every(slam)
        slam.update(snapshot=[0, 1, 2], hold=True)
        assert slam._decidable() == every(slam)
        read.append(len(every(slam)))
        slam.release([0, 1, 2])
        assert slam._decidable() == every(slam)
        if i == 1:
            slam.replace_tags([0, 1, 2])
            assert slam._decidable() == every(slam)
    assert any(r.decided for r in slam.relations.values()) and max(read) > 0
