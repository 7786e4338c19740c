"""Interoperability: mavsdk, an independent MAVLink implementation, flies the `companion sitl` vehicle.

``companion sitl`` runs as a subprocess in REAL TIME (mavsdk runs on the wall clock, so no
lockstep), from a copy of config/sitl.yaml with free loopback ports and no mission: the daemon
still runs (heartbeat, EKF origin, its streams) but does not fly. mavsdk 4 (MAVSDK's C++ core
through its native Python binding) connects as a ground station on the vehicle's GCS link and
does what a MAVSDK app does with ArduPilot Copter: discover the autopilot, read telemetry, wait
for a position, arm, take off to 1 m in GUIDED, hold, land, see the disarm.

Like ArduPilot with its default SRx_* stream rates (0), the vehicle sends only HEARTBEAT on a
GCS link until asked; a MAVSDK app against ArduPilot calls ``telemetry.set_rate_*()`` (which
sends MAV_CMD_SET_MESSAGE_INTERVAL) for what it reads, and so does this test. mavsdk maps
ArduCopter's modes onto its FlightMode enum: STABILIZE -> STABILIZED, GUIDED -> OFFBOARD,
LAND -> LAND.
"""

from __future__ import annotations

import asyncio
import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import REPO, free_port
from tests.sitl_helpers import write_sitl_config

SITL_SECONDS = 90  # --seconds: the vehicle's own end of the run, far beyond the flight
TAKEOFF_ALT_M = 1.0
ALT_TOLERANCE_M = 0.2
HOLD_S = 4.0
STOP_GRACE_S = 15.0  # SIGTERM -> exit (the harness gives each child 5 s), then SIGKILL
SITL_ORIGIN = (1.2966, 103.7764, 10.0)  # the daemon's origin in config/sitl.yaml (deg, deg, m AMSL)


@dataclass
class SitlRun:
    proc: subprocess.Popen
    gcs_port: int
    output: Path
    children: dict[int, bytes] = field(default_factory=dict)  # pid -> its command line

    def text(self) -> str:
        return self.output.read_text(errors="replace") if self.output.exists() else ""


def home_at(home: Any, place: tuple[float, float, float], tol_deg: float = 1e-6) -> Any:
    """``home`` (mavsdk Position) if it lies at ``place`` (lat deg, lon deg, alt m AMSL), else None."""
    if home is None:
        return None
    got = (home.latitude_deg, home.longitude_deg, home.absolute_altitude_m)
    return home if all(abs(a - b) <= tol_deg for a, b in zip(got, place)) else None


def cmdline_of(pid: int) -> bytes | None:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return None


def children_of(pid: int) -> dict[int, bytes]:
    """Direct children of a live process with their command lines (from /proc; empty once it is gone)."""
    found: dict[int, bytes] = {}
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            for child in (task / "children").read_text().split():
                cmdline = cmdline_of(int(child))
                if cmdline:
                    found[int(child)] = cmdline
    except OSError:
        pass
    return found


