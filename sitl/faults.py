"""`companion experiment faults --out R.json`: the fault suite, against the SITL, in real time.

Everything runs on loopback with the built-in vehicle and the daemon's *real* Hokuyo driver
(the SCIP bridge, config/sitl-real-driver.yaml by default). The daemon's MAVLink link goes
through a :class:`sitl.fault_proxy.FaultProxy`, which breaks the link, forges messages as the
autopilot, and counts every non-finite value the daemon sends the autopilot (measured outside
the daemon). The bridge breaks the scanners on command (``--faults-from-stdin``); with no
``sitl.scip_sensors`` the scanner faults cannot be made: they are left out (a warning says so).

Runs, in order (``--only`` picks faults by name):

- **flight**: mission ``faults`` (take off, hold, land). Once airborne and healthy, one fault at
  a time. First those a flight survives (the mission must still be running after them): NaN /
  infinity storms in every float the daemon consumes, spoofed heartbeats, another component
  claiming to be the autopilot, forged messages (acknowledgements nobody asked for, time going
  backwards), line noise on the MAVLink link, scanner corrupted frames / garbage frames / slow
  scans, a zenoh flood, a CPU-bound process on each core. Then those after which the mission need
  not fly on (on a vehicle whose only position source is the lidar they end the flight): the
  scanners unplugged 2 s, the autopilot stopped 2 s, the link lost for ``link_timeout_s`` + 1.5 s
  (the autopilot's EKF failsafe lands), the autopilot stopped 10 s, the autopilot killed and
  restarted. Between two faults the daemon must stay healthy :data:`SETTLE_S` in a row (within
  :data:`HEALTHY_WITHIN_S`); if it does not, the fault before it is marked not recovered (its
  recovery did not last) and its detail says why.
- **patrol with a NaN storm**: mission ``patrol`` with a 3 s NaN / infinity storm of ATTITUDE,
  HIGHRES_IMU and LOCAL_POSITION_NED in the middle; recovered = the mission completes with no
  failsafe and the daemon is healthy again within :data:`HEALTHY_WITHIN_S` of the storm's end
  (``recovery_s``: how long that took).
- **SIGTERM** in each state: before any autopilot answers, against a TCP endpoint that never
  accepts, in flight (the hold step reached), with the autopilot stopped (the daemon connected,
  then saw the link lost).
- **bad config files**: ``companion check-config`` on a device that never ends, a FIFO, an
  empty file, a binary file, a config whose mission is missing.

Per fault: ``recovered``; ``recovery_s`` (from the moment the fault clears until the daemon is
healthy again: estimates reaching the autopilot, every health component that was ok before
the fault ok again, link up; for SIGTERM: until the process exited; for config files: until
``check-config`` returned, Python's start-up included, hence its own budget
:data:`CONFIG_BUDGET_S`); ``crashes`` (supervised task restarts, or the daemon dying);
``nonfinite_sent`` (messages to the autopilot with a NaN or infinity, counted by the proxy);
``failsafes`` (as the flight report counts them: the mission's stops, holds and landings and
the autopilot's own failsafe mode changes; not its slowdowns on a degraded estimate);
``detail`` (what was seen).

A fault is recovered only if it is seen to have reached the daemon (:attr:`FlightFault.observed`:
a counter of the daemon's telemetry that must grow, the link seen down during the fault); if not,
its detail starts with "not observed". The scanner-slow, zenoh-flood and CPU faults have no such
counter. The CPU fault also requires the estimates never to stop longer than 0.2 s, but only if
the daemon ran at the service's priority (:data:`sitl.rig.SERVICE_NICE`); the report's
``priority`` says what every process actually got.

SIGTERM ends the suite cleanly (vehicle, bridge, daemon and CPU hogs stopped) and the report is
written all the same, ``"completed": false``. A run that fails (the vehicle never reaches its
hold step, say) records its faults as not recovered, with the error, and the suite goes on.

The processes of a flight run: sitl/rig.py (priorities included).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import logging
import math
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import yaml

from companion.config import Config, load_config
from companion.mavlink.link import mavlink
from companion.telemetry.keys import KEY_PREFIX
from sitl.harness import free_udp_port
from sitl.rig import (SERVICE_NICE, STOP_BUDGET_S, TELEMETRY_PERIOD_S, Rig, sigterm_exits, start_at_service_priority,
                      stop_process, wait_until)

log = logging.getLogger("companion.faults")

HEALTHY_WITHIN_S = 20.0  # a fault not recovered this long after it cleared is not recovered
SETTLE_S = 2.0  # healthy this long in a row between two faults
STORM_HZ = 200.0  # forged messages per second of each type in a storm
AIRBORNE_TIMEOUT_S = 90.0
PATROL_STORM_AT = 0.75  # mission progress: the patrol's fly step (index 4 of 6) is half done
CONFIG_BUDGET_S = 5.0  # check-config on a bad file: the error within this, Python's start-up included
LINK_LOSS_MARGIN_S = 1.5  # the link is blocked link_timeout_s + this: surely declared lost, whatever the heartbeat phase
AUTOPILOT_SILENT_S = 1.0  # the autopilot stopped 2 s: the daemon received nothing at least this long
NONFINITE = (math.nan, math.inf, -math.inf)

SIGTERM_FAULTS = ("sigterm_before_autopilot", "sigterm_never_accepting_tcp_peer", "sigterm_in_flight",
                  "sigterm_autopilot_stopped")
CONFIG_FAULTS = ("config_dev_zero", "config_fifo", "config_empty", "config_binary", "config_missing_mission")


@dataclass
class FaultResult:
    name: str
    recovered: bool
    recovery_s: float | None
    crashes: int
    nonfinite_sent: int
    failsafes: int
    detail: str = ""


def not_recovered(names: list[str], why: str) -> list[FaultResult]:
    """Results for faults that could not be made or measured (``why`` says so)."""
    return [FaultResult(name, False, None, 0, 0, 0, why) for name in names]


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


def attitude_imu_position_storm(value: float, boot_ms: int) -> list[mavlink.MAVLink_message]:
    """The patrol storm: ATTITUDE, HIGHRES_IMU and LOCAL_POSITION_NED, every float ``value``."""
    return nonfinite_storm_messages(value, boot_ms)[:3]


def spoof_messages(boot_ms: int) -> list[mavlink.MAVLink_message]:
    """Heartbeats claiming the autopilot is something else (sent from the autopilot's ids)."""
    return [mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                              mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4 << 16,
                                              mavlink.MAV_STATE_ACTIVE, 3)]


