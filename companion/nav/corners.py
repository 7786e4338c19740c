"""Corner features from adjacent line pairs (Wang et al. section III-A step 3, made stricter).

The paper uses the end points of the line clusters as point features. Deviation: an end point
is a corner only where a wall really turns, so here a corner is the intersection of two lines
that are ADJACENT in beam order and NOT PARALLEL (their directions differ by more than
``min_angle_deg``), and only when that intersection lies within ``max_endpoint_distance_m`` of
both lines' facing end points. That rejects the ends of walls cut off by an occlusion, a door
or the field of view (the intersection then lies far from at least one of the two ends), which
the known-corner map does not contain.

Frame: the frame of the lines (the planar localizer uses the levelled body frame: x forward,
y right, metres). Each corner carries a 2x2 covariance propagated from the two line fits:
line k moves along its normal at the corner by ``du_k - s_k dalpha_k`` (``du_k``: its offset
error at the centroid, variance ``offset_var_k``; ``dalpha_k``: its direction error, variance
``alpha_var_k``; ``s_k`` = signed distance along the line's tangent (-sin, cos) from its
centroid to the corner: the lever arm of the direction error), and the intersection maps the
two moves to x, y through the inverse of the matrix of the normals (``gain``). The corners also
keep those terms (``gain``, ``lever``, ``floor_var``) so that a fix from several corners and a
heading from the same lines can propagate the shared line errors jointly
(companion/nav/corner_fix.py). Far lines have fewer points and larger residuals, so far corners get
larger covariances. A floor ``floor_m + floor_per_m * range`` (1-sigma) is added for what the
fits do not see: the map itself (companion/world.py accepts a listed corner within 1 cm of the
walls' corner, about 5 mm 1-sigma), rounded corners, wall roughness, beam width.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.nav.lines import LineSet


@dataclass(frozen=True)
class CornerParams:
    """Thresholds of the corner detector."""

    min_angle_deg: float = 30.0  # the two line directions must differ by more, degrees
    max_endpoint_distance_m: float = 0.2  # intersection to each facing end point, metres
    floor_m: float = 0.005  # 1-sigma floor of every corner (the map's survey error: World.survey_error_m), metres ...
    floor_per_m: float = 0.001  # ... plus this per metre of range


@dataclass(frozen=True)
class Corners:
    """K corners, as parallel arrays, in the frame of the lines."""

    xy: np.ndarray  # (K, 2) metres
    cov: np.ndarray  # (K, 2, 2) m^2: the two lines' errors plus the floor
    range_m: np.ndarray  # (K,) distance from the frame origin, metres
    lines: np.ndarray  # (K, 2) int: indices of the two lines in the LineSet
    gain: np.ndarray  # (K, 2, 2): column j is the corner's move (m) per metre line lines[:, j] moves along its normal
    lever: np.ndarray  # (K, 2) m: s_k of each of the two lines (the module docstring)
    floor_var: np.ndarray  # (K,) m^2 per axis: the floor's part of ``cov`` (independent from corner to corner)

    @property
    def count(self) -> int:
        return int(self.xy.shape[0])

    def subset(self, keep: np.ndarray) -> Corners:
        """The corners selected by a boolean mask or index array."""
        return Corners(self.xy[keep], self.cov[keep], self.range_m[keep], self.lines[keep], self.gain[keep],
                       self.lever[keep], self.floor_var[keep])


def find_corners(lines: LineSet, params: CornerParams = CornerParams()) -> Corners:
    """Corners between consecutive lines of ``lines`` (see the module docstring)."""
    if lines.count < 2:
        return Corners(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0), np.zeros((0, 2), dtype=int),
                       np.zeros((0, 2, 2)), np.zeros((0, 2)), np.zeros(0))
    a = np.arange(lines.count - 1)
    b = a + 1
    c, s = np.cos(lines.alpha), np.sin(lines.alpha)  # every line's normal
    ca, sa, cb, sb = c[:-1], s[:-1], c[1:], s[1:]
    det = ca * sb - sa * cb  # sin(alpha_b - alpha_a): |det| = sin of the angle between the lines
    steep = np.abs(det) > np.sin(np.radians(params.min_angle_deg))
    det = np.where(steep, det, 1.0)
    da, db = lines.d[a], lines.d[b]
    xy = np.column_stack(((da * sb - db * sa) / det, (db * ca - da * cb) / det))
    gate = params.max_endpoint_distance_m
    near = ((np.hypot(*(xy - lines.end[a]).T) <= gate)
            & (np.hypot(*(xy - lines.start[b]).T) <= gate))
    keep = steep & near
    a, b, xy, det = a[keep], b[keep], xy[keep], det[keep]
    rng = np.hypot(xy[:, 0], xy[:, 1])
    lever_a, var_a = lines.normal_error_at(a, xy)  # each line's move at the corner
    lever_b, var_b = lines.normal_error_at(b, xy)
    # Columns of the inverse of [[cos a, sin a], [cos b, sin b]]: the effect of each line's move.
    ga = np.column_stack((s[b], -c[b])) / det[:, None]
    gb = np.column_stack((-s[a], c[a])) / det[:, None]
    floor = (params.floor_m + params.floor_per_m * rng) ** 2
    cov = (var_a[:, None, None] * ga[:, :, None] * ga[:, None, :]
           + var_b[:, None, None] * gb[:, :, None] * gb[:, None, :]
           + floor[:, None, None] * np.eye(2))
    return Corners(xy, cov, rng, np.column_stack((a, b)), np.stack((ga, gb), axis=2),
                   np.column_stack((lever_a, lever_b)), floor)

