"""The EKF origin, then home at the same point, but only once the autopilot's EKF has a horizontal
position: ArduPilot 4.0 SITL halts ("Should not be called on invalid location") when home is set
while its EKF has an altitude and no position. Against a small scripted autopilot on loopback."""

from __future__ import annotations

import asyncio
import os
import threading
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from companion import clock  # noqa: E402
from companion.config import MavlinkConfig, OriginConfig, VehicleConfig  # noqa: E402
from companion.health import Health  # noqa: E402
from companion.mavlink.autopilot import AutopilotState  # noqa: E402
from companion.mavlink.commands import Commander  # noqa: E402
from companion.mavlink.link import MavlinkLink, mavlink  # noqa: E402
from companion.mavlink.origin import OriginSetter  # noqa: E402
from tests.conftest import free_port  # noqa: E402

ORIGIN = OriginConfig(lat=1.2966, lon=103.7764, alt=10.0)
NO_POSITION, POSITION = 0x01 | 0x20, 0x01 | 0x08 | 0x10 | 0x20  # EKF flags: attitude, height (+ horizontal)


class ScriptedAutopilot(threading.Thread):
    """Heartbeats and EKF flags; keeps the origin and home it is sent and reports them on request."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1)
        self.has_position = threading.Event()
        self.silent = threading.Event()  # says nothing (a hung or rebooting autopilot)
        self.reports_flags = threading.Event()  # EKF_STATUS_REPORT streams (not yet, after a reboot)
        self.reports_flags.set()
        self.stop = threading.Event()
        self.origin: tuple[int, int, int] | None = None
        self.home: tuple[int, int, int] | None = None
        self.home_sent_at: list[float] = []  # when SET_HOME_POSITION arrived, and the flags then
        self.home_sent_with_position: list[bool] = []

    def run(self) -> None:
        last = 0.0
        while not self.stop.is_set():
            if time.monotonic() - last > 0.1 and not self.silent.is_set():
                last = time.monotonic()
                self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                                             mavlink.MAV_STATE_STANDBY)
                if self.reports_flags.is_set():
                    flags = POSITION if self.has_position.is_set() else NO_POSITION
                    self.conn.mav.ekf_status_report_send(flags, 0, 0, 0, 0, 0)
            msg = self.conn.recv_match(blocking=True, timeout=0.02)
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "SET_GPS_GLOBAL_ORIGIN":
                self.origin = (msg.latitude, msg.longitude, msg.altitude)
            elif kind == "SET_HOME_POSITION":
                self.home = (msg.latitude, msg.longitude, msg.altitude)
                self.home_sent_at.append(time.monotonic())
                self.home_sent_with_position.append(self.has_position.is_set())
            elif kind == "COMMAND_LONG":
                self.conn.mav.command_ack_send(msg.command, mavlink.MAV_RESULT_ACCEPTED)
                wanted = int(msg.param1)
                if wanted == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN and self.origin is not None:
                    self.conn.mav.gps_global_origin_send(*self.origin)
                if wanted == mavlink.MAVLINK_MSG_ID_HOME_POSITION and self.home is not None:
                    self.conn.mav.home_position_send(*self.home, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0)


async def until(condition, seconds: float) -> bool:  # noqa: ANN001
    for _ in range(int(seconds / 0.1)):
        if condition():
            return True
        await asyncio.sleep(0.1)
    return condition()


def test_home_follows_the_origin_only_once_the_ekf_has_a_horizontal_position() -> None:
    port = free_port()
    autopilot = ScriptedAutopilot(port)
    autopilot.start()

    async def main() -> OriginSetter:
        cfg = MavlinkConfig(command_timeout_s=0.2, link_timeout_s=0.5)
        link = MavlinkLink(cfg, VehicleConfig(), f"udpout:127.0.0.1:{port}", Health(clock.now))
        state = AutopilotState(link)
        origin = OriginSetter(link, state, Commander(link, state, cfg), ORIGIN, Health(clock.now))
        tasks = [asyncio.ensure_future(link.run()), asyncio.ensure_future(origin.run())]
        try:
            assert await until(lambda: origin.confirmed, 4.0)  # the origin is confirmed without a position
            assert not origin.ready
            await asyncio.sleep(2.0)  # still no position: no home
            assert autopilot.home_sent_at == []
            autopilot.has_position.set()
            assert await until(lambda: origin.ready, 4.0)

            # the autopilot goes quiet and comes back without a position and without its EKF stream
            # yet (a reboot): the position it reported before does not count, home waits for a new report
            autopilot.silent.set()
            autopilot.has_position.clear()
            autopilot.reports_flags.clear()
            assert await until(lambda: not link.connected, 2.0)
            sent_before = len(autopilot.home_sent_at)
            back = clock.now()
            autopilot.silent.clear()
            # confirmed again on the new connection (the flag of the old one is still set until then)
            assert await until(lambda: origin.confirmed and origin.confirmed_at > back, 4.0)
            await asyncio.sleep(1.5)
            assert len(autopilot.home_sent_at) == sent_before and not origin.ready
            autopilot.has_position.set()
            autopilot.reports_flags.set()
            assert await until(lambda: origin.ready, 4.0)
            return origin
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    try:
        origin = asyncio.run(main())
    finally:
        autopilot.stop.set()
        autopilot.join(2)
    assert origin.ready and origin.home_confirmed
    assert autopilot.home_sent_at and all(autopilot.home_sent_with_position)
    assert autopilot.home == autopilot.origin == (12966000, 1037764000, 10000)
