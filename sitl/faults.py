"""`companion experiment faults --out R.json`: the fault suite, against the SITL, in real time.

Everything runs on loopback with the built-in vehicle and the daemon's *real* Hokuyo driver
(the SCIP bridge, config/sitl-real-driver.yaml by default). The daemon's MAVLink link goes
through a :class:`sitl.fault_proxy.FaultProxy`, which breaks the link, forges messages as the
autopilot, and counts every non-finite value the daemon sends the autopilot (measured outside
the daemon). The bridge breaks the scanners on command (``--faults-from-stdin``).

Runs, in order (``--only`` picks faults by name):

- **flight**: mission ``faults`` (take off, hold, land). Once airborne and settled, one fault
  at a time: NaN / infinity storms in every float the daemon consumes, spoofed heartbeats,
  forged messages (acknowledgements, boot time going backwards, another component claiming to
  be the autopilot), line noise on the MAVLink link, scanner unplugged / corrupted frames /
  garbage frames / slow, a zenoh flood, a CPU-bound process on each core, the autopilot stopped
  2 s; then the faults that end a real flight: the link lost 3 s (the autopilot's EKF failsafe
  lands), the autopilot stopped 10 s, the autopilot killed and restarted.
- **patrol with a NaN storm**: mission ``patrol`` with a 3 s NaN / infinity storm of ATTITUDE,
  HIGHRES_IMU and LOCAL_POSITION_NED in the middle; recovered = the mission completes with no
  failsafe.
- **SIGTERM** in each state: before any autopilot answers, against a TCP endpoint that never
  accepts, in flight, with the autopilot stopped (link lost).
- **bad config files**: ``companion check-config`` on a device that never ends, a FIFO, an
  empty file, a binary file, a config whose mission is missing.

Per fault: ``recovered``; ``recovery_s`` (from the moment the fault clears until the daemon is
healthy again: estimates reaching the autopilot, every health component that was ok before
the fault ok again, link up; for SIGTERM and config files: until the process exited);
``crashes`` (supervised task restarts, or the daemon dying); ``nonfinite_sent`` (messages to
the autopilot with a NaN or infinity, counted by the proxy); ``failsafes`` (as the flight
report counts them: the mission's stops, holds and landings and the autopilot's own failsafe
mode changes; not its slowdowns on a degraded estimate); ``detail`` (what was seen).

The processes of a flight run: sitl/rig.py (priorities included).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import yaml

from companion.config import Config, load_config
from companion.mavlink.link import mavlink
from companion.telemetry.keys import KEY_PREFIX
from sitl.harness import free_udp_port
from sitl.rig import (SERVICE_NICE, STOP_BUDGET_S, TELEMETRY_PERIOD_S, Rig, start_at_service_priority, stop_process,
                      wait_until)

log = logging.getLogger("companion.faults")

HEALTHY_WITHIN_S = 20.0  # a fault not recovered this long after it cleared is not recovered
SETTLE_S = 2.0  # healthy this long between two faults
STORM_HZ = 200.0  # forged messages per second of each type in a storm
AIRBORNE_TIMEOUT_S = 90.0
PATROL_STORM_AT = 0.75  # mission progress: the patrol's fly step (index 4 of 6) is half done


@dataclass
class FaultResult:
    name: str
    recovered: bool
    recovery_s: float | None
    crashes: int
    nonfinite_sent: int
    failsafes: int
    detail: str = ""


# -- forged messages -----------------------------------------------------------------------------

def nonfinite_storm_messages(value: float, boot_ms: int) -> list[mavlink.MAVLink_message]:
    """One of each autopilot message the daemon reads a float from, every float ``value`` (NaN or inf)."""
    v, q = value, [value] * 4
    return [
        mavlink.MAVLink_attitude_message(boot_ms, v, v, v, v, v, v),
        mavlink.MAVLink_highres_imu_message(boot_ms * 1000, v, v, v, v, v, v, v, v, v, v, v, v, v, 0xFFFF),
        mavlink.MAVLink_local_position_ned_message(boot_ms, v, v, v, v, v, v),
        mavlink.MAVLink_home_position_message(12966000, 1037764000, 10000, v, v, v, q, v, v, v),
        mavlink.MAVLink_ekf_status_report_message(0x3FF, v, v, v, v, v, v),
        mavlink.MAVLink_sim_state_message(*q, v, v, v, v, v, v, v, v, v, v, v, v, v, v, v, v, v),
        mavlink.MAVLink_attitude_quaternion_message(boot_ms, *q, v, v, v),
    ]


def spoof_messages(boot_ms: int) -> list[mavlink.MAVLink_message]:
    """Heartbeats claiming the autopilot is something else (sent from the autopilot's ids)."""
    return [mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                              mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4 << 16,
                                              mavlink.MAV_STATE_ACTIVE, 3)]