def forged_messages(boot_ms: int) -> list[mavlink.MAVLink_message]:
    """Acknowledgements nobody asked for (LAND accepted, arming denied) and time going backwards:
    an ATTITUDE stamped 10 minutes before the autopilot's boot time, a SYSTEM_TIME with boot time
    5 ms."""
    return [mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_RESULT_ACCEPTED),
            mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_DENIED),
            mavlink.MAVLink_attitude_message(max(boot_ms - 600_000, 0), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
            mavlink.MAVLink_system_time_message(0, 5)]


def other_component_heartbeat(boot_ms: int) -> list[mavlink.MAVLink_message]:
    """An autopilot heartbeat from a component that is not the autopilot (sent as compid 2)."""
    return [mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                              mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 9, mavlink.MAV_STATE_ACTIVE, 3)]


# -- making faults -------------------------------------------------------------------------------

def storm(rig: Rig, seconds: float, make: Callable[[int], list[mavlink.MAVLink_message]],
          src: tuple[int, int] | None = None) -> None:
    """Send ``make(boot_ms)`` at STORM_HZ for ``seconds``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rig.proxy.inject(make(rig.boot_ms()), src)
        time.sleep(1.0 / STORM_HZ)


def cycling(make: Callable[[float, int], list[mavlink.MAVLink_message]]
            ) -> Callable[[int], list[mavlink.MAVLink_message]]:
    """``make(value, boot_ms)`` with value NaN, +inf, -inf in turn, one per call (for :func:`storm`)."""
    values = itertools.cycle(NONFINITE)
    return lambda boot_ms: make(next(values), boot_ms)


def line_noise(rig: Rig, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rig.proxy.inject_bytes(os.urandom(280))
        rig.proxy.inject_bytes(b"\xfd\x09\x00\x00\x07\x01\x01\x00\x00\x00" + os.urandom(20))
        time.sleep(1.0 / STORM_HZ)


def zenoh_flood(rig: Rig, seconds: float) -> None:
    """A zenoh peer publishing as fast as it can, on the daemon's keys and another."""
    from companion.telemetry.session import open_session

    session = open_session("peer", [], rig.cfg.telemetry.listen, False, False)
    try:
        keys = [f"{KEY_PREFIX}/{rig.cfg.vehicle.sysid}/pose", f"{KEY_PREFIX}/{rig.cfg.vehicle.sysid}/command",
                "flood/a"]
        publishers = [session.declare_publisher(k) for k in keys]
        payload = os.urandom(4096)
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            for p in publishers:
                p.put(payload)
    finally:
        session.close()


