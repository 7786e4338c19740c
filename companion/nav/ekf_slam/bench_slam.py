"""Timings of :class:`companion.nav.ekf_slam.filter.EkfSlam` for ``companion bench``.

A map of 100 landmarks (305 states with the GNSS bias, full covariance) built by flying over a ring of them with the
seed's Table 1 noise; then timed on this machine, (median, p99) ms over ``repeat`` calls: one
prediction (40 Hz input), one update with one landmark (the issue's <= 2 ms figure), one 5 Hz
frame of five landmarks. The timed updates use noise-free observations of the current estimate
(zero innovation), so repeated calls leave the state where it is and the
observations stay valid.
"""

from __future__ import annotations

import math

import numpy as np

from companion.nav.ekf_slam.config import EkfSlamConfig
from companion.nav.ekf_slam.filter import EkfSlam
from companion.nav.ekf_slam.model import observe
from companion.timing import time_stage

LANDMARKS = 100


def bench_filter(n_landmarks: int = LANDMARKS, seed: int = 0) -> EkfSlam:
    """A filter holding ``n_landmarks`` landmarks with correlated covariance."""
    cfg = EkfSlamConfig()
    rng = np.random.default_rng(seed)
    slam = EkfSlam(cfg, (0.0, 0.0, 0.0), np.diag([1e-4, 1e-4, 1e-8]))
    for i in range(n_landmarks):
        for _ in range(8):
            slam.predict(5.0, 0.05, 0.025)
        bearing = rng.uniform(-math.pi, math.pi)
        horizontal = rng.uniform(8.0, 30.0)
        pose = slam.x[:3]
        landmark = np.array([pose[0] + horizontal * math.cos(bearing), pose[1] + horizontal * math.sin(bearing),
                             -rng.uniform(0.0, 5.0)])
        slam.update({i: observe(pose, slam.down_m, landmark)})
    return slam


def run_slam_bench(repeat: int) -> dict[str, tuple[float, float]]:
    """{stage: (median ms, p99 ms)}."""
    slam = bench_filter()
    ids = slam.ids[-5:]

    def frame(which: list[int]) -> dict[int, np.ndarray]:
        return {i: observe(slam.x[:3], slam.down_m, slam.landmark(i)[0]) for i in which}

    one = frame(ids[:1])
    five = frame(ids)
    if slam.update(five).used != ids:
        raise AssertionError("the bench observations were not used")
    n = slam.x.shape[0]
    return {
        f"ekf_slam.predict ({LANDMARKS} landmarks, {n} states)": time_stage(lambda: slam.predict(0.0, 0.0, 0.025),
                                                                             repeat),
        f"ekf_slam.update (1 landmark of {LANDMARKS}, Joseph form)": time_stage(lambda: slam.update(one), repeat),
        f"ekf_slam.update (5 landmarks of {LANDMARKS}: one 5 Hz frame)": time_stage(lambda: slam.update(five),
                                                                                   repeat),
    }
