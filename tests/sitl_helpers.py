"""Helpers for the end-to-end tests: the daemon against the real SITL vehicle process.

Everything runs on loopback with free ports (tests/conftest.py ``free_port``), so the tests never
collide with each other or with a running demo. Subprocesses are started through
:class:`Processes`, which kills whatever is still running when the test ends.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402

from companion.clock import LockstepEventLoop  # noqa: E402
from companion.config import Config  # noqa: E402
from companion.daemon import Daemon  # noqa: E402
from companion.frames import euler_from_quat  # noqa: E402
from companion.messages import PoseEstimate  # noqa: E402
from companion.selection import SourceSelector  # noqa: E402
from sitl.truth import TruthSource  # noqa: E402
from sitl.harness import TelemetryListener  # noqa: E402
from tests.conftest import REPO, free_port  # noqa: E402

HOME = (1.2966, 103.7764, 10.0)  # config/sitl.yaml's origin; the vehicle's --home
HOVER_MISSION = REPO / "config" / "missions" / "hover.yaml"
GCS_SYSID = 255
GCS_COMPID = 190  # MAV_COMP_ID_MISSIONPLANNER


# -- configs --------------------------------------------------------------------------------


def write_config(path: Path, *, vehicle_port: int, zenoh_port: int | None = None, mission: bool | Path = True,
                 sim_state_hz: float = 0.0, mavlink: dict | None = None, telemetry: dict | None = None,
                 vehicle_position_source: str = "gps", sections: dict[str, dict] | None = None) -> Path:
    """A daemon config on loopback: MAVLink udpout to ``vehicle_port``, zenoh on ``zenoh_port``
    (None: telemetry disabled), with arming allowed and the mission file ``mission`` (True: the
    hover mission; False: none). ``sections`` are merged into the top-level sections (e.g.
    ``{"control": {"output": "position_only"}, "mission": {"failsafe": {...}}}``).

    The ``sitl`` section (used by ``companion sitl`` only) points at free ports too.
    """
    mission_file = HOVER_MISSION if mission is True else (mission or None)
    doc: dict[str, Any] = {
        "origin": {"lat": HOME[0], "lon": HOME[1], "alt": HOME[2]},
        "vehicle": {"sysid": 1, "compid": 197},
        "mavlink": {"url": f"udpout:127.0.0.1:{vehicle_port}", "estimate_rate_hz": 30,
                    "streams": {"sim_state": sim_state_hz}, **(mavlink or {})},
        "telemetry": ({"enabled": False} if zenoh_port is None else
                      {"listen": [f"tcp/127.0.0.1:{zenoh_port}"], **(telemetry or {})}),
        "mission": {"file": str(mission_file) if mission_file else None, "allow_arm": True},
        "sitl": {"world": str(REPO / "config" / "worlds" / "arena.yaml"),
                 "vehicle_url": f"udpin:127.0.0.1:{vehicle_port}",
                 "gcs_urls": [f"udpout:127.0.0.1:{free_port()}"],
                 "position_source": vehicle_position_source, "gust_mps": 0.2},
    }
    for section, values in (sections or {}).items():
        doc.setdefault(section, {}).update(values)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def vehicle_args(port: int, *, log: Path | None = None, lockstep: bool = False, seconds: float | None = None,
                 position_source: str = "gps", gps: bool = True, seed: int = 0,
                 gcs: tuple[str, ...] = (), start: str | None = None, legacy_streams: bool = False,
                 refuse_intervals: tuple[int, ...] = ()) -> list[str]:
    """Command line of ``python -m sitl.vehicle`` listening for the companion on ``port``."""
    args = [sys.executable, "-m", "sitl.vehicle", "--companion", f"udpin:127.0.0.1:{port}",
            "--seed", str(seed), "--home", ",".join(str(v) for v in HOME),
            "--position-source", position_source]
    if log is not None:
        args += ["--log", str(log)]
    if lockstep:
        args.append("--lockstep")
    if seconds is not None:
        args += ["--seconds", str(seconds)]
    if not gps:
        args.append("--no-gps")
    if start is not None:
        args += ["--start", start]
    for url in gcs:
        args += ["--gcs", url]
    if legacy_streams:
        args.append("--legacy-streams")
    for msgid in refuse_intervals:
        args += ["--refuse-interval", str(msgid)]
    return args


def read_log(path: Path) -> dict:
    """The vehicle's flight log (sitl/flight_log.py)."""
    return json.loads(path.read_text())


