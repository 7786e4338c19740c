"""The harness's view of an ArduPilot SITL run: a MAVLink tap for the daemon, a ground link for
truth, and the flight log they fill (the same document as the built-in vehicle's, sitl/flight_log.py).

- **Tap**: the daemon connects to a loopback TCP port of the harness instead of SITL's SERIAL0;
  every byte is forwarded unchanged both ways, and parsed on the side: what the companion sent
  (VISION_POSITION_ESTIMATE, VISION_SPEED_ESTIMATE, DISTANCE_SENSOR, SET_POSITION_TARGET_LOCAL_NED and a
  fixed wing's guided waypoints, MISSION_ITEM_INT in MAV_FRAME_GLOBAL, as position setpoints in the truth
  frame; commands, origin) is logged with its arrival time, as the built-in vehicle logs what it receives. The
  tap mirrors the connection: SITL gone -> the daemon's connection is closed; the daemon
  reconnecting -> a new connection to SITL. Only the harness sees it: the daemon talks to
  ArduPilot exactly as it would on TCP.
- **Ground link** (SITL's SERIAL1, as a listening ground station: sysid 254, see GROUND_SYSID): SIMSTATE and SCALED_PRESSURE
  give the truth (``sitl.truth``: true attitude and position, the altitude from SITL's
  noiseless barometer), HEARTBEAT the mode and arming, STATUSTEXT the EKF's "using external nav",
  GPS_GLOBAL_ORIGIN the origin, LOCAL_POSITION_NED the autopilot's own estimate. It reconnects by
  itself after SITL restarts. It also sets the parameters of ``sitl.ardupilot.parameter_events`` at
  their flight times (PARAM_SET, read back): faults injected into the autopilot.

Times are seconds since :class:`ArduPilotObserver` started (time.monotonic() - t0): the daemon
stamps its estimates with the same CLOCK_MONOTONIC, so ``clock.monotonic_at_sim_zero`` in the log
maps them onto this time line. Everything runs on one asyncio loop in a thread of the harness.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from companion.config import MavlinkConfig, OriginConfig, ParameterEvent, StreamRatesConfig, VehicleConfig
from companion.frames import euler_from_quat, ned_from_geodetic
from companion.health import Health
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.commands import Commander
from companion.mavlink.link import MavlinkLink, mavlink, nonfinite_fields
from companion.mavlink.params import ParameterClient, ParamError
from companion.mavlink.setpoints import GUIDED_WAYPOINT_CURRENT, Setpoint
from companion.mavlink.streams import StreamNegotiator
from sitl.truth import TruthSample, TruthSource
from sitl.flight_log import FlightLog

log = logging.getLogger("companion.sitl.ardupilot")

# Not 255: ArduPilot takes heartbeats from SYSID_MYGCS (255) as a ground station being there,
# which would hide its GCS failsafe; the observer only listens.
GROUND_SYSID, GROUND_COMPID = 254, mavlink.MAV_COMP_ID_MISSIONPLANNER
TRUTH_HZ = 50.0
ORIGIN_POLL_S = 2.0
# What the tap keeps the arrival times of, per direction (the fault tests read them).
THREAD_NAME = "ardupilot-observer"
WATCHED = {"to_autopilot": ("SET_GPS_GLOBAL_ORIGIN", "SET_HOME_POSITION", "COMMAND_LONG", "REQUEST_DATA_STREAM",
                            "VISION_POSITION_ESTIMATE", "HEARTBEAT"),
           "to_companion": ("HEARTBEAT", "COMMAND_ACK")}


@dataclass
class TapRecord:
    """Arrival times (observer seconds) of the watched messages, and what the tap counted."""

    times: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))  # "direction:TYPE" -> times
    stream_requests: list[tuple[float, int]] = field(default_factory=list)  # (t, message id) of SET_MESSAGE_INTERVAL
    connections: int = 0
    nonfinite: int = 0

    def first_after(self, key: str, t: float) -> float | None:
        return next((x for x in self.times.get(key, ()) if x >= t), None)


class _Parser:
    """A MAVLink parser that never raises (garbage is skipped)."""

    def __init__(self) -> None:
        self.codec = mavlink.MAVLink(None, GROUND_SYSID, GROUND_COMPID)
        self.codec.robust_parsing = True

    def feed(self, data: bytes) -> list[mavlink.MAVLink_message]:
        try:
            return [m for m in self.codec.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]
        except Exception:  # a frame pymavlink cannot decode: drop what is buffered
            self.codec.buf, self.codec.buf_index = bytearray(), 0
            return []


class ArduPilotObserver:
    """Tap + ground link + flight log for one run; see the module docstring."""

    def __init__(self, *, serial0_port: int, serial1_port: int, seed: int, autopilot_sysid: int = 1,
                 parameter_events: list[ParameterEvent] | None = None) -> None:
        self.serial0_port = serial0_port
        self.serial1_port = serial1_port
        self.parameter_events = sorted(parameter_events or [], key=lambda e: e.at_s)
        self.origin: OriginConfig | None = None  # the frame of the truth, from begin()
        self.seed = seed
        self.autopilot_sysid = autopilot_sysid
        self.t0 = time.monotonic()
        self.log = FlightLog(seed=seed, lockstep=False, monotonic_at_sim_zero=self.t0)  # begin() starts it anew
        self.tap = TapRecord()
        self.tap_port: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._stopped: asyncio.Event | None = None
        self._tasks: list[asyncio.Task] = []
        self._error: BaseException | None = None
        self._last_truth_t: float | None = None
        self.state: AutopilotState | None = None

    def now(self) -> float:
        """Observer time: seconds since start."""
        return time.monotonic() - self.t0

    # -- lifecycle (called from the harness thread) ----------------------------------------

    def start(self, timeout_s: float = 5.0) -> int:
        """Start the observer thread with the tap; the tap's port (the daemon's endpoint: tcp:127.0.0.1:PORT)."""
        self._thread = threading.Thread(target=self._thread_main, name=THREAD_NAME, daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s) or self.tap_port is None:
            raise RuntimeError(f"the ArduPilot observer did not start: {self._error}")
        return self.tap_port

    def begin(self, origin: OriginConfig) -> None:
        """Time zero of the flight log: connect the ground link and record truth in the frame at
        ``origin`` from now on."""
        assert self._loop is not None
        self.origin = origin
        self.t0 = time.monotonic()
        self.log = FlightLog(seed=self.seed, lockstep=False, monotonic_at_sim_zero=self.t0)
        started = threading.Event()

        def connect() -> None:
            self._tasks.extend(self._ground_link())
            started.set()

        self._loop.call_soon_threadsafe(connect)
        started.wait(2.0)

    def stop(self, timeout_s: float = 3.0) -> None:
        if self._loop is not None and self._stopped is not None:
            self._loop.call_soon_threadsafe(self._stopped.set)
        if self._thread is not None:
            self._thread.join(timeout_s)

    def write_log(self, path: Path) -> None:
        self.log.write(str(path), self.now())

    # -- the observer's loop -----------------------------------------------------------------

    def _thread_main(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # reported by start() or logged
            self._error = exc
            log.exception("ArduPilot observer failed")
            self._ready.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stopped = asyncio.Event()
        server = await asyncio.start_server(self._tap_connection, "127.0.0.1", 0)
        self.tap_port = server.sockets[0].getsockname()[1]
        self._ready.set()
        try:
            await self._stopped.wait()
        finally:
            server.close()
            for task in self._tasks:
                task.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)
            await server.wait_closed()

    def _ground_link(self) -> list[asyncio.Task]:
        cfg = MavlinkConfig(url=f"tcp:127.0.0.1:{self.serial1_port}", link_timeout_s=2.0, streams=StreamRatesConfig(
            attitude=0, imu=0, local_position=10, gps_raw=0, home_position=1, estimator_status=5, sim_state=TRUTH_HZ))
        ids = VehicleConfig(sysid=GROUND_SYSID, compid=GROUND_COMPID, autopilot_sysid=self.autopilot_sysid)
        health = Health(lambda: self.now())
        link = MavlinkLink(cfg, ids, cfg.url, health)
        self.state = state = AutopilotState(link)
        commander = Commander(link, state, cfg)
        streams = StreamNegotiator(link, state, commander, cfg.streams, health)
        assert self.origin is not None
        TruthSource(link, self.origin, listener=self._on_truth)
        link.subscribe("HEARTBEAT", self._on_heartbeat)
        link.subscribe("STATUSTEXT", self._on_statustext)
        link.subscribe("GPS_GLOBAL_ORIGIN", self._on_origin)
        loop = asyncio.get_running_loop()
        params = ParameterClient(link, lambda: state.firmware)
        return [loop.create_task(link.run()), loop.create_task(streams.run()),
                loop.create_task(commander.identify_every_connection()),
                loop.create_task(self._poll_origin(commander)), loop.create_task(self._set_parameters(params))]

    async def _set_parameters(self, params: ParameterClient) -> None:
        """Each of ``parameter_events`` at its time (observer seconds since begin()); a failed write is logged."""
        for event in self.parameter_events:
            await asyncio.sleep(max(0.0, event.at_s - self.now()))
            try:
                await params.write(event.name, event.value)
                log.info("t=%.1f s: %s set to %g", self.now(), event.name, event.value)
            except ParamError as exc:
                log.error("t=%.1f s: parameter event failed: %s", self.now(), exc)

    async def _poll_origin(self, commander: Commander) -> None:
        """Ask for GPS_GLOBAL_ORIGIN until the autopilot has one (ArduPilot sends it on request)."""
        while self.log.origin["set_at"] is None:
            await asyncio.sleep(ORIGIN_POLL_S)
            await commander.command_result(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)

    # -- ground link records -----------------------------------------------------------------

    def _on_truth(self, sample: TruthSample) -> None:
        """Every truth sample, with the autopilot's own estimate (in the origin frame) beside it."""
        state = self.state
        estimate = state.local_position_ned if state is not None else None
        t = sample.t - self.t0
        self.log.sample(t, truth_pos=sample.position_ned, truth_vel=sample.velocity_ned,
                        truth_euler=euler_from_quat(sample.quat), est_valid=estimate is not None,
                        est_pos=estimate if estimate is not None else np.full(3, math.nan))
        if state is not None and self._last_truth_t is not None:
            self.log.add_external_nav(t, state.external_nav_in_use, t - self._last_truth_t)
        self._last_truth_t = t

    def _on_heartbeat(self, msg: mavlink.MAVLink_message) -> None:
        if self.state is not None and self.state.mode is not None:
            self.log.add_mode(self.now(), self.state.mode, self.state.armed)

    def _on_statustext(self, msg: mavlink.MAVLink_message) -> None:
        self.log.add_statustext(self.now(), msg.severity, msg.text)

    def _on_origin(self, msg: mavlink.MAVLink_message) -> None:
        self.log.set_origin(self.now(), msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)

    # -- the tap -----------------------------------------------------------------------------

    async def _tap_connection(self, down_reader: asyncio.StreamReader, down_writer: asyncio.StreamWriter) -> None:
        """One daemon connection: forward it to SITL's SERIAL0 until either side ends."""
        self.tap.connections += 1
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.serial0_port)
        except OSError:  # SITL is not there: hang up, as SITL itself would refuse
            down_writer.close()
            return
        pumps = [asyncio.ensure_future(self._pump(down_reader, up_writer, "to_autopilot")),
                 asyncio.ensure_future(self._pump(up_reader, down_writer, "to_companion"))]
        try:
            await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for pump in pumps:
                pump.cancel()
            for writer in (up_writer, down_writer):
                writer.close()
                with contextlib.suppress(OSError, asyncio.CancelledError):
                    await writer.wait_closed()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, direction: str) -> None:
        parser = _Parser()
        while True:
            data = await reader.read(65536)
            if not data:
                return
            writer.write(data)
            t = self.now()
            for msg in parser.feed(data):
                self._tapped(t, direction, msg)
            await writer.drain()

    def _tapped(self, t: float, direction: str, msg: mavlink.MAVLink_message) -> None:
        kind = msg.get_type()
        if kind in WATCHED[direction]:
            self.tap.times[f"{direction}:{kind}"].append(t)
        if direction == "to_companion":
            if kind == "COMMAND_ACK":
                self.log.add_command(t, msg.command, msg.result)
            return
        if nonfinite_fields(msg):
            self.tap.nonfinite += 1
            self.log.rejected["nonfinite"] += 1
            return
        if kind == "VISION_POSITION_ESTIMATE":
            self.log.add_vision_position(t, msg.usec, (msg.x, msg.y, msg.z), (msg.roll, msg.pitch, msg.yaw),
                                         msg.reset_counter, msg.covariance)
        elif kind == "VISION_SPEED_ESTIMATE":
            self.log.add_vision_speed(t, msg.usec, (msg.x, msg.y, msg.z))
        elif kind == "DISTANCE_SENSOR":
            self.log.add_distance_sensor(t, msg.time_boot_ms, msg.id, msg.orientation, msg.current_distance,
                                         msg.min_distance, msg.max_distance)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            self.log.add_setpoint(t, msg.coordinate_frame, msg.type_mask, (msg.x, msg.y, msg.z),
                                  (msg.vx, msg.vy, msg.vz), (msg.afx, msg.afy, msg.afz))
        elif kind == "MISSION_ITEM_INT" and msg.current == GUIDED_WAYPOINT_CURRENT and self.origin is not None \
                and msg.frame == mavlink.MAV_FRAME_GLOBAL:
            o = self.origin
            target = Setpoint(position_ned=ned_from_geodetic(msg.x * 1e-7, msg.y * 1e-7, msg.z, (o.lat, o.lon, o.alt)))
            self.log.add_setpoint(t, mavlink.MAV_FRAME_LOCAL_NED, target.type_mask, target.position_ned, (0, 0, 0),
                                  (0, 0, 0))
        elif kind == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            self.tap.stream_requests.append((t, int(msg.param1)))
