"""`companion sitl`: the simulated vehicle and the daemon as separate processes on loopback.

The harness writes a run config derived from the given one (mission, absolute paths), starts
``python -m sitl.vehicle`` (MAVLink on loopback UDP) and ``companion run`` (which publishes
zenoh telemetry on loopback TCP), listens to that telemetry as a zenoh peer (the last payload
of each stream, and every ``attitude_check``: the attitude-only estimates), and at the end
scores the run against the vehicle's ground truth (sitl/report.py).

With ``--dashboard PORT`` it also starts ``companion dashboard`` on that loopback port, joined
to the daemon's telemetry, and prints the page's URL.

With ``sitl.scip_sensors`` (real time only) it also starts ``python -m sitl.scip_bridge``
before the daemon: the bridge gets its own vehicle link (an extra ``--gcs`` on a free loopback
UDP port) for SIM_STATE truth and serves those sensors over SCIP 2.0 on their
``settings.tcp_port``, where the daemon's real Hokuyo driver connects.

With ``--ardupilot PATH`` (or ``sitl.ardupilot.binary``) the vehicle is a real ArduPilot SITL
binary instead (sitl/ardupilot_run.py): set up by ``companion setup-autopilot``, flown by the
daemon through a recording tap, scored against the SITL's own truth with the same report.
Real time only.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from companion.config import Config, ConfigError, load_config
from companion.dashboard.app import spawn_dashboard
from companion.recording.reader import Recording
from companion.recording.mcap_files import FILE_GLOB
from companion.telemetry.keys import KEY_PREFIX
from drivers.lidar_models import MODELS
from sitl.ardupilot_observer import THREAD_NAME as OBSERVER_THREAD
from sitl.ardupilot_run import ArduPilotRun, ArduPilotStartFailure
from sitl.frame_shift import moved_origin, shift_mission, shift_world, shifted, takeoff_pose, write_shifted
from sitl.report import PAIR_STREAM_KEYS, build_report
from sitl.replay_report import write_scoring_file
from companion.world import load_world

log = logging.getLogger("companion.sitl")

STOP_GRACE_S = 5.0
VEHICLE_STOP_GRACE_S = 30.0  # the vehicle writes its flight log at exit: 14 MB for a ten-minute flight, seconds under load
BRIDGE_READY_S = 15.0  # the SCIP bridge must listen on every port within this


class StartFailure(Exception):
    """A process of the run did not come up."""


# Streams the report scores sample by sample (sitl/report.py score_attitude), and the keys kept of
# each payload (None: all of it).
KEPT_STREAMS: dict[str, tuple[str, ...] | None] = {"attitude_check": None, **PAIR_STREAM_KEYS}


class TelemetryListener:
    """Keeps the last JSON payload of every stream of one vehicle, and when it came (a zenoh peer);
    of the ``KEPT_STREAMS``, every payload in arrival order."""

    def __init__(self, connect: list[str], sysid: int) -> None:
        from companion.telemetry.session import open_session

        self.latest: dict[str, dict] = {}
        self.kept: dict[str, list[dict]] = {stream: [] for stream in KEPT_STREAMS}
        self.received: dict[str, float] = {}  # time.monotonic() of each stream's last payload
        self._lock = threading.Lock()
        self.session = open_session("peer", [], connect, False, False)
        self.subscriber = self.session.declare_subscriber(f"{KEY_PREFIX}/{sysid}/*", self._on_sample)

    def _on_sample(self, sample) -> None:  # type: ignore[no-untyped-def]
        try:
            payload = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        stream = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            self.latest[stream] = payload
            self.received[stream] = time.monotonic()
            if stream in self.kept:
                keys = KEPT_STREAMS[stream]
                self.kept[stream].append(payload if keys is None else {k: payload.get(k) for k in keys})

    def snapshot(self) -> dict[str, dict]:
        with self._lock:
            return dict(self.latest)

    def every(self, stream: str) -> list[dict]:
        """Every payload of ``stream`` (one of ``KEPT_STREAMS``) received so far, oldest first."""
        with self._lock:
            return list(self.kept[stream])

    def age(self, stream: str) -> float:
        """Seconds since ``stream`` last arrived (inf: never)."""
        with self._lock:
            received = self.received.get(stream)
        return float("inf") if received is None else time.monotonic() - received

    def close(self) -> None:
        self.subscriber.undeclare()
        self.session.close()


def companion_url_for(vehicle_url: str) -> str:
    """The daemon's endpoint for a vehicle listening at ``udpin:HOST:PORT`` (or tcpin)."""
    scheme, _, address = vehicle_url.partition(":")
    return {"udpin": "udpout", "tcpin": "tcp"}.get(scheme, scheme) + ":" + address