# -- processes ------------------------------------------------------------------------------


class Processes:
    """Starts subprocesses with their output in files; kills every one still alive at close.

    Use as a fixture (``yield p`` then ``p.close()``) so that no process outlives its test.
    """

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, args: list[str]) -> subprocess.Popen:
        with open(self.directory / f"{name}.out", "w") as out:
            proc = subprocess.Popen(args, cwd=REPO, stdout=out, stderr=subprocess.STDOUT)
        self.procs.append((name, proc))
        return proc

    def output(self, name: str) -> str:
        path = self.directory / f"{name}.out"
        return path.read_text() if path.exists() else ""

    @staticmethod
    def stop(proc: subprocess.Popen, timeout_s: float = 10.0) -> int:
        """SIGTERM, then SIGKILL if it does not exit in ``timeout_s``; the exit status."""
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                return proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
        return proc.wait()

    def close(self) -> None:
        for _, proc in self.procs:
            if proc.poll() is None:
                proc.kill()
            proc.wait()


def wait_for(condition: Callable[[], Any], timeout_s: float, what: str, poll_s: float = 0.05) -> Any:
    """Poll ``condition`` (wall clock) until it returns something truthy; fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(poll_s)


# -- telemetry and ground station -----------------------------------------------------------


class TelemetryRecorder(TelemetryListener):
    """sitl.harness.TelemetryListener that also keeps every payload, in arrival order."""

    def __init__(self, zenoh_port: int, sysid: int = 1) -> None:
        self.history: list[tuple[str, dict]] = []
        super().__init__([f"tcp/127.0.0.1:{zenoh_port}"], sysid)

    def _on_sample(self, sample) -> None:  # type: ignore[no-untyped-def]
        super()._on_sample(sample)
        stream = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if stream in self.latest:
                self.history.append((stream, self.latest[stream]))

    def mark(self) -> int:
        """A position in the history, for :meth:`stream` ``since``."""
        with self._lock:
            return len(self.history)

    def stream(self, name: str, since: int = 0) -> list[dict]:
        """Every payload of stream ``name`` received (after history position ``since``)."""
        with self._lock:
            return [payload for s, payload in self.history[since:] if s == name]

    def get(self, stream: str) -> dict:
        return self.snapshot().get(stream, {})


class GroundStation:
    """A pymavlink ground station on a vehicle GCS link (the vehicle sends with udpout to us)."""

    def __init__(self) -> None:
        self.port = free_port()
        self.url_for_vehicle = f"udpout:127.0.0.1:{self.port}"
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{self.port}", source_system=GCS_SYSID,
                                               source_component=GCS_COMPID, dialect="ardupilotmega")
        self.received: list[Any] = []

    def pump(self, timeout_s: float = 0.05) -> None:
        """Read whatever arrived (waiting at most ``timeout_s`` for the first message)."""
        msg = self.conn.recv_match(blocking=True, timeout=timeout_s)
        while msg is not None:
            if msg.get_type() != "BAD_DATA":
                self.received.append(msg)
            msg = self.conn.recv_match(blocking=False)

    def wait_for(self, predicate: Callable[[Any], bool], timeout_s: float, what: str) -> Any:
        deadline = time.monotonic() + timeout_s
        seen = 0
        while True:
            for msg in self.received[seen:]:
                if predicate(msg):
                    return msg
            seen = len(self.received)
            if time.monotonic() > deadline:
                raise AssertionError(f"ground station: timed out after {timeout_s:g} s waiting for {what}")
            self.pump()

    def command_long(self, command: int, *params: float, target: tuple[int, int] = (1, 1)) -> None:
        """Send COMMAND_LONG to the vehicle (once it has spoken: udpin replies to the last sender)."""
        self.wait_for(lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1, 15,
                      "the vehicle's HEARTBEAT")
        padded = [float(p) for p in params] + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(*target, command, 0, *padded)

    def close(self) -> None:
        self.conn.close()


# -- the daemon in-process, in lockstep with the vehicle -------------------------------------


class TruthPipeline:
    """TEST-ONLY pipeline: simulator truth (SIM_STATE) plus seeded noise, with an honest covariance.

    Not an estimator: it exercises the estimate API, the stamps and the frame end to end. Each
    step returns the newest truth sample (stamped with its capture time on the daemon clock)
    plus N(0, ``position_sigma_m``) per axis and N(0, ``angle_sigma_rad``) per Euler angle.
    Faults for the tests: ``frame="enu"`` reports ENU instead of NED (x/y swapped, z negated,
    yaw from east), ``nan_every`` makes every n-th estimate's x NaN, ``crash_on_call`` raises,
    ``blackout=(t0, t1)`` emits nothing from daemon time t0 to t1 (s), ``offset=(t0, (dx, dy, dz))``
    shifts every estimate from t0 on by that many metres (a wrong relocalization).
    """

    name = "test_truth"
    telemetry_streams: tuple[str, ...] = ()

    def __init__(self, truth: TruthSource, seed: int, *, frame: str = "ned", nan_every: int | None = None,
                 crash_on_call: int | None = None, position_sigma_m: float = 0.01,
                 angle_sigma_rad: float = math.radians(0.5), blackout: tuple[float, float] | None = None,
                 offset: tuple[float, tuple[float, float, float]] | None = None) -> None:
        self.truth = truth
        self.rng = np.random.default_rng(seed)
        self.frame = frame
        self.nan_every = nan_every
        self.crash_on_call = crash_on_call
        self.blackout = blackout
        self.offset = offset
        self.position_sigma_m = position_sigma_m
        self.angle_sigma_rad = angle_sigma_rad
        self.calls = 0
        self.emitted = 0
        self.nan_emitted = 0
        self.crash_time: float | None = None
        self.timings: dict = {}  # no stages worth timing
        self._last_t: float | None = None

    def snapshot(self) -> dict:
        """Telemetry counters (the daemon's system stream)."""
        return {"emitted": self.emitted, "nan_emitted": self.nan_emitted}

    def subscriptions(self) -> dict:
        return {}  # reads the truth source directly

    def telemetry(self, static_due: bool) -> dict:
        return {}

    def operating_area(self) -> None:
        return None

    def step(self, now: float) -> list[PoseEstimate]:
        estimate = self._estimate(now)
        return [] if estimate is None else [estimate]

    def _estimate(self, now: float) -> PoseEstimate | None:
        self.calls += 1
        if self.calls == self.crash_on_call:
            self.crash_time = now
            raise RuntimeError(f"test pipeline exploded on call {self.calls}")
        sample = self.truth.latest
        if sample is None or sample.t == self._last_t:
            return None
        if self.blackout is not None and self.blackout[0] <= now < self.blackout[1]:
            return None
        self._last_t = sample.t
        position = sample.position_ned + self.rng.normal(0.0, self.position_sigma_m, 3)
        if self.offset is not None and now >= self.offset[0]:
            position = position + np.asarray(self.offset[1])
        euler = np.asarray(euler_from_quat(sample.quat)) + self.rng.normal(0.0, self.angle_sigma_rad, 3)
        if self.frame in ("enu", "enu_position"):
            position = np.array([position[1], position[0], -position[2]])
        if self.frame == "enu":
            euler = np.array([euler[1], euler[0], math.pi / 2 - euler[2]])
        self.emitted += 1
        if self.nan_every and self.emitted % self.nan_every == 0:
            position[0] = math.nan
            self.nan_emitted += 1
        covariance = np.diag([self.position_sigma_m ** 2] * 3 + [self.angle_sigma_rad ** 2] * 3)
        return PoseEstimate(sample.t, position, (float(euler[0]), float(euler[1]), float(euler[2])),
                            covariance, source=self.name)


class PipelineDaemon(Daemon):
    """The real daemon with one test pipeline built on its link and origin."""

    def __init__(self, cfg: Config, make_pipeline: Callable[[TruthSource], Any]) -> None:
        super().__init__(cfg)
        self._make_pipeline = make_pipeline
        self.pipeline: Any = None

    def build_pipelines(self) -> list:
        self.pipeline = self._make_pipeline(TruthSource(self.link, self.cfg.origin))
        return [self.pipeline]

    def _build_selector(self, pipelines: list) -> SourceSelector:
        """The test pipeline is the one pose source (it is not in the config)."""
        p = self.cfg.pipelines
        return SourceSelector([self.pipeline.name], p.source_timeout_s, p.source_return_s, p.source_max_sigma_m)


def run_daemon_with_vehicle(daemon: Daemon, vehicle: subprocess.Popen, timeout_s: float = 50.0) -> int:
    """Run ``daemon.run()`` on a LockstepEventLoop until the (lockstep) vehicle process exits.

    A watcher thread waits for the vehicle on the wall clock (simulation time stops with it),
    then asks the daemon to stop; a vehicle still running after ``timeout_s`` is killed.
    """
    loop = LockstepEventLoop()

    def watch() -> None:
        try:
            vehicle.wait(timeout_s)
        except subprocess.TimeoutExpired:
            vehicle.kill()
            vehicle.wait()
        try:
            loop.call_soon_threadsafe(daemon.request_stop)
        except RuntimeError:  # the loop is already closed
            pass

    watcher = threading.Thread(target=watch, name="vehicle-watch", daemon=True)
    watcher.start()
    asyncio.set_event_loop(loop)
    try:
        return loop.run_until_complete(daemon.run())
    finally:
        asyncio.set_event_loop(None)
        loop.close()
        watcher.join(timeout=1.0)


def write_sitl_config(path: Path, *, vehicle_port: int, gcs_port: int, zenoh_port: int,
                      mission: str | None, source: str = "sitl.yaml") -> Path:
    """config/``source`` (default sitl.yaml) with free loopback ports, absolute paths and the given
    mission file (None: none)."""
    raw = yaml.safe_load((REPO / "config" / source).read_text())
    raw["mavlink"]["url"] = f"udpout:127.0.0.1:{vehicle_port}"
    raw["telemetry"]["listen"] = [f"tcp/127.0.0.1:{zenoh_port}"]
    raw["mission"]["file"] = mission
    raw["sitl"]["vehicle_url"] = f"udpin:127.0.0.1:{vehicle_port}"
    raw["sitl"]["gcs_urls"] = [f"udpout:127.0.0.1:{gcs_port}"]
    raw["sitl"]["world"] = str(REPO / "config" / raw["sitl"]["world"])
    raw["pipelines"]["lidar"]["map"] = str(REPO / "config" / raw["pipelines"]["lidar"]["map"])
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def real_driver_config(directory: Path, **sitl: object) -> tuple[Path, dict]:
    """config/sitl-real-driver.yaml on free loopback ports with absolute paths, beside a copy of
    config/missions (``--mission NAME`` looks there); ``sitl`` keys override."""
    raw = yaml.safe_load((REPO / "config" / "sitl-real-driver.yaml").read_text())
    vehicle_port = free_port()
    raw["mavlink"]["url"] = f"udpout:127.0.0.1:{vehicle_port}"
    raw["telemetry"]["listen"] = [f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]
    raw["sitl"].update(vehicle_url=f"udpin:127.0.0.1:{vehicle_port}", gcs_urls=[f"udpout:127.0.0.1:{free_port()}"],
                       world=str(REPO / "config" / "worlds" / "arena.yaml"), **sitl)
    raw["pipelines"]["lidar"]["map"] = str(REPO / "config" / "worlds" / "arena.yaml")
    for sensor in raw["sensors"].values():
        if sensor["kind"] == "lidar":
            sensor["settings"]["tcp_port"] = free_port(socket.SOCK_STREAM)
    shutil.copytree(REPO / "config" / "missions", directory / "missions", dirs_exist_ok=True)
    path = directory / "companion.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path, raw
