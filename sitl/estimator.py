"""The simulated autopilot's own navigation estimate (a small stand-in for ArduPilot's EKF3).

Position and velocity in the EKF's local NED frame (m, m/s, relative to the EKF origin once one
is set), attitude as ZYX Euler (rad) of body FRD -> NED.

* Attitude ("AHRS"): roll and pitch are the truth plus a small bias and slow wander; yaw is the
  estimator's own heading, carried by the true yaw increments plus a small gyro drift and
  pulled towards the heading source: external-nav yaw while it is in use and fresh
  (EK3_SRC1_YAW=6), otherwise the compass. A compass-only heading (ArduPilot's DCM backend)
  is kept beside it for the pre-arm consistency check.
* Translation: a linear Kalman filter per NED axis with states (position, velocity,
  accelerometer bias), propagated at the IMU rate by the accelerometer rotated with the AHRS
  attitude plus gravity. Covariances of the three axes are independent, so each axis is a
  3-state filter on plain floats.
* Corrections: external-nav position and velocity (VISION_POSITION_ESTIMATE /
  VISION_SPEED_ESTIMATE), GPS position and velocity, baro height. Measurement times are
  compensated with ~0.5 s of state history: the innovation is taken against the state at the
  capture time and the correction is applied to the current state (corrections made after a
  capture time are credited to the history, so nothing is counted twice).
* Innovation gate (5 sigma by default, like EK3_POS_I_GATE 500): gated samples are counted,
  and if position samples keep failing for more than 1 s the position is reset to the
  measurement.

Rules that make the companion's mistakes visible: no position estimate (``pos_valid``) without
an origin; external-nav data is fused only after the origin is set and with
position_source "extnav"; the external-nav source is lost 0.3 s after its last sample;
GPS is fused only with position_source "gps", a 3D fix and an origin.
"""

from __future__ import annotations

import math

from companion.frames import GRAVITY_MPS2, ned_from_geodetic, wrap_pi
from sitl.dynamics import GaussianStream
from sitl.sensors import GpsSample

# MAV_SEVERITY
SEVERITY_CRITICAL = 2
SEVERITY_WARNING = 4
SEVERITY_INFO = 6

# MAV_ESTIMATOR_STATUS_FLAGS
EKF_ATTITUDE = 1
EKF_VELOCITY_HORIZ = 2
EKF_VELOCITY_VERT = 4
EKF_POS_HORIZ_REL = 8
EKF_POS_HORIZ_ABS = 16
EKF_POS_VERT_ABS = 32
EKF_CONST_POS_MODE = 128
EKF_PRED_POS_HORIZ_REL = 256

POSITION_SOURCES = ("extnav", "gps")


class StatusQueue:
    """STATUSTEXT messages (MAV_SEVERITY, text) waiting to be sent, oldest first."""

    def __init__(self) -> None:
        self._items: list[tuple[int, str]] = []

    def push(self, severity: int, text: str) -> None:
        """Queue one message."""
        self._items.append((severity, text))

    def drain(self) -> list[tuple[int, str]]:
        """All queued messages, emptying the queue."""
        items, self._items = self._items, []
        return items


