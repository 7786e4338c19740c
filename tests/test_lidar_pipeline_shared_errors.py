"""The lidar pipeline's estimate claims no more than its fixes' shared errors allow.

Hovering between two door recesses of config/worlds/corridor.yaml, the position along the
corridor is measured only by where the walls end (companion/nav/edges.py). Where between two
beams a wall ends is the same error in every scan while the vehicle stays put, so the fusion's
average of 40 fixes a second is no better than one of them: the estimate sent must not claim less
variance along the corridor than one fix has, also after fixes that measure that direction no
better than the ends did.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.messages import ImuSample, PoseEstimate
from companion.nav.lidar_pipeline import LidarPipeline, wall_ends_floor
from companion.world import load_world
from tests.conftest import REPO
from tests.lidar_feed import LidarFeed

CORRIDOR = load_world(REPO / "config" / "worlds" / "corridor.yaml")
HOVER = np.array([31.0, 1.2, -1.0])  # NED m: between the recesses at 29 m and 38 m north, 1 m up


def _hover(seconds: float) -> tuple[LidarPipeline, PoseEstimate]:
    """The pipeline after hovering still at HOVER for ``seconds``: IMU at 50 Hz, horizontal scans
    at 40 Hz, vertical ones at 10 Hz (fresh range noise in each), one nav cycle per IMU sample."""
    feed = LidarFeed(CORRIDOR, (31.0, 1.2, 0.0), vertical_z_m=-0.05, seed=7)
    pipeline = feed.pipeline
    estimate = None
    for k in range(int(seconds * 200)):  # 5 ms ticks
        t = k * 0.005
        if k % 5 == 0:  # 40 Hz
            pipeline.on_horizontal_scan(feed.horizontal_scan(t, HOVER, sequence=k))
        if k % 20 == 0:  # 10 Hz
            pipeline.on_vertical_scan(feed.vertical_scan(t, HOVER, sequence=k))
        if k % 4 == 0:  # 50 Hz
            pipeline.imu.add(ImuSample(t, np.array([0.0, 0.0, -9.81]), np.zeros(3), euler_rad=(0.0, 0.0, 0.0)))
            for made in pipeline.step(t):
                estimate = made
    assert isinstance(estimate, PoseEstimate)
    return pipeline, estimate


def test_hovering_where_only_wall_ends_measure_the_corridors_axis_the_estimate_claims_no_less_than_one_fix() -> None:
    pipeline, estimate = _hover(3.0)
    fix = pipeline.last_horizontal.fix if pipeline.last_horizontal is not None else None
    assert fix is not None and fix.measured and "of their ends" in fix.reason, fix and fix.reason
    assert fix.ends_only is not None and abs(fix.ends_only[0]) == 1.0  # north: the corridor's axis
    one_fix = fix.covariance[0, 0]
    filtered = pipeline.fusion.state(estimate.t_capture).position_covariance[0, 0]
    assert filtered < 0.5 * one_fix  # the filter averaged the fixes as if independent ...
    assert estimate.pose_covariance[0, 0] >= one_fix  # ... the estimate sent does not claim it
    assert abs(estimate.position_ned[0] - HOVER[0]) < 3.0 * math.sqrt(estimate.pose_covariance[0, 0])


def test_the_wall_ends_floor_outlives_fixes_that_measure_the_corridors_axis_no_better() -> None:
    pipeline, _ = _hover(1.0)
    ends = pipeline.last_horizontal.fix if pipeline.last_horizontal is not None else None
    assert ends is not None and ends.ends_only is not None
    floor = wall_ends_floor(ends, None)
    assert floor is not None and floor[1] == pytest.approx(ends.covariance[0, 0])
    walls_only = dataclasses.replace(ends, ends_only=None, unmeasured=(1.0, 0.0),
                                     covariance=np.diag([100.0, 1e-4, 1e-5]))  # the corridor's axis unmeasured
    one_corner = dataclasses.replace(ends, ends_only=None, matched=1, walls_matched=0,
                                     covariance=np.diag([4.0 * floor[1], 4.0 * floor[1], 1e-5]))
    corners = dataclasses.replace(ends, ends_only=None, matched=3, walls_matched=0,
                                  covariance=np.diag([0.25 * floor[1], 0.25 * floor[1], 1e-5]))
    assert wall_ends_floor(walls_only, floor) is floor
    assert wall_ends_floor(one_corner, floor) is floor
    assert wall_ends_floor(corners, floor) is None
    assert wall_ends_floor(walls_only, None) is None
