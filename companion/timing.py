"""Wall-clock timing helpers: the running stage records of the daemon (:class:`Timings`) and the
bench's (milliseconds, median and 99th percentile)."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np


def percentiles_ms(samples_s: Sequence[float] | np.ndarray) -> tuple[float, float]:
    """(median ms, p99 ms) of durations given in seconds."""
    ms = np.asarray(samples_s, dtype=float) * 1e3
    return float(np.median(ms)), float(np.percentile(ms, 99))


def time_stage(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    """(median ms, p99 ms) of ``fn()`` over ``repeat`` calls after a short warm-up."""
    for _ in range(min(50, repeat)):
        fn()
    samples = np.empty(repeat)
    for i in range(repeat):
        start = time.perf_counter()
        fn()
        samples[i] = time.perf_counter() - start
    return percentiles_ms(samples)


class Timings:
    """Bounded record of durations in milliseconds with median / p99."""

    def __init__(self, size: int = 6000) -> None:
        self._values: deque[float] = deque(maxlen=size)

    def add(self, ms: float) -> None:
        self._values.append(ms)

    def percentile(self, q: float) -> float | None:
        if not self._values:
            return None
        return float(np.percentile(np.fromiter(self._values, float), q))

    def summary(self) -> dict[str, float | None]:
        """{p50, p99, count}: both percentiles from one copy of the values (the status task calls
        this for every stage at telemetry.status_hz, on the event loop)."""
        if not self._values:
            return {"p50": None, "p99": None, "count": 0}
        p50, p99 = np.percentile(np.fromiter(self._values, float, len(self._values)), (50, 99))
        return {"p50": float(p50), "p99": float(p99), "count": len(self._values)}
