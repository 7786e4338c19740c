"""EKF origin and home: make the autopilot use the configured origin, and know when it does.

Without GPS the autopilot's EKF estimates no position until an origin is set. Every second,
until GPS_GLOBAL_ORIGIN confirms, the companion sends SET_GPS_GLOBAL_ORIGIN and asks for
GPS_GLOBAL_ORIGIN. After an autopilot reboot or a lost link it starts over. An autopilot that
already had a different origin (ArduPilot sets it only once) is reported; the local NED frame
is still the autopilot's, which is what estimates are in.

Home is then set at the same point (SET_HOME_POSITION, once a second until HOME_POSITION
confirms it), so that firmware reading positions relative to home (ArduPilot < 4.1) and the
EKF-origin frame agree, and arming does not move home. It is sent only once the EKF reports a
horizontal position: ArduPilot 4.0 SITL halts with "Should not be called on invalid location"
when home is set while the EKF has an altitude but no position yet (Copter::read_inertia).
"""

from __future__ import annotations

import asyncio
import logging

import numpy as np

from companion import clock
from companion.config import OriginConfig
from companion.frames import ned_from_geodetic
from companion.health import Health, State
from companion.mavlink.autopilot import AutopilotState, Origin
from companion.mavlink.commands import CommandFailed, Commander
from companion.mavlink.link import MavlinkLink, mavlink, run_per_connection

log = logging.getLogger("companion.origin")

MATCH_TOLERANCE_M = 0.5  # origin: an autopilot that kept its own further away than this is reported
HOME_TOLERANCE_M = 0.05  # home: at the origin within this (ArduPilot keeps home in cm and 1e-7 deg)
POLL_S = 0.1  # how often a confirming report is looked for
HOME_ATTEMPTS = 10  # SET_HOME_POSITION sent this often without HOME_POSITION at the origin: give up, say so


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
        self.home_confirmed = False
        self.home_done = False  # the home phase is over: confirmed, or given up (positions are converted)
        self._restart = asyncio.Event()
        link.on_connect(self._restart.set)
        health.report("origin", State.LOST, "not confirmed by the autopilot yet")

    async def run(self) -> None:
        await run_per_connection(self._restart, self._establish)

    async def _establish(self) -> None:
        """Origin, then home, for one connection: each confirmed by a report received on it.
        Until then the origin is unconfirmed, in health as in telemetry (``confirmed``)."""
        self.confirmed = self.home_confirmed = self.home_done = False
        self.health.report("origin", State.LOST, "not confirmed on this connection yet")
        since = clock.now()
        await self._until_confirmed(since)
        await self._until_home_set(since)

    @property
    def ready(self) -> bool:
        """The origin is confirmed and home is settled: positions mean the same to both sides."""
        return self.confirmed and self.home_done

    async def _until_confirmed(self, since: float) -> None:
        """Send the origin every second until the autopilot reports one (after daemon time ``since``);
        the report is looked for every :data:`POLL_S`."""
        while True:
            self._send_origin()
            await self._ask_for(mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
            resend_at = clock.now() + 1.0
            while clock.now() < resend_at:
                await asyncio.sleep(POLL_S)
                if self.state.origin_time is not None and self.state.origin_time >= since:
                    self._confirm()
                    return

    async def _until_home_set(self, since: float) -> None:
        """Set home at the origin once the EKF has a horizontal position (see the module docstring):
        the EKF flags are reset at every connection (AutopilotState), so this waits for a report
        of this connection."""
        attempts = 0
        while True:
            if self.state.home_time is not None and self.state.home_time >= since and self._home_at_origin():
                self.home_confirmed = self.home_done = True
                log.info("home set at the origin, confirmed by HOME_POSITION")
                return
            if attempts == HOME_ATTEMPTS:
                log.warning("the autopilot did not take home at the origin after %d attempts; positions relative "
                            "to home are converted with the home it reports", attempts)
                self.home_done = True
                return
            if self.state.ekf_flags & mavlink.EKF_POS_HORIZ_ABS:  # = ESTIMATOR_POS_HORIZ_ABS (PX4)
                attempts += 1
                self._send_home()
                await self._ask_for(mavlink.MAVLINK_MSG_ID_HOME_POSITION)
            await asyncio.sleep(1.0)

    async def _ask_for(self, msg_id: int) -> None:
        """REQUEST_MESSAGE ``msg_id``; a refusal is no error here (the next round asks again)."""
        try:
            await self.commander.request_message(msg_id)
        except CommandFailed as exc:
            log.debug("request for message %d: %s", msg_id, exc)

    def _home_at_origin(self) -> bool:
        assert self.state.home is not None
        return self._distance_from_origin(self.state.home) <= HOME_TOLERANCE_M

    def _distance_from_origin(self, place: Origin) -> float:
        """Distance (m) of ``place`` (as the autopilot reports it) from the configured origin."""
        offset = ned_from_geodetic(place.lat, place.lon, place.alt, (self.origin.lat, self.origin.lon, self.origin.alt))
        return float(np.linalg.norm(offset))

    def _geodetic(self) -> tuple[int, int, int, int]:
        """(lat 1e-7 deg, lon 1e-7 deg, alt mm, time usec) of the configured origin."""
        o = self.origin
        return int(round(o.lat * 1e7)), int(round(o.lon * 1e7)), int(round(o.alt * 1000)), int(clock.now() * 1e6)

    def _send_origin(self) -> None:
        lat, lon, alt, usec = self._geodetic()
        self.link.send(mavlink.MAVLink_set_gps_global_origin_message(self.link.ids.autopilot_sysid, lat, lon, alt, usec))

    def _send_home(self) -> None:
        lat, lon, alt, usec = self._geodetic()
        self.link.send(mavlink.MAVLink_set_home_position_message(
            self.link.ids.autopilot_sysid, lat, lon, alt, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, usec))

    def _confirm(self) -> None:
        assert self.state.origin is not None
        distance = self._distance_from_origin(self.state.origin)
        self.confirmed = True
        self.confirmed_at = clock.now()
        if distance > MATCH_TOLERANCE_M:
            reason = f"autopilot kept its own origin, {distance:.1f} m from the configured one"
            self.health.report("origin", State.DEGRADED, reason)
        else:
            self.health.report("origin", State.OK, "confirmed by GPS_GLOBAL_ORIGIN")
