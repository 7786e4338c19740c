"""ArduPlane-like flight controller of the simulated fixed wing (plain floats, no I/O).

It acts on the autopilot's own estimate (:class:`sitl.estimator.Estimator`), the IMU and the
airspeed sensor, never on the truth, and sets a :class:`sitl.fixedwing.FixedWingCommand`.
Frames: NED (m, m/s) in the EKF frame, body FRD, angles in rad; heights are -z.

Modes use ArduPlane custom_mode numbers. There are no pilot sticks: MANUAL holds neutral rates
at trim throttle, STABILIZE and FBWA hold the wings level at trim pitch and throttle, CIRCLE
banks at a third of the roll limit holding its entry height.

- TAKEOFF, or MAV_CMD_NAV_TAKEOFF in GUIDED: full throttle along the heading of the runway
  (the heading when it starts), rotate at TKOFF_ROTATE_SPD, climb wings level to the height,
  then loiter (around the GUIDED target if one came meanwhile, else where the climb ended).
- GUIDED: a position target (SET_POSITION_TARGET_LOCAL_NED with a position) is a loiter circle
  of WP_LOITER_RAD around it at its height, as ArduPlane flies a guided waypoint; velocity-
  and acceleration-only targets are refused.
- LOITER: circle where the mode was entered; RTL: loiter over home at RTL_ALTITUDE.
- AUTO is the landing that :meth:`PlaneController.land` starts (there are no missions):
  loiter down to the final-approach point, fly the glide slope to home, flare, brake, disarm
  LAND_DISARMDELAY after stopping.
"""

from __future__ import annotations

import math

from companion.frames import wrap_pi
from sitl.estimator import SEVERITY_INFO, Estimator, StatusQueue
from sitl.fixedwing import FixedWingCommand
from sitl.flight_controller_base import IGNORE_YAW, FlightControllerBase, target_kind
from sitl.plane_guidance import (L1Loiter, PlaneLimits, Tecs, attitude_rates, bank_for_accel, bank_for_course,
                                 line_course)

MANUAL, CIRCLE, STABILIZE, FBWA, AUTO, RTL, LOITER, TAKEOFF, GUIDED = 0, 1, 2, 5, 10, 11, 12, 13, 15
MODE_NAMES = {MANUAL: "MANUAL", CIRCLE: "CIRCLE", STABILIZE: "STABILIZE", FBWA: "FBWA", AUTO: "AUTO", RTL: "RTL",
              LOITER: "LOITER", TAKEOFF: "TAKEOFF", GUIDED: "GUIDED"}
POSITION_MODES = frozenset({AUTO, RTL, LOITER, TAKEOFF, GUIDED})
ARMABLE_MODES = frozenset({MANUAL, STABILIZE, FBWA, TAKEOFF, GUIDED, LOITER})
LANDED_SPEED_MPS = 1.0


