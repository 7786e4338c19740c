"""Ground truth for simulated sensor backends, from the simulator's MAVLink messages.

The one documented truth interface is MAVLink on the autopilot link:

- ``SIM_STATE`` (the built-in SITL vehicle, and recent ArduPilot SITL): attitude quaternion,
  NED velocity, ``lat_int``/``lon_int`` (1e-7 deg, so about 1.1 cm) and altitude. The built-in
  vehicle sends an ``ATT_POS_MOCAP`` just before each (its motion capture: the position in NED
  metres from its anchor, float32, micrometres here): a simulated scanner rendering from the
  1.1 cm steps of ``lat_int`` saw the arena from up to 5.5 mm off (3.2 mm RMS per axis), the
  largest error of the clean arena's flights. The position is taken from it when it agrees with
  the geodetic one to :data:`MOCAP_AGREEMENT_M` (the vehicle's anchor is the configured origin;
  another anchor would not agree, and the geodetic position is kept);
- ``SIMSTATE`` (ArduPilot SITL before SIM_STATE, e.g. 4.0): true attitude and ``lat``/``lng``
  (1e-7 deg) but no altitude. The altitude then comes from ArduPilot SITL's simulated
  barometer (SCALED_PRESSURE), which is an exact function of the true altitude through
  ArduPilot's standard atmosphere when its error sources are off (SIM_BARO_RND, SIM_BARO_DRIFT,
  SIM_BARO_GLITCH, SIM_BARO_DELAY, SIM_TEMP_BFACTOR all 0: ``companion sitl --ardupilot`` sets
  them; the EKF does not use that barometer, it takes height from the external navigation).
  ArduCopter reads it at 10 Hz, so its altitude is followed between readings
  (:class:`BaroAltitude`) rather than held.
  Never the autopilot's own estimate (LOCAL_POSITION_NED, AHRS2): that is not truth.

Samples are stamped with the daemon clock on arrival (in lockstep that is exactly the
simulation time they were sampled at) and converted to the project frame (LOCAL_NED at the
configured origin). :meth:`TruthSource.at` interpolates a pose at a capture time, which is
what a simulated scanner or camera renders from. Only simulated backends may use this: it is
never an input to a real estimator.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from companion import clock
from companion.config import OriginConfig
from companion.frames import euler_from_quat, ned_from_geodetic, quat_from_euler
from companion.mavlink.link import MavlinkLink, mavlink

HISTORY_S = 2.0
SIMSTATE_VELOCITY_FIT_S = 0.5  # SIMSTATE velocity: the slope of the positions received over this span
SIMSTATE_VELOCITY_MIN_SPAN_S = 0.2  # ... once they span at least this (else zero: just started)
SIM_STATE_PREFERRED_S = 1.0  # a SIM_STATE this recent makes SIMSTATE redundant
MOCAP_AGREEMENT_M = 0.05  # an ATT_POS_MOCAP position this close to SIM_STATE's geodetic one refines it
MOCAP_PAIR_S = 0.005  # ... and received at most this long before it (the vehicle sends them back to back)
# ArduCopter reads its barometer at 10 Hz (the scheduler's update_altitude), each reading the mean of
# the samples since the one before, and SCALED_PRESSURE repeats the latest reading at whatever rate it
# is streamed: a reading is the altitude about half a reading period before it first arrives.
BARO_READING_S = 0.1
BARO_READING_LAG_S = 0.5 * BARO_READING_S
BARO_EXTRAPOLATE_S = 2.0 * BARO_READING_S  # past the newest reading its slope is followed this long, then held

# ArduPilot's AP_Baro::SimpleAtmosphere (troposphere), as its SITL barometer uses it.
SSL_AIR_PRESSURE_PA = 101325.01576
SSL_AIR_TEMPERATURE_K = 288.15
EARTH_RADIUS_KM = 6369.0
GAS_CONSTANT_GMR = 34.163195
LAPSE_RATE_K_PER_KM = 6.5


def sitl_baro_altitude_m(pressure_hpa: float) -> float:
    """Altitude (m AMSL) at which ArduPilot SITL's noiseless barometer reads ``pressure_hpa``: the
    inverse of AP_Baro::SimpleAtmosphere (geopotential troposphere, then geometric altitude)."""
    delta = pressure_hpa * 100.0 / SSL_AIR_PRESSURE_PA
    theta = delta ** (LAPSE_RATE_K_PER_KM / GAS_CONSTANT_GMR)
    h_km = (1.0 - theta) * SSL_AIR_TEMPERATURE_K / LAPSE_RATE_K_PER_KM
    return 1000.0 * h_km * EARTH_RADIUS_KM / (EARTH_RADIUS_KM - h_km)


class TruthPose(Protocol):
    """A ground-truth sample as a simulated sensor reads it (:class:`TruthSample` is one)."""

    @property
    def position_ned(self) -> np.ndarray:
        """(3,) body origin in NED, m."""

    @property
    def velocity_ned(self) -> np.ndarray:
        """(3,) velocity in NED, m/s."""

    @property
    def quat(self) -> np.ndarray:
        """(4,) attitude [w, x, y, z], body FRD -> NED."""


class TruthLike(Protocol):
    """The part of :class:`TruthSource` a simulated sensor uses (tests give their own)."""

    def at(self, t: float) -> TruthPose | None:
        """The pose at daemon time ``t`` (s), or None if unknown."""


@dataclass(frozen=True)
class TruthSample:
    t: float  # daemon clock, seconds
    position_ned: np.ndarray  # m
    velocity_ned: np.ndarray  # m/s (from SIMSTATE: fitted to the positions of the last 0.5 s, see _simstate_velocity)
    quat: np.ndarray  # [w, x, y, z], body FRD -> NED


def slerp(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """The unit quaternion (w, x, y, z) the fraction ``w`` (0..1) of the way from ``a`` to ``b`` along
    the shorter great arc."""
    dot = float(np.dot(a, b))
    if dot < 0.0:
        b, dot = -b, -dot
    if dot > 0.9995:  # nearly equal: the chord is the arc
        q = a + w * (b - a)
        return q / np.linalg.norm(q)
    theta = math.acos(dot)
    return (math.sin((1.0 - w) * theta) * a + math.sin(w * theta) * b) / math.sin(theta)


class MocapRefinement:
    """The position of a ``SIM_STATE`` refined by the ``ATT_POS_MOCAP`` the built-in vehicle sent
    just before it (module docstring); clock: the caller's, seconds."""

    def __init__(self) -> None:
        self._pending: tuple[float, np.ndarray] | None = None

    def on_mocap(self, msg: mavlink.MAVLink_message, now: float) -> None:
        position = np.array([msg.x, msg.y, msg.z], dtype=float)
        self._pending = (now, position) if np.all(np.isfinite(position)) else None

    def position(self, geodetic_ned: np.ndarray, now: float) -> np.ndarray:
        """NED metres for a SIM_STATE received at ``now`` whose lat_int/lon_int/alt give ``geodetic_ned``."""
        pending, self._pending = self._pending, None
        if pending is None or now - pending[0] > MOCAP_PAIR_S:
            return geodetic_ned
        mocap = pending[1]
        return mocap if float(np.linalg.norm(mocap - geodetic_ned)) <= MOCAP_AGREEMENT_M else geodetic_ned


