"""The simulated vehicle process (sitl/vehicle.py) over real MAVLink 2 on loopback UDP.

Each test starts ``python -m sitl.vehicle`` as a subprocess on free ports and talks to it as a
ground station (a pymavlink ``udpin`` the vehicle sends to) and/or as the companion (a pymavlink
``udpout`` to the vehicle's ``udpin`` companion link).
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TICK_S = 0.005
GCS_SYSID, GCS_COMPID = 255, mav.MAV_COMP_ID_MISSIONPLANNER
COMPANION_COMPID = mav.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def connect(url: str, compid: int, sysid: int = GCS_SYSID) -> mavutil.mavfile:
    return mavutil.mavlink_connection(url, source_system=sysid, source_component=compid, dialect="ardupilotmega")


@pytest.fixture
def start_vehicle(tmp_path: Path) -> Iterator[Callable[..., subprocess.Popen]]:
    """Factory starting the vehicle with the given extra arguments; every process is killed after."""
    procs: list[subprocess.Popen] = []

    def start(*args: str) -> subprocess.Popen:
        stderr = open(tmp_path / f"vehicle{len(procs)}.stderr", "w")
        proc = subprocess.Popen([sys.executable, "-m", "sitl.vehicle", *args], cwd=REPO,
                                stdout=subprocess.DEVNULL, stderr=stderr)
        stderr.close()
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
        proc.wait()


class Rig:
    """A real-time vehicle with one GCS link (this test) and a companion link."""

    def __init__(self, start: Callable[..., subprocess.Popen], *args: str) -> None:
        self.gcs_port, self.companion_port = free_udp_port(), free_udp_port()
        self.gcs = connect(f"udpin:127.0.0.1:{self.gcs_port}", GCS_COMPID)
        self.proc = start("--companion", f"udpin:127.0.0.1:{self.companion_port}",
                          "--gcs", f"udpout:127.0.0.1:{self.gcs_port}", *args)
        self.heartbeat = self.recv("HEARTBEAT", timeout=15)

    def recv(self, mtype: str | list[str], timeout: float = 3.0,
             condition: Callable[[mav.MAVLink_message], bool] | None = None) -> mav.MAVLink_message:
        """The next message of a type from the autopilot (1, 1); fails on timeout."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            assert remaining > 0, f"no {mtype} within {timeout} s"
            msg = self.gcs.recv_match(type=mtype, blocking=True, timeout=remaining)
            if msg is not None and (msg.get_srcSystem(), msg.get_srcComponent()) == (1, 1) and (
                    condition is None or condition(msg)):
                return msg

    def command(self, command: int, *params: float) -> mav.MAVLink_message:
        """COMMAND_LONG to the vehicle; returns its COMMAND_ACK."""
        p = list(params) + [0.0] * (7 - len(params))
        self.gcs.mav.command_long_send(1, 1, command, 0, *p)
        return self.recv("COMMAND_ACK", condition=lambda m: m.command == command)

    def companion(self) -> mavutil.mavfile:
        """A companion endpoint that has introduced itself with a HEARTBEAT."""
        comp = connect(f"udpout:127.0.0.1:{self.companion_port}", COMPANION_COMPID, sysid=1)
        comp.mav.heartbeat_send(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        return comp


def count_for(rig: Rig, mtype: str, seconds: float) -> int:
    n, deadline = 0, time.monotonic() + seconds
    while (remaining := deadline - time.monotonic()) > 0:
        msg = rig.gcs.recv_match(type=mtype, blocking=True, timeout=remaining)
        n += msg is not None
    return n


def test_heartbeat_identifies_ardupilot_copter_on_mavlink2(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    hb = rig.heartbeat
    assert hb.get_msgbuf()[0] == 0xFD  # MAVLink 2 framing
    assert hb.type == mav.MAV_TYPE_QUADROTOR
    assert hb.autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.custom_mode == 0  # STABILIZE
    assert hb.system_status == mav.MAV_STATE_STANDBY


def test_streams_are_off_by_default_except_heartbeat(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    assert count_for(rig, "ATTITUDE", 0.6) == 0


def test_set_message_interval_starts_attitude_at_the_asked_rate_and_minus_one_stops_it(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    ack = rig.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, 50_000)
    assert ack.result == mav.MAV_RESULT_ACCEPTED
    assert 14 <= count_for(rig, "ATTITUDE", 1.0) <= 26  # 20 Hz
    assert rig.command(mav.MAV_CMD_GET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE).result \
        == mav.MAV_RESULT_ACCEPTED
    assert rig.recv("MESSAGE_INTERVAL").interval_us == 50_000
    ack = rig.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, -1)
    assert ack.result == mav.MAV_RESULT_ACCEPTED
    count_for(rig, "ATTITUDE", 0.1)  # in flight before the stop
    assert count_for(rig, "ATTITUDE", 0.5) == 0


def test_set_message_interval_zero_means_default_4hz(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    rig.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_SYS_STATUS, 0)
    assert 3 <= count_for(rig, "SYS_STATUS", 1.0) <= 6


def test_request_data_stream_enables_a_legacy_group(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    rig.gcs.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_POSITION, 10, 1)
    rig.gcs.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_EXTRA1, 10, 1)
    assert 7 <= count_for(rig, "ATTITUDE", 1.0) <= 13
    rig.gcs.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_EXTRA1, 0, 0)
    count_for(rig, "ATTITUDE", 0.1)
    assert count_for(rig, "ATTITUDE", 0.4) == 0


