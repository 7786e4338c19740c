"""Flying over a table that hides the floor, the lidar pipeline never takes its top for the floor.

With the floor hidden, the vertical scanner's furthest floor-like line is the table top; the height
estimator refuses it while the fused (IMU-carried) height says the floor is further
(companion/nav/height.py). That must hold however long the floor stays hidden: once the fusion has
had no height fix for a second it reports the height lost, and it re-seeds its height from the next
fix that fails its gate (its relock) - a table top let through then becomes a confident height 0.75 m
off, and the vehicle climbs by the table's height. A table top seen beside the floor before, though,
stands in for it with the step between them (its height above the floor) added.
"""

from __future__ import annotations

import numpy as np

from companion.health import Health, State
from companion.messages import ImuSample
from companion.nav.bench_stages import DEFAULT_WORLD
from companion.nav.lidar_pipeline import LidarPipeline
from companion.world import load_world
from tests.lidar_feed import LidarFeed

ARENA = load_world(DEFAULT_WORLD)
BESIDE_TABLE = np.array([6.5, 1.6, -0.9])  # NED m: in the north-west room, 0.9 m up, the table ahead
AWAY_FROM_TABLE = np.array([6.5, 3.0, -0.9])  # the same room and height, the table out of the vertical scan
OVER_TABLE = np.array([7.4, 1.6, -0.9])  # above the 0.75 m table: only its top in the vertical scan


def hover_then_over_table(vertical_before: np.ndarray) -> tuple[LidarPipeline, Health, list[float], int]:
    """5 s with the vertical scanner seeing the room from ``vertical_before`` (NED m), then 2.5 s
    with only the table top in its view (the horizontal one sees the room from beside the table
    throughout, the IMU says the vehicle is still): the pipeline, its health, the fused heights
    (m) over the table and the height fixes taken there."""
    feed = LidarFeed(ARENA, (6.5, 1.6, 0.0), vertical_z_m=0.05, seed=3)
    pipeline = feed.pipeline
    heights = []
    fixes_before = 0
    for k in range(1500):  # 7.5 s of 5 ms ticks
        t = k * 0.005
        if k % 5 == 0:  # 40 Hz
            pipeline.on_horizontal_scan(feed.horizontal_scan(t, BESIDE_TABLE, sequence=k))
        if k % 20 == 0:  # 10 Hz
            if k == 1000:  # 5 s: over the table from now
                fixes_before = pipeline.stats.height_fixes
            pipeline.on_vertical_scan(feed.vertical_scan(t, vertical_before if t < 5.0 else OVER_TABLE, sequence=k))
        if k % 4 == 0:  # 50 Hz
            pipeline.imu.add(ImuSample(t, np.array([0.0, 0.0, -9.81]), np.zeros(3), euler_rad=(0.0, 0.0, 0.0)))
            pipeline.step(t)
            if t > 5.0:
                heights.append(-float(pipeline.fusion.state(t).position_ned[2]))
    return pipeline, feed.health, heights, pipeline.stats.height_fixes - fixes_before


def test_a_table_never_seen_beside_the_floor_never_becomes_the_height_while_it_hides_the_floor() -> None:
    """The height is carried by the IMU and reported lost, never re-seeded to the table top."""
    pipeline, health, heights, fixes_over_table = hover_then_over_table(AWAY_FROM_TABLE)
    assert pipeline.fusion.stats.relocks == 0 and fixes_over_table == 0
    assert max(abs(h - 0.9) for h in heights) < 0.05  # carried by the IMU, not 0.15 m over the table
    height = health.get("nav:height")
    assert height is not None and height.state == State.LOST and "table top" in height.reason


def test_a_table_seen_beside_the_floor_stands_in_for_it_while_it_hides_the_floor() -> None:
    """The table top plus its step above the floor keeps giving height fixes (degraded)."""
    pipeline, health, heights, fixes_over_table = hover_then_over_table(BESIDE_TABLE)
    assert pipeline.fusion.stats.relocks == 0 and fixes_over_table >= 20  # of 25 scans
    assert max(abs(h - 0.9) for h in heights) < 0.02
    height = health.get("nav:height")
    assert height is not None and height.state == State.DEGRADED and "stands in" in height.reason
