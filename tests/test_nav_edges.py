"""Occluding line ends: a wall's end where the scan steps back to a surface behind it is an edge;
an end cut by something nearer, by the field of view or by missing beams is not; a mixed pixel may
lengthen a wall seen at a slant, and its end's variance says by how much."""

from __future__ import annotations

import math

import numpy as np

from companion.nav.edges import EdgeParams, occluding_ends
from companion.nav.lines import LineParams, extract_lines

ANGLES = np.radians(np.arange(-60.0, 60.0 + 1e-9, 0.25))  # beams from +x towards +y
NOISE = LineParams()


def _scan(segments: list[tuple[float, float, float, float]], angles: np.ndarray = ANGLES,
          dropped: tuple[int, ...] = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (N, 2), valid (N,), ranges (N,)) of a noise-free scan from the origin of segments
    [x0, y0, x1, y1] (metres): the nearest hit per beam; ``dropped`` beams return nothing."""
    direction = np.column_stack((np.cos(angles), np.sin(angles)))
    ranges = np.full(angles.size, np.inf)
    for x0, y0, x1, y1 in segments:
        a, e = np.array([x0, y0]), np.array([x1 - x0, y1 - y0])
        denom = direction[:, 0] * -e[1] + direction[:, 1] * e[0]  # det [dir, -e]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (a[0] * -e[1] + a[1] * e[0]) / denom  # along the ray
            u = (direction[:, 0] * a[1] - direction[:, 1] * a[0]) / denom  # along the segment
        hit = np.isfinite(t) & (t > 0) & (u >= 0) & (u <= 1)
        ranges = np.where(hit & (t < ranges), t, ranges)
    valid = np.isfinite(ranges)
    valid[list(dropped)] = False
    ranges = np.where(valid, ranges, 0.0)
    return direction * ranges[:, None], valid, ranges


def _edges(segments: list[tuple[float, float, float, float]], params: EdgeParams = EdgeParams(), **kwargs: object):
    points, valid, ranges = _scan(segments, **kwargs)
    lines = extract_lines(points, valid, NOISE, ranges)
    return lines, occluding_ends(lines, points, valid, ranges, np.zeros(2), NOISE, params)


def _line_along(lines, x: float) -> int:
    """Index of the line lying on x = const (normal along +x)."""
    return int(np.flatnonzero(np.abs(lines.d * np.cos(lines.alpha) - x) < 0.02)[0])


def test_a_wall_ending_in_front_of_a_farther_wall_has_an_edge_at_its_true_end() -> None:
    # near wall x = 2 from y = -1 to y = 1, the far wall x = 4 seen past its end; a scanner without
    # mixed pixels (with them, the last test: the variance grows by how far one may lengthen the wall)
    lines, edges = _edges([(2.0, -1.0, 2.0, 1.0), (4.0, -3.0, 4.0, 5.0)], EdgeParams(mixed_pixels=False))
    near = _line_along(lines, 2.0)
    at_end = edges.xy[edges.line == near]
    assert at_end.shape[0] == 2  # both ends step back to the far wall
    ends_y = np.sort(at_end[:, 1])
    var = np.sort(edges.along_var[edges.line == near])
    spacing = 2.0 * math.radians(0.25) / math.cos(math.atan(0.5)) ** 2  # beam spacing along the wall there
    np.testing.assert_allclose(ends_y, [-1.0, 1.0], atol=spacing)
    assert np.all(np.sqrt(var) < spacing)
    # the far wall's ends are at the field of view or behind the near wall: none is an edge
    assert not np.any(edges.line == _line_along(lines, 4.0))


def test_a_wall_cut_by_a_nearer_object_has_no_edge_there() -> None:
    # a wall x = 3 with a post at x = 1.5 in front of it: the wall's pieces end at the post
    lines, edges = _edges([(3.0, -4.0, 3.0, 4.0), (1.5, -0.2, 1.5, 0.2)])
    assert not np.any(np.isin(edges.line, np.flatnonzero(np.abs(lines.d * np.cos(lines.alpha) - 3.0) < 0.02)))
    post = _line_along(lines, 1.5)
    assert np.count_nonzero(edges.line == post) == 2  # the post itself occludes at both ends


def test_an_end_at_missing_beams_is_no_edge() -> None:
    points, valid, ranges = _scan([(2.0, -1.0, 2.0, 1.0), (4.0, -3.0, 4.0, 5.0)])
    lines = extract_lines(points, valid, NOISE, ranges)
    near = _line_along(lines, 2.0)
    after = int(lines.last_beam[near]) + 1
    points, valid, ranges = _scan([(2.0, -1.0, 2.0, 1.0), (4.0, -3.0, 4.0, 5.0)], dropped=(after,))
    lines = extract_lines(points, valid, NOISE, ranges)
    edges = occluding_ends(lines, points, valid, ranges, np.zeros(2), NOISE)
    near = _line_along(lines, 2.0)
    assert np.count_nonzero(edges.line == near) == 1  # the other end still is one


# A corridor wall (y = 1.2, from x = 1) with a 1 m recess at x = 7..8 in it, seen from the origin:
# its end at x = 7 lies 10 deg off the wall's direction, where one beam spans about 0.18 m of it.
CORRIDOR_WALL = [(1.0, 1.2, 7.0, 1.2), (7.0, 2.2, 8.0, 2.2), (8.0, 1.2, 8.0, 2.2), (8.0, 1.2, 14.0, 1.2)]


def _end_with_a_mixed_pixel(mixed_pixels: bool) -> tuple[float, float]:
    """The wall end's (x error m, 1-sigma m) when the first beam past it returned a mixed pixel 3 cm
    behind the wall (a range between the wall and the recess behind, within the split threshold)."""
    points, valid, ranges = _scan(CORRIDOR_WALL)
    past = int(np.flatnonzero(valid & (np.abs(points[:, 1] - 1.2) > 0.01) & (points[:, 0] > 7.0))[-1])
    ranges[past] = 1.23 / math.sin(ANGLES[past])  # on its ray, 3 cm beyond the wall's line
    points[past] = ranges[past] * np.array([math.cos(ANGLES[past]), math.sin(ANGLES[past])])
    lines = extract_lines(points, valid, NOISE, ranges)
    edges = occluding_ends(lines, points, valid, ranges, np.zeros(2), NOISE,
                           EdgeParams(mixed_pixels=mixed_pixels))
    near_end_x = np.minimum(lines.start[:, 0], lines.end[:, 0])
    wall = int(np.flatnonzero((np.abs(lines.d - 1.2) < 0.02) & (near_end_x < 2.0))[0])
    (k,) = np.flatnonzero(edges.line == wall)
    return float(edges.xy[k, 0] - 7.0), math.sqrt(float(edges.along_var[k]))


def test_a_mixed_pixel_lengthening_a_wall_seen_at_a_slant_is_within_the_ends_variance() -> None:
    error, sigma = _end_with_a_mixed_pixel(mixed_pixels=True)
    assert error > 0.2  # the mixed pixel joined the wall: its end looks 0.2 m or more further
    assert error < 2.0 * sigma
    error_clean, sigma_clean = _end_with_a_mixed_pixel(mixed_pixels=False)
    assert error_clean == error and error > 4.0 * sigma_clean  # a scanner declared without them: over-confident


def test_an_end_seen_square_on_is_known_as_well_with_mixed_pixels_as_without() -> None:
    """The near wall's ends of the first test, 27-45 deg off its direction: the reach of a mixed
    pixel there is a few centimetres, no more than a beam spacing."""
    points, valid, ranges = _scan([(2.0, -1.0, 2.0, 1.0), (4.0, -3.0, 4.0, 5.0)])
    lines = extract_lines(points, valid, NOISE, ranges)
    mixed = occluding_ends(lines, points, valid, ranges, np.zeros(2), NOISE)
    none = occluding_ends(lines, points, valid, ranges, np.zeros(2), NOISE, EdgeParams(mixed_pixels=False))
    np.testing.assert_array_equal(mixed.xy, none.xy)
    assert np.all(np.sqrt(mixed.along_var) < 0.1) and np.all(mixed.along_var > none.along_var)
