"""GNSS pseudo-attitude of a fixed wing: Doppler velocity -> acceleration -> pseudo Euler angles
-> pseudo rates -> body rates (Roberts, Walker, O'Shea 2005, eqs. 1-8, after Kornfeld, Hansman,
Deyst 1998).

Frames and units: velocity and acceleration in MAVLink LOCAL_NED (m/s, m/s^2), gravity
``(0, 0, +9.80665)`` m/s^2 along +D; angles are ZYX Euler (roll, pitch, yaw) in radians, yaw
from north towards east; body rates (p, q, r) rad/s in body FRD; times in seconds of the
caller's monotonic clock, each fix stamped at its capture.

The pseudo-attitude is the attitude of the *velocity vector* (wind-axis-like frame), not of the
airframe: pseudo-yaw is the course, pseudo-pitch the flight-path angle, pseudo-roll the bank of
the lift vector. In coordinated flight (no lateral specific force, see
:func:`coordination_check`) it equals the airframe's roll and differs from its pitch by the
angle of attack and from its yaw by the sideslip and the wind; otherwise the roll is off too.
Exactly: the ZYX rotation of (roll, pitch, yaw) has its x axis along ``v`` and its -z axis along
the specific force's component normal to ``v``.

Re-derived from the seed text (its conversion garbled the equations):

- Pseudo-roll (eqs. 1-5): the specific force ``f = a - g`` projected on the plane normal to ``v``
  is the pseudo lift direction ``L`` (eq. 3 is ``A_n - g_n``, the same thing). With the
  horizontal right axis ``y0 = unit(down x v)`` (eq. 4's ``g x V``, pointing to the right of the
  motion) and ``z0 = unit(v) x y0`` (in the vertical plane through ``v``, downwards), the lift of
  a body rolled right by ``phi`` points along ``sin(phi) y0 - cos(phi) z0``, so
  ``phi = atan2(f . y0, -f . z0)``. Eq. 5's arcsin gives the same angle within +/-90 deg; atan2
  keeps the full range. Roll right (right wing down) is positive, as body FRD.
- Pseudo-pitch (eq. 6): ``atan2(-v_d, hypot(v_n, v_e))``, climb positive.
- Pseudo-yaw (eq. 7, printed as ``arctan2(V_N / V_E)``): the course ``atan2(v_e, v_n)``.
- Body rates (eq. 8): the printed matrix is a direction-cosine matrix applied to
  ``(phi', phi', psi')``, which is not the kinematic relation. Used instead: the standard ZYX
  relation ``p = phi' - psi' sin(theta)``, ``q = theta' cos(phi) + psi' sin(phi) cos(theta)``,
  ``r = -theta' sin(phi) + psi' cos(phi) cos(theta)``.
- Pseudo Euler rates: finite differences of successive pseudo-attitudes (the seed says "the
  derivative wrt time"); the filter carries no jerk, so its own prediction cannot give the roll
  rate. With the autopilot's gyro, :class:`GyroAidedAngle` blends its roll rate into the roll.

Singularities: the course is undefined at zero ground speed and the lift plane at a vertical
velocity (refused below ``min_ground_speed_mps`` and beyond ``max_flight_path_rad``); the roll is
undefined when the normal specific force vanishes (zero-g, refused below
``min_normal_specific_force_mps2``); ZYX Euler rates diverge at pitch +/-90 deg (excluded by the
flight-path limit).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from companion.frames import GRAVITY_MPS2, wrap_pi

_GRAVITY_NED = np.array([0.0, 0.0, GRAVITY_MPS2])


@dataclass(frozen=True)
class KinematicEstimate:
    """Velocity and acceleration (NED) at ``time_s`` with their joint covariance."""

    time_s: float  # s, caller's monotonic clock
    velocity_ned: np.ndarray  # (3,) m/s
    acceleration_ned: np.ndarray  # (3,) m/s^2
    covariance: np.ndarray  # (6, 6) order v_n, v_e, v_d (m/s), a_n, a_e, a_d (m/s^2)


class DopplerAccelerationFilter:
    """Kalman filter of GNSS Doppler velocity fixes (NED m/s), one independent filter per NED
    axis with state (velocity m/s, acceleration m/s^2).

    Model: constant acceleration driven by white jerk of power spectral density
    ``jerk_psd`` (m^2/s^5), so over ``dt`` seconds ``Q = jerk_psd [[dt^3/3, dt^2/2],
    [dt^2/2, dt]]``; irregular intervals are exact. A fix carries its capture time and its
    1-sigma speed accuracy per axis (m/s, one value for all axes or (n, e, d)). The first fix,
    and any fix more than ``max_gap_s`` after the previous one, (re)starts the filter at the fix's
    velocity and zero acceleration of sigma ``initial_acceleration_sigma_mps2``. A fix not later
    than the last one is refused. Receiver latency: query :meth:`estimate` at the current time,
    the state is predicted forward from the last capture time. With ``history_s`` (s) above 0 the
    posteriors of the fixes of that span are kept for :meth:`smoothed`, the estimate of an
    earlier instant from the fixes on both sides of it.

    ``jerk_psd`` trades noise for lag (no Singer decay time: the acceleration is a random
    walk). Measured in tests/test_gnss_pseudo_attitude.py (0.05 m/s fixes at 5 Hz, 25 m/s,
    30 deg bank): at the default 0.5 the steady-turn pseudo-roll RMS error is 0.86 deg and it
    lags a 30 deg/s roll-in by up to 7.5 deg; 0.1 gives 0.52 deg and 10.5 deg. Smoothed with
    0.6 s of fixes after the instant, over a manoeuvring flight, 0.2 is best
    (sitl/pseudo_attitude_eval.py).
    """

    def __init__(self, jerk_psd: float = 0.5, initial_acceleration_sigma_mps2: float = 5.0,
                 max_gap_s: float = 1.5, history_s: float = 0.0) -> None:
        self.jerk_psd = jerk_psd
        self.initial_acceleration_sigma_mps2 = initial_acceleration_sigma_mps2
        self.max_gap_s = max_gap_s
        self.history_s = history_s
        self._time_s: float | None = None
        self._state = np.zeros((3, 2))  # per axis: velocity m/s, acceleration m/s^2
        self._cov = np.zeros((3, 2, 2))  # per axis 2x2 covariance
        # the posteriors of the fixes of the last ``history_s`` (and the one before): (time s, state, cov)
        self._history: deque[tuple[float, np.ndarray, np.ndarray]] = deque()

    @property
    def last_fix_time_s(self) -> float | None:
        """Capture time (s) of the last fix used, None before the first."""
        return self._time_s

    @property
    def first_kept_time_s(self) -> float | None:
        """Capture time (s) of the oldest fix kept for :meth:`smoothed`, None when none is."""
        return self._history[0][0] if self._history else None

    def _transition(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        f = np.array([[1.0, dt], [0.0, 1.0]])
        q = self.jerk_psd * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        return f, q

    def _predicted(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return _predicted_from(self._state, self._cov, *self._transition(dt))

    def update(self, time_s: float, velocity_ned: np.ndarray, speed_sigma_mps: float | np.ndarray) -> bool:
        """Fuse a Doppler velocity fix (NED m/s, captured at ``time_s`` s, 1-sigma per axis m/s).
        Returns False (fix ignored) when it is not later than the last fix."""
        v = np.asarray(velocity_ned, dtype=float)
        var = np.broadcast_to(np.asarray(speed_sigma_mps, dtype=float) ** 2, (3,))
        if self._time_s is not None and time_s <= self._time_s:
            return False
        if self._time_s is None or time_s - self._time_s > self.max_gap_s:
            self._state = np.column_stack([v, np.zeros(3)])
            self._cov = np.zeros((3, 2, 2))
            self._cov[:, 0, 0] = var
            self._cov[:, 1, 1] = self.initial_acceleration_sigma_mps2**2
            self._history.clear()
        else:
            state, cov = self._predicted(time_s - self._time_s)
            innovation = v - state[:, 0]
            s = cov[:, 0, 0] + var
            gain = cov[:, :, 0] / s[:, None]  # (3, 2)
            self._state = state + gain * innovation[:, None]
            self._cov = cov - gain[:, :, None] * cov[:, 0, None, :]
            self._cov = 0.5 * (self._cov + np.transpose(self._cov, (0, 2, 1)))
        self._time_s = time_s
        if self.history_s > 0:
            self._history.append((time_s, self._state.copy(), self._cov.copy()))
            while len(self._history) > 2 and self._history[1][0] < time_s - self.history_s:
                self._history.popleft()
        return True

    def estimate(self, time_s: float) -> KinematicEstimate | None:
        """Velocity and acceleration predicted to ``time_s`` (s, not before the last fix), or
        None before the first fix or more than ``max_gap_s`` after the last one."""
        if self._time_s is None or time_s - self._time_s > self.max_gap_s:
            return None
        if time_s < self._time_s:
            raise ValueError(f"query at {time_s} s is before the last fix at {self._time_s} s")
        return _joint_estimate(time_s, *self._predicted(time_s - self._time_s))

    def smoothed(self, time_s: float) -> KinematicEstimate | None:
        """Velocity and acceleration at ``time_s`` (s) from every fix kept, before and after it:
        the Rauch-Tung-Striebel smoother of the filter's fixes from ``time_s`` to the last one
        (fixed lag: ask once the fixes up to ``time_s`` plus the lag have been fused). From the
        last fix on this is :meth:`estimate`; None when ``time_s`` precedes the fixes kept
        (``history_s`` after construction, and none across a restart)."""
        if self._time_s is None or time_s >= self._time_s:
            return self.estimate(time_s)
        later = [i for i, (t, _, _) in enumerate(self._history) if t > time_s]
        if not later or later[0] == 0:
            return None
        t_node, state, cov = self._history[later[0] - 1]  # the last fix at or before time_s
        state, cov = _predicted_from(state, cov, *self._transition(time_s - t_node))
        nodes = [(time_s, state, cov)] + [self._history[i] for i in later]
        smooth_state, smooth_cov = nodes[-1][1], nodes[-1][2]
        for (t0, state0, cov0), (t1, _, _) in zip(nodes[-2::-1], nodes[:0:-1]):
            f, q = self._transition(t1 - t0)
            prior_state, prior_cov = _predicted_from(state0, cov0, f, q)
            gain = cov0 @ f.T @ np.linalg.inv(prior_cov)  # (3, 2, 2): per axis C = P F^T P-^-1
            smooth_state = state0 + np.einsum("aij,aj->ai", gain, smooth_state - prior_state)
            smooth_cov = cov0 + gain @ (smooth_cov - prior_cov) @ np.transpose(gain, (0, 2, 1))
            smooth_cov = 0.5 * (smooth_cov + np.transpose(smooth_cov, (0, 2, 1)))
        return _joint_estimate(time_s, smooth_state, smooth_cov)


def _predicted_from(state: np.ndarray, cov: np.ndarray, f: np.ndarray,
                    q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis state (3, 2) and covariance (3, 2, 2) moved on by the transition ``f`` with
    process noise ``q`` (2, 2)."""
    return state @ f.T, f @ cov @ f.T + q