def forged_messages(boot_ms: int) -> list[mavlink.MAVLink_message]:
    """Acknowledgements nobody asked for (LAND accepted, arming denied), a boot time that went
    backwards, a disarmed heartbeat in LAND."""
    return [mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_RESULT_ACCEPTED),
            mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_DENIED),
            mavlink.MAVLink_attitude_message(max(boot_ms - 600_000, 0), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
            mavlink.MAVLink_system_time_message(0, 5)]


def other_component_heartbeat(boot_ms: int) -> list[mavlink.MAVLink_message]:
    """An autopilot heartbeat from a component that is not the autopilot (sent as compid 2)."""
    return [mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                              mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 9, mavlink.MAV_STATE_ACTIVE, 3)]


# -- the processes of one run --------------------------------------------------------------------

# -- running faults ------------------------------------------------------------------------------

def storm(rig: Rig, seconds: float, make: Callable[[int], list[mavlink.MAVLink_message]],
          src: tuple[int, int] | None = None) -> None:
    """Send ``make(boot_ms)`` at STORM_HZ for ``seconds``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rig.proxy.inject(make(rig.boot_ms()), src)
        time.sleep(1.0 / STORM_HZ)


def nan_and_inf(rig: Rig, seconds: float) -> None:
    values = (math.nan, math.inf, -math.inf)
    i = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rig.proxy.inject(nonfinite_storm_messages(values[i % 3], rig.boot_ms()))
        i += 1
        time.sleep(1.0 / STORM_HZ)


def line_noise(rig: Rig, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rig.proxy.inject_bytes(os.urandom(280))
        rig.proxy.inject_bytes(b"\xfd\x09\x00\x00\x07\x01\x01\x00\x00\x00" + os.urandom(20))
        time.sleep(1.0 / STORM_HZ)


def zenoh_flood(rig: Rig, seconds: float) -> None:
    """A zenoh peer publishing as fast as it can, on the daemon's keys and others."""
    from companion.telemetry.session import open_session

    session = open_session("peer", [], rig.cfg.telemetry.listen, False, False)
    try:
        keys = [f"{KEY_PREFIX}/{rig.cfg.vehicle.sysid}/pose", f"{KEY_PREFIX}/{rig.cfg.vehicle.sysid}/command",
                "flood/a", f"{KEY_PREFIX}/**"]
        publishers = [session.declare_publisher(k) for k in keys if "*" not in k]
        payload = os.urandom(4096)
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            for p in publishers:
                p.put(payload)
    finally:
        session.close()


