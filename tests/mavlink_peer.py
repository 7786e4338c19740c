"""A fake autopilot on loopback UDP for the link tests, and the link under test on an asyncio loop.

The :class:`FakeAutopilot` is a pymavlink ``udpin`` endpoint (sysid 1, compid 1 by default); the
:class:`~companion.mavlink.link.MavlinkLink` under test connects to it with ``udpout`` and speaks
first (its HEARTBEAT), which tells the fake where to answer. Everything is real MAVLink 2 over
127.0.0.1; the fake can also speak as another component, unsigned while the link signs, or with
another key.
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Callable
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402

from companion import clock  # noqa: E402
from companion.config import MavlinkConfig, VehicleConfig  # noqa: E402
from companion.health import Health  # noqa: E402
from companion.mavlink.link import MavlinkLink, mavlink  # noqa: E402
from tests.conftest import free_port  # noqa: E402

COMPANION_COMPID = 197


class FakeAutopilot:
    """The autopilot end of a loopback UDP link (see the module docstring)."""

    def __init__(self, key: bytes | None = None) -> None:
        self.port = free_port()
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{self.port}", source_system=1, source_component=1,
                                               dialect="ardupilotmega")
        if key is not None:
            self.conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=lambda _mav, _msg_id: False)
        self.received: list[Any] = []
        self._t0 = time.monotonic()

    @property
    def url(self) -> str:
        """The link's URL for this autopilot."""
        return f"udpout:127.0.0.1:{self.port}"

    def boot_ms(self, offset_ms: int = 0) -> int:
        """This autopilot's boot clock now (ms), started ``offset_ms`` before the fake was made."""
        return offset_ms + round((time.monotonic() - self._t0) * 1000)

    def pump(self) -> None:
        """Keep what the link sent (BAD_DATA included: refused signatures show as that)."""
        while (msg := self.conn.recv_match(blocking=False)) is not None:
            self.received.append(msg)

    def send(self, msg: mavlink.MAVLink_message, compid: int = 1) -> None:
        """Send ``msg`` as component ``compid`` of system 1 (signed if this fake has a key)."""
        mav = self.conn.mav
        mav.srcComponent = compid
        try:
            mav.send(msg)
        finally:
            mav.srcComponent = 1

    def write(self, frame: bytes) -> None:
        """Send raw bytes (a frame packed elsewhere)."""
        self.conn.write(frame)

    def heartbeat(self, autopilot: int = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                  mav_type: int = mavlink.MAV_TYPE_QUADROTOR, compid: int = 1, custom_mode: int = 0) -> None:
        """A HEARTBEAT as component ``compid`` (an ArduPilot quadrotor by default)."""
        self.send(mavlink.MAVLink_heartbeat_message(mav_type, autopilot, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                                                    custom_mode, mavlink.MAV_STATE_STANDBY, 3), compid)

    def attitude(self, boot_ms: int, roll: float = 0.0) -> None:
        self.send(mavlink.MAVLink_attitude_message(boot_ms, roll, 0.0, 0.0, 0.0, 0.0, 0.0))

    def companion_heard(self) -> bool:
        return any(m.get_type() == "HEARTBEAT" and m.get_srcComponent() == COMPANION_COMPID for m in self.received)

    async def until(self, condition: Callable[[], Any], what: str, timeout_s: float = 5.0) -> None:
        """Pump, and let the link run, until ``condition()`` holds; fail after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert time.monotonic() < deadline, f"timed out after {timeout_s:g} s waiting for {what}"
            self.pump()
            await asyncio.sleep(0.01)

    async def connect(self, link: MavlinkLink) -> None:
        """Wait for the link's HEARTBEAT, then answer with ours until the link is connected."""
        await self.until(self.companion_heard, "the companion's HEARTBEAT")
        self.heartbeat()
        await self.until(lambda: link.connected, "the link to connect")

    def close(self) -> None:
        self.conn.close()


def make_link(url: str, key: bytes | None = None, **mavlink_cfg: Any) -> MavlinkLink:
    """The link under test (companion sysid 1 compid 197, autopilot 1/1) with its own health registry."""
    return MavlinkLink(MavlinkConfig(**mavlink_cfg), VehicleConfig(), url, Health(clock.now), signing_key=key)
