"""Simulated landmark sensor: the EKF-SLAM seed's vision sensor (``kind: landmarks, backend: sim``).

What it sees: the world's point landmarks (``landmarks:`` of the world file) inside a cone of
half-angle ``half_fov_deg`` around the sensor's boresight, within ``max_range_m``. The boresight
is the sensor frame's +z axis (down for a mount with rpy [0, 0, 0]: a nadir-looking camera), so
the footprint tilts with the vehicle. Defaults are the seed's Table 1: 5 Hz, 20 degrees half
field of view, range noise 0.2 m, azimuth noise 0.16 deg, elevation noise 0.12 deg.

What it reports (:class:`companion.messages.LandmarkSightings`): range, azimuth and elevation in
the level heading frame, as a real sensor levels its bearings with the vehicle's attitude. The
attitude it levels with is the truth plus a constant error of ``attitude_error_deg`` per axis
(roll, pitch, yaw; drawn once per run, 1-sigma; 0 by default as in the seed), the error source
a real vehicle meets beyond the seed's white noise. Noise: white Gaussian per landmark and
frame, the 1-sigma values stated in the message.

Timing: frames at ``t0 + k / rate_hz`` (daemon clock, s) from :meth:`open`, each describing the
truth at its epoch and delivered ``latency_s`` later (the image processing delay).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.frames import rotation_from_euler, rotation_from_quat, wrap_pi
from companion.messages import LandmarkSightings
from companion.schema import meta
from companion.world import Landmark
from drivers.base import Backend
from drivers.mount import Mount
from sitl.capture_grid import CaptureGrid
from sitl.truth import TruthLike, TruthPose


@dataclass(frozen=True)
class SimLandmarkSettings:
    """``settings:`` of a landmarks sensor with ``backend: sim`` (a companion.schema dataclass)."""

    rate_hz: float = field(default=5.0, metadata=meta("Frame rate, Hz (seed: 5).", (0.1, 100)))
    latency_s: float = field(default=0.0, metadata=meta("From a frame's epoch to its delivery, seconds.", (0, 2)))
    half_fov_deg: float = field(default=20.0, metadata=meta(
        "Half-angle of the cone around the boresight (sensor +z) in which landmarks are seen, degrees (seed: 20).",
        (0.1, 89)))
    min_range_m: float = field(default=1.0, metadata=meta(
        "Landmarks nearer than this are not seen (a real sensor has a minimum range; on the ground over the landing "
        "pad a range of 0 with 0.2 m of noise would be negative), metres.", (0, 100)))
    max_range_m: float = field(default=500.0, metadata=meta("Landmarks further than this are not seen, metres.",
                                                            (1, 10000)))
    range_sigma_m: float = field(default=0.2, metadata=meta("Range noise, 1-sigma, metres (seed: 0.2).", (0, 100)))
    azimuth_sigma_deg: float = field(default=0.16, metadata=meta("Azimuth noise, 1-sigma, degrees (seed: 0.16).",
                                                                 (0, 30)))
    elevation_sigma_deg: float = field(default=0.12, metadata=meta(
        "Elevation noise, 1-sigma, degrees (seed: 0.12).", (0, 30)))
    attitude_error_deg: float = field(default=0.0, metadata=meta(
        "1-sigma per axis of the constant attitude error the bearings are levelled with (drawn once per run), degrees.",
        (0, 30)))
    seed: int = field(default=0, metadata=meta("Seed of the noise.", (0, 999999)))

    @property
    def sigma(self) -> tuple[float, float, float]:
        """(range m, azimuth rad, elevation rad) 1-sigma."""
        return self.range_sigma_m, math.radians(self.azimuth_sigma_deg), math.radians(self.elevation_sigma_deg)


def level_bearings(relative_ned: np.ndarray, yaw_rad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(range m, azimuth rad, elevation rad) of (N, 3) NED vectors from the sensor to the landmarks
    for a vehicle heading ``yaw_rad`` (the convention of :class:`LandmarkSightings`)."""
    d = np.asarray(relative_ned, dtype=float).reshape(-1, 3)
    horizontal = np.hypot(d[:, 0], d[:, 1])
    return (np.linalg.norm(d, axis=1), wrap_pi(np.arctan2(d[:, 1], d[:, 0]) - yaw_rad),
            np.arctan2(-d[:, 2], horizontal))