def write_run_config(cfg: Config, mission: str | None, out_dir: Path, autopilot_url: str | None,
                     control_law: str | None = None, origin_at_takeoff: bool = False,
                     record_dir: Path | None = None) -> Path:
    """A copy of the config with the mission (and control law) chosen, absolute paths and the matching
    link URL; with ``origin_at_takeoff``, in the frame whose origin is the take-off point (sitl/frame_shift.py);
    with ``record_dir``, the flight recorder on, recording there (the config's other record settings kept)."""
    raw = yaml.safe_load(Path(cfg.source).read_text()) or {}
    if control_law is not None:
        raw.setdefault("control", {})["law"] = control_law
    if record_dir is not None:
        raw["record"] = {**(raw.get("record") or {}), "enabled": True, "dir": str(record_dir.resolve())}
    mission_file = cfg.resolve(f"missions/{mission}.yaml") if mission else (
        cfg.resolve(cfg.mission.file) if cfg.mission.file else None)
    raw.setdefault("mission", {})["file"] = str(mission_file) if mission_file else None
    raw.setdefault("sitl", {})["world"] = str(cfg.resolve(cfg.sitl.world))
    raw.setdefault("mavlink", {})["url"] = autopilot_url or companion_url_for(cfg.sitl.vehicle_url)
    # The copy lives elsewhere: every path the config holds becomes absolute.
    if cfg.mavlink.signing_key_file:
        raw["mavlink"]["signing_key_file"] = str(cfg.resolve(cfg.mavlink.signing_key_file))
    for name in cfg.pipelines.enabled:
        _absolute_files(cfg, raw["pipelines"][name])
    for name in cfg.sensors:
        _absolute_files(cfg, raw["sensors"][name].get("settings") or {})
    for key in ("binary", "defaults"):
        value = getattr(cfg.sitl.ardupilot, key)
        if value:
            raw["sitl"].setdefault("ardupilot", {})[key] = str(cfg.resolve(value))
    if origin_at_takeoff:  # ArduPilot SITL: also, the daemon is wired to its SERIAL0 (through the tap)
        raw["mavlink"]["autopilot_serial_port"] = 0
        _move_origin_to_takeoff(cfg, raw, out_dir)
    path = out_dir / "companion.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def _absolute_files(cfg: Config, section: dict) -> None:
    """Make every value of ``section`` (a sensor's settings, a pipeline's section) that names an
    existing file relative to the config's directory absolute, in place."""
    for key, value in section.items():
        if isinstance(value, str) and not Path(value).is_absolute() and cfg.resolve(value).is_file():
            section[key] = str(cfg.resolve(value))