def _joint_estimate(time_s: float, state: np.ndarray, cov: np.ndarray) -> KinematicEstimate:
    """The :class:`KinematicEstimate` of per-axis states (3, 2) and covariances (3, 2, 2)."""
    joint = np.zeros((6, 6))
    idx = np.arange(3)
    joint[idx, idx] = cov[:, 0, 0]
    joint[idx, idx + 3] = cov[:, 0, 1]
    joint[idx + 3, idx] = cov[:, 1, 0]
    joint[idx + 3, idx + 3] = cov[:, 1, 1]
    return KinematicEstimate(time_s, state[:, 0].copy(), state[:, 1].copy(), joint)


@dataclass(frozen=True)
class PseudoAttitudeLimits:
    """Where the pseudo-attitude is defined (see the module docstring's singularities)."""

    min_ground_speed_mps: float = 5.0  # below: course undefined, m/s
    max_flight_path_rad: float = math.radians(60.0)  # beyond: velocity too near vertical, rad
    min_normal_specific_force_mps2: float = 0.3 * GRAVITY_MPS2  # below: no lift direction, m/s^2


@dataclass(frozen=True)
class PseudoAttitude:
    """Pseudo Euler angles (ZYX, rad) of the velocity vector at ``time_s`` (s): roll = bank of
    the lift (right positive), pitch = flight-path angle (climb positive), yaw = course (from
    north towards east); ``covariance`` (3x3, rad^2, order roll, pitch, yaw) first-order from
    the velocity/acceleration covariance; ``along_over_normal`` the specific force's component
    along the velocity over its part normal to it (dimensionless: the along-track acceleration
    plus g times the sine of the flight-path angle, over the lift's share)."""

    time_s: float
    roll: float
    pitch: float
    yaw: float
    covariance: np.ndarray
    along_over_normal: float = 0.0


