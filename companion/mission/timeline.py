"""Where on a planned trajectory the reference is (pure, no I/O): a time warp plus pauses at holds.

The flown reference is ``p(tau(t))`` for the planned trajectory ``p``: ``tau`` advances at a
``rate`` (1 normally, less while the estimate is degraded) that changes smoothly, and stands
still while holding at a waypoint (where the trajectory is at rest). Seconds; velocities m/s,
accelerations m/s^2 in LOCAL_NED.
"""

from __future__ import annotations

import numpy as np

from companion.control.reference import Reference
from companion.control.trajectory import Trajectory


class TimeWarp:
    """Trajectory time ``tau`` advancing at ``rate`` (0..1) times the clock: slowing down without replanning.

    ``rate`` follows its target at most ``ramp_per_s`` per second, so the references stay
    smooth: with ``p(tau)`` the planned trajectory, the flown one is ``p(tau(t))`` with velocity
    ``p'(tau) rate`` and acceleration ``p''(tau) rate^2 + p'(tau) rate'``.
    """

    def __init__(self, ramp_per_s: float = 0.5) -> None:
        self.ramp_per_s = ramp_per_s
        self.tau = 0.0
        self.rate = 1.0
        self.rate_dot = 0.0

    def advance(self, dt: float, target_rate: float) -> None:
        """Move on by ``dt`` seconds of the clock with the rate heading for ``target_rate``."""
        step = self.ramp_per_s * dt
        new = min(max(target_rate, self.rate - step), self.rate + step)
        self.rate_dot = (new - self.rate) / dt if dt > 0 else 0.0
        self.tau += 0.5 * (self.rate + new) * dt
        self.rate = new

    def pause(self) -> None:
        """Hold ``tau`` (at a stop, where the trajectory is at rest); the rate is kept."""
        self.rate_dot = 0.0

    def scale(self, velocity: np.ndarray, acceleration: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The flown velocity (m/s) and acceleration (m/s^2) from the planned ones at ``tau``."""
        return velocity * self.rate, acceleration * self.rate ** 2 + velocity * self.rate_dot


class Timeline:
    """Trajectory time for one flight: the warp, and the holds ``{waypoint index: (tau there, seconds)}``."""

    def __init__(self, trajectory: Trajectory, holds: dict[int, tuple[float, float]], ramp_per_s: float = 0.5) -> None:
        self.trajectory = trajectory
        self.warp = TimeWarp(ramp_per_s)
        self._holds = sorted((tau, seconds, index) for index, (tau, seconds) in holds.items())
        self.held: int | None = None  # the waypoint being held
        self.hold_left = 0.0  # s

    @property
    def tau(self) -> float:
        return min(self.warp.tau, self.trajectory.duration)

    @property
    def holding(self) -> bool:
        return self.held is not None

    @property
    def finished(self) -> bool:
        """The reference is at the end and no hold is running."""
        return self.warp.tau >= self.trajectory.duration and not self.holding

    def advance(self, dt: float, rate: float) -> None:
        """Move on ``dt`` clock seconds at (a rate heading for) ``rate``; stop at the next hold."""
        if self.holding:
            self.hold_left -= dt
            self.warp.pause()
            if self.hold_left <= 0.0:
                self.held, self.hold_left = None, 0.0
            return
        self.warp.advance(dt, rate)
        if self._holds and self.warp.tau >= self._holds[0][0]:
            self.warp.tau, self.hold_left, self.held = self._holds.pop(0)

    def reference(self) -> Reference:
        """The reference now: the trajectory's at ``tau``, its rates scaled by the warp (0 while
        holding and at the end, where ``tau`` stands still)."""
        sample = self.trajectory.sample(self.tau)
        if self.holding or self.warp.tau >= self.trajectory.duration:
            velocity = acceleration = np.zeros(3)
            yaw_rate = 0.0
        else:
            velocity, acceleration = self.warp.scale(sample.velocity, sample.acceleration)
            yaw_rate = float(sample.yaw_rate) * self.warp.rate
        return Reference(sample.position, velocity, acceleration, float(sample.yaw_rad), yaw_rate)
