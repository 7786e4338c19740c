"""Fixed-wing truth model for the built-in SITL: a point mass with an attitude (plain floats, no I/O).

Frames follow :mod:`companion.frames`: position and velocity NED (m, m/s) from the simulation
anchor, body FRD, quaternion ``[w, x, y, z]`` body->NED. The runway is the plane NED z = 0.

Forces: thrust along body x (a fixed-pitch propeller whose thrust falls linearly to zero at
``prop_speed_mps`` of airspeed), lift and drag in the stability axes, side force from sideslip,
gravity. Lift is linear in the angle of attack up to the critical angle and collapses beyond it
to a flat plate's (the sigmoid blend of Beard & McLain, *Small Unmanned Aircraft*, eq. 4.10).
Angle of attack and sideslip come from the air-relative velocity in body axes (velocity minus
the wind of :class:`sitl.dynamics.AirMass`):

    alpha = atan2(w, u), beta = asin(v / Va), (u, v, w) = R^T (v_ned - wind_ned).

Attitude: the body rates follow the rates commanded by the autopilot (its rate loops and the
control surfaces lumped into a first-order lag whose authority goes with dynamic pressure), plus
two aerodynamic moments: weathercock stability yaws the nose into the relative wind (so a turn
flown with the coordination yaw rate has ~zero sideslip, and a yaw-rate offset, the "rudder",
holds a steady sideslip), and beyond the critical angle of attack the nose drops.

On the runway the wheels allow no sideways motion and no roll; the nose may rotate up (to
``ground_pitch_max_rad``) once the elevator has authority, and lift-off happens when lift
exceeds weight.

Everything runs on plain Python floats (one 400 Hz step costs some tens of microseconds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.frames import GRAVITY_MPS2, quat_from_euler
from sitl.dynamics import AirMass, GaussianStream, WindConfig
from sitl.rigid_body import RigidBody


@dataclass(frozen=True)
class FixedWingParams:
    """A small electric UAV (about 2.5 kg, 1.6 m span, cruise 17 m/s, stall 10 m/s). SI units."""

    mass_kg: float = 2.5
    wing_area_m2: float = 0.35
    span_m: float = 1.6
    air_density_kgm3: float = 1.225
    cl0: float = 0.2  # lift coefficient at zero angle of attack
    cl_alpha_per_rad: float = 4.8
    alpha_stall_rad: float = math.radians(15.0)  # where lift has half collapsed (the blend's centre)
    stall_sharpness_per_rad: float = 50.0  # sigmoid blend into the flat plate
    cd0: float = 0.03  # parasitic drag coefficient
    oswald: float = 0.8
    cy_beta_per_rad: float = -0.6  # side force per sideslip
    thrust_max_n: float = 25.0  # static thrust at full throttle
    prop_speed_mps: float = 35.0  # airspeed at which the propeller thrust falls to zero
    throttle_tau_s: float = 0.1  # motor lag
    rate_tau_s: float = 0.08  # body-rate response at the reference airspeed
    reference_airspeed_mps: float = 17.0
    rate_max_rad_s: tuple[float, float, float] = (3.0, 2.0, 1.5)  # roll, pitch, yaw command limits
    weathercock_per_s2: float = 20.0  # yaw acceleration per rad of sideslip at the reference airspeed
    stall_pitch_down_per_s2: float = 30.0  # pitch acceleration per rad of angle of attack past the stall
    rolling_friction: float = 0.04  # rolling-resistance coefficient on the runway
    brake_decel_mps2: float = 2.0  # wheel brakes at full command
    ground_pitch_max_rad: float = math.radians(12.0)  # tail strike

    @property
    def aspect_ratio(self) -> float:
        """Span^2 / wing area."""
        return self.span_m**2 / self.wing_area_m2

    @property
    def alpha_cl_max_rad(self) -> float:
        """Angle of attack of the largest lift coefficient (a little below ``alpha_stall_rad``, the
        centre of the blend into the flat plate), to 0.1 deg: past it the wing is stalled."""
        angles = [math.radians(0.1 * i) for i in range(round(10.0 * math.degrees(self.alpha_stall_rad)) + 1)]
        return max(angles, key=lambda a: lift_drag_coefficients(a, self)[0])

    @property
    def cl_max(self) -> float:
        """The largest lift coefficient."""
        return lift_drag_coefficients(self.alpha_cl_max_rad, self)[0]

    @property
    def stall_speed_mps(self) -> float:
        """Level-flight (1 g) stall airspeed, m/s."""
        return math.sqrt(2.0 * self.mass_kg * GRAVITY_MPS2 / (self.air_density_kgm3 * self.wing_area_m2 * self.cl_max))


@dataclass
class FixedWingCommand:
    """What the autopilot sets each step: throttle [0, 1], body rates (FRD, rad/s), brake [0, 1]."""

    throttle: float = 0.0
    roll_rate: float = 0.0
    pitch_rate: float = 0.0
    yaw_rate: float = 0.0
    brake: float = 0.0


def lift_drag_coefficients(alpha: float, p: FixedWingParams) -> tuple[float, float]:
    """(CL, CD) at angle of attack ``alpha`` (rad): linear lift blended into a flat plate past the stall."""
    m, a0 = p.stall_sharpness_per_rad, p.alpha_stall_rad
    e_minus = math.exp(min(50.0, -m * (alpha - a0)))
    e_plus = math.exp(min(50.0, m * (alpha + a0)))
    sigma = (1.0 + e_minus + e_plus) / ((1.0 + e_minus) * (1.0 + e_plus))
    cl_linear = p.cl0 + p.cl_alpha_per_rad * alpha
    s = math.sin(alpha)
    cl_plate = 2.0 * math.copysign(s * s, alpha) * math.cos(alpha)
    cl = (1.0 - sigma) * cl_linear + sigma * cl_plate
    cd_attached = p.cd0 + cl_linear * cl_linear / (math.pi * p.oswald * p.aspect_ratio)
    cd_plate = p.cd0 + 2.0 * s * s
    return cl, (1.0 - sigma) * cd_attached + sigma * cd_plate


class FixedWingDynamics(RigidBody):
    """Truth state (:class:`sitl.rigid_body.RigidBody`) and its integration (semi-implicit Euler,
    renormalised quaternion) under thrust, aerodynamics and the runway.

    Public attributes besides the rigid body's (read them, do not write): ``airspeed`` m/s,
    ``alpha`` / ``beta`` angle of attack and sideslip rad, ``thrust`` N, ``on_ground``, ``stalled``
    (in flight past the angle of attack of maximum lift), ``touchdown_sink_mps`` (descent rate at
    the last touchdown). ``air`` is the wind.
    """

    def __init__(self, *, noise: GaussianStream, params: FixedWingParams | None = None,
                 wind: WindConfig | None = None, start_ned: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 start_yaw_rad: float = 0.0, start_airspeed_mps: float = 0.0) -> None:
        super().__init__(start_ned, start_yaw_rad)
        self.params = params or FixedWingParams()
        self.air = AirMass(wind or WindConfig(), noise)
        self.on_ground = self.pz >= 0.0
        c, s = math.cos(start_yaw_rad), math.sin(start_yaw_rad)
        self.vx, self.vy = start_airspeed_mps * c, start_airspeed_mps * s
        self.airspeed = float(start_airspeed_mps)
        self.alpha = self.beta = 0.0
        self.thrust = 0.0
        self.stalled = False
        self.touchdown_sink_mps = 0.0
        self._wind = (0.0, 0.0, 0.0)
        self._alpha_cl_max = self.params.alpha_cl_max_rad

    @property
    def wind_ned(self) -> np.ndarray:
        """Air velocity (mean + gust) at the vehicle, NED m/s."""
        return np.array(self._wind)

    # ------------------------------------------------------------------ integration
    def step(self, dt: float, cmd: FixedWingCommand) -> None:
        """Advance by ``dt`` seconds under the autopilot's command."""
        p = self.params
        r = self._rotation()
        self._wind = self.air.step(dt)
        fbx, fby, fbz = self._aero_and_thrust(dt, cmd, r)
        inv_m = 1.0 / p.mass_kg
        # NED acceleration = R f_body / m + g
        ax = (r[0] * fbx + r[1] * fby + r[2] * fbz) * inv_m
        ay = (r[3] * fbx + r[4] * fby + r[5] * fbz) * inv_m
        az = (r[6] * fbx + r[7] * fby + r[8] * fbz) * inv_m + GRAVITY_MPS2
        if self.on_ground and az >= 0.0:
            self._roll_on_ground(dt, cmd, ax, ay, az)
        else:
            self.on_ground = False
            self._fly(ax, ay, az, dt)
            self._rotate(dt, cmd)
            if self.pz >= 0.0:
                self._touch_down(ax, ay, az, dt)
        self.stalled = not self.on_ground and self.alpha > self._alpha_cl_max

    def _aero_and_thrust(self, dt: float, cmd: FixedWingCommand, r: tuple[float, ...]) -> tuple[float, float, float]:
        """Body-frame force (N) of thrust, lift, drag and side force; updates airspeed, alpha, beta."""
        p = self.params
        rn, re, rd = self.vx - self._wind[0], self.vy - self._wind[1], self.vz - self._wind[2]
        u = r[0] * rn + r[3] * re + r[6] * rd  # R^T (v - wind)
        v = r[1] * rn + r[4] * re + r[7] * rd
        w = r[2] * rn + r[5] * re + r[8] * rd
        va = math.sqrt(u * u + v * v + w * w)
        self.airspeed = va
        if va > 0.5:
            self.alpha = math.atan2(w, u)
            self.beta = math.asin(max(-1.0, min(1.0, v / va)))
        else:
            self.alpha = self.beta = 0.0
        throttle = 0.0 if cmd.throttle < 0.0 else (1.0 if cmd.throttle > 1.0 else cmd.throttle)
        target = p.thrust_max_n * throttle * max(0.0, 1.0 - u / p.prop_speed_mps)
        self.thrust += dt / (p.throttle_tau_s + dt) * (target - self.thrust)
        qs = 0.5 * p.air_density_kgm3 * va * va * p.wing_area_m2
        cl, cd = lift_drag_coefficients(self.alpha, p)
        lift, drag = qs * cl, qs * cd
        ca, sa = math.cos(self.alpha), math.sin(self.alpha)
        # drag opposes the air-relative velocity (all three body components), lift is normal to it in x-z
        fx = self.thrust + lift * sa - drag * (u / va if va > 0.5 else 0.0)
        fy = qs * p.cy_beta_per_rad * self.beta - drag * (v / va if va > 0.5 else 0.0)
        fz = -lift * ca - drag * (w / va if va > 0.5 else 0.0)
        return fx, fy, fz

    def _rotate(self, dt: float, cmd: FixedWingCommand) -> None:
        """Body rates: lagged commanded rates, weathercock yaw, stall nose-drop; then the quaternion."""
        p = self.params
        q_ratio = min(1.5, (self.airspeed / p.reference_airspeed_mps) ** 2)
        k = q_ratio * dt / p.rate_tau_s
        lim = p.rate_max_rad_s
        pc = max(-lim[0], min(lim[0], cmd.roll_rate))
        qc = max(-lim[1], min(lim[1], cmd.pitch_rate))
        rc = max(-lim[2], min(lim[2], cmd.yaw_rate))
        self.wx += k * (pc - self.wx)
        pitch_down = max(0.0, self.alpha - p.alpha_stall_rad) * p.stall_pitch_down_per_s2
        self.wy += k * (qc - self.wy) - q_ratio * pitch_down * dt
        self.wz += k * (rc - self.wz) + q_ratio * p.weathercock_per_s2 * self.beta * dt
        self._integrate_attitude(dt)

    def _roll_on_ground(self, dt: float, cmd: FixedWingCommand, ax: float, ay: float, az: float) -> None:
        """On the runway: along the heading only, rolling resistance and brakes; no roll, nose up only."""
        p = self.params
        _, pitch, yaw = self.euler()
        cy, sy = math.cos(yaw), math.sin(yaw)
        speed = self.vx * cy + self.vy * sy
        along = ax * cy + ay * sy
        resist = p.rolling_friction * az + p.brake_decel_mps2 * max(0.0, min(1.0, cmd.brake))
        if speed > 0.0 or along > resist:  # rolling, or thrust overcomes the friction
            along -= resist
            if speed + along * dt < 0.0:  # friction stops the roll within this step
                along = -speed / dt
        else:  # held (or stopped, if the wind pushed it back)
            along = -speed / dt
        speed += along * dt
        self.vx, self.vy, self.vz = speed * cy, speed * sy, 0.0
        self.px += self.vx * dt
        self.py += self.vy * dt
        self.pz = 0.0
        self._specific_force(along * cy, along * sy, 0.0)
        q_ratio = min(1.5, (self.airspeed / p.reference_airspeed_mps) ** 2)
        self.wx = 0.0
        self.wy += q_ratio * dt / p.rate_tau_s * (cmd.pitch_rate - self.wy)
        if (pitch <= 0.0 and self.wy < 0.0) or (pitch >= p.ground_pitch_max_rad and self.wy > 0.0):
            self.wy = 0.0
        self.wz = max(-0.5, min(0.5, cmd.yaw_rate)) if speed > 0.5 else 0.0  # nosewheel steering
        self._set_euler(0.0, max(0.0, min(p.ground_pitch_max_rad, pitch + self.wy * dt)), yaw + self.wz * dt)

    def _touch_down(self, ax: float, ay: float, az: float, dt: float) -> None:
        """Wheels on the runway: the descent stops within this step, wings level, velocity along the heading."""
        p = self.params
        self.touchdown_sink_mps = self.vz
        az_step = az - self.vz / dt
        _, pitch, yaw = self.euler()
        self.pz = 0.0
        self.vz = 0.0
        speed = self.vx * math.cos(yaw) + self.vy * math.sin(yaw)
        self.vx, self.vy = speed * math.cos(yaw), speed * math.sin(yaw)
        self.on_ground = True
        self.wx = self.wy = self.wz = 0.0
        self._set_euler(0.0, max(0.0, min(p.ground_pitch_max_rad, pitch)), yaw)
        self._specific_force(ax, ay, az_step)

    def _set_euler(self, roll: float, pitch: float, yaw: float) -> None:
        self.qw, self.qx, self.qy, self.qz = (float(v) for v in quat_from_euler(roll, pitch, yaw))
