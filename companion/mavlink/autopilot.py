"""What the companion knows about its autopilot, from the messages it streams.

:class:`AutopilotState` is fed by the link's dispatch and never sends anything. It decodes the
firmware (``companion.mavlink.firmware``), the flight mode for ArduPilot Copter and PX4,
arming, the EKF origin and home, the estimator flags, the attitude and IMU the pipelines use,
and whether the autopilot says it fuses external navigation (ArduPilot STATUSTEXT "... is using
external nav data", or PX4's ESTIMATOR_STATUS flags with the EV aiding bits unavailable from
MAVLink: there the horizontal position flag while no GPS is fused is the best signal).

Everything is kept in the project frame: LOCAL_POSITION_NED from firmware that reports it
relative to home (ArduPilot < 4.1) is moved to the EKF origin with the home and origin the
autopilot itself reports. Every value used here has been checked by the link (finite, within
bounds: companion/mavlink/edge.py): a NaN from the autopilot never reaches a pipeline.

Only the autopilot's own messages arrive here (the link's trust rules, companion/mavlink/trust.py):
from its sysid and compid, HEARTBEATs with the identity locked by the first one (so the firmware
family and vehicle type never change under the companion), and only samples whose
``time_boot_ms`` is in order: an ATTITUDE, LOCAL_POSITION_NED or SCALED_IMU stamped before the
last of its kind, or off the boot clock, outside a confirmed reboot, is dropped and counted by the
link (``time_anomalies``). IMU samples stamped in microseconds (HIGHRES_IMU, RAW_IMU) that go back
land before the last kept one, or stale, and are dropped here (``imu_rejected``).

The IMU comes from one message, the one the stream negotiation chose (``imu_source``:
HIGHRES_IMU, or SCALED_IMU / RAW_IMU / SCALED_IMU2 where the firmware does not stream it);
the scaled ones carry mG and mrad/s, converted here to m/s^2 and rad/s, and no barometric
altitude: the newest SCALED_PRESSURE (mavlink.streams.pressure) is attached to them. Every sample goes to the
IMU listeners in order (:meth:`AutopilotState.on_imu`: the ``imu`` sensor's ``autopilot`` backend,
drivers/imu_autopilot.py), with the newest ATTITUDE, stamped with the autopilot's own sample time
mapped onto the daemon clock (``companion.jitter``): a stream that arrives in bursts (ArduPilot
SITL over TCP) keeps its real spacing. The last :data:`IMU_QUEUE` samples are kept for diagnostics.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from companion import clock
from companion.frames import GRAVITY_MPS2, ned_from_geodetic
from companion.jitter import JitterCorrection
from companion.mavlink.firmware import Firmware, firmware_from_heartbeat, with_version
from companion.messages import ImuSample
from companion.mavlink.link import MavlinkLink, mavlink, mavutil

log = logging.getLogger("companion.autopilot")

# Modes in which an autopilot takes setpoints from the companion.
COMMANDABLE_MODES = {"GUIDED", "OFFBOARD"}
IMU_MESSAGES = ("HIGHRES_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "RAW_IMU")
IMU_QUEUE = 64  # samples kept: > 1 s at 50 Hz, far more than one nav cycle
ATTITUDE_HISTORY = 256  # ATTITUDE messages kept for attitude_at: 5 s at 50 Hz
ATTITUDE_MATCH_S = 0.1  # attitude_at answers only with a message received this close to the time asked
IMU_CLOCK_WINDOW = 50  # samples in the clock-offset minimum (1 s at 50 Hz)
HIGHRES_PRESSURE_ALT = 1 << 11  # HIGHRES_IMU fields_updated: pressure_alt is valid
PRESSURE_MAX_AGE_S = 0.5  # the SCALED_PRESSURE altitude attached to a scaled IMU sample is at most this old
ISA_SEA_LEVEL_HPA = 1013.25
VELOCITY_MAX_AGE_S = 1.0  # the autopilot velocity attached to an IMU sample is at most this old
FAILSAFE_WORDS = ("failsafe", "ekf variance")  # in an autopilot STATUSTEXT: it acted by itself
FAILSAFE_OVER_WORDS = ("clear", " off", "resolved")  # ... unless the text says a failsafe ended
MILLI_G = GRAVITY_MPS2 / 1000.0  # SCALED_IMU* (and ArduPilot's RAW_IMU) accelerations are in mG


def new_imu_clock() -> JitterCorrection:
    """The mapping of the autopilot's IMU sample times onto the daemon clock."""
    return JitterCorrection(window=IMU_CLOCK_WINDOW)