# A CPU-bound process that also ends when its parent does (SIGKILLed, say): it is reparented.
HOG_PROGRAM = "import os\np = os.getppid()\nwhile os.getppid() == p:\n    pass\n"


@contextlib.contextmanager
def cpu_hogs(n: int) -> Iterator[None]:
    """``n`` CPU-bound processes (this process's priority) while inside."""
    hogs = [subprocess.Popen([sys.executable, "-c", HOG_PROGRAM]) for _ in range(n)]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def cpu_hog(seconds: float) -> None:
    """A CPU-bound process on each core for ``seconds``."""
    with cpu_hogs(os.cpu_count() or 2):
        time.sleep(seconds)


def stop_vehicle(rig: Rig, seconds: float) -> None:
    assert rig.vehicle is not None
    rig.vehicle.send_signal(signal.SIGSTOP)
    try:
        time.sleep(seconds)
    finally:
        rig.vehicle.send_signal(signal.SIGCONT)


def link_loss(rig: Rig) -> str:
    """Drop everything both ways for ``link_timeout_s`` + :data:`LINK_LOSS_MARGIN_S`."""
    seconds = rig.cfg.mavlink.link_timeout_s + LINK_LOSS_MARGIN_S
    rig.proxy.block(seconds)
    time.sleep(seconds)
    return f"link blocked {seconds:g} s (link_timeout_s {rig.cfg.mavlink.link_timeout_s:g} + {LINK_LOSS_MARGIN_S:g})"


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


def _autopilot_ids(rig: Rig) -> tuple[int, int]:
    return rig.cfg.vehicle.autopilot_sysid, rig.cfg.vehicle.autopilot_compid


# -- evidence that a fault reached the daemon ----------------------------------------------------

# The daemon's telemetry ({stream: payload}, the listener's snapshot) before a fault and after its
# recovery; the one after also holds "during": what :class:`DuringFault` saw while it was made.
Snapshot = dict[str, dict]
Evidence = Callable[[Snapshot, Snapshot], str | None]


def _count(value: object) -> int:
    """A counter of the telemetry: a number, or a dict of them (per type) summed."""
    if isinstance(value, dict):
        return sum(_count(v) for v in value.values())
    return int(value) if isinstance(value, (int, float)) and math.isfinite(value) else 0


def link_counter_grew(*keys: str) -> Evidence:
    """Observed if any of the link stream's counters ``keys`` grew."""
    def rule(before: Snapshot, after: Snapshot) -> str | None:
        if any(_count(after.get("link", {}).get(k)) > _count(before.get("link", {}).get(k)) for k in keys):
            return None
        return f"not observed: link {' / '.join(keys)} did not grow"
    return rule


def driver_counter_grew(key: str) -> Evidence:
    """Observed if the drivers' ``key`` (system stream, all drivers summed) grew."""
    def total(snapshot: Snapshot) -> int:
        return sum(_count(d.get(key)) for d in snapshot.get("system", {}).get("drivers", {}).values())

    def rule(before: Snapshot, after: Snapshot) -> str | None:
        return None if total(after) > total(before) else f"not observed: the drivers' {key} did not grow"
    return rule


def link_seen_down(before: Snapshot, after: Snapshot) -> str | None:
    if after.get("during", {}).get("link_down"):
        return None
    return "not observed: the link was never reported down during the fault"


def autopilot_seen_silent(before: Snapshot, after: Snapshot) -> str | None:
    silent = after.get("during", {}).get("rx_stall_s", 0.0)
    if silent >= AUTOPILOT_SILENT_S:
        return None
    return f"not observed: the daemon's received messages stopped at most {silent:.1f} s (< {AUTOPILOT_SILENT_S:g})"


