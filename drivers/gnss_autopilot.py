"""The autopilot's GNSS receiver as a sensor: ``kind: gnss, backend: autopilot``.

Receiver 1 arrives as GPS_RAW_INT, receiver 2 as GPS2_RAW (``settings.instance``). The daemon
asks for GPS_RAW_INT as its ``gps_raw`` stream (``mavlink.streams.gps_raw``, companion/mavlink/
streams.py); GPS2_RAW is not among its streams: the autopilot must send it unasked (ArduPilot:
in its EXTENDED_STATUS group, SRn_EXT_STAT, when it has a second receiver). Each message becomes
a :class:`~companion.messages.GnssFix`:

- ``fix_type`` as sent (MAVLink GPS_FIX_TYPE); latitude and longitude from 1e-7 degrees (WGS-84),
  altitude from mm above mean sea level;
- velocity from the ground speed ``vel`` (cm/s) and course over ground ``cog`` (centidegrees from
  true north, clockwise): north = v cos(cog), east = v sin(cog). The message has no vertical
  velocity, so down is NaN: "not measured": use the velocity horizontally only. Given
  only with a 3-D fix or better, and when both vel and cog are known (not UINT16_MAX);
- accuracies from the MAVLink 2 extensions ``h_acc``, ``v_acc`` (mm) and ``vel_acc`` (mm/s);
  0 (what ArduPilot sends when its receiver does not say, and what a MAVLink 1 message leaves)
  means unknown: None. ``eph``/``epv`` are dilutions of precision, not accuracies, and unused;
- satellites from ``satellites_visible`` (255: unknown, None); ``jamming`` is always False
  (neither message carries interference).

``t_capture`` is the arrival on the daemon clock minus ``latency_s`` (the receiver's output
delay plus the autopilot's forwarding: the message's own ``time_usec`` is on the autopilot's
clock). A message with a position fix that repeats the previous one's nonzero ``time_usec`` is
the same solution sent again (ArduPilot sends the boot time of its last fix there, and streams
faster than its receiver may solve) and is skipped; a report without a fix is always handed on
(ArduPilot keeps the time of the last fix in it). Messages are queued between the
link's dispatch and the frontend (bounded: a stalled consumer loses the oldest, counted in
``fixes.overflowed``); with no message for ``timeout_s`` the sensor is reported lost and waited for
again, like a device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion import clock
from companion.messages import GNSS_2D, GNSS_3D, GnssFix
from companion.plugins import register_backend
from companion.schema import meta
from drivers.base import Backend, PushedMessages

MESSAGES = {1: "GPS_RAW_INT", 2: "GPS2_RAW"}  # receiver instance -> its MAVLink message
QUEUE_FIXES = 50  # 5 s at 10 Hz
UNKNOWN_U16 = 0xFFFF  # vel, cog: not known
UNKNOWN_SATELLITES = 255


@dataclass
class AutopilotGnssSettings:
    """``settings:`` of a gnss with ``backend: autopilot``."""

    instance: int = field(default=1, metadata=meta(
        "The autopilot's receiver: 1 (GPS_RAW_INT) or 2 (GPS2_RAW).", (1, 2)))
    latency_s: float = field(default=0.0, metadata=meta(
        "Subtracted from the arrival time to give the fix's capture time: the receiver's output delay plus the "
        "autopilot's forwarding, seconds.", (0.0, 1.0)))
    timeout_s: float = field(default=2.0, metadata=meta(
        "No message for this long: the receiver is lost (reported, and waited for again), seconds.", (0.2, 30.0)))


def gnss_fix(msg: Any, receiver_id: str, t_capture: float) -> GnssFix:
    """The GnssFix of a GPS_RAW_INT or GPS2_RAW ``msg`` (see the module docstring for the units)."""
    velocity = None
    if msg.fix_type >= GNSS_3D and msg.vel != UNKNOWN_U16 and msg.cog != UNKNOWN_U16:
        speed, course = msg.vel / 100.0, math.radians(msg.cog / 100.0)
        velocity = np.array([speed * math.cos(course), speed * math.sin(course), math.nan])
    return GnssFix(
        receiver_id=receiver_id, t_capture=t_capture, fix_type=msg.fix_type,
        lat_deg=msg.lat * 1e-7, lon_deg=msg.lon * 1e-7, alt_m=msg.alt / 1000.0, velocity_ned_mps=velocity,
        h_acc_m=msg.h_acc / 1000.0 if msg.h_acc else None,
        v_acc_m=msg.v_acc / 1000.0 if msg.v_acc else None,
        speed_acc_mps=msg.vel_acc / 1000.0 if msg.vel_acc else None,
        satellites=None if msg.satellites_visible == UNKNOWN_SATELLITES else msg.satellites_visible)


class AutopilotGnss(Backend[GnssFix]):
    """The fixes of one of the autopilot's receivers, every new one, in order."""

    def __init__(self, link: Any, settings: AutopilotGnssSettings, receiver_id: str) -> None:
        self.settings = settings
        self.receiver_id = receiver_id
        self.message = MESSAGES[settings.instance]
        self.description = f"autopilot GNSS {settings.instance} ({self.message})"
        self.fixes: PushedMessages[GnssFix] = PushedMessages(QUEUE_FIXES)
        self._open = False
        self._last_time_usec = 0
        link.subscribe(self.message, self._on_message)  # the link has no unsubscribe: ignored while closed

    def _on_message(self, msg: Any) -> None:
        if not self._open or (msg.fix_type >= GNSS_2D and msg.time_usec and msg.time_usec == self._last_time_usec):
            return
        self._last_time_usec = msg.time_usec
        self.fixes.push(gnss_fix(msg, self.receiver_id, clock.now() - self.settings.latency_s))

    async def open(self) -> None:
        self.fixes.clear()
        self._last_time_usec = 0
        self._open = True

    async def read(self) -> GnssFix:
        return await self.fixes.get(self.settings.timeout_s, self.message)

    async def close(self) -> None:
        self._open = False


@register_backend("gnss", "autopilot", AutopilotGnssSettings)
def _autopilot_gnss(name: str, settings: AutopilotGnssSettings, ctx: Any) -> AutopilotGnss:
    """The autopilot's receiver ``settings.instance``, from its GPS_RAW_INT or GPS2_RAW over the link."""
    return AutopilotGnss(ctx.link, settings, receiver_id=name)
