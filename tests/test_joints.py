"""Joint estimation on synthetic ground truth: model choice, axis, states, uncertainty, outliers; metrics."""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from artclass_core import InputError, Params, hookimpl, load_registry
from artclass_core.interfaces import JointEstimate, JointEstimator
from artclass_core.joint_metrics import (
    axis_direction_error_rad,
    axis_position_error_m,
    joint_type_accuracy,
    part_iou,
    state_error,
)
from artclass_plugins.joints import BICJointParams, fit_joint
from artclass_plugins.joints.synthetic import synthetic_joint
from artclass_plugins.parts import chain_pair_motions

NOISE_M, NOISE_RAD = 0.001, np.radians(0.5)  # 1 mm and 0.5 degree per axis
UP = np.array([0.0, 0.0, 1.0])


def noisy(kind: str, *, n_outliers: int = 0, seed: int = 0, **kw):
    travel = {"revolute": np.radians(74), "prismatic": 0.3, "fixed": 0.0}[kind]
    return synthetic_joint(
        kind,
        travel=kw.pop("travel", travel),
        noise_m=kw.pop("noise_m", NOISE_M),
        noise_rad=kw.pop("noise_rad", NOISE_RAD),
        n_outliers=n_outliers,
        seed=seed,
        **kw,
    )


def aligned(truth, estimate) -> bool:
    return bool(truth.direction @ estimate.axis_direction > 0)


# -- model choice and accuracy -------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_revolute_is_recovered_and_chosen_over_prismatic(seed):
    truth = noisy("revolute", seed=seed)
    est = fit_joint(truth.poses)
    assert est.type == "revolute"
    assert est.scores["revolute"] < min(est.scores["prismatic"], est.scores["fixed"])
    assert np.degrees(axis_direction_error_rad(truth.direction, est.axis_direction)) < 1.0
    part = truth.poses[0, :3, 3]
    position_error = axis_position_error_m(
        truth.point_m, truth.direction, est.axis_point_m, est.axis_direction, at_m=part
    )
    assert position_error < 0.003
    assert np.degrees(state_error(truth.states, est.states, same_direction=aligned(truth, est))) < 0.5
    assert est.inliers.all() and est.states[0] == 0.0
    assert np.nanmax(est.states) == pytest.approx(np.radians(74), abs=np.radians(1))


@pytest.mark.parametrize("seed", [0, 1])
def test_prismatic_is_recovered_and_chosen_over_revolute(seed):
    truth = noisy("prismatic", seed=seed)
    est = fit_joint(truth.poses)
    assert est.type == "prismatic" and est.scores["prismatic"] < est.scores["revolute"]
    assert (
        np.degrees(axis_direction_error_rad(truth.direction, est.axis_direction, sign_invariant=False)) < 1.0
    )
    assert state_error(truth.states, est.states) < 0.002  # metres
    assert est.state_unit == "m"


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_fixed_part_gets_a_fixed_joint(seed):
    est = fit_joint(noisy("fixed", seed=seed).poses)
    assert est.type == "fixed" and est.axis_direction is None
    assert est.summary(up=UP) == "fixed joint: the part does not move relative to its parent"


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["revolute", "prismatic", "fixed"])
def test_outlier_poses_do_not_flip_the_choice(kind):
    truth = noisy(kind, n_outliers=5, seed=4)
    est = fit_joint(truth.poses)
    assert est.type == kind
    np.testing.assert_array_equal(~est.inliers, truth.outliers)
    assert np.isnan(est.states[truth.outliers]).all()
    if kind != "fixed":
        assert np.degrees(axis_direction_error_rad(truth.direction, est.axis_direction)) < 1.0


@pytest.mark.slow
def test_a_small_turn_is_still_a_turn_but_noise_alone_is_not():
    """3 degrees at 20 cm from the axis is 1 cm of travel, ten times the noise: revolute. Without
    motion the same noise gives no joint (the states are counted as parameters in the BIC)."""
    assert fit_joint(noisy("revolute", travel=np.radians(3)).poses).type == "revolute"
    assert fit_joint(noisy("revolute", travel=0.0).poses).type == "fixed"


