"""The fixed wing behind the vehicle process (``python -m sitl.vehicle --vehicle plane``) over real
MAVLink 2 on 127.0.0.1: an ArduPlane HEARTBEAT the companion reads as a plane (and asks for modes
by ArduPlane's numbers), and a lockstep flight (arm, take off, fly to a GUIDED target) driven by a
stand-in companion."""

from __future__ import annotations

import asyncio
import json
import math
import subprocess
from collections.abc import Callable
from pathlib import Path

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion import clock
from companion.config import MavlinkConfig, VehicleConfig
from companion.health import Health
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.commands import Commander
from companion.mavlink.firmware import firmware_from_heartbeat
from companion.mavlink.link import MavlinkLink
from tests.test_sitl_vehicle import LockstepCompanion, Rig, start_vehicle  # noqa: F401 (fixture)

PLANE_GUIDED = 15
TARGET_NED = (250.0, 150.0, -40.0)


def test_the_heartbeat_is_an_arduplane_and_the_companion_sees_a_plane(start_vehicle) -> None:
    rig = Rig(start_vehicle, "--vehicle", "plane")
    hb = rig.heartbeat
    assert hb.type == mav.MAV_TYPE_FIXED_WING and hb.autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert mavutil.mode_string_v10(hb) == "MANUAL"
    firmware = firmware_from_heartbeat("ArduPilot", hb.type)
    assert firmware.vehicle == "plane"
    assert firmware.ardupilot_mode_number("GUIDED") == PLANE_GUIDED
    assert not firmware.setpoint_z_relative_to_home
    ack = rig.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 12)  # LOITER needs a position
    assert ack.result == mav.MAV_RESULT_FAILED
    ack = rig.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 2)  # STABILIZE
    assert ack.result == mav.MAV_RESULT_ACCEPTED
    hb = rig.recv("HEARTBEAT", condition=lambda m: m.custom_mode == 2)
    assert mavutil.mode_string_v10(hb) == "STABILIZE"


def fly(start: Callable[..., subprocess.Popen], log: Path, seconds: float) -> dict:
    """Lockstep: origin, GUIDED, arm, take off to 30 m, then a GUIDED target; the flight log."""
    comp = LockstepCompanion(start, "--vehicle", "plane", "--position-source", "gps", "--wind", "0,3,0",
                             "--gust", "0.5", "--seconds", str(seconds), "--log", str(log), "--seed", "3")
    comp.hello()
    comp.conn.mav.set_gps_global_origin_send(1, 12_966_000, 1_037_764_000, 10_000, 0)
    comp.answer(0)
    tick = 0
    while (ts1 := comp.next_tick(timeout=10)) is not None:
        tick += 1
        if tick == 400:  # 2 s: GPS in use
            comp.conn.mav.command_long_send(1, 1, mav.MAV_CMD_DO_SET_MODE, 0, 1, PLANE_GUIDED, 0, 0, 0, 0, 0)
            comp.conn.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
            comp.conn.mav.command_long_send(1, 1, mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 30.0)
        if tick == 4000:  # 20 s: climbed out
            comp.conn.mav.set_position_target_local_ned_send(
                ts1 // 1_000_000, 1, 1, mav.MAV_FRAME_LOCAL_NED, 3576, *TARGET_NED, 0, 0, 0, 0, 0, 0, 0, 0)
        comp.answer(ts1)
    assert comp.proc.wait(timeout=10) == 0
    return json.loads(log.read_text())


def test_the_plane_arms_takes_off_and_circles_a_guided_target_over_mavlink(start_vehicle, tmp_path: Path) -> None:
    doc = fly(start_vehicle, tmp_path / "log.json", 70.0)
    assert [c[1:] for c in doc["commands"][:3]] == [
        [mav.MAV_CMD_DO_SET_MODE, 0], [mav.MAV_CMD_COMPONENT_ARM_DISARM, 0], [mav.MAV_CMD_NAV_TAKEOFF, 0]]
    assert "Takeoff complete" in [text for *_, text in doc["statustext"]]
    assert len(doc["setpoints"]["pos"]) == 1
    assert ["GUIDED", True] in [m[1:] for m in doc["modes"]]
    truth = doc["truth"]
    last = [(t, p) for t, p in zip(truth["t"], truth["pos_ned"]) if t >= 55.0]
    distances = [math.hypot(p[0] - TARGET_NED[0], p[1] - TARGET_NED[1]) for _, p in last]
    assert 30.0 < min(distances) and max(distances) < 50.0  # on the 40 m loiter circle
    assert all(abs(p[2] - TARGET_NED[2]) < 4.0 for _, p in last)


def test_the_companion_asks_an_arduplane_for_guided_by_arduplane_s_number() -> None:
    async def main() -> tuple[tuple[int, int], tuple[int, int], str | None]:
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now))
        state = AutopilotState(link)
        link.autopilot = "ArduPilot"
        unknown = state.custom_mode_for("GUIDED")  # before any HEARTBEAT: ArduCopter's table, as always
        heartbeat = mav.MAVLink_heartbeat_message(mav.MAV_TYPE_FIXED_WING, mav.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                  mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 12, mav.MAV_STATE_ACTIVE, 3)
        codec = mav.MAVLink(None, 1, 1)
        link._dispatch(codec.parse_char(heartbeat.pack(codec)))
        return unknown, state.custom_mode_for("GUIDED"), state.mode
    unknown, plane, mode = asyncio.run(main())
    assert unknown[1] == 4
    assert plane == (mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PLANE_GUIDED)
    assert mode == "LOITER"


def test_landing_a_plane_means_rtl_since_arduplane_has_no_land_mode() -> None:
    async def main() -> tuple[str, str, int]:
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now))
        state = AutopilotState(link)
        commander = Commander(link, state, MavlinkConfig())
        link.autopilot = "ArduPilot"
        before = commander.landing_mode  # no HEARTBEAT yet: a copter's LAND
        heartbeat = mav.MAVLink_heartbeat_message(mav.MAV_TYPE_FIXED_WING, mav.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                  mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 15, mav.MAV_STATE_ACTIVE, 3)
        codec = mav.MAVLink(None, 1, 1)
        link._dispatch(codec.parse_char(heartbeat.pack(codec)))
        return before, commander.landing_mode, state.custom_mode_for(commander.landing_mode)[1]
    before, plane, number = asyncio.run(main())
    assert (before, plane, number) == ("LAND", "RTL", 11)  # ArduPlane's RTL
