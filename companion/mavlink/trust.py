"""Which messages are the companion's own autopilot speaking: its locked identity and its boot clock.

Bookkeeping only (no I/O, no logging): :class:`companion.mavlink.link.MavlinkLink` asks, then
counts, reports and drops what is refused.

**Identity** (:class:`IdentityLock`). The first HEARTBEAT from the configured autopilot ids
(``vehicle.autopilot_sysid`` / ``autopilot_compid``) that looks like an autopilot
(``autopilot`` not MAV_AUTOPILOT_INVALID, ``type`` a vehicle: not in :data:`NOT_VEHICLE_TYPES`) locks the
identity: those ids, that autopilot family and that MAV_TYPE. Refused from then on: a HEARTBEAT
from the locked ids with another family or type (:attr:`Heartbeat.CHANGED`). Refused before the
lock as after: an autopilot-looking HEARTBEAT from the autopilot's system with another component
id (:attr:`Heartbeat.IMPOSTOR`). Heartbeats that do not look like an autopilot (a gimbal or a
camera of the same system sends MAV_AUTOPILOT_INVALID, a companion MAV_TYPE_ONBOARD_CONTROLLER)
are other components' own and no conflict. The lock holds for the life of the process: a
vehicle whose firmware really changed needs the companion restarted.

**Boot clock** (:class:`BootClock`). Every ``time_boot_ms`` of the autopilot's messages (ATTITUDE,
SYSTEM_TIME, LOCAL_POSITION_NED, SCALED_IMU, ...) is placed on the autopilot's boot clock. A stamp
fits the clock when it is at most :data:`BACKWARD_TOLERANCE_MS` older than the newest stamp taken
(messages of different types are stamped at slightly different moments), at most
:data:`FORWARD_SLACK_MS` plus :data:`CLOCK_RATE_MARGIN` times the daemon time passed since that
stamp newer (the clock runs; a message may have been delayed more than the next), and not older
than the last stamp of its own message type (:attr:`Stamp.IN_ORDER`). A stamp that does not fit
is held back (:attr:`Stamp.DROPPED`): one odd stamp, backwards or far ahead, never moves the
clock. Only :data:`CONFIRMATIONS` consecutive stamps that fit one another and not the clock
(no stamp of the old clock between them), once the old clock has been silent for
:data:`OLD_CLOCK_SILENT_S` (an autopilot takes longer than that to boot; a forger interleaving
its own clock with the real one's stamps never gets there), make a new clock: an earlier one is a reboot
(:attr:`Stamp.REBOOT`), a later one a jump (:attr:`Stamp.JUMP`). The clock is kept across link
loss, so a link that comes back on an earlier clock is a reboot too. A reboot during a link loss
that ends with the new clock already past the old one cannot be told from the clock.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

AUTOPILOT_NAMES = {
    mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: "ArduPilot",
    mavlink.MAV_AUTOPILOT_PX4: "PX4",
}
# MAV_TYPEs that are not vehicles: a component of such a type (GCS, companion, gimbal, camera,
# ADS-B, an AP_Periph CAN node, ...) is no autopilot, whatever autopilot family it reports.
NOT_VEHICLE_TYPES = frozenset(getattr(mavlink, f"MAV_TYPE_{name}") for name in (
    "ANTENNA_TRACKER", "GCS", "ONBOARD_CONTROLLER", "GIMBAL", "ADSB", "CAMERA", "CHARGING_STATION", "FLARM",
    "SERVO", "ODID", "BATTERY", "PARACHUTE", "LOG", "OSD", "IMU", "GPS", "WINCH", "ILLUMINATOR", "GRIPPER"))
BACKWARD_TOLERANCE_MS = 1000
FORWARD_SLACK_MS = 1000
CLOCK_RATE_MARGIN = 2.0  # the autopilot's clock may run up to this many times the daemon's (SITL speed-up)
CONFIRMATIONS = 3
OLD_CLOCK_SILENT_S = 1.0  # no stamp on the old clock for this long before a new clock is believed


def looks_like_autopilot(msg: mavlink.MAVLink_message) -> bool:
    """Whether a HEARTBEAT claims an autopilot: a family other than INVALID, and a vehicle type."""
    return msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.type not in NOT_VEHICLE_TYPES


def autopilot_name(autopilot: int) -> str:
    """"ArduPilot", "PX4" or "autopilot type N" for a MAV_AUTOPILOT value."""
    return AUTOPILOT_NAMES.get(autopilot, f"autopilot type {autopilot}")


def _type_name(mav_type: int) -> str:
    entry = mavlink.enums["MAV_TYPE"].get(mav_type)
    return entry.name.removeprefix("MAV_TYPE_").lower() if entry is not None else f"type {mav_type}"


@dataclass(frozen=True)
class Identity:
    """Who a HEARTBEAT says it is."""

    sysid: int
    compid: int
    autopilot: int  # MAV_AUTOPILOT
    mav_type: int  # MAV_TYPE

    @classmethod
    def of(cls, msg: mavlink.MAVLink_message) -> Identity:
        return cls(msg.get_srcSystem(), msg.get_srcComponent(), msg.autopilot, msg.type)

    def __str__(self) -> str:
        """e.g. "ArduPilot quadrotor (sysid 1 compid 1)"."""
        return f"{autopilot_name(self.autopilot)} {_type_name(self.mav_type)} (sysid {self.sysid} compid {self.compid})"


class Heartbeat(enum.Enum):
    """What a HEARTBEAT from the autopilot's system is, to the companion."""

    AUTOPILOT = "the autopilot"  # the locked identity (or the one just locked)
    OTHER = "another component"  # not an autopilot (gimbal, camera, companion): not ours, no conflict
    CHANGED = "another autopilot type from the autopilot's ids"
    IMPOSTOR = "an autopilot at another component id"