def sim_state_position(msg: mavlink.MAVLink_message, origin: tuple[float, float, float]) -> np.ndarray:
    """NED metres at ``origin`` (lat deg, lon deg, alt m) of a SIM_STATE's lat_int/lon_int (or, from
    an older sender, its float lat/lon) and alt."""
    lat_int = getattr(msg, "lat_int", 0)
    lat = lat_int * 1e-7 if lat_int else msg.lat
    lon = msg.lon_int * 1e-7 if lat_int else msg.lon
    return ned_from_geodetic(lat, lon, msg.alt, origin)


class BaroAltitude:
    """ArduPilot SITL's barometer altitude (m AMSL) as a function of daemon time (s), from the
    SCALED_PRESSURE messages: each new reading stamped when it first arrived, less
    :data:`BARO_READING_LAG_S`; between the two newest readings linear, past the newest one along
    their slope for up to :data:`BARO_EXTRAPOLATE_S`, then held. Taking the reading held at each
    arrival instead put the simulated scans up to 0.1 s behind the autopilot's IMU in altitude: at
    takeoff (1 m/s) the height fixes fell 10-13 cm below the IMU-carried height, were refused, and
    the estimate sent lagged the climb by 24 cm with a 3 cm sigma until its relock (ArduCopter 4.0
    SITL, the hover of tests/test_ardupilot_sitl.py).

    A reading equal to the one before is only seen as the same value still arriving: once it still
    arrives a reading period plus two message intervals after it was first seen, a newer reading
    must have equalled it (the vehicle stopped dead, e.g. landed) and the altitude is held there
    instead of followed on along the slope. The slope's time base stays the first arrival: a repeat
    is only known late, by up to a message interval, and taking its late time as a reading's halved
    the time base of the next slope (a patrol's tracking went from 0.15 to 0.65 m RMS that way)."""

    def __init__(self) -> None:
        self._readings: deque[tuple[float, float]] = deque(maxlen=2)  # (daemon time, altitude m AMSL)
        self._first_seen = -math.inf  # daemon time the newest reading first arrived (s)
        self._last_arrival = -math.inf  # daemon time of the newest message (s)
        self._interval = BARO_READING_S  # time between the two newest messages (s)
        self._stopped = False  # a newer reading equalled the newest: the altitude is held there

    def add(self, t_arrival: float, altitude_m: float) -> None:
        """A SCALED_PRESSURE's altitude, received at ``t_arrival``."""
        if self._last_arrival < t_arrival:
            self._interval = t_arrival - self._last_arrival
        self._last_arrival = t_arrival
        if not self._readings or altitude_m != self._readings[-1][1]:
            self._readings.append((t_arrival - BARO_READING_LAG_S, altitude_m))
            self._first_seen, self._stopped = t_arrival, False
        elif t_arrival > self._first_seen + BARO_READING_S + 2.0 * self._interval:
            self._stopped = True

    def at(self, t: float) -> float | None:
        """The altitude at daemon time ``t`` (m AMSL), None before the first reading."""
        if not self._readings:
            return None
        t1, a1 = self._readings[-1]
        if len(self._readings) == 1 or (self._stopped and t >= t1):
            return a1
        t0, a0 = self._readings[0]
        slope = (a1 - a0) / max(t1 - t0, 1e-6)
        return a1 + slope * max(min(t - t1, BARO_EXTRAPOLATE_S), t0 - t1)