def pseudo_attitude_refusal(velocity_ned: np.ndarray, acceleration_ned: np.ndarray,
                            limits: PseudoAttitudeLimits = PseudoAttitudeLimits()) -> str | None:
    """Why the pseudo-attitude of velocity (NED m/s) and acceleration (NED m/s^2) is undefined,
    or None when its assumptions (other than coordinated flight) hold."""
    v = np.asarray(velocity_ned, dtype=float)
    f = np.asarray(acceleration_ned, dtype=float) - _GRAVITY_NED
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(f))):
        return "non-finite velocity or acceleration"
    ground_speed = math.hypot(v[0], v[1])
    if ground_speed < limits.min_ground_speed_mps:
        return f"ground speed {ground_speed:.2f} m/s below {limits.min_ground_speed_mps} m/s"
    if abs(math.atan2(-v[2], ground_speed)) > limits.max_flight_path_rad:
        return "velocity too near vertical"
    normal = f - (f @ v) / (v @ v) * v
    if np.linalg.norm(normal) < limits.min_normal_specific_force_mps2:
        return "normal specific force too small for a lift direction"
    return None


def _angles(x: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) rad of the 6-vector (velocity NED m/s, acceleration NED m/s^2)."""
    v, f = x[:3], x[3:] - _GRAVITY_NED
    yaw = math.atan2(v[1], v[0])
    pitch = math.atan2(-v[2], math.hypot(v[0], v[1]))
    x0 = v / np.linalg.norm(v)
    sy, cy = math.sin(yaw), math.cos(yaw)
    y0 = np.array([-sy, cy, 0.0])  # unit(down x v): horizontal, right
    z0 = np.array([-x0[2] * cy, -x0[2] * sy, x0[0] * cy + x0[1] * sy])  # x0 x y0 (np.cross is slow)
    roll = math.atan2(float(f @ y0), float(-(f @ z0)))
    return np.array([roll, pitch, yaw])


def pseudo_attitude(estimate: KinematicEstimate,
                    limits: PseudoAttitudeLimits = PseudoAttitudeLimits()) -> PseudoAttitude | None:
    """Pseudo-roll, -pitch, -yaw (module docstring) of a filter estimate, with their covariance
    propagated through a central-difference Jacobian; None where
    :func:`pseudo_attitude_refusal` refuses."""
    if pseudo_attitude_refusal(estimate.velocity_ned, estimate.acceleration_ned, limits) is not None:
        return None
    x = np.concatenate([estimate.velocity_ned, estimate.acceleration_ned]).astype(float)
    angles = _angles(x)
    jacobian = np.zeros((3, 6))
    for i in range(6):
        step = 1e-6 * max(1.0, abs(x[i]))
        dx = np.zeros(6)
        dx[i] = step
        diff = _angles(x + dx) - _angles(x - dx)
        jacobian[:, i] = [wrap_pi(float(d)) for d in diff]
        jacobian[:, i] /= 2 * step
    covariance = jacobian @ estimate.covariance @ jacobian.T
    v, f = x[:3], x[3:] - _GRAVITY_NED
    along = float(f @ v) / float(np.linalg.norm(v))
    normal = math.sqrt(max(float(f @ f) - along * along, 0.0))  # > 0: the refusal checked it
    return PseudoAttitude(estimate.time_s, float(angles[0]), float(angles[1]), float(angles[2]),
                          0.5 * (covariance + covariance.T), along / normal)


def pseudo_euler_rates(earlier: PseudoAttitude, later: PseudoAttitude) -> np.ndarray:
    """(roll', pitch', yaw') rad/s between two pseudo-attitudes by finite difference (yaw
    wrapped), valid at their mid-time."""
    dt = later.time_s - earlier.time_s
    if dt <= 0:
        raise ValueError("pseudo-attitudes not in time order")
    return np.array([wrap_pi(later.roll - earlier.roll), later.pitch - earlier.pitch,
                     wrap_pi(later.yaw - earlier.yaw)]) / dt


def body_rates_from_euler_rates(roll: float, pitch: float, euler_rates: np.ndarray) -> np.ndarray:
    """Body FRD rates (p, q, r) rad/s from ZYX Euler angles (rad) and their rates (roll', pitch',
    yaw') rad/s: the standard kinematic relation (module docstring; the inverse of
    :func:`companion.frames.euler_yaw_rate` for yaw)."""
    droll, dpitch, dyaw = (float(r) for r in euler_rates)
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    return np.array([droll - dyaw * sp, dpitch * cr + dyaw * sr * cp, -dpitch * sr + dyaw * cr * cp])


def coordination_check(specific_force_body: np.ndarray,
                       max_lateral_angle_rad: float = math.radians(3.0)) -> tuple[bool, float]:
    """Whether flight is coordinated, from a measured specific force (body FRD m/s^2, e.g. an
    IMU's accelerometer). Returns (coordinated, lateral angle rad): the sideslip indicator
    ``atan2(f_y, -f_z)``, positive when the specific force points right of the body's -z, must
    stay within ``max_lateral_angle_rad``. The pseudo-attitude puts the whole normal specific
    force in its own x-z plane, so a lateral angle means the airframe is not aligned with it
    (slip or skid) and the pseudo-roll is off from the airframe's roll by about that angle."""
    f = np.asarray(specific_force_body, dtype=float)
    lateral = math.atan2(float(f[1]), float(-f[2]))
    return abs(lateral) <= max_lateral_angle_rad, lateral


def euler_rates_from_body_rates(roll: float, pitch: float, gyro_body: np.ndarray) -> np.ndarray:
    """ZYX Euler rates (roll', pitch', yaw') rad/s of body FRD rates (p, q, r) rad/s at ``roll``,
    ``pitch`` (rad), the inverse of :func:`body_rates_from_euler_rates`: roll' = p + (q sin(roll) +
    r cos(roll)) tan(pitch), pitch' = q cos(roll) - r sin(roll), yaw' = (q sin(roll) + r
    cos(roll)) / cos(pitch)."""
    p, q, r = (float(w) for w in gyro_body)
    sr, cr = math.sin(roll), math.cos(roll)
    turn = q * sr + r * cr
    return np.array([p + turn * math.tan(pitch), q * cr - r * sr, turn / math.cos(pitch)])


class GyroAidedAngle:
    """One Euler angle measured without the gyro (the pseudo-roll; the flow's pitch or yaw)
    blended with the gyro's Euler rate of that angle: a second-order complementary filter whose
    angle follows the gyro's increments over short spans and the measurement over spans beyond
    ``tau_s`` (s), with the gyro's rate bias estimated (integral term), so a constant gyro bias
    leaves no steady error. Critically damped: ``angle' = rate - bias + (2 / tau) e``,
    ``bias' = -e / tau^2``, ``e = measured - angle``; its response to the measurement is a
    second-order low pass of natural period ``2 pi tau``. Without ``learn_bias`` the bias stays 0:
    a first-order blend, ``angle' = rate + (2 / tau) e``, for an angle whose gyro rate has no bias
    of its own to learn (the gyro's is taken off before) and whose measurement's slow errors must
    not be learnt as one. After a (re)start the angle's gain is
    the running mean's (1/n at the n-th measurement) until the filter's is larger, so it does
    not hold the first measurement's error for a time constant.

    The pseudo-roll's errors are the Doppler filter's, correlated over about a second (its
    smoothing span) and worst in bank changes; the flow's pitch and yaw errors are its focus of
    expansion's, from pair to pair; the gyro is exact there, its errors a bias and a scale error,
    slow. Angles rad (wrapped to [-pi, pi]), times s, on the caller's clock, in time order."""

    def __init__(self, tau_s: float, learn_bias: bool = True) -> None:
        self.tau_s = tau_s
        self.learn_bias = learn_bias
        self._time_s: float | None = None
        self._start_s: float | None = None  # time of the first update since construction or reset
        self._measured_s: float | None = None  # time of the last update with a measurement
        self._measurements = 0  # since the (re)start
        self._angle = 0.0  # rad
        self._bias = 0.0  # gyro Euler rate bias of the angle, rad/s

    @property
    def last_time_s(self) -> float | None:
        """Time (s) of the last update, None before the first or after :meth:`reset`."""
        return self._time_s

    @property
    def angle(self) -> float | None:
        """The angle (rad) at the last update, None before the first or after :meth:`reset`."""
        return None if self._time_s is None else self._angle

    @property
    def last_measured_s(self) -> float | None:
        """Time (s) of the last update with a measurement, None before the first or after :meth:`reset`."""
        return self._measured_s

    @property
    def settled(self) -> bool:
        """Whether the blend has run ``tau_s`` since it (re)started: before that its angle is
        mostly the first measurement it took (in a roll-in the smoother's first, one-sided
        pseudo-rolls were 12-16 deg off in SITL) and its bias is unlearnt."""
        return self._start_s is not None and self._time_s is not None and self._time_s - self._start_s >= self.tau_s

    def reset(self) -> None:
        """Forget the angle and the bias: the next update starts at its measurement."""
        self._time_s = None
        self._start_s = None
        self._measured_s = None
        self._bias = 0.0

    def update(self, time_s: float, measured: float | None, increment: float) -> float:
        """The blended angle (rad) at ``time_s`` from the measurement there (rad; None: none, or
        not the airframe's, e.g. the pseudo-roll in a slip or at low load, so the gyro's increment
        alone carries the angle and the bias is kept) and the gyro's Euler increment of the angle
        (rad) since the previous update (ignored on the first, which needs a measurement). At the
        time of the previous update: that update's angle, unchanged."""
        if self._time_s is None:
            if measured is None:
                raise ValueError("the first update needs a measurement")
            self._time_s = self._start_s = self._measured_s = time_s
            self._angle, self._measurements = measured, 1
            return measured
        dt = time_s - self._time_s
        if dt < 0:
            raise ValueError("updates not in time order")
        if dt == 0:
            return self._angle
        predicted = self._angle + increment - self._bias * dt
        self._time_s = time_s
        if measured is None:
            self._angle = wrap_pi(predicted)
            return self._angle
        self._measured_s = time_s
        self._measurements += 1
        error = wrap_pi(measured - predicted)
        gain = max(min(1.0, 2.0 * dt / self.tau_s), 1.0 / self._measurements)  # a running mean at the start
        self._angle = wrap_pi(predicted + gain * error)
        if self.learn_bias:
            self._bias -= dt / self.tau_s**2 * error
        return self._angle