def test_a_slide_seen_in_few_poses_is_not_taken_for_a_far_hinge():
    """Over five poses, a hinge whose axis is far off fits a slide's orientation noise better, and
    BIC's penalty of log 5 per parameter does not stop it: the hinge must beat the slide by more than
    two parameters do from noise alone."""
    hinges = sum(
        fit_joint(noisy("prismatic", travel=0.03, n_frames=5, noise_rad=np.radians(1), seed=s).poses).type
        == "revolute"
        for s in range(20)
    )
    assert hinges <= 4


def test_a_slide_that_turns_by_a_drift_is_no_hinge_off_the_object():
    """A carried drawer: its base's error about a flat face turns the slide by 5 degrees over 30 cm of
    travel, which a hinge 3.4 m off fits. Where the object reaches 30 cm from the part, no joint can lie
    that far off: a slide. A true hinge 20 cm from the part stays a hinge, even where the points seen
    reach only 15 cm."""
    truth = noisy("prismatic")
    drift = Rotation.from_rotvec(np.outer(np.linspace(0, np.radians(5), len(truth.poses)), [0.3, 1.0, 0.2]))
    poses = truth.poses.copy()
    poses[:, :3, :3] = (drift * Rotation.from_matrix(truth.poses[:, :3, :3])).as_matrix()
    assert fit_joint(poses).type in ("revolute", "screw")
    assert fit_joint(poses, reach_m=0.3).type == "prismatic"
    assert fit_joint(noisy("revolute").poses, reach_m=0.15).type == "revolute"


@pytest.mark.slow
def test_uncertainties_are_the_size_of_the_errors():
    """Over seeds, the errors are within three reported standard deviations, and not far below one."""
    ratios = []
    for seed in range(4):
        truth = noisy("revolute", seed=seed)
        est = fit_joint(truth.poses)
        ratios.append(
            axis_direction_error_rad(truth.direction, est.axis_direction) / est.axis_direction_std_rad
        )
        part = truth.poses[0, :3, 3]
        ratios.append(
            axis_position_error_m(
                truth.point_m, truth.direction, est.axis_point_m, est.axis_direction, at_m=part
            )
            / est.axis_point_std_m
        )
        assert np.all(est.states_std[est.inliers] > 0)
    assert max(ratios) < 3.0 and np.median(ratios) > 0.2, ratios


@pytest.mark.slow
def test_noise_levels_are_estimated_from_the_data():
    est = fit_joint(noisy("revolute", noise_m=0.003, noise_rad=np.radians(1.0)).poses)
    assert est.info["sigma_position_m"] == pytest.approx(0.003, rel=0.25)
    assert est.info["sigma_orientation_rad"] == pytest.approx(np.radians(1.0), rel=0.25)


@pytest.mark.slow
def test_unknown_frames_stay_unknown():
    truth = noisy("revolute")
    poses = truth.poses.copy()
    poses[[0, 7, 8]] = np.nan
    est = fit_joint(poses)
    assert (
        est.type == "revolute" and np.isnan(est.states[[0, 7, 8]]).all() and not est.inliers[[0, 7, 8]].any()
    )
    assert est.states[1] == 0.0, "states count from the first known frame"


@pytest.mark.slow
def test_summary_reads_like_a_sentence():
    est = fit_joint(noisy("revolute").poses)
    tilt = np.degrees(np.arccos(noisy("revolute").direction @ UP))
    text = est.summary(up=UP)
    assert re.fullmatch(r"revolute joint, axis \d+ deg from vertical, 0-7[345] deg over the video", text), (
        text
    )
    assert f"axis {tilt:.0f} deg" in text
    assert fit_joint(noisy("prismatic").poses).summary(up=UP).startswith("prismatic joint, direction ")
    assert "0-30" in fit_joint(noisy("prismatic").poses).summary(up=UP)  # 0-300 mm (0-299 with noise)


