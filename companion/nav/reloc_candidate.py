"""A relocalization jump waiting for confirmation over several scans (planar.py, "Relocalization").

A search that lands away from the held pose (or finds a first pose) proposes a candidate; it
becomes the pose only when ``needed`` scans in a row found it, each within ``gate_m`` / ``gate_rad``
of the previous finding moved by the motion given with the scan (``moved_m``: odometry or the
fused IMU, in the body frame of the previous scan; ``yaw_delta``: the gyro's yaw change). A scan
that can test nothing carries the candidate along with that motion, up to ``needed`` such scans
in a row; a scan finding another pose starts over with it.

The poses a search weighed are kept for telemetry as :class:`RelocHypothesis` records, best first
(:func:`ranked_hypotheses`).

Frames and units: positions are LOCAL_NED (x north, y east) in metres, yaw in radians from north
towards east; the motion is (forward, right) metres in the body frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from companion.frames import planar_moved, wrap_pi


@dataclass(frozen=True)
class RelocCandidate:
    """A relocalization jump not yet confirmed: the pose the search found (x, y m; yaw rad; moved
    with the body since), the scans that found it, the corners it matched and whether it was found
    near the held pose."""

    x: float
    y: float
    yaw: float
    frames: int
    matched: int
    local: bool  # found near the held pose (True) or by the global search
    idle: int = 0  # scans since it was last found that could not test it (carried by the motion)
    walls: int = 0  # map walls it put lines on, when found by the walls instead of corners

    def describe(self, needed: int) -> str:
        """What the candidate is and how far its confirmation got (``needed`` scans)."""
        found = f"{self.walls} walls" if self.walls else f"{self.matched} corners"
        return (f"{'local' if self.local else 'global'} candidate ({self.x:.2f}, {self.y:.2f}) m, "
                f"{math.degrees(self.yaw):.0f} deg, {found}: found by {self.frames} of the {needed} scans needed")

    def moved(self, moved_m: tuple[float, float], yaw_delta: float) -> tuple[float, float, float]:
        """Where the candidate pose (x, y m, yaw rad) is after the body moved ``moved_m`` (forward,
        right m) and turned ``yaw_delta`` (rad)."""
        return planar_moved((self.x, self.y, self.yaw), *moved_m, yaw_delta)


@dataclass(frozen=True)
class RelocHypothesis:
    """A pose a relocalization search weighed, with its scores (planar.py, "Relocalization").

    ``x``, ``y``: the body's position, m (LOCAL_NED north, east); ``yaw``: rad from north towards
    east. ``source``: ``"corners"`` (a corner correspondence, refined by the corners' update) or
    ``"walls"`` (observed lines of two wall directions on map walls near the held pose; the position
    weighed, before the wall fix refines the winner). ``corners``: observed corners matched there (0
    for a wall hypothesis). ``wall_fraction``: fraction (0-1) of the scan's points (every 4th) within
    ``reloc_wall_tolerance_m`` of a map wall there; None when not computed (no map walls, or a corner
    hypothesis matching fewer corners than the best one, which cannot win). ``local``: weighed by the
    search near the held pose (False: by the global one)."""

    x: float
    y: float
    yaw: float
    source: Literal["corners", "walls"]
    corners: int
    wall_fraction: float | None
    local: bool


def ranked_hypotheses(source: Literal["corners", "walls"], xy: np.ndarray, yaw: np.ndarray, corners: np.ndarray,
                      wall_fraction: np.ndarray, local: bool, limit: int) -> tuple[RelocHypothesis, ...]:
    """The best ``limit`` of H weighed poses as hypotheses, best first: most ``corners`` (H,), then
    the highest ``wall_fraction`` (H,; NaN: not computed, behind every computed one); equal scores
    keep their order. ``xy``: (H, 2) positions, m (north, east); ``yaw``: (H,) rad."""
    computed = ~np.isnan(wall_fraction)
    order = np.lexsort((-np.where(computed, wall_fraction, -np.inf), -corners))[:limit]
    return tuple(RelocHypothesis(float(xy[i, 0]), float(xy[i, 1]), float(yaw[i]), source, int(corners[i]),
                                 float(wall_fraction[i]) if computed[i] else None, local) for i in order)


def carried(c: RelocCandidate | None, moved_m: tuple[float, float], yaw_delta: float,
            needed: int) -> RelocCandidate | None:
    """The candidate after a scan that neither found nor contradicted it (too few corners, no
    clear winner): moved with the body, dropped after ``needed`` such scans in a row."""
    if c is None or c.idle >= needed:
        return None
    x, y, yaw = c.moved(moved_m, yaw_delta)
    return replace(c, x=x, y=y, yaw=yaw, idle=c.idle + 1)


def found_again(c: RelocCandidate | None, xy: np.ndarray, yaw: float, matched: int, walls: int, local: bool,
                moved_m: tuple[float, float], yaw_delta: float, gate_m: float, gate_rad: float) -> RelocCandidate:
    """The candidate after a scan found a jump at ``xy`` (m), ``yaw`` (rad), by ``matched`` corners
    or else ``walls`` walls: one more scan for ``c`` if it agrees with ``c`` moved by the motion
    since (within ``gate_m`` and ``gate_rad``), else a new candidate found by this scan alone."""
    x, y = float(xy[0]), float(xy[1])
    frames = 1
    if c is not None:
        cx, cy, cyaw = c.moved(moved_m, yaw_delta)
        if math.hypot(x - cx, y - cy) <= gate_m and abs(wrap_pi(yaw - cyaw)) <= gate_rad:
            frames = c.frames + 1
    return RelocCandidate(x, y, yaw, frames, matched, local, walls=walls)
