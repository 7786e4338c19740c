"""Smooth 3-D trajectories through waypoints: minimum-jerk and minimum-snap splines (numpy, no I/O).

Frame and units: LOCAL_NED metres (x north, y east, z down), seconds, yaw in radians from north
towards east, wrapped to [-pi, pi). ``t = 0`` is the start of the trajectory (the caller adds
its clock's start time).

Shape (fixed segment times). One polynomial per segment and axis, in the normalised segment
time ``tau = (t - t_i) / T_i`` in [0, 1]: degree 5 for ``minimum_jerk`` (r = 3), degree 7 for
``minimum_snap`` (r = 4). The unknowns are the derivatives 1 .. r-1 at every joint (velocity
and acceleration, plus jerk for snap); a segment's coefficients follow from the derivatives at
its two ends, so position and derivatives up to r-1 are continuous at the joints by
construction. The cost, the integral of the squared r-th derivative over the whole trajectory,
is a quadratic form in those joint derivatives; it is minimised over the free ones (every
interior joint, except ``stops``) in one linear solve over all segments: the unconstrained
formulation of Richter, Bry and Roy (2013) of the minimum-snap problem of Mellinger and
Kumar (2011). Fixed: the positions at all joints (the trajectory passes exactly through every
waypoint), and derivatives 1 .. r-1 = 0 at the first and last waypoint (start and end at rest)
and at the ``stops``. The optimum is the minimiser of the cost among all smooth curves through
the joints with those end conditions; its derivatives are even continuous up to order 2r-2 at
the flown-through joints (4 for jerk, 6 for snap).

Time allocation. Segment times start from a rest-to-rest trapezoid per segment; then
repeatedly: solve, find each segment's peak |v|, |a|, |j| (on a grid of 65 points), and scale
that segment's time by (a damped power of) its ratio ``max(v/v_max, sqrt(a/a_max),
cbrt(j/j_max))``, the factor that would put an isolated segment exactly on its binding limit,
until every segment is within 1 % of its limit or 10 solves bring no 0.1 % gain. Two update
rules are run, each segment on its own ratio, and a segment over its limit also slowing its
neighbours (a peak at a joint depends on both: this is what converges when legs have different
speed limits). A common time scale leaves the optimal shape unchanged (the coefficients in
``tau`` do not change) and divides v, a, j by k, k^2, k^3: so every iterate, scaled by its
largest ratio, is feasible, and the shortest one is kept, scaled by its exact largest ratio
(polynomial extrema: roots of the derivative of the squared norm, plus the grid). Limits hold
everywhere, exactly; the duration is close to, not at, the time-optimal one.

Corridor (``corridor_m``). An interpolating spline swings wide of sharp corners, more so the
faster it flies through them: through the default patrol it would touch the arena's north wall.
So after allocation each segment is checked against the straight leg of the waypoint list it
belongs to (201 samples per segment); where it strays further than ``corridor_m`` the segment
is split at its midpoint (an extra joint on the straight leg, as in Richter et al.'s collision
handling) and everything is solved and allocated again. Up to 8 rounds of splits; a segment
still out after that makes the corner nearest to where it strays a stop, one corner per round;
a leg between two stops is flown exactly straight, and as a single segment without
overshooting its ends (its inner joints are then removed). So the corridor is always met. The
result stays within ``corridor_m`` of the waypoint polyline, which is what the mission author
checked against walls and doors, and slows down for sharp corners by itself (the acceleration
limit). Default 0.15 m, the goto step's arrival tolerance; ``corridor_m=None`` disables it.
The inserted joints are internal: ``waypoints``, ``waypoint_times`` and the indices of
``closest_approach`` / ``max_deviation`` are the caller's; ``stops`` lists the requested stops
and those the corridor added.

Yaw (``yaw_mode``):

- ``hold``: ``initial_yaw_rad`` throughout, rate 0.
- ``face_next``: along leg i the target is the bearing from waypoint i to waypoint i+1 (legs
  shorter than 5 cm horizontally, e.g. pure climbs, keep the previous target); the reference
  follows the target with a yaw rate limited to ``yaw_rate_max_rad_s`` and a yaw acceleration
  limited to ``yaw_accel_max_rad_s2`` (so the rate is continuous), always turning the short
  way round (wrap handled), starting from ``initial_yaw_rad``.
- ``fixed``: the same smoother from ``initial_yaw_rad`` to ``yaw_fixed_rad``.

The yaw profile is integrated on a 10 ms grid and interpolated linearly; a turn still running at
``duration`` finishes afterwards (``yaw_settled_time``), the position holding at the end.
Before 0 and after ``duration`` the position is the first / last waypoint and all derivatives
are zero.

Typical use::

    traj = plan(waypoints, v_max_mps=0.5, a_max_mps2=0.5, kind="minimum_snap", yaw_mode="face_next",
                initial_yaw_rad=yaw_now)
    ref = traj.sample(t)   # ref.position, ref.velocity, ref.acceleration, ref.yaw_rad, ref.yaw_rate
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np
from numpy.polynomial import polynomial as P

from companion.control.reference import Reference

Kind = Literal["minimum_jerk", "minimum_snap"]
YawMode = Literal["hold", "face_next", "fixed"]

_ORDER = {"minimum_jerk": 3, "minimum_snap": 4}  # r: the minimised derivative; degree 2r - 1
YAW_DT_S = 0.01  # yaw profile grid
FACE_MIN_LEG_M = 0.05  # face_next: legs shorter than this horizontally keep the previous heading
MIN_SEPARATION_M = 1e-3  # consecutive waypoints closer than this are rejected as repeated
LIMIT_TOLERANCE = 0.01  # time allocation stops when every segment is within 1 % of its limit
MAX_ALLOCATION_ITERATIONS = 60
ALLOCATION_STEP = 1.25  # per-iteration bound on the factor applied to a segment's time
ALLOCATION_DAMPING = 0.5  # the per-segment factor is ratio ** this
ALLOCATION_PATIENCE = 10  # stop after this many solves without a 0.1 % shorter candidate
SPLIT_ROUNDS = 8  # corridor: rounds of splitting before corners become stops
MIN_SPLIT_M = 0.02  # segments shorter than this are not split further


def _wrap(a: np.ndarray | float) -> np.ndarray:
    """Angle(s) wrapped to [-pi, pi)."""
    w = (np.asarray(a, dtype=float) + np.pi) % (2 * np.pi) - np.pi
    return np.where(w >= np.pi, w - 2 * np.pi, w)  # (x + pi) % 2 pi can round up to 2 pi


# --- the polynomial algebra ------------------------------------------------------------------

@lru_cache(maxsize=None)
def _basis(r: int) -> tuple[np.ndarray, np.ndarray]:
    """(A_inv, H) for order r in normalised time: coefficients c = A_inv @ D, where D holds the
    tau-derivatives 0..r-1 at tau = 0 then at tau = 1; and D^T H D = integral over [0, 1] of the
    squared r-th tau-derivative."""
    n = 2 * r
    a = np.zeros((n, n))
    for m in range(r):
        a[m, m] = math.factorial(m)
        for k in range(m, n):
            a[r + m, k] = math.factorial(k) / math.factorial(k - m)
    q = np.zeros((n, n))
    for k in range(r, n):
        for l in range(r, n):
            fk = math.factorial(k) / math.factorial(k - r)
            fl = math.factorial(l) / math.factorial(l - r)
            q[k, l] = fk * fl / (k + l - 2 * r + 1)
    a_inv = np.linalg.inv(a)
    h = a_inv.T @ q @ a_inv
    h = (h + h.T) / 2
    a_inv.setflags(write=False)
    h.setflags(write=False)
    return a_inv, h


def _solve_coefficients(points: np.ndarray, times: np.ndarray, r: int, stops: Sequence[int]) -> np.ndarray:
    """Coefficients (S, 2r, 3) in tau (lowest power first) of the optimal spline through
    ``points`` with segment times ``times``; at rest (derivatives 1..r-1 zero) at both ends and
    at the joint indices ``stops``."""
    n_joints = len(points)
    a_inv, h = _basis(r)
    tn = times / times.mean()  # a common time unit near 1 keeps the system well conditioned
    size = n_joints * r
    cost = np.zeros((size, size))
    scales = []
    for i, t in enumerate(tn):
        s = np.tile(t ** np.arange(r), 2)  # physical derivative m -> tau-derivative: * T^m
        scales.append(s)
        idx = np.concatenate([i * r + np.arange(r), (i + 1) * r + np.arange(r)])
        cost[np.ix_(idx, idx)] += t ** (1 - 2 * r) * (s[:, None] * h * s[None, :])
    fixed = np.zeros(size, dtype=bool)
    fixed[::r] = True  # positions
    for j in (0, n_joints - 1, *stops):
        fixed[j * r:(j + 1) * r] = True
    x = np.zeros((size, 3))
    x[::r] = points
    free = ~fixed
    if free.any():
        x[free] = np.linalg.solve(cost[np.ix_(free, free)], -cost[np.ix_(free, fixed)] @ x[fixed])
    coeffs = np.empty((len(tn), 2 * r, 3))
    for i, s in enumerate(scales):
        d = np.concatenate([x[i * r:(i + 1) * r], x[(i + 1) * r:(i + 2) * r]])
        coeffs[i] = a_inv @ (s[:, None] * d)
    return coeffs


def _real_roots_01(poly: np.ndarray) -> np.ndarray:
    """Real roots in [0, 1] of a polynomial (coefficients lowest first)."""
    scale = float(np.max(np.abs(poly))) if poly.size else 0.0
    if scale == 0.0:
        return np.empty(0)
    poly = P.polytrim(poly, tol=1e-13 * scale)
    if len(poly) < 2:
        return np.empty(0)
    roots = P.polyroots(poly)
    roots = roots[np.abs(roots.imag) <= 1e-7].real
    return roots[(roots >= 0.0) & (roots <= 1.0)]


_GRID = np.linspace(0.0, 1.0, 65)
_DENSE = np.linspace(0.0, 1.0, 201)


def _squared_norm(c: np.ndarray) -> np.ndarray:
    """|q(tau)|^2 as a polynomial, for a vector polynomial q (coefficients (n, 3))."""
    return sum(np.convolve(c[:, a], c[:, a]) for a in range(c.shape[1]))


def _max_norm(c: np.ndarray) -> float:
    """Max over tau in [0, 1] of |q(tau)| for a vector polynomial q (coefficients (n, 3))."""
    sq = _squared_norm(c)
    tau = np.concatenate([_GRID, _real_roots_01(P.polyder(sq))])
    return math.sqrt(max(0.0, float(np.max(P.polyval(tau, sq)))))


def _min_distance(c: np.ndarray, point: np.ndarray) -> float:
    """Min over tau in [0, 1] of the distance between q(tau) (coefficients (n, 3)) and a point."""
    c = c.copy()
    c[0] -= point
    sq = _squared_norm(c)
    tau = np.concatenate([_GRID, _real_roots_01(P.polyder(sq))])
    return math.sqrt(max(0.0, float(np.min(P.polyval(tau, sq)))))


def _distance_to_leg(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances of points (M, 3) from the line segment a-b."""
    ab = b - a
    s = np.clip((p - a) @ ab / float(ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + s[:, None] * ab), axis=1)