class PlaneController(FlightControllerBase):
    """Mode logic, take-off, landing, GUIDED targets and the control laws; the public state, arming,
    disarming and the take-off checks are :class:`sitl.flight_controller_base.FlightControllerBase`'s.

    ``rudder_rad_s`` is a yaw-rate offset added to the turn coordination (a deliberate sideslip;
    0 = coordinated).
    """

    MODE_NAMES = MODE_NAMES
    POSITION_MODES = POSITION_MODES
    ARMABLE_MODES = ARMABLE_MODES
    ARMING_NEEDS_POSITION = POSITION_MODES
    TAKEOFF_MODES = frozenset({GUIDED, TAKEOFF})
    GUIDED_MODE = GUIDED
    RTL_MODE = RTL

    def __init__(self, *, status: StatusQueue, estimator: Estimator, limits: PlaneLimits | None = None) -> None:
        super().__init__(status=status, estimator=estimator, mode=MANUAL)
        self.limits = limits or PlaneLimits()
        self.tecs = Tecs(self.limits)
        self.loiter = L1Loiter(self.limits)
        self.rudder_rad_s = 0.0
        self._phase = ""  # "takeoff", "loiter", "level", "circle", "neutral"; AUTO: "to_final", "final", "flare", "rollout"
        self._centre = (0.0, 0.0)
        self._height_d = 0.0
        self._airspeed_d = self.limits.airspeed_cruise_mps
        self._runway_yaw = 0.0
        self._pending: tuple[float, float, float] | None = None  # GUIDED target received during the take-off
        self._final_start = (0.0, 0.0)
        self._stopped_since: float | None = None
        self._still_s = 0.0

    # ------------------------------------------------------------------ commands
    def _mode_change_failure(self, mode: int) -> str:
        """AUTO is refused (no mission); then the shared position and home checks, armed or not."""
        if mode == AUTO:
            return "Mode change to AUTO failed: no mission"
        return super()._mode_change_failure(mode)

    def land(self) -> tuple[bool, str]:
        """Land at home (mode AUTO): final approach, glide slope, flare; in flight with a home only."""
        if not self.armed or self.landed:
            return False, "Land: not flying"
        if self.home_ned is None or not self.est.pos_valid:
            return False, "Land: requires position and home"
        home = self.home_ned
        n, e = self._position()[:2]
        bearing = math.atan2(home[1] - e, home[0] - n)
        length = self.limits.land_final_m
        self.mode = AUTO
        self._final_start = (home[0] - length * math.cos(bearing), home[1] - length * math.sin(bearing))
        self._centre = self._final_start
        self._height_d = -home[2] + length * math.tan(self.limits.land_glide_rad)
        self._airspeed_d = self.limits.airspeed_cruise_mps
        self._phase = "to_final"
        self.status.push(SEVERITY_INFO, "Landing approach started")
        return True, ""

    def start_in_flight(self) -> None:
        """Begin airborne: armed, in FBWA, wings level along the heading it has (as after a hand
        launch); a mission switches to GUIDED and gives it a target. (In GUIDED it would circle
        where it is: no straight flight for what needs one before the mission starts.)"""
        self.armed = True
        self.landed = False
        self._arming_z = 0.0
        self._enter_mode(FBWA)

    def set_position_target(self, frame: int, type_mask: int, pos: tuple[float, float, float],
                            vel: tuple[float, float, float], acc: tuple[float, float, float],
                            yaw: float, yaw_rate: float) -> bool:
        """SET_POSITION_TARGET_LOCAL_NED with a position: loiter around it at its height; False when ignored."""
        del vel, acc, yaw_rate  # a fixed wing flies to the point; speeds and yaw are its own
        kind = target_kind(frame, type_mask)
        if self.mode != GUIDED or kind is None or "pos" not in kind:
            return False
        values = tuple(float(v) for v in pos) + (() if type_mask & IGNORE_YAW else (float(yaw),))
        if not all(math.isfinite(v) for v in values):
            self.nonfinite_rejected += 1
            return False
        p = self._target_position(frame, values[:3])
        if self._phase == "takeoff" or self.landed:
            self._pending = p
        else:
            self._loiter_at((p[0], p[1]), -p[2])
        return True

    # ------------------------------------------------------------------ per-step
    def update(self, t: float, dt: float, gyro: tuple[float, float, float], accel_x: float,
               airspeed: float) -> FixedWingCommand:
        """Supervisor and control laws for one step from the IMU gyro (rad/s), its forward specific
        force (m/s^2) and the measured airspeed (m/s)."""
        self.t = t
        if not self.armed:
            self.landed = True
            if self.home_ned is None and self.est.pos_valid:
                self.home_ned = self._position()
            return FixedWingCommand(brake=1.0)
        if self._phase == "takeoff":
            return self._fly_takeoff(dt, gyro, accel_x, airspeed)
        if self.landed:
            self.tecs.reset()
            stopped = self._stopped_since
            if self.mode == AUTO and stopped is not None and t - stopped > self.limits.land_disarm_delay_s:
                self._disarm()
            return FixedWingCommand(brake=1.0)
        if self.mode == AUTO:
            self._advance_landing()
        else:
            self._detect_stop(dt)
        return self._fly(dt, gyro, accel_x, airspeed)

    def _fly(self, dt: float, gyro: tuple[float, float, float], accel_x: float, airspeed: float) -> FixedWingCommand:
        lim, ahrs = self.limits, self.est.ahrs
        if self._phase == "neutral":
            return FixedWingCommand(throttle=lim.throttle_trim)
        if self._phase == "rollout":
            roll_d, pitch_d, throttle = 0.0, 0.0, 0.0
        else:
            roll_d = self._bank_demand()
            throttle, pitch_d = self.tecs.update(dt, self._height(), -self.est.axes[2].v, airspeed, accel_x,
                                                 ahrs.pitch, self._height_d, self._airspeed_d,
                                                 climb_ff=self._glide_rate(), climb_d=self._climb_override())
            if self._phase == "level":
                pitch_d, throttle = 0.03, lim.throttle_trim
            elif self._phase == "flare":
                throttle = 0.0
        p, q, r = attitude_rates(roll_d, pitch_d, ahrs.roll, ahrs.pitch, gyro, airspeed, self.rudder_rad_s)
        return FixedWingCommand(throttle=throttle, roll_rate=p, pitch_rate=q, yaw_rate=r,
                                brake=1.0 if self._phase == "rollout" else 0.0)

    def _bank_demand(self) -> float:
        """Bank angle (rad) of the current lateral guidance."""
        lim = self.limits
        if self._phase in ("level", "flare"):
            return 0.0
        if self._phase == "circle":
            return lim.roll_limit_rad / 3.0
        n, e = self.est.axes[0], self.est.axes[1]
        if self._phase == "final":
            course_d, _ = line_course(n.p, e.p, self._final_start, self.home_ned[:2])
            return bank_for_course(course_d, math.atan2(e.v, n.v), math.hypot(n.v, e.v), lim.roll_limit_rad)
        ahrs = self.est.ahrs
        accel = self.loiter.lateral_accel(n.p, e.p, n.v, e.v, ahrs.yaw, self._centre, lim.loiter_radius_m)
        return bank_for_accel(accel, ahrs.pitch, lim.roll_limit_rad)

    def _glide_rate(self) -> float:
        """Climb rate (m/s, negative) of the glide-slope height demand on the final approach, else 0."""
        if self._phase != "final":
            return 0.0
        n, e = self.est.axes[0], self.est.axes[1]
        return -math.hypot(n.v, e.v) * math.tan(self.limits.land_glide_rad)

    def _climb_override(self) -> float | None:
        """Climb-rate demand (m/s) where the phase fixes it (flare), else None (height demand)."""
        return -self.limits.land_flare_sink_mps if self._phase == "flare" else None

    # ------------------------------------------------------------------ take-off
    def _start_takeoff(self, altitude_m: float) -> None:
        ground = -self._ground_z()
        self._phase = "takeoff"
        self._height_d = ground + altitude_m
        self._runway_yaw = self.est.ahrs.yaw
        self.landed = False
        self.tecs.reset()
        self.status.push(SEVERITY_INFO, f"Takeoff to {altitude_m:.0f} m")

    def _fly_takeoff(self, dt: float, gyro: tuple[float, float, float], accel_x: float,
                     airspeed: float) -> FixedWingCommand:
        """Full throttle on the runway heading, rotate, climb wings level; then loiter."""
        lim, ahrs = self.limits, self.est.ahrs
        height = self._height()
        if height >= self._height_d - 2.0:
            self.status.push(SEVERITY_INFO, "Takeoff complete")
            n, e = self._position()[:2]
            target = self._pending
            self._pending = None
            if target is not None:
                self._loiter_at((target[0], target[1]), -target[2])
            else:
                self._loiter_at((n, e), self._height_d)
            return self._fly(dt, gyro, accel_x, airspeed)
        heading_error = wrap_pi(self._runway_yaw - ahrs.yaw)
        pitch_d = lim.takeoff_pitch_rad if airspeed >= lim.takeoff_rotate_mps else 0.0
        p, q, r = attitude_rates(0.0, pitch_d, ahrs.roll, ahrs.pitch, gyro, airspeed)
        return FixedWingCommand(throttle=1.0, roll_rate=p, pitch_rate=q, yaw_rate=r + 1.0 * heading_error)

    # ------------------------------------------------------------------ landing
    def _advance_landing(self) -> None:
        """AUTO landing phases: to the final-approach point, glide slope, flare, roll-out to a stop."""
        lim = self.limits
        n, e, d = self.est.axes
        home = self.home_ned
        if self._phase == "to_final":
            level = abs(self._height() - self._height_d) < 3.0
            to_home = math.atan2(home[1] - e.p, home[0] - n.p)
            aligned = abs(wrap_pi(math.atan2(e.v, n.v) - to_home)) < math.radians(20.0)
            near = math.hypot(n.p - self._centre[0], e.p - self._centre[1]) < 1.5 * lim.loiter_radius_m
            if level and aligned and near:
                self._phase = "final"
                self._final_start = (n.p, e.p)
                self._airspeed_d = lim.airspeed_approach_mps
        elif self._phase == "final":
            _, to_go = line_course(n.p, e.p, self._final_start, home[:2])
            self._height_d = -home[2] + max(0.0, to_go) * math.tan(lim.land_glide_rad)
            if self._height() - (-home[2]) < lim.land_flare_alt_m:
                self._phase = "flare"
                self.status.push(SEVERITY_INFO, "Flare")
        elif self._phase in ("flare", "rollout"):
            self._phase = "rollout" if abs(d.v) < 0.2 and self._height() - (-home[2]) < 0.5 else self._phase
            if math.hypot(n.v, e.v) < LANDED_SPEED_MPS:
                self._stopped_since = self.t
                self.landed = True
                self.status.push(SEVERITY_INFO, "Landed")

    def _detect_stop(self, dt: float) -> None:
        """Outside a landing: at rest for 3 s (ground speed and climb rate below 1 and 0.3 m/s) is landed
        (an off-field landing or a crash), so that it can be disarmed."""
        n, e, d = self.est.axes
        if math.hypot(n.v, e.v) < LANDED_SPEED_MPS and abs(d.v) < 0.3:
            self._still_s += dt
        else:
            self._still_s = 0.0
        if self._still_s > 3.0:
            self.landed = True
            self._still_s = 0.0
            self.status.push(SEVERITY_INFO, "Landed")

    # ------------------------------------------------------------------ helpers
    def _enter_mode(self, mode: int) -> None:
        """Switch mode and set what the mode flies from here."""
        self.mode = mode
        if self._phase == "takeoff" and mode in (GUIDED, TAKEOFF):
            return  # the climb-out goes on
        self._stopped_since = None
        n, e = self._position()[:2]
        if mode == MANUAL:
            self._phase = "neutral"
        elif mode in (STABILIZE, FBWA):
            self._phase = "level"
        elif mode == CIRCLE:
            self._phase, self._height_d = "circle", self._height()
        elif mode == RTL:
            home = self.home_ned
            self._loiter_at((home[0], home[1]), -home[2] + self.limits.rtl_alt_m)
        elif mode == TAKEOFF and self.armed and self.landed:
            self._start_takeoff(self.limits.takeoff_alt_m)
        else:  # LOITER, GUIDED, TAKEOFF in flight: circle here at this height
            self._loiter_at((n, e), self._height())

    def _loiter_at(self, centre: tuple[float, float], height: float) -> None:
        self._phase = "loiter"
        self._centre = centre
        self._height_d = height
        self._airspeed_d = self.limits.airspeed_cruise_mps

    def _end_flight(self) -> None:
        self._phase = ""
        self._stopped_since = None
        self._pending = None

    def _height(self) -> float:
        """Estimated height, m above the EKF origin (-z)."""
        return -self.est.axes[2].p
