"""Mapping of a remote sender's timestamps onto local time, after ArduPilot's JitterCorrection.

Used both ways: the simulated autopilot places the companion's VISION_* stamps (``usec``, the
companion's monotonic capture time) on its clock, and the companion places the autopilot's IMU
samples (``time_usec`` / ``time_boot_ms``, the autopilot's boot clock) on its own, so a burst of
samples arriving together keeps the spacing they were measured with. Neither side can know the
offset between the two clocks, so, like ArduPilot's ``JitterCorrection`` (libraries/AP_RTC), it
assumes that the fastest transport seen recently took no time: the offset is the minimum over a
sliding window of ``local_receive_time - remote_time``, and a sample is placed at
``remote_time + offset``. A remote clock running slow or fast by ``d`` (ArduPilot SITL runs about
1 % slow) biases the result by at most ``d`` times the window's span.

Differences from ArduPilot, which clamps instead of dropping: a sample that would land more than
``max_lag_s`` before its arrival (stale) or more than ``max_lag_s`` after its arrival (claiming
to come from the future) is dropped and counted. A remote clock that jumps forward is re-learned
after ``rebase_after`` consecutive future samples; one that jumps back is re-learned as the old
minimum slides out of the window.

All times are in seconds; the result is in the local clock (simulation time for the vehicle).
"""

from __future__ import annotations

from collections import deque


class JitterCorrection:
    """Sliding-window minimum-offset clock mapping with a max-lag rule (seconds)."""

    def __init__(self, max_lag_s: float = 0.5, window: int = 100, rebase_after: int = 5) -> None:
        """``window``: samples in the minimum; ``rebase_after``: future samples before re-basing."""
        if max_lag_s <= 0 or window < 1 or rebase_after < 1:
            raise ValueError("max_lag_s must be > 0, window and rebase_after >= 1")
        self.max_lag_s = max_lag_s
        self.rebase_after = rebase_after
        self._diffs: deque[float] = deque(maxlen=window)
        self._future_run = 0
        self.rejected = 0

    @property
    def offset_s(self) -> float | None:
        """Current offset local - remote (s), None before the first sample."""
        return min(self._diffs) if self._diffs else None

    def correct(self, remote_s: float, local_s: float) -> float | None:
        """Local time (s) of a sample stamped ``remote_s`` and received at ``local_s``.

        Returns None (and counts it in ``rejected``) for a stale or future sample.
        """
        diff = local_s - remote_s
        offset = self.offset_s
        if offset is not None and diff < offset - self.max_lag_s:
            return self._future(diff, local_s)
        self._future_run = 0
        self._diffs.append(diff)
        estimate = remote_s + min(self._diffs)
        if estimate < local_s - self.max_lag_s:
            self.rejected += 1
            return None
        return estimate

    def _future(self, diff: float, local_s: float) -> float | None:
        """A sample claiming to be captured after it arrived: drop it, or re-base on a run of them."""
        self._future_run += 1
        if self._future_run < self.rebase_after:
            self.rejected += 1
            return None
        self._future_run = 0
        self._diffs.clear()
        self._diffs.append(diff)
        return local_s
