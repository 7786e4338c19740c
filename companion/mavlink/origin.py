"""EKF origin: make the autopilot use the configured origin, and know when it does.

Without GPS the autopilot's EKF estimates no position until an origin is set. Every second,
until GPS_GLOBAL_ORIGIN confirms, the companion sends SET_GPS_GLOBAL_ORIGIN and
SET_HOME_POSITION and asks for GPS_GLOBAL_ORIGIN. After an autopilot reboot or a lost link it
starts over. An autopilot that already had a different origin (ArduPilot sets it only once)
is reported; the local NED frame is still the autopilot's, which is what estimates are in.
"""

from __future__ import annotations

import asyncio
import logging

from companion import clock
from companion.config import OriginConfig
from companion.frames import ned_from_geodetic
from companion.health import Health, State
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.commands import CommandFailed, Commander
from companion.mavlink.link import MavlinkLink, mavlink

log = logging.getLogger("companion.origin")

MATCH_TOLERANCE_M = 0.5


class OriginSetter:
    """Supervised task body: sets and confirms the EKF origin, again after each reconnect."""

    def __init__(self, link: MavlinkLink, state: AutopilotState, commander: Commander,
                 origin: OriginConfig, health: Health) -> None:
        self.link = link
        self.state = state
        self.commander = commander
        self.origin = origin
        self.health = health
        self.confirmed = False
        self.confirmed_at: float | None = None
        self._restart = asyncio.Event()
        link.on_connect(self._restart.set)
        health.report("origin", State.LOST, "not confirmed by the autopilot yet")

    async def run(self) -> None:
        while True:
            await self._restart.wait()
            self._restart.clear()
            self.confirmed = False
            self.state.origin = None
            await self._until_confirmed()

    async def _until_confirmed(self) -> None:
        while not self._restart.is_set():
            self._send_origin()
            try:
                await self.commander.request_message(mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
            except CommandFailed as exc:
                log.debug("GPS_GLOBAL_ORIGIN request: %s", exc)
            await asyncio.sleep(1.0)
            if self.state.origin is not None:
                self._confirm()
                return

    def _send_origin(self) -> None:
        o = self.origin
        sysid = self.link.ids.autopilot_sysid
        usec = int(clock.now() * 1e6)
        lat, lon, alt = int(round(o.lat * 1e7)), int(round(o.lon * 1e7)), int(round(o.alt * 1000))
        self.link.send(mavlink.MAVLink_set_gps_global_origin_message(sysid, lat, lon, alt, usec))
        self.link.send(mavlink.MAVLink_set_home_position_message(
            sysid, lat, lon, alt, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, usec))

    def _confirm(self) -> None:
        got = self.state.origin
        assert got is not None
        offset = ned_from_geodetic(got.lat, got.lon, got.alt, (self.origin.lat, self.origin.lon, self.origin.alt))
        distance = float((offset ** 2).sum() ** 0.5)
        self.confirmed = True
        self.confirmed_at = clock.now()
        if distance > MATCH_TOLERANCE_M:
            reason = f"autopilot kept its own origin, {distance:.1f} m from the configured one"
            self.health.report("origin", State.DEGRADED, reason)
        else:
            self.health.report("origin", State.OK, "confirmed by GPS_GLOBAL_ORIGIN")
