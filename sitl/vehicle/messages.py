"""Outgoing messages of the simulated vehicle: one builder per MAVLink message it streams or answers with."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.frames import GRAVITY_MPS2, ned_from_geodetic, rotation_from_quat

FLIGHT_SW_VERSION = (4 << 24) | (5 << 16) | (7 << 8) | mav.FIRMWARE_VERSION_TYPE_OFFICIAL  # 4.5.7
CAPABILITIES = (
    mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mav.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
)
# Approximate geomagnetic field at the default home (Singapore), NED, gauss.
EARTH_FIELD_NED_GAUSS = np.array([0.40, 0.0, -0.12])
UINT16_MAX = 65535

MessageBuilder = Callable[[], "mav.MAVLink_message | None"]


def _clamp_int(value: float, lo: int, hi: int) -> int:
    return int(max(lo, min(hi, round(value))))


def _i16(value: float) -> int:
    return _clamp_int(value, -32768, 32767)


def _e7(deg: float) -> int:
    return int(round(deg * 1e7))


def _cdeg(rad: float) -> int:
    """Heading in centidegrees [0, 36000)."""
    return int(math.degrees(rad) % 360.0 * 100.0) % 36000


def _pressure_hpa(alt_m: float) -> float:
    """ISA static pressure (hPa) at a pressure altitude (m)."""
    return 1013.25 * (1.0 - 2.25577e-5 * alt_m) ** 5.25588


class MessagesMixin:
    """Part of :class:`sitl.vehicle.core.Vehicle` (which sets the attributes): message builders."""

    @property
    def _time_boot_ms(self) -> int:
        return self.t_us // 1000

    def _mag_body_gauss(self) -> np.ndarray:
        """Earth field seen by a body-fixed magnetometer at the true attitude (gauss, FRD)."""
        return rotation_from_quat(self.copter.truth.quat).T @ EARTH_FIELD_NED_GAUSS

    def _heartbeat(self) -> mav.MAVLink_message:
        c = self.copter
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_STABILIZE_ENABLED
        if c.guided:
            base |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        if c.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        status = mav.MAV_STATE_ACTIVE if c.armed else mav.MAV_STATE_STANDBY
        return mav.MAVLink_heartbeat_message(
            c.MAV_TYPE, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, base, c.mode, status, 3)

    def _attitude(self) -> mav.MAVLink_message:
        """Estimated attitude (rad) and IMU body rates (rad/s)."""
        roll, pitch, yaw = (float(v) for v in self.copter.estimate.euler)
        gx, gy, gz = (float(v) for v in self.copter.imu.gyro_body)
        return mav.MAVLink_attitude_message(self._time_boot_ms, roll, pitch, yaw, gx, gy, gz)

    def _attitude_quaternion(self) -> mav.MAVLink_message:
        q = [float(v) for v in self.copter.estimate.quat]
        gx, gy, gz = (float(v) for v in self.copter.imu.gyro_body)
        return mav.MAVLink_attitude_quaternion_message(self._time_boot_ms, *q, gx, gy, gz, [0.0] * 4)

    def _highres_imu(self) -> mav.MAVLink_message:
        """IMU in SI units (m/s^2, rad/s, gauss, hPa), body FRD."""
        imu, alt = self.copter.imu, float(self.copter.baro_alt_m)
        acc, gyro, mag = imu.accel_body, imu.gyro_body, self._mag_body_gauss()
        return mav.MAVLink_highres_imu_message(
            self.t_us, *(float(v) for v in acc), *(float(v) for v in gyro), *(float(v) for v in mag),
            _pressure_hpa(alt), 0.0, alt, 25.0, 0x1BFF, 0)

    def _scaled_pressure(self) -> mav.MAVLink_message:
        """The barometer as ArduPilot sends it: absolute pressure hPa, temperature cdegC."""
        return mav.MAVLink_scaled_pressure_message(self._time_boot_ms, _pressure_hpa(float(self.copter.baro_alt_m)),
                                                   0.0, 2500)

    def _scaled_imu_fields(self) -> list[int]:
        """ArduPilot's SCALED_IMU/RAW_IMU scaling: mG, mrad/s, mgauss."""
        imu = self.copter.imu
        acc = [_i16(float(v) * 1000.0 / GRAVITY_MPS2) for v in imu.accel_body]
        gyro = [_i16(float(v) * 1000.0) for v in imu.gyro_body]
        mag = [_i16(float(v) * 1000.0) for v in self._mag_body_gauss()]
        return acc + gyro + mag

    def _scaled_imu(self) -> mav.MAVLink_message:
        return mav.MAVLink_scaled_imu_message(self._time_boot_ms, *self._scaled_imu_fields(), 2500)

    def _raw_imu(self) -> mav.MAVLink_message:
        return mav.MAVLink_raw_imu_message(self.t_us, *self._scaled_imu_fields(), 0, 2500)

    def _local_position_ned(self) -> mav.MAVLink_message | None:
        """The vehicle's estimate in the world frame (m, m/s), only while it is valid."""
        est = self.copter.estimate
        if not est.pos_valid:
            return None
        return mav.MAVLink_local_position_ned_message(
            self._time_boot_ms, *(float(v) for v in est.pos_ned), *(float(v) for v in est.vel_ned))

    def _global_position_int(self) -> mav.MAVLink_message | None:
        """The estimate as degE7 / mm AMSL / mm above home / cm/s, while valid and with an origin."""
        location = self._estimated_location()
        if location is None:
            return None
        lat, lon, alt = location
        home = self.copter.home_position
        ref_alt = float(home[2]) if home is not None else float(self.copter.origin[2])
        vn, ve, vd = (float(v) for v in self.copter.estimate.vel_ned)
        return mav.MAVLink_global_position_int_message(
            self._time_boot_ms, _e7(lat), _e7(lon), int(round(alt * 1000)), int(round((alt - ref_alt) * 1000)),
            _i16(vn * 100), _i16(ve * 100), _i16(vd * 100), _cdeg(float(self.copter.estimate.euler[2])))

    def _gps_raw_int(self) -> mav.MAVLink_message:
        """The GPS receiver (fix_type 0 NO_GPS when disabled or before its first fix)."""
        g = self.copter.gps
        if g is None:
            return mav.MAVLink_gps_raw_int_message(
                self.t_us, mav.GPS_FIX_TYPE_NO_GPS, 0, 0, 0, UINT16_MAX, UINT16_MAX, UINT16_MAX, UINT16_MAX, 0)
        vn, ve = float(g.vel_ned[0]), float(g.vel_ned[1])
        alt_mm = int(round(g.alt_m * 1000))
        return mav.MAVLink_gps_raw_int_message(
            self.t_us, g.fix_type, _e7(g.lat_deg), _e7(g.lon_deg), alt_mm,
            _clamp_int(g.eph_m * 100, 0, UINT16_MAX), _clamp_int(g.epv_m * 100, 0, UINT16_MAX),
            _clamp_int(math.hypot(vn, ve) * 100, 0, UINT16_MAX - 1), _cdeg(math.atan2(ve, vn)),
            g.satellites, alt_mm, _clamp_int(g.eph_m * 1000, 0, 2**32 - 1),
            _clamp_int(g.epv_m * 1000, 0, 2**32 - 1), 0, 0, 0)

    def _home_position(self) -> mav.MAVLink_message | None:
        """Home (degE7, mm AMSL) and its local NED position relative to the origin (m)."""
        home = self.copter.home_position
        if home is None:
            return None
        lat, lon, alt = (float(v) for v in home)
        origin = self.copter.origin
        x, y, z = ned_from_geodetic(lat, lon, alt, tuple(origin)) if origin is not None else (0.0, 0.0, 0.0)
        return mav.MAVLink_home_position_message(
            _e7(lat), _e7(lon), int(round(alt * 1000)), float(x), float(y), float(z),
            [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, self.t_us)

    def _gps_global_origin(self) -> mav.MAVLink_message | None:
        origin = self.copter.origin
        if origin is None:
            return None
        lat, lon, alt = (float(v) for v in origin)
        return mav.MAVLink_gps_global_origin_message(_e7(lat), _e7(lon), int(round(alt * 1000)), self.t_us)

    def _ekf_status_report(self) -> mav.MAVLink_message:
        est = self.copter.estimate
        return mav.MAVLink_ekf_status_report_message(
            int(est.flags) & 0xFFFF, float(est.vel_variance), float(est.pos_variance_m2),
            float(est.height_variance_m2), 0.0, 0.0, 0.0)

    def _sys_status(self) -> mav.MAVLink_message:
        """Fixed sensor set and battery; AHRS health from the estimator's attitude flag."""
        sensors = (
            mav.MAV_SYS_STATUS_SENSOR_3D_GYRO | mav.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | mav.MAV_SYS_STATUS_SENSOR_3D_MAG | mav.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | mav.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL | mav.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
            | mav.MAV_SYS_STATUS_SENSOR_YAW_POSITION | mav.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
            | mav.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL | mav.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            | mav.MAV_SYS_STATUS_AHRS | mav.MAV_SYS_STATUS_SENSOR_BATTERY)
        if self.cfg.gps:
            sensors |= mav.MAV_SYS_STATUS_SENSOR_GPS
        health = sensors
        if not int(self.copter.estimate.flags) & mav.ESTIMATOR_ATTITUDE:
            health &= ~mav.MAV_SYS_STATUS_AHRS
        current_ca = 1500 if self.copter.armed else 50
        return mav.MAVLink_sys_status_message(
            sensors, sensors, health, 100, 16000, current_ca, 90, 0, 0, 0, 0, 0, 0, 0, 0, 0)

    def _system_time(self) -> mav.MAVLink_message:
        """Unix time (us; 0 without a GPS fix, as ArduPilot without an RTC source) and boot time (ms)."""
        gps = self.copter.gps
        if gps is None or gps.fix_type < mav.GPS_FIX_TYPE_2D_FIX:
            unix_us = 0
        else:
            unix_us = int(self._unix_at_zero_s * 1e6) + self.t_us
        return mav.MAVLink_system_time_message(unix_us, self._time_boot_ms)

    def _vfr_hud(self) -> mav.MAVLink_message:
        """Speeds (m/s), heading (deg), throttle (%), altitude (m AMSL) and climb rate (m/s)."""
        c, est = self.copter, self.copter.estimate
        vn, ve, vd = (float(v) for v in est.vel_ned)
        location = self._estimated_location()
        alt = location[2] if location is not None else float(c.baro_alt_m)
        throttle = _clamp_int(c.throttle_percent, 0, 100) if c.armed and not c.landed else 0
        heading = int(math.degrees(float(est.euler[2])) % 360.0) % 360
        return mav.MAVLink_vfr_hud_message(float(c.airspeed_mps), math.hypot(vn, ve), heading, throttle, alt, -vd)

    def _extended_sys_state(self) -> mav.MAVLink_message:
        c = self.copter
        if c.landed:
            landed = mav.MAV_LANDED_STATE_ON_GROUND
        elif c.landing:
            landed = mav.MAV_LANDED_STATE_LANDING
        else:
            landed = mav.MAV_LANDED_STATE_IN_AIR
        return mav.MAVLink_extended_sys_state_message(mav.MAV_VTOL_STATE_UNDEFINED, landed)

    def _battery_status(self) -> mav.MAVLink_message:
        """A fixed, healthy 4S battery."""
        cells = [4000] * 4 + [UINT16_MAX] * 6
        current_ca = 1500 if self.copter.armed else 50
        return mav.MAVLink_battery_status_message(
            0, mav.MAV_BATTERY_FUNCTION_UNKNOWN, mav.MAV_BATTERY_TYPE_LIPO, 32767, cells, current_ca,
            -1, -1, 90, 0, mav.MAV_BATTERY_CHARGE_STATE_OK, [0] * 4, 0, 0)

    def _sim_state(self) -> mav.MAVLink_message:
        """Ground truth: attitude, body specific force (m/s^2) and rates (rad/s), geodetic, NED velocity."""
        tr = self.copter.truth
        q = [float(v) for v in tr.quat]
        roll, pitch, yaw = (float(v) for v in tr.euler)
        ax, ay, az = (float(v) for v in tr.accel_body)
        gx, gy, gz = (float(v) for v in tr.gyro_body)
        vn, ve, vd = (float(v) for v in tr.vel_ned)
        lat, lon = float(tr.lat_deg), float(tr.lon_deg)
        return mav.MAVLink_sim_state_message(
            *q, roll, pitch, yaw, ax, ay, az, gx, gy, gz, lat, lon, float(tr.alt_m), 0.0, 0.0,
            vn, ve, vd, _e7(lat), _e7(lon))

    def _truth_position(self) -> mav.MAVLink_message:
        """Ground truth's position as a motion-capture system gives it: NED metres from the anchor
        (``--home``), float32 (micrometres here; SIM_STATE's lat_int/lon_int step by 1.1 cm), sent
        just before each SIM_STATE (sitl/truth.py)."""
        tr = self.copter.truth
        x, y, z = (float(v) for v in tr.pos_ned)
        return mav.MAVLink_att_pos_mocap_message(self.t_us, [float(v) for v in tr.quat], x, y, z, [math.nan] + [0.0] * 20)

    def _autopilot_version(self) -> mav.MAVLink_message:
        return mav.MAVLink_autopilot_version_message(
            CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, self.sysid, [0] * 18)