class IdentityLock:
    """The autopilot's identity, locked by its first HEARTBEAT (see the module docstring)."""

    def __init__(self, sysid: int, compid: int) -> None:
        self.sysid = sysid
        self.compid = compid
        self.locked: Identity | None = None

    def judge(self, msg: mavlink.MAVLink_message) -> Heartbeat:
        """What HEARTBEAT ``msg`` (from the autopilot's sysid) is; the first autopilot one locks the identity."""
        claimed = Identity.of(msg)
        if claimed.compid != self.compid:
            return Heartbeat.IMPOSTOR if looks_like_autopilot(msg) else Heartbeat.OTHER
        if self.locked is None:
            if not looks_like_autopilot(msg):
                return Heartbeat.OTHER
            self.locked = claimed
        return Heartbeat.AUTOPILOT if claimed == self.locked else Heartbeat.CHANGED


class Stamp(enum.Enum):
    """What one ``time_boot_ms`` is on the autopilot's boot clock."""

    IN_ORDER = "in order"
    DROPPED = "does not fit the clock"  # held back: an odd stamp, or a new clock not confirmed yet
    REBOOT = "a new, earlier clock"
    JUMP = "a new, later clock"


@dataclass
class _Mark:
    """A stamp (ms, autopilot clock) and when it arrived (s, daemon clock)."""

    ms: int
    t: float

    def fits(self, ms: int, t: float) -> bool:
        ahead_ms = FORWARD_SLACK_MS + max(t - self.t, 0.0) * 1000.0 * CLOCK_RATE_MARGIN
        return self.ms - BACKWARD_TOLERANCE_MS <= ms <= self.ms + ahead_ms

    def advance(self, ms: int, t: float) -> None:
        if ms > self.ms:
            self.ms, self.t = ms, t


class BootClock:
    """The autopilot's boot clock, told apart from odd stamps (see the module docstring)."""

    def __init__(self) -> None:
        self._clock: _Mark | None = None  # the newest stamp taken
        self._latest: dict[str, int] = {}  # message type -> its newest stamp taken
        self._run: _Mark | None = None  # the newest of consecutive stamps off the clock
        self._run_length = 0

    @property
    def ms(self) -> int | None:
        """The newest stamp taken (ms since the autopilot booted), None before the first."""
        return None if self._clock is None else self._clock.ms

    def observe(self, msg_type: str, ms: int, t: float) -> Stamp:
        """Place stamp ``ms`` of a ``msg_type`` message arriving at daemon time ``t`` (s)."""
        if self._clock is None or self._clock.fits(ms, t):
            self._run, self._run_length = None, 0
            if ms < self._latest.get(msg_type, ms):
                return Stamp.DROPPED
            self._take(msg_type, ms, t)
            return Stamp.IN_ORDER
        if self._run is not None and self._run.fits(ms, t):
            self._run.advance(ms, t)
            self._run_length += 1
        else:
            self._run, self._run_length = _Mark(ms, t), 1
        if self._run_length < CONFIRMATIONS or t - self._clock.t < OLD_CLOCK_SILENT_S:
            return Stamp.DROPPED
        earlier = ms < self._clock.ms
        self._clock, self._latest, self._run, self._run_length = None, {}, None, 0
        self._take(msg_type, ms, t)
        return Stamp.REBOOT if earlier else Stamp.JUMP

    def _take(self, msg_type: str, ms: int, t: float) -> None:
        self._latest[msg_type] = ms
        if self._clock is None:
            self._clock = _Mark(ms, t)
        else:
            self._clock.advance(ms, t)
