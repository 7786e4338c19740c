"""FusionFilter against synthetic truth: a 3-D figure-eight at up to 1 m/s with a noisy, biased
IMU and 10 Hz lidar-like fixes (1 cm noise) that arrive 30 ms after capture."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest

from companion.frames import GRAVITY_MPS2, wrap_pi
from companion.health import State
from companion.nav.fusion import FusedState, FusionConfig, FusionFilter
from companion.nav.fusion_io import ROLL_PITCH_VARIANCE_RAD2, to_pose_estimate

IMU_DT = 0.02  # 50 Hz
FIX_PERIOD = 0.1  # 10 Hz
DELAY = 0.03  # s from capture to delivery
FIX_STD = 0.01  # m (and rad for yaw)
ACCEL_NOISE = 0.05  # m/s^2 per sample
ATTITUDE_NOISE = 0.002  # rad
BIAS_BODY = np.array([0.1, -0.1, 0.1])  # m/s^2
COMPASS_OFFSET = 0.4  # rad between the autopilot's yaw and the map heading
OMEGA, AMPLITUDE = 0.45, 1.5  # figure-eight: peak speed 0.97 m/s, peak acceleration 0.6 m/s^2


def truth(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Position (m), velocity (m/s), acceleration (m/s^2) in NED and map heading (rad) at t."""
    w, a = OMEGA, AMPLITUDE
    s1, c1, s2, c2 = math.sin(w * t), math.cos(w * t), math.sin(2 * w * t), math.cos(2 * w * t)
    p = np.array([a * s1, a / 2 * s2, -1.5 + 0.3 * s1])
    v = np.array([a * w * c1, a * w * c2, 0.3 * w * c1])
    acc = np.array([-a * w * w * s1, -2 * a * w * w * s2, -0.3 * w * w * s1])
    return p, v, acc, wrap_pi(0.6 + 0.8 * math.sin(0.3 * t))


def thrust_attitude(accel_ned: np.ndarray, yaw: float) -> tuple[np.ndarray, float, float]:
    """Body->NED rotation of a multirotor whose thrust (body -z) produces ``accel_ned``."""
    f = accel_ned - np.array([0.0, 0.0, GRAVITY_MPS2])
    zb = -f / np.linalg.norm(f)
    yb = np.cross(zb, [math.cos(yaw), math.sin(yaw), 0.0])
    yb /= np.linalg.norm(yb)
    R = np.column_stack([np.cross(yb, zb), yb, zb])
    return R, math.atan2(R[2, 1], R[2, 2]), -math.asin(R[2, 0])


@dataclass
class Fix:
    t_deliver: float
    kind: str  # "xy", "height", "yaw"
    t_capture: float
    value: np.ndarray | float
    error: np.ndarray | float  # value - truth


@dataclass
class Run:
    filter: FusionFilter
    t: list[float] = field(default_factory=list)
    states: list[FusedState] = field(default_factory=list)
    position_error: list[np.ndarray] = field(default_factory=list)
    velocity_error: list[np.ndarray] = field(default_factory=list)
    yaw_error: list[float] = field(default_factory=list)
    held_fix_error: list[np.ndarray] = field(default_factory=list)  # newest raw fix used as "now"
    fix_errors: dict[str, list] = field(default_factory=lambda: {"xy": [], "height": [], "yaw": []})

    def rms(self, name: str, after: float = 10.0) -> np.ndarray:
        values = np.array([e for t, e in zip(self.t, getattr(self, name)) if t >= after])
        return np.sqrt(np.mean(np.square(values), axis=0))


