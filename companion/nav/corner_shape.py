"""A corner's shape: the directions of the walls that meet at it, so that a corner is associated
only with a map corner of the same shape.

A corner is a point, and two corners a few decimetres apart (the back and the mouth of a door
recess, 20 cm apart) both lie inside the association gate. Where the map misses one of them (a
survey misses corners), the observed one would pair with its neighbour and pull the position by
their distance, confidently: the realistic corridor's flight (config/sitl-corridor-realistic.yaml)
flew 3 m with its cross-track position 21 cm off (4.6 sigma) that way. The rays tell them apart:
the back of a recess has its walls running out towards the corridor's axis and along the recess,
its mouth along the corridor and into the recess.

Rays are unit vectors from the corner along each wall, in the frame of the points (metres). An
observed corner (corners.py) has two: along its first line towards that line's start, along its
second towards its end (beam order). A map corner has one ray per wall ending at it and two per
wall passing through it (a T junction), from its map's walls; without walls there is nothing to
compare and every shape agrees.

How far an observed ray may turn from the map's depends on its line: within 20 deg
(``PlanarParams.corner_shape_tolerance_deg``) for a line of the heading's ``min_length_m`` (0.4 m)
or more, within 70 deg (``corner_shape_short_tolerance_deg``) for a shorter one. A door recess's
0.2 m side seen at a slant with mixed pixels ran 21-60 deg off on correctly paired corners in the
realistic corridor, too poor for the 20 deg test; but which way it runs from the corner is what
tells a recess's back from its mouth (the back's side runs out towards the corridor, the mouth's
into the recess: 180 deg apart), and a recess's back seen from across the corridor has both its
lines that short. Without a test of short lines such a corner, 16-26 cm lines with rays 90 and 180
deg from the mouth's, paired with the mouth's map corner 20 cm away in the same flight (seed 1,
with the fusion's IMU hold uncertainty doubled) and held the estimate 32 cm off across the corridor.
"""

from __future__ import annotations

import math

import numpy as np

from companion.nav.corners import Corners
from companion.nav.lines import LineSet
from companion.nav.wall_hypotheses import MapWalls

BLOCK = 256  # map corners compared with every wall at once


def observed_rays(lines: LineSet, corners: Corners) -> np.ndarray:
    """(K, 2, 2): each corner's two rays (unit vectors along its first and its second line, away
    from the corner), in the frame of the lines."""
    along = (lines.end - lines.start) / lines.length[:, None]  # every line's direction in beam order
    return np.stack((-along[corners.lines[:, 0]], along[corners.lines[:, 1]]), axis=1)


def ray_limits(lines: LineSet, corners: Corners, min_length_m: float, max_angle_deg: float,
               short_max_angle_deg: float) -> np.ndarray:
    """(K, 2): the cosine of the largest angle each ray of :func:`observed_rays` may make with a map
    ray: ``max_angle_deg`` along a line of ``min_length_m`` or more, ``short_max_angle_deg`` along a
    shorter one (module docstring)."""
    long_enough = lines.length[corners.lines] >= min_length_m
    return np.where(long_enough, math.cos(math.radians(max_angle_deg)), math.cos(math.radians(short_max_angle_deg)))


def map_corner_rays(corners: np.ndarray, walls: MapWalls, near_m: float) -> np.ndarray:
    """(M, R, 2): the rays of each map corner of ``corners`` (M, 2) along the map's ``walls``
    passing within ``near_m`` of it (metres): towards each end of such a wall further than
    ``near_m`` from the corner. Rows with fewer than R rays repeat their first; a corner no wall
    reaches has none (NaN)."""
    start, unit, length = walls.segments[:, 0:2], walls.direction, walls.length
    found: list[np.ndarray] = []
    for first in range(0, corners.shape[0], BLOCK):  # in blocks: a large map's corners x walls would not fit at once
        rel = corners[first:first + BLOCK, None, :] - start[None, :, :]  # (B, S, 2)
        u = np.einsum("bsk,sk->bs", rel, unit)  # the foot of the corner along each wall, from its start
        off = np.abs(rel[..., 0] * unit[None, :, 1] - rel[..., 1] * unit[None, :, 0])
        on = (off <= near_m) & (u >= -near_m) & (u <= length[None, :] + near_m)
        backward = on & (u > near_m)  # the wall's start is further than near_m: a ray towards it
        forward = on & (u < length[None, :] - near_m)
        found += [np.concatenate((-unit[b], unit[f])) for b, f in zip(backward, forward)]
    rays = np.full((corners.shape[0], max([1] + [f.shape[0] for f in found]), 2), np.nan)
    for m, f in enumerate(found):
        if f.shape[0]:
            rays[m] = f[0]
            rays[m, :f.shape[0]] = f
    return rays


def shapes_agree(observed: np.ndarray, limits: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(N,) bool: whether each ray of the observed corners ``observed`` (N, 2, 2) lies within its
    angle (``limits`` (N, 2): the cosines of :func:`ray_limits`) of a ray of the map corner paired
    with it in ``known`` (N, R, 2) (both in the same frame); a map corner without rays (NaN) agrees
    with anything. The leading dimension broadcasts like numpy's: (K, 1, 2, 2), (K, 1, 2) and
    (1, M, R, 2) compare every observed corner with every map corner, (K, M)."""
    # NaN dots (a map corner without rays) are never "far": they veto nothing
    far = np.einsum("...ik,...rk->...ir", observed, known).max(axis=-1) < limits
    return ~far.any(axis=-1)
