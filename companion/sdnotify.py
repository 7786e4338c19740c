"""systemd readiness and watchdog notifications without any dependency.

A ``Type=notify`` unit gets the path of an AF_UNIX datagram socket in ``NOTIFY_SOCKET``
(a leading ``@`` names a socket in the abstract namespace).  The service reports its state by
sending newline-separated ``KEY=VALUE`` assignments to that socket: ``READY=1`` once it is
up, ``STATUS=...`` free text shown by ``systemctl status``, ``WATCHDOG=1`` to keep the
watchdog from firing and ``STOPPING=1`` when it shuts down (see sd_notify(3)).

Outside systemd ``NOTIFY_SOCKET`` is unset and every call here does nothing, so the daemon
can call the notifier unconditionally.

The watchdog is only worth anything if it is fed by the work itself: the navigation loop
calls :meth:`WatchdogGate.beat` on each iteration and :func:`run_watchdog` pings systemd only
while the last beat is recent, so a stalled loop (not just a dead process) gets the service
restarted.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import time
from collections.abc import Callable, Mapping

__all__ = ["Notifier", "WatchdogGate", "run_watchdog"]

log = logging.getLogger(__name__)

Clock = Callable[[], float]


class Notifier:
    """Sends sd_notify(3) messages to the socket named by ``NOTIFY_SOCKET``.

    The environment is read once, at construction.  Without ``NOTIFY_SOCKET`` (or with an
    address this implementation cannot use) the notifier is disabled and its methods return
    ``False`` without touching any socket.  Send errors are logged once at WARNING (later
    ones at DEBUG) and never raised: losing systemd must not take the navigation down.
    """

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        """Read ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID``.

        Args:
            environ: the environment to read; ``os.environ`` when ``None``.
        """
        env = os.environ if environ is None else environ
        self._address = _socket_address(env.get("NOTIFY_SOCKET", ""))
        self._watchdog_usec = env.get("WATCHDOG_USEC")
        self._watchdog_pid = env.get("WATCHDOG_PID")
        self._sock: socket.socket | None = None
        self._error_logged = False

    @property
    def enabled(self) -> bool:
        """True when a notification socket is configured."""
        return self._address is not None

    def notify(self, *assignments: str) -> bool:
        """Send ``KEY=VALUE`` assignments as one datagram.

        Returns:
            True if the datagram was handed to the kernel, False if disabled or on error.
        """
        if self._address is None:
            return False
        payload = "\n".join(assignments).encode("utf-8", errors="replace")
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                # Never block the event loop if systemd is slow to drain its queue.
                self._sock.setblocking(False)
            self._sock.sendto(payload, self._address)
        except OSError as exc:
            level = logging.DEBUG if self._error_logged else logging.WARNING
            log.log(level, "sd_notify to %r failed: %s", self._address, exc)
            self._error_logged = True
            return False
        return True

    def ready(self) -> bool:
        """Tell systemd start-up is complete (``READY=1``)."""
        return self.notify("READY=1")

    def status(self, text: str) -> bool:
        """Set the one-line status shown by ``systemctl status`` (``STATUS=...``).

        Line breaks are replaced by spaces so the text cannot inject other assignments.
        """
        return self.notify("STATUS=" + " ".join(text.splitlines()))

    def watchdog(self) -> bool:
        """Reset the service watchdog timer (``WATCHDOG=1``)."""
        return self.notify("WATCHDOG=1")

    def stopping(self) -> bool:
        """Tell systemd the service is shutting down (``STOPPING=1``)."""
        return self.notify("STOPPING=1")

    def watchdog_interval(self) -> float | None:
        """The watchdog timeout in seconds (``WatchdogSec=``), or None if not enabled.

        None when notifications are disabled, when ``WATCHDOG_USEC`` is unset or not a
        positive integer, or when ``WATCHDOG_PID`` is set to another process (the variables
        were inherited and are not meant for this one).  Ping at half this interval.
        """
        if self._address is None or not self._watchdog_usec:
            return None
        try:
            usec = int(self._watchdog_usec)
        except ValueError:
            log.warning("ignoring invalid WATCHDOG_USEC=%r", self._watchdog_usec)
            return None
        if usec <= 0:
            log.warning("ignoring invalid WATCHDOG_USEC=%r", self._watchdog_usec)
            return None
        if self._watchdog_pid:
            try:
                pid = int(self._watchdog_pid)
            except ValueError:
                log.warning("ignoring invalid WATCHDOG_PID=%r", self._watchdog_pid)
                return None
            if pid != os.getpid():
                return None
        return usec / 1_000_000

    def close(self) -> None:
        """Close the socket; a later notification opens a new one."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _socket_address(value: str) -> str | None:
    """Translate a ``NOTIFY_SOCKET`` value into an AF_UNIX address, or None if unusable."""
    if not value:
        return None
    if value.startswith("@"):
        return "\0" + value[1:]  # abstract namespace: leading NUL byte
    if value.startswith("/"):
        return value
    # e.g. "vsock:..." (systemd >= 254, used for VMs): not an AF_UNIX path.
    log.warning("unsupported NOTIFY_SOCKET=%r; systemd notifications disabled", value)
    return None


