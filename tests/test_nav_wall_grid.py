"""The wall grid answers "near a wall?" as comparing each point with every wall does."""

from __future__ import annotations

import numpy as np
import pytest

from companion.nav.wall_grid import WallGrid


def _near_any_wall(points: np.ndarray, walls: np.ndarray, tolerance: float) -> np.ndarray:
    a, edge = walls[:, 0:2], walls[:, 2:4] - walls[:, 0:2]
    rel = points[:, None, :] - a[None]
    u = np.clip(np.einsum("psk,sk->ps", rel, edge) / np.maximum(np.einsum("sk,sk->s", edge, edge), 1e-18), 0.0, 1.0)
    off = rel - u[:, :, None] * edge[None]
    return (off[..., 0] ** 2 + off[..., 1] ** 2 <= tolerance ** 2).any(axis=1)


def test_points_near_walls_are_found_as_by_comparing_every_wall() -> None:
    rng = np.random.default_rng(3)
    for trial in range(40):
        walls = rng.uniform(-20.0, 20.0, (int(rng.integers(1, 60)), 4))
        walls[: walls.shape[0] // 2, 2] = walls[: walls.shape[0] // 2, 0]  # half of them axis-aligned
        walls[0, 2:4] = walls[0, 0:2]  # a zero-length wall is a point
        grid = WallGrid(walls, reach_m=0.3, cell_m=float(rng.choice([0.25, 1.0, 3.0])))
        # points on or beside the walls (and some far outside the grid)
        t = rng.uniform(0.0, 1.0, 400)
        pick = rng.integers(0, walls.shape[0], 400)
        points = walls[pick, 0:2] + t[:, None] * (walls[pick, 2:4] - walls[pick, 0:2]) + rng.normal(0.0, 0.3, (400, 2))
        points = np.vstack([points, rng.uniform(-60.0, 60.0, (100, 2))])
        for tolerance in (0.1, 0.3):
            np.testing.assert_array_equal(grid.near_wall(points, tolerance), _near_any_wall(points, walls, tolerance))


def test_a_tolerance_beyond_the_grids_reach_is_refused() -> None:
    grid = WallGrid(np.array([[0.0, 0.0, 1.0, 0.0]]), reach_m=0.1)
    with pytest.raises(ValueError, match="reach"):
        grid.near_wall(np.zeros((1, 2)), 0.2)


def test_an_empty_map_has_no_point_near_a_wall() -> None:
    grid = WallGrid(np.zeros((0, 4)), reach_m=0.1)
    assert not grid.near_wall(np.zeros((3, 2)), 0.1).any()