def _move_origin_to_takeoff(cfg: Config, raw: dict, out_dir: Path) -> None:
    """Rewrite ``raw`` (and write shifted copies of the world, map and mission) so that the origin
    is the take-off point: ``sitl.start``, else the world's start."""
    world_path = cfg.resolve(cfg.sitl.world)
    start = takeoff_pose(cfg)
    offset = (-start[0], -start[1])
    lat, lon, alt = moved_origin((cfg.origin.lat, cfg.origin.lon, cfg.origin.alt), (start[0], start[1]))
    raw["origin"] = {"lat": lat, "lon": lon, "alt": alt}
    raw["sitl"]["world"] = str(write_shifted(world_path, out_dir / "world.yaml", offset, shift_world))
    if cfg.sitl.start is not None:
        raw["sitl"]["start"] = shifted(cfg.sitl.start, offset)

    def move_map(path: str) -> str:
        """A map (world YAML) in the moved frame: the shifted world itself, or a shifted copy."""
        p = cfg.resolve(path)
        return raw["sitl"]["world"] if p.resolve() == world_path.resolve() else \
            str(write_shifted(p, out_dir / f"map-{p.stem}.yaml", offset, shift_world))

    for name, section in cfg.pipelines.enabled.items():
        raw["pipelines"][name] = section.moved(raw["pipelines"][name], offset, move_map)
    if raw["mission"]["file"]:
        raw["mission"]["file"] = str(write_shifted(Path(raw["mission"]["file"]), out_dir / "mission.yaml", offset,
                                                   shift_mission))
    box = cfg.mission.geofence.box_ned_m
    if box is not None:
        raw["mission"].setdefault("geofence", {})["box_ned_m"] = [shifted(corner, offset) for corner in box]


def vehicle_command(cfg: Config, args: argparse.Namespace, log_path: Path,
                    extra_gcs: tuple[str, ...] = ()) -> list[str]:
    """``python -m sitl.vehicle`` for this config; it signs its companion link with the daemon's
    ``mavlink.signing_key_file`` when there is one."""
    s = cfg.sitl
    start = takeoff_pose(cfg)
    cmd = [sys.executable, "-m", "sitl.vehicle", "--companion", s.vehicle_url,
           "--seed", str(args.seed), "--log", str(log_path), "--tick", str(s.tick_s),
           "--home", f"{cfg.origin.lat},{cfg.origin.lon},{cfg.origin.alt}",
           "--position-source", s.position_source,
           "--wind", ",".join(str(w) for w in s.wind_ned_mps), "--gust", str(s.gust_mps),
           "--start", ",".join(str(v) for v in start), "--sysid", str(cfg.vehicle.autopilot_sysid),
           "--vehicle", s.vehicle]
    for url in (*s.gcs_urls, *extra_gcs):
        cmd += ["--gcs", url]
    if not s.gps:
        cmd.append("--no-gps")
    if s.start_in_flight is not None:
        cmd += ["--in-flight", f"{s.start_in_flight.height_m},{s.start_in_flight.airspeed_mps}"]
    for e in s.events:
        cmd += ["--event", f"{e.start_s},{e.end_s},{e.sideslip_deg_s},{e.tilt_fault_deg[0]},{e.tilt_fault_deg[1]}"]
    if args.lockstep:
        cmd.append("--lockstep")
    if args.seconds is not None:
        cmd += ["--seconds", str(args.seconds)]
    if cfg.mavlink.signing_key_file:
        cmd += ["--signing-key", str(cfg.resolve(cfg.mavlink.signing_key_file))]
    return cmd


