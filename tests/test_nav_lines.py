"""Split-and-merge lines and corner features on synthetic scans (ray cast, 1 cm noise)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.nav.bench_stages import DEFAULT_WORLD, make_mount, synthetic_scan
from companion.nav.corners import find_corners
from companion.nav.lines import LineParams, extract_lines
from drivers.lidar_models import UTM_30LX
from sitl.raycast import WorldGeometry
from companion.world import World, load_world
from tests.scan_synthesis import square_room

NOISE_M = 0.01  # UTM-30LX
UTM30LX_ANGLES = UTM_30LX.angles_rad()
AT_BODY_ORIGIN = make_mount((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))


def room(size: float = 4.0) -> WorldGeometry:
    """A closed square room [0, size]^2, walls 3 m high, nothing else."""
    return WorldGeometry.from_world(square_room(size))


def sensor_points(geometry: WorldGeometry, x: float, y: float, yaw: float, noise: float,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 2) in the sensor frame, valid) of a level UTM-30LX at 1 m height."""
    scan = synthetic_scan(geometry, UTM_30LX, AT_BODY_ORIGIN, np.array([x, y, -1.0]), (0.0, 0.0, yaw), rng, noise)
    r = np.where(scan.valid, scan.ranges_m, 0.0)
    return np.column_stack((r * np.cos(scan.angles_rad), r * np.sin(scan.angles_rad))), scan.valid


def angle_diff(a: np.ndarray, b: float) -> np.ndarray:
    return np.abs((a - b + math.pi) % (2 * math.pi) - math.pi)


@pytest.fixture(scope="module")
def arena() -> World:
    return load_world(DEFAULT_WORLD)


