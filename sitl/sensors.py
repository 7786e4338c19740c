"""Simulated autopilot sensors: IMU, barometer, compass, GPS and airspeed (seeded noise, no I/O).

Each sensor reads the truth of :class:`sitl.dynamics.QuadrotorDynamics` and adds the errors
that make the autopilot's own estimate differ from the truth. Units: m, m/s, m/s^2, rad,
rad/s; vectors in body FRD (IMU) or NED (GPS velocity); geodetic in degrees and m AMSL.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.frames import geodetic_from_ned, wrap_pi
from sitl.dynamics import GaussianStream

GPS_NO_FIX_ERROR_M = 655.35  # MAVLink's UINT16_MAX cm: "unknown" eph/epv


@dataclass
class ImuSample:
    """One IMU reading as the autopilot sees it: specific force m/s^2 and rate rad/s, body FRD."""

    t: float
    accel_body: np.ndarray
    gyro_body: np.ndarray


@dataclass
class GpsSample:
    """One GPS fix: geodetic position, NED velocity m/s, accuracies m; fix_type 0 = no GPS, 3 = 3D."""

    t: float
    fix_type: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    vel_ned: np.ndarray
    eph_m: float
    epv_m: float
    satellites: int


@dataclass(frozen=True)
class ImuErrors:
    """IMU error model: per-sample white noise, initial bias (1 sigma) and bias random walk."""

    accel_noise_mps2: float = 0.03
    gyro_noise_rad_s: float = 0.0015
    accel_bias_mps2: float = 0.02
    gyro_bias_rad_s: float = 0.001
    accel_bias_walk_mps2_per_sqrt_s: float = 2e-4
    gyro_bias_walk_rad_s_per_sqrt_s: float = 2e-5


# ArduPilot reports its IMU through low-pass filters (INS_ACCEL_FILTER, INS_GYRO_FILTER,
# 20 Hz by default), so a 50 Hz HIGHRES_IMU stream does not alias a touchdown impulse.
REPORT_FILTER_HZ = 20.0


class Imu:
    """400 Hz accelerometer + gyro. Latest raw reading in floats ``ax ay az`` (m/s^2), ``gx gy gz``
    (rad/s), which the flight controller and estimator use; :meth:`snapshot` gives the
    20 Hz low-passed values the autopilot reports over MAVLink."""

    def __init__(self, noise: GaussianStream, errors: ImuErrors | None = None) -> None:
        self._noise = noise
        self.errors = e = errors or ImuErrors()
        draw = noise.draw
        self._accel_bias = [e.accel_bias_mps2 * draw() for _ in range(3)]
        self._gyro_bias = [e.gyro_bias_rad_s * draw() for _ in range(3)]
        self.ax, self.ay, self.az = 0.0, 0.0, 0.0
        self.gx, self.gy, self.gz = 0.0, 0.0, 0.0
        self._reported: list[float] | None = None  # low-passed [ax, ay, az, gx, gy, gz]

    def sample(self, dt: float, specific_force: tuple[float, float, float], rate: tuple[float, float, float]) -> None:
        """Read the true body specific force (m/s^2) and angular rate (rad/s) after ``dt`` seconds."""
        e, draw = self.errors, self._noise.draw
        ab, gb = self._accel_bias, self._gyro_bias
        sa = e.accel_bias_walk_mps2_per_sqrt_s * math.sqrt(dt)
        sg = e.gyro_bias_walk_rad_s_per_sqrt_s * math.sqrt(dt)
        for i in range(3):
            ab[i] += sa * draw()
            gb[i] += sg * draw()
        na, ng = e.accel_noise_mps2, e.gyro_noise_rad_s
        self.ax = specific_force[0] + ab[0] + na * draw()
        self.ay = specific_force[1] + ab[1] + na * draw()
        self.az = specific_force[2] + ab[2] + na * draw()
        self.gx = rate[0] + gb[0] + ng * draw()
        self.gy = rate[1] + gb[1] + ng * draw()
        self.gz = rate[2] + gb[2] + ng * draw()
        raw = [self.ax, self.ay, self.az, self.gx, self.gy, self.gz]
        if self._reported is None:
            self._reported = raw
        else:
            k = dt / (dt + 1.0 / (2 * math.pi * REPORT_FILTER_HZ))
            self._reported = [f + k * (r - f) for f, r in zip(self._reported, raw)]

    def snapshot(self, t: float) -> ImuSample:
        """The reported (20 Hz low-passed) reading as an :class:`ImuSample` at simulation time ``t``."""
        f = self._reported or [self.ax, self.ay, self.az, self.gx, self.gy, self.gz]
        return ImuSample(t, np.array(f[:3]), np.array(f[3:]))


class Barometer:
    """Pressure altitude, m AMSL: truth + white noise + slowly drifting offset (random walk)."""

    def __init__(self, noise: GaussianStream, *, noise_m: float = 0.08, drift_m_per_sqrt_s: float = 0.005) -> None:
        self._noise = noise
        self.noise_m = noise_m
        self.drift_m_per_sqrt_s = drift_m_per_sqrt_s
        self._drift = 0.0
        self.alt_m = 0.0

    def sample(self, dt: float, true_alt_m: float) -> float:
        """Read the altitude (m AMSL) ``dt`` seconds after the previous reading."""
        self._drift += self.drift_m_per_sqrt_s * math.sqrt(dt) * self._noise.draw()
        self.alt_m = true_alt_m + self._drift + self.noise_m * self._noise.draw()
        return self.alt_m


class Compass:
    """Magnetic heading, rad from north: truth yaw + fixed bias + white noise."""

    def __init__(self, noise: GaussianStream, *, bias_std_rad: float = math.radians(1.0),
                 noise_rad: float = math.radians(0.5)) -> None:
        self._noise = noise
        self.bias_rad = bias_std_rad * noise.draw()
        self.noise_rad = noise_rad

    def sample(self, true_yaw_rad: float) -> float:
        """Read the heading, rad in [-pi, pi)."""
        return wrap_pi(true_yaw_rad + self.bias_rad + self.noise_rad * self._noise.draw())


class Gps:
    """5 Hz GPS receiver referenced to the simulation anchor ``(lat deg, lon deg, alt m)``.

    Position error is a first-order Gauss-Markov process (about ``horizontal_std_m`` per
    horizontal axis, ``vertical_std_m`` vertically, correlation time ``tau_s``); velocity error
    is white. With ``enabled`` False (GPS absent or denied) every fix has fix_type 0.
    """

    RATE_HZ = 5.0

    def __init__(self, noise: GaussianStream, anchor: tuple[float, float, float], *, enabled: bool = True,
                 horizontal_std_m: float = 0.3, vertical_std_m: float = 0.5, tau_s: float = 10.0,
                 velocity_noise_mps: float = 0.05) -> None:
        self._noise = noise
        self.anchor = anchor
        self.enabled = enabled
        self._std = (horizontal_std_m, horizontal_std_m, vertical_std_m)
        self._tau_s = tau_s
        self._velocity_noise = velocity_noise_mps
        self._error = [s * noise.draw() for s in self._std]

    def sample(self, t: float, dt: float, pos_ned: tuple[float, float, float],
               vel_ned: tuple[float, float, float]) -> GpsSample:
        """A fix of the true NED position (m) and velocity (m/s), ``dt`` s after the previous one."""
        draw = self._noise.draw
        decay = dt / self._tau_s
        for i in range(3):
            self._error[i] += -self._error[i] * decay + self._std[i] * math.sqrt(2.0 * decay) * draw()
        if not self.enabled:
            return GpsSample(t, 0, 0.0, 0.0, 0.0, np.zeros(3), GPS_NO_FIX_ERROR_M, GPS_NO_FIX_ERROR_M, 0)
        noisy = np.array([pos_ned[i] + self._error[i] for i in range(3)])
        lat, lon, alt = geodetic_from_ned(noisy, self.anchor)
        vel = np.array([v + self._velocity_noise * draw() for v in vel_ned])
        return GpsSample(t, 3, lat, lon, alt, vel, 2.0 * self._std[0], 2.0 * self._std[2], 14)


class Airspeed:
    """Pitot airspeed, m/s: the true airspeed + a fixed calibration error + white noise, never negative."""

    def __init__(self, noise: GaussianStream, *, bias_std_mps: float = 0.3, noise_mps: float = 0.2) -> None:
        self._noise = noise
        self.bias_mps = bias_std_mps * noise.draw()
        self.noise_mps = noise_mps
        self.airspeed_mps = 0.0

    def sample(self, true_airspeed_mps: float) -> float:
        """Read the airspeed, m/s."""
        self.airspeed_mps = max(0.0, true_airspeed_mps + self.bias_mps + self.noise_mps * self._noise.draw())
        return self.airspeed_mps