class WatchdogGate:
    """Tracks whether the navigation loop is alive.

    The loop calls :meth:`beat` once per iteration; :meth:`healthy` is true only while the
    last beat is younger than ``max_age`` seconds.  No beat yet means unhealthy.
    """

    def __init__(self, max_age: float, clock: Clock = time.monotonic) -> None:
        """Create a gate.

        Args:
            max_age: seconds after the last beat at which the loop counts as stalled.
            clock: monotonic clock used by :meth:`beat`; :meth:`healthy` must be given
                times from the same clock.

        Raises:
            ValueError: if ``max_age`` is not positive.
        """
        if not max_age > 0:
            raise ValueError(f"max_age must be positive, got {max_age!r}")
        self.max_age = max_age
        self._clock = clock
        self._last_beat: float | None = None

    def beat(self) -> None:
        """Record that the loop completed an iteration now."""
        self._last_beat = self._clock()

    def age(self, now: float) -> float | None:
        """Seconds since the last beat at ``now``, or None before the first beat."""
        if self._last_beat is None:
            return None
        return now - self._last_beat

    def healthy(self, now: float) -> bool:
        """True if the last beat is younger than ``max_age`` at time ``now``."""
        age = self.age(now)
        return age is not None and age < self.max_age


async def run_watchdog(
    notifier: Notifier, gate: WatchdogGate, clock: Clock = time.monotonic
) -> None:
    """Ping the systemd watchdog every half interval while ``gate`` is healthy.

    Returns at once if the watchdog is not enabled for this process; otherwise runs until
    cancelled.  While the gate is unhealthy no ping is sent, so systemd kills and restarts
    the service once ``WatchdogSec`` passes without one.

    Args:
        notifier: where to send ``WATCHDOG=1``.
        gate: the navigation loop's heartbeat.
        clock: the clock ``gate`` was created with.
    """
    interval = notifier.watchdog_interval()
    if interval is None:
        return
    period = interval / 2
    log.debug("systemd watchdog %.3f s: pinging every %.3f s while healthy", interval, period)
    stalled = False  # a stall has been reported and not yet recovered from
    waiting_logged = False
    while True:
        now = clock()
        age = gate.age(now)
        if gate.healthy(now):
            notifier.watchdog()
            if stalled:
                log.warning("navigation loop beating again; watchdog pings resumed")
                stalled = False
        elif age is None:
            if not waiting_logged:
                log.info("no watchdog ping until the navigation loop's first beat")
                waiting_logged = True
        elif not stalled:
            log.error(
                "navigation loop stalled (last beat %.2f s ago); withholding watchdog pings",
                age,
            )
            stalled = True
        await asyncio.sleep(period)