@contextlib.contextmanager
def cpu_hogs(n: int) -> Iterator[None]:
    """``n`` CPU-bound processes (default priority) while inside."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def stop_vehicle(rig: Rig, seconds: float) -> None:
    assert rig.vehicle is not None
    rig.vehicle.send_signal(signal.SIGSTOP)
    try:
        time.sleep(seconds)
    finally:
        rig.vehicle.send_signal(signal.SIGCONT)


def scanner_fault(rig: Rig, command: str, seconds: float, every_s: float | None = None) -> None:
    """Send the bridge ``command`` for every bridged scanner ({name}), again ``every_s`` if given,
    for ``seconds``."""
    end = time.monotonic() + seconds
    while True:
        for name in rig.cfg.sitl.scip_sensors:
            rig.bridge_command(command.format(name=name))
        if every_s is None:
            break
        time.sleep(min(every_s, max(end - time.monotonic(), 0.0)))
        if time.monotonic() >= end:
            return
    time.sleep(max(end - time.monotonic(), 0.0))


def side_effects(rig: Rig, fault: FlightFault, link_before: dict) -> list[str]:
    """What the fault changed that it must not have: the mission (a survivable fault), the
    detected autopilot, the count of autopilot reboots."""
    link, mission = rig.listener.snapshot().get("link", {}), rig.listener.snapshot().get("mission", {})
    wrong = []
    if fault.survivable and mission.get("state") != "running":
        wrong.append(f"mission {mission.get('state')}: {mission.get('reason')}")
    if link.get("autopilot") != link_before.get("autopilot"):
        wrong.append(f"autopilot {link_before.get('autopilot')} -> {link.get('autopilot')}")
    reboots = link.get("autopilot_reboots", 0) - link_before.get("autopilot_reboots", 0)
    if reboots != fault.reboots:
        wrong.append(f"{reboots} autopilot reboots counted ({fault.reboots} real)")
    return wrong


def reboot_pending(rig: Rig, fault: FlightFault, link_before: dict) -> str | None:
    """Why not recovered yet from a restarted autopilot: the daemon has not counted its reboot
    (and so has not started over: origin, streams, estimator)."""
    counted = rig.telemetry("link").get("autopilot_reboots", 0) - link_before.get("autopilot_reboots", 0)
    return f"reboot not counted yet ({counted} of {fault.reboots})" if counted < fault.reboots else None


def measure(rig: Rig, fault: FlightFault, expected: set[str], timeout_s: float = HEALTHY_WITHIN_S) -> FaultResult:
    """Inject one fault and measure the recovery (see the module docstring)."""
    before = rig.counters()
    link_before = rig.listener.snapshot().get("link", {})
    daemon = rig.daemon
    started = time.monotonic()
    log.info("fault %s: injecting", fault.name)
    fault.inject(rig)
    cleared = time.monotonic()
    healthy_at: float | None = None
    why: str | None = None
    deadline = cleared + timeout_s
    while time.monotonic() < deadline:
        why = rig.unhealthy(expected) or reboot_pending(rig, fault, link_before)
        if why is None:
            healthy_at = time.monotonic()
            break
        time.sleep(0.05)
    after = rig.counters()
    crashes = after.restarts - before.restarts + (1 if daemon is not None and daemon.poll() is not None else 0)
    time.sleep(2 * TELEMETRY_PERIOD_S)  # the link and mission state after the recovery
    gap = rig.proxy.longest_estimate_gap(started, cleared)
    wrong = side_effects(rig, fault, link_before)
    gap_checked = fault.max_gap_s is not None and rig.at_service_priority()
    gap_ok = not gap_checked or gap <= (fault.max_gap_s or 0.0)
    recovered = healthy_at is not None and not wrong and gap_ok
    parts = [f"longest estimate gap during the fault {gap * 1000:.0f} ms", *wrong]
    if fault.max_gap_s is not None:
        limit = f"{fault.max_gap_s * 1000:.0f} ms"
        parts.append(f"over the {limit} limit" if not gap_ok else f"within the {limit} limit" if gap_checked else
                     f"the {limit} limit not applied: the daemon ran at nice {rig.priorities.get('daemon')}, "
                     f"not {SERVICE_NICE} (not permitted to raise it)")
    text = "; ".join(parts)
    if healthy_at is None:
        text += f"; still unhealthy {timeout_s:g} s after: {why}"
    result = FaultResult(fault.name, recovered, None if healthy_at is None else round(healthy_at - cleared, 2),
                         crashes, after.nonfinite_sent - before.nonfinite_sent, after.failsafes - before.failsafes, text)
    log.info("fault %s: %s", fault.name, result)
    return result


# -- the runs ------------------------------------------------------------------------------------

def cpu_hog(seconds: float) -> None:
    """A CPU-bound process on each core for ``seconds``."""
    with cpu_hogs(os.cpu_count() or 2):
        time.sleep(seconds)


def link_loss(rig: Rig, seconds: float) -> None:
    rig.proxy.block(seconds)
    time.sleep(seconds)


def _autopilot_ids(rig: Rig) -> tuple[int, int]:
    return rig.cfg.vehicle.autopilot_sysid, rig.cfg.vehicle.autopilot_compid


@dataclass(frozen=True)
class FlightFault:
    """One fault of the flight run: ``inject(rig)`` returns when the fault clears."""

    name: str
    inject: Callable[[Rig], None]
    max_gap_s: float | None = None  # recovered only if estimates never stopped longer than this
    survivable: bool = True  # a flight survives it: the mission flies on, the autopilot is the same one
    reboots: int = 0  # autopilot reboots the daemon must count (the killed and restarted autopilot)


# The flight run, in order: the faults a flight survives, then those that end a real flight whose
# only position source is the lidar: both scanners gone, the autopilot hung or gone, the link
# lost (the autopilot's EKF failsafe lands; the companion must recover all the same).
FLIGHT_FAULTS = (
    FlightFault("nan_inf_storm", lambda rig: nan_and_inf(rig, 3.0)),
    FlightFault("spoofed_heartbeats", lambda rig: storm(rig, 3.0, spoof_messages)),
    FlightFault("other_component_claims_autopilot", lambda rig: storm(
        rig, 3.0, other_component_heartbeat, (_autopilot_ids(rig)[0], _autopilot_ids(rig)[1] + 1))),
    FlightFault("forged_acks_and_time_backwards", lambda rig: storm(rig, 3.0, forged_messages)),
    FlightFault("mavlink_line_noise", lambda rig: line_noise(rig, 3.0)),
    FlightFault("scanner_corrupted_frames", lambda rig: scanner_fault(rig, "corrupt {name} 3", 3.0, every_s=0.5)),
    FlightFault("scanner_garbage_frames", lambda rig: scanner_fault(rig, "garbage {name} 3", 3.0, every_s=0.5)),
    FlightFault("scanner_slow", lambda rig: scanner_fault(rig, "delay {name} 15 0.15", 3.0)),
    FlightFault("zenoh_flood", lambda rig: zenoh_flood(rig, 3.0)),
    FlightFault("cpu_hog", lambda rig: cpu_hog(5.0), max_gap_s=0.2),
    FlightFault("scanner_unplug", lambda rig: scanner_fault(rig, "unplug {name} 2.0", 2.0), survivable=False),
    FlightFault("autopilot_stopped_2s", lambda rig: stop_vehicle(rig, 2.0), survivable=False),
    FlightFault("link_loss_3s", lambda rig: link_loss(rig, 3.0), survivable=False),
    FlightFault("autopilot_stopped_10s", lambda rig: stop_vehicle(rig, 10.0), survivable=False),
    FlightFault("autopilot_killed_restarted", lambda rig: rig.restart_vehicle(), survivable=False, reboots=1),
)


def run_flight(cfg: Config, work: Path, seed: int, wanted: Callable[[str], bool],
               priorities: dict[str, dict]) -> list[FaultResult]:
    rig = Rig(cfg, "faults", work / "flight", seed)
    results: list[FaultResult] = []
    try:
        rig.start()
        if not wait_until(lambda: rig.telemetry("mission").get("step_kind") == "hold", AIRBORNE_TIMEOUT_S):
            raise RuntimeError(f"the vehicle did not reach the hold step: {rig.listener.snapshot().get('mission')}")
        if not wait_until(lambda: rig.unhealthy(rig.ok_components()) is None and rig.ok_components(), 10.0):
            raise RuntimeError(f"not healthy before the faults: {rig.unhealthy(rig.ok_components())}")
        expected = rig.ok_components()
        log.info("healthy components before the faults: %s", ", ".join(sorted(expected)))
        for fault in FLIGHT_FAULTS:
            if wanted(fault.name):
                results.append(measure(rig, fault, expected))
            wait_until(lambda: rig.unhealthy(expected) is None, SETTLE_S)
            time.sleep(SETTLE_S)
    finally:
        rig.close()
        priorities["flight"] = dict(rig.priorities)
    return results


def run_patrol_storm(cfg: Config, work: Path, seed: int, priorities: dict[str, dict]) -> FaultResult:
    """Patrol with a 3 s NaN / infinity storm of ATTITUDE, HIGHRES_IMU and LOCAL_POSITION_NED in the middle."""
    rig = Rig(cfg, "patrol", work / "patrol", seed)
    try:
        rig.start()
        if not wait_until(lambda: rig.telemetry("mission").get("step_kind") == "fly", AIRBORNE_TIMEOUT_S):
            raise RuntimeError("the patrol did not start flying")
        wait_until(lambda: (rig.telemetry("mission").get("tracking_error_m") is not None
                            and rig.telemetry("mission").get("progress", 0.0) >= PATROL_STORM_AT), 120.0)
        before = rig.counters()
        started = time.monotonic()

        def three(boot_ms: int) -> list[mavlink.MAVLink_message]:
            value = (math.nan, math.inf, -math.inf)[int(time.monotonic() * STORM_HZ) % 3]
            return nonfinite_storm_messages(value, boot_ms)[:3]

        storm(rig, 3.0, three)
        cleared = time.monotonic()
        ended = wait_until(lambda: rig.listener.snapshot().get("mission", {}).get("state")
                           in ("completed", "failed", "aborted"), 180.0, 0.2)
        mission = rig.listener.snapshot().get("mission", {})
        after = rig.counters()
        crashes = after.restarts - before.restarts + (1 if rig.daemon is not None and rig.daemon.poll() is not None
                                                      else 0)
        failsafes = after.failsafes - before.failsafes
        completed = ended and mission.get("state") == "completed"
        gap = rig.proxy.longest_estimate_gap(started, cleared)
        return FaultResult("patrol_nan_storm", completed and failsafes == 0, 0.0 if completed else None, crashes,
                           after.nonfinite_sent - before.nonfinite_sent, failsafes,
                           f"mission {mission.get('state')} {mission.get('reason') or ''}; "
                           f"longest estimate gap in the storm {gap * 1000:.0f} ms".replace("  ", " "))
    finally:
        rig.close()
        priorities["patrol"] = dict(rig.priorities)


def sigterm_result(name: str, proc: subprocess.Popen, detail: str = "") -> FaultResult:
    rc, took = stop_process(proc)
    ok = rc == 0 and took <= STOP_BUDGET_S
    return FaultResult(name, ok, round(took, 2), 0 if rc is not None and rc >= 0 else 1, 0, 0,
                       f"exit {rc} after {took:.2f} s {detail}".strip())


def minimal_config(work: Path, url: str) -> Path:
    path = work / "minimal.yaml"
    path.write_text(yaml.safe_dump({"origin": {"lat": 1.0, "lon": 2.0, "alt": 3.0}, "telemetry": {"enabled": False},
                                    "mavlink": {"url": url, "link_timeout_s": 1.0}}))
    return path


def daemon_process(config: Path) -> tuple[subprocess.Popen, int | None]:
    """The daemon on ``config`` at the service's priority where permitted: (process, its nice value)."""
    return start_at_service_priority([sys.executable, "-m", "companion.cli", "run", "-c", str(config)],
                                     stderr=subprocess.DEVNULL)


