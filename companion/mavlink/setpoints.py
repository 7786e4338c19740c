"""Setpoint API: position / velocity / acceleration targets in LOCAL_NED, kept alive.

While commanding, the current target is re-sent at ``setpoint_rate_hz`` (>= 10 Hz):
ArduPilot stops after 3 s without a velocity or acceleration target, PX4 leaves OFFBOARD
when setpoints stop. An ArduPilot fixed wing's (``Firmware.vehicle == "plane"``) GUIDED target
is a guided waypoint instead, MISSION_ITEM_INT with current = 2, what ground stations send for
"fly to here" (ArduPlane's documented GUIDED interface; checked on ArduPlane 4.0.7 SITL, which
answers MAV_FRAME_GLOBAL_RELATIVE_ALT_INT with MAV_MISSION_UNSUPPORTED_FRAME, so the frame is
MAV_FRAME_GLOBAL: metres above sea level). The plane
flies to it and circles it until told otherwise, so it is sent once per new target and repeated
only (every ``GUIDED_WAYPOINT_RETRY_S``) until a MISSION_ACK answers it (a refusal is logged).
The moment the autopilot leaves GUIDED/OFFBOARD because of someone else
(pilot, GCS, failsafe) the stream stops at once and ``on_takeover`` is called: the companion
never fights the pilot.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion import clock
from companion.frames import geodetic_from_ned
from companion.mavlink.autopilot import COMMANDABLE_MODES, AutopilotState
from companion.mavlink.link import MavlinkLink, mavlink

log = logging.getLogger("companion.setpoints")

IGNORE_POSITION = 0b0000_0000_0111  # x, y, z
IGNORE_VELOCITY = 0b0000_0011_1000
IGNORE_ACCELERATION = 0b0001_1100_0000
IGNORE_YAW = 0b0100_0000_0000
IGNORE_YAW_RATE = 0b1000_0000_0000
GUIDED_WAYPOINT_CURRENT = 2  # MISSION_ITEM(_INT).current: a guided-mode target, not a mission item
GUIDED_WAYPOINT_RETRY_S = 1.0  # a guided waypoint not yet acknowledged is sent again after this


@dataclass(frozen=True)
class Setpoint:
    """A LOCAL_NED target; unset parts are ignored by the autopilot (type_mask)."""

    position_ned: np.ndarray | None = None  # m
    velocity_ned: np.ndarray | None = None  # m/s
    acceleration_ned: np.ndarray | None = None  # m/s^2
    yaw_rad: float | None = None  # heading, radians from north
    yaw_rate_rads: float | None = None

    @property
    def type_mask(self) -> int:
        """POSITION_TARGET_TYPEMASK: e.g. position only 3576, velocity 3527, pos+vel+acc 3072."""
        mask = IGNORE_YAW | IGNORE_YAW_RATE
        if self.position_ned is None:
            mask |= IGNORE_POSITION
        if self.velocity_ned is None:
            mask |= IGNORE_VELOCITY
        if self.acceleration_ned is None:
            mask |= IGNORE_ACCELERATION
        if self.yaw_rad is not None:
            mask &= ~IGNORE_YAW
        if self.yaw_rate_rads is not None:
            mask &= ~IGNORE_YAW_RATE
        return mask


def setpoint_message(sp: Setpoint, time_boot_ms: int, target: tuple[int, int],
                     z_offset_m: float = 0.0) -> mavlink.MAVLink_message:
    """SET_POSITION_TARGET_LOCAL_NED for ``sp`` (ignored fields are sent as 0). ``z_offset_m`` is
    added to the position's z for firmware that reads it relative to home
    (``AutopilotState.setpoint_z_offset_m``)."""
    zero = np.zeros(3)
    p = sp.position_ned + np.array([0.0, 0.0, z_offset_m]) if sp.position_ned is not None else zero
    v = sp.velocity_ned if sp.velocity_ned is not None else zero
    a = sp.acceleration_ned if sp.acceleration_ned is not None else zero
    return mavlink.MAVLink_set_position_target_local_ned_message(
        time_boot_ms, target[0], target[1], mavlink.MAV_FRAME_LOCAL_NED, sp.type_mask,
        float(p[0]), float(p[1]), float(p[2]), float(v[0]), float(v[1]), float(v[2]),
        float(a[0]), float(a[1]), float(a[2]),
        float(sp.yaw_rad or 0.0), float(sp.yaw_rate_rads or 0.0))


def guided_waypoint_message(position_ned: np.ndarray, origin: tuple[float, float, float],
                            target: tuple[int, int]) -> mavlink.MAVLink_message:
    """MISSION_ITEM_INT "fly to here" (current 2, MAV_CMD_NAV_WAYPOINT) at ``position_ned`` (LOCAL_NED m,
    relative to the EKF ``origin`` = (lat deg, lon deg, alt m AMSL)), in MAV_FRAME_GLOBAL (alt m AMSL)."""
    lat, lon, alt = geodetic_from_ned(position_ned, origin)
    return mavlink.MAVLink_mission_item_int_message(
        target[0], target[1], 0, mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_CMD_NAV_WAYPOINT, GUIDED_WAYPOINT_CURRENT,
        1, 0.0, 0.0, 0.0, 0.0, int(round(lat * 1e7)), int(round(lon * 1e7)), float(alt))


class SetpointStream:
    """Holds the current target and streams it while commanding."""

    def __init__(self, link: MavlinkLink, state: AutopilotState, rate_hz: float,
                 on_takeover: Callable[[str], None] | None = None) -> None:
        self.link = link
        self.state = state
        self.rate_hz = rate_hz
        self.on_takeover = on_takeover or (lambda mode: None)
        self.current: Setpoint | None = None
        self.sent = 0
        self._last_sent = -float("inf")  # daemon clock of the last send
        self._commanding = False
        self._expected_mode: str | None = None
        self._wake = asyncio.Event()
        self._waypoint_answered = False  # (a fixed wing) a MISSION_ACK answered the current guided waypoint
        state.on_mode_change(self._on_mode_change)
        link.subscribe("MISSION_ACK", self._on_mission_ack)

    @property
    def commanding(self) -> bool:
        return self._commanding

    def expect_mode(self, mode: str) -> None:
        """Note that the companion itself asked for ``mode`` (not a pilot takeover)."""
        self._expected_mode = mode

    @property
    def guided_waypoints(self) -> bool:
        """Targets go as guided waypoints (an ArduPilot fixed wing), not as a setpoint stream."""
        firmware = self.state.firmware
        return firmware is not None and firmware.autopilot == "ArduPilot" and firmware.vehicle == "plane"

    def command(self, setpoint: Setpoint) -> None:
        """Make ``setpoint`` the target and send it now; keep it alive until :meth:`stop`."""
        if self.guided_waypoints and self.current is not None and _same_position(self.current, setpoint):
            self._commanding = True
            return  # the plane flies it already
        self.current = setpoint
        self._commanding = True
        self._waypoint_answered = False
        self._send()
        self._wake.set()

    def stop(self) -> None:
        """Stop streaming (the autopilot falls back to its own behaviour: hold/brake)."""
        if self._commanding:
            log.info("setpoint stream stopped")
        self._commanding = False
        self.current = None

    async def run(self) -> None:
        """Keepalive task: re-sends the current target whenever ``1 / rate_hz`` passed without a send."""
        while True:
            period = GUIDED_WAYPOINT_RETRY_S if self.guided_waypoints else 1.0 / self.rate_hz
            if not self._commanding or self._answered_waypoint():
                self._wake.clear()
                await self._wake.wait()
                continue
            due = self._last_sent + period
            await clock.sleep_until(due)
            now = clock.now()
            if self._commanding and now >= self._last_sent + period and not self._answered_waypoint():
                # Count from the deadline, not the (slightly late) wake-up: no drift below rate_hz.
                self._send(sent_at=due if now - due < period else now)

    def _answered_waypoint(self) -> bool:
        """A guided waypoint is the target and the autopilot answered it: nothing to repeat."""
        return self.guided_waypoints and self._waypoint_answered

    def _send(self, sent_at: float | None = None) -> None:
        if self.current is None:
            return
        now = clock.now()
        self._last_sent = now if sent_at is None else sent_at
        if self.guided_waypoints:
            message = self._guided_waypoint(self.current)
            if message is None:
                return
        else:
            message = setpoint_message(self.current, int(now * 1000) & 0xFFFFFFFF, self.link.target(),
                                       self.state.setpoint_z_offset_m())
        if self.link.send(message):
            self.sent += 1

    def _guided_waypoint(self, sp: Setpoint) -> mavlink.MAVLink_message | None:
        """The guided waypoint for ``sp`` (its position only); None, logged, when there is none to send."""
        origin = self.state.origin
        if sp.position_ned is None or origin is None:
            log.warning("a fixed wing flies position targets only, with a known EKF origin: %s not sent",
                        "velocity target" if sp.position_ned is None else "position target")
            return None
        return guided_waypoint_message(sp.position_ned, (origin.lat, origin.lon, origin.alt), self.link.target())

    def _on_mission_ack(self, msg: mavlink.MAVLink_message) -> None:
        if not self.guided_waypoints:
            return
        self._waypoint_answered = True
        if msg.type != mavlink.MAV_MISSION_ACCEPTED:
            log.warning("guided waypoint refused: MISSION_ACK type %d", msg.type)

    def _on_mode_change(self, old: str | None, new: str) -> None:
        if new == self._expected_mode:
            return
        if self._commanding and old in COMMANDABLE_MODES and new not in COMMANDABLE_MODES:
            log.warning("mode changed to %s by someone else: stop commanding", new)
            self.stop()
            self.on_takeover(new)


def _same_position(a: Setpoint, b: Setpoint) -> bool:
    """Both targets are the same position (velocity, acceleration and yaw aside: a fixed wing flies none of them)."""
    return a.position_ned is not None and b.position_ned is not None and bool(np.array_equal(a.position_ned,
                                                                                             b.position_ned))
