"""Sensor driver abstraction: one frontend for every sensor, one backend per device, simulation
or recording (like ArduPilot's AP_RangeFinder: the frontend owns health, counters and recovery;
a backend only talks to its device, its simulation or its recording).

A backend implements :class:`Backend`: ``open()``, ``read()`` returning the next message of its
kind (:class:`~companion.messages.Scan`, ``Frame``, ``ImuSample``, ``GnssFix``), ``close()``.
It registers itself with :func:`companion.plugins.register_backend`. It signals trouble with
exceptions:

- :class:`CorruptFrame`: one frame was bad (checksum, truncated block, error status). The
  frontend counts it and reads on; nothing else is lost.
- ``OSError`` (including pyserial's SerialException, ConnectionError, EOF as
  :class:`DeviceLost`): the device is gone. The frontend closes it, reports the sensor lost
  and reopens with backoff (0.25 s doubling to 1 s; reset once data flows again) until it
  comes back.
- :class:`EndOfData`: a replay has no more data (the frontend stops, health says why).

:class:`SensorDriver` is the frontend; it hands every good message to each subscriber (the
pipelines that consume the sensor, in subscription order) and is run by the daemon's supervisor
as one task per sensor. A decoded message that its kind's check (drivers/checks.py) refuses, a
non-finite value or a capture time not after the previous one, is dropped and counted per
reason (``DriverStats.rejected``): no pipeline sees it.
"""

from __future__ import annotations

import asyncio
import logging
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from companion.health import Health, State, often

log = logging.getLogger("companion.drivers")

MIN_BACKOFF_S = 0.25
MAX_BACKOFF_S = 1.0  # a replugged scanner is found within this (an open that fails is cheap)
LOG_EVERY_ATTEMPTS = 30  # while it stays lost, one warning per this many failed reopens (the others: debug)


class CorruptFrame(Exception):
    """One frame could not be decoded; the next one may be fine."""


class DeviceLost(OSError):
    """The device stopped answering or closed the connection."""


class EndOfData(Exception):
    """A replay has delivered its last message."""


M = TypeVar("M")


class Backend(ABC, Generic[M]):
    """A source of one sensor's messages: a device, a simulation or a recording."""

    description: str = "sensor"

    @abstractmethod
    async def open(self) -> None:
        """Connect and start streaming; raise OSError if the device is not there."""

    @abstractmethod
    async def read(self) -> M:
        """The next message; raise CorruptFrame, OSError/DeviceLost or EndOfData."""

    @abstractmethod
    async def close(self) -> None:
        """Stop streaming and release the device; never raises."""


class PushedMessages(Generic[M]):
    """A bounded queue between a callback that pushes messages (the MAVLink link's dispatch, for the
    sensors the autopilot carries) and a backend's ``read()``; the oldest are dropped when a slow
    reader lets it fill (counted in ``overflowed``)."""

    def __init__(self, size: int) -> None:
        self._queue: deque[M] = deque(maxlen=size)
        self._arrived = asyncio.Event()
        self.overflowed = 0

    def push(self, message: M) -> None:
        self.overflowed += len(self._queue) == self._queue.maxlen
        self._queue.append(message)
        self._arrived.set()

    def clear(self) -> None:
        self._queue.clear()

    async def get(self, timeout_s: float, what: str) -> M:
        """The oldest message; DeviceLost("no WHAT for ... s") when none arrives for ``timeout_s``."""
        while not self._queue:
            self._arrived.clear()
            try:
                async with asyncio.timeout(timeout_s):  # no task per wait, unlike wait_for
                    await self._arrived.wait()
            except TimeoutError:
                raise DeviceLost(f"no {what} for {timeout_s:g} s") from None
        return self._queue.popleft()


@dataclass
class DriverStats:
    messages: int = 0  # handed to the subscribers
    corrupt_frames: int = 0
    rejected: dict[str, int] = field(default_factory=dict)  # decoded but unusable, per reason
    reconnects: int = 0  # losses after data had flowed (an opened device that never sent is not one)
    last_error: str | None = None