def run_sigterms(cfg: Config, work: Path, seed: int, wanted: Callable[[str], bool],
                 priorities: dict[str, dict]) -> list[FaultResult]:
    results = []
    work.mkdir(parents=True, exist_ok=True)
    if wanted("sigterm_before_autopilot"):
        proc, nice = daemon_process(minimal_config(work, f"udpout:127.0.0.1:{free_udp_port()}"))
        priorities["sigterm_before_autopilot"] = {"daemon": nice}
        time.sleep(3.0)
        results.append(sigterm_result("sigterm_before_autopilot", proc))
    if wanted("sigterm_never_accepting_tcp_peer"):
        with never_accepting_listener() as port:
            proc, nice = daemon_process(minimal_config(work, f"tcp:127.0.0.1:{port}"))
            priorities["sigterm_never_accepting_tcp_peer"] = {"daemon": nice}
            time.sleep(3.0)
            results.append(sigterm_result("sigterm_never_accepting_tcp_peer", proc))
    if wanted("sigterm_in_flight") or wanted("sigterm_autopilot_stopped"):
        rig = Rig(cfg, "hover", work / "sigterm", seed)
        try:
            rig.start()
            wait_until(lambda: rig.telemetry("mission").get("step_kind") == "hold", AIRBORNE_TIMEOUT_S)
            if wanted("sigterm_in_flight"):
                results.append(sigterm_result("sigterm_in_flight", rig.daemon, "(mission on_daemon_stop: LAND)"))
            if wanted("sigterm_autopilot_stopped"):
                if rig.daemon.poll() is not None:
                    rig.start_daemon()
                    time.sleep(3.0)
                assert rig.vehicle is not None
                rig.vehicle.send_signal(signal.SIGSTOP)
                try:
                    time.sleep(4.0)  # > link_timeout_s: the link is lost
                    results.append(sigterm_result("sigterm_autopilot_stopped", rig.daemon))
                finally:
                    rig.vehicle.send_signal(signal.SIGCONT)
        finally:
            rig.close()
            priorities["sigterm"] = dict(rig.priorities)
    return results