@pytest.mark.slow
def test_same_input_same_result():
    poses = noisy("revolute", n_outliers=3).poses
    a, b = fit_joint(poses), fit_joint(poses)
    np.testing.assert_array_equal(a.states, b.states)
    assert a.scores == b.scores


@pytest.mark.parametrize(
    "poses, problem",
    [
        (np.zeros((5, 3, 3)), "shape"),
        (np.full((5, 4, 4), np.nan), "at least 3 known poses"),
    ],
)
def test_bad_poses_raise_one_line(poses, problem):
    with pytest.raises(InputError, match=problem) as err:
        fit_joint(poses)
    assert "\n" not in str(err.value)


@pytest.mark.slow
def test_poses_given_twice_count_once_with_n_independent():
    """Each pose given twice, with n_independent the number of distinct ones, weighs as the poses
    given once: the same BIC scores, type and uncertainties (not a chi-square doubled), up to the
    few per cent by which the noise levels of fits from other starting pairs differ."""
    poses = noisy("revolute").poses
    once = fit_joint(poses)
    twice = fit_joint(np.concatenate([poses, poses]), n_independent=len(poses))
    doubled = fit_joint(np.concatenate([poses, poses]))
    assert twice.type == once.type == "revolute"
    for name, score in once.scores.items():
        assert twice.scores[name] == pytest.approx(score, rel=0.05), name
        assert abs(doubled.scores[name] - score) > 0.5 * abs(score), "counted twice, the evidence doubles"
    assert twice.axis_direction_std_rad == pytest.approx(once.axis_direction_std_rad, rel=0.05)
    assert twice.axis_point_std_m == pytest.approx(once.axis_point_std_m, rel=0.05)
    assert twice.info["n_independent"] == len(poses)


@pytest.mark.parametrize("n_independent", [0, 61])
def test_n_independent_beyond_the_known_poses_is_one_line(n_independent):
    with pytest.raises(InputError, match="n_independent must be between 1 and the 60 known poses") as err:
        fit_joint(noisy("revolute").poses, n_independent=n_independent)
    assert "\n" not in str(err.value)


@pytest.mark.slow
def test_given_noise_levels_are_used():
    est = fit_joint(
        noisy("revolute").poses, params=BICJointParams(sigma_position_m=0.002, sigma_orientation_rad=0.01)
    )
    assert est.info["sigma_position_m"] == 0.002 and est.info["sigma_orientation_rad"] == 0.01


# -- poses from pairs ------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["prismatic", "revolute", "screw"])
def test_batched_residuals_and_jacobian_match_one_at_a_time(name):
    """The models evaluate many parameter vectors at once (the starts of least median of squares,
    the steps of a forward-difference Jacobian): each row equals its own evaluation, and the batched
    Jacobian equals scipy's 2-point one."""
    from scipy.optimize._numdiff import approx_derivative

    from artclass_plugins.joints import models

    poses, pairs = _start_problem()
    fit = models._best_start(name, poses, pairs)
    x = np.random.default_rng(2).normal(0.0, 0.01, (5, len(fit.x)))
    batched = fit.residuals(x, poses)
    np.testing.assert_allclose(batched, np.stack([fit.residuals(row, poses) for row in x]), atol=1e-9)
    expected = approx_derivative(fit.residuals, x[0], args=(poses,))
    # both are forward differences: they agree to the rounding of a step of 1.5e-8
    np.testing.assert_allclose(fit.jacobian(x[0], poses), expected, atol=1e-6 * np.abs(expected).max())


def test_one_residual_evaluation_per_jacobian_and_no_refit_after_recentring(monkeypatch):
    """The cost of a fit: the forward-difference Jacobian evaluates the residuals at x and its steps in
    one batched call, and least squares runs once for the general model (robustly) and once for
    each model but the fixed one (in closed form); the chosen model, already at its optimum, is
    recentred without another run."""
    from artclass_plugins.joints import models

    runs, evaluations = [], []
    least_squares, residuals = models.least_squares, models._Fit.residuals
    monkeypatch.setattr(models, "least_squares", lambda *a, **kw: runs.append(1) or least_squares(*a, **kw))

    def counted(self, x, poses):
        evaluations.append(np.shape(x))
        return residuals(self, x, poses)

    monkeypatch.setattr(models._Fit, "residuals", counted)
    fit = models._best_start("revolute", *_start_problem())
    evaluations.clear()
    fit.jacobian(np.zeros(len(fit.x)), _start_problem()[0])
    assert evaluations == [(len(fit.x) + 1, len(fit.x))]
    runs.clear()
    assert fit_joint(noisy("revolute").poses).type == "revolute"
    assert len(runs) == 1 + len(models.MODELS) - 1


