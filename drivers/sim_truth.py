"""Ground truth for simulated sensor backends, from the simulator's MAVLink messages.

The one documented truth interface is MAVLink on the autopilot link:

- ``SIM_STATE`` (the built-in SITL vehicle, and recent ArduPilot SITL): attitude quaternion,
  NED velocity, ``lat_int``/``lon_int`` (1e-7 deg, so about 1.1 cm) and altitude;
- ``SIMSTATE`` (older ArduPilot SITL): attitude and ``lat``/``lng`` (1e-7 deg) but no
  altitude, which is then taken from the autopilot's LOCAL_POSITION_NED.

Samples are stamped with the daemon clock on arrival (in lockstep that is exactly the
simulation time they were sampled at) and converted to the project frame (LOCAL_NED at the
configured origin). :meth:`TruthSource.at` interpolates a pose at a capture time, which is
what a simulated scanner or camera renders from. Only simulated backends may use this: it is
never an input to a real estimator.
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass

import numpy as np

from companion import clock
from companion.config import OriginConfig
from companion.frames import euler_from_quat, ned_from_geodetic, quat_from_euler
from companion.mavlink.link import MavlinkLink, mavlink

HISTORY_S = 2.0


@dataclass(frozen=True)
class TruthSample:
    t: float  # daemon clock, seconds
    position_ned: np.ndarray  # m
    velocity_ned: np.ndarray  # m/s
    quat: np.ndarray  # [w, x, y, z], body FRD -> NED


class TruthSource:
    """Keeps ``HISTORY_S`` seconds of simulator truth and interpolates it."""

    def __init__(self, link: MavlinkLink, origin: OriginConfig) -> None:
        self._origin = (origin.lat, origin.lon, origin.alt)
        self._samples: deque[TruthSample] = deque()
        self._last_z: float | None = None  # LOCAL_POSITION_NED z, for SIMSTATE
        link.subscribe("SIM_STATE", self._on_sim_state)
        link.subscribe("SIMSTATE", self._on_simstate)
        link.subscribe("LOCAL_POSITION_NED", self._on_local_position)

    @property
    def latest(self) -> TruthSample | None:
        return self._samples[-1] if self._samples else None

    def at(self, t: float) -> TruthSample | None:
        """Truth at daemon time ``t`` (linear in position/velocity, nearest attitude); None if unknown."""
        samples = self._samples
        if not samples or t < samples[0].t or t > samples[-1].t + 0.1:
            return None
        times = [s.t for s in samples]
        i = bisect.bisect_right(times, t)
        if i >= len(samples):
            return samples[-1]
        a, b = samples[i - 1], samples[i]
        w = 0.0 if b.t == a.t else (t - a.t) / (b.t - a.t)
        return TruthSample(t, a.position_ned + w * (b.position_ned - a.position_ned),
                           a.velocity_ned + w * (b.velocity_ned - a.velocity_ned), a.quat if w < 0.5 else b.quat)

    def euler_at(self, t: float) -> tuple[float, float, float] | None:
        sample = self.at(t)
        return None if sample is None else euler_from_quat(sample.quat)

    def _add(self, sample: TruthSample) -> None:
        self._samples.append(sample)
        while self._samples and sample.t - self._samples[0].t > HISTORY_S:
            self._samples.popleft()

    def _on_sim_state(self, msg: mavlink.MAVLink_message) -> None:
        lat_int = getattr(msg, "lat_int", 0)
        lat = lat_int * 1e-7 if lat_int else msg.lat
        lon = msg.lon_int * 1e-7 if lat_int else msg.lon
        self._add(TruthSample(clock.now(), ned_from_geodetic(lat, lon, msg.alt, self._origin),
                              np.array([msg.vn, msg.ve, msg.vd]), np.array([msg.q1, msg.q2, msg.q3, msg.q4])))

    def _on_simstate(self, msg: mavlink.MAVLink_message) -> None:
        if self._last_z is None:
            return
        position = ned_from_geodetic(msg.lat * 1e-7, msg.lng * 1e-7, self._origin[2], self._origin)
        position[2] = self._last_z
        previous = self.latest
        now = clock.now()
        velocity = np.zeros(3) if previous is None or now <= previous.t else (position - previous.position_ned) / (now - previous.t)
        self._add(TruthSample(now, position, velocity, quat_from_euler(msg.roll, msg.pitch, msg.yaw)))

    def _on_local_position(self, msg: mavlink.MAVLink_message) -> None:
        self._last_z = msg.z
