"""Split-and-merge line extraction from one 2-D scan (Wang et al., section III-A step 1).

Input: the points of one sweep in beam order, as (N, 2) x, y metres in one planar frame (the
scanner's own frame, or the levelled body frame the planar localizer uses), with a validity
mask. Output: a :class:`LineSet`, every line in the same frame as the points.

Algorithm (the paper's steps 1-4, made vectorised and robust):

0. Break the sweep into runs of valid beams at every gap of more than ``max_missing_beams``
   invalid beams (0, the paper's rule by default: at every invalid beam) and at every range
   discontinuity. Bridging a few invalid beams (the planar localizer does) keeps walls whole
   through scattered dropouts (dust, dark or glancing surfaces). A discontinuity: consecutive
   valid points further apart than ``max_gap_m + max_gap_per_m * r``, or than the adaptive
   breakpoint distance of Borges and Aldon (2004), ``r sin(dphi) / sin(lambda - dphi) + 3 sigma(r)``:
   the furthest the next point can be on a surface seen at ``break_grazing_deg`` (lambda, 5 deg)
   or more from the beam, ``dphi`` the angle between the two points seen from the frame origin,
   ``r`` the nearer range. On a dense scanner (0.25 deg) that is about 0.1 m at 1.5 m: a step
   between two parallel walls (a door recess seen past its edge) breaks the run there instead of
   joining the walls by a short slanted line, whose corners with both walls would be phantom
   corners a few centimetres off the real ones, each reported with millimetres of uncertainty.
   On a sparse one (1 deg) the fixed rule is the tighter everywhere beyond 0.7 m (with 10 deg
   instead of 5, the real Intel lab log replayed with its own odometry lost its heading: 22 deg
   RMS against 0.54).
   Runs with fewer than ``min_points`` points are dropped.
1.-4. Split: connect the first (A) and last (B) point of a segment, find the point C furthest
   from the chord AB; if that distance exceeds the split threshold at C's range, split into
   A-C and C-B (C belongs to both) and repeat. All segments of one level are processed in
   one pass of numpy operations (breadth-first instead of the paper's recursion, same result),
   so the cost is a few dozen numpy calls per level, not per point. Pieces with fewer than
   ``min_points`` points or a chord shorter than ``min_length_m`` are dropped at once (they
   cannot become lines). Deviation: the depth is bounded by ``max_split_levels``; a surface
   that still splits after that (foliage, a fence: each split peels off a few points) holds
   no wall and is dropped, which bounds the time on such scans.
5. Fit every segment by total least squares (orthogonal regression) from prefix sums.
   Deviation from the paper: the paper keeps the endpoint chord as the final line for speed;
   here the chord is only the split test and the final line is the least-squares fit, which
   costs no per-point work thanks to the prefix sums and is less sensitive to the noise of
   the two end points (the heading tracker relies on the line directions).
6. Merge adjacent segments (sharing a split point) whose normals agree within
   ``merge_angle_deg`` and whose joint fit stays within ``merge_rms_sigmas`` noise sigmas:
   splits caused by noise are undone. A chain of mergeable pairs is merged as one group,
   unless the group's joint fit fails the RMS test (a gentle curve), then it is left split.
   A split point still shared by two segments is then dropped from both (deviation: the
   paper keeps C in both; it is rarely exactly on the corner).
7. Keep the lines at least ``min_length_m`` long (each had ``min_points`` points before its
   shared split points were dropped).

Line parameters: unit normal ``n = (cos alpha, sin alpha)`` pointing from the frame origin to
the line, and distance ``d >= 0``: the line is ``{p : n . p = d}``. ``alpha`` is an angle in
the frame's x-y plane measured from +x towards +y (for FRD frames: clockwise seen from above,
like yaw), in (-pi, pi].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LineParams:
    """Thresholds of the line extraction (defaults for a Hokuyo UTM-30LX, ~1 cm noise)."""

    noise_m: float = 0.01  # 1-sigma range noise of the scanner at 0 m, metres
    noise_per_m: float = 0.001  # growth of that 1-sigma noise per metre of range
    split_distance_m: float = 0.03  # split threshold of a noise-free scanner, metres
    split_sigmas: float = 3.0  # plus this many noise sigmas at the range of the split point
    max_gap_m: float = 0.2  # consecutive points further apart than this break a run, metres ...
    max_gap_per_m: float = 0.03  # ... plus this much per metre of range (sparse far beams)
    # ... and further than a surface seen at this grazing angle (degrees between beam and surface)
    # puts consecutive points: the adaptive breakpoint distance (module docstring, step 0); 0: off.
    break_grazing_deg: float = 5.0
    # A run bridges at most this many consecutive invalid beams. 0 (the paper): every invalid beam
    # breaks a run. The planar localizer, whose heading the gyro predicts, bridges 10 (2.5 deg on a
    # UTM-30LX): scattered dropouts then keep walls whole. Not by default: on the real URG-04LX
    # recording (61 % of its beams invalid) a heading tracked from lines alone, without a gyro,
    # aliased by 90 deg once over its 63 s when even single dropouts were bridged.
    max_missing_beams: int = 0
    merge_angle_deg: float = 2.0  # adjacent segments whose normals differ less may merge, degrees
    merge_rms_sigmas: float = 2.0  # ... if their joint fit RMS is within this many noise sigmas
    min_points: int = 6  # fewer points: no line
    min_length_m: float = 0.15  # shorter: no line, metres
    max_split_levels: int = 24  # split depth bound: walls need < 10; rough surfaces are dropped
    model_floor_m: float = 0.002  # 1-sigma model error added to every fit (wall roughness), metres

    def sigma(self, range_m: np.ndarray) -> np.ndarray:
        """1-sigma range noise in metres at ``range_m`` metres."""
        return self.noise_m + self.noise_per_m * range_m

    def split_threshold(self, range_m: np.ndarray) -> np.ndarray:
        """How far (m) a point ``range_m`` metres away may lie off a segment's chord and still not split it."""
        return self.split_distance_m + self.split_sigmas * self.sigma(range_m)


