"""Wall-clock timing helpers for `companion bench` (milliseconds, median and 99th percentile)."""

from __future__ import annotations

import time
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
