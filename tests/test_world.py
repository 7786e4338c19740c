"""The simulated world: the default arena keeps its invariants, bad worlds are refused by line."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.schema import SchemaError
from companion.world import Walker, World, load_world

REPO = Path(__file__).resolve().parent.parent
ARENA = REPO / "config" / "worlds" / "arena.yaml"

# A valid 4 m x 4 m room; the cases below append to it from line 10 on.
BASE = """\
name: box
wall_angle_deg: 45
bounds: {min: [0, 0], max: [4, 4]}
start: [1, 1, 0]
walls:
  - {start: [0, 0], end: [4, 0]}
  - {start: [4, 0], end: [4, 4]}
  - {start: [4, 4], end: [0, 4]}
  - {start: [0, 4], end: [0, 0]}
"""


@pytest.fixture(scope="module")
def arena() -> World:
    return load_world(ARENA)


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "world.yaml"
    path.write_text(text)
    return path


def test_arena_has_the_features_the_pipelines_need(arena: World) -> None:
    assert arena.wall_angle_deg == 45
    assert any(math.isclose(w.direction_deg % 90, 45, abs_tol=0.1) for w in arena.walls)
    kinds = {o.kind for o in arena.openings}
    assert kinds == {"door", "window"}
    window = next(o for o in arena.openings if o.kind == "window")
    assert 0.5 <= window.bottom_m <= 1.0 and 1.4 <= window.top_m <= 2.0
    table = next(o for o in arena.obstacles if o.name == "table")
    sides = sorted(np.subtract(table.max, table.min))
    assert np.allclose(sides, [0.8, 1.2]) and table.height_m == 0.75
    assert len(arena.corners) >= 12
    assert len({m.id for m in arena.floor_markers}) >= 4


def test_arena_corners_are_exactly_the_wall_junctions(arena: World) -> None:
    junctions = {p for w in arena.walls for p in (w.start, w.end) if arena.is_corner(*p)}
    assert set(arena.corners) == junctions
    diagonal = next(w for w in arena.walls if math.isclose(w.direction_deg % 90, 45, abs_tol=0.1))
    assert {diagonal.start, diagonal.end} <= set(arena.corners)


def test_arena_start_is_clear(arena: World) -> None:
    x, y, _ = arena.start
    assert arena.floor_height_at(x, y) == 0.0
    assert min(w.locate((x, y))[0] for w in arena.walls) >= 0.5
    assert all(math.dist((x, y), m.position) >= 0.5 for m in arena.floor_markers)


def test_numpy_accessors(arena: World) -> None:
    segments = arena.segments()
    assert segments.shape == (len(arena.walls), 4) and segments.dtype == float
    assert segments[2].tolist() == [*arena.walls[2].start, *arena.walls[2].end]
    corners = arena.corner_array()
    assert corners.shape == (len(arena.corners), 2)
    assert corners[3].tolist() == list(arena.corners[3])


def test_floor_height_is_the_table_over_the_table_and_zero_elsewhere(arena: World) -> None:
    table = next(o for o in arena.obstacles if o.name == "table")
    assert arena.floor_height_at(*np.add(table.min, table.max) / 2) == 0.75
    for x in np.arange(0.05, 10.0, 0.1):
        for y in np.arange(0.05, 10.0, 0.1):
            over = table.min[0] <= x <= table.max[0] and table.min[1] <= y <= table.max[1]
            assert arena.floor_height_at(x, y) == (0.75 if over else 0.0), (x, y)


def test_the_base_world_is_valid(tmp_path: Path) -> None:
    world = load_world(write(tmp_path, BASE))
    assert world.corners == () and world.floor_height_at(2, 2) == 0.0


def test_walkers_load_with_their_defaults(tmp_path: Path) -> None:
    world = load_world(write(tmp_path, BASE + "walkers:\n  - {start: [1, 2], end: [3, 2], speed_mps: 0.8}\n"))
    assert world.walkers == (Walker(start=(1.0, 2.0), end=(3.0, 2.0), speed_mps=0.8, radius_m=0.25, height_m=1.8),)


def test_a_box_turned_by_the_wall_offset_is_valid(tmp_path: Path) -> None:
    """A square room turned by 30 deg: valid with wall_offset_deg 30, refused without."""
    c, s_ = math.cos(math.radians(30)), math.sin(math.radians(30))
    corners = [(2 + c * x - s_ * y, 2 + s_ * x + c * y) for x, y in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    walls = "".join(f"  - {{start: [{a[0]:.5f}, {a[1]:.5f}], end: [{b[0]:.5f}, {b[1]:.5f}]}}\n"
                    for a, b in zip(corners, corners[1:] + corners[:1]))
    text = f"name: turned\nwall_angle_deg: 90\nbounds: {{min: [0, 0], max: [4, 4]}}\nstart: [2, 2, 30]\nwalls:\n{walls}"
    with pytest.raises(SchemaError, match="minus wall_offset_deg = 0 is not a multiple of wall_angle_deg = 90"):
        load_world(write(tmp_path, text))
    assert load_world(write(tmp_path, text + "wall_offset_deg: 30\n")).wall_offset_deg == 30.0


@pytest.mark.parametrize("extra, line, key_path, words", [
    ("  - {start: [1, 1], end: [1.866, 1.5]}\n", 10, "walls[4]", "not a multiple of wall_angle_deg = 45"),
    ("  - {start: [1, 1], end: [2, 1]}\n  - start: [1, 1]\n    end: [1.866, 1.5]\n",
     11, "walls[5]", "direction 30.00 deg"),
    ("  - {start: [2, 2], end: [2, 2]}\n", 10, "walls[4].end", "zero length"),
    ("corners:\n  - [0, 0]\n  - [2, 2]\n", 12, "corners[1]", "not a corner of the map"),
    ("corners: [[0, 0], [2, 0]]\n", 10, "corners[1]", "not a corner of the map"),
    ("ceiling_m: 3.0\n", 10, "ceiling_m", "unknown key"),
    ("openings:\n  - {name: d, kind: door, center: [2, 2], width_m: 0.9, bottom_m: 0, top_m: 2}\n",
     11, "openings[0].center", "not on any wall"),
    ("openings:\n  - {name: d, kind: door, center: [0.3, 0], width_m: 0.9, bottom_m: 0, top_m: 2}\n",
     11, "openings[0].width_m", "does not fit"),
    ("openings:\n  - {name: w, kind: window, center: [2, 0], width_m: 1, bottom_m: 0, top_m: 1.5}\n",
     11, "openings[0].bottom_m", "a window starts above the floor"),
    ("obstacles:\n  - {name: crate, min: [3, 3], max: [5, 5], height_m: 1}\n",
     11, "obstacles[0].max", "outside bounds"),
    ("floor_markers:\n  - {id: 7, position: [3.95, 2], size_m: 0.3}\n",
     11, "floor_markers[0].position", "does not lie inside bounds"),
    ("obstacles:\n  - {name: table, min: [0.5, 0.5], max: [1.5, 1.5], height_m: 0.75}\n",
     4, "start", "on obstacle 'table'"),
    ("walkers:\n  - {start: [1, 1], end: [3.9, 1]}\n", 11, "walkers[0].end", "is not inside bounds"),
    ("walkers:\n  - {start: [1, 1], end: [3, 1], speed_mps: 9}\n", 11, "walkers[0].speed_mps", "must be within"),
])
def test_bad_worlds_name_file_key_and_line(
        tmp_path: Path, extra: str, line: int, key_path: str, words: str) -> None:
    file = write(tmp_path, BASE + extra)
    with pytest.raises(SchemaError) as err:
        load_world(file)
    assert (err.value.file, err.value.line, err.value.key_path) == (str(file), line, key_path)
    assert words in err.value.message
    assert str(err.value).startswith(f"{file}:{line}: {key_path}: ")


def test_segments_at_cut_the_openings_at_that_height(tmp_path: Path) -> None:
    world = load_world(write(tmp_path, BASE + """\
