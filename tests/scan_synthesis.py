"""Test-only worlds for synthetic scans: bare walls given as segments (no openings, no boxes).

Scans themselves are rendered by :func:`companion.nav.bench_stages.synthetic_scan` (ray cast by
sitl.raycast); these worlds are built directly, without load_world's checks, so that tests can
use walls at any angle (e.g. clutter that breaks the wall-angle assumption on purpose).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from companion.world import Bounds, Wall, World


def walls_world(segments: Iterable[tuple[float, float, float, float]], wall_angle_deg: int = 45,
                height_m: float = 3.0) -> World:
    """A world of the given wall segments [x0, y0, x1, y1] (NED metres), ``height_m`` high."""
    rows = np.array(list(segments), dtype=float).reshape(-1, 4)
    xy = rows.reshape(-1, 2)
    walls = tuple(Wall((x0, y0), (x1, y1), height_m) for x0, y0, x1, y1 in rows.tolist())
    bounds = Bounds(tuple(xy.min(axis=0).tolist()), tuple(xy.max(axis=0).tolist()))
    return World("test", wall_angle_deg, bounds, (*xy.mean(axis=0).tolist(), 0.0), walls)


def square_room(size: float = 4.0, wall_angle_deg: int = 45) -> World:
    """A closed square room [0, size]^2, walls 3 m high, nothing else."""
    c = [(0.0, 0.0), (size, 0.0), (size, size), (0.0, size)]
    return walls_world([(*c[i], *c[(i + 1) % 4]) for i in range(4)], wall_angle_deg)
