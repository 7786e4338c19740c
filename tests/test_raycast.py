"""sitl/raycast.py against hand-computed geometry in the default arena (config/worlds/arena.yaml).

Heights in the comments are above the floor; NED z is minus the height.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.raycast import WorldGeometry, cast
from companion.world import Bounds, Wall, World, load_world
from tests.conftest import REPO

NORTH = (1.0, 0.0, 0.0)
EAST = (0.0, 1.0, 0.0)
DOWN = (0.0, 0.0, 1.0)
UP = (0.0, 0.0, -1.0)
S2 = math.sqrt(0.5)


@pytest.fixture(scope="module")
def arena() -> WorldGeometry:
    return WorldGeometry.from_world(load_world(REPO / "config" / "worlds" / "arena.yaml"))


def one(geometry: WorldGeometry, origin: tuple[float, float, float], direction: tuple[float, float, float]) -> float:
    return float(cast(geometry, np.array(origin), np.array([direction]))[0])


def test_wall_at_known_distance(arena: WorldGeometry) -> None:
    # SW room, 2 m from the south wall (x = 0), 3 m from the inner wall x = 5 (its door is at
    # y 2.05..2.95) and 4 m from the wall y = 5 (between its door, x 0.75..1.65, and window).
    assert one(arena, (2.0, 1.0, -1.0), (-1.0, 0.0, 0.0)) == pytest.approx(2.0, abs=1e-5)
    assert one(arena, (2.0, 1.0, -1.0), NORTH) == pytest.approx(3.0, abs=1e-5)
    assert one(arena, (2.0, 1.0, -1.0), EAST) == pytest.approx(4.0, abs=1e-5)
    assert one(arena, (1.2, 1.0, -1.0), EAST) == pytest.approx(9.0, abs=1e-5)  # through door-sw-se to y = 10


def test_45_degree_beams(arena: WorldGeometry) -> None:
    # Onto the 45-degree wall x + y = 18 from (7, 7): hits (9, 9).
    assert one(arena, (7.0, 7.0, -1.0), (S2, S2, 0.0)) == pytest.approx(2 * math.sqrt(2), abs=1e-5)
    # From (1, 2) north-east along y = x + 1: the wall y = 5 at x = 4, where the window
    # (x 2.9..4.1, 0.8..1.6 m high) is. At 0.5 m the wall stops the beam ...
    assert one(arena, (1.0, 2.0, -0.5), (S2, S2, 0.0)) == pytest.approx(3 * math.sqrt(2), abs=1e-5)
    # ... at 1.2 m it flies through the window on to the wall x = 5 at y = 6.
    assert one(arena, (1.0, 2.0, -1.2), (S2, S2, 0.0)) == pytest.approx(4 * math.sqrt(2), abs=1e-5)


def test_window_gap_versus_wall_below_and_above(arena: WorldGeometry) -> None:
    # East from (3.5, 2): the window-sw-se in the wall y = 5 spans 0.8..1.6 m.
    assert one(arena, (3.5, 2.0, -1.2), EAST) == pytest.approx(8.0, abs=1e-5)  # through it, to the east wall y = 10
    assert one(arena, (3.5, 2.0, -0.5), EAST) == pytest.approx(3.0, abs=1e-5)  # the wall below it
    assert one(arena, (3.5, 2.0, -2.0), EAST) == pytest.approx(3.0, abs=1e-5)  # the wall above it
    assert one(arena, (3.5, 2.0, -0.8), EAST) == pytest.approx(3.0, abs=1e-5)  # the sill counts as wall


def test_door_gap_versus_wall_above(arena: WorldGeometry) -> None:
    # North from (2.5, 2.5): door-sw-nw in the wall x = 5, 2.05..2.95 east, up to 2 m.
    assert one(arena, (2.5, 2.5, -1.0), NORTH) == pytest.approx(7.5, abs=1e-5)  # through the door, north wall x = 10
    assert one(arena, (2.5, 2.5, -2.5), NORTH) == pytest.approx(2.5, abs=1e-5)  # the lintel above it
    assert one(arena, (2.5, 1.9, -1.0), NORTH) == pytest.approx(2.5, abs=1e-5)  # beside it


def test_table_top_versus_floor(arena: WorldGeometry) -> None:
    # The table: x 7..7.8, y 1..2.2, top 0.75 m high.
    assert one(arena, (7.4, 1.6, -1.0), DOWN) == pytest.approx(0.25, abs=1e-6)
    assert one(arena, (6.5, 1.6, -1.0), DOWN) == pytest.approx(1.0, abs=1e-6)
    assert one(arena, (6.0, 1.6, -0.5), NORTH) == pytest.approx(1.0, abs=1e-5)  # its side, below the top
    assert one(arena, (6.0, 1.6, -1.0), NORTH) == pytest.approx(4.0, abs=1e-5)  # over it, to the wall x = 10
    # 45 degrees down towards the north from (6, 1.6) at 1.5 m: the top plane is 0.75 m down,
    # reached 0.75 m further north at x = 6.75, short of the table: the side at x = 7 (0.5 m high).
    assert one(arena, (6.0, 1.6, -1.5), (S2, 0.0, S2)) == pytest.approx(math.sqrt(2), abs=1e-5)
    # From (6.5, 1.6) at 1.5 m the top plane is met at x = 7.25: on the table.
    assert one(arena, (6.5, 1.6, -1.5), (S2, 0.0, S2)) == pytest.approx(0.75 * math.sqrt(2), abs=1e-5)


def test_ceiling_and_no_hit(arena: WorldGeometry) -> None:
    assert one(arena, (2.5, 2.5, -1.0), UP) == pytest.approx(2.0, abs=1e-6)  # ceiling at the 3 m walls
    # Outside the arena, level and away from it: nothing.
    assert one(arena, (-1.0, 5.0, -1.0), (-1.0, 0.0, 0.0)) == math.inf
    # A world of one wall (its 3 m height makes the ceiling): a level beam along it hits nothing.
    lone = WorldGeometry.from_world(World(
        name="lone", wall_angle_deg=90, bounds=Bounds(min=(0.0, 0.0), max=(10.0, 10.0)), start=(1.0, 1.0, 0.0),
        walls=(Wall(start=(0.0, 0.0), end=(0.0, 10.0)),)))
    assert one(lone, (2.0, 5.0, -1.0), (-1.0, 0.0, 0.0)) == pytest.approx(2.0, abs=1e-5)
    assert one(lone, (2.0, 5.0, -1.0), NORTH) == math.inf


def test_edges_corners_and_seams_are_watertight(arena: WorldGeometry) -> None:
    assert one(arena, (2.0, 2.0, -1.0), (-S2, -S2, 0.0)) == pytest.approx(2 * math.sqrt(2), abs=1e-5)  # corner (0, 0)
    assert one(arena, (2.5, 2.05, -2.0), NORTH) == pytest.approx(2.5, abs=1e-5)  # the door's top corner
    assert one(arena, (2.9, 2.0, -0.8), EAST) == pytest.approx(3.0, abs=1e-5)  # the window's lower corner
    # 2.5 m up every wall is solid (doors end at 2 m): random level rays inside the arena all hit.
    rng = np.random.default_rng(1)
    origins = np.column_stack((rng.uniform(0.1, 7.9, 5000), rng.uniform(0.1, 9.9, 5000), np.full(5000, -2.5)))
    a = rng.uniform(0, 2 * math.pi, 5000)
    distances = cast(arena, origins, np.column_stack((np.cos(a), np.sin(a), np.zeros(5000))))
    assert np.isfinite(distances).all() and distances.max() < 10 * math.sqrt(2)


def test_per_ray_origins_and_a_full_sweep(arena: WorldGeometry) -> None:
    origins = np.array([[2.0, 1.0, -1.0], [7.4, 1.6, -1.0], [-1.0, 5.0, -1.0]])
    directions = np.array([NORTH, DOWN, (-1.0, 0.0, 0.0)])
    np.testing.assert_allclose(cast(arena, origins, directions), [3.0, 0.25, math.inf], atol=1e-5)
    # A level 360-degree sweep inside a closed room hits something on every beam.
    a = np.radians(np.arange(1440) * 0.25)
    sweep = cast(arena, np.array([2.0, 1.0, -1.0]), np.column_stack((np.cos(a), np.sin(a), np.zeros_like(a))))
    assert np.isfinite(sweep).all() and sweep.min() == pytest.approx(1.0, abs=1e-4)  # the west wall y = 0
    with pytest.raises(ValueError):
        cast(arena, np.zeros((2, 3)), np.zeros((3, 3)))