def test_the_fixed_fit_in_closed_form_is_the_least_squares_optimum():
    """The mean origin and the Karcher mean orientation are where Levenberg-Marquardt ends up from the
    least-median start, to well within the noise (1 mm, 0.5 degree), and the chi-square is no higher."""
    from artclass_plugins.joints import models

    truth = noisy("fixed", n_frames=30, seed=3)
    poses = _observed(truth, NOISE_M, NOISE_RAD)
    closed = models._fixed(poses)
    start = models._best_start("fixed", poses, models._draw_pairs(30, 48, np.random.default_rng(0)))
    iterated = models._refine(start, poses, robust=False)
    _, R_closed, t_closed = closed.unpack()
    _, R_iterated, t_iterated = iterated.unpack()
    np.testing.assert_allclose(t_closed, t_iterated, atol=0.01 * NOISE_M)
    angle = np.linalg.norm(models._quat_to_rotvec(models._quat_mul(models._quat_inv(R_closed), R_iterated)))
    assert angle < 0.01 * NOISE_RAD
    assert closed.chi2 <= iterated.chi2 * (1 + 1e-9)


@pytest.mark.parametrize("kind", ["revolute", "prismatic"])
def test_the_robust_fit_keeps_its_pose_at_state_0_in_place(kind):
    """The pose at state 0 sliding along the joint changes no prediction, and the gauge residual holds
    it in place: the robust fit of the general model (Cauchy loss, outliers present) ends with it
    moved along the joint by a small fraction of a noise sigma, not by tens of them."""
    from artclass_plugins.joints import models

    truth = noisy(kind, n_outliers=5)
    poses = _observed(truth, NOISE_M, NOISE_RAD)
    start = models._best_start("screw", poses, models._draw_pairs(len(poses.t), 48, np.random.default_rng(0)))
    fit = models._refine(start, poses, robust=True)
    w, v, n = fit.shape.start[:3], fit.shape.start[3:], fit.shape.n_joint
    along = np.r_[w / NOISE_RAD, (np.cross(w, fit.t0) + v) / NOISE_M]  # sigmas per unit step along the joint
    assert abs(fit.x[n : n + 6] @ along) < 0.1


def _observed(truth, sigma_m: float, sigma_rad: float):
    """The estimator's view of a synthetic joint's poses, with the given noise levels."""
    from artclass_plugins.joints import models

    return models._Poses(
        Rotation.from_matrix(truth.poses[:, :3, :3]).as_quat(), truth.poses[:, :3, 3], sigma_m, sigma_rad
    )


def _start_problem():
    from artclass_plugins.joints import models

    truth = synthetic_joint("revolute", n_frames=12, travel=0.8, noise_m=0.001, noise_rad=0.005, seed=1)
    poses = _observed(truth, 0.001, 0.005)
    return poses, models._draw_pairs(12, 20, np.random.default_rng(0))


