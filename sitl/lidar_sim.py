"""Simulated Hokuyo scanner: scans rendered from simulator ground truth by ray casting.

For capture time ``t`` (daemon clock, s) the backend takes the vehicle pose from the truth
source (:class:`sitl.truth.TruthSource`, or anything with the same ``at(t)``), places
the sensor through its :class:`~drivers.mount.Mount`, casts the model's beams
(:mod:`drivers.lidar_models`) into the world (:mod:`sitl.raycast`) and adds the model's range
noise and random dropouts. Invalid beams (no hit, shorter than the model's minimum or longer
than its maximum range, dropped) have ``valid`` False and range 0.

Timing: capture times lie on a grid ``t0 + k / rate`` from :meth:`SimulatedLidar.open`, and the
scan captured at ``t`` is delivered at ``t + sweep`` (the model's first-to-last-beam time,
like a real device, which sends a scan once it has swept it), waiting with ``asyncio.sleep`` on
the daemon clock, so lockstep simulation paces it exactly. ``Scan.sequence`` is the grid index
k: a reader more than one period late skips to the latest due capture, and a capture with no
truth (none received yet, or the truth stream stalled) yields no scan; both show as gaps.

Simplification: every beam is rendered at the capture-time pose (the device sweeps its beams
over ``sweep`` seconds while the vehicle moves). The scans therefore carry ``sweep_s = 0``,
which describes the data truthfully; only the delivery latency of the sweep is simulated.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from companion.schema import meta
from drivers.base import Backend
from drivers.lidar_models import MODELS, LidarModel
from drivers.mount import Mount, beam_directions
from companion.messages import Scan
from sitl.raycast import WorldGeometry, cast
from companion.world import World
from sitl.capture_grid import CaptureGrid
from sitl.truth import TruthLike


@dataclass(frozen=True)
class SimLidarSettings:
    """``settings:`` of a lidar with ``backend: sim`` (a companion.schema dataclass)."""

    model: Literal["UTM-30LX", "URG-04LX"] = field(default="UTM-30LX", metadata=meta(
        "Scanner model: beams, rate, range limits and noise (drivers/lidar_models.py)."))
    seed: int = field(default=0, metadata=meta("Seed of the range noise and dropout generator.", (0, 999999)))
    dropout_prob: float = field(default=0.0, metadata=meta("Probability that a beam returns nothing.", (0, 1)))
    noise_scale: float = field(default=1.0, metadata=meta(
        "Multiplies the model's range noise (1 = datasheet accuracy as 3 sigma, 0 = exact ranges).", (0, 100)))
    rate_hz: float | None = field(default=None, metadata=meta(
        "Scan rate, Hz; null = the model's (UTM-30LX 40, URG-04LX 10).", (0.1, 100)))

    @property
    def lidar_model(self) -> LidarModel:
        return MODELS[self.model]


class SimulatedLidar(Backend[Scan]):
    """A scanner of ``settings.model`` on ``mount``, seeing ``world`` from ``truth``'s poses."""

    def __init__(self, sensor_id: str, settings: SimLidarSettings, mount: Mount, world: World,
                 truth: TruthLike) -> None:
        self.sensor_id = sensor_id
        self.settings = settings
        self.model = settings.lidar_model
        self.mount = mount
        self.truth = truth
        self.geometry = WorldGeometry.from_world(world)
        self.grid = CaptureGrid(1.0 / settings.rate_hz if settings.rate_hz else self.model.scan_period_s)
        self.description = f"simulated {self.model.name}"
        self._angles = self.model.angles_rad()
        self._angles.flags.writeable = False  # shared by every scan
        self._directions = beam_directions(self._angles)  # (N, 3) in the sensor frame
        self._rng = np.random.default_rng(settings.seed)

    async def open(self) -> None:
        """Start the capture grid at the current daemon time."""
        self.grid.start()

    async def read(self) -> Scan:
        """The next scan, once its sweep is over (see the module docstring for the timing)."""
        while True:
            slot, t_capture = await self.grid.next(self.model.sweep_s)
            pose = self.truth.at(t_capture)
            if pose is not None:
                return self.render(t_capture, pose.position_ned, pose.quat, slot)

    async def close(self) -> None:
        """Nothing to release."""

    def render(self, t_capture: float, position_ned: np.ndarray, quat: np.ndarray, sequence: int = 0) -> Scan:
        """The scan seen from a vehicle at ``position_ned`` (m, NED) with attitude ``quat``
        ([w, x, y, z], body FRD -> NED), stamped ``t_capture`` (daemon clock, s)."""
        rotation, origin = self.mount.sensor_to_world(position_ned, quat)
        ranges, valid = self.measure(cast(self.geometry, origin, self._directions @ rotation.T))
        return Scan(self.sensor_id, t_capture, self._angles, ranges, valid, sweep_s=0.0, sequence=sequence)

    def measure(self, true_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ranges m, valid) the scanner reports for true distances ``true_m`` (inf = no hit):
        the model's range noise, its min/max range and the configured dropouts; 0 where invalid."""
        hit = np.isfinite(true_m)
        true_m = np.where(hit, true_m, 0.0)
        bound = self.model.accuracy_bound_m(true_m) * self.settings.noise_scale
        noise = np.clip(self._rng.standard_normal(len(true_m)) * (bound / 3.0), -bound, bound)
        ranges = true_m + noise
        valid = (hit & (ranges >= self.model.min_range_m) & (ranges <= self.model.max_range_m)
                 & (self._rng.random(len(true_m)) >= self.settings.dropout_prob))
        return np.where(valid, ranges, 0.0), valid