def make_fixes(duration: float, rng: np.random.Generator, gap: tuple[float, float] | None,
               outlier_at: float | None) -> list[Fix]:
    """Planar fixes (x, y, yaw) and height fixes at 10 Hz, off the IMU grid, sorted by delivery;
    plus a 1 m outlier captured at ``outlier_at``."""
    fixes = []
    for n in range(int(duration / FIX_PERIOD)):
        for kind, tc in (("xy", 0.007 + n * FIX_PERIOD), ("yaw", 0.007 + n * FIX_PERIOD),
                         ("height", 0.053 + n * FIX_PERIOD)):
            if gap is not None and gap[0] <= tc < gap[1]:
                continue
            p, _, _, yaw = truth(tc)
            if kind == "xy":
                error = rng.normal(0.0, FIX_STD, 2)
                value = p[0:2] + error
            elif kind == "yaw":
                error = rng.normal(0.0, FIX_STD)
                value = wrap_pi(yaw + error)
            else:
                error = rng.normal(0.0, FIX_STD)
                value = -p[2] + error
            fixes.append(Fix(tc + DELAY, kind, tc, value, error))
    if outlier_at is not None:  # one extra planar fix 1 m off
        fixes.append(Fix(outlier_at + DELAY, "xy", outlier_at, truth(outlier_at)[0][0:2] + [1.0, 0.0],
                         np.array([1.0, 0.0])))
    fixes.sort(key=lambda f: f.t_deliver)
    return fixes


def deliver(f: FusionFilter, fix: Fix, t_capture: float) -> bool:
    if fix.kind == "xy":
        return f.correct_position(t_capture, fix.value, np.eye(2) * FIX_STD ** 2)
    if fix.kind == "yaw":
        return f.correct_yaw(t_capture, fix.value, FIX_STD ** 2)
    return f.correct_height(t_capture, fix.value, FIX_STD ** 2)


def simulate(duration: float = 60.0, *, compensate: bool = True, seed: int = 1,
             gap: tuple[float, float] | None = None, outlier_at: float | None = None,
             config: FusionConfig | None = None) -> Run:
    """Fly the figure-eight; each 50 Hz step: IMU sample, then the fixes due, then the output.

    ``compensate=False`` stamps each fix with its delivery time (the delay ignored).
    """
    rng = np.random.default_rng(seed)
    fixes = make_fixes(duration, rng, gap, outlier_at)
    run = Run(FusionFilter(config))
    f, i, held = run.filter, 0, None
    for k in range(1, int(duration / IMU_DT)):
        t = k * IMU_DT
        p, v, acc, yaw = truth(t)
        R, roll, pitch = thrust_attitude(acc, yaw)
        specific_force = R.T @ (acc - [0.0, 0.0, GRAVITY_MPS2]) + BIAS_BODY + rng.normal(0.0, ACCEL_NOISE, 3)
        attitude = (roll + rng.normal(0.0, ATTITUDE_NOISE), pitch + rng.normal(0.0, ATTITUDE_NOISE),
                    wrap_pi(yaw + COMPASS_OFFSET + rng.normal(0.0, ATTITUDE_NOISE)))
        assert f.predict(t, specific_force, attitude)
        while i < len(fixes) and fixes[i].t_deliver <= t + 1e-9:
            fix = fixes[i]
            i += 1
            deliver(f, fix, fix.t_capture if compensate else t)
            if fix.t_capture != outlier_at:
                run.fix_errors[fix.kind].append(fix.error)
            if fix.kind == "xy":
                held = fix.value
        state = f.state(t)
        run.t.append(t)
        run.states.append(state)
        run.position_error.append(state.position_ned - p)
        run.velocity_error.append(state.velocity_ned - v)
        run.yaw_error.append(wrap_pi(state.yaw - yaw))
        run.held_fix_error.append(np.zeros(2) if held is None else held - p[0:2])
    return run


@pytest.fixture(scope="module")
def figure_eight() -> Run:
    return simulate()


def test_fused_position_beats_the_raw_fixes(figure_eight: Run) -> None:
    run = figure_eight
    assert all(s.healthy for t, s in zip(run.t, run.states) if t > 1.0)
    position = run.rms("position_error")
    raw = np.sqrt(np.mean(np.square(run.fix_errors["xy"]), axis=0))
    raw_height = math.sqrt(np.mean(np.square(run.fix_errors["height"])))
    assert np.all(position < 0.02)
    assert float(np.sqrt(np.sum(position ** 2))) < 0.02  # 3-D RMS
    # Lower than the fixes' own noise at capture, and far below the newest fix held until the next.
    assert np.all(position[0:2] < raw) and position[2] < raw_height
    assert np.all(position[0:2] < 0.3 * run.rms("held_fix_error"))
    assert np.all(run.rms("velocity_error") < 0.03)
    assert run.rms("yaw_error") < 0.01  # rad; the autopilot's yaw is 0.4 rad off the map


