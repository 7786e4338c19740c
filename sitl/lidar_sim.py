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

Error sources of a real scanner, each off by default (then no random number is drawn for it,
so a seed gives the same scans as without it):

- ``mixed_pixel_prob``: at a depth edge (two neighbouring beams that both hit, their true ranges
  more than ``MIXED_PIXEL_EDGE_M`` apart) each of the two beams, with this probability, returns a
  uniform blend of the two true ranges, a point between the surfaces (the "mixed pixel" or
  veiling effect of a spot that falls on both), before the range noise;
- ``mount_error_deg``: the scanner really sits turned from its configured mount by these ZYX
  roll, pitch, yaw degrees (sensor -> body = nominal rotation @ R(error)); the scans are
  rendered with that mount while the daemon keeps the nominal one;
- ``motion_distortion``: see below;
- walkers (``walkers:`` of the world, :mod:`sitl.walkers`): people walking back and forth, the
  nearer of them and the static world (:mod:`sitl.raycast`) is what a beam meets.

Motion: by default every beam is rendered at the capture-time pose (the device sweeps its beams
over ``sweep`` seconds while the vehicle moves) and the scans carry ``sweep_s = 0``, which
describes the data truthfully; only the delivery latency of the sweep is simulated. With
``motion_distortion`` beam i of N is rendered at its own time ``t + i / (N - 1) * sweep`` (walkers
too), from the sensor pose between the truth at ``t`` and at ``t + sweep`` (the capture-time pose
again if the truth does not know that), origin linearly and attitude along the shortest rotation
(like the simulated camera's motion blur, sitl/camera_sim.py), and the scans carry ``sweep_s =
sweep``: a moving scanner sees a skewed world, as a real one does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

import cv2
import numpy as np

from companion.frames import rotation_from_euler
from companion.schema import meta
from drivers.base import Backend
from drivers.lidar_models import MODELS, LidarModel
from drivers.mount import Mount, beam_directions
from companion.messages import Scan
from sitl.raycast import WorldGeometry, cast
from companion.world import World
from sitl.capture_grid import CaptureGrid
from sitl.truth import TruthLike
from sitl.walkers import cast_walkers

MIXED_PIXEL_EDGE_M = 0.2  # neighbouring beams whose true ranges differ by more are a depth edge, m

SensorPose = tuple[np.ndarray, np.ndarray]  # (rotation sensor -> NED (3x3), sensor origin NED (3,) m)


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
    mixed_pixel_prob: float = field(default=0.0, metadata=meta(
        f"Probability that each beam of a depth edge (neighbouring hits more than {MIXED_PIXEL_EDGE_M:g} m apart) "
        "returns a range between the two surfaces (mixed pixels).", (0, 1)))
    mount_error_deg: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=meta(
        "The scanner really sits turned from its configured mount by this roll, pitch, yaw (degrees, in its own "
        "frame): rendered so, unknown to the daemon.", (-10, 10)))
    whole_mm: bool = field(default=False, metadata=meta(
        "Ranges in whole millimetres, as SCIP reports them (the real driver's mm / 1000.0); false: unquantised. "
        "Off by default for now: with it the corridor flight (config/sitl-corridor.yaml, lockstep seed 1) does "
        "not complete its mission, a fragility of the corridor localization to sub-millimetre changes."))
    motion_distortion: bool = field(default=False, metadata=meta(
        "Render every beam from the pose at its own time in the sweep (scans carry the model's sweep_s); "
        "false: the whole scan from the capture-time pose, sweep_s 0."))

    @property
    def lidar_model(self) -> LidarModel:
        return MODELS[self.model]


def misaligned(mount: Mount, error_deg: tuple[float, float, float]) -> Mount:
    """``mount`` turned in its own sensor frame by ``error_deg`` (ZYX roll, pitch, yaw, degrees):
    the sensor -> body rotation becomes ``mount.rotation @ R(error)``, the offset stays."""
    roll, pitch, yaw = (math.radians(v) for v in error_deg)
    return replace(mount, rotation=mount.rotation @ rotation_from_euler(roll, pitch, yaw))


