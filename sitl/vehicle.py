"""The built-in simulated vehicle process: an ArduPilot-Copter-4.x-like autopilot on MAVLink 2.

``python -m sitl.vehicle --companion udpin:127.0.0.1:14555 [--gcs udpout:127.0.0.1:14550] ...``

It wraps :class:`sitl.copter.SimulatedCopter` (physics, flight controller, estimator) and speaks
MAVLink 2 as system ``--sysid``, component 1 (MAV_COMP_ID_AUTOPILOT1) on one pymavlink connection
per link: the companion link and any number of ground-station links. Like ArduPilot, each link
has its own stream intervals (SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM), commands are ACKed on
the link they came in on, STATUSTEXT goes to every link, and messages not addressed to this
vehicle are forwarded to the other links (TIMESYNC excepted: it is answered, never forwarded).

Frames (companion/frames.py): world = MAVLink LOCAL_NED at the EKF origin, body FRD, quaternions
[w, x, y, z]. Ground truth (SIM_STATE, flight log) is relative to the ``--home`` anchor, which is
the same frame once the companion sets the EKF origin there.

Time: simulation time t (s) advances in ticks of ``--tick``. In real time (default)
t = time.monotonic() - t0, paced by the wall clock. With ``--lockstep`` the companion's clock is
driven by the vehicle, which makes runs deterministic for a seed:

1. until a HEARTBEAT from a component other than 1 arrives on the companion link, send our
   HEARTBEAT on every link once a wall-clock second; then t = 0;
2. send TIMESYNC(tc1=0, ts1=round(t*1e9)) on the companion link and handle incoming messages
   (all links, arrival order) until the reply, a TIMESYNC with tc1 != 0 and that ts1, arrives
   on the companion link; what the companion sent after its reply is handled at the next tick;
3. send everything due at t, step the copter one tick, t += tick, and go to 2 (until
   ``--seconds``). A reply missing for 15 s is reported on stderr, for 60 s it ends the run.

At exit (``--seconds`` reached, SIGTERM or SIGINT) the flight log (sitl/flight_log.py) is written
to ``--log`` and the process exits 0; a lockstep reply missing for 60 s exits 3.

Signing: with ``--signing-key FILE`` (the daemon's ``mavlink.signing_key_file``) the companion
link signs everything it sends and takes only messages signed with that key, with timestamps
that only go forward (companion/mavlink/signing.py, the daemon's rules); the others are dropped and
counted in the flight log's ``signing`` (``unsigned_rejected``, ``bad_signatures``), and the first
is reported on stderr. An unsigned companion can then neither command the vehicle nor, in
lockstep, start it. Ground-station links stay unsigned; what they send for the companion is
forwarded as it came, as a router does.
"""

from __future__ import annotations

import argparse
import math
import os
import select
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink picks its wire protocol

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

from companion.frames import GRAVITY_MPS2, geodetic_from_ned, ned_from_geodetic, rotation_from_quat  # noqa: E402
from companion.mavlink.link import load_signing_key  # noqa: E402
from companion.mavlink.signing import require_signatures  # noqa: E402
from sitl.copter import SimulatedCopter, WindConfig  # noqa: E402
from sitl.flight_log import FlightLog  # noqa: E402
from companion.jitter import JitterCorrection  # noqa: E402

