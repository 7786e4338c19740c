"""The nav loop: the fused-output cycle (50 Hz by default) that every pipeline plugs into.

Each cycle: step every pipeline (plain numpy objects, no I/O), hand their estimates to the
estimate output, publish the pose on telemetry, record timings, and beat the watchdog gate:
systemd keeps the service alive only while this loop turns.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from typing import Protocol

import numpy as np

from companion.mavlink.estimate import EstimateSender, PoseEstimate
from companion.sdnotify import WatchdogGate
from companion.telemetry.publisher import TelemetryPublisher


class Pipeline(Protocol):
    """A navigation pipeline as the nav loop sees it."""

    name: str
    timings: dict[str, "Timings"]  # per stage, milliseconds (e.g. "lidar", "fusion")

    def step(self, now: float) -> PoseEstimate | None:
        """Advance to daemon time ``now`` (s); return a new estimate, or None if there is none."""


class Timings:
    """Bounded record of durations in milliseconds with median / p99."""

    def __init__(self, size: int = 6000) -> None:
        self._values: deque[float] = deque(maxlen=size)

    def add(self, ms: float) -> None:
        self._values.append(ms)

    def percentile(self, q: float) -> float | None:
        if not self._values:
            return None
        return float(np.percentile(np.fromiter(self._values, float), q))

    def summary(self) -> dict[str, float | None]:
        """{p50, p99, count}: both percentiles from one copy of the values (the status task calls
        this for every stage at telemetry.status_hz, on the event loop)."""
        if not self._values:
            return {"p50": None, "p99": None, "count": 0}
        p50, p99 = np.percentile(np.fromiter(self._values, float, len(self._values)), (50, 99))
        return {"p50": float(p50), "p99": float(p99), "count": len(self._values)}


class NavLoop:
    """Runs the pipelines at ``rate_hz`` on the daemon clock."""

    def __init__(self, pipelines: list[Pipeline], estimate: EstimateSender, telemetry: TelemetryPublisher,
                 gate: WatchdogGate, rate_hz: float, clock: Callable[[], float]) -> None:
        self.pipelines = pipelines
        self.estimate = estimate
        self.telemetry = telemetry
        self.gate = gate
        self.rate_hz = rate_hz
        self.clock = clock
        self.jitter_ms = Timings()
        self.last_estimate: PoseEstimate | None = None  # the newest with a finite position

    def stage_summaries(self) -> dict[str, dict[str, float | None]]:
        """{stage: {p50, p99, count}} over every pipeline's stages (ms)."""
        return {stage: timings.summary() for p in self.pipelines for stage, timings in p.timings.items()}

    async def run(self) -> None:
        period = 1.0 / self.rate_hz
        next_tick = self.clock()
        while True:
            next_tick += period
            delay = next_tick - self.clock()
            if delay > 0:
                await asyncio.sleep(delay)
            now = self.clock()
            self.jitter_ms.add(max(0.0, now - next_tick) * 1e3)
            if now - next_tick > 5 * period:
                next_tick = now  # we fell far behind (suspend, overload): do not burst to catch up
            self.cycle(now)

    def cycle(self, now: float) -> None:
        """One nav cycle at daemon time ``now``."""
        for pipeline in self.pipelines:
            estimate = pipeline.step(now)
            if estimate is not None:
                self.estimate.submit(estimate)  # drops and reports a non-finite one
                if np.all(np.isfinite(estimate.position_ned)):
                    self.last_estimate = estimate  # what missions fly on
                self.telemetry.publish("pose", {
                    "position_ned_m": estimate.position_ned, "euler_rad": estimate.euler_rad,
                    "velocity_ned_mps": estimate.velocity_ned,
                    "position_variance_m2": np.diag(estimate.pose_covariance)[:3],
                    "yaw_variance_rad2": float(estimate.pose_covariance[5, 5]),
                    "t_capture": estimate.t_capture, "source": estimate.source,
                })
        self.gate.beat()
