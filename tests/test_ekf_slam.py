"""EKF-SLAM core and recovery planner (companion/nav/ekf_slam, issue 14): Jacobians against
numerical differentiation, the O(n^2) Joseph update against the dense textbook form, the
augmentation covariance, gating, first-estimates Jacobians against the plain EKF on a small Monte
Carlo, sub-maps, and the planner's STEPs. Scored against simulated truth, never the estimator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.nav.ekf_slam.config import EkfSlamConfig, RecoveryPlannerConfig
from companion.nav.ekf_slam.filter import LOST_MAX_M, EkfSlam, chi2_quantile, nees, nees_band, pose_error
from companion.nav.ekf_slam.model import (
    full_observation_jacobian,
    inverse_observe,
    inverse_observe_jacobians,
    level_offset,
    level_offset_cov,
    level_offset_jacobian,
    motion,
    motion_jacobians,
    observe,
    predict_level_offset,
    wrap,
)
from companion.nav.ekf_slam.planner import RecoveryPlanner

DOWN = -100.0


def numeric_jacobian(fn, x: np.ndarray, eps: float = 1e-6, wrap_rows: tuple[int, ...] = ()) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    f0 = fn(x)
    jac = np.zeros((f0.size, x.size))
    for j in range(x.size):
        d = np.zeros_like(x)
        d[j] = eps
        diff = fn(x + d) - fn(x - d)
        for r in wrap_rows:
            diff[r] = wrap(diff[r])
        jac[:, j] = diff / (2 * eps)
    return jac


@pytest.mark.parametrize("pose, landmark", [
    ((3.0, -2.0, 0.4), (20.0, 10.0, -3.0)),
    ((0.0, 0.0, -2.9), (-15.0, 25.0, 0.0)),
    ((100.0, 50.0, 1.6), (95.0, 30.0, -4.5)),
])
def test_observation_jacobian_matches_numerical_differentiation(pose, landmark) -> None:
    def h(s: np.ndarray) -> np.ndarray:
        return observe(s[:3], DOWN, s[3:])

    state = np.array(pose + landmark)
    delta = np.array(landmark) - np.array([pose[0], pose[1], DOWN])
    np.testing.assert_allclose(full_observation_jacobian(delta), numeric_jacobian(h, state, wrap_rows=(1,)),
                               atol=1e-7, rtol=1e-5)


def test_observation_conventions_ned_azimuth_clockwise_elevation_negative_below() -> None:
    # a landmark 10 m east of a vehicle facing north, on the ground 100 m below
    r, az, el = observe(np.array([0.0, 0.0, 0.0]), DOWN, np.array([0.0, 10.0, 0.0]))
    assert r == pytest.approx(math.hypot(10.0, 100.0))
    assert az == pytest.approx(math.pi / 2)  # clockwise from the nose
    assert el == pytest.approx(-math.atan2(100.0, 10.0))  # below the horizontal: negative


@pytest.mark.parametrize("lateral", [0.0, -1.3])
def test_motion_jacobians_match_numerical_differentiation(lateral: float) -> None:
    pose, v, w, dt = np.array([5.0, -3.0, 0.7]), 5.0, 0.2, 0.025
    f, g = motion_jacobians(pose, v, w, dt, lateral)
    np.testing.assert_allclose(f, numeric_jacobian(lambda p: motion(p, v, w, dt, lateral), pose, wrap_rows=(2,)),
                               atol=1e-8)
    np.testing.assert_allclose(g, numeric_jacobian(lambda u: motion(pose, u[0], u[2], dt, u[1]),
                                                   np.array([v, lateral, w]), wrap_rows=(2,)), atol=1e-8)


def test_a_lateral_speed_moves_the_vehicle_to_the_right_of_its_heading() -> None:
    east_heading = np.array([0.0, 0.0, math.pi / 2])
    np.testing.assert_allclose(motion(east_heading, 0.0, 0.0, 2.0, 1.5), [-3.0, 0.0, math.pi / 2], atol=1e-12)


def test_inverse_observation_inverts_and_its_jacobians_match_numerical_differentiation() -> None:
    pose, landmark = np.array([10.0, 20.0, 2.5]), np.array([-5.0, 40.0, -2.0])
    z = observe(pose, DOWN, landmark)
    np.testing.assert_allclose(inverse_observe(pose, DOWN, z), landmark, atol=1e-9)
    gv, gz = inverse_observe_jacobians(pose, z)
    np.testing.assert_allclose(gv, numeric_jacobian(lambda p: inverse_observe(p, DOWN, z), pose), atol=1e-6)
    # the seed's eq. 38 prints d e / d theta with the wrong sign: ours is the derivative
    np.testing.assert_allclose(gz, numeric_jacobian(lambda zz: inverse_observe(pose, DOWN, zz), z), atol=1e-6)


def _filter_with_landmarks(consistency: str = "plain", count: int = 6, seed: int = 1) -> tuple[EkfSlam, np.ndarray]:
    rng = np.random.default_rng(seed)
    cfg = EkfSlamConfig(consistency=consistency)
    slam = EkfSlam(cfg, (0.0, 0.0, 0.3), np.diag([0.2, 0.3, 1e-3]))
    truth = np.column_stack([rng.uniform(-30, 30, count), rng.uniform(-30, 30, count), -rng.uniform(0, 5, count)])
    for i, lm in enumerate(truth):
        for _ in range(8):
            slam.predict(5.0, 0.1, 0.025)
        slam.update({i: observe(slam.x[:3], DOWN, lm)})
    return slam, truth


def test_joseph_update_in_order_n_squared_equals_the_dense_textbook_form() -> None:
    slam, truth = _filter_with_landmarks()
    lid = 3
    z = observe(slam.x[:3], DOWN, truth[lid]) + np.array([0.1, 0.001, -0.001])
    nu, h6, s, idx = slam.innovation(lid, z)
    n = slam.x.size
    h = np.zeros((3, n))
    h[:, idx] = h6
    p0, x0 = slam.P.copy(), slam.x.copy()
    k = p0 @ h.T @ np.linalg.inv(h @ p0 @ h.T + slam.R)
    i_kh = np.eye(n) - k @ h
    dense = i_kh @ p0 @ i_kh.T + k @ slam.R @ k.T
    assert slam.update({lid: z}).used == [lid]
    np.testing.assert_allclose(slam.P, dense, atol=1e-12)
    expected_x = x0 + k @ nu
    np.testing.assert_allclose(slam.x[3:], expected_x[3:], atol=1e-12)
    assert np.array_equal(slam.P, slam.P.T)  # exactly symmetric


def test_augmentation_covariance_is_the_seeds_eq_35_with_the_inverse_model_jacobians() -> None:
    slam, _ = _filter_with_landmarks(count=3)
    p0, pose = slam.P.copy(), slam.x[:3].copy()
    z = np.array([101.0, 0.4, -1.35])
    slam.augment(42, z)
    gv, gz = inverse_observe_jacobians(pose, z)
    n = p0.shape[0]
    p_aug = np.zeros((n + 3, n + 3))  # seed eq. 32
    p_aug[:n, :n] = p0
    p_aug[n:, n:] = slam.R
    jac = np.eye(n + 3)  # seed eq. 36 (its last block is grad g_z)
    jac[n:, :] = 0.0
    jac[n:, :3] = gv
    jac[n:, n:] = gz
    np.testing.assert_allclose(slam.P, jac @ p_aug @ jac.T, atol=1e-12)
    np.testing.assert_allclose(slam.landmark(42)[0], inverse_observe(pose, DOWN, z))


def test_gating_rejects_a_landmark_that_moved_and_counts_it() -> None:
    slam, truth = _filter_with_landmarks(count=4)
    rng = np.random.default_rng(5)
    moved = truth.copy()
    moved[2, :2] += 6.0  # someone carried landmark 2 away
    sig = np.sqrt(np.diag(slam.R))
    for _ in range(10):
        slam.predict(0.0, 0.0, 0.2)
        frame = {i: observe(slam.x[:3], DOWN, moved[i]) + rng.normal(0, 1, 3) * sig for i in range(4)}
        result = slam.update(frame)
        assert 2 not in result.used
    assert slam.rejections[2] >= slam.config.moved_after
    assert 2 in slam.moved and 2 not in slam.landmarks()
    assert all(slam.rejections[i] == 0 for i in (0, 1, 3))


def test_new_landmarks_at_the_nadir_are_not_added() -> None:
    slam = EkfSlam(EkfSlamConfig(), (0.0, 0.0, 0.0), np.eye(3) * 1e-4)
    result = slam.update({7: observe(slam.x, DOWN, np.array([1.0, 0.5, 0.0]))})
    assert result.skipped == [7] and slam.n_landmarks == 0


def test_level_offset_inverts_the_observation_and_its_jacobian_matches_numerical_differentiation() -> None:
    pose, landmark = np.array([3.0, -2.0, 2.2]), np.array([4.0, -0.5, -1.0])
    z = observe(pose, DOWN, landmark)
    np.testing.assert_allclose(level_offset(z), predict_level_offset(pose, DOWN, landmark), atol=1e-9)

    def h(s: np.ndarray) -> np.ndarray:
        return predict_level_offset(s[:3], DOWN, s[3:])

    delta = landmark - np.array([pose[0], pose[1], DOWN])
    np.testing.assert_allclose(level_offset_jacobian(pose[2], delta), numeric_jacobian(h, np.r_[pose, landmark]),
                               atol=1e-7)


def test_level_offset_covariance_matches_sampled_noise_and_is_never_thin_across_the_nadir() -> None:
    sigmas = (0.2, math.radians(0.16), math.radians(0.12))
    rng = np.random.default_rng(3)
    z = observe(np.zeros(3), DOWN, np.array([2.0, 1.0, 0.0]))  # 2.2 m off the nadir from 100 m up
    samples = np.array([level_offset(z + rng.normal(0, 1, 3) * sigmas) for _ in range(20000)])
    cov = level_offset_cov(z, sigmas)
    # along the bearing and down: the first-order propagation is the sampled spread
    radial = np.array([math.cos(z[1]), math.sin(z[1]), 0.0])
    for axis in (radial, np.array([0.0, 0.0, 1.0])):
        assert axis @ cov @ axis == pytest.approx(np.var(samples @ axis), rel=0.05)
    # across it the azimuth alone would give 2.2 m * 0.16 deg = 6 mm; the floor is r * sigma_el
    across = np.array([-math.sin(z[1]), math.cos(z[1]), 0.0])
    assert math.sqrt(across @ cov @ across) == pytest.approx(z[0] * sigmas[2], rel=1e-6)
    assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_a_known_landmark_at_the_nadir_keeps_correcting_the_vehicle_during_a_descent() -> None:
    """A vehicle descending onto a mapped landmark (a landing pad) while its dead reckoning
    says it drifts 0.2 m/s north: the landmark, seen within min_horizontal_m of the nadir all the
    way down, is used in every frame and keeps the position error under a metre (16 m unchecked)."""
    config = EkfSlamConfig()
    rng = np.random.default_rng(11)
    sig = np.array([config.sigma_range_m, math.radians(config.sigma_azimuth_deg),
                    math.radians(config.sigma_elevation_deg)])
    pad = np.array([0.0, 0.0, 0.0])
    slam = EkfSlam(config, (0.0, 0.0, 0.0), np.diag([0.3, 0.3, 1e-4]))
    slam.x[:2] = (0.0, -10.0)
    slam.augment(1, observe(slam.x, DOWN, pad))  # mapped from 10 m west of it
    slam.x[:2] = 0.0
    truth = np.zeros(3)
    used, worst = 0, 0.0
    for k in range(400):  # 80 s at 5 Hz from 100 m to 4 m
        slam.down_m = DOWN + 0.24 * k
        slam.predict(0.2, 0.0, 0.2)  # a drift that is not there
        z = observe(truth, slam.down_m, pad) + rng.normal(0, 1, 3) * sig
        result = slam.update({1: z})
        used += len(result.used)
        worst = max(worst, float(np.linalg.norm(slam.x[:2] - truth[:2])))
    assert used == 400
    assert worst < 1.0


def test_submap_keeps_the_vehicle_and_the_start_landmark_with_their_covariance() -> None:
    slam, _ = _filter_with_landmarks(count=5)
    pose, pv = slam.pose, slam.pose_cov
    lm, pl = slam.landmark(3)
    cross = slam.P[:3, slam.slot[3]:slam.slot[3] + 3].copy()
    slam.start_submap(keep_landmark=3)
    assert slam.ids == [3] and slam.x.size == slam.head + 3
    np.testing.assert_array_equal(slam.pose, pose)
    np.testing.assert_array_equal(slam.pose_cov, pv)
    np.testing.assert_array_equal(slam.landmark(3)[1], pl)
    np.testing.assert_array_equal(slam.P[:3, slam.head:], cross)
    slam.start_submap()
    assert slam.n_landmarks == 0
    np.testing.assert_array_equal(slam.pose_cov, pv)
    slam.augment(3, np.array([101.0, 0.0, -1.4]))  # an id seen again is a new landmark of the new sub-map
    assert slam.n_landmarks == 1


def test_chi2_quantiles_and_nees_band() -> None:
    assert chi2_quantile(0.975, 3) == pytest.approx(9.348, rel=0.01)
    assert chi2_quantile(0.025, 90) == pytest.approx(65.65, rel=0.01)
    lo, hi = nees_band(3, 30)
    assert lo == pytest.approx(65.65 / 30, rel=0.01) and hi == pytest.approx(117.35 / 30, rel=0.01)


def _circle_run(consistency: str, seed: int, seconds: float = 30.0) -> np.ndarray:
    """A vehicle circling over 12 ground landmarks 20 m below with a poorly known initial yaw and
    noisy inputs: the average-NEES regime where the plain EKF-SLAM is known to turn over-confident."""
    cfg = EkfSlamConfig(consistency=consistency, sigma_omega_dps=20.0, sigma_azimuth_deg=3.0,
                        sigma_elevation_deg=3.0, sigma_range_m=1.0, altitude_m=20.0, min_horizontal_m=2.0,
                        gate_chi2=1e9)
    rng = np.random.default_rng(seed)
    lms = np.column_stack([rng.uniform(-30, 30, 12), rng.uniform(-30, 30, 12), np.zeros(12)])
    truth = np.array([0.0, -20.0, 0.0])
    p0 = np.diag([0.1 ** 2, 0.1 ** 2, math.radians(5.0) ** 2])
    slam = EkfSlam(cfg, truth + rng.normal(0, 1, 3) * np.sqrt(np.diag(p0)), p0)
    sig = np.sqrt(np.diag(slam.R))
    dt, v = 0.025, 3.0
    out = []
    for k in range(int(seconds / dt)):
        if k % 8 == 0:
            slam.update({i: observe(truth, cfg.down_m, lm) + rng.normal(0, 1, 3) * sig
                         for i, lm in enumerate(lms) if np.hypot(*(lm[:2] - truth[:2])) < 25})
            out.append(nees(pose_error(truth, slam.x), slam.pose_cov))
        truth = motion(truth, v, v / 20.0, dt)
        slam.predict(v + rng.normal(0, cfg.sigma_v_mps), v / 20.0 + rng.normal(0, math.radians(20.0)), dt)
    return np.array(out)


def test_first_estimates_jacobians_stay_nearer_the_nees_band_than_the_plain_ekf() -> None:
    runs = 12
    lo, hi = nees_band(3, runs)
    plain = np.mean([_circle_run("plain", s) for s in range(runs)], axis=0)
    fej = np.mean([_circle_run("fej", s) for s in range(runs)], axis=0)
    late = slice(len(plain) // 3, None)
    assert np.mean(plain[late]) > hi  # over-confident
    assert np.mean(fej[late]) < np.mean(plain[late]) * 0.75
    assert np.mean(fej[late] <= hi) > np.mean(plain[late] <= hi) + 0.3


# --- planner ----------------------------------------------------------------------------------

BASE = (353.5, 353.5)


def test_planner_heads_for_the_base_and_circles_the_reference_landmark_nearest_it() -> None:
    cfg = RecoveryPlannerConfig()
    planner = RecoveryPlanner(cfg, BASE)
    in_view = {1: (10.0, -5.0), 2: (12.0, 14.0), 3: (-20.0, 0.0)}
    out = planner.target(0.0, (0.0, 0.0, 0.0), in_view, in_view)
    assert planner.heading_to_base == pytest.approx(math.radians(45.0))  # eq. 39, atan2(east, north)
    assert out.kind == "circle" and out.reference == 2
    assert out.target_ne == (12.0, 14.0)
    assert out.radius_m == pytest.approx(0.8 * 100.0 * math.tan(math.radians(20.0)))
    # the carrot lies on the circle, ahead (clockwise seen from above)
    assert math.hypot(out.carrot_ne[0] - 12.0, out.carrot_ne[1] - 14.0) == pytest.approx(out.radius_m)


def _fly_circle(planner: RecoveryPlanner, centre: np.ndarray, radius: float, mapped: dict, t0: float,
                turns: float) -> list:
    outs = []
    for k in range(int(turns * 72) + 1):
        a = math.pi + math.radians(5.0 * k)
        pos = centre + radius * np.array([math.cos(a), math.sin(a)])
        outs.append(planner.target(t0 + k, (pos[0], pos[1], 0.0), {}, mapped))
    return outs


def test_planner_after_the_loops_goes_to_the_mapped_landmark_nearest_the_base_and_starts_a_new_submap() -> None:
    cfg = RecoveryPlannerConfig(loops=2)
    planner = RecoveryPlanner(cfg, BASE)
    mapped = {1: np.array([10.0, 10.0]), 5: np.array([40.0, 45.0]), 6: np.array([60.0, 20.0]), 7: np.array([-30.0, 0.0])}
    planner.target(0.0, (0.0, 0.0, 0.0), {1: mapped[1]}, mapped)
    outs = _fly_circle(planner, mapped[1], cfg.circle_radius_m, mapped, 1.0, 1.5)
    assert all(o.kind == "circle" for o in outs)  # 1.5 of the 2 loops
    outs = _fly_circle(planner, mapped[1], cfg.circle_radius_m, mapped, 200.0, 1.0)
    goto = [o for o in outs if o.kind == "goto"]
    assert goto and goto[0].target_ne == (40.0, 45.0)  # the mapped landmark nearest the base
    out = planner.target(300.0, (40.5, 45.0, 0.0), {5: mapped[5], 6: mapped[6]}, mapped)
    assert out.new_submap and out.keep_landmark == 5
    assert out.kind == "circle" and out.reference == 5  # of those in view, 5 is nearest the base
    assert planner.start_ne is not None and tuple(planner.start_ne) == (40.0, 45.0)


def test_planner_flies_straight_home_when_near_and_lands_at_the_base() -> None:
    cfg = RecoveryPlannerConfig(final_leg_m=50.0, land_radius_m=1.0)
    planner = RecoveryPlanner(cfg, BASE)
    out = planner.target(0.0, (320.0, 330.0, 0.0), {1: (325.0, 330.0)}, {})
    assert out.kind == "goto" and out.carrot_ne == BASE
    out = planner.target(1.0, (353.0, 353.2, 0.0), {}, {})
    assert out.kind == "land"
    assert planner.target(2.0, (0.0, 0.0, 0.0), {1: (1.0, 1.0)}, {}).kind == "land"  # terminal


@pytest.mark.parametrize("on_timeout", ["hold", "land"])
def test_planner_searches_an_expanding_square_then_holds_or_lands(on_timeout: str) -> None:
    cfg = RecoveryPlannerConfig(search_leg_m=20.0, search_time_s=100.0, on_search_timeout=on_timeout, arrive_m=1.0)
    planner = RecoveryPlanner(cfg, BASE)
    out = planner.target(0.0, (0.0, 0.0, 0.0), {}, {})
    assert out.kind == "search"
    corners = [np.array(out.carrot_ne)]
    t = 0.0
    while len(corners) < 5:
        t += 1.0
        out = planner.target(t, (corners[-1][0], corners[-1][1], 0.0), {}, {})
        if not np.allclose(out.carrot_ne, corners[-1]):
            corners.append(np.array(out.carrot_ne))
    legs = [np.linalg.norm(b - a) for a, b in zip([np.zeros(2)] + corners[:-1], corners)]
    np.testing.assert_allclose(legs, [20.0, 20.0, 40.0, 40.0, 60.0])  # widening
    out = planner.target(101.0, (5.0, 5.0, 0.0), {}, {})
    assert out.kind == on_timeout and out.target_ne == (5.0, 5.0)


def test_planner_search_ends_when_a_landmark_comes_into_view() -> None:
    planner = RecoveryPlanner(RecoveryPlannerConfig(), BASE)
    assert planner.target(0.0, (0.0, 0.0, 0.0), {}, {}).kind == "search"
    out = planner.target(5.0, (25.0, 25.0, 0.0), {4: (30.0, 20.0)}, {4: (30.0, 20.0)})
    assert out.kind == "circle" and out.reference == 4


def test_larger_loop_variant_circles_without_a_landmark_towards_the_base() -> None:
    cfg = RecoveryPlannerConfig(variant="larger_loop", larger_loop_factor=2.0)
    planner = RecoveryPlanner(cfg, BASE)
    out = planner.target(0.0, (0.0, 0.0, 0.0), {}, {})
    assert out.kind == "circle" and out.reference is None
    r = 2.0 * 100.0 * math.tan(math.radians(20.0))
    assert out.radius_m == pytest.approx(r)
    np.testing.assert_allclose(out.target_ne, (r / math.sqrt(2), r / math.sqrt(2)))  # the start point is on it


def test_planner_in_view_submap_keeps_the_landmarks_in_view_and_start_keeps_only_the_start() -> None:
    mapped = {1: np.array([10.0, 10.0]), 5: np.array([40.0, 45.0]), 6: np.array([60.0, 20.0])}
    for keep, expected in (("in_view", (6,)), ("start", ())):
        cfg = RecoveryPlannerConfig(loops=1, submap_keep=keep)
        planner = RecoveryPlanner(cfg, BASE)
        planner.target(0.0, (0.0, 0.0, 0.0), {1: mapped[1]}, mapped)
        _fly_circle(planner, mapped[1], cfg.circle_radius_m, mapped, 1.0, 1.2)
        out = planner.target(300.0, (40.5, 45.0, 0.0), {5: mapped[5], 6: mapped[6]}, mapped)
        assert out.new_submap and out.keep_landmark == 5 and out.also_keep == expected


def test_submap_can_keep_further_landmarks_with_their_joint_covariance() -> None:
    slam, _ = _filter_with_landmarks(count=5)
    block = slam.P[np.ix_(range(3), range(3))].copy()
    o2, o4 = slam.slot[2], slam.slot[4]
    joint = slam.P[np.ix_([o2, o2 + 1, o2 + 2, o4, o4 + 1, o4 + 2], [o2, o2 + 1, o2 + 2, o4, o4 + 1, o4 + 2])].copy()
    slam.start_submap(keep_landmark=2, also_keep=(4, 99))  # 99 is not mapped: ignored
    assert slam.ids == [2, 4]
    np.testing.assert_array_equal(slam.pose_cov, block)
    np.testing.assert_array_equal(slam.P[slam.head:, slam.head:], joint)


def test_when_every_landmark_is_refused_the_vehicle_is_lost_not_the_map_and_its_covariance_grows_until_they_pass() -> None:
    slam, truth = _filter_with_landmarks(count=4)
    rng = np.random.default_rng(6)
    sig = np.sqrt(np.diag(slam.R))
    true_pose = slam.x[:3].copy()
    slam.x[:2] += 4.0  # the vehicle's estimate 5.7 m off, its covariance still small
    for _ in range(25):
        frame = {i: observe(true_pose, DOWN, truth[i]) + rng.normal(0, 1, 3) * sig for i in range(4)}
        slam.update(frame)
    assert not slam.moved and slam.inflations >= 1  # no landmark blamed
    assert np.hypot(*(slam.x[:2] - true_pose[:2])) < 1.0  # pulled back onto the map (from 5.7 m)


def test_a_disagreement_inflation_cannot_fix_stays_bounded_and_never_raises() -> None:
    slam, truth = _filter_with_landmarks(count=4)
    rng = np.random.default_rng(7)
    sig = np.sqrt(np.diag(slam.R))
    true_pose = slam.x[:3].copy()
    slam.down_m += 3.0  # a height 3 m off: every range refused, whatever the horizontal position
    for _ in range(400):  # 80 s at 5 Hz
        slam.update({i: observe(true_pose, DOWN, truth[i]) + rng.normal(0, 1, 3) * sig for i in range(4)})
    assert np.all(np.isfinite(slam.P)) and math.sqrt(slam.P[0, 0] + slam.P[1, 1]) < 2.0 * LOST_MAX_M


def test_fixes_with_a_wandering_bias_leave_the_vehicle_no_surer_than_the_bias_allows() -> None:
    """A vehicle hovering at the origin for 10 minutes, fixes at 5 Hz with a 0.5 m Gauss-Markov
    bias (60 s) and 0.5 m white noise, stated as 0.7 m: with the bias states the position NEES over
    the last 5 minutes averages near its 2 degrees of freedom; fused as white noise (no bias
    states) the filter claims centimetres and the NEES is in the hundreds."""
    def mean_nees(bias_sigma: float) -> float:
        slam = EkfSlam(EkfSlamConfig(gnss_bias_sigma_m=bias_sigma), (0.0, 0.0, 0.0), np.diag([0.49, 0.49, 1e-2]))
        rng = np.random.default_rng(2)
        a = math.exp(-0.2 / 60.0)
        bias = rng.normal(0.0, 0.5, 2)
        values = []
        for k in range(3000):
            slam.predict(0.0, 0.0, 0.2)
            bias = a * bias + rng.normal(0.0, 0.5 * math.sqrt(1 - a * a), 2)
            slam.update_position(bias + rng.normal(0.0, 0.5, 2), np.eye(2) * 0.49)
            if k >= 1500:
                values.append(nees(slam.x[:2], slam.P[:2, :2]))
        return float(np.mean(values))

    assert 0.5 < mean_nees(0.5) < 4.0
    assert mean_nees(0.0) > 50.0


def test_a_frame_is_weighed_with_the_noise_its_sensor_states_else_the_configs() -> None:
    slam, truth = _filter_with_landmarks(count=4)
    z = observe(slam.x[:3], DOWN, truth[2]) + np.array([0.5, 0.0, 0.0])
    stated = (2.0, math.radians(0.5), math.radians(0.4))
    _, h, s_stated, idx = slam.innovation(2, z, stated)
    np.testing.assert_allclose(s_stated, h @ slam.P[np.ix_(idx, idx)] @ h.T + np.diag(np.square(stated)))
    _, _, s_config, _ = slam.innovation(2, z)
    np.testing.assert_allclose(s_config, h @ slam.P[np.ix_(idx, idx)] @ h.T + slam.R)
    for unusable in ((0.0, 0.0, 0.0), (float("nan"), 1.0, 1.0)):  # an empty marker frame states zeros
        np.testing.assert_allclose(slam.innovation(2, z, unusable)[2], s_config)
    noisy, by_id, exact = (_filter_with_landmarks(count=4)[0] for _ in range(3))
    noisy.update({2: z}, stated)
    by_id.update({2: z}, {2: stated, 3: (1.0, 1.0, 1.0)})  # a frame stating each landmark's own
    exact.update({2: z})
    np.testing.assert_array_equal(by_id.x, noisy.x)
    moved = np.linalg.norm(noisy.x[:2] - slam.x[:2]), np.linalg.norm(exact.x[:2] - slam.x[:2])
    assert 0.0 < moved[0] < 0.5 * moved[1]