COMPID = mav.MAV_COMP_ID_AUTOPILOT1
SIGNING_LINK_ID = 0  # the link id in the companion link's signatures
DEFAULT_HOME = (1.2966, 103.7764, 10.0)
DEFAULT_STREAM_INTERVAL_US = 250_000  # SET_MESSAGE_INTERVAL with interval 0: "default rate", 4 Hz
HEARTBEAT_INTERVAL_US = 1_000_000
LOG_SAMPLE_INTERVAL_US = 20_000  # truth / estimate in the flight log at 50 Hz
FORCE_MAGIC = 21196  # COMPONENT_ARM_DISARM param2 that skips checks
FLIGHT_SW_VERSION = (4 << 24) | (5 << 16) | (7 << 8) | mav.FIRMWARE_VERSION_TYPE_OFFICIAL  # 4.5.7
CAPABILITIES = (
    mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mav.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
)
MODE_GUIDED = 4  # ArduCopter custom_mode numbers
MODE_LAND = 9
LOCKSTEP_WARN_S = 15.0
LOCKSTEP_FAIL_S = 60.0
EXIT_LOCKSTEP_TIMEOUT = 3
# Approximate geomagnetic field at the default home (Singapore), NED, gauss.
EARTH_FIELD_NED_GAUSS = np.array([0.40, 0.0, -0.12])
STATUSTEXT_LEN = 50
UINT16_MAX = 65535
# COMMAND_INT commands whose x/y are latitude/longitude in degE7 (params 5/6 in degrees).
LATLON_COMMANDS = frozenset({mav.MAV_CMD_DO_SET_HOME, mav.MAV_CMD_NAV_TAKEOFF, mav.MAV_CMD_NAV_LAND})
AMSL_FRAMES = frozenset({mav.MAV_FRAME_GLOBAL, mav.MAV_FRAME_GLOBAL_INT})
RELATIVE_FRAMES = frozenset({mav.MAV_FRAME_GLOBAL_RELATIVE_ALT, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT})
# ArduPilot's stream groups (REQUEST_DATA_STREAM), approximately.
STREAM_GROUPS: dict[int, tuple[int, ...]] = {
    mav.MAV_DATA_STREAM_RAW_SENSORS: (
        mav.MAVLINK_MSG_ID_RAW_IMU, mav.MAVLINK_MSG_ID_SCALED_IMU, mav.MAVLINK_MSG_ID_HIGHRES_IMU),
    mav.MAV_DATA_STREAM_EXTENDED_STATUS: (
        mav.MAVLINK_MSG_ID_SYS_STATUS, mav.MAVLINK_MSG_ID_GPS_RAW_INT, mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE),
    mav.MAV_DATA_STREAM_POSITION: (
        mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED),
    mav.MAV_DATA_STREAM_EXTRA1: (mav.MAVLINK_MSG_ID_ATTITUDE, mav.MAVLINK_MSG_ID_SIM_STATE),
    mav.MAV_DATA_STREAM_EXTRA2: (mav.MAVLINK_MSG_ID_VFR_HUD,),
    mav.MAV_DATA_STREAM_EXTRA3: (
        mav.MAVLINK_MSG_ID_SYSTEM_TIME, mav.MAVLINK_MSG_ID_BATTERY_STATUS, mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT),
}
UNIX_EPOCH_LOCKSTEP_S = 1_735_689_600  # SYSTEM_TIME epoch at sim zero in lockstep: 2025-01-01T00:00Z

MessageBuilder = Callable[[], "mav.MAVLink_message | None"]


class _Shutdown(Exception):
    """Ends the run: the log is written and ``code`` becomes the exit status."""

    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


@dataclass(frozen=True)
class VehicleConfig:
    """Command-line options (see :func:`parse_args`)."""

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


def _next_due(due_us: int, interval_us: int, now_us: int) -> int:
    """Next due time of a periodic output that was due at ``due_us`` and sent at ``now_us``.

    Keeps the period on schedule, but skips missed periods instead of bursting to catch up.
    """
    due_us += interval_us
    return due_us if due_us > now_us else now_us + interval_us


class Link:
    """One MAVLink channel: a pymavlink connection with its own stream schedule and clock mapping."""

    def __init__(self, name: str, url: str, sysid: int) -> None:
        self.name = name
        self.conn = mavutil.mavlink_connection(
            url, source_system=sysid, source_component=COMPID, dialect="ardupilotmega")
        self.intervals_us: dict[int, int] = {mav.MAVLINK_MSG_ID_HEARTBEAT: HEARTBEAT_INTERVAL_US}
        self.next_due_us: dict[int, int] = {}
        self.jitter = JitterCorrection()

    def fileno(self) -> int:
        """Current socket file descriptor, for select() (a tcpin link's changes on accept)."""
        return self.conn.fd

    def send(self, msg: mav.MAVLink_message) -> None:
        """Send a message from this vehicle (own sequence numbers per link)."""
        self.conn.mav.send(msg)

    def forward(self, msg: mav.MAVLink_message) -> None:
        """Send another system's message unchanged (routing)."""
        self.conn.write(msg.get_msgbuf())

    def recv(self) -> mav.MAVLink_message | None:
        """The next received message, or None when nothing is waiting (non-blocking)."""
        return self.conn.recv_msg()

    def set_interval(self, msgid: int, interval_us: int | None, now_us: int) -> None:
        """Stream ``msgid`` every ``interval_us`` of sim time from now on (None: stop it)."""
        if interval_us is None:
            self.intervals_us.pop(msgid, None)
            self.next_due_us.pop(msgid, None)
            return
        self.intervals_us[msgid] = interval_us
        self.next_due_us[msgid] = now_us

    def due(self, now_us: int) -> list[int]:
        """Message ids whose stream is due at sim time ``now_us``; advances their schedule."""
        ids = []
        for msgid, interval in self.intervals_us.items():
            next_us = self.next_due_us.get(msgid, now_us)
            if now_us >= next_us:
                ids.append(msgid)
                self.next_due_us[msgid] = _next_due(next_us, interval, now_us)
        return ids

    def close(self) -> None:
        self.conn.close()


