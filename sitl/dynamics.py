"""Rigid-body quadrotor truth model for the built-in SITL (plain floats, no I/O).

Frames follow :mod:`companion.frames`: positions and velocities in NED (m, m/s) relative to the
simulation anchor, body FRD, quaternion ``[w, x, y, z]`` body->NED. The floor is the plane
NED z = 0; flying means z < 0.

Motor layout (ArduPilot quad X, FRD body): motor 1 front-right and motor 2 back-left spin
counter-clockwise seen from above, motors 3 front-left and 4 back-right clockwise. A motor
command is the requested thrust fraction in [0, 1]; the rotor speed follows
``max_speed * sqrt(command)`` with a first-order lag, and thrust and yaw torque go with the
square of the rotor speed.

Everything runs on plain Python floats because one 400 Hz step must cost only a few tens of
microseconds; numpy arrays are built only when a caller asks for a snapshot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.frames import GRAVITY_MPS2
from sitl.rigid_body import RigidBody


class GaussianStream:
    """Seeded standard-normal numbers, drawn from numpy in blocks and handed out as floats."""

    BLOCK = 4096

    def __init__(self, seed: np.random.SeedSequence | int) -> None:
        self._rng = np.random.default_rng(seed)
        self._buffer: list[float] = []

    def draw(self) -> float:
        """One N(0, 1) sample."""
        if not self._buffer:
            self._buffer = self._rng.standard_normal(self.BLOCK).tolist()
        return self._buffer.pop()


@dataclass(frozen=True)
class AirframeParams:
    """Physical constants of the simulated quadrotor (SI units)."""

    mass_kg: float = 1.5
    inertia_kgm2: tuple[float, float, float] = (0.015, 0.015, 0.028)
    arm_length_m: float = 0.225  # motor distance from the centre
    motor_tau_s: float = 0.03  # first-order rotor-speed lag
    max_thrust_per_motor_n: float = 8.0
    max_rotor_speed_rad_s: float = 1100.0
    yaw_torque_per_thrust_m: float = 0.016  # rotor drag torque / thrust (k_Q / k_T)
    drag_linear_n_per_mps: float = 0.25
    drag_quadratic_n_per_mps2: float = 0.04
    angular_drag_nm_per_rad_s: float = 0.002
    ground_friction: float = 0.8  # Coulomb coefficient of the landing gear on the floor

    @property
    def arm_xy_m(self) -> float:
        """Forward/right offset of each motor from the centre (X frame at 45 degrees), m."""
        return self.arm_length_m / math.sqrt(2.0)

    @property
    def hover_thrust_n(self) -> float:
        """Total thrust that balances gravity, N."""
        return self.mass_kg * GRAVITY_MPS2


@dataclass
class WindConfig:
    """Wind = velocity of the air mass (NED m/s, i.e. the direction it blows towards) plus an
    Ornstein-Uhlenbeck gust per axis with standard deviation gust_std_mps and correlation time
    gust_tau_s."""

    mean_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_std_mps: float = 0.3
    gust_tau_s: float = 2.0


class AirMass:
    """The air velocity of a :class:`WindConfig` (NED m/s): the mean plus the gusts, stepped in time.

    ``gust`` is the current gust per NED axis, m/s; :meth:`step` advances it by ``dt`` seconds
    and returns the air velocity (vn, ve, vd).
    """

    def __init__(self, wind: WindConfig, noise: GaussianStream) -> None:
        self.config = wind
        self._noise = noise
        self.gust = [0.0, 0.0, 0.0]

    def step(self, dt: float) -> tuple[float, float, float]:
        """Advance the Ornstein-Uhlenbeck gusts by ``dt`` s; the air velocity, NED m/s."""
        wind = self.config
        decay = dt / wind.gust_tau_s
        kick = wind.gust_std_mps * math.sqrt(2.0 * decay)
        g, draw = self.gust, self._noise.draw
        for i in range(3):
            g[i] += -g[i] * decay + kick * draw()
        mean = wind.mean_ned_mps
        return mean[0] + g[0], mean[1] + g[1], mean[2] + g[2]


class QuadrotorDynamics(RigidBody):
    """Truth state (:class:`sitl.rigid_body.RigidBody`) and its integration (semi-implicit Euler,
    renormalised quaternion) under the four motors; ``resting`` is True while the vehicle sits on
    the floor.
    """

    def __init__(
        self,
        *,
        noise: GaussianStream,
        airframe: AirframeParams | None = None,
        wind: WindConfig | None = None,
        start_ned: tuple[float, float, float] = (0.0, 0.0, 0.0),
        start_yaw_rad: float = 0.0,
    ) -> None:
        super().__init__(start_ned, start_yaw_rad)
        self.airframe = airframe or AirframeParams()
        self.air = AirMass(wind or WindConfig(), noise)
        a = self.airframe
        self._k_thrust = a.max_thrust_per_motor_n / a.max_rotor_speed_rad_s**2
        self.rotor_speed = [0.0, 0.0, 0.0, 0.0]
        self.resting = self.pz >= 0.0

    # ------------------------------------------------------------------ integration
    def step(self, dt: float, commands: list[float]) -> None:
        """Advance by ``dt`` seconds with motor thrust-fraction ``commands`` (4 values in [0, 1])."""
        thrust, tx, ty, tz = self._motors(dt, commands)
        ax, ay, az = self._linear_acceleration(dt, thrust)
        if self.resting and az >= 0.0:
            self._rest(ax, ay, az, dt)
        else:
            self.resting = False
            self._fly(ax, ay, az, dt)
            self._rotate(tx, ty, tz, dt)
            if self.pz >= 0.0:
                self._touch_down(ax, ay, az, dt)

    def _motors(self, dt: float, commands: list[float]) -> tuple[float, float, float, float]:
        """Rotor lag; returns total thrust N and body torques N m (roll, pitch, yaw)."""
        a = self.airframe
        alpha = dt / (a.motor_tau_s + dt)
        w = self.rotor_speed
        wmax, k = a.max_rotor_speed_rad_s, self._k_thrust
        f = [0.0, 0.0, 0.0, 0.0]
        for i in range(4):
            u = commands[i]
            u = 0.0 if u < 0.0 else (1.0 if u > 1.0 else u)
            w[i] += alpha * (wmax * math.sqrt(u) - w[i])
            f[i] = k * w[i] * w[i]
        d = a.arm_xy_m
        thrust = f[0] + f[1] + f[2] + f[3]
        tx = d * (-f[0] + f[1] + f[2] - f[3])
        ty = d * (f[0] - f[1] + f[2] - f[3])
        tz = a.yaw_torque_per_thrust_m * (f[0] + f[1] - f[2] - f[3])
        return thrust, tx, ty, tz

    def _linear_acceleration(self, dt: float, thrust: float) -> tuple[float, float, float]:
        """NED acceleration (m/s^2) from thrust, drag and gravity, ignoring the floor.

        Also caches the thrust direction and non-gravity force for the contact model and the
        accelerometer.
        """
        a = self.airframe
        w, x, y, z = self.qw, self.qx, self.qy, self.qz
        # third column of R (body z axis in NED); thrust acts along -z body
        r02 = 2 * (x * z + w * y)
        r12 = 2 * (y * z - w * x)
        r22 = 1 - 2 * (x * x + y * y)
        wn, we, wd = self.air.step(dt)
        rx = self.vx - wn
        ry = self.vy - we
        rz = self.vz - wd
        c = a.drag_linear_n_per_mps + a.drag_quadratic_n_per_mps2 * math.sqrt(rx * rx + ry * ry + rz * rz)
        inv_m = 1.0 / a.mass_kg
        self._force = (-thrust * r02 - c * rx, -thrust * r12 - c * ry, -thrust * r22 - c * rz)
        fx, fy, fz = self._force
        return fx * inv_m, fy * inv_m, fz * inv_m + GRAVITY_MPS2

    def _rest(self, ax: float, ay: float, az: float, dt: float) -> None:
        """On the floor: the normal force cancels az; static/kinetic friction on horizontal motion."""
        grip = self.airframe.ground_friction * az  # friction deceleration available, m/s^2
        push = math.hypot(ax, ay)
        speed = math.hypot(self.vx, self.vy)
        if speed == 0.0 and push <= grip:
            ax = ay = 0.0
        elif speed > 0.0:
            ax -= grip * self.vx / speed
            ay -= grip * self.vy / speed
            if speed <= grip * dt:  # friction stops the slide within this step
                ax = ay = 0.0
                self.vx = self.vy = 0.0
        else:
            ax -= grip * ax / push
            ay -= grip * ay / push
        self.vx += ax * dt
        self.vy += ay * dt
        self.vz = 0.0
        self.px += self.vx * dt
        self.py += self.vy * dt
        self.pz = 0.0
        self.wx = self.wy = self.wz = 0.0
        self._specific_force(ax, ay, 0.0)

    def _touch_down(self, ax: float, ay: float, az: float, dt: float) -> None:
        """Inelastic contact with the floor: no sinking, no bounce; the gear levels the body.

        The impact stops the descent within this step, so the accelerometer sees it.
        """
        az_step = az - self.vz / dt  # mean vertical acceleration over the step, velocity ending at 0
        self.pz = 0.0
        self.vz = 0.0
        self.resting = True
        self.wx = self.wy = self.wz = 0.0
        yaw = self.euler()[2]
        self.qw, self.qx, self.qy, self.qz = math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)
        self._specific_force(ax, ay, az_step)

    def _rotate(self, tx: float, ty: float, tz: float, dt: float) -> None:
        """Euler's rotation equations and quaternion kinematics."""
        a = self.airframe
        ixx, iyy, izz = a.inertia_kgm2
        c = a.angular_drag_nm_per_rad_s
        wx, wy, wz = self.wx, self.wy, self.wz
        wx += (tx - (izz - iyy) * wy * wz - c * wx) / ixx * dt
        wy += (ty - (ixx - izz) * wz * wx - c * wy) / iyy * dt
        wz += (tz - (iyy - ixx) * wx * wy - c * wz) / izz * dt
        self.wx, self.wy, self.wz = wx, wy, wz
        self._integrate_attitude(dt)