Check = Callable[[M, "float | None"], "str | None"]  # (message, previous capture time) -> problem or None


class SensorDriver(Generic[M]):
    """Frontend for one sensor: recovery, counters and health around a backend.

    ``check(message, previous_t)`` says why a decoded message must not reach a pipeline (None:
    it may); ``stamp(message)`` is its capture time on the daemon clock, s.
    """

    def __init__(self, name: str, backend: Backend[M], health: Health, check: Check,
                 stamp: Callable[[M], float]) -> None:
        self.name = name
        self.backend = backend
        self.health = health
        self.check = check
        self.stamp = stamp
        self.subscribers: list[Callable[[M], None]] = []
        self.stats = DriverStats()
        self._component = f"sensor:{name}"
        self._backoff = MIN_BACKOFF_S  # wait before the next open after a loss, s
        self._attempts = 0  # losses and failed reopens since data last flowed (for the log's rate)
        self._last_t: float | None = None  # capture time of the last message handed on, daemon clock s
        self._streamed = False  # a message arrived since the backend was last opened

    def subscribe(self, handler: Callable[[M], None]) -> None:
        """Hand every good message to ``handler`` (called on the event loop; it must not block)."""
        self.subscribers.append(handler)

    async def run(self) -> None:
        """Read forever (until cancelled or a replay ends), reopening the device when it drops."""
        while True:
            try:
                await self.backend.open()
            except OSError as exc:
                await self._lost(f"cannot open {self.backend.description}: {exc}")
                continue
            self.health.report(self._component, State.OK, f"{self.backend.description} streaming")
            self._last_t = None  # a reopened device's clock is mapped afresh
            self._streamed = False
            try:
                reason = await self._read_until_lost()
            except EndOfData:
                self.health.report(self._component, State.LOST, "replay finished")
                await asyncio.Event().wait()  # done; stay quiet until cancelled
            finally:
                await self.backend.close()
            self.stats.reconnects += self._streamed  # lost after data flowed (not: nothing ever came)
            await self._lost(reason)

    async def _read_until_lost(self) -> str:
        """Read until the device is lost; returns why."""
        while True:
            try:
                message = await self.backend.read()
            except CorruptFrame as exc:
                self.stats.corrupt_frames += 1
                self.stats.last_error = str(exc)
                log.debug("%s: corrupt frame skipped: %s", self.name, exc)
                continue
            except OSError as exc:
                return f"{self.backend.description} lost: {exc}"
            self._backoff, self._attempts = MIN_BACKOFF_S, 0  # data flows: the next loss starts afresh
            self._streamed = True
            problem = self.check(message, self._last_t)
            if problem is not None:
                self._reject(problem)
                continue
            self._last_t = self.stamp(message)
            self.stats.messages += 1
            self.health.report(self._component, State.OK, f"{self.backend.description} streaming")
            for handler in self.subscribers:
                handler(message)

    def _reject(self, problem: str) -> None:
        rejected = self.stats.rejected
        rejected[problem] = rejected.get(problem, 0) + 1
        self.health.report(self._component, State.DEGRADED, f"dropped: {problem}")
        if often(rejected[problem]):
            log.error("%s: message dropped: %s (%d so far)", self.name, problem, rejected[problem])

    async def _lost(self, reason: str) -> None:
        """Report the loss, then wait the backoff before the next open (doubling each time)."""
        self.stats.last_error = reason
        self.health.report(self._component, State.LOST, reason)
        self._attempts += 1
        level = logging.WARNING if self._attempts % LOG_EVERY_ATTEMPTS == 1 else logging.DEBUG
        log.log(level, "%s: %s (attempt %d); retrying every %.2g s at most", self.name, reason, self._attempts,
                MAX_BACKOFF_S)
        await asyncio.sleep(self._backoff)
        self._backoff = min(2 * self._backoff, MAX_BACKOFF_S)
