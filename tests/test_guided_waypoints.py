"""A fixed wing's position targets: guided waypoints (MISSION_ITEM_INT, current 2) sent on change, not a stream.

ArduPlane 4.0 ignores SET_POSITION_TARGET_LOCAL_NED in GUIDED and takes MISSION_ITEM_INT with current 2 in
MAV_FRAME_GLOBAL / GLOBAL_RELATIVE_ALT (checked on the 4.0.7 SITL), the built-in plane likewise.
"""

from __future__ import annotations

import asyncio
from collections import defaultdict
from collections.abc import Callable

import numpy as np
import pytest

from companion.frames import ned_from_geodetic
from companion.mavlink import setpoints as setpoints_module
from companion.mavlink.autopilot import Origin
from companion.mavlink.firmware import Firmware
from companion.mavlink.link import mavlink
from companion.mavlink.setpoints import Setpoint, SetpointStream

ORIGIN = Origin(47.3977, 8.5456, 488.0)
TARGET = np.array([600.0, 300.0, -100.0])


class _Link:
    """What SetpointStream uses of MavlinkLink: send, target, subscribe (dispatch by hand)."""

    def __init__(self) -> None:
        self.sent: list[mavlink.MAVLink_message] = []
        self.handlers: dict[str, list[Callable]] = defaultdict(list)

    def send(self, msg: mavlink.MAVLink_message) -> bool:
        self.sent.append(msg)
        return True

    def target(self) -> tuple[int, int]:
        return 1, 1

    def subscribe(self, kind: str, handler: Callable) -> None:
        self.handlers[kind].append(handler)

    def deliver(self, msg: mavlink.MAVLink_message) -> None:
        for handler in self.handlers[msg.get_type()]:
            handler(msg)

    def of(self, kind: str) -> list[mavlink.MAVLink_message]:
        return [m for m in self.sent if m.get_type() == kind]


class _State:
    def __init__(self, vehicle: str) -> None:
        self.firmware = Firmware("ArduPilot", vehicle, (4, 0, 7))
        self.origin = ORIGIN

    def on_mode_change(self, listener: Callable) -> None:
        pass

    def setpoint_z_offset_m(self) -> float:
        return 0.0


def _ack(kind: int = mavlink.MAV_MISSION_ACCEPTED) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_mission_ack_message(255, 0, kind, mavlink.MAV_MISSION_TYPE_MISSION)


def _in_loop(action: Callable[[], None]) -> None:
    """Run ``action`` inside an event loop (the daemon's clock is the loop's)."""
    async def run() -> None:
        action()
    asyncio.run(run())


async def _stream_for(stream: SetpointStream, seconds: float) -> None:
    task = asyncio.create_task(stream.run())
    await asyncio.sleep(seconds)
    task.cancel()


def test_a_plane_target_is_a_guided_waypoint_at_the_same_point_in_metres_above_sea_level() -> None:
    link = _Link()
    stream = SetpointStream(link, _State("plane"), 20.0)  # type: ignore[arg-type]
    _in_loop(lambda: stream.command(Setpoint(position_ned=TARGET)))

    (item,) = link.of("MISSION_ITEM_INT")
    assert (item.current, item.command, item.frame) == (2, mavlink.MAV_CMD_NAV_WAYPOINT, mavlink.MAV_FRAME_GLOBAL)
    back = ned_from_geodetic(item.x * 1e-7, item.y * 1e-7, item.z, (ORIGIN.lat, ORIGIN.lon, ORIGIN.alt))
    np.testing.assert_allclose(back, TARGET, atol=0.02)  # 1e-7 deg: about 1 cm
    assert link.of("SET_POSITION_TARGET_LOCAL_NED") == []


def test_an_acknowledged_plane_target_is_not_repeated_at_the_setpoint_rate_nor_when_commanded_again() -> None:
    link = _Link()
    stream = SetpointStream(link, _State("plane"), 20.0)  # type: ignore[arg-type]

    async def fly() -> None:
        task = asyncio.create_task(stream.run())  # the keepalive task is already waiting
        await asyncio.sleep(0.05)
        stream.command(Setpoint(position_ned=TARGET))
        await asyncio.sleep(0.05)
        link.deliver(_ack())  # answered while the keepalive sleeps towards its retry
        await asyncio.sleep(1.2)
        stream.command(Setpoint(position_ned=TARGET.copy()))  # the same point again (e.g. a hold)
        task.cancel()

    asyncio.run(fly())
    assert len(link.of("MISSION_ITEM_INT")) == 1


def test_an_unanswered_plane_target_is_repeated_until_a_mission_ack(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(setpoints_module, "GUIDED_WAYPOINT_RETRY_S", 0.1)
    link = _Link()
    stream = SetpointStream(link, _State("plane"), 20.0)  # type: ignore[arg-type]

    async def fly() -> int:
        stream.command(Setpoint(position_ned=TARGET))
        await _stream_for(stream, 0.35)
        before_ack = len(link.of("MISSION_ITEM_INT"))
        link.deliver(_ack())
        await _stream_for(stream, 0.35)
        return before_ack

    before_ack = asyncio.run(fly())
    assert before_ack >= 3
    assert len(link.of("MISSION_ITEM_INT")) == before_ack


def test_a_new_plane_target_is_sent_at_once() -> None:
    link = _Link()
    stream = SetpointStream(link, _State("plane"), 20.0)  # type: ignore[arg-type]

    def two_targets() -> None:
        stream.command(Setpoint(position_ned=TARGET))
        link.deliver(_ack())
        stream.command(Setpoint(position_ned=np.zeros(3)))

    _in_loop(two_targets)
    assert len(link.of("MISSION_ITEM_INT")) == 2


def test_a_velocity_target_is_never_sent_to_a_plane() -> None:
    link = _Link()
    stream = SetpointStream(link, _State("plane"), 20.0)  # type: ignore[arg-type]
    _in_loop(lambda: stream.command(Setpoint(velocity_ned=TARGET)))
    assert link.sent == []


def test_a_copter_target_still_streams_at_the_setpoint_rate() -> None:
    link = _Link()
    stream = SetpointStream(link, _State("copter"), 20.0)  # type: ignore[arg-type]

    async def fly() -> None:
        stream.command(Setpoint(position_ned=TARGET))
        await _stream_for(stream, 0.5)

    asyncio.run(fly())
    assert link.of("MISSION_ITEM_INT") == []
    assert len(link.of("SET_POSITION_TARGET_LOCAL_NED")) >= 8
