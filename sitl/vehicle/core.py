"""The simulated vehicle: a SimulatedCopter or SimulatedPlane behind ArduPilot-like MAVLink links, put together
from its parts."""

from __future__ import annotations

import math
import socket
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.mavlink.signing import require_signatures
from sitl.copter import SimulatedCopter, WindConfig
from sitl.plane import SimulatedPlane
from sitl.flight_log import FlightLog
from sitl.vehicle.commands import CommandsMixin
from sitl.vehicle.link import Link
from sitl.vehicle.messages import MessageBuilder, MessagesMixin
from sitl.vehicle.receiving import ReceivingMixin
from sitl.vehicle.run_loop import RunLoopMixin
from sitl.vehicle.state import StateTrackingMixin

SIGNING_LINK_ID = 0  # the link id in the companion link's signatures
DEFAULT_HOME = (1.2966, 103.7764, 10.0)
UNIX_EPOCH_LOCKSTEP_S = 1_735_689_600  # SYSTEM_TIME epoch at sim zero in lockstep: 2025-01-01T00:00Z
AIRFRAMES: dict[str, type[SimulatedCopter] | type[SimulatedPlane]] = {"copter": SimulatedCopter, "plane": SimulatedPlane}


@dataclass(frozen=True)
class VehicleConfig:
    """Command-line options (see :func:`sitl.vehicle.cli.parse_args`)."""

    companion: str
    gcs: tuple[str, ...] = ()
    lockstep: bool = False
    tick_s: float = 0.005
    seed: int = 0
    seconds: float | None = None
    log: str | None = None
    home: tuple[float, float, float] = DEFAULT_HOME
    gps: bool = True
    position_source: str = "extnav"
    wind_ned_mps: tuple[float, float, float] | None = None
    gust_mps: float | None = None
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)  # north m, east m, yaw deg
    sysid: int = 1
    legacy_streams: bool = False  # like older firmware: SET_MESSAGE_INTERVAL unknown, REQUEST_DATA_STREAM only
    refuse_intervals: tuple[int, ...] = ()  # message ids whose SET_MESSAGE_INTERVAL fails, as on ArduPilot 4.0
    signing_key: bytes | None = None  # MAVLink 2 signing on the companion link (--signing-key)
    airframe: str = "copter"  # --vehicle: "copter" (ArduCopter-like) or "plane" (ArduPlane-like)
    in_flight: tuple[float, float] | None = None  # --in-flight: (height m, airspeed m/s) of a plane started flying
    events: tuple[tuple[float, ...], ...] = ()  # --event: (start s, end s, sideslip deg/s, tilt roll deg, tilt pitch deg)