def test_delay_compensation_clearly_beats_ignoring_the_delay(figure_eight: Run) -> None:
    ignored = simulate(compensate=False)
    compensated_3d = np.linalg.norm(figure_eight.rms("position_error"))
    ignored_3d = np.linalg.norm(ignored.rms("position_error"))
    assert compensated_3d < 0.5 * ignored_3d, (compensated_3d, ignored_3d)


def test_accelerometer_bias_is_learned(figure_eight: Run) -> None:
    final = figure_eight.states[-1]
    assert np.all(np.abs(final.accel_bias_body - BIAS_BODY) < 0.02), final.accel_bias_body
    stats = figure_eight.filter.stats
    assert stats.fixes_stale == stats.fixes_invalid == stats.imu_rejected_nonfinite == 0


def _imu(f: FusionFilter, t: float, accel: tuple[float, float, float] = (0.0, 0.0, -GRAVITY_MPS2)) -> None:
    assert f.predict(t, np.array(accel), (0.0, 0.0, 0.0))


def _hovering_filter(t_end: float = 1.0) -> FusionFilter:
    """Initialised at (0, 0, -1), yaw 0, with fixes every 0.1 s up to ``t_end``."""
    f = FusionFilter()
    t = 0.0
    for k in range(1, int(round(t_end / IMU_DT)) + 1):
        t = k * IMU_DT
        _imu(f, t)
        if k % 5 == 0:
            assert f.correct_position(t - 0.01, [0.0, 0.0], np.eye(2) * 1e-4)
            assert f.correct_height(t - 0.01, 1.0, 1e-4)
            assert f.correct_yaw(t - 0.01, 0.0, 1e-4)
    return f


def _same(a: FusedState, b: FusedState) -> bool:
    return (np.allclose(a.position_ned, b.position_ned, atol=1e-12, rtol=0)
            and np.allclose(a.velocity_ned, b.velocity_ned, atol=1e-12, rtol=0)
            and np.allclose(a.position_covariance, b.position_covariance, atol=1e-15, rtol=1e-9)
            and abs(a.yaw - b.yaw) < 1e-12)


def test_late_and_out_of_order_fixes_are_re_propagated_exactly() -> None:
    """A fix applied 30 ms late (or after a newer one) equals the same fix applied on time."""
    rng = np.random.default_rng(3)
    accel = rng.normal(0.0, 0.3, (40, 3)) + [0.0, 0.0, -GRAVITY_MPS2]
    fixes = [(1.0 + 0.1 * n + 0.007, rng.normal(0.0, 0.01, 2), rng.normal(0.0, 0.01)) for n in range(6)]
    on_time, late, shuffled = _hovering_filter(), _hovering_filter(), _hovering_filter()
    late_order = [(f[0] + DELAY, f) for f in fixes]
    shuffled_order = [(fixes[n + 1 if n % 2 == 0 else n - 1][0] + 0.1 + DELAY,  # pairs swapped
                       fixes[n]) for n in range(6)]
    for k in range(1, 40):
        t = 1.0 + k * IMU_DT
        for t_capture, xy, yaw in fixes:  # on time: known before the IMU passes the capture time
            if t - IMU_DT < t_capture <= t:
                assert on_time.correct_position(t_capture, xy, np.eye(2) * 1e-4)
                assert on_time.correct_yaw(t_capture, yaw, 1e-4)
        for f in (on_time, late, shuffled):
            _imu(f, t, tuple(accel[k]))
        for f, order in ((late, late_order), (shuffled, shuffled_order)):
            for due, (t_capture, xy, yaw) in order:
                if t - IMU_DT < due <= t:
                    assert f.correct_position(t_capture, xy, np.eye(2) * 1e-4)
                    assert f.correct_yaw(t_capture, yaw, 1e-4)
    t = 1.0 + 39 * IMU_DT
    assert _same(on_time.state(t), late.state(t))
    assert _same(on_time.state(t), shuffled.state(t))
    assert on_time.stats.fixes_accepted == late.stats.fixes_accepted == shuffled.stats.fixes_accepted


