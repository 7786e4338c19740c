"""The simulated fixed wing with its ArduPlane-like autopilot (sitl/plane.py), stepped directly:
take-off, GUIDED loiter around a target, RTL, landing, modes, seeds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.dynamics import WindConfig
from sitl.plane import SimulatedPlane
from sitl.plane_control import AUTO, CIRCLE, FBWA, GUIDED, LOITER, MANUAL, RTL, TAKEOFF

HOME = (1.2966, 103.7764, 10.0)
POS_MASK = 3576  # position only, yaw ignored
LOCAL_NED = 1


def ready(seed: int = 1, wind: WindConfig | None = None) -> SimulatedPlane:
    """On the runway, origin set, GPS in use, GUIDED and armed."""
    plane = SimulatedPlane(seed=seed, home=HOME, wind=wind)
    assert plane.set_origin(*HOME)
    plane.step(2.0)
    assert plane.set_mode(GUIDED) == (True, "")
    assert plane.arm() == (True, "")
    return plane


def target(plane: SimulatedPlane, north: float, east: float, down: float) -> bool:
    zeros = np.zeros(3)
    return plane.set_position_target(LOCAL_NED, POS_MASK, np.array([north, east, down]), zeros, zeros, 0.0, 0.0)


def texts(plane: SimulatedPlane) -> list[str]:
    return [text for _, text in plane.drain_statustext()]


def test_it_arms_in_guided_only_with_a_position_and_starts_in_manual() -> None:
    plane = SimulatedPlane(seed=0, home=HOME)
    assert (plane.mode, plane.mode_name) == (MANUAL, "MANUAL")
    assert plane.set_mode(GUIDED)[0] is False  # no origin, no position
    assert plane.arm()[0] is True  # MANUAL needs none
    assert plane.disarm() == (True, "")
    assert plane.set_mode(AUTO) == (False, "Mode change to AUTO failed: no mission")


def test_it_takes_off_on_the_runway_heading_and_loiters_at_the_height() -> None:
    plane = ready()
    assert plane.takeoff(30.0) == (True, "")
    plane.step(6.0)
    truth = plane.truth
    assert truth.pos_ned[2] < -3.0  # airborne within 6 s
    assert abs(truth.pos_ned[1]) < 3.0  # along the runway (north)
    plane.step(40.0)
    assert "Takeoff complete" in texts(plane)
    assert abs(plane.truth.pos_ned[2] + 30.0) < 3.0
    assert plane.mode == GUIDED and not plane.landed


def test_guided_target_is_reached_and_circled_at_its_height() -> None:
    plane = ready(wind=WindConfig(mean_ned_mps=(0.0, 3.0, 0.0), gust_std_mps=0.5))
    plane.takeoff(30.0)
    plane.step(15.0)
    assert target(plane, 300.0, 200.0, -50.0)
    plane.step(40.0)
    distances, heights, betas = [], [], []
    for _ in range(200):  # 40 s around the target: more than one loiter circle
        plane.step(0.2)
        pos = plane.truth.pos_ned
        distances.append(math.hypot(pos[0] - 300.0, pos[1] - 200.0))
        heights.append(-pos[2])
        betas.append(plane.aero[2])
    radius = 40.0
    assert radius - 8.0 < min(distances) and max(distances) < radius + 8.0
    assert max(abs(h - 50.0) for h in heights) < 3.0
    assert max(abs(b) for b in betas) < math.radians(5.0)


def test_targets_are_ignored_outside_guided_and_without_a_position() -> None:
    plane = ready()
    zeros = np.zeros(3)
    assert not plane.set_position_target(LOCAL_NED, 3527, zeros, np.ones(3), zeros, 0.0, 0.0)  # velocity only
    assert not target(plane, float("nan"), 0.0, -30.0)
    assert plane.nonfinite_rejected == 1
    plane.set_mode(LOITER)
    assert not target(plane, 100.0, 0.0, -30.0)


def test_rtl_circles_home_and_land_brings_it_down_near_home() -> None:
    plane = ready(seed=2, wind=WindConfig(mean_ned_mps=(-2.0, 2.0, 0.0)))
    plane.takeoff(40.0)
    plane.step(20.0)
    target(plane, -200.0, 300.0, -60.0)
    plane.step(30.0)
    assert plane.set_mode(RTL) == (True, "")
    plane.step(40.0)
    assert math.hypot(*plane.truth.pos_ned[:2]) < 60.0
    assert plane.land() == (True, "")
    assert plane.mode == AUTO and plane.landing
    touchdown = None
    for _ in range(240 * 5):
        plane.step(0.2)
        if touchdown is None and plane.truth.pos_ned[2] > -0.01:
            touchdown = plane.truth.pos_ned[:2]
        if plane.landed:
            break
    assert plane.landed and not plane.landing
    assert touchdown is not None and math.hypot(*touchdown) < 40.0  # on the glide slope to home
    assert math.hypot(*plane.truth.pos_ned[:2]) < 100.0  # after the roll-out (here downwind)
    assert "Landed" in texts(plane)
    plane.step(21.0)
    assert not plane.armed  # LAND_DISARMDELAY


@pytest.mark.parametrize("mode", [CIRCLE, LOITER])
def test_circle_and_loiter_hold_the_height(mode: int) -> None:
    plane = ready()
    plane.takeoff(40.0)
    plane.step(25.0)
    assert plane.set_mode(mode) == (True, "")
    plane.step(30.0)
    assert abs(plane.truth.pos_ned[2] + 40.0) < 3.0


def test_in_flight_start_and_takeoff_mode() -> None:
    plane = SimulatedPlane(seed=4, home=HOME, start_ned=(0.0, 0.0, -80.0), start_airspeed_mps=17.0)
    assert plane.armed and not plane.landed and plane.mode == FBWA  # wings level along its heading
    plane.step(5.0)
    assert abs(plane.truth.pos_ned[1]) < 5.0 and plane.truth.pos_ned[0] > 75.0  # straight on north
    assert abs(plane.truth.pos_ned[2] + 80.0) < 3.0
    height = -plane.truth.pos_ned[2]
    assert plane.set_origin(*HOME)  # as the companion does before its mission's mode step
    plane.step(1.0)
    assert plane.set_mode(GUIDED) == (True, "")  # loiters where it is, at that height
    plane.step(20.0)
    assert abs(-plane.truth.pos_ned[2] - height) < 3.0
    assert abs(plane.airspeed_mps - plane.aero[0]) < 1.5  # the pitot
    assert 10.0 < plane.throttle_percent < 60.0
    runway = ready(seed=5)
    assert runway.set_mode(TAKEOFF) == (True, "")
    runway.step(30.0)
    assert abs(runway.truth.pos_ned[2] + 30.0) < 3.0  # TKOFF_ALT


def test_a_seed_gives_the_same_flight() -> None:
    runs = []
    for _ in range(2):
        plane = ready(seed=7, wind=WindConfig(gust_std_mps=1.0))
        plane.takeoff(20.0)
        plane.step(10.0)
        runs.append(plane.truth.pos_ned)
    assert np.array_equal(runs[0], runs[1])


def test_a_rudder_offset_makes_the_flight_uncoordinated_until_it_is_removed() -> None:
    plane = SimulatedPlane(seed=6, home=HOME, start_ned=(0.0, 0.0, -80.0), start_airspeed_mps=17.0)
    plane.step(5.0)
    assert abs(plane.aero[2]) < math.radians(1.0)
    plane.set_rudder(0.15)
    plane.step(3.0)
    assert abs(plane.aero[2]) > math.radians(2.5)
    assert abs(plane.truth.accel_body[1]) > 0.5  # the accelerometer feels the side force
    plane.set_rudder(float("nan"))
    assert plane.nonfinite_rejected == 1
    plane.set_rudder(0.0)
    plane.step(3.0)
    assert abs(plane.aero[2]) < math.radians(1.0)


def test_a_target_sent_before_the_take_off_is_flown_after_it() -> None:
    plane = ready(seed=8)
    assert target(plane, -150.0, 250.0, -45.0)
    plane.takeoff(25.0)
    plane.step(70.0)
    pos = plane.truth.pos_ned
    assert abs(math.hypot(pos[0] + 150.0, pos[1] - 250.0) - 40.0) < 10.0
    assert abs(pos[2] + 45.0) < 4.0
