"""The nav loop: the fused-output cycle (50 Hz by default) that every pipeline plugs into.

Each cycle at daemon time ``now``: step every pipeline (plain numpy objects, no I/O); offer
their poses to the source selection and forward the selected one (``on_pose``: the estimate
output to the autopilot); hand range estimates (``on_range``: DISTANCE_SENSOR) and attitude
estimates (``on_attitude``: the cross-check) on; publish the forwarded pose on telemetry;
record timings; beat the watchdog gate (systemd keeps the service alive only while this loop
turns).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion.messages import AttitudeEstimate, PoseEstimate, RangeEstimate
from companion.pipeline import Pipeline
from companion.sdnotify import WatchdogGate
from companion.selection import SourceSelector
from companion.timing import Timings


@dataclass
class NavOutputs:
    """Where the loop hands its results (the daemon wires these to the link and telemetry)."""

    pose: Callable[[PoseEstimate], None]  # the selected pose, to the autopilot
    range: Callable[[RangeEstimate], None]
    attitude: Callable[[AttitudeEstimate], None]
    publish: Callable[[str, dict], None]  # telemetry: (stream, payload)


class NavLoop:
    """Runs the pipelines at ``rate_hz`` on the daemon clock."""

    def __init__(self, pipelines: list[Pipeline], selector: SourceSelector | None, outputs: NavOutputs,
                 gate: WatchdogGate, rate_hz: float, clock: Callable[[], float]) -> None:
        self.pipelines = pipelines
        self.selector = selector
        self.outputs = outputs
        self.gate = gate
        self.rate_hz = rate_hz
        self.clock = clock
        self.jitter_ms = Timings()

    @property
    def last_estimate(self) -> PoseEstimate | None:
        """The active source's newest pose (what missions fly on)."""
        return self.selector.current if self.selector is not None else None

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
        poses: dict[str, PoseEstimate] = {}
        for pipeline in self.pipelines:
            for estimate in pipeline.step(now):
                if isinstance(estimate, PoseEstimate):
                    poses[estimate.source] = estimate
                    if self.selector is not None:
                        self.selector.offer(estimate, now)
                elif isinstance(estimate, RangeEstimate):
                    self.outputs.range(estimate)
                else:
                    self.outputs.attitude(estimate)
        if self.selector is not None:
            chosen = self.selector.select(now, poses)
            if chosen is not None:
                self._forward(chosen)
        self.gate.beat()

    def _forward(self, estimate: PoseEstimate) -> None:
        self.outputs.pose(estimate)  # drops and reports a non-finite one
        self.outputs.publish("pose", {
            "position_ned_m": estimate.position_ned, "euler_rad": estimate.euler_rad,
            "velocity_ned_mps": estimate.velocity_ned,
            "position_variance_m2": np.diag(estimate.pose_covariance)[:3],
            "yaw_variance_rad2": float(estimate.pose_covariance[5, 5]),
            "t_capture": estimate.t_capture, "source": estimate.source,
        })
