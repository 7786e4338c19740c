"""Height above the floor from the vertical scanner (Wang et al. section III-B).

The vertical scanner's plane contains body x and z (mount roll 90 deg: sensor y = body down).
Steps: split-and-merge lines on its scan (lines.py, in the sensor frame); keep the lines whose
direction is floor-like once roll and pitch are compensated; sort them by how far below the
scanner they lie; keep the furthest ones (within ``furthest_tolerance_m``) and among them the
one whose height has the least variance (below): the floor (the paper: the longest; on an uneven
floor a long line far ahead is worse than a shorter one under the vehicle). Surfaces above the
floor (a table top) are floor-like but nearer, so the floor wins as long as some beams reach it.

Attitude compensation, exact for any mount: let ``G = L(roll, pitch) M`` map sensor axes to
the levelled frame (``M`` the mount rotation, ``L`` the attitude without yaw). A sensor-plane
point (u, v) is ``g . (u, v)`` metres below the scanner, ``g = (G[2,0], G[2,1])``. So the floor
is the sensor-plane line with unit normal ``g / |g|`` (its expected direction: the gradient
test), and every point on it, its centroid ``c`` too, lies ``g . c`` below the scanner. With the
scan plane vertical (no roll) ``|g| = 1`` and pitch only tilts the floor line; roll tilts the
plane sideways and ``|g| = cos(roll)`` for the usual mount. The body origin is ``(L p_mount)_z``
above the scanner (``p_mount`` the mount offset, FRD), which is added.

The paper takes ``H = |g| d`` (``d`` the fitted line's perpendicular distance), which extends the
fitted line back under the scanner: a far floor line a few degrees off (range noise at grazing
angles, mixed pixels where the floor meets a wall) levers ``d`` by its range times the sine of
that (in the realistic arena 5 deg at 2.6 m: 0.2 m while the line's centroid was within 2 cm), and
the furthest such line was the one taken. The centroid's depth alone instead levers the attitude's
error (0.3 deg at 2.6 m: 1.4 cm). So each line's direction is the fit's and the levelled floor's
(``attitude_sd_deg``) combined by their variances, and the height is that line's through the
centroid: its variance the offset's at the centroid plus the combined direction's times the lever
to under the scanner. An exact attitude gives ``g . c``, a useless one the paper's ``|g| d``.
The fit's direction is that of the floor where the line lies, which is not level on a real floor
(``floor_tilt_sd_deg`` 1-sigma, in its variance): in the realistic corridor with 4 mm of relief,
floor lines 1-4 m ahead put the floor under the vehicle 10-30 mm off at a 6 mm sigma.

Deviation: a jump of the height by more than ``jump_m`` between fixes is reported degraded (it
is what a step in the floor seen as the floor looks like, e.g. when only a table is in view).
And with the fused height given (``expected``: what the IMU carried since the last fixes), a
floor candidate NEARER than that by more than ``jump_m`` and three sigmas is no fix at all
(lost): with the floor hidden, a table top is the furthest floor-like line, and as a fix it
would be a confident wrong height once the fusion re-seeds to it (its relock after a second of
gated fixes: the vehicle climbs by the table's height). A candidate further than a well-known
expected height is the floor (beams never reach below it).

A surface seen beside the floor stands in for it (as ArduPilot's EKF3 carries a terrain offset
under its rangefinder): whenever the floor is found consistent with a fused height known within
``jump_m / 2`` (1 sigma) and a floor-like line lies above it by more than ``jump_m``, the
estimator remembers that step: how far above the floor, and where (given the vehicle's map pose:
its line's centroid), averaged over sightings. A surface may be a step if it lies as far above the
floor within three sigmas (the fused height's, the surface's and the step's) and near the step's
place (within ``step_margin_m`` beyond both lines' half lengths; anywhere when either place is
unknown). With the floor hidden and the furthest surface refused as above, the one step confirmed
by ``step_confirm_scans`` sightings that the surface may be turns it into a degraded fix: the
surface's height plus the step, its variance the sum. Hovering over a table no longer leaves the
height to the IMU alone (a realistic patrol held 1.7 s over one, the height drifting 15 cm). Two
remembered steps that both may be it give no fix: which surface it is, the scan cannot tell.

The same memory guards a fused height too unsure to refuse a table top (3 sigma beyond the
table's height: after seconds without a fix, or the filter not initialised): a furthest surface
that a confirmed step may be is no fix (lost) unless the scan tells it is the floor: it is longer
than that step was ever seen (by ``step_length_margin_m``), or the step itself is in view above it.
Away from the remembered tables the floor is taken as before; without the vehicle's pose every
step is near, and a short floor line (between obstacles, by a wall) waits for a longer one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from companion.frames import rotation_from_euler
from companion.nav.lines import LineParams, LineSet, extract_lines
from companion.messages import Scan

HeightState = Literal["ok", "degraded", "lost"]


@dataclass(frozen=True)
class HeightParams:
    """Thresholds of the height fix (line defaults for a URG-04LX: ~1 cm, 3 % beyond 1 m)."""

    # No adaptive breakpoint (lines.py step 0): this scanner sees the floor at grazing angles by
    # design (with a 10 deg breakpoint a touchdown in the realistic arena took a 0.34 m height error).
    lines: LineParams = field(default_factory=lambda: LineParams(noise_m=0.01, noise_per_m=0.01, break_grazing_deg=0.0))
    floor_angle_tolerance_deg: float = 10.0  # a floor line's normal within this of the expected
    furthest_tolerance_m: float = 0.1  # floor candidates: within this of the furthest one, metres
    min_length_m: float = 0.3  # shorter floor-like lines are ignored, m; a longer one is a fix like any other
    min_gradient: float = 0.3  # |g| below this: the scan plane is too flat to see the floor
    jump_m: float = 0.2  # a larger change from the previous fix is reported, metres
    variance_floor_m2: float = 0.005 ** 2  # model floor of the variance, m^2
    attitude_sd_deg: float = 0.3  # 1-sigma error of the autopilot's roll and pitch, degrees
    floor_tilt_sd_deg: float = 0.3  # 1-sigma tilt of the floor under a line against the level, degrees
    step_confirm_scans: int = 3  # sightings beside the floor before a step stands in for it
    max_steps: int = 4  # steps remembered (the most recently seen), e.g. tables in the room
    step_length_margin_m: float = 0.3  # a floor line longer than a step was ever seen by this is not that step, m
    step_margin_m: float = 0.5  # a surface this near a step (beyond both lines' half lengths) may be it, m


@dataclass(frozen=True)
class HeightFix:
    """Height of the body origin above the floor (metres, positive up; NED z = -height_m)."""

    height_m: float  # 0.0 when lost
    variance: float  # m^2 (large when lost)
    state: HeightState
    reason: str
    floor_lines: int  # floor-like lines seen


LOST_VARIANCE_M2 = 100.0


@dataclass(frozen=True)
class _Surface:
    """A floor-like line of one scan: how far above the floor (or the expected floor) it lies (m),
    the variance of that (m^2), its length (m) and where its centroid lies (north, east m in the
    map; None without the vehicle's pose)."""

    above_m: float
    variance: float
    length_m: float
    where_ne: tuple[float, float] | None


@dataclass
class _Step:
    """A floor-like surface seen above the floor: how far above (m), its variance (m^2), the longest
    line it gave (m), where (north, east m: the mean of its sightings' centroids; None if seen
    without a pose) and its sightings."""

    above_m: float
    variance: float
    length_m: float
    where_ne: tuple[float, float] | None
    sightings: int = 1

    def matches(self, surface: _Surface) -> bool:
        """Whether ``surface`` lies as far above the floor as this step, within three sigmas."""
        return abs(surface.above_m - self.above_m) <= 3.0 * math.sqrt(surface.variance + self.variance)

    def near(self, surface: _Surface, margin_m: float) -> bool:
        """Whether ``surface`` lies within ``margin_m`` of this step beyond both lines' half lengths
        (True when either place is unknown)."""
        if self.where_ne is None or surface.where_ne is None:
            return True
        reach = (self.length_m + surface.length_m) / 2.0 + margin_m
        return math.dist(self.where_ne, surface.where_ne) <= reach

    def add(self, surface: _Surface, variance_floor: float) -> None:
        """Count another sighting in: the longest line kept, the place the mean of the sightings',
        how far above the floor inverse-variance weighted (the variance not below ``variance_floor``;
        both variances 0, it is kept as it is)."""
        self.length_m = max(self.length_m, surface.length_m)
        self.sightings += 1
        if surface.where_ne is not None:
            if self.where_ne is None:
                self.where_ne = surface.where_ne
            else:
                n, e = self.where_ne
                self.where_ne = (n + (surface.where_ne[0] - n) / self.sightings,
                                 e + (surface.where_ne[1] - e) / self.sightings)
        total = self.variance + surface.variance
        if total > 0.0:  # both 0 (noise-free data, no noise or model error declared): nothing to weigh
            self.above_m += self.variance / total * (surface.above_m - self.above_m)
            self.variance = max(self.variance * surface.variance / total, variance_floor)


class HeightEstimator:
    """Height above the floor from scans of a vertical scanner."""

    def __init__(self, mount_position: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 mount_rpy: tuple[float, float, float] = (math.pi / 2, 0.0, 0.0),
                 params: HeightParams = HeightParams()) -> None:
        """``mount_position``: scanner origin in the body frame (FRD, metres); ``mount_rpy``:
        its roll, pitch, yaw relative to the body (radians; default: plane = body x-z)."""
        self.mount_position = np.asarray(mount_position, dtype=float)
        self.mount_rotation = rotation_from_euler(*mount_rpy)
        self.params = params
        self._previous: float | None = None
        self._steps: list[_Step] = []  # the most recently seen last

    def floor_beam_fraction(self, scan: Scan) -> float:
        """Where in its sweep (0: first beam, 1: last) the scanner looks straight down the body's z
        axis (its beam nearest that): when it sees the floor under the vehicle."""
        m = self.mount_rotation
        down = m[2, 0] * np.cos(scan.angles_rad) + m[2, 1] * np.sin(scan.angles_rad)
        return float(np.argmax(down)) / max(scan.angles_rad.size - 1, 1)

    def update(self, scan: Scan | np.ndarray, roll: float = 0.0, pitch: float = 0.0,
               valid: np.ndarray | None = None, expected: tuple[float, float] | None = None,
               pose: tuple[float, float, float] | None = None) -> HeightFix:
        """Height from one scan (a Scan, or (N, 2) sensor-plane points in beam order with an
        optional validity mask) at body ``roll`` and ``pitch`` (radians); ``expected``: the
        fused height above the floor and its 1-sigma (m) at the scan's time, if known; ``pose``:
        the vehicle's map pose (north m, east m, yaw rad), if known: where the surfaces seen lie."""
        p = self.params
        points, ok, ranges = _sensor_points(scan, valid)
        level = rotation_from_euler(roll, pitch, 0.0)
        g = (level @ self.mount_rotation)[2, :2]
        gain = float(np.hypot(g[0], g[1]))
        if gain < p.min_gradient:
            return _lost(f"scan plane too flat to see the floor (|g| = {gain:.2f})", 0)
        lines = extract_lines(points, ok, p.lines, ranges)
        floor_normal = math.atan2(g[1], g[0])
        off = np.angle(np.exp(1j * (lines.alpha - floor_normal)))
        floor = np.flatnonzero((np.abs(off) <= math.radians(p.floor_angle_tolerance_deg))
                               & (lines.length >= p.min_length_m))
        if floor.size == 0:
            return _lost("no floor-like line", 0)
        heights, variances = self._floor_heights(lines, floor, off[floor], floor_normal, gain)
        heights += float((level @ self.mount_position)[2])
        furthest = np.flatnonzero(heights >= heights.max() - p.furthest_tolerance_m)
        k = int(furthest[np.argmin(variances[furthest])])
        height, variance = float(heights[k]), float(variances[k])
        if expected is not None:
            where = self._where(lines.centroid[floor], level, pose)
            lengths = lines.length[floor].tolist()
            above = expected[0] - height
            # The furthest lines are one surface: as long as its longest piece, the fix its surest one.
            longest = max(lengths[j] for j in furthest.tolist())
            candidate = _Surface(above, variance + expected[1] ** 2, longest, where[k] if where else None)
            if above > max(p.jump_m, 3.0 * math.sqrt(candidate.variance)):
                return self._stand_in(height, variance, candidate, int(floor.size))
            # The lines above the candidate (by more than jump_m): steps, if the candidate is the floor.
            seen = [_Surface(height - h, variance + v, length, where[j] if where else None)
                    for j, (h, v, length) in enumerate(zip(heights.tolist(), variances.tolist(), lengths))
                    if height - h > p.jump_m]
            if expected[1] < p.jump_m / 2.0 and abs(above) <= 3.0 * math.sqrt(candidate.variance):
                self._remember_steps(seen)
            elif step := self._could_be_a_step(candidate, seen):
                return _lost(f"the furthest floor-like surface may be the floor or the surface seen "
                             f"{step.above_m:.2f} m above it (the fused height is known to {expected[1]:.2f} m)",
                             int(floor.size))
        return self._fix(height, variance, int(floor.size))

    def _where(self, centroids: np.ndarray, level: np.ndarray,
               pose: tuple[float, float, float] | None) -> list[tuple[float, float]] | None:
        """Where (north, east m in the map) the sensor-plane ``centroids`` (n, 2) m lie, the body
        levelled by ``level`` at map ``pose`` (north m, east m, yaw rad); None without a pose."""
        if pose is None:
            return None
        body = centroids @ self.mount_rotation[:, :2].T + self.mount_position
        forward, right = (body @ level.T)[:, :2].T
        c, s = math.cos(pose[2]), math.sin(pose[2])
        return list(zip((pose[0] + c * forward - s * right).tolist(), (pose[1] + s * forward + c * right).tolist()))

    def _floor_heights(self, lines: LineSet, k: np.ndarray, off: np.ndarray, floor_normal: float,
                       gain: float) -> tuple[np.ndarray, np.ndarray]:
        """How far below the scanner (m) lines ``k`` put the floor, and the variances (m^2): each
        line through its centroid, its direction the fit's (``off`` rad from the levelled floor's
        normal ``floor_normal``; its variance the fit's plus the floor's tilt) and the attitude's
        combined by their variances."""
        attitude_var = math.radians(self.params.attitude_sd_deg) ** 2
        fit_var = lines.alpha_var[k] + math.radians(self.params.floor_tilt_sd_deg) ** 2
        total = np.maximum(attitude_var + fit_var, 1e-18)  # both 0: an exact attitude and fit agree
        alpha = floor_normal + off * attitude_var / total
        alpha_var = attitude_var * fit_var / total
        c, s = np.cos(alpha), np.sin(alpha)
        centroid = lines.centroid[k]
        d = centroid[:, 0] * c + centroid[:, 1] * s
        lever = centroid[:, 1] * c - centroid[:, 0] * s  # from the foot of the normal to the centroid, m
        return gain * d, gain * gain * (lines.offset_var[k] + alpha_var * lever ** 2) + self.params.variance_floor_m2

    def _remember_steps(self, seen: list[_Surface]) -> None:
        """Average the surfaces ``seen`` above the floor (their ``above_m`` from it) into the
        remembered steps: a step is one that lies as far above the floor, near the same place."""
        p = self.params
        for surface in seen:
            step = next((s for s in reversed(self._steps)
                         if s.matches(surface) and s.near(surface, p.step_margin_m)), None)
            if step is None:
                if len(self._steps) == p.max_steps:
                    self._steps.pop(0)
                self._steps.append(_Step(surface.above_m, surface.variance, surface.length_m, surface.where_ne))
            else:
                step.add(surface, 2.0 * p.variance_floor_m2)
                self._seen_last(step)

    def _confirmed_steps(self, surface: _Surface) -> list[_Step]:
        """The remembered steps, confirmed by ``step_confirm_scans`` sightings, that ``surface`` (its
        ``above_m`` from the expected floor, the fused height's variance in its own) may be: as far
        above the floor, near the same place."""
        p = self.params
        return [s for s in self._steps
                if s.sightings >= p.step_confirm_scans and s.matches(surface) and s.near(surface, p.step_margin_m)]

    def _could_be_a_step(self, candidate: _Surface, seen: list[_Surface]) -> _Step | None:
        """A confirmed step that the floor ``candidate`` may be instead of the floor, None if none.
        It is the floor if it is longer than the step was ever seen (by ``step_length_margin_m``),
        or if the scan shows the step itself above it (``seen``: the scan's surfaces above the
        candidate, their ``above_m`` from it)."""
        margin = self.params.step_length_margin_m
        return next((s for s in self._confirmed_steps(candidate)
                     if candidate.length_m <= s.length_m + margin and not any(map(s.matches, seen))), None)

    def _seen_last(self, step: _Step) -> None:
        """Move ``step`` to the end of the list: the most recently seen, the last to be forgotten."""
        self._steps.remove(step)
        self._steps.append(step)

    def _stand_in(self, height: float, variance: float, surface: _Surface, count: int) -> HeightFix:
        """The fix from ``surface``, the furthest floor-like line, ``height`` m below the body
        (variance m^2) and ``surface.above_m`` above the expected floor (the floor hidden): the one
        confirmed step it may be, else lost."""
        steps = self._confirmed_steps(surface)
        if len(steps) != 1:
            reason = "more than one remembered surface matches it" if steps else "the floor is not in view"
            return _lost(f"the furthest floor-like surface is {surface.above_m:.2f} m above the expected floor "
                         f"(a table top?): {reason}", count)
        step = steps[0]
        self._seen_last(step)
        self._previous = height + step.above_m
        return HeightFix(height + step.above_m, variance + step.variance, "degraded",
                         f"the floor hidden: a surface seen {step.above_m:.2f} m above it stands in", count)

    def _fix(self, height: float, variance: float, count: int) -> HeightFix:
        p = self.params
        previous, self._previous = self._previous, height
        if previous is not None and abs(height - previous) > p.jump_m:
            return HeightFix(height, variance, "degraded",
                             f"height jumped by {height - previous:+.2f} m: a step in the floor?", count)
        return HeightFix(height, variance, "ok", "", count)


def _lost(reason: str, count: int) -> HeightFix:
    return HeightFix(0.0, LOST_VARIANCE_M2, "lost", reason, count)


def _sensor_points(scan: Scan | np.ndarray,
                   valid: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (N, 2) in the sensor plane, valid (N,), ranges (N,)), invalid rows zeroed."""
    if isinstance(scan, Scan):
        ok = scan.valid & np.isfinite(scan.ranges_m)
        r = np.where(ok, scan.ranges_m, 0.0)
        return np.column_stack((r * np.cos(scan.angles_rad), r * np.sin(scan.angles_rad))), ok, r
    pts = np.asarray(scan, dtype=float)
    ok = np.isfinite(pts).all(axis=1) if valid is None else valid & np.isfinite(pts).all(axis=1)
    pts = np.where(ok[:, None], pts, 0.0)
    return pts, ok, np.hypot(pts[:, 0], pts[:, 1])