@pytest.mark.parametrize("position_error_m", [0.0, 1.0])  # 1 m: the position is gated out, the yaw is not
def test_one_pose_correction_equals_a_position_then_a_yaw_correction(position_error_m: float) -> None:
    """correct_pose re-propagates once; the state and counters are those of the two calls."""
    rng = np.random.default_rng(5)
    accel = rng.normal(0.0, 0.3, (30, 3)) + [0.0, 0.0, -GRAVITY_MPS2]
    two_calls, one_call = _hovering_filter(), _hovering_filter()
    for k in range(1, 30):
        t = 1.0 + k * IMU_DT
        for f in (two_calls, one_call):
            _imu(f, t, tuple(accel[k]))
        if k % 2 == 0:  # 40 ms late, 3 stored steps to re-run
            t_capture, xy, yaw = t - 0.04, rng.normal(0.0, 0.01, 2) + position_error_m, rng.normal(0.0, 0.01)
            accepted = two_calls.correct_position(t_capture, xy, np.eye(2) * 1e-4)
            accepted &= two_calls.correct_yaw(t_capture, yaw, 1e-4)
            assert one_call.correct_pose(t_capture, xy, np.eye(2) * 1e-4, yaw, 1e-4) == accepted
    t = 1.0 + 29 * IMU_DT
    assert _same(two_calls.state(t), one_call.state(t))
    assert two_calls.stats == one_call.stats
    assert one_call.stats.fixes_gated["position"] == (14 if position_error_m else 0)
    assert one_call.stats.fixes_accepted["yaw"] > 14


def test_gate_rejects_a_one_metre_outlier_and_counts_it(figure_eight: Run) -> None:
    with_outlier = simulate(20.0, outlier_at=15.03)
    clean = simulate(20.0)
    gated = with_outlier.filter.stats.fixes_gated["position"] - clean.filter.stats.fixes_gated["position"]
    assert gated == 1
    # Rejected before it touched anything: the run is identical to the clean one.
    assert all(_same(a, b) for a, b in zip(with_outlier.states, clean.states))


def test_fix_older_than_the_buffer_is_rejected_and_counted() -> None:
    f = _hovering_filter()
    before = f.state(1.0)
    assert not f.correct_position(1.0 - 0.6, [5.0, 5.0], np.eye(2) * 1e-4)
    assert not f.correct_height(1.0 - 0.6, 3.0, 1e-4)
    assert f.stats.fixes_stale == 2
    assert _same(before, f.state(1.0))
    assert f.correct_position(1.0 - 0.45, [0.0, 0.0], np.eye(2) * 1e-4)  # inside the buffer: used


def test_health_ok_degraded_lost_and_back() -> None:
    f = FusionFilter()
    assert not f.state(0.0).healthy
    assert "not initialised" in f.state(0.0).reason
    run = simulate(8.0, gap=(3.0, 5.0))
    by_time = dict(zip(run.t, run.states))
    last_capture = 2.953  # newest fix (a height fix) before the gap; the newest position fix is 2.907
    def at(t: float) -> FusedState:
        return by_time[min(by_time, key=lambda s: abs(s - t))]
    assert at(3.1).status == State.OK and at(3.1).healthy
    degraded = at(2.907 + 0.34)
    assert degraded.status == State.DEGRADED and degraded.healthy
    assert "no position fix" in degraded.reason
    lost = at(last_capture + 1.06)
    assert lost.status == State.LOST and not lost.healthy
    assert at(4.9).status == State.LOST
    assert at(5.3).status == State.OK and at(5.3).healthy  # fixes are back
    for state in (at(3.1), degraded, lost):  # the daemon's STATUSTEXT says "<component> <state>: <reason>"
        text = f"companion: nav:fusion {state.status.label}: {state.reason}"
        assert text.count(state.status.label) == 1, text
    assert np.all(run.rms("position_error", after=5.5) < 0.02)
    with pytest.raises(ValueError):
        to_pose_estimate(lost, 0.0, 0.0)