class Vehicle(RunLoopMixin, ReceivingMixin, CommandsMixin, StateTrackingMixin, MessagesMixin):
    """The simulated autopilot: a SimulatedCopter or SimulatedPlane behind ArduPilot-like MAVLink links.

    Its parts (sitl/vehicle/*.py) are mixins sharing this object's attributes, which are all set here;
    ``copter`` is the simulated vehicle whichever its airframe.
    """

    def __init__(self, cfg: VehicleConfig) -> None:
        self.cfg = cfg
        self.sysid = cfg.sysid
        self.tick_us = int(round(cfg.tick_s * 1e6))
        if self.tick_us <= 0:
            raise ValueError("--tick must be at least 1 us")
        if cfg.airframe not in AIRFRAMES:
            raise ValueError(f"--vehicle must be one of {sorted(AIRFRAMES)}, not {cfg.airframe!r}")
        in_flight = {} if cfg.in_flight is None else {"start_airspeed_mps": cfg.in_flight[1]}
        height = 0.0 if cfg.in_flight is None else cfg.in_flight[0]
        self.copter: SimulatedCopter | SimulatedPlane = AIRFRAMES[cfg.airframe](
            seed=cfg.seed, home=cfg.home, gps_enabled=cfg.gps, position_source=cfg.position_source,
            wind=_wind(cfg), start_ned=(cfg.start[0], cfg.start[1], -height),
            start_yaw_rad=math.radians(cfg.start[2]), **in_flight)
        self.links = [Link("companion", cfg.companion, cfg.sysid)]
        self.links += [Link(f"gcs{i}", url, cfg.sysid) for i, url in enumerate(cfg.gcs)]
        self.companion = self.links[0]
        if cfg.signing_key is not None:
            require_signatures(self.companion.conn.mav, cfg.signing_key, SIGNING_LINK_ID, self._signature_refused)
        self.n = 0  # ticks done; sim time t = n * tick
        self.t0: float | None = None  # time.monotonic() at sim zero (real time only)
        self.log = FlightLog(seed=cfg.seed, lockstep=cfg.lockstep, monotonic_at_sim_zero=None)
        self._awaited_ts1: int | None = None
        self._replies: list[mav.MAVLink_message] = []  # sent after the COMMAND_ACK being prepared
        self._texts: list[tuple[int, str]] = []  # own STATUSTEXTs, sent with the copter's by _observe
        self._companion_heard = False
        self._next_sample_us = 0
        self._last_home: tuple[float, float, float] | None = None
        self._announced_mode = self.copter.mode  # a change is announced with a HEARTBEAT at once
        self._unix_at_zero_s = float(UNIX_EPOCH_LOCKSTEP_S)
        self._nonfinite = 0
        self._stale_or_future = 0
        self._stop_requested = False
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._builders: dict[int, MessageBuilder] = {
            mav.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat,
            mav.MAVLINK_MSG_ID_ATTITUDE: self._attitude,
            mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: self._attitude_quaternion,
            mav.MAVLINK_MSG_ID_HIGHRES_IMU: self._highres_imu,
            mav.MAVLINK_MSG_ID_SCALED_IMU: self._scaled_imu,
            mav.MAVLINK_MSG_ID_RAW_IMU: self._raw_imu,
            mav.MAVLINK_MSG_ID_SCALED_PRESSURE: self._scaled_pressure,
            mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._local_position_ned,
            mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._global_position_int,
            mav.MAVLINK_MSG_ID_GPS_RAW_INT: self._gps_raw_int,
            mav.MAVLINK_MSG_ID_HOME_POSITION: self._home_position,
            mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: self._gps_global_origin,
            mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT: self._ekf_status_report,
            mav.MAVLINK_MSG_ID_SYS_STATUS: self._sys_status,
            mav.MAVLINK_MSG_ID_SYSTEM_TIME: self._system_time,
            mav.MAVLINK_MSG_ID_VFR_HUD: self._vfr_hud,
            mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self._extended_sys_state,
            mav.MAVLINK_MSG_ID_BATTERY_STATUS: self._battery_status,
            mav.MAVLINK_MSG_ID_SIM_STATE: self._sim_state,
        }
        self._requestable: dict[int, MessageBuilder] = {
            **self._builders, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self._autopilot_version}
        self._handlers: dict[str, Callable[[Link, mav.MAVLink_message], None]] = {
            "HEARTBEAT": self._on_heartbeat,
            "COMMAND_LONG": self._on_command_long,
            "COMMAND_INT": self._on_command_int,
            "SET_MODE": self._on_set_mode,
            "REQUEST_DATA_STREAM": self._on_request_data_stream,
            "SET_GPS_GLOBAL_ORIGIN": self._on_set_gps_global_origin,
            "SET_HOME_POSITION": self._on_set_home_position,
            "VISION_POSITION_ESTIMATE": self._on_vision_position,
            "VISION_SPEED_ESTIMATE": self._on_vision_speed,
            "DISTANCE_SENSOR": self._on_distance_sensor,
            "SET_POSITION_TARGET_LOCAL_NED": self._on_set_position_target,
            "MISSION_ITEM_INT": self._on_mission_item_int,
        }
        self._commands: dict[int, Callable[[Link, tuple[float, ...], int | None], int]] = {
            mav.MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_message_interval,
            mav.MAV_CMD_GET_MESSAGE_INTERVAL: self._cmd_get_message_interval,
            mav.MAV_CMD_REQUEST_MESSAGE: self._cmd_request_message,
            mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._cmd_request_capabilities,
            mav.MAV_CMD_DO_SET_MODE: self._cmd_do_set_mode,
            mav.MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm_disarm,
            mav.MAV_CMD_NAV_TAKEOFF: self._cmd_takeoff,
            mav.MAV_CMD_NAV_LAND: self._cmd_land,
            mav.MAV_CMD_DO_SET_HOME: self._cmd_set_home,
            mav.MAV_CMD_DO_SET_SERVO: self._cmd_set_servo,
            mav.MAV_CMD_DO_GRIPPER: self._cmd_gripper,
        }


def _wind(cfg: VehicleConfig) -> WindConfig | None:
    """Wind from --wind/--gust (WindConfig defaults for the one not given), None for neither."""
    if cfg.wind_ned_mps is None and cfg.gust_mps is None:
        return None
    kwargs: dict[str, object] = {}
    if cfg.wind_ned_mps is not None:
        kwargs["mean_ned_mps"] = cfg.wind_ned_mps
    if cfg.gust_mps is not None:
        kwargs["gust_std_mps"] = cfg.gust_mps
    return WindConfig(**kwargs)
