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
  ArduCopter reads it at 10 Hz, so between readings the altitude is carried by SIMSTATE's true
  acceleration (:class:`BaroAltitude`) rather than held.
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
from companion.frames import GRAVITY_MPS2, euler_from_quat, ned_from_geodetic, quat_from_euler, rotation_from_euler
from companion.mavlink.link import MavlinkLink, mavlink

HISTORY_S = 2.0
SIMSTATE_VELOCITY_FIT_S = 0.5  # SIMSTATE velocity: the slope of the positions received over this span
SIMSTATE_VELOCITY_MIN_SPAN_S = 0.2  # ... once they span at least this (else zero: just started)
SIM_STATE_PREFERRED_S = 1.0  # a SIM_STATE this recent makes SIMSTATE redundant
MOCAP_AGREEMENT_M = 0.05  # an ATT_POS_MOCAP position this close to SIM_STATE's geodetic one refines it
MOCAP_PAIR_S = 0.005  # ... and received at most this long before it (the vehicle sends them back to back)
# ArduCopter reads its barometer at 10 Hz (the scheduler's update_altitude), each reading the SITL
# barometer's newest sample (AP_Baro_SITL keeps the latest, it does not average), and SCALED_PRESSURE
# repeats the newest reading at whatever rate it is streamed. Fitted on two recorded ArduCopter 4.0
# hovers against SIMSTATE's true acceleration, a reading is the altitude 0-15 ms before it first
# arrives (a mean over the reading period, 50 ms before, fitted worse and lagged the climb).
BARO_READING_S = 0.1
BARO_READING_LAG_S = 0.01
BARO_EXTRAPOLATE_S = 2.0 * BARO_READING_S  # past the newest reading it is carried on this long, then held
BARO_INTERVAL_GAIN = 0.1  # weight of each new gap between SCALED_PRESSUREs in their running mean

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


def simstate_upward_acceleration(msg: mavlink.MAVLink_message) -> float:
    """The vehicle's upward acceleration (m/s^2) from a SIMSTATE: its ``xacc``/``yacc``/``zacc`` are
    the simulated airframe's true specific force (body FRD, m/s^2, what a perfect accelerometer
    reads: -9.81 on ``zacc`` standing level), turned to NED by its true attitude, gravity added."""
    force_ned = rotation_from_euler(msg.roll, msg.pitch, msg.yaw) @ np.array([msg.xacc, msg.yacc, msg.zacc])
    return -(float(force_ned[2]) + GRAVITY_MPS2)


class _Climb:
    """The double integral of the true upward acceleration (m, from 0 at rest before the first
    sample): each sample held until the next, :data:`HISTORY_S` kept; before the oldest kept
    sample it runs on back at that sample's velocity."""

    def __init__(self) -> None:
        self._knots: deque[tuple[float, float, float, float]] = deque()  # (t s, height m, velocity m/s, accel m/s^2)

    def add(self, t: float, up_mps2: float) -> None:
        """One sample: ``up_mps2`` (m/s^2) from daemon time ``t`` (s) on; one older than the newest is dropped."""
        if not self._knots:
            self._knots.append((t, 0.0, 0.0, up_mps2))
            return
        t0, h0, v0, a0 = self._knots[-1]
        if t < t0:
            return
        dt = t - t0
        self._knots.append((t, h0 + v0 * dt + 0.5 * a0 * dt * dt, v0 + a0 * dt, up_mps2))
        while len(self._knots) > 2 and t - self._knots[1][0] > HISTORY_S:
            self._knots.popleft()

    def at(self, t: float) -> tuple[float, float]:
        """(height m, velocity m/s) at daemon time ``t``."""
        if not self._knots:
            return 0.0, 0.0
        t0, h0, v0, a0 = self._knots[self._segment(t)]
        if t < t0:  # before the oldest sample: at its velocity
            return h0 + v0 * (t - t0), v0
        dt = t - t0
        return h0 + v0 * dt + 0.5 * a0 * dt * dt, v0 + a0 * dt

    def _segment(self, t: float) -> int:
        """Index of the sample holding at ``t`` (0 before the oldest)."""
        for i in range(len(self._knots) - 1, -1, -1):
            if self._knots[i][0] <= t:
                return i
        return 0


