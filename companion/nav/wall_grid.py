"""Map walls bucketed in a square grid: which points lie near a wall, in time that grows with
the points, not with the map (relocalization checks some 30 candidate poses per scan against
every wall of the map otherwise).

Frame: the map's (LOCAL_NED north, east), metres.
"""

from __future__ import annotations

import numpy as np


class WallGrid:
    """Walls (S, 4) segments [x0, y0, x1, y1] m, each listed in every cell of side ``cell_m`` that
    its bounding box widened by ``reach_m`` touches: all the walls within ``reach_m`` of a point
    are listed in the point's own cell."""

    def __init__(self, walls: np.ndarray, reach_m: float, cell_m: float = 1.0) -> None:
        self.walls = np.asarray(walls, dtype=float).reshape(-1, 4)
        self.reach_m = reach_m
        self.cell_m = cell_m
        lo = np.floor((np.minimum(self.walls[:, 0:2], self.walls[:, 2:4]) - reach_m) / cell_m).astype(np.int64)
        hi = np.floor((np.maximum(self.walls[:, 0:2], self.walls[:, 2:4]) + reach_m) / cell_m).astype(np.int64)
        self._origin = lo.min(axis=0) if len(lo) else np.zeros(2, dtype=np.int64)
        self._width = int((hi[:, 1].max() - self._origin[1]) + 1) if len(hi) else 1
        self._rows = int((hi[:, 0].max() - self._origin[0]) + 1) if len(hi) else 0
        keys, owners = [], []
        for s in range(self.walls.shape[0]):
            rows = np.arange(lo[s, 0], hi[s, 0] + 1) - self._origin[0]
            cols = np.arange(lo[s, 1], hi[s, 1] + 1) - self._origin[1]
            cell_keys = (rows[:, None] * self._width + cols[None, :]).ravel()
            keys.append(cell_keys)
            owners.append(np.full(cell_keys.size, s))
        key = np.concatenate(keys) if keys else np.zeros(0, dtype=np.int64)
        owner = np.concatenate(owners) if owners else np.zeros(0, dtype=int)
        order = np.argsort(key, kind="stable")
        key, self._wall_of = key[order], owner[order]  # walls listed cell by cell
        starts = np.flatnonzero(np.concatenate(([True], key[1:] != key[:-1]))) if key.size else np.zeros(0, dtype=int)
        self._keys = key[starts]
        self._start = starts
        self._count = np.diff(np.append(starts, key.size))
        self._edge = self.walls[:, 2:4] - self.walls[:, 0:2]
        self._edge_len2 = np.maximum(np.einsum("sk,sk->s", self._edge, self._edge), 1e-18)

    def near_wall(self, points: np.ndarray, tolerance_m: float) -> np.ndarray:
        """(P,) bool: whether each point (P, 2) lies within ``tolerance_m`` (<= the grid's reach)
        of a wall, exactly as comparing it with every wall would say."""
        if tolerance_m > self.reach_m:
            raise ValueError(f"tolerance {tolerance_m} m beyond the grid's reach {self.reach_m} m")
        out = np.zeros(points.shape[0], dtype=bool)
        if self._keys.size == 0 or points.shape[0] == 0:
            return out
        cell = np.floor(points / self.cell_m).astype(np.int64) - self._origin
        inside = (cell[:, 0] >= 0) & (cell[:, 0] < self._rows) & (cell[:, 1] >= 0) & (cell[:, 1] < self._width)
        which = np.flatnonzero(inside)
        key = cell[which, 0] * self._width + cell[which, 1]
        slot = np.minimum(np.searchsorted(self._keys, key), self._keys.size - 1)
        listed = self._keys[slot] == key
        which, slot = which[listed], slot[listed]
        hits = self._count[slot]
        total = int(hits.sum())
        if total == 0:
            return out
        point = np.repeat(which, hits)
        wall = self._wall_of[np.repeat(self._start[slot], hits) + np.arange(total) - np.repeat(np.cumsum(hits) - hits, hits)]
        rel = points[point] - self.walls[wall, 0:2]
        edge = self._edge[wall]
        u = np.clip(np.einsum("ik,ik->i", rel, edge) / self._edge_len2[wall], 0.0, 1.0)
        off = rel - u[:, None] * edge
        close = off[:, 0] ** 2 + off[:, 1] ** 2 <= tolerance_m ** 2
        out[point[close]] = True
        return out