class DuringFault:
    """While a fault is made (``with``): samples the daemon's link telemetry in a thread; whether
    the link was reported down, and the longest time ``messages_rx`` stood still."""

    def __init__(self, rig: Rig, period_s: float = 0.05) -> None:
        self.rig = rig
        self.period_s = period_s
        self.link_down = False
        self.rx_stall_s = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="during-fault", daemon=True)

    def __enter__(self) -> DuringFault:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2.0)

    def _run(self) -> None:
        rx, changed = None, time.monotonic()
        while not self._stop.wait(self.period_s):
            link, now = self.rig.telemetry("link"), time.monotonic()
            if not link:
                continue  # not fresh: says nothing
            self.link_down |= link.get("connected") is False
            if link.get("messages_rx") != rx:
                rx, changed = link.get("messages_rx"), now
            self.rx_stall_s = max(self.rx_stall_s, now - changed)

    def summary(self) -> dict:
        return {"link_down": self.link_down, "rx_stall_s": round(self.rx_stall_s, 2)}


# -- measuring -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class FlightFault:
    """One fault of the flight run: ``inject(rig)`` returns when the fault clears (a note for the
    detail, or None)."""

    name: str
    inject: Callable[[Rig], str | None]
    observed: Evidence | None = None  # (before, after) -> None if the fault reached the daemon, else why not
    max_gap_s: float | None = None  # recovered only if estimates never stopped longer than this (at SERVICE_NICE)
    survivable: bool = True  # a flight survives it: the mission flies on, the autopilot is the same one
    reboots: int = 0  # autopilot reboots the daemon must count (the killed and restarted autopilot)
    scanners: bool = False  # made through the SCIP bridge (needs sitl.scip_sensors)


# The flight run, in order: the faults a flight survives, then those that end a real flight whose
# only position source is the lidar: both scanners gone, the autopilot hung or gone, the link
# lost (the autopilot's EKF failsafe lands; the companion must recover all the same).
FLIGHT_FAULTS = (
    FlightFault("nan_inf_storm", lambda rig: storm(rig, 3.0, cycling(nonfinite_storm_messages)),
                link_counter_grew("values_rejected")),
    FlightFault("spoofed_heartbeats", lambda rig: storm(rig, 3.0, spoof_messages),
                link_counter_grew("identity_changed")),
    FlightFault("other_component_claims_autopilot", lambda rig: storm(
        rig, 3.0, other_component_heartbeat, (_autopilot_ids(rig)[0], _autopilot_ids(rig)[1] + 1)),
        link_counter_grew("identity_impostors")),
    FlightFault("forged_acks_and_time_backwards", lambda rig: storm(rig, 3.0, forged_messages),
                link_counter_grew("time_anomalies", "acks_ignored")),
    FlightFault("mavlink_line_noise", lambda rig: line_noise(rig, 3.0), link_counter_grew("parse_errors")),
    FlightFault("scanner_corrupted_frames", lambda rig: scanner_fault(rig, "corrupt {name} 3", 3.0, every_s=0.5),
                driver_counter_grew("corrupt_frames"), scanners=True),
    FlightFault("scanner_garbage_frames", lambda rig: scanner_fault(rig, "garbage {name} 3", 3.0, every_s=0.5),
                driver_counter_grew("corrupt_frames"), scanners=True),
    FlightFault("scanner_slow", lambda rig: scanner_fault(rig, "delay {name} 15 0.15", 3.0), scanners=True),
    FlightFault("zenoh_flood", lambda rig: zenoh_flood(rig, 3.0)),
    FlightFault("cpu_hog", lambda rig: cpu_hog(5.0), max_gap_s=0.2),
    FlightFault("scanner_unplug", lambda rig: scanner_fault(rig, "unplug {name} 2.0", 2.0),
                driver_counter_grew("reconnects"), survivable=False, scanners=True),
    FlightFault("autopilot_stopped_2s", lambda rig: stop_vehicle(rig, 2.0), autopilot_seen_silent, survivable=False),
    FlightFault("link_loss", link_loss, link_seen_down, survivable=False),
    FlightFault("autopilot_stopped_10s", lambda rig: stop_vehicle(rig, 10.0), link_seen_down, survivable=False),
    FlightFault("autopilot_killed_restarted", lambda rig: rig.restart_vehicle(),
                link_counter_grew("autopilot_reboots"), survivable=False, reboots=1),
)

FAULT_NAMES = (*(f.name for f in FLIGHT_FAULTS), "patrol_nan_storm", *SIGTERM_FAULTS, *CONFIG_FAULTS)


def side_effects(fault: FlightFault, link_before: dict, after: Snapshot) -> list[str]:
    """What the fault changed that it must not have: the mission (a survivable fault), the
    detected autopilot, the count of autopilot reboots."""
    link, mission = after.get("link", {}), after.get("mission", {})
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