def test_a_fix_measuring_one_direction_leaves_the_other_to_grow_until_the_estimate_is_withdrawn() -> None:
    """Corridor fixes (cross-track east measured, the along-track north axis not): repeating the
    filter's own north position with a large variance would shrink the north variance at every
    fix; given through without_direction it grows on the IMU alone, so the estimate goes degraded
    and then lost (not sent) instead of staying confidently wrong."""
    from companion.nav.fusion import without_direction

    c = FusionConfig()
    corridor = np.diag([100.0, 1e-4])
    runs = {}
    for name, pseudo in (("repeated", corridor), ("projected", without_direction(corridor, (1.0, 0.0)))):
        f = _hovering_filter()
        states = []
        for k in range(1, 1000):
            t = 1.0 + k * IMU_DT
            _imu(f, t)
            if k % 5 == 0:
                north = float(f.state(t - 0.01).position_ned[0])
                f.correct_position(t - 0.01, [north, 0.0], pseudo)
                f.correct_height(t - 0.01, 1.0, 1e-4)
                f.correct_yaw(t - 0.01, 0.0, 1e-4)
            states.append(f.state(t))
        assert max(math.sqrt(s.position_covariance[1, 1]) for s in states) < 0.02  # east: measured
        runs[name] = states
    sigma = {name: np.sqrt([s.position_covariance[0, 0] for s in states]) for name, states in runs.items()}
    last_5s = int(5.0 / IMU_DT)
    assert sigma["repeated"][-1] < 1.05 * sigma["repeated"][-last_5s]  # levelled off: looks known for ever
    assert sigma["projected"][-1] > 2 * sigma["repeated"][-1] and np.all(np.diff(sigma["projected"][::5]) > 0)
    assert sigma["projected"][-1] > c.lost_position_std_m
    first_degraded = next(s for s in runs["projected"] if s.status == State.DEGRADED)
    assert "horizontal position uncertain" in first_degraded.reason
    assert not runs["projected"][-1].healthy and "uncertain" in runs["projected"][-1].reason


def test_imu_stop_is_lost_and_a_long_gap_reinitialises() -> None:
    f = _hovering_filter()
    assert not f.state(1.0 + 0.25).healthy and "IMU" in f.state(1.25).reason
    counter = f.state(1.0).reset_counter
    _imu(f, 2.5)  # 1.5 s gap: the estimate is forgotten
    assert f.stats.reinitialisations == 1 and "not initialised" in f.state(2.5).reason
    _imu(f, 2.52)
    f.correct_position(2.51, [1.0, 2.0, -1.5], np.eye(3) * 1e-4)  # a 3-D fix gives the height too
    f.correct_yaw(2.51, 0.3, 1e-4)
    state = f.state(2.52)
    assert state.healthy and state.reset_counter > counter
    assert np.allclose(state.position_ned, [1.0, 2.0, -1.5], atol=0.01)