openings:
  - {name: w, kind: window, center: [2, 0], width_m: 1, bottom_m: 0.8, top_m: 1.6}
  - {name: d, kind: door, center: [4, 1], width_m: 0.8, bottom_m: 0, top_m: 2}
obstacles:
  - {name: crate, min: [2, 2], max: [3, 3], height_m: 0.75}
"""))

    def rows(height: float) -> list[list[float]]:
        segments = world.segments_at(height)
        assert segments.shape[1] == 4 and segments.dtype == float
        return np.round(segments, 9).tolist()

    walls = [[0, 0, 4, 0], [4, 0, 4, 4], [4, 4, 0, 4], [0, 4, 0, 0]]
    crate = [[2, 2, 3, 2], [3, 2, 3, 3], [3, 3, 2, 3], [2, 3, 2, 2]]
    door_cut = [[4, 0, 4, 0.6], [4, 1.4, 4, 4]]
    window_cut = [[0, 0, 1.5, 0], [2.5, 0, 4, 0]]
    # 0.5 m: below the window's sill (not cut), in the door (cut); the crate is taller than that.
    assert rows(0.5) == [walls[0], *door_cut, *walls[2:], *crate]
    # 1.0 m and 1.2 m: in the door and in the window (both cut); the crate is lower.
    assert rows(1.0) == rows(1.2) == [*window_cut, *door_cut, *walls[2:]]
    assert rows(0.75) == [walls[0], *door_cut, *walls[2:], *crate]  # as high as the crate: it counts
    assert rows(2.5) == walls  # above both openings
    assert rows(3.5) == []  # above the walls (3 m): nothing


def test_segments_at_in_the_arena(arena: World) -> None:
    window = next(o for o in arena.openings if o.kind == "window")
    door = next(o for o in arena.openings if o.kind == "door")

    def blocked(height: float, opening_center: tuple[float, float]) -> bool:
        """Whether a segment at ``height`` covers the opening's centre."""
        s = arena.segments_at(height)
        a, edge = s[:, :2], s[:, 2:] - s[:, :2]
        u = np.einsum("sk,sk->s", np.subtract(opening_center, a), edge) / np.einsum("sk,sk->s", edge, edge)
        u = np.clip(u, 0.0, 1.0)
        return bool(np.min(np.hypot(*(a + u[:, None] * edge - opening_center).T)) < 1e-9)

    assert blocked(0.5, window.center) and not blocked(1.2, window.center)
    assert not blocked(1.0, door.center) and blocked(2.5, door.center)
    assert len(arena.segments_at(0.5)) == len(arena.segments_at(1.2)) - 1 + 4  # window cut, table