def wait_healthy(rig: Rig, expected: set[str], timeout_s: float,
                 also: Callable[[], str | None] = lambda: None) -> tuple[float | None, str | None]:
    """Wait until the daemon is healthy (:meth:`Rig.unhealthy` with ``expected``, and ``also``):
    (when it was, None) or (None, why not) after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    why: str | None = None
    while time.monotonic() < deadline:
        why = rig.unhealthy(expected) or also()
        if why is None:
            return time.monotonic(), None
        time.sleep(0.05)
    return None, why


def settle(rig: Rig, expected: set[str], seconds: float = SETTLE_S, within_s: float = HEALTHY_WITHIN_S) -> str | None:
    """Wait until the daemon has been healthy ``seconds`` in a row: None, or why not within ``within_s``."""
    deadline = time.monotonic() + within_s
    since: float | None = None
    why: str | None = None
    while time.monotonic() < deadline:
        why = rig.unhealthy(expected)
        now = time.monotonic()
        if why is not None:
            since = None
        elif since is None:
            since = now
        elif now - since >= seconds:
            return None
        time.sleep(0.05)
    return why or f"healthy less than {seconds:g} s in a row"


def measure(rig: Rig, fault: FlightFault, expected: set[str], timeout_s: float = HEALTHY_WITHIN_S) -> FaultResult:
    """Make one fault and measure the recovery (see the module docstring)."""
    assert rig.listener is not None
    before, seen_before = rig.counters(), rig.listener.snapshot()
    link_before = seen_before.get("link", {})
    daemon = rig.daemon
    started = time.monotonic()
    log.info("fault %s: injecting", fault.name)
    with DuringFault(rig) as during:
        note = fault.inject(rig)
    cleared = time.monotonic()
    healthy_at, why = wait_healthy(rig, expected, timeout_s, lambda: reboot_pending(rig, fault, link_before))
    after = rig.counters()
    crashes = after.restarts - before.restarts + (1 if daemon is not None and daemon.poll() is not None else 0)
    time.sleep(2 * TELEMETRY_PERIOD_S)  # the link and mission state after the recovery
    seen_after = {**rig.listener.snapshot(), "during": during.summary()}
    unseen = fault.observed(seen_before, seen_after) if fault.observed is not None else None
    gap = rig.proxy.longest_estimate_gap(started, cleared)
    wrong = side_effects(fault, link_before, seen_after)
    gap_checked = fault.max_gap_s is not None and rig.at_service_priority()
    gap_ok = not gap_checked or gap <= (fault.max_gap_s or 0.0)
    recovered = healthy_at is not None and not wrong and unseen is None and gap_ok
    parts = [unseen, note, f"longest estimate gap during the fault {gap * 1000:.0f} ms", *wrong]
    if fault.max_gap_s is not None:
        limit = f"{fault.max_gap_s * 1000:.0f} ms"
        parts.append(f"over the {limit} limit" if not gap_ok else f"within the {limit} limit" if gap_checked else
                     f"the {limit} limit not applied: the daemon ran at nice {rig.priorities.get('daemon')}, "
                     f"not {SERVICE_NICE} (not permitted to raise it)")
    if healthy_at is None:
        parts.append(f"still unhealthy {timeout_s:g} s after: {why}")
    result = FaultResult(fault.name, recovered, None if healthy_at is None else round(healthy_at - cleared, 2),
                         crashes, after.nonfinite_sent - before.nonfinite_sent, after.failsafes - before.failsafes,
                         "; ".join(p for p in parts if p))
    log.info("fault %s: %s", fault.name, result)
    return result


# -- the runs ------------------------------------------------------------------------------------

def run_flight(cfg: Config, work: Path, seed: int, faults: list[FlightFault], priorities: dict[str, dict],
               results: list[FaultResult]) -> None:
    """The flight run's ``faults``, in order, their results appended to ``results`` as they come.
    After each, the daemon must stay healthy SETTLE_S in a row within HEALTHY_WITHIN_S, else that
    fault is marked not recovered (its recovery did not last). If the run fails, the faults not
    measured yet are recorded not recovered, with the error."""
    rig = Rig(cfg, "faults", work / "flight", seed)
    try:
        rig.start()
        if not wait_until(lambda: rig.telemetry("mission").get("step_kind") == "hold", AIRBORNE_TIMEOUT_S):
            raise RuntimeError(f"the vehicle did not reach the hold step: {rig.listener.snapshot().get('mission')}")
        if not wait_until(lambda: rig.unhealthy(rig.ok_components()) is None and rig.ok_components(), 10.0):
            raise RuntimeError(f"not healthy before the faults: {rig.unhealthy(rig.ok_components())}")
        expected = rig.ok_components()
        log.info("healthy components before the faults: %s", ", ".join(sorted(expected)))
        for fault in faults:
            result = measure(rig, fault, expected)
            results.append(result)
            relapse = settle(rig, expected)
            if relapse is not None:
                result.recovered = False
                result.detail += f"; not healthy {SETTLE_S:g} s in a row within {HEALTHY_WITHIN_S:g} s after: {relapse}"
    except Exception as exc:
        log.exception("the flight run failed")
        done = {r.name for r in results}
        results += not_recovered([f.name for f in faults if f.name not in done], f"flight run failed: {exc}")
    finally:
        rig.close()
        priorities["flight"] = dict(rig.priorities)


def run_patrol_storm(cfg: Config, work: Path, seed: int, priorities: dict[str, dict]) -> FaultResult:
    """Patrol with a 3 s NaN / infinity storm of ATTITUDE, HIGHRES_IMU and LOCAL_POSITION_NED in the
    middle: recovered = mission completed, no failsafe, healthy again (every component ok before the
    storm) within HEALTHY_WITHIN_S of its end, and the daemon rejected values."""
    rig = Rig(cfg, "patrol", work / "patrol", seed)
    try:
        rig.start()
        assert rig.listener is not None
        if not wait_until(lambda: rig.telemetry("mission").get("step_kind") == "fly", AIRBORNE_TIMEOUT_S):
            raise RuntimeError(f"the patrol did not start flying: {rig.listener.snapshot().get('mission')}")
        if not wait_until(lambda: (rig.telemetry("mission").get("tracking_error_m") is not None
                                   and rig.telemetry("mission").get("progress", 0.0) >= PATROL_STORM_AT), 120.0):
            raise RuntimeError(f"the patrol did not reach {PATROL_STORM_AT:.0%} of its mission: "
                               f"{rig.listener.snapshot().get('mission')}")
        expected = rig.ok_components()
        before, seen_before = rig.counters(), rig.listener.snapshot()
        started = time.monotonic()
        storm(rig, 3.0, cycling(attitude_imu_position_storm))
        cleared = time.monotonic()
        healthy_at, why = wait_healthy(rig, expected, HEALTHY_WITHIN_S)
        ended = wait_until(lambda: rig.listener.snapshot().get("mission", {}).get("state")
                           in ("completed", "failed", "aborted"), 180.0, 0.2)
        seen_after = rig.listener.snapshot()
        mission = seen_after.get("mission", {})
        after = rig.counters()
        crashes = after.restarts - before.restarts + (1 if rig.daemon is not None and rig.daemon.poll() is not None
                                                      else 0)
        failsafes = after.failsafes - before.failsafes
        completed = ended and mission.get("state") == "completed"
        unseen = link_counter_grew("values_rejected")(seen_before, seen_after)
        gap = rig.proxy.longest_estimate_gap(started, cleared)
        parts = [unseen, f"mission {mission.get('state')}" + (f" {mission['reason']}" if mission.get("reason") else ""),
                 f"longest estimate gap in the storm {gap * 1000:.0f} ms",
                 None if healthy_at is not None else f"still unhealthy {HEALTHY_WITHIN_S:g} s after: {why}"]
        return FaultResult("patrol_nan_storm", completed and failsafes == 0 and healthy_at is not None and unseen is None,
                           None if healthy_at is None else round(healthy_at - cleared, 2), crashes,
                           after.nonfinite_sent - before.nonfinite_sent, failsafes, "; ".join(p for p in parts if p))
    except Exception as exc:
        log.exception("the patrol run failed")
        return not_recovered(["patrol_nan_storm"], f"patrol run failed: {exc}")[0]
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


@contextlib.contextmanager
def daemon_process(config: Path) -> Iterator[tuple[subprocess.Popen, int | None]]:
    """While inside, the daemon on ``config`` at the service's priority where permitted: (process,
    its nice value); killed on the way out if still running (the suite interrupted)."""
    proc, nice = start_at_service_priority([sys.executable, "-m", "companion.cli", "run", "-c", str(config)],
                                           stderr=subprocess.DEVNULL)
    try:
        yield proc, nice
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def run_sigterms(cfg: Config, work: Path, seed: int, wanted: Callable[[str], bool], priorities: dict[str, dict],
                 results: list[FaultResult]) -> None:
    """The SIGTERM faults (see the module docstring), their results appended to ``results``."""
    work.mkdir(parents=True, exist_ok=True)
    if wanted("sigterm_before_autopilot"):
        with daemon_process(minimal_config(work, f"udpout:127.0.0.1:{free_udp_port()}")) as (proc, nice):
            priorities["sigterm_before_autopilot"] = {"daemon": nice}
            time.sleep(3.0)
            results.append(sigterm_result("sigterm_before_autopilot", proc))
    if wanted("sigterm_never_accepting_tcp_peer"):
        with never_accepting_listener() as port, \
                daemon_process(minimal_config(work, f"tcp:127.0.0.1:{port}")) as (proc, nice):
            priorities["sigterm_never_accepting_tcp_peer"] = {"daemon": nice}
            time.sleep(3.0)
            results.append(sigterm_result("sigterm_never_accepting_tcp_peer", proc))
    in_flight = [name for name in ("sigterm_in_flight", "sigterm_autopilot_stopped") if wanted(name)]
    if in_flight:
        rig = Rig(cfg, "hover", work / "sigterm", seed)
        try:
            rig.start()
            assert rig.daemon is not None and rig.vehicle is not None
            if wanted("sigterm_in_flight"):
                if wait_until(lambda: rig.telemetry("mission").get("step_kind") == "hold", AIRBORNE_TIMEOUT_S):
                    results.append(sigterm_result("sigterm_in_flight", rig.daemon, "(mission on_daemon_stop: LAND)"))
                else:
                    results += not_recovered(["sigterm_in_flight"], "not observed: the vehicle never reached the "
                                             f"hold step: {rig.listener.snapshot().get('mission')}")
            if wanted("sigterm_autopilot_stopped"):
                results.append(sigterm_autopilot_stopped(rig))
        except Exception as exc:
            log.exception("the SIGTERM run failed")
            done = {r.name for r in results}
            results += not_recovered([n for n in in_flight if n not in done], f"SIGTERM run failed: {exc}")
        finally:
            rig.close()
            priorities["sigterm"] = dict(rig.priorities)


def sigterm_autopilot_stopped(rig: Rig) -> FaultResult:
    """SIGTERM the daemon once it has connected to the autopilot, then seen it stop (link lost)."""
    assert rig.daemon is not None and rig.vehicle is not None
    name = "sigterm_autopilot_stopped"
    if rig.daemon.poll() is not None:
        rig.start_daemon()
        time.sleep(2 * (TELEMETRY_PERIOD_S + 0.5))  # the old daemon's telemetry is stale by then
    if not wait_until(lambda: rig.telemetry("link").get("connected") is True, 30.0):
        return not_recovered([name], "not observed: the daemon never connected to the autopilot")[0]
    timeout_s = rig.cfg.mavlink.link_timeout_s + LINK_LOSS_MARGIN_S
    rig.vehicle.send_signal(signal.SIGSTOP)
    try:
        if not wait_until(lambda: rig.telemetry("link").get("connected") is False, timeout_s):
            return not_recovered([name], f"not observed: the link not reported lost {timeout_s:g} s after "
                                         "the autopilot stopped")[0]
        return sigterm_result(name, rig.daemon, "(link lost)")
    finally:
        rig.vehicle.send_signal(signal.SIGCONT)


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


def bad_config_files(work: Path) -> dict[str, tuple[Path, bool]]:
    """Config files a user could hand to the daemon by mistake or malice, by fault name: (the file,
    whether its error has a line: not for a device or a FIFO, which are refused unread)."""
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
    return {"config_dev_zero": (Path("/dev/zero"), False), "config_fifo": (fifo, False),
            "config_empty": (empty, True), "config_binary": (binary, True), "config_missing_mission": (missing, True)}


def run_config_faults(work: Path, wanted: Callable[[str], bool], results: list[FaultResult]) -> None:
    """``companion check-config`` on each bad file: recovered = exit 2 with ``companion: FILE:LINE: ...``
    (``FILE: ...`` for a device or FIFO) on stderr and no traceback, within CONFIG_BUDGET_S
    (Python's start-up included; ``recovery_s`` is that time); the results appended to ``results``."""
    for name, (path, has_line) in bad_config_files(work).items():
        if not wanted(name):
            continue
        started = time.monotonic()
        try:
            proc = subprocess.run([sys.executable, "-m", "companion.cli", "check-config", str(path)],
                                  capture_output=True, text=True, timeout=2 * CONFIG_BUDGET_S)
            rc, stderr = proc.returncode, proc.stderr.strip()
        except subprocess.TimeoutExpired:
            rc, stderr = None, f"did not return within {2 * CONFIG_BUDGET_S:g} s"
        took = time.monotonic() - started
        crashed = "Traceback" in stderr or (rc is not None and rc < 0)
        line = r":\d+" if has_line else ""
        message = re.match(rf"companion: {re.escape(str(path))}{line}: \S", stderr)
        ok = rc == 2 and message is not None and not crashed and took <= CONFIG_BUDGET_S
        text = f"exit {rc}: {stderr.splitlines()[-1] if stderr else ''}"[:200]
        if took > CONFIG_BUDGET_S:
            text += f"; over the {CONFIG_BUDGET_S:g} s budget"
        results.append(FaultResult(name, ok, round(took, 2), int(crashed), 0, 0, text))


def run_faults(args: argparse.Namespace) -> int:
    """The whole suite; writes ``args.out`` (always, partial if interrupted: ``"completed": false``)
    and prints the table. Exit 0 if it completed and every fault recovered."""
    cfg = load_config(args.config)
    only = set(args.only.split(",")) if args.only else None
    if only is not None and only - set(FAULT_NAMES):
        log.warning("--only: no fault named %s (faults: %s)", ", ".join(sorted(only - set(FAULT_NAMES))),
                    ", ".join(FAULT_NAMES))

    def wanted(name: str) -> bool:
        return only is None or name in only

    faults = [fault for fault in FLIGHT_FAULTS if wanted(fault.name)]
    if not cfg.sitl.scip_sensors:
        left_out = [fault.name for fault in faults if fault.scanners]
        faults = [fault for fault in faults if not fault.scanners]
        if left_out:
            log.warning("%s serves no sensor through the SCIP bridge (sitl.scip_sensors): the scanner faults "
                        "are not run and left out of the results (%s)", cfg.source, ", ".join(left_out))
    work = Path(tempfile.mkdtemp(prefix="companion-faults-"))
    results: list[FaultResult] = []
    priorities: dict[str, dict] = {}
    completed = False
    try:
        with sigterm_exits():
            if faults:
                run_flight(cfg, work, args.seed, faults, priorities, results)
            if wanted("patrol_nan_storm"):
                results.append(run_patrol_storm(cfg, work, args.seed, priorities))
            run_sigterms(cfg, work / "sigterm", args.seed, wanted, priorities, results)
            run_config_faults(work / "configs", wanted, results)
            completed = True
    finally:
        if not completed:
            log.warning("the suite was interrupted: the report in %s holds the faults measured so far", args.out)
        report = {"faults": [asdict(r) for r in results],
                  "all_recovered": completed and all(r.recovered for r in results),
                  "completed": completed,
                  "priority": {"service_nice": SERVICE_NICE, "nice_measured": priorities},
                  "work_dir": str(work)}
        Path(args.out).write_text(json.dumps(report, indent=2) + "\n")
    print(format_table(results))
    print(f"all recovered: {report['all_recovered']}; {priority_summary(priorities)}; report in {args.out}")
    return 0 if report["all_recovered"] else 1


def priority_summary(priorities: dict[str, dict]) -> str:
    """What the processes ran at, in a few words."""
    values = {nice for run in priorities.values() for nice in run.values()}
    if not values:
        return "no daemon started"
    if values == {SERVICE_NICE}:
        return f"every process at nice {SERVICE_NICE}"
    return f"not every process at nice {SERVICE_NICE}: {json.dumps(priorities)}"


def format_table(results: list[FaultResult]) -> str:
    """The results as a Markdown table (the README quotes it)."""
    lines = ["| fault | recovered | recovery s | crashes | non-finite sent | failsafes | detail |",
             "|---|---|---|---|---|---|---|"]
    for r in results:
        recovery = "-" if r.recovery_s is None else f"{r.recovery_s:.2f}"
        lines.append(f"| {r.name} | {'yes' if r.recovered else 'NO'} | {recovery} | {r.crashes} | "
                     f"{r.nonfinite_sent} | {r.failsafes} | {r.detail} |")
    return "\n".join(lines)