def fractional_rotations(rotvec: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations about the axis of ``rotvec`` (3,) (axis times angle, radians) by the
    ``fractions`` (N,) of its angle: Rodrigues' formula, vectorised."""
    angle = float(np.linalg.norm(rotvec))
    if angle == 0.0:
        return np.broadcast_to(np.eye(3), (len(fractions), 3, 3))
    kx, ky, kz = rotvec / angle
    k = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    turned = (fractions * angle)[:, None, None]
    return np.eye(3) + np.sin(turned) * k + (1.0 - np.cos(turned)) * (k @ k)


class SimulatedLidar(Backend[Scan]):
    """A scanner of ``settings.model`` on ``mount``, seeing ``world`` from ``truth``'s poses.

    ``self.mount`` is the mount the scans are rendered with: ``mount`` turned by
    ``settings.mount_error_deg`` (:func:`misaligned`)."""

    def __init__(self, sensor_id: str, settings: SimLidarSettings, mount: Mount, world: World,
                 truth: TruthLike) -> None:
        self.sensor_id = sensor_id
        self.settings = settings
        self.model = settings.lidar_model
        self.mount = misaligned(mount, settings.mount_error_deg)
        self.truth = truth
        self.geometry = WorldGeometry.from_world(world)
        self.walkers = world.walkers
        self.grid = CaptureGrid(1.0 / settings.rate_hz if settings.rate_hz else self.model.scan_period_s)
        self.description = f"simulated {self.model.name}"
        self._angles = self.model.angles_rad()
        self._angles.flags.writeable = False  # shared by every scan
        self._directions = beam_directions(self._angles)  # (N, 3) in the sensor frame
        self._sweep_fractions = np.linspace(0.0, 1.0, len(self._angles))  # beam i at i / (N - 1) of the sweep
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
        ([w, x, y, z], body FRD -> NED), stamped ``t_capture`` (daemon clock, s). With
        ``motion_distortion`` that is the pose of the first beam, and the pose of the last is
        the truth at ``t_capture + sweep`` (see the module docstring)."""
        start = self.mount.sensor_to_world(position_ned, quat)
        if not self.settings.motion_distortion:
            rotation, origin = start
            true_m = self.true_ranges(t_capture, origin, self._directions @ rotation.T)
            return Scan(self.sensor_id, t_capture, self._angles, *self.measure(true_m), sweep_s=0.0, sequence=sequence)
        sweep = self.model.sweep_s
        last = self.truth.at(t_capture + sweep)
        end = start if last is None else self.mount.sensor_to_world(last.position_ned, last.quat)
        true_m = self.true_ranges(t_capture + self._sweep_fractions * sweep, *self.swept_rays(start, end))
        return Scan(self.sensor_id, t_capture, self._angles, *self.measure(true_m), sweep_s=sweep, sequence=sequence)

    def swept_rays(self, start: SensorPose, end: SensorPose) -> tuple[np.ndarray, np.ndarray]:
        """(origins (N, 3) NED m, unit directions (N, 3) NED) of the beams of a sweep from the
        sensor pose ``start`` (first beam) to ``end`` (last beam): origin linear, attitude along
        the shortest rotation, both in proportion to the beam's time."""
        (r0, o0), (r1, o1) = start, end
        rotvec = cv2.Rodrigues(r0.T @ r1)[0].ravel()  # from start to end, in the start's sensor frame
        fractions = self._sweep_fractions
        turned = np.einsum("nij,nj->ni", fractional_rotations(rotvec, fractions), self._directions)
        return o0 + fractions[:, None] * (o1 - o0), turned @ r0.T

    def true_ranges(self, t: float | np.ndarray, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distance (m, inf = no hit) along each ray to the nearer of the world's surfaces and its
        walkers at daemon time ``t`` (s; scalar or one per ray); ``origins`` (3,) or (N, 3) NED m,
        ``directions`` (N, 3) NED unit vectors."""
        return np.minimum(cast(self.geometry, origins, directions), cast_walkers(self.walkers, t, origins, directions))

    def measure(self, true_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ranges m, valid) the scanner reports for true distances ``true_m`` (inf = no hit), in
        beam order: mixed pixels at depth edges, the model's range noise, whole millimetres
        (``whole_mm``), its min/max range and the configured dropouts; 0 where invalid."""
        true_m = self.mix_edges(true_m)
        hit = np.isfinite(true_m)
        true_m = np.where(hit, true_m, 0.0)
        bound = self.model.accuracy_bound_m(true_m) * self.settings.noise_scale
        noise = np.clip(self._rng.standard_normal(len(true_m)) * (bound / 3.0), -bound, bound)
        ranges = true_m + noise
        if self.settings.whole_mm:
            ranges = np.rint(ranges * 1000.0) / 1000.0
        valid = (hit & (ranges >= self.model.min_range_m) & (ranges <= self.model.max_range_m)
                 & (self._rng.random(len(true_m)) >= self.settings.dropout_prob))
        return np.where(valid, ranges, 0.0), valid

    def mix_edges(self, true_m: np.ndarray) -> np.ndarray:
        """``true_m`` (m, inf = no hit, beam order) with mixed pixels: at every depth edge (two
        neighbouring beams that both hit, more than ``MIXED_PIXEL_EDGE_M`` apart) each of the
        two beams, with probability ``mixed_pixel_prob``, takes a uniform blend of the two
        true ranges. Draws no random number when that probability is 0."""
        if self.settings.mixed_pixel_prob == 0.0:
            return true_m
        hit = np.isfinite(true_m)
        gap = np.abs(np.diff(np.where(hit, true_m, 0.0)))
        edges = np.flatnonzero(hit[:-1] & hit[1:] & (gap > MIXED_PIXEL_EDGE_M))  # between beams k and k + 1
        beams, others = np.concatenate((edges, edges + 1)), np.concatenate((edges + 1, edges))
        mixed = self._rng.random(len(beams)) < self.settings.mixed_pixel_prob
        beams, others = beams[mixed], others[mixed]
        out = true_m.copy()
        out[beams] = true_m[beams] + self._rng.random(len(beams)) * (true_m[others] - true_m[beams])
        return out
