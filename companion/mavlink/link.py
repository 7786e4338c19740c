"""The companion's MAVLink connection to its autopilot (pymavlink, MAVLink 2).

One :class:`MavlinkLink` owns the connection: it opens it (retrying with backoff when a serial
device is unplugged or a TCP peer is down), reads it without blocking the event loop,
dispatches messages to subscribers, sends the 1 Hz HEARTBEAT as MAV_TYPE_ONBOARD_CONTROLLER,
recognises the autopilot (ArduPilot or PX4) from its HEARTBEAT, notices link loss and
autopilot reboots, and answers TIMESYNC (which also drives the clock in lockstep, see
companion/clock.py).

:meth:`MavlinkLink.send` is the single exit to the autopilot: a message with any non-finite
float field is dropped there, counted and logged, so a NaN never reaches the autopilot.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from companion import clock  # noqa: E402
from companion.config import MavlinkConfig, VehicleConfig  # noqa: E402
from companion.health import Health, State  # noqa: E402

log = logging.getLogger("companion.mavlink")

Handler = Callable[[mavlink.MAVLink_message], None]

AUTOPILOT_NAMES = {
    mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: "ArduPilot",
    mavlink.MAV_AUTOPILOT_PX4: "PX4",
}


@dataclass
class LinkStats:
    messages_rx: int = 0
    messages_tx: int = 0
    nonfinite_dropped: int = 0
    send_errors: int = 0
    reconnects: int = 0
    autopilot_reboots: int = 0


def load_signing_key(path: Path) -> bytes:
    """The 32-byte MAVLink 2 signing secret from a file (32 raw bytes or 64 hex characters)."""
    data = path.read_bytes()
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    if len(data) == 32:
        return data
    raise ValueError(f"{path}: a signing key is 32 raw bytes or 64 hex characters, got {len(data)} bytes")


def nonfinite_fields(msg: mavlink.MAVLink_message) -> list[str]:
    """Names of the message's float fields holding NaN or infinity."""
    bad = []
    for name in msg.get_fieldnames():
        value = getattr(msg, name)
        values = value if isinstance(value, (list, tuple)) else (value,)
        if any(isinstance(v, float) and not math.isfinite(v) for v in values):
            bad.append(name)
    return bad