def imu_remote_time_s(msg: mavlink.MAVLink_message) -> float:
    """The autopilot's sample time of an IMU message, s since its boot (``time_usec`` or ``time_boot_ms``)."""
    usec = getattr(msg, "time_usec", None)
    return usec * 1e-6 if usec is not None else msg.time_boot_ms * 1e-3


def imu_sample(msg: mavlink.MAVLink_message) -> tuple[np.ndarray, np.ndarray]:
    """(specific force m/s^2, angular rate rad/s), body FRD, from HIGHRES_IMU or a scaled IMU message
    (SCALED_IMU*, and ArduPilot's RAW_IMU, which carries the same mG / mrad/s units)."""
    accel = np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float)
    gyro = np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=float)
    if msg.get_type() == "HIGHRES_IMU":
        return accel, gyro
    return accel * MILLI_G, gyro * 1e-3


def pressure_altitude(msg: mavlink.MAVLink_message) -> float | None:
    """HIGHRES_IMU's barometric altitude (m) when its fields_updated says it is there and it is
    finite; None for any other IMU message."""
    if msg.get_type() != "HIGHRES_IMU" or not msg.fields_updated & HIGHRES_PRESSURE_ALT:
        return None
    return float(msg.pressure_alt) if math.isfinite(msg.pressure_alt) else None


def isa_pressure_altitude_m(pressure_hpa: float) -> float:
    """The ISA pressure altitude (m, up, above the 1013.25 hPa level) of a static pressure (hPa),
    as HIGHRES_IMU's ``pressure_alt``: an offset from the true altitude that the weather sets, so
    a user takes differences (e.g. from a datum taken on the ground)."""
    return 44330.77 * (1.0 - (pressure_hpa / ISA_SEA_LEVEL_HPA) ** 0.190263)


@dataclass
class Origin:
    lat: float  # degrees
    lon: float  # degrees
    alt: float  # metres AMSL


