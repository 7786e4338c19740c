"""A scan is levelled with the autopilot's attitude when it was captured, not the newest.

A scan reaches the pipeline after its sweep and waits for the next nav cycle: the newest attitude is
then a tenth of a second newer than a 10 Hz scanner's beams. Pitching at 30 deg/s that is 3 deg,
enough to tilt the floor the vertical scanner sees and move the height it gives by millimetres.
"""

from __future__ import annotations

import math

import numpy as np

from companion.frames import rotation_from_euler
from companion.messages import ImuSample, Scan
from companion.nav.bench_stages import DEFAULT_WORLD
from companion.world import load_world
from tests.lidar_feed import LidarFeed

ARENA = load_world(DEFAULT_WORLD)
POSITION = np.array([6.5, 3.0, -0.9])  # NED m: a room of the arena, 0.9 m up, open floor below
AMPLITUDE_RAD = math.radians(5.0)  # pitch 5 deg either way at 1 Hz: up to 31 deg/s
VERTICAL_DELAY_S = 0.1  # a 10 Hz scan reaches the pipeline a sweep after its capture
HORIZONTAL_DELAY_S = 0.025


def pitch_at(t: float) -> float:
    return AMPLITUDE_RAD * math.sin(2.0 * math.pi * t)


def test_a_vertical_scan_captured_while_pitching_gives_the_height_of_its_own_attitude() -> None:
    """Hovering 0.9 m up and pitching +/-5 deg at 1 Hz, each scan rendered at its capture-time
    attitude and delivered a sweep later: the fused height stays within 2.5 mm (1.1 mm here;
    levelled with the newest attitude it was 5.4 mm off, 3 mm RMS)."""
    feed = LidarFeed(ARENA, (6.5, 3.0, 0.0), vertical_z_m=0.05, seed=4)
    pipeline = feed.pipeline
    in_flight: list[tuple[float, bool, Scan]] = []  # (delivery time s, horizontal?, scan)
    errors = []
    for k in range(1600):  # 8 s of 5 ms ticks
        t = k * 0.005
        attitude = (0.0, pitch_at(t), 0.0)
        if k % 5 == 0:  # 40 Hz
            in_flight.append((t + HORIZONTAL_DELAY_S, True, feed.horizontal_scan(t, POSITION, attitude, k)))
        if k % 20 == 0:  # 10 Hz
            in_flight.append((t + VERTICAL_DELAY_S, False, feed.vertical_scan(t, POSITION, attitude, k)))
        for item in [item for item in in_flight if item[0] <= t + 1e-9]:
            in_flight.remove(item)
            (pipeline.on_horizontal_scan if item[1] else pipeline.on_vertical_scan)(item[2])
        if k % 4 == 0:  # 50 Hz
            gravity_body = rotation_from_euler(*attitude).T @ np.array([0.0, 0.0, -9.81])
            rate = np.array([0.0, AMPLITUDE_RAD * 2.0 * math.pi * math.cos(2.0 * math.pi * t), 0.0])
            pipeline.imu.add(ImuSample(t, gravity_body, rate, euler_rad=attitude))
            pipeline.step(t)
            state = pipeline.fusion.state(t)
            if t > 2.0 and state.healthy:
                errors.append(abs(-float(state.position_ned[2]) - 0.9))
    assert len(errors) > 250
    assert max(errors) < 0.0025