@dataclass(frozen=True)
class LineSet:
    """K lines in beam order, as parallel arrays (all in the frame of the input points)."""

    alpha: np.ndarray  # (K,) normal angle, rad, from +x towards +y, in (-pi, pi]
    d: np.ndarray  # (K,) distance from the frame origin, metres, >= 0
    start: np.ndarray  # (K, 2) first point in beam order, projected onto the line, metres
    end: np.ndarray  # (K, 2) last point in beam order, projected onto the line, metres
    centroid: np.ndarray  # (K, 2) mean of the points, metres
    n_points: np.ndarray  # (K,) int, points in the fit
    length: np.ndarray  # (K,) |end - start|, metres
    rms: np.ndarray  # (K,) RMS orthogonal residual of the fit, metres
    alpha_var: np.ndarray  # (K,) variance of alpha, rad^2 (from residuals and point spread)
    offset_var: np.ndarray  # (K,) variance of the line's normal offset at the centroid, m^2
    range_m: np.ndarray  # (K,) mean range of the points, metres
    first_beam: np.ndarray  # (K,) int, index of the first beam in the input array
    last_beam: np.ndarray  # (K,) int, index of the last beam

    @property
    def count(self) -> int:
        return int(self.alpha.shape[0])

    def normal_error_at(self, k: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """How lines ``k`` (indices) are uncertain along their normals at the points ``xy`` (len(k), 2)
        (frame of the lines, metres): (lever (len(k),) m: signed distance along each line's tangent
        (-sin alpha, cos alpha) from its centroid to the point; variance (len(k),) m^2 of the line's
        normal offset there, ``offset_var + alpha_var * lever^2``: a direction error swings the line
        about its centroid). The origin gives the variance of ``d`` (the foot of the normal)."""
        c, s = np.cos(self.alpha[k]), np.sin(self.alpha[k])
        lever = (xy[:, 1] - self.centroid[k, 1]) * c - (xy[:, 0] - self.centroid[k, 0]) * s
        return lever, self.offset_var[k] + self.alpha_var[k] * lever ** 2


def extract_lines(points: np.ndarray, valid: np.ndarray | None = None, params: LineParams = LineParams(),
                  ranges: np.ndarray | None = None) -> LineSet:
    """Lines of one sweep.

    ``points``: (N, 2) metres in beam order (invalid rows are ignored, may hold anything);
    ``valid``: (N,) bool, default all finite rows; ``ranges``: (N,) measured ranges in metres
    for the noise model, default the distance of each point from the frame origin.
    """
    if valid is None:
        valid = np.isfinite(points).all(axis=1)
    beams = np.flatnonzero(valid)
    pts = points[beams]
    rng = np.hypot(pts[:, 0], pts[:, 1]) if ranges is None else ranges[beams]
    starts, ends = _runs(beams, pts, rng, params)
    if starts.size == 0:
        return _empty()
    starts, ends = _split(pts, rng, starts, ends, params)
    if starts.size == 0:
        return _empty()
    prefix = _prefix_sums(pts, rng)
    starts, ends, fit = _merge(prefix, rng, starts, ends, params)
    return _line_set(fit, pts, beams, starts, ends, params)


def _empty() -> LineSet:
    z = np.zeros(0)
    zi = np.zeros(0, dtype=int)
    z2 = np.zeros((0, 2))
    return LineSet(z, z, z2, z2, z2, zi, z, z, z, z, z, zi, zi)


def _runs(beams: np.ndarray, pts: np.ndarray, rng: np.ndarray,
          params: LineParams) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) inclusive indices into ``pts`` of the unbroken runs with enough points."""
    if pts.shape[0] < params.min_points:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    step = pts[1:] - pts[:-1]
    gap = np.hypot(step[:, 0], step[:, 1])
    near = np.minimum(rng[1:], rng[:-1])
    limit = params.max_gap_m + params.max_gap_per_m * near
    # Adaptive breakpoint: its distance is at least 3 sigma(near), so only a step longer than that
    # (or than the fixed limit) can break the run; the trigonometry runs on those few pairs alone.
    k = np.flatnonzero(gap > np.minimum(limit, 3.0 * params.sigma(near)))
    a, b, r = pts[k], pts[k + 1], near[k]
    # The angle between the two points as seen from the frame origin.
    dphi = np.arctan2(np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])
    grazing = np.radians(params.break_grazing_deg)
    sparse = dphi >= grazing  # beams further apart than the grazing angle: the fixed rule alone
    adaptive = r * np.sin(dphi) / np.sin(np.where(sparse, np.pi / 2, grazing - dphi)) + 3.0 * params.sigma(r)
    limit[k] = np.where(sparse, limit[k], np.minimum(limit[k], adaptive))
    breaks = np.flatnonzero((beams[1:] - beams[:-1] > 1 + params.max_missing_beams) | (gap > limit))
    starts = np.concatenate(([0], breaks + 1))
    ends = np.concatenate((breaks, [pts.shape[0] - 1]))
    keep = ends - starts + 1 >= params.min_points
    return starts[keep], ends[keep]


def _split(pts: np.ndarray, rng: np.ndarray, starts: np.ndarray, ends: np.ndarray,
           params: LineParams) -> tuple[np.ndarray, np.ndarray]:
    """Split every segment at its furthest point from the chord until all are within the
    threshold (steps 1-4, level by level). Returns the final segments sorted by start."""
    done_s: list[np.ndarray] = []
    done_e: list[np.ndarray] = []
    x, y = pts[:, 0].copy(), pts[:, 1].copy()
    s, e = starts, ends
    for _ in range(params.max_split_levels):  # what is still unresolved after that is rough: dropped
        if not s.size:
            break
        n = e - s + 1
        offsets = np.cumsum(n) - n
        idx = np.arange(offsets[-1] + n[-1]) + np.repeat(s - offsets, n)
        ax, ay = x[s], y[s]
        ux, uy = x[e] - ax, y[e] - ay
        norm = np.maximum(np.hypot(ux, uy), 1e-12)
        ux /= norm
        uy /= norm
        # distance to the chord: |u x (p - a)| = |ux py - uy px - (ux ay - uy ax)|
        dist = np.abs(np.repeat(ux, n) * y[idx] - np.repeat(uy, n) * x[idx] - np.repeat(ux * ay - uy * ax, n))
        dmax = np.maximum.reduceat(dist, offsets)
        at_max = np.flatnonzero(dist == np.repeat(dmax, n))
        c = idx[at_max[np.searchsorted(at_max, offsets)]]  # every segment's first point at its maximum
        ok = dmax <= params.split_threshold(rng[c])
        done_s.append(s[ok])
        done_e.append(e[ok])
        s = np.concatenate((s[~ok], c[~ok]))
        e = np.concatenate((c[~ok], e[~ok]))
        big = (e - s + 1 >= params.min_points) & (np.hypot(x[e] - x[s], y[e] - y[s]) >= params.min_length_m)
        s, e = s[big], e[big]
    s, e = np.concatenate(done_s), np.concatenate(done_e)
    order = np.argsort(s, kind="stable")
    return s[order], e[order]


def _prefix_sums(pts: np.ndarray, rng: np.ndarray) -> np.ndarray:
    """(N + 1, 6) cumulative sums of x, y, xx, xy, yy and the range with a leading zero row."""
    x, y = pts[:, 0], pts[:, 1]
    out = np.empty((pts.shape[0] + 1, 6))
    out[0] = 0.0
    terms = out[1:]
    terms[:, :2] = pts
    np.multiply(x, x, out=terms[:, 2])
    np.multiply(x, y, out=terms[:, 3])
    np.multiply(y, y, out=terms[:, 4])
    terms[:, 5] = rng
    np.cumsum(terms, axis=0, out=terms)
    return out


@dataclass(frozen=True)
class _Fit:
    """Total-least-squares fits of index ranges (parallel arrays)."""

    alpha: np.ndarray
    d: np.ndarray
    mean: np.ndarray  # (K, 2)
    range_m: np.ndarray  # mean range of the points, m
    n: np.ndarray
    rms: np.ndarray
    spread: np.ndarray  # second moment along the line, m^2 (largest eigenvalue)


def _fit(prefix: np.ndarray, s: np.ndarray, e: np.ndarray) -> _Fit:
    """Orthogonal-regression fit of the points s..e (inclusive) of every segment."""
    n = (e - s + 1).astype(float)
    means = (prefix[e + 1] - prefix[s]) / n[:, None]  # x, y, xx, xy, yy, range
    mx, my = means[:, 0], means[:, 1]
    sxx = means[:, 2] - mx * mx
    sxy = means[:, 3] - mx * my
    syy = means[:, 4] - my * my
    half_trace = 0.5 * (sxx + syy)
    root = np.hypot(0.5 * (sxx - syy), sxy)
    alpha = 0.5 * np.arctan2(2.0 * sxy, sxx - syy) + 0.5 * np.pi  # principal axis + 90 deg
    d = np.cos(alpha) * mx + np.sin(alpha) * my
    alpha = np.where(d < 0, alpha - np.pi, alpha)  # (0, pi], flipped to (-pi, 0] when d < 0
    return _Fit(alpha, np.abs(d), means[:, :2], means[:, 5], n,
                np.sqrt(np.maximum(half_trace - root, 0.0)), half_trace + root)


def _take(fit: _Fit, sel: slice | np.ndarray) -> _Fit:
    return _Fit(fit.alpha[sel], fit.d[sel], fit.mean[sel], fit.range_m[sel], fit.n[sel], fit.rms[sel], fit.spread[sel])


def _merge(prefix: np.ndarray, rng: np.ndarray, s: np.ndarray, e: np.ndarray,
           params: LineParams) -> tuple[np.ndarray, np.ndarray, _Fit]:
    """Merge chains of adjacent, collinear segments (module docstring, step 6), then drop the
    split points shared by two segments from both. Returns the segments and their fits."""
    k = s.size
    us, ue = _unshare(s, e)
    both = _fit(prefix, np.concatenate((us, s[:-1])), np.concatenate((ue, e[1:])))  # segments, pairs
    fit, pair = _take(both, slice(0, k)), _take(both, slice(k, None))
    if k < 2:
        return us, ue, fit
    turn = np.abs((fit.alpha[1:] - fit.alpha[:-1] + np.pi) % (2.0 * np.pi) - np.pi)
    sigma = params.sigma(0.5 * (rng[s[:-1]] + rng[e[1:]]))
    mergeable = ((e[:-1] == s[1:]) & (turn <= np.radians(params.merge_angle_deg))
                 & (pair.rms <= params.merge_rms_sigmas * sigma))
    if not mergeable.any():
        return us, ue, fit
    group = np.concatenate(([0], np.cumsum(~mergeable)))
    first = np.flatnonzero(np.concatenate(([True], group[1:] != group[:-1])))
    last = np.concatenate((first[1:] - 1, [k - 1]))
    gs, ge = s[first], e[last]
    joint = _fit(prefix, gs, ge)
    good = joint.rms <= params.merge_rms_sigmas * params.sigma(0.5 * (rng[gs] + rng[ge]))
    # A group whose joint fit fails stays as its original segments.
    keep_member = np.repeat(~good, last - first + 1)
    out_s = np.concatenate((gs[good], s[keep_member]))
    out_e = np.concatenate((ge[good], e[keep_member]))
    order = np.argsort(out_s, kind="stable")
    us, ue = _unshare(out_s[order], out_e[order])
    return us, ue, _fit(prefix, us, ue)


def _unshare(s: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Segments without the split points they share with a neighbour. A split point lies on
    both lines only if a beam hit the corner exactly; usually it is the first point of the
    other wall and would bias the fit of a short line."""
    shared = e[:-1] == s[1:]
    return (s + np.concatenate(([False], shared)), e - np.concatenate((shared, [False])))


