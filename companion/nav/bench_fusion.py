"""Timings of :class:`companion.nav.fusion.FusionFilter` for ``companion bench``.

A hovering vehicle at 50 Hz IMU with 10 Hz position/height/yaw fixes: wall-clock
milliseconds per call on this machine, (median, p99) over ``repeat`` calls.
"""

from __future__ import annotations

import time

import numpy as np

from companion.frames import GRAVITY_MPS2
from companion.nav.fusion import FusionFilter
from companion.nav.fusion_io import to_pose_estimate
from companion.timing import percentiles_ms

IMU_DT_S = 0.02  # 50 Hz
FIX_DELAY_STEPS = 4.5  # the benchmarked fix was captured 90 ms ago: 5 stored steps to re-run
_COV_XY = np.eye(2) * 1e-4


class _Hover:
    """A filter in steady state over a noisy hover, stepped one IMU sample at a time."""

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.filter = FusionFilter()
        self.t = 0.0
        self.k = 0
        # Pre-drawn noise, so that the timings are the filter's and not the generator's.
        self.accel = np.array([0.0, 0.0, -GRAVITY_MPS2]) + self.rng.normal(0.0, 0.05, (4096, 3))
        for _ in range(100):  # 2 s: initialised, buffer full, bias settling
            self.step()
            if self.k % 5 == 0:
                self.fix(self.t - 0.03)

    def step(self) -> None:
        self.t += IMU_DT_S
        self.k += 1
        self.filter.predict(self.t, self.accel[self.k % len(self.accel)], (0.0, 0.0, 0.1))

    def fix(self, t_capture: float) -> None:
        f = self.filter
        f.correct_position(t_capture, self.rng.normal(0.0, 0.01, 2), _COV_XY)
        f.correct_height(t_capture, 1.0 + self.rng.normal(0.0, 0.01), 1e-4)
        f.correct_yaw(t_capture, 0.1, 1e-4)


def run_fusion_bench(repeat: int) -> dict[str, tuple[float, float]]:
    """Stage name -> (median ms, p99 ms) of the fusion hot paths over ``repeat`` calls each."""
    hover = _Hover()
    predict, step = [], []
    for i in range(repeat):
        start = time.perf_counter()
        hover.step()
        predict.append(time.perf_counter() - start)
        start = time.perf_counter()
        hover.step()
        state = hover.filter.state(hover.t)
        to_pose_estimate(state, 0.0, 0.0)
        step.append(time.perf_counter() - start)
        if i % 5 == 0:
            hover.fix(hover.t - 0.03)
    correct = []
    for _ in range(repeat):
        for _ in range(5):
            hover.step()
        t_capture = hover.t - FIX_DELAY_STEPS * IMU_DT_S
        f = hover.filter
        start = time.perf_counter()
        f.correct_position(t_capture, hover.rng.normal(0.0, 0.01, 2), _COV_XY)
        correct.append(time.perf_counter() - start)
        f.correct_height(t_capture, 1.0 + hover.rng.normal(0.0, 0.01), 1e-4)
        f.correct_yaw(t_capture, 0.1, 1e-4)
    return {
        "fusion.predict (one 50 Hz IMU step)": percentiles_ms(predict),
        "fusion.predict + state + to_pose_estimate": percentiles_ms(step),
        "fusion.correct_position (90 ms late, 5 steps re-run)": percentiles_ms(correct),
    }