def test_request_message_autopilot_version_reports_ardupilot_4_5_7(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    ack = rig.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert ack.result == mav.MAV_RESULT_ACCEPTED
    version = rig.recv("AUTOPILOT_VERSION")
    assert version.flight_sw_version == 0x040507FF
    for cap in (mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2, mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED,
                mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT, mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT,
                mav.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET):
        assert version.capabilities & cap


def test_unknown_command_is_acked_unsupported(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    assert rig.command(mav.MAV_CMD_DO_FLIGHTTERMINATION, 1).result == mav.MAV_RESULT_UNSUPPORTED


def test_set_gps_global_origin_is_answered_with_gps_global_origin(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    comp = rig.companion()
    time.sleep(0.1)
    comp.mav.set_gps_global_origin_send(1, 12_966_000, 1_037_764_000, 10_000, 0)
    origin = comp.recv_match(type="GPS_GLOBAL_ORIGIN", blocking=True, timeout=3)
    assert origin is not None
    assert (origin.latitude, origin.longitude, origin.altitude) == (12_966_000, 1_037_764_000, 10_000)


def test_command_int_set_home_is_announced_with_home_position(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    rig.gcs.mav.set_gps_global_origin_send(1, 12_966_000, 1_037_764_000, 10_000, 0)
    rig.recv("GPS_GLOBAL_ORIGIN")
    rig.gcs.mav.command_int_send(1, 1, mav.MAV_FRAME_GLOBAL_INT, mav.MAV_CMD_DO_SET_HOME, 0, 0,
                                 0, 0, 0, 0, 12_966_090, 1_037_764_000, 12.0)
    ack = rig.recv("COMMAND_ACK", condition=lambda m: m.command == mav.MAV_CMD_DO_SET_HOME)
    assert ack.result == mav.MAV_RESULT_ACCEPTED
    home = rig.recv("HOME_POSITION")
    assert (home.latitude, home.longitude, home.altitude) == (12_966_090, 1_037_764_000, 12_000)
    assert (home.x, home.y, home.z) == pytest.approx((1.0019, 0.0, -2.0), abs=1e-3)  # NED from the origin


def test_arming_is_refused_without_origin(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    assert rig.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4).result \
        == mav.MAV_RESULT_ACCEPTED
    ack = rig.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert ack.result == mav.MAV_RESULT_FAILED
    text = rig.recv("STATUSTEXT")
    assert "PreArm" in text.text or "Arm" in text.text
    assert not rig.recv("HEARTBEAT").base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED


def test_guided_mode_shows_in_heartbeat_and_bad_mode_fails_with_statustext(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    rig.gcs.mav.set_mode_send(1, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)
    assert rig.recv("COMMAND_ACK").result == mav.MAV_RESULT_ACCEPTED
    hb = rig.recv("HEARTBEAT", condition=lambda m: m.custom_mode == 4)
    assert hb.base_mode & mav.MAV_MODE_FLAG_GUIDED_ENABLED
    ack = rig.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 99)
    assert ack.result == mav.MAV_RESULT_FAILED
    assert "Mode change" in rig.recv("STATUSTEXT").text


def test_timesync_request_is_answered_with_own_time(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    rig.gcs.mav.timesync_send(0, 123_456_789)
    reply = rig.recv("TIMESYNC", condition=lambda m: m.ts1 == 123_456_789)
    assert reply.tc1 > 0


def test_companion_heartbeat_and_statustext_are_forwarded_to_the_gcs(start_vehicle) -> None:
    rig = Rig(start_vehicle)
    comp = rig.companion()
    comp.mav.statustext_send(mav.MAV_SEVERITY_INFO, b"companion ready")
    deadline = time.monotonic() + 3
    seen = set()
    while time.monotonic() < deadline and seen != {"HEARTBEAT", "STATUSTEXT"}:
        msg = rig.gcs.recv_match(type=["HEARTBEAT", "STATUSTEXT"], blocking=True, timeout=0.5)
        if msg is not None and msg.get_srcComponent() == COMPANION_COMPID:
            seen.add(msg.get_type())
    assert seen == {"HEARTBEAT", "STATUSTEXT"}


def test_sim_state_carries_ground_truth_at_the_home_anchor(start_vehicle) -> None:
    rig = Rig(start_vehicle, "--home", "1.2966,103.7764,10.0", "--start", "2,3,90")
    rig.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_SIM_STATE, 20_000)
    sim = rig.recv("SIM_STATE")
    assert sim.lat_int == pytest.approx(1.2966e7 + math.degrees(2 / 6_378_137.0) * 1e7, abs=2)
    assert sim.lat == pytest.approx(sim.lat_int * 1e-7, abs=1e-6)
    assert sim.yaw == pytest.approx(math.pi / 2, abs=0.05)
    assert sim.zacc == pytest.approx(-9.8, abs=0.5)  # specific force at rest, body FRD
    assert math.hypot(sim.q1, math.hypot(sim.q2, math.hypot(sim.q3, sim.q4))) == pytest.approx(1.0, abs=1e-5)


def test_nan_and_stale_vision_are_counted_in_the_log(start_vehicle, tmp_path: Path) -> None:
    log = tmp_path / "log.json"
    rig = Rig(start_vehicle, "--seconds", "1.5", "--log", str(log))
    comp = rig.companion()
    now_us = int(time.monotonic() * 1e6)
    comp.mav.vision_position_estimate_send(now_us, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, [math.nan] * 21, 0)
    comp.mav.vision_position_estimate_send(now_us, math.nan, 0.0, 0.0, 0.0, 0.0, 0.0, [math.nan] * 21, 0)
    comp.mav.vision_position_estimate_send(now_us - 2_000_000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, [math.nan] * 21, 0)
    assert rig.proc.wait(timeout=15) == 0
    doc = json.loads(log.read_text())
    assert doc["rejected"]["nonfinite"] == 1
    assert doc["rejected"]["stale_or_future"] == 1
    assert len(doc["vision_position"]["usec"]) == 3
    assert doc["vision_position"]["pos_ned"][1][0] is None
    assert doc["clock"]["monotonic_at_sim_zero"] is not None
    assert doc["sim_seconds"] == pytest.approx(1.5)
    assert len(doc["truth"]["t"]) == 75  # 50 Hz
    assert doc["modes"][0][1:] == ["STABILIZE", False]


def test_sigterm_writes_the_log_and_exits_zero(start_vehicle, tmp_path: Path) -> None:
    log = tmp_path / "log.json"
    rig = Rig(start_vehicle, "--log", str(log))
    rig.proc.send_signal(signal.SIGTERM)
    assert rig.proc.wait(timeout=10) == 0
    doc = json.loads(log.read_text())
    assert doc["schema"] == 1 and doc["lockstep"] is False and doc["sim_seconds"] > 0


# ---------------------------------------------------------------- lockstep


class LockstepCompanion:
    """Plays the companion daemon in lockstep: answers the vehicle's TIMESYNC ticks."""

    def __init__(self, start: Callable[..., subprocess.Popen], *args: str) -> None:
        port = free_udp_port()
        self.proc = start("--companion", f"udpin:127.0.0.1:{port}", "--lockstep", *args)
        self.conn = connect(f"udpout:127.0.0.1:{port}", COMPANION_COMPID, sysid=1)
        self.sim_state: mav.MAVLink_message | None = None

    def hello(self) -> None:
        """HEARTBEAT until the vehicle's first tick request (t = 0) arrives; do not answer it yet."""
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            self.conn.mav.heartbeat_send(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            if self.next_tick(timeout=0.3) is not None:
                return
        raise AssertionError("no lockstep TIMESYNC from the vehicle")

    def next_tick(self, timeout: float = 5.0) -> int | None:
        """ts1 (ns) of the next tick request, None after ``timeout`` s or once the vehicle exited.

        Remembers the SIM_STATE seen on the way.
        """
        deadline = time.monotonic() + timeout
        while (remaining := deadline - time.monotonic()) > 0:
            msg = self.conn.recv_match(type=["TIMESYNC", "SIM_STATE"], blocking=True, timeout=min(remaining, 0.2))
            if msg is None:
                if self.proc.poll() is not None:
                    return None
                continue
            if msg.get_type() == "SIM_STATE":
                self.sim_state = msg
            elif msg.tc1 == 0:
                return msg.ts1
        return None

    def answer(self, ts1: int) -> None:
        self.conn.mav.timesync_send(max(ts1, 1), ts1)


def test_lockstep_sim_time_advances_only_when_ticks_are_answered(start_vehicle, tmp_path: Path) -> None:
    log = tmp_path / "log.json"
    comp = LockstepCompanion(start_vehicle, "--seconds", "0.5", "--log", str(log))
    comp.hello()
    comp.answer(0)
    stamps = []
    for _ in range(5):
        ts1 = comp.next_tick()
        assert ts1 is not None
        stamps.append(ts1)
        comp.answer(ts1)
    assert stamps == [round(k * TICK_S * 1e9) for k in range(1, 6)]
    ts1 = comp.next_tick()
    assert comp.next_tick(timeout=0.5) is None  # unanswered: the vehicle waits
    comp.answer(ts1)
    while (ts1 := comp.next_tick(timeout=5)) is not None:
        comp.answer(ts1)
    assert comp.proc.wait(timeout=10) == 0
    doc = json.loads(log.read_text())
    assert doc["lockstep"] is True and doc["clock"]["monotonic_at_sim_zero"] is None
    assert doc["sim_seconds"] == pytest.approx(0.5)


def fly_lockstep(start: Callable[..., subprocess.Popen], log: Path, seconds: float) -> dict:
    """A deterministic companion: origin, SIM_STATE-based vision at 40 Hz, GUIDED, arm, takeoff to 2 m."""
    comp = LockstepCompanion(start, "--seconds", str(seconds), "--log", str(log), "--seed", "7")
    comp.hello()
    comp.conn.mav.set_gps_global_origin_send(1, 12_966_000, 1_037_764_000, 10_000, 0)
    comp.conn.mav.command_long_send(1, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                    mav.MAVLINK_MSG_ID_SIM_STATE, 25_000, 0, 0, 0, 0, 0)
    comp.answer(0)
    tick = 0
    while (ts1 := comp.next_tick(timeout=10)) is not None:
        tick += 1
        sim = comp.sim_state
        if sim is not None and tick % 5 == 0:
            north = (sim.lat_int * 1e-7 - 1.2966) * math.pi / 180 * 6_378_137.0
            east = (sim.lon_int * 1e-7 - 103.7764) * math.pi / 180 * 6_378_137.0 * math.cos(math.radians(1.2966))
            comp.conn.mav.vision_position_estimate_send(
                ts1 // 1000, north, east, 10.0 - sim.alt, sim.roll, sim.pitch, sim.yaw, [math.nan] * 21, 0)
            comp.conn.mav.vision_speed_estimate_send(ts1 // 1000, sim.vn, sim.ve, sim.vd, [math.nan] * 9, 0)
        if tick == 400:
            comp.conn.mav.command_long_send(1, 1, mav.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
            comp.conn.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
            comp.conn.mav.command_long_send(1, 1, mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 2.0)
        comp.answer(ts1)
    assert comp.proc.wait(timeout=10) == 0
    return json.loads(log.read_text())


def test_lockstep_same_seed_gives_identical_logs_and_the_copter_flies(start_vehicle, tmp_path: Path) -> None:
    first = fly_lockstep(start_vehicle, tmp_path / "a.json", 6.0)
    second_path = tmp_path / "b.json"
    fly_lockstep(start_vehicle, second_path, 6.0)
    assert (tmp_path / "a.json").read_bytes() == second_path.read_bytes()
    assert first["origin"]["set_at"] == 0.0
    assert first["external_nav"]["first_in_use_at"] is not None
    assert [c[1:] for c in first["commands"][-3:]] == [
        [mav.MAV_CMD_DO_SET_MODE, 0], [mav.MAV_CMD_COMPONENT_ARM_DISARM, 0], [mav.MAV_CMD_NAV_TAKEOFF, 0]]
    assert first["truth"]["pos_ned"][-1][2] < -1.0  # climbing towards 2 m
    assert first["rejected"] == {"nonfinite": 0, "stale_or_future": 0, "gated": first["rejected"]["gated"]}


# ---------------------------------------------------------------- mavsdk


def test_mavsdk_discovers_the_vehicle_as_ardupilot_and_reads_its_flight_mode(start_vehicle) -> None:
    from mavsdk.asyncio import Autopilot, ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync

    port = free_udp_port()

    async def discover() -> tuple[Autopilot, FlightMode]:
        async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as sdk:
            await sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
            start_vehicle("--companion", f"udpin:127.0.0.1:{free_udp_port()}", "--gcs", f"udpout:127.0.0.1:{port}")
            system = await sdk.first_autopilot(timeout_s=15.0)
            assert system is not None
            telemetry = TelemetryAsync(system)
            mode = FlightMode.UNKNOWN
            async for mode in telemetry.subscribe_flight_mode():
                if mode != FlightMode.UNKNOWN:
                    break
            return await system.autopilot_type(), mode

    autopilot, mode = asyncio.run(asyncio.wait_for(discover(), timeout=30))
    assert autopilot == Autopilot.ARDUPILOT
    assert mode == FlightMode.STABILIZED
