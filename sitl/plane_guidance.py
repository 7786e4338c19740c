"""Guidance and control laws of the simulated ArduPlane-like autopilot (plain floats, no I/O).

- Loiter: ArduPlane's own L1 loiter law (:class:`L1Loiter`, AP_L1_Control::update_loiter): an L1
  capture of the centre from outside the circle, handed over to a PD law on the radial error with
  the centripetal feed-forward where the two demands cross; its lateral acceleration becomes a
  bank angle (phi = atan(a / g)). (Until 2026-12-05 an orbit vector field of Beard & McLain,
  *Small Unmanned Aircraft*, ch. 10, which is singular at the centre: arriving at a target it
  reversed a 45 deg bank 3-4 times in 15 s, at up to 170 deg/s of roll rate.)
- The final approach: a straight-line vector field (Beard & McLain's) on the ground course; the
  course error becomes a lateral acceleration and so a bank angle.
- :class:`Tecs`: a small total-energy controller (ArduPlane's TECS in spirit): throttle from the
  specific total-energy rate, pitch from the energy-balance rate, both with an integrator.
- :func:`attitude_rates`: the roll and pitch attitude loops and the turn coordination, giving
  the body rates (FRD, rad/s) the airframe should fly.

Angles in rad (course and heading from north towards east), NED metres, m/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.frames import GRAVITY_MPS2, wrap_pi

LINE_GAIN = 0.03  # 1/m: cross-track error -> course offset (k_path)
LINE_ENTRY_RAD = math.radians(60.0)  # course offset far from the line (chi_inf)
COURSE_GAIN = 1.2  # 1/s: course error -> lateral acceleration per m/s of ground speed


@dataclass(frozen=True)
class PlaneLimits:
    """Speeds, angles and heights of the autopilot (ArduPlane parameter in brackets)."""

    airspeed_cruise_mps: float = 17.0  # TRIM_ARSPD_CM / AIRSPEED_CRUISE
    airspeed_min_mps: float = 12.0  # ARSPD_FBW_MIN / AIRSPEED_MIN
    airspeed_max_mps: float = 25.0  # ARSPD_FBW_MAX
    airspeed_approach_mps: float = 13.0  # TECS_LAND_ARSPD
    roll_limit_rad: float = math.radians(45.0)  # LIM_ROLL_CD / ROLL_LIMIT_DEG
    pitch_max_rad: float = math.radians(20.0)  # LIM_PITCH_MAX / PTCH_LIM_MAX_DEG
    pitch_min_rad: float = math.radians(-25.0)  # LIM_PITCH_MIN / PTCH_LIM_MIN_DEG
    climb_max_mps: float = 4.0  # TECS_CLMB_MAX
    sink_max_mps: float = 4.0  # TECS_SINK_MAX
    throttle_trim: float = 0.2  # TRIM_THROTTLE (this airframe's level flight at cruise)
    loiter_radius_m: float = 40.0  # WP_LOITER_RAD
    l1_period_s: float = 17.0  # NAVL1_PERIOD
    l1_damping: float = 0.75  # NAVL1_DAMPING
    takeoff_alt_m: float = 30.0  # TKOFF_ALT
    takeoff_rotate_mps: float = 12.0  # TKOFF_ROTATE_SPD
    takeoff_pitch_rad: float = math.radians(12.0)  # TKOFF_LVL_PITCH
    rtl_alt_m: float = 50.0  # RTL_ALTITUDE / ALT_HOLD_RTL
    land_glide_rad: float = math.radians(5.0)  # glide slope of the final approach
    land_final_m: float = 200.0  # length of the final approach
    land_flare_alt_m: float = 2.0  # LAND_FLARE_ALT
    land_flare_sink_mps: float = 0.5  # LAND_FLARE_SINK
    land_disarm_delay_s: float = 20.0  # LAND_DISARMDELAY


class L1Loiter:
    """ArduPlane's L1 loiter law (AP_L1_Control::update_loiter, with its ``_prevent_indecision``):
    the lateral acceleration (m/s^2, right positive) that brings the aircraft onto a circle of
    ``radius_m`` around ``centre`` (NED north, east m) and holds it there, clockwise
    (``direction`` +1) or counter-clockwise (-1).

    Outside the circle the L1 capture law steers at the centre (``K_L1 V^2 / L1 sin(Nu)``,
    ``Nu`` the angle between the ground velocity and the direction to the centre, at most 90
    deg); the circle law is a PD on the radial error and radial velocity plus the centripetal
    acceleration of the tangential speed. The capture flies while the aircraft is outside and its
    demand is the smaller of the two (turning in the loiter's sense), so the hand-over is where
    they cross. Frames: NED m, m/s; angles rad."""

    def __init__(self, limits: PlaneLimits) -> None:
        self.limits = limits
        self._last_nu = 0.0

    def lateral_accel(self, north: float, east: float, v_north: float, v_east: float, yaw: float,
                      centre: tuple[float, float], radius_m: float, direction: int = 1) -> float:
        """Lateral acceleration demand (m/s^2, right positive) at the position (m) with the ground
        velocity (m/s) and heading ``yaw`` (rad) of the aircraft."""
        period, damping = self.limits.l1_period_s, self.limits.l1_damping
        omega = 2.0 * math.pi / period
        kx, kv = omega * omega, 2.0 * damping * omega
        k_l1 = 4.0 * damping * damping
        speed = max(math.hypot(v_north, v_east), 1.0)
        l1_m = damping * period * speed / math.pi
        an, ae = north - centre[0], east - centre[1]  # the aircraft from the centre
        distance = math.hypot(an, ae)
        if distance > 0.1:
            un, ue = an / distance, ae / distance
        else:  # on the centre: along the velocity
            un, ue = v_north / speed, v_east / speed
        across = un * v_east - ue * v_north  # velocity across the radial line (A x v)
        inbound = -(v_north * un + v_east * ue)  # velocity along it, towards the centre
        nu = math.atan2(across, inbound)
        bearing_to_centre = math.atan2(-ae, -an)
        limit = 0.9 * math.pi
        away = abs(wrap_pi(bearing_to_centre - yaw)) > math.radians(120.0)
        if abs(nu) > limit and abs(self._last_nu) > limit and away and nu * self._last_nu < 0.0:
            nu = self._last_nu  # flying away from the centre: keep turning the way it started (indecision)
        self._last_nu = nu
        nu = max(-math.pi / 2, min(math.pi / 2, nu))
        capture = k_l1 * speed * speed / l1_m * math.sin(nu)
        radial_error = distance - radius_m
        circle_pd = radial_error * kx - inbound * kv
        tangential = across * direction
        if inbound > 0.0 and tangential < 0.0:  # flying the wrong way round: the PD must not turn it further
            circle_pd = max(circle_pd, 0.0)
        circle = direction * (circle_pd + tangential * tangential / max(0.5 * radius_m, radius_m + radial_error))
        if radial_error > 0.0 and direction * capture < direction * circle:
            return capture
        return circle


def bank_for_accel(accel_mps2: float, pitch: float, roll_limit: float) -> float:
    """Bank angle (rad, right positive) for a lateral acceleration demand (m/s^2), as ArduPlane's
    nav_roll_cd: ``cos(pitch) atan(a / g)``, within the roll limit."""
    return max(-roll_limit, min(roll_limit, math.cos(pitch) * math.atan(accel_mps2 / GRAVITY_MPS2)))


def line_course(north: float, east: float, start: tuple[float, float], end: tuple[float, float]) -> tuple[float, float]:
    """(commanded course rad, distance to go m) of the straight-line field from ``start`` to ``end``."""
    line = math.atan2(end[1] - start[1], end[0] - start[0])
    cl, sl = math.cos(line), math.sin(line)
    dn, de = north - start[0], east - start[1]
    cross = -sl * dn + cl * de  # right of the line is positive
    to_go = cl * (end[0] - north) + sl * (end[1] - east)
    return wrap_pi(line - LINE_ENTRY_RAD * 2.0 / math.pi * math.atan(LINE_GAIN * cross)), to_go


def bank_for_course(course_cmd: float, course: float, ground_speed: float, roll_limit: float) -> float:
    """Bank angle (rad, right positive) that turns the ground course (rad) towards ``course_cmd`` at
    ``ground_speed`` (m/s)."""
    accel = COURSE_GAIN * max(ground_speed, 1.0) * wrap_pi(course_cmd - course)
    return max(-roll_limit, min(roll_limit, math.atan(accel / GRAVITY_MPS2)))


def attitude_rates(roll_d: float, pitch_d: float, roll: float, pitch: float, gyro: tuple[float, float, float],
                   airspeed: float, rudder_rad_s: float = 0.0) -> tuple[float, float, float]:
    """Body rates (p, q, r) rad/s for the attitude demand: P loops on the Euler angles, turned
    into body rates with the measured gyro, and the coordinated-turn yaw rate
    r = g sin(phi) cos(theta) / V plus ``rudder_rad_s`` (a deliberate sideslip)."""
    roll_rate = 4.0 * wrap_pi(roll_d - roll)
    pitch_rate = 4.0 * (pitch_d - pitch)
    _, q, r = gyro
    sr, cr = math.sin(roll), math.cos(roll)
    p_cmd = roll_rate - (q * sr + r * cr) * math.tan(pitch)
    q_cmd = (pitch_rate + r * sr) / max(cr, 0.2)
    r_cmd = GRAVITY_MPS2 * sr * math.cos(pitch) / max(airspeed, 5.0) + rudder_rad_s
    return p_cmd, q_cmd, r_cmd


class Tecs:
    """Height and airspeed to throttle and pitch (a light TECS).

    Demands: height rate from the height error (time constant ``tau_s``, within the climb and
    sink limits), airspeed rate from the speed error. Throttle follows the total specific energy
    rate (V dV/dt + g dh/dt), pitch the balance rate (g dh/dt - V dV/dt); below the minimum
    airspeed the pitch flies the speed only.
    """

    def __init__(self, limits: PlaneLimits, tau_s: float = 5.0) -> None:
        self.limits = limits
        self.tau_s = tau_s
        self.reset()

    def reset(self) -> None:
        """Forget the integrators and the filtered acceleration."""
        self._thr_i = 0.0
        self._pitch_i = 0.0
        self._vdot = 0.0

    def update(self, dt: float, height: float, climb: float, airspeed: float, accel_x: float, pitch: float,
               height_d: float, airspeed_d: float, *, climb_ff: float = 0.0,
               climb_d: float | None = None) -> tuple[float, float]:
        """(throttle [0, 1], pitch demand rad) for a height demand (m) moving at ``climb_ff`` (m/s),
        or for a climb-rate demand ``climb_d`` (m/s)."""
        lim, g = self.limits, GRAVITY_MPS2
        v = max(airspeed, 3.0)
        self._vdot += dt / (dt + 0.2) * (accel_x - g * math.sin(pitch) - self._vdot)
        if climb_d is None:
            climb_d = (height_d - height) / self.tau_s + climb_ff
        climb_d = max(-lim.sink_max_mps, min(lim.climb_max_mps, climb_d))
        airspeed_d = max(lim.airspeed_min_mps, min(lim.airspeed_max_mps, airspeed_d))
        vdot_d = max(-2.0, min(2.0, 0.4 * (airspeed_d - airspeed)))
        ste_d, ste = v * vdot_d + g * climb_d, v * self._vdot + g * climb
        ste_err = (ste_d - ste) / g
        self._thr_i = max(-0.3, min(0.3, self._thr_i + 0.05 * ste_err * dt))
        throttle = lim.throttle_trim + 0.12 * ste_d / g + 0.15 * ste_err + self._thr_i
        underspeed = airspeed < lim.airspeed_min_mps
        weight = 0.0 if underspeed else 1.0  # 0: pitch flies the speed only
        seb_d = weight * g * climb_d - v * vdot_d
        seb = weight * g * climb - v * self._vdot
        seb_err = (seb_d - seb) / (g * v)
        self._pitch_i = max(-0.2, min(0.2, self._pitch_i + 0.1 * seb_err * dt))
        pitch_d = 0.03 + seb_d / (g * v) + 0.5 * seb_err + self._pitch_i
        return (max(0.0, min(1.0, 1.0 if underspeed else throttle)),
                max(lim.pitch_min_rad, min(lim.pitch_max_rad, pitch_d)))
