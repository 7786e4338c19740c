"""Rays against the walking people of a world (:class:`companion.world.Walker`), for simulated scanners.

Frame: world LOCAL_NED (x north, y east, z down, metres); the floor is z = 0. A walker is a
closed vertical cylinder of radius ``radius_m`` standing on the floor, from z = 0 up to
z = -``height_m``, centred where :meth:`~companion.world.Walker.position_at` puts it at the
given daemon time. A ray meets its side from outside or its top from above; a ray starting
inside a walker does not see that walker. Static surfaces are :mod:`sitl.raycast`'s business:
a scanner takes the nearer of the two.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from companion.world import Walker


def cast_walkers(walkers: Sequence[Walker], t: float | np.ndarray, origins: np.ndarray,
                 directions: np.ndarray) -> np.ndarray:
    """Distance (m) along each ray to the first walker it hits, ``inf`` where it hits none.

    ``walkers`` are placed at daemon time ``t`` (s): a scalar for all rays or (N,) one per ray.
    ``origins``: (3,) one NED origin (m) for every ray, or (N, 3) one per ray.
    ``directions``: (N, 3) NED *unit* vectors. Returns (N,) float64.
    """
    d = np.asarray(directions, dtype=float)
    o = np.atleast_2d(np.asarray(origins, dtype=float))
    if not walkers:
        return np.full(len(d), np.inf)
    centres = np.stack([w.position_at(t) for w in walkers], axis=-2)  # (W, 2) or (N, W, 2)
    radius = np.array([w.radius_m for w in walkers])
    top_z = -np.array([w.height_m for w in walkers])
    rel = o[:, None, :2] - centres  # (N or 1, W, 2): origin relative to each axis
    oz, dz = o[:, 2:3], d[:, 2:3]  # (N or 1, 1), (N, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        # Side: |rel + s d_xy| = r, the smaller root (entering), at a height on the cylinder.
        a = np.sum(d[:, :2] ** 2, axis=1)[:, None]  # (N, 1)
        b = np.sum(rel * d[:, None, :2], axis=2)  # (N, W): rel . d_xy
        c = np.sum(rel ** 2, axis=2) - radius ** 2
        s_side = (-b - np.sqrt(b * b - a * c)) / a  # NaN: misses the circle or runs vertically
        z_side = oz + s_side * dz
        side = np.where((s_side > 0) & (z_side <= 0.0) & (z_side >= top_z), s_side, np.inf)
        # Top: the disc at z = -height, met going down from above it.
        s_top = (top_z - oz) / dz
        foot = rel + s_top[..., None] * d[:, None, :2]
        top = np.where((s_top > 0) & (oz < top_z) & (np.sum(foot ** 2, axis=2) <= radius ** 2), s_top, np.inf)
    return np.minimum(side, top).min(axis=1)