@pytest.mark.parametrize("seed", range(5))
def test_square_room_gives_four_lines_with_correct_alpha_and_d(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x, y, yaw = 1.7, 2.2, math.radians(35 + 5 * seed)  # the blind rear sector faces corner (0, 0)
    points, valid = sensor_points(room(), x, y, yaw, NOISE_M, rng)
    lines = extract_lines(points, valid)
    assert lines.count == 4
    # Wall x = 0 is at world normal angle pi (seen from inside), distance x; etc. In the sensor
    # frame the normal angle is the world angle minus the yaw.
    expected = {math.pi: x, -math.pi / 2: y, 0.0: 4 - x, math.pi / 2: 4 - y}
    for world_alpha, distance in expected.items():
        k = int(np.argmin(angle_diff(lines.alpha, world_alpha - yaw)))
        error = angle_diff(lines.alpha[k:k + 1], world_alpha - yaw)[0]
        assert error < math.radians(0.5) and error < 4 * math.sqrt(lines.alpha_var[k])
        assert abs(lines.d[k] - distance) < 0.01
    assert np.all(lines.rms < 2 * NOISE_M)
    assert np.all(lines.alpha_var > 0) and np.all(lines.offset_var > 0)


def test_noise_free_corner_end_points_are_exact() -> None:
    points, valid = sensor_points(room(), 2.0, 2.0, math.radians(45), 0.0, np.random.default_rng(0))
    lines = extract_lines(points, valid)
    assert lines.count == 4
    assert np.all(lines.rms < 1e-6)
    ends = np.concatenate((lines.start, lines.end))
    # The two corners in front ((4, 0) and (4, 4) relative to the sensor at (2, 2), yaw 45 deg).
    c, s = math.cos(math.radians(45)), math.sin(math.radians(45))
    for corner in ((4.0, 0.0), (4.0, 4.0), (0.0, 4.0)):
        dx, dy = corner[0] - 2.0, corner[1] - 2.0
        local = np.array([c * dx + s * dy, -s * dx + c * dy])
        assert np.min(np.hypot(*(ends - local).T)) < 0.03  # within about one beam spacing
    assert np.allclose(lines.length, np.hypot(*(lines.end - lines.start).T))


def test_long_noisy_wall_is_one_line_not_oversplit() -> None:
    # A 10 m wall 1 m in front, seen at incidence angles up to 79 degrees.
    a = UTM30LX_ANGLES[np.abs(UTM30LX_ANGLES) < math.radians(79)]
    for seed in range(30):
        rng = np.random.default_rng(seed)
        r = 1.0 / np.cos(a) + rng.normal(0.0, NOISE_M, a.shape)
        lines = extract_lines(np.column_stack((r * np.cos(a), r * np.sin(a))))
        assert lines.count == 1, seed
        assert abs(lines.d[0] - 1.0) < 0.005 and angle_diff(lines.alpha, 0.0)[0] < math.radians(0.2)


def test_scattered_dropouts_are_bridged_and_a_longer_gap_or_a_range_jump_breaks_lines() -> None:
    a = UTM30LX_ANGLES[np.abs(UTM30LX_ANGLES) < math.radians(60)]
    r = 1.0 / np.cos(a)
    points = np.column_stack((r * np.cos(a), r * np.sin(a)))
    valid = np.random.default_rng(5).random(a.size) >= 0.3  # 30 % of the beams dropped at random
    valid[[0, -1]] = True
    bridging = LineParams(max_missing_beams=10)
    valid[200:210] = False  # the longest gap bridged
    lines = extract_lines(points, valid, bridging)
    assert lines.count == 1 and lines.first_beam[0] == 0 and lines.last_beam[0] == a.size - 1
    valid[210] = False  # one more: the wall is cut there
    lines = extract_lines(points, valid, bridging)
    assert lines.count == 2
    assert lines.last_beam[0] < 200 < lines.first_beam[1]
    assert extract_lines(points, valid).count == 0  # without bridging (the paper): pieces too short
    # A doorway: the beams in between see a wall 3 m further; collinear pieces stay apart.
    far = np.abs(a) < math.radians(5)
    r2 = np.where(far, 4.0 / np.cos(a), r)
    lines = extract_lines(np.column_stack((r2 * np.cos(a), r2 * np.sin(a))))
    assert lines.count == 3
    assert sorted(np.round(lines.d, 2)) == [1.0, 1.0, 4.0]


def test_rough_surface_gives_no_line() -> None:
    """A 5 cm sawtooth every beam (a fence, foliage): no wall, and the split depth is bounded."""
    a = UTM30LX_ANGLES
    r = 2.0 + 0.05 * (np.arange(a.size) % 3)
    assert extract_lines(np.column_stack((r * np.cos(a), r * np.sin(a)))).count == 0


def test_degenerate_inputs_give_no_lines_and_no_nan() -> None:
    n = UTM30LX_ANGLES.size
    assert extract_lines(np.zeros((n, 2)), np.zeros(n, dtype=bool)).count == 0
    assert extract_lines(np.full((n, 2), np.nan)).count == 0
    assert extract_lines(np.zeros((3, 2))).count == 0
    few = np.column_stack((np.ones(5), np.linspace(0, 1, 5)))
    assert extract_lines(few, params=LineParams(min_points=6)).count == 0


def test_room_corners_and_their_covariance() -> None:
    rng = np.random.default_rng(2)
    x, y, yaw = 1.0, 1.5, math.radians(30)
    points, valid = sensor_points(room(), x, y, yaw, NOISE_M, rng)
    corners = find_corners(extract_lines(points, valid))
    c, s = math.cos(yaw), math.sin(yaw)
    world = np.array([x, y]) + corners.xy @ np.array([[c, -s], [s, c]]).T
    truth = np.array([[4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])  # (0, 0) is behind, in the blind sector
    assert corners.count == 3
    assert np.max(np.min(np.hypot(*(world[:, None, :] - truth[None]).transpose(2, 0, 1)), axis=1)) < 0.02
    eig = np.linalg.eigvalsh(corners.cov)
    assert np.all(eig > 0) and np.all(np.sqrt(eig) < 0.05)
    near = int(np.argmin(corners.range_m))
    far = int(np.argmax(corners.range_m))
    assert np.trace(corners.cov[far]) > np.trace(corners.cov[near])


def test_corners_in_the_arena_are_only_real_corners(arena: World) -> None:
    """Over random poses no corner is reported where the map has none: door jambs, the ends of
    walls occluded by nearer ones and the field-of-view cuts are all rejected."""
    geometry = WorldGeometry.from_world(arena)
    truth = arena.corner_array()
    rng = np.random.default_rng(7)
    found = 0
    for _ in range(60):
        x, y = rng.uniform(0.4, 9.6, 2)
        if min(abs(x - 5), abs(y - 5)) < 0.4 or (x > 5 and abs(y - 4) < 0.4) or x + y > 17.4 \
                or (7.1 < x < 8.4 and 5.6 < y < 6.9):
            continue
        yaw = rng.uniform(-math.pi, math.pi)
        points, valid = sensor_points(geometry, x, y, yaw, NOISE_M, rng)
        corners = find_corners(extract_lines(points, valid))
        c, s = math.cos(yaw), math.sin(yaw)
        world = np.array([x, y]) + corners.xy @ np.array([[c, -s], [s, c]]).T
        if corners.count:
            nearest = np.min(np.hypot(*(world[:, None, :] - truth[None]).transpose(2, 0, 1)), axis=1)
            assert np.all(nearest < 0.05), (x, y, yaw, world[nearest >= 0.05])
        found += corners.count
    assert found > 60  # and they are plentiful


def test_parallel_and_far_apart_neighbours_make_no_corner() -> None:
    # Two parallel walls seen one after the other (a step), and an L whose arms end far apart.
    a = UTM30LX_ANGLES[np.abs(UTM30LX_ANGLES) < math.radians(40)]
    r = np.where(a < 0, 1.0, 1.5) / np.cos(a)
    step = extract_lines(np.column_stack((r * np.cos(a), r * np.sin(a))))
    assert step.count == 2 and find_corners(step).count == 0
    arm1 = np.column_stack((np.full(50, 2.0), np.linspace(-1.0, -0.5, 50)))  # ends at (2, -0.5)
    arm2 = np.column_stack((np.linspace(1.5, 1.0, 50), np.full(50, 0.5)))  # meets x = 2 at (2, 0.5)
    lines = extract_lines(np.concatenate((arm1, arm2)))
    assert lines.count == 2 and find_corners(lines).count == 0


@pytest.mark.parametrize("break_grazing_deg, phantoms_expected", [(LineParams.break_grazing_deg, False), (0.0, True)])
def test_a_door_recess_seen_past_its_edge_makes_no_phantom_corner(break_grazing_deg: float,
                                                                  phantoms_expected: bool) -> None:
    """Just past a door recess (config/worlds/corridor.yaml, the recess at x 28-29 on the east
    wall) the scan steps from the recess's back wall to the corridor wall 0.2 m nearer. Joined
    into one run, a short slanted line bridges the step, and its intersections with the two walls
    were reported as corners 6-12 cm from the map's with millimetres of uncertainty (they pulled
    the corridor flight's estimate ahead). The adaptive breakpoint breaks the run at the step;
    without it (break_grazing_deg 0, the fixed gap rule alone) the phantoms are back."""
    corridor = load_world(DEFAULT_WORLD.parent / "corridor.yaml")
    geometry, truth = WorldGeometry.from_world(corridor), corridor.corner_array()
    params = LineParams(break_grazing_deg=break_grazing_deg)
    rng = np.random.default_rng(3)
    worst_sigmas, found = 0.0, 0
    for x in np.linspace(27.5, 29.7, 12):  # up to the recess, past its edge
        points, valid = sensor_points(geometry, x, 1.2, 0.0, NOISE_M, rng)
        corners = find_corners(extract_lines(points, valid, params))
        found += corners.count
        for xy, cov in zip(corners.xy + [x, 1.2], corners.cov):
            error = truth[np.argmin(np.hypot(*(truth - xy).T))] - xy
            worst_sigmas = max(worst_sigmas, math.sqrt(error @ np.linalg.solve(cov, error)))
    assert found >= 12  # the recess's real corners are still found
    assert (worst_sigmas > 5.0) == phantoms_expected, worst_sigmas


def test_a_lines_normal_error_at_a_point_matches_the_spread_of_fits_to_noisy_scans() -> None:
    # A wall 3 m ahead (normal angle 0) seen from y = -1 to 1 m with 1 cm range noise, fitted 400
    # times: the spread of each fit's normal position at the middle of the wall and 4 m along it
    # (where the direction error dominates) is what normal_error_at claims there.
    rng = np.random.default_rng(7)
    angles = np.arctan2(np.linspace(-1.0, 1.0, 120), 3.0)
    params = LineParams(model_floor_m=0.0)
    at = np.array([[3.0, 0.0], [3.0, 4.0]])
    errors, claimed = [], []
    for _ in range(400):
        r = 3.0 / np.cos(angles) + rng.normal(0.0, NOISE_M, angles.size)
        lines = extract_lines(np.column_stack((r * np.cos(angles), r * np.sin(angles))), params=params)
        assert lines.count == 1
        k = np.zeros(2, dtype=int)
        errors.append(at @ np.array([math.cos(lines.alpha[0]), math.sin(lines.alpha[0])]) - lines.d[0])
        claimed.append(lines.normal_error_at(k, at)[1])
    spread, sigma = np.std(errors, axis=0), np.sqrt(np.mean(claimed, axis=0))
    assert sigma[1] > 5 * sigma[0]  # the lever arm: 4 m from the centroid
    np.testing.assert_allclose(spread, sigma, rtol=0.2)