def test_start_twists_of_a_turn_and_of_a_standstill():
    """A pair's relative motion, a turn of 0.5 rad about the axis (0, 0, 1) through (0.1, 0, 0), gives
    the revolute start of that axis (and the screw start of the same twist, scaled to unit length);
    a pair that does not move gives no revolute, prismatic or screw start (NaN), and the fixed start."""
    from artclass_plugins.joints import models

    u, c = np.array([0.0, 0.0, 1.0]), np.array([0.1, 0.0, 0.0])
    xi = np.stack([np.r_[0.5 * u, np.cross(c, 0.5 * u)], np.zeros(6)])
    displacement = np.stack([[0.0, 0.05, 0.0], np.zeros(3)])
    revolute = models._start_twists("revolute", xi, displacement)
    np.testing.assert_allclose(revolute[0], np.r_[u, np.cross(c, u)], atol=1e-12)
    np.testing.assert_allclose(
        models._start_twists("screw", xi, displacement)[0], xi[0] / np.linalg.norm(xi[0])
    )
    np.testing.assert_allclose(models._start_twists("prismatic", xi, displacement)[0], [0, 0, 0, 0, 1, 0])
    for name in ("revolute", "prismatic", "screw"):
        assert np.isnan(models._start_twists(name, xi, displacement)[1]).any(), name
    assert not models._start_twists("fixed", xi, displacement).any()


def test_chain_pair_motions_rebuilds_the_poses():
    truth = noisy("revolute", noise_m=0.0, noise_rad=0.0, n_frames=12)
    P = truth.poses
    pairs = [(i, i + 2, P[i + 2] @ np.linalg.inv(P[i])) for i in range(0, 10, 2)]  # even frames
    pairs += [(3, 1, P[1] @ np.linalg.inv(P[3]))]  # an island
    poses = chain_pair_motions(12, pairs, origin_m=P[0, :3, 3])
    even = np.arange(0, 12, 2)
    # the part's origin and its motion are those of the truth (the orientation is the part's at frame 0)
    np.testing.assert_allclose(poses[even, :3, 3], P[even, :3, 3], atol=1e-9)
    np.testing.assert_allclose(poses[even, :3, :3] @ P[0, :3, :3], P[even, :3, :3], atol=1e-9)
    assert np.isnan(poses[[1, 3, 5, 7, 9, 11]]).all(), "frames not linked to the first one stay unknown"
    assert fit_joint(poses).type == "revolute"


# -- metrics ---------------------------------------------------------------------------------------------


def test_axis_direction_error_is_sign_invariant_for_hinges():
    a, b = np.array([0, 0, 1.0]), np.array([0, np.sin(0.1), -np.cos(0.1)])
    assert axis_direction_error_rad(a, b) == pytest.approx(0.1)
    assert axis_direction_error_rad(a, b, sign_invariant=False) == pytest.approx(np.pi - 0.1)


def test_axis_position_error_is_measured_at_the_part():
    """Two axes crossing at the origin at 0.01 rad: 1 mm apart 10 cm up, 5 mm apart 50 cm up."""
    z, tilted = np.array([0, 0, 1.0]), np.array([np.sin(0.01), 0, np.cos(0.01)])
    at_10cm = axis_position_error_m(np.zeros(3), z, np.zeros(3), tilted, at_m=[0.3, 0.2, 0.1])
    at_50cm = axis_position_error_m(np.zeros(3), z, np.zeros(3), tilted, at_m=[0.0, 0.0, 0.5])
    assert at_10cm == pytest.approx(0.001, rel=1e-3) and at_50cm == pytest.approx(0.005, rel=1e-3)
    shifted = axis_position_error_m([0, 0, 0], z, [0.003, 0.004, 7.0], z, at_m=[1, 1, 1])
    assert shifted == pytest.approx(0.005)


def test_state_error_aligns_zero_and_sign():
    truth = np.radians([0, 10, 20, 30, np.nan])
    assert state_error(truth, truth + 0.3) == pytest.approx(0.0)
    assert state_error(truth, -truth, same_direction=False) == pytest.approx(0.0)
    assert state_error(truth, truth * 1.1) == pytest.approx(np.radians(1.0))  # 0-3 deg off, median 1 deg
    assert np.isnan(state_error([np.nan], [1.0]))


def test_joint_type_accuracy():
    assert (
        joint_type_accuracy(
            ["revolute", "prismatic", "fixed", "revolute"], ["revolute", "revolute", "fixed", "revolute"]
        )
        == 0.75
    )
    with pytest.raises(ValueError):
        joint_type_accuracy(["fixed"], [])