@contextlib.contextmanager
def never_accepting_listener() -> Iterator[int]:
    """A loopback TCP port whose accept queue is full: a connect() to it just waits."""
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(0)
    fillers = []
    for _ in range(3):
        filler = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        filler.setblocking(False)
        filler.connect_ex(listener.getsockname())
        fillers.append(filler)
    try:
        yield listener.getsockname()[1]
    finally:
        for sock in (*fillers, listener):
            sock.close()


def bad_config_files(work: Path) -> dict[str, Path]:
    """Config files a user could hand to the daemon by mistake or malice, by fault name."""
    work.mkdir(parents=True, exist_ok=True)
    fifo = work / "fifo.yaml"
    if not fifo.exists():
        os.mkfifo(fifo)
    empty = work / "empty.yaml"
    empty.write_text("")
    binary = work / "binary.yaml"
    binary.write_bytes(bytes(range(256)) * 8)
    missing = work / "missing-mission.yaml"
    missing.write_text("origin: {lat: 1.0, lon: 2.0, alt: 3.0}\nmission:\n  file: missions/not-there.yaml\n")
    return {"config_dev_zero": Path("/dev/zero"), "config_fifo": fifo, "config_empty": empty,
            "config_binary": binary, "config_missing_mission": missing}


def run_config_faults(work: Path, wanted: Callable[[str], bool]) -> list[FaultResult]:
    """``companion check-config`` on each bad file: recovered = exit 2 with ``file:line: key:`` on
    stderr and no traceback, within STOP_BUDGET_S."""
    results = []
    for name, path in bad_config_files(work).items():
        if not wanted(name):
            continue
        started = time.monotonic()
        try:
            proc = subprocess.run([sys.executable, "-m", "companion.cli", "check-config", str(path)],
                                  capture_output=True, text=True, timeout=10.0)
            rc, stderr = proc.returncode, proc.stderr.strip()
        except subprocess.TimeoutExpired:
            rc, stderr = None, "did not return within 10 s"
        took = time.monotonic() - started
        crashed = "Traceback" in stderr or (rc is not None and rc < 0)
        ok = rc == 2 and stderr.startswith(f"companion: {path}") and not crashed and took <= STOP_BUDGET_S
        results.append(FaultResult(name, ok, round(took, 2), int(crashed), 0, 0,
                                   f"exit {rc}: {stderr.splitlines()[-1] if stderr else ''}"[:200]))
    return results