class Ahrs:
    """Attitude as the autopilot believes it (see the module docstring). Angles in rad.

    Float attributes: ``roll pitch yaw`` (the estimate), ``dcm_yaw`` (compass-only heading) and
    the body->NED rotation matrix of the estimate, ``r00 .. r22``. ``tilt_fault_rad`` (roll, pitch)
    is added to the estimate while set: a fault (a failing gyro, a board that moved in its mount)
    that the autopilot does not see, so it flies on the wrong tilt.
    """

    def __init__(self, noise: GaussianStream, *, start_yaw_rad: float,
                 tilt_bias_std_rad: float = math.radians(0.1), tilt_wander_std_rad: float = math.radians(0.05),
                 wander_tau_s: float = 5.0, yaw_drift_std_rad_s: float = math.radians(0.01)) -> None:
        self._noise = noise
        self._bias = (tilt_bias_std_rad * noise.draw(), tilt_bias_std_rad * noise.draw())
        self._wander = [0.0, 0.0]
        self._wander_std = tilt_wander_std_rad
        self._wander_tau = wander_tau_s
        self._yaw_drift = yaw_drift_std_rad_s * noise.draw()
        self._truth_yaw = start_yaw_rad
        self.roll = self.pitch = 0.0
        self.yaw = self.dcm_yaw = wrap_pi(start_yaw_rad)
        self.aligned = False  # heading snapped to the first compass reading
        self.tilt_fault_rad = (0.0, 0.0)
        self._update_rotation()

    def propagate(self, dt: float, truth_roll: float, truth_pitch: float, truth_yaw: float) -> None:
        """Follow the true attitude over ``dt`` seconds, adding this AHRS's errors."""
        decay = dt / self._wander_tau
        kick = self._wander_std * math.sqrt(2.0 * decay)
        w, draw = self._wander, self._noise.draw
        w[0] += -w[0] * decay + kick * draw()
        w[1] += -w[1] * decay + kick * draw()
        self.roll = truth_roll + self._bias[0] + w[0] + self.tilt_fault_rad[0]
        self.pitch = truth_pitch + self._bias[1] + w[1] + self.tilt_fault_rad[1]
        turn = wrap_pi(truth_yaw - self._truth_yaw) + self._yaw_drift * dt
        self._truth_yaw = truth_yaw
        self.yaw = wrap_pi(self.yaw + turn)
        self.dcm_yaw = wrap_pi(self.dcm_yaw + turn)
        self._update_rotation()

    def correct_yaw(self, innovation_rad: float, gain: float) -> float:
        """Move the heading by ``gain * innovation``; returns the applied change, rad."""
        delta = gain * innovation_rad
        self.yaw = wrap_pi(self.yaw + delta)
        return delta

    def correct_dcm(self, compass_yaw_rad: float, gain: float) -> None:
        """Pull the compass-only heading towards a compass reading."""
        self.dcm_yaw = wrap_pi(self.dcm_yaw + gain * wrap_pi(compass_yaw_rad - self.dcm_yaw))

    def _update_rotation(self) -> None:
        cr, sr = math.cos(self.roll), math.sin(self.roll)
        cp, sp = math.cos(self.pitch), math.sin(self.pitch)
        cy, sy = math.cos(self.yaw), math.sin(self.yaw)
        self.r00, self.r01, self.r02 = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
        self.r10, self.r11, self.r12 = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
        self.r20, self.r21, self.r22 = -sp, cp * sr, cp * cr


