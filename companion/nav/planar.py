"""Planar localization from the horizontal scanner (Wang et al. section III-A), plus global
relocalization.

Frames. The scan is in the SENSOR frame (companion/messages.py). The scanner sits at ``Mount2D``
in the body frame (FRD: x forward, y right, z down, metres; yaw from body x towards body y).
Every scan is first mapped into the LEVELLED BODY frame: origin at the body origin, x/y axes
horizontal, rotated from the world by the body yaw only. With roll and pitch the scan plane is
tilted; the 3-D hit points (mount offset included) are rotated by the attitude and projected
onto the horizontal plane, which is exact for vertical walls (scaling x by cos(pitch) and y by
cos(roll) is the first-order form of this projection). The world is LOCAL_NED (x north, y east).

Transform (derived for OUR frames; it replaces eq. 5-6 of the paper, whose printed matrix
[[cos, sin], [-sin, cos]] is R(-psi), i.e. the opposite sign convention for psi or for the
scanner angles, and inconsistent with its own eq. 2 where angles add): a levelled-body point
``q`` is in the world at ``p + R(yaw) q`` with ``R(yaw) = [[cos, -sin], [sin, cos]]`` acting on
(north, east): body x at yaw ``psi`` points to (cos psi, sin psi), body y (right) to
(-sin psi, cos psi). Directions therefore add: a sensor angle ``a`` is ``yaw + a`` in the world,
which is what heading.py (eq. 2) uses.

One update (eqs. 2-8):

1. lines (lines.py), corners from adjacent non-parallel lines (corners.py);
2. heading from the wall directions modulo the wall angle (heading.py, eqs. 2-4), predicted
   from the previous heading plus the optional gyro yaw change;
3. observed corners to the world with the previous (or prior) position and the new heading
   (eq. 5 with our R), mutual nearest neighbours among the known corners within ``gate_m``
   (beyond the paper: with map walls, only among those whose walls run the same ways,
   corner_shape.py: a door recess's back and mouth corners lie within the gate of each other);
4. position = previous + weighted mean displacement (eqs. 7-8). Deviation: the weights are the
   inverse traces of the corner covariances (corners.py) rather than a bare range law; they
   fall with range as the paper asks, and also with poor line fits and short lever arms.
   Outliers: iteratively drop matches whose residual exceeds ``outlier_k`` times the median
   residual (at least ``outlier_floor_m``), then recompute (needs 3 or more matches).
5. covariance (x, y, yaw): the weighted mean's ``sum(W_j^2 C_j)`` (``W_j`` the normalised
   weights, ``C_j`` the world corner covariances), scaled up by the residual chi-square per
   degree of freedom when the corners disagree more than their covariances say, plus the
   heading variance through the lever arm of the mean corner (a heading error swings the
   corners around the vehicle), and the x/y-yaw cross terms of that lever arm. With ONE
   corner the position is still determined (the corner's map position and the wall heading fix
   it), with that corner's covariance (from its two line fits, growing with range) plus the
   lever-arm term, but nothing cross-checks the association: the covariance is multiplied by
   ``single_corner_inflation`` and the state is degraded.

Walls (beyond the paper): when no corner matches while tracking, the observed lines lying on
map walls (parallel within ``wall_angle_tolerance_deg``, within ``wall_gate_m`` along the normal,
overlapping the wall within ``wall_overlap_margin_m``) each measure the position along their
normal (point-to-line, weight from the line's offset variance at the vehicle plus
``map_error_m``). A matched line ending at an occluding edge (edges.py: the nearer surface at a
range jump) within ``edge_gate_m`` of its map wall's end, where the map lists a corner (within
``edge_corner_m``), also measures the position along that wall (the end's position, with the
variance of the beam spacing there). Walls in two directions, or one direction and such an end,
give the position; a corridor's parallel walls alone give the cross-track position only, and the
fix reports the along-track direction with ``lost_variance_m2`` (``walls_matched`` > 0,
``matched`` 0, ``degraded``, measured). As for corners, the covariance is scaled up by the
residual chi-square per degree of freedom when the wall lines disagree more than their variances
say: a wall a few centimetres off its map line, or furniture along a wall taken for it (the lines'
own residuals; the ends are left out: along a corridor they are the only along-track measurement).

States: ``tracking`` (>= ``min_matches`` corners), ``degraded`` (1 corner; walls only; or
neither for fewer than ``lost_after_frames`` frames: then the fix is not a measurement,
``measured`` is False and the position is the previous one with a growing covariance; or the
heading near its inter-frame limit), ``lost`` (nothing matched for ``lost_after_frames``
frames, or the wall directions are ambiguous; tracking then resumes only with ``min_matches``
corners, and only if no other position within the drift since the last fix (3 sigma of
``coast_growth_m2`` per scan, plus the gate) matches as many, or by relocalization, by corners or
by walls). A fix that is not ``measured`` must not be sent to the autopilot.

Relocalization (beyond the paper), tried when lost or when no pose is known: the wall directions
fix the heading modulo the wall angle, so the candidate headings are a small discrete set (360 /
A of them). For each, every correspondence (observed corner i, map corner a) of the same shape
(their walls running the same ways at that heading, corner_shape.py) proposes a translation
(corner_hypotheses.py); its score is the number of observed corners that then land within
``reloc_tolerance_m`` of a map corner of their shape (a score of 2 or more means an observed
pair matches a map pair in distance AND direction). The best distinct poses are refined by the
normal association and update; if the walls are known, the fraction of scan points lying on a
wall breaks ties (it sees, for instance, which room's doors the beams go through). Only a clear
winner is accepted (more corners than every other distinct pose, or as many but a wall fraction
``reloc_wall_margin`` higher). With a pose held (lost after coasting), the hypotheses within
``reloc_local_m`` of it (or that drift, if more) and at the heading nearest its yaw are tried
first and the whole map only when they have no clear winner: a map has look-alike places, and
the held pose says which one the vehicle is more likely in. With a pose held, the heading
measured and no corner winner, the walls are searched near the held pose (within
``reloc_local_m`` or the drift): every position at which an observed line of each of two wall
directions lies on a map wall (wall_hypotheses.py), scored by the fraction of scan points then
on walls; a clear winner (every position more than ``reloc_distinct_m`` away at least
``reloc_wall_margin`` behind) whose walls fix the position in both directions is a candidate
like a corner one (a real building's rooms hold too few corners for a 1-deg scanner to see
three, and most of its scans see walls of two directions). A winner within ``jump_m`` /
``jump_rad`` of the held pose resumes tracking at once. A jump (or a first pose) is only a
candidate (:attr:`PlanarLocalizer.candidate`, reloc_candidate.py) until ``reloc_confirm_frames`` scans found it,
each within ``reloc_confirm_gate_m`` of the previous one moved by the motion given with the
scans (``moved_m``: odometry or the fused IMU; at 40 scans/s without it the gate allows 12 m/s)
and turned by the gyro's yaw change within ``reloc_confirm_gate_rad``. A scan that can test
nothing (too few corners, no clear winner) carries the candidate along with that motion, up to
``reloc_confirm_frames`` such scans in a row; a scan finding another pose starts over. Meanwhile
the fix stays lost (None without a pose), never a confident wrong pose. The confirming fix has
``relocalized`` True, so the daemon increments ``reset_counter``. For telemetry the localizer keeps
the hypotheses the newest relocalization weighed with their scores (:attr:`PlanarLocalizer.hypotheses`,
reloc_candidate.py RelocHypothesis: the best ``reloc_hypotheses_reported`` of the corner search that
decided, the local one when it had a clear winner, else the global one; then those of the wall
search, if it ran) and why it found no pose (:attr:`PlanarLocalizer.reloc_outcome`); both are
emptied once a pose is measured or set again, so they are empty while tracking.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from companion.frames import planar_rotation, rotation_from_euler, wrap_pi
from companion.nav.corner_fix import corner_fix_covariance
from companion.nav.corner_shape import map_corner_rays, observed_rays, ray_limits, shapes_agree
from companion.nav.corners import CornerParams, Corners, find_corners
from companion.nav.edges import EdgeParams, Edges, occluding_ends
from companion.nav.heading import (UNMEASURED_VARIANCE_RAD2, HeadingParams, HeadingResult,
                                   heading_hypotheses, track_heading)
from companion.nav.lines import LineParams, LineSet, extract_lines
from companion.nav.reloc_candidate import RelocCandidate, RelocHypothesis, carried, found_again, ranked_hypotheses
from companion.nav.corner_hypotheses import distinct_poses, pose_hypotheses
from companion.nav.wall_fix import WallMap, wall_fix
from companion.nav.wall_hypotheses import MapWalls, wall_hypotheses
from companion.nav.wall_grid import WallGrid
from companion.messages import Scan

PlanarState = Literal["tracking", "degraded", "lost"]


# Consecutive invalid beams a wall's run bridges in the horizontal scan (lines.py: scattered
# dropouts keep walls whole; the heading between scans is predicted with the gyro).
BRIDGED_DROPOUTS = 10


@dataclass(frozen=True)
class Mount2D:
    """Pose of the horizontal scanner in the body frame (FRD, metres, radians)."""

    x_m: float = 0.0  # forward of the body origin
    y_m: float = 0.0  # right of the body origin
    yaw_rad: float = 0.0  # sensor x from body x towards body y
    z_m: float = 0.0  # below the body origin (negative: above); used only with roll/pitch


@dataclass(frozen=True)
class PlanarParams:
    """Thresholds of the planar localizer (stage thresholds in their own dataclasses)."""

    lines: LineParams = field(default_factory=lambda: LineParams(max_missing_beams=BRIDGED_DROPOUTS))
    heading: HeadingParams = field(default_factory=HeadingParams)
    corners: CornerParams = field(default_factory=CornerParams)
    gate_m: float = 0.5  # association gate around a predicted corner, metres
    # With map walls, a pair needs each wall at the observed corner within this of one at the map's, degrees
    corner_shape_tolerance_deg: float = 20.0
    corner_shape_short_tolerance_deg: float = 70.0  # ... this for a wall seen shorter than heading.min_length_m
    outlier_k: float = 3.0  # drop a match beyond this many median residuals ...
    outlier_floor_m: float = 0.05  # ... and beyond this, metres
    min_matches: int = 2  # fewer matched corners: degraded
    lost_after_frames: int = 5  # frames without a matched corner before lost
    coast_growth_m2: float = 0.01  # x and y variance added per frame without a match, m^2
    single_corner_inflation: float = 4.0  # covariance factor for a fix from one corner
    lost_variance_m2: float = 100.0  # x and y variance reported while lost, m^2
    reloc_min_inliers: int = 3  # corners a relocalization must match
    reloc_tolerance_m: float = 0.15  # an observed corner lands on a map corner within this
    reloc_distinct_m: float = 0.5  # poses closer than this (same heading) are one candidate
    reloc_max_corners: int = 10  # best observed corners used for the search
    reloc_candidates: int = 30  # at most this many distinct poses (within 1 of the best score) compared
    reloc_wall_tolerance_m: float = 0.1  # a scan point on a wall, metres
    reloc_wall_margin: float = 0.1  # wall fraction lead needed to break a tie in corners
    reloc_min_wall_fraction: float = 0.5  # the winner's points on walls (when walls are known)
    # Lost, more positions than this near the held pose putting lines on walls: too many look-alikes
    # (a long drift in a building of repeated walls) to tell by walls, so they resume nothing. It also
    # bounds the search's time (~4 ms for 100 positions on 1081 beams here; the real Intel and ACES
    # logs never had more than 16), which runs on every lost scan.
    reloc_wall_positions_max: int = 100
    wall_gate_m: float = 0.3  # an observed line within this of a map wall (and parallel) constrains, metres
    wall_angle_tolerance_deg: float = 3.0  # ... parallel within this, degrees
    wall_overlap_margin_m: float = 0.3  # ... and overlapping the wall's extent within this, metres
    edges: EdgeParams = field(default_factory=lambda: EdgeParams(max_missing_beams=BRIDGED_DROPOUTS))
    edge_gate_m: float = 0.5  # an occluding line end this near its map wall's end measures along it, metres ...
    edge_corner_m: float = 0.1  # ... if a map corner lies within this of that end, metres
    map_error_m: float = 0.005  # 1-sigma of a map wall's position (World.survey_error_m), metres
    # 1-sigma of the map's wall directions (World.wall_direction_error_deg), rad: added to every fix's
    # heading variance (update()), not through the lever arm to its position (see update()).
    map_heading_error_rad: float = 0.0
    floor_clearance_m: float = 0.15  # with the height known, hits this close to the floor or ceiling are dropped, metres
    jump_m: float = 0.3  # a relocalization moving the pose more than this is a reset
    jump_rad: float = math.radians(10.0)  # ... or turning it more than this
    reloc_local_m: float = 1.5  # with a pose held, hypotheses within this of it are tried first, metres
    reloc_confirm_frames: int = 3  # scans that must find a jump (none finding another) before it becomes the pose
    reloc_confirm_gate_m: float = 0.3  # ... each within this of the previous one, metres
    reloc_confirm_gate_rad: float = math.radians(5.0)  # ... and turned by the gyro's change within this
    reloc_hypotheses_reported: int = 5  # hypotheses of each search kept for telemetry (best first)


@dataclass(frozen=True)
class PlanarFix:
    """The body pose in the map: x north, y east (metres), yaw from north towards east (rad)."""

    x: float
    y: float
    yaw: float
    covariance: np.ndarray  # (3, 3) of (x, y, yaw): m^2, m rad, rad^2
    matched: int  # map corners used
    state: PlanarState
    reason: str  # why degraded or lost ("" when tracking cleanly)
    relocalized: bool  # a jump from the pose held before: increment reset_counter
    heading_status: str  # HeadingResult.status of this scan
    timing_ms: dict[str, float] = field(default_factory=dict)  # per stage, wall clock
    walls_matched: int = 0  # map walls used (point-to-line) when no corner was matched
    unmeasured: tuple[float, float] | None = None  # unit (north, east) direction no wall measures: a corridor's axis
    # Unit (north, east) direction that only wall ends measure (a corridor's axis seen with an end
    # in view), if any: their error (where between two beams the wall ends) stays the same from
    # scan to scan while the vehicle moves less than a beam spacing, so averaging fixes does not
    # shrink it; the fix's variance along it is the least the estimate can claim there.
    ends_only: tuple[float, float] | None = None
    # The corners the fix used (after the outlier test): (index into the scan's corners, index into
    # the map's corners) per pair; empty for a fix from walls alone, a coasted or a lost report.
    corner_pairs: tuple[tuple[int, int], ...] = ()

    @property
    def measured(self) -> bool:
        """Whether this fix is a position measurement (send it) or a coasted / lost report. A
        fix from walls alone measures the directions they constrain; the covariance is large
        (``lost_variance_m2``) along a direction no wall constrains (a corridor's axis)."""
        return (self.matched > 0 or self.walls_matched > 0) and self.state != "lost"


@dataclass(frozen=True)
class Match:
    """Result of associating corners with the map and updating the position (eqs. 5-8)."""

    xy: np.ndarray  # (2,) updated position, metres
    covariance: np.ndarray  # (3, 3) x, y, yaw
    matched: int
    rms_m: float  # RMS residual of the matched corners after the update
    pairs: tuple[tuple[int, int], ...] = ()  # (observed corner, map corner) indices of the ``matched``


def _near_any(points: np.ndarray, others: np.ndarray, radius: float) -> np.ndarray:
    """(P,) bool: whether each of ``points`` (P, 2) lies within ``radius`` of any of ``others`` (Q, 2)."""
    near = np.zeros(points.shape[0], dtype=bool)
    for start in range(0, others.shape[0], 256):  # in blocks: a large map's walls x corners would not fit at once
        block = others[start:start + 256]
        near |= (np.hypot(points[:, None, 0] - block[None, :, 0], points[:, None, 1] - block[None, :, 1]) <= radius).any(axis=1)
    return near


class PlanarLocalizer:
    """Tracks the body pose (x, y, yaw) in a map of known corners from horizontal scans."""

    def __init__(self, corners: np.ndarray, wall_angle_deg: float, mount: Mount2D = Mount2D(),
                 walls: np.ndarray | None = None, params: PlanarParams = PlanarParams(),
                 initial_pose: tuple[float, float, float] | None = None, ceiling_m: float | None = None,
                 wall_offset_deg: float = 0.0) -> None:
        """``corners``: (M, 2) known map corners [north, east] m; ``wall_angle_deg``: every
        wall at a multiple of it (90, 45, 30); ``walls``: optional (S, 4) segments
        [x0, y0, x1, y1] m, for the wall fixes, the corners' shapes and relocalization's wall
        check (cut the doors and windows at the scan height out of them: beams through an opening
        then tell rooms apart);
        ``initial_pose``:
        (x m, y m, yaw rad), or None to relocalize from the first scans; ``ceiling_m``: the
        ceiling's height above the floor (m), if known, to drop a tilted scanner's ceiling hits;
        ``wall_offset_deg``: the walls run at this plus multiples of the wall angle (degrees from
        north towards east: a building not aligned with north)."""
        self.ceiling_m = ceiling_m
        self.wall_offset = math.radians(wall_offset_deg)
        self.map = np.asarray(corners, dtype=float).reshape(-1, 2)
        self.wall_angle = math.radians(wall_angle_deg)
        self.mount = mount
        self.walls = None if walls is None else np.asarray(walls, dtype=float).reshape(-1, 4)
        self._wall_map: WallMap | None = None
        self._corner_rays: np.ndarray | None = None
        if self.walls is not None:
            self._wall_grid = WallGrid(self.walls, params.reloc_wall_tolerance_m)  # relocalization's wall check
            map_walls = MapWalls.from_segments(self.walls, self.wall_angle, self.wall_offset)
            # Whether each wall's start / end is a listed corner. Only there does the map vouch that
            # the wall really ends; a map built from a log also ends walls where the walk saw no more.
            self._wall_map = WallMap(map_walls, np.column_stack([
                _near_any(self.walls[:, c:c + 2], self.map, params.edge_corner_m) for c in (0, 2)]))
            # (M, R, 2): the directions of the walls meeting at each map corner (corner_shape.py)
            self._corner_rays = map_corner_rays(self.map, map_walls, params.edge_corner_m)
        self.params = params
        self._pose: tuple[float, float, float] | None = None
        self.last_lines: LineSet | None = None  # what update() extracted from its last scan (never mutated)
        self.last_corners: Corners | None = None
        self._cov = np.diag([params.lost_variance_m2, params.lost_variance_m2, UNMEASURED_VARIANCE_RAD2])
        self._misses = 0
        self.candidate: RelocCandidate | None = None  # an unconfirmed relocalization jump
        # The newest relocalization's hypotheses, best first, and why it found no pose (module
        # docstring); empty once a pose is measured or set again.
        self.hypotheses: tuple[RelocHypothesis, ...] = ()
        self.reloc_outcome = ""
        self._yaw_delta = 0.0  # the gyro's yaw change given with the scan being processed, rad
        self._moved: tuple[float, float] = (0.0, 0.0)  # the body displacement given with it (forward, right), m
        self._angles: np.ndarray | None = None
        self._unit = np.zeros((0, 2))
        self._level_cache: tuple[float, float, np.ndarray, np.ndarray] | None = None
        self.last_reason = ""  # why the last update returned None
        if initial_pose is not None:
            self.reset(*initial_pose)

    def reset(self, x: float, y: float, yaw: float) -> None:
        """Set the pose (metres, radians), e.g. a known take-off pose."""
        self._pose = (x, y, wrap_pi(yaw))
        self._misses = 0
        self._clear_search()

    def forget(self) -> None:
        """Drop the pose (and any relocalization candidate and hypotheses): the next update relocalizes afresh."""
        self._pose = None
        self.candidate = None
        self._clear_search()

    def _clear_search(self) -> None:
        """Drop the newest relocalization's hypotheses and outcome (a pose is measured or set)."""
        self.hypotheses = ()
        self.reloc_outcome = ""

    @property
    def pose(self) -> tuple[float, float, float] | None:
        """The pose held now (x m, y m, yaw rad), or None."""
        return self._pose

    def update(self, scan: Scan | np.ndarray, prior: tuple[float, float, float] | None = None, *,
               roll: float = 0.0, pitch: float = 0.0, yaw_delta: float = 0.0, moved_m: tuple[float, float] = (0.0, 0.0),
               valid: np.ndarray | None = None, height_m: float | None = None) -> PlanarFix | None:
        """Process one scan; None only when no pose is known and relocalization found none.

        ``scan``: a Scan, or (N, 2) sensor-frame points in beam order (``valid`` marks the
        real returns, default the finite rows). ``prior``: (x, y, yaw) predicted for the
        capture time (e.g. the EKF), replacing the held pose as the prediction. ``roll``,
        ``pitch``: body attitude at capture (rad) for tilt compensation. ``yaw_delta``: the
        gyro's yaw change since the previous scan (rad), added to the predicted heading (leave
        it 0 with a ``prior`` whose yaw already includes the turn). ``moved_m``: the body's
        displacement since the previous scan (forward, right, metres, in the body frame of the
        previous scan; odometry or the fused IMU), which moves a relocalization candidate before
        this scan is checked against it. ``height_m``: the body's height
        above the floor (m) when known, to drop floor hits of a tilted scanner.

        The fix's heading variance includes the map's wall direction error
        (``map_heading_error_rad``): its walls may run that far off the directions the heading is
        measured against. The yaw's variance only: the position's covariance carries the heading
        the lines measured through the lever arm, and a built map's wall direction error is an
        upper bound holding its reference poses' own heading error (through the lever arm it put
        the real logs' position NEES below its band: README, "Real buildings")."""
        fix = self._update(scan, prior, roll, pitch, yaw_delta, moved_m, valid, height_m)
        extra = self.params.map_heading_error_rad ** 2
        if fix is None or extra == 0.0:
            return fix
        cov = fix.covariance.copy()
        cov[2, 2] += extra
        return replace(fix, covariance=cov)

    def _update(self, scan: Scan | np.ndarray, prior: tuple[float, float, float] | None, roll: float, pitch: float,
                yaw_delta: float, moved_m: tuple[float, float], valid: np.ndarray | None,
                height_m: float | None) -> PlanarFix | None:
        """:meth:`update` without the map's wall direction error."""
        t0 = time.perf_counter()
        self._yaw_delta, self._moved = yaw_delta, moved_m
        points, ok, ranges = self.level_points(scan, roll, pitch, valid, height_m)
        lines = extract_lines(points, ok, self.params.lines, ranges)
        t1 = time.perf_counter()
        corners = find_corners(lines, self.params.corners)
        t2 = time.perf_counter()
        self.last_lines, self.last_corners = lines, corners
        timing = {"lines": (t1 - t0) * 1e3, "corners": (t2 - t1) * 1e3}
        if prior is not None:
            self._pose = (prior[0], prior[1], wrap_pi(prior[2]))
        if self._pose is None:
            return self._relocalize(lines, corners, points[ok], "no pose known", None, None, timing, t0)
        x, y, yaw = self._pose
        heading = track_heading(lines, yaw, self.wall_angle, yaw_delta, self.params.heading, self.wall_offset)
        t3 = time.perf_counter()
        timing["heading"] = (t3 - t2) * 1e3
        if not heading.measured:
            return self._miss(heading, heading.reason, heading.status == "ambiguous", lines, corners,
                              points[ok], timing, t0)
        best, yaw_used = self._best_alias(lines, corners, np.array([x, y]), heading)
        timing["match"] = (time.perf_counter() - t3) * 1e3
        # Once lost, the held position is stale: resume tracking only on a cross-checked match.
        needed = self.params.min_matches if self._misses >= self.params.lost_after_frames else 1
        if best.matched < needed:
            why = f"{best.matched} corners within {self.params.gate_m:g} m of a map corner"
            edges = occluding_ends(lines, points, ok, ranges, self._level_transform(roll, pitch)[1][:2],
                                   self.params.lines, self.params.edges) if self.walls is not None else None
            if self._misses < self.params.lost_after_frames:  # tracking: the walls still constrain
                walls = self._wall_fix(lines, edges, np.array([x, y]), heading, why, timing, t0)
                if walls is not None:
                    return walls
            return self._miss(heading, why, False, lines, corners, points[ok], timing, t0, edges)
        if self._misses >= self.params.lost_after_frames:
            rival = self._rival_resume(lines, corners, best, yaw_used)
            if rival is not None:
                why = (f"{best.matched} corners match near the dead-reckoned pose, and as many "
                       f"{math.dist(rival, best.xy):.1f} m away within its uncertainty")
                return self._miss(heading, why, False, lines, corners, points[ok], timing, t0)
        return self._accept(best, yaw_used, heading, False, timing, t0)

    def _drift_radius(self) -> float:
        """How far (m) the held position may be from the truth after ``_misses`` scans without a
        measurement: 3 sigma of the coasting drift (``coast_growth_m2`` per scan) plus the gate."""
        return 3.0 * math.sqrt(self._misses * self.params.coast_growth_m2) + self.params.gate_m

    def _rival_resume(self, lines: LineSet, corners: Corners, best: Match, yaw: float) -> np.ndarray | None:
        """After a loss (the held position dead-reckoned for ``_misses`` scans), another position
        (north, east m) within that drift's 3 sigma (``coast_growth_m2`` per scan) of the held one
        where the corners (found in ``lines``) also match as many map corners of their shapes as
        ``best`` does, if any: resuming there or at ``best`` would be a guess (look-alike corners)."""
        assert self._pose is not None
        p = self.params
        poses = pose_hypotheses(corners.xy, self.map, np.array([yaw]), p.gate_m, best.matched,
                                self.corner_shapes(lines, corners, 0.0))
        held = np.array(self._pose[:2])
        near = np.hypot(*(poses[:, 2:4] - held).T) <= self._drift_radius()
        apart = np.hypot(*(poses[:, 2:4] - best.xy).T) > p.reloc_distinct_m
        rivals = poses[near & apart]
        return None if rivals.shape[0] == 0 else rivals[0, 2:4]

    def level_points(self, scan: Scan | np.ndarray, roll: float = 0.0, pitch: float = 0.0,
                     valid: np.ndarray | None = None,
                     height_m: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points (N, 2) in the levelled body frame, metres; valid (N,); measured ranges (N,)).

        ``height_m``: the body origin's height above the floor (m), if known: hits less than
        ``floor_clearance_m`` above the floor or below the ceiling (a tilted scanner sweeping
        them) are marked invalid, they are no walls; a scanner itself that close (on the ground)
        keeps the hits at its own height."""
        if isinstance(scan, Scan):
            ok = scan.valid & np.isfinite(scan.ranges_m)
            r = np.where(ok, scan.ranges_m, 0.0)
            local = r[:, None] * self._unit_vectors(scan.angles_rad)
        else:
            local = np.asarray(scan, dtype=float)
            ok = np.isfinite(local).all(axis=1) if valid is None else valid & np.isfinite(local).all(axis=1)
            local = np.where(ok[:, None], local, 0.0)
            r = np.hypot(local[:, 0], local[:, 1])
        matrix, offset = self._level_transform(roll, pitch)
        levelled = local @ matrix.T + offset  # (N, 3): x, y and z (down) from the body origin
        if height_m is not None:
            above_floor = height_m - levelled[:, 2]
            scanner = height_m - offset[2]  # the scanner's own height above the floor
            # A scanner closer to the floor (or ceiling) than twice the clearance keeps its level hits.
            clearance = self.params.floor_clearance_m
            ok = ok & (above_floor >= min(clearance, scanner - clearance))
            if self.ceiling_m is not None:
                ok &= above_floor <= self.ceiling_m - min(clearance, self.ceiling_m - scanner - clearance)
        return levelled[:, :2], ok, r

    def match(self, lines: LineSet, corners: Corners, xy: np.ndarray, heading: HeadingResult,
              gate_m: float | None = None) -> Match:
        """Associate ``corners`` (levelled body frame, found in ``lines``) with the map from the
        position ``xy`` and the heading (measured from ``lines``), and update the position (eqs.
        5-8 with outlier rejection; the covariance: companion/nav/corner_fix.py)."""
        gate = self.params.gate_m if gate_m is None else gate_m
        rot = planar_rotation(heading.yaw)
        world = corners.xy @ rot.T  # R q for every corner (eq. 5 without the position)
        obs, idx = associate(xy + world, self.map, gate, self.corner_shapes(lines, corners, heading.yaw))
        if obs.size == 0:
            return Match(np.asarray(xy, dtype=float), self._cov, 0, 0.0)
        disp = self.map[idx] - (xy + world[obs])  # eq. 8: map corner minus observed corner
        cov = rot @ corners.cov[obs] @ rot.T
        weight = 1.0 / (cov[:, 0, 0] + cov[:, 1, 1])
        keep = self._inliers(disp, weight)
        disp, cov, weight = disp[keep], cov[keep], weight[keep]
        w = weight / weight.sum()
        delta = w @ disp
        resid = disp - delta
        scale = _chi2_scale(resid, cov) * (self.params.single_corner_inflation if w.size == 1 else 1.0)
        full = corner_fix_covariance(lines, corners.subset(obs[keep]), w, rot, heading, scale)
        rms = math.sqrt(float(np.dot(resid.ravel(), resid.ravel())) / w.size)
        pairs = tuple(zip(obs[keep].tolist(), idx[keep].tolist()))
        return Match(xy + delta, full, int(w.size), rms, pairs)

    def corner_shapes(self, lines: LineSet, corners: Corners,
                      yaw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """What :func:`associate` needs to pair only corners of the same shape (corner_shape.py):
        (the rays of ``corners`` (found in ``lines``, levelled body frame) turned to the world by
        ``yaw`` rad, the cosines of their largest angles, the map corners' rays), or None without
        map walls."""
        if self._corner_rays is None or corners.count == 0:
            return None
        p = self.params
        rays = observed_rays(lines, corners) @ planar_rotation(yaw).T
        limits = ray_limits(lines, corners, p.heading.min_length_m, p.corner_shape_tolerance_deg,
                            p.corner_shape_short_tolerance_deg)
        return rays, limits, self._corner_rays

    # -- internals ----------------------------------------------------------------------------

    def _unit_vectors(self, angles: np.ndarray) -> np.ndarray:
        """(cos a, sin a) per beam, cached while the beam angles stay the same."""
        if self._angles is None or (self._angles is not angles and not np.array_equal(self._angles, angles)):
            self._angles = angles
            self._unit = np.column_stack((np.cos(angles), np.sin(angles)))
        return self._unit

    def _level_transform(self, roll: float, pitch: float) -> tuple[np.ndarray, np.ndarray]:
        """(3x2 matrix, offset (3,)) from sensor-plane x, y to levelled-body x, y, z (see module doc)."""
        cached = self._level_cache
        if cached is not None and cached[0] == roll and cached[1] == pitch:
            return cached[2], cached[3]
        level = rotation_from_euler(roll, pitch, 0.0)
        m = self.mount
        matrix = level[:, :2] @ planar_rotation(m.yaw_rad)
        offset = level @ np.array([m.x_m, m.y_m, m.z_m])
        self._level_cache = (roll, pitch, matrix, offset)
        return matrix, offset

    def _inliers(self, disp: np.ndarray, weight: np.ndarray) -> np.ndarray:
        """Mask of the matches kept by the iterated k-times-median residual test."""
        keep = np.ones(disp.shape[0], dtype=bool)
        while keep.sum() >= 3:
            w = weight[keep] / weight[keep].sum()
            resid = np.hypot(*(disp - w @ disp[keep]).T)
            limit = max(self.params.outlier_k * statistics.median(resid[keep].tolist()), self.params.outlier_floor_m)
            bad = keep & (resid > limit)
            if not bad.any():
                break
            keep &= ~bad
        return keep

    def _best_alias(self, lines: LineSet, corners: Corners, xy: np.ndarray,
                    heading: HeadingResult) -> tuple[Match, float]:
        """Match with the measured heading; near the inter-frame limit also with its aliases
        +/- A (a rotation beyond A/2 aliases by A), and keep the one matching most corners."""
        best = self.match(lines, corners, xy, heading)
        yaw = heading.yaw
        if heading.status == "near_limit":
            for k in (-1, 1):
                alias = _with_yaw(heading, wrap_pi(heading.yaw + k * self.wall_angle))
                m = self.match(lines, corners, xy, alias)
                if m.matched > best.matched or (m.matched == best.matched > 0 and m.rms_m < best.rms_m):
                    best, yaw = m, alias.yaw
        return best, yaw

    def _wall_fix(self, lines: LineSet, edges: Edges | None, xy: np.ndarray, heading: HeadingResult, why: str,
                  timing: dict[str, float], t0: float) -> PlanarFix | None:
        """:meth:`_wall_solution` from the held position ``xy``, which becomes the pose held."""
        fix = self._wall_solution(lines, edges, xy, heading, why, timing, t0)
        if fix is not None:
            self._hold(fix)
        return fix

    def _hold(self, fix: PlanarFix) -> None:
        """Hold ``fix`` (a measurement) as the pose."""
        self._pose = (fix.x, fix.y, fix.yaw)
        self._cov = fix.covariance.copy()
        self._misses = 0
        self._clear_search()

    def _wall_solution(self, lines: LineSet, edges: Edges | None, xy: np.ndarray, heading: HeadingResult, why: str,
                       timing: dict[str, float], t0: float) -> PlanarFix | None:
        """The wall fix (wall_fix.py) near the position ``xy`` (m) when no corner matched, None if no
        wall matched; the pose held is not changed."""
        if self._wall_map is None or edges is None:
            return None
        found = wall_fix(lines, edges, xy, heading, self._wall_map, self.params, why)
        if found is None:
            return None
        timing["total"] = (time.perf_counter() - t0) * 1e3
        return PlanarFix(float(found.xy[0]), float(found.xy[1]), heading.yaw, found.covariance, 0, "degraded",
                         found.reason, False, heading.status, timing, walls_matched=found.walls_matched,
                         unmeasured=found.unmeasured, ends_only=found.ends_only)

    def _accept(self, m: Match, yaw: float, heading: HeadingResult, relocalized: bool,
                timing: dict[str, float], t0: float) -> PlanarFix:
        self._pose = (float(m.xy[0]), float(m.xy[1]), yaw)
        self.candidate = None
        self._clear_search()
        self._cov = m.covariance
        self._misses = 0
        state: PlanarState = "tracking"
        reason = ""
        if m.matched < self.params.min_matches:
            state = "degraded"
            reason = f"{m.matched} corner matched: no cross-check of the association"
        elif heading.status == "near_limit":
            state = "degraded"
            reason = heading.reason
        if yaw != heading.yaw:
            reason = (f"{reason}; " if reason else "") + "heading alias resolved by the corners"
        timing["total"] = (time.perf_counter() - t0) * 1e3
        return PlanarFix(self._pose[0], self._pose[1], yaw, m.covariance.copy(), m.matched, state, reason,
                         relocalized, heading.status, timing, corner_pairs=m.pairs)

    def _miss(self, heading: HeadingResult, reason: str, lost_now: bool, lines: LineSet, corners: Corners,
              points: np.ndarray, timing: dict[str, float], t0: float, edges: Edges | None = None) -> PlanarFix | None:
        """A scan without a position measurement: coast, or report lost and try to relocalize
        (``points``: the valid levelled points; ``edges``: the lines' occluding ends, if known)."""
        assert self._pose is not None
        self._misses += 1
        x, y, _ = self._pose
        self._pose = (x, y, heading.yaw)
        if lost_now or self._misses >= self.params.lost_after_frames:
            return self._relocalize(lines, corners, points, reason, heading, edges, timing, t0)
        cov = self._cov.copy()
        cov[:2, :2] += self._misses * self.params.coast_growth_m2 * np.eye(2)
        if heading.measured:
            cov[2, 2] = heading.variance
        timing["total"] = (time.perf_counter() - t0) * 1e3
        return PlanarFix(x, y, heading.yaw, cov, 0, "degraded",
                         f"{reason} ({self._misses}/{self.params.lost_after_frames} frames)",
                         False, heading.status, timing)

    def _relocalize(self, lines: LineSet, corners: Corners, points: np.ndarray, why: str,
                    heading: HeadingResult | None, edges: Edges | None, timing: dict[str, float],
                    t0: float) -> PlanarFix | None:
        """Search (see the module docstring): by corners, then, with a pose held and the heading
        measured, by the walls near it. A pose within ``jump_m`` / ``jump_rad`` of the held one
        resumes tracking; a jump becomes the pose only after ``reloc_confirm_frames`` scans found it
        (module docstring); until then a lost fix (or None without a pose) names the candidate. The
        searches' hypotheses replace :attr:`hypotheses`, and why they found no pose :attr:`reloc_outcome`."""
        t = time.perf_counter()
        found, detail, self.hypotheses = self._search(lines, corners, points)
        on_walls: PlanarFix | None = None
        if found is None and heading is not None and heading.measured and edges is not None:
            on_walls, walls_detail, by_walls = self._wall_search(lines, edges, points, heading, why, timing, t0)
            self.hypotheses += by_walls
            detail = f"{detail}; by walls: {walls_detail}" if on_walls is None else detail
        timing["relocalize"] = (time.perf_counter() - t) * 1e3
        self.reloc_outcome = detail if found is None and on_walls is None else ""
        if found is None and on_walls is None:
            self.candidate = carried(self.candidate, self._moved, self._yaw_delta, self.params.reloc_confirm_frames)
        else:
            if found is not None:
                match, at, local = found
                xy, yaw, matched, walls = match.xy, at.yaw, match.matched, 0
            else:
                assert on_walls is not None
                xy, yaw, matched, local = np.array([on_walls.x, on_walls.y]), on_walls.yaw, 0, True
                walls = on_walls.walls_matched
            jump = self._pose is None or (
                math.dist(self._pose[:2], xy) > self.params.jump_m
                or abs(wrap_pi(self._pose[2] - yaw)) > self.params.jump_rad)
            if not jump or self._confirmed(xy, yaw, matched, walls, local):
                if found is not None:
                    return self._accept(match, yaw, at, jump, timing, t0)
                assert on_walls is not None
                self.candidate = None
                self._hold(on_walls)
                return replace(on_walls, relocalized=jump,
                               reason=f"resumed on the walls near the dead-reckoned pose: {on_walls.reason}")
            assert self.candidate is not None
            detail = self.candidate.describe(self.params.reloc_confirm_frames)
        timing["total"] = (time.perf_counter() - t0) * 1e3
        if self._pose is None:
            self.last_reason = f"{why}; relocalization: {detail}"
            return None
        x, y, yaw = self._pose
        cov = np.diag([self.params.lost_variance_m2, self.params.lost_variance_m2, UNMEASURED_VARIANCE_RAD2])
        return PlanarFix(x, y, yaw, cov, 0, "lost", f"{why}; relocalization: {detail}", False,
                         "" if heading is None else heading.status, timing)

    def _wall_search(self, lines: LineSet, edges: Edges, points: np.ndarray, heading: HeadingResult, why: str,
                     timing: dict[str, float],
                     t0: float) -> tuple[PlanarFix | None, str, tuple[RelocHypothesis, ...]]:
        """Lost with a pose held: the position near it (within ``reloc_local_m``, or the drift since
        the last fix if more) where the observed lines of two wall directions lie on map walls
        (wall_hypotheses.py), scored by the fraction of the scan ``points`` (levelled body frame)
        then on walls; only a clear winner (every position more than ``reloc_distinct_m`` from it at
        least ``reloc_wall_margin`` behind) whose walls fix the position in both directions. Returns that
        fix (the pose held is not changed) or None and why not, and the positions weighed (best first,
        none when there were too many to weigh)."""
        p = self.params
        assert self._pose is not None and self._wall_map is not None
        held = np.array(self._pose[:2])
        use = np.flatnonzero(lines.length >= p.heading.min_length_m)
        poses = wall_hypotheses(lines, use, held, heading.yaw, self._wall_map.walls,
                                max(p.reloc_local_m, self._drift_radius()), p.wall_angle_tolerance_deg,
                                p.reloc_wall_tolerance_m)
        if poses.shape[0] == 0:
            return None, "no lines of two wall directions on map walls near the held pose", ()
        if poses.shape[0] > p.reloc_wall_positions_max:
            return None, f"{poses.shape[0]} positions near the held pose put lines on walls: too many look-alikes", ()
        fraction = self._wall_fractions(points, poses, heading.yaw)
        n = poses.shape[0]
        weighed = ranked_hypotheses("walls", poses, np.full(n, heading.yaw), np.zeros(n, dtype=int), fraction, True,
                                    p.reloc_hypotheses_reported)
        best = int(np.argmax(fraction))
        if fraction[best] < p.reloc_min_wall_fraction:
            return None, f"the best pose puts only {fraction[best]:.0%} of the points on walls", weighed
        rivals = ((np.hypot(*(poses - poses[best]).T) > p.reloc_distinct_m)
                  & (fraction > fraction[best] - p.reloc_wall_margin))
        if rivals.any():
            return None, (f"{int(rivals.sum()) + 1} poses put {fraction[best]:.0%} of the points on walls, "
                          "no clear winner"), weighed
        fix = self._wall_solution(lines, edges, poses[best], heading, why, timing, t0)
        if fix is None or fix.unmeasured is not None:
            return None, "the walls at the best pose do not fix the position in both directions", weighed
        return fix, "", weighed

    def _confirmed(self, xy: np.ndarray, yaw: float, matched: int, walls: int, local: bool) -> bool:
        """Count this scan for the candidate jump it found (reloc_candidate.py); True once enough
        scans found it, none finding another pose in between."""
        p = self.params
        self.candidate = found_again(self.candidate, xy, yaw, matched, walls, local, self._moved, self._yaw_delta,
                                     p.reloc_confirm_gate_m, p.reloc_confirm_gate_rad)
        return self.candidate.frames >= p.reloc_confirm_frames

    def _search(self, lines: LineSet, corners: Corners, points: np.ndarray
                ) -> tuple[tuple[Match, HeadingResult, bool] | None, str, tuple[RelocHypothesis, ...]]:
        """The relocalized pose (match, heading, whether it was found near the held pose) or why none,
        and the hypotheses of the search that decided (:meth:`_clear_winner`). With a pose held, the
        hypotheses within ``reloc_local_m`` of it (or the drift since it was measured, if more) and at
        the heading nearest its yaw are tried first; the global search only when they give no clear
        winner."""
        p = self.params
        yaws, base = heading_hypotheses(lines, self.wall_angle, p.heading, self.wall_offset)
        if yaws.size == 0:
            return None, base.reason, ()
        if corners.count < p.reloc_min_inliers:
            return None, f"{corners.count} corners visible, at least {p.reloc_min_inliers} needed", ()
        spread = corners.cov[:, 0, 0] + corners.cov[:, 1, 1]
        corners = corners.subset(np.argsort(spread)[:p.reloc_max_corners])
        poses = pose_hypotheses(corners.xy, self.map, yaws, p.reloc_tolerance_m, p.reloc_min_inliers,
                                self.corner_shapes(lines, corners, 0.0))
        if self._pose is not None:
            hx, hy, hyaw = self._pose
            near = ((np.hypot(poses[:, 2] - hx, poses[:, 3] - hy) <= max(p.reloc_local_m, self._drift_radius()))
                    & (np.abs(wrap_pi(poses[:, 1] - hyaw)) <= 0.5 * self.wall_angle))
            found, _, weighed = self._clear_winner(poses[near], lines, corners, points, base, True)
            if found is not None:
                return (*found, True), "", weighed
        found, detail, weighed = self._clear_winner(poses, lines, corners, points, base, False)
        return (None, detail, weighed) if found is None else ((*found, False), "", weighed)

    def _clear_winner(self, poses: np.ndarray, lines: LineSet, corners: Corners, points: np.ndarray,
                      base: HeadingResult, local: bool
                      ) -> tuple[tuple[Match, HeadingResult] | None, str, tuple[RelocHypothesis, ...]]:
        """Refine the best distinct pose rows (score, yaw, x, y) and keep a clear winner, if any; also
        the refined poses as hypotheses (best first; ``local``: the search near the held pose)."""
        p = self.params
        if poses.shape[0]:
            poses = poses[poses[:, 0] >= poses[0, 0] - 1]
        matched = []
        for score, yaw, tx, ty in distinct_poses(poses, p.reloc_distinct_m, p.reloc_candidates):
            heading = _with_yaw(base, float(yaw))
            matched.append((self.match(lines, corners, np.array([tx, ty]), heading, p.reloc_tolerance_m), heading))
        # Only the poses matching the most corners can win or tie: the wall check for those alone.
        most = max((m.matched for m, _ in matched), default=0)
        scored = [(m.matched, self._wall_fraction(points, m.xy, heading.yaw) if m.matched == most else 0.0, m, heading)
                  for m, heading in matched]
        scored.sort(key=lambda s: (s[0], s[1]), reverse=True)
        weighed = ranked_hypotheses(
            "corners", np.array([m.xy for _, _, m, _ in scored]).reshape(-1, 2),
            np.array([heading.yaw for *_, heading in scored]), np.array([s[0] for s in scored], dtype=int),
            np.array([f if self.walls is not None and n == most else math.nan for n, f, _, _ in scored]), local,
            p.reloc_hypotheses_reported)
        if not scored or scored[0][0] < p.reloc_min_inliers:
            return None, f"no pose matches {p.reloc_min_inliers} corners", weighed
        best = scored[0]
        if self.walls is not None and best[1] < p.reloc_min_wall_fraction:
            return None, f"best pose puts only {best[1]:.0%} of the points on walls", weighed
        for other in scored[1:]:
            if other[0] == best[0] and (self.walls is None or best[1] - other[1] < p.reloc_wall_margin):
                return None, f"{len(scored)} candidate poses, no clear winner", weighed
        return (best[2], best[3]), "", weighed

    def _wall_fraction(self, points: np.ndarray, xy: np.ndarray, yaw: float) -> float:
        """Fraction of (every 4th) levelled-body point within the tolerance of a map wall."""
        return float(self._wall_fractions(points, xy[None, :], yaw)[0])

    def _wall_fractions(self, points: np.ndarray, xys: np.ndarray, yaw: float) -> np.ndarray:
        """(H,): :meth:`_wall_fraction` at each position of ``xys`` (H, 2), m."""
        if self.walls is None or points.shape[0] == 0:
            return np.zeros(xys.shape[0])
        body = points[::4] @ planar_rotation(yaw).T
        world = (xys[:, None, :] + body[None, :, :]).reshape(-1, 2)
        on = self._wall_grid.near_wall(world, self.params.reloc_wall_tolerance_m)
        return on.reshape(xys.shape[0], body.shape[0]).mean(axis=1)


def _with_yaw(heading: HeadingResult, yaw: float) -> HeadingResult:
    return replace(heading, yaw=yaw)


def associate(predicted: np.ndarray, landmarks: np.ndarray, gate: float,
              shapes: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(observed indices, map indices) of mutual nearest neighbours closer than ``gate`` (the
    localizer's association; telemetry shows the same). ``shapes`` (:meth:`PlanarLocalizer.corner_shapes`):
    only pairs whose walls run the same ways are candidates (corner_shape.py)."""
    none = np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    if landmarks.shape[0] == 0 or predicted.shape[0] == 0:
        return none
    # Only landmarks in the gate-widened box of the predictions can be matched; dropping the others
    # changes no nearest neighbour within the gate and no mutual check (a large map: most of it).
    lo, hi = predicted.min(axis=0) - gate, predicted.max(axis=0) + gate
    inside = np.flatnonzero((landmarks[:, 0] >= lo[0]) & (landmarks[:, 0] <= hi[0])
                            & (landmarks[:, 1] >= lo[1]) & (landmarks[:, 1] <= hi[1]))
    if inside.size == 0:
        return none
    diff = predicted[:, None, :] - landmarks[inside][None, :, :]
    dist = np.hypot(diff[..., 0], diff[..., 1])
    if shapes is not None:  # only pairs inside the gate can be matched or block a match: test those
        obs, known = np.nonzero(dist <= gate)
        rays, limits, map_rays = shapes
        differ = ~shapes_agree(rays[obs], limits[obs], map_rays[inside[known]])
        dist[obs[differ], known[differ]] = np.inf
    nearest = dist.argmin(axis=1)
    mutual = dist.argmin(axis=0)[nearest] == np.arange(predicted.shape[0])
    ok = mutual & (dist[np.arange(predicted.shape[0]), nearest] <= gate)
    return np.flatnonzero(ok), inside[nearest[ok]]


def _chi2_scale(resid: np.ndarray, cov: np.ndarray) -> float:
    """max(1, chi-square per degree of freedom) of the residuals after the weighted mean."""
    n = resid.shape[0]
    if n < 2:
        return 1.0
    x, y = resid[:, 0], resid[:, 1]
    a, b, d = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    chi2 = float(np.sum((d * x * x - 2.0 * b * x * y + a * y * y) / (a * d - b * b)))  # r^T C^-1 r, 2x2 closed form
    return max(1.0, chi2 / (2 * (n - 1)))
