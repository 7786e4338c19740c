"""Simulated GNSS receiver: fixes from simulator ground truth (``kind: gnss, backend: sim``).

Timing: the receiver solves at epochs ``t0 + k / rate_hz`` (daemon clock, s) from
:meth:`SimulatedGnss.open`. The fix of epoch ``t`` describes the truth at ``t``, is stamped
``t_capture = t`` (GnssFix: the solution's epoch) and arrives ``latency_s`` later (the
receiver's computation and output delay), waited for on the daemon clock like the other
simulated sensors. A reader more than a period late skips to the latest due epoch; an epoch
without truth yields no fix.

Errors, per axis, 1-sigma ``horizontal_sigma_m`` north and east and ``vertical_sigma_m`` down
(reported as ``h_acc_m`` and ``v_acc_m``): a slow bias holding ``bias_share`` of the variance (a
random walk pulled back towards zero with time constant ``bias_tau_s``: first-order Gauss-Markov,
drawn afresh at open) plus white noise holding the rest. Velocity: the true NED velocity plus
white noise of ``velocity_sigma_mps`` per axis (``speed_acc_mps``), as a Doppler solution. The
position (NED at the EKF origin) becomes WGS-84 by :func:`companion.frames.geodetic_from_ned`
around the configured origin; the altitude is AMSL.

Denial (jamming): a fix whose epoch lies in a ``denied`` window ``[start_s, end_s)`` (seconds since
open), and every fix delivered while :meth:`SimulatedGnss.deny` is on, reports ``fix_type`` 1 (no
fix), ``jamming`` True, no satellites, latitude, longitude and altitude 0 (as MAVLink's GPS_RAW_INT
does) and no velocity or accuracies. The bias keeps drifting meanwhile.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.frames import geodetic_from_ned
from companion.messages import GNSS_NO_FIX, GnssFix
from companion.schema import meta
from drivers.base import Backend
from sitl.capture_grid import CaptureGrid
from sitl.truth import TruthLike, TruthPose


@dataclass(frozen=True)
class SimGnssSettings:
    """``settings:`` of a gnss with ``backend: sim`` (a companion.schema dataclass)."""

    rate_hz: float = field(default=5.0, metadata=meta("Fix rate, Hz.", (0.1, 50)))
    latency_s: float = field(default=0.1, metadata=meta(
        "From a fix's epoch to its delivery (the receiver's computation and output delay), seconds.", (0, 2)))
    horizontal_sigma_m: float = field(default=1.0, metadata=meta(
        "Position error north and east, 1-sigma per axis, metres (reported as h_acc).", (0, 100)))
    vertical_sigma_m: float = field(default=1.5, metadata=meta(
        "Position error down, 1-sigma, metres (reported as v_acc).", (0, 100)))
    bias_share: float = field(default=0.5, metadata=meta(
        "Share of the position error variance in the slow bias (the rest is white noise per fix).", (0, 1)))
    bias_tau_s: float = field(default=60.0, metadata=meta("Correlation time of the bias, seconds.", (1, 100000)))
    velocity_sigma_mps: float = field(default=0.05, metadata=meta(
        "Velocity error, 1-sigma per axis, m/s (reported as speed accuracy).", (0, 10)))
    fix_type: int = field(default=3, metadata=meta(
        "fix_type while not denied (MAVLink GPS_FIX_TYPE: 2 2-D, 3 3-D, 4 DGPS, 5 RTK float, 6 RTK fixed).", (2, 6)))
    satellites: int = field(default=12, metadata=meta("Satellites reported while not denied.", (0, 100)))
    seed: int = field(default=0, metadata=meta("Seed of the errors.", (0, 999999)))
    denied: tuple[tuple[float, float], ...] = field(default=(), metadata=meta(
        "Windows [start_s, end_s] (seconds since the receiver opened) with no fix (jamming)."))

    def validate(self) -> tuple[str, str] | None:
        for i, (start, end) in enumerate(self.denied):
            if not 0 <= start < end:
                return f"denied[{i}]", f"a window [start_s, end_s] needs 0 <= start_s < end_s, got [{start:g}, {end:g}]"
        return None


class SimulatedGnss(Backend[GnssFix]):
    """A receiver at the vehicle's reference point, fixing ``truth`` around ``origin`` = (lat deg,
    lon deg, alt m AMSL) of the EKF origin."""

    def __init__(self, receiver_id: str, settings: SimGnssSettings, origin: tuple[float, float, float],
                 truth: TruthLike) -> None:
        self.receiver_id = receiver_id
        self.settings = settings
        self.origin = origin
        self.truth = truth
        self.grid = CaptureGrid(1.0 / settings.rate_hz)
        self.description = f"simulated GNSS at {settings.rate_hz:g} Hz"
        sigma = np.array([settings.horizontal_sigma_m, settings.horizontal_sigma_m, settings.vertical_sigma_m])
        self._bias_sigma = sigma * math.sqrt(settings.bias_share)  # per axis, m
        self._white_sigma = sigma * math.sqrt(1.0 - settings.bias_share)
        self._rng = np.random.default_rng(settings.seed)
        self._bias = np.zeros(3)  # NED, m
        self._bias_slot = 0  # epoch the bias is at
        self._denied = False  # commanded by deny()

    def deny(self, on: bool) -> None:
        """Deny (True) or restore (False) the fixes delivered from now on (commanded jamming)."""
        self._denied = on

    async def open(self) -> None:
        """Start the epochs at the current daemon time, with a fresh bias."""
        self.grid.start()
        self._bias = self._rng.standard_normal(3) * self._bias_sigma
        self._bias_slot = 0

    async def read(self) -> GnssFix:
        """The next fix, ``latency_s`` after its epoch (see the module docstring)."""
        while True:
            slot, epoch = await self.grid.next(self.settings.latency_s)
            sample = self.truth.at(epoch)
            if sample is not None:
                return self.fix(epoch, sample, slot)

    async def close(self) -> None:
        """Nothing to release."""

    def fix(self, epoch: float, sample: TruthPose, slot: int) -> GnssFix:
        """The fix of epoch number ``slot`` at daemon time ``epoch`` (s) for the truth ``sample``."""
        self._drift_bias(slot)
        since_open = slot * self.grid.period_s
        if self._denied or any(start <= since_open < end for start, end in self.settings.denied):
            return GnssFix(self.receiver_id, epoch, GNSS_NO_FIX, 0.0, 0.0, 0.0, satellites=0, jamming=True)
        s = self.settings
        error = self._bias + self._rng.standard_normal(3) * self._white_sigma
        lat, lon, alt = geodetic_from_ned(np.asarray(sample.position_ned, dtype=float) + error, self.origin)
        velocity = np.asarray(sample.velocity_ned, dtype=float) + self._rng.standard_normal(3) * s.velocity_sigma_mps
        return GnssFix(self.receiver_id, epoch, s.fix_type, lat, lon, alt, velocity_ned_mps=velocity,
                       h_acc_m=s.horizontal_sigma_m, v_acc_m=s.vertical_sigma_m, speed_acc_mps=s.velocity_sigma_mps,
                       satellites=s.satellites)

    def _drift_bias(self, slot: int) -> None:
        """Move the bias on from its epoch to epoch ``slot`` (Gauss-Markov, exact for any step)."""
        if slot <= self._bias_slot:
            return
        decay = math.exp(-(slot - self._bias_slot) * self.grid.period_s / self.settings.bias_tau_s)
        self._bias = decay * self._bias + math.sqrt(1.0 - decay * decay) * self._bias_sigma * self._rng.standard_normal(3)
        self._bias_slot = slot