def note_children(run: SitlRun, timeout_s: float = 10.0) -> None:
    """Remember the harness's two children (vehicle, daemon) as soon as they exist, for stop_sitl."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and run.proc.poll() is None:
        run.children.update(children_of(run.proc.pid))
        if len(run.children) >= 2:
            return
        time.sleep(0.05)


def stop_sitl(run: SitlRun) -> int:
    """SIGTERM the harness, SIGKILL it after STOP_GRACE_S; then end any child it left behind."""
    proc = run.proc
    run.children.update(children_of(proc.pid))
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            proc.kill()
    rc = proc.wait()
    for pid, cmdline in run.children.items():  # the vehicle and the daemon, if the harness left them
        if cmdline_of(pid) == cmdline:  # still that process, not a reused pid
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    return rc


@pytest.fixture
def companion_sitl(tmp_path: Path) -> Iterator[SitlRun]:
    """`companion sitl` (real time, no mission) with a GCS link to a free port; always stopped after."""
    gcs_port = free_port()
    cfg = write_sitl_config(tmp_path / "sitl.yaml", vehicle_port=free_port(), gcs_port=gcs_port,
                            zenoh_port=free_port(socket.SOCK_STREAM), mission=None)
    output = tmp_path / "sitl.out"
    with open(output, "w") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "companion.cli", "sitl", "-c", str(cfg), "--seconds", str(SITL_SECONDS)],
            cwd=REPO, stdout=out, stderr=subprocess.STDOUT)
    run = SitlRun(proc, gcs_port, output)
    try:
        note_children(run)
        yield run
    finally:
        stop_sitl(run)


# ---------------------------------------------------------------- mavsdk side


class Recorder:
    """Every telemetry update mavsdk delivers, in background tasks, with wall-clock stamps."""

    def __init__(self, telemetry: Any) -> None:
        self.t = telemetry
        self.latest: dict[str, Any] = {}
        self.history: dict[str, list[tuple[float, Any]]] = {}
        self.tasks: list[asyncio.Task] = []

    def start(self) -> None:
        for name in ("flight_mode", "armed", "attitude_euler", "position", "position_velocity_ned", "health",
                     "home", "landed_state", "status_text"):
            self.tasks.append(asyncio.create_task(self._collect(name, getattr(self.t, f"subscribe_{name}")())))

    async def _collect(self, name: str, updates: AsyncIterator[Any]) -> None:
        async for value in updates:
            self.latest[name] = value
            self.history.setdefault(name, []).append((time.monotonic(), value))

    async def stop(self) -> None:
        for task in self.tasks:
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)

    async def wait_for(self, condition: Callable[[], Any], timeout_s: float, what: str) -> Any:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                value = condition()
            except KeyError:  # nothing received yet for a stream the condition reads
                value = None
            if value:
                return value
            if time.monotonic() > deadline:
                seen = {k: v for k, v in self.latest.items() if k != "status_text"}
                raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}; last telemetry: {seen}")
            await asyncio.sleep(0.05)

    def altitude_m(self) -> tuple[float, float]:
        """(relative altitude from GLOBAL_POSITION_INT, height from LOCAL_POSITION_NED), metres."""
        return self.latest["position"].relative_altitude_m, -self.latest["position_velocity_ned"].position.down_m

    def texts(self) -> list[str]:
        return [s.text for _, s in self.history.get("status_text", [])]


async def fly_with_mavsdk(gcs_port: int, log: list[str]) -> dict[str, Any]:
    """The flight, with mavsdk's log in ``log``; returns what the assertions need (waits assert themselves)."""
    from mavsdk import log_subscribe, log_unsubscribe

    def on_log(level: Any, message: str, file: str | None, line: int) -> bool:
        log.append(f"{level.name} {message}")
        return True  # keep mavsdk's own console output out of the test output

    log_subscribe(on_log)
    try:
        return await _fly(gcs_port)
    finally:
        log_unsubscribe()  # after the Mavsdk instance is gone: nothing logs any more


async def _fly(gcs_port: int) -> dict[str, Any]:
    from mavsdk.asyncio import Autopilot, ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.telemetry import FlightMode, LandedState, TelemetryAsync

    out: dict[str, Any] = {}
    async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{gcs_port}")
        system = await sdk.first_autopilot(timeout_s=30.0)
        assert system is not None, "mavsdk discovered no autopilot within 30 s"
        out["autopilot"] = await system.autopilot_type()
        assert out["autopilot"] == Autopilot.ARDUPILOT

        telemetry, action = TelemetryAsync(system), ActionAsync(system)
        rec = Recorder(telemetry)
        rec.start()
        try:
            # ArduPilot streams nothing but HEARTBEAT until asked (SRx_* = 0): ask, as a MAVSDK app does.
            for name, rate_hz in (("attitude_euler", 10.0), ("position", 10.0), ("position_velocity_ned", 10.0),
                                  ("landed_state", 4.0), ("home", 1.0)):
                await asyncio.wait_for(getattr(telemetry, f"set_rate_{name}")(rate_hz), 10)

            await rec.wait_for(lambda: rec.latest["flight_mode"] != FlightMode.UNKNOWN, 15, "a flight mode")
            out["initial_mode"] = rec.latest["flight_mode"]
            out["attitude"] = await rec.wait_for(lambda: rec.latest["attitude_euler"], 15, "ATTITUDE")
            # The daemon sets the EKF origin (and home); the autopilot then has a local position and home.
            await rec.wait_for(lambda: rec.latest["health"].is_local_position_ok
                               and rec.latest["health"].is_home_position_ok, 30, "local position and home ok")
            out["ground_position"] = await rec.wait_for(lambda: rec.latest["position"], 10, "GLOBAL_POSITION_INT")
            # Like ArduPilot, the vehicle sets home where it stands once it has a position; the
            # daemon then moves home to its origin (after the EKF has a horizontal position).
            out["home"] = await rec.wait_for(lambda: home_at(rec.latest["home"], SITL_ORIGIN), 10,
                                             "HOME_POSITION at the daemon's origin")
            out["ground_pvn"] = await rec.wait_for(lambda: rec.latest["position_velocity_ned"], 10,
                                                   "LOCAL_POSITION_NED")
            assert not rec.latest["armed"]

            await asyncio.wait_for(action.set_takeoff_altitude(TAKEOFF_ALT_M), 10)
            await asyncio.wait_for(action.arm(), 15)
            await rec.wait_for(lambda: rec.latest["armed"], 10, "the armed state in HEARTBEAT")
            await asyncio.wait_for(action.takeoff(), 15)  # ArduPilot path: GUIDED, then MAV_CMD_NAV_TAKEOFF
            out["takeoff_mode"] = await rec.wait_for(
                lambda: rec.latest["flight_mode"] if rec.latest["flight_mode"] == FlightMode.OFFBOARD else None,
                10, "GUIDED (mavsdk: OFFBOARD)")

            def at_altitude() -> bool:
                return all(abs(a - TAKEOFF_ALT_M) <= ALT_TOLERANCE_M for a in rec.altitude_m())

            await rec.wait_for(at_altitude, 20, f"{TAKEOFF_ALT_M} m above home")
            await rec.wait_for(lambda: rec.latest["landed_state"] == LandedState.IN_AIR, 5, "landed state IN_AIR")
            hold_start = time.monotonic()
            samples: list[tuple[float, float]] = []
            while time.monotonic() - hold_start < HOLD_S:
                samples.append(rec.altitude_m())
                await asyncio.sleep(0.1)
            out["hold_samples"] = samples
            out["hold_modes"] = {m for t, m in rec.history["flight_mode"] if t >= hold_start}

            await asyncio.wait_for(action.land(), 15)
            out["land_mode"] = await rec.wait_for(
                lambda: rec.latest["flight_mode"] if rec.latest["flight_mode"] == FlightMode.LAND else None,
                10, "LAND")
            await rec.wait_for(lambda: not rec.latest["armed"], 40, "disarm after touchdown")
            out["landed_state"] = await rec.wait_for(
                lambda: rec.latest["landed_state"] if rec.latest["landed_state"] == LandedState.ON_GROUND else None,
                10, "landed state ON_GROUND")
            out["final_altitude"] = rec.altitude_m()
            out["texts"] = rec.texts()
        finally:
            await rec.stop()
    return out


