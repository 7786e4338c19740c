"""Sensor driver abstraction: one frontend, one backend per device kind (like ArduPilot's
AP_RangeFinder: the frontend owns health, counters and recovery; a backend only talks to
its device, its simulation or its recording).

A backend implements :class:`ScanBackend`: ``open()``, ``read()`` returning the next
:class:`~drivers.scan.Scan`, ``close()``. It signals trouble with exceptions:

- :class:`CorruptFrame`: one frame was bad (checksum, truncated block, error status). The
  frontend counts it and reads on; nothing else is lost.
- ``OSError`` (including pyserial's SerialException, ConnectionError, EOF as
  :class:`DeviceLost`): the device is gone. The frontend closes it, reports the sensor lost
  and reopens with backoff (0.25 s doubling to 1 s; reset once scans flow again) until it
  comes back.
- :class:`EndOfData`: a replay has no more scans (the frontend stops, health says why).

:class:`LidarDriver` is the frontend; it hands every good scan to ``on_scan`` (the pipeline)
and is run by the daemon's supervisor as one task per sensor. A decoded scan with a non-finite
time, range or angle, or a capture time not after the previous one, is dropped and counted
per reason (``DriverStats.rejected_scans``, :func:`scan_problem`): no pipeline sees it.
"""

from __future__ import annotations

import asyncio
import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from companion.health import Health, State, often
from drivers.scan import Scan

log = logging.getLogger("companion.drivers")

MIN_BACKOFF_S = 0.25
MAX_BACKOFF_S = 1.0  # a replugged scanner is found within this (an open that fails is cheap)
LOG_EVERY_ATTEMPTS = 30  # while it stays lost, one warning per this many failed reopens (the others: debug)


class CorruptFrame(Exception):
    """One frame could not be decoded; the next one may be fine."""


class DeviceLost(OSError):
    """The device stopped answering or closed the connection."""


class EndOfData(Exception):
    """A replay has delivered its last scan."""


class ScanBackend(ABC):
    """A source of scans: a device, a simulation or a recording."""

    description: str = "scanner"

    @abstractmethod
    async def open(self) -> None:
        """Connect and start streaming; raise OSError if the device is not there."""

    @abstractmethod
    async def read(self) -> Scan:
        """The next scan; raise CorruptFrame, OSError/DeviceLost or EndOfData."""

    @abstractmethod
    async def close(self) -> None:
        """Stop streaming and release the device; never raises."""


@dataclass
class DriverStats:
    scans: int = 0
    corrupt_frames: int = 0
    rejected_scans: dict[str, int] = field(default_factory=dict)  # decoded but unusable, per reason (scan_problem)
    reconnects: int = 0
    last_error: str | None = None


def scan_problem(scan: Scan, previous_t: float | None) -> str | None:
    """Why a decoded scan must not reach a pipeline, or None: a non-finite capture time, range or
    angle (a backend bug, a corrupt replay), or a capture time not after the previous scan's."""
    if not math.isfinite(scan.t_capture):
        return "non-finite capture time"
    if previous_t is not None and scan.t_capture <= previous_t:
        return "capture time not after the previous scan's"
    if not (np.all(np.isfinite(scan.angles_rad)) and np.all(np.isfinite(scan.ranges_m[scan.valid]))):
        return "non-finite range or angle"
    return None


class LidarDriver:
    """Frontend for one scanner: recovery, counters and health around a backend."""

    def __init__(self, name: str, backend: ScanBackend, health: Health, on_scan: Callable[[Scan], None]) -> None:
        self.name = name
        self.backend = backend
        self.health = health
        self.on_scan = on_scan
        self.stats = DriverStats()
        self._component = f"sensor:{name}"
        self._backoff = MIN_BACKOFF_S  # wait before the next open after a loss, s
        self._attempts = 0  # losses and failed reopens since scans last flowed (for the log's rate)
        self._last_t: float | None = None  # capture time of the last scan handed on, daemon clock s

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
            try:
                reason = await self._read_until_lost()
            except EndOfData:
                self.health.report(self._component, State.LOST, "replay finished")
                await asyncio.Event().wait()  # done; stay quiet until cancelled
            finally:
                await self.backend.close()
            self.stats.reconnects += 1
            await self._lost(reason)

    async def _read_until_lost(self) -> str:
        """Read until the device is lost; returns why."""
        while True:
            try:
                scan = await self.backend.read()
            except CorruptFrame as exc:
                self.stats.corrupt_frames += 1
                self.stats.last_error = str(exc)
                log.debug("%s: corrupt frame skipped: %s", self.name, exc)
                continue
            except OSError as exc:
                return f"{self.backend.description} lost: {exc}"
            self._backoff, self._attempts = MIN_BACKOFF_S, 0  # scans flow: the next loss starts afresh
            problem = scan_problem(scan, self._last_t)
            if problem is not None:
                self._reject(problem)
                continue
            self._last_t = scan.t_capture
            self.stats.scans += 1
            self.health.report(self._component, State.OK, f"{self.backend.description} streaming")
            self.on_scan(scan)

    def _reject(self, problem: str) -> None:
        rejected = self.stats.rejected_scans
        rejected[problem] = rejected.get(problem, 0) + 1
        self.health.report(self._component, State.DEGRADED, f"scans dropped: {problem}")
        if often(rejected[problem]):
            log.error("%s: scan dropped: %s (%d so far)", self.name, problem, rejected[problem])

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
