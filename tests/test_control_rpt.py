"""RPT outer loop (Wang et al. section IV): gains and poles (eqs. 13-18), integral action,
anti-windup, bumpless engage, limits, tracking against the PID baseline, non-finite input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.control.bench_control import control_figures, run_control_bench
from companion.control.pid import PID_XY, PID_Z, PidAxis, PidController
from companion.control.response import (PAPER_MODEL, PAPER_XY, PAPER_Z, AxisPlant, FigureEight, PlantModel,
                                        advance, AxisState, compare_tracking, simulate_axis, step_metrics,
                                        step_response)
from companion.control.outer_loop import ControlOutput, MeasuredState, NonFiniteInput, position_only_target
from companion.control.reference import Reference
from companion.control.rpt import (ACCELERATION, VELOCITY, XY_PARAMS, Z_PARAMS, AxisLimits, RptAxis, RptController,
                                   RptLimits, RptParams, augmented_model, closed_loop_matrix)
from companion.control.trajectory import plan

XY_SETS = [XY_PARAMS, RptParams(0.5, 1.2, 0.5, 0.5), RptParams(2.0, 0.8, 1.0, 0.1),
           RptParams(0.8, 1.5, 1.5, 0.3), RptParams(1.0, 0.99, 0.707, 0.0)]
Z_SETS = [Z_PARAMS, RptParams(0.5, 0.559, 2.0, 0.0), RptParams(1.0, 1.0, 0.7, 0.0), RptParams(1.5, 2.0, 1.0, 0.0)]
FREE = RptLimits.unlimited()
FREE_XY = AxisLimits.from_limits(FREE, ACCELERATION)
FREE_Z = AxisLimits.from_limits(FREE, VELOCITY)


def _sorted(z: np.ndarray) -> np.ndarray:
    z = np.asarray(z, dtype=complex)
    return z[np.lexsort((np.round(z.imag, 9), np.round(z.real, 9)))]


# ------------------------------------------------------------------ gains and poles
def test_default_gains_are_eq15_and_eq18_derived() -> None:
    g = XY_PARAMS.gains(ACCELERATION)
    w, z, k = 0.99, 0.707, 0.25
    assert g.k_int == pytest.approx(k * w * w)  # 0.2450
    assert g.k_p == pytest.approx(w * w + 2 * z * w * k)  # 1.3301
    assert g.k_d == pytest.approx(2 * z * w + k)  # 1.6499
    # eq. 15 read as one row over [xi, p_r, v_r, a_r, p, v], first entry negative for xi' = p - p_r
    assert XY_PARAMS.feedback(ACCELERATION) == pytest.approx((-0.245025, 1.330065, 1.64986, 1.0, -1.330065, -1.64986))
    gz = Z_PARAMS.gains(VELOCITY)
    assert gz.k_int == pytest.approx(0.559**2) and gz.k_p == pytest.approx(2 * 2.0 * 0.559)
    assert Z_PARAMS.feedback(VELOCITY) == pytest.approx((-0.312481, 2.236, 1.0, -2.236))


@pytest.mark.parametrize("params", XY_SETS)
def test_xy_closed_loop_poles_are_eq16_roots(params: RptParams) -> None:
    placed = np.roots(np.polymul([1.0, params.k_i], [1.0, 2 * params.zeta * params.omega_n, params.omega_n**2]))
    placed = placed / params.epsilon  # roots of p_i(eps s)
    acl = closed_loop_matrix(params, ACCELERATION)
    # the loop block (xi, p, v): exactly the placed poles
    loop = acl[np.ix_([0, 4, 5], [0, 4, 5])]
    np.testing.assert_allclose(_sorted(np.linalg.eigvals(loop)), _sorted(placed), atol=1e-9)
    # the whole 6x6 augmented matrix: those plus the exosystem's three zeros (p_r, v_r, a_r)
    np.testing.assert_allclose(_sorted(np.linalg.eigvals(acl)), _sorted(np.r_[placed, 0, 0, 0]), atol=1e-5)
    np.testing.assert_allclose(_sorted(params.poles(ACCELERATION)), _sorted(placed), atol=1e-12)
    assert np.all(placed.real < 0) if params.k_i > 0 else np.all(placed.real <= 0)  # k_i = 0: eta unused


@pytest.mark.parametrize("params", Z_SETS)
def test_z_closed_loop_poles_are_eq16_roots(params: RptParams) -> None:
    placed = np.roots([1.0, 2 * params.zeta * params.omega_n, params.omega_n**2]) / params.epsilon
    acl = closed_loop_matrix(params, VELOCITY)
    loop = acl[np.ix_([0, 3], [0, 3])]
    np.testing.assert_allclose(_sorted(np.linalg.eigvals(loop)), _sorted(placed), atol=1e-9)
    np.testing.assert_allclose(_sorted(np.linalg.eigvals(acl)), _sorted(np.r_[placed, 0, 0]), atol=1e-6)


def test_paper_default_poles() -> None:
    np.testing.assert_allclose(_sorted(XY_PARAMS.poles(ACCELERATION)),
                               _sorted([-0.25, -0.69993 + 0.70014j, -0.69993 - 0.70014j]), atol=1e-4)
    np.testing.assert_allclose(sorted(Z_PARAMS.poles(VELOCITY).real), [-2.0862, -0.1498], atol=1e-4)


def test_epsilon_scales_every_pole_by_one_over_epsilon() -> None:
    for kind, base in ((ACCELERATION, XY_PARAMS), (VELOCITY, Z_PARAMS)):
        fast = RptParams(0.25, base.omega_n, base.zeta, base.k_i)
        eig1 = np.linalg.eigvals(closed_loop_matrix(base, kind))
        eig4 = np.linalg.eigvals(closed_loop_matrix(fast, kind))
        np.testing.assert_allclose(_sorted(eig4), _sorted(4.0 * eig1), atol=1e-4)


def test_the_seed_texts_literal_sign_of_the_integral_gain_is_unstable() -> None:
    """Eq. 15 as printed (+k_i w^2/e^3) with eq. 13 as printed (xi' = p - p_r) has a RHP pole."""
    a, b = augmented_model(ACCELERATION)
    f = np.array(XY_PARAMS.feedback(ACCELERATION))
    f[0] = -f[0]
    assert np.max(np.linalg.eigvals(a + b @ f[None, :]).real) > 0.1


def test_the_implementation_runs_the_derived_law() -> None:
    """Probe RptAxis.law: its gains on (eta, p_r, v_r, a_r, p, v) are F (eta = -xi)."""
    for kind, params, n in ((ACCELERATION, XY_PARAMS, 6), (VELOCITY, Z_PARAMS, 4)):
        axis = RptAxis(params, kind, FREE_XY if kind == ACCELERATION else FREE_Z)
        f = params.feedback(kind)
        probe = []
        for j in range(n):
            x = np.zeros(n)
            x[j] = 1.0
            if kind == ACCELERATION:
                axis.error_integral = -x[0]
                probe.append(axis.law(x[1], x[2], x[3], x[4], x[5]))
            else:
                axis.error_integral = -x[0]
                probe.append(axis.law(x[1], x[2], 0.0, x[3], 0.0))
        assert probe == pytest.approx(f)


# (no repeated poles here: a double pole splits by O(sqrt(dt)) under discretization)
@pytest.mark.parametrize("kind, params", [(ACCELERATION, p) for p in (XY_SETS[0], XY_SETS[1], XY_SETS[3])]
                         + [(VELOCITY, p) for p in Z_SETS[:3]])
def test_discrete_loop_of_the_implementation_has_the_placed_poles(kind: str, params: RptParams) -> None:
    """The implemented step() closed around the exact ZOH plant at 1 kHz: log(eig)/dt -> eq. 16."""
    dt = 1e-3
    plant = AxisPlant(kind, 0.0)
    dims = 3 if kind == ACCELERATION else 2
    phi = np.zeros((dims, dims))
    for j in range(dims):
        axis = RptAxis(params, kind, FREE_XY if kind == ACCELERATION else FREE_Z)
        axis.engage(0.0, 0.0, 0.0, 0.0, 0.0)
        x0 = np.eye(dims)[j]
        axis.error_integral = x0[0]
        s = AxisState(x0[1], x0[2] if dims == 3 else 0.0)
        u = axis.step(dt, 0.0, 0.0, 0.0, s.p, s.v)
        advance(plant, s, u, dt)
        phi[:, j] = [axis.error_integral, s.p, s.v][:dims]
    poles = np.log(np.linalg.eigvals(phi).astype(complex)) / dt
    placed = params.poles(kind)
    np.testing.assert_allclose(_sorted(poles), _sorted(placed), atol=5e-3 * np.max(np.abs(placed)))


# ------------------------------------------------------------------ integral action
@pytest.mark.parametrize("kind", [ACCELERATION, VELOCITY])
def test_zero_steady_state_error_to_a_step_and_a_ramp_under_a_constant_disturbance(kind: str) -> None:
    params, lim = (XY_PARAMS, FREE_XY) if kind == ACCELERATION else (Z_PARAMS, FREE_Z)
    plant = AxisPlant(kind, 0.0 if kind == ACCELERATION else 0.1)
    d = 0.3  # m/s^2 (x, y) or m/s (z): a bias the autopilot does not cancel
    step = simulate_axis(RptAxis(params, kind, lim), plant, lambda t: (1.0, 0.0, 0.0), 80.0, disturbance=d)
    assert abs(step.reference[-1] - step.position[-1]) < 1e-4
    ramp = simulate_axis(RptAxis(params, kind, lim), plant, lambda t: (0.5 * t, 0.5, 0.0), 80.0, disturbance=d)
    assert abs(ramp.reference[-1] - ramp.position[-1]) < 1e-4
    if kind == ACCELERATION:  # without the integral (k_i = 0) the bias leaves an error d / omega_n^2
        no_i = RptParams(1.0, 0.99, 0.707, 0.0)
        run = simulate_axis(RptAxis(no_i, kind, lim), plant, lambda t: (1.0, 0.0, 0.0), 80.0, disturbance=d)
        assert abs(run.reference[-1] - run.position[-1]) == pytest.approx(d / 0.99**2, rel=1e-3)


def test_parabola_is_tracked_exactly_from_its_start_state() -> None:
    """Perfect tracking: with a_r fed forward, a constant-acceleration reference leaves no error."""
    axis = RptAxis(XY_PARAMS, ACCELERATION, FREE_XY)
    run = simulate_axis(axis, PAPER_XY, lambda t: (0.25 * t * t, 0.5 * t, 0.5), 20.0, continuation=0.5)
    assert np.max(np.abs(run.reference - run.position)) < 1e-9


# ------------------------------------------------------------------ anti-windup
def _gust_run(anti_windup: bool):
    lim = AxisLimits.from_limits(RptLimits(), ACCELERATION)  # 2.5 m/s^2, 5 m/s^3, 2 m/s
    axis = RptAxis(XY_PARAMS, ACCELERATION, lim, anti_windup=anti_windup)
    gust = lambda t: -2.7 if 1.0 <= t < 6.0 else 0.0  # beyond the 2.5 m/s^2 authority for 5 s
    return simulate_axis(axis, PAPER_XY, lambda t: (0.0, 0.0, 0.0), 60.0, disturbance=gust), axis


def test_anti_windup_bounds_the_overshoot_after_5_s_of_saturation() -> None:
    with_aw, axis = _gust_run(True)
    without, _ = _gust_run(False)
    saturated_s = np.sum(np.abs(with_aw.output) >= 2.5 - 1e-9) * 0.02
    assert saturated_s >= 5.0
    excursion = -np.min(with_aw.position)  # pushed back ~7.4 m
    after = with_aw.t >= 6.0
    overshoot_aw = np.max(with_aw.position[after])  # past the setpoint 0 on the way back
    overshoot_no = np.max(without.position[after])
    assert excursion > 5.0
    assert overshoot_aw < 0.1 * excursion  # measured 0.46 m
    assert overshoot_no > 10 * overshoot_aw  # measured 5.7 m
    assert abs(with_aw.position[-1]) < 1e-3 and abs(axis.integral_term) <= 1.0 + 1e-12
    assert np.all(np.abs(np.diff(with_aw.output)) <= 5.0 * 0.02 + 1e-12)  # the 1-D jerk limit
    assert np.all(np.abs(with_aw.velocity) <= 2.0 + 1e-6)  # the 1-D speed guard


def test_integral_term_is_clamped() -> None:
    axis = RptAxis(XY_PARAMS, ACCELERATION, AxisLimits.from_limits(RptLimits(), ACCELERATION))
    axis.engage(0.0, 0.0, 0.0, 0.0, 0.0)
    for _ in range(5000):  # a vehicle that does not move at all (stuck), error 0.3 m
        axis.step(0.02, 0.3, 0.0, 0.0, 0.0, 0.0)
    assert axis.integral_term == pytest.approx(1.0)


# ------------------------------------------------------------------ bumpless engage
def test_engage_continues_the_current_acceleration_and_climb_rate() -> None:
    c = RptController()
    meas = MeasuredState((1.0, 2.0, -1.0), (0.5, -0.2, -0.3), acceleration_ned=(0.4, -0.2, 0.0))
    ref = Reference((1.3, 1.9, -1.2), (0.4, 0.0, -0.2), (0.0, 0.1, 0.0))  # 0.3 m, 0.2 m/s off
    c.engage(meas, ref)
    first = c.step(0.02, ref, meas)
    assert first.acceleration_ned[:2] == pytest.approx((0.4, -0.2), abs=1e-12)
    assert first.velocity_ned_z == pytest.approx(-0.3, abs=1e-12)
    # a fresh controller whose integrator starts at 0 would jump by the law's value
    cold = RptAxis(XY_PARAMS, ACCELERATION, FREE_XY)
    cold.engage(1.3, 0.4, 0.0, 1.0, 0.5, continuation=None)
    cold.error_integral = 0.0
    assert abs(cold.law(1.3, 0.4, 0.0, 1.0, 0.5) - 0.4) > 5.0 * 0.02  # more than one step's jerk


def test_output_stays_continuous_after_engage() -> None:
    c = RptController()
    traj = FigureEight()
    ref0 = traj.sample(3.0)
    meas = MeasuredState(tuple(p + 0.2 for p in ref0.position), ref0.velocity, ref0.acceleration)
    c.engage(meas, ref0)
    prev = np.array(ref0.acceleration[:2])
    for k in range(1, 100):
        out = c.step(0.02, traj.sample(3.0 + 0.02 * k), meas)
        a = np.array(out.acceleration_ned[:2])
        assert np.linalg.norm(a - prev) <= 5.0 * 0.02 + 1e-9
        prev = a


def test_auto_engage_on_first_step_starts_from_hover() -> None:
    c = RptController()
    out = c.step(0.02, Reference((5.0, 0.0, -1.0)), MeasuredState((0.0, 0.0, -1.0), (0.0, 0.0, 0.0)))
    assert math.hypot(*out.acceleration_ned[:2]) <= 5.0 * 0.02 + 1e-12


# ------------------------------------------------------------------ limits
def test_acceleration_jerk_speed_and_climb_limits_are_respected() -> None:
    lim = RptLimits()
    c = RptController(limits=lim)
    rng = np.random.default_rng(3)
    states = [AxisState(), AxisState(), AxisState(-1.0)]
    plants = (PAPER_XY, PAPER_XY, PAPER_Z)
    dt = 0.02
    target = (0.0, 0.0, -1.0)
    prev_a, prev_vz = np.zeros(2), 0.0
    max_speed = 0.0
    for k in range(6000):
        if k % 150 == 0:  # a new far target every 3 s, as steps (the worst case for the limits)
            target = tuple(rng.uniform(-10, 10, 2)) + (float(rng.uniform(-5, 0)),)
        meas = MeasuredState(tuple(s.p for s in states), tuple(s.v for s in states))
        out = c.step(dt, Reference(target), meas)
        a = np.array(out.acceleration_ned[:2])
        assert np.linalg.norm(a) <= lim.accel_xy_mps2 * (1 + 1e-12)
        assert np.linalg.norm(a - prev_a) <= lim.jerk_xy_mps3 * dt * (1 + 1e-9)
        assert -lim.climb_mps - 1e-12 <= out.velocity_ned_z <= lim.descent_mps + 1e-12
        assert abs(out.velocity_ned_z - prev_vz) <= lim.accel_z_mps2 * dt * (1 + 1e-9)
        assert abs(out.acceleration_ned[2]) <= lim.accel_z_mps2 * (1 + 1e-9)
        prev_a, prev_vz = a, out.velocity_ned_z
        for i, u in enumerate((a[0], a[1], out.velocity_ned_z)):
            advance(plants[i], states[i], u, dt)
        max_speed = max(max_speed, math.hypot(states[0].v, states[1].v))
    assert max_speed <= lim.speed_xy_mps * 1.02  # the speed guard (soft: jerk-limited braking; measured 2.016)
    assert max_speed > 0.8 * lim.speed_xy_mps


def test_z_feedforward_is_the_rate_of_the_velocity_reference() -> None:
    c = RptController(limits=FREE)
    traj = FigureEight()
    ref0 = traj.sample(0.0)
    p0, v0 = np.array(ref0.position) + 0.1, np.array(ref0.velocity) * 0.5  # off the trajectory
    c.engage(MeasuredState(p0, v0), ref0)
    outs = [c.step(0.02, traj.sample(0.02 * k), MeasuredState(p0 + v0 * 0.02 * k, v0)) for k in range(200)]
    vz = np.array([o.velocity_ned_z for o in outs])
    az = np.array([o.acceleration_ned[2] for o in outs])
    np.testing.assert_allclose(np.diff(vz) / 0.02, az[1:], atol=0.02)


# ------------------------------------------------------------------ RPT vs PID
def test_pid_baseline_has_the_same_poles_as_rpt() -> None:
    assert (PID_XY.k_p, PID_XY.k_d, PID_XY.k_i) == pytest.approx((1.330065, 1.64986, 0.245025))
    assert (PID_Z.k_p, PID_Z.k_i, PID_Z.k_d) == pytest.approx((2.236, 0.312481, 0.0))
    m_rpt, _ = step_response(RptAxis(XY_PARAMS, ACCELERATION, FREE_XY))
    m_pid, _ = step_response(PidAxis(PID_XY, ACCELERATION, FREE_XY))
    assert m_rpt == pytest.approx(m_pid)  # a step has nothing to feed forward: same response


def test_step_response_figures_of_the_default_gains() -> None:
    m, run = step_response(RptAxis(XY_PARAMS, ACCELERATION, FREE_XY))
    assert m.rise_s == pytest.approx(1.50, abs=0.05)
    assert m.overshoot_pct == pytest.approx(24.7, abs=0.5)
    assert m.settling_s == pytest.approx(12.9, abs=0.2)
    mz, _ = step_response(RptAxis(Z_PARAMS, VELOCITY, FREE_Z), AxisPlant(VELOCITY, 0.0))
    assert mz.rise_s == pytest.approx(0.82, abs=0.05)
    assert mz.overshoot_pct == pytest.approx(4.8, abs=0.3)
    assert mz.settling_s == pytest.approx(9.0, abs=0.2)


def test_step_metrics_on_a_known_first_order_response() -> None:
    t = np.arange(0, 20, 0.001)
    m = step_metrics(t, 1 - np.exp(-t))
    assert m.rise_s == pytest.approx(math.log(9), abs=2e-3)
    assert m.settling_s == pytest.approx(-math.log(0.02), abs=2e-3)
    assert m.overshoot_pct == 0.0


def test_rpt_tracks_a_figure_eight_better_than_pid() -> None:
    """Measured: paper model RPT 1.8 mm RMS vs PID 921 mm (521x); with a 0.1 s lag on every
    axis RPT 16.8 mm vs PID 916 mm (54x)."""
    res = compare_tracking(FigureEight(), PAPER_MODEL, {"rpt": RptController(), "pid": PidController()})
    assert res["rpt"].rms_m < 0.005 and res["rpt"].max_m < 0.01
    assert res["pid"].rms_m / res["rpt"].rms_m > 100
    lagged = PlantModel(AxisPlant(ACCELERATION, 0.1), PAPER_Z)
    res = compare_tracking(FigureEight(), lagged, {"rpt": RptController(), "pid": PidController()})
    assert res["rpt"].rms_m < 0.03
    assert res["pid"].rms_m / res["rpt"].rms_m > 20


def test_compare_tracking_takes_other_trajectory_types() -> None:
    """``duration`` (trajectory.py's name) instead of ``duration_s`` and references of numpy arrays."""
    eight = FigureEight(laps=0.5)

    class Other:
        duration = eight.duration_s

        def sample(self, t: float) -> Reference:
            r = eight.sample(t)
            return Reference(np.array(r.position), np.array(r.velocity), np.array(r.acceleration))

    ours = compare_tracking(eight, PAPER_MODEL, {"rpt": RptController()})
    theirs = compare_tracking(Other(), PAPER_MODEL, {"rpt": RptController()})
    assert theirs["rpt"] == pytest.approx(ours["rpt"])


def test_compare_tracking_flies_a_planned_trajectory() -> None:
    """The planner's samples are the controller's references (one Reference type)."""
    traj = plan([[0.0, 0.0, -1.5], [2.0, 0.0, -1.5], [2.0, 2.0, -1.0]], 0.5, 0.5)
    res = compare_tracking(traj, PAPER_MODEL, {"rpt": RptController(), "pid": PidController()})
    assert res["rpt"].max_m < 0.01 and res["pid"].rms_m > 100 * res["rpt"].rms_m  # measured 2.9 mm, 254x


# ------------------------------------------------------------------ non-finite and extreme input
def test_no_nan_for_any_finite_input() -> None:
    rng = np.random.default_rng(7)
    for limits in (RptLimits(), FREE):
        for ctrl in (RptController(limits=limits), PidController(limits=limits)):
            for _ in range(3000):
                mags = 10.0 ** rng.uniform(-300, 300, 15) * rng.choice([-1.0, 1.0], 15)
                mags[rng.random(15) < 0.2] = 0.0
                dt = float(10.0 ** rng.uniform(-6, 3))
                out = ctrl.step(dt, Reference(tuple(mags[0:3]), tuple(mags[3:6]), tuple(mags[6:9])),
                                MeasuredState(tuple(mags[9:12]), tuple(mags[12:15])))
                flat = [*out.acceleration_ned, out.velocity_ned_z, *out.position_ned, *out.velocity_ned]
                assert all(math.isfinite(v) for v in flat), out
                assert out.valid
            for extreme in (1e308, -1e308, 5e-324):
                out = ctrl.step(0.02, Reference((extreme,) * 3, (extreme,) * 3, (extreme,) * 3),
                                MeasuredState((-extreme,) * 3, (-extreme,) * 3))
                assert all(math.isfinite(v) for v in [*out.acceleration_ned, out.velocity_ned_z])


def test_nonfinite_input_returns_the_held_safe_output() -> None:
    c = RptController()
    ref = Reference((1.0, 0.0, -1.0))
    meas = MeasuredState((0.0, 0.0, -1.2), (0.0, 0.0, 0.0))
    for _ in range(50):
        good = c.step(0.02, ref, meas)
    eta = (c.x.error_integral, c.y.error_integral, c.z.error_integral)
    assert math.hypot(*good.acceleration_ned[:2]) > 0.05
    a_prev = math.hypot(*good.acceleration_ned[:2])
    for bad in (Reference((math.nan, 0.0, -1.0)), Reference((1.0, 0.0, -1.0), (0.0, math.inf, 0.0))):
        held = c.step(0.02, bad, meas)
        assert not held.valid
        assert held.position_ned == (0.0, 0.0, -1.2)  # hold at the last finite measured position
        assert held.velocity_ned[:2] == (0.0, 0.0)
        a = math.hypot(*held.acceleration_ned[:2])
        assert a_prev - a == pytest.approx(min(a_prev, 5.0 * 0.02))  # ramps to 0 under the jerk limit
        a_prev = a
        assert (c.x.error_integral, c.y.error_integral, c.z.error_integral) == eta  # frozen
    held = c.step(math.nan, ref, MeasuredState((math.nan,) * 3, (0.0,) * 3))
    assert not held.valid and all(math.isfinite(v) for v in [*held.acceleration_ned, held.velocity_ned_z])
    for _ in range(200):
        held = c.step(0.02, ref, MeasuredState((0.0, math.nan, 0.0), (0.0,) * 3))
    assert held.acceleration_ned == (0.0, 0.0, 0.0) and held.velocity_ned_z == 0.0
    assert c.nonfinite_inputs == 203
    assert c.step(0.02, ref, meas).valid  # recovers with the next finite input


def test_nonfinite_before_any_measurement_raises_and_bad_dt_raises() -> None:
    with pytest.raises(NonFiniteInput):
        RptController().step(0.02, Reference((0.0, 0.0, 0.0)), MeasuredState((math.nan, 0.0, 0.0), (0.0,) * 3))
    with pytest.raises(ValueError):
        RptController().step(0.0, Reference((0.0, 0.0, 0.0)), MeasuredState((0.0,) * 3, (0.0,) * 3))
    with pytest.raises(ValueError):
        RptParams(epsilon=0.0)
    with pytest.raises(ValueError):
        RptParams(k_i=math.nan)


def test_numpy_inputs_give_plain_float_outputs() -> None:
    c = RptController()
    out = c.step(0.02, Reference(np.array([1.0, 2.0, -1.0]), np.zeros(3), np.zeros(3)),
                 MeasuredState(np.array([0.9, 2.0, -1.1]), np.zeros(3)))
    assert all(type(v) is float for v in [*out.acceleration_ned, out.velocity_ned_z, *out.position_ned])


# ------------------------------------------------------------------ what to send
def test_setpoint_fields_make_a_pos_vel_acc_target() -> None:
    from companion.mavlink.setpoints import Setpoint

    c = RptController()
    out = c.step(0.02, Reference((1.0, 0.0, -1.0)), MeasuredState((0.0, 0.0, -1.2), (0.1, 0.0, 0.0)))
    sp = Setpoint(**out.setpoint_fields())
    assert sp.type_mask == 3072
    assert tuple(sp.position_ned) == (1.0, 0.0, -1.0)  # the reference: the autopilot's loop closes on it too
    assert sp.velocity_ned[2] == out.velocity_ned_z and sp.velocity_ned[0] == 0.0  # reference velocity
    assert tuple(sp.acceleration_ned[:2]) == out.acceleration_ned[:2] and out.acceleration_ned[0] > 0.0


def test_position_only_target_inverts_the_autopilot_cascade() -> None:
    out = ControlOutput((0.6, -0.4, 0.0), -0.3, (9.0, 9.0, -9.0), (0.0, 0.0, -0.3), (1.0, 2.0, -1.0),
                        (0.2, 0.1, 0.0), (False,) * 3)
    kp, kv, kpz = 1.0, 2.0, 1.0
    tx, ty, tz = position_only_target(out, pos_gain_xy=kp, vel_gain_xy=kv, pos_gain_z=kpz)
    # the autopilot's linear cascade demands exactly the RPT output
    assert kv * (kp * (tx - 1.0) - 0.2) == pytest.approx(0.6)
    assert kv * (kp * (ty - 2.0) - 0.1) == pytest.approx(-0.4)
    assert kpz * (tz + 1.0) == pytest.approx(-0.3)
    far = ControlOutput((2.5, 0.0, 0.0), 1.0, (5.0, 0.0, -1.0), (0.0, 0.0, 1.0), (0.0, 0.0, -1.0),
                        (2.0, 0.0, 0.0), (False,) * 3)
    tx, ty, tz = position_only_target(far, max_lead_m=1.0)
    assert math.hypot(tx, ty) == pytest.approx(1.0) and tz == pytest.approx(0.0)
    held = far._replace(valid=False)
    assert position_only_target(held) == (0.0, 0.0, -1.0)


# ------------------------------------------------------------------ bench
def test_control_bench_reports_every_stage() -> None:
    result = run_control_bench(300)
    assert set(result) >= {"control.rpt step (3 axes, tuples)", "control.pid step (3 axes, tuples)"}
    for median, p99 in result.values():  # timing targets live in `companion bench`, not here
        assert 0.0 < median <= p99


def test_control_figures() -> None:
    figures = control_figures()
    assert figures["step.xy.ideal"] == pytest.approx(figures["step.xy.ideal.pid"])
    assert figures["tracking.paper model (xy ideal, z lag 0.1 s).pid_over_rpt_rms"] > 100