class TruthSource:
    """Keeps ``HISTORY_S`` seconds of simulator truth and interpolates it."""

    def __init__(self, link: MavlinkLink, origin: OriginConfig,
                 listener: Callable[[TruthSample], None] | None = None) -> None:
        """``listener`` is called with every new sample (the harness records them)."""
        self._origin = (origin.lat, origin.lon, origin.alt)
        self._listener = listener
        self._samples: deque[TruthSample] = deque()
        self._baro = BaroAltitude()  # from SCALED_PRESSURE, for SIMSTATE
        self._sim_state_t: float | None = None  # daemon time of the last SIM_STATE
        self._mocap = MocapRefinement()
        link.subscribe("ATT_POS_MOCAP", lambda msg: self._mocap.on_mocap(msg, clock.now()))
        link.subscribe("SIM_STATE", self._on_sim_state)
        link.subscribe("SIMSTATE", self._on_simstate)
        link.subscribe("SCALED_PRESSURE", self._on_pressure)

    @property
    def latest(self) -> TruthSample | None:
        return self._samples[-1] if self._samples else None

    def at(self, t: float) -> TruthSample | None:
        """Truth at daemon time ``t`` (linear in position and velocity, attitude by slerp between the two
        samples around ``t``); None if unknown. The attitude is interpolated, not the nearest sample's: a
        fixed wing rolling at 25 deg/s turns half a degree between 50 Hz samples, and a flow field or
        image pair rendered from snapped attitudes carries a rotation the vehicle never made."""
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
                           a.velocity_ned + w * (b.velocity_ned - a.velocity_ned), slerp(a.quat, b.quat, w))

    def euler_at(self, t: float) -> tuple[float, float, float] | None:
        sample = self.at(t)
        return None if sample is None else euler_from_quat(sample.quat)

    def _add(self, sample: TruthSample) -> None:
        self._samples.append(sample)
        while self._samples and sample.t - self._samples[0].t > HISTORY_S:
            self._samples.popleft()
        if self._listener is not None:
            self._listener(sample)

    def _on_sim_state(self, msg: mavlink.MAVLink_message) -> None:
        values = (msg.lat, msg.lon, msg.alt, msg.vn, msg.ve, msg.vd, msg.q1, msg.q2, msg.q3, msg.q4)
        if not all(math.isfinite(v) for v in values):
            return
        self._sim_state_t = clock.now()
        position = self._mocap.position(sim_state_position(msg, self._origin), self._sim_state_t)
        self._add(TruthSample(self._sim_state_t, position, np.array([msg.vn, msg.ve, msg.vd]),
                              np.array([msg.q1, msg.q2, msg.q3, msg.q4])))

    def _on_pressure(self, msg: mavlink.MAVLink_message) -> None:
        if math.isfinite(msg.press_abs) and msg.press_abs > 0:
            self._baro.add(clock.now(), sitl_baro_altitude_m(msg.press_abs))

    def _on_simstate(self, msg: mavlink.MAVLink_message) -> None:
        now = clock.now()
        altitude = self._baro.at(now)
        if altitude is None or not all(math.isfinite(v) for v in (msg.roll, msg.pitch, msg.yaw)):
            return
        if self._sim_state_t is not None and now - self._sim_state_t < SIM_STATE_PREFERRED_S:
            return
        position = ned_from_geodetic(msg.lat * 1e-7, msg.lng * 1e-7, altitude, self._origin)
        self._add(TruthSample(now, position, self._simstate_velocity(now, position),
                              quat_from_euler(msg.roll, msg.pitch, msg.yaw)))

    def _simstate_velocity(self, now: float, position: np.ndarray) -> np.ndarray:
        """NED m/s at ``now``: the least-squares slope of the SIMSTATE positions received over the
        last :data:`SIMSTATE_VELOCITY_FIT_S` (with this one). SIMSTATE carries no velocity and no
        time stamp: the difference of two positions over their arrival times, which a TCP link
        delivers in bursts microseconds apart, gave thousands of m/s (a simulated GNSS Doppler
        built on it threw the EKF-SLAM kilometres off on ArduCopter SITL); the slope over half a
        second averages the burst timing out, at the cost of a quarter-second lag."""
        recent = [s for s in self._samples if now - s.t <= SIMSTATE_VELOCITY_FIT_S]
        if not recent or now - recent[0].t < SIMSTATE_VELOCITY_MIN_SPAN_S:
            return np.zeros(3)
        t = np.array([s.t for s in recent] + [now])
        p = np.vstack([s.position_ned for s in recent] + [position])
        dt = t - t.mean()
        return (dt @ (p - p.mean(axis=0))) / float(dt @ dt)
