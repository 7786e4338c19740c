"""GNSS pseudo-attitude (companion/nav/gnss_flow/pseudo_attitude.py): the Doppler acceleration
filter, pseudo roll / pitch / yaw, pseudo rates and body rates, the refusals and the
coordination check. Trajectories are analytic, velocity NED m/s, fixes with 0.05 m/s Doppler
noise at about 5 Hz."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.frames import GRAVITY_MPS2, rotation_from_euler, wrap_pi
from companion.nav.gnss_flow.pseudo_attitude import (
    DopplerAccelerationFilter,
    KinematicEstimate,
    PseudoAttitude,
    PseudoAttitudeLimits,
    body_rates_from_euler_rates,
    coordination_check,
    euler_rates_from_body_rates,
    pseudo_attitude,
    pseudo_attitude_refusal,
    pseudo_euler_rates,
)

SPEED = 25.0  # m/s
BANK = math.radians(30.0)
TURN_RATE = GRAVITY_MPS2 * math.tan(BANK) / SPEED  # rad/s, coordinated level turn
DOPPLER_SIGMA = 0.05  # m/s


def turn_velocity(t: float) -> np.ndarray:
    """NED velocity (m/s) of a level right turn (course increasing) at time t (s)."""
    return SPEED * np.array([math.cos(TURN_RATE * t), math.sin(TURN_RATE * t), 0.0])


def fix_times(rng: np.random.Generator, duration_s: float) -> list[float]:
    """Capture times (s) at 5 Hz with +/-20 ms jitter (irregular intervals)."""
    times, t = [], 0.0
    while t < duration_s:
        times.append(t)
        t += 0.2 + rng.uniform(-0.02, 0.02)
    return times


def fly(velocity, seed: int, duration_s: float = 30.0, jerk_psd: float = 0.5):
    """Feed noisy fixes of ``velocity(t)`` to a filter; yields (t, filter) after each fix."""
    rng = np.random.default_rng(seed)
    filt = DopplerAccelerationFilter(jerk_psd=jerk_psd)
    for t in fix_times(rng, duration_s):
        assert filt.update(t, velocity(t) + rng.normal(0.0, DOPPLER_SIGMA, 3), DOPPLER_SIGMA)
        yield t, filt


def settled_attitudes(velocity, seed: int, settle_s: float = 10.0) -> list[PseudoAttitude]:
    out = []
    for t, filt in fly(velocity, seed):
        if t >= settle_s:
            attitude = pseudo_attitude(filt.estimate(t))
            assert attitude is not None
            out.append(attitude)
    return out


def test_steady_coordinated_turn_gives_its_bank_as_pseudo_roll_and_course_as_yaw():
    roll_err, yaw_err = [], []
    for seed in range(5):
        for att in settled_attitudes(turn_velocity, seed):
            roll_err.append(att.roll - BANK)
            yaw_err.append(wrap_pi(att.yaw - TURN_RATE * att.time_s))
    roll_err_deg, yaw_err_deg = np.degrees(roll_err), np.degrees(yaw_err)
    # measured (5 seeds x 100 fixes): mean -0.01 deg, RMS 0.86 deg, max 3.4 deg; yaw max 0.33 deg
    assert abs(roll_err_deg.mean()) < 0.2
    assert np.sqrt(np.mean(roll_err_deg**2)) < 1.2
    assert np.abs(roll_err_deg).max() < 4.0
    assert np.abs(yaw_err_deg).max() < 0.5


def test_pseudo_roll_covariance_covers_its_error_in_a_turn():
    normalized = []
    for seed in range(5):
        for att in settled_attitudes(turn_velocity, seed):
            normalized.append((att.roll - BANK) ** 2 / att.covariance[0, 0])
            assert np.all(np.linalg.eigvalsh(att.covariance) >= 0)
    # the white-jerk model is conservative for a steady turn: measured 0.3, never over-confident
    assert 0.1 < np.mean(normalized) < 1.5


def test_steady_climb_gives_its_flight_path_angle_as_pseudo_pitch():
    climb = np.array([20.0, 10.0, -3.0])  # m/s NED, 3 m/s up
    gamma = math.atan2(3.0, math.hypot(20.0, 10.0))
    atts = settled_attitudes(lambda t: climb, seed=1)
    pitch_err = np.degrees([a.pitch - gamma for a in atts])
    assert np.abs(pitch_err).max() < 0.5
    assert np.abs(np.degrees([a.roll for a in atts])).max() < 2.0
    assert np.abs(np.degrees([wrap_pi(a.yaw - math.atan2(10.0, 20.0)) for a in atts])).max() < 0.5


def test_straight_and_level_gives_zero_roll_and_pitch():
    atts = settled_attitudes(lambda t: np.array([0.0, -SPEED, 0.0]), seed=2)  # flying west
    roll_deg = np.degrees([a.roll for a in atts])
    assert abs(roll_deg.mean()) < 0.3 and np.abs(roll_deg).max() < 3.0
    # measured: pitch max 0.31 deg (0.05 m/s vertical noise over 25 m/s is 0.11 deg per fix)
    assert np.abs(np.degrees([a.pitch for a in atts])).max() < 0.5
    assert np.abs(np.degrees([wrap_pi(a.yaw + math.pi / 2) for a in atts])).max() < 0.5


def test_roll_sign_follows_body_frd_left_turn_negative():
    left = settled_attitudes(lambda t: turn_velocity(-t), seed=3)
    assert np.degrees(np.mean([a.roll for a in left])) == pytest.approx(-30.0, abs=0.5)


def test_pseudo_roll_follows_a_roll_in_with_a_bounded_lag():
    # bank 0 -> 30 deg at 30 deg/s from t = 10 s, course integrated at 1 ms
    step, course, samples = 0.001, 0.0, []
    for i in range(20_000):
        t = i * step
        bank = BANK * min(max(t - 10.0, 0.0), 1.0)
        if i % 200 == 0:
            samples.append((t, SPEED * np.array([math.cos(course), math.sin(course), 0.0]), bank))
        course += GRAVITY_MPS2 * math.tan(bank) / SPEED * step
    rng = np.random.default_rng(5)
    filt = DopplerAccelerationFilter()
    during, after = [], []
    for t, velocity, bank in samples:
        filt.update(t, velocity + rng.normal(0.0, DOPPLER_SIGMA, 3), DOPPLER_SIGMA)
        error = math.degrees(pseudo_attitude(filt.estimate(t)).roll - bank)
        (during if 10.0 <= t <= 12.0 else after if t >= 13.0 else []).append(error)
    # measured (seed 5): the white-jerk filter lags, worst ~7.5 deg while rolling at 30 deg/s
    assert np.abs(during).max() < 10.0
    assert np.abs(after).max() < 3.0


@pytest.mark.parametrize("jerk_psd, max_error", [(0.5, 0.6), (0.01, 0.15)])
def test_filter_acceleration_converges_under_constant_acceleration(jerk_psd, max_error):
    accel = np.array([1.5, -0.8, 0.3])  # m/s^2 NED
    v0 = np.array([20.0, 5.0, -1.0])
    errors, normalized = [], []
    for seed in range(10):
        for t, filt in fly(lambda t: v0 + accel * t, seed, duration_s=20.0, jerk_psd=jerk_psd):
            last = filt.estimate(t)
        assert np.abs(last.velocity_ned - (v0 + accel * t)).max() < 0.15
        errors.append(np.abs(last.acceleration_ned - accel))
        normalized.append(errors[-1] / np.sqrt(np.diag(last.covariance)[3:]))
    # the prior is 5 m/s^2; measured worst axis over 10 seeds: 0.42 m/s^2 at the default
    # 0.5 m^2/s^5 (its sigma 0.30), 0.08 m/s^2 at 0.01 (sigma 0.076); never beyond 3 sigma
    assert np.max(errors) < max_error
    assert np.max(normalized) < 3.0


def simulate_white_jerk(filt: DopplerAccelerationFilter, rng: np.random.Generator, steps: int,
                        predict_s: float) -> tuple[KinematicEstimate, np.ndarray]:
    """Truth from the filter's own model (white jerk of its PSD, initial acceleration of its
    prior); returns the estimate ``predict_s`` after the last fix and the true state there."""
    q = filt.jerk_psd
    x = np.column_stack([rng.normal(0.0, 10.0, 3),
                         rng.normal(0.0, filt.initial_acceleration_sigma_mps2, 3)])
    t = 0.0

    def propagate(x: np.ndarray, dt: float) -> np.ndarray:
        cov = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        noise = rng.multivariate_normal(np.zeros(2), cov, 3)
        return np.column_stack([x[:, 0] + dt * x[:, 1], x[:, 1]]) + noise

    filt.update(t, x[:, 0] + rng.normal(0.0, DOPPLER_SIGMA, 3), DOPPLER_SIGMA)
    for _ in range(steps - 1):
        dt = 0.2 + rng.uniform(-0.05, 0.05)
        x = propagate(x, dt)
        t += dt
        filt.update(t, x[:, 0] + rng.normal(0.0, DOPPLER_SIGMA, 3), DOPPLER_SIGMA)
    if predict_s > 0:
        x = propagate(x, predict_s)
    return filt.estimate(t + predict_s), x


@pytest.mark.parametrize("predict_s", [0.0, 0.4])
def test_filter_covariance_is_consistent_nees_near_its_dimension(predict_s):
    runs = 1000
    nees = []
    for seed in range(runs):
        rng = np.random.default_rng(100 + seed)
        est, truth = simulate_white_jerk(DopplerAccelerationFilter(), rng, 25, predict_s)
        err = np.concatenate([est.velocity_ned - truth[:, 0], est.acceleration_ned - truth[:, 1]])
        nees.append(err @ np.linalg.solve(est.covariance, err))
    # 6 states: a consistent filter's mean of 1000 NEES lies in 6 +/- 2.576 sqrt(12 / 1000) =
    # [5.72, 6.28] 99 % of the time (chi-square 6000 / 1000)
    assert 6.0 - 2.576 * math.sqrt(12 / runs) < np.mean(nees) < 6.0 + 2.576 * math.sqrt(12 / runs)


def test_latency_querying_at_now_predicts_the_fix_forward():
    latency = 0.2  # s: each fix reaches us this long after its capture
    now_err, capture_err, yaw_now_err, yaw_capture_err = [], [], [], []
    for t, filt in fly(turn_velocity, seed=4):
        if t < 10.0:
            continue
        now = t + latency
        at_now, at_capture = filt.estimate(now), filt.estimate(t)
        now_err.append(np.linalg.norm(at_now.velocity_ned - turn_velocity(now)))
        capture_err.append(np.linalg.norm(at_capture.velocity_ned - turn_velocity(now)))
        yaw_now_err.append(wrap_pi(pseudo_attitude(at_now).yaw - TURN_RATE * now))
        yaw_capture_err.append(wrap_pi(pseudo_attitude(at_capture).yaw - TURN_RATE * now))
        assert np.all(np.diag(at_now.covariance) > np.diag(at_capture.covariance))
    # the capture-time estimate is a 0.2 s old turn: 25 m/s x 0.226 rad/s x 0.2 s = 1.13 m/s off
    assert np.mean(capture_err) > 1.0
    assert np.mean(now_err) < 0.25  # measured 0.14 m/s: the filter's own noise
    assert abs(np.degrees(np.mean(yaw_capture_err)) + math.degrees(TURN_RATE * latency)) < 0.2
    # measured: now-yaw mean 0.0 deg, max 0.52 deg (velocity noise over 25 m/s)
    assert abs(np.degrees(np.mean(yaw_now_err))) < 0.1
    assert np.abs(np.degrees(yaw_now_err)).max() < 1.0


def test_a_gap_restarts_the_filter_and_stale_queries_return_none():
    filt = DopplerAccelerationFilter(max_gap_s=1.5)
    for i in range(20):
        filt.update(0.2 * i, np.array([20.0 + 0.4 * i, 0.0, 0.0]), DOPPLER_SIGMA)  # 2 m/s^2 north
    last = filt.last_fix_time_s
    assert filt.estimate(last).acceleration_ned[0] == pytest.approx(2.0, abs=0.1)
    assert filt.estimate(last + 1.4) is not None
    assert filt.estimate(last + 1.6) is None
    assert filt.update(last + 2.0, np.array([30.0, 0.0, 0.0]), DOPPLER_SIGMA)
    restarted = filt.estimate(last + 2.0)
    assert np.all(restarted.acceleration_ned == 0.0)
    assert restarted.covariance[3, 3] == pytest.approx(filt.initial_acceleration_sigma_mps2**2)
    assert restarted.velocity_ned[0] == 30.0


def test_a_fix_not_later_than_the_last_is_refused_and_queries_before_it_raise():
    filt = DopplerAccelerationFilter()
    assert filt.estimate(0.0) is None
    assert filt.update(1.0, np.array([20.0, 0.0, 0.0]), DOPPLER_SIGMA)
    assert not filt.update(1.0, np.array([99.0, 0.0, 0.0]), DOPPLER_SIGMA)
    assert not filt.update(0.8, np.array([99.0, 0.0, 0.0]), DOPPLER_SIGMA)
    assert filt.estimate(1.0).velocity_ned[0] == 20.0
    with pytest.raises(ValueError):
        filt.estimate(0.9)


def estimate_of(velocity, acceleration=(0.0, 0.0, 0.0)) -> KinematicEstimate:
    return KinematicEstimate(0.0, np.asarray(velocity, dtype=float),
                             np.asarray(acceleration, dtype=float), np.eye(6) * 0.01)


@pytest.mark.parametrize(
    "velocity, acceleration, reason",
    [
        ((3.0, 2.0, 0.0), (0.0, 0.0, 0.0), "ground speed"),
        ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), "ground speed"),
        ((6.0, 0.0, -30.0), (0.0, 0.0, 0.0), "vertical"),
        ((25.0, 0.0, 0.0), (0.0, 0.0, GRAVITY_MPS2), "normal specific force"),  # zero-g arc
        ((25.0, float("nan"), 0.0), (0.0, 0.0, 0.0), "non-finite"),
    ],
)
def test_pseudo_attitude_is_refused_where_undefined_never_nan(velocity, acceleration, reason):
    assert reason in pseudo_attitude_refusal(np.array(velocity), np.array(acceleration))
    assert pseudo_attitude(estimate_of(velocity, acceleration)) is None


def test_assumptions_hold_at_cruise_and_the_minimum_speed_is_configurable():
    assert pseudo_attitude_refusal(np.array([25.0, 0.0, -2.0]), np.zeros(3)) is None
    slow = np.array([4.0, 0.0, 0.0])
    assert pseudo_attitude_refusal(slow, np.zeros(3)) is not None
    lenient = PseudoAttitudeLimits(min_ground_speed_mps=3.0)
    assert pseudo_attitude_refusal(slow, np.zeros(3), lenient) is None


def test_pseudo_roll_beyond_90_degrees_keeps_its_sign():
    # inverted-ish: lift pointing right and down (specific force right and +D)
    att = pseudo_attitude(estimate_of((25.0, 0.0, 0.0), (0.0, 15.0, 2 * GRAVITY_MPS2)))
    expected = 180.0 - math.degrees(math.atan2(15.0, GRAVITY_MPS2))
    assert math.degrees(att.roll) == pytest.approx(expected, abs=1e-6)


def test_pseudo_attitude_frame_has_x_along_velocity_and_lift_along_minus_z():
    rng = np.random.default_rng(6)
    checked = 0
    for _ in range(50):
        velocity = rng.normal(0.0, 20.0, 3)
        acceleration = rng.normal(0.0, 5.0, 3)
        att = pseudo_attitude(estimate_of(velocity, acceleration))
        if att is None:
            continue
        frame = rotation_from_euler(att.roll, att.pitch, att.yaw)  # pseudo body -> NED
        assert np.allclose(frame[:, 0], velocity / np.linalg.norm(velocity), atol=1e-9)
        specific_force = acceleration - np.array([0.0, 0.0, GRAVITY_MPS2])
        normal = specific_force - (specific_force @ frame[:, 0]) * frame[:, 0]
        assert np.allclose(-frame[:, 2], normal / np.linalg.norm(normal), atol=1e-9)
        checked += 1
    assert checked > 30


def test_body_rates_in_a_steady_turn_are_zero_w_sin_bank_w_cos_bank():
    rates = []
    for seed in range(3):
        atts = settled_attitudes(turn_velocity, seed)
        for earlier, later in zip(atts, atts[1:]):
            mid_roll, mid_pitch = 0.5 * (earlier.roll + later.roll), 0.5 * (earlier.pitch + later.pitch)
            rates.append(body_rates_from_euler_rates(mid_roll, mid_pitch, pseudo_euler_rates(earlier, later)))
    rates = np.array(rates)
    expected = np.array([0.0, TURN_RATE * math.sin(BANK), TURN_RATE * math.cos(BANK)])
    # measured mean error 0.0011 rad/s (p), < 0.0001 (q, r); one 0.2 s difference: p (from the
    # roll difference) std 0.11 rad/s, q and r within 0.03 rad/s
    assert np.abs(rates.mean(axis=0) - expected).max() < 0.005
    assert np.abs(rates[:, 1:] - expected[1:]).max() < 0.05


def test_body_rates_match_the_rotation_of_the_attitude():
    roll, pitch, yaw = 0.4, -0.2, 1.0
    euler_rates = np.array([0.05, -0.03, 0.2])
    dt = 1e-6
    r0 = rotation_from_euler(roll, pitch, yaw)
    r1 = rotation_from_euler(*(np.array([roll, pitch, yaw]) + euler_rates * dt))
    skew = r0.T @ (r1 - r0) / dt  # R' = R [w]x with w in body FRD
    body = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
    assert np.allclose(body_rates_from_euler_rates(roll, pitch, euler_rates), body, atol=1e-5)
    assert np.allclose(euler_rates_from_body_rates(roll, pitch, body), euler_rates, atol=1e-5)  # and back


def test_coordination_check_accepts_a_coordinated_turn_and_flags_a_skid():
    f_ned = TURN_RATE * SPEED * np.array([0.0, 1.0, 0.0]) - np.array([0.0, 0.0, GRAVITY_MPS2])
    coordinated_body = rotation_from_euler(BANK, 0.0, 0.0).T @ f_ned
    ok, lateral = coordination_check(coordinated_body)
    assert ok and abs(lateral) < 1e-9
    skidding_body = rotation_from_euler(BANK - math.radians(5.0), 0.0, 0.0).T @ f_ned  # 5 deg under-banked
    ok, lateral = coordination_check(skidding_body)
    assert not ok and math.degrees(lateral) == pytest.approx(5.0, abs=1e-6)
