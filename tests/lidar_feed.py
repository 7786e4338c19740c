"""A lidar pipeline fed synthetic scans, for the tests that drive it scan by scan.

The horizontal scanner is a UTM-30LX 10 cm above the body origin, the vertical one a URG-04LX
scanning the body x-z plane 5 cm ahead (its height as given); both with 1 cm range noise,
rendered from a pose in the world (NED m, roll / pitch / yaw rad) by ray casting.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from companion.config import MountConfig
from companion.health import Health
from companion.messages import Scan
from companion.nav.bench_stages import make_mount, synthetic_scan
from companion.nav.lidar_pipeline import LidarPipeline, LidarPipelineConfig
from companion.world import World
from drivers.lidar_models import URG_04LX, UTM_30LX
from sitl.raycast import WorldGeometry

HORIZONTAL = MountConfig(position_m=(0.0, 0.0, -0.10))

Attitude = tuple[float, float, float]
LEVEL: Attitude = (0.0, 0.0, 0.0)


class LidarFeed:
    """A :class:`LidarPipeline` in ``world`` starting at ``initial_pose`` (north m, east m, yaw deg),
    its health, and the scans its two scanners would see."""

    def __init__(self, world: World, initial_pose: tuple[float, float, float], *, vertical_z_m: float,
                 seed: int) -> None:
        vertical = MountConfig(position_m=(0.05, 0.0, vertical_z_m), rpy_deg=(90.0, 0.0, 0.0))
        self.health = Health(lambda: 0.0)
        cfg = LidarPipelineConfig(horizontal_sensor="h", vertical_sensor="v", initial_pose=initial_pose)
        self.pipeline = LidarPipeline(cfg, world, HORIZONTAL, vertical, self.health)
        self._geometry = WorldGeometry.from_world(world)
        self._rng = np.random.default_rng(seed)
        self._horizontal = make_mount(HORIZONTAL.position_m, (0.0, 0.0, 0.0))
        self._vertical = make_mount(vertical.position_m, (math.pi / 2, 0.0, 0.0))

    def horizontal_scan(self, t: float, position_ned: np.ndarray, attitude: Attitude = LEVEL,
                        sequence: int = 0) -> Scan:
        """The horizontal scanner's scan captured at ``t`` (s) from ``position_ned`` at ``attitude``."""
        scan = synthetic_scan(self._geometry, UTM_30LX, self._horizontal, position_ned, attitude, self._rng, 0.01,
                              sequence=sequence)
        return dataclasses.replace(scan, t_capture=t)

    def vertical_scan(self, t: float, position_ned: np.ndarray, attitude: Attitude = LEVEL,
                      sequence: int = 0) -> Scan:
        """The vertical scanner's scan captured at ``t`` (s) from ``position_ned`` at ``attitude``."""
        scan = synthetic_scan(self._geometry, URG_04LX, self._vertical, position_ned, attitude, self._rng, 0.01,
                              sequence=sequence)
        return dataclasses.replace(scan, t_capture=t)
