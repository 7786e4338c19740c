"""One MAVLink channel of the simulated vehicle: a pymavlink connection with its own stream schedule."""

from __future__ import annotations

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.jitter import JitterCorrection

COMPID = mav.MAV_COMP_ID_AUTOPILOT1
HEARTBEAT_INTERVAL_US = 1_000_000


def next_due(due_us: int, interval_us: int, now_us: int) -> int:
    """Next due time of a periodic output that was due at ``due_us`` and sent at ``now_us``.

    Keeps the period on schedule, but skips missed periods instead of bursting to catch up.
    """
    due_us += interval_us
    return due_us if due_us > now_us else now_us + interval_us


class Link:
    """One MAVLink channel: a pymavlink connection with its own stream schedule and clock mapping."""

    def __init__(self, name: str, url: str, sysid: int) -> None:
        self.name = name
        self.conn = mavutil.mavlink_connection(
            url, source_system=sysid, source_component=COMPID, dialect="ardupilotmega")
        self.intervals_us: dict[int, int] = {mav.MAVLINK_MSG_ID_HEARTBEAT: HEARTBEAT_INTERVAL_US}
        self.next_due_us: dict[int, int] = {}
        self.jitter = JitterCorrection()

    def fileno(self) -> int:
        """Current socket file descriptor, for select() (a tcpin link's changes on accept)."""
        return self.conn.fd

    def send(self, msg: mav.MAVLink_message) -> None:
        """Send a message from this vehicle (own sequence numbers per link)."""
        self.conn.mav.send(msg)

    def forward(self, msg: mav.MAVLink_message) -> None:
        """Send another system's message unchanged (routing)."""
        self.conn.write(msg.get_msgbuf())

    def recv(self) -> mav.MAVLink_message | None:
        """The next received message, or None when nothing is waiting (non-blocking)."""
        return self.conn.recv_msg()

    def set_interval(self, msgid: int, interval_us: int | None, now_us: int) -> None:
        """Stream ``msgid`` every ``interval_us`` of sim time from now on (None: stop it)."""
        if interval_us is None:
            self.intervals_us.pop(msgid, None)
            self.next_due_us.pop(msgid, None)
            return
        self.intervals_us[msgid] = interval_us
        self.next_due_us[msgid] = now_us

    def due(self, now_us: int) -> list[int]:
        """Message ids whose stream is due at sim time ``now_us``; advances their schedule."""
        ids = []
        for msgid, interval in self.intervals_us.items():
            next_us = self.next_due_us.get(msgid, now_us)
            if now_us >= next_us:
                ids.append(msgid)
                self.next_due_us[msgid] = next_due(next_us, interval, now_us)
        return ids

    def close(self) -> None:
        self.conn.close()