def run_faults(args: argparse.Namespace) -> int:
    """The whole suite; writes ``args.out`` and prints the table. Exit 0 if every fault recovered."""
    cfg = load_config(args.config)
    only = set(args.only.split(",")) if args.only else None

    def wanted(name: str) -> bool:
        return only is None or name in only

    if cfg.sensors and not cfg.sitl.scip_sensors:
        log.warning("%s serves no sensor through the SCIP bridge: the scanner faults are skipped", cfg.source)
    work = Path(tempfile.mkdtemp(prefix="companion-faults-"))
    results: list[FaultResult] = []
    priorities: dict[str, dict] = {}
    if any(wanted(fault.name) for fault in FLIGHT_FAULTS):
        results += run_flight(cfg, work, args.seed, wanted, priorities)
    if wanted("patrol_nan_storm"):
        results.append(run_patrol_storm(cfg, work, args.seed, priorities))
    results += run_sigterms(cfg, work / "sigterm", args.seed, wanted, priorities)
    results += run_config_faults(work / "configs", wanted)
    report = {"faults": [asdict(r) for r in results], "all_recovered": all(r.recovered for r in results),
              "priority": {"service_nice": SERVICE_NICE, "nice_measured": priorities},
              "work_dir": str(work)}
    Path(args.out).write_text(json.dumps(report, indent=2) + "\n")
    print(format_table(results))
    print(f"all recovered: {report['all_recovered']}; report in {args.out}")
    return 0 if report["all_recovered"] else 1


def format_table(results: list[FaultResult]) -> str:
    """The results as a Markdown table (the README quotes it)."""
    lines = ["| fault | recovered | recovery s | crashes | non-finite sent | failsafes | detail |",
             "|---|---|---|---|---|---|---|"]
    for r in results:
        recovery = "-" if r.recovery_s is None else f"{r.recovery_s:.2f}"
        lines.append(f"| {r.name} | {'yes' if r.recovered else 'NO'} | {recovery} | {r.crashes} | "
                     f"{r.nonfinite_sent} | {r.failsafes} | {r.detail} |")
    return "\n".join(lines)