def test_nan_inputs_are_rejected_counted_and_never_reach_the_output() -> None:
    f = _hovering_filter()
    nan, inf = float("nan"), float("inf")
    assert not f.predict(1.02, np.array([nan, 0.0, -9.8]), (0.0, 0.0, 0.0))
    assert not f.predict(1.02, np.array([0.0, 0.0, -9.8]), (0.0, inf, 0.0))
    assert not f.predict(nan, np.array([0.0, 0.0, -9.8]), (0.0, 0.0, 0.0))
    assert not f.predict(1.02, np.array([0.0, 0.0, -9.8]), (0.0, 0.0, 0.0), np.array([0.0, 0.0, nan]))
    assert f.stats.imu_rejected_nonfinite == 4
    assert not f.predict(0.5, np.array([0.0, 0.0, -9.8]), (0.0, 0.0, 0.0))  # before the newest sample
    assert f.stats.imu_rejected_out_of_order == 1
    bad_position = [
        ([nan, 0.0], np.eye(2) * 1e-4), ([0.0, 0.0], np.full((2, 2), nan)), ([0.0, 0.0], -np.eye(2)),
        ([0.0, 0.0], np.eye(3)), ([0.0], np.eye(1)),
        ([0.0, 0.0], np.array([[1.0, 2.0], [2.0, 1.0]])),  # positive diagonal, not positive definite
    ]
    for xy, cov in bad_position:
        assert not f.correct_position(0.99, xy, cov)
    assert not f.correct_position(nan, [0.0, 0.0], np.eye(2) * 1e-4)
    assert not f.correct_height(0.99, nan, 1e-4)
    assert not f.correct_height(0.99, 1.0, 0.0)
    assert not f.correct_yaw(0.99, inf, 1e-4)
    assert not f.correct_yaw(0.99, 0.0, nan)
    assert not f.correct_yaw(0.99, 0.0, -1e-4)
    assert not f.reset(np.array([nan, 0.0, 0.0]), 0.0, 1.0)
    assert not f.correct_position(1.0 + 0.6, [0.0, 0.0], np.eye(2) * 1e-4)  # captured in the future
    assert not f.reset(np.array([0.0, 0.0, -1.0]), 0.0, 1.0 + 0.6)
    assert f.stats.fixes_invalid == 15 and f.stats.resets == 0 and f.state(1.0).reset_counter == 0
    for t in np.arange(1.02, 1.5, IMU_DT):
        _imu(f, float(t))
        state = f.state(float(t) + 0.005)
        numbers = [state.position_ned, state.velocity_ned, state.position_covariance, state.velocity_covariance,
                   [state.yaw, state.yaw_variance, state.t], state.accel_bias_body]
        assert all(np.all(np.isfinite(n)) for n in numbers)
        assert to_pose_estimate(state, 0.01, -0.02).is_finite()


def test_pose_estimate_covariances() -> None:
    f = _hovering_filter()
    state = f.state(1.01)
    estimate = to_pose_estimate(state, 0.01, -0.02, reset=True, source="lidar2d")
    assert estimate.t_capture == state.t == 1.01 and estimate.reset and estimate.source == "lidar2d"
    assert estimate.euler_rad == (0.01, -0.02, state.yaw)
    cov = estimate.pose_covariance
    assert np.array_equal(cov[0:3, 0:3], state.position_covariance)
    assert cov[3, 3] == cov[4, 4] == ROLL_PITCH_VARIANCE_RAD2 and cov[5, 5] == state.yaw_variance
    assert np.count_nonzero(cov[3:6, 0:3]) == 0
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.array_equal(estimate.velocity_covariance, state.velocity_covariance)
    assert to_pose_estimate(state, 0.0, 0.0, t_capture=0.98).t_capture == 0.98
    # Extrapolation ahead of the newest IMU sample grows the uncertainty.
    assert np.all(np.diag(f.state(1.05).position_covariance) > np.diag(f.state(1.0).position_covariance))


def test_reset_jumps_and_older_fixes_stay_in_the_old_frame() -> None:
    f = _hovering_filter()
    for k in range(51, 61):  # fly north at 0.5 m/s for 0.2 s: accelerate, then coast
        _imu(f, k * IMU_DT, (2.5 if k <= 55 else 0.0, 0.0, -GRAVITY_MPS2))
    before = f.state(1.2)
    counter = before.reset_counter
    # Relocalization valid at 1.15 s: the map is rotated by +90 deg and moved.
    assert f.reset(np.array([10.0, 20.0, -1.0]), math.pi / 2, 1.15)
    after = f.state(1.2)
    assert after.reset_counter == counter + 1 and f.stats.resets == 1
    assert abs(after.yaw - math.pi / 2) < 1e-3
    assert abs(after.position_ned[0] - 10.0) < 0.01 and after.position_ned[1] > 20.0  # north became east
    assert np.allclose(after.velocity_ned[0:2], [0.0, np.hypot(*before.velocity_ned[0:2])], atol=0.02)
    # A fix captured before the jump (old frame, delivered late) is applied before it.
    assert f.correct_position(1.107, [before.position_ned[0] - 0.02, 0.0], np.eye(2) * 1e-4)
    # It refines the velocity a little but does not drag the position back to old-frame values.
    assert np.allclose(f.state(1.2).position_ned[0:2], after.position_ned[0:2], atol=0.005)
    # A reset older than the buffer applies now.
    assert f.reset(np.array([0.0, 0.0, -1.0]), 0.0, 0.1)
    assert np.allclose(f.state(1.2).position_ned, [0.0, 0.0, -1.0]) and f.state(1.2).yaw == 0.0