def test_mavsdk_flies_the_sitl_vehicle_like_ardupilot_copter(companion_sitl: SitlRun) -> None:
    from mavsdk.asyncio.plugins.telemetry import FlightMode

    mavsdk_log: list[str] = []
    try:
        result = asyncio.run(asyncio.wait_for(fly_with_mavsdk(companion_sitl.gcs_port, mavsdk_log), 150))
    except BaseException:
        print("---- companion sitl output ----\n" + companion_sitl.text())
        print("---- mavsdk log ----\n" + "\n".join(mavsdk_log[-200:]))
        raise
    assert companion_sitl.proc.poll() is None, "companion sitl ended during the flight"
    children = children_of(companion_sitl.proc.pid)
    assert len(children) == 2  # the vehicle and the daemon
    assert stop_sitl(companion_sitl) == 0  # SIGTERM: the harness stops both and exits cleanly
    assert all(cmdline_of(pid) != cmdline for pid, cmdline in children.items())
    assert "companion sitl: stopped" in companion_sitl.text()

    assert result["initial_mode"] == FlightMode.STABILIZED
    att = result["attitude"]
    assert abs(att.roll_deg) < 5 and abs(att.pitch_deg) < 5  # standing level on the floor
    ground = result["ground_position"]
    assert ground.latitude_deg == pytest.approx(1.2966, abs=1e-3)
    assert ground.longitude_deg == pytest.approx(103.7764, abs=1e-3)
    assert abs(ground.relative_altitude_m) < 0.3
    home = result["home"]
    assert (home.latitude_deg, home.longitude_deg, home.absolute_altitude_m) == pytest.approx(SITL_ORIGIN, abs=1e-6)
    assert math.isfinite(result["ground_pvn"].position.north_m)

    assert result["takeoff_mode"] == FlightMode.OFFBOARD  # ArduCopter GUIDED in mavsdk's enum
    samples = result["hold_samples"]
    assert len(samples) >= 20
    worst = max(abs(a - TAKEOFF_ALT_M) for pair in samples for a in pair)
    assert worst <= ALT_TOLERANCE_M, f"altitude left {TAKEOFF_ALT_M} +/- {ALT_TOLERANCE_M} m while holding: {samples}"
    assert result["hold_modes"] <= {FlightMode.OFFBOARD}

    assert result["land_mode"] == FlightMode.LAND
    assert all(abs(a) < 0.3 for a in result["final_altitude"])
    assert "Arming motors" in result["texts"] and "Disarming motors" in result["texts"]