def free_udp_port() -> int:
    """A currently free loopback UDP port."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def ports_in_use(cfg: Config, builtin_vehicle: bool) -> list[str]:
    """The loopback ports this run would listen on that something else holds already: the
    vehicle's UDP port and the daemon's zenoh TCP endpoints. Two runs on the same ports would
    silently talk to each other (pymavlink's udpin shares its port); better to refuse."""
    taken = []
    if builtin_vehicle and cfg.sitl.vehicle_url.startswith("udpin:"):
        host, port = cfg.sitl.vehicle_url.split(":")[1:3]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            try:
                sock.bind((host, int(port)))
            except OSError:
                taken.append(f"UDP {host}:{port} (sitl.vehicle_url)")
    for endpoint in cfg.telemetry.listen if cfg.telemetry.enabled else []:
        proto, _, address = endpoint.partition("/")
        host, _, port = address.rpartition(":")
        if proto != "tcp" or not port.isdigit():
            continue
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # TIME_WAIT is fine, a listener is not
            try:
                sock.bind((host.strip("[]"), int(port)))
            except OSError:
                taken.append(f"TCP {address} (telemetry.listen)")
    return taken


def scip_bridge_command(cfg: Config, args: argparse.Namespace, vehicle_url: str) -> list[str]:
    """``python -m sitl.scip_bridge`` serving ``sitl.scip_sensors`` (validated by Config) from
    the vehicle link ``vehicle_url``: model, mount and TCP port of each from its config."""
    cmd = [sys.executable, "-m", "sitl.scip_bridge", "--vehicle", vehicle_url,
           "--world", str(cfg.resolve(cfg.sitl.world)),
           "--home", f"{cfg.origin.lat},{cfg.origin.lon},{cfg.origin.alt}", "--seed", str(args.seed)]
    for name in cfg.sitl.scip_sensors:
        sensor = cfg.sensors[name]
        values = (*sensor.mount.position_m, *sensor.mount.rpy_deg, sensor.settings.get("tcp_port", 10940))
        cmd += ["--sensor", ",".join([name, sensor.settings["model"], *(str(v) for v in values)])]
    return cmd


def scip_ports(cfg: Config) -> list[int]:
    return [int(cfg.sensors[name].settings.get("tcp_port", 10940)) for name in cfg.sitl.scip_sensors]


def wait_listening(proc: subprocess.Popen, ports: list[int], timeout_s: float) -> bool:
    """Until ``proc`` accepts TCP connections on every loopback port (True), exits or times out."""
    deadline = time.monotonic() + timeout_s
    waiting = list(ports)
    while waiting:
        if proc.poll() is not None or time.monotonic() > deadline:
            return False
        try:
            with socket.create_connection(("127.0.0.1", waiting[0]), timeout=0.5):
                waiting.pop(0)
        except OSError:
            time.sleep(0.05)
    return True


def process_cpu_rss(pid: int) -> tuple[float, float] | None:
    """(CPU seconds used, peak resident MB) of a live process, from /proc."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        ticks = os.sysconf("SC_CLK_TCK")
        cpu_s = (int(stat[11]) + int(stat[12])) / ticks
        hwm_kb = next(int(line.split()[1]) for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                      if line.startswith("VmHWM:"))
        return cpu_s, hwm_kb / 1024
    except (OSError, StopIteration, IndexError, ValueError):
        return None


def cpu_jiffies() -> tuple[int, int] | None:
    """(steal, total) CPU time of the whole machine so far, in clock ticks, from /proc/stat (None
    where there is none): steal is the time a hypervisor ran something else while this VM's CPUs
    had work."""
    try:
        fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]]
    except (OSError, ValueError):
        return None
    return (fields[7], sum(fields)) if len(fields) == 8 else None


def steal_percent(start: tuple[int, int] | None, end: tuple[int, int] | None) -> float | None:
    """The share (%) of the CPU time between two :func:`cpu_jiffies` readings that was stolen."""
    if start is None or end is None or end[1] <= start[1]:
        return None
    return 100.0 * (end[0] - start[0]) / (end[1] - start[1])


SELF_EXIT_GRACE_S = 2.0  # after Ctrl-C, which the whole foreground group receives
MISSION_END_GRACE_S = 1.0  # --report without --seconds: the run ends this long (wall) after the mission


def _terminate(proc: subprocess.Popen, name: str, interrupted: bool = False, grace_s: float = STOP_GRACE_S) -> int:
    """Stop a child: SIGTERM, then SIGKILL after ``grace_s``. After a Ctrl-C the child got the
    SIGINT too and is already stopping: give it a moment first, or SIGTERM could land just
    after it restored its default handlers and kill its exit."""
    if interrupted and proc.poll() is None:
        try:
            return proc.wait(SELF_EXIT_GRACE_S)
        except subprocess.TimeoutExpired:
            pass
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            return proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            log.error("%s did not stop within %.0f s of SIGTERM; killing it", name, grace_s)
            proc.kill()
            return proc.wait()
    return proc.returncode


@contextlib.contextmanager
def _sigterm_as_ctrl_c() -> Iterator[None]:
    """While inside, SIGTERM raises KeyboardInterrupt, so the children are stopped, not orphaned."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@dataclass
class Session:
    """The processes of one SITL run and what the harness learns about them."""

    vehicle: subprocess.Popen | None = None  # the built-in vehicle
    ardupilot: ArduPilotRun | None = None  # or ArduPilot SITL (--ardupilot)
    daemon: subprocess.Popen | None = None
    bridge: subprocess.Popen | None = None  # the SCIP bridge (sitl.scip_sensors)
    bridge_rc: int | None = None  # its exit code; 1 if it ended during the run
    dashboard: subprocess.Popen | None = None  # `companion dashboard` (--dashboard)
    dashboard_url: str | None = None
    run_config: Path | None = None  # the config the daemon runs with (written by the harness)
    listener: TelemetryListener | None = None
    started: float = field(default_factory=time.monotonic)
    usage: tuple[float, float] | None = None  # daemon (CPU s, peak RSS MB)
    cpu_at_start: tuple[int, int] | None = None  # the machine's (steal, total) CPU ticks when the run began

    def wait(self, seconds: float | None, until_mission_end: bool = False) -> None:
        """Until the built-in vehicle ends the run (--seconds), the daemon or ArduPilot SITL dies,
        (ArduPilot, external autopilot) time is up, or, with ``until_mission_end``, the mission is
        over (completed, failed or aborted) and MISSION_END_GRACE_S more have passed."""
        assert self.daemon is not None
        started = time.monotonic()
        ended_at: float | None = None
        while True:
            if until_mission_end and ended_at is None and self.listener is not None:
                state = self.listener.snapshot().get("mission", {}).get("state")
                ended_at = time.monotonic() if state in ("completed", "failed", "aborted") else None
            if ended_at is not None and time.monotonic() - ended_at > MISSION_END_GRACE_S:
                return
            if self.vehicle is not None and self.vehicle.poll() is not None:
                return
            if self.ardupilot is not None and not self.ardupilot.alive:
                log.error("ArduPilot SITL stopped during the run: %s", "; ".join(self.ardupilot.internal_errors())
                          or "no internal error reported")
                return
            if self.daemon.poll() is not None:
                log.error("the daemon exited with %s during the run", self.daemon.returncode)
                return
            if self.bridge is not None and self.bridge.poll() is not None:
                log.error("the SCIP bridge exited with %s during the run", self.bridge.returncode)
                return
            if self.vehicle is None and seconds is not None and time.monotonic() - started > seconds:
                return
            self.usage = process_cpu_rss(self.daemon.pid) or self.usage
            time.sleep(0.2)

    def stop(self, interrupted: bool = False) -> tuple[int, int, dict[str, dict]]:
        """Stop everything; (daemon exit code, vehicle exit code, last telemetry)."""
        if self.daemon is not None:
            self.usage = process_cpu_rss(self.daemon.pid) or self.usage
        telemetry = self.listener.snapshot() if self.listener else {}
        bridge_ended_early = self.bridge is not None and self.bridge.poll() is not None
        ardupilot_flew_the_run = self.ardupilot is not None and self.ardupilot.alive
        errors_in_run = len(self.ardupilot.internal_errors()) if self.ardupilot is not None else 0
        daemon_rc = _terminate(self.daemon, "daemon", interrupted) if self.daemon is not None else 0
        vehicle_rc = (_terminate(self.vehicle, "vehicle", interrupted, VEHICLE_STOP_GRACE_S)
                      if self.vehicle is not None else 0)
        if self.ardupilot is not None:
            vehicle_rc = self.ardupilot.stop() or 0
            teardown_errors = self.ardupilot.internal_errors()[errors_in_run:]
            if vehicle_rc and ardupilot_flew_the_run and teardown_errors:
                # ArduPlane 4.0.7 SITL can panic writing to SERIAL0 once the daemon has hung up
                # ("Short write on UART"): a teardown fault of the firmware, not of the run. It is
                # still reported (report autopilot.internal_errors), not counted as the vehicle dying.
                log.warning("ArduPilot SITL exited %d while being stopped, after the run: %s", vehicle_rc,
                            "; ".join(teardown_errors))
                vehicle_rc = 0
        if self.bridge is not None:
            rc = _terminate(self.bridge, "SCIP bridge", interrupted)
            self.bridge_rc = (rc or 1) if bridge_ended_early else rc
        if self.dashboard is not None:
            _terminate(self.dashboard, "dashboard", interrupted)
        if self.listener:
            self.listener.close()
        return daemon_rc, vehicle_rc, telemetry


def _start(session: Session, cfg: Config, args: argparse.Namespace, work: Path, vehicle_log: Path) -> Path:
    """Start the vehicle (built-in, or ArduPilot SITL set up for this config), the bridge, the
    daemon and the dashboard; the run config the daemon uses."""
    extra_gcs: tuple[str, ...] = ()
    if cfg.sitl.scip_sensors:
        port = free_udp_port()
        extra_gcs = (f"udpout:127.0.0.1:{port}",)
        session.bridge = subprocess.Popen(scip_bridge_command(cfg, args, f"udpin:127.0.0.1:{port}"))
    autopilot_url = args.autopilot
    if session.ardupilot is not None:
        autopilot_url = session.ardupilot.start_tap()
    run_cfg = write_run_config(cfg, args.mission, work, autopilot_url, args.control_law,
                               origin_at_takeoff=session.ardupilot is not None,
                               record_dir=Path(args.record) if args.record else None)
    if session.ardupilot is not None:
        try:
            session.ardupilot.boot(run_cfg)
        except ArduPilotStartFailure as exc:
            raise StartFailure(str(exc)) from None
        session.ardupilot.begin()
    elif args.autopilot is None:
        session.vehicle = subprocess.Popen(vehicle_command(cfg, args, vehicle_log, extra_gcs))
    if session.bridge is not None and not wait_listening(session.bridge, scip_ports(cfg), BRIDGE_READY_S):
        raise StartFailure(f"the SCIP bridge is not serving {', '.join(cfg.sitl.scip_sensors)} "
                           f"on 127.0.0.1:{', '.join(str(p) for p in scip_ports(cfg))}")
    daemon_cmd = [sys.executable, "-m", "companion.cli", "run", "-c", str(run_cfg)]
    if args.lockstep:
        daemon_cmd.append("--lockstep")
    session.daemon = subprocess.Popen(daemon_cmd)
    if cfg.telemetry.enabled:
        session.listener = TelemetryListener(cfg.telemetry.listen, cfg.vehicle.sysid)
    if args.dashboard is not None:
        try:
            session.dashboard, session.dashboard_url = spawn_dashboard(run_cfg, args.dashboard)
        except RuntimeError as exc:
            raise StartFailure(str(exc)) from None
    return run_cfg


def ardupilot_binary(cfg: Config, args: argparse.Namespace) -> Path | None:
    """The ArduPilot SITL binary of this run: --ardupilot, else sitl.ardupilot.binary, else None."""
    if args.ardupilot:
        return Path(args.ardupilot).resolve()
    return cfg.resolve(cfg.sitl.ardupilot.binary).resolve() if cfg.sitl.ardupilot.binary else None


def refusal(cfg: Config, args: argparse.Namespace, ardupilot: Path | None) -> str | None:
    """Why this combination of options cannot run, or None."""
    if ardupilot is not None:
        if args.autopilot is not None:
            return "--ardupilot starts its own autopilot: leave out --autopilot"
        if args.lockstep:
            return "ArduPilot SITL runs in real time with the daemon (its clock is not the daemon's): leave out --lockstep"
        if cfg.sitl.scip_sensors:
            return "sitl.scip_sensors needs the built-in vehicle (its truth link); use backend: sim sensors with --ardupilot"
        if cfg.sitl.start_in_flight is not None:
            return "ArduPilot SITL starts on the ground: leave out sitl.start_in_flight (take off in the mission)"
        if cfg.sitl.events:
            return "sitl.events script the built-in vehicle; ArduPilot SITL has its own SIM_ parameters for faults"
        if not ardupilot.is_file() or not os.access(ardupilot, os.X_OK):
            return f"{ardupilot}: not an executable ArduPilot SITL binary"
    elif cfg.sitl.ardupilot.parameter_events:
        return "sitl.ardupilot.parameter_events set ArduPilot SITL's parameters: run with --ardupilot"
    if cfg.sitl.scip_sensors and (args.lockstep or args.autopilot is not None):
        return ("sitl.scip_sensors needs the built-in vehicle in real time (the SCIP bridge runs on the "
                "wall clock); lockstep runs use backend: sim sensors")
    return None


def check_sitl_section(cfg: Config) -> None:
    """What only the simulator can check of the ``sitl`` section (ConfigError at the key): the world
    loads, and every ``scip_sensors`` scanner is of a model the SCIP bridge emulates. Config checks
    the rest (real loopback lidars on distinct ports); ``companion check-config`` runs this too."""
    cfg.load_referenced("sitl.world", cfg.sitl.world, load_world)
    for i, name in enumerate(cfg.sitl.scip_sensors):
        if cfg.sensors[name].settings.get("model") not in MODELS:
            raise ConfigError(cfg.source, f"sitl.scip_sensors[{i}]", cfg.line_of(f"sitl.scip_sensors[{i}]"),
                              f"sensor {name!r}: settings.model must name the emulated model ({', '.join(sorted(MODELS))})")


class _QuietObserver(logging.Filter):
    """The ArduPilot observer reuses the daemon's MAVLink classes in this process: below ERROR their
    lines would repeat what the daemon itself logs about the same autopilot."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.threadName != OBSERVER_THREAD or record.levelno >= logging.ERROR


def _keep_scoring_inputs(record_dir: Path, inputs: dict, world_file: Path) -> None:
    """Beside the flight's recording (the newest in ``record_dir``), what its report was scored from,
    so that `companion replay` scores the replay's report the same way (sitl/replay_report.py)."""
    parts = sorted(record_dir.glob(FILE_GLOB), key=lambda p: p.stat().st_mtime)
    if not parts:
        log.error("no recording in %s: the daemon recorded nothing (see its log)", record_dir)
        return
    recording = Recording.open(parts[-1])
    try:
        path = write_scoring_file(record_dir, recording.id, inputs, world_file)
    except OSError as exc:  # e.g. the disk the recording filled
        log.error("cannot keep the scoring inputs beside the recording in %s: %s", record_dir, exc)
        return
    print(f"companion sitl: recording {', '.join(p.name for p in recording.parts)} in {record_dir}; "
          f"scoring inputs {path.name}", flush=True)


def run_harness(args: argparse.Namespace) -> int:
    """Run one SITL session; returns the exit code (0 = ran and, if asked, reported)."""
    for handler in logging.getLogger().handlers:
        handler.addFilter(_QuietObserver())
    try:
        cfg = load_config(args.config)
        if args.mission and not cfg.resolve(f"missions/{args.mission}.yaml").exists():
            raise ConfigError(cfg.source, "mission", None, f"no mission {args.mission!r} in {cfg.resolve('missions')}")
        check_sitl_section(cfg)
    except ConfigError as exc:
        print(f"companion: {exc}", file=sys.stderr)
        return 2
    ardupilot = ardupilot_binary(cfg, args)
    problem = refusal(cfg, args, ardupilot)
    if problem is not None:
        print(f"companion: {problem}", file=sys.stderr)
        return 2
    taken = ports_in_use(cfg, builtin_vehicle=args.autopilot is None and ardupilot is None)
    if taken:
        print(f"companion: in use already (another `companion sitl` running?): {', '.join(taken)}; "
              "stop it, or give this run other ports in a copy of the config", file=sys.stderr)
        return 2
    work = Path(tempfile.mkdtemp(prefix="companion-sitl-"))
    vehicle_log = work / "vehicle-log.json"
    mission_name = args.mission or (Path(cfg.mission.file).stem if cfg.mission.file else "none")
    session = Session()
    if ardupilot is not None:
        session.ardupilot = ArduPilotRun(ardupilot, cfg.sitl.ardupilot, cfg.base_dir, work, args.seed,
                                         cfg.vehicle.autopilot_sysid)
    interrupted = False
    start_failed = False
    with _sigterm_as_ctrl_c():
        try:
            session.run_config = _start(session, cfg, args, work, vehicle_log)
            session.started = time.monotonic()
            session.cpu_at_start = cpu_jiffies()
            bridge = f"; SCIP bridge serving {', '.join(cfg.sitl.scip_sensors)}" if session.bridge else ""
            vehicle = f"ArduPilot SITL {ardupilot.name}" if ardupilot is not None else "vehicle"
            print(f"companion sitl: {vehicle} + daemon running (mission {mission_name}, "
                  f"{'lockstep' if args.lockstep else 'real time'}, seed {args.seed}); "
                  f"telemetry on zenoh {', '.join(cfg.telemetry.listen)}; GCS links {', '.join(cfg.sitl.gcs_urls)}"
                  f"{bridge}", flush=True)
            if session.dashboard_url is not None:
                print(f"companion sitl: dashboard at {session.dashboard_url}", flush=True)
            session.wait(args.seconds, until_mission_end=args.report is not None and args.seconds is None)
        except KeyboardInterrupt:
            interrupted = True
        except StartFailure as exc:
            log.error("%s", exc)
            start_failed = True
        except Exception:  # a bug: still leave no process behind (ArduPilot SITL would spin on)
            session.stop()
            raise
        wall = time.monotonic() - session.started
        stolen = steal_percent(session.cpu_at_start, cpu_jiffies())
        daemon_rc, vehicle_rc, telemetry = session.stop(interrupted)
    if interrupted:
        print("companion sitl: stopped", flush=True)
    if start_failed:
        return 1
    ok = daemon_rc == 0 and vehicle_rc == 0 and session.bridge_rc in (None, 0)
    if not ok:
        bridge_exit = f", SCIP bridge exit {session.bridge_rc}" if session.bridge is not None else ""
        print(f"companion sitl: daemon exit {daemon_rc}, vehicle exit {vehicle_rc}{bridge_exit}", file=sys.stderr)
    if args.report:
        if session.ardupilot is not None:
            session.ardupilot.write_log(vehicle_log)
        if not vehicle_log.exists():
            print("companion sitl: no flight log, cannot score a report (the vehicle was killed before writing it, "
                  "see above; or an external autopilot given with --autopilot, which records no truth: use "
                  "--ardupilot PATH to have the harness run ArduPilot SITL)", file=sys.stderr)
            return 1
        sim_log = json.loads(vehicle_log.read_text())
        run_cfg = load_config(session.run_config) if session.run_config is not None else cfg
        frame = run_cfg.origin
        world = run_cfg.load_referenced("sitl.world", run_cfg.sitl.world, load_world)
        usage = session.usage
        inputs = dict(
            mission=mission_name, seconds=sim_log["sim_seconds"], lockstep=bool(args.lockstep), seed=args.seed,
            control_law=args.control_law or cfg.control.law, log=sim_log, telemetry=telemetry,
            origin=(frame.lat, frame.lon, frame.alt),
            internal_errors=session.ardupilot.internal_errors() if session.ardupilot is not None else None,
            cpu_percent=None if usage is None else 100.0 * usage[0] / max(wall, 1e-6),
            rss_mb=None if usage is None else usage[1], base_ne=world.base, cpu_steal_percent=stolen,
            attitude_checks=session.listener.every("attitude_check") if session.listener is not None else [],
            pair_streams={stream: session.listener.every(stream) for stream in PAIR_STREAM_KEYS}
            if session.listener is not None else None)
        if args.record:  # before build_report, which may not keep its inputs as they are
            _keep_scoring_inputs(Path(args.record), json.loads(json.dumps(inputs)),
                                 run_cfg.resolve(run_cfg.sitl.world))
        report = build_report(**inputs, ground_height=world.floor_height_at)
        Path(args.report).write_text(json.dumps(report, indent=2) + "\n")
        print(json.dumps(report, indent=2), flush=True)
        print(f"companion sitl: flight log (truth, everything the autopilot received) in {vehicle_log}", flush=True)
    return 0 if ok else 1
