"""The rigid-body truth state both airframe models (:class:`sitl.dynamics.QuadrotorDynamics`,
:class:`sitl.fixedwing.FixedWingDynamics`) integrate, with its snapshots and the integration
steps they share (plain floats, no I/O).

Frames follow :mod:`companion.frames`: position and velocity NED (m, m/s) from the simulation
anchor, body FRD, quaternion ``[w, x, y, z]`` body->NED. The ground is the plane NED z = 0.
"""

from __future__ import annotations

import math

import numpy as np

from companion.frames import GRAVITY_MPS2


class RigidBody:
    """Truth state: ``px py pz`` NED position m, ``vx vy vz`` NED velocity m/s (ground-relative),
    ``qw qx qy qz`` attitude, ``wx wy wz`` body angular rate rad/s (FRD), ``fx fy fz`` body specific
    force m/s^2 (what an ideal accelerometer reads). Read them, do not write: the airframe model
    integrates them.

    It starts at rest at ``start_ned`` (m, lifted to the ground if below it), level, heading
    ``start_yaw_rad`` (rad).
    """

    def __init__(self, start_ned: tuple[float, float, float], start_yaw_rad: float) -> None:
        self.px, self.py, self.pz = (float(v) for v in start_ned)
        self.pz = min(self.pz, 0.0)
        self.vx = self.vy = self.vz = 0.0
        self.qw, self.qx, self.qy, self.qz = math.cos(start_yaw_rad / 2), 0.0, 0.0, math.sin(start_yaw_rad / 2)
        self.wx = self.wy = self.wz = 0.0
        self.fx, self.fy, self.fz = 0.0, 0.0, -GRAVITY_MPS2

    # ------------------------------------------------------------------ snapshots
    @property
    def position(self) -> np.ndarray:
        """NED position, m."""
        return np.array([self.px, self.py, self.pz])

    @property
    def velocity(self) -> np.ndarray:
        """NED velocity (ground-relative), m/s."""
        return np.array([self.vx, self.vy, self.vz])

    @property
    def quaternion(self) -> np.ndarray:
        """Attitude quaternion [w, x, y, z], body FRD -> NED."""
        return np.array([self.qw, self.qx, self.qy, self.qz])

    def euler(self) -> tuple[float, float, float]:
        """ZYX Euler angles (roll, pitch, yaw), rad."""
        w, x, y, z = self.qw, self.qx, self.qy, self.qz
        roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
        pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
        yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        return roll, pitch, yaw

    # ------------------------------------------------------------------ integration
    def _fly(self, ax: float, ay: float, az: float, dt: float) -> None:
        """Free flight under the NED acceleration (m/s^2) for ``dt`` s: semi-implicit Euler on
        velocity then position; the accelerometer reads it."""
        self.vx += ax * dt
        self.vy += ay * dt
        self.vz += az * dt
        self.px += self.vx * dt
        self.py += self.vy * dt
        self.pz += self.vz * dt
        self._specific_force(ax, ay, az)

    def _integrate_attitude(self, dt: float) -> None:
        """Quaternion kinematics: turn the attitude at the body rates for ``dt`` s, renormalised."""
        wx, wy, wz = self.wx, self.wy, self.wz
        h = 0.5 * dt
        qw, qx, qy, qz = self.qw, self.qx, self.qy, self.qz
        nw = qw - h * (qx * wx + qy * wy + qz * wz)
        nx = qx + h * (qw * wx + qy * wz - qz * wy)
        ny = qy + h * (qw * wy - qx * wz + qz * wx)
        nz = qz + h * (qw * wz + qx * wy - qy * wx)
        inv = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
        self.qw, self.qx, self.qy, self.qz = nw * inv, nx * inv, ny * inv, nz * inv

    def _rotation(self) -> tuple[float, ...]:
        """Body->NED rotation matrix, row-major."""
        w, x, y, z = self.qw, self.qx, self.qy, self.qz
        return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))

    def _specific_force(self, ax: float, ay: float, az: float) -> None:
        """Body-frame specific force (acceleration minus gravity, m/s^2) of the NED acceleration."""
        r = self._rotation()
        nx, ny, nz = ax, ay, az - GRAVITY_MPS2
        self.fx = r[0] * nx + r[3] * ny + r[6] * nz
        self.fy = r[1] * nx + r[4] * ny + r[7] * nz
        self.fz = r[2] * nx + r[5] * ny + r[8] * nz
