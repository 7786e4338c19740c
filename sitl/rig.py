"""One SITL run for the experiments (``companion experiment faults|soak``): the built-in vehicle,
the SCIP bridge (real Hokuyo driver, ``--faults-from-stdin``) and the daemon, the daemon's MAVLink
link through a :class:`sitl.fault_proxy.FaultProxy`; real time, loopback only.

The daemon, the vehicle and the bridge are given the service's priority (:data:`SERVICE_NICE`,
the ``Nice=`` of systemd/companion.service) right after they start, where this process may raise
priorities (root, or CAP_SYS_NICE; not every container grants it); the vehicle and the bridge
stand for hardware that does not share the companion's CPU. What each process actually got is
measured (:attr:`Rig.priorities`): the fault suite reports it and applies its timing checks only
where the priority was the service's. The daemon publishes its status at 10 Hz by default here
(recovery times to 0.1 s).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import yaml

from companion.config import Config
from sitl.fault_proxy import FaultProxy
from sitl.report import DEGRADED_SLOWDOWN
from sitl.harness import (TelemetryListener, free_udp_port, scip_bridge_command, scip_ports, vehicle_command,
                          wait_listening, write_run_config)

SERVICE_NICE = -10  # systemd/companion.service: Nice= (a test keeps them equal)
STOP_BUDGET_S = 2.0  # SIGTERM -> exit 0 within this
ESTIMATE_FRESH_S = 0.3  # VISION_POSITION_ESTIMATE at 30 Hz: older than this = not flowing
TELEMETRY_PERIOD_S = 0.1  # status at 10 Hz in the run config
TELEMETRY_FRESH_S = 0.5


def set_service_priority(pid: int) -> int | None:
    """Give process ``pid`` the service's priority where this process may; the nice value it has
    then (None: it is gone).

    Called right after ``Popen`` returns: the child has just exec'd its interpreter and has one
    thread, and the threads it starts later inherit its nice value (on Linux, nice is per thread).
    Not a ``preexec_fn``: that runs between fork and exec in a copy of this process, whose other
    threads (the fault proxy's, zenoh's) may hold locks the child then waits for forever."""
    with contextlib.suppress(PermissionError):
        os.setpriority(os.PRIO_PROCESS, pid, SERVICE_NICE)
    try:
        return os.getpriority(os.PRIO_PROCESS, pid)
    except ProcessLookupError:
        return None


def start_at_service_priority(cmd: list[str], **popen: object) -> tuple[subprocess.Popen, int | None]:
    """``Popen(cmd, **popen)`` at the service's priority where permitted: (process, its nice value)."""
    proc = subprocess.Popen(cmd, **popen)  # type: ignore[call-overload]
    return proc, set_service_priority(proc.pid)


class Counters(NamedTuple):
    """Totals so far (see :meth:`Rig.counters`); compare two to measure one fault."""

    restarts: int  # supervised task restarts in the daemon
    failsafes: int  # as the flight report counts them: the mission's stops, holds and landings and
    # the autopilot's own failsafe mode changes, not its slowdowns on a degraded estimate
    nonfinite_sent: int  # messages to the autopilot with a NaN or infinity (counted by the proxy)


