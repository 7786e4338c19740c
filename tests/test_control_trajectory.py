"""Smooth trajectories (companion/control/trajectory.py): interpolation, continuity, rest at the
ends, limits by dense sampling on the patrol mission, window/door passes in the arena, minimum
snap vs minimum jerk, straight lines, yaw references and degenerate inputs."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.control.trajectory import Trajectory, from_segment_times, plan
from companion.mission.steps import load_mission
from companion.world import load_world
from tests.conftest import REPO

KINDS = ("minimum_jerk", "minimum_snap")
V_MAX, A_MAX = 0.5, 0.5


def patrol() -> tuple[np.ndarray, list]:
    """The takeoff point (the arena's start pose at the 1 m takeoff height) then the waypoints of
    config/missions/patrol.yaml's fly step (speeds filled in from the step); and those waypoints."""
    mission = load_mission(REPO / "config/missions/patrol.yaml")
    world = load_world(REPO / "config/worlds/arena.yaml")
    takeoff = next(s.takeoff for s in mission.steps if s.takeoff)
    fly = next(s.fly for s in mission.steps if s.fly)
    waypoints = [dataclasses.replace(w, speed_mps=w.speed_mps or fly.speed_mps) for w in fly.waypoints]
    start = [world.start[0], world.start[1], -takeoff.altitude_m]
    return np.array([start] + [list(w.position) for w in waypoints], dtype=float), waypoints


def hold_indices(waypoints: list) -> tuple[int, ...]:
    return tuple(i + 1 for i, w in enumerate(waypoints) if w.hold_s > 0 or w.stop)


@pytest.fixture(scope="module", params=KINDS)
def patrol_traj(request) -> Trajectory:
    w, _ = patrol()
    return plan(w, V_MAX, A_MAX, kind=request.param, yaw_mode="face_next")


def left(t: float) -> float:
    """The float just below t: evaluation there uses the segment ending at t."""
    return float(np.nextafter(t, -np.inf))


def dense(traj: Trajectory, dt: float = 0.005) -> np.ndarray:
    return np.unique(np.concatenate([np.arange(0.0, traj.duration, dt), traj.joint_times]))


# --- interpolation and continuity -------------------------------------------------------------

def test_passes_through_every_waypoint(patrol_traj: Trajectory) -> None:
    w, gotos = patrol()
    t = patrol_traj.waypoint_times
    assert t.shape == (len(w),) and t[0] == 0.0 and t[-1] == pytest.approx(patrol_traj.duration)
    assert np.all(np.diff(t) > 0)
    np.testing.assert_allclose(patrol_traj.sample_many(t).position, w, atol=1e-6)
    for i in range(1, len(w) - 1):  # from both sides of the joint
        np.testing.assert_allclose(patrol_traj.derivative(left(t[i]), 0), w[i], atol=1e-6)
    for i, g in enumerate(gotos, start=1):  # the window and the doors included
        assert patrol_traj.closest_approach(i) <= 1e-6
    # and every inserted joint lies on its straight leg
    assert len(patrol_traj.joints) >= len(w)


def test_continuous_derivatives_at_every_joint(patrol_traj: Trajectory) -> None:
    orders = range(3) if patrol_traj.kind == "minimum_jerk" else range(4)  # p, v, a (, jerk)
    for t in patrol_traj.joint_times[1:-1]:
        for m in orders:
            before, after = patrol_traj.derivative(left(t), m), patrol_traj.derivative(t, m)
            np.testing.assert_allclose(before, after, atol=1e-7, err_msg=f"order {m} at t={t:.3f}")


def test_sample_and_sample_many_agree(patrol_traj: Trajectory) -> None:
    ts = np.linspace(-1.0, patrol_traj.duration + 1.0, 37)
    many = patrol_traj.sample_many(ts)
    assert many.position.shape == (37, 3) and np.shape(many.yaw_rad) == (37,)
    for k, t in enumerate(ts):
        one = patrol_traj.sample(t)
        np.testing.assert_allclose(one.position, many.position[k], atol=1e-12)
        np.testing.assert_allclose(one.velocity, many.velocity[k], atol=1e-12)
        np.testing.assert_allclose(one.acceleration, many.acceleration[k], atol=1e-12)
        assert one.yaw_rad == pytest.approx(many.yaw_rad[k]) and one.yaw_rate == pytest.approx(many.yaw_rate[k])


@pytest.mark.parametrize("kind", KINDS)
def test_starts_and_ends_at_rest(kind: str) -> None:
    w, gotos = patrol()
    for stops in ((), hold_indices(gotos)):
        traj = plan(w, V_MAX, A_MAX, kind=kind, stops=stops)
        rest_orders = (1, 2) if kind == "minimum_jerk" else (1, 2, 3)
        for t in (0.0, traj.duration):
            for m in rest_orders:
                np.testing.assert_allclose(traj.derivative(t, m), 0.0, atol=1e-9)
        for i in stops:  # the holds of the mission: at rest there too
            for m in rest_orders:
                np.testing.assert_allclose(traj.derivative(traj.waypoint_times[i], m), 0.0, atol=1e-9)
        # outside the trajectory: held at the ends
        before, after = traj.sample(-5.0), traj.sample(traj.duration + 5.0)
        np.testing.assert_allclose(before.position, w[0], atol=1e-9)
        np.testing.assert_allclose(after.position, w[-1], atol=1e-9)
        for ref in (before, after):
            assert not ref.velocity.any() and not ref.acceleration.any()


def test_single_segment_is_the_classic_polynomial() -> None:
    """Rest to rest over one segment: 10-15-6 (minimum jerk) and 35-84-70-20 (minimum snap)."""
    a, b = np.array([1.0, 2.0, -1.0]), np.array([3.0, -1.0, -2.0])
    tau = np.linspace(0, 1, 11)
    shapes = {"minimum_jerk": 10 * tau**3 - 15 * tau**4 + 6 * tau**5,
              "minimum_snap": 35 * tau**4 - 84 * tau**5 + 70 * tau**6 - 20 * tau**7}
    for kind, s in shapes.items():
        traj = from_segment_times([a, b], 4.0, kind)
        np.testing.assert_allclose(traj.sample_many(4.0 * tau).position, a + s[:, None] * (b - a), atol=1e-12)


# --- limits ------------------------------------------------------------------------------------

def test_limits_respected_on_the_patrol_by_dense_sampling(patrol_traj: Trajectory) -> None:
    ts = dense(patrol_traj)
    speed = np.linalg.norm(patrol_traj.derivative(ts, 1), axis=1)
    accel = np.linalg.norm(patrol_traj.derivative(ts, 2), axis=1)
    jerk = np.linalg.norm(patrol_traj.derivative(ts, 3), axis=1)
    assert speed.max() <= V_MAX + 1e-9 and accel.max() <= A_MAX + 1e-9
    # the reported peaks are exact (polynomial extrema): never below what sampling finds
    assert speed.max() <= patrol_traj.max_speed + 1e-12 and patrol_traj.max_speed <= V_MAX * (1 + 1e-9)
    assert accel.max() <= patrol_traj.max_acceleration + 1e-12
    assert jerk.max() <= patrol_traj.max_jerk + 1e-12
    assert patrol_traj.max_speed == pytest.approx(speed.max(), rel=1e-3)
    # and time-efficient: the binding limit is reached
    assert max(patrol_traj.max_speed / V_MAX, patrol_traj.max_acceleration / A_MAX) == pytest.approx(1.0, abs=1e-6)
    # finite-difference check of the derivatives themselves
    p = patrol_traj.derivative(ts[:2000], 0)
    v = patrol_traj.derivative(ts[:2000], 1)
    np.testing.assert_allclose(np.gradient(p, ts[:2000], axis=0)[1:-1], v[1:-1], atol=1e-4)


@pytest.mark.parametrize("kind", KINDS)
def test_per_leg_speed_and_jerk_limits(kind: str) -> None:
    """The mission's own per-leg speeds (0.3 m/s through doors and the window) and a jerk limit."""
    w, gotos = patrol()
    v_legs = np.array([g.speed_mps for g in gotos])
    traj = plan(w, v_legs, A_MAX, j_max_mps3=0.5, kind=kind, stops=hold_indices(gotos))
    for i, v_leg in enumerate(v_legs):
        ts = np.arange(traj.waypoint_times[i], traj.waypoint_times[i + 1], 0.005)
        assert np.linalg.norm(traj.derivative(ts, 1), axis=1).max() <= v_leg + 1e-9, f"leg {i}"
    ts = dense(traj)
    assert np.linalg.norm(traj.derivative(ts, 2), axis=1).max() <= A_MAX + 1e-9
    assert np.linalg.norm(traj.derivative(ts, 3), axis=1).max() <= 0.5 + 1e-9
    assert traj.max_jerk <= 0.5 * (1 + 1e-9)


def test_slower_limits_give_a_longer_trajectory() -> None:
    w, _ = patrol()
    fast, slow = plan(w, 1.0, 1.0), plan(w, 0.25, 0.25)
    assert slow.duration > 2 * fast.duration
    assert slow.max_speed <= 0.25 * (1 + 1e-9) and fast.max_speed <= 1.0 * (1 + 1e-9)


# --- geometry: corridor, window and doors ------------------------------------------------------

def wall_clearance(positions: np.ndarray) -> float:
    """Smallest horizontal distance from the arena's walls at each sample's own height (the
    window and the doors are gaps at their heights)."""
    world = load_world(REPO / "config/worlds/arena.yaml")
    best = math.inf
    heights = np.round(-positions[:, 2], 2)
    for h in np.unique(heights):
        segs = world.segments_at(float(h))
        q = positions[heights == h][:, None, :2]
        a, b = segs[None, :, :2], segs[None, :, 2:]
        ab = b - a
        s = np.clip(((q - a) * ab).sum(-1) / (ab * ab).sum(-1), 0, 1)
        best = min(best, float(np.linalg.norm(q - (a + s[..., None] * ab), axis=-1).min()))
    return best


@pytest.mark.parametrize("kind", KINDS)
def test_patrol_stays_in_its_corridor_and_clear_of_the_walls(kind: str) -> None:
    w, gotos = patrol()
    polyline = np.concatenate([np.linspace(w[i], w[i + 1], 400) for i in range(len(w) - 1)])
    assert wall_clearance(polyline) >= 0.45 - 1e-6  # what the mission author planned: door half-widths
    for stops in ((), hold_indices(gotos)):
        traj = plan(w, V_MAX, A_MAX, kind=kind, stops=stops, corridor_m=0.15, tolerances=0.15)
        for i in range(len(w) - 1):
            assert traj.max_deviation(i) <= 0.15 + 0.005, f"leg {i}"
        positions = traj.derivative(dense(traj, 0.01), 0)
        assert wall_clearance(positions) >= 0.30  # 0.45 - the corridor: through the doors and the window
        # every inserted joint lies on a straight leg of the waypoint list
        for p in traj.joints:
            d = min(np.linalg.norm(np.cross(p - w[i], w[i + 1] - w[i])) / np.linalg.norm(w[i + 1] - w[i])
                    for i in range(len(w) - 1))
            assert d < 1e-9


def test_without_the_corridor_the_patrol_swings_wide() -> None:
    """Why the corridor exists: flown through, the sharp corner at (9.0, 5.2) pulls the spline
    a metre off its leg, to the arena's north wall."""
    w, _ = patrol()
    traj = plan(w, V_MAX, A_MAX, kind="minimum_snap", corridor_m=None)
    assert len(traj.joints) == len(w)
    assert max(traj.max_deviation(i) for i in range(len(w) - 1)) > 0.5


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("corridor", [0.05, 0.01])
def test_hairpins_within_a_tight_corridor(kind: str, corridor: float) -> None:
    """Near-reversals flown fast: split legs, and when that is not enough, stops at the corners."""
    w = np.array([[0, 0, -1], [5, 0, -1], [0, 0.3, -1], [5, 0.6, -1], [5, 3, -1]], dtype=float)
    traj = plan(w, 2.0, 3.0, kind=kind, corridor_m=corridor)
    for i in range(len(w) - 1):
        assert traj.max_deviation(i) <= corridor * 1.02 + 1e-9, f"leg {i}"
    np.testing.assert_allclose(traj.sample_many(traj.waypoint_times).position, w, atol=1e-6)
    for i in traj.stops:
        np.testing.assert_allclose(traj.derivative(traj.waypoint_times[i], 1), 0.0, atol=1e-9)
    assert traj.max_speed <= 2.0 * (1 + 1e-9) and traj.max_acceleration <= 3.0 * (1 + 1e-9)
    if kind == "minimum_snap" and corridor == 0.01:
        assert traj.stops  # this one needs them


def test_random_waypoints_keep_every_promise() -> None:
    rng = np.random.default_rng(7)
    for case in range(12):
        n = int(rng.integers(2, 10))
        w = rng.uniform([-5, -5, -3], [5, 5, -0.5], (n, 3))
        kind = KINDS[case % 2]
        v, a, j = rng.uniform(0.2, 3), rng.uniform(0.2, 5), (None if case % 3 else rng.uniform(0.5, 5))
        stops = [i for i in range(1, n - 1) if rng.random() < 0.2]
        traj = plan(w, v, a, j, kind=kind, stops=stops, yaw_mode="face_next", initial_yaw_rad=rng.uniform(-3, 3))
        np.testing.assert_allclose(traj.sample_many(traj.waypoint_times).position, w, atol=1e-6)
        ts = dense(traj, traj.duration / 20000)
        assert np.linalg.norm(traj.derivative(ts, 1), axis=1).max() <= v * (1 + 1e-9)
        assert np.linalg.norm(traj.derivative(ts, 2), axis=1).max() <= a * (1 + 1e-9)
        if j is not None:
            assert np.linalg.norm(traj.derivative(ts, 3), axis=1).max() <= j * (1 + 1e-9)
        assert max(traj.max_deviation(i) for i in range(n - 1)) <= 0.15 * 1.02
        assert set(stops) <= set(traj.stops)
        assert_rate_limited(traj, 0.5, 0.05)


def test_window_pass_height() -> None:
    """Through window-sw-se (0.8-1.6 m above the floor, 1.2 m wide at x = 3.5) at 1.2 m."""
    w, _ = patrol()
    world = load_world(REPO / "config/worlds/arena.yaml")
    window = next(o for o in world.openings if o.name == "window-sw-se")
    for kind in KINDS:
        traj = plan(w, V_MAX, A_MAX, kind=kind)
        ts = dense(traj, 0.002)
        p = traj.derivative(ts, 0)
        crossing = np.flatnonzero(np.diff(p[:, 1] >= window.center[1]))
        crossing = [k for k in crossing if p[k, 0] < 5.0]  # the SW|SE wall runs x = 0..5 at y = 5
        assert len(crossing) == 1
        x, z = p[crossing[0], 0], p[crossing[0], 2]
        assert abs(x - window.center[0]) <= window.width_m / 2 - 0.3
        assert window.bottom_m + 0.2 <= -z <= window.top_m - 0.2


# --- optimality --------------------------------------------------------------------------------

def rest_to_rest_snap(traj: Trajectory, h: float) -> float:
    """Integrated squared snap of the whole motion, at rest before and after, by finite
    differences of the jerk at step h: a jerk step (an impulse of snap) adds step^2 / h."""
    ts = np.arange(-1.0, traj.duration + 1.0, h)
    snap = np.diff(traj.derivative(ts, 3), axis=0) / h
    return float((snap**2).sum() * h)


def test_minimum_snap_is_smoother_than_minimum_jerk_on_the_same_times() -> None:
    """Integrated squared snap from rest to rest, on the same segment times: the minimum-snap
    profile's is finite (its jerk is continuous, zero at the ends), the minimum-jerk profile's is
    not: its jerk steps from rest to a nonzero value at the start and back at the end. (Over the
    polynomial pieces alone the minimum-jerk one can score lower, precisely because it skips the
    jerk = 0 end conditions: on the patrol 0.036 against 0.046.)"""
    w, gotos = patrol()
    times = plan(w, V_MAX, A_MAX, kind="minimum_jerk", corridor_m=None).segment_times
    jerk = from_segment_times(w, times, "minimum_jerk")
    snap = from_segment_times(w, times, "minimum_snap")
    np.testing.assert_allclose(jerk.joint_times, snap.joint_times)
    assert np.linalg.norm(jerk.derivative(0.0, 3)) > 0.01 and np.allclose(snap.derivative(0.0, 3), 0.0, atol=1e-12)
    s1, s2 = rest_to_rest_snap(snap, 2e-3), rest_to_rest_snap(snap, 1e-3)
    j1, j2 = rest_to_rest_snap(jerk, 2e-3), rest_to_rest_snap(jerk, 1e-3)
    assert s2 == pytest.approx(snap.cost(4), rel=0.02) and s1 == pytest.approx(s2, rel=0.02)  # converges
    assert j2 > 1.8 * j1  # diverges like 1 / h: the jerk steps
    assert 10 * s2 < j1
    # and each is optimal for its own cost among curves its problem allows: the min-jerk spline
    # is C2 with v = a = 0 at the ends, which the min-snap spline also is
    assert jerk.cost(3) < snap.cost(3)
    for stops in ((), hold_indices(gotos)):
        for traj in (from_segment_times(w, times, "minimum_jerk", stops=stops),
                     from_segment_times(w, times, "minimum_snap", stops=stops)):
            ts = np.unique(np.concatenate([np.linspace(0, traj.duration, 400001), traj.joint_times]))
            for m in (3, 4):  # cost() agrees with dense numerical integration (trapezoid rule)
                f = (traj.derivative(ts, m) ** 2).sum(axis=1)
                numeric = float(np.sum((f[1:] + f[:-1]) / 2 * np.diff(ts)))
                assert traj.cost(m) == pytest.approx(numeric, rel=2e-3)


def test_perturbing_the_solution_increases_its_cost() -> None:
    """The solved joint derivatives are the minimum: moving one interior velocity costs more."""
    w = np.array([[0, 0, -1], [2, 1, -1.5], [3, 3, -1], [1, 4, -1.2]], dtype=float)
    times = np.array([3.0, 2.5, 3.5])
    for kind, order in (("minimum_jerk", 3), ("minimum_snap", 4)):
        best = from_segment_times(w, times, kind).cost(order)
        # a different (suboptimal) spline: the same waypoints stopping in the middle
        assert from_segment_times(w, times, kind, stops=[1]).cost(order) > best
        assert from_segment_times(w, times, kind, stops=[2]).cost(order) > best


# --- straight lines ----------------------------------------------------------------------------

@pytest.mark.parametrize("kind", KINDS)
def test_straight_line_gives_a_straight_path(kind: str) -> None:
    a, b = np.array([1.0, 1.0, -1.0]), np.array([6.0, 4.0, -2.5])
    s = np.array([0.0, 0.1, 0.35, 0.4, 0.8, 1.0])  # uneven spacing
    w = a + s[:, None] * (b - a)
    traj = plan(w, V_MAX, A_MAX, kind=kind)
    assert len(traj.joints) == len(w)  # nothing to correct
    p = traj.derivative(dense(traj, 0.01), 0)
    u = (b - a) / np.linalg.norm(b - a)
    along = (p - a) @ u
    lateral = np.linalg.norm((p - a) - along[:, None] * u, axis=1)
    assert lateral.max() < 1e-9
    assert along.min() >= -1e-9 and along.max() <= np.linalg.norm(b - a) + 1e-9  # no overshoot past the ends
    v = traj.derivative(dense(traj, 0.01), 1)
    np.testing.assert_allclose(np.cross(v, u), 0.0, atol=1e-9)  # the velocity points along the line
    assert traj.max_speed <= V_MAX * (1 + 1e-9)


def test_non_consecutive_repeats_are_allowed() -> None:
    """A loop back to the start is fine (only consecutive repeats are degenerate)."""
    w = [[0, 0, -1], [2, 0, -1], [2, 2, -1], [0, 0, -1]]
    traj = plan(w, V_MAX, A_MAX)
    np.testing.assert_allclose(traj.sample_many(traj.waypoint_times).position, w, atol=1e-6)


# --- yaw -----------------------------------------------------------------------------------------

def assert_rate_limited(traj: Trajectory, rate_max: float, dt: float) -> np.ndarray:
    ts = np.arange(0.0, traj.yaw_settled_time + 1.0, dt)
    ref = traj.sample_many(ts)
    yaw = np.asarray(ref.yaw_rad)
    assert np.all(yaw >= -math.pi) and np.all(yaw < math.pi)
    step = np.abs(np.remainder(np.diff(yaw) + math.pi, 2 * math.pi) - math.pi)
    assert step.max() <= rate_max * dt + 1e-9
    assert np.abs(ref.yaw_rate).max() <= rate_max + 1e-12
    return ts


def test_face_next_wraps_across_pi() -> None:
    """Legs heading 170 deg then -170 deg: a 20 deg turn through +-pi, not 340 deg back."""
    h1, h2 = math.radians(170), math.radians(-170)
    w = np.array([[0, 0, -1], [3 * math.cos(h1), 3 * math.sin(h1), -1]])
    w = np.vstack([w, w[-1] + [3 * math.cos(h2), 3 * math.sin(h2), -1 - w[-1][2]]])
    rate = 0.3
    traj = plan(w, V_MAX, A_MAX, yaw_mode="face_next", initial_yaw_rad=h1, yaw_rate_max_rad_s=rate)
    ts = assert_rate_limited(traj, rate, 0.02)
    yaw = np.asarray(traj.sample_many(ts).yaw_rad)
    unwrapped = np.unwrap(yaw)
    assert unwrapped.max() - unwrapped.min() == pytest.approx(math.radians(20), abs=1e-6)
    assert np.all(np.diff(unwrapped) >= -1e-12)  # turns one way only, east through south
    assert traj.sample(traj.duration + 100.0).yaw_rad == pytest.approx(h2, abs=1e-6)
    assert traj.sample(traj.waypoint_times[1] / 2).yaw_rad == pytest.approx(h1, abs=1e-9)  # first leg: no turn
    assert traj.yaw_settled_time >= traj.duration


def test_face_next_on_the_patrol(patrol_traj: Trajectory) -> None:
    w, _ = patrol()
    assert_rate_limited(patrol_traj, 0.5, 0.01)
    ts = np.sort(np.random.default_rng(3).uniform(0, patrol_traj.duration, 4000))
    yaw = np.asarray(patrol_traj.sample_many(ts).yaw_rad)
    step = np.abs(np.remainder(np.diff(yaw) + math.pi, 2 * math.pi) - math.pi)
    assert np.all(step <= 0.5 * np.diff(ts) + 1e-9)
    # the yaw rate is the derivative of the yaw
    fine = np.arange(0.0, patrol_traj.duration, 0.01)
    ref = patrol_traj.sample_many(fine)
    fd = np.remainder(np.diff(ref.yaw_rad) + math.pi, 2 * math.pi) - math.pi
    np.testing.assert_allclose(fd / 0.01, (ref.yaw_rate[1:] + ref.yaw_rate[:-1]) / 2, atol=0.011)
    # long legs are flown facing their waypoint by their end
    for i in range(len(w) - 1):
        d = w[i + 1] - w[i]
        if patrol_traj.waypoint_times[i + 1] - patrol_traj.waypoint_times[i] > 8.0:
            yaw_end = patrol_traj.sample(patrol_traj.waypoint_times[i + 1] - 0.05).yaw_rad
            assert math.remainder(yaw_end - math.atan2(d[1], d[0]), 2 * math.pi) == pytest.approx(0, abs=1e-3)


def test_hold_and_fixed_yaw() -> None:
    w, _ = patrol()
    hold = plan(w, V_MAX, A_MAX, yaw_mode="hold", initial_yaw_rad=3.5)  # wrapped into [-pi, pi)
    ref = hold.sample_many(np.linspace(-1, hold.duration + 1, 50))
    np.testing.assert_allclose(ref.yaw_rad, 3.5 - 2 * math.pi)
    assert not np.any(ref.yaw_rate)
    fixed = plan(w, V_MAX, A_MAX, yaw_mode="fixed", yaw_fixed_rad=-math.pi / 2, initial_yaw_rad=0.0,
                 yaw_rate_max_rad_s=0.4)
    assert_rate_limited(fixed, 0.4, 0.01)
    assert fixed.sample(0.0).yaw_rad == pytest.approx(0.0)
    assert fixed.sample(10.0).yaw_rad == pytest.approx(-math.pi / 2, abs=1e-9)
    assert fixed.sample(fixed.duration).yaw_rate == 0.0


# --- degenerate inputs -------------------------------------------------------------------------

GOOD = [[0, 0, -1], [1, 0, -1], [1, 1, -1]]


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"waypoints": [[0, 0, -1]]}, "at least 2 waypoints"),
    ({"waypoints": np.zeros((0, 3))}, "at least 2 waypoints"),
    ({"waypoints": [[0, 0, -1], [1, 0, -1], [1, 0, -1], [2, 0, -1]]}, "waypoints 1 and 2 are repeated"),
    ({"waypoints": [[0, 0, -1], [0, 0, -1]]}, "waypoints 0 and 1 are repeated"),
    ({"waypoints": [[0, 0, -1], [1, float("nan"), -1], [2, 0, -1]]}, "waypoint 1 is not finite"),
    ({"waypoints": [[0, 0, -1], [1, 0, float("inf")]]}, "waypoint 1 is not finite"),
    ({"waypoints": [[0, 0], [1, 0]]}, r"\(N, 3\)"),
    ({"waypoints": [[0, 0, -1], [1, 0]]}, r"\(N, 3\)"),
    ({"v_max_mps": 0.0}, "v_max_mps must be finite and > 0"),
    ({"v_max_mps": float("nan")}, "v_max_mps must be finite and > 0"),
    ({"v_max_mps": [0.5, 0.5, 0.5]}, "one per leg"),
    ({"a_max_mps2": -1.0}, "a_max_mps2 must be finite and > 0"),
    ({"j_max_mps3": 0.0}, "j_max_mps3 must be finite and > 0"),
    ({"kind": "minimum_crackle"}, "kind must be"),
    ({"yaw_mode": "spin"}, "yaw_mode must be"),
    ({"yaw_mode": "fixed"}, "needs yaw_fixed_rad"),
    ({"yaw_mode": "fixed", "yaw_fixed_rad": float("nan")}, "yaw_fixed_rad must be finite"),
    ({"yaw_fixed_rad": 1.0}, "only used with yaw_mode 'fixed'"),
    ({"initial_yaw_rad": float("inf")}, "initial_yaw_rad must be finite"),
    ({"yaw_rate_max_rad_s": 0.0}, "yaw_rate_max_rad_s must be finite and > 0"),
    ({"tolerances": [0.1, -0.1, 0.1]}, "tolerances must be finite and >= 0"),
    ({"tolerances": [0.1, 0.1]}, "one per waypoint"),
    ({"stops": [0]}, "interior waypoint indices"),
    ({"stops": [2]}, "interior waypoint indices"),
    ({"corridor_m": 0.0}, "corridor_m must be finite and > 0"),
])
def test_degenerate_inputs_raise_value_error(kwargs: dict, message: str) -> None:
    args = {"waypoints": GOOD, "v_max_mps": V_MAX, "a_max_mps2": A_MAX} | kwargs
    with pytest.raises(ValueError, match=message):
        plan(**args)


def test_bad_queries_raise_value_error() -> None:
    traj = plan(GOOD, V_MAX, A_MAX)
    with pytest.raises(ValueError, match="finite"):
        traj.sample(float("nan"))
    with pytest.raises(ValueError, match="finite"):
        traj.sample_many([0.0, float("inf")])
    with pytest.raises(ValueError, match="out of range"):
        traj.closest_approach(3)
    with pytest.raises(ValueError, match="out of range"):
        traj.max_deviation(2)
    with pytest.raises(ValueError, match="segment_times must be finite and > 0"):
        from_segment_times(GOOD, [1.0, 0.0])
    with pytest.raises(ValueError, match="segment_times must be a number or one per leg"):
        from_segment_times(GOOD, [1.0, 1.0, 1.0])