class BaroAltitude:
    """ArduPilot SITL's barometer altitude (m AMSL) as a function of daemon time (s), from the
    SCALED_PRESSURE messages, carried between readings by SIMSTATE's true acceleration.

    A new reading is stamped where it first arrived less :data:`BARO_READING_LAG_S`. The altitude
    is the true acceleration's double integral (:meth:`add_acceleration`) plus the line through the
    two newest readings less that integral (exact for any acceleration, if the stamps are), up to
    :data:`BARO_EXTRAPOLATE_S` past the newest reading, then held. Taking the reading held at each
    arrival put the simulated scans up to 0.1 s behind the autopilot's IMU (at takeoff, 1 m/s, the
    height fixes fell 10-13 cm below the IMU-carried height and were refused); the two readings'
    slope alone, stamped 50 ms before arrival as if each were a mean over its period, missed the
    next reading of a recorded ArduCopter hover by up to 4.3 cm, and lagged the climb by 4 cm.

    A reading equal to the one before is only seen as the same value still arriving: once it still
    arrives a reading period plus two message intervals (their running mean: the link delivers
    them in bursts) after it was first seen, a newer reading equalled it. The vehicle stood still
    (landed, or hovering within the barometer's resolution of about 1 cm) until at least that
    much before the repeat, and from then the altitude is that reading plus what the acceleration
    adds from rest. The line's time base stays the first arrivals: a repeat is only known late,
    and taking its late time as a reading's halved the next slope's time base (a patrol's tracking
    went from 0.15 to 0.65 m RMS that way)."""

    def __init__(self) -> None:
        self._readings: deque[tuple[float, float]] = deque(maxlen=2)  # (daemon time, altitude m AMSL)
        self._last_arrival = -math.inf  # daemon time of the newest message (s)
        self._interval = BARO_READING_S  # mean time between messages (s), a running average
        self._still_since: float | None = None  # once a newer reading equalled the newest: at rest until then
        self._climb = _Climb()

    def add(self, t_arrival: float, altitude_m: float) -> None:
        """A SCALED_PRESSURE's altitude, received at ``t_arrival``."""
        if self._last_arrival < t_arrival:
            gap = min(t_arrival - self._last_arrival, BARO_READING_S)
            self._interval += BARO_INTERVAL_GAIN * (gap - self._interval)
        self._last_arrival = t_arrival
        if not self._readings or altitude_m != self._readings[-1][1]:
            self._readings.append((t_arrival - BARO_READING_LAG_S, altitude_m))
            self._still_since = None
        elif t_arrival > self._readings[-1][0] + BARO_READING_LAG_S + BARO_READING_S + 2.0 * self._interval:
            self._still_since = t_arrival - BARO_READING_S - 2.0 * self._interval

    def add_acceleration(self, t: float, up_mps2: float) -> None:
        """The vehicle's true upward acceleration (m/s^2, gravity removed) from daemon time ``t``
        until the next sample."""
        self._climb.add(t, up_mps2)

    def at(self, t: float) -> float | None:
        """The altitude at daemon time ``t`` (m AMSL), None before the first reading."""
        if not self._readings:
            return None
        t1, a1 = self._readings[-1]
        if self._still_since is not None and t >= self._still_since:
            start = self._still_since
            t = min(t, start + BARO_EXTRAPOLATE_S)
            (h0, v0), (h, _) = self._climb.at(start), self._climb.at(t)
            return a1 + h - h0 - v0 * (t - start)
        if len(self._readings) == 1:
            return a1
        t0, a0 = self._readings[0]
        t = min(max(t, t0), t1 + BARO_EXTRAPOLATE_S)
        c0, c1 = a0 - self._climb.at(t0)[0], a1 - self._climb.at(t1)[0]
        return self._climb.at(t)[0] + c1 + (c1 - c0) / max(t1 - t0, 1e-6) * (t - t1)


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
        if not all(math.isfinite(v) for v in (msg.roll, msg.pitch, msg.yaw, msg.xacc, msg.yacc, msg.zacc)):
            return
        self._baro.add_acceleration(now, simstate_upward_acceleration(msg))
        altitude = self._baro.at(now)
        if altitude is None:
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