class AxisFilter:
    """Kalman filter of one NED axis: position p (m), velocity v (m/s), accel bias b (m/s^2).

    ``P`` is symmetric; its six distinct entries are floats ``p00 p01 p02 p11 p12 p22``.
    """

    __slots__ = ("p", "v", "b", "p00", "p01", "p02", "p11", "p12", "p22")

    def __init__(self, pos_var: float, vel_var: float, bias_var: float) -> None:
        self.p = self.v = self.b = 0.0
        self.p00, self.p11, self.p22 = pos_var, vel_var, bias_var
        self.p01 = self.p02 = self.p12 = 0.0

    def predict(self, accel: float, dt: float, q_vel: float, q_bias: float) -> None:
        """Propagate by ``dt`` s with measured acceleration ``accel`` (m/s^2, gravity included)."""
        a = accel - self.b
        self.p += (self.v + 0.5 * a * dt) * dt
        self.v += a * dt
        p00, p01, p02, p11, p12, p22 = self.p00, self.p01, self.p02, self.p11, self.p12, self.p22
        self.p00 = p00 + dt * (2.0 * p01 + dt * p11)
        self.p01 = p01 + dt * (p11 - p02 - dt * p12)
        self.p02 = p02 + dt * p12
        self.p11 = p11 + dt * (dt * p22 - 2.0 * p12) + q_vel
        self.p12 = p12 - dt * p22
        self.p22 = p22 + q_bias

    def innovation_variance(self, index: int, r: float) -> float:
        """H P H^T + R for a direct measurement of state ``index`` (0 position, 1 velocity)."""
        return (self.p00 if index == 0 else self.p11) + r

    def update(self, index: int, innovation: float, s: float) -> tuple[float, float]:
        """Kalman update with a measured position (index 0) or velocity (index 1).

        ``s`` is the innovation variance; returns the (position, velocity) corrections applied.
        """
        if index == 0:
            c0, c1, c2 = self.p00, self.p01, self.p02
        else:
            c0, c1, c2 = self.p01, self.p11, self.p12
        k0, k1, k2 = c0 / s, c1 / s, c2 / s
        dp, dv = k0 * innovation, k1 * innovation
        self.p += dp
        self.v += dv
        self.b += k2 * innovation
        self.p00 -= k0 * c0
        self.p01 -= k0 * c1
        self.p02 -= k0 * c2
        self.p11 -= k1 * c1
        self.p12 -= k1 * c2
        self.p22 -= k2 * c2
        return dp, dv

    def reset_velocity(self, velocity: float, variance: float) -> float:
        """Jump the velocity to ``velocity`` (m/s) with ``variance`` ((m/s)^2); returns the jump."""
        jump = velocity - self.v
        self.v = velocity
        self.p01, self.p11, self.p12 = 0.0, variance, 0.0
        return jump

    def reset_position(self, position: float, variance: float) -> float:
        """Jump the position to ``position`` (m) with ``variance`` (m^2); returns the jump."""
        jump = position - self.p
        self.p = position
        self.p00, self.p01, self.p02 = variance, 0.0, 0.0
        return jump


