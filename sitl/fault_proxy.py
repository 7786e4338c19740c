"""A MAVLink UDP proxy between the daemon and the SITL vehicle that can break the link on purpose.

The fault suite (``companion experiment faults``, sitl/faults.py) points the daemon's
``udpout`` at :attr:`FaultProxy.port` and the proxy forwards every datagram, unchanged, to the
vehicle's ``udpin`` port and back. On command it

- drops everything both ways for a while (:meth:`FaultProxy.block`: a lost radio link),
- sends the daemon messages it forges as if from the autopilot (:meth:`FaultProxy.inject`:
  NaN / infinity storms, spoofed heartbeats, forged acknowledgements, time going backwards),
- sends the daemon raw bytes (:meth:`FaultProxy.inject_bytes`: line noise),

and it watches what the daemon sends the autopilot: every message with a NaN or infinity in a
float field is counted (:attr:`ProxyCounters.nonfinite_sent`: the fault suite's "non-finite
values sent", measured outside the daemon), and the arrival time of every
VISION_POSITION_ESTIMATE is kept (the estimate reaching the autopilot, the suite's recovery
signal). A datagram that cannot be sent (ENOBUFS, ECONNREFUSED while the vehicle is dead) is
dropped and counted (:attr:`ProxyCounters.send_errors`), as a radio would lose it: the
forwarding thread goes on. Loopback only; one daemon, one vehicle. Times are
``time.monotonic()`` seconds.
"""

from __future__ import annotations

import logging
import os
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from companion.mavlink.link import nonfinite_fields  # noqa: E402

log = logging.getLogger("companion.fault_proxy")

DATAGRAM_MAX = 65535


@dataclass
class ProxyCounters:
    """What the proxy saw; read under :attr:`FaultProxy.lock`."""

    to_vehicle: int = 0  # datagrams forwarded daemon -> vehicle
    to_daemon: int = 0  # datagrams forwarded vehicle -> daemon
    blocked: int = 0  # datagrams dropped by block()
    injected: int = 0  # forged messages sent to the daemon
    nonfinite_sent: int = 0  # daemon -> vehicle messages with a NaN or infinity in a float field
    send_errors: int = 0  # datagrams that could not be sent (either way, injected ones included): dropped
    estimates: deque[float] = field(default_factory=lambda: deque(maxlen=20000))  # VISION_POSITION_ESTIMATE arrivals


class FaultProxy:
    """Daemon <-> proxy (127.0.0.1:``port``) <-> vehicle (``vehicle_port``); see the module docstring."""

    def __init__(self, vehicle_port: int, autopilot_ids: tuple[int, int] = (1, 1)) -> None:
        self.vehicle = ("127.0.0.1", vehicle_port)
        self.lock = threading.Lock()
        self.counters = ProxyCounters()
        self._front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the daemon's side
        self._front.bind(("127.0.0.1", 0))
        self.port: int = self._front.getsockname()[1]
        self._back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the vehicle's side
        self._back.bind(("127.0.0.1", 0))
        self._daemon: tuple[str, int] | None = None
        self._blocked_until = 0.0
        self._forger = mavlink.MAVLink(None, srcSystem=autopilot_ids[0], srcComponent=autopilot_ids[1])
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fault-proxy", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._front.close()
        self._back.close()

    # -- faults ---------------------------------------------------------------------------------

    def block(self, seconds: float) -> None:
        """Drop every datagram, both ways, for ``seconds`` from now."""
        with self.lock:
            self._blocked_until = time.monotonic() + seconds

    def inject(self, messages: Iterable[mavlink.MAVLink_message], src: tuple[int, int] | None = None) -> int:
        """Send ``messages`` to the daemon as if from the autopilot (or from ``src`` = (sysid, compid));
        how many went out (none before the daemon has spoken)."""
        forger = self._forger if src is None else mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
        sent = 0
        for msg in messages:
            if self.inject_bytes(msg.pack(forger, force_mavlink1=False)):
                sent += 1
        with self.lock:
            self.counters.injected += sent
        return sent

    def inject_bytes(self, data: bytes) -> bool:
        """Send ``data`` to the daemon as one datagram from the autopilot's port."""
        if self._daemon is None:
            return False
        return self._send(self._front, data, self._daemon)

    # -- observation ----------------------------------------------------------------------------

    def last_estimate_age(self, now: float | None = None) -> float:
        """Seconds since the last VISION_POSITION_ESTIMATE reached the proxy (inf: none yet)."""
        now = time.monotonic() if now is None else now
        with self.lock:
            return now - self.counters.estimates[-1] if self.counters.estimates else float("inf")

    def longest_estimate_gap(self, start: float, end: float) -> float:
        """The longest time (s) without a VISION_POSITION_ESTIMATE between ``start`` and ``end``."""
        with self.lock:
            times = [t for t in self.counters.estimates if start <= t <= end]
        edges = [start, *times, end]
        return max(b - a for a, b in zip(edges, edges[1:]))

    # -- the forwarding thread ------------------------------------------------------------------

    def _run(self) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self._front, selectors.EVENT_READ)
            selector.register(self._back, selectors.EVENT_READ)
            while not self._stop.is_set():
                for key, _ in selector.select(timeout=0.1):
                    try:
                        data, sender = key.fileobj.recvfrom(DATAGRAM_MAX)  # type: ignore[union-attr]
                    except OSError:
                        continue
                    try:
                        if key.fileobj is self._front:
                            self._from_daemon(data, sender)
                        else:
                            self._from_vehicle(data)
                    except Exception:  # a bug here must not end the link silently
                        log.exception("fault proxy: datagram dropped")

    def _send(self, sock: socket.socket, data: bytes, address: tuple[str, int]) -> bool:
        """``sock.sendto``; False (counted in ``send_errors``) if the OS refused it."""
        try:
            sock.sendto(data, address)
        except OSError as exc:
            with self.lock:
                self.counters.send_errors += 1
                errors = self.counters.send_errors
            if errors == 1 or errors % 100 == 0:
                log.warning("fault proxy: cannot send to %s:%d (%s); %d datagrams dropped so far",
                            *address, exc, errors)
            return False
        return True

    def _is_blocked(self) -> bool:
        with self.lock:
            blocked = time.monotonic() < self._blocked_until
            if blocked:
                self.counters.blocked += 1
            return blocked

    def _from_daemon(self, data: bytes, sender: tuple[str, int]) -> None:
        self._daemon = sender
        if self._is_blocked() or not self._send(self._back, data, self.vehicle):
            return
        now = time.monotonic()
        messages = self._parser.parse_buffer(data) or []
        with self.lock:
            self.counters.to_vehicle += 1
            for msg in messages:
                if msg.get_type() == "BAD_DATA":
                    continue
                if nonfinite_fields(msg):
                    self.counters.nonfinite_sent += 1
                elif msg.get_type() == "VISION_POSITION_ESTIMATE":
                    self.counters.estimates.append(now)

    def _from_vehicle(self, data: bytes) -> None:
        if self._daemon is None or self._is_blocked() or not self._send(self._front, data, self._daemon):
            return
        with self.lock:
            self.counters.to_daemon += 1
