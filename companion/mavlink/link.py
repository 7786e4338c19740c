"""The companion's MAVLink connection to its autopilot (MAVLink 2, pymavlink's codec).

One :class:`MavlinkLink` owns the connection: it opens it without blocking the event loop
(``companion.mavlink.transport``: TCP, UDP, serial), reopens it with backoff when it ends (a TCP
peer closed, a serial device unplugged, a dead TCP peer found by keepalive), reads it without
blocking, dispatches messages to subscribers, sends the 1 Hz HEARTBEAT as
MAV_TYPE_ONBOARD_CONTROLLER, recognises the autopilot (ArduPilot or PX4) from its HEARTBEAT,
notices link loss and autopilot reboots, and answers TIMESYNC (which also drives the clock in
lockstep, see companion/clock.py).

Only the autopilot is listened to (``companion.mavlink.trust``): subscribers get messages from the
autopilot's sysid and compid only (others of its system are counted, ``other_components_rx``); its
identity (ids, autopilot family, MAV_TYPE) is locked by its first HEARTBEAT, and HEARTBEATs that
claim another are refused, counted (``identity_changed``, ``identity_impostors``), reported
(health component ``autopilot_identity`` degraded while they arrive, ok again at the autopilot's
first message :data:`ALERT_HOLD_S` after the last one; the counts stay) and logged; a message
with a value the companion reads that is non-finite or out of bounds (``companion.mavlink.edge``)
is dropped before anything else sees it, counted per type (``values_rejected``) and reported
(``autopilot_values``, degraded the same way); a message whose ``time_boot_ms``
does not fit the autopilot's boot clock is dropped and counted (``time_anomalies``), and only a
confirmed new, earlier clock is a reboot (``autopilot_reboots``; the clock is kept across link
loss). With a signing key, everything sent is signed and only correctly signed messages are taken
(``companion.mavlink.signing``): the others are counted (``unsigned_rejected``, ``bad_signatures``),
not as parse errors.

An autopilot that merely stops talking (hung, paused, rebooting on a serial line) makes the
link *lost* (health, ``connected``) but the port stays open: closing a TCP connection to a
paused ArduPilot SITL would only make it fail when it resumes. Bytes that do not parse are
counted (``parse_errors``) and skipped.

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
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")  # before the first pymavlink import, which reads it
from pymavlink import mavutil  # noqa: E402,F401 (the mode tables, for autopilot.py)
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from companion import clock  # noqa: E402
from companion.config import MavlinkConfig, VehicleConfig  # noqa: E402
from companion.health import Alert, Health, State, often  # noqa: E402
from companion.mavlink.edge import BOUNDS, rejection  # noqa: E402
from companion.mavlink.signing import is_refused, require_signatures  # noqa: E402
from companion.mavlink.transport import Transport, TransportClosed, open_transport  # noqa: E402
from companion.mavlink.trust import BootClock, Heartbeat, Identity, IdentityLock, Stamp, autopilot_name  # noqa: E402
from companion.schema import read_regular_file  # noqa: E402

log = logging.getLogger("companion.mavlink")

CONNECT_TIMEOUT_S = 2.0  # a TCP peer that does not accept within this is retried later
ALERT_HOLD_S = 1.0  # autopilot_identity / autopilot_values stay degraded this long after the last refusal
REOPEN_BACKOFF_S = (0.25, 2.0)  # first and longest wait before reopening an ended port
SIGNING_LINK_ID = 1  # the link id in the daemon's signatures

Handler = Callable[[mavlink.MAVLink_message], None]


async def run_per_connection(connected: asyncio.Event, body: Callable[[], Awaitable[None]]) -> None:
    """Run ``body`` after every (re)connection (``connected`` set, e.g. by :meth:`MavlinkLink.on_connect`);
    a new connection cancels a body still running and starts it again at once: what it waits for
    (an ACK, a retry) belongs to the previous connection."""
    while True:
        await connected.wait()
        connected.clear()
        task = asyncio.ensure_future(body())
        reconnected = asyncio.ensure_future(connected.wait())
        try:
            await asyncio.wait({task, reconnected}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            reconnected.cancel()
            if not task.done():
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
        if task.done() and not task.cancelled() and task.exception() is not None:
            connected.set()  # the supervisor's restart of the caller runs the body again for this connection
            raise task.exception()  # type: ignore[misc]


@dataclass
class LinkStats:
    messages_rx: int = 0
    messages_tx: int = 0
    nonfinite_dropped: int = 0
    send_errors: int = 0
    parse_errors: int = 0  # undecodable bytes or frames (noise, a wrong baud rate, a hostile peer)
    reconnects: int = 0
    autopilot_reboots: int = 0  # confirmed: a new, earlier boot clock (companion.mavlink.trust)
    other_components_rx: int = 0  # not passed on: other compids of its sysid (gimbal, camera), non-autopilot HEARTBEATs
    identity_changed: int = 0  # HEARTBEATs from the autopilot's ids with another autopilot type or MAV_TYPE: refused
    identity_impostors: int = 0  # autopilot-looking HEARTBEATs from the autopilot's sysid, another compid: refused
    time_anomalies: int = 0  # messages dropped: their time_boot_ms does not fit the autopilot's boot clock
    acks_ignored: int = 0  # COMMAND_ACKs for no pending command of ours, or addressed to someone else (Commander)
    unsigned_rejected: int = 0  # signing on: unsigned messages refused
    bad_signatures: int = 0  # signing on: wrong key, or a replayed / old signing timestamp
    values_rejected: dict[str, int] = field(default_factory=dict)  # per type: a value read was non-finite or out of bounds


SIGNING_KEY_MAX_BYTES = 1024  # a key file is 32 or 64 bytes, with room for whitespace around a hex key


def load_signing_key(path: Path) -> bytes:
    """The 32-byte MAVLink 2 signing secret from a file (32 raw bytes or 64 hex characters).

    OSError if the file is not a regular file of at most :data:`SIGNING_KEY_MAX_BYTES` (a FIFO or
    /dev/zero is refused, never read); ValueError, naming the file, if it holds anything else.
    """
    data = read_regular_file(path, SIGNING_KEY_MAX_BYTES)
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
    """Names of the message's float fields holding NaN or infinity.

    Every message sent passes here: the sum of its numbers is tested first (a NaN or an infinity
    makes it non-finite; values a MAVLink field can carry, below 3.4e38, cannot overflow it), and
    the fields are named one by one only when it is not finite."""
    total = 0.0
    for name in msg.get_fieldnames():
        value = getattr(msg, name)
        if isinstance(value, float):
            total += value
        elif isinstance(value, (list, tuple)):  # numeric arrays (char arrays are str or bytes)
            try:
                total += sum(value)
            except TypeError:  # not all numbers (a hand-built message): checked one by one below
                total = math.nan
    if math.isfinite(total):
        return []
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
        self.autopilot: str | None = None  # "ArduPilot", "PX4" or None until a HEARTBEAT locks the identity
        self.last_heartbeat: float | None = None  # daemon clock, seconds
        self._transport: Transport | None = None
        self._codec: mavlink.MAVLink | None = None
        self._ended = asyncio.Event()  # the open port ended (EOF, I/O error): reopen it
        self._heartbeats = 0  # autopilot HEARTBEATs received, ever
        self._handlers: dict[str, list[Handler]] = defaultdict(list)
        self._addressed: list[Handler] = []  # COMMAND_LONGs addressed to this companion, from anyone
        self._on_connect: list[Callable[[], None]] = []
        self._observers: list[Callable[[str, mavlink.MAVLink_message], None]] = []
        self._connected = False
        self._paused = False  # lockstep: reading stops at a tick until the loop is idle
        self._ticked = asyncio.Event()  # lockstep: the vehicle's first tick arrived
        self._tick_batch: list[mavlink.MAVLink_message] = []  # lockstep: read, not yet dispatched
        self._identity = IdentityLock(ids.autopilot_sysid, ids.autopilot_compid)
        self._identity_alert = Alert(health, "autopilot_identity", ALERT_HOLD_S)
        self._values_alert = Alert(health, "autopilot_values", ALERT_HOLD_S)
        self._boot_clock = BootClock()  # kept across link loss: a link back on an earlier clock is a reboot
        self._stamped_since_connect = False  # a boot time fitted the clock since the last (re)connection
        self._signing_streams: dict[tuple[int, int, int], int] = {}  # newest signing timestamp per stream, all ports
        self.health.report("link", State.LOST, "not connected yet")
        self.subscribe("HEARTBEAT", self._on_heartbeat)
        self.subscribe("TIMESYNC", self._on_timesync)

    # -- public API -------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """True while autopilot HEARTBEATs arrive within ``link_timeout_s``."""
        return self._connected

    def subscribe(self, msg_type: str, handler: Handler) -> None:
        """Call ``handler(msg)`` for every message of ``msg_type`` from the autopilot (its sysid and
        compid; HEARTBEATs with its locked identity; boot times that fit its clock)."""
        self._handlers[msg_type].append(handler)

    def on_addressed_command(self, handler: Handler) -> None:
        """Call ``handler(msg)`` for every COMMAND_LONG addressed to this companion (its sysid and
        compid), whoever sent it: the autopilot routes a ground station's commands to us. The
        handler decides whom it obeys (companion.mavlink.inbound); with signing, only signed ones
        arrive."""
        self._addressed.append(handler)

    def on_connect(self, callback: Callable[[], None]) -> None:
        """Call ``callback()`` whenever the autopilot is (re)found: first contact, link regained, reboot."""
        self._on_connect.append(callback)

    def observe(self, callback: Callable[[str, mavlink.MAVLink_message], None]) -> None:
        """Call ``callback("in", msg)`` for every message received that parsed (from anyone, before
        the trust checks) and ``callback("out", msg)`` for every message sent (the flight recorder)."""
        self._observers.append(callback)

    def send(self, msg: mavlink.MAVLink_message) -> bool:
        """Send ``msg`` to the autopilot; False if it was dropped (no port, non-finite field, I/O error)."""
        bad = nonfinite_fields(msg)
        if bad:
            self.stats.nonfinite_dropped += 1
            log.error("dropped %s with non-finite %s: never sent to the autopilot", msg.get_type(), ", ".join(bad))
            return False
        if self._codec is None or self._transport is None:
            return False
        dropped_before = self._transport.dropped_writes
        try:
            self._codec.send(msg)
        except TransportClosed as exc:
            self.stats.send_errors += 1
            self._port_ended(f"send {msg.get_type()}: {exc}")
            return False
        if self._transport.dropped_writes != dropped_before:
            self.stats.send_errors += 1  # the kernel's buffer is full (a stalled peer): dropped whole
            return False
        self.stats.messages_tx += 1
        for observer in self._observers:
            observer("out", msg)
        return True

    def target(self) -> tuple[int, int]:
        """(target_system, target_component) of the autopilot."""
        return self.ids.autopilot_sysid, self.ids.autopilot_compid

    async def run(self) -> None:
        """Open the port (with backoff), then read, heartbeat and watch the link until cancelled.

        A port that ends is reopened after a wait that doubles from ``REOPEN_BACKOFF_S[0]`` to
        ``REOPEN_BACKOFF_S[1]``; it starts short again once the autopilot has answered on a port.
        """
        backoff = REOPEN_BACKOFF_S[0]
        while True:
            try:
                await self._open()
            except (OSError, ValueError, TimeoutError) as exc:
                reason = str(exc) or type(exc).__name__
                self.health.report("link", State.LOST, f"cannot open {self.url}: {reason}")
                log.warning("cannot open %s: %s; retrying in %.2g s", self.url, reason, backoff)
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, REOPEN_BACKOFF_S[1])
                continue
            heartbeats_before = self._heartbeats
            try:
                await self._serve()
            finally:
                self._close()
            if self._heartbeats != heartbeats_before:
                backoff = REOPEN_BACKOFF_S[0]
            self.stats.reconnects += 1
            log.warning("reopening the port %s in %.2g s", self.url, backoff)
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, REOPEN_BACKOFF_S[1])

    # -- connection lifecycle ---------------------------------------------------------------

    async def _open(self) -> None:
        transport = await open_transport(self.url, CONNECT_TIMEOUT_S)
        codec = mavlink.MAVLink(transport, srcSystem=self.ids.sysid, srcComponent=self.ids.compid)
        codec.robust_parsing = True
        if self.signing_key is not None:
            require_signatures(codec, self.signing_key, SIGNING_LINK_ID, self._signature_refused,
                               self._signing_streams)
        self._transport, self._codec = transport, codec
        self._ended.clear()
        asyncio.get_running_loop().add_reader(transport.fd, self._on_readable)
        log.info("MAVLink port open: %s (sysid %d compid %d)", self.url, self.ids.sysid, self.ids.compid)

    def _close(self) -> None:
        transport, self._transport, self._codec = self._transport, None, None
        if transport is None:
            return
        try:
            asyncio.get_running_loop().remove_reader(transport.fd)
        except (ValueError, OSError):
            pass
        transport.close()
        self._set_connected(False, "port closed")

    def _port_ended(self, reason: str) -> None:
        """The port failed (EOF, I/O error): stop reading; :meth:`run` reopens it."""
        if self._transport is not None and not self._ended.is_set():
            log.warning("%s: %s", self.url, reason)
            try:
                asyncio.get_running_loop().remove_reader(self._transport.fd)
            except (ValueError, OSError):
                pass
            self._ended.set()

    async def _serve(self) -> None:
        """Heartbeat and link watch until the port ends."""
        period = 1.0 / self.cfg.heartbeat_hz
        while not self._ended.is_set():
            self._send_heartbeat()
            now = clock.now()
            if self._connected and now - (self.last_heartbeat or 0.0) > self.cfg.link_timeout_s:
                self._set_connected(False, f"no autopilot HEARTBEAT for {self.cfg.link_timeout_s:g} s")
            ended = asyncio.ensure_future(self._ended.wait())
            beat = asyncio.ensure_future(self._until_next_heartbeat(period))
            try:
                await asyncio.wait({ended, beat}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                ended.cancel()
                beat.cancel()

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
        transport, codec = self._transport, self._codec
        if transport is None or codec is None or self._paused or self._ended.is_set():
            return
        try:
            data = transport.read()
        except TransportClosed as exc:
            self._port_ended(str(exc))
            return
        if not data:
            return
        try:
            messages = codec.parse_buffer(data) or []
        except Exception as exc:  # pymavlink raises more than MAVError on crafted frames
            self.stats.parse_errors += 1
            log.debug("undecodable bytes from %s: %s", self.url, exc)
            codec.buf, codec.buf_index = bytearray(), 0
            return
        lockstep = isinstance(asyncio.get_running_loop(), clock.LockstepEventLoop)
        for msg in messages:
            if lockstep:
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
            if not is_refused(msg):  # a refused signature is counted by _signature_refused
                self.stats.parse_errors += 1
            return
        self.stats.messages_rx += 1
        for observer in self._observers:
            observer("in", msg)
        if (msg_type == "COMMAND_LONG" and msg.target_system == self.ids.sysid
                and msg.target_component == self.ids.compid):
            handlers = self._addressed
        elif msg.get_srcSystem() != self.ids.autopilot_sysid or not self._from_autopilot(msg):
            return
        else:
            handlers = self._handlers.get(msg_type, ())
        for handler in handlers:
            try:
                handler(msg)
            except Exception:
                log.exception("handler for %s failed", msg_type)

    # -- trust: only the autopilot is listened to (companion.mavlink.trust) -------------------

    def _from_autopilot(self, msg: mavlink.MAVLink_message) -> bool:
        """Whether a message from the autopilot's sysid is the autopilot's: a HEARTBEAT with its locked
        identity, anything else from its compid with a boot time (if any) that fits its clock.
        What is not is counted (and a conflicting identity reported)."""
        if msg.get_type() == "HEARTBEAT":
            trusted = self._trusted_heartbeat(msg)
        elif msg.get_srcComponent() != self.ids.autopilot_compid:
            self.stats.other_components_rx += 1
            return False
        else:
            trusted = self._values_ok(msg) and self._fits_boot_clock(msg)
        if trusted and self._identity_alert.active:
            self._identity_ok()
        return trusted

    def _values_ok(self, msg: mavlink.MAVLink_message) -> bool:
        """Whether the values the companion reads from ``msg`` are usable (companion.mavlink.edge);
        a message that is not is counted per type and reported, and its boot time never taken."""
        msg_type = msg.get_type()
        problem = rejection(msg)
        if problem is None:
            if msg_type in BOUNDS and (self._values_alert.active or self.health.get("autopilot_values") is None):
                self._values_alert.good("every value read is finite and within bounds")
            return True
        rejected = self.stats.values_rejected
        rejected[msg_type] = rejected.get(msg_type, 0) + 1
        total = sum(rejected.values())
        self._values_alert.bad(f"{total} messages dropped, last {msg_type}: {problem}")
        if often(total):
            log.error("dropped %s from the autopilot: %s (%d so far)", msg_type, problem, total)
        return False

    def _trusted_heartbeat(self, msg: mavlink.MAVLink_message) -> bool:
        verdict = self._identity.judge(msg)
        if verdict is Heartbeat.OTHER:
            self.stats.other_components_rx += 1
        elif verdict is not Heartbeat.AUTOPILOT:
            self._identity_conflict(verdict, msg)
        elif self.autopilot is None:
            self._identity_locked()
            self._identity_ok()
        return verdict is Heartbeat.AUTOPILOT

    def _identity_ok(self) -> None:
        """The autopilot spoke: identity ok, unless a conflict came within ALERT_HOLD_S."""
        refused = self.stats.identity_changed + self.stats.identity_impostors
        history = f"; {refused} conflicting HEARTBEATs refused before" if refused else ""
        self._identity_alert.good(f"locked: {self._identity.locked}{history}")

    def _identity_locked(self) -> None:
        identity = self._identity.locked
        assert identity is not None
        self.autopilot = autopilot_name(identity.autopilot)
        log.info("autopilot detected: %s; its identity is locked for the life of this process", identity)

    def _identity_conflict(self, verdict: Heartbeat, msg: mavlink.MAVLink_message) -> None:
        """A HEARTBEAT claiming to be the autopilot with another identity: counted, reported, logged; not obeyed."""
        if verdict is Heartbeat.CHANGED:
            self.stats.identity_changed += 1
        else:
            self.stats.identity_impostors += 1
        count = self.stats.identity_changed + self.stats.identity_impostors
        claim = f"{Identity.of(msg)}: {verdict.value}"
        self._identity_alert.bad(f"{count} HEARTBEATs refused, last {claim}")
        if often(count):
            locked = self._identity.locked
            log.warning("refused a HEARTBEAT from %s (%d so far); the autopilot is %s. Its identity is locked for "
                        "the life of this process: if the autopilot really changed (new firmware, another vehicle), "
                        "restart the companion", claim, count,
                        f"locked to {locked}" if locked else "not found yet")

    def _fits_boot_clock(self, msg: mavlink.MAVLink_message) -> bool:
        """Whether the message's ``time_boot_ms`` (if it has one) fits the autopilot's boot clock; a
        confirmed new, earlier clock is a reboot (counted; a new connection for the on_connect
        callbacks unless one was announced since the last boot time, e.g. when the link came back)."""
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is None:
            return True
        before = self._boot_clock.ms
        stamp = self._boot_clock.observe(msg.get_type(), boot_ms, clock.now())
        if stamp is Stamp.DROPPED:
            self.stats.time_anomalies += 1
            if often(self.stats.time_anomalies):
                log.warning("dropped %s at boot time %d ms: off the autopilot's clock at %s ms (%d so far)",
                            msg.get_type(), boot_ms, before, self.stats.time_anomalies)
            return False
        if stamp is Stamp.REBOOT:
            self.stats.autopilot_reboots += 1
            log.warning("autopilot rebooted (its boot clock restarted: %d ms after %s ms)", boot_ms, before)
            if self._connected and self._stamped_since_connect:
                self._fire_on_connect()
        elif stamp is Stamp.JUMP:
            log.warning("the autopilot's boot clock jumped ahead: %d ms after %s ms", boot_ms, before)
        self._stamped_since_connect = self._connected
        return True

    def _signature_refused(self, signed: bool) -> None:
        """Signing on: a message that was unsigned (``signed`` False) or badly signed was refused."""
        if signed:
            self.stats.bad_signatures += 1
        else:
            self.stats.unsigned_rejected += 1
        count = self.stats.bad_signatures + self.stats.unsigned_rejected
        if often(count):
            log.warning("refused %s message on %s (%d unsigned, %d badly signed so far): is the key the autopilot's?",
                        "a badly signed (wrong key, replayed or old timestamp)" if signed else "an unsigned",
                        self.url, self.stats.unsigned_rejected, self.stats.bad_signatures)

    # -- built-in handlers ------------------------------------------------------------------

    def _on_heartbeat(self, msg: mavlink.MAVLink_message) -> None:
        self.last_heartbeat = clock.now()
        self._heartbeats += 1
        if not self._connected:
            self._set_connected(True, f"{self.autopilot} heartbeat")

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
            self._stamped_since_connect = False
            self._fire_on_connect()
        else:
            self.health.report("link", State.LOST, reason)

    def _fire_on_connect(self) -> None:
        for callback in self._on_connect:
            try:
                callback()
            except Exception:
                log.exception("on_connect callback failed")