class MavlinkLink:
    """The connection to one autopilot; see the module docstring for what it guarantees."""

    def __init__(self, cfg: MavlinkConfig, ids: VehicleConfig, url: str, health: Health,
                 signing_key: bytes | None = None) -> None:
        self.cfg = cfg
        self.ids = ids
        self.url = url
        self.health = health
        self.signing_key = signing_key
        self.stats = LinkStats()
        self.autopilot: str | None = None  # "ArduPilot", "PX4" or None until a HEARTBEAT arrives
        self.last_heartbeat: float | None = None  # daemon clock, seconds
        self._conn: mavutil.mavfile | None = None
        self._handlers: dict[str, list[Handler]] = defaultdict(list)
        self._on_connect: list[Callable[[], None]] = []
        self._connected = False
        self._paused = False  # lockstep: reading stops at a tick until the loop is idle
        self._ticked = asyncio.Event()  # lockstep: the vehicle's first tick arrived
        self._tick_batch: list[mavlink.MAVLink_message] = []  # lockstep: read, not yet dispatched
        self._last_boot_ms: int | None = None
        self.health.report("link", State.LOST, "not connected yet")
        self.subscribe("HEARTBEAT", self._on_heartbeat)
        self.subscribe("TIMESYNC", self._on_timesync)
        self.subscribe("SYSTEM_TIME", self._on_boot_time)
        self.subscribe("ATTITUDE", self._on_boot_time)

    # -- public API -------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """True while autopilot HEARTBEATs arrive within ``link_timeout_s``."""
        return self._connected

    def subscribe(self, msg_type: str, handler: Handler) -> None:
        """Call ``handler(msg)`` for every message of ``msg_type`` from the autopilot."""
        self._handlers[msg_type].append(handler)

    def on_connect(self, callback: Callable[[], None]) -> None:
        """Call ``callback()`` whenever the autopilot is (re)found: first contact, link regained, reboot."""
        self._on_connect.append(callback)

    def send(self, msg: mavlink.MAVLink_message) -> bool:
        """Send ``msg`` to the autopilot; False if it was dropped (no port, non-finite field, I/O error)."""
        bad = nonfinite_fields(msg)
        if bad:
            self.stats.nonfinite_dropped += 1
            log.error("dropped %s with non-finite %s: never sent to the autopilot", msg.get_type(), ", ".join(bad))
            return False
        if self._conn is None:
            return False
        try:
            self._conn.mav.send(msg)
        except OSError as exc:
            self.stats.send_errors += 1
            log.warning("send %s failed: %s", msg.get_type(), exc)
            return False
        self.stats.messages_tx += 1
        return True

    def target(self) -> tuple[int, int]:
        """(target_system, target_component) of the autopilot."""
        return self.ids.autopilot_sysid, self.ids.autopilot_compid

    async def run(self) -> None:
        """Open the port (with backoff), then read, heartbeat and watch the link until cancelled."""
        backoff = 0.5
        while True:
            try:
                self._open()
            except (OSError, ValueError) as exc:
                self.health.report("link", State.LOST, f"cannot open {self.url}: {exc}")
                log.warning("cannot open %s: %s; retrying in %.1f s", self.url, exc, backoff)
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, 10.0)
                continue
            backoff = 0.5
            try:
                await self._serve()
            finally:
                self._close()
            self.stats.reconnects += 1
            await asyncio.sleep(0.5)

    # -- connection lifecycle ---------------------------------------------------------------

    def _open(self) -> None:
        conn = mavutil.mavlink_connection(
            self.url, source_system=self.ids.sysid, source_component=self.ids.compid,
            dialect="ardupilotmega", autoreconnect=False, baud=921600,
            retries=0)  # no blocking retry loop inside pymavlink: run() retries with backoff
        conn.mav.robust_parsing = True
        if self.signing_key is not None:
            conn.setup_signing(self.signing_key, sign_outgoing=True)
        if conn.fd is None:
            conn.close()
            raise OSError(f"{self.url} has no pollable file descriptor")
        self._conn = conn
        asyncio.get_running_loop().add_reader(conn.fd, self._on_readable)
        log.info("MAVLink port open: %s (sysid %d compid %d)", self.url, self.ids.sysid, self.ids.compid)

    def _close(self) -> None:
        conn, self._conn = self._conn, None
        if conn is None:
            return
        try:
            asyncio.get_running_loop().remove_reader(conn.fd)
        except (ValueError, OSError):
            pass
        conn.close()
        self._set_connected(False, "port closed")

    async def _serve(self) -> None:
        """Heartbeat and link watch until the port fails (serial/TCP: or stays silent)."""
        period = 1.0 / self.cfg.heartbeat_hz
        reopen = not self.url.startswith(("udpin:", "udpout:", "udp:"))
        lost_since = clock.now()
        while self._conn is not None:
            self._send_heartbeat()
            now = clock.now()
            if self._connected and now - (self.last_heartbeat or 0.0) > self.cfg.link_timeout_s:
                self._set_connected(False, f"no autopilot HEARTBEAT for {self.cfg.link_timeout_s:g} s")
                lost_since = now
            if not self._connected and reopen and now - lost_since > 2 * self.cfg.link_timeout_s:
                log.warning("no autopilot on %s; reopening the port", self.url)
                return
            await self._until_next_heartbeat(period)

    async def _until_next_heartbeat(self, period: float) -> None:
        """Wait ``period`` seconds of daemon time between two HEARTBEATs.

        In lockstep, before the vehicle's first tick, simulation time stands still until the
        vehicle hears a HEARTBEAT, and the first one may have gone out before it listened (a
        udpin vehicle cannot speak first): until that tick, repeat it every ``period`` of wall
        time. From the first tick on the schedule is simulation time again.
        """
        loop = asyncio.get_running_loop()
        if isinstance(loop, clock.LockstepEventLoop) and not self._ticked.is_set():
            ticked = asyncio.ensure_future(self._ticked.wait())
            wall = loop.run_in_executor(None, time.sleep, period)
            try:
                await asyncio.wait({ticked, wall}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                ticked.cancel()
                wall.cancel()
            if not self._ticked.is_set():
                return
        await asyncio.sleep(period)

    def _send_heartbeat(self) -> None:
        self.send(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
            mavlink.MAV_STATE_ACTIVE, 3))

    # -- reading ----------------------------------------------------------------------------

    def _on_readable(self) -> None:
        conn = self._conn
        while conn is not None and not self._paused:
            try:
                msg = conn.recv_msg()
            except Exception as exc:  # OSError, or pyserial's SerialException on unplug
                log.warning("read from %s failed: %s", self.url, exc)
                self._close()
                return
            if msg is None:
                return
            if isinstance(asyncio.get_running_loop(), clock.LockstepEventLoop):
                self._batch_until_tick(msg)
            else:
                self._dispatch(msg)

    def _batch_until_tick(self, msg: mavlink.MAVLink_message) -> None:
        """Lockstep: hold messages until the vehicle's next tick request, then dispatch them all.

        Everything the vehicle sends between two ticks is handled at the same daemon time, in
        order and in one go: no task they wake runs between two of them, whatever the pace at
        which the datagrams arrive (otherwise a task woken by a COMMAND_ACK could see or miss
        the HEARTBEAT sent right after it, and two runs with the same seed would differ).
        """
        self._tick_batch.append(msg)
        if (msg.get_type() == "TIMESYNC" and msg.tc1 == 0
                and msg.get_srcSystem() == self.ids.autopilot_sysid):
            batch, self._tick_batch = self._tick_batch, []
            for m in batch:
                self._dispatch(m)

    def _dispatch(self, msg: mavlink.MAVLink_message) -> None:
        msg_type = msg.get_type()
        if msg_type == "BAD_DATA":
            return
        self.stats.messages_rx += 1
        if msg.get_srcSystem() != self.ids.autopilot_sysid:
            return
        for handler in self._handlers.get(msg_type, ()):
            try:
                handler(msg)
            except Exception:
                log.exception("handler for %s failed", msg_type)

    # -- built-in handlers ------------------------------------------------------------------

    def _on_heartbeat(self, msg: mavlink.MAVLink_message) -> None:
        if msg.get_srcComponent() != self.ids.autopilot_compid or msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:
            return
        self.last_heartbeat = clock.now()
        name = AUTOPILOT_NAMES.get(msg.autopilot, f"autopilot type {msg.autopilot}")
        if name != self.autopilot:
            self.autopilot = name
            log.info("autopilot detected: %s (sysid %d)", name, msg.get_srcSystem())
        if not self._connected:
            self._set_connected(True, f"{name} heartbeat")

    def _on_boot_time(self, msg: mavlink.MAVLink_message) -> None:
        boot_ms = msg.time_boot_ms
        if self._last_boot_ms is not None and boot_ms + 1000 < self._last_boot_ms:
            self.stats.autopilot_reboots += 1
            log.warning("autopilot rebooted (boot time %d ms < %d ms)", boot_ms, self._last_boot_ms)
            self._last_boot_ms = boot_ms
            self._fire_on_connect()
        self._last_boot_ms = boot_ms

    def _on_timesync(self, msg: mavlink.MAVLink_message) -> None:
        if msg.tc1 != 0:
            return
        loop = asyncio.get_running_loop()
        if isinstance(loop, clock.LockstepEventLoop):
            self._ticked.set()
            # Stop reading; let what earlier messages woke finish at the current time; only
            # then advance the clock, run what is due, and answer once idle again.
            self._paused = True
            loop.call_when_idle(lambda: self._advance_then_answer(loop, msg.ts1))
        else:
            self._answer_timesync(msg.ts1)

    def _advance_then_answer(self, loop: clock.LockstepEventLoop, ts1: int) -> None:
        loop.advance(ts1 * 1e-9)
        loop.call_when_idle(lambda: self._answer_tick(ts1))

    def _answer_timesync(self, ts1: int) -> None:
        # tc1 = 0 would make the answer a request: at simulation time 0, say 1 ns.
        self.send(mavlink.MAVLink_timesync_message(max(1, int(clock.now() * 1e9)), ts1))

    def _answer_tick(self, ts1: int) -> None:
        self._answer_timesync(ts1)
        self._paused = False
        asyncio.get_running_loop().call_soon(self._on_readable)

    def _set_connected(self, connected: bool, reason: str) -> None:
        if connected == self._connected:
            return
        self._connected = connected
        if connected:
            self.health.report("link", State.OK, reason)
            self._fire_on_connect()
        else:
            self._last_boot_ms = None
            self.health.report("link", State.LOST, reason)

    def _fire_on_connect(self) -> None:
        for callback in self._on_connect:
            try:
                callback()
            except Exception:
                log.exception("on_connect callback failed")
