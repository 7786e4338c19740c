"""What every built-in simulated vehicle shares: its sensors, the autopilot's own estimator, the
truth and estimate snapshots, and the MAVLink-facing commands; :class:`sitl.copter.SimulatedCopter`
and :class:`sitl.plane.SimulatedPlane` add their airframe and flight controller.

Plain numpy/floats: no I/O, no asyncio, no MAVLink. Frames follow :mod:`companion.frames`:
truth positions are NED metres from the simulation anchor ``home`` (lat deg, lon deg,
alt m AMSL); the estimate is NED metres from the EKF origin the companion sets. Times are
simulation seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, TypedDict

import numpy as np

from companion.frames import geodetic_from_ned, ned_from_geodetic, quat_from_euler
from sitl.dynamics import GaussianStream
from sitl.estimator import Estimator, StatusQueue
from sitl.sensors import Barometer, Compass, Gps, GpsSample, Imu, ImuSample

__all__ = ["EstimateState", "GpsSample", "ImuSample", "SensorOptions", "SimulatedVehicle", "TruthState"]


@dataclass
class TruthState:
    """Ground truth at simulation time ``t`` (s).

    pos_ned m and vel_ned m/s from the simulation anchor, quat [w, x, y, z] body->NED,
    euler (roll, pitch, yaw) rad, gyro_body true angular rate rad/s (FRD), accel_body true
    specific force m/s^2 (FRD), lat/lon deg and alt m AMSL of pos_ned.
    """

    t: float
    pos_ned: np.ndarray
    vel_ned: np.ndarray
    quat: np.ndarray
    euler: tuple[float, float, float]
    gyro_body: np.ndarray
    accel_body: np.ndarray
    lat_deg: float
    lon_deg: float
    alt_m: float


@dataclass
class EstimateState:
    """The autopilot's own estimate at ``t`` (s), in the EKF's NED frame (m, m/s, rad).

    ``flags`` are MAV_ESTIMATOR_STATUS_FLAGS; variances in m^2 and (m/s)^2;
    ``rejected_ext_nav`` counts gated-out vision samples.
    """

    t: float
    pos_valid: bool
    pos_ned: np.ndarray
    vel_ned: np.ndarray
    euler: tuple[float, float, float]
    quat: np.ndarray
    flags: int
    ext_nav_in_use: bool
    pos_variance_m2: float
    vel_variance: float
    height_variance_m2: float
    rejected_ext_nav: int


def position_error_from_pose_covariance(covariance: np.ndarray | None) -> float | None:
    """1-sigma position error (m) from VISION_POSITION_ESTIMATE's 21-element covariance, or None.

    Like ArduPilot, only the x, y, z variances (elements 0, 6, 11) are used, collapsed into one
    error; None (unknown) when absent, NaN or negative.
    """
    return _collapse(covariance, (0, 6, 11))


def velocity_error_from_covariance(covariance: np.ndarray | None) -> float | None:
    """1-sigma velocity error (m/s) from VISION_SPEED_ESTIMATE's 9-element (3x3 row-major) covariance."""
    return _collapse(covariance, (0, 4, 8))


def _collapse(covariance: np.ndarray | None, diagonal: tuple[int, int, int]) -> float | None:
    if covariance is None or len(covariance) <= diagonal[-1]:
        return None
    variances = [float(covariance[i]) for i in diagonal]
    if not all(math.isfinite(v) and v >= 0.0 for v in variances):
        return None
    return math.sqrt(sum(variances) / 3.0)


class SensorOptions(TypedDict, total=False):
    """The sensor and estimator keywords every simulated vehicle takes and hands to
    :class:`SimulatedVehicle` (defaults there): ``gps_enabled``; ``vision_delay_s`` plays
    VISO_DELAY_MS (s, subtracted from each vision sample's ``t_capture``); ``viso_pos_noise_m`` /
    ``viso_vel_noise_mps`` are the measurement-noise floors VISO_POS_M_NSE (m) / VISO_VEL_M_NSE (m/s).
    """

    gps_enabled: bool
    vision_delay_s: float
    viso_pos_noise_m: float
    viso_vel_noise_mps: float


