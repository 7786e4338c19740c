"""A lidar map (walls, corners, wall angle and offset, survey error) from scans at known poses.

Input: 2-D scans, each as sensor-frame points (FRD: x forward, y right, metres) with a validity
mask and the pose they were taken at (x north, y east in metres, yaw from north towards east in
radians: the map frame, LOCAL_NED). A log's reference poses (a CARMEN "corrected" log) or a
survey walk with a good pose source give them. Output: a :class:`BuiltMap` that
``companion map build`` writes as a world YAML (companion/world.py) for ``pipelines.lidar.map``.

Steps (plain numpy, no I/O):

1. lines of every scan (companion/nav/lines.py) within ``max_range_m``, placed in the map with
   the scan's pose;
2. the wall offset: the length-weighted circular mean of the segment directions modulo the wall
   angle (a building need not be aligned with north);
3. every segment within ``angle_tolerance_deg`` of a wall direction joins that direction's
   family (the others, clutter at odd angles, are dropped); within a family, segments whose
   normal offsets chain within ``merge_offset_m`` and whose extents overlap or leave a gap under
   ``merge_gap_m`` are one wall, at their length-weighted mean offset, exactly along the family's
   direction; walls seen fewer than ``min_observations`` times (people, doors that moved) or
   shorter than ``min_length_m`` are dropped;
4. corners: two non-parallel walls whose intersection lies within ``corner_reach_m`` of an end
   of one of them and on (or within reach of) the other; the ends within reach are moved onto
   the intersection, so each corner is a wall end lying on another wall, as a world requires;
5. the survey error: the length-weighted RMS of the segments' offsets about their wall's (scan
   noise and pose error included: an upper bound of the map's own error); the wall direction
   error: the wall-length-weighted RMS of each wall's mean direction (its segments' length-weighted
   mean) about its family's, i.e. how far the building's walls run from the map's exact directions
   (what every heading measured on them carries; the poses' heading error, averaged over each
   wall's segments, included).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from companion.frames import planar_rotation
from companion.nav.lines import LineParams, extract_lines


@dataclass(frozen=True)
class MapBuildParams:
    """Thresholds of the map builder (defaults for a building surveyed with a SICK / Hokuyo)."""

    wall_angle_deg: int = 90  # every wall runs at the offset plus a multiple of this (90, 45, 30)
    max_range_m: float = 15.0  # returns further away are not used (sparse, noisy lines)
    min_segment_m: float = 0.3  # shorter lines are not used, metres
    angle_tolerance_deg: float = 3.0  # a segment joins a wall direction within this, degrees
    merge_offset_m: float = 0.08  # segments whose normal offsets chain within this are one wall ...
    merge_gap_m: float = 0.5  # ... where their extents overlap or leave a gap shorter than this
    min_observations: int = 3  # a wall must be seen in this many segments
    min_length_m: float = 0.5  # shorter walls are dropped, metres
    corner_reach_m: float = 0.3  # a wall end this close to another wall's line makes a corner


@dataclass(frozen=True)
class BuiltMap:
    """Walls (K, 4) [x0, y0, x1, y1] and corners (M, 2) [x, y] in the map frame (NED, metres)."""

    wall_angle_deg: int
    wall_offset_deg: float  # in (-wall_angle/2, wall_angle/2]
    walls: np.ndarray
    observations: np.ndarray  # (K,) segments merged into each wall
    corners: np.ndarray
    survey_error_m: float  # 1-sigma, metres (an upper bound: scan noise and pose error included)
    wall_direction_error_deg: float  # 1-sigma, degrees: the walls' directions about their family's


def build_map(scans: Iterable[tuple[np.ndarray, np.ndarray, tuple[float, float, float]]],
              params: MapBuildParams = MapBuildParams()) -> BuiltMap:
    """The map of ``scans``: (points (N, 2) sensor frame m, valid (N,), pose (x m, y m, yaw rad))."""
    start, end = _segments(scans, params)
    if start.shape[0] == 0:
        raise ValueError("no line in the scans: nothing to build a map from")
    angle = math.radians(params.wall_angle_deg)
    d = end - start
    length = np.hypot(d[:, 0], d[:, 1])
    direction = np.arctan2(d[:, 1], d[:, 0])
    offset = _circular_mean(direction, length, angle)
    family = np.round((direction - offset) / angle).astype(int)
    residual = direction - offset - family * angle
    family = np.mod(family, int(round(math.pi / angle)))  # directions modulo 180 degrees
    keep = np.abs(residual) <= math.radians(params.angle_tolerance_deg)
    walls, counts, rho_resid, resid_len, wall_turn, wall_len = [], [], [], [], [], []
    for f in np.unique(family[keep]):
        phi = offset + f * angle
        t, n = np.array([math.cos(phi), math.sin(phi)]), np.array([-math.sin(phi), math.cos(phi)])
        sel = keep & (family == f)
        mid = 0.5 * (start[sel] + end[sel])
        rho, u0, u1 = mid @ n, np.minimum(start[sel] @ t, end[sel] @ t), np.maximum(start[sel] @ t, end[sel] @ t)
        for members in _walls_of_family(rho, u0, u1, params):
            w = length[sel][members]
            wall_rho = float(w @ rho[members] / w.sum())
            a, b = float(u0[members].min()), float(u1[members].max())
            if members.size < params.min_observations or b - a < params.min_length_m:
                continue
            walls.append(np.concatenate((wall_rho * n + a * t, wall_rho * n + b * t)))
            counts.append(members.size)
            rho_resid.append(rho[members] - wall_rho)
            resid_len.append(w)
            wall_turn.append(float(w @ residual[sel][members] / w.sum()))
            wall_len.append(b - a)
    if not walls:
        raise ValueError("no wall seen often enough: check the poses and the wall angle")
    wall_array = np.array(walls)
    corners = _corners(wall_array, params.corner_reach_m)
    r, w = np.concatenate(rho_resid), np.concatenate(resid_len)
    turn, span = np.array(wall_turn), np.array(wall_len)
    return BuiltMap(params.wall_angle_deg, math.degrees(offset), wall_array, np.array(counts), corners,
                    float(math.sqrt(w @ r ** 2 / w.sum())),
                    math.degrees(math.sqrt(float(span @ turn ** 2 / span.sum()))))


def _segments(scans: Iterable[tuple[np.ndarray, np.ndarray, tuple[float, float, float]]],
              params: MapBuildParams) -> tuple[np.ndarray, np.ndarray]:
    """(start (S, 2), end (S, 2)) of every scan's lines, in the map frame."""
    starts, ends = [], []
    line_params = LineParams()
    for points, valid, (x, y, yaw) in scans:
        near = valid & (np.hypot(points[:, 0], points[:, 1]) <= params.max_range_m)
        lines = extract_lines(points, near, line_params)
        long = lines.length >= params.min_segment_m
        rot = planar_rotation(yaw)
        starts.append(np.array([x, y]) + lines.start[long] @ rot.T)
        ends.append(np.array([x, y]) + lines.end[long] @ rot.T)
    if not starts:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(starts), np.concatenate(ends)


