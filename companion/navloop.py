"""The nav loop: the fused-output cycle (50 Hz by default) that every pipeline plugs into.

Each cycle at daemon time ``now``: step every pipeline (plain numpy objects, no I/O); offer
their poses to the source selection and forward the selected one (``on_pose``: the estimate
output to the autopilot); hand range estimates (``on_range``: DISTANCE_SENSOR) and attitude
estimates (``on_attitude``: the cross-check) on; publish the forwarded pose on telemetry;
record timings; beat the watchdog gate (systemd keeps the service alive only while this loop
turns). Periodic work elsewhere on the event loop (the mission's control step, telemetry) waits
for a cycle with :meth:`NavLoop.after_cycle` rather than on its own timer, so it never runs at a tick.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass

from typing import Any

import numpy as np

from companion import plugins
from companion.health import Health
from companion.messages import AttitudeEstimate, Estimate, PoseEstimate, RangeEstimate
from companion.pipeline import Pipeline, PipelineContext
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


CycleHook = Callable[[float, list[Estimate], PoseEstimate | None], None]


def build_pipelines(cfg: Any, health: Health, names: list[str] | None = None) -> list[Pipeline]:
    """The enabled pipelines of ``cfg`` (only ``names`` of them if given), built by the registry,
    in the order the config enables them. The daemon and ``companion replay`` both build them here."""
    ctx = PipelineContext(cfg, health)
    return [plugins.pipeline(name).build(section, ctx) for name, section in cfg.pipelines.enabled.items()
            if names is None or name in names]


def build_selector(cfg: Any, pipelines: list[Pipeline],
                   on_switch: Callable[[str | None, str | None, str], None] | None = None) -> SourceSelector | None:
    """The pose-source selection over ``pipelines.sources`` (None without a pose pipeline: missions
    then fly on the autopilot's own estimate)."""
    priority = cfg.source_priority()
    if not pipelines or not priority:
        return None
    p = cfg.pipelines
    extra = {} if on_switch is None else {"on_switch": on_switch}
    return SourceSelector(priority, p.source_timeout_s, p.source_return_s, p.source_max_sigma_m, **extra)


class NavLoop:
    """Runs the pipelines at ``rate_hz`` on the daemon clock. ``on_cycle``, if set, is called after
    each cycle with its time, every estimate the pipelines made in it and the pose forwarded (the
    flight recorder's hook; ``companion replay`` collects the replayed cycles with it)."""

    def __init__(self, pipelines: list[Pipeline], selector: SourceSelector | None, outputs: NavOutputs,
                 gate: WatchdogGate, rate_hz: float, clock: Callable[[], float]) -> None:
        self.on_cycle: CycleHook | None = None
        self.pipelines = pipelines
        self.selector = selector
        self.outputs = outputs
        self.gate = gate
        self.rate_hz = rate_hz
        self.clock = clock
        self.jitter_ms = Timings()
        self._waiters: list[tuple[float, asyncio.Future[None]]] = []  # (earliest tick, waiter): after_cycle()

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
            self._release_waiters(next_tick)

    async def after_cycle(self, due: float) -> None:
        """Return right after the first cycle that ticks at or after daemon time ``due`` (s; a tick
        up to half a period before it counts), or at ``due`` plus two periods if none has by then.

        Periodic work on the event loop (the mission's control step, telemetry) waits here instead
        of on a timer of its own: it then runs between two cycles, never at a tick, so the cycle
        wakes on time (a 1 ms control step whose timer fell just before the tick, at the same rate,
        made every tick of a flight late), and it sees the estimate the cycle has just made.
        """
        loop = asyncio.get_running_loop()
        waiter: asyncio.Future[None] = loop.create_future()
        entry = (due - 0.5 / self.rate_hz, waiter)
        self._waiters.append(entry)
        fallback = loop.call_at(due + 2.0 / self.rate_hz, _release, waiter)
        try:
            await waiter
        finally:
            fallback.cancel()
            if entry in self._waiters:
                self._waiters.remove(entry)

    def _release_waiters(self, tick: float) -> None:
        due = [entry for entry in self._waiters if entry[0] <= tick]
        for entry in due:
            self._waiters.remove(entry)
            _release(entry[1])

    def cycle(self, now: float) -> None:
        """One nav cycle at daemon time ``now``."""
        poses: dict[str, PoseEstimate] = {}
        made: list[Estimate] = []
        chosen = None
        for pipeline in self.pipelines:
            for estimate in pipeline.step(now):
                made.append(estimate)
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
        if self.on_cycle is not None:
            self.on_cycle(now, made, chosen)
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


def _release(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_result(None)