def _segment_deviation(c: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Largest distance of a segment (coefficients (n, 3), dense sampling) from the leg a-b, and
    where along the leg (0 at a, 1 at b) the farthest sample projects."""
    p = P.polyval(_DENSE, c).T
    d = _distance_to_leg(p, a, b)
    k = int(np.argmax(d))
    return float(d[k]), float((p[k] - a) @ (b - a) / float((b - a) @ (b - a)))


# --- the trajectory --------------------------------------------------------------------------

class Trajectory:
    """A planned trajectory: piecewise polynomials in NED plus a yaw profile. Immutable.

    ``waypoints`` (N, 3) are the caller's; ``joints`` (J, 3) are all the points the spline is
    pinned to (the waypoints plus any the corridor inserted on the straight legs), with
    ``segment_times`` (J-1,) between them and ``joint_times`` (J,)."""

    def __init__(self, waypoints: np.ndarray, joints: np.ndarray, waypoint_joint: np.ndarray,
                 segment_times: np.ndarray, coeffs: np.ndarray, kind: Kind, stops: tuple[int, ...],
                 yaw: tuple[np.ndarray, np.ndarray, np.ndarray], iterations: int = 0) -> None:
        self.waypoints = waypoints
        self.joints = joints
        self.kind: Kind = kind
        self.order = _ORDER[kind]
        self.stops = stops  # waypoint indices where it comes to rest (requested + corridor's)
        self.iterations = iterations  # time-allocation solves (0: times given)
        self.segment_times = segment_times
        self.joint_times = np.concatenate([[0.0], np.cumsum(segment_times)])
        self._waypoint_joint = waypoint_joint
        self._waypoint_times = self.joint_times[waypoint_joint]
        self._coeffs = coeffs
        self._dcoeffs = [coeffs]
        for _ in range(2 * self.order):
            self._dcoeffs.append(P.polyder(self._dcoeffs[-1], axis=1))
        self._yaw_t, self._yaw, self._yaw_rate = yaw
        peaks = np.array([[_max_norm(self._dcoeffs[m][i]) / segment_times[i] ** m for m in (1, 2, 3)]
                          for i in range(len(segment_times))])
        self.segment_peaks = peaks  # (J-1, 3): exact max |v|, |a|, |j| per segment
        for arr in (self.waypoints, self.joints, self.segment_times, self.joint_times, self._waypoint_joint,
                    self._waypoint_times, self._yaw_t, self._yaw, self._yaw_rate, self.segment_peaks):
            arr.setflags(write=False)

    # timing
    @property
    def duration(self) -> float:
        """Seconds from the first waypoint to rest at the last one."""
        return float(self.joint_times[-1])

    @property
    def waypoint_times(self) -> np.ndarray:
        """(N,) when each waypoint is passed (exactly: the spline interpolates them)."""
        return self._waypoint_times

    @property
    def yaw_settled_time(self) -> float:
        """When the yaw reference stops changing (>= duration if a turn is still running)."""
        return float(self._yaw_t[-1])

    # peaks, exact (polynomial extrema)
    @property
    def max_speed(self) -> float:
        return float(self.segment_peaks[:, 0].max())

    @property
    def max_acceleration(self) -> float:
        return float(self.segment_peaks[:, 1].max())

    @property
    def max_jerk(self) -> float:
        return float(self.segment_peaks[:, 2].max())

    def summary(self) -> dict:
        return {"kind": self.kind, "waypoints": len(self.waypoints), "joints": len(self.joints),
                "duration_s": self.duration, "max_speed_mps": self.max_speed,
                "max_accel_mps2": self.max_acceleration, "max_jerk_mps3": self.max_jerk,
                "iterations": self.iterations}

    # evaluation
    def derivative(self, ts: float | np.ndarray, order: int) -> np.ndarray:
        """The ``order``-th time derivative of the position at time(s) ``ts``: (3,) for a scalar,
        (..., 3) for an array. At a joint the later segment is used; outside [0, duration] the
        position is clamped to the ends and every derivative is zero."""
        t = np.asarray(ts, dtype=float)
        if not np.all(np.isfinite(t)):
            raise ValueError("trajectory time must be finite")
        if order < 0:
            raise ValueError("derivative order must be >= 0")
        flat = t.reshape(-1)
        tc = np.clip(flat, 0.0, self.duration)
        seg = np.clip(np.searchsorted(self.joint_times, tc, side="right") - 1, 0, len(self.segment_times) - 1)
        tau = ((tc - self.joint_times[seg]) / self.segment_times[seg])[:, None]
        if order >= len(self._dcoeffs):
            out = np.zeros((flat.size, 3))
        else:
            c = self._dcoeffs[order]
            out = c[seg, -1].copy()
            for k in range(c.shape[1] - 2, -1, -1):
                out = out * tau + c[seg, k]
            out /= (self.segment_times[seg] ** order)[:, None]
        if order > 0:
            out[(flat < 0.0) | (flat > self.duration)] = 0.0
        return out.reshape(t.shape + (3,))

    def _yaw_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        yaw = np.interp(t, self._yaw_t, self._yaw)
        rate = np.interp(t, self._yaw_t, self._yaw_rate)
        return _wrap(yaw), rate

    def sample(self, t: float) -> Reference:
        """The reference at time ``t`` (seconds from the start)."""
        ts = np.array([float(t)])
        if not np.isfinite(ts[0]):
            raise ValueError("trajectory time must be finite")
        yaw, rate = self._yaw_at(ts)
        return Reference(self.derivative(ts, 0)[0], self.derivative(ts, 1)[0], self.derivative(ts, 2)[0],
                         float(yaw[0]), float(rate[0]))

    def sample_many(self, ts: Iterable[float] | np.ndarray) -> Reference:
        """Vectorised ``sample``: arrays (M, 3) and (M,)."""
        t = np.asarray(ts, dtype=float).reshape(-1)
        if not np.all(np.isfinite(t)):
            raise ValueError("trajectory time must be finite")
        yaw, rate = self._yaw_at(t)
        return Reference(self.derivative(t, 0), self.derivative(t, 1), self.derivative(t, 2), yaw, rate)

    # geometry checks
    def closest_approach(self, waypoint_index: int) -> float:
        """Smallest distance (m) between the whole trajectory and the waypoint, exact (roots of the
        derivative of the squared-distance polynomial). Zero up to rounding, since the spline
        interpolates every waypoint: the check a window or door pass is verified with."""
        w = self.waypoints[self._index(waypoint_index)]
        return min(_min_distance(self._coeffs[i], w) for i in range(len(self.segment_times)))

    def max_deviation(self, leg_index: int, samples: int = 400) -> float:
        """Largest distance (m) of the trajectory between waypoints i and i+1 from the straight
        leg between them (dense sampling): how far the smooth path strays from the polyline,
        e.g. next to a door frame. Within ``corridor_m`` when planned with one."""
        i = int(leg_index)
        if not 0 <= i < len(self.waypoints) - 1:
            raise ValueError(f"leg index {leg_index} out of range 0..{len(self.waypoints) - 2}")
        t = np.linspace(self._waypoint_times[i], self._waypoint_times[i + 1], samples)
        return float(_distance_to_leg(self.derivative(t, 0), self.waypoints[i], self.waypoints[i + 1]).max())

    def cost(self, order: int) -> float:
        """Integral over the trajectory of |d^order p / dt^order|^2, exact (per segment)."""
        if order < 0:
            raise ValueError("derivative order must be >= 0")
        if order >= len(self._dcoeffs):
            return 0.0
        total = 0.0
        for i, seg_t in enumerate(self.segment_times):
            sq = _squared_norm(self._dcoeffs[order][i])
            total += float(P.polyval(1.0, P.polyint(sq))) * seg_t ** (1 - 2 * order)
        return total

    def _index(self, waypoint_index: int) -> int:
        i = int(waypoint_index)
        n = len(self.waypoints)
        if not -n <= i < n:
            raise ValueError(f"waypoint index {waypoint_index} out of range 0..{n - 1}")
        return i % n


# --- inputs ----------------------------------------------------------------------------------

def _check_waypoints(waypoints: object) -> np.ndarray:
    try:
        w = np.array(waypoints, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"waypoints must be an (N, 3) array of NED metres: {exc}") from None
    if w.ndim != 2 or w.shape[1] != 3:
        raise ValueError(f"waypoints must be an (N, 3) array of NED metres, got shape {w.shape}")
    if len(w) < 2:
        raise ValueError(f"a trajectory needs at least 2 waypoints (start and goal), got {len(w)}")
    bad = np.flatnonzero(~np.all(np.isfinite(w), axis=1))
    if bad.size:
        raise ValueError(f"waypoint {int(bad[0])} is not finite: {w[bad[0]].tolist()}")
    gaps = np.linalg.norm(np.diff(w, axis=0), axis=1)
    rep = np.flatnonzero(gaps < MIN_SEPARATION_M)
    if rep.size:
        i = int(rep[0])
        raise ValueError(f"waypoints {i} and {i + 1} are repeated (closer than {MIN_SEPARATION_M:g} m): "
                         f"{w[i].tolist()}; remove the duplicate (to stop there, use stops=)")
    return w


def _positive(name: str, value: object, count: int | None = None) -> np.ndarray:
    """A finite number > 0, or (with ``count``) optionally one per segment."""
    try:
        v = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if count is not None and v.ndim == 1:
        if v.shape != (count,):
            raise ValueError(f"{name} must be a number or one per leg ({count}), got shape {v.shape}")
    elif v.ndim != 0:
        raise ValueError(f"{name} must be a number, got shape {v.shape}")
    if not np.all(np.isfinite(v)) or np.any(v <= 0):
        raise ValueError(f"{name} must be finite and > 0, got {value!r}")
    return v if count is None or v.ndim == 1 else np.full(count, float(v))


def _check_stops(stops: Iterable[int], n: int) -> tuple[int, ...]:
    out = []
    for s in stops:
        if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or not 0 < int(s) < n - 1:
            raise ValueError(f"stops must be interior waypoint indices 1..{n - 2}, got {s!r}")
        out.append(int(s))
    return tuple(sorted(set(out)))


def _check_angle(name: str, value: object) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an angle in radians, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return v


def _check_kind(kind: str) -> int:
    if kind not in _ORDER:
        raise ValueError(f"kind must be 'minimum_jerk' or 'minimum_snap', got {kind!r}")
    return _ORDER[kind]


def _check_tolerances(tolerances: object, n: int) -> np.ndarray | None:
    if tolerances is None:
        return None
    try:
        tol = np.broadcast_to(np.array(tolerances, dtype=float), (n,)).copy()
    except (TypeError, ValueError):
        raise ValueError(f"tolerances must be a number or one per waypoint ({n}), got {tolerances!r}") from None
    if not np.all(np.isfinite(tol)) or np.any(tol < 0):
        raise ValueError(f"tolerances must be finite and >= 0, got {tolerances!r}")
    return tol


# --- yaw -------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _YawSpec:
    mode: str
    initial: float
    fixed: float | None
    rate_max: float
    accel_max: float


def _yaw_spec(yaw_mode: str, yaw_fixed_rad: float | None, initial_yaw_rad: float, yaw_rate_max_rad_s: float,
              yaw_accel_max_rad_s2: float) -> _YawSpec:
    if yaw_mode not in ("hold", "face_next", "fixed"):
        raise ValueError(f"yaw_mode must be 'hold', 'face_next' or 'fixed', got {yaw_mode!r}")
    initial = _check_angle("initial_yaw_rad", initial_yaw_rad)
    if yaw_mode == "fixed":
        if yaw_fixed_rad is None:
            raise ValueError("yaw_mode 'fixed' needs yaw_fixed_rad")
        fixed: float | None = _check_angle("yaw_fixed_rad", yaw_fixed_rad)
    elif yaw_fixed_rad is not None:
        raise ValueError(f"yaw_fixed_rad is only used with yaw_mode 'fixed' (got yaw_mode {yaw_mode!r})")
    else:
        fixed = None
    return _YawSpec(yaw_mode, initial, fixed, float(_positive("yaw_rate_max_rad_s", yaw_rate_max_rad_s)),
                    float(_positive("yaw_accel_max_rad_s2", yaw_accel_max_rad_s2)))


def _yaw_profile(spec: _YawSpec, w: np.ndarray, w_times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times, unwrapped yaw, yaw rate) on the YAW_DT_S grid, extended past the end until settled."""
    duration = float(w_times[-1])
    if spec.mode == "hold":
        return np.array([0.0, duration]), np.full(2, float(_wrap(spec.initial))), np.zeros(2)
    if spec.mode == "fixed":
        headings = np.array([spec.fixed])
    else:
        headings = np.empty(len(w) - 1)
        prev = spec.initial
        for i, d in enumerate(np.diff(w, axis=0)):
            if math.hypot(d[0], d[1]) >= FACE_MIN_LEG_M:
                prev = math.atan2(d[1], d[0])
            headings[i] = prev
    dt = YAW_DT_S
    n_flight = int(math.ceil(duration / dt))
    n_extra = int(math.ceil((math.pi / spec.rate_max + 2 * spec.rate_max / spec.accel_max + 1.0) / dt))
    t = np.arange(n_flight + n_extra + 1) * dt
    leg = np.clip(np.searchsorted(w_times, t, side="right") - 1, 0, len(headings) - 1)
    target = headings[leg]
    yaw = np.empty(t.size)
    rate = np.empty(t.size)
    psi, omega = float(_wrap(spec.initial)), 0.0
    dv = spec.accel_max * dt
    end = t.size
    for k in range(t.size):
        yaw[k], rate[k] = psi, omega
        e = math.remainder(target[k] - psi, 2 * math.pi)  # the short way round
        if k >= n_flight and abs(e) < 1e-9 and abs(omega) < 1e-9:
            end = k + 1
            break
        # the fastest approach that can still stop in time in steps of dv (n steps from n * dv
        # cover n (n + 1) / 2 * dv * dt), rate- and acceleration-limited, landing on the target
        n = (math.sqrt(1.0 + 8.0 * abs(e) / (dv * dt)) - 1.0) / 2.0
        speed = min(spec.rate_max, n * dv, abs(e) / dt)
        omega += min(dv, max(-dv, math.copysign(speed, e) - omega))
        psi += omega * dt
    return t[:end], yaw[:end], rate[:end]


# --- planning --------------------------------------------------------------------------------

def _verify_tolerances(traj: Trajectory, tol: np.ndarray | None) -> None:
    if tol is None:
        return
    for i, limit in enumerate(tol):
        d = traj.closest_approach(i)
        if d > limit + 1e-9:  # cannot happen with an interpolating spline; a guard against regressions
            raise RuntimeError(f"trajectory passes {d:.3g} m from waypoint {i}, beyond its tolerance {limit:g} m")


def from_segment_times(waypoints: object, segment_times: object, kind: Kind = "minimum_snap", *,
                       stops: Iterable[int] = (), yaw_mode: YawMode = "hold", yaw_fixed_rad: float | None = None,
                       initial_yaw_rad: float = 0.0, yaw_rate_max_rad_s: float = 0.5,
                       yaw_accel_max_rad_s2: float = 1.0) -> Trajectory:
    """The optimal spline of ``kind`` through ``waypoints`` with the given segment times
    (seconds, one number or (N-1,)): no time allocation, no limits, no corridor. Same
    conventions as ``plan``."""
    w = _check_waypoints(waypoints)
    r = _check_kind(kind)
    times = _positive("segment_times", segment_times, len(w) - 1)
    stop_idx = _check_stops(stops, len(w))
    yaw = _yaw_spec(yaw_mode, yaw_fixed_rad, initial_yaw_rad, yaw_rate_max_rad_s, yaw_accel_max_rad_s2)
    coeffs = _solve_coefficients(w, times, r, stop_idx)
    knots = np.concatenate([[0.0], np.cumsum(times)])
    return Trajectory(w, w.copy(), np.arange(len(w)), times.copy(), coeffs, kind, stop_idx,
                      _yaw_profile(yaw, w, knots))


def _trapezoid_times(points: np.ndarray, v: np.ndarray, a: float) -> np.ndarray:
    d = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.where(d >= v * v / a, d / v + v / a, 2 * np.sqrt(d / a))


def _grid_peaks(coeffs: np.ndarray, times: np.ndarray, orders: int) -> np.ndarray:
    """(S, orders): max over a tau grid of |v|, |a| (, |j|) per segment, vectorised; slightly
    below the exact peaks (``_max_norm``), used to steer the allocation."""
    out = np.empty((len(times), orders))
    c = coeffs
    for m in range(1, orders + 1):
        c = P.polyder(c, axis=1)
        values = np.einsum("gk,skd->sgd", _GRID[:, None] ** np.arange(c.shape[1]), c)
        out[:, m - 1] = np.linalg.norm(values, axis=2).max(axis=1) / times ** m
    return out


def _ratios(peaks: np.ndarray, v_lim: np.ndarray, a_lim: float, j_lim: float | None) -> np.ndarray:
    """Per segment, the common time scale that puts it exactly on its binding limit."""
    ratio = np.maximum(peaks[:, 0] / v_lim, np.sqrt(peaks[:, 1] / a_lim))
    if j_lim is not None:
        ratio = np.maximum(ratio, np.cbrt(peaks[:, 2] / j_lim))
    return ratio


def _allocate(points: np.ndarray, times: np.ndarray, v_lim: np.ndarray, a_lim: float, j_lim: float | None,
              r: int, stops: Sequence[int]) -> tuple[np.ndarray, np.ndarray, int]:
    """(segment times, coefficients, solves): the shortest feasible iterate from ``times`` on
    (see the module doc) of either update rule, scaled by its exact largest ratio."""
    orders = 2 if j_lim is None else 3
    coupled = ~np.isin(np.arange(1, len(times)), stops)  # joint k+1 links segments k and k+1
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    solves = 0
    for share in (False, True):
        t = times
        since_best = 0
        for _ in range(MAX_ALLOCATION_ITERATIONS):
            coeffs = _solve_coefficients(points, t, r, stops)
            solves += 1
            ratio = _ratios(_grid_peaks(coeffs, t, orders), v_lim, a_lim, j_lim)
            total = float(t.sum() * ratio.max())
            since_best += 1
            if best is None or total < best[0] * (1 - 1e-3):
                since_best = 0
            if best is None or total < best[0]:
                best = (total, t, coeffs)
            if np.all(np.abs(ratio - 1.0) <= LIMIT_TOLERANCE) or since_best >= ALLOCATION_PATIENCE:
                break
            factor = ratio.copy()
            if share:
                # A segment's peak is often at a joint, where its neighbour's time matters too: a
                # segment over its limit then also slows its neighbours (not across a stop, where
                # the joint is at rest). Needed when legs have different speed limits.
                over = np.where(ratio > 1.0, ratio, 0.0)
                factor[1:] = np.where(coupled, np.maximum(factor[1:], over[:-1]), factor[1:])
                factor[:-1] = np.where(coupled, np.maximum(factor[:-1], over[1:]), factor[:-1])
            t = t * np.clip(factor, 1 / ALLOCATION_STEP, ALLOCATION_STEP) ** ALLOCATION_DAMPING
    assert best is not None
    _, times, coeffs = best
    exact = np.array([[_max_norm(c) / t ** m for m, c in enumerate(_derivatives(coeffs[i], orders), 1)]
                      for i, t in enumerate(times)])
    return times * float(_ratios(exact, v_lim, a_lim, j_lim).max()), coeffs, solves


def _derivatives(c: np.ndarray, orders: int) -> list[np.ndarray]:
    out = []
    for _ in range(orders):
        c = P.polyder(c, axis=0)
        out.append(c)
    return out


def plan(waypoints: object, v_max_mps: float | Sequence[float], a_max_mps2: float, j_max_mps3: float | None = None,
         *, kind: Kind = "minimum_snap", yaw_mode: YawMode = "hold", yaw_fixed_rad: float | None = None,
         initial_yaw_rad: float = 0.0, yaw_rate_max_rad_s: float = 0.5, yaw_accel_max_rad_s2: float = 1.0,
         tolerances: float | Sequence[float] | None = None, stops: Iterable[int] = (),
         corridor_m: float | Sequence[float] | None = 0.15) -> Trajectory:
    """A smooth trajectory through ``waypoints`` ((N, 3) LOCAL_NED metres, N >= 2), at rest at the
    first and last waypoint (and at the interior waypoint indices in ``stops``), flown through
    the others.

    ``v_max_mps``: speed limit (m/s), one number or one per leg (N-1; e.g. slower through
    doors); ``a_max_mps2`` the acceleration limit (m/s^2); ``j_max_mps3`` an optional jerk limit.
    Segment times are allocated so that |v|, |a| (and |j|) stay within the limits everywhere
    (exact polynomial peaks; see ``max_speed``, ``max_acceleration``, ``max_jerk``).
    ``kind``: "minimum_jerk" (degree 5, continuous p/v/a) or "minimum_snap" (degree 7, also
    continuous jerk). ``corridor_m``: the largest distance (m, one number or one per leg) from
    the straight legs; extra joints are inserted on a leg, and as a last resort corners become
    stops, until it holds (None: no corridor).
    ``yaw_mode``: "hold" (``initial_yaw_rad`` throughout), "face_next" (the bearing of the
    current leg, rate- and acceleration-limited from ``initial_yaw_rad``) or "fixed" (turn from
    ``initial_yaw_rad`` to ``yaw_fixed_rad``). ``tolerances``: metres, one number or one per
    waypoint; the trajectory is verified to pass within them (it interpolates every waypoint
    exactly, so this only guards). ValueError on degenerate input: fewer than 2 waypoints,
    non-finite values, consecutive repeated waypoints, non-positive limits, unknown modes.
    """
    w = _check_waypoints(waypoints)
    r = _check_kind(kind)
    n_leg = len(w) - 1
    v_lim = _positive("v_max_mps", v_max_mps, n_leg)
    a_lim = float(_positive("a_max_mps2", a_max_mps2))
    j_lim = None if j_max_mps3 is None else float(_positive("j_max_mps3", j_max_mps3))
    corridor = None if corridor_m is None else _positive("corridor_m", corridor_m, n_leg)
    stop_idx = _check_stops(stops, len(w))
    tol = _check_tolerances(tolerances, len(w))
    yaw = _yaw_spec(yaw_mode, yaw_fixed_rad, initial_yaw_rad, yaw_rate_max_rad_s, yaw_accel_max_rad_s2)

    joints = w.copy()
    leg = np.arange(n_leg)  # the waypoint leg each segment lies on
    times = _trapezoid_times(joints, v_lim, a_lim)
    all_stops = set(stop_idx)
    solves = splits = 0
    while True:  # ends: each pass splits (at most SPLIT_ROUNDS times), adds a stop or straightens a leg
        waypoint_joint = np.concatenate([np.searchsorted(leg, np.arange(n_leg)), [len(joints) - 1]])
        stop_joints = tuple(int(waypoint_joint[s]) for s in sorted(all_stops))
        times, coeffs, n = _allocate(joints, times, v_lim[leg], a_lim, j_lim, r, stop_joints)
        solves += n
        if corridor is None:
            break
        found = [_segment_deviation(coeffs[k], w[leg[k]], w[leg[k] + 1]) for k in range(len(leg))]
        deviation = np.array([d for d, _ in found])
        bad = deviation > corridor[leg]
        if not bad.any():
            break
        split = bad & (np.linalg.norm(np.diff(joints, axis=0), axis=1) >= 2 * MIN_SPLIT_M)
        if splits < SPLIT_ROUNDS and split.any():
            splits += 1
            new_joints, new_leg, new_times = [joints[0]], [], []
            for k in range(len(leg)):
                if split[k]:
                    new_joints.append((joints[k] + joints[k + 1]) / 2)
                    new_leg.append(leg[k])
                    new_times.append(times[k] / 2)
                new_joints.append(joints[k + 1])
                new_leg.append(leg[k])
                new_times.append(times[k] / 2 if split[k] else times[k])
            joints, leg, times = np.array(new_joints), np.array(new_leg), np.array(new_times)
            continue
        # Still out: stop at the corner nearest to where the worst segment strays (a leg between
        # two stops is flown exactly straight); the other end if that one is already at rest.
        k = int(np.flatnonzero(bad)[np.argmax(deviation[bad])])
        near, far = (leg[k], leg[k] + 1) if found[k][1] < 0.5 else (leg[k] + 1, leg[k])
        corner = next((int(c) for c in (near, far) if 0 < c < n_leg and c not in all_stops), None)
        if corner is not None:
            all_stops.add(corner)
            continue
        # Both ends at rest: the leg is straight but overshoots an end along its line (possible
        # with inner joints); as one rest-to-rest segment it moves monotonically from end to end.
        first, last = waypoint_joint[leg[k]], waypoint_joint[leg[k] + 1]
        keep = np.ones(len(joints), dtype=bool)
        keep[first + 1:last] = False
        times = np.concatenate([times[:first], [times[first:last].sum()], times[last:]])
        joints, leg = joints[keep], np.concatenate([leg[:first + 1], leg[last:]])

    knots = np.concatenate([[0.0], np.cumsum(times)])
    traj = Trajectory(w, joints, waypoint_joint, times, coeffs, kind, tuple(sorted(all_stops)),
                      _yaw_profile(yaw, w, knots[waypoint_joint]), iterations=solves)
    peaks = traj.segment_peaks
    slack = 1.0 + 1e-9
    if np.any(peaks[:, 0] > v_lim[leg] * slack) or peaks[:, 1].max() > a_lim * slack or (
            j_lim is not None and peaks[:, 2].max() > j_lim * slack):
        raise RuntimeError(f"time allocation failed to respect the limits: {traj.summary()}")
    _verify_tolerances(traj, tol)
    return traj