class SimulatedVehicle:
    """Sensors, estimator and commands around an airframe ``_dyn`` and a flight controller ``_fc``
    that a subclass builds in its ``__init__`` (after calling this one) and steps in :meth:`_substep`.

    ``_dyn`` is a :class:`sitl.rigid_body.RigidBody` (``px .. pz``, ``vx .. vz``, ``wx .. wz``,
    ``fx .. fz``, ``position``, ``velocity``, ``quaternion``, ``euler()``); ``_fc`` a
    :class:`sitl.flight_controller_base.FlightControllerBase` (``mode``, ``mode_name``, ``armed``,
    ``landed``, ``home_ned``, ``home_locked``, ``nonfinite_rejected``, ``set_mode``, ``arm``,
    ``disarm``, ``takeoff``) with a ``set_position_target``.

    ``seed`` seeds ``stream_count`` noise streams ``_streams``: 0 for the airframe, 1-5 for the
    sensors and the estimator here, the rest for the subclass. ``home`` is the geodetic anchor of
    the truth NED frame (lat deg, lon deg, alt m AMSL; the ground is at its altitude).
    ``position_source`` is EK3_SRC1_POSXY: "extnav" (vision from the companion; yaw too) or "gps";
    ``start_yaw_rad`` the heading the estimator starts from; the rest are :class:`SensorOptions`.

    For the MAVLink process a subclass also tells ``MAV_TYPE`` (its HEARTBEAT type) and the
    properties ``landing`` (landing now), ``airspeed_mps`` and ``throttle_percent`` (VFR_HUD).
    """

    MAV_TYPE: int

    PHYSICS_HZ = 400
    BARO_DIVIDER = 8  # 50 Hz
    COMPASS_DIVIDER = 8  # 50 Hz
    GPS_DIVIDER = 80  # 5 Hz

    def __init__(self, *, seed: int, stream_count: int, home: tuple[float, float, float], position_source: str,
                 start_yaw_rad: float, gps_enabled: bool = True, vision_delay_s: float = 0.01,
                 viso_pos_noise_m: float = 0.2, viso_vel_noise_mps: float = 0.1) -> None:
        self._streams = streams = [GaussianStream(s) for s in np.random.SeedSequence(seed).spawn(stream_count)]
        self._anchor = (float(home[0]), float(home[1]), float(home[2]))
        self._dt = 1.0 / self.PHYSICS_HZ
        self._step_count = 0
        self._status = StatusQueue()
        self._imu = Imu(streams[1])
        self._baro = Barometer(streams[2])
        self._compass = Compass(streams[3])
        self._gps = Gps(streams[4], self._anchor, enabled=gps_enabled)
        self._gps_sample: GpsSample | None = None
        self._est = Estimator(status=self._status, noise=streams[5], position_source=position_source,
                              rate_hz=self.PHYSICS_HZ, start_yaw_rad=start_yaw_rad,
                              viso_pos_noise_m=viso_pos_noise_m, viso_vel_noise_mps=viso_vel_noise_mps,
                              vision_delay_s=vision_delay_s)
        self._pending_home: tuple[float, float, float] | None = None
        self._nonfinite = 0

    def _attach(self, dyn: Any, fc: Any) -> None:
        """Take the subclass's airframe and flight controller; the barometer reads its first altitude."""
        self._dyn = dyn
        self._fc = fc
        self._baro.sample(0.0, self._true_alt())

    # ------------------------------------------------------------------ stepping
    @property
    def t(self) -> float:
        """Simulation time, s."""
        return self._step_count / self.PHYSICS_HZ

    def step(self, dt: float) -> None:
        """Advance by ``dt`` seconds (a multiple of 1/PHYSICS_HZ) in 400 Hz substeps."""
        n = round(dt * self.PHYSICS_HZ)
        if n < 0 or abs(n - dt * self.PHYSICS_HZ) > 1e-6:
            raise ValueError(f"dt={dt} is not a multiple of 1/{self.PHYSICS_HZ} s")
        for _ in range(n):
            self._substep()

    def _substep(self) -> None:
        """One physics step: the subclass's controller and airframe, then :meth:`_sense`."""
        raise NotImplementedError

    def _sense(self) -> None:
        """After the airframe moved one physics step: IMU, estimator prediction, baro, compass, GPS."""
        dt, dyn, imu, est = self._dt, self._dyn, self._imu, self._est
        imu.sample(dt, (dyn.fx, dyn.fy, dyn.fz), (dyn.wx, dyn.wy, dyn.wz))
        est.predict(dt, (imu.ax, imu.ay, imu.az), dyn.euler())
        self._step_count = k = self._step_count + 1
        if k % self.BARO_DIVIDER == 0:
            est.fuse_baro(self._baro.sample(self.BARO_DIVIDER * dt, self._true_alt()))
        if k % self.COMPASS_DIVIDER == 0:
            est.fuse_compass(self._compass.sample(dyn.euler()[2]))
        if k % self.GPS_DIVIDER == 0:
            self._gps_sample = self._gps.sample(self.t, self.GPS_DIVIDER * dt, (dyn.px, dyn.py, dyn.pz),
                                                (dyn.vx, dyn.vy, dyn.vz))
            est.fuse_gps(self._gps_sample)

    def _true_alt(self) -> float:
        return self._anchor[2] - self._dyn.pz

    # ------------------------------------------------------------------ observation
    @property
    def truth(self) -> TruthState:
        """Ground truth now."""
        d = self._dyn
        pos = d.position
        lat, lon, alt = geodetic_from_ned(pos, self._anchor)
        return TruthState(self.t, pos, d.velocity, d.quaternion, d.euler(), np.array([d.wx, d.wy, d.wz]),
                          np.array([d.fx, d.fy, d.fz]), lat, lon, alt)

    @property
    def imu(self) -> ImuSample:
        """Latest IMU reading (noisy, biased), body FRD."""
        return self._imu.snapshot(self.t)

    @property
    def gps(self) -> GpsSample | None:
        """Latest 5 Hz GPS fix (fix_type 0 when GPS is disabled), None before the first."""
        return self._gps_sample

    @property
    def baro_alt_m(self) -> float:
        """Latest barometric altitude, m AMSL (truth + noise + drift)."""
        return self._baro.alt_m

    @property
    def estimate(self) -> EstimateState:
        """The autopilot's own estimate now."""
        est = self._est
        n, e, d = est.axes
        a = est.ahrs
        euler = (a.roll, a.pitch, a.yaw)
        return EstimateState(self.t, est.pos_valid, np.array([n.p, e.p, d.p]), np.array([n.v, e.v, d.v]), euler,
                             quat_from_euler(*euler), est.flags, est.ext_nav_in_use, est.pos_variance_m2,
                             est.vel_variance, est.height_variance_m2, est.rejected_ext_nav)

    @property
    def mode(self) -> int:
        """ArduPilot Copter custom_mode number."""
        return self._fc.mode

    @property
    def mode_name(self) -> str:
        """ArduPilot Copter mode name."""
        return self._fc.mode_name

    @property
    def guided(self) -> bool:
        """In GUIDED (position targets are flown)."""
        return self._fc.guided

    @property
    def armed(self) -> bool:
        """Motors armed."""
        return self._fc.armed

    @property
    def landed(self) -> bool:
        """The autopilot's land detector (not the truth contact)."""
        return self._fc.landed

    @property
    def origin(self) -> tuple[float, float, float] | None:
        """EKF origin (lat deg, lon deg, alt m AMSL) or None."""
        return self._est.origin

    @property
    def home_position(self) -> tuple[float, float, float] | None:
        """Home (lat deg, lon deg, alt m AMSL) or None."""
        home, origin = self._fc.home_ned, self._est.origin
        if home is None or origin is None:
            return self._pending_home
        return geodetic_from_ned(np.array(home), origin)

    @property
    def nonfinite_rejected(self) -> int:
        """Commands or samples refused because a used field was NaN or infinite."""
        return self._nonfinite + self._est.nonfinite_rejected + self._fc.nonfinite_rejected

    def drain_statustext(self) -> list[tuple[int, str]]:
        """(MAV_SEVERITY, text) messages queued since the last call."""
        return self._status.drain()

    # ------------------------------------------------------------------ commands
    def set_mode(self, custom_mode: int) -> tuple[bool, str]:
        """Change flight mode; (accepted, reason if refused)."""
        return self._fc.set_mode(int(custom_mode))

    def arm(self, force: bool = False) -> tuple[bool, str]:
        """Arm (ArduPilot-like checks unless ``force``)."""
        return self._fc.arm(force)

    def disarm(self, force: bool = False) -> tuple[bool, str]:
        """Disarm (refused in flight unless ``force``)."""
        return self._fc.disarm(force)

    def set_tilt_fault(self, roll_rad: float, pitch_rad: float) -> None:
        """Make the autopilot's attitude estimate wrong by (roll, pitch) rad (0, 0: healthy); it flies on it."""
        self._est.ahrs.tilt_fault_rad = (float(roll_rad), float(pitch_rad))

    def takeoff(self, altitude_m: float) -> tuple[bool, str]:
        """Take off to ``altitude_m`` above home; GUIDED and armed only."""
        return self._fc.takeoff(float(altitude_m))

    def set_origin(self, lat: float, lon: float, alt: float) -> bool:
        """Set the EKF origin (deg, deg, m AMSL); only the first valid call is accepted."""
        if not self._est.set_origin(float(lat), float(lon), float(alt)):
            return False
        if self._pending_home is not None:
            self.set_home(*self._pending_home)
        return True

    def set_home(self, lat: float, lon: float, alt: float) -> None:
        """Set home (deg, deg, m AMSL); kept until the origin exists if there is none yet."""
        lat, lon, alt = float(lat), float(lon), float(alt)
        if not all(math.isfinite(v) for v in (lat, lon, alt)):
            self._nonfinite += 1
            return
        origin = self._est.origin
        if origin is None:
            self._pending_home = (lat, lon, alt)
            return
        self._pending_home = None
        ned = ned_from_geodetic(lat, lon, alt, origin)
        self._fc.home_ned = (float(ned[0]), float(ned[1]), float(ned[2]))
        self._fc.home_locked = True

    def set_gps_enabled(self, enabled: bool) -> None:
        """Switch the GPS receiver on or off (off = fix_type 0, e.g. jamming or denial)."""
        self._gps.enabled = bool(enabled)

    def set_position_target(self, frame: int, type_mask: int, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
                            yaw: float, yaw_rate: float) -> bool:
        """SET_POSITION_TARGET_LOCAL_NED; False if ignored (not GUIDED, unsupported frame/mask, NaN)."""
        return self._fc.set_position_target(int(frame), int(type_mask), pos, vel, acc, float(yaw), float(yaw_rate))

    def vision_position(self, t_capture: float, pos_ned: np.ndarray, euler: tuple[float, float, float],
                        covariance: np.ndarray | None, reset_counter: int) -> None:
        """VISION_POSITION_ESTIMATE: NED position m, (roll, pitch, yaw) rad, captured at ``t_capture`` s."""
        pos = (float(pos_ned[0]), float(pos_ned[1]), float(pos_ned[2]))
        if not all(math.isfinite(float(a)) for a in euler[:2]):
            self._nonfinite += 1
            return
        self._est.fuse_vision_position(float(t_capture), pos, float(euler[2]),
                                       position_error_from_pose_covariance(covariance), int(reset_counter))

    def vision_speed(self, t_capture: float, vel_ned: np.ndarray, covariance: np.ndarray | None,
                     reset_counter: int) -> None:
        """VISION_SPEED_ESTIMATE: NED velocity m/s captured at ``t_capture`` s."""
        del reset_counter  # ArduPilot ignores it for velocity; position resets handle frame jumps
        vel = (float(vel_ned[0]), float(vel_ned[1]), float(vel_ned[2]))
        self._est.fuse_vision_velocity(float(t_capture), vel, velocity_error_from_covariance(covariance))