def _line_set(fit: _Fit, pts: np.ndarray, beams: np.ndarray, s: np.ndarray, e: np.ndarray,
              params: LineParams) -> LineSet:
    """Project the end points of the fitted segments onto their lines, filter, and package."""
    normal = np.empty((s.size, 2))
    normal[:, 0] = np.cos(fit.alpha)
    normal[:, 1] = np.sin(fit.alpha)
    ends = pts[np.array((s, e))]  # (2, K, 2): first points, last points
    off = (ends * normal).sum(axis=2) - fit.d
    ends -= off[:, :, None] * normal
    start, end = ends
    length = np.hypot(end[:, 0] - start[:, 0], end[:, 1] - start[:, 1])
    keep = length >= params.min_length_m  # every segment has min_points (see _split)
    # Residual variance with the 2 fitted dof removed, plus a model floor; the variances of
    # the normal angle and offset follow from the point spread along the line.
    var = fit.rms ** 2 * fit.n / np.maximum(fit.n - 2.0, 1.0) + params.model_floor_m ** 2
    return LineSet(
        alpha=fit.alpha[keep], d=fit.d[keep], start=start[keep], end=end[keep],
        centroid=fit.mean[keep], n_points=fit.n[keep].astype(int), length=length[keep],
        rms=fit.rms[keep], alpha_var=(var / (fit.n * np.maximum(fit.spread, 1e-12)))[keep],
        offset_var=(var / fit.n)[keep], range_m=fit.range_m[keep],
        first_beam=beams[s][keep], last_beam=beams[e][keep])
