"""The autopilot's attitude over the last second, at any instant: what a scan or a camera frame is
levelled with.

A scan reaches a pipeline after its sweep and is processed at the next nav cycle: the newest
attitude is then 0.05-0.2 s newer than the scan's beams (a 10 Hz scanner: 0.1 s, 3 deg at a
30 deg/s pitch); a frame likewise after its exposure. Levelled with the attitude of its own time,
a manoeuvre does not tilt the floor or the walls it sees.

Frames and units (README, "Frames and time"): roll, pitch, yaw of body FRD in NED, radians;
daemon-clock seconds.
"""

from __future__ import annotations

import math
from collections import deque

from companion.frames import wrap_pi

Euler = tuple[float, float, float]


class AttitudeHistory:
    """Attitude samples (time, roll, pitch, yaw) of the last ``span_s`` seconds, oldest first."""

    def __init__(self, span_s: float = 1.0) -> None:
        self.span_s = span_s
        self._samples: deque[tuple[float, Euler]] = deque()

    def add(self, t: float, euler: Euler) -> None:
        """Keep the attitude ``euler`` (rad) at daemon time ``t`` (s); a sample not newer than the
        newest is ignored (the history stays in time order), samples older than ``span_s`` are dropped."""
        samples = self._samples
        if samples and t <= samples[-1][0]:
            return
        samples.append((t, euler))
        while samples[0][0] < t - self.span_s:
            samples.popleft()

    def at(self, t: float, max_gap_s: float = math.inf) -> Euler | None:
        """The attitude at daemon time ``t`` (s): interpolated between the samples around it (yaw
        the short way round), the oldest or newest sample outside them. None when there is no
        sample, or when the nearest one is more than ``max_gap_s`` from ``t``."""
        samples = self._samples
        if not samples:
            return None
        if t >= samples[-1][0]:
            return samples[-1][1] if t - samples[-1][0] <= max_gap_s else None
        k = len(samples) - 1
        while k > 0 and samples[k - 1][0] > t:  # from the newest: a scan's time is a few samples back
            k -= 1
        if k == 0:
            return samples[0][1] if samples[0][0] - t <= max_gap_s else None
        (t0, a), (t1, b) = samples[k - 1], samples[k]
        if min(t - t0, t1 - t) > max_gap_s:
            return None
        w = (t - t0) / (t1 - t0)
        return (a[0] + w * (b[0] - a[0]), a[1] + w * (b[1] - a[1]), wrap_pi(a[2] + w * wrap_pi(b[2] - a[2])))