class Estimator:
    """Position/velocity/attitude estimate of the simulated autopilot (see the module docstring).

    Read the estimate from ``axes`` (north, east, down :class:`AxisFilter`), ``ahrs`` and the
    properties; feed it with :meth:`predict` at the IMU rate and the ``fuse_*`` methods.
    """

    HISTORY_S = 0.5
    EXTNAV_TIMEOUT_S = 0.3
    GPS_TIMEOUT_S = 1.0
    REJECT_RESET_S = 1.0
    REJECT_RESET_VEL_VAR = 1.0  # velocity is zeroed with this variance, (m/s)^2, when position resets
    CONST_POS_PERIOD_S = 0.1
    CONST_POS_NOISE_M = 0.5
    EXTNAV_YAW_GAIN = 0.2  # per fused sample
    COMPASS_YAW_GAIN = 0.02  # per compass reading (50 Hz -> ~1 s)
    DCM_YAW_GAIN = 0.05

    def __init__(
        self,
        *,
        status: StatusQueue,
        noise: GaussianStream,
        position_source: str = "extnav",
        rate_hz: float = 400.0,
        start_yaw_rad: float = 0.0,
        viso_pos_noise_m: float = 0.2,
        viso_vel_noise_mps: float = 0.1,
        vision_delay_s: float = 0.01,
        gate_sigma: float = 5.0,
        accel_noise_mps2: float = 0.35,
        accel_bias_noise_mps3: float = 0.01,
        accel_bias_init_mps2: float = 0.2,
        baro_noise_m: float = 0.3,
        gps_pos_noise_m: float = 0.5,
        gps_vel_noise_mps: float = 0.3,
    ) -> None:
        if position_source not in POSITION_SOURCES:
            raise ValueError(f"position_source must be one of {POSITION_SOURCES}, not {position_source!r}")
        self.status = status
        self.position_source = position_source
        self.rate_hz = rate_hz
        self.viso_pos_noise_m = viso_pos_noise_m
        self.viso_vel_noise_mps = viso_vel_noise_mps
        self.vision_delay_s = vision_delay_s
        self.gate_sigma = gate_sigma
        self._q_vel_psd = accel_noise_mps2**2
        self._q_bias_psd = accel_bias_noise_mps3**2
        self._baro_var = baro_noise_m**2
        self._gps_pos_var = gps_pos_noise_m**2
        self._gps_vel_var = gps_vel_noise_mps**2
        self.ahrs = Ahrs(noise, start_yaw_rad=start_yaw_rad)
        self.axes = tuple(AxisFilter(1.0, 0.1, accel_bias_init_mps2**2) for _ in range(3))
        self.origin: tuple[float, float, float] | None = None
        self.t = 0.0
        self.ext_nav_in_use = False
        self.gps_in_use = False
        self.rejected_ext_nav = 0
        self.nonfinite_rejected = 0
        self.ext_nav_yaw: float | None = None  # latest received external-nav yaw, rad
        self.ext_nav_rx_t = -math.inf  # simulation time of the latest external-nav position sample
        self._gps_rx_t = -math.inf
        self._hpos_accept_t = self._vpos_accept_t = -math.inf
        self._reset_counter: int | None = None
        self._baro_datum: float | None = None  # z = datum - baro altitude
        self._const_pos = (0.0, 0.0)
        self._next_const_pos_t = 0.0
        # ring buffer of (p_n, p_e, p_d, v_n, v_e, v_d, yaw) minus the corrections made so far
        self._corr = [0.0] * 7
        self._history_len = int(round(self.HISTORY_S * rate_hz)) + 1
        self._history: list[tuple[float, ...]] = [(0.0,) * 7] * self._history_len
        self._step = 0

    # ------------------------------------------------------------------ state
    @property
    def pos_valid(self) -> bool:
        """True when the horizontal position is aided and referenced to an origin."""
        return self.origin is not None and (self.ext_nav_in_use or self.gps_in_use)

    @property
    def horizontal_aiding(self) -> bool:
        """True when a horizontal position source is being fused."""
        return self.ext_nav_in_use or self.gps_in_use

    @property
    def flags(self) -> int:
        """EKF_STATUS_REPORT flags (MAV_ESTIMATOR_STATUS_FLAGS bits)."""
        flags = EKF_ATTITUDE | EKF_VELOCITY_VERT | EKF_POS_VERT_ABS
        if self.pos_valid:
            flags |= EKF_VELOCITY_HORIZ | EKF_POS_HORIZ_REL | EKF_POS_HORIZ_ABS | EKF_PRED_POS_HORIZ_REL
        else:
            flags |= EKF_CONST_POS_MODE
        return flags

    @property
    def pos_variance_m2(self) -> float:
        """Horizontal position variance (north + east), m^2."""
        return self.axes[0].p00 + self.axes[1].p00

    @property
    def vel_variance(self) -> float:
        """Velocity variance summed over the three axes, (m/s)^2."""
        return self.axes[0].p11 + self.axes[1].p11 + self.axes[2].p11

    @property
    def height_variance_m2(self) -> float:
        """Vertical position variance, m^2."""
        return self.axes[2].p00

    def set_origin(self, lat: float, lon: float, alt: float) -> bool:
        """Set the EKF origin (deg, deg, m AMSL) once; False if already set or invalid."""
        if not all(math.isfinite(v) for v in (lat, lon, alt)):
            self.nonfinite_rejected += 1
            return False
        if self.origin is not None or abs(lat) > 90.0 or abs(lon) > 180.0:
            return False
        self.origin = (float(lat), float(lon), float(alt))
        self.status.push(SEVERITY_INFO, "EKF3 IMU0 origin set")
        return True

    # ------------------------------------------------------------------ prediction
    def predict(self, dt: float, accel_body: tuple[float, float, float],
                truth_euler: tuple[float, float, float]) -> None:
        """One IMU step: attitude, then position/velocity from the specific force (m/s^2, body)."""
        self._step += 1
        self.t = self._step / self.rate_hz
        ahrs = self.ahrs
        ahrs.propagate(dt, *truth_euler)
        fx, fy, fz = accel_body
        an = ahrs.r00 * fx + ahrs.r01 * fy + ahrs.r02 * fz
        ae = ahrs.r10 * fx + ahrs.r11 * fy + ahrs.r12 * fz
        ad = ahrs.r20 * fx + ahrs.r21 * fy + ahrs.r22 * fz + GRAVITY_MPS2
        q_vel, q_bias = self._q_vel_psd * dt, self._q_bias_psd * dt
        n, e, d = self.axes
        n.predict(an, dt, q_vel, q_bias)
        e.predict(ae, dt, q_vel, q_bias)
        d.predict(ad, dt, q_vel, q_bias)
        c = self._corr
        self._history[self._step % self._history_len] = (
            n.p - c[0], e.p - c[1], d.p - c[2], n.v - c[3], e.v - c[4], d.v - c[5], ahrs.yaw - c[6])
        self._check_timeouts()
        if not self.horizontal_aiding and self.t >= self._next_const_pos_t:
            self._fuse_constant_position()

    def _history_at(self, t_meas: float) -> tuple[float, ...]:
        """Estimated (p_n, p_e, p_d, v_n, v_e, v_d, yaw) at ``t_meas``, with later corrections applied."""
        lag = int(round((self.t - t_meas) * self.rate_hz))
        lag = max(0, min(lag, self._history_len - 1, self._step))
        h = self._history[(self._step - lag) % self._history_len]
        c = self._corr
        return (h[0] + c[0], h[1] + c[1], h[2] + c[2], h[3] + c[3], h[4] + c[4], h[5] + c[5], h[6] + c[6])

    def _credit(self, index: int, delta: float) -> None:
        """Record a correction of ``delta`` to history component ``index``."""
        self._corr[index] += delta

    # ------------------------------------------------------------------ health
    def _check_timeouts(self) -> None:
        if self.ext_nav_in_use and self.t - self.ext_nav_rx_t > self.EXTNAV_TIMEOUT_S:
            self.ext_nav_in_use = False
            self._enter_constant_position()
            self.status.push(SEVERITY_INFO, "EKF3 IMU0 stopped using external nav data")
        if self.gps_in_use and self.t - self._gps_rx_t > self.GPS_TIMEOUT_S:
            self.gps_in_use = False
            self._enter_constant_position()
            self.status.push(SEVERITY_INFO, "EKF3 IMU0 stopped aiding")

    def _enter_constant_position(self) -> None:
        """Hold the last horizontal position as a weak pseudo-measurement (CONST_POS_MODE)."""
        self._const_pos = (self.axes[0].p, self.axes[1].p)
        self._next_const_pos_t = self.t

    def _fuse_constant_position(self) -> None:
        self._next_const_pos_t = self.t + self.CONST_POS_PERIOD_S
        r = self.CONST_POS_NOISE_M**2
        for i in (0, 1):
            axis = self.axes[i]
            dp, dv = axis.update(0, self._const_pos[i] - axis.p, axis.innovation_variance(0, r))
            self._credit(i, dp)
            self._credit(3 + i, dv)

    # ------------------------------------------------------------------ external nav
    def fuse_vision_position(self, t_capture: float, pos_ned: tuple[float, float, float], yaw: float,
                             pos_error_m: float | None, reset_counter: int) -> None:
        """An external-nav pose: NED position (m), yaw (rad), 1-sigma position error (m) or None.

        ``t_capture`` is the simulation time the pose was valid; VISO_DELAY (``vision_delay_s``)
        is subtracted from it, like ArduPilot.
        """
        values = (t_capture, *pos_ned, yaw) + (() if pos_error_m is None else (pos_error_m,))
        if not all(math.isfinite(v) for v in values):
            self.nonfinite_rejected += 1
            return
        if self.position_source != "extnav":
            return
        self.ext_nav_yaw = wrap_pi(yaw)
        self.ext_nav_rx_t = self.t
        if self.origin is None:
            return
        r = max(pos_error_m or 0.0, self.viso_pos_noise_m) ** 2
        t_meas = t_capture - self.vision_delay_s
        reset = self._reset_counter is not None and reset_counter != self._reset_counter
        self._reset_counter = reset_counter
        if not self.ext_nav_in_use:
            self.ext_nav_in_use = True
            self.status.push(SEVERITY_INFO, "EKF3 IMU0 is using external nav data")
            self._reset_to_vision(t_meas, pos_ned, yaw, r, horizontal=True, vertical=True)
        elif reset:
            self._reset_to_vision(t_meas, pos_ned, yaw, r, horizontal=True, vertical=True)
        else:
            self._filter_vision(t_meas, pos_ned, yaw, r)

    def _filter_vision(self, t_meas: float, pos: tuple[float, float, float], yaw: float, r: float) -> None:
        """Gated Kalman update with an external-nav position, then the heading correction."""
        past = self._history_at(t_meas)
        n, e, d = self.axes
        yn, ye, yd = pos[0] - past[0], pos[1] - past[1], pos[2] - past[2]
        sn, se, sd = n.innovation_variance(0, r), e.innovation_variance(0, r), d.innovation_variance(0, r)
        gate2 = self.gate_sigma**2
        h_ok = yn * yn + ye * ye <= gate2 * (sn + se)
        v_ok = yd * yd <= gate2 * sd
        if h_ok:
            self._hpos_accept_t = self.t
            self._apply(0, 0, yn, sn)
            self._apply(1, 0, ye, se)
        if v_ok:
            self._vpos_accept_t = self.t
            self._apply(2, 0, yd, sd)
        if not (h_ok and v_ok):
            self.rejected_ext_nav += 1
            self._reset_if_stuck(t_meas, pos, yaw, r, not h_ok, not v_ok)
        self._credit(6, self.ahrs.correct_yaw(wrap_pi(yaw - past[6]), self.EXTNAV_YAW_GAIN))

    def _apply(self, axis_index: int, state_index: int, innovation: float, s: float) -> None:
        dp, dv = self.axes[axis_index].update(state_index, innovation, s)
        self._credit(axis_index, dp)
        self._credit(3 + axis_index, dv)

    def _reset_if_stuck(self, t_meas: float, pos: tuple[float, float, float], yaw: float, r: float,
                        horizontal: bool, vertical: bool) -> None:
        """Reset to the measurement when position samples were gated out for > REJECT_RESET_S."""
        h = horizontal and self.t - self._hpos_accept_t > self.REJECT_RESET_S
        v = vertical and self.t - self._vpos_accept_t > self.REJECT_RESET_S
        if h or v:
            self.status.push(SEVERITY_WARNING, "EKF3 IMU0 ext nav position reset: innovations rejected")
            self._reset_to_vision(t_meas, pos, yaw, r, horizontal=h, vertical=v, align_yaw=False)
            for i in ((0, 1) if h else ()) + ((2,) if v else ()):
                self._credit(3 + i, self.axes[i].reset_velocity(0.0, self.REJECT_RESET_VEL_VAR))

    def _reset_to_vision(self, t_meas: float, pos: tuple[float, float, float], yaw: float, r: float, *,
                         horizontal: bool, vertical: bool, align_yaw: bool = True) -> None:
        """Jump position (and heading) to an external-nav sample, keeping motion since capture."""
        past = self._history_at(t_meas)
        axes = (0, 1, 2) if horizontal and vertical else ((0, 1) if horizontal else (2,))
        for i in axes:
            axis = self.axes[i]
            self._credit(i, axis.reset_position(axis.p + pos[i] - past[i], r))
        if horizontal:
            self._hpos_accept_t = self.t
        if vertical:
            self._vpos_accept_t = self.t
            self._baro_datum = None  # re-anchor baro to the new height
        if align_yaw:
            self._credit(6, self.ahrs.correct_yaw(wrap_pi(yaw - past[6]), 1.0))

    def fuse_vision_velocity(self, t_capture: float, vel_ned: tuple[float, float, float],
                             vel_error_mps: float | None) -> None:
        """An external-nav NED velocity (m/s) with 1-sigma error (m/s) or None; fused while in use."""
        values = (t_capture, *vel_ned) + (() if vel_error_mps is None else (vel_error_mps,))
        if not all(math.isfinite(v) for v in values):
            self.nonfinite_rejected += 1
            return
        if not self.ext_nav_in_use:
            return
        r = max(vel_error_mps or 0.0, self.viso_vel_noise_mps) ** 2
        past = self._history_at(t_capture - self.vision_delay_s)
        innovations = [vel_ned[i] - past[3 + i] for i in range(3)]
        variances = [self.axes[i].innovation_variance(1, r) for i in range(3)]
        gate2 = self.gate_sigma**2
        if sum(y * y for y in innovations) > gate2 * sum(variances):
            self.rejected_ext_nav += 1
            return
        for i in range(3):
            self._apply(i, 1, innovations[i], variances[i])

    # ------------------------------------------------------------------ other sensors
    def fuse_baro(self, alt_m: float) -> None:
        """Barometric altitude (m AMSL). Fused for height unless external nav supplies it."""
        d = self.axes[2]
        if self._baro_datum is None:
            self._baro_datum = d.p + alt_m
        if self.ext_nav_in_use:
            # track the baro offset so that height stays continuous if external nav is lost
            self._baro_datum += 0.01 * (d.p + alt_m - self._baro_datum)
            return
        self._apply(2, 0, self._baro_datum - alt_m - d.p, d.innovation_variance(0, self._baro_var))

    def fuse_compass(self, yaw_rad: float) -> None:
        """Compass heading (rad). Steers the AHRS heading unless external-nav yaw is in use."""
        ahrs = self.ahrs
        if not ahrs.aligned:
            ahrs.aligned = True
            ahrs.yaw = ahrs.dcm_yaw = yaw_rad
            return
        ahrs.correct_dcm(yaw_rad, self.DCM_YAW_GAIN)
        if not self.ext_nav_in_use:
            self._credit(6, ahrs.correct_yaw(wrap_pi(yaw_rad - ahrs.yaw), self.COMPASS_YAW_GAIN))

    def fuse_gps(self, fix: GpsSample) -> None:
        """A GPS fix; fused (horizontal position, 3D velocity) with position_source "gps" only."""
        if self.position_source != "gps" or fix.fix_type < 3 or self.origin is None:
            return
        pos = ned_from_geodetic(fix.lat_deg, fix.lon_deg, fix.alt_m, self.origin)
        self._gps_rx_t = self.t
        n, e = self.axes[0], self.axes[1]
        if not self.gps_in_use:
            self.gps_in_use = True
            self.status.push(SEVERITY_INFO, "EKF3 IMU0 is using GPS")
            self._credit(0, n.reset_position(float(pos[0]), self._gps_pos_var))
            self._credit(1, e.reset_position(float(pos[1]), self._gps_pos_var))
            return
        for i in (0, 1):
            axis = self.axes[i]
            s = axis.innovation_variance(0, self._gps_pos_var)
            y = float(pos[i]) - axis.p
            if y * y <= self.gate_sigma**2 * s:
                self._apply(i, 0, y, s)
        for i in range(3):
            axis = self.axes[i]
            s = axis.innovation_variance(1, self._gps_vel_var)
            y = float(fix.vel_ned[i]) - axis.v
            if y * y <= self.gate_sigma**2 * s:
                self._apply(i, 1, y, s)
