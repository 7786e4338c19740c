"""What the companion knows about its autopilot, from the messages it streams.

:class:`AutopilotState` is fed by the link's dispatch and never sends anything. It decodes the
flight mode for ArduPilot Copter and PX4, arming, the EKF origin and home, the estimator
flags, the attitude and IMU the pipelines use, and whether the autopilot says it fuses
external navigation (ArduPilot STATUSTEXT "... is using external nav data", or PX4's
ESTIMATOR_STATUS flags with the EV aiding bits unavailable from MAVLink: there the horizontal
position flag while no GPS is fused is the best signal).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from companion import clock
from companion.mavlink.link import MavlinkLink, mavlink, mavutil

log = logging.getLogger("companion.autopilot")

# Modes in which an autopilot takes setpoints from the companion.
COMMANDABLE_MODES = {"GUIDED", "OFFBOARD"}


@dataclass
class Origin:
    lat: float  # degrees
    lon: float  # degrees
    alt: float  # metres AMSL


@dataclass
class AutopilotState:
    """Latest autopilot state; times are daemon-clock seconds of reception."""

    link: MavlinkLink
    mode: str | None = None
    armed: bool = False
    origin: Origin | None = None
    home: Origin | None = None
    external_nav_in_use: bool = False
    ekf_flags: int = 0
    attitude_euler: tuple[float, float, float] | None = None  # roll, pitch, yaw rad (body FRD -> NED)
    attitude_time: float | None = None
    local_position_ned: np.ndarray | None = None  # m, the autopilot's own estimate
    local_velocity_ned: np.ndarray | None = None  # m/s
    local_position_time: float | None = None
    accel_body: np.ndarray | None = None  # specific force, body FRD, m/s^2 (HIGHRES_IMU)
    gyro_body: np.ndarray | None = None  # rad/s
    imu_time: float | None = None
    statustext: list[tuple[float, int, str]] = field(default_factory=list)
    _mode_listeners: list[Callable[[str | None, str], None]] = field(default_factory=list)

    def __post_init__(self) -> None:
        for msg_type, handler in (
            ("HEARTBEAT", self._on_heartbeat),
            ("GPS_GLOBAL_ORIGIN", self._on_origin),
            ("HOME_POSITION", self._on_home),
            ("EKF_STATUS_REPORT", self._on_ekf_status),
            ("ESTIMATOR_STATUS", self._on_estimator_status),
            ("ATTITUDE", self._on_attitude),
            ("LOCAL_POSITION_NED", self._on_local_position),
            ("HIGHRES_IMU", self._on_imu),
            ("STATUSTEXT", self._on_statustext),
        ):
            self.link.subscribe(msg_type, handler)

    def on_mode_change(self, listener: Callable[[str | None, str], None]) -> None:
        """Call ``listener(old_mode, new_mode)`` when the HEARTBEAT mode changes."""
        self._mode_listeners.append(listener)

    @property
    def commandable(self) -> bool:
        """True when the autopilot is in a mode that follows companion setpoints."""
        return self.mode in COMMANDABLE_MODES

    def custom_mode_for(self, name: str) -> tuple[int, int]:
        """(base_mode, custom_mode) to request mode ``name`` from this autopilot."""
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.link.autopilot == "PX4":
            if name not in mavutil.px4_map:
                raise ValueError(f"PX4 has no mode {name!r}")
            base_mode, main, sub = mavutil.px4_map[name]
            return base_mode, (main << 16) | (sub << 24)
        by_name = {v: k for k, v in mavutil.mode_mapping_acm.items()}
        if name not in by_name:
            raise ValueError(f"ArduPilot Copter has no mode {name!r}")
        return base, by_name[name]

    # -- handlers ---------------------------------------------------------------------------

    def _on_heartbeat(self, msg: mavlink.MAVLink_message) -> None:
        if msg.get_srcComponent() != self.link.ids.autopilot_compid:
            return
        self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        mode = mavutil.mode_string_v10(msg)
        if mode != self.mode:
            old, self.mode = self.mode, mode
            log.info("autopilot mode %s -> %s", old, mode)
            for listener in self._mode_listeners:
                listener(old, mode)

    def _on_origin(self, msg: mavlink.MAVLink_message) -> None:
        self.origin = Origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)

    def _on_home(self, msg: mavlink.MAVLink_message) -> None:
        self.home = Origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)

    def _on_ekf_status(self, msg: mavlink.MAVLink_message) -> None:
        self.ekf_flags = msg.flags

    def _on_estimator_status(self, msg: mavlink.MAVLink_message) -> None:
        self.ekf_flags = msg.flags

    def _on_attitude(self, msg: mavlink.MAVLink_message) -> None:
        self.attitude_euler = (msg.roll, msg.pitch, msg.yaw)
        self.attitude_time = clock.now()

    def _on_local_position(self, msg: mavlink.MAVLink_message) -> None:
        self.local_position_ned = np.array([msg.x, msg.y, msg.z])
        self.local_velocity_ned = np.array([msg.vx, msg.vy, msg.vz])
        self.local_position_time = clock.now()

    def _on_imu(self, msg: mavlink.MAVLink_message) -> None:
        self.accel_body = np.array([msg.xacc, msg.yacc, msg.zacc])
        self.gyro_body = np.array([msg.xgyro, msg.ygyro, msg.zgyro])
        self.imu_time = clock.now()

    def _on_statustext(self, msg: mavlink.MAVLink_message) -> None:
        text = msg.text
        if msg.get_srcComponent() == self.link.ids.autopilot_compid:  # not our own, routed back
            log.log(logging.WARNING if msg.severity <= mavlink.MAV_SEVERITY_WARNING else logging.INFO,
                    "autopilot says: %s", text)
        self.statustext.append((clock.now(), msg.severity, text))
        del self.statustext[:-50]
        if "using external nav" in text:
            in_use = "stopped" not in text
            if in_use != self.external_nav_in_use:
                log.info("autopilot %s external nav (%r)", "uses" if in_use else "stopped using", text)
            self.external_nav_in_use = in_use
