"""What a pose pipeline built around a :class:`~companion.nav.fusion.FusionFilter` does at its
edges each nav cycle: keep the IMU samples that arrived since the previous cycle and predict with
them (:class:`ImuFeed`), and turn the filter's state into what the pipeline may send
(:class:`FusedOutput`, :func:`to_pose_estimate`). The lidar and laser-dot pipelines share them.

Frames and units as in companion/nav/fusion.py: world LOCAL_NED, body FRD, radians, daemon-clock
seconds.
"""

from __future__ import annotations

import numpy as np

from companion.health import Health, State
from companion.messages import ImuSample, PoseEstimate
from companion.nav.attitude_history import AttitudeHistory
from companion.nav.fusion import FusedState, FusionFilter

# Roll and pitch come from the autopilot's own attitude estimate; the pose covariance gives them
# this small constant variance, (0.01 rad)^2 ~ (0.6 deg)^2. ArduPilot folds roll/pitch/yaw into
# one angle error, so keeping these small keeps the yaw variance meaningful.
ROLL_PITCH_VARIANCE_RAD2 = 1e-4


class ImuFeed:
    """The IMU samples a pipeline received since its previous nav cycle (oldest first), and the
    autopilot's attitude (roll, pitch, yaw rad of body FRD in NED): the newest (zeros before
    any), and over the last second at any instant (:meth:`euler_at`)."""

    def __init__(self) -> None:
        self.samples: list[ImuSample] = []
        self.euler: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._attitudes = AttitudeHistory()

    def add(self, sample: ImuSample) -> None:
        """The driver's handler: keep ``sample`` for the next cycle."""
        self.samples.append(sample)
        if sample.euler_rad is not None:
            self.euler = sample.euler_rad
            self._attitudes.add(sample.t, sample.euler_rad)

    def euler_at(self, t: float) -> tuple[float, float, float]:
        """The autopilot's attitude at daemon time ``t`` (s), what a scan or frame captured then is
        levelled with (companion/nav/attitude_history.py); the newest before any is kept."""
        return self._attitudes.at(t) or self.euler

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


def to_pose_estimate(state: FusedState, roll: float, pitch: float, t_capture: float | None = None,
                     reset: bool = False, source: str = "fusion") -> PoseEstimate:
    """The :class:`PoseEstimate` of a healthy fused state.

    ``roll``/``pitch`` (rad) come from the autopilot and get ``ROLL_PITCH_VARIANCE_RAD2``;
    ``t_capture`` (s, daemon clock) defaults to ``state.t``; ``reset`` marks a jump (compare
    ``state.reset_counter`` with the previous one). Position-velocity correlations are
    dropped: MAVLink has no field for them. Raises ValueError for an unhealthy state, which
    must not be sent.
    """
    if not state.healthy:
        raise ValueError(f"fused state is not healthy ({state.reason}): do not send it")
    cov = np.zeros((6, 6))
    cov[0:3, 0:3] = state.position_covariance
    cov[3, 3] = cov[4, 4] = ROLL_PITCH_VARIANCE_RAD2
    cov[5, 5] = state.yaw_variance
    return PoseEstimate(state.t if t_capture is None else float(t_capture), state.position_ned.copy(),
                        (float(roll), float(pitch), state.yaw), cov, state.velocity_ned.copy(),
                        state.velocity_covariance.copy(), reset, source, degraded=state.status != State.OK)
