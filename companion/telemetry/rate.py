"""Message rate over a sliding time window, for the telemetry counters (publisher and dashboard)."""

from __future__ import annotations

from collections import deque

RATE_WINDOW_S = 5.0
"""Rates are measured over the events of the last this many seconds."""


class RateWindow:
    """Event times of one stream; :meth:`rate_hz` is the mean rate over the last window:
    (events - 1) / (newest - oldest) of the events in it, so a steady 1 Hz stream reads
    1.0 (not 0.8 or 1.2 by where the window falls); 0.0 with fewer than two events. A stream
    that stops (nothing for two of its intervals) reads (events - 1) / (now - oldest), falling
    to 0 as its events leave the window.

    Keeps at most ``capacity`` times, so rates above ``capacity / window_s`` Hz read low; the
    default holds 100 Hz over the 5 s window. Not thread-safe: callers hold their own lock.
    """

    def __init__(self, window_s: float = RATE_WINDOW_S, capacity: int = 500) -> None:
        self.window_s = window_s
        self._times: deque[float] = deque(maxlen=capacity)

    def add(self, t: float) -> None:
        """Record one event at time ``t`` (s, any monotonic clock, non-decreasing)."""
        self._times.append(t)

    def rate_hz(self, now: float) -> float:
        """Events per second among those in ``(now - window_s, now]`` (s, the clock of :meth:`add`)."""
        start = now - self.window_s
        while self._times and self._times[0] <= start:
            self._times.popleft()
        n = len(self._times)
        if n < 2 or self._times[-1] <= self._times[0]:
            return 0.0
        span = self._times[-1] - self._times[0]
        if now - self._times[-1] > 2.0 * span / (n - 1):  # stopped: count the silence too
            span = now - self._times[0]
        return (n - 1) / span