def _covariance(msg: mav.MAVLink_message) -> list[float] | None:
    """A VISION_* covariance as sent, or None ("unknown") when any entry is non-finite."""
    return list(msg.covariance) if _finite(msg.covariance) else None


def _finite(values: Sequence[float]) -> bool:
    return all(math.isfinite(v) for v in values)


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


class Vehicle:
    """The simulated autopilot: a SimulatedCopter behind ArduPilot-like MAVLink links."""

    def __init__(self, cfg: VehicleConfig) -> None:
        self.cfg = cfg
        self.sysid = cfg.sysid
        self.tick_us = int(round(cfg.tick_s * 1e6))
        if self.tick_us <= 0:
            raise ValueError("--tick must be at least 1 us")
        self.copter = SimulatedCopter(
            seed=cfg.seed, home=cfg.home, gps_enabled=cfg.gps, position_source=cfg.position_source,
            wind=_wind(cfg), start_ned=(cfg.start[0], cfg.start[1], 0.0),
            start_yaw_rad=math.radians(cfg.start[2]))
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
            "SET_POSITION_TARGET_LOCAL_NED": self._on_set_position_target,
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

    # ------------------------------------------------------------------ time

    @property
    def t_us(self) -> int:
        """Simulation time of the current tick, integer microseconds."""
        return self.n * self.tick_us

    @property
    def t(self) -> float:
        """Simulation time of the current tick (s)."""
        return self.t_us / 1e6

    def _now(self) -> float:
        """Simulation time (s) for a message received now: the tick in lockstep, the wall clock else."""
        if self.cfg.lockstep or self.t0 is None:
            return self.t
        return time.monotonic() - self.t0

    # ------------------------------------------------------------------ run loops

    def request_stop(self) -> None:
        """Ask the run to end (signal-safe: also wakes a waiting select())."""
        self._stop_requested = True
        try:
            self._wake_w.send(b"\0")
        except OSError:
            pass

    @property
    def wake_fd(self) -> int:
        """File descriptor for signal.set_wakeup_fd()."""
        return self._wake_w.fileno()

    def run(self) -> int:
        """Run until --seconds, a stop request or a lockstep failure; write the log; exit status."""
        code = 0
        self._observe()
        try:
            if self.cfg.lockstep:
                self._run_lockstep()
            else:
                self._run_realtime()
        except _Shutdown as stop:
            code = stop.code
        finally:
            self._write_log()
        return code

    def close(self) -> None:
        """Release the sockets (after the signal handlers that use the wake-up pipe are gone)."""
        for link in self.links:
            link.close()
        self._wake_r.close()
        self._wake_w.close()

    def _end_tick(self) -> float:
        """Number of ticks to run (inf without --seconds)."""
        if self.cfg.seconds is None:
            return math.inf
        return math.ceil(round(self.cfg.seconds * 1e6) / self.tick_us)

    def _run_realtime(self) -> None:
        self.t0 = time.monotonic()
        self._unix_at_zero_s = time.time()
        self.log.monotonic_at_sim_zero = self.t0
        end = self._end_tick()
        while self.n < end:
            if self._stop_requested:
                raise _Shutdown(0)
            self._send_due()
            self._step()
            self._wait_until(self.t0 + self.t)

    def _run_lockstep(self) -> None:
        self._await_companion()
        self._sync()
        end = self._end_tick()
        while self.n < end:
            self._send_due()
            self._step()
            self._sync()

    def _step(self) -> None:
        """Advance the copter one tick and record what changed."""
        self.copter.step(self.tick_us / 1e6)
        self.n += 1
        self.log.add_external_nav(self.t, bool(self.copter.estimate.ext_nav_in_use), self.tick_us / 1e6)
        self._observe()

    def _send_due(self) -> None:
        """Log sample and every stream due at the current tick, on every link."""
        if self.t_us >= self._next_sample_us:
            self._record_sample()
            self._next_sample_us = _next_due(self._next_sample_us, LOG_SAMPLE_INTERVAL_US, self.t_us)
        built: dict[int, mav.MAVLink_message | None] = {}
        for link in self.links:
            for msgid in link.due(self.t_us):
                if msgid not in built:
                    built[msgid] = self._builders[msgid]()
                msg = built[msgid]
                if msg is not None:
                    link.send(msg)

    def _wait_until(self, wall_deadline: float) -> None:
        """Handle incoming traffic until time.monotonic() reaches ``wall_deadline`` (real time)."""
        while True:
            self._service_all()
            remaining = wall_deadline - time.monotonic()
            if remaining <= 0:
                return
            self._select(remaining)

    def _await_companion(self) -> None:
        """Lockstep start: wait for the companion's HEARTBEAT, sending ours at 1 Hz wall time."""
        next_heartbeat = time.monotonic()
        while True:
            if time.monotonic() >= next_heartbeat:
                heartbeat = self._heartbeat()
                for link in self.links:
                    link.send(heartbeat)
                next_heartbeat += 1.0
            self._service_all()
            if self._companion_heard:
                return
            self._select(next_heartbeat - time.monotonic())

    def _sync(self) -> None:
        """Lockstep: TIMESYNC(tc1=0, ts1=t ns) to the companion, then handle traffic until its reply.

        The reply is a TIMESYNC on the companion link with tc1 != 0 and the same ts1. Messages
        behind it on the companion link stay queued for the next tick, so what the companion
        sends between two replies is always handled at the same simulation time.
        """
        self._awaited_ts1 = self.t_us * 1000
        self.companion.send(mav.MAVLink_timesync_message(0, self._awaited_ts1))
        started = time.monotonic()
        warned = False
        while not self._service_all():
            waited = time.monotonic() - started
            if waited >= LOCKSTEP_FAIL_S:
                print(f"sitl.vehicle: lockstep: no TIMESYNC reply for tick {self.n} (t={self.t:.3f} s) "
                      f"within {LOCKSTEP_FAIL_S:.0f} s; giving up", file=sys.stderr, flush=True)
                raise _Shutdown(EXIT_LOCKSTEP_TIMEOUT)
            if waited >= LOCKSTEP_WARN_S and not warned:
                print(f"sitl.vehicle: lockstep: no TIMESYNC reply for tick {self.n} (t={self.t:.3f} s) "
                      f"within {LOCKSTEP_WARN_S:.0f} s; still waiting", file=sys.stderr, flush=True)
                warned = True
            self._select((LOCKSTEP_FAIL_S if warned else LOCKSTEP_WARN_S) - waited)
        self._awaited_ts1 = None

    def _select(self, timeout_s: float) -> None:
        """Block until a link or the stop pipe is readable, or ``timeout_s`` passes."""
        fds = [link.fileno() for link in self.links] + [self._wake_r.fileno()]  # tcpin's fd changes
        readable, _, _ = select.select(fds, [], [], max(0.0, timeout_s))
        if self._wake_r.fileno() in readable:
            try:
                while self._wake_r.recv(64):
                    pass
            except BlockingIOError:
                pass
        if self._stop_requested:
            raise _Shutdown(0)

    # ------------------------------------------------------------------ receiving

    def _service_all(self) -> bool:
        """Handle every waiting message on every link; True if the awaited lockstep reply came."""
        replied = False
        for link in self.links:
            replied = self._service(link) or replied
        return replied

    def _service(self, link: Link) -> bool:
        """Handle a link's waiting messages in order; stops after the awaited lockstep reply."""
        while True:
            msg = link.recv()
            if msg is None:
                return False
            if self._dispatch(link, msg):
                return True

    def _dispatch(self, link: Link, msg: mav.MAVLink_message) -> bool:
        """Route and handle one message; True if it is the awaited lockstep reply."""
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            return False
        if mtype == "TIMESYNC":
            return self._on_timesync(link, msg)
        target_system = getattr(msg, "target_system", 0)
        target_component = getattr(msg, "target_component", 0)
        for_me = target_system in (0, self.sysid) and target_component in (0, COMPID)
        if not (target_system == self.sysid and target_component in (0, COMPID)):
            for other in self.links:
                if other is not link:
                    other.forward(msg)
        handler = self._handlers.get(mtype)
        if for_me and handler is not None:
            handler(link, msg)
            self._observe()
        return False

    def _signature_refused(self, signed: bool) -> None:
        """Signing on: an unsigned (``signed`` False) or badly signed message on the companion link was dropped."""
        counts = self.log.signing
        if counts["unsigned_rejected"] + counts["bad_signatures"] == 0:
            print(f"sitl.vehicle: dropped {'a badly signed' if signed else 'an unsigned'} message on the companion "
                  "link (--signing-key): does the companion sign with the same key (mavlink.signing_key_file)?",
                  file=sys.stderr, flush=True)
        counts["bad_signatures" if signed else "unsigned_rejected"] += 1

    def _on_timesync(self, link: Link, msg: mav.MAVLink_message) -> bool:
        """Answer TIMESYNC requests; recognise the companion's reply to the lockstep tick."""
        if msg.tc1 == 0:
            now_ns = self.t_us * 1000 if self.cfg.lockstep else int(self._now() * 1e9)
            link.send(mav.MAVLink_timesync_message(max(1, now_ns), msg.ts1))
            return False
        return link is self.companion and self._awaited_ts1 is not None and msg.ts1 == self._awaited_ts1

    def _on_heartbeat(self, link: Link, msg: mav.MAVLink_message) -> None:
        if link is self.companion and msg.get_srcComponent() != COMPID:
            self._companion_heard = True

    def _on_set_mode(self, link: Link, msg: mav.MAVLink_message) -> None:
        result = self._set_mode(msg.base_mode, msg.custom_mode)
        self._ack(link, msg, mav.MAVLINK_MSG_ID_SET_MODE, result)

    def _on_request_data_stream(self, link: Link, msg: mav.MAVLink_message) -> None:
        """Legacy stream groups: rate Hz, or stop when start_stop is 0 or the rate is 0."""
        groups = STREAM_GROUPS.values() if msg.req_stream_id == mav.MAV_DATA_STREAM_ALL else (
            [STREAM_GROUPS[msg.req_stream_id]] if msg.req_stream_id in STREAM_GROUPS else [])
        on = msg.start_stop != 0 and msg.req_message_rate > 0
        interval = int(round(1e6 / msg.req_message_rate)) if on else None
        for group in groups:
            for msgid in group:
                link.set_interval(msgid, interval, self.t_us)

    def _on_set_gps_global_origin(self, link: Link, msg: mav.MAVLink_message) -> None:
        """Set the EKF origin (only if none yet) and confirm with GPS_GLOBAL_ORIGIN, like ArduPilot."""
        if self.copter.set_origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3):
            origin = self._gps_global_origin()
            if origin is not None:
                link.send(origin)

    def _on_set_home_position(self, link: Link, msg: mav.MAVLink_message) -> None:
        self.copter.set_home(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        self._last_home = None  # _observe announces it

    def _on_vision_position(self, link: Link, msg: mav.MAVLink_message) -> None:
        """VISION_POSITION_ESTIMATE: world-frame position (m) and ZYX Euler (rad) at ``usec``."""
        t_rx = self._now()
        pos = (msg.x, msg.y, msg.z)
        euler = (msg.roll, msg.pitch, msg.yaw)
        self.log.add_vision_position(t_rx, msg.usec, pos, euler, msg.reset_counter, msg.covariance[0])
        t_capture = self._vision_capture_time(link, msg.usec, t_rx, pos + euler)
        if t_capture is not None:
            self.copter.vision_position(t_capture, np.array(pos), np.array(euler), _covariance(msg), msg.reset_counter)

    def _on_vision_speed(self, link: Link, msg: mav.MAVLink_message) -> None:
        """VISION_SPEED_ESTIMATE: world-frame velocity (m/s) at ``usec``."""
        t_rx = self._now()
        vel = (msg.x, msg.y, msg.z)
        self.log.add_vision_speed(t_rx, msg.usec, vel)
        t_capture = self._vision_capture_time(link, msg.usec, t_rx, vel)
        if t_capture is not None:
            self.copter.vision_speed(t_capture, np.array(vel), _covariance(msg), msg.reset_counter)

    def _vision_capture_time(self, link: Link, usec: int, t_rx: float, values: tuple[float, ...]) -> float | None:
        """Sim time of a vision sample, or None (counted) if a value is non-finite or the stamp is dropped."""
        if not _finite(values):
            self._nonfinite += 1
            return None
        return self._capture_time(link, usec, t_rx)

    def _capture_time(self, link: Link, usec: int, t_rx: float) -> float | None:
        """Sim time of a companion capture stamp (JitterCorrection); None (counted) if dropped."""
        t_capture = link.jitter.correct(usec * 1e-6, t_rx)
        if t_capture is None:
            self._stale_or_future += 1
        return t_capture

    def _on_set_position_target(self, link: Link, msg: mav.MAVLink_message) -> None:
        """SET_POSITION_TARGET_LOCAL_NED addressed to this system -> the copter's guided controller."""
        if msg.target_system != self.sysid:
            return
        pos, vel, acc = (msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz), (msg.afx, msg.afy, msg.afz)
        self.log.add_setpoint(self._now(), msg.coordinate_frame, msg.type_mask, pos, vel, acc)
        self.copter.set_position_target(
            msg.coordinate_frame, msg.type_mask, np.array(pos), np.array(vel), np.array(acc),
            msg.yaw, msg.yaw_rate)

    # ------------------------------------------------------------------ commands

    def _on_command_long(self, link: Link, msg: mav.MAVLink_message) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._run_command(link, msg, msg.command, params, None)

    def _on_command_int(self, link: Link, msg: mav.MAVLink_message) -> None:
        """COMMAND_INT: x/y are degE7 for positional commands, plain integers otherwise."""
        scale = 1e-7 if msg.command in LATLON_COMMANDS else 1.0
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x * scale, msg.y * scale, msg.z)
        self._run_command(link, msg, msg.command, params, msg.frame)

    def _run_command(self, link: Link, msg: mav.MAVLink_message, command: int,
                     params: tuple[float, ...], frame: int | None) -> None:
        """Handle a command, ACK it, then send what it asked for (ArduPilot's order)."""
        self._replies = []
        handler = self._commands.get(command)
        try:
            result = handler(link, params, frame) if handler else mav.MAV_RESULT_UNSUPPORTED
        except (ValueError, OverflowError):  # int() of a NaN or infinite parameter
            self._nonfinite += 1
            result = mav.MAV_RESULT_DENIED
        self._ack(link, msg, command, result)
        for reply in self._replies:
            link.send(reply)

    def _ack(self, link: Link, msg: mav.MAVLink_message, command: int, result: int) -> None:
        """COMMAND_ACK to the sender (progress and result_param2 0, as ArduPilot) and log it."""
        link.send(mav.MAVLink_command_ack_message(
            command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        self.log.add_command(self._now(), command, result)

    def _cmd_set_message_interval(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 message id, param2 interval us (0 default rate, -1 off)."""
        if self.cfg.legacy_streams:
            return mav.MAV_RESULT_UNSUPPORTED
        msgid = int(p[0])
        refused = msgid in self.cfg.refuse_intervals  # answered as ArduPilot 4.0 does (FAILED)
        if refused or msgid not in self._builders:
            self._texts.append((mav.MAV_SEVERITY_INFO, f"No ap_message for mavlink id ({msgid})"))
            return mav.MAV_RESULT_FAILED if refused else mav.MAV_RESULT_DENIED
        if p[1] < 0:
            interval: int | None = None
        elif p[1] == 0:
            interval = HEARTBEAT_INTERVAL_US if msgid == mav.MAVLINK_MSG_ID_HEARTBEAT else DEFAULT_STREAM_INTERVAL_US
        else:
            interval = int(round(p[1]))
        link.set_interval(msgid, interval, self.t_us)
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_get_message_interval(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        msgid = int(p[0])
        if msgid not in self._builders:
            return mav.MAV_RESULT_DENIED
        self._replies.append(mav.MAVLink_message_interval_message(msgid, link.intervals_us.get(msgid, -1)))
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_request_message(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 message id: sent once now if there is something to send."""
        builder = self._requestable.get(int(p[0]))
        if builder is None:
            return mav.MAV_RESULT_FAILED
        msg = builder()
        if msg is not None:
            self._replies.append(msg)
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_request_capabilities(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        self._replies.append(self._autopilot_version())
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_do_set_mode(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 base mode (CUSTOM_MODE_ENABLED), param2 custom (copter) mode."""
        return self._set_mode(int(p[0]), int(p[1]))

    def _set_mode(self, base_mode: int, custom_mode: int) -> int:
        if not base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mav.MAV_RESULT_UNSUPPORTED
        ok, reason = self.copter.set_mode(custom_mode)
        if ok:
            return mav.MAV_RESULT_ACCEPTED
        text = reason if reason.startswith("Mode change") else f"Mode change failed: {reason}"
        self._texts.append((mav.MAV_SEVERITY_WARNING, text))
        return mav.MAV_RESULT_FAILED

    def _cmd_arm_disarm(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 1 arm / 0 disarm, param2 21196 forces."""
        force = p[1] == FORCE_MAGIC
        if p[0] == 1:
            ok, _ = self.copter.arm(force=force)
        elif p[0] == 0:
            ok, _ = self.copter.disarm(force=force)
        else:
            return mav.MAV_RESULT_UNSUPPORTED
        return mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_FAILED

    def _cmd_takeoff(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param7 altitude above home (m)."""
        ok, _ = self.copter.takeoff(p[6])
        return mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_FAILED

    def _cmd_land(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        ok, _ = self.copter.land()
        return mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_FAILED

    def _cmd_set_servo(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 output number (1..32), param2 PWM (us); the flight log's commands record it."""
        if not (1 <= int(p[0]) <= 32 and 500 <= int(p[1]) <= 2500):
            return mav.MAV_RESULT_DENIED
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_gripper(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 gripper instance (>= 1), param2 GRIPPER_ACTIONS (0 release, 1 grab)."""
        if int(p[0]) < 1 or int(p[1]) not in (mav.GRIPPER_ACTION_RELEASE, mav.GRIPPER_ACTION_GRAB):
            return mav.MAV_RESULT_DENIED
        if int(p[1]) == mav.GRIPPER_ACTION_RELEASE:
            self._texts.append((mav.MAV_SEVERITY_INFO, "Gripper load released"))
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_set_home(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 1: current position; else param5/6 lat/lon (deg), param7 alt (m AMSL, or per frame)."""
        if p[0] == 1:
            location = self._estimated_location()
            if location is None:
                return mav.MAV_RESULT_FAILED
            lat, lon, alt = location
        else:
            lat, lon, alt = p[4], p[5], p[6]
            if frame in RELATIVE_FRAMES and self.copter.home_position is not None:
                alt += self.copter.home_position[2]
            elif frame is not None and frame not in AMSL_FRAMES:
                return mav.MAV_RESULT_DENIED
            if not (_finite((lat, lon, alt)) and abs(lat) <= 90 and abs(lon) <= 180):
                return mav.MAV_RESULT_FAILED
        self.copter.set_home(lat, lon, alt)
        self._last_home = None  # _observe announces it after the ACK
        return mav.MAV_RESULT_ACCEPTED

    # ------------------------------------------------------------------ state tracking

    def _observe(self) -> None:
        """After a step or a handled message: statustexts, mode, origin and home changes."""
        now = self._now()
        texts, self._texts = self._texts + self.copter.drain_statustext(), []
        for severity, text in texts:
            self._statustext(severity, text)
        self.log.add_mode(now, self.copter.mode_name, self.copter.armed)
        if self.copter.mode != self._announced_mode:
            # ArduPilot's set_mode() sends a HEARTBEAT on every link at once
            # (gcs().send_message(MSG_HEARTBEAT)): a companion learns of a pilot takeover
            # without waiting for the 1 Hz stream.
            self._announced_mode = self.copter.mode
            heartbeat = self._heartbeat()
            for link in self.links:
                link.send(heartbeat)
        origin = self.copter.origin
        if origin is not None:
            self.log.set_origin(now, *origin)
        home = self.copter.home_position
        if home is not None and tuple(home) != self._last_home:
            self._announce_home()

    def _announce_home(self) -> None:
        """HOME_POSITION and GPS_GLOBAL_ORIGIN to every link, as ArduPilot does on a new home."""
        home = self.copter.home_position
        self._last_home = None if home is None else tuple(home)
        for build in (self._home_position, self._gps_global_origin):
            msg = build()
            if msg is not None:
                for link in self.links:
                    link.send(msg)

    def _statustext(self, severity: int, text: str) -> None:
        """STATUSTEXT on every link (truncated to 50 characters, as ArduPilot) and in the log."""
        self.log.add_statustext(self._now(), severity, text)
        wire = text.encode("ascii", "replace")[:STATUSTEXT_LEN]
        msg = mav.MAVLink_statustext_message(severity, wire, 0, 0)
        for link in self.links:
            link.send(msg)

    def _record_sample(self) -> None:
        truth, est = self.copter.truth, self.copter.estimate
        self.log.sample(self.t, truth_pos=truth.pos_ned, truth_vel=truth.vel_ned, truth_euler=truth.euler,
                        est_valid=est.pos_valid, est_pos=est.pos_ned)

    def _write_log(self) -> None:
        if self.cfg.log is None:
            return
        self.log.rejected = {
            "nonfinite": self._nonfinite + int(self.copter.nonfinite_rejected),
            "stale_or_future": self._stale_or_future,
            "gated": int(self.copter.estimate.rejected_ext_nav),
        }
        self.log.write(self.cfg.log, self.t)

    def _estimated_location(self) -> tuple[float, float, float] | None:
        """(lat deg, lon deg, alt m AMSL) of the estimate, None without a valid position and origin."""
        origin = self.copter.origin
        if origin is None or not self.copter.estimate.pos_valid:
            return None
        return geodetic_from_ned(self.copter.estimate.pos_ned, tuple(origin))

    # ------------------------------------------------------------------ outgoing messages

    @property
    def _time_boot_ms(self) -> int:
        return self.t_us // 1000

    def _mag_body_gauss(self) -> np.ndarray:
        """Earth field seen by a body-fixed magnetometer at the true attitude (gauss, FRD)."""
        return rotation_from_quat(self.copter.truth.quat).T @ EARTH_FIELD_NED_GAUSS

    def _heartbeat(self) -> mav.MAVLink_message:
        c = self.copter
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_STABILIZE_ENABLED
        if c.mode == MODE_GUIDED:
            base |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        if c.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        status = mav.MAV_STATE_ACTIVE if c.armed else mav.MAV_STATE_STANDBY
        return mav.MAVLink_heartbeat_message(
            mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, base, c.mode, status, 3)

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
        throttle = 0
        if c.armed and not c.landed:
            throttle = _clamp_int(50.0 * -float(c.truth.accel_body[2]) / GRAVITY_MPS2, 0, 100)
        speed = math.hypot(vn, ve)
        heading = int(math.degrees(float(est.euler[2])) % 360.0) % 360
        return mav.MAVLink_vfr_hud_message(speed, speed, heading, throttle, alt, -vd)

    def _extended_sys_state(self) -> mav.MAVLink_message:
        c = self.copter
        if c.landed:
            landed = mav.MAV_LANDED_STATE_ON_GROUND
        elif c.mode == MODE_LAND:
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

    def _autopilot_version(self) -> mav.MAVLink_message:
        return mav.MAVLink_autopilot_version_message(
            CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, self.sysid, [0] * 18)


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


def _floats(count: int) -> Callable[[str], tuple[float, ...]]:
    """argparse type: ``count`` comma-separated floats."""

    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated numbers") from None
        if len(values) != count or not _finite(values):
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated finite numbers")
        return values

    return parse


def parse_args(argv: Sequence[str] | None = None) -> VehicleConfig:
    """The command line as a :class:`VehicleConfig`."""
    p = argparse.ArgumentParser(prog="python -m sitl.vehicle", description=__doc__.split("\n", 1)[0])
    p.add_argument("--companion", required=True, help="pymavlink URL of the companion link, e.g. udpin:127.0.0.1:14555")
    p.add_argument("--gcs", action="append", default=[], help="pymavlink URL of a ground-station link (repeatable)")
    p.add_argument("--lockstep", action="store_true", help="drive the companion's clock with TIMESYNC ticks")
    p.add_argument("--tick", type=float, default=0.005, help="simulation tick, s (default 0.005)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seconds", type=float, default=None, help="simulation seconds to run, then exit 0")
    p.add_argument("--log", default=None, help="flight log JSON written at exit")
    p.add_argument("--home", type=_floats(3), default=DEFAULT_HOME, help="arena anchor LAT,LON,ALT (deg, deg, m AMSL)")
    p.add_argument("--no-gps", action="store_true", help="no GPS receiver")
    p.add_argument("--position-source", choices=("extnav", "gps"), default="extnav")
    p.add_argument("--wind", type=_floats(3), default=None, help="mean wind N,E,D (m/s)")
    p.add_argument("--gust", type=float, default=None, help="gust standard deviation (m/s)")
    p.add_argument("--start", type=_floats(3), default=(0.0, 0.0, 0.0), help="start pose N,E,YAW_DEG (m, m, deg)")
    p.add_argument("--sysid", type=int, default=1)
    p.add_argument("--refuse-interval", type=int, action="append", default=[], metavar="MSGID",
                   help="answer SET_MESSAGE_INTERVAL for this message id with MAV_RESULT_FAILED, as ArduPilot 4.0 does "
                        "for HIGHRES_IMU (105) and SIM_STATE (108) (repeatable)")
    p.add_argument("--legacy-streams", action="store_true",
                   help="answer SET_MESSAGE_INTERVAL with MAV_RESULT_UNSUPPORTED, as firmware that only knows "
                        "REQUEST_DATA_STREAM groups does")
    p.add_argument("--signing-key", metavar="FILE", default=None,
                   help="MAVLink 2 signing on the companion link with this key (32 raw bytes or 64 hex characters)")
    a = p.parse_args(argv)
    if a.tick <= 0 or (a.seconds is not None and a.seconds < 0) or not 1 <= a.sysid <= 255:
        p.error("--tick must be > 0, --seconds >= 0 and --sysid 1..255")
    try:
        key = load_signing_key(Path(a.signing_key)) if a.signing_key else None
    except (OSError, ValueError) as exc:
        p.error(f"--signing-key: {exc}")
    return VehicleConfig(
        companion=a.companion, gcs=tuple(a.gcs), lockstep=a.lockstep, tick_s=a.tick, seed=a.seed,
        seconds=a.seconds, log=a.log, home=a.home, gps=not a.no_gps, position_source=a.position_source,
        wind_ned_mps=a.wind, gust_mps=a.gust, start=a.start, sysid=a.sysid, legacy_streams=a.legacy_streams,
        refuse_intervals=tuple(a.refuse_interval), signing_key=key)


@contextmanager
def _stop_on_signals(vehicle: Vehicle) -> Iterator[None]:
    """SIGTERM/SIGINT end the run cleanly (main thread only; elsewhere signals are left alone)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    for sig in previous:
        signal.signal(sig, lambda _signum, _frame: vehicle.request_stop())
    previous_wakeup = signal.set_wakeup_fd(vehicle.wake_fd, warn_on_full_buffer=False)
    try:
        yield
    finally:
        signal.set_wakeup_fd(previous_wakeup)
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the simulated vehicle; returns the exit status (0, or 3 for a lockstep timeout)."""
    vehicle = Vehicle(parse_args(argv))
    try:
        with _stop_on_signals(vehicle):
            return vehicle.run()
    finally:
        vehicle.close()


if __name__ == "__main__":
    sys.exit(main())
