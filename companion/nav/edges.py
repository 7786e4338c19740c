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

Mixed pixels (``mixed_pixels``, every real scanner has them): the beam that straddles the edge may
return a range between the wall and what lies behind it, a point beyond the end along the ray. One
within the extraction's split threshold of the line joins it, so the line may run past the true end
by up to that threshold over the tangent of the view's angle to the wall (at 7 m, a wall seen at
10 deg: 0.47 m, where one beam spans 0.18 m). Such an end is known that much worse: the mean square
of that reach, uniform from 0 (not shifted), is added to its variance. Found in the realistic
corridor (mixed pixels at every second edge): a recess edge 7 m ahead was seen from 0.29 m short to
0.32 m long, scan after scan, at a claimed 2-8 cm, and the estimate went 0.23 m off along the
corridor at a 2.6 cm sigma.

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
    mixed_pixels: bool = True  # the scanner may return a range between two surfaces at a depth edge


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
    none = Edges(np.zeros(0, dtype=int), np.zeros((0, 2)), np.zeros(0))
    beams = np.flatnonzero(valid)
    if lines.count == 0 or beams.size == 0:
        return none
    # Every line end, in the order (line 0 first end, line 0 last end, line 1 first end, ...);
    # ``step`` leads away from the line.
    line = np.repeat(np.arange(lines.count), 2)
    end_beam = np.column_stack((lines.first_beam, lines.last_beam)).ravel().astype(int)
    step = np.tile([-1, 1], lines.count)
    j = np.searchsorted(beams, end_beam) + step  # the next valid beam's place among the valid ones
    inside = (j >= 0) & (j < beams.size)
    nxt_beam = beams[np.clip(j, 0, beams.size - 1)]
    keep = inside & (np.abs(nxt_beam - end_beam) <= 1 + params.max_missing_beams)  # else nothing says why it ends
    alpha, d = lines.alpha[line], lines.d[line]
    n = np.column_stack((np.cos(alpha), np.sin(alpha)))
    nxt = points[nxt_beam]
    behind = np.einsum("ik,ik->i", n, nxt) - d
    keep &= behind >= np.maximum(params.behind_m, params.behind_sigmas * noise.sigma(ranges[nxt_beam]))
    ray = nxt - origin
    toward = np.einsum("ik,ik->i", n, ray)
    keep &= toward > 0.0  # else the next ray never meets the line
    line, end_beam, n, d, ray, toward = line[keep], end_beam[keep], n[keep], d[keep], ray[keep], toward[keep]
    on_line = origin + ray * ((d - n @ origin) / toward)[:, None]  # where the next ray meets the line
    last = points[end_beam]
    last_on_line = last - (np.einsum("ik,ik->i", n, last) - d)[:, None] * n
    spread = np.hypot(*(on_line - last_on_line).T)
    ok = spread <= params.max_spread_m
    tangent = np.column_stack((-n[:, 1], n[:, 0]))
    view = last - origin
    cos_view = np.abs(np.einsum("ik,ik->i", tangent, view)) / np.maximum(np.hypot(*view.T), 1e-9)
    var = spread ** 2 / 12.0 + (noise.sigma(ranges[end_beam]) * cos_view) ** 2
    if params.mixed_pixels:  # how far past the end a mixed pixel joined to the line may reach
        sin_view = np.sqrt(np.maximum(1.0 - cos_view * cos_view, 0.0))
        reach = noise.split_threshold(ranges[end_beam]) * cos_view / np.maximum(sin_view, 1e-9)
        var += reach * reach / 3.0
    return Edges(line[ok], 0.5 * (on_line[ok] + last_on_line[ok]), var[ok])
