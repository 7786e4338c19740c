"""ArduPilot-Copter-like flight controller of the simulated vehicle (plain floats, no I/O).

It acts only on the autopilot's own estimate (:class:`sitl.estimator.Estimator`) and IMU gyro,
never on the truth. Frames: NED (m, m/s, m/s^2) in the EKF frame, body FRD, angles in rad.

Cascade: position P (sqrt controller) -> shaped velocity PI -> acceleration -> (tilt, thrust) ->
attitude P -> body-rate PID -> mixer -> motor thrust fractions.

Modes use ArduPilot Copter custom_mode numbers. There are no pilot sticks: STABILIZE and
ALT_HOLD keep the attitude level and hold the altitude they were entered at.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.frames import GRAVITY_MPS2, wrap_pi
from sitl.dynamics import AirframeParams
from sitl.estimator import SEVERITY_CRITICAL, Estimator, StatusQueue
from sitl.flight_controller_base import (
    BODY_FRAMES, IGNORE_YAW, IGNORE_YAW_RATE, FlightControllerBase, rotate_xy, target_kind)

STABILIZE, ALT_HOLD, GUIDED, LOITER, RTL, LAND, BRAKE = 0, 2, 4, 5, 6, 9, 17
MODE_NAMES = {STABILIZE: "STABILIZE", ALT_HOLD: "ALT_HOLD", GUIDED: "GUIDED", LOITER: "LOITER",
              RTL: "RTL", LAND: "LAND", BRAKE: "BRAKE"}
POSITION_MODES = frozenset({GUIDED, LOITER, RTL, BRAKE})  # need a position estimate to fly
ARMABLE_MODES = frozenset({STABILIZE, ALT_HOLD, GUIDED, LOITER, LAND})
ARMING_NEEDS_POSITION = frozenset({GUIDED, LOITER, LAND})


@dataclass(frozen=True)
class ControlLimits:
    """Kinematic limits and timings (ArduPilot parameter in brackets)."""

    speed_xy_mps: float = 5.0  # WPNAV_SPEED
    accel_xy_mps2: float = 3.0  # WPNAV_ACCEL
    climb_mps: float = 2.5  # PILOT_SPEED_UP / WPNAV_SPEED_UP
    descent_mps: float = 1.5  # WPNAV_SPEED_DN / LAND_SPEED_HIGH
    accel_z_mps2: float = 5.0
    land_speed_mps: float = 0.5  # LAND_SPEED
    land_alt_low_m: float = 2.0  # below this LAND descends at land_speed
    takeoff_speed_mps: float = 1.0
    angle_max_rad: float = math.radians(30.0)  # ANGLE_MAX
    tilt_rate_max_rad_s: float = math.radians(180.0)
    yaw_rate_max_rad_s: float = math.radians(90.0)
    rtl_alt_m: float = 15.0  # RTL_ALT
    guided_timeout_s: float = 3.0
    ekf_failsafe_s: float = 1.0
    land_detect_s: float = 1.0
    disarm_delay_s: float = 10.0  # DISARM_DELAY
    prearm_yaw_tolerance_rad: float = math.radians(10.0)
    spin_arm: float = 0.05  # motor thrust fraction while armed on the ground
    spin_min: float = 0.08  # lowest thrust fraction in flight


@dataclass(frozen=True)
class ControlGains:
    """Controller gains: position in 1/s, velocity in 1/s (I in 1/s^2), attitude in 1/s,
    rates as angular acceleration per rate error (1/s, I 1/s^2, D dimensionless)."""

    pos_xy_p: float = 1.0
    vel_xy_p: float = 2.0
    vel_xy_i: float = 1.0
    vel_xy_imax: float = 2.0
    pos_z_p: float = 1.0
    vel_z_p: float = 4.0
    vel_z_i: float = 2.0
    vel_z_imax: float = 4.0
    ang_rp_p: float = 6.0
    ang_yaw_p: float = 3.0
    rate_rp_p: float = 20.0
    rate_rp_i: float = 10.0
    rate_rp_d: float = 0.2
    rate_yaw_p: float = 8.0
    rate_yaw_i: float = 2.0
    rate_imax: float = 10.0  # rad/s^2
    rate_d_filter_hz: float = 20.0


class FlightController(FlightControllerBase):
    """Mode logic, GUIDED targets and the control cascade; the public state, arming, disarming and
    the take-off checks are :class:`sitl.flight_controller_base.FlightControllerBase`'s.
    """

    MODE_NAMES = MODE_NAMES
    POSITION_MODES = POSITION_MODES
    ARMABLE_MODES = ARMABLE_MODES
    ARMING_NEEDS_POSITION = ARMING_NEEDS_POSITION
    TAKEOFF_MODES = frozenset({GUIDED})
    GUIDED_MODE = GUIDED
    RTL_MODE = RTL

    def __init__(self, *, status: StatusQueue, estimator: Estimator, airframe: AirframeParams,
                 limits: ControlLimits | None = None, gains: ControlGains | None = None) -> None:
        super().__init__(status=status, estimator=estimator, mode=STABILIZE)
        self.airframe = airframe
        self.limits = limits or ControlLimits()
        self.gains = gains or ControlGains()
        self._fmax = airframe.max_thrust_per_motor_n
        self._thrust = 0.0  # last collective thrust command, N
        # setpoints: horizontal "position" | "velocity" | "level", vertical "position" | "velocity"
        self._horizontal = "level"
        self._vertical = "position"
        self._sp = [0.0, 0.0, 0.0]
        self._vel_ff = [0.0, 0.0, 0.0]
        self._acc_ff = [0.0, 0.0, 0.0]
        self._yaw_sp = 0.0
        self._yaw_rate_sp = 0.0
        self._guided_kind = "pos"
        self._cmd_t = 0.0
        self._takeoff_z: float | None = None
        self._rtl_phase = ""
        self._no_pos_since: float | None = None
        self._land_timer = 0.0
        self._landed_since = 0.0
        self._reset_integrators()

    # ------------------------------------------------------------------ commands
    def _mode_change_failure(self, mode: int) -> str:
        """Like ArduCopter, a position mode needs a position (and RTL a home) only while armed."""
        return super()._mode_change_failure(mode) if self.armed else ""

    def _on_arm(self) -> None:
        """DISARM_DELAY on the ground counts from arming."""
        self._landed_since = self.t

    def _start_takeoff(self, altitude_m: float) -> None:
        """Climb to ``altitude_m`` above home (or the arming point) at <= takeoff speed."""
        self._takeoff_z = self._ground_z() - altitude_m
        self._guided_kind = "pos"
        self.landed = False
        self._land_timer = 0.0
        self._hold_here(stop=False)
        self._vertical = "position"

    def set_position_target(self, frame: int, type_mask: int, pos: tuple[float, float, float],
                            vel: tuple[float, float, float], acc: tuple[float, float, float],
                            yaw: float, yaw_rate: float) -> bool:
        """SET_POSITION_TARGET_LOCAL_NED semantics; False when ignored (not GUIDED, bad frame/mask/values)."""
        pos, vel, acc = (tuple(float(x) for x in v) for v in (pos, vel, acc))
        kind = target_kind(frame, type_mask)
        if self.mode != GUIDED or kind is None:
            return False
        use_yaw = not type_mask & IGNORE_YAW
        use_yaw_rate = not use_yaw and not type_mask & IGNORE_YAW_RATE
        used = ((pos if "pos" in kind else ()) + (vel if "vel" in kind else ()) + (acc if "acc" in kind else ())
                + ((yaw,) if use_yaw else ()) + ((yaw_rate,) if use_yaw_rate else ()))
        if not all(math.isfinite(v) for v in used):
            self.nonfinite_rejected += 1
            return False
        body = frame in BODY_FRAMES
        heading = self.est.ahrs.yaw
        if "pos" in kind:
            self._sp = list(self._target_position(frame, pos))
        elif not self.landed:
            self._sp = list(self._position())
        self._vel_ff = list(rotate_xy(vel, heading) if body else vel) if "vel" in kind else [0.0, 0.0, 0.0]
        self._acc_ff = list(rotate_xy(acc, heading) if body else acc) if "acc" in kind else [0.0, 0.0, 0.0]
        if kind == "acc" and not self.landed:
            self._vel_ff = list(self._velocity())
        self._guided_kind = kind
        self._horizontal = "position" if "pos" in kind else "velocity"
        self._vertical = self._horizontal
        self._takeoff_z = None
        self._cmd_t = self.t
        if use_yaw:
            self._yaw_sp = wrap_pi(yaw + heading) if body else wrap_pi(yaw)
        self._yaw_rate_sp = yaw_rate if use_yaw_rate else 0.0
        return True

    # ------------------------------------------------------------------ per-step
    def update(self, t: float, dt: float, gyro: tuple[float, float, float]) -> list[float]:
        """Run the supervisor and the cascade for one step; returns 4 motor thrust fractions."""
        self.t = t
        self._supervise(dt)
        if not self.armed:
            self._thrust = 0.0
            return [0.0, 0.0, 0.0, 0.0]
        if self.landed:
            self._on_ground()
            return [self.limits.spin_arm] * 4
        self._advance_setpoints(dt)
        acx, acy, acz = self._position_control(dt)
        roll_d, pitch_d = self._tilt(acx, acy, acz)
        return self._attitude_and_mix(dt, roll_d, pitch_d, acz, gyro)

    # ------------------------------------------------------------------ supervisor
    def _supervise(self, dt: float) -> None:
        """Home auto-set, EKF failsafe, GUIDED timeouts, land detector and auto-disarm."""
        est = self.est
        if not self.armed:
            self.landed = abs(est.axes[2].v) < 0.3
            if self.home_ned is None and est.pos_valid:
                self.home_ned = self._position()
            return
        if est.pos_valid:
            self._no_pos_since = None
        elif self._no_pos_since is None:
            self._no_pos_since = self.t
        elif self.mode in POSITION_MODES and self.t - self._no_pos_since > self.limits.ekf_failsafe_s:
            self.status.push(SEVERITY_CRITICAL, "EKF Failsafe: changed to LAND mode")
            self._enter_mode(LAND)
        if self.mode == GUIDED and not self.landed:
            self._check_guided_timeout()
        if self.landed:
            self._landed_checks()
        else:
            self._detect_landing(dt)

    def _check_guided_timeout(self) -> None:
        if self.t - self._cmd_t <= self.limits.guided_timeout_s:
            return
        self._yaw_rate_sp = 0.0
        if self._guided_kind in ("vel", "acc"):
            self._brake()
        elif self._guided_kind not in ("pos", "brake"):
            self._vel_ff = [0.0, 0.0, 0.0]
            self._acc_ff = [0.0, 0.0, 0.0]

    def _detect_landing(self, dt: float) -> None:
        """ArduPilot-style land detector: low thrust and no vertical motion for land_detect_s."""
        low_thrust = self._thrust < 0.85 * self.airframe.hover_thrust_n
        still = abs(self.est.axes[2].v) < 0.2
        if low_thrust and still and self._takeoff_z is None:
            self._land_timer += dt
        else:
            self._land_timer = 0.0
        if self._land_timer >= self.limits.land_detect_s:
            self.landed = True
            self._landed_since = self.t
            self._land_timer = 0.0

    def _landed_checks(self) -> None:
        """Disarm on touchdown in LAND / RTL, or after DISARM_DELAY on the ground."""
        if self.mode == LAND or (self.mode == RTL and self._rtl_phase == "land"):
            self._disarm()
        elif self.t - self._landed_since > self.limits.disarm_delay_s:
            self._disarm()

    def _arming_failure(self) -> str:
        """The shared checks, then ArduPilot's: ExtNav yaw consistent with the compass."""
        reason = super()._arming_failure()
        if reason:
            return reason
        est = self.est
        fresh = self.t - est.ext_nav_rx_t <= est.EXTNAV_TIMEOUT_S
        if est.position_source == "extnav" and fresh and est.ext_nav_yaw is not None:
            diff = abs(wrap_pi(est.ext_nav_yaw - est.ahrs.dcm_yaw))
            if diff > self.limits.prearm_yaw_tolerance_rad:
                return f"PreArm: AHRS: ExtNav yaw inconsistent with compass by {math.degrees(diff):.0f} deg"
        return ""

    def _end_flight(self) -> None:
        self._takeoff_z = None

    # ------------------------------------------------------------------ modes
    def _enter_mode(self, mode: int) -> None:
        """Switch mode and set the setpoints the mode starts from."""
        self.mode = mode
        self._takeoff_z = None
        self._yaw_rate_sp = 0.0
        self._yaw_sp = self.est.ahrs.yaw
        self._vel_ff = [0.0, 0.0, 0.0]
        self._acc_ff = [0.0, 0.0, 0.0]
        self._guided_kind = "pos"
        self._hold_here(stop=not self.landed)
        if mode in (STABILIZE, ALT_HOLD):
            self._horizontal = "level"
        elif mode == LAND:
            self._vertical = "velocity"
        elif mode == RTL:
            self._rtl_phase = "climb"
            climb_to = self._ground_z() - self.limits.rtl_alt_m
            self._sp[2] = min(self._sp[2], climb_to)

    def _hold_here(self, stop: bool) -> None:
        """Hold the current position (or, with ``stop``, the point where braking would end)."""
        p, v = self._position(), self._velocity()
        lim = self.limits
        if stop:
            ax = lim.accel_xy_mps2
            p = (p[0] + v[0] * abs(v[0]) / (2 * ax), p[1] + v[1] * abs(v[1]) / (2 * ax),
                 p[2] + v[2] * abs(v[2]) / (2 * lim.accel_z_mps2))
        self._sp = list(p)
        self._vel_ff = [0.0, 0.0, 0.0]
        self._acc_ff = [0.0, 0.0, 0.0]
        self._horizontal = "position"
        self._vertical = "position"

    def _advance_setpoints(self, dt: float) -> None:
        """Per-step setpoint motion: takeoff ramp, GUIDED feed-forward, LAND speed, RTL phases."""
        self._yaw_sp = wrap_pi(self._yaw_sp + self._yaw_rate_sp * dt)
        if self._takeoff_z is not None:
            self._advance_takeoff(dt)
        elif self.mode == GUIDED:
            self._advance_guided(dt)
        elif self.mode == LAND:
            self._vel_ff[2] = self._land_speed()
        elif self.mode == RTL:
            self._advance_rtl()

    def _advance_takeoff(self, dt: float) -> None:
        target = self._takeoff_z
        # climb at takeoff speed, slowing down over the last metre so as not to overshoot
        speed = min(self.limits.takeoff_speed_mps, self.gains.pos_z_p * (self._sp[2] - target) + 0.1)
        self._sp[2] = max(target, self._sp[2] - speed * dt)
        self._vel_ff[2] = -speed if self._sp[2] > target else 0.0
        if self._sp[2] == target and abs(self.est.axes[2].p - target) < 0.1:
            self._takeoff_z = None
            self._vel_ff[2] = 0.0

    def _brake(self) -> None:
        """Stop with a zero velocity target; :meth:`_advance_guided` then holds where it stopped."""
        self._guided_kind = "brake"
        self._vel_ff = [0.0, 0.0, 0.0]
        self._acc_ff = [0.0, 0.0, 0.0]
        self._horizontal = self._vertical = "velocity"

    def _advance_guided(self, dt: float) -> None:
        kind = self._guided_kind
        if kind == "brake":
            n, e, d = self.est.axes
            if n.v * n.v + e.v * e.v + d.v * d.v < 0.01:
                self._hold_here(stop=False)
                self._guided_kind = "pos"
        elif kind == "acc":
            for i in range(3):
                self._vel_ff[i] += self._acc_ff[i] * dt
            self._clamp_velocity(self._vel_ff)
        elif kind in ("posvel", "posvelacc"):
            for i in range(3):
                self._vel_ff[i] += self._acc_ff[i] * dt
                self._sp[i] += self._vel_ff[i] * dt

    def _land_speed(self) -> float:
        """Descent speed (m/s, positive down) by height above home / the arming point."""
        height = self._ground_z() - self.est.axes[2].p
        lim = self.limits
        return lim.land_speed_mps if height < lim.land_alt_low_m else lim.descent_mps

    def _advance_rtl(self) -> None:
        """Climb to RTL altitude, fly home, then land."""
        if self._rtl_phase == "climb" and abs(self.est.axes[2].p - self._sp[2]) < 0.5:
            self._rtl_phase = "return"
            self._sp[0], self._sp[1] = self.home_ned[0], self.home_ned[1]
        elif self._rtl_phase == "return":
            n, e = self.est.axes[0], self.est.axes[1]
            if math.hypot(n.p - self._sp[0], e.p - self._sp[1]) < 1.0 and math.hypot(n.v, e.v) < 0.5:
                self._rtl_phase = "land"
                self._vertical = "velocity"
        elif self._rtl_phase == "land":
            self._vel_ff[2] = self._land_speed()

    def _on_ground(self) -> None:
        """Armed on the ground: idle motors, integrators reset, setpoints follow the vehicle."""
        self._reset_integrators()
        self._yaw_sp = self.est.ahrs.yaw
        self._sp = list(self._position())
        self._thrust = 0.0

    # ------------------------------------------------------------------ cascade
    def _position_control(self, dt: float) -> tuple[float, float, float]:
        """NED acceleration command (m/s^2) from the setpoints; level attitude without a position."""
        if self._horizontal == "level" or not self.est.pos_valid:
            self._ix = self._iy = 0.0
            self._vc = [self.est.axes[0].v, self.est.axes[1].v]
            acx = acy = 0.0
        else:
            acx, acy = self._horizontal_control(dt)
        return acx, acy, self._vertical_control(dt)

    def _horizontal_control(self, dt: float) -> tuple[float, float]:
        """Position sqrt-controller -> velocity PI (integrating only while unsaturated)."""
        g, lim = self.gains, self.limits
        n, e = self.est.axes[0], self.est.axes[1]
        vcx, vcy = self._vel_ff[0], self._vel_ff[1]
        if self._horizontal == "position":
            ex, ey = self._sp[0] - n.p, self._sp[1] - e.p
            dist = math.hypot(ex, ey)
            if dist > 0.0:
                speed = _sqrt_controller(dist, g.pos_xy_p, lim.accel_xy_mps2 / 2) / dist
                vcx += ex * speed
                vcy += ey * speed
        vcx, vcy = _limit_norm(vcx, vcy, lim.speed_xy_mps)
        # shape the velocity command to the acceleration limit and feed its rate forward
        dvx, dvy = _limit_norm(vcx - self._vc[0], vcy - self._vc[1], lim.accel_xy_mps2 * dt)
        self._vc[0] += dvx
        self._vc[1] += dvy
        ex, ey = self._vc[0] - n.v, self._vc[1] - e.v
        acx = g.vel_xy_p * ex + self._ix + self._acc_ff[0] + dvx / dt
        acy = g.vel_xy_p * ey + self._iy + self._acc_ff[1] + dvy / dt
        if math.hypot(acx, acy) < lim.accel_xy_mps2:
            self._ix, self._iy = _limit_norm(self._ix + g.vel_xy_i * ex * dt, self._iy + g.vel_xy_i * ey * dt,
                                             g.vel_xy_imax)
        return _limit_norm(acx, acy, lim.accel_xy_mps2)

    def _vertical_control(self, dt: float) -> float:
        """Altitude P -> climb-rate PI -> vertical acceleration (m/s^2, positive down)."""
        g, lim = self.gains, self.limits
        d = self.est.axes[2]
        vcz = self._vel_ff[2]
        if self._vertical == "position":
            vcz += g.pos_z_p * (self._sp[2] - d.p)
        vcz = min(max(vcz, -lim.climb_mps), lim.descent_mps)
        ez = vcz - d.v
        self._iz = min(max(self._iz + g.vel_z_i * ez * dt, -g.vel_z_imax), g.vel_z_imax)
        return min(max(g.vel_z_p * ez + self._iz + self._acc_ff[2], -lim.accel_z_mps2), lim.accel_z_mps2)

    def _tilt(self, acx: float, acy: float, acz: float) -> tuple[float, float]:
        """Roll and pitch (rad) that point the thrust to give the NED acceleration command."""
        yaw = self.est.ahrs.yaw
        c, s = math.cos(yaw), math.sin(yaw)
        forward, right = c * acx + s * acy, -s * acx + c * acy
        lift = max(GRAVITY_MPS2 - acz, 1.0)
        amax = self.limits.angle_max_rad
        pitch = min(max(math.atan2(-forward, lift), -amax), amax)
        roll = min(max(math.atan2(right * math.cos(pitch), lift), -amax), amax)
        return roll, pitch

    def _attitude_and_mix(self, dt: float, roll_d: float, pitch_d: float, acz: float,
                          gyro: tuple[float, float, float]) -> list[float]:
        """Attitude P -> rate PID -> torques; collective from the vertical command; then the mixer."""
        g, lim, ahrs = self.gains, self.limits, self.est.ahrs
        roll, pitch = ahrs.roll, ahrs.pitch
        tilt_max = lim.tilt_rate_max_rad_s
        droll = min(max(g.ang_rp_p * (roll_d - roll), -tilt_max), tilt_max)
        dpitch = min(max(g.ang_rp_p * (pitch_d - pitch), -tilt_max), tilt_max)
        yaw_lim = lim.yaw_rate_max_rad_s
        dyaw = min(max(g.ang_yaw_p * wrap_pi(self._yaw_sp - ahrs.yaw) + self._yaw_rate_sp, -yaw_lim), yaw_lim)
        sr, cr = math.sin(roll), math.cos(roll)
        sp, cp = math.sin(pitch), math.cos(pitch)
        rate_cmd = (droll - sp * dyaw, cr * dpitch + sr * cp * dyaw, -sr * dpitch + cr * cp * dyaw)
        alpha = self._rate_pid(dt, rate_cmd, gyro)
        ixx, iyy, izz = self.airframe.inertia_kgm2
        self._thrust = self.airframe.mass_kg * (GRAVITY_MPS2 - acz) / max(cr * cp, 0.5)
        return self._mix(self._thrust, ixx * alpha[0], iyy * alpha[1], izz * alpha[2])

    def _rate_pid(self, dt: float, rate_cmd: tuple[float, float, float],
                  gyro: tuple[float, float, float]) -> tuple[float, float, float]:
        """Body angular acceleration command (rad/s^2) from body-rate errors."""
        g = self.gains
        out = [0.0, 0.0, 0.0]
        beta = dt / (dt + 1.0 / (2 * math.pi * g.rate_d_filter_hz))
        imax = g.rate_imax
        for i in range(3):
            err = rate_cmd[i] - gyro[i]
            kp, ki, kd = (g.rate_rp_p, g.rate_rp_i, g.rate_rp_d) if i < 2 else (g.rate_yaw_p, g.rate_yaw_i, 0.0)
            self._rate_i[i] = min(max(self._rate_i[i] + ki * err * dt, -imax), imax)
            self._rate_d[i] += beta * ((err - self._rate_err[i]) / dt - self._rate_d[i])
            self._rate_err[i] = err
            out[i] = kp * err + self._rate_i[i] + kd * self._rate_d[i]
        return out[0], out[1], out[2]

    def _mix(self, thrust: float, tx: float, ty: float, tz: float) -> list[float]:
        """Quad-X mixer: collective N and torques N m -> motor thrust fractions.

        Attitude has priority over collective; yaw is limited to a quarter of a motor's range.
        """
        a, lim = self.airframe, self.limits
        fmax = self._fmax
        fmin = lim.spin_min * fmax
        rx, ry = tx / (4 * a.arm_xy_m), ty / (4 * a.arm_xy_m)
        yaw = min(max(tz / (4 * a.yaw_torque_per_thrust_m), -0.25 * fmax), 0.25 * fmax)
        diff = [-rx + ry + yaw, rx - ry + yaw, rx + ry - yaw, -rx - ry - yaw]
        hi, lo = max(diff), min(diff)
        if hi - lo > fmax - fmin:
            scale = (fmax - fmin) / (hi - lo)
            diff = [x * scale for x in diff]
            hi, lo = hi * scale, lo * scale
        base = min(max(thrust / 4, fmin - lo), fmax - hi)
        return [(base + x) / fmax for x in diff]

    def _reset_integrators(self) -> None:
        self._ix = self._iy = self._iz = 0.0
        self._vc = [0.0, 0.0]  # shaped horizontal velocity command, m/s
        self._rate_i = [0.0, 0.0, 0.0]
        self._rate_d = [0.0, 0.0, 0.0]
        self._rate_err = [0.0, 0.0, 0.0]

    # ------------------------------------------------------------------ helpers
    def _velocity(self) -> tuple[float, float, float]:
        n, e, d = self.est.axes
        return n.v, e.v, d.v

    def _clamp_velocity(self, v: list[float]) -> None:
        lim = self.limits
        v[0], v[1] = _limit_norm(v[0], v[1], lim.speed_xy_mps)
        v[2] = min(max(v[2], -lim.climb_mps), lim.descent_mps)


def _sqrt_controller(error: float, p: float, accel: float) -> float:
    """ArduPilot's sqrt controller: ``p * error`` near the target, ``sqrt(2 a d)`` further away,
    so that the commanded speed can always be braked at ``accel``."""
    linear = accel / (p * p)
    if error <= linear:
        return p * error
    return math.sqrt(2.0 * accel * (error - linear / 2.0))


def _limit_norm(x: float, y: float, limit: float) -> tuple[float, float]:
    """Scale (x, y) down to length ``limit`` if longer."""
    norm = math.hypot(x, y)
    if norm > limit:
        k = limit / norm
        return x * k, y * k
    return x, y
