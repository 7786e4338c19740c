"""IMU + localization-fix fusion: the seed paper's Kalman filter (10 Hz fixes -> 50 Hz pose).

The two-lidar paper (Fig. 2) fuses 10 Hz localization fixes (x, y, heading from the planar
lidar, height from the vertical one) with the IMU's acceleration and attitude into a smoother
50 Hz pose. :class:`FusionFilter` does that, with the fixes' latency compensated.

Frames and units (README, ``companion/frames.py``): world LOCAL_NED (m, z down, the floor is
z = 0), body FRD, Euler ZYX in radians, times on the daemon clock in seconds.

State
    ``x = [p (3), v (3), b (3)]``: position NED (m), velocity NED (m/s) and the accelerometer
    bias (m/s^2) **in body FRD**, with its 9x9 covariance. The bias is a property of the
    sensor, so it is constant in the body frame: stored in NED it would have to rotate with
    every yaw change (the filter would keep re-learning it while the vehicle turns), and a
    relocalization that rotates the map would make it wrong. In body frame the model stays
    linear because the rotation is a known input: ``dv/db = -R dt``.
    Heading ``yaw`` (rad, north towards east, map frame) is a separate scalar state with its
    own variance, driven by the yaw rate and corrected by heading fixes.

Propagation (:meth:`FusionFilter.predict`)
    ``a_ned = R(roll, pitch, yaw) @ (f_body - b) + [0, 0, g]`` with ``f_body`` the specific
    force as HIGHRES_IMU reports it (about ``(0, 0, -9.81)`` at rest, level), roll and pitch
    from the autopilot's attitude and yaw from this filter (so the map heading, not the
    compass, rotates the accelerations). Each sample is held over the interval that ends at
    its time stamp. The yaw rate comes from the gyro when given (ZYX Euler kinematics), else
    from the change of the attitude's yaw between samples (its offset to the map does not
    matter). Process noise: white acceleration of density ``accel_noise_density`` and a bias
    random walk ``accel_bias_walk`` (continuous model, so splitting an interval does not change
    the noise).

Corrections
    Position (x, y or x, y, z), height (NED z = -height) and yaw fixes, each with its capture
    time. Chi-square innovation gate (99.9 % quantile), Joseph-form covariance update. A capture
    time is known on the IMU's time line to ``fix_time_sd_s``: each fix's variance is widened by
    the state's rate (velocity, yaw rate) times that when it is applied.

Delay compensation
    A ring buffer of the last ``buffer_s`` seconds holds, per IMU step, the state, covariance,
    yaw and the IMU input, and a log holds the fixes applied in that window. A fix captured at
    ``t_c`` rewinds to the last stored step before ``t_c``, is applied exactly at ``t_c`` (the
    interval is split), and every stored IMU input and logged fix after it is re-applied up to
    now, so late and out-of-order fixes give the same result as fixes delivered on time. A fix
    captured after the newest IMU sample waits in the log until the IMU reaches it. Fixes
    older than the buffer are rejected and counted.

Health (:meth:`FusionFilter.state`)
    Not initialised until a position, a height (or a 3-D position) and a yaw fix have been
    seen; then ok, degraded when the newest accepted position or height fix is older than
    ``degraded_after_s`` (yaw: ``yaw_degraded_after_s``), lost beyond ``lost_after_s`` (yaw:
    ``yaw_lost_after_s``) or when the IMU stopped for ``imu_timeout_s``. ``healthy`` is False
    when lost or not initialised: the caller must not send the estimate then.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass, field

import numpy as np

from companion.frames import GRAVITY_MPS2, euler_yaw_rate, rotation_from_euler, wrap_pi
from companion.health import State

# Chi-square 99.9 % quantiles by degrees of freedom: a consistent fix fails 1 time in 1000.
CHI2_GATE_999 = {1: 10.828, 2: 13.816, 3: 16.266}

# Variance reported for quantities the filter does not know yet (not initialised): finite, huge.
UNKNOWN_VARIANCE = 1e6
# Variance given to a position fix along a direction it does not measure (without_direction):
# the gain along it is then at most 1e-6 per fix for a filter variance of 100 m^2, nothing over
# minutes of fixes, while the 2x2 innovation stays well conditioned in double precision.
UNMEASURED_POSITION_VARIANCE_M2 = 1e8

_POSITION, _HEIGHT, _YAW, _RESET = range(4)
_KIND_NAMES = ("position", "height", "yaw")
_I3 = np.eye(3)
_I9 = np.eye(9)


@dataclass(frozen=True)
class FusionConfig:
    """Tuning of :class:`FusionFilter`; every default is documented with its reasoning."""

    # White-noise density of the acceleration error, (m/s^2)/sqrt(Hz). A per-sample std s at
    # rate f is s/sqrt(f): 0.05 m/s^2 at 50 Hz is 0.007. The default is larger because the error
    # of rotating the specific force with the autopilot's attitude (1 deg is 0.17 m/s^2),
    # vibration aliasing and the sample-and-hold of a changing acceleration all land here.
    accel_noise_density: float = 0.03
    # Random walk of the accelerometer bias, (m/s^2)/sqrt(s): lets the bias follow temperature
    # drift and slowly changing attitude offsets (which the bias also absorbs).
    accel_bias_walk: float = 0.005
    # White-noise density of the yaw rate, rad/s/sqrt(Hz) = rad/sqrt(s): the gyro's noise and the
    # part of its bias the autopilot's calibration leaves (not estimated here), over the interval
    # between heading fixes. 0.0015 is 0.013 deg per 25 ms (a fix at 40 Hz), 0.1 deg/s of bias plus
    # 0.01 rad/s of noise per 50 Hz sample with margin; the rate from attitude differences (no gyro)
    # jitters more. Until 2026-12-06 0.005: the yaw sent then claimed 0.06 deg where the realistic
    # arena's flights were 0.02 deg off (yaw NEES 0.15, below its band; README, "Real buildings").
    yaw_rate_noise_density: float = 0.0015
    init_velocity_std: float = 0.5  # m/s, velocity is unknown at initialisation (zero assumed)
    init_bias_std: float = 0.2  # m/s^2, a typical MEMS accelerometer turn-on bias bound
    reset_position_std: float = 0.05  # m, default std of a position given to reset()
    reset_yaw_std: float = 0.02  # rad, default std of a yaw given to reset()
    buffer_s: float = 0.5  # s of history kept for delay compensation; older fixes are rejected
    buffer_capacity: int = 256  # IMU steps the ring holds (>= buffer_s * IMU rate; 0.5 s at 500 Hz)
    degraded_after_s: float = 0.3  # s without an accepted position or height fix -> degraded
    lost_after_s: float = 1.0  # s without an accepted position or height fix -> lost
    # Horizontal position standard deviation (largest axis) beyond which the estimate is degraded
    # (missions slow down) and lost (not sent): a corridor's axis, measured by no fix, grows on
    # the IMU alone. A flight on corners stays at millimetres to centimetres.
    degraded_position_std_m: float = 0.25
    lost_position_std_m: float = 1.0
    yaw_degraded_after_s: float = 1.0  # s without a yaw fix -> degraded (gyro holds heading)
    yaw_lost_after_s: float = 5.0  # s without a yaw fix -> lost
    imu_timeout_s: float = 0.2  # s without an IMU sample -> lost (nothing to extrapolate with)
    max_imu_gap_s: float = 1.0  # s; a longer IMU gap drops the filter to not initialised
    # A fix failing the gate while its kind has had no accepted fix for this long re-seeds that
    # part of the state instead of being rejected, so a diverged filter cannot lock itself out.
    relock_after_s: float = 1.0
    # A fix's capture time on the IMU's time line is known to about this (s, 1 sigma): the scanner's
    # clock and the autopilot's are each mapped onto the daemon's, and the autopilot's accelerometer
    # filter delays its samples. The state moves by its rate times that, so a fix's variance grows by
    # (velocity x this)^2 along the velocity (yaw: yaw rate); fast flight trusts each fix less.
    # 10 ms: measured on ArduCopter SITL's link (README, "ArduPilot SITL"); 0: taken as exact.
    fix_time_sd_s: float = 0.01


@dataclass
class FusionStats:
    """Counters; fixes are counted once, when they are first applied or rejected."""

    imu_used: int = 0
    imu_rejected_nonfinite: int = 0
    imu_rejected_out_of_order: int = 0  # time stamp not after the previous sample
    fixes_accepted: dict[str, int] = field(default_factory=lambda: dict.fromkeys(_KIND_NAMES, 0))
    fixes_gated: dict[str, int] = field(default_factory=lambda: dict.fromkeys(_KIND_NAMES, 0))
    fixes_stale: int = 0  # captured before the buffer's oldest step
    # Non-finite value, time or covariance, covariance not positive definite, or captured more
    # than buffer_s after the newest IMU sample.
    fixes_invalid: int = 0
    relocks: int = 0  # gated fixes that re-seeded a state part after relock_after_s without fixes
    resets: int = 0  # reset() calls
    reinitialisations: int = 0  # drops to not initialised after an IMU gap


@dataclass(frozen=True)
class FusedState:
    """The fused estimate at time ``t`` (daemon clock, s) in LOCAL_NED."""

    t: float
    position_ned: np.ndarray  # (3,) m
    velocity_ned: np.ndarray  # (3,) m/s
    yaw: float  # rad, map heading from north towards east, in [-pi, pi)
    position_covariance: np.ndarray  # (3, 3) m^2
    velocity_covariance: np.ndarray  # (3, 3) (m/s)^2
    yaw_variance: float  # rad^2
    healthy: bool  # False when lost or not initialised: do not send the estimate
    reason: str
    status: State = State.LOST
    accel_bias_body: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) m/s^2, body FRD
    reset_counter: int = 0  # increments on every position/yaw jump (reset, relock, reinitialisation)


class _Fix:
    """One logged correction; ``gated`` until it has passed the gate once."""

    __slots__ = ("t", "kind", "z", "r", "rows", "gated", "reseed")

    def __init__(self, t: float, kind: int, z: np.ndarray | float, r: np.ndarray | float,
                 rows: slice | None) -> None:
        self.t = t
        self.kind = kind
        self.z = z
        self.r = r
        self.rows = rows  # state rows measured (position, height); None for yaw and reset
        self.gated = kind != _RESET
        self.reseed = False


class FusionFilter:
    """Kalman filter fusing IMU samples with delayed position / height / yaw fixes (module doc)."""

    def __init__(self, config: FusionConfig | None = None) -> None:
        self.config = c = config or FusionConfig()
        self.stats = FusionStats()
        self.reset_counter = 0
        n = c.buffer_capacity
        # Ring buffer: entry k is the state after the IMU input U[k] was held over (T[k-1], T[k]].
        self._T = np.zeros(n)
        self._X = np.zeros((n, 9))
        self._P = np.zeros((n, 9, 9))
        self._Yaw = np.zeros(n)
        self._YawVar = np.zeros(n)
        self._U = np.zeros((n, 6))  # fx, fy, fz (m/s^2 body), roll, pitch (rad), yaw rate (rad/s)
        self._newest = -1
        self._count = 0
        self._fixes: list[_Fix] = []  # sorted by capture time, within the buffer or pending
        self._fix_times: list[float] = []
        # Working state (the newest, or the one being replayed).
        self._x = np.zeros(9)
        self._cov = np.zeros((9, 9))
        self._yaw = 0.0
        self._yaw_var = 0.0
        self._accel_ned = (0.0, 0.0, 0.0)  # of the newest step, for extrapolation
        self._yaw_rate = 0.0  # rad/s of the working state's newest step
        self._F = np.eye(9)
        self._q_dt = -1.0  # the step length self._Q was made for (steps repeat: 1 / IMU rate)
        self._Q = np.zeros((9, 9))
        qa, qb = c.accel_noise_density ** 2, c.accel_bias_walk ** 2
        cubic, square, linear = np.zeros((9, 9)), np.zeros((9, 9)), np.zeros((9, 9))
        cubic[0:3, 0:3] = qa * _I3  # p-p: qa dt^3 / 3
        square[0:3, 3:6] = square[3:6, 0:3] = qa * _I3  # p-v: qa dt^2 / 2
        linear[3:6, 3:6], linear[6:9, 6:9] = qa * _I3, qb * _I3  # v-v: qa dt, b-b: qb dt
        self._noise_terms = (cubic, square, linear)
        self._initialised = False
        self._t_imu: float | None = None  # time of the newest used IMU sample
        self._attitude_yaw: float | None = None  # attitude yaw of that sample
        self._last_accepted = [-math.inf, -math.inf, -math.inf]  # capture time per fix kind
        # Newest fix of each kind while not initialised: (t, value, variance).
        self._seeds: list[tuple[float, float | np.ndarray, float | np.ndarray] | None] = [None, None, None]

    # ------------------------------------------------------------------ inputs

    def predict(self, t: float, accel_body_mps2: np.ndarray, attitude_euler_rad: tuple[float, float, float],
                gyro_body_radps: np.ndarray | None = None) -> bool:
        """Propagate to ``t`` (s) with one IMU sample; returns False if the sample was rejected.

        ``accel_body_mps2``: specific force in body FRD (HIGHRES_IMU x/y/zacc), m/s^2.
        ``attitude_euler_rad``: (roll, pitch, yaw) of body FRD in NED from the autopilot, rad.
        ``gyro_body_radps``: optional body rates (p, q, r) in rad/s; without it the yaw rate is
        the change of the attitude's yaw since the previous sample.
        Non-finite samples and time stamps not after the previous one are rejected and counted.
        """
        fx, fy, fz = (float(v) for v in accel_body_mps2)
        roll, pitch, att_yaw = (float(v) for v in attitude_euler_rad)
        values = [t, fx, fy, fz, roll, pitch, att_yaw]
        if gyro_body_radps is not None:
            values.extend(float(v) for v in gyro_body_radps)
        if not all(map(math.isfinite, values)):
            self.stats.imu_rejected_nonfinite += 1
            return False
        t = float(t)
        t_prev = self._t_imu
        if t_prev is not None and t <= t_prev:
            self.stats.imu_rejected_out_of_order += 1
            return False
        self.stats.imu_used += 1
        if gyro_body_radps is not None:
            yaw_rate = euler_yaw_rate(values[7:10], roll, pitch)
        elif t_prev is not None and self._attitude_yaw is not None:
            yaw_rate = wrap_pi(att_yaw - self._attitude_yaw) / (t - t_prev)
        else:
            yaw_rate = 0.0
        self._t_imu = t
        self._attitude_yaw = att_yaw
        if not self._initialised:
            self._try_initialise()
            return True
        if t - t_prev > self.config.max_imu_gap_s:
            self._uninitialise()
            self.stats.reinitialisations += 1
            return True
        self._advance(t_prev, t, fx, fy, fz, roll, pitch, yaw_rate, self._hold_variance(self._newest, fx, fy, fz, t - t_prev))
        k = (self._newest + 1) % self.config.buffer_capacity
        self._store(k, t)
        self._U[k] = (fx, fy, fz, roll, pitch, yaw_rate)
        self._newest = k
        self._count = min(self._count + 1, self.config.buffer_capacity)
        self._prune(t)
        return True

    def correct_position(self, t_capture: float, position: np.ndarray, covariance: np.ndarray) -> bool:
        """Fuse a position fix of the body origin captured at ``t_capture`` (s).

        ``position``: (x, y) or (x, y, z) in LOCAL_NED, m; ``covariance``: matching (2, 2) or
        (3, 3) in m^2. Returns True if the fix was applied (or waits for the IMU to reach its
        capture time), False if it was rejected (invalid, stale or gated; all counted).
        """
        fix = self._position_fix(t_capture, position, covariance)
        return fix is not None and self._submit(fix)

    def correct_pose(self, t_capture: float, position: np.ndarray, covariance: np.ndarray, yaw: float,
                     yaw_variance: float) -> bool:
        """:meth:`correct_position` and :meth:`correct_yaw` of one capture (a planar localizer's
        fix) with one re-propagation instead of two; the same result as the two calls in that
        order. Each part is validated, gated and counted on its own; returns True if both were
        applied (or wait for the IMU)."""
        fixes = [f for f in (self._position_fix(t_capture, position, covariance), self._yaw_fix(t_capture, yaw, yaw_variance))
                 if f is not None]
        return bool(fixes) and self._submit(*fixes) and len(fixes) == 2

    def _position_fix(self, t_capture: float, position: np.ndarray, covariance: np.ndarray) -> _Fix | None:
        """The logged fix of a position (see :meth:`correct_position`), None (counted) if invalid."""
        z = np.array(position, dtype=float).ravel()
        r = np.array(covariance, dtype=float)
        m = z.size
        if m not in (2, 3) or r.shape != (m, m) or not _valid(t_capture, z, r):
            self.stats.fixes_invalid += 1
            return None
        return _Fix(float(t_capture), _POSITION, z, 0.5 * (r + r.T), slice(0, m))

    def correct_height(self, t_capture: float, height_m_up: float, variance: float) -> bool:
        """Fuse a height above the floor (m, positive up: NED z = -height), variance in m^2."""
        z = -float(height_m_up)
        if not _valid(t_capture, np.array([z]), np.array([[float(variance)]])):
            self.stats.fixes_invalid += 1
            return False
        return self._submit(_Fix(float(t_capture), _HEIGHT, np.array([z]),
                                 np.array([[float(variance)]]), slice(2, 3)))

    def correct_yaw(self, t_capture: float, yaw: float, variance: float) -> bool:
        """Fuse a map heading (rad, north towards east) captured at ``t_capture``, variance rad^2."""
        fix = self._yaw_fix(t_capture, yaw, variance)
        return fix is not None and self._submit(fix)

    def _yaw_fix(self, t_capture: float, yaw: float, variance: float) -> _Fix | None:
        """The logged fix of a heading (see :meth:`correct_yaw`), None (counted) if invalid."""
        if not _valid(t_capture, np.array([yaw]), np.array([[float(variance)]])):
            self.stats.fixes_invalid += 1
            return None
        return _Fix(float(t_capture), _YAW, wrap_pi(float(yaw)), float(variance), None)

    def reset(self, position_ned: np.ndarray, yaw: float, t: float, position_variance: float | None = None,
              yaw_variance: float | None = None) -> bool:
        """Relocalization jump: position (3,) NED in m and yaw in rad are valid at ``t`` (s).

        Velocity and bias are kept (the velocity is rotated with the heading change); history
        before ``t`` is kept, so fixes captured before the jump still apply before it. A ``t``
        older than the buffer applies at the newest IMU time (and drops the older history).
        Initialises the filter if needed (at the first IMU sample when there was none yet).
        Variances default to ``reset_position_std``^2 / ``reset_yaw_std``^2. Returns False (and
        counts the call as invalid) on non-finite input.
        """
        c = self.config
        pos_var = c.reset_position_std ** 2 if position_variance is None else float(position_variance)
        yaw_var = c.reset_yaw_std ** 2 if yaw_variance is None else float(yaw_variance)
        p = np.array(position_ned, dtype=float).ravel()
        if p.size != 3 or not _valid(t, np.append(p, yaw), np.diag([pos_var, pos_var, pos_var, yaw_var])):
            self.stats.fixes_invalid += 1
            return False
        fix = _Fix(float(t), _RESET, np.append(p, wrap_pi(float(yaw))), (pos_var, yaw_var), None)
        if not self._initialised:
            self._seeds = [(fix.t, p[0:2], pos_var * np.eye(2)), (fix.t, float(p[2]), pos_var),
                           (fix.t, fix.z[3], yaw_var)]
            self._try_initialise()
        elif fix.t <= self._T[self._oldest()] or fix.t < self._t_imu - self.config.buffer_s:
            # Older than the history: the jump happens now and the old-frame history is dropped.
            self._apply_reset(fix)
            self._store(self._newest, self._t_imu)
            self._count = 1
            self._drop_fixes_until(self._t_imu)
            self._mark_accepted(_RESET, self._t_imu)
        elif not self._submit(fix):  # only a capture time too far in the future fails here
            return False
        self.stats.resets += 1
        self.reset_counter += 1
        return True

    # ------------------------------------------------------------------ output

    def state(self, t: float) -> FusedState:
        """The estimate at ``t`` (s): extrapolated from the newest IMU step when ``t`` is later.

        For ``t`` before the newest IMU step the newest state is returned (with its own time).
        Health as in the module doc; never contains a non-finite number.
        """
        c = self.config
        t = float(t)
        if not self._initialised:
            missing = [name for name, s in zip(_KIND_NAMES, self._seeds) if s is None]
            reason = "not initialised: waiting for " + (", ".join(missing) + " fix" if missing else "IMU")
            return _unknown_state(t, reason, self.reset_counter)
        t_imu = self._t_imu
        x, P = self._x, self._cov
        dt = t - t_imu
        if dt > 0:
            ax, ay, az = self._accel_ned
            h = 0.5 * dt * dt
            position = x[0:3] + dt * x[3:6] + (h * ax, h * ay, h * az)
            velocity = x[3:6] + (dt * ax, dt * ay, dt * az)
            pv = P[0:3, 3:6]
            q = c.accel_noise_density ** 2
            position_cov = P[0:3, 0:3] + dt * (pv + pv.T) + (dt * dt) * P[3:6, 3:6] + (q * dt ** 3 / 3) * np.eye(3)
            velocity_cov = P[3:6, 3:6] + (q * dt) * np.eye(3)
            yaw_var = self._yaw_var + c.yaw_rate_noise_density ** 2 * dt
        else:
            t = t_imu
            position, velocity = x[0:3].copy(), x[3:6].copy()
            position_cov, velocity_cov = P[0:3, 0:3].copy(), P[3:6, 3:6].copy()
            yaw_var = self._yaw_var
        status, reason = self._health(t, position_cov)
        return FusedState(t, position, velocity, self._yaw, position_cov, velocity_cov, yaw_var,
                          status != State.LOST, reason, status, x[6:9].copy(), self.reset_counter)

    # ------------------------------------------------------------------ internals

    def _health(self, t: float, position_cov: np.ndarray) -> tuple[State, str]:
        """Lost or degraded by the age of the last accepted fix of each kind, and by the horizontal
        position's standard deviation (its largest axis): fixes that measure one direction only
        (a corridor's walls) keep coming while the other grows on the IMU alone."""
        c = self.config
        imu_age = t - self._t_imu
        if imu_age > c.imu_timeout_s:
            return State.LOST, f"no IMU sample for {imu_age:.2f} s"
        worst, reason = State.OK, ""
        for kind, degraded, lost in ((_POSITION, c.degraded_after_s, c.lost_after_s),
                                     (_HEIGHT, c.degraded_after_s, c.lost_after_s),
                                     (_YAW, c.yaw_degraded_after_s, c.yaw_lost_after_s)):
            age = t - self._last_accepted[kind]
            state = State.LOST if age > lost else State.DEGRADED if age > degraded else State.OK
            if state > worst:
                worst, reason = state, f"no {_KIND_NAMES[kind]} fix for {age:.2f} s"
        (a, _), (b, d) = position_cov[0:2, 0:2].tolist()  # its lower triangle
        largest = 0.5 * (a + d) + math.hypot(0.5 * (a - d), b)  # the 2x2's larger eigenvalue
        sigma = math.sqrt(max(largest, 0.0))
        state = (State.LOST if sigma > c.lost_position_std_m
                 else State.DEGRADED if sigma > c.degraded_position_std_m else State.OK)
        if state > worst:
            worst, reason = state, f"horizontal position uncertain: {sigma:.2f} m (1 sigma)"
        if worst == State.OK:
            reason = f"position fix {t - self._last_accepted[_POSITION]:.2f} s old"
        return worst, reason

    def _submit(self, *fixes: _Fix) -> bool:
        """Seed, queue (captured after the newest IMU sample) or apply fixes of one capture time
        with one re-propagation. False if any was rejected (stale, a clock error or gated)."""
        if not self._initialised:
            for fix in fixes:
                self._seed(fix)
            return True
        t = fixes[0].t
        if t > self._t_imu:
            if t > self._t_imu + self.config.buffer_s:  # a clock error, not latency
                self.stats.fixes_invalid += len(fixes)
                return False
            for fix in fixes:
                self._insert(fix)  # applied by predict() when the IMU reaches it
            return True
        cap = self.config.buffer_capacity
        j, steps = self._newest, 1
        while self._T[j] >= t:
            if steps >= self._count:
                j = -1
                break
            j, steps = (j - 1) % cap, steps + 1
        if j < 0 or t < self._t_imu - self.config.buffer_s:
            self.stats.fixes_stale += len(fixes)
            return False
        for fix in fixes:
            self._insert(fix)
        applied = True
        while not self._replay(j):  # a new fix was gated out and removed from the log: the newest
            applied = False          # state was restored, so replay for the new fixes still logged
            if not any(logged is fix for fix in fixes for logged in self._fixes):
                break
        return applied

    def _replay(self, j: int) -> bool:
        """Re-run stored IMU inputs and logged fixes from ring entry ``j`` to the newest.

        The new fixes lie in the first interval: if the gate rejects one the replay stops and
        the newest state is restored untouched (the caller replays again for the others).
        """
        cap = self.config.buffer_capacity
        accel_ned = self._accel_ned
        self._load(j)
        k, t0 = j, float(self._T[j])
        while k != self._newest:
            k = (k + 1) % cap
            t1 = float(self._T[k])
            fx, fy, fz, roll, pitch, yaw_rate = self._U[k].tolist()
            hold_var = self._hold_variance((k - 1) % cap, fx, fy, fz, t1 - t0)
            if not self._advance(t0, t1, fx, fy, fz, roll, pitch, yaw_rate, hold_var):
                self._load(self._newest)
                self._accel_ned = accel_ned
                return False
            self._store(k, t1)
            t0 = t1
        return True

    def _hold_variance(self, previous: int, fx: float, fy: float, fz: float, dt: float) -> tuple[float, float, float]:
        """Velocity variance, (m/s)^2 along each body axis (FRD), of holding one IMU sample for ``dt`` s.

        A sample is the autopilot's low-passed accelerometer at one instant (ArduPilot:
        INS_ACCEL_FILTER, 20 Hz), held here for ``dt``. In smooth flight the signal moves little
        between samples and this adds next to nothing. An impact (a touchdown) is a pulse the
        filter stretches to a decay of tau = 8 ms, shorter than the 20 ms between samples of a
        50 Hz stream: the first sample after it sees the decay at an unknown phase, and the
        true velocity change exceeds the one integrated from the held samples by -0.7 to +3.8
        times |change| * dt, 1.4 times RMS over the phase (|change|: the jump from the previous
        sample; a late phase shows a small jump and hides most of the pulse). The samples after
        it add their own (smaller) changes, so one ``|change| * dt`` per sample and axis as the
        standard deviation covers the RMS: the next fixes then correct the velocity instead of
        failing the gate. (Half of it, on every axis, left the late phases to the gate: a touchdown
        20 ms before a sample set the vertical velocity 0.3 m/s off, every height fix was gated and
        the height ran 0.35 m below the floor until the relock a second later. Per axis, so that a
        turn does not open the vertical velocity: a height that the IMU carries while a table hides
        the floor must stay tight enough to tell the table from the floor.)
        """
        if self._count == 0:
            return (0.0, 0.0, 0.0)
        px, py, pz = self._U[previous, 0:3].tolist()
        return ((fx - px) * dt) ** 2, ((fy - py) * dt) ** 2, ((fz - pz) * dt) ** 2

    def _advance(self, t0: float, t1: float, fx: float, fy: float, fz: float, roll: float, pitch: float,
                 yaw_rate: float, hold_var: tuple[float, float, float]) -> bool:
        """Propagate the working state over (t0, t1], applying logged fixes captured in it.
        ``hold_var``: the velocity variances, (m/s)^2 along each body axis (FRD), of the IMU sample
        held over the step (:meth:`_hold_variance`).

        Returns False if a fix was rejected by the gate (it is removed from the log).
        """
        if any(hold_var):
            r = rotation_from_euler(roll, pitch, self._yaw)
            self._cov[3:6, 3:6] += (r * hold_var) @ r.T  # the body axes' variances in NED
        times = self._fix_times
        if not times or times[-1] <= t0:
            self._step(t1 - t0, fx, fy, fz, roll, pitch, yaw_rate)
            return True
        ok = True
        t = t0
        for fix in self._fixes[bisect_right(times, t0):bisect_right(times, t1)]:
            self._step(fix.t - t, fx, fy, fz, roll, pitch, yaw_rate)
            t = fix.t
            if not self._apply(fix):
                self._remove(fix)
                ok = False
        self._step(t1 - t, fx, fy, fz, roll, pitch, yaw_rate)
        return ok

    def _step(self, dt: float, fx: float, fy: float, fz: float, roll: float, pitch: float,
              yaw_rate: float) -> None:
        """Propagate the working state by ``dt`` s holding one IMU input."""
        if dt <= 0.0:
            return
        c = self.config
        psi = self._yaw + 0.5 * yaw_rate * dt  # heading at mid-interval rotates the input
        cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        cy, sy = math.cos(psi), math.sin(psi)
        r00, r01, r02 = cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy
        r10, r11, r12 = cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy
        r20, r21, r22 = -sp, sr * cp, cr * cp
        px, py, pz, vx, vy, vz, bx, by, bz = self._x.tolist()
        ux, uy, uz = fx - bx, fy - by, fz - bz
        ax = r00 * ux + r01 * uy + r02 * uz
        ay = r10 * ux + r11 * uy + r12 * uz
        az = r20 * ux + r21 * uy + r22 * uz + GRAVITY_MPS2
        h = 0.5 * dt * dt
        self._x[0:6] = (px + vx * dt + h * ax, py + vy * dt + h * ay, pz + vz * dt + h * az,
                        vx + dt * ax, vy + dt * ay, vz + dt * az)
        F = self._F
        F[0:6, 6:9] = ((-h * r00, -h * r01, -h * r02), (-h * r10, -h * r11, -h * r12), (-h * r20, -h * r21, -h * r22),
                       (-dt * r00, -dt * r01, -dt * r02), (-dt * r10, -dt * r11, -dt * r12),
                       (-dt * r20, -dt * r21, -dt * r22))  # dp/db = -R dt^2/2, dv/db = -R dt
        F[0, 3] = F[1, 4] = F[2, 5] = dt
        P = F @ self._cov @ F.T
        if dt != self._q_dt:
            self._Q = self._process_noise(dt)
            self._q_dt = dt
        P += self._Q
        self._cov = P
        self._yaw = wrap_pi(self._yaw + yaw_rate * dt)
        self._yaw_rate = yaw_rate
        self._yaw_var += c.yaw_rate_noise_density ** 2 * dt
        self._accel_ned = (ax, ay, az)

    def _process_noise(self, dt: float) -> np.ndarray:
        """(9, 9) discrete process noise of one ``dt`` s step: white acceleration integrated into
        position and velocity (with their coupling) and the bias random walk."""
        cubic, square, linear = self._noise_terms
        return (dt ** 3 / 3.0) * cubic + (0.5 * dt * dt) * square + dt * linear

    def _apply(self, fix: _Fix) -> bool:
        """Apply one logged fix to the working state; gate it the first time. False if rejected."""
        if fix.kind == _RESET:
            self._apply_reset(fix)
            self._mark_accepted(_RESET, fix.t)
            return True
        r = self._with_timing(fix)
        s_inv = None if fix.kind == _YAW else np.linalg.inv(self._cov[fix.rows, fix.rows] + r)  # innovation
        if fix.gated:
            if fix.kind == _YAW:
                y = wrap_pi(fix.z - self._yaw)
                nis, dof = y * y / (self._yaw_var + r), 1
            else:
                y = fix.z - self._x[fix.rows]
                nis, dof = float(y @ s_inv @ y), y.size
            if nis > CHI2_GATE_999[dof]:
                if fix.t - self._last_accepted[fix.kind] <= self.config.relock_after_s:
                    self.stats.fixes_gated[_KIND_NAMES[fix.kind]] += 1
                    return False
                fix.reseed = True
                self.stats.relocks += 1
                self.reset_counter += 1
            fix.gated = False
            self.stats.fixes_accepted[_KIND_NAMES[fix.kind]] += 1
            self._mark_accepted(fix.kind, fix.t)
            if fix.rows == slice(0, 3):
                self._mark_accepted(_HEIGHT, fix.t)
        if fix.kind == _YAW:
            if fix.reseed:
                self._yaw, self._yaw_var = fix.z, r
            else:
                s = self._yaw_var + r
                k = self._yaw_var / s
                self._yaw = wrap_pi(self._yaw + k * wrap_pi(fix.z - self._yaw))
                self._yaw_var = (1.0 - k) ** 2 * self._yaw_var + k * k * r  # Joseph form
        elif fix.reseed:
            rows = fix.rows
            self._x[rows] = fix.z
            self._cov[rows, :] = 0.0
            self._cov[:, rows] = 0.0
            self._cov[rows, rows] = r
        else:
            rows = fix.rows
            P = self._cov
            K = P[:, rows] @ s_inv
            self._x += K @ (fix.z - self._x[rows])
            A = _I9.copy()
            A[:, rows] -= K
            P = A @ P @ A.T + K @ r @ K.T  # Joseph form: stays symmetric positive definite
            self._cov = 0.5 * (P + P.T)
        return True

    def _with_timing(self, fix: _Fix) -> np.ndarray | float:
        """The fix's variance (m^2, or rad^2 for yaw) plus what its capture time's uncertainty
        (``fix_time_sd_s``) adds at the working state's velocity (or yaw rate)."""
        sd = self.config.fix_time_sd_s
        if sd == 0.0:
            return fix.r
        if fix.kind == _YAW:
            return fix.r + (sd * self._yaw_rate) ** 2
        rows = fix.rows
        v = sd * self._x[rows.start + 3:rows.stop + 3]
        return fix.r + np.outer(v, v)

    def _apply_reset(self, fix: _Fix) -> None:
        """Jump position and yaw; rotate velocity (and its covariance) by the heading change."""
        pos_var, yaw_var = fix.r
        d = wrap_pi(float(fix.z[3]) - self._yaw)
        A = _I9.copy()
        A[3:5, 3:5] = ((math.cos(d), -math.sin(d)), (math.sin(d), math.cos(d)))
        self._x[3:6] = A[3:6, 3:6] @ self._x[3:6]
        self._x[0:3] = fix.z[0:3]
        P = A @ self._cov @ A.T
        P[0:3, :] = 0.0
        P[:, 0:3] = 0.0
        P[0:3, 0:3] = pos_var * np.eye(3)
        self._cov = P
        self._yaw, self._yaw_var = float(fix.z[3]), yaw_var

    def _mark_accepted(self, kind: int, t: float) -> None:
        """Record an accepted fix of ``kind`` (a reset counts for every kind) captured at ``t``."""
        for k in (_POSITION, _HEIGHT, _YAW) if kind == _RESET else (kind,):
            self._last_accepted[k] = max(self._last_accepted[k], t)

    def _seed(self, fix: _Fix) -> None:
        """Keep the newest fix of each kind until all are there, then initialise."""
        if fix.kind == _YAW:
            self._seeds[_YAW] = (fix.t, fix.z, fix.r)
        elif fix.rows == slice(2, 3):
            self._seeds[_HEIGHT] = (fix.t, float(fix.z[0]), float(fix.r[0, 0]))
        else:
            self._seeds[_POSITION] = (fix.t, fix.z[0:2], fix.r[0:2, 0:2])
            if fix.z.size == 3:
                self._seeds[_HEIGHT] = (fix.t, float(fix.z[2]), float(fix.r[2, 2]))
        self._try_initialise()

    def _try_initialise(self) -> None:
        """Initialise at the newest IMU time once recent position, height and yaw seeds exist.

        The seeds are up to ``buffer_s`` old: their variances grow by the motion the unknown
        velocity (``init_velocity_std``) allows since capture.
        """
        t = self._t_imu
        if t is None or any(s is None or t - s[0] > self.config.buffer_s for s in self._seeds):
            return
        (tp, xy, rxy), (th, z, rz), (ty, yaw, ryaw) = self._seeds
        v2 = self.config.init_velocity_std ** 2
        cov = np.zeros((3, 3))
        cov[0:2, 0:2] = rxy + v2 * max(t - tp, 0.0) ** 2 * np.eye(2)
        cov[2, 2] = rz + v2 * max(t - th, 0.0) ** 2
        self._initialise(t, np.array([xy[0], xy[1], z]), cov, yaw, ryaw)
        self._last_accepted = [tp, th, ty]

    def _initialise(self, t: float, position: np.ndarray, position_cov: np.ndarray, yaw: float,
                    yaw_var: float) -> None:
        c = self.config
        self._x[:] = 0.0
        self._x[0:3] = position
        self._cov = np.zeros((9, 9))
        self._cov[0:3, 0:3] = position_cov
        self._cov[3:6, 3:6] = c.init_velocity_std ** 2 * np.eye(3)
        self._cov[6:9, 6:9] = c.init_bias_std ** 2 * np.eye(3)
        self._yaw, self._yaw_var = yaw, yaw_var
        self._accel_ned = (0.0, 0.0, 0.0)
        self._newest, self._count = 0, 1
        self._store(0, t)
        self._U[0] = 0.0
        self._fixes.clear()
        self._fix_times.clear()
        self._initialised = True

    def _uninitialise(self) -> None:
        """Forget the estimate (after an IMU gap): fresh fixes must seed it again."""
        self._initialised = False
        self._seeds = [None, None, None]
        self._fixes.clear()
        self._fix_times.clear()
        self._count, self._newest = 0, -1
        self.reset_counter += 1

    def _store(self, k: int, t: float) -> None:
        self._T[k] = t
        self._X[k] = self._x
        self._P[k] = self._cov
        self._Yaw[k] = self._yaw
        self._YawVar[k] = self._yaw_var

    def _load(self, k: int) -> None:
        self._x[:] = self._X[k]
        self._cov = self._P[k].copy()
        self._yaw = float(self._Yaw[k])
        self._yaw_var = float(self._YawVar[k])

    def _oldest(self) -> int:
        return (self._newest - self._count + 1) % self.config.buffer_capacity

    def _prune(self, t: float) -> None:
        """Forget history older than ``buffer_s`` (keeping one step at or before the horizon)."""
        cap, horizon = self.config.buffer_capacity, t - self.config.buffer_s
        oldest = self._oldest()
        while self._count > 1 and self._T[(oldest + 1) % cap] <= horizon:
            oldest = (oldest + 1) % cap
            self._count -= 1
        self._drop_fixes_until(float(self._T[oldest]))

    def _drop_fixes_until(self, t: float) -> None:
        """Forget logged fixes captured at or before ``t``: the stored states contain them."""
        n = bisect_right(self._fix_times, t)
        if n:
            del self._fixes[:n]
            del self._fix_times[:n]

    def _insert(self, fix: _Fix) -> None:
        i = bisect_right(self._fix_times, fix.t)
        self._fixes.insert(i, fix)
        self._fix_times.insert(i, fix.t)

    def _remove(self, fix: _Fix) -> None:
        i = self._fixes.index(fix)
        del self._fixes[i]
        del self._fix_times[i]


def without_direction(covariance: np.ndarray, direction: tuple[float, float]) -> np.ndarray:
    """A 2-D position covariance (m^2) whose unit ``direction`` (north, east) is unmeasured, for
    :meth:`FusionFilter.correct_position`: its variance along it made so large
    (:data:`UNMEASURED_POSITION_VARIANCE_M2`) that the Kalman update is the one projected on the
    measured direction. A fix that merely repeats the filter's own prediction along it (a
    corridor's axis) would otherwise shrink the filter's variance there at every fix."""
    u = np.asarray(direction, dtype=float)
    v = np.array([-u[1], u[0]])
    return np.outer(v, v) * float(v @ covariance @ v) + UNMEASURED_POSITION_VARIANCE_M2 * np.outer(u, u)


def _valid(t: float, z: np.ndarray, r: np.ndarray) -> bool:
    """Finite time, value and covariance, and the covariance (symmetrised) positive definite."""
    if not (math.isfinite(float(t)) and np.isfinite(z).all() and np.isfinite(r).all()):
        return False
    # The common fixes without LAPACK: heading and height (1x1), planar position (2x2: its leading
    # minors positive, Sylvester's criterion).
    if r.shape == (1, 1):
        return float(r[0, 0]) > 0.0
    if r.shape == (2, 2):
        (a, b), (c, d) = r.tolist()
        return a > 0.0 and a * d - 0.25 * (b + c) ** 2 > 0.0
    try:
        np.linalg.cholesky(0.5 * (r + r.T))
    except np.linalg.LinAlgError:
        return False
    return True


def _unknown_state(t: float, reason: str, reset_counter: int) -> FusedState:
    """A finite placeholder for the not-initialised filter (``healthy`` False)."""
    return FusedState(t, np.zeros(3), np.zeros(3), 0.0, UNKNOWN_VARIANCE * np.eye(3),
                      UNKNOWN_VARIANCE * np.eye(3), UNKNOWN_VARIANCE, False, reason, State.LOST,
                      np.zeros(3), reset_counter)