def test_reset_initialises_a_fresh_filter() -> None:
    f = FusionFilter()
    _imu(f, 0.02)
    assert f.reset(np.array([1.0, 2.0, -3.0]), 0.5, 0.02)
    state = f.state(0.02)
    assert state.healthy and np.allclose(state.position_ned, [1.0, 2.0, -3.0]) and state.yaw == 0.5


def test_persistent_jump_without_reset_relocks_after_a_second() -> None:
    f = _hovering_filter()
    counter = f.state(1.0).reset_counter
    for k in range(51, 121):  # the localization now says 0.8 m east, for 1.4 s
        t = k * IMU_DT
        _imu(f, t)
        if k % 5 == 0:
            f.correct_position(t - 0.01, [0.0, 0.8], np.eye(2) * 1e-4)
            f.correct_height(t - 0.01, 1.0, 1e-4)
            f.correct_yaw(t - 0.01, 0.0, 1e-4)
    state = f.state(2.4)
    assert f.stats.fixes_gated["position"] >= 9 and f.stats.relocks == 1
    assert abs(state.position_ned[1] - 0.8) < 0.02 and state.reset_counter == counter + 1
    assert state.status == State.OK


def test_gyro_rate_drives_yaw_between_fixes() -> None:
    f = _hovering_filter()
    variance = f.state(1.0).yaw_variance
    for k in range(51, 76):  # 0.5 s at 0.4 rad/s about body z, level: no heading fix
        assert f.predict(k * IMU_DT, np.array([0.0, 0.0, -GRAVITY_MPS2]), (0.0, 0.0, 0.0),
                         np.array([0.0, 0.0, 0.4]))
    assert abs(f.state(1.5).yaw - 0.2) < 1e-9
    assert f.state(1.5).yaw_variance > variance


def _touchdown_run(phase_s: float) -> tuple[float, float, FusionFilter]:
    """A descent at 0.5 m/s onto the floor (NED z = 0) that stops within 0.5 ms, ``phase_s``
    before a 50 Hz IMU sample. The accelerometer is simulated at 2 kHz and reported as ArduPilot
    reports it, through a first-order 20 Hz low-pass, sampled at each IMU time; 10 Hz fixes of
    the true height (5 mm), position and yaw. Returns the largest |height error| after the
    touchdown (m), the filter's height standard deviation at that moment (m) and the filter."""
    sim_dt, tau = 0.0005, 1.0 / (2.0 * math.pi * 20.0)
    f = FusionFilter()
    z, vz, reported, t = -1.0, 0.0, -GRAVITY_MPS2, 0.0
    descent_from = 1.0 - phase_s  # 1 s at 0.5 m/s^2 down, then 0.5 m/s: the floor at 3.5 s - phase
    landed_at, z_captured = math.inf, z
    worst, sigma = 0.0, math.nan
    for k in range(1, 251):
        t_sample = k * IMU_DT
        for _ in range(round(IMU_DT / sim_dt)):
            t += sim_dt
            accel = 0.5 if descent_from <= t < descent_from + 1.0 else 0.0
            vz += accel * sim_dt
            z += vz * sim_dt
            force = accel - GRAVITY_MPS2
            if z >= 0.0 and landed_at == math.inf:
                landed_at, force, z, vz = t, force - vz / sim_dt, 0.0, 0.0
            reported += sim_dt / (sim_dt + tau) * (force - reported)
            if abs(t - (t_sample - 0.01)) < sim_dt / 2:
                z_captured = z
        assert f.predict(t_sample, np.array([0.0, 0.0, reported]), (0.0, 0.0, 0.0))
        if k % 5 == 0:
            f.correct_position(t_sample - 0.01, [0.0, 0.0], np.eye(2) * 1e-4)
            f.correct_height(t_sample - 0.01, -z_captured, 0.005 ** 2)
            f.correct_yaw(t_sample - 0.01, 0.0, 1e-4)
        if t_sample > landed_at:
            state = f.state(t_sample)
            error = abs(float(state.position_ned[2]) - z)
            if error > worst:
                worst, sigma = error, math.sqrt(state.position_covariance[2, 2])
    return worst, sigma, f