@contextlib.contextmanager
def sigterm_exits() -> Iterator[None]:
    """Inside: SIGTERM raises SystemExit(143) in the main thread, so that the ``finally`` blocks
    stop the vehicle, the bridge, the daemon and any CPU hog, and the report is written (what
    SIGINT already does through KeyboardInterrupt). The previous handler is restored on the way out."""
    def exit_now(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, exit_now)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def stop_process(proc: subprocess.Popen, budget_s: float = STOP_BUDGET_S) -> tuple[int | None, float]:
    """SIGTERM ``proc``: (exit status or None if it had to be killed, seconds it took)."""
    started = time.monotonic()
    if proc.poll() is not None:
        return proc.returncode, 0.0
    proc.send_signal(signal.SIGTERM)
    try:
        rc = proc.wait(budget_s + 3.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        return None, time.monotonic() - started
    return rc, time.monotonic() - started


class Rig:
    """Vehicle + SCIP bridge + daemon, the daemon's link through a :class:`FaultProxy` (real time)."""

    def __init__(self, cfg: Config, mission: str | Path, work: Path, seed: int,
                 status_period_s: float = TELEMETRY_PERIOD_S) -> None:
        """``mission``: a mission name (``missions/NAME.yaml`` beside the config) or a mission file.
        ``status_period_s``: the daemon's ``telemetry.status_hz`` period (short: precise recovery
        times; the deployed 1 s: what a vehicle's daemon does)."""
        self.cfg = cfg
        self.work = work
        work.mkdir(parents=True, exist_ok=True)
        self.seed = seed
        self.status_period_s = status_period_s
        self.vehicle_port = int(cfg.sitl.vehicle_url.rsplit(":", 1)[1])
        self.proxy = FaultProxy(self.vehicle_port, (cfg.vehicle.autopilot_sysid, cfg.vehicle.autopilot_compid))
        self.run_config = self._write_run_config(mission, status_period_s)
        self.vehicle: subprocess.Popen | None = None
        self.bridge: subprocess.Popen | None = None
        self.daemon: subprocess.Popen | None = None
        self.listener: TelemetryListener | None = None
        self.vehicle_restarts = 0
        self._extra_gcs: tuple[str, ...] = ()  # the vehicle's links besides the daemon's (the bridge's)
        self.priorities: dict[str, int | None] = {}  # nice value of the daemon, vehicle, bridge (latest start)

    def _write_run_config(self, mission: str | Path, status_period_s: float) -> Path:
        name = mission if isinstance(mission, str) else None
        path = write_run_config(self.cfg, name, self.work, f"udpout:127.0.0.1:{self.proxy.port}")
        raw = yaml.safe_load(path.read_text())
        if isinstance(mission, Path):
            raw.setdefault("mission", {})["file"] = str(mission.resolve())
        raw.setdefault("telemetry", {})["status_hz"] = 1.0 / status_period_s
        path.write_text(yaml.safe_dump(raw, sort_keys=False))
        return path

    def _args(self) -> argparse.Namespace:
        return argparse.Namespace(seed=self.seed, lockstep=False, seconds=None)

    def start(self) -> None:
        self.proxy.start()
        bridge_port = free_udp_port()
        if self.cfg.sitl.scip_sensors:
            self.bridge, self.priorities["bridge"] = start_at_service_priority(
                [*scip_bridge_command(self.cfg, self._args(), f"udpin:127.0.0.1:{bridge_port}"), "--faults-from-stdin"],
                stdin=subprocess.PIPE, text=True)
            self._extra_gcs = (f"udpout:127.0.0.1:{bridge_port}",)
        self._start_vehicle()
        if self.bridge is not None and not wait_listening(self.bridge, scip_ports(self.cfg), 15.0):
            raise RuntimeError("the SCIP bridge did not come up")
        self.start_daemon()
        self.listener = TelemetryListener(self.cfg.telemetry.listen, self.cfg.vehicle.sysid)

    def _start_vehicle(self) -> None:
        cmd = vehicle_command(self.cfg, self._args(), self.work / f"vehicle-{self.vehicle_restarts}.json",
                              self._extra_gcs)
        self.vehicle, self.priorities["vehicle"] = start_at_service_priority(cmd)

    def restart_vehicle(self, timeout_s: float = 15.0) -> None:
        """Kill the vehicle (SIGKILL: no goodbye), start a new one on the same ports and return
        when it first speaks to the daemon (through the proxy)."""
        assert self.vehicle is not None
        self.vehicle.kill()
        self.vehicle.wait()
        with self.proxy.lock:
            heard = self.proxy.counters.to_daemon
        self.vehicle_restarts += 1
        self._start_vehicle()
        if not wait_until(lambda: self.proxy.counters.to_daemon > heard, timeout_s):
            raise RuntimeError(f"the restarted vehicle did not speak within {timeout_s:g} s")

    def start_daemon(self) -> None:
        self.daemon, self.priorities["daemon"] = start_at_service_priority(
            [sys.executable, "-m", "companion.cli", "run", "-c", str(self.run_config)])

    def at_service_priority(self, role: str = "daemon") -> bool:
        """Whether ``role`` (daemon, vehicle, bridge) was last started at the service's priority."""
        nice = self.priorities.get(role)
        return nice is not None and nice <= SERVICE_NICE

    def bridge_command(self, line: str) -> None:
        assert self.bridge is not None and self.bridge.stdin is not None
        self.bridge.stdin.write(line + "\n")
        self.bridge.stdin.flush()

    def close(self) -> None:
        for proc in (self.daemon, self.vehicle, self.bridge):
            if proc is not None:
                stop_process(proc, 5.0)
        if self.listener is not None:
            self.listener.close()
        self.proxy.close()

    # -- what the suite measures ------------------------------------------------------------

    def telemetry(self, stream: str) -> dict:
        """The latest payload of ``stream`` if it is fresh, else {}."""
        assert self.listener is not None
        if self.listener.age(stream) > TELEMETRY_FRESH_S + self.status_period_s:
            return {}
        return self.listener.snapshot().get(stream, {})

    def ok_components(self) -> set[str]:
        components = self.telemetry("health").get("components", {})
        return {name for name, c in components.items() if c["state"] == "ok" and not name.startswith("task:")}

    def unhealthy(self, expected: set[str]) -> str | None:
        """Why the daemon is not healthy now, or None: estimates reaching the autopilot, the link
        up and every component of ``expected`` ok."""
        if self.daemon is None or self.daemon.poll() is not None:
            return "daemon not running"
        age = self.proxy.last_estimate_age()
        if age > ESTIMATE_FRESH_S:
            return f"no estimate to the autopilot for {age:.1f} s"
        if not self.telemetry("link").get("connected"):
            return "link down"
        missing = expected - self.ok_components()
        if missing:
            return "not ok: " + ", ".join(sorted(missing))
        return None

    def counters(self) -> Counters:
        """The totals so far: task restarts, failsafes, non-finite values sent (see :class:`Counters`)."""
        assert self.listener is not None
        tasks = self.telemetry("health").get("tasks") or self.listener.snapshot().get("health", {}).get("tasks", {})
        restarts = sum(t.get("restarts", 0) for t in tasks.values())
        mission = self.listener.snapshot().get("mission", {})
        failsafes = sum(n for kind, n in mission.get("failsafe_counts", {}).items() if kind != DEGRADED_SLOWDOWN)
        with self.proxy.lock:
            nonfinite = self.proxy.counters.nonfinite_sent
        return Counters(restarts, failsafes, nonfinite)

    def boot_ms(self) -> int:
        """A boot time (ms) near the autopilot's, for forged messages: the daemon's uptime (the
        vehicle starts just before the daemon)."""
        assert self.listener is not None
        system = self.listener.snapshot().get("system", {})
        return int(system.get("uptime_s", 10.0) * 1000)


def wait_until(predicate: Callable[[], bool], timeout_s: float, period_s: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period_s)
    return predicate()