def test_part_iou_matches_parts_whatever_their_numbers():
    truth = np.zeros((10, 10), int)
    truth[:, :5], truth[:, 5:] = 1, 2
    estimate = np.where(truth == 1, 7, 3)
    estimate[:, 4] = 3  # one column of part 1 given to part 2
    scores = part_iou(truth, estimate)
    assert scores == {1: pytest.approx(40 / 50), 2: pytest.approx(50 / 60)}
    assert part_iou(truth, np.zeros_like(truth)) == {1: 0.0, 2: 0.0}


# -- the plugin kind -------------------------------------------------------------------------------------


@pytest.mark.slow
def test_hook_register_joint_estimators():
    """The built-in estimator comes from the entry points; a plugin adds its own through the hook."""

    class AlwaysFixed(JointEstimator):
        name = "always_fixed"
        description = "calls every joint fixed (test only)"
        Params = Params

        def estimate(self, poses):
            known = np.isfinite(poses).all(axis=(1, 2))
            return JointEstimate("fixed", None, None, np.where(known, 0.0, np.nan), known)

    @hookimpl
    def register_joint_estimators(register):
        register(AlwaysFixed)

    registry = load_registry(
        extra_plugins=(SimpleNamespace(register_joint_estimators=register_joint_estimators),),
        entry_point_setting="",
    )
    assert registry.names("joint_estimator") == ["always_fixed", "bic"]
    poses = noisy("revolute").poses
    assert registry.create("joint_estimator", "always_fixed").estimate(poses).type == "fixed"
    assert registry.create("joint_estimator", "bic").estimate(poses).type == "revolute"


def test_a_part_moving_freely_gets_no_joint():
    """Poses scattered 10 cm and 40 degrees at random fit no joint within the largest plausible noise."""
    rng = np.random.default_rng(0)
    poses = noisy("fixed").poses
    poses[:, :3, 3] += rng.normal(0, 0.1, (len(poses), 3))
    poses[:, :3, :3] = (
        Rotation.from_rotvec(rng.normal(0, 0.7, (len(poses), 3))).as_matrix() @ poses[:, :3, :3]
    )
    est = fit_joint(poses)
    assert est.type == "free" and est.axis_direction is None and np.isnan(est.states).all()
    assert est.summary(up=UP).startswith("free motion: no single joint explains the part's motion")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_part_turning_more_than_5_degrees_off_every_joint_moves_freely(seed):
    """A hinge's poses turned at random by 10 degrees (per axis) off its path follow no joint: free;
    by 2 degrees, a registration's error, they are still the hinge."""
    assert fit_joint(noisy("revolute", noise_rad=np.radians(10), seed=seed).poses).type == "free"
    assert fit_joint(noisy("revolute", noise_rad=np.radians(2), seed=seed).poses).type == "revolute"


