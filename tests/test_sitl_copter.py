"""Behaviour of the simulated quadrotor core (sitl/): physics, sensors, estimator, flight control.

Every test is deterministic (fixed seeds). Vision samples are fed from the truth like a perfect
companion would (plus 1 cm noise) unless a test deliberately corrupts them.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from sitl.copter import EstimateState, SimulatedCopter, WindConfig
from sitl.estimator import (
    EKF_CONST_POS_MODE,
    EKF_POS_HORIZ_ABS,
    EKF_POS_HORIZ_REL,
    SEVERITY_CRITICAL,
)
from sitl.flight_control import GUIDED, LAND, LOITER, RTL, STABILIZE, ControlLimits

HOME = (47.3977, 8.5456, 488.0)
TICK = 0.005  # lockstep tick, s
NAN3 = np.full(3, np.nan)
POSITION_MASK, VELOCITY_MASK = 3576, 3527

Transform = Callable[[np.ndarray, tuple[float, float, float]], tuple[np.ndarray, tuple[float, float, float]]]


class Flight:
    """A copter plus a companion stand-in that streams vision poses from the truth."""

    def __init__(self, *, seed: int = 1, gust_std_mps: float = 0.3, rate_hz: float = 30.0,
                 noise_m: float = 0.01, **copter_kwargs) -> None:
        copter_kwargs.setdefault("gps_enabled", False)
        self.copter = SimulatedCopter(seed=seed, home=HOME, wind=WindConfig(gust_std_mps=gust_std_mps),
                                      **copter_kwargs)
        self.rng = np.random.default_rng(seed + 1000)
        self.period = 1.0 / rate_hz
        self.noise_m = noise_m
        self.next_t = 0.0
        self.vision = True
        self.latency_s = 0.0
        self.reset_counter = 0
        self.transform: Transform = lambda pos, euler: (pos, euler)
        self.truth_log: list[np.ndarray] = []
        self._delayed: list[tuple[float, np.ndarray, tuple[float, float, float]]] = []

    def run(self, seconds: float) -> None:
        """Step ``seconds`` of simulation, sending vision at ``rate_hz`` while ``vision`` is on."""
        c = self.copter
        for _ in range(round(seconds / TICK)):
            if self.vision and c.t >= self.next_t - 1e-9:
                self.next_t += self.period
                truth = c.truth
                pos, euler = self.transform(truth.pos_ned + self.rng.normal(0.0, self.noise_m, 3), truth.euler)
                self._delayed.append((c.t, pos, euler))
            while self._delayed and self._delayed[0][0] <= c.t - self.latency_s + 1e-9:
                t_capture, pos, euler = self._delayed.pop(0)
                c.vision_position(t_capture, pos, euler, None, self.reset_counter)
            c.step(TICK)
            self.truth_log.append(c.truth.pos_ned)

    def take_off(self, altitude_m: float = 1.0, settle_s: float = 4.0) -> None:
        """Origin, GUIDED, arm, takeoff and wait ``settle_s``."""
        c = self.copter
        assert c.set_origin(*HOME)
        self.run(1.0)
        assert c.set_mode(GUIDED) == (True, "")
        assert c.arm() == (True, "")
        assert c.takeoff(altitude_m) == (True, "")
        self.run(settle_s)


def texts(copter: SimulatedCopter) -> list[str]:
    return [text for _, text in copter.drain_statustext()]


def horizontal_error(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.hypot(a[0] - b[0], a[1] - b[1]))


# ---------------------------------------------------------------------------------------------- physics

def test_disarmed_vehicle_rests_on_the_floor_without_sinking_or_sliding():
    flight = Flight(gust_std_mps=1.0)
    flight.vision = False
    for _ in range(10):
        flight.run(1.0)
        truth = flight.copter.truth
        assert truth.pos_ned[2] == 0.0
        assert np.all(truth.vel_ned == 0.0)
        assert np.all(truth.pos_ned == 0.0)
        assert truth.accel_body[2] == pytest.approx(-9.80665)


def test_armed_idle_on_the_floor_stays_put_and_auto_disarms_after_disarm_delay():
    flight = Flight()
    c = flight.copter
    c.set_origin(*HOME)
    flight.run(1.0)
    assert c.set_mode(GUIDED)[0] and c.arm()[0]
    flight.run(9.0)
    assert c.armed and c.landed
    assert np.all(c.truth.pos_ned == 0.0)
    flight.run(2.0)
    assert not c.armed
    assert "Disarming motors" in texts(c)


# ---------------------------------------------------------------------------------------------- flight

def test_guided_takeoff_to_1m_reaches_and_holds_altitude_in_gusts():
    flight = Flight(gust_std_mps=0.3)
    c = flight.copter
    flight.take_off(1.0, settle_s=0.0)
    start = len(flight.truth_log)
    flight.run(4.0)
    climb = np.diff(np.array(flight.truth_log[start:])[:, 2]) / TICK
    assert -climb.max() <= 1.1  # climbs at <= 1 m/s (+ tracking tolerance)
    assert c.truth.pos_ned[2] == pytest.approx(-1.0, abs=0.1)
    flight.truth_log.clear()
    flight.run(10.0)
    err = np.array(flight.truth_log) - np.array([0.0, 0.0, -1.0])
    assert math.sqrt(float((err**2).sum(axis=1).mean())) < 0.1
    assert not c.landed and c.mode == GUIDED


def test_without_origin_there_is_no_position_and_guided_arming_is_refused_despite_vision():
    flight = Flight()
    c = flight.copter
    flight.run(3.0)
    est = c.estimate
    assert not est.pos_valid and not est.ext_nav_in_use
    assert est.flags & EKF_CONST_POS_MODE and not est.flags & EKF_POS_HORIZ_REL
    assert c.set_mode(GUIDED) == (True, "")  # any mode is accepted while disarmed, like ArduPilot
    ok, reason = c.arm()
    assert not ok and "Position" in reason
    assert (SEVERITY_CRITICAL, reason) in c.drain_statustext()
    assert c.set_origin(*HOME)
    flight.run(0.1)
    assert c.estimate.pos_valid and c.estimate.flags & EKF_POS_HORIZ_ABS
    assert texts(c) == ["EKF3 IMU0 origin set", "EKF3 IMU0 is using external nav data"]
    assert c.arm() == (True, "")


def test_origin_is_accepted_only_once():
    c = Flight().copter
    assert c.set_origin(*HOME)
    assert not c.set_origin(HOME[0] + 1.0, HOME[1], HOME[2])
    assert c.origin == HOME


def test_vision_loss_drops_position_after_300ms_then_ekf_failsafe_lands_and_disarms():
    flight = Flight()
    c = flight.copter
    flight.take_off()
    texts(c)
    flight.vision = False
    flight.run(0.25)
    assert c.estimate.pos_valid
    flight.run(0.1)
    assert not c.estimate.pos_valid and not c.estimate.ext_nav_in_use
    assert texts(c) == ["EKF3 IMU0 stopped using external nav data"]
    flight.run(0.9)
    assert c.mode == GUIDED
    flight.run(0.2)
    assert c.mode == LAND
    assert any("EKF Failsafe" in text for text in texts(c))
    flight.run(6.0)
    assert not c.armed and c.truth.pos_ned[2] == 0.0


def test_vision_regained_queues_using_external_nav_again():
    flight = Flight()
    c = flight.copter
    c.set_origin(*HOME)
    flight.run(1.0)
    flight.vision = False
    flight.run(0.5)
    flight.vision = True
    flight.next_t = c.t
    flight.run(0.1)
    assert texts(c)[-2:] == ["EKF3 IMU0 stopped using external nav data", "EKF3 IMU0 is using external nav data"]
    assert c.estimate.pos_valid


def test_short_vision_gap_in_flight_recovers_without_failsafe():
    flight = Flight()
    c = flight.copter
    flight.take_off()
    flight.vision = False
    flight.run(0.5)
    assert not c.estimate.pos_valid
    flight.vision = True
    flight.next_t = c.t
    flight.run(3.0)
    assert c.estimate.pos_valid and c.mode == GUIDED
    assert np.linalg.norm(c.truth.pos_ned - [0.0, 0.0, -1.0]) < 0.15


def test_rtl_climbs_returns_home_lands_and_disarms():
    flight = Flight(limits=ControlLimits(rtl_alt_m=3.0))
    c = flight.copter
    flight.take_off(2.0)
    assert c.set_position_target(1, POSITION_MASK, np.array([4.0, 3.0, -2.0]), NAN3, NAN3, math.nan, math.nan)
    flight.run(8.0)
    assert c.set_mode(RTL) == (True, "")
    flight.truth_log.clear()
    flight.run(20.0)
    assert min(p[2] for p in flight.truth_log) == pytest.approx(-3.0, abs=0.2)
    assert not c.armed and horizontal_error(c.truth.pos_ned, np.zeros(3)) < 0.3


def test_arming_is_refused_while_not_landed():
    flight = Flight(start_ned=(0.0, 0.0, -5.0))
    c = flight.copter
    c.set_origin(*HOME)
    flight.run(0.5)
    c.set_mode(GUIDED)
    assert c.arm() == (False, "Arm: vehicle not landed")
    flight.run(2.0)
    assert c.truth.pos_ned[2] == 0.0 and c.arm() == (True, "")


def test_vision_sent_in_enu_instead_of_ned_is_visible():
    flight = Flight()
    c = flight.copter
    flight.take_off()
    target = np.array([1.0, 0.0, -1.0])
    assert c.set_position_target(1, POSITION_MASK, target, NAN3, NAN3, math.nan, math.nan)
    flight.run(5.0)
    assert np.linalg.norm(c.truth.pos_ned - target) < 0.2
    flight.transform = lambda p, e: (np.array([p[1], p[0], -p[2]]), (e[0], e[1], math.pi / 2 - e[2]))
    flight.run(3.0)
    assert c.estimate.rejected_ext_nav > 0
    assert np.linalg.norm(c.truth.pos_ned - target) > 0.5


def test_vision_yaw_inconsistent_with_compass_fails_prearm():
    flight = Flight()
    c = flight.copter
    flight.transform = lambda p, e: (p, (e[0], e[1], e[2] + math.radians(20)))
    c.set_origin(*HOME)
    flight.run(1.0)
    c.set_mode(GUIDED)
    ok, reason = c.arm()
    assert not ok and "yaw" in reason
    flight.transform = lambda p, e: (p, e)
    flight.run(1.0)
    assert c.arm() == (True, "")


def test_reset_counter_change_jumps_position_instead_of_filtering():
    flight = Flight()
    c = flight.copter
    c.set_origin(*HOME)
    flight.run(1.0)
    flight.transform = lambda p, e: (p + np.array([3.0, 0.0, 0.0]), e)
    flight.reset_counter = 1
    flight.run(0.05)
    assert c.estimate.pos_ned[0] == pytest.approx(3.0, abs=0.05)
    assert c.estimate.rejected_ext_nav == 0


def test_delayed_vision_is_compensated_with_the_capture_time():
    flight = Flight(gust_std_mps=0.0)
    c = flight.copter
    flight.latency_s = 0.1
    flight.take_off()
    assert c.set_position_target(1, VELOCITY_MASK, NAN3, np.array([2.0, 0.0, 0.0]), NAN3, math.nan, math.nan)
    flight.run(2.0)
    assert c.truth.vel_ned[0] == pytest.approx(2.0, abs=0.2)
    assert horizontal_error(c.estimate.pos_ned, c.truth.pos_ned) < 0.1  # 0.2 m if not compensated


def test_vision_speed_is_fused_when_consistent_and_gated_when_wrong():
    flight = Flight()
    c = flight.copter
    flight.take_off()
    for _ in range(10):
        c.vision_speed(c.t, c.truth.vel_ned, np.diag([0.01, 0.01, 0.01]).ravel(), 0)
        flight.run(0.05)
    assert c.estimate.rejected_ext_nav == 0
    c.vision_speed(c.t, np.array([10.0, 0.0, 0.0]), None, 0)
    assert c.estimate.rejected_ext_nav == 1
    assert np.linalg.norm(c.estimate.vel_ned) < 0.3


def test_velocity_target_times_out_after_3s_and_the_vehicle_holds():
    flight = Flight()
    c = flight.copter
    flight.take_off()
    assert c.set_position_target(1, VELOCITY_MASK, NAN3, np.array([1.0, 0.0, 0.0]), NAN3, math.nan, math.nan)
    flight.run(2.5)
    assert c.truth.vel_ned[0] == pytest.approx(1.0, abs=0.15)
    flight.run(2.5)
    stopped = c.truth.pos_ned
    assert 2.3 < stopped[0] < 3.6  # ~3 s at about 1 m/s, then braking
    assert abs(c.truth.vel_ned[0]) < 0.3
    flight.run(4.0)
    assert horizontal_error(c.truth.pos_ned, stopped) < 0.3


def test_position_target_persists_and_body_offset_frame_is_relative_to_heading():
    flight = Flight()
    c = flight.copter
    flight.take_off()
    # BODY_OFFSET_NED with yaw commanded to east: 2 m forward = 2 m east after turning
    assert c.set_position_target(1, POSITION_MASK - 1024, c.estimate.pos_ned, NAN3, NAN3, math.pi / 2, math.nan)
    flight.run(4.0)
    assert c.estimate.euler[2] == pytest.approx(math.pi / 2, abs=0.05)
    start = c.estimate.pos_ned
    assert c.set_position_target(9, POSITION_MASK, np.array([2.0, 0.0, 0.0]), NAN3, NAN3, math.nan, math.nan)
    flight.run(12.0)
    assert np.linalg.norm(c.truth.pos_ned - (start + [0.0, 2.0, 0.0])) < 0.15


def test_guided_targets_are_ignored_outside_guided_or_with_unsupported_frame_mask_or_nan():
    flight = Flight()
    c = flight.copter
    c.set_origin(*HOME)
    flight.run(0.5)
    target = np.array([1.0, 0.0, -1.0])
    assert not c.set_position_target(1, POSITION_MASK, target, NAN3, NAN3, 0.0, 0.0)  # STABILIZE
    c.set_mode(GUIDED)
    assert not c.set_position_target(6, POSITION_MASK, target, NAN3, NAN3, 0.0, 0.0)  # GLOBAL_RELATIVE_ALT
    assert not c.set_position_target(1, 0b110111111001, target, NAN3, NAN3, 0.0, 0.0)  # x ignored only
    assert not c.set_position_target(1, POSITION_MASK | 512, target, NAN3, NAN3, 0.0, 0.0)  # force
    assert not c.set_position_target(1, POSITION_MASK, np.array([np.nan, 0.0, -1.0]), NAN3, NAN3, 0.0, 0.0)
    assert c.nonfinite_rejected == 1
    for mask in (3576, 3527, 3135, 3520, 3072, 3576 - 1024, 3527 - 2048):
        assert c.set_position_target(1, mask, target, np.zeros(3), np.zeros(3), 0.0, 0.0), mask


def test_nonfinite_vision_is_rejected_and_counted():
    flight = Flight()
    c = flight.copter
    c.set_origin(*HOME)
    flight.run(1.0)
    before = c.estimate
    c.vision_position(c.t, np.array([np.nan, 0.0, 0.0]), (0.0, 0.0, 0.0), None, 0)
    c.vision_position(c.t, np.zeros(3), (0.0, 0.0, math.inf), None, 0)
    c.vision_speed(c.t, np.array([0.0, np.inf, 0.0]), None, 0)
    c.vision_position(c.t, np.zeros(3), (0.0, 0.0, 0.0), np.full(21, np.nan), 0)  # unknown covariance: fine
    after: EstimateState = c.estimate
    assert c.nonfinite_rejected == 3
    assert np.all(np.isfinite(after.pos_ned)) and np.all(np.isfinite(after.vel_ned))
    assert np.allclose(after.pos_ned, before.pos_ned, atol=0.05)


def test_land_descends_fast_then_slowly_below_2m_and_disarms_on_touchdown():
    flight = Flight()
    c = flight.copter
    flight.take_off(4.0, settle_s=7.0)
    texts(c)
    assert c.land() == (True, "")
    flight.truth_log.clear()
    flight.run(10.0)
    z = np.array(flight.truth_log)[:, 2]
    descent = np.diff(z) / TICK
    assert descent.max() == pytest.approx(1.5, abs=0.2)  # LAND_SPEED_HIGH above 2 m
    low = (z[1:] > -1.2) & (z[1:] < -0.8)
    assert descent[low].mean() == pytest.approx(0.5, abs=0.1)  # LAND_SPEED below 2 m
    assert not c.armed and c.landed and c.truth.pos_ned[2] == 0.0
    assert "Disarming motors" in texts(c)


def test_loiter_needs_position_to_arm_but_stabilize_does_not():
    flight = Flight()
    c = flight.copter
    flight.vision = False
    flight.run(0.5)
    c.set_mode(LOITER)
    assert not c.arm()[0]
    c.set_mode(STABILIZE)
    assert c.arm() == (True, "")
    assert not c.takeoff(1.0)[0]


def test_gps_source_needs_an_origin_then_flies_on_gps():
    flight = Flight(position_source="gps", gps_enabled=True)
    flight.vision = False
    c = flight.copter
    flight.run(2.0)
    assert c.gps is not None and c.gps.fix_type == 3
    assert not c.estimate.pos_valid
    c.set_origin(*HOME)
    flight.run(0.5)
    assert c.estimate.pos_valid
    assert c.set_mode(GUIDED)[0] and c.arm()[0] and c.takeoff(2.0)[0]
    flight.run(6.0)
    assert np.linalg.norm(c.truth.pos_ned - [0.0, 0.0, -2.0]) < 0.8
    lat, lon, alt = c.truth.lat_deg, c.truth.lon_deg, c.truth.alt_m
    assert alt == pytest.approx(HOME[2] - c.truth.pos_ned[2])
    assert abs(lat - HOME[0]) < 1e-5 and abs(lon - HOME[1]) < 1e-5
    c.set_gps_enabled(False)
    flight.run(2.5)
    assert c.gps.fix_type == 0 and not c.estimate.pos_valid and c.mode == LAND


def test_same_seed_gives_bit_identical_truth_and_another_seed_differs():
    def fly(seed: int) -> np.ndarray:
        flight = Flight(seed=seed)
        flight.take_off(1.0, settle_s=19.0)
        flight.run(0.0)
        truth = flight.copter.truth
        assert flight.copter.t == pytest.approx(20.0)
        return np.concatenate([truth.pos_ned, truth.vel_ned, truth.quat, truth.gyro_body])

    first, second, other = fly(7), fly(7), fly(8)
    assert np.array_equal(first, second)
    assert not np.array_equal(first, other)
