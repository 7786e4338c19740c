"""Positions near a held one that put the observed wall lines onto map walls (resuming after a loss).

After the planar localizer has dead-reckoned for a while (lost: nothing matched), its held
position may be a metre or more off, beyond the gates of the corner and wall association. If the
scan shows no three corners, relocalization by corners cannot help; its walls still can. With the
heading known (the wall directions measure it modulo the wall angle; the gyro picks the alias),
each observed line lying on a map wall of its direction fixes the position along that wall's
normal: a displacement ``s`` of the held position along it. Walls of two directions fix it
completely: every pair of such displacements (one per direction) is a hypothesis. The caller
scores the hypotheses (how many scan points then lie on walls) and keeps a clear winner only.

Frames: lines in the levelled body frame (companion/nav/lines.py); the held position, walls,
normals and displacements in the map frame (LOCAL_NED north, east, metres); yaw in radians from
north towards east.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.frames import planar_rotation
from companion.nav.lines import LineSet


@dataclass(frozen=True)
class MapWalls:
    """A map's wall segments and what is derived from them once (map frame: north, east, metres)."""

    segments: np.ndarray  # (S, 4) [x0, y0, x1, y1]
    direction: np.ndarray  # (S, 2) unit, start -> end
    length: np.ndarray  # (S,)
    normal: np.ndarray  # (S, 2) unit, left of the direction
    family: np.ndarray  # (S,) int: the direction as a multiple of the wall angle, modulo 180 deg

    @classmethod
    def from_segments(cls, segments: np.ndarray, wall_angle_rad: float, offset_rad: float) -> MapWalls:
        """``segments`` (S, 4) of a map whose walls run at ``offset_rad`` plus multiples of
        ``wall_angle_rad`` (parallel walls share a family)."""
        segments = np.asarray(segments, dtype=float).reshape(-1, 4)
        edge = segments[:, 2:4] - segments[:, 0:2]
        length = np.hypot(edge[:, 0], edge[:, 1])
        direction = edge / np.maximum(length, 1e-9)[:, None]
        angle = np.arctan2(direction[:, 1], direction[:, 0])
        steps = int(round(math.pi / wall_angle_rad))
        family = np.mod(np.round((angle - offset_rad) / wall_angle_rad).astype(int), steps)
        return cls(segments, direction, length, np.column_stack((-direction[:, 1], direction[:, 0])), family)


def lines_on_walls(lines: LineSet, use: np.ndarray, xy: np.ndarray, yaw: float, walls: MapWalls,
                   parallel_deg: float, gate_m: float, overlap_margin_m: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which observed lines may lie on which map walls, seen from the position ``xy`` (m) at
    heading ``yaw`` (rad): (the lines' middles (L, 2) in the map, m; the displacement of ``xy``
    along each wall's normal (left of its direction) that puts each line's middle on the wall's
    line (L, S), m; whether the pair may match (L, S): parallel within ``parallel_deg``, that
    displacement within ``gate_m``, the line overlapping the wall's extent within
    ``overlap_margin_m``). ``use``: indices of the lines (L of them); ``walls``: the map's S walls.
    Measured along the wall's normal, not the line's: a real wall is a little off its map line, and
    along the line's normal a long wall's residual would grow with its length."""
    angle = lines.alpha[use] + yaw
    normal = np.column_stack((np.cos(angle), np.sin(angle)))  # world normals of the observed lines
    rot = planar_rotation(yaw)
    start, end = xy + lines.start[use] @ rot.T, xy + lines.end[use] @ rot.T
    mid = 0.5 * (start + end)
    origin, wall_dir, wall_normal = walls.segments[:, 0:2], walls.direction, walls.normal
    parallel = np.abs(normal @ wall_dir.T) <= math.sin(math.radians(parallel_deg))
    shift = np.sum(wall_normal * origin, axis=1)[None, :] - mid @ wall_normal.T
    u0 = np.einsum("lsk,sk->ls", start[:, None, :] - origin[None, :, :], wall_dir)
    u1 = np.einsum("lsk,sk->ls", end[:, None, :] - origin[None, :, :], wall_dir)
    overlap = (np.maximum(u0, u1) >= -overlap_margin_m) & (np.minimum(u0, u1) <= walls.length + overlap_margin_m)
    return mid, shift, parallel & overlap & (np.abs(shift) <= gate_m)


def wall_hypotheses(lines: LineSet, use: np.ndarray, held: np.ndarray, yaw: float, walls: MapWalls,
                    radius_m: float, parallel_deg: float, cluster_m: float) -> np.ndarray:
    """(H, 2) positions (m) within ``radius_m`` of ``held`` at which an observed line of each of
    two wall directions lies on a map wall.

    ``use``: indices of the lines to place (long enough to trust their direction); ``yaw``: the
    heading (rad); ``walls``: the map's (walls of one family are parallel); ``parallel_deg``: a
    line lies on a wall only if they are parallel within this; displacements along one family
    closer than ``cluster_m`` are one (their mean). All of them are returned: the caller refuses to
    pick among too many rather than dropping some (the true one among them)."""
    none = np.zeros((0, 2))
    if use.size == 0 or walls.segments.shape[0] == 0:
        return none
    # Each line on a wall within the radius along its normal, overlapping it once moved by at most
    # the radius along it as well.
    _, shift, pairs = lines_on_walls(lines, use, held, yaw, walls, parallel_deg, radius_m, radius_m)
    line_i, wall_j = np.nonzero(pairs)
    if line_i.size == 0:
        return none
    wall_normal, family = walls.normal, walls.family
    # Per family, displacements along the family's reference normal (its first wall's).
    fams = np.unique(family[wall_j])
    reference = {f: wall_normal[wall_j[family[wall_j] == f][0]] for f in fams}
    shifts: dict[int, np.ndarray] = {}
    for f in fams:
        pick = family[wall_j] == f
        sign = np.sign(wall_normal[wall_j[pick]] @ reference[f])
        shifts[int(f)] = _clustered(sign * shift[line_i[pick], wall_j[pick]], cluster_m)
    out = []
    keys = sorted(shifts)
    for a_index, a in enumerate(keys):
        for b in keys[a_index + 1:]:
            basis = np.array([reference[a], reference[b]])  # rows: the two normals
            if abs(np.linalg.det(basis)) < math.sin(math.radians(20.0)):
                continue  # (nearly) parallel families fix one direction only
            sa, sb = np.meshgrid(shifts[a], shifts[b], indexing="ij")
            rhs = np.column_stack((sa.ravel(), sb.ravel()))
            out.append(np.linalg.solve(basis, rhs.T).T)
    if not out:
        return none
    delta = np.concatenate(out)
    delta = delta[np.hypot(delta[:, 0], delta[:, 1]) <= radius_m]
    return held + delta


def _clustered(values: np.ndarray, within: float) -> np.ndarray:
    """The means of the runs of sorted ``values`` whose steps are under ``within``."""
    v = np.sort(values)
    breaks = np.flatnonzero(np.diff(v) > within) + 1
    return np.array([run.mean() for run in np.split(v, breaks)])
