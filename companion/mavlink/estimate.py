"""Estimate output API: pipelines hand over a pose, the autopilot gets VISION_* messages.

A pipeline calls :meth:`EstimateSender.submit` with a :class:`PoseEstimate` whenever it has
one. The sender

- rate-limits to ``estimate_rate_hz`` (a GCRA scheduler that may send up to half a period
  early, so a 50 Hz pipeline yields exactly 30 Hz on average at the default, never a burst),
- never sends a non-finite value: such an estimate is dropped, counted and reported,
- never sends a capture time older than the last one it sent (ArduPilot's jitter filter
  assumes ordered stamps),
- stamps ``usec`` with the capture time on the daemon's monotonic clock (not wall time),
- increments ``reset_counter`` (mod 256) only when the estimate says it jumped,
- sends VISION_POSITION_ESTIMATE with the 21-element upper triangle of the 6x6 pose
  covariance (x, y, z, roll, pitch, yaw) and, when a velocity is given,
  VISION_SPEED_ESTIMATE with the 3x3 velocity covariance.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion.health import Health, State
from companion.mavlink.link import MavlinkLink, mavlink
from companion.messages import PoseEstimate

log = logging.getLogger("companion.estimate")

# After a non-finite estimate, estimate_output stays degraded until this long without another
# one: a pipeline emitting the odd NaN must not flip health (and STATUSTEXT) at its own rate.
NONFINITE_HOLD_S = 5.0


def upper_triangle(matrix: np.ndarray) -> list[float]:
    """Row-major upper triangle of a square matrix, as MAVLink covariance fields expect."""
    n = matrix.shape[0]
    return [float(matrix[i, j]) for i in range(n) for j in range(i, n)]


@dataclass
class EstimateStats:
    submitted: int = 0
    sent_position: int = 0
    sent_speed: int = 0
    rate_limited: int = 0
    nonfinite_dropped: int = 0
    out_of_order_dropped: int = 0
    resets: int = 0


class EstimateSender:
    """Turns :class:`PoseEstimate` into VISION_POSITION_ESTIMATE (+ VISION_SPEED_ESTIMATE)."""

    def __init__(self, link: MavlinkLink, rate_hz: float, health: Health, clock: Callable[[], float],
                 on_alert: Callable[[str], None] | None = None) -> None:
        self.link = link
        self.rate_hz = rate_hz
        self.health = health
        self.clock = clock
        self.on_alert = on_alert or (lambda text: None)
        self.stats = EstimateStats()
        self.reset_counter = 0
        self._next_due: float | None = None  # GCRA theoretical send time, daemon clock
        self._last_sent_capture = -float("inf")
        self._last_nonfinite = -float("inf")  # daemon clock of the last non-finite estimate
        self._reset_pending = False

    def submit(self, estimate: PoseEstimate) -> bool:
        """Offer an estimate; returns True if it went to the autopilot now."""
        self.stats.submitted += 1
        self._reset_pending |= estimate.reset
        if not estimate.is_finite():
            self.stats.nonfinite_dropped += 1
            self._last_nonfinite = self.clock()
            self.health.report("estimate_output", State.DEGRADED,
                               f"dropped {self.stats.nonfinite_dropped} non-finite estimates from {estimate.source}")
            if self.stats.nonfinite_dropped == 1:
                self.on_alert(f"companion: non-finite {estimate.source} estimate dropped")
            log.error("non-finite estimate from %s dropped (never sent)", estimate.source)
            return False
        if estimate.t_capture <= self._last_sent_capture:
            self.stats.out_of_order_dropped += 1
            return False
        if not self._slot_free():
            self.stats.rate_limited += 1
            return False
        if self._reset_pending:
            self.reset_counter = (self.reset_counter + 1) % 256
            self.stats.resets += 1
            self._reset_pending = False
        self._send(estimate)
        self._last_sent_capture = estimate.t_capture
        if self.clock() - self._last_nonfinite >= NONFINITE_HOLD_S:
            self.health.report("estimate_output", State.OK, f"sending {estimate.source}")
        return True

    def _slot_free(self) -> bool:
        """Generic cell rate algorithm: average <= rate_hz, early by at most half a period."""
        now = self.clock()
        period = 1.0 / self.rate_hz
        if self._next_due is not None and now < self._next_due - period / 2:
            return False
        self._next_due = max(self._next_due or now, now) + period
        return True

    def _send(self, e: PoseEstimate) -> None:
        usec = int(round(e.t_capture * 1e6))
        p = e.position_ned
        roll, pitch, yaw = e.euler_rad
        if self.link.send(mavlink.MAVLink_vision_position_estimate_message(
                usec, float(p[0]), float(p[1]), float(p[2]), float(roll), float(pitch), float(yaw),
                upper_triangle(e.pose_covariance), self.reset_counter)):
            self.stats.sent_position += 1
        if e.velocity_ned is None or e.velocity_covariance is None:
            return
        v = e.velocity_ned
        # VISION_SPEED_ESTIMATE carries the full row-major 3x3, not a triangle.
        velocity_cov = [float(x) for x in np.asarray(e.velocity_covariance).ravel()]
        if self.link.send(mavlink.MAVLink_vision_speed_estimate_message(
                usec, float(v[0]), float(v[1]), float(v[2]), velocity_cov, self.reset_counter)):
            self.stats.sent_speed += 1
