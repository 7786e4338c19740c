"""The pure parts of missions: estimate classification, geofence, time warp, flight planning, and
mission files (errors name file, key and line)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.config import GeofenceConfig
from companion.control.trajectory import plan
from companion.health import State
from companion.messages import PoseEstimate
from companion.mission.failsafe import Geofence, classify_estimate, stopping_point
from companion.mission.flight import TrajectoryFlight, plan_flight
from companion.mission.steps import FlyStep, Waypoint, load_mission
from companion.mission.timeline import Timeline, TimeWarp
from companion.schema import SchemaError
from tests.conftest import REPO

OK = (State.OK, "")


def estimate(t: float, position: tuple[float, float, float] = (1.0, 2.0, -1.0)) -> PoseEstimate:
    return PoseEstimate(t, np.array(position), (0.0, 0.0, 0.0), np.eye(6) * 1e-4)


# -- estimate status --------------------------------------------------------------------------

def test_no_estimate_or_an_old_one_is_lost() -> None:
    assert classify_estimate(10.0, None, OK, 0.5).state == State.LOST
    assert classify_estimate(10.0, estimate(9.4), OK, 0.5).state == State.LOST
    assert "0.60 s" in classify_estimate(10.0, estimate(9.4), OK, 0.5).reason
    assert classify_estimate(10.0, estimate(9.6), OK, 0.5).state == State.OK


def test_a_non_finite_estimate_is_lost() -> None:
    assert classify_estimate(10.0, estimate(10.0, (math.nan, 0.0, -1.0)), OK, 0.5).state == State.LOST


def test_a_degraded_nav_component_slows_down_with_its_reason() -> None:
    status = classify_estimate(10.0, estimate(10.0), (State.DEGRADED, "nav:lidar: 1 corner matched"), 0.5)
    assert status == (State.DEGRADED, "nav:lidar: 1 corner matched")


# -- geofence ---------------------------------------------------------------------------------

def test_the_geofence_is_the_map_box_inset_with_a_ceiling() -> None:
    fence = Geofence.from_config(GeofenceConfig(inset_m=0.3, ceiling_m=2.5), ((0.0, 0.0), (10.0, 10.0)))
    assert fence == Geofence(0.3, 0.3, 9.7, 9.7, 2.5)
    assert fence.violation(np.array([5.0, 5.0, -1.0])) is None
    assert "outside the fence x 0.3..9.7" in fence.violation(np.array([9.8, 5.0, -1.0]))
    assert "ceiling" in fence.violation(np.array([5.0, 5.0, -2.6]))
    path = np.array([[1.0, 1.0, -1.0], [5.0, 9.9, -1.0], [9.9, 9.9, -1.0]])
    assert "(5.00, 9.90)" in fence.first_violation(path)


def test_an_explicit_box_wins_and_no_box_means_no_fence() -> None:
    box = GeofenceConfig(box_ned_m=((-1.0, -2.0), (3.0, 4.0)), inset_m=0.0)
    assert Geofence.from_config(box, ((0.0, 0.0), (10.0, 10.0))) == Geofence(-1.0, -2.0, 3.0, 4.0, 3.0)
    assert Geofence.from_config(GeofenceConfig(), None) is None
    assert Geofence.from_config(GeofenceConfig(enabled=False), ((0.0, 0.0), (10.0, 10.0))) is None
    with pytest.raises(ValueError, match="leaves nothing"):
        Geofence.from_config(GeofenceConfig(inset_m=2.0), ((0.0, 0.0), (3.0, 10.0)))


# -- time warp and braking ---------------------------------------------------------------------

def test_time_warp_runs_at_clock_rate_and_ramps_smoothly_to_a_slower_rate() -> None:
    warp = TimeWarp(ramp_per_s=0.5)
    for _ in range(50):
        warp.advance(0.02, 1.0)
    assert warp.tau == pytest.approx(1.0) and warp.rate == 1.0
    rates = []
    for _ in range(100):
        warp.advance(0.02, 0.5)
        rates.append(warp.rate)
    assert rates[-1] == pytest.approx(0.5) and rates[49] == pytest.approx(0.5)  # 1 s at 0.5 per s
    assert np.all(np.abs(np.diff(rates)) <= 0.5 * 0.02 + 1e-12)
    assert warp.tau == pytest.approx(1.0 + 0.75 + 0.5)  # the ramp's average rate, then half speed


def test_time_warp_scales_velocity_and_acceleration_like_the_chain_rule() -> None:
    traj = plan([[0, 0, -1], [4, 0, -1]], 0.5, 0.5)
    warp = TimeWarp(ramp_per_s=0.5)
    warp.tau, warp.rate = 3.0, 0.6
    warp.advance(0.02, 0.5)
    ref = traj.sample(warp.tau)
    v, a = warp.scale(ref.velocity, ref.acceleration)
    np.testing.assert_allclose(v, ref.velocity * warp.rate)
    np.testing.assert_allclose(a, ref.acceleration * warp.rate ** 2 + ref.velocity * (-0.5))


def test_the_timeline_pauses_at_a_hold_at_rest_and_finishes_at_the_end() -> None:
    traj = plan([[0, 0, -1], [2, 0, -1], [2, 2, -1]], 0.5, 0.5, stops=[1])
    t_stop = float(traj.waypoint_times[1])
    timeline = Timeline(traj, {0: (t_stop, 1.0)})
    steps = 0
    while not timeline.holding:
        timeline.advance(0.02, 1.0)
        steps += 1
    assert timeline.tau == t_stop and t_stop <= steps * 0.02 < t_stop + 0.02 + 1e-9
    reference = timeline.reference()
    np.testing.assert_allclose(reference.position, [2, 0, -1], atol=1e-9)
    assert np.all(reference.velocity == 0.0) and np.all(reference.acceleration == 0.0) and reference.yaw_rate == 0.0
    for _ in range(50):  # one second of hold: tau stands still
        timeline.advance(0.02, 1.0)
    assert timeline.tau == t_stop
    while not timeline.finished:
        timeline.advance(0.02, 1.0)
    assert timeline.tau == pytest.approx(traj.duration)


def test_stopping_point_is_the_braking_distance_ahead_at_the_same_height() -> None:
    np.testing.assert_allclose(stopping_point(np.array([1.0, 2.0, -1.0]), np.array([1.0, 0.0, 0.3]), 1.0),
                               [1.5, 2.0, -1.0])


# -- planning a fly step -----------------------------------------------------------------------

def test_a_flight_plan_stops_at_holds_and_stops_and_keeps_per_leg_speeds() -> None:
    step = FlyStep(waypoints=[Waypoint((3.0, 1.0, -1.0), stop=True),
                              Waypoint((3.0, 3.0, -1.0), speed_mps=0.2, hold_s=2.0), Waypoint((1.0, 3.0, -1.0))])
    flight = plan_flight(step, np.array([1.0, 1.0, -1.0]), tuple(step.waypoints), 0.0)
    assert len(flight.waypoints) == 3
    traj = flight.trajectory
    assert {1, 2} <= set(traj.stops)
    np.testing.assert_allclose(traj.sample(flight.time_of(1)).velocity, 0.0, atol=1e-9)
    assert traj.segment_peaks[1, 0] <= 0.2 + 1e-9  # the slow leg


def test_after_a_recovered_loss_the_held_waypoint_the_ones_ahead_and_the_last_are_left_to_fly() -> None:
    a, b, c = Waypoint((3.0, 1.0, -1.0)), Waypoint((3.0, 3.0, -1.0), hold_s=4.0), Waypoint((1.0, 3.0, -1.0))
    flight = plan_flight(FlyStep(waypoints=[a, b, c]), np.array([1.0, 1.0, -1.0]), (a, b, c), 0.0)
    timeline = Timeline(flight.trajectory, {1: (flight.time_of(1), 4.0)})
    while timeline.tau < flight.time_of(0) + 0.5:  # past a: b and c are ahead
        timeline.advance(0.02, 1.0)
    assert TrajectoryFlight._left_to_fly(flight, timeline) == (b, c)
    while not timeline.holding:
        timeline.advance(0.02, 1.0)
    for _ in range(50):  # 1 s of b's 4 s hold
        timeline.advance(0.02, 1.0)
    left = TrajectoryFlight._left_to_fly(flight, timeline)
    assert [w.position for w in left] == [b.position, c.position] and left[0].hold_s == pytest.approx(3.0)
    while not timeline.finished:
        timeline.advance(0.02, 1.0)
    assert TrajectoryFlight._left_to_fly(flight, timeline) == (c,)  # the end: arrive there all the same


# -- mission files -----------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["hover", "survey-points", "patrol"])
def test_the_shipped_missions_load(name: str) -> None:
    mission = load_mission(REPO / "config" / "missions" / f"{name}.yaml")
    assert mission.name == name and mission.steps[-1].land is not None


@pytest.mark.parametrize("text, where", [
    ("name: m\nsteps:\n  - fly: {waypoints: []}\n", "mission.yaml:3: steps[0].fly.waypoints: needs at least one"),
    ("name: m\nsteps:\n  - fly:\n      yaw: fixed\n      waypoints: [{position: [1, 2, -1]}]\n",
     "mission.yaml:4: steps[0].fly.yaw_deg: yaw: fixed needs yaw_deg"),
    ("name: m\nsteps:\n  - fly:\n      waypoints:\n        - {position: [1, 2]}\n", "mission.yaml:5: steps[0].fly.waypoints[0].position"),
    ("name: m\nsteps:\n  - fly:\n      waypoints:\n        - {position: [1, 2, -1], speed_mps: 9}\n",
     "mission.yaml:5: steps[0].fly.waypoints[0].speed_mps: must be within [0.05, 5]"),
    ("name: m\nsteps:\n  - goto: {position: [1, 2, -1]}\n", "mission.yaml:3: steps[0].goto"),
    ("name: m\nsteps:\n  - fly:\n      waypoints:\n        - {position: [1, 2, -1]}\n        - {position: [1, 2, -1]}\n",
     "mission.yaml:6: steps[0].fly.waypoints[1].position: repeats waypoints[0]"),
])
def test_a_mission_file_with_errors_is_rejected_with_file_key_and_line(tmp_path: Path, text: str, where: str) -> None:
    path = tmp_path / "mission.yaml"
    path.write_text(text)
    with pytest.raises(SchemaError) as info:
        load_mission(path)
    assert where in str(info.value)