@pytest.mark.parametrize("phase_s", [0.001, 0.010, 0.019])
def test_a_touchdown_between_imu_samples_is_corrected_by_the_next_height_fixes_not_gated(phase_s: float) -> None:
    """The 50 Hz samples see the touchdown's filtered pulse at any phase; a late one shows little
    of it and the integrated vertical velocity stays 0.3 m/s off. The held sample's uncertainty
    must let the next height fixes correct that: with half of it, every fix was gated for a second
    and the height ran 0.4 m below the floor until the relock."""
    worst, sigma, f = _touchdown_run(phase_s)
    assert f.stats.fixes_gated["height"] == 0 and f.stats.relocks == 0
    assert worst < 0.05
    assert worst < 3.0 * sigma  # and the filter says how uncertain it is meanwhile



def _climb_with_jittered_fix_stamps(config: FusionConfig, seed: int) -> tuple[FusionFilter, float, float]:
    """Hovering at 1 m, then 5 m/s^2 up for 0.2 s and 2.8 s at 1 m/s, exact IMU; each 10 Hz
    height fix (5 mm) is the height at its stamp plus a random 10 ms (1 sigma): the clock
    mappings' error between a scanner's stamps and the autopilot's IMU. Returns the filter, the
    largest |height error| after the lift-off (m) and the mean NEES of the height (1 if honest)."""
    rng = np.random.default_rng(seed)
    f = FusionFilter(config)

    def height(t: float) -> float:
        s = min(max(t - 1.0, 0.0), 0.2)
        return 1.0 + 2.5 * s * s + max(t - 1.2, 0.0)

    worst, nees = 0.0, []
    for k in range(1, 201):
        t = k * IMU_DT
        _imu(f, t, (0.0, 0.0, -GRAVITY_MPS2 - (5.0 if 1.0 < t <= 1.2 + 1e-9 else 0.0)))
        if k % 5 == 0:
            captured = t - 0.01
            f.correct_position(captured, [0.0, 0.0], np.eye(2) * 1e-4)
            f.correct_height(captured, height(captured + rng.normal(0.0, 0.01)), 0.005 ** 2)
            f.correct_yaw(captured, 0.0, 1e-4)
        if t > 1.0:
            state = f.state(t)
            error = -float(state.position_ned[2]) - height(t)
            worst = max(worst, abs(error))
            nees.append(error * error / state.position_covariance[2, 2])
    return f, worst, float(np.mean(nees))


def test_height_fixes_with_stamps_off_by_the_clock_mappings_error_are_used_not_gated_in_a_fast_climb() -> None:
    """At 1 m/s a fix stamped 10 ms off is 1 cm off, two of its 5 mm sigmas. Taken as exactly
    timed (``fix_time_sd_s`` 0), such fixes fail the gate and the filter claims more than it knows
    (NEES above 1); with the capture time's uncertainty (10 ms, the default) in their variance,
    every fix is used and the claimed height sigma covers the error."""
    exact = [_climb_with_jittered_fix_stamps(FusionConfig(fix_time_sd_s=0.0), seed) for seed in range(3)]
    assert sum(f.stats.fixes_gated["height"] for f, _, _ in exact) >= 5
    assert max(nees for _, _, nees in exact) > 2.0
    timed = FusionConfig()
    for f, worst, nees in (_climb_with_jittered_fix_stamps(timed, seed) for seed in range(3)):
        assert f.stats.fixes_gated["height"] == 0 and f.stats.relocks == 0
        assert worst < 0.03 and nees < 1.5
