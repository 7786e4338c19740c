"""Pure pieces of the mission's failsafes (no I/O, no asyncio): estimate status, geofence, braking.

Frames: LOCAL_NED metres at the EKF origin (the map frame), seconds of the daemon clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from companion.config import GeofenceConfig
from companion.health import State
from companion.messages import PoseEstimate


class EstimateStatus(NamedTuple):
    state: State  # OK: fly; DEGRADED: slow down; LOST: brake and hold on the autopilot's estimate
    reason: str


def classify_estimate(now: float, estimate: PoseEstimate | None, nav: tuple[State, str],
                      timeout_s: float) -> EstimateStatus:
    """What the mission may do with the companion's estimate at daemon time ``now`` (s).

    Lost: no estimate yet, none for ``timeout_s`` (capture time), or a non-finite one. Degraded:
    estimates flow but a navigation component (``nav``: the worst ``nav:*`` health and its
    reason) is not ok, e.g. too few corners matched. Otherwise ok.
    """
    if estimate is None:
        return EstimateStatus(State.LOST, "no estimate yet")
    age = now - estimate.t_capture
    if age > timeout_s:
        return EstimateStatus(State.LOST, f"no fused estimate for {age:.2f} s")
    if not np.all(np.isfinite(estimate.position_ned)):
        return EstimateStatus(State.LOST, "non-finite estimate")
    state, reason = nav
    if state != State.OK:
        return EstimateStatus(State.DEGRADED, reason)
    return EstimateStatus(State.OK, "")


@dataclass(frozen=True)
class Geofence:
    """An axis-aligned box in the map frame with a ceiling: ``x_min <= x <= x_max``, same for y,
    and height ``-z <= ceiling_m``."""

    x_min: float
    y_min: float
    x_max: float
    y_max: float
    ceiling_m: float

    @classmethod
    def from_config(cls, fence: GeofenceConfig,
                    map_box: tuple[tuple[float, float], tuple[float, float]] | None) -> Geofence | None:
        """The configured fence (``box_ned_m``, else ``map_box``, shrunk by ``inset_m``); None if
        disabled or there is no box to take it from."""
        box = fence.box_ned_m if fence.box_ned_m is not None else map_box
        if not fence.enabled or box is None:
            return None
        (x0, y0), (x1, y1) = box
        d = fence.inset_m
        if x1 - x0 <= 2 * d or y1 - y0 <= 2 * d:
            raise ValueError(f"mission.geofence.inset_m {d:g} leaves nothing of the box {box}")
        return cls(x0 + d, y0 + d, x1 - d, y1 - d, fence.ceiling_m)

    def violation(self, p: np.ndarray) -> str | None:
        """Why the NED point ``p`` (m) is outside, or None when it is inside."""
        x, y, z = (float(c) for c in p)
        if not (self.x_min <= x <= self.x_max and self.y_min <= y <= self.y_max):
            return (f"({x:.2f}, {y:.2f}) is outside the fence x {self.x_min:g}..{self.x_max:g}, "
                    f"y {self.y_min:g}..{self.y_max:g}")
        if -z > self.ceiling_m:
            return f"height {-z:.2f} m is above the {self.ceiling_m:g} m ceiling"
        return None

    def first_violation(self, points: np.ndarray) -> str | None:
        """The first point of an (M, 3) path that is outside, described; None if all are inside."""
        for p in points:
            why = self.violation(p)
            if why is not None:
                return why
        return None


def stopping_point(position: np.ndarray, velocity: np.ndarray, decel_mps2: float) -> np.ndarray:
    """Where a vehicle at ``position`` (m) moving at ``velocity`` (m/s) stops braking at ``decel_mps2``
    horizontally; the height is kept."""
    v = np.array([velocity[0], velocity[1], 0.0])
    speed = math.hypot(v[0], v[1])
    return np.asarray(position, dtype=float) + v * speed / (2.0 * decel_mps2)