@dataclass
class AutopilotState:
    """Latest autopilot state; times are daemon-clock seconds of reception."""

    link: MavlinkLink
    firmware: Firmware | None = None
    mode: str | None = None
    armed: bool = False
    origin: Origin | None = None  # the EKF origin, as the autopilot last reported it (GPS_GLOBAL_ORIGIN)
    origin_time: float | None = None  # daemon clock of that report
    home: Origin | None = None  # as the autopilot last reported it (HOME_POSITION)
    home_time: float | None = None
    external_nav_in_use: bool = False
    ekf_flags: int = 0
    attitude_euler: tuple[float, float, float] | None = None  # roll, pitch, yaw rad (body FRD -> NED)
    attitude_time: float | None = None
    attitude_history: deque[tuple[float, tuple[float, float, float]]] = field(
        default_factory=lambda: deque(maxlen=ATTITUDE_HISTORY))  # (reception time, euler), oldest first
    local_position_ned: np.ndarray | None = None  # m, the autopilot's own estimate, at the EKF origin
    local_velocity_ned: np.ndarray | None = None  # m/s
    local_position_time: float | None = None
    imu_source: str | None = None  # the message the IMU is taken from (set by the stream negotiation)
    imu: deque[ImuSample] = field(default_factory=lambda: deque(maxlen=IMU_QUEUE))  # oldest first
    imu_rejected: int = 0  # IMU samples whose time stamp could not be placed (stale, or a clock jump)
    pressure_alt_m: float | None = None  # newest SCALED_PRESSURE as ISA pressure altitude, m up
    pressure_time: float | None = None  # daemon clock of its reception
    statustext: list[tuple[float, int, str]] = field(default_factory=list)  # (time, severity, text), the last 50
    _mode_listeners: list[Callable[[str | None, str], None]] = field(default_factory=list)
    _imu_listeners: list[Callable[[ImuSample], None]] = field(default_factory=list)
    _imu_clock: JitterCorrection = field(default_factory=new_imu_clock)

    def __post_init__(self) -> None:
        for msg_type, handler in (
            ("HEARTBEAT", self._on_heartbeat),
            ("GPS_GLOBAL_ORIGIN", self._on_origin),
            ("HOME_POSITION", self._on_home),
            ("EKF_STATUS_REPORT", self._on_ekf_status),
            ("ESTIMATOR_STATUS", self._on_estimator_status),
            ("ATTITUDE", self._on_attitude),
            ("LOCAL_POSITION_NED", self._on_local_position),
            ("AUTOPILOT_VERSION", self._on_version),
            ("STATUSTEXT", self._on_statustext),
            ("SCALED_PRESSURE", self._on_scaled_pressure),
            *((name, self._on_imu) for name in IMU_MESSAGES),
        ):
            self.link.subscribe(msg_type, handler)
        self.link.on_connect(self._new_connection)

    def _new_connection(self) -> None:
        """What an autopilot said about its estimator belongs to the connection it said it on: after
        a reboot or a lost link, the EKF has to report a position and external navigation again,
        and the IMU clock is learnt afresh (a rebooted autopilot's boot clock starts over). The
        last origin and home are kept (positions keep their frame until new ones arrive)."""
        self.ekf_flags = 0
        self.external_nav_in_use = False
        self._imu_clock = new_imu_clock()

    def on_mode_change(self, listener: Callable[[str | None, str], None]) -> None:
        """Call ``listener(old_mode, new_mode)`` when the HEARTBEAT mode changes."""
        self._mode_listeners.append(listener)

    def custom_mode_for(self, name: str) -> tuple[int, int]:
        """(base_mode, custom_mode) to request mode ``name`` from this autopilot."""
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.link.autopilot == "PX4":
            if name not in mavutil.px4_map:
                raise ValueError(f"PX4 has no mode {name!r}")
            base_mode, main, sub = mavutil.px4_map[name]
            return base_mode, (main << 16) | (sub << 24)
        firmware = self.firmware or Firmware(self.link.autopilot or "unknown", "copter")
        return base, firmware.ardupilot_mode_number(name)

    # -- handlers ---------------------------------------------------------------------------

    def on_imu(self, listener: Callable[[ImuSample], None]) -> Callable[[], None]:
        """Call ``listener(sample)`` with every IMU sample from now on, in order; returns the
        function that stops it."""
        self._imu_listeners.append(listener)
        return lambda: self._imu_listeners.remove(listener)

    def failsafe_text(self, since: float) -> str | None:
        """The newest failsafe announcement the autopilot made after daemon time ``since`` (ArduPilot:
        "EKF Failsafe...", "GCS Failsafe...", "Battery Failsafe", "EKF variance"; not "... Cleared"
        or "... Off"), or None."""
        for t, _, text in reversed(self.statustext):
            if t < since:
                return None
            lower = text.lower()
            if any(w in lower for w in FAILSAFE_WORDS) and not any(w in lower for w in FAILSAFE_OVER_WORDS):
                return text
        return None

    def home_offset_ned(self) -> np.ndarray | None:
        """Home in the EKF-origin frame (m), from the home and origin the autopilot reports; None if unknown."""
        if self.home is None or self.origin is None:
            return None
        return ned_from_geodetic(self.home.lat, self.home.lon, self.home.alt,
                                 (self.origin.lat, self.origin.lon, self.origin.alt))

    def setpoint_z_offset_m(self) -> float:
        """What to add to a LOCAL_NED setpoint z for this firmware: the height of home above the
        origin where the firmware reads z relative to home (ArduPilot Copter < 4.1), else 0."""
        if self.firmware is None or not self.firmware.setpoint_z_relative_to_home:
            return 0.0
        offset = self.home_offset_ned()
        return 0.0 if offset is None else -float(offset[2])

    def _on_heartbeat(self, msg: mavlink.MAVLink_message) -> None:
        if self.firmware is None:  # the link locked the identity with this HEARTBEAT: it stays
            self.firmware = firmware_from_heartbeat(self.link.autopilot or "unknown", msg.type)
        self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        mode = mavutil.mode_string_v10(msg)
        if mode != self.mode:
            old, self.mode = self.mode, mode
            log.info("autopilot mode %s -> %s", old, mode)
            for listener in self._mode_listeners:
                listener(old, mode)

    def _on_version(self, msg: mavlink.MAVLink_message) -> None:
        if self.firmware is None:
            return
        firmware = with_version(self.firmware, msg)
        if firmware != self.firmware:
            log.info("autopilot firmware: %s", firmware.label)
        self.firmware = firmware

    def _on_origin(self, msg: mavlink.MAVLink_message) -> None:
        self.origin = Origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        self.origin_time = clock.now()

    def _on_home(self, msg: mavlink.MAVLink_message) -> None:
        self.home = Origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        self.home_time = clock.now()

    def _on_ekf_status(self, msg: mavlink.MAVLink_message) -> None:
        self.ekf_flags = msg.flags

    def _on_estimator_status(self, msg: mavlink.MAVLink_message) -> None:
        self.ekf_flags = msg.flags

    def _on_attitude(self, msg: mavlink.MAVLink_message) -> None:
        self.attitude_euler = (msg.roll, msg.pitch, msg.yaw)
        self.attitude_time = clock.now()
        self.attitude_history.append((self.attitude_time, self.attitude_euler))

    def attitude_at(self, t: float) -> tuple[float, float, float] | None:
        """The autopilot's attitude (roll, pitch, yaw rad, body FRD -> NED) received nearest the daemon
        time ``t`` (s) among the last :data:`ATTITUDE_HISTORY` messages; None when none came within
        :data:`ATTITUDE_MATCH_S` of it. For comparisons with an estimate of an earlier instant (an
        estimate waits for its GNSS fixes): the newest attitude would differ by the turn since."""
        best = min(self.attitude_history, key=lambda sample: abs(sample[0] - t), default=None)
        return best[1] if best is not None and abs(best[0] - t) <= ATTITUDE_MATCH_S else None

    def _on_local_position(self, msg: mavlink.MAVLink_message) -> None:
        position = np.array([msg.x, msg.y, msg.z], dtype=float)
        if self.firmware is not None and self.firmware.local_position_relative_to_home:
            offset = self.home_offset_ned()
            if offset is None:
                return  # home-relative, and home not known yet: not usable in the project frame
            position = position + offset
        self.local_position_ned = position
        self.local_velocity_ned = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        self.local_position_time = clock.now()

    def _fresh_velocity(self) -> np.ndarray | None:
        """The autopilot's velocity estimate (NED m/s) if finite and at most
        ``VELOCITY_MAX_AGE_S`` old, else None (attached to IMU samples)."""
        v, t = self.local_velocity_ned, self.local_position_time
        if v is None or t is None or clock.now() - t > VELOCITY_MAX_AGE_S or not np.all(np.isfinite(v)):
            return None
        return v

    def _on_scaled_pressure(self, msg: mavlink.MAVLink_message) -> None:
        if msg.press_abs > 0.0:
            self.pressure_alt_m = isa_pressure_altitude_m(msg.press_abs)
            self.pressure_time = clock.now()

    def _sample_pressure_altitude(self, msg: mavlink.MAVLink_message) -> float | None:
        """The barometric altitude attached to an IMU sample (m up): HIGHRES_IMU's own, else the
        newest SCALED_PRESSURE if at most ``PRESSURE_MAX_AGE_S`` old (mavlink.streams.pressure)."""
        if msg.get_type() == "HIGHRES_IMU":
            return pressure_altitude(msg)
        t = self.pressure_time
        return self.pressure_alt_m if t is not None and clock.now() - t <= PRESSURE_MAX_AGE_S else None

    def _on_imu(self, msg: mavlink.MAVLink_message) -> None:
        if msg.get_type() != self.imu_source:
            return
        accel, gyro = imu_sample(msg)
        t = self._imu_clock.correct(imu_remote_time_s(msg), clock.now())
        if t is None or (self.imu and t <= self.imu[-1].t):
            self.imu_rejected += 1
            return
        sample = ImuSample(t, accel, gyro, self.attitude_euler, self._fresh_velocity(),
                           self._sample_pressure_altitude(msg))
        self.imu.append(sample)
        for listener in self._imu_listeners:
            listener(sample)

    def _on_statustext(self, msg: mavlink.MAVLink_message) -> None:
        text = msg.text
        log.log(logging.WARNING if msg.severity <= mavlink.MAV_SEVERITY_WARNING else logging.INFO,
                "autopilot says: %s", text)
        self.statustext.append((clock.now(), msg.severity, text))
        del self.statustext[:-50]
        if "using external nav" in text:
            in_use = "stopped" not in text
            if in_use != self.external_nav_in_use:
                log.info("autopilot %s external nav (%r)", "uses" if in_use else "stopped using", text)
            self.external_nav_in_use = in_use
