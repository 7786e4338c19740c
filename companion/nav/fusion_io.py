"""What a pose pipeline built around a :class:`~companion.nav.fusion.FusionFilter` does at its
edges each nav cycle: keep the IMU samples that arrived since the previous cycle and predict with
them (:class:`ImuFeed`), and turn the filter's state into what the pipeline may send
(:class:`FusedOutput`). The lidar and laser-dot pipelines share them.

Frames and units as in companion/nav/fusion.py: world LOCAL_NED, body FRD, radians, daemon-clock
seconds.
"""

from __future__ import annotations

from companion.health import Health, State
from companion.messages import ImuSample
from companion.nav.fusion import FusedState, FusionFilter


class ImuFeed:
    """The IMU samples a pipeline received since its previous nav cycle (oldest first), and the
    autopilot's newest attitude (roll, pitch, yaw rad of body FRD in NED; zeros before any)."""

    def __init__(self) -> None:
        self.samples: list[ImuSample] = []
        self.euler: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def add(self, sample: ImuSample) -> None:
        """The driver's handler: keep ``sample`` for the next cycle."""
        self.samples.append(sample)
        if sample.euler_rad is not None:
            self.euler = sample.euler_rad

    def predict(self, fusion: FusionFilter) -> None:
        """Propagate ``fusion`` with every sample kept, in order, and forget them."""
        for sample in self.samples:
            fusion.predict(sample.t, sample.accel_body, sample.euler_rad or self.euler, sample.gyro_body)
        self.samples.clear()


class FusedOutput:
    """A pipeline's fused state each nav cycle: its health reported as ``component`` (lost while
    not healthy, else the filter's own status), None while not healthy (nothing to send), and
    whether the filter's ``reset_counter`` moved since the previous cycle (the estimate jumped)."""

    def __init__(self, fusion: FusionFilter, health: Health, component: str) -> None:
        self.fusion = fusion
        self.health = health
        self.component = component
        self._reset_counter = 0

    def at(self, now: float) -> tuple[FusedState, bool] | None:
        """(state at daemon time ``now`` s, reset) while healthy, else None."""
        state = self.fusion.state(now)
        if not state.healthy:
            self.health.report(self.component, State.LOST, state.reason)
            return None
        self.health.report(self.component, state.status, state.reason or "fused")
        reset = state.reset_counter != self._reset_counter
        self._reset_counter = state.reset_counter
        return state, reset
