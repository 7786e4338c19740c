"""The companion daemon: wires the link, estimate output, setpoints, nav loop, telemetry and
mission together under one supervisor, and shuts all of it down cleanly on SIGTERM/SIGINT.

What systemd sees: READY=1 once the tasks run, STATUS= with the health summary, WATCHDOG=1
only while the nav loop turns, STOPPING=1 on shutdown, exit 0 within 2 s of SIGTERM.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import resource
import signal
import threading
import time
import uuid
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from companion import clock, plugins
from companion.config import Config
from companion.crosscheck import AttitudeCrossCheck
from companion.health import ComponentHealth, Health, State
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.commands import CommandFailed, Commander
from companion.mavlink.distance import DistanceSender
from companion.mavlink.estimate import EstimateSender
from companion.mavlink.inbound import InboundCommands
from companion.mavlink.link import MavlinkLink, load_signing_key, mavlink
from companion.mavlink.origin import OriginSetter
from companion.mavlink.setpoints import SetpointStream
from companion.mavlink.streams import StreamNegotiator
from companion.messages import PoseEstimate
from companion.mission.context import MissionContext
from companion.mission.failsafe import Geofence
from companion.mission.runner import MissionRunner
from companion.mission.steps import Mission, load_mission
from companion.navloop import NavLoop, NavOutputs, build_pipelines, build_selector
from companion.pipeline import GuidanceSource, Pipeline
from companion.sdnotify import Notifier, WatchdogGate, run_watchdog
from companion.selection import SourceSelector
from companion.sensors import SensorContext, build_driver, check_sensor_files
from companion.supervisor import Supervisor
from companion.telemetry.publisher import TelemetryPublisher
from companion.telemetry.session import open_session
from drivers.base import SensorDriver

if TYPE_CHECKING:
    from companion.recording.recorder import Recorder

log = logging.getLogger("companion.daemon")

SHUTDOWN_BUDGET_S = 1.5
# How long a worker thread (telemetry encoding, zenoh callbacks) may hold the GIL before the event
# loop's thread gets it back: Python's 5 ms default would add up to 5 ms to a nav-loop wake-up.
GIL_SWITCH_INTERVAL_S = 0.0005
STATIC_STREAM_PERIOD_S = 2.0  # pipelines' static streams (a map) are re-published this often for late listeners
STATUSTEXT_SEVERITY = {State.OK: mavlink.MAV_SEVERITY_INFO, State.DEGRADED: mavlink.MAV_SEVERITY_WARNING,
                       State.LOST: mavlink.MAV_SEVERITY_ERROR}


@dataclass(frozen=True)
class NamedFiles:
    """The files a config names that the daemon itself reads (see :func:`load_named_files`)."""

    mission: Mission | None
    signing_key: bytes | None


def load_named_files(cfg: Config) -> NamedFiles:
    """Load every file ``cfg`` names (mission, signing key, and through the registry each sensor's and
    pipeline's: recordings, maps, the simulated world); ConfigError at the config key and line of the
    first bad one. ``companion check-config`` and the daemon's start both use this."""
    for name, section in cfg.pipelines.enabled.items():
        entry = plugins.pipeline(name)
        if entry is not None and entry.check_files is not None:
            entry.check_files(cfg, section)
    check_sensor_files(cfg)
    mission, key = cfg.mission.file, cfg.mavlink.signing_key_file
    return NamedFiles(
        mission=cfg.load_referenced("mission.file", mission, lambda path: _mission_for(cfg, path)) if mission else None,
        signing_key=cfg.load_referenced("mavlink.signing_key_file", key, load_signing_key) if key else None)


def config_warnings(cfg: Config) -> list[str]:
    """Warnings about settings that load but may fail in flight, from each enabled pipeline's
    ``advise`` hook (companion/plugins.py), each prefixed with its config key."""
    out = []
    for name, section in cfg.pipelines.enabled.items():
        entry = plugins.pipeline(name)
        if entry is not None and entry.advise is not None:
            out += [f"pipelines.{name}: {text}" for text in entry.advise(cfg, section)]
    return out


def _mission_for(cfg: Config, path: Path) -> Mission:
    """The mission at ``path``; ValueError if a ``pose_source`` step names no pose source of ``cfg``."""
    mission = load_mission(path)
    sources = cfg.source_priority()
    for i, step in enumerate(mission.steps):
        if step.pose_source is not None and step.pose_source.source is not None and step.pose_source.source not in sources:
            raise ValueError(f"{path}: steps[{i}].pose_source.source: {step.pose_source.source!r} is not a pose "
                             f"source of this config ({', '.join(sources) or 'none'})")
    return mission


class Daemon:
    """One companion instance. ``await Daemon(cfg).run()`` returns the process exit code."""

    def __init__(self, cfg: Config, mavlink_url: str | None = None) -> None:
        self.cfg = cfg
        self.url = mavlink_url or cfg.mavlink.url
        self.health = Health(clock.now)  # called from the loop only
        self.notifier = Notifier()
        self.supervisor = Supervisor(self.health)
        self.session = None
        self.started_wall = time.monotonic()
        self.drivers: dict[str, SensorDriver] = {}
        self.files: NamedFiles | None = None  # what the config names, loaded at the start of run()
        self.recorder: Recorder | None = None  # the flight recorder, with record.enabled
        self._first_contact = True
        self._static_due = -math.inf  # daemon time the pipelines' static streams are next published
        self._stop = asyncio.Event()

    def request_stop(self) -> None:
        """Make :meth:`run` shut down and return 0, as SIGTERM and SIGINT do.

        Call it on the daemon's event loop (from another thread: ``loop.call_soon_threadsafe``).
        """
        self._stop.set()

    async def run(self) -> int:
        cfg = self.cfg
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self.request_stop)

        files = self.files = load_named_files(cfg)  # before anything starts: a bad file stops here
        for text in config_warnings(cfg):
            log.warning("config: %s", text)
        self.link = link = MavlinkLink(cfg.mavlink, cfg.vehicle, self.url, self.health, files.signing_key)
        self.state = state = AutopilotState(link)
        self.commander = commander = Commander(link, state, cfg.mavlink)
        self.origin = origin = OriginSetter(link, state, commander, cfg.origin, self.health)
        self.streams = streams = StreamNegotiator(link, state, commander, cfg.mavlink.streams, self.health)
        self.telemetry = telemetry = self._open_telemetry()
        self.recorder = self._make_recorder()
        self.estimate = EstimateSender(link, cfg.mavlink.estimate_rate_hz, self.health, clock.now,
                                       on_alert=self.statustext)
        self.distance = DistanceSender(link)
        self.setpoints = setpoints = SetpointStream(link, state, cfg.mavlink.setpoint_rate_hz)
        pipelines = self.build_pipelines()
        self._start_recorder()  # after the pipelines loaded their files: the recording keeps a copy of each
        self.selector = self._build_selector(pipelines)
        self.mission = self._build_mission(pipelines)
        self.commands = self._build_inbound_commands(pipelines)
        gate = WatchdogGate(max_age=1.0, clock=clock.now)
        p = cfg.pipelines
        crosscheck = AttitudeCrossCheck(state.attitude_at, self.health, telemetry.publish,
                                        p.attitude_alarm_deg, p.attitude_alarm_s)
        outputs = NavOutputs(pose=self.estimate.submit, range=self.distance.submit, attitude=crosscheck.submit,
                             publish=telemetry.publish)
        self.nav = NavLoop(pipelines, self.selector, outputs, gate, p.fusion_rate_hz, clock.now)
        if self.recorder is not None:
            self.nav.on_cycle = self.recorder.cycle
        self.health.on_change(self._announce)
        link.on_connect(self._on_autopilot_found)

        sup = self.supervisor
        sup.spawn("link", link.run)
        sup.spawn("origin", origin.run)
        sup.spawn("streams", streams.run)
        sup.spawn("firmware", commander.identify_every_connection)
        sup.spawn("setpoints", setpoints.run)
        sup.spawn("nav", self.nav.run)
        sup.spawn("status", self._publish_status)
        if self.notifier.watchdog_interval() is not None:
            sup.spawn("watchdog", lambda: run_watchdog(self.notifier, gate, clock.now))
        if self.mission is not None:
            sup.spawn("mission", self.mission.run)
        self.notifier.ready()
        log.info("companion running: autopilot link %s, %d pipelines", self.url, len(self.nav.pipelines))
        await self._stop.wait()
        await self._shutdown()
        return 0

    def _build_mission(self, pipelines: list[Pipeline]) -> MissionRunner | None:
        """The configured mission's runner (None without one), flying on the companion's estimate."""
        cfg = self.cfg
        mission = self.files.mission
        if mission is None:
            return None
        area = next((a for a in (p.operating_area() for p in pipelines) if a is not None), None)
        ctx = MissionContext(
            state=self.state, commander=self.commander, setpoints=self.setpoints, origin=self.origin,
            estimate=self._mission_estimate, nav_health=lambda: self.health.worst("nav:"), publish=self.telemetry.publish,
            control=cfg.control, failsafe=cfg.mission.failsafe, payload=cfg.mission.payload,
            geofence=Geofence.from_config(cfg.mission.geofence, area), select_source=self._select_source)
        if cfg.control.rate_hz <= cfg.pipelines.fusion_rate_hz:  # else its own timer: faster than the estimate
            ctx.control_tick = lambda due: self.nav.after_cycle(due)
        guide = next((p for p in pipelines if isinstance(p, GuidanceSource)), None)
        if guide is not None:
            ctx.guidance = lambda: guide.guidance(clock.now())
            ctx.request_guidance = lambda reason: guide.request_guidance(clock.now(), reason)
        if guide is not None and self.recorder is not None:
            ctx.request_guidance = self._recorded_guidance_request(ctx.request_guidance)
        if ctx.geofence is None:
            log.warning("mission %s: no companion geofence (mission.geofence disabled, or neither its box_ned_m "
                        "nor a pipeline's operating area); the autopilot's own fence still applies", mission.name)
        return MissionRunner(mission, cfg.mission.allow_arm, ctx, cfg.mission.on_daemon_stop)

    def _build_inbound_commands(self, pipelines: list[Pipeline]) -> InboundCommands:
        """The commands a ground station may address to the companion (companion.mavlink.inbound):
        MAV_CMD_NAV_RETURN_TO_LAUNCH starts a guidance pipeline's return (the EKF-SLAM return to
        base), flown by the mission runner as a takeover (its next ``return_to_base`` step)."""
        commands = InboundCommands(self.link, self.cfg.mavlink.command_sysids, self.statustext)
        if any(isinstance(p, GuidanceSource) for p in pipelines):
            commands.register(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, self._commanded_return)
        return commands

    def _commanded_return(self, _msg: object) -> str | None:
        """Start the return if a mission runner is there to fly it: not before the mission starts
        (the runner flies takeovers only in its steps), and not after it ended, even airborne."""
        if self.mission is None:
            return "no mission runs: nobody to fly the return"
        if self.mission.status != "running":
            return f"the mission is {self.mission.status}: nobody to fly the return"
        return self.mission.ctx.request_guidance("MAVLink command")

    def _select_source(self, source: str | None) -> None:
        """A commanded pose source (a mission's ``pose_source`` step)."""
        if self.selector is None:
            raise CommandFailed("no pose source to command: the config has no pose pipeline")
        try:
            self.selector.command(source)
        except ValueError as exc:
            raise CommandFailed(str(exc)) from exc
        if self.recorder is not None:
            self.recorder.event("/nav/source_command", clock.now(), {"source": source})

    def _recorded_guidance_request(self, request: Callable[[str], str | None]) -> Callable[[str], str | None]:
        """``request`` (start a guidance pipeline's return), recorded: it changes the pipeline from outside."""
        def recorded(reason: str) -> str | None:
            self.recorder.event("/nav/guidance_request", clock.now(), {"reason": reason})
            return request(reason)
        return recorded

    def _mission_estimate(self) -> PoseEstimate | None:
        """What missions fly on: the active pose source's newest estimate, or the autopilot's own
        (LOCAL_POSITION_NED) when this daemon runs no pose pipeline (e.g. a GPS vehicle)."""
        if self.selector is not None:
            return self.selector.current
        s = self.state
        if s.local_position_ned is None or s.local_position_time is None:
            return None
        return PoseEstimate(s.local_position_time, s.local_position_ned, s.attitude_euler or (0.0, 0.0, 0.0),
                            np.zeros((6, 6)), s.local_velocity_ned, np.zeros((3, 3)), source="autopilot")

    def build_pipelines(self) -> list[Pipeline]:
        """The enabled pipelines, each subscribed to its sensors' drivers (one supervised task per
        sensor). The registry builds both; nothing here is written for one sensor or pipeline."""
        cfg = self.cfg
        ctx = SensorContext(cfg, self.health, self.link, self.state)
        self.drivers = {name: build_driver(name, sensor, ctx) for name, sensor in cfg.sensors.items()}
        pipelines = build_pipelines(cfg, self.health)
        if self.recorder is not None:
            for name, driver in self.drivers.items():
                driver.subscribe(self.recorder.sensor(name))
        for pipeline in pipelines:
            for sensor, handler in pipeline.subscriptions().items():
                self.drivers[sensor].subscribe(handler)
            self.telemetry.add_streams(pipeline.telemetry_streams)
        for name, driver in self.drivers.items():
            if not driver.subscribers:
                log.warning("sensor %s feeds no pipeline; its data is counted and dropped", name)
            self.supervisor.spawn(f"driver:{name}", driver.run)
        return pipelines

    def _build_selector(self, pipelines: list[Pipeline]) -> SourceSelector | None:
        """The pose-source selection over ``pipelines.sources`` (companion.navloop.build_selector)."""
        return build_selector(self.cfg, pipelines, on_switch=self._source_switched)

    def _source_switched(self, old: str | None, new: str | None, reason: str) -> None:
        """Announce a change of the pose source (STATUSTEXT + telemetry ``sources``). Losing every
        source and getting one back are announced by health ``nav:source`` (its state changes);
        a switch between two sources keeps it ok, so it is announced here."""
        if old is not None and new is not None:
            log.warning("pose source %s -> %s (%s)", old, new, reason)
            self.statustext(f"companion: pose source {old} -> {new}")
        self.health.report("nav:source", State.OK if new is not None else State.LOST,
                           f"pose from {new}" if new is not None else f"no pose source ({reason})")
        self.telemetry.publish("sources", {**self.selector.snapshot(clock.now()), "reason": reason})

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_WARNING) -> None:
        """Send a STATUSTEXT (<= 50 characters) to the autopilot, which forwards it to the GCS."""
        self.link.send(mavlink.MAVLink_statustext_message(severity, text[:50].encode(), 0, 0))
        self.telemetry.publish("alerts", {"severity": severity, "text": text})

    # -- internals --------------------------------------------------------------------------

    def _make_recorder(self) -> Recorder | None:
        """The flight recorder (None with neither ``record.enabled`` nor ``record.foxglove_server``),
        hooked to the link, telemetry and health here; to the drivers and nav loop where they are
        built; started by :meth:`_start_recorder`. Its modules (MCAP, foxglove) are imported only
        here: a daemon that records nothing does not load them (about 90 ms of start-up CPU)."""
        cfg, r = self.cfg, self.cfg.record
        if not (r.enabled or r.foxglove_server):
            return None
        from companion.recording.foxglove_live import FoxgloveLive
        from companion.recording.mcap_files import McapFiles
        from companion.recording.recorder import Recorder, Sink

        sinks: list[Sink] = []
        recording_id = uuid.uuid4().hex
        if r.enabled:
            source = Path(cfg.source)
            sinks.append(McapFiles(r, cfg.resolve(r.dir), recording_id, source.read_text() if source.is_file() else "",
                                   cfg.source, cfg.referenced))
        if r.foxglove_server:
            sinks.append(FoxgloveLive(r.foxglove_host, r.foxglove_port))
        recorder = Recorder(r, sinks, clock.now, recording_id)
        if r.mavlink:
            self.link.observe(lambda direction, msg: recorder.mavlink(direction, clock.now(), msg))
        if r.telemetry:
            self.telemetry.observer = recorder.telemetry
        self.health.on_change(lambda name, new, old: recorder.event(
            "/health/changes", clock.now(), {"component": name, "state": new.state.label, "reason": new.reason}))
        return recorder

    def _start_recorder(self) -> None:
        """Start the recorder's sinks and thread; if they cannot start (a directory it may not write, the
        Foxglove port taken) health ``recorder`` says why and the daemon runs on without it."""
        recorder = self.recorder
        if recorder is None:
            return
        try:
            recorder.start()
        except (OSError, ImportError) as exc:
            self.health.report("recorder", State.DEGRADED, f"cannot record: {exc}")
            return
        where = ", ".join(f"{k}: {v}" for k, v in recorder.snapshot().items() if k in ("parts", "foxglove_url"))
        self.health.report("recorder", State.OK, f"recording ({where})")
        log.info("recording (%s)", where)

    def _recorder_health(self) -> None:
        """Health ``recorder`` degraded once the recording stopped (disk full): the daemon flies on."""
        recorder = self.recorder
        if recorder is not None and recorder.stats.stopped is not None:
            self.health.report("recorder", State.DEGRADED, f"recording stopped: {recorder.stats.stopped}")

    def _open_telemetry(self) -> TelemetryPublisher:
        t = self.cfg.telemetry
        if t.enabled:
            try:
                self.session = open_session(t.mode, t.listen, t.connect, t.multicast_scouting, t.gossip_scouting)
            except Exception as exc:  # zenoh.ZError: bad endpoint, port in use
                self.health.report("telemetry", State.DEGRADED, f"zenoh session failed: {exc}")
        # Not attitude_check: one stream for every attitude source, whose estimates often share an
        # instant (two flow paths of one frame pair), where a stream's limit would refuse all but the
        # first; each is published (the report scores them one by one), at the sources' own rates.
        rates = {"pose": t.pose_hz, "velocity": t.pose_hz}
        # loop.time (not clock.now): the publisher's worker thread reads the clock too.
        publisher = TelemetryPublisher(self.session, self.cfg.vehicle.sysid, t.queue_size, rates,
                                       clock=asyncio.get_running_loop().time)
        if self.session is not None:
            self._start_stream_tasks()
        return publisher

    def _start_stream_tasks(self) -> None:
        """Supervised tasks for the streams faster than status: the setpoint, and the pipelines' streams.

        Tasks start when run() first awaits, after it has built the nav loop and the setpoint
        stream they read.
        """
        t = self.cfg.telemetry
        self.supervisor.spawn("telemetry:setpoint",
                              lambda: every(1.0 / t.setpoint_hz, self._publish_setpoint, self.nav.after_cycle))
        if self.cfg.pipelines.enabled:
            self.supervisor.spawn("telemetry:pipelines",
                                  lambda: every(1.0 / t.scan_hz, self._publish_pipeline_streams, self.nav.after_cycle))

    def _on_autopilot_found(self) -> None:
        if self._first_contact:
            self._first_contact = False
            log.info("autopilot %s found: `companion setup-autopilot -c %s` checks the parameters this config needs",
                     self.link.autopilot, self.cfg.source)

    def _announce(self, name: str, new: ComponentHealth, old: ComponentHealth | None) -> None:
        if name == "link" or name.startswith("task:") or old is None:
            return
        self.statustext(f"companion: {name} {new.state.label}: {new.reason}", STATUSTEXT_SEVERITY[new.state])

    async def _publish_status(self) -> None:
        period = 1.0 / self.cfg.telemetry.status_hz
        while True:
            self._recorder_health()
            self.notifier.status(self.health.summary())
            self._publish_snapshots()
            await self.nav.after_cycle(clock.now() + period)

    def _publish_snapshots(self) -> None:
        t, link, state = self.telemetry, self.link, self.state
        t.publish("health", {**self.health.snapshot(), "tasks": self.supervisor.snapshot()})
        t.publish("link", {"connected": link.connected, "autopilot": link.autopilot, "url": self.url,
                           "heartbeat_age_s": None if link.last_heartbeat is None else clock.now() - link.last_heartbeat,
                           **asdict(link.stats)})  # copies: the encoder thread reads them later
        t.publish("autopilot", {"mode": state.mode, "armed": state.armed,
                                "firmware": state.firmware.label if state.firmware else None,
                                "origin_confirmed": self.origin.confirmed,  # as health "origin" says
                                "home_at_origin": self.origin.home_confirmed,
                                "external_nav_in_use": state.external_nav_in_use, "ekf_flags": state.ekf_flags,
                                "local_position_ned_m": state.local_position_ned,
                                "streams": dict(self.streams.chosen),
                                "imu_rejected": state.imu_rejected})
        t.publish("estimate_stats", {**asdict(self.estimate.stats), "reset_counter": self.estimate.reset_counter,
                                     "nonfinite_dropped_link": link.stats.nonfinite_dropped,
                                     "distance_sent": self.distance.sent, "distance_dropped": self.distance.dropped})
        if self.selector is not None:
            t.publish("sources", self.selector.snapshot(clock.now()))
        t.publish("system", {**process_usage(self.started_wall),
                             "loop_jitter_ms": self.nav.jitter_ms.summary(),
                             "stage_ms": self.nav.stage_summaries(),
                             "pipelines": {p.name: p.snapshot() for p in self.nav.pipelines},
                             "drivers": {n: asdict(d.stats) for n, d in self.drivers.items()},
                             "setpoints_sent": self.setpoints.sent,
                             "recorder": self.recorder.snapshot() if self.recorder is not None else None})
        t.publish("rates", {"streams": t.stats()})
        if self.mission is not None:
            t.publish("mission", self.mission.snapshot())

    def _publish_setpoint(self) -> None:
        """The setpoint being sent, while commanding."""
        sp = self.setpoints.current
        if sp is not None:
            self.telemetry.publish("setpoint", {
                "type_mask": sp.type_mask, "position_ned_m": sp.position_ned, "velocity_ned_mps": sp.velocity_ned,
                "acceleration_ned_mps2": sp.acceleration_ned})

    def _publish_pipeline_streams(self) -> None:
        """Each pipeline's own streams (what it computed since the last call; static ones when due)."""
        now = clock.now()
        static_due = now >= self._static_due
        if static_due:
            self._static_due = now + STATIC_STREAM_PERIOD_S
        for pipeline in self.nav.pipelines:
            for stream, payload in pipeline.telemetry(static_due).items():
                self.telemetry.publish(stream, payload)

    async def _shutdown(self) -> None:
        log.info("shutting down")
        loop = asyncio.get_running_loop()
        if isinstance(loop, clock.LockstepEventLoop):
            loop.release()  # the simulator no longer ticks; shutdown timeouts must still expire
        self.notifier.stopping()
        if self.mission is not None:
            await self.supervisor.cancel("mission")  # nothing may command after the hold below
            await self.mission.on_daemon_stop(mode_timeout_s=0.4)
        self.setpoints.stop()
        await self.supervisor.stop(timeout_s=0.5)  # cancelling the link task closes the port
        self.telemetry.close(timeout_s=0.4)
        if self.recorder is not None:
            self.recorder.close(timeout_s=0.5)
        if self.session is not None:
            closer = threading.Thread(target=self.session.close, daemon=True)
            closer.start()
            closer.join(timeout=0.4)
        log.info("stopped")


async def every(period_s: float, action: Callable[[], None], until: Callable[[float], Awaitable[None]]) -> None:
    """Call ``action()`` every ``period_s`` seconds of the daemon clock, the first time after one
    period; ``until(t)`` waits for daemon time ``t`` (NavLoop.after_cycle: between nav cycles)."""
    while True:
        await until(clock.now() + period_s)
        action()


def process_usage(started_monotonic: float) -> dict[str, float]:
    """CPU percent of one core since start, resident memory (MB) and uptime (s) of this process."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    uptime = max(time.monotonic() - started_monotonic, 1e-6)
    return {"cpu_percent": 100.0 * (usage.ru_utime + usage.ru_stime) / uptime,
            "rss_mb": _rss_bytes() / 1e6, "uptime_s": uptime}


def _rss_bytes() -> int:
    try:
        for line in Path(f"/proc/{os.getpid()}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