@pytest.mark.parametrize("kind", ["revolute", "prismatic", "screw", "small turn"])
def test_compiled_prediction_is_the_twist_arithmetic(kind):
    """The compiled loop of a fit predicts each pose as exp(q ξ) P0: poses on the joint's path get
    back their own states with zero residual, and any pose the state its twist relative to P0 projects
    onto ξ, the pose twist_exp gives at that state, and that pose's error against the observed one."""
    from artclass_plugins.joints import models

    rng = np.random.default_rng(3)
    xi = {
        "revolute": np.r_[0.0, 0.6, 0.8, np.cross([0.1, 0.0, 0.2], [0.0, 0.6, 0.8])],
        "prismatic": np.r_[0.0, 0.0, 0.0, 0.6, 0.0, 0.8],
        "screw": np.r_[0.0, 0.6, 0.8, 0.05, 0.02, 0.1],
        "small turn": np.r_[1e-6, 0.0, 0.0, 0.0, 0.3, 0.0],
    }[kind]
    R0, t0 = Rotation.from_rotvec([0.2, -0.1, 0.3]).as_quat(), np.array([0.1, 0.2, 0.6])
    states = rng.uniform(-1.0, 1.0, 20)
    R_m, t_m = models.twist_exp(xi, states)
    on_path = models._Poses(models._quat_mul(R_m, R0), models._quat_apply(R_m, t0) + t_m, NOISE_M, NOISE_RAD)
    q, R_hat, t_hat = models._predict(on_path, xi, R0, t0)
    np.testing.assert_allclose(q, states, atol=1e-9)
    np.testing.assert_allclose(on_path.residuals(R_hat, t_hat), 0.0, atol=1e-6)

    off = models._Poses(
        Rotation.random(20, random_state=4).as_quat(), rng.normal(0.0, 0.2, (20, 3)), NOISE_M, NOISE_RAD
    )
    q, R_hat, t_hat = models._predict(off, xi, R0, t0)
    logs = models.twist_log(models._quat_mul(off.R, models._quat_inv(R0)), off.t - t0)
    centred = (
        np.r_[xi[:3], xi[3:] + np.cross(xi[:3], t0)] * np.r_[[(NOISE_M / NOISE_RAD) ** 2] * 3, [1.0] * 3]
    )
    np.testing.assert_allclose(q, logs @ centred / (centred @ np.r_[xi[:3], xi[3:] + np.cross(xi[:3], t0)]))
    R_m, t_m = models.twist_exp(xi, q)
    np.testing.assert_allclose(R_hat, models._quat_mul(R_m, R0), atol=1e-12)
    np.testing.assert_allclose(t_hat, models._quat_apply(R_m, t0) + t_m, atol=1e-12)
    error = Rotation.from_quat(off.R).inv() * Rotation.from_quat(R_hat)
    np.testing.assert_allclose(
        off.residuals(R_hat, t_hat),
        np.c_[(t_hat - off.t) / NOISE_M, error.as_rotvec() / NOISE_RAD],
        atol=1e-6,
    )


@pytest.mark.parametrize("name", ["fixed", "prismatic", "revolute", "screw"])
def test_compiled_fit_residuals_are_the_poses_and_the_gauge(name):
    """The one compiled pass that least squares calls gives each model's pose residuals (the numpy
    steps: the twist of the steps, the corrected pose at state 0, the predicted poses) followed by its
    gauge rows: the slide of the pose at state 0 along the start's twist in noise sigmas, and for the
    screw its twist's scale."""
    from artclass_plugins.joints import models

    rng = np.random.default_rng(5)
    poses = models._Poses(
        Rotation.random(12, random_state=6).as_quat(), rng.normal(0.0, 0.2, (12, 3)), NOISE_M, NOISE_RAD
    )
    start = {
        "fixed": np.zeros(6),
        "prismatic": np.r_[0.0, 0.0, 0.0, 0.6, 0.0, 0.8],
        "revolute": np.r_[0.0, 0.6, 0.8, np.cross([0.1, 0.0, 0.2], [0.0, 0.6, 0.8])],
        "screw": np.r_[0.0, 0.6, 0.8, 0.05, 0.02, 0.1] / np.linalg.norm([0.0, 0.6, 0.8, 0.05, 0.02, 0.1]),
    }[name]
    shape = models._Shape(name, start, anchor=np.array([0.3, -0.1, 0.5]) if name == "revolute" else None)
    fit = models._Fit(
        shape, np.zeros(shape.n_joint + 6), Rotation.random(random_state=7).as_quat(), np.r_[0.1, 0.2, 0.6]
    )
    x = rng.normal(0.0, 0.05, (3, shape.n_joint + 6))
    pose = fit.pose_residuals(x, poses).reshape(3, -1)
    along = np.r_[start[:3] / NOISE_RAD, (np.cross(start[:3], fit.t0) + start[3:]) / NOISE_M]
    gauge = np.zeros((3, 0)) if name == "fixed" else (x[:, shape.n_joint :] @ along)[:, None]
    if name == "screw":
        gauge = np.c_[gauge, x[:, :6] @ start * np.linalg.norm(along)]
    np.testing.assert_allclose(fit.residuals(x, poses), np.c_[pose, gauge], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(fit.residuals(x[1], poses), np.r_[pose[1], gauge[1]], rtol=1e-9, atol=1e-9)