def _circular_mean(direction: np.ndarray, weight: np.ndarray, period: float) -> float:
    """Weighted circular mean of ``direction`` modulo ``period`` (rad), in (-period/2, period/2]."""
    phase = np.exp(1j * 2.0 * math.pi * direction / period)
    mean = float(np.angle(weight @ phase)) * period / (2.0 * math.pi)
    return mean if mean > -period / 2 else mean + period


def _walls_of_family(rho: np.ndarray, u0: np.ndarray, u1: np.ndarray, params: MapBuildParams) -> list[np.ndarray]:
    """Index arrays of the segments of one direction that form one wall each (module doc, step 3)."""
    order = np.argsort(rho, kind="stable")
    breaks = np.flatnonzero(np.diff(rho[order]) > params.merge_offset_m) + 1
    walls = []
    for group in np.split(order, breaks):
        group = group[np.argsort(u0[group], kind="stable")]
        members, reach = [group[0]], u1[group[0]]
        for k in group[1:]:
            if u0[k] <= reach + params.merge_gap_m:
                members.append(k)
                reach = max(reach, u1[k])
            else:
                walls.append(np.array(members))
                members, reach = [k], u1[k]
        walls.append(np.array(members))
    return walls


def _corners(walls: np.ndarray, reach: float) -> np.ndarray:
    """Corners of ``walls`` (module doc, step 4); moves the wall ends that make them onto them."""
    a, b = walls[:, 0:2], walls[:, 2:4]
    t = (b - a) / np.hypot(*(b - a).T)[:, None]
    corners = []
    for i in range(walls.shape[0]):
        for j in range(i + 1, walls.shape[0]):
            cross = t[i, 0] * t[j, 1] - t[i, 1] * t[j, 0]
            if abs(cross) < math.sin(math.radians(20.0)):
                continue  # (nearly) parallel
            s = ((a[j] - a[i])[0] * t[j, 1] - (a[j] - a[i])[1] * t[j, 0]) / cross
            p = a[i] + s * t[i]  # the intersection of the two lines
            nearest = [(k, min((0, 2), key=lambda e: math.dist(walls[k, e:e + 2], p))) for k in (i, j)]
            ends = [(k, e) for k, e in nearest if math.dist(walls[k, e:e + 2], p) <= reach]  # one end per wall
            if not ends or not all(_within(walls[k], p, reach) for k in (i, j)):
                continue
            for k, e in ends:
                walls[k, e:e + 2] = p
            corners.append(p)
    return _distinct_points(np.array(corners).reshape(-1, 2), 0.05)


def _within(wall: np.ndarray, p: np.ndarray, reach: float) -> bool:
    """Whether ``p`` lies on ``wall``'s segment, its ends extended by ``reach``."""
    a, b = wall[0:2], wall[2:4]
    t = b - a
    u = float((p - a) @ t / (t @ t))
    return -reach / math.sqrt(t @ t) <= u <= 1.0 + reach / math.sqrt(t @ t)


def _distinct_points(points: np.ndarray, within: float) -> np.ndarray:
    """``points`` without the ones closer than ``within`` to an earlier one."""
    kept: list[np.ndarray] = []
    for p in points:
        if all(math.dist(p, q) >= within for q in kept):
            kept.append(p)
    return np.array(kept).reshape(-1, 2)