class SimulatedLandmarkSensor(Backend[LandmarkSightings]):
    """A landmark sensor at ``mount`` on the body seeing ``landmarks`` from the ``truth`` pose."""

    def __init__(self, sensor_id: str, settings: SimLandmarkSettings, mount: Mount,
                 landmarks: tuple[Landmark, ...], truth: TruthLike) -> None:
        self.sensor_id = sensor_id
        self.settings = settings
        self.mount = mount
        self.truth = truth
        self.grid = CaptureGrid(1.0 / settings.rate_hz)
        self.description = f"simulated landmark sensor at {settings.rate_hz:g} Hz, {len(landmarks)} landmarks"
        self._ids = np.array([m.id for m in landmarks], dtype=int)
        self._points = np.array([m.ned() for m in landmarks], dtype=float).reshape(-1, 3)
        self._rng = np.random.default_rng(settings.seed)
        self._attitude_error = np.zeros(3)
        self._sequence = 0

    async def open(self) -> None:
        """Start the frames at the current daemon time; draw this run's attitude error."""
        self.grid.start()
        self._attitude_error = self._rng.standard_normal(3) * math.radians(self.settings.attitude_error_deg)

    async def read(self) -> LandmarkSightings:
        """The next frame, ``latency_s`` after its epoch (frames without truth are skipped)."""
        while True:
            _, epoch = await self.grid.next(self.settings.latency_s)
            sample = self.truth.at(epoch)
            if sample is not None:
                return self.sightings(epoch, sample)

    async def close(self) -> None:
        """Nothing to release."""

    def visible(self, sample: TruthPose) -> tuple[np.ndarray, np.ndarray]:
        """(ids (K,), NED vectors sensor -> landmark (K, 3) m) of the landmarks in the cone at ``sample``."""
        sensor_to_ned, sensor_ned = self.mount.sensor_to_world(np.asarray(sample.position_ned, dtype=float),
                                                               np.asarray(sample.quat, dtype=float))
        boresight = sensor_to_ned[:, 2]
        relative = self._points - sensor_ned
        distance = np.linalg.norm(relative, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_off = (relative @ boresight) / distance
        seen = ((distance >= self.settings.min_range_m) & (distance <= self.settings.max_range_m)
                & (cos_off >= math.cos(math.radians(self.settings.half_fov_deg))))
        return self._ids[seen], relative[seen]

    def sightings(self, epoch: float, sample: TruthPose) -> LandmarkSightings:
        """The frame at daemon time ``epoch`` (s) for the truth ``sample``."""
        ids, relative = self.visible(sample)
        rotation = rotation_from_quat(np.asarray(sample.quat, dtype=float))
        error = rotation_from_euler(*self._attitude_error)
        believed = rotation @ error  # the attitude the sensor levels with
        # A vector measured in the body frame, levelled with the believed attitude:
        measured = relative @ rotation @ believed.T
        yaw = math.atan2(believed[1, 0], believed[0, 0])
        rng_m, azimuth, elevation = level_bearings(measured, yaw)
        s = self.settings
        sigma = s.sigma
        n = len(ids)
        self._sequence += 1
        return LandmarkSightings(self.sensor_id, epoch, ids,
                                 rng_m + self._rng.standard_normal(n) * sigma[0],
                                 wrap_pi(azimuth + self._rng.standard_normal(n) * sigma[1]),
                                 elevation + self._rng.standard_normal(n) * sigma[2],
                                 sigma, self._sequence)
