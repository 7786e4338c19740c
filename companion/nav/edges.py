"""Occluding line ends: where a wall really ends, seen in one 2-D scan (beyond Wang et al.).

A line that ends because the next beam leaves it for a surface BEHIND it (a range discontinuity
away from the scanner) ends at a real edge of that wall: the nearer surface occludes the farther
one, never the other way round. A door recess seen past its edge, the end of a wall at an
opening, a convex corner seen from one side: each such end fixes the position ALONG the wall,
which the wall's own offset cannot (a corridor's walls leave their axis unmeasured; their ends
do not). The end of a line cut by a nearer object, by the field of view, by invalid beams or by
the adaptive breakpoint on a grazing wall (the next point continues the same line) is not an
edge and is not returned.

The edge lies between the line's last point and the point where the next beam's ray meets the
line (that beam already missed the wall): it is taken at the middle, with the variance of a
uniform spread over that interval plus the range noise projected along the line.

Frame: the frame of the lines and points (the planar localizer's levelled body frame, metres),
the scanner at ``origin`` in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.nav.lines import LineParams, LineSet


@dataclass(frozen=True)
class EdgeParams:
    """Thresholds of the occluding-end test."""

    behind_m: float = 0.05  # the next point must lie at least this far behind the line's extension, metres ...
    behind_sigmas: float = 4.0  # ... and this many range-noise sigmas
    max_missing_beams: int = 0  # invalid beams allowed between the line's end and the next point
    max_spread_m: float = 0.3  # an end known only within a wider interval (a grazing view) is no edge, metres


@dataclass(frozen=True)
class Edges:
    """M occluding line ends, as parallel arrays, in the frame of the lines."""

    line: np.ndarray  # (M,) int, index of the line in the LineSet
    xy: np.ndarray  # (M, 2) the edge, metres
    along_var: np.ndarray  # (M,) variance of its position along the line, m^2

    @property
    def count(self) -> int:
        return int(self.line.shape[0])


def occluding_ends(lines: LineSet, points: np.ndarray, valid: np.ndarray, ranges: np.ndarray,
                   origin: np.ndarray, noise: LineParams, params: EdgeParams = EdgeParams()) -> Edges:
    """The ends of ``lines`` that are occluding edges (module docstring). ``points`` (N, 2),
    ``valid`` (N,) and ``ranges`` (N,) are the scan the lines were extracted from (their
    ``first_beam`` / ``last_beam`` index it); ``origin`` (2,) the scanner in that frame, metres;
    ``noise`` the range-noise model of the extraction."""
    found_line, found_xy, found_var = [], [], []
    beams = np.flatnonzero(valid)
    for k in range(lines.count):
        n = np.array([np.cos(lines.alpha[k]), np.sin(lines.alpha[k])])
        for end_beam, step in ((int(lines.first_beam[k]), -1), (int(lines.last_beam[k]), 1)):
            i = int(np.searchsorted(beams, end_beam))  # the end beam's place among the valid ones
            j = i + step
            if not 0 <= j < beams.size or abs(int(beams[j]) - end_beam) > 1 + params.max_missing_beams:
                continue  # the field of view or invalid beams end the line: nothing says why
            nxt = points[beams[j]]
            behind = float(n @ nxt - lines.d[k])
            sigma = float(noise.sigma(np.asarray(ranges[beams[j]])))
            if behind < max(params.behind_m, params.behind_sigmas * sigma):
                continue  # the same surface continues, or something nearer cuts the line
            ray = nxt - origin
            toward = float(n @ ray)
            if toward <= 0.0:
                continue
            on_line = origin + ray * (lines.d[k] - float(n @ origin)) / toward  # the next ray meets the line
            last = points[end_beam]
            last_on_line = last - (float(n @ last) - lines.d[k]) * n
            spread = float(np.hypot(*(on_line - last_on_line)))
            if spread > params.max_spread_m:
                continue
            tangent = np.array([-n[1], n[0]])
            cos_view = abs(float(tangent @ (last - origin))) / max(float(np.hypot(*(last - origin))), 1e-9)
            found_line.append(k)
            found_xy.append(0.5 * (on_line + last_on_line))
            found_var.append(spread ** 2 / 12.0 + (float(noise.sigma(np.asarray(ranges[end_beam]))) * cos_view) ** 2)
    if not found_line:
        return Edges(np.zeros(0, dtype=int), np.zeros((0, 2)), np.zeros(0))
    return Edges(np.array(found_line), np.array(found_xy), np.array(found_var))
