"""The planar localizer's position fix from walls alone (point-to-line), when no corner matched
(companion/nav/planar.py; the corner fix's covariance is corner_fix.py).

Each observed line of the heading's ``min_length_m`` or more lying on a map wall near the
position held measures the position along the wall's normal; each of its occluding ends
(edges.py) lying within ``edge_gate_m`` of an end of its map wall that the map lists as a corner
measures it along the wall. Walls of one direction without such an end (a corridor) measure the
cross-track direction only: the along-track direction is reported unmeasured, with the lost
variance, instead of the fix going lost.

Frames: the map frame (LOCAL_NED north, east, metres; yaw from north towards east, rad); lines
and edges in the levelled body frame (x forward, y right, metres).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from companion.frames import planar_rotation
from companion.nav.edges import Edges
from companion.nav.heading import HeadingParams, HeadingResult
from companion.nav.lines import LineSet
from companion.nav.wall_hypotheses import MapWalls, lines_on_walls


class WallFixParams(Protocol):
    """The settings the wall fix reads (companion/nav/planar.py's PlanarParams has them)."""

    heading: HeadingParams  # its min_length_m: the shortest line used, m
    wall_angle_tolerance_deg: float
    wall_gate_m: float
    wall_overlap_margin_m: float
    map_error_m: float
    lost_variance_m2: float
    edge_gate_m: float


@dataclass(frozen=True)
class WallMap:
    """The map's walls as the wall fix reads them."""

    walls: MapWalls
    end_is_corner: np.ndarray  # (S, 2) bool: whether each wall's start / end is a listed map corner


@dataclass(frozen=True)
class WallFix:
    """A position from walls: ``xy`` (2,) north, east m; ``covariance`` (3, 3) of (x, y, yaw) in
    m^2, m rad, rad^2; the wall lines used; why (for the fix's reason); the unit (north, east)
    direction no wall measures (a corridor's axis) and the one only wall ends measure, if any."""

    xy: np.ndarray
    covariance: np.ndarray
    walls_matched: int
    reason: str
    unmeasured: tuple[float, float] | None
    ends_only: tuple[float, float] | None


def wall_fix(lines: LineSet, edges: Edges, xy: np.ndarray, heading: HeadingResult, wall_map: WallMap,
             p: WallFixParams, why: str) -> WallFix | None:
    """Position from observed ``lines`` (with their occluding ``edges``) lying on map walls near the
    position ``xy`` (m) at the measured ``heading``, None if no wall matched (module docstring);
    ``why`` (no corner matched, and why) begins the reason."""
    use = np.flatnonzero(lines.length >= p.heading.min_length_m)
    if use.size == 0:
        return None
    walls = wall_map.walls
    rot = planar_rotation(heading.yaw)
    mid, resid, candidate = lines_on_walls(lines, use, xy, heading.yaw, walls, p.wall_angle_tolerance_deg,
                                           p.wall_gate_m, p.wall_overlap_margin_m)
    has = candidate.any(axis=1)
    if not has.any():
        return None
    nearest = np.argmin(np.where(candidate, np.abs(resid), np.inf), axis=1)[has]
    # Along the map wall's normal, not the observed line's: a corridor's parallel walls then
    # leave the along-track direction exactly unmeasured.
    n, r = walls.normal[nearest], resid[has, nearest]
    k = use[has]
    # The offset is measured at the foot of the normal.
    var = lines.normal_error_at(k, np.zeros((k.size, 2)))[1] + p.map_error_m ** 2
    w = 1.0 / var
    info = (w[:, None, None] * n[:, :, None] * n[:, None, :]).sum(axis=0)
    b = (w * r) @ n
    # d(residual)/d(yaw): turning the scan about the scanner moves each line's middle sideways.
    arm = mid[has] - xy
    db_dyaw = (w * (n[:, 0] * arm[:, 1] - n[:, 1] * arm[:, 0])) @ n
    ends = _wall_ends(edges, k, nearest, xy, rot, wall_map, p.edge_gate_m)
    ends_only = None
    walls_rank = 2  # directions the walls alone measure
    if ends is not None:
        walls_val, walls_vec = np.linalg.eigh(info)
        if walls_val[0] * p.wall_gate_m ** 2 < 1.0:  # a direction they leave to the ends
            ends_only = (float(walls_vec[0, 0]), float(walls_vec[1, 0]))
            walls_rank = 1
        direction, along, along_var, dalong_dyaw = ends
        w_end = 1.0 / (along_var + p.map_error_m ** 2)
        info = info + (w_end[:, None, None] * direction[:, :, None] * direction[:, None, :]).sum(axis=0)
        b = b + (w_end * along) @ direction
        db_dyaw = db_dyaw + (w_end * dalong_dyaw) @ direction
    eigval, eigvec = np.linalg.eigh(info)
    if eigval[1] <= 0.0:
        return None
    ended = "" if ends is None else f" and {ends[1].size} of their ends"
    if eigval[0] * p.wall_gate_m ** 2 < 1.0:  # a direction measured worse than the gate: a corridor's axis
        u = eigvec[:, 1]
        delta = (u @ b) / eigval[1] * u
        dp_dyaw = (u @ db_dyaw) / eigval[1] * u
        cov2 = (np.outer(u, u) / eigval[1] * _wall_chi2_scale(n, r, w, delta, walls_rank=1)
                + p.lost_variance_m2 * np.outer(eigvec[:, 0], eigvec[:, 0]))
        reason = f"{why}: {k.size} walls{ended} constrain the cross-track position only"
        unmeasured: tuple[float, float] | None = (float(eigvec[0, 0]), float(eigvec[1, 0]))
    else:
        cov2 = np.linalg.inv(info)
        delta = cov2 @ b
        dp_dyaw = cov2 @ db_dyaw
        cov2 = cov2 * _wall_chi2_scale(n, r, w, delta, walls_rank)
        reason = f"{why}: {k.size} walls{ended} constrain the position"
        unmeasured = None
    # The heading's uncertainty moves the position through dp_dyaw, as for corners (planar.py's match()).
    cov = np.empty((3, 3))
    cov[:2, :2] = cov2 + heading.variance * np.outer(dp_dyaw, dp_dyaw)
    cov[:2, 2] = cov[2, :2] = heading.variance * dp_dyaw
    cov[2, 2] = heading.variance
    return WallFix(np.array([xy[0] + delta[0], xy[1] + delta[1]]), cov, int(k.size), reason, unmeasured,
                   None if unmeasured is not None else ends_only)


def _wall_ends(edges: Edges, k: np.ndarray, wall: np.ndarray, xy: np.ndarray, rot: np.ndarray, wall_map: WallMap,
               gate_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The occluding ends of the lines ``k`` (matched to the map walls ``wall``) that lie within
    ``gate_m`` of an end of their wall listed as a corner: (wall directions (E, 2), how far to move
    the position along them to put each observed end on the map's (E,), m; their variances (E,),
    m^2; the derivatives of those distances with the yaw (E,), m/rad), or None if there are none."""
    if edges.count == 0:
        return None
    of_line = {int(line): j for line, j in zip(k, wall)}
    pick = np.array([int(line) in of_line for line in edges.line])
    if not pick.any():
        return None
    j = np.array([of_line[int(line)] for line in edges.line[pick]])
    arm = edges.xy[pick] @ rot.T  # scanner to end, world frame
    world = xy + arm
    walls = wall_map.walls
    direction, length = walls.direction[j], walls.length[j]
    u = np.einsum("ij,ij->i", world - walls.segments[j, 0:2], direction)  # along the wall from its start
    at_end = u >= 0.5 * length  # the nearer end: the wall's end (True) or start
    along = np.where(at_end, length, 0.0) - u
    near = (np.abs(along) <= gate_m) & wall_map.end_is_corner[j, at_end.astype(int)]
    if not near.any():
        return None
    dalong_dyaw = direction[:, 0] * arm[:, 1] - direction[:, 1] * arm[:, 0]  # -direction . d(arm)/d(yaw)
    return direction[near], along[near], edges.along_var[pick][near], dalong_dyaw[near]


def _wall_chi2_scale(normal: np.ndarray, resid: np.ndarray, weight: np.ndarray, delta: np.ndarray,
                     walls_rank: int) -> float:
    """max(1, chi-square per degree of freedom) of the point-to-line measurements after the
    position moved by ``delta`` (m): each wall line's ``resid`` (m) along its unit ``normal`` with
    ``weight`` (1 / variance, m^-2); ``walls_rank`` directions were estimated from them. The wall
    ends are left out: along a corridor they are the only measurement, and two ends a few beams
    apart would otherwise widen the well-measured cross-track direction with the along-track one."""
    dof = resid.shape[0] - walls_rank
    if dof < 1:
        return 1.0
    left = resid - normal @ delta
    return max(1.0, float(weight @ (left * left)) / dof)
